//! Wavefront OBJ, read once for every reader of an OBJ file: line files (`v` and `l`
//! records, this file's [`FORMAT`], which `write_lines` also writes), meshes (`v` and `f`: the synthetic scenes' mesh sampler) and the
//! vertices of ABC models (`eval::abc`). Other records (`vn`, `vt`, `o`, `g`, `s`,
//! `usemtl`, ...) and `#` comments are skipped.

use std::io::Write;
use std::path::Path;

use crate::geom::Segment;

use super::error::{Error, Position};
use super::format::{self, Detect, LineFormat, LineWriter, Origin, Parsed, Probe};
use super::text::{data_rows, number};
use super::write::{num, write_atomic};

pub(crate) static FORMAT: LineFormat = LineFormat {
    id: "obj",
    name: "OBJ",
    extensions: &["obj"],
    summary: "`v` and `l` records (Line3D++, LIMAP, ELSR); a file whose `l` records are \
              missing or broken falls back to consecutive vertex pairs, with a warning",
    help: Some("ELSR `.obj`"),
    hint: Some(".obj (v/l records)"),
    rank: 13,
    detect: Detect::Text(detect),
    parse: |path, bytes, _| parse_lines(path, format::text(path, bytes)?),
    read_folder: None,
};

pub(crate) static WRITER: LineWriter = LineWriter {
    format: &FORMAT,
    ext: "obj",
    help: "`.obj`",
    write,
};

/// Named `.obj`, or any `v` or `l` record.
fn detect(p: &Probe) -> bool {
    let obj_record = |r: &str| matches!(r.split_whitespace().next(), Some("v" | "l"));
    p.ext == "obj"
        || p.text
            .is_some_and(|t| data_rows(t).any(|(_, r)| obj_record(r)))
}

/// An `l` (polyline) or `f` (face) record.
#[derive(Clone, Debug, PartialEq)]
pub struct Element {
    /// 1-based line of the record.
    pub line: usize,
    /// How many `v` records came before it: where a negative index counts back from.
    pub defined: usize,
    /// The vertex indices as written (1-based, or negative), or why a corner is not one:
    /// its first corner that is not a non-zero whole number (`a`, `a/b`, `a//c` and
    /// `a/b/c` give `a`).
    pub indices: Result<Vec<i64>, BadIndex>,
}

/// A corner of an `l` or `f` record that is not a vertex index: the token as written.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
#[error("`{0}` is not a vertex index")]
pub struct BadIndex(pub String);

/// The records of an OBJ file that the readers use, in file order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Records {
    /// `(line, [x, y, z])` of each `v` record.
    pub vertices: Vec<(usize, [f64; 3])>,
    /// The `l` records.
    pub polylines: Vec<Element>,
    /// The `f` records.
    pub faces: Vec<Element>,
}

/// The `v`, `l` and `f` records of `text`; `path` names the file in errors. A `v` record
/// needs three finite numbers (`what` names them in the error: "line coordinate",
/// "vertex coordinate"); an element's indices are only checked to be numbers, each reader
/// deciding what a broken one means.
pub fn parse(path: &Path, text: &str, what: &'static str) -> Result<Records, Error> {
    let mut out = Records::default();
    for (line, row) in data_rows(text) {
        let mut toks = row.split_whitespace();
        match toks.next() {
            Some("v") => {
                let mut c = [0.0; 3];
                for (k, slot) in c.iter_mut().enumerate() {
                    let Some(t) = toks.next() else {
                        return Err(Error::parse(
                            path,
                            Position::Line(line),
                            format!("`v` record with {k} coordinates, expected 3"),
                        ));
                    };
                    let value = k + 2;
                    let x = number(path, t, line, value)?;
                    if !x.is_finite() {
                        let pos = Position::LineValue { line, value };
                        return Err(Error::non_finite(path, pos, what, x));
                    }
                    *slot = x;
                }
                out.vertices.push((line, c));
            }
            Some(kind @ ("l" | "f")) => {
                let element = Element {
                    line,
                    defined: out.vertices.len(),
                    indices: toks.map(index).collect(),
                };
                if kind == "l" {
                    out.polylines.push(element);
                } else {
                    out.faces.push(element);
                }
            }
            _ => {}
        }
    }
    Ok(out)
}

/// The vertex index of one corner (`3`, `3/7`, `3//2`, `-1`).
fn index(tok: &str) -> Result<i64, BadIndex> {
    let head = tok.split('/').next().unwrap_or("");
    match head.parse::<i64>() {
        Ok(i) if i != 0 => Ok(i),
        _ => Err(BadIndex(tok.to_string())),
    }
}

/// The segments of the `l` records (a polyline `l a b c` is the segments a-b and b-c).
fn parse_lines(path: &Path, text: &str) -> Result<Parsed, Error> {
    let obj = parse(path, text, "line coordinate")?;
    let verts = obj.vertices;
    let faces = obj.faces.len();
    let no_records = obj.polylines.is_empty();
    // The first broken `l` record, if any; else the records' indices, still unresolved.
    let mut broken: Option<(usize, String)> = None;
    let mut records: Vec<(usize, Vec<i64>)> = Vec::new();
    for e in obj.polylines {
        match e.indices {
            Err(what) => {
                broken.get_or_insert((e.line, what.to_string()));
            }
            Ok(idx) if idx.len() < 2 => {
                broken.get_or_insert((e.line, "an `l` record needs two vertex indices".into()));
            }
            Ok(idx) => records.push((e.line, idx)),
        }
    }
    let mut p = Parsed::new(Origin::Records(""));
    let mut lines = Vec::new();
    if broken.is_none() && !no_records {
        // Resolve 1-based and negative (relative to the end) indices; any miss is "broken".
        let nv = verts.len() as i64;
        'records: for (line, idx) in &records {
            let mut resolved = Vec::with_capacity(idx.len());
            for &i in idx {
                let r = if i > 0 { i - 1 } else { nv + i };
                if r < 0 || r >= nv {
                    broken = Some((
                        *line,
                        format!("vertex index {i} is out of range (the file has {nv} vertices)"),
                    ));
                    break 'records;
                }
                resolved.push(r as usize);
            }
            // A polyline `l a b c` is the segments a-b and b-c.
            for w in resolved.windows(2) {
                p.segments
                    .push(Segment::from_arrays(verts[w[0]].1, verts[w[1]].1));
                lines.push(*line);
            }
        }
    }
    if broken.is_some() || no_records {
        if no_records && faces > 0 {
            return Err(Error::unknown(
                path,
                format!("the OBJ has {faces} faces and no `l` records: a mesh, not line segments"),
            ));
        }
        if verts.is_empty() {
            return Err(Error::no_data(path, "the OBJ has no `v` records"));
        }
        let why = match &broken {
            Some((line, what)) => format!("line {line}: broken `l` record ({what})"),
            None => "no `l` records".to_string(),
        };
        let odd = if verts.len() % 2 == 1 {
            format!(
                "; the last vertex (line {}) has no partner and was ignored",
                verts[verts.len() - 1].0
            )
        } else {
            String::new()
        };
        p.warnings.push(format!(
            "{}: {why}: read the {} vertices as consecutive pairs instead{odd}",
            path.display(),
            verts.len()
        ));
        p.segments.clear();
        lines.clear();
        for pair in verts.chunks_exact(2) {
            p.segments.push(Segment::from_arrays(pair[0].1, pair[1].1));
            lines.push(pair[0].0);
        }
    }
    p.origin = Origin::Lines(lines);
    Ok(p)
}

fn write(path: &Path, lines: &[Segment]) -> Result<(), Error> {
    write_atomic(path, |w| {
        writeln!(w, "# {} line segments, written by linegs-gpu", lines.len())?;
        for (i, s) in lines.iter().enumerate() {
            writeln!(w, "v {} {} {}", num(s.p1.x), num(s.p1.y), num(s.p1.z))?;
            writeln!(w, "v {} {} {}", num(s.p2.x), num(s.p2.y), num(s.p2.z))?;
            writeln!(w, "l {} {}", 2 * i + 1, 2 * i + 2)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_polylines_and_negative_indices() {
        let p = parse_lines(
            Path::new("p.obj"),
            "v 0 0 0\nv 1 0 0\nv 1 1 0\nl 1 2 3\nl -1 -3\n",
        )
        .unwrap();
        assert_eq!(p.segments.len(), 3);
        assert_eq!(
            p.segments[1],
            Segment::from_arrays([1.0, 0.0, 0.0], [1.0, 1.0, 0.0])
        );
        assert_eq!(
            p.segments[2],
            Segment::from_arrays([1.0, 1.0, 0.0], [0.0, 0.0, 0.0])
        );
        assert!(p.warnings.is_empty());
    }

    #[test]
    fn records_keep_their_lines_and_the_vertices_before_them() {
        let text =
            "# c\nv 0 0 0\nv 1 0 0 # end\nl 1 -1\nvn 0 0 1\nv 0 1 0\nf 1/1 2//3 -1\nf 1 x 2\n";
        let r = parse(Path::new("a.obj"), text, "vertex coordinate").unwrap();
        assert_eq!(r.vertices.len(), 3);
        assert_eq!(r.vertices[1], (3, [1.0, 0.0, 0.0]));
        assert_eq!(
            r.polylines,
            [Element {
                line: 4,
                defined: 2,
                indices: Ok(vec![1, -1]),
            }]
        );
        assert_eq!(r.faces[0].indices, Ok(vec![1, 2, -1]));
        assert_eq!(r.faces[0].defined, 3);
        let bad = r.faces[1].indices.clone().unwrap_err();
        assert_eq!(bad, BadIndex("x".into()));
        assert_eq!(bad.to_string(), "`x` is not a vertex index");
    }

    #[test]
    fn a_bad_vertex_is_an_error_at_its_line_and_value() {
        let p = Path::new("m.obj");
        let e = parse(p, "v 0 0 0\nv 1 0\n", "vertex coordinate").unwrap_err();
        assert!(e.to_string().contains("m.obj: line 2"), "{e}");
        let e = parse(p, "v 0 inf 0\n", "vertex coordinate").unwrap_err();
        assert!(e.to_string().contains("line 1, value 3"), "{e}");
        assert!(
            e.to_string().contains("vertex coordinate is not finite"),
            "{e}"
        );
    }
}
