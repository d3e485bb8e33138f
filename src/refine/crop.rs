//! Step 9, overextension: an end whose window is sparse next to the middle of the segment
//! is cut back by a binary search for the end of the dense part. All segments' window
//! counts go as one batch, then each round of probes (every active end) as one batch.

use crate::engine::{Engine, EngineError, Query, Want};
use crate::geom::Segment;
use crate::refine::params::{group, Check};
use crate::refine::{Fixes, Pass, Settings, Step};

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

/// Fix `crop_chance`: the largest chance of an end window so sparse at the middle's
/// density for which the end is still searched (as `--split-gaps`' default level).
pub const CROP_CHANCE: f64 = 0.01;

/// `P(X <= n)` for `X ~ Poisson(lambda)` (1 for `lambda <= 0`).
pub fn poisson_cdf(n: u64, lambda: f64) -> f64 {
    if lambda.is_nan() || lambda <= 0.0 {
        return 1.0;
    }
    // Terms in log space: exp(k ln(lambda) - lambda - ln k!), summed while they matter.
    let mut log_term = -lambda;
    let mut sum = log_term.exp();
    for k in 1..=n {
        log_term += lambda.ln() - (k as f64).ln();
        sum += log_term.exp();
        if sum >= 1.0 {
            return 1.0;
        }
    }
    sum.min(1.0)
}

/// Whether `P(X <= n) <= alpha` for `X ~ Poisson(lambda)`. Below the mean the Chernoff
/// bound `exp(-lambda) (e lambda / n)^n` decides most cases at once (it bounds the
/// probability from above); the exact sum, [`poisson_cdf`], decides the rest, whose
/// means are small, so a dense model's large counts cost no long sum.
pub fn poisson_at_most(n: u64, lambda: f64, alpha: f64) -> bool {
    let k = n as f64;
    if k > 0.0 && k < lambda {
        let log_bound = -lambda + k * (1.0 + (lambda / k).ln());
        if log_bound <= alpha.ln() {
            return true;
        }
    }
    poisson_cdf(n, lambda) <= alpha
}

pub fn crop(
    engine: &dyn Engine,
    segments: &[Segment],
    s: &Settings,
) -> Result<Vec<Segment>, EngineError> {
    let (r, p, fixes) = (s.radius(), &s.params().crop, s.fixes());
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
            let n_end = w[3 * i + end].count;
            let de = super::density(n_end, e);
            // Fix `crop_chance`: the end window must be sparse beyond chance, not only
            // below the ratio: at the middle's density it would hold `dm x e` points on
            // average, and so few (or fewer) come by chance at most CROP_CHANCE of the
            // time. A sparse model's end window expects a point or two, and its
            // emptiness says nothing; a dense model's says as much as before.
            let sparse = de < p.crop_ratio * dm;
            if sparse && (!fixes.crop_chance || poisson_at_most(n_end, dm * e, CROP_CHANCE)) {
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
                let h = p.probe_half(fixes) * seg.length();
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
                let dens = super::density(st.count, 2.0 * p.probe_half(fixes) * seg.length());
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
    if p.crop_extend > 0.0 {
        // The ends that crop left alone: their windows are dense.
        let mut sparse = vec![[false; 2]; segments.len()];
        for s in &searches {
            sparse[s.seg][usize::from(!s.first)] = true;
        }
        let dense: Vec<(usize, bool)> = (0..segments.len())
            .flat_map(|i| [(i, true), (i, false)])
            .filter(|&(i, first)| !sparse[i][usize::from(!first)])
            .collect();
        for (i, first, u) in extend(engine, segments, &dense, &mid_density, r, p, fixes)? {
            if first {
                ends[i].0 = -u;
            } else {
                ends[i].1 = segments[i].length() + u;
            }
        }
    }
    // The cuts the search found: (search, where, how long).
    let mut cuts = Vec::with_capacity(searches.len());
    for (j, s) in searches.iter().enumerate() {
        let t = 0.5 * (s.a + s.b);
        // Fix `crop_min_cut`: a sparse stretch shorter than the cylinder's radius at an end
        // is no overextension: it is where the Gaussians thin out at a corner (trained
        // models thin out within a splat's size of an edge, more where edges meet), as
        // `--split-gaps` leaves interior holes shorter than r.
        let cut = if s.first {
            t
        } else {
            segments[s.seg].length() - t
        };
        if fixes.crop_min_cut && cut < r {
            continue;
        }
        cuts.push((j, t, cut));
    }
    if fixes.crop_stretch && !cuts.is_empty() {
        // Fix `crop_stretch`: the whole stretch to be cut must be sparse, as the end window
        // was, not only the probe where the search stopped. An overextension past the true
        // end holds few points all along; a stretch of a model whose Gaussians come in
        // clumps along the edge (flat splats on uniform faces, dense only where the colour
        // changes) holds about the middle's density, and its gaps between clumps are no end.
        let stretches: Vec<Query> = cuts
            .iter()
            .map(|&(j, t, _)| {
                let s = &searches[j];
                let seg = &segments[s.seg];
                if s.first {
                    Query::new(seg.sub(0.0, t), r)
                } else {
                    Query::new(seg.sub(t, seg.length()), r)
                }
            })
            .collect();
        let counts = engine.stats(&stretches, Want::COUNT)?;
        let mut k = 0;
        cuts.retain(|&(j, _, cut)| {
            let n = counts[k].count;
            k += 1;
            let dm = mid_density[searches[j].seg];
            super::density(n, cut) < p.crop_ratio * dm
                && (!fixes.crop_chance || poisson_at_most(n, dm * cut, CROP_CHANCE))
        });
    }
    for &(j, t, _) in &cuts {
        let s = &searches[j];
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

/// One dense end marching outward: `u` is how far past the end it has got.
#[derive(Clone, Copy, Debug)]
struct March {
    seg: usize,
    first: bool,
    u: f64,
    /// Bisection interval once a sparse window was met.
    bisect: Option<(f64, f64)>,
    probes: u32,
    /// Windows marched so far; bounded by [`MAX_MARCH_STEPS`].
    steps: u32,
    done: bool,
}

/// Most windows one end marches outward: the march is otherwise bounded only by
/// `crop_extend / (2 x crop_probe_half)`, which a tiny probe makes arbitrarily large.
const MAX_MARCH_STEPS: u32 = 256;

/// `--crop-extend`: each dense end `(segment, is_p1)` moves outward along its line while
/// the next window of `2 h` past it is dense (density >= `crop_ratio x` the middle
/// density of the pre-crop segment), at most `crop_extend x L`; the first sparse window is
/// bisected as the crop's search is. Returns `(segment, is_p1, distance past the end)` for
/// the ends that moved. One batch per round over all ends still moving.
fn extend(
    engine: &dyn Engine,
    segments: &[Segment],
    dense: &[(usize, bool)],
    mid_density: &[f64],
    r: f64,
    p: &CropParams,
    fixes: &Fixes,
) -> Result<Vec<(usize, bool, f64)>, EngineError> {
    let mut m: Vec<March> = dense
        .iter()
        .filter(|&&(i, _)| mid_density[i] > 0.0)
        .map(|&(seg, first)| March {
            seg,
            first,
            u: 0.0,
            bisect: None,
            probes: 0,
            steps: 0,
            done: false,
        })
        .collect();
    // The window `[u0, u1]` past an end, as a segment along the line.
    let window = |k: &March, u0: f64, u1: f64| {
        let s = &segments[k.seg];
        let (end, out) = if k.first {
            (s.p1, -s.dir())
        } else {
            (s.p2, s.dir())
        };
        Segment::new(end + out * u0, end + out * u1)
    };
    loop {
        let active: Vec<usize> = (0..m.len()).filter(|&j| !m[j].done).collect();
        if active.is_empty() {
            break;
        }
        let queries: Vec<Query> = active
            .iter()
            .map(|&j| {
                let k = &m[j];
                let h = p.probe_half(fixes) * segments[k.seg].length();
                match k.bisect {
                    None => Query::new(window(k, k.u, k.u + 2.0 * h), r),
                    Some((a, b)) => {
                        let c = 0.5 * (a + b);
                        Query::new(window(k, c - h, c + h), r)
                    }
                }
            })
            .collect();
        let res = engine.stats(&queries, Want::COUNT)?;
        for (&j, st) in active.iter().zip(&res) {
            let k = &mut m[j];
            let l = segments[k.seg].length();
            let h = p.probe_half(fixes) * l;
            let limit = p.crop_extend * l;
            let is_dense = super::density(st.count, 2.0 * h) >= p.crop_ratio * mid_density[k.seg];
            match k.bisect {
                None if is_dense => {
                    k.u = (k.u + 2.0 * h).min(limit);
                    k.steps += 1;
                    k.done = k.u >= limit || k.steps >= MAX_MARCH_STEPS;
                }
                None => k.bisect = Some((k.u, (k.u + 2.0 * h).min(limit))),
                Some((a, b)) => {
                    let c = 0.5 * (a + b);
                    let (a, b) = if is_dense { (c, b) } else { (a, c) };
                    k.probes += 1;
                    k.bisect = Some((a, b));
                    if k.probes >= p.crop_max_probes || b - a < p.crop_min_interval {
                        k.u = 0.5 * (a + b);
                        k.done = true;
                    }
                }
            }
        }
    }
    Ok(m.into_iter()
        .filter(|k| k.u > 0.0)
        .map(|k| (k.seg, k.first, k.u))
        .collect())
}

group! {
    /// Step 9's parameters.
    pub struct CropParams {
        /// Crop: length of each end window as a fraction of L.
        crop_end_frac: f64 = 0.02, Check::Fraction;
        /// Crop: length of the middle window as a fraction of L.
        crop_mid_frac: f64 = 0.6, Check::Fraction;
        /// Crop: an end (or probe) is sparse below this x the middle density.
        crop_ratio: f64 = 0.5, Check::Fraction;
        /// Crop: half length of a binary-search probe window, as a fraction of L. Default:
        /// 0.1 with the authors' side-balance test (their `m ± 0.1 L`), 0.03 with the density
        /// test, whose window centred on the true end holds half the middle density whatever
        /// its size; a short window keeps the Gaussians of edges meeting at a corner from
        /// holding the end out past the corner.
        crop_probe_half: Option<f64> = None, Check::Positive;
        /// Crop: also extend an end whose window is dense, along the line, while windows past
        /// it stay dense, by at most this x L (0: never extend, the paper's crop). Windows of
        /// 2 x the probe half length march outward, one batch per step, and the last is
        /// bisected; a corner stops the march, since past it the cylinder holds only the
        /// other edge's cross-section. 0 to 10; at most 256 windows an end.
        crop_extend: f64 = 0.0, Check::ExtendFactor;
        /// Crop: most probes of the binary search, 1 to 64 (after 53 halvings an f64
        /// interval cannot shrink further, so more would only spin).
        crop_max_probes: u32 = 10, Check::Whole { lo: 1, hi: 64 };
        /// Crop: the binary search stops when its interval is shorter than this (a positive
        /// number; the probe limit bounds the search whatever its value).
        crop_min_interval: f64 = 1e-4, Check::Positive;
    }
}

impl CropParams {
    /// The probe half window in effect (see `crop_probe_half`).
    pub fn probe_half(&self, fixes: &Fixes) -> f64 {
        self.crop_probe_half
            .unwrap_or(if fixes.crop_density { 0.03 } else { 0.1 })
    }
}

/// Step 9, the stage `crop`.
pub struct Crop;

impl Step for Crop {
    fn name(&self) -> &'static str {
        "crop"
    }

    fn run(&self, pass: &mut Pass) -> Result<(), EngineError> {
        pass.lines.segments = crop(pass.engine, &pass.lines.segments, pass.settings)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::{poisson_at_most, poisson_cdf};

    #[test]
    fn poisson_cdf_matches_the_closed_forms() {
        // P(X <= 0) = e^-l, P(X <= 1) = e^-l (1 + l), and the whole mass is 1.
        for l in [0.5, 2.0, 7.3] {
            assert!((poisson_cdf(0, l) - (-l).exp()).abs() < 1e-15);
            assert!((poisson_cdf(1, l) - (-l).exp() * (1.0 + l)).abs() < 1e-15);
            assert!((poisson_cdf(200, l) - 1.0).abs() < 1e-12);
        }
        // An end window expecting 1.2 points is empty by chance 30 % of the time: never
        // beyond chance; expecting 20 and holding 3 is (2e-6).
        assert!(poisson_cdf(0, 1.2) > 0.3);
        assert!(poisson_cdf(3, 20.0) < 1e-5);
        // No density: nothing is beyond chance.
        assert_eq!(poisson_cdf(0, 0.0), 1.0);
        assert_eq!(poisson_cdf(0, f64::NAN), 1.0);
        // A dense model's count far below its mean underflows to 0, not NaN.
        assert_eq!(poisson_cdf(5, 5000.0), 0.0);
    }

    #[test]
    fn the_bounded_test_decides_as_the_exact_sum() {
        for lambda in [0.3, 1.2, 5.0, 20.0, 33.0, 80.0, 400.0] {
            for n in 0..(2.0 * lambda) as u64 + 3 {
                assert_eq!(
                    poisson_at_most(n, lambda, 0.01),
                    poisson_cdf(n, lambda) <= 0.01,
                    "n {n} lambda {lambda}"
                );
            }
        }
        // A huge count far below its mean: decided by the bound, no sum of 10^6 terms.
        assert!(poisson_at_most(1_000_000, 3_000_000.0, 0.01));
    }
}
