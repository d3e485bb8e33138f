//! Step 9, overextension: an end whose window is sparse next to the middle of the segment
//! is cut back by a binary search for the end of the dense part. All segments' window
//! counts go as one batch, then each round of probes (every active end) as one batch.

use crate::engine::{Engine, EngineError, Query, Want};
use crate::geom::Segment;
use crate::refine::Settings;

/// Binary-search state of one end, in axial coordinates of the pre-crop segment.
#[derive(Clone, Copy, Debug)]
struct Search {
    seg: usize,
    /// `true` for the P1 end (inward = increasing t), `false` for P2.
    first: bool,
    a: f64,
    b: f64,
    probes: u32,
    done: bool,
}

pub fn crop(
    engine: &dyn Engine,
    segments: &[Segment],
    s: &Settings,
) -> Result<Vec<Segment>, EngineError> {
    let (r, p, fixes) = (s.radius(), s.params(), s.fixes());
    // Windows: [0, e L], [(1-e) L, L] and the middle m L around the midpoint.
    let mut queries = Vec::with_capacity(segments.len() * 3);
    for s in segments {
        let l = s.length();
        let e = p.crop_end_frac * l;
        let h = 0.5 * p.crop_mid_frac * l;
        queries.push(Query::new(s.sub(0.0, e), r));
        queries.push(Query::new(s.sub(l - e, l), r));
        queries.push(Query::new(s.sub(0.5 * l - h, 0.5 * l + h), r));
    }
    let w = engine.stats(&queries, Want::COUNT)?;
    let mut mid_density = Vec::with_capacity(segments.len());
    let mut searches = Vec::new();
    for (i, s) in segments.iter().enumerate() {
        let l = s.length();
        let e = p.crop_end_frac * l;
        let dm = super::density(w[3 * i + 2].count, p.crop_mid_frac * l);
        mid_density.push(dm);
        for (end, first) in [(0usize, true), (1, false)] {
            let de = super::density(w[3 * i + end].count, e);
            if de < p.crop_ratio * dm {
                let (a, b) = if first { (0.0, 0.5 * l) } else { (0.5 * l, l) };
                searches.push(Search {
                    seg: i,
                    first,
                    a,
                    b,
                    probes: 0,
                    done: false,
                });
            }
        }
    }
    loop {
        let active: Vec<usize> = (0..searches.len())
            .filter(|&j| {
                let s = &searches[j];
                // At most 64 probes whatever the options say: beyond 53 halvings an f64
                // interval stops shrinking, and a tiny `crop_min_interval` would spin.
                !s.done
                    && s.probes < p.crop_max_probes.min(64)
                    && (s.b - s.a) >= p.crop_min_interval
            })
            .collect();
        if active.is_empty() {
            break;
        }
        let probes: Vec<Query> = active
            .iter()
            .map(|&j| {
                let s = &searches[j];
                let seg = &segments[s.seg];
                let h = p.crop_probe_half() * seg.length();
                let m = 0.5 * (s.a + s.b);
                Query::with_plane(seg.sub(m - h, m + h), r, seg.point_at(m))
            })
            .collect();
        let want = if fixes.crop_density {
            Want::COUNT
        } else {
            Want::SIDES
        };
        let res = engine.stats(&probes, want)?;
        for (&j, st) in active.iter().zip(&res) {
            let s = &mut searches[j];
            let seg = &segments[s.seg];
            s.probes += 1;
            let m = 0.5 * (s.a + s.b);
            // +1 moves the end outward (away from the midpoint), -1 inward, 0 stays.
            let step: i32 = if fixes.crop_density {
                let dens = super::density(st.count, 2.0 * p.crop_probe_half() * seg.length());
                if dens >= p.crop_ratio * mid_density[s.seg] {
                    1
                } else {
                    -1
                }
            } else if st.count == 0 {
                -1
            } else {
                let diff = (st.side_pos as f64 - st.side_neg() as f64).abs() / st.count as f64;
                if diff > 0.5 {
                    -1
                } else if diff < 0.5 {
                    1
                } else {
                    0
                }
            };
            match (step, s.first) {
                (0, _) => s.done = true,
                (1, true) | (-1, false) => s.b = m,
                _ => s.a = m,
            }
        }
    }
    let mut ends: Vec<(f64, f64)> = segments.iter().map(|s| (0.0, s.length())).collect();
    for s in &searches {
        let t = 0.5 * (s.a + s.b);
        if s.first {
            ends[s.seg].0 = t;
        } else {
            ends[s.seg].1 = t;
        }
    }
    Ok(segments
        .iter()
        .zip(&ends)
        .map(|(s, &(a, b))| {
            if a == 0.0 && b == s.length() {
                *s
            } else {
                Segment::new(
                    if a == 0.0 { s.p1 } else { s.point_at(a) },
                    if b == s.length() { s.p2 } else { s.point_at(b) },
                )
            }
        })
        .collect())
}
