//! Opening an input file so that no file can make a reader hang or exhaust memory: regular
//! files are read up to their size, pipes (FIFOs, `<(...)`) are read once up to a limit,
//! and devices (`/dev/zero`, `/dev/urandom`), folders and sockets are refused.

use std::fs::File;
use std::io::Read;
use std::path::Path;

use super::error::Error;

/// Most bytes read from a pipe, which has no size to bound the read by: a model or line
/// file larger than this should be saved to a file first.
pub const STREAM_LIMIT: u64 = 1 << 30;

/// An input, opened once.
pub(crate) enum Input {
    /// A regular file and its size.
    File { file: File, len: u64 },
    /// Everything a pipe delivered (at most [`STREAM_LIMIT`] bytes).
    Bytes(Vec<u8>),
}

/// Opens `path` for reading once (see the module comment).
pub(crate) fn open_input(path: &Path) -> Result<Input, Error> {
    open_input_bounded(path, STREAM_LIMIT)
}

/// [`open_input`] with a pipe read up to `limit` bytes.
fn open_input_bounded(path: &Path, limit: u64) -> Result<Input, Error> {
    let meta = check_readable(path)?;
    let file = File::open(path).map_err(|e| Error::io(path, "open", e))?;
    if meta.is_file() {
        return Ok(Input::File {
            file,
            len: meta.len(),
        });
    }
    // A FIFO: read once, so `info` (which looks at the head, then parses) cannot block on
    // a second open, and bounded, so an endless writer cannot exhaust memory.
    Ok(Input::Bytes(read_bounded(path, file, limit)?))
}

/// The metadata of `path` if it is a regular file or a FIFO; devices, folders and sockets
/// are refused without being opened.
pub(crate) fn check_readable(path: &Path) -> Result<std::fs::Metadata, Error> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, "open", e))?;
    let refuse = |what: &str| {
        Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: format!("{what}, not a file; give a regular file (or a pipe)"),
        })
    };
    if meta.is_dir() {
        return refuse("is a folder");
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        let t = meta.file_type();
        if t.is_char_device() || t.is_block_device() {
            return refuse("is a device (it has no end, or no size to bound the read)");
        }
        if t.is_socket() {
            return refuse("is a socket");
        }
    }
    Ok(meta)
}

/// Reads the whole of `path` with the same bounds as the readers (devices refused,
/// pipes at most [`STREAM_LIMIT`]), for readers outside this module (the mesh sampler).
pub(crate) fn read_input(path: &Path) -> Result<Vec<u8>, Error> {
    open_input(path)?.into_bytes(path)
}

/// Reads a small input (a transform, a manifest, a track file) whole: like
/// [`read_input`], and a regular file longer than `limit` bytes is refused before it is
/// read, `what` naming the kind of file in the message; with `regular_only`, a pipe is
/// refused too (a member of an input folder, which a pipe there would hang).
pub(crate) fn read_small(
    path: &Path,
    what: &str,
    limit: u64,
    regular_only: bool,
) -> Result<Vec<u8>, Error> {
    let meta = check_readable(path)?;
    if regular_only && !meta.is_file() {
        return Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: format!("is a pipe, not a file; {what} is read from a regular file"),
        });
    }
    if meta.is_file() && meta.len() > limit {
        return Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: format!(
                "{} bytes, more than the {limit} that {what} may have",
                meta.len()
            ),
        });
    }
    match open_input_bounded(path, limit)? {
        Input::Bytes(b) => Ok(b),
        i => i.into_bytes(path),
    }
}

/// Reads all of `r`, refusing a stream longer than `limit` bytes.
pub(crate) fn read_bounded(path: &Path, r: impl Read, limit: u64) -> Result<Vec<u8>, Error> {
    let mut out = Vec::new();
    r.take(limit + 1)
        .read_to_end(&mut out)
        .map_err(|e| Error::io(path, "read", e))?;
    if out.len() as u64 > limit {
        return Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: format!(
                "the pipe delivers more than {limit} bytes, the most read from a pipe; save it to a file first"
            ),
        });
    }
    Ok(out)
}

impl Input {
    /// The whole content (a regular file is read up to the size it had when opened, so a
    /// file that grows while it is read cannot grow the read without bound).
    pub(crate) fn into_bytes(self, path: &Path) -> Result<Vec<u8>, Error> {
        match self {
            Input::Bytes(b) => Ok(b),
            Input::File { file, len } => {
                let mut out = Vec::with_capacity(len.min(STREAM_LIMIT) as usize);
                file.take(len)
                    .read_to_end(&mut out)
                    .map_err(|e| Error::io(path, "read", e))?;
                Ok(out)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io;

    #[test]
    fn a_stream_longer_than_the_limit_is_refused() {
        let p = Path::new("pipe");
        assert_eq!(read_bounded(p, &[1u8, 2, 3][..], 3).unwrap(), [1, 2, 3]);
        let e = read_bounded(p, io::repeat(0), 1000).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("pipe: the pipe delivers more than 1000 bytes"),
            "{e}"
        );
    }

    #[cfg(unix)]
    #[test]
    fn devices_and_folders_are_refused_without_reading() {
        let e = open_input(Path::new("/dev/zero")).err().unwrap();
        assert!(e.to_string().contains("/dev/zero: is a device"), "{e}");
        let e = open_input(Path::new("/")).err().unwrap();
        assert!(e.to_string().contains("is a folder"), "{e}");
    }
}
