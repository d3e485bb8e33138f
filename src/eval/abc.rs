//! Ground truth straight from an ABC model: its feature file (`*_features_*.yml`: every
//! curve with its type, `sharp` flag and the mesh vertices it runs through), its mesh
//! (`*_trimesh_*.obj`, the vertices those indices name, in the model's own units) and
//! its `chunk_*_stats.json` entry (the bounding box that defines the unit-cube frame of
//! the ABC-NEF renders: `scale = 1 / largest extent`, `offset = 0.5 - scale * centre`).
//!
//! The feature file is YAML; only the subset ABC writes is read (a `curves:` list of
//! maps whose values are scalars, `[...]` lists, possibly over several lines, or block
//! lists), so no YAML crate is needed.

use crate::eval::gt::GtEdges;
use crate::geom::Segment;
use crate::io::{Error, Position};
use glam::DVec3;
use std::path::Path;

/// The curve types of ABC feature files.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CurveKind {
    Line,
    Circle,
    Ellipse,
    BSpline,
}

impl CurveKind {
    fn parse(s: &str) -> Option<CurveKind> {
        Some(match s {
            "Line" => CurveKind::Line,
            "Circle" => CurveKind::Circle,
            "Ellipse" => CurveKind::Ellipse,
            "BSpline" => CurveKind::BSpline,
            _ => return None,
        })
    }
}

/// One curve of a feature file.
#[derive(Clone, Debug, PartialEq)]
pub struct Curve {
    pub kind: CurveKind,
    pub sharp: bool,
    /// Mesh vertices along the curve, in order (0-based).
    pub vert_indices: Vec<usize>,
    /// The curve parameter at each of those vertices.
    pub vert_parameters: Vec<f64>,
    /// 1-based line of the curve's entry in the feature file.
    pub line: usize,
}

fn read_text(path: &Path) -> Result<String, Error> {
    std::fs::read_to_string(path).map_err(|cause| Error::Io {
        path: path.to_path_buf(),
        action: "read",
        cause,
    })
}

/// A map entry being read: key, value text (continuation lines joined), its line.
struct Field {
    key: String,
    value: String,
    line: usize,
}

fn parse_list<T: std::str::FromStr>(path: &Path, f: &Field, curve: usize) -> Result<Vec<T>, Error> {
    let v = f.value.trim();
    let body = if let Some(inner) = v.strip_prefix('[') {
        inner.strip_suffix(']').ok_or_else(|| {
            Error::parse(
                path,
                Position::Line(f.line),
                format!("curve {curve}: `{}` has no closing `]`", f.key),
            )
        })?
    } else {
        v
    };
    body.split([',', ' '])
        .map(str::trim)
        .filter(|t| !t.is_empty() && *t != "-")
        .enumerate()
        .map(|(i, t)| {
            t.parse::<T>().map_err(|_| {
                Error::parse(
                    path,
                    Position::Line(f.line),
                    format!(
                        "curve {curve}: `{}` value {} is `{t}`, not a number of the expected kind",
                        f.key,
                        i + 1
                    ),
                )
            })
        })
        .collect()
}

fn curve_of(path: &Path, fields: &[Field], start: usize, curve: usize) -> Result<Curve, Error> {
    let get = |k: &str| fields.iter().find(|f| f.key == k);
    let missing = |k: &str| {
        Error::parse(
            path,
            Position::Line(start),
            format!("curve {curve} has no `{k}`"),
        )
    };
    let t = get("type").ok_or_else(|| missing("type"))?;
    let kind = CurveKind::parse(t.value.trim()).ok_or_else(|| {
        Error::parse(
            path,
            Position::Line(t.line),
            format!(
                "curve {curve}: unknown curve type `{}`; expected Line, Circle, Ellipse or BSpline",
                t.value.trim()
            ),
        )
    })?;
    let s = get("sharp").ok_or_else(|| missing("sharp"))?;
    let sharp = match s.value.trim() {
        "true" | "True" => true,
        "false" | "False" => false,
        other => {
            return Err(Error::parse(
                path,
                Position::Line(s.line),
                format!("curve {curve}: `sharp` is `{other}`, not true or false"),
            ))
        }
    };
    let vi = get("vert_indices").ok_or_else(|| missing("vert_indices"))?;
    let vert_indices: Vec<usize> = parse_list(path, vi, curve)?;
    let vert_parameters: Vec<f64> = match get("vert_parameters") {
        Some(f) => parse_list(path, f, curve)?,
        None => Vec::new(),
    };
    Ok(Curve {
        kind,
        sharp,
        vert_indices,
        vert_parameters,
        line: start,
    })
}

/// Parses the `curves:` list of a feature file's text (`path` names it in errors).
pub fn parse_features(text: &str, path: &Path) -> Result<Vec<Curve>, Error> {
    let mut curves = Vec::new();
    let mut in_curves = false;
    let mut seen_curves = false;
    let mut fields: Vec<Field> = Vec::new();
    let mut start = 0usize;
    let flush = |fields: &mut Vec<Field>, start: usize, curves: &mut Vec<Curve>| {
        if fields.is_empty() {
            return Ok(());
        }
        let c = curve_of(path, fields, start, curves.len())?;
        curves.push(c);
        fields.clear();
        Ok::<(), Error>(())
    };
    for (i, raw) in text.lines().enumerate() {
        let ln = i + 1;
        let line = raw.trim_end();
        if line.trim().is_empty() || line.trim_start().starts_with('#') {
            continue;
        }
        let indent = line.len() - line.trim_start().len();
        if indent == 0 && !line.starts_with('-') {
            // A top-level key: `curves:` starts the list, any other ends it.
            flush(&mut fields, start, &mut curves)?;
            in_curves = line.starts_with("curves:");
            if in_curves {
                seen_curves = true;
                if line["curves:".len()..].trim() == "[]" {
                    in_curves = false;
                }
            }
            continue;
        }
        if !in_curves {
            continue;
        }
        let (body, new_item) = if indent == 0 {
            (line[1..].trim_start(), true)
        } else {
            (line.trim_start(), false)
        };
        if new_item {
            flush(&mut fields, start, &mut curves)?;
            start = ln;
        }
        // A key of the current item sits at the item's indent (2) and is `key: ...`;
        // anything deeper, or a `- ` block item, continues the previous key's value.
        let is_key = (new_item || indent == 2)
            && !body.starts_with('-')
            && !body.starts_with('[')
            && body.split_once(':').is_some_and(|(k, _)| {
                !k.is_empty() && k.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
            });
        if is_key {
            let (k, v) = body.split_once(':').expect("checked");
            fields.push(Field {
                key: k.to_string(),
                value: v.trim().to_string(),
                line: ln,
            });
        } else if let Some(f) = fields.last_mut() {
            f.value.push(' ');
            f.value.push_str(body);
        } else {
            return Err(Error::parse(
                path,
                Position::Line(ln),
                "expected `- key: value` starting a curve of the `curves:` list",
            ));
        }
    }
    flush(&mut fields, start, &mut curves)?;
    if !seen_curves {
        return Err(Error::parse(
            path,
            Position::Line(1),
            "no `curves:` list: not an ABC feature file",
        ));
    }
    Ok(curves)
}

/// Reads an ABC feature file.
pub fn read_features(path: &Path) -> Result<Vec<Curve>, Error> {
    parse_features(&read_text(path)?, path)
}

/// The `v x y z` vertices of an OBJ mesh, in file order (io's OBJ reader).
pub fn read_obj_vertices(path: &Path) -> Result<Vec<DVec3>, Error> {
    let text = read_text(path)?;
    let obj = crate::io::obj::parse(path, &text, "vertex coordinate")?;
    Ok(obj
        .vertices
        .into_iter()
        .map(|(_, p)| DVec3::from_array(p))
        .collect())
}

/// The map from an ABC model's units to the unit-cube frame: `p * scale + offset`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Normalization {
    pub scale: f64,
    pub offset: DVec3,
}

impl Normalization {
    /// EMAP's `get_gt_points`: `scale = 1 / max(ranges)`, `offset = 0.5 - centre * scale`.
    pub fn from_bbox(min: DVec3, max: DVec3, range: DVec3) -> Normalization {
        let scale = 1.0 / range.max_element();
        let centre = DVec3::new(
            (min.x + max.x) / 2.0,
            (min.y + max.y) / 2.0,
            (min.z + max.z) / 2.0,
        ) * scale;
        Normalization {
            scale,
            offset: DVec3::splat(0.5) - centre,
        }
    }

    /// From the mesh's own vertices (off by up to ~1e-4 from the stats file's box).
    pub fn from_vertices(v: &[DVec3]) -> Normalization {
        let lo = v
            .iter()
            .copied()
            .fold(DVec3::splat(f64::INFINITY), DVec3::min);
        let hi = v
            .iter()
            .copied()
            .fold(DVec3::splat(f64::NEG_INFINITY), DVec3::max);
        Normalization::from_bbox(lo, hi, hi - lo)
    }

    pub fn apply(&self, p: DVec3) -> DVec3 {
        p * self.scale + self.offset
    }
}

/// The model's entry of a `chunk_*_stats.json` (the whole chunk's file or one entry):
/// the one keyed `model` (the feature file's 8-digit id), or the only entry.
pub fn read_stats(path: &Path, model: Option<&str>) -> Result<Normalization, Error> {
    let text = read_text(path)?;
    let bad = |msg: String| Error::parse(path, Position::Line(1), msg);
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| bad(format!("not JSON: {e}")))?;
    let obj = json
        .as_object()
        .ok_or_else(|| bad("expected an object keyed by model id".into()))?;
    let entry = match model.and_then(|m| obj.get(m)) {
        Some(e) => e,
        None if obj.len() == 1 => obj.values().next().expect("one"),
        None => {
            return Err(bad(format!(
                "no entry for model {} among {} entries",
                model.unwrap_or("(unknown id)"),
                obj.len()
            )))
        }
    };
    let b: Vec<f64> = entry
        .get("bbox")
        .and_then(|b| b.as_array())
        .map(|a| a.iter().filter_map(|x| x.as_f64()).collect())
        .unwrap_or_default();
    if b.len() != 9 || b.iter().any(|x| !x.is_finite()) || b[6..9].iter().any(|&r| r <= 0.0) {
        return Err(bad(
            "`bbox` must be 9 finite numbers: min x y z, max x y z, positive ranges x y z".into(),
        ));
    }
    Ok(Normalization::from_bbox(
        DVec3::new(b[0], b[1], b[2]),
        DVec3::new(b[3], b[4], b[5]),
        DVec3::new(b[6], b[7], b[8]),
    ))
}

/// ABC ground truth of one model, in the unit-cube frame.
#[derive(Clone, Debug)]
pub struct AbcGroundTruth {
    pub curves: Vec<Curve>,
    pub vertices: Vec<DVec3>,
    pub norm: Normalization,
    /// What the reader would have the user know (no stats file).
    pub warnings: Vec<String>,
}

impl AbcGroundTruth {
    /// Reads the feature file and the mesh, checks every vertex index against the mesh,
    /// and normalizes with the stats file (or, with a warning, the mesh's box).
    pub fn read(
        features: &Path,
        mesh: &Path,
        stats: Option<&Path>,
    ) -> Result<AbcGroundTruth, Error> {
        let curves = read_features(features)?;
        let vertices = read_obj_vertices(mesh)?;
        for (i, c) in curves.iter().enumerate() {
            if let Some(&bad) = c.vert_indices.iter().find(|&&v| v >= vertices.len()) {
                return Err(Error::parse(
                    features,
                    Position::Line(c.line),
                    format!(
                        "curve {i}: vertex index {bad} is beyond the {} vertices of {}",
                        vertices.len(),
                        mesh.display()
                    ),
                ));
            }
        }
        let mut warnings = Vec::new();
        let norm = match stats {
            Some(s) => {
                let name = features.file_name().and_then(|n| n.to_str()).unwrap_or("");
                let id = name
                    .get(..8)
                    .filter(|p| p.bytes().all(|b| b.is_ascii_digit()));
                read_stats(s, id)?
            }
            None => {
                warnings.push(format!(
                    "{}: no --abc-stats: normalizing by the mesh's own bounding box, which can \
                     differ from the ABC-NEF frame (the stats file's box) by about 1e-4",
                    mesh.display()
                ));
                Normalization::from_vertices(&vertices)
            }
        };
        Ok(AbcGroundTruth {
            curves,
            vertices,
            norm,
            warnings,
        })
    }

    /// The sharp curves as GT edges (EMAP's `edge_type="all"`), or the sharp straight
    /// lines only: polylines in the model's units with the normalization.
    pub fn edges(&self, lines_only: bool) -> GtEdges {
        let polylines = self
            .curves
            .iter()
            .filter(|c| c.sharp && (!lines_only || c.kind == CurveKind::Line))
            .map(|c| c.vert_indices.iter().map(|&i| self.vertices[i]).collect())
            .collect();
        GtEdges {
            polylines,
            scale: self.norm.scale,
            offset: self.norm.offset,
            points: None,
        }
    }

    /// Each sharp `Line` as one segment between its vertices at the smallest and the
    /// largest curve parameter, in the unit-cube frame.
    pub fn line_segments(&self) -> Vec<Segment> {
        self.curves
            .iter()
            .filter(|c| c.sharp && c.kind == CurveKind::Line && c.vert_indices.len() >= 2)
            .map(|c| {
                let (mut lo, mut hi) = (0, c.vert_indices.len() - 1);
                if c.vert_parameters.len() == c.vert_indices.len() {
                    let by = |a: &usize, b: &usize| {
                        c.vert_parameters[*a].total_cmp(&c.vert_parameters[*b])
                    };
                    let idx: Vec<usize> = (0..c.vert_indices.len()).collect();
                    lo = *idx.iter().min_by(|a, b| by(a, b)).expect("non-empty");
                    hi = *idx.iter().max_by(|a, b| by(a, b)).expect("non-empty");
                }
                let p = |k: usize| self.norm.apply(self.vertices[c.vert_indices[k]]);
                Segment::new(p(lo), p(hi))
            })
            .collect()
    }

    /// Sharp curves per kind: (lines, circles, ellipses, B-splines), and the non-sharp.
    pub fn counts(&self) -> ([usize; 4], usize) {
        let mut k = [0usize; 4];
        let mut not_sharp = 0;
        for c in &self.curves {
            if !c.sharp {
                not_sharp += 1;
                continue;
            }
            k[match c.kind {
                CurveKind::Line => 0,
                CurveKind::Circle => 1,
                CurveKind::Ellipse => 2,
                CurveKind::BSpline => 3,
            }] += 1;
        }
        (k, not_sharp)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const P: &str = "model_features.yml";

    #[test]
    fn reads_flow_block_and_multiline_values() {
        let text = "curves:\n- closed: false\n  poles:\n  - [1.0, 2.0, 3.0]\n  - [4.0, 5.0, 6.0]\n  sharp: true\n  type: BSpline\n  vert_indices: [0, 20,\n    21, 1]\n  vert_parameters: [0.5, 1.0,\n    1.5, 2.0]\n- sharp: false\n  type: Line\n  vert_indices:\n  - 3\n  - 4\nsurfaces:\n- type: Plane\n  vert_indices: [9]\n";
        let c = parse_features(text, Path::new(P)).unwrap();
        assert_eq!(c.len(), 2);
        assert_eq!(c[0].kind, CurveKind::BSpline);
        assert!(c[0].sharp);
        assert_eq!(c[0].vert_indices, vec![0, 20, 21, 1]);
        assert_eq!(c[0].vert_parameters, vec![0.5, 1.0, 1.5, 2.0]);
        assert_eq!(c[0].line, 2);
        assert_eq!(c[1].kind, CurveKind::Line);
        assert!(!c[1].sharp);
        assert_eq!(c[1].vert_indices, vec![3, 4]);
        assert_eq!(c[1].line, 12);
    }

    #[test]
    fn unknown_type_names_the_line() {
        let text = "curves:\n- sharp: true\n  type: Hyperbola\n  vert_indices: [0, 1]\n";
        let e = parse_features(text, Path::new(P)).unwrap_err().to_string();
        assert!(e.contains("model_features.yml: line 3"), "{e}");
        assert!(e.contains("unknown curve type `Hyperbola`"), "{e}");
    }

    #[test]
    fn bad_index_value_is_an_error() {
        let text = "curves:\n- sharp: true\n  type: Line\n  vert_indices: [0, x1]\n";
        let e = parse_features(text, Path::new(P)).unwrap_err().to_string();
        assert!(e.contains("line 4") && e.contains("`x1`"), "{e}");
    }

    #[test]
    fn normalization_maps_the_box_into_the_unit_cube() {
        let n = Normalization::from_bbox(
            DVec3::new(-2.0, -1.0, 0.0),
            DVec3::new(2.0, 1.0, 1.0),
            DVec3::new(4.0, 2.0, 1.0),
        );
        assert_eq!(n.scale, 0.25);
        assert_eq!(
            n.apply(DVec3::new(-2.0, -1.0, 0.0)),
            DVec3::new(0.0, 0.25, 0.375)
        );
        assert_eq!(
            n.apply(DVec3::new(2.0, 1.0, 1.0)),
            DVec3::new(1.0, 0.75, 0.625)
        );
    }
}
