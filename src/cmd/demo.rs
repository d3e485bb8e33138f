use super::{engine, metrics_table, BackendArgs};
use crate::cmd::eval::SeriesCols;
use crate::cmd::render::{AFTER, BEFORE};
use anyhow::{Context, Result};
use clap::Args;
use linegs_gpu::eval::{self, gt};
use linegs_gpu::io;
use linegs_gpu::pipeline;
use linegs_gpu::refine::Params;
use linegs_gpu::render::{self, Layer, Panel};
use linegs_gpu::synth;
use serde_json::json;
use std::path::PathBuf;
use std::time::Instant;

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Folder for the inputs, outputs, report, pictures and viewer.
    #[arg(long, default_value = "linegs-demo")]
    pub out: PathBuf,
    #[command(flatten)]
    pub engine: BackendArgs,
    /// Seed of the synthetic scene.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Number of Gaussians in the synthetic scene.
    #[arg(short = 'n', long, value_name = "N", default_value_t = 20_000)]
    pub num_gaussians: usize,
}

pub fn run(a: DemoArgs, verbose: bool) -> Result<()> {
    let t0 = Instant::now();
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create the demo folder", a.out.display()))?;
    let scene = synth::toy_scene(&synth::ToyParams {
        seed: a.seed,
        n_gaussians: a.num_gaussians,
        ..Default::default()
    });
    println!(
        "synthetic toy scene (LineGS sec. 3.2): {} Gaussians, {} input segments with planted \
         defects, {} ground-truth edges",
        scene.gaussians.len(),
        scene.lines.len(),
        scene.gt.len()
    );
    let params = Params::default();
    let prep = pipeline::prepare(&scene.gaussians, &scene.lines.segments, &params)?;
    let eng = engine(a.engine.backend, prep.grid.clone(), verbose)?;
    let out = pipeline::run(eng.as_ref(), &scene.lines, prep.radius, &params, |_| {})?;
    println!(
        "refined {} -> {} segments on {} ({}) in {:.2} s",
        scene.lines.len(),
        out.lines.len(),
        out.backend,
        out.adapter,
        t0.elapsed().as_secs_f64()
    );
    print!(
        "{}",
        metrics_table(&[("before", &out.before), ("after", &out.after)])
    );
    let gt_before = gt::gt_metrics(&scene.lines.segments, &scene.gt, gt::STEP, &gt::THRESHOLDS);
    let gt_after = gt::gt_metrics(&out.lines.segments, &scene.gt, gt::STEP, &gt::THRESHOLDS);
    let f = |m: &gt::GtMetrics| m.scores.get(1).map_or(0.0, |s| s.f_score);
    println!(
        "against the ground-truth edges: accuracy {:.4} -> {:.4}, completeness {:.4} -> {:.4}, F@0.01 {:.3} -> {:.3}",
        gt_before.accuracy.unwrap_or(f64::NAN),
        gt_after.accuracy.unwrap_or(f64::NAN),
        gt_before.completeness.unwrap_or(f64::NAN),
        gt_after.completeness.unwrap_or(f64::NAN),
        f(&gt_before),
        f(&gt_after)
    );

    let d = &a.out;
    let mut files = Vec::new();
    let mut file = |name: &str| {
        let p = d.join(name);
        files.push(p.clone());
        p
    };
    io::write_gaussians_3dgs(&file("gaussians.ply"), &scene.gaussians, None)?;
    // Line3D++ text keeps the scene's line groups, so `refine` on these files runs the
    // collinear merge as the demo did and reproduces its numbers exactly (tests/cli.rs).
    io::write_lines_line3dpp(&file("input.txt"), &scene.lines)?;
    io::write_lines(&file("ground_truth.obj"), &scene.gt)?;
    io::write_lines(&file("refined.obj"), &out.lines.segments)?;
    io::write_lines_ply_layers(
        &file("before_after.ply"),
        &[
            (&scene.lines.segments[..], BEFORE),
            (&out.lines.segments[..], AFTER),
        ],
    )?;
    let radii = [0.02, 0.05, 0.1, 0.2];
    let rl = params.fixes().r_l;
    let sw_b = eval::sweep(
        eng.as_ref(),
        &scene.lines.segments,
        &params.eval,
        rl,
        &radii,
    )?;
    let sw_a = eval::sweep(eng.as_ref(), &out.lines.segments, &params.eval, rl, &radii)?;
    let (cb, ca) = (SeriesCols::new(&sw_b), SeriesCols::new(&sw_a));
    let series = [cb.series("before", &radii), ca.series("after", &radii)];
    let title = "synthetic toy scene: metrics against the evaluation radius";
    render::sweep_plot_png(&series, title, 1400, 900).write_png(&file("sweep.png"))?;
    io::write_bytes_atomic(
        &file("sweep.svg"),
        render::sweep_plot_svg(&series, title).as_bytes(),
    )?;
    let mline = |m: &eval::Metrics| {
        vec![
            format!("{} segments", m.segments + m.skipped),
            format!("E_rms {:.3} cm", m.e_rms_cm.unwrap_or(f64::NAN)),
            format!("R_covered {:.2} %", m.coverage_pct.unwrap_or(f64::NAN)),
            format!(
                "R_L {:.3}  score {:.3}",
                m.r_l.unwrap_or(f64::NAN),
                m.score.unwrap_or(f64::NAN)
            ),
        ]
    };
    let panels = [
        Panel {
            title: "before: input segments",
            layers: vec![Layer {
                name: "input",
                segments: &scene.lines.segments,
                color: BEFORE,
            }],
            metrics: mline(&out.before),
        },
        Panel {
            title: "after: refined (default profile)",
            layers: vec![Layer {
                name: "refined",
                segments: &out.lines.segments,
                color: AFTER,
            }],
            metrics: mline(&out.after),
        },
    ];
    render::render_comparison(&scene.gaussians, &panels, 1600, 900)
        .write_png(&file("before_after.png"))?;
    let layers = render::viewer_layers(
        &scene.lines.segments,
        Some(&out.lines.segments),
        Some(&scene.gt),
    );
    let html = render::viewer_html(
        &scene.gaussians,
        &layers,
        "linegs-gpu demo (synthetic)",
        200_000,
    );
    io::write_bytes_atomic(&file("viewer.html"), html.as_bytes())?;
    let report = json!({
        "tool": "linegs-gpu",
        "version": env!("CARGO_PKG_VERSION"),
        "command": "demo",
        "synthetic": true,
        "scene": scene.description,
        "backend": out.backend,
        "adapter": out.adapter,
        "profile": params.profile,
        "params": params,
        "fixes": params.fixes(),
        "radius": out.radius,
        "input": {
            "gaussians": scene.gaussians.len(),
            "segments": scene.lines.len(),
            "n_box": out.n_box,
        },
        "stages": out.stages,
        "before": out.before,
        "after": out.after,
        "ground_truth": { "before": gt_before, "after": gt_after },
        "sweep": { "radii": radii, "before": sw_b, "after": sw_a },
    });
    io::write_bytes_atomic(
        &file("report.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;
    println!("wrote to {}:", d.display());
    for f in &files {
        println!("  {}", f.display());
    }
    Ok(())
}
