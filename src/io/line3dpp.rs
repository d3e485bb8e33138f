//! Line3D++ `saveTXT` files: one 3D line a row, `n` segments (`P1 P2`), then `m` 2D
//! residuals (`camID segID x1 y1 x2 y2`). The rows are kept as the segments' groups (the
//! collinear merge uses them) and the residuals as LIMAP-style supports.

use std::path::Path;

use crate::geom::Segment;

use super::error::{Error, Position};
use super::format::{self, Detect, LineFormat, Origin, Parsed, Probe};
use super::input::read_input;
use super::limap::Support;
use super::text::{coord, data_rows};

pub(crate) static FORMAT: LineFormat = LineFormat {
    id: "line3dpp",
    name: "Line3D++ text",
    extensions: &["txt"],
    summary: "`n`, then `n` endpoint pairs, then the 2D residuals; one 3D line a row (its \
              line groups are kept for the collinear merge, its residuals as supports)",
    help: Some("Line3D++ `.txt`/`.obj`/`.stl`"),
    hint: Some("Line3D++ .txt"),
    rank: 15,
    detect: Detect::Text(detect),
    parse: |path, bytes, _| parse_line3dpp(path, format::text(path, bytes)?),
    read_folder: None,
};

/// The first data row reads as a Line3D++ row.
fn detect(p: &Probe) -> bool {
    p.text
        .and_then(|t| data_rows(t).next())
        .is_some_and(|(_, first)| looks_like_line3dpp(first))
}

/// `n`, then `6n` numbers, then an integer `m` where the row says it is.
fn looks_like_line3dpp(row: &str) -> bool {
    let toks: Vec<&str> = row.split_whitespace().collect();
    let Some(n) = toks.first().and_then(|t| t.parse::<usize>().ok()) else {
        return false;
    };
    // `n < len / 6` first, so a huge count cannot overflow `6 n`.
    n >= 1
        && n < toks.len() / 6 + 1
        && toks.len() > 1 + 6 * n
        && toks[1..=6 * n].iter().all(|t| t.parse::<f64>().is_ok())
        && toks[1 + 6 * n].parse::<usize>().is_ok()
}

/// Line3D++ `saveTXT`: per row `n  (P1 P2) x n  m  (camID segID x1 y1 x2 y2) x m`.
pub(crate) fn parse_line3dpp(path: &Path, text: &str) -> Result<Parsed, Error> {
    let mut lines = Vec::new();
    let mut groups = Vec::new();
    let mut p = Parsed::new(Origin::Records(""));
    for (group, (line, row)) in data_rows(text).enumerate() {
        let toks: Vec<&str> = row.split_whitespace().collect();
        let count = |i: usize, what: &str| -> Result<usize, Error> {
            let Some(t) = toks.get(i) else {
                return Err(Error::parse(
                    path,
                    Position::Line(line),
                    format!(
                        "Line3D++ row ends after {} values, where the {what} should be",
                        toks.len()
                    ),
                ));
            };
            t.parse::<usize>().map_err(|_| {
                Error::parse(
                    path,
                    Position::LineValue { line, value: i + 1 },
                    format!("expected the {what} (a non-negative integer), found `{t}`"),
                )
            })
        };
        let n = count(0, "segment count n")?;
        // Checked before `6 n` is computed, so a huge count cannot overflow it.
        if n > toks.len() / 6 {
            return Err(Error::parse(
                path,
                Position::Line(line),
                format!(
                    "Line3D++ row says n = {n} segments, but the row has only {} values",
                    toks.len()
                ),
            ));
        }
        let m = count(1 + 6 * n, "residual count m")?;
        let need = 2 + 6 * n as u128 + 6 * m as u128;
        if toks.len() as u128 != need {
            return Err(Error::parse(
                path,
                Position::Line(line),
                format!(
                    "Line3D++ row with n = {n} segments and m = {m} residuals needs 2 + 6n + 6m = {need} values, found {}",
                    toks.len()
                ),
            ));
        }
        for s in 0..n {
            let mut v = [0.0; 6];
            for (k, slot) in v.iter_mut().enumerate() {
                let i = 1 + 6 * s + k;
                *slot = coord(path, toks[i], line, i + 1)?;
            }
            p.segments
                .push(Segment::from_arrays([v[0], v[1], v[2]], [v[3], v[4], v[5]]));
            lines.push(line);
            groups.push(group as u32);
        }
    }
    p.origin = Origin::Lines(lines);
    p.groups = Some(groups);
    Ok(p)
}

/// The 2D observations of every segment of a Line3D++ `.txt`, in file order: each 3D
/// line's residuals (`camID segID p1x p1y p2x p2y`) as LIMAP supports (image = camera id,
/// line = 2D segment id), shared by the line's segments.
pub fn read_line3dpp_supports(path: &Path) -> Result<Vec<Vec<Support>>, Error> {
    let bytes = read_input(path)?;
    let text = String::from_utf8_lossy(&bytes);
    // The reader has checked the counts; a file changed since is refused here.
    parse_line3dpp(path, &text)?;
    let mut out = Vec::new();
    for (_, row) in data_rows(&text) {
        let toks: Vec<&str> = row.split_whitespace().collect();
        let n: usize = toks[0].parse().unwrap_or(0);
        let m: usize = toks[1 + 6 * n].parse().unwrap_or(0);
        let obs: Vec<Support> = (0..m)
            .map(|k| {
                let t = &toks[2 + 6 * n + 6 * k..2 + 6 * n + 6 * k + 6];
                let f = |i: usize| t[i].parse::<f64>().unwrap_or(f64::NAN);
                Support {
                    image_id: t[0].parse().unwrap_or(-1),
                    line_id: t[1].parse().unwrap_or(-1),
                    line2d: Some([f(2), f(3), f(4), f(5)]),
                }
            })
            .collect();
        for _ in 0..n {
            out.push(obs.clone());
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn line3dpp_counts_are_checked() {
        let p = Path::new("l.txt");
        let ok = parse_line3dpp(p, "2 0 0 0 1 0 0 1 0 0 2 0 0 1 0 7 1 2 3 4\n").unwrap();
        assert_eq!(ok.segments.len(), 2);
        assert_eq!(ok.groups, Some(vec![0, 0]));
        let e = parse_line3dpp(p, "1 0 0 0 1 0 0 1 0 7 1 2 3\n").unwrap_err();
        assert_eq!(e.position(), Some(&Position::Line(1)));
        assert!(
            e.to_string()
                .contains("needs 2 + 6n + 6m = 14 values, found 13"),
            "{e}"
        );
        // Counts near usize::MAX must be rejected, not overflow `6 n` or `6 m`.
        let e = parse_line3dpp(p, "18446744073709551615 0 0 0 1 1 1 0\n").unwrap_err();
        assert!(
            e.to_string()
                .contains("n = 18446744073709551615 segments, but the row has only 8 values"),
            "{e}"
        );
        let e = parse_line3dpp(p, "1 0 0 0 1 1 1 18446744073709551615 1\n").unwrap_err();
        assert!(
            e.to_string()
                .contains("needs 2 + 6n + 6m = 110680464442257309698 values"),
            "{e}"
        );
        assert!(!looks_like_line3dpp("18446744073709551615 0 0 0 1 1 1 0"));
    }
}
