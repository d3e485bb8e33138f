use super::{engine, input_report, load, metrics_table, BackendArgs, InputArgs};
use anyhow::Result;
use clap::Args;
use linegs_gpu::eval::{self, gt, Metrics};
use linegs_gpu::index::{Grid, WorkingSet};
use linegs_gpu::io;
use linegs_gpu::refine::{EvalParams, Profile, RlMode};
use linegs_gpu::render;
use serde::Serialize;
use std::path::PathBuf;
use std::sync::Arc;

#[derive(Args, Debug)]
pub struct EvalArgs {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub engine: BackendArgs,
    #[command(flatten)]
    pub eval: EvalParams,
    /// Profile whose R_L convention applies when --r-l is not given (default: paper's
    /// equation; reference: the authors' ln N_box).
    #[arg(long, value_enum, default_value_t = Profile::Default)]
    pub profile: Profile,
    /// A second segment set measured beside the first (e.g. the refined lines), on the
    /// same working set (the box of the first set).
    #[arg(long, value_name = "FILE")]
    pub compare: Option<PathBuf>,
    /// The paper's radius sweep: metrics at each radius, e.g. 0.02,0.05,0.1,0.2.
    #[arg(long, value_name = "R,R,...", value_delimiter = ',', value_parser = linegs_gpu::refine::params::positive)]
    pub radii: Option<Vec<f64>>,
    /// Write the radius-sweep plot (needs --radii): `.png` or `.svg`.
    #[arg(long, value_name = "FILE", requires = "radii")]
    pub plot: Option<PathBuf>,
    /// Ground-truth edges (any line format) for the ABC-NEF metrics: accuracy,
    /// completeness, precision/recall/F at 0.005, 0.01, 0.02 (same frame as the lines).
    #[arg(long, value_name = "FILE")]
    pub gt: Option<PathBuf>,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

#[derive(Serialize)]
struct SetResult {
    lines: String,
    segments_read: usize,
    metrics: Vec<Metrics>,
    #[serde(skip_serializing_if = "Option::is_none")]
    gt: Option<gt::GtMetrics>,
}

#[derive(Serialize)]
struct EvalReport {
    tool: &'static str,
    version: &'static str,
    command: &'static str,
    backend: String,
    adapter: String,
    r_l_mode: RlMode,
    input: super::InputReport,
    sets: Vec<SetResult>,
    // Flattened first-set metrics at the first radius, for scripts that want the keys of
    // SPEC 7 at the top.
    e_rms_cm: Option<f64>,
    coverage_pct: Option<f64>,
    r_l: Option<f64>,
    score: Option<f64>,
    segments: usize,
    skipped: usize,
}

pub fn run(a: EvalArgs, verbose: bool) -> Result<()> {
    if let Some(p) = &a.plot {
        io::check_plot_output(p)?;
    }
    let loaded = load(&a.input)?;
    let mut sets = vec![(
        a.input.lines.display().to_string(),
        loaded.lines.lines.clone(),
    )];
    if let Some(c) = &a.compare {
        let f = io::read_lines(c)?;
        for w in &f.warnings {
            eprintln!("warning: {w}");
        }
        sets.push((c.display().to_string(), f.lines));
    }
    let gt_lines = match &a.gt {
        Some(p) => Some(io::read_lines(p)?.lines.segments),
        None => None,
    };
    let ws = WorkingSet::new(&loaded.cloud.centers, &loaded.lines.lines.segments);
    let radii = a.radii.clone().unwrap_or_else(|| vec![a.eval.eval_radius]);
    let min_r = radii.iter().copied().fold(f64::INFINITY, f64::min);
    let grid = Arc::new(Grid::build(&ws.points, ws.bounds, min_r));
    let eng = engine(a.engine.backend, grid, verbose)?;
    let rl = a.eval.r_l.unwrap_or(match a.profile {
        Profile::Default => RlMode::Paper,
        Profile::Reference => RlMode::Authors,
    });
    let mut results = Vec::new();
    for (name, lines) in &sets {
        let metrics = eval::sweep(eng.as_ref(), &lines.segments, &a.eval, rl, &radii)?;
        let gt_m = gt_lines
            .as_ref()
            .map(|g| gt::gt_metrics(&lines.segments, g, gt::STEP, &gt::THRESHOLDS));
        results.push(SetResult {
            lines: name.clone(),
            segments_read: lines.len(),
            metrics,
            gt: gt_m,
        });
    }
    if let Some(p) = &a.plot {
        let labels: Vec<String> = if results.len() == 2 {
            vec!["before".into(), "after".into()]
        } else {
            vec!["lines".into()]
        };
        let cols: Vec<SeriesCols> = results
            .iter()
            .map(|r| SeriesCols::new(&r.metrics))
            .collect();
        let series: Vec<render::SweepSeries> = cols
            .iter()
            .zip(&labels)
            .map(|(c, l)| c.series(l, &radii))
            .collect();
        let title = format!(
            "metrics against the evaluation radius ({} Gaussians)",
            ws.len()
        );
        let svg = p.extension().is_some_and(|e| e.eq_ignore_ascii_case("svg"));
        if svg {
            io::write_bytes_atomic(p, render::sweep_plot_svg(&series, &title).as_bytes())?;
        } else {
            render::sweep_plot_png(&series, &title, 1400, 900).write_png(p)?;
        }
        if !a.json {
            println!("wrote {}", p.display());
        }
    }
    let first = &results[0].metrics[0];
    if a.json {
        let report = EvalReport {
            tool: "linegs-gpu",
            version: env!("CARGO_PKG_VERSION"),
            command: "eval",
            backend: eng.backend().to_string(),
            adapter: eng.adapter(),
            r_l_mode: rl,
            input: input_report(&a.input, &loaded, ws.len()),
            e_rms_cm: first.e_rms_cm,
            coverage_pct: first.coverage_pct,
            r_l: first.r_l,
            score: first.score,
            segments: first.segments,
            skipped: first.skipped,
            sets: results,
        };
        println!("{}", serde_json::to_string_pretty(&report)?);
        return Ok(());
    }
    println!(
        "{} Gaussians read, {} in the working set; {} ({}); R_L: {:?}",
        loaded.cloud.centers.len(),
        ws.len(),
        eng.backend(),
        eng.adapter(),
        rl
    );
    for r in &results {
        println!("\n{} ({} segments)", r.lines, r.segments_read);
        let cols: Vec<(String, &Metrics)> = r
            .metrics
            .iter()
            .map(|m| (format!("r_e={}", m.radius), m))
            .collect();
        let refs: Vec<(&str, &Metrics)> = cols.iter().map(|(n, m)| (n.as_str(), *m)).collect();
        print!("{}", metrics_table(&refs));
        if let Some(g) = &r.gt {
            println!(
                "ground truth: accuracy {} completeness {} ({} / {} samples)",
                g.accuracy.map_or("-".into(), |x| format!("{x:.5}")),
                g.completeness.map_or("-".into(), |x| format!("{x:.5}")),
                g.predicted_samples,
                g.gt_samples
            );
            for s in &g.scores {
                println!(
                    "  @{:<6} precision {:.4} recall {:.4} F {:.4}",
                    s.threshold, s.precision, s.recall, s.f_score
                );
            }
        }
    }
    Ok(())
}

/// Metrics of one set split into columns for the plot.
pub struct SeriesCols {
    e: Vec<Option<f64>>,
    c: Vec<Option<f64>>,
    rl: Vec<Option<f64>>,
    s: Vec<Option<f64>>,
}

impl SeriesCols {
    pub fn new(m: &[Metrics]) -> Self {
        SeriesCols {
            e: m.iter().map(|x| x.e_rms_cm).collect(),
            c: m.iter().map(|x| x.coverage_pct).collect(),
            rl: m.iter().map(|x| x.r_l).collect(),
            s: m.iter().map(|x| x.score).collect(),
        }
    }

    pub fn series<'a>(&'a self, label: &'a str, radii: &'a [f64]) -> render::SweepSeries<'a> {
        render::SweepSeries {
            label,
            radii,
            e_rms_cm: &self.e,
            coverage_pct: &self.c,
            r_l: &self.rl,
            score: &self.s,
        }
    }
}
