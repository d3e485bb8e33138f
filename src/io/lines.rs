//! Line segments in every format of docs/formats.md: the formats listed in `registry.rs`,
//! each chosen by content (and, where content alone cannot tell, by extension; never by
//! folder names), and the writers chosen by the output's extension.

use std::path::Path;
use std::sync::LazyLock;

use crate::geom::{LineSet, Segment, MIN_LENGTH};

use super::error::Error;
use super::format::{extension, Detect, LineFormat, LineOptions, LineWriter, Parsed, Probe};
use super::input::open_input;
use super::ply;
use super::registry::join_or;
use super::registry::{LINE_FORMATS, LINE_WRITERS};
use super::text::{data_rows, plain_tokens};
use super::write::check_finite;

/// Segments read from a file, and what was dropped on the way.
#[derive(Clone, Debug, PartialEq)]
pub struct LineFile {
    /// Valid segments only; `groups` is `Some` for Line3D++ `.txt` (row index per segment).
    pub lines: LineSet,
    pub format: &'static LineFormat,
    /// Degenerate segments (`L <= 1e-12`, docs/method.md#geometry) that were dropped.
    pub dropped_invalid: usize,
    /// The index of each segment of `lines` among the file's segments (in file order,
    /// degenerate ones counted), when some were dropped; `None`: the same indices.
    pub file_index: Option<Vec<u32>>,
    /// One line each, naming the file.
    pub warnings: Vec<String>,
}

/// Reads line segments from any format of docs/formats.md.
///
/// Degenerate segments (`L <= 1e-12`) are dropped and counted with one warning; a NaN or
/// infinite coordinate is an error naming its position; a file with no valid segment is an
/// error.
pub fn read_lines(path: &Path) -> Result<LineFile, Error> {
    read_lines_with(path, &LineOptions::default())
}

/// [`read_lines`] with options. A folder is read by the format that reads folders (LIMAP's
/// `finaltracks/`).
pub fn read_lines_with(path: &Path, opts: &LineOptions) -> Result<LineFile, Error> {
    if path.is_dir() {
        if let Some((format, read)) = LINE_FORMATS
            .iter()
            .find_map(|f| f.read_folder.map(|r| (*f, r)))
        {
            return finish(path, format, &mut read(path)?);
        }
    }
    let bytes = open_input(path)?.into_bytes(path)?;
    parse_lines_with(path, bytes, opts)
}

/// [`read_lines`] on bytes already in memory; `path` names them in messages (and its
/// extension tells a broken binary STL apart).
pub fn parse_lines(path: &Path, bytes: Vec<u8>) -> Result<LineFile, Error> {
    parse_lines_with(path, bytes, &LineOptions::default())
}

/// [`parse_lines`] with options.
pub fn parse_lines_with(
    path: &Path,
    mut bytes: Vec<u8>,
    opts: &LineOptions,
) -> Result<LineFile, Error> {
    // Editors on Windows prefix text with a UTF-8 byte-order mark; no binary format starts so.
    if bytes.starts_with(ply::BOM) {
        bytes.drain(..3);
    }
    let format = detect(path, &bytes)?;
    let mut parsed = (format.parse)(path, &bytes, opts)?;
    finish(path, format, &mut parsed)
}

/// Drops degenerate segments (with their groups) and builds the result.
fn finish(path: &Path, format: &'static LineFormat, p: &mut Parsed) -> Result<LineFile, Error> {
    let total = p.segments.len();
    let mut keep = Vec::with_capacity(total);
    let mut kept = Vec::with_capacity(total);
    let mut groups = p.groups.as_ref().map(|_| Vec::with_capacity(total));
    let mut first_bad = None;
    for (i, s) in p.segments.iter().enumerate() {
        if s.length() > MIN_LENGTH {
            keep.push(*s);
            kept.push(i as u32);
            if let (Some(out), Some(g)) = (groups.as_mut(), p.groups.as_ref()) {
                out.push(g[i]);
            }
        } else if first_bad.is_none() {
            first_bad = Some(i);
        }
    }
    let dropped = total - keep.len();
    let mut warnings = std::mem::take(&mut p.warnings);
    if let Some(i) = first_bad {
        warnings.push(format!(
            "{}: dropped {dropped} degenerate segment{} (length <= 1e-12; first at {})",
            path.display(),
            if dropped == 1 { "" } else { "s" },
            p.position(i)
        ));
    }
    if keep.is_empty() {
        return Err(Error::no_data(
            path,
            if total == 0 {
                format!("the {format} file holds no line segments")
            } else {
                format!("all {total} segments are degenerate (length <= 1e-12)")
            },
        ));
    }
    Ok(LineFile {
        lines: LineSet {
            segments: keep,
            groups,
        },
        format,
        dropped_invalid: dropped,
        file_index: (dropped > 0).then_some(kept),
        warnings,
    })
}

/// The line formats in the order they are tried.
fn by_rank() -> Vec<&'static LineFormat> {
    let mut formats = LINE_FORMATS.to_vec();
    formats.sort_by_key(|f| f.rank);
    formats
}

/// Picks the format of a line file from its bytes: the formats' detectors in rank order,
/// those that look at bytes first; the text formats only see valid UTF-8 with a data row.
pub(crate) fn detect(path: &Path, bytes: &[u8]) -> Result<&'static LineFormat, Error> {
    if bytes.iter().all(|b| b.is_ascii_whitespace()) {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    let ext = extension(path);
    let text = std::str::from_utf8(bytes).ok();
    let probe = Probe {
        bytes,
        text,
        ext: &ext,
    };
    let formats = by_rank();
    for f in &formats {
        if let Detect::Bytes(d) = f.detect {
            if d(&probe) {
                return Ok(f);
            }
        }
    }
    let Some(text) = text else {
        return Err(Error::unknown(
            path,
            "binary content that is not PLY, .npy or a binary STL (84-byte header, then 50 bytes per facet)",
        ));
    };
    let Some((line, first)) = data_rows(text).next() else {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    };
    for f in &formats {
        if let Detect::Text(d) = f.detect {
            if d(&probe) {
                return Ok(f);
            }
        }
    }
    let toks: Vec<&str> = plain_tokens(first).collect();
    let shown: String = first.chars().take(60).collect();
    Err(Error::unknown(
        path,
        format!(
            "line {line} (`{shown}{}`) has {} values: not 6 numbers (plain text) and not a Line3D++ row (n, 6n numbers, m, 6m residuals)",
            if first.chars().count() > 60 { "..." } else { "" },
            toks.len()
        ),
    ))
}

/// The segment formats `write_lines` writes, by extension (`registry::LINE_WRITERS`).
pub static LINE_OUTPUTS: LazyLock<Vec<&'static str>> =
    LazyLock::new(|| LINE_WRITERS.iter().map(|w| w.ext).collect());

/// Checks that `write_lines` can write `path` (by its extension), so a command can refuse
/// a bad output name before doing any work.
pub fn check_line_output(path: &Path) -> Result<String, Error> {
    Ok(writer_for(path)?.ext.to_string())
}

/// The writer of `path`'s extension.
fn writer_for(path: &Path) -> Result<&'static LineWriter, Error> {
    let ext = extension(path);
    if let Some(w) = LINE_WRITERS.iter().find(|w| w.ext == ext) {
        return Ok(w);
    }
    let names: Vec<String> = LINE_OUTPUTS.iter().map(|e| format!(".{e}")).collect();
    Err(Error::Unsupported {
        path: path.to_path_buf(),
        msg: format!(
            "cannot tell the line format from the extension `{ext}`; use {}",
            join_or(&names)
        ),
    })
}

/// Writes segments in the format named by the extension (`LINE_OUTPUTS`): `.obj`, `.stl`
/// (Line3D++ style), `.ply` (vertex + edge), `.txt` (x1 y1 z1 x2 y2 z2 per row) or `.npy`
/// (N x 2 x 3 f64).
pub fn write_lines(path: &Path, lines: &[Segment]) -> Result<(), Error> {
    let writer = writer_for(path)?;
    check_finite(path, lines, 0)?;
    (writer.write)(path, lines)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn detect_str(name: &str, text: &str) -> Result<&'static str, Error> {
        detect(Path::new(name), text.as_bytes()).map(|f| f.id)
    }

    #[test]
    fn detection_by_content_not_by_name() {
        assert_eq!(detect_str("a.txt", "# c\n1 2 3 4 5 6\n").unwrap(), "plain");
        assert_eq!(
            detect_str("a.obj.txt", "v 1 2 3\nv 4 5 6\nl 1 2\n").unwrap(),
            "obj"
        );
        assert_eq!(
            detect_str("noext", "1 0 0 0 1 1 1 0 0\n").unwrap(),
            "line3dpp"
        );
        assert_eq!(detect_str("x.dat", "solid s\nendsolid s\n").unwrap(), "stl");
        assert!(matches!(
            detect_str("e.txt", " \n\t\n"),
            Err(Error::Empty { .. })
        ));
        assert!(matches!(
            detect_str("c.txt", "# only\n# comments\n"),
            Err(Error::Empty { .. })
        ));
        let e = detect_str("u.txt", "hello world\n").unwrap_err();
        assert!(matches!(e, Error::UnknownFormat { .. }));
        assert!(
            e.to_string()
                .contains("line 1 (`hello world`) has 2 values"),
            "{e}"
        );
    }
}
