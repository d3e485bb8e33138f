//! SuperSplat / PlayCanvas compressed PLY (SuperSplat's default export, read by Brush and
//! the PlayCanvas engine): a `chunk` element with the bounds of every 256 splats, then a
//! `vertex` element of packed 32-bit words (and optionally an `sh` element of bytes).
//!
//! `packed_position` holds x in bits 21–31 (11 bits), y in bits 11–20 (10 bits) and z in
//! bits 0–10 (11 bits), each the fraction `v / (2^bits - 1)` of its chunk's `[min, max]`;
//! `packed_color`'s low byte is the opacity in `[0, 1]` (sigmoid already applied). The
//! decode below follows PlayCanvas' splat-transform (in f64, as JavaScript computes, then
//! rounded to f32), so centers and opacity logits come out bit for bit as that tool writes
//! them in an uncompressed PLY (tested on all 90,854 splats of the guitar model).

use std::path::Path;

use super::error::{Error, Position};
use super::format::{GaussianFormat, GaussianRead};
use super::ply::{self, Element, Encoding, GaussianCloud, Header, PropKind, Scalar};
use super::sink::Sink;

pub(crate) static FORMAT: GaussianFormat = GaussianFormat {
    id: "ply-compressed",
    name: "SuperSplat / PlayCanvas compressed PLY",
    extensions: &["ply"],
    summary: "`chunk` + `packed_position`: the centers bit for bit as splat-transform decodes \
              them",
    help: "SuperSplat compressed `.ply`",
    variant: Some("SuperSplat compressed"),
    family: "PLY",
    hint: None,
    sniff_hint: None,
    sniff: |path, head, len| {
        Ok(head.starts_with(b"ply")
            && is_compressed(&ply::parse_header(path, head, head.len() as u64 == len)?))
    },
    by_extension: false,
    is_ply: true,
    read: GaussianRead::Bytes(read),
};

/// Splats per chunk.
const CHUNK_SIZE: usize = 256;

/// A PLY whose `vertex` has `packed_position` and which has a `chunk` element.
pub(crate) fn is_compressed(h: &Header) -> bool {
    h.element("chunk").is_some()
        && h.element("vertex")
            .is_some_and(|v| h.elements[v].prop("packed_position").is_some())
}

/// Byte offset of property `i` in a fixed-size record.
fn offset(e: &Element, i: usize) -> usize {
    e.props[..i]
        .iter()
        .map(|p| match p.kind {
            PropKind::Scalar(s) => s.size(),
            PropKind::List { .. } => 0,
        })
        .sum()
}

pub(crate) fn read(
    path: &Path,
    bytes: &[u8],
    mut sink: Sink,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    let header = ply::parse_header(path, bytes, true)?;
    if header.encoding != Encoding::BinaryLe {
        return Err(Error::parse(
            path,
            Position::Line(2),
            format!(
                "a compressed PLY (chunk + packed_position) must be binary_little_endian, this one is {}",
                header.encoding.name()
            ),
        ));
    }
    // Where every element's records start; all have fixed-size records.
    let mut starts = Vec::with_capacity(header.elements.len());
    let mut at = header.len as u64;
    for e in &header.elements {
        let Some(stride) = e.stride() else {
            return Err(Error::parse(
                path,
                Position::Line(e.line),
                format!(
                    "element `{}` has a list property; a compressed PLY has fixed-size records only",
                    e.name
                ),
            ));
        };
        starts.push(at);
        // Saturating: a lying count must not wrap around to a small length.
        let len = (stride as u64).saturating_mul(e.count as u64);
        if at.saturating_add(len) > bytes.len() as u64 {
            let index = ((bytes.len() as u64).saturating_sub(at) / stride.max(1) as u64) as usize;
            return Err(Error::truncated(
                path,
                Position::record(&e.name, index, Some(at + index as u64 * stride as u64)),
                format!(
                    "the header promises {} {} records of {stride} bytes from byte {at}, but the file has {} bytes",
                    e.count,
                    e.name,
                    bytes.len()
                ),
            ));
        }
        at += len;
    }
    let ci = header.element("chunk").unwrap_or(0);
    let vi = header.element("vertex").unwrap_or(0);
    let chunk = &header.elements[ci];
    let vertex = &header.elements[vi];
    let n = vertex.count;
    if chunk.count < n.div_ceil(CHUNK_SIZE) {
        return Err(Error::parse(
            path,
            Position::Line(chunk.line),
            format!(
                "{n} packed splats need {} chunks of {CHUNK_SIZE}, the header has `element chunk {}`",
                n.div_ceil(CHUNK_SIZE),
                chunk.count
            ),
        ));
    }
    let chunk_prop = |name: &str| -> Result<(usize, Scalar), Error> {
        match chunk.prop(name).map(|i| (i, chunk.props[i].kind)) {
            Some((i, PropKind::Scalar(s))) => Ok((offset(chunk, i), s)),
            _ => Err(Error::missing(
                path,
                format!("the `chunk` element of a compressed PLY has no `{name}` property"),
            )),
        }
    };
    let bounds = ["min_x", "min_y", "min_z", "max_x", "max_y", "max_z"]
        .map(chunk_prop)
        .into_iter()
        .collect::<Result<Vec<_>, _>>()?;
    let word = |name: &str| -> Result<usize, Error> {
        match vertex.prop(name).map(|i| (i, vertex.props[i].kind)) {
            Some((i, PropKind::Scalar(Scalar::U32))) => Ok(offset(vertex, i)),
            Some(_) => Err(Error::parse(
                path,
                Position::Line(vertex.line),
                format!("vertex property `{name}` of a compressed PLY must be `uint`"),
            )),
            None => Err(Error::missing(
                path,
                format!("the `vertex` element of a compressed PLY has no `{name}` property"),
            )),
        }
    };
    let pos_off = word("packed_position")?;
    let color_off = word("packed_color")?;
    let c_stride = chunk.stride().unwrap_or(0);
    let v_stride = vertex.stride().unwrap_or(0);
    let (c_start, v_start) = (starts[ci] as usize, starts[vi] as usize);
    sink.reserve(n);
    let mut lo_hi = [0f64; 6];
    for i in 0..n {
        if i % CHUNK_SIZE == 0 {
            let rec = &bytes[c_start + (i / CHUNK_SIZE) * c_stride..];
            for (slot, &(o, s)) in lo_hi.iter_mut().zip(&bounds) {
                *slot = s.decode(&rec[o..], false);
            }
        }
        let rec = &bytes[v_start + i * v_stride..];
        let u32_at = |o: usize| u32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]]);
        let p = u32_at(pos_off);
        let t = [unorm(p >> 21, 11), unorm(p >> 11, 10), unorm(p, 11)];
        let mut c = [0f32; 3];
        for k in 0..3 {
            c[k] = lerp(lo_hi[k], lo_hi[k + 3], t[k]) as f32;
        }
        let w = unorm(u32_at(color_off), 8);
        let logit = (-(1.0 / w - 1.0).ln()) as f32;
        sink.push(c, w, logit, || {
            Position::record("vertex", i, Some((v_start + i * v_stride) as u64))
        })?;
    }
    sink.finish(
        n,
        format!(
            "SuperSplat compressed PLY ({}, {} chunks of {CHUNK_SIZE})",
            header.format(),
            chunk.count
        ),
    )
}

/// The low `bits` of `v` as a fraction of their maximum, in f64 as JavaScript computes it.
#[inline]
fn unorm(v: u32, bits: u32) -> f64 {
    let max = (1u32 << bits) - 1;
    (v & max) as f64 / max as f64
}

/// splat-transform's `lerp`: `a * (1 - t) + b * t`.
#[inline]
fn lerp(a: f64, b: f64, t: f64) -> f64 {
    a * (1.0 - t) + b * t
}
