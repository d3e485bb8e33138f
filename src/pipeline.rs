//! The whole job of docs/method.md#the-refinement-steps, behind one entry point that every
//! caller uses (the CLI's `refine`, `eval`, `demo`, `bench` and `batch`, the Python
//! package, the tests):
//!
//! 1. a [`Scene`]: the Gaussian centers and the lines, loaded from files
//!    ([`Scene::load`]) or taken as arrays ([`Scene::from_arrays`]);
//! 2. a [`Job`]: the parameters, the backend and what to measure beyond the paper's
//!    metrics (a radius sweep, ground truth);
//! 3. [`Job::refine`] or [`Job::evaluate`]: builds the working set, resolves the
//!    [`Settings`] once, builds the grid and the engine once (a [`Refiner`]), runs the
//!    steps and the evaluations, and returns one [`Report`]
//!    (docs/formats.md#the-report) — the same shape for refine, eval and demo.

use crate::engine::dedup::Dedup;
use crate::engine::gpu::GpuSetup;
use crate::engine::select::{prepare, Backend};
use crate::engine::{Engine, EngineError};
use crate::eval::{self, gt, Metrics};
use crate::geom::{LineSet, Segment, MIN_LENGTH};
use crate::index::{Grid, WorkingSet};
use crate::io::{self, PlyOptions};
use crate::refine::{self, Params, RadiusArg, Settings};
use crate::report::{GroundTruth, InputReport, Report, Sweep};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

pub use crate::refine::auto_radius;

/// One timed stage of a run.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Stage {
    pub name: String,
    /// Segments after the stage.
    pub segments: usize,
    pub seconds: f64,
    /// GPU engine: host time of its batches in this stage (preparing queries, deciding
    /// flagged points), excluding waits for the device.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub host_seconds: Option<f64>,
    /// GPU engine: time waiting for the device in this stage.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub device_seconds: Option<f64>,
}

impl Stage {
    fn since(name: &str, segments: usize, t: Instant) -> Stage {
        Stage {
            name: name.to_string(),
            segments,
            seconds: t.elapsed().as_secs_f64(),
            host_seconds: None,
            device_seconds: None,
        }
    }
}

#[derive(thiserror::Error, Debug)]
pub enum RunError {
    #[error(transparent)]
    Engine(#[from] EngineError),
    #[error(transparent)]
    Io(#[from] io::Error),
    /// The input or the options cannot work together (exit code 2).
    #[error("{0}")]
    Input(String),
    /// The lines and the Gaussians are not in one frame ([`Job::check_frames`]; exit
    /// code 2): the message says why and what fixes it.
    #[error("{0}")]
    FrameMismatch(String),
}

impl RunError {
    /// Whether the user's input is at fault (exit code 2) rather than the machine.
    pub fn is_input_error(&self) -> bool {
        match self {
            RunError::Input(_) | RunError::FrameMismatch(_) => true,
            RunError::Io(e) => e.is_input_error(),
            RunError::Engine(_) => false,
        }
    }
}

/// How to read a scene's files.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LoadOptions {
    /// Keep only Gaussians with opacity `>= min_opacity` (in `[0, 1]`).
    pub min_opacity: Option<f64>,
    /// A NaN or infinite Gaussian center is an error instead of a counted warning.
    pub strict: bool,
    /// Maps the Gaussians into the lines' frame (`--gaussians-transform`).
    pub transform: Option<io::GaussianTransform>,
    /// The line readers' options (`--curves`).
    pub lines: io::LineOptions,
}

/// Reads a Gaussian model with `opts` (checked first).
pub fn read_gaussians(path: &Path, opts: &LoadOptions) -> Result<io::GaussianCloud, RunError> {
    Ok(io::read_gaussians(path, &ply_options(opts)?)?)
}

/// The model's centers and, where the file has them and they line up with the centers
/// (one per center kept), its attributes: what `refine` reads, a pipe read once.
pub fn read_gaussians_and_attributes(
    path: &Path,
    opts: &LoadOptions,
) -> Result<(io::GaussianCloud, Option<io::GaussianAttributes>), RunError> {
    let (cloud, attrs) = io::read_gaussians_and_attributes(path, &ply_options(opts)?)?;
    let attrs = attrs.filter(|a| a.normals.len() == cloud.centers.len());
    Ok((cloud, attrs))
}

fn ply_options(opts: &LoadOptions) -> Result<PlyOptions, RunError> {
    if let Some(o) = opts.min_opacity {
        if !(0.0..=1.0).contains(&o) {
            return Err(RunError::Input(format!(
                "--min-opacity {o}: expected an opacity in [0, 1]"
            )));
        }
    }
    Ok(PlyOptions {
        min_opacity: opts.min_opacity,
        strict: opts.strict,
    })
}

/// The Gaussian centers and the line segments of one scene, in memory, with what loading
/// them found (counts, drops, warnings).
#[derive(Clone, Debug)]
pub struct Scene {
    pub gaussians: Vec<[f32; 3]>,
    pub lines: LineSet,
    pub input: InputReport,
    /// One line each, for the user and the report.
    pub warnings: Vec<String>,
    /// Seconds spent reading the files (0 for arrays).
    pub load_seconds: f64,
    /// Each Gaussian's surface normal (its shortest axis; zero where it is not flat), in
    /// the order of `gaussians`, where the file has rotations and scales (the edge fit's
    /// corner test). Read by a second pass over the PLY.
    pub normals: Option<Vec<[f32; 3]>>,
    /// Each Gaussian's largest standard deviation (scene units), same order, where the
    /// file has scales (`--max-scale`).
    pub max_scale: Option<Vec<f32>>,
    /// Smallest standard deviation of each Gaussian (its thickness), where the file has
    /// scales.
    pub min_scale: Option<Vec<f32>>,
    /// Each Gaussian's opacity in `[0, 1]`, same order, where the file has rotations,
    /// scales and opacities (`--fit-opacity-weight`).
    pub opacity: Option<Vec<f32>>,
    /// What the scene is, when it was made rather than read (the demo's synthetic scene).
    pub description: Option<String>,
}

impl Scene {
    /// Reads the Gaussians (`point_cloud.ply` or any format of docs/formats.md) and the lines.
    pub fn load(gaussians: &Path, lines: &Path, opts: &LoadOptions) -> Result<Scene, RunError> {
        let t = Instant::now();
        // Normals for the edge fit (PLY with rotations and scales). A frame transform
        // would have to turn them too: with one, the edge fit uses the centers only.
        let (mut cloud, attrs) = read_gaussians_and_attributes(gaussians, opts)?;
        let (normals, max_scale, min_scale, opacity) = match attrs {
            // Opacities do not depend on the frame; normals would have to turn and scales
            // to scale with it: with a transform only the opacities are used.
            Some(a) if opts.transform.is_some() => (None, None, None, a.opacity),
            Some(a) => (
                Some(a.normals),
                Some(a.max_scale),
                Some(a.min_scale),
                a.opacity,
            ),
            None => (None, None, None, None),
        };
        if let Some(t) = &opts.transform {
            t.apply(&mut cloud.centers);
        }
        let file = io::read_lines_with(lines, &opts.lines)?;
        let mut warnings = cloud.warnings;
        warnings.extend(file.warnings);
        let input = InputReport {
            gaussians: Some(gaussians.display().to_string()),
            lines: Some(lines.display().to_string()),
            lines_format: Some(file.format.name().to_string()),
            gaussians_read: cloud.centers.len(),
            gaussians_nonfinite_skipped: cloud.skipped_nonfinite,
            gaussians_below_opacity: cloud.dropped_low_opacity,
            segments_read: file.lines.len(),
            segments_invalid_dropped: file.dropped_invalid,
            input_lines: file.lines.input_lines(),
            n_box: 0,
            gaussians_transform: opts.transform.as_ref().map(|t| t.describe.clone()),
        };
        Ok(Scene {
            gaussians: cloud.centers,
            lines: file.lines,
            input,
            warnings,
            load_seconds: t.elapsed().as_secs_f64(),
            normals,
            max_scale,
            min_scale,
            opacity,
            description: None,
        })
    }

    /// A scene from arrays (the Python package, synthetic scenes): Gaussians with a NaN
    /// or infinite center are skipped with a warning that counts them (docs/formats.md); segments
    /// with a NaN or infinite coordinate are an error; degenerate segments
    /// (`L <= 1e-12`) are dropped with a warning (docs/method.md#geometry).
    pub fn from_arrays(gaussians: Vec<[f32; 3]>, lines: LineSet) -> Result<Scene, RunError> {
        let mut warnings = Vec::new();
        let n_read = gaussians.len();
        let mut gaussians = gaussians;
        gaussians.retain(|c| c.iter().all(|v| v.is_finite()));
        let nonfinite = n_read - gaussians.len();
        if nonfinite > 0 {
            warnings.push(format!(
                "gaussians: skipped {nonfinite} Gaussian{} with a NaN or infinite center",
                if nonfinite == 1 { "" } else { "s" }
            ));
        }
        if gaussians.is_empty() {
            return Err(RunError::Input(
                "gaussians: the model holds no Gaussian with a finite center".into(),
            ));
        }
        if let Some(i) = lines
            .segments
            .iter()
            .position(|s| !(s.p1.is_finite() && s.p2.is_finite()))
        {
            return Err(RunError::Input(format!(
                "segments: segment {i} has a NaN or infinite coordinate"
            )));
        }
        let keep: Vec<usize> = (0..lines.len())
            .filter(|&i| lines.segments[i].length() > MIN_LENGTH)
            .collect();
        let dropped = lines.len() - keep.len();
        let lines = if dropped > 0 {
            warnings.push(format!(
                "segments: dropped {dropped} degenerate segment{} (length <= 1e-12)",
                if dropped == 1 { "" } else { "s" }
            ));
            lines.select(&keep)
        } else {
            lines
        };
        if lines.is_empty() {
            return Err(RunError::Input(
                "segments: no valid line segment (none given, or all of length <= 1e-12)".into(),
            ));
        }
        let input = InputReport {
            gaussians: None,
            lines: None,
            lines_format: None,
            gaussians_read: gaussians.len(),
            gaussians_nonfinite_skipped: nonfinite,
            gaussians_below_opacity: 0,
            segments_read: lines.len(),
            segments_invalid_dropped: dropped,
            input_lines: lines.input_lines(),
            n_box: 0,
            gaussians_transform: None,
        };
        Ok(Scene {
            gaussians,
            lines,
            input,
            warnings,
            load_seconds: 0.0,
            normals: None,
            max_scale: None,
            min_scale: None,
            opacity: None,
            description: None,
        })
    }
}

/// The grid cell of the working set: near the refinement radius, and not below half the
/// evaluation radius (so an evaluation cylinder spans few cells). One rule for refine and
/// eval, so that both build the same grid from the same parameters.
pub fn grid_cell(settings: &Settings) -> f64 {
    settings.radius().max(settings.eval().eval_radius * 0.5)
}

/// The built state of one run: the resolved settings and the engine over the grid of the
/// working set. Build it once; evaluate and refine as often as needed.
pub struct Refiner {
    settings: Settings,
    engine: Box<dyn Engine>,
    notes: Vec<String>,
    stages: Vec<Stage>,
    /// Per-Gaussian attributes of the working set for the edge fit (none by default).
    attrs: refine::fit::Attributes,
}

impl Refiner {
    /// Working set of the box of `segments` (docs/method.md#geometry), settings resolved
    /// over it, grid, and the engine of `backend` (a GPU engine opened the default way,
    /// [`GpuSetup::default`]).
    pub fn new(
        gaussians: &[[f32; 3]],
        segments: &[Segment],
        params: &Params,
        backend: Backend,
    ) -> Result<Refiner, RunError> {
        Refiner::with_setup(gaussians, segments, params, backend, &GpuSetup::default())
    }

    /// [`Refiner::new`] with a GPU engine opened as `gpu` says.
    pub fn with_setup(
        gaussians: &[[f32; 3]],
        segments: &[Segment],
        params: &Params,
        backend: Backend,
        gpu: &GpuSetup,
    ) -> Result<Refiner, RunError> {
        // The device opens (and its kernels compile) while the grid is built.
        let pending = prepare(backend, gpu);
        Refiner::with_engine(gaussians, segments, params, |grid| pending.finish(grid))
    }

    /// [`Refiner::new`] with an engine of the caller's making (tests: a GPU engine with
    /// particular options). `make` returns the engine and the notes to show the user.
    /// Every engine is wrapped in [`Dedup`], so that identical queries in a batch (copies
    /// of a segment) are answered once.
    pub fn with_engine(
        gaussians: &[[f32; 3]],
        segments: &[Segment],
        params: &Params,
        make: impl FnOnce(Arc<Grid>) -> Result<(Box<dyn Engine>, Vec<String>), EngineError>,
    ) -> Result<Refiner, RunError> {
        let t = Instant::now();
        let ws = WorkingSet::new(gaussians, segments);
        let settings = Settings::resolve(params.clone(), &ws.points).map_err(RunError::Input)?;
        let grid = Arc::new(Grid::build(&ws.points, ws.bounds, grid_cell(&settings)));
        drop(ws);
        let mut stages = vec![Stage::since("index", segments.len(), t)];
        let t = Instant::now();
        let (engine, notes) = make(grid)?;
        let engine: Box<dyn Engine> = Box::new(Dedup::new(engine));
        stages.push(Stage::since("engine", segments.len(), t));
        Ok(Refiner {
            settings,
            engine,
            notes,
            stages,
            attrs: refine::fit::Attributes::default(),
        })
    }

    pub fn settings(&self) -> &Settings {
        &self.settings
    }

    pub fn engine(&self) -> &dyn Engine {
        self.engine.as_ref()
    }

    /// What choosing the engine said (`auto`: which adapter, or why the CPU).
    pub fn notes(&self) -> &[String] {
        &self.notes
    }

    /// The stages of building it (index, engine).
    pub fn stages(&self) -> &[Stage] {
        &self.stages
    }

    /// `N_box`.
    pub fn n_box(&self) -> usize {
        self.engine.n_points()
    }

    /// The paper's metrics of `segments` at the evaluation radius (docs/method.md#evaluation).
    pub fn evaluate(&self, segments: &[Segment]) -> Result<Metrics, EngineError> {
        let s = &self.settings;
        eval::evaluate(self.engine(), segments, s.eval(), s.r_l(), None)
    }

    /// The metrics of `segments` at each radius.
    pub fn sweep(&self, segments: &[Segment], radii: &[f64]) -> Result<Vec<Metrics>, EngineError> {
        let s = &self.settings;
        eval::sweep(self.engine(), segments, s.eval(), s.r_l(), radii)
    }

    /// Gives the edge fit the Gaussians' `normals` (order of `gaussians`, the arrays this
    /// refiner was built from with `segments`); `false` when the counts differ.
    pub fn set_normals(
        &mut self,
        gaussians: &[[f32; 3]],
        normals: &[[f32; 3]],
        segments: &[Segment],
    ) -> bool {
        self.set_attributes(gaussians, Some(normals), None, segments)
    }

    /// Gives the edge fit the Gaussians' `normals` and `opacity` (each in the order of
    /// `gaussians`, the arrays this refiner was built from with `segments`); `false` (and
    /// nothing set) when a count differs.
    pub fn set_attributes(
        &mut self,
        gaussians: &[[f32; 3]],
        normals: Option<&[[f32; 3]]>,
        opacity: Option<&[f32]>,
        segments: &[Segment],
    ) -> bool {
        let n = self.n_box();
        let normals = match normals {
            Some(v) => match refine::fit::cut_to_working_set(gaussians, v, segments) {
                Some(w) if w.len() == n => Some(w),
                _ => return false,
            },
            None => None,
        };
        let opacity = match opacity {
            Some(v) => match refine::fit::cut_to_working_set(gaussians, v, segments) {
                Some(w) if w.len() == n => Some(w),
                _ => return false,
            },
            None => None,
        };
        let a = refine::fit::Attributes {
            normals,
            opacity,
            thickness: None,
        };
        self.attrs = a;
        true
    }

    /// Gives the move gate each Gaussian's thickness (smallest standard deviation, in the
    /// order of `gaussians`); `false` (and nothing set) when the count differs.
    pub fn set_thickness(
        &mut self,
        gaussians: &[[f32; 3]],
        thickness: &[f32],
        segments: &[Segment],
    ) -> bool {
        match refine::fit::cut_to_working_set(gaussians, thickness, segments) {
            Some(w) if w.len() == self.n_box() => {
                self.attrs.thickness = Some(w);
                true
            }
            _ => false,
        }
    }

    /// Before-evaluation, the steps of docs/method.md#the-refinement-steps and
    /// after-evaluation, calling `on_stage` after each stage.
    pub fn refine(
        &self,
        lines: &LineSet,
        mut on_stage: impl FnMut(&Stage),
    ) -> Result<Refined, RunError> {
        let mut stages = Vec::new();
        // The engine's clocks (GPU engine) split each stage into host and device time.
        let mut clock = self.engine().seconds();
        let mut push = |mut s: Stage, stages: &mut Vec<Stage>| {
            let now = self.engine().seconds();
            if let (Some(a), Some(b)) = (clock, now) {
                s.host_seconds = Some(b.0 - a.0);
                s.device_seconds = Some(b.1 - a.1);
            }
            clock = now;
            on_stage(&s);
            stages.push(s);
        };
        let t = Instant::now();
        let before = self.evaluate(&lines.segments)?;
        push(Stage::since("evaluate_before", lines.len(), t), &mut stages);
        let (refined, steps) = refine::run_steps_noted(
            self.engine(),
            lines,
            &self.attrs,
            &self.settings,
            |name, n, t| push(Stage::since(name, n, t), &mut stages),
        )?;
        let t = Instant::now();
        let after = self.evaluate(&refined.segments)?;
        push(
            Stage::since("evaluate_after", refined.len(), t),
            &mut stages,
        );
        Ok(Refined {
            lines: refined,
            before,
            after,
            stages,
            steps,
        })
    }
}

/// What [`Refiner::refine`] produced.
#[derive(Clone, Debug)]
pub struct Refined {
    pub lines: LineSet,
    pub before: Metrics,
    pub after: Metrics,
    pub stages: Vec<Stage>,
    /// Step 4's shifts, the edge fit's counts and segment length per stage.
    pub steps: refine::StepNotes,
}

/// One run's parameters and what to measure beyond the paper's metrics.
#[derive(Clone, Debug, Default)]
pub struct Job {
    pub params: Params,
    pub backend: Backend,
    /// How the GPU engine opens (adapter, options): the commands read it from their
    /// environment; the default is [`GpuSetup::default`].
    pub gpu: GpuSetup,
    /// The paper's radius sweep: metrics at each of these radii, before and after.
    pub sweep: Option<Vec<f64>>,
    /// Ground-truth edges and the protocol of the ABC-NEF metrics (same frame as the
    /// lines).
    pub gt: Option<gt::Reference>,
    /// Check that the lines and the Gaussians share a frame ([`crate::frames`]): `refine`
    /// stops with [`RunError::FrameMismatch`] when they are different (almost no segment
    /// has a Gaussian center within `r`, or most have none and the boxes disagree) and
    /// adds a warning to the report when they are doubtful; `evaluate` warns in both cases.
    pub check_frames: bool,
}

/// A refinement's segments and its report.
#[derive(Clone, Debug)]
pub struct Outcome {
    pub lines: LineSet,
    pub report: Report,
}

/// `--max-scale`'s scene and what it did: how many Gaussians were left out, or why none.
type ScaleCut = (Scene, Result<usize, String>);

impl Job {
    /// The job with `params` on `backend`, nothing extra.
    pub fn new(params: Params, backend: Backend) -> Job {
        Job {
            params,
            backend,
            ..Job::default()
        }
    }

    /// The engine for `scene`, built once.
    pub fn refiner(&self, scene: &Scene) -> Result<Refiner, RunError> {
        Refiner::with_setup(
            &scene.gaussians,
            &scene.lines.segments,
            &self.params,
            self.backend,
            &self.gpu,
        )
    }

    /// `--max-scale`: `scene` without the Gaussians whose largest standard deviation
    /// exceeds `max_scale x r`, with how many were left out, or a warning when the model
    /// has no scales; `None` when the option is off.
    fn scale_cut(&self, scene: &Scene) -> Result<Option<ScaleCut>, RunError> {
        let k = self.params.max_scale();
        if k <= 0.0 {
            return Ok(None);
        }
        let Some(sc) = &scene.max_scale else {
            // Not a warning when the user did not ask: most models carry no scales.
            if self.params.max_scale.is_none() {
                return Ok(None);
            }
            return Ok(Some((
                scene.clone(),
                Err(format!(
                    "--max-scale {k}: the Gaussians carry no scales (or a frame transform is \
                     given); nothing was left out"
                )),
            )));
        };
        let r = match self.params.radius {
            RadiusArg::Fixed(r) => r,
            RadiusArg::Auto => {
                let ws = crate::index::WorkingSet::new(&scene.gaussians, &scene.lines.segments);
                Settings::resolve(self.params.clone(), &ws.points)
                    .map_err(RunError::Input)?
                    .radius()
            }
        };
        let limit = k * r;
        let keep: Vec<bool> = sc.iter().map(|&s| f64::from(s) <= limit).collect();
        fn pick_of<T: Copy>(v: &[T], keep: &[bool]) -> Vec<T> {
            v.iter()
                .zip(keep)
                .filter(|(_, &k)| k)
                .map(|(x, _)| *x)
                .collect()
        }
        let pick = |v: &[[f32; 3]]| pick_of(v, &keep);
        let gaussians = pick(&scene.gaussians);
        let cut = scene.gaussians.len() - gaussians.len();
        if gaussians.is_empty() {
            return Ok(Some((
                scene.clone(),
                Err(format!(
                    "--max-scale {k}: every Gaussian is wider than {limit} (largest standard \
                     deviation); none was left out"
                )),
            )));
        }
        let out = Scene {
            gaussians,
            normals: scene.normals.as_deref().map(pick),
            max_scale: Some(pick_of(sc, &keep)),
            min_scale: scene.min_scale.as_deref().map(|v| pick_of(v, &keep)),
            opacity: scene.opacity.as_deref().map(|o| pick_of(o, &keep)),
            lines: scene.lines.clone(),
            input: scene.input.clone(),
            warnings: scene.warnings.clone(),
            load_seconds: scene.load_seconds,
            description: scene.description.clone(),
        };
        Ok(Some((out, Ok(cut))))
    }

    /// Refines `scene` (docs/method.md#the-refinement-steps) and reports
    /// (docs/formats.md#the-report).
    pub fn refine(&self, scene: &Scene, on_stage: impl FnMut(&Stage)) -> Result<Outcome, RunError> {
        let t = Instant::now();
        let whole = scene;
        let cut = self.scale_cut(scene)?;
        let (scene, cut_note) = match &cut {
            Some((s, n)) => (s, Some(n.clone())),
            None => (scene, None),
        };
        let mut refiner = self.refiner(scene)?;
        let frame_warning =
            match self.frame_mismatch(scene, &refiner, refiner.settings().radius())? {
                Some((crate::frames::FrameVerdict::Different, msg)) => {
                    return Err(RunError::FrameMismatch(msg))
                }
                Some((_, msg)) => Some(msg),
                None => None,
            };
        let mut normals_unused = false;
        if scene.normals.is_some() || scene.opacity.is_some() {
            normals_unused = !refiner.set_attributes(
                &scene.gaussians,
                scene.normals.as_deref(),
                scene.opacity.as_deref(),
                &scene.lines.segments,
            );
            if let Some(th) = &scene.min_scale {
                normals_unused |=
                    !refiner.set_thickness(&scene.gaussians, th, &scene.lines.segments);
            }
        }
        let mut out = refiner.refine(&scene.lines, on_stage)?;
        let mut n_box = refiner.n_box();
        // The scale cut serves the steps; the metrics are the whole model's, as `eval`
        // measures them (one more grid over the uncut working set).
        let measured = match &cut_note {
            Some(Ok(n)) if *n > 0 => {
                let m = self.refiner(whole)?;
                out.before = m.evaluate(&whole.lines.segments)?;
                out.after = m.evaluate(&out.lines.segments)?;
                n_box = m.n_box();
                Some(m)
            }
            _ => None,
        };
        let sweep = self.sweep_of(
            measured.as_ref().unwrap_or(&refiner),
            &scene.lines.segments,
            Some(&out.lines.segments),
        )?;
        let ground_truth = self.gt.as_ref().map(|g| GroundTruth {
            before: g.measure(&scene.lines.segments),
            after: Some(g.measure(&out.lines.segments)),
        });
        let mut report = Report::new("refine", scene, &refiner, out.before);
        report.warnings.extend(frame_warning);
        report.input.n_box = n_box;
        report.stages.extend(out.stages);
        report.after = Some(out.after);
        if normals_unused {
            report
                .warnings
                .push("the Gaussians' normals did not line up with their centers; the edge fit uses the centers only".into());
        }
        report.warnings.extend(out.steps.warnings.iter().cloned());
        let mut steps = out.steps;
        match cut_note {
            Some(Ok(n)) => steps.scale_cut = Some(n),
            Some(Err(w)) => report.warnings.push(w),
            None => {}
        }
        report.refine = Some(steps);
        report.sweep = sweep;
        report.ground_truth = ground_truth;
        report.engine_counters = Some(refiner.engine().counters());
        report.total_seconds = scene.load_seconds + t.elapsed().as_secs_f64();
        Ok(Outcome {
            lines: out.lines,
            report,
        })
    }

    /// Measures `scene`'s lines, and `compare` beside them on the same working set (the
    /// box of the scene's lines), with the same grid rule as [`Job::refine`]. In the
    /// report, `before` is the scene's lines and `after` is `compare` (null without).
    pub fn evaluate(&self, scene: &Scene, compare: Option<&LineSet>) -> Result<Report, RunError> {
        let t = Instant::now();
        let refiner = self.refiner(scene)?;
        let radius = self
            .sweep
            .iter()
            .flatten()
            .copied()
            .fold(refiner.settings().eval().eval_radius, f64::min);
        let mismatch = self.frame_mismatch(scene, &refiner, radius)?;
        let t_eval = Instant::now();
        let before = refiner.evaluate(&scene.lines.segments)?;
        let after = match compare {
            Some(c) => Some(refiner.evaluate(&c.segments)?),
            None => None,
        };
        let sweep = self.sweep_of(
            &refiner,
            &scene.lines.segments,
            compare.map(|c| &c.segments[..]),
        )?;
        let ground_truth = self.gt.as_ref().map(|g| GroundTruth {
            before: g.measure(&scene.lines.segments),
            after: compare.map(|c| g.measure(&c.segments)),
        });
        let mut report = Report::new("eval", scene, &refiner, before);
        report.warnings.extend(mismatch.map(|(_, msg)| msg));
        report.stages.push(Stage::since(
            "evaluate",
            scene.lines.len() + compare.map_or(0, |c| c.len()),
            t_eval,
        ));
        report.after = after;
        report.sweep = sweep;
        report.ground_truth = ground_truth;
        report.engine_counters = Some(refiner.engine().counters());
        report.total_seconds = scene.load_seconds + t.elapsed().as_secs_f64();
        Ok(report)
    }

    /// With `check_frames`, the verdict and the message when the scene's lines and
    /// Gaussians may not share a frame ([`crate::frames`]; one batch of count queries at
    /// `radius`); `None` when they do.
    fn frame_mismatch(
        &self,
        scene: &Scene,
        refiner: &Refiner,
        radius: f64,
    ) -> Result<Option<(crate::frames::FrameVerdict, String)>, RunError> {
        if !self.check_frames {
            return Ok(None);
        }
        let fc = crate::frames::check_frames(
            refiner.engine(),
            &scene.lines.segments,
            radius,
            &scene.gaussians,
        )?;
        let verdict = fc.verdict();
        Ok((verdict != crate::frames::FrameVerdict::Same).then(|| {
            let name = |p: &Option<String>, what: &str| p.clone().unwrap_or_else(|| what.into());
            let msg = format!(
                "{} and {}: {}",
                name(&scene.input.lines, "the lines"),
                name(&scene.input.gaussians, "the Gaussians"),
                fc.message()
            );
            (verdict, msg)
        }))
    }

    fn sweep_of(
        &self,
        refiner: &Refiner,
        before: &[Segment],
        after: Option<&[Segment]>,
    ) -> Result<Option<Sweep>, RunError> {
        let Some(radii) = &self.sweep else {
            return Ok(None);
        };
        Ok(Some(Sweep {
            radii: radii.clone(),
            before: refiner.sweep(before, radii)?,
            after: match after {
                Some(a) => Some(refiner.sweep(a, radii)?),
                None => None,
            },
        }))
    }
}

/// Where a refinement's files go.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Outputs {
    /// The refined segments; the format follows the extension.
    pub lines: PathBuf,
    /// The JSON report.
    pub report: Option<PathBuf>,
    /// A PLY with the input (red) and refined (blue) segments as coloured edges.
    pub compare_ply: Option<PathBuf>,
}

/// Makes `out` a result the readers accept: zero-length segments (which f64 rounding can
/// make of a scene far from the origin, or a refinement can leave) are dropped with a
/// warning, and a result with no segment is an error that says why, before any file is
/// written.
fn readable_result(input: &LineSet, out: &mut Outcome) -> Result<(), RunError> {
    let keep: Vec<usize> = (0..out.lines.len())
        .filter(|&k| out.lines.segments[k].is_valid())
        .collect();
    let (mut lo, mut hi) = (
        glam::DVec3::splat(f64::INFINITY),
        glam::DVec3::splat(f64::NEG_INFINITY),
    );
    for s in input.segments.iter().filter(|s| s.is_valid()) {
        lo = lo.min(s.p1).min(s.p2);
        hi = hi.max(s.p1).max(s.p2);
    }
    let (far, size) = (
        lo.abs().max(hi.abs()).max_element(),
        (hi - lo).max_element(),
    );
    let hint = if far.is_finite() && far > 1e5 * size.max(f64::MIN_POSITIVE) {
        format!(
            "; the scene lies {far:.3e} from the origin and is {size:.3e} across, where the model's f32 centers cannot resolve it: recentre the lines and the model near the origin (subtract the scene's center from both)"
        )
    } else {
        String::new()
    };
    if keep.len() < out.lines.len() {
        let msg = format!(
            "{} of {} refined segments have zero length and were left out of the output{hint}",
            out.lines.len() - keep.len(),
            out.lines.len()
        );
        match &mut out.report.refine {
            Some(steps) => steps.warnings.push(msg),
            None => out.report.warnings.push(msg),
        }
        out.lines = out.lines.select(&keep);
    }
    if out.lines.is_empty() {
        return Err(RunError::Input(format!(
            "no segment is left after refinement ({} in the input){}; nothing was written",
            input.len(),
            if hint.is_empty() {
                " (see the stages' counts with --verbose: the outlier step, --outlier-ratio, drops the segments with the fewest Gaussians)"
                    .to_string()
            } else {
                hint
            }
        )));
    }
    Ok(())
}

/// Colours of the input and refined layers in comparison files.
pub const BEFORE_COLOR: [u8; 3] = [220, 50, 40];
pub const AFTER_COLOR: [u8; 3] = [30, 90, 220];

impl Outputs {
    /// Checks every output path before any work, so a typo or a collision costs nothing:
    /// extensions, folders, and that no output is one of `inputs` or another output
    /// ([`io::OutputSet::check`]).
    pub fn check(&self, inputs: &[&Path]) -> Result<(), RunError> {
        let mut set = io::OutputSet::new();
        for p in inputs {
            set.input(p);
        }
        set.output("-o", &self.lines, &io::LINE_OUTPUTS);
        if let Some(p) = &self.report {
            set.output("--report", p, &["json"]);
        }
        if let Some(p) = &self.compare_ply {
            set.output("--compare-ply", p, &["ply"]);
        }
        set.check()?;
        Ok(())
    }

    /// Writes the refined lines, the comparison PLY and the report (each atomically), the
    /// report last and with the `write` stage and the output path in it.
    pub fn write(&self, input: &LineSet, out: &mut Outcome) -> Result<(), RunError> {
        // All of them land together or none does: a failure leaves earlier files as they were.
        let mut set = io::OutputSet::new();
        self.stage(&mut set, input, out)?;
        set.commit()?;
        Ok(())
    }

    /// Like [`Outputs::write`], into `set`: nothing lands until the caller commits it
    /// (with its own files, as one transaction).
    pub fn stage(
        &self,
        set: &mut io::OutputSet,
        input: &LineSet,
        out: &mut Outcome,
    ) -> Result<(), RunError> {
        readable_result(input, out)?;
        let t = Instant::now();
        set.write(&self.lines, |p| io::write_lines(p, &out.lines.segments))?;
        if let Some(cp) = &self.compare_ply {
            set.write(cp, |p| {
                io::write_lines_ply_layers(
                    p,
                    &[
                        (&input.segments[..], BEFORE_COLOR),
                        (&out.lines.segments[..], AFTER_COLOR),
                    ],
                )
            })?;
        }
        let write = Stage::since("write", out.lines.len(), t);
        out.report.total_seconds += write.seconds;
        out.report.stages.push(write);
        out.report.output = Some(self.lines.display().to_string());
        if let Some(rp) = &self.report {
            let json = out.report.to_json();
            set.write(rp, |p| io::write_bytes_atomic(p, json.as_bytes()))?;
        }
        Ok(())
    }
}
