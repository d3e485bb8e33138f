//! Merge and join with duplicates (SPEC 3 steps 7-8, issue 9): the whole refinement
//! (steps 4-9, CPU engine) of `n` exact copies of one segment, and `reference` on the real
//! Line3D++ output with Gaussians sampled around it (as the tests do).
//! Targets: 10^4 copies <= 2 s; 10^5 copies <= 12x that; Line3D++ reference <= 5 s.

use criterion::{criterion_group, criterion_main, Criterion};
use glam::DVec3;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::pipeline::Refiner;
use linegs_gpu::refine::{run_steps, Params};
use linegs_gpu::{io, synth};
use std::path::Path;

/// The command line's huge-page advice for large blocks, so that the numbers are its own.
#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

fn refine(points: &[[f32; 3]], lines: &LineSet, p: &Params) -> usize {
    let r = Refiner::new(points, &lines.segments, p, Backend::Cpu).unwrap();
    // `LINEGS_BENCH_STAGES=1` prints each step's time.
    let show = std::env::var_os("LINEGS_BENCH_STAGES").is_some();
    run_steps(r.engine(), lines, r.settings(), |name, n, t| {
        if show {
            eprintln!("{name}: {n} segments, {:.3} s", t.elapsed().as_secs_f64());
        }
    })
    .unwrap()
    .len()
}

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("mergejoin");
    g.sample_size(10);
    let s = Segment::new(DVec3::new(0.1, 0.2, 0.3), DVec3::new(1.1, 0.4, 0.2));
    let points = synth::gaussians_around_segments(&[s], 20_000, 0.004, 0.1, 3);
    for n in [10_000usize, 100_000] {
        let lines = LineSet::new(vec![s; n]);
        for p in [Params::default(), Params::reference()] {
            g.bench_function(format!("copies/{n}/{:?}", p.profile), |b| {
                b.iter(|| assert_eq!(refine(&points, &lines, &p), 1))
            });
        }
    }
    let txt =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/line3dpp/line3dpp_optimized.txt");
    let lines = io::read_lines(&txt).unwrap().lines;
    let points = synth::gaussians_around_segments(&lines.segments, 150_000, 0.004, 0.1, 5);
    g.bench_function("line3dpp/Reference", |b| {
        b.iter(|| refine(&points, &lines, &Params::reference()))
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
