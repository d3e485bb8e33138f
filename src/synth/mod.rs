//! Synthetic scenes with known answers, for tests, the `demo` command and the benchmarks.
//!
//! Everything here is made up and says so in [`SynthScene::description`]: boxes and
//! quadrilaterals whose edges are the ground truth, Gaussian centres dense along those
//! edges (as trained 3DGS models are), and input segments with the five defects of the
//! LineGS paper (sec. 3.2) planted in known amounts and labelled one by one.
//!
//! - [`toy_scene`]: the paper's toy scene (about 20,000 Gaussians, about 300 segments).
//! - [`s200k_scene`]: a box scene of the authors' s200k shape (200,000 Gaussians, 318
//!   segments with every defect planted in fixed numbers), for the whole-process benchmark.
//! - [`scaled_scene`]: the same kind of world tiled for benchmarks, 10^5 to 10^7 Gaussians.
//! - [`mesh`]: OBJ meshes, their sharp edges and Gaussians sampled from them.
//! - [`gaussians_around_segments`]: centres for line sets that come without a model.
//!
//! Every generator is deterministic for its seed and independent of the thread count.

pub mod mesh;
pub mod rng;
mod s200k;
mod sample;
mod scaled;
mod toy;
mod world;

pub use mesh::{
    gaussians_from_mesh, read_obj_mesh, sharp_edges, sharp_lines, MeshGaussianOptions, TriMesh,
};
pub use rng::Rng;
pub use s200k::{s200k_scene, S200K_GAUSSIANS, S200K_SEGMENTS};
pub use sample::gaussians_around_segments;
pub use scaled::{scaled_scene, SCALED_GAUSSIANS_PER_BOX, SCALED_MAX_SEGMENTS_PER_EDGE};
pub use toy::{toy_scene, DefectAmounts, DefectSizes, ToyParams};

use crate::geom::{LineSet, Segment};

/// What was planted in one input segment.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Defect {
    /// The ground-truth edge with endpoint noise only.
    Clean,
    /// Position bias: moved perpendicular to its edge.
    Offset,
    /// Extended beyond its edge into empty space at one or both ends.
    Overextended,
    /// Not on any edge: in empty space, far from every Gaussian cluster.
    Outlier,
    /// An extra, nearby copy of an edge from another input line.
    Duplicate,
    /// One piece of an edge broken into pieces with gaps (discontinuity).
    Split,
}

impl Defect {
    pub const ALL: [Defect; 6] = [
        Defect::Clean,
        Defect::Offset,
        Defect::Overextended,
        Defect::Outlier,
        Defect::Duplicate,
        Defect::Split,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Defect::Clean => "clean",
            Defect::Offset => "offset",
            Defect::Overextended => "overextended",
            Defect::Outlier => "outlier",
            Defect::Duplicate => "duplicate",
            Defect::Split => "split",
        }
    }
}

/// A synthetic scene: Gaussian centres, noisy input segments and the answer.
#[derive(Clone, Debug)]
pub struct SynthScene {
    /// Gaussian centres (the only part of a 3DGS model that refinement uses).
    pub gaussians: Vec<[f32; 3]>,
    /// Input segments. `groups` is always `Some`: the pieces of one split edge share a
    /// group (as Line3D++ groups collinear segments), every other segment has its own.
    pub lines: LineSet,
    /// Ground-truth edges.
    pub gt: Vec<Segment>,
    /// What was planted in each input segment (`labels[i]` for `lines.segments[i]`).
    pub labels: Vec<Defect>,
    /// Index into `gt` of the edge each input segment was made from; `None` for outliers.
    pub gt_index: Vec<Option<u32>>,
    /// One-paragraph account of what was generated, starting with "SYNTHETIC".
    pub description: String,
}

impl SynthScene {
    /// Number of input segments labelled `d`.
    pub fn count(&self, d: Defect) -> usize {
        self.labels.iter().filter(|&&l| l == d).count()
    }

    /// "12 clean, 3 offset, ..." for descriptions.
    fn label_summary(&self) -> String {
        Defect::ALL
            .iter()
            .map(|&d| format!("{} {}", self.count(d), d.name()))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// Input segments planted together: one segment, or the pieces of one split edge.
#[derive(Clone, Debug)]
struct Unit {
    segments: Vec<Segment>,
    defect: Defect,
    source: Option<u32>,
}

/// Shuffles the units (so that the copies of one edge are not neighbours in the file, as in
/// real outputs) and lays them out as a grouped line set with one label per segment.
fn assemble(mut units: Vec<Unit>, rng: &mut Rng) -> (LineSet, Vec<Defect>, Vec<Option<u32>>) {
    rng.shuffle(&mut units);
    let mut segments = Vec::new();
    let mut groups = Vec::new();
    let mut labels = Vec::new();
    let mut sources = Vec::new();
    for (g, u) in units.into_iter().enumerate() {
        for s in u.segments {
            segments.push(s);
            groups.push(g as u32);
            labels.push(u.defect);
            sources.push(u.source);
        }
    }
    let lines = LineSet {
        segments,
        groups: Some(groups),
    };
    (lines, labels, sources)
}
