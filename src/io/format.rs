//! What a file format is to the readers and writers (docs/contributing.md, "Adding a
//! format"): one [`GaussianFormat`], [`LineFormat`] or [`LineWriter`] value, defined in the
//! format's own file and listed once in `registry.rs`. Detection, reading, writing, `info`,
//! `convert`, the `--help` texts, the fuzz targets, the Python binding's list and the table
//! of docs/formats.md all come from those lists.

use std::fmt;
use std::path::Path;

use crate::geom::Segment;

use super::error::{Error, Position};
use super::ply::{GaussianCloud, PlyOptions};
use super::sink::Sink;

/// Where a Gaussian reader takes its bytes from.
pub(crate) enum Source<'a> {
    /// A regular file, which a reader may stream.
    File,
    /// The whole content, already in memory (a pipe's, or a file read whole).
    Bytes(&'a [u8]),
}

/// The centers, and the opacity logits when they were asked for.
pub(crate) type Read = Result<(GaussianCloud, Option<Vec<f32>>), Error>;

/// How a Gaussian format is read.
pub(crate) enum GaussianRead {
    /// From the whole content, into the common [`Sink`] (NaN centers, `--min-opacity` and
    /// empty models handled the same way for every format).
    Bytes(fn(&Path, &[u8], Sink) -> Read),
    /// By a reader of its own that may stream a file (`Source::File`): `path`, the source,
    /// the options, and whether the opacity logits are wanted.
    Own(fn(&Path, Source, &PlyOptions, bool) -> Read),
}

/// A Gaussian model format.
pub struct GaussianFormat {
    /// Stable key (`info --formats`, tests).
    pub id: &'static str,
    /// What the format is called in docs/formats.md and `info --formats`.
    pub name: &'static str,
    /// File extensions, lower case without the dot, the usual one first.
    pub extensions: &'static [&'static str],
    /// How it is recognised and what is read, for docs/formats.md's table.
    pub summary: &'static str,
    /// The words of the `--gaussians` help (`3DGS `point_cloud.ply``).
    pub help: &'static str,
    /// `info`'s and `convert`'s short lists name formats by family ("PLY", "SPZ",
    /// ".splat"); formats of one family are listed as its variants ("3DGS or SuperSplat
    /// compressed PLY"). The variant's words, or `None` for a family of one.
    pub variant: Option<&'static str>,
    /// The family's name in `info`'s short list.
    pub family: &'static str,
    /// The words of the unknown-format hints (`None`: an earlier format's words cover it).
    pub hint: Option<&'static str>,
    /// The words of the Gaussian reader's "none of them" message (`None`: an earlier
    /// format's words cover it).
    pub sniff_hint: Option<&'static str>,
    /// By content: `Ok(true)` when `head` (the first MiB, after a byte-order mark) is this
    /// format; an error where the content is this format's but broken.
    pub(crate) sniff: fn(&Path, &[u8], u64) -> Result<bool, Error>,
    /// Also chosen by extension, when no format's content matched (a format without a
    /// signature, or a broken file that its reader should name).
    pub(crate) by_extension: bool,
    /// Whether [`super::info`] lists PLY elements and properties (the format is a PLY).
    pub(crate) is_ply: bool,
    pub(crate) read: GaussianRead,
}

impl PartialEq for GaussianFormat {
    fn eq(&self, other: &Self) -> bool {
        self.id == other.id
    }
}

impl Eq for GaussianFormat {}

impl fmt::Debug for GaussianFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.id)
    }
}

/// The file given to a line format's detector.
pub(crate) struct Probe<'a> {
    /// The content (after a byte-order mark).
    pub(crate) bytes: &'a [u8],
    /// The content as text, where it is valid UTF-8.
    pub(crate) text: Option<&'a str>,
    /// The file's extension, lower case.
    pub(crate) ext: &'a str,
}

/// How a line format is recognised.
pub(crate) enum Detect {
    /// From the bytes, before the content is required to be text.
    Bytes(fn(&Probe) -> bool),
    /// From the text (valid UTF-8 with at least one data row), in rank order.
    Text(fn(&Probe) -> bool),
}

/// Reads a folder of a format that is one.
pub(crate) type ReadFolder = fn(&Path) -> Result<Parsed, Error>;

/// A line-segment format that [`super::read_lines`] reads.
pub struct LineFormat {
    /// Stable key (`info --formats`, tests).
    pub id: &'static str,
    /// What `info` and messages call it (`Line3D++ text`).
    pub name: &'static str,
    /// File extensions, lower case without the dot, the usual one first (a folder: none).
    pub extensions: &'static [&'static str],
    /// How it is recognised and what is read, for docs/formats.md's table.
    pub summary: &'static str,
    /// The words of the `--lines` help (`None`: an earlier format's words cover it).
    pub help: Option<&'static str>,
    /// The words of the unknown-format hint (`None`: an earlier format's words cover it).
    pub hint: Option<&'static str>,
    /// Detection order: lower first (content signatures before guesses from the text).
    pub(crate) rank: u8,
    pub(crate) detect: Detect,
    /// Reads the content (text formats get valid UTF-8).
    pub(crate) parse: fn(&Path, &[u8], &LineOptions) -> Result<Parsed, Error>,
    /// Reads a folder, for a format that is one.
    pub(crate) read_folder: Option<ReadFolder>,
}

impl LineFormat {
    pub fn name(&self) -> &'static str {
        self.name
    }
}

impl PartialEq for LineFormat {
    fn eq(&self, other: &Self) -> bool {
        self.id == other.id
    }
}

impl Eq for LineFormat {}

impl std::hash::Hash for LineFormat {
    fn hash<H: std::hash::Hasher>(&self, h: &mut H) {
        self.id.hash(h)
    }
}

impl fmt::Debug for LineFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.id)
    }
}

impl fmt::Display for LineFormat {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name)
    }
}

/// A segment file that [`super::write_lines`] writes, chosen by extension.
pub struct LineWriter {
    /// The extension, lower case without the dot.
    pub ext: &'static str,
    /// The format the file reads back as.
    pub format: &'static LineFormat,
    /// The words of `refine -o`'s help (`.ply` (with an edge element)).
    pub help: &'static str,
    pub(crate) write: fn(&Path, &[Segment]) -> Result<(), Error>,
}

/// What to do with the Bézier curves of an edge file.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Curves {
    /// Count them and leave them out, with a warning.
    #[default]
    Skip,
    /// Sample each into 16 straight segments (one group a curve).
    Polyline,
}

/// How [`super::read_lines_with`] treats what is not a straight segment.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LineOptions {
    /// Bézier curves of EMAP/EdgeGaussians edge files: skipped, or sampled as polylines.
    pub curves: Curves,
}

/// Where segment `i` came from, to name it in the degenerate-segment warning.
#[derive(Debug)]
pub(crate) enum Origin {
    /// 1-based text line of each segment.
    Lines(Vec<usize>),
    /// Record index of each segment in a binary element (`facet`, `edge`, `row`).
    Records(&'static str),
}

/// What a line format's parser returns: every segment of the file (degenerate ones
/// included; [`super::read_lines`] drops them), and its groups and warnings.
#[derive(Debug)]
pub(crate) struct Parsed {
    pub(crate) segments: Vec<Segment>,
    pub(crate) groups: Option<Vec<u32>>,
    pub(crate) origin: Origin,
    pub(crate) warnings: Vec<String>,
}

impl Parsed {
    pub(crate) fn new(origin: Origin) -> Self {
        Parsed {
            segments: Vec::new(),
            groups: None,
            origin,
            warnings: Vec::new(),
        }
    }

    pub(crate) fn position(&self, i: usize) -> Position {
        match &self.origin {
            Origin::Lines(l) => Position::Line(l[i]),
            Origin::Records(e) => Position::record(e, i, None),
        }
    }
}

/// The content of a text format (its detector has checked that it is UTF-8).
pub(crate) fn text<'a>(path: &Path, bytes: &'a [u8]) -> Result<&'a str, Error> {
    std::str::from_utf8(bytes).map_err(|_| Error::unknown(path, "the file is not text"))
}

/// A file's extension, lower case (empty where it has none).
pub(crate) fn extension(path: &Path) -> String {
    path.extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default()
}
