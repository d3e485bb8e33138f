//! Step 4 beyond the paper: where the line goes. `--fit paper` is the published translation
//! (mean offset of the nearest 40%, [`super::translate`]); `--fit none` leaves the lines;
//! `--fit edge` estimates the edge itself from the Gaussians in the cylinder and moves the
//! line onto it, iterated to convergence by the engine ([`Engine::fit_edges`]); the
//! mathematics of one step (two faces' corner, or the ridge of the centers) and its bounds
//! are [`crate::geom::fit`]'s. Here: the parameters and attributes it is given, and the
//! move gate that judges each move afterwards.

use crate::engine::{Engine, EngineError, FitJob, Member, Query};
pub use crate::geom::fit::{basis, FitResult, FitSpec, How, LineFit, MIN_ELONGATION};
use crate::geom::fit::{families, median, FitPoints};
use crate::geom::kernel::Columns;
use crate::geom::Segment;
use crate::refine::Params;
use glam::{DVec2, DVec3};

/// Per-point attributes of the working set (index = working-set id), where the file has them.
#[derive(Clone, Debug, Default)]
pub struct Attributes {
    /// Unit surface normal of each Gaussian (its shortest axis).
    pub normals: Option<Vec<[f32; 3]>>,
    /// Opacity of each Gaussian in `[0, 1]`: the fit's per-point weight with
    /// `--fit-opacity-weight`.
    pub opacity: Option<Vec<f32>>,
    /// Thickness of each Gaussian (its smallest standard deviation): the move gate widens
    /// a face's slab of splats by it.
    pub thickness: Option<Vec<f32>>,
}

/// `values` (one per center, same order) cut to the working set of `segments` by the same
/// box test as [`crate::index::WorkingSet::new`]; `None` when the counts differ.
pub fn cut_to_working_set<T: Copy>(
    centers: &[[f32; 3]],
    values: &[T],
    segments: &[Segment],
) -> Option<Vec<T>> {
    if centers.len() != values.len() {
        return None;
    }
    let bounds = crate::geom::Aabb::of_segments(segments).grown(0.1);
    Some(
        centers
            .iter()
            .zip(values)
            .filter(|(c, _)| !bounds.is_empty() && bounds.contains(crate::geom::p64(**c)))
            .map(|(_, n)| *n)
            .collect(),
    )
}

impl Attributes {
    /// Per-Gaussian `normals` (same order as `centers`) cut to the working set of
    /// `segments` by the same box test as [`crate::index::WorkingSet::new`]; `None` when
    /// the counts differ.
    pub fn for_working_set(
        centers: &[[f32; 3]],
        normals: &[[f32; 3]],
        segments: &[Segment],
    ) -> Option<Attributes> {
        Some(Attributes {
            normals: Some(cut_to_working_set(centers, normals, segments)?),
            opacity: None,
            thickness: None,
        })
    }

    /// The fit's weight of working-set point `id`: its opacity where the attributes carry
    /// opacities, else 1.
    pub(crate) fn weight(&self, id: u32) -> f64 {
        self.opacity
            .as_ref()
            .map_or(1.0, |o| f64::from(o[id as usize]))
    }
}

impl From<&Params> for FitSpec {
    fn from(p: &Params) -> FitSpec {
        FitSpec {
            iterations: p.fit_iterations,
            max_turn_deg: p.fit_max_turn_deg,
            max_move: p.fit_max_move,
            bandwidth: p.fit_bandwidth,
            min_points: p.fit_min_points,
            opacity_weight: p.fit_opacity_weight,
        }
    }
}

impl Attributes {
    /// What the fit reads of the attributes.
    pub fn fit_points(&self) -> FitPoints<'_> {
        FitPoints {
            normals: self.normals.as_deref(),
            opacity: self.opacity.as_deref(),
        }
    }
}

/// The ridge of [`crate::geom::fit::ridge`] with the kernel width of `p`, from its wide
/// start.
pub(crate) fn ridge(
    pts: &[(f64, DVec2)],
    pw: &[f64],
    r: f64,
    p: &Params,
) -> Option<(LineFit, f64)> {
    crate::geom::fit::ridge(pts, pw, r, p.fit_bandwidth, false)
}

/// The members' axial positions and cross-section offsets in the frame `(e1, e2)`, and
/// their weights (opacities with `--fit-opacity-weight`, else 1).
fn cross_section(
    members: &[Member],
    frame: (DVec3, DVec3),
    attrs: &Attributes,
    p: &Params,
) -> (Vec<(f64, DVec2)>, Vec<f64>) {
    crate::geom::fit::cross_section(members, frame, &attrs.fit_points(), p.fit_opacity_weight)
}

/// `--fit edge`: every segment moved onto the edge its Gaussians describe (the engine's
/// [`Engine::fit_edges`]).
pub fn fit_edges(
    engine: &dyn Engine,
    segments: &[Segment],
    attrs: &Attributes,
    r: f64,
    p: &Params,
) -> Result<FitResult, EngineError> {
    engine.fit_edges(&FitJob {
        segments,
        r,
        spec: &FitSpec::from(p),
        points: attrs.fit_points(),
    })
}

/// The move gate's ridge test: a ridge of centers stands only where less than this share
/// of its kernel weight comes from flat Gaussians (face splats, [`Attributes::normals`]
/// non-zero). Face splats mark surfaces, and their centers' densest line is not an edge:
/// on trained models it sits a splat's size inside the faces (measured on the trained
/// pairs: 0.35 to 1 of a fitted ridge's weight, median 0.8); a ridge sampled on an edge,
/// or of small round or needle-shaped Gaussians, has none.
pub const GATE_FACE_SHARE: f64 = 1.0 / 3.0;

/// The move gate's slab: a face's splats, offsets along its normal, span this many robust
/// standard deviations (1.4826 x the median absolute deviation) to each side.
pub const GATE_SLAB_SIGMAS: f64 = 3.0;

/// Median and robust standard deviation (1.4826 x the median absolute deviation) of `v`.
fn median_sigma(v: &mut [f64]) -> (f64, f64) {
    let m = median(v);
    let mut dev: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
    (m, 1.4826 * median(&mut dev))
}

/// What [`gate_corner`] reads of one fitted segment: its members (cross-section offsets,
/// weights, working-set ids), the model's normals and thicknesses, the fitted line's
/// cross-section frame and the input line's ends in it.
#[derive(Clone, Copy)]
struct CornerInput<'a> {
    pts: &'a [(f64, DVec2)],
    pw: &'a [f64],
    normals: &'a [[f32; 3]],
    thickness: Option<&'a [f32]>,
    ids: &'a [u32],
    frame: (DVec3, DVec3),
    ends: [DVec2; 2],
}

/// The corner test: both faces' splats form slabs no thicker than the kernel `h` (each
/// half-width [`GATE_SLAB_SIGMAS`] times the robust deviation of their offsets along the
/// face's normal combined with the splats' median thickness), and an end of the input
/// line (`ends`, offsets in the fitted line's frame) lies outside one of them. A line
/// inside both slabs is as consistent with the faces as their intersection is: the splats
/// cannot place the edge more finely than their slabs.
fn gate_corner(c: &CornerInput<'_>, r: f64, h: f64, min_points: usize) -> bool {
    let CornerInput {
        pts,
        pw,
        normals,
        thickness,
        ids,
        frame: (e1, e2),
        ends,
    } = *c;
    let mut keep = Vec::new();
    let mut n2 = Vec::new();
    for (i, (p, id)) in pts.iter().zip(ids).enumerate() {
        if p.1.length() > r {
            continue;
        }
        let n = crate::geom::p64(normals[*id as usize]);
        let across = DVec2::new(n.dot(e1), n.dot(e2));
        if across.length() > 0.866 {
            keep.push(i);
            n2.push(across.normalize());
        }
    }
    let sub_w: Vec<f64> = keep.iter().map(|&i| pw[i]).collect();
    let Some(fam) = families(&n2, &sub_w, min_points) else {
        return false;
    };
    let mut thickest: f64 = 0.0;
    let mut outside = false;
    for (n, members) in &fam {
        let mut off: Vec<f64> = members.iter().map(|&j| n.dot(pts[keep[j]].1)).collect();
        let (c, sigma) = median_sigma(&mut off);
        // Each splat's own extent along its normal adds to the spread of their centers.
        let own = thickness.map_or(0.0, |th| {
            let mut t: Vec<f64> = members
                .iter()
                .map(|&j| f64::from(th[ids[keep[j]] as usize]))
                .collect();
            median(&mut t)
        });
        let half = GATE_SLAB_SIGMAS * sigma.hypot(own);
        thickest = thickest.max(half);
        outside |= ends.iter().any(|e| (n.dot(*e) - c).abs() > half);
    }
    thickest <= h && outside
}

/// The ridge test: around the fitted line (mean shift with the kernel `h` from it), less
/// than [`GATE_FACE_SHARE`] of the kernel weight comes from flat Gaussians (`flat`).
fn gate_ridge(pts: &[(f64, DVec2)], pw: &[f64], flat: &[bool], h: f64) -> bool {
    let mut cols = Columns::new(pts.iter().map(|p| p.1), pw);
    let mut c = DVec2::ZERO;
    let mut sw = 0.0;
    for _ in 0..50 {
        let s;
        (sw, s) = cols.round(c, h);
        if sw <= 0.0 {
            break;
        }
        let next = s / sw;
        let moved = (next - c).length();
        c = next;
        if moved < 1e-6 * h {
            break;
        }
    }
    cols.round(c, h);
    let faces: f64 = cols
        .k
        .iter()
        .zip(pw)
        .zip(flat)
        .filter(|(_, f)| **f)
        .map(|((k, w), _)| w * k)
        .sum();
    sw > 0.0 && faces / sw < GATE_FACE_SHARE
}

/// The move gate (`--fit-gate`): each segment the edge fit moved (`fitted`, from `input`)
/// keeps its move only where the Gaussians within r of its new line explain it (a corner
/// by `gate_corner`, a ridge by `gate_ridge`); the others go back to their input and
/// are marked [`How::Kept`]. One engine batch of members, none without normals (every
/// ridge then stands); the decision is the host's, so both engines agree. Returns how
/// many moves it undid.
pub fn gate(
    engine: &dyn Engine,
    input: &[Segment],
    fitted: &mut FitResult,
    attrs: &Attributes,
    r: f64,
    p: &Params,
) -> Result<usize, EngineError> {
    // Without normals every ridge stands and there is no corner: nothing to ask.
    let Some(ns) = attrs.normals.as_deref() else {
        return Ok(0);
    };
    let moved: Vec<usize> = (0..input.len())
        .filter(|&i| {
            fitted.segments[i] != input[i]
                && matches!(fitted.how[i], How::Corner | How::Ridge)
                && fitted.segments[i].is_valid()
        })
        .collect();
    if moved.is_empty() {
        return Ok(0);
    }
    // The decision is a function of the fitted and the input segment's bits and how the
    // line was found: copies of a segment (merged runs, busy areas) are decided once, and
    // their member lists listed once. Asking for every copy's list held one list a copy:
    // 10^4 copies in 20,000 Gaussians took 7 GB and 10 s.
    let all = moved;
    let mut seen: std::collections::HashMap<[u64; 13], usize> = Default::default();
    let mut moved = Vec::new();
    let of: Vec<usize> = all
        .iter()
        .map(|&i| {
            let (f, g) = (fitted.segments[i], input[i]);
            let mut k = [0u64; 13];
            for (j, v) in [f.p1, f.p2, g.p1, g.p2].iter().enumerate() {
                k[3 * j..3 * j + 3].copy_from_slice(&v.to_array().map(f64::to_bits));
            }
            k[12] = fitted.how[i] as u64;
            *seen.entry(k).or_insert_with(|| {
                moved.push(i);
                moved.len() - 1
            })
        })
        .collect();
    let queries: Vec<Query> = moved
        .iter()
        .map(|&i| Query::new(fitted.segments[i], r))
        .collect();
    let members = engine.members(&queries)?;
    let h = p.fit_bandwidth * r;
    let min_points = p.fit_min_points.max(1) as usize;
    let stands: Vec<bool> = {
        use rayon::prelude::*;
        moved
            .par_iter()
            .zip(&members)
            .map(|(&i, m)| {
                let s = &fitted.segments[i];
                let d = s.dir();
                let (e1, e2) = basis(d);
                let (pts, pw) = cross_section(m, (e1, e2), attrs, p);
                match fitted.how[i] {
                    How::Corner => {
                        let ids: Vec<u32> = m.iter().map(|m| m.id).collect();
                        let end = |q: glam::DVec3| {
                            let v = q - s.p1;
                            let o = v - d * v.dot(d);
                            DVec2::new(o.dot(e1), o.dot(e2))
                        };
                        let ends = [end(input[i].p1), end(input[i].p2)];
                        let input = CornerInput {
                            pts: &pts,
                            pw: &pw,
                            normals: ns,
                            thickness: attrs.thickness.as_deref(),
                            ids: &ids,
                            frame: (e1, e2),
                            ends,
                        };
                        gate_corner(&input, r, h, min_points)
                    }
                    _ => {
                        let flat: Vec<bool> =
                            m.iter().map(|m| ns[m.id as usize] != [0.0; 3]).collect();
                        gate_ridge(&pts, &pw, &flat, h)
                    }
                }
            })
            .collect()
    };
    let mut undone = 0;
    for (&i, &d) in all.iter().zip(&of) {
        if !stands[d] {
            fitted.segments[i] = input[i];
            fitted.how[i] = How::Kept;
            undone += 1;
        }
    }
    Ok(undone)
}
