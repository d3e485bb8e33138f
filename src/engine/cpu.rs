//! The CPU engine: rayon over queries, taken along a Morton curve through their midpoints
//! ([`super::order`]), exact f64 tests on the grid's rows. Each query sums its points in grid
//! order, so results do not depend on the thread count or the order of work.

use super::bound::ListBound;
use super::order::SpatialOrder;
use super::walk::{any_member, for_each_member, members_into};
use super::{
    Answers, Ask, Counters, Coverage, CylStats, Engine, EngineError, FitJob, Member, Nearest,
    NearestSum, Query,
};
use crate::geom::fit::FitResult;
use crate::geom::p64;
use crate::index::Grid;
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;

pub use super::walk::member_list;

pub struct CpuEngine {
    grid: Arc<Grid>,
    batches: AtomicU64,
    queries: AtomicU64,
}

impl CpuEngine {
    pub fn new(grid: Arc<Grid>) -> Self {
        CpuEngine {
            grid,
            batches: AtomicU64::new(0),
            queries: AtomicU64::new(0),
        }
    }

    /// The engine over `points` alone: a grid of `cell`-sized cells over their bounding
    /// box (for tests and small tools; a refinement builds its grid from the working set).
    pub fn over_points(points: &[[f32; 3]], cell: f64) -> Self {
        let mut b = crate::geom::Aabb::empty();
        for p in points {
            b.extend(p64(*p));
        }
        CpuEngine::new(Arc::new(Grid::build(points, b, cell)))
    }

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    fn count_batch(&self, n: usize) {
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.queries.fetch_add(n as u64, Ordering::Relaxed);
    }

    /// Calls `f(sorted index, t1, offset)` for each member of `X(q)`, in grid order.
    #[inline]
    fn for_each_member(&self, q: &Query, f: impl FnMut(usize, f64, DVec3)) {
        for_each_member(&self.grid, q, f)
    }

    /// One query of a fused batch: one walk over its rows gives the stats, the members'
    /// coverage bits (into `mask`, when given) and, when `nearest` is asked, its sums
    /// over the `k` members nearest to the line (ranked by `(d2, grid index)`).
    fn one(
        &self,
        i: usize,
        q: &Query,
        ask: &Ask<'_>,
        mask: Option<&[AtomicU64]>,
        members: &mut Vec<(f64, usize, DVec3)>,
    ) -> (CylStats, NearestSum) {
        let mut s = CylStats::default();
        let d = q.seg.dir();
        let g = &*self.grid;
        let want = ask.want;
        let near = ask.nearest != Nearest::No;
        members.clear();
        self.for_each_member(q, |j, _, v| {
            s.count += 1;
            if want.sums {
                s.sum_d2 += v.length_squared();
                s.sum_offset += v;
            }
            if want.sides && (p64(g.points[j]) - q.plane).dot(d) > 0.0 {
                s.side_pos += 1;
            }
            if let Some(mask) = mask {
                // A plain load first: a point inside several cylinders (copies and
                // pieces of one edge) pays the locked read-modify-write once.
                let (word, bit) = (&mask[j / 64], 1u64 << (j % 64));
                if word.load(Ordering::Relaxed) & bit == 0 {
                    word.fetch_or(bit, Ordering::Relaxed);
                }
            }
            if near {
                members.push((v.length_squared(), j, v));
            }
        });
        let mut out = NearestSum::default();
        let Some(k) = ask.nearest.k_of(i, s.count) else {
            return (s, out);
        };
        let k = (k as usize).min(members.len());
        out.k = k as u64;
        add_nearest(members, k, &mut out);
        (s, out)
    }
}

/// Adds to `acc` the sums of the `need` entries of `m` (squared distance, point index,
/// offset) nearest the line, ranked by (d2, index) and summed in that order: the one
/// ranking of both engines (the GPU engine's host path decides its boundary band with it).
pub(crate) fn add_nearest<I: Ord + Copy>(
    m: &mut [(f64, I, DVec3)],
    need: usize,
    acc: &mut NearestSum,
) {
    if need == 0 {
        return;
    }
    let order = |a: &(f64, I, DVec3), b: &(f64, I, DVec3)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    if need < m.len() {
        m.select_nth_unstable_by(need - 1, order);
    }
    let first = &mut m[..need];
    first.sort_unstable_by(order);
    for x in first.iter() {
        acc.sum_d2 += x.0;
        acc.sum_offset += x.2;
    }
}

/// [`Engine::members`] over `grid` on the host, f64: at most `bound.limit` members in
/// all ([`ListBound`]), else [`EngineError::Limit`] (no list holds more than what is left
/// of the bound while it is walked).
pub fn members_of(
    grid: &Grid,
    queries: &[Query],
    bound: &ListBound,
) -> Result<Vec<Vec<Member>>, EngineError> {
    let order = SpatialOrder::new(grid, queries);
    let listed = AtomicUsize::new(0);
    let over = AtomicBool::new(false);
    let lists = order.restore(
        (0..queries.len())
            .into_par_iter()
            .with_min_len(8)
            .map_init(Vec::new, |buf, j| {
                let left = bound.limit.saturating_sub(listed.load(Ordering::Relaxed));
                // Listed into a buffer the thread reuses, then copied once at its size.
                if over.load(Ordering::Relaxed)
                    || !members_into(grid, &queries[order.index(j)], buf, left)
                    || listed.fetch_add(buf.len(), Ordering::Relaxed) + buf.len() > bound.limit
                {
                    over.store(true, Ordering::Relaxed);
                    return Vec::new();
                }
                buf.clone()
            })
            .collect(),
    );
    if over.load(Ordering::Relaxed) {
        return Err(bound.exceeded(
            "the edge fit's decision rule (or --max-sagitta's check) on the CPU engine",
        ));
    }
    Ok(lists)
}

/// [`Engine::extent`] over `grid` on the host, f64.
pub fn extents_of(grid: &Grid, queries: &[Query]) -> Vec<super::Extent> {
    let order = SpatialOrder::new(grid, queries);
    let sent: Vec<super::Extent> = (0..queries.len())
        .into_par_iter()
        .with_min_len(8)
        .map(|j| extent_of(grid, &queries[order.index(j)]))
        .collect();
    order.restore_copied(&sent)
}

/// [`Engine::extent`] of one query on the host.
pub fn extent_of(grid: &Grid, q: &Query) -> super::Extent {
    let (mut e, l) = (super::Extent::default(), q.seg.length());
    for_each_member(grid, q, |_, t1, _| e.add(t1.clamp(0.0, l)));
    e
}

impl Engine for CpuEngine {
    fn backend(&self) -> &'static str {
        "cpu"
    }

    fn adapter(&self) -> String {
        format!("cpu ({} threads)", rayon::current_num_threads())
    }

    fn n_points(&self) -> usize {
        self.grid.len()
    }

    fn query(&self, queries: &[Query], ask: &Ask<'_>) -> Result<Answers, EngineError> {
        ask.nearest.check(queries.len())?;
        self.count_batch(queries.len());
        let mask: Option<Vec<AtomicU64>> = ask.coverage.then(|| {
            (0..self.grid.len().div_ceil(64))
                .map(|_| AtomicU64::new(0))
                .collect()
        });
        let order = SpatialOrder::new(&self.grid, queries);
        let sent = |j: usize, members: &mut Vec<(f64, usize, DVec3)>| {
            let i = order.index(j);
            self.one(i, &queries[i], ask, mask.as_deref(), members)
        };
        // Without nearest sums only the stats are collected (and restored).
        let (stats, nearest) = if ask.nearest == Nearest::No {
            let stats: Vec<CylStats> = (0..queries.len())
                .into_par_iter()
                .with_min_len(8)
                .map_init(Vec::new, |members, j| sent(j, members).0)
                .collect();
            (order.restore_copied(&stats), Vec::new())
        } else {
            let both: Vec<(CylStats, NearestSum)> = (0..queries.len())
                .into_par_iter()
                .with_min_len(8)
                .map_init(Vec::new, |members, j| sent(j, members))
                .collect();
            order.restore_copied(&both).into_iter().unzip()
        };
        Ok(Answers {
            stats,
            nearest,
            coverage: mask.map(|m| Coverage {
                mask: m.into_iter().map(|a| a.into_inner()).collect(),
            }),
        })
    }

    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<Member>>, EngineError> {
        self.count_batch(queries.len());
        members_of(&self.grid, queries, &ListBound::new()?)
    }

    /// The walks stop at their first member.
    fn occupied(&self, queries: &[Query]) -> Result<Vec<bool>, EngineError> {
        self.count_batch(queries.len());
        let order = SpatialOrder::new(&self.grid, queries);
        let sent: Vec<bool> = (0..queries.len())
            .into_par_iter()
            .with_min_len(8)
            .map(|j| any_member(&self.grid, &queries[order.index(j)]))
            .collect();
        Ok(order.restore_copied(&sent))
    }

    /// Only the axial positions, straight from the walk: no member records, no sort by
    /// id (the positions are sorted by value).
    fn axial(&self, queries: &[Query]) -> Result<Vec<Vec<f64>>, EngineError> {
        self.count_batch(queries.len());
        let order = SpatialOrder::new(&self.grid, queries);
        Ok(order.restore(
            (0..queries.len())
                .into_par_iter()
                .with_min_len(8)
                .map(|j| {
                    let q = &queries[order.index(j)];
                    let mut t = Vec::new();
                    self.for_each_member(q, |_, t1, _| t.push(t1));
                    super::sorted_axial(t.into_iter(), q.seg.length())
                })
                .collect(),
        ))
    }

    /// The ends of the axial positions straight from the walk: no list, no sort.
    fn extent(&self, queries: &[Query]) -> Result<Vec<super::Extent>, EngineError> {
        self.count_batch(queries.len());
        Ok(extents_of(&self.grid, queries))
    }

    /// Each segment's neighbourhood gathered once and iterated on in cache
    /// ([`super::fit::gathered`]): one batch, a query per step.
    fn fit_edges(&self, job: &FitJob<'_>) -> Result<FitResult, EngineError> {
        let (out, steps) = super::fit::gathered(&self.grid, job);
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.queries.fetch_add(steps, Ordering::Relaxed);
        Ok(out)
    }

    fn counters(&self) -> Counters {
        Counters {
            uploads: 0,
            batches: self.batches.load(Ordering::Relaxed),
            queries: self.queries.load(Ordering::Relaxed),
            ..Default::default()
        }
    }
}
