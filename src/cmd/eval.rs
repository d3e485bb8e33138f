use super::params::{choices, chosen, EvalParamsArgs, ProtocolArg};
use super::{load_framed, metrics_table, print_engine, BackendArgs, InputArgs};
use anyhow::Result;
use clap::Args;
use linegs_gpu::eval::abc::AbcGroundTruth;
use linegs_gpu::eval::gt::{GtMetrics, Protocol, Reference};
use linegs_gpu::eval::Metrics;
use linegs_gpu::io;
use linegs_gpu::pipeline::Job;
use linegs_gpu::refine::{Params, Profile};
use linegs_gpu::render;
use std::path::PathBuf;

#[derive(Args, Debug)]
#[command(
    after_help = "A paper-style ABC-NEF row (EMAP's protocol: Acc / Comp in mm, P / R / F at 5 / 10 / 20 mm):
  linegs-gpu eval -g point_cloud.ply -l refined.obj --protocol emap \\
    --gt-abc MODEL_features_001.yml --gt-mesh MODEL_trimesh_001.obj --abc-stats chunk_0000_stats.json
A dataset's table (per-object means, as the papers print): a batch manifest with a gt column, then
  linegs-gpu batch scenes.csv -o results --protocol emap      (results/summary.md)
More: docs/evaluation.md."
)]
pub struct EvalArgs {
    #[command(flatten)]
    pub input: InputArgs,
    #[command(flatten)]
    pub engine: BackendArgs,
    #[command(flatten)]
    pub eval: EvalParamsArgs,
    /// Profile whose R_L convention applies when --r-l is not given (default: paper's
    /// equation; reference: the authors' ln N_box).
    #[arg(long, default_value_t = Profile::default().name().to_string(), value_parser = choices(Profile::CHOICES))]
    pub profile: String,
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
    /// Ground-truth edges for the ABC-NEF metrics (accuracy, completeness, precision /
    /// recall / F at 0.005, 0.01, 0.02), in the lines' frame: any line format, or a
    /// `.ply` of sampled GT points without edges (EMAP / EdgeGaussians `*_0.005.ply`).
    #[arg(long, value_name = "FILE", conflicts_with = "gt_abc")]
    pub gt: Option<PathBuf>,
    /// Ground truth from an ABC model's feature file (`*_features_*.yml`): every sharp
    /// curve (lines, circles, ellipses, B-splines), through the vertices of --gt-mesh,
    /// moved into the ABC-NEF unit cube by --abc-stats.
    #[arg(long, value_name = "FEAT.yml", requires = "gt_mesh")]
    pub gt_abc: Option<PathBuf>,
    /// The ABC model's mesh in its own units (`*_trimesh_*.obj`), for --gt-abc.
    #[arg(long, value_name = "MODEL.obj", requires = "gt_abc")]
    pub gt_mesh: Option<PathBuf>,
    /// The model's `chunk_*_stats.json` (the whole file or its entry): its bbox defines
    /// the unit-cube frame. Without it the mesh's own box is used, with a warning.
    #[arg(long, value_name = "STATS.json", requires = "gt_abc")]
    pub abc_stats: Option<PathBuf>,
    /// With --gt-abc: the sharp straight lines only (line-only studies).
    #[arg(long, requires = "gt_abc")]
    pub gt_lines_only: bool,
    /// How the ground truth scores the lines. `exact` (default): both sets sampled every
    /// 0.005 with both ends, every sample scored, thresholds inclusive; distances in the
    /// lines' units. `emap`: the published ABC-NEF tables' rules (EMAP's eval_ABC.py):
    /// GT sampled at 0.005 in the ABC model's own units, floor(L / 0.005) samples per
    /// segment, predicted samples averaged per voxel of a 256^3 grid over [-1, 1]^3,
    /// strict thresholds; accuracy and completeness printed in mm (x 1000).
    #[arg(long, value_enum, default_value_t = ProtocolArg::Exact)]
    pub protocol: ProtocolArg,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(a: EvalArgs, verbose: bool) -> Result<()> {
    let mut outs = super::outputs(&a.input);
    for p in a
        .compare
        .iter()
        .chain(&a.gt)
        .chain(&a.gt_abc)
        .chain(&a.gt_mesh)
        .chain(&a.abc_stats)
    {
        outs.input(p);
    }
    if let Some(p) = &a.plot {
        outs.output("--plot", p, &["png", "svg"]);
    }
    outs.check()?;
    let params = Params {
        profile: chosen(&a.profile),
        eval: a.eval.clone().into(),
        ..Params::default()
    };
    let scene = load_framed(&a.input, &params, true)?;
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
        params,
        backend: a.engine.backend.into(),
        gpu: super::env::gpu_setup()?.clone(),
        sweep: a.radii.clone(),
        gt: ground_truth(&a)?,
        check_frames: true,
    };
    let report = job.evaluate(&scene, compare.as_ref())?;
    if let Some(g) = &report.ground_truth {
        frame_check(&a, &g.before)?;
    }
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
            .map(|m| (format!("r_e={}", super::fmt_radius(m.radius)), *m))
            .collect();
        let refs: Vec<(&str, &Metrics)> = cols.iter().map(|(n, m)| (n.as_str(), *m)).collect();
        print!("{}", metrics_table(&refs));
        let gt = gts.and_then(|(b, af)| if i == 0 { Some(b) } else { af });
        if let Some(g) = gt {
            print_ground_truth(g);
        }
    }
    Ok(())
}

fn print_ground_truth(g: &GtMetrics) {
    if g.protocol == Protocol::Emap {
        let mm = |x: Option<f64>| x.map_or("-".into(), |x| format!("{:.2} mm", 1000.0 * x));
        println!(
            "ground truth (emap protocol): accuracy {} completeness {} ({} voxel-averaged / {} GT samples)",
            mm(g.accuracy),
            mm(g.completeness),
            g.predicted_samples,
            g.gt_samples
        );
        for s in &g.scores {
            println!(
                "  @{:>2} mm precision {:5.1} recall {:5.1} F {:5.1}",
                (1000.0 * s.threshold).round(),
                100.0 * s.precision,
                100.0 * s.recall,
                100.0 * s.f_score
            );
        }
        return;
    }
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

/// The ground truth of `--gt` or `--gt-abc`, with the protocol, its warnings printed.
fn ground_truth(a: &EvalArgs) -> Result<Option<Reference>> {
    let edges = if let Some(feat) = &a.gt_abc {
        let mesh = a.gt_mesh.as_ref().expect("clap requires --gt-mesh");
        let g = AbcGroundTruth::read(feat, mesh, a.abc_stats.as_deref())?;
        for w in &g.warnings {
            eprintln!("warning: {w}");
        }
        g.edges(a.gt_lines_only)
    } else if let Some(p) = &a.gt {
        let (edges, warnings) = linegs_gpu::eval::gt::read_gt_file(p)?;
        for w in &warnings {
            eprintln!("warning: {w}");
        }
        edges
    } else {
        return Ok(None);
    };
    Ok(Some(Reference {
        edges,
        protocol: a.protocol.into(),
    }))
}

/// Farther than this from every GT sample, the lines are taken to be in another frame.
const FRAME_DISTANCE: f64 = 0.1;

/// Stops (exit 2) when no predicted sample lies within 0.1 of the ground truth: the GT
/// and the lines are then in different frames (ABC units against the unit cube, say).
fn frame_check(a: &EvalArgs, g: &GtMetrics) -> Result<()> {
    let Some(d) = g.closest else { return Ok(()) };
    if d <= FRAME_DISTANCE {
        return Ok(());
    }
    let gt =
        a.gt.as_ref()
            .or(a.gt_abc.as_ref())
            .expect("ground truth given");
    Err(super::input_error(format!(
        "{}: the ground truth is not in the frame of {}: no line sample lies within {FRAME_DISTANCE} \
         of it (the closest is {d:.4} away); give the GT in the lines' frame (for ABC models: \
         --gt-abc with --gt-mesh and --abc-stats, which move it into the ABC-NEF unit cube)",
        gt.display(),
        a.input.lines.display()
    )))
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
