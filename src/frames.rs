//! Are the lines and the Gaussians in one frame? Line3D++ and LIMAP lines are in the SfM
//! (COLMAP) frame, as is an Inria `point_cloud.ply`; nerfstudio's splatfacto and gsplat
//! (with `normalize_world_space`) export models in a normalized frame. Refining lines
//! against a model in another frame finds no Gaussian near (almost) any segment, or fits a
//! few segments to the wrong Gaussians where the two frames happen to overlap, so the check
//! compares what it sees with what one frame would give: the share of segments with a
//! Gaussian center within `r`, and the two bounding boxes (the lines' box larger than the
//! model's, or the lines' endpoints outside the model's box). `refine` stops (exit 2) with
//! a message that says why and what fixes it when the frames are different
//! ([`FrameVerdict::Different`]), and warns when they are doubtful; `eval` warns in both
//! cases.

use crate::engine::{Engine, EngineError, Query};
use crate::geom::{p64, Aabb, Segment};
use glam::DVec3;

/// How many segments found a Gaussian center within `radius`, and the two boxes.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameCheck {
    pub segments: usize,
    /// Segments with at least one Gaussian center within `radius`.
    pub near: usize,
    pub radius: f64,
    pub lines_box: Aabb,
    pub gaussians_box: Aabb,
    /// Segment endpoints inside the model's box (grown by `radius`).
    pub endpoints_inside: usize,
}

/// What the check concludes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FrameVerdict {
    /// Most segments have Gaussians near them and the boxes agree.
    Same,
    /// Most segments have no Gaussian near them, or the boxes disagree, not both: a warning.
    Doubtful,
    /// (Almost) no segment has a Gaussian near it, or most have none and the boxes
    /// disagree: `refine` refuses.
    Different,
}

/// Below this share of segments with a Gaussian near them, "most segments see none".
pub const NEAR_SHARE: f64 = 0.5;
/// The lines' box may be at most this many times the size of the model's (a trained
/// model reaches beyond the lines, with background and floaters; the reverse is a
/// scaled frame).
pub const MAX_SIZE_RATIO: f64 = 2.0;
/// At least this share of the segments' endpoints lies inside the model's box.
pub const MIN_INSIDE_SHARE: f64 = 0.5;

impl FrameCheck {
    /// Share of segments with a Gaussian center within `radius`.
    pub fn near_share(&self) -> f64 {
        self.near as f64 / self.segments.max(1) as f64
    }

    /// The lines' box size over the model's (largest extents).
    pub fn size_ratio(&self) -> f64 {
        let size = |a: &Aabb| (a.max - a.min).max_element();
        size(&self.lines_box) / size(&self.gaussians_box)
    }

    /// Share of the segments' endpoints inside the model's box.
    pub fn inside_share(&self) -> f64 {
        self.endpoints_inside as f64 / (2 * self.segments).max(1) as f64
    }

    /// The lines' box is much larger than the model's, or mostly outside it.
    pub fn boxes_disagree(&self) -> bool {
        let ratio = self.size_ratio();
        (ratio.is_finite() && ratio > MAX_SIZE_RATIO) || self.inside_share() < MIN_INSIDE_SHARE
    }

    pub fn verdict(&self) -> FrameVerdict {
        if self.segments == 0 {
            return FrameVerdict::Same;
        }
        let few = self.near_share() < NEAR_SHARE;
        let disagree = self.boxes_disagree();
        if self.near < self.segments.div_ceil(100).max(1) || (few && disagree) {
            FrameVerdict::Different
        } else if few || disagree {
            FrameVerdict::Doubtful
        } else {
            FrameVerdict::Same
        }
    }

    /// The frames are different ([`FrameVerdict::Different`]).
    pub fn mismatch(&self) -> bool {
        self.verdict() == FrameVerdict::Different
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
        let ratio = self.size_ratio();
        let units = if ratio.is_finite() && !(0.2..=5.0).contains(&ratio) {
            format!(
                " The line box is {ratio:.3} times the size of the model's: different units or a scaled (normalized) frame."
            )
        } else {
            String::new()
        };
        let likely = match self.verdict() {
            FrameVerdict::Different => "are most likely not in one frame",
            _ => "may not be in one frame",
        };
        format!(
            "only {} of {} segments have a Gaussian center within r = {}, and {:.0} % of their endpoints lie in the model's box: the lines and the Gaussians {likely} (or not in the same units). \
             Lines: {}; Gaussians: {}.{units} \
             Models from nerfstudio (splatfacto) and gsplat with normalize_world_space are stored in a normalized frame: pass \
             --gaussians-transform dataparser_transforms.json (inverted for you); for EMAP/EdgeGaussians data, \
             --gaussians-transform meta_data.json (its worldtogt); for any other tool give --gaussians-transform a 4x4 matrix \
             (text, row by row) that maps the Gaussians into the lines' frame (README: Frames). \
             If the frames are right and the model is only sparse near the lines, try --radius auto or a larger --radius.",
            self.near,
            self.segments,
            self.radius,
            100.0 * self.inside_share(),
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
    let occupied = engine.occupied(&queries)?;
    let mut gaussians_box = Aabb::empty();
    for c in centers {
        gaussians_box.extend(p64(*c));
    }
    let grown = Aabb {
        min: gaussians_box.min - DVec3::splat(radius),
        max: gaussians_box.max + DVec3::splat(radius),
    };
    let inside = |p: DVec3| p.cmpge(grown.min).all() && p.cmple(grown.max).all();
    let endpoints_inside = segments
        .iter()
        .map(|s| usize::from(inside(s.p1)) + usize::from(inside(s.p2)))
        .sum();
    Ok(FrameCheck {
        segments: segments.len(),
        near: occupied.iter().filter(|&&o| o).count(),
        radius,
        lines_box: Aabb::of_segments(segments),
        gaussians_box,
        endpoints_inside,
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

    #[test]
    fn the_verdict_weighs_the_share_near_against_the_boxes() {
        let unit = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        let fc = |near: usize, lines_size: f64, inside: usize| FrameCheck {
            segments: 100,
            near,
            radius: 0.01,
            lines_box: Aabb {
                min: DVec3::ZERO,
                max: DVec3::splat(lines_size),
            },
            gaussians_box: unit,
            endpoints_inside: inside,
        };
        use FrameVerdict::*;
        // most segments see Gaussians, boxes agree (a model larger than the lines is usual)
        assert_eq!(fc(90, 1.0, 200).verdict(), Same);
        assert_eq!(fc(50, 0.1, 200).verdict(), Same);
        // under 1 %: different, whatever the boxes say
        assert_eq!(fc(0, 1.0, 200).verdict(), Different);
        // most see none and the boxes disagree (lines' box 3x the model's, or outside it)
        assert_eq!(fc(7, 3.0, 200).verdict(), Different);
        assert_eq!(fc(49, 1.0, 99).verdict(), Different);
        // one of the two: a warning
        assert_eq!(fc(20, 1.0, 200).verdict(), Doubtful);
        assert_eq!(fc(90, 3.0, 200).verdict(), Doubtful);
        assert_eq!(fc(90, 1.0, 40).verdict(), Doubtful);
        // the boundaries: half the segments, twice the size, half the endpoints
        assert_eq!(fc(50, 2.0, 100).verdict(), Same);
        assert!(fc(7, 3.0, 200)
            .message()
            .contains("most likely not in one frame"));
        assert!(fc(20, 1.0, 200)
            .message()
            .contains("may not be in one frame"));
    }
}
