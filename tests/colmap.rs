//! COLMAP sparse models (tests/data/real_pairs/proc/colmap_text_model: the real text model
//! of the proc pair) and the automatic frame: the proc pair's trained model normalized as
//! gsplat's `normalize_world_space` stores it, refined against the lines in the COLMAP
//! frame with `--colmap` and no transform, finds the frame and gives the segments that
//! the matrix given by hand gives.

mod common;

use std::path::{Path, PathBuf};

use common::{data, run, stderr};
use glam::{DMat4, DVec3};
use linegs_gpu::autoframe;
use linegs_gpu::io::{
    read_colmap, read_gaussians, read_lines, write_colmap_binary, write_gaussians_ply, PlyOptions,
};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn model_dir() -> PathBuf {
    data("real_pairs/proc/colmap_text_model")
}

/// gsplat's own `normalize.py` (numpy 2.4) on this model: `similarity_from_cameras`
/// alone, and the whole `normalize_world_space` of its `colmap.py` (T3 T2 T1), row by row.
const GSPLAT_T1: [[f64; 4]; 3] = [
    [
        0.3134840782014395,
        0.003349564217957852,
        -0.0033393169606150933,
        -0.13704510628855268,
    ],
    [
        -0.003349564217957852,
        0.0009427181393581719,
        -0.31350044594239324,
        0.06596032288255385,
    ],
    [
        -0.0033393169606150933,
        0.31350044594239324,
        0.0009783967380602517,
        -0.13492024659070534,
    ],
];
const GSPLAT_T: [[f64; 4]; 3] = [
    [
        0.25240093389433954,
        0.1859043494733914,
        0.005289548200010699,
        -0.2148115121128586,
    ],
    [
        -0.18593829416518007,
        0.2520549179070143,
        0.013780675812568666,
        -0.040371865927562214,
    ],
    [
        0.003918830977224797,
        -0.014231272247529245,
        0.31317207978682987,
        -0.04309457514890258,
    ],
];

fn mat(rows: &[[f64; 4]; 3]) -> DMat4 {
    let mut a = [0.0; 16];
    for r in 0..3 {
        a[4 * r..4 * r + 4].copy_from_slice(&rows[r]);
    }
    a[15] = 1.0;
    DMat4::from_cols_array(&a).transpose()
}

fn max_diff(a: &DMat4, b: &DMat4) -> f64 {
    (0..4)
        .map(|c| (a.col(c) - b.col(c)).abs().max_element())
        .fold(0.0, f64::max)
}

#[test]
fn the_real_text_model_reads_and_its_binary_copy_reads_the_same() {
    let m = read_colmap(&model_dir()).unwrap();
    assert!(!m.binary);
    assert_eq!(m.cameras.len(), 1);
    assert_eq!(m.cameras[0].model, "PINHOLE");
    assert_eq!((m.cameras[0].width, m.cameras[0].height), (800, 800));
    assert_eq!(
        m.cameras[0].params,
        vec![1111.111365, 1111.111365, 399.5, 399.5]
    );
    assert_eq!(m.images.len(), 60);
    assert_eq!(m.images[0].name, "000.png");
    assert_eq!(m.images[0].tvec, [-0.5, 0.330431858739, 3.585930701304]);
    assert_eq!(m.images[0].points2d[0], ([515.732, 473.722], 2));
    assert_eq!(m.points.len(), 2693);
    assert_eq!(m.points[0].xyz, [0.203658, 0.279553, 0.181248]);
    assert_eq!(m.points[0].rgb, [34, 48, 104]);
    assert_eq!(&m.points[0].track[..2], &[(2, 0), (3, 0)]);
    // The renders' cameras sit on a sphere about the unit cube's centre, looking in.
    for im in &m.images {
        let d = (im.center() - DVec3::splat(0.5)).length();
        assert!((2.0..6.0).contains(&d), "{}: {d}", im.name);
    }
    let dir = tempfile::tempdir().unwrap();
    write_colmap_binary(dir.path(), &m).unwrap();
    let b = read_colmap(dir.path()).unwrap();
    assert!(b.binary);
    assert_eq!(
        (&b.cameras, &b.images, &b.points),
        (&m.cameras, &m.images, &m.points)
    );
    // A folder holding the model under sparse/0, as COLMAP's own layout.
    let nested = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(nested.path().join("sparse/0")).unwrap();
    write_colmap_binary(&nested.path().join("sparse/0"), &m).unwrap();
    assert_eq!(read_colmap(nested.path()).unwrap().points, m.points);
}

#[test]
fn our_gsplat_normalization_is_gsplats_own() {
    let m = read_colmap(&model_dir()).unwrap();
    let cands = autoframe::gsplat_normalizations(&m);
    assert_eq!(cands.len(), 5);
    let d1 = max_diff(&cands[0].to_model, &mat(&GSPLAT_T1));
    assert!(d1 < 1e-12, "T1 differs by {d1}");
    // numpy's eigenvectors have no fixed sign: one of the four choices is gsplat's.
    let best = cands[1..]
        .iter()
        .map(|c| max_diff(&c.to_model, &mat(&GSPLAT_T)))
        .fold(f64::MAX, f64::min);
    assert!(best < 1e-7, "T differs by {best}");
}

/// nerfstudio's COLMAP dataparser (`colmap_dataparser.py`, `camera_utils.py`:
/// `auto_orient_and_center_poses` with `up` and `poses`, auto scale) transcribed line by
/// line from torch to numpy and run on this model: `scale * transform @ applied_transform`.
const NERFSTUDIO: [[f64; 4]; 3] = [
    [
        0.34213037825438314,
        0.003655647469634812,
        -0.003644463823476181,
        -0.17067660549136124,
    ],
    [
        -0.003644463823476181,
        0.34214824167428376,
        0.0010678024655387138,
        -0.17534200302480454,
    ],
    [
        0.003655647469634812,
        -0.001028863569084743,
        0.34214824167428376,
        -0.8511383951918992,
    ],
];

#[test]
fn our_nerfstudio_normalization_is_its_dataparsers() {
    let m = read_colmap(&model_dir()).unwrap();
    let n = autoframe::nerfstudio_normalization(&m).unwrap();
    // nerfstudio computes in float32.
    let d = max_diff(&n.to_model, &mat(&NERFSTUDIO));
    assert!(d < 1e-6, "differs by {d}");
}

/// The proc pair's model mapped by gsplat's normalization of its COLMAP model.
fn gsplat_normalized_model(dir: &Path) -> PathBuf {
    let opts = PlyOptions {
        min_opacity: None,
        strict: false,
    };
    let cloud = read_gaussians(&data("real_pairs/proc/point_cloud.ply"), &opts).unwrap();
    let t = mat(&GSPLAT_T);
    let moved: Vec<[f32; 3]> = cloud
        .centers
        .iter()
        .map(|c| {
            let p = t.transform_point3(DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64));
            [p.x as f32, p.y as f32, p.z as f32]
        })
        .collect();
    let g = dir.join("gsplat_normalized.ply");
    write_gaussians_ply(&g, &moved, None, "gsplat normalized").unwrap();
    g
}

/// The matrix rows of the `note: Gaussians mapped by the frame ...` line.
fn printed_matrix(err: &str) -> String {
    let line = err
        .lines()
        .find(|l| l.starts_with("note: Gaussians mapped by the frame found from"))
        .unwrap_or_else(|| panic!("no frame note in {err}"));
    let rows = line.split("row by row: [").nth(1).unwrap();
    rows.trim_end_matches(']').replace("; ", "\n")
}

#[test]
fn refine_finds_the_gsplat_frame_from_the_colmap_model_and_matches_the_hand_matrix() {
    let dir = tempfile::tempdir().unwrap();
    let g = gsplat_normalized_model(dir.path());
    let l = data("real_pairs/proc/lines.txt");
    let colmap = model_dir();
    let (auto, hand, exact) = (
        dir.path().join("auto.obj"),
        dir.path().join("hand.obj"),
        dir.path().join("exact.obj"),
    );
    let refine = |out: &Path, extra: &[&str]| {
        let mut args = vec![
            "refine",
            "--backend",
            "cpu",
            "-g",
            s(&g),
            "-l",
            s(&l),
            "-o",
            s(out),
            "--radius",
            "0.03",
        ];
        args.extend_from_slice(extra);
        run(&args)
    };
    // Without anything: refused, as before.
    let o = refine(&auto, &[]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("not in one frame"), "{}", stderr(&o));
    // With the COLMAP model: found, with its residual.
    let o = refine(&auto, &["--colmap", s(&colmap)]);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("gsplat normalize_world_space"), "{err}");
    assert!(err.contains("residual"), "{err}");
    assert!(
        err.contains("58 of 58 segments near Gaussians (before: 1)"),
        "{err}"
    );
    assert!(!err.contains("warning"), "{err}");
    // The matrix printed, given by hand: the very same bytes.
    let m = dir.path().join("found.txt");
    std::fs::write(&m, printed_matrix(&err)).unwrap();
    let o = refine(&exact, &["--gaussians-transform", s(&m)]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        std::fs::read(&auto).unwrap(),
        std::fs::read(&exact).unwrap()
    );
    // gsplat's own matrix inverted, given by hand: the same segments (to f32 rounding of
    // the centers).
    let inv = mat(&GSPLAT_T).inverse();
    let hm = dir.path().join("hand.txt");
    std::fs::write(&hm, autoframe::matrix_rows(&inv)).unwrap();
    let o = refine(&hand, &["--gaussians-transform", s(&hm)]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (a, h) = (
        read_lines(&auto).unwrap().lines.segments,
        read_lines(&hand).unwrap().lines.segments,
    );
    assert_eq!(a.len(), h.len());
    for (x, y) in a.iter().zip(&h) {
        let d = (x.p1 - y.p1).length().max((x.p2 - y.p2).length());
        assert!(d < 1e-4, "{x:?} vs {y:?}");
    }
    // eval and render take it too.
    let e = run(&[
        "eval",
        "--backend",
        "cpu",
        "-g",
        s(&g),
        "-l",
        s(&l),
        "--colmap",
        s(&colmap),
    ]);
    assert!(e.status.success(), "{}", stderr(&e));
    assert!(stderr(&e).contains("frame found"), "{}", stderr(&e));
    assert!(!stderr(&e).contains("not in one frame"), "{}", stderr(&e));
}

#[test]
fn a_model_that_fits_no_normalization_is_refused_and_bad_models_exit_2() {
    let dir = tempfile::tempdir().unwrap();
    let g = gsplat_normalized_model(dir.path());
    let l = data("real_pairs/proc/lines.txt");
    let out = dir.path().join("out.obj");
    // A COLMAP model of other cameras and points: nothing fits, the usual refusal.
    let mut m = read_colmap(&model_dir()).unwrap();
    for im in &mut m.images {
        im.tvec = [im.tvec[0] * 3.0 + 1.0, im.tvec[1] - 2.0, im.tvec[2] * 0.5];
    }
    for p in &mut m.points {
        p.xyz = [p.xyz[2] * 7.0, p.xyz[0], -p.xyz[1]];
    }
    let other = dir.path().join("other");
    std::fs::create_dir(&other).unwrap();
    write_colmap_binary(&other, &m).unwrap();
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
        "0.03",
    ];
    let mut args = base.to_vec();
    args.extend(["--colmap", s(&other)]);
    let o = run(&args);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("no normalization of the COLMAP model fits"),
        "{}",
        stderr(&o)
    );
    assert!(stderr(&o).contains("not in one frame"), "{}", stderr(&o));
    assert!(!out.exists());
    // A malformed model: the file and the place, exit 2.
    let bad = dir.path().join("bad");
    std::fs::create_dir(&bad).unwrap();
    for f in ["cameras.txt", "images.txt", "points3D.txt"] {
        std::fs::copy(model_dir().join(f), bad.join(f)).unwrap();
    }
    let pts = std::fs::read_to_string(bad.join("points3D.txt")).unwrap();
    std::fs::write(
        bad.join("points3D.txt"),
        pts.replacen("0.279553", "0.27x", 1),
    )
    .unwrap();
    let mut args = base.to_vec();
    args.extend(["--colmap", s(&bad)]);
    let o = run(&args);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("points3D.txt: line 2, value 3"),
        "{}",
        stderr(&o)
    );
    assert!(!out.exists());
    // Both a transform and --colmap: one or the other.
    let mut args = base.to_vec();
    args.extend(["--colmap", s(&bad), "--gaussians-transform", s(&bad)]);
    assert_eq!(run(&args).status.code(), Some(2));
}

/// A COLMAP model for the toy scene: 24 cameras on two rings about the middle of its
/// Gaussians, looking at it with world z up, and every 7th Gaussian center as a sparse
/// point.
fn toy_colmap(centers: &[[f32; 3]]) -> linegs_gpu::io::ColmapModel {
    use glam::{DMat3, DQuat};
    use linegs_gpu::io::{Camera, ColmapModel, Image, Point3D};
    let pts: Vec<DVec3> = centers
        .iter()
        .map(|c| DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64))
        .collect();
    let (lo, hi) = pts.iter().fold(
        (DVec3::splat(f64::MAX), DVec3::splat(f64::MIN)),
        |(a, b), p| (a.min(*p), b.max(*p)),
    );
    let (mid, size) = ((lo + hi) * 0.5, (hi - lo).max_element());
    let images = (0..24)
        .map(|k| {
            let a = k as f64 * std::f64::consts::TAU / 12.0 + 0.1;
            let h = if k < 12 { 0.4 } else { 1.1 };
            let c = mid + DVec3::new(a.cos(), a.sin(), h).normalize() * 2.5 * size;
            let fwd = (mid - c).normalize();
            let right = fwd.cross(DVec3::Z).normalize();
            let down = fwd.cross(right);
            let r = DMat3::from_cols(right, down, fwd).transpose();
            let q = DQuat::from_mat3(&r);
            let t = -(r * c);
            Image {
                id: k + 1,
                qvec: [q.w, q.x, q.y, q.z],
                tvec: t.to_array(),
                camera_id: 1,
                name: format!("{k:03}.png"),
                points2d: vec![],
            }
        })
        .collect();
    ColmapModel {
        cameras: vec![Camera {
            id: 1,
            model: "PINHOLE".into(),
            width: 800,
            height: 600,
            params: vec![700.0, 700.0, 400.0, 300.0],
        }],
        images,
        points: pts
            .iter()
            .step_by(7)
            .enumerate()
            .map(|(i, p)| Point3D {
                id: i as u64 + 1,
                xyz: p.to_array(),
                rgb: [128, 128, 128],
                error: 0.5,
                track: vec![],
            })
            .collect(),
        ..Default::default()
    }
}

#[test]
fn the_toy_scene_normalized_by_gsplat_or_nerfstudio_finds_its_frame() {
    let dir = tempfile::tempdir().unwrap();
    let (g, l) = common::synth_toy(dir.path(), 20_000);
    let opts = PlyOptions {
        min_opacity: None,
        strict: false,
    };
    let centers = read_gaussians(&g, &opts).unwrap().centers;
    let model = toy_colmap(&centers);
    let colmap = dir.path().join("sparse/0");
    std::fs::create_dir_all(&colmap).unwrap();
    write_colmap_binary(&colmap, &model).unwrap();
    let cands = autoframe::normalizations(&model);
    // A gsplat candidate with two axes flipped, and nerfstudio's.
    for (k, family) in [(3, "gsplat"), (cands.len() - 1, "nerfstudio")] {
        let n = &cands[k];
        assert!(n.name.starts_with(family), "{}", n.name);
        let moved: Vec<[f32; 3]> = centers
            .iter()
            .map(|c| {
                let p =
                    n.to_model
                        .transform_point3(DVec3::new(c[0] as f64, c[1] as f64, c[2] as f64));
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect();
        let gn = dir.path().join(format!("{family}.ply"));
        write_gaussians_ply(&gn, &moved, None, family).unwrap();
        let (auto, hand) = (dir.path().join("auto.obj"), dir.path().join("hand.obj"));
        let refine = |out: &Path, extra: &[&str]| {
            let mut args = vec![
                "refine",
                "--backend",
                "cpu",
                "-g",
                s(&gn),
                "-l",
                s(&l),
                "-o",
                s(out),
            ];
            args.extend_from_slice(extra);
            run(&args)
        };
        let o = refine(&auto, &["--colmap", s(dir.path())]);
        let err = stderr(&o);
        assert!(o.status.success(), "{family}: {err}");
        assert!(
            err.contains("COLMAP binary model: 1 cameras, 24 images"),
            "{err}"
        );
        assert!(err.contains(&n.name), "{family}: {err}");
        assert!(err.contains("residual"), "{err}");
        // The right matrix by hand: the same bytes.
        let m = dir.path().join("hand.txt");
        std::fs::write(&m, autoframe::matrix_rows(&n.to_colmap())).unwrap();
        let o = refine(&hand, &["--gaussians-transform", s(&m)]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert_eq!(std::fs::read(&auto).unwrap(), std::fs::read(&hand).unwrap());
    }
}
