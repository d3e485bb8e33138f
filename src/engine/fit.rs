//! The edge fit's iterations over an engine (`--fit edge`): every segment steps
//! ([`crate::geom::fit::step`]) from the members of its current cylinder until it settles
//! or has taken `iterations` steps.
//!
//! Two ways to the same answers, bit for bit:
//! - [`gathered`] (the CPU engine's [`Engine::fit_edges`], and the GPU engine's wherever
//!   its fit runs on the host): per segment, the points within `r + GATHER_MARGIN r` of
//!   its line are gathered from the grid once into a compact list (working-set order),
//!   and every step takes its members from that list, in cache, by the same cylinder test
//!   as a walk; the list is gathered again only when the line has moved more than the
//!   margin from where it was gathered.
//! - [`by_batches`] (the default [`Engine::fit_edges`], the GPU engine's device fit): one
//!   [`Engine::fit_lines`] batch per iteration for all segments still moving.

use super::cpu::member_list;
use super::order::SpatialOrder;
use super::{Engine, EngineError, FitAnswer, FitAsk, FitJob, Query};
use crate::geom::fit::{
    basis, near_threshold, step, step_section, FitResult, LineFit, Member, Section, Track,
};
use crate::geom::kernel::avx2;
use crate::geom::{p64, Segment};
use crate::index::Grid;
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;

/// How far (in units of r) a line may move from where its neighbourhood was gathered
/// before it is gathered again. A wider margin gathers less often but tests more points
/// per step.
pub const GATHER_MARGIN: f64 = 0.5;

/// The fit with one engine batch ([`Engine::fit_lines`]) per iteration, for all segments
/// still moving; exact copies (the same segment now and at the start) are asked once.
pub fn by_batches<E: Engine + ?Sized>(
    engine: &E,
    job: &FitJob<'_>,
) -> Result<FitResult, EngineError> {
    let r = job.r;
    let spec = job.spec;
    let mut tracks: Vec<Track> = job.segments.iter().map(|s| Track::new(*s)).collect();
    let mut active: Vec<usize> = (0..tracks.len()).filter(|&i| tracks[i].starts()).collect();
    let mut iterations = 0;
    while !active.is_empty() && iterations < spec.iterations {
        iterations += 1;
        let mut seen: HashMap<[u64; 12], usize> = HashMap::new();
        let mut uniq: Vec<usize> = Vec::new();
        let of: Vec<usize> = active
            .iter()
            .map(|&i| {
                let (a, b) = (tracks[i].cur, tracks[i].origin);
                // (Tracks with the same start and the same line have the same history, and so
                // the same `warm`.)
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
        let queries: Vec<Query> = uniq.iter().map(|&i| Query::new(tracks[i].cur, r)).collect();
        let near = |j: usize, f: &LineFit| {
            let t = &tracks[uniq[j]];
            near_threshold(&t.cur, f, &t.origin, r, spec)
        };
        let warm: Vec<bool> = uniq.iter().map(|&i| tracks[i].warm).collect();
        let ask = FitAsk {
            spec,
            points: job.points,
            sensitive: Some(&near),
            warm: &warm,
        };
        let steps = engine.fit_lines(&queries, &ask)?;
        let mut next = Vec::with_capacity(active.len());
        for (&i, &d) in active.iter().zip(&of) {
            if tracks[i].advance(steps[d], r, spec) {
                next.push(i);
            }
        }
        active = next;
    }
    Ok(FitResult::of_tracks(&tracks))
}

/// [`step`] of every query's segment (`q.seg`, radius `q.r`) from its members: the
/// default [`Engine::fit_lines`], and the host's answer wherever an engine has none. The
/// segments are fitted in parallel; each step depends only on its own members, so the
/// answers are the same for every thread count.
pub fn steps(queries: &[Query], members: &[Vec<Member>], ask: &FitAsk<'_>) -> Vec<FitAnswer> {
    queries
        .par_iter()
        .zip(members)
        .enumerate()
        .with_min_len(4)
        .map(|(i, (q, m))| {
            let warm = ask.warm.get(i).copied().unwrap_or(false);
            step(&q.seg, m, &ask.points, q.r, ask.spec, warm)
        })
        .collect()
}

/// One gathered point: its working-set id in the high half, its place in the grid's
/// point array in the low half, so that sorting the keys as integers sorts the points
/// into working-set order (8-byte keys sort faster than id-and-coordinate records).
type Gathered = u64;

/// The points of `grid` within `reach` of segment `g` (and a few more: the test is
/// generous by a relative 1e-7), in working-set order.
fn gather(
    grid: &Grid,
    g: &Segment,
    reach: f64,
    rows: &mut Vec<(u32, u32)>,
    out: &mut Vec<Gathered>,
) {
    out.clear();
    let d = g.dir();
    let scale = g.p1.abs().max_element().max(g.p2.abs().max_element()) + 1.0;
    let reach = reach * (1.0 + 1e-7) + 1e-9 * scale;
    // The capsule of radius `reach` around `g` lies in the capped cylinder around `g`
    // lengthened by `reach` at each end, whose rows the grid visits.
    let long = Segment::new(g.p1 - d * reach, g.p2 + d * reach);
    let (l, r2) = (g.length(), reach * reach);
    grid.visit_ranges(&long, reach, rows, |range| {
        let start = range.start;
        // Every point is written at the next free place, which advances only past the
        // points within reach: no branch on the test.
        let mut k = out.len();
        out.resize(k + range.len(), 0);
        for (j, p) in grid.points[range].iter().enumerate() {
            let w = p64(*p) - g.p1;
            let t = w.dot(d).clamp(0.0, l);
            let at = start + j;
            out[k] = u64::from(grid.ids[at]) << 32 | at as u64;
            k += usize::from((w - d * t).length_squared() <= r2);
        }
        out.truncate(k);
    });
    out.sort_unstable();
}

/// Largest move of an end from `a` to `b`.
fn end_move(a: &Segment, b: &Segment) -> f64 {
    (a.p1 - b.p1).length().max((a.p2 - b.p2).length())
}

/// A segment's gathered neighbourhood in columns (working-set order): ids and
/// coordinates (widened to f64 once, at the gather, rather than at every step).
#[derive(Default)]
struct Near {
    ids: Vec<u32>,
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
    /// Per point, from the last [`section_among`]: axial position, cross-section offset
    /// in the frame and whether it is a member.
    t: Vec<f64>,
    qx: Vec<f64>,
    qy: Vec<f64>,
    inside: Vec<bool>,
}

impl Near {
    /// The gathered points `g` of `grid` (sorted keys).
    fn fill(&mut self, grid: &Grid, g: &[Gathered]) {
        self.ids.clear();
        self.x.clear();
        self.y.clear();
        self.z.clear();
        for &key in g {
            let p = grid.points[(key & 0xFFFF_FFFF) as usize];
            self.ids.push((key >> 32) as u32);
            self.x.push(f64::from(p[0]));
            self.y.push(f64::from(p[1]));
            self.z.push(f64::from(p[2]));
        }
        let n = g.len();
        self.t.resize(n, 0.0);
        self.qx.resize(n, 0.0);
        self.qy.resize(n, 0.0);
        self.inside.resize(n, false);
    }

    fn len(&self) -> usize {
        self.ids.len()
    }
}

/// Every near point's cylinder test against `cyl` and its offset in the frame
/// `(e1, e2)`: the arithmetic of [`crate::geom::Cylinder::test`] and [`Section::push`],
/// one point per vector lane (no branch).
#[inline(always)]
fn test_body(n: &mut Near, cyl: &crate::geom::Cylinder, (e1, e2): (DVec3, DVec3)) {
    let m = n.len();
    let (xs, ys, zs) = (&n.x[..m], &n.y[..m], &n.z[..m]);
    let (ts, qx, qy, ins) = (
        &mut n.t[..m],
        &mut n.qx[..m],
        &mut n.qy[..m],
        &mut n.inside[..m],
    );
    for i in 0..m {
        let p = DVec3::new(xs[i], ys[i], zs[i]);
        let w = p - cyl.p1;
        let t1 = w.dot(cyl.d);
        let beyond = (cyl.p2 - p).dot(cyl.d);
        let v = w - cyl.d * t1;
        ts[i] = t1;
        qx[i] = v.dot(e1);
        qy[i] = v.dot(e2);
        let past_an_end = (t1 < 0.0) | (beyond < 0.0);
        ins[i] = !past_an_end & (v.length_squared() <= cyl.r2);
    }
}

/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn test_avx2(n: &mut Near, cyl: &crate::geom::Cylinder, frame: (DVec3, DVec3)) {
    test_body(n, cyl, frame)
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn test_avx2(n: &mut Near, cyl: &crate::geom::Cylinder, frame: (DVec3, DVec3)) {
    test_body(n, cyl, frame)
}

/// The cross-section of the members of `X(s, r)` among `near` (which holds every point
/// within `r` of `s`), in their order: the test and arithmetic of a walk
/// ([`member_list`]), then those of [`Section::push`].
fn section_among(near: &mut Near, s: &Segment, r: f64, job: &FitJob<'_>, out: &mut Section) {
    let cyl = crate::geom::Cylinder::new(s, r);
    let frame = basis(s.dir());
    if avx2() {
        // SAFETY: the CPU has AVX2.
        unsafe { test_avx2(near, &cyl, frame) }
    } else {
        test_body(near, &cyl, frame)
    }
    // Every point is written at the next free place, which advances only past members:
    // no branch on the test (points near the cylinder's surface defeat prediction).
    // Straight into the ridge's columns: the step reads them as they are.
    let n = near.len();
    out.t.resize(n, 0.0);
    out.cols.x.resize(n, 0.0);
    out.cols.y.resize(n, 0.0);
    out.cols.w.resize(n, 0.0);
    out.ids.resize(n, 0);
    let (ot, ox, oy) = (&mut out.t[..n], &mut out.cols.x[..n], &mut out.cols.y[..n]);
    let (ow, oi) = (&mut out.cols.w[..n], &mut out.ids[..n]);
    let (ow_on, points) = (job.spec.opacity_weight, &job.points);
    let mut k = 0;
    for i in 0..n {
        let id = near.ids[i];
        ot[k] = near.t[i];
        ox[k] = near.qx[i];
        oy[k] = near.qy[i];
        ow[k] = points.weight_if(ow_on, id);
        oi[k] = id;
        k += usize::from(near.inside[i]);
    }
    out.t.truncate(k);
    out.cols.x.truncate(k);
    out.cols.y.truncate(k);
    out.cols.w.truncate(k);
    out.ids.truncate(k);
}

/// Buffers one thread reuses from segment to segment.
#[derive(Default)]
struct Scratch {
    rows: Vec<(u32, u32)>,
    gathered: Vec<Gathered>,
    near: Near,
    section: Section,
}

/// One segment's iterations, its neighbourhood gathered once (and again only after it
/// moved more than [`GATHER_MARGIN`] r from where it was gathered).
fn track_gathered(grid: &Grid, job: &FitJob<'_>, seg: Segment, s: &mut Scratch) -> Track {
    let (r, spec) = (job.r, job.spec);
    let mut t = Track::new(seg);
    if !t.starts() {
        return t;
    }
    let margin = GATHER_MARGIN * r;
    // Radii the capsule argument does not cover (not a positive finite r) walk per step.
    let direct = !(r.is_finite() && r > 0.0);
    let mut at: Option<Segment> = None;
    while t.steps < spec.iterations {
        if direct {
            s.section.clear();
            let frame = basis(t.cur.dir());
            for m in member_list(grid, &Query::new(t.cur, r)) {
                let ow = spec.opacity_weight;
                s.section.push(m.id, m.t, m.offset, frame, &job.points, ow);
            }
        } else if !t.cur.is_valid() {
            s.section.clear();
        } else {
            // Every point of X(cur, r) lies within r of cur, and cur within the margin
            // of `at` (end by end, so every point of it): within r + margin of `at`.
            let covers = |g: Segment| end_move(&g, &t.cur) <= margin;
            if !at.is_some_and(covers) {
                gather(grid, &t.cur, r + margin, &mut s.rows, &mut s.gathered);
                s.near.fill(grid, &s.gathered);
                at = Some(t.cur);
            }
            section_among(&mut s.near, &t.cur, r, job, &mut s.section);
        }
        let answer = step_section(&t.cur, &mut s.section, &job.points, r, spec, t.warm);
        if !t.advance(answer, r, spec) {
            break;
        }
    }
    t
}

/// The fit over `grid`, each segment's neighbourhood gathered once and iterated on in
/// cache: the answers of [`by_batches`] over an exact engine of the same grid. Also
/// returns the steps taken (cylinders answered), all segments together.
pub fn gathered(grid: &Grid, job: &FitJob<'_>) -> (FitResult, u64) {
    // Segments along a Morton curve through their midpoints' cells, so that neighbouring
    // segments, which share points, run close together in time: only an order of work,
    // never part of an answer.
    let order = SpatialOrder::of_segments(grid, job.segments);
    let done: Vec<(usize, Track)> = (0..job.segments.len())
        .into_par_iter()
        .with_min_len(4)
        .map_init(Scratch::default, |s, j| {
            let i = order.index(j);
            (i, track_gathered(grid, job, job.segments[i], s))
        })
        .collect();
    let mut tracks: Vec<Track> = job.segments.iter().map(|s| Track::new(*s)).collect();
    let mut steps = 0;
    for (i, t) in done {
        steps += u64::from(t.steps);
        tracks[i] = t;
    }
    (FitResult::of_tracks(&tracks), steps)
}
