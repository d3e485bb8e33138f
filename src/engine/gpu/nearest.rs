//! Launcher of `shaders/nearest.wgsl` (two modes of one kernel) and the host side of the
//! exact k nearest: the histogram gives the bin of the k-th distance; the device sums the
//! members below it; the members inside it are ranked exactly in f64, by
//! (distance², sorted index) like `CpuEngine::nearest`.

use super::device::Context;
use super::items::CHUNK;
use super::{Job, Scratch};
use crate::engine::{EngineError, NearestSum, Query};
use crate::geom::{p64, Cylinder};
use crate::index::Grid;
use bytemuck::{Pod, Zeroable};
use glam::DVec3;

/// Histogram bins per query (`NBINS` in the shader).
pub const NBINS: usize = 64;
/// `cut` value that puts every member below the cut.
pub const ALL_BELOW: u32 = NBINS as u32;

/// `struct Below` of the shader.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Below {
    pub count: u32,
    pub sum_d2: f32,
    pub off: [f32; 3],
    pub in_cut: [u32; CHUNK / 32],
}

pub struct Nearest {
    pipeline: wgpu::ComputePipeline,
}

impl Nearest {
    pub fn new(ctx: &Context) -> Self {
        Nearest {
            pipeline: ctx.pipeline(
                "nearest",
                &super::kernel_source(include_str!("../../../shaders/nearest.wgsl")),
            ),
        }
    }

    /// Mode 0: adds the members of the slice of `job` to `hist` (`hist_bytes` long,
    /// cleared by the caller). Submits without waiting.
    pub fn histogram(
        &self,
        ctx: &Context,
        s: &mut Scratch,
        job: &Job<'_>,
        hist: &wgpu::Buffer,
        hist_bytes: u64,
    ) {
        // Mode 0 reads no cut and writes no `Below`: one slot each keeps the bindings valid.
        let below_bytes = std::mem::size_of::<Below>() as u64;
        let cut = s.cut.get(ctx, 4).clone();
        let below = s.out.get(ctx, below_bytes).clone();
        s.submit(
            ctx,
            &self.pipeline,
            job,
            0,
            &[(hist, hist_bytes), (&cut, 4), (&below, below_bytes)],
        );
    }

    /// Mode 1: per item, the members below `cut[query]` and the bitmask of those in it,
    /// handed to `f` in the slice's build order.
    pub fn below<R>(
        &self,
        ctx: &Context,
        s: &mut Scratch,
        job: &Job<'_>,
        (hist, hist_bytes): (&wgpu::Buffer, u64),
        (cut, cut_bytes): (&wgpu::Buffer, u64),
        f: impl FnOnce(&[Below]) -> R,
    ) -> Result<R, EngineError> {
        let bytes = (job.items.len() * std::mem::size_of::<Below>()) as u64;
        let below = s.out.get(ctx, bytes).clone();
        s.submit(
            ctx,
            &self.pipeline,
            job,
            1,
            &[(hist, hist_bytes), (cut, cut_bytes), (&below, bytes)],
        );
        let staging = s.staging.get(ctx, bytes).clone();
        ctx.read_back(ctx.encoder(), &below, &staging, bytes, |b| {
            f(&super::device::pods(b))
        })
    }
}

/// What the host decided for one query from its histogram.
#[derive(Clone, Copy, Debug, Default)]
pub struct Plan {
    /// `min(k, N)`.
    pub k: u64,
    /// Bin holding the k-th nearest, or `ALL_BELOW`.
    pub cut: u32,
    /// Members in the bins below the cut (what the device must report).
    pub below: u64,
    /// Members in the cut bin (the bits the device must set).
    pub in_cut: u64,
}

impl Plan {
    pub fn new(hist: &[u32], k: u64) -> Plan {
        let total: u64 = hist.iter().map(|&h| h as u64).sum();
        let k = k.min(total);
        if k == 0 || k == total {
            return Plan {
                k,
                cut: ALL_BELOW,
                below: total,
                in_cut: 0,
            };
        }
        let mut below = 0u64;
        for (b, &h) in hist.iter().enumerate() {
            if below + h as u64 >= k {
                return Plan {
                    k,
                    cut: b as u32,
                    below,
                    in_cut: h as u64,
                };
            }
            below += h as u64;
        }
        unreachable!("k <= total")
    }

    /// Members of the cut bin that complete the k nearest.
    pub fn needed(&self) -> usize {
        (self.k - self.below.min(self.k)) as usize
    }
}

/// Adds to `acc` the `plan.needed()` members of `flagged` (sorted indices, all in the
/// query's cut bin) nearest to the line, ranked by (distance², index) in f64.
pub fn resolve_cut(grid: &Grid, q: &Query, plan: &Plan, flagged: &[u32], acc: &mut NearestSum) {
    let cyl = Cylinder::new(&q.seg, q.r);
    let mut m: Vec<(f64, u32, DVec3)> = flagged
        .iter()
        .map(|&i| {
            let w = p64(grid.points[i as usize]) - cyl.p1;
            let v = w - cyl.d * w.dot(cyl.d);
            (v.length_squared(), i, v)
        })
        .collect();
    let need = plan.needed().min(m.len());
    if need == 0 {
        return;
    }
    let order =
        |a: &(f64, u32, DVec3), b: &(f64, u32, DVec3)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    if need < m.len() {
        m.select_nth_unstable_by(need - 1, order);
    }
    let first = &mut m[..need];
    first.sort_unstable_by(order);
    for x in first.iter() {
        acc.sum_d2 += x.0;
        acc.sum_offset += x.2;
    }
}

/// The exact answer on the host, for a query whose device passes disagreed (a safety net:
/// both passes run the same code on the same data, so this should never be needed).
pub fn exact(grid: &Grid, q: &Query, k: u64) -> NearestSum {
    let mut m: Vec<(f64, usize, DVec3)> = Vec::new();
    if q.seg.is_valid() {
        let cyl = Cylinder::new(&q.seg, q.r);
        grid.visit_rows(&q.seg, q.r, |row| {
            let range = grid.row_range(&row);
            let start = range.start;
            for (j, p) in grid.points[range].iter().enumerate() {
                if let Some((_, v)) = cyl.test(p64(*p)) {
                    m.push((v.length_squared(), start + j, v));
                }
            }
        });
    }
    m.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let k = (k as usize).min(m.len());
    let mut out = NearestSum {
        k: k as u64,
        ..Default::default()
    };
    for x in &m[..k] {
        out.sum_d2 += x.0;
        out.sum_offset += x.2;
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plan_finds_the_bin_of_the_kth() {
        let mut h = vec![0u32; NBINS];
        h[3] = 5;
        h[10] = 4;
        h[63] = 1;
        let p = Plan::new(&h, 7);
        assert_eq!(
            (p.k, p.cut, p.below, p.in_cut, p.needed()),
            (7, 10, 5, 4, 2)
        );
        let p = Plan::new(&h, 5);
        assert_eq!((p.cut, p.below, p.needed()), (3, 0, 5));
        let p = Plan::new(&h, 100);
        assert_eq!((p.k, p.cut, p.below, p.needed()), (10, ALL_BELOW, 10, 0));
        let p = Plan::new(&h, 0);
        assert_eq!((p.k, p.needed()), (0, 0));
    }
}
