//! Step 7, duplication and discontinuity: segments of different input lines that are
//! similar (close and nearly parallel) are grouped by a thresholded union-find, so that
//! step 8 merges and joins only inside a group.
//!
//! The similarity of docs/method.md#step-7-cluster is `w = dist_w x len_w` with
//! `dist_w = 1 / (1 + 2 (dist / r_c)^2)` and `len_w < 1`, so an edge `w >= w_min` needs
//! `dist_w >= w_min`, that is `dist <= B = r_c sqrt((1/w_min - 1) / 2)` (`r_c sqrt(0.75)`
//! for the default 0.4). With the fixed distance the candidate pairs come from a spatial
//! hash built on that bound (see [`edges`]); the `reference` distance ignores the lateral
//! offset of segments that do not overlap, so it has no spatial bound across a segment's
//! axis: its candidates come from a tree of the endpoints that is cut by position along
//! the axis, by direction and by length (see [`EndQuery`]).

use crate::engine::EngineError;
use crate::geom::{LineSet, Segment};
use crate::refine::params::{group, Check};
use crate::refine::{Pass, Settings, Step};
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};

group! {
    /// Step 7's parameters.
    pub struct ClusterParams {
        /// Cluster: minimum similarity w of an edge.
        cluster_min_weight: f64 = 0.4, Check::Fraction;
        /// Cluster: initial per-root threshold c (thr = w + c / size after a join).
        cluster_c: f64 = 1.5, Check::Positive;
        /// Cluster: |cos| between directions above which the length weight is non-zero.
        cluster_min_cos: f64 = 0.5, Check::Fraction;
    }
}

/// Step 7, the stage `cluster`: the clusters for the merge and join (the segments stay
/// as they are, so the report's lengths do not list it).
pub struct Cluster;

impl Step for Cluster {
    fn name(&self) -> &'static str {
        "cluster"
    }

    fn measured(&self) -> bool {
        false
    }

    fn run(&self, pass: &mut Pass) -> Result<(), crate::engine::EngineError> {
        pass.clusters = cluster(&pass.lines, pass.settings)?;
        Ok(())
    }
}

/// A similarity edge between segments `i < j` of different input lines, with its weight
/// `w >= 0`, packed in 16 bytes whose order is the order step 7 takes edges in: `w`
/// ascending (a non-negative `f64` orders as its bits), then `i`, then `j`. Dense inputs
/// keep about a hundred edges per segment, so the size is most of the step's memory.
#[derive(Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Edge(u128);

impl Edge {
    /// Indices below 2^32 (a line set of more segments would not fit in memory).
    pub fn new(i: usize, j: usize, w: f64) -> Edge {
        debug_assert!(i < j && w >= 0.0, "edge ({i}, {j}, {w})");
        let index = |k: usize| u32::try_from(k).expect("segment index below 2^32") as u128;
        // `+ 0.0` turns a -0.0 into +0.0, whose bits order below every positive weight.
        Edge((((w + 0.0).to_bits() as u128) << 64) | (index(i) << 32) | index(j))
    }

    pub fn i(self) -> usize {
        (self.0 >> 32) as u32 as usize
    }

    pub fn j(self) -> usize {
        self.0 as u32 as usize
    }

    pub fn w(self) -> f64 {
        f64::from_bits((self.0 >> 64) as u64)
    }
}

impl std::fmt::Debug for Edge {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Edge({}, {}, {})", self.i(), self.j(), self.w())
    }
}

/// Similarity `w` of docs/method.md#step-7-cluster. The longer segment is `a` when the
/// lengths are equal, so callers pass pairs in a fixed order (`i < j`) to get a repeatable value.
pub fn similarity(a: &Segment, b: &Segment, r_c: f64, fix_distance: bool, min_cos: f64) -> f64 {
    let ends = [(a, a.length(), a.dir()), (b, b.length(), b.dir())];
    similarity_of(ends, r_c, fix_distance, min_cos, 0.0)
}

/// [`similarity`] of two segments given with their lengths and directions; 0 as soon as
/// `dist_w < min_dist_w` (then `w <= dist_w` is below it too), before the `tanh`.
fn similarity_of(
    [(a, la, da), (b, lb, db)]: [(&Segment, f64, DVec3); 2],
    r_c: f64,
    fix_distance: bool,
    min_cos: f64,
    min_dist_w: f64,
) -> f64 {
    let (long, short, l_long, l_short, d, ds) = if la >= lb {
        (a, b, la, lb, da, db)
    } else {
        (b, a, lb, la, db, da)
    };
    let cos = d.dot(ds).clamp(-1.0, 1.0).abs();
    if cos <= min_cos {
        return 0.0;
    }
    let dist = pair_distance(long, short, d, l_long, fix_distance);
    let x = dist / r_c;
    let dist_w = 1.0 / (1.0 + 2.0 * x * x);
    if dist_w < min_dist_w {
        return 0.0;
    }
    let ratio = l_long / l_short;
    let len_w = (ratio * ratio * cos).tanh();
    dist_w * len_w
}

/// `dist` of step 7 between the longer segment (direction `d`, length `l_long`) and the
/// shorter one.
fn pair_distance(long: &Segment, short: &Segment, d: DVec3, l_long: f64, fix: bool) -> f64 {
    let t = [(short.p1 - long.p1).dot(d), (short.p2 - long.p1).dot(d)];
    if t.iter().any(|&t| 0.0 < t && t < l_long) {
        // Overlap: the nearer of the shorter's endpoints to the longer's (infinite) line.
        long.line_dist2(short.p1)
            .min(long.line_dist2(short.p2))
            .sqrt()
    } else if fix {
        long.distance_to(short)
    } else {
        // The authors' gap: along the longer's axis only, lateral offset ignored.
        t.iter()
            .flat_map(|&t| [t.abs(), (t - l_long).abs()])
            .fold(f64::INFINITY, f64::min)
    }
}

/// Largest `dist` an edge can have: `dist_w >= w_min` (because `len_w < 1`). `None` when
/// every pair can be an edge (`w_min <= 0`).
fn distance_bound(r_c: f64, min_weight: f64) -> Option<f64> {
    if min_weight <= 0.0 {
        return None;
    }
    let b = r_c * ((1.0 / min_weight - 1.0) / 2.0).max(0.0).sqrt();
    // Slack so that rounding in `similarity` can never put an edge just outside the bound.
    b.is_finite().then_some(b * (1.0 + 1e-9) + 1e-12)
}

/// Most edges a segment keeps to the segments it is the longer member of (its
/// neighbours): the [`MAX_NEIGHBOURS`] most similar (highest `w`, ties to the lower
/// index). Real line sets have a few to about a hundred (the Line3D++ test set at
/// r = 0.2: 16 on average, 103 at most); only inputs far denser than the
/// radius (10^5 short segments on the edges of a unit box) reach it, where all their
/// edges took quadratic time and memory (10^8 edges, 2.6 GB for 10^5 segments).
pub const MAX_NEIGHBOURS: usize = 128;

/// Every edge `w >= p.cluster_min_weight` between segments of different input lines,
/// sorted ascending by `w` (ties in `(i, j)` order, which is what a stable sort of the
/// all-pairs loop gives). With the fixed distance, a segment keeps at most
/// [`MAX_NEIGHBOURS`] edges to the segments it is the longer of.
pub fn edges(lines: &LineSet, s: &Settings) -> Result<Vec<Edge>, EngineError> {
    let (r_c, p, fixes) = (s.radius(), &s.params().cluster, s.fixes());
    let bound = distance_bound(r_c, p.cluster_min_weight);
    let limit = edge_limit(lines.len());
    let e = match bound {
        // At most MAX_NEIGHBOURS <= MAX_EDGES_PER_SEGMENT a segment.
        Some(b) if fixes.cluster_distance && lines.len() > 1 => Some(edges_hashed(
            lines,
            r_c,
            b,
            p.cluster_min_weight,
            p.cluster_min_cos,
            MAX_NEIGHBOURS,
        )),
        Some(b) if lines.len() > 1 => edges_reference_within(
            lines,
            r_c,
            b,
            p.cluster_min_weight,
            p.cluster_min_cos,
            limit,
        ),
        _ => edges_all_pairs_within(
            lines,
            r_c,
            fixes.cluster_distance,
            p.cluster_min_weight,
            p.cluster_min_cos,
            limit,
        ),
    };
    let Some(mut e) = e else {
        return Err(EngineError::Limit(format!(
            "step 7 (cluster) needs more than {limit} similarity edges for {} segments, and \
             it holds at most {MAX_EDGES_PER_SEGMENT} a segment ({} bytes each, so at most \
             {:.1} MB here): the segments are too dense for the radius {r_c} under the \
             {}; try a smaller --radius, a higher --cluster-min-weight, or --profile \
             default (it keeps the {MAX_NEIGHBOURS} most similar neighbours a segment)",
            lines.len(),
            std::mem::size_of::<Edge>(),
            (limit * std::mem::size_of::<Edge>()) as f64 / 1e6,
            if fixes.cluster_distance {
                "3D distance"
            } else {
                "authors' distance, which links near-parallel segments that end near each \
                 other however far apart they are across their axis"
            },
        )));
    };
    e.par_sort_unstable();
    Ok(e)
}

/// Most similarity edges step 7 holds, on average a segment: the edges take 16 bytes
/// each, so the step's edge list never passes 16 KiB a segment (16 MiB for inputs of
/// up to 1,024 segments, see [`edge_limit`]). Real line sets have a few to about a
/// hundred a segment; the `default` profile keeps at most [`MAX_NEIGHBOURS`]. A run
/// that needs more ends with [`EngineError::Limit`] (exit code 1) while the edges are
/// being found, before they are sorted or clustered.
pub const MAX_EDGES_PER_SEGMENT: usize = 1024;

/// Most edges step 7 holds for `n` segments: [`MAX_EDGES_PER_SEGMENT`] a segment, and
/// no fewer than 2^20.
pub fn edge_limit(n: usize) -> usize {
    n.saturating_mul(MAX_EDGES_PER_SEGMENT).max(1 << 20)
}

/// Every pair `i < j`, in parallel over `i` (the result is in `(i, j)` order).
fn edges_all_pairs(lines: &LineSet, r_c: f64, fix: bool, min_w: f64, min_cos: f64) -> Vec<Edge> {
    edges_all_pairs_within(lines, r_c, fix, min_w, min_cos, usize::MAX).expect("no limit to pass")
}

/// [`edges_all_pairs`], or `None` as soon as there are more than `limit` edges.
fn edges_all_pairs_within(
    lines: &LineSet,
    r_c: f64,
    fix: bool,
    min_w: f64,
    min_cos: f64,
    limit: usize,
) -> Option<Vec<Edge>> {
    let segs = &lines.segments;
    let count = AtomicUsize::new(0);
    let rows: Vec<Vec<Edge>> = (0..segs.len())
        .into_par_iter()
        .map(|i| {
            if count.load(Relaxed) > limit {
                return Vec::new();
            }
            let row: Vec<Edge> = (i + 1..segs.len())
                .filter_map(|j| {
                    if lines.group(i) == lines.group(j) {
                        return None;
                    }
                    let w = similarity(&segs[i], &segs[j], r_c, fix, min_cos);
                    (w >= min_w).then(|| Edge::new(i, j, w))
                })
                .collect();
            count.fetch_add(row.len(), Relaxed);
            row
        })
        .collect();
    if count.into_inner() > limit {
        return None;
    }
    Some(rows.concat())
}

/// Most cells of the segment grid (a `u32` start per cell): 16 MiB of table.
const MAX_CELLS: f64 = (1u64 << 22) as f64;

/// Most cells of the candidate grid per segment.
const CELLS_PER_SEGMENT: f64 = 64.0;

/// A uniform grid of cubic cells over the segments' box, numbered x-fastest.
struct CellGrid {
    origin: DVec3,
    h: f64,
    dims: [i64; 3],
}

impl CellGrid {
    /// Cells of edge `h` or larger, so that there are at most `max_cells`.
    fn new(lo: DVec3, hi: DVec3, mut h: f64, max_cells: f64) -> Self {
        loop {
            let span = (hi - lo) / h;
            let dims = [
                span.x.ceil() as i64 + 1,
                span.y.ceil() as i64 + 1,
                span.z.ceil() as i64 + 1,
            ];
            if (dims[0] as f64) * (dims[1] as f64) * (dims[2] as f64) <= max_cells {
                return CellGrid {
                    origin: lo,
                    h,
                    dims,
                };
            }
            h *= 1.25;
        }
    }

    fn n_cells(&self) -> usize {
        (self.dims[0] * self.dims[1] * self.dims[2]) as usize
    }

    fn key(&self, c: [i64; 3]) -> u32 {
        (c[0] + self.dims[0] * (c[1] + self.dims[1] * c[2])) as u32
    }

    /// Every cell that holds a point within `radius` of segment `[a, b]` (a superset),
    /// each once. A point within `radius` of the segment lies in a cell whose center is
    /// within `keep = radius + sqrt(3)/2 h` of it; those centers are found piece by piece
    /// (pieces of about `2h`, each scanning the cells of its box grown by `keep`), and a
    /// center belongs to the piece that holds its closest point on the segment, so no cell
    /// comes twice and no sort is needed.
    fn cells(&self, a: DVec3, b: DVec3, radius: f64, out: &mut Vec<u32>) {
        out.clear();
        let ab = b - a;
        let l2 = ab.length_squared();
        let n = ((l2.sqrt() / (2.0 * self.h)).ceil() as usize).max(1);
        let keep = radius + 0.87 * self.h;
        let keep2 = keep * keep;
        let grow = DVec3::splat(keep * (1.0 + 1e-9));
        for k in 0..n {
            let (t0, t1) = (k as f64 / n as f64, (k + 1) as f64 / n as f64);
            let (pa, pb) = (a + ab * t0, a + ab * t1);
            let lo = self.center_index(pa.min(pb) - grow, f64::ceil);
            let hi = self.center_index(pa.max(pb) + grow, f64::floor);
            for z in lo[2]..=hi[2] {
                for y in lo[1]..=hi[1] {
                    for x in lo[0]..=hi[0] {
                        let c = self.origin
                            + DVec3::new(x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5) * self.h;
                        let t = if l2 > 0.0 {
                            ((c - a).dot(ab) / l2).clamp(0.0, 1.0)
                        } else {
                            0.0
                        };
                        let mine = (k == 0 || t >= t0) && (k + 1 == n || t < t1);
                        if mine && (a + ab * t - c).length_squared() <= keep2 {
                            out.push(self.key([x, y, z]));
                        }
                    }
                }
            }
        }
    }

    /// The cells of the box of segment `[a, b]` (a superset of those it passes through)
    /// when they are at most `most`, else [`CellGrid::cells`] with radius 0.
    fn cells_on(&self, a: DVec3, b: DVec3, most: i64, out: &mut Vec<u32>) {
        let cell = |p: DVec3| {
            let q = (p - self.origin) / self.h;
            [q.x, q.y, q.z]
                .map(|v| v.floor().max(0.0) as i64)
                .into_iter()
                .zip(self.dims)
                .map(|(v, n)| v.min(n - 1))
                .collect::<Vec<i64>>()
        };
        let (lo, hi) = (cell(a.min(b)), cell(a.max(b)));
        let count: i64 = (0..3).map(|k| hi[k] - lo[k] + 1).product();
        if count > most {
            return self.cells(a, b, 0.0, out);
        }
        out.clear();
        for z in lo[2]..=hi[2] {
            for y in lo[1]..=hi[1] {
                for x in lo[0]..=hi[0] {
                    out.push(self.key([x, y, z]));
                }
            }
        }
    }

    /// Index of the cell whose center is the first (`ceil`) or last (`floor`) at or past
    /// `p`, clamped to the grid (no capsule reaches outside it).
    fn center_index(&self, p: DVec3, round: fn(f64) -> f64) -> [i64; 3] {
        let q = (p - self.origin) / self.h - DVec3::splat(0.5);
        let f = |v: f64, n: i64| (round(v).max(0.0) as i64).min(n - 1);
        [
            f(q.x, self.dims[0]),
            f(q.y, self.dims[1]),
            f(q.z, self.dims[2]),
        ]
    }
}
/// The part of segment `[a, b]` inside the box `[lo, hi]` (slab clipping); `None` if none.
fn clip(a: DVec3, b: DVec3, lo: DVec3, hi: DVec3) -> Option<(DVec3, DVec3)> {
    let d = b - a;
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for k in 0..3 {
        if d[k] == 0.0 {
            if a[k] < lo[k] || a[k] > hi[k] {
                return None;
            }
        } else {
            let u = (lo[k] - a[k]) / d[k];
            let v = (hi[k] - a[k]) / d[k];
            t0 = t0.max(u.min(v));
            t1 = t1.min(u.max(v));
        }
    }
    (t0 <= t1).then(|| (a + d * t0, a + d * t1))
}

/// What the candidate loop reads of a segment, in one place (one cache line or two).
struct Packed {
    seg: Segment,
    dir: DVec3,
    len: f64,
    group: u32,
    /// Index in the line set.
    orig: u32,
}

/// The most similar edges of one segment `G` to the shorter segments (at most `most`,
/// highest `w` first, ties to the lower other index), kept while its candidates are read,
/// and what that set prunes: once it is full, a candidate whose `w` cannot reach its
/// weakest member (`w_min`, strictly below it) cannot enter it. `w = dist_w x len_w`
/// with `dist_w <= 1` and `len_w = tanh(ratio^2 cos) <= tanh(ratio^2)`, so a candidate
/// is left out when `tanh((L_G / L_S)^2) < w_min` (its length) or when a lower bound of
/// its `dist` gives `dist_w < w_min` (its place); both tests keep a margin for rounding.
struct Kept {
    most: usize,
    min_w: f64,
    r_c: f64,
    /// Min-heap of `(w bits, u32::MAX - other)`: the weakest member on top.
    heap: std::collections::BinaryHeap<std::cmp::Reverse<(u64, u32)>>,
    /// When full: `atanh(w_min)` (a length ratio whose square is below it fails) and the
    /// `dist` above which `dist_w < w_min`.
    ratio2_cut: f64,
    dist_cut: f64,
}

impl Kept {
    fn new(most: usize, min_w: f64, r_c: f64) -> Self {
        Kept {
            most,
            min_w,
            r_c,
            heap: Default::default(),
            ratio2_cut: 0.0,
            dist_cut: f64::INFINITY,
        }
    }

    fn clear(&mut self) {
        self.heap.clear();
        (self.ratio2_cut, self.dist_cut) = (0.0, f64::INFINITY);
    }

    /// Takes the edge to `other` of weight `w >= min_w` if it is among the most similar.
    fn offer(&mut self, w: f64, other: u32) {
        let key = (w.to_bits(), u32::MAX - other);
        if self.heap.len() < self.most {
            self.heap.push(std::cmp::Reverse(key));
        } else if self.heap.peek().is_some_and(|t| key > t.0) {
            self.heap.pop();
            self.heap.push(std::cmp::Reverse(key));
        } else {
            return;
        }
        if self.heap.len() == self.most {
            let weakest = f64::from_bits(self.heap.peek().expect("full").0 .0);
            // Only weights below 1 prune (`tanh` and the product can round to 1).
            if weakest > self.min_w && weakest < 1.0 {
                self.ratio2_cut = weakest.atanh() * (1.0 - 1e-9);
                self.dist_cut = self.r_c * ((1.0 / weakest - 1.0) / 2.0).sqrt() * (1.0 + 1e-9);
            }
        }
    }

    /// The shorter segment (length `l_s <= l_g`) is too long for any later candidate
    /// of its cell to enter: `tanh((l_g / l_s)^2) < w_min`.
    fn too_long(&self, l_g: f64, l_s: f64) -> bool {
        let ratio = l_g / l_s;
        ratio * ratio < self.ratio2_cut
    }

    /// A lower bound of `dist` (the 3D distance, or the line distance of an endpoint when
    /// they overlap) puts `dist_w` below `w_min`. From `S`'s midpoint `m`: an endpoint is
    /// within `L_S / 2` of it, so with `m` at `t` along `G`'s axis and `lat` off it, an
    /// overlap has `|t - clamp(t, 0, L_G)| <= L_S / 2` and `dist >= lat - L_S / 2`, and
    /// otherwise `dist >= |m - G| - L_S / 2`. Only where `similarity` takes `G` as the
    /// longer (on equal lengths it takes the lower index, and `S`'s axis would count).
    fn too_far(&self, g: &Packed, s: &Packed, slack: f64) -> bool {
        if self.dist_cut == f64::INFINITY || (s.len >= g.len && s.orig < g.orig) {
            return false;
        }
        let m = (s.seg.p1 + s.seg.p2) * 0.5;
        let v = m - g.seg.p1;
        let t = v.dot(g.dir);
        let along = (-t).max(t - g.len).max(0.0);
        let lat = v.cross(g.dir).length();
        let half = 0.5 * s.len;
        let d = if along > half {
            (lat * lat + along * along).sqrt()
        } else {
            lat
        };
        d - half - slack > self.dist_cut
    }
}

/// Candidate pairs from a spatial hash, then the exact test.
///
/// Why it finds every edge: let `G` be the longer of an edge (the one `similarity` calls
/// long) and `S` the shorter, `dist <= B`. If an endpoint of `S` projects inside `G`,
/// `dist` is the distance of an endpoint `q` of `S` to `G`'s infinite line, and `q`
/// projects within `L_S <= L_G` of `G`'s ends (the other endpoint is inside), so `q` is
/// within `B` of `G` extended by `L_G` at both ends (`G_ext`). Otherwise `dist` is the 3D
/// distance from `S` to `G`, so `S` is again within `B` of `G_ext`: a point of `S` within
/// `B` of `G_ext` lies in a cell of `G_ext`'s `B`-capsule, and `S` is listed in every cell
/// it passes through. Each segment is hashed by the cells on it (a few, so a pair is
/// seen a few times, not tens) and queried with its extended capsule; a pair is tested
/// from its longer member only, so every edge is found exactly once. Each keeps its
/// [`MAX_NEIGHBOURS`] most similar edges (`max_neighbours`).
///
/// What keeps it fast on dense inputs: the segments are renumbered in grid order, so the
/// candidates of neighbouring segments are neighbours in memory; each cell lists its
/// segments by rank (length, then index, so that a pair's longer member has the higher
/// rank) and a query stops reading a cell at its own rank; the edges take 16 bytes.
fn edges_hashed(
    lines: &LineSet,
    r_c: f64,
    bound: f64,
    min_w: f64,
    min_cos: f64,
    max_neighbours: usize,
) -> Vec<Edge> {
    let segs = &lines.segments;
    let n = segs.len();
    let mut lo = DVec3::splat(f64::INFINITY);
    let mut hi = DVec3::splat(f64::NEG_INFINITY);
    let mut total_len = 0.0;
    for s in segs {
        lo = lo.min(s.p1).min(s.p2);
        hi = hi.max(s.p1).max(s.p2);
        total_len += s.length();
    }
    if !(lo.is_finite() && hi.is_finite() && total_len.is_finite() && total_len > 0.0) {
        // Invalid segments are dropped at load; should one get here, no grid is needed.
        return edges_all_pairs(lines, r_c, true, min_w, min_cos);
    }
    // Cells near the bound, but no finer than a quarter of the mean length, which keeps
    // the samples per segment bounded.
    let h = bound.max(total_len / n as f64 / 4.0);
    let margin = DVec3::splat(bound + 2.0 * h);
    let (lo, hi) = (lo - margin, hi + margin);
    if !(lo.is_finite() && hi.is_finite()) {
        // A radius near f64's range (`--radius 1e308`): no grid spans it, and every pair
        // is a candidate anyway.
        return edges_all_pairs(lines, r_c, true, min_w, min_cos);
    }
    // At most CELLS_PER_SEGMENT cells a segment (and MAX_CELLS): the cell table is
    // allocated and scanned whole, and a few hundred segments in a wide scene would
    // otherwise pay for millions of empty cells (12 ms of a 0.13 s run at 318 segments).
    // Coarser cells change only how many candidates a query meets, never the edges.
    let most = MAX_CELLS.min((CELLS_PER_SEGMENT * n as f64).max(4096.0));
    let grid = CellGrid::new(lo, hi, h, most);

    // Segments in grid order (the cell of the midpoint, then the index): `pk[k]`.
    let mut order: Vec<(u32, u32)> = (0..n)
        .into_par_iter()
        .map(|i| {
            let m = (segs[i].p1 + segs[i].p2) * 0.5;
            let c = ((m - grid.origin) / grid.h).floor().as_i64vec3();
            let c = [c.x, c.y, c.z].map(|v| v.max(0));
            let c = [0, 1, 2].map(|k| c[k].min(grid.dims[k] - 1));
            (grid.key(c), i as u32)
        })
        .collect();
    order.par_sort_unstable();
    let pk: Vec<Packed> = order
        .par_iter()
        .map(|&(_, i)| {
            let seg = segs[i as usize];
            Packed {
                seg,
                dir: seg.dir(),
                len: seg.length(),
                group: lines.group(i as usize),
                orig: i,
            }
        })
        .collect();
    drop(order);
    // rank[k]: position by length, then by index downwards. The longer member of a pair
    // (`similarity` calls the lower index long on equal lengths) has the higher rank.
    let mut by_rank: Vec<u32> = (0..n as u32).collect();
    by_rank.par_sort_unstable_by(|&a, &b| {
        let (a, b) = (&pk[a as usize], &pk[b as usize]);
        a.len.total_cmp(&b.len).then(b.orig.cmp(&a.orig))
    });
    let mut rank = vec![0u32; n];
    for (r, &k) in by_rank.iter().enumerate() {
        rank[k as usize] = r as u32;
    }

    // The cells each segment passes through, as a counting-sorted table: cell c holds
    // members[start[c]..start[c+1]], each `rank << 32 | k`, by rank.
    let cells_of: Vec<Vec<u32>> = pk
        .par_iter()
        .map_init(Vec::new, |cells, p| {
            grid.cells_on(p.seg.p1, p.seg.p2, 8, cells);
            cells.clone()
        })
        .collect();
    let mut start = vec![0u32; grid.n_cells() + 1];
    for cells in &cells_of {
        for &c in cells {
            start[c as usize + 1] += 1;
        }
    }
    for c in 0..grid.n_cells() {
        start[c + 1] += start[c];
    }
    let mut fill = start.clone();
    let mut members = vec![0u64; start[grid.n_cells()] as usize];
    for &k in &by_rank {
        for &c in &cells_of[k as usize] {
            members[fill[c as usize] as usize] = (u64::from(rank[k as usize]) << 32) | u64::from(k);
            fill[c as usize] += 1;
        }
    }
    drop((cells_of, fill, by_rank));

    // Chunks of segments share one scratch mark array (n entries) for deduplication.
    let chunk = (n / (8 * rayon::current_num_threads())).clamp(256, 1 << 14);
    // Rounding slack of the pruning bounds (see `Kept`), in the scene's units.
    let slack = 1e-9 * (1.0 + lo.abs().max_element().max(hi.abs().max_element()));
    let parts: Vec<Vec<Edge>> = (0..n.div_ceil(chunk))
        .into_par_iter()
        .map(|c| {
            let mut seen = vec![u32::MAX; n];
            let mut cells = Vec::new();
            let mut near: Vec<(f64, u32)> = Vec::new();
            let mut kept = Kept::new(max_neighbours, min_w, r_c);
            let mut out = Vec::new();
            for g in c * chunk..((c + 1) * chunk).min(n) {
                let pg = &pk[g];
                let s = &pg.seg;
                let ext = pg.dir * pg.len;
                let Some((a, b)) = clip(s.p1 - ext, s.p2 + ext, lo, hi) else {
                    continue;
                };
                grid.cells(a, b, bound, &mut cells);
                // The nearest cells first, so that the kept set's weakest weight rises
                // early and prunes the rest.
                near.clear();
                near.extend(cells.iter().map(|&cell| {
                    let k = cell as i64;
                    let (x, y, z) = (
                        k % grid.dims[0],
                        (k / grid.dims[0]) % grid.dims[1],
                        k / (grid.dims[0] * grid.dims[1]),
                    );
                    let ctr = grid.origin
                        + DVec3::new(x as f64 + 0.5, y as f64 + 0.5, z as f64 + 0.5) * grid.h;
                    (point_segment_distance(ctr, (s.p1, s.p2)), cell)
                }));
                near.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                kept.clear();
                let below = u64::from(rank[g]) << 32;
                for &(_, cell) in &near {
                    let range = start[cell as usize] as usize..start[cell as usize + 1] as usize;
                    for &m in &members[range] {
                        if m >= below {
                            break; // the rest are longer: `g` is not their pair's long one
                        }
                        let o = m as u32;
                        if seen[o as usize] == g as u32 {
                            continue;
                        }
                        seen[o as usize] = g as u32;
                        let po = &pk[o as usize];
                        // The cell lists its segments shortest first: once the length
                        // alone cannot reach the kept set, no later one in it can.
                        if kept.too_long(pg.len, po.len) {
                            break;
                        }
                        if po.group == pg.group || kept.too_far(pg, po, slack) {
                            continue;
                        }
                        let (pi, pj) = if pg.orig < po.orig {
                            (pg, po)
                        } else {
                            (po, pg)
                        };
                        let w = similarity_of(
                            [(&pi.seg, pi.len, pi.dir), (&pj.seg, pj.len, pj.dir)],
                            r_c,
                            true,
                            min_cos,
                            min_w,
                        );
                        if w >= min_w {
                            kept.offer(w, po.orig);
                        }
                    }
                }
                let me = pg.orig as usize;
                out.extend(kept.heap.iter().map(|&std::cmp::Reverse((w, o))| {
                    let o = (u32::MAX - o) as usize;
                    Edge::new(me.min(o), me.max(o), f64::from_bits(w))
                }));
            }
            out
        })
        .collect();
    drop((members, start, pk, rank));
    // One copy of the edges at a time: each part is freed once copied.
    let mut all = Vec::with_capacity(parts.iter().map(Vec::len).sum());
    for p in parts {
        all.extend_from_slice(&p);
    }
    all
}

/// Entries of `d d^T` for a unit direction `d`: `(d . g)^2` is linear in them for any `g`.
fn moments(d: DVec3) -> [f64; 6] {
    [
        d.x * d.x,
        d.y * d.y,
        d.z * d.z,
        d.x * d.y,
        d.x * d.z,
        d.y * d.z,
    ]
}

/// A node of [`EndTree`]: the box of its endpoints, the range of each of [`moments`] over
/// their segments' directions, the lowest rank among those segments, and its children
/// (`u32::MAX` for a leaf) or, in a leaf, its points `start..end`.
struct EndNode {
    lo: DVec3,
    hi: DVec3,
    m_lo: [f64; 6],
    m_hi: [f64; 6],
    min_rank: u32,
    start: u32,
    end: u32,
    left: u32,
    right: u32,
}

/// Most points of a leaf of [`EndTree`].
const END_LEAF: usize = 8;

/// A k-d tree over the endpoints of the segments (each point with its segment), split at
/// the median of the widest axis; a node knows enough of its segments (directions, ranks)
/// to be skipped whole by a query that none of them can answer.
struct EndTree {
    nodes: Vec<EndNode>,
    points: Vec<(DVec3, u32)>,
}

impl EndTree {
    fn new(points: Vec<(DVec3, u32)>, m: &[[f64; 6]], rank: &[u32]) -> Self {
        let n = points.len();
        let mut t = EndTree {
            nodes: Vec::with_capacity(2 * n.div_ceil(END_LEAF) + 1),
            points,
        };
        t.build(0, n, m, rank);
        t
    }

    fn build(&mut self, start: usize, end: usize, m: &[[f64; 6]], rank: &[u32]) -> u32 {
        let pts = &mut self.points[start..end];
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        let (mut m_lo, mut m_hi) = ([f64::INFINITY; 6], [f64::NEG_INFINITY; 6]);
        let mut min_rank = u32::MAX;
        for &(p, s) in pts.iter() {
            lo = lo.min(p);
            hi = hi.max(p);
            let ms = &m[s as usize];
            for k in 0..6 {
                m_lo[k] = m_lo[k].min(ms[k]);
                m_hi[k] = m_hi[k].max(ms[k]);
            }
            min_rank = min_rank.min(rank[s as usize]);
        }
        let id = self.nodes.len();
        self.nodes.push(EndNode {
            lo,
            hi,
            m_lo,
            m_hi,
            min_rank,
            start: start as u32,
            end: end as u32,
            left: u32::MAX,
            right: u32::MAX,
        });
        if end - start > END_LEAF {
            let e = hi - lo;
            let axis = if e.x >= e.y && e.x >= e.z {
                0
            } else if e.y >= e.z {
                1
            } else {
                2
            };
            let mid = (end - start) / 2;
            pts.select_nth_unstable_by(mid, |a, b| a.0[axis].total_cmp(&b.0[axis]));
            let left = self.build(start, start + mid, m, rank);
            let right = self.build(start + mid, end, m, rank);
            self.nodes[id].left = left;
            self.nodes[id].right = right;
        }
        id as u32
    }
}

/// What a segment `G` asks the [`EndTree`] under the authors' distance: the endpoints of
/// shorter segments (lower rank) near enough in direction (`cos > min_cos`) that lie
/// where an edge's `dist <= B` puts one of them.
///
/// Why that finds every edge of `G` as the longer member (`t`: an endpoint's position
/// along `G`'s axis from `G.p1`, `L`: lengths): if an endpoint of the shorter `S` has
/// `0 < t < L_G` (overlap), `dist` is the distance of an endpoint to `G`'s line and both
/// endpoints have `-L_S < t < L_G + L_S`, so that endpoint is within `B` of `G` extended
/// by `L_G` at both ends; otherwise `dist` is the least of `|t|` and `|t - L_G|` over
/// both endpoints, so one lies in the slab of width `2B` around the plane through an
/// end of `G` across its axis. The slabs have no lateral bound (the authors' gap ignores
/// the lateral offset), which is why the tree also skips nodes by direction: `(d_G .
/// d_S)^2` is linear in [`moments`] of `d_S`, so a node's ranges bound it.
struct EndQuery {
    p1: DVec3,
    d: DVec3,
    len: f64,
    /// `G` extended by its length at both ends.
    ext: (DVec3, DVec3),
    /// `B` with slack for rounding.
    reach: f64,
    coef: [f64; 6],
    /// Below this bound of `cos^2` no pair passes (`-1`: no angle gate).
    min_cos2: f64,
    rank: u32,
}

impl EndQuery {
    fn node_may(&self, n: &EndNode) -> bool {
        if n.min_rank >= self.rank {
            return false;
        }
        let mut ub = 0.0;
        for k in 0..6 {
            let c = self.coef[k];
            ub += c * if c >= 0.0 { n.m_hi[k] } else { n.m_lo[k] };
        }
        if ub < self.min_cos2 {
            return false;
        }
        let c = (n.lo + n.hi) * 0.5;
        let e = (n.hi - n.lo) * 0.5;
        let tc = (c - self.p1).dot(self.d);
        let ht = e.dot(self.d.abs()) + self.reach;
        tc.abs() <= ht
            || (tc - self.len).abs() <= ht
            || point_segment_distance(c, self.ext) <= self.reach + e.length()
    }

    fn point_may(&self, p: DVec3) -> bool {
        let t = (p - self.p1).dot(self.d);
        t.abs() <= self.reach
            || (t - self.len).abs() <= self.reach
            || point_segment_distance(p, self.ext) <= self.reach
    }
}

fn point_segment_distance(p: DVec3, (a, b): (DVec3, DVec3)) -> f64 {
    let ab = b - a;
    let l2 = ab.length_squared();
    let t = if l2 > 0.0 {
        ((p - a).dot(ab) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (a + ab * t - p).length()
}

/// Every edge under the authors' distance (`reference`), the same as
/// [`edges_all_pairs`] gives, from an [`EndTree`] of the endpoints: each segment asks for
/// the shorter segments that can be its pair ([`EndQuery`]), so a pair is tested from its
/// longer member only, and every edge is kept (no neighbour bound: the step's decisions
/// are the authors'). The cost follows the candidates: pairs within `B` of each other,
/// and near-parallel pairs that end within `B` of each other along the longer's axis
/// wherever they are across it, which the authors' distance makes edges.
#[cfg(test)]
fn edges_reference(lines: &LineSet, r_c: f64, bound: f64, min_w: f64, min_cos: f64) -> Vec<Edge> {
    edges_reference_within(lines, r_c, bound, min_w, min_cos, usize::MAX).expect("no limit to pass")
}

/// [`edges_reference`], or `None` as soon as there are more than `limit` edges.
fn edges_reference_within(
    lines: &LineSet,
    r_c: f64,
    bound: f64,
    min_w: f64,
    min_cos: f64,
    limit: usize,
) -> Option<Vec<Edge>> {
    let segs = &lines.segments;
    let n = segs.len();
    let mut scale = 0.0f64;
    for s in segs {
        scale = scale
            .max(s.p1.abs().max_element())
            .max(s.p2.abs().max_element());
    }
    if !scale.is_finite() {
        // Invalid segments are dropped at load; should one get here, no tree is needed.
        return edges_all_pairs_within(lines, r_c, false, min_w, min_cos, limit);
    }
    let dir: Vec<DVec3> = segs.par_iter().map(Segment::dir).collect();
    let len: Vec<f64> = segs.par_iter().map(Segment::length).collect();
    // rank: position by length, then by index downwards, so that the longer member of a
    // pair (`similarity` calls the lower index long on equal lengths) has the higher rank.
    let mut by_rank: Vec<u32> = (0..n as u32).collect();
    by_rank
        .par_sort_unstable_by(|&a, &b| len[a as usize].total_cmp(&len[b as usize]).then(b.cmp(&a)));
    let mut rank = vec![0u32; n];
    for (r, &k) in by_rank.iter().enumerate() {
        rank[k as usize] = r as u32;
    }
    drop(by_rank);
    let m: Vec<[f64; 6]> = dir.iter().map(|&d| moments(d)).collect();
    let points: Vec<(DVec3, u32)> = (0..n)
        .flat_map(|k| [(segs[k].p1, k as u32), (segs[k].p2, k as u32)])
        .collect();
    let tree = EndTree::new(points, &m, &rank);
    drop(m);
    // Queries in tree order, so that neighbouring queries read neighbouring nodes.
    let mut placed = vec![false; n];
    let order: Vec<u32> = tree
        .points
        .iter()
        .filter_map(|&(_, k)| (!std::mem::replace(&mut placed[k as usize], true)).then_some(k))
        .collect();
    drop(placed);
    let reach = bound + 1e-9 * (1.0 + scale);
    let min_cos2 = if min_cos > 0.0 {
        min_cos * min_cos * (1.0 - 1e-9)
    } else {
        -1.0
    };
    let chunk = (n / (8 * rayon::current_num_threads())).clamp(256, 1 << 14);
    let count = AtomicUsize::new(0);
    let parts: Vec<Vec<Edge>> = order
        .par_chunks(chunk)
        .map(|ks| {
            let mut seen = vec![u32::MAX; n];
            let mut stack: Vec<u32> = Vec::new();
            let mut cands: Vec<u32> = Vec::new();
            let mut out = Vec::new();
            for &g in ks {
                if count.load(Relaxed) > limit {
                    break;
                }
                let before = out.len();
                let (gs, d, l) = (&segs[g as usize], dir[g as usize], len[g as usize]);
                let q = EndQuery {
                    p1: gs.p1,
                    d,
                    len: l,
                    ext: (gs.p1 - d * l, gs.p2 + d * l),
                    reach,
                    coef: [
                        d.x * d.x,
                        d.y * d.y,
                        d.z * d.z,
                        2.0 * d.x * d.y,
                        2.0 * d.x * d.z,
                        2.0 * d.y * d.z,
                    ],
                    min_cos2,
                    rank: rank[g as usize],
                };
                cands.clear();
                stack.clear();
                stack.push(0);
                while let Some(id) = stack.pop() {
                    let node = &tree.nodes[id as usize];
                    if !q.node_may(node) {
                        continue;
                    }
                    if node.left != u32::MAX {
                        stack.extend([node.right, node.left]);
                        continue;
                    }
                    for &(p, o) in &tree.points[node.start as usize..node.end as usize] {
                        if rank[o as usize] < q.rank && seen[o as usize] != g && q.point_may(p) {
                            seen[o as usize] = g;
                            cands.push(o);
                        }
                    }
                }
                for &o in &cands {
                    let (i, j) = (g.min(o) as usize, g.max(o) as usize);
                    if lines.group(i) == lines.group(j) {
                        continue;
                    }
                    let w = similarity_of(
                        [(&segs[i], len[i], dir[i]), (&segs[j], len[j], dir[j])],
                        r_c,
                        false,
                        min_cos,
                        min_w,
                    );
                    if w >= min_w {
                        out.push(Edge::new(i, j, w));
                    }
                }
                count.fetch_add(out.len() - before, Relaxed);
            }
            out
        })
        .collect();
    drop((tree, order, rank));
    if count.into_inner() > limit {
        return None;
    }
    let mut all = Vec::with_capacity(parts.iter().map(Vec::len).sum());
    for p in parts {
        all.extend_from_slice(&p);
    }
    Some(all)
}

/// Union-find by size with a threshold per root: edges (ascending) join two roots when
/// `w` is within both thresholds; the new root's threshold becomes `w + c / size`.
/// Returns the root of every segment.
fn union_find(n: usize, edges: &[Edge], c: f64) -> Vec<usize> {
    let mut parent: Vec<usize> = (0..n).collect();
    let mut size = vec![1usize; n];
    let mut thr = vec![c; n];
    fn find(parent: &mut [usize], mut x: usize) -> usize {
        while parent[x] != x {
            parent[x] = parent[parent[x]];
            x = parent[x];
        }
        x
    }
    for e in edges {
        let (w, ra, rb) = (e.w(), find(&mut parent, e.i()), find(&mut parent, e.j()));
        if ra == rb || w > thr[ra] || w > thr[rb] {
            continue;
        }
        let (big, small) = if size[ra] >= size[rb] {
            (ra, rb)
        } else {
            (rb, ra)
        };
        parent[small] = big;
        size[big] += size[small];
        thr[big] = w + c / size[big] as f64;
    }
    (0..n).map(|i| find(&mut parent, i)).collect()
}

/// The members of every cluster in greedy-matching order, [`greedy_order`] of each
/// cluster in one pass over the edges (ascending, as union-find took them) from the end:
/// a run of equal weights is taken in `(i, j)` order, so each cluster sees its own edges
/// in [`greedy_order`]'s order, and no cluster's edges are copied out.
fn greedy_orders(members: &[Vec<usize>], cluster_of: &[u32], edges: &[Edge]) -> Vec<Vec<usize>> {
    let mut placed = vec![false; cluster_of.len()];
    let mut order: Vec<Vec<usize>> = members
        .iter()
        .map(|m| Vec::with_capacity(m.len()))
        .collect();
    let mut end = edges.len();
    while end > 0 {
        let w = edges[end - 1].w().to_bits();
        let mut start = end - 1;
        while start > 0 && edges[start - 1].w().to_bits() == w {
            start -= 1;
        }
        for e in &edges[start..end] {
            let (i, j) = (e.i(), e.j());
            let c = cluster_of[i];
            if c == cluster_of[j] && !placed[i] && !placed[j] {
                placed[i] = true;
                placed[j] = true;
                order[c as usize].extend([i, j]);
            }
        }
        end = start;
    }
    for (order, m) in order.iter_mut().zip(members) {
        order.extend(m.iter().filter(|&&k| !placed[k]));
    }
    order
}

/// Clusters of step 7: every segment in exactly one cluster, clusters ordered by their
/// smallest member, members in greedy-matching order. Pairs only join segments of
/// different input lines.
///
/// Exact copies of one segment that no other segment is similar to, in two or more input
/// lines, form a cluster of their own, whose members step 8 all merges into the first:
/// such a group is set aside before the edges are built (its `m^2 / 2` edges would cost
/// quadratic time and memory) and comes back as one cluster, its first member in front as
/// the greedy order puts it, the others in index order (which step 8 cannot tell apart).
pub fn cluster(lines: &LineSet, s: &Settings) -> Result<Vec<Vec<usize>>, EngineError> {
    let copies = isolated_copies(lines, s)?;
    if copies.is_empty() {
        return cluster_all(lines, s);
    }
    let mut rest = vec![false; lines.len()];
    for c in &copies {
        for &k in &c[1..] {
            rest[k] = true;
        }
    }
    let keep: Vec<usize> = (0..lines.len()).filter(|&k| !rest[k]).collect();
    let mut out: Vec<Vec<usize>> = cluster_all(&lines.select(&keep), s)?
        .into_iter()
        .map(|c| c.into_iter().map(|k| keep[k]).collect())
        .collect();
    let mut cluster_of_first = vec![usize::MAX; lines.len()];
    for (ci, c) in out.iter().enumerate() {
        cluster_of_first[c[0]] = ci;
    }
    for c in copies {
        // The first copy has no edge left, so it is a cluster alone.
        let ci = cluster_of_first[c[0]];
        debug_assert_eq!(out[ci], vec![c[0]]);
        out[ci] = c;
    }
    Ok(out)
}

/// Groups (ascending indices, two or more) of bit-identical segments that step 7 puts in
/// a cluster of their own and step 8 merges into their first member: the segment has no
/// edge to any other distinct segment (tested in both pair orders, groups ignored), its
/// copies are similar to each other (`w >= w_min`) and lie in two or more input lines (so
/// union-find joins them all: every threshold stays above their common `w < 1`), and, when
/// merge results are ordered (`order_endpoints`), it is ordered already, so the merge of
/// two copies gives back the first one bit for bit (`G' = G`, tie keeps `G`).
fn isolated_copies(lines: &LineSet, st: &Settings) -> Result<Vec<Vec<usize>>, EngineError> {
    let (r_c, p, fixes) = (st.radius(), &st.params().cluster, st.fixes());
    let bits = |s: &Segment| {
        let (a, b) = (s.p1.to_array(), s.p2.to_array());
        [a[0], a[1], a[2], b[0], b[1], b[2]].map(f64::to_bits)
    };
    let mut slot = std::collections::HashMap::new();
    let mut same: Vec<Vec<usize>> = Vec::new();
    for (k, s) in lines.segments.iter().enumerate() {
        let id = *slot.entry(bits(s)).or_insert_with(|| {
            same.push(Vec::new());
            same.len() - 1
        });
        same[id].push(k);
    }
    if same.len() == lines.len() {
        return Ok(Vec::new());
    }
    let reps = LineSet::new(same.iter().map(|c| lines.segments[c[0]]).collect());
    let mut linked = vec![false; reps.len()];
    for e in edges(&reps, st)? {
        linked[e.i()] = true;
        linked[e.j()] = true;
    }
    let n = reps.len();
    let reversed = LineSet::new(reps.segments.iter().rev().copied().collect());
    for e in edges(&reversed, st)? {
        linked[n - 1 - e.i()] = true;
        linked[n - 1 - e.j()] = true;
    }
    Ok(same
        .into_iter()
        .zip(linked)
        .filter(|(c, linked)| {
            let s = &lines.segments[c[0]];
            let w = similarity(s, s, r_c, fixes.cluster_distance, p.cluster_min_cos);
            c.len() >= 2
                && !linked
                && w >= p.cluster_min_weight
                && c.iter().any(|&k| lines.group(k) != lines.group(c[0]))
                && (!fixes.order_endpoints || s.p1.length() <= s.p2.length())
        })
        .map(|(c, _)| c)
        .collect())
}

/// [`cluster`] without setting copies aside: the definition.
pub(crate) fn cluster_all(lines: &LineSet, s: &Settings) -> Result<Vec<Vec<usize>>, EngineError> {
    let n = lines.len();
    let p = &s.params().cluster;
    let edges = edges(lines, s)?;
    let root = union_find(n, &edges, p.cluster_c);
    let mut id_of_root = vec![usize::MAX; n];
    let mut members: Vec<Vec<usize>> = Vec::new();
    let mut cluster_of = vec![0u32; n];
    for i in 0..n {
        let r = root[i];
        if id_of_root[r] == usize::MAX {
            id_of_root[r] = members.len();
            members.push(Vec::new());
        }
        cluster_of[i] = id_of_root[r] as u32;
        members[id_of_root[r]].push(i);
    }
    drop((root, id_of_root));
    Ok(greedy_orders(&members, &cluster_of, &edges))
}

/// Members of one cluster in greedy-matching order, the definition of [`greedy_orders`]: pairs by descending weight (ties in `(i, j)` order),
/// a pair placed when neither member is yet; the rest in index order. `members` is
/// ascending; `edges` are the edges inside the cluster.
#[cfg(test)]
fn greedy_order(members: &[usize], edges: &[Edge]) -> Vec<usize> {
    let mut e = edges.to_vec();
    e.sort_by(|a, b| {
        b.w()
            .total_cmp(&a.w())
            .then((a.i(), a.j()).cmp(&(b.i(), b.j())))
    });
    let mut is_placed = vec![false; members.len()];
    let mut order = Vec::with_capacity(members.len());
    for ed in &e {
        let (Ok(a), Ok(b)) = (
            members.binary_search(&ed.i()),
            members.binary_search(&ed.j()),
        ) else {
            continue;
        };
        if !is_placed[a] && !is_placed[b] {
            is_placed[a] = true;
            is_placed[b] = true;
            order.push(ed.i());
            order.push(ed.j());
        }
    }
    for (k, &m) in members.iter().enumerate() {
        if !is_placed[k] {
            order.push(m);
        }
    }
    order
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::Params;

    fn seg(a: [f64; 3], b: [f64; 3]) -> Segment {
        Segment::from_arrays(a, b)
    }

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() <= 1e-12 * b.abs().max(1.0)
    }

    /// Deterministic LCG so the tests need no RNG crate.
    struct Lcg(u64);
    impl Lcg {
        fn f(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64) / ((1u64 << 53) as f64)
        }
        fn v(&mut self) -> DVec3 {
            DVec3::new(self.f(), self.f(), self.f())
        }
    }

    #[test]
    fn similarity_of_an_overlapping_pair_uses_the_lateral_offset() {
        // The shorter projects inside the longer, 0.03 = r_c away: dist_w = 1/3, and
        // len_w = tanh((2/1)^2 x 1).
        let a = seg([0.0, 0.0, 0.0], [2.0, 0.0, 0.0]);
        let b = seg([0.5, 0.03, 0.0], [1.5, 0.03, 0.0]);
        let want = 4f64.tanh() / 3.0;
        for fix in [false, true] {
            assert!(close(similarity(&a, &b, 0.03, fix, 0.5), want));
            assert!(close(similarity(&b, &a, 0.03, fix, 0.5), want));
        }
        // The nearer endpoint counts, even when it projects outside the longer.
        let c = seg([1.5, 0.06, 0.0], [2.5, 0.0, 0.0]);
        let cos = 1.0 / (1.0f64 + 0.06 * 0.06).sqrt();
        let ratio2 = 4.0 / (1.0 + 0.06 * 0.06);
        assert!(close(
            similarity(&a, &c, 0.03, true, 0.5),
            (ratio2 * cos).tanh()
        ));
    }

    #[test]
    fn similarity_of_a_gap_differs_between_the_two_distances() {
        // No overlap: the shorter starts 0.02 past the end of the longer, 0.03 to the side.
        let a = seg([0.0, 0.0, 0.0], [2.0, 0.0, 0.0]);
        let b = seg([2.02, 0.03, 0.0], [3.02, 0.03, 0.0]);
        let len_w = 4f64.tanh();
        // reference: only the 0.02 along the axis counts.
        let x: f64 = 0.02 / 0.03;
        let reference = len_w / (1.0 + 2.0 * x * x);
        assert!(close(similarity(&a, &b, 0.03, false, 0.5), reference));
        // fix: the 3D distance sqrt(0.02^2 + 0.03^2).
        let x2 = (0.02f64 * 0.02 + 0.03 * 0.03) / (0.03 * 0.03);
        let fixed = len_w / (1.0 + 2.0 * x2);
        assert!(close(similarity(&a, &b, 0.03, true, 0.5), fixed));
        // A far-away segment at the end of the longer's axis: reference calls it a
        // perfect neighbour, the fix does not.
        let far = seg([2.0, 5.0, 0.0], [3.0, 5.0, 0.0]);
        assert!(close(similarity(&a, &far, 0.03, false, 0.5), len_w));
        assert!(similarity(&a, &far, 0.03, true, 0.5) < 1e-4);
    }

    #[test]
    fn similarity_is_zero_at_or_below_the_angle_gate() {
        // |cos| = 0.6 exactly (a 3-4-5 direction); the pair overlaps with dist 0, and the
        // lengths are 20 and 5.
        let a = seg([0.0, 0.0, 0.0], [20.0, 0.0, 0.0]);
        let s = seg([1.0, 0.0, 0.0], [4.0, 4.0, 0.0]);
        assert!(close(
            similarity(&a, &s, 0.03, true, 0.5),
            (16.0f64 * 0.6).tanh()
        ));
        assert_eq!(similarity(&a, &s, 0.03, true, 0.6), 0.0);
        assert_eq!(similarity(&a, &s, 0.03, false, 0.6), 0.0);
        // Reversed direction: the absolute cosine counts.
        let r = seg([4.0, 4.0, 0.0], [1.0, 0.0, 0.0]);
        assert!(close(
            similarity(&a, &r, 0.03, true, 0.5),
            (16.0f64 * 0.6).tanh()
        ));
        // Perpendicular: zero whatever the distance.
        let q = seg([1.0, 0.0, 0.0], [1.0, 1.0, 0.0]);
        assert_eq!(similarity(&a, &q, 0.03, true, 0.5), 0.0);
    }

    #[test]
    fn distance_bound_matches_the_default_weight() {
        let b = distance_bound(0.03, 0.4).unwrap();
        assert!((b - 0.03 * 0.75f64.sqrt()).abs() < 1e-10);
        // At the bound the distance weight is exactly the minimum weight.
        let x = 0.75f64.sqrt();
        assert!(close(1.0 / (1.0 + 2.0 * x * x), 0.4));
        assert_eq!(distance_bound(0.03, 0.0), None);
    }

    fn e(i: usize, j: usize, w: f64) -> Edge {
        Edge::new(i, j, w)
    }

    #[test]
    fn union_find_thresholds_tighten_as_clusters_grow() {
        // c = 1.5: sizes 2, 3, 4, 5 give thr = w + 0.75, + 0.5, + 0.375, + 0.3.
        let edges = [
            e(0, 1, 0.40),
            e(1, 2, 0.41), // size 3, thr 0.91
            e(2, 3, 0.42), // size 4, thr 0.795
            e(3, 4, 0.43), // size 5, thr 0.73
            e(4, 5, 0.75), // 0.75 > 0.73: refused
            e(5, 6, 0.80), // new pair, thr 1.55
            e(0, 6, 0.85), // 0.85 > 0.73: refused
            e(6, 7, 0.90), // 0.90 <= 1.55 and <= 1.5: joins, size 3
        ];
        let root = union_find(9, &edges, 1.5);
        for k in 1..5 {
            assert_eq!(root[k], root[0]);
        }
        assert_ne!(root[5], root[0]);
        assert_eq!(root[6], root[5]);
        assert_eq!(root[7], root[5]);
        assert_ne!(root[8], root[0]);
        assert_ne!(root[8], root[5]);
        // c = 0.45: the chain still joins (thr 0.625, 0.56, 0.5325, 0.52 each time above
        // the next w), but every edge above 0.45 now meets a singleton's threshold c.
        let root = union_find(9, &edges, 0.45);
        assert_eq!(root[4], root[0]);
        assert_eq!(root[3], root[0]);
        assert_eq!(root[5..], [5, 6, 7, 8]);
    }

    #[test]
    fn greedy_order_places_the_strongest_pairs_first() {
        let members = [0, 1, 2, 3, 4, 5];
        let edges = [
            e(0, 3, 0.9),
            e(1, 3, 0.8),
            e(1, 2, 0.7),
            e(2, 4, 0.95),
            e(0, 5, 0.7), // ties with (1,2): (0,5) comes first in (i, j) order
        ];
        assert_eq!(greedy_order(&members, &edges), vec![2, 4, 0, 3, 1, 5]);
        let tie = [e(1, 2, 0.5), e(0, 3, 0.5)];
        assert_eq!(greedy_order(&[0, 1, 2, 3], &tie), vec![0, 3, 1, 2]);
    }

    /// The one-pass order of all clusters is each cluster's own greedy order, also where
    /// weights tie across and inside clusters.
    #[test]
    fn greedy_orders_of_all_clusters_are_each_clusters_greedy_order() {
        let mut r = Lcg(9);
        for scene in 0..6 {
            let lines = random_lines(700, scene + 1, scene % 2 == 0);
            let st = Params::default().with_radius([0.03, 0.05, 0.1][scene as usize % 3]);
            let mut edges = edges(&lines, &st).unwrap();
            if scene >= 3 {
                // Weights on a coarse lattice: many ties.
                edges = edges
                    .iter()
                    .map(|e| Edge::new(e.i(), e.j(), (e.w() * 8.0 + r.f()).floor() / 8.0))
                    .collect();
                edges.sort_unstable();
            }
            let root = union_find(lines.len(), &edges, 1.5);
            let mut members: Vec<Vec<usize>> = Vec::new();
            let mut id = std::collections::HashMap::new();
            let mut cluster_of = vec![0u32; lines.len()];
            for (k, r) in root.iter().enumerate() {
                let c = *id.entry(*r).or_insert_with(|| {
                    members.push(Vec::new());
                    members.len() - 1
                });
                members[c].push(k);
                cluster_of[k] = c as u32;
            }
            assert!(
                members.iter().any(|m| m.len() > 3),
                "scene {scene}: no cluster"
            );
            let want: Vec<Vec<usize>> = members
                .iter()
                .enumerate()
                .map(|(c, m)| {
                    let inner: Vec<Edge> = edges
                        .iter()
                        .filter(|e| cluster_of[e.i()] == c as u32 && cluster_of[e.j()] == c as u32)
                        .copied()
                        .collect();
                    greedy_order(m, &inner)
                })
                .collect();
            assert_eq!(
                greedy_orders(&members, &cluster_of, &edges),
                want,
                "scene {scene}"
            );
        }
    }

    #[test]
    fn edges_order_by_weight_then_indices() {
        let mut e = [
            e(3, 4, 0.5),
            e(1, 9, 0.5),
            e(0, 2, 0.75),
            e(7, 8, 0.0),
            e(1, 2, 0.5),
            e(5, 6, 1e-300),
        ];
        e.sort();
        let got: Vec<(usize, usize, f64)> = e.iter().map(|e| (e.i(), e.j(), e.w())).collect();
        assert_eq!(
            got,
            [
                (7, 8, 0.0),
                (5, 6, 1e-300),
                (1, 2, 0.5),
                (1, 9, 0.5),
                (3, 4, 0.5),
                (0, 2, 0.75)
            ]
        );
        assert_eq!(Edge::new(0, 1, -0.0), Edge::new(0, 1, 0.0));
    }

    #[test]
    fn duplicates_of_different_lines_cluster_but_not_of_the_same_line() {
        let s = |y: f64, x0: f64, x1: f64| seg([x0, y, 0.0], [x1, y, 0.0]);
        let lines = LineSet {
            segments: vec![
                s(0.0, 0.0, 1.0),  // 0
                s(5.0, 0.0, 1.0),  // 1, alone
                s(0.01, 0.1, 0.9), // 2, duplicate of 0
                s(0.0, 0.2, 0.8),  // 3, duplicate of 0, same line as 0
                s(5.0, 0.2, 0.7),  // 4, same line as 1
            ],
            groups: Some(vec![0, 1, 2, 0, 1]),
        };
        let p = Params::default();
        let c = cluster(&lines, &p.with_radius(0.03)).unwrap();
        // 3 joins 0 and 2 through its edge with 2; 4 never meets 1. Inside, (2, 3) is the
        // strongest pair (the larger length ratio), so it leads the greedy order.
        assert_eq!(c, vec![vec![2, 3, 0], vec![1], vec![4]]);
        // reference: 1 lies 5 away beside 0, with equal lengths and no endpoint strictly
        // inside, so only the (zero) axial gap counts and 1 joins the cluster.
        let p = Params::reference();
        let c = cluster(&lines, &p.with_radius(0.03)).unwrap();
        assert_eq!(c, vec![vec![2, 3, 0, 1], vec![4]]);
    }

    #[test]
    fn isolated_exact_copies_form_one_cluster_without_their_edges() {
        let s = |x: f64, y: f64| seg([x, y, 0.0], [x + 1.0, y, 0.0]);
        // 0, 2, 4 copies of one edge (in lines 0 and 1); 1 and 3 copies of another, both
        // in line 2 (no edge between them); 5 a near copy of the second edge.
        let (a, b) = (s(0.0, 0.0), s(3.0, 1.0));
        let lines = LineSet {
            segments: vec![a, b, a, b, a, s(3.0, 1.001)],
            groups: Some(vec![0, 2, 1, 2, 0, 3]),
        };
        for p in [Params::default(), Params::reference()] {
            let st = p.with_radius(0.03);
            assert_eq!(isolated_copies(&lines, &st).unwrap(), vec![vec![0, 2, 4]]);
            let c = cluster(&lines, &st).unwrap();
            let all = cluster_all(&lines, &st).unwrap();
            assert_eq!(c, vec![vec![0, 2, 4], vec![1, 5, 3]]);
            // The definition: the same clusters, the first member the same.
            assert_eq!(all.len(), c.len());
            for (a, b) in all.iter().zip(&c) {
                assert_eq!(a[0], b[0]);
                let (mut a, mut b) = (a.clone(), b.clone());
                a.sort();
                b.sort();
                assert_eq!(a, b);
            }
        }
    }

    /// Scenes with short and long segments, near-duplicates and equal lengths.
    fn random_lines(n: usize, seed: u64, grouped: bool) -> LineSet {
        let mut r = Lcg(seed);
        let mut segments = Vec::with_capacity(n);
        while segments.len() < n {
            let k = segments.len();
            let s = match k % 5 {
                // near-duplicate of an earlier one
                0 | 1 if k > 0 => {
                    let o: Segment = segments[(r.f() * k as f64) as usize];
                    let j = (r.v() - 0.5) * 0.05;
                    let t = (r.v() - 0.5) * 0.05;
                    Segment::new(o.p1 + j, o.p2 + t)
                }
                // long
                2 => {
                    let a = r.v();
                    Segment::new(a, a + (r.v() - 0.5) * 1.5)
                }
                // same length as the previous one, shifted along itself
                3 => {
                    let o = segments[k - 1];
                    let d = o.p2 - o.p1;
                    Segment::new(o.p1 + d * 1.01, o.p2 + d * 1.01)
                }
                _ => {
                    let a = r.v();
                    Segment::new(a, a + (r.v() - 0.5) * 0.1)
                }
            };
            if s.is_valid() {
                segments.push(s);
            }
        }
        let groups = grouped.then(|| (0..n).map(|i| (i / 3) as u32).collect());
        LineSet { segments, groups }
    }

    #[test]
    fn the_spatial_index_finds_exactly_the_all_pairs_edges() {
        for (seed, n, r_c, w_min) in [
            (1u64, 600usize, 0.03, 0.4),
            (2, 800, 0.05, 0.4),
            (3, 500, 0.02, 0.2),
            (4, 400, 0.1, 0.7),
        ] {
            for grouped in [false, true] {
                let lines = random_lines(n, seed, grouped);
                let b = distance_bound(r_c, w_min).unwrap();
                let mut hashed = edges_hashed(&lines, r_c, b, w_min, 0.5, usize::MAX);
                let mut all = edges_all_pairs(&lines, r_c, true, w_min, 0.5);
                let order = |a: &Edge, b: &Edge| (a.i(), a.j()).cmp(&(b.i(), b.j()));
                hashed.sort_by(order);
                all.sort_by(order);
                assert!(all.len() > n / 4, "scene too sparse: {} edges", all.len());
                assert_eq!(hashed, all, "seed {seed} grouped {grouped}");
            }
        }
    }

    /// The segments of a Line3D++ `.obj` (`v` records, `l a b` records).
    fn read_obj(path: &str) -> LineSet {
        let text = std::fs::read_to_string(path).unwrap();
        let mut v = Vec::new();
        let mut segments = Vec::new();
        for line in text.lines() {
            let mut f = line.split_whitespace();
            match f.next() {
                Some("v") => {
                    let c: Vec<f64> = f.map(|x| x.parse().unwrap()).collect();
                    v.push(DVec3::new(c[0], c[1], c[2]));
                }
                Some("l") => {
                    let k: Vec<usize> = f.map(|x| x.parse().unwrap()).collect();
                    segments.push(Segment::new(v[k[0] - 1], v[k[1] - 1]));
                }
                _ => {}
            }
        }
        LineSet::new(segments)
    }

    #[test]
    fn the_index_finds_exactly_the_all_pairs_edges_on_real_segments() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/data/line3dpp/line3dpp_optimized.obj"
        );
        let lines = read_obj(path);
        assert_eq!(lines.len(), 2503);
        // The paper's radii for synthetic and real scenes, and a coarse one.
        for r_c in [0.03, 0.05, 0.2] {
            let b = distance_bound(r_c, 0.4).unwrap();
            let mut hashed = edges_hashed(&lines, r_c, b, 0.4, 0.5, usize::MAX);
            hashed.sort_by_key(|e| (e.i(), e.j()));
            let all = edges_all_pairs(&lines, r_c, true, 0.4, 0.5);
            assert!(all.len() > 100, "{} edges at r_c {r_c}", all.len());
            assert_eq!(hashed, all, "r_c {r_c}");
        }
    }

    /// The neighbour bound changes nothing on the test scenes (random ones, the real
    /// Line3D++ set at three radii): the edges are the all-pairs ones.
    #[test]
    fn the_neighbour_bound_keeps_every_edge_of_the_test_scenes() {
        let real = read_obj(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/data/line3dpp/line3dpp_optimized.obj"
        ));
        let mut scenes: Vec<(LineSet, f64)> = [0.03, 0.05, 0.2]
            .into_iter()
            .map(|r| (real.clone(), r))
            .collect();
        for seed in 1..=4 {
            scenes.push((random_lines(800, seed, true), 0.05));
        }
        for (lines, r_c) in scenes {
            let b = distance_bound(r_c, 0.4).unwrap();
            let mut bounded = edges_hashed(&lines, r_c, b, 0.4, 0.5, MAX_NEIGHBOURS);
            bounded.sort_by_key(|e| (e.i(), e.j()));
            let all = edges_all_pairs(&lines, r_c, true, 0.4, 0.5);
            let mut degree = vec![0usize; lines.len()];
            for e in &all {
                let (li, lj) = (
                    lines.segments[e.i()].length(),
                    lines.segments[e.j()].length(),
                );
                degree[if li >= lj { e.i() } else { e.j() }] += 1;
            }
            let most = degree.iter().max().copied().unwrap_or(0);
            assert!(
                bounded == all,
                "r_c {r_c}: {} of {} edges kept, the most neighbours {most}",
                bounded.len(),
                all.len()
            );
        }
    }

    /// Past the bound, each segment keeps its most similar edges (ties: the lower other
    /// index) among those it is the longer member of.
    #[test]
    fn a_dense_scene_keeps_the_most_similar_neighbours() {
        // 3000 short segments on one unit edge: hundreds of neighbours each.
        let mut r = Lcg(5);
        let segments: Vec<Segment> = (0..3000)
            .map(|_| {
                let t = r.f() * 0.95;
                let j = r.v() * 0.004;
                Segment::new(
                    DVec3::new(t, 0.0, 0.0) + j,
                    DVec3::new(t + 0.02 + 0.03 * r.f(), 0.0, 0.0) - j,
                )
            })
            .collect();
        let lines = LineSet::new(segments);
        let b = distance_bound(0.03, 0.4).unwrap();
        let k = 8;
        let bounded = edges_hashed(&lines, 0.03, b, 0.4, 0.5, k);
        let all = edges_hashed(&lines, 0.03, b, 0.4, 0.5, usize::MAX);
        assert!(all.len() > 50 * lines.len(), "{} edges", all.len());
        let long = |e: &Edge| {
            if lines.segments[e.i()].length() >= lines.segments[e.j()].length() {
                e.i()
            } else {
                e.j()
            }
        };
        let mut per: Vec<Vec<Edge>> = vec![Vec::new(); lines.len()];
        for e in &all {
            per[long(e)].push(*e);
        }
        let mut want: Vec<Edge> = Vec::new();
        for (g, mut es) in per.into_iter().enumerate() {
            let other = |e: &Edge| e.i() + e.j() - g;
            es.sort_by(|a, b| b.w().total_cmp(&a.w()).then(other(a).cmp(&other(b))));
            es.truncate(k);
            want.extend(es);
        }
        let key = |e: &Edge| (e.i(), e.j());
        want.sort_by_key(key);
        let mut got = bounded;
        got.sort_by_key(key);
        assert_eq!(got, want);
    }

    #[test]
    fn the_index_finds_overlapping_pairs_far_from_each_other() {
        // Only one endpoint of the shorter projects inside the longer, and the endpoint that
        // is on the longer's line lies past the longer's end, 2.3 away from it in 3D: an
        // edge for the step 7 formula, which a plain capsule test would miss.
        let lines = LineSet::new(vec![
            seg([0.0, 0.0, 0.0], [10.0, 0.0, 0.0]),
            seg([9.0, 5.0, 0.0], [13.0, 0.0, 0.0]),
        ]);
        let all = edges_all_pairs(&lines, 0.03, true, 0.4, 0.5);
        assert_eq!(all.len(), 1);
        let b = distance_bound(0.03, 0.4).unwrap();
        assert_eq!(edges_hashed(&lines, 0.03, b, 0.4, 0.5, usize::MAX), all);
    }

    /// Under the authors' distance the tree finds exactly the all-pairs edges: random
    /// scenes (near-duplicates, equal lengths, groups), the real Line3D++ set, and pairs
    /// that end at the other's end far across its axis, which only that distance links.
    #[test]
    fn the_endpoint_tree_finds_exactly_the_authors_all_pairs_edges() {
        let real = read_obj(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/tests/data/line3dpp/line3dpp_optimized.obj"
        ));
        let mut scenes: Vec<(LineSet, f64, f64, f64)> = vec![
            (real.clone(), 0.03, 0.4, 0.5),
            (real.clone(), 0.2, 0.4, 0.5),
            (real, 0.05, 0.2, 0.0),
        ];
        for (seed, n, r_c, w_min, min_cos) in [
            (1u64, 600usize, 0.03, 0.4, 0.5),
            (2, 800, 0.05, 0.4, 0.5),
            (3, 500, 0.02, 0.2, 0.9),
            (4, 400, 0.1, 0.7, 0.5),
            (5, 700, 0.05, 0.4, 0.0),
        ] {
            for grouped in [false, true] {
                scenes.push((random_lines(n, seed, grouped), r_c, w_min, min_cos));
            }
        }
        // Parallel pieces on a grid across one axis: every piece ends where others end.
        let mut r = Lcg(9);
        let across: Vec<Segment> = (0..600)
            .map(|k| {
                let o = DVec3::new(0.0, (k % 20) as f64 * 0.7, (k / 20) as f64 * 0.9);
                let t = (k % 7) as f64 * 0.3 + r.f() * 0.01;
                seg(
                    (o + DVec3::new(t, 0.0, 0.0)).to_array(),
                    (o + DVec3::new(t + 0.3 + r.f() * 0.05, r.f() * 0.2, 0.0)).to_array(),
                )
            })
            .collect();
        scenes.push((LineSet::new(across), 0.03, 0.4, 0.5));
        for (k, (lines, r_c, w_min, min_cos)) in scenes.into_iter().enumerate() {
            let b = distance_bound(r_c, w_min).unwrap();
            let mut tree = edges_reference(&lines, r_c, b, w_min, min_cos);
            tree.sort_by_key(|e| (e.i(), e.j()));
            let all = edges_all_pairs(&lines, r_c, false, w_min, min_cos);
            let far = all
                .iter()
                .filter(|e| lines.segments[e.i()].distance_to(&lines.segments[e.j()]) > 2.0 * b)
                .count();
            assert!(
                all.len() > lines.len() / 4,
                "scene {k}: {} edges",
                all.len()
            );
            assert!(far > 0, "scene {k}: no edge across the axis");
            assert_eq!(tree, all, "scene {k}");
        }
    }

    /// 4,000 pieces within 0.02 of each other on one line, each its own input line: every
    /// pair is an edge under the authors' distance, 8 x 10^6 of them, past the bound of
    /// 1,024 a segment; step 7 says so instead of taking the memory. The default profile
    /// keeps 128 a segment and clusters them.
    #[test]
    fn step_7_stops_at_its_edge_bound_with_a_message() {
        let mut r = Lcg(3);
        let lines = LineSet::new(
            (0..4000)
                .map(|_| {
                    let t = r.f() * 0.019;
                    let j = (r.v() - 0.5) * 2e-4;
                    Segment::new(
                        DVec3::new(t, 0.0, 0.0) + j,
                        DVec3::new(t + 1e-3, 0.0, 0.0) - j,
                    )
                })
                .collect(),
        );
        assert_eq!(edge_limit(lines.len()), 4000 * MAX_EDGES_PER_SEGMENT);
        let reference = Params::reference().with_radius(0.03);
        let Err(EngineError::Limit(why)) = cluster(&lines, &reference) else {
            panic!("no limit reached");
        };
        assert!(
            why.contains("step 7") && why.contains("4096000 similarity edges for 4000 segments"),
            "{why}"
        );
        let c = cluster(&lines, &Params::default().with_radius(0.03)).unwrap();
        assert!(c.len() < 100, "{} clusters", c.len());
        // Under the bound the same scene clusters: a tenth of it.
        let few = lines.select(&(0..400).collect::<Vec<_>>());
        assert!(cluster(&few, &reference).unwrap().len() < 100);
    }

    #[test]
    fn clusters_do_not_depend_on_the_thread_count() {
        let lines = random_lines(1500, 7, true);
        let run = |threads: usize, p: &Params| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| cluster(&lines, &p.with_radius(0.03)).unwrap())
        };
        for p in [Params::default(), Params::reference()] {
            let one = run(1, &p);
            assert!(one.len() < lines.len(), "nothing clustered");
            let mut all: Vec<usize> = one.iter().flatten().copied().collect();
            all.sort_unstable();
            assert_eq!(all, (0..lines.len()).collect::<Vec<_>>());
            assert_eq!(one, run(3, &p));
            assert_eq!(one, run(2, &p));
        }
    }
}
