//! What killed runs leave behind, and how the next run knows it is theirs.
//!
//! Writers put every output in a temporary file beside its target first
//! (`.linegs-XXXXXX.<ext>`, six random letters or digits), and `main` may make a private
//! runtime folder (`linegs-gpu-runtime-XXXXXX` in the system's temporary folder). A live
//! run holds an exclusive `flock` on each of them as long as they exist; the kernel drops
//! the locks of a killed process with it. So what carries one of those names, belongs to
//! this user, is unlocked and older than [`STALE_AGE`] is no live run's, and the next run
//! that writes beside it removes it (the age covers the instants between creating a file
//! and locking it). Without Unix there are no locks and nothing is removed.

use std::fs::File;
use std::path::Path;
use std::time::{Duration, SystemTime};

/// How old unlocked litter must be before a run removes it.
pub const STALE_AGE: Duration = Duration::from_secs(60);

/// Prefix of every temporary file of the writers.
pub(crate) const TEMP_PREFIX: &str = ".linegs-";

/// Prefix of `main`'s private runtime folders.
pub const RUNTIME_PREFIX: &str = "linegs-gpu-runtime-";

/// An exclusive `flock` on `file` without waiting: `Ok(false)` when another process holds
/// it. (Elsewhere than Unix, always `Ok(true)`: no lock.)
pub fn try_lock(file: &File) -> std::io::Result<bool> {
    #[cfg(unix)]
    {
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a file descriptor this function borrows for the call.
        if unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) } == 0 {
            return Ok(true);
        }
        let e = std::io::Error::last_os_error();
        if e.kind() == std::io::ErrorKind::WouldBlock {
            return Ok(false);
        }
        Err(e)
    }
    #[cfg(not(unix))]
    {
        let _ = file;
        Ok(true)
    }
}

/// `.linegs-` and six ASCII letters or digits, then `.` and an extension of 1 to 16 bytes
/// without a dot: a writer's temporary file, or with `ext` given, that extension only.
pub(crate) fn is_temp_name(name: &str, ext: Option<&str>) -> bool {
    let Some(rest) = name.strip_prefix(TEMP_PREFIX) else {
        return false;
    };
    let (Some(rand), Some(tail)) = (rest.get(..6), rest.get(6..)) else {
        return false;
    };
    let Some(e) = tail.strip_prefix('.') else {
        return false;
    };
    rand.bytes().all(|b| b.is_ascii_alphanumeric())
        && (1..=16).contains(&e.len())
        && !e.contains('.')
        && ext.is_none_or(|x| x == e)
}

/// This user's, and last changed [`STALE_AGE`] ago or earlier.
fn old_and_ours(meta: &std::fs::Metadata) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::MetadataExt;
        // SAFETY: getuid has no preconditions.
        if meta.uid() != unsafe { libc::getuid() } {
            return false;
        }
    }
    meta.modified()
        .ok()
        .and_then(|m| SystemTime::now().duration_since(m).ok())
        .is_some_and(|age| age >= STALE_AGE)
}

/// Removes `path` if no live run holds it: it is locked for the removal, so a run that
/// opens it meanwhile finds it gone.
fn remove_if_unlocked(path: &Path, dir: bool) -> bool {
    if !cfg!(unix) {
        return false;
    }
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

/// Removes the stale temporary files of killed runs in `dir` (see the module comment) and
/// returns how many. A folder that still holds the journal of an unfinished output set
/// (see `io::journal`) is left alone: its temporary files are that set's outputs.
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
        .any(|(n, _)| is_temp_name(n, Some(super::journal::JOURNAL_EXT)))
    {
        return 0;
    }
    names
        .iter()
        .filter(|(_, p)| {
            std::fs::symlink_metadata(p).is_ok_and(|m| m.is_file() && old_and_ours(&m))
                && remove_if_unlocked(p, false)
        })
        .count()
}

/// Removes the runtime folders that killed runs of `main` left in the system's temporary
/// folder and returns how many.
pub fn clean_stale_runtime_dirs() -> usize {
    let Ok(rd) = std::fs::read_dir(std::env::temp_dir()) else {
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
        ] {
            assert!(is_temp_name(n, None), "{n}");
        }
        for n in [
            ".linegs-batch.lock",
            ".linegs-Ab3xY9",
            ".linegs-Ab3xY.obj",
            ".linegs-Ab3xY9.tar.gz",
            ".linegs-Ab3-Y9.obj",
            "linegs-Ab3xY9.obj",
            ".linegs-Ab3xY9.abcdefghijklmnopq",
            "refined.obj",
        ] {
            assert!(!is_temp_name(n, None), "{n}");
        }
        assert!(is_temp_name(".linegs-Ab3xY9.json", Some("json")));
        assert!(!is_temp_name(".linegs-Ab3xY9.obj", Some("json")));
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
