//! `members.wgsl`: a members batch's (and every list kernel's) member lists: each item's
//! sure-member count gathered, scanned into offsets and scattered back, then a member
//! pass of `eval.wgsl` writes each query's members contiguously.

use super::super::device::{self, Context};
use super::super::layout::MODE_MEMBERS;
use super::super::pipelines::{KernelSpec, Kernels, When};
use super::super::stages::{Recorder, Stage};
use super::kernel_source;
use crate::engine::EngineError;

pub static KERNELS: [KernelSpec; 2] = [
    KernelSpec {
        name: "members",
        shader: "members.wgsl",
        source: || kernel_source(include_str!("../../../../shaders/members.wgsl")),
        entry: "gather",
        when: When::OnUse,
        structs: &[],
    },
    KernelSpec {
        name: "members",
        shader: "members.wgsl",
        source: || kernel_source(include_str!("../../../../shaders/members.wgsl")),
        entry: "scatter",
        when: When::OnUse,
        structs: &[],
    },
];

impl Kernels {
    /// The gather and scatter pipelines, compiled now if this is their first use.
    pub fn members(
        &self,
        ctx: &Context,
    ) -> Result<(&wgpu::ComputePipeline, &wgpu::ComputePipeline), EngineError> {
        Ok((self.get(ctx, &KERNELS[0])?, self.get(ctx, &KERNELS[1])?))
    }
}

impl Stage<'_> {
    /// Gather, scan, scatter, then the member pass.
    pub fn members(&self, rec: &mut Recorder<'_>, ctx: &Context) -> Result<(), EngineError> {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let (gather, scatter) = self.k.members(ctx)?;
        let bind = [
            h(&bd.ctl, sz.ctl),
            h(&bd.partials, sz.partials),
            h(&bd.mscan, sz.mscan),
        ];
        let base = rec.base;
        rec.bind(gather, base, &bind);
        rec.indirect(&bd.indirect, 0);
        self.scan(rec, &bd.mscan, sz.mscan, &sz.mlevels);
        rec.bind(scatter, base, &bind);
        rec.indirect(&bd.indirect, 0);
        self.evaluate(rec, self.k.eval(ctx, MODE_MEMBERS, false)?, MODE_MEMBERS);
        Ok(())
    }
}
