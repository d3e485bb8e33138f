//! The one list of file formats (docs/contributing.md, "Adding a format"): every Gaussian
//! format, every line format and every segment writer, each defined in its own file. The
//! readers try them from here, and every list of formats a user sees is made from here:
//! the unknown-format hint, the `--gaussians`, `--lines`, `info`, `convert` and `refine -o`
//! help texts, the Python binding's `FORMATS`, the fuzz targets' file names and the table
//! of docs/formats.md (checked by tests/formats.rs).

use std::fmt;
use std::sync::OnceLock;

use super::error::KnownFormats;
use super::format::{GaussianFormat, LineFormat, LineWriter};
use super::{edges_json, limap, line3dpp, npy, obj, plain, ply_3dgs, ply_compressed, ply_lines};
use super::{splat, spz, stl};

/// The Gaussian model formats, in the order their signatures are tried and listed.
pub static GAUSSIAN_FORMATS: &[&GaussianFormat] = &[
    &ply_3dgs::FORMAT,
    &ply_compressed::FORMAT,
    &spz::FORMAT,
    &splat::FORMAT,
];

/// The line-segment formats, in the order they are listed (each has its own detection
/// rank).
pub static LINE_FORMATS: &[&LineFormat] = &[
    &line3dpp::FORMAT,
    &stl::FORMAT,
    &npy::FORMAT,
    &limap::TRACKS,
    &limap::ALLTRACKS,
    &obj::FORMAT,
    &edges_json::FORMAT,
    &plain::FORMAT,
    &ply_lines::FORMAT,
];

/// The segment writers, chosen by the output's extension, in the order they are listed.
pub static LINE_WRITERS: &[&LineWriter] = &[
    &obj::WRITER,
    &stl::WRITER,
    &ply_lines::WRITER,
    &plain::WRITER,
    &npy::WRITER,
];

/// The line format with this [`LineFormat::id`].
pub fn line_format(id: &str) -> Option<&'static LineFormat> {
    LINE_FORMATS.iter().copied().find(|f| f.id == id)
}

/// The Gaussian format with this [`GaussianFormat::id`].
pub fn gaussian_format(id: &str) -> Option<&'static GaussianFormat> {
    GAUSSIAN_FORMATS.iter().copied().find(|f| f.id == id)
}

impl fmt::Display for KnownFormats {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(known_formats())
    }
}

/// `a`, `a or b`, `a, b or c`.
pub(crate) fn join_or<S: AsRef<str>>(words: &[S]) -> String {
    join(words, " or ")
}

/// `a`, `a and b`, `a, b and c`.
pub(crate) fn join_and<S: AsRef<str>>(words: &[S]) -> String {
    join(words, " and ")
}

fn join<S: AsRef<str>>(words: &[S], last: &str) -> String {
    let words: Vec<&str> = words.iter().map(|w| w.as_ref()).collect();
    match words.split_last() {
        None => String::new(),
        Some((w, [])) => w.to_string(),
        Some((w, rest)) => format!("{}{last}{w}", rest.join(", ")),
    }
}

/// The formats `read_lines` and `read_gaussians` understand, for the unknown-format hint.
pub fn known_formats() -> &'static str {
    static TEXT: OnceLock<String> = OnceLock::new();
    TEXT.get_or_init(|| {
        let words: Vec<&str> = GAUSSIAN_FORMATS
            .iter()
            .filter_map(|f| f.hint)
            .chain(LINE_FORMATS.iter().filter_map(|f| f.hint))
            .collect();
        words.join(", ")
    })
}

/// The Gaussian formats for the `--gaussians` help: "3DGS `point_cloud.ply`, ... or
/// antimatter15 `.splat`".
pub fn gaussian_format_words() -> String {
    let words: Vec<&str> = GAUSSIAN_FORMATS.iter().map(|f| f.help).collect();
    join_or(&words)
}

/// The Gaussian formats by family, for `info`'s and `convert`'s short lists: "3DGS or
/// SuperSplat compressed PLY, SPZ, .splat", or with `by_extension` "3DGS or SuperSplat
/// compressed `.ply`, `.spz`, `.splat`".
pub fn gaussian_family_words(by_extension: bool) -> String {
    let mut families: Vec<(&str, &str, Vec<&str>)> = Vec::new();
    for f in GAUSSIAN_FORMATS {
        match families.iter_mut().find(|(name, _, _)| *name == f.family) {
            Some((_, _, variants)) => variants.extend(f.variant),
            None => families.push((
                f.family,
                f.extensions.first().copied().unwrap_or(""),
                f.variant.into_iter().collect(),
            )),
        }
    }
    let words: Vec<String> = families
        .iter()
        .map(|(name, ext, variants)| {
            let name = match by_extension {
                true => format!("`.{ext}`"),
                false => name.to_string(),
            };
            match variants.is_empty() {
                true => name,
                false => format!("{} {name}", variants.join(" or ")),
            }
        })
        .collect();
    words.join(", ")
}

/// The line formats for the `--lines` help: "Line3D++ `.txt`/`.obj`/`.stl`, ... or our
/// `.ply` with edges".
pub fn line_format_words() -> String {
    let words: Vec<&str> = LINE_FORMATS.iter().filter_map(|f| f.help).collect();
    join_or(&words)
}

/// The segment writers for the `-o` helps: "`.obj`, `.stl`, `.ply`, `.txt` or `.npy`", or
/// with `detailed` each with its note, "`.obj`, ..., `.txt` (6 numbers a row), `.npy`".
pub fn line_output_words(detailed: bool) -> String {
    if detailed {
        let words: Vec<&str> = LINE_WRITERS.iter().map(|w| w.help).collect();
        return words.join(", ");
    }
    let words: Vec<String> = LINE_WRITERS
        .iter()
        .map(|w| format!("`.{}`", w.ext))
        .collect();
    join_or(&words)
}

/// One file name per extension the formats of a kind are read by (`stem.ext`, in registry
/// order, each once), for the fuzz targets and their replay (tests/robust.rs): the first
/// byte of a fuzz input picks the name. `gaussians`: the Gaussian formats; else the line
/// formats, and the bare `stem` last (content alone decides).
pub fn file_names(stem: &str, gaussians: bool) -> Vec<String> {
    let exts: Vec<&str> = match gaussians {
        true => GAUSSIAN_FORMATS
            .iter()
            .flat_map(|f| f.extensions)
            .copied()
            .collect(),
        false => LINE_FORMATS
            .iter()
            .flat_map(|f| f.extensions)
            .copied()
            .collect(),
    };
    let mut names: Vec<String> = Vec::new();
    for e in exts {
        let name = format!("{stem}.{e}");
        if !names.contains(&name) {
            names.push(name);
        }
    }
    if !gaussians {
        names.push(stem.to_string());
    }
    names
}

/// Markdown tables of every format read and written, as docs/formats.md holds them.
pub fn format_table() -> String {
    let exts = |e: &[&str]| -> String {
        let v: Vec<String> = e.iter().map(|x| format!("`.{x}`")).collect();
        v.join(", ")
    };
    // Names such as `track_<id>.txt` are text, not HTML.
    let html = |s: &str| s.replace('<', "&lt;").replace('>', "&gt;");
    let mut out = String::from("| Reads | Format | Extension | Recognised by, notes |\n");
    out.push_str("|---|---|---|---|\n");
    for f in GAUSSIAN_FORMATS {
        out.push_str(&format!(
            "| Gaussians | {} | {} | {} |\n",
            html(f.name),
            exts(f.extensions),
            f.summary
        ));
    }
    let mut lines = LINE_FORMATS.to_vec();
    lines.sort_by_key(|f| f.rank);
    for f in lines {
        let ext = match f.read_folder {
            Some(_) => format!("{}, a folder", exts(f.extensions)),
            None => exts(f.extensions),
        };
        out.push_str(&format!(
            "| line segments | {} | {ext} | {} |\n",
            html(f.name),
            f.summary
        ));
    }
    out.push_str("\n| Writes (by the extension of `-o`) | Format |\n|---|---|\n");
    for w in LINE_WRITERS {
        out.push_str(&format!("| `.{}` | {} |\n", w.ext, html(w.format.name)));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_unique_and_every_writer_has_a_reader() {
        let mut ids: Vec<&str> = GAUSSIAN_FORMATS.iter().map(|f| f.id).collect();
        ids.sort();
        ids.dedup();
        assert_eq!(ids.len(), GAUSSIAN_FORMATS.len());
        let mut ids: Vec<&str> = LINE_FORMATS.iter().map(|f| f.id).collect();
        ids.sort();
        ids.dedup();
        assert_eq!(ids.len(), LINE_FORMATS.len());
        let mut ranks: Vec<u8> = LINE_FORMATS.iter().map(|f| f.rank).collect();
        ranks.sort();
        ranks.dedup();
        assert_eq!(ranks.len(), LINE_FORMATS.len(), "two formats share a rank");
        for w in LINE_WRITERS {
            assert!(
                LINE_FORMATS.contains(&w.format) && w.format.extensions.contains(&w.ext),
                ".{} writes a format that is not listed, or not by its extension",
                w.ext
            );
        }
    }

    #[test]
    fn word_lists() {
        assert_eq!(join_or(&["a"]), "a");
        assert_eq!(join_or(&["a", "b"]), "a or b");
        assert_eq!(join_and(&["a", "b", "c"]), "a, b and c");
        assert_eq!(
            gaussian_family_words(false),
            "3DGS or SuperSplat compressed PLY, SPZ, .splat"
        );
        assert_eq!(
            gaussian_family_words(true),
            "3DGS or SuperSplat compressed `.ply`, `.spz`, `.splat`"
        );
        assert_eq!(file_names("m", true), ["m.ply", "m.spz", "m.splat"]);
        assert_eq!(
            file_names("l", false),
            ["l.txt", "l.stl", "l.npy", "l.obj", "l.json", "l.ply", "l"]
        );
        assert_eq!(
            line_output_words(false),
            "`.obj`, `.stl`, `.ply`, `.txt` or `.npy`"
        );
    }
}
