//! PLY: the header (`header.rs`), a record walker shared by every element and encoding
//! (`records.rs`), and here the Gaussian reader with its fast path for 3DGS
//! `point_cloud.ply` files (docs/formats.md).

mod header;
mod records;

pub(crate) use header::*;
pub(crate) use records::*;

use std::io::Read;
use std::path::Path;

use super::attributes::{opacity_of, Attribute, GaussianAttributes};
use super::chunked::{Chunked, CHUNK};
use super::error::{Error, Position};
use super::input::{open_input, Input};
use rayon::prelude::*;

/// Options for [`crate::io::read_gaussians`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlyOptions {
    /// Keep only Gaussians with `sigmoid(opacity) >= min_opacity` (3DGS stores the logit).
    pub min_opacity: Option<f64>,
    /// Make a NaN or infinite center an error instead of a counted, skipped Gaussian.
    pub strict: bool,
}

/// The Gaussian centers of a PLY model and what was dropped on the way.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianCloud {
    pub centers: Vec<[f32; 3]>,
    /// The header's format line without `format`, e.g. `"binary_little_endian 1.0"`.
    pub format: String,
    /// Records in the `vertex` element, before anything was dropped.
    pub vertex_count: usize,
    /// Property names of the `vertex` element, in file order.
    pub properties: Vec<String>,
    pub skipped_nonfinite: usize,
    pub dropped_low_opacity: usize,
    /// One line each, naming the file (the NaN-center warning of docs/formats.md, trailing data).
    pub warnings: Vec<String>,
}

/// Collects centers and the counts of what was dropped; one per read.
struct Collect<'a> {
    path: &'a Path,
    centers: Vec<[f32; 3]>,
    min_opacity: Option<OpacityCut>,
    strict: bool,
    nonfinite: usize,
    /// Of `nonfinite`: centers finite in the file that overflow f32.
    overflow: usize,
    first_nonfinite: Option<Position>,
    low: usize,
}

impl Collect<'_> {
    /// Takes one Gaussian; `loc` is only turned into a position on the rare bad record.
    #[inline(always)]
    fn push(
        &mut self,
        c: [f32; 3],
        opacity: f32,
        loc: impl FnOnce() -> Position,
    ) -> Result<(), Error> {
        if !(c[0].is_finite() && c[1].is_finite() && c[2].is_finite()) {
            let pos = loc();
            if self.strict {
                return Err(Error::strict_center(self.path, pos, c));
            }
            self.nonfinite += 1;
            self.first_nonfinite.get_or_insert(pos);
            return Ok(());
        }
        if let Some(cut) = &self.min_opacity {
            if !cut.keeps(opacity) {
                self.low += 1;
                return Ok(());
            }
        }
        self.centers.push(c);
        Ok(())
    }

    /// [`Self::push`] of a center read as f64: one beyond the range of f32 is counted
    /// (or refused under strict) as an overflow, not as NaN or infinite.
    fn push_f64(
        &mut self,
        v: &[f64],
        opacity: f32,
        loc: impl FnOnce() -> Position,
    ) -> Result<(), Error> {
        let (c, over) = super::error::narrow_center(v);
        if let Some(value) = over {
            let pos = loc();
            if self.strict {
                return Err(Error::strict_overflow(self.path, pos, value));
            }
            self.overflow += 1;
            return self.push(c, opacity, || pos);
        }
        self.push(c, opacity, loc)
    }
}

#[inline(always)]
fn sigmoid(x: f64) -> f64 {
    1.0 / (1.0 + (-x).exp())
}

/// `sigmoid(x) >= t` without an `exp` per Gaussian (it halved the read speed): sigmoid is
/// increasing, so `x` is compared with `logit(t)`, and only a logit within rounding
/// distance of the threshold takes the exact test, so the answer is the same.
#[derive(Clone, Copy, Debug)]
struct OpacityCut {
    t: f64,
    /// NaN where `logit(t)` is too ill-conditioned to trust (t near 0 or 1).
    logit: f64,
}

impl OpacityCut {
    fn new(t: f64) -> Self {
        let logit = if t > 1e-6 && t < 1.0 - 1e-6 {
            (t / (1.0 - t)).ln()
        } else {
            f64::NAN
        };
        OpacityCut { t, logit }
    }

    #[inline(always)]
    fn keeps(&self, x: f32) -> bool {
        let x = x as f64;
        let d = x - self.logit;
        // NaN (either side) fails this and takes the exact test, where NaN opacity is dropped.
        if d.abs() > 1e-9 * (1.0 + self.logit.abs()) {
            d > 0.0
        } else {
            sigmoid(x) >= self.t
        }
    }
}

#[inline(always)]
fn f32_le(rec: &[u8], o: usize) -> f32 {
    f32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]])
}

/// Reads the Gaussian centers (`vertex` x, y, z) of a PLY file.
///
/// Memory stays at the 12 bytes per kept center plus one 1 MiB read buffer: records are
/// decoded straight out of the buffer. NaN/Inf centers are skipped and counted with one
/// warning (an error with `strict`); a file with no usable Gaussian is an error.
pub fn read_gaussians(path: &Path, opts: &PlyOptions) -> Result<GaussianCloud, Error> {
    Ok(match open_input(path)? {
        Input::File { file, len } => gaussians_from(path, file.take(len), len, opts, false)?,
        Input::Bytes(b) => gaussians_from(path, &b[..], b.len() as u64, opts, false)?,
    }
    .0)
}

/// [`read_gaussians`] and the Gaussians' [`GaussianAttributes`] from the same walk over
/// the file, where it is a binary little-endian 3DGS PLY whose rotations, scales (and
/// opacities) are f32, as trainers write them; `None` attributes otherwise (then
/// [`crate::io::read_gaussian_attributes`] reads them in a pass of its own). The
/// attributes are those of exactly the Gaussians kept, in their order.
pub fn read_gaussians_with_attributes(
    path: &Path,
    opts: &PlyOptions,
) -> Result<(GaussianCloud, Option<GaussianAttributes>), Error> {
    match open_input(path)? {
        Input::File { file, len } => gaussians_from(path, file.take(len), len, opts, true),
        Input::Bytes(b) => gaussians_from(path, &b[..], b.len() as u64, opts, true),
    }
}

/// [`read_gaussians_with_attributes`] of bytes already in memory.
pub fn parse_gaussians_with_attributes(
    path: &Path,
    bytes: &[u8],
    opts: &PlyOptions,
) -> Result<(GaussianCloud, Option<GaussianAttributes>), Error> {
    gaussians_from(path, bytes, bytes.len() as u64, opts, true)
}

/// Byte offsets in a vertex record (little-endian f32 values) of what
/// [`GaussianAttributes`] holds.
struct AttrPlan {
    rot: [usize; 4],
    scale: [usize; 3],
    opacity: Option<usize>,
    dc: Option<[usize; 3]>,
}

impl AttrPlan {
    /// The plan for `vertex`, where every property it reads is an f32 scalar.
    fn of(vertex: &Element) -> Option<AttrPlan> {
        let f32_at = |name: &str| {
            let i = vertex.prop(name)?;
            (vertex.props[i].kind == PropKind::Scalar(Scalar::F32)).then(|| vertex.offset(i))
        };
        let rot = ["rot_0", "rot_1", "rot_2", "rot_3"].map(f32_at);
        let scale = ["scale_0", "scale_1", "scale_2"].map(f32_at);
        let opacity = match vertex.prop("opacity") {
            Some(_) => Some(f32_at("opacity")?),
            None => None,
        };
        let dc = ["f_dc_0", "f_dc_1", "f_dc_2"].map(f32_at);
        Some(AttrPlan {
            rot: [rot[0]?, rot[1]?, rot[2]?, rot[3]?],
            scale: [scale[0]?, scale[1]?, scale[2]?],
            opacity,
            dc: match dc {
                [Some(a), Some(b), Some(c)] => Some([a, b, c]),
                _ => None,
            },
        })
    }

    /// Record `rec`'s attributes.
    #[inline]
    fn attribute(&self, rec: &[u8]) -> Attribute {
        let v = |o: usize| f64::from(f32_le(rec, o));
        Attribute::of(
            self.rot.map(v),
            self.scale.map(v),
            self.opacity.map(|o| opacity_of(f32_le(rec, o))),
            self.dc.map(|d| d.map(v)),
        )
    }
}

/// [`crate::io::read_gaussians`] on bytes already in memory; `path` names them in messages.
pub fn parse_gaussians(
    path: &Path,
    bytes: &[u8],
    opts: &PlyOptions,
) -> Result<GaussianCloud, Error> {
    Ok(gaussians_from(path, bytes, bytes.len() as u64, opts, false)?.0)
}

/// The Gaussian reader over a stream of exactly `file_len` bytes.
fn gaussians_from<R: Read>(
    path: &Path,
    input: R,
    file_len: u64,
    opts: &PlyOptions,
    want_attributes: bool,
) -> Result<(GaussianCloud, Option<GaussianAttributes>), Error> {
    if file_len == 0 {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    let mut ch = Chunked::new(input, CHUNK.min(file_len as usize + 1), 0);
    ch.fill().map_err(|e| Error::io(path, "read", e))?;
    // A byte-order mark from a Windows editor: skipped here as in the line reader, so
    // `info` and `eval` agree about such a file.
    let bom = if ch.available().starts_with(BOM) {
        ch.consume(BOM.len());
        BOM.len()
    } else {
        0
    };
    let head = ch.available();
    if !head.starts_with(b"ply") {
        return Err(Error::unknown(
            path,
            "Gaussians are read from PLY files, and this file does not start with `ply`",
        ));
    }
    let header = parse_header(path, head, (bom + head.len()) as u64 == file_len)?;
    let header_lines = head[..header.len].iter().filter(|&&b| b == b'\n').count();
    ch.consume(header.len);

    let Some(vi) = header.element("vertex") else {
        return Err(Error::missing(
            path,
            "the PLY has no `vertex` element, so it holds no Gaussians",
        ));
    };
    let vertex = &header.elements[vi];
    let scalar_prop = |name: &str| -> Result<(usize, Scalar), Error> {
        match vertex.prop(name).map(|i| (i, vertex.props[i].kind)) {
            Some((i, PropKind::Scalar(s))) => Ok((i, s)),
            Some(_) => Err(Error::parse(
                path,
                Position::Line(vertex.line),
                format!("vertex property `{name}` is a list, expected a number"),
            )),
            None => Err(Error::missing(
                path,
                format!(
                    "the `vertex` element has no `{name}` property (it has: {})",
                    vertex
                        .props
                        .iter()
                        .map(|p| p.name.as_str())
                        .collect::<Vec<_>>()
                        .join(" ")
                ),
            )),
        }
    };
    let x = scalar_prop("x")?;
    let y = scalar_prop("y")?;
    let z = scalar_prop("z")?;
    let opacity = match opts.min_opacity {
        Some(_) => Some(scalar_prop("opacity").map_err(|_| {
            Error::missing(
                path,
                "--min-opacity needs an `opacity` property on `vertex` (3DGS models have one; this file has none)",
            )
        })?),
        None => None,
    };
    if vertex.count == 0 {
        return Err(Error::no_data(
            path,
            "the model has no Gaussians (`element vertex 0`)",
        ));
    }

    let mut warnings = Vec::new();
    let data_start = (bom + header.len) as u64;
    let have = file_len.saturating_sub(data_start);
    let binary = header.encoding != Encoding::Ascii;
    // A lying header is caught before anything is allocated for it.
    if binary {
        if let Some(data_len) = header.fixed_data_len() {
            if (have as u128) < data_len {
                return Err(short_file(path, &header, data_start, file_len));
            }
            if have as u128 > data_len {
                return Err(Error::parse(
                    path,
                    Position::Byte(data_start + data_len as u64),
                    format!(
                        "{} bytes after the last element: the header's elements take {data_len} bytes, the file has {have} after the header (a property or a count missing from the header?)",
                        have as u128 - data_len
                    ),
                ));
            }
        }
    }
    let capacity = vertex.max_records(header.encoding, have);
    let mut col = Collect {
        path,
        centers: Vec::with_capacity(capacity),
        min_opacity: opts.min_opacity.map(OpacityCut::new),
        strict: opts.strict,
        nonfinite: 0,
        overflow: 0,
        first_nonfinite: None,
        low: 0,
    };

    let fast = header.encoding == Encoding::BinaryLe
        && vertex.stride().is_some()
        && [Some(x), Some(y), Some(z), opacity]
            .iter()
            .flatten()
            .all(|p| p.1 == Scalar::F32);
    let plan = (want_attributes && fast)
        .then(|| AttrPlan::of(vertex))
        .flatten();
    let mut attributes = plan
        .as_ref()
        .map(|p| GaussianAttributes::with_capacity(capacity, p.opacity.is_some(), p.dc.is_some()));
    let mut body = Body::new(ch, &header, header_lines);
    for elem in &header.elements[..vi] {
        body.skip(path, elem)?;
    }
    match (&mut body, fast) {
        (Body::Binary { ch, .. }, true) => {
            let stride = vertex.stride().unwrap_or(0);
            let offs = [x.0, y.0, z.0].map(|i| vertex.offset(i));
            let oo = opacity.map(|o| vertex.offset(o.0));
            let attrs = plan.as_ref().zip(attributes.as_mut());
            read_fast_le(path, ch, vertex, stride, (offs, oo), &mut col, attrs)?;
        }
        _ => {
            let mut wanted = vec![x.0, y.0, z.0];
            wanted.extend(opacity.map(|o| o.0));
            body.for_each(path, vertex, &wanted, |loc, v| {
                let op = v.get(3).copied().unwrap_or(0.0) as f32;
                col.push_f64(v, op, || loc.position("vertex"))
            })?;
        }
    }
    for elem in &header.elements[vi + 1..] {
        body.skip(path, elem)?;
    }
    body.finish(path, Some(file_len))?;

    if col.nonfinite > 0 {
        warnings.push(super::error::skipped_centers_warning(
            path,
            col.nonfinite,
            col.overflow,
            col.first_nonfinite.as_ref(),
        ));
    }
    if col.centers.is_empty() {
        return Err(Error::none_usable(
            path,
            vertex.count,
            col.nonfinite,
            col.low,
            opts.min_opacity,
        ));
    }
    col.centers.shrink_to_fit();
    Ok((
        GaussianCloud {
            centers: col.centers,
            format: header.format(),
            vertex_count: vertex.count,
            properties: vertex.props.iter().map(|p| p.name.clone()).collect(),
            skipped_nonfinite: col.nonfinite,
            dropped_low_opacity: col.low,
            warnings,
        },
        attributes,
    ))
}

/// The 3DGS hot loop: fixed stride, little-endian f32 x/y/z (and opacity) at offsets
/// computed once; each chunk is walked with `chunks_exact`, nothing is allocated.
fn read_fast_le<R: Read>(
    path: &Path,
    ch: &mut Chunked<R>,
    vertex: &Element,
    stride: usize,
    ([ox, oy, oz], oo): ([usize; 3], Option<usize>),
    col: &mut Collect,
    mut attrs: Option<(&AttrPlan, &mut GaussianAttributes)>,
) -> Result<(), Error> {
    let mut index = 0usize;
    // The records of a chunk whose centers were kept (their attributes are computed on
    // every thread: three `exp`s and a rotation each, most of the reading time otherwise).
    let mut kept_recs: Vec<u32> = Vec::new();
    while index < vertex.count {
        let avail = ch.available().len() / stride;
        if avail == 0 {
            if !ch.ensure(stride).map_err(|e| Error::io(path, "read", e))? {
                return Err(short_record(path, vertex, index, ch.offset()));
            }
            continue;
        }
        let n = avail.min(vertex.count - index);
        let base = ch.offset();
        let bytes = &ch.available()[..n * stride];
        kept_recs.clear();
        let want = attrs.is_some();
        let mut centers = || -> Result<(), Error> {
            for (k, rec) in bytes.chunks_exact(stride).enumerate() {
                let c = [f32_le(rec, ox), f32_le(rec, oy), f32_le(rec, oz)];
                let op = match oo {
                    Some(o) => f32_le(rec, o),
                    None => 0.0,
                };
                let kept = col.centers.len();
                col.push(c, op, || {
                    Position::record("vertex", index + k, Some(base + (k * stride) as u64))
                })?;
                if want && col.centers.len() > kept {
                    kept_recs.push(k as u32);
                }
            }
            Ok(())
        };
        if let Some((plan, out)) = attrs.as_mut() {
            // The centers on this thread while the other threads compute every record's
            // attributes (the records a center test drops are computed for nothing, and
            // are rare); then the kept records' attributes in order.
            let plan = &**plan;
            let (walked, computed) = rayon::join(&mut centers, || {
                bytes
                    .par_chunks_exact(stride)
                    .with_min_len(512)
                    .map(|rec| plan.attribute(rec))
                    .collect::<Vec<Attribute>>()
            });
            walked?;
            if kept_recs.len() == computed.len() {
                for a in computed {
                    out.push_one(a);
                }
            } else {
                for &k in &kept_recs {
                    out.push_one(computed[k as usize]);
                }
            }
        } else {
            centers()?;
        }
        ch.consume(n * stride);
        index += n;
    }
    Ok(())
}

/// The truncation error for a binary file shorter than its header's fixed-size elements
/// (whose data starts at byte `data_start`).
fn short_file(path: &Path, header: &Header, data_start: u64, file_len: u64) -> Error {
    let mut at = data_start;
    for e in &header.elements {
        let stride = e.stride().unwrap_or(0) as u64;
        let len = stride.saturating_mul(e.count as u64);
        if at.saturating_add(len) > file_len {
            let index = ((file_len.saturating_sub(at)) / stride.max(1)) as usize;
            return Error::truncated(
                path,
                Position::record(&e.name, index, Some(at + index as u64 * stride)),
                format!(
                    "the header promises {} {} records of {stride} bytes ({} bytes from byte {at}) but the file has {file_len} bytes, so it stops inside {} {index} (cut-short download or copy, or a wrong count in the header)",
                    e.count, e.name, len, e.name
                ),
            );
        }
        at += len;
    }
    Error::truncated(
        path,
        Position::Byte(file_len),
        "the data is shorter than the header says",
    )
}

/// Opens a PLY file for the line reader (small files; the whole file is in memory).
pub(crate) fn open_in_memory<'a>(
    path: &Path,
    bytes: &'a [u8],
) -> Result<(Header, Body<&'a [u8]>), Error> {
    let header = parse_header(path, bytes, true)?;
    let header_lines = bytes[..header.len].iter().filter(|&&b| b == b'\n').count();
    let have = (bytes.len() - header.len) as u64;
    if header.encoding != Encoding::Ascii {
        if let Some(data_len) = header.fixed_data_len() {
            if (have as u128) < data_len {
                return Err(short_file(
                    path,
                    &header,
                    header.len as u64,
                    bytes.len() as u64,
                ));
            }
        }
    }
    let rest = &bytes[header.len..];
    let ch = Chunked::new(rest, rest.len().clamp(1, CHUNK), header.len as u64);
    let body = Body::new(ch, &header, header_lines);
    Ok((header, body))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_walk_gives_the_attributes_of_two() {
        // A model OpenSplat trained (62 f32 properties): the centers and the attributes
        // from one walk equal the center reader's and the attribute reader's, with and
        // without an opacity cut.
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data/real_pairs/abc00000006/point_cloud.ply");
        for min_opacity in [None, Some(0.3)] {
            let opts = PlyOptions {
                min_opacity,
                ..Default::default()
            };
            let (cloud, fused) = read_gaussians_with_attributes(&path, &opts).unwrap();
            let fused = fused.expect("a 3DGS PLY in f32 is read in one walk");
            assert_eq!(cloud, read_gaussians(&path, &opts).unwrap());
            let apart = crate::io::read_gaussian_attributes(&path, min_opacity)
                .unwrap()
                .unwrap();
            assert_eq!(fused, apart);
            assert_eq!(fused.normals.len(), cloud.centers.len());
            assert!(fused
                .opacity
                .as_ref()
                .is_some_and(|o| o.len() == cloud.centers.len()));
            if min_opacity.is_some() {
                assert!(cloud.dropped_low_opacity > 0);
            }
        }
    }

    #[test]
    fn header_with_lists_and_comments() {
        let text = b"ply\r\nformat binary_big_endian 1.0\r\ncomment made by hand\r\nelement face 2\r\nproperty list uchar int vertex_indices\r\nelement vertex 3\r\nproperty double x\r\nproperty float32 y\r\nproperty uint8 red\r\nend_header\r\nDATA";
        let h = parse_header(Path::new("h.ply"), text, true).unwrap();
        assert_eq!(h.encoding, Encoding::BinaryBe);
        assert_eq!(h.format(), "binary_big_endian 1.0");
        assert_eq!(h.len, text.len() - 4);
        assert_eq!(h.elements[0].stride(), None);
        let v = &h.elements[1];
        assert_eq!((v.name.as_str(), v.count, v.line), ("vertex", 3, 6));
        assert_eq!(v.stride(), Some(13));
        assert_eq!(v.offset(2), 12);
        assert_eq!(v.props[1].kind, PropKind::Scalar(Scalar::F32));
    }

    #[test]
    fn header_errors_name_the_line() {
        let p = Path::new("bad.ply");
        let e = parse_header(
            p,
            b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n",
            true,
        )
        .unwrap_err();
        assert_eq!(e.position(), Some(&Position::Line(3)));
        let e = parse_header(
            p,
            b"ply\nformat ascii 1.0\nelement vertex 3\nproperty half x\n",
            true,
        )
        .unwrap_err();
        assert!(
            e.to_string()
                .starts_with("bad.ply: line 4: unknown property type `half`"),
            "{e}"
        );
        let e = parse_header(p, b"ply\nformat ascii 1.0\nelement vertex 3\n", true).unwrap_err();
        assert!(
            matches!(
                e,
                Error::Truncated {
                    pos: Position::Line(4),
                    ..
                }
            ),
            "{e}"
        );
        let e = parse_header(p, b"ply\nelement vertex 3\nend_header\n", true).unwrap_err();
        assert!(e.to_string().contains("without a `format`"), "{e}");
    }

    #[test]
    fn scalar_decoding_both_endians() {
        assert_eq!(Scalar::I16.decode(&[0xff, 0xfe], false), -257.0);
        assert_eq!(Scalar::I16.decode(&[0xff, 0xfe], true), -2.0);
        assert_eq!(Scalar::U32.decode(&7u32.to_be_bytes(), true), 7.0);
        assert_eq!(Scalar::F64.decode(&1.5f64.to_le_bytes(), false), 1.5);
        assert_eq!(Scalar::I8.decode(&[0x80], false), -128.0);
    }

    #[test]
    fn sigmoid_threshold_is_on_the_probability() {
        assert_eq!(sigmoid(0.0), 0.5);
        assert!((sigmoid(2.0) - 0.880797).abs() < 1e-6);
    }

    #[test]
    fn the_logit_cut_agrees_with_the_sigmoid_everywhere() {
        // Thresholds that are exactly sigmoid of an f32 put Gaussians right on the boundary.
        let thresholds = [
            0.5,
            sigmoid(2.0),
            sigmoid(-3.25),
            0.1,
            0.999,
            1e-7,
            1.0 - 1e-9,
            0.0,
            1.0,
        ];
        for t in thresholds {
            let cut = OpacityCut::new(t);
            let l = (t / (1.0 - t)).ln() as f32;
            let mut xs = vec![
                f32::NAN,
                f32::INFINITY,
                f32::NEG_INFINITY,
                0.0,
                -0.0,
                40.0,
                -40.0,
            ];
            for k in -3i32..=3 {
                if l.is_finite() {
                    xs.push(f32::from_bits((l.to_bits() as i32 + k) as u32));
                }
            }
            xs.extend((-200..=200).map(|i| i as f32 * 0.05));
            for x in xs {
                assert_eq!(cut.keeps(x), sigmoid(x as f64) >= t, "t {t}, x {x}");
            }
        }
    }
}
