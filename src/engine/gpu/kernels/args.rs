//! `args.wgsl`: the items' total and the indirect dispatch sizes of the per-item kernels
//! (empty grids when the items do not fit).

use super::super::device;
use super::super::pipelines::{KernelSpec, When};
use super::super::stages::{Recorder, Stage, StageSpec};
use super::kernel_source;

pub static KERNELS: [KernelSpec; 1] = [KernelSpec {
    name: "args",
    shader: "args.wgsl",
    source: || kernel_source(include_str!("../../../../shaders/args.wgsl")),
    entry: "main",
    when: When::Open,
    structs: &[],
}];

/// Every try of every batch, after the items are counted and scanned.
pub static STAGE: StageSpec = StageSpec {
    name: "args",
    record: |s, rec| {
        s.size_items(rec);
        Ok(())
    },
    ..StageSpec::BASE
};

impl Stage<'_> {
    /// Sizes the emit pass (at byte 12 of the indirect buffer) and the per-item passes
    /// (at 0).
    fn size_items(&self, rec: &mut Recorder<'_>) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let bind = [
            h(&bd.scan, sz.scan),
            h(&bd.ctl, sz.ctl),
            h(&bd.indirect, 24),
        ];
        let base = rec.base;
        let pipeline = self.k.compiled(&KERNELS[0]).expect("compiled at open");
        rec.bind(pipeline, base, &bind);
        rec.dispatch((1, 1));
    }
}
