use super::{load, metrics_table, print_engine, BackendArgs, InputArgs};
use anyhow::Result;
use clap::Args;
use linegs_gpu::eval::Metrics;
use linegs_gpu::io;
use linegs_gpu::pipeline::Job;
use linegs_gpu::refine::{EvalParams, Params, Profile};
use linegs_gpu::render;
use std::path::PathBuf;

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

pub fn run(a: EvalArgs, verbose: bool) -> Result<()> {
    let mut outs = super::outputs(&a.input);
    for p in a.compare.iter().chain(&a.gt) {
        outs.input(p);
    }
    if let Some(p) = &a.plot {
        outs.output("--plot", p, &["png", "svg"]);
    }
    outs.check()?;
    let scene = load(&a.input)?;
    let compare = match &a.compare {
        Some(c) => {
            let f = io::read_lines(c)?;
            for w in &f.warnings {
                eprintln!("warning: {w}");
            }
            Some(f.lines)
        }
        None => None,
    };
    let job = Job {
        params: Params {
            profile: a.profile,
            eval: a.eval.clone(),
            ..Params::default()
        },
        backend: a.engine.backend,
        sweep: a.radii.clone(),
        gt: match &a.gt {
            Some(p) => Some(io::read_lines(p)?.lines.segments),
            None => None,
        },
        check_frames: true,
    };
    let report = job.evaluate(&scene, compare.as_ref())?;
    // Loading printed the scene's own warnings; the report adds the frame check's.
    for w in report.warnings.iter().skip(scene.warnings.len()) {
        eprintln!("warning: {w}");
    }
    print_engine(&report, verbose);
    if let (Some(p), Some(sw)) = (&a.plot, &report.sweep) {
        let mut cols = vec![("lines", SeriesCols::new(&sw.before))];
        if let Some(after) = &sw.after {
            cols = vec![
                ("before", SeriesCols::new(&sw.before)),
                ("after", SeriesCols::new(after)),
            ];
        }
        let series: Vec<render::SweepSeries> =
            cols.iter().map(|(l, c)| c.series(l, &sw.radii)).collect();
        let title = format!(
            "metrics against the evaluation radius ({} Gaussians)",
            report.input.n_box
        );
        let svg = p.extension().is_some_and(|e| e.eq_ignore_ascii_case("svg"));
        let (w, h) = render::PLOT_SIZE;
        let doc = render::sweep_plot_svg(&series, &title, w, h);
        outs.write(p, |tmp| {
            if svg {
                io::write_bytes_atomic(tmp, doc.as_bytes())
            } else {
                render::svg_to_image(&doc)
                    .map_err(|e| io::Error::Output {
                        path: tmp.to_path_buf(),
                        msg: format!("cannot render the plot: {e}"),
                    })?
                    .write_png(tmp)
            }
        })?;
        outs.commit()?;
        if !a.json {
            println!("wrote {}", p.display());
        }
    }
    if a.json {
        println!("{}", report.to_json());
        return Ok(());
    }
    println!(
        "{} Gaussians read, {} in the working set; {} ({}); R_L: {:?}",
        report.input.gaussians_read,
        report.input.n_box,
        report.backend,
        report.adapter,
        report.fixes.r_l
    );
    let mut sets = vec![(a.input.lines.display().to_string(), &report.before)];
    if let (Some(c), Some(m)) = (&a.compare, &report.after) {
        sets.push((c.display().to_string(), m));
    }
    let sweeps = report
        .sweep
        .as_ref()
        .map(|sw| (&sw.before, sw.after.as_ref()));
    let gts = report
        .ground_truth
        .as_ref()
        .map(|g| (&g.before, g.after.as_ref()));
    for (i, (name, m)) in sets.iter().enumerate() {
        println!("\n{name} ({} segments)", m.segments + m.skipped);
        let sweep = sweeps.and_then(|(b, af)| if i == 0 { Some(b) } else { af });
        let metrics: Vec<&Metrics> = match sweep {
            Some(sw) => sw.iter().collect(),
            None => vec![*m],
        };
        let cols: Vec<(String, &Metrics)> = metrics
            .iter()
            .map(|m| (format!("r_e={}", m.radius), *m))
            .collect();
        let refs: Vec<(&str, &Metrics)> = cols.iter().map(|(n, m)| (n.as_str(), *m)).collect();
        print!("{}", metrics_table(&refs));
        let gt = gts.and_then(|(b, af)| if i == 0 { Some(b) } else { af });
        if let Some(g) = gt {
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
