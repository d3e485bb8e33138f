use super::params::{BackendArg, ParamsArgs, ProtocolArg};
use super::{input_error, FormatArg};
use anyhow::Result;
use clap::Args;
use linegs_gpu::batch::{self, BatchOptions, Manifest, Shard, Status};
use std::path::PathBuf;

#[derive(Args, Debug)]
#[command(after_help = "Manifest (CSV, paths relative to it):
  name,gaussians,lines,gt,radius,eval_radius
  chair,chair/point_cloud.ply,chair/Line3D++.txt,,0.05,
  abc_00000006,abc/6/gaussians.ply,abc/6/lines.obj,abc/6/gt.txt,0.01,0.02

Slurm: scripts/slurm-submit.sh (docs/cluster.md). Concurrent shards run with --no-summary;
one `linegs-gpu batch m.csv -o out --summary-only` after them writes the summary.")]
pub struct BatchArgs {
    /// The manifest: a CSV with a header `name,gaussians,lines` and optionally `gt`,
    /// `radius`, `eval_radius` (a scene's values override the options), one scene a row.
    #[arg(value_name = "MANIFEST.csv")]
    pub manifest: PathBuf,
    /// Output folder: `<name>/refined.<format>` and `<name>/report.json` per scene
    /// (`<name>/error.txt` when it failed), `summary.csv` and `summary.md`.
    #[arg(short, long, value_name = "OUTDIR")]
    pub output: PathBuf,
    /// Leave the scenes that already have a report (resume an interrupted run).
    #[arg(long)]
    pub skip_existing: bool,
    /// Do not write summary.csv/summary.md (for shards that run at the same time, whose
    /// summaries would each see only part of the dataset).
    #[arg(long, conflicts_with = "summary_only")]
    pub no_summary: bool,
    /// Run no scene: write summary.csv/summary.md from the scenes' folders (after the
    /// shards), and remove the temporary folders that killed runs left behind.
    #[arg(long)]
    pub summary_only: bool,
    /// Run nothing: print the manifest's scene names, one a line in manifest order (the
    /// scene of array task i of scripts/slurm-submit.sh is line i, from 0).
    #[arg(long, conflicts_with_all = ["summary_only", "no_summary", "skip_existing"])]
    pub list: bool,
    /// Run every n-th scene starting at the i-th (0-based), e.g. `1/4`. Default: from
    /// SLURM_ARRAY_TASK_ID / SLURM_ARRAY_TASK_COUNT (minus SLURM_ARRAY_TASK_MIN) when
    /// they are set, else all scenes.
    #[arg(long, value_name = "i/n")]
    pub shard: Option<Shard>,
    /// Format of the refined segments (`<name>/refined.<format>`): obj, stl, ply, txt or
    /// npy (`auto` is obj).
    #[arg(long, value_enum, default_value_t = FormatArg::Obj)]
    pub format: FormatArg,
    /// How the manifest's `gt` edges score the lines: `exact` (every sample, `<=`
    /// thresholds) or `emap` (the published ABC-NEF tables' rules; see `eval --help`).
    #[arg(long, value_enum, default_value_t = ProtocolArg::Exact)]
    pub protocol: ProtocolArg,
    /// Which engine answers the cylinder queries: `auto`, `gpu` or `cpu`.
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    pub backend: BackendArg,
    #[command(flatten)]
    pub params: ParamsArgs,
}

/// Reads the manifest, with a progress bar on the standard error (a terminal only) for a
/// large one.
fn read_manifest(path: &std::path::Path) -> Result<Manifest> {
    let bar = indicatif::ProgressBar::hidden();
    let m = Manifest::read_with_progress(path, |rows, done, total| {
        if bar.is_hidden() {
            bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
            bar.set_length(total as u64);
            bar.set_style(
                indicatif::ProgressStyle::with_template("reading {msg} {bar:30} {percent}%")
                    .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
            );
        }
        bar.set_message(format!("{} ({rows} scenes)", path.display()));
        bar.set_position(done as u64);
    });
    bar.finish_and_clear();
    Ok(m?)
}

pub fn run(a: BatchArgs, verbose: bool) -> Result<()> {
    let shard = match a.shard {
        Some(s) => s,
        None => Shard::from_env(|k| std::env::var(k).ok())
            .map_err(|e| input_error(e.to_string()))?
            .unwrap_or_default(),
    };
    let format = match a.format {
        FormatArg::Auto => "obj",
        f => f.extension().ok_or_else(|| {
            input_error(
                "--format: batch writes a segment file a scene (`refined.<format>`): obj, \
                 stl, ply, txt or npy",
            )
        })?,
    };
    let m = read_manifest(&a.manifest)?;
    if a.list {
        for e in &m.entries {
            println!("{}", e.name);
        }
        return Ok(());
    }
    if a.summary_only {
        batch::check_paths(&m, &a.output, format, None, true)?;
        let removed = batch::remove_partial_dirs(&a.output)?;
        let s = batch::write_summary(&m, &a.output)?;
        println!(
            "wrote {} and summary.md: {} of {} scenes finished{}",
            a.output.join("summary.csv").display(),
            s.finished,
            s.rows.len(),
            if removed > 0 {
                format!("; removed {removed} folders of killed runs")
            } else {
                String::new()
            }
        );
        return Ok(());
    }
    let mine = (0..m.entries.len()).filter(|&i| shard.includes(i)).count();
    println!(
        "{}: {} scenes, shard {}/{} runs {mine}",
        a.manifest.display(),
        m.entries.len(),
        shard.index,
        shard.count
    );
    let opts = BatchOptions {
        params: a.params.into(),
        backend: a.backend.into(),
        gpu: super::env::gpu_setup()?.clone(),
        shard,
        skip_existing: a.skip_existing,
        format: format.to_string(),
        protocol: a.protocol.into(),
        summary: !a.no_summary,
    };
    let mut k = 0;
    let results = batch::run(&m, &a.output, &opts, |e, st| {
        k += 1;
        match st {
            Status::Done { seconds } => println!("[{k}/{mine}] {}: done in {seconds:.2} s", e.name),
            Status::Skipped => println!("[{k}/{mine}] {}: skipped (it has a report)", e.name),
            Status::Busy => println!(
                "[{k}/{mine}] {}: skipped (another batch is working on it: {} is locked)",
                e.name,
                batch::scene_dir(&a.output, &e.name)
                    .join(batch::LOCK_NAME)
                    .display()
            ),
            Status::Failed(msg) => {
                println!("[{k}/{mine}] {}: FAILED", e.name);
                eprintln!("error: {}: {msg}", e.name);
            }
        }
        if verbose {
            println!("  {}", batch::scene_dir(&a.output, &e.name).display());
        }
    })?;
    if a.no_summary {
        println!("no summary written (--no-summary)");
    } else {
        let s = batch::summarize(&m, &a.output);
        println!(
            "wrote {} and summary.md: {} of {} scenes finished",
            a.output.join("summary.csv").display(),
            s.finished,
            s.rows.len()
        );
    }
    let failed = results
        .iter()
        .filter(|(_, st)| matches!(st, Status::Failed(_)))
        .count();
    if failed > 0 {
        anyhow::bail!(
            "{failed} of {mine} scenes of this shard failed (see their error.txt and the summary)"
        );
    }
    Ok(())
}
