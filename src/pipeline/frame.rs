//! The automatic frame of a [`Scene`] ([`crate::autoframe`]): with the COLMAP model the
//! lines came from, a scene whose Gaussians do not meet its lines is searched for the
//! normalization a trainer applied, and mapped back when one fits.

use super::{RunError, Scene};
use crate::autoframe::{self, FrameSearch, Tried};
use crate::frames::FrameVerdict;
use crate::io::{self, ColmapModel};
use crate::refine::{auto_radius, Params, RadiusArg};
use glam::DMat4;

/// What [`Scene::find_frame`] did.
#[derive(Clone, Debug)]
pub struct FrameFound {
    /// The scene as it was, checked at the run's radius.
    pub before: Tried,
    /// The candidates' checks; `None` when the scene's frames already agreed.
    pub search: Option<FrameSearch>,
    /// The map applied to the Gaussians, when one was found.
    pub transform: Option<io::GaussianTransform>,
}

impl FrameFound {
    /// One line for the user: what was found (matrix rows, residual) or what was tried.
    pub fn message(&self) -> Option<String> {
        let search = self.search.as_ref()?;
        Some(match (&self.transform, search.best()) {
            (Some(t), Some(b)) => format!(
                "{}; Gaussians to lines' frame, row by row: [{}]",
                t.describe,
                autoframe::matrix_rows(&b.matrix).replace('\n', "; ")
            ),
            _ => format!(
                "no normalization of the COLMAP model fits the lines (tried {})",
                search.summary()
            ),
        })
    }
}

fn radius_of(params: &Params, centers: &[[f32; 3]], scene: &Scene) -> Option<f64> {
    match params.radius {
        RadiusArg::Fixed(r) => Some(r),
        RadiusArg::Auto => {
            let ws = crate::index::WorkingSet::new(centers, &scene.lines.segments);
            auto_radius(&ws.points)
        }
    }
}

impl Scene {
    /// Maps the Gaussians by `t`, as [`Scene::load`] does with a transform: the normals
    /// and scales (which would have to turn and scale too) are dropped, opacities and
    /// colours kept.
    pub fn apply_transform(&mut self, t: &io::GaussianTransform) {
        t.apply(&mut self.gaussians);
        self.normals = None;
        self.max_scale = None;
        self.min_scale = None;
        self.input.gaussians_transform = Some(t.describe.clone());
    }

    /// The automatic frame: checks the scene at `params`' radius (`--radius auto`: on the
    /// Gaussians near the lines) and, when the lines and the Gaussians are not in one
    /// frame, tries every normalization of `model` ([`crate::autoframe`]) and maps the
    /// Gaussians back into the lines' frame by the one that fits best, if any.
    pub fn find_frame(
        &mut self,
        model: &ColmapModel,
        params: &Params,
    ) -> Result<FrameFound, RunError> {
        let segs = &self.lines.segments;
        // Without a radius (auto, no Gaussian near the lines) nothing is near: any small
        // radius says so.
        let nominal = || {
            let b = crate::geom::Aabb::of_segments(segs);
            1e-3 * (b.max - b.min).max_element().max(1e-9)
        };
        let r0 = radius_of(params, &self.gaussians, self).unwrap_or_else(nominal);
        let before = autoframe::try_matrix("as given", DMat4::IDENTITY, &self.gaussians, segs, r0)?;
        let verdict = before.check.verdict();
        if verdict == FrameVerdict::Same {
            return Ok(FrameFound {
                before,
                search: None,
                transform: None,
            });
        }
        let mut tried = Vec::new();
        for n in autoframe::normalizations(model) {
            let m = n.to_colmap();
            let mut mapped = self.gaussians.clone();
            let t = io::GaussianTransform {
                matrix: m,
                describe: String::new(),
            };
            t.apply(&mut mapped);
            let r = radius_of(params, &mapped, self).unwrap_or_else(nominal);
            tried.push(autoframe::try_matrix(&n.name, m, &self.gaussians, segs, r)?);
        }
        let baseline = (verdict == FrameVerdict::Doubtful).then_some(before.check.near);
        let found = autoframe::pick(&tried, baseline);
        let search = FrameSearch { tried, found };
        let transform = search.best().map(|b| io::GaussianTransform {
            matrix: b.matrix,
            describe: format!(
                "found from {}: {}, residual {:.6} ({:.3} r: median RMS distance of the Gaussians within r = {} of a segment), {} of {} segments near Gaussians (before: {})",
                model.describe(),
                b.name,
                b.residual,
                b.residual / b.check.radius,
                b.check.radius,
                b.check.near,
                b.check.segments,
                before.check.near
            ),
        });
        if let Some(t) = &transform {
            self.apply_transform(t);
        }
        Ok(FrameFound {
            before,
            search: Some(search),
            transform,
        })
    }
}
