//! The memory bounds of the steps whose state grows with the pairs of segments rather than
//! with the segments: a run past one says which bound and how to raise it, exits 1 and
//! writes nothing (docs/robustness.md#dense-inputs).

mod common;

use common::{linegs, run, stderr};
use std::path::Path;

/// 400 pieces of length 0.005 within 0.1 on one edge (each its own input line, ends
/// within 1e-4 of the edge) and 3,000 Gaussians around the edge: step 8 merges them into
/// a few segments, holding about 17 pair entries a piece on the way.
fn dense_edge(dir: &Path) -> (String, String) {
    let (lines, edge, g) = (
        dir.join("lines.txt"),
        dir.join("edge.txt"),
        dir.join("g.ply"),
    );
    // A fixed LCG, so the test needs no RNG crate.
    let mut state = 11u64;
    let mut f = || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((state >> 11) as f64) / ((1u64 << 53) as f64)
    };
    let mut text = String::new();
    for _ in 0..400 {
        let t = f() * 0.095;
        let mut j = || (f() - 0.5) * 2e-4;
        let (a, b, c, d) = (j(), j(), j(), j());
        text += &format!("{t:.7} {a:.7} {b:.7} {:.7} {c:.7} {d:.7}\n", t + 5e-3);
    }
    std::fs::write(&lines, text).unwrap();
    std::fs::write(&edge, "0 0 0 0.1 0 0\n").unwrap();
    let gp = g.to_str().unwrap().to_string();
    let o = run(&[
        "synth",
        "around",
        "-l",
        edge.to_str().unwrap(),
        "-o",
        &gp,
        "-n",
        "3000",
        "--sigma",
        "0.001",
        "--background",
        "0",
        "--seed",
        "5",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    (lines.to_str().unwrap().to_string(), gp)
}

fn refine(g: &str, l: &str, out: &Path, pairs: Option<&str>) -> std::process::Output {
    let mut c = linegs();
    c.args([
        "refine",
        "--backend",
        "cpu",
        "-g",
        g,
        "-l",
        l,
        "-o",
        out.to_str().unwrap(),
        "--radius",
        "0.03",
    ]);
    match pairs {
        Some(v) => c.env("LINEGS_MAX_PAIRS_PER_SEGMENT", v),
        None => c.env_remove("LINEGS_MAX_PAIRS_PER_SEGMENT"),
    };
    c.output().unwrap()
}

/// Step 8 holds at most `LINEGS_MAX_PAIRS_PER_SEGMENT` pair entries a segment: lowered to
/// 2, the dense edge crosses it, and `refine` says which bound and how to raise it, exits
/// 1 and writes nothing; at 64 a segment (and at the default) it refines the same input.
#[test]
fn step_8_stops_at_its_pair_bound_with_exit_1_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let (l, g) = dense_edge(dir.path());
    let out = dir.path().join("out.obj");
    let o = refine(&g, &l, &out, Some("2"));
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let msg = stderr(&o);
    assert!(
        msg.contains("step 8 (merge_join) holds more than 800 pair entries for 400 segments")
            && msg.contains("at most 2 a segment (LINEGS_MAX_PAIRS_PER_SEGMENT)")
            && msg.contains("raise the bound with LINEGS_MAX_PAIRS_PER_SEGMENT=N")
            && !msg.contains("panicked"),
        "{msg}"
    );
    assert!(!out.exists(), "partial output written");

    for pairs in [Some("64"), None] {
        let o = refine(&g, &l, &out, pairs);
        assert!(o.status.success(), "{pairs:?}: {}", stderr(&o));
        let obj = std::fs::read_to_string(&out).unwrap();
        let kept = obj.lines().filter(|s| s.starts_with("l ")).count();
        assert!((1..20).contains(&kept), "{pairs:?}: {kept} segments");
        std::fs::remove_file(&out).unwrap();
    }
}

/// A value of `LINEGS_MAX_PAIRS_PER_SEGMENT` that is no positive whole number is named,
/// not ignored.
#[test]
fn an_unreadable_pair_bound_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (l, g) = dense_edge(dir.path());
    let out = dir.path().join("out.obj");
    for bad in ["0", "many", "-5"] {
        let o = refine(&g, &l, &out, Some(bad));
        assert_eq!(o.status.code(), Some(1), "{bad}: {}", stderr(&o));
        let msg = stderr(&o);
        assert!(
            msg.contains(&format!(
                "LINEGS_MAX_PAIRS_PER_SEGMENT=\"{bad}\" is not a positive"
            )),
            "{msg}"
        );
        assert!(!out.exists());
    }
}

/// `refine` on the dense edge with `extra` options and `LINEGS_MAX_LISTED_MEMBERS=listed`
/// (`None`: unset).
fn refine_listed(
    g: &str,
    l: &str,
    out: &Path,
    listed: Option<&str>,
    extra: &[&str],
) -> std::process::Output {
    let mut c = linegs();
    c.args([
        "refine",
        "--backend",
        "cpu",
        "-g",
        g,
        "-l",
        l,
        "-o",
        out.to_str().unwrap(),
        "--radius",
        "0.03",
    ])
    .args(extra);
    c.env_remove("LINEGS_MAX_PAIRS_PER_SEGMENT");
    match listed {
        Some(v) => c.env("LINEGS_MAX_LISTED_MEMBERS", v),
        None => c.env_remove("LINEGS_MAX_LISTED_MEMBERS"),
    };
    c.output().unwrap()
}

/// The edge fit's decision rule lists the members of the segments it moved, at most
/// `LINEGS_MAX_LISTED_MEMBERS` in one batch: lowered to 1,000, the 400 pieces' lists
/// (about 150 members each) cross it, and `refine` says which bound and how to raise it,
/// exits 1 and writes nothing; at the default it refines the same input.
#[test]
fn the_edge_fit_stops_at_its_member_list_bound_with_exit_1_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let (l, g) = dense_edge(dir.path());
    let out = dir.path().join("out.obj");
    let o = refine_listed(&g, &l, &out, Some("1000"), &["--fit", "edge"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let msg = stderr(&o);
    assert!(
        msg.contains("the edge fit's decision rule (or --max-sagitta's check) on the CPU engine needs more than 1000 listed members in one batch")
            && msg.contains("at most 1000 (LINEGS_MAX_LISTED_MEMBERS)")
            && msg.contains("raise the bound with LINEGS_MAX_LISTED_MEMBERS=N")
            && !msg.contains("panicked"),
        "{msg}"
    );
    assert!(!out.exists(), "partial output written");
    let o = refine_listed(&g, &l, &out, None, &["--fit", "edge"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(out.exists());
}

/// `--split-gaps` with interior splits lists the sorted positions of as many segments at
/// a time as `LINEGS_MAX_LISTED_MEMBERS` allows: a segment that alone holds more stops the
/// run with exit 1 and the bound's message, nothing written (the batches themselves:
/// `gaps::tests`); at the default it refines the same input.
#[test]
fn split_gaps_stops_past_its_member_list_bound_with_exit_1_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let (l, g) = dense_edge(dir.path());
    let out = dir.path().join("out.obj");
    // No fit: its lists would cross the bound first.
    let opts = [
        "--fit",
        "none",
        "--split-gaps",
        "0.01",
        "--split-interior",
        "true",
    ];
    let o = refine_listed(&g, &l, &out, Some("20"), &opts);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    let msg = stderr(&o);
    assert!(
        msg.contains("--split-gaps with interior splits needs more than 20 listed members")
            && msg.contains("LINEGS_MAX_LISTED_MEMBERS=N")
            && !msg.contains("panicked"),
        "{msg}"
    );
    assert!(!out.exists(), "partial output written");
    let o = refine_listed(&g, &l, &out, None, &opts);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(out.exists());
}

/// A value of `LINEGS_MAX_LISTED_MEMBERS` that is no positive whole number is named.
#[test]
fn an_unreadable_member_list_bound_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let (l, g) = dense_edge(dir.path());
    let out = dir.path().join("out.obj");
    let o = refine_listed(&g, &l, &out, Some("lots"), &["--fit", "edge"]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("LINEGS_MAX_LISTED_MEMBERS=\"lots\" is not a positive whole number"),
        "{}",
        stderr(&o)
    );
    assert!(!out.exists());
}
