//! The GPU engine: wgpu + WGSL kernels answering the same batches as
//! [`CpuEngine`](super::cpu::CpuEngine), within the tolerance of SPEC 2.
//!
//! The grid's sorted centers go to the device once, as f32 coordinates relative to their
//! cell's origin (computed in f64). A batch becomes work items (`items.rs`): a query and at
//! most [`CHUNK`] points of one cell, with the f64 geometry done on the host. Each kernel
//! (`stats.rs`, `nearest.rs`, `coverage.rs`, one `shaders/*.wgsl` each) gives every item
//! its own output slot or uses integer atomics; the host reduces the slots per query in
//! item order, so results repeat exactly. What keeps the device within its limits:
//! - no invocation loops over more than `CHUNK` points (lavapipe stops an invocation after
//!   65,535 iterations);
//! - the point buffer is split into parts no larger than the storage binding limit, and no
//!   item crosses a part;
//! - a batch runs in sub-batches of at most `max_queries` queries, each in dispatches of at
//!   most `max_items` items, tiled in 2D beyond `max_workgroups_x` workgroups;
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
use device::{Context, Reusable};
use glam::DVec3;
use items::{Dispatch, Group, Item, Work};
use nearest::Plan;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Size limits of the engine. The defaults suit every adapter; tests lower them to cover
/// the splitting paths with small data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Largest storage buffer binding in bytes; `None`: the device's
    /// `max_storage_buffer_binding_size`. Never above the device's limit.
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

/// Texels per row of a point texture (`ROW` in the shaders).
const ROW: usize = 4096;

/// One piece of the sorted points on the device, from sorted index `base` on, as an
/// `Rgba32Uint` texture of `ROW`-texel rows holding the bits of f32 x, y, z.
pub(crate) struct Part {
    view: wgpu::TextureView,
    base: usize,
}

/// One dispatch: `groups` (one workgroup each) of `items`, all reading `part`, tiled at
/// `max_x` workgroups.
pub(crate) struct Job<'a> {
    part: &'a Part,
    items: &'a [Item],
    groups: &'a [Group],
    max_x: u32,
}

/// Per-batch buffers, reused across batches.
pub(crate) struct Scratch {
    params: wgpu::Buffer,
    items: Reusable,
    groups: Reusable,
    out: Reusable,
    staging: Reusable,
    /// Histogram (nearest) or bitmask (coverage).
    aux: Reusable,
    aux_staging: Reusable,
    cut: Reusable,
}

struct Kernels {
    stats: stats::Stats,
    nearest: nearest::Nearest,
    coverage: coverage::Coverage,
}

pub struct GpuEngine {
    grid: Arc<Grid>,
    ctx: Context,
    kernels: Kernels,
    parts: Vec<Part>,
    /// Points per part (the last may hold fewer).
    part_len: usize,
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
            .min(ROW * ctx.limits.max_texture_dimension_2d as usize)
            .max(1);
        let slot_bytes = std::mem::size_of::<Item>().max(std::mem::size_of::<nearest::Below>());
        let max_items = opts.max_items.min(binding as usize / slot_bytes).max(1);
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
                items: Reusable::new("items", wgpu::BufferUsages::STORAGE),
                groups: Reusable::new("groups", wgpu::BufferUsages::STORAGE),
                out: Reusable::new("out", storage),
                staging: Reusable::new("staging", read),
                aux: Reusable::new("aux", storage),
                aux_staging: Reusable::new("aux staging", read),
                cut: Reusable::new("cut", wgpu::BufferUsages::STORAGE),
            }
        })?;
        let engine = GpuEngine {
            parts: Vec::new(),
            grid,
            ctx,
            kernels,
            part_len,
            max_items,
            max_x: opts.max_workgroups_x.max(1),
            max_queries: opts.max_queries.clamp(1, items::MAX_QUERY_SLOTS),
            scratch: Mutex::new(scratch),
            uploads: AtomicU64::new(0),
            batches: AtomicU64::new(0),
            queries: AtomicU64::new(0),
            fallbacks: AtomicU64::new(0),
        };
        engine.upload()
    }

    /// Sends the sorted centers to the device, relative to their cells' origins.
    fn upload(mut self) -> Result<Self, EngineError> {
        let g = &*self.grid;
        let (dx, dy) = (g.dims[0], g.dims[1]);
        let rel: Vec<[f32; 4]> = g
            .points
            .par_iter()
            .map(|p| {
                let p = p64(*p);
                // Same function the grid sorted with, so this is the point's own cell.
                let c = g.cell_of(p);
                let o = g.cell_origin(c % dx, (c / dx) % dy, c / (dx * dy));
                let r = p - o;
                [r.x as f32, r.y as f32, r.z as f32, 0.0]
            })
            .collect();
        let ctx = &self.ctx;
        let part_len = self.part_len;
        self.parts = ctx.scoped("uploading the Gaussians", || {
            rel.chunks(part_len)
                .enumerate()
                .map(|(i, chunk)| {
                    let rows = chunk.len().div_ceil(ROW);
                    let size = wgpu::Extent3d {
                        width: ROW as u32,
                        height: rows as u32,
                        depth_or_array_layers: 1,
                    };
                    let texture = ctx.device.create_texture(&wgpu::TextureDescriptor {
                        label: Some("points"),
                        size,
                        mip_level_count: 1,
                        sample_count: 1,
                        dimension: wgpu::TextureDimension::D2,
                        format: wgpu::TextureFormat::Rgba32Uint,
                        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
                        view_formats: &[],
                    });
                    let mut texels = chunk.to_vec();
                    texels.resize(rows * ROW, [0.0; 4]);
                    ctx.queue.write_texture(
                        wgpu::TexelCopyTextureInfo {
                            texture: &texture,
                            mip_level: 0,
                            origin: wgpu::Origin3d::ZERO,
                            aspect: wgpu::TextureAspect::All,
                        },
                        bytemuck::cast_slice(&texels),
                        wgpu::TexelCopyBufferLayout {
                            offset: 0,
                            bytes_per_row: Some((ROW * 16) as u32),
                            rows_per_image: Some(rows as u32),
                        },
                        size,
                    );
                    Part {
                        view: texture.create_view(&wgpu::TextureViewDescriptor::default()),
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
        (self.parts.len(), self.part_len)
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

    fn job<'a>(&'a self, work: &'a Work, d: &Dispatch) -> Job<'a> {
        Job {
            part: &self.parts[d.part],
            items: &work.items[d.items.clone()],
            groups: &work.groups[d.groups.clone()],
            max_x: self.max_x,
        }
    }

    /// The work items of a sub-batch, grouped and cut into dispatches.
    fn work(&self, queries: &[Query]) -> Work {
        let all = items::build(&self.grid, queries, self.part_len);
        items::group(all, self.part_len, self.max_items)
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
            for d in &work.dispatches {
                let partials = self.ctx.scoped("stats kernel", || {
                    self.kernels
                        .stats
                        .run(&self.ctx, &mut s, &self.job(&work, d))
                })??;
                for (it, p) in work.items[d.items.clone()].iter().zip(&partials) {
                    let a = &mut acc[it.query()];
                    a.count += p.count as u64;
                    a.side_pos += p.side_pos as u64;
                    a.sum_d2 += p.sum_d2 as f64;
                    a.sum_offset += p64(p.off);
                }
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
                let mut clear = self
                    .ctx
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
                clear.clear_buffer(&hist, 0, Some(hist_bytes));
                self.ctx.queue.submit([clear.finish()]);
                for d in &work.dispatches {
                    self.kernels.nearest.histogram(
                        &self.ctx,
                        &mut s,
                        &self.job(&work, d),
                        hist_bytes,
                    );
                }
                let staging = s.aux_staging.get(&self.ctx, hist_bytes).clone();
                let encoder = self
                    .ctx
                    .device
                    .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
                self.ctx
                    .read_back(encoder, &hist, &staging, hist_bytes)
                    .map(|b| bytemuck::pod_collect_to_vec(&b))
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
                let cut = s.cut.get(&self.ctx, cut_bytes);
                self.ctx
                    .queue
                    .write_buffer(cut, 0, bytemuck::cast_slice(&cuts));
                for d in &work.dispatches {
                    let res = self.kernels.nearest.below(
                        &self.ctx,
                        &mut s,
                        &self.job(&work, d),
                        hist_bytes,
                        cut_bytes,
                    )?;
                    for (it, b) in work.items[d.items.clone()].iter().zip(&res) {
                        let q = it.query();
                        if plans[q].k == 0 {
                            continue;
                        }
                        below[q] += b.count as u64;
                        acc[q].sum_d2 += b.sum_d2 as f64;
                        acc[q].sum_offset += p64(b.off);
                        // `it.start` is the chunk's global first point.
                        for (w, &bits) in b.in_cut.iter().enumerate() {
                            let mut bits = bits;
                            while bits != 0 {
                                let j = bits.trailing_zeros() as usize + 32 * w;
                                bits &= bits - 1;
                                flagged.push((q as u32, it.start + j as u32));
                            }
                        }
                    }
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
            let mut clear = self
                .ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
            clear.clear_buffer(&mask, 0, Some(mask_bytes));
            self.ctx.queue.submit([clear.finish()]);
            for range in self.sub_batches(queries.len()) {
                let work = self.work(&queries[range]);
                for d in &work.dispatches {
                    self.kernels.coverage.run(
                        &self.ctx,
                        &mut s,
                        &self.job(&work, d),
                        &mask,
                        mask_bytes,
                    );
                }
            }
            let staging = s.aux_staging.get(&self.ctx, mask_bytes).clone();
            let encoder = self
                .ctx
                .device
                .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
            self.ctx
                .read_back(encoder, &mask, &staging, mask_bytes)
                .map(|b| bytemuck::pod_collect_to_vec(&b))
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
