//! The `emap` protocol against numbers EMAP's own evaluation code computed on the same
//! files (tests/data/emap/README.md says how), and the ABC ground-truth reader against
//! the derived straight-line file of the same model.

use glam::DVec3;
use linegs_gpu::eval::abc::AbcGroundTruth;
use linegs_gpu::eval::gt::{emap_metrics, GtEdges, GtMetrics};
use linegs_gpu::geom::Segment;
use linegs_gpu::io;
use std::io::Read;
use std::path::{Path, PathBuf};

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(rel)
}

/// The model's ground truth: the feature file's curves and the mesh's vertices (stored
/// gzipped; unpacked into `dir`).
fn abc(dir: &Path, stats: bool) -> AbcGroundTruth {
    let mut obj = String::new();
    flate2::read::GzDecoder::new(
        std::fs::File::open(data("emap/00000006_trimesh_vertices.obj.gz")).unwrap(),
    )
    .read_to_string(&mut obj)
    .unwrap();
    let mesh = dir.join("00000006_trimesh.obj");
    std::fs::write(&mesh, obj).unwrap();
    let st = data("emap/chunk_0000_stats_00000006.json");
    AbcGroundTruth::read(
        &data("emap/00000006_features_curves.yml"),
        &mesh,
        stats.then_some(st.as_path()),
    )
    .unwrap()
}

fn lines(rel: &str) -> Vec<Segment> {
    io::read_lines(&data(rel)).unwrap().lines.segments
}

fn expected() -> serde_json::Value {
    serde_json::from_slice(&std::fs::read(data("emap/expected.json")).unwrap()).unwrap()
}

fn check(name: &str, m: &GtMetrics, want: &serde_json::Value) {
    let f = |k: &str| want[k].as_f64().unwrap();
    let ctx = format!("{name}: ours {m:?}");
    assert_eq!(m.predicted_samples as f64, f("pred_samples"), "{ctx}");
    assert_eq!(m.gt_samples as f64, f("gt_samples"), "{ctx}");
    assert!(
        (1000.0 * m.accuracy.unwrap() - f("acc_mm")).abs() < 0.01,
        "{ctx}"
    );
    assert!(
        (1000.0 * m.completeness.unwrap() - f("comp_mm")).abs() < 0.01,
        "{ctx}"
    );
    for (i, t) in ["0.005", "0.01", "0.02"].iter().enumerate() {
        let s = &m.scores[i];
        assert!(
            (s.precision - f(&format!("precision_{t}"))).abs() < 1e-4,
            "{ctx}"
        );
        assert!((s.recall - f(&format!("recall_{t}"))).abs() < 1e-4, "{ctx}");
        assert!(
            (s.f_score - f(&format!("fscore_{t}"))).abs() < 1e-4,
            "{ctx}"
        );
    }
}

#[test]
fn emap_protocol_equals_emaps_own_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let g = abc(dir.path(), true);
    let exp = expected();
    let mut seen = 0;
    let mut sums = [0.0f64; 2];
    for want in exp["pairs"].as_array().unwrap() {
        let name = want["name"].as_str().unwrap();
        let gt = want["gt"].as_str().unwrap();
        let edges = match gt {
            "all" => g.edges(false),
            "line" => g.edges(true),
            ply => {
                let c =
                    io::read_gaussians(&data(&format!("emap/{ply}")), &Default::default()).unwrap();
                GtEdges::from_points(c.centers.iter().map(|p| p.map(f64::from).into()).collect())
            }
        };
        // The perfect prediction is the GT's own pieces (EMAP's script made them the same
        // way: vertex * scale + offset, every piece of every sharp curve).
        let pred = match name {
            "perfect" => g.edges(false).segments(),
            _ => lines(&format!("emap/{}", want["lines"].as_str().unwrap())),
        };
        let m = emap_metrics(&pred, &edges);
        check(name, &m, want);
        sums[0] += m.scores[0].f_score;
        sums[1] += m.accuracy.unwrap();
        seen += 1;
    }
    assert_eq!(seen, 8);
    // The dataset mean as eval_ABC.py prints it: per object, then averaged.
    let mean = &exp["mean"];
    assert!((sums[0] / seen as f64 - mean["fscore_0.005"].as_f64().unwrap()).abs() < 1e-4);
    assert!((1000.0 * sums[1] / seen as f64 - mean["acc_mm"].as_f64().unwrap()).abs() < 0.01);
}

#[test]
fn abc_lines_equal_the_derived_line_file_and_curves_are_all_there() {
    let dir = tempfile::tempdir().unwrap();
    let g = abc(dir.path(), true);
    let (kinds, not_sharp) = g.counts();
    // 12 lines, 8 circles, no ellipse, 12 sharp B-splines; the 13th B-spline is not sharp.
    assert_eq!(kinds, [12, 8, 0, 12]);
    assert_eq!(not_sharp, 1);
    assert!(g.warnings.is_empty());
    let want = lines("abc_00000006/gt_sharp_lines.txt");
    let got = g.line_segments();
    assert_eq!(got.len(), want.len());
    for (a, b) in got.iter().zip(&want) {
        for (p, q) in [(a.p1, b.p1), (a.p2, b.p2)] {
            assert!((p - q).abs().max_element() < 1e-6, "{a:?} vs {b:?}");
        }
    }
    // The polylines of every sharp curve, in the unit cube.
    let all = g.edges(false);
    assert_eq!(all.polylines.len(), 32);
    let segs = all.segments();
    let (lo, hi) = segs.iter().fold(
        (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY)),
        |(lo, hi), s| (lo.min(s.p1).min(s.p2), hi.max(s.p1).max(s.p2)),
    );
    assert!(
        lo.min_element() > -1e-9 && hi.max_element() < 1.0 + 1e-9,
        "{lo} {hi}"
    );
    // Without the stats file: the mesh's box, a warning, and a frame off by < 2e-4.
    let m = abc(dir.path(), false);
    assert_eq!(m.warnings.len(), 1);
    assert!(m.warnings[0].contains("--abc-stats"));
    for (a, b) in m.line_segments().iter().zip(&got) {
        let d = (a.p1 - b.p1).abs().max_element();
        assert!(d < 2e-4 && d > 0.0, "{d}");
    }
}
