//! Beyond the paper, `--max-sagitta`: is a segment a line or a chord of a curve? The
//! Gaussians' ridge is found, by the edge fit's mean shift ([`super::fit`]), in each third
//! of the segment's cylinder; where the middle third's ridge sits off the chord through the
//! end thirds' ridges, the Gaussians bend across the segment. For an arc of sagitta `s`
//! over the segment the thirds' centres see `4 s / 9` of it, so the measure is reported as
//! `9/4` of the middle third's offset: the sagitta of the arc through the three ridge
//! positions, in units of r. One engine batch of members for all segments.

use crate::engine::{Engine, EngineError, Query};
use crate::geom::Segment;
use crate::refine::fit::{basis, ridge, Attributes};
use crate::refine::Params;
use glam::DVec2;

type Third = (Vec<(f64, DVec2)>, Vec<f64>);

/// Each segment's sagitta in units of r, or `None` where a third holds fewer than
/// `fit_min_points` points under the ridge kernel (no judgement: the segment is kept).
pub fn straightness(
    engine: &dyn Engine,
    segments: &[Segment],
    attrs: &Attributes,
    r: f64,
    p: &Params,
) -> Result<Vec<Option<f64>>, EngineError> {
    let queries: Vec<Query> = segments.iter().map(|s| Query::new(*s, r)).collect();
    let members = engine.members(&queries)?;
    Ok(segments
        .iter()
        .zip(&members)
        .map(|(s, m)| {
            let (e1, e2) = basis(s.dir());
            let l = s.length();
            // Per third: the members' (axial position, cross-section offset), and weights.
            let mut thirds: [Third; 3] = Default::default();
            for x in m {
                let k = ((3.0 * x.t / l).floor().max(0.0) as usize).min(2);
                thirds[k]
                    .0
                    .push((x.t, DVec2::new(x.offset.dot(e1), x.offset.dot(e2))));
                thirds[k].1.push(if p.fit_opacity_weight {
                    attrs.weight(x.id)
                } else {
                    1.0
                });
            }
            let mut c = [(0.0, DVec2::ZERO); 3];
            for (ck, (pts, pw)) in c.iter_mut().zip(&thirds) {
                let (f, weight) = ridge(pts, pw, r, p)?;
                if weight < f64::from(p.fit_min_points) {
                    return None;
                }
                *ck = (f.t0, f.a);
            }
            let (t1, t3) = (c[0].0, c[2].0);
            if t3 - t1 <= 0.0 {
                return None;
            }
            let chord = c[0].1 + (c[2].1 - c[0].1) * ((c[1].0 - t1) / (t3 - t1));
            Some(2.25 * (c[1].1 - chord).length() / r)
        })
        .collect())
}
