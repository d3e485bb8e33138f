//! What the text formats share: data rows without comments, tokens, and numbers that
//! name their line and value when they are not numbers (or, for coordinates, not finite).

use std::path::Path;

use super::error::{Error, Position};

/// Text rows without comments and blanks: (1-based line, content).
pub(crate) fn data_rows(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().filter_map(|(i, l)| {
        let l = l.split('#').next().unwrap_or("").trim();
        (!l.is_empty()).then_some((i + 1, l))
    })
}

/// Plain-text values are separated by whitespace or commas (CSV exports).
pub(crate) fn plain_tokens(row: &str) -> impl Iterator<Item = &str> {
    row.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
}

pub(crate) fn number(path: &Path, tok: &str, line: usize, value: usize) -> Result<f64, Error> {
    tok.parse::<f64>().map_err(|_| {
        Error::parse(
            path,
            Position::LineValue { line, value },
            format!("`{tok}` is not a number"),
        )
    })
}

/// A coordinate: a number, and finite (docs/formats.md: NaN/Inf line coordinates are errors).
pub(crate) fn coord(path: &Path, tok: &str, line: usize, value: usize) -> Result<f64, Error> {
    let x = number(path, tok, line, value)?;
    if !x.is_finite() {
        return Err(Error::non_finite(
            path,
            Position::LineValue { line, value },
            "line coordinate",
            x,
        ));
    }
    Ok(x)
}
