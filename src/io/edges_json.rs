//! EMAP and EdgeGaussians `parametric_edges.json`: `lines_end_pts` (straight edges, 6
//! numbers each, however nested) and `curves_ctl_pts` (cubic Bézier curves, 4 control
//! points each). Curves are not segments: they are counted and skipped with a warning, or,
//! with `--curves polyline`, sampled into [`POLYLINE_PIECES`] segments each that share one
//! group (so the collinear merge may join the straight parts back).

use std::path::Path;

use crate::geom::Segment;

use super::error::{Error, Position};
use super::format::{self, Curves, Detect, LineFormat, Origin, Parsed};

pub(crate) static FORMAT: LineFormat = LineFormat {
    id: "emap",
    name: "EMAP/EdgeGaussians parametric edges (JSON)",
    extensions: &["json"],
    summary: "EMAP / EdgeGaussians `parametric_edges.json` (`lines_end_pts`; Bézier \
              `curves_ctl_pts` counted and skipped, or sampled with `--curves polyline`)",
    help: Some("EMAP/EdgeGaussians `parametric_edges.json`"),
    hint: Some("EMAP/EdgeGaussians parametric_edges.json"),
    rank: 10,
    detect: Detect::Text(|p| p.text.is_some_and(looks_like_edges)),
    parse: |path, bytes, opts| {
        let (segments, groups, warnings) = parse(path, format::text(path, bytes)?, opts.curves)?;
        let mut p = Parsed::new(Origin::Records("edge"));
        p.segments = segments;
        p.groups = groups;
        p.warnings = warnings;
        Ok(p)
    },
    read_folder: None,
};

/// Segments a Bézier curve becomes with `--curves polyline`.
pub const POLYLINE_PIECES: usize = 16;

/// A JSON object with one of the edge keys.
pub(crate) fn looks_like_edges(text: &str) -> bool {
    text.trim_start().starts_with('{')
        && (text.contains("\"lines_end_pts\"") || text.contains("\"curves_ctl_pts\""))
}

/// A JSON value where an edge file needs a number (or an array of numbers), as written.
#[derive(Debug, thiserror::Error)]
#[error("`{0}` is not a number")]
struct NotANumber(serde_json::Value);

/// Every number under `v`, depth first, with the first non-number found.
fn flatten(v: &serde_json::Value, out: &mut Vec<f64>) -> Result<(), NotANumber> {
    match v {
        serde_json::Value::Array(a) => a.iter().try_for_each(|x| flatten(x, out)),
        serde_json::Value::Number(n) => {
            out.push(n.as_f64().unwrap_or(f64::NAN));
            Ok(())
        }
        other => Err(NotANumber(other.clone())),
    }
}

fn numbers(
    path: &Path,
    json: &serde_json::Value,
    key: &str,
    per: usize,
) -> Result<Vec<f64>, Error> {
    let Some(v) = json.get(key) else {
        return Ok(Vec::new());
    };
    let mut out = Vec::new();
    flatten(v, &mut out).map_err(|msg| {
        Error::parse(
            path,
            Position::RowValue {
                row: out.len() / per,
                value: out.len() % per,
            },
            format!("`{key}`: {msg}"),
        )
    })?;
    if out.len() % per != 0 {
        return Err(Error::parse(
            path,
            Position::RowValue {
                row: out.len() / per,
                value: out.len() % per,
            },
            format!(
                "`{key}` holds {} numbers, not a multiple of {per} ({})",
                out.len(),
                if per == 6 {
                    "two 3D endpoints a line"
                } else {
                    "four 3D control points a curve"
                }
            ),
        ));
    }
    if let Some(i) = out.iter().position(|x| !x.is_finite()) {
        return Err(Error::non_finite(
            path,
            Position::RowValue {
                row: i / per,
                value: i % per,
            },
            "line coordinate",
            out[i],
        ));
    }
    Ok(out)
}

/// Segments, their groups (only with sampled curves) and warnings.
pub(crate) type Edges = (Vec<Segment>, Option<Vec<u32>>, Vec<String>);

/// Straight edges, their groups (only with sampled curves) and warnings.
pub(crate) fn parse(path: &Path, text: &str, curves: Curves) -> Result<Edges, Error> {
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
    if !json.is_object()
        || (json.get("lines_end_pts").is_none() && json.get("curves_ctl_pts").is_none())
    {
        return Err(Error::missing(
            path,
            "an edge file (EMAP, EdgeGaussians parametric_edges.json) has `lines_end_pts` or `curves_ctl_pts`, and this JSON has neither",
        ));
    }
    let lines = numbers(path, &json, "lines_end_pts", 6)?;
    let ctl = numbers(path, &json, "curves_ctl_pts", 12)?;
    let mut segs: Vec<Segment> = lines
        .chunks_exact(6)
        .map(|v| Segment::from_arrays([v[0], v[1], v[2]], [v[3], v[4], v[5]]))
        .collect();
    let n_curves = ctl.len() / 12;
    let mut warnings = Vec::new();
    let mut groups = None;
    match curves {
        Curves::Skip if n_curves > 0 => warnings.push(format!(
            "{}: skipped {n_curves} Bézier curve{} (`curves_ctl_pts`); --curves polyline samples each into {POLYLINE_PIECES} segments",
            path.display(),
            if n_curves == 1 { "" } else { "s" }
        )),
        Curves::Polyline if n_curves > 0 => {
            let mut g: Vec<u32> = (0..segs.len() as u32).collect();
            for (c, p) in ctl.chunks_exact(12).enumerate() {
                let pt = |k: usize| glam::DVec3::new(p[3 * k], p[3 * k + 1], p[3 * k + 2]);
                let (b0, b1, b2, b3) = (pt(0), pt(1), pt(2), pt(3));
                let at = |t: f64| {
                    let s = 1.0 - t;
                    b0 * (s * s * s) + b1 * (3.0 * s * s * t) + b2 * (3.0 * s * t * t) + b3 * (t * t * t)
                };
                for k in 0..POLYLINE_PIECES {
                    let t0 = k as f64 / POLYLINE_PIECES as f64;
                    let t1 = (k + 1) as f64 / POLYLINE_PIECES as f64;
                    segs.push(Segment::new(at(t0), at(t1)));
                    g.push((lines.len() / 6 + c) as u32);
                }
            }
            groups = Some(g);
        }
        _ => {}
    }
    Ok((segs, groups, warnings))
}

/// `segments` as an EMAP / EdgeGaussians `parametric_edges.json`: every segment in
/// `lines_end_pts` (`[x1, y1, z1, x2, y2, z2]`), no curves.
pub fn edges_json_text(segments: &[Segment]) -> String {
    let rows: Vec<String> = segments
        .iter()
        .map(|s| {
            let v: Vec<String> =
                s.p1.to_array()
                    .iter()
                    .chain(&s.p2.to_array())
                    .map(|x| serde_json::Number::from_f64(*x).map_or("0".into(), |n| n.to_string()))
                    .collect();
            format!("[{}]", v.join(", "))
        })
        .collect();
    format!(
        "{{\"curves_ctl_pts\": [], \"lines_end_pts\": [\n{}\n]}}\n",
        rows.join(",\n")
    )
}
