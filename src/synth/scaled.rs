//! Large scenes for benchmarks: the toy scene's boxes tiled on a lattice.

use super::rng::Rng;
use super::toy::{outlier_bounds, world_sampler, DefectAmounts, DefectSizes, Planter};
use super::world::{Layout, World};
use super::{assemble, SynthScene, Unit};

/// Gaussians per box at which an edge carries the toy scene's density (about 330 edge
/// centres per unit length with the scaled layout's 0.15–0.3 boxes).
pub const SCALED_GAUSSIANS_PER_BOX: usize = 1_600;

/// Most segments per edge (Line3D++ on many views yields a few per edge); more segments
/// than that add boxes instead.
pub const SCALED_MAX_SEGMENTS_PER_EDGE: usize = 8;

/// Slots 0.75 apart hold boxes of 0.15–0.3: packed tighter than the toy scene to keep the
/// grid of a 10^7 scene small, while a 30 % overextension still ends more than 0.13 from
/// any other box.
pub(crate) const SCALED_LAYOUT: Layout = Layout {
    spacing: 0.75,
    size_min: 0.15,
    size_max: 0.3,
};

/// A scene with exactly `n_gaussians` centres and `n_segments` input segments, for
/// benchmarks; deterministic for `seed` and independent of the thread count.
///
/// Boxes are tiled on a cubic lattice, as many as `n_gaussians / 1,600` (so an edge keeps
/// the toy scene's Gaussian density however large the scene) or as `n_segments` needs at
/// up to 8 segments per edge, whichever is more; only in the second case does the density
/// drop. Gaussians: 60 % along edges (noise 0.004), 3 % background, the rest on faces.
/// Segments: a tenth are outliers; the others are spread evenly over the edges (a random
/// subset of edges when there are fewer segments than edges), each edge's first segment
/// clean, offset, overextended or split with the toy's shares, its others duplicates.
pub fn scaled_scene(n_gaussians: usize, n_segments: usize, seed: u64) -> SynthScene {
    let n_outliers = n_segments / 10;
    let on_edges = n_segments - n_outliers;
    let by_gaussians = n_gaussians.div_ceil(SCALED_GAUSSIANS_PER_BOX);
    let by_segments = on_edges.div_ceil(12 * SCALED_MAX_SEGMENTS_PER_EDGE);
    let n_boxes = by_gaussians.max(by_segments).max(1);

    let root = Rng::new(seed);
    let world = World::generate(n_boxes, 0, SCALED_LAYOUT, &mut root.fork(0));
    let gt = world.edges();
    let gaussians = world_sampler(&world, &gt, 0.6, 0.03, 0.004, 0.002)
        .sample(n_gaussians, root.fork(1).next_u64());

    let mut rng = root.fork(2);
    let e = gt.len();
    let mut order: Vec<usize> = (0..e).collect();
    rng.shuffle(&mut order);
    let mut budget = vec![0usize; e];
    for (j, &i) in order.iter().enumerate() {
        budget[i] = on_edges / e + usize::from(j < on_edges % e);
    }

    let sizes = DefectSizes::default();
    let amounts = DefectAmounts::default();
    let planter = Planter {
        radius: 0.03,
        endpoint_sigma: 0.002,
        sizes: &sizes,
    };
    let mut units: Vec<Unit> = Vec::with_capacity(n_segments);
    for (i, g) in gt.iter().enumerate() {
        let k = budget[i];
        if k == 0 {
            continue;
        }
        let u = rng.uniform();
        let first = if u < amounts.offset {
            planter.offset(g, i, &mut rng)
        } else if u < amounts.offset + amounts.overextended {
            planter.overextended(g, i, &mut rng)
        } else if u < amounts.offset + amounts.overextended + amounts.split && k >= 2 {
            let pieces = (2 + rng.below(2) as usize).min(k);
            planter.split(g, pieces, i, &mut rng)
        } else {
            planter.clean(g, i, &mut rng)
        };
        let rest = k - first.segments.len();
        units.push(first);
        for _ in 0..rest {
            units.push(planter.duplicate(g, i, &mut rng));
        }
    }
    let bounds = outlier_bounds(&world);
    units.extend((0..n_outliers).filter_map(|_| planter.outlier(&world, &bounds, &mut rng)));
    let (lines, labels, gt_index) = assemble(units, &mut rng);

    let mut scene = SynthScene {
        gaussians,
        lines,
        gt,
        labels,
        gt_index,
        description: String::new(),
    };
    let extent = world.aabb();
    scene.description = format!(
        "SYNTHETIC scaled benchmark scene (seed {seed}): {n_boxes} boxes on a {:?} lattice \
         spanning {:.1} x {:.1} x {:.1} units, {} ground-truth edges; {} Gaussian centres \
         (60 % along edges, 3 % background, the rest on faces); {} input segments ({}).",
        world.dims,
        extent.max.x - extent.min.x,
        extent.max.y - extent.min.y,
        extent.max.z - extent.min.z,
        scene.gt.len(),
        scene.gaussians.len(),
        scene.lines.len(),
        scene.label_summary(),
    );
    scene
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::synth::Defect;

    fn total_length(sc: &SynthScene) -> f64 {
        sc.gt.iter().map(|s| s.length()).sum()
    }

    #[test]
    fn sizes_are_exact_and_outliers_a_tenth() {
        let sc = scaled_scene(100_000, 1_000, 7);
        assert!(sc.description.starts_with("SYNTHETIC"));
        assert_eq!(sc.gaussians.len(), 100_000);
        assert_eq!(sc.lines.len(), 1_000);
        assert_eq!(sc.count(Defect::Outlier), 100);
        // 100,000 / 1,600 -> 63 boxes.
        assert_eq!(sc.gt.len(), 63 * 12);
        for d in [
            Defect::Clean,
            Defect::Offset,
            Defect::Overextended,
            Defect::Duplicate,
        ] {
            assert!(sc.count(d) > 0, "no {d:?}");
        }
    }

    #[test]
    fn edge_density_stays_the_same_as_the_scene_grows() {
        let small = scaled_scene(100_000, 1_000, 1);
        let large = scaled_scene(1_000_000, 10_000, 1);
        let rho_small = small.gaussians.len() as f64 / total_length(&small);
        let rho_large = large.gaussians.len() as f64 / total_length(&large);
        assert!(
            (rho_small / rho_large - 1.0).abs() < 0.03,
            "{rho_small} {rho_large}"
        );
        // About the toy scene's edge density: 60 % of the Gaussians per unit of edge.
        assert!((250.0..450.0).contains(&(0.6 * rho_large)), "{rho_large}");
        assert_eq!(large.lines.len(), 10_000);
        // Segments spread evenly: 9,000 on 7,500 edges is one or two per edge.
        let mut per_edge = vec![0usize; large.gt.len()];
        for e in large.gt_index.iter().flatten() {
            per_edge[*e as usize] += 1;
        }
        assert!(per_edge.iter().all(|&k| (1..=2).contains(&k)));
    }

    #[test]
    fn many_segments_add_boxes_instead_of_piling_onto_edges() {
        let sc = scaled_scene(10_000, 20_000, 3);
        assert_eq!(sc.lines.len(), 20_000);
        // 18,000 on edges at no more than 8 per edge: 188 boxes.
        assert_eq!(sc.gt.len(), 188 * 12);
        let mut per_edge = vec![0usize; sc.gt.len()];
        for e in sc.gt_index.iter().flatten() {
            per_edge[*e as usize] += 1;
        }
        assert!(
            per_edge.iter().all(|&k| (7..=8).contains(&k)),
            "{per_edge:?}"
        );
    }

    #[test]
    fn fewer_segments_than_edges_touch_each_edge_once() {
        let sc = scaled_scene(1_000_000, 500, 5);
        assert_eq!(sc.lines.len(), 500);
        let mut seen = std::collections::HashSet::new();
        for e in sc.gt_index.iter().flatten() {
            assert!(seen.insert(*e), "edge {e} used twice");
        }
        assert_eq!(seen.len(), 450);
        assert_eq!(sc.count(Defect::Split), 0);
        assert_eq!(sc.count(Defect::Duplicate), 0);
    }

    #[test]
    fn outliers_keep_their_distance_in_large_scenes_too() {
        let sc = scaled_scene(200_000, 2_000, 9);
        for i in 0..sc.lines.len() {
            if sc.labels[i] == Defect::Outlier {
                let s = sc.lines.segments[i];
                let d = sc
                    .gt
                    .iter()
                    .map(|g| s.distance_to(g))
                    .fold(f64::INFINITY, f64::min);
                assert!(d >= 0.1, "outlier {i} is {d} from an edge");
            }
        }
    }

    #[test]
    fn the_layout_keeps_overextensions_clear_of_other_boxes() {
        let max_ext = DefectSizes::default().overextension.1;
        assert!(SCALED_LAYOUT.extension_clearance(max_ext) > 0.1);
        assert!(SCALED_LAYOUT.solid_reach() < 0.5 * SCALED_LAYOUT.spacing);
    }

    #[test]
    fn output_does_not_depend_on_the_thread_count() {
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| scaled_scene(300_000, 3_000, 11))
        };
        let one = run(1);
        let four = run(4);
        assert_eq!(one.gaussians, four.gaussians);
        assert_eq!(one.lines, four.lines);
        assert_eq!(one.labels, four.labels);
        // The scene spans several independently seeded chunks.
        assert!(one.gaussians.len() > 8 * crate::synth::sample::CHUNK);
    }
}
