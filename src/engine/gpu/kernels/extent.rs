//! `extent.wgsl`: each query's extent over its member list, in f64 (a list kernel,
//! [`super::lists`]): the ends of the sure members from the device, each taken from its
//! member's own f64 position on the host.

use super::super::answers::per_query;
use super::super::host;
use super::super::layout::{self, shared, FitQuery, FLAG_CANDIDATE, STATUS_HOST};
use super::super::pipelines::{ExtentFn, KernelSpec, ListKernel, Route, When};
use super::super::resources::Buffers;
use super::super::GpuEngine;
use super::list_kernel_source;
use super::lists::{self, ListOut};
use crate::engine::{EngineError, Extent, Query};
use crate::geom::{p64, Cylinder};
use crate::index::Grid;

pub static KERNELS: [KernelSpec; 1] = [KernelSpec {
    name: "extent",
    shader: "extent.wgsl",
    source: || {
        let own = format!(
            "// Generated from src/engine/gpu/kernels/extent.rs: do not edit here.\n{}{}",
            layout::wgsl_consts(&[
                ("MAX_EXTENT_MEMBERS", MAX_EXTENT_MEMBERS),
                ("EXTENT_OK", EXTENT_OK),
                ("EXTENT_NONE", EXTENT_NONE),
                ("EXTENT_HOST", EXTENT_HOST),
            ]),
            ExtentOut::WGSL
        );
        list_kernel_source(&format!(
            "{own}\n{}",
            include_str!("../../../../shaders/extent.wgsl")
        ))
    },
    entry: "main",
    when: When::F64,
    structs: &[(
        "ExtentOut",
        std::mem::size_of::<ExtentOut>(),
        ExtentOut::FIELDS,
    )],
}];

/// Most members of a query the extent kernel takes (its loop runs
/// `MAX_EXTENT_MEMBERS / FIT_WG + log2(FIT_WG)` iterations: 16,390); a query with more is
/// the host's.
const MAX_EXTENT_MEMBERS: u32 = 1 << 20;
/// `ExtentOut::status`: the ends found; no sure member; the host answers the query.
const EXTENT_OK: u32 = 0;
const EXTENT_NONE: u32 = 1;
const EXTENT_HOST: u32 = 2;

shared! {
    /// One query's extent from the extent kernel (`extent.wgsl`, f64): the smallest and
    /// largest axial position of its sure members (from `P1`, unclamped), the members
    /// (sorted indices) holding them, and each end's runner-up (`±1e300`: none).
    struct ExtentOut {
        status: u32 => "u32",
        ilo: u32 => "u32",
        ihi: u32 => "u32",
        pad0: u32 => "u32",
        lo: f64 => "f64",
        lo2: f64 => "f64",
        hi: f64 => "f64",
        hi2: f64 => "f64",
    }
}

/// The extent of each query: an [`ExtentOut`] a query.
static EXTENT: ListKernel = ListKernel {
    spec: &KERNELS[0],
    out: std::mem::size_of::<ExtentOut>() as u64,
};

/// [`crate::engine::Engine::extent`] on the device (`kernels::ROUTES`).
pub static ROUTE: Route<ExtentFn> = Route {
    kernel: &EXTENT,
    answer: GpuEngine::extent_batch,
};

impl GpuEngine {
    /// Every query's extent (see [`crate::engine::Engine::extent`]) from device batches:
    /// the count and the ends of the sure members from the device (`extent.wgsl`), each
    /// end taken from its member's own f64 position; the flagged points decided and added
    /// on the host. A query whose end the device cannot tell apart from its runner-up
    /// (within 1e-9 of the coordinates' scale, beyond any f64 rounding of the kernel's),
    /// or that the device leaves to the host, is walked on the host (`host_fallbacks`).
    fn extent_batch(&self, b: &mut Buffers, queries: &[Query]) -> Result<Vec<Extent>, EngineError> {
        let frames: Vec<FitQuery> = queries.iter().map(lists::frame).collect();
        let mut out = vec![Extent::default(); queries.len()];
        let grid = &*self.grid;
        self.run_list(b, &EXTENT, queries, &frames, &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            let extents = o.list_out::<ExtentOut>();
            per_query(&mut out[first..first + n], &o, 64, |i, flags, e| {
                let q = &qs[i];
                let device = o.results[i].status & STATUS_HOST == 0 && !o.bad;
                let got = extents
                    .get(i)
                    .filter(|_| device)
                    .and_then(|x| decide(grid, q, o.results[i].count, x, flags));
                *e = got.unwrap_or_else(|| {
                    self.to_host();
                    self.cpu_extent(q)
                });
            });
            Ok(())
        })?;
        Ok(out)
    }
}

/// One query's extent ([`crate::engine::Engine::extent`]) from the device's: `sure` sure
/// members (the stats pass's count), the members holding the smallest and largest axial
/// position among them with each end's runner-up (`x`, f64 on the device), and the
/// flagged points (`flags`), decided with the CPU engine's own f64 test. Each end is its
/// member's own f64 position from that test, so the answer is the CPU engine's bit for
/// bit whenever the device's choice of member is: where the runner-up lies within 1e-9 of
/// the coordinates' scale of the end (far above the kernel's f64 rounding), a tie the
/// rounding could turn, `None` (as for a point outside the grid, a member the test
/// rejects, or a status the host must answer): the caller walks the query on the host.
fn decide(
    grid: &Grid,
    q: &Query,
    sure: u32,
    x: &ExtentOut,
    flags: &[(u32, u32)],
) -> Option<crate::engine::Extent> {
    let mut e = crate::engine::Extent::default();
    if !host::valid(q) {
        return None;
    }
    let cyl = Cylinder::new(&q.seg, q.r);
    let l = q.seg.length();
    let t_of = |i: u32| -> Option<f64> {
        let p = grid.points.get(i as usize)?;
        cyl.test(p64(*p)).map(|(t, _)| t)
    };
    match x.status {
        EXTENT_NONE if sure == 0 => {}
        EXTENT_OK if sure > 0 => {
            let (a, b) = (q.seg.p1.abs().max_element(), q.seg.p2.abs().max_element());
            let tol = 1e-9 * (a.max(b) + l + q.r.abs());
            if !(x.lo2 - x.lo > tol && x.hi - x.hi2 > tol) && sure > 1 {
                return None;
            }
            let (lo, hi) = (t_of(x.ilo)?, t_of(x.ihi)?);
            e = crate::engine::Extent {
                count: sure as u64,
                lo: lo.clamp(0.0, l),
                hi: hi.clamp(0.0, l),
            };
        }
        _ => return None,
    }
    for f in flags.iter().filter(|f| f.0 & FLAG_CANDIDATE == 0) {
        if let Some(t) = t_of(f.1) {
            e.add(t.clamp(0.0, l));
        }
    }
    Some(e)
}
