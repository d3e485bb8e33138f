//! The answers of device batches: [`GpuEngine::run_with`] sends a batch in sub-batches that
//! fit the buffers, and each kind of batch turns a sub-batch's [`Output`] into its
//! queries' answers (the flagged points decided on the host in f64, the queries the device
//! left to the host answered there), one query at a time in parallel ([`per_query`]).

use super::batch::{self, Kind, Output};
use super::query::stats_of;
use super::resources::{self, Buffers};
use super::{host, layout, GpuEngine};
use crate::engine::{Coverage, CylStats, EngineError, Member, NearestSum, Query, Want};
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::Ordering;

/// `answer(i, flags of query i, &mut out[i])` for every query of a sub-batch, in parallel
/// (`min_len` queries a task): `out` is the sub-batch's slice of the answers, `o` its
/// output.
pub(super) fn per_query<T: Send>(
    out: &mut [T],
    o: &Output,
    min_len: usize,
    answer: impl Fn(usize, &[(u32, u32)], &mut T) + Sync + Send,
) {
    per_query_in(out, o, &host::spans(&o.flags, out.len()), min_len, answer)
}

/// [`per_query`] with the sub-batch's flag spans already found ([`host::spans`]).
fn per_query_in<T: Send>(
    out: &mut [T],
    o: &Output,
    spans: &[std::ops::Range<usize>],
    min_len: usize,
    answer: impl Fn(usize, &[(u32, u32)], &mut T) + Sync + Send,
) {
    out.par_iter_mut()
        .enumerate()
        .with_min_len(min_len)
        .for_each(|(i, a)| answer(i, &o.flags[spans[i].clone()], a));
}

/// [`GpuEngine::members_batch_parts`]' receiver: `(first query, its part's lists)`; the
/// lists it leaves in place lend their memory to the next part's.
pub(super) type Give<'a> = dyn FnMut(usize, &mut [Vec<Member>]) -> Result<(), EngineError> + 'a;

impl GpuEngine {
    /// Counts a query the device left to the host, which the host answers from its own
    /// walk (`host_fallbacks`, `host_lists`).
    pub(super) fn to_host(&self) {
        self.fallbacks.fetch_add(1, Ordering::Relaxed);
        self.host_lists.fetch_add(1, Ordering::Relaxed);
    }

    /// Runs `kind` over `queries` in sub-batches, calling `each(first query, output)` for
    /// every sub-batch in order; a sub-batch too large for the buffers is split, and a
    /// single query that still does not fit is marked for the host.
    pub(super) fn run(
        &self,
        b: &mut Buffers,
        kind: Kind,
        queries: &[Query],
        ks: &[u64],
        each: &mut dyn FnMut(usize, Output) -> Result<(), EngineError>,
    ) -> Result<(), EngineError> {
        self.run_with(b, kind, queries, ks, &[], each)
    }

    /// [`Self::run`] with the fit batch's per-query frames (`fit`, one per query).
    pub(super) fn run_with(
        &self,
        b: &mut Buffers,
        kind: Kind,
        queries: &[Query],
        ks: &[u64],
        fit: &[layout::FitQuery],
        each: &mut dyn FnMut(usize, Output) -> Result<(), EngineError>,
    ) -> Result<(), EngineError> {
        let t = std::time::Instant::now();
        // The queries' upload is parallel work: the workers, asleep since the caller's
        // last parallel loop, wake while the batch is sized.
        super::device::wake_workers();
        let mut waited = 0.0;
        let mut todo: Vec<std::ops::Range<usize>> = (0..queries.len())
            .step_by(self.opts.max_queries)
            .map(|a| a..(a + self.opts.max_queries).min(queries.len()))
            .rev()
            .collect();
        while let Some(r) = todo.pop() {
            let ks = if ks.is_empty() { ks } else { &ks[r.clone()] };
            let fit = if fit.is_empty() { fit } else { &fit[r.clone()] };
            let ctx = &self.ctx;
            let out = ctx.scoped("running a batch", || {
                batch::submit(
                    ctx,
                    &self.kernels,
                    &self.stages,
                    &self.statics,
                    &self.opts,
                    &self.grid,
                    b,
                    kind,
                    &queries[r.clone()],
                    ks,
                    fit,
                )
            })??;
            match out {
                batch::Attempt::Done(o, w) => {
                    waited += w;
                    self.touched(o.items_run, o.points_read);
                    each(r.start, o)?;
                }
                batch::Attempt::TooLarge(w, items, points) => {
                    waited += w;
                    self.touched(items, points);
                    if r.len() > 1 {
                        let mid = r.start + r.len() / 2;
                        todo.push(mid..r.end);
                        todo.push(r.start..mid);
                    } else {
                        each(r.start, Output::host_only(1))?;
                    }
                }
            }
        }
        // The caller's own work inside `each` (a part's receiver) is not the engine's.
        let callers = self.callers_ns.swap(0, Ordering::Relaxed) as f64 * 1e-9;
        self.clock
            .add(t.elapsed().as_secs_f64() - waited - callers, waited);
        Ok(())
    }

    /// The stats of every query (fields not in `want` zeroed) and, with `cover`, the
    /// coverage mask of the batch, from one device batch.
    pub(super) fn stats_batch(
        &self,
        b: &mut Buffers,
        queries: &[Query],
        want: Want,
        cover: bool,
    ) -> Result<(Vec<CylStats>, Option<Coverage>), EngineError> {
        let n_points = self.grid.len();
        let ctx = &self.ctx;
        let asked = cover;
        let cover = cover && n_points > 0;
        if cover {
            ctx.scoped("clearing the coverage mask", || {
                resources::clear_mask(ctx, b, &self.opts, n_points)
            })??;
        }
        let mut out = vec![CylStats::default(); queries.len()];
        let grid = &*self.grid;
        // Members the device left to the host (flagged points, host-answered queries).
        let mut extra: Vec<u32> = Vec::new();
        let kind = Kind::Stats {
            sides: want.sides,
            cover,
        };
        self.run(b, kind, queries, &[], &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            per_query(&mut out[first..first + n], &o, 64, |i, flags, s| {
                let r = &o.results[i];
                if r.status & layout::STATUS_HOST != 0 {
                    self.to_host();
                    *s = host::stats(grid, &qs[i]);
                    return;
                }
                *s = stats_of(r, grid.cell);
                for f in flags {
                    host::add_member(grid, &qs[i], f.1, s);
                }
            });
            if cover {
                for (i, r) in o.results.iter().enumerate() {
                    if r.status & layout::STATUS_HOST != 0 {
                        host::for_each_member(grid, &qs[i], |j| extra.push(j as u32));
                    }
                }
                for &(q, p) in &o.flags {
                    if host::is_member(grid, &qs[q as usize], p) {
                        extra.push(p);
                    }
                }
            }
            Ok(())
        })?;
        for a in &mut out {
            if !want.sums {
                a.sum_d2 = 0.0;
                a.sum_offset = DVec3::ZERO;
            }
            if !want.sides {
                a.side_pos = 0;
            }
        }
        if !cover {
            return Ok((out, asked.then(Coverage::default)));
        }
        let t = std::time::Instant::now();
        let (words, waited) = ctx.scoped("reading the coverage mask", || {
            resources::read_mask(ctx, b, n_points)
        })??;
        let mut mask: Vec<u64> = words
            .chunks(2)
            .map(|w| w[0] as u64 | (w.get(1).copied().unwrap_or(0) as u64) << 32)
            .collect();
        for p in extra {
            mask[p as usize / 64] |= 1u64 << (p % 64);
        }
        self.clock.add(t.elapsed().as_secs_f64() - waited, waited);
        Ok((out, Some(Coverage { mask })))
    }

    /// For query `i`, sums over its `k[i]` members nearest to the line, and its count.
    pub(super) fn nearest_batch(
        &self,
        b: &mut Buffers,
        queries: &[Query],
        k: &[u64],
    ) -> Result<(Vec<NearestSum>, Vec<u64>), EngineError> {
        let mut out = vec![(NearestSum::default(), 0u64); queries.len()];
        let grid = &*self.grid;
        self.run(b, Kind::Nearest, queries, k, &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            // One plan a query (none for a sub-batch the host answers).
            let plans = super::device::pods::<layout::Plan>(&o.back);
            per_query(&mut out[first..first + n], &o, 64, |i, flags, s| {
                let (q, k) = (&qs[i], k[first + i]);
                let plan = plans.get(i);
                match host::nearest(grid, q, k, &o.results[i], plan, flags) {
                    Some(x) => *s = x,
                    None => {
                        self.to_host();
                        *s = host::exact_nearest(grid, q, k);
                    }
                }
            });
            Ok(())
        })?;
        Ok(out.into_iter().unzip())
    }

    /// Every query's members (see [`crate::engine::Engine::members`]) from device batches;
    /// a query the device leaves to the host (walk too long, too many members, a
    /// miscount) gets the CPU engine's list.
    pub(super) fn members_batch(
        &self,
        b: &mut Buffers,
        queries: &[Query],
    ) -> Result<Vec<Vec<Member>>, EngineError> {
        let mut out: Vec<Vec<Member>> = Vec::with_capacity(queries.len());
        self.members_batch_parts(b, queries, usize::MAX, &mut |_, lists| {
            out.extend(lists.iter_mut().map(std::mem::take));
            Ok(())
        })?;
        Ok(out)
    }

    /// [`Self::members_batch`] handed to `give(first query, lists)` in order, at most
    /// `part` queries at a time: each part's lists are made from the sub-batch's readback
    /// as they are handed out, in the memory of the part before (the lists `give` leaves
    /// in place), so that one part's lists are all the memory they take, and it stays
    /// in cache.
    pub(super) fn members_batch_parts(
        &self,
        b: &mut Buffers,
        queries: &[Query],
        part: usize,
        give: &mut Give<'_>,
    ) -> Result<(), EngineError> {
        let grid = &*self.grid;
        let part = part.max(1);
        // Each part's lists, made where the part before left its lists.
        let mut lists_of_part: Vec<Vec<Member>> = Vec::new();
        self.run(b, Kind::Members, queries, &[], &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            // Query after query, the device's sure members (as far as the list's capacity),
            // read in place: a copy was a fresh 4 bytes a member each sub-batch, and the
            // first sub-batch's fresh memory is page faults (see docs/benchmarks.md).
            // Records (`kernels/records.rs`) where the batch sent them, else sorted
            // indices: one entry a member either way.
            let records = o.records;
            self.record_batches
                .fetch_add(records as u64, Ordering::Relaxed);
            let (members, recs) = if records {
                (Default::default(), super::device::pods::<[u32; 4]>(&o.back))
            } else {
                (super::device::pods::<u32>(&o.back), Default::default())
            };
            let listed_len = if records { recs.len() } else { members.len() };
            let mut at = 0usize;
            let lists: Vec<std::ops::Range<usize>> = o
                .results
                .iter()
                .map(|r| {
                    let c = if r.status & layout::STATUS_HOST == 0 {
                        r.count as usize
                    } else {
                        0
                    };
                    at += c;
                    at - c..at
                })
                .collect();
            let spans = host::spans(&o.flags, n);
            let mut p = 0;
            while p < n {
                let len = part.min(n - p);
                if lists_of_part.len() < len {
                    lists_of_part.resize_with(len, Vec::new);
                }
                let out = &mut lists_of_part[..len];
                // Each list's room: taken by the thread that fills it (where the list
                // before in this place had less).
                per_query_in(out, &o, &spans[p..p + len], 8, |k, flags, m| {
                    let i = p + k;
                    m.clear();
                    m.reserve(lists[i].len() + spans[i].len());
                    let q = &qs[i];
                    let device = o.results[i].status & layout::STATUS_HOST == 0
                        && !o.bad
                        && lists[i].end <= listed_len
                        && q.r.is_finite()
                        && q.r >= 0.0;
                    let listed = device
                        && if records {
                            let got = (lists[i].len() <= layout::RECORD_MAX as usize)
                                .then(|| {
                                    host::members_of_records(
                                        grid,
                                        q,
                                        &recs[lists[i].clone()],
                                        flags,
                                        m,
                                    )
                                })
                                .flatten();
                            if got == Some(true) {
                                self.sorted_on_host.fetch_add(1, Ordering::Relaxed);
                            }
                            got.is_some()
                        } else {
                            host::members(grid, q, &members[lists[i].clone()], flags, m).is_some()
                        };
                    if !listed {
                        self.to_host();
                        *m = self.cpu_members(q);
                    }
                });
                give(first + p, out)?;
                p += len;
            }
            Ok(())
        })
    }
}
