//! Work items: the host cuts a batch into (query, chunk) pieces, a chunk being at most
//! CHUNK consecutive sorted points of one grid cell. The geometry that needs f64 (the
//! reference point on the axis, the cap and side-plane offsets) is done here, once per
//! item, so the kernels only subtract numbers of the size of a cell.
//!
//! Items are then grouped by chunk, at most GROUP items (queries) per group: one workgroup
//! per group, one invocation per item, every invocation walking the same points. The point
//! loads are then uniform across the workgroup, which lets lavapipe (llvmpipe) turn them
//! into one scalar load instead of one per lane; that was the kernels' main cost.

use super::super::Query;
use crate::geom::Segment;
use crate::index::Grid;
use bytemuck::{Pod, Zeroable};
use rayon::prelude::*;

/// Most points per work item: the loop bound of every kernel (see `shaders/*.wgsl`).
pub const CHUNK: usize = 256;
/// `count_query` keeps the count in its low 9 bits (CHUNK fits) and the query slot above.
const COUNT_BITS: u32 = 9;
/// Most queries per sub-batch that `count_query` can address.
pub const MAX_QUERY_SLOTS: usize = 1 << (32 - COUNT_BITS);
/// Items per group: the kernels' workgroup size, llvmpipe's SIMD width on AVX2 (8 x f32),
/// so that one group fills one SIMD pass.
pub const GROUP: usize = 8;

/// One workgroup's share, laid out as `struct Group` in the shaders (16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct Group {
    /// First point of the chunk, relative to the part of the point buffer it lies in.
    pub start: u32,
    /// Points in the chunk (at most CHUNK).
    pub count: u32,
    /// First item of the group, relative to the dispatch.
    pub first: u32,
    /// Items in the group (at most GROUP).
    pub len: u32,
}

/// A batch's work, ready for the device: items sorted by chunk and their groups, cut into
/// dispatches that each read one part of the point buffer.
#[derive(Debug, Default)]
pub struct Work {
    pub items: Vec<Item>,
    pub groups: Vec<Group>,
    pub dispatches: Vec<Dispatch>,
}

/// `groups[groups]` (whose items are `items[items]`) over part `part`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Dispatch {
    pub part: usize,
    pub groups: std::ops::Range<usize>,
    pub items: std::ops::Range<usize>,
}

/// One work item, laid out as `struct Item` in the shaders (48 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Item {
    /// Reference point `o` on the axis, relative to the cell origin.
    pub o: [f32; 3],
    /// `-t_o`: `t1 >= 0` iff `u >= lo`, with `u = (p - o)·d`.
    pub lo: f32,
    pub d: [f32; 3],
    /// `L - t_o`: `t2 >= 0` iff `u <= hi`.
    pub hi: f32,
    /// `(plane - o)·d`: the point is on the positive side iff `u > mid`.
    pub mid: f32,
    pub r2: f32,
    /// First sorted point of the chunk (global). Host-side only: the kernels take the
    /// chunk from the item's group.
    pub start: u32,
    pub count_query: u32,
}

impl Item {
    pub fn count(&self) -> usize {
        (self.count_query & ((1 << COUNT_BITS) - 1)) as usize
    }

    /// Slot of the item's query in its sub-batch.
    pub fn query(&self) -> usize {
        (self.count_query >> COUNT_BITS) as usize
    }
}

/// The items of `queries` (slot = position in the slice), in query order, then in the
/// grid order of `visit_rows`. No item crosses a multiple of `part_len` (a split of the
/// point buffer) and none holds an empty cell.
pub fn build(grid: &Grid, queries: &[Query], part_len: usize) -> Vec<Item> {
    assert!(queries.len() <= MAX_QUERY_SLOTS, "sub-batch too large");
    const QUERIES_PER_TASK: usize = 16;
    let pieces: Vec<Vec<Item>> = queries
        .par_chunks(QUERIES_PER_TASK)
        .enumerate()
        .map(|(c, qs)| {
            let mut out = Vec::new();
            for (j, q) in qs.iter().enumerate() {
                push_query(grid, q, c * QUERIES_PER_TASK + j, part_len, &mut out);
            }
            out
        })
        .collect();
    let total = pieces.iter().map(Vec::len).sum();
    let mut items = Vec::with_capacity(total);
    for p in pieces {
        items.extend_from_slice(&p);
    }
    items
}

fn push_query(grid: &Grid, q: &Query, slot: usize, part_len: usize, out: &mut Vec<Item>) {
    let seg: &Segment = &q.seg;
    if !seg.is_valid() {
        return;
    }
    let len = seg.length();
    let d = seg.dir();
    let half = grid.cell * 0.5;
    let df = d.as_vec3().to_array();
    let r2 = (q.r * q.r) as f32;
    let slot = (slot as u32) << COUNT_BITS;
    grid.visit_rows(seg, q.r, |row| {
        for x in row.x0..=row.x1 {
            let range = grid.cell_range(x, row.y, row.z);
            if range.is_empty() {
                continue;
            }
            let origin = grid.cell_origin(x, row.y, row.z);
            // The axis point nearest the cell centre keeps |p - o| within a few cells for
            // every member, which is what makes f32 accurate enough.
            let t_o = (origin + half - seg.p1).dot(d).clamp(0.0, len);
            let o = seg.p1 + d * t_o;
            let base = Item {
                o: (o - origin).as_vec3().to_array(),
                lo: -t_o as f32,
                d: df,
                hi: (len - t_o) as f32,
                mid: (q.plane - o).dot(d) as f32,
                r2,
                start: 0,
                count_query: 0,
            };
            let mut s = range.start;
            while s < range.end {
                let part_end = (s / part_len + 1) * part_len;
                let e = range.end.min(s + CHUNK).min(part_end);
                out.push(Item {
                    start: s as u32,
                    count_query: slot | (e - s) as u32,
                    ..base
                });
                s = e;
            }
        }
    });
}

/// Sorts `items` by (chunk, query), groups them and cuts the groups into dispatches of at
/// most `max_items` items that never cross a part. The order is a function of the items
/// alone, so reductions in this order repeat exactly.
pub fn group(items: Vec<Item>, part_len: usize, max_items: usize) -> Work {
    if items.is_empty() {
        return Work::default();
    }
    // Each (chunk, query) pair occurs once, so the keys are distinct and the order total.
    let mut keys: Vec<u64> = items
        .par_iter()
        .enumerate()
        .map(|(i, it)| ((it.start as u64) << 32) | i as u64)
        .collect();
    keys.par_sort_unstable();
    let sorted: Vec<Item> = keys
        .par_iter()
        .map(|k| items[(k & 0xffff_ffff) as usize])
        .collect();
    drop(items);
    let mut work = Work {
        items: Vec::new(),
        groups: Vec::with_capacity(sorted.len() / 2 + 1),
        dispatches: Vec::new(),
    };
    let mut d = Dispatch {
        part: sorted[0].start as usize / part_len,
        groups: 0..0,
        items: 0..0,
    };
    let mut a = 0;
    while a < sorted.len() {
        let start = sorted[a].start;
        let mut b = a + 1;
        while b < sorted.len() && b - a < GROUP && sorted[b].start == start {
            b += 1;
        }
        let part = start as usize / part_len;
        if part != d.part || b - d.items.start > max_items {
            let next = Dispatch {
                part,
                groups: work.groups.len()..work.groups.len(),
                items: a..a,
            };
            work.dispatches.push(std::mem::replace(&mut d, next));
        }
        work.groups.push(Group {
            start: start - (part * part_len) as u32,
            count: sorted[a].count() as u32,
            first: (a - d.items.start) as u32,
            len: (b - a) as u32,
        });
        d.groups.end = work.groups.len();
        d.items.end = b;
        a = b;
    }
    work.dispatches.push(d);
    work.items = sorted;
    work
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{p64, Aabb, Cylinder};
    use glam::DVec3;

    fn grid(points: &[[f32; 3]], cell: f64) -> Grid {
        let mut b = Aabb::empty();
        for p in points {
            b.extend(p64(*p));
        }
        Grid::build(points, b, cell)
    }

    #[test]
    fn items_cover_every_member_once_within_chunk_and_part() {
        // 2,000 points on a line in one cell, 50 more spread around.
        let mut pts: Vec<[f32; 3]> = (0..2000)
            .map(|i| [0.01 + i as f32 * 1e-5, 0.015, 0.015])
            .collect();
        for i in 0..50 {
            let f = i as f32 / 50.0;
            pts.push([f, 0.3 * f, 0.02]);
        }
        let g = grid(&pts, 0.05);
        let seg = Segment::new(DVec3::new(0.0, 0.015, 0.015), DVec3::new(1.0, 0.3, 0.02));
        let q = Query::new(seg, 0.05);
        let items = build(&g, &[q, q], 700);
        let cyl = Cylinder::new(&seg, 0.05);
        let mut seen = vec![0u32; g.len()];
        for it in &items {
            assert!(it.count() >= 1 && it.count() <= CHUNK);
            let s = it.start as usize;
            assert_eq!(s / 700, (s + it.count() - 1) / 700, "item crosses a part");
            for n in &mut seen[s..s + it.count()] {
                *n += 1;
            }
        }
        assert_eq!(
            items.iter().filter(|i| i.query() == 1).count() * 2,
            items.len()
        );
        for (i, p) in g.points.iter().enumerate() {
            if cyl.test(p64(*p)).is_some() {
                assert_eq!(seen[i], 2, "member {i} covered {} times", seen[i]);
            }
        }
        let work = group(items.clone(), 700, 5);
        assert_eq!(work.items.len(), items.len());
        let mut pairs = std::collections::HashSet::new();
        for d in &work.dispatches {
            assert!(d.items.len() <= 5);
            for gr in &work.groups[d.groups.clone()] {
                assert!(gr.len as usize <= GROUP && gr.len > 0);
                assert!(gr.start as usize + gr.count as usize <= 700);
                for it in &work.items[d.items.clone()][gr.first as usize..][..gr.len as usize] {
                    // Every item of a group reads the group's chunk, in the group's part.
                    assert_eq!(it.start as usize, d.part * 700 + gr.start as usize);
                    assert_eq!(it.count(), gr.count as usize);
                    assert!(pairs.insert((it.start, it.query())));
                }
            }
        }
        assert_eq!(pairs.len(), items.len());
        // Dispatches tile the groups and items in order.
        let mut next = (0, 0);
        for d in &work.dispatches {
            assert_eq!((d.groups.start, d.items.start), next);
            next = (d.groups.end, d.items.end);
        }
        assert_eq!(next, (work.groups.len(), work.items.len()));
    }

    #[test]
    fn invalid_queries_make_no_items() {
        let g = grid(&[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], 0.1);
        let p = DVec3::splat(0.5);
        let far = Segment::new(DVec3::splat(5.0), DVec3::splat(6.0));
        let items = build(
            &g,
            &[Query::new(Segment::new(p, p), 1.0), Query::new(far, 0.1)],
            1 << 20,
        );
        assert!(items.is_empty());
    }
}
