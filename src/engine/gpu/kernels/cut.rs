//! `cut.wgsl`: each query's k-nearest cut bin from its histogram (nearest batches), then
//! a below-the-cut pass of `eval.wgsl`; the plans come back for the host to rank the
//! candidates.

use super::super::device::{self, Context};
use super::super::layout::MODE_BELOW;
use super::super::pipelines::{KernelSpec, When};
use super::super::stages::{Recorder, Stage};
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

impl Stage<'_> {
    /// The cut, one invocation per query, then the sums of the points below it.
    pub fn nearest(&self, rec: &mut Recorder<'_>, ctx: &Context) -> Result<(), EngineError> {
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
