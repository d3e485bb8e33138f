//! The host's share of a batch: the flagged points decided in f64 with the CPU engine's
//! own test ([`Cylinder::test`]), the k-nearest cut band ranked exactly, and the rare query
//! answered wholly here.

use super::layout::{Plan, QResult, ALL_BELOW, FLAG_CANDIDATE, STATUS_HOST};
use crate::engine::cpu::add_nearest;
use crate::engine::{CylStats, Member, NearestSum, Query};
use crate::geom::{p64, Cylinder};
use crate::index::Grid;
use glam::DVec3;

/// For each of `n` query slots, its run of `flags` (sorted by query).
pub fn spans(flags: &[(u32, u32)], n: usize) -> Vec<std::ops::Range<usize>> {
    let mut spans = vec![0..0; n];
    let mut a = 0;
    while a < flags.len() {
        let q = (flags[a].0 & !FLAG_CANDIDATE) as usize;
        let mut b = a;
        while b < flags.len() && (flags[b].0 & !FLAG_CANDIDATE) as usize == q {
            b += 1;
        }
        if q < n {
            spans[q] = a..b;
        }
        a = b;
    }
    spans
}

pub(in crate::engine::gpu) fn valid(q: &Query) -> bool {
    q.seg.is_valid() && q.r.is_finite() && q.r >= 0.0
}

/// Whether sorted point `i` is in `X(q)`, exactly as the CPU engine decides it.
pub fn is_member(grid: &Grid, q: &Query, i: u32) -> bool {
    valid(q)
        && Cylinder::new(&q.seg, q.r)
            .test(p64(grid.points[i as usize]))
            .is_some()
}

/// Adds sorted point `i` to `s` when it is a member of `X(q)`.
pub fn add_member(grid: &Grid, q: &Query, i: u32, s: &mut CylStats) {
    if !valid(q) {
        return;
    }
    let p = p64(grid.points[i as usize]);
    if let Some((_, v)) = Cylinder::new(&q.seg, q.r).test(p) {
        s.count += 1;
        s.sum_d2 += v.length_squared();
        s.sum_offset += v;
        if (p - q.plane).dot(q.seg.dir()) > 0.0 {
            s.side_pos += 1;
        }
    }
}

/// Calls `f(sorted index)` for each member of `X(q)`, in grid order (as the CPU engine).
pub fn for_each_member(grid: &Grid, q: &Query, mut f: impl FnMut(usize)) {
    if !valid(q) {
        return;
    }
    let cyl = Cylinder::new(&q.seg, q.r);
    grid.visit_rows(&q.seg, q.r, |row| {
        let range = grid.row_range(&row);
        let start = range.start;
        for (j, p) in grid.points[range].iter().enumerate() {
            if cyl.test(p64(*p)).is_some() {
                f(start + j);
            }
        }
    });
}

/// The whole answer of one query on the host.
pub fn stats(grid: &Grid, q: &Query) -> CylStats {
    let mut s = CylStats::default();
    for_each_member(grid, q, |i| add_member(grid, q, i as u32, &mut s));
    s
}

/// `(d2, index, offset)` of member `i`.
fn ranked(grid: &Grid, cyl: &Cylinder, i: u32) -> (f64, u32, DVec3) {
    let w = p64(grid.points[i as usize]) - cyl.p1;
    let v = w - cyl.d * w.dot(cyl.d);
    (v.length_squared(), i, v)
}

/// The exact k nearest from the device's sums below the cut, the candidates of the cut
/// band and the members among the boundary points (`flags`: this query's, sorted).
///
/// The device's histogram holds the sure members `D`; the host adds the boundary members
/// `M`. With `e` the bound of the f32 error of d2 and `[lo, hi]` the plan's band, every
/// point with f64 d2 `< lo + e` is below the cut bin and every one in a bin up to it has
/// f64 d2 `<= hi - e`. So when fewer than k points (`before` of `D`, plus those of `M`) can
/// lie below `lo + e`, and at least k (`upto`, plus those of `M`) lie up to `hi - e`, the
/// k-th distance is in that band: everything below it is in the set, nothing above, and
/// the host ranks only the band. `None` when that does not hold (or a count is
/// inconsistent): the caller then answers the query on the host. Also returns `N(s)`
/// (the sure members and the boundary ones that are members).
pub fn nearest(
    grid: &Grid,
    q: &Query,
    k: u64,
    r: &QResult,
    plan: Option<&Plan>,
    flags: &[(u32, u32)],
) -> Option<(NearestSum, u64)> {
    if r.status & STATUS_HOST != 0 {
        return None;
    }
    let plan = plan?;
    let cyl = Cylinder::new(&q.seg, q.r);
    let mut boundary: Vec<(f64, u32, DVec3)> = flags
        .iter()
        .filter(|f| f.0 & FLAG_CANDIDATE == 0 && is_member(grid, q, f.1))
        .map(|f| ranked(grid, &cyl, f.1))
        .collect();
    let total = plan.total as u64 + boundary.len() as u64;
    let k = k.min(total);
    let mut out = NearestSum {
        k,
        ..Default::default()
    };
    if k == 0 {
        return Some((out, total));
    }
    let dev = super::query::stats_of(r, grid.cell);
    out.sum_d2 = dev.sum_d2;
    out.sum_offset = dev.sum_offset;
    let add_all = |m: &[(f64, u32, DVec3)], out: &mut NearestSum| {
        for x in m {
            out.sum_d2 += x.0;
            out.sum_offset += x.2;
        }
    };
    if plan.cut == ALL_BELOW {
        // The device summed every sure member: right only when all members are wanted.
        if k == total && dev.count == plan.total as u64 {
            add_all(&boundary, &mut out);
            return Some((out, total));
        }
        return None;
    }
    let c2 = grid.cell * grid.cell;
    let e2 = super::query::e2_of(grid, q);
    let t_lo = (plan.lo as f64 + e2) * c2;
    let t_hi = (plan.hi as f64 - e2) * c2;
    boundary.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let n_low = boundary.partition_point(|x| x.0 < t_lo);
    let n_upto = boundary.partition_point(|x| x.0 <= t_hi);
    if plan.before as u64 + n_low as u64 >= k || (plan.upto as u64 + n_upto as u64) < k {
        return None;
    }
    let mut band: Vec<(f64, u32, DVec3)> = flags
        .iter()
        .filter(|f| f.0 & FLAG_CANDIDATE != 0)
        .map(|f| ranked(grid, &cyl, f.1))
        .collect();
    band.extend_from_slice(&boundary[n_low..n_upto]);
    let fixed = dev.count + n_low as u64;
    if fixed > k || fixed + (band.len() as u64) < k {
        return None;
    }
    add_all(&boundary[..n_low], &mut out);
    add_nearest(&mut band, (k - fixed) as usize, &mut out);
    Some((out, total))
}

/// The exact k nearest on the host alone, and `N(s)`.
pub fn exact_nearest(grid: &Grid, q: &Query, k: u64) -> (NearestSum, u64) {
    let cyl = Cylinder::new(&q.seg, q.r);
    let mut m: Vec<(f64, u32, DVec3)> = Vec::new();
    for_each_member(grid, q, |i| m.push(ranked(grid, &cyl, i as u32)));
    let k = (k as usize).min(m.len());
    let mut out = NearestSum {
        k: k as u64,
        ..Default::default()
    };
    add_nearest(&mut m, k, &mut out);
    (out, m.len() as u64)
}

/// One query's members from the device's sure members (`sure`, sorted indices) and its
/// flagged points (`flags`), each decided and measured with the CPU engine's own f64 test
/// and sorted by working-set id: the CPU engine's list, bit for bit. `None` when the
/// device named a point that is not in the grid (the caller then answers on the host).
///
/// The points are measured in the order the device names them (sure members by sorted
/// index: the grid's memory order, read front to back), and the accepted ones then put in
/// working-set order by 8-byte keys (`id` above the place of the measurement: ids are
/// unique, so the order is the CPU engine's) and copied out in that order. Measuring in
/// working-set order instead read the grid's points at random (a cache miss a member at
/// 10^7 points); sorting the 40-byte members instead of keys took a third of the host's
/// time for the edge-fit gate's lists.
pub fn members(
    grid: &Grid,
    q: &Query,
    sure: &[u32],
    flags: &[(u32, u32)],
    out: &mut Vec<Member>,
) -> Option<()> {
    out.clear();
    if !q.seg.is_valid() {
        return Some(());
    }
    let cyl = Cylinder::new(&q.seg, q.r);
    let flagged = flags
        .iter()
        .filter(|f| f.0 & FLAG_CANDIDATE == 0)
        .map(|f| f.1);
    KEYS.with_borrow_mut(|(keys, measured)| {
        keys.clear();
        measured.clear();
        for (j, i) in sure.iter().copied().chain(flagged).enumerate() {
            if let Some(&ahead) = sure.get(j + PREFETCH_AHEAD) {
                prefetch(grid, ahead as usize);
            }
            let id = *grid.ids.get(i as usize)?;
            if let Some(m) = cyl.test(p64(grid.points[i as usize])) {
                keys.push((id as u64) << 32 | measured.len() as u64);
                measured.push(m);
            }
        }
        keys.sort_unstable();
        out.extend(keys.iter().map(|&k| {
            let (t, offset) = measured[k as u32 as usize];
            Member {
                id: (k >> 32) as u32,
                t,
                offset,
            }
        }));
        Some(())
    })
}

/// [`members`] from a members batch's records (`kernels/records.rs`: each sure member's
/// working-set id and its centre's own f32 coordinates, in working-set order where the
/// device ranked the list): each measured in f64 from its record as the CPU engine
/// measures it, the flagged points decided from the grid, and the list sorted by id only
/// where it is not in that order already (a list the device did not rank, or a flagged
/// member; `Some(true)` where it sorted). `None` when a record or a flag names no point
/// of the grid.
pub fn members_of_records(
    grid: &Grid,
    q: &Query,
    records: &[[u32; 4]],
    flags: &[(u32, u32)],
    out: &mut Vec<Member>,
) -> Option<bool> {
    out.clear();
    if !q.seg.is_valid() {
        return Some(false);
    }
    let cyl = Cylinder::new(&q.seg, q.r);
    let n = grid.ids.len();
    let (mut sorted, mut last) = (true, None::<u32>);
    let mut add = |id: u32, p: [f32; 3], out: &mut Vec<Member>| {
        if let Some((t, offset)) = cyl.test(p64(p)) {
            sorted &= last.is_none_or(|l| l < id);
            last = Some(id);
            out.push(Member { id, t, offset });
        }
    };
    for r in records {
        if r[0] as usize >= n {
            return None;
        }
        let p = [r[1], r[2], r[3]].map(f32::from_bits);
        add(r[0], p, out);
    }
    for f in flags.iter().filter(|f| f.0 & FLAG_CANDIDATE == 0) {
        let i = f.1 as usize;
        add(*grid.ids.get(i)?, *grid.points.get(i)?, out);
    }
    if !sorted {
        out.sort_unstable_by_key(|m| m.id);
    }
    Some(!sorted)
}

/// How many sure members ahead [`members`] asks the cache for: a list is a few dozen runs
/// of consecutive indices, one a cell row, and each run's first points are a miss of
/// their own at 10^7 points (the id and the centre: two arrays of 40 and 120 MB).
const PREFETCH_AHEAD: usize = 16;

/// Asks the cache for sorted point `i`'s id and centre (no effect on results; none
/// where `i` is out of range or the target has no prefetch instruction).
#[inline(always)]
fn prefetch(grid: &Grid, i: usize) {
    #[cfg(target_arch = "x86_64")]
    if let (Some(id), Some(p)) = (grid.ids.get(i), grid.points.get(i)) {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: a prefetch is a hint that reads nothing and faults on no address; both
        // pointers are to live elements.
        unsafe {
            _mm_prefetch::<_MM_HINT_T0>((id as *const u32).cast());
            _mm_prefetch::<_MM_HINT_T0>((p as *const [f32; 3]).cast());
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (grid, i);
}

/// Sort keys (working-set id above the place of a measurement) and the measurements
/// (axial position, offset) they point into.
type Keyed = (Vec<u64>, Vec<(f64, DVec3)>);

thread_local! {
    /// [`members`]' keys and measurements, reused from query to query on each thread.
    static KEYS: std::cell::RefCell<Keyed> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}
