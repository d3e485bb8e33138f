//! `eval` with and without ground truth on the toy box scene (about 20,000 Gaussians,
//! about 300 segments), its lines plus 10% strays moved 100 units away, CPU engine.
//! Target: `eval --gt` (either protocol) at most 2x `eval` without it; the nearest-sample
//! search is a k-d tree, so the strays cost no more than lines on the edges.
//! `gt_only/*`: the ground-truth metrics alone.

use criterion::{criterion_group, criterion_main, Criterion};
use glam::DVec3;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::eval::gt::{GtEdges, Protocol, Reference};
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::pipeline::{Job, Scene};
use linegs_gpu::refine::Params;
use linegs_gpu::synth;

/// The command line's huge-page advice for large blocks, so that the numbers are its own.
#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

fn bench(c: &mut Criterion) {
    let toy = synth::toy_scene(&Default::default());
    let mut segs = toy.lines.segments.clone();
    let n = segs.len();
    for (i, s) in toy.lines.segments.iter().enumerate().take(n / 10) {
        let d = DVec3::new(100.0, 3.0 * i as f64, -100.0);
        segs.push(Segment::new(s.p1 + d, s.p2 + d));
    }
    let scene = Scene::from_arrays(toy.gaussians.clone(), LineSet::new(segs.clone())).unwrap();
    let mut g = c.benchmark_group("eval_gt");
    g.sample_size(10);
    let plain = Job::new(Params::default(), Backend::Cpu);
    g.bench_function("eval", |b| b.iter(|| plain.evaluate(&scene, None).unwrap()));
    for protocol in [Protocol::Exact, Protocol::Emap] {
        let gt = Reference {
            edges: GtEdges::from_segments(&toy.gt),
            protocol,
        };
        let job = Job {
            gt: Some(gt.clone()),
            ..Job::new(Params::default(), Backend::Cpu)
        };
        g.bench_function(format!("eval_gt/{}", protocol.name()), |b| {
            b.iter(|| job.evaluate(&scene, None).unwrap())
        });
        g.bench_function(format!("gt_only/{}", protocol.name()), |b| {
            b.iter(|| gt.measure(&segs))
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
