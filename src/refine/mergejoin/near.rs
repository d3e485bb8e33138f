//! Which pairs of a group can pass the CPU part of a rule at all: an interval sweep along
//! the group's main direction, so that a restart looks at the pairs that can overlap or
//! join, not at every pair of a cluster of thousands of pieces of one edge.
//!
//! Both rules need the two segments close in space, by a distance bounded by their lengths
//! (docs/method.md#step-8-merge-and-join; `p` the parameters, `L` lengths, `G` the longer
//! of a merge pair and `S` the shorter, `θ` `merge_angle_deg`):
//!
//! - a merge needs `S` to overlap `G` and an endpoint of `S` within `lim = merge_dist_frac
//!   L_G` of `G`'s line. When a point of `S` projects onto `G` itself, the line distance
//!   grows by at most `L_S` along `S`, so `dist(S, G) <= lim + L_S`; when a point of `G`
//!   projects onto `S` (fix `merge_overlap`), the directions within `θ` put `S`'s near
//!   endpoint within `(L_S + lim) / cos θ` of that point along `G`'s line, so
//!   `dist <= (L_S + lim) / cos θ + lim`;
//! - a join needs the middle two of the four sorted endpoints within `join_gap_frac x` both
//!   lengths. From different segments they bound the distance by that; both from one
//!   segment means a gap of that segment's whole length, impossible for `join_gap_frac < 1`
//!   (and with the authors' order, by distance from `a.P1`, `a.P1` comes first, so both
//!   would be `b`'s, within `L_a` of `a.P1`).
//!
//! So `dist(a, b) <= k (L_a + L_b)` with `k` from the parameters alone. The distance
//! between two segments is at least the gap between their projections on any unit
//! direction `d`: each item's projection widened by `k L` on both sides (and a rounding
//! slack) must meet the other's. A pair whose intervals do not meet fails the rule's CPU
//! part, so leaving it out changes no decision (the tests compare with the sequential
//! loops). Without a bound (`merge_angle_deg >= 90`; `join_gap_frac >= 1` with the fix
//! `join_order`) and in small groups every pair is listed, as the loops state.
//!
//! The intervals live in buckets along `d`; an item whose segment changes is filed into
//! the buckets its new interval adds, and stale entries are filtered by the exact interval
//! test when read.

use super::{Ctx, Item, Mode};
use glam::DVec3;

/// Groups smaller than this list every pair (cheaper than the buckets).
pub(super) const SWEEP_FROM: usize = 48;

/// Most buckets per item.
const BUCKETS_PER_ITEM: f64 = 2.0;

pub(super) enum Near {
    /// Every pair.
    All {
        m: usize,
    },
    Swept(Box<Sweep>),
}

pub(super) struct Sweep {
    d: DVec3,
    /// Widening per unit length, and the rounding slack.
    k: f64,
    slack: f64,
    lo: Vec<f64>,
    hi: Vec<f64>,
    /// Bucket `b` covers `[b0 + b w, b0 + (b + 1) w)`; the end buckets also hold what lies
    /// beyond.
    b0: f64,
    inv_w: f64,
    buckets: Vec<Vec<u32>>,
    /// The buckets an item is filed in (inclusive).
    filed: Vec<(u32, u32)>,
    /// Per item, the last query that met it (to list it once).
    seen: Vec<u32>,
    query: u32,
    /// Entries in `buckets` in all (they are never taken out).
    entries: usize,
}

/// `k` of the module comment for the rules `mode` runs; `None` without a bound.
pub(super) fn widening(cx: &Ctx) -> Option<f64> {
    let p = cx.p;
    let join = if p.join_gap_frac < 0.999 {
        p.join_gap_frac
    } else if !cx.fixes.join_order {
        p.join_gap_frac.max(1.0)
    } else {
        return None;
    };
    match cx.mode {
        Mode::Collinear => Some(join),
        Mode::Cluster => {
            let cos = p.merge_angle_deg.to_radians().cos();
            if cos.is_nan() || cos <= 1e-6 {
                return None;
            }
            let frac = p.merge_dist_frac;
            let merge = frac.max(1.0) / cos + frac;
            let k = merge.max(join);
            k.is_finite().then_some(k)
        }
    }
}

/// The main direction of the segments: the top eigenvector of `sum L d d^T`.
fn main_direction(items: &[Item]) -> DVec3 {
    let mut m = [DVec3::ZERO; 3];
    let mut start = DVec3::X;
    let mut longest = 0.0;
    for it in items {
        let (l, d) = (it.seg.length(), it.seg.dir());
        if !(l.is_finite() && d.is_finite()) {
            continue;
        }
        for (r, row) in m.iter_mut().enumerate() {
            *row += d * (d[r] * l);
        }
        if l > longest {
            longest = l;
            start = d;
        }
    }
    let mut v = start;
    for _ in 0..32 {
        let w = DVec3::new(m[0].dot(v), m[1].dot(v), m[2].dot(v));
        let n = w.length();
        if n.is_nan() || n <= 0.0 || n.is_infinite() {
            break;
        }
        v = w / n;
    }
    if v.is_finite() && v.length() > 0.5 {
        v.normalize()
    } else {
        DVec3::X
    }
}

impl Near {
    /// The sweep for a group of `sweep_from` items or more ([`SWEEP_FROM`]), else all pairs.
    pub(super) fn new(items: &[Item], cx: &Ctx, sweep_from: usize) -> Near {
        let m = items.len();
        let Some(k) = widening(cx).filter(|_| m >= sweep_from.max(1)) else {
            return Near::All { m };
        };
        let d = main_direction(items);
        let mut scale = 1.0f64;
        for it in items {
            scale = scale
                .max(it.seg.p1.abs().max_element())
                .max(it.seg.p2.abs().max_element());
        }
        if !scale.is_finite() {
            return Near::All { m };
        }
        let mut s = Sweep {
            d,
            k: k * (1.0 + 1e-9),
            slack: 1e-9 * scale,
            lo: vec![0.0; m],
            hi: vec![0.0; m],
            b0: 0.0,
            inv_w: 0.0,
            buckets: Vec::new(),
            filed: vec![(1, 0); m],
            seen: vec![0; m],
            query: 0,
            entries: 0,
        };
        for (i, it) in items.iter().enumerate() {
            (s.lo[i], s.hi[i]) = s.interval(it);
        }
        let finite = || {
            s.lo.iter()
                .zip(&s.hi)
                .filter(|(a, b)| a.is_finite() && b.is_finite())
        };
        let lo = finite().map(|(a, _)| *a).fold(f64::INFINITY, f64::min);
        let hi = finite().map(|(_, b)| *b).fold(f64::NEG_INFINITY, f64::max);
        let mut widths: Vec<f64> = finite().map(|(a, b)| b - a).collect();
        if widths.is_empty() {
            return Near::All { m };
        }
        let mid = widths.len() / 2;
        let typical = *widths.select_nth_unstable_by(mid, f64::total_cmp).1;
        let span = hi - lo;
        let n = if span > 0.0 && typical > 0.0 {
            (span / typical).min(BUCKETS_PER_ITEM * m as f64).max(1.0)
        } else {
            1.0
        };
        let n = n.ceil() as usize;
        s.b0 = lo;
        s.inv_w = if span > 0.0 { n as f64 / span } else { 0.0 };
        s.buckets = vec![Vec::new(); n];
        for i in 0..m {
            s.file(i);
        }
        Near::Swept(Box::new(s))
    }

    /// Entries in the sweep's buckets (what it holds beyond a few per item).
    pub(super) fn entries(&self) -> usize {
        match self {
            Near::All { .. } => 0,
            Near::Swept(s) => s.entries,
        }
    }

    /// Item `i`'s segment is now `it.seg`.
    pub(super) fn update(&mut self, i: usize, it: &Item) {
        if let Near::Swept(s) = self {
            (s.lo[i], s.hi[i]) = s.interval(it);
            s.file(i);
        }
    }

    /// The alive items `c >= from` whose pairs with `a < from` can pass a rule, ascending.
    pub(super) fn columns(&mut self, a: usize, from: usize, alive: &[bool], out: &mut Vec<usize>) {
        out.clear();
        match self {
            Near::All { m } => out.extend((from..*m).filter(|&c| alive[c])),
            Near::Swept(s) => s.meet(a, alive, out, |c| c >= from),
        }
    }

    /// The alive items `a < h` whose pairs with `h` can pass a rule, ascending.
    pub(super) fn rows(&mut self, h: usize, alive: &[bool], out: &mut Vec<usize>) {
        out.clear();
        match self {
            Near::All { .. } => out.extend((0..h).filter(|&a| alive[a])),
            Near::Swept(s) => s.meet(h, alive, out, |a| a < h),
        }
    }
}

impl Sweep {
    fn interval(&self, it: &Item) -> (f64, f64) {
        let (a, b) = (self.d.dot(it.seg.p1), self.d.dot(it.seg.p2));
        let wide = self.k * it.seg.length() + self.slack;
        let (lo, hi) = (a.min(b) - wide, a.max(b) + wide);
        if lo.is_finite() && hi.is_finite() {
            (lo, hi)
        } else {
            // Not a segment any rule passes; met by every query all the same.
            (f64::NEG_INFINITY, f64::INFINITY)
        }
    }

    fn bucket(&self, x: f64) -> u32 {
        let last = self.buckets.len() - 1;
        let b = ((x - self.b0) * self.inv_w).floor();
        if b >= last as f64 {
            last as u32
        } else if b > 0.0 {
            b as u32
        } else {
            0
        }
    }

    /// Files item `i` in every bucket its interval covers that it is not filed in yet
    /// (and those between, so that its buckets stay one range).
    fn file(&mut self, i: usize) {
        let (n0, n1) = (self.bucket(self.lo[i]), self.bucket(self.hi[i]));
        let (f0, f1) = self.filed[i];
        let (u0, u1) = if f0 > f1 {
            (n0, n1)
        } else {
            (n0.min(f0), n1.max(f1))
        };
        for b in u0..=u1 {
            if f0 > f1 || b < f0 || b > f1 {
                self.buckets[b as usize].push(i as u32);
                self.entries += 1;
            }
        }
        self.filed[i] = (u0, u1);
    }

    fn meet(
        &mut self,
        a: usize,
        alive: &[bool],
        out: &mut Vec<usize>,
        keep: impl Fn(usize) -> bool,
    ) {
        self.query = self.query.wrapping_add(1);
        if self.query == 0 {
            self.seen.fill(0);
            self.query = 1;
        }
        let (lo, hi) = (self.lo[a], self.hi[a]);
        let (b0, b1) = (self.bucket(lo), self.bucket(hi));
        for b in b0..=b1 {
            for &c in &self.buckets[b as usize] {
                let c = c as usize;
                if self.seen[c] == self.query {
                    continue;
                }
                self.seen[c] = self.query;
                if c != a && alive[c] && keep(c) && self.lo[c] <= hi && lo <= self.hi[c] {
                    out.push(c);
                }
            }
        }
        out.sort_unstable();
    }
}
