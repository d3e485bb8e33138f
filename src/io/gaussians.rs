//! Gaussian models in every format the splatting tools write (docs/formats.md): the 3DGS PLY (in
//! `ply.rs`), SuperSplat's compressed PLY, Niantic SPZ v1–v4 and antimatter15 `.splat`,
//! chosen by content (and, for `.splat`, which has no magic, by extension and size). Every
//! reader feeds one [`Sink`], so NaN centers, `--min-opacity` and empty models are handled
//! the same way whatever the format.

use std::fs::File;
use std::io::Read;
use std::path::Path;

use super::error::{Error, Position};
use super::input::{check_readable, open_input, read_input, Input};
use super::ply::{self, GaussianCloud, PlyOptions, PropKind, BOM};
use super::{ply_compressed, splat, spz};

/// The Gaussian formats [`read_gaussians`] recognises.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GaussianFormat {
    /// A PLY with `x`, `y`, `z` on `vertex` (3DGS `point_cloud.ply` and its relatives).
    Ply,
    /// SuperSplat / PlayCanvas compressed PLY: `chunk` bounds and `packed_position`.
    CompressedPly,
    /// Niantic SPZ (gzip, versions 1–3; ZSTD streams, version 4).
    Spz,
    /// antimatter15 `.splat`: 32 bytes a splat, no header.
    Splat,
}

/// Picks the Gaussian format of a file from its first bytes (up to 1 MiB), its length and
/// its extension.
pub fn detect_gaussians(path: &Path, head: &[u8], file_len: u64) -> Result<GaussianFormat, Error> {
    if file_len == 0 {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    if head.starts_with(b"ply") {
        let header = ply::parse_header(path, head, head.len() as u64 == file_len)?;
        return Ok(if ply_compressed::is_compressed(&header) {
            GaussianFormat::CompressedPly
        } else {
            GaussianFormat::Ply
        });
    }
    if spz::sniff(head) {
        return Ok(GaussianFormat::Spz);
    }
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if ext == "splat" {
        return Ok(GaussianFormat::Splat);
    }
    if ext == "spz" {
        // Named .spz but neither magic: let the SPZ reader say what is wrong.
        return Ok(GaussianFormat::Spz);
    }
    Err(Error::unknown(
        path,
        "Gaussians are read from PLY (3DGS or SuperSplat compressed), Niantic .spz \
         (starts with `NGSP` or a gzip header) and antimatter15 .splat (by extension), \
         and this file is none of them",
    ))
}

/// True when `path` holds Gaussians (any readable model format) rather than lines: a PLY
/// without an `edge` element, an SPZ or a `.splat`. Folders and unreadable files are not.
pub fn is_gaussian_model(path: &Path) -> Result<bool, Error> {
    if path.is_dir() {
        return Ok(false);
    }
    let (head, len) = head_of(path)?;
    Ok(match detect_gaussians(path, &head, len) {
        Ok(GaussianFormat::Ply | GaussianFormat::CompressedPly) => {
            ply::parse_header(path, &head, head.len() as u64 == len)?
                .element("edge")
                .is_none()
        }
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
    match detect_gaussians(path, &head, len)? {
        // The 3DGS reader streams and has a fast path; it only lacks the opacity output.
        GaussianFormat::Ply if !keep_opacity => Ok((ply::read_gaussians(path, opts)?, None)),
        GaussianFormat::Ply => read_ply_with_opacity(path, opts),
        GaussianFormat::CompressedPly => {
            let bytes = read_all(path)?;
            ply_compressed::read(path, &bytes, Sink::new(path, opts, keep_opacity))
        }
        GaussianFormat::Spz => {
            let bytes = read_all(path)?;
            spz::read(path, &bytes, Sink::new(path, opts, keep_opacity))
        }
        GaussianFormat::Splat => {
            let bytes = read_all(path)?;
            splat::read(path, &bytes, Sink::new(path, opts, keep_opacity))
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
) -> Result<(GaussianCloud, Option<super::GaussianAttributes>), Error> {
    match open_input(path)? {
        Input::Bytes(b) => parse_gaussians_and_attributes(path, &b, opts),
        Input::File { .. } => {
            let (head, len) = head_of(path)?;
            if detect_gaussians(path, &head, len)? == GaussianFormat::Ply {
                // One walk for both where the PLY has the 3DGS layout in f32.
                let (cloud, attributes) = ply::read_gaussians_with_attributes(path, opts)?;
                if let Some(a) = attributes {
                    return Ok((cloud, Some(a)));
                }
                return Ok((
                    cloud,
                    super::read_gaussian_attributes(path, opts.min_opacity)?,
                ));
            }
            Ok((
                read(path, opts, false)?.0,
                super::read_gaussian_attributes(path, opts.min_opacity)?,
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
) -> Result<(GaussianCloud, Option<super::GaussianAttributes>), Error> {
    let head = bytes.strip_prefix(BOM).unwrap_or(bytes);
    let head = &head[..head.len().min(1 << 20)];
    let apart = || super::normals::parse_gaussian_attributes(path, bytes, opts.min_opacity);
    if detect_gaussians(path, head, bytes.len() as u64)? == GaussianFormat::Ply {
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
/// in messages, and its extension tells a `.splat` (which has no magic).
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
    match detect_gaussians(path, head, b.len() as u64)? {
        GaussianFormat::Ply if !keep_opacity => Ok((ply::parse_gaussians(path, b, opts)?, None)),
        GaussianFormat::Ply => Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: "the opacities of a PLY are read from a file, not a pipe; save it first".into(),
        }),
        GaussianFormat::CompressedPly => {
            ply_compressed::read(path, b, Sink::new(path, opts, keep_opacity))
        }
        GaussianFormat::Spz => spz::read(path, b, Sink::new(path, opts, keep_opacity)),
        GaussianFormat::Splat => splat::read(path, b, Sink::new(path, opts, keep_opacity)),
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

/// The whole file, bounded like every reader (see `input.rs`).
fn read_all(path: &Path) -> Result<Vec<u8>, Error> {
    read_input(path)
}

/// A plain PLY read through the generic record walker, keeping the opacity logits.
fn read_ply_with_opacity(
    path: &Path,
    opts: &PlyOptions,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    // The streaming reader validates everything first (and names the faults the same way).
    let checked = ply::read_gaussians(
        path,
        &PlyOptions {
            min_opacity: None,
            strict: opts.strict,
        },
    )?;
    let bytes = read_all(path)?;
    let (header, mut body) = ply::open_in_memory(path, &bytes)?;
    let vi = header
        .element("vertex")
        .ok_or_else(|| Error::missing(path, "the PLY has no `vertex` element"))?;
    let vertex = &header.elements[vi];
    let scalar = |n: &str| {
        vertex
            .prop(n)
            .filter(|&i| matches!(vertex.props[i].kind, PropKind::Scalar(_)))
    };
    let (Some(x), Some(y), Some(z)) = (scalar("x"), scalar("y"), scalar("z")) else {
        return Err(Error::missing(path, "the `vertex` element has no x, y, z"));
    };
    let op = scalar("opacity");
    if opts.min_opacity.is_some() && op.is_none() {
        return Err(Error::missing(
            path,
            "--min-opacity needs an `opacity` property on `vertex` (3DGS models have one; this file has none)",
        ));
    }
    let mut wanted = vec![x, y, z];
    wanted.extend(op);
    for elem in &header.elements[..vi] {
        body.skip(path, elem)?;
    }
    let mut sink = Sink::new(path, opts, op.is_some());
    body.for_each(path, vertex, &wanted, |loc, v| {
        let logit = v.get(3).copied().unwrap_or(0.0) as f32;
        sink.push_f64(v, sigmoid(logit as f64), logit, || loc.position("vertex"))
    })?;
    let (mut cloud, opacity) = sink.finish(vertex.count, header.format())?;
    cloud.properties = checked.properties;
    cloud.warnings = checked.warnings;
    Ok((cloud, opacity))
}

#[inline]
pub(crate) fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// Collects the usable centers of one read, whatever the format: NaN/Inf centers skipped
/// and counted (an error with `strict`), the `min_opacity` cut on the opacity in `[0, 1]`.
pub(crate) struct Sink<'a> {
    path: &'a Path,
    min_opacity: Option<f64>,
    strict: bool,
    keep_opacity: bool,
    centers: Vec<[f32; 3]>,
    logits: Vec<f32>,
    nonfinite: usize,
    /// Of `nonfinite`: centers finite in the file that overflow f32.
    overflow: usize,
    first_nonfinite: Option<Position>,
    low: usize,
    /// Appended to the cloud's warnings (format-specific notes).
    pub(crate) warnings: Vec<String>,
}

impl<'a> Sink<'a> {
    pub(crate) fn new(path: &'a Path, opts: &PlyOptions, keep_opacity: bool) -> Self {
        Sink {
            path,
            min_opacity: opts.min_opacity,
            strict: opts.strict,
            keep_opacity,
            centers: Vec::new(),
            logits: Vec::new(),
            nonfinite: 0,
            overflow: 0,
            first_nonfinite: None,
            low: 0,
            warnings: Vec::new(),
        }
    }

    pub(crate) fn reserve(&mut self, n: usize) {
        self.centers.reserve(n);
        if self.keep_opacity {
            self.logits.reserve(n);
        }
    }

    /// Takes one Gaussian: its center, opacity in `[0, 1]` (for the cut) and the logit that
    /// a 3DGS PLY would store (for `convert`).
    #[inline]
    pub(crate) fn push(
        &mut self,
        c: [f32; 3],
        opacity: f64,
        logit: f32,
        pos: impl FnOnce() -> Position,
    ) -> Result<(), Error> {
        if !c.iter().all(|v| v.is_finite()) {
            let pos = pos();
            if self.strict {
                return Err(Error::strict_center(self.path, pos, c));
            }
            self.nonfinite += 1;
            self.first_nonfinite.get_or_insert(pos);
            return Ok(());
        }
        if let Some(t) = self.min_opacity {
            // NaN opacity fails the test and is dropped, as in the PLY reader.
            if opacity.partial_cmp(&t).is_none_or(|o| o.is_lt()) {
                self.low += 1;
                return Ok(());
            }
        }
        self.centers.push(c);
        if self.keep_opacity {
            self.logits.push(logit);
        }
        Ok(())
    }

    /// [`Self::push`] of a center read as f64: one beyond the range of f32 is counted
    /// (or refused under strict) as an overflow, not as NaN or infinite.
    pub(crate) fn push_f64(
        &mut self,
        v: &[f64],
        opacity: f64,
        logit: f32,
        pos: impl FnOnce() -> Position,
    ) -> Result<(), Error> {
        let (c, over) = super::error::narrow_center(v);
        if let Some(value) = over {
            let at = pos();
            if self.strict {
                return Err(Error::strict_overflow(self.path, at, value));
            }
            self.overflow += 1;
            return self.push(c, opacity, logit, || at);
        }
        self.push(c, opacity, logit, pos)
    }

    /// The cloud, or the error for a model with nothing usable. `total` is the number of
    /// Gaussians in the file; `format` what `info` shows.
    pub(crate) fn finish(
        mut self,
        total: usize,
        format: String,
    ) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
        let mut warnings = std::mem::take(&mut self.warnings);
        if self.nonfinite > 0 {
            warnings.push(super::error::skipped_centers_warning(
                self.path,
                self.nonfinite,
                self.overflow,
                self.first_nonfinite.as_ref(),
            ));
        }
        if total == 0 {
            return Err(Error::no_data(self.path, "the model has no Gaussians"));
        }
        if self.centers.is_empty() {
            return Err(Error::none_usable(
                self.path,
                total,
                self.nonfinite,
                self.low,
                self.min_opacity,
            ));
        }
        self.centers.shrink_to_fit();
        let opacity = self.keep_opacity.then_some(self.logits);
        Ok((
            GaussianCloud {
                centers: self.centers,
                format,
                vertex_count: total,
                properties: Vec::new(),
                skipped_nonfinite: self.nonfinite,
                dropped_low_opacity: self.low,
                warnings,
            },
            opacity,
        ))
    }
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
            detect_gaussians(Path::new("a.SPLAT"), &[0u8; 32], 32).unwrap(),
            GaussianFormat::Splat
        );
    }
}
