//! The refinement pipeline of SPEC 3, one file per step. Steps talk to the Gaussians only
//! through [`crate::engine::Engine`] batches.

pub mod params;

pub use params::{auto_radius, EvalParams, Fixes, Params, Profile, RadiusArg, RlMode, Settings};

pub mod cluster;
pub mod crop;
pub mod mergejoin;
pub mod outliers;
pub mod translate;

use crate::engine::{Engine, EngineError};
use crate::geom::LineSet;
use std::time::Instant;

/// `rho = N / L` (0 when `L = 0`).
pub fn density(count: u64, length: f64) -> f64 {
    if length > 0.0 {
        count as f64 / length
    } else {
        0.0
    }
}

/// Steps 4–9 in order, calling `stage(name, segments_out, started)` after each.
pub fn run_steps(
    engine: &dyn Engine,
    input: &LineSet,
    s: &Settings,
    mut stage: impl FnMut(&str, usize, Instant),
) -> Result<LineSet, EngineError> {
    let (r, p, fixes) = (s.radius(), s.params(), s.fixes());
    let mut lines = input.clone();
    if fixes.order_endpoints {
        for s in &mut lines.segments {
            if s.p1.length() > s.p2.length() {
                *s = s.reversed();
            }
        }
    }
    let t = Instant::now();
    lines.segments = translate::translate(engine, &lines.segments, r, p.translate_keep)?;
    stage("translate", lines.len(), t);

    let t = Instant::now();
    let o = outliers::outliers(engine, &lines.segments, r, p.outlier_ratio)?;
    lines = lines.select(&o.kept);
    stage("outliers", lines.len(), t);

    if p.collinear_merge && lines.groups.is_some() {
        let t = Instant::now();
        lines = mergejoin::collinear_merge(engine, &lines, s)?;
        stage("collinear_merge", lines.len(), t);
    }

    let t = Instant::now();
    let clusters = cluster::cluster(&lines, s);
    stage("cluster", lines.len(), t);

    let t = Instant::now();
    lines = mergejoin::merge_join(engine, &lines, &clusters, s)?;
    stage("merge_join", lines.len(), t);

    let t = Instant::now();
    lines.segments = crop::crop(engine, &lines.segments, s)?;
    stage("crop", lines.len(), t);
    Ok(lines)
}
