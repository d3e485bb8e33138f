//! Lines that keep their tracks: `--provenance` lists each output segment's input
//! segments, `--format limap` writes LIMAP `finaltracks/` whose supports are those of the
//! inputs, `--format emap` writes `parametric_edges.json`; each is read back by our own
//! readers. On the real proc pair (Line3D++ lines with their 2D observations).

mod common;

use std::collections::BTreeSet;
use std::path::Path;

use common::{data, run, stderr};
use linegs_gpu::geom::Segment;
use linegs_gpu::io::{read_line3dpp_supports, read_lines, read_supports};

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

const R: f64 = 0.03;

fn refine(lines: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    let g = data("real_pairs/proc/point_cloud.ply");
    let mut args = vec![
        "refine",
        "--backend",
        "cpu",
        "-g",
        s(&g),
        "-l",
        s(lines),
        "-o",
        s(out),
        "--radius",
        "0.03",
    ];
    args.extend_from_slice(extra);
    let o = run(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    o
}

fn provenance(p: &Path) -> Vec<Vec<usize>> {
    let v: serde_json::Value = serde_json::from_slice(&std::fs::read(p).unwrap()).unwrap();
    v["segments"]
        .as_array()
        .unwrap()
        .iter()
        .map(|e| {
            e["sources"]
                .as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_u64().unwrap() as usize)
                .collect()
        })
        .collect()
}

fn near(a: &Segment, b: &Segment, tol: f64) -> bool {
    (a.p1 - b.p1).length().max((a.p2 - b.p2).length()) < tol
}

#[test]
fn every_output_segment_lists_the_input_segments_it_came_from() {
    let dir = tempfile::tempdir().unwrap();
    let l = data("real_pairs/proc/lines.txt");
    let input = read_lines(&l).unwrap().lines;
    let (out, prov, rep) = (
        dir.path().join("out.obj"),
        dir.path().join("prov.json"),
        dir.path().join("report.json"),
    );
    refine(&l, &out, &["--provenance", s(&prov), "--report", s(&rep)]);
    let refined = read_lines(&out).unwrap().lines.segments;
    let p = provenance(&prov);
    assert_eq!(p.len(), refined.len());
    let mut used = BTreeSet::new();
    for (k, src) in p.iter().enumerate() {
        assert!(!src.is_empty(), "segment {k} has no sources");
        assert!(src.windows(2).all(|w| w[0] < w[1]), "{src:?}");
        for &i in src {
            assert!(used.insert(i), "input {i} feeds two outputs");
            // A source lies where its output is: within a few r of the output's line
            // (the fit moves a line by under r; a merge spans both inputs).
            let (a, b) = (&input.segments[i], &refined[k]);
            let d = a.distance_to(b);
            assert!(d < R, "output {k} from input {i}: {d}");
            let dir_cos = (a.p2 - a.p1)
                .normalize()
                .dot((b.p2 - b.p1).normalize())
                .abs();
            assert!(dir_cos > 0.99, "output {k} from input {i}: cos {dir_cos}");
        }
    }
    // This pair merges two inputs into one output (58 -> 57).
    assert_eq!((input.len(), refined.len()), (58, 57));
    assert_eq!(p.iter().filter(|s| s.len() == 2).count(), 1, "{p:?}");
    // The report carries the same lists.
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&rep).unwrap()).unwrap();
    let rs: Vec<Vec<usize>> = serde_json::from_value(r["sources"].clone()).unwrap();
    assert_eq!(rs, p);
    // Without --provenance, no `sources` in the report.
    refine(&l, &out, &["--report", s(&rep)]);
    let r: serde_json::Value = serde_json::from_slice(&std::fs::read(&rep).unwrap()).unwrap();
    assert!(r.get("sources").is_none());
}

#[test]
fn sources_count_the_files_segments_dropped_on_reading() {
    // A degenerate first segment is dropped on reading; the indices stay the file's.
    let dir = tempfile::tempdir().unwrap();
    let input = read_lines(&data("real_pairs/proc/lines.txt"))
        .unwrap()
        .lines;
    let mut text = String::from("0.5 0.5 0.5 0.5 0.5 0.5\n");
    for sg in &input.segments {
        let (a, b) = (sg.p1, sg.p2);
        text.push_str(&format!(
            "{} {} {} {} {} {}\n",
            a.x, a.y, a.z, b.x, b.y, b.z
        ));
    }
    let l = dir.path().join("lines_plain.txt");
    std::fs::write(&l, text).unwrap();
    let (out, prov) = (dir.path().join("out.obj"), dir.path().join("prov.json"));
    refine(&l, &out, &["--provenance", s(&prov)]);
    let refined = read_lines(&out).unwrap().lines.segments;
    let p = provenance(&prov);
    assert!(p.iter().flatten().all(|&i| i >= 1), "{p:?}");
    for (k, src) in p.iter().enumerate() {
        for &i in src {
            assert!(
                input.segments[i - 1].distance_to(&refined[k]) < R,
                "{k} {i}"
            );
        }
    }
}

#[test]
fn limap_tracks_keep_the_inputs_supports_and_read_back() {
    let dir = tempfile::tempdir().unwrap();
    let l = data("real_pairs/proc/lines.txt");
    let obs = read_line3dpp_supports(&l).unwrap();
    let (tracks, prov, obj) = (
        dir.path().join("tracks"),
        dir.path().join("prov.json"),
        dir.path().join("out.obj"),
    );
    refine(&l, &obj, &[]);
    refine(
        &l,
        &tracks,
        &["--format", "limap", "--provenance", s(&prov)],
    );
    let back = read_lines(&tracks).unwrap();
    let plain = read_lines(&obj).unwrap().lines.segments;
    assert_eq!(back.lines.len(), plain.len());
    for (a, b) in back.lines.segments.iter().zip(&plain) {
        assert!(near(a, b, 1e-6), "{a:?} vs {b:?}");
    }
    // Track k's supports: its sources' observations, each (image, 2D line) once.
    let p = provenance(&prov);
    let sup = read_supports(&tracks).unwrap().unwrap();
    assert_eq!(sup.len(), p.len());
    for (k, src) in p.iter().enumerate() {
        let want: BTreeSet<(i64, i64)> = src
            .iter()
            .flat_map(|&i| obs[i].iter().map(|x| (x.image_id, x.line_id)))
            .collect();
        let got: Vec<(i64, i64)> = sup[k].iter().map(|x| (x.image_id, x.line_id)).collect();
        assert_eq!(got.len(), want.len(), "track {k}");
        assert_eq!(
            got.iter().copied().collect::<BTreeSet<_>>(),
            want,
            "track {k}"
        );
        assert!(sup[k].iter().all(|x| x.line2d.is_some()));
        assert!(!got.is_empty());
    }
    // The 2D segments are the observations' own.
    let first = &obs[p[0][0]][0];
    assert_eq!(sup[0][0].line2d, first.line2d);
    // LIMAP in, LIMAP out: the supports travel on.
    let (again, prov2) = (dir.path().join("again"), dir.path().join("prov2.json"));
    refine(
        &tracks,
        &again,
        &["--format", "limap", "--provenance", s(&prov2)],
    );
    let sup2 = read_supports(&again).unwrap().unwrap();
    for (k, src) in provenance(&prov2).iter().enumerate() {
        let want: BTreeSet<(i64, i64)> = src
            .iter()
            .flat_map(|&i| sup[i].iter().map(|x| (x.image_id, x.line_id)))
            .collect();
        let got: BTreeSet<(i64, i64)> = sup2[k].iter().map(|x| (x.image_id, x.line_id)).collect();
        assert_eq!(got, want, "track {k}");
    }
    // A folder that holds files already is refused before any work.
    let o = run(&[
        "refine",
        "--backend",
        "cpu",
        "-g",
        s(&data("real_pairs/proc/point_cloud.ply")),
        "-l",
        s(&l),
        "-o",
        s(&again),
        "--format",
        "limap",
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("not empty"), "{}", stderr(&o));
}

#[test]
fn emap_edges_read_back_as_the_refined_segments() {
    let dir = tempfile::tempdir().unwrap();
    let l = data("real_pairs/proc/lines.txt");
    let (npy, edges_dir) = (dir.path().join("out.npy"), dir.path().join("emap"));
    std::fs::create_dir(&edges_dir).unwrap();
    refine(&l, &npy, &[]);
    refine(&l, &edges_dir, &["--format", "emap"]);
    let f = edges_dir.join("parametric_edges.json");
    let back = read_lines(&f).unwrap().lines.segments;
    let want = read_lines(&npy).unwrap().lines.segments;
    // Written exactly (shortest round-trip digits); serde_json's parser may miss the last
    // bit without its `float_roundtrip` feature.
    assert_eq!(back.len(), want.len());
    for (a, b) in back.iter().zip(&want) {
        assert!(near(a, b, 1e-15), "{a:?} vs {b:?}");
    }
    let named = dir.path().join("edges.json");
    refine(&l, &named, &["--format", "emap"]);
    assert_eq!(std::fs::read(&named).unwrap(), std::fs::read(&f).unwrap());
}
