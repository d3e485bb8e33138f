//! `linegs-gpu info FILE`: what a file is and what is in it, before anyone runs a refine.

use std::fmt;
use std::fs::File;
use std::io::Read;
use std::path::{Path, PathBuf};

use crate::geom::{p64, Aabb};

use super::error::Error;
use super::format::LineOptions;
use super::gaussians::{detect_gaussians, read_gaussians};
use super::input::{open_input, Input};
use super::lines::{parse_lines_with, read_lines_with, LineFile};
use super::ply::{parse_gaussians, parse_header, PlyOptions, BOM};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FileKind {
    Gaussians,
    Lines,
}

/// Summary of a Gaussian model or a line file.
#[derive(Clone, Debug, PartialEq)]
pub struct FileInfo {
    pub path: PathBuf,
    pub bytes: u64,
    pub kind: FileKind,
    /// `"PLY binary_little_endian 1.0"`, `"Line3D++ text"`, ...
    pub format: String,
    /// Usable Gaussians or valid segments.
    pub count: usize,
    /// PLY elements as (name, count), in header order.
    pub elements: Vec<(String, usize)>,
    /// `vertex` properties as written in the header (`float x`), for Gaussian PLYs.
    pub properties: Vec<String>,
    /// Gaussians with a NaN/Inf center, or degenerate segments, that were dropped.
    pub dropped_invalid: usize,
    /// Distinct input lines, when the format groups segments (Line3D++ `.txt`).
    pub groups: Option<usize>,
    /// Box of the usable centers or of the valid segments' endpoints.
    pub bbox: Aabb,
    /// Shortest, median and longest segment length (line files).
    pub lengths: Option<[f64; 3]>,
    pub warnings: Vec<String>,
}

/// Reads `path` as a Gaussian model (a PLY without `edge` element, or any other format of
/// `registry.rs`) or as a line file (a LIMAP `finaltracks/` folder included).
pub fn info(path: &Path) -> Result<FileInfo, Error> {
    info_with(path, &LineOptions::default())
}

/// [`info`] with the options of the line readers (`--curves`).
pub fn info_with(path: &Path, line_opts: &LineOptions) -> Result<FileInfo, Error> {
    if path.is_dir() {
        return lines_info(path, 0, read_lines_with(path, line_opts)?);
    }
    // A pipe is read once (a second open would wait for a writer that has gone): its
    // bytes are looked at and parsed in memory. Devices are refused here.
    if let Input::Bytes(b) = open_input(path)? {
        return info_of_bytes(path, b, line_opts);
    }
    let bytes = std::fs::metadata(path)
        .map_err(|e| Error::io(path, "open", e))?
        .len();
    let mut head = Vec::new();
    File::open(path)
        .map_err(|e| Error::io(path, "open", e))?
        .take(1 << 20)
        .read_to_end(&mut head)
        .map_err(|e| Error::io(path, "read", e))?;
    // A byte-order mark is skipped by every reader, so `info` looks past it too.
    let complete = head.len() as u64 == bytes;
    if head.starts_with(BOM) {
        head.drain(..BOM.len());
    }
    let is_ply = head.starts_with(b"ply\n") || head.starts_with(b"ply\r\n");
    let not_ply_gaussians =
        !is_ply && matches!(detect_gaussians(path, &head, bytes), Ok(f) if !f.is_ply);
    if not_ply_gaussians {
        let cloud = read_gaussians(path, &PlyOptions::default())?;
        let mut bbox = Aabb::empty();
        for c in &cloud.centers {
            bbox.extend(p64(*c));
        }
        return Ok(FileInfo {
            path: path.to_path_buf(),
            bytes,
            kind: FileKind::Gaussians,
            format: cloud.format,
            count: cloud.centers.len(),
            elements: Vec::new(),
            properties: Vec::new(),
            dropped_invalid: cloud.skipped_nonfinite,
            groups: None,
            bbox,
            lengths: None,
            warnings: cloud.warnings,
        });
    }
    if is_ply {
        let header = parse_header(path, &head, complete)?;
        if header.element("edge").is_none() {
            let cloud = read_gaussians(path, &PlyOptions::default())?;
            let compressed = cloud.format.starts_with("SuperSplat");
            let mut bbox = Aabb::empty();
            for c in &cloud.centers {
                bbox.extend(p64(*c));
            }
            let properties = header
                .element("vertex")
                .map(|v| {
                    header.elements[v]
                        .props
                        .iter()
                        .map(|p| p.describe())
                        .collect()
                })
                .unwrap_or_default();
            return Ok(FileInfo {
                path: path.to_path_buf(),
                bytes,
                kind: FileKind::Gaussians,
                format: if compressed {
                    cloud.format
                } else {
                    format!("PLY {}", cloud.format)
                },
                count: cloud.centers.len(),
                elements: header
                    .elements
                    .iter()
                    .map(|e| (e.name.clone(), e.count))
                    .collect(),
                properties,
                dropped_invalid: cloud.skipped_nonfinite,
                groups: None,
                bbox,
                lengths: None,
                warnings: cloud.warnings,
            });
        }
    }
    lines_info(path, bytes, read_lines_with(path, line_opts)?)
}

/// [`info_with`] of a pipe's content: a 3DGS PLY without edges, or a line file.
fn info_of_bytes(path: &Path, b: Vec<u8>, line_opts: &LineOptions) -> Result<FileInfo, Error> {
    let bytes = b.len() as u64;
    let text = b.strip_prefix(BOM).unwrap_or(&b);
    if text.starts_with(b"ply\n") || text.starts_with(b"ply\r\n") {
        let header = parse_header(path, text, true)?;
        if header.element("edge").is_none() {
            let cloud = parse_gaussians(path, &b, &PlyOptions::default())?;
            let mut bbox = Aabb::empty();
            for c in &cloud.centers {
                bbox.extend(p64(*c));
            }
            return Ok(FileInfo {
                path: path.to_path_buf(),
                bytes,
                kind: FileKind::Gaussians,
                format: format!("PLY {}", cloud.format),
                count: cloud.centers.len(),
                elements: header
                    .elements
                    .iter()
                    .map(|e| (e.name.clone(), e.count))
                    .collect(),
                properties: Vec::new(),
                dropped_invalid: cloud.skipped_nonfinite,
                groups: None,
                bbox,
                lengths: None,
                warnings: cloud.warnings,
            });
        }
    }
    lines_info(path, bytes, parse_lines_with(path, b, line_opts)?)
}

fn lines_info(path: &Path, bytes: u64, file: LineFile) -> Result<FileInfo, Error> {
    let segs = &file.lines.segments;
    let mut lens: Vec<f64> = segs.iter().map(|s| s.length()).collect();
    lens.sort_by(f64::total_cmp);
    let groups = file.lines.input_lines();
    Ok(FileInfo {
        path: path.to_path_buf(),
        bytes,
        kind: FileKind::Lines,
        format: file.format.name().to_string(),
        count: segs.len(),
        elements: Vec::new(),
        properties: Vec::new(),
        dropped_invalid: file.dropped_invalid,
        groups,
        bbox: Aabb::of_segments(segs),
        lengths: Some([lens[0], lens[lens.len() / 2], lens[lens.len() - 1]]),
        warnings: file.warnings,
    })
}

/// `f_rest_0 f_rest_1 ... f_rest_44` shown as `f_rest_0..44`, so 62 names fit on a line.
fn compress_names(names: &[&str]) -> String {
    let split = |n: &str| -> Option<(String, u32)> {
        let (stem, num) = n.rsplit_once('_')?;
        Some((format!("{stem}_"), num.parse().ok()?))
    };
    let mut out: Vec<String> = Vec::new();
    let mut i = 0;
    while i < names.len() {
        if let Some((stem, a)) = split(names[i]) {
            let mut j = i + 1;
            while j < names.len() && split(names[j]) == Some((stem.clone(), a + (j - i) as u32)) {
                j += 1;
            }
            if j - i >= 3 {
                out.push(format!("{stem}{a}..{}", a + (j - i - 1) as u32));
                i = j;
                continue;
            }
        }
        out.push(names[i].to_string());
        i += 1;
    }
    out.join(" ")
}

fn fmt_point(p: glam::DVec3) -> String {
    format!("[{:.6}, {:.6}, {:.6}]", p.x, p.y, p.z)
}

impl fmt::Display for FileInfo {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "{}", self.path.display())?;
        let kind = match self.kind {
            FileKind::Gaussians => "Gaussian model",
            FileKind::Lines => "line segments",
        };
        writeln!(f, "  kind:        {kind}")?;
        writeln!(f, "  format:      {}, {} bytes", self.format, self.bytes)?;
        if !self.elements.is_empty() {
            let e: Vec<String> = self
                .elements
                .iter()
                .map(|(n, c)| format!("{n} {c}"))
                .collect();
            writeln!(f, "  elements:    {}", e.join(", "))?;
        }
        if !self.properties.is_empty() {
            let (types, names): (Vec<&str>, Vec<&str>) = self
                .properties
                .iter()
                .map(|p| p.rsplit_once(' ').unwrap_or(("", p.as_str())))
                .unzip();
            let all_same = types.iter().all(|t| *t == types[0]);
            let typ = if all_same {
                format!(", all {}", types[0])
            } else {
                String::new()
            };
            writeln!(
                f,
                "  properties:  {}{typ}: {}",
                names.len(),
                if all_same {
                    compress_names(&names)
                } else {
                    self.properties.join(", ")
                }
            )?;
        }
        match self.kind {
            FileKind::Gaussians => writeln!(
                f,
                "  gaussians:   {} ({} with a NaN or infinite center skipped)",
                self.count, self.dropped_invalid
            )?,
            FileKind::Lines => {
                writeln!(
                    f,
                    "  segments:    {} ({} degenerate dropped)",
                    self.count, self.dropped_invalid
                )?;
                if let Some(g) = self.groups {
                    writeln!(f, "  input lines: {g} (segments grouped per 3D line)")?;
                }
                if let Some([lo, med, hi]) = self.lengths {
                    writeln!(
                        f,
                        "  length:      min {lo:.6}, median {med:.6}, max {hi:.6}"
                    )?;
                }
            }
        }
        let size = self.bbox.max - self.bbox.min;
        writeln!(
            f,
            "  bbox:        {} .. {} (size {:.6} x {:.6} x {:.6})",
            fmt_point(self.bbox.min),
            fmt_point(self.bbox.max),
            size.x,
            size.y,
            size.z
        )?;
        for w in &self.warnings {
            writeln!(f, "  warning:     {w}")?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn runs_of_numbered_names_are_compressed() {
        let names = [
            "x", "y", "f_dc_0", "f_dc_1", "f_dc_2", "rot_0", "rot_1", "scale_7",
        ];
        assert_eq!(compress_names(&names), "x y f_dc_0..2 rot_0 rot_1 scale_7");
    }
}
