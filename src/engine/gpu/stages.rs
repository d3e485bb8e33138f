//! How the stages of one device batch are recorded: the [`Recorder`] of one compute pass
//! and the [`Stage`] every kernel's launcher (`kernels/`) records its dispatch from, in
//! the order [`super::batch`] calls them:
//!
//! ```text
//! count ─ scan ─ size_items ─ emit ─ evaluate ─┬─────────────────────────┬─ reduce ─ list kernel
//!  walk    scan     args       walk     eval    ├ members: gather, scan,  │   reduce    fit, extent
//!                                               │   scatter, eval members │
//!                                               └ nearest: cut, eval below┘
//! ```
//!
//! Binding 0 of every kernel is its own slot of the uniform buffer ([`Params`]); the
//! [`Recorder`] hands out the slots and returns their bytes for the host to write before
//! the submit.

use super::device::{self, Context};
use super::layout::*;
use super::pipelines::Kernels;
use super::resources::{Limits, Statics};
use super::sizes::{Bound, Sizes};

/// Most uniform slots a try records: the walk's two passes, the args, the members'
/// gather and scatter, the cut, the reduction and the fit (8); two slots per scan level
/// of each scan, less one (up the levels, then back down but the top); and three
/// evaluation passes per point-store part (stats, then below-the-cut or members).
pub fn most_slots(sz: &Sizes, parts: usize) -> usize {
    let scan = |levels: usize| (2 * levels).saturating_sub(1);
    8 + scan(sz.levels.len()) + scan(sz.mlevels.len()) + 3 * parts
}

/// The uniform slot `i` of `buf`, for binding 0.
fn slot(buf: &wgpu::Buffer, i: usize) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer: buf,
        offset: i as u64 * PARAMS_SLOT,
        size: std::num::NonZeroU64::new(std::mem::size_of::<Params>() as u64),
    })
}

/// Records dispatches into one compute pass, giving each its own uniform slot.
pub struct Recorder<'a> {
    ctx: &'a Context,
    pass: wgpu::ComputePass<'a>,
    params: &'a wgpu::Buffer,
    slots: Vec<Params>,
    most: usize,
    /// What every slot starts from.
    pub base: Params,
}

impl<'a> Recorder<'a> {
    /// A pass in `enc` whose slots live in `params` (room for `most`).
    pub fn new(
        ctx: &'a Context,
        enc: &'a mut wgpu::CommandEncoder,
        params: &'a wgpu::Buffer,
        most: usize,
        base: Params,
    ) -> Recorder<'a> {
        Recorder {
            ctx,
            pass: enc.begin_compute_pass(&wgpu::ComputePassDescriptor::default()),
            params,
            slots: Vec::new(),
            most,
            base,
        }
    }

    /// Sets `pipeline` with a new slot holding `p` at binding 0 and `bind` after it.
    pub(in crate::engine::gpu) fn bind(
        &mut self,
        pipeline: &wgpu::ComputePipeline,
        p: Params,
        bind: &[wgpu::BindingResource<'_>],
    ) -> &mut Self {
        assert!(
            self.slots.len() < self.most,
            "more uniform slots than planned"
        );
        let mut all = vec![slot(self.params, self.slots.len())];
        all.extend_from_slice(bind);
        self.slots.push(p);
        let group = self.ctx.bind(pipeline, &all);
        self.pass.set_pipeline(pipeline);
        self.pass.set_bind_group(0, &group, &[]);
        self
    }

    pub(in crate::engine::gpu) fn dispatch(&mut self, (x, y): (u32, u32)) {
        self.pass.dispatch_workgroups(x, y, 1);
    }

    /// A dispatch sized by `args.wgsl`: the per-item grid at 0, the emit pass's at 12.
    pub(in crate::engine::gpu) fn indirect(&mut self, buf: &wgpu::Buffer, offset: u64) {
        self.pass.dispatch_workgroups_indirect(buf, offset);
    }

    /// Ends the pass; the bytes of the uniform buffer, slot after slot.
    pub fn finish(self) -> Vec<u8> {
        drop(self.pass);
        let mut uniform = vec![0u8; self.slots.len() * PARAMS_SLOT as usize];
        for (i, p) in self.slots.iter().enumerate() {
            let at = i * PARAMS_SLOT as usize;
            uniform[at..at + std::mem::size_of::<Params>()].copy_from_slice(bytemuck::bytes_of(p));
        }
        uniform
    }
}

/// What every stage reads: the kernels, the grid's buffers, the sizes and the bound
/// buffers of this try.
pub struct Stage<'a> {
    pub k: &'a Kernels,
    pub st: &'a Statics,
    pub lim: &'a Limits,
    pub sz: &'a Sizes,
    pub bd: &'a Bound,
}

impl Stage<'_> {
    /// A workgroup per [`WG`] queries (tiled past `max_x`).
    pub(in crate::engine::gpu) fn per_query(&self) -> (u32, u32) {
        device::tiles(self.sz.n as u64, WG as u64, self.lim.max_x)
    }
}
