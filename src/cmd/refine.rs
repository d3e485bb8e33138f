use super::params::{BackendArg, ParamsArgs};
use super::{load, metrics_table, print_engine, BackendArgs, InputArgs};
use anyhow::Result;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use linegs_gpu::pipeline::{Job, Outputs, RunError};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct RefineArgs {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub engine: BackendArgs,
    /// Where to write the refined segments; the format follows the extension: `.obj`,
    /// `.stl`, `.ply` (with an edge element), `.txt` (6 numbers a row), `.npy`.
    #[arg(short, long, value_name = "FILE")]
    pub output: PathBuf,
    /// Write the JSON report (backend, adapter, parameters, inputs, stages, before/after);
    /// a `.json` file.
    #[arg(long, value_name = "JSON")]
    pub report: Option<PathBuf>,
    /// Also write a PLY with the input (red) and refined (blue) segments as coloured edges.
    #[arg(long, value_name = "PLY")]
    pub compare_ply: Option<PathBuf>,
    /// Refine even when (almost) no segment has a Gaussian center within r, which
    /// otherwise stops the run (lines and model in different frames or units).
    #[arg(long)]
    pub no_frame_check: bool,
    #[command(flatten)]
    pub params: ParamsArgs,
}

pub fn run(a: RefineArgs, verbose: bool) -> Result<()> {
    let outputs = Outputs {
        lines: a.output.clone(),
        report: a.report.clone(),
        compare_ply: a.compare_ply.clone(),
    };
    outputs.check(&a.input.paths())?;
    let scene = load(&a.input)?;
    let bar = ProgressBar::new_spinner();
    if let Ok(style) = ProgressStyle::with_template("{spinner} {elapsed} {msg}") {
        bar.set_style(style);
    }
    bar.enable_steady_tick(std::time::Duration::from_millis(120));
    bar.set_message("indexing the Gaussians");
    crate::oom::doing(
        format!(
            "refining {} segments against {} Gaussians",
            scene.lines.len(),
            scene.gaussians.len()
        ),
        if a.engine.backend == BackendArg::Cpu {
            "free memory or raise the limit (ulimit -v)"
        } else {
            "free memory, raise the limit (ulimit -v), or try --backend cpu"
        },
    );
    let job = Job {
        check_frames: !a.no_frame_check,
        ..super::env::job(a.params.into(), a.engine.backend.into())?
    };
    let refined = job.refine(&scene, |s| {
        bar.set_message(format!("{} done: {} segments", s.name, s.segments));
        if verbose {
            bar.println(format!(
                "{:<18} {:>8} segments {:>9.3} s",
                s.name, s.segments, s.seconds
            ));
        }
    });
    bar.finish_and_clear();
    let mut out = refined.map_err(|e| match e {
        RunError::FrameMismatch(m) => RunError::FrameMismatch(format!(
            "{m} (--no-frame-check refines anyway); nothing was written"
        )),
        e => e,
    })?;
    print_engine(&out.report, verbose);
    outputs.write(&scene.lines, &mut out)?;
    let r = &out.report;
    println!(
        "{} -> {} segments, r = {}, {} Gaussians in the working set, {} ({})",
        scene.lines.len(),
        out.lines.len(),
        r.radius,
        r.input.n_box,
        r.backend,
        r.adapter
    );
    if let Some(after) = &r.after {
        print!(
            "{}",
            metrics_table(&[("before", &r.before), ("after", after)])
        );
    }
    // The report's warnings: the frame check's, the steps', the scale cut's; loading
    // printed the scene's own, which the report starts with.
    for w in r.warnings.iter().skip(scene.warnings.len()) {
        eprintln!("warning: {w}");
    }
    if let Some(steps) = &r.refine {
        if let Some(sh) = &steps.shifts {
            println!(
                "step 4 (--fit {}) moved {} of {} segments: median {:.3} r, 90th percentile {:.3} r",
                steps.fit.name(),
                sh.moved,
                scene.lines.len(),
                sh.median_r,
                sh.p90_r
            );
        }
    }
    println!("wrote {} in {:.2} s", a.output.display(), r.total_seconds);
    if let Some(rp) = &a.report {
        println!("wrote {}", rp.display());
    }
    Ok(())
}
