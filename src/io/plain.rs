//! Plain text: six numbers a row, `x1 y1 z1 x2 y2 z2`, separated by whitespace or commas,
//! `#` comments. Read and written.

use std::io::Write;
use std::path::Path;

use crate::geom::Segment;

use super::error::{Error, Position};
use super::format::{self, Detect, LineFormat, LineWriter, Origin, Parsed, Probe};
use super::text::{coord, data_rows, plain_tokens};
use super::write::{num, write_atomic};

pub(crate) static FORMAT: LineFormat = LineFormat {
    id: "plain",
    name: "plain text (x1 y1 z1 x2 y2 z2)",
    extensions: &["txt"],
    summary: "6 numbers a row (whitespace or commas), `#` comments",
    help: Some("plain text (6 numbers a row)"),
    hint: Some("plain text with 6 numbers per row"),
    rank: 14,
    detect: Detect::Text(detect),
    parse: |path, bytes, _| parse_plain(path, format::text(path, bytes)?),
    read_folder: None,
};

pub(crate) static WRITER: LineWriter = LineWriter {
    format: &FORMAT,
    ext: "txt",
    help: "`.txt` (6 numbers a row)",
    write,
};

/// The first data row is 6 numbers.
fn detect(p: &Probe) -> bool {
    let Some((_, first)) = p.text.and_then(|t| data_rows(t).next()) else {
        return false;
    };
    let toks: Vec<&str> = plain_tokens(first).collect();
    toks.len() == 6 && toks.iter().all(|t| t.parse::<f64>().is_ok())
}

pub(crate) fn parse_plain(path: &Path, text: &str) -> Result<Parsed, Error> {
    let mut lines = Vec::new();
    let mut p = Parsed::new(Origin::Records(""));
    let mut v = [0.0; 6];
    for (line, row) in data_rows(text) {
        let mut k = 0;
        for tok in plain_tokens(row) {
            if k < 6 {
                v[k] = coord(path, tok, line, k + 1)?;
            }
            k += 1;
        }
        if k != 6 {
            return Err(Error::parse(
                path,
                Position::Line(line),
                format!("expected 6 numbers (x1 y1 z1 x2 y2 z2), found {k}"),
            ));
        }
        p.segments
            .push(Segment::from_arrays([v[0], v[1], v[2]], [v[3], v[4], v[5]]));
        lines.push(line);
    }
    p.origin = Origin::Lines(lines);
    Ok(p)
}

fn write(path: &Path, lines: &[Segment]) -> Result<(), Error> {
    write_atomic(path, |w| {
        writeln!(
            w,
            "# x1 y1 z1 x2 y2 z2 ({} segments, linegs-gpu)",
            lines.len()
        )?;
        for s in lines {
            writeln!(
                w,
                "{} {} {} {} {} {}",
                num(s.p1.x),
                num(s.p1.y),
                num(s.p1.z),
                num(s.p2.x),
                num(s.p2.y),
                num(s.p2.z)
            )?;
        }
        Ok(())
    })
}
