//! The working set and the uniform grid shared by both engines (docs/method.md#geometry,
//! docs/architecture.md#the-engine-contract).
//!
//! Centers are sorted by cell with a radix sort; cells are numbered x-fastest, so the
//! cells `x0..=x1` of one `(y, z)` row hold one contiguous range of the sorted points. A
//! cylinder query is answered by visiting only the rows its capped cylinder can touch,
//! each as one point range.

use crate::geom::{p64, Aabb, Segment};
use glam::DVec3;
use rayon::prelude::*;
use std::borrow::Cow;

/// Upper bound on the number of cells: the table stays small next to the points even when
/// the scene is huge compared with the radius (the cell then grows beyond `r`).
const MAX_CELLS: f64 = (1u64 << 24) as f64;

/// Cells per point at most (and at least this many cells in all), so the table is never
/// large next to the points it indexes, whatever the scene's extent.
const CELLS_PER_POINT: f64 = 8.0;
const MIN_CELLS: f64 = 4096.0;

/// Cells per point a grid that only the host reads may have beyond `MAX_CELLS` (from
/// about 1.1 x 10^7 points up): a 10^8-point scene then gets the cells of a 10^7 one, not
/// cells twice as wide, each holding 8x the points (`MAX_CELLS` holds the cell table
/// within a device's binding limit, which the host does not have).
const HOST_CELLS_PER_POINT: f64 = 1.5;

/// Most cells for `n` points; `host`: for a grid only the CPU engine reads.
fn max_cells(n: usize, host: bool) -> f64 {
    let cap = if host {
        MAX_CELLS.max(n as f64 * HOST_CELLS_PER_POINT)
    } else {
        MAX_CELLS
    };
    // Cells are numbered in a u32 (the radix sort's key), with room to spare.
    (n as f64 * CELLS_PER_POINT).clamp(MIN_CELLS, cap.min((1u64 << 31) as f64))
}

/// Gaussian centers inside the box of all segment endpoints grown by 0.1x its longest edge.
#[derive(Clone, Debug)]
pub struct WorkingSet<'a> {
    pub bounds: Aabb,
    /// The centers inside, in their order: the caller's own array where every center is
    /// inside (no copy), else a copy of those inside.
    pub points: Cow<'a, [[f32; 3]]>,
}

impl<'a> WorkingSet<'a> {
    /// Keeps the centers inside `Aabb::of_segments(segments).grown(0.1)` (inclusive).
    pub fn new(centers: &'a [[f32; 3]], segments: &[Segment]) -> Self {
        let bounds = Aabb::of_segments(segments).grown(0.1);
        let points = if bounds.is_empty() {
            Cow::Owned(Vec::new())
        } else {
            // Counted first, then written in place: a parallel filter that collects
            // chains and copies its pieces, and took longer than one thread's filter.
            const CHUNK: usize = 1 << 16;
            let keep = |p: &[f32; 3]| bounds.contains(p64(*p));
            let counts: Vec<usize> = centers
                .par_chunks(CHUNK)
                .map(|c| c.iter().filter(|p| keep(p)).count())
                .collect();
            // Every center inside (a model the lines span): the working set is the
            // caller's array itself (a copy of 1.2 GB at 10^8 centers took a fifth of the
            // index stage).
            if counts.iter().sum::<usize>() == centers.len() {
                return WorkingSet {
                    bounds,
                    points: Cow::Borrowed(centers),
                };
            }
            let mut points = vec![[0f32; 3]; counts.iter().sum()];
            let mut rest = &mut points[..];
            let mut outs = Vec::with_capacity(counts.len());
            for &n in &counts {
                let (out, tail) = rest.split_at_mut(n);
                outs.push(out);
                rest = tail;
            }
            centers.par_chunks(CHUNK).zip(outs).for_each(|(c, out)| {
                for (p, o) in c.iter().filter(|p| keep(p)).zip(out.iter_mut()) {
                    *o = *p;
                }
            });
            Cow::Owned(points)
        };
        WorkingSet { bounds, points }
    }

    /// `N_box`.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }
}

/// One row of cells `x0..=x1` at `(y, z)` and the sorted points it holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Row {
    pub y: u32,
    pub z: u32,
    pub x0: u32,
    pub x1: u32,
}

/// Uniform grid over the working set.
#[derive(Clone, Debug)]
pub struct Grid {
    /// Corner of cell (0,0,0).
    pub origin: DVec3,
    /// Edge length of a cubic cell.
    pub cell: f64,
    pub dims: [u32; 3],
    /// Border cells extend to infinity (the grid spans a quantile box of the points; see
    /// [`Grid::build`]).
    pub open: bool,
    /// `cell_start[c]..cell_start[c+1]` are the sorted points of cell `c`; length cells+1.
    pub cell_start: Vec<u32>,
    /// Centers sorted by cell (absolute coordinates, as read).
    pub points: Vec<[f32; 3]>,
    /// Index in the working set of each sorted point.
    pub ids: Vec<u32>,
}

impl Grid {
    /// Builds the grid over `points` (all inside `bounds`) with cells near `cell_hint`
    /// (the query radius), never more than 8 cells per point (and 2^24 in all).
    ///
    /// When `bounds` would stretch the cells past `4 x` the hint, the grid spans the points
    /// instead: one segment endpoint flung far away grows the working box
    /// (docs/method.md#geometry) but not the grid, so the cells stay near `r` and a far
    /// segment costs what a near one does.
    ///
    /// When a few far points (floaters) would still blow the cells up past `4 x` the hint,
    /// the grid spans the 0.1% to 99.9% quantile box instead and its border cells are
    /// open-ended: they hold every point beyond them, and queries beyond the grid visit
    /// them, so the answer stays exact while the core keeps fine cells.
    pub fn build(points: &[[f32; 3]], bounds: Aabb, cell_hint: f64) -> Grid {
        Grid::build_capped(points, bounds, cell_hint, false)
    }

    /// [`Grid::build`] for a grid that only the CPU engine reads: above about 1.1 x 10^7
    /// points it may have more than 2^24 cells (1.5 per point), so cells stay as fine as
    /// at 10^7 points. Below that, the very grid of [`Grid::build`].
    pub fn build_for_host(points: &[[f32; 3]], bounds: Aabb, cell_hint: f64) -> Grid {
        Grid::build_capped(points, bounds, cell_hint, true)
    }

    fn build_capped(points: &[[f32; 3]], bounds: Aabb, cell_hint: f64, host: bool) -> Grid {
        // The working box as before when it gives cells near the hint (normal scenes get
        // the very same grid); otherwise the points' box, then the quantile box below.
        // The points' box, by both cores (min and max in any order give the same box).
        let union = |a: Aabb, b: Aabb| Aabb {
            min: a.min.min(b.min),
            max: a.max.max(b.max),
        };
        let pts_box = points
            .par_chunks(1 << 16)
            .map(|c| {
                let mut b = Aabb::empty();
                for p in c {
                    b.extend(p64(*p));
                }
                b
            })
            .reduce(Aabb::empty, union);
        let mut b = union(bounds, pts_box);
        if b.is_empty() {
            b = Aabb {
                min: DVec3::ZERO,
                max: DVec3::ZERO,
            };
        }
        let hint = if cell_hint.is_finite() && cell_hint > 0.0 {
            Some(cell_hint)
        } else {
            None
        };
        let most = max_cells(points.len(), host);
        let mut cell = cell_size(&b, hint, most);
        let mut open = false;
        if let Some(h) = hint {
            if cell > 4.0 * h && !pts_box.is_empty() {
                let c = cell_size(&pts_box, hint, most);
                if c < cell {
                    (b, cell) = (pts_box, c);
                }
            }
            if cell > 4.0 * h && points.len() >= 1000 {
                let core = quantile_box(points, 0.001);
                let c = cell_size(&core, hint, most);
                if c < cell {
                    (b, cell, open) = (core, c, true);
                }
            }
        }
        let ext = (b.max - b.min).max(DVec3::splat(1e-9));
        let dims = [
            (ext.x / cell).floor() as u32 + 1,
            (ext.y / cell).floor() as u32 + 1,
            (ext.z / cell).floor() as u32 + 1,
        ];
        let mut grid = Grid {
            origin: b.min,
            cell,
            dims,
            open,
            cell_start: Vec::new(),
            points: Vec::new(),
            ids: Vec::new(),
        };
        let total = dims[0] as usize * dims[1] as usize * dims[2] as usize;
        // (cell << 32 | id) per point, then sorted by cell with a stable radix sort: ids
        // stay ascending within a cell. Every pass streams through memory; scattering
        // each point straight to its cell's place (a counting sort) touched the cell
        // table and the output at random, a cache miss or three per point (0.92 s of
        // 1.18 s at 10^7 points and 1.3 x 10^7 cells).
        let mut items: Vec<u64> = points
            .par_iter()
            .enumerate()
            .map(|(i, p)| u64::from(grid.cell_of(p64(*p))) << 32 | i as u64)
            .collect();
        radix_sort_high(&mut items, total);
        let (start, ids, sorted) = starts_ids_points(&items, total, points, SORTED_RUN);
        drop(items);
        grid.cell_start = start;
        grid.points = sorted;
        grid.ids = ids;
        grid
    }

    pub fn n_cells(&self) -> usize {
        self.cell_start.len() - 1
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The cell layer of coordinate `v` on `axis`, clamped into the grid.
    #[inline]
    fn axis_cell(&self, v: f64, axis: usize) -> u32 {
        self.layer((v - self.origin[axis]) / self.cell, axis)
    }

    /// The layer on `axis` at `cells` cells from the grid's corner, clamped into the
    /// grid: its floor. The cast truncates, which is the floor from 0 up, and saturates
    /// (below 0 and NaN give 0), so no `floor` is called: on the x86-64 baseline (no
    /// SSE4.1) `f64::floor` is a call into libm, three per point.
    #[inline]
    fn layer(&self, cells: f64, axis: usize) -> u32 {
        (cells as u32).min(self.dims[axis] - 1)
    }

    /// Linear index (x fastest) of the cell holding `p` (clamped into the grid).
    #[inline]
    pub fn cell_of(&self, p: DVec3) -> u32 {
        let [x, y, z] = self.cell_xyz(p);
        self.linear(x, y, z)
    }

    /// The column, row and layer of [`Self::cell_of`]`(p)`.
    #[inline]
    pub fn cell_xyz(&self, p: DVec3) -> [u32; 3] {
        [
            self.axis_cell(p.x, 0),
            self.axis_cell(p.y, 1),
            self.axis_cell(p.z, 2),
        ]
    }

    #[inline]
    pub fn linear(&self, x: u32, y: u32, z: u32) -> u32 {
        (z * self.dims[1] + y) * self.dims[0] + x
    }

    /// Corner of cell `(x, y, z)`.
    pub fn cell_origin(&self, x: u32, y: u32, z: u32) -> DVec3 {
        self.origin + DVec3::new(x as f64, y as f64, z as f64) * self.cell
    }

    /// Sorted point range of a row.
    #[inline]
    pub fn row_range(&self, row: &Row) -> std::ops::Range<usize> {
        let a = self.linear(row.x0, row.y, row.z) as usize;
        let b = self.linear(row.x1, row.y, row.z) as usize + 1;
        self.cell_start[a] as usize..self.cell_start[b] as usize
    }

    /// Sorted point range of one cell.
    #[inline]
    pub fn cell_range(&self, x: u32, y: u32, z: u32) -> std::ops::Range<usize> {
        let a = self.linear(x, y, z) as usize;
        self.cell_start[a] as usize..self.cell_start[a + 1] as usize
    }

    /// Calls `f` for every row of cells that the capped cylinder `C(seg, r)` can touch, in a
    /// fixed order (z, then y). A superset: every point inside the cylinder lies in a
    /// visited row; the exact test is the caller's.
    pub fn visit_rows(&self, seg: &Segment, r: f64, mut f: impl FnMut(Row)) {
        if self.points.is_empty()
            || r.is_nan()
            || r < 0.0
            || !seg.p1.is_finite()
            || !seg.p2.is_finite()
        {
            return;
        }
        let l = seg.length();
        let d = seg.dir();
        let p = seg.p1;
        // Extent of the radial disc along each axis: r sqrt(1 - d_j^2), plus a margin that
        // covers rounding in the cell assignment of points lying on a cell face.
        let margin = 1e-6 * self.cell + 1e-9 * (self.origin.abs().max_element() + 1.0);
        let rr = DVec3::new(
            r * (1.0 - d.x * d.x).max(0.0).sqrt(),
            r * (1.0 - d.y * d.y).max(0.0).sqrt(),
            r * (1.0 - d.z * d.z).max(0.0).sqrt(),
        ) + DVec3::splat(margin);
        let full = (0.0, l);
        let z_span = axis_span(p.z, d.z, full, rr.z);
        let Some((z0, z1)) = self.cell_span(z_span, 2) else {
            return;
        };
        for z in z0..=z1 {
            let slab = self.slab(z, 2, rr.z);
            let Some(tz) = t_interval(p.z, d.z, slab, full) else {
                continue;
            };
            let Some((y0, y1)) = self.cell_span(axis_span(p.y, d.y, tz, rr.y), 1) else {
                continue;
            };
            for y in y0..=y1 {
                let slab = self.slab(y, 1, rr.y);
                let Some(tyz) = t_interval(p.y, d.y, slab, tz) else {
                    continue;
                };
                if let Some((x0, x1)) = self.cell_span(axis_span(p.x, d.x, tyz, rr.x), 0) {
                    f(Row { y, z, x0, x1 });
                }
            }
        }
    }

    /// [`Grid::visit_rows`] as point ranges, fetched ahead: the rows' cell-table entries
    /// are requested from memory all at once, before the first is read, and each row's
    /// first points while the row before it is tested. A walk otherwise waits on each
    /// row's table entry and then on its points, one row at a time. `rows` is scratch
    /// space the caller keeps.
    #[inline]
    pub fn visit_ranges(
        &self,
        seg: &Segment,
        r: f64,
        rows: &mut Vec<(u32, u32)>,
        mut f: impl FnMut(std::ops::Range<usize>),
    ) {
        rows.clear();
        self.visit_rows(seg, r, |row| {
            let a = self.linear(row.x0, row.y, row.z);
            let b = self.linear(row.x1, row.y, row.z) + 1;
            prefetch(&self.cell_start[a as usize]);
            prefetch(&self.cell_start[b as usize]);
            rows.push((a, b));
        });
        let range = |&(a, b): &(u32, u32)| {
            self.cell_start[a as usize] as usize..self.cell_start[b as usize] as usize
        };
        let mut next = rows.first().map(range);
        for k in 0..rows.len() {
            let here = next.take().unwrap_or(0..0);
            next = rows.get(k + 1).map(range);
            if let Some(n) = &next {
                if let Some(p) = self.points.get(n.start) {
                    prefetch(p);
                }
            }
            f(here);
        }
    }

    /// Coordinate interval of cell layer `i` on `axis`, grown by `grow`.
    fn slab(&self, i: u32, axis: usize, grow: f64) -> (f64, f64) {
        let lo = self.origin[axis] + i as f64 * self.cell;
        let (mut a, mut b) = (lo - grow, lo + self.cell + grow);
        if self.open {
            if i == 0 {
                a = f64::NEG_INFINITY;
            }
            if i + 1 == self.dims[axis] {
                b = f64::INFINITY;
            }
        }
        (a, b)
    }

    /// Cell index range covering the coordinate interval, or `None` when it misses the grid.
    fn cell_span(&self, span: (f64, f64), axis: usize) -> Option<(u32, u32)> {
        let lo = (span.0 - self.origin[axis]) / self.cell;
        let hi = (span.1 - self.origin[axis]) / self.cell;
        let n = self.dims[axis] as f64;
        if lo.is_nan() || hi.is_nan() || lo > hi {
            return None;
        }
        if self.open {
            // Open borders: a span beyond the grid falls in its border layer.
            return Some((self.layer(lo, axis), self.layer(hi, axis)));
        }
        if hi < 0.0 || lo >= n {
            return None;
        }
        Some((self.layer(lo, axis), self.layer(hi, axis)))
    }
}

/// Asks for the cache line holding `x` (a hint: no effect on results).
#[inline(always)]
fn prefetch<T>(x: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: prefetching is a hint that never faults, even for an invalid address.
    unsafe {
        std::arch::x86_64::_mm_prefetch(x as *const T as *const i8, std::arch::x86_64::_MM_HINT_T0);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = x;
}

/// How many items ahead [`starts_ids_points`] asks for the point it will gather.
const GATHER_AHEAD: usize = 16;

/// Sorted items per task of [`starts_ids_points`].
const SORTED_RUN: usize = 1 << 15;

/// From `items` (`cell << 32 | id`, sorted by cell) over `total` cells: the first point
/// of each cell and the end (`total + 1` starts), the ids, and the points of `points` in
/// that order, in one pass over the items by all cores, `run` items a task.
///
/// A task's items write the starts of the cells from the one after its first item's
/// predecessor's cell up to its last item's cell: each cell's start is written by the
/// task holding the first item at or beyond it, so the tasks' shares of the starts are
/// disjoint and tile them (the cells after the last item's start at the end).
fn starts_ids_points(
    items: &[u64],
    total: usize,
    points: &[[f32; 3]],
    run: usize,
) -> (Vec<u32>, Vec<u32>, Vec<[f32; 3]>) {
    let cell = |k: usize| (items[k] >> 32) as usize;
    let n = items.len();
    let mut start = vec![0u32; total + 1];
    let mut ids = vec![0u32; n];
    let mut sorted = vec![[0f32; 3]; n];
    // Each task's share of the starts: from past its predecessor's last cell.
    let run = run.max(1);
    let mut shares = Vec::with_capacity(n.div_ceil(run));
    let mut rest = &mut start[..];
    let mut done = 0;
    for j0 in (0..n).step_by(run) {
        let j1 = (j0 + run).min(n);
        let end = cell(j1 - 1) + 1;
        let (share, tail) = std::mem::take(&mut rest).split_at_mut(end - done);
        shares.push((j0, share, done));
        rest = tail;
        done = end;
    }
    rest.fill(n as u32);
    ids.par_chunks_mut(run)
        .zip(sorted.par_chunks_mut(run))
        .zip(shares)
        .for_each(|((ids, sorted), (j0, share, first))| {
            let mut next = first;
            for (k, (id, p)) in ids.iter_mut().zip(sorted.iter_mut()).enumerate() {
                let j = j0 + k;
                let c = cell(j);
                // Cells `next..=c` start at `j`: the empty ones before `c`, and `c`.
                if c >= next {
                    share[next - first..=c - first].fill(j as u32);
                    next = c + 1;
                }
                let i = items[j] as u32;
                *id = i;
                *p = points[i as usize];
                if let Some(&ahead) = items.get(j + GATHER_AHEAD) {
                    prefetch(&points[(ahead as u32) as usize]);
                }
            }
        });
    (start, ids, sorted)
}

/// Sorts `items` by their high 32 bits (all below `bound`), stably. Small sorts (or keys
/// of at most [`TOP_BITS`] bits): a least significant digit radix sort over the whole
/// array ([`lsd_slices`]). Large ones: one pass by the key's
/// top [`TOP_BITS`] bits into buckets, counted and scattered by both cores, then each
/// bucket sorted by the rest of its bits on its own, in parallel: a bucket (about 25,000
/// items at 10^8 points) sorts in the cache, where a pass over the whole array scatters
/// into 4,096 places of a 0.8 GB array at random.
pub(crate) fn radix_sort_high(items: &mut Vec<u64>, bound: usize) {
    let bits = usize::BITS - bound.saturating_sub(1).leading_zeros();
    if items.len() < 2 || bits == 0 {
        return;
    }
    let mut other = vec![0u64; items.len()];
    if bits <= TOP_BITS || items.len() < SPLIT_FROM {
        let passes = bits.div_ceil(LOW_BITS);
        lsd_slices(items, &mut other, bits.div_ceil(passes), passes);
        if !passes.is_multiple_of(2) {
            std::mem::swap(items, &mut other);
        }
        return;
    }
    let low = bits - TOP_BITS;
    let top = |it: u64| (it >> (32 + low)) as usize;
    const BUCKETS: usize = 1 << TOP_BITS;
    // Each chunk's count of each bucket, then the chunks scatter into their own pieces of
    // each bucket (chunk order within a bucket: stable).
    let chunk = items
        .len()
        .div_ceil(4 * rayon::current_num_threads())
        .max(1 << 14);
    let counts: Vec<Vec<usize>> = items
        .par_chunks(chunk)
        .map(|c| {
            let mut h = vec![0usize; BUCKETS];
            for &it in c {
                h[top(it)] += 1;
            }
            h
        })
        .collect();
    let mut sizes = vec![0usize; BUCKETS];
    for h in &counts {
        for (s, k) in sizes.iter_mut().zip(h) {
            *s += k;
        }
    }
    {
        let mut pieces: Vec<Vec<&mut [u64]>> =
            counts.iter().map(|_| Vec::with_capacity(BUCKETS)).collect();
        let mut rest: &mut [u64] = &mut other;
        for b in 0..BUCKETS {
            for (c, h) in counts.iter().enumerate() {
                let (piece, tail) = std::mem::take(&mut rest).split_at_mut(h[b]);
                pieces[c].push(piece);
                rest = tail;
            }
        }
        items
            .par_chunks(chunk)
            .zip(pieces.par_iter_mut())
            .for_each(|(c, pieces)| {
                let mut at = vec![0usize; BUCKETS];
                for &it in c {
                    let d = top(it);
                    pieces[d][at[d]] = it;
                    at[d] += 1;
                }
            });
    }
    // Each bucket (in `other`) by its low bits, with the same range of `items` as scratch:
    // every bucket takes the same number of passes, so every one ends in the same array.
    let passes = low.div_ceil(LOW_BITS);
    if passes > 0 {
        let width = low.div_ceil(passes);
        let mut buckets: Vec<(&mut [u64], &mut [u64])> = Vec::with_capacity(BUCKETS);
        let (mut a, mut b): (&mut [u64], &mut [u64]) = (&mut other, items);
        for &n in &sizes {
            let (x, a_rest) = std::mem::take(&mut a).split_at_mut(n);
            let (y, b_rest) = std::mem::take(&mut b).split_at_mut(n);
            buckets.push((x, y));
            (a, b) = (a_rest, b_rest);
        }
        buckets
            .into_par_iter()
            .for_each(|(data, scratch)| lsd_slices(data, scratch, width, passes));
    }
    // After an even number of passes within the buckets, the sorted items are in `other`.
    if passes.is_multiple_of(2) {
        std::mem::swap(items, &mut other);
    }
}

/// Keys of more bits than this are sorted by their top this many bits first
/// ([`radix_sort_high`]).
const TOP_BITS: u32 = 12;
/// The widest digit of a pass over the low bits (its counts: 16 KiB).
const LOW_BITS: u32 = 11;
/// Items from which [`radix_sort_high`] splits by the top digit first.
const SPLIT_FROM: usize = 1 << 16;

/// `passes` least significant digit passes of `width` bits over the high half's low bits,
/// from `data` to `scratch` and back (no pass skipped): after an odd number the sorted
/// items are in `scratch`, after an even number in `data`.
fn lsd_slices(data: &mut [u64], scratch: &mut [u64], width: u32, passes: u32) {
    let mask = (1usize << width) - 1;
    let mut next = [0usize; 1 << LOW_BITS];
    let next = &mut next[..=mask];
    let (mut from, mut to) = (data, scratch);
    for pass in 0..passes {
        let shift = 32 + pass * width;
        next.fill(0);
        for &it in from.iter() {
            next[(it >> shift) as usize & mask] += 1;
        }
        let mut at = 0;
        for n in next.iter_mut() {
            (*n, at) = (at, at + *n);
        }
        for &it in from.iter() {
            let d = (it >> shift) as usize & mask;
            to[next[d]] = it;
            next[d] += 1;
        }
        std::mem::swap(&mut from, &mut to);
    }
}

/// Edge of cubic cells near `hint` over box `b`, grown until there are at most `most`.
fn cell_size(b: &Aabb, hint: Option<f64>, most: f64) -> f64 {
    let ext = (b.max - b.min).max(DVec3::splat(1e-9));
    let mut cell = hint.unwrap_or(ext.max_element());
    let n_cells = |c: f64| {
        ((ext.x / c).floor() + 1.0) * ((ext.y / c).floor() + 1.0) * ((ext.z / c).floor() + 1.0)
    };
    if n_cells(cell) > most {
        let vol = ext.x * ext.y * ext.z;
        cell = cell.max((vol / most).cbrt());
        while n_cells(cell) > most {
            cell *= 1.1;
        }
    }
    cell
}

/// Per axis, the `q` and `1 - q` quantiles of the points.
fn quantile_box(points: &[[f32; 3]], q: f64) -> Aabb {
    let n = points.len();
    let lo_k = ((n as f64 * q) as usize).min(n - 1);
    let hi_k = n - 1 - lo_k;
    let mut min = DVec3::ZERO;
    let mut max = DVec3::ZERO;
    let mut v: Vec<f32> = Vec::with_capacity(n);
    for axis in 0..3 {
        v.clear();
        v.extend(points.iter().map(|p| p[axis]));
        min[axis] = *v.select_nth_unstable_by(lo_k, f32::total_cmp).1 as f64;
        max[axis] = *v.select_nth_unstable_by(hi_k, f32::total_cmp).1 as f64;
    }
    Aabb { min, max }
}

/// Range of `p + t d` over `t` in `ts`, grown by `grow`.
fn axis_span(p: f64, d: f64, ts: (f64, f64), grow: f64) -> (f64, f64) {
    let a = p + ts.0 * d;
    let b = p + ts.1 * d;
    (a.min(b) - grow, a.max(b) + grow)
}

/// `{t in ts : p + t d in slab}`, or `None` when empty.
fn t_interval(p: f64, d: f64, slab: (f64, f64), ts: (f64, f64)) -> Option<(f64, f64)> {
    if d.abs() < 1e-12 {
        return if p >= slab.0 && p <= slab.1 {
            Some(ts)
        } else {
            None
        };
    }
    let a = (slab.0 - p) / d;
    let b = (slab.1 - p) / d;
    let (a, b) = if a <= b { (a, b) } else { (b, a) };
    // Widen by a relative epsilon so that rounding in the division never drops a row.
    let eps = 1e-9 * (ts.1 - ts.0).abs().max(1e-12);
    let lo = a.max(ts.0) - eps;
    let hi = b.min(ts.1) + eps;
    if lo > hi {
        None
    } else {
        Some((lo.max(ts.0), hi.min(ts.1)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Cylinder;
    use crate::synth::Rng;

    /// Uniform in `[0, 1)` from the library's generator.
    fn uni(rng: &mut Rng) -> f64 {
        rng.uniform()
    }

    #[test]
    fn the_sort_keeps_every_point_in_its_cell_in_input_order() {
        let mut s = Rng::new(7);
        let pts: Vec<[f32; 3]> = (0..5000)
            .map(|_| {
                [
                    uni(&mut s) as f32,
                    uni(&mut s) as f32 * 2.0,
                    uni(&mut s) as f32,
                ]
            })
            .collect();
        let mut b = Aabb::empty();
        for p in &pts {
            b.extend(p64(*p));
        }
        let g = Grid::build(&pts, b, 0.1);
        assert_eq!(g.len(), 5000);
        let mut seen = vec![false; 5000];
        for c in 0..g.n_cells() {
            for i in g.cell_start[c] as usize..g.cell_start[c + 1] as usize {
                assert_eq!(g.cell_of(p64(g.points[i])) as usize, c);
                assert_eq!(g.points[i], pts[g.ids[i] as usize]);
                if i > g.cell_start[c] as usize {
                    assert!(g.ids[i - 1] < g.ids[i], "cell {c}: ids out of order");
                }
                seen[g.ids[i] as usize] = true;
            }
        }
        assert!(seen.iter().all(|&x| x));
    }

    #[test]
    fn starts_ids_and_points_by_tasks_are_the_sequential_walks() {
        // Cells with many points (one spanning several tasks), empty cells between and
        // after them, and a run of one item a task.
        let mut s = Rng::new(11);
        let total = 300;
        let mut items: Vec<u64> = (0..2000u64)
            .map(|i| {
                let c = if i % 7 == 0 {
                    150
                } else {
                    (uni(&mut s) * 200.0) as u64 * 3 / 2
                };
                c << 32 | i
            })
            .collect();
        items.sort_by_key(|&it| it >> 32);
        let points: Vec<[f32; 3]> = (0..2000).map(|i| [i as f32, -(i as f32), 0.5]).collect();
        let mut want: Vec<u32> = Vec::new();
        for (j, &it) in items.iter().enumerate() {
            let c = (it >> 32) as usize;
            while want.len() <= c {
                want.push(j as u32);
            }
        }
        want.resize(total + 1, items.len() as u32);
        for run in [1, 3, 64, 1000, 5000] {
            let (start, ids, sorted) = starts_ids_points(&items, total, &points, run);
            assert_eq!(start, want, "run {run}");
            for (j, &it) in items.iter().enumerate() {
                assert_eq!(ids[j], it as u32);
                assert_eq!(sorted[j], points[it as u32 as usize]);
            }
        }
        let (start, ids, sorted) = starts_ids_points(&[], 5, &points, 4);
        assert_eq!((start, ids.len(), sorted.len()), (vec![0; 6], 0, 0));
    }

    #[test]
    fn cell_layers_are_the_floors_clamped_into_the_grid() {
        let g = Grid {
            origin: DVec3::new(-1.0, 0.5, 2.0),
            cell: 0.25,
            dims: [8, 3, 1],
            open: false,
            cell_start: vec![0; 25],
            points: vec![[0.0; 3]],
            ids: vec![0],
        };
        for v in [
            -3.0f64,
            -1.0001,
            -1.0,
            -0.76,
            -0.75,
            -0.5,
            0.0,
            0.99,
            1.0,
            9.0,
            f64::NAN,
        ] {
            let want = ((v + 1.0) / 0.25).floor().clamp(0.0, 7.0) as u32;
            assert_eq!(g.axis_cell(v, 0), want, "x {v}");
        }
        for v in [0.4f64, 0.5, 0.74, 0.75, 1.24, 1.25, 2.0] {
            let want = ((v - 0.5) / 0.25).floor().clamp(0.0, 2.0) as u32;
            assert_eq!(g.axis_cell(v, 1), want, "y {v}");
        }
        assert_eq!(g.cell_span((-0.9, -0.3), 0), Some((0, 2)));
        assert_eq!(g.cell_span((-5.0, -0.3), 0), Some((0, 2)));
        assert_eq!(g.cell_span((0.3, 5.0), 0), Some((5, 7)));
        assert_eq!(g.cell_span((-5.0, -1.5), 0), None);
        assert_eq!(g.cell_span((1.0, 5.0), 0), None);
        let open = Grid { open: true, ..g };
        assert_eq!(open.cell_span((-5.0, -1.5), 0), Some((0, 0)));
        assert_eq!(open.cell_span((1.0, f64::INFINITY), 0), Some((7, 7)));
    }

    #[test]
    fn the_radix_sort_is_a_stable_sort_by_the_high_half() {
        let mut s = Rng::new(3);
        // Over the whole array: one pass, two, three (a bound beyond 2^22), and two passes
        // over keys that all share their high digit (every key below 2^12).
        for (bound, n, below) in [
            (1usize, 10, 1u64),
            (300, 1000, 300),
            (5_000_000, 3000, 5_000_000),
            (1 << 30, 3000, 1 << 30),
            (1 << 20, 3000, 1 << 12),
            // Split by the top digit first (at least SPLIT_FROM items, keys beyond 12
            // bits): within the buckets one pass (20 bits), two (24, 30 bits), and keys
            // crowded into a few buckets (every key below 2^14 of 2^24).
            (1 << 20, 100_000, 1 << 20),
            (1 << 24, 100_000, 1 << 24),
            (1 << 30, 100_000, 1 << 30),
            (1 << 24, 100_000, 1 << 14),
            (5_000, 100_000, 5_000),
        ] {
            let mut items: Vec<u64> = (0..n)
                .map(|i| ((uni(&mut s) * below as f64) as u64).min(below - 1) << 32 | i)
                .collect();
            let mut want = items.clone();
            want.sort_by_key(|it| it >> 32);
            radix_sort_high(&mut items, bound);
            assert_eq!(items, want, "bound {bound}");
        }
    }

    #[test]
    fn rows_cover_every_point_inside_the_cylinder() {
        let mut s = Rng::new(11);
        let pts: Vec<[f32; 3]> = (0..20000)
            .map(|_| [uni(&mut s) as f32, uni(&mut s) as f32, uni(&mut s) as f32])
            .collect();
        let mut b = Aabb::empty();
        for p in &pts {
            b.extend(p64(*p));
        }
        let g = Grid::build(&pts, b, 0.05);
        for _ in 0..300 {
            let a = DVec3::new(uni(&mut s), uni(&mut s), uni(&mut s)) * 1.4 - 0.2;
            let c = DVec3::new(uni(&mut s), uni(&mut s), uni(&mut s)) * 1.4 - 0.2;
            let seg = Segment::new(a, c);
            let r = 0.01 + 0.1 * uni(&mut s);
            let cyl = Cylinder::new(&seg, r);
            let mut visited = vec![false; pts.len()];
            let mut touched = 0usize;
            g.visit_rows(&seg, r, |row| {
                for i in g.row_range(&row) {
                    visited[i] = true;
                    touched += 1;
                }
            });
            for (i, p) in g.points.iter().enumerate() {
                if cyl.test(p64(*p)).is_some() {
                    assert!(visited[i], "missed point {i} for {seg:?} r={r}");
                }
            }
            // The traversal is tight: far fewer points than the whole grid.
            assert!(touched < pts.len());
            // The ranges fetched ahead are the rows' own, in the same order.
            let mut want = Vec::new();
            g.visit_rows(&seg, r, |row| want.push(g.row_range(&row)));
            let (mut got, mut rows) = (Vec::new(), vec![(7, 9); 3]);
            g.visit_ranges(&seg, r, &mut rows, |range| got.push(range));
            assert_eq!(got, want, "{seg:?} r={r}");
        }
    }

    #[test]
    fn segment_outside_the_grid_visits_nothing() {
        let pts = vec![[0.0f32, 0.0, 0.0], [1.0, 1.0, 1.0]];
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        let g = Grid::build(&pts, b, 0.1);
        let mut n = 0;
        g.visit_rows(
            &Segment::new(DVec3::new(5.0, 5.0, 5.0), DVec3::new(6.0, 5.0, 5.0)),
            0.1,
            |_| n += 1,
        );
        assert_eq!(n, 0);
    }

    #[test]
    fn huge_scene_caps_the_cell_table() {
        let pts = vec![[0.0f32, 0.0, 0.0], [1000.0, 1000.0, 1000.0]];
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::splat(1000.0),
        };
        let g = Grid::build(&pts, b, 0.03);
        assert!(g.n_cells() as f64 <= MAX_CELLS);
        assert!(g.cell > 0.03);
    }

    #[test]
    fn a_host_grid_may_pass_the_cap_from_about_ten_million_points() {
        // The cell table's cap: 2^24 for any grid; 1.5 cells a point for a host grid once
        // that is more (from 1.1 x 10^7 points), so 10^8 points get 10^7's cells.
        assert_eq!(max_cells(10_000_000, true), MAX_CELLS);
        assert_eq!(max_cells(10_000_000, false), MAX_CELLS);
        assert_eq!(max_cells(100_000_000, false), MAX_CELLS);
        assert_eq!(max_cells(100_000_000, true), 1.5e8);
        assert_eq!(max_cells(1_000, true), 8_000.0);
        assert_eq!(max_cells(10, true), MIN_CELLS);
        assert_eq!(max_cells(usize::MAX / 4, true), (1u64 << 31) as f64);
        // Below that, the very grid of `build`.
        let mut s = Rng::new(9);
        let pts: Vec<[f32; 3]> = (0..5000)
            .map(|_| {
                [
                    uni(&mut s) as f32 * 50.0,
                    uni(&mut s) as f32,
                    uni(&mut s) as f32,
                ]
            })
            .collect();
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::new(50.0, 1.0, 1.0),
        };
        let (g, h) = (
            Grid::build(&pts, b, 0.01),
            Grid::build_for_host(&pts, b, 0.01),
        );
        assert_eq!((g.cell, g.dims, g.open), (h.cell, h.dims, h.open));
        assert_eq!(
            (&g.cell_start, &g.points, &g.ids),
            (&h.cell_start, &h.points, &h.ids)
        );
    }

    /// Points visited by the queries of `segs` and the exact counts they find.
    fn cost_and_counts(g: &Grid, segs: &[Segment], r: f64) -> (Vec<usize>, Vec<usize>) {
        let mut cost = Vec::new();
        let mut counts = Vec::new();
        for seg in segs {
            let cyl = Cylinder::new(seg, r);
            let (mut touched, mut inside) = (0, 0);
            g.visit_rows(seg, r, |row| {
                for i in g.row_range(&row) {
                    touched += 1;
                    inside += cyl.test(p64(g.points[i])).is_some() as usize;
                }
            });
            cost.push(touched);
            counts.push(inside);
        }
        (cost, counts)
    }

    #[test]
    fn a_far_flung_endpoint_and_floaters_cost_no_more_than_near_segments() {
        // A unit scene with 20,000 points, 30 segments in it, and a few floaters far away.
        let mut s = Rng::new(5);
        let mut pts: Vec<[f32; 3]> = (0..20000)
            .map(|_| [uni(&mut s) as f32, uni(&mut s) as f32, uni(&mut s) as f32])
            .collect();
        let near: Vec<Segment> = (0..30)
            .map(|_| {
                let a = DVec3::new(uni(&mut s), uni(&mut s), uni(&mut s));
                let b = DVec3::new(uni(&mut s), uni(&mut s), uni(&mut s));
                Segment::new(a, b)
            })
            .collect();
        let r = 0.03;
        let ws = WorkingSet::new(&pts, &near);
        let n_ws = ws.len();
        let g = Grid::build(&ws.points, ws.bounds, r);
        drop(ws);
        let (cost, counts) = cost_and_counts(&g, &near, r);
        // Now one endpoint flies to (1000, 1000, 1000), and floaters join the working set.
        for k in 0..10 {
            pts.push([900.0 + k as f32, 950.0, 990.0 - k as f32]);
        }
        let mut far = near.clone();
        far[0] = Segment::new(far[0].p1, DVec3::splat(1000.0));
        let ws_far = WorkingSet::new(&pts, &far);
        assert_eq!(ws_far.len(), n_ws + 10);
        let gf = Grid::build(&ws_far.points, ws_far.bounds, r);
        assert!(gf.n_cells() <= 8 * ws_far.len(), "{} cells", gf.n_cells());
        assert!(gf.cell <= 4.0 * r, "cells stay near r: {}", gf.cell);
        let (cost_f, counts_f) = cost_and_counts(&gf, &far, r);
        // Same answers for the other segments, at no more than about the same cost.
        assert_eq!(&counts_f[1..], &counts[1..]);
        for i in 1..near.len() {
            assert!(
                cost_f[i] <= 2 * cost[i] + 100,
                "segment {i}: {} points visited, {} before",
                cost_f[i],
                cost[i]
            );
        }
        // The far segment is exact (every point checked by brute force) and cheap.
        let cyl = Cylinder::new(&far[0], r);
        let brute = ws_far
            .points
            .iter()
            .filter(|p| cyl.test(p64(**p)).is_some())
            .count();
        assert_eq!(counts_f[0], brute);
        let longest = *cost.iter().max().unwrap();
        assert!(
            cost_f[0] <= 2 * longest + 100,
            "far segment visits {}",
            cost_f[0]
        );
        // Queries entirely among the floaters, beyond the core grid, still find them.
        let out = Segment::new(
            DVec3::new(899.0, 950.0, 991.0),
            DVec3::new(910.0, 950.0, 980.0),
        );
        let (_, c) = cost_and_counts(&gf, &[out], 0.5);
        assert_eq!(c[0], 10);
    }

    #[test]
    fn working_set_uses_the_grown_box() {
        let segs = [Segment::new(DVec3::ZERO, DVec3::new(10.0, 0.0, 0.0))];
        let c = [
            [-1.0f32, 0.0, 0.0],
            [-1.01, 0.0, 0.0],
            [5.0, 1.0, -1.0],
            [11.0, 0.0, 1.1],
        ];
        let ws = WorkingSet::new(&c, &segs);
        assert_eq!(*ws.points, [[-1.0f32, 0.0, 0.0], [5.0, 1.0, -1.0]]);
        assert!(matches!(ws.points, Cow::Owned(_)));
        // Every center inside: the caller's array itself, not a copy.
        let inside = [c[0], c[2]];
        let ws = WorkingSet::new(&inside, &segs);
        assert!(matches!(ws.points, Cow::Borrowed(p) if std::ptr::eq(p, &inside[..])));
    }
}
