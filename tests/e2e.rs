//! End to end on the paper's toy scene and on real line files.

mod common;

use common::data;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::eval::gt;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::io;
use linegs_gpu::pipeline::{Refined, Refiner};
use linegs_gpu::refine::Params;
use linegs_gpu::synth;

fn refine_cpu(points: &[[f32; 3]], lines: &LineSet, params: &Params) -> Refined {
    let r = Refiner::new(points, &lines.segments, params, Backend::Cpu).unwrap();
    let out = r.refine(lines, |_| {}).unwrap();
    assert_eq!(r.engine().counters().uploads, 0);
    out
}

fn assert_sane(out: &Refined, input: usize) {
    // The steps up to crop never add segments; `--split-gaps` may split one into pieces.
    let crop = out.stages.iter().find(|s| s.name == "crop").unwrap();
    assert!(!out.lines.is_empty() && crop.segments <= input);
    let split = out.steps.gaps.gaps_split.unwrap_or(0);
    assert!(split > 0 || out.lines.len() <= crop.segments);
    for s in &out.lines.segments {
        assert!(
            s.p1.is_finite() && s.p2.is_finite() && s.length() > 0.0,
            "{s:?}"
        );
    }
    for m in [&out.before, &out.after] {
        for v in [m.e_rms_cm, m.coverage_pct, m.r_l, m.score] {
            let v = v.expect("metric defined");
            assert!(v.is_finite() && v >= 0.0);
        }
        assert!(m.coverage_pct.unwrap() <= 100.0);
    }
}

fn accuracy(segs: &[Segment], gt_edges: &[Segment]) -> f64 {
    // mean distance of the segment's samples to the GT edges
    gt::gt_metrics(segs, gt_edges, gt::STEP, &gt::THRESHOLDS)
        .accuracy
        .unwrap()
}

#[test]
fn the_toy_scene_is_cleaned_and_default_beats_reference() {
    let scene = synth::toy_scene(&synth::ToyParams::default());
    let n_in = scene.lines.len();
    let d = refine_cpu(&scene.gaussians, &scene.lines, &Params::default());
    let r = refine_cpu(&scene.gaussians, &scene.lines, &Params::reference());
    assert_sane(&d, n_in);
    assert_sane(&r, n_in);
    // compact: far fewer segments than the noisy input
    assert!(d.lines.len() * 2 < n_in, "{} of {n_in}", d.lines.len());
    // the paper score improves
    assert!(d.after.score.unwrap() > d.before.score.unwrap());
    // closer to the ground-truth edges than the input and than the reference profile,
    // with less total length (reference keeps more duplicates)
    let m_in = gt::gt_metrics(&scene.lines.segments, &scene.gt, gt::STEP, &gt::THRESHOLDS);
    let m_d = gt::gt_metrics(&d.lines.segments, &scene.gt, gt::STEP, &gt::THRESHOLDS);
    let m_r = gt::gt_metrics(&r.lines.segments, &scene.gt, gt::STEP, &gt::THRESHOLDS);
    assert!(
        m_d.accuracy.unwrap() < 0.2 * m_in.accuracy.unwrap(),
        "{m_d:?}"
    );
    assert!(m_d.completeness.unwrap() < m_in.completeness.unwrap());
    assert!(
        m_d.scores[1].recall > m_r.scores[1].recall,
        "{m_d:?} {m_r:?}"
    );
    // Since reference runs every cluster's merge/join to its end (issue 9), its accuracy
    // on this scene is as good as default's (its crop stops inside the dense ends, which
    // costs recall, not accuracy).
    assert!(
        m_d.accuracy.unwrap() < 1.1 * m_r.accuracy.unwrap(),
        "{m_d:?} {m_r:?}"
    );
    // Default keeps the true extent that reference's crop cuts, and places it better.
    assert!(
        m_d.scores[0].f_score > m_r.scores[0].f_score + 0.05,
        "{m_d:?} {m_r:?}"
    );
    assert!(
        m_d.scores[2].f_score > 0.99 && m_d.scores[1].f_score > 0.97,
        "{m_d:?}"
    );
    assert!(d.lines.len() <= r.lines.len());
    assert!(d.after.score.unwrap() > r.after.score.unwrap());
    // the planted outliers are gone
    let far = d
        .lines
        .segments
        .iter()
        .filter(|s| accuracy(&[**s], &scene.gt) > 0.1)
        .count();
    assert_eq!(far, 0);
}

#[test]
fn output_is_identical_across_runs_and_thread_counts() {
    let scene = synth::toy_scene(&synth::ToyParams {
        seed: 3,
        ..Default::default()
    });
    let dir = tempfile::tempdir().unwrap();
    let mut bytes = Vec::new();
    for threads in [1, 2, 2] {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        for params in [Params::default(), Params::reference()] {
            let out = pool.install(|| refine_cpu(&scene.gaussians, &scene.lines, &params));
            let p = dir.path().join("out.obj");
            io::write_lines(&p, &out.lines.segments).unwrap();
            bytes.push(std::fs::read(&p).unwrap());
        }
    }
    assert_eq!(bytes[0], bytes[2]);
    assert_eq!(bytes[0], bytes[4]);
    assert_eq!(bytes[1], bytes[3]);
    assert_eq!(bytes[1], bytes[5]);
}

#[test]
fn real_line3dpp_output_refines_with_its_line_groups() {
    // No 3DGS model exists for this scene: the Gaussians are sampled around the segments
    // (synthetic), which is what a trained model concentrates at image edges.
    let txt = io::read_lines(&data("line3dpp/line3dpp_optimized.txt")).unwrap();
    let obj = io::read_lines(&data("line3dpp/line3dpp_optimized.obj")).unwrap();
    assert!(txt.lines.groups.is_some());
    let pts = synth::gaussians_around_segments(&txt.lines.segments, 150_000, 0.004, 0.1, 5);
    // (The reference profile is left out here: with the lateral offset ignored its
    // clusters on this real scene hold hundreds of segments and take a minute; the toy
    // scene covers it.)
    for (lines, profile) in [
        (&txt.lines, Params::default()),
        (&obj.lines, Params::default()),
    ] {
        let out = refine_cpu(&pts, lines, &profile);
        assert_sane(&out, lines.len());
        // a real reconstruction keeps most of its structure
        assert!(out.lines.len() > lines.len() / 10, "{}", out.lines.len());
        assert!(out.after.coverage_pct.unwrap() > 20.0);
    }
}

#[test]
fn nef_lines_refine_against_gaussians_sampled_from_the_abc_mesh() {
    let mesh = synth::mesh::read_obj_mesh(data("abc_00000006/mesh.obj")).unwrap();
    let pts = synth::mesh::gaussians_from_mesh(
        &mesh,
        60_000,
        2,
        &synth::mesh::MeshGaussianOptions::default(),
    );
    let nef = io::read_lines(&data("abc_00000006/nef_pred_lines.txt")).unwrap();
    let gt_edges = io::read_lines(&data("abc_00000006/gt_sharp_lines.txt")).unwrap();
    let params = Params {
        radius: linegs_gpu::refine::RadiusArg::Fixed(0.01),
        eval: linegs_gpu::refine::EvalParams {
            eval_radius: 0.02,
            ..Default::default()
        },
        ..Default::default()
    };
    let out = refine_cpu(&pts, &nef.lines, &params);
    assert_sane(&out, nef.lines.len());
    // GT holds only the 12 straight sharp edges (NEF also fits lines to curves), so
    // completeness (GT -> predicted) is the measure here.
    let g = &gt_edges.lines.segments;
    let m_in = gt::gt_metrics(&nef.lines.segments, g, gt::STEP, &gt::THRESHOLDS);
    let m = gt::gt_metrics(&out.lines.segments, g, gt::STEP, &gt::THRESHOLDS);
    assert!(m.completeness.unwrap() < 0.03, "{m:?}");
    assert!(
        m.completeness.unwrap() < 1.5 * m_in.completeness.unwrap(),
        "{m:?} {m_in:?}"
    );
    assert!(
        m.accuracy.unwrap() < 1.2 * m_in.accuracy.unwrap(),
        "{m:?} {m_in:?}"
    );
}
