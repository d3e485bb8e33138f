//! One error type for everything that reads or writes files (docs/formats.md): every variant names
//! the file, parse errors also name the place, so the CLI can print one line and exit 2.

use std::fmt;
use std::path::{Path, PathBuf};

/// Where in a file something went wrong.
///
/// Text positions are 1-based like an editor's (`line 12, value 5` is the fifth number on
/// line 12); record, row and byte positions are 0-based like array indices (`vertex 0` is
/// the first vertex, `byte 0` the first byte of the file).
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Position {
    /// A whole text line.
    Line(usize),
    /// One number on a text line.
    LineValue { line: usize, value: usize },
    /// A byte offset from the start of the file.
    Byte(u64),
    /// A record of a binary element (`vertex 17`, `edge 3`, `facet 9`), with its byte offset
    /// where known.
    Record {
        element: String,
        index: usize,
        byte: Option<u64>,
    },
    /// One value of an array row (`.npy`: row = segment, values 0..6 = x1 y1 z1 x2 y2 z2).
    RowValue { row: usize, value: usize },
}

impl Position {
    pub(crate) fn record(element: &str, index: usize, byte: Option<u64>) -> Self {
        Position::Record {
            element: element.to_string(),
            index,
            byte,
        }
    }
}

impl fmt::Display for Position {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Position::Line(l) => write!(f, "line {l}"),
            Position::LineValue { line, value } => write!(f, "line {line}, value {value}"),
            Position::Byte(b) => write!(f, "byte {b}"),
            Position::Record {
                element,
                index,
                byte: Some(b),
            } => write!(f, "{element} {index} (byte {b})"),
            Position::Record {
                element,
                index,
                byte: None,
            } => write!(f, "{element} {index}"),
            Position::RowValue { row, value } => write!(f, "row {row}, value {value}"),
        }
    }
}

/// The formats the readers understand, for the unknown-format hint: its `Display` is made
/// from the format registry (`registry.rs`).
#[derive(Clone, Copy, Debug)]
pub struct KnownFormats;

/// Errors of the `io` module. Display is `<path>: <position>: <what is wrong>`, followed
/// where it helps by what to do.
#[derive(thiserror::Error, Debug)]
pub enum Error {
    /// The operating system refused (missing file, permissions, full disk, ...). The OS
    /// message is part of the text and deliberately not a `source`, so that a printed
    /// chain (`{:#}`) says it once.
    #[error("{}: cannot {action}: {cause}", .path.display())]
    Io {
        path: PathBuf,
        action: &'static str,
        cause: std::io::Error,
    },

    /// Zero bytes, or nothing but whitespace and comments.
    #[error("{}: the file is empty", .path.display())]
    Empty { path: PathBuf },

    /// Neither content nor extension matches a format we read.
    #[error("{}: unknown format: {why}; expected one of: {}", .path.display(), KnownFormats)]
    UnknownFormat { path: PathBuf, why: String },

    /// Malformed content: a bad header line, a token that is not a number, wrong counts.
    #[error("{}: {pos}: {msg}", .path.display())]
    Parse {
        path: PathBuf,
        pos: Position,
        msg: String,
    },

    /// The file ends before the data its header (or its own counts) promise.
    #[error("{}: {pos}: file ends early: {msg}", .path.display())]
    Truncated {
        path: PathBuf,
        pos: Position,
        msg: String,
    },

    /// A NaN or infinite coordinate where none is allowed: a line endpoint always, a
    /// Gaussian center with `strict`.
    #[error("{}: {pos}: {what} is not finite ({value}){hint}", .path.display())]
    NonFinite {
        path: PathBuf,
        pos: Position,
        what: &'static str,
        value: f64,
        /// What to do about it, starting with "; " (empty when there is nothing to add).
        hint: &'static str,
    },

    /// A PLY without the element or property we need (`vertex`, `x`, `opacity`, ...).
    #[error("{}: {msg}", .path.display())]
    Missing { path: PathBuf, msg: String },

    /// A file that parses but holds nothing usable (no Gaussians, no valid segment).
    #[error("{}: {msg}", .path.display())]
    NoData { path: PathBuf, msg: String },

    /// A writer was asked for something it cannot produce, or a path is not a file we can
    /// read (a device, a folder).
    #[error("{}: {msg}", .path.display())]
    Unsupported { path: PathBuf, msg: String },

    /// An output path that cannot be used: its folder is missing or read-only, or it is
    /// the same file as an input or as another output. Found before any work.
    #[error("{}: {msg}", .path.display())]
    Output { path: PathBuf, msg: String },
}

impl Error {
    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            Error::Io { path, .. }
            | Error::Empty { path }
            | Error::UnknownFormat { path, .. }
            | Error::Parse { path, .. }
            | Error::Truncated { path, .. }
            | Error::NonFinite { path, .. }
            | Error::Missing { path, .. }
            | Error::NoData { path, .. }
            | Error::Unsupported { path, .. }
            | Error::Output { path, .. } => path,
        }
    }

    /// The position in the file, for errors that have one.
    pub fn position(&self) -> Option<&Position> {
        match self {
            Error::Parse { pos, .. }
            | Error::Truncated { pos, .. }
            | Error::NonFinite { pos, .. } => Some(pos),
            _ => None,
        }
    }

    pub(crate) fn io(path: &Path, action: &'static str, cause: std::io::Error) -> Self {
        Error::Io {
            path: path.to_path_buf(),
            action,
            cause: without_temp_path(cause),
        }
    }

    /// The same error about `path` instead (an output written under a temporary name is
    /// reported under its real one).
    pub(crate) fn with_path(mut self, new: &Path) -> Self {
        match &mut self {
            Error::Io { path, .. }
            | Error::Empty { path }
            | Error::UnknownFormat { path, .. }
            | Error::Parse { path, .. }
            | Error::Truncated { path, .. }
            | Error::NonFinite { path, .. }
            | Error::Missing { path, .. }
            | Error::NoData { path, .. }
            | Error::Unsupported { path, .. }
            | Error::Output { path, .. } => *path = new.to_path_buf(),
        }
        self
    }

    pub(crate) fn parse(path: &Path, pos: Position, msg: impl Into<String>) -> Self {
        Error::Parse {
            path: path.to_path_buf(),
            pos,
            msg: msg.into(),
        }
    }

    pub(crate) fn truncated(path: &Path, pos: Position, msg: impl Into<String>) -> Self {
        Error::Truncated {
            path: path.to_path_buf(),
            pos,
            msg: msg.into(),
        }
    }

    pub(crate) fn non_finite(path: &Path, pos: Position, what: &'static str, value: f64) -> Self {
        Error::NonFinite {
            path: path.to_path_buf(),
            pos,
            what,
            value,
            hint: "",
        }
    }

    /// A Gaussian center with a NaN or infinite coordinate under `--strict` (without it,
    /// every reader skips such Gaussians with one warning).
    pub(crate) fn strict_center(path: &Path, pos: Position, c: [f32; 3]) -> Self {
        let bad = c
            .iter()
            .copied()
            .find(|v| !v.is_finite())
            .unwrap_or(f32::NAN);
        let mut e = Error::non_finite(path, pos, "Gaussian center", bad as f64);
        if let Error::NonFinite { hint, .. } = &mut e {
            *hint = "; without --strict such Gaussians are skipped with a warning";
        }
        e
    }

    /// A Gaussian center with a finite coordinate `value` beyond the range of f32 (a PLY
    /// `double`) under `--strict`.
    pub(crate) fn strict_overflow(path: &Path, pos: Position, value: f64) -> Self {
        Error::Parse {
            path: path.to_path_buf(),
            pos,
            msg: format!(
                "Gaussian center coordinate {value:e} overflows f32 (beyond ±3.4e38); without --strict such Gaussians are skipped with a warning"
            ),
        }
    }

    /// No Gaussian of a non-empty model survived the skips: says how many each skip took.
    pub(crate) fn none_usable(
        path: &Path,
        total: usize,
        nonfinite: usize,
        low: usize,
        min_opacity: Option<f64>,
    ) -> Self {
        let mut why = Vec::new();
        if nonfinite > 0 {
            why.push(format!("{nonfinite} with a NaN or infinite center"));
        }
        if low > 0 {
            why.push(format!(
                "{low} below --min-opacity {}",
                min_opacity.unwrap_or(0.0)
            ));
        }
        Error::no_data(
            path,
            format!(
                "none of the {total} Gaussians is usable ({})",
                why.join(", ")
            ),
        )
    }

    pub(crate) fn unknown(path: &Path, why: impl Into<String>) -> Self {
        Error::UnknownFormat {
            path: path.to_path_buf(),
            why: why.into(),
        }
    }

    pub(crate) fn missing(path: &Path, msg: impl Into<String>) -> Self {
        Error::Missing {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }

    pub(crate) fn no_data(path: &Path, msg: impl Into<String>) -> Self {
        Error::NoData {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }
}

/// `tempfile` wraps OS errors as "<message> at path \"/dir/.linegs-Xy12.tmp\""; the
/// temporary name means nothing to a user, so only the OS error is kept.
/// The OS error comes back as itself (`(os error N)`), so that its kind and number still
/// tell a resource limit from a fault.
pub(crate) fn without_temp_path(e: std::io::Error) -> std::io::Error {
    if e.raw_os_error().is_some() {
        return e;
    }
    let Some(inner) = e.get_ref() else {
        return e;
    };
    let text = inner.to_string();
    let Some(i) = text.rfind(" at path ") else {
        return e;
    };
    let head = &text[..i];
    let os = head
        .strip_suffix(')')
        .and_then(|h| h.rsplit_once("(os error "))
        .and_then(|(_, n)| n.parse::<i32>().ok());
    match os {
        Some(n) => std::io::Error::from_raw_os_error(n),
        None => std::io::Error::new(e.kind(), head.to_string()),
    }
}

impl Error {
    /// True when the fault is in the user's input (a file that cannot be opened or read,
    /// or whose content is wrong) rather than in writing our outputs.
    pub fn is_input_error(&self) -> bool {
        match self {
            // Out of file descriptors or memory is a resource limit, whatever the action.
            Error::Io { cause, .. } if is_resource_limit(cause) => false,
            Error::Io { action, .. } => {
                matches!(*action, "open" | "read" | "read metadata of")
            }
            _ => true,
        }
    }
}

/// A limit of the process or the system (too many open files, no memory), not a fault of
/// the file: exit 1, not 2.
pub(crate) fn is_resource_limit(e: &std::io::Error) -> bool {
    if e.kind() == std::io::ErrorKind::OutOfMemory {
        return true;
    }
    #[cfg(unix)]
    {
        matches!(
            e.raw_os_error(),
            Some(libc::EMFILE | libc::ENFILE | libc::ENOMEM)
        )
    }
    #[cfg(not(unix))]
    {
        false
    }
}

/// The one warning for Gaussians skipped for a NaN or infinite center; `overflow` of the
/// `n` were finite numbers in the file (a PLY `double`) beyond the range of f32.
pub(crate) fn skipped_centers_warning(
    path: &Path,
    n: usize,
    overflow: usize,
    first: Option<&Position>,
) -> String {
    let first = first
        .map(|p| format!(" (first at {p})"))
        .unwrap_or_default();
    let why = if overflow == n {
        "has a coordinate that overflows f32 (beyond ±3.4e38)"
    } else if overflow > 0 {
        "is NaN, infinite or overflows f32 (beyond ±3.4e38)"
    } else {
        "is NaN or infinite"
    };
    format!(
        "{}: skipped {n} Gaussian{} whose center {why}{first}; --strict makes this an error",
        path.display(),
        if n == 1 { "" } else { "s" },
    )
}

/// A center read as f64 (PLY `double`) narrowed to f32, with the first coordinate that
/// was finite in the file but overflowed in the narrowing.
pub(crate) fn narrow_center(v: &[f64]) -> ([f32; 3], Option<f64>) {
    let c = [v[0] as f32, v[1] as f32, v[2] as f32];
    let over = (0..3).find(|&i| v[i].is_finite() && !c[i].is_finite());
    (c, over.map(|i| v[i]))
}
