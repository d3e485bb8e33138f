//! Ground-truth metrics against reference edges (ABC-NEF protocol, as used by EMAP and
//! EdgeGaussians): both sets are sampled every `step` along their segments; accuracy is
//! the mean distance from predicted samples to the nearest GT sample, completeness the
//! reverse; precision / recall / F-score at each threshold.

use crate::geom::Segment;
use glam::DVec3;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::collections::HashMap;

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GtScore {
    pub threshold: f64,
    pub precision: f64,
    pub recall: f64,
    pub f_score: f64,
}

#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GtMetrics {
    pub step: f64,
    pub predicted_samples: usize,
    pub gt_samples: usize,
    /// Mean distance predicted -> GT.
    pub accuracy: Option<f64>,
    /// Mean distance GT -> predicted.
    pub completeness: Option<f64>,
    pub scores: Vec<GtScore>,
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

/// Nearest-neighbour distances from `from` to the point set `to` through a hash grid.
pub fn nearest_distances(from: &[DVec3], to: &[DVec3], cell: f64) -> Vec<f64> {
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

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// ABC-NEF metrics of `predicted` against `gt` (same frame).
pub fn gt_metrics(
    predicted: &[Segment],
    gt: &[Segment],
    step: f64,
    thresholds: &[f64],
) -> GtMetrics {
    let ps = sample(predicted, step);
    let gs = sample(gt, step);
    let cell = thresholds.iter().copied().fold(step, f64::max);
    let d_pg = nearest_distances(&ps, &gs, cell);
    let d_gp = nearest_distances(&gs, &ps, cell);
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
            let f_score = if precision + recall > 0.0 {
                2.0 * precision * recall / (precision + recall)
            } else {
                0.0
            };
            GtScore {
                threshold: t,
                precision,
                recall,
                f_score,
            }
        })
        .collect();
    GtMetrics {
        step,
        predicted_samples: ps.len(),
        gt_samples: gs.len(),
        accuracy: if gs.is_empty() { None } else { mean(&d_pg) },
        completeness: if ps.is_empty() { None } else { mean(&d_gp) },
        scores,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let mut s = 3u64;
        let mut f = || {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let a: Vec<DVec3> = (0..500).map(|_| DVec3::new(f(), f(), f())).collect();
        let b: Vec<DVec3> = (0..300).map(|_| DVec3::new(f(), f(), f()) * 0.3).collect();
        let d = nearest_distances(&a, &b, 0.02);
        for (i, p) in a.iter().enumerate() {
            let want = b
                .iter()
                .map(|q| (*q - *p).length())
                .fold(f64::INFINITY, f64::min);
            assert_eq!(d[i], want);
        }
    }
}
