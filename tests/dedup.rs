//! Copies cost once: the [`Dedup`] wrapper that every `Refiner` puts around its
//! engine answers a batch full of identical queries exactly as the bare engine does, and
//! a refinement of copied segments is the same with and without it.

mod common;

use common::*;
use glam::DVec3;
use linegs_gpu::engine::dedup::Dedup;
use linegs_gpu::engine::gpu::GpuOptions;
use linegs_gpu::engine::{Engine, Query, Want};
use linegs_gpu::eval;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::index::{Grid, WorkingSet};
use linegs_gpu::pipeline::grid_cell;
use linegs_gpu::refine::{run_steps, Params, Settings};
use std::sync::Arc;

/// Each of `distinct` queries asked 1 to ~10 times, interleaved, with per-query k.
fn copied_batch(distinct: &[Query], n: usize, seed: u64) -> (Vec<Query>, Vec<u64>) {
    let mut g = TestRng::new(seed);
    let mut q = Vec::with_capacity(n);
    let mut k = Vec::with_capacity(n);
    for _ in 0..n {
        q.push(distinct[(g.f() * distinct.len() as f64) as usize]);
        k.push(if g.f() < 0.5 { 3 } else { 50 });
    }
    (q, k)
}

/// Dedup(engine) answers equal the bare engine's, query for query, and the inner engine
/// answered only the distinct queries.
fn check_engine(bare: &dyn Engine, wrapped: &Dedup) {
    let distinct = random_queries(30, 5, 0.04);
    let (q, k) = copied_batch(&distinct, 400, 6);
    let before = wrapped.counters().queries;
    for want in [Want::COUNT, Want::SUMS, Want::SIDES, Want::ALL] {
        assert_eq!(
            wrapped.stats(&q, want).unwrap(),
            bare.stats(&q, want).unwrap()
        );
    }
    assert_eq!(
        wrapped.nearest(&q, &k).unwrap(),
        bare.nearest(&q, &k).unwrap()
    );
    assert_eq!(wrapped.coverage(&q).unwrap(), bare.coverage(&q).unwrap());
    assert_eq!(wrapped.members(&q).unwrap(), bare.members(&q).unwrap());
    // 4 stats, 1 coverage and 1 members batch of <= 30 queries, 1 nearest batch of <= 60.
    let answered = wrapped.counters().queries - before;
    assert!(answered <= 6 * 30 + 60, "{answered} queries answered");
    assert!(wrapped.asked() >= 7 * 400);
}

fn scene_grid() -> (Vec<[f32; 3]>, Arc<Grid>) {
    let pts = random_scene(6000, 3);
    let g = Arc::new(grid_of(&pts, 0.05));
    (pts, g)
}

#[test]
fn cpu_engine_answers_are_unchanged_by_dedup() {
    let (_, g) = scene_grid();
    let bare = linegs_gpu::engine::cpu::CpuEngine::new(g.clone());
    let wrapped = Dedup::new(Box::new(linegs_gpu::engine::cpu::CpuEngine::new(g)));
    check_engine(&bare, &wrapped);
}

#[test]
fn gpu_engine_answers_are_unchanged_by_dedup() {
    let (_, g) = scene_grid();
    let Some(bare) = gpu_engine(g.clone(), GpuOptions::default()) else {
        return;
    };
    let Some(inner) = gpu_engine(g, GpuOptions::default()) else {
        return;
    };
    let wrapped = Dedup::new(Box::new(inner));
    assert_eq!(wrapped.backend(), "gpu");
    check_engine(&bare, &wrapped);
}

/// Three edges, each seen as three noisy segments; every segment copied 20 times in a
/// shuffled order, and a sparse outlier copied 5 times.
fn copied_scene() -> (Vec<[f32; 3]>, LineSet) {
    let mut rng = TestRng::new(9);
    let edges = [
        seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
        seg([0.0, 0.0, 0.0], [0.0, 0.8, 0.1]),
        seg([1.0, 0.0, 0.0], [1.0, 0.9, 0.0]),
    ];
    let mut pts = Vec::new();
    for e in &edges {
        pts.extend(edge_points(e, 1500, 0.004, &mut rng));
    }
    for _ in 0..300 {
        let v = rng.v();
        pts.push([v.x as f32, v.y as f32, v.z as f32]);
    }
    let mut distinct = Vec::new();
    for e in &edges {
        for _ in 0..3 {
            let n = |r: &mut TestRng| (r.v() - 0.5) * 0.02;
            let a = e.p1 + n(&mut rng) + (e.p2 - e.p1) * 0.1 * rng.f();
            let b = e.p2 + n(&mut rng) - (e.p2 - e.p1) * 0.1 * rng.f();
            distinct.push(Segment::new(a, b));
        }
    }
    let outlier = Segment::new(DVec3::new(0.2, 0.6, 0.7), DVec3::new(0.8, 0.5, 0.6));
    let mut segs: Vec<Segment> = Vec::new();
    for s in &distinct {
        segs.extend(std::iter::repeat_n(*s, 20));
    }
    segs.extend(std::iter::repeat_n(outlier, 5));
    // Fisher-Yates with the test LCG.
    for i in (1..segs.len()).rev() {
        let j = (rng.f() * (i + 1) as f64) as usize;
        segs.swap(i, j.min(i));
    }
    (pts, LineSet::new(segs))
}

#[test]
fn refining_copied_segments_gives_the_same_output_with_and_without_dedup() {
    let (pts, lines) = copied_scene();
    for params in [Params::default(), Params::reference()] {
        let ws = WorkingSet::new(&pts, &lines.segments);
        let s = Settings::resolve(params.clone(), &ws.points).unwrap();
        let grid = Arc::new(Grid::build(&ws.points, ws.bounds, grid_cell(&s)));
        let bare = linegs_gpu::engine::cpu::CpuEngine::new(grid.clone());
        let wrapped = Dedup::new(Box::new(linegs_gpu::engine::cpu::CpuEngine::new(grid)));
        let a = run_steps(&bare, &lines, &s, |_, _, _| {}).unwrap();
        let b = run_steps(&wrapped, &lines, &s, |_, _, _| {}).unwrap();
        assert_eq!(a, b, "{:?}", params.profile);
        assert!(a.len() < lines.len() / 5, "{} of {}", a.len(), lines.len());
        for segs in [&lines.segments, &a.segments] {
            let m = |e: &dyn Engine| eval::evaluate(e, segs, s.eval(), s.r_l(), None).unwrap();
            assert_eq!(m(&bare), m(&wrapped));
        }
        // The copies were asked once: far fewer queries reached the inner engine (the
        // later steps see merged, distinct segments; translate's fused batch asks once).
        let (asked, answered) = (wrapped.asked(), wrapped.counters().queries);
        assert!(answered * 3 < asked, "{answered} of {asked}");
        assert_eq!(asked, bare.counters().queries);
    }
}
