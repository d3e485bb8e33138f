//! What every kernel over the queries' member lists shares (`shaders/lists.wgsl` on the
//! device side): a batch of [`Kind::List`] lists each query's sure members on the device
//! (walk, stats pass, `members.wgsl` and the member pass), reduces, then runs the list
//! kernel, one workgroup of [`FIT_WG`] lanes per query, over bindings that are the same
//! for every such kernel: the queries' frames ([`FitQuery`], f64), the scan, the items'
//! offsets, the results, the member list, the centers' own coordinates and its own
//! per-query output ([`ListKernel::out`] bytes a query), which comes back in
//! [`Output::list`]. A new list kernel is its shader, a launcher with its [`ListKernel`]
//! and the answers it reads from that output, and one line in [`super::KERNELS`].

use super::super::batch::{Kind, Output};
use super::super::device;
use super::super::layout::{FitQuery, FIT_WG};
use super::super::pipelines::ListKernel;
use super::super::resources::Buffers;
use super::super::sizes::BufferSpec;
use super::super::stages::{Recorder, Stage, StageSpec};
use super::super::GpuEngine;
use crate::engine::{EngineError, Query};

/// The list kernel of every try of a list batch, after the reduction; its output comes
/// back.
pub static STAGE: StageSpec = StageSpec {
    name: "list",
    runs_in: |kind| matches!(kind, Kind::List(_)),
    buffers: &BUFFERS,
    record: |s, rec| {
        if let Kind::List(l) = s.kind {
            s.list(rec, l);
        }
        Ok(())
    },
    back: |s| matches!(s.kind, Kind::List(_)).then(|| s.own(&BUFFERS[OUT])),
    ..StageSpec::BASE
};

/// The queries' frames (written at the first try) and the kernel's output.
static BUFFERS: [BufferSpec; 2] = [
    BufferSpec {
        name: "fitq",
        bytes: |_, sz, _| sz.n as u64 * std::mem::size_of::<FitQuery>() as u64,
        frames: true,
    },
    BufferSpec {
        name: "fitout",
        bytes: |kind, sz, _| match kind {
            Kind::List(l) => l.out * sz.n as u64,
            _ => 0,
        },
        frames: false,
    },
];
const FRAMES: usize = 0;
const OUT: usize = 1;

/// A list kernel's output, one `T` a query, as the device wrote it (read in place).
pub(super) trait ListOut {
    fn list_out<T: bytemuck::Pod>(&self) -> std::borrow::Cow<'_, [T]>;
}

impl ListOut for Output {
    fn list_out<T: bytemuck::Pod>(&self) -> std::borrow::Cow<'_, [T]> {
        super::super::device::pods(&self.back)
    }
}

/// The frame of `q` every list kernel reads: `P1`, the unit direction (`Segment::dir`)
/// and the radius, in f64 (the rest zero, for the kernel's own fields).
pub(super) fn frame(q: &Query) -> FitQuery {
    let (p1, d) = (q.seg.p1, q.seg.dir());
    FitQuery {
        p1x: p1.x,
        p1y: p1.y,
        p1z: p1.z,
        dx: d.x,
        dy: d.y,
        dz: d.z,
        r: q.r,
        ..Default::default()
    }
}

impl Stage<'_> {
    /// List kernel `l` over each query's member list, after the reduction has counted its
    /// members. Nothing without the kernel or the centers' coordinates on the device.
    fn list(&self, rec: &mut Recorder<'_>, l: &ListKernel) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let (Some(pipeline), Some((world, world_bytes))) =
            (self.k.compiled(l.spec), &self.st.world)
        else {
            return;
        };
        let ((fitq, fitq_bytes), (out, out_bytes)) =
            (self.own(&BUFFERS[FRAMES]), self.own(&BUFFERS[OUT]));
        let bind = [
            h(fitq, fitq_bytes),
            h(&bd.scan, sz.scan),
            h(&bd.partials, sz.partials),
            h(&bd.results, sz.results),
            h(&bd.aux, sz.members),
            h(world, *world_bytes),
            h(out, out_bytes),
        ];
        let base = rec.base;
        rec.bind(pipeline, base, &bind);
        let n = sz.n as u64 * FIT_WG as u64;
        rec.dispatch(device::tiles(n, FIT_WG as u64, self.lim.max_x));
    }
}

impl GpuEngine {
    /// Runs list kernel `l` over `queries` (their `frames`, one each) in sub-batches,
    /// calling `each(first query, output)` for every sub-batch in order.
    pub(super) fn run_list(
        &self,
        b: &mut Buffers,
        l: &'static ListKernel,
        queries: &[Query],
        frames: &[FitQuery],
        each: &mut dyn FnMut(usize, Output) -> Result<(), EngineError>,
    ) -> Result<(), EngineError> {
        self.run_with(b, Kind::List(l), queries, &[], frames, each)
    }
}
