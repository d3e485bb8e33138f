//! Each refinement step does its job on a scene built for it.

mod common;

use common::*;
use linegs_gpu::refine::{crop, outliers, translate, Params};

const R: f64 = 0.03;

#[test]
fn an_offset_edge_is_pulled_back_onto_its_gaussians() {
    let mut rng = TestRng::new(1);
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let pts = edge_points(&edge, 3000, 0.004, &mut rng);
    for offset in [0.5 * R, 0.7 * R] {
        let input = seg([0.0, offset, 0.0], [1.0, offset, 0.0]);
        let e = cpu_engine(&pts, &[input], R);
        let out = translate::translate(&e, &[input], R, 0.4).unwrap();
        let moved = out[0];
        // back within a quarter of the radius, both ends, and no motion along the edge
        assert!(moved.p1.y.abs() < 0.25 * R, "offset {offset}: {moved:?}");
        assert!(moved.p2.y.abs() < 0.25 * R);
        assert!((moved.p1.x - 0.0).abs() < 1e-12 && (moved.p2.x - 1.0).abs() < 1e-12);
        assert!(moved.p1.y < offset * 0.6);
    }
}

#[test]
fn a_segment_with_no_gaussians_stays_where_it_is() {
    let mut rng = TestRng::new(2);
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let pts = edge_points(&edge, 500, 0.004, &mut rng);
    let lonely = seg([0.0, 0.5, 0.5], [1.0, 0.5, 0.5]);
    let e = cpu_engine(&pts, &[edge, lonely], R);
    let out = translate::translate(&e, &[lonely], R, 0.4).unwrap();
    assert_eq!(out[0], lonely);
}

#[test]
fn a_planted_outlier_is_dropped() {
    let mut rng = TestRng::new(3);
    let edges = [
        seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
        seg([0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        seg([1.0, 0.0, 0.0], [1.0, 1.0, 0.0]),
    ];
    let mut pts = Vec::new();
    for e in &edges {
        pts.extend(edge_points(e, 1500, 0.004, &mut rng));
    }
    // a sparse background
    for _ in 0..300 {
        let v = rng.v();
        pts.push([v.x as f32, v.y as f32, v.z as f32]);
    }
    let outlier = seg([0.2, 0.6, 0.7], [0.8, 0.5, 0.6]);
    let mut segs = edges.to_vec();
    segs.insert(1, outlier);
    let e = cpu_engine(&pts, &segs, R);
    let res = outliers::outliers(&e, &segs, R, 0.2).unwrap();
    assert_eq!(res.kept, vec![0, 2, 3]);
    assert!(res.density[1] <= res.theta && res.density[0] > res.theta);
    // the mean - 2 std rule keeps the edges too
    let res2 = outliers::outliers(&e, &segs, R, -1.0).unwrap();
    assert!(res2.kept.contains(&0) && res2.kept.contains(&2) && res2.kept.contains(&3));
}

#[test]
fn an_overextended_edge_is_cropped_back_to_its_dense_part() {
    let mut rng = TestRng::new(4);
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let pts = edge_points(&edge, 4000, 0.004, &mut rng);
    // overextended by 0.3 at P1 and by 0.15 at P2
    let input = seg([-0.3, 0.0, 0.0], [1.15, 0.0, 0.0]);
    let l = input.length();
    for params in [Params::default(), Params::reference()] {
        let e = cpu_engine(&pts, &[input], R);
        let out = crop::crop(&e, &[input], &params.with_radius(R)).unwrap()[0];
        let tol = 0.05 * l;
        assert!(out.p1.x.abs() < tol, "{:?}: {out:?}", params.profile);
        assert!(
            (out.p2.x - 1.0).abs() < tol,
            "{:?}: {out:?}",
            params.profile
        );
        // never extends, stays on the line
        assert!(out.p1.x >= input.p1.x && out.p2.x <= input.p2.x);
        assert_eq!(out.p1.y, 0.0);
        if params.fixes().crop_density {
            // the density test finds the end of the dense part closely
            assert!(out.p1.x.abs() < 0.01 * l, "{out:?}");
        } else {
            // the side-balance test stops inside the dense part: it over-crops by about
            // a third of the probe's half window (0.1 L / 3)
            assert!(out.p1.x > 0.0 && out.p2.x < 1.0, "{out:?}");
        }
    }
}

#[test]
fn a_segment_dense_to_its_ends_is_not_cropped() {
    let mut rng = TestRng::new(5);
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let pts = edge_points(&edge, 4000, 0.004, &mut rng);
    let input = seg([0.01, 0.0, 0.0], [0.99, 0.0, 0.0]);
    let e = cpu_engine(&pts, &[input], R);
    let p = Params::default();
    let out = crop::crop(&e, &[input], &p.with_radius(R)).unwrap();
    assert_eq!(out[0], input);
}

/// A model whose Gaussians come in clumps along the edge (a trained model's flat splats on
/// uniform faces, dense where the colour changes): an edge [0, 1] holding 10 clumps 0.04
/// long, one every 0.1 from 0.05 on, so each end of the segment starts in a gap. The end
/// window is empty beyond chance and the binary search stops at some gap; the whole
/// stretch it would cut still holds the middle's density, so `default` keeps the true
/// extent. Without the stretch check the end is cut by at least r.
#[test]
fn a_clumpy_edge_keeps_its_extent() {
    let mut rng = TestRng::new(6);
    let mut pts = Vec::new();
    for k in 0..10 {
        let a = 0.05 + 0.1 * k as f64;
        pts.extend(edge_points(
            &seg([a, 0.0, 0.0], [a + 0.04, 0.0, 0.0]),
            400,
            0.004,
            &mut rng,
        ));
    }
    let input = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let e = cpu_engine(&pts, &[input], R);
    let p = Params::default();
    assert!(p.fixes().crop_stretch);
    let out = crop::crop(&e, &[input], &p.with_radius(R)).unwrap()[0];
    assert_eq!(out, input);
    let mut off = Params::default();
    off.switches.fix_crop_stretch = Some(false);
    let cut = crop::crop(&e, &[input], &off.with_radius(R)).unwrap()[0];
    assert!(
        input.length() - cut.length() >= R,
        "without the stretch check the clumps' gaps cut an end: {cut:?}"
    );
    // A true overextension of 0.3 past the last clump (which ends at 0.99) is still cut
    // back to it.
    let long = seg([0.0, 0.0, 0.0], [1.3, 0.0, 0.0]);
    let e = cpu_engine(&pts, &[long], R);
    let out = crop::crop(&e, &[long], &p.with_radius(R)).unwrap()[0];
    assert!(out.p2.x < 1.03 && out.p2.x > 0.95, "{out:?}");
}

/// The command line's names in its order, as they were before the steps declared them:
/// `--help`, the report's `params` and scripts that pass options by name rely on them.
const NAMES_BEFORE: [&str; 51] = [
    "profile",
    "radius",
    "translate_keep",
    "fit",
    "fit_iterations",
    "fit_max_turn_deg",
    "fit_max_move",
    "fit_bandwidth",
    "fit_min_points",
    "fit_opacity_weight",
    "fit_gate",
    "max_scale",
    "max_sagitta",
    "split_gaps",
    "split_interior",
    "outlier_ratio",
    "collinear_merge",
    "cluster_min_weight",
    "cluster_c",
    "cluster_min_cos",
    "merge_angle_deg",
    "merge_dist_frac",
    "merge_density_ratio",
    "join_angle_deg",
    "join_gap_frac",
    "join_chord_shrink",
    "join_gap_density",
    "join_density_ratio",
    "join_rmse_ratio",
    "crop_end_frac",
    "crop_mid_frac",
    "crop_ratio",
    "crop_probe_half",
    "crop_extend",
    "crop_max_probes",
    "crop_min_interval",
    "fix_cluster_distance",
    "fix_merge_extent",
    "fix_merge_overlap",
    "fix_join_order",
    "fix_join_gap",
    "fix_crop_density",
    "fix_crop_min_cut",
    "fix_crop_chance",
    "fix_crop_stretch",
    "fix_merge_fidelity",
    "order_endpoints",
    "eval_radius",
    "unit_scale",
    "score_lambda",
    "r_l",
];

#[test]
fn the_steps_declare_the_names_of_the_command_line_in_its_order() {
    // A new parameter goes into this list where its step's group sits in `Params`.
    assert_eq!(Params::NAMES, NAMES_BEFORE);
}
