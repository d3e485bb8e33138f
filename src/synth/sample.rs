//! Gaussian centres drawn from a mixture of edges, surfaces and a uniform background.
//!
//! The output is cut into fixed-size chunks, and chunk `c` draws from `Rng::fork(c)` of the
//! seed's generator, so the result depends on the seed and the chunk size only, never on
//! how many threads rayon runs.

use glam::DVec3;
use rayon::prelude::*;

use super::rng::Rng;
use crate::geom::{Aabb, Segment};

/// Points per independently seeded chunk. Fixed: changing it changes every scene.
pub(crate) const CHUNK: usize = 1 << 15;

/// What to sample and with which noise. Weights need not sum to 1; a part with nothing to
/// sample (no edges, no triangles, an empty box) gets none of the points.
pub(crate) struct PointSampler {
    /// Edges as (start, start-to-end vector), by length.
    edges: Option<AliasTable<(DVec3, DVec3)>>,
    /// Triangles by area.
    triangles: Option<AliasTable<[DVec3; 3]>>,
    background: Aabb,
    /// Cumulative probabilities of edge and of edge-or-face.
    p_edge: f64,
    p_edge_or_face: f64,
    edge_sigma: f64,
    face_sigma: f64,
    /// No part has anything to sample.
    empty: bool,
}

/// Walker's alias table (Vose's construction) over items: picks an item with probability
/// proportional to its weight in O(1). Each slot holds its item beside its threshold, so a
/// pick touches one or two cache lines; with 10^5 edges and 10^7 points, memory misses,
/// not arithmetic, set the speed.
pub(crate) struct AliasTable<T> {
    slots: Vec<Slot<T>>,
}

struct Slot<T> {
    /// Chance of keeping this slot's item rather than taking the alias slot's.
    keep: f64,
    alias: u32,
    item: T,
}

impl<T: Copy> AliasTable<T> {
    /// Table over `(item, weight)` pairs; items with a non-finite or non-positive weight
    /// are left out, so they are never picked. `None` when no weight is positive.
    pub fn new(weighted: impl Iterator<Item = (T, f64)>) -> Option<Self> {
        let (items, w): (Vec<T>, Vec<f64>) =
            weighted.filter(|(_, w)| w.is_finite() && *w > 0.0).unzip();
        let n = w.len();
        let total: f64 = w.iter().sum();
        if n == 0 || !total.is_finite() || n > u32::MAX as usize {
            return None;
        }
        let mut p: Vec<f64> = w.iter().map(|x| x * n as f64 / total).collect();
        let mut keep = vec![1.0; n];
        let mut alias: Vec<u32> = (0..n as u32).collect();
        let (mut small, mut large): (Vec<usize>, Vec<usize>) = (0..n).partition(|&i| p[i] < 1.0);
        while let (Some(&l), Some(&g)) = (small.last(), large.last()) {
            small.pop();
            keep[l] = p[l];
            alias[l] = g as u32;
            p[g] = (p[g] + p[l]) - 1.0;
            if p[g] < 1.0 {
                large.pop();
                small.push(g);
            }
        }
        // What is left is 1 up to rounding and keeps its own item (`keep` stays 1).
        let slots = items
            .into_iter()
            .zip(keep.into_iter().zip(alias))
            .map(|(item, (keep, alias))| Slot { keep, alias, item })
            .collect();
        Some(AliasTable { slots })
    }

    /// Item drawn by one uniform `u` in `[0, 1)`: its integer part picks the slot, its
    /// fraction decides between the slot's item and its alias's.
    pub fn pick(&self, u: f64) -> T {
        let n = self.slots.len();
        let x = u * n as f64;
        let i = (x as usize).min(n - 1);
        let slot = &self.slots[i];
        if x - (i as f64) < slot.keep {
            slot.item
        } else {
            self.slots[slot.alias as usize].item
        }
    }
}

/// Weight clamped into `[0, ∞)`, NaN as 0.
fn weight(w: f64) -> f64 {
    if w.is_finite() && w > 0.0 {
        w
    } else {
        0.0
    }
}

impl PointSampler {
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        edges: &[Segment],
        edge_weight: f64,
        edge_sigma: f64,
        triangles: Vec<[DVec3; 3]>,
        face_weight: f64,
        face_sigma: f64,
        background: Aabb,
        background_weight: f64,
    ) -> Self {
        let edges = AliasTable::new(edges.iter().map(|s| ((s.p1, s.p2 - s.p1), s.length())));
        let triangles = AliasTable::new(
            triangles
                .into_iter()
                .map(|t| (t, 0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length())),
        );
        let we = if edges.is_some() {
            weight(edge_weight)
        } else {
            0.0
        };
        let wf = if triangles.is_some() {
            weight(face_weight)
        } else {
            0.0
        };
        let wb = if background.is_empty()
            || !(background.min.is_finite() && background.max.is_finite())
        {
            0.0
        } else {
            weight(background_weight)
        };
        let total = we + wf + wb;
        let (p_edge, p_edge_or_face) = if total > 0.0 {
            (we / total, (we + wf) / total)
        } else {
            (0.0, 0.0)
        };
        PointSampler {
            edges,
            triangles,
            background,
            p_edge,
            p_edge_or_face,
            edge_sigma: weight(edge_sigma),
            face_sigma: weight(face_sigma),
            empty: total <= 0.0,
        }
    }

    fn one(&self, rng: &mut Rng) -> [f32; 3] {
        let u = rng.uniform();
        // A part with no table has probability 0, so the tables used here exist.
        let p = if let (true, Some(edges)) = (u < self.p_edge, &self.edges) {
            let (a, v) = edges.pick(rng.uniform());
            a + v * rng.uniform() + rng.normal3(self.edge_sigma)
        } else if let (true, Some(triangles)) = (u < self.p_edge_or_face, &self.triangles) {
            let t = triangles.pick(rng.uniform());
            // Uniform on the triangle: the square root undoes the area growth towards
            // the base.
            let r1 = rng.uniform().sqrt();
            let r2 = rng.uniform();
            t[0] * (1.0 - r1)
                + t[1] * (r1 * (1.0 - r2))
                + t[2] * (r1 * r2)
                + rng.normal3(self.face_sigma)
        } else {
            let b = &self.background;
            let f = DVec3::new(rng.uniform(), rng.uniform(), rng.uniform());
            b.min + (b.max - b.min) * f
        };
        [p.x as f32, p.y as f32, p.z as f32]
    }

    /// `n` points for `seed`, in parallel over fixed chunks; empty when there is nothing
    /// to sample.
    pub fn sample(&self, n: usize, seed: u64) -> Vec<[f32; 3]> {
        if self.empty {
            return Vec::new();
        }
        let root = Rng::new(seed);
        let mut out = vec![[0f32; 3]; n];
        out.par_chunks_mut(CHUNK)
            .enumerate()
            .for_each(|(c, chunk)| {
                let mut rng = root.fork(c as u64);
                for slot in chunk {
                    *slot = self.one(&mut rng);
                }
            });
        out
    }
}

/// Gaussian centres for line segments that come without a Gaussian model (the real
/// Line3D++ scenes): `n` points, a `1 - background_fraction` share spread uniformly along
/// the segments by length with isotropic normal noise `sigma`, the rest uniform in the
/// segments' bounding box. Invalid segments (docs/method.md#geometry) are ignored; without
/// a valid segment the result is empty. Synthetic: use it for tests and demos, never as a
/// stand-in for a trained model in reported numbers.
pub fn gaussians_around_segments(
    segs: &[Segment],
    n: usize,
    sigma: f64,
    background_fraction: f64,
    seed: u64,
) -> Vec<[f32; 3]> {
    let valid: Vec<Segment> = segs.iter().copied().filter(Segment::is_valid).collect();
    if valid.is_empty() {
        return Vec::new();
    }
    let bg = weight(background_fraction).min(1.0);
    PointSampler::new(
        &valid,
        1.0 - bg,
        sigma,
        Vec::new(),
        0.0,
        0.0,
        Aabb::of_segments(&valid),
        bg,
    )
    .sample(n, seed)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::p64;

    fn segs() -> Vec<Segment> {
        vec![
            Segment::from_arrays([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]),
            Segment::from_arrays([0.0, 1.0, 0.0], [0.0, 1.0, 3.0]),
            // invalid: ignored
            Segment::from_arrays([5.0, 5.0, 5.0], [5.0, 5.0, 5.0]),
        ]
    }

    #[test]
    fn alias_table_picks_by_weight_and_never_picks_zero_weights() {
        let w = [1.0, 0.0, 3.0, 6.0, f64::NAN, -2.0, 10.0];
        let t = AliasTable::new(w.iter().copied().enumerate()).unwrap();
        let mut hist = [0usize; 7];
        let mut rng = Rng::new(12);
        let n = 400_000;
        for _ in 0..n {
            hist[t.pick(rng.uniform())] += 1;
        }
        for (i, &h) in hist.iter().enumerate() {
            let want = if w[i] > 0.0 { w[i] / 20.0 } else { 0.0 };
            assert!((h as f64 / n as f64 - want).abs() < 0.003, "{i}: {hist:?}");
        }
        assert_eq!(hist[1] + hist[4] + hist[5], 0);
        assert!(AliasTable::new([(0, 0.0), (1, f64::NAN)].into_iter()).is_none());
        assert!(AliasTable::<u8>::new(std::iter::empty()).is_none());
        // The extremes of u stay in range.
        assert!(t.pick(0.0) < 7 && t.pick(1.0 - f64::EPSILON) < 7);
    }

    #[test]
    fn points_follow_the_segments_by_length_within_a_few_sigma() {
        let sigma = 0.01;
        let pts = gaussians_around_segments(&segs(), 40_000, sigma, 0.0, 17);
        assert_eq!(pts.len(), 40_000);
        let s = segs();
        let mut near = [0usize; 2];
        for p in &pts {
            let p = p64(*p);
            let d: Vec<f64> = s[..2]
                .iter()
                .map(|seg| {
                    let t = seg.axial(p).clamp(0.0, seg.length());
                    (p - seg.point_at(t)).length()
                })
                .collect();
            // 3D noise: distance is chi with 3 degrees of freedom; 6 sigma is never
            // reached in 40,000 draws (p < 1e-7 each).
            let (i, dmin) = if d[0] < d[1] { (0, d[0]) } else { (1, d[1]) };
            assert!(dmin < 6.0 * sigma, "{p} is {dmin} from the segments");
            near[i] += 1;
        }
        // Lengths 1 and 3: a quarter of the points on the first segment.
        let share = near[0] as f64 / pts.len() as f64;
        assert!((share - 0.25).abs() < 0.01, "share {share}");
    }

    #[test]
    fn background_fills_the_bounding_box() {
        let pts = gaussians_around_segments(&segs(), 20_000, 0.0, 1.0, 3);
        let bb = Aabb::of_segments(&segs()[..2]);
        let mut far = 0;
        for p in &pts {
            let p = p64(*p);
            assert!(bb.grown(1e-6).contains(p));
            if p.y > 0.1 && p.y < 0.9 {
                far += 1;
            }
        }
        // With no line share, 80 % of the points lie between the segments' y = 0 and 1.
        assert!((far as f64 / 20_000.0 - 0.8).abs() < 0.02);
    }

    #[test]
    fn same_seed_same_points_and_nothing_without_segments() {
        let a = gaussians_around_segments(&segs(), 5_000, 0.01, 0.1, 1);
        let b = gaussians_around_segments(&segs(), 5_000, 0.01, 0.1, 1);
        let c = gaussians_around_segments(&segs(), 5_000, 0.01, 0.1, 2);
        assert_eq!(a, b);
        assert_ne!(a, c);
        assert!(gaussians_around_segments(&segs()[2..], 100, 0.01, 0.1, 1).is_empty());
        assert!(gaussians_around_segments(&[], 100, 0.01, 0.1, 1).is_empty());
        assert!(gaussians_around_segments(&segs(), 0, 0.01, 0.1, 1).is_empty());
    }

    #[test]
    fn chunks_beyond_the_first_are_seeded_by_their_number() {
        // The second chunk must not repeat the first one's points.
        let pts = gaussians_around_segments(&segs(), 2 * CHUNK, 0.01, 0.0, 4);
        assert_ne!(pts[0], pts[CHUNK]);
        assert_ne!(pts[1], pts[CHUNK + 1]);
    }
}
