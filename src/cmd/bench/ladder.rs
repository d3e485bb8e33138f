//! `bench --case ladder`: the synthetic scene at 10^5 x 10^3, 10^6 x 10^4, ... up to `--max`
//! Gaussians (a hundredth as many segments), one row per size and engine, with the growth
//! of time and peak memory against the row 10x smaller: how the run scales.

use super::{BenchArgs, Cell, Row, Table};
use crate::cmd::input_error;
use crate::cmd::params::{chosen, BackendArg};
use anyhow::Result;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::mem;
use linegs_gpu::pipeline::Scene;
use linegs_gpu::refine::{Params, Profile};
use linegs_gpu::synth;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// The smallest row.
const FIRST: usize = 100_000;
/// Gaussians per segment in every row.
const PER_SEGMENT: usize = 100;

/// The rows' sizes: `FIRST`, 10x, ... while at most `max`.
pub fn sizes(max: usize) -> Vec<(usize, usize)> {
    std::iter::successors(Some(FIRST), |&n| n.checked_mul(10))
        .take_while(|&n| n <= max)
        .map(|n| (n, n / PER_SEGMENT))
        .collect()
}

pub fn run(a: &BenchArgs) -> Result<Table> {
    let sizes = sizes(a.max);
    if sizes.is_empty() {
        return Err(input_error(format!(
            "bench --case ladder: --max {} is below the first row ({FIRST} Gaussians)",
            a.max
        )));
    }
    let backends = backends_of(a);
    let params = params_of(a);
    // The options beside the sizes and the engine, as the rows' commands repeat them.
    let mut flags = String::new();
    if params.profile != Profile::default() {
        flags += &format!(" --profile {}", a.profile);
    }
    if a.seed != 7 {
        flags += &format!(" --seed {}", a.seed);
    }
    if a.repeat > 1 {
        flags += &format!(" --repeat {}", a.repeat);
    }
    let mut table = Table {
        case: "ladder".into(),
        title: format!(
            "Scale ladder: the synthetic scene from {FIRST} Gaussians to {} (10x a row, a \
             hundredth as many segments), {} threads",
            sizes.last().map_or(0, |s| s.0),
            rayon::current_num_threads()
        ),
        command: format!(
            "linegs-gpu bench --case ladder --max {}{}{flags}{}",
            a.max,
            super::backend_flag(&backends),
            if a.in_process { " --in-process" } else { "" }
        ),
        columns: [
            "Gaussians",
            "segments",
            "engine",
            "build (s)",
            "refine (s)",
            "x time",
            "cpu (s)",
            "x cpu",
            "peak (MB)",
            "x memory",
            "slowest stage (s)",
            "segments out",
        ]
        .map(String::from)
        .to_vec(),
        rows: Vec::new(),
        notes: vec![
            "build: making the synthetic scene (not in refine); refine: the whole refinement, \
             the fastest of --repeat; cpu: the process's CPU seconds in it (user and system, \
             all threads: less sensitive than wall time to other programs on the machine); peak: the process's resident peak over building and \
             refining the row; x: against the row 10x smaller"
                .into(),
            if a.in_process {
                "every row in this process, one after another (--in-process)".into()
            } else {
                "every row in a process of its own, as its command runs it".into()
            },
        ],
    };
    // Per engine, the previous row.
    let mut previous: Vec<Option<Measured>> = vec![None; backends.len()];
    for (n, m) in sizes {
        let row = if a.in_process {
            measure(a, &params, &backends, n, m)?
        } else {
            in_own_process(a, n)?
        };
        for ((k, &b), now) in backends.iter().enumerate().zip(row.engines) {
            let growth = |now: Option<f64>, before: Option<f64>| match (now, before) {
                (Some(x), Some(y)) if y > 0.0 => Cell::Num(x / y, 2),
                _ => Cell::None,
            };
            let before = previous[k].as_ref();
            table.rows.push(Row {
                cells: vec![
                    Cell::Count(n as u64),
                    Cell::Count(m as u64),
                    Cell::Text(Backend::from(b).as_str().into()),
                    Cell::Num(row.build_seconds, 2),
                    Cell::Num(now.seconds, 2),
                    growth(Some(now.seconds), before.map(|p| p.seconds)),
                    now.cpu.map_or(Cell::None, |c| Cell::Num(c, 2)),
                    growth(now.cpu, before.and_then(|p| p.cpu)),
                    now.peak.map_or(Cell::None, |p| Cell::Num(p, 0)),
                    growth(now.peak, before.and_then(|p| p.peak)),
                    Cell::Text(now.slowest.clone()),
                    Cell::Count(now.out as u64),
                ],
                command: format!(
                    "linegs-gpu bench -n {n} --num-segments {m} --backend {}{flags}",
                    Backend::from(b).as_str(),
                ),
            });
            previous[k] = Some(now);
        }
    }
    Ok(table)
}

/// The engines of the rows (`--backend`, or the CPU engine).
fn backends_of(a: &BenchArgs) -> Vec<BackendArg> {
    if a.backend.is_empty() {
        vec![BackendArg::Cpu]
    } else {
        a.backend.clone()
    }
}

fn params_of(a: &BenchArgs) -> Params {
    Params {
        profile: chosen(&a.profile),
        ..Params::default()
    }
}

/// One row: the scene's build and each engine's fastest refinement of it.
#[derive(Serialize, Deserialize)]
struct RowMeasured {
    build_seconds: f64,
    /// In the order of `--backend`.
    engines: Vec<Measured>,
}

/// The row of `n` Gaussians measured in a process of its own: this program run as the
/// row's child (`bench --ladder-row n` with the same options), which prints the row's
/// numbers as one JSON line. Each row then starts as its command does, on a fresh heap:
/// in one process a row inherits the pages the allocator kept from the rows before it,
/// which speeds the 10^7 row more than the 10^8 one (docs/benchmarks.md, "Scale").
fn in_own_process(a: &BenchArgs, n: usize) -> Result<RowMeasured> {
    let exe = std::env::current_exe()
        .map_err(|e| anyhow::anyhow!("bench --case ladder: this program's path: {e}"))?;
    let mut cmd = std::process::Command::new(exe);
    cmd.args(["bench", "--ladder-row", &n.to_string()])
        .args(["--profile", &a.profile])
        .args(["--seed", &a.seed.to_string()])
        .args(["--repeat", &a.repeat.to_string()])
        .stdin(std::process::Stdio::null())
        .stderr(std::process::Stdio::inherit());
    let names: Vec<&str> = backends_of(a)
        .iter()
        .map(|&b| Backend::from(b).as_str())
        .collect();
    cmd.args(["--backend", &names.join(",")]);
    let out = cmd
        .output()
        .map_err(|e| anyhow::anyhow!("bench --case ladder: starting the row of {n}: {e}"))?;
    if !out.status.success() {
        anyhow::bail!(
            "bench --case ladder: the row of {n} Gaussians ended with {} (its messages above)",
            out.status
        );
    }
    serde_json::from_slice(&out.stdout).map_err(|e| {
        anyhow::anyhow!("bench --case ladder: the row of {n} Gaussians printed no numbers: {e}")
    })
}

/// `bench --ladder-row n`: the row of `n` Gaussians in this process, printed as one JSON
/// line for the ladder that started it.
pub fn child(a: &BenchArgs, n: usize) -> Result<()> {
    if a.repeat == 0 {
        return Err(input_error("bench needs --repeat >= 1"));
    }
    let row = measure(a, &params_of(a), &backends_of(a), n, n / PER_SEGMENT)?;
    println!("{}", serde_json::to_string(&row)?);
    Ok(())
}

/// The row of `n` Gaussians and `m` segments in this process: the scene built, then each
/// engine's fastest of `--repeat` refinements.
fn measure(
    a: &BenchArgs,
    params: &Params,
    backends: &[BackendArg],
    n: usize,
    m: usize,
) -> Result<RowMeasured> {
    mem::reset_peak_rss();
    let t = Instant::now();
    let scene = {
        let s = synth::scaled_scene(n, m, a.seed);
        Scene::from_arrays(s.gaussians, s.lines)?
    };
    let build_seconds = t.elapsed().as_secs_f64();
    let build_peak = peak_mb();
    let mut engines = Vec::with_capacity(backends.len());
    for &b in backends {
        let job = crate::cmd::env::job(params.clone(), b.into())?;
        let mut best: Option<Measured> = None;
        for _ in 0..a.repeat {
            mem::reset_peak_rss();
            let cpu0 = cpu_seconds();
            let out = job.refine(&scene, |_| {})?;
            let cpu = cpu_seconds().zip(cpu0).map(|(b, a)| b - a);
            let r = out.report;
            let peak = match (peak_mb(), build_peak) {
                (Some(x), Some(y)) => Some(x.max(y)),
                (x, y) => x.or(y),
            };
            let slowest = r
                .stages
                .iter()
                .max_by(|x, y| x.seconds.total_cmp(&y.seconds))
                .map_or(String::new(), |s| format!("{} {:.2}", s.name, s.seconds));
            if best.as_ref().is_none_or(|x| r.total_seconds < x.seconds) {
                best = Some(Measured {
                    seconds: r.total_seconds,
                    cpu,
                    peak,
                    slowest,
                    out: out.lines.len(),
                });
            }
        }
        engines.push(best.expect("repeat >= 1"));
    }
    Ok(RowMeasured {
        build_seconds,
        engines,
    })
}

/// One row's numbers (the fastest of `--repeat`).
#[derive(Clone, Serialize, Deserialize)]
struct Measured {
    /// The refinement's wall seconds and CPU seconds.
    seconds: f64,
    cpu: Option<f64>,
    /// MB, over building the scene and refining it.
    peak: Option<f64>,
    /// The slowest stage and its seconds.
    slowest: String,
    /// Segments out.
    out: usize,
}

/// The process's CPU seconds so far (user and system, all threads); `None` off Unix.
fn cpu_seconds() -> Option<f64> {
    #[cfg(unix)]
    {
        // SAFETY: `rusage` is plain integers (all zeros is a valid value), and getrusage
        // writes only the struct it is given.
        let mut u: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut u) } != 0 {
            return None;
        }
        let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 * 1e-6;
        Some(s(u.ru_utime) + s(u.ru_stime))
    }
    #[cfg(not(unix))]
    None
}

fn peak_mb() -> Option<f64> {
    mem::peak_rss_bytes().map(|b| b as f64 / 1048576.0)
}

#[cfg(test)]
mod tests {
    use super::sizes;

    #[test]
    fn the_rows_go_10x_up_to_max() {
        assert_eq!(sizes(99_999), vec![]);
        assert_eq!(sizes(100_000), vec![(100_000, 1_000)]);
        assert_eq!(
            sizes(50_000_000),
            vec![(100_000, 1_000), (1_000_000, 10_000), (10_000_000, 100_000)]
        );
        assert_eq!(sizes(usize::MAX).len(), 15);
    }
}
