//! Subcommands. Each parses its arguments, calls the library, and prints.

pub mod batch;
pub mod bench;
pub mod convert;
pub mod demo;
pub mod env;
pub mod eval;
pub mod info;
pub mod params;
pub mod refine;
pub mod render;
pub mod synth;

use anyhow::Result;
use clap::Args;
use linegs_gpu::eval::Metrics;
use linegs_gpu::io;
use linegs_gpu::pipeline::{LoadOptions, RunError, Scene};
use linegs_gpu::report::Report;
use params::{BackendArg, CurvesArg};
use std::path::PathBuf;

/// Marks an error as the user's input being wrong (exit code 2).
#[derive(Debug)]
pub struct InputError(pub String);

impl std::fmt::Display for InputError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for InputError {}

pub fn input_error(msg: impl Into<String>) -> anyhow::Error {
    anyhow::Error::new(InputError(msg.into()))
}

/// 2 for bad input (unreadable or malformed files, impossible options), 1 otherwise.
pub fn exit_code(e: &anyhow::Error) -> u8 {
    for cause in e.chain() {
        if cause.is::<InputError>() {
            return 2;
        }
        if let Some(ioe) = cause.downcast_ref::<io::Error>() {
            return if ioe.is_input_error() { 2 } else { 1 };
        }
        if let Some(re) = cause.downcast_ref::<RunError>() {
            return if re.is_input_error() { 2 } else { 1 };
        }
    }
    1
}

/// The Gaussians and lines every command reads.
#[derive(Args, Debug, Clone)]
pub struct InputArgs {
    // The formats' words come from the format registry (io::GAUSSIAN_FORMATS).
    #[arg(short, long, value_name = "MODEL", help = format!(
        "The trained model; only the centers are used: {}",
        io::gaussian_format_words()
    ))]
    pub gaussians: PathBuf,
    // The formats' words come from the format registry (io::LINE_FORMATS).
    #[arg(short, long, value_name = "FILE", help = format!(
        "The line segments: {}",
        io::line_format_words()
    ))]
    pub lines: PathBuf,
    #[command(flatten)]
    pub frame: FrameArgs,
    /// The COLMAP sparse model the lines and the model were made from (a folder with
    /// `cameras`, `images`, `points3D`, text or binary; or its `sparse/0/`): when the
    /// lines and the Gaussians are not in one frame, the normalization gsplat
    /// (`normalize_world_space`) or nerfstudio applied to it is recomputed and undone
    /// (docs/formats.md: the automatic frame).
    #[arg(long, value_name = "DIR", conflicts_with = "gaussians_transform")]
    pub colmap: Option<PathBuf>,
    /// Keep only Gaussians with opacity >= this (in [0, 1]: sigmoid of the logit that 3DGS
    /// stores; SPZ, .splat and compressed PLY store it directly).
    #[arg(long, value_name = "ALPHA")]
    pub min_opacity: Option<f64>,
    /// Make Gaussians with NaN or infinite centers an error instead of a warning.
    #[arg(long)]
    pub strict: bool,
}

/// `--format`: how the refined segments are written (`refine`, `batch`). `auto`: by the
/// output's extension; `obj` ... `npy`: that segment file; `limap`: LIMAP `finaltracks/`;
/// `emap`: EMAP/EdgeGaussians `parametric_edges.json`.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum FormatArg {
    Auto,
    Obj,
    Stl,
    Ply,
    Txt,
    Npy,
    Limap,
    Emap,
}

impl FormatArg {
    /// The segment file's extension, for the formats that are one.
    pub fn extension(self) -> Option<&'static str> {
        match self {
            FormatArg::Obj => Some("obj"),
            FormatArg::Stl => Some("stl"),
            FormatArg::Ply => Some("ply"),
            FormatArg::Txt => Some("txt"),
            FormatArg::Npy => Some("npy"),
            FormatArg::Auto | FormatArg::Limap | FormatArg::Emap => None,
        }
    }
}

/// The engine choice of the commands that query the Gaussians (`render` only draws).
#[derive(Args, Debug, Clone)]
pub struct BackendArgs {
    /// Which engine answers the cylinder queries: `auto` (a hardware GPU adapter when
    /// there is one, else the CPU engine), `gpu` (any adapter, software ones such as
    /// lavapipe included) or `cpu`.
    #[arg(long, value_enum, default_value_t = BackendArg::Auto)]
    pub backend: BackendArg,
}

impl InputArgs {
    /// The options of [`Scene::load`]; reads the `--gaussians-transform` file.
    pub fn load_options(&self) -> Result<LoadOptions> {
        Ok(LoadOptions {
            min_opacity: self.min_opacity,
            strict: self.strict,
            transform: self.frame.read_transform()?,
            lines: self.frame.line_options(),
        })
    }
}

/// How the Gaussians are brought into the lines' frame, and what to do with curves.
#[derive(Args, Debug, Clone)]
pub struct FrameArgs {
    /// Map the Gaussians into the lines' frame first: a 4x4 matrix as text (row-major,
    /// applied as given), nerfstudio's `dataparser_transforms.json` (inverted, so a
    /// splatfacto/gsplat model goes back to the COLMAP frame of the lines) or an
    /// EMAP/EdgeGaussians (SDFStudio) `meta_data.json` (its `worldtogt`, applied as given).
    #[arg(long, value_name = "FILE")]
    pub gaussians_transform: Option<PathBuf>,
    /// Bezier curves of EMAP/EdgeGaussians edge files: `skip` them (with a warning) or
    /// sample each as a `polyline` of 16 segments.
    #[arg(long, value_enum, default_value_t = CurvesArg::Skip)]
    pub curves: CurvesArg,
}

impl FrameArgs {
    pub fn line_options(&self) -> io::LineOptions {
        io::LineOptions {
            curves: self.curves.into(),
        }
    }

    /// The `--gaussians-transform` file, read and announced.
    pub fn read_transform(&self) -> Result<Option<io::GaussianTransform>> {
        let Some(p) = &self.gaussians_transform else {
            return Ok(None);
        };
        let t = io::read_transform(p)?;
        eprintln!("note: Gaussians mapped by {}", t.describe);
        Ok(Some(t))
    }

    /// Applies `--gaussians-transform` to `cloud`.
    pub fn transform(&self, cloud: &mut io::GaussianCloud) -> Result<()> {
        if let Some(t) = self.read_transform()? {
            t.apply(&mut cloud.centers);
        }
        Ok(())
    }
}

impl InputArgs {
    /// Every file these options read: the model, the lines, the `--gaussians-transform`.
    pub fn paths(&self) -> Vec<&std::path::Path> {
        let mut v = vec![self.gaussians.as_path(), self.lines.as_path()];
        v.extend(self.frame.gaussians_transform.as_deref());
        v
    }
}

/// An output set whose outputs may not replace any file of the inputs every command reads.
pub fn outputs(a: &InputArgs) -> io::OutputSet {
    let mut outs = io::OutputSet::new();
    for p in a.paths() {
        outs.input(p);
    }
    outs
}

/// Reads the scene, finds its frame with `--colmap` when `check` (the automatic frame, at
/// `params`' radius) and prints what loading it found.
pub fn load_framed(
    a: &InputArgs,
    params: &linegs_gpu::refine::Params,
    check: bool,
) -> Result<Scene> {
    let mut scene = load(a)?;
    let Some(dir) = &a.colmap else {
        return Ok(scene);
    };
    let model = io::read_colmap(dir)?;
    if !check {
        eprintln!(
            "note: --no-frame-check: the COLMAP model {} is not used",
            model.describe()
        );
        return Ok(scene);
    }
    let found = scene.find_frame(&model, params)?;
    match (&found.transform, found.message()) {
        (Some(_), Some(m)) => eprintln!("note: Gaussians mapped by the frame {m}"),
        (None, Some(m)) => eprintln!("warning: {m}"),
        _ => {}
    }
    Ok(scene)
}

/// Reads the scene and prints what loading it found.
pub fn load(a: &InputArgs) -> Result<Scene> {
    crate::oom::doing(
        format!(
            "reading {} and {}",
            a.gaussians.display(),
            a.lines.display()
        ),
        "the model is held in memory whole: free memory or raise the limit (ulimit -v)",
    );
    let scene = Scene::load(&a.gaussians, &a.lines, &a.load_options()?)?;
    for w in &scene.warnings {
        eprintln!("warning: {w}");
    }
    Ok(scene)
}

/// Prints what choosing the engine said: which adapter `auto` picked is a note, a
/// fallback a warning; with `verbose`, the engine that answered.
pub fn print_engine(r: &Report, verbose: bool) {
    for w in &r.notes {
        let kind = if w.contains("using the GPU adapter") {
            "note"
        } else {
            "warning"
        };
        eprintln!("{kind}: {w}");
    }
    if verbose {
        eprintln!("engine: {} ({})", r.backend, r.adapter);
    }
}

fn fmt_opt(v: Option<f64>, prec: usize) -> String {
    match v {
        Some(x) => format!("{x:.prec$}"),
        None => "-".to_string(),
    }
}

/// A radius for a table header or cell: as written when short, else in exponent form
/// (`1e-30`, not 32 digits), so a column stays narrow for any radius.
pub fn fmt_radius(r: f64) -> String {
    let s = format!("{r}");
    if s.len() <= 12 {
        s
    } else {
        format!("{r:e}")
    }
}

/// The metrics as a small aligned table, one column per labelled set. A column is 14
/// characters wide, wider where a header or cell needs it, always with a space before it.
pub fn metrics_table(cols: &[(&str, &Metrics)]) -> String {
    type Cell = Box<dyn Fn(&Metrics) -> String>;
    let rows: [(&str, Cell); 7] = [
        ("r_e", Box::new(|m: &Metrics| fmt_radius(m.radius))),
        ("E_rms (cm)", Box::new(|m: &Metrics| fmt_opt(m.e_rms_cm, 4))),
        (
            "R_covered (%)",
            Box::new(|m: &Metrics| fmt_opt(m.coverage_pct, 3)),
        ),
        ("R_L", Box::new(|m: &Metrics| fmt_opt(m.r_l, 4))),
        ("score", Box::new(|m: &Metrics| fmt_opt(m.score, 4))),
        ("segments", Box::new(|m: &Metrics| m.segments.to_string())),
        ("skipped", Box::new(|m: &Metrics| m.skipped.to_string())),
    ];
    let cells: Vec<Vec<String>> = rows
        .iter()
        .map(|(_, f)| cols.iter().map(|(_, m)| f(m)).collect())
        .collect();
    let widths: Vec<usize> = cols
        .iter()
        .enumerate()
        .map(|(j, (name, _))| {
            let widest = cells
                .iter()
                .map(|r| r[j].chars().count())
                .chain([name.chars().count()])
                .max()
                .unwrap_or(0);
            (widest + 1).max(14)
        })
        .collect();
    let mut out = String::new();
    out.push_str(&format!("{:<16}", "metric"));
    for ((name, _), w) in cols.iter().zip(&widths) {
        out.push_str(&format!("{name:>w$}"));
    }
    out.push('\n');
    for ((label, _), row) in rows.iter().zip(&cells) {
        out.push_str(&format!("{label:<16}"));
        for (c, w) in row.iter().zip(&widths) {
            out.push_str(&format!("{c:>w$}"));
        }
        out.push('\n');
    }
    for (name, m) in cols {
        if let Some(msg) = &m.message {
            out.push_str(&format!("note ({name}): {msg}\n"));
        }
    }
    out
}
