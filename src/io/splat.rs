//! antimatter15 `.splat` (the WebGL viewer's format, used by many web demos): no header,
//! 32 bytes a splat — position f32 x3, scale f32 x3, RGBA u8 x4 (A is the opacity in
//! `[0, 1]`), rotation u8 x4. Positions are in the frame of the PLY it was made from.

use std::path::Path;

use super::error::{Error, Position};
use super::format::{GaussianFormat, GaussianRead};
use super::ply::GaussianCloud;
use super::sink::Sink;

pub(crate) static FORMAT: GaussianFormat = GaussianFormat {
    id: "splat",
    name: "antimatter15 .splat",
    extensions: &["splat"],
    summary: "by extension (no signature), 32 bytes a splat",
    help: "antimatter15 `.splat`",
    variant: None,
    family: ".splat",
    hint: Some("antimatter15 .splat"),
    sniff_hint: Some("antimatter15 .splat (by extension)"),
    sniff: |_, _, _| Ok(false),
    by_extension: true,
    is_ply: false,
    read: GaussianRead::Bytes(read),
};

pub(crate) const RECORD: usize = 32;

pub(crate) fn read(
    path: &Path,
    bytes: &[u8],
    mut sink: Sink,
) -> Result<(GaussianCloud, Option<Vec<f32>>), Error> {
    if !bytes.len().is_multiple_of(RECORD) {
        let whole = bytes.len() / RECORD;
        return Err(Error::truncated(
            path,
            Position::record("splat", whole, Some((whole * RECORD) as u64)),
            format!(
                "a .splat file is 32 bytes a splat, and this one has {} bytes ({whole} whole splats and {} bytes left over)",
                bytes.len(),
                bytes.len() % RECORD
            ),
        ));
    }
    let n = bytes.len() / RECORD;
    sink.reserve(n);
    for (i, rec) in bytes.chunks_exact(RECORD).enumerate() {
        let f = |o: usize| f32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]]);
        let a = rec[27];
        let p = a as f32 / 255.0;
        sink.push(
            [f(0), f(4), f(8)],
            a as f64 / 255.0,
            (p / (1.0 - p)).ln(),
            || Position::record("splat", i, Some((i * RECORD) as u64)),
        )?;
    }
    sink.finish(
        n,
        format!("antimatter15 .splat ({n} splats of {RECORD} bytes)"),
    )
}
