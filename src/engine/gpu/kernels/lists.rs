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
use super::super::stages::{Recorder, Stage};
use super::super::GpuEngine;
use crate::engine::{EngineError, Query};

/// A list kernel's output, one `T` a query, as the device wrote it.
pub trait ListOut {
    fn list_out<T: bytemuck::Pod>(&self) -> Vec<T>;
}

impl ListOut for Output {
    fn list_out<T: bytemuck::Pod>(&self) -> Vec<T> {
        bytemuck::pod_collect_to_vec(&self.list)
    }
}

/// The frame of `q` every list kernel reads: `P1`, the unit direction (`Segment::dir`)
/// and the radius, in f64 (the rest zero, for the kernel's own fields).
pub fn frame(q: &Query) -> FitQuery {
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
    pub fn list(&self, rec: &mut Recorder<'_>, l: &ListKernel) {
        let (sz, bd, h) = (self.sz, self.bd, device::head);
        let (Some(fitq), Some(out), Some(pipeline), Some((world, world_bytes))) = (
            &bd.fitq,
            &bd.fitout,
            self.k.compiled(l.spec),
            &self.st.world,
        ) else {
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
        rec.bind(pipeline, base, &bind);
        let n = sz.n as u64 * FIT_WG as u64;
        rec.dispatch(device::tiles(n, FIT_WG as u64, self.lim.max_x));
    }
}

impl GpuEngine {
    /// Runs list kernel `l` over `queries` (their `frames`, one each) in sub-batches,
    /// calling `each(first query, output)` for every sub-batch in order.
    pub(in crate::engine::gpu) fn run_list(
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
