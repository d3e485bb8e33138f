//! Ground-truth metrics against reference edges, in two protocols ([`Protocol`]).
//!
//! `exact`: both sets are sampled every `step` along their segments; accuracy is the
//! mean distance from predicted samples to the nearest GT sample, completeness the
//! reverse; precision / recall / F at each threshold count distances `<=` it.
//!
//! `emap`: the ABC-NEF protocol exactly as EMAP's `src/eval/eval_ABC.py` and
//! `eval_util.py` compute it (and CurveGaussian, SketchSplat, EdgeGaussians reuse): GT
//! polylines sampled at 0.005 in their own (raw ABC) units with `floor(L / 0.005)` points
//! by `linspace` per polyline piece, then moved into the unit cube; predicted segments
//! sampled the same way in the frame; the predicted samples averaged per voxel of a
//! 256^3 grid over [-1, 1]^3; distances in single precision; `<` thresholds.

use crate::eval::kdtree::KdTree;
use crate::geom::Segment;
use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

/// How predictions are scored against the ground truth.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Protocol {
    /// Both sets sampled every 0.005 (both ends included), every sample scored, `<=`
    /// thresholds: continuous distances, no grid.
    #[default]
    Exact,
    /// EMAP's ABC-NEF evaluation, rule for rule (what the published tables report).
    Emap,
}

impl Protocol {
    pub fn name(self) -> &'static str {
        match self {
            Protocol::Exact => "exact",
            Protocol::Emap => "emap",
        }
    }
}

/// Ground-truth edges: polylines in their source's units and the map into the lines'
/// frame (`p * scale + offset`), or points already sampled in that frame.
#[derive(Clone, Debug, PartialEq)]
pub struct GtEdges {
    pub polylines: Vec<Vec<DVec3>>,
    pub scale: f64,
    pub offset: DVec3,
    /// Sampled GT points (EMAP / EdgeGaussians `*_0.005.ply`), used as they are.
    pub points: Option<Vec<DVec3>>,
}

impl GtEdges {
    /// Straight segments already in the lines' frame.
    pub fn from_segments(segs: &[Segment]) -> GtEdges {
        GtEdges {
            polylines: segs.iter().map(|s| vec![s.p1, s.p2]).collect(),
            scale: 1.0,
            offset: DVec3::ZERO,
            points: None,
        }
    }

    /// Points already sampled along the edges, in the lines' frame.
    pub fn from_points(points: Vec<DVec3>) -> GtEdges {
        GtEdges {
            polylines: Vec::new(),
            scale: 1.0,
            offset: DVec3::ZERO,
            points: Some(points),
        }
    }

    /// Every polyline piece as a segment in the lines' frame.
    pub fn segments(&self) -> Vec<Segment> {
        let f = |p: DVec3| p * self.scale + self.offset;
        self.polylines
            .iter()
            .flat_map(|pl| pl.windows(2).map(|w| Segment::new(f(w[0]), f(w[1]))))
            .collect()
    }

    /// The `exact` protocol's GT samples.
    fn exact_samples(&self, step: f64) -> Vec<DVec3> {
        match &self.points {
            Some(p) => p.clone(),
            None => sample(&self.segments(), step),
        }
    }

    /// EMAP's GT samples (`get_gt_points`): per polyline piece from `a` to `b`,
    /// `floor(|b - a| / 0.005)` points `t a + (1 - t) b` at `t = linspace(0, 1, n)` in
    /// the source's units, then mapped into the frame and rounded to `f32`.
    pub fn emap_samples(&self) -> Vec<[f32; 3]> {
        if let Some(p) = &self.points {
            return p.iter().map(|q| q.as_vec3().to_array()).collect();
        }
        let mut out = Vec::new();
        for pl in &self.polylines {
            for w in pl.windows(2) {
                let (a, b) = (w[0], w[1]);
                let n = floor_div((b - a).length(), STEP);
                for t in linspace(n) {
                    let p = DVec3::new(
                        t * a.x + (1.0 - t) * b.x,
                        t * a.y + (1.0 - t) * b.y,
                        t * a.z + (1.0 - t) * b.z,
                    );
                    let q = p * self.scale + self.offset;
                    out.push(q.as_vec3().to_array());
                }
            }
        }
        out
    }
}

/// Reads a ground-truth file: edges in any line format, or a `.ply` whose header declares
/// vertices and no edges (sampled GT points, EMAP / EdgeGaussians `*_0.005.ply`). Also
/// returns the reader's warnings.
pub fn read_gt_file(path: &std::path::Path) -> Result<(GtEdges, Vec<String>), crate::io::Error> {
    let is_ply = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
    if is_ply {
        let mut head = vec![0u8; 4096];
        let n = std::fs::File::open(path)
            .and_then(|mut f| std::io::Read::read(&mut f, &mut head))
            .map_err(|cause| crate::io::Error::Io {
                path: path.to_path_buf(),
                action: "read",
                cause,
            })?;
        let text = String::from_utf8_lossy(&head[..n]);
        let header = text.split("end_header").next().unwrap_or("");
        if header.contains("element vertex") && !header.contains("element edge") {
            let cloud = crate::io::read_gaussians(path, &Default::default())?;
            let pts = cloud
                .centers
                .iter()
                .map(|c| c.map(f64::from).into())
                .collect();
            return Ok((GtEdges::from_points(pts), Vec::new()));
        }
    }
    let f = crate::io::read_lines(path)?;
    Ok((GtEdges::from_segments(&f.lines.segments), f.warnings))
}

/// The ground truth and the protocol to score against it.
#[derive(Clone, Debug, PartialEq)]
pub struct Reference {
    pub edges: GtEdges,
    pub protocol: Protocol,
}

impl Reference {
    pub fn measure(&self, predicted: &[Segment]) -> GtMetrics {
        match self.protocol {
            Protocol::Exact => exact_metrics(predicted, &self.edges, STEP, &THRESHOLDS),
            Protocol::Emap => emap_metrics(predicted, &self.edges),
        }
    }
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GtScore {
    pub threshold: f64,
    pub precision: f64,
    pub recall: f64,
    pub f_score: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GtMetrics {
    /// The protocol the numbers follow.
    #[serde(default)]
    pub protocol: Protocol,
    pub step: f64,
    /// Predicted samples scored (`emap`: after the voxel averaging).
    pub predicted_samples: usize,
    pub gt_samples: usize,
    /// Mean distance predicted -> GT.
    pub accuracy: Option<f64>,
    /// Mean distance GT -> predicted.
    pub completeness: Option<f64>,
    pub scores: Vec<GtScore>,
    /// The smallest predicted -> GT distance (null without samples): far above the
    /// thresholds when the ground truth is in another frame than the lines.
    #[serde(default)]
    pub closest: Option<f64>,
}

impl GtMetrics {
    /// Accuracy and completeness in the unit the protocol reports them in: `emap`
    /// prints "mm" (unit-cube units x 1000, as the papers do), `exact` the lines' units.
    pub fn distance_scale(&self) -> f64 {
        match self.protocol {
            Protocol::Exact => 1.0,
            Protocol::Emap => 1000.0,
        }
    }
}

/// The thresholds of the ABC-NEF protocol.
pub const THRESHOLDS: [f64; 3] = [0.005, 0.01, 0.02];
/// Sampling step of the ABC-NEF protocol.
pub const STEP: f64 = 0.005;

/// Points every `step` along each segment, both endpoints included.
pub fn sample(segments: &[Segment], step: f64) -> Vec<DVec3> {
    let mut out = Vec::new();
    for s in segments {
        let l = s.length();
        let n = (l / step).ceil().max(1.0) as usize;
        for i in 0..=n {
            out.push(s.p1 + (s.p2 - s.p1) * (i as f64 / n as f64));
        }
    }
    out
}

/// Distance from each point of `from` to its nearest point of `to` (a k-d tree; exact).
pub fn nearest_distances(from: &[DVec3], to: &[DVec3]) -> Vec<f64> {
    if to.is_empty() {
        return vec![f64::INFINITY; from.len()];
    }
    let tree = KdTree::new(to);
    from.par_iter()
        .map(|&p| tree.nearest(p).map_or(f64::INFINITY, |(_, d2)| d2.sqrt()))
        .collect()
}

/// Python's (and NumPy's) float floor division `a // b` for `a >= 0`, `b > 0`, as an
/// integer: through `fmod`, so a quotient that rounds up to an integer is not floored
/// up (`floor(a / b)` would be one more there).
pub fn floor_div(a: f64, b: f64) -> usize {
    let m = a % b;
    let div = (a - m) / b;
    let mut f = div.floor();
    if div - f > 0.5 {
        f += 1.0;
    }
    f.max(0.0) as usize
}

/// NumPy's `linspace(0, 1, n)`: `i * (1 / (n - 1))`, the last exactly 1; `[0]` for 1.
pub fn linspace(n: usize) -> impl Iterator<Item = f64> {
    let step = if n > 1 { 1.0 / (n - 1) as f64 } else { 0.0 };
    (0..n).map(move |i| {
        if n > 1 && i == n - 1 {
            1.0
        } else {
            i as f64 * step
        }
    })
}

/// EMAP's predicted samples (`get_pred_points_and_directions`): per segment
/// `floor(L / 0.005)` points `(1 - t) p1 + t p2` at `t = linspace(0, 1, n)`, in `f32`.
pub fn emap_predicted_samples(segments: &[Segment]) -> Vec<[f32; 3]> {
    let mut out = Vec::new();
    for s in segments {
        let n = floor_div((s.p1 - s.p2).length(), STEP);
        for t in linspace(n) {
            let p = (1.0 - t) * s.p1 + t * s.p2;
            out.push(p.as_vec3().to_array());
        }
    }
    out
}

/// Voxels per axis of EMAP's averaging grid, and the grid's span.
pub const EMAP_VOXELS: usize = 256;
pub const EMAP_GRID: (f64, f64) = (-1.0, 1.0);

/// point_cloud_utils' `downsample_point_cloud_on_voxel_grid` as EMAP calls it: the
/// points of each voxel (`floor((p - min) / size)` in `f32`; points outside the grid's
/// span keep their own voxels) averaged in `f32`, summed in input order.
pub fn voxel_average(points: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let size = ((EMAP_GRID.1 - EMAP_GRID.0) / EMAP_VOXELS as f64) as f32;
    let min = EMAP_GRID.0 as f32;
    let mut cells: HashMap<[i32; 3], (usize, [f32; 3], u32)> = HashMap::new();
    for p in points {
        let key = p.map(|c| ((c - min) / size).floor() as i32);
        let n = cells.len();
        let e = cells.entry(key).or_insert((n, [0.0; 3], 0));
        for (sum, c) in e.1.iter_mut().zip(p) {
            *sum += c;
        }
        e.2 += 1;
    }
    let mut v: Vec<(usize, [f32; 3], u32)> = cells.into_values().collect();
    v.sort_unstable_by_key(|c| c.0);
    v.into_iter()
        .map(|(_, s, n)| s.map(|c| c / n as f32))
        .collect()
}

/// For each point of `from`, the distance to its nearest point of `to` computed in `f32`
/// (NumPy's `norm` of the `f32` difference), the nearest found in `f64`.
fn nearest_f32(from: &[[f32; 3]], to: &[[f32; 3]]) -> Vec<f32> {
    let to64: Vec<DVec3> = to.iter().map(|p| p.map(f64::from).into()).collect();
    let tree = KdTree::new(&to64);
    from.par_iter()
        .map(|p| {
            let q: DVec3 = p.map(f64::from).into();
            let (i, _) = tree.nearest(q).expect("non-empty");
            let d = [p[0] - to[i][0], p[1] - to[i][1], p[2] - to[i][2]];
            (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
        })
        .collect()
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// `exact` metrics of `predicted` against segments `gt` (same frame).
pub fn gt_metrics(
    predicted: &[Segment],
    gt: &[Segment],
    step: f64,
    thresholds: &[f64],
) -> GtMetrics {
    exact_metrics(predicted, &GtEdges::from_segments(gt), step, thresholds)
}

fn f_score(precision: f64, recall: f64) -> f64 {
    if precision + recall > 0.0 {
        2.0 * precision * recall / (precision + recall)
    } else {
        // EMAP's NaN (0 / 0), which its dataset mean counts as 0.
        0.0
    }
}

/// `exact` metrics of `predicted` against `gt` (same frame).
pub fn exact_metrics(
    predicted: &[Segment],
    gt: &GtEdges,
    step: f64,
    thresholds: &[f64],
) -> GtMetrics {
    let ps = sample(predicted, step);
    let gs = gt.exact_samples(step);
    let d_pg = nearest_distances(&ps, &gs);
    let d_gp = nearest_distances(&gs, &ps);
    let frac = |d: &[f64], t: f64| {
        if d.is_empty() {
            0.0
        } else {
            d.iter().filter(|&&x| x <= t).count() as f64 / d.len() as f64
        }
    };
    let scores = thresholds
        .iter()
        .map(|&t| {
            let precision = frac(&d_pg, t);
            let recall = frac(&d_gp, t);
            GtScore {
                threshold: t,
                precision,
                recall,
                f_score: f_score(precision, recall),
            }
        })
        .collect();
    let both = !gs.is_empty() && !ps.is_empty();
    GtMetrics {
        protocol: Protocol::Exact,
        step,
        predicted_samples: ps.len(),
        gt_samples: gs.len(),
        accuracy: if gs.is_empty() { None } else { mean(&d_pg) },
        completeness: if ps.is_empty() { None } else { mean(&d_gp) },
        scores,
        closest: both.then(|| d_pg.iter().copied().fold(f64::INFINITY, f64::min)),
    }
}

/// `emap` metrics of `predicted` against `gt` (EMAP's `process_scan` for one object).
/// Without a predicted or a GT sample every value is null (EMAP skips the object).
pub fn emap_metrics(predicted: &[Segment], gt: &GtEdges) -> GtMetrics {
    let ps = voxel_average(&emap_predicted_samples(predicted));
    let gs = gt.emap_samples();
    let mut m = GtMetrics {
        protocol: Protocol::Emap,
        step: STEP,
        predicted_samples: ps.len(),
        gt_samples: gs.len(),
        accuracy: None,
        completeness: None,
        scores: Vec::new(),
        closest: None,
    };
    if ps.is_empty() || gs.is_empty() {
        return m;
    }
    let d_pg = nearest_f32(&ps, &gs);
    let d_gp = nearest_f32(&gs, &ps);
    let mean32 = |d: &[f32]| d.iter().map(|&x| f64::from(x)).sum::<f64>() / d.len() as f64;
    m.accuracy = Some(mean32(&d_pg));
    m.completeness = Some(mean32(&d_gp));
    m.closest = d_pg.iter().copied().reduce(f32::min).map(f64::from);
    let frac = |d: &[f32], t: f32| d.iter().filter(|&&x| x < t).count() as f64 / d.len() as f64;
    m.scores = THRESHOLDS
        .iter()
        .map(|&t| {
            // NumPy compares a float32 array with a Python float in float32.
            let (precision, recall) = (frac(&d_pg, t as f32), frac(&d_gp, t as f32));
            GtScore {
                threshold: t,
                precision,
                recall,
                f_score: f_score(precision, recall),
            }
        })
        .collect();
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The hash-grid ring search the k-d tree replaced, kept to show the distances are
    /// the same.
    fn ring_nearest_distances(from: &[DVec3], to: &[DVec3], cell: f64) -> Vec<f64> {
        if to.is_empty() {
            return vec![f64::INFINITY; from.len()];
        }
        let key = |p: DVec3| {
            let c = (p / cell).floor();
            (c.x as i64, c.y as i64, c.z as i64)
        };
        let mut map: HashMap<(i64, i64, i64), Vec<u32>> = HashMap::new();
        for (i, p) in to.iter().enumerate() {
            map.entry(key(*p)).or_default().push(i as u32);
        }
        // Largest ring ever needed: the box of all points.
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for p in from.iter().chain(to) {
            lo = lo.min(*p);
            hi = hi.max(*p);
        }
        let max_ring = (((hi - lo).max_element() / cell).ceil() as i64) + 1;
        from.par_iter()
            .map(|&p| {
                let (cx, cy, cz) = key(p);
                let mut best = f64::INFINITY;
                let mut ring = 0i64;
                // Every point outside ring k is at least k * cell away.
                while ring <= max_ring && best > (ring as f64 - 1.0).max(0.0) * cell {
                    // Far from every point: a plain scan is cheaper than more rings.
                    if ((2 * ring + 1) as usize).pow(3) > 4 * to.len() {
                        best = to.iter().map(|q| (*q - p).length()).fold(best, f64::min);
                        break;
                    }
                    for dz in -ring..=ring {
                        for dy in -ring..=ring {
                            for dx in -ring..=ring {
                                if dx.abs().max(dy.abs()).max(dz.abs()) != ring {
                                    continue;
                                }
                                if let Some(v) = map.get(&(cx + dx, cy + dy, cz + dz)) {
                                    for &j in v {
                                        best = best.min((to[j as usize] - p).length());
                                    }
                                }
                            }
                        }
                    }
                    ring += 1;
                }
                best
            })
            .collect()
    }

    #[test]
    fn identical_sets_are_perfect() {
        let gt = [Segment::from_arrays([0.0, 0.0, 0.0], [0.5, 0.0, 0.0])];
        let m = gt_metrics(&gt, &gt, STEP, &THRESHOLDS);
        assert_eq!(m.accuracy, Some(0.0));
        assert_eq!(m.completeness, Some(0.0));
        assert!(m.scores.iter().all(|s| s.f_score == 1.0));
        assert_eq!(m.gt_samples, 101);
    }

    #[test]
    fn a_shifted_half_edge_by_hand() {
        // GT: x in [0, 1]; predicted: x in [0, 0.5] shifted by 0.008 in y.
        let gt = [Segment::from_arrays([0.0, 0.0, 0.0], [1.0, 0.0, 0.0])];
        let pr = [Segment::from_arrays([0.0, 0.008, 0.0], [0.5, 0.008, 0.0])];
        let m = gt_metrics(&pr, &gt, STEP, &THRESHOLDS);
        assert!((m.accuracy.unwrap() - 0.008).abs() < 1e-12);
        // precision: 0 at 0.005, 1 at 0.01 and 0.02
        assert_eq!(m.scores[0].precision, 0.0);
        assert_eq!(m.scores[1].precision, 1.0);
        // recall at 0.01: GT samples with x <= 0.5 + sqrt(0.01^2 - 0.008^2) = 0.506
        // -> x = 0, 0.005, ..., 0.505: 102 of 201
        assert!((m.scores[1].recall - 102.0 / 201.0).abs() < 1e-12);
        let f = 2.0 * (102.0 / 201.0) / (1.0 + 102.0 / 201.0);
        assert!((m.scores[1].f_score - f).abs() < 1e-12);
        // completeness: the far half of GT is ~ (x - 0.5) away
        assert!(m.completeness.unwrap() > 0.1);
    }

    #[test]
    fn nearest_matches_brute_force() {
        let mut rng = crate::synth::Rng::new(3);
        let mut f = || rng.uniform();
        let a: Vec<DVec3> = (0..500).map(|_| DVec3::new(f(), f(), f())).collect();
        let b: Vec<DVec3> = (0..300).map(|_| DVec3::new(f(), f(), f()) * 0.3).collect();
        let d = nearest_distances(&a, &b);
        for (i, p) in a.iter().enumerate() {
            let want = b
                .iter()
                .map(|q| (*q - *p).length())
                .fold(f64::INFINITY, f64::min);
            assert_eq!(d[i], want);
        }
    }

    fn lines(rel: &str) -> Vec<Segment> {
        let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(rel);
        crate::io::read_lines(&p).unwrap().lines.segments
    }

    #[test]
    fn the_tree_gives_the_ring_searchs_metrics() {
        // Real lines against real GT, a toy scene, and predictions with far strays.
        let gt = lines("tests/data/abc_00000006/gt_sharp_lines.txt");
        let nef = lines("tests/data/abc_00000006/nef_pred_lines.txt");
        let toy = crate::synth::toy_scene(&Default::default());
        let mut strays = nef.clone();
        for (i, s) in nef.iter().enumerate().take(5) {
            let d = DVec3::new(100.0, -40.0 * i as f64, 7.0);
            strays.push(Segment::new(s.p1 + d, s.p2 + d));
        }
        let toy_lines: Vec<Segment> = toy.lines.segments.clone();
        for (pred, gt) in [(&nef, &gt), (&strays, &gt), (&toy_lines, &toy.gt)] {
            let (ps, gs) = (sample(pred, STEP), sample(gt, STEP));
            for (a, b) in [(&ps, &gs), (&gs, &ps)] {
                let tree = nearest_distances(a, b);
                let ring = ring_nearest_distances(a, b, 0.02);
                assert_eq!(tree, ring);
            }
        }
    }
}
