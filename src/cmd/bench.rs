use super::input_error;
use super::params::{choices, chosen, BackendArg};
use anyhow::Result;
use clap::Args;
use linegs_gpu::mem;
use linegs_gpu::pipeline::{Scene, Stage};
use linegs_gpu::refine::{Params, Profile};
use linegs_gpu::synth;
use serde::Serialize;
use std::time::Instant;

mod ladder;
mod s200k;

#[derive(Args, Debug)]
pub struct BenchArgs {
    /// Gaussian counts of the synthetic scenes (a comma list; every count is run with
    /// every segment count).
    #[arg(
        short = 'n',
        long,
        value_name = "N,N,...",
        value_delimiter = ',',
        default_value = "100000,1000000"
    )]
    pub num_gaussians: Vec<usize>,
    /// Segment counts of the synthetic scenes (a comma list).
    #[arg(
        long,
        value_name = "M,M,...",
        value_delimiter = ',',
        default_value = "1000,10000"
    )]
    pub num_segments: Vec<usize>,
    /// Engines to time (a comma list of `cpu`, `gpu`, `auto`), in one run so that their
    /// ratio is fair on a noisy machine. Default: `cpu,gpu` for the size grid; each case
    /// says its own (the ladder: `cpu`).
    #[arg(long, value_enum, value_delimiter = ',')]
    pub backend: Vec<BackendArg>,
    /// Named cases instead of the size grid (a comma list; each prints one table with the
    /// command of every row beside it).
    #[arg(long, value_name = "CASE,...", value_delimiter = ',', value_parser = case_names())]
    pub case: Vec<String>,
    /// The ladder's largest Gaussian count: its rows are 10^5, 10^6, ... up to this, each
    /// with a hundredth as many segments.
    #[arg(long, value_name = "N", default_value_t = 10_000_000)]
    pub max: usize,
    /// Refinement profile.
    #[arg(long, default_value_t = Profile::default().name().to_string(), value_parser = choices(Profile::CHOICES))]
    pub profile: String,
    /// Repetitions per case; the fastest total is kept. With 2 or more, an engine's kept
    /// run is not normally the process's first use of its memory, which the first engine
    /// in a process pays for alone (docs/benchmarks.md#host-share-of-the-gpu-engine).
    #[arg(long, default_value_t = 1)]
    pub repeat: usize,
    /// Seed of the synthetic scenes.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// The ladder: run every row in this process, one after another, instead of each in a
    /// process of its own (its row's command).
    #[arg(long)]
    pub in_process: bool,
    /// The ladder's child: measure the row of this many Gaussians in this process and
    /// print its numbers as one JSON line (what `--case ladder` reads from each row's
    /// process).
    #[arg(long, value_name = "N", hide = true)]
    pub ladder_row: Option<usize>,
    /// Print JSON.
    #[arg(long)]
    pub json: bool,
}

/// One named case: `linegs-gpu bench --case NAME` runs `run` and prints its table. A
/// case is one function in its own file (`src/cmd/bench/NAME.rs`) and one entry here.
struct Named {
    name: &'static str,
    /// The `--help` line.
    doc: &'static str,
    run: fn(&BenchArgs) -> Result<Table>,
}

const CASES: &[Named] = &[
    Named {
        name: "ladder",
        doc: "10^5 x 10^3 .. --max Gaussians (10x a row): seconds, peak memory, growth per row",
        run: ladder::run,
    },
    Named {
        name: "s200k",
        doc: "the authors' s200k shape (synth s200k): the whole refine --report process, median",
        run: s200k::run,
    },
];

fn case_names() -> clap::builder::PossibleValuesParser {
    clap::builder::PossibleValuesParser::new(
        CASES
            .iter()
            .map(|c| clap::builder::PossibleValue::new(c.name).help(c.doc)),
    )
}

/// What a case prints: a title, columns, and rows each with the command that measures
/// that row alone beside it; `--json` prints the same as an object.
#[derive(Serialize, Debug, Default)]
pub struct Table {
    /// The case's name (`--case NAME`).
    pub case: String,
    pub title: String,
    /// The command that prints the whole table.
    pub command: String,
    pub columns: Vec<String>,
    pub rows: Vec<Row>,
    /// Lines printed under the table (the machine, what a column means).
    pub notes: Vec<String>,
}

#[derive(Serialize, Debug)]
pub struct Row {
    pub cells: Vec<Cell>,
    /// The command that measures this row alone.
    pub command: String,
}

/// One value of a table: a number shown with `digits` decimals (JSON: the number), a
/// count, a text, or nothing (shown `-`, JSON `null`).
#[derive(Debug, Clone)]
pub enum Cell {
    Num(f64, usize),
    Count(u64),
    Text(String),
    None,
}

impl Serialize for Cell {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        match self {
            Cell::Num(x, _) if x.is_finite() => s.serialize_f64(*x),
            Cell::Count(n) => s.serialize_u64(*n),
            Cell::Text(t) => s.serialize_str(t),
            _ => s.serialize_none(),
        }
    }
}

impl std::fmt::Display for Cell {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Cell::Num(x, d) if x.is_finite() => write!(f, "{x:.d$}"),
            Cell::Count(n) => write!(f, "{n}"),
            Cell::Text(t) => f.write_str(t),
            _ => f.write_str("-"),
        }
    }
}

impl Table {
    /// The table as text: numbers right-aligned, the command last.
    pub fn render(&self) -> String {
        let text: Vec<Vec<String>> = self
            .rows
            .iter()
            .map(|r| r.cells.iter().map(|c| c.to_string()).collect())
            .collect();
        let width = |i: usize| {
            text.iter()
                .filter_map(|r| r.get(i))
                .map(|c| c.chars().count())
                .chain([self.columns[i].chars().count()])
                .max()
                .unwrap_or(0)
        };
        let widths: Vec<usize> = (0..self.columns.len()).map(width).collect();
        let mut out = format!("\n{}\n", self.title);
        let line = |cells: &[String], command: &str| {
            let mut l = String::new();
            for (c, w) in cells.iter().zip(&widths) {
                l += &format!("{c:>w$}  ");
            }
            l += command;
            l.trim_end().to_string() + "\n"
        };
        out += &line(&self.columns, "command");
        for (r, t) in self.rows.iter().zip(&text) {
            out += &line(t, &r.command);
        }
        for n in &self.notes {
            out += n;
            out += "\n";
        }
        out += &format!("(all rows: {})\n", self.command);
        out
    }
}

#[derive(Serialize)]
struct Case {
    gaussians: usize,
    segments: usize,
    /// Seconds the scene took to build (the first engine's; each builds it for itself).
    synth_seconds: f64,
    runs: Vec<RunTiming>,
    /// GPU total / CPU total, when both ran.
    gpu_over_cpu: Option<f64>,
    /// The GPU run's host seconds against the CPU run's whole time, per stage, when both
    /// ran: what bounds `--backend gpu` on any device.
    #[serde(skip_serializing_if = "Option::is_none")]
    host_share: Option<HostShare>,
}

/// The GPU run's host seconds (all of them, and per stage) as a share of the CPU run's
/// total seconds, with the device's work per stage.
#[derive(Serialize)]
struct HostShare {
    cpu_total_seconds: f64,
    gpu_host_seconds: f64,
    /// `gpu_host_seconds / cpu_total_seconds`.
    share: f64,
    /// The GPU run's index and engine stages together (the grid and the upload; the
    /// device opened while the scene was built) and the CPU run's index stage.
    gpu_setup_seconds: f64,
    cpu_index_seconds: f64,
    stages: Vec<StageShare>,
}

#[derive(Serialize)]
struct StageShare {
    name: String,
    /// The CPU run's seconds in the stage of the same name.
    cpu_seconds: f64,
    host_seconds: f64,
    device_seconds: f64,
    /// The GPU run's stage seconds outside its engine's batches (neither `host_seconds`
    /// nor `device_seconds`): the stage's own host work, which the CPU run does too (the
    /// decision rule's weighing, the clustering, merge/join's decisions).
    outside_seconds: f64,
    /// `host_seconds / cpu_total_seconds`.
    share: f64,
    device_items: u64,
    point_bytes: u64,
    host_lists: u64,
}

impl HostShare {
    /// `None` unless both a CPU and a GPU run (with host clocks) are there.
    fn of(runs: &[RunTiming]) -> Option<HostShare> {
        let cpu_run = runs.iter().find(|r| r.backend == "cpu")?;
        let cpu = cpu_run.total_seconds;
        let gpu = runs.iter().find(|r| r.backend == "gpu")?;
        let seconds = |r: &RunTiming, name: &str| {
            r.stages
                .iter()
                .filter(|s| s.name == name)
                .map(|s| s.seconds)
                .sum::<f64>()
        };
        let host = gpu.host_seconds?;
        if cpu <= 0.0 {
            return None;
        }
        let stages = gpu
            .stages
            .iter()
            .filter_map(|s| {
                Some(StageShare {
                    name: s.name.clone(),
                    cpu_seconds: seconds(cpu_run, &s.name),
                    host_seconds: s.host_seconds?,
                    device_seconds: s.device_seconds.unwrap_or(0.0),
                    outside_seconds: (s.seconds
                        - s.host_seconds?
                        - s.device_seconds.unwrap_or(0.0))
                    .max(0.0),
                    share: s.host_seconds? / cpu,
                    device_items: s.device_items.unwrap_or(0),
                    point_bytes: s.point_bytes.unwrap_or(0),
                    host_lists: s.host_lists.unwrap_or(0),
                })
            })
            .collect();
        Some(HostShare {
            cpu_total_seconds: cpu,
            gpu_host_seconds: host,
            share: host / cpu,
            gpu_setup_seconds: seconds(gpu, "index") + seconds(gpu, "engine"),
            cpu_index_seconds: seconds(cpu_run, "index"),
            stages,
        })
    }
}

#[derive(Serialize)]
struct RunTiming {
    backend: String,
    adapter: String,
    n_box: usize,
    segments_out: usize,
    stages: Vec<Stage>,
    total_seconds: f64,
    /// GPU engine: host and device-wait seconds of its batches over the run.
    #[serde(skip_serializing_if = "Option::is_none")]
    host_seconds: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    device_seconds: Option<f64>,
    /// Batches and queries the engine answered (GPU engine: how many small batches went
    /// to the host).
    engine_counters: Option<linegs_gpu::engine::Counters>,
    peak_rss_mb: Option<f64>,
    /// GPU and auto: seconds the device's opening took (adapter, device, kernels,
    /// warm-up), on its own thread while the scene was built, so not in the run's stages,
    /// and how long the bench still waited for it after the build (what a `refine`
    /// whose files read faster than the opening would see in its engine stage).
    #[serde(skip_serializing_if = "Option::is_none")]
    device_open_seconds: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    device_open_wait_seconds: Option<f64>,
}

pub fn run(a: BenchArgs, verbose: bool) -> Result<()> {
    if let Some(n) = a.ladder_row {
        return ladder::child(&a, n);
    }
    if !a.case.is_empty() {
        return run_cases(&a);
    }
    sizes(a, verbose)
}

/// The named cases, one table each, printed as each ends (`--json`: one object at the end).
fn run_cases(a: &BenchArgs) -> Result<()> {
    if a.repeat == 0 {
        return Err(input_error("bench needs --repeat >= 1"));
    }
    let mut tables = Vec::new();
    for name in &a.case {
        let case = CASES
            .iter()
            .find(|c| c.name == name)
            .unwrap_or_else(|| unreachable!("the parser accepts only the names in CASES"));
        let t = (case.run)(a)?;
        if !a.json {
            print!("{}", t.render());
        }
        tables.push(t);
    }
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "tool": "linegs-gpu",
                "command": "bench",
                "threads": rayon::current_num_threads(),
                "tables": tables,
            }))?
        );
    }
    Ok(())
}

/// Every `-n` with every `--num-segments`, per engine, stage by stage.
fn sizes(a: BenchArgs, _verbose: bool) -> Result<()> {
    let backends = if a.backend.is_empty() {
        vec![BackendArg::Cpu, BackendArg::Gpu]
    } else {
        a.backend.clone()
    };
    if a.num_gaussians.is_empty() || a.num_segments.is_empty() || a.repeat == 0 {
        return Err(input_error(
            "bench needs at least one size and --repeat >= 1",
        ));
    }
    let params = Params {
        profile: chosen(&a.profile),
        ..Params::default()
    };
    let mut cases = Vec::new();
    for &n in &a.num_gaussians {
        for &m in &a.num_segments {
            let mut runs = Vec::new();
            let mut synth_seconds = None;
            for &b in &backends {
                let job = super::env::job(params.clone(), b.into())?;
                // Each backend builds the scene for itself (the same scene: the seed
                // decides it), with nothing of another backend's left in the process. A
                // GPU run's device opens while its scene is built, as `refine` opens it
                // while it reads the files, and serves every repeat, as `batch` and the
                // Python module keep theirs; it is waited for before the first timed run.
                let mut device = job.open();
                let t = Instant::now();
                let synth = synth::scaled_scene(n, m, a.seed);
                let scene = Scene::from_arrays(synth.gaussians, synth.lines)?;
                synth_seconds.get_or_insert(t.elapsed().as_secs_f64());
                let opened = device.wait();
                let mut best: Option<RunTiming> = None;
                for _ in 0..a.repeat {
                    mem::reset_peak_rss();
                    let out = job.refine_on(&scene, &mut device, |_| {})?;
                    let r = out.report;
                    let sum = |f: fn(&Stage) -> Option<f64>| {
                        r.stages.iter().filter_map(f).reduce(|a, b| a + b)
                    };
                    let host_seconds = sum(|s| s.host_seconds);
                    let device_seconds = sum(|s| s.device_seconds);
                    // `auto` without a hardware adapter ran the CPU engine: nothing opened.
                    let opened = opened.filter(|_| r.backend != "cpu");
                    let run = RunTiming {
                        host_seconds,
                        device_seconds,
                        engine_counters: r.engine_counters,
                        backend: r.backend,
                        adapter: r.adapter,
                        n_box: r.input.n_box,
                        segments_out: out.lines.len(),
                        stages: r.stages,
                        total_seconds: r.total_seconds,
                        peak_rss_mb: mem::peak_rss_bytes().map(|b| b as f64 / 1048576.0),
                        device_open_seconds: opened.map(|o| o.0),
                        device_open_wait_seconds: opened.map(|o| o.1),
                    };
                    if best
                        .as_ref()
                        .is_none_or(|x| run.total_seconds < x.total_seconds)
                    {
                        best = Some(run);
                    }
                }
                runs.push(best.expect("repeat >= 1"));
            }
            let tot = |name: &str| {
                runs.iter()
                    .find(|r| r.backend == name)
                    .map(|r| r.total_seconds)
            };
            let gpu_over_cpu = match (tot("gpu"), tot("cpu")) {
                (Some(g), Some(c)) if c > 0.0 => Some(g / c),
                _ => None,
            };
            let case = Case {
                gaussians: n,
                segments: m,
                synth_seconds: synth_seconds.unwrap_or(0.0),
                host_share: HostShare::of(&runs),
                runs,
                gpu_over_cpu,
            };
            if !a.json {
                print_case(&case);
            }
            cases.push(case);
        }
    }
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "tool": "linegs-gpu",
                "command": "bench",
                "threads": rayon::current_num_threads(),
                "profile": params.profile,
                "cases": cases,
            }))?
        );
    }
    Ok(())
}

fn print_case(c: &Case) {
    println!(
        "\n{} Gaussians x {} segments (synthetic scene built in {:.2} s for each engine, not timed below)",
        c.gaussians, c.segments, c.synth_seconds
    );
    print!("{:<18}", "stage (s)");
    for r in &c.runs {
        print!("{:>12}", r.backend);
    }
    println!();
    if let Some(first) = c.runs.first() {
        for (i, s) in first.stages.iter().enumerate() {
            print!("{:<18}", s.name);
            for r in &c.runs {
                print!("{:>12.3}", r.stages.get(i).map_or(f64::NAN, |x| x.seconds));
            }
            println!();
        }
    }
    print!("{:<18}", "total");
    for r in &c.runs {
        print!("{:>12.3}", r.total_seconds);
    }
    println!();
    print!("{:<18}", "peak RSS (MB)");
    for r in &c.runs {
        print!("{:>12.0}", r.peak_rss_mb.unwrap_or(f64::NAN));
    }
    println!();
    print!("{:<18}", "segments out");
    for r in &c.runs {
        print!("{:>12}", r.segments_out);
    }
    println!();
    for r in &c.runs {
        println!("  {}: {} (N_box {})", r.backend, r.adapter, r.n_box);
        if let (Some(o), Some(w)) = (r.device_open_seconds, r.device_open_wait_seconds) {
            println!(
                "  {}: device opened in {o:.3} s while the scene was built (not in the stages; {w:.3} s of it after the build)",
                r.backend
            );
        }
        if let (Some(h), Some(d)) = (r.host_seconds, r.device_seconds) {
            println!(
                "  {}: host {h:.3} s, waiting for the device {d:.3} s",
                r.backend
            );
        }
        if let Some(c) = r.engine_counters.filter(|c| c.cpu_batches > 0) {
            println!(
                "  {}: {} of {} batches ({} queries) answered on the host (batches under the device's size, and member lists where the host reads them)",
                r.backend, c.cpu_batches, c.batches, c.cpu_queries
            );
        }
        if let Some(c) = r.engine_counters.filter(|c| c.device_fits > 0) {
            println!(
                "  {}: {} edge-fit steps fitted on the device (f64), {} of those sent there refitted on the host",
                r.backend, c.device_fits, c.device_fits_refitted
            );
        }
    }
    if let Some(x) = c.gpu_over_cpu {
        println!("gpu / cpu total time: {x:.2}");
    }
    if let Some(h) = &c.host_share {
        print_host_share(h);
    }
}

/// The GPU run's host seconds per stage beside the CPU run's seconds in the same stage
/// and its total, and the device's work.
fn print_host_share(h: &HostShare) {
    println!(
        "gpu host share (the gpu run's host seconds / the cpu run's total {:.3} s):",
        h.cpu_total_seconds
    );
    println!(
        "{:<18}{:>10}{:>10}{:>10}{:>12}{:>8}{:>12}{:>12}{:>12}",
        "stage",
        "cpu (s)",
        "host (s)",
        "dev (s)",
        "outside (s)",
        "share",
        "items",
        "MB read",
        "host lists"
    );
    for s in &h.stages {
        println!(
            "{:<18}{:>10.3}{:>10.3}{:>10.3}{:>12.3}{:>7.1}%{:>12}{:>12.1}{:>12}",
            s.name,
            s.cpu_seconds,
            s.host_seconds,
            s.device_seconds,
            s.outside_seconds,
            100.0 * s.share,
            s.device_items,
            s.point_bytes as f64 / 1e6,
            s.host_lists
        );
    }
    println!(
        "{:<18}{:>10.3}{:>10.3}{:>10}{:>12}{:>7.1}%",
        "total",
        h.cpu_total_seconds,
        h.gpu_host_seconds,
        "",
        "",
        100.0 * h.share
    );
    println!(
        "gpu index + engine {:.3} s (the grid, the upload; the device opened before); cpu index {:.3} s",
        h.gpu_setup_seconds, h.cpu_index_seconds
    );
}

/// The `--backend` option that reproduces `backends` in a printed command (none for the
/// CPU engine alone, the cases' default).
fn backend_flag(backends: &[BackendArg]) -> String {
    if backends == [BackendArg::Cpu] {
        String::new()
    } else {
        let names: Vec<&str> = backends
            .iter()
            .map(|&b| linegs_gpu::engine::select::Backend::from(b).as_str())
            .collect();
        format!(" --backend {}", names.join(","))
    }
}
