//! CPU/GPU parity: every query kind on random and adversarial
//! scenes, on whatever adapter wgpu picks (lavapipe in CI). Membership is exact on the GPU
//! engine (points within the f32 error bound of a boundary are decided on the host in
//! f64), so counts, side counts, coverage and k-nearest sets equal the CPU engine's; sums
//! agree to float precision; repeated GPU runs are identical.

mod common;

use common::*;
use glam::DVec3;
use linegs_gpu::engine::cpu::CpuEngine;
use linegs_gpu::engine::gpu::{GpuEngine, GpuOptions};
use linegs_gpu::engine::{
    axial_of_members, Ask, Coverage, Engine, EngineError, Extent, Nearest, NearestSum, Query, Want,
};
use linegs_gpu::geom::Segment;
use linegs_gpu::index::Grid;
use std::sync::Arc;

/// Float precision of a sum of `n` terms: relative to the sum of the terms' sizes (an
/// offset sum may cancel to zero).
const REL: f64 = 1e-5;

/// f32 precision of one offset, relative to the radius: a point near the axis has a tiny
/// d2 whose own relative error is large.
const REL_R: f64 = 1e-6;

fn close(a: f64, b: f64, n: u64, r: f64) -> bool {
    let r = if r.is_finite() { r } else { 0.0 };
    (a - b).abs() <= REL * a.abs().max(b.abs()) + 2.0 * REL_R * n as f64 * r * r
}

fn close_vec(a: DVec3, b: DVec3, n: u64, sum_d2: f64, r: f64) -> bool {
    let r = if r.is_finite() { r.abs() } else { 0.0 };
    (a - b).length() <= REL * (n as f64 * sum_d2).sqrt() + REL_R * n as f64 * r
}

/// `tested` answers `queries` like `reference`: counts, sides, k, coverage and member
/// lists equal, sums to float precision.
fn check_parity(reference: &dyn Engine, tested: &dyn Engine, queries: &[Query]) {
    check_members(reference, tested, queries);
    check_axial(reference, tested, queries);
    check_extent(reference, tested, queries);
    for want in [Want::COUNT, Want::SUMS, Want::SIDES, Want::ALL] {
        let a = reference.stats(queries, want).unwrap();
        let b = tested.stats(queries, want).unwrap();
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(&b).enumerate() {
            let q = &queries[i];
            assert_eq!(
                (x.count, x.side_pos),
                (y.count, y.side_pos),
                "query {i} {want:?}: {q:?}"
            );
            if !want.sums {
                assert_eq!((y.sum_d2, y.sum_offset), (0.0, DVec3::ZERO), "query {i}");
            }
            assert!(
                close(x.sum_d2, y.sum_d2, x.count, q.r),
                "query {i} {want:?}: sum_d2 {} vs {}",
                x.sum_d2,
                y.sum_d2
            );
            assert!(
                close_vec(x.sum_offset, y.sum_offset, x.count, x.sum_d2, q.r),
                "query {i} {want:?}: offsets {} vs {}",
                x.sum_offset,
                y.sum_offset
            );
        }
    }

    let counts = reference.stats(queries, Want::COUNT).unwrap();
    // k as step 4 asks (0.4 n), plus the edges: none, one, all, more than all.
    let ks: Vec<u64> = counts
        .iter()
        .enumerate()
        .map(|(i, s)| match i % 7 {
            0 => 0,
            1 => 1.min(s.count),
            2 => s.count,
            3 => s.count + 5,
            _ => (s.count * 2) / 5,
        })
        .collect();
    let a = reference.nearest(queries, &ks).unwrap();
    let b = tested.nearest(queries, &ks).unwrap();
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        assert_eq!(x.k, y.k, "query {i}");
        assert!(
            nearest_close(x, y, queries[i].r),
            "query {i}: nearest {x:?} vs {y:?} (k = {})",
            ks[i]
        );
    }

    let coverage = reference.coverage(queries).unwrap();
    assert_eq!(coverage, tested.coverage(queries).unwrap());
    check_fused(reference, tested, queries, &ks, &coverage);
}

/// The fused batch: one ask for the stats, the nearest sums (translate's `floor(0.4 n)`,
/// or explicit `k`) and the coverage answers what the separate batches answer, on both
/// engines; a nearest-only ask still gives every count.
fn check_fused(
    reference: &dyn Engine,
    tested: &dyn Engine,
    queries: &[Query],
    ks: &[u64],
    coverage: &Coverage,
) {
    let all = reference.stats(queries, Want::ALL).unwrap();
    let keep: Vec<u64> = all
        .iter()
        .map(|s| (0.4 * s.count as f64).floor() as u64)
        .collect();
    let near = reference.nearest(queries, &keep).unwrap();
    let ask = Ask {
        want: Want::ALL,
        nearest: Nearest::Keep(0.4),
        coverage: true,
    };
    let a = reference.query(queries, &ask).unwrap();
    // The CPU engine's fused walk gives its separate answers to the bit.
    assert_eq!(a.stats, all);
    assert_eq!(a.nearest, near);
    assert_eq!(a.coverage.as_ref(), Some(coverage));
    let b = tested.query(queries, &ask).unwrap();
    assert_eq!(b.coverage.as_ref(), Some(coverage));
    for (i, (x, y)) in a.stats.iter().zip(&b.stats).enumerate() {
        assert_eq!(
            (x.count, x.side_pos),
            (y.count, y.side_pos),
            "fused query {i}"
        );
        assert!(
            close(x.sum_d2, y.sum_d2, x.count, queries[i].r),
            "fused query {i}"
        );
    }
    for (i, (x, y)) in a.nearest.iter().zip(&b.nearest).enumerate() {
        assert_eq!(x.k, y.k, "fused query {i}");
        assert!(
            nearest_close(x, y, queries[i].r),
            "fused query {i}: {x:?} vs {y:?}"
        );
    }
    let ask = Ask {
        nearest: Nearest::K(ks),
        ..Default::default()
    };
    let b = tested.query(queries, &ask).unwrap();
    assert!(b.coverage.is_none());
    for (i, (x, y)) in all.iter().zip(&b.stats).enumerate() {
        assert_eq!(x.count, y.count, "nearest-only query {i}");
    }
    assert_eq!(b.nearest.len(), queries.len());
}

/// The member lists are the same, bit for bit (ids, axial positions and offsets).
fn check_members(reference: &dyn Engine, tested: &dyn Engine, queries: &[Query]) {
    let a = reference.members(queries).unwrap();
    let b = tested.members(queries).unwrap();
    assert_eq!(a.len(), b.len());
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        if x != y {
            let first = x.iter().zip(y).position(|(m, n)| m != n);
            panic!(
                "query {i}: {} members vs {}, first difference at {first:?}: {:?}",
                x.len(),
                y.len(),
                queries[i]
            );
        }
    }
}

/// The axial positions the same, bit for bit, both engines' and those of the member
/// lists (`Engine::axial`: the CPU engine's straight from its walk, the GPU engine's from
/// its device lists or, for small batches, the CPU engine's walk).
fn check_axial(reference: &dyn Engine, tested: &dyn Engine, queries: &[Query]) {
    let from_members = axial_of_members(&reference.members(queries).unwrap(), queries);
    let bits = |v: &[Vec<f64>]| -> Vec<Vec<u64>> {
        v.iter()
            .map(|t| t.iter().map(|x| x.to_bits()).collect())
            .collect()
    };
    let want = bits(&from_members);
    assert_eq!(bits(&reference.axial(queries).unwrap()), want);
    assert_eq!(bits(&tested.axial(queries).unwrap()), want);
}

/// The extents the same, bit for bit, both engines' and the ends of the sorted axial
/// positions (`Engine::extent`: the GPU engine's from the device's extent kernel).
fn check_extent(reference: &dyn Engine, tested: &dyn Engine, queries: &[Query]) {
    let bits = |e: &[Extent]| -> Vec<(u64, u64, u64)> {
        e.iter()
            .map(|e| (e.count, e.lo.to_bits(), e.hi.to_bits()))
            .collect()
    };
    let ends: Vec<Extent> = reference
        .axial(queries)
        .unwrap()
        .iter()
        .map(|t| Extent::of_sorted(t))
        .collect();
    let want = bits(&ends);
    assert_eq!(bits(&reference.extent(queries).unwrap()), want);
    let got = bits(&tested.extent(queries).unwrap());
    for (i, (x, y)) in want.iter().zip(&got).enumerate() {
        assert_eq!(x, y, "extent of query {i}: {:?}", queries[i]);
    }
    assert_eq!(got.len(), want.len());
}

fn nearest_close(x: &NearestSum, y: &NearestSum, r: f64) -> bool {
    close(x.sum_d2, y.sum_d2, x.k, r) && close_vec(x.sum_offset, y.sum_offset, x.k, x.sum_d2, r)
}

/// Both engines over `points`; `None` when there is no adapter.
fn engines(
    points: &[[f32; 3]],
    cell: f64,
    opts: GpuOptions,
) -> Option<(Arc<Grid>, CpuEngine, GpuEngine)> {
    let grid = Arc::new(grid_of(points, cell));
    let gpu = gpu_engine(grid.clone(), opts)?;
    Some((grid.clone(), CpuEngine::new(grid), gpu))
}

#[test]
fn random_scenes_match_the_cpu() {
    for seed in 1..4 {
        let pts = random_scene(20_000, seed);
        let qs = random_queries(300, seed + 100, 0.04);
        for cell in [0.03, 0.2, 0.01] {
            let Some((_, cpu, gpu)) = engines(&pts, cell, GpuOptions::default()) else {
                return;
            };
            check_parity(&cpu, &gpu, &qs);
            // The member lists came from the device, not from the host's fallback.
            assert!(gpu.host_fallbacks() <= 3, "{}", gpu.host_fallbacks());
        }
    }
}

#[test]
fn points_within_float_rounding_of_a_boundary_are_decided_like_the_cpu() {
    // Members placed a hair (1e-7 relative) inside and outside the caps and the radius,
    // where f32 cannot tell: the host decides them in f64, so the counts are exact.
    let seg = Segment::new(DVec3::new(0.1, 0.3, 0.3), DVec3::new(0.9, 0.6, 0.4));
    let r = 0.05;
    let d = seg.dir();
    let n = d.cross(DVec3::Z).normalize();
    let mut pts = random_scene(20_000, 42);
    let mut rng = TestRng::new(7);
    for i in 0..400 {
        let s = if i % 2 == 0 { 1.0 } else { -1.0 } * 1e-7 * (1.0 + rng.f());
        let p = match i % 3 {
            0 => seg.p1 + n * (r * rng.f()) - d * (s * 0.9),
            1 => seg.p2 + n * (r * rng.f()) + d * (s * 0.9),
            _ => seg.point_at(seg.length() * rng.f()) + n * (r * (1.0 + s)),
        };
        pts.push([p.x as f32, p.y as f32, p.z as f32]);
    }
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    let mut qs = random_queries(200, 43, 0.05);
    qs.push(Query::new(seg, r));
    qs.push(Query::new(seg.reversed(), r));
    check_parity(&cpu, &gpu, &qs);
    let a = cpu.stats(&qs, Want::ALL).unwrap();
    let total: u64 = a.iter().map(|s| s.count).sum();
    assert!(total > 2_000, "{total} members");
}

#[test]
fn points_on_cylinder_boundaries() {
    let (pts, qs) = boundary_scene();
    for cell in [0.1, 0.0625, 1.0] {
        let Some((grid, cpu, gpu)) = engines(&pts, cell, GpuOptions::default()) else {
            return;
        };
        check_parity(&cpu, &gpu, &qs);
        assert!(grid.len() > 60);
    }
}

/// 100,000 points in one grid cell on one segment: a query with more members than the
/// 65,535 loop iterations after which lavapipe silently stops an invocation.
fn dense_cell() -> (Vec<[f32; 3]>, Segment) {
    let mut r = TestRng::new(5);
    let pts: Vec<[f32; 3]> = (0..100_000)
        .map(|i| {
            let x = 0.1 + 0.8 * (i as f64 + 0.5) / 100_000.0;
            [
                x as f32,
                (0.5 + (r.f() - 0.5) * 0.01) as f32,
                (0.5 + (r.f() - 0.5) * 0.01) as f32,
            ]
        })
        .collect();
    let seg = Segment::new(DVec3::new(0.05, 0.5, 0.5), DVec3::new(0.95, 0.5, 0.5));
    (pts, seg)
}

/// A members batch reads back about as much of its member list as the last batch's
/// members a query suggest, and the rest in a copy of its own: a batch of a long list after
/// one of short lists still gets every member from the device.
#[test]
fn a_long_member_list_after_short_ones_comes_back_whole() {
    let (pts, seg) = dense_cell();
    let Some((_, cpu, gpu)) = engines(&pts, 0.05, GpuOptions::default()) else {
        return;
    };
    let short = [Query::new(seg, 5e-5), Query::new(seg, 3e-5)];
    let m = gpu.members(&short).unwrap();
    assert!(m[0].len() < 50, "{}", m[0].len());
    assert_eq!(m, cpu.members(&short).unwrap());
    let long = [Query::new(seg, 0.02), Query::new(seg, 0.01)];
    let m = gpu.members(&long).unwrap();
    assert_eq!(m[0].len(), 100_000);
    assert_eq!(m, cpu.members(&long).unwrap());
    // Every list from the device, none walked on the host.
    assert_eq!(gpu.host_fallbacks(), 0);
    assert_eq!(gpu.counters().host_lists, 0);
}

#[test]
fn a_query_with_more_than_65535_members_in_one_cell() {
    let (pts, seg) = dense_cell();
    let Some((grid, cpu, gpu)) = engines(&pts, 1.0, GpuOptions::default()) else {
        return;
    };
    assert_eq!(grid.n_cells(), 1);
    let qs = [
        Query::new(seg, 0.02),
        Query::with_plane(seg, 0.004, DVec3::new(0.3, 0.5, 0.5)),
    ];
    let s = gpu.stats(&qs, Want::ALL).unwrap();
    assert_eq!(s[0].count, 100_000);
    assert_eq!(s[0].side_pos, 50_000);
    let want = brute_stats(&grid, &qs[0]).0;
    assert!((s[0].sum_d2 - want.sum_d2).abs() <= 1e-4 * want.sum_d2);
    check_parity(&cpu, &gpu, &qs);
    // Answered on the device (100,000 points, 391 items of one query), not on the host.
    assert_eq!(gpu.host_fallbacks(), 0);
    let k = [40_000, 70_000];
    let near = gpu.nearest(&qs, &k).unwrap();
    let (kk, off, d2) = brute_nearest(&grid, &qs[0], 40_000);
    assert_eq!(near[0].k, kk);
    assert!((near[0].sum_d2 - d2).abs() <= 1e-4 * d2);
    assert!((near[0].sum_offset - off).length() <= 1e-4 * (kk as f64 * d2).sqrt());
    assert_eq!(gpu.coverage(&qs[..1]).unwrap().count(), 100_000);
    // The members of the dense query, from the device: all 100,000, in working-set order.
    let m = gpu.members(&qs).unwrap();
    assert_eq!(m[0].len(), 100_000);
    assert!(m[0].windows(2).all(|w| w[0].id < w[1].id));
    assert_eq!(m, cpu.members(&qs).unwrap());
    assert_eq!(gpu.host_fallbacks(), 0);

    // The edge fit: 16,000 members, just under the kernel's MAX_FIT_MEMBERS (each lane
    // then takes 250 of them a pass, at most 102 passes: 25,500 iterations), on the device
    // and like the host; the 100,000-member query goes to the host whole. (Over cells of
    // 0.05: in one cell of 1 the f32 error bound, a few 1e-6, is near the points' spacing
    // of 8e-6, and a member flagged at a cap would send the fit to the host.)
    use linegs_gpu::engine::FitAsk;
    let Some((_, cpu, gpu)) = engines(&pts, 0.05, GpuOptions::default()) else {
        return;
    };
    let part = Segment::new(DVec3::new(0.3, 0.5, 0.5), DVec3::new(0.428, 0.5, 0.5));
    let fq = [Query::new(part, 0.02), Query::new(seg, 0.02)];
    let n = cpu.members(&fq[..1]).unwrap()[0].len();
    assert!((15_000..16_384).contains(&n), "{n}");
    let spec = linegs_gpu::refine::fit::FitSpec::from(&linegs_gpu::refine::Params::default().fit);
    let ask = FitAsk::new(&spec, Default::default());
    let before = gpu.counters();
    let want = cpu.fit_lines(&fq, &ask).unwrap();
    let got = gpu.fit_lines(&fq, &ask).unwrap();
    let c = gpu.counters();
    assert_eq!(
        (
            c.device_fits - before.device_fits,
            c.device_fits_refitted - before.device_fits_refitted
        ),
        (1, 1)
    );
    for (w, g) in want.iter().zip(&got) {
        assert_eq!(w.1, g.1);
        let (w, g) = (w.0.unwrap(), g.0.unwrap());
        for t in [0.0, part.length()] {
            let d = (w.a + w.b * (t - w.t0)) - (g.a + g.b * (t - g.t0));
            assert!(d.length() <= 1e-12 * 0.02, "{w:?} vs {g:?}");
        }
    }
}

#[test]
fn empty_cells_segments_outside_and_empty_batches() {
    // Two clusters far apart: most cells between them are empty.
    let mut pts = random_scene(3_000, 8);
    pts.extend(
        random_scene(3_000, 9)
            .iter()
            .map(|p| [p[0] + 5.0, p[1], p[2] + 5.0]),
    );
    let Some((grid, cpu, gpu)) = engines(&pts, 0.05, GpuOptions::default()) else {
        return;
    };
    let through_gap = Segment::new(DVec3::new(1.5, 0.5, 1.5), DVec3::new(4.5, 0.5, 4.5));
    let outside = Segment::new(DVec3::new(-3.0, -3.0, -3.0), DVec3::new(-2.0, -3.0, -3.0));
    let crossing = Segment::new(DVec3::new(-1.0, 0.5, 0.5), DVec3::new(7.0, 0.5, 5.5));
    let point = Segment::new(DVec3::splat(0.5), DVec3::splat(0.5));
    let qs = [
        Query::new(through_gap, 0.1),
        Query::new(outside, 0.5),
        Query::new(crossing, 0.2),
        Query::new(point, 0.2),
        Query::new(crossing, -1.0),
        Query::new(crossing, f64::NAN),
    ];
    check_parity(&cpu, &gpu, &qs);
    let s = gpu.stats(&qs, Want::ALL).unwrap();
    for i in [0, 1, 3, 4, 5] {
        assert_eq!(s[i].count, 0, "query {i}");
    }
    assert!(s[2].count > 0);
    assert!(gpu.stats(&[], Want::ALL).unwrap().is_empty());
    assert!(gpu.nearest(&[], &[]).unwrap().is_empty());
    let none = gpu.coverage(&[]).unwrap();
    assert_eq!(none.mask.len(), grid.len().div_ceil(64));
    assert_eq!(none.count(), 0);
    assert!(matches!(
        gpu.nearest(&qs, &[1]),
        Err(EngineError::BadQuery { .. })
    ));
}

#[test]
fn a_grid_with_no_points() {
    let Some((_, cpu, gpu)) = engines(&[], 0.1, GpuOptions::default()) else {
        return;
    };
    let qs = random_queries(20, 3, 0.1);
    check_parity(&cpu, &gpu, &qs);
    assert_eq!(gpu.n_points(), 0);
    assert!(gpu.coverage(&qs).unwrap().mask.is_empty());
}

#[test]
fn a_hundred_thousand_queries() {
    let pts = random_scene(20_000, 21);
    let qs = random_queries(100_000, 22, 0.03);
    let Some((grid, cpu, gpu)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    let a = cpu.stats(&qs, Want::ALL).unwrap();
    let b = gpu.stats(&qs, Want::ALL).unwrap();
    for (i, (x, y)) in a.iter().zip(&b).enumerate() {
        assert_eq!((x.count, x.side_pos), (y.count, y.side_pos), "query {i}");
        assert!(
            close(x.sum_d2, y.sum_d2, x.count, qs[i].r),
            "query {i}: {x:?} vs {y:?} {:?}",
            qs[i]
        );
    }
    let k: Vec<u64> = a.iter().map(|s| s.count / 2).collect();
    let na = cpu.nearest(&qs, &k).unwrap();
    let nb = gpu.nearest(&qs, &k).unwrap();
    for (i, (x, y)) in na.iter().zip(&nb).enumerate() {
        assert!(
            x.k == y.k && nearest_close(x, y, qs[i].r),
            "query {i}: {x:?} vs {y:?}"
        );
    }
    let ca = cpu.coverage(&qs).unwrap();
    assert_eq!(ca, gpu.coverage(&qs).unwrap());
    assert!(ca.count() > 1000);
    assert!(grid.len() == 20_000);
    // Nearly every query is answered on the device.
    assert!(gpu.host_fallbacks() <= 3_000, "{}", gpu.host_fallbacks());
}

#[test]
fn split_buffers_sub_batches_and_tiled_dispatches_give_the_same_answers() {
    let pts = random_scene(20_000, 31);
    let qs = random_queries(300, 32, 0.05);
    let small = GpuOptions {
        // 3,000 points per part: the point buffer is split in 7 parts.
        max_binding_bytes: Some(3_000 * 16),
        // Sub-batches of 11 queries, split further when their items exceed 400.
        max_items: 400,
        max_workgroups_x: 2,
        max_queries: 11,
        small_batch: 0,
        ..GpuOptions::default()
    };
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, small) else {
        return;
    };
    assert_eq!(gpu.parts(), (7, 3_000));
    check_parity(&cpu, &gpu, &qs);
    let (_, _, whole) = engines(&pts, 0.03, GpuOptions::default()).unwrap();
    assert_eq!(whole.parts().0, 1);
    let a = gpu.stats(&qs, Want::ALL).unwrap();
    let b = whole.stats(&qs, Want::ALL).unwrap();
    for (x, y) in a.iter().zip(&b) {
        assert_eq!((x.count, x.side_pos), (y.count, y.side_pos));
    }
    assert_eq!(gpu.coverage(&qs).unwrap(), whole.coverage(&qs).unwrap());
    // The small buffers split the batches; they do not send its queries to the host.
    assert!(
        gpu.host_fallbacks() <= 6 * 300 / 20,
        "{}",
        gpu.host_fallbacks()
    );
}

#[test]
fn small_batches_are_answered_on_the_host_with_the_cpu_engines_answers() {
    // Kernel tests use the default options: every batch goes to the device.
    assert_eq!(GpuOptions::default().small_batch, 0);
    let pts = random_scene(20_000, 61);
    let qs = random_queries(40, 62, 0.05);
    let opts = GpuOptions {
        small_batch: 8,
        ..GpuOptions::default()
    };
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, opts) else {
        return;
    };
    let ask = Ask {
        want: Want::ALL,
        nearest: Nearest::Keep(0.4),
        coverage: true,
    };
    // A batch of 5: the CPU engine's code over the same grid, so the very same answers.
    let small = gpu.query(&qs[..5], &ask).unwrap();
    assert_eq!(small, cpu.query(&qs[..5], &ask).unwrap());
    assert!(small.stats.iter().any(|s| s.count > 0));
    let c = gpu.counters();
    assert_eq!(
        (c.batches, c.queries, c.cpu_batches, c.cpu_queries),
        (1, 5, 1, 5)
    );
    // A batch of 40 goes to the device (float sums, not the CPU's to the bit).
    check_parity(&cpu, &gpu, &qs);
    let c = gpu.counters();
    assert_eq!((c.cpu_batches, c.cpu_queries), (1, 5));
    assert!(c.batches > 1);
}

#[test]
fn extents_come_from_the_device_and_only_ties_are_walked_on_the_host() {
    // Random queries over a random scene (ends far apart), plus twins: every point of a
    // dense row doubled, so that each end of a query along the row is held by two points
    // at the same position (a tie the device cannot break: the host walks that query),
    // away from the random queries.
    let mut pts = random_scene(20_000, 81);
    let row = seg([0.1, 2.0, 0.5], [0.9, 2.0, 0.5]);
    for k in 0..400 {
        let p = row.point_at(row.length() * (k as f64 + 0.5) / 400.0);
        let p = [p.x as f32, p.y as f32, p.z as f32];
        pts.extend([p, p]);
    }
    let mut qs = random_queries(200, 82, 0.05);
    let plain = qs.len() as u64;
    qs.push(Query::new(row, 0.01));
    qs.push(Query::new(seg([0.3, 2.0, 0.5], [0.7, 2.0, 0.5]), 0.01));
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    // The queries the device leaves to the host whatever the batch (walks too long for
    // its loop bound), as a count batch finds them.
    gpu.stats(&qs[..plain as usize], Want::COUNT).unwrap();
    let left = gpu.counters().host_lists;
    let c0 = gpu.counters();
    check_extent(&cpu, &gpu, &qs[..plain as usize]);
    let c = gpu.counters();
    if gpu.fits_on_device() {
        // The device's extents: no other query walked on the host, no batch went to the
        // CPU engine.
        assert_eq!((c.host_lists - left, c.cpu_batches), (left, 0), "{c:?}");
        let items = c.device_items - c0.device_items;
        assert!(
            items > 0 && c.point_bytes - c0.point_bytes >= 16 * items,
            "{c:?}"
        );
    }
    check_extent(&cpu, &gpu, &qs);
    let twins = gpu.counters().host_lists - c.host_lists;
    let e = gpu.extent(&qs[plain as usize..]).unwrap();
    assert_eq!((e[0].count, e[1].count), (800, 400));
    if gpu.fits_on_device() {
        // The two queries along the twinned row, each tied at both ends.
        assert_eq!(twins, 2);
    }
}

#[test]
fn member_lists_go_where_the_option_says() {
    use linegs_gpu::engine::gpu::MembersOn;
    let pts = random_scene(20_000, 71);
    let qs = random_queries(40, 72, 0.05);
    let mut lists = Vec::new();
    for on in [MembersOn::Device, MembersOn::Host, MembersOn::Auto] {
        let opts = GpuOptions {
            members: on,
            ..GpuOptions::default()
        };
        let Some((_, cpu, gpu)) = engines(&pts, 0.03, opts) else {
            return;
        };
        let m = gpu.members(&qs).unwrap();
        assert_eq!(m, cpu.members(&qs).unwrap());
        // Auto: the host on a software adapter (lavapipe), the device on a hardware one.
        let host = on == MembersOn::Host || (on == MembersOn::Auto && gpu.is_software());
        let c = gpu.counters();
        assert_eq!(
            c.cpu_batches,
            u64::from(host),
            "{on:?} on {}",
            gpu.adapter()
        );
        lists.push(m);
    }
    assert!(lists[0].iter().any(|l| !l.is_empty()));
}

#[test]
fn member_lists_come_back_from_the_device_in_working_set_order() {
    // With the member lists and the ridge on the device (the options' default), a members
    // batch's lists come back as records that the device ranked by id: the host sorts
    // only the lists longer than the records kernel ranks (1,024 members) and any that a
    // flagged member puts out of order.
    let pts = random_scene(20_000, 91);
    let mut qs = random_queries(300, 92, 0.04);
    qs.extend(random_queries(30, 93, 0.25));
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    let want = cpu.members(&qs).unwrap();
    assert_eq!(gpu.members(&qs).unwrap(), want);
    assert_eq!(gpu.host_fallbacks(), 0);
    // The records need the centers' coordinates on the device (uploaded for its fit).
    if gpu.fits_on_device() {
        let long = want.iter().filter(|l| l.len() > 1024).count() as u64;
        assert!(long > 0 && long < 30, "{long} long lists");
        let sorted = gpu.lists_sorted_on_host();
        assert!(
            (long..=long + 3).contains(&sorted),
            "{sorted} lists sorted on the host, {long} longer than 1,024"
        );
    }
}

#[test]
fn member_lists_come_back_as_records_after_a_batch_too_large_for_them() {
    // A batch listing more members than the records' binding holds (a quarter of the
    // member list's most entries) grows the shared member capacity past it and lists
    // its members without records; a later, smaller batch comes back as records again.
    let pts = random_scene(20_000, 94);
    let Some((_, cpu, gpu)) = engines(&pts, 0.2, GpuOptions::default()) else {
        return;
    };
    if !gpu.fits_on_device() {
        return;
    }
    // Every point is a member of each of these.
    let all = Query::new(
        Segment::new(DVec3::new(-1.0, 0.5, 0.5), DVec3::new(2.0, 0.5, 0.5)),
        1.0,
    );
    let big = vec![all; 220];
    let lists = gpu.members(&big).unwrap();
    assert!(lists.iter().all(|l| l.len() == pts.len()));
    assert_eq!(lists[0], cpu.members(&big[..1]).unwrap()[0]);
    // 4.4 million members: more than the records of a 128 MiB binding (lavapipe's),
    // 4.2 million.
    let with_records = gpu.record_batches();
    let qs = random_queries(300, 92, 0.04);
    assert_eq!(gpu.members(&qs).unwrap(), cpu.members(&qs).unwrap());
    assert_eq!(gpu.record_batches(), with_records + 1);
    assert_eq!(gpu.host_fallbacks(), 0);
}

#[test]
fn member_lists_come_in_parts_of_whole_groups() {
    // `members_in_parts` hands every query's list out once, the CPU engine's list, in
    // whole groups (here a segment's two lines), at most `part` queries a part. The GPU
    // engine answers the whole batch in one device batch, also where its sub-batches
    // (7 queries here) end inside a group, and the receiver's time is not its host time.
    let pts = random_scene(20_000, 95);
    let qs = random_queries(300, 96, 0.04);
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    let small = GpuOptions {
        max_queries: 7,
        ..GpuOptions::default()
    };
    let Some((_, _, gpu7)) = engines(&pts, 0.03, small) else {
        return;
    };
    let want = cpu.members(&qs).unwrap();
    for (name, e) in [
        ("cpu", &cpu as &dyn Engine),
        ("gpu", &gpu),
        ("gpu, sub-batches of 7", &gpu7),
    ] {
        let before = e.counters().batches;
        let host_before = e.seconds().map_or(0.0, |s| s.0);
        let mut seen = vec![false; qs.len()];
        let mut parts = 0;
        e.members_in_parts(&qs, 2, 64, &mut |idx, lists| {
            assert!(
                idx.len() <= 64 && idx.len() % 2 == 0,
                "{name}: {}",
                idx.len()
            );
            assert_eq!(idx.len(), lists.len());
            for pair in idx.chunks(2) {
                assert!(
                    pair[0] % 2 == 0 && pair[1] == pair[0] + 1,
                    "{name}: {pair:?}"
                );
            }
            for (&i, l) in idx.iter().zip(lists) {
                assert!(!seen[i], "{name}: query {i} twice");
                seen[i] = true;
                assert_eq!(l, &want[i], "{name}: query {i}");
            }
            parts += 1;
            std::thread::sleep(std::time::Duration::from_millis(20));
            Ok(())
        })
        .unwrap();
        assert!(seen.iter().all(|&s| s), "{name}");
        assert!(parts >= 5, "{name}: {parts} parts");
        if name != "cpu" {
            assert_eq!(e.counters().batches - before, 1, "{name}");
            // 100 ms and more asleep in the receiver, none of it the engine's.
            let host = e.seconds().unwrap().0 - host_before;
            assert!(host < 0.05, "{name}: {host} s of host time");
        }
    }
    assert_eq!(gpu.host_fallbacks() + gpu7.host_fallbacks(), 0);
}

#[test]
fn the_edge_fit_runs_where_the_option_says() {
    use linegs_gpu::engine::gpu::FitOn;
    use linegs_gpu::engine::FitAsk;
    let r = 0.03;
    let (pts, qs) = ridge_scene(r);
    let spec = linegs_gpu::refine::fit::FitSpec::from(&linegs_gpu::refine::Params::default().fit);
    let ask = FitAsk::new(&spec, Default::default());
    for on in [FitOn::Device, FitOn::Host, FitOn::Auto] {
        let opts = GpuOptions {
            fit: on,
            ..GpuOptions::default()
        };
        let Some((_, cpu, gpu)) = engines(&pts, 0.03, opts) else {
            return;
        };
        // Auto: the host on a software adapter (lavapipe), the device on a hardware one
        // (both with f64 in shaders).
        let device = on == FitOn::Device || (on == FitOn::Auto && !gpu.is_software());
        assert_eq!(gpu.fits_on_device(), device, "{on:?} on {}", gpu.adapter());
        let got = gpu.fit_lines(&qs, &ask).unwrap();
        assert_eq!(gpu.counters().device_fits > 0, device, "{on:?}");
        if !device {
            // the host's step over the device's member lists: the CPU engine's answers
            assert_eq!(got, cpu.fit_lines(&qs, &ask).unwrap());
        }
    }
}

#[test]
fn repeated_runs_are_identical_and_the_points_are_uploaded_once() {
    let pts = random_scene(30_000, 51);
    let qs = random_queries(500, 52, 0.05);
    let Some((_, _, gpu)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    assert_eq!(gpu.counters().uploads, 1);
    let run = || {
        let s = gpu.stats(&qs, Want::ALL).unwrap();
        let k: Vec<u64> = s.iter().map(|x| x.count / 2).collect();
        (s, gpu.nearest(&qs, &k).unwrap(), gpu.coverage(&qs).unwrap())
    };
    let first = run();
    for _ in 0..3 {
        assert_eq!(run(), first);
    }
    let c = gpu.counters();
    assert_eq!(c.uploads, 1);
    assert_eq!(c.batches, 4 * 3);
    assert_eq!(c.queries, 4 * 3 * 500);
    assert_eq!(gpu.backend(), "gpu");
    assert!(
        gpu.host_fallbacks() <= 3 * 500 / 50,
        "{}",
        gpu.host_fallbacks()
    );
    eprintln!("adapter: {}", gpu.adapter());
}

/// Points along four ridges (spread 0.1 r across), a uniform background, and segments
/// near the ridges (offset up to 0.4 r, slightly turned) plus random ones.
fn ridge_scene(r: f64) -> (Vec<[f32; 3]>, Vec<Query>) {
    let mut g = TestRng::new(77);
    let mut pts = Vec::new();
    let mut qs = Vec::new();
    for _ in 0..4 {
        let a = g.v() * 0.6 + 0.2;
        let b = a + (g.v() - 0.5) * 0.5;
        let ridge = Segment::new(a, b);
        let d = ridge.dir();
        let e1 = d.any_orthonormal_vector();
        let e2 = d.cross(e1);
        for _ in 0..3_000 {
            let p = ridge.point_at(ridge.length() * g.f())
                + (e1 * (g.f() - 0.5) + e2 * (g.f() - 0.5)) * (0.2 * r);
            pts.push([p.x as f32, p.y as f32, p.z as f32]);
        }
        for _ in 0..12 {
            let t = 0.4 * g.f();
            let (u, v) = (
                ridge.point_at(ridge.length() * t),
                ridge.point_at(ridge.length() * (t + 0.5)),
            );
            let o1 = (e1 * (g.f() - 0.5) + e2 * (g.f() - 0.5)) * (0.8 * r);
            let o2 = (e1 * (g.f() - 0.5) + e2 * (g.f() - 0.5)) * (0.8 * r);
            qs.push(Query::new(Segment::new(u + o1, v + o2), r));
        }
    }
    for _ in 0..5_000 {
        let p = g.v();
        pts.push([p.x as f32, p.y as f32, p.z as f32]);
    }
    qs.extend(
        random_queries(40, 78, r)
            .into_iter()
            .map(|q| Query::new(q.seg, r)),
    );
    (pts, qs)
}

#[test]
fn the_device_fit_answers_like_the_host() {
    use linegs_gpu::engine::FitAsk;
    use linegs_gpu::refine::fit::{Attributes, FitSpec, How};
    use linegs_gpu::refine::Params;
    let r = 0.03;
    let (pts, qs) = ridge_scene(r);
    let spec = FitSpec::from(&Params::default().fit);
    let ask = FitAsk::new(&spec, Default::default());
    // Whole, and with the point store split in two (13 bytes a point per binding: the
    // option splits the 16-byte cell-relative points in two parts, while the 12-byte
    // coordinates the fit reads fit one binding).
    let split = GpuOptions {
        max_binding_bytes: Some(pts.len() as u64 * 13),
        ..Default::default()
    };
    let mut last = None;
    for opts in [GpuOptions::default(), split] {
        let Some((_, cpu, gpu)) = engines(&pts, 0.03, opts) else {
            return;
        };
        assert_eq!(
            gpu.parts().0,
            if opts.max_binding_bytes.is_some() {
                2
            } else {
                1
            }
        );
        // (lavapipe and the GPUs this is for have f64 in shaders; an adapter without it
        // fits on the host, and this test would prove nothing there)
        assert!(gpu.fits_on_device(), "{}", gpu.adapter());
        let want = cpu.fit_lines(&qs, &ask).unwrap();
        let got = gpu.fit_lines(&qs, &ask).unwrap();
        assert_eq!(want.len(), got.len());
        let ridges = want.iter().filter(|a| a.1 == How::Ridge).count();
        assert!(ridges >= 40, "{ridges} ridges");
        for (i, ((fw, hw), (fg, hg))) in want.iter().zip(&got).enumerate() {
            assert_eq!(hw, hg, "query {i}");
            assert_eq!(fw.is_some(), fg.is_some(), "query {i}");
            if let (Some(a), Some(b)) = (fw, fg) {
                // The fitted line at both ends of the segment, within 1e-12 r: the kernel
                // runs the host's arithmetic in f64, only the sums' order differs.
                let l = qs[i].seg.length();
                for t in [0.0, l] {
                    let qa = a.a + a.b * (t - a.t0);
                    let qb = b.a + b.b * (t - b.t0);
                    assert!(
                        (qa - qb).length() <= 1e-12 * r,
                        "query {i} at t = {t}: {a:?} vs {b:?}"
                    );
                }
            }
        }
        // Fitted on the device, but for the few queries with a member within f32
        // rounding of a boundary, which the host refits exactly.
        let c = gpu.counters();
        assert_eq!(c.device_fits + c.device_fits_refitted, qs.len() as u64);
        assert!(c.device_fits_refitted <= qs.len() as u64 / 8, "{c:?}");
        // ... and the same answers with the store split.
        if let Some(prev) = &last {
            assert_eq!(prev, &got);
        }
        last = Some(got);
    }
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    // With normals the two-face fit runs on the host over the device's members: the same
    // answers, bit for bit.
    let normals: Vec<[f32; 3]> = (0..pts.len())
        .map(|i| {
            if i % 2 == 0 {
                [0.0, 0.0, 1.0]
            } else {
                [0.0, 1.0, 0.0]
            }
        })
        .collect();
    let with = Attributes {
        normals: Some(normals),
        opacity: None,
        extent: None,
        colour: None,
    };
    let ask = FitAsk::new(&spec, with.fit_points());
    assert_eq!(
        cpu.fit_lines(&qs, &ask).unwrap(),
        gpu.fit_lines(&qs, &ask).unwrap()
    );
}

#[test]
fn the_side_nearest_and_member_kernels_compile_on_first_use() {
    use linegs_gpu::engine::gpu::FitOn;
    let pts = random_scene(20_000, 61);
    let qs = random_queries(200, 62, 0.04);
    // With the ridge on the device (lavapipe and hardware adapters have f64), the member
    // kernels compile when the device opens: every refinement's edge fit needs them; with
    // the member lists on the device too (the options' default), so does the records
    // kernel its members batches come back through.
    let Some((_, _, fits)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    if fits.fits_on_device() {
        assert_eq!(
            fits.kernels_compiled_on_use(),
            ["eval members", "members", "records"]
        );
    }
    let host_fit = GpuOptions {
        fit: FitOn::Host,
        ..GpuOptions::default()
    };
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, host_fit) else {
        return;
    };
    // Plain counts and sums (with coverage): nothing beyond the kernels compiled at open.
    let ask = Ask {
        want: Want::SUMS,
        coverage: true,
        ..Default::default()
    };
    let (a, b) = (cpu.query(&qs, &ask).unwrap(), gpu.query(&qs, &ask).unwrap());
    assert_eq!(a.coverage, b.coverage);
    assert!(
        gpu.kernels_compiled_on_use().is_empty(),
        "{:?}",
        gpu.kernels_compiled_on_use()
    );
    // Each kind of batch compiles its own kernels when first asked for, and answers.
    let s = gpu.stats(&qs, Want::SIDES).unwrap();
    let c = cpu.stats(&qs, Want::SIDES).unwrap();
    let sides = |v: &[linegs_gpu::engine::CylStats]| -> Vec<(u64, u64)> {
        v.iter().map(|x| (x.count, x.side_pos)).collect()
    };
    assert_eq!(sides(&s), sides(&c));
    assert_eq!(gpu.kernels_compiled_on_use(), ["eval sides"]);
    let k: Vec<u64> = c.iter().map(|x| x.count / 3).collect();
    let (n1, n2) = (cpu.nearest(&qs, &k).unwrap(), gpu.nearest(&qs, &k).unwrap());
    for (i, (x, y)) in n1.iter().zip(&n2).enumerate() {
        assert!(nearest_close(x, y, qs[i].r), "query {i}: {x:?} vs {y:?}");
    }
    assert_eq!(
        gpu.kernels_compiled_on_use(),
        ["eval sides", "eval histogram", "eval below", "cut"]
    );
    assert_eq!(cpu.members(&qs).unwrap(), gpu.members(&qs).unwrap());
    assert_eq!(
        gpu.kernels_compiled_on_use(),
        [
            "eval sides",
            "eval histogram",
            "eval below",
            "eval members",
            "cut",
            "members"
        ]
    );
}

#[test]
fn a_point_store_computed_for_another_grid_is_not_uploaded() {
    use linegs_gpu::engine::gpu::{GpuDevice, PointStore};
    let (a, b) = (random_scene(20_000, 71), random_scene(20_000, 72));
    let qs = random_queries(300, 73, 0.04);
    let (ga, gb) = (Arc::new(grid_of(&a, 0.03)), Arc::new(grid_of(&b, 0.03)));
    let open = || match GpuDevice::open_setup(&common::gpu_setup(GpuOptions::default())) {
        Ok(d) => Some(d),
        Err(EngineError::NoAdapter(_)) if common::skip_gpu_tests() => None,
        Err(e) => panic!("GPU engine failed to start: {e}"),
    };
    let Some(device) = open() else {
        return;
    };
    // The store of grid a, handed to an engine over grid b: b's own points are uploaded.
    let gpu = device
        .engine_with(gb.clone(), Some(PointStore::of(&ga)))
        .unwrap();
    check_parity(&CpuEngine::new(gb.clone()), &gpu, &qs);
    // Its own grid's store is used as given.
    let gpu = open()
        .unwrap()
        .engine_with(ga.clone(), Some(PointStore::of(&ga)))
        .unwrap();
    check_parity(&CpuEngine::new(ga), &gpu, &qs);
}

#[test]
fn a_warmed_up_device_answers_like_the_cpu_and_counts_none_of_its_warm_up() {
    let pts = random_scene(20_000, 81);
    let qs = random_queries(300, 82, 0.04);
    let opts = GpuOptions {
        warm_up: true,
        ..Default::default()
    };
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, opts) else {
        return;
    };
    // The warm-up's engine, batches and buffers are gone; only eager kernels ran.
    let c = gpu.counters();
    assert_eq!((c.batches, c.queries), (0, 0), "{c:?}");
    // (The member kernels compile at opening where the ridge runs on the device, and the
    // records kernel where the member lists are the device's too.)
    let eager: &[&str] = if gpu.fits_on_device() {
        &["eval members", "members", "records"]
    } else {
        &[]
    };
    assert_eq!(gpu.kernels_compiled_on_use(), eager);
    check_parity(&cpu, &gpu, &qs);
}

#[test]
fn the_device_fits_last_few_segments_go_on_on_the_host() {
    use linegs_gpu::engine::gpu::{FitOn, MembersOn};
    use linegs_gpu::engine::FitJob;
    use linegs_gpu::refine::fit::FitSpec;
    let r = 0.03;
    let (pts, qs) = ridge_scene(r);
    let segs: Vec<Segment> = qs.iter().map(|q| q.seg).collect();
    let spec = FitSpec::from(&linegs_gpu::refine::Params::default().fit);
    let job = FitJob {
        segments: &segs,
        r,
        spec: &spec,
        points: Default::default(),
    };
    let at_most = |fit_tail| GpuOptions {
        fit: FitOn::Device,
        members: MembersOn::Device,
        fit_tail,
        ..GpuOptions::default()
    };
    let Some((_, cpu, _)) = engines(&pts, r, at_most(0)) else {
        return;
    };
    let want = cpu.fit_edges(&job).unwrap();
    let still_moving = |k: u32| want.steps.iter().filter(|&&s| s > k).count();
    // (The scene's fit: every segment takes a first step, a few take a third.)
    assert!(
        still_moving(2) > 0 && still_moving(2) < still_moving(1),
        "{:?}",
        want.steps
    );
    let tail = still_moving(2);
    let mut runs = Vec::new();
    for fit_tail in [0, tail, usize::MAX] {
        let (_, _, gpu) = engines(&pts, r, at_most(fit_tail)).unwrap();
        let got = gpu.fit_edges(&job).unwrap();
        let c = gpu.counters();
        // The iterations the device ran, and one host batch for the rest where a tail
        // took over.
        assert_eq!(c.cpu_batches, u64::from(fit_tail > 0), "{fit_tail}: {c:?}");
        assert_eq!(
            c.device_fits > 0,
            fit_tail < segs.len(),
            "{fit_tail}: {c:?}"
        );
        assert_eq!(got.how, want.how, "{fit_tail}");
        assert_eq!(got.steps, want.steps, "{fit_tail}");
        for (i, (a, b)) in want.segments.iter().zip(&got.segments).enumerate() {
            let d = (a.p1 - b.p1).length().max((a.p2 - b.p2).length());
            assert!(d <= 1e-9 * r, "{fit_tail}: segment {i} {a:?} vs {b:?}");
        }
        runs.push((got, c));
    }
    // All on the host: the CPU engine's fit, bit for bit, and its steps counted as the
    // host's.
    let (all, c) = &runs[2];
    assert_eq!(all.segments, want.segments);
    let steps: u64 = want.steps.iter().map(|&s| u64::from(s)).sum();
    assert_eq!((c.cpu_queries, c.host_lists), (steps, steps), "{c:?}");
    // The tail's: the steps after the device's second iteration.
    let (_, c) = &runs[1];
    let late: u64 = want
        .steps
        .iter()
        .map(|&s| u64::from(s.saturating_sub(2)))
        .sum();
    assert_eq!(c.cpu_queries, late, "{c:?}");
}

#[test]
fn the_first_member_lists_get_room_for_the_members_the_counts_before_them_found() {
    // 800,000 members: far more than the 65,536 a new engine's member list holds.
    let pts = random_scene(200_000, 91);
    let qs = random_queries(3_000, 92, 0.05);
    let Some((_, cpu, counted)) = engines(&pts, 0.03, GpuOptions::default()) else {
        return;
    };
    let (_, _, listed) = engines(&pts, 0.03, GpuOptions::default()).unwrap();
    let members: u64 = counted
        .stats(&qs, Want::COUNT)
        .unwrap()
        .iter()
        .map(|s| s.count)
        .sum();
    assert!(members > 8 * 65_536, "{members}");
    // The work items of one members batch: the second of an engine that listed these
    // members before (its list has the room they need).
    let items = |e: &GpuEngine| e.counters().device_items;
    listed.members(&qs).unwrap();
    let first_try = items(&listed);
    listed.members(&qs).unwrap();
    let one = items(&listed) - first_try;
    // The engine that listed first ran its batch more than once (its first try's
    // buffers were a new engine's).
    assert!(first_try > one, "{first_try} {one}");
    // The engine that counted first lists them in one try, and lists them right.
    let before = items(&counted);
    let lists = counted.members(&qs).unwrap();
    assert_eq!(items(&counted) - before, one);
    assert_eq!(lists, cpu.members(&qs).unwrap());
}

#[test]
fn a_batch_needing_more_items_than_the_first_guess_is_rerun_with_room_for_them() {
    // Fine cells and long segments: hundreds of work items a query, far above the guess
    // of 24 a query that a fresh engine's buffers start from.
    let pts = random_scene(20_000, 91);
    let qs: Vec<Query> = (0..3000)
        .map(|i| {
            let t = i as f64 / 3000.0;
            let a = DVec3::new(0.02, t, 1.0 - t);
            Query::new(Segment::new(a, DVec3::new(0.98, 1.0 - t, t)), 0.04)
        })
        .collect();
    let Some((_, cpu, gpu)) = engines(&pts, 0.01, GpuOptions::default()) else {
        return;
    };
    check_parity(&cpu, &gpu, &qs);
    assert!(gpu.item_capacity() > 24 * 3000, "{}", gpu.item_capacity());
    assert_eq!(gpu.host_fallbacks(), 0);
}

#[test]
fn uploads_through_staging_memory_give_the_same_answers() {
    // A hardware adapter's path (lavapipe writes its buffers in place by default).
    let pts = random_scene(20_000, 101);
    let qs = random_queries(300, 102, 0.04);
    let opts = GpuOptions {
        mapped_uploads: false,
        ..Default::default()
    };
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, opts) else {
        return;
    };
    check_parity(&cpu, &gpu, &qs);
}

#[test]
fn a_large_device_fit_batch_matches_the_cpu() {
    // More than 256 queries (two levels in the counts' scan) and more than 65,536 work
    // items (three in the member scan), members and fit on the device: the batch records
    // more dispatches than a small one (it once ran out of its planned uniform slots, a
    // panic on every hardware adapter at 10^6 Gaussians x 10^4 segments).
    use linegs_gpu::engine::gpu::{FitOn, MembersOn};
    use linegs_gpu::engine::FitAsk;
    let pts = random_scene(200_000, 91);
    let qs = random_queries(3_000, 92, 0.05);
    let opts = GpuOptions {
        fit: FitOn::Device,
        members: MembersOn::Device,
        ..GpuOptions::default()
    };
    let Some((_, cpu, gpu)) = engines(&pts, 0.03, opts) else {
        return;
    };
    let spec = linegs_gpu::refine::fit::FitSpec::from(&linegs_gpu::refine::Params::default().fit);
    let ask = FitAsk::new(&spec, Default::default());
    let want = cpu.fit_lines(&qs, &ask).unwrap();
    let got = gpu.fit_lines(&qs, &ask).unwrap();
    let c = gpu.counters();
    assert!(c.device_fits > qs.len() as u64 / 2, "{c:?}");
    assert_eq!(c.cpu_batches, 0, "{c:?}");
    let mut moved = 0;
    for ((w, g), q) in want.iter().zip(&got).zip(&qs) {
        assert_eq!(w.1, g.1);
        let (Some(w), Some(g)) = (w.0, g.0) else {
            assert_eq!(w.0.is_some(), g.0.is_some());
            continue;
        };
        moved += 1;
        for t in [0.0, q.seg.length()] {
            let d = (w.a + w.b * (t - w.t0)) - (g.a + g.b * (t - g.t0));
            assert!(d.length() <= 1e-9 * q.r, "{w:?} vs {g:?}");
        }
    }
    assert!(moved > qs.len() / 2, "{moved}");
}
