//! Clustering (docs/method.md, step 7).
//!
//! `cargo bench --bench cluster`: 10^4 and 10^5 segments, 5 noisy copies of each edge, the
//! candidate index of the default profile (criterion). Target: 10^5 segments in under 2 s.
//!
//! `cargo bench --bench cluster -- dense`: short segments on the edges of boxes at a fixed
//! density (10^5 on one box, 10^6 on ten), each segment its own input line, run once and
//! reported with the peak resident memory. Targets: 10^5 in at most 10 s and 1 GB, 10^6
//! in at most 100 s and 4 GB.

use criterion::Criterion;
use glam::DVec3;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::refine::{cluster::cluster, Params};
use linegs_gpu::synth::Rng;
use std::time::Instant;

/// The command line's huge-page advice for large blocks, so that the numbers are its own.
#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

fn scene(edges: usize) -> LineSet {
    let mut r = Rng::new(11);
    let mut v = || DVec3::new(r.uniform(), r.uniform(), r.uniform());
    let mut segments = Vec::with_capacity(edges * 5);
    let extent = (edges as f64 / 20_000.0).cbrt() * 5.0;
    for _ in 0..edges {
        let a = v() * extent;
        let b = a + (v() - 0.5) * 0.2;
        for _ in 0..5 {
            segments.push(Segment::new(a + (v() - 0.5) * 0.03, b + (v() - 0.5) * 0.03));
        }
    }
    LineSet::new(segments)
}

/// `n` short segments (length 0.02 to 0.05, endpoints within 0.003 of the edge) on the 12
/// edges of unit boxes, 10^5 per box, the boxes 2 apart along x.
pub fn dense_boxes(n: usize, seed: u64) -> LineSet {
    let mut r = Rng::new(seed);
    let boxes = n.div_ceil(100_000);
    let corners = |k: usize| DVec3::new((k & 1) as f64, ((k >> 1) & 1) as f64, (k >> 2) as f64);
    let box_edges: Vec<(DVec3, DVec3)> = (0..8)
        .flat_map(|a| (0..3).map(move |axis| (a, a | (1 << axis))))
        .filter(|&(a, b)| a != b)
        .map(|(a, b)| (corners(a), corners(b)))
        .collect();
    let mut segments = Vec::with_capacity(n);
    for k in 0..n {
        let offset = DVec3::new(2.0 * (k % boxes) as f64, 0.0, 0.0);
        let (a, b) = box_edges[(r.uniform() * 12.0) as usize % 12];
        let len = 0.02 + 0.03 * r.uniform();
        let t = r.uniform() * (1.0 - len);
        let mut jitter = || DVec3::new(r.uniform(), r.uniform(), r.uniform()) * 0.006 - 0.003;
        let p = a + (b - a) * t + offset + jitter();
        let q = a + (b - a) * (t + len) + offset + jitter();
        segments.push(Segment::new(p, q));
    }
    LineSet::new(segments)
}

/// The dense cases: the sizes on the command line (`-- dense 300000`), else 10^5 and 10^6.
fn dense() {
    let s = Params::default().with_radius(0.03);
    let mut sizes: Vec<usize> = std::env::args().filter_map(|a| a.parse().ok()).collect();
    if sizes.is_empty() {
        sizes = vec![100_000, 1_000_000];
    }
    for n in sizes {
        let lines = dense_boxes(n, 7);
        linegs_gpu::mem::reset_peak_rss();
        let base = linegs_gpu::mem::current_rss_bytes().unwrap_or(0);
        let t = Instant::now();
        let clusters = cluster(&lines, &s).unwrap();
        let secs = t.elapsed().as_secs_f64();
        let peak = linegs_gpu::mem::peak_rss_bytes().unwrap_or(0);
        // FNV-1a over every member in order: equal digests, equal clusters.
        let digest = clusters.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, c| {
            c.iter()
                .chain([&usize::MAX])
                .fold(h, |h, &m| (h ^ m as u64).wrapping_mul(0x100_0000_01b3))
        });
        println!(
            "cluster/dense/{n}: {secs:.2} s, {} clusters (digest {digest:016x}), peak RSS {:.0} MB ({:.0} MB above the input)",
            clusters.len(),
            peak as f64 / 1e6,
            peak.saturating_sub(base) as f64 / 1e6
        );
    }
}

fn main() {
    if std::env::args().any(|a| a == "dense") {
        dense();
        return;
    }
    let mut c = Criterion::default().configure_from_args();
    let s = Params::default().with_radius(0.03);
    let mut g = c.benchmark_group("cluster");
    g.sample_size(10);
    for edges in [2_000usize, 20_000] {
        let lines = scene(edges);
        g.bench_function(format!("default/{}", lines.len()), |b| {
            b.iter(|| cluster(&lines, &s).unwrap())
        });
    }
    g.finish();
    c.final_summary();
}
