//! Dataset runs (`linegs-gpu batch`): a manifest of scenes, each refined through
//! [`crate::pipeline`] into its own folder, a shard of them per process (a Slurm array
//! task), and a summary of every finished scene in the columns of the paper's Table I.
//!
//! Layout of `OUTDIR`: `<name>/refined.<ext>` and `<name>/report.json` for a finished
//! scene, `<name>/error.txt` for a failed one; each folder appears whole (built under a
//! temporary name, then renamed). `summary.csv` and `summary.md` are rewritten from the
//! folders after a run (unless `summary` is off, as for concurrent shards), one row per
//! scene of the manifest with its state (`ok`, `failed: ...`, `pending`), so a summary
//! says which scenes it saw.

use crate::engine::select::Backend;
use crate::eval::Metrics;
use crate::io::{self, Position};
use crate::pipeline::{Job, LoadOptions, Outputs, RunError, Scene};
use crate::refine::{Params, RadiusArg};
use crate::report::Report;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// One scene of the manifest.
#[derive(Clone, Debug, PartialEq)]
pub struct Entry {
    pub name: String,
    pub gaussians: PathBuf,
    pub lines: PathBuf,
    pub gt: Option<PathBuf>,
    pub radius: Option<RadiusArg>,
    pub eval_radius: Option<f64>,
    /// 1-based line of the manifest.
    pub line: usize,
}

/// The scenes of a manifest, paths resolved against its folder.
#[derive(Clone, Debug, PartialEq)]
pub struct Manifest {
    pub path: PathBuf,
    pub entries: Vec<Entry>,
}

/// Splits one CSV record (RFC 4180 quoting: `"a, b"`, `""` for a quote).
fn csv_fields(line: &str) -> Result<Vec<String>, String> {
    let mut out = Vec::new();
    let mut cur = String::new();
    let mut chars = line.chars().peekable();
    let mut quoted = false;
    let mut was_quoted = false;
    while let Some(c) = chars.next() {
        match (quoted, c) {
            (true, '"') if chars.peek() == Some(&'"') => {
                chars.next();
                cur.push('"');
            }
            (true, '"') => quoted = false,
            (true, c) => cur.push(c),
            (false, '"') if cur.trim().is_empty() => {
                cur.clear();
                quoted = true;
                was_quoted = true;
            }
            (false, ',') => {
                out.push(if was_quoted {
                    cur.clone()
                } else {
                    cur.trim().to_string()
                });
                cur.clear();
                was_quoted = false;
            }
            // spaces between a closing quote and the comma
            (false, c) if was_quoted && c.is_whitespace() => {}
            (false, c) => cur.push(c),
        }
    }
    if quoted {
        return Err("a quoted field is not closed".into());
    }
    out.push(if was_quoted {
        cur
    } else {
        cur.trim().to_string()
    });
    Ok(out)
}

/// One CSV field, quoted when it needs to be.
fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

const COLUMNS: [&str; 6] = ["name", "gaussians", "lines", "gt", "radius", "eval_radius"];

impl Manifest {
    /// Reads a manifest: a header naming the columns (`name`, `gaussians`, `lines`, and
    /// optionally `gt`, `radius`, `eval_radius`, in any order), then one scene a row;
    /// blank lines and lines starting with `#` are skipped. Paths are relative to the
    /// manifest's folder. Names must be unique and usable as folder names.
    pub fn read(path: &Path) -> Result<Manifest, RunError> {
        let text = std::fs::read_to_string(path).map_err(|e| io::Error::io(path, "read", e))?;
        let bad = |line: usize, msg: String| -> RunError {
            io::Error::parse(path, Position::Line(line), msg).into()
        };
        let base = path.parent().unwrap_or(Path::new("."));
        let mut rows = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.trim_start_matches('\u{feff}')))
            .filter(|(_, l)| !l.trim().is_empty() && !l.trim_start().starts_with('#'));
        let Some((hl, header)) = rows.next() else {
            return Err(bad(1, "the manifest is empty; expected a header `name,gaussians,lines[,gt,radius,eval_radius]`".into()));
        };
        let header = csv_fields(header).map_err(|e| bad(hl, e))?;
        let mut col = [None; 6];
        for (i, h) in header.iter().enumerate() {
            let Some(k) = COLUMNS.iter().position(|c| c.eq_ignore_ascii_case(h)) else {
                return Err(bad(
                    hl,
                    format!(
                        "unknown column `{h}`; the columns are {}",
                        COLUMNS.join(", ")
                    ),
                ));
            };
            if col[k].replace(i).is_some() {
                return Err(bad(hl, format!("column `{h}` appears twice")));
            }
        }
        for (k, c) in COLUMNS.iter().enumerate().take(3) {
            if col[k].is_none() {
                return Err(bad(hl, format!("the header has no `{c}` column")));
            }
        }
        let mut entries: Vec<Entry> = Vec::new();
        for (line, row) in rows {
            let f = csv_fields(row).map_err(|e| bad(line, e))?;
            if f.len() != header.len() {
                return Err(bad(
                    line,
                    format!("{} fields, the header has {}", f.len(), header.len()),
                ));
            }
            let get = |k: usize| col[k].map(|i| f[i].as_str()).filter(|s| !s.is_empty());
            let need = |k: usize| {
                get(k).ok_or_else(|| bad(line, format!("the `{}` field is empty", COLUMNS[k])))
            };
            let name = need(0)?.to_string();
            if name.starts_with('.') || name.contains(['/', '\\']) || name == "summary.csv" {
                return Err(bad(
                    line,
                    format!(
                        "scene name `{name}` cannot be a folder name (no `/`, `\\` or leading `.`)"
                    ),
                ));
            }
            if let Some(prev) = entries.iter().find(|e| e.name == name) {
                return Err(bad(
                    line,
                    format!("scene name `{name}` is already used on line {}", prev.line),
                ));
            }
            let radius = get(4)
                .map(|s| s.parse::<RadiusArg>())
                .transpose()
                .map_err(|e| bad(line, format!("radius: {e}")))?;
            let eval_radius = get(5)
                .map(crate::refine::params::positive)
                .transpose()
                .map_err(|e| bad(line, format!("eval_radius: {e}")))?;
            entries.push(Entry {
                gaussians: base.join(need(1)?),
                lines: base.join(need(2)?),
                gt: get(3).map(|g| base.join(g)),
                name,
                radius,
                eval_radius,
                line,
            });
        }
        if entries.is_empty() {
            return Err(bad(hl, "the manifest lists no scene".into()));
        }
        Ok(Manifest {
            path: path.to_path_buf(),
            entries,
        })
    }
}

/// Which scenes this process runs: every `count`-th, starting at `index` (0-based).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Shard {
    pub index: usize,
    pub count: usize,
}

impl Default for Shard {
    fn default() -> Self {
        Shard { index: 0, count: 1 }
    }
}

impl std::str::FromStr for Shard {
    type Err = String;
    /// `i/n` with `0 <= i < n`.
    fn from_str(s: &str) -> Result<Shard, String> {
        let err = || format!("expected `i/n` with 0 <= i < n (e.g. `0/4`), got `{s}`");
        let (i, n) = s.split_once('/').ok_or_else(err)?;
        let (index, count) = (
            i.trim().parse::<usize>().map_err(|_| err())?,
            n.trim().parse::<usize>().map_err(|_| err())?,
        );
        if count == 0 || index >= count {
            return Err(err());
        }
        Ok(Shard { index, count })
    }
}

impl Shard {
    /// The shard of a Slurm array task: `SLURM_ARRAY_TASK_ID - SLURM_ARRAY_TASK_MIN` of
    /// `SLURM_ARRAY_TASK_COUNT`, or `None` outside an array job.
    pub fn from_env(var: impl Fn(&str) -> Option<String>) -> Result<Option<Shard>, String> {
        let (Some(id), Some(count)) = (var("SLURM_ARRAY_TASK_ID"), var("SLURM_ARRAY_TASK_COUNT"))
        else {
            return Ok(None);
        };
        let num = |name: &str, v: &str| {
            v.trim()
                .parse::<usize>()
                .map_err(|_| format!("{name}={v} is not a task number"))
        };
        let id = num("SLURM_ARRAY_TASK_ID", &id)?;
        let count = num("SLURM_ARRAY_TASK_COUNT", &count)?;
        let min = match var("SLURM_ARRAY_TASK_MIN") {
            Some(m) => num("SLURM_ARRAY_TASK_MIN", &m)?,
            None => 0,
        };
        let index = id.checked_sub(min).filter(|&i| i < count).ok_or_else(|| {
            format!(
                "SLURM_ARRAY_TASK_ID={id} is not one of {count} tasks from {min}; \
                 use a contiguous --array range or pass --shard i/n"
            )
        })?;
        Ok(Some(Shard { index, count }))
    }

    pub fn includes(&self, i: usize) -> bool {
        i % self.count == self.index
    }
}

/// How to run a batch.
#[derive(Clone, Debug)]
pub struct BatchOptions {
    /// Parameters of every scene; a manifest's `radius` and `eval_radius` override them.
    pub params: Params,
    pub backend: Backend,
    pub shard: Shard,
    /// Leave scenes that already have a report alone.
    pub skip_existing: bool,
    /// Extension of the refined segments' file (`obj`, `stl`, `ply`, `txt`, `npy`).
    pub format: String,
    /// Rewrite the summary after the run. Off for concurrent shards (Slurm array tasks),
    /// whose summaries would each see a different part of the dataset; one later run
    /// (`--summary-only`) then writes it from every scene's folder.
    pub summary: bool,
}

/// What happened to one scene in this run.
#[derive(Clone, Debug, PartialEq)]
pub enum Status {
    Done { seconds: f64 },
    Skipped,
    Failed(String),
}

/// The scene's folder.
pub fn scene_dir(outdir: &Path, name: &str) -> PathBuf {
    outdir.join(name)
}

/// The parameters of `e`: the batch's, with the manifest's overrides.
pub fn entry_params(e: &Entry, base: &Params) -> Params {
    let mut p = base.clone();
    if let Some(r) = e.radius {
        p.radius = r;
    }
    if let Some(r) = e.eval_radius {
        p.eval.eval_radius = r;
    }
    p
}

fn run_scene(e: &Entry, opts: &BatchOptions, dir: &Path) -> Result<(), RunError> {
    let scene = Scene::load(&e.gaussians, &e.lines, &LoadOptions::default())?;
    let gt = match &e.gt {
        Some(p) => Some(io::read_lines(p)?.lines.segments),
        None => None,
    };
    let job = Job {
        gt,
        ..Job::new(entry_params(e, &opts.params), opts.backend)
    };
    let mut out = job.refine(&scene, |_| {})?;
    Outputs {
        lines: dir.join(format!("refined.{}", opts.format)),
        report: Some(dir.join("report.json")),
        compare_ply: None,
    }
    .write(&scene.lines, &mut out)
}

/// Builds `<outdir>/<name>` under a temporary name with `fill`, then swaps it in, so the
/// folder is never seen half written.
fn commit_dir(
    outdir: &Path,
    name: &str,
    fill: impl FnOnce(&Path) -> Result<(), RunError>,
) -> Result<(), RunError> {
    let tmp = tempfile::Builder::new()
        .prefix(&format!(".{name}.partial-"))
        .tempdir_in(outdir)
        .map_err(|e| io::Error::io(outdir, "create a folder in", e))?;
    fill(tmp.path())?;
    let dst = scene_dir(outdir, name);
    let old = outdir.join(format!(".{name}.old-{}", std::process::id()));
    let had_old = dst.exists();
    if had_old {
        std::fs::rename(&dst, &old).map_err(|e| io::Error::io(&dst, "move aside", e))?;
    }
    let tmp = tmp.keep();
    std::fs::rename(&tmp, &dst).map_err(|e| io::Error::io(&dst, "create", e))?;
    if had_old {
        let _ = std::fs::remove_dir_all(&old);
    }
    Ok(())
}

/// Runs this shard's scenes of `m` into `outdir`, calling `on_scene` after each, then
/// (with `opts.summary`) rewrites the summary from every finished scene. A failing scene is recorded
/// (`<name>/error.txt`) and does not stop the others.
pub fn run(
    m: &Manifest,
    outdir: &Path,
    opts: &BatchOptions,
    mut on_scene: impl FnMut(&Entry, &Status),
) -> Result<Vec<(String, Status)>, RunError> {
    io::check_line_output(Path::new(&format!("refined.{}", opts.format)))?;
    std::fs::create_dir_all(outdir).map_err(|e| io::Error::io(outdir, "create", e))?;
    let mut done = Vec::new();
    for (i, e) in m.entries.iter().enumerate() {
        if !opts.shard.includes(i) {
            continue;
        }
        let status =
            if opts.skip_existing && scene_dir(outdir, &e.name).join("report.json").is_file() {
                Status::Skipped
            } else {
                let t = Instant::now();
                match commit_dir(outdir, &e.name, |d| run_scene(e, opts, d)) {
                    Ok(()) => Status::Done {
                        seconds: t.elapsed().as_secs_f64(),
                    },
                    Err(err) => {
                        let msg = err.to_string();
                        commit_dir(outdir, &e.name, |d| {
                            io::write_bytes_atomic(
                                &d.join("error.txt"),
                                format!("{msg}\n").as_bytes(),
                            )?;
                            Ok(())
                        })?;
                        Status::Failed(msg)
                    }
                }
            };
        on_scene(e, &status);
        done.push((e.name.clone(), status));
    }
    if opts.summary {
        write_summary(m, outdir)?;
    }
    Ok(done)
}

/// Removes the temporary folders (`.<name>.partial-*`, `.<name>.old-*`) that runs killed
/// mid-scene left in `outdir`; returns how many. Only safe when no run is writing there.
pub fn remove_partial_dirs(outdir: &Path) -> Result<usize, RunError> {
    let entries = std::fs::read_dir(outdir).map_err(|e| io::Error::io(outdir, "read", e))?;
    let mut n = 0;
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        let ours = name.starts_with('.') && (name.contains(".partial-") || name.contains(".old-"));
        if ours && entry.path().is_dir() {
            let p = entry.path();
            std::fs::remove_dir_all(&p).map_err(|e| io::Error::io(&p, "remove", e))?;
            n += 1;
        }
    }
    Ok(n)
}

/// What the output folder holds for one scene.
#[derive(Clone, Debug)]
pub enum Finished {
    Ok(Box<Report>),
    Failed(String),
    Pending,
}

/// Reads the state of every scene of `m` from `outdir`.
pub fn collect(m: &Manifest, outdir: &Path) -> Vec<(String, Finished)> {
    m.entries
        .iter()
        .map(|e| {
            let d = scene_dir(outdir, &e.name);
            let state = if let Ok(bytes) = std::fs::read(d.join("report.json")) {
                match serde_json::from_slice::<Report>(&bytes) {
                    Ok(r) => Finished::Ok(Box::new(r)),
                    Err(err) => Finished::Failed(format!("report.json does not read back: {err}")),
                }
            } else if let Ok(msg) = std::fs::read_to_string(d.join("error.txt")) {
                Finished::Failed(msg.trim().to_string())
            } else {
                Finished::Pending
            };
            (e.name.clone(), state)
        })
        .collect()
}

/// Relative improvement in percent, positive when `after` is better: lower is better for
/// E_rms and R_L, higher for R_covered and the score.
pub fn improvement(before: Option<f64>, after: Option<f64>, lower_is_better: bool) -> Option<f64> {
    let (b, a) = (before?, after?);
    if b == 0.0 || !b.is_finite() || !a.is_finite() {
        return None;
    }
    let d = if lower_is_better { b - a } else { a - b };
    Some(100.0 * d / b.abs())
}

/// The numbers of one summary row (`None`: not defined or not measured).
fn row_values(r: &Report) -> Vec<Option<f64>> {
    let a = r.after.as_ref();
    let mut v = vec![
        Some(r.before.segments as f64 + r.before.skipped as f64),
        a.map(|m| m.segments as f64 + m.skipped as f64),
    ];
    type Metric = fn(&Metrics) -> Option<f64>;
    let metrics: [(Metric, bool); 4] = [
        (|m| m.e_rms_cm, true),
        (|m| m.coverage_pct, false),
        (|m| m.r_l, true),
        (|m| m.score, false),
    ];
    for (f, lower) in metrics {
        let (b, af) = (f(&r.before), a.and_then(f));
        v.extend([b, af, improvement(b, af, lower)]);
    }
    let g = r.ground_truth.as_ref();
    let gb = g.map(|g| &g.before);
    let ga = g.and_then(|g| g.after.as_ref());
    v.extend([
        gb.and_then(|m| m.accuracy),
        ga.and_then(|m| m.accuracy),
        gb.and_then(|m| m.completeness),
        ga.and_then(|m| m.completeness),
    ]);
    for k in 0..crate::eval::gt::THRESHOLDS.len() {
        v.push(gb.and_then(|m| m.scores.get(k)).map(|s| s.f_score));
        v.push(ga.and_then(|m| m.scores.get(k)).map(|s| s.f_score));
    }
    v.push(Some(r.total_seconds));
    v
}

fn value_columns() -> Vec<String> {
    let mut c: Vec<String> = vec!["segments_before".into(), "segments_after".into()];
    for m in ["e_rms_cm", "coverage_pct", "r_l", "score"] {
        c.extend([
            format!("{m}_before"),
            format!("{m}_after"),
            format!("{m}_improvement_pct"),
        ]);
    }
    for m in ["gt_accuracy", "gt_completeness"] {
        c.extend([format!("{m}_before"), format!("{m}_after")]);
    }
    for t in crate::eval::gt::THRESHOLDS {
        c.extend([format!("gt_f{t}_before"), format!("gt_f{t}_after")]);
    }
    c.push("seconds".into());
    c
}

/// The summary's table: one row per scene of the manifest, then the mean over the
/// finished scenes (its improvements are those of the mean before and after values, as
/// Table I of the paper reads).
pub struct Summary {
    pub columns: Vec<String>,
    /// `(name, status, values)`; status is `ok`, `failed: ...` or `pending`.
    pub rows: Vec<(String, String, Vec<Option<f64>>)>,
    pub mean: Vec<Option<f64>>,
    pub finished: usize,
}

pub fn summarize(m: &Manifest, outdir: &Path) -> Summary {
    let columns = value_columns();
    let mut rows = Vec::new();
    for (name, state) in collect(m, outdir) {
        let (status, values) = match state {
            Finished::Ok(r) => ("ok".to_string(), row_values(&r)),
            Finished::Failed(msg) => (
                format!("failed: {}", msg.replace(['\n', '\r'], " ")),
                vec![None; columns.len()],
            ),
            Finished::Pending => ("pending".to_string(), vec![None; columns.len()]),
        };
        rows.push((name, status, values));
    }
    let ok: Vec<&Vec<Option<f64>>> = rows.iter().filter(|r| r.1 == "ok").map(|r| &r.2).collect();
    let mut mean: Vec<Option<f64>> = (0..columns.len())
        .map(|k| {
            let xs: Vec<f64> = ok.iter().filter_map(|v| v[k]).collect();
            (!xs.is_empty()).then(|| xs.iter().sum::<f64>() / xs.len() as f64)
        })
        .collect();
    // improvements of the mean row: from the mean before and after
    for (k, c) in columns.iter().enumerate() {
        if let Some(metric) = c.strip_suffix("_improvement_pct") {
            let lower = matches!(metric, "e_rms_cm" | "r_l");
            mean[k] = improvement(mean[k - 2], mean[k - 1], lower);
        }
    }
    let finished = ok.len();
    Summary {
        columns,
        rows,
        mean,
        finished,
    }
}

fn num(v: Option<f64>, prec: usize) -> String {
    v.map_or(String::new(), |x| format!("{x:.prec$}"))
}

impl Summary {
    pub fn to_csv(&self) -> String {
        let mut s = String::from("name,status");
        for c in &self.columns {
            s.push(',');
            s.push_str(c);
        }
        s.push('\n');
        let mean = (
            "mean".to_string(),
            format!("mean of {} finished", self.finished),
            self.mean.clone(),
        );
        for (name, status, v) in self.rows.iter().chain(std::iter::once(&mean)) {
            s.push_str(&csv_field(name));
            s.push(',');
            s.push_str(&csv_field(status));
            for x in v {
                s.push(',');
                if let Some(x) = x {
                    s.push_str(&format!("{x}"));
                }
            }
            s.push('\n');
        }
        s
    }

    /// Table I of the paper, before → after with the improvement, plus ground truth.
    pub fn to_markdown(&self) -> String {
        let col = |name: &str| self.columns.iter().position(|c| c == name).expect("column");
        let ba = |v: &[Option<f64>], m: &str, prec: usize| {
            let (b, a) = (
                v[col(&format!("{m}_before"))],
                v[col(&format!("{m}_after"))],
            );
            if b.is_none() && a.is_none() {
                return String::new();
            }
            let mut s = format!("{} → {}", num(b, prec), num(a, prec));
            let imp = format!("{m}_improvement_pct");
            if let Some(i) = self
                .columns
                .iter()
                .position(|c| *c == imp)
                .and_then(|k| v[k])
            {
                let _ = write!(s, " ({i:+.1} %)");
            }
            s
        };
        let mut s = String::from(
            "| scene | segments | E_rms (cm) | R_covered (%) | R_L | score | GT accuracy | GT F@0.01 |\n\
             |---|---|---|---|---|---|---|---|\n",
        );
        let mean = ("**mean**".to_string(), "ok".to_string(), self.mean.clone());
        for (name, status, v) in self.rows.iter().chain(std::iter::once(&mean)) {
            if status != "ok" {
                let _ = writeln!(s, "| {name} | {status} | | | | | | |");
                continue;
            }
            let _ = writeln!(
                s,
                "| {name} | {} | {} | {} | {} | {} | {} | {} |",
                ba(v, "segments", 0),
                ba(v, "e_rms_cm", 3),
                ba(v, "coverage_pct", 2),
                ba(v, "r_l", 3),
                ba(v, "score", 3),
                ba(v, "gt_accuracy", 4),
                ba(v, "gt_f0.01", 3),
            );
        }
        let _ = write!(
            s,
            "\n{} of {} scenes finished. Improvement: positive is better (lower E_rms and R_L, \
             higher R_covered and score); the mean row's is that of the mean values.\n",
            self.finished,
            self.rows.len()
        );
        s
    }
}

/// (Re)writes `summary.csv` and `summary.md` in `outdir` from every finished scene.
pub fn write_summary(m: &Manifest, outdir: &Path) -> Result<Summary, RunError> {
    let s = summarize(m, outdir);
    io::write_bytes_atomic(&outdir.join("summary.csv"), s.to_csv().as_bytes())?;
    io::write_bytes_atomic(&outdir.join("summary.md"), s.to_markdown().as_bytes())?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn csv_fields_trim_and_unquote() {
        assert_eq!(csv_fields("a, b ,c").unwrap(), ["a", "b", "c"]);
        assert_eq!(
            csv_fields(r#""x, y",  "say ""hi""" ,z"#).unwrap(),
            ["x, y", r#"say "hi""#, "z"]
        );
        assert_eq!(csv_fields("a,,").unwrap(), ["a", "", ""]);
        assert!(csv_fields(r#""open"#).is_err());
        assert_eq!(csv_field("a,b"), r#""a,b""#);
    }

    #[test]
    fn shards_parse_and_come_from_slurm() {
        assert_eq!("1/3".parse::<Shard>(), Ok(Shard { index: 1, count: 3 }));
        for bad in ["3/3", "0/0", "x/2", "1"] {
            assert!(bad.parse::<Shard>().is_err(), "{bad}");
        }
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| pairs.iter().find(|p| p.0 == k).map(|p| p.1.to_string())
        };
        assert_eq!(Shard::from_env(env(&[])), Ok(None));
        let s = Shard::from_env(env(&[
            ("SLURM_ARRAY_TASK_ID", "2"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]));
        assert_eq!(s, Ok(Some(Shard { index: 2, count: 4 })));
        // --array=1-4: ids 1..=4
        let s = Shard::from_env(env(&[
            ("SLURM_ARRAY_TASK_ID", "4"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
            ("SLURM_ARRAY_TASK_MIN", "1"),
        ]));
        assert_eq!(s, Ok(Some(Shard { index: 3, count: 4 })));
        let s = Shard::from_env(env(&[
            ("SLURM_ARRAY_TASK_ID", "4"),
            ("SLURM_ARRAY_TASK_COUNT", "4"),
        ]));
        assert!(s.is_err());
        let every: Vec<usize> = (0..7)
            .filter(|&i| Shard { index: 1, count: 3 }.includes(i))
            .collect();
        assert_eq!(every, [1, 4]);
    }

    #[test]
    fn a_manifest_resolves_paths_and_names_its_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.csv");
        std::fs::write(
            &p,
            "# scenes\nname, lines, gaussians, radius\na, a/l.obj, a/g.ply, auto\n\nb,/abs/l.txt,g.ply,\n",
        )
        .unwrap();
        let m = Manifest::read(&p).unwrap();
        assert_eq!(m.entries.len(), 2);
        assert_eq!(m.entries[0].gaussians, dir.path().join("a/g.ply"));
        assert_eq!(m.entries[0].radius, Some(RadiusArg::Auto));
        assert_eq!(m.entries[1].lines, PathBuf::from("/abs/l.txt"));
        assert_eq!(m.entries[1].radius, None);
        assert_eq!(m.entries[1].line, 5);
        for (text, needle) in [
            ("name,lines\na,b\n", "no `gaussians` column"),
            ("name,gaussians,lines,colour\n", "unknown column `colour`"),
            (
                "name,gaussians,lines\na,g,l\na,g,l\n",
                "line 3: scene name `a` is already used on line 2",
            ),
            (
                "name,gaussians,lines\n../x,g,l\n",
                "cannot be a folder name",
            ),
            (
                "name,gaussians,lines\na,g\n",
                "line 2: 2 fields, the header has 3",
            ),
            (
                "name,gaussians,lines,radius\na,g,l,-1\n",
                "radius: expected a positive number",
            ),
            ("name,gaussians,lines\n", "lists no scene"),
            ("", "empty"),
        ] {
            std::fs::write(&p, text).unwrap();
            let e = Manifest::read(&p).unwrap_err();
            assert!(e.is_input_error());
            let msg = e.to_string();
            assert!(
                msg.contains(needle) && msg.contains("m.csv"),
                "{text:?}: {msg}"
            );
        }
    }

    #[test]
    fn improvement_is_positive_when_better() {
        assert_eq!(improvement(Some(4.0), Some(3.0), true), Some(25.0));
        assert_eq!(improvement(Some(4.0), Some(5.0), false), Some(25.0));
        assert_eq!(improvement(Some(0.0), Some(5.0), false), None);
        assert_eq!(improvement(None, Some(5.0), false), None);
    }
}
