//! The executable definition of steps 6 and 8: the restart loops of
//! docs/method.md#the-refinement-steps written as directly as the paper and the authors'
//! code state them, asking the engine one query at a time and remembering nothing between
//! pairs. Quadratic per restart and slow by design; [`super::merge_join`] and
//! [`super::collinear_merge`] must give exactly its output (tests check it on many random
//! groups).

use super::rules;
use super::{in_input_order, input_lines, items_of, line_set, Ctx, Item, Mode};
use crate::engine::{CylStats, Engine, EngineError, Query, Want};
use crate::geom::{LineSet, Segment};
use crate::refine::Settings;

/// `X(s, r)`, asked alone.
fn ask(engine: &dyn Engine, s: Segment, r: f64) -> Result<CylStats, EngineError> {
    Ok(engine.stats(&[Query::new(s, r)], Want::SUMS)?[0])
}

/// The merge (`merge == true`) or the join of items `a` and `b`, or `None`.
fn try_pair(
    engine: &dyn Engine,
    a: &Item,
    b: &Item,
    merge: bool,
    cx: Ctx,
) -> Result<Option<Segment>, EngineError> {
    let (sa, sb) = (&a.seg, &b.seg);
    let overlap = rules::overlaps(sa, sb, cx.fixes);
    if merge {
        let Some(c) = overlap
            .then(|| rules::merge_candidate(sa, sb, cx.p, cx.fidelity()))
            .flatten()
        else {
            return Ok(None);
        };
        let (st_a, st_b) = (ask(engine, *sa, cx.r)?, ask(engine, *sb, cx.r)?);
        let st_prime = ask(engine, c.g_prime, cx.r)?;
        let made = rules::merge((sa, st_a), (sb, st_b), &c, st_prime, cx.p, cx.fixes);
        return Ok(made.map(|m| m.seg));
    }
    if overlap && cx.mode == Mode::Cluster {
        return Ok(None);
    }
    let Some(c) = rules::join_candidate(sa, sb, cx.p, cx.fixes, cx.fidelity()) else {
        return Ok(None);
    };
    let (st_a, st_b) = (ask(engine, *sa, cx.r)?, ask(engine, *sb, cx.r)?);
    // A degenerate chord (touching segments) holds no point.
    let n_chord = match c.chord.is_valid() {
        true => ask(engine, c.chord, cx.r)?.count,
        false => 0,
    };
    let st_j = ask(engine, c.joined, cx.r)?;
    let made = rules::join((sa, st_a), (sb, st_b), &c, n_chord, st_j, cx.p, cx.fixes);
    Ok(made.map(|m| m.seg))
}

/// Scan the pairs `(i, j)`, `i < j`; apply the first success (the result takes `i`'s
/// place and `i`'s input line, `j` goes) and scan again from the start; stop when a
/// whole scan finds nothing.
fn restart_loop(
    engine: &dyn Engine,
    items: &mut Vec<Item>,
    merge: bool,
    cx: Ctx,
) -> Result<(), EngineError> {
    'scan: loop {
        for i in 0..items.len() {
            for j in i + 1..items.len() {
                if let Some(seg) = try_pair(engine, &items[i], &items[j], merge, cx)? {
                    items[i].seg = seg;
                    items.remove(j);
                    continue 'scan;
                }
            }
        }
        return Ok(());
    }
}

/// Step 8, sequentially: in each cluster the merge loop to its end, then the join loop.
pub fn merge_join_sequential(
    engine: &dyn Engine,
    lines: &LineSet,
    clusters: &[Vec<usize>],
    s: &Settings,
) -> Result<LineSet, EngineError> {
    let cx = Ctx::new(Mode::Cluster, s);
    let mut out = Vec::with_capacity(lines.len());
    for c in clusters {
        let mut items = items_of(lines, c);
        restart_loop(engine, &mut items, true, cx)?;
        restart_loop(engine, &mut items, false, cx)?;
        out.extend(items);
    }
    Ok(line_set(out.into_iter(), lines.groups.is_some()))
}

/// Step 6, sequentially: in each input line the join loop on every pair.
pub fn collinear_merge_sequential(
    engine: &dyn Engine,
    lines: &LineSet,
    s: &Settings,
) -> Result<LineSet, EngineError> {
    let (Some(groups), true) = (&lines.groups, s.params().collinear.collinear_merge) else {
        return Ok(lines.clone());
    };
    let cx = Ctx::new(Mode::Collinear, s);
    let members = input_lines(groups);
    let mut results = Vec::with_capacity(members.len());
    for m in &members {
        let mut items = items_of(lines, m);
        restart_loop(engine, &mut items, false, cx)?;
        // The executable definition keeps no provenance.
        results.push(Some(items.into_iter().map(|it| (it, Vec::new())).collect()));
    }
    Ok(in_input_order(lines, &members, results).0)
}
