//! The edge fit two ways, bit for bit: the CPU engine's `fit_edges` (each segment's
//! neighbourhood gathered once, every step on it in cache) against one engine batch of
//! member lists per iteration (`engine::fit::by_batches`, the fit as it ran before the
//! gathering), and one batch per iteration until a few segments are left that then go
//! on as the gathered fit takes them (`engine::fit::Tail`, the GPU engine's last
//! iterations on the host), on the toy scene, NEF lines on the ABC mesh, the real Line3D++ output and
//! the real trained pairs (normals: the two-face fit; opacities: the weighted fit).

mod common;

use common::*;
use linegs_gpu::engine::fit::{by_batches, by_batches_in, finish_gathered, Tail, GATHER_MARGIN};
use linegs_gpu::engine::{Engine, FitJob};
use linegs_gpu::geom::Segment;
use linegs_gpu::io;
use linegs_gpu::refine::fit::{cut_to_working_set, Attributes, FitResult, FitSpec, How};
use linegs_gpu::refine::Params;
use linegs_gpu::synth;

fn bits(s: &[Segment]) -> Vec<[u64; 6]> {
    s.iter()
        .map(|s| {
            let (a, b) = (s.p1, s.p2);
            [a.x, a.y, a.z, b.x, b.y, b.z].map(f64::to_bits)
        })
        .collect()
}

/// Both fits of `segments` over `points` (with `attrs` of the working set) for `spec`;
/// asserts they agree bit for bit and returns the result.
fn both(
    points: &[[f32; 3]],
    segments: &[Segment],
    attrs: &Attributes,
    r: f64,
    spec: &FitSpec,
) -> FitResult {
    both_with_tails(points, segments, attrs, r, spec).0
}

/// [`both`], and how many segments each of its tails took: of at most 1, a twentieth of
/// the segments, and all of them.
fn both_with_tails(
    points: &[[f32; 3]],
    segments: &[Segment],
    attrs: &Attributes,
    r: f64,
    spec: &FitSpec,
) -> (FitResult, Vec<usize>) {
    let e = cpu_engine(points, segments, r);
    let job = FitJob {
        segments,
        r,
        spec,
        points: attrs.fit_points(),
    };
    let once = e.fit_edges(&job).unwrap();
    same_fit(&once, &by_batches(&e, &job).unwrap(), "per iteration");
    // Batches until at most `at_most` segments are still moving, then the rest of each
    // one's steps gathered: the same bits wherever the batches stop (all of them from the
    // start where `at_most` covers every segment).
    let mut handed = Vec::new();
    for at_most in [1, segments.len() / 20, usize::MAX] {
        let taken = std::sync::Mutex::new(0);
        let finish = |j: &FitJob<'_>, rest: &mut [linegs_gpu::geom::fit::Track]| {
            *taken.lock().unwrap() += rest.len();
            finish_gathered(e.grid(), j, rest);
            Ok(())
        };
        let tail = Tail {
            at_most,
            finish: &finish,
        };
        let with_tail = by_batches_in(&e, &job, None, Some(&tail)).unwrap();
        same_fit(
            &once,
            &with_tail,
            &format!("with a tail of at most {at_most}"),
        );
        handed.push(taken.into_inner().unwrap());
    }
    // Every segment that steps at all went to the tail of any size (exact copies once).
    let input = bits(segments);
    let stepping = (0..segments.len())
        .filter(|&i| once.steps[i] > 0)
        .map(|i| input[i])
        .collect::<std::collections::HashSet<_>>()
        .len();
    assert_eq!(handed[2], stepping, "{handed:?}");
    (once, handed)
}

/// Asserts that `other` (fitted `how`) is the gathered fit `once` bit for bit: its
/// segments, how each moved, its iterations and steps.
fn same_fit(once: &FitResult, other: &FitResult, how: &str) {
    let (a, b) = (bits(&once.segments), bits(&other.segments));
    if let Some(i) = (0..a.len()).find(|&i| a[i] != b[i]) {
        panic!(
            "segment {i} of {}: {:?} gathered once, {:?} {how}",
            a.len(),
            once.segments[i],
            other.segments[i]
        );
    }
    assert_eq!(once.how, other.how, "{how}");
    assert_eq!(once.iterations, other.iterations, "{how}");
    assert_eq!(once.steps, other.steps, "{how}");
}

/// How many segments moved, and by more than `GATHER_MARGIN` r from their start (their
/// neighbourhood then was gathered more than once).
fn moved(input: &[Segment], f: &FitResult, r: f64) -> (usize, usize) {
    let d = |a: &Segment, b: &Segment| (a.p1 - b.p1).length().max((a.p2 - b.p2).length());
    let m: Vec<f64> = input
        .iter()
        .zip(&f.segments)
        .map(|(a, b)| d(a, b))
        .collect();
    (
        m.iter().filter(|&&x| x > 0.0).count(),
        m.iter().filter(|&&x| x > GATHER_MARGIN * r).count(),
    )
}

fn spec() -> FitSpec {
    FitSpec::from(&Params::default().fit)
}

#[test]
fn the_toy_scene_fits_alike_both_ways() {
    let scene = synth::toy_scene(&synth::ToyParams::default());
    let segs = &scene.lines.segments;
    let r = 0.03;
    let (f, handed) = both_with_tails(&scene.gaussians, segs, &Attributes::default(), r, &spec());
    let (any, far) = moved(segs, &f, r);
    assert!(any > segs.len() / 2, "{any} of {} moved", segs.len());
    assert!(far > 10, "{far} moved beyond the gathering margin");
    assert!(f.iterations > 2, "{}", f.iterations);
    // The tail of a twentieth took over after some batches, with some segments still
    // moving.
    let stepping = f.steps.iter().filter(|&&s| s > 0).count();
    assert!(
        handed[1] > 0 && handed[1] < stepping,
        "{handed:?} of {stepping}"
    );
    // A wider allowed move and more, shorter-kernel steps: lines travel further.
    let wide = FitSpec {
        max_move: 4.0,
        iterations: 20,
        bandwidth: 0.15,
        ..spec()
    };
    both(&scene.gaussians, segs, &Attributes::default(), r, &wide);
}

#[test]
fn nef_lines_on_the_abc_mesh_fit_alike_both_ways() {
    let mesh = synth::mesh::read_obj_mesh(data("abc_00000006/mesh.obj")).unwrap();
    let pts = synth::mesh::gaussians_from_mesh(
        &mesh,
        60_000,
        2,
        &synth::mesh::MeshGaussianOptions::default(),
    );
    let nef = io::read_lines(&data("abc_00000006/nef_pred_lines.txt")).unwrap();
    let segs = &nef.lines.segments;
    let f = both(&pts, segs, &Attributes::default(), 0.01, &spec());
    assert!(moved(segs, &f, 0.01).0 > segs.len() / 2);
}

#[test]
fn real_line3dpp_lines_fit_alike_both_ways() {
    let txt = io::read_lines(&data("line3dpp/line3dpp_optimized.txt")).unwrap();
    let segs = &txt.lines.segments;
    let pts = synth::gaussians_around_segments(segs, 150_000, 0.004, 0.1, 5);
    let f = both(&pts, segs, &Attributes::default(), 0.03, &spec());
    assert!(moved(segs, &f, 0.03).0 > segs.len() / 2);
    // Exact copies of every segment: each answered like its original.
    let twice: Vec<Segment> = segs.iter().chain(segs).copied().collect();
    let g = both(&pts, &twice, &Attributes::default(), 0.03, &spec());
    assert_eq!(bits(&g.segments[..segs.len()]), bits(&f.segments));
    assert_eq!(bits(&g.segments[segs.len()..]), bits(&f.segments));
    // ... and asked once: per iteration the engine gets the distinct segments alone.
    let asked = |s: &[Segment]| {
        let e = cpu_engine(&pts, s, 0.03);
        let (spec, attrs) = (spec(), Attributes::default());
        let job = FitJob {
            segments: s,
            r: 0.03,
            spec: &spec,
            points: attrs.fit_points(),
        };
        by_batches(&e, &job).unwrap();
        e.counters().queries
    };
    assert_eq!(asked(&twice), asked(segs));
}

#[test]
fn the_trained_pairs_fit_alike_both_ways_with_normals_and_opacities() {
    for pair in ["proc", "abc00000006"] {
        let scene = pair_scene(pair);
        let segs = &scene.lines.segments;
        let c = &scene.gaussians;
        let cut = |v: &Option<Vec<f32>>| cut_to_working_set(c, v.as_ref().unwrap(), segs);
        let attrs = Attributes {
            normals: cut_to_working_set(c, scene.normals.as_ref().unwrap(), segs),
            opacity: cut(&scene.opacity),
            extent: None,
            colour: None,
        };
        let r = 0.03;
        let f = both(c, segs, &attrs, r, &spec());
        let corners = f.how.iter().filter(|&&h| h == How::Corner).count();
        let ridges = f.how.iter().filter(|&&h| h == How::Ridge).count();
        assert!(
            corners > 0 && ridges > 0,
            "{pair}: {corners} corners, {ridges} ridges"
        );
        assert!(moved(segs, &f, r).0 > segs.len() / 2, "{pair}");
        let weighted = FitSpec {
            opacity_weight: true,
            ..spec()
        };
        both(c, segs, &attrs, r, &weighted);
    }
}
