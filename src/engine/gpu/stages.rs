//! How the stages of one device batch are declared and recorded: each stage a
//! [`StageSpec`] of its kernel's launcher (`kernels/`), which says the kinds of batch it
//! runs in, its own buffers, its uniform slots, what it records and what comes back;
//! the registry (`kernels::STAGES`) lists them in order, and [`super::batch`] records
//! every stage of the [`Sequence`] that runs in the batch's kind, in that order:
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
use super::sizes::{Bound, BufferSpec, Kind, Sizes};
use crate::engine::EngineError;

/// One stage of a device batch, declared by its kernel's launcher and listed, in the
/// order the batch records it, in `kernels::STAGES`.
pub struct StageSpec {
    /// Its name ([`super::batch_stages`]).
    pub name: &'static str,
    /// Whether it runs in batches of this kind.
    pub runs_in: fn(Kind) -> bool,
    /// Whether a rerun of the sub-batch (with larger item, flag or member buffers)
    /// records it again; a stage whose output depends only on the queries (the count
    /// walk and its scan) runs in the first try only.
    pub on_rerun: bool,
    /// Most work items a batch it runs in may have (a sub-batch with more is split).
    pub max_items: fn(&Limits) -> u32,
    /// Its own buffers, bound in the batches it runs in ([`Stage::own`]).
    pub buffers: &'static [BufferSpec],
    /// Most uniform slots it takes in one try, from the sizes, the limits and the parts of
    /// the point store.
    pub slots: fn(&Sizes, &Limits, usize) -> usize,
    /// Commands before the compute pass (a clear of what its kernels add into).
    pub before: fn(&Stage<'_>, &mut wgpu::CommandEncoder),
    /// Records its dispatches.
    pub record: fn(&Stage<'_>, &mut Recorder<'_>) -> Result<(), EngineError>,
    /// What comes back from the batch after the per-query results and the control words
    /// (one stage of a kind at most): a buffer and its bytes.
    pub back: for<'a> fn(&'a Stage<'a>) -> Option<(&'a wgpu::Buffer, u64)>,
    /// Compiles the pipelines it uses in batches of this kind that compile on first use
    /// (the device opening's, where the ridge runs on the device).
    pub prepare: fn(&Kernels, &Context, Kind) -> Result<(), EngineError>,
}

impl StageSpec {
    /// What a launcher's stage leaves as it is: runs in every batch and every try, no
    /// bound of its own on the items, one slot, no buffers of its own, nothing before the pass, nothing back, nothing to
    /// compile ahead; records nothing.
    pub const BASE: StageSpec = StageSpec {
        name: "",
        runs_in: |_| true,
        on_rerun: true,
        max_items: |_| u32::MAX,
        buffers: &[],
        slots: |_, _, _| 1,
        before: |_, _| {},
        record: |_, _| Ok(()),
        back: |_| None,
        prepare: |_, _, _| Ok(()),
    };
}

/// The stages of the registry, in order, with their own buffers one after another (each
/// its index in [`Sizes::own`], [`Bound::own`] and the buffers' `own`).
pub struct Sequence {
    stages: &'static [&'static StageSpec],
    buffers: Vec<&'static BufferSpec>,
}

impl Sequence {
    pub fn new(stages: &'static [&'static StageSpec]) -> Sequence {
        let buffers = stages.iter().flat_map(|s| s.buffers.iter()).collect();
        Sequence { stages, buffers }
    }

    /// Every stage's own buffer, stage after stage.
    pub fn buffers(&self) -> &[&'static BufferSpec] {
        &self.buffers
    }

    /// The stages a try of `kind` records, in order (a `rerun` without those that run in
    /// the first try only).
    pub fn running(&self, kind: Kind, rerun: bool) -> impl Iterator<Item = &'static StageSpec> {
        let stages = self.stages;
        stages
            .iter()
            .copied()
            .filter(move |s| (s.runs_in)(kind) && (s.on_rerun || !rerun))
    }

    /// The bytes of every own buffer in a try of `kind` (`None` where its stage does not
    /// run).
    pub fn own_sizes(&self, kind: Kind, sz: &Sizes, lim: &Limits) -> Vec<Option<u64>> {
        self.stages
            .iter()
            .flat_map(|s| {
                let runs = (s.runs_in)(kind);
                s.buffers
                    .iter()
                    .map(move |b| runs.then(|| (b.bytes)(kind, sz, lim)))
            })
            .collect()
    }

    /// Most work items a batch of `kind` may have: its stages' least.
    pub fn most_items(&self, kind: Kind, lim: &Limits) -> u32 {
        self.running(kind, false)
            .map(|s| (s.max_items)(lim))
            .min()
            .unwrap_or(u32::MAX)
    }

    /// Most uniform slots a try of `kind` records: its stages' together.
    pub fn most_slots(&self, kind: Kind, sz: &Sizes, lim: &Limits, parts: usize) -> usize {
        self.running(kind, false)
            .map(|s| (s.slots)(sz, lim, parts))
            .sum()
    }

    /// Compiles ahead what the stages of `kind` compile on first use.
    pub fn prepare(&self, k: &Kernels, ctx: &Context, kind: Kind) -> Result<(), EngineError> {
        self.running(kind, false)
            .try_for_each(|s| (s.prepare)(k, ctx, kind))
    }

    fn slot(&self, b: &BufferSpec) -> usize {
        self.buffers
            .iter()
            .position(|x| std::ptr::eq(*x, b))
            .unwrap_or_else(|| panic!("buffer `{}` of no registered stage", b.name))
    }
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

/// What every stage reads: the device, the kernels, the grid's buffers, the kind of
/// batch, the sizes and the bound buffers of this try.
pub struct Stage<'a> {
    pub ctx: &'a Context,
    pub k: &'a Kernels,
    pub st: &'a Statics,
    pub lim: &'a Limits,
    pub kind: Kind,
    pub seq: &'a Sequence,
    pub sz: &'a Sizes,
    pub bd: &'a Bound,
}

impl Stage<'_> {
    /// The stage's own buffer `b` (one of its [`StageSpec::buffers`]) and its bytes in
    /// this try.
    pub fn own(&self, b: &BufferSpec) -> (&wgpu::Buffer, u64) {
        let i = self.seq.slot(b);
        match (&self.bd.own[i], self.sz.own[i]) {
            (Some(buf), Some(bytes)) => (buf, bytes),
            _ => panic!(
                "buffer `{}` used in a batch its stage does not run in",
                b.name
            ),
        }
    }

    /// A workgroup per [`WG`] queries (tiled past `max_x`).
    pub(in crate::engine::gpu) fn per_query(&self) -> (u32, u32) {
        device::tiles(self.sz.n as u64, WG as u64, self.lim.max_x)
    }
}
