//! Clustering (SPEC 3 step 7) of 10^4 and 10^5 segments: 5 noisy copies of each edge,
//! the candidate index of the default profile. Target: 10^5 segments in under 2 s.

use criterion::{criterion_group, criterion_main, Criterion};
use glam::DVec3;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::refine::{cluster::cluster, Params};
use linegs_gpu::synth::Rng;

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

fn bench(c: &mut Criterion) {
    let s = Params::default().with_radius(0.03);
    let mut g = c.benchmark_group("cluster");
    g.sample_size(10);
    for edges in [2_000usize, 20_000] {
        let lines = scene(edges);
        g.bench_function(format!("default/{}", lines.len()), |b| {
            b.iter(|| cluster(&lines, &s))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
