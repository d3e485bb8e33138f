//! The GPU engine: wgpu + WGSL kernels answering the same batches as
//! [`CpuEngine`](super::cpu::CpuEngine), within the tolerance of SPEC 2.
//!
//! The grid's sorted centers go to the device once, as f32 coordinates relative to the
//! origin of their block of a few cells (computed in f64). A batch becomes work items
//! (`items.rs`): a query and a chunk of at most [`CHUNK`] points of one block row, with
//! the f64 geometry done on the host; items sharing a chunk run side by side. Each kernel
//! (`stats.rs`, `nearest.rs`, `coverage.rs`, one `shaders/*.wgsl` each) gives every item
//! its own output slot or uses integer atomics; the host reduces the slots per query in
//! build order, so results repeat exactly. Kernel inputs are textures: on lavapipe a
//! texel fetch is a SIMD gather, a storage-buffer load a scalar loop over the lanes.
//!
//! What keeps the device within its limits:
//! - no invocation loops over more than `CHUNK` points (lavapipe stops an invocation after
//!   65,535 iterations);
//! - the point store is split into parts no larger than the binding limit (and the
//!   texture size limit), and no item crosses a part;
//! - a batch runs in sub-batches of at most `max_queries` queries, each in slices of at
//!   most `max_items` items, so every per-batch buffer stays under the binding limit;
//!   dispatches are tiled in 2D beyond `max_workgroups_x` workgroups;
//! - every wgpu call runs inside error scopes, so errors come back as `EngineError::Gpu`.

mod coverage;
mod device;
mod items;
mod nearest;
mod stats;

pub use items::CHUNK;

use super::{Counters, Coverage, CylStats, Engine, EngineError, NearestSum, Query, Want};
use crate::geom::p64;
use crate::index::Grid;
use device::{Context, Reusable, Table};
use glam::DVec3;
use items::{Item, Layout, Slice, Work};
use nearest::Plan;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Size limits of the engine. The defaults suit every adapter; tests lower them to cover
/// the splitting paths with small data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Largest buffer binding and point-store part in bytes (16 per point); `None`: the
    /// device's `max_storage_buffer_binding_size`. Never above the device's limit.
    pub max_binding_bytes: Option<u64>,
    /// Most work items per dispatch.
    pub max_items: usize,
    /// Most workgroups along x before a dispatch is tiled in 2D (65,535 in WebGPU).
    pub max_workgroups_x: u32,
    /// Most queries per sub-batch (bounds the per-query buffers).
    pub max_queries: usize,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            max_binding_bytes: None,
            max_items: 1 << 20,
            max_workgroups_x: 65_535,
            max_queries: 1 << 14,
        }
    }
}

/// One piece of the sorted points on the device, from sorted index `base` on: a table
/// texture (`device::Table`) of the bits of f32 x, y, z (and an unused w).
pub(crate) struct Part {
    view: wgpu::TextureView,
    base: usize,
}

/// One slice of work for a kernel: its items, their order by chunk and groups, and the
/// point store's parts its dispatches read; dispatches are tiled at `max_x` workgroups.
pub(crate) struct Job<'a> {
    parts: &'a [Part],
    items: &'a [Item],
    slice: &'a Slice,
    max_x: u32,
}

/// Per-batch buffers, reused across batches.
pub(crate) struct Scratch {
    params: wgpu::Buffer,
    items: Table,
    order: Table,
    groups: Table,
    out: Reusable,
    staging: Reusable,
    /// Histogram (nearest) or bitmask (coverage).
    aux: Reusable,
    aux_staging: Reusable,
    cut: Reusable,
}

impl Scratch {
    /// Uploads the slice of `job` and submits `pipeline` over it, one dispatch per part
    /// of the point store. Bindings: params, points, items, order, groups, then `outputs`
    /// (buffer, bytes bound).
    fn submit(
        &mut self,
        ctx: &Context,
        pipeline: &wgpu::ComputePipeline,
        job: &Job<'_>,
        mode: u32,
        outputs: &[(&wgpu::Buffer, u64)],
    ) {
        let sl = job.slice;
        let items = self.items.write(ctx, bytemuck::cast_slice(job.items));
        // Four order entries per texel.
        let mut order: Vec<u32> = sl.order.clone();
        order.resize(order.len().next_multiple_of(4), 0);
        let order = self.order.write(ctx, bytemuck::cast_slice(&order));
        let groups = self.groups.write(ctx, bytemuck::cast_slice(&sl.groups));
        for d in &sl.dispatches {
            let part = &job.parts[d.part];
            let params = device::Params {
                n_groups: d.groups.len() as u32,
                part_base: part.base as u32,
                mode,
                group_base: d.groups.start as u32,
            };
            // Written before this dispatch's submit, after the previous one's: each
            // dispatch sees its own parameters.
            ctx.queue
                .write_buffer(&self.params, 0, bytemuck::bytes_of(&params));
            let mut res = vec![
                self.params.as_entire_binding(),
                wgpu::BindingResource::TextureView(&part.view),
                wgpu::BindingResource::TextureView(&items),
                wgpu::BindingResource::TextureView(&order),
                wgpu::BindingResource::TextureView(&groups),
            ];
            res.extend(outputs.iter().map(|&(b, n)| device::head(b, n)));
            let bind = ctx.bind(pipeline, &res);
            let encoder = device::encode(ctx, pipeline, &bind, d.groups.len(), job.max_x);
            ctx.queue.submit([encoder.finish()]);
        }
    }
}

struct Kernels {
    stats: stats::Stats,
    nearest: nearest::Nearest,
    coverage: coverage::Coverage,
}

/// The layouts, textures and loaders every kernel shares (`shaders/common.wgsl`).
pub const COMMON_WGSL: &str = include_str!("../../../shaders/common.wgsl");

/// A kernel's full source: the shared prelude, then the kernel (WGSL has no include).
pub fn kernel_source(kernel: &str) -> String {
    format!("{COMMON_WGSL}\n{kernel}")
}

pub struct GpuEngine {
    grid: Arc<Grid>,
    ctx: Context,
    kernels: Kernels,
    parts: Vec<Part>,
    /// Points per part (the last may hold fewer) and cells per block.
    layout: Layout,
    max_items: usize,
    max_x: u32,
    max_queries: usize,
    /// One batch at a time: the scratch buffers and the error scopes are per batch.
    scratch: Mutex<Scratch>,
    uploads: AtomicU64,
    batches: AtomicU64,
    queries: AtomicU64,
    /// Nearest queries answered by the host's exact fallback (see `nearest::exact`).
    fallbacks: AtomicU64,
}

impl GpuEngine {
    /// Opens the adapter chosen by `WGPU_ADAPTER_NAME` / `WGPU_BACKEND` (or wgpu's default)
    /// and uploads the grid.
    pub fn new(grid: Arc<Grid>) -> Result<Self, EngineError> {
        Self::with_options(grid, GpuOptions::default())
    }

    pub fn with_options(grid: Arc<Grid>, opts: GpuOptions) -> Result<Self, EngineError> {
        let adapter = device::pick_adapter()?;
        let ctx = Context::new(&adapter)?;
        let binding = opts
            .max_binding_bytes
            .unwrap_or(u64::MAX)
            .min(ctx.limits.max_storage_buffer_binding_size)
            .min(ctx.limits.max_buffer_size);
        let point_bytes = std::mem::size_of::<[f32; 4]>() as u64;
        let part_len = ((binding / point_bytes) as usize)
            .min(device::ROW * ctx.limits.max_texture_dimension_2d as usize)
            .max(1);
        let slot_bytes = std::mem::size_of::<Item>().max(std::mem::size_of::<nearest::Below>());
        // Items take 3 texels of a table texture.
        let table_texels = device::ROW * ctx.limits.max_texture_dimension_2d as usize;
        let max_items = opts
            .max_items
            .min(binding as usize / slot_bytes)
            .min(table_texels / 3)
            .max(1);
        let kernels = ctx.scoped("compiling the kernels", || Kernels {
            stats: stats::Stats::new(&ctx),
            nearest: nearest::Nearest::new(&ctx),
            coverage: coverage::Coverage::new(&ctx),
        })?;
        let scratch = ctx.scoped("allocating buffers", || {
            let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
            let read = wgpu::BufferUsages::MAP_READ;
            Scratch {
                params: ctx.buffer(
                    "params",
                    std::mem::size_of::<device::Params>() as u64,
                    wgpu::BufferUsages::UNIFORM,
                ),
                items: Table::new("items"),
                order: Table::new("order"),
                groups: Table::new("groups"),
                out: Reusable::new("out", storage),
                staging: Reusable::new("staging", read),
                aux: Reusable::new("aux", storage),
                aux_staging: Reusable::new("aux staging", read),
                cut: Reusable::new("cut", wgpu::BufferUsages::STORAGE),
            }
        })?;
        let engine = GpuEngine {
            parts: Vec::new(),
            layout: Layout::for_grid(&grid, part_len),
            grid,
            ctx,
            kernels,
            max_items,
            max_x: opts.max_workgroups_x.max(1),
            // The nearest histograms take 256 bytes per query of a sub-batch.
            max_queries: opts
                .max_queries
                .min(binding as usize / (nearest::NBINS * 4))
                .clamp(1, items::MAX_QUERY_SLOTS),
            scratch: Mutex::new(scratch),
            uploads: AtomicU64::new(0),
            batches: AtomicU64::new(0),
            queries: AtomicU64::new(0),
            fallbacks: AtomicU64::new(0),
        };
        engine.upload()
    }

    /// Sends the sorted centers to the device, relative to their blocks' origins.
    fn upload(mut self) -> Result<Self, EngineError> {
        let g = &*self.grid;
        let layout = self.layout;
        let (dx, dy) = (g.dims[0], g.dims[1]);
        let rel: Vec<[f32; 4]> = g
            .points
            .par_iter()
            .map(|p| {
                let p = p64(*p);
                // Same function the grid sorted with, so this is the point's own cell.
                let c = g.cell_of(p);
                let o = layout.block_origin(g, c % dx, (c / dx) % dy, c / (dx * dy));
                let r = p - o;
                [r.x as f32, r.y as f32, r.z as f32, 0.0]
            })
            .collect();
        let ctx = &self.ctx;
        let part_len = self.layout.part_len;
        self.parts = ctx.scoped("uploading the Gaussians", || {
            rel.chunks(part_len)
                .enumerate()
                .map(|(i, chunk)| {
                    let (texture, view) =
                        device::table_texture(ctx, "points", device::Table::rows(chunk.len()));
                    device::write_texels(ctx, &texture, bytemuck::cast_slice(chunk));
                    Part {
                        view,
                        base: i * part_len,
                    }
                })
                .collect()
        })?;
        self.ctx.queue.submit([]);
        self.uploads.fetch_add(1, Ordering::Relaxed);
        Ok(self)
    }

    /// Nearest queries whose two device passes disagreed and that the host answered
    /// alone; 0 unless the device is not deterministic.
    pub fn nearest_fallbacks(&self) -> u64 {
        self.fallbacks.load(Ordering::Relaxed)
    }

    /// How the point buffer is split: (parts, points per part).
    pub fn parts(&self) -> (usize, usize) {
        (self.parts.len(), self.layout.part_len)
    }

    fn count_batch(&self, n: usize) {
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.queries.fetch_add(n as u64, Ordering::Relaxed);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Scratch> {
        self.scratch.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The sub-batches of a batch of `n` queries.
    fn sub_batches(&self, n: usize) -> impl Iterator<Item = std::ops::Range<usize>> + '_ {
        (0..n)
            .step_by(self.max_queries)
            .map(move |a| a..(a + self.max_queries).min(n))
    }

    fn job<'a>(&'a self, work: &'a Work, slice: &'a Slice) -> Job<'a> {
        Job {
            parts: &self.parts,
            items: &work.items[slice.items.clone()],
            slice,
            max_x: self.max_x,
        }
    }

    /// The work items of a sub-batch, grouped and cut into dispatches.
    fn work(&self, queries: &[Query]) -> Work {
        let all = items::build(&self.grid, queries, self.layout);
        items::group(all, self.layout.part_len, self.max_items)
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

    fn stats(&self, queries: &[Query], want: Want) -> Result<Vec<CylStats>, EngineError> {
        self.count_batch(queries.len());
        let mut out = vec![CylStats::default(); queries.len()];
        let mut s = self.lock();
        for range in self.sub_batches(queries.len()) {
            let work = self.work(&queries[range.clone()]);
            let acc = &mut out[range];
            for sl in &work.slices {
                let items = &work.items[sl.items.clone()];
                self.ctx.scoped("stats kernel", || {
                    let job = self.job(&work, sl);
                    self.kernels.stats.run(&self.ctx, &mut s, &job, |partials| {
                        for (it, p) in items.iter().zip(partials) {
                            let a = &mut acc[it.query()];
                            a.count += p.count as u64;
                            a.side_pos += p.side_pos as u64;
                            a.sum_d2 += p.sum_d2 as f64;
                            a.sum_offset += p64(p.off);
                        }
                    })
                })??;
            }
        }
        for a in &mut out {
            if !want.sums {
                a.sum_d2 = 0.0;
                a.sum_offset = DVec3::ZERO;
            }
            if !want.sides {
                a.side_pos = 0;
            }
        }
        Ok(out)
    }

    fn nearest(&self, queries: &[Query], k: &[u64]) -> Result<Vec<NearestSum>, EngineError> {
        if k.len() != queries.len() {
            return Err(EngineError::BadQuery {
                index: k.len().min(queries.len()),
                why: format!("{} queries but {} k values", queries.len(), k.len()),
            });
        }
        self.count_batch(queries.len());
        let mut out = vec![NearestSum::default(); queries.len()];
        let mut s = self.lock();
        for range in self.sub_batches(queries.len()) {
            let qs = &queries[range.clone()];
            let work = self.work(qs);
            let hist_bytes = (qs.len() * nearest::NBINS * 4) as u64;
            let cut_bytes = (qs.len() * 4) as u64;
            // Pass 0: per-query histograms of the members' distances.
            let hist: Vec<u32> = self.ctx.scoped("nearest kernel (histogram)", || {
                let hist = s.aux.get(&self.ctx, hist_bytes).clone();
                let mut clear = self.ctx.encoder();
                clear.clear_buffer(&hist, 0, Some(hist_bytes));
                self.ctx.queue.submit([clear.finish()]);
                for sl in &work.slices {
                    let job = self.job(&work, sl);
                    self.kernels
                        .nearest
                        .histogram(&self.ctx, &mut s, &job, &hist, hist_bytes);
                }
                let staging = s.aux_staging.get(&self.ctx, hist_bytes).clone();
                self.ctx
                    .read_back(self.ctx.encoder(), &hist, &staging, hist_bytes, |b| {
                        bytemuck::pod_collect_to_vec(b)
                    })
            })??;
            let ks = &k[range.clone()];
            let plans: Vec<Plan> = hist
                .chunks(nearest::NBINS)
                .zip(ks)
                .map(|(h, &k)| Plan::new(h, k))
                .collect();
            let cuts: Vec<u32> = plans.iter().map(|p| p.cut).collect();
            // Pass 1: sums below each query's cut bin; the members in it, flagged.
            let acc = &mut out[range];
            let mut below = vec![0u64; qs.len()];
            let mut flagged: Vec<(u32, u32)> = Vec::new();
            self.ctx.scoped("nearest kernel (sums)", || {
                let hist = s.aux.get(&self.ctx, hist_bytes).clone();
                let cut = s.cut.get(&self.ctx, cut_bytes).clone();
                self.ctx
                    .queue
                    .write_buffer(&cut, 0, bytemuck::cast_slice(&cuts));
                for sl in &work.slices {
                    let items = &work.items[sl.items.clone()];
                    let job = self.job(&work, sl);
                    self.kernels.nearest.below(
                        &self.ctx,
                        &mut s,
                        &job,
                        (&hist, hist_bytes),
                        (&cut, cut_bytes),
                        |res| {
                            for (it, b) in items.iter().zip(res) {
                                let q = it.query();
                                if plans[q].k == 0 {
                                    continue;
                                }
                                below[q] += b.count as u64;
                                acc[q].sum_d2 += b.sum_d2 as f64;
                                acc[q].sum_offset += p64(b.off);
                                // Bit j: point `start + j` of the item's chunk.
                                for (w, &bits) in b.in_cut.iter().enumerate() {
                                    let mut bits = bits;
                                    while bits != 0 {
                                        let j = bits.trailing_zeros() + 32 * w as u32;
                                        bits &= bits - 1;
                                        flagged.push((q as u32, it.start + j));
                                    }
                                }
                            }
                        },
                    )?;
                }
                Ok::<(), EngineError>(())
            })??;
            // The cut bins, ranked exactly on the host.
            flagged.sort_unstable();
            let mut spans = vec![0..0; qs.len()];
            let mut a = 0;
            while a < flagged.len() {
                let q = flagged[a].0 as usize;
                let mut b = a;
                while b < flagged.len() && flagged[b].0 as usize == q {
                    b += 1;
                }
                spans[q] = a..b;
                a = b;
            }
            let grid = &*self.grid;
            acc.par_iter_mut()
                .enumerate()
                .with_min_len(16)
                .for_each(|(q, r)| {
                    let plan = &plans[q];
                    if plan.k == 0 {
                        return;
                    }
                    let span = spans[q].clone();
                    let consistent = below[q] == plan.below && span.len() as u64 == plan.in_cut;
                    if !consistent {
                        self.fallbacks.fetch_add(1, Ordering::Relaxed);
                        *r = nearest::exact(grid, &qs[q], plan.k);
                        return;
                    }
                    r.k = plan.k;
                    let ids: Vec<u32> = flagged[span].iter().map(|f| f.1).collect();
                    nearest::resolve_cut(grid, &qs[q], plan, &ids, r);
                });
        }
        Ok(out)
    }

    /// Documented fallback: answered on the host over the same grid by the CPU engine's
    /// code (no kernel writes per-point lists; reading them back is O(members) anyway).
    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<super::Member>>, EngineError> {
        self.count_batch(queries.len());
        Ok(super::cpu::members_of(&self.grid, queries))
    }

    fn coverage(&self, queries: &[Query]) -> Result<Coverage, EngineError> {
        self.count_batch(queries.len());
        let n = self.grid.len();
        if n == 0 {
            return Ok(Coverage { mask: Vec::new() });
        }
        let mask_bytes = (n.div_ceil(32) * 4) as u64;
        if mask_bytes > self.ctx.limits.max_storage_buffer_binding_size {
            return Err(EngineError::Gpu(format!(
                "coverage of {n} points needs a {mask_bytes}-byte mask, above the device's binding limit"
            )));
        }
        let mut s = self.lock();
        let words: Vec<u32> = self.ctx.scoped("coverage kernel", || {
            let mask = s.aux.get(&self.ctx, mask_bytes).clone();
            let mut clear = self.ctx.encoder();
            clear.clear_buffer(&mask, 0, Some(mask_bytes));
            self.ctx.queue.submit([clear.finish()]);
            for range in self.sub_batches(queries.len()) {
                let work = self.work(&queries[range]);
                for sl in &work.slices {
                    let job = self.job(&work, sl);
                    self.kernels
                        .coverage
                        .run(&self.ctx, &mut s, &job, &mask, mask_bytes);
                }
            }
            let staging = s.aux_staging.get(&self.ctx, mask_bytes).clone();
            self.ctx
                .read_back(self.ctx.encoder(), &mask, &staging, mask_bytes, |b| {
                    bytemuck::pod_collect_to_vec(b)
                })
        })??;
        let mask = words
            .chunks(2)
            .map(|w| w[0] as u64 | (w.get(1).copied().unwrap_or(0) as u64) << 32)
            .collect();
        Ok(Coverage { mask })
    }

    fn counters(&self) -> Counters {
        Counters {
            uploads: self.uploads.load(Ordering::Relaxed),
            batches: self.batches.load(Ordering::Relaxed),
            queries: self.queries.load(Ordering::Relaxed),
        }
    }
}
