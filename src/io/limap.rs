//! LIMAP line tracks: the `finaltracks/` folder (`track_<id>.txt`, one file a track, what
//! `limap.util.io.save_folder_linetracks` writes) and `alltracks.txt` (all tracks in one
//! file, `save_txt_linetracks`). Each track is one 3D segment; its track id is kept as the
//! segment's group. LIMAP's pickled `.npy` files are refused with what to save instead.
//!
//! `track_<id>.txt` (LIMAP `LineTrack::Write`):
//! ```text
//! x1 y1 z1 x2 y2 z2
//! n_lines n_images
//! image_id_list <n_lines ids>
//! line_id_list <n_lines ids>
//! line2d_list
//! ...
//! ```
//! `alltracks.txt`: `n_tracks`, then per track `track_id n_lines n_images`, the start
//! point, the end point, `n_lines` image ids and `n_lines` line ids.

use std::path::{Path, PathBuf};

use crate::geom::Segment;

use super::error::{Error, Position};
use super::format::{self, Detect, LineFormat, Origin, Parsed, Probe};

pub(crate) static TRACKS: LineFormat = LineFormat {
    id: "limap-tracks",
    name: "LIMAP line tracks (track_<id>.txt)",
    extensions: &["txt"],
    summary: "LIMAP `finaltracks/` folders (`track_<id>.txt`), or one such file; one \
              segment a track, track ids kept as groups",
    help: Some("LIMAP `.npy`, `finaltracks/` or `alltracks.txt`"),
    hint: Some("LIMAP finaltracks/ and alltracks.txt"),
    rank: 11,
    detect: Detect::Text(|p| p.text.is_some_and(looks_like_track)),
    parse: |path, bytes, _| {
        let (line, seg) = parse_track(path, format::text(path, bytes)?)?;
        let mut p = Parsed::new(Origin::Lines(vec![line]));
        p.segments = vec![seg];
        Ok(p)
    },
    read_folder: Some(|dir| {
        let (segments, ids, warnings) = read_folder(dir)?;
        let mut p = Parsed::new(Origin::Records("track"));
        p.segments = segments;
        p.groups = Some(ids);
        p.warnings = warnings;
        Ok(p)
    }),
};

pub(crate) static ALLTRACKS: LineFormat = LineFormat {
    id: "limap-alltracks",
    name: "LIMAP alltracks.txt",
    extensions: &["txt"],
    summary: "LIMAP `alltracks.txt` (every track in one file; no 2D segments)",
    help: None,
    hint: None,
    rank: 12,
    detect: Detect::Text(|p: &Probe| p.text.is_some_and(looks_like_alltracks)),
    parse: |path, bytes, _| {
        let (segments, ids, lines) = parse_alltracks(path, format::text(path, bytes)?)?;
        let mut p = Parsed::new(Origin::Lines(lines));
        p.segments = segments;
        p.groups = Some(ids);
        Ok(p)
    },
    read_folder: None,
};

/// Whitespace tokens with their 1-based line and 1-based place on the line.
struct Tokens<'a> {
    path: &'a Path,
    toks: Vec<(usize, usize, &'a str)>,
    at: usize,
}

impl<'a> Tokens<'a> {
    fn new(path: &'a Path, text: &'a str) -> Self {
        let mut toks = Vec::new();
        for (i, line) in text.lines().enumerate() {
            for (k, t) in line.split_whitespace().enumerate() {
                toks.push((i + 1, k + 1, t));
            }
        }
        Tokens { path, toks, at: 0 }
    }

    fn next(&mut self, what: &str) -> Result<(usize, usize, &'a str), Error> {
        match self.toks.get(self.at) {
            Some(&t) => {
                self.at += 1;
                Ok(t)
            }
            None => {
                let line = self.toks.last().map_or(1, |t| t.0);
                Err(Error::truncated(
                    self.path,
                    Position::Line(line),
                    format!("the file ends where {what} should be"),
                ))
            }
        }
    }

    fn coord(&mut self, what: &str) -> Result<f64, Error> {
        let (line, value, t) = self.next(what)?;
        let pos = Position::LineValue { line, value };
        let x: f64 = t.parse().map_err(|_| {
            Error::parse(
                self.path,
                pos.clone(),
                format!("{what}: `{t}` is not a number"),
            )
        })?;
        if !x.is_finite() {
            return Err(Error::non_finite(self.path, pos, "line coordinate", x));
        }
        Ok(x)
    }

    fn int(&mut self, what: &str) -> Result<(usize, i64), Error> {
        let (line, value, t) = self.next(what)?;
        let x = t.parse::<i64>().map_err(|_| {
            Error::parse(
                self.path,
                Position::LineValue { line, value },
                format!("expected {what} (an integer), found `{t}`"),
            )
        })?;
        Ok((line, x))
    }

    fn count(&mut self, what: &str) -> Result<(usize, usize), Error> {
        let (line, value, t) = self.next(what)?;
        let n = t.parse::<usize>().map_err(|_| {
            Error::parse(
                self.path,
                Position::LineValue { line, value },
                format!("expected {what} (a non-negative integer), found `{t}`"),
            )
        })?;
        // Every counted item is at least one token; a larger count is a damaged file.
        if n > self.toks.len() {
            return Err(Error::parse(
                self.path,
                Position::LineValue { line, value },
                format!("{what} {n} is more than the file could hold"),
            ));
        }
        Ok((line, n))
    }

    fn keyword(&mut self, word: &str) -> Result<(), Error> {
        let (line, value, t) = self.next(&format!("`{word}`"))?;
        if t != word {
            return Err(Error::parse(
                self.path,
                Position::LineValue { line, value },
                format!("expected `{word}` (a LIMAP track file), found `{t}`"),
            ));
        }
        Ok(())
    }

    fn segment(&mut self) -> Result<(usize, Segment), Error> {
        let line = self.toks.get(self.at).map_or(1, |t| t.0);
        let mut v = [0.0; 6];
        for (k, slot) in v.iter_mut().enumerate() {
            *slot = self.coord(["x1", "y1", "z1", "x2", "y2", "z2"][k])?;
        }
        Ok((
            line,
            Segment::from_arrays([v[0], v[1], v[2]], [v[3], v[4], v[5]]),
        ))
    }
}

/// One data row's tokens.
fn row_tokens(text: &str, row: usize) -> Option<Vec<&str>> {
    text.lines()
        .filter(|l| !l.trim().is_empty())
        .nth(row)
        .map(|l| l.split_whitespace().collect())
}

/// A single `track_<id>.txt`: 6 numbers, 2 counts, then `image_id_list`.
pub(crate) fn looks_like_track(text: &str) -> bool {
    let (Some(a), Some(b), Some(c)) = (
        row_tokens(text, 0),
        row_tokens(text, 1),
        row_tokens(text, 2),
    ) else {
        return false;
    };
    a.len() == 6
        && a.iter().all(|t| t.parse::<f64>().is_ok())
        && b.len() == 2
        && b.iter().all(|t| t.parse::<usize>().is_ok())
        && c.first() == Some(&"image_id_list")
}

/// `alltracks.txt`: a track count alone on the first row, then `id n_lines n_images`.
pub(crate) fn looks_like_alltracks(text: &str) -> bool {
    let Some(a) = row_tokens(text, 0) else {
        return false;
    };
    if a.len() != 1 || a[0].parse::<usize>().is_err() {
        return false;
    }
    match row_tokens(text, 1) {
        Some(b) => b.len() == 3 && b.iter().all(|t| t.parse::<i64>().is_ok()),
        None => a[0] == "0",
    }
}

/// Reads one track file: its segment and the 1-based line it is on.
pub(crate) fn parse_track(path: &Path, text: &str) -> Result<(usize, Segment), Error> {
    let mut t = Tokens::new(path, text);
    let (line, seg) = t.segment()?;
    let (_, n_lines) = t.count("the line count n_lines")?;
    t.count("the image count n_images")?;
    t.keyword("image_id_list")?;
    for _ in 0..n_lines {
        t.int("an image id")?;
    }
    t.keyword("line_id_list")?;
    for _ in 0..n_lines {
        t.int("a line id")?;
    }
    Ok((line, seg))
}

/// Segments with one number each (a track id, or a text line), and warnings.
type Tracks<T> = (Vec<Segment>, Vec<u32>, Vec<T>);

/// Segments, their track ids and their lines, from `alltracks.txt`.
pub(crate) fn parse_alltracks(path: &Path, text: &str) -> Result<Tracks<usize>, Error> {
    let mut t = Tokens::new(path, text);
    let (_, n) = t.count("the track count")?;
    let mut segs = Vec::with_capacity(n);
    let mut ids = Vec::with_capacity(n);
    let mut lines = Vec::with_capacity(n);
    for _ in 0..n {
        let (line, id) = t.int("a track id")?;
        let id = u32::try_from(id).map_err(|_| {
            Error::parse(
                path,
                Position::Line(line),
                format!("track id {id} is not a non-negative 32-bit integer"),
            )
        })?;
        let (_, n_lines) = t.count("the line count")?;
        t.count("the image count")?;
        let (line, seg) = t.segment()?;
        for _ in 0..2 * n_lines {
            t.int("an image or line id")?;
        }
        segs.push(seg);
        ids.push(id);
        lines.push(line);
    }
    if let Some(&(line, value, tok)) = t.toks.get(t.at) {
        return Err(Error::parse(
            path,
            Position::LineValue { line, value },
            format!("`{tok}` after the {n} tracks the first line announces (wrong track count?)"),
        ));
    }
    Ok((segs, ids, lines))
}

/// Most bytes of one `track_<id>.txt` (a track is one line and its few supports).
const TRACK_LIMIT: u64 = 64 << 20;

/// A `finaltracks/` folder: every `track_<id>.txt` in it, by id. Each must be a regular
/// file (a device or a pipe there is refused, not read), and ids are unique.
pub(crate) fn read_folder(dir: &Path) -> Result<Tracks<String>, Error> {
    let entries = std::fs::read_dir(dir).map_err(|e| Error::io(dir, "read", e))?;
    let mut tracks: Vec<(u32, PathBuf)> = Vec::new();
    for entry in entries {
        let entry = entry.map_err(|e| Error::io(dir, "read", e))?;
        let name = entry.file_name();
        let name = name.to_string_lossy();
        let Some(id) = name
            .strip_prefix("track_")
            .and_then(|s| s.strip_suffix(".txt"))
            .and_then(|s| s.parse::<u32>().ok())
        else {
            continue;
        };
        tracks.push((id, entry.path()));
    }
    if tracks.is_empty() {
        return Err(Error::unknown(
            dir,
            "a folder is read as LIMAP line tracks (finaltracks/ with track_<id>.txt files), and this one holds none",
        ));
    }
    tracks.sort();
    if let Some(w) = tracks.windows(2).find(|w| w[0].0 == w[1].0) {
        return Err(Error::Unsupported {
            path: w[1].1.clone(),
            msg: format!(
                "holds track {} like `{}`; a LIMAP folder has one track_<id>.txt per id",
                w[0].0,
                w[0].1.file_name().unwrap_or_default().to_string_lossy()
            ),
        });
    }
    let mut warnings = Vec::new();
    let (lo, hi) = (tracks[0].0 as usize, tracks[tracks.len() - 1].0 as usize);
    if lo != 0 || hi + 1 != tracks.len() {
        warnings.push(format!(
            "{}: the track files are numbered {lo}..{hi} with {} missing; LIMAP writes track_0.txt .. track_<n-1>.txt",
            dir.display(),
            hi + 1 - tracks.len()
        ));
    }
    let mut segs = Vec::with_capacity(tracks.len());
    let mut ids = Vec::with_capacity(tracks.len());
    for (id, p) in tracks {
        let bytes = super::input::read_small(&p, "a LIMAP track", TRACK_LIMIT, true)?;
        let text = std::str::from_utf8(&bytes)
            .map_err(|_| Error::unknown(&p, "a LIMAP track file is text, and this one is not"))?;
        if text.trim().is_empty() {
            return Err(Error::Empty { path: p });
        }
        let (_, seg) = parse_track(&p, text)?;
        segs.push(seg);
        ids.push(id);
    }
    Ok((segs, ids, warnings))
}

/// LIMAP (and other Python tools) save dicts and lists of objects with `np.save`, which
/// pickles them (`'descr': '|O'`). Unpickling runs code, so such files are refused.
pub(crate) fn refuse_pickled_npy(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    let head = &bytes[..bytes.len().min(4096)];
    let head = String::from_utf8_lossy(head);
    let compact: String = head.chars().filter(|c| !c.is_whitespace()).collect();
    if compact.contains("'descr':'|O'") || compact.contains("\"descr\":\"|O\"") {
        return Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: "this .npy holds pickled Python objects (LIMAP saves its tracks, configs and image collections this way), which linegs-gpu does not unpickle. \
                  Give --lines LIMAP's finaltracks/ folder or alltracks.txt, or save a float array: \
                  np.save('lines.npy', np.array([[t.line.start, t.line.end] for t in linetracks]))"
                .to_string(),
        });
    }
    Ok(())
}

/// One 2D observation of a LIMAP track: the image, the 2D line's id in it and, where the
/// file has it (`track_<id>.txt`, not `alltracks.txt`), the 2D segment `x1 y1 x2 y2`.
#[derive(Clone, Debug, PartialEq)]
pub struct Support {
    pub image_id: i64,
    pub line_id: i64,
    pub line2d: Option<[f64; 4]>,
}

/// The supports of one `track_<id>.txt` (after its segment and counts).
fn track_supports(path: &Path, text: &str) -> Result<Vec<Support>, Error> {
    let mut t = Tokens::new(path, text);
    t.segment()?;
    let (_, n) = t.count("the line count n_lines")?;
    t.count("the image count n_images")?;
    t.keyword("image_id_list")?;
    let mut images = Vec::with_capacity(n);
    for _ in 0..n {
        images.push(t.int("an image id")?.1);
    }
    t.keyword("line_id_list")?;
    let mut out = Vec::with_capacity(n);
    for &image_id in &images {
        out.push(Support {
            image_id,
            line_id: t.int("a line id")?.1,
            line2d: None,
        });
    }
    // LIMAP's reader takes a file that ends here (its earlier versions wrote no 2D lines).
    if t.toks.get(t.at).map(|x| x.2) == Some("line2d_list") {
        t.at += 1;
        for s in &mut out {
            let mut v = [0.0; 4];
            for x in &mut v {
                *x = t.coord("a 2D line coordinate")?;
            }
            s.line2d = Some(v);
        }
    }
    Ok(out)
}

/// The supports of every track of a LIMAP line file, in the order its segments are read
/// (a `finaltracks/` folder by id, one track file, `alltracks.txt` in file order);
/// `None` for any other file.
pub fn read_supports(path: &Path) -> Result<Option<Vec<Vec<Support>>>, Error> {
    if path.is_dir() {
        let entries = std::fs::read_dir(path).map_err(|e| Error::io(path, "read", e))?;
        let mut tracks: Vec<(u32, PathBuf)> = Vec::new();
        for entry in entries {
            let entry = entry.map_err(|e| Error::io(path, "read", e))?;
            let name = entry.file_name();
            if let Some(id) = name
                .to_string_lossy()
                .strip_prefix("track_")
                .and_then(|s| s.strip_suffix(".txt"))
                .and_then(|s| s.parse::<u32>().ok())
            {
                tracks.push((id, entry.path()));
            }
        }
        tracks.sort();
        let mut out = Vec::with_capacity(tracks.len());
        for (_, p) in tracks {
            let bytes = super::input::read_small(&p, "a LIMAP track", TRACK_LIMIT, true)?;
            let text = String::from_utf8_lossy(&bytes);
            out.push(track_supports(&p, &text)?);
        }
        return Ok(Some(out));
    }
    let bytes = super::input::read_input(path)?;
    let text = String::from_utf8_lossy(&bytes);
    if looks_like_track(&text) {
        return Ok(Some(vec![track_supports(path, &text)?]));
    }
    if looks_like_alltracks(&text) {
        let mut t = Tokens::new(path, &text);
        let (_, n) = t.count("the track count")?;
        let mut out = Vec::with_capacity(n);
        for _ in 0..n {
            t.int("a track id")?;
            let (_, k) = t.count("the line count n_lines")?;
            t.count("the image count n_images")?;
            t.segment()?;
            let mut images = Vec::with_capacity(k);
            for _ in 0..k {
                images.push(t.int("an image id")?.1);
            }
            let mut s = Vec::with_capacity(k);
            for image_id in images {
                s.push(Support {
                    image_id,
                    line_id: t.int("a line id")?.1,
                    line2d: None,
                });
            }
            out.push(s);
        }
        return Ok(Some(out));
    }
    Ok(None)
}

/// One `track_<id>.txt` as LIMAP's `LineTrack::Write` writes it (fixed, 10 decimals); the
/// `line2d_list` section only when every support has its 2D segment (LIMAP's reader takes
/// a file without it).
pub fn track_text(seg: &Segment, supports: &[Support]) -> String {
    use std::fmt::Write;
    let mut s = String::new();
    for x in seg.p1.to_array().iter().chain(&seg.p2.to_array()) {
        let _ = write!(s, "{x:.10} ");
    }
    s.push('\n');
    let mut images: Vec<i64> = supports.iter().map(|x| x.image_id).collect();
    images.sort_unstable();
    images.dedup();
    let _ = writeln!(s, "{} {}", supports.len(), images.len());
    s.push_str("image_id_list ");
    for x in supports {
        let _ = write!(s, "{} ", x.image_id);
    }
    s.push_str("\nline_id_list ");
    for x in supports {
        let _ = write!(s, "{} ", x.line_id);
    }
    s.push('\n');
    if supports.iter().all(|x| x.line2d.is_some()) {
        s.push_str("line2d_list\n");
        for x in supports {
            let v = x.line2d.unwrap_or_default();
            let _ = writeln!(s, "{:.10} {:.10} {:.10} {:.10} ", v[0], v[1], v[2], v[3]);
        }
    }
    s.push_str("END\n");
    s
}
