//! Beyond the paper, `--split-gaps`: a segment spanning a stretch of its cylinder that
//! holds no Gaussian is split there (the empty stretch removed), and an empty stretch at
//! an end is cut off. Crop looks only at the ends' windows against the middle's density;
//! this looks at the whole cylinder, at the resolution of the points themselves.
//!
//! Which gaps count: along a segment uniformly covered at density `rho = N / L`, a given
//! stretch of length `g` is empty with probability `exp(-rho g)` (Poisson). An end gap is
//! one of two tested, so it is cut when `2 exp(-rho g) <= alpha`; an interior gap is the
//! largest of about `N + 1`, so it splits when `(N + 1) exp(-rho g) <= alpha`. With
//! `alpha = 0.01` a segment of 100 points splits at a gap holding no point where about 9
//! were expected. No stretch shorter than r is cut: below the cylinder's own radius a
//! hole is not a break in the line (and where the Gaussians cluster, as along a trained
//! or noisy edge, short holes are more common than the uniform model says). Pieces of a
//! split holding fewer than `fit_min_points` points are dropped (a few stray points past
//! a gap are not a line). One engine batch for all segments of each one's count and extent
//! (`Engine::extent`); with interior splits then their sorted axial positions
//! (`Engine::axial`), in batches of at most [`crate::engine::bound::MAX_LISTED_MEMBERS`]
//! positions by those counts.

use crate::engine::bound::ListBound;
use crate::engine::{Engine, EngineError, Extent, Query};
use crate::geom::{LineSet, Segment};
use crate::refine::params::{group, Check};
use crate::refine::{Pass, Profile, Step};
use serde::{Deserialize, Serialize};

/// What [`split_gaps`] did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct GapNotes {
    /// Ends cut back to the last point before an empty end stretch.
    pub ends_cut: usize,
    /// Segments split at one or more interior gaps.
    pub split: usize,
    /// Pieces of splits dropped as too few points.
    pub pieces_dropped: usize,
}

/// How far (in units of r) a cut end lies beyond the member that ends its piece.
pub const CUT_PAD: f64 = 1e-7;

/// The kept `[a, b]` intervals (axial, from P1) of one segment of length `l`, given its
/// members' sorted axial positions `t`; no stretch shorter than `min_gap` is cut, and
/// interior gaps split the segment only with `interior`.
pub fn pieces(
    t: &[f64],
    l: f64,
    alpha: f64,
    min_gap: f64,
    min_points: u32,
    interior: bool,
) -> (Vec<(f64, f64)>, GapNotes) {
    let n = t.len();
    let Some((lo, hi, mut notes)) = ends(&Extent::of_sorted(t), l, alpha, min_gap) else {
        return (vec![(0.0, l)], GapNotes::default());
    };
    let inner_gap = (((n as f64 + 1.0) / alpha).ln() / (n as f64 / l)).max(min_gap);
    // Runs of points separated by interior gaps: [start index, end index].
    let mut runs = vec![(0usize, n - 1)];
    for i in 0..n.saturating_sub(1) * usize::from(interior) {
        if t[i + 1] - t[i] >= inner_gap {
            runs.last_mut().expect("one run").1 = i;
            runs.push((i + 1, n - 1));
        }
    }
    if runs.len() == 1 {
        return (vec![(lo, hi)], notes);
    }
    notes.split = 1;
    let last = runs.len() - 1;
    let mut out = Vec::with_capacity(runs.len());
    for (k, &(i, j)) in runs.iter().enumerate() {
        if ((j - i + 1) as u64) < u64::from(min_points) {
            notes.pieces_dropped += 1;
            continue;
        }
        let a = if k == 0 { lo } else { t[i] };
        let b = if k == last { hi } else { t[j] };
        if b > a {
            out.push((a, b));
        } else {
            notes.pieces_dropped += 1;
        }
    }
    (out, notes)
}

/// The segment `[lo, hi]` left after its empty end stretches are cut, from its members'
/// count and their smallest and largest axial positions (all that the ends need), and
/// what was cut; `None`: nothing to test (fewer than two members, an empty segment, `alpha
/// <= 0`).
pub fn ends(e: &Extent, l: f64, alpha: f64, min_gap: f64) -> Option<(f64, f64, GapNotes)> {
    let mut notes = GapNotes::default();
    let n = e.count;
    if n < 2 || l <= 0.0 || alpha <= 0.0 {
        return None;
    }
    let rho = n as f64 / l;
    let end_gap = ((2.0 / alpha).ln() / rho).max(min_gap);
    let (mut lo, mut hi) = (0.0, l);
    if e.lo >= end_gap {
        lo = e.lo;
        notes.ends_cut += 1;
    }
    if l - e.hi >= end_gap {
        hi = e.hi;
        notes.ends_cut += 1;
    }
    Some((lo, hi, notes))
}

/// Splits every segment of `lines` at its empty stretches (see the module); a split's
/// pieces keep the segment's group and place. `alpha <= 0`: unchanged.
pub fn split_gaps(
    engine: &dyn Engine,
    lines: &LineSet,
    r: f64,
    alpha: f64,
    min_points: u32,
    interior: bool,
) -> Result<(LineSet, GapNotes), EngineError> {
    let (out, notes, _) = split_gaps_traced(engine, lines, r, alpha, min_points, interior)?;
    Ok((out, notes))
}

/// [`split_gaps`] with the index into `lines` of the segment each piece comes from.
pub fn split_gaps_traced(
    engine: &dyn Engine,
    lines: &LineSet,
    r: f64,
    alpha: f64,
    min_points: u32,
    interior: bool,
) -> Result<(LineSet, GapNotes, Vec<usize>), EngineError> {
    let bound = ListBound::new()?;
    split_gaps_within(engine, lines, r, alpha, min_points, interior, bound)
}

/// [`split_gaps_traced`] under the bound `bound` on the positions a batch lists.
fn split_gaps_within(
    engine: &dyn Engine,
    lines: &LineSet,
    r: f64,
    alpha: f64,
    min_points: u32,
    interior: bool,
    bound: ListBound,
) -> Result<(LineSet, GapNotes, Vec<usize>), EngineError> {
    let mut total = GapNotes::default();
    if alpha <= 0.0 || lines.is_empty() {
        return Ok((lines.clone(), total, (0..lines.len()).collect()));
    }
    let mut from = Vec::with_capacity(lines.len());
    let queries: Vec<Query> = lines.segments.iter().map(|s| Query::new(*s, r)).collect();
    // Without interior splits only the ends are tested: each cylinder's count and
    // extent, not its sorted positions. With them, the sorted positions of as many
    // segments at a time as the bound on listed members allows, by their counts.
    let extents = engine.extent(&queries)?;
    let kept_of = |i: usize, t: Option<&[f64]>| {
        let l = lines.segments[i].length();
        match t {
            Some(t) => pieces(t, l, alpha, r, min_points, true),
            None => match ends(&extents[i], l, alpha, r) {
                Some((lo, hi, notes)) => (vec![(lo, hi)], notes),
                None => (vec![(0.0, l)], GapNotes::default()),
            },
        }
    };
    let mut kept_all = Vec::with_capacity(lines.len());
    if interior {
        for chunk in bounded_chunks(&extents, bound.limit) {
            let Some(chunk) = chunk else {
                return Err(bound.exceeded("--split-gaps with interior splits"));
            };
            let axial = engine.axial(&queries[chunk.clone()])?;
            kept_all.extend(chunk.zip(&axial).map(|(i, t)| kept_of(i, Some(t))));
        }
    } else {
        kept_all.extend((0..lines.len()).map(|i| kept_of(i, None)));
    }
    let mut segments = Vec::with_capacity(lines.len());
    let mut groups = lines
        .groups
        .as_ref()
        .map(|_| Vec::with_capacity(lines.len()));
    for ((i, s), (kept, notes)) in lines.segments.iter().enumerate().zip(kept_all) {
        let l = s.length();
        total.ends_cut += notes.ends_cut;
        total.split += notes.split;
        total.pieces_dropped += notes.pieces_dropped;
        // A cut end lies at its last member's axial position; moved out by a rounding's
        // worth it keeps that member inside the new cylinder under any rounding of the
        // new end (at the position itself, the member's own test is a coin flip).
        let pad = CUT_PAD * r;
        for (a, b) in kept {
            let a = if a > 0.0 { (a - pad).max(0.0) } else { a };
            let b = if b < l { (b + pad).min(l) } else { b };
            segments.push(if a == 0.0 && b == l {
                *s
            } else {
                Segment::new(
                    if a == 0.0 { s.p1 } else { s.point_at(a) },
                    if b == l { s.p2 } else { s.point_at(b) },
                )
            });
            if let (Some(g), Some(src)) = (groups.as_mut(), lines.groups.as_ref()) {
                g.push(src[i]);
            }
            from.push(i);
        }
    }
    Ok((LineSet { segments, groups }, total, from))
}

/// Consecutive ranges of queries whose member counts sum to at most `limit` each, in
/// order, each as long as the bound allows; `None` for a query that alone has more.
fn bounded_chunks(
    extents: &[Extent],
    limit: usize,
) -> impl Iterator<Item = Option<std::ops::Range<usize>>> + '_ {
    let mut start = 0;
    std::iter::from_fn(move || {
        if start == extents.len() {
            return None;
        }
        let (mut end, mut sum) = (start, 0u64);
        while end < extents.len() && sum + extents[end].count <= limit as u64 {
            sum += extents[end].count;
            end += 1;
        }
        if end == start {
            // Ends the iteration: the caller stops at the first `None`.
            start = extents.len();
            return Some(None);
        }
        let r = start..end;
        start = end;
        Some(Some(r))
    })
}

group! {
    /// The gap split's parameters.
    pub struct GapsParams {
        /// After crop, split a segment where a stretch of its cylinder holds no Gaussian
        /// (and cut an empty stretch off an end): a stretch at least r long is empty beyond
        /// chance when, at the segment's own density, the chance of so long an empty stretch
        /// among the segment's gaps (2 at the ends, N + 1 inside) is at most this. Pieces
        /// with fewer than fit-min-points points are dropped. 0: off. Default: the profile's
        /// (0.01 for default, 0 for reference).
        split_gaps: Option<f64> = None, Check::Fraction;
        /// `--split-gaps` also splits a segment at an empty interior stretch (not only cuts an
        /// empty end). Off by default: trained models leave stretches of a true edge without
        /// Gaussians (textureless faces, thinning near edges), and the chance rule, which
        /// assumes evenly spread Gaussians, split true edges there.
        split_interior: bool = false, Check::Switch;
    }
}

impl GapsParams {
    /// `--split-gaps` in effect: the user's, else the profile's (0.01 for default, 0 for
    /// reference).
    pub fn split_gaps_for(&self, profile: Profile) -> f64 {
        self.split_gaps.unwrap_or(match profile {
            Profile::Default => 0.01,
            Profile::Reference => 0.0,
        })
    }
}

/// What the gap split did (the report's `refine` section; null when off).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct GapsNotes {
    /// `--split-gaps`: ends cut at an empty end stretch, segments split at an empty
    /// interior stretch, and pieces dropped as too few points (null when off).
    pub gaps_ends_cut: Option<usize>,
    pub gaps_split: Option<usize>,
    pub gaps_pieces_dropped: Option<usize>,
}

/// The stage `split_gaps` (`--split-gaps` above 0).
pub struct SplitGaps;

impl Step for SplitGaps {
    fn name(&self) -> &'static str {
        "split_gaps"
    }

    fn on(&self, pass: &Pass) -> bool {
        let p = pass.settings.params();
        p.gaps.split_gaps_for(p.profile) > 0.0
    }

    fn run(&self, pass: &mut Pass) -> Result<(), EngineError> {
        let (r, p) = (pass.settings.radius(), pass.settings.params());
        let alpha = p.gaps.split_gaps_for(p.profile);
        let (split, g, from) = split_gaps_traced(
            pass.engine,
            &pass.lines,
            r,
            alpha,
            p.fit.fit_min_points,
            p.gaps.split_interior,
        )?;
        pass.pieces(split, &from);
        pass.notes.gaps = GapsNotes {
            gaps_ends_cut: Some(g.ends_cut),
            gaps_split: Some(g.split),
            gaps_pieces_dropped: Some(g.pieces_dropped),
        };
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::engine::cpu::CpuEngine;
    use glam::DVec3;

    fn engine(points: &[[f32; 3]]) -> CpuEngine {
        CpuEngine::over_points(points, 0.1)
    }

    /// Points every `step` along x in `[a, b)`, alternating a little off the axis.
    fn row(a: f64, b: f64, step: f64, out: &mut Vec<[f32; 3]>) {
        let mut x = a;
        let mut k = 0;
        while x < b {
            let y = if k % 2 == 0 { 0.002 } else { -0.002 };
            out.push([x as f32, y, 0.0]);
            x += step;
            k += 1;
        }
    }

    #[test]
    fn a_segment_across_an_empty_middle_third_is_split_there() {
        // Dense on [0, 0.27] and [0.54, 0.81], nothing between: the NEF case.
        let mut pts = Vec::new();
        row(0.0, 0.27, 0.002, &mut pts);
        row(0.54, 0.81, 0.002, &mut pts);
        let e = engine(&pts);
        let lines = LineSet {
            segments: vec![Segment::new(DVec3::ZERO, DVec3::new(0.81, 0.0, 0.0))],
            groups: Some(vec![7]),
        };
        let (out, notes) = split_gaps(&e, &lines, 0.01, 0.01, 8, true).unwrap();
        assert_eq!(out.len(), 2, "{:?}", out.segments);
        assert_eq!(notes.split, 1);
        assert_eq!(out.groups, Some(vec![7, 7]));
        let (a, b) = (out.segments[0], out.segments[1]);
        assert!(
            a.p1.x.abs() < 1e-9 && (a.p2.x - 0.27).abs() < 0.003,
            "{a:?}"
        );
        assert!(
            (b.p1.x - 0.54).abs() < 0.003 && (b.p2.x - 0.81).abs() < 1e-9,
            "{b:?}"
        );
        // Off: unchanged.
        let (same, _) = split_gaps(&e, &lines, 0.01, 0.0, 8, true).unwrap();
        assert_eq!(same, lines);
    }

    #[test]
    fn a_gap_plausible_among_many_does_not_split_and_an_empty_end_is_cut() {
        // Points every 0.001 on [0, 0.3] but for one gap of 0.007 (about 7 points
        // expected): unlikely at a given place, but among ~300 gaps the largest is often
        // this long, so no split.
        let mut pts = Vec::new();
        row(0.0, 0.15, 0.001, &mut pts);
        row(0.157, 0.3, 0.001, &mut pts);
        let e = engine(&pts);
        // The segment runs 0.1 past the last point: that end is cut, the other kept. (r
        // 0.005: the gap is longer than r, so only the statistics keep it.)
        let lines = LineSet::new(vec![Segment::new(DVec3::ZERO, DVec3::new(0.4, 0.0, 0.0))]);
        let (out, notes) = split_gaps(&e, &lines, 0.005, 0.01, 8, true).unwrap();
        assert_eq!(out.len(), 1, "{:?}", out.segments);
        assert_eq!((notes.split, notes.ends_cut), (0, 1));
        let s = out.segments[0];
        assert_eq!(s.p1, DVec3::ZERO);
        assert!((s.p2.x - 0.3).abs() < 0.002, "{s:?}");
    }

    #[test]
    fn a_cut_end_keeps_the_member_it_was_cut_at() {
        // Segments in skewed directions with points along their first 60 %: each far end
        // is cut at its last point. The cut piece's cylinder holds every point the
        // segment's did (at the point's own axial position the test is a coin flip of
        // rounding, which lost about half of them).
        let mut rng = crate::synth::Rng::new(11);
        let (mut pts, mut segs) = (Vec::new(), Vec::new());
        for i in 0..40 {
            let a = DVec3::new(i as f64 * 0.1, 0.0, 0.0) + rng.normal3(0.01);
            let b = a + rng.unit_vector() * 0.3;
            for k in 0..60 {
                let q = a + (b - a) * (k as f64 * 0.01 + 0.003) + rng.normal3(0.001);
                pts.push(q.as_vec3().to_array());
            }
            segs.push(Segment::new(a, b));
        }
        let e = engine(&pts);
        let lines = LineSet::new(segs.clone());
        let (out, notes) = split_gaps(&e, &lines, 0.01, 0.01, 8, false).unwrap();
        assert_eq!((out.len(), notes.ends_cut), (40, 40));
        let ask = |s: &[Segment]| {
            let q: Vec<Query> = s.iter().map(|s| Query::new(*s, 0.01)).collect();
            e.members(&q).unwrap()
        };
        for (before, after) in ask(&segs).iter().zip(ask(&out.segments)) {
            assert_eq!(before.len(), after.len());
        }
    }

    #[test]
    fn a_few_stray_points_past_a_gap_are_dropped() {
        let mut t: Vec<f64> = (0..200).map(|i| i as f64 * 0.001).collect();
        t.extend([0.5, 0.501, 0.502]);
        let (kept, notes) = pieces(&t, 0.51, 0.01, 0.01, 8, true);
        assert_eq!(kept.len(), 1, "{kept:?}");
        assert_eq!((notes.split, notes.pieces_dropped), (1, 1));
        assert!((kept[0].1 - 0.199).abs() < 1e-9);
    }

    #[test]
    fn a_hole_shorter_than_r_is_not_a_break() {
        // 1000 points over [0, 0.1] but for a hole of 0.005 (50 expected): certain
        // beyond chance, but shorter than r = 0.01.
        let t: Vec<f64> = (0..1050)
            .map(|i| i as f64 * 1e-4)
            .filter(|&x| !(0.05..0.055).contains(&x))
            .collect();
        let l = t[t.len() - 1];
        let (kept, notes) = pieces(&t, l, 0.01, 0.01, 8, true);
        assert_eq!((kept.len(), notes.split), (1, 0), "{kept:?}");
        let (kept, notes) = pieces(&t, l, 0.01, 0.001, 8, true);
        assert_eq!((kept.len(), notes.split), (2, 1), "{kept:?}");
    }

    /// With interior splits the positions are listed in batches of at most the bound's
    /// members by the segments' counts: any bound that holds the largest segment gives the
    /// unbounded result, piece for piece and note for note, and a smaller one is the
    /// bound's error.
    #[test]
    fn interior_splits_list_in_bounded_batches_with_the_same_pieces() {
        // Rows with holes along x at several heights: each segment splits or not.
        let mut pts = Vec::new();
        let mut segs = Vec::new();
        for k in 0..12 {
            let y = k as f64 * 0.5;
            let mut row_k = Vec::new();
            row(0.0, 0.2 + 0.005 * k as f64, 0.001, &mut row_k);
            row(0.3, 0.6, 0.001, &mut row_k);
            pts.extend(row_k.iter().map(|p| [p[0], p[1] + y as f32, p[2]]));
            segs.push(Segment::new(
                DVec3::new(-0.05, y, 0.0),
                DVec3::new(0.65 + 0.02 * k as f64, y, 0.0),
            ));
        }
        let e = engine(&pts);
        let lines = LineSet::new(segs);
        let run =
            |limit: usize| split_gaps_within(&e, &lines, 0.01, 0.01, 8, true, ListBound::of(limit));
        let whole = run(usize::MAX).unwrap();
        assert_eq!(whole.0.len(), 24, "{:?}", whole.0.segments);
        assert_eq!(whole.1.split, 12);
        let counts = e
            .extent(
                &lines
                    .segments
                    .iter()
                    .map(|s| Query::new(*s, 0.01))
                    .collect::<Vec<_>>(),
            )
            .unwrap();
        let most = counts.iter().map(|c| c.count).max().unwrap() as usize;
        let all: u64 = counts.iter().map(|c| c.count).sum();
        assert!(most > 400 && (all as usize) > 3 * most, "{most} {all}");
        let batches = |limit| bounded_chunks(&counts, limit).count();
        assert_eq!(batches(most), 12);
        assert!(batches(2 * most) > 1 && batches(2 * most) < 12);
        for limit in [most, most + 1, 2 * most, 5 * most, all as usize] {
            assert_eq!(run(limit).unwrap(), whole, "limit {limit}");
        }
        let err = run(most - 1).unwrap_err().to_string();
        assert!(
            err.contains(&format!("needs more than {} listed members", most - 1)),
            "{err}"
        );
    }
}
