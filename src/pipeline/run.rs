//! A [`Job`] run on a [`Scene`]: the [`Refiner`] (working set, settings, grid, engine)
//! built once, the steps and the evaluations, one report.

use super::{RunError, Scene, Stage};
use crate::engine::dedup::Dedup;
use crate::engine::gpu::GpuSetup;
use crate::engine::select::{prepare, Backend, Pending};
use crate::engine::{Engine, EngineError};
use crate::eval::{self, gt, Metrics};
use crate::geom::{LineSet, Segment};
use crate::index::{Grid, WorkingSet};
use crate::refine::{self, Params, RadiusArg, Settings};
use crate::report::{GroundTruth, InputReport, Report, Sweep};
use std::sync::Arc;
use std::time::Instant;

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
    /// The engine and attributes of the Gaussians that place lines, when they are not
    /// this refiner's (`--max-scale`): see [`refine::run_steps_noted`].
    placement: Option<Box<Refiner>>,
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
        // Only the CPU engine will read the grid: it may have the finer cells of
        // `Grid::build_for_host` (scenes above 10^7 Gaussians).
        let host = backend == Backend::Cpu;
        Refiner::build(gaussians, segments, params, host, |grid| {
            pending.finish(grid)
        })
    }

    /// [`Refiner::with_setup`] on the device `pending` opens (or opened for an engine
    /// before: the same device, nothing opened again).
    pub fn with_pending(
        gaussians: &[[f32; 3]],
        segments: &[Segment],
        params: &Params,
        backend: Backend,
        pending: &mut Pending,
    ) -> Result<Refiner, RunError> {
        let host = backend == Backend::Cpu;
        Refiner::build(gaussians, segments, params, host, |grid| {
            pending.engine(grid)
        })
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
        Refiner::build(gaussians, segments, params, false, make)
    }

    /// [`Refiner::with_engine`]; `host`: the grid is for the CPU engine alone.
    fn build(
        gaussians: &[[f32; 3]],
        segments: &[Segment],
        params: &Params,
        host: bool,
        make: impl FnOnce(Arc<Grid>) -> Result<(Box<dyn Engine>, Vec<String>), EngineError>,
    ) -> Result<Refiner, RunError> {
        let t = Instant::now();
        let ws = WorkingSet::new(gaussians, segments);
        let settings = Settings::resolve(params.clone(), &ws.points)
            .map_err(|e| RunError::Input(e.to_string()))?;
        let cell = grid_cell(&settings);
        let grid = Arc::new(if host {
            Grid::build_for_host(&ws.points, ws.bounds, cell)
        } else {
            Grid::build(&ws.points, ws.bounds, cell)
        });
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
            placement: None,
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
            Some(v) => match self.cut(gaussians, v, segments) {
                Some(w) if w.len() == n => Some(w),
                _ => return false,
            },
            None => None,
        };
        let opacity = match opacity {
            Some(v) => match self.cut(gaussians, v, segments) {
                Some(w) if w.len() == n => Some(w),
                _ => return false,
            },
            None => None,
        };
        let a = refine::fit::Attributes {
            normals,
            opacity,
            extent: None,
            colour: None,
        };
        self.attrs = a;
        true
    }

    /// `values` (one per center of `gaussians`, the centers this refiner was built from
    /// with `segments`) cut to the working set, as [`refine::fit::cut_to_working_set`]
    /// does. When every center is in the working set the cut keeps everything: a copy,
    /// without testing each center against the box again (four passes over the model
    /// otherwise, for the normals, opacities, extents and colours).
    fn cut<T: Copy>(
        &self,
        gaussians: &[[f32; 3]],
        values: &[T],
        segments: &[Segment],
    ) -> Option<Vec<T>> {
        if values.len() != gaussians.len() {
            return None;
        }
        if gaussians.len() == self.n_box() {
            return Some(values.to_vec());
        }
        refine::fit::cut_to_working_set(gaussians, values, segments)
    }

    /// Gives the decision rule each Gaussian's extent (largest standard deviation, in the
    /// order of `gaussians`); `false` (and nothing set) when the count differs.
    pub fn set_extent(
        &mut self,
        gaussians: &[[f32; 3]],
        extent: &[f32],
        segments: &[Segment],
    ) -> bool {
        match self.cut(gaussians, extent, segments) {
            Some(w) if w.len() == self.n_box() => {
                self.attrs.extent = Some(w);
                true
            }
            _ => false,
        }
    }

    /// Gives the decision rule each Gaussian's base colour (in the order of `gaussians`);
    /// `false` (and nothing set) when the count differs.
    pub fn set_colour(
        &mut self,
        gaussians: &[[f32; 3]],
        colour: &[[f32; 3]],
        segments: &[Segment],
    ) -> bool {
        match self.cut(gaussians, colour, segments) {
            Some(w) if w.len() == self.n_box() => {
                self.attrs.colour = Some(w);
                true
            }
            _ => false,
        }
    }

    /// Gives `scene`'s attributes (normals, opacity, extent, colour) to the edge fit; `true`
    /// when the model had some that did not line up with its centers (they are not used).
    pub fn set_scene_attributes(&mut self, scene: &Scene) -> bool {
        let mut unused = false;
        if scene.normals.is_some() || scene.opacity.is_some() {
            let (g, l) = (&scene.gaussians, &scene.lines.segments);
            unused = !self.set_attributes(g, scene.normals.as_deref(), scene.opacity.as_deref(), l);
            if let Some(ex) = &scene.max_scale {
                unused |= !self.set_extent(g, ex, l);
            }
            if let Some(c) = &scene.colour {
                unused |= !self.set_colour(g, c, l);
            }
        }
        unused
    }

    /// Lets `placer` (built over a subset of this refiner's Gaussians, with the same
    /// settings, and given its attributes) answer the steps that place lines.
    pub fn set_placement(&mut self, placer: Refiner) {
        self.placement = Some(Box::new(placer));
    }

    /// The work counters of this refiner's engine and of its placement engine, if any.
    pub fn counters(&self) -> crate::engine::Counters {
        let mut c = self.engine().counters();
        if let Some(p) = &self.placement {
            c += p.engine().counters();
        }
        c
    }

    /// Before-evaluation, the steps of docs/method.md#the-refinement-steps and
    /// after-evaluation, calling `on_stage` after each stage.
    pub fn refine(
        &self,
        lines: &LineSet,
        mut on_stage: impl FnMut(&Stage),
    ) -> Result<Refined, RunError> {
        let mut stages = Vec::new();
        // The engine's clocks (GPU engine) split each stage into host and device time, and
        // its counters give the device's work in it.
        let mut clock = self.engine().seconds();
        let mut work = self.engine().counters();
        let mut push = |mut s: Stage, stages: &mut Vec<Stage>| {
            let now = self.engine().seconds();
            let done = self.engine().counters();
            if let (Some(a), Some(b)) = (clock, now) {
                s.host_seconds = Some(b.0 - a.0);
                s.device_seconds = Some(b.1 - a.1);
                s.device_items = Some(done.device_items - work.device_items);
                s.point_bytes = Some(done.point_bytes - work.point_bytes);
                s.host_lists = Some(done.host_lists - work.host_lists);
            }
            (clock, work) = (now, done);
            on_stage(&s);
            stages.push(s);
        };
        let t = Instant::now();
        let before = self.evaluate(&lines.segments)?;
        push(Stage::since("evaluate_before", lines.len(), t), &mut stages);
        let place = self.placement.as_deref().unwrap_or(self);
        let (refined, steps, sources) = refine::run_steps_traced(
            self.engine(),
            (place.engine(), &place.attrs),
            lines,
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
            sources,
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
    /// For each output segment, the indices into the input `lines` of the segments it
    /// came from ([`refine::run_steps_traced`]).
    pub sources: Vec<Vec<u32>>,
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
    /// Provenance: for each segment of `lines`, the 0-based indices of the input
    /// segments it came from, in the input file's order (increasing).
    pub sources: Vec<Vec<u32>>,
}

/// `--max-scale`'s scene (only where it left some Gaussians out) and what it did: how
/// many Gaussians were left out, or why none.
type ScaleCut = (Option<Scene>, Result<usize, ScaleCutWarning>);

/// Why `--max-scale` left no Gaussian out (a warning of the report).
#[derive(Clone, Debug, thiserror::Error)]
enum ScaleCutWarning {
    #[error(
        "--max-scale {k}: the Gaussians carry no scales (or a frame transform is given); \
         nothing was left out"
    )]
    NoScales { k: f64 },
    #[error(
        "--max-scale {k}: every Gaussian is wider than {limit} (largest standard deviation); \
         none was left out"
    )]
    AllWider { k: f64, limit: f64 },
}

/// The parts every report shares: tool, engine, settings, input, the stages so far
/// (load, index, engine) and the input's metrics.
fn new_report(command: &str, scene: &Scene, r: &Refiner, before: Metrics) -> Report {
    let s = r.settings();
    let mut stages = Vec::new();
    if scene.input.gaussians.is_some() {
        stages.push(Stage {
            name: "load".into(),
            segments: scene.lines.len(),
            seconds: scene.load_seconds,
            host_seconds: None,
            device_seconds: None,
            device_items: None,
            point_bytes: None,
            host_lists: None,
        });
    }
    stages.extend(r.stages().iter().cloned());
    Report {
        tool: "linegs-gpu".into(),
        version: env!("CARGO_PKG_VERSION").into(),
        command: command.into(),
        backend: r.engine().backend().into(),
        adapter: r.engine().adapter(),
        profile: s.params().profile,
        params: s.params().clone(),
        fixes: *s.fixes(),
        radius: s.radius(),
        input: InputReport {
            n_box: r.n_box(),
            ..scene.input.clone()
        },
        output: None,
        stages,
        total_seconds: 0.0,
        before,
        after: None,
        sweep: None,
        ground_truth: None,
        refine: None,
        scene: scene.description.clone(),
        notes: r.notes().to_vec(),
        engine_counters: None,
        warnings: scene.warnings.clone(),
        sources: None,
    }
}

impl Job {
    /// The job with `params` on `backend`, nothing extra.
    pub fn new(params: Params, backend: Backend) -> Job {
        Job {
            params,
            backend,
            ..Job::default()
        }
    }

    /// [`Job::refiner`] on the device of `pending`.
    fn refiner_on(&self, scene: &Scene, pending: &mut Pending) -> Result<Refiner, RunError> {
        Refiner::with_pending(
            &scene.gaussians,
            &scene.lines.segments,
            &self.params,
            self.backend,
            pending,
        )
    }

    /// The engine for `scene`, built once, on a device of its own.
    pub fn refiner(&self, scene: &Scene) -> Result<Refiner, RunError> {
        self.refiner_on(scene, &mut self.open())
    }

    /// `--max-scale`: `scene` without the Gaussians whose largest standard deviation
    /// exceeds `max_scale x r`, with how many were left out, or a warning when the model
    /// has no scales; `None` when the option is off.
    fn scale_cut(&self, scene: &Scene) -> Result<Option<ScaleCut>, RunError> {
        let k = self.params.fit.max_scale_for(self.params.profile);
        if k <= 0.0 {
            return Ok(None);
        }
        let Some(sc) = &scene.max_scale else {
            // Not a warning when the user did not ask: most models carry no scales.
            if self.params.fit.max_scale.is_none() {
                return Ok(None);
            }
            return Ok(Some((None, Err(ScaleCutWarning::NoScales { k }))));
        };
        let r = match self.params.radius {
            RadiusArg::Fixed(r) => r,
            RadiusArg::Auto => {
                let ws = crate::index::WorkingSet::new(&scene.gaussians, &scene.lines.segments);
                Settings::resolve(self.params.clone(), &ws.points)
                    .map_err(|e| RunError::Input(e.to_string()))?
                    .radius()
            }
        };
        let limit = k * r;
        let keep: Vec<bool> = sc.iter().map(|&s| f64::from(s) <= limit).collect();
        let kept = keep.iter().filter(|&&k| k).count();
        let cut = keep.len() - kept;
        if cut == 0 {
            // Nothing to leave out: no copy of the scene.
            return Ok(Some((None, Ok(0))));
        }
        if kept == 0 {
            return Ok(Some((None, Err(ScaleCutWarning::AllWider { k, limit }))));
        }
        fn pick_of<T: Copy>(v: &[T], keep: &[bool]) -> Vec<T> {
            v.iter()
                .zip(keep)
                .filter(|(_, &k)| k)
                .map(|(x, _)| *x)
                .collect()
        }
        let pick = |v: &[[f32; 3]]| pick_of(v, &keep);
        let gaussians = pick(&scene.gaussians);
        let out = Scene {
            gaussians,
            normals: scene.normals.as_deref().map(pick),
            max_scale: Some(pick_of(sc, &keep)),
            min_scale: scene.min_scale.as_deref().map(|v| pick_of(v, &keep)),
            opacity: scene.opacity.as_deref().map(|o| pick_of(o, &keep)),
            colour: scene.colour.as_deref().map(|c| pick_of(c, &keep)),
            lines: scene.lines.clone(),
            input: scene.input.clone(),
            warnings: scene.warnings.clone(),
            load_seconds: scene.load_seconds,
            description: scene.description.clone(),
        };
        Ok(Some((Some(out), Ok(cut))))
    }

    /// Refines `scene` (docs/method.md#the-refinement-steps) and reports
    /// (docs/formats.md#the-report).
    pub fn refine(&self, scene: &Scene, on_stage: impl FnMut(&Stage)) -> Result<Outcome, RunError> {
        self.refine_on(scene, &mut self.open(), on_stage)
    }

    /// Starts opening this job's device (the GPU engine's adapter, device and kernels; for
    /// the CPU engine nothing) on a thread of its own, for [`Job::refine_on`]: called before
    /// the scene is read, the opening runs while the files are parsed.
    pub fn open(&self) -> Pending {
        prepare(self.backend, &self.gpu)
    }

    /// [`Job::refine`] on the device `pending` opens ([`Job::open`]), or opened for an
    /// earlier engine (`batch`: one device for every scene).
    pub fn refine_on(
        &self,
        scene: &Scene,
        pending: &mut Pending,
        on_stage: impl FnMut(&Stage),
    ) -> Result<Outcome, RunError> {
        let t = Instant::now();
        let cut = self.scale_cut(scene)?;
        let (placing, cut_note) = match cut {
            Some((s, n)) => (s, Some(n)),
            None => (None, None),
        };
        // The whole model witnesses the lines (outliers, merges, crop, gaps, the metrics
        // as `eval` measures them); the scale cut's Gaussians place them (the edge fit).
        // Both engines run on one device, opened once.
        let mut refiner = self.refiner_on(scene, pending)?;
        let frame_warning =
            match self.frame_mismatch(scene, &refiner, refiner.settings().radius())? {
                Some((crate::frames::FrameVerdict::Different, msg)) => {
                    return Err(RunError::FrameMismatch(msg))
                }
                Some((_, msg)) => Some(msg),
                None => None,
            };
        let normals_unused = match &placing {
            Some(placing) => {
                let mut placer = self.refiner_on(placing, pending)?;
                let unused = placer.set_scene_attributes(placing);
                refiner.set_placement(placer);
                unused
            }
            None => refiner.set_scene_attributes(scene),
        };
        let out = refiner.refine(&scene.lines, on_stage)?;
        let n_box = refiner.n_box();
        let sweep = self.sweep_of(&refiner, &scene.lines.segments, Some(&out.lines.segments))?;
        let ground_truth = self.gt.as_ref().map(|g| GroundTruth {
            before: g.measure(&scene.lines.segments),
            after: Some(g.measure(&out.lines.segments)),
        });
        let mut report = new_report("refine", scene, &refiner, out.before);
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
            Some(Err(w)) => report.warnings.push(w.to_string()),
            None => {}
        }
        report.refine = Some(steps);
        report.sweep = sweep;
        report.ground_truth = ground_truth;
        report.engine_counters = Some(refiner.counters());
        report.total_seconds = scene.load_seconds + t.elapsed().as_secs_f64();
        // Indices in the file's order (degenerate segments dropped on reading count).
        let sources = match &scene.input.file_index {
            Some(f) => out
                .sources
                .iter()
                .map(|v| v.iter().map(|&i| f[i as usize]).collect())
                .collect(),
            None => out.sources,
        };
        Ok(Outcome {
            lines: out.lines,
            report,
            sources,
        })
    }

    /// Measures `scene`'s lines, and `compare` beside them on the same working set (the
    /// box of the scene's lines), with the same grid rule as [`Job::refine`]. In the
    /// report, `before` is the scene's lines and `after` is `compare` (null without).
    pub fn evaluate(&self, scene: &Scene, compare: Option<&LineSet>) -> Result<Report, RunError> {
        self.evaluate_on(scene, compare, &mut self.open())
    }

    /// [`Job::evaluate`] on the device `pending` opens ([`Job::open`]), or opened for an
    /// earlier engine (the Python binding: one device for the calls of a process).
    pub fn evaluate_on(
        &self,
        scene: &Scene,
        compare: Option<&LineSet>,
        pending: &mut Pending,
    ) -> Result<Report, RunError> {
        let t = Instant::now();
        let refiner = self.refiner_on(scene, pending)?;
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
        let mut report = new_report("eval", scene, &refiner, before);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::refine::Fit;

    fn job() -> Job {
        let params = {
            let mut q = Params::default();
            q.fit.fit = Some(Fit::Paper);
            q
        };
        Job::new(params, Backend::Cpu)
    }

    #[test]
    fn a_job_moves_the_segment_onto_its_gaussians_and_reports_it() {
        let scene = super::super::axis_scene();
        let out = job().refine(&scene, |_| {}).unwrap();
        assert_eq!(out.lines.len(), 1);
        let s = out.lines.segments[0];
        // The translate step moves it by the mean offset of its nearest points: onto y = 0.
        assert!(s.p1.y.abs() < 1e-6 && s.p2.y.abs() < 1e-6, "{s:?}");
        assert!(s.length() > 0.9, "{s:?}");
        let r = &out.report;
        assert_eq!((r.command.as_str(), r.backend.as_str()), ("refine", "cpu"));
        assert_eq!(r.input.n_box, 1000);
        assert_eq!(r.before.points_in_cylinders, 1000);
        assert_eq!(r.after.as_ref().unwrap().points_in_cylinders, 1000);
        assert!(r.stages.iter().any(|st| st.name == "index"));
        // Evaluating the same lines measures what the refinement measured before.
        let eval = job().evaluate(&scene, None).unwrap();
        assert_eq!(eval.before, r.before);
        assert!(eval.after.is_none());
    }

    #[test]
    fn attributes_are_cut_to_the_working_set_whether_or_not_it_holds_every_center() {
        // Centers along x from -1.995 to 1.995 and a segment from 0 to 1: the working box
        // (grown by 0.1 of its longest edge) keeps x in [-0.1, 1.1] only; with the segment
        // from -2 to 2 it keeps them all. Each attribute is its center's x.
        let centers: Vec<[f32; 3]> = (0..400)
            .map(|i| [i as f32 / 100.0 - 1.995, 0.0, 0.0])
            .collect();
        let xs: Vec<f32> = centers.iter().map(|c| c[0]).collect();
        let normals: Vec<[f32; 3]> = xs.iter().map(|&x| [x, 1.0, 0.0]).collect();
        let colour: Vec<[f32; 3]> = xs.iter().map(|&x| [0.0, 0.0, x]).collect();
        for (a, b, n) in [(0.0, 1.0, 120), (-2.0, 2.0, 400)] {
            let segs = [Segment::from_arrays([a, 0.0, 0.0], [b, 0.0, 0.0])];
            let mut r = Refiner::new(&centers, &segs, &Params::default(), Backend::Cpu).unwrap();
            assert_eq!(r.n_box(), n);
            assert!(r.set_attributes(&centers, Some(&normals), Some(&xs), &segs));
            assert!(r.set_extent(&centers, &xs, &segs));
            assert!(r.set_colour(&centers, &colour, &segs));
            let kept: Vec<f32> = xs
                .iter()
                .copied()
                .filter(|&x| f64::from(x) >= a - 0.1 * (b - a) && f64::from(x) <= b + 0.1 * (b - a))
                .collect();
            assert_eq!(kept.len(), n);
            let at = &r.attrs;
            assert_eq!(at.opacity.as_deref(), Some(&kept[..]));
            assert_eq!(at.extent.as_deref(), Some(&kept[..]));
            let nx: Vec<f32> = at.normals.as_ref().unwrap().iter().map(|v| v[0]).collect();
            let cz: Vec<f32> = at.colour.as_ref().unwrap().iter().map(|v| v[2]).collect();
            assert_eq!((nx, cz), (kept.clone(), kept));
            // A count that is not the model's is refused, in both cases.
            assert!(!r.set_extent(&centers, &xs[1..], &segs));
        }
    }

    #[test]
    fn lines_away_from_every_gaussian_stop_the_run() {
        let mut scene = super::super::axis_scene();
        scene.lines = LineSet::new(vec![Segment::from_arrays(
            [50.0, 50.0, 50.0],
            [51.0, 50.0, 50.0],
        )]);
        let checked = Job {
            check_frames: true,
            ..job()
        };
        let e = checked.refine(&scene, |_| {}).unwrap_err();
        assert!(matches!(e, RunError::FrameMismatch(_)), "{e}");
        assert!(e.is_input_error());
    }
}
