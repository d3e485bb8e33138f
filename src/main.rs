//! The `linegs-gpu` command line: argument parsing and printing only; the work is in the
//! library.

mod cmd;

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Turn noisy 3D line segments (Line3D++, ELSR, LIMAP) into a clean, compact line model
/// using the Gaussian centers of a trained 3D Gaussian Splatting model (the LineGS method),
/// with every cylinder query answered in batches by WGSL compute kernels or by the CPU.
#[derive(Parser, Debug)]
#[command(name = "linegs-gpu", version, about, long_about = None)]
#[command(after_help = "Examples:
  linegs-gpu demo
  linegs-gpu refine --gaussians point_cloud.ply --lines Line3D++.txt -o refined.obj --report report.json
  linegs-gpu eval --gaussians point_cloud.ply --lines refined.obj --radii 0.02,0.05,0.1,0.2 --plot sweep.png
  linegs-gpu info point_cloud.ply
  linegs-gpu convert model.spz -o model.ply
  linegs-gpu batch scenes.csv -o results --skip-existing

Exit codes: 0 success, 1 failure (GPU, I/O), 2 bad input or usage.")]
struct Cli {
    /// Print more (the adapter, per-stage timings, warnings in full).
    #[arg(short, long, global = true)]
    verbose: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Refine line segments against the Gaussian centers and report before/after metrics.
    Refine(cmd::refine::RefineArgs),
    /// Measure line segments against the Gaussian centers (the paper's metrics).
    Eval(cmd::eval::EvalArgs),
    /// Describe a Gaussian model or line file: format, counts, bounding box, properties.
    Info(cmd::info::InfoArgs),
    /// Convert a Gaussian model to a standard PLY, or lines to another line format.
    Convert(cmd::convert::ConvertArgs),
    /// Build the synthetic toy scene, refine it, and write inputs, outputs, report,
    /// pictures and a 3D viewer to a folder.
    Demo(cmd::demo::DemoArgs),
    /// Make synthetic Gaussians (and lines): the toy scene, a mesh, or around segments.
    Synth(cmd::synth::SynthArgs),
    /// Draw Gaussian centers and one or two segment sets to a PNG (and an HTML viewer).
    Render(cmd::render::RenderArgs),
    /// Refine every scene of a manifest (CSV) into its own folder, a shard per process
    /// (Slurm array), and summarize them in the columns of the paper's Table I.
    Batch(cmd::batch::BatchArgs),
    /// Time whole runs on synthetic scenes of given sizes, per stage, CPU and GPU.
    Bench(cmd::bench::BenchArgs),
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    let verbose = cli.verbose;
    let result = match cli.command {
        Command::Refine(a) => cmd::refine::run(a, verbose),
        Command::Eval(a) => cmd::eval::run(a, verbose),
        Command::Info(a) => cmd::info::run(a),
        Command::Convert(a) => cmd::convert::run(a),
        Command::Demo(a) => cmd::demo::run(a, verbose),
        Command::Synth(a) => cmd::synth::run(a),
        Command::Render(a) => cmd::render::run(a),
        Command::Bench(a) => cmd::bench::run(a, verbose),
        Command::Batch(a) => cmd::batch::run(a, verbose),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(cmd::exit_code(&e))
        }
    }
}
