//! The refinement pipeline of docs/method.md#the-refinement-steps: a list of steps
//! ([`STEPS`]), one file (or folder) each, driven by one loop that times and records them.
//! A step owns its parameters (a [`params::group!`] struct, flattened into [`Params`]),
//! its notes for the report (flattened into [`StepNotes`]) and its [`Step::run`]. Steps
//! talk to the Gaussians only through [`crate::engine::Engine`] batches.

pub mod params;

pub use params::{
    auto_radius, Check, EvalParams, Fit, FixParams, Fixes, Group, ParamError, Profile, RadiusArg,
    RlMode, Settings,
};

pub mod cluster;
pub mod crop;
pub mod fit;
pub mod gaps;
pub mod mergejoin;
pub mod outliers;
pub mod straight;
pub mod translate;

use crate::engine::{Engine, EngineError};
use crate::geom::{LineSet, Segment};
use params::group;
use serde::{Deserialize, Serialize};
use std::time::Instant;

/// The refinement steps, in the order they run. Adding a step: its file (its parameters,
/// notes and [`Step`]), a `pub mod` line above and its line here; its parameters and notes
/// each get a line in [`Params`] and [`StepNotes`] (docs/contributing.md#adding-a-step).
pub const STEPS: &[&dyn Step] = &[
    &fit::Place,
    &outliers::Outliers,
    &mergejoin::CollinearMerge,
    &cluster::Cluster,
    &mergejoin::MergeJoin,
    &crop::Crop,
    &gaps::SplitGaps,
    &straight::Straightness,
];

group! {
    /// The refinement thresholds of docs/method.md#the-refinement-steps (defaults from the
    /// paper / the authors' code): the profile and the radius, then each step's own
    /// parameters, the profile's fixes and the evaluation options, in the command line's
    /// order (the JSON report's `params` lists them flat, in this order too).
    pub struct Params {
        /// `default` (the paper's intent, all fixes on) or `reference` (the authors' code,
        /// quirks included).
        profile: Profile = Profile::Default, Check::Choice(Profile::CHOICES);
        /// Cylinder radius r for refinement (scene units; the paper uses 0.03 for ABC-NEF and
        /// 0.05 for real scenes), or `auto`: 0.02 x the 95th-percentile distance of the working
        /// set's Gaussian centers from their centroid. Also the clustering distance scale r_c.
        radius: RadiusArg = RadiusArg::Fixed(0.03), Check::Radius;
        ..fit: fit::FitParams,
        ..straight: straight::StraightParams,
        ..gaps: gaps::GapsParams,
        ..outliers: outliers::OutliersParams,
        ..collinear: mergejoin::CollinearParams,
        ..cluster: cluster::ClusterParams,
        ..merge_join: mergejoin::MergeJoinParams,
        ..crop: crop::CropParams,
        ..switches: FixParams,
        ..eval: EvalParams,
    }
}

/// One refinement step: a stage of the report and the timings.
pub trait Step: Sync {
    /// The stage's name (the report's `stages` and `refine.lengths`).
    fn name(&self) -> &'static str;
    /// Whether the step runs on `pass` (one that is off is neither timed nor recorded).
    fn on(&self, _pass: &Pass) -> bool {
        true
    }
    /// Whether the report's `refine.lengths` records the stage (a step that only prepares
    /// the next, as the clustering does, leaves the segments as they were).
    fn measured(&self) -> bool {
        true
    }
    /// Runs the step: reads and replaces `pass.lines` (and their sources), writes its notes.
    fn run(&self, pass: &mut Pass) -> Result<(), EngineError>;
}

/// What the steps work on, handed from one to the next.
pub struct Pass<'a> {
    /// Answers the steps that ask whether Gaussians are there (outliers, merge and join,
    /// crop, gaps).
    pub engine: &'a dyn Engine,
    /// Answers the steps that move a line onto the Gaussians (the edge fit, its gate, the
    /// straightness test), with the attributes of its Gaussians (see [`run_steps_noted`]).
    pub place: &'a dyn Engine,
    pub attrs: &'a fit::Attributes,
    pub settings: &'a Settings,
    pub lines: LineSet,
    /// Each segment's sources: the indices into the input of the segments it came from.
    pub sources: Vec<Vec<u32>>,
    pub notes: StepNotes,
    /// The clusters of `lines` (the cluster step's, for the merge and join).
    pub clusters: Vec<Vec<usize>>,
}

impl Pass<'_> {
    /// Keeps the segments `kept` (indices into `lines`, increasing) and their sources.
    pub fn keep(&mut self, kept: &[usize]) {
        self.lines = self.lines.select(kept);
        self.sources = kept.iter().map(|&k| self.sources[k].clone()).collect();
    }

    /// Replaces the lines with `lines`, whose segment `i` comes from `from[i]` (an index
    /// into the lines before: a piece of it).
    pub fn pieces(&mut self, lines: LineSet, from: &[usize]) {
        self.lines = lines;
        self.sources = from.iter().map(|&k| self.sources[k].clone()).collect();
    }

    /// Replaces the lines with `lines`, whose segment `i` is made of the segments
    /// `members[i]` (indices into the lines before: a merge or join holds both).
    pub fn regroup(&mut self, lines: LineSet, members: &[Vec<usize>]) {
        self.lines = lines;
        self.sources = members
            .iter()
            .map(|m| {
                let mut v: Vec<u32> = m
                    .iter()
                    .flat_map(|&k| self.sources[k].iter().copied())
                    .collect();
                v.sort_unstable();
                v.dedup();
                v
            })
            .collect();
    }
}

/// `rho = N / L` (0 when `L = 0`).
pub fn density(count: u64, length: f64) -> f64 {
    if length > 0.0 {
        count as f64 / length
    } else {
        0.0
    }
}

/// How far step 4 moved the segments, in units of r (each segment: the mean of its two
/// endpoints' moves).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Shifts {
    pub median_r: f64,
    pub p90_r: f64,
    pub max_r: f64,
    /// Segments that moved more than 1e-3 r.
    pub moved: usize,
    /// The median move is a quarter of r or more: the Gaussians' ridge sits off the lines
    /// systematically.
    pub systematic: bool,
}

impl Shifts {
    /// Moves from `before` to `after` (same length and order), `None` when empty.
    pub fn between(before: &[Segment], after: &[Segment], r: f64) -> Option<Shifts> {
        let mut m: Vec<f64> = before
            .iter()
            .zip(after)
            .map(|(a, b)| 0.5 * ((b.p1 - a.p1).length() + (b.p2 - a.p2).length()) / r)
            .collect();
        if m.is_empty() {
            return None;
        }
        m.sort_by(f64::total_cmp);
        let q = |f: f64| m[((f * (m.len() - 1) as f64).round() as usize).min(m.len() - 1)];
        let median_r = q(0.5);
        Some(Shifts {
            median_r,
            p90_r: q(0.9),
            max_r: m[m.len() - 1],
            moved: m.iter().filter(|&&x| x > 1e-3).count(),
            systematic: median_r >= 0.25,
        })
    }
}

/// Total segment length after one stage, and what the stage removed.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StageLength {
    pub name: String,
    pub length: f64,
    /// Length before the stage minus length after (negative when it grew).
    pub removed: f64,
}

/// What the steps did beyond the segment counts (the report's `refine` section): each
/// step's own notes, flattened, and what the loop and the pipeline record.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StepNotes {
    #[serde(flatten)]
    pub fit: fit::FitNotes,
    pub lengths: Vec<StageLength>,
    /// `--max-scale`: Gaussians left out as wider than `max_scale x r` (null when off).
    pub scale_cut: Option<usize>,
    #[serde(flatten)]
    pub straight: straight::StraightNotes,
    #[serde(flatten)]
    pub gaps: gaps::GapsNotes,
    pub warnings: Vec<String>,
}

fn total_length(s: &[Segment]) -> f64 {
    s.iter().map(Segment::length).sum()
}

/// Steps 4–9 in order, calling `stage(name, segments_out, started)` after each.
pub fn run_steps(
    engine: &dyn Engine,
    input: &LineSet,
    s: &Settings,
    stage: impl FnMut(&str, usize, Instant),
) -> Result<LineSet, EngineError> {
    let none = fit::Attributes::default();
    Ok(run_steps_noted(engine, (engine, &none), input, s, stage)?.0)
}

/// [`run_steps`] with the notes, and the Gaussians that place lines apart from those that
/// witness them: `place` (an engine and its Gaussians' attributes: normals, thickness,
/// opacity) answers the steps that move a line onto the Gaussians (the edge fit, its
/// gate, the straightness test), `engine` every step that asks whether Gaussians are
/// there (outliers, merge and join, crop, gaps). The two differ under `--max-scale`:
/// a Gaussian wider than the cylinder cannot place a line within r, but it is evidence
/// that a surface is there.
pub fn run_steps_noted(
    engine: &dyn Engine,
    place: (&dyn Engine, &fit::Attributes),
    input: &LineSet,
    s: &Settings,
    stage: impl FnMut(&str, usize, Instant),
) -> Result<(LineSet, StepNotes), EngineError> {
    let (lines, notes, _) = run_steps_traced(engine, place, input, s, stage)?;
    Ok((lines, notes))
}

/// [`run_steps_noted`] with each output segment's sources: the indices into `input` of
/// the segments it came from (increasing; a merge or join holds those of both, a split's
/// pieces those of the segment split).
pub fn run_steps_traced(
    engine: &dyn Engine,
    place: (&dyn Engine, &fit::Attributes),
    input: &LineSet,
    s: &Settings,
    mut stage: impl FnMut(&str, usize, Instant),
) -> Result<(LineSet, StepNotes, Vec<Vec<u32>>), EngineError> {
    let (place, attrs) = place;
    let mut lines = input.clone();
    if s.fixes().order_endpoints {
        for s in &mut lines.segments {
            if s.p1.length() > s.p2.length() {
                *s = s.reversed();
            }
        }
    }
    let mut pass = Pass {
        engine,
        place,
        attrs,
        settings: s,
        sources: (0..input.len() as u32).map(|i| vec![i]).collect(),
        lines,
        notes: StepNotes::default(),
        clusters: Vec::new(),
    };
    let mut last_len = total_length(&pass.lines.segments);
    for step in STEPS {
        if !step.on(&pass) {
            continue;
        }
        let t = Instant::now();
        step.run(&mut pass)?;
        if step.measured() {
            let l = total_length(&pass.lines.segments);
            pass.notes.lengths.push(StageLength {
                name: step.name().to_string(),
                length: l,
                removed: last_len - l,
            });
            last_len = l;
        }
        stage(step.name(), pass.lines.len(), t);
    }
    debug_assert_eq!(pass.sources.len(), pass.lines.len());
    Ok((pass.lines, pass.notes, pass.sources))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::select::Backend;
    use crate::pipeline::Refiner;

    /// The stages run on the toy scene (its lines are grouped: the collinear merge runs),
    /// and the lengths the report lists.
    fn stages(p: &Params) -> (Vec<String>, Vec<String>) {
        let scene = crate::synth::toy_scene(&crate::synth::ToyParams::default());
        let r = Refiner::new(&scene.gaussians, &scene.lines.segments, p, Backend::Cpu).unwrap();
        let mut seen = Vec::new();
        let (out, notes) = run_steps_noted(
            r.engine(),
            (r.engine(), &fit::Attributes::default()),
            &scene.lines,
            r.settings(),
            |name, n, _| seen.push(format!("{name} {n}")),
        )
        .unwrap();
        assert!(seen.last().unwrap().ends_with(&format!(" {}", out.len())));
        let names = seen
            .iter()
            .map(|s| s.split(' ').next().unwrap().to_string());
        let lengths = notes.lengths.iter().map(|l| l.name.clone()).collect();
        (names.collect(), lengths)
    }

    #[test]
    fn the_loop_runs_the_steps_that_are_on_in_order_and_measures_all_but_the_clustering() {
        let names: Vec<&str> = STEPS.iter().map(|s| s.name()).collect();
        assert_eq!(
            names,
            [
                "translate",
                "outliers",
                "collinear_merge",
                "cluster",
                "merge_join",
                "crop",
                "split_gaps",
                "straightness"
            ]
        );
        let (ran, lengths) = stages(&Params::default());
        assert_eq!(ran, names[..7]);
        assert_eq!(lengths, [&names[..3], &names[4..7]].concat());
        let mut p = Params::reference();
        p.straight.max_sagitta = 0.5;
        p.collinear.collinear_merge = false;
        let (ran, _) = stages(&p);
        assert_eq!(ran, [&names[..2], &names[3..6], &names[7..]].concat());
    }
}
