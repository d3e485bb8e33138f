//! Niantic SPZ (Scaniverse's format, the payload of glTF's KHR_gaussian_splatting
//! compression), versions 1–4, read for the Gaussian centers and opacities.
//!
//! Versions 1–3 are one gzip stream holding a 16-byte header (`NGSP`, version, count, SH
//! degree, fractional bits, flags, reserved) and then the attributes one after the other:
//! positions, alphas, colors, scales, rotations, SH. Version 4 has a 32-byte plain header
//! (the same fields, plus the number of streams and the byte offset of a table of
//! contents); the table holds (compressed, uncompressed) sizes of independent ZSTD
//! streams, one per non-empty attribute, in the same order. Positions are 24-bit signed
//! fixed point with `fractional_bits` bits of fraction (version 1: float16). SPZ stores
//! RUB axes (x right, y up, z back); 3DGS PLY files, and so the lines made from the same
//! photos, use RDF (y down, z forward), so y and z change sign on the way in, as Niantic's
//! loader does when asked for RDF.
//!
//! Every size is known from the header before anything is decompressed, and no stream is
//! decompressed past it, so a small file cannot expand into a large allocation.

use std::io::Read;
use std::path::Path;

use super::error::{Error, Position};
use super::format::{GaussianFormat, GaussianRead};
use super::ply::GaussianCloud;
use super::sink::Sink;

pub(crate) static FORMAT: GaussianFormat = GaussianFormat {
    id: "spz",
    name: "Niantic SPZ",
    extensions: &["spz"],
    summary: "versions 1–4 (gzip; version 4's ZSTD streams); SPZ stores RUB axes, turned into \
              the PLY convention (y and z negated)",
    help: "Niantic `.spz` (v1-v4)",
    variant: None,
    family: "SPZ",
    hint: Some("Niantic .spz (v1-v4)"),
    sniff_hint: Some("Niantic .spz (starts with `NGSP` or a gzip header)"),
    sniff: |_, head, _| Ok(sniff(head)),
    // Named .spz but neither magic: the SPZ reader says what is wrong.
    by_extension: true,
    is_ply: false,
    read: GaussianRead::Bytes(read),
};

pub(crate) const MAGIC: &[u8; 4] = b"NGSP";
const GZIP: [u8; 2] = [0x1f, 0x8b];
const LEGACY_HEADER: usize = 16;
const HEADER_V4: usize = 32;
/// Deflate cannot expand by more than about 1032:1; ZSTD can, but Niantic's loader refuses
/// counts beyond this ratio too (real streams compress far less), so we do the same.
const MAX_RATIO: u64 = 1032;
const FLAG_EXTENSIONS: u8 = 0x2;

/// True for what only SPZ files start with: the v4 magic or a gzip header.
pub(crate) fn sniff(head: &[u8]) -> bool {
    head.starts_with(MAGIC) || head.starts_with(&GZIP)
}

/// The fields of either header that the reader needs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct Header {
    pub(crate) version: u32,
    pub(crate) count: u32,
    pub(crate) sh_degree: u8,
    pub(crate) fractional_bits: u8,
    pub(crate) flags: u8,
}

impl Header {
    fn parse(b: &[u8]) -> Header {
        let u32_at = |o: usize| u32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]]);
        Header {
            version: u32_at(4),
            count: u32_at(8),
            sh_degree: b[12],
            fractional_bits: b[13],
            flags: b[14],
        }
    }

    /// Bytes of each attribute, in file order: positions, alphas, colors, scales,
    /// rotations, SH.
    fn sections(&self) -> [(&'static str, u64); 6] {
        let n = self.count as u64;
        let dim = ((self.sh_degree as u64 + 1).pow(2)) - 1;
        [
            ("positions", n * if self.version == 1 { 6 } else { 9 }),
            ("alphas", n),
            ("colors", 3 * n),
            ("scales", 3 * n),
            ("rotations", n * if self.version >= 3 { 4 } else { 3 }),
            ("spherical harmonics", n * dim * 3),
        ]
    }

    fn describe(&self) -> String {
        format!(
            "Niantic SPZ version {} ({}), {} Gaussians, SH degree {}, {} fractional bits",
            self.version,
            if self.version >= 4 {
                "ZSTD streams"
            } else {
                "gzip"
            },
            self.count,
            self.sh_degree,
            self.fractional_bits
        )
    }

    /// The checks both layouts share; `bound` is the largest count the file size allows.
    fn check(
        &self,
        path: &Path,
        versions: std::ops::RangeInclusive<u32>,
        bound: u64,
    ) -> Result<(), Error> {
        if !versions.contains(&self.version) {
            return Err(Error::parse(
                path,
                Position::Byte(4),
                format!(
                    "SPZ version {} is not supported here (this layout holds versions {}–{})",
                    self.version,
                    versions.start(),
                    versions.end()
                ),
            ));
        }
        if self.count == 0 {
            return Err(Error::no_data(
                path,
                "the SPZ header says 0 Gaussians (byte 8)",
            ));
        }
        if self.count > i32::MAX as u32 || self.count as u64 > bound {
            return Err(Error::parse(
                path,
                Position::Byte(8),
                format!(
                    "the SPZ header claims {} Gaussians, more than a file of this size can hold (at most {bound}); the file is damaged or not SPZ",
                    self.count
                ),
            ));
        }
        if self.sh_degree > 4 {
            return Err(Error::parse(
                path,
                Position::Byte(12),
                format!("SH degree {} is not 0–4", self.sh_degree),
            ));
        }
        if self.version >= 2 && self.fractional_bits > 23 {
            return Err(Error::parse(
                path,
                Position::Byte(13),
                format!(
                    "{} fractional bits do not fit a 24-bit position",
                    self.fractional_bits
                ),
            ));
        }
        Ok(())
    }
}

/// Reads an SPZ file held in `bytes`.
pub(crate) fn read(
    path: &Path,
    bytes: &[u8],
    mut sink: Sink,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    let (header, positions, alphas) = if bytes.starts_with(MAGIC) {
        read_v4(path, bytes, &mut sink)?
    } else if bytes.starts_with(&GZIP) {
        read_gzip(path, bytes, &mut sink)?
    } else {
        return Err(Error::unknown(
            path,
            "an SPZ file starts with `NGSP` (version 4) or a gzip header (versions 1–3), and this one starts with neither",
        ));
    };
    decode(path, &header, &positions, &alphas, &mut sink)?;
    sink.finish(header.count as usize, header.describe())
}

/// Centers (RUB to RDF) and opacities into the sink.
fn decode(
    path: &Path,
    h: &Header,
    positions: &[u8],
    alphas: &[u8],
    sink: &mut Sink,
) -> Result<(), Error> {
    let n = h.count as usize;
    sink.reserve(n);
    // Version 1 has float16 positions and no use for the fractional bits (unchecked there).
    let scale = (0.5f64).powi(h.fractional_bits as i32) as f32;
    for (i, &a) in alphas.iter().enumerate().take(n) {
        let mut c = [0f32; 3];
        if h.version == 1 {
            for (k, v) in c.iter_mut().enumerate() {
                let o = 6 * i + 2 * k;
                *v = half_to_f32(u16::from_le_bytes([positions[o], positions[o + 1]]));
            }
        } else {
            for (k, v) in c.iter_mut().enumerate() {
                let o = 9 * i + 3 * k;
                let raw = positions[o] as u32
                    | (positions[o + 1] as u32) << 8
                    | (positions[o + 2] as u32) << 16;
                // Sign-extend the 24-bit value.
                let fixed = ((raw << 8) as i32) >> 8;
                *v = fixed as f32 * scale;
            }
        }
        // `0.0 - v` rather than `-v`: no negative zeros in the output.
        let c = [c[0], 0.0 - c[1], 0.0 - c[2]];
        let p = a as f32 / 255.0;
        let logit = (p / (1.0 - p)).ln();
        sink.push(c, a as f64 / 255.0, logit, || {
            Position::record("SPZ Gaussian", i, None)
        })?;
    }
    let _ = path;
    Ok(())
}

/// IEEE half to f32 (SPZ version 1 positions).
fn half_to_f32(h: u16) -> f32 {
    let sign = if h & 0x8000 != 0 { -1.0f32 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f32;
    match exp {
        0 => sign * frac * (2.0f32).powi(-24),
        31 if frac == 0.0 => sign * f32::INFINITY,
        31 => f32::NAN,
        e => sign * (1.0 + frac / 1024.0) * (2.0f32).powi(e - 15),
    }
}

type Decoded = (Header, Vec<u8>, Vec<u8>);

/// Versions 1–3: header and attributes inside one gzip stream.
fn read_gzip(path: &Path, bytes: &[u8], sink: &mut Sink) -> Result<Decoded, Error> {
    let mut gz = flate2::read::GzDecoder::new(bytes);
    let corrupt = |e: std::io::Error, at: u64| {
        Error::parse(
            path,
            Position::Byte(0),
            format!("the gzip stream is damaged (at decompressed byte {at}): {e}"),
        )
    };
    let mut head = [0u8; LEGACY_HEADER];
    let got = read_up_to(&mut gz, &mut head).map_err(|e| corrupt(e, 0))?;
    if got < LEGACY_HEADER {
        return Err(Error::truncated(
            path,
            Position::Byte(bytes.len() as u64),
            format!("the gzip stream holds {got} bytes, fewer than the 16-byte SPZ header"),
        ));
    }
    if &head[..4] != MAGIC {
        return Err(Error::parse(
            path,
            Position::Byte(0),
            "a gzip file, but what it holds does not start with the SPZ magic `NGSP`",
        ));
    }
    let h = Header::parse(&head);
    let per_point: u64 = h.sections().iter().map(|s| s.1).sum::<u64>() / (h.count.max(1) as u64);
    h.check(
        path,
        1..=3,
        (bytes.len() as u64 * MAX_RATIO) / per_point.max(1),
    )?;
    let mut at = LEGACY_HEADER as u64;
    let mut take = |name: &str, len: u64, keep: bool| -> Result<Vec<u8>, Error> {
        let mut out = Vec::new();
        let got = if keep {
            (&mut gz).take(len).read_to_end(&mut out)
        } else {
            std::io::copy(&mut (&mut gz).take(len), &mut std::io::sink()).map(|n| n as usize)
        }
        .map_err(|e| corrupt(e, at))? as u64;
        if got < len {
            return Err(Error::truncated(
                path,
                Position::Byte(bytes.len() as u64),
                format!(
                    "the gzip stream ends inside the {name} (decompressed byte {}; the header's {} Gaussians need {} bytes there)",
                    at + got,
                    h.count,
                    len
                ),
            ));
        }
        at += len;
        Ok(out)
    };
    let [pos, alpha, rest @ ..] = h.sections();
    let positions = take(pos.0, pos.1, true)?;
    let alphas = take(alpha.0, alpha.1, true)?;
    for (name, len) in rest {
        take(name, len, false)?;
    }
    // Reading on to the end checks the gzip CRC; extensions (flag 0x2) may follow.
    let mut tail = Vec::new();
    (&mut gz)
        .take(1 << 20)
        .read_to_end(&mut tail)
        .map_err(|e| corrupt(e, at))?;
    if h.flags & FLAG_EXTENSIONS != 0 {
        sink.warnings.push(extensions_warning(path));
    } else if !tail.is_empty() {
        sink.warnings.push(format!(
            "{}: {}{} bytes after the SPZ attributes were ignored (wrong count in the header?)",
            path.display(),
            if tail.len() == 1 << 20 { "over " } else { "" },
            tail.len()
        ));
    }
    Ok((h, positions, alphas))
}

fn extensions_warning(path: &Path) -> String {
    format!(
        "{}: the SPZ file carries extensions, which were ignored (an extension that changes the coordinate system would change the centers)",
        path.display()
    )
}

/// `read` until `buf` is full or the stream ends.
fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

/// Version 4: plain header, table of contents, one ZSTD stream per non-empty attribute.
fn read_v4(path: &Path, bytes: &[u8], sink: &mut Sink) -> Result<Decoded, Error> {
    let len = bytes.len() as u64;
    if bytes.len() < HEADER_V4 {
        return Err(Error::truncated(
            path,
            Position::Byte(len),
            format!("an SPZ version 4 header is 32 bytes, the file has {len}"),
        ));
    }
    let h = Header::parse(bytes);
    h.check(path, 4..=4, len * MAX_RATIO / 9)?;
    let num_streams = bytes[15] as usize;
    let toc = u32::from_le_bytes([bytes[16], bytes[17], bytes[18], bytes[19]]) as u64;
    let wanted: Vec<(&str, u64)> = h.sections().into_iter().filter(|s| s.1 > 0).collect();
    if num_streams != wanted.len() {
        return Err(Error::parse(
            path,
            Position::Byte(15),
            format!(
                "the header lists {num_streams} streams; SH degree {} needs {} (positions, alphas, colors, scales, rotations{})",
                h.sh_degree,
                wanted.len(),
                if h.sh_degree > 0 { ", SH" } else { "" }
            ),
        ));
    }
    let toc_end = toc + 16 * num_streams as u64;
    if toc < HEADER_V4 as u64 || toc_end > len {
        return Err(Error::parse(
            path,
            Position::Byte(16),
            format!(
                "the table of contents at byte {toc} ({} bytes) does not fit between the 32-byte header and the end of the file ({len} bytes)",
                16 * num_streams
            ),
        ));
    }
    if h.flags & FLAG_EXTENSIONS != 0 {
        sink.warnings.push(extensions_warning(path));
    }
    let u64_at = |o: u64| {
        let o = o as usize;
        u64::from_le_bytes(bytes[o..o + 8].try_into().unwrap_or([0; 8]))
    };
    let mut offset = toc_end;
    let mut streams = Vec::with_capacity(num_streams);
    for (i, &(name, need)) in wanted.iter().enumerate() {
        let entry = toc + 16 * i as u64;
        let (compressed, uncompressed) = (u64_at(entry), u64_at(entry + 8));
        if uncompressed != need {
            return Err(Error::parse(
                path,
                Position::Byte(entry + 8),
                format!(
                    "stream {i} ({name}) says {uncompressed} bytes uncompressed; {} Gaussians need {need}",
                    h.count
                ),
            ));
        }
        if compressed > len - offset {
            return Err(Error::truncated(
                path,
                Position::Byte(entry),
                format!(
                    "stream {i} ({name}) is {compressed} bytes from byte {offset}, past the end of the file ({len} bytes)"
                ),
            ));
        }
        streams.push((name, offset, compressed, need));
        offset += compressed;
    }
    if offset != len {
        sink.warnings.push(format!(
            "{}: {} bytes after the last SPZ stream were ignored",
            path.display(),
            len - offset
        ));
    }
    let unpack = |k: usize| -> Result<Vec<u8>, Error> {
        let (name, start, size, need) = streams[k];
        let src = &bytes[start as usize..(start + size) as usize];
        let bad = |msg: String| {
            Error::parse(
                path,
                Position::Byte(start),
                format!("the ZSTD stream of the {name}: {msg}"),
            )
        };
        let mut dec =
            ruzstd::decoding::StreamingDecoder::new(src).map_err(|e| bad(e.to_string()))?;
        let mut out = Vec::new();
        // One byte more than promised shows a stream that would go on.
        (&mut dec)
            .take(need + 1)
            .read_to_end(&mut out)
            .map_err(|e| bad(e.to_string()))?;
        if out.len() as u64 != need {
            return Err(bad(format!(
                "decompresses to {}{} bytes, the table of contents says {need}",
                if out.len() as u64 > need {
                    "more than "
                } else {
                    ""
                },
                out.len().min(need as usize)
            )));
        }
        Ok(out)
    };
    let positions = unpack(0)?;
    let alphas = unpack(1)?;
    Ok((h, positions, alphas))
}

/// An SPZ file from centers (in the PLY convention, RDF) and opacities in `[0, 1]`, for
/// tests and round trips: versions 1–3 as gzip, 4 as ZSTD streams. Colors, scales and
/// rotations are neutral; no SH.
pub fn encode_spz(version: u32, centers: &[[f32; 3]], opacity: &[f32]) -> Vec<u8> {
    assert!((1..=4).contains(&version) && centers.len() == opacity.len());
    let n = centers.len();
    let frac = 12u8;
    let mut positions = Vec::with_capacity(9 * n);
    for c in centers {
        let rub = [c[0], -c[1], -c[2]];
        for v in rub {
            if version == 1 {
                positions.extend_from_slice(&f32_to_half(v).to_le_bytes());
            } else {
                let fixed = (v * (1u32 << frac) as f32).round() as i32;
                positions.extend_from_slice(&fixed.to_le_bytes()[..3]);
            }
        }
    }
    let alphas: Vec<u8> = opacity
        .iter()
        .map(|a| (a * 255.0).round().clamp(0.0, 255.0) as u8)
        .collect();
    let colors = vec![128u8; 3 * n];
    let scales = vec![80u8; 3 * n];
    let rotations = if version >= 3 {
        // Smallest three with w (index 3) largest: identity.
        [3u8, 0, 0, 0].repeat(n)
    } else {
        vec![128u8; 3 * n]
    };
    let sections = [positions, alphas, colors, scales, rotations];
    let mut head = Vec::new();
    head.extend_from_slice(MAGIC);
    head.extend_from_slice(&version.to_le_bytes());
    head.extend_from_slice(&(n as u32).to_le_bytes());
    head.extend_from_slice(&[0, frac, 0]);
    if version < 4 {
        head.push(0);
        let mut raw = head;
        for s in &sections {
            raw.extend_from_slice(s);
        }
        let mut enc = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        std::io::Write::write_all(&mut enc, &raw).expect("in-memory write");
        return enc.finish().expect("in-memory write");
    }
    head.push(sections.len() as u8);
    head.extend_from_slice(&(HEADER_V4 as u32).to_le_bytes());
    head.resize(HEADER_V4, 0);
    let packed: Vec<Vec<u8>> = sections
        .iter()
        .map(|s| {
            ruzstd::encoding::compress_to_vec(&s[..], ruzstd::encoding::CompressionLevel::Fastest)
        })
        .collect();
    for (p, s) in packed.iter().zip(&sections) {
        head.extend_from_slice(&(p.len() as u64).to_le_bytes());
        head.extend_from_slice(&(s.len() as u64).to_le_bytes());
    }
    for p in packed {
        head.extend_from_slice(&p);
    }
    head
}

/// f32 to IEEE half, round to nearest (for the version 1 encoder).
fn f32_to_half(v: f32) -> u16 {
    let bits = v.to_bits();
    let sign = ((bits >> 16) & 0x8000) as u16;
    let a = v.abs();
    if a.is_nan() {
        return sign | 0x7e00;
    }
    if a >= 65520.0 {
        return sign | 0x7c00;
    }
    if a < 6.103_515_6e-5 {
        // Subnormal: multiples of 2^-24.
        return sign | (a * (1u32 << 24) as f32).round() as u16;
    }
    let e = a.log2().floor() as i32;
    let mut m = ((a / (2.0f32).powi(e) - 1.0) * 1024.0).round() as u32;
    let mut e = e;
    if m == 1024 {
        m = 0;
        e += 1;
    }
    sign | (((e + 15) as u16) << 10) | m as u16
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn half_floats_round_trip() {
        for v in [0.0f32, 1.0, -2.5, 0.333, 1000.0, -0.000_1, 65504.0] {
            let h = f32_to_half(v);
            let back = half_to_f32(h);
            assert!(
                (back - v).abs() <= v.abs() * 1e-3 + 1e-7,
                "{v} -> {h:#x} -> {back}"
            );
        }
        assert_eq!(half_to_f32(0x3c00), 1.0);
        assert_eq!(half_to_f32(0xc000), -2.0);
        assert_eq!(half_to_f32(0x7c00), f32::INFINITY);
    }
}
