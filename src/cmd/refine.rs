use super::{engine, input_report, load, metrics_table, InputArgs, InputReport};
use anyhow::Result;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use linegs_gpu::eval::Metrics;
use linegs_gpu::io;
use linegs_gpu::pipeline::{self, Stage};
use linegs_gpu::refine::{Fixes, Params};
use serde::Serialize;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct RefineArgs {
    #[command(flatten)]
    pub input: InputArgs,
    /// Where to write the refined segments; the format follows the extension: `.obj`,
    /// `.stl`, `.ply` (with an edge element), `.txt` (6 numbers a row), `.npy`.
    #[arg(short, long, value_name = "FILE")]
    pub output: PathBuf,
    /// Write the JSON report (backend, adapter, parameters, inputs, stages, before/after).
    #[arg(long, value_name = "JSON")]
    pub report: Option<PathBuf>,
    /// Also write a PLY with the input (red) and refined (blue) segments as coloured edges.
    #[arg(long, value_name = "PLY")]
    pub compare_ply: Option<PathBuf>,
    #[command(flatten)]
    pub params: Params,
}

#[derive(Serialize)]
pub struct Report<'a> {
    pub tool: &'static str,
    pub version: &'static str,
    pub command: &'static str,
    pub backend: String,
    pub adapter: String,
    pub profile: linegs_gpu::refine::Profile,
    pub params: &'a Params,
    pub fixes: Fixes,
    pub radius: f64,
    pub input: InputReport,
    pub output: String,
    pub stages: &'a [Stage],
    pub total_seconds: f64,
    pub before: &'a Metrics,
    pub after: &'a Metrics,
    /// Step 4's shifts (units of r) and segment length per stage.
    pub refine: &'a linegs_gpu::refine::StepNotes,
    pub warnings: Vec<String>,
}

pub fn run(a: RefineArgs, verbose: bool) -> Result<()> {
    let t0 = Instant::now();
    // Check the output format before any work, so a typo costs nothing.
    io::check_line_output(&a.output)?;
    let loaded = load(&a.input)?;
    let prep = pipeline::prepare(
        &loaded.cloud.centers,
        &loaded.lines.lines.segments,
        &a.params,
    )?;
    let eng = engine(a.input.backend, prep.grid.clone(), verbose)?;
    let bar = ProgressBar::new_spinner();
    if let Ok(style) = ProgressStyle::with_template("{spinner} {elapsed} {msg}") {
        bar.set_style(style);
    }
    bar.enable_steady_tick(std::time::Duration::from_millis(120));
    bar.set_message("evaluating the input");
    let mut load_stage = vec![Stage {
        name: "load_and_index".into(),
        segments: loaded.lines.lines.len(),
        seconds: t0.elapsed().as_secs_f64(),
    }];
    // The edge fit uses the Gaussians' normals where the file has rotations and scales.
    let mut attrs = linegs_gpu::refine::fit::Attributes::default();
    if a.params.fixes().fit == linegs_gpu::refine::Fit::Edge {
        if let Some(n) = io::read_gaussian_normals(&a.input.gaussians, a.input.min_opacity)? {
            match linegs_gpu::refine::fit::Attributes::for_working_set(
                &loaded.cloud.centers,
                &n,
                &loaded.lines.lines.segments,
            ) {
                Some(at) if at.normals.as_ref().map(Vec::len) == Some(prep.working_set_len) => {
                    attrs = at
                }
                _ => eprintln!(
                    "warning: {}: the normals did not line up with the centers; the edge fit uses the centers only",
                    a.input.gaussians.display()
                ),
            }
        }
    }
    let out = pipeline::run_with(
        eng.as_ref(),
        &loaded.lines.lines,
        &attrs,
        prep.radius,
        &a.params,
        |s| {
            bar.set_message(format!("{} done: {} segments", s.name, s.segments));
            if verbose {
                bar.println(format!(
                    "{:<18} {:>8} segments {:>9.3} s",
                    s.name, s.segments, s.seconds
                ));
            }
        },
    )?;
    bar.finish_and_clear();
    for w in &out.warnings {
        eprintln!("warning: {w}");
    }
    let t = Instant::now();
    io::write_lines(&a.output, &out.lines.segments)?;
    if let Some(p) = &a.compare_ply {
        io::write_lines_ply_layers(
            p,
            &[
                (&loaded.lines.lines.segments[..], [220, 50, 40]),
                (&out.lines.segments[..], [30, 90, 220]),
            ],
        )?;
    }
    let mut stages = std::mem::take(&mut load_stage);
    stages.extend(out.stages.iter().cloned());
    stages.push(Stage {
        name: "write".into(),
        segments: out.lines.len(),
        seconds: t.elapsed().as_secs_f64(),
    });
    let total = t0.elapsed().as_secs_f64();
    println!(
        "{} -> {} segments, r = {}, {} Gaussians in the working set, {} ({})",
        loaded.lines.lines.len(),
        out.lines.len(),
        prep.radius,
        prep.working_set_len,
        out.backend,
        out.adapter
    );
    print!(
        "{}",
        metrics_table(&[("before", &out.before), ("after", &out.after)])
    );
    if let Some(sh) = &out.refine.shifts {
        println!(
            "step 4 (--fit {}) moved {} of {} segments: median {:.3} r, 90th percentile {:.3} r",
            out.refine.fit.name(),
            sh.moved,
            loaded.lines.lines.len(),
            sh.median_r,
            sh.p90_r
        );
    }
    println!("wrote {} in {total:.2} s", a.output.display());
    if let Some(rp) = &a.report {
        let mut warnings = loaded.cloud.warnings.clone();
        warnings.extend(loaded.lines.warnings.iter().cloned());
        warnings.extend(out.warnings.iter().cloned());
        let report = Report {
            tool: "linegs-gpu",
            version: env!("CARGO_PKG_VERSION"),
            command: "refine",
            backend: out.backend.clone(),
            adapter: out.adapter.clone(),
            profile: a.params.profile,
            params: &a.params,
            fixes: a.params.fixes(),
            radius: prep.radius,
            input: input_report(&a.input, &loaded, prep.working_set_len),
            output: a.output.display().to_string(),
            stages: &stages,
            total_seconds: total,
            before: &out.before,
            after: &out.after,
            refine: &out.refine,
            warnings,
        };
        io::write_bytes_atomic(rp, serde_json::to_string_pretty(&report)?.as_bytes())?;
        println!("wrote {}", rp.display());
    }
    Ok(())
}
