//! The kernels: each WGSL source assembled from the generated prelude, `common.wgsl` and
//! the kernel (WGSL has no include), and their pipelines, compiled when the device opens
//! or, for the kinds of batch a run may never send, on first use.

use super::device::Context;
use super::layout::{self, *};
use crate::engine::EngineError;
use std::sync::OnceLock;

/// The layouts and helpers every kernel shares: the prelude generated from `layout.rs`,
/// `shaders/common.wgsl`, then the query accessor generated from `GQuery`'s fields
/// ([`layout::query_of_wgsl`]).
pub fn common_wgsl() -> String {
    format!(
        "{}\n{}\n{}",
        layout::prelude(),
        include_str!("../../../shaders/common.wgsl"),
        layout::query_of_wgsl()
    )
}

/// A kernel's full source: the shared prelude, then the kernel (WGSL has no include).
pub fn kernel_source(kernel: &str) -> String {
    format!("{}\n{kernel}", common_wgsl())
}

/// The fit kernel's full source: the shared prelude, its own f64 prelude, then
/// `fit.wgsl` (compiled only on a device with `SHADER_F64`).
pub fn fit_source() -> String {
    f64_kernel_source(include_str!("../../../shaders/fit.wgsl"))
}

/// An f64 kernel's full source (`fit.wgsl`, `extent.wgsl`): the shared prelude, the f64
/// prelude with their structs, then the kernel.
pub fn f64_kernel_source(kernel: &str) -> String {
    kernel_source(&format!("{}\n{kernel}", layout::fit_prelude()))
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

pub struct Kernels {
    /// The grid walk's count and emit passes ([`walk_source`]).
    pub walk_count: wgpu::ComputePipeline,
    pub walk_emit: wgpu::ComputePipeline,
    pub scan: wgpu::ComputePipeline,
    pub scan_add: wgpu::ComputePipeline,
    pub args: wgpu::ComputePipeline,
    /// One evaluation pipeline per mode and coverage switch ([`EVAL_VARIANTS`]), each
    /// compiled with both as constants ([`eval_source`]): the plain stats modes
    /// (every evaluation, outlier test, crop and merge) when the device opens, the others
    /// (sides, k nearest, member lists) on first use, like the k-nearest cut and the member
    /// lists' gather and scatter: a run that never asks for them never compiles them.
    eval: Vec<OnceLock<wgpu::ComputePipeline>>,
    cut: OnceLock<wgpu::ComputePipeline>,
    pub reduce: wgpu::ComputePipeline,
    gather: OnceLock<wgpu::ComputePipeline>,
    scatter: OnceLock<wgpu::ComputePipeline>,
    /// The edge fit's ridge, in f64: only on a device with `SHADER_F64`.
    pub fit: Option<wgpu::ComputePipeline>,
    /// The extent of each query's member list (`extent.wgsl`, f64), compiled with the
    /// fit kernel.
    pub extent: Option<wgpu::ComputePipeline>,
}

impl Kernels {
    /// Compiles every kernel; the fit kernel only with `fit` (and f64 on the device).
    pub fn new(ctx: &Context, fit: bool) -> Kernels {
        let k = |name: &str, src: &str, entry: &str| ctx.pipeline(name, &kernel_source(src), entry);
        let scan = include_str!("../../../shaders/scan.wgsl");
        Kernels {
            walk_count: ctx.pipeline("walk count", &walk_source(false), "main"),
            walk_emit: ctx.pipeline("walk emit", &walk_source(true), "main"),
            scan: k("scan", scan, "main"),
            scan_add: k("scan add", scan, "add"),
            args: k("args", include_str!("../../../shaders/args.wgsl"), "main"),
            eval: EVAL_VARIANTS
                .iter()
                .map(|&(m, c)| {
                    let cell = OnceLock::new();
                    if m == MODE_STATS {
                        let _ = cell.set(ctx.pipeline("eval", &eval_source(m, c), "main"));
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
                        ctx.pipeline("fit", &fit_source(), "main")
                    })
                    .ok()
                })
                .flatten(),
            extent: (fit && ctx.f64)
                .then(|| {
                    ctx.scoped("compiling the extent kernel", || {
                        let src = f64_kernel_source(include_str!("../../../shaders/extent.wgsl"));
                        ctx.pipeline("extent", &src, "main")
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
    pub fn eval(
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
            ctx.pipeline("eval", &eval_source(mode, cover), "main")
        })
    }

    /// The k-nearest cut (nearest batches).
    pub fn cut(&self, ctx: &Context) -> Result<&wgpu::ComputePipeline, EngineError> {
        lazy(&self.cut, ctx, "compiling the cut kernel", || {
            let src = kernel_source(include_str!("../../../shaders/cut.wgsl"));
            ctx.pipeline("cut", &src, "main")
        })
    }

    /// The member lists' gather and scatter of the items' counts (members batches).
    pub fn members(
        &self,
        ctx: &Context,
    ) -> Result<(&wgpu::ComputePipeline, &wgpu::ComputePipeline), EngineError> {
        let src = || kernel_source(include_str!("../../../shaders/members.wgsl"));
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
