//! The CPU engine: rayon over queries, exact f64 tests on the grid's rows. Each query sums
//! its points in grid order, so results do not depend on the thread count.

use super::{Counters, Coverage, CylStats, Engine, EngineError, Member, NearestSum, Query, Want};
use crate::geom::{p64, Cylinder};
use crate::index::Grid;
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

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

    pub fn grid(&self) -> &Grid {
        &self.grid
    }

    fn count_batch(&self, n: usize) {
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.queries.fetch_add(n as u64, Ordering::Relaxed);
    }

    /// Calls `f(sorted index, t1, offset)` for each member of `X(q)`, in grid order.
    #[inline]
    fn for_each_member(&self, q: &Query, mut f: impl FnMut(usize, f64, DVec3)) {
        if !q.seg.is_valid() {
            return;
        }
        let cyl = Cylinder::new(&q.seg, q.r);
        let g = &*self.grid;
        g.visit_rows(&q.seg, q.r, |row| {
            let range = g.row_range(&row);
            let start = range.start;
            for (j, p) in g.points[range].iter().enumerate() {
                if let Some((t1, v)) = cyl.test(p64(*p)) {
                    f(start + j, t1, v);
                }
            }
        });
    }

    fn one_stats(&self, q: &Query, want: Want) -> CylStats {
        let mut s = CylStats::default();
        let d = q.seg.dir();
        let g = &*self.grid;
        if want.sides {
            self.for_each_member(q, |i, _, v| {
                s.count += 1;
                if want.sums {
                    s.sum_d2 += v.length_squared();
                    s.sum_offset += v;
                }
                if (p64(g.points[i]) - q.plane).dot(d) > 0.0 {
                    s.side_pos += 1;
                }
            });
        } else if want.sums {
            self.for_each_member(q, |_, _, v| {
                s.count += 1;
                s.sum_d2 += v.length_squared();
                s.sum_offset += v;
            });
        } else {
            self.for_each_member(q, |_, _, _| s.count += 1);
        }
        s
    }
}

/// [`Engine::members`] over `grid` on the host, f64; also the GPU engine's answer (the
/// per-point output has no kernel: it is O(members) to read back either way).
pub fn members_of(grid: &Grid, queries: &[Query]) -> Vec<Vec<Member>> {
    queries
        .par_iter()
        .with_min_len(8)
        .map(|q| {
            let mut out = Vec::new();
            if !q.seg.is_valid() {
                return out;
            }
            let cyl = Cylinder::new(&q.seg, q.r);
            grid.visit_rows(&q.seg, q.r, |row| {
                let range = grid.row_range(&row);
                let start = range.start;
                for (j, p) in grid.points[range].iter().enumerate() {
                    if let Some((t, offset)) = cyl.test(p64(*p)) {
                        out.push(Member {
                            id: grid.ids[start + j],
                            t,
                            offset,
                        });
                    }
                }
            });
            // Working-set order, not grid order: the grid's layout follows the working
            // box, so a far segment would otherwise reorder the members (and the fit's
            // sums) of every other segment in the last bits.
            out.sort_unstable_by_key(|m| m.id);
            out
        })
        .collect()
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

    fn stats(&self, queries: &[Query], want: Want) -> Result<Vec<CylStats>, EngineError> {
        self.count_batch(queries.len());
        Ok(queries
            .par_iter()
            .with_min_len(8)
            .map(|q| self.one_stats(q, want))
            .collect())
    }

    fn nearest(&self, queries: &[Query], k: &[u64]) -> Result<Vec<NearestSum>, EngineError> {
        if k.len() != queries.len() {
            return Err(EngineError::BadQuery {
                index: k.len().min(queries.len()),
                why: format!("{} queries but {} k values", queries.len(), k.len()),
            });
        }
        self.count_batch(queries.len());
        Ok(queries
            .par_iter()
            .zip(k.par_iter())
            .with_min_len(8)
            .map_init(
                Vec::new,
                |members: &mut Vec<(f64, usize, DVec3)>, (q, &k)| {
                    members.clear();
                    self.for_each_member(q, |i, _, v| members.push((v.length_squared(), i, v)));
                    let k = (k as usize).min(members.len());
                    let mut out = NearestSum {
                        k: k as u64,
                        ..Default::default()
                    };
                    if k == 0 {
                        return out;
                    }
                    let order = |a: &(f64, usize, DVec3), b: &(f64, usize, DVec3)| {
                        a.0.total_cmp(&b.0).then(a.1.cmp(&b.1))
                    };
                    if k < members.len() {
                        members.select_nth_unstable_by(k - 1, order);
                    }
                    let first = &mut members[..k];
                    first.sort_unstable_by(order);
                    for m in first.iter() {
                        out.sum_d2 += m.0;
                        out.sum_offset += m.2;
                    }
                    out
                },
            )
            .collect())
    }

    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<Member>>, EngineError> {
        self.count_batch(queries.len());
        Ok(members_of(&self.grid, queries))
    }

    fn coverage(&self, queries: &[Query]) -> Result<Coverage, EngineError> {
        self.count_batch(queries.len());
        let words = self.grid.len().div_ceil(64);
        let mask: Vec<AtomicU64> = (0..words).map(|_| AtomicU64::new(0)).collect();
        queries.par_iter().for_each(|q| {
            self.for_each_member(q, |i, _, _| {
                mask[i / 64].fetch_or(1u64 << (i % 64), Ordering::Relaxed);
            })
        });
        Ok(Coverage {
            mask: mask.into_iter().map(|a| a.into_inner()).collect(),
        })
    }

    fn counters(&self) -> Counters {
        Counters {
            uploads: 0,
            batches: self.batches.load(Ordering::Relaxed),
            queries: self.queries.load(Ordering::Relaxed),
        }
    }
}
