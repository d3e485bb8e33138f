//! Step 5, outliers: segments whose density `rho = N / L` is at most `theta` are dropped,
//! `theta = ratio x mean(rho)` (ratio -1: `max(mean - 2 std, 0)`, population std).

use crate::engine::{Engine, EngineError, Query, Want};
use crate::geom::Segment;
use crate::refine::params::{group, Check};
use crate::refine::{Pass, Profile, Step};

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

group! {
    /// Step 5's parameter.
    pub struct OutliersParams {
        /// Outliers: drop segments with density <= ratio x mean density, a ratio in [0, 1];
        /// -1 uses max(mean - 2 std, 0). `default` profile: 0.1 (a trained model's density
        /// varies tenfold between its faces and its thin features); `reference`: 0.2.
        outlier_ratio: Option<f64> = None, Check::OutlierRatio;
    }
}

impl OutliersParams {
    /// `--outlier-ratio` in effect: the user's, else the profile's (0.1 for default, 0.2,
    /// the paper's, for reference).
    pub fn outlier_ratio_for(&self, profile: Profile) -> f64 {
        self.outlier_ratio.unwrap_or(match profile {
            Profile::Default => 0.1,
            Profile::Reference => 0.2,
        })
    }
}

/// Step 5, the stage `outliers`.
pub struct Outliers;

impl Step for Outliers {
    fn name(&self) -> &'static str {
        "outliers"
    }

    fn run(&self, pass: &mut Pass) -> Result<(), EngineError> {
        let (r, p) = (pass.settings.radius(), pass.settings.params());
        let ratio = p.outliers.outlier_ratio_for(p.profile);
        let o = outliers(pass.engine, &pass.lines.segments, r, ratio)?;
        pass.keep(&o.kept);
        Ok(())
    }
}
