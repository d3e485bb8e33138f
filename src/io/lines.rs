//! Line-segment readers for every format of docs/formats.md, chosen by content (and, where content
//! alone cannot tell, by extension; never by folder names).

use std::fmt;
use std::path::Path;

use crate::geom::{LineSet, Segment, MIN_LENGTH};

use super::edges_json::{self, Curves};
use super::error::{Error, Position};
use super::input::open_input;
use super::limap;
use super::npy;
use super::ply::{self, PropKind};

/// The line formats `read_lines` recognises.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LineFormat {
    /// Line3D++ `.txt`: one 3D line per row, `n` segments then `m` 2D residuals.
    Line3dppTxt,
    /// Wavefront `.obj` with `v` and `l` records (Line3D++, LIMAP, ELSR).
    Obj,
    /// Line3D++ `.stl`: degenerate facets `P1 P2 P1`, ASCII or binary.
    Stl,
    /// LIMAP `.npy`: float array `N x 2 x 3`.
    Npy,
    /// Six numbers per row, `x1 y1 z1 x2 y2 z2`, `#` comments.
    PlainText,
    /// PLY with `vertex` and `edge` elements (what `write_lines` writes).
    Ply,
    /// LIMAP `finaltracks/` folder (`track_<id>.txt`), or one such track file.
    LimapTracks,
    /// LIMAP `alltracks.txt` (every track in one file).
    LimapAllTracks,
    /// EMAP / EdgeGaussians `parametric_edges.json`.
    EdgesJson,
}

impl LineFormat {
    pub fn name(self) -> &'static str {
        match self {
            LineFormat::Line3dppTxt => "Line3D++ text",
            LineFormat::Obj => "OBJ",
            LineFormat::Stl => "STL",
            LineFormat::Npy => "NumPy .npy",
            LineFormat::PlainText => "plain text (x1 y1 z1 x2 y2 z2)",
            LineFormat::Ply => "PLY (vertex + edge)",
            LineFormat::LimapTracks => "LIMAP line tracks (track_<id>.txt)",
            LineFormat::LimapAllTracks => "LIMAP alltracks.txt",
            LineFormat::EdgesJson => "EMAP/EdgeGaussians parametric edges (JSON)",
        }
    }
}

impl fmt::Display for LineFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// Segments read from a file, and what was dropped on the way.
#[derive(Clone, Debug, PartialEq)]
pub struct LineFile {
    /// Valid segments only; `groups` is `Some` for Line3D++ `.txt` (row index per segment).
    pub lines: LineSet,
    pub format: LineFormat,
    /// Degenerate segments (`L <= 1e-12`, docs/method.md#geometry) that were dropped.
    pub dropped_invalid: usize,
    /// The index of each segment of `lines` among the file's segments (in file order,
    /// degenerate ones counted), when some were dropped; `None`: the same indices.
    pub file_index: Option<Vec<u32>>,
    /// One line each, naming the file.
    pub warnings: Vec<String>,
}

/// Where segment `i` came from, to name it in the degenerate-segment warning.
#[derive(Debug)]
enum Origin {
    /// 1-based text line of each segment.
    Lines(Vec<usize>),
    /// Record index of each segment in a binary element (`facet`, `edge`, `row`).
    Records(&'static str),
}

#[derive(Debug)]
struct Parsed {
    segments: Vec<Segment>,
    groups: Option<Vec<u32>>,
    origin: Origin,
    warnings: Vec<String>,
}

impl Parsed {
    fn new(origin: Origin) -> Self {
        Parsed {
            segments: Vec::new(),
            groups: None,
            origin,
            warnings: Vec::new(),
        }
    }

    fn position(&self, i: usize) -> Position {
        match &self.origin {
            Origin::Lines(l) => Position::Line(l[i]),
            Origin::Records(e) => Position::record(e, i, None),
        }
    }
}

/// Reads line segments from any format of docs/formats.md.
///
/// Degenerate segments (`L <= 1e-12`) are dropped and counted with one warning; a NaN or
/// infinite coordinate is an error naming its position; a file with no valid segment is an
/// error.
pub fn read_lines(path: &Path) -> Result<LineFile, Error> {
    read_lines_with(path, &LineOptions::default())
}

/// How [`read_lines_with`] treats what is not a straight segment.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LineOptions {
    /// Bézier curves of EMAP/EdgeGaussians edge files: skipped, or sampled as polylines.
    pub curves: Curves,
}

/// [`read_lines`] with options. A folder is read as LIMAP's `finaltracks/`.
pub fn read_lines_with(path: &Path, opts: &LineOptions) -> Result<LineFile, Error> {
    if path.is_dir() {
        let (segments, ids, warnings) = limap::read_folder(path)?;
        let mut p = Parsed::new(Origin::Records("track"));
        p.segments = segments;
        p.groups = Some(ids);
        p.warnings = warnings;
        return finish(path, LineFormat::LimapTracks, &mut p);
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
    let mut parsed = match format {
        LineFormat::Ply => parse_ply(path, &bytes)?,
        LineFormat::Npy => {
            limap::refuse_pickled_npy(path, &bytes)?;
            let mut p = Parsed::new(Origin::Records("row"));
            p.segments = npy::parse(path, &bytes)?;
            p
        }
        LineFormat::Stl if !is_ascii_stl(&bytes) => parse_binary_stl(path, &bytes)?,
        _ => {
            // `detect` only returns the text formats for valid UTF-8.
            let text = std::str::from_utf8(&bytes)
                .map_err(|_| Error::unknown(path, "the file is not text"))?;
            match format {
                LineFormat::Stl => parse_ascii_stl(path, text)?,
                LineFormat::Obj => parse_obj(path, text)?,
                LineFormat::PlainText => parse_plain(path, text)?,
                LineFormat::LimapTracks => {
                    let (line, seg) = limap::parse_track(path, text)?;
                    let mut p = Parsed::new(Origin::Lines(vec![line]));
                    p.segments = vec![seg];
                    p
                }
                LineFormat::LimapAllTracks => {
                    let (segments, ids, lines) = limap::parse_alltracks(path, text)?;
                    let mut p = Parsed::new(Origin::Lines(lines));
                    p.segments = segments;
                    p.groups = Some(ids);
                    p
                }
                LineFormat::EdgesJson => {
                    let (segments, groups, warnings) = edges_json::parse(path, text, opts.curves)?;
                    let mut p = Parsed::new(Origin::Records("edge"));
                    p.segments = segments;
                    p.groups = groups;
                    p.warnings = warnings;
                    p
                }
                _ => parse_line3dpp(path, text)?,
            }
        }
    };
    finish(path, format, &mut parsed)
}

/// Drops degenerate segments (with their groups) and builds the result.
fn finish(path: &Path, format: LineFormat, p: &mut Parsed) -> Result<LineFile, Error> {
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

fn extension(path: &Path) -> String {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
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

/// Text rows without comments and blanks: (1-based line, content).
pub(super) fn data_rows(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines().enumerate().filter_map(|(i, l)| {
        let l = l.split('#').next().unwrap_or("").trim();
        (!l.is_empty()).then_some((i + 1, l))
    })
}

/// Plain-text values are separated by whitespace or commas (CSV exports).
fn plain_tokens(row: &str) -> impl Iterator<Item = &str> {
    row.split(|c: char| c.is_whitespace() || c == ',')
        .filter(|t| !t.is_empty())
}

/// Picks the format of a line file from its bytes and, for binary STL, its extension.
pub(crate) fn detect(path: &Path, bytes: &[u8]) -> Result<LineFormat, Error> {
    if bytes.iter().all(|b| b.is_ascii_whitespace()) {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    if bytes.starts_with(b"ply\n") || bytes.starts_with(b"ply\r\n") {
        return Ok(LineFormat::Ply);
    }
    if bytes.starts_with(npy::MAGIC) {
        return Ok(LineFormat::Npy);
    }
    if binary_stl_count(bytes).is_some() || is_ascii_stl(bytes) {
        return Ok(LineFormat::Stl);
    }
    let ext = extension(path);
    let Ok(text) = std::str::from_utf8(bytes) else {
        if ext == "stl" {
            // Binary, named .stl, but the size does not match the count: a broken STL.
            return Ok(LineFormat::Stl);
        }
        return Err(Error::unknown(
            path,
            "binary content that is not PLY, .npy or a binary STL (84-byte header, then 50 bytes per facet)",
        ));
    };
    if data_rows(text).next().is_none() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    if edges_json::looks_like_edges(text) {
        return Ok(LineFormat::EdgesJson);
    }
    if limap::looks_like_track(text) {
        return Ok(LineFormat::LimapTracks);
    }
    if limap::looks_like_alltracks(text) {
        return Ok(LineFormat::LimapAllTracks);
    }
    let obj_record = |r: &str| matches!(r.split_whitespace().next(), Some("v" | "l"));
    if ext == "obj" || data_rows(text).any(|(_, r)| obj_record(r)) {
        return Ok(LineFormat::Obj);
    }
    let Some((line, first)) = data_rows(text).next() else {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    };
    let toks: Vec<&str> = plain_tokens(first).collect();
    if toks.len() == 6 && toks.iter().all(|t| t.parse::<f64>().is_ok()) {
        return Ok(LineFormat::PlainText);
    }
    if looks_like_line3dpp(first) {
        return Ok(LineFormat::Line3dppTxt);
    }
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

pub(super) fn number(path: &Path, tok: &str, line: usize, value: usize) -> Result<f64, Error> {
    tok.parse::<f64>().map_err(|_| {
        Error::parse(
            path,
            Position::LineValue { line, value },
            format!("`{tok}` is not a number"),
        )
    })
}

/// A coordinate: a number, and finite (docs/formats.md: NaN/Inf line coordinates are errors).
fn coord(path: &Path, tok: &str, line: usize, value: usize) -> Result<f64, Error> {
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

fn parse_plain(path: &Path, text: &str) -> Result<Parsed, Error> {
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

/// Line3D++ `saveTXT`: per row `n  (P1 P2) x n  m  (camID segID x1 y1 x2 y2) x m`.
fn parse_line3dpp(path: &Path, text: &str) -> Result<Parsed, Error> {
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

fn parse_obj(path: &Path, text: &str) -> Result<Parsed, Error> {
    let obj = super::obj::parse(path, text, "line coordinate")?;
    let verts = obj.vertices;
    let faces = obj.faces.len();
    let no_records = obj.polylines.is_empty();
    // The first broken `l` record, if any; else the records' indices, still unresolved.
    let mut broken: Option<(usize, String)> = None;
    let mut records: Vec<(usize, Vec<i64>)> = Vec::new();
    for e in obj.polylines {
        match e.indices {
            Err(what) => {
                broken.get_or_insert((e.line, what));
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

/// The 2D observations of every segment of a Line3D++ `.txt`, in file order: each 3D
/// line's residuals (`camID segID p1x p1y p2x p2y`) as LIMAP supports (image = camera id,
/// line = 2D segment id), shared by the line's segments.
pub fn read_line3dpp_supports(path: &Path) -> Result<Vec<Vec<super::Support>>, Error> {
    let bytes = super::input::read_input(path)?;
    let text = String::from_utf8_lossy(&bytes);
    // The reader has checked the counts; a file changed since is refused here.
    parse_line3dpp(path, &text)?;
    let mut out = Vec::new();
    for (_, row) in data_rows(&text) {
        let toks: Vec<&str> = row.split_whitespace().collect();
        let n: usize = toks[0].parse().unwrap_or(0);
        let m: usize = toks[1 + 6 * n].parse().unwrap_or(0);
        let obs: Vec<super::Support> = (0..m)
            .map(|k| {
                let t = &toks[2 + 6 * n + 6 * k..2 + 6 * n + 6 * k + 6];
                let f = |i: usize| t[i].parse::<f64>().unwrap_or(f64::NAN);
                super::Support {
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

    fn detect_str(name: &str, text: &str) -> Result<LineFormat, Error> {
        detect(Path::new(name), text.as_bytes())
    }

    #[test]
    fn detection_by_content_not_by_name() {
        assert_eq!(
            detect_str("a.txt", "# c\n1 2 3 4 5 6\n").unwrap(),
            LineFormat::PlainText
        );
        assert_eq!(
            detect_str("a.obj.txt", "v 1 2 3\nv 4 5 6\nl 1 2\n").unwrap(),
            LineFormat::Obj
        );
        assert_eq!(
            detect_str("noext", "1 0 0 0 1 1 1 0 0\n").unwrap(),
            LineFormat::Line3dppTxt
        );
        assert_eq!(
            detect_str("x.dat", "solid s\nendsolid s\n").unwrap(),
            LineFormat::Stl
        );
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

    #[test]
    fn obj_polylines_and_negative_indices() {
        let p = parse_obj(
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
