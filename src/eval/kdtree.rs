//! A static 3-d tree for exact nearest-neighbour queries: the ground-truth metrics ask,
//! for every sample of one set, the closest sample of the other. Built once by median
//! splits on the widest axis (O(n log n)), each query costs O(log n) on average however
//! far the query lies from the points (a stray 100 units away prunes as fast as a
//! sample on an edge). No approximation: a query returns a point at the smallest
//! squared distance, computed as `(q - p).length_squared()`, so the distances equal a
//! brute-force scan's bit for bit.

use glam::DVec3;

/// Points per leaf: small leaves keep the scan short, large ones the tree shallow.
const LEAF: usize = 8;

enum Node {
    /// `idx[start..end]` are the leaf's points.
    Leaf { start: u32, end: u32 },
    /// Split at the median of the widest axis: the lower half under `left`.
    Split { left: u32, right: u32 },
}

pub struct KdTree {
    points: Vec<DVec3>,
    idx: Vec<u32>,
    nodes: Vec<Node>,
    /// The tight bounding box of each node's points (lo, hi).
    boxes: Vec<(DVec3, DVec3)>,
}

impl KdTree {
    pub fn new(points: &[DVec3]) -> KdTree {
        let mut t = KdTree {
            points: points.to_vec(),
            idx: (0..points.len() as u32).collect(),
            nodes: Vec::with_capacity(2 * points.len() / LEAF + 1),
            boxes: Vec::with_capacity(2 * points.len() / LEAF + 1),
        };
        if !points.is_empty() {
            t.build(0, points.len());
        }
        t
    }

    pub fn len(&self) -> usize {
        self.points.len()
    }

    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// Builds the subtree of `idx[start..end]` and returns its node's index.
    fn build(&mut self, start: usize, end: usize) -> u32 {
        let id = self.nodes.len() as u32;
        let mut lo = DVec3::splat(f64::INFINITY);
        let mut hi = DVec3::splat(f64::NEG_INFINITY);
        for &i in &self.idx[start..end] {
            lo = lo.min(self.points[i as usize]);
            hi = hi.max(self.points[i as usize]);
        }
        self.boxes.push((lo, hi));
        let ext = hi - lo;
        if end - start <= LEAF || ext.max_element() == 0.0 {
            // Few points, or all equal: one leaf, however many.
            self.nodes.push(Node::Leaf {
                start: start as u32,
                end: end as u32,
            });
            return id;
        }
        let axis = if ext.x >= ext.y && ext.x >= ext.z {
            0
        } else if ext.y >= ext.z {
            1
        } else {
            2
        };
        let mid = (start + end) / 2;
        let pts = &self.points;
        self.idx[start..end].select_nth_unstable_by(mid - start, |&a, &b| {
            pts[a as usize][axis].total_cmp(&pts[b as usize][axis])
        });
        self.nodes.push(Node::Split { left: 0, right: 0 });
        let left = self.build(start, mid);
        let right = self.build(mid, end);
        if let Node::Split {
            left: l, right: r, ..
        } = &mut self.nodes[id as usize]
        {
            *l = left;
            *r = right;
        }
        id
    }

    /// Squared distance from `q` to node `n`'s bounding box (0 inside).
    fn box_distance(&self, n: u32, q: DVec3) -> f64 {
        let (lo, hi) = self.boxes[n as usize];
        let d = (lo - q).max(q - hi).max(DVec3::ZERO);
        d.length_squared()
    }

    /// The index (into the points given to [`KdTree::new`]) of a nearest point to `q` and
    /// its squared distance; `None` for an empty tree.
    pub fn nearest(&self, q: DVec3) -> Option<(usize, f64)> {
        if self.points.is_empty() {
            return None;
        }
        let mut best = (usize::MAX, f64::INFINITY);
        // (node, squared distance from q to the node's bounding box): nodes wait on the
        // stack and are skipped once farther than the best. Tight boxes (not the cells the
        // splits cut) let a query far from every point prune all but the nearest nodes.
        let mut stack: Vec<(u32, f64)> = Vec::with_capacity(64);
        stack.push((0, self.box_distance(0, q)));
        while let Some((n, bound)) = stack.pop() {
            // The margin keeps a node whose bound came out a few ulps high from rounding.
            if bound > best.1 + best.1 * 1e-9 {
                continue;
            }
            match self.nodes[n as usize] {
                Node::Leaf { start, end } => {
                    for &i in &self.idx[start as usize..end as usize] {
                        let d = (q - self.points[i as usize]).length_squared();
                        if d < best.1 || (d == best.1 && (i as usize) < best.0) {
                            best = (i as usize, d);
                        }
                    }
                }
                Node::Split { left, right, .. } => {
                    let (dl, dr) = (self.box_distance(left, q), self.box_distance(right, q));
                    // The farther child first onto the stack, so the nearer is searched first.
                    if dl <= dr {
                        stack.push((right, dr));
                        stack.push((left, dl));
                    } else {
                        stack.push((left, dl));
                        stack.push((right, dr));
                    }
                }
            }
        }
        Some(best)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cloud(n: usize, seed: u64, scale: f64) -> Vec<DVec3> {
        let mut rng = crate::synth::Rng::new(seed);
        let mut f = || rng.uniform();
        (0..n).map(|_| DVec3::new(f(), f(), f()) * scale).collect()
    }

    #[test]
    fn equals_a_brute_force_scan() {
        // Points on a coarse lattice give many equal coordinates and exact ties.
        let mut pts = cloud(2000, 7, 1.0);
        pts.extend(
            cloud(500, 8, 1.0)
                .iter()
                .map(|p| (*p * 10.0).floor() / 10.0),
        );
        pts.extend([DVec3::splat(0.5); 20]);
        let t = KdTree::new(&pts);
        let mut qs = cloud(1000, 9, 1.2);
        qs.extend(cloud(50, 10, 1.0).iter().map(|p| *p + DVec3::splat(100.0)));
        qs.extend(pts.iter().step_by(37).copied());
        for q in qs {
            let (i, d) = t.nearest(q).unwrap();
            let want = pts
                .iter()
                .map(|p| (q - *p).length_squared())
                .fold(f64::INFINITY, f64::min);
            assert_eq!(d, want, "query {q}");
            assert_eq!((q - pts[i]).length_squared(), d);
        }
    }

    #[test]
    fn empty_and_single() {
        assert!(KdTree::new(&[]).nearest(DVec3::ZERO).is_none());
        let t = KdTree::new(&[DVec3::new(1.0, 2.0, 3.0)]);
        assert_eq!(t.nearest(DVec3::ZERO), Some((0, 14.0)));
    }
}
