use super::{input_error, metrics_table, print_engine, BackendArgs};
use crate::cmd::eval::SeriesCols;
use crate::cmd::render::{AFTER, BEFORE};
use anyhow::{Context, Result};
use clap::Args;
use linegs_gpu::eval::{self, gt};
use linegs_gpu::io;
use linegs_gpu::pipeline::{Job, Outputs, Scene};
use linegs_gpu::refine::Params;
use linegs_gpu::render::{self, Layer, Panel};
use linegs_gpu::synth;
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

/// What the demo writes into its folder, in the order it lists them.
const FILES: [&str; 10] = [
    "gaussians.ply",
    "input.txt",
    "ground_truth.obj",
    "refined.obj",
    "before_after.ply",
    "report.json",
    "sweep.png",
    "sweep.svg",
    "before_after.png",
    "viewer.html",
];

pub fn run(a: DemoArgs, verbose: bool) -> Result<()> {
    let t0 = Instant::now();
    if a.out.exists() && !a.out.is_dir() {
        return Err(input_error(format!(
            "{}: --out is a file; the demo writes its files into a folder",
            a.out.display()
        )));
    }
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("{}: cannot create the demo folder", a.out.display()))?;
    let d = &a.out;
    let file = |name: &str| d.join(name);
    // Every file checked before any work, and all of them land together at the end.
    let mut outs = io::OutputSet::new();
    for name in FILES {
        outs.output("--out", &file(name), &[]);
    }
    outs.check()?;
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
    let toy_gt = scene.gt.clone();
    let description = scene.description.clone();
    let mut input = Scene::from_arrays(scene.gaussians, scene.lines)?;
    input.description = Some(description);
    let radii = vec![0.02, 0.05, 0.1, 0.2];
    let job = Job {
        sweep: Some(radii.clone()),
        gt: Some(gt::Reference {
            edges: gt::GtEdges::from_segments(&toy_gt),
            protocol: gt::Protocol::Exact,
        }),
        ..super::env::job(Params::default(), a.engine.backend.into())?
    };
    let mut out = job.refine(&input, |_| {})?;
    print_engine(&out.report, verbose);
    let scene = &input;
    let gt_edges = &toy_gt;
    let before = &out.report.before.clone();
    let after = out.report.after.clone().expect("refine");
    println!(
        "refined {} -> {} segments on {} ({}) in {:.2} s",
        scene.lines.len(),
        out.lines.len(),
        out.report.backend,
        out.report.adapter,
        t0.elapsed().as_secs_f64()
    );
    print!(
        "{}",
        metrics_table(&[("before", before), ("after", &after)])
    );
    let g = out
        .report
        .ground_truth
        .clone()
        .expect("the job has ground truth");
    let (gt_before, gt_after) = (&g.before, g.after.as_ref().expect("refine"));
    let f = |m: &gt::GtMetrics| m.scores.get(1).map_or(0.0, |s| s.f_score);
    println!(
        "against the ground-truth edges: accuracy {:.4} -> {:.4}, completeness {:.4} -> {:.4}, F@0.01 {:.3} -> {:.3}",
        gt_before.accuracy.unwrap_or(f64::NAN),
        gt_after.accuracy.unwrap_or(f64::NAN),
        gt_before.completeness.unwrap_or(f64::NAN),
        gt_after.completeness.unwrap_or(f64::NAN),
        f(gt_before),
        f(gt_after)
    );

    outs.write(&file("gaussians.ply"), |p| {
        io::write_gaussians_3dgs(p, &scene.gaussians, None)
    })?;
    // Line3D++ text keeps the scene's line groups, so `refine` on these files runs the
    // collinear merge as the demo did and reproduces its numbers exactly (tests/cli.rs).
    outs.write(&file("input.txt"), |p| {
        io::write_lines_line3dpp(p, &scene.lines)
    })?;
    outs.write(&file("ground_truth.obj"), |p| io::write_lines(p, gt_edges))?;
    let outputs = Outputs {
        lines: file("refined.obj"),
        compare_ply: Some(file("before_after.ply")),
        report: Some(file("report.json")),
        ..Default::default()
    };
    outputs.stage(&mut outs, &scene.lines, &mut out)?;
    let sw = out.report.sweep.as_ref().expect("the job has a sweep");
    let (cb, ca) = (
        SeriesCols::new(&sw.before),
        SeriesCols::new(sw.after.as_ref().expect("refine")),
    );
    let series = [cb.series("before", &radii), ca.series("after", &radii)];
    let title = "synthetic toy scene: metrics against the evaluation radius";
    let (w, h) = render::PLOT_SIZE;
    let doc = render::sweep_plot_svg(&series, title, w, h);
    let png = render::svg_to_image(&doc)
        .map_err(|e| anyhow::anyhow!("cannot render the sweep plot: {e}"))?;
    outs.write(&file("sweep.png"), |p| png.write_png(p))?;
    outs.write(&file("sweep.svg"), |p| {
        io::write_bytes_atomic(p, doc.as_bytes())
    })?;
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
            metrics: mline(before),
        },
        Panel {
            title: "after: refined (default profile)",
            layers: vec![Layer {
                name: "refined",
                segments: &out.lines.segments,
                color: AFTER,
            }],
            metrics: mline(&after),
        },
    ];
    let img = render::render_comparison(&scene.gaussians, &panels, 1600, 900);
    outs.write(&file("before_after.png"), |p| img.write_png(p))?;
    let layers = render::viewer_layers(
        &scene.lines.segments,
        Some(&out.lines.segments),
        Some(gt_edges),
    );
    let html = render::viewer_html(
        &scene.gaussians,
        &layers,
        "linegs-gpu demo (synthetic)",
        200_000,
    );
    outs.write(&file("viewer.html"), |p| {
        io::write_bytes_atomic(p, html.as_bytes())
    })?;
    outs.commit()?;
    println!("wrote to {}:", d.display());
    for name in FILES {
        println!("  {}", file(name).display());
    }
    Ok(())
}
