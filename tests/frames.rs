//! The frame check on real trained pairs (OpenSplat models and Line3D++ lines of the same
//! renders, tests/data/real_pairs): every pair refines without a frame warning, and the
//! same pair with the model normalized as nerfstudio stores it (lines left in the world
//! frame, the two boxes partly overlapping) is refused with the hint, although some
//! segments do find Gaussians there; its `meta_data.json` (`worldtogt`) fixes it.

mod common;

use std::path::{Path, PathBuf};

use common::{data, run, stderr};
use linegs_gpu::geom::Segment;
use linegs_gpu::io::{read_gaussians, read_lines, write_gaussians_ply, write_lines, PlyOptions};

const PAIRS: [&str; 2] = ["real_pairs/proc", "real_pairs/abc00000006"];

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

#[test]
fn every_real_pair_refines_and_evaluates_without_a_frame_warning() {
    let dir = tempfile::tempdir().unwrap();
    for pair in PAIRS {
        let (g, l) = (
            data(&format!("{pair}/point_cloud.ply")),
            data(&format!("{pair}/lines.txt")),
        );
        let out = dir.path().join("out.obj");
        let o = run(&[
            "refine",
            "--backend",
            "cpu",
            "-g",
            s(&g),
            "-l",
            s(&l),
            "-o",
            s(&out),
            "--radius",
            "0.03",
        ]);
        assert!(o.status.success(), "{pair}: {}", stderr(&o));
        assert!(!stderr(&o).contains("frame"), "{pair}: {}", stderr(&o));
        assert!(!stderr(&o).contains("warning"), "{pair}: {}", stderr(&o));
        assert!(
            !read_lines(&out).unwrap().lines.segments.is_empty(),
            "{pair}"
        );
        let e = run(&["eval", "--backend", "cpu", "-g", s(&g), "-l", s(&l)]);
        assert!(e.status.success(), "{pair}: {}", stderr(&e));
        assert!(!stderr(&e).contains("frame"), "{pair}: {}", stderr(&e));
    }
}

/// The proc pair in a "world" frame 4 times its size, moved by (-1, -1, 0) (the lines),
/// and its model normalized into [-1, 1] about the center of its box, as nerfstudio's
/// dataparser does (the Gaussians); with the SDFStudio `meta_data.json` whose `worldtogt`
/// undoes the normalization.
fn normalized_model_world_lines(dir: &Path) -> (PathBuf, PathBuf, PathBuf) {
    let (k, t) = (4.0f64, [-1.0f64, -1.0, 0.0]);
    let world = |p: [f64; 3]| [k * p[0] + t[0], k * p[1] + t[1], k * p[2] + t[2]];
    let lines = read_lines(&data("real_pairs/proc/lines.txt"))
        .unwrap()
        .lines;
    let moved: Vec<Segment> = lines
        .segments
        .iter()
        .map(|sg| Segment::from_arrays(world(sg.p1.to_array()), world(sg.p2.to_array())))
        .collect();
    let l = dir.join("world_lines.obj");
    write_lines(&l, &moved).unwrap();
    let opts = PlyOptions {
        min_opacity: None,
        strict: false,
    };
    let cloud = read_gaussians(&data("real_pairs/proc/point_cloud.ply"), &opts).unwrap();
    let w: Vec<[f64; 3]> = cloud
        .centers
        .iter()
        .map(|c| world([c[0] as f64, c[1] as f64, c[2] as f64]))
        .collect();
    let (mut lo, mut hi) = ([f64::MAX; 3], [f64::MIN; 3]);
    for p in &w {
        for i in 0..3 {
            lo[i] = lo[i].min(p[i]);
            hi[i] = hi[i].max(p[i]);
        }
    }
    let c: Vec<f64> = (0..3).map(|i| 0.5 * (lo[i] + hi[i])).collect();
    let h = (0..3).map(|i| 0.5 * (hi[i] - lo[i])).fold(0.0, f64::max);
    let normalized: Vec<[f32; 3]> = w
        .iter()
        .map(|p| {
            [
                ((p[0] - c[0]) / h) as f32,
                ((p[1] - c[1]) / h) as f32,
                ((p[2] - c[2]) / h) as f32,
            ]
        })
        .collect();
    let g = dir.join("normalized.ply");
    write_gaussians_ply(&g, &normalized, None, "normalized").unwrap();
    let meta = dir.join("meta_data.json");
    std::fs::write(
        &meta,
        format!(
            r#"{{"camera_model": "OPENCV", "height": 400, "width": 400,
  "worldtogt": [[{h}, 0, 0, {}], [0, {h}, 0, {}], [0, 0, {h}, {}], [0, 0, 0, 1]],
  "scene_box": {{"aabb": [[-1, -1, -1], [1, 1, 1]], "near": 0.05, "far": 6.0}}, "frames": []}}"#,
            c[0], c[1], c[2]
        ),
    )
    .unwrap();
    (g, l, meta)
}

/// `only N of M segments` of the frame message.
fn near_of(msg: &str) -> (usize, usize) {
    let rest = msg.split("only ").nth(1).expect("an `only N of M` message");
    let w: Vec<&str> = rest.split_whitespace().collect();
    (w[0].parse().unwrap(), w[2].parse().unwrap())
}

#[test]
fn a_normalized_model_with_world_lines_is_refused_and_its_worldtogt_fixes_it() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l, meta) = normalized_model_world_lines(dir.path());
    let out = dir.path().join("out.obj");
    // r = 0.03 of the pair's frame, in the 4x larger world frame
    let base = [
        "refine",
        "--backend",
        "cpu",
        "-g",
        s(&g),
        "-l",
        s(&l),
        "-o",
        s(&out),
        "--radius",
        "0.12",
    ];
    let o = run(&base);
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("not in one frame"), "{err}");
    assert!(err.contains("--gaussians-transform"), "{err}");
    assert!(err.contains("meta_data.json"), "{err}");
    assert!(!out.exists(), "a refused run writes nothing");
    // Some segments do see Gaussians where the two frames overlap: more than the 1 % that
    // a count alone would call a mismatch, fewer than half.
    let (near, total) = near_of(&err);
    assert!(
        near * 100 >= total && 2 * near < total,
        "{near} of {total}: {err}"
    );

    // eval measures anyway, with the warning
    let e = run(&[
        "eval",
        "--backend",
        "cpu",
        "-g",
        s(&g),
        "-l",
        s(&l),
        "--eval-radius",
        "0.4",
    ]);
    assert!(e.status.success(), "{}", stderr(&e));
    assert!(stderr(&e).contains("warning") && stderr(&e).contains("not in one frame"));

    // the model back in the world frame: no refusal, no warning
    let mut args = base.to_vec();
    args.extend(["--gaussians-transform", s(&meta)]);
    let o = run(&args);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("worldtogt"), "{err}");
    assert!(
        !err.contains("not in one frame") && !err.contains("warning"),
        "{err}"
    );
    assert!(!read_lines(&out).unwrap().lines.segments.is_empty());
}
