//! The GPU engine: wgpu + WGSL kernels answering the same batches as
//! [`CpuEngine`](super::cpu::CpuEngine), with the same counts, sides, coverage and
//! k-nearest sets, and sums to float precision.
//!
//! On the device, uploaded once: the grid's cell table (`cell_start`) and the sorted
//! centers, as f32 offsets from their own cell's corner in cell units, in a 2D texture of
//! [`STORE_W`](layout::STORE_W) points a row (split into parts where one texture cannot
//! hold them). The evaluation kernel fetches points as texels: a texel fetch is a load
//! every GPU serves from its texture cache, and on a SIMD implementation such as lavapipe
//! it gathers the lanes' points in a few instructions, where a storage load with a
//! different address per lane is a loop over the lanes (the evaluation kernel 2.3x faster
//! there). Per batch the host uploads only the queries (96 bytes each, in the Morton
//! order of their midpoints' cells: `order.rs`), as a texture whose texels the kernels
//! fetch, and one submit runs the stages that run in the batch's kind, in the order of
//! the registry's `kernels::STAGES` (each declared and recorded by its kernel's launcher,
//! `kernels/`):
//! 1. `walk.wgsl` (count): per query, the work items its capped cylinder needs (cells it
//!    can touch, each cell cut into chunks of at most [`CHUNK`] points);
//! 2. `scan.wgsl`: exclusive prefix sum of those counts (multi-level workgroup scan);
//! 3. `args.wgsl`: the total, and the indirect dispatch size of the per-item kernels;
//! 4. `walk.wgsl` (emit): the items, contiguous per query;
//! 5. `eval.wgsl`: per item, its members' sums into its own slot (or the coverage bits, or
//!    the k-nearest histogram; `cut.wgsl` then plans the cut and `eval.wgsl` sums below it;
//!    or, for member lists, `members.wgsl` and a member pass);
//!    points within the f32 error bound of a boundary are flagged instead;
//! 6. `reduce.wgsl`: per query, its items' slots summed in grid order (Kahan, no atomics);
//! 7. `fit.wgsl` (the edge fit's batches): the ridge over each query's member list.
//! 8. `extent.wgsl` (the end gaps' batches): the members at both ends of each query's
//!    member list, whose own positions the host then reads in f64.
//!
//! The host then reads back the per-query results and the flag list (one readback) and
//! decides the flagged points in f64 — the only per-point work left on the host, and
//! what makes membership exact (`answers.rs`). When the items or flags outgrow their
//! buffers the batch is rerun with larger ones (the sizes are kept for later batches).
//!
//! The files: `options.rs` (what callers choose), `kernels/` (one launcher a kernel,
//! and the registry: the pipelines the device opening compiles, the stages of a batch in
//! order, and which launcher answers which query), `pipelines.rs` (a kernel's
//! description, the queries a list kernel may answer, and the compiled pipelines),
//! `resources.rs` (limits, what is uploaded once, per-batch buffers), `sizes.rs` (a
//! batch's kind, sizes and bound buffers), `query.rs` (a query as the kernels read
//! it), `order.rs` (the queries' order), `batch.rs` (one sub-batch: sizes, buffers, the
//! stages in order, submit, readback), `stages.rs` (a stage's description, the sequence
//! of them and the recorder of a compute pass),
//! `answers.rs` (outputs into answers), `host.rs` (the host's f64
//! decisions), `device.rs` (wgpu), `layout.rs` (the structs shared with WGSL).
//!
//! What keeps the device within its limits: every kernel loop is bounded (see each
//! shader); the point store is split where a texture reaches the device's largest side,
//! and no chunk crosses a part;
//! dispatches are tiled in 2D beyond `max_workgroups_x` workgroups; every wgpu call runs
//! inside error scopes, so errors come back as `EngineError::Gpu`.

mod answers;
mod batch;
mod device;
mod host;
mod kernels;
pub mod layout;
mod options;
mod pipelines;
mod query;
mod resources;
mod sizes;
mod stages;

pub use device::{
    describe as describe_adapter, enumerate_adapters, find_pci_bus_id, parse_pci_bus_id,
    PciBusError,
};
pub use kernels::{
    common_wgsl, f64_kernel_source, kernel_source, kernel_specs, list_kernel_source,
};
pub use layout::CHUNK;
pub use options::{FitOn, GpuOptions, GpuSetup, GpuSetupError, MembersOn, SMALL_BATCH};
pub use pipelines::{KernelSpec, When};
pub use resources::PointStore;

use super::{
    Answers, Ask, Counters, CylStats, Engine, EngineError, FitAnswer, FitAsk, FitJob, Nearest,
    Query, Want,
};
use crate::engine::order::SpatialOrder;
use crate::geom::fit::{FitPoints, FitResult, FitSpec};
use crate::index::Grid;
use device::Context;
use glam::DVec3;
use resources::Buffers;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Each kind of device batch and the stages a try of it records, in order, each with its
/// own buffers, as the registry (`kernels::STAGES`) makes them (with `rerun`, a rerun's:
/// the sub-batch again with larger buffers): what `tests/shaders.rs` checks the order of.
/// The kinds: `stats`, `stats sides cover`, `nearest`, `members`, and `list <kernel>` for
/// each list kernel of `kernels::ROUTES`.
#[allow(clippy::type_complexity)]
pub fn batch_stages(rerun: bool) -> Vec<(String, Vec<(&'static str, Vec<&'static str>)>)> {
    use sizes::Kind;
    let seq = stages::Sequence::new(kernels::STAGES);
    let r = &kernels::ROUTES;
    let lists = [
        r.axial.map(|r| r.kernel),
        r.extent.map(|r| r.kernel),
        r.fit_lines.map(|r| r.route.kernel),
    ];
    let mut kinds = vec![
        (
            "stats".to_string(),
            Kind::Stats {
                sides: false,
                cover: false,
            },
        ),
        (
            "stats sides cover".to_string(),
            Kind::Stats {
                sides: true,
                cover: true,
            },
        ),
        ("nearest".to_string(), Kind::Nearest),
        ("members".to_string(), Kind::Members),
    ];
    kinds.extend(
        lists
            .into_iter()
            .flatten()
            .map(|l| (format!("list {}", l.spec.name), Kind::List(l))),
    );
    kinds
        .into_iter()
        .map(|(name, kind)| {
            let stages = seq
                .running(kind, rerun)
                .map(|s| (s.name, s.buffers.iter().map(|b| b.name).collect()))
                .collect();
            (name, stages)
        })
        .collect()
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
    kernels: pipelines::Kernels,
    /// The stages of every batch, in order (`kernels::STAGES`).
    stages: stages::Sequence,
    statics: resources::Statics,
    opts: resources::Limits,
    /// One batch at a time: the buffers and the error scopes are per batch.
    buffers: Mutex<Buffers>,
    uploads: AtomicU64,
    batches: AtomicU64,
    queries: AtomicU64,
    /// Queries answered wholly on the host (walks too long, or k-nearest sets with a
    /// boundary member); rare by design.
    fallbacks: AtomicU64,
    /// Member lists that came back as records out of working-set order and were sorted on
    /// the host (longer than the records kernel ranks, or with a flagged member).
    sorted_on_host: AtomicU64,
    /// Sub-batches of members batches whose lists came back as records.
    record_batches: AtomicU64,
    /// Nanoseconds of the running batch spent in the caller's own work (a part's
    /// receiver, [`Engine::members_in_parts`]), left out of its host seconds.
    callers_ns: AtomicU64,
    clock: Clock,
    /// The CPU engine over the same grid, used only through the [`Engine`] interface:
    /// the batches of at most `small_batch` queries, member lists on the host, and the
    /// queries the device leaves to the host.
    cpu: Box<dyn Engine>,
    small_batch: usize,
    /// [`GpuOptions::fit_tail`].
    fit_tail: usize,
    /// [`GpuOptions::members`] resolved for this adapter.
    members_on_host: bool,
    cpu_batches: AtomicU64,
    cpu_queries: AtomicU64,
    device_fits: AtomicU64,
    device_fits_refitted: AtomicU64,
    /// [`Counters::device_items`], [`Counters::point_bytes`], [`Counters::host_lists`].
    device_items: AtomicU64,
    point_bytes: AtomicU64,
    host_lists: AtomicU64,
}

/// How many times this process began to open a device ([`GpuDevice::open`]).
static OPENED: AtomicU64 = AtomicU64::new(0);

/// How many devices this process has begun to open so far: a run opens one, whatever
/// engines it makes on it (tests, diagnostics).
pub fn devices_opened() -> u64 {
    OPENED.load(Ordering::Relaxed)
}

/// An opened device with the kernels compiled, before any Gaussians: what does not depend
/// on the grid, so that the commands can open it while the grid is built
/// (`select::prepare`). [`GpuDevice::engine`] uploads a grid and gives the engine. A clone
/// shares the device and the kernels (a second engine of the same run, `--max-scale`'s
/// placing Gaussians, opens nothing again).
#[derive(Clone)]
pub struct GpuDevice {
    ctx: Context,
    kernels: pipelines::Kernels,
    opts: GpuOptions,
    fit_wanted: bool,
    software: bool,
}

impl GpuDevice {
    /// wgpu's default adapter (`WGPU_BACKEND` and `WGPU_POWER_PREF` honoured, as wgpu
    /// reads them).
    pub fn open_default(opts: GpuOptions) -> Result<GpuDevice, EngineError> {
        GpuDevice::open(&device::pick_adapter(None)?, opts)
    }

    /// The adapter and options of `setup` (what the commands read from their environment).
    pub fn open_setup(setup: &GpuSetup) -> Result<GpuDevice, EngineError> {
        let adapter = match &setup.adapter_pci_bus_id {
            Some(bus) => device::pick_adapter_at(bus)?,
            None => device::pick_adapter(setup.adapter_name.as_deref())?,
        };
        GpuDevice::open(&adapter, setup.options)
    }

    /// Opens `adapter` and compiles the kernels.
    pub fn open(adapter: &wgpu::Adapter, opts: GpuOptions) -> Result<GpuDevice, EngineError> {
        OPENED.fetch_add(1, Ordering::Relaxed);
        let ctx = Context::new(adapter, opts.mapped_uploads, opts.fill_garbage)?;
        let software = ctx.info.device_type == wgpu::DeviceType::Cpu;
        let fit_wanted = ctx.f64
            && match opts.fit {
                FitOn::Device => true,
                FitOn::Host => false,
                FitOn::Auto => !software,
            };
        let kernels = ctx.scoped("compiling the kernels", || {
            pipelines::Kernels::new(&ctx, kernels::kernel_specs(), fit_wanted)
        })?;
        // Where the ridge runs on the device, every refinement sends member batches (the
        // fit's, the end gaps'): their kernels compile here, on the opening thread while
        // the grid is built, instead of in the run's first fit batch.
        if fit_wanted {
            stages::Sequence::new(kernels::STAGES).prepare(&kernels, &ctx, sizes::Kind::Members)?;
        }
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
        store: Option<resources::PointStore>,
    ) -> Result<GpuEngine, EngineError> {
        let GpuDevice {
            ctx,
            kernels,
            opts,
            fit_wanted,
            software,
        } = self;
        let limits = resources::Limits::new(&ctx, &opts, grid.len());
        let members_on_host = members_on_host(&opts, software);
        let statics =
            resources::Statics::upload(&ctx, &grid, store, &limits, fit_wanted, !members_on_host)?;
        let buffers = ctx.scoped("allocating buffers", || Buffers::new(&ctx, &limits))?;
        Ok(GpuEngine {
            cpu: Box::new(super::cpu::CpuEngine::new(grid.clone())),
            small_batch: opts.small_batch,
            fit_tail: opts.fit_tail,
            members_on_host,
            cpu_batches: AtomicU64::new(0),
            cpu_queries: AtomicU64::new(0),
            device_fits: AtomicU64::new(0),
            device_fits_refitted: AtomicU64::new(0),
            device_items: AtomicU64::new(0),
            point_bytes: AtomicU64::new(0),
            host_lists: AtomicU64::new(0),
            grid,
            ctx,
            kernels,
            stages: stages::Sequence::new(kernels::STAGES),
            statics,
            opts: limits,
            buffers: Mutex::new(buffers),
            uploads: AtomicU64::new(1),
            batches: AtomicU64::new(0),
            queries: AtomicU64::new(0),
            fallbacks: AtomicU64::new(0),
            sorted_on_host: AtomicU64::new(0),
            record_batches: AtomicU64::new(0),
            callers_ns: AtomicU64::new(0),
            clock: Clock::default(),
        })
    }
}

impl GpuEngine {
    /// Opens wgpu's default adapter with the default options and uploads the grid.
    pub fn new(grid: Arc<Grid>) -> Result<Self, EngineError> {
        Self::with_options(grid, GpuOptions::default())
    }

    /// [`GpuEngine::new`] with `opts`.
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
        kernels::ROUTES
            .fit_lines
            .is_some_and(|r| self.answers(r.route.kernel))
    }

    /// The kernels this engine has compiled on first use (those of the side counts, the k
    /// nearest and the member lists; the rest compile when the device opens, and the
    /// member lists' too where the ridge runs on the device), named as
    /// `eval sides`, `eval histogram`, `eval below`, `eval members`, `cut`, `members`.
    pub fn kernels_compiled_on_use(&self) -> Vec<String> {
        self.kernels.compiled_on_use()
    }

    /// Queries answered wholly on the host; 0 on ordinary scenes.
    pub fn host_fallbacks(&self) -> u64 {
        self.fallbacks.load(Ordering::Relaxed)
    }

    /// Member lists of members batches that came back as records (the member lists and
    /// the fit on the device) and that the host sorted by id: those longer than the
    /// records kernel ranks, and those with a flagged member out of order.
    pub fn lists_sorted_on_host(&self) -> u64 {
        self.sorted_on_host.load(Ordering::Relaxed)
    }

    /// Sub-batches of members batches whose lists came back as records
    /// (`kernels/records.rs`): every one whose members fit the records' binding, where
    /// the member lists and the fit are on the device.
    pub fn record_batches(&self) -> u64 {
        self.record_batches.load(Ordering::Relaxed)
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

    /// Counts the device work of a sub-batch: `items` work items evaluated, `points`
    /// points read from the point store (16 bytes each).
    fn touched(&self, items: u64, points: u64) {
        self.device_items.fetch_add(items, Ordering::Relaxed);
        self.point_bytes.fetch_add(points * 16, Ordering::Relaxed);
    }

    fn count_batch(&self, n: usize) {
        self.batches.fetch_add(1, Ordering::Relaxed);
        self.queries.fetch_add(n as u64, Ordering::Relaxed);
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Buffers> {
        self.buffers.lock().unwrap_or_else(|p| p.into_inner())
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
            return self.on_cpu(queries.len(), || self.cpu.query(queries, ask));
        }
        let (order, sent) = self.in_order(queries);
        let ks = match ask.nearest {
            Nearest::K(k) => self.on_host(|| order.apply(k)),
            _ => Vec::new(),
        };
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

    /// Where member lists are the host's (a small batch, or [`GpuOptions::members`] on
    /// the host), the CPU engine's positions straight from the walk; otherwise the kernel
    /// of `kernels::ROUTES.axial` where there is one on this device, or the device's
    /// member lists.
    fn axial(&self, queries: &[Query]) -> Result<Vec<Vec<f64>>, EngineError> {
        if !queries.is_empty() && (queries.len() <= self.small_batch || self.members_on_host) {
            self.count_batch(queries.len());
            self.host_lists
                .fetch_add(queries.len() as u64, Ordering::Relaxed);
            return self.on_cpu(queries.len(), || self.cpu.axial(queries));
        }
        if let Some(r) = kernels::ROUTES.axial.filter(|r| self.answers(r.kernel)) {
            self.count_batch(queries.len());
            let (order, sent) = self.in_order(queries);
            let axial = (r.answer)(self, &mut self.lock(), &sent)?;
            return Ok(self.on_host(|| order.restore(axial)));
        }
        let members = self.members(queries)?;
        Ok(self.on_host(|| super::axial_of_members(&members, queries)))
    }

    /// Where the kernel of `kernels::ROUTES.extent` runs (the extent kernel: f64 and the
    /// coordinates on the device, as for the device fit) and the batch is not small, one
    /// device batch: the walk, the stats pass and the member pass, then each query's ends
    /// over its list on the device; the host reads one extent a query (and decides the
    /// flagged points). Where member lists are the host's ([`GpuOptions::members`]; its
    /// member pass is the extent's), the CPU engine's walk; without the kernel, the
    /// device's member lists.
    fn extent(&self, queries: &[Query]) -> Result<Vec<super::Extent>, EngineError> {
        if !queries.is_empty() && (queries.len() <= self.small_batch || self.members_on_host) {
            self.count_batch(queries.len());
            self.host_lists
                .fetch_add(queries.len() as u64, Ordering::Relaxed);
            return self.on_cpu(queries.len(), || self.cpu.extent(queries));
        }
        let Some(route) = kernels::ROUTES.extent.filter(|r| self.answers(r.kernel)) else {
            let members = self.members(queries)?;
            return Ok(self.on_host(|| {
                members
                    .iter()
                    .zip(queries)
                    .map(|(m, q)| super::Extent::of(m.iter().map(|m| m.t), q.seg.length()))
                    .collect()
            }));
        };
        self.count_batch(queries.len());
        let (order, sent) = self.in_order(queries);
        let ext = (route.answer)(self, &mut self.lock(), &sent)?;
        Ok(self.on_host(|| order.restore(ext)))
    }

    /// One device batch: the walk and the stats pass, a scan of the items' member counts
    /// and a member pass that writes each query's sure members contiguously; the host
    /// measures them (and decides the flagged points) in f64, as the CPU engine does.
    /// Batches of at most `small_batch` queries (a host fit's last iterations) are answered
    /// on the host, like small [`Engine::query`] batches, and so is every batch where
    /// [`GpuOptions::members`] resolved to the host (a software adapter, for the commands).
    fn members(&self, queries: &[Query]) -> Result<Vec<Vec<super::Member>>, EngineError> {
        self.count_batch(queries.len());
        if !queries.is_empty() && (queries.len() <= self.small_batch || self.members_on_host) {
            self.host_lists
                .fetch_add(queries.len() as u64, Ordering::Relaxed);
            return self.on_cpu(queries.len(), || self.cpu.members(queries));
        }
        let (order, sent) = self.in_order(queries);
        let lists = self.members_batch(&mut self.lock(), &sent)?;
        Ok(self.on_host(|| order.restore(lists)))
    }

    /// One members batch for all of `queries` (the groups in this engine's spatial order,
    /// each group's queries together), each part's lists made from the readback as it is
    /// handed out. The receiver's time is the caller's, not the engine's host time.
    fn members_in_parts(
        &self,
        queries: &[Query],
        group: usize,
        part: usize,
        f: &mut super::Parts<'_>,
    ) -> Result<(), EngineError> {
        let group = group.max(1);
        if queries.is_empty()
            || queries.len() <= self.small_batch
            || self.members_on_host
            || !queries.len().is_multiple_of(group)
        {
            return super::hand_out(self.members(queries)?, group, part, f);
        }
        self.count_batch(queries.len());
        let (sent_idx, sent) = self.on_host(|| {
            let leaders: Vec<Query> = queries.iter().step_by(group).copied().collect();
            let order = SpatialOrder::new(&self.grid, &leaders);
            let idx: Vec<usize> = (0..leaders.len())
                .flat_map(|j| {
                    let g = order.index(j) * group;
                    g..g + group
                })
                .collect();
            let sent: Vec<Query> = idx.iter().map(|&i| queries[i]).collect();
            (idx, sent)
        });
        let per = super::part_len(group, part);
        // Whole groups only: a sub-batch may end inside one, whose lists wait here.
        let (mut held_idx, mut held): (Vec<usize>, Vec<Vec<super::Member>>) =
            (Vec::new(), Vec::new());
        let mut give = |first: usize, lists: &mut [Vec<super::Member>]| {
            let idx = &sent_idx[first..first + lists.len()];
            let t = std::time::Instant::now();
            let got = if held.is_empty() && lists.len().is_multiple_of(group) {
                // A part of whole groups (all but a sub-batch's last): handed out as made.
                f(idx, lists)
            } else {
                held_idx.extend_from_slice(idx);
                held.extend(lists.iter_mut().map(std::mem::take));
                let whole = held.len() / group * group;
                let got = if whole > 0 {
                    f(&held_idx[..whole], &held[..whole])
                } else {
                    Ok(())
                };
                held_idx.drain(..whole);
                held.drain(..whole);
                got
            };
            self.callers_ns
                .fetch_add(t.elapsed().as_nanos() as u64, Ordering::Relaxed);
            got
        };
        let out = self.members_batch_parts(&mut self.lock(), &sent, per, &mut give);
        // (A batch that failed inside a part leaves its receiver's time here.)
        self.callers_ns.store(0, Ordering::Relaxed);
        out
    }

    /// With [`GpuOptions::fit`] on the device, the kernel of `kernels::ROUTES.fit_lines`
    /// where it takes the fit (the ridge: no normals, no opacity weights) and the batch has
    /// more than `small_batch` queries; otherwise [`Engine::members`] and the host's step.
    fn fit_lines(
        &self,
        queries: &[Query],
        ask: &FitAsk<'_>,
    ) -> Result<Vec<FitAnswer>, EngineError> {
        let route = self
            .fit_route(ask.spec, &ask.points)
            .filter(|_| queries.len() > self.small_batch);
        let Some(route) = route else {
            // The steps are the host's: counted as host walks wherever the device listed
            // the members (the host's own lists count themselves).
            let listed_on_host = queries.len() <= self.small_batch || self.members_on_host;
            let members = self.members(queries)?;
            if !listed_on_host {
                self.host_lists
                    .fetch_add(queries.len() as u64, Ordering::Relaxed);
            }
            let t = std::time::Instant::now();
            let out = super::fit::steps(queries, &members, ask);
            self.clock.add(t.elapsed().as_secs_f64(), 0.0);
            return Ok(out);
        };
        self.count_batch(queries.len());
        if ask.in_order {
            // The caller keeps this engine's order (the edge fit's iterations).
            return (route.answer)(self, &mut self.lock(), queries, ask);
        }
        let (order, sent) = self.on_host(|| {
            let order = SpatialOrder::new(&self.grid, queries);
            let sent = order.apply(queries);
            (order, sent)
        });
        let by_caller = &order;
        let sensitive = ask
            .sensitive
            .map(|s| move |j: usize, line: &crate::geom::fit::LineFit| s(by_caller.index(j), line));
        let warm: Vec<bool> = if ask.warm.is_empty() {
            Vec::new()
        } else {
            (0..sent.len()).map(|j| ask.warm[order.index(j)]).collect()
        };
        let ask = FitAsk {
            sensitive: sensitive.as_ref().map(|s| s as &super::Sensitive<'_>),
            warm: &warm,
            ..*ask
        };
        let answers = (route.answer)(self, &mut self.lock(), &sent, &ask)?;
        Ok(self.on_host(|| order.restore(answers)))
    }

    /// With the ridge on the device ([`GpuOptions::fit`], a fit that
    /// `kernels::ROUTES.fit_lines` takes), one batch per iteration
    /// ([`super::fit::by_batches_in`], the segments in this engine's spatial order: each
    /// batch's ridge on the device) until at most [`GpuOptions::fit_tail`] segments are
    /// still moving, which the host then takes on to the end as the CPU engine's fit
    /// does (one host batch: [`super::fit::finish_gathered`]);
    /// otherwise the CPU engine's [`Engine::fit_edges`] over the same grid (each
    /// neighbourhood gathered once), as one host batch.
    fn fit_edges(&self, job: &FitJob<'_>) -> Result<FitResult, EngineError> {
        if self.fit_route(job.spec, &job.points).is_some() {
            // The iterations' own host work (the tracks, the queries, each step's
            // advance) counts as host work too, beside the batches' (counted inside).
            let t = std::time::Instant::now();
            let (h0, d0) = GpuEngine::seconds(self);
            let order = |s: &[crate::geom::Segment]| SpatialOrder::of_segments(&self.grid, s);
            // The last iterations' few segments: the host's, counted as host batches and
            // walks (a step a query, as for the CPU engine's fit below).
            let finish = |job: &FitJob<'_>, rest: &mut [crate::geom::fit::Track]| {
                self.count_batch(0);
                let steps = self.on_cpu(0, || super::fit::finish_gathered(&self.grid, job, rest));
                self.host_steps(steps);
                Ok(())
            };
            let tail = super::fit::Tail {
                at_most: self.fit_tail,
                finish: &finish,
            };
            let tail = (self.fit_tail > 0).then_some(&tail);
            let out = super::fit::by_batches_in(self, job, Some(&order), tail);
            let (h1, d1) = GpuEngine::seconds(self);
            let own = t.elapsed().as_secs_f64() - (h1 - h0) - (d1 - d0);
            self.clock.add(own.max(0.0), 0.0);
            return out;
        }
        self.count_batch(0);
        let before = self.cpu.counters().queries;
        let out = self.on_cpu(0, || self.cpu.fit_edges(job))?;
        self.host_steps(self.cpu.counters().queries - before);
        Ok(out)
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
            device_items: self.device_items.load(Ordering::Relaxed),
            point_bytes: self.point_bytes.load(Ordering::Relaxed),
            host_lists: self.host_lists.load(Ordering::Relaxed),
        }
    }

    fn seconds(&self) -> Option<(f64, f64)> {
        Some(GpuEngine::seconds(self))
    }
}

/// Whether member lists are the host's ([`GpuOptions::members`]; `auto`: on a software
/// adapter).
fn members_on_host(opts: &GpuOptions, software: bool) -> bool {
    match opts.members {
        MembersOn::Device => false,
        MembersOn::Host => true,
        MembersOn::Auto => software,
    }
}

impl GpuEngine {
    /// Whether list kernel `l` answers on this device: compiled (f64 in shaders, the
    /// device fit wanted) and the centers' coordinates uploaded.
    fn answers(&self, l: &pipelines::ListKernel) -> bool {
        self.kernels.compiled(l.spec).is_some() && self.statics.world.is_some()
    }

    /// The route of the edge fit's ridge where its kernel answers on this device and
    /// takes the fit of `spec` over `points`.
    fn fit_route(
        &self,
        spec: &FitSpec,
        points: &FitPoints<'_>,
    ) -> Option<&'static pipelines::Route<pipelines::FitLinesFn>> {
        kernels::ROUTES
            .fit_lines
            .filter(|r| self.answers(r.route.kernel) && (r.takes)(self, spec, points))
            .map(|r| &r.route)
    }

    /// The CPU engine's members of `q` (the host's walk), for a query the device leaves
    /// to the host.
    fn cpu_members(&self, q: &Query) -> Vec<super::Member> {
        // The CPU engine answers every batch (its `members` cannot fail).
        let lists = self.cpu.members(std::slice::from_ref(q));
        lists.ok().and_then(|mut l| l.pop()).unwrap_or_default()
    }

    /// The CPU engine's extent of `q` (the host's walk).
    fn cpu_extent(&self, q: &Query) -> super::Extent {
        // As [`Self::cpu_members`].
        let e = self.cpu.extent(std::slice::from_ref(q));
        e.ok().and_then(|mut e| e.pop()).unwrap_or_default()
    }

    /// Counts `steps` edge-fit steps taken on the host: each a query answered there, whose
    /// members the host walked.
    fn host_steps(&self, steps: u64) {
        self.queries.fetch_add(steps, Ordering::Relaxed);
        self.cpu_queries.fetch_add(steps, Ordering::Relaxed);
        self.host_lists.fetch_add(steps, Ordering::Relaxed);
    }

    /// `f()`, its time counted as the engine's host work (`host_seconds`).
    fn on_host<R>(&self, f: impl FnOnce() -> R) -> R {
        let t = std::time::Instant::now();
        let out = f();
        self.clock.add(t.elapsed().as_secs_f64(), 0.0);
        out
    }

    /// A batch of `n` queries that the CPU engine's code answers on the host (`f`),
    /// counted as such (`cpu_batches`, `cpu_queries`) and as host work.
    fn on_cpu<R>(&self, n: usize, f: impl FnOnce() -> R) -> R {
        self.cpu_batches.fetch_add(1, Ordering::Relaxed);
        self.cpu_queries.fetch_add(n as u64, Ordering::Relaxed);
        self.on_host(f)
    }

    /// The order the device gets `queries` in, and the queries in it; the ordering is
    /// host work of the batch (`host_seconds`).
    fn in_order(&self, queries: &[Query]) -> (SpatialOrder, Vec<Query>) {
        self.on_host(|| {
            let order = SpatialOrder::new(&self.grid, queries);
            let sent = order.apply(queries);
            (order, sent)
        })
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
