//! What killed runs leave behind, and the one rule for who may remove it.
//!
//! Writers put every output in a temporary file beside its target first, named
//! `.linegs-<host>-<pid>-XXXXXX.<ext>` (the host and process that made it, six random
//! letters or digits), and `main` may make a private runtime folder
//! (`linegs-gpu-runtime-XXXXXX` in the system's temporary folder). A live run holds an
//! exclusive lock (`File::lock`: `flock` on Unix, `LockFileEx` on Windows) on each of them
//! as long as they exist; the system drops the locks of a killed process with it.
//!
//! The ownership rule, used by every command (`refine`, `batch`, `convert`, ...): a
//! temporary file is removed or renamed only by the run that holds its lock, or, once its
//! lock is free, when it belongs to this user, is older than [`STALE_AGE`] (the age covers
//! the instants between creating a file and locking it) and was made on this host. A lock
//! held on another host may not be seen here (NFS), so another host's temporary files are
//! never removed; a run on that host removes them. Names of earlier versions
//! (`.linegs-XXXXXX.<ext>`, no host) follow the same rule without the host test.

use std::fs::File;
use std::path::Path;
use std::sync::OnceLock;
use std::time::{Duration, SystemTime};

/// How old unlocked litter must be before a run removes it.
pub const STALE_AGE: Duration = Duration::from_secs(60);

/// Prefix of every temporary file of the writers.
pub(crate) const TEMP_PREFIX: &str = ".linegs-";

/// Extension of an output set's journal (`journal.rs`): a temporary file like the others,
/// that the set's commit renames its outputs by.
pub(crate) const JOURNAL_EXT: &str = "commit";

/// Prefix of `main`'s private runtime folders.
pub const RUNTIME_PREFIX: &str = "linegs-gpu-runtime-";

/// Longest host name kept in a temporary name.
const HOST_MAX: usize = 32;

/// An exclusive lock on `file` without waiting (`File::try_lock`): `Ok(false)` when
/// another process (or another open file of this one) holds it.
pub fn try_lock(file: &File) -> std::io::Result<bool> {
    match file.try_lock() {
        Ok(()) => Ok(true),
        Err(std::fs::TryLockError::WouldBlock) => Ok(false),
        Err(std::fs::TryLockError::Error(e)) => Err(e),
    }
}

/// This host's name as temporary names carry it: the short name (up to the first `.`),
/// letters, digits and `-` (anything else becomes `-`), at most [`HOST_MAX`] bytes.
pub(crate) fn host() -> &'static str {
    static HOST: OnceLock<String> = OnceLock::new();
    HOST.get_or_init(|| sanitize_host(&raw_host()))
}

fn raw_host() -> String {
    #[cfg(unix)]
    {
        let mut buf = [0u8; 256];
        // SAFETY: gethostname writes at most `len` bytes into the buffer it is given.
        if unsafe { libc::gethostname(buf.as_mut_ptr().cast(), buf.len()) } == 0 {
            let end = buf.iter().position(|&b| b == 0).unwrap_or(buf.len());
            return String::from_utf8_lossy(&buf[..end]).into_owned();
        }
        String::new()
    }
    // Elsewhere the library asks no system for its name (and reads no environment
    // variable): every host is `host`, so the age rule alone decides there.
    #[cfg(not(unix))]
    {
        String::new()
    }
}

fn sanitize_host(raw: &str) -> String {
    let short = raw.split('.').next().unwrap_or("");
    let mut h: String = short
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '-' })
        .take(HOST_MAX)
        .collect();
    if h.is_empty() {
        h.push_str("host");
    }
    h
}

/// The prefix of this run's temporary names: `.linegs-<host>-<pid>-` (the random part and
/// the extension follow).
pub fn temp_prefix() -> String {
    format!("{TEMP_PREFIX}{}-{}-", host(), std::process::id())
}

/// Who made a temporary file, as its name says: `Some((host, pid))`, or `None` for the
/// names of earlier versions that say nothing.
pub(crate) type Maker<'a> = Option<(&'a str, u32)>;

/// The parts of a writer's temporary name: who made it and its extension.
pub(crate) fn parse_temp_name(name: &str) -> Option<(Maker<'_>, &str)> {
    let rest = name.strip_prefix(TEMP_PREFIX)?;
    // The folder probe of earlier versions: `.linegs-XXXXXX`, no extension.
    if rest.len() == 6 && rest.bytes().all(|b| b.is_ascii_alphanumeric()) {
        return Some((None, ""));
    }
    let (stem, ext) = rest.split_once('.')?;
    if !(1..=16).contains(&ext.len()) || ext.contains('.') {
        return None;
    }
    let random = |s: &str| s.len() == 6 && s.bytes().all(|b| b.is_ascii_alphanumeric());
    let mut parts = stem.rsplitn(3, '-');
    let (rand, pid, host) = (parts.next()?, parts.next(), parts.next());
    if !random(rand) {
        return None;
    }
    match (pid, host) {
        (None, _) => Some((None, ext)),
        (Some(pid), Some(host))
            if (1..=HOST_MAX).contains(&host.len())
                && host.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'-')
                && (1..=10).contains(&pid.len())
                && pid.bytes().all(|b| b.is_ascii_digit()) =>
        {
            Some((Some((host, pid.parse().ok()?)), ext))
        }
        _ => None,
    }
}

/// A writer's temporary name (see [`parse_temp_name`]), or with `ext` given, one with
/// that extension only.
pub(crate) fn is_temp_name(name: &str, ext: Option<&str>) -> bool {
    parse_temp_name(name).is_some_and(|(_, e)| ext.is_none_or(|x| x == e))
}

/// Made on another host (its lock may not be visible here).
pub(crate) fn made_elsewhere(maker: Maker<'_>) -> bool {
    maker.is_some_and(|(h, _)| h != host())
}

/// This user's.
pub(crate) fn ours(meta: &std::fs::Metadata) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        // SAFETY: getuid has no preconditions.
        meta.uid() == unsafe { libc::getuid() }
    }
    #[cfg(not(unix))]
    {
        let _ = meta;
        true
    }
}

/// Last changed [`STALE_AGE`] ago or earlier.
pub(crate) fn old(meta: &std::fs::Metadata) -> bool {
    meta.modified()
        .ok()
        .and_then(|m| SystemTime::now().duration_since(m).ok())
        .is_some_and(|age| age >= STALE_AGE)
}

/// This user's, and last changed [`STALE_AGE`] ago or earlier.
fn old_and_ours(meta: &std::fs::Metadata) -> bool {
    ours(meta) && old(meta)
}

/// Removes `path` if no live run holds it: it is locked for the removal, so a run that
/// opens it meanwhile finds it gone.
fn remove_if_unlocked(path: &Path, dir: bool) -> bool {
    let Ok(f) = File::open(path) else {
        return false;
    };
    if !matches!(try_lock(&f), Ok(true)) {
        return false;
    }
    let gone = if dir {
        std::fs::remove_dir_all(path)
    } else {
        std::fs::remove_file(path)
    };
    gone.is_ok()
}

/// Removes the stale temporary files of killed runs in `dir` by the rule of the module
/// comment, and returns how many. A folder that still holds the journal of an unfinished
/// output set (see `io::journal`) is left alone: its temporary files are that set's
/// outputs.
pub fn clean_stale_temps(dir: &Path) -> usize {
    let Ok(rd) = std::fs::read_dir(dir) else {
        return 0;
    };
    let names: Vec<(String, std::path::PathBuf)> = rd
        .flatten()
        .filter_map(|d| Some((d.file_name().into_string().ok()?, d.path())))
        .filter(|(n, _)| is_temp_name(n, None))
        .collect();
    if names
        .iter()
        .any(|(n, _)| is_temp_name(n, Some(JOURNAL_EXT)))
    {
        return 0;
    }
    names
        .iter()
        .filter(|(n, p)| {
            parse_temp_name(n).is_some_and(|(maker, _)| !made_elsewhere(maker))
                && std::fs::symlink_metadata(p).is_ok_and(|m| m.is_file() && old_and_ours(&m))
                && remove_if_unlocked(p, false)
        })
        .count()
}

/// Removes the runtime folders that killed runs of `main` left in the system's temporary
/// folder and returns how many.
pub fn clean_stale_runtime_dirs() -> usize {
    clean_stale_runtime_dirs_in(&std::env::temp_dir())
}

/// [`clean_stale_runtime_dirs`] in `base` (the folder the private runtime folder is made
/// in when the temporary folder is unusable).
pub fn clean_stale_runtime_dirs_in(base: &Path) -> usize {
    let Ok(rd) = std::fs::read_dir(base) else {
        return 0;
    };
    rd.flatten()
        .filter(|d| {
            d.file_name()
                .to_str()
                .is_some_and(|n| n.starts_with(RUNTIME_PREFIX))
        })
        .filter(|d| {
            let p = d.path();
            std::fs::symlink_metadata(&p).is_ok_and(|m| m.is_dir() && old_and_ours(&m))
                && remove_if_unlocked(&p, true)
        })
        .count()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Moves a file's time back past [`STALE_AGE`], as if a run had been killed long ago.
    pub(crate) fn age(path: &Path) {
        let old = SystemTime::now() - STALE_AGE - Duration::from_secs(5);
        File::options()
            .write(true)
            .open(path)
            .or_else(|_| File::open(path))
            .unwrap()
            .set_modified(old)
            .unwrap();
    }

    #[test]
    fn temp_names_are_the_writers_own() {
        for n in [
            ".linegs-Ab3xY9.obj",
            ".linegs-000000.tmp",
            ".linegs-aaaaaa.commit",
            ".linegs-node-17-4242-Ab3xY9.obj",
            ".linegs-n1-1-Ab3xY9.probe",
            ".linegs-Ab3xY9",
        ] {
            assert!(is_temp_name(n, None), "{n}");
        }
        for n in [
            ".linegs-batch.lock",
            ".linegs-Ab3xY",
            ".linegs-Ab3xY.obj",
            ".linegs-Ab3xY9.tar.gz",
            ".linegs-Ab3-Y9.obj",
            "linegs-Ab3xY9.obj",
            ".linegs-Ab3xY9.abcdefghijklmnopq",
            ".linegs-node-x42-Ab3xY9.obj",
            ".linegs--42-Ab3xY9.obj",
            ".linegs-no_de-42-Ab3xY9.obj",
            "refined.obj",
        ] {
            assert!(!is_temp_name(n, None), "{n}");
        }
        assert!(is_temp_name(".linegs-Ab3xY9.json", Some("json")));
        assert!(!is_temp_name(".linegs-Ab3xY9.obj", Some("json")));
        assert_eq!(
            parse_temp_name(".linegs-node-17-4242-Ab3xY9.obj"),
            Some((Some(("node-17", 4242)), "obj"))
        );
        assert_eq!(parse_temp_name(".linegs-Ab3xY9.obj"), Some((None, "obj")));
        // What this run makes parses back to this host and process.
        let mine = format!("{}Zz9zZ9.obj", temp_prefix());
        assert_eq!(
            parse_temp_name(&mine),
            Some((Some((host(), std::process::id())), "obj"))
        );
        assert_eq!(sanitize_host("gpu_07.cluster.example.org"), "gpu-07");
        assert_eq!(sanitize_host(""), "host");
        assert_eq!(sanitize_host(&"x".repeat(99)).len(), HOST_MAX);
    }

    /// Another host's lock may be invisible here: its files are never removed, however old
    /// and unlocked they look; this host's (and unnamed ones of earlier versions) are.
    #[test]
    fn another_hosts_temporary_files_are_never_removed() {
        let d = tempfile::tempdir().unwrap();
        let p = |n: &str| d.path().join(n);
        let other = if host() == "elsewhere" {
            "yonder"
        } else {
            "elsewhere"
        };
        let names = [
            format!(".linegs-{other}-77-Ab3xY9.obj"),
            format!(".linegs-{}-77-Ab3xY9.obj", host()),
            ".linegs-Cd4eF5.obj".to_string(),
        ];
        for n in &names {
            std::fs::write(p(n), b"x").unwrap();
            age(&p(n));
        }
        assert_eq!(clean_stale_temps(d.path()), 2);
        assert!(p(&names[0]).exists());
        assert!(!p(&names[1]).exists() && !p(&names[2]).exists());
    }

    #[cfg(unix)]
    #[test]
    fn only_old_unlocked_temporary_files_are_removed() {
        let d = tempfile::tempdir().unwrap();
        let p = |n: &str| d.path().join(n);
        for n in [
            ".linegs-killed.obj",
            ".linegs-living.json",
            ".linegs-fresh1.obj",
            "notes.txt",
            ".linegs-batch.lock",
        ] {
            std::fs::write(p(n), b"x").unwrap();
        }
        for n in [
            ".linegs-killed.obj",
            ".linegs-living.json",
            "notes.txt",
            ".linegs-batch.lock",
        ] {
            age(&p(n));
        }
        let living = File::open(p(".linegs-living.json")).unwrap();
        assert!(try_lock(&living).unwrap());
        assert_eq!(clean_stale_temps(d.path()), 1);
        assert!(!p(".linegs-killed.obj").exists());
        for n in [
            ".linegs-living.json",
            ".linegs-fresh1.obj",
            "notes.txt",
            ".linegs-batch.lock",
        ] {
            assert!(p(n).exists(), "{n}");
        }
        // The lock gone with its run: removed.
        drop(living);
        assert_eq!(clean_stale_temps(d.path()), 1);
        assert!(!p(".linegs-living.json").exists());
    }
}
