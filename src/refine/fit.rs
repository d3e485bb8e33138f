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
use crate::refine::params::{group, Check};
use crate::refine::{Fit, Pass, Profile, Shifts, Step};
use glam::{DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// Per-point attributes of the working set (index = working-set id), where the file has them.
#[derive(Clone, Debug, Default)]
pub struct Attributes {
    /// Unit surface normal of each Gaussian (its shortest axis).
    pub normals: Option<Vec<[f32; 3]>>,
    /// Opacity of each Gaussian in `[0, 1]`: the fit's per-point weight with
    /// `--fit-opacity-weight`.
    pub opacity: Option<Vec<f32>>,
    /// Extent of each Gaussian (its largest standard deviation, scene units): how far a
    /// face's splats reach beyond their centres, for the face-end estimate.
    pub extent: Option<Vec<f32>>,
    /// Base colour of each Gaussian (RGB from its SH degree-0 terms), for the colour-change
    /// estimate.
    pub colour: Option<Vec<[f32; 3]>>,
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
            extent: None,
            colour: None,
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

impl From<&FitParams> for FitSpec {
    fn from(p: &FitParams) -> FitSpec {
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
    p: &FitParams,
) -> Option<(LineFit, f64)> {
    crate::geom::fit::ridge(pts, pw, r, p.fit_bandwidth, false)
}

/// The members' axial positions and cross-section offsets in the frame `(e1, e2)`, and
/// their weights (opacities with `--fit-opacity-weight`, else 1).
fn cross_section(
    members: &[Member],
    frame: (DVec3, DVec3),
    attrs: &Attributes,
    p: &FitParams,
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
    p: &FitParams,
) -> Result<FitResult, EngineError> {
    engine.fit_edges(&FitJob {
        segments,
        r,
        spec: &FitSpec::from(p),
        points: attrs.fit_points(),
    })
}

/// Which estimate of the edge a decision weighed ([`decide`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Estimate {
    /// The corner of two faces: planes fitted to the positions of the splats whose normals
    /// split them into two families.
    Corner,
    /// The ridge of the centers: the mode of their cross-section.
    Ridge,
    /// The end of one face's splats across the line: where their centres stop, plus
    /// their extent.
    FaceEnd,
    /// A change of the splats' colour across the line within one face.
    Colour,
}

/// What [`decide`] did with one segment.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Verdict {
    /// The line lay outside the estimate's uncertainty by the margin: moved onto it.
    Moved,
    /// The line lies within the margin of the estimate's uncertainty: the model knows the
    /// edge no better than the line does, and the line stays.
    ModelKnowsLess,
    /// Too few members for any estimate: the line stays.
    TooFewMembers,
}

/// The corner's evidence: the two faces the normals split the members into.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CornerEvidence {
    /// Distance between the corners of the faces' splats near it and far from it.
    pub near_far: f64,
    /// Members of each face.
    pub counts: [usize; 2],
    /// Robust spread (1.4826 x the median absolute deviation) of each face's splats about
    /// their own plane, scene units.
    pub residuals: [f64; 2],
    /// Angle between the faces' normals, degrees.
    pub angle_deg: f64,
    /// Share of the members within r with a normal that is more than 20° off both faces
    /// (a rounded corner, or normals that say nothing about the positions) or with no
    /// normal at all (round splats).
    pub off_faces: f64,
    /// How far the input line lies outside both faces (the smaller of its two distances,
    /// each its ends' mean, on the side away from the other face's splats); negative where
    /// it lies inside one: the splats sit that far below the line.
    pub outside: f64,
    /// Distance of the input line from the corner (its farther end), scene units.
    pub distance: f64,
    /// How well the corner is known: systematic floor (the faces' residuals) and
    /// statistical part (the planes' standard errors), scene units.
    pub floor: f64,
    pub statistical: f64,
}

/// The ridge's evidence: the centers' cross-section about their mode.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RidgeEvidence {
    /// Share of the members within r with a normal across the line, how much those
    /// normals agree (resultant length of their doubled angles, 1: one face) and the robust
    /// spread of the members' positions along their mean normal.
    pub face_share: f64,
    pub face_agree: f64,
    pub face_residual: f64,
    /// How far the mode moves when the kernel is twice as wide.
    pub wide: f64,
    /// Weight (members, or their opacities) within r/2 of the ridge.
    pub weight: f64,
    /// Share of the weight within r of the ridge that lies within r/2 of it.
    pub inner: f64,
    /// Root mean square distance from the ridge of the members within r/2 of it.
    pub spread: f64,
    /// Ratio of the smaller to the larger principal spread of those members (1: round
    /// blob, 0: a face through the ridge).
    pub roundness: f64,
    /// Distance of the input line from the ridge (its farther end), scene units.
    pub distance: f64,
    /// How well the ridge is known: systematic floor and statistical part.
    pub floor: f64,
    pub statistical: f64,
}

/// The face end's evidence: one face whose splats stop across the line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FaceEndEvidence {
    /// Members of the face (on its plane, normals within 20° of its normal).
    pub count: usize,
    /// Robust spread of the face's splats about their plane, scene units.
    pub residual: f64,
    /// Where the centres stop (the face's [`FACE_END_RANK`]-th member from its end,
    /// measured along the face from the input line, positive inside the face) and the
    /// splats' extent there (median largest standard deviation of the members within r/4
    /// of the end), scene units; the edge lies [`FACE_END_REACH`] extents beyond the
    /// centres' end.
    pub stop: f64,
    pub extent: f64,
    /// Face members per unit length across the line within r/4 of the end.
    pub density: f64,
    /// Share of the members within r with a normal more than 20° off the face (and off a
    /// second face where the normals split into two) or with no normal at all.
    pub off_faces: f64,
    /// Distance of the input line from the face's end (its farther end), scene units.
    pub distance: f64,
    /// How well the end is known: systematic floor (the face's residual, half the
    /// reach and, where a second face meets it, the end's distance from the two faces'
    /// corner, over the share of the normals that agree) and statistical part (the mean
    /// gap between members at the end, `1 / density`).
    pub floor: f64,
    pub statistical: f64,
}

/// The colour change's evidence: a step in the base colour of one face's splats across
/// the line, the face continuing on both sides.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ColourEvidence {
    /// Members of the face (on its plane, normals within 20° of its normal).
    pub count: usize,
    /// The step: distance between the two sides' mean colours (RGB in `[0, 1]`), and the
    /// share of the members whose colour is nearer the other side's.
    pub step: f64,
    pub mixed: f64,
    /// Half the width of the span of steps that leave at most `sqrt(k)` (at least 1) more
    /// members on the wrong side than the best step's `k` (a profile of the count), scene
    /// units.
    pub width: f64,
    /// The splats' extent at the step (median largest standard deviation within r/4).
    pub extent: f64,
    /// Distance of the input line from the step (its farther end), scene units.
    pub distance: f64,
    /// How well the step is known: systematic floor (the profile's half width and half
    /// the extent, over the share of members the two colours explain and the share of
    /// the members within r that are flat) and statistical part (the mean gap between
    /// members at the step).
    pub floor: f64,
    pub statistical: f64,
}

/// One segment's decision with its numbers (the report's `refine.fit_decisions`,
/// `refine --explain N`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Decision {
    /// Index of the segment in the lines given to the step.
    pub segment: usize,
    pub verdict: Verdict,
    /// The estimate weighed (the better known of the two), if any.
    pub estimate: Option<Estimate>,
    /// Members within r of the fitted line.
    pub members: usize,
    /// Share of those members that are flat (a normal: shortest axis 1.5x shorter than
    /// the next), where the model has normals.
    pub flat_share: Option<f64>,
    /// The input line's distance from the estimate and how well the estimate is known
    /// (`sqrt(floor^2 + statistical^2)`), scene units; the line moves when `distance`
    /// exceeds [`MOVE_MARGIN`] x `sigma`.
    pub distance: f64,
    pub sigma: f64,
    pub corner: Option<CornerEvidence>,
    pub ridge: Option<RidgeEvidence>,
    pub face_end: Option<FaceEndEvidence>,
    pub colour: Option<ColourEvidence>,
    /// The input segment and the fitted one (`x1 y1 z1 x2 y2 z2`).
    pub input: [f64; 6],
    pub fitted: [f64; 6],
    /// The two estimates' lines, where they exist.
    pub corner_line: Option<[f64; 6]>,
    pub ridge_line: Option<[f64; 6]>,
    pub face_end_line: Option<[f64; 6]>,
    pub colour_line: Option<[f64; 6]>,
}

/// A line moves onto an estimate only when it lies farther from it than this many times
/// the estimate's uncertainty.
pub const MOVE_MARGIN: f64 = 3.5;

/// The decision rule lists the members of at most this many segments at a time (each at
/// its fitted and its input line): what it holds at once stays bounded at any scene size.
pub const DECIDE_CHUNK: usize = 4096;

/// The decision rule weighs the lists of at most this many queries at a time, as the
/// engine hands them out ([`crate::engine::Engine::members_in_parts`]).
pub const DECIDE_PART: usize = 512;

/// The ridge's floor counts how far its mode moves with a kernel twice as wide this many
/// times.
pub const RIDGE_WIDE: f64 = 2.0;

/// The ridge's floor counts its spread this many times the share of its members that the
/// normals name as surface.
pub const RIDGE_SURFACE: f64 = 6.0;

/// Median and robust standard deviation (1.4826 x the median absolute deviation) of `v`.
fn median_sigma(v: &mut [f64]) -> (f64, f64) {
    let m = median(v);
    let mut dev: Vec<f64> = v.iter().map(|x| (x - m).abs()).collect();
    (m, 1.4826 * median(&mut dev))
}

/// The farther of `ends` from `c`.
fn farther(ends: &[DVec2; 2], c: DVec2) -> f64 {
    (ends[0] - c).length().max((ends[1] - c).length())
}

/// The ridge of the cross-section `pts` (mean shift with the kernel `h` from the fitted
/// line) and what the members say of how well it is known.
fn ridge_evidence(
    pts: &[(f64, DVec2)],
    pw: &[f64],
    ends: &[DVec2; 2],
    r: f64,
    h: f64,
) -> Option<(DVec2, RidgeEvidence)> {
    let mut cols = Columns::new(pts.iter().map(|p| p.1), pw);
    let c = mode(&mut cols, DVec2::ZERO, h)?;
    let wide = mode(&mut cols, c, 2.0 * h).unwrap_or(c);
    let (mut w_all, mut w_in) = (0.0, 0.0);
    let (mut sxx, mut syy, mut sxy) = (0.0, 0.0, 0.0);
    for (p, w) in pts.iter().zip(pw) {
        let d = p.1 - c;
        let l = d.length();
        if l <= r {
            w_all += w;
        }
        if l <= 0.5 * r {
            w_in += w;
            sxx += w * d.x * d.x;
            syy += w * d.y * d.y;
            sxy += w * d.x * d.y;
        }
    }
    if w_in <= 0.0 {
        return None;
    }
    let (sxx, syy, sxy) = (sxx / w_in, syy / w_in, sxy / w_in);
    let tr = sxx + syy;
    let det = sxx * syy - sxy * sxy;
    let disc = (0.25 * tr * tr - det).max(0.0).sqrt();
    let (l1, l2) = (0.5 * tr + disc, (0.5 * tr - disc).max(0.0));
    let spread = tr.sqrt();
    let roundness = if l1 > 0.0 { (l2 / l1).sqrt() } else { 1.0 };
    let inner = w_in / w_all.max(w_in);
    let statistical = spread / w_in.sqrt();
    let floor = 0.0;
    Some((
        c,
        RidgeEvidence {
            face_share: 0.0,
            face_agree: 0.0,
            face_residual: 0.0,
            wide: (wide - c).length(),
            weight: w_in,
            inner,
            spread,
            roundness,
            distance: farther(ends, c),
            floor,
            statistical,
        },
    ))
}

/// The mode of the offsets in `cols` by mean shift with the kernel `h`, from `c`.
fn mode(cols: &mut Columns, mut c: DVec2, h: f64) -> Option<DVec2> {
    for _ in 0..100 {
        let (sw, s) = cols.round(c, h);
        if sw <= 0.0 {
            return None;
        }
        let next = s / sw;
        let moved = (next - c).length();
        c = next;
        if moved < 1e-6 * h {
            break;
        }
    }
    Some(c)
}

/// The face through the ridge `c`, where the members' normals name one: the share of the
/// members within r of `c` with a normal across the line, the resultant length of those
/// normals' doubled angles (1: all alike), and the robust spread of their offsets along
/// the mean normal.
fn face_through(
    pts: &[(f64, DVec2)],
    m: &[Member],
    normals: &[[f32; 3]],
    (e1, e2): (DVec3, DVec3),
    c: DVec2,
    r: f64,
) -> (f64, f64, f64) {
    let mut n_all = 0usize;
    let mut q = Vec::new();
    let mut across = Vec::new();
    let mut dbl = DVec2::ZERO;
    for (p, mm) in pts.iter().zip(m) {
        if (p.1 - c).length() > r {
            continue;
        }
        n_all += 1;
        let n = crate::geom::p64(normals[mm.id as usize]);
        let a = DVec2::new(n.dot(e1), n.dot(e2));
        if a.length() > 0.866 {
            let a = a.normalize();
            dbl += DVec2::new(a.x * a.x - a.y * a.y, 2.0 * a.x * a.y);
            q.push(p.1);
            across.push(a);
        }
    }
    if q.len() < 3 || n_all == 0 {
        return (0.0, 0.0, 0.0);
    }
    // One face: the resultant of the doubled angles. Two faces: the two families'
    // resultants, less what two halves of random directions reach (2/pi), rescaled.
    let mut agree = dbl.length() / q.len() as f64;
    if let Some(fam) = families(&across, &vec![1.0; across.len()], 2) {
        let two: f64 = fam
            .iter()
            .map(|(_, m)| {
                m.iter()
                    .map(|&j| {
                        let a = across[j];
                        DVec2::new(a.x * a.x - a.y * a.y, 2.0 * a.x * a.y)
                    })
                    .sum::<DVec2>()
                    .length()
            })
            .sum::<f64>()
            / q.len() as f64;
        let random = 2.0 / std::f64::consts::PI;
        agree = agree.max((two - random) / (1.0 - random));
    }
    let ang = 0.5 * dbl.y.atan2(dbl.x);
    let n = DVec2::new(ang.cos(), ang.sin());
    let mut off: Vec<f64> = q.iter().map(|p| n.dot(*p)).collect();
    let (_, s) = median_sigma(&mut off);
    (q.len() as f64 / n_all as f64, agree, s)
}

/// The corner of the members' two faces (normals split them into families; each face's
/// plane is the median offset of its splats' positions along the family's normal) and
/// what the members say of how well it is known.
fn corner_evidence(
    c: &CornerInput<'_>,
    r: f64,
    min_points: usize,
) -> Option<(DVec2, CornerEvidence)> {
    let CornerInput {
        pts,
        pw,
        normals,
        ids,
        frame: (e1, e2),
        ends,
    } = *c;
    let d = e1.cross(e2);
    let mut keep = Vec::new();
    let mut n2 = Vec::new();
    let mut with_normal = Vec::new();
    let mut within = 0usize;
    for (i, (p, id)) in pts.iter().zip(ids).enumerate() {
        if p.1.length() > r {
            continue;
        }
        within += 1;
        let n = crate::geom::p64(normals[*id as usize]);
        if n != DVec3::ZERO {
            with_normal.push(n);
        }
        let across = DVec2::new(n.dot(e1), n.dot(e2));
        if across.length() > 0.866 {
            keep.push(i);
            n2.push(across.normalize());
        }
    }
    let sub_w: Vec<f64> = keep.iter().map(|&i| pw[i]).collect();
    let fam = families(&n2, &sub_w, min_points)?;
    let mut off_of: [Vec<f64>; 2] = Default::default();
    let mut centre = [0.0; 2];
    let mut resid = [0.0; 2];
    let mut counts = [0; 2];
    for (k, (n, members)) in fam.iter().enumerate() {
        let mut off: Vec<f64> = members.iter().map(|&j| n.dot(pts[keep[j]].1)).collect();
        let (m, s) = median_sigma(&mut off);
        off_of[k] = members.iter().map(|&j| n.dot(pts[keep[j]].1)).collect();
        centre[k] = m;
        resid[k] = s;
        counts[k] = members.len();
    }
    let (n1, n2v) = (fam[0].0, fam[1].0);
    let det = n1.x * n2v.y - n1.y * n2v.x;
    if det.abs() < 1e-9 {
        return None;
    }
    let corner = DVec2::new(
        (centre[0] * n2v.y - centre[1] * n1.y) / det,
        (n1.x * centre[1] - n2v.x * centre[0]) / det,
    );
    let sin = det.abs();
    let solve = |c0: f64, c1: f64| {
        DVec2::new(
            (c0 * n2v.y - c1 * n1.y) / det,
            (n1.x * c1 - n2v.x * c0) / det,
        )
    };
    // The planes of the members near the corner and of those farther off.
    let part = |near: bool| -> Option<DVec2> {
        let mut cc = [0.0; 2];
        for (k, (n, members)) in fam.iter().enumerate() {
            let mut off: Vec<f64> = members
                .iter()
                .filter(|&&j| ((pts[keep[j]].1 - corner).length() <= 0.5 * r) == near)
                .map(|&j| n.dot(pts[keep[j]].1))
                .collect();
            if off.len() < 3 {
                return None;
            }
            cc[k] = median(&mut off);
        }
        Some(solve(cc[0], cc[1]))
    };
    let near_far = match (part(true), part(false)) {
        (Some(a), Some(b)) => (a - b).length(),
        _ => -1.0,
    };
    // Normals more than 20° off both faces (3D: a normal along the line is off both),
    // and members with no normal (round: they do not say where a face is).
    let lift = |n: DVec2| e1 * n.x + e2 * n.y;
    let cos20 = 20f64.to_radians().cos();
    let off = with_normal
        .iter()
        .filter(|n| n.dot(lift(n1)).abs() < cos20 && n.dot(lift(n2v)).abs() < cos20)
        .count();
    let off_faces = (off + within - with_normal.len()) as f64 / within.max(1) as f64;
    let _ = d;
    // The outside of face k: away from the other face's splats.
    let mut outside = f64::INFINITY;
    for k in 0..2 {
        let n = fam[k].0;
        let mut other: Vec<f64> = off_of[1 - k].iter().map(|_| 0.0).collect();
        for (o, &j) in other.iter_mut().zip(&fam[1 - k].1) {
            *o = n.dot(pts[keep[j]].1) - centre[k];
        }
        let inside = median(&mut other).signum();
        let out = -inside * 0.5 * ((n.dot(ends[0]) - centre[k]) + (n.dot(ends[1]) - centre[k]));
        outside = outside.min(out);
    }
    let floor = resid[0].hypot(resid[1]) / sin;
    let se = |k: usize| 1.2533 * resid[k] / (counts[k] as f64).sqrt();
    let statistical = se(0).hypot(se(1)) / sin;
    let angle_deg = n1.dot(n2v).abs().min(1.0).acos().to_degrees();
    Some((
        corner,
        CornerEvidence {
            near_far,
            counts,
            residuals: resid,
            angle_deg,
            off_faces,
            outside,
            distance: farther(&ends, corner),
            floor,
            statistical,
        },
    ))
}

/// An estimate of the edge with its systematic floor and statistical part: known to
/// `floor (+) statistical` (added in quadrature).
trait Known {
    fn sigma(&self) -> f64;
}

impl Known for FaceEndEvidence {
    fn sigma(&self) -> f64 {
        self.floor.hypot(self.statistical)
    }
}

impl Known for ColourEvidence {
    fn sigma(&self) -> f64 {
        self.floor.hypot(self.statistical)
    }
}

/// `best` becomes `(edge, e)` where it is empty or `e` is better known (the first of
/// equals stays).
fn keep_surer<E: Known>(best: &mut Option<(DVec2, E)>, edge: DVec2, e: E) {
    if best.as_ref().is_none_or(|b| e.sigma() < b.1.sigma()) {
        *best = Some((edge, e));
    }
}

/// The centres of a face's splats stop this many of its members before its end (the
/// `FACE_END_RANK`-th member from the end: one stray splat does not move the end).
pub const FACE_END_RANK: usize = 3;

/// A face end counts where it lies within this many r of the input line: a quarter r of
/// the face beyond it stays inside the cylinder, and lines up to half r off are reached.
pub const FACE_END_WITHIN: f64 = 0.6;

/// A face's edge lies this many of its splats' extents (largest standard deviation)
/// beyond where their centres stop: a trained splat straddling the edge would paint past
/// it, so the trainer leaves the centres about one extent inside. Half of it counts in the
/// estimate's floor.
pub const FACE_END_REACH: f64 = 1.0;

/// The end of one face's splats across the input line (`pts`: the members of the input
/// line's cylinder in its own cross-section frame, where the line is the origin): normals
/// name the faces (one, or two families); each face's plane is the median of its
/// splats' offsets along its normal; a face that stops inside the cylinder (its members
/// all on one side of their end, the end within [`FACE_END_WITHIN`] r of the line) gives
/// an edge [`FACE_END_REACH`] extents beyond its [`FACE_END_RANK`]-th member from the
/// end. The best known face's end, if any.
fn face_end_evidence(
    c: &CornerInput<'_>,
    extent: Option<&[f32]>,
    r: f64,
    min_points: usize,
) -> Option<(DVec2, FaceEndEvidence)> {
    let CornerInput {
        pts,
        pw,
        normals,
        ids,
        frame: (e1, e2),
        ..
    } = *c;
    let mut keep = Vec::new();
    let mut n2 = Vec::new();
    let mut with_normal = Vec::new();
    let mut within = 0usize;
    for (i, (p, id)) in pts.iter().zip(ids).enumerate() {
        if p.1.length() > r {
            continue;
        }
        within += 1;
        let n = crate::geom::p64(normals[*id as usize]);
        if n == DVec3::ZERO {
            continue;
        }
        with_normal.push(n);
        let across = DVec2::new(n.dot(e1), n.dot(e2));
        if across.length() > 0.866 {
            keep.push(i);
            n2.push(across.normalize());
        }
    }
    if keep.len() < 2 * min_points.max(FACE_END_RANK) {
        return None;
    }
    // The faces: two families where the normals split, else their one mean direction.
    let sub_w: Vec<f64> = keep.iter().map(|&i| pw[i]).collect();
    let faces: Vec<DVec2> = match families(&n2, &sub_w, min_points) {
        Some(f) => vec![f[0].0, f[1].0],
        None => {
            let dbl: DVec2 = n2
                .iter()
                .map(|a| DVec2::new(a.x * a.x - a.y * a.y, 2.0 * a.x * a.y))
                .sum();
            let ang = 0.5 * dbl.y.atan2(dbl.x);
            vec![DVec2::new(ang.cos(), ang.sin())]
        }
    };
    let cos20 = 20f64.to_radians().cos();
    let lift = |n: DVec2| e1 * n.x + e2 * n.y;
    let off = with_normal
        .iter()
        .filter(|n| faces.iter().all(|f| n.dot(lift(*f)).abs() < cos20))
        .count();
    let off_faces = (off + within - with_normal.len()) as f64 / within.max(1) as f64;
    // Each face's members and plane (median offset along its normal, robust spread).
    let planes: Vec<(DVec2, Vec<usize>, f64, f64)> = faces
        .iter()
        .map(|&n| {
            let on: Vec<usize> = keep
                .iter()
                .zip(&n2)
                .filter(|(_, a)| a.dot(n).abs() >= cos20)
                .map(|(&i, _)| i)
                .collect();
            let mut offs: Vec<f64> = on.iter().map(|&i| n.dot(pts[i].1)).collect();
            let (plane, residual) = if offs.is_empty() {
                (0.0, 0.0)
            } else {
                median_sigma(&mut offs)
            };
            (n, on, plane, residual)
        })
        .collect();
    // Where two faces meet, their corner: a face end away from it is not the edge (a
    // face that stops short of the corner), and the floor counts how far it is.
    let corner = match planes.as_slice() {
        [(a, _, ca, _), (b, _, cb, _)] => {
            let det = a.x * b.y - a.y * b.x;
            (det.abs() > 1e-9)
                .then(|| DVec2::new((ca * b.y - cb * a.y) / det, (a.x * cb - b.x * ca) / det))
        }
        _ => None,
    };
    let mut best: Option<(DVec2, FaceEndEvidence)> = None;
    for (n, on, plane, residual) in planes {
        if on.len() < 2 * min_points.max(FACE_END_RANK) {
            continue;
        }
        let u = DVec2::new(-n.y, n.x);
        let band = (3.0 * residual).max(1e-9);
        let mut across: Vec<(f64, usize)> = on
            .iter()
            .filter(|&&i| (n.dot(pts[i].1) - plane).abs() <= band)
            .map(|&i| (u.dot(pts[i].1), i))
            .collect();
        if across.len() < 2 * min_points.max(FACE_END_RANK) {
            continue;
        }
        // The face lies on the side with more of its members; its end is toward the
        // other side.
        let plus = across.iter().filter(|a| a.0 > 0.0).count();
        let side = if 2 * plus >= across.len() { 1.0 } else { -1.0 };
        for a in &mut across {
            a.0 *= side;
        }
        across.sort_by(|a, b| a.0.total_cmp(&b.0));
        let end = across[FACE_END_RANK - 1].0;
        // The face must stop inside the cylinder, with r/4 of it seen beyond its end
        // (not where it merely leaves the cylinder).
        if end.abs() > FACE_END_WITHIN * r {
            continue;
        }
        let near: Vec<usize> = across
            .iter()
            .filter(|a| a.0 - end <= 0.25 * r)
            .map(|a| a.1)
            .collect();
        if near.len() < min_points.max(FACE_END_RANK) {
            continue;
        }
        let density = near.len() as f64 / (0.25 * r);
        let mut ext: Vec<f64> = across
            .iter()
            .filter(|a| a.0 - end <= 0.25 * r)
            .map(|a| extent.map_or(0.0, |e| f64::from(e[ids[a.1] as usize])))
            .filter(|e| e.is_finite())
            .collect();
        let extent = if ext.is_empty() {
            0.0
        } else {
            median(&mut ext)
        };
        let reach = FACE_END_REACH * extent;
        let edge = n * plane + u * (side * (end - reach));
        let apart = corner.map_or(0.0, |c| (edge - c).length());
        let floor = residual.hypot(0.5 * reach).hypot(apart) / (1.0 - off_faces).max(1e-3);
        let statistical = 1.0 / density;
        let e = FaceEndEvidence {
            count: across.len(),
            residual,
            stop: end,
            extent,
            density,
            off_faces,
            distance: edge.length(),
            floor,
            statistical,
        };
        keep_surer(&mut best, edge, e);
    }
    best
}

/// A step of the base colour across the input line within one face (`pts` as for
/// [`face_end_evidence`]): the faces' planes as there; for each face that continues at
/// least `r/2` on both sides of its best step, the step that best splits the members'
/// colours in two (least squares of the RGB means over every split of the members
/// ordered across the line), placed on the face's plane midway between the two members
/// it falls between. The best known step, if any.
fn colour_evidence(
    c: &CornerInput<'_>,
    colour: &[[f32; 3]],
    extent: Option<&[f32]>,
    r: f64,
    min_points: usize,
) -> Option<(DVec2, ColourEvidence)> {
    let CornerInput {
        pts,
        normals,
        ids,
        frame: (e1, e2),
        ..
    } = *c;
    let lim = 2 * min_points.max(FACE_END_RANK);
    let mut keep = Vec::new();
    let mut n2 = Vec::new();
    let (mut in_r, mut round) = (0usize, 0usize);
    for (i, (p, id)) in pts.iter().zip(ids).enumerate() {
        if p.1.length() > r {
            continue;
        }
        in_r += 1;
        let n = crate::geom::p64(normals[*id as usize]);
        round += usize::from(n == DVec3::ZERO);
        let across = DVec2::new(n.dot(e1), n.dot(e2));
        if n != DVec3::ZERO && across.length() > 0.866 {
            keep.push(i);
            n2.push(across.normalize());
        }
    }
    if keep.len() < lim {
        return None;
    }
    let w1 = vec![1.0; n2.len()];
    let faces: Vec<DVec2> = match families(&n2, &w1, min_points) {
        Some(f) => vec![f[0].0, f[1].0],
        None => {
            let dbl: DVec2 = n2
                .iter()
                .map(|a| DVec2::new(a.x * a.x - a.y * a.y, 2.0 * a.x * a.y))
                .sum();
            let ang = 0.5 * dbl.y.atan2(dbl.x);
            vec![DVec2::new(ang.cos(), ang.sin())]
        }
    };
    let cos20 = 20f64.to_radians().cos();
    let rgb = |i: usize| DVec3::from(colour[ids[i] as usize].map(f64::from));
    let mut best: Option<(DVec2, ColourEvidence)> = None;
    for n in faces {
        let on: Vec<usize> = keep
            .iter()
            .zip(&n2)
            .filter(|(_, a)| a.dot(n).abs() >= cos20)
            .map(|(&i, _)| i)
            .collect();
        if on.len() < lim {
            continue;
        }
        let mut offs: Vec<f64> = on.iter().map(|&i| n.dot(pts[i].1)).collect();
        let (plane, residual) = median_sigma(&mut offs);
        let u = DVec2::new(-n.y, n.x);
        let band = (3.0 * residual).max(1e-9);
        let mut across: Vec<(f64, usize)> = on
            .iter()
            .filter(|&&i| (n.dot(pts[i].1) - plane).abs() <= band)
            .map(|&i| (u.dot(pts[i].1), i))
            .filter(|_| true)
            .collect();
        let k = across.len();
        if k < lim || across.iter().any(|a| !rgb(a.1).is_finite()) {
            continue;
        }
        across.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        // Least squares over every split j (members [0, j) | [j, k)), both sides at least
        // `min_points`: the best split maximises j |m1|^2 + (k - j) |m2|^2.
        let total: DVec3 = across.iter().map(|a| rgb(a.1)).sum();
        let lo = min_points.max(FACE_END_RANK);
        let mut acc = DVec3::ZERO;
        let mut split: Option<(usize, f64)> = None;
        for j in 1..k {
            acc += rgb(across[j - 1].1);
            if j < lo || k - j < lo {
                continue;
            }
            let (a, b) = (acc / j as f64, (total - acc) / (k - j) as f64);
            let gain = j as f64 * a.length_squared() + (k - j) as f64 * b.length_squared();
            if split.is_none_or(|s| gain > s.1) {
                split = Some((j, gain));
            }
        }
        let Some((j, _)) = split else { continue };
        let pos = 0.5 * (across[j - 1].0 + across[j].0);
        // The face continues on both sides of the step.
        if pos - across[0].0 < 0.5 * r || across[k - 1].0 - pos < 0.5 * r {
            continue;
        }
        let head: DVec3 = across[..j].iter().map(|a| rgb(a.1)).sum::<DVec3>() / j as f64;
        let tail = (total - head * j as f64) / (k - j) as f64;
        let dv = tail - head;
        let step = dv.length();
        if step <= 0.0 {
            continue;
        }
        // Which side each member's colour is nearer; the count of members on the wrong
        // side of every split, and the span of splits within sqrt(best) (at least 1) of
        // the best count.
        let far: Vec<bool> = across
            .iter()
            .map(|a| (rgb(a.1) - head).dot(dv) > 0.5 * dv.length_squared())
            .collect();
        let mut wrong: Vec<usize> = Vec::with_capacity(k + 1);
        let mut count = far.iter().filter(|&&f| !f).count();
        wrong.push(count);
        for f in &far {
            if *f {
                count += 1;
            } else {
                count -= 1;
            }
            wrong.push(count);
        }
        let least = *wrong.iter().min()?;
        let within = least as f64 + (least as f64).sqrt().max(1.0);
        let at = |s: usize| match s {
            0 => across[0].0,
            s if s == k => across[k - 1].0,
            s => 0.5 * (across[s - 1].0 + across[s].0),
        };
        let inside: Vec<usize> = (0..=k).filter(|&s| wrong[s] as f64 <= within).collect();
        let width = 0.5 * (at(*inside.last()?) - at(inside[0]));
        let mixed = least as f64 / k as f64;
        let near: Vec<f64> = across
            .iter()
            .filter(|a| (a.0 - pos).abs() <= 0.25 * r)
            .map(|a| extent.map_or(0.0, |e| f64::from(e[ids[a.1] as usize])))
            .filter(|e| e.is_finite())
            .collect();
        let density = near.len() as f64 / (0.5 * r);
        let mut near = near;
        let extent = if near.is_empty() {
            0.0
        } else {
            median(&mut near)
        };
        let flat = 1.0 - round as f64 / in_r.max(1) as f64;
        let floor = width.hypot(0.5 * extent) / ((1.0 - 2.0 * mixed) * flat).max(1e-3);
        let statistical = 1.0 / density.max(1e-9);
        let edge = n * plane + u * pos;
        let e = ColourEvidence {
            count: k,
            step,
            mixed,
            width,
            extent,
            distance: edge.length(),
            floor,
            statistical,
        };
        keep_surer(&mut best, edge, e);
    }
    best
}

/// What [`corner_evidence`] reads of one fitted segment: its members (cross-section
/// offsets, weights, working-set ids), the model's normals, the fitted line's
/// cross-section frame and the input line's ends in it.
#[derive(Clone, Copy)]
struct CornerInput<'a> {
    pts: &'a [(f64, DVec2)],
    pw: &'a [f64],
    normals: &'a [[f32; 3]],
    ids: &'a [u32],
    frame: (DVec3, DVec3),
    ends: [DVec2; 2],
}

fn seg6(s: &Segment) -> [f64; 6] {
    [s.p1.x, s.p1.y, s.p1.z, s.p2.x, s.p2.y, s.p2.z]
}

/// The decision rule (`--fit-gate`, on in `default`): for each segment the edge fit
/// moved (`fitted`, from `input`), both estimates of the edge near its new line (the
/// corner of two faces, where normals split the members into two; the ridge of the
/// centers) with how well the members know each: a systematic floor that does not shrink
/// with their count and a statistical part that does. The better known estimate is
/// weighed: the line moves onto it only where the input line lies farther from it than
/// [`MOVE_MARGIN`] times its uncertainty; otherwise it goes back to its input
/// ([`How::Kept`]). One engine batch of members; the decision is the host's, so both
/// engines agree. Returns every weighed segment's decision.
pub fn decide(
    engine: &dyn Engine,
    input: &[Segment],
    fitted: &mut FitResult,
    attrs: &Attributes,
    r: f64,
    p: &FitParams,
) -> Result<Vec<Decision>, EngineError> {
    decide_in_chunks(engine, input, fitted, attrs, r, p, DECIDE_CHUNK)
}

/// [`decide`] listing the members of at most `chunk` distinct moved segments per engine
/// batch (at least 1): the decisions do not depend on it.
pub fn decide_in_chunks(
    engine: &dyn Engine,
    input: &[Segment],
    fitted: &mut FitResult,
    attrs: &Attributes,
    r: f64,
    p: &FitParams,
    chunk: usize,
) -> Result<Vec<Decision>, EngineError> {
    let moved: Vec<usize> = (0..input.len())
        .filter(|&i| {
            fitted.segments[i] != input[i]
                && matches!(fitted.how[i], How::Corner | How::Ridge)
                && fitted.segments[i].is_valid()
        })
        .collect();
    let mut out: Vec<Decision> = (0..input.len())
        .filter(|&i| fitted.how[i] == How::Unclear)
        .map(|i| Decision {
            segment: i,
            verdict: Verdict::TooFewMembers,
            estimate: None,
            members: 0,
            flat_share: None,
            distance: 0.0,
            sigma: 0.0,
            corner: None,
            ridge: None,
            face_end: None,
            colour: None,
            input: seg6(&input[i]),
            fitted: seg6(&fitted.segments[i]),
            corner_line: None,
            ridge_line: None,
            face_end_line: None,
            colour_line: None,
        })
        .collect();
    if moved.is_empty() {
        return Ok(out);
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
    // The fitted lines' members (corner, ridge) and the input lines' (face end), in
    // chunks of at most `chunk` segments (of equal sizes: no chunk is small enough to
    // count as a small batch where the whole is not): the member lists held at once stay
    // bounded, and each segment's decision depends on its own lists only.
    let h = p.fit_bandwidth * r;
    let min_points = p.fit_min_points.max(1) as usize;
    let fitted_ref: &FitResult = fitted;
    let weigh = |i: usize, m: &[Member], m_in: &[Member]| -> (Decision, Option<Segment>) {
        let s = &fitted_ref.segments[i];
        let d = s.dir();
        let (e1, e2) = basis(d);
        let (pts, pw) = cross_section(m, (e1, e2), attrs, p);
        let end = |q: glam::DVec3| {
            let v = q - s.p1;
            let o = v - d * v.dot(d);
            DVec2::new(o.dot(e1), o.dot(e2))
        };
        let ends = [end(input[i].p1), end(input[i].p2)];
        let mut ridge = ridge_evidence(&pts, &pw, &ends, r, h);
        if let (Some((c, e)), Some(ns)) = (ridge.as_mut(), attrs.normals.as_deref()) {
            let (share, agree, res) = face_through(&pts, m, ns, (e1, e2), *c, r);
            e.face_share = share;
            e.face_agree = agree;
            e.face_residual = res;
        }
        let corner = attrs.normals.as_deref().and_then(|ns| {
            let ids: Vec<u32> = m.iter().map(|m| m.id).collect();
            corner_evidence(
                &CornerInput {
                    pts: &pts,
                    pw: &pw,
                    normals: ns,
                    ids: &ids,
                    frame: (e1, e2),
                    ends,
                },
                r,
                min_points,
            )
        });
        // The face end, in the input line's own frame.
        let g = &input[i];
        let frame_in = basis(g.dir());
        // One cross-section of the input line's members serves both estimates.
        let section_in = attrs.normals.as_deref().map(|ns| {
            let (pts, pw) = cross_section(m_in, frame_in, attrs, p);
            let ids: Vec<u32> = m_in.iter().map(|m| m.id).collect();
            (pts, pw, ids, ns)
        });
        let at_in = section_in.as_ref().map(|(pts, pw, ids, ns)| CornerInput {
            pts,
            pw,
            normals: ns,
            ids,
            frame: frame_in,
            ends: [DVec2::ZERO; 2],
        });
        let face_end = at_in
            .as_ref()
            .and_then(|c| face_end_evidence(c, attrs.extent.as_deref(), r, min_points));
        let shifted = |base: &Segment, (e1, e2): (DVec3, DVec3), c: DVec2| {
            let shift = e1 * c.x + e2 * c.y;
            Segment::new(base.p1 + shift, base.p2 + shift)
        };
        let face_end_line = face_end.as_ref().map(|c| seg6(&shifted(g, frame_in, c.0)));
        let colour = match (at_in.as_ref(), attrs.colour.as_deref()) {
            (Some(c), Some(cs)) => colour_evidence(c, cs, attrs.extent.as_deref(), r, min_points),
            _ => None,
        };
        let colour_line = colour.as_ref().map(|c| seg6(&shifted(g, frame_in, c.0)));
        let at = |c: DVec2| seg6(&shifted(s, (e1, e2), c));
        let corner_line = corner.as_ref().map(|c| at(c.0));
        let ridge_line = ridge.as_ref().map(|c| at(c.0));
        // The corner's floor: its faces' residuals and the disagreement of the
        // splats near it with those far off, over the share of the normals that
        // agree with the faces.
        let mut corner = corner;
        if let Some((_, e)) = corner.as_mut() {
            e.floor = e.floor.hypot(e.near_far.max(0.0)) / (1.0 - e.off_faces).max(1e-3);
        }
        // The ridge's floor: how far its mode moves with a kernel twice as wide,
        // how flat the cross-section is, and how much of it the normals name as
        // surface (a face, or the corner's two).
        if let Some((_, e)) = ridge.as_mut() {
            let agree = corner
                .as_ref()
                .map_or(e.face_agree, |c| e.face_agree.max(1.0 - c.1.off_faces));
            let surface = e.face_share * agree;
            e.floor = (RIDGE_WIDE * e.wide)
                .hypot(e.spread * (1.0 - e.roundness) / e.roundness.max(1e-3))
                .hypot(RIDGE_SURFACE * surface * e.spread);
        }
        let sig = |f: f64, s: f64| f.hypot(s);
        // The better known estimate.
        let mut best: Option<(Estimate, DVec2, f64, f64)> = None;
        if let Some((c, e)) = &corner {
            best = Some((
                Estimate::Corner,
                *c,
                e.distance,
                sig(e.floor, e.statistical),
            ));
        }
        if let Some((c, e)) = &ridge {
            let s = sig(e.floor, e.statistical);
            if best.is_none_or(|b| s < b.3) {
                best = Some((Estimate::Ridge, *c, e.distance, s));
            }
        }
        if let Some((c, e)) = &face_end {
            let s = sig(e.floor, e.statistical);
            if best.is_none_or(|b| s < b.3) {
                best = Some((Estimate::FaceEnd, *c, e.distance, s));
            }
        }
        if let Some((c, e)) = &colour {
            let s = sig(e.floor, e.statistical);
            if best.is_none_or(|b| s < b.3) {
                best = Some((Estimate::Colour, *c, e.distance, s));
            }
        }
        let (verdict, estimate, distance, sigma, seg) = match best {
            None => (Verdict::TooFewMembers, None, 0.0, 0.0, None),
            Some((est, c, dist, sigma)) => {
                if dist > MOVE_MARGIN * sigma {
                    let seg = if matches!(est, Estimate::FaceEnd | Estimate::Colour) {
                        shifted(g, frame_in, c)
                    } else {
                        shifted(s, (e1, e2), c)
                    };
                    (Verdict::Moved, Some(est), dist, sigma, Some(seg))
                } else {
                    (Verdict::ModelKnowsLess, Some(est), dist, sigma, None)
                }
            }
        };
        (
            Decision {
                segment: i,
                verdict,
                estimate,
                members: m.len(),
                flat_share: attrs.normals.as_deref().map(|ns| {
                    let flat = m.iter().filter(|mm| ns[mm.id as usize] != [0.0; 3]).count();
                    flat as f64 / m.len().max(1) as f64
                }),
                distance,
                sigma,
                corner: corner.map(|c| c.1),
                ridge: ridge.map(|c| c.1),
                face_end: face_end.map(|c| c.1),
                colour: colour.map(|c| c.1),
                input: seg6(&input[i]),
                fitted: seg6(s),
                corner_line,
                ridge_line,
                face_end_line,
                colour_line,
            },
            seg,
        )
    };
    let chunks = moved.len().div_ceil(chunk.max(1));
    let size = moved.len().div_ceil(chunks);
    let mut decided: Vec<Option<(Decision, Option<Segment>)>> = vec![None; moved.len()];
    // The input lines' members serve the face end and the colour change only, both read
    // off normals: a model without normals lists the fitted lines alone.
    let at_input_too = attrs.normals.is_some();
    let group = 1 + at_input_too as usize;
    for (c, chunk) in moved.chunks(size).enumerate() {
        // Each segment's fitted line, then (with normals) its input line: one group.
        let queries: Vec<Query> = chunk
            .iter()
            .flat_map(|&i| {
                let fit = Query::new(fitted_ref.segments[i], r);
                std::iter::once(fit).chain(at_input_too.then(|| Query::new(input[i], r)))
            })
            .collect();
        // The lists come a part at a time and are weighed as they come: the lists held
        // at once are one part's (a few MB, in cache), not the chunk's.
        let slots = &mut decided[c * size..c * size + chunk.len()];
        engine.members_in_parts(&queries, group, DECIDE_PART, &mut |idx, lists| {
            use rayon::prelude::*;
            let weighed: Vec<(usize, (Decision, Option<Segment>))> = idx
                .par_chunks(group)
                .zip(lists.par_chunks(group))
                .map(|(ix, ls)| {
                    let k = ix[0] / group;
                    let m_in = ls.get(1).map_or(&[][..], |l| &l[..]);
                    (k, weigh(chunk[k], &ls[0], m_in))
                })
                .collect();
            for (k, w) in weighed {
                slots[k] = Some(w);
            }
            Ok(())
        })?;
    }
    let decided: Vec<(Decision, Option<Segment>)> = decided
        .into_iter()
        .collect::<Option<_>>()
        .ok_or_else(|| EngineError::Gpu("the engine left a member list out".into()))?;
    // One decision per moved segment on top of the unclear ones: room taken once (a
    // decision is 720 bytes; growing by doubling copied and took fresh pages
    // again at each step).
    out.reserve(all.len());
    for (&i, &d) in all.iter().zip(&of) {
        let (dec, seg) = &decided[d];
        match (dec.verdict, seg) {
            (Verdict::Moved, Some(seg)) => {
                fitted.segments[i] = *seg;
                fitted.how[i] = match dec.estimate {
                    Some(Estimate::Corner | Estimate::FaceEnd | Estimate::Colour) => How::Corner,
                    _ => How::Ridge,
                };
            }
            (Verdict::TooFewMembers, _) => {
                fitted.segments[i] = input[i];
                fitted.how[i] = How::Unclear;
            }
            _ => {
                fitted.segments[i] = input[i];
                fitted.how[i] = How::Kept;
            }
        }
        out.push(Decision {
            segment: i,
            ..dec.clone()
        });
    }
    out.sort_by_key(|d| d.segment);
    Ok(out)
}

/// What the model is near the lines, from the decisions (the report's
/// `refine.diagnosis`): the kind most segments show, in words, and the counts.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Diagnosis {
    /// `edges` (centres on the edges), `faces` (splats on the faces), `sunk` (flat splats
    /// below the faces, off the edges), `round` (round splats, no face to speak of, off
    /// the edges) or `sparse` (too few members).
    pub kind: String,
    /// The kind in words, with how far the model's centres sit from the lines where they
    /// are off the edges.
    pub text: String,
    /// Segments of each kind.
    pub edges: usize,
    pub faces: usize,
    pub sunk: usize,
    pub round: usize,
    pub sparse: usize,
    /// Segments the rule moved, kept because the model knows the edge less well than the
    /// line does, and kept for lack of members.
    pub moved: usize,
    pub model_knows_less: usize,
    pub too_few_members: usize,
    /// Median distance from the lines of the centres' ridge, where the model is sunk or
    /// round.
    pub sunk_by: Option<f64>,
}

/// An estimate from the faces (corner, face end, colour change) whose floor is below
/// this many r says the splats lie on the faces.
pub const FACES_FLOOR: f64 = 0.15;

/// A ridge whose floor is below this many r says the centres lie on the edges.
pub const EDGES_FLOOR: f64 = 0.15;

/// Members off the edges and off the faces are `round` where fewer than this share of
/// them are flat (else `sunk`).
pub const ROUND_FLAT: f64 = 0.5;

/// The diagnosis of the model near the lines from the rule's decisions; `None` when there
/// are none. Each segment is named by its own evidence: centres on the edges where the
/// ridge is well known, splats on the faces where an estimate from the faces is,
/// otherwise round (mostly round members) or sunk (mostly flat ones, whose faces do not
/// meet at the line), or sparse (too few members).
pub fn diagnose(decisions: &[Decision], r: f64) -> Option<Diagnosis> {
    if decisions.is_empty() {
        return None;
    }
    let (mut edges, mut faces, mut sunk, mut round, mut sparse) = (0, 0, 0, 0, 0);
    let mut depth = Vec::new();
    for d in decisions {
        let on_faces = d.corner.as_ref().is_some_and(|c| c.floor < FACES_FLOOR * r)
            || d.face_end
                .as_ref()
                .is_some_and(|c| c.floor < FACES_FLOOR * r)
            || d.colour.as_ref().is_some_and(|c| c.floor < FACES_FLOOR * r);
        let ridge = d.ridge.as_ref().filter(|e| e.floor < EDGES_FLOOR * r);
        if d.verdict == Verdict::TooFewMembers {
            sparse += 1;
        } else if on_faces {
            faces += 1;
        } else if ridge.is_some() {
            edges += 1;
        } else {
            if d.flat_share.is_some_and(|f| f < ROUND_FLAT) {
                round += 1;
            } else {
                sunk += 1;
            }
            if let Some(e) = &d.ridge {
                depth.push(e.distance);
            }
        }
    }
    let count = |v: Verdict| decisions.iter().filter(|d| d.verdict == v).count();
    let sunk_by = (!depth.is_empty()).then(|| median(&mut depth));
    let most = [edges, faces, sunk, round, sparse]
        .into_iter()
        .max()
        .unwrap_or(0);
    let n = decisions.len();
    let off = |what: &str| match sunk_by {
        Some(x) => format!("{what}: the centres' ridge lies about {x:.3} from the lines"),
        None => what.to_string(),
    };
    let (kind, text) = if most == edges {
        ("edges", "centres on the edges".to_string())
    } else if most == faces {
        ("faces", "splats on the faces".to_string())
    } else if most == sunk {
        ("sunk", off("sunk below the faces"))
    } else if most == round {
        ("round", off("round splats off the edges"))
    } else {
        ("sparse", "too sparse".to_string())
    };
    Some(Diagnosis {
        kind: kind.to_string(),
        text: format!("{text} ({most} of {n} segments)"),
        edges,
        faces,
        sunk,
        round,
        sparse,
        moved: count(Verdict::Moved),
        model_knows_less: count(Verdict::ModelKnowsLess),
        too_few_members: count(Verdict::TooFewMembers),
        sunk_by,
    })
}

impl Decision {
    /// The decision in words, with its numbers (`refine --explain N`), distances also in
    /// units of `r`.
    pub fn explain(&self, r: f64) -> String {
        let u = |x: f64| format!("{x:.4} ({:.2} r)", x / r);
        let mut s = match self.verdict {
            Verdict::TooFewMembers => {
                return "stayed: too few members for any estimate of the edge".to_string()
            }
            Verdict::Moved => format!(
                "moved onto the {}: the line lay {} from it, more than {MOVE_MARGIN} x its \
                 uncertainty {}",
                self.estimate.map_or("estimate", Estimate::name),
                u(self.distance),
                u(self.sigma)
            ),
            Verdict::ModelKnowsLess => format!(
                "stayed: the line lies {} from the {}, within {MOVE_MARGIN} x its uncertainty \
                 {} (the model knows the edge less well than the line does)",
                u(self.distance),
                self.estimate.map_or("estimate", Estimate::name),
                u(self.sigma)
            ),
        };
        s += &format!("; {} members within r", self.members);
        if let Some(c) = &self.corner {
            s += &format!(
                "\n  corner: {} from the line, floor {} (faces' residuals {:.4}, {:.4}; \
                 {:.0} % of normals off both faces; faces {:.0} deg apart, {} and {} splats), \
                 statistical {}",
                u(c.distance),
                u(c.floor),
                c.residuals[0],
                c.residuals[1],
                100.0 * c.off_faces,
                c.angle_deg,
                c.counts[0],
                c.counts[1],
                u(c.statistical)
            );
        }
        if let Some(e) = &self.face_end {
            s += &format!(
                "\n  face end: {} from the line, floor {} (face's residual {:.4}; centres stop \
                 {:.4} along the face from the line, extent {:.4}; {:.0} % of normals off the \
                 faces; {} splats), statistical {} ({:.0} members per unit across)",
                u(e.distance),
                u(e.floor),
                e.residual,
                e.stop,
                e.extent,
                100.0 * e.off_faces,
                e.count,
                u(e.statistical),
                e.density
            );
        }
        if let Some(e) = &self.colour {
            s += &format!(
                "\n  colour change: {} from the line, floor {} (step {:.3} in RGB, {:.0} % of \
                 splats nearer the other side's colour, profile half width {:.4}, extent \
                 {:.4}; {} splats), statistical {}",
                u(e.distance),
                u(e.floor),
                e.step,
                100.0 * e.mixed,
                e.width,
                e.extent,
                e.count,
                u(e.statistical)
            );
        }
        if let Some(e) = &self.ridge {
            s += &format!(
                "\n  ridge: {} from the line, floor {} (mode moves {} with a kernel twice as \
                 wide; roundness {:.2}; {:.0} % of members with normals naming a surface), \
                 statistical {} (spread {} over {:.0} members)",
                u(e.distance),
                u(e.floor),
                u(e.wide),
                e.roundness,
                100.0 * e.face_share * e.face_agree,
                u(e.statistical),
                u(e.spread),
                e.weight
            );
        }
        s
    }
}

impl Estimate {
    /// The estimate's name in words.
    pub fn name(self) -> &'static str {
        match self {
            Estimate::Corner => "corner of two faces",
            Estimate::Ridge => "ridge of the centres",
            Estimate::FaceEnd => "end of a face's splats",
            Estimate::Colour => "change of the splats' colour",
        }
    }
}

group! {
    /// Step 4's parameters: where each line goes (`--fit`), the edge fit's, and which
    /// Gaussians may place a line (`--max-scale`).
    pub struct FitParams {
        /// Translate: fraction of the points nearest to the line whose mean offset moves it.
        translate_keep: f64 = 0.4, Check::Fraction;
        /// Step 4: `paper` (mean offset of the nearest translate-keep, the published step: to
        /// reproduce the paper, or to put the lines where the Gaussians are), `edge` (fit the
        /// edge: two faces' corner where the model has normals, else the dense ridge, iterated;
        /// to put the lines on the true edges) or `none`. Default: the profile's (`edge` for
        /// default, `paper` for reference).
        fit: Option<Fit> = None, Check::Choice(Fit::CHOICES);
        /// Edge fit: most iterations (one engine batch each).
        fit_iterations: u32 = 12, Check::Whole { lo: 0, hi: u32::MAX };
        /// Edge fit: largest turn of a line per iteration (degrees).
        fit_max_turn_deg: f64 = 3.0, Check::Positive;
        /// Edge fit: largest total move of an endpoint, in units of r.
        fit_max_move: f64 = 2.0, Check::Positive;
        /// Edge fit: final width of the ridge kernel, in units of r.
        fit_bandwidth: f64 = 0.25, Check::Positive;
        /// Edge fit: fewest points under the kernel (or per face family) for a move; 1 or
        /// more.
        fit_min_points: u32 = 8, Check::Whole { lo: 1, hi: u32::MAX };
        /// Edge fit: weight each Gaussian by its opacity (PLY `opacity`, after the sigmoid),
        /// so that faint floaters pull less; the fewest-points test still counts points. No
        /// effect where the model has no opacities or all are equal.
        fit_opacity_weight: bool = false, Check::Switch;
        /// Edge fit: keep a segment where it is unless its Gaussians explain the move (the
        /// move gate): a corner only when both faces are thin slabs of splats and the input
        /// line lies outside one of them; a ridge only when less than a third of it is face
        /// splats. Measured in one batch of members of the fitted lines. `false`: every
        /// fitted move stands.
        fit_gate: bool = true, Check::Switch;
        /// Leave out of the steps that place lines (the edge fit, its gate, the straightness
        /// test) every Gaussian whose largest standard deviation (`exp(max scale_i)`) exceeds
        /// this x r: a Gaussian wider than the cylinder cannot place a line within r. The
        /// steps that ask whether Gaussians are there (outliers, merges, crop, gaps) and the
        /// metrics see the whole model. Needs a 3DGS PLY with scales; 0: keep all.
        /// Default: the profile's (1 for default, 0 for reference).
        max_scale: Option<f64> = None, Check::NonNegative;
    }
}

impl FitParams {
    /// `--max-scale` in effect: the user's, else the profile's (1 for default, 0 for
    /// reference, which keeps every Gaussian as the authors' code does).
    pub fn max_scale_for(&self, profile: Profile) -> f64 {
        self.max_scale.unwrap_or(match profile {
            Profile::Default => 1.0,
            Profile::Reference => 0.0,
        })
    }
}

/// What step 4 did (the report's `refine` section).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FitNotes {
    pub fit: Fit,
    pub shifts: Option<Shifts>,
    /// Engine batches of the edge fit (0 for the other fits).
    pub fit_iterations: u32,
    /// Edge fit: segments placed on two faces' corner, on a ridge, and left (unclear).
    pub fit_corner: usize,
    pub fit_ridge: usize,
    pub fit_unclear: usize,
    /// Edge fit: segments the move gate kept at their input (`--fit-gate`): an estimate
    /// existed, but the Gaussians did not explain the move.
    #[serde(default)]
    pub fit_kept: usize,
    /// Edge fit: each weighed segment's decision with its numbers (`--fit-gate`).
    #[serde(default)]
    pub fit_decisions: Vec<Decision>,
    /// Edge fit: what the model is near the lines, from the decisions (`--fit-gate`).
    #[serde(default)]
    pub diagnosis: Option<Diagnosis>,
}

impl Default for FitNotes {
    fn default() -> Self {
        FitNotes {
            fit: Fit::None,
            shifts: None,
            fit_iterations: 0,
            fit_corner: 0,
            fit_ridge: 0,
            fit_unclear: 0,
            fit_kept: 0,
            fit_decisions: Vec::new(),
            diagnosis: None,
        }
    }
}

/// Step 4, the stage `translate`: each line moved as `--fit` says (the published
/// translation, the edge fit with its gate, or no move), and how far they moved.
pub struct Place;

impl Step for Place {
    fn name(&self) -> &'static str {
        "translate"
    }

    fn run(&self, pass: &mut Pass) -> Result<(), EngineError> {
        let s = pass.settings;
        let (r, p, how) = (s.radius(), &s.params().fit, s.fixes().fit);
        let (place, attrs, segments) = (pass.place, pass.attrs, &pass.lines.segments);
        let notes = &mut pass.notes.fit;
        notes.fit = how;
        let moved = match how {
            Fit::Paper => super::translate::translate(place, segments, r, p.translate_keep)?,
            Fit::None => segments.clone(),
            Fit::Edge => {
                let mut f = fit_edges(place, segments, attrs, r, p)?;
                if p.fit_gate {
                    notes.fit_decisions = decide(place, segments, &mut f, attrs, r, p)?;
                    notes.diagnosis = diagnose(&notes.fit_decisions, r);
                }
                notes.fit_iterations = f.iterations;
                let count = |h| f.how.iter().filter(|&&x| x == h).count();
                notes.fit_corner = count(How::Corner);
                notes.fit_ridge = count(How::Ridge);
                notes.fit_unclear = count(How::Unclear);
                notes.fit_kept = count(How::Kept);
                f.segments
            }
        };
        notes.shifts = Shifts::between(segments, &moved, r);
        if let Some(s) = &notes.shifts {
            // The edge fit moves lines onto edges on purpose; the published step follows
            // the Gaussians wherever they sit.
            if s.systematic && how == Fit::Paper {
                pass.notes.warnings.push(format!(
                    "--fit paper: the median segment moved {:.2} r (90th percentile {:.2} r): \
                     the Gaussians' ridge sits off the lines, so this step trades the lines' \
                     own position for closeness to the Gaussians (and the paper's score); \
                     compare --fit none and --fit edge",
                    s.median_r, s.p90_r
                ));
            }
        }
        pass.lines.segments = moved;
        Ok(())
    }
}
