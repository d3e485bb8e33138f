//! `--gaussians-transform FILE`: the affine map that takes Gaussian centers into the frame
//! of the lines. Two kinds of file: a 4x4 matrix as text (row-major, 16 numbers; `#`
//! comments; a 3x4 `[R | t]` is completed with `0 0 0 1`), which is applied as given, or a
//! nerfstudio `dataparser_transforms.json` (`{"transform": 3x4, "scale": s}`), which says
//! how nerfstudio moved the COLMAP frame (`p_ns = s * (T p)`) and is therefore inverted, or
//! an SDFStudio-format `meta_data.json` as EMAP and EdgeGaussians read it (`"worldtogt"`:
//! 4x4, from the normalized frame the model was trained in to the ground truth's frame),
//! which is applied as given.

use std::path::Path;

use glam::{DMat4, DVec3, DVec4};

use super::error::{Error, Position};

/// An affine map for Gaussian centers, and where it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct GaussianTransform {
    pub matrix: DMat4,
    /// What the file was and what was done with it, for messages and reports.
    pub describe: String,
}

impl GaussianTransform {
    /// Maps every center (in f64) into the lines' frame.
    pub fn apply(&self, centers: &mut [[f32; 3]]) {
        for c in centers {
            let p = self
                .matrix
                .transform_point3(DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64));
            *c = [p.x as f32, p.y as f32, p.z as f32];
        }
    }
}

/// Reads a transform file (matrix text or nerfstudio JSON, told apart by content).
pub fn read_transform(path: &Path) -> Result<GaussianTransform, Error> {
    let bytes = super::input::read_small(path, "a transform", 1 << 20, false)?;
    let text = std::str::from_utf8(&bytes)
        .map_err(|_| Error::unknown(path, "a transform is a text matrix or a JSON file"))?;
    if text.trim().is_empty() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
        });
    }
    if text.trim_start().starts_with('{') {
        nerfstudio(path, text)
    } else {
        matrix_text(path, text)
    }
}

fn rows_to_matrix(path: &Path, v: &[f64], pos: Position) -> Result<DMat4, Error> {
    let mut m = [0.0; 16];
    m[..v.len()].copy_from_slice(v);
    if v.len() == 12 {
        m[15] = 1.0;
    }
    // glam is column-major; the file is row-major.
    let mat = DMat4::from_cols_array(&m).transpose();
    let last = mat.row(3);
    if (last - DVec4::new(0.0, 0.0, 0.0, 1.0)).abs().max_element() > 1e-9 {
        return Err(Error::parse(
            path,
            pos,
            format!(
                "the last row is {} {} {} {}, not 0 0 0 1: a projective matrix cannot move points between frames",
                last.x, last.y, last.z, last.w
            ),
        ));
    }
    let det = mat.determinant();
    if !det.is_finite() || det.abs() < 1e-12 {
        return Err(Error::parse(
            path,
            pos,
            format!("the matrix is singular (determinant {det}); it would collapse the model"),
        ));
    }
    Ok(mat)
}

fn matrix_text(path: &Path, text: &str) -> Result<GaussianTransform, Error> {
    let mut v = Vec::new();
    let mut last_line = 1;
    for (i, line) in text.lines().enumerate() {
        let data = line.split('#').next().unwrap_or("");
        for (k, tok) in data
            .split(|c: char| c.is_whitespace() || c == ',' || c == '[' || c == ']')
            .filter(|t| !t.is_empty())
            .enumerate()
        {
            let x: f64 = tok.parse().map_err(|_| {
                Error::parse(
                    path,
                    Position::LineValue {
                        line: i + 1,
                        value: k + 1,
                    },
                    format!("`{tok}` is not a number (a transform is 16 numbers, a 4x4 matrix row by row)"),
                )
            })?;
            if !x.is_finite() {
                return Err(Error::non_finite(
                    path,
                    Position::LineValue {
                        line: i + 1,
                        value: k + 1,
                    },
                    "matrix entry",
                    x,
                ));
            }
            v.push(x);
            last_line = i + 1;
        }
    }
    if v.len() != 16 && v.len() != 12 {
        return Err(Error::parse(
            path,
            Position::Line(last_line),
            format!(
                "found {} numbers; a transform is a 4x4 matrix (16 numbers, row by row) or a 3x4 [R | t] (12)",
                v.len()
            ),
        ));
    }
    let matrix = rows_to_matrix(path, &v, Position::Line(last_line))?;
    Ok(GaussianTransform {
        matrix,
        describe: format!("{}: 4x4 matrix, applied as given", path.display()),
    })
}

/// The numbers of a JSON matrix (3 or 4 rows of 4), row by row.
fn json_rows(path: &Path, key: &str, t: &serde_json::Value) -> Result<Vec<f64>, Error> {
    let bad = |msg: String| Error::parse(path, Position::Line(1), msg);
    let rows = t
        .as_array()
        .ok_or_else(|| bad(format!("`{key}` is not a list of rows")))?;
    let mut v = Vec::new();
    for (r, row) in rows.iter().enumerate() {
        let row = row
            .as_array()
            .ok_or_else(|| bad(format!("`{key}` row {r} is not a list")))?;
        if row.len() != 4 {
            return Err(bad(format!(
                "`{key}` row {r} has {} numbers, expected 4",
                row.len()
            )));
        }
        for x in row {
            let x = x
                .as_f64()
                .filter(|x| x.is_finite())
                .ok_or_else(|| bad(format!("`{key}` row {r} holds `{x}`, not a finite number")))?;
            v.push(x);
        }
    }
    if v.len() != 12 && v.len() != 16 {
        return Err(bad(format!(
            "`{key}` has {} rows; expected 3 (a 3x4 [R | t]) or 4 (a 4x4 matrix)",
            rows.len()
        )));
    }
    Ok(v)
}

fn nerfstudio(path: &Path, text: &str) -> Result<GaussianTransform, Error> {
    let json: serde_json::Value = serde_json::from_str(text).map_err(|e| {
        Error::parse(
            path,
            Position::LineValue {
                line: e.line(),
                value: e.column(),
            },
            format!("not valid JSON: {e}"),
        )
    })?;
    let bad = |msg: String| Error::parse(path, Position::Line(1), msg);
    if json.get("transform").is_none() {
        if let Some(w) = json.get("worldtogt") {
            let v = json_rows(path, "worldtogt", w)?;
            return Ok(GaussianTransform {
                matrix: rows_to_matrix(path, &v, Position::Line(1))?,
                describe: format!(
                    "{}: `worldtogt` of an SDFStudio meta_data.json (EMAP, EdgeGaussians), applied as given: normalized frame to the ground truth's",
                    path.display()
                ),
            });
        }
    }
    let Some(t) = json.get("transform") else {
        return Err(Error::missing(
            path,
            "a JSON transform needs a `transform` matrix (nerfstudio's dataparser_transforms.json has `transform` and `scale`) or a `worldtogt` matrix (SDFStudio's meta_data.json, as EMAP and EdgeGaussians use)",
        ));
    };
    let v = json_rows(path, "transform", t)?;
    let scale = match json.get("scale") {
        None => 1.0,
        Some(s) => s
            .as_f64()
            .filter(|s| s.is_finite() && *s > 0.0)
            .ok_or_else(|| bad(format!("`scale` is `{s}`, not a positive number")))?,
    };
    let forward =
        DMat4::from_scale(DVec3::splat(scale)) * rows_to_matrix(path, &v, Position::Line(1))?;
    Ok(GaussianTransform {
        matrix: forward.inverse(),
        describe: format!(
            "{}: nerfstudio dataparser transform (scale {scale}), inverted to map the model back to the COLMAP frame",
            path.display()
        ),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(name: &str, text: &str) -> (tempfile::TempDir, std::path::PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        (dir, p)
    }

    #[test]
    fn a_row_major_matrix_moves_points_as_written() {
        let (_d, p) = write(
            "m.txt",
            "# scale 2 and move x by 10\n2 0 0 10\n0 2 0 0\n0 0 2 0\n0 0 0 1\n",
        );
        let t = read_transform(&p).unwrap();
        let mut c = [[1.0f32, 2.0, 3.0]];
        t.apply(&mut c);
        assert_eq!(c[0], [12.0, 4.0, 6.0]);
    }

    #[test]
    fn nerfstudio_transforms_are_inverted() {
        // p_ns = 0.5 * (R p + t) with R a quarter turn about z and t = (1, 2, 3).
        let (_d, p) = write(
            "dataparser_transforms.json",
            r#"{"transform": [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3]], "scale": 0.5}"#,
        );
        let t = read_transform(&p).unwrap();
        let colmap = DVec3::new(4.0, -1.0, 2.5);
        let r = DVec3::new(-colmap.y, colmap.x, colmap.z) + DVec3::new(1.0, 2.0, 3.0);
        let ns = r * 0.5;
        let mut c = [[ns.x as f32, ns.y as f32, ns.z as f32]];
        t.apply(&mut c);
        for k in 0..3 {
            assert!((c[0][k] as f64 - colmap[k]).abs() < 1e-6, "{:?}", c[0]);
        }
    }

    #[test]
    fn sdfstudio_meta_data_worldtogt_is_applied_as_given() {
        // EMAP's meta_data.json: worldtogt = inverse of "to the unit cube" (scale 0.25
        // about center (10, 20, 30)), with the frames and the scene box around it.
        let (_d, p) = write(
            "meta_data.json",
            r#"{"camera_model": "OPENCV", "height": 400, "width": 400,
                "worldtogt": [[4, 0, 0, 10], [0, 4, 0, 20], [0, 0, 4, 30], [0, 0, 0, 1]],
                "scene_box": {"aabb": [[-1, -1, -1], [1, 1, 1]]}, "frames": []}"#,
        );
        let t = read_transform(&p).unwrap();
        let mut c = [[0.5f32, -0.25, 1.0]];
        t.apply(&mut c);
        assert_eq!(c[0], [12.0, 19.0, 34.0]);
        assert!(t.describe.contains("worldtogt"), "{}", t.describe);
        let (_d, p) = write(
            "meta_data.json",
            r#"{"worldtogt": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1]]}"#,
        );
        assert!(read_transform(&p)
            .unwrap_err()
            .to_string()
            .contains("projective"));
        let (_d, p) = write("meta_data.json", r#"{"worldtogt": [[1, 0, 0], [0, 1, 0]]}"#);
        let e = read_transform(&p).unwrap_err().to_string();
        assert!(e.contains("`worldtogt` row 0 has 3 numbers"), "{e}");
    }

    #[test]
    fn bad_transforms_name_the_place() {
        let (_d, p) = write("m.txt", "1 0 0 0\n0 1 0 0\n0 0 x 0\n0 0 0 1\n");
        let e = read_transform(&p).unwrap_err();
        assert!(e.to_string().contains("line 3, value 3"), "{e}");
        let (_d, p) = write("m.txt", "1 0 0\n0 1 0\n");
        assert!(read_transform(&p)
            .unwrap_err()
            .to_string()
            .contains("found 6 numbers"));
        let (_d, p) = write("m.txt", "0 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n");
        assert!(read_transform(&p)
            .unwrap_err()
            .to_string()
            .contains("singular"));
        let (_d, p) = write("m.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 1 1\n");
        assert!(read_transform(&p)
            .unwrap_err()
            .to_string()
            .contains("projective"));
        let (_d, p) = write("t.json", r#"{"scale": 2}"#);
        assert!(read_transform(&p)
            .unwrap_err()
            .to_string()
            .contains("`transform`"));
        let (_d, p) = write(
            "t.json",
            r#"{"transform": [[1,0,0,0],[0,1,0,0],[0,0,1,0]], "scale": -1}"#,
        );
        assert!(read_transform(&p)
            .unwrap_err()
            .to_string()
            .contains("`scale`"));
    }
}
