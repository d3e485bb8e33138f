//! `eval --gt ... --protocol`, `--gt-abc`, sampled GT points and the ground truth's
//! input errors, through the binary as a user runs it.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn data(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(rel)
}

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_linegs-gpu"))
        .args(args)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

/// Gaussians sampled on the ABC mesh (unit-cube frame) and the model's raw files: the
/// feature file, the mesh in ABC units (unpacked) and the stats entry.
struct Scene {
    dir: tempfile::TempDir,
    gaussians: PathBuf,
    mesh: PathBuf,
}

fn scene() -> Scene {
    let dir = tempfile::tempdir().unwrap();
    let gaussians = dir.path().join("g.ply");
    let o = run(&[
        "synth",
        "mesh",
        "--mesh",
        s(&data("abc_00000006/mesh.obj")),
        "-o",
        s(&gaussians),
        "-n",
        "4000",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut obj = String::new();
    flate2::read::GzDecoder::new(
        std::fs::File::open(data("emap/00000006_trimesh_vertices.obj.gz")).unwrap(),
    )
    .read_to_string(&mut obj)
    .unwrap();
    let mesh = dir.path().join("00000006_trimesh.obj");
    std::fs::write(&mesh, obj).unwrap();
    Scene {
        dir,
        gaussians,
        mesh,
    }
}

fn eval_json(sc: &Scene, lines: &Path, gt: &[&str]) -> serde_json::Value {
    let mut args = vec![
        "eval",
        "--backend",
        "cpu",
        "--gaussians",
        s(&sc.gaussians),
        "--lines",
        s(lines),
        "--json",
    ];
    args.extend_from_slice(gt);
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    serde_json::from_slice(&o.stdout).unwrap()
}

fn expected(name: &str) -> serde_json::Value {
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(data("emap/expected.json")).unwrap()).unwrap();
    v["pairs"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == name)
        .unwrap()
        .clone()
}

#[test]
fn gt_abc_with_the_emap_protocol_prints_emaps_numbers() {
    let sc = scene();
    let feat = data("emap/00000006_features_curves.yml");
    let stats = data("emap/chunk_0000_stats_00000006.json");
    let lines = data("emap/l3d_default.txt");
    let abc = [
        "--gt-abc",
        s(&feat),
        "--gt-mesh",
        s(&sc.mesh),
        "--abc-stats",
        s(&stats),
    ];
    let mut args = abc.to_vec();
    args.extend(["--protocol", "emap"]);
    let v = eval_json(&sc, &lines, &args);
    let g = &v["ground_truth"]["before"];
    let want = expected("l3d_default");
    assert_eq!(g["protocol"], "emap");
    let acc = 1000.0 * g["accuracy"].as_f64().unwrap();
    assert!(
        (acc - want["acc_mm"].as_f64().unwrap()).abs() < 0.01,
        "{acc}"
    );
    let f5 = g["scores"][0]["f_score"].as_f64().unwrap();
    assert!((f5 - want["fscore_0.005"].as_f64().unwrap()).abs() < 1e-4);
    // The default protocol is `exact` and says so; its numbers differ.
    let x = eval_json(&sc, &lines, &abc);
    assert_eq!(x["ground_truth"]["before"]["protocol"], "exact");
    assert_ne!(x["ground_truth"]["before"]["accuracy"], g["accuracy"]);
    // The table prints mm and percent, and names the protocol.
    let mut t = vec![
        "eval",
        "--backend",
        "cpu",
        "--gaussians",
        s(&sc.gaussians),
        "--lines",
        s(&lines),
        "--protocol",
        "emap",
    ];
    t.extend_from_slice(&abc);
    let o = run(&t);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("(emap protocol)") && out.contains(" mm"),
        "{out}"
    );
}

#[test]
fn sampled_gt_points_score_with_strict_thresholds() {
    let sc = scene();
    let v = eval_json(
        &sc,
        &data("emap/threshold_line.txt"),
        &[
            "--gt",
            s(&data("emap/threshold_gt_0.005.ply")),
            "--protocol",
            "emap",
        ],
    );
    let g = &v["ground_truth"]["before"];
    assert_eq!(g["gt_samples"], 65);
    assert_eq!(g["scores"][1]["f_score"], 0.0);
    assert_eq!(g["scores"][2]["f_score"], 1.0);
}

fn assert_input_error(o: &Output, needles: &[&str]) {
    assert_eq!(o.status.code(), Some(2), "stderr: {}", stderr(o));
    let e = stderr(o);
    for n in needles {
        assert!(e.contains(n), "`{n}` not in: {e}");
    }
    assert!(!e.contains("panicked"), "{e}");
}

#[test]
fn bad_ground_truth_exits_2_naming_the_file_and_place() {
    let sc = scene();
    let d = sc.dir.path();
    let lines = data("emap/l3d_input.txt");
    let base = [
        "eval",
        "--backend",
        "cpu",
        "--gaussians",
        s(&sc.gaussians),
        "--lines",
        s(&lines),
    ];
    let small_mesh = d.join("m.obj");
    std::fs::write(&small_mesh, "v 0 0 0\nv 1 0 0\nv 0 1 0\n").unwrap();
    // A vertex index beyond the mesh.
    let feat = d.join("00000001_features.yml");
    std::fs::write(
        &feat,
        "curves:\n- sharp: true\n  type: Line\n  vert_indices: [0, 1]\n- sharp: true\n  type: Line\n  vert_indices: [1, 3]\n",
    )
    .unwrap();
    let mut a = base.to_vec();
    a.extend(["--gt-abc", s(&feat), "--gt-mesh", s(&small_mesh)]);
    assert_input_error(
        &run(&a),
        &["00000001_features.yml: line 5", "vertex index 3", "m.obj"],
    );
    // An unknown curve type.
    std::fs::write(
        &feat,
        "curves:\n- sharp: true\n  type: Line\n  vert_indices: [0, 1]\n- sharp: true\n  type: Spiral\n  vert_indices: [1, 2]\n",
    )
    .unwrap();
    assert_input_error(&run(&a), &["00000001_features.yml: line 6", "`Spiral`"]);
    // GT in ABC units against lines in the unit cube: no stats, no mesh box either (a
    // plain line file in the model's own units).
    let raw = d.join("raw_units.txt");
    std::fs::write(
        &raw,
        "-2.38 1.37 1.58 -2.38 1.37 0.0\n2.38 -1.37 1.58 2.38 -1.37 0.0\n",
    )
    .unwrap();
    let mut a = base.to_vec();
    a.extend(["--gt", s(&raw)]);
    assert_input_error(
        &run(&a),
        &["raw_units.txt", "not in the frame", "l3d_input.txt"],
    );
    let mut a = base.to_vec();
    a.extend(["--gt", s(&raw), "--protocol", "emap"]);
    assert_input_error(&run(&a), &["raw_units.txt", "not in the frame"]);
}

#[test]
fn help_explains_both_protocols() {
    let o = run(&["eval", "--help"]);
    let h = String::from_utf8_lossy(&o.stdout);
    for needle in [
        "--protocol",
        "exact",
        "emap",
        "--gt-abc",
        "--abc-stats",
        "256^3",
        "--protocol emap      (results/summary.md)",
    ] {
        assert!(h.contains(needle), "`{needle}` not in --help");
    }
}

#[test]
fn batch_summary_prints_the_papers_per_object_means_with_the_protocol() {
    let sc = scene();
    let d = sc.dir.path();
    // Scene b's lines are all shorter than 0.005 and none survives refinement: the scene
    // fails (an empty result is refused) and only a enters the papers' table. (The rule
    // that an object whose lines give no sample is left out of the mean is tested on the
    // table itself, src/batch.rs.)
    let short = d.join("short.txt");
    std::fs::write(
        &short,
        "0.0671 0.7499 0.5 0.0671 0.7499 0.503\n0.0671 0.2501 0.4 0.0671 0.2501 0.403\n",
    )
    .unwrap();
    let gt = data("abc_00000006/gt_sharp_lines.txt");
    let lines = data("emap/l3d_input.txt");
    let manifest = d.join("m.csv");
    std::fs::write(
        &manifest,
        format!(
            "name,gaussians,lines,gt,radius\na,{g},{l},{gt},0.03\nb,{g},{s},{gt},0.03\n",
            g = s(&sc.gaussians),
            l = s(&lines),
            s = s(&short),
            gt = s(&gt)
        ),
    )
    .unwrap();
    let out = d.join("out");
    let o = run(&[
        "batch",
        s(&manifest),
        "-o",
        s(&out),
        "--backend",
        "cpu",
        "--protocol",
        "emap",
    ]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("b: no segment is left"),
        "{}",
        stderr(&o)
    );
    let md = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(md.contains("Ground truth, emap protocol"), "{md}");
    assert!(md.contains("(of 1 with ground truth)"), "{md}");
    // Scene a alone, measured by eval with the same protocol and GT.
    let v = eval_json(&sc, &lines, &["--gt", s(&gt), "--protocol", "emap"]);
    let g = &v["ground_truth"]["before"];
    let row = format!(
        "| input lines | 1 | {:.2} | {:.2} | {:.1} |",
        1000.0 * g["accuracy"].as_f64().unwrap(),
        1000.0 * g["completeness"].as_f64().unwrap(),
        100.0 * g["scores"][0]["precision"].as_f64().unwrap()
    );
    assert!(md.contains(&row), "`{row}` not in:\n{md}");
}
