//! Segments, cylinders and boxes (docs/method.md#geometry). All host-side math is f64.

pub mod fit;
pub mod kernel;

use glam::DVec3;

/// Segments shorter than this are invalid (docs/method.md#geometry) and dropped at load.
pub const MIN_LENGTH: f64 = 1e-12;

/// A 3D line segment `s = (P1, P2)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Segment {
    pub p1: DVec3,
    pub p2: DVec3,
}

impl Segment {
    pub fn new(p1: DVec3, p2: DVec3) -> Self {
        Segment { p1, p2 }
    }

    pub fn from_arrays(a: [f64; 3], b: [f64; 3]) -> Self {
        Segment::new(DVec3::from_array(a), DVec3::from_array(b))
    }

    /// `L = |P2 - P1|`.
    pub fn length(&self) -> f64 {
        (self.p2 - self.p1).length()
    }

    /// `d = (P2 - P1) / L`; zero for a degenerate segment.
    pub fn dir(&self) -> DVec3 {
        let v = self.p2 - self.p1;
        let l = v.length();
        if l > 0.0 {
            v / l
        } else {
            DVec3::ZERO
        }
    }

    pub fn midpoint(&self) -> DVec3 {
        (self.p1 + self.p2) * 0.5
    }

    /// Finite endpoints and `L > 1e-12` (docs/method.md#geometry).
    pub fn is_valid(&self) -> bool {
        self.p1.is_finite() && self.p2.is_finite() && self.length() > MIN_LENGTH
    }

    /// `P1 + t d`.
    pub fn point_at(&self, t: f64) -> DVec3 {
        self.p1 + self.dir() * t
    }

    /// Axial coordinate `(p - P1) · d`.
    pub fn axial(&self, p: DVec3) -> f64 {
        (p - self.p1).dot(self.dir())
    }

    /// Perpendicular offset `v = (p-P1) - ((p-P1)·d) d` from the line to `p`.
    pub fn perp_offset(&self, p: DVec3) -> DVec3 {
        let d = self.dir();
        let w = p - self.p1;
        w - d * w.dot(d)
    }

    /// Squared distance from `p` to the infinite line through the segment.
    pub fn line_dist2(&self, p: DVec3) -> f64 {
        self.perp_offset(p).length_squared()
    }

    /// Foot of the perpendicular from `p` on the infinite line.
    pub fn foot(&self, p: DVec3) -> DVec3 {
        p - self.perp_offset(p)
    }

    /// Inclusive flat-capped cylinder test of docs/method.md#geometry.
    pub fn cylinder_contains(&self, p: DVec3, r: f64) -> bool {
        Cylinder::new(self, r).test(p).is_some()
    }

    /// Both endpoints moved by `t`.
    pub fn translated(&self, t: DVec3) -> Segment {
        Segment::new(self.p1 + t, self.p2 + t)
    }

    /// Same segment with `P1`/`P2` swapped.
    pub fn reversed(&self) -> Segment {
        Segment::new(self.p2, self.p1)
    }

    /// Sub-segment between axial coordinates `a <= b` (measured from `P1` along `d`).
    pub fn sub(&self, a: f64, b: f64) -> Segment {
        Segment::new(self.point_at(a), self.point_at(b))
    }

    /// Closest distance between two segments in 3D (not their lines).
    pub fn distance_to(&self, other: &Segment) -> f64 {
        segment_segment_distance(self.p1, self.p2, other.p1, other.p2)
    }
}

/// A set of segments, optionally grouped into input 3D lines (Line3D++ `.txt` groups the
/// segments of one line; docs/method.md#step-6-collinear-merge and the "different input
/// lines" rule of step 7).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct LineSet {
    pub segments: Vec<Segment>,
    /// `groups[i]` is the input line of segment `i`; `None` when the format has no groups
    /// (every segment is then its own line).
    pub groups: Option<Vec<u32>>,
}

impl LineSet {
    pub fn new(segments: Vec<Segment>) -> Self {
        LineSet {
            segments,
            groups: None,
        }
    }

    pub fn len(&self) -> usize {
        self.segments.len()
    }

    pub fn is_empty(&self) -> bool {
        self.segments.is_empty()
    }

    /// The segments at `idx` (in that order), with their groups.
    pub fn select(&self, idx: &[usize]) -> LineSet {
        LineSet {
            segments: idx.iter().map(|&i| self.segments[i]).collect(),
            groups: self
                .groups
                .as_ref()
                .map(|g| idx.iter().map(|&i| g[i]).collect()),
        }
    }

    /// Number of distinct input lines, when the format groups segments.
    pub fn input_lines(&self) -> Option<usize> {
        self.groups.as_ref().map(|g| {
            let mut g = g.clone();
            g.sort_unstable();
            g.dedup();
            g.len()
        })
    }

    /// Input line of segment `i` (its own index when ungrouped).
    pub fn group(&self, i: usize) -> u32 {
        match &self.groups {
            Some(g) => g[i],
            None => i as u32,
        }
    }
}

/// `C(s, r)` with its direction precomputed. Every exact membership test in the crate goes
/// through [`Cylinder::test`], so the CPU engine and the brute-force checks agree bit for bit.
#[derive(Clone, Copy, Debug)]
pub struct Cylinder {
    pub p1: DVec3,
    pub p2: DVec3,
    pub d: DVec3,
    pub r2: f64,
}

impl Cylinder {
    pub fn new(s: &Segment, r: f64) -> Self {
        Cylinder {
            p1: s.p1,
            p2: s.p2,
            d: s.dir(),
            r2: r * r,
        }
    }

    /// `Some((t1, v))` when `p` is inside: `t1 = (p-P1)·d` and `v` the perpendicular
    /// offset from the axis; `None` otherwise.
    #[inline]
    pub fn test(&self, p: DVec3) -> Option<(f64, DVec3)> {
        let w = p - self.p1;
        let t1 = w.dot(self.d);
        if t1 < 0.0 || (self.p2 - p).dot(self.d) < 0.0 {
            return None;
        }
        let v = w - self.d * t1;
        if v.length_squared() <= self.r2 {
            Some((t1, v))
        } else {
            None
        }
    }
}

/// Closest distance between segments `[p1,q1]` and `[p2,q2]` (Ericson, Real-Time Collision
/// Detection, 5.1.9), robust for degenerate and parallel segments.
pub fn segment_segment_distance(p1: DVec3, q1: DVec3, p2: DVec3, q2: DVec3) -> f64 {
    let d1 = q1 - p1;
    let d2 = q2 - p2;
    let r = p1 - p2;
    let a = d1.length_squared();
    let e = d2.length_squared();
    let f = d2.dot(r);
    let eps = 1e-300;
    let (s, t);
    if a <= eps && e <= eps {
        return r.length();
    }
    if a <= eps {
        s = 0.0;
        t = (f / e).clamp(0.0, 1.0);
    } else {
        let c = d1.dot(r);
        if e <= eps {
            t = 0.0;
            s = (-c / a).clamp(0.0, 1.0);
        } else {
            let b = d1.dot(d2);
            let denom = a * e - b * b;
            let mut s0 = if denom > 1e-14 * a * e {
                ((b * f - c * e) / denom).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let mut t0 = (b * s0 + f) / e;
            if t0 < 0.0 {
                t0 = 0.0;
                s0 = (-c / a).clamp(0.0, 1.0);
            } else if t0 > 1.0 {
                t0 = 1.0;
                s0 = ((b - c) / a).clamp(0.0, 1.0);
            }
            s = s0;
            t = t0;
        }
    }
    let c1 = p1 + d1 * s;
    let c2 = p2 + d2 * t;
    (c1 - c2).length()
}

/// Axis-aligned box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: DVec3,
    pub max: DVec3,
}

impl Aabb {
    pub fn empty() -> Self {
        Aabb {
            min: DVec3::splat(f64::INFINITY),
            max: DVec3::splat(f64::NEG_INFINITY),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.min.x > self.max.x || self.min.y > self.max.y || self.min.z > self.max.z
    }

    pub fn extend(&mut self, p: DVec3) {
        self.min = self.min.min(p);
        self.max = self.max.max(p);
    }

    /// Box of all endpoints of `segments`.
    pub fn of_segments(segments: &[Segment]) -> Self {
        let mut b = Aabb::empty();
        for s in segments {
            b.extend(s.p1);
            b.extend(s.p2);
        }
        b
    }

    pub fn longest_edge(&self) -> f64 {
        if self.is_empty() {
            return 0.0;
        }
        let e = self.max - self.min;
        e.x.max(e.y).max(e.z)
    }

    /// The box grown by `frac x` its longest edge on every side (docs/method.md#geometry
    /// working set).
    pub fn grown(&self, frac: f64) -> Self {
        let g = frac * self.longest_edge();
        Aabb {
            min: self.min - DVec3::splat(g),
            max: self.max + DVec3::splat(g),
        }
    }

    /// Inclusive containment.
    pub fn contains(&self, p: DVec3) -> bool {
        p.x >= self.min.x
            && p.y >= self.min.y
            && p.z >= self.min.z
            && p.x <= self.max.x
            && p.y <= self.max.y
            && p.z <= self.max.z
    }
}

/// Point as f64 vector.
#[inline]
pub fn p64(p: [f32; 3]) -> DVec3 {
    DVec3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn seg(a: [f64; 3], b: [f64; 3]) -> Segment {
        Segment::from_arrays(a, b)
    }

    #[test]
    fn cylinder_is_inclusive_and_flat_capped() {
        let s = seg([0.0, 0.0, 0.0], [2.0, 0.0, 0.0]);
        assert!(s.cylinder_contains(DVec3::new(0.0, 0.5, 0.0), 0.5));
        assert!(s.cylinder_contains(DVec3::new(2.0, 0.0, 0.5), 0.5));
        assert!(!s.cylinder_contains(DVec3::new(2.0 + 1e-9, 0.0, 0.0), 0.5));
        assert!(!s.cylinder_contains(DVec3::new(-1e-9, 0.0, 0.0), 0.5));
        assert!(!s.cylinder_contains(DVec3::new(1.0, 0.5 + 1e-9, 0.0), 0.5));
        // flat cap: a point beyond the end but inside the sphere cap is outside
        assert!(!s.cylinder_contains(DVec3::new(2.1, 0.0, 0.0), 0.5));
    }

    #[test]
    fn offsets_and_distances() {
        let s = seg([0.0, 0.0, 0.0], [0.0, 0.0, 4.0]);
        let p = DVec3::new(3.0, 4.0, 1.0);
        assert_eq!(s.perp_offset(p), DVec3::new(3.0, 4.0, 0.0));
        assert_eq!(s.line_dist2(p), 25.0);
        assert_eq!(s.axial(p), 1.0);
        assert_eq!(s.foot(p), DVec3::new(0.0, 0.0, 1.0));
        assert_eq!(s.length(), 4.0);
    }

    #[test]
    fn segment_distance_cases() {
        let a = seg([0.0, 0.0, 0.0], [1.0, 0.0, 0.0]);
        // parallel, overlapping, offset by 0.3
        let b = seg([0.5, 0.3, 0.0], [2.0, 0.3, 0.0]);
        assert!((a.distance_to(&b) - 0.3).abs() < 1e-12);
        // collinear with a gap of 0.5
        let c = seg([1.5, 0.0, 0.0], [3.0, 0.0, 0.0]);
        assert!((a.distance_to(&c) - 0.5).abs() < 1e-12);
        // skew crossing lines 1 apart
        let e = seg([0.5, -1.0, 1.0], [0.5, 1.0, 1.0]);
        assert!((a.distance_to(&e) - 1.0).abs() < 1e-12);
        // gap and lateral offset together
        let f = seg([2.0, 1.0, 0.0], [3.0, 1.0, 0.0]);
        assert!((a.distance_to(&f) - 2f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn box_grows_by_longest_edge() {
        let b = Aabb::of_segments(&[seg([0.0, 0.0, 0.0], [10.0, 2.0, 1.0])]);
        let g = b.grown(0.1);
        assert_eq!(g.min, DVec3::splat(-1.0));
        assert_eq!(g.max, DVec3::new(11.0, 3.0, 2.0));
        assert!(g.contains(DVec3::new(11.0, 3.0, 2.0)));
    }

    #[test]
    fn invalid_segments() {
        assert!(!seg([1.0, 1.0, 1.0], [1.0, 1.0, 1.0]).is_valid());
        assert!(!seg([f64::NAN, 0.0, 0.0], [1.0, 1.0, 1.0]).is_valid());
        assert!(seg([0.0, 0.0, 0.0], [1e-6, 0.0, 0.0]).is_valid());
    }
}
