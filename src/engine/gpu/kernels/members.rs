//! `members.wgsl`: a members batch's (and every list kernel's) member lists: each item's
//! sure-member count gathered, scanned into offsets and scattered back, then a member
//! pass of `eval.wgsl` writes each query's members contiguously.

use super::super::device::{self, Context};
use super::super::layout::MODE_MEMBERS;
use super::super::layout::SCAN_WG;
use super::super::pipelines::{KernelSpec, Kernels, When};
use super::super::resources::Limits;
use super::super::sizes::{scan_levels, BufferSpec, Kind, Level, Sizes};
use super::super::stages::{Recorder, Stage, StageSpec};
use super::{kernel_source, scan};
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

/// The member lists of every try of a members or list batch, after the stats pass; a
/// members batch sends the list back.
pub static STAGE: StageSpec = StageSpec {
    name: "members",
    runs_in: Kind::lists,
    buffers: &BUFFERS,
    max_items: member_scan_max,
    slots: |sz, lim, parts| 2 + scan::slots(&levels(sz, lim).0) + parts,
    record: |s, rec| s.members(rec),
    back: |s| {
        (s.kind == Kind::Members && !super::records::on(s)).then_some((&s.bd.aux, s.sz.members))
    },
    prepare: |k, ctx, _| {
        k.eval(ctx, MODE_MEMBERS, false)?;
        k.members(ctx)?;
        Ok(())
    },
    ..StageSpec::BASE
};

/// The scan of the items' member counts.
static BUFFERS: [BufferSpec; 1] = [BufferSpec {
    name: "mscan",
    bytes: |_, sz, lim| levels(sz, lim).1 as u64 * 4,
    frames: false,
}];

/// Most items a batch that lists members may have: its scan of their member counts is
/// one level within `max_x` workgroups.
fn member_scan_max(lim: &Limits) -> u32 {
    SCAN_WG.saturating_mul(lim.max_x)
}

/// The levels of the scan of the items' member counts and its length: over the item
/// buffer's capacity (the total is on the device; entries past it do not change the
/// offsets before it).
fn levels(sz: &Sizes, lim: &Limits) -> (Vec<Level>, u32) {
    let (levels, _, len) = scan_levels(sz.item_cap.min(member_scan_max(lim)));
    (levels, len)
}

impl Kernels {
    /// The gather and scatter pipelines, compiled now if this is their first use.
    fn members(
        &self,
        ctx: &Context,
    ) -> Result<(&wgpu::ComputePipeline, &wgpu::ComputePipeline), EngineError> {
        Ok((self.get(ctx, &KERNELS[0])?, self.get(ctx, &KERNELS[1])?))
    }
}

impl Stage<'_> {
    /// Gather, scan, scatter, then the member pass.
    fn members(&self, rec: &mut Recorder<'_>) -> Result<(), EngineError> {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let (gather, scatter) = self.k.members(self.ctx)?;
        let (mscan, mscan_bytes) = self.own(&BUFFERS[0]);
        let bind = [
            h(&bd.ctl, sz.ctl),
            h(&bd.partials, sz.partials),
            h(mscan, mscan_bytes),
        ];
        let base = rec.base;
        rec.bind(gather, base, &bind);
        rec.indirect(&bd.indirect, 0);
        self.scan(rec, mscan, mscan_bytes, &levels(sz, self.lim).0);
        rec.bind(scatter, base, &bind);
        rec.indirect(&bd.indirect, 0);
        self.evaluate(
            rec,
            self.k.eval(self.ctx, MODE_MEMBERS, false)?,
            MODE_MEMBERS,
        );
        Ok(())
    }
}
