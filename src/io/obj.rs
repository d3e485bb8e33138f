//! Wavefront OBJ, read once for every reader of an OBJ file: line files (`v` and `l`
//! records, `lines.rs`), meshes (`v` and `f`: the synthetic scenes' mesh sampler) and the
//! vertices of ABC models (`eval::abc`). Other records (`vn`, `vt`, `o`, `g`, `s`,
//! `usemtl`, ...) and `#` comments are skipped.

use std::path::Path;

use super::error::{Error, Position};
use super::lines::{data_rows, number};

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
    pub indices: Result<Vec<i64>, String>,
}

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
fn index(tok: &str) -> Result<i64, String> {
    let head = tok.split('/').next().unwrap_or("");
    match head.parse::<i64>() {
        Ok(i) if i != 0 => Ok(i),
        _ => Err(format!("`{tok}` is not a vertex index")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        assert_eq!(r.faces[1].indices, Err("`x` is not a vertex index".into()));
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
