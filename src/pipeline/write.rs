//! A refinement's files: checked before any work, written together or not at all.

use super::{Outcome, RunError, Stage};
use crate::geom::LineSet;
use crate::io;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Where a refinement's files go.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Outputs {
    /// The refined segments; the format follows the extension.
    pub lines: PathBuf,
    /// The JSON report.
    pub report: Option<PathBuf>,
    /// A PLY with the input (red) and refined (blue) segments as coloured edges.
    pub compare_ply: Option<PathBuf>,
    /// How `lines` is written (`--format`).
    pub format: LinesOut,
    /// Provenance JSON (`--provenance`): each output segment's input segments.
    pub provenance: Option<PathBuf>,
}

/// The refined segments' file kind (`--format`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum LinesOut {
    /// By the extension of `lines` ([`io::LINE_OUTPUTS`]).
    #[default]
    ByExtension,
    /// LIMAP `finaltracks/`: `lines` is a new (or empty) folder that gets one
    /// `track_<k>.txt` per segment, its supports those of the input tracks it came from.
    Limap,
    /// EMAP / EdgeGaussians `parametric_edges.json` (`lines`, or that name in the folder
    /// `lines`).
    Emap,
}

/// Makes `out` a result the readers accept: zero-length segments (which f64 rounding can
/// make of a scene far from the origin, or a refinement can leave) are dropped with a
/// warning, and a result with no segment is an error that says why, before any file is
/// written.
fn readable_result(input: &LineSet, out: &mut Outcome) -> Result<(), RunError> {
    let keep: Vec<usize> = (0..out.lines.len())
        .filter(|&k| out.lines.segments[k].is_valid())
        .collect();
    let (mut lo, mut hi) = (
        glam::DVec3::splat(f64::INFINITY),
        glam::DVec3::splat(f64::NEG_INFINITY),
    );
    for s in input.segments.iter().filter(|s| s.is_valid()) {
        lo = lo.min(s.p1).min(s.p2);
        hi = hi.max(s.p1).max(s.p2);
    }
    let (far, size) = (
        lo.abs().max(hi.abs()).max_element(),
        (hi - lo).max_element(),
    );
    let hint = if far.is_finite() && far > 1e5 * size.max(f64::MIN_POSITIVE) {
        format!(
            "; the scene lies {far:.3e} from the origin and is {size:.3e} across, where the model's f32 centers cannot resolve it: recentre the lines and the model near the origin (subtract the scene's center from both)"
        )
    } else {
        String::new()
    };
    if keep.len() < out.lines.len() {
        let msg = format!(
            "{} of {} refined segments have zero length and were left out of the output{hint}",
            out.lines.len() - keep.len(),
            out.lines.len()
        );
        match &mut out.report.refine {
            Some(steps) => steps.warnings.push(msg),
            None => out.report.warnings.push(msg),
        }
        out.lines = out.lines.select(&keep);
        out.sources = keep.iter().map(|&k| out.sources[k].clone()).collect();
    }
    if out.lines.is_empty() {
        return Err(RunError::Input(format!(
            "no segment is left after refinement ({} in the input){}; nothing was written",
            input.len(),
            if hint.is_empty() {
                " (see the stages' counts with --verbose: the outlier step, --outlier-ratio, drops the segments with the fewest Gaussians)"
                    .to_string()
            } else {
                hint
            }
        )));
    }
    Ok(())
}

/// Colours of the input and refined layers in comparison files.
pub const BEFORE_COLOR: [u8; 3] = [220, 50, 40];
pub const AFTER_COLOR: [u8; 3] = [30, 90, 220];

impl Outputs {
    /// Checks every output path before any work, so a typo or a collision costs nothing:
    /// extensions, folders, and that no output is one of `inputs` or another output
    /// ([`io::OutputSet::check`]).
    pub fn check(&self, inputs: &[&Path]) -> Result<(), RunError> {
        let mut set = io::OutputSet::new();
        for p in inputs {
            set.input(p);
        }
        match self.format {
            LinesOut::ByExtension => {
                set.output("-o", &self.lines, &io::LINE_OUTPUTS);
            }
            LinesOut::Emap => {
                set.output("-o", &self.emap_path(), &["json"]);
            }
            LinesOut::Limap => self.check_track_folder(inputs)?,
        }
        if let Some(p) = &self.provenance {
            set.output("--provenance", p, &["json"]);
        }
        if let Some(p) = &self.report {
            set.output("--report", p, &["json"]);
        }
        if let Some(p) = &self.compare_ply {
            set.output("--compare-ply", p, &["ply"]);
        }
        set.check()?;
        Ok(())
    }

    /// Writes the refined lines, the comparison PLY and the report (each atomically), the
    /// report last and with the `write` stage and the output path in it.
    pub fn write(&self, input: &LineSet, out: &mut Outcome) -> Result<(), RunError> {
        // All of them land together or none does: a failure leaves earlier files as they were.
        let mut set = io::OutputSet::new();
        // A LIMAP folder is written whole beside its place and renamed into it last.
        let tracks = match self.format {
            LinesOut::Limap => {
                readable_result(input, out)?;
                Some(self.write_tracks(out)?)
            }
            _ => None,
        };
        self.stage(&mut set, input, out)?;
        set.commit()?;
        if let Some(tmp) = tracks {
            let tmp = tmp.keep();
            if self.lines.is_dir() {
                let _ = std::fs::remove_dir(&self.lines);
            }
            std::fs::rename(&tmp, &self.lines)
                .map_err(|e| io::Error::io(&self.lines, "create", e))?;
        }
        Ok(())
    }

    /// `-o` of `--format emap`: the file, or `parametric_edges.json` in the folder.
    pub fn emap_path(&self) -> PathBuf {
        let s = self.lines.as_os_str().to_string_lossy();
        if self.lines.is_dir() || s.ends_with('/') || s.ends_with('\\') {
            self.lines.join("parametric_edges.json")
        } else {
            self.lines.clone()
        }
    }

    /// `-o` of `--format limap`: a new or empty folder in an existing one, not an input.
    fn check_track_folder(&self, inputs: &[&Path]) -> Result<(), RunError> {
        let d = &self.lines;
        let bad = |msg: &str| RunError::Input(format!("{}: {msg}", d.display()));
        if inputs.iter().any(|p| io::same_file(p, d)) {
            return Err(bad(
                "is an input; --format limap writes a new folder of tracks",
            ));
        }
        if d.exists() {
            if !d.is_dir() {
                return Err(bad("exists and is not a folder; --format limap writes a folder of track_<k>.txt files"));
            }
            let full = std::fs::read_dir(d)
                .map_err(|e| io::Error::io(d, "read", e))?
                .next()
                .is_some();
            if full {
                return Err(bad(
                    "is not empty; --format limap writes its tracks into a new or empty folder",
                ));
            }
        } else {
            let parent = d.parent().filter(|p| !p.as_os_str().is_empty());
            if parent.is_some_and(|p| !p.is_dir()) {
                return Err(bad("its folder does not exist"));
            }
        }
        Ok(())
    }

    /// Writes the LIMAP tracks into a temporary folder beside `lines`.
    fn write_tracks(&self, out: &mut Outcome) -> Result<tempfile::TempDir, RunError> {
        let d = &self.lines;
        let parent = d
            .parent()
            .filter(|p| !p.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let tmp = tempfile::Builder::new()
            .prefix(".linegs-tracks-")
            .tempdir_in(parent)
            .map_err(|e| io::Error::io(d, "create a temporary folder beside", e))?;
        let line3dpp = io::line_format("line3dpp").map(|f| f.name);
        let supports = match &out.report.input.lines {
            Some(l) if out.report.input.lines_format.as_deref() == line3dpp => {
                Some(io::read_line3dpp_supports(Path::new(l))?)
            }
            Some(l) => io::read_supports(Path::new(l))?,
            None => None,
        };
        if supports.is_none() {
            out.report.warnings.push(format!(
                "--format limap: the input lines ({}) carry no LIMAP supports; the tracks list none",
                out.report.input.lines_format.as_deref().unwrap_or("arrays")
            ));
        }
        for (k, seg) in out.lines.segments.iter().enumerate() {
            // The sources' supports, each (image, 2D line) once: segments of one input
            // line share its observations.
            let mut seen = std::collections::HashSet::new();
            let sup: Vec<io::Support> = match &supports {
                Some(s) => out.sources[k]
                    .iter()
                    .flat_map(|&i| s.get(i as usize).into_iter().flatten())
                    .filter(|x| seen.insert((x.image_id, x.line_id)))
                    .cloned()
                    .collect(),
                None => Vec::new(),
            };
            let p = tmp.path().join(format!("track_{k}.txt"));
            io::write_bytes_atomic(&p, io::track_text(seg, &sup).as_bytes())?;
        }
        Ok(tmp)
    }

    /// Like [`Outputs::write`], into `set`: nothing lands until the caller commits it
    /// (with its own files, as one transaction).
    pub fn stage(
        &self,
        set: &mut io::OutputSet,
        input: &LineSet,
        out: &mut Outcome,
    ) -> Result<(), RunError> {
        readable_result(input, out)?;
        let t = Instant::now();
        match self.format {
            LinesOut::ByExtension => {
                set.write(&self.lines, |p| io::write_lines(p, &out.lines.segments))?;
            }
            LinesOut::Emap => {
                let text = io::edges_json_text(&out.lines.segments);
                set.write(&self.emap_path(), |p| {
                    io::write_bytes_atomic(p, text.as_bytes())
                })?;
            }
            // Written by `write` (a folder, renamed into place after the set).
            LinesOut::Limap => {}
        }
        if let Some(pp) = &self.provenance {
            out.report.sources = Some(out.sources.clone());
            // One output segment a row.
            let rows: Vec<String> = out
                .sources
                .iter()
                .map(|s| serde_json::json!({ "sources": s }).to_string())
                .collect();
            let text = format!(
                "{{\"lines\": {},\n\"output\": {},\n\"segments\": [\n{}\n]}}\n",
                serde_json::json!(out.report.input.lines),
                serde_json::json!(self.lines.display().to_string()),
                rows.join(",\n")
            );
            set.write(pp, |p| io::write_bytes_atomic(p, text.as_bytes()))?;
        }
        if let Some(cp) = &self.compare_ply {
            set.write(cp, |p| {
                io::write_lines_ply_layers(
                    p,
                    &[
                        (&input.segments[..], BEFORE_COLOR),
                        (&out.lines.segments[..], AFTER_COLOR),
                    ],
                )
            })?;
        }
        let write = Stage::since("write", out.lines.len(), t);
        out.report.total_seconds += write.seconds;
        out.report.stages.push(write);
        out.report.output = Some(self.lines.display().to_string());
        if let Some(rp) = &self.report {
            let json = out.report.to_json();
            set.write(rp, |p| io::write_bytes_atomic(p, json.as_bytes()))?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::super::{axis_scene, Job};
    use super::*;
    use crate::engine::select::Backend;
    use crate::refine::Params;

    fn refined() -> (crate::pipeline::Scene, Outcome) {
        let scene = axis_scene();
        let out = Job::new(Params::default(), Backend::Cpu)
            .refine(&scene, |_| {})
            .unwrap();
        (scene, out)
    }

    #[test]
    fn the_lines_the_comparison_and_the_report_land_together() {
        let (scene, mut out) = refined();
        let dir = tempfile::tempdir().unwrap();
        let outputs = Outputs {
            lines: dir.path().join("out.txt"),
            report: Some(dir.path().join("report.json")),
            compare_ply: Some(dir.path().join("compare.ply")),
            ..Default::default()
        };
        outputs.check(&[Path::new("in.txt")]).unwrap();
        outputs.write(&scene.lines, &mut out).unwrap();
        let back = io::read_lines(&outputs.lines).unwrap();
        assert_eq!(back.lines.len(), out.lines.len());
        let text = std::fs::read_to_string(dir.path().join("report.json")).unwrap();
        let json: serde_json::Value = serde_json::from_str(&text).unwrap();
        let stages = json["stages"].as_array().unwrap();
        assert_eq!(stages.last().unwrap()["name"], "write");
        let compare = io::read_lines(&dir.path().join("compare.ply")).unwrap();
        assert_eq!(compare.lines.len(), scene.lines.len() + out.lines.len());
    }

    #[test]
    fn nothing_is_written_for_an_empty_result_or_onto_an_input() {
        let (scene, mut out) = refined();
        let dir = tempfile::tempdir().unwrap();
        let outputs = Outputs {
            lines: dir.path().join("out.obj"),
            report: Some(dir.path().join("report.json")),
            compare_ply: None,
            ..Default::default()
        };
        out.lines = LineSet::new(Vec::new());
        let e = outputs.write(&scene.lines, &mut out).unwrap_err();
        assert!(
            e.is_input_error() && e.to_string().contains("nothing was written"),
            "{e}"
        );
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        let onto_input = Outputs {
            lines: dir.path().join("in.obj"),
            ..Outputs::default()
        };
        assert!(onto_input.check(&[&dir.path().join("in.obj")]).is_err());
    }
}
