//! Triangle meshes from OBJ files, their sharp edges, and Gaussian centres sampled from
//! them the way trained 3DGS models place them: on the surface, concentrated at edges.

use std::collections::HashMap;
use std::path::Path;

use glam::DVec3;

use super::sample::PointSampler;
use crate::geom::{Aabb, Segment};
use crate::io::{Error, Position};

/// An indexed triangle mesh.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TriMesh {
    pub vertices: Vec<DVec3>,
    /// Vertex indices; triangles that name a missing vertex are ignored by every function
    /// here rather than trusted.
    pub triangles: Vec<[u32; 3]>,
}

/// Reads the `v` and `f` records of a Wavefront OBJ file with io's OBJ reader
/// ([`crate::io::obj`]); other records are skipped. Face corners may be written `a`,
/// `a/b`, `a//c` or `a/b/c`; only the vertex index is used, negative indices count back
/// from the last vertex defined so far, and polygons are split into triangle fans. Errors
/// name the file and, for content, the line.
pub fn read_obj_mesh(path: impl AsRef<Path>) -> Result<TriMesh, Error> {
    let path = path.as_ref();
    // Bounded like every reader: a device is refused, a pipe read at most 1 GiB.
    let bytes = crate::io::read_input(path)?;
    // Comments and names may hold any bytes; the records we read are ASCII.
    parse_obj_mesh(&String::from_utf8_lossy(&bytes), path)
}

/// [`read_obj_mesh`] on text already in memory; `path` names it in errors.
pub fn parse_obj_mesh(text: &str, path: &Path) -> Result<TriMesh, Error> {
    let obj = crate::io::obj::parse(path, text, "vertex coordinate")?;
    if obj.vertices.len() >= u32::MAX as usize {
        let line = obj.vertices[u32::MAX as usize - 1].0;
        return Err(Error::parse(
            path,
            Position::Line(line),
            "more than 2^32 - 1 vertices",
        ));
    }
    let mut mesh = TriMesh {
        vertices: obj
            .vertices
            .iter()
            .map(|(_, p)| DVec3::from_array(*p))
            .collect(),
        triangles: Vec::new(),
    };
    let mut corners: Vec<u32> = Vec::new();
    for f in obj.faces {
        let err = |message: String| Error::parse(path, Position::Line(f.line), message);
        let indices = f.indices.map_err(|e| err(format!("face corner {e}")))?;
        let defined = f.defined as i64;
        corners.clear();
        for k in indices {
            let index = if k > 0 { k - 1 } else { defined + k };
            if index < 0 || index >= defined {
                return Err(err(format!(
                    "face corner `{k}` refers to a vertex that is not defined \
                     ({defined} vertices so far)"
                )));
            }
            corners.push(index as u32);
        }
        if corners.len() < 3 {
            return Err(err(format!(
                "face needs at least 3 corners, found {}",
                corners.len()
            )));
        }
        for w in 1..corners.len() - 1 {
            mesh.triangles
                .push([corners[0], corners[w], corners[w + 1]]);
        }
    }
    if mesh.triangles.is_empty() {
        return Err(Error::no_data(
            path,
            "no faces (an OBJ mesh needs `f` records)",
        ));
    }
    Ok(mesh)
}

impl TriMesh {
    /// Box of the vertices.
    pub fn aabb(&self) -> Aabb {
        let mut b = Aabb::empty();
        for v in &self.vertices {
            b.extend(*v);
        }
        b
    }

    /// Triangles whose indices all name vertices.
    fn valid_triangles(&self) -> impl Iterator<Item = [u32; 3]> + '_ {
        let n = self.vertices.len();
        self.triangles
            .iter()
            .copied()
            .filter(move |t| t.iter().all(|&i| (i as usize) < n))
    }

    /// Triangles as corner positions.
    pub fn triangle_points(&self) -> Vec<[DVec3; 3]> {
        self.valid_triangles()
            .map(|t| t.map(|i| self.vertices[i as usize]))
            .collect()
    }

    /// Total surface area.
    pub fn area(&self) -> f64 {
        self.triangle_points()
            .iter()
            .map(|t| 0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length())
            .sum()
    }

    /// The mesh with vertices closer than `eps` merged into the first of them (CAD
    /// exports repeat a vertex for every face that uses it, which hides which faces are
    /// neighbours). Triangles that collapse are dropped; vertices keep their first-seen
    /// order.
    pub fn welded(&self, eps: f64) -> TriMesh {
        let eps = if eps.is_finite() { eps.max(0.0) } else { 0.0 };
        // Cells of size eps: two points within eps are in the same or adjacent cells.
        let cell = |p: DVec3| -> [i64; 3] {
            let q = p / eps;
            [q.x.floor() as i64, q.y.floor() as i64, q.z.floor() as i64]
        };
        let mut grid: HashMap<[i64; 3], Vec<u32>> = HashMap::new();
        let mut vertices: Vec<DVec3> = Vec::new();
        let remap: Vec<u32> = self
            .vertices
            .iter()
            .map(|&p| {
                let c = cell(p);
                for dz in -1..=1 {
                    for dy in -1..=1 {
                        for dx in -1..=1 {
                            let key = [c[0] + dx, c[1] + dy, c[2] + dz];
                            if let Some(reps) = grid.get(&key) {
                                for &r in reps {
                                    if (vertices[r as usize] - p).length() <= eps {
                                        return r;
                                    }
                                }
                            }
                        }
                    }
                }
                let r = vertices.len() as u32;
                vertices.push(p);
                grid.entry(c).or_default().push(r);
                r
            })
            .collect();
        let triangles = self
            .valid_triangles()
            .map(|t| t.map(|i| remap[i as usize]))
            .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
            .collect();
        TriMesh {
            vertices,
            triangles,
        }
    }
}

/// Welding tolerance relative to the mesh size: far below any real feature, far above the
/// rounding of printed coordinates.
const WELD_RELATIVE: f64 = 1e-7;

/// Sharp edges as vertex pairs of the welded mesh (sorted, deterministic).
fn sharp_edge_graph(mesh: &TriMesh, min_dihedral_deg: f64) -> (Vec<DVec3>, Vec<[u32; 2]>) {
    let bb = mesh.aabb();
    let diag = if bb.is_empty() {
        0.0
    } else {
        (bb.max - bb.min).length()
    };
    let m = mesh.welded(WELD_RELATIVE * diag);
    let normals: Vec<Option<DVec3>> = m
        .triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| m.vertices[i as usize]);
            let n = (b - a).cross(c - a);
            // Slivers with no usable normal would make any neighbour look sharp.
            let scale = (b - a).length_squared().max((c - a).length_squared());
            (n.length() > 1e-12 * scale).then(|| n.normalize())
        })
        .collect();
    // (low vertex, high vertex, triangle, traversed low -> high)
    let mut half_edges: Vec<(u32, u32, u32, bool)> = Vec::with_capacity(3 * m.triangles.len());
    for (ti, t) in m.triangles.iter().enumerate() {
        if normals[ti].is_none() {
            continue;
        }
        for k in 0..3 {
            let (a, b) = (t[k], t[(k + 1) % 3]);
            half_edges.push((a.min(b), a.max(b), ti as u32, a < b));
        }
    }
    half_edges.sort_unstable();
    let cos_limit = min_dihedral_deg.to_radians().cos();
    let mut edges = Vec::new();
    for group in half_edges.chunk_by(|x, y| (x.0, x.1) == (y.0, y.1)) {
        let sharp = match group {
            // A boundary edge has no second face to bend to.
            [_] => false,
            [f, g] => {
                let n1 = normals[f.2 as usize].unwrap_or(DVec3::ZERO);
                let mut n2 = normals[g.2 as usize].unwrap_or(DVec3::ZERO);
                // Consistently oriented neighbours walk their shared edge in opposite
                // directions; if they don't, one of them is flipped.
                if f.3 == g.3 {
                    n2 = -n2;
                }
                n1.dot(n2) < cos_limit
            }
            // Three or more faces on one edge: a junction of surfaces, a feature anyway.
            _ => true,
        };
        if sharp {
            edges.push([group[0].0, group[0].1]);
        }
    }
    (m.vertices, edges)
}

/// Edges where the two adjacent faces' normals differ by more than `min_dihedral_deg`
/// degrees (30 is usual), one segment per mesh edge, after welding vertices that share a
/// position. Boundary edges (one face) are not sharp; edges shared by three or more faces
/// always are.
pub fn sharp_edges(mesh: &TriMesh, min_dihedral_deg: f64) -> Vec<Segment> {
    let (v, edges) = sharp_edge_graph(mesh, min_dihedral_deg);
    edges
        .iter()
        .map(|&[a, b]| Segment::new(v[a as usize], v[b as usize]))
        .collect()
}

/// Sharp edges chained into straight lines: a chain runs on through a vertex where
/// exactly two sharp edges meet, as long as each new edge stays within `max_turn_deg` of
/// the chain's first edge (so that a finely tessellated curve is not taken for a line).
pub fn sharp_lines(mesh: &TriMesh, min_dihedral_deg: f64, max_turn_deg: f64) -> Vec<Segment> {
    let (v, edges) = sharp_edge_graph(mesh, min_dihedral_deg);
    let mut incident: Vec<Vec<u32>> = vec![Vec::new(); v.len()];
    for (e, &[a, b]) in edges.iter().enumerate() {
        incident[a as usize].push(e as u32);
        incident[b as usize].push(e as u32);
    }
    let cos_limit = max_turn_deg.to_radians().cos();
    let mut used = vec![false; edges.len()];
    let mut lines = Vec::new();
    // Follows the chain from vertex `at` away from the chain's start, in direction `dir`.
    let walk = |mut at: u32, dir: DVec3, used: &mut Vec<bool>| -> u32 {
        loop {
            let inc = &incident[at as usize];
            if inc.len() != 2 {
                return at;
            }
            let Some(&next) = inc.iter().find(|&&e| !used[e as usize]) else {
                return at;
            };
            let [a, b] = edges[next as usize];
            let other = if a == at { b } else { a };
            let step = (v[other as usize] - v[at as usize]).normalize_or_zero();
            if step.dot(dir) < cos_limit {
                return at;
            }
            used[next as usize] = true;
            at = other;
        }
    };
    for e in 0..edges.len() {
        if used[e] {
            continue;
        }
        used[e] = true;
        let [a, b] = edges[e];
        let dir = (v[b as usize] - v[a as usize]).normalize_or_zero();
        let end = walk(b, dir, &mut used);
        let start = walk(a, -dir, &mut used);
        lines.push(Segment::new(v[start as usize], v[end as usize]));
    }
    lines
}

/// How [`gaussians_from_mesh`] places centres. Noise defaults suit meshes normalized to
/// the unit cube (the ABC-NEF frame) and a query radius of about 0.03.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MeshGaussianOptions {
    /// Share of the centres along sharp edges (trained models concentrate there).
    pub edge_fraction: f64,
    /// Share uniform in the mesh's box (floaters).
    pub background_fraction: f64,
    /// Dihedral angle that makes an edge sharp, in degrees.
    pub min_dihedral_deg: f64,
    /// Standard deviation (per axis) of edge centres around their edge.
    pub edge_sigma: f64,
    /// Standard deviation (per axis) of surface centres around the surface.
    pub surface_sigma: f64,
}

impl Default for MeshGaussianOptions {
    fn default() -> Self {
        MeshGaussianOptions {
            edge_fraction: 0.6,
            background_fraction: 0.0,
            min_dihedral_deg: 30.0,
            edge_sigma: 0.004,
            surface_sigma: 0.002,
        }
    }
}

/// `n` synthetic Gaussian centres for `mesh`: an `edge_fraction` share along its sharp
/// edges (by length, isotropic normal noise), a `background_fraction` share uniform in its
/// box, the rest on its surface by area. Deterministic for `seed`, independent of the
/// thread count; empty for a mesh with no area.
pub fn gaussians_from_mesh(
    mesh: &TriMesh,
    n: usize,
    seed: u64,
    opts: &MeshGaussianOptions,
) -> Vec<[f32; 3]> {
    let edges = sharp_edges(mesh, opts.min_dihedral_deg);
    let clamp = |x: f64| if x.is_nan() { 0.0 } else { x.clamp(0.0, 1.0) };
    let edge = clamp(opts.edge_fraction);
    let background = clamp(opts.background_fraction).min(1.0 - edge);
    PointSampler::new(
        &edges,
        edge,
        opts.edge_sigma,
        mesh.triangle_points(),
        1.0 - edge - background,
        opts.surface_sigma,
        mesh.aabb(),
        background,
    )
    .sample(n, seed)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::p64;
    use std::path::PathBuf;

    fn parse(text: &str) -> Result<TriMesh, Error> {
        parse_obj_mesh(text, Path::new("test.obj"))
    }

    /// Unit cube with shared vertices, quads written in every corner form, some faces
    /// with negative (relative) indices.
    const CUBE: &str = "\
# unit cube
o cube
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
vn 0 0 1
vt 0 0
f 1 4 3 2
f 5/1 6/1 7/1 8/1
f 1//1 2//1 6//1 5//1
f 2/1/1 3/1/1 7/1/1 6/1/1
f -5 -1 -2 -6
f -8 -4 -1 -5
";

    /// The same cube as CAD exports write it: four private vertices per face.
    fn unwelded_cube() -> String {
        let c = parse(CUBE).unwrap();
        let mut text = String::new();
        let quads = [
            [0, 3, 2, 1],
            [4, 5, 6, 7],
            [0, 1, 5, 4],
            [1, 2, 6, 5],
            [2, 3, 7, 6],
            [3, 0, 4, 7],
        ];
        for (f, q) in quads.iter().enumerate() {
            for &i in q {
                let v: DVec3 = c.vertices[i];
                text += &format!("v {} {} {}\n", v.x, v.y, v.z);
            }
            let b = 4 * f + 1;
            text += &format!("f {} {} {} {}\n", b, b + 1, b + 2, b + 3);
        }
        text
    }

    /// Every segment is one of the cube's 12 unit edges, each found once.
    fn assert_cube_edges(edges: &[Segment]) {
        assert_eq!(edges.len(), 12, "{edges:?}");
        let mut keys: Vec<[i64; 6]> = edges
            .iter()
            .map(|s| {
                let (a, b) = (s.p1.to_array(), s.p2.to_array());
                let (a, b) = if a < b { (a, b) } else { (b, a) };
                assert!((s.length() - 1.0).abs() < 1e-12);
                [a[0], a[1], a[2], b[0], b[1], b[2]].map(|x| x.round() as i64)
            })
            .collect();
        keys.sort();
        keys.dedup();
        assert_eq!(keys.len(), 12);
    }

    #[test]
    fn reads_every_face_form_and_fan_triangulates() {
        let m = parse(CUBE).unwrap();
        assert_eq!(m.vertices.len(), 8);
        assert_eq!(m.triangles.len(), 12);
        // `f -5 -1 -2 -6` after 8 vertices is 4 8 7 3 (1-based).
        assert_eq!(m.triangles[8], [3, 7, 6]);
        assert_eq!(m.triangles[9], [3, 6, 2]);
        assert!((m.area() - 6.0).abs() < 1e-12);
    }

    #[test]
    fn a_cube_has_twelve_sharp_edges() {
        let m = parse(CUBE).unwrap();
        assert_cube_edges(&sharp_edges(&m, 30.0));
        // The face diagonals are flat, so a chain never turns into them.
        assert_cube_edges(&sharp_lines(&m, 30.0, 1.0));
    }

    #[test]
    fn welding_finds_the_neighbours_in_a_cad_style_cube() {
        let m = parse(&unwelded_cube()).unwrap();
        assert_eq!(m.vertices.len(), 24);
        let w = m.welded(1e-9);
        assert_eq!(w.vertices.len(), 8);
        assert_eq!(w.triangles.len(), 12);
        assert_cube_edges(&sharp_edges(&m, 30.0));
    }

    #[test]
    fn a_face_wound_the_other_way_does_not_make_its_diagonal_sharp() {
        let flipped = CUBE.replace("f 1 4 3 2", "f 1 2 3 4");
        assert_cube_edges(&sharp_edges(&parse(&flipped).unwrap(), 30.0));
    }

    #[test]
    fn the_dihedral_threshold_decides() {
        // Two triangles meeting at 20 degrees along the x axis, and a lone boundary.
        let (s, c) = 20f64.to_radians().sin_cos();
        let text = format!(
            "v 0 0 0\nv 1 0 0\nv 0.5 1 0\nv 0.5 {} {}\nf 1 2 3\nf 2 1 4\n",
            -c, -s
        );
        let m = parse(&text).unwrap();
        assert!(sharp_edges(&m, 30.0).is_empty());
        let e = sharp_edges(&m, 10.0);
        assert_eq!(e.len(), 1);
        assert_eq!(e[0].length(), 1.0);
    }

    #[test]
    fn sharp_lines_join_collinear_pieces_and_stop_at_bends() {
        // A roof whose 90 degree ridge along x is two mesh edges long.
        let text = "\
v 0 0 0
v 1 0 0
v 2 0 0
v 0 1 -1
v 1 1 -1
v 2 1 -1
v 0 -1 -1
v 1 -1 -1
v 2 -1 -1
f 1 2 5 4
f 2 3 6 5
f 2 1 7 8
f 3 2 8 9
";
        let m = parse(text).unwrap();
        let e = sharp_edges(&m, 30.0);
        assert_eq!(e.len(), 2);
        let lines = sharp_lines(&m, 30.0, 1.0);
        assert_eq!(lines.len(), 1);
        let l = lines[0];
        let (a, b) = if l.p1.x < l.p2.x {
            (l.p1, l.p2)
        } else {
            (l.p2, l.p1)
        };
        assert_eq!((a, b), (DVec3::ZERO, DVec3::new(2.0, 0.0, 0.0)));
    }

    #[test]
    fn bad_files_name_the_file_and_line() {
        let cases = [
            ("v 0 0 0\nv 1 0\n", 2, "2 coordinates, expected 3"),
            ("v 0 0 0\nv 1 x 0\n", 2, "`x` is not a number"),
            ("v 0 0 nan\n", 1, "not finite"),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n", 4, "not defined"),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n", 4, "not defined"),
            (
                "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n",
                4,
                "`0` is not a vertex index",
            ),
            ("v 0 0 0\nv 1 0 0\n\nf 1 2\n", 4, "at least 3"),
            ("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 a/3\n", 4, "`a/3`"),
        ];
        for (text, line, what) in cases {
            let e = parse(text).unwrap_err();
            assert!(e.is_input_error(), "{e}");
            let msg = e.to_string();
            assert!(msg.contains("test.obj") && msg.contains(what), "{msg}");
            assert!(msg.contains(&format!("line {line}")), "{msg}");
        }
        let e = parse("v 0 0 0\n# no faces\n").unwrap_err();
        assert!(e.to_string().contains("no faces"), "{e}");
        let e = read_obj_mesh("/nonexistent/mesh.obj").unwrap_err();
        assert!(matches!(e, Error::Io { .. }));
        assert!(e.to_string().contains("/nonexistent/mesh.obj"));
        #[cfg(unix)]
        {
            let e = read_obj_mesh("/dev/zero").unwrap_err();
            assert!(e.to_string().contains("is a device"), "{e}");
        }
    }

    #[test]
    fn out_of_range_triangles_in_a_hand_built_mesh_are_ignored() {
        let mut m = parse(CUBE).unwrap();
        m.triangles.push([0, 1, 99]);
        assert_cube_edges(&sharp_edges(&m, 30.0));
        assert!((m.area() - 6.0).abs() < 1e-12);
    }

    fn distance_to_cube_edges(p: DVec3, edges: &[Segment]) -> f64 {
        edges
            .iter()
            .map(|s| {
                let t = s.axial(p).clamp(0.0, s.length());
                (p - s.point_at(t)).length()
            })
            .fold(f64::INFINITY, f64::min)
    }

    #[test]
    fn mesh_gaussians_crowd_the_sharp_edges_and_lie_on_the_surface() {
        let m = parse(CUBE).unwrap();
        let opts = MeshGaussianOptions::default();
        let pts = gaussians_from_mesh(&m, 30_000, 5, &opts);
        assert_eq!(pts.len(), 30_000);
        let edges = sharp_edges(&m, 30.0);
        let mut near = 0;
        for p in &pts {
            let p = p64(*p);
            // Distance to the cube's surface (outside or inside).
            let inside = (p - DVec3::splat(0.5)).abs() - DVec3::splat(0.5);
            let surf = if inside.max_element() > 0.0 {
                inside.max(DVec3::ZERO).length()
            } else {
                -inside.max_element()
            };
            assert!(
                surf < 6.0 * opts.edge_sigma,
                "{p} is {surf} off the surface"
            );
            if distance_to_cube_edges(p, &edges) < 4.0 * opts.edge_sigma {
                near += 1;
            }
        }
        // 60 % edge samples (99.9 % of them within 4 sigma) plus the surface samples in
        // the 2 x 0.016 strips beside the 12 edges: 40 % x 0.384 / 6 = 2.6 %.
        let share = near as f64 / pts.len() as f64;
        assert!((share - 0.626).abs() < 0.012, "share near edges {share}");
        assert_eq!(pts, gaussians_from_mesh(&m, 30_000, 5, &opts));
        assert_ne!(pts, gaussians_from_mesh(&m, 30_000, 6, &opts));
    }

    #[test]
    fn mesh_gaussians_do_not_depend_on_the_thread_count() {
        let m = parse(CUBE).unwrap();
        let opts = MeshGaussianOptions::default();
        let run = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| gaussians_from_mesh(&m, 200_000, 1, &opts))
        };
        assert_eq!(run(1), run(2));
    }

    fn abc_path(file: &str) -> PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/data/abc_00000006")
            .join(file)
    }

    fn abc_gt() -> Vec<Segment> {
        let text = std::fs::read_to_string(abc_path("gt_sharp_lines.txt")).unwrap();
        text.lines()
            .filter(|l| !l.trim_start().starts_with('#') && !l.trim().is_empty())
            .map(|l| {
                let v: Vec<f64> = l.split_whitespace().map(|x| x.parse().unwrap()).collect();
                Segment::from_arrays([v[0], v[1], v[2]], [v[3], v[4], v[5]])
            })
            .collect()
    }

    #[test]
    fn abc_sharp_edges_cover_every_ground_truth_edge() {
        let m = read_obj_mesh(abc_path("mesh.obj")).unwrap();
        assert_eq!(m.vertices.len(), 16_332);
        let sharp = sharp_edges(&m, 30.0);
        let gt = abc_gt();
        assert_eq!(gt.len(), 12);
        // The model has curved features too, so more sharp edges than GT lines.
        assert!(sharp.len() > 12);
        for g in &gt {
            // ABC-NEF samples edges every 0.005.
            let n = (g.length() / 0.005).ceil() as usize;
            for i in 0..=n {
                let p = g.p1.lerp(g.p2, i as f64 / n as f64);
                let d = distance_to_cube_edges(p, &sharp);
                assert!(d <= 0.005, "GT point {p} is {d} from the sharp edges");
            }
        }
        // Chained into straight lines, the curves fall apart into short pieces within
        // the 1 degree turn limit, and the long lines are exactly the 12 GT edges.
        let lines: Vec<Segment> = sharp_lines(&m, 30.0, 1.0)
            .into_iter()
            .filter(|s| s.length() > 0.05)
            .collect();
        assert_eq!(lines.len(), 12);
        for g in &gt {
            let matched = lines.iter().any(|l| {
                let same = (l.p1 - g.p1).length().max((l.p2 - g.p2).length());
                let swapped = (l.p1 - g.p2).length().max((l.p2 - g.p1).length());
                same.min(swapped) < 0.005
            });
            assert!(matched, "no sharp line matches GT edge {g:?}");
        }
    }
}
