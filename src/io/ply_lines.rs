//! Line segments as a PLY: a `vertex` element (x y z) and an `edge` element (vertex1
//! vertex2), what `write_lines` writes and MeshLab and CloudCompare show.

use std::path::Path;

use crate::geom::Segment;

use super::error::Error;
use super::format::{Detect, LineFormat, LineWriter, Origin, Parsed, Probe};
use super::ply::{self, PropKind};
use super::write::{write_lines_ply_layers, DEFAULT_LINE_COLOR};

pub(crate) static FORMAT: LineFormat = LineFormat {
    id: "ply",
    name: "PLY (vertex + edge)",
    extensions: &["ply"],
    summary: "`vertex` (x y z) and `edge` (vertex1 vertex2) elements, as `refine` writes them",
    help: Some("our `.ply` with edges"),
    hint: None,
    rank: 0,
    detect: Detect::Bytes(detect),
    parse: |path, bytes, _| parse_ply(path, bytes),
    read_folder: None,
};

pub(crate) static WRITER: LineWriter = LineWriter {
    format: &FORMAT,
    ext: "ply",
    help: "`.ply` (with an edge element)",
    write: |path, lines| write_lines_ply_layers(path, &[(lines, DEFAULT_LINE_COLOR)]),
};

fn detect(p: &Probe) -> bool {
    p.bytes.starts_with(b"ply\n") || p.bytes.starts_with(b"ply\r\n")
}

/// Our own PLY output: `vertex` (x y z) and `edge` (vertex1 vertex2) elements.
fn parse_ply(path: &Path, bytes: &[u8]) -> Result<Parsed, Error> {
    let (header, mut body) = ply::open_in_memory(path, bytes)?;
    let Some(ei) = header.element("edge") else {
        return Err(Error::missing(
            path,
            "the PLY has no `edge` element, so it holds points (a Gaussian model?), not line segments",
        ));
    };
    let Some(vi) = header.element("vertex") else {
        return Err(Error::missing(
            path,
            "the PLY has an `edge` but no `vertex` element",
        ));
    };
    let scalar = |e: usize, name: &str| -> Result<usize, Error> {
        let elem = &header.elements[e];
        match elem.prop(name) {
            Some(i) if matches!(elem.props[i].kind, PropKind::Scalar(_)) => Ok(i),
            _ => Err(Error::missing(
                path,
                format!(
                    "the `{}` element has no number property `{name}`",
                    elem.name
                ),
            )),
        }
    };
    let xyz = [scalar(vi, "x")?, scalar(vi, "y")?, scalar(vi, "z")?];
    let ends = [scalar(ei, "vertex1")?, scalar(ei, "vertex2")?];
    // Reserved by what the data can hold, never by the header's word alone.
    let have = (bytes.len() - header.len) as u64;
    let (v, e) = (&header.elements[vi], &header.elements[ei]);
    let mut points: Vec<[f64; 3]> = Vec::with_capacity(v.max_records(header.encoding, have));
    let mut edges: Vec<([f64; 2], ply::Loc)> =
        Vec::with_capacity(e.max_records(header.encoding, have));
    for (i, elem) in header.elements.iter().enumerate() {
        if i == vi {
            body.for_each(path, elem, &xyz, |loc, v| {
                if let Some(bad) = v.iter().find(|x| !x.is_finite()) {
                    return Err(Error::non_finite(
                        path,
                        loc.position("vertex"),
                        "line coordinate",
                        *bad,
                    ));
                }
                points.push([v[0], v[1], v[2]]);
                Ok(())
            })?;
        } else if i == ei {
            body.for_each(path, elem, &ends, |loc, v| {
                edges.push(([v[0], v[1]], loc));
                Ok(())
            })?;
        } else {
            body.skip(path, elem)?;
        }
    }
    body.finish(path, Some(bytes.len() as u64))?;
    let mut p = Parsed::new(Origin::Records("edge"));
    for (k, (e, loc)) in edges.iter().enumerate() {
        let mut end = [0usize; 2];
        for (slot, &x) in end.iter_mut().zip(e) {
            if x.fract() != 0.0 || x < 0.0 || x >= points.len() as f64 {
                return Err(Error::parse(
                    path,
                    loc.position("edge"),
                    format!(
                        "edge {k} refers to vertex {x}, but there are {} vertices",
                        points.len()
                    ),
                ));
            }
            *slot = x as usize;
        }
        p.segments
            .push(Segment::from_arrays(points[end[0]], points[end[1]]));
    }
    Ok(p)
}
