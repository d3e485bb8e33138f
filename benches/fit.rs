//! The edge fit against one evaluation pass, on `linegs-gpu bench`'s synthetic scene
//! (`synth::scaled_scene`, seed 7, the `default` profile's radius, CPU engine):
//! `cargo bench --bench fit`. Measured, each in one run of the same process:
//! - `pass`: `Refiner::evaluate` of the input segments (counts, sums, sides and the
//!   coverage of every cylinder: what the `evaluate_before` stage costs);
//! - `fit`: the edge fit as a refinement runs it (each segment's neighbourhood gathered
//!   once, every step on it in cache);
//! - `fit_per_iteration`: the same fit with one member batch per iteration
//!   (`engine::fit::by_batches`), the same answers.
//!
//! `LINEGS_BENCH_FIT_SIZE=10000000x100000` sets the size (default 10^6 x 10^4).

use criterion::{criterion_group, criterion_main, Criterion};
use linegs_gpu::engine::fit::by_batches;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::engine::FitJob;
use linegs_gpu::pipeline::Refiner;
use linegs_gpu::refine::fit::FitSpec;
use linegs_gpu::refine::Params;
use std::time::Duration;

/// The command line's huge-page advice for large blocks, so that the numbers are its own.
#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

fn size() -> (usize, usize) {
    let s = std::env::var("LINEGS_BENCH_FIT_SIZE").unwrap_or_else(|_| "1000000x10000".into());
    let (a, b) = s.split_once('x').expect("LINEGS_BENCH_FIT_SIZE: NxM");
    (a.parse().expect("N"), b.parse().expect("M"))
}

fn bench_fit(c: &mut Criterion) {
    let (n, m) = size();
    let scene = linegs_gpu::synth::scaled_scene(n, m, 7);
    let params = Params::default();
    let segs = &scene.lines.segments;
    let refiner = Refiner::new(&scene.gaussians, segs, &params, Backend::Cpu).unwrap();
    let r = refiner.settings().radius();
    let spec = FitSpec::from(&params.fit);
    let job = FitJob {
        segments: segs,
        r,
        spec: &spec,
        points: Default::default(),
    };
    let e = refiner.engine();
    let mut group = c.benchmark_group(format!("{n}x{m}"));
    group.sample_size(10);
    group.warm_up_time(Duration::from_millis(500));
    group.measurement_time(Duration::from_secs(5));
    group.bench_function("pass", |b| b.iter(|| refiner.evaluate(segs).unwrap()));
    group.bench_function("fit", |b| b.iter(|| e.fit_edges(&job).unwrap()));
    group.bench_function("fit_per_iteration", |b| {
        b.iter(|| by_batches(e, &job).unwrap())
    });
    group.finish();
}

criterion_group!(benches, bench_fit);
criterion_main!(benches);
