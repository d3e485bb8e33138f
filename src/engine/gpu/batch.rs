//! One batch on the device: the kernels' pipelines, the buffers uploaded once and those
//! reused between batches, and `submit`, which records the whole chain (walk, scan, emit,
//! evaluate, reduce) in one command buffer, submits it and reads back one staging buffer.

use super::device::{self, Context, Reusable};
use super::layout::*;
use super::GpuOptions;
use crate::engine::{CylStats, EngineError, Query};
use crate::geom::p64;
use crate::index::Grid;
use glam::DVec3;
use rayon::prelude::*;
use std::sync::OnceLock;

/// What a batch asks of the evaluation kernel.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Kind {
    /// Counts and sums (and side counts); with `cover`, the coverage mask too.
    Stats {
        sides: bool,
        cover: bool,
    },
    Nearest,
    /// The members: each query's sure members' sorted indices (and the flagged points).
    Members,
    /// The edge fit's ridge of each query (`fit.wgsl`) over its sure members, left on the
    /// device (and the flagged points).
    Fit,
}

impl Kind {
    /// Whether the batch lists each query's members on the device.
    fn lists(self) -> bool {
        matches!(self, Kind::Members | Kind::Fit)
    }
}

/// The sizes the engine works within, from the options and the device.
pub struct Limits {
    /// Points per part of the point store.
    pub part_len: u32,
    /// The device's own binding limit (cell table, coverage mask).
    pub device_binding: u64,
    pub item_max: u32,
    pub flag_max: u32,
    /// Most entries of a members batch's member list.
    pub member_max: u32,
    pub max_queries: usize,
    pub max_x: u32,
}

impl Limits {
    pub fn new(ctx: &Context, opts: &GpuOptions, _n_points: usize) -> Limits {
        let device_binding = ctx
            .limits
            .max_storage_buffer_binding_size
            .min(ctx.limits.max_buffer_size);
        let binding = opts
            .max_binding_bytes
            .unwrap_or(u64::MAX)
            .min(device_binding);
        let part_len = (binding / 16).clamp(1, u32::MAX as u64 / 2) as u32;
        let item_max = (opts.max_items as u64)
            .min(device_binding / std::mem::size_of::<Partial>() as u64)
            .clamp(1, 1 << 28) as u32;
        let flag_max = ((device_binding / 4 - CTL_HEAD as u64) / 2).min(1 << 30) as u32;
        let per_query = (NBINS as u64 * 4).max(std::mem::size_of::<GQuery>() as u64);
        let max_queries = opts
            .max_queries
            .min((device_binding / per_query) as usize)
            .clamp(1, 1 << 22);
        // Half the binding: the staging buffer holds the list and the per-query results.
        let member_max = (device_binding / 8).clamp(1, 1 << 30) as u32;
        Limits {
            part_len,
            device_binding,
            item_max,
            flag_max,
            member_max,
            max_queries,
            max_x: opts.max_workgroups_x.max(1),
        }
    }
}

pub struct Kernels {
    /// The grid walk's count and emit passes ([`super::walk_source`]).
    walk_count: wgpu::ComputePipeline,
    walk_emit: wgpu::ComputePipeline,
    scan: wgpu::ComputePipeline,
    scan_add: wgpu::ComputePipeline,
    args: wgpu::ComputePipeline,
    /// One evaluation pipeline per mode and coverage switch ([`EVAL_VARIANTS`]), each
    /// compiled with both as constants ([`super::eval_source`]): the plain stats modes
    /// (every evaluation, outlier test, crop and merge) when the device opens, the others
    /// (sides, k nearest, member lists) on first use, like the k-nearest cut and the member
    /// lists' gather and scatter: a run that never asks for them never compiles them.
    eval: Vec<OnceLock<wgpu::ComputePipeline>>,
    cut: OnceLock<wgpu::ComputePipeline>,
    reduce: wgpu::ComputePipeline,
    gather: OnceLock<wgpu::ComputePipeline>,
    scatter: OnceLock<wgpu::ComputePipeline>,
    /// The edge fit's ridge, in f64: only on a device with `SHADER_F64`.
    pub fit: Option<wgpu::ComputePipeline>,
}

impl Kernels {
    /// Compiles every kernel; the fit kernel only with `fit` (and f64 on the device).
    pub fn new(ctx: &Context, fit: bool) -> Kernels {
        let k = |name: &str, src: &str, entry: &str| {
            ctx.pipeline(name, &super::kernel_source(src), entry)
        };
        let scan = include_str!("../../../shaders/scan.wgsl");
        Kernels {
            walk_count: ctx.pipeline("walk count", &super::walk_source(false), "main"),
            walk_emit: ctx.pipeline("walk emit", &super::walk_source(true), "main"),
            scan: k("scan", scan, "main"),
            scan_add: k("scan add", scan, "add"),
            args: k("args", include_str!("../../../shaders/args.wgsl"), "main"),
            eval: EVAL_VARIANTS
                .iter()
                .map(|&(m, c)| {
                    let cell = OnceLock::new();
                    if m == MODE_STATS {
                        let _ = cell.set(ctx.pipeline("eval", &super::eval_source(m, c), "main"));
                    }
                    cell
                })
                .collect(),
            cut: OnceLock::new(),
            reduce: k(
                "reduce",
                include_str!("../../../shaders/reduce.wgsl"),
                "main",
            ),
            gather: OnceLock::new(),
            scatter: OnceLock::new(),
            // In its own error scope: a driver that offers f64 but cannot compile the
            // kernel costs the device fit (the host's step takes over), not the engine.
            fit: (fit && ctx.f64)
                .then(|| {
                    ctx.scoped("compiling the fit kernel", || {
                        ctx.pipeline("fit", &super::fit_source(), "main")
                    })
                    .ok()
                })
                .flatten(),
        }
    }
}

/// The evaluation kernel's variants, each its own pipeline: (mode, coverage bits).
pub const EVAL_VARIANTS: [(u32, bool); 7] = [
    (MODE_STATS, false),
    (MODE_STATS, true),
    (MODE_STATS_SIDES, false),
    (MODE_STATS_SIDES, true),
    (MODE_HIST, false),
    (MODE_BELOW, false),
    (MODE_MEMBERS, false),
];

impl Kernels {
    /// The evaluation pipeline of `mode` (coverage bits only in the stats modes),
    /// compiled now if this is its first use.
    fn eval(
        &self,
        ctx: &Context,
        mode: u32,
        cover: bool,
    ) -> Result<&wgpu::ComputePipeline, EngineError> {
        let cover = cover && (mode == MODE_STATS || mode == MODE_STATS_SIDES);
        let i = EVAL_VARIANTS
            .iter()
            .position(|&v| v == (mode, cover))
            .expect("an evaluation variant");
        lazy(&self.eval[i], ctx, "compiling an evaluation kernel", || {
            ctx.pipeline("eval", &super::eval_source(mode, cover), "main")
        })
    }

    /// The k-nearest cut (nearest batches).
    fn cut(&self, ctx: &Context) -> Result<&wgpu::ComputePipeline, EngineError> {
        lazy(&self.cut, ctx, "compiling the cut kernel", || {
            let src = super::kernel_source(include_str!("../../../shaders/cut.wgsl"));
            ctx.pipeline("cut", &src, "main")
        })
    }

    /// The member lists' gather and scatter of the items' counts (members batches).
    fn members(
        &self,
        ctx: &Context,
    ) -> Result<(&wgpu::ComputePipeline, &wgpu::ComputePipeline), EngineError> {
        let src = || super::kernel_source(include_str!("../../../shaders/members.wgsl"));
        let gather = lazy(&self.gather, ctx, "compiling the members kernels", || {
            ctx.pipeline("members gather", &src(), "gather")
        })?;
        let scatter = lazy(&self.scatter, ctx, "compiling the members kernels", || {
            ctx.pipeline("members scatter", &src(), "scatter")
        })?;
        Ok((gather, scatter))
    }

    /// The kernels compiled on first use that have been so far: `eval sides`, `eval sides
    /// cover`, `eval histogram`, `eval below`, `eval members`, `cut`, `members`.
    pub fn compiled_on_use(&self) -> Vec<String> {
        let mut out: Vec<String> = EVAL_VARIANTS
            .iter()
            .zip(&self.eval)
            .filter(|(&(m, _), cell)| m != MODE_STATS && cell.get().is_some())
            .map(|(&(m, c), _)| {
                let mode = match m {
                    MODE_STATS_SIDES => "sides",
                    MODE_HIST => "histogram",
                    MODE_BELOW => "below",
                    _ => "members",
                };
                format!("eval {mode}{}", if c { " cover" } else { "" })
            })
            .collect();
        if self.cut.get().is_some() {
            out.push("cut".into());
        }
        if self.gather.get().is_some() && self.scatter.get().is_some() {
            out.push("members".into());
        }
        out
    }
}

/// The pipeline in `cell`, compiled by `make` (in its own error scope) on first use.
fn lazy<'a>(
    cell: &'a OnceLock<wgpu::ComputePipeline>,
    ctx: &Context,
    what: &str,
    make: impl FnOnce() -> wgpu::ComputePipeline,
) -> Result<&'a wgpu::ComputePipeline, EngineError> {
    if let Some(p) = cell.get() {
        return Ok(p);
    }
    let p = ctx.scoped(what, make)?;
    Ok(cell.get_or_init(|| p))
}

/// What lives on the device for the engine's whole life.
pub struct Statics {
    cell_start: wgpu::Buffer,
    cell_bytes: u64,
    pub parts: Vec<(wgpu::Buffer, u64)>,
    dims: [u32; 3],
    /// The sorted centers' own f32 coordinates (3 words each), for the fit kernel's f64
    /// geometry; uploaded only for the device fit, and only when one binding holds them.
    pub world: Option<(wgpu::Buffer, u64)>,
}

/// The point store's contents: every sorted center as its offset from its own cell's
/// corner in cell units (computed in f64, so the f32 keeps ~1e-7 of a cell) and its cell's
/// x index. Needs the grid, not the device: [`crate::engine::select`] computes it while the
/// device is still opening.
pub struct PointStore {
    /// The grid it was computed from.
    grid: std::sync::Weak<Grid>,
    rel: Vec<[f32; 4]>,
}

impl PointStore {
    pub fn of(grid: &std::sync::Arc<Grid>) -> PointStore {
        let mut rel = vec![[0f32; 4]; grid.points.len()];
        rel.par_chunks_mut(STORE_RUN)
            .enumerate()
            .for_each(|(k, run)| store_run(grid, k * STORE_RUN, run));
        PointStore {
            grid: std::sync::Arc::downgrade(grid),
            rel,
        }
    }
}

/// Points per piece of the point store computed at once (64 KiB: a piece is written to
/// the staging memory from a reused buffer that stays in cache).
const STORE_RUN: usize = 4096;

/// The point store's entries of the sorted points `start..start + out.len()`. Each point's
/// cell is the one whose range of the cell table holds it (the cell the grid sorted it
/// into), found once per piece and then stepped, so the cost is the offsets' arithmetic.
fn store_run(grid: &Grid, start: usize, out: &mut [[f32; 4]]) {
    let (dx, dy) = (grid.dims[0], grid.dims[1]);
    let inv = 1.0 / grid.cell;
    let starts = &grid.cell_start;
    // The last cell whose range begins at or before `start`: the cell holding it.
    let mut c = starts.partition_point(|&s| s as usize <= start) - 1;
    let mut cell = None;
    for (j, slot) in out.iter_mut().enumerate() {
        let i = start + j;
        while starts[c + 1] as usize <= i {
            c += 1;
            cell = None;
        }
        let (x, o) = *cell.get_or_insert_with(|| {
            let (x, t) = (c as u32 % dx, c as u32 / dx);
            (x, grid.cell_origin(x, t % dy, t / dy))
        });
        let r = (p64(grid.points[i]) - o) * inv;
        // w: the cell's x index mod 2^16 (exact in f32), for the kernels to move the point
        // into a neighbouring cell's frame.
        *slot = [r.x as f32, r.y as f32, r.z as f32, (x & 0xFFFF) as f32];
    }
}

/// The point store's entries of the sorted points `first..` written straight into `dst`
/// (the upload's staging memory), piece by piece in parallel: no store of its own.
fn write_store(grid: &Grid, dst: wgpu::WriteOnly<'_, [u8]>, first: usize) {
    const PIECE: usize = STORE_RUN * 16;
    let (whole, tail) = dst.into_chunks::<PIECE>();
    let pieces: Vec<wgpu::WriteOnly<'_, [u8; PIECE]>> = whole.into_iter().collect();
    let n_whole = pieces.len();
    let write = |buf: &mut Vec<[f32; 4]>, k: usize, mut piece: wgpu::WriteOnly<'_, [u8]>| {
        let run = &mut buf[..piece.len() / 16];
        store_run(grid, first + k * STORE_RUN, run);
        piece.copy_from_slice(bytemuck::cast_slice(run));
    };
    pieces.into_par_iter().enumerate().for_each_init(
        || vec![[0f32; 4]; STORE_RUN],
        |buf, (k, piece)| write(buf, k, piece.into()),
    );
    if !tail.is_empty() {
        write(&mut vec![[0f32; 4]; STORE_RUN], n_whole, tail);
    }
}

impl Statics {
    /// Uploads the cell table and the point store (computed now unless given for this
    /// very grid); with `world`, also the centers' own coordinates where one binding holds
    /// them.
    pub fn upload(
        ctx: &Context,
        grid: &std::sync::Arc<Grid>,
        store: Option<PointStore>,
        lim: &Limits,
        world: bool,
    ) -> Result<Statics, EngineError> {
        let cell_bytes = (grid.cell_start.len() * 4) as u64;
        if cell_bytes > lim.device_binding {
            return Err(EngineError::Gpu(format!(
                "the grid's cell table ({cell_bytes} bytes) is above the device's binding limit"
            )));
        }
        // A store computed for another grid is not used (computed here instead).
        let given = match store {
            Some(s) if std::ptr::eq(s.grid.as_ptr(), std::sync::Arc::as_ptr(grid)) => Some(s.rel),
            _ => None,
        };
        // The bytes of `src` at the start of `dst`.
        let copy = |mut dst: wgpu::WriteOnly<'_, [u8]>, src: &[u8]| {
            dst.slice(..src.len()).copy_from_slice(src)
        };
        ctx.scoped("uploading the Gaussians", || {
            let storage = wgpu::BufferUsages::STORAGE;
            let cell_start = ctx.filled_buffer("cell_start", cell_bytes, |dst| {
                copy(dst, bytemuck::cast_slice(&grid.cell_start))
            });
            let mut parts = Vec::new();
            let n = grid.points.len();
            let part_len = lim.part_len as usize;
            for first in (0..n).step_by(part_len) {
                let len = part_len.min(n - first);
                let bytes = (len * 16) as u64;
                // Computed straight into the buffer or the staging memory unless given.
                let buf = ctx.filled_buffer("points", bytes, |dst| match &given {
                    Some(rel) => copy(dst, bytemuck::cast_slice(&rel[first..first + len])),
                    None => write_store(grid, dst, first),
                });
                parts.push((buf, bytes));
            }
            if parts.is_empty() {
                parts.push((ctx.buffer("points", 16, storage), 16));
            }
            let world_bytes = (grid.points.len() * 12).max(12) as u64;
            let world = (world && world_bytes <= lim.device_binding).then(|| {
                let buf = ctx.filled_buffer("world", world_bytes, |dst| {
                    copy(dst, bytemuck::cast_slice(&grid.points))
                });
                (buf, world_bytes)
            });
            ctx.queue.submit([]);
            Statics {
                cell_start,
                cell_bytes,
                parts,
                world,
                dims: grid.dims,
            }
        })
    }
}

/// Per-batch buffers, reused and grown across batches, with the capacities learnt.
pub struct Buffers {
    params: Reusable,
    queries: Reusable,
    scan: Reusable,
    items: Reusable,
    partials: Reusable,
    results: Reusable,
    ctl: Reusable,
    indirect: Reusable,
    /// The k-nearest histograms, or the coverage mask.
    aux: Reusable,
    plans: Reusable,
    /// Members batches: the scan of the items' member counts, and the member list.
    mscan: Reusable,
    members: Reusable,
    /// Fit batches: the queries' frames and the ridges.
    fitq: Reusable,
    fitout: Reusable,
    staging: Reusable,
    /// Bytes of the coverage mask in `aux` (set by `clear_mask`).
    aux_len: u64,
    item_cap: u32,
    /// Whether `item_cap` was sized for a first batch ([`submit`]).
    sized: bool,
    flag_cap: u32,
    member_cap: u32,
}

impl Buffers {
    /// See [`super::GpuEngine::item_capacity`].
    pub fn item_cap(&self) -> u32 {
        self.item_cap
    }

    pub fn new(_ctx: &Context, lim: &Limits) -> Buffers {
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        Buffers {
            params: Reusable::new("params", wgpu::BufferUsages::UNIFORM),
            queries: Reusable::new("queries", storage),
            scan: Reusable::new("scan", storage),
            items: Reusable::new("items", storage),
            partials: Reusable::new("partials", storage),
            results: Reusable::new("results", storage),
            ctl: Reusable::new("ctl", storage),
            indirect: Reusable::new(
                "indirect",
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT,
            ),
            aux: Reusable::new("aux", storage),
            plans: Reusable::new("plans", storage),
            mscan: Reusable::new("mscan", storage),
            members: Reusable::new("members", storage),
            fitq: Reusable::new("fitq", storage),
            fitout: Reusable::new("fitout", storage),
            staging: Reusable::new("staging", wgpu::BufferUsages::MAP_READ),
            aux_len: 4,
            item_cap: lim.item_max.min(1 << 16),
            sized: false,
            flag_cap: lim.flag_max.min(1 << 14),
            member_cap: lim.member_max.min(1 << 16),
        }
    }
}

/// One sub-batch's answers: per query its result (and k-nearest plan), and the flagged
/// points as (query slot | kind, sorted point index), sorted. A members batch also has
/// the sure members' sorted indices, query after query (`results[i].count` each, none for
/// a query answered on the host), and `bad` when the device miscounted them.
#[derive(Default)]
pub struct Output {
    pub results: Vec<QResult>,
    pub plans: Vec<Plan>,
    pub flags: Vec<(u32, u32)>,
    pub members: Vec<u32>,
    pub bad: bool,
    /// A fit batch's ridges, one per query.
    pub fits: Vec<FitOut>,
}

impl Output {
    /// `n` queries for the host to answer.
    pub fn host_only(n: usize) -> Output {
        Output {
            results: vec![
                QResult {
                    status: STATUS_HOST,
                    ..Default::default()
                };
                n
            ],
            ..Default::default()
        }
    }
}

pub enum Attempt {
    /// The output and the seconds spent waiting for the device.
    Done(Output, f64),
    /// The sub-batch needs more items or flags than one submit may hold.
    TooLarge(f64),
}

/// The f32 error bounds of the kernels for a query of axial length `len` and radius `r`
/// (cell units). The axis point a kernel starts from is accurate to a few roundings of
/// its own size (a few cells); the caps carry the rounding of `len` and of `len - t`, and
/// the direction's rounding over the length: all within 2 roundings of relative 2^-24 of
/// `len + 2 r + 8`, and the bound allows 8. A squared distance of at most `(r + eps)^2`
/// then errs by at most `4 eps (r + eps)` plus its own rounding.
pub fn error_bounds(len: f64, r: f64) -> (f64, f64) {
    let eps = (len + 2.0 * r + 8.0) * (2f64).powi(-21);
    let e2 = 4.0 * eps * (r + eps) + r * r * (2f64).powi(-20);
    (eps, e2)
}

/// `x` with its 12 leading significant bits (toward zero), as the kernels' `bits12`.
fn bits12(x: f32) -> f32 {
    f32::from_bits(x.to_bits() & 0xFFFF_F000)
}

/// The `e2` bound the kernels use for `q` (cell units, as rounded to f32).
pub fn e2_of(grid: &Grid, q: &Query) -> f64 {
    let inv = 1.0 / grid.cell;
    error_bounds(q.seg.length() * inv, q.r * inv).1 as f32 as f64
}

/// Cells from the grid's origin beyond which a query goes to the host (f32 integers stay
/// exact far beyond).
const FAR: f64 = (1u64 << 22) as f64;

fn gquery(grid: &Grid, q: &Query, k: u64) -> GQuery {
    let s = &q.seg;
    let valid = !grid.is_empty()
        && s.is_valid()
        && s.p1.is_finite()
        && s.p2.is_finite()
        && q.r.is_finite()
        && q.r >= 0.0
        && q.plane.is_finite();
    if !valid {
        return GQuery {
            r2: -1.0,
            ..Default::default()
        };
    }
    let inv = 1.0 / grid.cell;
    let a = (s.p1 - grid.origin) * inv;
    if a.abs().max_element() > FAR || s.length() * inv > FAR {
        // Integer cells beyond f32's exact range: the host answers the query.
        return GQuery {
            r2: -2.0,
            ..Default::default()
        };
    }
    let i = a.floor();
    let f = (a - i).as_vec3();
    let d = s.dir();
    let df = d.as_vec3();
    let dh =
        glam::Vec3::new(bits12(df.x.abs()), bits12(df.y.abs()), bits12(df.z.abs())) * df.signum();
    let dl = (d - dh.as_dvec3()).as_vec3();
    let len = s.length() * inv;
    let r = q.r * inv;
    let (eps, e2) = error_bounds(len, r);
    GQuery {
        ix: i.x as i32,
        iy: i.y as i32,
        iz: i.z as i32,
        len: len as f32,
        fx: f.x,
        fy: f.y,
        fz: f.z,
        r2: (r * r) as f32,
        dx: df.x,
        dy: df.y,
        dz: df.z,
        mid: ((q.plane - s.p1).dot(d) * inv) as f32,
        dhx: dh.x,
        dhy: dh.y,
        dhz: dh.z,
        r: r as f32,
        dlx: dl.x,
        dly: dl.y,
        dlz: dl.z,
        eps: eps as f32,
        e2: e2 as f32,
        k: k.min(u32::MAX as u64) as u32,
        pad0: 0,
        pad1: 0,
    }
}

/// A query's device result in scene units.
pub fn stats_of(r: &QResult, cell: f64) -> CylStats {
    let pair = |a: f32, b: f32| a as f64 + b as f64;
    CylStats {
        count: r.count as u64,
        side_pos: r.side as u64,
        sum_d2: pair(r.d2, r.d2_c) * cell * cell,
        sum_offset: DVec3::new(pair(r.ox, r.ox_c), pair(r.oy, r.oy_c), pair(r.oz, r.oz_c)) * cell,
    }
}

/// Levels of the prefix scan over `n` counts: (base, elements, block sums) each, and the
/// index of the grand total and the scan buffer's length.
fn scan_levels(n: u32) -> (Vec<(u32, u32, u32)>, u32, u32) {
    let mut levels = Vec::new();
    let (mut base, mut len) = (0u32, n);
    loop {
        let blocks = len.div_ceil(SCAN_WG).max(1);
        let sums = base + len;
        levels.push((base, len, sums));
        if blocks == 1 {
            return (levels, sums, sums + 1);
        }
        base = sums;
        len = blocks;
    }
}

/// Work items per query that [`submit`] makes room for in the engine's first batch (the
/// bench scene's evaluation, a refinement's first batch, needs 17 a query).
const ITEMS_PER_QUERY_GUESS: u64 = 24;

fn grow(need: u32, max: u32) -> u32 {
    (need as u64 + need as u64 / 4 + 64).min(max as u64) as u32
}

/// Records, submits and reads back one sub-batch of `kind`; reruns it with larger item
/// or flag buffers when the first try did not fit.
#[allow(clippy::too_many_arguments)]
pub fn submit(
    ctx: &Context,
    k: &Kernels,
    st: &Statics,
    lim: &Limits,
    grid: &Grid,
    b: &mut Buffers,
    kind: Kind,
    qs: &[Query],
    ks: &[u64],
    fit: &[FitQuery],
) -> Result<Attempt, EngineError> {
    let n = qs.len();
    if n == 0 {
        return Ok(Attempt::Done(Output::default(), 0.0));
    }
    let gq: Vec<GQuery> = qs
        .par_iter()
        .enumerate()
        .with_min_len(256)
        .map(|(i, q)| gquery(grid, q, ks.get(i).copied().unwrap_or(0)))
        .collect();
    let mut waited = 0.0;
    let mut rerun = false;
    // The engine's first batch starts from a guess from its size, so that it does not
    // learn the capacity by a rerun (a count walk, its scan and reduction, and a round
    // trip for nothing). Later batches start from what the earlier ones needed: a
    // guess above that would grow the buffers, and wgpu clears a new buffer before its
    // first use.
    if !b.sized {
        let guess = (n as u64 * ITEMS_PER_QUERY_GUESS).min(lim.item_max as u64) as u32;
        b.item_cap = b.item_cap.max(guess);
        b.sized = true;
    }
    let member_max = lim.member_max;
    b.member_cap = b.member_cap.min(member_max);
    loop {
        let (out, w, total, n_flags, n_members) =
            attempt(ctx, k, st, lim, b, kind, &gq, fit, rerun)?;
        rerun = true;
        waited += w;
        let mut again = false;
        if kind.lists() && total > member_scan_max(lim) {
            return Ok(Attempt::TooLarge(waited));
        }
        if total > b.item_cap {
            if total > lim.item_max {
                return Ok(Attempt::TooLarge(waited));
            }
            b.item_cap = grow(total, lim.item_max);
            again = true;
        } else if n_members > b.member_cap as u64 {
            // (Counted only when every item was evaluated.)
            if n_members > member_max as u64 {
                return Ok(Attempt::TooLarge(waited));
            }
            b.member_cap = grow(n_members as u32, member_max);
            again = true;
        }
        if n_flags > b.flag_cap {
            if n_flags > lim.flag_max {
                return Ok(Attempt::TooLarge(waited));
            }
            b.flag_cap = grow(n_flags, lim.flag_max);
            again = true;
        }
        if !again {
            return Ok(Attempt::Done(out, waited));
        }
    }
}

/// Most items a members batch may scan: one scan level within `max_x` workgroups.
fn member_scan_max(lim: &Limits) -> u32 {
    SCAN_WG.saturating_mul(lim.max_x)
}

fn slot(buf: &wgpu::Buffer, i: usize) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer: buf,
        offset: i as u64 * PARAMS_SLOT,
        size: std::num::NonZeroU64::new(std::mem::size_of::<Params>() as u64),
    })
}

/// One try: returns the output, the wait, the items needed, the flags raised and (a
/// members batch) the members found. A
/// `rerun` starts from the sizing of the dispatches: the count walk and the scan of the
/// try before are still in their buffers (whose sizes depend only on the queries).
#[allow(clippy::too_many_arguments)]
fn attempt(
    ctx: &Context,
    k: &Kernels,
    st: &Statics,
    lim: &Limits,
    b: &mut Buffers,
    kind: Kind,
    gq: &[GQuery],
    fit: &[FitQuery],
    rerun: bool,
) -> Result<(Output, f64, u32, u32, u64), EngineError> {
    let n = gq.len() as u32;
    let item_cap = b.item_cap;
    let flag_cap = b.flag_cap;
    let member_cap = b.member_cap;
    let (levels, total_idx, scan_len) = scan_levels(n);
    let nearest = kind == Kind::Nearest;
    let members = kind.lists();
    let fitting = kind == Kind::Fit;
    // The items' member counts are scanned over the buffer's capacity (the total is on
    // the device); entries past the total do not change the offsets before it.
    let (mlevels, _, mscan_len) = scan_levels(item_cap.min(member_scan_max(lim)));
    let mscan_bytes = if members { mscan_len as u64 * 4 } else { 4 };
    let mem_bytes = member_cap as u64 * 4;
    let fitq_bytes = n as u64 * std::mem::size_of::<FitQuery>() as u64;
    let fitout_bytes = n as u64 * std::mem::size_of::<FitOut>() as u64;

    // Sizes of everything bound.
    let q_bytes = n as u64 * std::mem::size_of::<GQuery>() as u64;
    let scan_bytes = scan_len as u64 * 4;
    let item_bytes = item_cap as u64 * std::mem::size_of::<Item>() as u64;
    let part_bytes = item_cap as u64 * std::mem::size_of::<Partial>() as u64;
    let res_bytes = n as u64 * std::mem::size_of::<QResult>() as u64;
    let ctl_bytes = (CTL_HEAD as u64 + 2 * flag_cap as u64) * 4;
    let hist_bytes = n as u64 * NBINS as u64 * 4;
    let plan_bytes = n as u64 * std::mem::size_of::<Plan>() as u64;

    // The uniform slots, one per dispatch, in recording order.
    let base = Params {
        n,
        dims_x: st.dims[0],
        dims_y: st.dims[1],
        dims_z: st.dims[2],
        part_len: lim.part_len,
        item_cap,
        flag_cap,
        max_x: lim.max_x,
        total: total_idx,
        cover: matches!(kind, Kind::Stats { cover: true, .. }) as u32,
        member_cap,
        ..Default::default()
    };
    let mut slots: Vec<Params> = Vec::new();
    let mut push = |p: Params| {
        slots.push(p);
        slots.len() - 1
    };
    let walk_count = push(Params {
        mode: MODE_COUNT,
        ..base
    });
    let walk_emit = push(Params {
        mode: MODE_EMIT,
        ..base
    });
    // The uniform of each level of a multi-level scan.
    let scan_params = |levels: &[(u32, u32, u32)]| -> Vec<Params> {
        levels
            .iter()
            .map(|&(b0, len, sums)| Params {
                n: len,
                base: b0,
                sums,
                ..base
            })
            .collect()
    };
    let scan_slots: Vec<usize> = scan_params(&levels).into_iter().map(&mut push).collect();
    let args_slot = push(base);
    let eval_mode = match kind {
        Kind::Stats { sides: false, .. } | Kind::Members | Kind::Fit => MODE_STATS,
        Kind::Stats { sides: true, .. } => MODE_STATS_SIDES,
        Kind::Nearest => MODE_HIST,
    };
    let part_slots = |mode: u32, push: &mut dyn FnMut(Params) -> usize| -> Vec<usize> {
        (0..st.parts.len())
            .map(|p| {
                push(Params {
                    mode,
                    part: p as u32,
                    part_base: p as u32 * lim.part_len,
                    ..base
                })
            })
            .collect()
    };
    let eval_slots = part_slots(eval_mode, &mut push);
    let below_slots = if nearest {
        part_slots(MODE_BELOW, &mut push)
    } else {
        Vec::new()
    };
    let (gather_slot, mscan_slots, member_slots) = if members {
        let g = push(base);
        let levels: Vec<usize> = scan_params(&mlevels).into_iter().map(&mut push).collect();
        (g, levels, part_slots(MODE_MEMBERS, &mut push))
    } else {
        (0, Vec::new(), Vec::new())
    };
    let cut_slot = push(base);
    let reduce_slot = push(base);
    let fit_slot = push(base);
    let mut uniform = vec![0u8; slots.len() * PARAMS_SLOT as usize];
    for (i, p) in slots.iter().enumerate() {
        let at = i * PARAMS_SLOT as usize;
        uniform[at..at + std::mem::size_of::<Params>()].copy_from_slice(bytemuck::bytes_of(p));
    }

    let params = b.params.get(ctx, uniform.len() as u64).clone();
    ctx.queue.write_buffer(&params, 0, &uniform);
    let queries = b.queries.get(ctx, q_bytes).clone();
    if !rerun {
        ctx.queue
            .write_buffer(&queries, 0, bytemuck::cast_slice(gq));
    }
    let scan = b.scan.get(ctx, scan_bytes).clone();
    let items = b.items.get(ctx, item_bytes).clone();
    let partials = b.partials.get(ctx, part_bytes).clone();
    let results = b.results.get(ctx, res_bytes).clone();
    let ctl = b.ctl.get(ctx, ctl_bytes).clone();
    let indirect = b.indirect.get(ctx, 24).clone();
    let aux_bytes = match kind {
        Kind::Nearest => hist_bytes,
        Kind::Stats { cover: true, .. } => b.aux_len,
        Kind::Stats { cover: false, .. } => 4,
        Kind::Members | Kind::Fit => mem_bytes,
    };
    // A members batch's list takes the place of the histograms or the mask.
    let aux = if members {
        b.members.get(ctx, aux_bytes).clone()
    } else {
        b.aux.get(ctx, aux_bytes).clone()
    };
    let mscan = b.mscan.get(ctx, mscan_bytes).clone();
    let (fitq, fitout) = if fitting {
        let q = b.fitq.get(ctx, fitq_bytes).clone();
        if !rerun {
            ctx.queue.write_buffer(&q, 0, bytemuck::cast_slice(fit));
        }
        (Some(q), Some(b.fitout.get(ctx, fitout_bytes).clone()))
    } else {
        (None, None)
    };
    let plans = b.plans.get(ctx, plan_bytes.max(16)).clone();
    let staging_bytes = res_bytes
        + ctl_bytes
        + if nearest { plan_bytes } else { 0 }
        + match kind {
            Kind::Members => mem_bytes,
            Kind::Fit => fitout_bytes,
            _ => 0,
        };
    let staging = b.staging.get(ctx, staging_bytes).clone();

    let h = device::head;
    let cells = h(&st.cell_start, st.cell_bytes);
    let bind = |p: &wgpu::ComputePipeline, res: Vec<wgpu::BindingResource<'_>>| ctx.bind(p, &res);
    let walk_group = |p: &wgpu::ComputePipeline, s: usize| {
        bind(
            p,
            vec![
                slot(&params, s),
                h(&queries, q_bytes),
                cells.clone(),
                h(&scan, scan_bytes),
                h(&items, item_bytes),
                h(&results, res_bytes),
            ],
        )
    };
    let scan_group =
        |p: &wgpu::ComputePipeline, s: usize| bind(p, vec![slot(&params, s), h(&scan, scan_bytes)]);
    let eval_group = |pipeline: &wgpu::ComputePipeline, s: usize, part: usize| {
        let (pb, pbytes) = &st.parts[part];
        bind(
            pipeline,
            vec![
                slot(&params, s),
                h(&queries, q_bytes),
                h(&items, item_bytes),
                h(pb, *pbytes),
                h(&partials, part_bytes),
                h(&ctl, ctl_bytes),
                h(&aux, aux_bytes),
                h(&plans, plan_bytes.max(16)),
            ],
        )
    };

    let mut enc = ctx.encoder();
    enc.clear_buffer(&ctl, 0, Some(CTL_HEAD as u64 * 4));
    if nearest {
        enc.clear_buffer(&aux, 0, Some(hist_bytes.next_multiple_of(4)));
    }
    {
        let groups_q = device::tiles(n as u64, WG as u64, lim.max_x);
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
        let g = walk_group(&k.walk_count, walk_count);
        pass.set_pipeline(&k.walk_count);
        pass.set_bind_group(0, &g, &[]);
        // A rerun starts at the sizing: the counts and their scan are in place.
        let fresh = !rerun;
        if fresh {
            pass.dispatch_workgroups(groups_q.0, groups_q.1, 1);
        }
        // Scan up the levels, then add the block sums back down.
        for (i, &(_, len, _)) in levels.iter().enumerate() {
            let g = scan_group(&k.scan, scan_slots[i]);
            pass.set_pipeline(&k.scan);
            pass.set_bind_group(0, &g, &[]);
            if fresh {
                pass.dispatch_workgroups(len.div_ceil(SCAN_WG).max(1), 1, 1);
            }
        }
        for i in (0..levels.len().saturating_sub(1)).rev() {
            let g = scan_group(&k.scan_add, scan_slots[i]);
            pass.set_pipeline(&k.scan_add);
            pass.set_bind_group(0, &g, &[]);
            if fresh {
                pass.dispatch_workgroups(levels[i].1.div_ceil(SCAN_WG).max(1), 1, 1);
            }
        }
        let g = bind(
            &k.args,
            vec![
                slot(&params, args_slot),
                h(&scan, scan_bytes),
                h(&ctl, ctl_bytes),
                h(&indirect, 24),
            ],
        );
        pass.set_pipeline(&k.args);
        pass.set_bind_group(0, &g, &[]);
        pass.dispatch_workgroups(1, 1, 1);
        let g = walk_group(&k.walk_emit, walk_emit);
        pass.set_pipeline(&k.walk_emit);
        pass.set_bind_group(0, &g, &[]);
        // Sized by `args`: empty when the items do not fit.
        pass.dispatch_workgroups_indirect(&indirect, 12);
        let ev = k.eval(ctx, eval_mode, base.cover != 0)?;
        pass.set_pipeline(ev);
        for (p, &s) in eval_slots.iter().enumerate() {
            let g = eval_group(ev, s, p);
            pass.set_bind_group(0, &g, &[]);
            pass.dispatch_workgroups_indirect(&indirect, 0);
        }
        if members {
            let mgroup = |p: &wgpu::ComputePipeline, s: usize| {
                bind(
                    p,
                    vec![
                        slot(&params, s),
                        h(&ctl, ctl_bytes),
                        h(&partials, part_bytes),
                        h(&mscan, mscan_bytes),
                    ],
                )
            };
            let (gather, scatter) = k.members(ctx)?;
            let g = mgroup(gather, gather_slot);
            pass.set_pipeline(gather);
            pass.set_bind_group(0, &g, &[]);
            pass.dispatch_workgroups_indirect(&indirect, 0);
            let sgroup = |p: &wgpu::ComputePipeline, s: usize| {
                bind(p, vec![slot(&params, s), h(&mscan, mscan_bytes)])
            };
            for (i, &(_, len, _)) in mlevels.iter().enumerate() {
                let g = sgroup(&k.scan, mscan_slots[i]);
                pass.set_pipeline(&k.scan);
                pass.set_bind_group(0, &g, &[]);
                pass.dispatch_workgroups(len.div_ceil(SCAN_WG).max(1), 1, 1);
            }
            for i in (0..mlevels.len().saturating_sub(1)).rev() {
                let g = sgroup(&k.scan_add, mscan_slots[i]);
                pass.set_pipeline(&k.scan_add);
                pass.set_bind_group(0, &g, &[]);
                pass.dispatch_workgroups(mlevels[i].1.div_ceil(SCAN_WG).max(1), 1, 1);
            }
            let g = mgroup(scatter, gather_slot);
            pass.set_pipeline(scatter);
            pass.set_bind_group(0, &g, &[]);
            pass.dispatch_workgroups_indirect(&indirect, 0);
            let ev = k.eval(ctx, MODE_MEMBERS, false)?;
            pass.set_pipeline(ev);
            for (p, &s) in member_slots.iter().enumerate() {
                let g = eval_group(ev, s, p);
                pass.set_bind_group(0, &g, &[]);
                pass.dispatch_workgroups_indirect(&indirect, 0);
            }
        }
        if nearest {
            let cut = k.cut(ctx)?;
            let g = bind(
                cut,
                vec![
                    slot(&params, cut_slot),
                    h(&queries, q_bytes),
                    h(&aux, hist_bytes),
                    h(&plans, plan_bytes),
                ],
            );
            pass.set_pipeline(cut);
            pass.set_bind_group(0, &g, &[]);
            pass.dispatch_workgroups(groups_q.0, groups_q.1, 1);
            let ev = k.eval(ctx, MODE_BELOW, false)?;
            pass.set_pipeline(ev);
            for (p, &s) in below_slots.iter().enumerate() {
                let g = eval_group(ev, s, p);
                pass.set_bind_group(0, &g, &[]);
                pass.dispatch_workgroups_indirect(&indirect, 0);
            }
        }
        {
            let g = bind(
                &k.reduce,
                vec![
                    slot(&params, reduce_slot),
                    h(&scan, scan_bytes),
                    h(&partials, part_bytes),
                    h(&results, res_bytes),
                ],
            );
            pass.set_pipeline(&k.reduce);
            pass.set_bind_group(0, &g, &[]);
            pass.dispatch_workgroups(groups_q.0, groups_q.1, 1);
        }
        if let (Some(fitq), Some(fitout), Some(fit), Some((world, world_bytes))) =
            (&fitq, &fitout, &k.fit, &st.world)
        {
            // One workgroup per query, after the reduction has counted its members.
            let g = bind(
                fit,
                vec![
                    slot(&params, fit_slot),
                    h(fitq, fitq_bytes),
                    h(&scan, scan_bytes),
                    h(&partials, part_bytes),
                    h(&results, res_bytes),
                    h(&aux, mem_bytes),
                    h(world, *world_bytes),
                    h(fitout, fitout_bytes),
                ],
            );
            let groups = device::tiles(n as u64 * FIT_WG as u64, FIT_WG as u64, lim.max_x);
            pass.set_pipeline(fit);
            pass.set_bind_group(0, &g, &[]);
            pass.dispatch_workgroups(groups.0, groups.1, 1);
        }
    }
    enc.copy_buffer_to_buffer(&results, 0, &staging, 0, res_bytes);
    enc.copy_buffer_to_buffer(&ctl, 0, &staging, res_bytes, ctl_bytes);
    if nearest {
        enc.copy_buffer_to_buffer(&plans, 0, &staging, res_bytes + ctl_bytes, plan_bytes);
    }
    if kind == Kind::Members {
        enc.copy_buffer_to_buffer(&aux, 0, &staging, res_bytes + ctl_bytes, mem_bytes);
    }
    if let Some(fitout) = &fitout {
        enc.copy_buffer_to_buffer(fitout, 0, &staging, res_bytes + ctl_bytes, fitout_bytes);
    }
    let ((out, total, n_flags, n_members), waited) =
        ctx.submit_and_map(enc, &staging, staging_bytes, |bytes| {
            let (r, rest) = bytes.split_at(res_bytes as usize);
            let (c, p) = rest.split_at(ctl_bytes as usize);
            let results: Vec<QResult> = bytemuck::pod_collect_to_vec(r);
            let ctlw: &[u32] = &device::pods::<u32>(c);
            let total = ctlw[0];
            let n_flags = ctlw[1];
            let kept = n_flags.min(flag_cap) as usize;
            let head = CTL_HEAD as usize;
            let mut flags: Vec<(u32, u32)> = (0..kept)
                .map(|i| (ctlw[head + 2 * i], ctlw[head + 2 * i + 1]))
                .collect();
            flags.sort_unstable_by_key(|&(q, p)| ((q & !FLAG_CANDIDATE), q >> 31, p));
            let plans: Vec<Plan> = if nearest {
                bytemuck::pod_collect_to_vec(&p[..plan_bytes as usize])
            } else {
                Vec::new()
            };
            let (mut n_members, mut list, mut bad, mut fits) =
                (0u64, Vec::new(), false, Vec::new());
            if fitting {
                fits = bytemuck::pod_collect_to_vec(&p[..fitout_bytes as usize]);
            }
            if members {
                n_members = results
                    .iter()
                    .filter(|r| r.status & STATUS_HOST == 0)
                    .map(|r| r.count as u64)
                    .sum();
                if !fitting {
                    let kept = n_members.min(member_cap as u64) as usize;
                    list = device::pods::<u32>(&p[..kept * 4]).into_owned();
                }
                bad = ctlw[CTL_MEMBERS_BAD as usize] != 0;
            }
            (
                Output {
                    results,
                    plans,
                    flags,
                    members: list,
                    bad,
                    fits,
                },
                total,
                n_flags,
                n_members,
            )
        })?;
    Ok((out, waited, total, n_flags, n_members))
}

/// Allocates and clears the coverage mask over `n` points (`b.aux`).
pub fn clear_mask(
    ctx: &Context,
    b: &mut Buffers,
    lim: &Limits,
    n: usize,
) -> Result<(), EngineError> {
    let bytes = (n.div_ceil(32) * 4) as u64;
    if bytes > lim.device_binding {
        return Err(EngineError::Gpu(format!(
            "coverage of {n} points needs a {bytes}-byte mask, above the device's binding limit"
        )));
    }
    b.aux_len = bytes;
    let aux = b.aux.get(ctx, bytes).clone();
    let mut enc = ctx.encoder();
    enc.clear_buffer(&aux, 0, Some(bytes.next_multiple_of(4)));
    ctx.queue.submit([enc.finish()]);
    Ok(())
}

/// Reads the coverage mask back: the u32 words, and the seconds spent waiting.
pub fn read_mask(ctx: &Context, b: &mut Buffers, n: usize) -> Result<(Vec<u32>, f64), EngineError> {
    let bytes = (n.div_ceil(32) * 4) as u64;
    let aux = b.aux.get(ctx, bytes).clone();
    let staging = b.staging.get(ctx, bytes).clone();
    let mut enc = ctx.encoder();
    enc.copy_buffer_to_buffer(&aux, 0, &staging, 0, bytes);
    ctx.submit_and_map(enc, &staging, bytes, bytemuck::pod_collect_to_vec)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Aabb;
    use std::sync::Arc;

    /// A grid with empty cells, crowded cells and more points than a few pieces.
    fn grid() -> Arc<Grid> {
        let mut s = 5u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let pts: Vec<[f32; 3]> = (0..3 * STORE_RUN + 123)
            .map(|i| {
                let t = next();
                if i % 3 == 0 {
                    // A dense line: crowded cells among empty ones.
                    [t as f32, 0.5, 0.5]
                } else {
                    [t as f32, next() as f32, next() as f32]
                }
            })
            .collect();
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        Arc::new(Grid::build(&pts, b, 0.05))
    }

    /// Each point's entry from its own cell (`cell_of`, the function the grid sorted with).
    fn by_cell_of(g: &Grid) -> Vec<[f32; 4]> {
        let (dx, dy) = (g.dims[0], g.dims[1]);
        g.points
            .iter()
            .map(|p| {
                let p = p64(*p);
                let c = g.cell_of(p);
                let r = (p - g.cell_origin(c % dx, (c / dx) % dy, c / (dx * dy))) / g.cell;
                [
                    r.x as f32,
                    r.y as f32,
                    r.z as f32,
                    ((c % dx) & 0xFFFF) as f32,
                ]
            })
            .collect()
    }

    #[test]
    fn the_point_store_finds_each_points_own_cell() {
        let g = grid();
        assert!(g.cell_start.windows(2).any(|w| w[0] == w[1]), "empty cells");
        let want = by_cell_of(&g);
        let rel = PointStore::of(&g).rel;
        assert_eq!(rel.len(), want.len());
        for (i, (a, b)) in rel.iter().zip(&want).enumerate() {
            // The same arithmetic up to the multiplication by 1 / cell: within an ulp.
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() <= 1e-6, "point {i}: {a:?} vs {b:?}");
            }
            assert_eq!(a[3], b[3], "point {i}: cell x index");
        }
    }

    #[test]
    fn the_store_written_into_staging_memory_is_the_computed_one() {
        let g = grid();
        let rel = PointStore::of(&g).rel;
        // From point 100 on, as a part that starts mid-grid, with a piece left over.
        let first = 100;
        let mut got = vec![[0f32; 4]; rel.len() - first];
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(got.as_mut_slice());
        write_store(&g, wgpu::WriteOnly::from_mut(bytes), first);
        assert_eq!(got, &rel[first..]);
    }
}
