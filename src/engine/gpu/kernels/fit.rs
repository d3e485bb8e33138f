//! `fit.wgsl`: the edge fit's ridge over each query's member list, in f64 (a list kernel,
//! [`super::lists`]): the device's ridge where it is sure, the host's exact fit otherwise.

use super::super::host;
use super::super::layout::{self, shared, FitQuery, FLAG_CANDIDATE, STATUS_HOST};
use super::super::pipelines::{FitRoute, KernelSpec, ListKernel, Route, When};
use super::super::resources::Buffers;
use super::super::GpuEngine;
use super::list_kernel_source;
use super::lists::{self, ListOut};
use crate::engine::{EngineError, FitAnswer, FitAsk, Query};
use rayon::prelude::*;
use std::sync::atomic::Ordering;

pub static KERNELS: [KernelSpec; 1] = [KernelSpec {
    name: "fit",
    shader: "fit.wgsl",
    source: fit_source,
    entry: "main",
    when: When::F64,
    structs: &[("FitOut", std::mem::size_of::<FitOut>(), FitOut::FIELDS)],
}];

/// Most mean-shift steps of the ridge (`ridge()`'s schedule in src/geom/fit.rs).
const FIT_STEPS: u32 = 100;
/// Most members of a query the fit kernel takes; a query with more is fitted on the host.
/// The kernel's loops then stay below FIT_STEPS + 1 passes of
/// `MAX_FIT_MEMBERS / FIT_WG + log2(FIT_WG)` iterations (26,724), far below lavapipe's
/// 65,535.
const MAX_FIT_MEMBERS: u32 = 16_384;
/// `FitOut::status`: the ridge found (`t0`, `a`, `b`, `weight`); no weight left (no
/// members, or the kernel lost them all: "unclear"); or a decision too close to its
/// threshold for rounding to be sure of (or a query too large) for the device: the host
/// fits the query.
const FIT_OK: u32 = 0;
const FIT_NONE: u32 = 1;
const FIT_HOST: u32 = 2;

shared! {
    /// One query's ridge from the fit kernel, in scene units and f64: the line
    /// `a + b (t - t0)` (`t` from `P1`) and the weight under the final kernel.
    struct FitOut {
        status: u32 => "u32",
        /// Mean-shift steps run.
        steps: u32 => "u32",
        weight: f64 => "f64",
        t0: f64 => "f64",
        ax: f64 => "f64", ay: f64 => "f64",
        bx: f64 => "f64", by: f64 => "f64",
    }
}

/// The fit kernel's full source ([`list_kernel_source`] of `fit.wgsl`; compiled only on
/// a device with `SHADER_F64`).
fn fit_source() -> String {
    let own = format!(
        "// Generated from src/engine/gpu/kernels/fit.rs: do not edit here.\n{}\
         const MIN_ELONGATION: f64 = {:?}lf;\n\
         const RIDGE_SHRINK: f64 = {:?}lf;\n\
         const RIDGE_STOP: f64 = {:?}lf;\n{}",
        layout::wgsl_consts(&[
            ("FIT_STEPS", FIT_STEPS),
            ("MAX_FIT_MEMBERS", MAX_FIT_MEMBERS),
            ("FIT_OK", FIT_OK),
            ("FIT_NONE", FIT_NONE),
            ("FIT_HOST", FIT_HOST),
        ]),
        crate::geom::fit::MIN_ELONGATION,
        crate::geom::fit::RIDGE_SHRINK,
        crate::geom::fit::RIDGE_STOP,
        FitOut::WGSL
    );
    list_kernel_source(&format!(
        "{own}\n{}",
        include_str!("../../../../shaders/fit.wgsl")
    ))
}

/// The ridge of each query: a [`FitOut`] a query.
static FIT: ListKernel = ListKernel {
    spec: &KERNELS[0],
    out: std::mem::size_of::<FitOut>() as u64,
};

/// [`crate::engine::Engine::fit_lines`] on the device (`kernels::ROUTES`), for the plain
/// ridge: no normals (the two-face fit stays on the host), no opacity weights, and points
/// to fit.
pub static ROUTE: FitRoute = FitRoute {
    route: Route {
        kernel: &FIT,
        answer: GpuEngine::fit_batch,
    },
    takes: |engine, spec, points| {
        points.normals.is_none() && !spec.opacity_weight && !engine.grid.is_empty()
    },
};

impl GpuEngine {
    /// The edge fit's step of every query: the ridge on the device (`fit.wgsl`, f64) over
    /// the members the batch lists there. A query whose members include a flagged
    /// boundary point, whose ridge the kernel left to the host, whose weight lies within
    /// 1e-9 (relative) of `fit_min_points`, or that the device could not take, is fitted
    /// on the host from its exact members (`host_fallbacks` counts them).
    fn fit_batch(
        &self,
        b: &mut Buffers,
        queries: &[Query],
        ask: &FitAsk<'_>,
    ) -> Result<Vec<FitAnswer>, EngineError> {
        use crate::geom::fit::{How, LineFit};
        let grid = &*self.grid;
        let p = ask.spec;
        // The host's own values (`Cylinder::new`, `basis`, `ridge`'s widths).
        let frames: Vec<FitQuery> = queries
            .par_iter()
            .enumerate()
            .with_min_len(1024)
            .map(|(i, q)| {
                let (e1, e2) = crate::geom::fit::basis(q.seg.dir());
                FitQuery {
                    e1x: e1.x,
                    e1y: e1.y,
                    e1z: e1.z,
                    e2x: e2.x,
                    e2y: e2.y,
                    e2z: e2.z,
                    h_min: p.bandwidth * q.r,
                    h_start: crate::geom::fit::ridge_start(
                        q.r,
                        p.bandwidth,
                        ask.warm.get(i).copied().unwrap_or(false),
                    ),
                    ..lists::frame(q)
                }
            })
            .collect();
        let min_points = p.min_points as f64;
        let mut out: Vec<FitAnswer> = vec![(None, How::Unclear); queries.len()];
        // Counted once for the batch, not by every answer on both threads.
        let mut on_device = vec![false; queries.len()];
        self.run_list(b, &FIT, queries, &frames, &mut |first, o| {
            let n = o.results.len();
            let qs = &queries[first..first + n];
            let spans = host::spans(&o.flags, n);
            let fits = o.list_out::<FitOut>();
            out[first..first + n]
                .par_iter_mut()
                .zip(&mut on_device[first..first + n])
                .enumerate()
                .with_min_len(8)
                .for_each(|(i, (a, dev))| {
                    let q = &qs[i];
                    let device = o.results[i].status & STATUS_HOST == 0
                        && !o.bad
                        && q.r.is_finite()
                        && q.r > 0.0
                        && !o.flags[spans[i].clone()]
                            .iter()
                            .any(|f| f.0 & FLAG_CANDIDATE == 0 && host::is_member(grid, q, f.1));
                    let answer = fits.get(i).filter(|_| device).and_then(|f| match f.status {
                        FIT_NONE => Some((None, How::Unclear)),
                        FIT_OK => {
                            let w = f.weight;
                            // Within rounding of the threshold: the host decides.
                            if (w - min_points).abs() <= 1e-9 * min_points.max(1.0) {
                                return None;
                            }
                            if w < min_points {
                                return Some((None, How::Unclear));
                            }
                            let line = LineFit {
                                t0: f.t0,
                                a: glam::DVec2::new(f.ax, f.ay),
                                b: glam::DVec2::new(f.bx, f.by),
                            };
                            // A decision of the caller's close to its threshold: exact.
                            if ask.sensitive.is_some_and(|s| s(first + i, &line)) {
                                return None;
                            }
                            Some((Some(line), How::Ridge))
                        }
                        _ => None,
                    });
                    *dev = answer.is_some();
                    *a = answer.unwrap_or_else(|| {
                        self.to_host();
                        let m = self.cpu_members(q);
                        let one = FitAsk {
                            warm: ask.warm.get(first + i..=first + i).unwrap_or(&[]),
                            ..*ask
                        };
                        crate::engine::fit::steps(std::slice::from_ref(q), &[m], &one)[0]
                    });
                });
            Ok(())
        })?;
        let fitted = on_device.iter().filter(|&&d| d).count() as u64;
        self.device_fits.fetch_add(fitted, Ordering::Relaxed);
        self.device_fits_refitted
            .fetch_add(queries.len() as u64 - fitted, Ordering::Relaxed);
        Ok(out)
    }
}
