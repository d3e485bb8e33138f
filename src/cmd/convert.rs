//! `linegs-gpu convert IN -o OUT`: a model in any readable format to a standard PLY
//! (centers and opacity), or lines in any readable format to any writable one.

use super::{input_error, FrameArgs};
use anyhow::Result;
use clap::Args;
use linegs_gpu::io::{self, PlyOptions};
use std::path::PathBuf;

#[derive(Args, Debug)]
pub struct ConvertArgs {
    // The formats' words come from the format registry (io::GAUSSIAN_FORMATS).
    #[arg(help = format!(
        "A Gaussian model ({}) or a line file or folder in any format `refine --lines` reads",
        io::gaussian_family_words(true)
    ))]
    pub input: PathBuf,
    // The writers come from the format registry (io::LINE_WRITERS).
    #[arg(short, long, value_name = "FILE", help = format!(
        "Gaussians: a `.ply` (binary, `float x y z opacity`, opacity as the 3DGS logit). \
         Lines: {}, by extension",
        io::line_output_words(false)
    ))]
    pub output: PathBuf,
    /// Gaussians: keep only those with opacity >= this (in [0, 1]).
    #[arg(long, value_name = "ALPHA")]
    pub min_opacity: Option<f64>,
    /// Gaussians: a NaN or infinite center is an error instead of a skipped Gaussian.
    #[arg(long)]
    pub strict: bool,
    #[command(flatten)]
    pub frame: FrameArgs,
}

pub fn run(a: ConvertArgs) -> Result<()> {
    let gaussians = io::is_gaussian_model(&a.input)?;
    // Checked before any work: the extension, the folder, and that `-o` is not an input.
    let mut outs = io::OutputSet::new();
    outs.input(&a.input);
    if let Some(t) = &a.frame.gaussians_transform {
        outs.input(t);
    }
    match gaussians {
        true => outs.output("-o", &a.output, &["ply"]),
        false => outs.output("-o", &a.output, &io::LINE_OUTPUTS),
    };
    outs.check()?;
    crate::oom::doing(
        format!("converting {}", a.input.display()),
        "the input is held in memory whole: free memory or raise the limit (ulimit -v)",
    );
    if gaussians {
        if let Some(o) = a.min_opacity {
            if !(0.0..=1.0).contains(&o) {
                return Err(input_error(format!(
                    "--min-opacity {o}: expected an opacity in [0, 1]"
                )));
            }
        }
        let (mut cloud, opacity) = io::read_gaussians_with_opacity(
            &a.input,
            &PlyOptions {
                min_opacity: a.min_opacity,
                strict: a.strict,
            },
        )?;
        for w in &cloud.warnings {
            eprintln!("warning: {w}");
        }
        a.frame.transform(&mut cloud)?;
        let comment = format!(
            "converted by linegs-gpu {} from {} ({})",
            env!("CARGO_PKG_VERSION"),
            a.input
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            cloud.format
        );
        outs.write(&a.output, |p| {
            io::write_gaussians_ply(p, &cloud.centers, opacity.as_deref(), &comment)
        })?;
        outs.commit()?;
        println!(
            "{}: {} of {} Gaussians ({}) -> {}{}",
            a.input.display(),
            cloud.centers.len(),
            cloud.vertex_count,
            cloud.format,
            a.output.display(),
            if opacity.is_some() {
                ""
            } else {
                " (no opacity in the input, centers only)"
            }
        );
        return Ok(());
    }
    if a.frame.gaussians_transform.is_some() || a.min_opacity.is_some() {
        return Err(input_error(format!(
            "{}: holds line segments; --gaussians-transform and --min-opacity apply to Gaussian models",
            a.input.display()
        )));
    }
    let lines = io::read_lines_with(&a.input, &a.frame.line_options())?;
    for w in &lines.warnings {
        eprintln!("warning: {w}");
    }
    outs.write(&a.output, |p| io::write_lines(p, &lines.lines.segments))?;
    outs.commit()?;
    println!(
        "{}: {} segments ({}) -> {}",
        a.input.display(),
        lines.lines.len(),
        lines.format,
        a.output.display()
    );
    Ok(())
}
