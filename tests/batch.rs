//! `linegs-gpu batch`: a manifest of small synthetic scenes run as two shards (one from
//! Slurm's variables), resumed with `--skip-existing`, and a failing scene that does not
//! stop the others.

mod common;

use common::{linegs, stderr, stdout};
use std::path::{Path, PathBuf};
use std::process::Output;

/// `linegs-gpu args` with `env` set and no Slurm variables of the test's own environment.
fn run(args: &[&str], env: &[(&str, &str)]) -> Output {
    let mut c = linegs();
    c.args(args);
    for k in [
        "SLURM_ARRAY_TASK_ID",
        "SLURM_ARRAY_TASK_COUNT",
        "SLURM_ARRAY_TASK_MIN",
    ] {
        c.env_remove(k);
    }
    for (k, v) in env {
        c.env(k, v);
    }
    c.output().unwrap()
}

/// Three toy scenes in `dir/s1..s3` (the first with ground truth) and their manifest.
fn scenes(dir: &Path) -> PathBuf {
    for i in 1..=3 {
        let s = dir.join(format!("s{i}"));
        std::fs::create_dir(&s).unwrap();
        let (g, l, gt) = (s.join("g.ply"), s.join("l.txt"), s.join("gt.obj"));
        let seed = i.to_string();
        let o = run(
            &[
                "synth",
                "toy",
                "-o",
                g.to_str().unwrap(),
                "--lines-out",
                l.to_str().unwrap(),
                "--gt-out",
                gt.to_str().unwrap(),
                "-n",
                "3000",
                "--seed",
                &seed,
            ],
            &[],
        );
        assert!(o.status.success(), "{}", stderr(&o));
    }
    let m = dir.join("scenes.csv");
    std::fs::write(
        &m,
        "name,gaussians,lines,gt,radius,eval_radius\n\
         first,s1/g.ply,s1/l.txt,s1/gt.obj,,\n\
         second,s2/g.ply,s2/l.txt,,0.04,0.12\n\
         third,s3/g.ply,s3/l.txt,,,\n",
    )
    .unwrap();
    m
}

fn summary_rows(out: &Path) -> Vec<Vec<String>> {
    std::fs::read_to_string(out.join("summary.csv"))
        .unwrap()
        .lines()
        .map(|l| l.split(',').map(str::to_string).collect())
        .collect()
}

#[test]
fn two_shards_then_a_resume_give_every_scene_and_a_summary_with_a_mean() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    let out = dir.path().join("out");
    let (ms, os) = (m.to_str().unwrap(), out.to_str().unwrap());
    let o = run(
        &["batch", ms, "-o", os, "--shard", "0/2", "--backend", "cpu"],
        &[],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(out.join("first/report.json").is_file() && out.join("third/report.json").is_file());
    assert!(!out.join("second").exists());
    // the second shard from Slurm's array variables
    let o = run(
        &["batch", ms, "-o", os, "--backend", "cpu"],
        &[
            ("SLURM_ARRAY_TASK_ID", "1"),
            ("SLURM_ARRAY_TASK_COUNT", "2"),
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("shard 1/2 runs 1"), "{}", stdout(&o));
    let before = std::fs::read(out.join("first/report.json")).unwrap();
    let o = run(
        &["batch", ms, "-o", os, "--skip-existing", "--backend", "cpu"],
        &[],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(stdout(&o).matches("skipped").count(), 3, "{}", stdout(&o));
    assert_eq!(
        std::fs::read(out.join("first/report.json")).unwrap(),
        before
    );

    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        ["first", "second", "summary.csv", "summary.md", "third"]
    );
    for s in ["first", "second", "third"] {
        assert!(out.join(s).join("refined.obj").is_file(), "{s}");
    }
    // the manifest's per-scene radius reached the run
    let r: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("second/report.json")).unwrap()).unwrap();
    assert_eq!(r["radius"], 0.04);
    assert_eq!(r["before"]["radius"], 0.12);

    let rows = summary_rows(&out);
    assert_eq!(rows.len(), 5, "header, three scenes, mean");
    let col = |name: &str| rows[0].iter().position(|c| c == name).unwrap();
    assert_eq!(rows[1][0], "first");
    assert_eq!(rows[4][0], "mean");
    for row in &rows[1..4] {
        assert_eq!(row[col("status")], "ok");
        let b: f64 = row[col("score_before")].parse().unwrap();
        let a: f64 = row[col("score_after")].parse().unwrap();
        let imp: f64 = row[col("score_improvement_pct")].parse().unwrap();
        assert!((imp - 100.0 * (a - b) / b).abs() < 1e-9);
    }
    let mean = |k: &str| -> f64 {
        rows[1..4]
            .iter()
            .map(|r| r[col(k)].parse::<f64>().unwrap())
            .sum::<f64>()
            / 3.0
    };
    let m_score: f64 = rows[4][col("score_after")].parse().unwrap();
    assert!((m_score - mean("score_after")).abs() < 1e-9);
    // ground truth where the manifest gives it, empty elsewhere
    assert!(rows[1][col("gt_accuracy_after")].parse::<f64>().is_ok());
    assert_eq!(rows[2][col("gt_accuracy_after")], "");
    let md = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        md.contains("| **mean** |") && md.contains("3 of 3 scenes finished"),
        "{md}"
    );
}

#[test]
fn a_failing_scene_is_reported_and_the_others_finish() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    std::fs::write(dir.path().join("s2/l.txt"), "3\n1 2 3\n").unwrap();
    let out = dir.path().join("out");
    let o = run(
        &[
            "batch",
            m.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--backend",
            "cpu",
        ],
        &[],
    );
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(stderr(&o).contains("1 of 3 scenes"), "{}", stderr(&o));
    assert!(out.join("first/report.json").is_file() && out.join("third/report.json").is_file());
    let err = std::fs::read_to_string(out.join("second/error.txt")).unwrap();
    assert!(err.contains("l.txt"), "{err}");
    let rows = summary_rows(&out);
    assert_eq!(rows.len(), 5);
    assert!(
        rows[2][1].trim_start_matches('"').starts_with("failed: "),
        "{:?}",
        rows[2]
    );
    assert!(rows[4][1].contains("mean of 2"), "{:?}", rows[4]);
    // a bad manifest is the user's input: exit 2, nothing written
    let bad = dir.path().join("bad.csv");
    std::fs::write(&bad, "name,lines\nx,l.txt\n").unwrap();
    let o2 = dir.path().join("out2");
    let o = run(
        &["batch", bad.to_str().unwrap(), "-o", o2.to_str().unwrap()],
        &[],
    );
    assert_eq!(o.status.code(), Some(2));
    assert!(stderr(&o).contains("bad.csv: line 1"), "{}", stderr(&o));
    assert!(!o2.exists());
}

fn names_in(dir: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

/// The natural layout: each scene's inputs in `./<name>/` and `-o .`. The scene folders
/// keep every file `batch` did not write, across reruns, failures and successes.
#[test]
fn an_output_folder_that_holds_the_inputs_keeps_every_file_batch_did_not_write() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    std::fs::write(
        &m,
        "name,gaussians,lines\ns1,s1/g.ply,s1/l.txt\ns2,s2/g.ply,s2/l.txt\n",
    )
    .unwrap();
    std::fs::write(dir.path().join("s1/notes.txt"), "mine").unwrap();
    // Litter of killed runs: a temporary of an owned output and an old-style folder.
    std::fs::write(dir.path().join("s1/.linegs-AbC123.tmp"), "x").unwrap();
    make_old(&dir.path().join("s1/.linegs-AbC123.tmp"));
    std::fs::create_dir(dir.path().join(".s1.partial-Xy12ab")).unwrap();
    std::fs::write(dir.path().join(".s1.partial-Xy12ab/refined.obj"), "x").unwrap();
    let batch = || {
        let mut c = linegs();
        c.current_dir(dir.path())
            .args(["batch", "scenes.csv", "-o", ".", "--backend", "cpu"]);
        c.output().unwrap()
    };
    let o = batch();
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        names_in(&dir.path().join("s1")),
        [
            "g.ply",
            "gt.obj",
            "l.txt",
            "notes.txt",
            "refined.obj",
            "report.json"
        ]
    );
    assert!(!dir.path().join(".s1.partial-Xy12ab").exists());
    // A rerun replaces only the owned files; a failure then swaps the report for an
    // error, and a later success swaps it back, the inputs and notes untouched.
    let o = batch();
    assert!(o.status.success(), "{}", stderr(&o));
    let good = std::fs::read(dir.path().join("s2/l.txt")).unwrap();
    std::fs::write(dir.path().join("s2/l.txt"), "3\n1 2 3\n").unwrap();
    let o = batch();
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert_eq!(
        names_in(&dir.path().join("s2")),
        ["error.txt", "g.ply", "gt.obj", "l.txt"]
    );
    std::fs::write(dir.path().join("s2/l.txt"), good).unwrap();
    let o = batch();
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        names_in(&dir.path().join("s2")),
        ["g.ply", "gt.obj", "l.txt", "refined.obj", "report.json"]
    );
    assert_eq!(
        std::fs::read_to_string(dir.path().join("s1/notes.txt")).unwrap(),
        "mine"
    );
    assert_eq!(
        names_in(dir.path()),
        ["s1", "s2", "s3", "scenes.csv", "summary.csv", "summary.md"]
    );
}

/// An input named like an owned output is never replaced or removed.
#[test]
fn an_input_named_like_an_output_of_batch_is_refused_not_overwritten() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    let input = dir.path().join("s1/refined.txt");
    std::fs::rename(dir.path().join("s1/l.txt"), &input).unwrap();
    std::fs::write(&m, "name,gaussians,lines\ns1,s1/g.ply,s1/refined.txt\n").unwrap();
    let before = std::fs::read(&input).unwrap();
    let o = run(
        &[
            "batch",
            m.to_str().unwrap(),
            "-o",
            dir.path().to_str().unwrap(),
            "--format",
            "txt",
            "--backend",
            "cpu",
        ],
        &[],
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("refined.txt is an input of scene `s1`"),
        "{}",
        stderr(&o)
    );
    assert_eq!(std::fs::read(&input).unwrap(), before);
    assert!(!dir.path().join("s1/report.json").exists());
    assert!(!dir.path().join("s1/error.txt").exists());
}

/// A scene another `batch` is working on (its lock held) is left alone, and said so.
#[cfg(unix)]
#[test]
fn a_scene_locked_by_another_batch_is_left_to_it() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    let out = dir.path().join("out");
    std::fs::create_dir_all(out.join("first")).unwrap();
    let lock = std::fs::File::create(out.join("first/.linegs-batch.lock")).unwrap();
    {
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a descriptor that `lock` owns.
        let r = unsafe { libc::flock(lock.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        assert_eq!(r, 0);
    }
    let o = run(
        &[
            "batch",
            m.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--backend",
            "cpu",
        ],
        &[],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("first: skipped (another batch is working on it"),
        "{}",
        stdout(&o)
    );
    assert!(!out.join("first/report.json").exists());
    assert!(out.join("second/report.json").is_file());
    // The others' locks are gone after the run; the held one stays.
    assert_eq!(
        names_in(&out.join("second")),
        ["refined.obj", "report.json"]
    );
    assert!(out.join("first/.linegs-batch.lock").exists());
    drop(lock);
}

#[test]
fn concurrent_shards_write_no_summary_and_summary_only_writes_the_one_summary() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    let out = dir.path().join("out");
    let (ms, os) = (m.to_str().unwrap(), out.to_str().unwrap());
    // a shard that saw only part of the dataset: no summary of that part
    let o = run(
        &[
            "batch",
            ms,
            "-o",
            os,
            "--shard",
            "0/2",
            "--no-summary",
            "--backend",
            "cpu",
        ],
        &[],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stdout(&o).contains("no summary written"), "{}", stdout(&o));
    assert!(out.join("first/report.json").is_file());
    assert!(!out.join("summary.csv").exists() && !out.join("summary.md").exists());
    // a run killed inside a scene leaves its temporary folder
    std::fs::create_dir(out.join(".second.partial-Xy12ab")).unwrap();
    std::fs::write(out.join(".second.partial-Xy12ab/refined.obj"), "v 0 0 0\n").unwrap();
    // --summary-only runs nothing: it names the scene nobody ran as pending
    let o = run(&["batch", ms, "-o", os, "--summary-only"], &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stdout(&o).contains("2 of 3 scenes finished"),
        "{}",
        stdout(&o)
    );
    assert!(stdout(&o).contains("removed 1 folders"), "{}", stdout(&o));
    assert!(!out.join("second").exists() && !out.join(".second.partial-Xy12ab").exists());
    let rows = summary_rows(&out);
    let status: Vec<(&str, &str)> = rows[1..4]
        .iter()
        .map(|r| (r[0].as_str(), r[1].as_str()))
        .collect();
    assert_eq!(
        status,
        [("first", "ok"), ("second", "pending"), ("third", "ok")]
    );
    // the two options contradict each other
    let o = run(
        &["batch", ms, "-o", os, "--no-summary", "--summary-only"],
        &[],
    );
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
}

/// A `refine` writing into a scene's folder while `batch` works on that scene: its
/// temporary files (locked, fresh) are its own, and `batch` leaves them alone, as it
/// leaves another host's; only old, unlocked litter of this host is removed.
#[test]
fn batch_leaves_the_temporary_files_of_a_live_refine_in_the_scene_folder_alone() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    let out = dir.path().join("out");
    let s = out.join("first");
    std::fs::create_dir_all(&s).unwrap();
    // A live run's staged outputs, named as earlier versions and this one name them.
    let live = [".linegs-AbC123.obj", ".linegs-AbC124.json"];
    let held: Vec<std::fs::File> = live
        .iter()
        .map(|n| {
            std::fs::write(s.join(n), "new set").unwrap();
            let f = std::fs::File::open(s.join(n)).unwrap();
            f.try_lock().unwrap();
            f
        })
        .collect();
    // Old and unlocked: a killed run's on another host (kept), an earlier version's here
    // (removed).
    let elsewhere = ".linegs-some-other-node-4242-Xy12ab.obj";
    for n in [elsewhere, ".linegs-Old123.tmp"] {
        std::fs::write(s.join(n), "x").unwrap();
        make_old(&s.join(n));
    }
    let o = run(
        &[
            "batch",
            m.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--backend",
            "cpu",
        ],
        &[],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        names_in(&s),
        [live[0], live[1], elsewhere, "refined.obj", "report.json"]
    );
    for n in live {
        assert_eq!(std::fs::read_to_string(s.join(n)).unwrap(), "new set");
    }
    drop(held);
}

/// Sets a file's time back past the age at which litter is stale.
fn make_old(p: &Path) {
    let old = std::time::SystemTime::now() - linegs_gpu::io::STALE_AGE * 2;
    std::fs::File::options()
        .write(true)
        .open(p)
        .unwrap()
        .set_modified(old)
        .unwrap();
}

/// Every path `batch` writes is checked against every path it reads before any work: the
/// manifest named `summary.csv` in the output folder, a scene input that is a summary
/// table, one scene's output that is another's input. Exit 2, every input intact, no
/// scene run.
#[test]
fn batch_refuses_to_write_over_its_manifest_or_any_scenes_input() {
    let dir = tempfile::tempdir().unwrap();
    let m = scenes(dir.path());
    let d = dir.path().to_str().unwrap();
    let check = |manifest: &str, text: &str, extra: &[&str], needle: &str| {
        let p = dir.path().join(manifest);
        std::fs::write(&p, text).unwrap();
        let mut args = vec!["batch", p.to_str().unwrap(), "-o", d, "--backend", "cpu"];
        args.extend_from_slice(extra);
        let before: Vec<_> = ["s1/l.txt", "s2/l.txt", "summary.md", "first/refined.obj"]
            .iter()
            .map(|f| std::fs::read(dir.path().join(f)).ok())
            .collect();
        let o = run(&args, &[]);
        assert_eq!(o.status.code(), Some(2), "{manifest}: {}", stderr(&o));
        assert!(stderr(&o).contains(needle), "{manifest}: {}", stderr(&o));
        assert_eq!(std::fs::read_to_string(&p).unwrap(), text, "{manifest}");
        let after: Vec<_> = ["s1/l.txt", "s2/l.txt", "summary.md", "first/refined.obj"]
            .iter()
            .map(|f| std::fs::read(dir.path().join(f)).ok())
            .collect();
        assert_eq!(before, after, "{manifest}");
        assert!(!dir.path().join("first/report.json").exists(), "{manifest}");
        assert!(!dir.path().join("s1/report.json").exists(), "{manifest}");
    };
    let one = "name,gaussians,lines\ns1,s1/g.ply,s1/l.txt\n";
    check("summary.csv", one, &[], "is the manifest");
    check("summary.csv", one, &["--summary-only"], "is the manifest");
    std::fs::write(dir.path().join("summary.md"), "my notes").unwrap();
    check(
        "m.csv",
        "name,gaussians,lines\ns1,s1/g.ply,summary.md\n",
        &[],
        "the summary table summary.md is an input of scene `s1` (manifest line 2)",
    );
    std::fs::create_dir(dir.path().join("first")).unwrap();
    std::fs::copy(
        dir.path().join("s2/l.txt"),
        dir.path().join("first/refined.obj"),
    )
    .unwrap();
    check(
        "m.csv",
        "name,gaussians,lines\nfirst,s1/g.ply,s1/l.txt\nsecond,s2/g.ply,first/refined.obj\n",
        &[],
        "scene `first`'s refined.obj is an input of scene `second` (manifest line 3)",
    );
    drop(m);
}

/// A manifest is read in linear time: 10^5 scenes well within a few seconds (the
/// quadratic name check took over 100 s).
#[test]
fn a_manifest_of_a_hundred_thousand_scenes_is_read_in_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("m.csv");
    let mut text = String::from("name,gaussians,lines\n");
    for i in 0..100_000 {
        text.push_str(&format!("scene{i},g{i}.ply,l{i}.txt\n"));
    }
    std::fs::write(&p, text).unwrap();
    let t = std::time::Instant::now();
    let m = linegs_gpu::batch::Manifest::read(&p).unwrap();
    let secs = t.elapsed().as_secs_f64();
    assert_eq!(m.entries.len(), 100_000);
    assert_eq!(m.entries[99_999].name, "scene99999");
    assert!(secs < 5.0, "{secs} s");
    // The checks still see every earlier row: a late duplicate names the first.
    std::fs::write(
        &p,
        format!("{}scene7,g,l\n", std::fs::read_to_string(&p).unwrap()),
    )
    .unwrap();
    let e = linegs_gpu::batch::Manifest::read(&p)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("line 100002: scene name `scene7` is already used on line 9"),
        "{e}"
    );
}
