//! Dataset runs (`linegs-gpu batch`): a manifest of scenes, each refined through
//! [`crate::pipeline`] into its own folder, a shard of them per process (a Slurm array
//! task), and a summary of every finished scene in the columns of the paper's Table I.
//!
//! Layout of `OUTDIR`: `<name>/refined.<ext>` and `<name>/report.json` for a finished
//! scene, `<name>/error.txt` for a failed one. These are the only files `batch` writes or
//! removes in a scene's folder, so the folder may also hold the scene's inputs (`-o .`
//! with inputs in `./<name>/`) or anything else; each is written atomically, and a lock
//! file (`<name>/.linegs-batch.lock`, removed afterwards) keeps two runs from working on
//! one scene at the same time. `summary.csv` and `summary.md` are rewritten from the
//! folders after a run (unless `summary` is off, as for concurrent shards), one row per
//! scene of the manifest with its state (`ok`, `failed: ...`, `pending`), so a summary
//! says which scenes it saw.

use crate::engine::select::{prepare, Backend, Pending};
use crate::eval::Metrics;
use crate::io::{self, Position};
use crate::pipeline::{Job, LoadOptions, Outputs, RunError, Scene};
use crate::refine::{Params, RadiusArg};
use crate::report::Report;
use std::collections::HashMap;
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

/// The files of the summary in the output folder.
pub const SUMMARY_FILES: [&str; 2] = ["summary.csv", "summary.md"];

/// How many manifest rows between two calls of the progress of
/// [`Manifest::read_with_progress`].
pub const MANIFEST_PROGRESS_ROWS: usize = 1 << 16;

impl Manifest {
    /// Reads a manifest: a header naming the columns (`name`, `gaussians`, `lines`, and
    /// optionally `gt`, `radius`, `eval_radius`, in any order), then one scene a row;
    /// blank lines and lines starting with `#` are skipped. Paths are relative to the
    /// manifest's folder. Names must be unique and usable as folder names. Linear in the
    /// manifest's size.
    pub fn read(path: &Path) -> Result<Manifest, RunError> {
        Self::read_with_progress(path, |_, _, _| {})
    }

    /// [`Manifest::read`], calling `progress(rows, bytes_read, bytes)` every
    /// [`MANIFEST_PROGRESS_ROWS`] rows.
    pub fn read_with_progress(
        path: &Path,
        mut progress: impl FnMut(usize, usize, usize),
    ) -> Result<Manifest, RunError> {
        let bytes = io::read_small(path, "a manifest", 256 << 20, false)?;
        let text = String::from_utf8(bytes).map_err(|e| {
            // The line of the first byte that is not UTF-8.
            let at = e.utf8_error().valid_up_to();
            let line = 1 + e.as_bytes()[..at].iter().filter(|&&b| b == b'\n').count();
            io::Error::parse(
                path,
                Position::Line(line),
                "a manifest is UTF-8 text; this line is not".to_string(),
            )
        })?;
        let total = text.len();
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
        // Names seen, folded to lower case: the index of their entry (one lookup a row
        // finds both a repeated name and one that differs only in case).
        let mut folded: HashMap<String, usize> = HashMap::with_capacity(total / 64);
        for (line, row) in rows {
            if entries.len() % MANIFEST_PROGRESS_ROWS == MANIFEST_PROGRESS_ROWS - 1 {
                let done = row.as_ptr() as usize - text.as_ptr() as usize;
                progress(entries.len() + 1, done, total);
            }
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
            if name.starts_with('.') || name.contains(['/', '\\']) {
                return Err(bad(
                    line,
                    format!(
                        "scene name `{name}` cannot be a folder name (no `/`, `\\` or leading `.`)"
                    ),
                ));
            }
            if SUMMARY_FILES.iter().any(|f| f.eq_ignore_ascii_case(&name)) {
                return Err(bad(
                    line,
                    format!(
                        "scene name `{name}` is the name of the summary table that batch \
                         writes in the output folder; rename the scene"
                    ),
                ));
            }
            let lower = name.to_lowercase();
            let prev = folded.get(&lower).map(|&k| &entries[k]);
            if let Some(prev) = prev.filter(|p| p.name == name) {
                return Err(bad(
                    line,
                    format!("scene name `{name}` is already used on line {}", prev.line),
                ));
            }
            // Folders `S1` and `s1` are one folder on case-insensitive file systems.
            if let Some(prev) = prev {
                return Err(bad(
                    line,
                    format!(
                        "scene name `{name}` differs from `{}` on line {} only in case, and \
                         their folders would be one on a case-insensitive file system",
                        prev.name, prev.line
                    ),
                ));
            }
            if name.eq_ignore_ascii_case("mean") {
                return Err(bad(
                    line,
                    "scene name `mean` is the summary's row of the mean; rename the scene".into(),
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
            folded.insert(lower, entries.len());
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

/// A `--shard` value or a Slurm array task's variables that name no shard.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum ShardError {
    /// `--shard` is not `i/n` with `0 <= i < n`.
    #[error("expected `i/n` with 0 <= i < n (e.g. `0/4`), got `{0}`")]
    Syntax(String),
    /// A `SLURM_ARRAY_TASK_*` variable is not a whole number.
    #[error("{name}={value} is not a task number")]
    NotANumber { name: &'static str, value: String },
    /// The task id is outside the array's `count` tasks from `min`.
    #[error(
        "SLURM_ARRAY_TASK_ID={id} is not one of {count} tasks from {min}; \
         use a contiguous --array range or pass --shard i/n"
    )]
    OutsideArray { id: usize, count: usize, min: usize },
}

impl std::str::FromStr for Shard {
    type Err = ShardError;
    /// `i/n` with `0 <= i < n`.
    fn from_str(s: &str) -> Result<Shard, ShardError> {
        let err = || ShardError::Syntax(s.to_string());
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
    pub fn from_env(var: impl Fn(&str) -> Option<String>) -> Result<Option<Shard>, ShardError> {
        let (Some(id), Some(count)) = (var("SLURM_ARRAY_TASK_ID"), var("SLURM_ARRAY_TASK_COUNT"))
        else {
            return Ok(None);
        };
        let num = |name: &'static str, v: &str| {
            v.trim()
                .parse::<usize>()
                .map_err(|_| ShardError::NotANumber {
                    name,
                    value: v.to_string(),
                })
        };
        let id = num("SLURM_ARRAY_TASK_ID", &id)?;
        let count = num("SLURM_ARRAY_TASK_COUNT", &count)?;
        let min = match var("SLURM_ARRAY_TASK_MIN") {
            Some(m) => num("SLURM_ARRAY_TASK_MIN", &m)?,
            None => 0,
        };
        let index = id
            .checked_sub(min)
            .filter(|&i| i < count)
            .ok_or(ShardError::OutsideArray { id, count, min })?;
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
    /// How the GPU engine opens (the commands' environment).
    pub gpu: crate::engine::gpu::GpuSetup,
    pub shard: Shard,
    /// Leave scenes that already have a report alone.
    pub skip_existing: bool,
    /// Extension of the refined segments' file (`obj`, `stl`, `ply`, `txt`, `npy`).
    pub format: String,
    /// How the manifest's `gt` edges score the lines.
    pub protocol: crate::eval::gt::Protocol,
    /// Rewrite the summary after the run. Off for concurrent shards (Slurm array tasks),
    /// whose summaries would each see a different part of the dataset; one later run
    /// (`--summary-only`) then writes it from every scene's folder.
    pub summary: bool,
}

/// What happened to one scene in this run.
#[derive(Clone, Debug, PartialEq)]
pub enum Status {
    Done {
        seconds: f64,
    },
    Skipped,
    /// Another `batch` holds the scene's lock (it is working on it now).
    Busy,
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

/// The files `batch` writes in a scene's folder: the refined segments, the report, the
/// error of a failed scene. Nothing else in the folder is touched.
fn owned_files(dir: &Path, format: &str) -> [PathBuf; 3] {
    [
        dir.join(format!("refined.{format}")),
        dir.join("report.json"),
        dir.join("error.txt"),
    ]
}

/// The files of `e` the run reads, which no file of the run may replace.
fn entry_inputs(e: &Entry) -> Vec<&Path> {
    let mut v = vec![e.gaussians.as_path(), e.lines.as_path()];
    v.extend(e.gt.as_deref());
    v
}

/// The device of the batch's scenes: opened for the first scene that runs (while its files
/// are read) and kept for the next ones (each uploads its own Gaussians).
type Device = Option<Pending>;

fn run_scene(
    e: &Entry,
    opts: &BatchOptions,
    dir: &Path,
    device: &mut Device,
) -> Result<(), RunError> {
    let [refined, report, _] = owned_files(dir, &opts.format);
    let outputs = Outputs {
        lines: refined,
        report: Some(report),
        compare_ply: None,
        ..Default::default()
    };
    outputs.check(&entry_inputs(e))?;
    let device = device.get_or_insert_with(|| prepare(opts.backend, &opts.gpu));
    let scene = Scene::load(&e.gaussians, &e.lines, &LoadOptions::default())?;
    let gt = match &e.gt {
        Some(p) => Some(crate::eval::gt::Reference {
            edges: crate::eval::gt::read_gt_file(p)?.0,
            protocol: opts.protocol,
        }),
        None => None,
    };
    let job = Job {
        gt,
        gpu: opts.gpu.clone(),
        ..Job::new(entry_params(e, &opts.params), opts.backend)
    };
    let mut out = job.refine_on(&scene, device, |_| {})?;
    outputs.write(&scene.lines, &mut out)
}

/// Removes `path` if it exists and is not one of `inputs`.
fn remove_owned(path: &Path, inputs: &[&Path]) -> Result<(), RunError> {
    if inputs.iter().any(|i| io::same_file(path, i)) {
        return Ok(());
    }
    match std::fs::remove_file(path) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            Err(io::Error::io(path, "remove the earlier", e).into())
        }
        _ => Ok(()),
    }
}

/// Name of the lock file in a scene's folder, held while a run works on the scene.
pub const LOCK_NAME: &str = ".linegs-batch.lock";

/// The lock of one scene's folder: while it is held, no other `batch` works on the scene.
/// Dropping it removes the lock file.
struct SceneLock {
    path: PathBuf,
    _file: std::fs::File,
}

impl Drop for SceneLock {
    fn drop(&mut self) {
        // Removed while still locked, so a run that opened it meanwhile sees a stale inode
        // and opens the new file instead (see `lock_scene`).
        let _ = std::fs::remove_file(&self.path);
    }
}

/// Takes the lock of `dir` (created if missing), or `None` when another run holds it.
fn lock_scene(dir: &Path) -> Result<Option<SceneLock>, RunError> {
    let path = dir.join(LOCK_NAME);
    loop {
        let file = std::fs::OpenOptions::new()
            .create(true)
            .truncate(false)
            .write(true)
            .open(&path)
            .map_err(|e| io::Error::io(&path, "create", e))?;
        match io::try_lock(&file) {
            Ok(true) => {}
            Ok(false) => return Ok(None),
            Err(e) => return Err(io::Error::io(&path, "lock", e).into()),
        }
        // The holder before us may have removed the file after we opened it: the lock is
        // ours only if the path still names the file we locked.
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            let (Ok(a), Ok(b)) = (file.metadata(), std::fs::metadata(&path)) else {
                continue;
            };
            if (a.dev(), a.ino()) != (b.dev(), b.ino()) {
                continue;
            }
        }
        return Ok(Some(SceneLock { path, _file: file }));
    }
}

/// Removes what killed runs left for scene `name`, by the one rule of `io::litter` (a
/// temporary file is taken only when its lock is free, it is old and it was made on this
/// host: the scene's lock does not keep a `refine` that writes into the same folder out),
/// and the `.NAME.partial-*` / `.NAME.old-*` folders that earlier versions built scenes
/// in. A killed run's committed output set is finished first: its temporary files are
/// the set's new outputs. If it cannot be, they stay.
fn clean_litter(outdir: &Path, name: &str, dir: &Path) {
    if io::finish_output_sets(dir).is_ok() {
        io::clean_stale_temps(dir);
    }
    let (partial, old) = (format!(".{name}.partial-"), format!(".{name}.old-"));
    if let Ok(rd) = std::fs::read_dir(outdir) {
        for d in rd.flatten() {
            let f = d.file_name().to_string_lossy().into_owned();
            if (f.starts_with(&partial) || f.starts_with(&old))
                && d.file_type().is_ok_and(|t| t.is_dir())
            {
                let _ = std::fs::remove_dir_all(d.path());
            }
        }
    }
}

/// Runs scene `e` into its folder, which may hold other files (the scene's own inputs, a
/// user's notes): only the owned files are written, each atomically, and the one that
/// does not apply to the outcome (`error.txt` after a success, the report and refined
/// segments after a failure) is removed. `None` when another run holds the scene.
fn run_locked(
    e: &Entry,
    opts: &BatchOptions,
    outdir: &Path,
    device: &mut Device,
) -> Result<Option<Status>, RunError> {
    let dir = scene_dir(outdir, &e.name);
    std::fs::create_dir_all(&dir).map_err(|err| io::Error::io(&dir, "create", err))?;
    let Some(_lock) = lock_scene(&dir)? else {
        return Ok(None);
    };
    clean_litter(outdir, &e.name, &dir);
    let [refined, report, error] = owned_files(&dir, &opts.format);
    let inputs = entry_inputs(e);
    let t = Instant::now();
    Ok(Some(match run_scene(e, opts, &dir, device) {
        Ok(()) => {
            remove_owned(&error, &inputs)?;
            Status::Done {
                seconds: t.elapsed().as_secs_f64(),
            }
        }
        Err(err) => {
            // The next scene opens a device of its own: this one may be what failed.
            *device = None;
            let msg = err.to_string();
            let mut set = io::OutputSet::new();
            for i in &inputs {
                set.input(i);
            }
            set.output("error.txt", &error, &["txt"]);
            set.check()?;
            set.write(&error, |p| {
                io::write_bytes_atomic(p, format!("{msg}\n").as_bytes())
            })?;
            set.commit()?;
            remove_owned(&report, &inputs)?;
            remove_owned(&refined, &inputs)?;
            Status::Failed(msg)
        }
    }))
}

/// Checks every path a run of `m` into `outdir` writes against every path it reads, before
/// any work, as `refine` does: the summary tables (when `summary`), and for each scene of
/// `shard` (none for `--summary-only`: `shard` is `None`) its refined segments (`format`),
/// report, error and lock files, against the manifest and every scene's inputs. A clash is
/// bad input (exit 2) and nothing is written.
pub fn check_paths(
    m: &Manifest,
    outdir: &Path,
    format: &str,
    shard: Option<Shard>,
    summary: bool,
) -> Result<(), RunError> {
    let mut reads = io::PathIndex::new();
    reads.add(&m.path);
    let mut seen = std::collections::HashSet::new();
    for e in &m.entries {
        for p in entry_inputs(e) {
            if seen.insert(p) {
                reads.add(p);
            }
        }
    }
    let clash = |what: String, path: &Path| -> Result<(), RunError> {
        let Some(input) = reads.find(path) else {
            return Ok(());
        };
        let whose = if input == m.path {
            "the manifest".to_string()
        } else {
            let owner = m
                .entries
                .iter()
                .find(|e| entry_inputs(e).contains(&input))
                .map(|e| format!("an input of scene `{}` (manifest line {})", e.name, e.line))
                .unwrap_or_else(|| "an input".into());
            format!("{owner} `{}`", input.display())
        };
        Err(io::Error::Output {
            path: path.to_path_buf(),
            msg: format!("{what} is {whose}; writing it would destroy the input"),
        }
        .into())
    };
    if summary {
        for f in SUMMARY_FILES {
            clash(format!("the summary table {f}"), &outdir.join(f))?;
        }
    }
    if let Some(shard) = shard {
        for (i, e) in m.entries.iter().enumerate() {
            if !shard.includes(i) {
                continue;
            }
            let dir = scene_dir(outdir, &e.name);
            let [refined, report, error] = owned_files(&dir, format);
            for p in [refined, report, error, dir.join(LOCK_NAME)] {
                let file = p.file_name().unwrap_or_default().to_string_lossy();
                clash(format!("scene `{}`'s {file}", e.name), &p)?;
            }
        }
    }
    Ok(())
}

/// Runs this shard's scenes of `m` into `outdir`, calling `on_scene` after each, then
/// (with `opts.summary`) rewrites the summary from every finished scene. A failing scene
/// is recorded (`<name>/error.txt`) and does not stop the others; a scene that another
/// `batch` is working on at the same time is left to it ([`Status::Busy`]).
pub fn run(
    m: &Manifest,
    outdir: &Path,
    opts: &BatchOptions,
    mut on_scene: impl FnMut(&Entry, &Status),
) -> Result<Vec<(String, Status)>, RunError> {
    io::check_line_output(Path::new(&format!("refined.{}", opts.format)))?;
    check_paths(m, outdir, &opts.format, Some(opts.shard), opts.summary)?;
    std::fs::create_dir_all(outdir).map_err(|e| io::Error::io(outdir, "create", e))?;
    let mut done = Vec::new();
    let mut device: Device = None;
    for (i, e) in m.entries.iter().enumerate() {
        if !opts.shard.includes(i) {
            continue;
        }
        let status =
            if opts.skip_existing && scene_dir(outdir, &e.name).join("report.json").is_file() {
                Status::Skipped
            } else {
                run_locked(e, opts, outdir, &mut device)?.unwrap_or(Status::Busy)
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
    /// The ground-truth table the papers print (per-object means), when scenes have GT.
    pub ground_truth: Option<GtTable>,
}

/// Per-object means of the ground-truth metrics, as EMAP's `eval_ABC.py` prints them:
/// each metric averaged over the objects that have predictions (an object whose lines
/// give no sample is left out, as there; a NaN F counts as 0).
#[derive(Clone, Debug, PartialEq)]
pub struct GtTable {
    /// `exact`, `emap`, or `mixed` when the reports disagree.
    pub protocol: String,
    /// Scenes with ground truth.
    pub scenes: usize,
    /// `(label, objects averaged, accuracy, completeness, [(P, R, F) per threshold])`
    /// for the input and the refined lines.
    pub rows: Vec<GtRow>,
}

pub type GtRow = (String, usize, Option<f64>, Option<f64>, Vec<[f64; 3]>);

fn gt_row(label: &str, ms: &[&crate::eval::gt::GtMetrics]) -> GtRow {
    let with: Vec<_> = ms.iter().filter(|m| m.accuracy.is_some()).collect();
    let n = with.len();
    let avg = |f: &dyn Fn(&crate::eval::gt::GtMetrics) -> f64| {
        (n > 0).then(|| with.iter().map(|m| f(m)).sum::<f64>() / n as f64)
    };
    let acc = avg(&|m| m.accuracy.unwrap_or(0.0));
    let comp = avg(&|m| m.completeness.unwrap_or(0.0));
    let k = with.first().map_or(0, |m| m.scores.len());
    let scores = (0..k)
        .map(|i| {
            let s = |f: fn(&crate::eval::gt::GtScore) -> f64| {
                avg(&|m| m.scores.get(i).map_or(0.0, f)).unwrap_or(0.0)
            };
            [s(|x| x.precision), s(|x| x.recall), s(|x| x.f_score)]
        })
        .collect();
    (label.to_string(), n, acc, comp, scores)
}

fn gt_table(reports: &[&Report]) -> Option<GtTable> {
    let gts: Vec<_> = reports
        .iter()
        .filter_map(|r| r.ground_truth.as_ref())
        .collect();
    let first = gts.first()?;
    let p = first.before.protocol;
    let protocol = if gts.iter().all(|g| g.before.protocol == p) {
        p.name().to_string()
    } else {
        "mixed".to_string()
    };
    let before: Vec<_> = gts.iter().map(|g| &g.before).collect();
    let after: Vec<_> = gts.iter().filter_map(|g| g.after.as_ref()).collect();
    Some(GtTable {
        protocol,
        scenes: gts.len(),
        rows: vec![gt_row("input lines", &before), gt_row("refined", &after)],
    })
}

impl GtTable {
    /// The papers' table: Acc and Comp (mm under `emap`), then P / R / F in percent.
    pub fn to_markdown(&self) -> String {
        let emap = self.protocol == "emap";
        let unit = if emap { "mm" } else { "lines' units" };
        let mut s = format!(
            "\nGround truth, {} protocol: per-object means over the scenes whose lines give \
             samples (of {} with ground truth); accuracy and completeness in {unit}, \
             precision / recall / F in percent at {}.\n\n",
            self.protocol,
            self.scenes,
            if emap {
                "5 / 10 / 20 mm"
            } else {
                "0.005 / 0.01 / 0.02"
            }
        );
        s.push_str(
            "| lines | objects | Acc | Comp | P5 | R5 | F5 | P10 | R10 | F10 | P20 | R20 | F20 |\n",
        );
        s.push_str("|---|---|---|---|---|---|---|---|---|---|---|---|---|\n");
        let scale = if emap { 1000.0 } else { 1.0 };
        let prec = if emap { 2 } else { 5 };
        for (label, n, acc, comp, scores) in &self.rows {
            let _ = write!(
                s,
                "| {label} | {n} | {} | {} |",
                num(acc.map(|x| x * scale), prec),
                num(comp.map(|x| x * scale), prec)
            );
            for prf in scores {
                for x in prf {
                    let _ = write!(s, " {:.1} |", 100.0 * x);
                }
            }
            s.push('\n');
        }
        s
    }
}

pub fn summarize(m: &Manifest, outdir: &Path) -> Summary {
    let columns = value_columns();
    let mut rows = Vec::new();
    let states = collect(m, outdir);
    let reports: Vec<&Report> = states
        .iter()
        .filter_map(|(_, st)| match st {
            Finished::Ok(r) => Some(&**r),
            _ => None,
        })
        .collect();
    let ground_truth = gt_table(&reports);
    for (name, state) in states.iter().cloned() {
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
        ground_truth,
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
            // A `|` would end the table cell.
            let (name, status) = (name.replace('|', "\\|"), status.replace('|', "\\|"));
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
        if let Some(g) = &self.ground_truth {
            s.push_str(&g.to_markdown());
        }
        s
    }
}

/// (Re)writes `summary.csv` and `summary.md` in `outdir` from every finished scene.
pub fn write_summary(m: &Manifest, outdir: &Path) -> Result<Summary, RunError> {
    let s = summarize(m, outdir);
    // One set: a kill never leaves a new table beside an old one.
    let (csv, md) = (outdir.join("summary.csv"), outdir.join("summary.md"));
    let mut set = io::OutputSet::new();
    set.output("summary.csv", &csv, &["csv"])
        .output("summary.md", &md, &["md"]);
    set.check()?;
    set.write(&csv, |p| io::write_bytes_atomic(p, s.to_csv().as_bytes()))?;
    set.write(&md, |p| {
        io::write_bytes_atomic(p, s.to_markdown().as_bytes())
    })?;
    set.commit()?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A scene whose run was killed between the renames of its outputs: the next run's
    /// cleaning finishes the set instead of removing its new files.
    #[test]
    fn a_scene_killed_between_its_renames_is_finished_not_cleaned_away() {
        let out = tempfile::tempdir().unwrap();
        let dir = out.path().join("s1");
        std::fs::create_dir(&dir).unwrap();
        let [refined, report, _] = owned_files(&dir, "obj");
        let mut set = io::OutputSet::new();
        for f in [&refined, &report] {
            std::fs::write(f, "old").unwrap();
            set.output("-o", f, &[]);
        }
        set.check().unwrap();
        for f in [&refined, &report] {
            set.write(f, |p| io::write_bytes_atomic(p, b"new")).unwrap();
        }
        set.commit_stopping(io::Stop::AfterRenames(1)).unwrap_err();
        assert_eq!(std::fs::read_to_string(&report).unwrap(), "old");
        clean_litter(out.path(), "s1", &dir);
        for f in [&refined, &report] {
            assert_eq!(
                std::fs::read_to_string(f).unwrap(),
                "new",
                "{}",
                f.display()
            );
        }
        let left: Vec<_> = std::fs::read_dir(&dir).unwrap().flatten().collect();
        assert_eq!(left.len(), 2, "{left:?}");
    }

    #[test]
    fn the_papers_mean_leaves_out_an_object_whose_lines_give_no_sample() {
        use crate::eval::gt::{GtMetrics, GtScore, Protocol};
        let m = |acc: Option<f64>, f: f64| GtMetrics {
            protocol: Protocol::Emap,
            step: 0.005,
            predicted_samples: usize::from(acc.is_some()),
            gt_samples: 10,
            accuracy: acc,
            completeness: acc.map(|a| 2.0 * a),
            scores: vec![GtScore {
                threshold: 0.005,
                precision: f,
                recall: f,
                f_score: f,
            }],
            closest: acc,
        };
        let (with, without, other) = (m(Some(0.004), 0.8), m(None, 0.0), m(Some(0.002), 0.6));
        let (label, n, acc, comp, scores) = gt_row("input lines", &[&with, &without, &other]);
        assert_eq!((label.as_str(), n), ("input lines", 2));
        assert!((acc.unwrap() - 0.003).abs() < 1e-15);
        assert!((comp.unwrap() - 0.006).abs() < 1e-15);
        assert!((scores[0][2] - 0.7).abs() < 1e-15, "{scores:?}");
        // No object with samples: no mean at all.
        assert_eq!(gt_row("refined", &[&without]).2, None);
    }

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
        assert_eq!(
            s.unwrap_err().to_string(),
            "SLURM_ARRAY_TASK_ID=4 is not one of 4 tasks from 0; use a contiguous --array \
             range or pass --shard i/n"
        );
        assert_eq!(
            "x/2".parse::<Shard>().unwrap_err().to_string(),
            "expected `i/n` with 0 <= i < n (e.g. `0/4`), got `x/2`"
        );
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
            (
                "name,gaussians,lines\nS1,g,l\ns1,g,l\n",
                "line 3: scene name `s1` differs from `S1` on line 2 only in case",
            ),
            (
                "name,gaussians,lines\nMean,g,l\n",
                "`mean` is the summary's row",
            ),
            ("", "empty"),
            (
                "name,gaussians,lines\nSummary.CSV,g,l\n",
                "line 2: scene name `Summary.CSV` is the name of the summary table",
            ),
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

    /// A byte that is not UTF-8 is reported on its own line.
    #[test]
    fn a_manifest_that_is_not_utf8_names_the_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.csv");
        std::fs::write(&p, b"name,gaussians,lines\na,g\xff.ply,l\n").unwrap();
        let e = Manifest::read(&p).unwrap_err();
        assert!(e.is_input_error());
        assert!(
            e.to_string().contains("m.csv: line 2: a manifest is UTF-8"),
            "{e}"
        );
    }

    #[test]
    fn a_bar_in_a_scene_name_stays_in_its_cell_of_summary_md() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.csv");
        std::fs::write(&p, "name,gaussians,lines\na|b,g,l\n").unwrap();
        let m = Manifest::read(&p).unwrap();
        let md = summarize(&m, dir.path()).to_markdown();
        assert!(md.contains("| a\\|b | pending | | | | | | |\n"), "{md}");
    }

    #[test]
    fn improvement_is_positive_when_better() {
        assert_eq!(improvement(Some(4.0), Some(3.0), true), Some(25.0));
        assert_eq!(improvement(Some(4.0), Some(5.0), false), Some(25.0));
        assert_eq!(improvement(Some(0.0), Some(5.0), false), None);
        assert_eq!(improvement(None, Some(5.0), false), None);
    }
}
