//! The stages of one device batch, each a small function that declares its uniform slot
//! and its bindings right where it dispatches, in the order [`super::batch`] records them:
//!
//! ```text
//! count ─ scan ─ size_items ─ emit ─ evaluate ─┬─────────────────────────┬─ reduce ─ (fit | extent)
//!  walk    scan     args       walk     eval    ├ members: gather, scan,  │   reduce    fit, extent
//!                                               │   scatter, eval members │
//!                                               └ nearest: cut, eval below┘
//! ```
//!
//! Binding 0 of every kernel is its own slot of the uniform buffer ([`Params`]); the
//! [`Recorder`] hands out the slots and returns their bytes for the host to write before
//! the submit.

use super::device::{self, Context};
use super::kernels::Kernels;
use super::layout::*;
use super::resources::{Limits, Statics};
use super::sizes::{Bound, Level, Sizes};
use crate::engine::EngineError;

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
    fn bind(
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

    fn dispatch(&mut self, (x, y): (u32, u32)) {
        self.pass.dispatch_workgroups(x, y, 1);
    }

    /// A dispatch sized by `args.wgsl`: the per-item grid at 0, the emit pass's at 12.
    fn indirect(&mut self, buf: &wgpu::Buffer, offset: u64) {
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
    fn per_query(&self) -> (u32, u32) {
        device::tiles(self.sz.n as u64, WG as u64, self.lim.max_x)
    }

    /// The walk's bindings: the queries, the cell table, the counts' scan, the items and
    /// the per-query results.
    fn walk(&self, rec: &mut Recorder<'_>, pipeline: &wgpu::ComputePipeline, mode: u32) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let p = Params { mode, ..rec.base };
        rec.bind(
            pipeline,
            p,
            &[
                wgpu::BindingResource::TextureView(&bd.qtex),
                h(&self.st.cell_start, self.st.cell_bytes),
                h(&bd.scan, sz.scan),
                h(&bd.items, sz.items),
                h(&bd.results, sz.results),
            ],
        );
    }

    /// `walk.wgsl`, count pass: each query's work items.
    pub fn count(&self, rec: &mut Recorder<'_>) {
        self.walk(rec, &self.k.walk_count, MODE_COUNT);
        rec.dispatch(self.per_query());
    }

    /// `scan.wgsl`: the exclusive prefix sum of `buf` over `levels`, up the levels (each
    /// level's block sums into the next), then the scanned block sums added back down.
    pub fn scan(&self, rec: &mut Recorder<'_>, buf: &wgpu::Buffer, bytes: u64, levels: &[Level]) {
        let base = rec.base;
        let p = |l: &Level| Params {
            n: l.len,
            base: l.base,
            sums: l.sums,
            ..base
        };
        for l in levels {
            rec.bind(&self.k.scan, p(l), &[device::head(buf, bytes)]);
            rec.dispatch((l.groups(), 1));
        }
        for l in levels.iter().rev().skip(1) {
            rec.bind(&self.k.scan_add, p(l), &[device::head(buf, bytes)]);
            rec.dispatch((l.groups(), 1));
        }
    }

    /// `args.wgsl`: the items' total and the indirect dispatch sizes (empty grids when the
    /// items do not fit).
    pub fn size_items(&self, rec: &mut Recorder<'_>) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let bind = [
            h(&bd.scan, sz.scan),
            h(&bd.ctl, sz.ctl),
            h(&bd.indirect, 24),
        ];
        let base = rec.base;
        rec.bind(&self.k.args, base, &bind);
        rec.dispatch((1, 1));
    }

    /// `walk.wgsl`, emit pass: the items, contiguous per query.
    pub fn emit(&self, rec: &mut Recorder<'_>) {
        self.walk(rec, &self.k.walk_emit, MODE_EMIT);
        rec.indirect(&self.bd.indirect, 12);
    }

    /// `eval.wgsl` compiled for `mode`, once per part of the point store: every point of
    /// every item of that part.
    pub fn evaluate(&self, rec: &mut Recorder<'_>, eval: &wgpu::ComputePipeline, mode: u32) {
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

    /// `members.wgsl` and a member pass of `eval.wgsl`: each item's sure-member count
    /// gathered, scanned into offsets and scattered back, then each query's members
    /// written contiguously.
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

    /// `cut.wgsl` and a below-the-cut pass of `eval.wgsl`: each query's cut bin from its
    /// histogram, then the sums of the points below it.
    pub fn nearest(&self, rec: &mut Recorder<'_>, ctx: &Context) -> Result<(), EngineError> {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let bind = [
            wgpu::BindingResource::TextureView(&bd.qtex),
            h(&bd.aux, sz.hist),
            h(&bd.plans, sz.plans),
        ];
        let base = rec.base;
        rec.bind(self.k.cut(ctx)?, base, &bind);
        rec.dispatch(self.per_query());
        self.evaluate(rec, self.k.eval(ctx, MODE_BELOW, false)?, MODE_BELOW);
        Ok(())
    }

    /// `reduce.wgsl`: each query's item slots summed in grid order.
    pub fn reduce(&self, rec: &mut Recorder<'_>) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let bind = [
            h(&bd.scan, sz.scan),
            h(&bd.partials, sz.partials),
            h(&bd.results, sz.results),
        ];
        let base = rec.base;
        rec.bind(&self.k.reduce, base, &bind);
        rec.dispatch(self.per_query());
    }

    /// `fit.wgsl`: the edge fit's ridge over each query's member list, one workgroup per
    /// query, after the reduction has counted its members. Nothing without the kernel or
    /// the centers' coordinates on the device.
    pub fn fit(&self, rec: &mut Recorder<'_>) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let (Some(fitq), Some(fitout), Some(fit), Some((world, world_bytes))) =
            (&bd.fitq, &bd.fitout, &self.k.fit, &self.st.world)
        else {
            return;
        };
        let bind = [
            h(fitq, sz.fitq),
            h(&bd.scan, sz.scan),
            h(&bd.partials, sz.partials),
            h(&bd.results, sz.results),
            h(&bd.aux, sz.members),
            h(world, *world_bytes),
            h(fitout, sz.fitout),
        ];
        let base = rec.base;
        rec.bind(fit, base, &bind);
        let n = sz.n as u64 * FIT_WG as u64;
        rec.dispatch(device::tiles(n, FIT_WG as u64, self.lim.max_x));
    }

    /// `extent.wgsl`: each query's extent over its member list, one workgroup per query,
    /// after the reduction has counted its members. Nothing without the kernel or the
    /// centers' coordinates on the device.
    pub fn extent(&self, rec: &mut Recorder<'_>) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let (Some(fitq), Some(out), Some(extent), Some((world, world_bytes))) =
            (&bd.fitq, &bd.fitout, &self.k.extent, &self.st.world)
        else {
            return;
        };
        let bind = [
            h(fitq, sz.fitq),
            h(&bd.scan, sz.scan),
            h(&bd.partials, sz.partials),
            h(&bd.results, sz.results),
            h(&bd.aux, sz.members),
            h(world, *world_bytes),
            h(out, sz.fitout),
        ];
        let base = rec.base;
        rec.bind(extent, base, &bind);
        let n = sz.n as u64 * FIT_WG as u64;
        rec.dispatch(device::tiles(n, FIT_WG as u64, self.lim.max_x));
    }
}
