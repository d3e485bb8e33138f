//! Beyond the paper, `--max-sagitta`: is a segment a line or a chord of a curve? The
//! Gaussians' ridge is found, by the edge fit's mean shift ([`super::fit`]), in each third
//! of the segment's cylinder; where the middle third's ridge sits off the chord through the
//! end thirds' ridges, the Gaussians bend across the segment. For an arc of sagitta `s`
//! over the segment the thirds' centres see `4 s / 9` of it, so the measure is reported as
//! `9/4` of the middle third's offset: the sagitta of the arc through the three ridge
//! positions, in units of r. One engine batch of members for each 4,096 segments.

use crate::engine::{Engine, EngineError, Member, Query};
use crate::geom::Segment;
use crate::refine::fit::{basis, ridge, Attributes, FitParams};
use crate::refine::params::{group, Check};
use crate::refine::{Pass, Step};
use glam::DVec2;
use serde::{Deserialize, Serialize};

type Third = (Vec<(f64, DVec2)>, Vec<f64>);

/// Segments whose members one batch of [`straightness`] lists.
const STRAIGHT_CHUNK: usize = 4096;

/// Each segment's sagitta in units of r, or `None` where a third holds fewer than
/// `fit_min_points` points under the ridge kernel (no judgement: the segment is kept).
pub fn straightness(
    engine: &dyn Engine,
    segments: &[Segment],
    attrs: &Attributes,
    r: f64,
    p: &FitParams,
) -> Result<Vec<Option<f64>>, EngineError> {
    // The members of at most `STRAIGHT_CHUNK` segments at a time (each segment's measure
    // reads its own list only): the lists held at once stay well inside the engine's
    // bound on listed members.
    let mut out = Vec::with_capacity(segments.len());
    for chunk in segments.chunks(STRAIGHT_CHUNK) {
        let queries: Vec<Query> = chunk.iter().map(|s| Query::new(*s, r)).collect();
        let members = engine.members(&queries)?;
        out.extend(
            chunk
                .iter()
                .zip(&members)
                .map(|(s, m)| sagitta(s, m, attrs, r, p)),
        );
    }
    Ok(out)
}

/// One segment's sagitta in units of r from its members (see [`straightness`]).
fn sagitta(s: &Segment, m: &[Member], attrs: &Attributes, r: f64, p: &FitParams) -> Option<f64> {
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
}

group! {
    /// The straightness test's parameter.
    pub struct StraightParams {
        /// Drop a segment whose Gaussians' ridge bends across it by more than this x r: it
        /// follows a curve, not a line. The ridge is found (the edge fit's mean shift) in each
        /// third of the cylinder; the bend is the sagitta of the arc through the three, 9/4 of
        /// the middle one's offset from the chord through the others. A third with too few
        /// points is not judged. Runs after crop; 0: off.
        max_sagitta: f64 = 0.0, Check::NonNegative;
    }
}

/// What the straightness test did (the report's `refine` section).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StraightNotes {
    /// `--max-sagitta`: segments dropped as curves (null when off).
    pub curved_dropped: Option<usize>,
}

/// The stage `straightness` (`--max-sagitta` above 0): segments whose Gaussians bend
/// across them by more than `max_sagitta x r` are dropped.
pub struct Straightness;

impl Step for Straightness {
    fn name(&self) -> &'static str {
        "straightness"
    }

    fn on(&self, pass: &Pass) -> bool {
        pass.settings.params().straight.max_sagitta > 0.0
    }

    fn run(&self, pass: &mut Pass) -> Result<(), EngineError> {
        let (r, p) = (pass.settings.radius(), pass.settings.params());
        let lines = &pass.lines;
        let st = straightness(pass.place, &lines.segments, pass.attrs, r, &p.fit)?;
        let max = p.straight.max_sagitta;
        let kept: Vec<usize> = (0..lines.len())
            .filter(|&i| st[i].is_none_or(|sag| sag <= max))
            .collect();
        pass.notes.straight.curved_dropped = Some(lines.len() - kept.len());
        pass.keep(&kept);
        Ok(())
    }
}
