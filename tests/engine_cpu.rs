//! The CPU engine equals a brute-force scan exactly, on random and adversarial scenes.

mod common;

use common::*;
use glam::DVec3;
use linegs_gpu::engine::{cpu::CpuEngine, Engine, Query, Want};
use linegs_gpu::geom::Segment;
use std::sync::Arc;

fn check_exact(points: &[[f32; 3]], queries: &[Query], cell: f64) {
    let grid = Arc::new(grid_of(points, cell));
    let e = CpuEngine::new(grid.clone());
    let got = e.stats(queries, Want::ALL).unwrap();
    let ks: Vec<u64> = got.iter().map(|s| (s.count * 2) / 5).collect();
    let near = e.nearest(queries, &ks).unwrap();
    let cov = e.coverage(queries).unwrap();
    let mut union = vec![false; grid.len()];
    for (i, q) in queries.iter().enumerate() {
        let (want, members) = brute_stats(&grid, q);
        assert_eq!(got[i], want, "query {i}: {q:?}");
        let (k, off, d2) = brute_nearest(&grid, q, ks[i] as usize);
        assert_eq!(near[i].k, k);
        assert_eq!(near[i].sum_offset, off);
        assert_eq!(near[i].sum_d2, d2);
        for m in members {
            union[m] = true;
        }
    }
    let want_union = union.iter().filter(|&&b| b).count() as u64;
    assert_eq!(cov.count(), want_union);
    for (i, &b) in union.iter().enumerate() {
        assert_eq!(cov.mask[i / 64] >> (i % 64) & 1 == 1, b);
    }
}

#[test]
fn random_scenes_match_brute_force_exactly() {
    for seed in 1..4 {
        let pts = random_scene(20_000, seed);
        let qs = random_queries(300, seed + 100, 0.04);
        check_exact(&pts, &qs, 0.03);
        // a grid much coarser and much finer than the radius gives the same answers
        check_exact(&pts, &qs[..60], 0.2);
        check_exact(&pts, &qs[..60], 0.01);
    }
}

#[test]
fn points_on_cylinder_boundaries_count_inclusively() {
    let (pts, qs) = boundary_scene();
    check_exact(&pts, &qs, 0.1);
    let grid = Arc::new(grid_of(&pts, 0.1));
    let e = CpuEngine::new(grid);
    let s = e.stats(&qs, Want::ALL).unwrap();
    // r = 0.25: 17 x 4 rows on or inside the surface + the two end points on the caps;
    // the two points beyond the caps and the one just outside the radius are excluded.
    assert_eq!(s[0].count, 17 * 4 + 2);
    assert_eq!(s[1].count, s[0].count);
    // (p - m)·d > 0 with m at x = 0.5: x in 9/16..16/16 (8 values x 4) + the end point
    assert_eq!(s[0].side_pos, 8 * 4 + 1);
    // r = 0.125: the axis points and the (0.125, 0.125) diagonal points are outside
    // (0.125² + 0.125² > 0.125²), the axis row and end points are in.
    assert_eq!(s[2].count, 17 + 2);
}

#[test]
fn empty_and_degenerate_queries() {
    let pts = random_scene(1000, 9);
    let grid = Arc::new(grid_of(&pts, 0.05));
    let e = CpuEngine::new(grid);
    assert!(e.stats(&[], Want::ALL).unwrap().is_empty());
    let far = Segment::new(DVec3::splat(10.0), DVec3::splat(11.0));
    let point = Segment::new(DVec3::splat(0.5), DVec3::splat(0.5));
    let s = e
        .stats(&[Query::new(far, 0.1), Query::new(point, 0.1)], Want::ALL)
        .unwrap();
    assert_eq!(s[0].count, 0);
    assert_eq!(s[1].count, 0);
    assert!(s[0].rmse().is_infinite());
    assert!(e.nearest(&[Query::new(far, 0.1)], &[]).is_err());
}

#[test]
fn results_do_not_depend_on_thread_count() {
    let pts = random_scene(30_000, 5);
    let qs = random_queries(500, 6, 0.05);
    let grid = Arc::new(grid_of(&pts, 0.03));
    let run = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            let e = CpuEngine::new(grid.clone());
            let s = e.stats(&qs, Want::ALL).unwrap();
            let k: Vec<u64> = s.iter().map(|x| x.count / 2).collect();
            (s, e.nearest(&qs, &k).unwrap(), e.coverage(&qs).unwrap())
        })
    };
    assert_eq!(run(1), run(3));
}
