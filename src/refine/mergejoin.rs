//! Steps 6 and 8: merge (duplication) and join (discontinuity) inside a group of segments,
//! each loop restarting after every success.
//!
//! Step 8 runs, inside each cluster of step 7, the merge loop to its end and then the join
//! loop; step 6 runs the join alone on every pair of each input line. A loop scans the pairs
//! `(i, j)`, `i < j`, of the group's current list and applies the first pair that passes;
//! the result takes the place of `i`, `j` is removed and the scan starts again.
//!
//! Batching (SPEC 4): every group is a small state machine. In one round each unfinished
//! group lists, in scan order from where it stands, the pairs that pass the CPU-only checks
//! with the queries their decision needs; all groups' queries go to the engine as one
//! batch; then each group applies the first pair that succeeded, in its list order, and
//! starts its scan again, or moves its scan past the listed pairs. Nothing changes between
//! the pairs of one list until a success, so this is exactly the sequential loop, in about
//! `successes + 1` rounds. Stats of the current segments (`N`, `E`) are kept across rounds.

use crate::engine::{CylStats, Engine, EngineError, Query, Want};
use crate::geom::{LineSet, Segment};
use crate::refine::{density, Fixes, Params, Settings};
use rayon::prelude::*;
use std::collections::HashMap;

/// Pairs one group may list in its first round. A group whose list runs out without a
/// success doubles it, so a huge cluster costs a few more rounds, not a huge batch.
const FIRST_BUDGET: usize = 1024;

#[derive(Clone, Copy, Debug)]
struct Item {
    seg: Segment,
    group: u32,
    /// Count and squared-distance sum of `X(seg, r)` once a batch has answered them.
    stats: Option<CylStats>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
enum Phase {
    Merge,
    Join,
    Done,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Mode {
    /// Step 8: merge on overlapping pairs, then join on the others.
    Cluster,
    /// Step 6: join on every pair.
    Collinear,
}

/// A pair that passed the CPU-only checks; `q*` index the group's part of the batch.
#[derive(Clone, Copy, Debug)]
enum Cand {
    Merge {
        i: usize,
        j: usize,
        /// `G` (the longer) is item `i`.
        g_first: bool,
        g_prime: Segment,
        q: usize,
    },
    Join {
        i: usize,
        j: usize,
        joined: Segment,
        chord_len: f64,
        /// `None` when the chord is degenerate (it then holds no point).
        q_chord: Option<usize>,
        q_joined: usize,
    },
    /// Decided in favour in an earlier round; needs no query.
    Known {
        i: usize,
        j: usize,
        item: Item,
        phase: Phase,
    },
}

#[derive(Default)]
struct Listing {
    cands: Vec<Cand>,
    queries: Vec<Query>,
    /// `(item, query)`: stats of current items not known yet.
    inputs: Vec<(usize, usize)>,
    /// Where the scan goes on when no listed pair succeeds; `None` at the end of the scan.
    resume: Option<(Phase, usize, usize)>,
}

struct Machine {
    items: Vec<Item>,
    phase: Phase,
    /// Next pair `(i, j)` of `phase` to look at.
    next: (usize, usize),
    budget: usize,
    first_budget: usize,
    /// Identity of each item's current content: a merge or join gives the result a new one.
    uids: Vec<u64>,
    next_uid: u64,
    /// Pairs (by content) already decided against. A decision reads only the two items,
    /// so after a restart these pairs need no new query: a round re-asks only about pairs
    /// that involve the item the last success changed.
    failed: std::collections::HashSet<(u64, u64, Phase)>,
    /// Pairs (by content) decided in favour in a round where an earlier pair won.
    won: std::collections::HashMap<(u64, u64, Phase), Item>,
    /// After a success at `(i, j)` in `phase`: every pair before `(i, j)` in scan order
    /// failed and only item `i` changed, so in rows `a < i` the pair `(a, i)` is the only
    /// one that can decide differently. The restart skips the rest of those rows, which
    /// keeps a cluster of `k` segments at `O(k)` work per restart instead of `O(k^2)`.
    hot: Option<(Phase, usize)>,
}

/// The parameters every decision reads.
#[derive(Clone, Copy)]
struct Ctx<'a> {
    mode: Mode,
    r: f64,
    p: &'a Params,
    fixes: &'a Fixes,
}

impl Machine {
    fn new(items: Vec<Item>, mode: Mode, budget: usize) -> Self {
        Machine {
            items: items.clone(),
            phase: match mode {
                Mode::Cluster => Phase::Merge,
                Mode::Collinear => Phase::Join,
            },
            next: (0, 1),
            budget,
            first_budget: budget,
            uids: (0..items.len() as u64).collect(),
            next_uid: items.len() as u64,
            failed: Default::default(),
            won: Default::default(),
            hot: None,
        }
    }

    /// The pairs of this round, from `next` on, across the end of the merge scan into the
    /// join scan (whose pairs are then speculative: they count only if no merge succeeds).
    fn list(&self, cx: Ctx) -> Listing {
        let mut l = Listing::default();
        let mut asked = vec![false; self.items.len()];
        let m = self.items.len();
        let mut phase = self.phase;
        let (mut i, mut j) = self.next;
        loop {
            if j >= m {
                i += 1;
                j = i + 1;
            }
            if j >= m {
                if phase == Phase::Merge {
                    phase = Phase::Join;
                    (i, j) = (0, 1);
                    continue;
                }
                return l;
            }
            if let Some((hp, h)) = self.hot {
                if hp == phase && i < h {
                    if j < h {
                        j = h;
                    } else if j > h {
                        j = m;
                        continue;
                    }
                }
            }
            if l.cands.len() >= self.budget {
                l.resume = Some((phase, i, j));
                return l;
            }
            let (a, b) = (&self.items[i].seg, &self.items[j].seg);
            let known = |ph| self.failed.contains(&(self.uids[i], self.uids[j], ph));
            let key = (self.uids[i], self.uids[j], phase);
            if let Some(item) = self.won.get(&key) {
                l.cands.push(Cand::Known {
                    i,
                    j,
                    item: *item,
                    phase,
                });
                j += 1;
                continue;
            }
            let merge = phase == Phase::Merge && !known(Phase::Merge) && overlaps(a, b);
            let join = phase == Phase::Join
                && !known(Phase::Join)
                && (cx.mode == Mode::Collinear || !overlaps(a, b));
            let merge = if merge { merge_check(a, b, cx.p) } else { None };
            let join = if join {
                join_check(a, b, cx.p, cx.fixes)
            } else {
                None
            };
            if merge.is_some() || join.is_some() {
                for k in [i, j] {
                    if self.items[k].stats.is_none() && !asked[k] {
                        asked[k] = true;
                        l.inputs.push((k, l.queries.len()));
                        l.queries.push(Query::new(self.items[k].seg, cx.r));
                    }
                }
            }
            if let Some((g_first, g_prime)) = merge {
                l.cands.push(Cand::Merge {
                    i,
                    j,
                    g_first,
                    g_prime,
                    q: l.queries.len(),
                });
                l.queries.push(Query::new(g_prime, cx.r));
            }
            if let Some((joined, chord)) = join {
                // A degenerate chord (touching segments) holds no point; not worth a query.
                let q_chord = chord.is_valid().then(|| {
                    l.queries.push(Query::new(chord, cx.r));
                    l.queries.len() - 1
                });
                l.cands.push(Cand::Join {
                    i,
                    j,
                    joined,
                    chord_len: chord.length(),
                    q_chord,
                    q_joined: l.queries.len(),
                });
                l.queries.push(Query::new(joined, cx.r));
            }
            j += 1;
        }
    }

    /// Applies the first success of the round's list, or moves the scan on.
    fn apply(&mut self, l: Listing, res: &[CylStats], cx: Ctx) {
        for &(k, q) in &l.inputs {
            self.items[k].stats = Some(res[q]);
        }
        let mut first = None;
        for c in &l.cands {
            let (i, j, item, phase) = match *c {
                Cand::Known { i, j, item, phase } => (i, j, Some(item), phase),
                Cand::Merge {
                    i,
                    j,
                    g_first,
                    g_prime,
                    q,
                } => (
                    i,
                    j,
                    decide_merge(&self.items[i], &self.items[j], g_first, g_prime, res[q], cx),
                    Phase::Merge,
                ),
                Cand::Join {
                    i,
                    j,
                    joined,
                    chord_len,
                    q_chord,
                    q_joined,
                } => {
                    let n_chord = q_chord.map_or(0, |q| res[q].count);
                    let item = decide_join(
                        &self.items[i],
                        &self.items[j],
                        joined,
                        chord_len,
                        n_chord,
                        res[q_joined],
                        cx,
                    );
                    (i, j, item, Phase::Join)
                }
            };
            let key = (self.uids[i], self.uids[j], phase);
            match item {
                None => {
                    self.failed.insert(key);
                }
                Some(it) => {
                    self.won.insert(key, it);
                    if first.is_none() {
                        first = Some((i, j, it, phase));
                    }
                }
            }
        }
        if let Some((i, j, item, phase)) = first {
            self.items[i] = item;
            self.items.remove(j);
            self.uids[i] = self.next_uid;
            self.next_uid += 1;
            self.uids.remove(j);
            self.phase = phase;
            self.next = (0, 1);
            self.hot = Some((phase, i));
            self.budget = self.first_budget;
            return;
        }
        match l.resume {
            None => self.phase = Phase::Done,
            Some((phase, i, j)) => {
                self.phase = phase;
                self.next = (i, j);
                self.budget = self.budget.saturating_mul(2);
            }
        }
    }
}

/// A merge case: an endpoint of one projects strictly inside the other, or (beyond the
/// letter of SPEC 3) their extents along one's axis overlap over a positive length, which
/// adds only segments that cover exactly the same extent: without it two copies of one
/// edge with the same ends would go to the join, whose gap is then the whole length.
fn overlaps(a: &Segment, b: &Segment) -> bool {
    let on = |s: &Segment, q1, q2| {
        let l = s.length();
        let (t1, t2) = (s.axial(q1), s.axial(q2));
        let strictly_inside = |t: f64| 0.0 < t && t < l;
        strictly_inside(t1) || strictly_inside(t2) || t1.min(t2).max(0.0) < t1.max(t2).min(l)
    };
    on(a, b.p1, b.p2) || on(b, a.p1, a.p2)
}

/// CPU checks of the merge: `G` the longer (the first on equal lengths), `S` the shorter.
/// Returns whether `G` is `a`, and `G' = G + prop (foot(G.P1 on line S) - G.P1)`.
fn merge_check(a: &Segment, b: &Segment, p: &Params) -> Option<(bool, Segment)> {
    let (la, lb) = (a.length(), b.length());
    let g_first = la >= lb;
    let (g, s, lg, ls) = if g_first {
        (a, b, la, lb)
    } else {
        (b, a, lb, la)
    };
    if g.dir().dot(s.dir()).abs() < p.merge_angle_deg.to_radians().cos() {
        return None;
    }
    let lim = p.merge_dist_frac * lg;
    if g.line_dist2(s.p1) > lim * lim && g.line_dist2(s.p2) > lim * lim {
        return None;
    }
    let prop = ls / (ls + lg);
    Some((g_first, g.translated((s.foot(g.p1) - g.p1) * prop)))
}

fn decide_merge(
    a: &Item,
    b: &Item,
    g_first: bool,
    g_prime: Segment,
    st_prime: CylStats,
    cx: Ctx,
) -> Option<Item> {
    let (g, s) = if g_first { (a, b) } else { (b, a) };
    let st_g = g.stats?;
    let rho_g = density(st_g.count, g.seg.length());
    if density(st_prime.count, g_prime.length()) < cx.p.merge_density_ratio * rho_g {
        return None;
    }
    // E/N (an empty cylinder gives +inf); ties keep G.
    let e_per_n = |st: &CylStats| st.rmse() / st.count as f64;
    let (kept, st) = if e_per_n(&st_prime) < e_per_n(&st_g) {
        (g_prime, st_prime)
    } else {
        (g.seg, st_g)
    };
    let (seg, stats) = match cx.fixes.merge_extent {
        true => match union_extent(&kept, &s.seg) {
            Some(u) => (u, None),
            None => (kept, Some(st)),
        },
        false => (kept, Some(st)),
    };
    Some(Item {
        seg,
        group: a.group,
        stats,
    })
}

/// `k` stretched along its own line over the projections of `s`'s endpoints; `None` when
/// they fall within `k` already.
fn union_extent(k: &Segment, s: &Segment) -> Option<Segment> {
    let l = k.length();
    let (ta, tb) = (k.axial(s.p1), k.axial(s.p2));
    let lo = ta.min(tb);
    let hi = ta.max(tb);
    if lo >= 0.0 && hi <= l {
        return None;
    }
    Some(Segment::new(
        if lo < 0.0 { k.point_at(lo) } else { k.p1 },
        if hi > l { k.point_at(hi) } else { k.p2 },
    ))
}

/// CPU checks of the join: the four endpoints sorted (`reference`: by distance from
/// `a.P1`; fix: by projection on `a`'s direction); the outer two make `J`, the middle two
/// the gap. Returns `J` and the gap chord shrunk at both ends.
fn join_check(a: &Segment, b: &Segment, p: &Params, fixes: &Fixes) -> Option<(Segment, Segment)> {
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
    let gap = (g1 - g0).length();
    if gap > p.join_gap_frac * a.length() || gap > p.join_gap_frac * b.length() {
        return None;
    }
    let sh = (g1 - g0) * p.join_chord_shrink;
    Some((joined, Segment::new(g0 + sh, g1 - sh)))
}

fn decide_join(
    a: &Item,
    b: &Item,
    joined: Segment,
    chord_len: f64,
    n_chord: u64,
    st_j: CylStats,
    cx: Ctx,
) -> Option<Item> {
    let (s1, s2) = (a.stats?, b.stats?);
    let rho1 = density(s1.count, a.seg.length());
    let rho2 = density(s2.count, b.seg.length());
    let expected = 0.5 * (rho1 + rho2) * chord_len;
    let need = if cx.fixes.join_gap {
        // Touching pieces have no gap that could be empty: nothing to ask of it.
        if chord_len <= crate::geom::MIN_LENGTH {
            0.0
        } else {
            (cx.p.join_gap_density * expected).max(1.0)
        }
    } else {
        expected.floor()
    };
    if (n_chord as f64) < need {
        return None;
    }
    let rho_j = density(st_j.count, joined.length());
    let dr = cx.p.join_density_ratio;
    if rho_j < dr * rho1 || rho_j < dr * rho2 {
        return None;
    }
    let (e_j, er) = (st_j.rmse(), cx.p.join_rmse_ratio);
    if e_j > er * s1.rmse() || e_j > er * s2.rmse() {
        return None;
    }
    Some(Item {
        seg: joined,
        group: a.group,
        stats: Some(st_j),
    })
}

/// Runs every group to its end, one engine batch per round.
fn run(engine: &dyn Engine, machines: &mut [Machine], cx: Ctx) -> Result<(), EngineError> {
    loop {
        let listings: Vec<Option<Listing>> = machines
            .par_iter()
            .map(|m| (m.phase != Phase::Done).then(|| m.list(cx)))
            .collect();
        let mut queries = Vec::new();
        let mut offsets = Vec::with_capacity(listings.len());
        for l in &listings {
            offsets.push(queries.len());
            if let Some(l) = l {
                queries.extend_from_slice(&l.queries);
            }
        }
        // Every listed pair asks at least one query, so no query means no pair left.
        if queries.is_empty() {
            return Ok(());
        }
        let res = engine.stats(&queries, Want::SUMS)?;
        machines
            .par_iter_mut()
            .zip(listings.into_par_iter())
            .zip(offsets.into_par_iter())
            .for_each(|((m, l), off)| {
                if let Some(l) = l {
                    let n = l.queries.len();
                    m.apply(l, &res[off..off + n], cx);
                }
            });
    }
}

fn items_of(lines: &LineSet, idx: &[usize]) -> Vec<Item> {
    idx.iter()
        .map(|&k| Item {
            seg: lines.segments[k],
            group: lines.group(k),
            stats: None,
        })
        .collect()
}

fn line_set(items: impl Iterator<Item = Item>, grouped: bool) -> LineSet {
    let (segments, groups): (Vec<Segment>, Vec<u32>) = items.map(|it| (it.seg, it.group)).unzip();
    LineSet {
        segments,
        groups: grouped.then_some(groups),
    }
}

/// Step 8: merge, then join, inside each cluster (indices into `lines`, e.g. from
/// [`super::cluster::cluster`]). The result lists the clusters' segments in cluster order;
/// a merged or joined segment takes the group of the first of its pair.
///
/// # Panics
/// If a cluster names a segment index `>= lines.len()`.
pub fn merge_join(
    engine: &dyn Engine,
    lines: &LineSet,
    clusters: &[Vec<usize>],
    s: &Settings,
) -> Result<LineSet, EngineError> {
    merge_join_budget(engine, lines, clusters, s, FIRST_BUDGET)
}

fn merge_join_budget(
    engine: &dyn Engine,
    lines: &LineSet,
    clusters: &[Vec<usize>],
    s: &Settings,
    budget: usize,
) -> Result<LineSet, EngineError> {
    let (r, p, fixes) = (s.radius(), s.params(), s.fixes());
    let cx = Ctx {
        mode: Mode::Cluster,
        r,
        p,
        fixes,
    };
    let mut machines: Vec<Machine> = clusters
        .iter()
        .map(|c| Machine::new(items_of(lines, c), Mode::Cluster, budget))
        .collect();
    run(engine, &mut machines, cx)?;
    Ok(line_set(
        machines.into_iter().flat_map(|m| m.items),
        lines.groups.is_some(),
    ))
}

/// Step 6: inside each input line with two or more segments, the join on every pair,
/// restarting after each success. A line's result takes the place of its first segment;
/// ungrouped input (or `p.collinear_merge` off) comes back unchanged.
pub fn collinear_merge(
    engine: &dyn Engine,
    lines: &LineSet,
    s: &Settings,
) -> Result<LineSet, EngineError> {
    let (r, p, fixes) = (s.radius(), s.params(), s.fixes());
    let Some(groups) = &lines.groups else {
        return Ok(lines.clone());
    };
    if !p.collinear_merge {
        return Ok(lines.clone());
    }
    let mut slot: HashMap<u32, usize> = HashMap::new();
    let mut members: Vec<Vec<usize>> = Vec::new();
    for (i, &g) in groups.iter().enumerate() {
        let k = *slot.entry(g).or_insert_with(|| {
            members.push(Vec::new());
            members.len() - 1
        });
        members[k].push(i);
    }
    let cx = Ctx {
        mode: Mode::Collinear,
        r,
        p,
        fixes,
    };
    let mut machines: Vec<Machine> = members
        .iter()
        .map(|m| {
            let items = if m.len() >= 2 {
                items_of(lines, m)
            } else {
                Vec::new()
            };
            Machine::new(items, Mode::Collinear, FIRST_BUDGET)
        })
        .collect();
    run(engine, &mut machines, cx)?;
    let mut out = Vec::with_capacity(lines.len());
    for (i, &g) in groups.iter().enumerate() {
        let k = slot[&g];
        if members[k].len() < 2 {
            out.push(items_of(lines, &[i])[0]);
        } else if members[k][0] == i {
            out.append(&mut machines[k].items);
        }
    }
    Ok(line_set(out.into_iter(), true))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::cpu::CpuEngine;
    use crate::geom::{p64, Aabb};
    use crate::index::Grid;
    use glam::DVec3;
    use std::sync::Arc;

    const R: f64 = 0.03;

    fn engine(points: &[[f32; 3]]) -> CpuEngine {
        let mut b = Aabb::empty();
        for p in points {
            b.extend(p64(*p));
        }
        CpuEngine::new(Arc::new(Grid::build(points, b, 0.1)))
    }

    /// Gaussian centers every `step` along x over `[x0, x1]`, at height `y`, as a trained
    /// model puts them on an edge.
    fn ridge(x0: f64, x1: f64, step: f64, y: f64) -> Vec<[f32; 3]> {
        let n = ((x1 - x0) / step + 1e-9).floor() as usize;
        (0..=n)
            .map(|k| [(x0 + k as f64 * step) as f32, y as f32, 0.0])
            .collect()
    }

    fn seg(x0: f64, y0: f64, x1: f64, y1: f64) -> Segment {
        Segment::new(DVec3::new(x0, y0, 0.0), DVec3::new(x1, y1, 0.0))
    }

    fn one_cluster(segs: Vec<Segment>) -> (LineSet, Vec<Vec<usize>>) {
        let c = vec![(0..segs.len()).collect()];
        (LineSet::new(segs), c)
    }

    fn run(e: &CpuEngine, segs: Vec<Segment>, p: &Params) -> Vec<Segment> {
        let (lines, c) = one_cluster(segs);
        merge_join(e, &lines, &c, &p.with_radius(R))
            .unwrap()
            .segments
    }

    fn near(a: &Segment, b: &Segment, tol: f64) -> bool {
        a.p1.distance(b.p1) <= tol && a.p2.distance(b.p2) <= tol
    }

    #[test]
    fn duplicates_become_one_segment() {
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let segs = vec![
            seg(0.0, 0.0, 2.0, 0.0),
            seg(0.02, 0.005, 1.98, 0.005),
            seg(0.1, -0.004, 1.9, -0.004),
        ];
        for p in [Params::default(), Params::reference()] {
            let out = run(&e, segs.clone(), &p);
            // The longest sits on the ridge: every merge keeps it (G' moves off the ridge).
            assert_eq!(out, vec![segs[0]]);
        }
    }

    #[test]
    fn a_merge_keeps_the_shifted_longer_when_it_fits_better() {
        // Ridge at y = 0.01; G at y = 0 (2 long), S at y = 0.02 (1 long): prop = 1/3, so G'
        // sits at y = 0.02/3, closer to the ridge, with the same count: G' is kept.
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.01));
        let g = seg(0.0, 0.0, 2.0, 0.0);
        let s = seg(0.5, 0.02, 1.5, 0.02);
        let want = g.translated(DVec3::new(0.0, 0.02 / 3.0, 0.0));
        for p in [Params::default(), Params::reference()] {
            let out = run(&e, vec![s, g], &p);
            assert_eq!(out.len(), 1);
            assert!(near(&out[0], &want, 1e-12), "{:?}", out[0]);
        }
    }

    #[test]
    fn a_merge_is_refused_across_a_wide_angle() {
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        // 40 degrees apart, crossing in the middle of the longer.
        let (c, s) = (40f64.to_radians().cos(), 40f64.to_radians().sin());
        let segs = vec![seg(0.0, 0.0, 2.0, 0.0), seg(1.0, 0.0, 1.0 + c, s)];
        let out = run(&e, segs.clone(), &Params::default());
        assert_eq!(out, segs);
    }

    #[test]
    fn merge_extent_fix_keeps_the_union_of_both() {
        // G = [0, 1.5], S = [1, 2] on the same dense ridge: G' = G (collinear), tie keeps G.
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let segs = vec![seg(0.0, 0.0, 1.5, 0.0), seg(1.0, 0.0, 2.0, 0.0)];
        let reference = run(&e, segs.clone(), &Params::reference());
        assert_eq!(reference, vec![segs[0]]);
        let fixed = run(&e, segs.clone(), &Params::default());
        assert_eq!(fixed.len(), 1);
        assert!(near(&fixed[0], &seg(0.0, 0.0, 2.0, 0.0), 1e-12));
    }

    #[test]
    fn a_split_edge_with_gaussians_in_the_gap_is_joined() {
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let segs = vec![seg(0.0, 0.0, 0.9, 0.0), seg(1.1, 0.0, 2.0, 0.0)];
        for p in [Params::default(), Params::reference()] {
            let out = run(&e, segs.clone(), &p);
            assert_eq!(out, vec![seg(0.0, 0.0, 2.0, 0.0)]);
        }
    }

    #[test]
    fn a_split_edge_with_an_empty_gap_stays_two() {
        let mut pts = ridge(0.0, 0.9, 0.005, 0.0);
        pts.extend(ridge(1.1, 2.0, 0.005, 0.0));
        let e = engine(&pts);
        let segs = vec![seg(0.0, 0.0, 0.9, 0.0), seg(1.1, 0.0, 2.0, 0.0)];
        for p in [Params::default(), Params::reference()] {
            assert_eq!(run(&e, segs.clone(), &p), segs);
        }
    }

    #[test]
    fn gap_rule_reference_floor_versus_fix_fraction() {
        // Gap at 3/4 of the density of the pieces: 29 points on the chord, where reference
        // wants floor(201 x 0.192) = 38 and the fix 0.6 x 38.6 = 23.2.
        let mut pts = ridge(0.0, 0.9, 0.005, 0.0);
        pts.extend(ridge(1.1, 2.0, 0.005, 0.0));
        pts.extend((1..30).map(|k| [(0.9 + k as f64 * 0.2 / 30.0) as f32, 0.0, 0.0]));
        let e = engine(&pts);
        let segs = vec![seg(0.0, 0.0, 0.9, 0.0), seg(1.1, 0.0, 2.0, 0.0)];
        assert_eq!(run(&e, segs.clone(), &Params::reference()), segs);
        assert_eq!(
            run(&e, segs.clone(), &Params::default()),
            vec![seg(0.0, 0.0, 2.0, 0.0)]
        );
        // A 0.002 gap with no point: floor(0.39) = 0 lets reference join; the fix wants 1.
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let segs = vec![seg(0.0, 0.0, 0.9, 0.0), seg(0.902, 0.0, 2.0, 0.0)];
        assert_eq!(
            run(&e, segs.clone(), &Params::reference()),
            vec![seg(0.0, 0.0, 2.0, 0.0)]
        );
        assert_eq!(run(&e, segs.clone(), &Params::default()), segs);
        // Each fix alone switches its own rule.
        let only_gap = Params {
            fix_join_gap: Some(true),
            ..Params::reference()
        };
        assert_eq!(run(&e, segs.clone(), &only_gap), segs);
    }

    #[test]
    fn join_order_reference_sorts_by_distance_from_the_first_p1() {
        // The first segment points away from the second: by distance from its P1 (x = 0.9)
        // the "gap" becomes [1.1, 0], longer than 0.8 x 0.9, and reference refuses; by
        // projection on its direction the gap is [0.9, 1.1] and the fix joins.
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let segs = vec![seg(0.9, 0.0, 0.0, 0.0), seg(1.1, 0.0, 2.0, 0.0)];
        assert_eq!(run(&e, segs.clone(), &Params::reference()), segs);
        let fixed = run(&e, segs.clone(), &Params::default());
        assert_eq!(fixed, vec![seg(2.0, 0.0, 0.0, 0.0)]);
        let only_order = Params {
            fix_join_order: Some(true),
            ..Params::reference()
        };
        assert_eq!(run(&e, segs, &only_order), fixed);
    }

    /// Four clusters, each an edge broken in three: [0, .6], [.7, 1.3], [1.4, 2].
    fn broken_edges() -> (CpuEngine, LineSet, Vec<Vec<usize>>) {
        let ys = [0.0, 0.5, 1.0, 1.5];
        let mut pts = Vec::new();
        let mut segs = Vec::new();
        for &y in &ys {
            pts.extend(ridge(0.0, 2.0, 0.005, y));
            segs.extend([
                seg(0.0, y, 0.6, y),
                seg(0.7, y, 1.3, y),
                seg(1.4, y, 2.0, y),
            ]);
        }
        let clusters = (0..4).map(|c| vec![3 * c, 3 * c + 1, 3 * c + 2]).collect();
        (engine(&pts), LineSet::new(segs), clusters)
    }

    #[test]
    fn each_round_is_one_batch_for_all_clusters() {
        let (e, lines, clusters) = broken_edges();
        let p = Params::default();
        let before = e.counters();
        let out = merge_join(&e, &lines, &clusters, &p.with_radius(R)).unwrap();
        let after = e.counters();
        let want: Vec<Segment> = [0.0, 0.5, 1.0, 1.5]
            .iter()
            .map(|&y| seg(0.0, y, 2.0, y))
            .collect();
        assert_eq!(out.segments, want);
        assert_eq!(out.groups, None);
        // Round 1: per cluster the pairs (0,1) and (1,2) pass the CPU checks ((0,2) has a
        // 0.8 gap): 3 inputs + 2 x (chord, J) = 7 queries; (0,1) joins. Round 2: the pair
        // left, inputs cached: chord and J. Then one segment each, no round 3.
        assert_eq!(after.batches - before.batches, 2);
        assert_eq!(after.queries - before.queries, 4 * (7 + 2));
    }

    #[test]
    fn output_does_not_depend_on_the_thread_count() {
        // Noisy copies of the broken edges, three per piece, in one cluster per edge.
        let (e, lines, _) = broken_edges();
        let mut segs = Vec::new();
        let mut clusters = vec![Vec::new(); 4];
        for (k, s) in lines.segments.iter().enumerate() {
            for m in 0..3 {
                let t = DVec3::new(0.0, 0.004 * (m as f64 - 1.0), 0.0);
                let shrink = (s.p2 - s.p1) * 0.03 * m as f64;
                clusters[k / 3].push(segs.len());
                segs.push(Segment::new(s.p1 + t + shrink, s.p2 + t - shrink));
            }
        }
        let lines = LineSet::new(segs);
        for p in [Params::default(), Params::reference()] {
            let go = |threads: usize| {
                rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap()
                    .install(|| merge_join(&e, &lines, &clusters, &p.with_radius(R)).unwrap())
            };
            let one = go(1);
            assert!(one.len() <= 8, "{} segments left", one.len());
            assert_eq!(one, go(3));
            assert_eq!(one, go(2));
        }
    }

    #[test]
    fn copies_with_the_same_extent_are_merged() {
        // Neither copy has an endpoint strictly inside the other. Equal lengths: G is the
        // first, prop = 1/2, and G' halfway to the ridge fits better.
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let segs = vec![seg(0.0, 0.004, 2.0, 0.004), seg(0.0, 0.0, 2.0, 0.0)];
        for p in [Params::default(), Params::reference()] {
            let out = run(&e, segs.clone(), &p);
            assert_eq!(out.len(), 1);
            assert!(near(&out[0], &seg(0.0, 0.002, 2.0, 0.002), 1e-12));
        }
    }

    #[test]
    fn the_round_budget_changes_rounds_not_results() {
        // 60 parallel copies of an edge on two ridges 0.3 apart (within 0.2 L of each
        // other, so every pair passes the CPU checks): 1770 candidate pairs at first.
        let mut pts = ridge(0.0, 2.0, 0.005, 0.0);
        pts.extend(ridge(0.0, 2.0, 0.005, 0.3));
        let e = engine(&pts);
        let segs: Vec<Segment> = (0..60)
            .map(|k| {
                let y = 0.3 * (k % 2) as f64 + 0.0001 * k as f64;
                seg(0.01 * (k % 7) as f64, y, 2.0 - 0.01 * (k % 5) as f64, y)
            })
            .collect();
        let (lines, c) = one_cluster(segs);
        for p in [Params::default(), Params::reference()] {
            let go = |budget: usize| {
                let b = e.counters().batches;
                let out = merge_join_budget(&e, &lines, &c, &p.with_radius(R), budget).unwrap();
                (out, e.counters().batches - b)
            };
            let (all, rounds_all) = go(usize::MAX);
            let (small, rounds_small) = go(3);
            assert_eq!(all, small);
            assert!(rounds_small > rounds_all, "{rounds_small} vs {rounds_all}");
            assert!(all.len() < 10, "{} left", all.len());
        }
    }

    #[test]
    fn collinear_merge_joins_inside_input_lines_only() {
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let lines = LineSet {
            segments: vec![
                seg(0.0, 0.0, 0.9, 0.0), // line 7
                seg(0.0, 0.0, 1.2, 0.0), // line 3, overlapping pair: joined too
                seg(1.1, 0.0, 2.0, 0.0), // line 7
                seg(0.8, 0.0, 2.0, 0.0), // line 3
                seg(1.1, 0.0, 2.0, 0.0), // line 5, alone
            ],
            groups: Some(vec![7, 3, 7, 3, 5]),
        };
        let p = Params::default();
        let out = collinear_merge(&e, &lines, &p.with_radius(R)).unwrap();
        assert_eq!(
            out.segments,
            vec![
                seg(0.0, 0.0, 2.0, 0.0),
                seg(0.0, 0.0, 2.0, 0.0),
                seg(1.1, 0.0, 2.0, 0.0)
            ]
        );
        assert_eq!(out.groups, Some(vec![7, 3, 5]));
        // Ungrouped input, or the step switched off: unchanged, and no query.
        let q = e.counters().queries;
        let flat = LineSet::new(lines.segments.clone());
        assert_eq!(collinear_merge(&e, &flat, &p.with_radius(R)).unwrap(), flat);
        let off = Params {
            collinear_merge: false,
            ..Params::default()
        };
        assert_eq!(
            collinear_merge(&e, &lines, &off.with_radius(R)).unwrap(),
            lines
        );
        assert_eq!(e.counters().queries, q);
    }

    #[test]
    fn merged_and_joined_segments_take_the_group_of_the_first() {
        let e = engine(&ridge(0.0, 2.0, 0.005, 0.0));
        let lines = LineSet {
            segments: vec![seg(1.1, 0.0, 2.0, 0.0), seg(0.0, 0.0, 0.9, 0.0)],
            groups: Some(vec![4, 9]),
        };
        let p = Params::default();
        let out = merge_join(&e, &lines, &[vec![1, 0]], &p.with_radius(R)).unwrap();
        assert_eq!(out.segments, vec![seg(0.0, 0.0, 2.0, 0.0)]);
        assert_eq!(out.groups, Some(vec![9]));
    }
}
