//! The paper's toy scene (LineGS sec. 3.2): boxes and quadrilaterals whose edges carry
//! dense Gaussian ridges, and input segments with each defect planted in known amounts.

use glam::DVec3;

use super::rng::Rng;
use super::sample::PointSampler;
use super::world::{Layout, World};
use super::{assemble, Defect, SynthScene, Unit};
use crate::geom::{Aabb, Segment};

/// Slots 1 unit apart hold solids of 0.2–0.4 units: a 3 x 2 x 2 lattice spans about 2.4
/// units, and an edge extended by 30 % still ends more than 0.18 from any other solid.
pub(crate) const TOY_LAYOUT: Layout = Layout {
    spacing: 1.0,
    size_min: 0.2,
    size_max: 0.4,
};

/// How many defects to plant, as shares of the ground-truth edges.
///
/// Each edge gets one primary segment that is offset, overextended, split or clean (the
/// three shares are taken in that order and capped so that they fit), and, independently,
/// a `duplicated` share of the edges gets 2–3 extra copies.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DefectAmounts {
    /// Share of edges whose segment is moved perpendicular to the edge (position bias).
    pub offset: f64,
    /// Share of edges whose segment runs past the edge into empty space.
    pub overextended: f64,
    /// Share of edges broken into 2–3 pieces with gaps (discontinuity).
    pub split: f64,
    /// Share of edges that get 2–3 extra copies from other input lines (duplication).
    pub duplicated: f64,
    /// Number of segments in empty space (outliers).
    pub outliers: usize,
}

impl Default for DefectAmounts {
    fn default() -> Self {
        DefectAmounts {
            offset: 0.2,
            overextended: 0.2,
            split: 0.2,
            duplicated: 0.3,
            outliers: 40,
        }
    }
}

/// How large the planted defects are.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DefectSizes {
    /// Perpendicular offset of an offset segment, in multiples of the query radius. The
    /// translate step can only pull back what its cylinder reaches, so the bias stays
    /// below r.
    pub offset: (f64, f64),
    /// Extension of each extended end, as a share of the edge length. Up to 0.3 the
    /// layout keeps the extension in empty space.
    pub overextension: (f64, f64),
    /// Length of each gap between split pieces, as a share of the edge length.
    pub split_gap: (f64, f64),
    /// Largest lateral offset of a duplicate, in multiples of the query radius.
    pub duplicate_offset: f64,
    /// Largest angle between a duplicate and its edge, in degrees.
    pub duplicate_angle_deg: f64,
    /// Largest share of the edge length cut from each end of a duplicate.
    pub duplicate_trim: f64,
    /// Length range of outliers, in scene units.
    pub outlier_length: (f64, f64),
    /// Smallest distance from an outlier to any solid (and so to its Gaussian clusters),
    /// in scene units; capped at 0.4 x the slot spacing.
    pub outlier_clearance: f64,
}

impl Default for DefectSizes {
    fn default() -> Self {
        DefectSizes {
            offset: (0.3, 0.8),
            overextension: (0.1, 0.3),
            split_gap: (0.05, 0.15),
            duplicate_offset: 0.3,
            duplicate_angle_deg: 1.0,
            duplicate_trim: 0.15,
            outlier_length: (0.1, 0.3),
            outlier_clearance: 0.1,
        }
    }
}

/// Parameters of [`toy_scene`]. The defaults make the paper's toy scene: 9 boxes and 3
/// quadrilaterals (120 edges) spanning about 2 units, 20,000 Gaussians and about 290
/// segments, at the scale of a 0.03 query radius.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToyParams {
    pub seed: u64,
    pub n_gaussians: usize,
    pub n_boxes: usize,
    pub n_quads: usize,
    /// Share of the Gaussians along the edges.
    pub edge_fraction: f64,
    /// Share of the Gaussians uniform in the scene's box; the rest lie on the faces.
    pub background_fraction: f64,
    /// Standard deviation (per axis) of edge Gaussians around their edge.
    pub noise_sigma: f64,
    /// Standard deviation (per axis) of face Gaussians around their face.
    pub face_sigma: f64,
    /// Standard deviation (per axis) of the noise on every segment endpoint.
    pub endpoint_sigma: f64,
    /// The query radius the defect sizes are measured in (docs/method.md#step-2-radius default).
    pub radius: f64,
    pub defects: DefectAmounts,
    pub sizes: DefectSizes,
}

impl Default for ToyParams {
    fn default() -> Self {
        ToyParams {
            seed: 2024,
            n_gaussians: 20_000,
            n_boxes: 9,
            n_quads: 3,
            edge_fraction: 0.6,
            background_fraction: 0.03,
            noise_sigma: 0.004,
            face_sigma: 0.002,
            endpoint_sigma: 0.002,
            radius: 0.03,
            defects: DefectAmounts::default(),
            sizes: DefectSizes::default(),
        }
    }
}

/// Clamps a share into `[0, 1]`, NaN as 0.
fn share(x: f64) -> f64 {
    if x.is_nan() {
        0.0
    } else {
        x.clamp(0.0, 1.0)
    }
}

/// Plants defects on ground-truth edges.
pub(crate) struct Planter<'a> {
    pub radius: f64,
    pub endpoint_sigma: f64,
    pub sizes: &'a DefectSizes,
}

impl Planter<'_> {
    fn noisy(&self, s: Segment, rng: &mut Rng) -> Segment {
        Segment::new(
            s.p1 + rng.normal3(self.endpoint_sigma),
            s.p2 + rng.normal3(self.endpoint_sigma),
        )
    }

    fn unit(segment: Segment, defect: Defect, source: usize) -> Unit {
        Unit {
            segments: vec![segment],
            defect,
            source: Some(source as u32),
        }
    }

    pub fn clean(&self, gt: &Segment, source: usize, rng: &mut Rng) -> Unit {
        Self::unit(self.noisy(*gt, rng), Defect::Clean, source)
    }

    pub fn offset(&self, gt: &Segment, source: usize, rng: &mut Rng) -> Unit {
        let (lo, hi) = self.sizes.offset;
        let t = rng.perpendicular(gt.dir()) * (rng.range(lo, hi) * self.radius);
        Self::unit(self.noisy(gt.translated(t), rng), Defect::Offset, source)
    }

    pub fn overextended(&self, gt: &Segment, source: usize, rng: &mut Rng) -> Unit {
        let (lo, hi) = self.sizes.overextension;
        let l = gt.length();
        // 0: before P1 only, 1: past P2 only, 2: both ends.
        let ends = rng.below(3);
        let e1 = if ends != 1 {
            rng.range(lo, hi) * l
        } else {
            0.0
        };
        let e2 = if ends != 0 {
            rng.range(lo, hi) * l
        } else {
            0.0
        };
        let s = gt.sub(-e1, l + e2);
        Self::unit(self.noisy(s, rng), Defect::Overextended, source)
    }

    /// `pieces` pieces separated by gaps, together spanning the edge.
    pub fn split(&self, gt: &Segment, pieces: usize, source: usize, rng: &mut Rng) -> Unit {
        let (lo, hi) = self.sizes.split_gap;
        let l = gt.length();
        let gaps: Vec<f64> = (1..pieces).map(|_| rng.range(lo, hi) * l).collect();
        let solid = (l - gaps.iter().sum::<f64>()).max(0.0);
        // Unequal pieces, none shorter than a seventh of the solid length.
        let weights: Vec<f64> = (0..pieces).map(|_| rng.range(0.5, 1.5)).collect();
        let wsum: f64 = weights.iter().sum();
        let mut t = 0.0;
        let mut segments = Vec::with_capacity(pieces);
        for (i, w) in weights.iter().enumerate() {
            let len = solid * w / wsum;
            segments.push(self.noisy(gt.sub(t, t + len), rng));
            t += len + gaps.get(i).copied().unwrap_or(0.0);
        }
        Unit {
            segments,
            defect: Defect::Split,
            source: Some(source as u32),
        }
    }

    /// A copy with both ends trimmed a little, moved sideways a little and turned a little.
    pub fn duplicate(&self, gt: &Segment, source: usize, rng: &mut Rng) -> Unit {
        let s = self.sizes;
        let l = gt.length();
        let sub = gt.sub(
            rng.range(0.0, s.duplicate_trim) * l,
            l - rng.range(0.0, s.duplicate_trim) * l,
        );
        let d = gt.dir();
        let shift = rng.perpendicular(d) * (rng.range(0.0, s.duplicate_offset) * self.radius);
        let tilt = rng.range(0.0, s.duplicate_angle_deg).to_radians().tan() * 0.5 * sub.length();
        let w = rng.perpendicular(d) * tilt;
        let copy = Segment::new(sub.p1 + shift - w, sub.p2 + shift + w);
        Self::unit(self.noisy(copy, rng), Defect::Duplicate, source)
    }

    /// A segment inside `bounds` that keeps `clearance` from every solid, or `None` when
    /// 10,000 tries find no room.
    pub fn outlier(&self, world: &World, bounds: &Aabb, rng: &mut Rng) -> Option<Unit> {
        let clearance = self.sizes.outlier_clearance.min(0.4 * world.layout.spacing);
        let step = 0.25 * clearance;
        let (lo, hi) = self.sizes.outlier_length;
        for _ in 0..10_000 {
            let f = DVec3::new(rng.uniform(), rng.uniform(), rng.uniform());
            let mid = bounds.min + (bounds.max - bounds.min) * f;
            let half = rng.unit_vector() * (0.5 * rng.range(lo, hi));
            let s = Segment::new(mid - half, mid + half);
            // Probes every `step` can miss up to step/2, so ask for that much more.
            if s.is_valid() && world.segment_clearance(&s, step) >= clearance + 0.5 * step {
                return Some(Unit {
                    segments: vec![s],
                    defect: Defect::Outlier,
                    source: None,
                });
            }
        }
        None
    }
}

/// Where outliers go: the solids' box grown by 10 % of its longest edge, or the cube
/// `[-1, 1]^3` for a world without solids.
pub(crate) fn outlier_bounds(world: &World) -> Aabb {
    let b = world.aabb();
    if b.is_empty() {
        Aabb {
            min: DVec3::splat(-1.0),
            max: DVec3::splat(1.0),
        }
    } else {
        b.grown(0.1)
    }
}

/// Gaussians of a world: edges, faces, and background in the solids' box grown by 5 %.
pub(crate) fn world_sampler(
    world: &World,
    gt: &[Segment],
    edge_fraction: f64,
    background_fraction: f64,
    edge_sigma: f64,
    face_sigma: f64,
) -> PointSampler {
    let edge = share(edge_fraction);
    let background = share(background_fraction).min(1.0 - edge);
    let bounds = world.aabb();
    let bounds = if bounds.is_empty() {
        bounds
    } else {
        bounds.grown(0.05)
    };
    PointSampler::new(
        gt,
        edge,
        edge_sigma,
        world.triangles(),
        1.0 - edge - background,
        face_sigma,
        bounds,
        background,
    )
}

/// The paper's toy scene with every defect planted; deterministic for `p.seed`.
///
/// Gaussians: `edge_fraction` along the ground-truth edges (uniform along each edge,
/// isotropic normal noise `noise_sigma`), `background_fraction` uniform in the scene's
/// box, the rest uniform on the faces of the boxes and on the quadrilaterals. Segments: one
/// primary per edge (clean, offset, overextended or split, see [`DefectAmounts`]),
/// duplicates, and outliers, every endpoint with noise `endpoint_sigma`; the segments are
/// shuffled, keeping the pieces of each split edge together in one group.
pub fn toy_scene(p: &ToyParams) -> SynthScene {
    let root = Rng::new(p.seed);
    // Separate streams, so that, say, more Gaussians leave the segments unchanged.
    let world = World::generate(p.n_boxes, p.n_quads, TOY_LAYOUT, &mut root.fork(0));
    let gt = world.edges();
    let gaussians = world_sampler(
        &world,
        &gt,
        p.edge_fraction,
        p.background_fraction,
        p.noise_sigma,
        p.face_sigma,
    )
    .sample(p.n_gaussians, root.fork(1).next_u64());

    let mut rng = root.fork(2);
    let e = gt.len();
    let count = |x: f64, left: usize| ((share(x) * e as f64).round() as usize).min(left);
    let n_offset = count(p.defects.offset, e);
    let n_over = count(p.defects.overextended, e - n_offset);
    let n_split = count(p.defects.split, e - n_offset - n_over);
    let mut primary: Vec<Defect> = [
        (Defect::Offset, n_offset),
        (Defect::Overextended, n_over),
        (Defect::Split, n_split),
        (Defect::Clean, e - n_offset - n_over - n_split),
    ]
    .iter()
    .flat_map(|&(d, n)| std::iter::repeat_n(d, n))
    .collect();
    rng.shuffle(&mut primary);
    let mut duplicated: Vec<usize> = (0..e).collect();
    rng.shuffle(&mut duplicated);
    duplicated.truncate(count(p.defects.duplicated, e));
    duplicated.sort_unstable();

    let planter = Planter {
        radius: p.radius,
        endpoint_sigma: p.endpoint_sigma,
        sizes: &p.sizes,
    };
    let mut units = Vec::new();
    for (i, (g, kind)) in gt.iter().zip(&primary).enumerate() {
        units.push(match kind {
            Defect::Offset => planter.offset(g, i, &mut rng),
            Defect::Overextended => planter.overextended(g, i, &mut rng),
            Defect::Split => planter.split(g, 2 + rng.below(2) as usize, i, &mut rng),
            _ => planter.clean(g, i, &mut rng),
        });
    }
    for &i in &duplicated {
        for _ in 0..2 + rng.below(2) {
            units.push(planter.duplicate(&gt[i], i, &mut rng));
        }
    }
    let bounds = outlier_bounds(&world);
    units
        .extend((0..p.defects.outliers).filter_map(|_| planter.outlier(&world, &bounds, &mut rng)));
    let (lines, labels, gt_index) = assemble(units, &mut rng);

    let mut scene = SynthScene {
        gaussians,
        lines,
        gt,
        labels,
        gt_index,
        description: String::new(),
    };
    scene.description = format!(
        "SYNTHETIC toy scene in the style of LineGS sec. 3.2 (seed {}): {} boxes and {} \
         quadrilaterals with {} ground-truth edges; {} Gaussian centres ({:.0} % along edges, \
         {:.0} % uniform background, the rest on faces; edge noise sigma {}); {} input \
         segments ({}), defect sizes relative to radius {}.",
        p.seed,
        p.n_boxes,
        p.n_quads,
        scene.gt.len(),
        scene.gaussians.len(),
        100.0 * share(p.edge_fraction),
        100.0 * share(p.background_fraction).min(1.0 - share(p.edge_fraction)),
        p.noise_sigma,
        scene.lines.len(),
        scene.label_summary(),
        p.radius,
    );
    scene
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::p64;
    use std::collections::HashMap;

    fn scene() -> SynthScene {
        toy_scene(&ToyParams::default())
    }

    /// Distance from `p` to the closed segment `s`.
    fn dist_to_segment(s: &Segment, p: DVec3) -> f64 {
        let t = s.axial(p).clamp(0.0, s.length());
        (p - s.point_at(t)).length()
    }

    /// Gaussians inside the flat-capped cylinder of docs/method.md#geometry.
    fn count_in(s: &Segment, r: f64, pts: &[[f32; 3]]) -> usize {
        pts.iter()
            .filter(|p| s.cylinder_contains(p64(**p), r))
            .count()
    }

    fn of_kind(sc: &SynthScene, d: Defect) -> Vec<(Segment, Segment)> {
        (0..sc.lines.len())
            .filter(|&i| sc.labels[i] == d)
            .map(|i| {
                (
                    sc.lines.segments[i],
                    sc.gt[sc.gt_index[i].unwrap() as usize],
                )
            })
            .collect()
    }

    #[test]
    fn default_scene_has_the_papers_sizes_and_the_planted_counts() {
        let sc = scene();
        assert!(sc.description.starts_with("SYNTHETIC"));
        assert_eq!(sc.gt.len(), 9 * 12 + 3 * 4);
        assert_eq!(sc.gaussians.len(), 20_000);
        let n = sc.lines.len();
        assert!((250..=350).contains(&n), "{n} segments");
        assert_eq!(sc.labels.len(), n);
        assert_eq!(sc.gt_index.len(), n);
        assert_eq!(sc.lines.groups.as_ref().unwrap().len(), n);
        // 20 % of 120 edges each, whole units.
        assert_eq!(sc.count(Defect::Offset), 24);
        assert_eq!(sc.count(Defect::Overextended), 24);
        assert_eq!(sc.count(Defect::Clean), 48);
        assert_eq!(sc.count(Defect::Outlier), 40);
        let split_edges: std::collections::HashSet<u32> = (0..n)
            .filter(|&i| sc.labels[i] == Defect::Split)
            .map(|i| sc.gt_index[i].unwrap())
            .collect();
        assert_eq!(split_edges.len(), 24);
        assert!((48..=72).contains(&sc.count(Defect::Split)));
        let dup_edges: std::collections::HashSet<u32> = (0..n)
            .filter(|&i| sc.labels[i] == Defect::Duplicate)
            .map(|i| sc.gt_index[i].unwrap())
            .collect();
        assert_eq!(dup_edges.len(), 36);
        assert!((72..=108).contains(&sc.count(Defect::Duplicate)));
        // Every edge has exactly one primary segment (or one split group).
        let mut primaries: HashMap<u32, std::collections::HashSet<u32>> = HashMap::new();
        for i in 0..n {
            if matches!(sc.labels[i], Defect::Outlier | Defect::Duplicate) {
                continue;
            }
            primaries
                .entry(sc.gt_index[i].unwrap())
                .or_default()
                .insert(sc.lines.group(i));
        }
        assert_eq!(primaries.len(), 120);
        assert!(primaries.values().all(|g| g.len() == 1));
        // Outliers have no source, all others do.
        for i in 0..n {
            assert_eq!(sc.gt_index[i].is_none(), sc.labels[i] == Defect::Outlier);
        }
        // Scene extent about 2 units.
        let bb = Aabb::of_segments(&sc.gt);
        assert!((1.8..3.0).contains(&bb.longest_edge()), "{bb:?}");
    }

    #[test]
    fn only_the_pieces_of_a_split_edge_share_a_group() {
        let sc = scene();
        let mut members: HashMap<u32, Vec<usize>> = HashMap::new();
        for i in 0..sc.lines.len() {
            members.entry(sc.lines.group(i)).or_default().push(i);
        }
        for m in members.values() {
            if m.len() > 1 {
                assert!((2..=3).contains(&m.len()));
                assert!(m.iter().all(|&i| sc.labels[i] == Defect::Split));
                assert!(m.iter().all(|&i| sc.gt_index[i] == sc.gt_index[m[0]]));
            } else {
                assert_ne!(sc.labels[m[0]], Defect::Split);
            }
        }
    }

    #[test]
    fn same_seed_same_scene_other_seed_other_scene() {
        let a = scene();
        let b = scene();
        assert_eq!(a.gaussians, b.gaussians);
        assert_eq!(a.lines, b.lines);
        assert_eq!(a.labels, b.labels);
        assert_eq!(a.gt, b.gt);
        let c = toy_scene(&ToyParams {
            seed: 7,
            ..ToyParams::default()
        });
        assert_ne!(a.gaussians, c.gaussians);
        assert_ne!(a.lines.segments, c.lines.segments);
        // More Gaussians leave the segments alone (separate streams).
        let d = toy_scene(&ToyParams {
            n_gaussians: 5_000,
            ..ToyParams::default()
        });
        assert_eq!(a.lines, d.lines);
        assert_eq!(d.gaussians.len(), 5_000);
    }

    #[test]
    fn gaussians_ridge_along_edges_lie_on_faces_and_sprinkle_the_background() {
        let p = ToyParams::default();
        let sc = scene();
        let world = World::generate(
            p.n_boxes,
            p.n_quads,
            TOY_LAYOUT,
            &mut Rng::new(p.seed).fork(0),
        );
        let (mut near_edge, mut off_solids) = (0usize, 0usize);
        for g in &sc.gaussians {
            let g = p64(*g);
            let d = sc
                .gt
                .iter()
                .map(|e| dist_to_segment(e, g))
                .fold(f64::INFINITY, f64::min);
            if d < 4.0 * p.noise_sigma {
                near_edge += 1;
            }
            if world.clearance(g) > 6.0 * p.noise_sigma {
                off_solids += 1;
            }
        }
        let n = sc.gaussians.len() as f64;
        // 60 % edge samples, nearly all within 4 sigma (3D: 99.9 %), plus the face
        // samples in the 2 x 0.016 strips beside the edges: about a fifth of the face
        // area of 0.2-0.4 boxes, so 7 % more. Edge noise twice as large would leave
        // about 0.37; no ridge at all, about 0.07.
        let near = near_edge as f64 / n;
        assert!((0.62..0.72).contains(&near), "near edges {near}");
        // Only the 3 % background lies away from every solid (most of the box is empty).
        let off = off_solids as f64 / n;
        assert!((0.02..0.035).contains(&off), "off solids {off}");
    }

    #[test]
    fn clean_and_offset_segments_sit_where_planted() {
        let p = ToyParams::default();
        let sc = scene();
        let tol = 5.0 * p.endpoint_sigma;
        for (s, g) in of_kind(&sc, Defect::Clean) {
            assert!((s.p1 - g.p1).length() < tol && (s.p2 - g.p2).length() < tol);
        }
        let offsets: Vec<f64> = of_kind(&sc, Defect::Offset)
            .iter()
            .map(|(s, g)| {
                // The segment runs along its edge, shifted sideways by 0.3-0.8 r.
                assert!(g.axial(s.p1).abs() < tol && (g.axial(s.p2) - g.length()).abs() < tol);
                let o1 = g.line_dist2(s.p1).sqrt();
                let o2 = g.line_dist2(s.p2).sqrt();
                assert!((o1 - o2).abs() < 2.0 * tol);
                0.5 * (o1 + o2) / p.radius
            })
            .collect();
        let slack = tol / p.radius;
        assert!(
            offsets
                .iter()
                .all(|o| (0.3 - slack..0.8 + slack).contains(o)),
            "{offsets:?}"
        );
        // The whole range is used, so both mild and strong bias are in the scene.
        assert!(offsets.iter().any(|&o| o < 0.45) && offsets.iter().any(|&o| o > 0.65));
    }

    #[test]
    fn overextended_segments_run_ten_to_thirty_percent_past_their_edge_into_empty_space() {
        let p = ToyParams::default();
        let sc = scene();
        let tol = 5.0 * p.endpoint_sigma;
        let mut both = 0;
        for (s, g) in of_kind(&sc, Defect::Overextended) {
            let l = g.length();
            assert!(g.line_dist2(s.p1).sqrt() < tol && g.line_dist2(s.p2).sqrt() < tol);
            let ext = [-g.axial(s.p1), g.axial(s.p2) - l];
            let mut extended = 0;
            for (k, e) in ext.iter().enumerate() {
                if e.abs() < tol {
                    continue;
                }
                let f = e / l;
                assert!((0.1 - tol / l..0.3 + tol / l).contains(&f), "extension {f}");
                extended += 1;
                // Past the corner's own neighbourhood the extension finds almost no
                // Gaussians: its density is a small part of its edge's.
                let (end, tip) = if k == 0 { (g.p1, s.p1) } else { (g.p2, s.p2) };
                let dir = (tip - end).normalize();
                let part = Segment::new(end + dir * (2.0 * p.radius), tip);
                if part.length() > 0.02 {
                    let rho_ext = count_in(&part, p.radius, &sc.gaussians) as f64 / part.length();
                    let rho_edge = count_in(&g, p.radius, &sc.gaussians) as f64 / l;
                    assert!(rho_ext < 0.1 * rho_edge, "{rho_ext} vs {rho_edge}");
                }
            }
            assert!(extended >= 1);
            if extended == 2 {
                both += 1;
            }
        }
        assert!(both > 0 && both < sc.count(Defect::Overextended));
    }

    #[test]
    fn split_edges_have_gaps_of_five_to_fifteen_percent() {
        let p = ToyParams::default();
        let sc = scene();
        let tol = 5.0 * p.endpoint_sigma;
        let mut by_group: HashMap<u32, Vec<usize>> = HashMap::new();
        for i in 0..sc.lines.len() {
            if sc.labels[i] == Defect::Split {
                by_group.entry(sc.lines.group(i)).or_default().push(i);
            }
        }
        assert_eq!(by_group.len(), 24);
        for members in by_group.values() {
            let g = sc.gt[sc.gt_index[members[0]].unwrap() as usize];
            let l = g.length();
            let mut spans: Vec<(f64, f64)> = members
                .iter()
                .map(|&i| {
                    let s = sc.lines.segments[i];
                    assert!(g.line_dist2(s.p1).sqrt() < tol);
                    let (a, b) = (g.axial(s.p1), g.axial(s.p2));
                    (a.min(b), a.max(b))
                })
                .collect();
            spans.sort_by(|x, y| x.0.total_cmp(&y.0));
            assert!(spans[0].0.abs() < tol && (spans.last().unwrap().1 - l).abs() < tol);
            for w in spans.windows(2) {
                let gap = (w[1].0 - w[0].1) / l;
                assert!(
                    (0.05 - 2.0 * tol / l..0.15 + 2.0 * tol / l).contains(&gap),
                    "{gap}"
                );
            }
        }
    }

    #[test]
    fn duplicates_are_near_copies_inside_their_edge() {
        let p = ToyParams::default();
        let sc = scene();
        let tol = 5.0 * p.endpoint_sigma;
        for (s, g) in of_kind(&sc, Defect::Duplicate) {
            let l = g.length();
            // Lateral 0.3 r plus half the length turned by 1 degree.
            let lateral = 0.3 * p.radius + 1f64.to_radians().tan() * 0.5 * l + tol;
            for q in [s.p1, s.p2] {
                assert!(g.line_dist2(q).sqrt() < lateral);
            }
            let (a, b) = (g.axial(s.p1), g.axial(s.p2));
            assert!(a > -tol && a < 0.15 * l + tol, "{a}");
            assert!(b < l + tol && b > 0.85 * l - tol, "{b}");
            assert!(s.dir().dot(g.dir()) > 1f64.to_radians().cos() - 0.01);
        }
    }

    #[test]
    fn outliers_are_far_from_every_gaussian_cluster() {
        let p = ToyParams::default();
        let sc = scene();
        let clean_rho: Vec<f64> = of_kind(&sc, Defect::Clean)
            .iter()
            .map(|(s, _)| count_in(s, p.radius, &sc.gaussians) as f64 / s.length())
            .collect();
        let mean_clean = clean_rho.iter().sum::<f64>() / clean_rho.len() as f64;
        for i in 0..sc.lines.len() {
            if sc.labels[i] != Defect::Outlier {
                continue;
            }
            let s = sc.lines.segments[i];
            assert!((0.1..=0.3).contains(&s.length()));
            for g in &sc.gt {
                assert!(s.distance_to(g) >= p.sizes.outlier_clearance);
            }
            let rho = count_in(&s, p.radius, &sc.gaussians) as f64 / s.length();
            assert!(
                rho < 0.05 * mean_clean,
                "outlier density {rho} vs {mean_clean}"
            );
        }
    }

    #[test]
    fn the_layout_keeps_overextensions_clear_of_other_solids() {
        let max_ext = DefectSizes::default().overextension.1;
        assert!(TOY_LAYOUT.extension_clearance(max_ext) > 0.1);
        // Solids fit in their slot cube, which `World::clearance` relies on.
        assert!(TOY_LAYOUT.solid_reach() < 0.5 * TOY_LAYOUT.spacing);
    }

    #[test]
    fn the_scene_does_not_depend_on_the_thread_count() {
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| toy_scene(&ToyParams::default()))
        };
        let (a, b) = (run(1), run(3));
        assert_eq!(a.gaussians, b.gaussians);
        assert_eq!(a.lines, b.lines);
    }

    #[test]
    fn odd_parameters_give_a_smaller_scene_not_a_panic() {
        let sc = toy_scene(&ToyParams {
            n_boxes: 0,
            n_quads: 0,
            ..ToyParams::default()
        });
        assert!(sc.gt.is_empty());
        // Only outliers (in the fallback cube) and no Gaussians: nothing to sample.
        assert_eq!(sc.count(Defect::Outlier), sc.lines.len());
        assert!(sc.gaussians.is_empty());
        let sc = toy_scene(&ToyParams {
            defects: DefectAmounts {
                offset: 0.8,
                overextended: 0.8,
                split: f64::NAN,
                duplicated: 2.0,
                outliers: 0,
            },
            edge_fraction: 1.5,
            ..ToyParams::default()
        });
        assert_eq!(sc.count(Defect::Offset), 96);
        assert_eq!(sc.count(Defect::Overextended), 24);
        assert_eq!(sc.count(Defect::Clean), 0);
        assert_eq!(sc.count(Defect::Split), 0);
        assert_eq!(sc.gaussians.len(), 20_000);
    }
}
