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
