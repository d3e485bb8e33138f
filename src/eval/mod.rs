//! The paper's metrics (docs/method.md#evaluation): E_rms, R_covered, R_L and the score, at
//! an evaluation radius, over the working set that refinement uses.

pub mod abc;
pub mod gt;
pub mod kdtree;

use crate::engine::{Ask, Engine, EngineError, Query, Want};
use crate::geom::Segment;
use crate::refine::{EvalParams, RlMode};
use serde::{Deserialize, Serialize};

/// Metrics of one segment set at one radius. `None` (JSON null) where undefined, with the
/// reason in `message`; never NaN.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    pub radius: f64,
    /// Mean RMS distance of the points to their segment's line, in centimetres.
    pub e_rms_cm: Option<f64>,
    /// Percent of the working set inside at least one cylinder.
    pub coverage_pct: Option<f64>,
    /// Compactness: total length over the log of the point count.
    pub r_l: Option<f64>,
    pub score: Option<f64>,
    /// Segments with at least one point (the ones measured).
    pub segments: usize,
    /// Segments with no point, skipped.
    pub skipped: usize,
    /// Sum of `N(s)` over measured segments.
    pub points_in_cylinders: u64,
    /// `|union of X(s)|`.
    pub covered_points: u64,
    /// `N_box`.
    pub n_box: usize,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
}

/// Evaluates `segments` at `p.eval_radius` (or `radius` when given).
pub fn evaluate(
    engine: &dyn Engine,
    segments: &[Segment],
    p: &EvalParams,
    r_l_mode: RlMode,
    radius: Option<f64>,
) -> Result<Metrics, EngineError> {
    let r = radius.unwrap_or(p.eval_radius);
    let queries: Vec<Query> = segments.iter().map(|s| Query::new(*s, r)).collect();
    // One batch: the sums and the coverage from one walk of the cylinders (segments
    // with no point add nothing to the union).
    let answers = engine.query(
        &queries,
        &Ask {
            want: Want::SUMS,
            coverage: true,
            ..Default::default()
        },
    )?;
    let stats = answers.stats;
    let mut kept = 0usize;
    let mut e_sum = 0.0;
    let mut len_sum = 0.0;
    let mut n_sum = 0u64;
    for (q, s) in queries.iter().zip(&stats) {
        if s.count == 0 {
            continue;
        }
        e_sum += 100.0 * p.unit_scale * s.rmse();
        len_sum += q.seg.length();
        n_sum += s.count;
        kept += 1;
    }
    let n_box = engine.n_points();
    let mut m = Metrics {
        radius: r,
        e_rms_cm: None,
        coverage_pct: None,
        r_l: None,
        score: None,
        segments: kept,
        skipped: segments.len() - kept,
        points_in_cylinders: n_sum,
        covered_points: 0,
        n_box,
        message: None,
    };
    if kept == 0 {
        m.message = Some(format!(
            "no segment has a Gaussian center within r_e = {r}: metrics are undefined \
             (are the lines and the Gaussians in the same frame and units?)"
        ));
        return Ok(m);
    }
    let covered = answers.coverage.map_or(0, |c| c.count());
    m.covered_points = covered;
    let e_rms = e_sum / kept as f64;
    m.e_rms_cm = Some(e_rms);
    m.coverage_pct = Some(100.0 * covered as f64 / n_box as f64);
    let denom = match r_l_mode {
        RlMode::Paper => (n_sum as f64).ln(),
        RlMode::Authors => (n_box as f64).ln(),
    };
    let mut why = Vec::new();
    if denom > 0.0 {
        m.r_l = Some(len_sum / denom);
    } else {
        why.push("R_L is undefined: ln of the point count is 0 (a single point)");
    }
    if let (Some(rl), Some(cov)) = (m.r_l, m.coverage_pct) {
        let d = (1.0 + e_rms).ln() * (1.0 + rl).ln();
        if d > 0.0 && d.is_finite() {
            m.score = Some(p.score_lambda * cov / d);
        } else {
            why.push("the score is undefined: E_rms or R_L is 0");
        }
    }
    if !why.is_empty() {
        m.message = Some(why.join("; "));
    }
    Ok(m)
}

/// The paper's radius sweep: metrics at each radius.
pub fn sweep(
    engine: &dyn Engine,
    segments: &[Segment],
    p: &EvalParams,
    r_l_mode: RlMode,
    radii: &[f64],
) -> Result<Vec<Metrics>, EngineError> {
    radii
        .iter()
        .map(|&r| evaluate(engine, segments, p, r_l_mode, Some(r)))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::cpu::CpuEngine;
    use glam::DVec3;

    fn engine(points: &[[f32; 3]]) -> CpuEngine {
        CpuEngine::over_points(points, 0.1)
    }

    #[test]
    fn metrics_by_hand_on_a_tiny_scene() {
        // Segment along x of length 2; points at distances 0, 0.03 (x2) and 0.04 inside
        // r_e = 0.1; one point outside every cylinder; a second segment with no point.
        let pts = [
            [0.5f32, 0.0, 0.0],
            [1.0, 0.03, 0.0],
            [1.5, 0.0, -0.03],
            [1.2, 0.0, 0.04],
            [1.0, 2.0, 0.0],
        ];
        let e = engine(&pts);
        let segs = [
            Segment::new(DVec3::ZERO, DVec3::new(2.0, 0.0, 0.0)),
            Segment::new(DVec3::new(0.0, 3.0, 3.0), DVec3::new(1.0, 3.0, 3.0)),
        ];
        let p = EvalParams::default();
        let m = evaluate(&e, &segs, &p, RlMode::Paper, None).unwrap();
        let d2 = [0.0f64, 0.03f32 as f64, 0.03f32 as f64, 0.04f32 as f64];
        let rmse = (d2.iter().map(|x| x * x).sum::<f64>() / 4.0).sqrt();
        assert_eq!(m.segments, 1);
        assert_eq!(m.skipped, 1);
        assert!((m.e_rms_cm.unwrap() - 100.0 * rmse).abs() < 1e-9);
        assert!((m.coverage_pct.unwrap() - 80.0).abs() < 1e-12);
        assert!((m.r_l.unwrap() - 2.0 / 4f64.ln()).abs() < 1e-12);
        let score = 0.1 * 80.0 / ((1.0 + 100.0 * rmse).ln() * (1.0 + 2.0 / 4f64.ln()).ln());
        assert!((m.score.unwrap() - score).abs() < 1e-9);
        let a = evaluate(&e, &segs, &p, RlMode::Authors, None).unwrap();
        assert!((a.r_l.unwrap() - 2.0 / 5f64.ln()).abs() < 1e-12);
        // unit scale converts to centimetres
        let p2 = EvalParams {
            unit_scale: 0.01,
            ..p.clone()
        };
        let m2 = evaluate(&e, &segs, &p2, RlMode::Paper, None).unwrap();
        assert!((m2.e_rms_cm.unwrap() - rmse).abs() < 1e-9);
    }

    #[test]
    fn no_segment_with_a_point_gives_nulls_not_nan() {
        let e = engine(&[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]);
        let segs = [Segment::new(DVec3::splat(5.0), DVec3::splat(6.0))];
        let m = evaluate(&e, &segs, &EvalParams::default(), RlMode::Paper, None).unwrap();
        assert_eq!(m.e_rms_cm, None);
        assert_eq!(m.score, None);
        assert_eq!(m.skipped, 1);
        assert!(m.message.is_some());
        let json = serde_json::to_string(&m).unwrap();
        assert!(json.contains("\"e_rms_cm\":null"));
        assert!(!json.contains("NaN"));
    }

    #[test]
    fn overlapping_cylinders_count_points_once() {
        let pts: Vec<[f32; 3]> = (0..100).map(|i| [i as f32 / 100.0, 0.0, 0.0]).collect();
        let e = engine(&pts);
        let s = Segment::new(DVec3::ZERO, DVec3::new(1.0, 0.0, 0.0));
        let m = evaluate(&e, &[s, s], &EvalParams::default(), RlMode::Paper, None).unwrap();
        assert_eq!(m.covered_points, 100);
        assert_eq!(m.points_in_cylinders, 200);
        assert!((m.coverage_pct.unwrap() - 100.0).abs() < 1e-12);
    }
}
