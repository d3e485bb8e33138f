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

/// The members of one query on the host, in working-set order.
pub fn member_list(grid: &Grid, q: &Query) -> Vec<Member> {
    let mut out = Vec::new();
    members_into(grid, q, &mut out);
    out
}

/// [`member_list`] into `out` (cleared first).
pub(crate) fn members_into(grid: &Grid, q: &Query, out: &mut Vec<Member>) {
    out.clear();
    // Working-set order, not grid order: the grid's layout follows the working
    // box, so a far segment would otherwise reorder the members (and the fit's
    // sums) of every other segment in the last bits. Measured in grid order, then
    // ordered by 8-byte keys (`id` above the place of the measurement; ids are unique)
    // and copied out: sorting the 40-byte members themselves cost more.
    ORDER.with_borrow_mut(|(keys, found)| {
        keys.clear();
        found.clear();
        for_each_member(grid, q, |j, t, offset| {
            keys.push((grid.ids[j] as u64) << 32 | found.len() as u64);
            found.push((t, offset));
        });
        keys.sort_unstable();
        out.extend(keys.iter().map(|&k| {
            let (t, offset) = found[k as u32 as usize];
            Member {
                id: (k >> 32) as u32,
                t,
                offset,
            }
        }));
    });
}

/// Sort keys (working-set id above the place of a measurement) and the measurements
/// (axial position, offset) they point into.
type Keyed = (Vec<u64>, Vec<(f64, DVec3)>);

thread_local! {
    /// [`members_into`]'s keys and measurements, reused from query to query.
    static ORDER: std::cell::RefCell<Keyed> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}
