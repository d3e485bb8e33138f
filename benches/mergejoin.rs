//! Merge and join with duplicates: the whole refinement (steps 4-9, CPU
//! engine) of `n` exact copies of one segment, and `reference` on the real Line3D++ output
//! with Gaussians sampled around it (as the tests do).
//! Targets: 10^4 copies <= 2 s; 10^5 copies <= 12x that; Line3D++ reference <= 5 s.
//!
//! `cargo bench --bench mergejoin -- dense`: dense clusters, `n` pieces of length 1e-3 on
//! six edges of a unit box (about 17 pieces over each point of an edge) with 5,000
//! Gaussians near the edges, r = 0.03, both profiles, run once each and reported with the
//! stage times and the peak resident memory. Targets: 10^5 pieces in at most 10 s and
//! 1 GB, 10^6 in at most 100 s and 4 GB. `-- dense 300000` runs other sizes.

use criterion::Criterion;
use glam::DVec3;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::pipeline::Refiner;
use linegs_gpu::refine::{run_steps, Params};
use linegs_gpu::synth::Rng;
use linegs_gpu::{io, synth};
use std::path::Path;
use std::time::Instant;

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

/// Six edges of the unit box: the three from the origin and the three from (1, 1, 1).
fn box_edges() -> Vec<Segment> {
    let (o, l) = (DVec3::ZERO, DVec3::ONE);
    [DVec3::X, DVec3::Y, DVec3::Z]
        .iter()
        .flat_map(|&a| [Segment::new(o, o + a), Segment::new(l, l - a)])
        .collect()
}

/// `n` pieces of length 1e-3 on [`box_edges`], uniformly placed, each end within 1e-4 of
/// its edge; each piece its own input line. And 5,000 Gaussians around the edges.
pub fn dense_edges(n: usize, seed: u64) -> (Vec<[f32; 3]>, LineSet) {
    let edges = box_edges();
    let mut r = Rng::new(seed);
    let mut segments = Vec::with_capacity(n);
    for k in 0..n {
        let e = edges[k % edges.len()];
        let t = r.uniform() * (1.0 - 1e-3);
        let mut jitter = || DVec3::new(r.uniform(), r.uniform(), r.uniform()) * 2e-4 - 1e-4;
        let p = e.point_at(t) + jitter();
        let q = e.point_at(t + 1e-3) + jitter();
        segments.push(Segment::new(p, q));
    }
    let points = synth::gaussians_around_segments(&edges, 5_000, 0.002, 0.0, seed);
    (points, LineSet::new(segments))
}

/// The dense cases: the sizes on the command line (`-- dense 300000`), else 10^5 and 10^6;
/// one profile only with `-- dense default` or `-- dense reference`.
fn dense() {
    let only = std::env::args().find(|a| a == "default" || a == "reference");
    let mut sizes: Vec<usize> = std::env::args().filter_map(|a| a.parse().ok()).collect();
    if sizes.is_empty() {
        sizes = vec![100_000, 1_000_000];
    }
    for n in sizes {
        let (points, lines) = dense_edges(n, 5);
        for p in [Params::default(), Params::reference()] {
            let name = format!("{:?}", p.profile).to_lowercase();
            if only.as_ref().is_some_and(|o| *o != name) {
                continue;
            }
            linegs_gpu::mem::reset_peak_rss();
            let t = Instant::now();
            let r = Refiner::new(&points, &lines.segments, &p, Backend::Cpu).unwrap();
            let mut stages = Vec::new();
            let out = run_steps(r.engine(), &lines, r.settings(), |name, _, t| {
                stages.push(format!("{name} {:.2}", t.elapsed().as_secs_f64()))
            });
            let secs = t.elapsed().as_secs_f64();
            let peak = linegs_gpu::mem::peak_rss_bytes().unwrap_or(0);
            // A stated bound reached (step 7's edges) is a result of this case too.
            let out = match out {
                Ok(out) => out,
                Err(e) => {
                    println!(
                        "mergejoin/dense/{n}/{:?}: stopped after {secs:.2} s, peak RSS {:.0} MB ({}): {e}",
                        p.profile,
                        peak as f64 / 1e6,
                        stages.join(", ")
                    );
                    continue;
                }
            };
            println!(
                "mergejoin/dense/{n}/{:?}: {secs:.2} s, peak RSS {:.0} MB, {} segments out ({})",
                p.profile,
                peak as f64 / 1e6,
                out.len(),
                stages.join(", ")
            );
        }
    }
}

fn main() {
    if std::env::args().any(|a| a == "dense") {
        dense();
        return;
    }
    let mut c = Criterion::default().configure_from_args();
    bench(&mut c);
    c.final_summary();
}
