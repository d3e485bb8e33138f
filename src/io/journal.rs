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
//! it (another host's journal, whose lock may not be visible here, is left until it is
//! [`super::STALE_AGE`] old: a commit takes milliseconds). So once every folder of the set
//! has been looked at by a later run, the set is the old one (killed before the commit
//! point) or the new one (after it).
//!
//! A journal is obeyed only when it names nothing but its own set: every journal of the
//! set carries the name of the run that wrote it (`.linegs-<host>-<pid>-XXXXXX.commit`,
//! [`super::litter`]), lists itself, and each rename is of a temporary file that the same
//! run made onto a file that is not a temporary name, in the folder of one of the set's
//! journals. Anything else (a stale temporary file of another run, a target in another
//! folder) is refused with a warning and the journal left alone, so it never blocks a run.

use std::fs::File;
use std::io::{Read, Write};
use std::path::{Path, PathBuf};

use tempfile::TempPath;

use super::error::Error;
use super::litter::{
    is_temp_name, made_elsewhere, old, ours, parse_temp_name, temp_prefix, try_lock, Maker,
    JOURNAL_EXT,
};

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
    if !s.len().is_multiple_of(2) {
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
        Some(plan)
    }

    /// Why the journal at `path`, written by `maker`, names more than its own set (see
    /// the module comment), or `None` when it does not.
    fn refusal(&self, path: &Path, maker: Maker<'_>) -> Option<String> {
        let name_of = |p: &Path| p.file_name().and_then(|n| n.to_str()).map(str::to_owned);
        let mine = |p: &Path| {
            name_of(p)
                .and_then(|n| parse_temp_name(&n).map(|(m, _)| m.map(|(h, i)| (h.to_owned(), i))))
                .is_some_and(|m| m == maker.map(|(h, i)| (h.to_owned(), i)))
        };
        if maker.is_none() {
            return Some(
                "an earlier version wrote it without naming its run, so its files cannot be \
                 told from other runs'"
                    .into(),
            );
        }
        let me = std::fs::canonicalize(path.parent()?)
            .ok()
            .zip(path.file_name())
            .map(|(d, n)| d.join(n));
        if !self.journals.iter().any(|j| Some(j) == me.as_ref()) {
            return Some("it does not list itself among the set's journals".into());
        }
        let folders: Vec<&Path> = self.journals.iter().filter_map(|j| j.parent()).collect();
        for j in &self.journals {
            let ok = j.is_absolute()
                && name_of(j).is_some_and(|n| is_temp_name(&n, Some(JOURNAL_EXT)))
                && mine(j);
            if !ok {
                return Some(format!(
                    "it names `{}`, not a journal of the same run",
                    j.display()
                ));
            }
        }
        for (temp, target) in &self.renames {
            let target_ok = name_of(target)
                .is_some_and(|n| !n.is_empty() && n != "." && n != ".." && !is_temp_name(&n, None));
            if !target_ok {
                return Some(format!(
                    "it would rename onto `{}`, a temporary name",
                    target.display()
                ));
            }
            if temp.parent() != target.parent()
                || !target.parent().is_some_and(|d| folders.contains(&d))
            {
                return Some(format!(
                    "it would write `{}`, outside the folders of its set",
                    target.display()
                ));
            }
            let temp_ok = name_of(temp)
                .is_some_and(|n| is_temp_name(&n, None) && !is_temp_name(&n, Some(JOURNAL_EXT)))
                && mine(temp);
            if !temp_ok {
                return Some(format!(
                    "it would rename `{}`, which is not a temporary file of the run that wrote it",
                    temp.display()
                ));
            }
        }
        None
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
            .prefix(&temp_prefix())
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
        // Reported under an output of the set in that folder: the journal's own name is a
        // temporary one, which means nothing to the user.
        let shown = plan
            .renames
            .iter()
            .map(|(_, target)| target)
            .find(|target| target.parent() == name.parent())
            .unwrap_or(&staged[0].target)
            .clone();
        let io = |e| Error::io(&shown, "write the journal of the output set beside", e);
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
/// and returns how many. A journal that names more than its own set is refused with a
/// warning on the standard error and left alone.
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
        let Some(name) = j.file_name().and_then(|n| n.to_str()) else {
            continue;
        };
        let Some((maker, _)) = parse_temp_name(name) else {
            continue;
        };
        let Ok(mut file) = File::open(&j) else {
            continue; // finished meanwhile
        };
        let Ok(meta) = file.metadata() else {
            continue;
        };
        if !(meta.is_file() && ours(&meta)) {
            continue;
        }
        if made_elsewhere(maker) && !old(&meta) {
            continue; // perhaps a live run on another host, whose lock is not seen here
        }
        if !matches!(try_lock(&file), Ok(true)) {
            continue; // a live run is committing it
        }
        // Read through the locked file (Windows' locks keep other handles out).
        let mut text = String::new();
        let plan = match file
            .read_to_string(&mut text)
            .ok()
            .and_then(|_| Plan::parse(&text))
        {
            Some(p) => p,
            None => {
                refuse(&j, "it cannot be read as a journal");
                continue;
            }
        };
        if let Some(why) = plan.refusal(&j, maker) {
            refuse(&j, &why);
            continue;
        }
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

/// The warning for a journal that is not obeyed, once per journal and process.
fn refuse(journal: &Path, why: &str) {
    static SAID: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());
    let mut said = SAID.lock().unwrap_or_else(|p| p.into_inner());
    if said.iter().any(|p| p == journal) {
        return;
    }
    said.push(journal.to_path_buf());
    eprintln!(
        "warning: {}: this journal of an unfinished output set is not followed ({why}); \
         it is left alone, remove it if its set's files are not needed",
        journal.display()
    );
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::litter::host;

    fn write_journal(dir: &Path, name: &str, renames: &[(PathBuf, PathBuf)]) -> PathBuf {
        let d = std::fs::canonicalize(dir).unwrap();
        let j = d.join(name);
        let plan = Plan {
            renames: renames.to_vec(),
            journals: vec![j.clone()],
        };
        std::fs::write(&j, plan.text()).unwrap();
        j
    }

    /// A journal is followed only for its own set: a stale temporary file of another run
    /// over a user's file, a target outside its folders, a journal of an earlier version
    /// that does not name its run are refused, left alone, and block nothing.
    #[test]
    fn a_journal_that_names_more_than_its_own_set_is_refused_and_left_alone() {
        let d = tempfile::tempdir().unwrap();
        let dir = std::fs::canonicalize(d.path()).unwrap();
        let other = tempfile::tempdir().unwrap();
        let h = host();
        let mine = dir.join("mine.obj");
        let put = |p: &Path, text: &str| std::fs::write(p, text).unwrap();
        put(&mine, "the user's");
        // Another run's (pid 2) stale temporary file, named by a journal of pid 1.
        let stale = dir.join(format!(".linegs-{h}-2-Stale1.obj"));
        put(&stale, "stale");
        let j1 = write_journal(
            &dir,
            &format!(".linegs-{h}-1-Jour01.commit"),
            &[(stale.clone(), mine.clone())],
        );
        // An earlier version's journal: nothing tells its run's files from others'.
        let old_temp = dir.join(".linegs-Stale2.obj");
        put(&old_temp, "stale");
        let j2 = write_journal(
            &dir,
            ".linegs-Jour02.commit",
            &[(old_temp.clone(), mine.clone())],
        );
        // A target in a folder that holds no journal of the set.
        let far = std::fs::canonicalize(other.path()).unwrap();
        let far_temp = far.join(format!(".linegs-{h}-3-Far001.obj"));
        put(&far_temp, "far");
        let j3 = write_journal(
            &dir,
            &format!(".linegs-{h}-3-Jour03.commit"),
            &[(far_temp.clone(), far.join("x.obj"))],
        );
        assert_eq!(recover(&dir).unwrap(), 0);
        assert_eq!(std::fs::read_to_string(&mine).unwrap(), "the user's");
        for p in [&stale, &old_temp, &far_temp, &j1, &j2, &j3] {
            assert!(p.exists(), "{}", p.display());
        }
        assert!(!far.join("x.obj").exists());
        // Its own set's temporary file is renamed, and the journal removed.
        let own = dir.join(format!(".linegs-{h}-4-Own001.obj"));
        put(&own, "new");
        let j4 = write_journal(
            &dir,
            &format!(".linegs-{h}-4-Jour04.commit"),
            &[(own.clone(), dir.join("set.obj"))],
        );
        assert_eq!(recover(&dir).unwrap(), 1);
        assert_eq!(std::fs::read_to_string(dir.join("set.obj")).unwrap(), "new");
        assert!(!own.exists() && !j4.exists());
    }

    /// Another host's journal may be live there (its lock unseen here): left alone until
    /// it is old.
    #[test]
    fn another_hosts_journal_waits_until_it_is_old() {
        let d = tempfile::tempdir().unwrap();
        let dir = std::fs::canonicalize(d.path()).unwrap();
        let h = if host() == "elsewhere" {
            "yonder"
        } else {
            "elsewhere"
        };
        let temp = dir.join(format!(".linegs-{h}-9-Tmp001.obj"));
        std::fs::write(&temp, "new").unwrap();
        let j = write_journal(
            &dir,
            &format!(".linegs-{h}-9-Jour01.commit"),
            &[(temp.clone(), dir.join("a.obj"))],
        );
        assert_eq!(recover(&dir).unwrap(), 0);
        assert!(temp.exists() && j.exists());
        let old = std::time::SystemTime::now() - crate::io::STALE_AGE * 2;
        File::options()
            .write(true)
            .open(&j)
            .unwrap()
            .set_modified(old)
            .unwrap();
        assert_eq!(recover(&dir).unwrap(), 1);
        assert_eq!(std::fs::read_to_string(dir.join("a.obj")).unwrap(), "new");
    }
}
