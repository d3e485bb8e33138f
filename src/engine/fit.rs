//! The edge fit's iterations over an engine (`--fit edge`): every segment steps
//! ([`crate::geom::fit::step`]) from the members of its current cylinder until it settles
//! or has taken `iterations` steps.
//!
//! Two ways to the same answers, bit for bit:
//! - [`gathered`] (the CPU engine's [`Engine::fit_edges`], and the GPU engine's wherever
//!   its fit runs on the host): per segment, the points within `r + GATHER_MARGIN r` of
//!   its line are gathered from the grid once into a compact list (working-set order),
//!   and every step takes its members from that list, in cache, by the same cylinder test
//!   as a walk; the list is gathered again only when the line has left the margin around
//!   the line it was gathered for (and a thread's next segment starts with it, which
//!   serves a near-duplicate or a shorter piece of the same edge without a gather).
//! - [`by_batches`] (the default [`Engine::fit_edges`], the GPU engine's device fit): one
//!   [`Engine::fit_lines`] batch per iteration for all segments still moving.

use super::order::SpatialOrder;
use super::walk::member_list;
use super::{Engine, EngineError, FitAnswer, FitAsk, FitJob, Query};
use crate::geom::fit::{
    basis, near_threshold, step, step_section, FitResult, LineFit, Member, Section, Track,
};
use crate::geom::kernel::avx2;
use crate::geom::{p64, Segment};
use crate::index::Grid;
use glam::DVec3;
use rayon::prelude::*;

/// How far (in units of r) a line may lie from the line its neighbourhood was gathered
/// for before it is gathered again. A wider margin gathers less often but tests more points
/// per step.
pub const GATHER_MARGIN: f64 = 0.5;

/// The fit with one engine batch ([`Engine::fit_lines`]) per iteration, for all segments
/// still moving; exact copies (the same input segment) are asked once
/// ([`super::dedup::fit_distinct`], as the [`super::dedup::Dedup`] wrapper asks them).
pub fn by_batches<E: Engine + ?Sized>(
    engine: &E,
    job: &FitJob<'_>,
) -> Result<FitResult, EngineError> {
    by_batches_in(engine, job, None, None)
}

/// `order(segments)`: the order an engine asks segments in ([`by_batches_in`]).
pub type OrderOf<'a> = dyn Fn(&[Segment]) -> SpatialOrder + Sync + 'a;

/// The fit's last iterations somewhere else than in batches ([`by_batches_in`]): once at
/// most `at_most` segments are still moving, `finish(job, tracks)` takes each of those
/// tracks on from where it is to where it settles (or takes the job's last iteration).
/// [`finish_gathered`] does that as the gathered fit would: the same answers as more
/// batches of an exact engine.
pub struct Tail<'a> {
    pub at_most: usize,
    pub finish: &'a Finish<'a>,
}

/// A [`Tail`]'s `finish(job, tracks)`.
pub type Finish<'a> = dyn Fn(&FitJob<'_>, &mut [Track]) -> Result<(), EngineError> + Sync + 'a;

/// Tracks a task of the fit loop's parallel passes (each track's query, each step's
/// advance: 0.1–0.2 µs a track). Small enough that a machine of 16 threads gets work for
/// every thread from the 10^4 segments of a typical scene (4,096 gave it three tasks).
const TRACKS_A_TASK: usize = 512;

/// [`by_batches`] with the segments asked in `order(segments)` ([`FitAsk::in_order`]),
/// where the engine gives one: its own batches' order ([`SpatialOrder`]), kept over the
/// iterations (the segments still moving, in the same order), so that the engine need
/// not order each batch again; and with the last iterations' few segments handed to
/// `tail` where one is given ([`Tail`]). The per-iteration work of the tracks (their
/// queries, each step's advance) is parallel. The answers are the same in any order.
pub fn by_batches_in<E: Engine + ?Sized>(
    engine: &E,
    job: &FitJob<'_>,
    order: Option<&OrderOf<'_>>,
    tail: Option<&Tail<'_>>,
) -> Result<FitResult, EngineError> {
    super::dedup::fit_distinct(job, |job| {
        let r = job.r;
        let spec = job.spec;
        let mut tracks: Vec<Track> = job.segments.iter().map(|s| Track::new(*s)).collect();
        // The tracks still moving (with their segment's index), in the order asked.
        let mut live: Vec<(usize, Track)> = match order {
            Some(order) => {
                let o = order(job.segments);
                (0..tracks.len()).map(|j| o.index(j)).collect::<Vec<_>>()
            }
            None => (0..tracks.len()).collect(),
        }
        .into_iter()
        .filter(|&i| tracks[i].starts())
        .map(|i| (i, tracks[i]))
        .collect();
        let mut iterations = 0;
        while !live.is_empty() && iterations < spec.iterations {
            if let Some(tail) = tail.filter(|t| live.len() <= t.at_most) {
                // Every live track has taken each iteration so far: its own steps
                // count them, and it goes on until it settles or takes the last.
                let mut rest: Vec<Track> = live.iter().map(|&(_, t)| t).collect();
                (tail.finish)(job, &mut rest)?;
                for (&(i, _), t) in live.iter().zip(rest) {
                    tracks[i] = t;
                }
                live.clear();
                break;
            }
            iterations += 1;
            let steps = {
                let (queries, warm): (Vec<Query>, Vec<bool>) = live
                    .par_iter()
                    .with_min_len(TRACKS_A_TASK)
                    .map(|(_, t)| (Query::new(t.cur, r), t.warm))
                    .unzip();
                let near = |j: usize, f: &LineFit| {
                    let t = &live[j].1;
                    near_threshold(&t.cur, f, &t.origin, r, spec)
                };
                let ask = FitAsk {
                    spec,
                    points: job.points,
                    sensitive: Some(&near),
                    warm: &warm,
                    in_order: order.is_some(),
                };
                engine.fit_lines(&queries, &ask)?
            };
            let more: Vec<bool> = live
                .par_iter_mut()
                .zip(&steps)
                .with_min_len(TRACKS_A_TASK)
                .map(|((_, t), &d)| t.advance(d, r, spec))
                .collect();
            let mut k = 0;
            live.retain(|&(i, t)| {
                k += 1;
                if !more[k - 1] {
                    tracks[i] = t;
                }
                more[k - 1]
            });
        }
        for (i, t) in live {
            tracks[i] = t;
        }
        Ok(FitResult::of_tracks(&tracks))
    })
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
/// generous by a relative 1e-7), in working-set order; tested in vector instructions
/// where `vector` (the CPU has AVX2), the same keys either way.
fn gather(
    grid: &Grid,
    g: &Segment,
    reach: f64,
    rows: &mut Vec<(u32, u32)>,
    out: &mut Vec<Gathered>,
    vector: bool,
) {
    out.clear();
    let scale = g.p1.abs().max_element().max(g.p2.abs().max_element()) + 1.0;
    let reach = reach * (1.0 + 1e-7) + 1e-9 * scale;
    let capsule = Capsule::around(g, reach * reach);
    // The capsule of radius `reach` around `g` lies in the capped cylinder around `g`
    // lengthened by `reach` at each end, whose rows the grid visits.
    let d = capsule.d;
    let long = Segment::new(g.p1 - d * reach, g.p2 + d * reach);
    grid.visit_ranges(&long, reach, rows, |range| {
        let k = out.len();
        out.reserve(range.len() + SPARE);
        // Places past the length, within the capacity: written here before the length
        // takes them in.
        let to = out.as_mut_ptr();
        #[cfg(target_arch = "x86_64")]
        let k = if vector {
            // SAFETY: the CPU has AVX2; `to` has room for every point of the range and
            // SPARE more past `k`.
            unsafe { x86::gather_range(grid, range, &capsule, to, k) }
        } else {
            gather_body(grid, range, &capsule, to, k)
        };
        #[cfg(not(target_arch = "x86_64"))]
        let k = {
            let _ = vector;
            gather_body(grid, range, &capsule, to, k)
        };
        // SAFETY: the first `k` places are written (the keys before and those within
        // reach here).
        unsafe { out.set_len(k) };
    });
    out.sort_unstable();
}

/// The capsule of a gather: points within `sqrt(r2)` of the segment from `p1` along the
/// unit direction `d` for `l`.
struct Capsule {
    p1: DVec3,
    d: DVec3,
    l: f64,
    r2: f64,
}

impl Capsule {
    /// The points within `sqrt(r2)` of the segment `g`.
    fn around(g: &Segment, r2: f64) -> Capsule {
        Capsule {
            p1: g.p1,
            d: g.dir(),
            l: g.length(),
            r2,
        }
    }

    /// Whether `p` lies within the capsule.
    #[inline(always)]
    fn holds(&self, p: DVec3) -> bool {
        let w = p - self.p1;
        let t = w.dot(self.d).clamp(0.0, self.l);
        (w - self.d * t).length_squared() <= self.r2
    }
}

/// The keys of the points of `range` within the capsule `c`, written at `to` from place
/// `k` on; returns the place after the last. Every point is written at the next free
/// place, which advances only past the points within reach: no branch on the test.
///
/// Places `k..k + range.len()` of `to` must be writable.
#[inline(always)]
fn gather_body(
    grid: &Grid,
    range: std::ops::Range<usize>,
    c: &Capsule,
    to: *mut Gathered,
    mut k: usize,
) -> usize {
    let start = range.start;
    for (j, p) in grid.points[range].iter().enumerate() {
        let at = start + j;
        // SAFETY: the caller's room: k <= k0 + j.
        unsafe { to.add(k).write(u64::from(grid.ids[at]) << 32 | at as u64) };
        k += usize::from(c.holds(p64(*p)));
    }
    k
}

/// A segment's gathered neighbourhood in columns (working-set order): ids and
/// coordinates (widened to f64 once, at the gather, rather than at every step).
#[derive(Default)]
struct Near {
    ids: Vec<u32>,
    x: Vec<f64>,
    y: Vec<f64>,
    z: Vec<f64>,
}

impl Near {
    /// The gathered points `g` of `grid` (sorted keys).
    fn fill(&mut self, grid: &Grid, g: &[Gathered]) {
        let n = g.len();
        self.ids.resize(n, 0);
        self.x.resize(n, 0.0);
        self.y.resize(n, 0.0);
        self.z.resize(n, 0.0);
        let (ids, x, y, z) = (
            &mut self.ids[..n],
            &mut self.x[..n],
            &mut self.y[..n],
            &mut self.z[..n],
        );
        for (j, &key) in g.iter().enumerate() {
            let p = grid.points[(key & 0xFFFF_FFFF) as usize];
            ids[j] = (key >> 32) as u32;
            x[j] = f64::from(p[0]);
            y[j] = f64::from(p[1]);
            z[j] = f64::from(p[2]);
        }
    }

    fn len(&self) -> usize {
        self.ids.len()
    }
}

/// Room past the last point that the gather's buffer and [`section_among`]'s columns
/// keep while they are written: the vector copies store four lanes at every place.
const SPARE: usize = 4;

/// The members among the near points `near[from..]` of the cylinder `cyl`, written in
/// their order from place `k` on in `out`'s position and offset columns (`t`, offsets in
/// the frame `(e1, e2)`, ids); returns the place after the last. The arithmetic of
/// [`crate::geom::Cylinder::test`] and [`Section::push`] point by point; every point is
/// written at the next free place, which advances only past members: no branch on the
/// test (points near the cylinder's surface defeat prediction).
#[inline(always)]
fn section_body(
    near: &Near,
    from: usize,
    cyl: &crate::geom::Cylinder,
    (e1, e2): (DVec3, DVec3),
    out: &mut Section,
    mut k: usize,
) -> usize {
    let n = near.len();
    let (xs, ys, zs, ids) = (&near.x[..n], &near.y[..n], &near.z[..n], &near.ids[..n]);
    let (ot, ox, oy) = (&mut out.t[..], &mut out.cols.x[..], &mut out.cols.y[..]);
    let oi = &mut out.ids[..];
    for i in from..n {
        let p = DVec3::new(xs[i], ys[i], zs[i]);
        let w = p - cyl.p1;
        let t1 = w.dot(cyl.d);
        let beyond = (cyl.p2 - p).dot(cyl.d);
        let v = w - cyl.d * t1;
        ot[k] = t1;
        ox[k] = v.dot(e1);
        oy[k] = v.dot(e2);
        oi[k] = ids[i];
        let past_an_end = (t1 < 0.0) | (beyond < 0.0);
        k += usize::from(!past_an_end & (v.length_squared() <= cyl.r2));
    }
    k
}

/// The cross-section of the members of `X(s, r)` among `near` (which holds every point
/// within `r` of `s`), in their order: the test and arithmetic of a walk
/// ([`member_list`]), then those of [`Section::push`].
fn section_among(near: &Near, s: &Segment, r: f64, job: &FitJob<'_>, out: &mut Section) {
    let cyl = crate::geom::Cylinder::new(s, r);
    let frame = basis(s.dir());
    // Straight into the ridge's columns: the step reads them as they are.
    let n = near.len();
    out.t.resize(n + SPARE, 0.0);
    out.cols.x.resize(n + SPARE, 0.0);
    out.cols.y.resize(n + SPARE, 0.0);
    out.ids.resize(n + SPARE, 0);
    #[cfg(target_arch = "x86_64")]
    let k = if avx2() {
        // SAFETY: the CPU has AVX2; every column has SPARE places past `n`.
        unsafe { x86::section(near, &cyl, frame, out) }
    } else {
        section_body(near, 0, &cyl, frame, out, 0)
    };
    #[cfg(not(target_arch = "x86_64"))]
    let k = section_body(near, 0, &cyl, frame, out, 0);
    out.t.truncate(k);
    out.cols.x.truncate(k);
    out.cols.y.truncate(k);
    out.ids.truncate(k);
    let (ow_on, points) = (job.spec.opacity_weight, &job.points);
    out.cols.w.clear();
    if ow_on {
        out.cols
            .w
            .extend(out.ids.iter().map(|&id| points.weight(id)));
    } else {
        out.cols.w.resize(k, 1.0);
    }
}

/// [`section_body`] four points at a time in explicit vector instructions (the same
/// operations in the same order, so the same bits): the members of each four are packed
/// to the front of a register by a permutation from a table and stored whole at the
/// next free place.
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{gather_body, section_body, Capsule, Gathered, Near, Section, SPARE};
    use crate::geom::Cylinder;
    use crate::index::Grid;
    use glam::DVec3;
    use std::arch::x86_64::*;

    /// Per 4-bit member mask, the 32-bit lane permutation that packs the members' lanes
    /// to the front: of 64-bit lanes (`wide`) or of 32-bit lanes.
    const fn pack_table(wide: bool) -> [[i32; 8]; 16] {
        let mut t = [[0i32; 8]; 16];
        let mut m = 0;
        while m < 16 {
            let mut slot = 0;
            let mut lane: i32 = 0;
            while lane < 4 {
                if m & (1 << lane) != 0 {
                    if wide {
                        t[m][2 * slot] = 2 * lane;
                        t[m][2 * slot + 1] = 2 * lane + 1;
                    } else {
                        t[m][slot] = lane;
                    }
                    slot += 1;
                }
                lane += 1;
            }
            m += 1;
        }
        t
    }

    static PACK64: [[i32; 8]; 16] = pack_table(true);
    static PACK32: [[i32; 8]; 16] = pack_table(false);

    /// [`gather_body`] four points at a time (the same arithmetic): each four's
    /// coordinates loaded in three reads and sorted into columns, their keys packed to
    /// the front by [`PACK64`] and stored whole.
    ///
    /// # Safety
    /// The CPU has AVX2, and places `k..k + range.len() + SPARE` of `to` are writable.
    #[target_feature(enable = "avx2")]
    pub unsafe fn gather_range(
        grid: &Grid,
        range: std::ops::Range<usize>,
        c: &Capsule,
        to: *mut Gathered,
        mut k: usize,
    ) -> usize {
        let s = _mm256_set1_pd;
        let (p1x, p1y, p1z) = (s(c.p1.x), s(c.p1.y), s(c.p1.z));
        let (dx, dy, dz) = (s(c.d.x), s(c.d.y), s(c.d.z));
        let (l, r2, zero) = (s(c.l), s(c.r2), _mm256_setzero_pd());
        let lanes = _mm256_set_epi64x(3, 2, 1, 0);
        let (pp, ip) = (grid.points.as_ptr().cast::<f32>(), grid.ids.as_ptr());
        let mut at = range.start;
        while at + 4 <= range.end {
            // Points at, at+1, at+2, at+3: [x0 y0 z0 x1] [y1 z1 x2 y2] [z2 x3 y3 z3].
            let a = _mm_loadu_ps(pp.add(3 * at));
            let b = _mm_loadu_ps(pp.add(3 * at + 4));
            let cc = _mm_loadu_ps(pp.add(3 * at + 8));
            let t1 = _mm_shuffle_ps::<0b01_00_11_10>(b, cc);
            let x = _mm_shuffle_ps::<0b11_00_11_00>(a, t1);
            let t2 = _mm_shuffle_ps::<0b00_00_01_01>(a, b);
            let t3 = _mm_shuffle_ps::<0b10_10_11_11>(b, cc);
            let y = _mm_shuffle_ps::<0b10_00_10_00>(t2, t3);
            let t4 = _mm_shuffle_ps::<0b01_01_10_10>(a, b);
            let t5 = _mm_shuffle_ps::<0b11_11_00_00>(cc, cc);
            let z = _mm_shuffle_ps::<0b10_00_10_00>(t4, t5);
            let wx = _mm256_sub_pd(_mm256_cvtps_pd(x), p1x);
            let wy = _mm256_sub_pd(_mm256_cvtps_pd(y), p1y);
            let wz = _mm256_sub_pd(_mm256_cvtps_pd(z), p1z);
            let t = _mm256_add_pd(
                _mm256_add_pd(_mm256_mul_pd(wx, dx), _mm256_mul_pd(wy, dy)),
                _mm256_mul_pd(wz, dz),
            );
            let t = _mm256_min_pd(_mm256_max_pd(t, zero), l);
            let ex = _mm256_sub_pd(wx, _mm256_mul_pd(dx, t));
            let ey = _mm256_sub_pd(wy, _mm256_mul_pd(dy, t));
            let ez = _mm256_sub_pd(wz, _mm256_mul_pd(dz, t));
            let e2 = _mm256_add_pd(
                _mm256_add_pd(_mm256_mul_pd(ex, ex), _mm256_mul_pd(ey, ey)),
                _mm256_mul_pd(ez, ez),
            );
            let m = _mm256_movemask_pd(_mm256_cmp_pd::<_CMP_LE_OQ>(e2, r2)) as usize;
            let ids = _mm256_cvtepu32_epi64(_mm_loadu_si128(ip.add(at).cast()));
            let keys = _mm256_or_si256(
                _mm256_slli_epi64::<32>(ids),
                _mm256_add_epi64(_mm256_set1_epi64x(at as i64), lanes),
            );
            let p64 = _mm256_loadu_si256(PACK64[m].as_ptr().cast());
            _mm256_storeu_si256(to.add(k).cast(), _mm256_permutevar8x32_epi32(keys, p64));
            k += (m as u32).count_ones() as usize;
            at += 4;
        }
        gather_body(grid, at..range.end, c, to, k)
    }

    /// The members among all of `near` from place 0 of `out`; returns their number.
    ///
    /// # Safety
    /// The CPU has AVX2, and `out`'s `t`, offset and id columns hold at least
    /// `near.len() + SPARE` places.
    #[target_feature(enable = "avx2")]
    pub unsafe fn section(
        near: &Near,
        cyl: &Cylinder,
        (e1, e2): (DVec3, DVec3),
        out: &mut Section,
    ) -> usize {
        let n = near.len();
        debug_assert!(out.t.len() >= n + SPARE && out.cols.x.len() >= n + SPARE);
        debug_assert!(out.cols.y.len() >= n + SPARE && out.ids.len() >= n + SPARE);
        let (xp, yp, zp) = (near.x.as_ptr(), near.y.as_ptr(), near.z.as_ptr());
        let ip = near.ids.as_ptr();
        let (ot, ox, oy) = (
            out.t.as_mut_ptr(),
            out.cols.x.as_mut_ptr(),
            out.cols.y.as_mut_ptr(),
        );
        let oi = out.ids.as_mut_ptr();
        let s = _mm256_set1_pd;
        let (p1x, p1y, p1z) = (s(cyl.p1.x), s(cyl.p1.y), s(cyl.p1.z));
        let (p2x, p2y, p2z) = (s(cyl.p2.x), s(cyl.p2.y), s(cyl.p2.z));
        let (dx, dy, dz) = (s(cyl.d.x), s(cyl.d.y), s(cyl.d.z));
        let (ax, ay, az) = (s(e1.x), s(e1.y), s(e1.z));
        let (bx, by, bz) = (s(e2.x), s(e2.y), s(e2.z));
        let (r2, zero) = (s(cyl.r2), _mm256_setzero_pd());
        let dot = |x: __m256d, y: __m256d, z: __m256d, u: __m256d, v: __m256d, w: __m256d| {
            _mm256_add_pd(
                _mm256_add_pd(_mm256_mul_pd(x, u), _mm256_mul_pd(y, v)),
                _mm256_mul_pd(z, w),
            )
        };
        let mut k = 0;
        let mut i = 0;
        while i + 4 <= n {
            let (x, y, z) = (
                _mm256_loadu_pd(xp.add(i)),
                _mm256_loadu_pd(yp.add(i)),
                _mm256_loadu_pd(zp.add(i)),
            );
            let (wx, wy, wz) = (
                _mm256_sub_pd(x, p1x),
                _mm256_sub_pd(y, p1y),
                _mm256_sub_pd(z, p1z),
            );
            let t1 = dot(wx, wy, wz, dx, dy, dz);
            let beyond = dot(
                _mm256_sub_pd(p2x, x),
                _mm256_sub_pd(p2y, y),
                _mm256_sub_pd(p2z, z),
                dx,
                dy,
                dz,
            );
            let vx = _mm256_sub_pd(wx, _mm256_mul_pd(dx, t1));
            let vy = _mm256_sub_pd(wy, _mm256_mul_pd(dy, t1));
            let vz = _mm256_sub_pd(wz, _mm256_mul_pd(dz, t1));
            let qx = dot(vx, vy, vz, ax, ay, az);
            let qy = dot(vx, vy, vz, bx, by, bz);
            let past = _mm256_or_pd(
                _mm256_cmp_pd::<_CMP_LT_OQ>(t1, zero),
                _mm256_cmp_pd::<_CMP_LT_OQ>(beyond, zero),
            );
            let within = _mm256_cmp_pd::<_CMP_LE_OQ>(dot(vx, vy, vz, vx, vy, vz), r2);
            let m = _mm256_movemask_pd(_mm256_andnot_pd(past, within)) as usize;
            let p64 = _mm256_loadu_si256(PACK64[m].as_ptr().cast());
            let pack =
                |v: __m256d| _mm256_castps_pd(_mm256_permutevar8x32_ps(_mm256_castpd_ps(v), p64));
            _mm256_storeu_pd(ot.add(k), pack(t1));
            _mm256_storeu_pd(ox.add(k), pack(qx));
            _mm256_storeu_pd(oy.add(k), pack(qy));
            let id = _mm256_castsi128_si256(_mm_loadu_si128(ip.add(i).cast()));
            let p32 = _mm256_loadu_si256(PACK32[m].as_ptr().cast());
            let id = _mm256_permutevar8x32_epi32(id, p32);
            _mm_storeu_si128(oi.add(k).cast(), _mm256_castsi256_si128(id));
            k += (m as u32).count_ones() as usize;
            i += 4;
        }
        section_body(near, i, cyl, (e1, e2), out, k)
    }
}

/// Buffers one thread reuses from segment to segment, and the neighbourhood it gathered
/// last: the points within `r + GATHER_MARGIN r` of `at`.
#[derive(Default)]
struct Scratch {
    rows: Vec<(u32, u32)>,
    gathered: Vec<Gathered>,
    near: Near,
    at: Option<Segment>,
    section: Section,
}

/// Whether the points within `r + margin` of `at` include every point within `r` of
/// `cur`: both ends of `cur` lie within `margin` of `at` (the distance to a segment is
/// convex along a line, so every point of `cur` does too), and a point within `r` of
/// some point of `cur` lies within `r + margin` of `at`.
fn covers(at: &Segment, cur: &Segment, margin: f64) -> bool {
    let c = Capsule::around(at, margin * margin);
    c.holds(cur.p1) && c.holds(cur.p2)
}

/// One segment's iterations, its members taken from the thread's last gathered
/// neighbourhood while that covers the line ([`covers`], with a margin of
/// [`GATHER_MARGIN`] r): a segment gathers at its first step at most, and again only
/// after its line has left the margin around the line the neighbourhood was gathered
/// for. The next segment in the thread's order (the work runs along a space-filling
/// curve) starts with the same neighbourhood, which serves it too where it lies along the
/// same stretch of edge: a near-duplicate, or a shorter piece of it. Members are the
/// points of a neighbourhood that pass a step's cylinder test, in the neighbourhood's
/// working-set order, so which covering neighbourhood they come from changes nothing.
fn track_gathered(grid: &Grid, job: &FitJob<'_>, seg: Segment, s: &mut Scratch) -> Track {
    let mut t = Track::new(seg);
    if t.starts() {
        go_on_gathered(grid, job, &mut t, s);
    }
    t
}

/// Takes the track `t` on, step by step over its gathered neighbourhood, until it settles
/// or has taken `job.spec.iterations` steps.
fn go_on_gathered(grid: &Grid, job: &FitJob<'_>, t: &mut Track, s: &mut Scratch) {
    let (r, spec) = (job.r, job.spec);
    let margin = GATHER_MARGIN * r;
    // Radii the capsule argument does not cover (not a positive finite r) walk per step.
    let direct = !(r.is_finite() && r > 0.0);
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
            // Every point of X(cur, r) lies within r of cur.
            if !s.at.is_some_and(|at| covers(&at, &t.cur, margin)) {
                gather(
                    grid,
                    &t.cur,
                    r + margin,
                    &mut s.rows,
                    &mut s.gathered,
                    avx2(),
                );
                s.near.fill(grid, &s.gathered);
                s.at = Some(t.cur);
            }
            section_among(&s.near, &t.cur, r, job, &mut s.section);
        }
        let answer = step_section(&t.cur, &mut s.section, &job.points, r, spec, t.warm);
        if !t.advance(answer, r, spec) {
            break;
        }
    }
}

/// A [`Tail`]'s `finish` over `grid`: each track taken on as the gathered fit takes a
/// segment ([`gathered`]), in parallel and in the order given (the caller's spatial
/// order). Returns the steps taken (cylinders answered), all tracks together.
pub fn finish_gathered(grid: &Grid, job: &FitJob<'_>, tracks: &mut [Track]) -> u64 {
    tracks
        .par_iter_mut()
        .with_min_len(4)
        .map_init(Scratch::default, |s, t| {
            let before = t.steps;
            go_on_gathered(grid, job, t, s);
            u64::from(t.steps - before)
        })
        .sum()
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::Rng;

    /// Near points around a segment, some exactly on the cylinder's surface or caps.
    #[cfg(target_arch = "x86_64")]
    fn near_points(rng: &mut Rng, s: &Segment, r: f64, n: usize) -> Near {
        let (e1, e2) = basis(s.dir());
        let mut near = Near::default();
        for i in 0..n {
            let t = rng.uniform() * 1.4 - 0.2;
            let a = rng.uniform() * std::f64::consts::TAU;
            let rho = if i % 5 == 0 {
                r
            } else {
                rng.uniform() * 1.5 * r
            };
            let t = if i % 7 == 0 { 0.0 } else { t };
            let p = s.p1 + (s.p2 - s.p1) * t + (e1 * a.cos() + e2 * a.sin()) * rho;
            let p = p.as_vec3().as_dvec3();
            near.ids.push((rng.uniform() * 1e6) as u32);
            near.x.push(p.x);
            near.y.push(p.y);
            near.z.push(p.z);
        }
        near
    }

    #[test]
    fn a_covering_neighbourhood_holds_every_point_near_the_line() {
        let mut rng = Rng::new(21);
        let (r, margin) = (0.03, 0.015);
        let at = Segment::new(DVec3::ZERO, DVec3::new(1.0, 0.0, 0.0));
        // A shorter piece of the same edge, and one tilted within the margin: covered,
        // although their ends are far from `at`'s (the old end-by-end rule refused them).
        let piece = Segment::new(DVec3::new(0.3, 0.01, 0.0), DVec3::new(0.6, 0.0, -0.01));
        assert!(covers(&at, &piece, margin));
        assert!(covers(&at, &piece.reversed(), margin));
        // Ends just beyond the margin: off the side, and past an end along the line.
        let side = Segment::new(DVec3::new(0.3, 0.0, 0.0), DVec3::new(0.6, 0.015001, 0.0));
        assert!(!covers(&at, &side, margin));
        let past = Segment::new(DVec3::new(0.5, 0.0, 0.0), DVec3::new(1.015001, 0.0, 0.0));
        assert!(!covers(&at, &past, margin));
        // Random pairs: where the rule covers, points within r of `cur` (on the sphere of
        // radius r around a point of it) lie within r + margin of `at`.
        let mut covered = 0;
        for _ in 0..2000 {
            let a = Segment::new(rng.normal3(0.3), rng.normal3(0.3));
            let cur = Segment::new(
                a.p1 + (a.p2 - a.p1) * rng.uniform() + rng.normal3(0.01),
                a.p1 + (a.p2 - a.p1) * rng.uniform() + rng.normal3(0.01),
            );
            if !covers(&a, &cur, margin) {
                continue;
            }
            covered += 1;
            for _ in 0..20 {
                let c = cur.p1 + (cur.p2 - cur.p1) * rng.uniform();
                let p = c + rng.normal3(1.0).normalize() * r;
                let reach = (r + margin) * (1.0 + 1e-12);
                assert!(Capsule::around(&a, reach * reach).holds(p));
            }
        }
        assert!(covered > 500, "{covered}");
    }

    #[test]
    fn the_vector_gather_is_the_scalar_one() {
        if !avx2() {
            return;
        }
        let mut rng = Rng::new(9);
        let pts: Vec<[f32; 3]> = (0..20_000)
            .map(|_| [0, 1, 2].map(|_| rng.uniform() as f32))
            .collect();
        let mut bounds = crate::geom::Aabb::empty();
        for p in &pts {
            bounds.extend(p64(*p));
        }
        let grid = Grid::build(&pts, bounds, 0.03);
        let (mut rows, mut a, mut b) = (Vec::new(), Vec::new(), Vec::new());
        let mut total = 0;
        for i in 0..40 {
            let p1 = DVec3::new(rng.uniform(), rng.uniform(), rng.uniform());
            let s = Segment::new(p1, p1 + rng.normal3(0.2));
            let reach = 0.01 + 0.002 * i as f64;
            gather(&grid, &s, reach, &mut rows, &mut a, false);
            gather(&grid, &s, reach, &mut rows, &mut b, true);
            assert_eq!(a, b, "segment {i}");
            // Every point within reach, and none far past it, in working-set order.
            let dist = |p: DVec3| {
                let w = p - s.p1;
                (w - s.dir() * w.dot(s.dir()).clamp(0.0, s.length())).length()
            };
            let want: Vec<u32> = (0..pts.len() as u32)
                .filter(|&id| dist(p64(pts[id as usize])) <= reach)
                .collect();
            let got: Vec<u32> = a.iter().map(|&key| (key >> 32) as u32).collect();
            assert!(want.iter().all(|id| got.binary_search(id).is_ok()), "{i}");
            assert!(got.windows(2).all(|w| w[0] < w[1]), "{i}");
            assert!(
                got.len() <= want.len() + 2,
                "{i}: {} {}",
                got.len(),
                want.len()
            );
            total += got.len();
        }
        assert!(total > 1000, "{total}");
    }

    #[test]
    #[cfg(target_arch = "x86_64")]
    fn the_vector_section_is_the_scalar_one_bit_for_bit() {
        if !avx2() {
            return;
        }
        let mut rng = Rng::new(3);
        let slanted = Segment::new(DVec3::new(0.1, -0.2, 0.3), DVec3::new(0.9, 0.4, -0.1));
        // Along x, r = 1/4: points exactly on the surface and on the end caps.
        let straight = Segment::new(DVec3::ZERO, DVec3::X);
        let mut members = 0;
        for (s, n) in [0, 1, 3, 4, 5, 7, 8, 9, 16, 31, 200, 1001]
            .map(|n| (slanted, n))
            .into_iter()
            .chain([(straight, 9), (straight, 40)])
        {
            let r = if s == straight { 0.25 } else { 0.05 };
            let cyl = crate::geom::Cylinder::new(&s, r);
            let frame = basis(s.dir());
            let mut near = near_points(&mut rng, &s, r, n);
            if s == straight {
                for (i, x) in near.x.iter_mut().enumerate() {
                    *x = [0.0, 1.0, 0.5, 1.0 + 1e-9][i % 4];
                }
                for (i, y) in near.y.iter_mut().enumerate() {
                    *y = [0.25, -0.25, 0.25 + 1e-12][i % 3];
                }
                near.z.fill(0.0);
            }
            let mut a = Section::default();
            let mut b = Section::default();
            for o in [&mut a, &mut b] {
                o.t.resize(n + SPARE, 0.0);
                o.cols.x.resize(n + SPARE, 0.0);
                o.cols.y.resize(n + SPARE, 0.0);
                o.ids.resize(n + SPARE, 0);
            }
            let ka = section_body(&near, 0, &cyl, frame, &mut a, 0);
            // SAFETY: checked above; every column has SPARE places.
            let kb = unsafe { x86::section(&near, &cyl, frame, &mut b) };
            assert_eq!(ka, kb, "{n} points");
            let bits = |v: &[f64]| v[..ka].iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&a.t), bits(&b.t), "{n}");
            assert_eq!(bits(&a.cols.x), bits(&b.cols.x), "{n}");
            assert_eq!(bits(&a.cols.y), bits(&b.cols.y), "{n}");
            assert_eq!(a.ids[..ka], b.ids[..kb], "{n}");
            // The members are those of the cylinder test, in order.
            let want: Vec<u32> = (0..n)
                .filter(|&i| {
                    cyl.test(DVec3::new(near.x[i], near.y[i], near.z[i]))
                        .is_some()
                })
                .map(|i| near.ids[i])
                .collect();
            assert_eq!(a.ids[..ka], want[..], "{n}");
            members += ka;
        }
        assert!(members > 300, "{members}");
    }
}
