//! The GPU engine: wgpu + WGSL kernels answering the same batches as
//! [`CpuEngine`](super::cpu::CpuEngine), with the same counts, sides, coverage and
//! k-nearest sets, and sums to float precision.
//!
//! On the device, uploaded once: the grid's cell table (`cell_start`) and the sorted
//! centers, as f32 offsets from their own cell's corner in cell units (split into parts at
//! the binding limit). Per batch the host uploads only the queries (96 bytes each, in the
//! Morton order of their midpoints' cells: `SpatialOrder`) and one submit runs
//! (`batch.rs`):
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

pub use batch::PointStore;
pub use device::{enumerate_adapters, skip_gpu_tests};
pub use layout::CHUNK;

use super::{
    Answers, Ask, Counters, Coverage, CylStats, Engine, EngineError, FitAnswer, FitAsk, Nearest,
    NearestSum, Query, Want,
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
    /// Where `--fit edge`'s ridge runs: on the device (`fit.wgsl`, in f64, over the
    /// member lists the batch leaves there) or as the host's step over member lists.
    pub fit: FitOn,
    /// Batches of at most this many queries are answered by the CPU engine's code over
    /// the same grid, on the host: a device round trip (submit, wait, read back) costs more
    /// than such a batch. 0 (the default here, so that tests exercise the kernels with
    /// any batch): never. The commands use [`SMALL_BATCH`].
    pub small_batch: usize,
    /// Where [`Engine::members`] lists are built (the edge fit, `--split-gaps`).
    pub members: MembersOn,
    /// Whether [`GpuDevice::open`] runs two small evaluation batches over a tiny grid of
    /// its own before it returns: drivers that generate a kernel's machine code at its
    /// first dispatch (lavapipe: about 40 ms for the first evaluation's kernels) then do
    /// that on the opening thread, which runs while the caller builds the grid, instead of
    /// in the first batch. The commands' choice; off here (tests open many engines).
    pub warm_up: bool,
    /// Whether, on a software adapter (whose device memory is the host's), the buffers
    /// uploaded once (cell table, point store) are created mapped and written in place
    /// instead of through the queue's staging memory and a copy (lavapipe: the first
    /// batch 20 ms shorter at 10^6 Gaussians). On by default; tests turn it off to run
    /// the staging path that hardware adapters take.
    pub mapped_uploads: bool,
}

/// Where the GPU engine builds per-point member lists.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum MembersOn {
    /// On the device (walk, exact test, compaction; the host measures each member in f64
    /// and sorts): the default here, so that tests exercise the kernels.
    #[default]
    Device,
    /// On the host, by the CPU engine's code over the same grid.
    Host,
    /// The device on a hardware adapter; the host on a software one (lavapipe, WARP,
    /// SwiftShader), whose "device" is the host's own cores: there the member passes and
    /// their readback cost about four times the host's walk (1.1 s against 0.3 s at 10^6
    /// Gaussians x 10^4 segments, README). The commands' choice.
    Auto,
}

/// Where the GPU engine runs the edge fit's ridge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FitOn {
    /// On the device where it can: an adapter with f64 in shaders (`SHADER_F64`: Vulkan
    /// on NVIDIA, AMD, lavapipe; not Metal), the plain ridge (no normals, no opacity
    /// weights) and the Gaussians' coordinates within one storage binding; the host's step
    /// otherwise. The default here, so that tests exercise the kernel.
    #[default]
    Device,
    /// The host's step over the member lists ([`GpuOptions::members`]).
    Host,
    /// The device on a hardware adapter, the host on a software one (on lavapipe the f64
    /// kernel runs on the host's own cores, slower than the host's step). The commands'
    /// choice.
    Auto,
}

/// The commands' [`GpuOptions::small_batch`]: the tail rounds of merge/join and crop ask
/// a few queries at a time, which the host answers in microseconds; a device round trip
/// costs a fraction of a millisecond on a real GPU (about one on lavapipe).
pub const SMALL_BATCH: usize = 16;

impl GpuOptions {
    /// The options the commands use: the defaults, with batches of at most
    /// [`SMALL_BATCH`] queries on the host (`LINEGS_GPU_SMALL_BATCH=N` sets another bound;
    /// 0 sends every batch to the device), member lists and the edge fit by adapter
    /// ([`MembersOn::Auto`], [`FitOn::Auto`]; `LINEGS_GPU_MEMBERS=device|host` and
    /// `LINEGS_GPU_FIT=device|host` choose).
    pub fn for_commands() -> Self {
        let small_batch = std::env::var("LINEGS_GPU_SMALL_BATCH")
            .ok()
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(SMALL_BATCH);
        let fit = match std::env::var("LINEGS_GPU_FIT").as_deref() {
            Ok("device") => FitOn::Device,
            Ok("host") => FitOn::Host,
            _ => FitOn::Auto,
        };
        let members = match std::env::var("LINEGS_GPU_MEMBERS").as_deref() {
            Ok("device") => MembersOn::Device,
            Ok("host") => MembersOn::Host,
            _ => MembersOn::Auto,
        };
        GpuOptions {
            small_batch,
            fit,
            members,
            warm_up: true,
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
            fit: FitOn::Device,
            small_batch: 0,
            members: MembersOn::Device,
            warm_up: false,
            mapped_uploads: true,
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

/// The fit kernel's full source: the shared prelude, its own f64 prelude, then
/// `fit.wgsl` (compiled only on a device with `SHADER_F64`).
pub fn fit_source() -> String {
    kernel_source(&format!(
        "{}\n{}",
        layout::fit_prelude(),
        include_str!("../../../shaders/fit.wgsl")
    ))
}

/// The lines of `eval.wgsl` that read the evaluation mode and the coverage switch from
/// the uniform.
const EVAL_MODE_LINE: &str = "let mode = params.mode;";
const EVAL_COVER_LINE: &str = "let cover_on = params.cover != 0u;";

/// The evaluation kernel compiled for one mode (and, for the stats modes, with or without
/// the coverage bits): both are constants instead of the uniform's, so each pipeline
/// carries only its own branches (on lavapipe the stats pass then costs about 40 % less
/// CPU time; on GPUs fewer registers).
pub fn eval_source(mode: u32, cover: bool) -> String {
    let src = include_str!("../../../shaders/eval.wgsl");
    assert!(
        src.contains(EVAL_MODE_LINE) && src.contains(EVAL_COVER_LINE),
        "eval.wgsl reads its mode and coverage switch"
    );
    kernel_source(
        &src.replace(EVAL_MODE_LINE, &format!("let mode = {mode}u;"))
            .replace(EVAL_COVER_LINE, &format!("let cover_on = {cover};")),
    )
}

/// The line of `walk.wgsl` that reads its pass (count or emit) from the uniform.
const WALK_EMIT_LINE: &str = "let emit = params.mode == MODE_EMIT;";

/// The grid walk compiled for one pass, the pass a constant: the count pass then carries
/// no item stores (a SIMD implementation such as lavapipe runs a branch's stores under a
/// mask even where no lane takes it) and the emit pass no count bookkeeping.
pub fn walk_source(emit: bool) -> String {
    let src = include_str!("../../../shaders/walk.wgsl");
    assert!(src.contains(WALK_EMIT_LINE), "walk.wgsl reads its pass");
    kernel_source(&src.replace(WALK_EMIT_LINE, &format!("let emit = {emit};")))
}

/// The order a batch's queries go to the device in: along a Morton (Z-order) curve through
/// the cells holding their segments' midpoints, so that queries next to each other in the
/// batch (the lanes of one SIMD group or warp, the invocations in flight together) walk
/// neighbouring rows of the cell table and read neighbouring points, and their items share
/// cache lines. In the caller's order (a file's, a step's) each lane reads its own stretch
/// of memory; on lavapipe the kernels of the bench scene's evaluation batch take a fifth
/// less time in this order. Answers are per query, so restoring the caller's order gives them
/// bit for bit (the coverage mask is a union, the same in any order).
struct SpatialOrder {
    /// `perm[j]`: the caller's index of the `j`-th query sent.
    perm: Vec<u32>,
}

impl SpatialOrder {
    fn new(grid: &Grid, queries: &[Query]) -> SpatialOrder {
        let (dx, dy) = (grid.dims[0], grid.dims[1]);
        // One u64 per query: the Morton code (its top 40 bits where the grid needs more)
        // above the query's index (24 bits), sorted as plain integers; ties keep the
        // caller's order.
        const INDEX_BITS: u32 = 24;
        let axis_bits =
            32 - (grid.dims.iter().max().copied().unwrap_or(1).max(1) - 1).leading_zeros();
        let shift = (3 * axis_bits).saturating_sub(64 - INDEX_BITS);
        let code = |q: &Query| {
            // `cell_of` clamps into the grid (an invalid segment's NaN midpoint: cell 0).
            let c = grid.cell_of(q.seg.midpoint());
            morton3(c % dx, (c / dx) % dy, c / (dx * dy))
        };
        if queries.len() >= 1 << INDEX_BITS {
            let mut keys: Vec<(u64, u32)> = queries
                .par_iter()
                .enumerate()
                .map(|(i, q)| (code(q), i as u32))
                .collect();
            keys.par_sort_unstable();
            return SpatialOrder {
                perm: keys.into_iter().map(|(_, i)| i).collect(),
            };
        }
        let mut keys: Vec<u64> = queries
            .par_iter()
            .with_min_len(4096)
            .enumerate()
            .map(|(i, q)| (code(q) >> shift) << INDEX_BITS | i as u64)
            .collect();
        keys.par_sort_unstable();
        let mask = (1u64 << INDEX_BITS) - 1;
        SpatialOrder {
            perm: keys.into_iter().map(|k| (k & mask) as u32).collect(),
        }
    }

    /// The caller's index of the `j`-th query sent.
    fn index(&self, j: usize) -> usize {
        self.perm[j] as usize
    }

    /// `xs` (one per query, in the caller's order) in the order sent.
    fn apply<T: Clone>(&self, xs: &[T]) -> Vec<T> {
        self.perm.iter().map(|&i| xs[i as usize].clone()).collect()
    }

    /// Answers in the order sent, back in the caller's order (empty stays empty).
    fn restore<T>(&self, ys: Vec<T>) -> Vec<T> {
        if ys.is_empty() {
            return ys;
        }
        debug_assert_eq!(ys.len(), self.perm.len());
        let mut out: Vec<Option<T>> = (0..ys.len()).map(|_| None).collect();
        for (&i, y) in self.perm.iter().zip(ys) {
            out[i as usize] = Some(y);
        }
        out.into_iter()
            .map(|y| y.expect("a permutation fills every slot"))
            .collect()
    }
}

/// Interleaves the low 21 bits of `x`, `y` and `z` (x lowest): the cell's Morton code.
fn morton3(x: u32, y: u32, z: u32) -> u64 {
    fn spread(v: u32) -> u64 {
        let mut v = (v & 0x1F_FFFF) as u64;
        v = (v | v << 32) & 0x001F_0000_0000_FFFF;
        v = (v | v << 16) & 0x001F_0000_FF00_00FF;
        v = (v | v << 8) & 0x100F_00F0_0F00_F00F;
        v = (v | v << 4) & 0x10C3_0C30_C30C_30C3;
        v = (v | v << 2) & 0x1249_2492_4924_9249;
        v
    }
    spread(x) | spread(y) << 1 | spread(z) << 2
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
    /// [`GpuOptions::fit`] resolved for this adapter (and the kernel compiled, the
    /// coordinates uploaded).
    device_fit: bool,
    clock: Clock,
    /// Answers the batches of at most `small_batch` queries, over the same grid.
    cpu: super::cpu::CpuEngine,
    small_batch: usize,
    /// [`GpuOptions::members`] resolved for this adapter.
    members_on_host: bool,
    cpu_batches: AtomicU64,
    cpu_queries: AtomicU64,
    device_fits: AtomicU64,
    device_fits_refitted: AtomicU64,
}

/// An opened device with the kernels compiled, before any Gaussians: what does not depend
/// on the grid, so that the commands can open it while the grid is built
/// (`select::prepare`). [`GpuDevice::engine`] uploads a grid and gives the engine.
pub struct GpuDevice {
    ctx: Context,
    kernels: batch::Kernels,
    opts: GpuOptions,
    fit_wanted: bool,
    software: bool,
}

impl GpuDevice {
    /// The adapter chosen by `WGPU_ADAPTER_NAME` / `WGPU_BACKEND` (or wgpu's default).
    pub fn open_default(opts: GpuOptions) -> Result<GpuDevice, EngineError> {
        GpuDevice::open(&device::pick_adapter()?, opts)
    }

    /// Opens `adapter` and compiles the kernels.
    pub fn open(adapter: &wgpu::Adapter, opts: GpuOptions) -> Result<GpuDevice, EngineError> {
        let ctx = Context::new(adapter, opts.mapped_uploads)?;
        let software = ctx.info.device_type == wgpu::DeviceType::Cpu;
        let fit_wanted = ctx.f64
            && match opts.fit {
                FitOn::Device => true,
                FitOn::Host => false,
                FitOn::Auto => !software,
            };
        let kernels = ctx.scoped("compiling the kernels", || {
            batch::Kernels::new(&ctx, fit_wanted)
        })?;
        let device = GpuDevice {
            ctx,
            kernels,
            opts,
            fit_wanted,
            software,
        };
        if opts.warm_up {
            device.warmed_up()
        } else {
            Ok(device)
        }
    }

    /// The device after one batch of each kind the first steps of a refinement send (an
    /// evaluation with coverage, a count batch) over a two-point grid of its own: the
    /// first dispatch of every pipeline they use happens here. The warm-up engine and its
    /// buffers and counters are dropped; the device and the kernels stay.
    fn warmed_up(self) -> Result<GpuDevice, EngineError> {
        use crate::geom::{Aabb, Segment};
        let (opts, fit_wanted, software) = (self.opts, self.fit_wanted, self.software);
        let pts = [[0.25f32, 0.5, 0.5], [0.75, 0.5, 0.5]];
        let unit = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        let grid = Arc::new(Grid::build(&pts, unit, 0.25));
        let engine = GpuDevice {
            opts: GpuOptions {
                small_batch: 0,
                ..opts
            },
            ..self
        }
        .engine(grid)?;
        let axis = Segment::new(DVec3::new(0.0, 0.5, 0.5), DVec3::new(1.0, 0.5, 0.5));
        let queries = [Query::new(axis, 0.1)];
        for (want, coverage) in [(Want::SUMS, true), (Want::COUNT, false)] {
            let ask = Ask {
                want,
                coverage,
                ..Default::default()
            };
            let got = engine.query(&queries, &ask)?;
            debug_assert_eq!(got.stats[0].count, 2);
        }
        let GpuEngine { ctx, kernels, .. } = engine;
        Ok(GpuDevice {
            ctx,
            kernels,
            opts,
            fit_wanted,
            software,
        })
    }

    /// The adapter's name and driver.
    pub fn adapter(&self) -> String {
        self.ctx.describe()
    }

    /// Uploads `grid` (once: every batch of the engine's life reads it there).
    pub fn engine(self, grid: Arc<Grid>) -> Result<GpuEngine, EngineError> {
        self.engine_with(grid, None)
    }

    /// [`Self::engine`] with the point store already computed from `grid` (while the
    /// device opened).
    pub fn engine_with(
        self,
        grid: Arc<Grid>,
        store: Option<batch::PointStore>,
    ) -> Result<GpuEngine, EngineError> {
        let GpuDevice {
            ctx,
            kernels,
            opts,
            fit_wanted,
            software,
        } = self;
        let limits = batch::Limits::new(&ctx, &opts, grid.len());
        let statics = batch::Statics::upload(&ctx, &grid, store, &limits, fit_wanted)?;
        let buffers = ctx.scoped("allocating buffers", || Buffers::new(&ctx, &limits))?;
        let device_fit = fit_wanted && kernels.fit.is_some() && statics.world.is_some();
        Ok(GpuEngine {
            cpu: super::cpu::CpuEngine::new(grid.clone()),
            small_batch: opts.small_batch,
            members_on_host: match opts.members {
                MembersOn::Device => false,
                MembersOn::Host => true,
                MembersOn::Auto => software,
            },
            cpu_batches: AtomicU64::new(0),
            cpu_queries: AtomicU64::new(0),
            device_fits: AtomicU64::new(0),
            device_fits_refitted: AtomicU64::new(0),
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
            device_fit,
            clock: Clock::default(),
        })
    }
}

impl GpuEngine {
    /// Opens the adapter chosen by `WGPU_ADAPTER_NAME` / `WGPU_BACKEND` (or wgpu's default)
    /// and uploads the grid.
    pub fn new(grid: Arc<Grid>) -> Result<Self, EngineError> {
        Self::with_options(grid, GpuOptions::default())
    }

    pub fn with_options(grid: Arc<Grid>, opts: GpuOptions) -> Result<Self, EngineError> {
        GpuDevice::open_default(opts)?.engine(grid)
    }

    /// The engine on a given adapter (`select.rs` picks it).
    pub fn on_adapter(
        adapter: &wgpu::Adapter,
        grid: Arc<Grid>,
        opts: GpuOptions,
    ) -> Result<Self, EngineError> {
        GpuDevice::open(adapter, opts)?.engine(grid)
    }

    /// Whether the adapter is a software one (`DeviceType::Cpu`: lavapipe, WARP,
    /// SwiftShader).
    pub fn is_software(&self) -> bool {
        self.ctx.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Whether `--fit edge`'s ridge runs on this device ([`GpuOptions::fit`], resolved:
    /// f64 in shaders, the coordinates within one binding).
    pub fn fits_on_device(&self) -> bool {
        self.device_fit
    }

    /// The kernels this engine has compiled on first use (those of the side counts, the k
    /// nearest and the member lists; the rest compile when the device opens), named as
    /// `eval sides`, `eval histogram`, `eval below`, `eval members`, `cut`, `members`.
    pub fn kernels_compiled_on_use(&self) -> Vec<String> {
        self.kernels.compiled_on_use()
    }

    /// Queries answered wholly on the host; 0 on ordinary scenes.
    pub fn host_fallbacks(&self) -> u64 {
        self.fallbacks.load(Ordering::Relaxed)
    }

    /// Former name of [`Self::host_fallbacks`].
    pub fn nearest_fallbacks(&self) -> u64 {
        self.host_fallbacks()
    }

    /// Work items a batch's buffers hold now (a guess from the batch size at first, then
    /// what the batches needed).
    pub fn item_capacity(&self) -> u32 {
        self.lock().item_cap()
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
        self.run_with(b, kind, queries, ks, &[], each)
    }

    /// [`Self::run`] with the fit batch's per-query frames (`fit`, one per query).
    fn run_with(
        &self,
        b: &mut Buffers,
        kind: Kind,
        queries: &[Query],
        ks: &[u64],
        fit: &[layout::FitQuery],
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
            let fit = if fit.is_empty() { fit } else { &fit[r.clone()] };
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
                    fit,
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

impl GpuEngine {
    /// Every query's members (see [`Engine::members`]) from device batches; a query the
    /// device leaves to the host (walk too long, too many members, a miscount) gets the
    /// CPU engine's list.
    fn members_batch(
        &self,
        b: &mut Buffers,
        queries: &[Query],
    ) -> Result<Vec<Vec<super::Member>>, EngineError> {
        let mut out: Vec<Vec<super::Member>> = vec![Vec::new(); queries.len()];
        let grid = &*self.grid;
        let fallbacks = &self.fallbacks;
        self.run(b, Kind::Members, queries, &[], &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            let spans = host::spans(&o.flags, n);
            // Query after query, the device's sure members.
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
            out[first..first + n]
                .par_iter_mut()
                .enumerate()
                .with_min_len(8)
                .for_each(|(i, m)| {
                    let q = &qs[i];
                    let device = o.results[i].status & layout::STATUS_HOST == 0
                        && !o.bad
                        && lists[i].end <= o.members.len()
                        && q.r.is_finite()
                        && q.r >= 0.0;
                    let list = device
                        .then(|| {
                            host::members(
                                grid,
                                q,
                                &o.members[lists[i].clone()],
                                &o.flags[spans[i].clone()],
                            )
                        })
                        .flatten();
                    *m = list.unwrap_or_else(|| {
                        fallbacks.fetch_add(1, Ordering::Relaxed);
                        super::cpu::member_list(grid, q)
                    });
                });
            Ok(())
        })?;
        Ok(out)
    }
}

impl GpuEngine {
    /// The edge fit's step of every query: the ridge on the device (`fit.wgsl`, f64) over
    /// the members the batch lists there. A query whose members include a flagged
    /// boundary point, whose ridge the kernel left to the host, whose weight lies within
    /// 1e-9 (relative) of `fit_min_points`, or that the device could not take, is fitted
    /// on the host from its exact members (`host_fallbacks` counts them).
    fn fit_batch(
        &self,
        b: &mut Buffers,
        queries: &[Query],
        ask: &FitAsk<'_>,
    ) -> Result<Vec<FitAnswer>, EngineError> {
        use crate::refine::fit::{How, LineFit};
        let grid = &*self.grid;
        let p = ask.params;
        // The host's own values (`Cylinder::new`, `basis`, `ridge`'s h_min).
        let frames: Vec<layout::FitQuery> = queries
            .iter()
            .map(|q| {
                let d = q.seg.dir();
                let (e1, e2) = crate::refine::fit::basis(d);
                let p1 = q.seg.p1;
                layout::FitQuery {
                    p1x: p1.x,
                    p1y: p1.y,
                    p1z: p1.z,
                    dx: d.x,
                    dy: d.y,
                    dz: d.z,
                    e1x: e1.x,
                    e1y: e1.y,
                    e1z: e1.z,
                    e2x: e2.x,
                    e2y: e2.y,
                    e2z: e2.z,
                    r: q.r,
                    h_min: p.fit_bandwidth * q.r,
                }
            })
            .collect();
        let min_points = p.fit_min_points as f64;
        let mut out: Vec<FitAnswer> = vec![(None, How::Unclear); queries.len()];
        let fallbacks = &self.fallbacks;
        let (device_fits, refitted) = (&self.device_fits, &self.device_fits_refitted);
        self.run_with(b, Kind::Fit, queries, &[], &frames, &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            let spans = host::spans(&o.flags, n);
            out[first..first + n]
                .par_iter_mut()
                .enumerate()
                .with_min_len(8)
                .for_each(|(i, a)| {
                    let q = &qs[i];
                    let device = o.results[i].status & layout::STATUS_HOST == 0
                        && !o.bad
                        && q.r.is_finite()
                        && q.r > 0.0
                        && !o.flags[spans[i].clone()].iter().any(|f| {
                            f.0 & layout::FLAG_CANDIDATE == 0 && host::is_member(grid, q, f.1)
                        });
                    let answer = o
                        .fits
                        .get(i)
                        .filter(|_| device)
                        .and_then(|f| match f.status {
                            layout::FIT_NONE => Some((None, How::Unclear)),
                            layout::FIT_OK => {
                                let w = f.weight;
                                // Within rounding of the threshold: the host decides.
                                if (w - min_points).abs() <= 1e-9 * min_points.max(1.0) {
                                    return None;
                                }
                                if w < min_points {
                                    return Some((None, How::Unclear));
                                }
                                let line = LineFit {
                                    t0: f.t0,
                                    a: glam::DVec2::new(f.ax, f.ay),
                                    b: glam::DVec2::new(f.bx, f.by),
                                };
                                // A decision of the caller's close to its threshold: exact.
                                if ask.sensitive.is_some_and(|s| s(first + i, &line)) {
                                    return None;
                                }
                                Some((Some(line), How::Ridge))
                            }
                            _ => None,
                        });
                    *a = match answer {
                        Some(a) => {
                            device_fits.fetch_add(1, Ordering::Relaxed);
                            a
                        }
                        None => {
                            fallbacks.fetch_add(1, Ordering::Relaxed);
                            refitted.fetch_add(1, Ordering::Relaxed);
                            let m = super::cpu::member_list(grid, q);
                            crate::refine::fit::steps(std::slice::from_ref(q), &[m], ask)[0]
                        }
                    };
                });
            Ok(())
        })?;
        Ok(out)
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
    /// k-nearest batch itself. The device gets the queries in `SpatialOrder`.
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
        // The ordering is host work of the batch (`host_seconds`).
        let (order, sent, ks) = self.on_host(|| {
            let order = SpatialOrder::new(&self.grid, queries);
            let sent = order.apply(queries);
            let ks = match ask.nearest {
                Nearest::K(k) => order.apply(k),
                _ => Vec::new(),
            };
            (order, sent, ks)
        });
        let nearest = match ask.nearest {
            Nearest::K(_) => Nearest::K(&ks),
            other => other,
        };
        let out = self.query_in_order(&sent, &Ask { nearest, ..*ask })?;
        Ok(self.on_host(|| Answers {
            stats: order.restore(out.stats),
            nearest: order.restore(out.nearest),
            coverage: out.coverage,
        }))
    }

    /// One device batch: the walk and the stats pass, a scan of the items' member counts
    /// and a member pass that writes each query's sure members contiguously; the host
    /// measures them (and decides the flagged points) in f64, as the CPU engine does.
    /// Batches of at most `small_batch` queries (the fit's last iterations) are answered
    /// on the host, like small [`Engine::query`] batches, and so is every batch where
    /// [`GpuOptions::members`] resolved to the host (a software adapter, for the commands).
    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<super::Member>>, EngineError> {
        self.count_batch(queries.len());
        if !queries.is_empty() && (queries.len() <= self.small_batch || self.members_on_host) {
            let t = std::time::Instant::now();
            let out = self.cpu.members(queries);
            self.cpu_batches.fetch_add(1, Ordering::Relaxed);
            self.cpu_queries
                .fetch_add(queries.len() as u64, Ordering::Relaxed);
            self.clock.add(t.elapsed().as_secs_f64(), 0.0);
            return out;
        }
        let (order, sent) = self.on_host(|| {
            let order = SpatialOrder::new(&self.grid, queries);
            let sent = order.apply(queries);
            (order, sent)
        });
        let lists = self.members_batch(&mut self.lock(), &sent)?;
        Ok(self.on_host(|| order.restore(lists)))
    }

    /// With [`GpuOptions::fit`] on the device, the ridge there where the fit is the plain
    /// ridge: no normals (the two-face fit stays on the host), no opacity weights, more
    /// than `small_batch` queries; otherwise [`Engine::members`] and the host's step.
    fn fit_lines(
        &self,
        queries: &[Query],
        ask: &FitAsk<'_>,
    ) -> Result<Vec<FitAnswer>, EngineError> {
        let device = self.device_fit
            && queries.len() > self.small_batch
            && ask.attrs.normals.is_none()
            && !ask.params.fit_opacity_weight
            && !self.grid.is_empty();
        if !device {
            let members = self.members(queries)?;
            let t = std::time::Instant::now();
            let out = crate::refine::fit::steps(queries, &members, ask);
            self.clock.add(t.elapsed().as_secs_f64(), 0.0);
            return Ok(out);
        }
        self.count_batch(queries.len());
        let (order, sent) = self.on_host(|| {
            let order = SpatialOrder::new(&self.grid, queries);
            let sent = order.apply(queries);
            (order, sent)
        });
        let by_caller = &order;
        let sensitive = ask.sensitive.map(|s| {
            move |j: usize, line: &crate::refine::fit::LineFit| s(by_caller.index(j), line)
        });
        let ask = FitAsk {
            sensitive: sensitive.as_ref().map(|s| s as &super::Sensitive<'_>),
            ..*ask
        };
        let answers = self.fit_batch(&mut self.lock(), &sent, &ask)?;
        Ok(self.on_host(|| order.restore(answers)))
    }

    fn counters(&self) -> Counters {
        Counters {
            uploads: self.uploads.load(Ordering::Relaxed),
            batches: self.batches.load(Ordering::Relaxed),
            queries: self.queries.load(Ordering::Relaxed),
            cpu_batches: self.cpu_batches.load(Ordering::Relaxed),
            cpu_queries: self.cpu_queries.load(Ordering::Relaxed),
            device_fits: self.device_fits.load(Ordering::Relaxed),
            device_fits_refitted: self.device_fits_refitted.load(Ordering::Relaxed),
        }
    }

    fn seconds(&self) -> Option<(f64, f64)> {
        Some(GpuEngine::seconds(self))
    }
}

impl GpuEngine {
    /// `f()`, its time counted as the engine's host work (`host_seconds`).
    fn on_host<R>(&self, f: impl FnOnce() -> R) -> R {
        let t = std::time::Instant::now();
        let out = f();
        self.clock.add(t.elapsed().as_secs_f64(), 0.0);
        out
    }

    /// One device batch for the stats and the coverage together (one walk, each point
    /// evaluated once), then, for nearest sums, the k-nearest batch (whose `k` may come
    /// from the first batch's counts); a nearest-only ask gets its counts from the
    /// k-nearest batch itself. `queries` in the order the device gets them.
    fn query_in_order(&self, queries: &[Query], ask: &Ask<'_>) -> Result<Answers, EngineError> {
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{Aabb, Segment};

    #[test]
    fn morton_codes_interleave_x_lowest() {
        assert_eq!(morton3(0, 0, 0), 0);
        assert_eq!(morton3(1, 0, 0), 0b001);
        assert_eq!(morton3(0, 1, 0), 0b010);
        assert_eq!(morton3(0, 0, 1), 0b100);
        assert_eq!(morton3(3, 0, 0), 0b001_001);
        assert_eq!(morton3(2, 3, 1), 0b011_110);
        // All 21 bits of each coordinate survive.
        let top = 1u32 << 20;
        assert_eq!(morton3(top, 0, 0), 1u64 << 60);
        assert_eq!(morton3(0, 0, top), 1u64 << 62);
    }

    fn grid_4x4x4() -> Grid {
        let pts: Vec<[f32; 3]> = (0..64)
            .map(|i| {
                [
                    (i % 4) as f32 + 0.5,
                    ((i / 4) % 4) as f32 + 0.5,
                    (i / 16) as f32 + 0.5,
                ]
            })
            .collect();
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::splat(3.99),
        };
        Grid::build(&pts, b, 1.0)
    }

    fn at(x: f64, y: f64, z: f64) -> Query {
        let p = DVec3::new(x, y, z);
        Query::new(Segment::new(p - DVec3::X * 0.1, p + DVec3::X * 0.1), 0.2)
    }

    #[test]
    fn queries_go_in_morton_order_and_answers_come_back_in_the_callers() {
        let g = grid_4x4x4();
        assert_eq!(g.dims, [4, 4, 4]);
        // Cells (3,3,3), (0,0,0), (1,0,0), (0,1,0), (0,0,1), and (0,0,0) again.
        let qs = [
            at(3.5, 3.5, 3.5),
            at(0.5, 0.5, 0.5),
            at(1.5, 0.5, 0.5),
            at(0.5, 1.5, 0.5),
            at(0.5, 0.5, 1.5),
            at(0.6, 0.4, 0.5),
        ];
        let order = SpatialOrder::new(&g, &qs);
        // Ties (queries 1 and 5 share a cell) keep the caller's order.
        assert_eq!(order.perm, vec![1, 5, 2, 3, 4, 0]);
        assert_eq!(order.index(5), 0);
        let sent = order.apply(&qs);
        assert_eq!(sent[0], qs[1]);
        assert_eq!(sent[5], qs[0]);
        // An answer computed from each sent query comes back to its own slot.
        let answers: Vec<f64> = sent
            .iter()
            .map(|q| q.seg.p1.x + 10.0 * q.seg.p1.z)
            .collect();
        let back = order.restore(answers);
        for (q, a) in qs.iter().zip(&back) {
            assert_eq!(*a, q.seg.p1.x + 10.0 * q.seg.p1.z);
        }
        assert!(order.restore(Vec::<f64>::new()).is_empty());
    }
}
