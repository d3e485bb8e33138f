//! The whole job of SPEC 3: working set, radius, grid, engine, before-evaluation, the
//! refinement steps, after-evaluation — timed per stage for the report.

use crate::engine::{Engine, EngineError};
use crate::eval::{evaluate, Metrics};
use crate::geom::{p64, LineSet, Segment};
use crate::index::{Grid, WorkingSet};
use crate::refine::{self, Params, RadiusArg};
use serde::Serialize;
use std::sync::Arc;
use std::time::Instant;

/// One timed stage of a run.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Stage {
    pub name: String,
    /// Segments after the stage.
    pub segments: usize,
    pub seconds: f64,
}

/// Everything a run produced.
#[derive(Clone, Debug, Serialize)]
pub struct RunOutput {
    #[serde(skip)]
    pub lines: LineSet,
    pub radius: f64,
    pub n_box: usize,
    pub before: Metrics,
    pub after: Metrics,
    pub stages: Vec<Stage>,
    pub backend: String,
    pub adapter: String,
    pub warnings: Vec<String>,
    /// Shifts of step 4 and segment length per stage.
    pub refine: refine::StepNotes,
}

#[derive(thiserror::Error, Debug)]
pub enum RunError {
    #[error(transparent)]
    Engine(#[from] EngineError),
    #[error("{0}")]
    Input(String),
}

/// `--radius auto` (SPEC 3 step 2): `c` = centroid of the working set; keep the centers
/// closer to `c` than the 95th percentile (linear interpolation, as numpy) of the
/// distances; `r = 0.02 x` the largest kept distance.
pub fn auto_radius(points: &[[f32; 3]]) -> Option<f64> {
    if points.is_empty() {
        return None;
    }
    let n = points.len() as f64;
    let c = points.iter().fold(glam::DVec3::ZERO, |a, p| a + p64(*p)) / n;
    let mut d: Vec<f64> = points.iter().map(|p| (p64(*p) - c).length()).collect();
    d.sort_by(f64::total_cmp);
    let pos = 0.95 * (d.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    let p95 = d[lo] + (d[hi] - d[lo]) * (pos - lo as f64);
    let kept = d
        .iter()
        .copied()
        .filter(|&x| x < p95)
        .fold(f64::NAN, f64::max);
    let r = 0.02 * if kept.is_nan() { p95 } else { kept };
    (r > 0.0).then_some(r)
}

/// The refinement radius for `params` over the working set.
pub fn resolve_radius(params: &Params, ws: &WorkingSet) -> Result<f64, RunError> {
    match params.radius {
        RadiusArg::Fixed(r) => Ok(r),
        RadiusArg::Auto => auto_radius(&ws.points).ok_or_else(|| {
            RunError::Input(
                "--radius auto needs Gaussian centers near the lines, and none are".into(),
            )
        }),
    }
}

/// Working set + radius + grid: what both engines are built on.
pub struct Prepared {
    pub working_set_len: usize,
    pub radius: f64,
    pub grid: Arc<Grid>,
    pub seconds: f64,
}

pub fn prepare(
    centers: &[[f32; 3]],
    segments: &[Segment],
    params: &Params,
) -> Result<Prepared, RunError> {
    let t = Instant::now();
    let ws = WorkingSet::new(centers, segments);
    let radius = resolve_radius(params, &ws)?;
    let cell = radius.max(params.eval.eval_radius * 0.5);
    let grid = Arc::new(Grid::build(&ws.points, ws.bounds, cell));
    Ok(Prepared {
        working_set_len: ws.len(),
        radius,
        grid,
        seconds: t.elapsed().as_secs_f64(),
    })
}

/// Runs before-evaluation, the refinement steps and after-evaluation on `engine`.
pub fn run(
    engine: &dyn Engine,
    lines: &LineSet,
    radius: f64,
    params: &Params,
    on_stage: impl FnMut(&Stage),
) -> Result<RunOutput, RunError> {
    let attrs = refine::fit::Attributes::default();
    run_with(engine, lines, &attrs, radius, params, on_stage)
}

/// [`run`] with the Gaussians' attributes (working-set order) for the edge fit.
pub fn run_with(
    engine: &dyn Engine,
    lines: &LineSet,
    attrs: &refine::fit::Attributes,
    radius: f64,
    params: &Params,
    mut on_stage: impl FnMut(&Stage),
) -> Result<RunOutput, RunError> {
    let fixes = params.fixes();
    let mut stages = Vec::new();
    let mut push = |name: &str, segments: usize, t: Instant, stages: &mut Vec<Stage>| {
        let s = Stage {
            name: name.to_string(),
            segments,
            seconds: t.elapsed().as_secs_f64(),
        };
        on_stage(&s);
        stages.push(s);
    };
    let t = Instant::now();
    let before = evaluate(engine, &lines.segments, &params.eval, fixes.r_l, None)?;
    push("evaluate_before", lines.len(), t, &mut stages);
    let (refined, notes) =
        refine::run_steps_noted(engine, lines, attrs, radius, params, |name, n, t| {
            push(name, n, t, &mut stages)
        })?;
    let t = Instant::now();
    let after = evaluate(engine, &refined.segments, &params.eval, fixes.r_l, None)?;
    push("evaluate_after", refined.len(), t, &mut stages);
    Ok(RunOutput {
        lines: refined,
        radius,
        n_box: engine.n_points(),
        before,
        after,
        stages,
        backend: engine.backend().to_string(),
        adapter: engine.adapter(),
        warnings: notes.warnings.clone(),
        refine: notes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn auto_radius_is_two_percent_of_the_kept_extent() {
        // 100 points at distances 1..=100 from the centroid (on alternating sides so the
        // centroid stays at 0, plus the origin).
        let mut pts = vec![[0f32, 0.0, 0.0]];
        for i in 1..=100 {
            pts.push([i as f32, 0.0, 0.0]);
            pts.push([-(i as f32), 0.0, 0.0]);
        }
        let r = auto_radius(&pts).unwrap();
        // distances: 0, then 1,1,2,2,...,100,100 (201 values); p95 at index 190 -> 95;
        // kept < 95 -> max 94.
        assert!((r - 0.02 * 94.0).abs() < 1e-12, "{r}");
        assert_eq!(auto_radius(&[]), None);
    }
}
