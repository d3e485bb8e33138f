//! The walk of one query over the grid on the host: every member of `X(q)`, in grid order
//! ([`for_each_member`]) or as a list in working-set order ([`member_list`]). The CPU
//! engine answers with it, and the edge fit's host path gathers with it.

use super::{Member, Query};
use crate::geom::{p64, Cylinder};
use crate::index::Grid;
use glam::DVec3;

thread_local! {
    /// Each thread's scratch rows for [`Grid::visit_ranges`].
    static ROWS: std::cell::RefCell<Vec<(u32, u32)>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Calls `f(sorted index, t1, offset)` for each member of `X(q)` in `grid`, in grid order:
/// the walk of every CPU-engine answer.
#[inline]
pub(crate) fn for_each_member(grid: &Grid, q: &Query, mut f: impl FnMut(usize, f64, DVec3)) {
    if !q.seg.is_valid() {
        return;
    }
    let cyl = Cylinder::new(&q.seg, q.r);
    ROWS.with_borrow_mut(|rows| {
        grid.visit_ranges(&q.seg, q.r, rows, |range| {
            let start = range.start;
            for (j, p) in grid.points[range].iter().enumerate() {
                if let Some((t1, v)) = cyl.test(p64(*p)) {
                    f(start + j, t1, v);
                }
            }
        })
    });
}

/// Whether `X(q)` has a member in `grid`: the walk of [`for_each_member`], stopped at the
/// first member found (the rows after it are not read).
pub(crate) fn any_member(grid: &Grid, q: &Query) -> bool {
    if !q.seg.is_valid() {
        return false;
    }
    let cyl = Cylinder::new(&q.seg, q.r);
    let mut found = false;
    ROWS.with_borrow_mut(|rows| {
        grid.visit_ranges(&q.seg, q.r, rows, |range| {
            if !found {
                found = grid.points[range]
                    .iter()
                    .any(|p| cyl.test(p64(*p)).is_some());
            }
        })
    });
    found
}

/// The members of one query on the host, in working-set order.
pub fn member_list(grid: &Grid, q: &Query) -> Vec<Member> {
    let mut out = Vec::new();
    members_into(grid, q, &mut out, usize::MAX);
    out
}

/// [`member_list`] into `out` (cleared first), when `q` has at most `most` members;
/// `false` (and `out` left empty) when it has more: the walk then holds no more than
/// `most` of them at any time.
pub(crate) fn members_into(grid: &Grid, q: &Query, out: &mut Vec<Member>, most: usize) -> bool {
    out.clear();
    // Working-set order, not grid order: the grid's layout follows the working
    // box, so a far segment would otherwise reorder the members (and the fit's
    // sums) of every other segment in the last bits. Measured in grid order, then
    // ordered by 8-byte keys (`id` above the place of the measurement; ids are unique)
    // and copied out: sorting the 40-byte members themselves cost more.
    ORDER.with_borrow_mut(|(keys, found)| {
        keys.clear();
        found.clear();
        let mut over = false;
        for_each_member(grid, q, |j, t, offset| {
            if found.len() == most {
                over = true;
                return;
            }
            keys.push((grid.ids[j] as u64) << 32 | found.len() as u64);
            found.push((t, offset));
        });
        if over {
            keys.clear();
            found.clear();
            return false;
        }
        keys.sort_unstable();
        out.extend(keys.iter().map(|&k| {
            let (t, offset) = found[k as u32 as usize];
            Member {
                id: (k >> 32) as u32,
                t,
                offset,
            }
        }));
        true
    })
}

/// Sort keys (working-set id above the place of a measurement) and the measurements
/// (axial position, offset) they point into.
type Keyed = (Vec<u64>, Vec<(f64, DVec3)>);

thread_local! {
    /// [`members_into`]'s keys and measurements, reused from query to query.
    static ORDER: std::cell::RefCell<Keyed> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

#[cfg(test)]
mod tests {
    use super::super::cpu::CpuEngine;
    use super::super::dedup::Dedup;
    use super::super::{Engine, Want};
    use super::*;
    use crate::geom::Segment;
    use crate::synth::Rng;

    /// Points in a unit cube and segments across it, some far outside, some degenerate,
    /// some touching a single point exactly on their cylinder's cap or wall.
    fn scene() -> (Vec<[f32; 3]>, Vec<Query>) {
        let mut rng = Rng::new(11);
        let mut u = || rng.uniform() as f32;
        let mut pts: Vec<[f32; 3]> = (0..3000).map(|_| [u(), u(), u()]).collect();
        pts.push([5.0, 5.0, 5.0]);
        let mut rng = Rng::new(12);
        let mut v = || DVec3::new(rng.uniform(), rng.uniform(), rng.uniform()) * 1.4 - 0.2;
        let mut qs: Vec<Query> = (0..400)
            .map(|i| {
                let r = [0.002, 0.01, 0.05][i % 3];
                Query::new(Segment::new(v(), v()), r)
            })
            .collect();
        let p = DVec3::new(5.0, 5.0, 5.0);
        // The lone point on the cap, on the wall, just outside the wall, far away.
        qs.push(Query::new(Segment::new(p, p + DVec3::X), 0.01));
        qs.push(Query::new(
            Segment::new(p + DVec3::Y * 0.01, p + DVec3::new(1.0, 0.01, 0.0)),
            0.01,
        ));
        qs.push(Query::new(
            Segment::new(p + DVec3::Y * 0.011, p + DVec3::new(1.0, 0.011, 0.0)),
            0.01,
        ));
        qs.push(Query::new(Segment::new(p * 3.0, p * 3.0 + DVec3::X), 0.01));
        qs.push(Query::new(Segment::new(p, p), 0.01));
        (pts, qs)
    }

    #[test]
    fn any_member_is_a_count_above_zero() {
        let (pts, qs) = scene();
        let cpu = CpuEngine::over_points(&pts, 0.02);
        let counts = cpu.stats(&qs, Want::COUNT).unwrap();
        let any: Vec<bool> = qs.iter().map(|q| any_member(cpu.grid(), q)).collect();
        let expect: Vec<bool> = counts.iter().map(|s| s.count > 0).collect();
        assert_eq!(any, expect);
        let n = expect.iter().filter(|&&x| x).count();
        assert!(n > 100 && n < qs.len() - 50, "{n} of {} occupied", qs.len());
        assert_eq!(&expect[qs.len() - 5..], [true, true, false, false, false]);
        assert_eq!(cpu.occupied(&qs).unwrap(), expect);
    }

    #[test]
    fn occupied_counts_its_batch_like_a_batch_of_counts() {
        let (pts, mut qs) = scene();
        // Copies of queries: Dedup asks the inner engine each distinct query once.
        let copies = qs[..50].to_vec();
        qs.extend(copies);
        let grid = std::sync::Arc::new(CpuEngine::over_points(&pts, 0.02).grid().clone());
        let a = Dedup::new(Box::new(CpuEngine::new(grid.clone())));
        let b = Dedup::new(Box::new(CpuEngine::new(grid)));
        let occ = a.occupied(&qs).unwrap();
        let counts = b.stats(&qs, Want::COUNT).unwrap();
        assert_eq!(occ, counts.iter().map(|s| s.count > 0).collect::<Vec<_>>());
        let (ca, cb) = (a.counters(), b.counters());
        assert_eq!((ca.batches, ca.queries), (cb.batches, cb.queries));
        assert_eq!(ca.queries, qs.len() as u64 - 50);
        assert_eq!(a.asked(), b.asked());
    }
}
