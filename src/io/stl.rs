//! Line3D++ `.stl`: every segment a degenerate facet `P1 P2 P1` (other tools repeat `P2`),
//! ASCII or binary (an 80-byte header, a facet count, 50 bytes a facet). Read and written.

use std::io::Write;
use std::path::Path;

use crate::geom::Segment;

use super::error::{Error, Position};
use super::format::{self, Detect, LineFormat, LineWriter, Origin, Parsed, Probe};
use super::text::{coord, data_rows};
use super::write::write_atomic;

pub(crate) static FORMAT: LineFormat = LineFormat {
    id: "stl",
    name: "STL",
    extensions: &["stl"],
    summary: "Line3D++ `.stl`: degenerate facets `P1 P2 P1`, ASCII or binary (a binary file \
              by its size, or by the extension where the size is wrong)",
    help: None,
    hint: Some(".stl (ASCII or binary, degenerate line facets)"),
    rank: 2,
    detect: Detect::Bytes(detect),
    parse: |path, bytes, _| {
        if is_ascii_stl(bytes) {
            parse_ascii_stl(path, format::text(path, bytes)?)
        } else {
            parse_binary_stl(path, bytes)
        }
    },
    read_folder: None,
};

pub(crate) static WRITER: LineWriter = LineWriter {
    format: &FORMAT,
    ext: "stl",
    help: "`.stl`",
    write,
};

/// A binary STL by its size, an ASCII one by its first word; or binary content named
/// `.stl` whose size does not match its count (a broken STL, for the reader to name).
fn detect(p: &Probe) -> bool {
    binary_stl_count(p.bytes).is_some()
        || is_ascii_stl(p.bytes)
        || (p.text.is_none() && p.ext == "stl")
}

/// ASCII STL starts with `solid` and never holds a NUL byte; binary STL headers may start
/// with `solid` too, but their facet attribute bytes are almost always zero.
fn is_ascii_stl(bytes: &[u8]) -> bool {
    let start = bytes
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(0);
    bytes[start..].starts_with(b"solid")
        && !bytes.contains(&0)
        && std::str::from_utf8(bytes).is_ok()
}

/// A binary STL is an 80-byte header, a facet count, and exactly 50 bytes per facet.
fn binary_stl_count(bytes: &[u8]) -> Option<u32> {
    if bytes.len() < 84 {
        return None;
    }
    let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]);
    (84 + 50 * n as u64 == bytes.len() as u64).then_some(n)
}

/// Line3D++ writes each segment as the facet `P1 P2 P1`; other tools repeat `P2`. Any facet
/// with two equal corners is a segment between the other two; three distinct corners are a
/// real triangle, which a line file must not contain.
fn facet_segment(v: &[[f64; 3]; 3]) -> Option<Segment> {
    let (a, b) = if v[2] == v[0] || v[2] == v[1] {
        (v[0], v[1])
    } else if v[0] == v[1] {
        (v[0], v[2])
    } else {
        return None;
    };
    Some(Segment::from_arrays(a, b))
}

fn parse_ascii_stl(path: &Path, text: &str) -> Result<Parsed, Error> {
    let mut p = Parsed::new(Origin::Records(""));
    let mut lines = Vec::new();
    let mut corners: Vec<[f64; 3]> = Vec::with_capacity(3);
    let mut facet_line: Option<usize> = None;
    let mut ended = false;
    let mut last = 0;
    for (line, row) in data_rows(text) {
        last = line;
        let mut toks = row.split_whitespace();
        let bad = |msg: String| Error::parse(path, Position::Line(line), msg);
        match toks.next() {
            Some("solid") | Some("outer") | Some("endloop") => {}
            Some("facet") => {
                if let Some(open) = facet_line {
                    return Err(bad(format!(
                        "`facet` inside the facet opened at line {open}"
                    )));
                }
                facet_line = Some(line);
                corners.clear();
            }
            Some("vertex") => {
                if facet_line.is_none() {
                    return Err(bad("`vertex` outside a facet".into()));
                }
                let mut c = [0.0; 3];
                for (k, slot) in c.iter_mut().enumerate() {
                    let Some(t) = toks.next() else {
                        return Err(bad(format!("`vertex` with {k} coordinates, expected 3")));
                    };
                    *slot = coord(path, t, line, k + 2)?;
                }
                corners.push(c);
            }
            Some("endfacet") => {
                let Some(open) = facet_line.take() else {
                    return Err(bad("`endfacet` without `facet`".into()));
                };
                let Ok(v) = <[[f64; 3]; 3]>::try_from(corners.as_slice()) else {
                    return Err(bad(format!(
                        "the facet opened at line {open} has {} vertices, expected 3",
                        corners.len()
                    )));
                };
                let Some(s) = facet_segment(&v) else {
                    return Err(bad(format!(
                        "the facet opened at line {open} is a triangle (three distinct corners), not a line facet P1 P2 P1"
                    )));
                };
                p.segments.push(s);
                lines.push(open);
            }
            Some("endsolid") => {
                ended = true;
                break;
            }
            Some(other) => return Err(bad(format!("unexpected `{other}` in an ASCII STL"))),
            None => {}
        }
    }
    if !ended {
        return Err(Error::truncated(
            path,
            Position::Line(last + 1),
            match facet_line {
                Some(open) => format!("inside the facet opened at line {open}"),
                None => "no `endsolid` line".to_string(),
            },
        ));
    }
    p.origin = Origin::Lines(lines);
    Ok(p)
}

fn parse_binary_stl(path: &Path, bytes: &[u8]) -> Result<Parsed, Error> {
    if bytes.len() < 84 {
        return Err(Error::truncated(
            path,
            Position::Byte(bytes.len() as u64),
            "a binary STL needs an 80-byte header and a facet count (84 bytes)",
        ));
    }
    let n = u32::from_le_bytes([bytes[80], bytes[81], bytes[82], bytes[83]]) as usize;
    let need = 84 + 50 * n as u64;
    if (bytes.len() as u64) < need {
        let index = (bytes.len() - 84) / 50;
        return Err(Error::truncated(
            path,
            Position::record("facet", index, Some(84 + 50 * index as u64)),
            format!(
                "the header promises {n} facets ({need} bytes) but the file has {} bytes",
                bytes.len()
            ),
        ));
    }
    if (bytes.len() as u64) > need {
        return Err(Error::parse(
            path,
            Position::Byte(need),
            format!(
                "{} bytes after the {n} facets the header announces (wrong facet count?)",
                bytes.len() as u64 - need
            ),
        ));
    }
    let mut p = Parsed::new(Origin::Records("facet"));
    for (i, rec) in bytes[84..].chunks_exact(50).enumerate() {
        let mut v = [[0.0f64; 3]; 3];
        for (c, corner) in v.iter_mut().enumerate() {
            for (k, slot) in corner.iter_mut().enumerate() {
                // Skip the 12-byte normal; corners follow as f32 triples.
                let o = 12 + 12 * c + 4 * k;
                let x = f32::from_le_bytes([rec[o], rec[o + 1], rec[o + 2], rec[o + 3]]) as f64;
                if !x.is_finite() {
                    return Err(Error::non_finite(
                        path,
                        Position::record("facet", i, Some(84 + 50 * i as u64 + o as u64)),
                        "line coordinate",
                        x,
                    ));
                }
                *slot = x;
            }
        }
        let Some(s) = facet_segment(&v) else {
            return Err(Error::parse(
                path,
                Position::record("facet", i, Some(84 + 50 * i as u64)),
                "a triangle (three distinct corners), not a line facet P1 P2 P1",
            ));
        };
        p.segments.push(s);
    }
    Ok(p)
}

fn write(path: &Path, lines: &[Segment]) -> Result<(), Error> {
    write_atomic(path, |w| {
        // Line3D++'s saveSTL layout: one degenerate facet P1 P2 P1 per segment.
        writeln!(w, "solid lineModel")?;
        for s in lines {
            writeln!(w, " facet normal 1.0e+000 0.0e+000 0.0e+000")?;
            writeln!(w, "  outer loop")?;
            for p in [s.p1, s.p2, s.p1] {
                writeln!(w, "   vertex {:e} {:e} {:e}", p.x, p.y, p.z)?;
            }
            writeln!(w, "  endloop")?;
            writeln!(w, " endfacet")?;
        }
        writeln!(w, "endsolid lineModel")
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn binary_stl_count_must_match_size() {
        let mut b = vec![0u8; 84 + 100];
        b[80] = 2;
        assert_eq!(binary_stl_count(&b), Some(2));
        b[80] = 3;
        assert_eq!(binary_stl_count(&b), None);
    }

    #[test]
    fn facets_with_a_repeated_corner_are_segments() {
        let a = [0.0, 0.0, 0.0];
        let b = [1.0, 0.0, 0.0];
        let c = [0.0, 1.0, 0.0];
        assert_eq!(facet_segment(&[a, b, a]), Some(Segment::from_arrays(a, b)));
        assert_eq!(facet_segment(&[a, b, b]), Some(Segment::from_arrays(a, b)));
        assert_eq!(facet_segment(&[a, a, b]), Some(Segment::from_arrays(a, b)));
        assert_eq!(facet_segment(&[a, b, c]), None);
    }
}
