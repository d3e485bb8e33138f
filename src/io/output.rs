//! All the outputs of one run as one transaction: every path is checked before any work
//! (extension, folder, not an input, not another output), each file is written under a
//! temporary name beside its target, and only when all of them are written are they
//! renamed into place, as one set ([`super::journal`]). A run that fails at any point
//! leaves every earlier file as it was. Checking the outputs also finishes the sets that
//! killed runs committed in the folders involved and removes their stale temporary files
//! ([`super::litter`]).
//!
//! ```no_run
//! # use linegs_gpu::io::{self, OutputSet, LINE_OUTPUTS};
//! # use std::path::Path;
//! # fn main() -> Result<(), io::Error> {
//! let mut outs = OutputSet::new();
//! outs.input(Path::new("point_cloud.ply"))
//!     .input(Path::new("lines.obj"))
//!     .output("-o", Path::new("refined.obj"), &LINE_OUTPUTS)
//!     .output("--report", Path::new("report.json"), &["json"]);
//! outs.check()?; // before any work
//! // ... the work ...
//! outs.write(Path::new("refined.obj"), |p| io::write_lines(p, &[]))?;
//! outs.write(Path::new("report.json"), |p| io::write_bytes_atomic(p, b"{}"))?;
//! outs.commit()?; // all or nothing
//! # Ok(()) }
//! ```

use std::path::{Path, PathBuf};

use super::error::Error;
use super::journal::{self, Staged};
use super::litter;

/// The outputs of one run; see the module comment.
#[derive(Default)]
pub struct OutputSet {
    inputs: Vec<PathBuf>,
    outputs: Vec<(&'static str, PathBuf, Vec<String>)>,
    staged: Vec<Staged>,
}

/// What makes two paths the same file: the canonical path (symlinks, `..`) and, for a
/// file that exists, its device and inode (hard links).
#[derive(Debug, PartialEq)]
struct FileId {
    canonical: Option<PathBuf>,
    inode: Option<(u64, u64)>,
}

impl FileId {
    fn of(path: &Path) -> FileId {
        let canonical = std::fs::canonicalize(path).ok().or_else(|| {
            let name = path.file_name()?;
            Some(std::fs::canonicalize(folder(path)).ok()?.join(name))
        });
        #[cfg(unix)]
        let inode = {
            use std::os::unix::fs::MetadataExt;
            std::fs::metadata(path).ok().map(|m| (m.dev(), m.ino()))
        };
        #[cfg(not(unix))]
        let inode = None;
        FileId { canonical, inode }
    }

    fn same(&self, other: &FileId) -> bool {
        (self.canonical.is_some() && self.canonical == other.canonical)
            || (self.inode.is_some() && self.inode == other.inode)
    }
}

/// The folder a path is written in (`.` for a bare name).
fn folder(path: &Path) -> &Path {
    match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    }
}

/// True when `a` and `b` name the same file (another spelling, a symlink or a hard link).
pub fn same_file(a: &Path, b: &Path) -> bool {
    FileId::of(a).same(&FileId::of(b))
}

/// Many files a run reads, to look a path up among them in constant time: by device and
/// inode for a file that exists (Unix; that covers other spellings, symlinks and hard
/// links with one `stat`), by canonical path otherwise. For runs that read too many files
/// for [`OutputSet`]'s pairwise checks (`batch`).
#[derive(Default)]
pub struct PathIndex {
    inodes: std::collections::HashMap<(u64, u64), PathBuf>,
    paths: std::collections::HashMap<PathBuf, PathBuf>,
}

impl PathIndex {
    pub fn new() -> Self {
        Self::default()
    }

    /// The keys of `path`: its (device, inode) when it exists on Unix, else its canonical
    /// path (that of its folder and its name, for a file that does not exist).
    fn key(path: &Path) -> (Option<(u64, u64)>, Option<PathBuf>) {
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            if let Ok(m) = std::fs::metadata(path) {
                return (Some((m.dev(), m.ino())), None);
            }
        }
        (None, FileId::of(path).canonical)
    }

    /// Adds a file that is read.
    pub fn add(&mut self, path: &Path) {
        match Self::key(path) {
            (Some(i), _) => {
                self.inodes.entry(i).or_insert_with(|| path.to_path_buf());
            }
            (None, Some(c)) => {
                self.paths.entry(c).or_insert_with(|| path.to_path_buf());
            }
            _ => {}
        }
    }

    /// The added path that names the same file as `path`, if any.
    pub fn find(&self, path: &Path) -> Option<&Path> {
        match Self::key(path) {
            (Some(i), _) => self.inodes.get(&i),
            (None, Some(c)) => self.paths.get(&c),
            _ => None,
        }
        .map(PathBuf::as_path)
    }
}

/// The suffix of a temporary file staged for `path`: its extension (so format-by-extension
/// writers work), only when short, so that the temporary name (`.linegs-<host>-<pid>-` and
/// six random characters before it) fits in 255 bytes for every valid final name.
pub(crate) fn temp_suffix(path: &Path) -> String {
    match path.extension().and_then(|e| e.to_str()) {
        Some(e) if !e.is_empty() && e.len() <= 16 => format!(".{e}"),
        _ => ".tmp".to_string(),
    }
}

fn refuse(path: &Path, msg: impl Into<String>) -> Error {
    Error::Output {
        path: path.to_path_buf(),
        msg: msg.into(),
    }
}

impl OutputSet {
    pub fn new() -> Self {
        Self::default()
    }

    /// A file the run reads, which no output may replace.
    pub fn input(&mut self, path: &Path) -> &mut Self {
        self.inputs.push(path.to_path_buf());
        self
    }

    /// A file the run will write, named in messages by its option (`-o`, `--report`), with
    /// the extensions it may have (none: any).
    pub fn output(&mut self, option: &'static str, path: &Path, extensions: &[&str]) -> &mut Self {
        self.outputs.push((
            option,
            path.to_path_buf(),
            extensions.iter().map(|e| e.to_string()).collect(),
        ));
        self
    }

    /// Checks every output: its extension, that its folder exists and takes new files,
    /// that it is not a folder or a device, and that it is neither an input nor another
    /// output. Call it before any work.
    pub fn check(&self) -> Result<(), Error> {
        // What killed runs left: their committed sets finished, then their litter removed.
        let mut folders: Vec<PathBuf> = Vec::new();
        for p in self.outputs.iter().map(|(_, p, _)| p) {
            let dir = std::fs::canonicalize(folder(p)).unwrap_or_else(|_| folder(p).into());
            if !folders.contains(&dir) {
                journal::recover(&dir)?;
                litter::clean_stale_temps(&dir);
                folders.push(dir);
            }
        }
        for p in &self.inputs {
            if let Ok(dir) = std::fs::canonicalize(folder(p)) {
                if !folders.contains(&dir) {
                    // An input's folder may be read-only: what cannot be finished stays.
                    let _ = journal::recover(&dir);
                    folders.push(dir);
                }
            }
        }
        let inputs: Vec<(PathBuf, FileId)> = self
            .inputs
            .iter()
            .map(|p| (p.clone(), FileId::of(p)))
            .collect();
        let mut seen: Vec<(&str, &Path, FileId)> = Vec::new();
        for (option, path, exts) in &self.outputs {
            let ext = path
                .extension()
                .map(|e| e.to_string_lossy().to_ascii_lowercase())
                .unwrap_or_default();
            if !exts.is_empty() && !exts.contains(&ext) {
                let list: Vec<String> = exts.iter().map(|e| format!(".{e}")).collect();
                let got = if ext.is_empty() {
                    "a name without an extension".to_string()
                } else {
                    format!("`.{ext}`")
                };
                return Err(refuse(
                    path,
                    format!(
                        "{option} cannot be written as {got}; use {}",
                        list.join(", ")
                    ),
                ));
            }
            if let Ok(m) = std::fs::metadata(path) {
                if m.is_dir() {
                    return Err(refuse(path, format!("{option} is a folder, not a file")));
                }
                if !m.is_file() {
                    return Err(refuse(
                        path,
                        format!(
                            "{option} is a device or pipe; outputs are written to regular files"
                        ),
                    ));
                }
            }
            let dir = folder(path);
            match std::fs::metadata(dir) {
                Ok(m) if m.is_dir() => {}
                Ok(_) => {
                    return Err(refuse(
                        path,
                        format!("{option}: `{}` is not a folder", dir.display()),
                    ))
                }
                Err(_) => {
                    return Err(refuse(
                        path,
                        format!(
                            "{option}: the folder `{}` does not exist; create it first",
                            dir.display()
                        ),
                    ))
                }
            }
            // The real test of "writable" (permissions, read-only mounts, ACLs): make a file.
            // (A temporary name with an extension, so a kill's leftover is litter by the rule.)
            if let Err(e) = tempfile::Builder::new()
                .prefix(&litter::temp_prefix())
                .suffix(".probe")
                .tempfile_in(dir)
            {
                let cause = super::error::without_temp_path(e);
                if super::error::is_resource_limit(&cause) {
                    // Out of file descriptors or memory: the limit, not the folder (exit 1).
                    return Err(Error::io(path, "create a temporary file beside", cause));
                }
                return Err(refuse(
                    path,
                    format!(
                        "{option}: cannot create files in the folder `{}`: {cause}",
                        dir.display()
                    ),
                ));
            }
            let id = FileId::of(path);
            if let Some((input, _)) = inputs.iter().find(|(_, i)| i.same(&id)) {
                return Err(refuse(
                    path,
                    format!(
                        "{option} is the input `{}`; writing it would destroy the input",
                        input.display()
                    ),
                ));
            }
            let parent = std::fs::canonicalize(dir).ok();
            if let Some(input) = self
                .inputs
                .iter()
                .find(|i| i.is_dir() && parent.is_some() && std::fs::canonicalize(i).ok() == parent)
            {
                return Err(refuse(
                    path,
                    format!(
                        "{option} is inside the input folder `{}`; writing there would change the input",
                        input.display()
                    ),
                ));
            }
            if let Some((other, p, _)) = seen.iter().find(|(_, _, i)| i.same(&id)) {
                return Err(refuse(
                    path,
                    format!(
                        "{option} is the same file as {other} `{}`; give each output its own name",
                        p.display()
                    ),
                ));
            }
            seen.push((option, path, id));
        }
        Ok(())
    }

    /// Writes one output: `write` is handed a temporary path beside `path` (with the same
    /// extension, so format-by-extension writers work), and errors are reported under
    /// `path`. Nothing replaces `path` until [`OutputSet::commit`].
    pub fn write(
        &mut self,
        path: &Path,
        write: impl FnOnce(&Path) -> Result<(), Error>,
    ) -> Result<(), Error> {
        let staged = tempfile::Builder::new()
            .prefix(&litter::temp_prefix())
            .suffix(&temp_suffix(path))
            .tempfile_in(folder(path))
            .map_err(|e| Error::io(path, "create a temporary file beside", e))?
            .into_temp_path();
        write(&staged).map_err(|e| e.with_path(path))?;
        // Locked until the commit, so no other run takes it for a killed run's litter.
        let lock = std::fs::File::open(&staged).ok();
        if let Some(f) = &lock {
            let _ = litter::try_lock(f);
        }
        self.staged.push(Staged {
            target: path.to_path_buf(),
            temp: staged,
            lock,
        });
        Ok(())
    }

    /// Renames every written output into place, as one set (each a rename within its own
    /// folder; see `io::journal`). Dropping the set without a commit removes the
    /// temporary files and leaves the targets as they were.
    pub fn commit(mut self) -> Result<(), Error> {
        journal::commit(std::mem::take(&mut self.staged))
    }

    /// [`OutputSet::commit`] stopped as a kill would stop it.
    #[cfg(test)]
    pub(crate) fn commit_stopping(mut self, stop: journal::Stop) -> Result<(), Error> {
        journal::commit_with(std::mem::take(&mut self.staged), stop)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    }

    /// Three outputs in two folders, written as `new` over files holding `old`, staged but
    /// not committed.
    fn staged_set(dir: &Path) -> (OutputSet, [PathBuf; 3]) {
        std::fs::create_dir_all(dir.join("sub")).unwrap();
        let files = [
            dir.join("x.obj"),
            dir.join("x.ply"),
            dir.join("sub").join("x.json"),
        ];
        let mut outs = OutputSet::new();
        for f in &files {
            std::fs::write(f, "old").unwrap();
            outs.output("-o", f, &[]);
        }
        outs.check().unwrap();
        for f in &files {
            outs.write(f, |p| super::super::write_bytes_atomic(p, b"new"))
                .unwrap();
        }
        (outs, files)
    }

    fn contents(files: &[PathBuf]) -> Vec<String> {
        files
            .iter()
            .map(|f| std::fs::read_to_string(f).unwrap())
            .collect()
    }

    fn litter(dir: &Path) -> Vec<String> {
        let mut v: Vec<String> = names(dir)
            .into_iter()
            .chain(names(&dir.join("sub")))
            .filter(|n| n.starts_with(".linegs-"))
            .collect();
        v.sort();
        v
    }

    /// A run that only writes in `folder` (a new file there).
    fn next_run(folder: &Path) -> Result<(), Error> {
        let mut outs = OutputSet::new();
        outs.output("-o", &folder.join("other.txt"), &["txt"]);
        outs.check()
    }

    #[test]
    fn a_kill_between_the_renames_leaves_a_set_the_next_run_finishes() {
        for done in 0..3 {
            for next_in in ["", "sub"] {
                let d = tempfile::tempdir().unwrap();
                let (outs, files) = staged_set(d.path());
                outs.commit_stopping(journal::Stop::AfterRenames(done))
                    .unwrap_err();
                // Mixed on disk: the first `done` are new; a journal in each folder.
                let mut want = vec!["old"; 3];
                want[..done].fill("new");
                assert_eq!(contents(&files), want);
                let journals = litter(d.path())
                    .into_iter()
                    .filter(|n| n.ends_with(".commit"))
                    .count();
                assert_eq!(journals, 2);
                // The next run in either folder finishes the whole set.
                next_run(&d.path().join(next_in)).unwrap();
                assert_eq!(
                    contents(&files),
                    ["new"; 3],
                    "done {done}, next in {next_in:?}"
                );
                assert!(litter(d.path()).is_empty(), "{:?}", litter(d.path()));
            }
        }
    }

    #[test]
    fn a_journal_a_live_run_holds_is_left_to_it() {
        let d = tempfile::tempdir().unwrap();
        let (outs, files) = staged_set(d.path());
        outs.commit_stopping(journal::Stop::AfterRenames(1))
            .unwrap_err();
        let j = names(d.path())
            .into_iter()
            .find(|n| n.ends_with(".commit"))
            .unwrap();
        let held = std::fs::File::open(d.path().join(j)).unwrap();
        assert!(super::super::litter::try_lock(&held).unwrap());
        next_run(d.path()).unwrap();
        assert_eq!(contents(&files), ["new", "old", "old"]);
        drop(held);
        next_run(d.path()).unwrap();
        assert_eq!(contents(&files), ["new"; 3]);
    }

    #[test]
    fn a_kill_before_the_commit_point_leaves_the_old_set_and_litter_a_later_run_removes() {
        let d = tempfile::tempdir().unwrap();
        let (outs, files) = staged_set(d.path());
        outs.commit_stopping(journal::Stop::BeforeJournal)
            .unwrap_err();
        assert_eq!(contents(&files), ["old"; 3]);
        let left = litter(d.path());
        assert_eq!(left.len(), 3, "{left:?}");
        // Too fresh to be sure no live run owns them.
        next_run(d.path()).unwrap();
        next_run(&d.path().join("sub")).unwrap();
        assert_eq!(litter(d.path()), left);
        let old = std::time::SystemTime::now() - super::super::STALE_AGE * 2;
        for n in &left {
            let p = [d.path().to_path_buf(), d.path().join("sub")]
                .into_iter()
                .map(|f| f.join(n))
                .find(|p| p.exists())
                .unwrap();
            std::fs::File::options()
                .write(true)
                .open(p)
                .unwrap()
                .set_modified(old)
                .unwrap();
        }
        next_run(d.path()).unwrap();
        next_run(&d.path().join("sub")).unwrap();
        assert!(litter(d.path()).is_empty(), "{:?}", litter(d.path()));
        assert_eq!(contents(&files), ["old"; 3]);
    }

    #[test]
    fn a_failing_last_output_leaves_every_earlier_file_as_it_was() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.txt");
        let b = dir.path().join("b.json");
        std::fs::write(&a, "old a").unwrap();
        std::fs::write(&b, "old b").unwrap();
        let mut outs = OutputSet::new();
        outs.output("-o", &a, &["txt"])
            .output("--report", &b, &["json"]);
        outs.check().unwrap();
        outs.write(&a, |p| super::super::write_bytes_atomic(p, b"new a"))
            .unwrap();
        let e = outs
            .write(&b, |p| {
                Err(Error::Unsupported {
                    path: p.to_path_buf(),
                    msg: "disk full".into(),
                })
            })
            .unwrap_err();
        // Reported under the real name, not the temporary one.
        assert_eq!(e.to_string(), format!("{}: disk full", b.display()));
        drop(outs);
        assert_eq!(std::fs::read_to_string(&a).unwrap(), "old a");
        assert_eq!(std::fs::read_to_string(&b).unwrap(), "old b");
        assert_eq!(names(dir.path()), ["a.txt", "b.json"], "no temporary left");
    }

    #[test]
    fn outputs_land_together_on_commit() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.obj");
        let b = dir.path().join("b.json");
        let mut outs = OutputSet::new();
        outs.output("-o", &a, &["obj"])
            .output("--report", &b, &["json"]);
        outs.check().unwrap();
        outs.write(&a, |p| {
            assert_eq!(p.extension().unwrap(), "obj");
            super::super::write_bytes_atomic(p, b"a")
        })
        .unwrap();
        outs.write(&b, |p| super::super::write_bytes_atomic(p, b"b"))
            .unwrap();
        assert!(
            !a.exists() && !b.exists(),
            "nothing lands before the commit"
        );
        outs.commit().unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), b"a");
        assert_eq!(std::fs::read(&b).unwrap(), b"b");
        assert_eq!(names(dir.path()), ["a.obj", "b.json"]);
    }

    #[test]
    fn collisions_missing_folders_and_extensions_are_found_before_any_work() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("in.ply");
        std::fs::write(&input, "ply").unwrap();
        let check = |outs: &[(&'static str, PathBuf, &[&str])]| {
            let mut set = OutputSet::new();
            set.input(&input);
            for (o, p, e) in outs {
                set.output(o, p, e);
            }
            set.check().map(|_| ()).map_err(|e| e.to_string())
        };
        let e = check(&[("-o", input.clone(), &["ply"])]).unwrap_err();
        assert!(e.contains("-o is the input"), "{e}");
        // Another spelling of the same path, and a hard link, are the same file.
        let dotted = dir.path().join(".").join("in.ply");
        assert!(check(&[("-o", dotted, &["ply"])]).is_err());
        let link = dir.path().join("link.ply");
        std::fs::hard_link(&input, &link).unwrap();
        let e = check(&[("-o", link, &["ply"])]).unwrap_err();
        assert!(e.contains("is the input"), "{e}");
        let o = dir.path().join("o.ply");
        let e = check(&[("-o", o.clone(), &["ply"]), ("--compare-ply", o, &["ply"])]).unwrap_err();
        assert!(e.contains("--compare-ply is the same file as -o"), "{e}");
        let e = check(&[("--report", dir.path().join("no/r.json"), &["json"])]).unwrap_err();
        assert!(
            e.contains("the folder") && e.contains("does not exist"),
            "{e}"
        );
        let e = check(&[("-o", dir.path().join("o.dwg"), &["obj", "ply"])]).unwrap_err();
        assert!(
            e.contains("-o cannot be written as `.dwg`; use .obj, .ply"),
            "{e}"
        );
        let e = check(&[("-o", dir.path().to_path_buf(), &[])]).unwrap_err();
        assert!(e.contains("is a folder"), "{e}");
        assert!(check(&[("-o", dir.path().join("fine.ply"), &["ply"])]).is_ok());
    }
}
