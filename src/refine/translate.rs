//! Step 4, position bias: each segment moves by the mean perpendicular offset of the
//! `floor(keep x n)` points of `X(s, r)` nearest to its line.

use crate::engine::{Engine, EngineError, Query, Want};
use crate::geom::Segment;

/// Returns the translated segments (one batch for the counts, one for the nearest sums).
pub fn translate(
    engine: &dyn Engine,
    segments: &[Segment],
    r: f64,
    keep: f64,
) -> Result<Vec<Segment>, EngineError> {
    let queries: Vec<Query> = segments.iter().map(|s| Query::new(*s, r)).collect();
    let counts = engine.stats(&queries, Want::COUNT)?;
    let k: Vec<u64> = counts
        .iter()
        .map(|s| (keep * s.count as f64).floor() as u64)
        .collect();
    let near = engine.nearest(&queries, &k)?;
    Ok(segments
        .iter()
        .zip(&near)
        .map(|(s, n)| {
            if n.k == 0 {
                *s
            } else {
                s.translated(n.sum_offset / n.k as f64)
            }
        })
        .collect())
}
