//! Committing the outputs of one run as one set.
//!
//! Renaming is atomic for one file, not for several, so a set of outputs (`-o X.obj
//! --report X.json ...`) is committed in three steps, each of which a kill can interrupt:
//!
//! 1. Every output is complete in its temporary file beside its target (already true when
//!    [`commit`] is called). A kill here leaves the old set; the temporary files are
//!    litter for the next run ([`super::litter`]).
//! 2. A journal, `.linegs-XXXXXX.commit`, is written in every folder of the set, naming
//!    each temporary file and its target (and every copy of the journal); it becomes
//!    visible under that name only once complete and on disk. The first journal to appear
//!    is the commit point: from then on the set is the new one.
//! 3. The temporary files are renamed onto their targets, then the journals removed.
//!
//! A kill during step 3 leaves some targets new, some old, and the journals. Before it
//! does anything else, the next run that reads or writes in one of those folders finishes
//! the renames ([`recover`]); a journal still locked belongs to a live run and is left to
//! it. So once every folder of the set has been looked at by a later run, the set is the
//! old one (killed before the commit point) or the new one (after it).

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};

use tempfile::TempPath;

use super::error::Error;
use super::litter::{is_temp_name, try_lock, TEMP_PREFIX};

/// Extension of a journal.
pub(crate) const JOURNAL_EXT: &str = "commit";

const HEADER: &str = "linegs-gpu output set 1";

/// One output ready to be renamed into place: its target, its complete temporary file, and
/// the open file that holds the temporary file's lock (see [`super::litter`]).
pub(crate) struct Staged {
    pub target: PathBuf,
    pub temp: TempPath,
    pub lock: Option<File>,
}

/// The folder a path is written in (`.` for a bare name), as an absolute path.
fn absolute_folder(path: &Path) -> Result<PathBuf, Error> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::canonicalize(dir).map_err(|e| Error::io(path, "find the folder of", e))
}

/// A path as one hexadecimal word (any bytes, no separator can appear in it).
fn hex(p: &Path) -> String {
    #[cfg(unix)]
    let bytes = {
        use std::os::unix::ffi::OsStrExt;
        p.as_os_str().as_bytes().to_vec()
    };
    #[cfg(not(unix))]
    let bytes = p.to_string_lossy().as_bytes().to_vec();
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn unhex(s: &str) -> Option<PathBuf> {
    if s.len() % 2 != 0 {
        return None;
    }
    let bytes = (0..s.len())
        .step_by(2)
        .map(|k| u8::from_str_radix(s.get(k..k + 2)?, 16).ok())
        .collect::<Option<Vec<u8>>>()?;
    #[cfg(unix)]
    {
        use std::os::unix::ffi::OsStringExt;
        Some(PathBuf::from(std::ffi::OsString::from_vec(bytes)))
    }
    #[cfg(not(unix))]
    {
        String::from_utf8(bytes).ok().map(PathBuf::from)
    }
}

/// What a journal holds: `(temporary file, target)` pairs and the journals of the set.
struct Plan {
    renames: Vec<(PathBuf, PathBuf)>,
    journals: Vec<PathBuf>,
}

impl Plan {
    fn text(&self) -> String {
        let mut t = format!("{HEADER}\n");
        for (temp, target) in &self.renames {
            t.push_str(&format!("rename {} {}\n", hex(temp), hex(target)));
        }
        for j in &self.journals {
            t.push_str(&format!("journal {}\n", hex(j)));
        }
        t
    }

    fn parse(text: &str) -> Option<Plan> {
        let mut lines = text.lines();
        if lines.next()? != HEADER {
            return None;
        }
        let mut plan = Plan {
            renames: Vec::new(),
            journals: Vec::new(),
        };
        for line in lines {
            let w: Vec<&str> = line.split(' ').collect();
            match w[..] {
                ["rename", a, b] => plan.renames.push((unhex(a)?, unhex(b)?)),
                ["journal", a] => plan.journals.push(unhex(a)?),
                _ => return None,
            }
        }
        // Only the writers' temporary files are ever renamed, each within its folder.
        let ok = plan.renames.iter().all(|(a, b)| {
            a.parent() == b.parent()
                && a.file_name()
                    .and_then(|n| n.to_str())
                    .is_some_and(|n| is_temp_name(n, None))
        }) && plan.journals.iter().all(|j| {
            j.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| is_temp_name(n, Some(JOURNAL_EXT)))
        });
        ok.then_some(plan)
    }
}

/// Where [`commit_with`] stops as if killed (tests only): before the journals, or after
/// this many renames.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) enum Stop {
    Never,
    #[cfg(test)]
    BeforeJournal,
    #[cfg(test)]
    AfterRenames(usize),
}

/// Renames every staged output onto its target as one set (see the module comment).
pub(crate) fn commit(staged: Vec<Staged>) -> Result<(), Error> {
    commit_with(staged, Stop::Never)
}

/// A kill as a test makes one: the temporary files and journals stay, the locks go.
#[cfg(test)]
fn killed(staged: Vec<Staged>, journals: Vec<File>) -> Error {
    for s in staged {
        let _ = s.temp.keep();
    }
    drop(journals);
    Error::Output {
        path: PathBuf::new(),
        msg: "stopped as if killed".into(),
    }
}

pub(crate) fn commit_with(staged: Vec<Staged>, stop: Stop) -> Result<(), Error> {
    #[cfg(test)]
    if stop == Stop::BeforeJournal {
        return Err(killed(staged, Vec::new()));
    }
    #[cfg(not(test))]
    let _ = stop;
    if staged.len() <= 1 {
        for s in staged {
            s.temp
                .persist(&s.target)
                .map_err(|e| Error::io(&s.target, "rename the finished file onto", e.error))?;
        }
        return Ok(());
    }
    let mut renames = Vec::new();
    let mut folders: Vec<PathBuf> = Vec::new();
    for s in &staged {
        let dir = absolute_folder(&s.target)?;
        let name = |p: &Path| p.file_name().map(PathBuf::from).unwrap_or_default();
        renames.push((dir.join(name(&s.temp)), dir.join(name(&s.target))));
        if !folders.contains(&dir) {
            folders.push(dir);
        }
    }
    // Step 2: the journals, complete and locked before any has its final name.
    let mut temps = Vec::new();
    for dir in &folders {
        let t = tempfile::Builder::new()
            .prefix(TEMP_PREFIX)
            .suffix(".tmp")
            .tempfile_in(dir)
            .map_err(|e| Error::io(&staged[0].target, "create a temporary file beside", e))?;
        let name = t.path().with_extension(JOURNAL_EXT);
        temps.push((t, name));
    }
    let plan = Plan {
        renames,
        journals: temps.iter().map(|(_, j)| j.clone()).collect(),
    };
    let text = plan.text();
    let mut journals = Vec::new();
    for (mut t, name) in temps {
        let io = |e| Error::io(&name, "write the journal of the output set", e);
        let _ = try_lock(t.as_file());
        t.write_all(text.as_bytes()).map_err(io)?;
        t.as_file().sync_all().map_err(io)?;
        let file = t.persist_noclobber(&name).map_err(|e| io(e.error))?;
        journals.push(file);
    }
    #[cfg(unix)]
    for dir in &folders {
        // The journal's name on disk before any rename that needs it.
        if let Ok(d) = File::open(dir) {
            let _ = d.sync_all();
        }
    }
    // Step 3.
    let mut rest = staged.into_iter().enumerate();
    while let Some((done, s)) = rest.next() {
        #[cfg(test)]
        if stop == Stop::AfterRenames(done) {
            let mut left = vec![s];
            left.extend(rest.map(|(_, s)| s));
            return Err(killed(left, journals));
        }
        #[cfg(not(test))]
        let _ = done;
        let target = s.target.clone();
        if let Err(e) = s.temp.persist(&target) {
            // The set is committed: what is left is renamed by the next run here.
            let _ = e.path.keep();
            for (_, s) in rest {
                let _ = s.temp.keep();
            }
            return Err(Error::io(
                &target,
                "rename the finished file onto (the run's other outputs are complete; the \
                 next run that writes in this folder puts them in place)",
                e.error,
            ));
        }
        drop(s.lock);
    }
    // Removed while still locked, so no other run takes them for a killed run's.
    for j in &plan.journals {
        let _ = std::fs::remove_file(j);
    }
    drop(journals);
    Ok(())
}

/// Finishes the output sets that killed runs committed in `dir` (see the module comment)
/// and returns how many.
pub fn recover(dir: &Path) -> Result<usize, Error> {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return Ok(0);
    };
    let journals: Vec<PathBuf> = rd
        .flatten()
        .filter(|d| {
            d.file_name()
                .to_str()
                .is_some_and(|n| is_temp_name(n, Some(JOURNAL_EXT)))
        })
        .map(|d| d.path())
        .collect();
    let mut n = 0;
    for j in journals {
        let Ok(file) = File::open(&j) else {
            continue; // finished meanwhile
        };
        if !file.metadata().is_ok_and(|m| m.is_file() && owned(&m)) {
            continue;
        }
        if !matches!(try_lock(&file), Ok(true)) {
            continue; // a live run is committing it
        }
        let bad = || Error::Output {
            path: j.clone(),
            msg: "cannot read this journal of an unfinished output set; remove it if the \
                  set's files are not needed"
                .into(),
        };
        let text = std::fs::read_to_string(&j).map_err(|_| bad())?;
        let plan = Plan::parse(&text).ok_or_else(bad)?;
        for (temp, target) in &plan.renames {
            // A temporary file already gone was renamed (by the run, or by another run
            // finishing the set from its journal in another folder).
            match std::fs::rename(temp, target) {
                Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
                    return Err(Error::io(target, "finish a killed run's output set at", e))
                }
                _ => {}
            }
        }
        for other in &plan.journals {
            let _ = std::fs::remove_file(other);
        }
        let _ = std::fs::remove_file(&j);
        n += 1;
    }
    Ok(n)
}

/// The user's own file (a journal written by someone else is not obeyed).
fn owned(m: &std::fs::Metadata) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        // SAFETY: getuid has no preconditions.
        m.uid() == unsafe { libc::getuid() }
    }
    #[cfg(not(unix))]
    {
        let _ = m;
        true
    }
}
