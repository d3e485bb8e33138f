//! Work items: the host cuts a batch into (query, chunk) pieces, a chunk being at most
//! CHUNK consecutive sorted points of one grid cell. The geometry that needs f64 (the
//! reference point on the axis, the cap and side-plane offsets) is done here, once per
//! item, so the kernels only subtract numbers of the size of a cell.
//!
//! Items are then grouped by chunk, at most GROUP items (queries) per group, one
//! invocation per item: the lanes of one SIMD pass of lavapipe (llvmpipe) then run the
//! same number of iterations over the same points.

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
/// Items per group (`GROUP` in the shaders): llvmpipe's SIMD width on AVX2 (8 x f32), so
/// that one group fills one SIMD pass.
pub const GROUP: usize = 8;

/// Items sharing a chunk, laid out as `struct Group` in the shaders (16 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct Group {
    /// First point of the chunk, relative to the part of the point store it lies in.
    pub start: u32,
    /// Points in the chunk (at most CHUNK).
    pub count: u32,
    /// The group's items are `order[first..first + len]` of its slice.
    pub first: u32,
    /// At most GROUP.
    pub len: u32,
}

/// A batch's work, ready for the device: items in build order (query order), cut into
/// slices of at most `max_items` items.
#[derive(Debug, Default)]
pub struct Work {
    pub items: Vec<Item>,
    pub slices: Vec<Slice>,
}

/// Items `items` of a [`Work`]: `order` lists them (slice-relative) by chunk, `groups`
/// cut that list into groups sharing a chunk, and `dispatches` cut the groups by the part
/// of the point store they read. Kernels write item `i`'s result to slot `i`, so the
/// host reads a slice's results in build order.
#[derive(Debug, Default)]
pub struct Slice {
    pub items: std::ops::Range<usize>,
    pub order: Vec<u32>,
    pub groups: Vec<Group>,
    pub dispatches: Vec<Dispatch>,
}

/// `groups` of a slice, all reading part `part`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Dispatch {
    pub part: usize,
    pub groups: std::ops::Range<usize>,
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

/// How the sorted points sit on the device.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Layout {
    /// Points per part of the point store (no chunk crosses a multiple of it).
    pub part_len: usize,
    /// Cells per block along x: the points of a block are stored relative to the block's
    /// origin (its first cell's), and a chunk never leaves its block. Blocks of a few
    /// cells give sparse grids items worth a dispatch slot, while every coordinate the
    /// kernels see stays within a few cells of its origin.
    pub block: u32,
}

impl Layout {
    /// Block size for `grid`: about 8 or more points per block row where cells are sparse.
    pub fn for_grid(grid: &Grid, part_len: usize) -> Layout {
        let nonempty = grid.cell_start.windows(2).filter(|w| w[1] > w[0]).count();
        let per_cell = grid.len() as f64 / nonempty.max(1) as f64;
        let block = if per_cell < 8.0 {
            4
        } else if per_cell < 16.0 {
            2
        } else {
            1
        };
        Layout { part_len, block }
    }

    /// Origin of the block holding cell `(x, y, z)`.
    pub fn block_origin(&self, grid: &Grid, x: u32, y: u32, z: u32) -> glam::DVec3 {
        grid.cell_origin(x - x % self.block, y, z)
    }
}

/// The items of `queries` (slot = position in the slice), in query order, then in the
/// grid order of `visit_rows`. An item covers a chunk of one block of a row: the block's
/// points from its first cell on, cut every CHUNK points and at every multiple of
/// `part_len`, so that items of different queries on one block share their chunks. No
/// item holds an empty range.
pub fn build(grid: &Grid, queries: &[Query], layout: Layout) -> Vec<Item> {
    assert!(queries.len() <= MAX_QUERY_SLOTS, "sub-batch too large");
    const QUERIES_PER_TASK: usize = 16;
    let pieces: Vec<Vec<Item>> = queries
        .par_chunks(QUERIES_PER_TASK)
        .enumerate()
        .map(|(c, qs)| {
            let mut out = Vec::new();
            for (j, q) in qs.iter().enumerate() {
                push_query(grid, q, c * QUERIES_PER_TASK + j, layout, &mut out);
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

fn push_query(grid: &Grid, q: &Query, slot: usize, layout: Layout, out: &mut Vec<Item>) {
    let seg: &Segment = &q.seg;
    if !seg.is_valid() {
        return;
    }
    let len = seg.length();
    let d = seg.dir();
    let df = d.as_vec3().to_array();
    let r2 = (q.r * q.r) as f32;
    let slot = (slot as u32) << COUNT_BITS;
    let b = layout.block;
    let last_x = grid.dims[0] - 1;
    grid.visit_rows(seg, q.r, |row| {
        for bx in row.x0 / b..=row.x1 / b {
            let (xa, xb) = (bx * b, (bx * b + b - 1).min(last_x));
            let start = grid.cell_range(xa, row.y, row.z).start;
            let end = grid.cell_range(xb, row.y, row.z).end;
            if start == end {
                continue;
            }
            let origin = grid.cell_origin(xa, row.y, row.z);
            let centre =
                origin + glam::DVec3::new((xb - xa + 1) as f64, 1.0, 1.0) * (grid.cell * 0.5);
            // The axis point nearest the block centre keeps |p - o| within a few cells for
            // every member, which is what makes f32 accurate enough.
            let t_o = (centre - seg.p1).dot(d).clamp(0.0, len);
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
            let mut s = start;
            while s < end {
                let part_end = (s / layout.part_len + 1) * layout.part_len;
                let e = end.min(s + CHUNK).min(part_end);
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

/// Cuts `items` into slices of at most `max_items`, orders each slice by (chunk, build
/// order), groups it and cuts the groups where the part changes. The result is a function
/// of the items alone, so reductions over it repeat exactly.
pub fn group(items: Vec<Item>, part_len: usize, max_items: usize) -> Work {
    let max_items = max_items.max(1);
    let slices = (0..items.len())
        .step_by(max_items)
        .map(|a| {
            let range = a..(a + max_items).min(items.len());
            slice(&items[range.clone()], range, part_len)
        })
        .collect();
    Work { items, slices }
}

fn slice(items: &[Item], range: std::ops::Range<usize>, part_len: usize) -> Slice {
    let order = order_by_start(items);
    let mut groups = Vec::with_capacity(items.len() / 4 + 1);
    let mut dispatches: Vec<Dispatch> = Vec::new();
    let mut a = 0;
    while a < order.len() {
        let first = &items[order[a] as usize];
        let start = first.start;
        let mut b = a + 1;
        while b < order.len() && b - a < GROUP && items[order[b] as usize].start == start {
            b += 1;
        }
        let part = start as usize / part_len;
        if dispatches.last().is_none_or(|d| d.part != part) {
            dispatches.push(Dispatch {
                part,
                groups: groups.len()..groups.len(),
            });
        }
        groups.push(Group {
            start: start - (part * part_len) as u32,
            count: first.count() as u32,
            first: a as u32,
            len: (b - a) as u32,
        });
        dispatches.last_mut().expect("pushed above").groups.end = groups.len();
        a = b;
    }
    Slice {
        items: range,
        order,
        groups,
        dispatches,
    }
}

/// Indices of `items` ordered by `start`, ties in index order: a stable LSD radix sort,
/// linear in the number of items (a comparison sort cost more than the kernels).
fn order_by_start(items: &[Item]) -> Vec<u32> {
    const BITS: u32 = 11;
    let max = items.iter().map(|i| i.start).max().unwrap_or(0);
    let bits = u32::BITS - max.leading_zeros();
    let mut keys: Vec<u32> = items.iter().map(|i| i.start).collect();
    let mut order: Vec<u32> = (0..items.len() as u32).collect();
    let mut keys2 = vec![0u32; keys.len()];
    let mut order2 = vec![0u32; keys.len()];
    let mut shift = 0;
    while shift < bits {
        let digit = |k: u32| ((k >> shift) & ((1 << BITS) - 1)) as usize;
        let mut at = vec![0usize; 1 << BITS];
        for &k in &keys {
            at[digit(k)] += 1;
        }
        let mut sum = 0;
        for c in at.iter_mut() {
            let n = *c;
            *c = sum;
            sum += n;
        }
        for (&k, &o) in keys.iter().zip(&order) {
            let slot = &mut at[digit(k)];
            keys2[*slot] = k;
            order2[*slot] = o;
            *slot += 1;
        }
        std::mem::swap(&mut keys, &mut keys2);
        std::mem::swap(&mut order, &mut order2);
        shift += BITS;
    }
    order
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
        for block in [1, 4] {
            cover_every_member_once(block);
        }
    }

    fn cover_every_member_once(block: u32) {
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
        let items = build(
            &g,
            &[q, q],
            Layout {
                part_len: 700,
                block,
            },
        );
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
        assert_eq!(work.items, items);
        let mut pairs = std::collections::HashSet::new();
        let mut next = 0;
        for sl in &work.slices {
            assert_eq!(sl.items.start, next);
            next = sl.items.end;
            assert!(sl.items.len() <= 5);
            let its = &work.items[sl.items.clone()];
            let mut groups_seen = 0;
            for d in &sl.dispatches {
                assert_eq!(d.groups.start, groups_seen);
                groups_seen = d.groups.end;
                for gr in &sl.groups[d.groups.clone()] {
                    assert!(gr.len as usize <= GROUP && gr.len > 0);
                    assert!(gr.start as usize + gr.count as usize <= 700);
                    for &i in &sl.order[gr.first as usize..][..gr.len as usize] {
                        let it = &its[i as usize];
                        // Every item of a group reads the group's chunk, in the group's part.
                        assert_eq!(it.start as usize, d.part * 700 + gr.start as usize);
                        assert_eq!(it.count(), gr.count as usize);
                        assert!(pairs.insert((it.start, it.query())));
                    }
                }
            }
            assert_eq!(groups_seen, sl.groups.len());
        }
        assert_eq!(next, items.len());
        assert_eq!(pairs.len(), items.len());
    }

    #[test]
    fn radix_order_is_stable_and_sorted() {
        let mut seed = 3u64;
        let items: Vec<Item> = (0..5000)
            .map(|_| {
                seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1);
                Item {
                    start: ((seed >> 33) % 70_000) as u32 * 97,
                    ..Default::default()
                }
            })
            .collect();
        let order = order_by_start(&items);
        let mut want: Vec<u32> = (0..items.len() as u32).collect();
        want.sort_by_key(|&i| items[i as usize].start);
        assert_eq!(order, want);
    }

    #[test]
    fn invalid_queries_make_no_items() {
        let g = grid(&[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], 0.1);
        let p = DVec3::splat(0.5);
        let far = Segment::new(DVec3::splat(5.0), DVec3::splat(6.0));
        let items = build(
            &g,
            &[Query::new(Segment::new(p, p), 1.0), Query::new(far, 0.1)],
            Layout {
                part_len: 1 << 20,
                block: 4,
            },
        );
        assert!(items.is_empty());
    }
}
