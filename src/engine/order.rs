//! The order the queries of a batch are answered in, by both engines.

use crate::engine::Query;
use crate::geom::Segment;
use crate::index::Grid;
use glam::DVec3;
use rayon::prelude::*;

/// The order a batch's queries are answered in: along a Morton (Z-order) curve through
/// the cells holding their segments' midpoints, so that queries answered close together in
/// time walk neighbouring rows of the cell table and read neighbouring points, and share
/// cache lines: on the device, the lanes of one SIMD group or warp and the invocations in
/// flight together; on the CPU engine, the queries one thread answers one after the
/// other. In the caller's order (a file's, a step's) each query reads its own stretch of
/// memory, and a pass over the cylinders waits on memory: on lavapipe the kernels of the
/// bench scene's evaluation batch take a fifth less time in this order, and the CPU
/// engine's evaluation pass about 40 % less (`cargo bench --bench fit`, 10^6 x 10^4).
/// Answers are per query, so restoring the caller's order gives them bit for bit (the
/// coverage mask is a union, the same in any order).
pub struct SpatialOrder {
    /// `perm[j]`: the caller's index of the `j`-th query sent.
    perm: Vec<u32>,
}

impl SpatialOrder {
    pub fn new(grid: &Grid, queries: &[Query]) -> SpatialOrder {
        SpatialOrder::by_midpoints(grid, queries.len(), |i| queries[i].seg.midpoint())
    }

    /// The order of `segments` along the same curve.
    pub fn of_segments(grid: &Grid, segments: &[Segment]) -> SpatialOrder {
        SpatialOrder::by_midpoints(grid, segments.len(), |i| segments[i].midpoint())
    }

    /// `n` items in the order of their points `mid(i)` along the curve.
    fn by_midpoints(grid: &Grid, n: usize, mid: impl Fn(usize) -> DVec3 + Sync) -> SpatialOrder {
        // One u64 per query: the Morton code (its top 40 bits where the grid needs more)
        // above the query's index (24 bits), sorted as plain integers; ties keep the
        // caller's order.
        const INDEX_BITS: u32 = 24;
        let axis_bits =
            32 - (grid.dims.iter().max().copied().unwrap_or(1).max(1) - 1).leading_zeros();
        let shift = (3 * axis_bits).saturating_sub(64 - INDEX_BITS);
        let code = |i: usize| {
            // `cell_xyz` clamps into the grid (an invalid segment's NaN midpoint: cell
            // 0). The cell's own coordinates, not its linear index taken apart by four
            // integer divisions: the GPU engine's orderings at 10^6 x 10^4 took 3.2 ms
            // of host time that way against 2.5 ms so (probes, not committed).
            let [x, y, z] = grid.cell_xyz(mid(i));
            morton3(x, y, z)
        };
        if n >= 1 << INDEX_BITS {
            let mut keys: Vec<(u64, u32)> = (0..n)
                .into_par_iter()
                .map(|i| (code(i), i as u32))
                .collect();
            keys.par_sort_unstable();
            return SpatialOrder {
                perm: keys.into_iter().map(|(_, i)| i).collect(),
            };
        }
        let code_bits = 3 * axis_bits;
        if code_bits <= 32 {
            // The code in the high half, the index in the low: a stable radix sort by the
            // high half gives the very order of the sort below (ties in the caller's
            // order), in two or three passes over the keys. With a comparison sort the
            // GPU engine's orderings at 10^6 x 10^4 took 4.3 ms of host time on two
            // threads, 40–60 ns a query; 2.8 ms so (probes, not committed).
            let mut keys: Vec<u64> = (0..n)
                .into_par_iter()
                .with_min_len(ORDER_TASK)
                .map(|i| code(i) << 32 | i as u64)
                .collect();
            crate::index::radix_sort_high(&mut keys, 1usize << code_bits);
            return SpatialOrder {
                perm: keys.into_iter().map(|k| k as u32).collect(),
            };
        }
        let mut keys: Vec<u64> = (0..n)
            .into_par_iter()
            .with_min_len(ORDER_TASK)
            .map(|i| (code(i) >> shift) << INDEX_BITS | i as u64)
            .collect();
        keys.par_sort_unstable();
        let mask = (1u64 << INDEX_BITS) - 1;
        SpatialOrder {
            perm: keys.into_iter().map(|k| (k & mask) as u32).collect(),
        }
    }

    /// The caller's index of the `j`-th query sent.
    pub fn index(&self, j: usize) -> usize {
        self.perm[j] as usize
    }

    /// `xs` (one per query, in the caller's order) in the order sent, gathered by every
    /// thread (a batch's queries on one thread: 0.1–0.4 ms a batch at 10^4–2 x 10^4).
    pub fn apply<T: Clone + Send + Sync>(&self, xs: &[T]) -> Vec<T> {
        self.perm
            .par_iter()
            .with_min_len(ORDER_TASK)
            .map(|&i| xs[i as usize].clone())
            .collect()
    }

    /// [`Self::restore`] of plain values, gathered in parallel through the inverse
    /// permutation into one new array (no array of options, no serial scatter: at 3 x 10^6
    /// answers a batch those were hundreds of MB of fresh pages and a cache miss a
    /// value on one thread).
    pub fn restore_copied<T: Copy + Send + Sync>(&self, ys: &[T]) -> Vec<T> {
        if ys.is_empty() {
            return Vec::new();
        }
        debug_assert_eq!(ys.len(), self.perm.len());
        let mut inverse = vec![0u32; ys.len()];
        for (j, &i) in self.perm.iter().enumerate() {
            inverse[i as usize] = j as u32;
        }
        inverse
            .par_iter()
            .with_min_len(ORDER_TASK)
            .map(|&j| ys[j as usize])
            .collect()
    }

    /// Answers in the order sent, back in the caller's order (empty stays empty).
    pub fn restore<T>(&self, ys: Vec<T>) -> Vec<T> {
        if ys.is_empty() {
            return ys;
        }
        debug_assert_eq!(ys.len(), self.perm.len());
        let mut out: Vec<Option<T>> = (0..ys.len()).map(|_| None).collect();
        for (&i, y) in self.perm.iter().zip(ys) {
            out[i as usize] = Some(y);
        }
        out.into_iter()
            .map(|y| y.expect("a permutation fills every slot"))
            .collect()
    }
}

/// Queries a task of the ordering's parallel passes: a batch of 10^4 queries gives
/// every thread of a 16-thread machine work.
const ORDER_TASK: usize = 512;

/// Interleaves the low 21 bits of `x`, `y` and `z` (x lowest): the cell's Morton code.
fn morton3(x: u32, y: u32, z: u32) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut v = (v & 0x1F_FFFF) as u64;
        v = (v | v << 32) & 0x001F_0000_0000_FFFF;
        v = (v | v << 16) & 0x001F_0000_FF00_00FF;
        v = (v | v << 8) & 0x100F_00F0_0F00_F00F;
        v = (v | v << 4) & 0x10C3_0C30_C30C_30C3;
        v = (v | v << 2) & 0x1249_2492_4924_9249;
        v
    }
    spread(x) | spread(y) << 1 | spread(z) << 2
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{Aabb, Segment};
    use glam::DVec3;

    #[test]
    fn morton_codes_interleave_x_lowest() {
        assert_eq!(morton3(0, 0, 0), 0);
        assert_eq!(morton3(1, 0, 0), 0b001);
        assert_eq!(morton3(0, 1, 0), 0b010);
        assert_eq!(morton3(0, 0, 1), 0b100);
        assert_eq!(morton3(3, 0, 0), 0b001_001);
        assert_eq!(morton3(2, 3, 1), 0b011_110);
        // All 21 bits of each coordinate survive.
        let top = 1u32 << 20;
        assert_eq!(morton3(top, 0, 0), 1u64 << 60);
        assert_eq!(morton3(0, 0, top), 1u64 << 62);
    }

    fn grid_4x4x4() -> Grid {
        let pts: Vec<[f32; 3]> = (0..64)
            .map(|i| {
                [
                    (i % 4) as f32 + 0.5,
                    ((i / 4) % 4) as f32 + 0.5,
                    (i / 16) as f32 + 0.5,
                ]
            })
            .collect();
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::splat(3.99),
        };
        Grid::build(&pts, b, 1.0)
    }

    fn at(x: f64, y: f64, z: f64) -> Query {
        let p = DVec3::new(x, y, z);
        Query::new(Segment::new(p - DVec3::X * 0.1, p + DVec3::X * 0.1), 0.2)
    }

    #[test]
    fn queries_go_in_morton_order_and_answers_come_back_in_the_callers() {
        let g = grid_4x4x4();
        assert_eq!(g.dims, [4, 4, 4]);
        // Cells (3,3,3), (0,0,0), (1,0,0), (0,1,0), (0,0,1), and (0,0,0) again.
        let qs = [
            at(3.5, 3.5, 3.5),
            at(0.5, 0.5, 0.5),
            at(1.5, 0.5, 0.5),
            at(0.5, 1.5, 0.5),
            at(0.5, 0.5, 1.5),
            at(0.6, 0.4, 0.5),
        ];
        let order = SpatialOrder::new(&g, &qs);
        // Ties (queries 1 and 5 share a cell) keep the caller's order.
        assert_eq!(order.perm, vec![1, 5, 2, 3, 4, 0]);
        assert_eq!(order.index(5), 0);
        let sent = order.apply(&qs);
        assert_eq!(sent[0], qs[1]);
        assert_eq!(sent[5], qs[0]);
        // An answer computed from each sent query comes back to its own slot.
        let answers: Vec<f64> = sent
            .iter()
            .map(|q| q.seg.p1.x + 10.0 * q.seg.p1.z)
            .collect();
        let back = order.restore(answers);
        for (q, a) in qs.iter().zip(&back) {
            assert_eq!(*a, q.seg.p1.x + 10.0 * q.seg.p1.z);
        }
        assert!(order.restore(Vec::<f64>::new()).is_empty());
    }

    /// The order every path of `by_midpoints` must give: by the cell's Morton code (its
    /// top 40 bits), ties in the caller's order.
    fn stable_by_code(g: &Grid, qs: &[Query]) -> Vec<u32> {
        let axis_bits = 32 - (g.dims.iter().max().unwrap() - 1).leading_zeros();
        let shift = (3 * axis_bits).saturating_sub(40);
        let mut idx: Vec<u32> = (0..qs.len() as u32).collect();
        idx.sort_by_key(|&i| {
            let [x, y, z] = g.cell_xyz(qs[i as usize].seg.midpoint());
            morton3(x, y, z) >> shift
        });
        idx
    }

    /// Queries at random places of `g`'s box, a third of them in cells already taken
    /// (ties), some beyond the grid (clamped into its border cells).
    fn scattered(g: &Grid, n: usize, seed: u64) -> Vec<Query> {
        let mut rng = crate::synth::rng::Rng::new(seed);
        let ext = DVec3::new(g.dims[0] as f64, g.dims[1] as f64, g.dims[2] as f64) * g.cell;
        let mut qs: Vec<Query> = Vec::with_capacity(n);
        for i in 0..n {
            let q = if i % 3 == 2 {
                qs[rng.below(i as u64) as usize]
            } else {
                let u = DVec3::new(rng.range(-0.1, 1.1), rng.range(-0.1, 1.1), rng.uniform());
                let p = g.origin + u * ext;
                Query::new(Segment::new(p - DVec3::X * 0.01, p + DVec3::X * 0.01), 0.1)
            };
            qs.push(q);
        }
        qs
    }

    #[test]
    fn the_radix_and_the_wide_grid_paths_sort_by_code_with_ties_in_order() {
        // 64^3 cells (18-bit codes, the radix sort) and 4,000 x 1 x 1 cells (36-bit
        // codes, the comparison sort).
        let cube: Vec<[f32; 3]> = (0..1 << 18)
            .map(|i| {
                [
                    (i % 64) as f32,
                    ((i / 64) % 64) as f32,
                    (i / 4096 % 64) as f32,
                ]
            })
            .collect();
        let line: Vec<[f32; 3]> = (0..4000).map(|i| [i as f32, 0.0, 0.0]).collect();
        for (pts, dims) in [(cube, [64, 64, 64]), (line, [4000, 1, 1])] {
            let mut b = Aabb::empty();
            for p in &pts {
                b.extend(crate::geom::p64(*p));
            }
            let g = Grid::build(&pts, b, 1.0);
            assert_eq!(g.dims, dims);
            let qs = scattered(&g, 20_000, 5);
            let order = SpatialOrder::new(&g, &qs);
            assert_eq!(order.perm, stable_by_code(&g, &qs), "dims {dims:?}");
        }
    }
}
