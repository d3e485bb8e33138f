//! `reduce.wgsl`: each query's item slots summed in grid order (Kahan, no atomics).

use super::super::device;
use super::super::pipelines::{KernelSpec, When};
use super::super::stages::{Recorder, Stage, StageSpec};
use super::kernel_source;

pub static KERNELS: [KernelSpec; 1] = [KernelSpec {
    name: "reduce",
    shader: "reduce.wgsl",
    source: || kernel_source(include_str!("../../../../shaders/reduce.wgsl")),
    entry: "main",
    when: When::Open,
    structs: &[],
}];

/// Every try of every batch, after the evaluation passes.
pub static STAGE: StageSpec = StageSpec {
    name: "reduce",
    record: |s, rec| {
        s.reduce(rec);
        Ok(())
    },
    ..StageSpec::BASE
};

impl Stage<'_> {
    /// One invocation per query.
    fn reduce(&self, rec: &mut Recorder<'_>) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let bind = [
            h(&bd.scan, sz.scan),
            h(&bd.partials, sz.partials),
            h(&bd.results, sz.results),
        ];
        let base = rec.base;
        let pipeline = self.k.compiled(&KERNELS[0]).expect("compiled at open");
        rec.bind(pipeline, base, &bind);
        rec.dispatch(self.per_query());
    }
}
