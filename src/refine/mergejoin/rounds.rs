//! The batched machinery that runs the restart loops of [`super::sequential`] for every
//! group at once, one engine batch per round (SPEC 4), with exactly the same result.
//!
//! Every group is a small state machine. In one round each unfinished group lists, in scan
//! order from where it stands, the pairs that pass the CPU parts of the rules with the
//! queries their decisions need (across the end of the merge scan into the join scan,
//! whose pairs then count only if no merge succeeds); all groups' queries go to the engine
//! as one batch; then each group walks its list in order:
//! - a pair whose result is item `i` itself, bit for bit (a copy merged into its twin):
//!   item `j` is dropped and the walk goes on, because nothing any other decision reads
//!   has changed — this is what the sequential loop does after its restart, which finds
//!   every earlier pair failing again;
//! - the first other success is applied and the scan restarts;
//! - no success: the scan moves past the listed pairs.
//!
//! Decisions are pure functions of the two items, so they are kept (the memo) by item
//! identity across rounds: after a restart a round asks only about pairs that involve the
//! changed item. A round whose pairs are all decided asks nothing but still applies; the
//! loop ends only when every group's full scan has found nothing to do.

use super::rules::{self, JoinCandidate, Made, MergeCandidate};
use super::{Ctx, Item, Mode};
use crate::engine::{CylStats, Engine, EngineError, Query, Want};
use crate::geom::Segment;
use rayon::prelude::*;
use std::collections::{HashMap, HashSet};

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub(super) enum Phase {
    Merge,
    Join,
    Done,
}

/// A pair that passed the CPU part of its rule; `q*` index the group's part of the batch.
#[derive(Clone, Copy, Debug)]
enum Cand {
    Merge {
        c: MergeCandidate,
        q: usize,
    },
    Join {
        c: JoinCandidate,
        /// `None` when the chord is degenerate (it then holds no point).
        q_chord: Option<usize>,
        q_joined: usize,
    },
    /// Decided in favour in an earlier round; needs no query.
    Known(Made),
}

#[derive(Default)]
struct Listing {
    /// `(i, j, phase, candidate)` in scan order.
    cands: Vec<(usize, usize, Phase, Cand)>,
    queries: Vec<Query>,
    /// The query of each distinct segment in `queries` (copies are asked once).
    asked: HashMap<[u64; 6], usize>,
    /// `(item, query)`: stats of current items not known yet.
    inputs: Vec<(usize, usize)>,
    /// Where the scan goes on when no listed pair succeeds; `None` at the end of the scan.
    resume: Option<(Phase, usize, usize)>,
}

impl Listing {
    fn ask(&mut self, seg: Segment, r: f64) -> usize {
        let n = self.queries.len();
        *self.asked.entry(bits(&seg)).or_insert_with(|| {
            self.queries.push(Query::new(seg, r));
            n
        })
    }
}

fn bits(s: &Segment) -> [u64; 6] {
    let (a, b) = (s.p1.to_array(), s.p2.to_array());
    [a[0], a[1], a[2], b[0], b[1], b[2]].map(f64::to_bits)
}

type Key = (u64, u64, Phase);

pub(super) struct Machine {
    pub(super) items: Vec<Item>,
    phase: Phase,
    /// Next pair `(i, j)` of `phase` to look at.
    next: (usize, usize),
    budget: usize,
    first_budget: usize,
    /// Identity of each item's content: a success that changes an item gives it a new one.
    uids: Vec<u64>,
    next_uid: u64,
    /// Pairs (by identity) decided against.
    failed: HashSet<Key>,
    /// Pairs (by identity) decided in favour in a round where an earlier pair won.
    won: HashMap<Key, Made>,
    /// After a restart caused by item `i` changing in `phase`: every pair before it in scan
    /// order failed and only item `i` changed, so in rows `a < i` the pair `(a, i)` is the
    /// only one that can decide differently. The scan skips the rest of those rows, which
    /// keeps a cluster of `k` segments at `O(k)` work per restart instead of `O(k^2)`.
    hot: Option<(Phase, usize)>,
}

impl Machine {
    pub(super) fn new(items: Vec<Item>, mode: Mode, budget: usize) -> Self {
        let n = items.len() as u64;
        Machine {
            items,
            phase: match mode {
                Mode::Cluster => Phase::Merge,
                Mode::Collinear => Phase::Join,
            },
            next: (0, 1),
            budget,
            first_budget: budget,
            uids: (0..n).collect(),
            next_uid: n,
            failed: Default::default(),
            won: Default::default(),
            hot: None,
        }
    }

    fn done(&self) -> bool {
        self.phase == Phase::Done
    }

    /// The pairs of this round, from `next` on, at most `budget` of them.
    fn list(&self, cx: Ctx) -> Listing {
        let mut l = Listing::default();
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
            let key = (self.uids[i], self.uids[j], phase);
            if let Some(made) = self.won.get(&key) {
                l.cands.push((i, j, phase, Cand::Known(*made)));
            } else if !self.failed.contains(&key) {
                if let Some(c) = self.candidate(i, j, phase, cx) {
                    for k in [i, j] {
                        if self.items[k].stats.is_none() {
                            let q = l.ask(self.items[k].seg, cx.r);
                            l.inputs.push((k, q));
                        }
                    }
                    let c = match c {
                        Ok(c) => Cand::Merge {
                            c,
                            q: l.ask(c.g_prime, cx.r),
                        },
                        Err(c) => Cand::Join {
                            c,
                            // A degenerate chord (touching segments) holds no point.
                            q_chord: c.chord.is_valid().then(|| l.ask(c.chord, cx.r)),
                            q_joined: l.ask(c.joined, cx.r),
                        },
                    };
                    l.cands.push((i, j, phase, c));
                }
            }
            j += 1;
        }
    }

    /// The CPU part of the rule of `phase` for the pair `(i, j)`.
    fn candidate(
        &self,
        i: usize,
        j: usize,
        phase: Phase,
        cx: Ctx,
    ) -> Option<Result<MergeCandidate, JoinCandidate>> {
        let (a, b) = (&self.items[i].seg, &self.items[j].seg);
        match phase {
            Phase::Merge if rules::overlaps(a, b, cx.fixes) => {
                rules::merge_candidate(a, b, cx.p).map(Ok)
            }
            Phase::Join if cx.mode == Mode::Collinear || !rules::overlaps(a, b, cx.fixes) => {
                rules::join_candidate(a, b, cx.p, cx.fixes).map(Err)
            }
            _ => None,
        }
    }

    /// Walks the round's list in order (see the module comment).
    fn apply(&mut self, l: Listing, res: &[CylStats], cx: Ctx) {
        for &(k, q) in &l.inputs {
            self.items[k].stats = Some(res[q]);
        }
        let mut dropped: Vec<usize> = Vec::new();
        let mut change = None;
        for &(i, j, phase, c) in &l.cands {
            let made = match c {
                Cand::Known(made) => Some(made),
                Cand::Merge { c, q } => {
                    let (a, b) = (&self.items[i], &self.items[j]);
                    rules::merge(input(a), input(b), &c, res[q], cx.p, cx.fixes)
                }
                Cand::Join {
                    c,
                    q_chord,
                    q_joined,
                } => {
                    let (a, b) = (&self.items[i], &self.items[j]);
                    let n_chord = q_chord.map_or(0, |q| res[q].count);
                    rules::join(
                        input(a),
                        input(b),
                        &c,
                        n_chord,
                        res[q_joined],
                        cx.p,
                        cx.fixes,
                    )
                }
            };
            let key = (self.uids[i], self.uids[j], phase);
            let Some(made) = made else {
                self.failed.insert(key);
                continue;
            };
            self.won.insert(key, made);
            // Pairs of an item dropped in this walk no longer exist; their decisions
            // stay in the memo (by identity) but do not apply.
            let gone = |k| dropped.binary_search(&k).is_ok();
            if change.is_some() || gone(i) || gone(j) {
                continue;
            }
            if bits(&made.seg) == bits(&self.items[i].seg) {
                // Kept sorted: a later row may drop an index below an earlier row's.
                let at = dropped.partition_point(|&d| d < j);
                dropped.insert(at, j);
            } else {
                change = Some((i, j, made, phase));
            }
        }
        let (phase, i, j) = match change {
            Some((i, j, made, phase)) => {
                self.items[i].seg = made.seg;
                self.items[i].stats = made.stats;
                self.uids[i] = self.next_uid;
                self.next_uid += 1;
                let at = dropped.partition_point(|&d| d < j);
                dropped.insert(at, j);
                self.compact(&dropped);
                let i = new_index(&dropped, i);
                self.hot = Some((phase, i));
                self.budget = self.first_budget;
                (phase, 0, 1)
            }
            None => {
                let Some((phase, i, j)) = l.resume else {
                    self.compact(&dropped);
                    self.phase = Phase::Done;
                    return;
                };
                self.compact(&dropped);
                self.hot = match self.hot {
                    Some((hp, h)) if !gone_in(&dropped, h) => Some((hp, new_index(&dropped, h))),
                    _ => None,
                };
                self.budget = self.budget.saturating_mul(2);
                let ni = new_index(&dropped, i);
                if gone_in(&dropped, i) {
                    (phase, ni, ni + 1)
                } else {
                    (phase, ni, new_index(&dropped, j))
                }
            }
        };
        self.phase = phase;
        self.next = (i, j);
    }

    /// Drops the items at the sorted indices `dropped`.
    fn compact(&mut self, dropped: &[usize]) {
        if dropped.is_empty() {
            return;
        }
        let keep = |k: &usize| !gone_in(dropped, *k);
        let mut k = 0;
        self.items.retain(|_| {
            k += 1;
            keep(&(k - 1))
        });
        let mut k = 0;
        self.uids.retain(|_| {
            k += 1;
            keep(&(k - 1))
        });
    }
}

fn gone_in(dropped: &[usize], k: usize) -> bool {
    dropped.binary_search(&k).is_ok()
}

/// Index of item `k` (or, if it was dropped, of the next kept one) after dropping.
fn new_index(dropped: &[usize], k: usize) -> usize {
    k - dropped.partition_point(|&d| d < k)
}

/// A current item as a rule's input (its stats are asked before any decision reads them).
fn input(it: &Item) -> (&Segment, CylStats) {
    (&it.seg, it.stats.expect("stats asked in the listing"))
}

/// Runs every group to its end, one engine batch per round.
pub(super) fn run(
    engine: &dyn Engine,
    machines: &mut [Machine],
    cx: Ctx,
) -> Result<(), EngineError> {
    while machines.iter().any(|m| !m.done()) {
        let listings: Vec<Option<Listing>> = machines
            .par_iter()
            .map(|m| (!m.done()).then(|| m.list(cx)))
            .collect();
        let mut queries = Vec::new();
        let mut offsets = Vec::with_capacity(listings.len());
        for l in listings.iter().flatten() {
            offsets.push(queries.len());
            queries.extend_from_slice(&l.queries);
        }
        // A round may ask nothing (its pairs were all decided earlier) and still apply.
        let res = if queries.is_empty() {
            Vec::new()
        } else {
            engine.stats(&queries, Want::SUMS)?
        };
        let mut offsets = offsets.into_iter();
        let work: Vec<(&mut Machine, Listing, usize)> = machines
            .iter_mut()
            .zip(listings)
            .filter_map(|(m, l)| l.map(|l| (m, l, offsets.next().unwrap_or(0))))
            .collect();
        work.into_par_iter().for_each(|(m, l, off)| {
            let n = l.queries.len();
            m.apply(l, &res[off..off + n], cx);
        });
    }
    Ok(())
}
