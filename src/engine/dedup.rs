//! Identical queries cost once: [`Dedup`] wraps any [`Engine`] and, per batch,
//! groups the queries whose bits are identical (`P1`, `P2`, `r`, `plane`, and for
//! [`Engine::nearest`] the query's `k`), asks the inner engine only the distinct ones, in
//! the order of their first occurrence, and copies each answer back to every copy.
//!
//! An engine's answer to a query is a function of that query's bits alone (both engines
//! answer each query on its own, summing its points in grid order), so the answers equal
//! those of asking the whole batch, bit for bit (`members` lists are cloned to each
//! copy). Coverage is a union: duplicates add nothing to it. Duplicated input segments (Line3D++ and LIMAP outputs in busy areas,
//! merged multi-run files) make every step ask the same cylinder many times; with this
//! wrapper each step's cost grows with the distinct segments, not the copies.
//!
//! Bits, not values: `0.0` and `-0.0` are different keys (asked twice, answered alike),
//! and a NaN query equals only its own bit pattern. A batch without duplicates goes to
//! the inner engine as it is, without a copy.

use super::{
    Answers, Ask, Counters, Engine, EngineError, FitAnswer, FitAsk, FitJob, Member, Nearest, Query,
};
use crate::geom::fit::{FitResult, LineFit};
use std::sync::atomic::{AtomicU64, Ordering};

/// The bit pattern a query is grouped by: its ten coordinates, then `k` (0 outside
/// `nearest`).
type Key = [u64; 11];

fn key(q: &Query, k: u64) -> Key {
    let (a, b, p) = (q.seg.p1, q.seg.p2, q.plane);
    [
        a.x.to_bits(),
        a.y.to_bits(),
        a.z.to_bits(),
        b.x.to_bits(),
        b.y.to_bits(),
        b.z.to_bits(),
        q.r.to_bits(),
        p.x.to_bits(),
        p.y.to_bits(),
        p.z.to_bits(),
        k,
    ]
}

/// A hash of a key for [`Groups::of`]'s table (a multiply-xorshift mix of each word, then
/// splitmix64's finaliser): which slot a key starts from, never whether two keys are equal.
fn hash(k: &Key) -> u64 {
    let mut h = 0x9E37_79B9_7F4A_7C15u64;
    for &w in k {
        h = (h ^ w).wrapping_mul(0xBF58_476D_1CE4_E5B9).rotate_left(31);
    }
    h ^= h >> 30;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 27;
    h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
    h ^ (h >> 31)
}

/// The distinct queries of a batch: `first[d]` is the batch index of distinct query `d`'s
/// first occurrence (increasing), `of[i]` the distinct query that batch query `i` is.
struct Groups {
    first: Vec<usize>,
    of: Vec<usize>,
}

impl Groups {
    /// `None` when every query is distinct.
    fn of(queries: &[Query], k: Option<&[u64]>) -> Option<Groups> {
        let n = queries.len();
        // A batch of 2^31 queries or more is asked as it is (it would not fit in memory).
        if !(2..1 << 31).contains(&n) {
            return None;
        }
        let key_of = |i: usize| key(&queries[i], k.map_or(0, |k| k[i]));
        // Open addressing over the distinct queries' numbers (`d + 1`; 0: empty), at most
        // half full, compared by the keys of their first occurrences: 8 bytes a query at
        // most, where a hash map of the keys took about 100 (at 3 x 10^6 queries a batch,
        // hundreds of MB read at random and written fresh on every batch).
        let slots = (2 * n).next_power_of_two();
        let mask = slots - 1;
        let mut table = vec![0u32; slots];
        let mut first: Vec<usize> = Vec::new();
        let mut of = Vec::with_capacity(n);
        for i in 0..n {
            let kq = key_of(i);
            let mut at = (hash(&kq) as usize) & mask;
            let d = loop {
                match table[at] {
                    0 => {
                        first.push(i);
                        table[at] = first.len() as u32;
                        break first.len() - 1;
                    }
                    e if key_of(first[e as usize - 1]) == kq => break e as usize - 1,
                    _ => at = (at + 1) & mask,
                }
            };
            of.push(d);
        }
        if first.len() == n {
            None
        } else {
            Some(Groups { first, of })
        }
    }

    fn queries(&self, queries: &[Query]) -> Vec<Query> {
        self.first.iter().map(|&i| queries[i]).collect()
    }

    fn fan_out<T: Clone>(&self, answers: &[T]) -> Vec<T> {
        self.of.iter().map(|&d| answers[d].clone()).collect()
    }

    /// An error about distinct query `d` names its first occurrence in the batch.
    fn error(&self, e: EngineError) -> EngineError {
        match e {
            EngineError::BadQuery { index, why } => EngineError::BadQuery {
                index: self.first.get(index).copied().unwrap_or(index),
                why,
            },
            other => other,
        }
    }
}

/// `fit` of the distinct segments of `job` (bit for bit: a segment's fit depends on its
/// own bits alone), each answer copied back to every copy.
pub(super) fn fit_distinct(
    job: &FitJob<'_>,
    fit: impl FnOnce(&FitJob<'_>) -> Result<FitResult, EngineError>,
) -> Result<FitResult, EngineError> {
    let queries: Vec<Query> = job.segments.iter().map(|s| Query::new(*s, job.r)).collect();
    Ok(match Groups::of(&queries, None) {
        None => fit(job)?,
        Some(g) => {
            let distinct: Vec<_> = g.first.iter().map(|&i| job.segments[i]).collect();
            let f = fit(&FitJob {
                segments: &distinct,
                ..*job
            })?;
            FitResult {
                segments: g.fan_out(&f.segments),
                how: g.fan_out(&f.how),
                iterations: f.iterations,
                steps: g.fan_out(&f.steps),
            }
        }
    })
}

/// An [`Engine`] that asks its inner engine each distinct query of a batch once. Every
/// other method (backend, adapter, counters, seconds) is the inner engine's: its
/// counters count the queries it actually answered; [`Dedup::asked`] counts those the
/// steps asked.
pub struct Dedup {
    inner: Box<dyn Engine>,
    asked: AtomicU64,
}

impl Dedup {
    pub fn new(inner: Box<dyn Engine>) -> Self {
        Dedup {
            inner,
            asked: AtomicU64::new(0),
        }
    }

    pub fn inner(&self) -> &dyn Engine {
        self.inner.as_ref()
    }

    /// Queries asked of this engine so far, duplicates included (the inner engine's
    /// `counters().queries` counts the distinct ones it answered).
    pub fn asked(&self) -> u64 {
        self.asked.load(Ordering::Relaxed)
    }

    fn count(&self, n: usize) {
        self.asked.fetch_add(n as u64, Ordering::Relaxed);
    }

    /// `ask` of the inner engine for each distinct query once, its answer copied to the
    /// query's copies: for answers that are a function of the query alone.
    fn per_distinct<T: Clone>(
        &self,
        queries: &[Query],
        ask: impl FnOnce(&dyn Engine, &[Query]) -> Result<Vec<T>, EngineError>,
    ) -> Result<Vec<T>, EngineError> {
        self.count(queries.len());
        match Groups::of(queries, None) {
            None => ask(&*self.inner, queries),
            Some(g) => {
                let a = ask(&*self.inner, &g.queries(queries)).map_err(|e| g.error(e))?;
                Ok(g.fan_out(&a))
            }
        }
    }
}

impl Engine for Dedup {
    fn backend(&self) -> &'static str {
        self.inner.backend()
    }

    fn adapter(&self) -> String {
        self.inner.adapter()
    }

    fn n_points(&self) -> usize {
        self.inner.n_points()
    }

    fn query(&self, queries: &[Query], ask: &Ask<'_>) -> Result<Answers, EngineError> {
        self.count(queries.len());
        let k = match ask.nearest {
            Nearest::K(k) => Some(k),
            _ => None,
        };
        if k.is_some_and(|k| k.len() != queries.len()) {
            // The inner engine says what is wrong with the batch.
            return self.inner.query(queries, ask);
        }
        match Groups::of(queries, k) {
            None => self.inner.query(queries, ask),
            Some(g) => {
                let ks: Vec<u64> =
                    k.map_or_else(Vec::new, |k| g.first.iter().map(|&i| k[i]).collect());
                let inner_ask = Ask {
                    nearest: if k.is_some() {
                        Nearest::K(&ks)
                    } else {
                        ask.nearest
                    },
                    ..*ask
                };
                let a = self
                    .inner
                    .query(&g.queries(queries), &inner_ask)
                    .map_err(|e| g.error(e))?;
                // Coverage is a union: the copies add nothing to it.
                Ok(Answers {
                    stats: g.fan_out(&a.stats),
                    nearest: if a.nearest.is_empty() {
                        Vec::new()
                    } else {
                        g.fan_out(&a.nearest)
                    },
                    coverage: a.coverage,
                })
            }
        }
    }

    fn axial(&self, queries: &[Query]) -> Result<Vec<Vec<f64>>, EngineError> {
        self.per_distinct(queries, |e, q| e.axial(q))
    }

    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<Member>>, EngineError> {
        self.per_distinct(queries, |e, q| e.members(q))
    }

    /// The inner engine's parts where the queries are distinct; otherwise the distinct
    /// queries' lists, copied to the copies, handed out in the caller's order.
    fn members_in_parts(
        &self,
        queries: &[Query],
        group: usize,
        part: usize,
        f: &mut super::Parts<'_>,
    ) -> Result<(), EngineError> {
        match Groups::of(queries, None) {
            None => {
                self.count(queries.len());
                self.inner.members_in_parts(queries, group, part, f)
            }
            Some(_) => super::hand_out(self.members(queries)?, group, part, f),
        }
    }

    fn occupied(&self, queries: &[Query]) -> Result<Vec<bool>, EngineError> {
        self.per_distinct(queries, |e, q| e.occupied(q))
    }

    fn extent(&self, queries: &[Query]) -> Result<Vec<super::Extent>, EngineError> {
        self.per_distinct(queries, |e, q| e.extent(q))
    }

    /// The step of a segment is a function of its query's bits (and the batch-wide ask):
    /// each distinct query is fitted once and its answer copied.
    fn fit_lines(
        &self,
        queries: &[Query],
        ask: &FitAsk<'_>,
    ) -> Result<Vec<FitAnswer>, EngineError> {
        self.count(queries.len());
        // A warm and a cold ridge of the same query are different steps.
        let warm: Option<Vec<u64>> =
            (!ask.warm.is_empty()).then(|| ask.warm.iter().map(|&w| u64::from(w)).collect());
        match Groups::of(queries, warm.as_deref()) {
            None => self.inner.fit_lines(queries, ask),
            Some(g) => {
                // The inner engine numbers the distinct queries.
                let outer = ask.sensitive;
                let first = &g.first;
                let remap = move |d: usize, f: &LineFit| outer.is_some_and(|s| s(first[d], f));
                let inner_warm: Vec<bool> = if ask.warm.is_empty() {
                    Vec::new()
                } else {
                    first.iter().map(|&i| ask.warm[i]).collect()
                };
                let inner_ask = FitAsk {
                    sensitive: Some(&remap),
                    warm: &inner_warm,
                    ..*ask
                };
                let a = self
                    .inner
                    .fit_lines(&g.queries(queries), &inner_ask)
                    .map_err(|e| g.error(e))?;
                Ok(g.fan_out(&a))
            }
        }
    }

    /// A segment's fit is a function of its bits (and the job's parameters): each
    /// distinct segment is fitted once and its result copied.
    /// Each step of a segment counts as a query asked.
    fn fit_edges(&self, job: &FitJob<'_>) -> Result<FitResult, EngineError> {
        let f = fit_distinct(job, |j| self.inner.fit_edges(j))?;
        let steps: u64 = f.steps.iter().map(|&s| u64::from(s)).sum();
        self.asked.fetch_add(steps, Ordering::Relaxed);
        Ok(f)
    }

    fn counters(&self) -> Counters {
        self.inner.counters()
    }

    fn seconds(&self) -> Option<(f64, f64)> {
        self.inner.seconds()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::cpu::CpuEngine;
    use crate::engine::Want;
    use crate::geom::{Aabb, Segment};
    use crate::index::Grid;
    use glam::DVec3;
    use std::sync::{Arc, Mutex};

    /// Every batch asked, each query with its `k` (0 outside `nearest`).
    type Log = Arc<Mutex<Vec<Vec<(Query, u64)>>>>;

    /// The CPU engine, recording every batch it is asked.
    struct Recording {
        cpu: CpuEngine,
        seen: Log,
    }

    impl Engine for Recording {
        fn backend(&self) -> &'static str {
            "recording"
        }
        fn adapter(&self) -> String {
            "recording cpu".into()
        }
        fn n_points(&self) -> usize {
            self.cpu.n_points()
        }
        fn query(&self, q: &[Query], ask: &Ask<'_>) -> Result<Answers, EngineError> {
            let k = |i: usize| match ask.nearest {
                Nearest::K(k) => k.get(i).copied().unwrap_or(0),
                _ => 0,
            };
            self.seen
                .lock()
                .unwrap()
                .push(q.iter().enumerate().map(|(i, q)| (*q, k(i))).collect());
            self.cpu.query(q, ask)
        }
        fn members(&self, q: &[Query]) -> Result<Vec<Vec<Member>>, EngineError> {
            self.seen
                .lock()
                .unwrap()
                .push(q.iter().map(|q| (*q, 0)).collect());
            self.cpu.members(q)
        }
        fn counters(&self) -> Counters {
            self.cpu.counters()
        }
    }

    struct Rng(u64);
    impl Rng {
        fn f(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64) / ((1u64 << 53) as f64)
        }
        fn v(&mut self) -> DVec3 {
            DVec3::new(self.f(), self.f(), self.f())
        }
    }

    fn cpu() -> CpuEngine {
        let mut g = Rng(7);
        let pts: Vec<[f32; 3]> = (0..4000)
            .map(|i| {
                let p = if i % 2 == 0 {
                    g.v()
                } else {
                    DVec3::new(g.f(), 0.5, 0.5) + (g.v() - 0.5) * 0.05
                };
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect();
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        CpuEngine::new(Arc::new(Grid::build(&pts, b, 0.1)))
    }

    /// 40 distinct queries, each asked 1 to 9 times in a shuffled batch of ~200, plus
    /// near-copies that must not be merged (one bit of P1, r or the plane; -0.0).
    fn batch() -> (Vec<Query>, Vec<u64>) {
        let mut g = Rng(11);
        let mut base: Vec<Query> = (0..40)
            .map(|_| {
                let a = DVec3::new(g.f(), 0.5, 0.5) + (g.v() - 0.5) * 0.1;
                let s = Segment::new(a, a + (g.v() - 0.5) * 0.5);
                Query::with_plane(s, 0.03 + 0.05 * g.f(), s.point_at(s.length() * g.f()))
            })
            .collect();
        let q0 = base[0];
        let mut bump = q0;
        bump.seg.p1.x = f64::from_bits(q0.seg.p1.x.to_bits() + 1);
        base.push(bump);
        let mut wider = q0;
        wider.r = f64::from_bits(q0.r.to_bits() + 1);
        base.push(wider);
        let mut plane = q0;
        plane.plane.y = f64::from_bits(q0.plane.y.to_bits() + 1);
        base.push(plane);
        let zero = Query::with_plane(
            Segment::new(DVec3::new(0.0, 0.5, 0.5), DVec3::new(1.0, 0.5, 0.5)),
            0.05,
            DVec3::new(0.0, 0.5, 0.5),
        );
        let mut neg = zero;
        neg.plane.x = -0.0;
        base.push(zero);
        base.push(neg);
        let mut out = Vec::new();
        let mut ks = Vec::new();
        for _ in 0..200 {
            let i = (g.f() * base.len() as f64) as usize;
            out.push(base[i]);
            // Two k values per query: the same cylinder with another k is another query.
            ks.push(if g.f() < 0.5 { 5 } else { 40 });
        }
        (out, ks)
    }

    fn distinct(q: &[Query], k: &[u64]) -> Vec<(Query, u64)> {
        let mut seen = std::collections::HashSet::new();
        q.iter()
            .zip(k)
            .filter(|(q, k)| seen.insert(key(q, **k)))
            .map(|(q, k)| (*q, *k))
            .collect()
    }

    #[test]
    fn answers_equal_the_inner_engines_and_each_distinct_query_is_asked_once() {
        let direct = cpu();
        let seen = Arc::new(Mutex::new(Vec::new()));
        let d = Dedup::new(Box::new(Recording {
            cpu: cpu(),
            seen: seen.clone(),
        }));
        let (q, k) = batch();
        let zeros = vec![0; q.len()];
        for want in [Want::COUNT, Want::SUMS, Want::SIDES, Want::ALL] {
            assert_eq!(d.stats(&q, want).unwrap(), direct.stats(&q, want).unwrap());
        }
        assert_eq!(d.nearest(&q, &k).unwrap(), direct.nearest(&q, &k).unwrap());
        assert_eq!(d.coverage(&q).unwrap(), direct.coverage(&q).unwrap());
        assert_eq!(d.members(&q).unwrap(), direct.members(&q).unwrap());
        let seen = seen.lock().unwrap();
        assert_eq!(seen.len(), 7);
        let once = distinct(&q, &zeros);
        assert!(once.len() < q.len() / 3, "{} distinct", once.len());
        for (b, batch) in seen.iter().enumerate() {
            let want = if b == 4 {
                distinct(&q, &k)
            } else {
                once.clone()
            };
            // Same queries, bit for bit, in first-occurrence order.
            let bits = |v: &[(Query, u64)]| v.iter().map(|(q, k)| key(q, *k)).collect::<Vec<_>>();
            assert_eq!(bits(batch), bits(&want), "batch {b}");
        }
        assert_eq!(d.asked(), 7 * q.len() as u64);
        assert_eq!(
            d.counters().queries,
            seen.iter().map(|b| b.len() as u64).sum::<u64>()
        );
    }

    #[test]
    fn a_batch_without_copies_goes_through_whole_and_errors_name_the_batch_index() {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let d = Dedup::new(Box::new(Recording {
            cpu: cpu(),
            seen: seen.clone(),
        }));
        let (q, _) = batch();
        let once: Vec<Query> = distinct(&q, &vec![0; q.len()])
            .into_iter()
            .map(|x| x.0)
            .collect();
        d.stats(&once, Want::COUNT).unwrap();
        assert_eq!(seen.lock().unwrap()[0].len(), once.len());
        assert!(d.stats(&[], Want::COUNT).unwrap().is_empty());
        match d.nearest(&q, &[1, 2]) {
            Err(EngineError::BadQuery { index, .. }) => assert_eq!(index, 2),
            other => panic!("{other:?}"),
        }
        let g = Groups::of(&[q0(), q0(), q1(), q1(), q0()], None).unwrap();
        assert_eq!(g.first, vec![0, 2]);
        assert_eq!(g.of, vec![0, 0, 1, 1, 0]);
        match g.error(EngineError::BadQuery {
            index: 1,
            why: String::new(),
        }) {
            EngineError::BadQuery { index, .. } => assert_eq!(index, 2),
            other => panic!("{other:?}"),
        }
        // Near-copies are other queries: one bit of P1, r or the plane, or -0.0.
        let a = q0();
        let mut near = vec![a; 5];
        near[1].seg.p1.x = f64::from_bits(a.seg.p1.x.to_bits() + 1);
        near[2].r = f64::from_bits(a.r.to_bits() + 1);
        near[3].plane.y = f64::from_bits(a.plane.y.to_bits() + 1);
        near[4].seg.p1.x = -0.0;
        assert!(Groups::of(&near, None).is_none());
        assert!(Groups::of(&[a, a], Some(&[1, 2])).is_none());
        assert!(Groups::of(&[a, a], Some(&[2, 2])).is_some());
    }

    fn q0() -> Query {
        Query::new(Segment::new(DVec3::ZERO, DVec3::X), 0.1)
    }

    fn q1() -> Query {
        Query::new(Segment::new(DVec3::ZERO, DVec3::Y), 0.1)
    }
}
