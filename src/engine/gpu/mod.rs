//! The GPU engine: wgpu + WGSL kernels answering the same batches as
//! [`CpuEngine`](super::cpu::CpuEngine), with the same counts, sides, coverage and
//! k-nearest sets, and sums to float precision.
//!
//! On the device, uploaded once: the grid's cell table (`cell_start`) and the sorted
//! centers, as f32 offsets from their own cell's corner in cell units (split into parts at
//! the binding limit). Per batch the host uploads only the queries (64 bytes each) and one
//! submit runs (`batch.rs`):
//! 1. `walk.wgsl` (count): per query, the work items its capped cylinder needs (cells it
//!    can touch, each cell cut into chunks of at most [`CHUNK`] points);
//! 2. `scan.wgsl`: exclusive prefix sum of those counts (multi-level workgroup scan);
//! 3. `args.wgsl`: the total, and the indirect dispatch size of the per-item kernels;
//! 4. `walk.wgsl` (emit): the items, contiguous per query;
//! 5. `eval.wgsl`: per item, its members' sums into its own slot (or the coverage bits, or
//!    the k-nearest histogram; `cut.wgsl` then plans the cut and `eval.wgsl` sums below it);
//!    points within the f32 error bound of a boundary are flagged instead;
//! 6. `reduce.wgsl`: per query, its items' slots summed in grid order (Kahan, no atomics).
//!
//! The host then reads back the per-query results and the flag list (one readback) and
//! decides the flagged points in f64 — the only per-point work left on the host, and
//! what makes membership exact. When the items or flags outgrow their buffers the batch is
//! rerun with larger ones (the sizes are kept for later batches).
//!
//! What keeps the device within its limits: every kernel loop is bounded (see each
//! shader); the point store is split at the binding limit and no chunk crosses a part;
//! dispatches are tiled in 2D beyond `max_workgroups_x` workgroups; every wgpu call runs
//! inside error scopes, so errors come back as `EngineError::Gpu`.

mod batch;
mod device;
mod host;
pub mod layout;

pub use device::{enumerate_adapters, skip_gpu_tests};
pub use layout::CHUNK;

use super::{
    Answers, Ask, Counters, Coverage, CylStats, Engine, EngineError, Nearest, NearestSum, Query,
    Want,
};
use crate::index::Grid;
use batch::{Buffers, Kind};
use device::Context;
use glam::DVec3;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Size limits of the engine. The defaults suit every adapter; tests lower them to cover
/// the splitting paths with small data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Largest point-store part and per-batch buffer binding in bytes (16 per point);
    /// `None`: the device's `max_storage_buffer_binding_size`. Never above the device's
    /// limit. (The cell table is bound whole and only checked against the device.)
    pub max_binding_bytes: Option<u64>,
    /// Most work items per submit; a sub-batch needing more is split.
    pub max_items: usize,
    /// Most workgroups along x before a dispatch is tiled in 2D (65,535 in WebGPU).
    pub max_workgroups_x: u32,
    /// Most queries per sub-batch (bounds the per-query buffers).
    pub max_queries: usize,
    /// Batches of at most this many queries are answered by the CPU engine's code over
    /// the same grid, on the host: a device round trip (submit, wait, read back) costs more
    /// than such a batch. 0 (the default here, so that tests exercise the kernels with
    /// any batch): never. The commands use [`SMALL_BATCH`].
    pub small_batch: usize,
}

/// The commands' [`GpuOptions::small_batch`]: the tail rounds of merge/join and crop ask
/// a few queries at a time, which the host answers in microseconds; a device round trip
/// costs a fraction of a millisecond on a real GPU (about one on lavapipe).
pub const SMALL_BATCH: usize = 16;

impl GpuOptions {
    /// The options the commands use: the defaults, with batches of at most
    /// [`SMALL_BATCH`] queries on the host (`LINEGS_GPU_SMALL_BATCH=N` sets another bound;
    /// 0 sends every batch to the device).
    pub fn for_commands() -> Self {
        let small_batch = std::env::var("LINEGS_GPU_SMALL_BATCH")
            .ok()
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(SMALL_BATCH);
        GpuOptions {
            small_batch,
            ..Default::default()
        }
    }
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            max_binding_bytes: None,
            max_items: 1 << 24,
            max_workgroups_x: 65_535,
            max_queries: 1 << 16,
            small_batch: 0,
        }
    }
}

/// The layouts and helpers every kernel shares: the prelude generated from `layout.rs`,
/// then `shaders/common.wgsl`.
pub fn common_wgsl() -> String {
    format!(
        "{}\n{}",
        layout::prelude(),
        include_str!("../../../shaders/common.wgsl")
    )
}

/// A kernel's full source: the shared prelude, then the kernel (WGSL has no include).
pub fn kernel_source(kernel: &str) -> String {
    format!("{}\n{kernel}", common_wgsl())
}

/// Seconds of host work and of waiting for the device, accumulated over the engine's life.
#[derive(Default)]
struct Clock {
    host_ns: AtomicU64,
    device_ns: AtomicU64,
}

impl Clock {
    fn add(&self, host: f64, device: f64) {
        self.host_ns
            .fetch_add((host.max(0.0) * 1e9) as u64, Ordering::Relaxed);
        self.device_ns
            .fetch_add((device.max(0.0) * 1e9) as u64, Ordering::Relaxed);
    }
}

pub struct GpuEngine {
    grid: Arc<Grid>,
    ctx: Context,
    kernels: batch::Kernels,
    statics: batch::Statics,
    opts: batch::Limits,
    /// One batch at a time: the buffers and the error scopes are per batch.
    buffers: Mutex<Buffers>,
    uploads: AtomicU64,
    batches: AtomicU64,
    queries: AtomicU64,
    /// Queries answered wholly on the host (walks too long, or k-nearest sets with a
    /// boundary member); rare by design.
    fallbacks: AtomicU64,
    clock: Clock,
    /// Answers the batches of at most `small_batch` queries, over the same grid.
    cpu: super::cpu::CpuEngine,
    small_batch: usize,
    cpu_batches: AtomicU64,
    cpu_queries: AtomicU64,
}

impl GpuEngine {
    /// Opens the adapter chosen by `WGPU_ADAPTER_NAME` / `WGPU_BACKEND` (or wgpu's default)
    /// and uploads the grid.
    pub fn new(grid: Arc<Grid>) -> Result<Self, EngineError> {
        Self::with_options(grid, GpuOptions::default())
    }

    pub fn with_options(grid: Arc<Grid>, opts: GpuOptions) -> Result<Self, EngineError> {
        let adapter = device::pick_adapter()?;
        Self::on_adapter(&adapter, grid, opts)
    }

    /// The engine on a given adapter (`select.rs` picks it).
    pub fn on_adapter(
        adapter: &wgpu::Adapter,
        grid: Arc<Grid>,
        opts: GpuOptions,
    ) -> Result<Self, EngineError> {
        let ctx = Context::new(adapter)?;
        let limits = batch::Limits::new(&ctx, &opts, grid.len());
        // The kernels compile on one thread while the grid uploads on the others.
        let (kernels, statics) = std::thread::scope(|s| {
            let kernels =
                s.spawn(|| ctx.scoped("compiling the kernels", || batch::Kernels::new(&ctx)));
            let statics = batch::Statics::upload(&ctx, &grid, &limits);
            let kernels = kernels
                .join()
                .unwrap_or_else(|p| std::panic::resume_unwind(p));
            (kernels, statics)
        });
        let (kernels, statics) = (kernels?, statics?);
        let buffers = ctx.scoped("allocating buffers", || Buffers::new(&ctx, &limits))?;
        Ok(GpuEngine {
            cpu: super::cpu::CpuEngine::new(grid.clone()),
            small_batch: opts.small_batch,
            cpu_batches: AtomicU64::new(0),
            cpu_queries: AtomicU64::new(0),
            grid,
            ctx,
            kernels,
            statics,
            opts: limits,
            buffers: Mutex::new(buffers),
            uploads: AtomicU64::new(1),
            batches: AtomicU64::new(0),
            queries: AtomicU64::new(0),
            fallbacks: AtomicU64::new(0),
            clock: Clock::default(),
        })
    }

    /// Queries answered wholly on the host; 0 on ordinary scenes.
    pub fn host_fallbacks(&self) -> u64 {
        self.fallbacks.load(Ordering::Relaxed)
    }

    /// Former name of [`Self::host_fallbacks`].
    pub fn nearest_fallbacks(&self) -> u64 {
        self.host_fallbacks()
    }

    /// How the point buffer is split: (parts, points per part).
    pub fn parts(&self) -> (usize, usize) {
        (self.statics.parts.len(), self.opts.part_len as usize)
    }

    /// (host seconds, device-wait seconds) spent answering batches so far.
    pub fn seconds(&self) -> (f64, f64) {
        (
            self.clock.host_ns.load(Ordering::Relaxed) as f64 * 1e-9,
            self.clock.device_ns.load(Ordering::Relaxed) as f64 * 1e-9,
        )
    }

    fn count_batch(&self, n: usize) {
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.queries.fetch_add(n as u64, Ordering::Relaxed);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Buffers> {
        self.buffers.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Runs `kind` over `queries` in sub-batches, calling `each(first query, output)` for
    /// every sub-batch in order; a sub-batch too large for the buffers is split, and a
    /// single query that still does not fit is marked for the host.
    fn run(
        &self,
        b: &mut Buffers,
        kind: Kind,
        queries: &[Query],
        ks: &[u64],
        each: &mut dyn FnMut(usize, batch::Output) -> Result<(), EngineError>,
    ) -> Result<(), EngineError> {
        let t = std::time::Instant::now();
        let mut waited = 0.0;
        let mut todo: Vec<std::ops::Range<usize>> = (0..queries.len())
            .step_by(self.opts.max_queries)
            .map(|a| a..(a + self.opts.max_queries).min(queries.len()))
            .rev()
            .collect();
        while let Some(r) = todo.pop() {
            let ks = if ks.is_empty() { ks } else { &ks[r.clone()] };
            let ctx = &self.ctx;
            let out = ctx.scoped("running a batch", || {
                batch::submit(
                    ctx,
                    &self.kernels,
                    &self.statics,
                    &self.opts,
                    &self.grid,
                    b,
                    kind,
                    &queries[r.clone()],
                    ks,
                )
            })??;
            match out {
                batch::Attempt::Done(o, w) => {
                    waited += w;
                    each(r.start, o)?;
                }
                batch::Attempt::TooLarge(w) => {
                    waited += w;
                    if r.len() > 1 {
                        let mid = r.start + r.len() / 2;
                        todo.push(mid..r.end);
                        todo.push(r.start..mid);
                    } else {
                        each(r.start, batch::Output::host_only(1))?;
                    }
                }
            }
        }
        self.clock.add(t.elapsed().as_secs_f64() - waited, waited);
        Ok(())
    }

    /// The stats of every query (fields not in `want` zeroed) and, with `cover`, the
    /// coverage mask of the batch, from one device batch.
    fn stats_batch(
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
                batch::clear_mask(ctx, b, &self.opts, n_points)
            })??;
        }
        let mut out = vec![CylStats::default(); queries.len()];
        let grid = &*self.grid;
        let cell = grid.cell;
        let fallbacks = &self.fallbacks;
        // Members the device left to the host (flagged points, host-answered queries).
        let mut extra: Vec<u32> = Vec::new();
        self.run(
            b,
            Kind::Stats {
                sides: want.sides,
                cover,
            },
            queries,
            &[],
            &mut |first, o| {
                let n = o.results.len();
                let qs = &queries[first..first + n];
                let spans = host::spans(&o.flags, n);
                out[first..first + n]
                    .par_iter_mut()
                    .enumerate()
                    .with_min_len(64)
                    .for_each(|(i, s)| {
                        let r = &o.results[i];
                        if r.status & layout::STATUS_HOST != 0 {
                            fallbacks.fetch_add(1, Ordering::Relaxed);
                            *s = host::stats(grid, &qs[i]);
                            return;
                        }
                        *s = batch::stats_of(r, cell);
                        for f in &o.flags[spans[i].clone()] {
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
            },
        )?;
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
            batch::read_mask(ctx, b, n_points)
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
    fn nearest_batch(
        &self,
        b: &mut Buffers,
        queries: &[Query],
        k: &[u64],
    ) -> Result<(Vec<NearestSum>, Vec<u64>), EngineError> {
        let mut out = vec![(NearestSum::default(), 0u64); queries.len()];
        let grid = &*self.grid;
        let fallbacks = &self.fallbacks;
        self.run(b, Kind::Nearest, queries, k, &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            let spans = host::spans(&o.flags, n);
            out[first..first + n]
                .par_iter_mut()
                .enumerate()
                .with_min_len(64)
                .for_each(|(i, s)| {
                    let q = &qs[i];
                    let k = k[first + i];
                    match host::nearest(
                        grid,
                        q,
                        k,
                        &o.results[i],
                        o.plans.get(i),
                        &o.flags[spans[i].clone()],
                    ) {
                        Some(x) => *s = x,
                        None => {
                            fallbacks.fetch_add(1, Ordering::Relaxed);
                            *s = host::exact_nearest(grid, q, k);
                        }
                    }
                });
            Ok(())
        })?;
        Ok(out.into_iter().unzip())
    }
}

impl Engine for GpuEngine {
    fn backend(&self) -> &'static str {
        "gpu"
    }

    fn adapter(&self) -> String {
        self.ctx.describe()
    }

    fn n_points(&self) -> usize {
        self.grid.len()
    }

    /// One device batch for the stats and the coverage together (one walk, each point
    /// evaluated once), then, for nearest sums, the k-nearest batch (whose `k` may come
    /// from the first batch's counts); a nearest-only ask gets its counts from the
    /// k-nearest batch itself.
    fn query(&self, queries: &[Query], ask: &Ask<'_>) -> Result<Answers, EngineError> {
        ask.nearest.check(queries.len())?;
        self.count_batch(queries.len());
        if !queries.is_empty() && queries.len() <= self.small_batch {
            let t = std::time::Instant::now();
            let out = self.cpu.query(queries, ask);
            self.cpu_batches.fetch_add(1, Ordering::Relaxed);
            self.cpu_queries
                .fetch_add(queries.len() as u64, Ordering::Relaxed);
            self.clock.add(t.elapsed().as_secs_f64(), 0.0);
            return out;
        }
        let mut b = self.lock();
        let stats_batch = ask.nearest == Nearest::No
            || ask.coverage
            || ask.want != Want::COUNT
            || matches!(ask.nearest, Nearest::Keep(_));
        let mut out = Answers::default();
        if stats_batch {
            let (stats, cov) = self.stats_batch(&mut b, queries, ask.want, ask.coverage)?;
            out.stats = stats;
            out.coverage = cov;
        }
        if ask.nearest != Nearest::No {
            let k: Vec<u64> = (0..queries.len())
                .map(|i| {
                    let n = out.stats.get(i).map_or(0, |s| s.count);
                    ask.nearest.k_of(i, n).unwrap_or(0)
                })
                .collect();
            let (near, counts) = self.nearest_batch(&mut b, queries, &k)?;
            if !stats_batch {
                out.stats = counts
                    .into_iter()
                    .map(|count| CylStats {
                        count,
                        ..Default::default()
                    })
                    .collect();
            }
            out.nearest = near;
        }
        Ok(out)
    }

    /// Documented fallback: answered on the host over the same grid by the CPU engine's
    /// code (no kernel writes per-point lists; reading them back is O(members) anyway).
    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<super::Member>>, EngineError> {
        self.count_batch(queries.len());
        Ok(super::cpu::members_of(&self.grid, queries))
    }

    fn counters(&self) -> Counters {
        Counters {
            uploads: self.uploads.load(Ordering::Relaxed),
            batches: self.batches.load(Ordering::Relaxed),
            queries: self.queries.load(Ordering::Relaxed),
            cpu_batches: self.cpu_batches.load(Ordering::Relaxed),
            cpu_queries: self.cpu_queries.load(Ordering::Relaxed),
        }
    }

    fn seconds(&self) -> Option<(f64, f64)> {
        Some(GpuEngine::seconds(self))
    }
}
