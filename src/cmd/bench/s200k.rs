//! `bench --case s200k`: the whole `refine --report` process on the box scene of the
//! authors' s200k shape (`synth s200k`: 200,000 Gaussians, 318 segments with every defect
//! planted), written once, then run as a user runs it (a new process each time, start to
//! exit), median of several runs: what a user waits for, against the authors' 559 s.

use super::{BenchArgs, Cell, Row, Table};
use crate::cmd::input_error;
use crate::cmd::params::{chosen, BackendArg};
use anyhow::{Context, Result};
use linegs_gpu::engine::select::Backend;
use linegs_gpu::io;
use linegs_gpu::refine::Profile;
use linegs_gpu::synth;
use std::path::Path;
use std::process::Command;
use std::time::Instant;

/// The authors' code on their s200k scene on the 2-core machine, seconds.
pub const AUTHORS_SECONDS: f64 = 559.0;

/// Runs per row when `--repeat` is not given (the median of these).
const RUNS: usize = 7;

/// Median of `v` (the upper middle of an even count); NaN when empty.
fn median(v: &[f64]) -> f64 {
    let mut s = v.to_vec();
    s.sort_by(f64::total_cmp);
    s.get(s.len() / 2).copied().unwrap_or(f64::NAN)
}

/// The first number of /proc/loadavg (other work on the machine), where there is one.
fn load_average() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/loadavg").ok()?;
    s.split_whitespace().next()?.parse().ok()
}

/// One run of the whole process; its wall seconds and its report.
fn run_once(exe: &Path, args: &[String], report: &Path) -> Result<(f64, serde_json::Value)> {
    let t = Instant::now();
    let out = Command::new(exe)
        .args(args)
        .output()
        .with_context(|| format!("could not start {}", exe.display()))?;
    let seconds = t.elapsed().as_secs_f64();
    if !out.status.success() {
        anyhow::bail!(
            "bench --case s200k: `linegs-gpu {}` failed ({}): {}",
            args.join(" "),
            out.status,
            String::from_utf8_lossy(&out.stderr).trim()
        );
    }
    let text = std::fs::read_to_string(report)
        .with_context(|| format!("could not read {}", report.display()))?;
    Ok((seconds, serde_json::from_str(&text)?))
}

/// The seconds of stage `name` in a report.
fn stage_seconds(r: &serde_json::Value, name: &str) -> f64 {
    r["stages"]
        .as_array()
        .and_then(|v| v.iter().find(|s| s["name"] == name))
        .and_then(|s| s["seconds"].as_f64())
        .unwrap_or(f64::NAN)
}

pub fn run(a: &BenchArgs) -> Result<Table> {
    let backends = if a.backend.is_empty() {
        vec![BackendArg::Cpu]
    } else {
        a.backend.clone()
    };
    let runs = if a.repeat > 1 { a.repeat } else { RUNS };
    let profile: Profile = chosen(&a.profile);
    let exe = std::env::current_exe().context("bench --case s200k: where is this program?")?;
    let dir = tempfile::Builder::new()
        .prefix("linegs-bench-s200k")
        .tempdir()
        .map_err(|e| input_error(format!("bench --case s200k: no temporary folder: {e}")))?;
    let (ply, lines) = (dir.path().join("g.ply"), dir.path().join("l.obj"));
    let t = Instant::now();
    let scene = synth::s200k_scene(a.seed);
    io::write_gaussians_3dgs(&ply, &scene.gaussians, None)?;
    io::write_lines(&lines, &scene.lines.segments)?;
    let build_seconds = t.elapsed().as_secs_f64();
    let (n, m) = (scene.gaussians.len(), scene.lines.len());
    drop(scene);

    let profile_flag = if profile != Profile::default() {
        format!(" --profile {}", a.profile)
    } else {
        String::new()
    };
    let load_start = load_average();
    let mut table = Table {
        case: "s200k".into(),
        title: format!(
            "The authors' s200k shape: the box scene with planted defects ({n} Gaussians, {m} \
             segments), the whole refine --report process, median of {runs} runs"
        ),
        command: format!(
            "linegs-gpu bench --case s200k{}{}{}{profile_flag}",
            super::backend_flag(&backends),
            if a.seed != 7 {
                format!(" --seed {}", a.seed)
            } else {
                String::new()
            },
            if a.repeat > 1 {
                format!(" --repeat {}", a.repeat)
            } else {
                String::new()
            },
        ),
        columns: [
            "Gaussians",
            "segments",
            "engine",
            "median (s)",
            "fastest (s)",
            "slowest (s)",
            "x authors",
            "load (s)",
            "translate (s)",
            "segments out",
        ]
        .map(String::from)
        .to_vec(),
        rows: Vec::new(),
        notes: Vec::new(),
    };
    for &b in &backends {
        let engine = Backend::from(b).as_str();
        let report = dir.path().join("r.json");
        let args: Vec<String> = [
            "refine",
            "--backend",
            engine,
            "-g",
            &ply.to_string_lossy(),
            "-l",
            &lines.to_string_lossy(),
            "-o",
            &dir.path().join("out.obj").to_string_lossy(),
            "--report",
            &report.to_string_lossy(),
            "--profile",
            &a.profile,
        ]
        .map(String::from)
        .to_vec();
        let mut wall = Vec::with_capacity(runs);
        let (mut load, mut translate) = (Vec::new(), Vec::new());
        let mut out_segments = 0;
        for _ in 0..runs {
            let (s, r) = run_once(&exe, &args, &report)?;
            wall.push(s);
            load.push(stage_seconds(&r, "load"));
            translate.push(stage_seconds(&r, "translate"));
            out_segments = r["after"]["segments"].as_u64().unwrap_or(0);
        }
        let med = median(&wall);
        table.rows.push(Row {
            cells: vec![
                Cell::Count(n as u64),
                Cell::Count(m as u64),
                Cell::Text(engine.into()),
                Cell::Num(med, 3),
                Cell::Num(wall.iter().copied().fold(f64::INFINITY, f64::min), 3),
                Cell::Num(wall.iter().copied().fold(0.0, f64::max), 3),
                Cell::Num(AUTHORS_SECONDS / med, 0),
                Cell::Num(median(&load), 3),
                Cell::Num(median(&translate), 3),
                Cell::Count(out_segments),
            ],
            command: format!(
                "linegs-gpu synth s200k --seed {} -o g.ply --lines-out l.obj; linegs-gpu refine \
                 --backend {engine} -g g.ply -l l.obj -o out.obj --report r.json{profile_flag}",
                a.seed
            ),
        });
    }
    let fmt_load = |l: Option<f64>| l.map_or("unknown".to_string(), |x| format!("{x:.2}"));
    table.notes = vec![
        format!(
            "each run: a new process from start to exit (wall clock), as a user runs it; load \
             and translate: medians of the report's stages; x authors: the authors' code on \
             their s200k scene ({AUTHORS_SECONDS} s on a 2-core machine) over the median; \
             target 0.11 s (5,000x); scene written once in {build_seconds:.2} s"
        ),
        format!(
            "{} threads; load average {} at the start, {} at the end (other work on the \
             machine slows every run)",
            rayon::current_num_threads(),
            fmt_load(load_start),
            fmt_load(load_average())
        ),
    ];
    Ok(table)
}

#[cfg(test)]
mod tests {
    use super::median;

    #[test]
    fn the_median_is_the_middle_run() {
        assert_eq!(median(&[0.3, 0.1, 0.2]), 0.2);
        assert_eq!(median(&[0.4, 0.1, 0.3, 0.2]), 0.3);
        assert!(median(&[]).is_nan());
    }
}
