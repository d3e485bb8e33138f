//! Are the lines and the Gaussians in one frame? Line3D++ and LIMAP lines are in the SfM
//! (COLMAP) frame, as is an Inria `point_cloud.ply`; nerfstudio's splatfacto and gsplat
//! (with `normalize_world_space`) export models in a normalized frame. Refining lines
//! against a model in another frame finds no Gaussian near any segment and would write an
//! empty result, so `refine` stops with a message that says why and what fixes it, and
//! `eval` warns.

use crate::engine::{Engine, EngineError, Query, Want};
use crate::geom::{p64, Aabb, Segment};

/// How many segments found a Gaussian center within `radius`.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameCheck {
    pub segments: usize,
    /// Segments with at least one Gaussian center within `radius`.
    pub near: usize,
    pub radius: f64,
    pub lines_box: Aabb,
    pub gaussians_box: Aabb,
}

impl FrameCheck {
    /// Fewer than 1% of the segments (and fewer than one) have a Gaussian near them.
    pub fn mismatch(&self) -> bool {
        self.segments > 0 && self.near < self.segments.div_ceil(100).max(1)
    }

    /// What went wrong, the likely cause and the option that fixes it.
    pub fn message(&self) -> String {
        let b = |a: &Aabb| {
            if a.is_empty() {
                "empty".to_string()
            } else {
                let s = a.max - a.min;
                format!(
                    "[{:.3}, {:.3}, {:.3}] .. [{:.3}, {:.3}, {:.3}] (size {:.3})",
                    a.min.x,
                    a.min.y,
                    a.min.z,
                    a.max.x,
                    a.max.y,
                    a.max.z,
                    s.max_element()
                )
            }
        };
        let size = |a: &Aabb| (a.max - a.min).max_element();
        let ratio = size(&self.lines_box) / size(&self.gaussians_box);
        let units = if ratio.is_finite() && !(0.2..=5.0).contains(&ratio) {
            format!(
                " The line box is {ratio:.3} times the size of the model's: different units or a scaled (normalized) frame."
            )
        } else {
            String::new()
        };
        format!(
            "only {} of {} segments have a Gaussian center within r = {}: the lines and the Gaussians are most likely not in one frame (or not in the same units). \
             Lines: {}; Gaussians: {}.{units} \
             Models from nerfstudio (splatfacto) and gsplat with normalize_world_space are stored in a normalized frame: pass \
             --gaussians-transform dataparser_transforms.json (inverted for you); for any other tool give --gaussians-transform a 4x4 matrix \
             (text, row by row) that maps the Gaussians into the lines' frame (README: Frames). \
             If the frames are right and the model is only sparse near the lines, try --radius auto or a larger --radius.",
            self.near,
            self.segments,
            self.radius,
            b(&self.lines_box),
            b(&self.gaussians_box),
        )
    }
}

/// Counts the segments that have a Gaussian center within `radius` (one batch of count
/// queries); `centers` are all the model's centers, for the message's box.
pub fn check_frames(
    engine: &dyn Engine,
    segments: &[Segment],
    radius: f64,
    centers: &[[f32; 3]],
) -> Result<FrameCheck, EngineError> {
    let queries: Vec<Query> = segments.iter().map(|s| Query::new(*s, radius)).collect();
    let stats = engine.stats(&queries, Want::COUNT)?;
    let mut gaussians_box = Aabb::empty();
    for c in centers {
        gaussians_box.extend(p64(*c));
    }
    Ok(FrameCheck {
        segments: segments.len(),
        near: stats.iter().filter(|s| s.count > 0).count(),
        radius,
        lines_box: Aabb::of_segments(segments),
        gaussians_box,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::cpu::CpuEngine;
    use crate::index::{Grid, WorkingSet};
    use std::sync::Arc;

    fn check(centers: &[[f32; 3]], segs: &[Segment], r: f64) -> FrameCheck {
        let ws = WorkingSet::new(centers, segs);
        let grid = Arc::new(Grid::build(&ws.points, ws.bounds, r));
        let eng = CpuEngine::new(grid);
        check_frames(&eng, segs, r, centers).unwrap()
    }

    #[test]
    fn a_model_in_another_frame_is_a_mismatch_and_the_same_frame_is_not() {
        let segs: Vec<Segment> = (0..50)
            .map(|i| Segment::from_arrays([i as f64, 0.0, 0.0], [i as f64, 1.0, 0.0]))
            .collect();
        let on: Vec<[f32; 3]> = (0..50)
            .flat_map(|i| (0..10).map(move |k| [i as f32, k as f32 / 10.0, 0.0]))
            .collect();
        let c = check(&on, &segs, 0.03);
        assert_eq!(c.near, 50);
        assert!(!c.mismatch());
        // The same model scaled and moved, as nerfstudio stores it.
        let moved: Vec<[f32; 3]> = on
            .iter()
            .map(|p| [p[0] * 0.02 + 0.3, p[1] * 0.02 - 0.1, p[2] * 0.02])
            .collect();
        let c = check(&moved, &segs, 0.03);
        assert!(c.mismatch(), "{c:?}");
        let m = c.message();
        assert!(m.contains("--gaussians-transform"), "{m}");
        assert!(m.contains("only 0 of 50"), "{m}");
        assert!(m.contains("units"), "{m}");
    }
}
