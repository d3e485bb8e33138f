//! The box scene of the authors' s200k shape (`synth s200k`) and its benchmark case
//! (`bench --case s200k`), as a user runs them. The scene is SYNTHETIC (centres placed by a
//! rule, dense on the box edges), not a trained model.

use std::path::Path;

mod common;
use common::{run, stderr, stdout};

fn synth(dir: &Path, seed: &str) -> (String, String) {
    let g = dir.join(format!("g{seed}.ply"));
    let l = dir.join(format!("l{seed}.obj"));
    let (g, l) = (g.to_str().unwrap(), l.to_str().unwrap());
    let o = run(&["synth", "s200k", "--seed", seed, "-o", g, "--lines-out", l]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("200000 Gaussians") && stdout(&o).contains("318 input segments"),
        "{}",
        stdout(&o)
    );
    (g.to_string(), l.to_string())
}

#[test]
fn the_scene_has_the_s200k_shape_and_refining_it_removes_its_defects() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = synth(dir.path(), "1");
    let gt = dir.path().join("gt.obj");
    let o = run(&[
        "synth",
        "s200k",
        "-o",
        dir.path().join("again.ply").to_str().unwrap(),
        "--lines-out",
        dir.path().join("again.obj").to_str().unwrap(),
        "--gt-out",
        gt.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // The default seed is 1, and the same seed writes the same bytes.
    assert_eq!(
        std::fs::read(&g).unwrap(),
        std::fs::read(dir.path().join("again.ply")).unwrap()
    );
    assert_eq!(
        std::fs::read(&l).unwrap(),
        std::fs::read(dir.path().join("again.obj")).unwrap()
    );
    let edges = std::fs::read_to_string(&gt).unwrap();
    assert_eq!(edges.lines().filter(|x| x.starts_with("l ")).count(), 120);

    let report = dir.path().join("r.json");
    let o = run(&[
        "refine",
        "--backend",
        "cpu",
        "-g",
        &g,
        "-l",
        &l,
        "-o",
        dir.path().join("out.obj").to_str().unwrap(),
        "--report",
        report.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(r["input"]["gaussians_read"], 200_000);
    assert_eq!(r["input"]["segments_read"], 318);
    assert_eq!(r["input"]["n_box"], 200_000);
    // 42 outliers dropped, 120 duplicates merged and 24 split edges joined leave about
    // one segment an edge (120 edges).
    let out = r["after"]["segments"].as_u64().unwrap();
    assert!((110..=160).contains(&out), "{out} segments out");
}

#[test]
fn another_seed_gives_another_scene_of_the_same_shape() {
    let dir = tempfile::tempdir().unwrap();
    let (g1, l1) = synth(dir.path(), "1");
    let (g2, l2) = synth(dir.path(), "2");
    assert_ne!(std::fs::read(g1).unwrap(), std::fs::read(g2).unwrap());
    assert_ne!(std::fs::read(l1).unwrap(), std::fs::read(l2).unwrap());
}

#[test]
fn the_bench_case_times_whole_runs_and_prints_the_command() {
    let o = run(&["bench", "--case", "s200k", "--repeat", "2", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let t = &v["tables"][0];
    assert_eq!(t["case"], "s200k");
    assert_eq!(t["command"], "linegs-gpu bench --case s200k --repeat 2");
    let row = &t["rows"][0];
    let cells = row["cells"].as_array().unwrap();
    assert_eq!(cells[0], 200_000);
    assert_eq!(cells[1], 318);
    assert_eq!(cells[2], "cpu");
    let (median, fastest, slowest) = (
        cells[3].as_f64().unwrap(),
        cells[4].as_f64().unwrap(),
        cells[5].as_f64().unwrap(),
    );
    assert!(fastest > 0.0 && fastest <= median && median <= slowest);
    assert!((cells[6].as_f64().unwrap() - 559.0 / median).abs() < 1e-6 * (559.0 / median));
    let load = cells[7].as_f64().unwrap();
    assert!(load > 0.0 && load < median, "load {load}, whole {median}");
    assert!(cells[9].as_u64().unwrap() < 318);
    let cmd = row["command"].as_str().unwrap();
    assert!(
        cmd.contains("synth s200k --seed 7") && cmd.contains("refine --backend cpu"),
        "{cmd}"
    );
}
