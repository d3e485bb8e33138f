//! `cut.wgsl`: each query's k-nearest cut bin from its histogram (nearest batches), then
//! a below-the-cut pass of `eval.wgsl`; the plans come back for the host to rank the
//! candidates.

use super::super::device;
use super::super::layout::MODE_BELOW;
use super::super::pipelines::{KernelSpec, When};
use super::super::sizes::Kind;
use super::super::stages::{Recorder, Stage, StageSpec};
use super::kernel_source;
use crate::engine::EngineError;

pub static KERNELS: [KernelSpec; 1] = [KernelSpec {
    name: "cut",
    shader: "cut.wgsl",
    source: || kernel_source(include_str!("../../../../shaders/cut.wgsl")),
    entry: "main",
    when: When::OnUse,
    structs: &[],
}];

/// The cut of every try of a nearest batch, after its histogram pass (which adds into the
/// histograms this clears first); the plans come back.
pub static STAGE: StageSpec = StageSpec {
    name: "cut",
    runs_in: |kind| kind == Kind::Nearest,
    slots: |_, _, parts| 1 + parts,
    before: |s, enc| enc.clear_buffer(&s.bd.aux, 0, Some(s.sz.hist.next_multiple_of(4))),
    record: |s, rec| s.nearest(rec),
    back: |s| Some((&s.bd.plans, s.sz.plans)),
    prepare: |k, ctx, _| {
        k.get(ctx, &KERNELS[0])?;
        k.eval(ctx, MODE_BELOW, false).map(|_| ())
    },
    ..StageSpec::BASE
};

impl Stage<'_> {
    /// The cut, one invocation per query, then the sums of the points below it.
    fn nearest(&self, rec: &mut Recorder<'_>) -> Result<(), EngineError> {
        let ctx = self.ctx;
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let bind = [
            wgpu::BindingResource::TextureView(&bd.qtex),
            h(&bd.aux, sz.hist),
            h(&bd.plans, sz.plans),
        ];
        let base = rec.base;
        rec.bind(self.k.get(ctx, &KERNELS[0])?, base, &bind);
        rec.dispatch(self.per_query());
        self.evaluate(rec, self.k.eval(ctx, MODE_BELOW, false)?, MODE_BELOW);
        Ok(())
    }
}
