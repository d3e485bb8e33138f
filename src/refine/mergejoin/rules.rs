//! The paper's two rules of step 8 (docs/method.md#step-8-merge-and-join), as pure
//! functions of two segments and the engine's answers about them: no engine, no
//! batching, no state.
//!
//! Each rule has a geometric part that runs on the CPU and says which cylinders the
//! decision needs ([`merge_candidate`], [`join_candidate`]), and a decision that reads
//! the answers ([`merge`], [`join`]). A pair goes to the merge or to the join by
//! [`overlaps`].

use super::MergeJoinParams;
use crate::engine::CylStats;
use crate::geom::{Segment, MIN_LENGTH};
use crate::refine::{density, Fixes};

/// A segment a rule made, with the stats of its own cylinder when they are already known.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Made {
    pub seg: Segment,
    /// `X(seg, r)`, exactly as a query of `seg` answers it; `None` when not asked yet.
    pub stats: Option<CylStats>,
}

/// `G` (the longer, `a` on equal lengths) and `S` of a pair; `true` when `G` is `a`.
fn longer_first(a: &Segment, b: &Segment) -> bool {
    a.length() >= b.length()
}

/// Merge or join? An endpoint of the shorter `S` projects strictly inside the longer `G`,
/// or (beyond the letter of the paper) `S`'s extent along `G` overlaps `G` over a positive
/// length, which adds only segments that cover exactly the same extent: without it two
/// copies of one edge would go to the join, whose gap is then the whole length. This is
/// the authors' test (`reference`); the fix `merge_overlap` also asks it the other way
/// round (`G`'s endpoints on `S`), which differs only for pairs at an angle.
pub fn overlaps(a: &Segment, b: &Segment, fixes: &Fixes) -> bool {
    let on = |s: &Segment, q: &Segment| {
        let l = s.length();
        let (t1, t2) = (s.axial(q.p1), s.axial(q.p2));
        let strictly_inside = |t: f64| 0.0 < t && t < l;
        strictly_inside(t1) || strictly_inside(t2) || t1.min(t2).max(0.0) < t1.max(t2).min(l)
    };
    let (g, s) = if longer_first(a, b) { (a, b) } else { (b, a) };
    on(g, s) || (fixes.merge_overlap && on(s, g))
}

/// The geometric part of a merge: whether `G` is `a`, and `G'`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MergeCandidate {
    pub g_is_a: bool,
    /// `G' = G + prop (foot(G.P1 on line S) - G.P1)`, `prop = L_S / (L_S + L_G)`.
    pub g_prime: Segment,
}

/// 8a, CPU part: `None` when the directions differ by more than `merge_angle_deg`, or
/// both endpoints of `S` are farther than `merge_dist_frac x L_G` from `G`'s line, or
/// (fix `merge_fidelity`, `fidelity = Some(tol)`) either is farther than `tol`: a merge
/// replaces two lines by one, which must stay within `tol` of both.
pub fn merge_candidate(
    a: &Segment,
    b: &Segment,
    p: &MergeJoinParams,
    fidelity: Option<f64>,
) -> Option<MergeCandidate> {
    let g_is_a = longer_first(a, b);
    let (g, s) = if g_is_a { (a, b) } else { (b, a) };
    let (lg, ls) = (g.length(), s.length());
    if g.dir().dot(s.dir()).abs() < p.merge_angle_deg.to_radians().cos() {
        return None;
    }
    let lim = p.merge_dist_frac * lg;
    if g.line_dist2(s.p1) > lim * lim && g.line_dist2(s.p2) > lim * lim {
        return None;
    }
    if let Some(tol) = fidelity {
        if g.line_dist2(s.p1) > tol * tol || g.line_dist2(s.p2) > tol * tol {
            return None;
        }
    }
    let prop = ls / (ls + lg);
    let g_prime = g.translated((s.foot(g.p1) - g.p1) * prop);
    Some(MergeCandidate { g_is_a, g_prime })
}

/// 8a, decision from `X(a)`, `X(b)` and `X(G')`: refused when `rho(G') < 0.6 rho(G)`;
/// otherwise whichever of `G`, `G'` has the smaller `E/N` (ties keep `G`), `S` dropped
/// (fix `merge_extent`: stretched over `S`'s extent along the kept line).
pub fn merge(
    (a, st_a): (&Segment, CylStats),
    (b, st_b): (&Segment, CylStats),
    c: &MergeCandidate,
    st_prime: CylStats,
    p: &MergeJoinParams,
    fixes: &Fixes,
) -> Option<Made> {
    let ((g, st_g), s) = if c.g_is_a {
        ((a, st_a), b)
    } else {
        ((b, st_b), a)
    };
    if density(st_prime.count, c.g_prime.length())
        < p.merge_density_ratio * density(st_g.count, g.length())
    {
        return None;
    }
    // E/N (an empty cylinder gives +inf).
    let e_per_n = |st: &CylStats| st.rmse() / st.count as f64;
    let (kept, st) = if e_per_n(&st_prime) < e_per_n(&st_g) {
        (c.g_prime, st_prime)
    } else {
        (*g, st_g)
    };
    let made = match fixes.merge_extent.then(|| union_extent(&kept, s)).flatten() {
        Some(u) => Made {
            seg: u,
            stats: None,
        },
        None => Made {
            seg: kept,
            stats: Some(st),
        },
    };
    Some(constructed(made, fixes))
}

/// `k` stretched along its own line over the projections of `s`'s endpoints; `None` when
/// they fall within `k` already. Rounding of the projections (a copy of `k` projects its
/// far end one ulp past `k`'s length) does not count as stretching.
fn union_extent(k: &Segment, s: &Segment) -> Option<Segment> {
    let l = k.length();
    let (ta, tb) = (k.axial(s.p1), k.axial(s.p2));
    let eps = 1e-12 * l;
    let (lo, hi) = (ta.min(tb), ta.max(tb));
    if lo >= -eps && hi <= l + eps {
        return None;
    }
    Some(Segment::new(
        if lo < -eps { k.point_at(lo) } else { k.p1 },
        if hi > l + eps { k.point_at(hi) } else { k.p2 },
    ))
}

/// The geometric part of a join: `J` and the gap chord.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JoinCandidate {
    /// The outer two of the four endpoints.
    pub joined: Segment,
    /// The middle two, shrunk by `join_chord_shrink` at each end.
    pub chord: Segment,
}

/// 8b, CPU part: the four endpoints sorted (`reference`: by distance from `a.P1`; fix
/// `join_order`: by projection on `a`'s direction); `None` when `J` is more than
/// `join_angle_deg` from either direction, or the gap is longer than `join_gap_frac x`
/// either length, or (fix `merge_fidelity`, `fidelity = Some(tol)`) an inner endpoint
/// lies farther than `tol` from `J`'s line: joined pieces of a curve would cut across it.
pub fn join_candidate(
    a: &Segment,
    b: &Segment,
    p: &MergeJoinParams,
    fixes: &Fixes,
    fidelity: Option<f64>,
) -> Option<JoinCandidate> {
    let d1 = a.dir();
    let pts = [a.p1, a.p2, b.p1, b.p2];
    let key = |q: glam::DVec3| {
        if fixes.join_order {
            (q - a.p1).dot(d1)
        } else {
            (q - a.p1).length()
        }
    };
    let mut o = [0usize, 1, 2, 3];
    o.sort_by(|&x, &y| key(pts[x]).total_cmp(&key(pts[y])));
    let joined = Segment::new(pts[o[0]], pts[o[3]]);
    if !joined.is_valid() {
        return None;
    }
    let min_cos = p.join_angle_deg.to_radians().cos();
    let dj = joined.dir();
    if dj.dot(d1).abs() < min_cos || dj.dot(b.dir()).abs() < min_cos {
        return None;
    }
    let (g0, g1) = (pts[o[1]], pts[o[2]]);
    if let Some(tol) = fidelity {
        if joined.line_dist2(g0) > tol * tol || joined.line_dist2(g1) > tol * tol {
            return None;
        }
    }
    let gap = (g1 - g0).length();
    if gap > p.join_gap_frac * a.length() || gap > p.join_gap_frac * b.length() {
        return None;
    }
    let sh = (g1 - g0) * p.join_chord_shrink;
    let chord = Segment::new(g0 + sh, g1 - sh);
    Some(JoinCandidate { joined, chord })
}

/// 8b, decision from `X(a)`, `X(b)`, the chord's count `n_chord` and `X(J)`: the gap must
/// hold `floor(mean rho x |chord|)` points (fix `join_gap`: `0.6 x mean rho x |chord|`, at
/// least 1), and `J` is refused when `rho(J) < 0.6 rho_i` or `E(J) > 1.1 E_i`.
pub fn join(
    (a, st_a): (&Segment, CylStats),
    (b, st_b): (&Segment, CylStats),
    c: &JoinCandidate,
    n_chord: u64,
    st_j: CylStats,
    p: &MergeJoinParams,
    fixes: &Fixes,
) -> Option<Made> {
    let (rho1, rho2) = (
        density(st_a.count, a.length()),
        density(st_b.count, b.length()),
    );
    let chord_len = c.chord.length();
    let expected = 0.5 * (rho1 + rho2) * chord_len;
    let need = if !fixes.join_gap {
        expected.floor()
    } else if chord_len <= MIN_LENGTH {
        // Touching pieces have no gap that could be empty.
        0.0
    } else {
        (p.join_gap_density * expected).max(1.0)
    };
    if (n_chord as f64) < need {
        return None;
    }
    let (rho_j, dr) = (density(st_j.count, c.joined.length()), p.join_density_ratio);
    if rho_j < dr * rho1 || rho_j < dr * rho2 {
        return None;
    }
    let (e_j, er) = (st_j.rmse(), p.join_rmse_ratio);
    if e_j > er * st_a.rmse() || e_j > er * st_b.rmse() {
        return None;
    }
    let made = Made {
        seg: c.joined,
        stats: Some(st_j),
    };
    Some(constructed(made, fixes))
}

/// The authors' segment constructor (`order_endpoints`): `|P1| <= |P2|`. Stats are kept
/// only for the segment they were asked about, so a reversed one is asked again.
fn constructed(m: Made, fixes: &Fixes) -> Made {
    if fixes.order_endpoints && m.seg.p1.length() > m.seg.p2.length() {
        Made {
            seg: m.seg.reversed(),
            stats: None,
        }
    } else {
        m
    }
}
