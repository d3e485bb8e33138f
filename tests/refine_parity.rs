//! `refine` and `eval` give the same segments and metrics on the GPU engine (lavapipe in
//! CI) and on the CPU engine: membership is exact on both, so every decision of every step
//! is the same and only float rounding of the sums separates them (issue 13's targets: the
//! same segment count, >= 99.5 % of endpoints within 1e-5 r, metrics within 1e-6
//! relative). Each backend alone repeats itself exactly; the Gaussians are uploaded once
//! per run.

mod common;

use linegs_gpu::engine::select::Backend;
use linegs_gpu::engine::{Engine, EngineError};
use linegs_gpu::eval::Metrics;
use linegs_gpu::geom::LineSet;
use linegs_gpu::io;
use linegs_gpu::pipeline::{Refined, Refiner};
use linegs_gpu::refine::Params;
use linegs_gpu::synth;
use std::path::Path;

fn run(r: &Refiner, lines: &LineSet) -> Refined {
    r.refine(lines, |_| {}).unwrap()
}

/// The same segment count; >= 99.5 % of one backend's segments match the other's segment
/// of the same index within 1e-5 r at both ends; metrics within `metric_tol` relative.
fn assert_close(a: &Refined, b: &Refined, r: f64, metric_tol: f64) {
    assert_eq!(a.lines.len(), b.lines.len(), "segment counts");
    let tol = 1e-5 * r;
    let hit = a
        .lines
        .segments
        .iter()
        .zip(&b.lines.segments)
        .filter(|(x, y)| (x.p1 - y.p1).length() <= tol && (x.p2 - y.p2).length() <= tol)
        .count();
    assert!(
        hit as f64 >= 0.995 * a.lines.len() as f64,
        "{hit} of {} match",
        a.lines.len()
    );
    for (what, ma, mb) in [
        ("before", &a.before, &b.before),
        ("after", &a.after, &b.after),
    ] {
        assert_metrics_close(what, ma, mb, metric_tol);
    }
}

fn assert_metrics_close(what: &str, a: &Metrics, b: &Metrics, tol: f64) {
    assert_eq!((a.segments, a.skipped), (b.segments, b.skipped));
    for (x, y) in [
        (a.e_rms_cm, b.e_rms_cm),
        (a.coverage_pct, b.coverage_pct),
        (a.r_l, b.r_l),
        (a.score, b.score),
    ] {
        let (x, y) = (x.unwrap(), y.unwrap());
        assert!(
            (x - y).abs() <= tol * x.abs().max(y.abs()),
            "{what}: {x} vs {y}\n{a:?}\n{b:?}"
        );
    }
}

fn check_scene(points: &[[f32; 3]], lines: &LineSet, profiles: &[Params], metric_tol: f64) {
    for p in profiles {
        // Both engines over the grid the library builds for these parameters.
        let gpu =
            Refiner::with_engine(points, &lines.segments, p, |grid| match common::gpu_engine(
                grid,
                Default::default(),
            ) {
                Some(e) => Ok((Box::new(e) as Box<dyn Engine>, Vec::new())),
                None => Err(EngineError::NoAdapter("skipped".into())),
            });
        let Ok(g) = gpu else {
            return;
        };
        let c = Refiner::new(points, &lines.segments, p, Backend::Cpu).unwrap();
        assert_eq!(g.settings(), c.settings());
        let out_g = run(&g, lines);
        let out_c = run(&c, lines);
        assert_close(&out_g, &out_c, g.settings().radius(), metric_tol);
        // the grid went to the device once for every step and both evaluations
        assert_eq!(g.engine().counters().uploads, 1);
        // and `--fit edge` fitted its ridges there (f64 kernel; lavapipe has f64)
        if g.settings().fixes().fit == linegs_gpu::refine::Fit::Edge {
            assert!(g.engine().counters().device_fits > 0);
        }
        // each backend alone repeats itself to the bit
        let again = run(&g, lines);
        assert_eq!(again.lines, out_g.lines);
        assert_eq!(again.after, out_g.after);
        assert_eq!(g.engine().counters().uploads, 1);
    }
}

#[test]
fn toy_scene_refines_alike_on_gpu_and_cpu_for_both_profiles() {
    let scene = synth::toy_scene(&synth::ToyParams::default());
    check_scene(
        &scene.gaussians,
        &scene.lines,
        &[Params::default(), Params::reference()],
        1e-6,
    );
}

#[test]
fn real_line3dpp_lines_refine_alike_on_gpu_and_cpu() {
    let p =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/line3dpp/line3dpp_optimized.txt");
    let lines = io::read_lines(&p).unwrap().lines;
    let pts = synth::gaussians_around_segments(&lines.segments, 100_000, 0.004, 0.1, 5);
    // Measured: 6e-9 relative after refinement (the evaluations' f32 sums), with the edge
    // fit on the device (in f64: its lines within 1e-9 r of the host's). With that fit in
    // f32 (1e-7 r) crop's probes decided 8 of 936 segments' ends differently and the
    // metrics differed by 1e-5.
    check_scene(&pts, &lines, &[Params::default()], 1e-6);
}

#[test]
fn nef_lines_refine_alike_on_gpu_and_cpu() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/abc_00000006");
    let mesh = synth::mesh::read_obj_mesh(dir.join("mesh.obj")).unwrap();
    let pts = synth::mesh::gaussians_from_mesh(&mesh, 40_000, 2, &Default::default());
    let lines = io::read_lines(&dir.join("nef_pred_lines.txt"))
        .unwrap()
        .lines;
    let p = Params {
        radius: linegs_gpu::refine::RadiusArg::Fixed(0.01),
        eval: linegs_gpu::refine::EvalParams {
            eval_radius: 0.02,
            ..Default::default()
        },
        ..Default::default()
    };
    let r = Params {
        profile: linegs_gpu::refine::Profile::Reference,
        ..p.clone()
    };
    // The device's f64 ridge puts a line within 1e-9 r of the host's; on this scene one
    // Gaussian lies that close to the boundary of a final segment's cylinder (the default
    // profile's crop leaves that end where the fit put it), so one point of 19,792 in the
    // after-evaluation differs: up to 5e-5 relative (the coverage).
    check_scene(&pts, &lines, &[p, r], 1e-4);
}

#[test]
fn no_stage_walks_member_lists_on_the_host_in_the_hardware_configuration() {
    // The configuration a hardware adapter gets (member lists and the fit on the device,
    // `LINEGS_GPU_MEMBERS=device LINEGS_GPU_FIT=device`), every batch on the device
    // (`small_batch` 0): no stage walks a member on the host (`host_lists`), and every
    // stage that asks the engine anything evaluates its points there. The edge fit's
    // steps are the device's, but for those it sends back to the host by design (a
    // decision within rounding of its threshold: `device_fits_refitted`, each one host
    // walk); its gate's member lists are the device's, measured on the host.
    let scene = synth::toy_scene(&synth::ToyParams::default());
    let p = Params::default();
    let gpu = Refiner::with_engine(&scene.gaussians, &scene.lines.segments, &p, |grid| {
        match common::gpu_engine(grid, Default::default()) {
            Some(e) => Ok((Box::new(e) as Box<dyn Engine>, Vec::new())),
            None => Err(EngineError::NoAdapter("skipped".into())),
        }
    });
    let Ok(g) = gpu else {
        return;
    };
    assert!(p.gaps.split_gaps_for(p.profile) > 0.0 && !p.gaps.split_interior && p.fit.fit_gate);
    let out = run(&g, &scene.lines);
    let c = g.counters();
    assert!(c.device_fits > 0, "{c:?}");
    // Every stage the run reports, so that a new stage is covered too; the stages before
    // the first batch (index, engine) and the clustering ask the engine nothing.
    let quiet = ["index", "engine", "cluster"];
    let mut checked = Vec::new();
    for s in &out.stages {
        let walked = s
            .host_lists
            .unwrap_or_else(|| panic!("{}: no counters", s.name));
        let allowed = if s.name == "translate" {
            c.device_fits_refitted
        } else {
            0
        };
        assert_eq!(walked, allowed, "{}: host walks {s:?} {c:?}", s.name);
        if quiet.contains(&s.name.as_str()) {
            continue;
        }
        let items = s.device_items.unwrap();
        assert!(items > 0, "{}: {s:?}", s.name);
        assert!(s.point_bytes.unwrap() >= 16 * items, "{}: {s:?}", s.name);
        checked.push(s.name.as_str());
    }
    for name in [
        "evaluate_before",
        "translate",
        "outliers",
        "merge_join",
        "crop",
        "split_gaps",
        "evaluate_after",
    ] {
        assert!(checked.contains(&name), "{name} not in {checked:?}");
    }
    // and the refinement is the CPU engine's
    let c = Refiner::new(&scene.gaussians, &scene.lines.segments, &p, Backend::Cpu).unwrap();
    assert_close(&out, &run(&c, &scene.lines), g.settings().radius(), 1e-6);
}
