//! Gaussian models in every format the splatting tools write (docs/formats.md): the
//! formats listed in `registry.rs`, chosen by content (and, for a format without a
//! signature such as `.splat`, by extension). Every reader feeds one [`Sink`], so NaN
//! centers, `--min-opacity` and empty models are handled the same way whatever the format.

use std::fs::File;
use std::io::Read;
use std::path::Path;

use super::attributes::GaussianAttributes;
use super::error::Error;
use super::format::{extension, GaussianFormat, GaussianRead, Source};
use super::input::{check_readable, open_input, read_input, Input};
use super::ply::{self, GaussianCloud, PlyOptions, BOM};
use super::ply_3dgs;
use super::registry::{join_and, GAUSSIAN_FORMATS};
use super::sink::Sink;

/// Picks the Gaussian format of a file from its first bytes (up to 1 MiB), its length and
/// its extension: the formats' signatures in registry order, then the formats chosen by
/// extension.
pub fn detect_gaussians(
    path: &Path,
    head: &[u8],
    file_len: u64,
) -> Result<&'static GaussianFormat, Error> {
    if file_len == 0 {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    for f in GAUSSIAN_FORMATS {
        if (f.sniff)(path, head, file_len)? {
            return Ok(f);
        }
    }
    let ext = extension(path);
    if let Some(f) = GAUSSIAN_FORMATS
        .iter()
        .find(|f| f.by_extension && f.extensions.contains(&ext.as_str()))
    {
        return Ok(f);
    }
    let words: Vec<&str> = GAUSSIAN_FORMATS
        .iter()
        .filter_map(|f| f.sniff_hint)
        .collect();
    Err(Error::unknown(
        path,
        format!(
            "Gaussians are read from {}, and this file is none of them",
            join_and(&words)
        ),
    ))
}

/// True when `path` holds Gaussians (any readable model format) rather than lines: a PLY
/// without an `edge` element, or any other Gaussian format. Folders and unreadable files
/// are not.
pub fn is_gaussian_model(path: &Path) -> Result<bool, Error> {
    if path.is_dir() {
        return Ok(false);
    }
    let (head, len) = head_of(path)?;
    Ok(match detect_gaussians(path, &head, len) {
        Ok(f) if f.is_ply => ply::parse_header(path, &head, head.len() as u64 == len)?
            .element("edge")
            .is_none(),
        Ok(_) => true,
        Err(_) => false,
    })
}

/// Reads the Gaussian centers of a model in any format of docs/formats.md.
///
/// NaN/Inf centers are skipped and counted with one warning (an error with `strict`);
/// `min_opacity` keeps Gaussians whose opacity (after the format's activation) is at least
/// the threshold; a file with no usable Gaussian is an error.
pub fn read_gaussians(path: &Path, opts: &PlyOptions) -> Result<GaussianCloud, Error> {
    Ok(read(path, opts, false)?.0)
}

/// Like [`read_gaussians`], and also the opacity of every kept Gaussian as the logit that
/// 3DGS stores (`None` when the file has no opacity), for `convert`.
pub fn read_gaussians_with_opacity(
    path: &Path,
    opts: &PlyOptions,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    read(path, opts, true)
}

fn read(
    path: &Path,
    opts: &PlyOptions,
    keep_opacity: bool,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    // A pipe is read once, into memory, and parsed there; devices are refused.
    if let Input::Bytes(b) = open_input(path)? {
        return read_bytes(path, &b, opts, keep_opacity);
    }
    let (head, len) = head_of(path)?;
    let format = detect_gaussians(path, &head, len)?;
    match format.read {
        GaussianRead::Own(read) => read(path, Source::File, opts, keep_opacity),
        GaussianRead::Bytes(read) => {
            let bytes = read_input(path)?;
            read(path, &bytes, Sink::new(path, opts, keep_opacity))
        }
    }
}

/// [`read_gaussians`] and [`super::read_gaussian_attributes`] of one model: a pipe is read
/// once and both are parsed from memory (a second open of a pipe would wait for a writer
/// that is gone); a 3DGS PLY file in f32 is walked once for both
/// ([`ply::read_gaussians_with_attributes`]), any other file twice.
pub fn read_gaussians_and_attributes(
    path: &Path,
    opts: &PlyOptions,
) -> Result<(GaussianCloud, Option<GaussianAttributes>), Error> {
    match open_input(path)? {
        Input::Bytes(b) => parse_gaussians_and_attributes(path, &b, opts),
        Input::File { .. } => {
            let (head, len) = head_of(path)?;
            if detect_gaussians(path, &head, len)? == &ply_3dgs::FORMAT {
                // One walk for both where the PLY has the 3DGS layout in f32.
                let (cloud, attributes) = ply::read_gaussians_with_attributes(path, opts)?;
                if let Some(a) = attributes {
                    return Ok((cloud, Some(a)));
                }
                return Ok((
                    cloud,
                    super::normals::read_gaussian_attributes(path, opts.min_opacity)?,
                ));
            }
            Ok((
                read(path, opts, false)?.0,
                super::normals::read_gaussian_attributes(path, opts.min_opacity)?,
            ))
        }
    }
}

/// [`read_gaussians_and_attributes`] of bytes already in memory (any model format); `path`
/// names them in messages.
pub fn parse_gaussians_and_attributes(
    path: &Path,
    bytes: &[u8],
    opts: &PlyOptions,
) -> Result<(GaussianCloud, Option<GaussianAttributes>), Error> {
    let head = bytes.strip_prefix(BOM).unwrap_or(bytes);
    let head = &head[..head.len().min(1 << 20)];
    let apart = || super::normals::parse_gaussian_attributes(path, bytes, opts.min_opacity);
    if detect_gaussians(path, head, bytes.len() as u64)? == &ply_3dgs::FORMAT {
        let (cloud, attributes) = ply::parse_gaussians_with_attributes(path, bytes, opts)?;
        let attributes = match attributes {
            Some(a) => Some(a),
            None => apart()?,
        };
        return Ok((cloud, attributes));
    }
    Ok((read_bytes(path, bytes, opts, false)?.0, apart()?))
}

/// [`read_gaussians`] on bytes already in memory (any model format); `path` names them
/// in messages, and its extension tells a format that has no signature.
pub fn parse_gaussian_model(
    path: &Path,
    bytes: &[u8],
    opts: &PlyOptions,
) -> Result<GaussianCloud, Error> {
    Ok(read_bytes(path, bytes, opts, false)?.0)
}

/// [`read`] of a pipe's content.
fn read_bytes(
    path: &Path,
    b: &[u8],
    opts: &PlyOptions,
    keep_opacity: bool,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    let head = b.strip_prefix(BOM).unwrap_or(b);
    let head = &head[..head.len().min(1 << 20)];
    match detect_gaussians(path, head, b.len() as u64)?.read {
        GaussianRead::Own(read) => read(path, Source::Bytes(b), opts, keep_opacity),
        GaussianRead::Bytes(read) => read(path, b, Sink::new(path, opts, keep_opacity)),
    }
}

/// The first MiB of a file (after a byte-order mark, which every reader skips) and the
/// length of the rest. Devices are refused, not read.
pub(crate) fn head_of(path: &Path) -> Result<(Vec<u8>, u64), Error> {
    if !check_readable(path)?.is_file() {
        return Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: "a pipe can be read only once; give a regular file here".into(),
        });
    }
    let file = File::open(path).map_err(|e| Error::io(path, "open", e))?;
    let len = file
        .metadata()
        .map_err(|e| Error::io(path, "read metadata of", e))?
        .len();
    let mut head = Vec::new();
    file.take(1 << 20)
        .read_to_end(&mut head)
        .map_err(|e| Error::io(path, "read", e))?;
    if head.starts_with(BOM) {
        head.drain(..BOM.len());
        return Ok((head, len - BOM.len() as u64));
    }
    Ok((head, len))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unknown_content_is_named_and_empty_files_are_empty() {
        let p = Path::new("model.bin");
        let e = detect_gaussians(p, b"hello", 5).unwrap_err();
        assert!(matches!(e, Error::UnknownFormat { .. }), "{e}");
        assert!(e.to_string().contains(".spz"), "{e}");
        let e = detect_gaussians(p, b"", 0).unwrap_err();
        assert!(matches!(e, Error::Empty { .. }), "{e}");
        assert_eq!(
            detect_gaussians(Path::new("a.SPLAT"), &[0u8; 32], 32)
                .unwrap()
                .id,
            "splat"
        );
    }
}
