//! Steps 6 and 8: merge (duplication) and join (discontinuity) inside a group of segments,
//! each loop restarting after every success.
//!
//! Step 8 runs, inside each cluster of step 7, the merge loop to its end and then the join
//! loop; step 6 runs the join alone on every pair of each input line. A loop scans the pairs
//! `(i, j)`, `i < j`, of the group's current list and applies the first pair that passes;
//! the result takes the place of `i`, `j` is removed and the scan starts again; the loop
//! ends when a full scan finds nothing.
//!
//! - [`rules`]: the merge and join tests of the paper, pure functions of two segments and
//!   the engine's answers about them.
//! - [`sequential`]: the restart loops exactly as stated, one query at a time: the
//!   executable definition.
//! - `rounds`: the same loops for every group at once, one engine batch per round, with a
//!   memo of decisions across restarts; [`merge_join`] and [`collinear_merge`] run it, and
//!   tests check it against [`sequential`] segment for segment.
//! - `near`: which pairs of a group can pass a rule's CPU part at all (an interval sweep
//!   along the group's direction), so that a large cluster of short pieces costs about
//!   linear time in its size, not quadratic.

mod near;
mod rounds;
pub use rounds::set_max_pairs_per_segment;
pub mod rules;
pub mod sequential;

use crate::engine::{CylStats, Engine, EngineError};
use crate::geom::{LineSet, Segment};
use crate::refine::params::{group, Check};
use crate::refine::{Fixes, Pass, Settings, Step};
use std::collections::HashMap;

/// Pairs one group may list in its first round. A group whose list runs out without a
/// success doubles it, so a huge cluster costs a few more rounds, not a huge batch.
const FIRST_BUDGET: usize = 1024;

/// A segment of a group with its input line and, once asked, its cylinder's stats.
#[derive(Clone, Copy, Debug)]
struct Item {
    seg: Segment,
    group: u32,
    /// `X(seg, r)` (count and squared-distance sum) once a batch has answered it.
    stats: Option<CylStats>,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Mode {
    /// Step 8: merge on overlapping pairs, then join on the others.
    Cluster,
    /// Step 6: join on every pair.
    Collinear,
}

/// The parameters every decision reads.
#[derive(Clone, Copy)]
struct Ctx<'a> {
    mode: Mode,
    r: f64,
    p: &'a MergeJoinParams,
    fixes: &'a Fixes,
}

impl<'a> Ctx<'a> {
    /// Fix `merge_fidelity`: how far a merge or join may put a line from its inputs'
    /// endpoints: `r / 2`, the most one edge-fit step moves a line.
    fn fidelity(&self) -> Option<f64> {
        self.fixes.merge_fidelity.then_some(0.5 * self.r)
    }

    fn new(mode: Mode, s: &'a Settings) -> Self {
        Ctx {
            mode,
            r: s.radius(),
            p: &s.params().merge_join,
            fixes: s.fixes(),
        }
    }
}

fn items_of(lines: &LineSet, idx: &[usize]) -> Vec<Item> {
    idx.iter()
        .map(|&k| Item {
            seg: lines.segments[k],
            group: lines.group(k),
            stats: None,
        })
        .collect()
}

fn line_set(items: impl Iterator<Item = Item>, grouped: bool) -> LineSet {
    let (segments, groups): (Vec<Segment>, Vec<u32>) = items.map(|it| (it.seg, it.group)).unzip();
    LineSet {
        segments,
        groups: grouped.then_some(groups),
    }
}

/// Step 8: merge, then join, inside each cluster (indices into `lines`, e.g. from
/// [`super::cluster::cluster`]). The result lists the clusters' segments in cluster order;
/// a merged or joined segment takes the group of the first of its pair.
///
/// # Panics
/// If a cluster names a segment index `>= lines.len()`.
pub fn merge_join(
    engine: &dyn Engine,
    lines: &LineSet,
    clusters: &[Vec<usize>],
    s: &Settings,
) -> Result<LineSet, EngineError> {
    Ok(merge_join_budget(engine, lines, clusters, s, FIRST_BUDGET, near::SWEEP_FROM)?.0)
}

/// [`merge_join`] with each result's members: the indices into `lines` of the segments
/// it was made of (itself, or those merged and joined into it), increasing.
pub fn merge_join_traced(
    engine: &dyn Engine,
    lines: &LineSet,
    clusters: &[Vec<usize>],
    s: &Settings,
) -> Result<(LineSet, Vec<Vec<usize>>), EngineError> {
    merge_join_budget(engine, lines, clusters, s, FIRST_BUDGET, near::SWEEP_FROM)
}

/// [`merge_join`] with the first round's budget and the smallest group that sweeps.
fn merge_join_budget(
    engine: &dyn Engine,
    lines: &LineSet,
    clusters: &[Vec<usize>],
    s: &Settings,
    budget: usize,
    sweep_from: usize,
) -> Result<(LineSet, Vec<Vec<usize>>), EngineError> {
    let cx = Ctx::new(Mode::Cluster, s);
    // A cluster of one segment has no pair: it comes back as it is, without a machine
    // (most clusters of a large scene are such; their machines' memory was most of the
    // step's).
    let mut machines: Vec<rounds::Machine> = clusters
        .iter()
        .filter(|c| c.len() > 1)
        .map(|c| rounds::Machine::new(items_of(lines, c), Mode::Cluster, budget, sweep_from))
        .collect();
    let segments = clusters.iter().map(Vec::len).sum();
    rounds::run(engine, &mut machines, cx, segments)?;
    let mut items = Vec::with_capacity(lines.len());
    let mut members = Vec::with_capacity(lines.len());
    let mut machines = machines.into_iter();
    for c in clusters {
        if c.len() == 1 {
            items.extend(items_of(lines, c));
            members.push(vec![c[0]]);
            continue;
        }
        let Some(m) = machines.next() else { break };
        for (it, k) in m.into_items_with_members() {
            items.push(it);
            let mut idx: Vec<usize> = k.into_iter().map(|k| c[k]).collect();
            idx.sort_unstable();
            members.push(idx);
        }
    }
    Ok((line_set(items.into_iter(), lines.groups.is_some()), members))
}

/// The members of each input line, lines in order of their first segment.
fn input_lines(groups: &[u32]) -> Vec<Vec<usize>> {
    let mut slot: HashMap<u32, usize> = HashMap::new();
    let mut members: Vec<Vec<usize>> = Vec::new();
    for (i, &g) in groups.iter().enumerate() {
        let k = *slot.entry(g).or_insert_with(|| {
            members.push(Vec::new());
            members.len() - 1
        });
        members[k].push(i);
    }
    members
}

/// One group's result: its items, each with the indices of the group's items it holds.
type GroupResult = Vec<(Item, Vec<usize>)>;

/// Puts each input line's result in the place of its first segment (`None`: the line's
/// one segment as it is).
fn in_input_order(
    lines: &LineSet,
    members: &[Vec<usize>],
    mut results: Vec<Option<GroupResult>>,
) -> (LineSet, Vec<Vec<usize>>) {
    let mut first: Vec<Option<usize>> = vec![None; lines.len()];
    for (k, m) in members.iter().enumerate() {
        first[m[0]] = Some(k);
    }
    let mut out = Vec::with_capacity(lines.len());
    let mut from = Vec::with_capacity(lines.len());
    for k in first.into_iter().flatten() {
        // `None`: the line's one segment, unchanged.
        let Some(result) = results[k].take() else {
            let i = members[k][0];
            out.extend(items_of(lines, &[i]));
            from.push(vec![i]);
            continue;
        };
        for (it, held) in result {
            out.push(it);
            let mut idx: Vec<usize> = held.into_iter().map(|h| members[k][h]).collect();
            idx.sort_unstable();
            from.push(idx);
        }
    }
    (line_set(out.into_iter(), true), from)
}

/// Step 6: inside each input line with two or more segments, the join on every pair,
/// restarting after each success. A line's result takes the place of its first segment;
/// ungrouped input (or `p.collinear_merge` off) comes back unchanged.
pub fn collinear_merge(
    engine: &dyn Engine,
    lines: &LineSet,
    s: &Settings,
) -> Result<LineSet, EngineError> {
    Ok(collinear_merge_traced(engine, lines, s)?.0)
}

/// [`collinear_merge`] with each result's members (indices into `lines`, increasing).
pub fn collinear_merge_traced(
    engine: &dyn Engine,
    lines: &LineSet,
    s: &Settings,
) -> Result<(LineSet, Vec<Vec<usize>>), EngineError> {
    collinear_merge_from(engine, lines, s, near::SWEEP_FROM)
}

/// [`collinear_merge_traced`] with the smallest group that sweeps.
fn collinear_merge_from(
    engine: &dyn Engine,
    lines: &LineSet,
    s: &Settings,
    sweep_from: usize,
) -> Result<(LineSet, Vec<Vec<usize>>), EngineError> {
    let unchanged = || (lines.clone(), (0..lines.len()).map(|i| vec![i]).collect());
    let Some(groups) = &lines.groups else {
        return Ok(unchanged());
    };
    if !s.params().collinear.collinear_merge {
        return Ok(unchanged());
    }
    let members = input_lines(groups);
    let cx = Ctx::new(Mode::Collinear, s);
    // A line of one segment has no pair: it comes back as it is, without a machine
    // (most lines of a large scene are such; their machines' memory was most of the
    // step's).
    let mut machines: Vec<rounds::Machine> = members
        .iter()
        .filter(|m| m.len() > 1)
        .map(|m| {
            let items = items_of(lines, m);
            rounds::Machine::new(items, Mode::Collinear, FIRST_BUDGET, sweep_from)
        })
        .collect();
    rounds::run(engine, &mut machines, cx, lines.len())?;
    let mut machines = machines.into_iter();
    let results = members
        .iter()
        .map(|m| match m.len() {
            1 => None,
            _ => machines.next().map(|m| m.into_items_with_members()),
        })
        .collect();
    Ok(in_input_order(lines, &members, results))
}

group! {
    /// Step 6's parameter.
    pub struct CollinearParams {
        /// Run the collinear merge inside input lines (Line3D++ `.txt` groups).
        collinear_merge: bool = true, Check::Bool;
    }
}

group! {
    /// Step 8's parameters: the merge and the join.
    pub struct MergeJoinParams {
        /// Merge: largest angle between the two directions (degrees).
        merge_angle_deg: f64 = 30.0, Check::Positive;
        /// Merge: reject when both endpoints of the shorter are farther than this x L_long
        /// from the longer's line.
        merge_dist_frac: f64 = 0.2, Check::Positive;
        /// Merge: reject when rho(G') < ratio x rho(G).
        merge_density_ratio: f64 = 0.6, Check::Positive;
        /// Join: largest angle between the joined segment and each input (degrees).
        join_angle_deg: f64 = 10.0, Check::Positive;
        /// Join: reject gaps longer than this x either length.
        join_gap_frac: f64 = 0.8, Check::Positive;
        /// Join: the gap chord is shrunk by this fraction at each end before counting.
        join_chord_shrink: f64 = 0.02, Check::Fraction;
        /// Join (fix): the gap must hold at least this x mean density x chord length points.
        join_gap_density: f64 = 0.6, Check::Positive;
        /// Join: reject J when rho(J) < ratio x rho of either input.
        join_density_ratio: f64 = 0.6, Check::Positive;
        /// Join: reject J when E(J) > ratio x E of either input.
        join_rmse_ratio: f64 = 1.1, Check::Positive;
    }
}

/// Step 6, the stage `collinear_merge` (on grouped input, `--collinear-merge true`).
pub struct CollinearMerge;

impl Step for CollinearMerge {
    fn name(&self) -> &'static str {
        "collinear_merge"
    }

    fn on(&self, pass: &Pass) -> bool {
        pass.settings.params().collinear.collinear_merge && pass.lines.groups.is_some()
    }

    fn run(&self, pass: &mut Pass) -> Result<(), EngineError> {
        let (merged, members) = collinear_merge_traced(pass.engine, &pass.lines, pass.settings)?;
        pass.regroup(merged, &members);
        Ok(())
    }
}

/// Step 8, the stage `merge_join`: each cluster of the cluster step merged and joined.
pub struct MergeJoin;

impl Step for MergeJoin {
    fn name(&self) -> &'static str {
        "merge_join"
    }

    fn run(&self, pass: &mut Pass) -> Result<(), EngineError> {
        let (joined, members) =
            merge_join_traced(pass.engine, &pass.lines, &pass.clusters, pass.settings)?;
        pass.regroup(joined, &members);
        Ok(())
    }
}

#[cfg(test)]
mod tests;
