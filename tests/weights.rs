//! Beyond the paper, the Gaussians' attributes and shapes: opacity as the edge fit's
//! weight (`--fit-opacity-weight`), the scale cut (`--max-scale`) and the straightness test
//! (`--max-sagitta`), each on a scene built for it.

mod common;

use common::*;
use glam::DVec3;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::pipeline::{Job, Scene};
use linegs_gpu::refine::fit::{cut_to_working_set, fit_edges, Attributes};
use linegs_gpu::refine::straight::straightness;
use linegs_gpu::refine::{run_steps_noted, Params, Profile};

const R: f64 = 0.03;

/// Distance of the segment's midpoint from the x axis.
fn mid_off_axis(s: &Segment) -> f64 {
    let m = s.point_at(0.5 * s.length());
    (m.y * m.y + m.z * m.z).sqrt()
}

#[test]
fn opacity_weighting_keeps_the_line_on_the_opaque_edge_not_on_faint_floaters() {
    let mut rng = TestRng::new(21);
    // An opaque edge on the x axis and three times as many faint floaters 0.45 r beside it.
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let faint = seg([0.0, 0.45 * R, 0.0], [1.0, 0.45 * R, 0.0]);
    let mut pts = edge_points(&edge, 1000, 0.03 * R, &mut rng);
    let mut opacity = vec![0.95f32; pts.len()];
    pts.extend(edge_points(&faint, 3000, 0.03 * R, &mut rng));
    opacity.resize(pts.len(), 0.05);
    let input = seg([0.0, 0.22 * R, 0.0], [1.0, 0.22 * R, 0.0]);
    let e = cpu_engine(&pts, &[input], R);
    let attrs = Attributes {
        normals: None,
        opacity: cut_to_working_set(&pts, &opacity, &[input]),
        extent: None,
        colour: None,
    };
    let weighted = {
        let mut q = Params::default();
        q.fit.fit_opacity_weight = true;
        q
    };
    let f = fit_edges(&e, &[input], &attrs, R, &weighted.fit).unwrap();
    assert!(
        mid_off_axis(&f.segments[0]) < 0.05 * R,
        "{:?}",
        f.segments[0]
    );
    // Unweighted (the default), the floaters' count wins.
    let f = fit_edges(&e, &[input], &attrs, R, &Params::default().fit).unwrap();
    assert!(
        mid_off_axis(&f.segments[0]) > 0.35 * R,
        "{:?}",
        f.segments[0]
    );
}

/// An edge of small Gaussians on the x axis, a denser band of wide ones (a blurry surface)
/// 0.5 r beside it, and the input line between them.
fn wide_band_scene() -> (Scene, usize) {
    let mut rng = TestRng::new(22);
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let band = seg([0.0, 0.5 * R, 0.0], [1.0, 0.5 * R, 0.0]);
    let mut pts = edge_points(&edge, 2000, 0.03 * R, &mut rng);
    let mut scales = vec![(0.1 * R) as f32; pts.len()];
    let wide = 6000;
    pts.extend(edge_points(&band, wide, 0.03 * R, &mut rng));
    scales.resize(pts.len(), (3.0 * R) as f32);
    let input = seg([0.0, 0.25 * R, 0.0], [1.0, 0.25 * R, 0.0]);
    let mut scene = Scene::from_arrays(pts, LineSet::new(vec![input])).unwrap();
    scene.max_scale = Some(scales);
    (scene, wide)
}

#[test]
fn the_scale_cut_leaves_out_wide_gaussians_and_the_line_stays_on_the_edge() {
    let (scene, wide) = wide_band_scene();
    let params = Params::default().with_radius(R).params().clone();
    assert_eq!(
        params.fit.max_scale_for(params.profile),
        1.0,
        "on in the default profile"
    );
    let out = Job::new(params.clone(), Backend::Cpu)
        .refine(&scene, |_| {})
        .unwrap();
    let notes = out.report.refine.as_ref().unwrap();
    assert_eq!(notes.scale_cut, Some(wide));
    assert!(
        mid_off_axis(&out.lines.segments[0]) < 0.1 * R,
        "{:?}",
        out.lines.segments[0]
    );
    // The metrics are the whole model's, as `eval` gives them.
    let ev = Job::new(params.clone(), Backend::Cpu)
        .evaluate(&scene, Some(&out.lines))
        .unwrap();
    assert_eq!(out.report.before, ev.before);
    assert_eq!(out.report.after, ev.after);
    assert_eq!(out.report.input.n_box, scene.gaussians.len());
    // Without the cut the wide band makes the ridge unsure (its mode moves with the
    // kernel's width) and the line does not reach the edge.
    let keep_all = {
        let mut q = params.clone();
        q.fit.max_scale = Some(0.0);
        q
    };
    let out = Job::new(keep_all, Backend::Cpu)
        .refine(&scene, |_| {})
        .unwrap();
    assert_eq!(out.report.refine.as_ref().unwrap().scale_cut, None);
    assert!(
        mid_off_axis(&out.lines.segments[0]) > 0.2 * R,
        "{:?}",
        out.lines.segments[0]
    );
    // The reference profile keeps every Gaussian, as the authors' code does.
    assert_eq!(
        Params::reference().fit.max_scale_for(Profile::Reference),
        0.0
    );
}

/// A sharp edge drawn by small Gaussians on the x axis, and a second true edge 10 r away
/// (on the line y = 10 r) that the model holds only as wide Gaussians (a thin feature of a
/// coarse model, splats wider than the cylinder along it); a line on each.
fn witnessed_by_wide_scene() -> Scene {
    let mut rng = TestRng::new(23);
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    let thin = seg([0.0, 10.0 * R, 0.0], [1.0, 10.0 * R, 0.0]);
    let mut pts = edge_points(&edge, 2000, 0.03 * R, &mut rng);
    let mut scales = vec![(0.1 * R) as f32; pts.len()];
    // Wide Gaussians' centers spread over 0.5 r around the thin edge.
    pts.extend(edge_points(&thin, 600, 0.5 * R, &mut rng));
    scales.resize(pts.len(), (2.0 * R) as f32);
    let lines = vec![edge, thin];
    let mut scene = Scene::from_arrays(pts, LineSet::new(lines)).unwrap();
    scene.max_scale = Some(scales);
    scene
}

#[test]
fn wide_gaussians_witness_a_line_that_they_do_not_place() {
    let scene = witnessed_by_wide_scene();
    let params = Params::default().with_radius(R).params().clone();
    let out = Job::new(params.clone(), Backend::Cpu)
        .refine(&scene, |_| {})
        .unwrap();
    assert_eq!(out.report.refine.as_ref().unwrap().scale_cut, Some(600));
    // Left out of the placing steps only: the thin edge's line has no small Gaussian in
    // its cylinder, yet the outlier step (which sees the whole model) keeps it, where it
    // was.
    assert_eq!(out.lines.len(), 2, "{:?}", out.lines.segments);
    let thin = out
        .lines
        .segments
        .iter()
        .find(|s| s.p1.y > 5.0 * R)
        .expect("the thin edge's line");
    assert!(
        (thin.p1.y - 10.0 * R).abs() < 1e-9 && (thin.p2.y - 10.0 * R).abs() < 1e-9,
        "{thin:?}"
    );
}

#[test]
fn the_report_counts_the_placing_engines_batches_too() {
    let scene = witnessed_by_wide_scene();
    let run = |fit| {
        let params = {
            let mut q = Params::default().with_radius(R).params().clone();
            q.fit.fit = Some(fit);
            q
        };
        let out = Job::new(params, Backend::Cpu)
            .refine(&scene, |_| {})
            .unwrap();
        out.report.engine_counters.unwrap()
    };
    let (edge, none) = (
        run(linegs_gpu::refine::Fit::Edge),
        run(linegs_gpu::refine::Fit::None),
    );
    // The edge fit (one batch) and its decision rule (one batch of members) run on the
    // placing engine.
    assert_eq!(edge.batches, none.batches + 2, "{edge:?} {none:?}");
    assert!(edge.queries > none.queries, "{edge:?} {none:?}");
}

#[test]
fn the_scale_cut_is_a_warning_when_the_model_has_no_scales_or_all_are_wide() {
    let (mut scene, _) = wide_band_scene();
    let asked = {
        let mut q = Params::default().with_radius(R).params().clone();
        q.fit.max_scale = Some(1.0);
        q
    };
    // every Gaussian wider than the limit: none left out, and said so
    scene.max_scale = Some(vec![1.0; scene.gaussians.len()]);
    let out = Job::new(asked.clone(), Backend::Cpu)
        .refine(&scene, |_| {})
        .unwrap();
    assert_eq!(out.report.refine.as_ref().unwrap().scale_cut, None);
    assert!(out
        .report
        .warnings
        .iter()
        .any(|w| w.contains("none was left out")));
    scene.max_scale = None;
    let out = Job::new(asked, Backend::Cpu)
        .refine(&scene, |_| {})
        .unwrap();
    assert!(out
        .report
        .warnings
        .iter()
        .any(|w| w.contains("carry no scales")));
    // not asked (the profile's default): no warning for a model without scales
    let out = Job::new(
        Params::default().with_radius(R).params().clone(),
        Backend::Cpu,
    )
    .refine(&scene, |_| {})
    .unwrap();
    assert!(!out
        .report
        .warnings
        .iter()
        .any(|w| w.contains("--max-scale")));
}

/// Gaussians along an arc in the plane z = 0 whose chord from (0, 0) to (1, 0) has
/// sagitta `sag` (bulging to +y), moved by `shift` along y, with noise.
fn arc_points(sag: f64, shift: f64, n: usize, rng: &mut TestRng) -> Vec<[f32; 3]> {
    // radius of the circle through the chord's ends and the apex
    let rad = (0.25 + sag * sag) / (2.0 * sag);
    let centre = DVec3::new(0.5, sag - rad, 0.0);
    let half = (0.5 / rad).asin();
    (0..n)
        .map(|_| {
            let a = std::f64::consts::FRAC_PI_2 + half * (2.0 * rng.f() - 1.0);
            let noise = DVec3::new(rng.f() - 0.5, rng.f() - 0.5, rng.f() - 0.5) * (0.05 * R);
            let p = centre + DVec3::new(a.cos(), a.sin(), 0.0) * rad + noise;
            [p.x as f32, (p.y + shift) as f32, p.z as f32]
        })
        .collect()
}

#[test]
fn a_segment_on_a_curve_is_measured_bent_and_dropped_and_a_straight_edge_kept() {
    let mut rng = TestRng::new(23);
    // An arc of sagitta 0.8 r and, 10 r away, a straight edge; each with its segment, the
    // arc's placed halfway between its chord and its apex (the whole arc in the cylinder).
    let sag = 0.8 * R;
    let mut pts = arc_points(sag, 0.0, 6000, &mut rng);
    let straight = seg([0.0, 0.0, 10.0 * R], [1.0, 0.0, 10.0 * R]);
    pts.extend(edge_points(&straight, 6000, 0.05 * R, &mut rng));
    let on_arc = seg([0.0, 0.5 * sag, 0.0], [1.0, 0.5 * sag, 0.0]);
    let lines = [on_arc, straight];
    let e = cpu_engine(&pts, &lines, R);
    let p = Params::default();
    let st = straightness(&e, &lines, &Attributes::default(), R, &p.fit).unwrap();
    let (a, s) = (st[0].unwrap(), st[1].unwrap());
    assert!((0.5..1.1).contains(&a), "arc: sagitta {a} r, built 0.8 r");
    assert!(s < 0.2, "straight edge: sagitta {s} r");

    // Through the steps: --max-sagitta 0.5 drops the arc's segment only; off keeps both.
    let input = LineSet::new(lines.to_vec());
    let drop = {
        let mut q = Params::default();
        q.straight.max_sagitta = 0.5;
        q.fit.fit = Some(linegs_gpu::refine::Fit::None);
        q
    }
    .with_radius(R);
    let (out, notes) = run_steps_noted(
        &e,
        (&e, &Attributes::default()),
        &input,
        &drop,
        |_, _, _| {},
    )
    .unwrap();
    assert_eq!(notes.straight.curved_dropped, Some(1));
    assert_eq!(out.len(), 1);
    assert!(
        (out.segments[0].p1.z - 10.0 * R).abs() < 0.1 * R,
        "{:?}",
        out.segments[0]
    );
    let off = {
        let mut q = Params::default();
        q.fit.fit = Some(linegs_gpu::refine::Fit::None);
        q
    }
    .with_radius(R);
    let (out, notes) =
        run_steps_noted(&e, (&e, &Attributes::default()), &input, &off, |_, _, _| {}).unwrap();
    assert_eq!(notes.straight.curved_dropped, None);
    assert_eq!(out.len(), 2);
}

#[test]
fn a_3dgs_ply_gives_each_gaussian_its_largest_scale_and_opacity() {
    let dir = std::env::temp_dir().join(format!("linegs-weights-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("g.ply");
    let centers = [[0.0f32, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
    // logits: sigmoid(0) = 0.5, sigmoid(2) = 0.88, sigmoid(-4) = 0.018
    linegs_gpu::io::write_gaussians_3dgs(&path, &centers, Some(&[0.0, 2.0, -4.0])).unwrap();
    let a = linegs_gpu::io::read_gaussian_attributes(&path, None)
        .unwrap()
        .unwrap();
    // the writer's scales are log 0.01 on every axis
    assert!(
        a.max_scale.iter().all(|&s| (s - 0.01).abs() < 1e-6),
        "{:?}",
        a.max_scale
    );
    let o = a.opacity.unwrap();
    let want = [0.5, 1.0 / (1.0 + (-2f32).exp()), 1.0 / (1.0 + 4f32.exp())];
    assert!(
        o.iter().zip(want).all(|(a, b)| (a - b).abs() < 1e-6),
        "{o:?}"
    );
    // the same opacity cut as the center reader, in the same order
    let cut = linegs_gpu::io::read_gaussian_attributes(&path, Some(0.4))
        .unwrap()
        .unwrap();
    assert_eq!(cut.opacity.unwrap().len(), 2);
    std::fs::remove_dir_all(&dir).ok();
}
