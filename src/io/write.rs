//! Writers (docs/formats.md). Every writer goes through [`write_atomic`]: the bytes land in a
//! temporary file beside the target, which is renamed over it only once complete, so a
//! failed or interrupted write never leaves a partial output file.

use std::fs::File;
use std::io::{self, BufWriter, Write};
use std::path::Path;

use crate::geom::{LineSet, Segment};

use super::error::{Error, Position};

/// Colour of `write_lines`' single PLY layer: visible on both light and dark backgrounds.
pub const DEFAULT_LINE_COLOR: [u8; 3] = [220, 40, 40];

/// Writes `path` through a temporary file in the same directory and a rename.
pub(crate) fn write_atomic(
    path: &Path,
    body: impl FnOnce(&mut BufWriter<&File>) -> io::Result<()>,
) -> Result<(), Error> {
    let parent = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    let mut builder = tempfile::Builder::new();
    let prefix = super::litter::temp_prefix();
    builder.prefix(&prefix).suffix(".tmp");
    // Temporary files are private (0600); outputs should get the usual umask-filtered mode.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        builder.permissions(std::fs::Permissions::from_mode(0o666));
    }
    let tmp = builder
        .tempfile_in(parent)
        .map_err(|e| Error::io(path, "create a temporary file beside", e))?;
    // Held while it exists, so no other run takes it for a killed run's litter.
    let _ = super::litter::try_lock(tmp.as_file());
    {
        let mut w = BufWriter::with_capacity(1 << 20, tmp.as_file());
        body(&mut w).map_err(|e| Error::io(path, "write", e))?;
        w.flush().map_err(|e| Error::io(path, "write", e))?;
    }
    tmp.as_file()
        .sync_all()
        .map_err(|e| Error::io(path, "flush", e))?;
    tmp.persist(path)
        .map_err(|e| Error::io(path, "rename the temporary file onto", e.error))?;
    Ok(())
}

/// Writes `bytes` to `path` atomically: for outputs that are not segments or Gaussians
/// (pictures, plots, reports, viewer pages).
pub fn write_bytes_atomic(path: &Path, bytes: &[u8]) -> Result<(), Error> {
    write_atomic(path, |w| w.write_all(bytes))
}

/// Checks that `path` ends in one of `allowed` (lower case, without the dot), so that a
/// command refuses a misnamed output before doing any work instead of writing, say, a PNG
/// into `r.jpg`. `what` names the output in the message ("the picture").
pub fn check_output_extension(path: &Path, what: &str, allowed: &[&str]) -> Result<(), Error> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase())
        .unwrap_or_default();
    if allowed.contains(&ext.as_str()) {
        return Ok(());
    }
    let list: Vec<String> = allowed.iter().map(|e| format!(".{e}")).collect();
    let got = if ext.is_empty() {
        "no extension".to_string()
    } else {
        format!("the extension `.{ext}`")
    };
    Err(Error::Unsupported {
        path: path.to_path_buf(),
        msg: format!(
            "{what} is written as {}; the name has {got}",
            list.join(" or ")
        ),
    })
}

/// Shortest text that reads back to the same f64, without the 300-digit expansions that
/// plain `Display` gives for tiny or huge values.
pub(crate) fn num(x: f64) -> String {
    let a = x.abs();
    if a == 0.0 || (1e-4..1e15).contains(&a) {
        format!("{x}")
    } else {
        format!("{x:e}")
    }
}

/// Writers cannot produce what the readers reject.
pub(crate) fn check_finite(path: &Path, lines: &[Segment], first: usize) -> Result<(), Error> {
    for (i, s) in lines.iter().enumerate() {
        if !(s.p1.is_finite() && s.p2.is_finite()) {
            let bad =
                s.p1.to_array()
                    .into_iter()
                    .chain(s.p2.to_array())
                    .find(|v| !v.is_finite())
                    .unwrap_or(f64::NAN);
            return Err(Error::Unsupported {
                path: path.to_path_buf(),
                msg: format!(
                    "segment {} has a coordinate {bad}; refusing to write a file no reader accepts",
                    first + i
                ),
            });
        }
    }
    Ok(())
}

/// Writes a Line3D++ `saveTXT` file: one row per input line, `n` then its `n` segments
/// (`P1 P2`), then `m = 0` (no 2D residuals), so that the reader gets the line groups back
/// and the collinear merge (docs/method.md#step-6-collinear-merge) runs on them. Rows
/// follow the groups' first appearance, so a set whose groups are contiguous (as every
/// reader and `synth` make them) reads back in the same segment order; without groups every
/// segment is its own row.
pub fn write_lines_line3dpp(path: &Path, lines: &LineSet) -> Result<(), Error> {
    check_output_extension(path, "a Line3D++ file", &["txt"])?;
    check_finite(path, &lines.segments, 0)?;
    let mut rows: Vec<Vec<usize>> = Vec::new();
    match &lines.groups {
        Some(g) => {
            let mut row_of = std::collections::HashMap::new();
            for (i, &id) in g.iter().enumerate() {
                let r = *row_of.entry(id).or_insert_with(|| {
                    rows.push(Vec::new());
                    rows.len() - 1
                });
                rows[r].push(i);
            }
        }
        None => rows.extend((0..lines.len()).map(|i| vec![i])),
    }
    write_atomic(path, |w| {
        for row in &rows {
            write!(w, "{}", row.len())?;
            for &i in row {
                let s = &lines.segments[i];
                for v in s.p1.to_array().into_iter().chain(s.p2.to_array()) {
                    write!(w, " {}", num(v))?;
                }
            }
            writeln!(w, " 0")?;
        }
        Ok(())
    })
}

/// Writes several coloured sets of segments into one binary PLY: a `vertex` element
/// (x y z as double, plus the layer colour) and an `edge` element
/// (vertex1 vertex2 red green blue), which MeshLab and CloudCompare display.
pub fn write_lines_ply_layers(path: &Path, layers: &[(&[Segment], [u8; 3])]) -> Result<(), Error> {
    let mut first = 0;
    for (segs, _) in layers {
        check_finite(path, segs, first)?;
        first += segs.len();
    }
    let n: usize = layers.iter().map(|(s, _)| s.len()).sum();
    if 2 * n > i32::MAX as usize {
        return Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: format!("{n} segments exceed the int vertex indices of a PLY edge"),
        });
    }
    write_atomic(path, |w| {
        write!(
            w,
            "ply\nformat binary_little_endian 1.0\ncomment linegs-gpu line segments, {} layer(s)\n\
             element vertex {}\nproperty double x\nproperty double y\nproperty double z\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\n\
             element edge {n}\nproperty int vertex1\nproperty int vertex2\n\
             property uchar red\nproperty uchar green\nproperty uchar blue\nend_header\n",
            layers.len(),
            2 * n
        )?;
        let mut rec = [0u8; 27];
        for (segs, rgb) in layers {
            rec[24..27].copy_from_slice(rgb);
            for s in segs.iter() {
                for p in [s.p1, s.p2] {
                    for (k, v) in p.to_array().into_iter().enumerate() {
                        rec[8 * k..8 * k + 8].copy_from_slice(&v.to_le_bytes());
                    }
                    w.write_all(&rec)?;
                }
            }
        }
        let mut edge = [0u8; 11];
        let mut i = 0i32;
        for (segs, rgb) in layers {
            edge[8..11].copy_from_slice(rgb);
            for _ in segs.iter() {
                edge[0..4].copy_from_slice(&i.to_le_bytes());
                edge[4..8].copy_from_slice(&(i + 1).to_le_bytes());
                w.write_all(&edge)?;
                i += 2;
            }
        }
        Ok(())
    })
}

/// The 62 float properties of a 3DGS `point_cloud.ply`, in the order 3DGS writes them.
pub fn gaussian_3dgs_properties() -> Vec<String> {
    let mut names: Vec<String> = ["x", "y", "z", "nx", "ny", "nz"]
        .iter()
        .map(|s| s.to_string())
        .collect();
    names.extend((0..3).map(|i| format!("f_dc_{i}")));
    names.extend((0..45).map(|i| format!("f_rest_{i}")));
    names.push("opacity".into());
    names.extend((0..3).map(|i| format!("scale_{i}")));
    names.extend((0..4).map(|i| format!("rot_{i}")));
    names
}

/// Opacity logit written when none is given: sigmoid(2) = 0.88, a well-trained surface.
pub const DEFAULT_OPACITY_LOGIT: f32 = 2.0;

/// Writes Gaussians in the standard 62-property 3DGS layout, binary little endian, with
/// plausible values for what only the centers define: no normals, a mid-grey DC colour,
/// no higher SH bands, small isotropic scales (log 0.01) and the identity rotation.
pub fn write_gaussians_3dgs(
    path: &Path,
    centers: &[[f32; 3]],
    opacity_logit: Option<&[f32]>,
) -> Result<(), Error> {
    check_opacities(path, centers, opacity_logit)?;
    if let Some(i) = centers
        .iter()
        .position(|c| !c.iter().all(|v| v.is_finite()))
    {
        return Err(Error::non_finite(
            path,
            Position::record("vertex", i, None),
            "Gaussian center to write",
            centers[i]
                .iter()
                .copied()
                .find(|v| !v.is_finite())
                .unwrap_or(f32::NAN) as f64,
        ));
    }
    let names = gaussian_3dgs_properties();
    write_gaussian_vertices(path, "", &names, centers.len(), |i, rec| {
        rec[0..3].copy_from_slice(&centers[i]);
        rec[54] = opacity_logit.map_or(DEFAULT_OPACITY_LOGIT, |o| o[i]);
        // f_dc = 0 is SH band 0 at grey 0.5; log-scale of 0.01; quaternion (w,x,y,z) = (1,0,0,0).
        rec[55..58].fill((0.01f32).ln());
        rec[58] = 1.0;
    })
}

/// Writes Gaussian centers (and opacity logits, when given) as a binary little-endian PLY
/// with `float x y z [opacity]`: what every 3DGS tool and this one read, 16 bytes a
/// Gaussian instead of the 248 of the full 3DGS layout.
pub fn write_gaussians_ply(
    path: &Path,
    centers: &[[f32; 3]],
    opacity_logit: Option<&[f32]>,
    comment: &str,
) -> Result<(), Error> {
    check_opacities(path, centers, opacity_logit)?;
    let mut names: Vec<String> = ["x", "y", "z"].map(String::from).to_vec();
    if opacity_logit.is_some() {
        names.push("opacity".into());
    }
    write_gaussian_vertices(path, comment, &names, centers.len(), |i, rec| {
        rec[0..3].copy_from_slice(&centers[i]);
        if let Some(o) = opacity_logit {
            rec[3] = o[i];
        }
    })
}

/// One opacity per center, when opacities are given.
fn check_opacities(
    path: &Path,
    centers: &[[f32; 3]],
    opacity_logit: Option<&[f32]>,
) -> Result<(), Error> {
    match opacity_logit {
        Some(op) if op.len() != centers.len() => Err(Error::Unsupported {
            path: path.to_path_buf(),
            msg: format!(
                "{} opacities for {} centers; give one per Gaussian",
                op.len(),
                centers.len()
            ),
        }),
        _ => Ok(()),
    }
}

/// The one Gaussian writer: a binary little-endian PLY (`comment` lines in its header)
/// whose `n` vertices have the float properties `names`; `fill(i, values)` writes
/// Gaussian `i`'s values (the buffer keeps what the previous call left).
fn write_gaussian_vertices(
    path: &Path,
    comment: &str,
    names: &[String],
    n: usize,
    mut fill: impl FnMut(usize, &mut [f32]),
) -> Result<(), Error> {
    let mut header = String::from("ply\nformat binary_little_endian 1.0\n");
    for line in comment.lines() {
        header.push_str(&format!("comment {line}\n"));
    }
    header.push_str(&format!("element vertex {n}\n"));
    for name in names {
        header.push_str(&format!("property float {name}\n"));
    }
    header.push_str("end_header\n");
    write_atomic(path, |w| {
        w.write_all(header.as_bytes())?;
        let mut rec = vec![0f32; names.len()];
        let mut bytes = vec![0u8; 4 * names.len()];
        for i in 0..n {
            fill(i, &mut rec);
            for (b, v) in bytes.chunks_exact_mut(4).zip(&rec) {
                b.copy_from_slice(&v.to_le_bytes());
            }
            w.write_all(&bytes)?;
        }
        Ok(())
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn numbers_round_trip_without_long_expansions() {
        for x in [0.0, 1.5, -2.110460, 1e-300, 6.02e23, 1e-4, 123456.789, -0.0] {
            let s = num(x);
            assert!(s.len() < 25, "{s}");
            assert_eq!(s.parse::<f64>().unwrap(), x);
        }
    }

    #[test]
    fn line3dpp_text_keeps_the_groups_and_the_order() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("l.txt");
        let s = |x: f64| Segment::from_arrays([x, 0.0, 0.0], [x + 1.0, 0.5, 1e-7]);
        let set = LineSet {
            segments: vec![s(0.0), s(2.0), s(4.0), s(6.0)],
            groups: Some(vec![0, 0, 1, 2]),
        };
        write_lines_line3dpp(&p, &set).unwrap();
        let text = std::fs::read_to_string(&p).unwrap();
        assert_eq!(text.lines().count(), 3, "{text}");
        assert!(
            text.starts_with("2 0 0 0 1 0.5 1e-7 2 0 0 3 0.5 1e-7 0\n"),
            "{text}"
        );
        let back = super::super::read_lines(&p).unwrap();
        assert_eq!(back.format.id, "line3dpp");
        assert_eq!(back.lines.segments, set.segments);
        assert_eq!(back.lines.groups, set.groups);
        let err = write_lines_line3dpp(&dir.path().join("l.obj"), &set).unwrap_err();
        assert!(err.to_string().contains(".txt"), "{err}");
    }

    #[test]
    fn the_3dgs_layout_has_62_properties_in_order() {
        let n = gaussian_3dgs_properties();
        assert_eq!(n.len(), 62);
        assert_eq!(&n[..3], ["x", "y", "z"]);
        assert_eq!(n[54], "opacity");
        assert_eq!(n[55], "scale_0");
        assert_eq!(n[58], "rot_0");
        assert_eq!(n[61], "rot_3");
    }
}
