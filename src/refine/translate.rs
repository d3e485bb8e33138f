//! Step 4, position bias: each segment moves by the mean perpendicular offset of the
//! `floor(keep x n)` points of `X(s, r)` nearest to its line.

use crate::engine::{Ask, Engine, EngineError, Nearest, Query};
use crate::geom::Segment;

/// Returns the translated segments (one fused batch: each segment's count and the sums
/// over its `floor(keep x n)` nearest members).
pub fn translate(
    engine: &dyn Engine,
    segments: &[Segment],
    r: f64,
    keep: f64,
) -> Result<Vec<Segment>, EngineError> {
    let queries: Vec<Query> = segments.iter().map(|s| Query::new(*s, r)).collect();
    let ask = Ask {
        nearest: Nearest::Keep(keep),
        ..Default::default()
    };
    let near = engine.query(&queries, &ask)?.nearest;
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
