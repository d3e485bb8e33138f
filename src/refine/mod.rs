//! The refinement pipeline of docs/method.md#the-refinement-steps, one file per step. Steps
//! talk to the Gaussians only through [`crate::engine::Engine`] batches.

pub mod params;

pub use params::{
    auto_radius, EvalParams, Fit, Fixes, Params, Profile, RadiusArg, RlMode, Settings,
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
use serde::{Deserialize, Serialize};
use std::time::Instant;

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

/// What the steps did beyond the segment counts (the report's `refine` section).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepNotes {
    pub fit: Fit,
    pub shifts: Option<Shifts>,
    /// Engine batches of the edge fit (0 for the other fits).
    pub fit_iterations: u32,
    /// Edge fit: segments placed on two faces' corner, on a ridge, and left (unclear).
    pub fit_corner: usize,
    pub fit_ridge: usize,
    pub fit_unclear: usize,
    /// Edge fit: segments the move gate kept at their input (`--fit-gate`): an estimate
    /// existed, but the Gaussians did not explain the move.
    #[serde(default)]
    pub fit_kept: usize,
    /// Edge fit: each weighed segment's decision with its numbers (`--fit-gate`).
    #[serde(default)]
    pub fit_decisions: Vec<fit::Decision>,
    /// Edge fit: what the model is near the lines, from the decisions (`--fit-gate`).
    #[serde(default)]
    pub diagnosis: Option<fit::Diagnosis>,
    pub lengths: Vec<StageLength>,
    /// `--max-scale`: Gaussians left out as wider than `max_scale x r` (null when off).
    pub scale_cut: Option<usize>,
    /// `--max-sagitta`: segments dropped as curves (null when off).
    pub curved_dropped: Option<usize>,
    /// `--split-gaps`: ends cut at an empty end stretch, segments split at an empty
    /// interior stretch, and pieces dropped as too few points (null when off).
    pub gaps_ends_cut: Option<usize>,
    pub gaps_split: Option<usize>,
    pub gaps_pieces_dropped: Option<usize>,
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
    let mut sources: Vec<Vec<u32>> = (0..input.len() as u32).map(|i| vec![i]).collect();
    // The sources of the step's output, from each output's members in the step's input.
    fn regroup(sources: &[Vec<u32>], members: &[Vec<usize>]) -> Vec<Vec<u32>> {
        members
            .iter()
            .map(|m| {
                let mut v: Vec<u32> = m.iter().flat_map(|&k| sources[k].iter().copied()).collect();
                v.sort_unstable();
                v.dedup();
                v
            })
            .collect()
    }
    let pick = |sources: &[Vec<u32>], kept: &[usize]| -> Vec<Vec<u32>> {
        kept.iter().map(|&k| sources[k].clone()).collect()
    };
    let (place, attrs) = place;
    let (r, p, fixes) = (s.radius(), s.params(), s.fixes());
    let mut lines = input.clone();
    if fixes.order_endpoints {
        for s in &mut lines.segments {
            if s.p1.length() > s.p2.length() {
                *s = s.reversed();
            }
        }
    }
    let mut notes = StepNotes {
        fit: fixes.fit,
        shifts: None,
        fit_iterations: 0,
        fit_corner: 0,
        fit_ridge: 0,
        fit_unclear: 0,
        fit_kept: 0,
        fit_decisions: Vec::new(),
        diagnosis: None,
        lengths: Vec::new(),
        scale_cut: None,
        curved_dropped: None,
        gaps_ends_cut: None,
        gaps_split: None,
        gaps_pieces_dropped: None,
        warnings: Vec::new(),
    };
    let mut last_len = total_length(&lines.segments);
    let mut note_len = |name: &str, segs: &[Segment], notes: &mut StepNotes| {
        let l = total_length(segs);
        notes.lengths.push(StageLength {
            name: name.to_string(),
            length: l,
            removed: last_len - l,
        });
        last_len = l;
    };

    let t = Instant::now();
    let moved = match fixes.fit {
        Fit::Paper => translate::translate(place, &lines.segments, r, p.translate_keep)?,
        Fit::None => lines.segments.clone(),
        Fit::Edge => {
            let mut f = fit::fit_edges(place, &lines.segments, attrs, r, p)?;
            if p.fit_gate {
                notes.fit_decisions = fit::decide(place, &lines.segments, &mut f, attrs, r, p)?;
                notes.diagnosis = fit::diagnose(&notes.fit_decisions, r);
            }
            notes.fit_iterations = f.iterations;
            let count = |h| f.how.iter().filter(|&&x| x == h).count();
            notes.fit_corner = count(fit::How::Corner);
            notes.fit_ridge = count(fit::How::Ridge);
            notes.fit_unclear = count(fit::How::Unclear);
            notes.fit_kept = count(fit::How::Kept);
            f.segments
        }
    };
    notes.shifts = Shifts::between(&lines.segments, &moved, r);
    if let Some(s) = &notes.shifts {
        // The edge fit moves lines onto edges on purpose; the published step follows the
        // Gaussians wherever they sit.
        if s.systematic && fixes.fit == Fit::Paper {
            notes.warnings.push(format!(
                "--fit paper: the median segment moved {:.2} r (90th percentile {:.2} r): the \
                 Gaussians' ridge sits off the lines, so this step trades the lines' own \
                 position for closeness to the Gaussians (and the paper's score); compare \
                 --fit none and --fit edge",
                s.median_r, s.p90_r
            ));
        }
    }
    lines.segments = moved;
    note_len("translate", &lines.segments, &mut notes);
    stage("translate", lines.len(), t);

    let t = Instant::now();
    let o = outliers::outliers(engine, &lines.segments, r, p.outlier_ratio())?;
    lines = lines.select(&o.kept);
    sources = pick(&sources, &o.kept);
    note_len("outliers", &lines.segments, &mut notes);
    stage("outliers", lines.len(), t);

    if p.collinear_merge && lines.groups.is_some() {
        let t = Instant::now();
        let (merged, members) = mergejoin::collinear_merge_traced(engine, &lines, s)?;
        lines = merged;
        sources = regroup(&sources, &members);
        note_len("collinear_merge", &lines.segments, &mut notes);
        stage("collinear_merge", lines.len(), t);
    }

    let t = Instant::now();
    let clusters = cluster::cluster(&lines, s)?;
    stage("cluster", lines.len(), t);

    let t = Instant::now();
    let (joined, members) = mergejoin::merge_join_traced(engine, &lines, &clusters, s)?;
    lines = joined;
    sources = regroup(&sources, &members);
    note_len("merge_join", &lines.segments, &mut notes);
    stage("merge_join", lines.len(), t);

    let t = Instant::now();
    lines.segments = crop::crop(engine, &lines.segments, s)?;
    note_len("crop", &lines.segments, &mut notes);
    stage("crop", lines.len(), t);

    let alpha = p.split_gaps();
    if alpha > 0.0 {
        let t = Instant::now();
        let (split, g, from) =
            gaps::split_gaps_traced(engine, &lines, r, alpha, p.fit_min_points, p.split_interior)?;
        lines = split;
        sources = pick(&sources, &from);
        notes.gaps_ends_cut = Some(g.ends_cut);
        notes.gaps_split = Some(g.split);
        notes.gaps_pieces_dropped = Some(g.pieces_dropped);
        note_len("split_gaps", &lines.segments, &mut notes);
        stage("split_gaps", lines.len(), t);
    }

    if p.max_sagitta > 0.0 {
        let t = Instant::now();
        let st = straight::straightness(place, &lines.segments, attrs, r, p)?;
        let kept: Vec<usize> = (0..lines.len())
            .filter(|&i| st[i].is_none_or(|sag| sag <= p.max_sagitta))
            .collect();
        notes.curved_dropped = Some(lines.len() - kept.len());
        lines = lines.select(&kept);
        sources = pick(&sources, &kept);
        note_len("straightness", &lines.segments, &mut notes);
        stage("straightness", lines.len(), t);
    }
    debug_assert_eq!(sources.len(), lines.len());
    Ok((lines, notes, sources))
}
