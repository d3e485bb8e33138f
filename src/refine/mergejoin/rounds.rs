//! The batched machinery that runs the restart loops of [`super::sequential`] for every
//! group at once, one engine batch per round (docs/architecture.md#the-engine-contract),
//! with exactly the same result.
//!
//! A decision is a pure function of the two items (and the phase), so everything decided
//! stays valid until one of its items changes. Every group is a small state machine that
//! keeps, per phase, the pairs not known to fail ([`Open`]): a pair leaves when its CPU
//! part or its queries decide against it, or when one of its items is dropped, and a
//! success that changes item `h` puts back only the pairs of `h`. A restart therefore
//! costs the pairs of the changed item, not a new scan of the whole group: a cluster of
//! hundreds of near-duplicates (the real Line3D++ output under `reference`) would
//! otherwise rescan `O(k^2)` failing pairs after each of its `O(k)` merges.
//!
//! In one round each unfinished group lists its open pairs in scan order, with the queries
//! their decisions need (across the end of the merge scan into the join scan, whose pairs
//! then count only if no merge succeeds), until its budget is full or it meets a pair
//! already known to succeed with a change (which ends the scan of this round: nothing
//! after it can apply); all groups' queries go to the engine as one batch; then each group
//! walks its list in order:
//! - a pair whose result is item `i` itself, bit for bit (a copy merged into its twin):
//!   item `j` is dropped and the walk goes on, because nothing any other decision reads
//!   has changed — this is what the sequential loop does after its restart, which finds
//!   every earlier pair failing again;
//! - the first other success is applied and the scan restarts;
//! - no success: the listed pairs leave the open set.
//!
//! Decisions that need queries are also kept (the memo) by item identity, the failed
//! ones and the successes that lost to an earlier pair of their round. A round whose pairs
//! are all decided asks nothing but still applies; the loop ends only when every group's
//! full scan has found nothing to do.

use super::near::Near;
use super::rules::{self, JoinCandidate, Made, MergeCandidate};
use super::{Ctx, Item, Mode};
use crate::engine::{CylStats, Engine, EngineError, Query, Want};
use crate::geom::Segment;
use rayon::prelude::*;
use std::collections::BTreeSet;
use std::hash::{BuildHasherDefault, Hasher};

/// A multiply-rotate hasher for the memo's keys (identities, phases) and the listing's
/// segment bits: these maps are only looked up, never iterated into a result, so the
/// hash function changes no decision, and SipHash took a sixth of the step's time on
/// dense clusters.
#[derive(Default, Clone, Copy)]
struct WordHasher(u64);

impl Hasher for WordHasher {
    fn write(&mut self, bytes: &[u8]) {
        for chunk in bytes.chunks(8) {
            let mut w = [0u8; 8];
            w[..chunk.len()].copy_from_slice(chunk);
            self.write_u64(u64::from_le_bytes(w));
        }
    }

    fn write_u64(&mut self, w: u64) {
        self.0 = (self.0.rotate_left(5) ^ w).wrapping_mul(0x51_7c_c1_b7_27_22_0a_95);
    }

    fn write_u8(&mut self, w: u8) {
        self.write_u64(u64::from(w));
    }

    fn write_usize(&mut self, w: usize) {
        self.write_u64(w as u64);
    }

    fn finish(&self) -> u64 {
        // The high bits mixed down: the table indexes by the low ones.
        self.0 ^ (self.0 >> 29)
    }
}

type HashMap<K, V> = std::collections::HashMap<K, V, BuildHasherDefault<WordHasher>>;
type HashSet<K> = std::collections::HashSet<K, BuildHasherDefault<WordHasher>>;

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
    /// The phase whose scan this listing did not finish (budget full, or a known success
    /// that changes an item); `None` when it reached the end of the last phase.
    stopped: Option<Phase>,
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

/// The pairs of one phase not known to fail: in row `a` (pairs `(a, c)`, `c > a`), the
/// columns in `pending[a]` and every column from `from[a]` on that [`Near`] lists (the
/// others fail the rules' CPU part). Columns of dropped items are skipped (and removed)
/// when a scan meets them.
struct Open {
    from: Vec<usize>,
    /// Sorted; columns below `from[a]` whose item changed after the scan passed them.
    pending: Vec<Vec<usize>>,
    /// The rows that may hold an open pair (the others have `from[a] == m` and nothing
    /// pending), so that a round does not walk every row of a large group.
    rows: BTreeSet<usize>,
    /// Entries of `pending` in all, for the step's bound ([`PairBound`]).
    held: usize,
}

impl Open {
    fn new(m: usize) -> Self {
        Open {
            from: (1..=m).collect(),
            pending: vec![Vec::new(); m],
            rows: (0..m).collect(),
            held: 0,
        }
    }

    /// Item `h` changed: every pair of it is open again, and only those (`near` lists the
    /// rows whose pair with `h` can pass a rule).
    fn reopen(&mut self, h: usize, alive: &[bool], near: &mut Near, buf: &mut Vec<usize>) {
        self.from[h] = h + 1;
        self.held -= self.pending[h].len();
        self.pending[h].clear();
        self.rows.insert(h);
        near.rows(h, alive, buf);
        for &a in buf.iter() {
            if self.from[a] > h {
                let pending = &mut self.pending[a];
                if let Err(at) = pending.binary_search(&h) {
                    pending.insert(at, h);
                    self.held += 1;
                }
                self.rows.insert(a);
            }
        }
    }
}

/// What the scan does with one open pair.
enum Offer {
    /// Decided against (CPU part or memo): the pair leaves the open set.
    Fail,
    /// Listed for this round's walk.
    Listed,
    /// The listing ends here (the pair was listed when `true`: a known success that
    /// changes an item; not when the budget is full).
    Stop,
}

pub(super) struct Machine {
    items: Vec<Item>,
    /// Items not dropped; a dropped item keeps its index, so scan order stays index order.
    alive: Vec<bool>,
    phase: Phase,
    /// Open pairs of the merge and of the join scan, made when the scan first gets there;
    /// the join's is dropped when a merge changes an item (its scan starts afresh).
    open_merge: Option<Open>,
    open_join: Option<Open>,
    budget: usize,
    first_budget: usize,
    /// Identity of each item's content: a success that changes an item gives it a new one.
    uids: Vec<u64>,
    next_uid: u64,
    /// The item each identity was given to (it is that item's content while
    /// `uids[item] == uid` and the item is alive).
    item_of: Vec<u32>,
    /// Size of the memo that makes it forget the decisions about identities gone.
    memo_limit: usize,
    /// Pairs (by identity) decided against by their queries.
    failed: HashSet<Key>,
    /// Pairs (by identity) decided in favour in a round where an earlier pair won.
    won: HashMap<Key, Made>,
    /// The group's input items each item holds (its own, and those merged or joined
    /// into it): the provenance of the result.
    members: Vec<Vec<usize>>,
    /// Which pairs can pass a rule at all; made at the first listing.
    near: Option<Near>,
    /// Groups of fewer items list every pair instead (tests set 0).
    sweep_from: usize,
    /// Scratch for [`Near`]'s answers.
    buf: Vec<usize>,
}

impl Machine {
    pub(super) fn new(items: Vec<Item>, mode: Mode, budget: usize, sweep_from: usize) -> Self {
        let n = items.len();
        Machine {
            items,
            alive: vec![true; n],
            members: (0..n).map(|k| vec![k]).collect(),
            phase: match mode {
                Mode::Cluster => Phase::Merge,
                Mode::Collinear => Phase::Join,
            },
            open_merge: None,
            open_join: None,
            budget,
            first_budget: budget,
            uids: (0..n as u64).collect(),
            next_uid: n as u64,
            item_of: (0..n as u32).collect(),
            memo_limit: MEMO_FIRST_LIMIT,
            failed: Default::default(),
            won: Default::default(),
            near: None,
            sweep_from,
            buf: Vec::new(),
        }
    }

    fn done(&self) -> bool {
        self.phase == Phase::Done
    }

    /// The group's items at the end, in order, each with the indices (into the items the
    /// machine was made with) of the items it holds, in increasing order.
    pub(super) fn into_items_with_members(self) -> Vec<(Item, Vec<usize>)> {
        let alive = self.alive;
        self.items
            .into_iter()
            .zip(self.members)
            .zip(alive)
            .filter_map(|((it, mut m), a)| {
                m.sort_unstable();
                a.then_some((it, m))
            })
            .collect()
    }

    /// Item `j` goes into item `i`.
    fn absorb(&mut self, i: usize, j: usize) {
        self.alive[j] = false;
        let mj = std::mem::take(&mut self.members[j]);
        self.members[i].extend(mj);
    }

    /// The open pairs of this round in scan order, at most `budget` of them (see the
    /// module comment). Pairs the scan finds decided against leave the open set.
    fn list(&mut self, cx: Ctx) -> Listing {
        let mut l = Listing::default();
        let m = self.items.len();
        if self.near.is_none() {
            self.near = Some(Near::new(&self.items, &cx, self.sweep_from));
        }
        if self.phase == Phase::Merge {
            let mut open = self.open_merge.take().unwrap_or_else(|| Open::new(m));
            let finished = self.scan(Phase::Merge, &mut open, &mut l, cx);
            self.open_merge = Some(open);
            if !finished {
                l.stopped = Some(Phase::Merge);
                return l;
            }
            if l.cands.is_empty() {
                // Nothing open is left: the merge loop has ended.
                self.phase = Phase::Join;
                self.open_merge = None;
            }
        }
        let mut open = self.open_join.take().unwrap_or_else(|| Open::new(m));
        if !self.scan(Phase::Join, &mut open, &mut l, cx) {
            l.stopped = Some(Phase::Join);
        }
        self.open_join = Some(open);
        l
    }

    /// Lists the open pairs of `phase` in scan order; `false` when the listing stopped.
    fn scan(&mut self, phase: Phase, open: &mut Open, l: &mut Listing, cx: Ctx) -> bool {
        let m = self.items.len();
        let mut near = self.near.take().expect("made at the first listing");
        let mut cols = std::mem::take(&mut self.buf);
        let finished = self.scan_rows(phase, open, l, cx, &mut near, &mut cols, m);
        self.near = Some(near);
        self.buf = cols;
        finished
    }

    #[allow(clippy::too_many_arguments)]
    fn scan_rows(
        &mut self,
        phase: Phase,
        open: &mut Open,
        l: &mut Listing,
        cx: Ctx,
        near: &mut Near,
        cols: &mut Vec<usize>,
        m: usize,
    ) -> bool {
        let mut next = open.rows.first().copied();
        while let Some(a) = next {
            next = open.rows.range(a + 1..).next().copied();
            if !self.alive[a] {
                open.rows.remove(&a);
                continue;
            }
            let pending = std::mem::take(&mut open.pending[a]);
            open.held -= pending.len();
            let mut keep = Vec::new();
            let mut rest = pending.into_iter();
            let mut stopped = false;
            for c in rest.by_ref() {
                if !self.alive[c] {
                    continue;
                }
                match self.offer(a, c, phase, l, cx) {
                    Offer::Fail => {}
                    Offer::Listed => keep.push(c),
                    Offer::Stop => {
                        keep.push(c);
                        stopped = true;
                        break;
                    }
                }
            }
            keep.extend(rest);
            open.held += keep.len();
            open.pending[a] = keep;
            if stopped {
                return false;
            }
            // The open columns from `from[a]` on: a failing prefix leaves the set; the
            // columns `near` leaves out fail.
            if open.from[a] < m {
                near.columns(a, open.from[a], &self.alive, cols);
                let mut prefix = true;
                for &c in cols.iter() {
                    match self.offer(a, c, phase, l, cx) {
                        Offer::Fail if prefix => open.from[a] = c + 1,
                        Offer::Fail => {}
                        Offer::Listed => prefix = false,
                        Offer::Stop => return false,
                    }
                }
                if prefix {
                    open.from[a] = m;
                }
            }
            if open.from[a] >= m && open.pending[a].is_empty() {
                open.rows.remove(&a);
            }
        }
        true
    }

    /// Looks at the open pair `(i, j)` of `phase` and lists it when it needs deciding.
    fn offer(&self, i: usize, j: usize, phase: Phase, l: &mut Listing, cx: Ctx) -> Offer {
        let key = (self.uids[i], self.uids[j], phase);
        if self.failed.contains(&key) {
            return Offer::Fail;
        }
        if let Some(made) = self.won.get(&key) {
            if l.cands.len() >= self.budget {
                return Offer::Stop;
            }
            l.cands.push((i, j, phase, Cand::Known(*made)));
            // A success that changes item `i` applies unless an earlier pair does: this
            // round's walk ends there either way.
            return match bits(&made.seg) == bits(&self.items[i].seg) {
                true => Offer::Listed,
                false => Offer::Stop,
            };
        }
        let Some(c) = self.candidate(i, j, phase, cx) else {
            return Offer::Fail;
        };
        if l.cands.len() >= self.budget {
            return Offer::Stop;
        }
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
        Offer::Listed
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
                rules::merge_candidate(a, b, cx.p, cx.fidelity()).map(Ok)
            }
            Phase::Join if cx.mode == Mode::Collinear || !rules::overlaps(a, b, cx.fixes) => {
                rules::join_candidate(a, b, cx.p, cx.fixes, cx.fidelity()).map(Err)
            }
            _ => None,
        }
    }

    /// Walks the round's list in order (see the module comment).
    fn apply(&mut self, l: Listing, res: &[CylStats], cx: Ctx) {
        for &(k, q) in &l.inputs {
            self.items[k].stats = Some(res[q]);
        }
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
            if change.is_some() || !self.alive[i] || !self.alive[j] {
                continue;
            }
            if bits(&made.seg) == bits(&self.items[i].seg) {
                self.absorb(i, j);
            } else {
                change = Some((i, j, made, phase));
            }
        }
        match change {
            Some((i, j, made, phase)) => {
                self.items[i].seg = made.seg;
                self.items[i].stats = made.stats;
                self.absorb(i, j);
                let near = self.near.as_mut().expect("made at the first listing");
                near.update(i, &self.items[i]);
                self.uids[i] = self.next_uid;
                self.item_of.push(i as u32);
                self.next_uid += 1;
                let open = match phase {
                    Phase::Merge => {
                        // The join scan starts afresh once the merge loop ends.
                        self.open_join = None;
                        &mut self.open_merge
                    }
                    _ => {
                        self.open_merge = None;
                        &mut self.open_join
                    }
                };
                open.as_mut()
                    .expect("a listed phase has its open set")
                    .reopen(i, &self.alive, near, &mut self.buf);
                self.phase = phase;
                self.budget = self.first_budget;
            }
            None => {
                match l.stopped {
                    None => self.phase = Phase::Done,
                    Some(p) => {
                        if p == Phase::Join {
                            // Every merge pair was listed and none changed anything.
                            self.open_merge = None;
                        }
                        self.phase = p;
                    }
                }
                self.budget = self.budget.saturating_mul(2);
            }
        }
        self.forget();
    }
}

/// The memo's size from which it is trimmed ([`Machine::forget`]); small in tests, so
/// that they trim it.
const MEMO_FIRST_LIMIT: usize = if cfg!(test) { 8 } else { 1 << 12 };

impl Machine {
    /// The pair entries the group holds: its memo, its open sets' pending columns and its
    /// sweep's bucket entries (what grows with the pairs, not with the items).
    fn held(&self) -> usize {
        let open = |o: &Option<Open>| o.as_ref().map_or(0, |o| o.held);
        self.failed.len()
            + self.won.len()
            + open(&self.open_merge)
            + open(&self.open_join)
            + self.near.as_ref().map_or(0, Near::entries)
    }

    /// Whether `uid` is the content of an alive item.
    fn live(&self, uid: u64) -> bool {
        let i = self.item_of[uid as usize] as usize;
        self.uids[i] == uid && self.alive[i]
    }

    /// Drops the decisions about identities no alive item has (a lookup only ever asks
    /// about alive items' identities, so no answer changes), once the memo has doubled
    /// since the last time: a cluster of many successes keeps a memo of its live pairs,
    /// not of every pair it ever decided.
    fn forget(&mut self) {
        if self.phase == Phase::Done {
            // Nothing is asked again: only the items are kept.
            self.failed = Default::default();
            self.won = Default::default();
            self.near = None;
            self.open_merge = None;
            self.open_join = None;
            return;
        }
        if self.failed.len() + self.won.len() <= self.memo_limit {
            return;
        }
        let mut failed = std::mem::take(&mut self.failed);
        failed.retain(|&(a, b, _)| self.live(a) && self.live(b));
        self.failed = failed;
        let mut won = std::mem::take(&mut self.won);
        won.retain(|&(a, b, _), _| self.live(a) && self.live(b));
        self.won = won;
        self.failed.shrink_to_fit();
        self.won.shrink_to_fit();
        let kept = self.failed.len() + self.won.len();
        self.memo_limit = self.memo_limit.max(2 * kept);
    }
}

/// A current item as a rule's input (its stats are asked before any decision reads them).
fn input(it: &Item) -> (&Segment, CylStats) {
    (&it.seg, it.stats.expect("stats asked in the listing"))
}

/// Most pair entries (memo, open pairs, sweep entries and the round's listed pairs) a
/// merge/join step holds, on average a segment of its input; each takes 8 to about 64
/// bytes (a memo entry in its hash set), so at most 64 KiB a segment, and never less
/// than [`PairBound::FLOOR`] entries in all. The dense box scenes of the benches hold
/// at most about 3 a segment (`cargo bench --bench mergejoin -- dense`, 10^5 and
/// 3 x 10^5 pieces). `LINEGS_MAX_PAIRS_PER_SEGMENT` sets another value (then without
/// the floor).
pub const MAX_PAIRS_PER_SEGMENT: usize = 1024;

/// The bound of a merge/join step on the pair entries it holds, checked after each
/// round's listing (before the round's batch is asked): past it the step ends with
/// [`EngineError::Limit`] (exit code 1) and a message that says which bound and how to
/// raise it.
pub(super) struct PairBound {
    per_segment: usize,
    /// From `LINEGS_MAX_PAIRS_PER_SEGMENT` (the message says so) or the default.
    from_env: bool,
    limit: usize,
    segments: usize,
}

/// The process's `LINEGS_MAX_PAIRS_PER_SEGMENT` as the command line read it (the library
/// reads no environment): `None` keeps the default bound.
static PAIRS_SETTING: std::sync::RwLock<Option<String>> = std::sync::RwLock::new(None);

/// Sets the pair-entry bound a segment of steps 6 and 8 (the text of
/// `LINEGS_MAX_PAIRS_PER_SEGMENT`, checked when a step starts; `None`: the default, with its
/// floor of [`PairBound::FLOOR`] entries in all).
pub fn set_max_pairs_per_segment(v: Option<String>) {
    if let Ok(mut s) = PAIRS_SETTING.write() {
        *s = v;
    }
}

impl PairBound {
    /// Fewest entries the bound allows, whatever the input's size.
    pub const FLOOR: usize = 1 << 20;

    /// The bound for `segments` input segments; an unreadable
    /// `LINEGS_MAX_PAIRS_PER_SEGMENT` is [`EngineError::Limit`] too, naming it.
    pub(super) fn new(segments: usize) -> Result<Self, EngineError> {
        let setting = PAIRS_SETTING.read().map(|s| s.clone()).unwrap_or(None);
        let (per_segment, from_env) = match setting {
            Some(v) => match v.trim().parse::<usize>() {
                Ok(n) if n > 0 => (n, true),
                _ => {
                    return Err(EngineError::Limit(format!(
                        "LINEGS_MAX_PAIRS_PER_SEGMENT={v:?} is not a positive whole number"
                    )))
                }
            },
            None => (MAX_PAIRS_PER_SEGMENT, false),
        };
        let floor = if from_env { 0 } else { Self::FLOOR };
        Ok(PairBound {
            per_segment,
            from_env,
            limit: segments.saturating_mul(per_segment).max(floor),
            segments,
        })
    }

    fn check(&self, held: usize, cx: &Ctx) -> Result<(), EngineError> {
        if held <= self.limit {
            return Ok(());
        }
        let step = match cx.mode {
            Mode::Cluster => "step 8 (merge_join)",
            Mode::Collinear => "step 6 (collinear_merge)",
        };
        Err(EngineError::Limit(format!(
            "{step} holds more than {} pair entries for {} segments, and it holds at most \
             {} a segment{} (up to 64 bytes each, so at most {:.1} MB here): the segments \
             are too dense for the rules' reach; try a smaller --radius (fewer segments a \
             cluster), or raise the bound with LINEGS_MAX_PAIRS_PER_SEGMENT=N where the \
             machine has the memory",
            self.limit,
            self.segments,
            self.per_segment,
            if self.from_env {
                " (LINEGS_MAX_PAIRS_PER_SEGMENT)"
            } else {
                ""
            },
            (self.limit as f64 * 64.0) / 1e6,
        )))
    }
}

/// Runs every group to its end, one engine batch per round; `segments`: the step's input
/// segments (the pair bound's base; groups of one segment need no machine).
pub(super) fn run(
    engine: &dyn Engine,
    machines: &mut [Machine],
    cx: Ctx,
    segments: usize,
) -> Result<(), EngineError> {
    let bound = PairBound::new(segments)?;
    // The groups still running: a round walks these, not every group (the long tail of
    // rounds of a few large groups would otherwise walk the finished ones each time).
    let mut active: Vec<&mut Machine> = machines.iter_mut().filter(|m| !m.done()).collect();
    while !active.is_empty() {
        // Each unfinished group's listing and the entries it holds with it.
        let (listings, held): (Vec<Listing>, Vec<usize>) = active
            .par_iter_mut()
            .map(|m| {
                let l = m.list(cx);
                let held = m.held() + l.cands.len();
                (l, held)
            })
            .unzip();
        bound.check(held.iter().sum(), &cx)?;
        let mut queries = Vec::new();
        let mut offsets = Vec::with_capacity(listings.len());
        for l in &listings {
            offsets.push(queries.len());
            queries.extend_from_slice(&l.queries);
        }
        // A round may ask nothing (its pairs were all decided earlier) and still apply.
        let res = if queries.is_empty() {
            Vec::new()
        } else {
            engine.stats(&queries, Want::SUMS)?
        };
        active
            .par_iter_mut()
            .zip(listings)
            .zip(offsets)
            .for_each(|((m, l), off)| {
                let n = l.queries.len();
                m.apply(l, &res[off..off + n], cx);
            });
        active.retain(|m| !m.done());
    }
    Ok(())
}
