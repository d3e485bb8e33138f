use super::params::{BackendArg, ParamsArgs};
use super::{
    input_error, load_framed, metrics_table, print_engine, BackendArgs, FormatArg, InputArgs,
};
use anyhow::Result;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use linegs_gpu::pipeline::{Job, LinesOut, Outputs, RunError};

use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct RefineArgs {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub engine: BackendArgs,
    // The writers come from the format registry (io::LINE_WRITERS).
    #[arg(short, long, value_name = "FILE", help = format!(
        "Where to write the refined segments; the format follows the extension: {}",
        linegs_gpu::io::line_output_words(true)
    ))]
    pub output: PathBuf,
    /// Write the JSON report (backend, adapter, parameters, inputs, stages, before/after);
    /// a `.json` file.
    #[arg(long, value_name = "JSON")]
    pub report: Option<PathBuf>,
    /// Also write a PLY with the input (red) and refined (blue) segments as coloured edges.
    #[arg(long, value_name = "PLY")]
    pub compare_ply: Option<PathBuf>,
    /// How -o is written: `auto` by its extension; `limap`: LIMAP `finaltracks/` (-o is a
    /// new or empty folder; one `track_<k>.txt` per segment whose supports are those of
    /// the input tracks it came from); `emap`: EMAP/EdgeGaussians `parametric_edges.json`
    /// (-o that file, or a folder to hold it).
    #[arg(long, value_enum, default_value_t = FormatArg::Auto)]
    pub format: FormatArg,
    /// Write each output segment's sources (0-based indices of the input segments, in
    /// file order, it came from), in output order: a `.json` file.
    #[arg(long, value_name = "JSON")]
    pub provenance: Option<PathBuf>,
    /// Refine even when (almost) no segment has a Gaussian center within r, which
    /// otherwise stops the run (lines and model in different frames or units).
    #[arg(long)]
    pub no_frame_check: bool,
    /// Print the edge fit's decision for input segment N (0-based): the estimates it
    /// weighed, how well the Gaussians know each, and the verdict (every segment's is in
    /// the report's `refine.fit_decisions`).
    #[arg(long, value_name = "N")]
    pub explain: Option<usize>,
    #[command(flatten)]
    pub params: ParamsArgs,
}

pub fn run(a: RefineArgs, verbose: bool) -> Result<()> {
    let outputs = Outputs {
        lines: a.output.clone(),
        report: a.report.clone(),
        compare_ply: a.compare_ply.clone(),
        format: match a.format {
            FormatArg::Limap => LinesOut::Limap,
            FormatArg::Emap => LinesOut::Emap,
            FormatArg::Auto => LinesOut::ByExtension,
            f => {
                // A segment file's format is its extension: `--format` only confirms it.
                let ext = f.extension().unwrap_or_default();
                let has = a.output.extension().and_then(|e| e.to_str());
                if !has.is_some_and(|e| e.eq_ignore_ascii_case(ext)) {
                    return Err(input_error(format!(
                        "--format {ext}: -o {} has another extension; a segment file's format \
                         is its extension (`--format auto`)",
                        a.output.display()
                    )));
                }
                LinesOut::ByExtension
            }
        },
        provenance: a.provenance.clone(),
    };
    outputs.check(&a.input.paths())?;
    let params: linegs_gpu::refine::Params = a.params.into();
    let job = Job {
        check_frames: !a.no_frame_check,
        ..super::env::job(params.clone(), a.engine.backend.into())?
    };
    // The device opens (and its kernels compile) while the files are read.
    let mut device = job.open();
    let scene = load_framed(&a.input, &params, !a.no_frame_check)?;
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
    let refined = job.refine_on(&scene, &mut device, |s| {
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
        if let Some(sh) = &steps.fit.shifts {
            println!(
                "step 4 (--fit {}) moved {} of {} segments: median {:.3} r, 90th percentile {:.3} r",
                steps.fit.fit.name(),
                sh.moved,
                scene.lines.len(),
                sh.median_r,
                sh.p90_r
            );
        }
        if let Some(d) = &steps.fit.diagnosis {
            println!(
                "the model near the lines: {}; the edge fit moved {}, kept {} where the model \
                 knows the edge less well than the line, {} for lack of members",
                d.text, d.moved, d.model_knows_less, d.too_few_members
            );
        }
        if let Some(n) = a.explain {
            match steps.fit.fit_decisions.iter().find(|d| d.segment == n) {
                Some(d) => println!("segment {n}: {}", d.explain(r.radius)),
                None => println!(
                    "segment {n}: no decision (the edge fit did not move it, or it is not \
                     one of the {} input segments)",
                    scene.lines.len()
                ),
            }
        }
    }
    println!("wrote {} in {:.2} s", a.output.display(), r.total_seconds);
    if let Some(rp) = &a.report {
        println!("wrote {}", rp.display());
    }
    if let Some(pp) = &a.provenance {
        println!("wrote {}", pp.display());
    }
    Ok(())
}
