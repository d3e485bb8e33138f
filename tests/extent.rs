//! Keeping the full extent and every true edge: a short segment on a long dense edge is
//! extended to the edge's end (and not past the corner there), and a turned segment on a
//! true edge survives the pipeline whole.

mod common;

use common::*;
use linegs_gpu::geom::{LineSet, Segment};
use linegs_gpu::refine::{self, crop, Fit, Params};

const R: f64 = 0.03;

/// Three edges of a square: (0,0,0)-(1,0,0) and the two sides meeting it at its corners.
fn u_shape(rng: &mut TestRng) -> Vec<[f32; 3]> {
    let mut pts = Vec::new();
    for e in [
        seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
        seg([0.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
        seg([1.0, 0.0, 0.0], [1.0, 1.0, 0.0]),
    ] {
        pts.extend(edge_points(&e, 6000, 0.003, rng));
    }
    pts
}

#[test]
fn a_short_segment_on_a_long_edge_is_extended_to_its_corners_and_not_past() {
    let mut rng = TestRng::new(21);
    let pts = u_shape(&mut rng);
    let short = seg([0.4, 0.0, 0.0], [0.6, 0.0, 0.0]);
    let e = cpu_engine(&pts, &[short, seg([0.0, 1.0, 0.0], [1.0, 1.0, 0.0])], R);
    let p = {
        let mut q = Params::default();
        q.crop.crop_extend = 4.0;
        q
    };
    let out = crop::crop(&e, &[short], &p.with_radius(R)).unwrap()[0];
    let (a, b) = (out.p1.x.min(out.p2.x), out.p1.x.max(out.p2.x));
    assert!(a.abs() < R && (b - 1.0).abs() < R, "{out:?}");
    // on the line, not bent towards the other edges
    assert!(out.p1.y.abs() < 1e-9 && out.p2.y.abs() < 1e-9);
    // the paper's crop never extends
    let p0 = Params::default();
    assert_eq!(
        crop::crop(&e, &[short], &p0.with_radius(R)).unwrap()[0],
        short
    );
}

#[test]
fn an_extension_is_bounded_by_its_limit() {
    let mut rng = TestRng::new(22);
    let pts = u_shape(&mut rng);
    let short = seg([0.4, 0.0, 0.0], [0.6, 0.0, 0.0]);
    let e = cpu_engine(&pts, &[short, seg([0.0, 1.0, 0.0], [1.0, 1.0, 0.0])], R);
    let p = {
        let mut q = Params::default();
        q.crop.crop_extend = 0.5;
        q
    };
    let out = crop::crop(&e, &[short], &p.with_radius(R)).unwrap()[0];
    assert!((out.length() - 0.4).abs() < 1e-9, "{out:?}");
}

/// Total length of `out` within `tol` of `edge`, sampled every 0.005 along the edge.
fn covered(edge: &Segment, out: &[Segment], tol: f64) -> f64 {
    let n = (edge.length() / 0.005) as usize;
    let hit = (0..=n)
        .filter(|&i| {
            let q = edge.point_at(edge.length() * i as f64 / n as f64);
            out.iter()
                .any(|s| s.distance_to(&Segment::new(q, q + glam::DVec3::splat(1e-12))) < tol)
        })
        .count();
    hit as f64 / (n + 1) as f64
}

#[test]
fn a_turned_segment_on_a_true_edge_is_kept_whole() {
    let mut rng = TestRng::new(23);
    let pts = u_shape(&mut rng);
    let edge = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
    // One end on the edge, the other 0.9 r off it: the published step moves it by the
    // mean offset, which leaves its far end off the ridge for the crop to cut.
    let turned = seg([0.05, 0.0, 0.0], [0.95, 0.9 * R, 0.0]);
    let lines = LineSet::new(vec![
        turned,
        seg([0.0, 0.05, 0.0], [0.0, 0.95, 0.0]),
        seg([1.0, 0.05, 0.0], [1.0, 0.95, 0.0]),
    ]);
    let e = cpu_engine(&pts, &lines.segments, R);
    let p = Params::default();
    assert_eq!(p.fixes().fit, Fit::Edge);
    let out = refine::run_steps(&e, &lines, &p.with_radius(R), |_, _, _| {}).unwrap();
    let c = covered(&edge, &out.segments, 0.2 * R);
    assert!(c > 0.85, "edge fit keeps {c:.3} of the edge");
    let paper = {
        let mut q = Params::default();
        q.fit.fit = Some(Fit::Paper);
        q
    };
    let out = refine::run_steps(&e, &lines, &paper.with_radius(R), |_, _, _| {}).unwrap();
    let c_paper = covered(&edge, &out.segments, 0.2 * R);
    assert!(c_paper < c, "paper {c_paper:.3} vs edge {c:.3}");
}
