//! The edge fit's mathematics (`--fit edge`, docs/method.md#step-4-translate): one step of
//! a segment from the points of its cylinder, the per-step bounds, and the per-segment
//! iteration state. Plain data in, plain data out: the engines run it over their own
//! member lists (the CPU engine gathers each neighbourhood once and iterates in cache,
//! `crate::engine::fit`), and the refinement's step only chooses the parameters.
//!
//! One step, per segment (in the frame of its current line: axial `t`, 2D offset `q`
//! in the plane perpendicular to `d`):
//! - **Two faces** (only where the Gaussians carry normals, a flat Gaussian's shortest
//!   axis): the normals that lie across the line fall into two families 20° or more apart;
//!   each family's plane is fitted robustly (median offset along its mean normal) in each
//!   half of the segment, and the two planes' intersection in each half gives the line.
//! - **Ridge** otherwise: a line `q = a + b (t - t̄)` fitted by iteratively reweighted least
//!   squares with a Gaussian kernel on the residual whose width shrinks from `r/2` to
//!   `bandwidth x r` — mode seeking, so a shell of face Gaussians around a dense ridge
//!   does not pull the line off it the way a mean does (after a ridge step taken whole,
//!   the next starts at the final width: [`ridge_start`]). The line turns only where its
//!   points are elongated along it ([`MIN_ELONGATION`]); a short one keeps its direction.
//! - **Neither clear** (too few points carry the kernel's weight): no move.
//!
//! Each step moves a line by at most `0.5 r` and turns it by at most `max_turn_deg` (and
//! so that neither end moves more than `r/4` by the turn); its total move stays within
//! `max_move x r` of where it started ([`apply`]), so a line is never carried over to
//! another edge.

use super::kernel::Columns;
use super::Segment;
use glam::{DVec2, DVec3};

/// One member of `X(s, r)`, for steps that need per-point data (the edge fit).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Member {
    /// Index of the point in the working set (the order the engine was built from).
    pub id: u32,
    /// Axial position `t1 = (p-P1)·d`.
    pub t: f64,
    /// Perpendicular offset `v = (p-P1) - t1 d`.
    pub offset: DVec3,
}

/// The fit's parameters, as plain numbers (the refinement's `--fit-*` options).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitSpec {
    /// Most steps per segment.
    pub iterations: u32,
    /// Most turn per step, in degrees.
    pub max_turn_deg: f64,
    /// Most total move of an end from its start, in units of r.
    pub max_move: f64,
    /// Final kernel width of the ridge, in units of r.
    pub bandwidth: f64,
    /// Fewest points (kernel weight) for a ridge or a face family.
    pub min_points: u32,
    /// Each point weighted by its opacity ([`FitPoints::opacity`]).
    pub opacity_weight: bool,
}

/// Per-point attributes of the working set (index = working-set id) that the fit reads,
/// where the file has them.
#[derive(Clone, Copy, Debug, Default)]
pub struct FitPoints<'a> {
    /// Unit surface normal of each Gaussian (its shortest axis); zero where it has none.
    pub normals: Option<&'a [[f32; 3]]>,
    /// Opacity of each Gaussian in `[0, 1]`: the per-point weight with
    /// [`FitSpec::opacity_weight`].
    pub opacity: Option<&'a [f32]>,
}

impl FitPoints<'_> {
    /// The fit's weight of working-set point `id`: its opacity where there are
    /// opacities, else 1.
    pub fn weight(&self, id: u32) -> f64 {
        self.opacity.map_or(1.0, |o| f64::from(o[id as usize]))
    }

    /// The fit's weight of point `id`: [`FitPoints::weight`] with
    /// [`FitSpec::opacity_weight`], else 1.
    #[inline]
    pub fn weight_if(&self, opacity_weight: bool, id: u32) -> f64 {
        if opacity_weight {
            self.weight(id)
        } else {
            1.0
        }
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

/// The fit of a set of segments.
#[derive(Clone, Debug, PartialEq)]
pub struct FitResult {
    pub segments: Vec<Segment>,
    /// How each segment's last move was decided.
    pub how: Vec<How>,
    /// Steps of the segment that took the most (the engine batches of a fit that asks
    /// once per iteration).
    pub iterations: u32,
    /// Steps each segment took (cylinder queries answered for it).
    pub steps: Vec<u32>,
}

/// Two perpendicular unit vectors across `d`.
pub fn basis(d: DVec3) -> (DVec3, DVec3) {
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

/// Weighted least squares of `q` on `t`, each point weighted `pw x k`; `None` without
/// weight. No slope (`b = 0`) without axial spread, or with less than [`MIN_ELONGATION`]
/// times the cross spread. Also returns the kernel values `k` summed (in point order,
/// as `Sum` adds them), which the first pass adds alongside its own sums.
fn weighted_line(t: &[f64], cols: &Columns) -> (Option<LineFit>, f64) {
    let n = t.len();
    let (qx, qy) = (&cols.x[..n], &cols.y[..n]);
    let (pw, k) = (&cols.w[..n], &cols.k[..n]);
    let w = |i: usize| pw[i] * k[i];
    let q = |i: usize| DVec2::new(qx[i], qy[i]);
    // The three sums in one pass, each in point order as three passes would add them.
    // (Starting values as `Sum` starts: -0.0 for f64, zero for glam's vectors.)
    let (mut sw, mut st, mut sq, mut sk) = (-0.0, -0.0, DVec2::ZERO, -0.0);
    for (i, &ti) in t.iter().enumerate() {
        let w = w(i);
        sw += w;
        st += ti * w;
        sq += q(i) * w;
        sk += k[i];
    }
    if sw <= 0.0 {
        return (None, sk);
    }
    let t0 = st / sw;
    let a = sq / sw;
    let mut stt = 0.0;
    let mut sqq = 0.0;
    let mut stq = DVec2::ZERO;
    for (i, &ti) in t.iter().enumerate() {
        let w = w(i);
        let dt = ti - t0;
        stt += w * dt * dt;
        sqq += w * (q(i) - a).length_squared();
        stq += (q(i) - a) * (w * dt);
    }
    let b = if stt > 1e-300 && stt >= MIN_ELONGATION * sqq {
        stq / stt
    } else {
        DVec2::ZERO
    };
    (Some(LineFit { t0, a, b }), sk)
}

/// The ridge's mean shift narrows its kernel by this factor a round, from its first width
/// ([`ridge_start`]) to `bandwidth x r`: from `r/2` to `r/4` (the `default` width) in
/// two rounds.
///
/// The narrowing keeps a line on the ridge that its wide kernel found first, where a
/// second one lies within r. Halving in one round lost edges on the mesh-sampled NEF scene
/// (F@0.005 0.619 -> 0.615, F@0.02 0.869 -> 0.855); 0.7 and the earlier 0.8 (four rounds)
/// give the same scores on every scene of docs/accuracy.md.
pub const RIDGE_SHRINK: f64 = 0.7;

/// The ridge's mean shift stops, at its final width, once a round moves the position by
/// less than this many times r.
///
/// Each round at the final width leaves about 0.3 of the round before it (measured: the
/// ratio of successive moves has quartiles 0.28-0.34 on the benchmark scene), so what is
/// left is under half the last move, 5e-4 r: twenty times finer than the step's own settle
/// rule ([`SETTLED`]) and far below the ridge's statistical spread (its kernel width over
/// the square root of its ~100 points, 0.025 r). With [`RIDGE_SHRINK`], measured on the
/// benchmark scene at 10^6 x 10^4: 5.9 rounds a cold ridge and 1.4 a warm one, where 0.8
/// and 1e-5 r took 10.6 and 4.9, for the same scores.
pub const RIDGE_STOP: f64 = 1e-3;

/// The ridge: first its position by mean shift of the cross-section offsets (a Gaussian
/// kernel whose width shrinks to `bandwidth x r`), then its direction by a fit of offset
/// against axial position weighted by the mean shift's last round: the kernel at the
/// width `bandwidth x r` around the position before the last move (less than
/// [`RIDGE_STOP`] r from the position found, which is the weighted mean of those
/// weights). Returns the fit and the number of points under that kernel (kernel weights
/// summed, without the per-point weights `pw`, so that a weighting never turns "too few
/// points" into enough). Each point counts with its weight `pw` (1, or its opacity)
/// times the kernel's. Position first: a line fitted freely through two parallel ridges
/// can settle crossing them.
///
/// `warm`: the line is already on its ridge (the step before it was this fit's ridge,
/// taken whole, [`Track::warm`]), and the mean shift starts at the final width
/// ([`ridge_start`]).
pub fn ridge(
    pts: &[(f64, DVec2)],
    pw: &[f64],
    r: f64,
    bandwidth: f64,
    warm: bool,
) -> Option<(LineFit, f64)> {
    let t: Vec<f64> = pts.iter().map(|p| p.0).collect();
    let mut cols = Columns::new(pts.iter().map(|p| p.1), pw);
    ridge_in(&mut cols, &t, r, bandwidth, warm)
}

/// [`ridge`] of the points at axial positions `t` whose offsets and weights `cols`
/// holds (one per position, sealed: [`Columns::seal`]).
pub fn ridge_in(
    cols: &mut Columns,
    t: &[f64],
    r: f64,
    bandwidth: f64,
    warm: bool,
) -> Option<(LineFit, f64)> {
    debug_assert_eq!(cols.n, t.len());
    if t.is_empty() {
        return None;
    }
    let h_min = bandwidth * r;
    let mut h = ridge_start(r, bandwidth, warm);
    let mut c = DVec2::ZERO;
    for _ in 0..100 {
        let (sw, sq) = cols.round(c, h);
        if sw <= 0.0 {
            return None;
        }
        let next = sq / sw;
        let moved = (next - c).length();
        c = next;
        if h > h_min {
            h = (h * RIDGE_SHRINK).max(h_min);
        } else if moved < RIDGE_STOP * r {
            break;
        }
    }
    let mut fit = LineFit {
        t0: 0.0,
        a: c,
        b: DVec2::ZERO,
    };
    // The last round's kernel, at the final width (the stop rule acts only there),
    // summed by the line's fit.
    let (line, weight) = weighted_line(t, cols);
    if let Some(f) = line {
        fit = f;
    }
    Some((fit, weight))
}

/// The ridge's first kernel width: `r/2`, or the final width `bandwidth x r` where the
/// line is already on its ridge (`warm`).
///
/// Starting at half the radius keeps the line on its own ridge when another lies within
/// r; a ridge that is the only one in the cylinder is reached from there, as the kernel's
/// mean is a mean of points. A line that the previous step put on its ridge (the step's
/// whole answer, no bound cut it) is at that mode already: only the cylinder's members
/// changed with the line, so the mean shift starts at the final width (measured on the
/// benchmark scene at 10^6 x 10^4: 1.4 rounds a warm ridge, 5.9 a cold one).
pub fn ridge_start(r: f64, bandwidth: f64, warm: bool) -> f64 {
    let h_min = bandwidth * r;
    if warm {
        h_min
    } else {
        (0.5 * r).max(h_min)
    }
}

/// Median of `v` (sorts it).
pub fn median(v: &mut [f64]) -> f64 {
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

/// Two face families' mean normals (2D, unit) and their members.
pub type Families = [(DVec2, Vec<usize>); 2];

/// Two surface-normal families across the line: their mean normals (2D, unit) and members.
/// Normals are sign-free, so they are clustered by doubled angle (2-means).
/// Each normal counts with its weight `pw` in the families' means.
pub fn families(normals: &[DVec2], pw: &[f64], min_points: usize) -> Option<Families> {
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
    let out: Families = [0, 1].map(|k| {
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
    fam: &Families,
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
    t: &[f64],
    cols: &Columns,
    normals: &[DVec2],
    keep: &[usize],
    len: f64,
    min_points: usize,
) -> Option<LineFit> {
    let sub_w: Vec<f64> = keep.iter().map(|&i| cols.w[i]).collect();
    let fam = families(normals, &sub_w, min_points)?;
    // Family members index `normals`, which are the points `keep`.
    let sub: Vec<(f64, DVec2)> = keep
        .iter()
        .map(|&i| (t[i], DVec2::new(cols.x[i], cols.y[i])))
        .collect();
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

/// The members' axial positions and cross-section offsets in the frame `(e1, e2)`, and
/// their weights (opacities with [`FitSpec::opacity_weight`], else 1).
pub fn cross_section(
    members: &[Member],
    (e1, e2): (DVec3, DVec3),
    points: &FitPoints<'_>,
    opacity_weight: bool,
) -> (Vec<(f64, DVec2)>, Vec<f64>) {
    let pts = members
        .iter()
        .map(|m| (m.t, DVec2::new(m.offset.dot(e1), m.offset.dot(e2))))
        .collect();
    let pw = members
        .iter()
        .map(|m| points.weight_if(opacity_weight, m.id))
        .collect();
    (pts, pw)
}

/// One segment's next line from its members (those of `X(s, r)`, in working-set order),
/// or `None` (stay).
pub fn step(
    s: &Segment,
    members: &[Member],
    points: &FitPoints<'_>,
    r: f64,
    spec: &FitSpec,
    warm: bool,
) -> (Option<LineFit>, How) {
    let mut sec = Section::default();
    let frame = basis(s.dir());
    for m in members {
        sec.push(m.id, m.t, m.offset, frame, points, spec.opacity_weight);
    }
    step_section(s, &mut sec, points, r, spec, warm)
}

/// One step's cross-section: per member of `X(s, r)` (working-set order), its axial
/// position `t`, and in `cols` its offset in the frame ([`basis`]) of the segment's
/// direction and its weight (opacity with [`FitSpec::opacity_weight`], else 1), and its
/// working-set id. Columns, so that the ridge's mean shift reads them as they are.
#[derive(Clone, Debug, Default)]
pub struct Section {
    pub t: Vec<f64>,
    /// Offsets and weights (the ridge's columns, [`ridge_in`]); room kept step to step.
    pub cols: Columns,
    pub ids: Vec<u32>,
}

impl Section {
    /// Empty, keeping its room.
    pub fn clear(&mut self) {
        self.t.clear();
        self.cols.clear();
        self.ids.clear();
    }

    /// Member `id` at axial position `t` and perpendicular offset `offset`: the values
    /// of [`cross_section`].
    #[inline]
    pub fn push(
        &mut self,
        id: u32,
        t: f64,
        offset: DVec3,
        (e1, e2): (DVec3, DVec3),
        points: &FitPoints<'_>,
        opacity_weight: bool,
    ) {
        self.t.push(t);
        let q = DVec2::new(offset.dot(e1), offset.dot(e2));
        self.cols.push(q, points.weight_if(opacity_weight, id));
        self.ids.push(id);
    }
}

/// [`step`] from the cross-section `sec` of the members of `X(s, r)`.
pub fn step_section(
    s: &Segment,
    sec: &mut Section,
    points: &FitPoints<'_>,
    r: f64,
    spec: &FitSpec,
    warm: bool,
) -> (Option<LineFit>, How) {
    let (e1, e2) = basis(s.dir());
    sec.cols.seal(sec.t.len());
    let min_points = spec.min_points as usize;
    if let Some(ns) = points.normals {
        // Normals across the line (a face through the edge): |n·d| < sin 30°; a Gaussian
        // with no normal (zero) is left out.
        let mut keep = Vec::new();
        let mut n2 = Vec::new();
        for (i, &id) in sec.ids.iter().enumerate() {
            let n = super::p64(ns[id as usize]);
            let across = DVec2::new(n.dot(e1), n.dot(e2));
            if across.length() > 0.866 {
                keep.push(i);
                n2.push(across.normalize());
            }
        }
        if let Some(f) = two_planes(&sec.t, &sec.cols, &n2, &keep, s.length(), min_points) {
            if f.a.length() <= r {
                return (Some(f), How::Corner);
            }
        }
    }
    match ridge_in(&mut sec.cols, &sec.t, r, spec.bandwidth, warm) {
        Some((f, weight)) if weight >= min_points as f64 => (Some(f), How::Ridge),
        _ => (None, How::Unclear),
    }
}

/// A step's line applied with the bounds ([`apply`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Applied {
    /// The new segment.
    pub seg: Segment,
    /// How far it moved (largest endpoint move).
    pub moved: f64,
    /// Whether the line was taken whole (no bound cut it): the next step starts warm.
    pub whole: bool,
    /// Whether a decision taken here lies within rounding (1e-5 r, or 1e-5 of the turn
    /// limit) of its threshold: the settle rule ([`SETTLED`]) and each bound, which
    /// decides [`Applied::whole`].
    pub near: bool,
}

/// Applies `f` to `s` with the per-step bounds. Neither end of the result lies more
/// than `max_move x r` (up to rounding) from its end of `origin`.
pub fn apply(s: &Segment, f: &LineFit, origin: &Segment, r: f64, spec: &FitSpec) -> Applied {
    let near_r = |x: f64, limit: f64| (x - limit).abs() <= 1e-5 * r;
    let d = s.dir();
    let (e1, e2) = basis(d);
    let lift = |v: DVec2| e1 * v.x + e2 * v.y;
    let l = s.length();
    // A turn moves each end by at most r/4 per step, and by at most max_turn_deg.
    let max_slope = spec.max_turn_deg.to_radians().tan().min(0.5 * r / l);
    let mut b = f.b;
    let mut whole = b.length() <= max_slope;
    let mut near = (b.length() - max_slope).abs() <= 1e-5 * max_slope;
    if !whole {
        b *= max_slope / b.length();
    }
    let mut a = f.a + b * (0.5 * l - f.t0); // offset at the midpoint
    let step_max = 0.5 * r;
    near |= near_r(a.length(), step_max);
    if a.length() > step_max {
        a *= step_max / a.length();
        whole = false;
    }
    let m1 = lift(a - b * (0.5 * l));
    let m2 = lift(a + b * (0.5 * l));
    let mut out = Segment::new(s.p1 + m1, s.p2 + m2);
    // Stay within max_move x r of the start: scale the total move back.
    let limit = spec.max_move * r;
    let total = (out.p1 - origin.p1)
        .length()
        .max((out.p2 - origin.p2).length());
    near |= near_r(total, limit);
    if total > limit {
        whole = false;
        let k = limit / total;
        out = Segment::new(
            origin.p1 + (out.p1 - origin.p1) * k,
            origin.p2 + (out.p2 - origin.p2) * k,
        );
    }
    let moved = (out.p1 - s.p1).length().max((out.p2 - s.p2).length());
    near |= near_r(moved, SETTLED * r);
    Applied {
        seg: out,
        moved,
        whole,
        near,
    }
}

/// A segment keeps iterating while its step moved it by more than this many r.
///
/// The steps of a line on its ridge shrink geometrically (each about a third of the
/// one before: the direction fit's kernel, centred on the ridge's position, recovers
/// about two thirds of a remaining tilt), so a line that moved less than 1 % of r is
/// within about 0.5 % of r of where further steps would take it: a tenth of the
/// accuracy measured on any scene with a ground truth. Measured on the benchmark scene
/// at 10^6 x 10^4: 2.8 steps per segment instead of 4.9 at 0.1 %, and 22 segments
/// instead of 282 that flip between two lines (a member on the cylinder's surface
/// entering and leaving) until the step limit; the accuracy tables moved in their third
/// decimal at most.
pub const SETTLED: f64 = 1e-2;

/// Whether a step's line `f` for segment `s` (started at `origin`) takes a decision
/// within rounding of its threshold ([`Applied::near`]): the iteration's decisions from a
/// step's answer, which an engine that fits to float precision leaves to the exact fit.
pub fn near_threshold(s: &Segment, f: &LineFit, origin: &Segment, r: f64, spec: &FitSpec) -> bool {
    apply(s, f, origin, r, spec).near
}

/// One segment's state through the iterations of the fit.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Track {
    /// Where the segment started.
    pub origin: Segment,
    /// Where it is now.
    pub cur: Segment,
    /// How its last move was decided.
    pub how: How,
    /// Steps taken.
    pub steps: u32,
    /// Whether the next step's ridge starts warm ([`ridge_start`]): the last step was a
    /// ridge, taken whole.
    pub warm: bool,
}

impl Track {
    pub fn new(origin: Segment) -> Self {
        Track {
            origin,
            cur: origin,
            how: How::Unclear,
            steps: 0,
            warm: false,
        }
    }

    /// Whether the segment takes a first step at all.
    pub fn starts(&self) -> bool {
        self.cur.is_valid()
    }

    /// Takes the step `answer` (from the members of `X(cur, r)`); returns whether the
    /// segment is still moving (its step moved it by more than [`SETTLED`] r).
    pub fn advance(&mut self, answer: (Option<LineFit>, How), r: f64, spec: &FitSpec) -> bool {
        self.steps += 1;
        let (f, h) = answer;
        // A segment that has moved keeps the model of its last move: a later step that
        // found too few points does not undo what placed it.
        let has_moved = self.cur != self.origin;
        self.warm = false;
        match f.map(|f| apply(&self.cur, &f, &self.origin, r, spec)) {
            Some(Applied {
                seg: s,
                moved,
                whole,
                ..
            }) => {
                self.warm = whole && h == How::Ridge;
                if moved > 0.0 || !has_moved {
                    self.how = h;
                }
                self.cur = s;
                moved > SETTLED * r
            }
            None => {
                if !has_moved {
                    self.how = h;
                }
                false
            }
        }
    }
}

impl FitResult {
    /// The result of finished tracks.
    pub fn of_tracks(tracks: &[Track]) -> FitResult {
        FitResult {
            segments: tracks.iter().map(|t| t.cur).collect(),
            how: tracks.iter().map(|t| t.how).collect(),
            iterations: tracks.iter().map(|t| t.steps).max().unwrap_or(0),
            steps: tracks.iter().map(|t| t.steps).collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn spec() -> FitSpec {
        FitSpec {
            iterations: 12,
            max_turn_deg: 3.0,
            max_move: 2.0,
            bandwidth: 0.25,
            min_points: 8,
            opacity_weight: false,
        }
    }

    #[test]
    fn a_warm_ridge_finds_the_cold_ones_line_from_its_ridge() {
        // A ridge along t at offset (0.004, -0.002) with a wide shell around it, r 0.03.
        let mut rng = crate::synth::Rng::new(3);
        let on = DVec2::new(0.004, -0.002);
        let mut pts = Vec::new();
        for i in 0..300 {
            let t = i as f64 * 0.001;
            let q = if i % 3 == 0 {
                DVec2::new(rng.range(-0.03, 0.03), rng.range(-0.03, 0.03))
            } else {
                on + DVec2::new(rng.normal(), rng.normal()) * 0.001
            };
            pts.push((t, q));
        }
        let pw = vec![1.0; pts.len()];
        let (cold, wc) = ridge(&pts, &pw, 0.03, 0.25, false).unwrap();
        assert!((cold.a - on).length() < 0.0005, "{cold:?}");
        // From the line on the ridge (offsets relative to it), warm and cold agree.
        let moved: Vec<(f64, DVec2)> = pts.iter().map(|(t, q)| (*t, *q - cold.a)).collect();
        let (warm, ww) = ridge(&moved, &pw, 0.03, 0.25, true).unwrap();
        let (again, _) = ridge(&moved, &pw, 0.03, 0.25, false).unwrap();
        assert!(warm.a.length() < 1e-4 * 0.03, "{warm:?}");
        assert!(
            (warm.a - again.a).length() < 1e-4 * 0.03,
            "{warm:?} {again:?}"
        );
        assert!((ww - wc).abs() < 1e-3 * wc);
    }

    #[test]
    fn only_a_ridge_taken_whole_makes_the_next_step_warm() {
        let s = Segment::new(DVec3::ZERO, DVec3::new(1.0, 0.0, 0.0));
        let r = 0.03;
        let line = |a: DVec2| LineFit {
            t0: 0.5,
            a,
            b: DVec2::ZERO,
        };
        let mut t = Track::new(s);
        assert!(!t.warm);
        // A ridge step of 0.2 r, whole.
        t.advance((Some(line(DVec2::new(0.006, 0.0))), How::Ridge), r, &spec());
        assert!(t.warm);
        // Cut to 0.5 r: cold again.
        t.advance((Some(line(DVec2::new(0.03, 0.0))), How::Ridge), r, &spec());
        assert!(!t.warm);
        t.advance((Some(line(DVec2::new(0.001, 0.0))), How::Ridge), r, &spec());
        assert!(t.warm);
        // A corner, whole: the next ridge starts cold.
        t.advance(
            (Some(line(DVec2::new(0.001, 0.0))), How::Corner),
            r,
            &spec(),
        );
        assert!(!t.warm);
        // No answer: cold.
        t.advance((Some(line(DVec2::new(0.001, 0.0))), How::Ridge), r, &spec());
        t.advance((None, How::Unclear), r, &spec());
        assert!(!t.warm);
    }

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
