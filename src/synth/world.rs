//! The synthetic world: boxes and planar quadrilaterals, one per slot of a cubic lattice.
//!
//! Every solid fits inside its slot's cube with room to spare, which is what lets the
//! generators promise "empty space" (overextensions, outliers) without searching the whole
//! world: a point can only be near the solids of the 27 slots around it.

use glam::DVec3;

use super::rng::Rng;
use crate::geom::{Aabb, Segment};

/// Sizes of the lattice and of the solids in it.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Layout {
    /// Distance between neighbouring slot centres.
    pub spacing: f64,
    /// Range of box edge lengths and quadrilateral widths/heights.
    pub size_min: f64,
    pub size_max: f64,
}

impl Layout {
    /// Largest distance from a slot centre to a point of its solid (half the space
    /// diagonal of the largest box).
    pub fn solid_reach(&self) -> f64 {
        0.5 * self.size_max * 3f64.sqrt()
    }

    /// Smallest distance from a point of a segment extended by `max_extension` x its
    /// length beyond its solid to any other solid, by bounding spheres.
    #[cfg(test)]
    pub fn extension_clearance(&self, max_extension: f64) -> f64 {
        self.spacing - 2.0 * self.solid_reach() - max_extension * self.size_max
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum SolidKind {
    Box,
    Quad,
}

/// A box or a planar quadrilateral with its edges, its surface as triangles and an
/// oriented bounding box for distance tests.
#[derive(Clone, Debug)]
pub(crate) struct Solid {
    pub center: DVec3,
    /// Orthonormal axes of the oriented bounding box.
    pub axes: [DVec3; 3],
    /// Half extents along `axes` (the third is 0 for a quadrilateral).
    pub half: DVec3,
    pub edges: Vec<Segment>,
    pub triangles: Vec<[DVec3; 3]>,
}

impl Solid {
    /// A box of edge lengths `size`, turned by `yaw` about the vertical axis, as objects
    /// standing on a floor are.
    pub fn cuboid(center: DVec3, size: DVec3, yaw: f64) -> Solid {
        let (s, c) = yaw.sin_cos();
        let axes = [DVec3::new(c, s, 0.0), DVec3::new(-s, c, 0.0), DVec3::Z];
        let half = size * 0.5;
        // Corner i has +half along axis k when bit k of i is set.
        let corner = |i: usize| {
            let mut p = center;
            for (k, axis) in axes.iter().enumerate() {
                let sign = if i >> k & 1 == 1 { 1.0 } else { -1.0 };
                p += *axis * (sign * half[k]);
            }
            p
        };
        let mut edges = Vec::with_capacity(12);
        for i in 0..8 {
            for k in 0..3 {
                if i >> k & 1 == 0 {
                    edges.push(Segment::new(corner(i), corner(i | 1 << k)));
                }
            }
        }
        // Each face: fix axis k to one side, walk the other two bits around the face.
        let mut triangles = Vec::with_capacity(12);
        for k in 0..3 {
            let (a, b) = ((k + 1) % 3, (k + 2) % 3);
            for side in [0, 1] {
                let base = side << k;
                let q = [
                    corner(base),
                    corner(base | 1 << a),
                    corner(base | 1 << a | 1 << b),
                    corner(base | 1 << b),
                ];
                triangles.push([q[0], q[1], q[2]]);
                triangles.push([q[0], q[2], q[3]]);
            }
        }
        Solid {
            center,
            axes,
            half,
            edges,
            triangles,
        }
    }

    /// A convex planar quadrilateral of width `w` and height `h` in the plane spanned by
    /// `axes[0]`, `axes[1]`; `taper` (each in (0, 1]) narrows its four corners so that it
    /// is a general quadrilateral, not a rectangle.
    pub fn quad(center: DVec3, axes: [DVec3; 3], w: f64, h: f64, taper: [f64; 4]) -> Solid {
        let (u, v) = (axes[0], axes[1]);
        let local = [
            (-0.5 * w * taper[0], -0.5 * h),
            (0.5 * w * taper[1], -0.5 * h),
            (0.5 * w * taper[2], 0.5 * h),
            (-0.5 * w * taper[3], 0.5 * h),
        ];
        let q: Vec<DVec3> = local.iter().map(|&(x, y)| center + u * x + v * y).collect();
        let edges = (0..4).map(|i| Segment::new(q[i], q[(i + 1) % 4])).collect();
        Solid {
            center,
            axes,
            half: DVec3::new(0.5 * w, 0.5 * h, 0.0),
            edges,
            triangles: vec![[q[0], q[1], q[2]], [q[0], q[2], q[3]]],
        }
    }

    /// Distance from `p` to the oriented bounding box (0 inside); never more than the
    /// distance to the solid itself.
    pub fn obb_distance(&self, p: DVec3) -> f64 {
        let w = p - self.center;
        let local = DVec3::new(
            w.dot(self.axes[0]),
            w.dot(self.axes[1]),
            w.dot(self.axes[2]),
        );
        (local.abs() - self.half).max(DVec3::ZERO).length()
    }
}

/// Solids on a lattice; slot `i` holds `solids[i]`, slots are filled x fastest.
#[derive(Clone, Debug)]
pub(crate) struct World {
    pub solids: Vec<Solid>,
    pub layout: Layout,
    pub dims: [usize; 3],
    /// Centre of slot (0, 0, 0).
    pub origin: DVec3,
}

/// Lattice dimensions for `n` slots, as close to a cube as possible.
pub(crate) fn lattice_dims(n: usize) -> [usize; 3] {
    if n == 0 {
        return [0, 0, 0];
    }
    let nx = (n as f64).cbrt().ceil() as usize;
    let nx = nx.max(1);
    let ny = ((n as f64 / nx as f64).sqrt().ceil() as usize).max(1);
    let nz = n.div_ceil(nx * ny);
    [nx, ny, nz]
}

impl World {
    /// `n_boxes` boxes and `n_quads` quadrilaterals with random sizes and orientations,
    /// in random slots of a lattice centred on the origin.
    pub fn generate(n_boxes: usize, n_quads: usize, layout: Layout, rng: &mut Rng) -> World {
        // `clearance` looks only at the 27 slots around a point.
        debug_assert!(layout.solid_reach() < 0.5 * layout.spacing);
        let n = n_boxes + n_quads;
        let dims = lattice_dims(n);
        let extent = DVec3::new(
            dims[0].saturating_sub(1) as f64,
            dims[1].saturating_sub(1) as f64,
            dims[2].saturating_sub(1) as f64,
        ) * layout.spacing;
        let origin = -extent * 0.5;
        let mut kinds: Vec<SolidKind> = std::iter::repeat_n(SolidKind::Box, n_boxes)
            .chain(std::iter::repeat_n(SolidKind::Quad, n_quads))
            .collect();
        rng.shuffle(&mut kinds);
        let solids = kinds
            .iter()
            .enumerate()
            .map(|(i, kind)| {
                let ix = i % dims[0];
                let iy = i / dims[0] % dims[1];
                let iz = i / (dims[0] * dims[1]);
                let center = origin + DVec3::new(ix as f64, iy as f64, iz as f64) * layout.spacing;
                let mut size = || rng.range(layout.size_min, layout.size_max);
                match kind {
                    SolidKind::Box => {
                        let s = DVec3::new(size(), size(), size());
                        let yaw = rng.range(0.0, std::f64::consts::FRAC_PI_2);
                        Solid::cuboid(center, s, yaw)
                    }
                    SolidKind::Quad => {
                        let (w, h) = (size(), size());
                        let normal = rng.unit_vector();
                        let u = rng.perpendicular(normal);
                        let v = normal.cross(u);
                        let taper = [0; 4].map(|_| rng.range(0.6, 1.0));
                        Solid::quad(center, [u, v, normal], w, h, taper)
                    }
                }
            })
            .collect();
        World {
            solids,
            layout,
            dims,
            origin,
        }
    }

    /// Every edge of every solid, in slot order: the ground truth.
    pub fn edges(&self) -> Vec<Segment> {
        self.solids
            .iter()
            .flat_map(|s| s.edges.iter().copied())
            .collect()
    }

    pub fn triangles(&self) -> Vec<[DVec3; 3]> {
        self.solids
            .iter()
            .flat_map(|s| s.triangles.iter().copied())
            .collect()
    }

    /// Box of all solids.
    pub fn aabb(&self) -> Aabb {
        let mut b = Aabb::empty();
        for s in &self.solids {
            for t in &s.triangles {
                for p in t {
                    b.extend(*p);
                }
            }
        }
        b
    }

    /// A lower bound on the distance from `p` to every solid, exact below `spacing / 2`:
    /// each solid lies inside its slot's cube, so only the 27 slots around `p` can hold
    /// a solid closer than that.
    pub fn clearance(&self, p: DVec3) -> f64 {
        let d = self.layout.spacing;
        let mut best = 0.5 * d;
        if self.solids.is_empty() {
            return best;
        }
        let rel = (p - self.origin) / d;
        let idx = [rel.x, rel.y, rel.z];
        let mut lo = [0usize; 3];
        let mut hi = [0usize; 3];
        for k in 0..3 {
            let c = idx[k].round().clamp(0.0, (self.dims[k] - 1) as f64) as usize;
            lo[k] = c.saturating_sub(1);
            hi[k] = (c + 1).min(self.dims[k] - 1);
        }
        for iz in lo[2]..=hi[2] {
            for iy in lo[1]..=hi[1] {
                for ix in lo[0]..=hi[0] {
                    let slot = ix + self.dims[0] * (iy + self.dims[1] * iz);
                    if let Some(s) = self.solids.get(slot) {
                        best = best.min(s.obb_distance(p));
                    }
                }
            }
        }
        best
    }

    /// Smallest clearance along segment `s`, probing every `step`; the true minimum is at
    /// least the returned value minus `step / 2`.
    pub fn segment_clearance(&self, s: &Segment, step: f64) -> f64 {
        let n = (s.length() / step).ceil().max(1.0) as usize;
        (0..=n)
            .map(|i| self.clearance(s.p1.lerp(s.p2, i as f64 / n as f64)))
            .fold(f64::INFINITY, f64::min)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cuboid_has_twelve_edges_of_its_three_sizes_and_its_surface_area() {
        let size = DVec3::new(0.2, 0.3, 0.4);
        let b = Solid::cuboid(DVec3::new(1.0, 2.0, 3.0), size, 0.7);
        assert_eq!(b.edges.len(), 12);
        let mut lengths: Vec<f64> = b.edges.iter().map(|e| e.length()).collect();
        lengths.sort_by(f64::total_cmp);
        for (i, l) in lengths.iter().enumerate() {
            assert!((l - [0.2, 0.3, 0.4][i / 4]).abs() < 1e-12, "{lengths:?}");
        }
        let area: f64 = b
            .triangles
            .iter()
            .map(|t| 0.5 * (t[1] - t[0]).cross(t[2] - t[0]).length())
            .sum();
        assert!((area - 2.0 * (0.06 + 0.08 + 0.12)).abs() < 1e-12);
        // Corners are on the bounding box, the centre is inside, a far point is away.
        for e in &b.edges {
            assert!(b.obb_distance(e.p1) < 1e-12);
        }
        assert_eq!(b.obb_distance(b.center), 0.0);
        let above = b.center + DVec3::Z * 0.5;
        assert!((b.obb_distance(above) - 0.3).abs() < 1e-12);
    }

    #[test]
    fn a_quadrilateral_is_planar_and_closed() {
        let mut rng = Rng::new(2);
        let n = rng.unit_vector();
        let u = rng.perpendicular(n);
        let q = Solid::quad(
            DVec3::ZERO,
            [u, n.cross(u), n],
            0.4,
            0.3,
            [0.7, 0.8, 0.9, 1.0],
        );
        assert_eq!(q.edges.len(), 4);
        for (i, e) in q.edges.iter().enumerate() {
            assert!(e.p1.dot(n).abs() < 1e-12);
            assert_eq!(e.p2, q.edges[(i + 1) % 4].p1);
            assert!(q.obb_distance(e.p1) < 1e-12);
        }
    }

    #[test]
    fn lattice_dims_hold_every_slot() {
        for n in 1..200 {
            let d = lattice_dims(n);
            assert!(d[0] * d[1] * d[2] >= n, "{n} {d:?}");
            // no all-empty layer
            assert!(d[0] * d[1] * (d[2] - 1) < n, "{n} {d:?}");
        }
        assert_eq!(lattice_dims(12), [3, 2, 2]);
    }

    #[test]
    fn clearance_equals_the_distance_to_the_nearest_solid_when_close() {
        let layout = Layout {
            spacing: 1.0,
            size_min: 0.2,
            size_max: 0.4,
        };
        let w = World::generate(20, 7, layout, &mut Rng::new(8));
        let mut rng = Rng::new(9);
        let bb = w.aabb().grown(0.1);
        for _ in 0..2000 {
            let p = DVec3::new(
                rng.range(bb.min.x, bb.max.x),
                rng.range(bb.min.y, bb.max.y),
                rng.range(bb.min.z, bb.max.z),
            );
            let brute = w
                .solids
                .iter()
                .map(|s| s.obb_distance(p))
                .fold(f64::INFINITY, f64::min);
            let c = w.clearance(p);
            assert!(c <= brute + 1e-12);
            if brute < 0.5 {
                assert!((c - brute).abs() < 1e-12, "{c} {brute}");
            }
        }
    }
}
