//! `records.wgsl`: a members batch's sure members as records (working-set id and the
//! centre's own f32 coordinates, 16 bytes), each list in working-set order where it has at
//! most [`SORT_MAX`] members; what comes back from a members batch wherever the device
//! holds the centers' coordinates and ids ([`super::super::resources::Statics::ids`]) and
//! the batch's records fit one binding ([`Sizes::records`]; a try with records lists at
//! most a quarter of the member list's most entries, `batch::submit`).
//! The host then measures each member in f64 from its record, in the order its answer
//! keeps: it reads neither the grid's ids nor its points, and sorts only the longer lists.

use super::super::device;
use super::super::layout::{self, RECORD_BYTES, RECORD_MAX, SORT_MAX};
use super::super::pipelines::{KernelSpec, Kernels, When};
use super::super::sizes::{BufferSpec, Kind, Sizes};
use super::super::stages::{Recorder, Stage, StageSpec};
use super::kernel_source;
use crate::engine::EngineError;

pub static KERNELS: [KernelSpec; 1] = [KernelSpec {
    name: "records",
    shader: "records.wgsl",
    source: || {
        kernel_source(&format!(
            "// Generated from src/engine/gpu/kernels/records.rs: do not edit here.\n{}\n{}",
            layout::wgsl_consts(&[("SORT_MAX", SORT_MAX), ("RECORD_MAX", RECORD_MAX)]),
            include_str!("../../../../shaders/records.wgsl")
        ))
    },
    entry: "main",
    when: When::OnUse,
    structs: &[],
}];

/// The records of every try of a members batch that sends them ([`Sizes::records`]); they
/// come back instead of the member list.
pub static STAGE: StageSpec = StageSpec {
    name: "records",
    runs_in: |kind| kind == Kind::Members,
    buffers: &BUFFERS,
    record: |s, rec| s.records(rec),
    back: |s| on(s).then(|| s.own(&BUFFERS[0])),
    // Compiled at the opening where the ridge runs on the device (with the member lists
    // there too, every refinement's members batches come back through it).
    prepare: |k, ctx, _| k.records(ctx).map(|_| ()),
    ..StageSpec::BASE
};

/// The records: 16 bytes a member-list entry where [`Sizes::records`], else one word.
static BUFFERS: [BufferSpec; 1] = [BufferSpec {
    name: "records",
    bytes: |_, sz: &Sizes, _| {
        if sz.records {
            sz.members / 4 * RECORD_BYTES
        } else {
            4
        }
    },
    frames: false,
}];

/// Whether a try's members come back as records.
pub(super) fn on(s: &Stage<'_>) -> bool {
    s.kind == Kind::Members && s.sz.records
}

impl Kernels {
    /// The records pipeline, compiled now if this is its first use.
    fn records(&self, ctx: &device::Context) -> Result<&wgpu::ComputePipeline, EngineError> {
        self.get(ctx, &KERNELS[0])
    }
}

impl Stage<'_> {
    /// One workgroup a query over its member list.
    fn records(&self, rec: &mut Recorder<'_>) -> Result<(), EngineError> {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let (true, Some((world, world_bytes)), Some((ids, ids_bytes))) =
            (on(self), &self.st.world, &self.st.ids)
        else {
            return Ok(());
        };
        let pipeline = self.k.records(self.ctx)?;
        let (out, out_bytes) = self.own(&BUFFERS[0]);
        let bind = [
            h(&bd.scan, sz.scan),
            h(&bd.partials, sz.partials),
            h(&bd.results, sz.results),
            h(&bd.aux, sz.members),
            h(world, *world_bytes),
            h(ids, *ids_bytes),
            h(out, out_bytes),
        ];
        let base = rec.base;
        rec.bind(pipeline, base, &bind);
        let n = sz.n as u64 * layout::WG as u64;
        rec.dispatch(device::tiles(n, layout::WG as u64, self.lim.max_x));
        Ok(())
    }
}
