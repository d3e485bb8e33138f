//! Step 4 beyond the paper: where the line goes. `--fit paper` is the published translation
//! (mean offset of the nearest 40%, [`super::translate`]); `--fit none` leaves the lines;
//! `--fit edge` estimates the edge itself from the Gaussians in the cylinder and moves the
//! line onto it, iterated to convergence with one engine batch per iteration for all
//! segments still moving.
//!
//! One iteration, per segment (in the frame of its current line: axial `t`, 2D offset `q`
//! in the plane perpendicular to `d`):
//! - **Two faces** (only where the Gaussians carry normals, a flat Gaussian's shortest
//!   axis): the normals that lie across the line fall into two families 20° or more apart;
//!   each family's plane is fitted robustly (median offset along its mean normal) in each
//!   half of the segment, and the two planes' intersection in each half gives the line.
//! - **Ridge** otherwise: a line `q = a + b (t - t̄)` fitted by iteratively reweighted least
//!   squares with a Gaussian kernel on the residual whose width shrinks from `r/2` to
//!   `fit_bandwidth x r` — mode seeking, so a shell of face Gaussians around a dense ridge
//!   does not pull the line off it the way a mean does. The line turns only where its
//!   points are elongated along it ([`MIN_ELONGATION`]); a short one keeps its direction.
//! - **Neither clear** (too few points carry the kernel's weight): no move.
//!
//! Each step moves a line by at most `0.5 r` and turns it by at most `fit_max_turn_deg`
//! (and so that neither end moves more than `r/4` by the turn);
//! its total move stays within `fit_max_move x r` (default 2) of where it started, so a
//! line is never carried over to another edge.

use crate::engine::{Engine, EngineError, FitAnswer, FitAsk, Member, Query};
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

/// What the fit did to one segment.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum How {
    /// Moved onto two faces' intersection.
    Corner,
    /// Moved onto a dense ridge of centers.
    Ridge,
    /// Too few points for any estimate: not moved.
    Unclear,
    /// An estimate existed, but the move gate found that the Gaussians do not explain it
    /// better than the input line: not moved.
    Kept,
}

pub struct FitResult {
    pub segments: Vec<Segment>,
    /// How each segment's last move was decided.
    pub how: Vec<How>,
    /// Engine batches used.
    pub iterations: u32,
}

/// Two perpendicular unit vectors across `d`.
pub(crate) fn basis(d: DVec3) -> (DVec3, DVec3) {
    let a = if d.x.abs() < 0.9 { DVec3::X } else { DVec3::Y };
    let e1 = (a - d * a.dot(d)).normalize();
    (e1, d.cross(e1))
}

/// The line model `q(t) = a + b (t - t0)` in a segment's cross-section frame
/// ([`basis`] of its direction; `t` from `P1`).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LineFit {
    pub t0: f64,
    pub a: DVec2,
    pub b: DVec2,
}

/// The ridge turns only where its points' weighted axial spread (variance of `t`) is at
/// least this many times their cross spread (variance of `q` about the line).
///
/// Refitting in the frame of the line just fitted moves a slope of `q` on `t` by about
/// `var(q) / var(t)` times the turn before it: where the cloud is short against its
/// width (a segment shorter than about `r`), each iteration would amplify the last one's
/// rounding (measured: doubling per iteration on the Line3D++ test scene, 1e-8 r → 2e-5 r
/// in 12 iterations) and the line would wander by the turn limit without settling.
/// With the ratio at 4 or more a step passes on at most a quarter of an earlier
/// difference; below it the line keeps its direction and only moves onto the ridge.
pub const MIN_ELONGATION: f64 = 4.0;

/// Weighted least squares of `q` on `t`; `None` without weight. No slope (`b = 0`)
/// without axial spread, or with less than [`MIN_ELONGATION`] times the cross spread.
fn weighted_line(pts: &[(f64, DVec2)], w: &[f64]) -> Option<LineFit> {
    let sw: f64 = w.iter().sum();
    if sw <= 0.0 {
        return None;
    }
    let t0 = pts.iter().zip(w).map(|(p, w)| p.0 * w).sum::<f64>() / sw;
    let a = pts.iter().zip(w).map(|(p, w)| p.1 * *w).sum::<DVec2>() / sw;
    let mut stt = 0.0;
    let mut sqq = 0.0;
    let mut stq = DVec2::ZERO;
    for (p, w) in pts.iter().zip(w) {
        let dt = p.0 - t0;
        stt += w * dt * dt;
        sqq += w * (p.1 - a).length_squared();
        stq += (p.1 - a) * (w * dt);
    }
    let b = if stt > 1e-300 && stt >= MIN_ELONGATION * sqq {
        stq / stt
    } else {
        DVec2::ZERO
    };
    Some(LineFit { t0, a, b })
}

/// The ridge: first its position by mean shift of the cross-section offsets (a Gaussian
/// kernel whose width shrinks to `fit_bandwidth x r`), then its direction by a
/// kernel-weighted fit of offset against axial position around that position. Returns the
/// fit and the number of points under the final kernel (kernel weights summed, without the
/// per-point weights `pw`, so that a weighting never turns "too few points" into enough).
/// Each point counts with its weight `pw` (1, or its opacity) times the kernel's. Position
/// first: a line fitted freely through two parallel ridges can settle crossing them.
pub(crate) fn ridge(
    pts: &[(f64, DVec2)],
    pw: &[f64],
    r: f64,
    p: &Params,
) -> Option<(LineFit, f64)> {
    if pts.is_empty() {
        return None;
    }
    let h_min = p.fit_bandwidth * r;
    // Starting at half the radius keeps the line on its own ridge when another lies
    // within r; a ridge that is the only one in the cylinder is reached from there, as
    // the kernel's mean is a mean of points.
    let mut h = (0.5 * r).max(h_min);
    let mut c = DVec2::ZERO;
    let mut w = vec![0.0; pts.len()];
    for _ in 0..100 {
        for ((wi, (_, q)), pw) in w.iter_mut().zip(pts).zip(pw) {
            *wi = pw * (-(*q - c).length_squared() / (2.0 * h * h)).exp();
        }
        let sw: f64 = w.iter().sum();
        if sw <= 0.0 {
            return None;
        }
        let next = pts.iter().zip(&w).map(|(p, w)| p.1 * *w).sum::<DVec2>() / sw;
        let moved = (next - c).length();
        c = next;
        if h > h_min {
            h = (h * 0.8).max(h_min);
        } else if moved < 1e-5 * r {
            break;
        }
    }
    let mut fit = LineFit {
        t0: 0.0,
        a: c,
        b: DVec2::ZERO,
    };
    let mut weight = 0.0;
    for ((wi, (_, q)), pw) in w.iter_mut().zip(pts).zip(pw) {
        let k = (-(*q - c).length_squared() / (2.0 * h_min * h_min)).exp();
        weight += k;
        *wi = pw * k;
    }
    if let Some(f) = weighted_line(pts, &w) {
        fit = f;
    }
    Some((fit, weight))
}

/// Median of `v` (sorts it).
fn median(v: &mut [f64]) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Weighted median of `(value, weight)` pairs: the smallest value whose cumulative weight
/// reaches half the total; the plain [`median`] when all weights are equal.
fn weighted_median(v: &mut [(f64, f64)]) -> f64 {
    if v.iter().all(|x| x.1 == v[0].1) {
        let mut vals: Vec<f64> = v.iter().map(|x| x.0).collect();
        return median(&mut vals);
    }
    v.sort_by(|a, b| a.0.total_cmp(&b.0));
    let half = 0.5 * v.iter().map(|x| x.1).sum::<f64>();
    let mut acc = 0.0;
    for &(x, w) in v.iter() {
        acc += w;
        if acc >= half {
            return x;
        }
    }
    v[v.len() - 1].0
}

/// Two surface-normal families across the line: their mean normals (2D, unit) and members.
/// Normals are sign-free, so they are clustered by doubled angle (2-means).
/// Each normal counts with its weight `pw` in the families' means.
fn families(normals: &[DVec2], pw: &[f64], min_points: usize) -> Option<[(DVec2, Vec<usize>); 2]> {
    let dbl: Vec<DVec2> = normals
        .iter()
        .map(|n| DVec2::new(n.x * n.x - n.y * n.y, 2.0 * n.x * n.y))
        .collect();
    if dbl.len() < 2 * min_points {
        return None;
    }
    // Seeds: the first normal and the one farthest from it in doubled angle.
    let c0 = dbl[0];
    let far = dbl
        .iter()
        .copied()
        .max_by(|a, b| (*a - c0).length().total_cmp(&(*b - c0).length()))?;
    let mut c = [c0, far];
    let mut label = vec![0usize; dbl.len()];
    for _ in 0..20 {
        for (l, u) in label.iter_mut().zip(&dbl) {
            *l = usize::from((*u - c[1]).length_squared() < (*u - c[0]).length_squared());
        }
        let mut s = [DVec2::ZERO; 2];
        for ((l, u), w) in label.iter().zip(&dbl).zip(pw) {
            s[*l] += *u * *w;
        }
        let next = [s[0].normalize_or_zero(), s[1].normalize_or_zero()];
        if next == c {
            break;
        }
        c = next;
    }
    let out: [(DVec2, Vec<usize>); 2] = [0, 1].map(|k| {
        // Back from doubled angle to a normal direction.
        let ang = 0.5 * c[k].y.atan2(c[k].x);
        let members = (0..dbl.len()).filter(|&i| label[i] == k).collect();
        (DVec2::new(ang.cos(), ang.sin()), members)
    });
    // 20° or more apart: cos(2 x 20°) in doubled angle.
    let apart = c[0].dot(c[1]) < (40f64).to_radians().cos();
    (apart && out.iter().all(|f| f.1.len() >= min_points)).then_some(out)
}

/// The corner of two face families in the points `sel` (indices into `pts`).
fn corner(
    pts: &[(f64, DVec2)],
    pw: &[f64],
    fam: &[(DVec2, Vec<usize>); 2],
    sel: impl Fn(f64) -> bool,
    min_points: usize,
) -> Option<DVec2> {
    let mut c = [0.0; 2];
    for (ck, (n, members)) in c.iter_mut().zip(fam) {
        let n = *n;
        let mut off: Vec<(f64, f64)> = members
            .iter()
            .filter(|&&i| sel(pts[i].0))
            .map(|&i| (n.dot(pts[i].1), pw[i]))
            .collect();
        if off.len() < min_points {
            return None;
        }
        *ck = weighted_median(&mut off);
    }
    let (n1, n2) = (fam[0].0, fam[1].0);
    let det = n1.x * n2.y - n1.y * n2.x;
    if det.abs() < 1e-9 {
        return None;
    }
    Some(DVec2::new(
        (c[0] * n2.y - c[1] * n1.y) / det,
        (n1.x * c[1] - n2.x * c[0]) / det,
    ))
}

/// The corner line of two face families, from the corners of the two halves (a single
/// corner, no turn, when a half has too few points).
fn two_planes(
    pts: &[(f64, DVec2)],
    pw: &[f64],
    normals: &[DVec2],
    keep: &[usize],
    len: f64,
    min_points: usize,
) -> Option<LineFit> {
    let sub_w: Vec<f64> = keep.iter().map(|&i| pw[i]).collect();
    let fam = families(normals, &sub_w, min_points)?;
    // Family members index `normals`, which are the points `keep`.
    let sub: Vec<(f64, DVec2)> = keep.iter().map(|&i| pts[i]).collect();
    let all = corner(&sub, &sub_w, &fam, |_| true, min_points)?;
    let half = 0.5 * len;
    match (
        corner(&sub, &sub_w, &fam, |t| t < half, min_points),
        corner(&sub, &sub_w, &fam, |t| t >= half, min_points),
    ) {
        (Some(c1), Some(c2)) => Some(LineFit {
            t0: half,
            a: 0.5 * (c1 + c2),
            b: (c2 - c1) / half,
        }),
        _ => Some(LineFit {
            t0: half,
            a: all,
            b: DVec2::ZERO,
        }),
    }
}

/// [`step`] of every query's segment (`q.seg`, radius `q.r`) from its members: the
/// default [`Engine::fit_lines`], and the host's answer wherever an engine has none. The
/// segments are fitted in parallel; each step depends only on its own members, so the
/// answers are the same for every thread count.
pub fn steps(queries: &[Query], members: &[Vec<Member>], ask: &FitAsk<'_>) -> Vec<FitAnswer> {
    use rayon::prelude::*;
    queries
        .par_iter()
        .zip(members)
        .with_min_len(4)
        .map(|(q, m)| step(&q.seg, m, ask.attrs, q.r, ask.params))
        .collect()
}

/// The members' axial positions and cross-section offsets in the frame `(e1, e2)`, and
/// their weights (opacities with `--fit-opacity-weight`, else 1).
fn cross_section(
    members: &[Member],
    (e1, e2): (DVec3, DVec3),
    attrs: &Attributes,
    p: &Params,
) -> (Vec<(f64, DVec2)>, Vec<f64>) {
    let pts = members
        .iter()
        .map(|m| (m.t, DVec2::new(m.offset.dot(e1), m.offset.dot(e2))))
        .collect();
    let pw = if p.fit_opacity_weight {
        members.iter().map(|m| attrs.weight(m.id)).collect()
    } else {
        vec![1.0; members.len()]
    };
    (pts, pw)
}

/// One segment's next position from its members, or `None` (stay).
fn step(
    s: &Segment,
    members: &[Member],
    attrs: &Attributes,
    r: f64,
    p: &Params,
) -> (Option<LineFit>, How) {
    let d = s.dir();
    let (e1, e2) = basis(d);
    let (pts, pw) = cross_section(members, (e1, e2), attrs, p);
    let min_points = p.fit_min_points as usize;
    if let Some(ns) = &attrs.normals {
        // Normals across the line (a face through the edge): |n·d| < sin 30°; a Gaussian
        // with no normal (zero) is left out.
        let mut keep = Vec::new();
        let mut n2 = Vec::new();
        for (i, m) in members.iter().enumerate() {
            let n = crate::geom::p64(ns[m.id as usize]);
            let across = DVec2::new(n.dot(e1), n.dot(e2));
            if across.length() > 0.866 {
                keep.push(i);
                n2.push(across.normalize());
            }
        }
        if let Some(f) = two_planes(&pts, &pw, &n2, &keep, s.length(), min_points) {
            if f.a.length() <= r {
                return (Some(f), How::Corner);
            }
        }
    }
    match ridge(&pts, &pw, r, p) {
        Some((f, weight)) if weight >= min_points as f64 => (Some(f), How::Ridge),
        _ => (None, How::Unclear),
    }
}

/// Applies `f` to `s` with the per-step bounds; returns the new segment and how far it moved
/// (largest endpoint move).
fn apply(s: &Segment, f: &LineFit, origin: &Segment, r: f64, p: &Params) -> (Segment, f64) {
    let d = s.dir();
    let (e1, e2) = basis(d);
    let lift = |v: DVec2| e1 * v.x + e2 * v.y;
    let l = s.length();
    // A turn moves each end by at most r/4 per step, and by at most fit_max_turn_deg.
    let max_slope = p.fit_max_turn_deg.to_radians().tan().min(0.5 * r / l);
    let mut b = f.b;
    if b.length() > max_slope {
        b *= max_slope / b.length();
    }
    let mut a = f.a + b * (0.5 * l - f.t0); // offset at the midpoint
    let step_max = 0.5 * r;
    if a.length() > step_max {
        a *= step_max / a.length();
    }
    let m1 = lift(a - b * (0.5 * l));
    let m2 = lift(a + b * (0.5 * l));
    let mut out = Segment::new(s.p1 + m1, s.p2 + m2);
    // Stay within fit_max_move x r of the start: scale the total move back.
    let limit = p.fit_max_move * r;
    let total = (out.p1 - origin.p1)
        .length()
        .max((out.p2 - origin.p2).length());
    if total > limit {
        let k = limit / total;
        out = Segment::new(
            origin.p1 + (out.p1 - origin.p1) * k,
            origin.p2 + (out.p2 - origin.p2) * k,
        );
    }
    let moved = (out.p1 - s.p1).length().max((out.p2 - s.p2).length());
    (out, moved)
}

/// `--fit edge`: every segment moved onto the edge its Gaussians describe.
pub fn fit_edges(
    engine: &dyn Engine,
    segments: &[Segment],
    attrs: &Attributes,
    r: f64,
    p: &Params,
) -> Result<FitResult, EngineError> {
    let mut cur = segments.to_vec();
    let mut how = vec![How::Unclear; cur.len()];
    let mut active: Vec<usize> = (0..cur.len()).filter(|&i| cur[i].is_valid()).collect();
    let mut iterations = 0;
    while !active.is_empty() && iterations < p.fit_iterations {
        iterations += 1;
        // Exact copies (the same segment now and at the start) fit alike: each distinct
        // one is asked and fitted once and its result given to its copies.
        let mut seen: std::collections::HashMap<[u64; 12], usize> = Default::default();
        let mut uniq: Vec<usize> = Vec::new();
        let of: Vec<usize> = active
            .iter()
            .map(|&i| {
                let (a, b) = (cur[i], segments[i]);
                let key = [a.p1, a.p2, b.p1, b.p2]
                    .map(|v| v.to_array().map(f64::to_bits))
                    .concat();
                *seen
                    .entry(key.try_into().expect("12 words"))
                    .or_insert_with(|| {
                        uniq.push(i);
                        uniq.len() - 1
                    })
            })
            .collect();
        let queries: Vec<Query> = uniq.iter().map(|&i| Query::new(cur[i], r)).collect();
        // The one threshold taken from an answer here: whether the segment moved more
        // than 1e-3 r (it then stays active).
        let near = |j: usize, f: &LineFit| {
            let i = uniq[j];
            let (_, moved) = apply(&cur[i], f, &segments[i], r, p);
            (moved - 1e-3 * r).abs() <= 1e-5 * r
        };
        let ask = FitAsk {
            attrs,
            params: p,
            sensitive: Some(&near),
        };
        let steps = engine.fit_lines(&queries, &ask)?;
        let fitted: Vec<(Option<(Segment, f64)>, How)> = uniq
            .iter()
            .zip(&steps)
            .map(|(&i, &(f, h))| (f.map(|f| apply(&cur[i], &f, &segments[i], r, p)), h))
            .collect();
        drop(steps);
        let mut next = Vec::with_capacity(active.len());
        for (&i, &d) in active.iter().zip(&of) {
            let (res, h) = fitted[d];
            // A segment that has moved keeps the model of its last move: a later step
            // that found too few points does not undo what placed it.
            let has_moved = cur[i] != segments[i];
            match res {
                Some((s, moved)) => {
                    if moved > 0.0 || !has_moved {
                        how[i] = h;
                    }
                    cur[i] = s;
                    if moved > 1e-3 * r {
                        next.push(i);
                    }
                }
                None if !has_moved => how[i] = h,
                None => {}
            }
        }
        active = next;
    }
    Ok(FitResult {
        segments: cur,
        how,
        iterations,
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
    let kernel = |c: DVec2, p: &(f64, DVec2), w: f64| {
        w * (-(p.1 - c).length_squared() / (2.0 * h * h)).exp()
    };
    let mut c = DVec2::ZERO;
    let mut sw = 0.0;
    for _ in 0..50 {
        let mut s = DVec2::ZERO;
        sw = 0.0;
        for (p, w) in pts.iter().zip(pw) {
            let k = kernel(c, p, *w);
            s += p.1 * k;
            sw += k;
        }
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
    let faces: f64 = pts
        .iter()
        .zip(pw)
        .zip(flat)
        .filter(|(_, f)| **f)
        .map(|((p, w), _)| kernel(c, p, *w))
        .sum();
    sw > 0.0 && faces / sw < GATE_FACE_SHARE
}

/// The move gate (`--fit-gate`): each segment the edge fit moved (`fitted`, from `input`)
/// keeps its move only where the Gaussians within r of its new line explain it (a corner
/// by [`gate_corner`], a ridge by [`gate_ridge`]); the others go back to their input and
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
    for (&i, &stand) in moved.iter().zip(&stands) {
        if !stand {
            fitted.segments[i] = input[i];
            fitted.how[i] = How::Kept;
            undone += 1;
        }
    }
    Ok(undone)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_doubled_angle_keeps_the_families_sign_free() {
        // Normals of two perpendicular faces, half of them flipped.
        let mut n = Vec::new();
        for i in 0..20 {
            let s = if i % 2 == 0 { 1.0 } else { -1.0 };
            n.push(DVec2::new(s, 0.0));
            n.push(DVec2::new(0.0, s));
        }
        let f = families(&n, &[1.0; 40], 5).unwrap();
        assert_eq!(f[0].1.len(), 20);
        assert_eq!(f[1].1.len(), 20);
        assert!(f[0].0.dot(f[1].0).abs() < 1e-9);
        // one family only: no corner
        assert!(families(
            &n.iter().step_by(2).copied().collect::<Vec<_>>(),
            &[1.0; 20],
            5
        )
        .is_none());
    }
}
