//! A box scene of the authors' s200k shape: 200,000 Gaussians and 318 input segments with
//! every defect of the paper planted in fixed numbers, for the whole-process benchmark.

use super::rng::Rng;
use super::toy::{outlier_bounds, world_sampler, DefectSizes, Planter, TOY_LAYOUT};
use super::world::World;
use super::{assemble, Defect, SynthScene};

/// Gaussian centres of the s200k scene.
pub const S200K_GAUSSIANS: usize = 200_000;

/// Input segments of the s200k scene.
pub const S200K_SEGMENTS: usize = 318;

/// What the s200k scene plants on its 120 edges (9 boxes, 3 quadrilaterals): each edge's
/// primary segment is one of 24 offset, 24 overextended, 24 split (12 in two pieces, 12 in
/// three: 60 segments) and 48 clean; 48 edges get extra copies (24 two, 24 three: 120
/// duplicates); 42 outliers. 24 + 24 + 60 + 48 + 120 + 42 = 318.
const BOXES: usize = 9;
const QUADS: usize = 3;
const OFFSET: usize = 24;
const OVEREXTENDED: usize = 24;
const SPLIT_IN_TWO: usize = 12;
const SPLIT_IN_THREE: usize = 12;
const DUPLICATED_TWICE: usize = 24;
const DUPLICATED_THRICE: usize = 24;
const OUTLIERS: usize = 42;

/// The s200k-shaped box scene; deterministic for `seed` and independent of the thread count.
///
/// The toy scene's world and sampling (9 boxes and 3 quadrilaterals spanning about 2.4
/// units, 120 ground-truth edges; 60 % of the Gaussians along the edges with noise 0.004,
/// 3 % uniform background, the rest on the faces) with 200,000 Gaussians, and exactly 318
/// segments for every seed: the counts of each defect are fixed (see the constants above),
/// which edges get which is drawn. Defect sizes are the toy scene's at radius 0.03.
pub fn s200k_scene(seed: u64) -> SynthScene {
    let root = Rng::new(seed);
    let world = World::generate(BOXES, QUADS, TOY_LAYOUT, &mut root.fork(0));
    let gt = world.edges();
    let gaussians = world_sampler(&world, &gt, 0.6, 0.03, 0.004, 0.002)
        .sample(S200K_GAUSSIANS, root.fork(1).next_u64());

    let mut rng = root.fork(2);
    let e = gt.len();
    // (kind, pieces) of each edge's primary segment, then shuffled over the edges.
    let n_split = SPLIT_IN_TWO + SPLIT_IN_THREE;
    let n_clean = e.saturating_sub(OFFSET + OVEREXTENDED + n_split);
    let mut primary: Vec<(Defect, usize)> = [
        (Defect::Offset, 1, OFFSET),
        (Defect::Overextended, 1, OVEREXTENDED),
        (Defect::Split, 2, SPLIT_IN_TWO),
        (Defect::Split, 3, SPLIT_IN_THREE),
        (Defect::Clean, 1, n_clean),
    ]
    .iter()
    .flat_map(|&(d, pieces, n)| std::iter::repeat_n((d, pieces), n))
    .take(e)
    .collect();
    rng.shuffle(&mut primary);
    let mut copies = vec![0usize; e];
    let mut order: Vec<usize> = (0..e).collect();
    rng.shuffle(&mut order);
    for (j, &i) in order.iter().enumerate() {
        copies[i] = if j < DUPLICATED_TWICE {
            2
        } else if j < DUPLICATED_TWICE + DUPLICATED_THRICE {
            3
        } else {
            0
        };
    }

    let sizes = DefectSizes::default();
    let planter = Planter {
        radius: 0.03,
        endpoint_sigma: 0.002,
        sizes: &sizes,
    };
    let mut units = Vec::new();
    for (i, (g, &(kind, pieces))) in gt.iter().zip(&primary).enumerate() {
        units.push(match kind {
            Defect::Offset => planter.offset(g, i, &mut rng),
            Defect::Overextended => planter.overextended(g, i, &mut rng),
            Defect::Split => planter.split(g, pieces, i, &mut rng),
            _ => planter.clean(g, i, &mut rng),
        });
    }
    for (i, &n) in copies.iter().enumerate() {
        for _ in 0..n {
            units.push(planter.duplicate(&gt[i], i, &mut rng));
        }
    }
    let bounds = outlier_bounds(&world);
    units.extend((0..OUTLIERS).filter_map(|_| planter.outlier(&world, &bounds, &mut rng)));
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
        "SYNTHETIC box scene of the authors' s200k shape (seed {}): {} boxes and {} \
         quadrilaterals with {} ground-truth edges; {} Gaussian centres (60 % along edges, \
         3 % uniform background, the rest on faces; edge noise sigma 0.004); {} input \
         segments ({}), defect sizes relative to radius 0.03.",
        seed,
        BOXES,
        QUADS,
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

    #[test]
    fn every_seed_gives_200000_gaussians_and_318_segments_with_the_fixed_defect_counts() {
        for seed in [1, 2, 7, 2024] {
            let sc = s200k_scene(seed);
            assert_eq!(sc.gt.len(), 120, "seed {seed}");
            assert_eq!(sc.gaussians.len(), S200K_GAUSSIANS, "seed {seed}");
            assert_eq!(sc.lines.len(), S200K_SEGMENTS, "seed {seed}");
            assert_eq!(sc.labels.len(), S200K_SEGMENTS);
            assert_eq!(sc.count(Defect::Offset), 24, "seed {seed}");
            assert_eq!(sc.count(Defect::Overextended), 24, "seed {seed}");
            assert_eq!(sc.count(Defect::Split), 60, "seed {seed}");
            assert_eq!(sc.count(Defect::Clean), 48, "seed {seed}");
            assert_eq!(sc.count(Defect::Duplicate), 120, "seed {seed}");
            assert_eq!(sc.count(Defect::Outlier), 42, "seed {seed}");
            // 24 split edges: 12 in two pieces, 12 in three.
            let groups = sc.lines.groups.as_ref().unwrap();
            let mut pieces = std::collections::HashMap::<u32, usize>::new();
            for (g, d) in groups.iter().zip(&sc.labels) {
                if *d == Defect::Split {
                    *pieces.entry(*g).or_default() += 1;
                }
            }
            let mut sizes: Vec<usize> = pieces.into_values().collect();
            sizes.sort_unstable();
            assert_eq!(sizes, [vec![2; 12], vec![3; 12]].concat(), "seed {seed}");
            // Duplicates: 24 edges with two copies, 24 with three.
            let mut per_edge = std::collections::HashMap::<u32, usize>::new();
            for (gi, d) in sc.gt_index.iter().zip(&sc.labels) {
                if *d == Defect::Duplicate {
                    *per_edge.entry(gi.unwrap()).or_default() += 1;
                }
            }
            let mut sizes: Vec<usize> = per_edge.into_values().collect();
            sizes.sort_unstable();
            assert_eq!(sizes, [vec![2; 24], vec![3; 24]].concat(), "seed {seed}");
        }
    }

    #[test]
    fn same_seed_same_scene_other_seed_other_scene() {
        let a = s200k_scene(1);
        let b = s200k_scene(1);
        let c = s200k_scene(2);
        assert_eq!(a.gaussians, b.gaussians);
        assert_eq!(a.lines.segments, b.lines.segments);
        assert_eq!(a.labels, b.labels);
        assert_ne!(a.lines.segments, c.lines.segments);
        assert_ne!(a.gaussians, c.gaussians);
        assert!(a.description.starts_with("SYNTHETIC"));
        assert!(
            a.description.contains("318 input segments"),
            "{}",
            a.description
        );
    }
}
