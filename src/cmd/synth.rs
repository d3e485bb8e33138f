use super::input_error;
use anyhow::Result;
use clap::{Args, Subcommand};
use linegs_gpu::io;
use linegs_gpu::synth;
use std::path::{Path, PathBuf};

#[derive(Args, Debug)]
pub struct SynthArgs {
    #[command(subcommand)]
    pub what: SynthKind,
}

/// Everything made here is synthetic: centers placed by a rule, not trained.
#[derive(Subcommand, Debug)]
pub enum SynthKind {
    /// The paper's toy scene (box edges) with every defect planted: Gaussians, input
    /// lines and the ground-truth edges.
    Toy {
        /// Gaussians to write (a standard 62-property 3DGS PLY).
        #[arg(short, long, value_name = "PLY")]
        output: PathBuf,
        /// The noisy input segments (format from the extension).
        #[arg(long, value_name = "FILE")]
        lines_out: PathBuf,
        /// The ground-truth edges.
        #[arg(long, value_name = "FILE")]
        gt_out: Option<PathBuf>,
        /// Number of Gaussians.
        #[arg(short = 'n', long, value_name = "N", default_value_t = 20_000)]
        num_gaussians: usize,
        /// Seed of the random scene (same seed, same files).
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// A box scene of the authors' s200k shape for the whole-process benchmark: the toy
    /// scene's 9 boxes and 3 quadrilaterals (120 edges), 200,000 Gaussians, and exactly 318
    /// input segments with every defect planted (24 offset, 24 overextended, 24 edges split
    /// into 60 pieces, 48 clean, 120 duplicates, 42 outliers).
    S200k {
        /// Gaussians to write (a standard 62-property 3DGS PLY).
        #[arg(short, long, value_name = "PLY")]
        output: PathBuf,
        /// The noisy input segments (format from the extension).
        #[arg(long, value_name = "FILE")]
        lines_out: PathBuf,
        /// The ground-truth edges.
        #[arg(long, value_name = "FILE")]
        gt_out: Option<PathBuf>,
        /// Seed of the random scene (same seed, same files).
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Gaussians on the surface of a triangle mesh (.obj), concentrated near its sharp
    /// edges (dihedral angle over 30°) as trained 3DGS models are.
    Mesh {
        /// The mesh (`v` and `f` records).
        #[arg(long, value_name = "OBJ")]
        mesh: PathBuf,
        /// Gaussians to write (a standard 62-property 3DGS PLY).
        #[arg(short, long, value_name = "PLY")]
        output: PathBuf,
        /// Number of Gaussians.
        #[arg(short = 'n', long, value_name = "N", default_value_t = 100_000)]
        num_gaussians: usize,
        /// Also write the detected sharp edges (format from the extension).
        #[arg(long, value_name = "FILE")]
        edges_out: Option<PathBuf>,
        /// Seed of the random sampling (same seed, same files).
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
    /// Gaussians along given segments with noise, plus a background (for line files that
    /// come without a 3DGS model).
    Around {
        /// The line segments to place Gaussians around (any supported line format).
        #[arg(short, long, value_name = "FILE")]
        lines: PathBuf,
        /// Gaussians to write (a standard 62-property 3DGS PLY).
        #[arg(short, long, value_name = "PLY")]
        output: PathBuf,
        /// Number of Gaussians.
        #[arg(short = 'n', long, value_name = "N", default_value_t = 100_000)]
        num_gaussians: usize,
        /// Standard deviation of the noise around the segments (scene units), finite and
        /// >= 0.
        #[arg(long, default_value_t = 0.004, value_parser = linegs_gpu::refine::params::nonnegative)]
        sigma: f64,
        /// Fraction of the centers spread uniformly in the lines' bounding box, in [0, 1].
        #[arg(long, default_value_t = 0.1, value_parser = linegs_gpu::refine::params::fraction)]
        background: f64,
        /// Seed of the random placement (same seed, same files).
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

pub fn run(a: SynthArgs) -> Result<()> {
    match a.what {
        SynthKind::Toy {
            output,
            lines_out,
            gt_out,
            num_gaussians,
            seed,
        } => {
            write_scene(
                "synthetic toy scene",
                &output,
                &lines_out,
                gt_out.as_deref(),
                || {
                    synth::toy_scene(&synth::ToyParams {
                        seed,
                        n_gaussians: num_gaussians,
                        ..Default::default()
                    })
                },
            )?;
        }
        SynthKind::S200k {
            output,
            lines_out,
            gt_out,
            seed,
        } => {
            write_scene(
                "synthetic s200k box scene",
                &output,
                &lines_out,
                gt_out.as_deref(),
                || synth::s200k_scene(seed),
            )?;
        }
        SynthKind::Mesh {
            mesh,
            output,
            num_gaussians,
            edges_out,
            seed,
        } => {
            let mut outs = io::OutputSet::new();
            outs.input(&mesh).output("-o", &output, &["ply"]);
            if let Some(e) = &edges_out {
                outs.output("--edges-out", e, &io::LINE_OUTPUTS);
            }
            outs.check()?;
            let m = synth::mesh::read_obj_mesh(&mesh).map_err(|e| input_error(e.to_string()))?;
            let pts = synth::mesh::gaussians_from_mesh(
                &m,
                num_gaussians,
                seed,
                &synth::mesh::MeshGaussianOptions::default(),
            );
            outs.write(&output, |p| io::write_gaussians_3dgs(p, &pts, None))?;
            if let Some(e) = &edges_out {
                let edges = synth::mesh::sharp_edges(&m.welded(1e-9), 30.0);
                outs.write(e, |p| io::write_lines(p, &edges))?;
            }
            outs.commit()?;
            println!(
                "synthetic: {} Gaussians from {} -> {}",
                pts.len(),
                mesh.display(),
                output.display()
            );
        }
        SynthKind::Around {
            lines,
            output,
            num_gaussians,
            sigma,
            background,
            seed,
        } => {
            let mut outs = io::OutputSet::new();
            outs.input(&lines).output("-o", &output, &["ply"]);
            outs.check()?;
            let l = io::read_lines(&lines)?;
            let pts = synth::gaussians_around_segments(
                &l.lines.segments,
                num_gaussians,
                sigma,
                background,
                seed,
            );
            outs.write(&output, |p| io::write_gaussians_3dgs(p, &pts, None))?;
            outs.commit()?;
            println!(
                "synthetic: {} Gaussians around {} segments of {} -> {}",
                pts.len(),
                l.lines.len(),
                lines.display(),
                output.display()
            );
        }
    }
    Ok(())
}

/// Checks the output paths, makes the scene, and writes its Gaussians (a standard 3DGS
/// PLY), input segments and, when asked, ground-truth edges, all or none.
fn write_scene(
    what: &str,
    output: &Path,
    lines_out: &Path,
    gt_out: Option<&Path>,
    make: impl FnOnce() -> synth::SynthScene,
) -> Result<()> {
    let mut outs = io::OutputSet::new();
    outs.output("-o", output, &["ply"])
        .output("--lines-out", lines_out, &io::LINE_OUTPUTS);
    if let Some(g) = gt_out {
        outs.output("--gt-out", g, &io::LINE_OUTPUTS);
    }
    outs.check()?;
    let scene = make();
    outs.write(output, |p| {
        io::write_gaussians_3dgs(p, &scene.gaussians, None)
    })?;
    outs.write(lines_out, |p| io::write_lines(p, &scene.lines.segments))?;
    if let Some(g) = gt_out {
        outs.write(g, |p| io::write_lines(p, &scene.gt))?;
    }
    outs.commit()?;
    println!(
        "{what}: {} Gaussians -> {}, {} input segments -> {}",
        scene.gaussians.len(),
        output.display(),
        scene.lines.len(),
        lines_out.display()
    );
    Ok(())
}
