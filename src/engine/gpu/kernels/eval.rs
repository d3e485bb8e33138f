//! `eval.wgsl`: every point of every work item, once per part of the point store, its
//! members' sums into the item's own slot (or the coverage bits, the k-nearest histogram,
//! the sums below the cut, the member list), compiled once per mode and coverage switch.

use super::super::device::{self, Context};
use super::super::layout::*;
use super::super::pipelines::{KernelSpec, Kernels, When};
use super::super::sizes::Kind;
use super::super::stages::{Recorder, Stage, StageSpec};
use super::kernel_source;
use crate::engine::EngineError;

/// One pipeline per mode and coverage switch ([`EVAL_VARIANTS`], in the same order),
/// each compiled with both as constants ([`eval_source`]): the plain stats modes (every
/// evaluation, outlier test, crop and merge) when the device opens, the others (sides, k
/// nearest, member lists) on first use.
pub static KERNELS: [KernelSpec; 7] = [
    spec("eval stats", || eval_source(MODE_STATS, false), When::Open),
    spec(
        "eval stats cover",
        || eval_source(MODE_STATS, true),
        When::Open,
    ),
    spec(
        "eval sides",
        || eval_source(MODE_STATS_SIDES, false),
        When::OnUse,
    ),
    spec(
        "eval sides cover",
        || eval_source(MODE_STATS_SIDES, true),
        When::OnUse,
    ),
    spec(
        "eval histogram",
        || eval_source(MODE_HIST, false),
        When::OnUse,
    ),
    spec("eval below", || eval_source(MODE_BELOW, false), When::OnUse),
    spec(
        "eval members",
        || eval_source(MODE_MEMBERS, false),
        When::OnUse,
    ),
];

const fn spec(name: &'static str, source: fn() -> String, when: When) -> KernelSpec {
    KernelSpec {
        name,
        shader: "eval.wgsl",
        source,
        entry: "main",
        when,
        structs: &[],
    }
}

/// The stats pass of every try of every batch (sides, the coverage bits, or the
/// k-nearest histogram, as the batch's kind asks), once per part of the point store.
pub static STAGE: StageSpec = StageSpec {
    name: "eval",
    slots: |_, _, parts| parts,
    record: |s, rec| {
        let mode = mode_of(s.kind);
        s.evaluate(rec, s.k.eval(s.ctx, mode, rec.base.cover != 0)?, mode);
        Ok(())
    },
    prepare: |k, ctx, kind| k.eval(ctx, mode_of(kind), false).map(|_| ()),
    ..StageSpec::BASE
};

/// The mode of a batch's stats pass.
fn mode_of(kind: Kind) -> u32 {
    match kind {
        Kind::Stats { sides: false, .. } | Kind::Members | Kind::List(_) => MODE_STATS,
        Kind::Stats { sides: true, .. } => MODE_STATS_SIDES,
        Kind::Nearest => MODE_HIST,
    }
}

/// The evaluation kernel's variants, each its own pipeline: (mode, coverage bits).
const EVAL_VARIANTS: [(u32, bool); 7] = [
    (MODE_STATS, false),
    (MODE_STATS, true),
    (MODE_STATS_SIDES, false),
    (MODE_STATS_SIDES, true),
    (MODE_HIST, false),
    (MODE_BELOW, false),
    (MODE_MEMBERS, false),
];

/// The lines of `eval.wgsl` that read the evaluation mode and the coverage switch from
/// the uniform.
const EVAL_MODE_LINE: &str = "let mode = params.mode;";
const EVAL_COVER_LINE: &str = "let cover_on = params.cover != 0u;";

/// The evaluation kernel compiled for one mode (and, for the stats modes, with or without
/// the coverage bits): both are constants instead of the uniform's, so each pipeline
/// carries only its own branches (on lavapipe the stats pass then costs about 40 % less
/// CPU time; on GPUs fewer registers).
fn eval_source(mode: u32, cover: bool) -> String {
    let src = include_str!("../../../../shaders/eval.wgsl");
    assert!(
        src.contains(EVAL_MODE_LINE) && src.contains(EVAL_COVER_LINE),
        "eval.wgsl reads its mode and coverage switch"
    );
    kernel_source(
        &src.replace(EVAL_MODE_LINE, &format!("let mode = {mode}u;"))
            .replace(EVAL_COVER_LINE, &format!("let cover_on = {cover};")),
    )
}

impl Kernels {
    /// The evaluation pipeline of `mode` (coverage bits only in the stats modes),
    /// compiled now if this is its first use.
    pub(super) fn eval(
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
        self.get(ctx, &KERNELS[i])
    }
}

impl Stage<'_> {
    /// `eval` (compiled for `mode`), once per part of the point store: every point of
    /// every item of that part, sized by `args.wgsl`.
    pub(super) fn evaluate(&self, rec: &mut Recorder<'_>, eval: &wgpu::ComputePipeline, mode: u32) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        for (part, points) in self.st.parts.iter().enumerate() {
            let p = Params {
                mode,
                part: part as u32,
                part_base: part as u32 * self.lim.part_len,
                ..rec.base
            };
            let bind = [
                wgpu::BindingResource::TextureView(&bd.qtex),
                h(&bd.items, sz.items),
                wgpu::BindingResource::TextureView(points),
                h(&bd.partials, sz.partials),
                h(&bd.ctl, sz.ctl),
                h(&bd.aux, sz.aux),
                h(&bd.plans, sz.plans.max(16)),
            ];
            rec.bind(eval, p, &bind);
            rec.indirect(&bd.indirect, 0);
        }
    }
}
