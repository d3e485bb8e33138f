//! Step 5, outliers: segments whose density `rho = N / L` is at most `theta` are dropped,
//! `theta = ratio x mean(rho)` (ratio -1: `max(mean - 2 std, 0)`, population std).

use crate::engine::{Engine, EngineError, Query, Want};
use crate::geom::Segment;

pub struct OutlierResult {
    /// Indices of the kept segments, in order.
    pub kept: Vec<usize>,
    pub theta: f64,
    /// `rho(s)` of every input segment.
    pub density: Vec<f64>,
}

pub fn threshold(density: &[f64], ratio: f64) -> f64 {
    if density.is_empty() {
        return 0.0;
    }
    let n = density.len() as f64;
    let mean = density.iter().sum::<f64>() / n;
    if ratio == -1.0 {
        let var = density.iter().map(|d| (d - mean) * (d - mean)).sum::<f64>() / n;
        (mean - 2.0 * var.sqrt()).max(0.0)
    } else {
        ratio * mean
    }
}

pub fn outliers(
    engine: &dyn Engine,
    segments: &[Segment],
    r: f64,
    ratio: f64,
) -> Result<OutlierResult, EngineError> {
    let queries: Vec<Query> = segments.iter().map(|s| Query::new(*s, r)).collect();
    let stats = engine.stats(&queries, Want::COUNT)?;
    let density: Vec<f64> = segments
        .iter()
        .zip(&stats)
        .map(|(s, st)| super::density(st.count, s.length()))
        .collect();
    let theta = threshold(&density, ratio);
    let kept = (0..segments.len())
        .filter(|&i| density[i] > theta)
        .collect();
    Ok(OutlierResult {
        kept,
        theta,
        density,
    })
}
