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
        set.output("-o", &self.lines, &io::LINE_OUTPUTS);
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
        self.stage(&mut set, input, out)?;
        set.commit()?;
        Ok(())
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
        set.write(&self.lines, |p| io::write_lines(p, &out.lines.segments))?;
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
