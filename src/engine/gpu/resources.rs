//! What the engine keeps on the device: the sizes it works within, the cell table and
//! point store uploaded once, and the per-batch buffers reused and grown across batches.

use super::device::{Context, QueryTexture, Reusable, Uploads};
use super::layout::*;
use super::GpuOptions;
use crate::engine::EngineError;
use crate::geom::p64;
use crate::index::Grid;
use rayon::prelude::*;

/// The sizes the engine works within, from the options and the device.
pub struct Limits {
    /// Points per part of the point store.
    pub part_len: u32,
    /// The device's own binding limit (cell table, coverage mask).
    pub device_binding: u64,
    pub item_max: u32,
    pub flag_max: u32,
    /// Most entries of a members batch's member list.
    pub member_max: u32,
    pub max_queries: usize,
    pub max_x: u32,
}

impl Limits {
    pub fn new(ctx: &Context, opts: &GpuOptions, _n_points: usize) -> Limits {
        let device_binding = ctx
            .limits
            .max_storage_buffer_binding_size
            .min(ctx.limits.max_buffer_size);
        // A part is one texture: rows of STORE_W points, one fewer than the device's
        // largest side so that `store_rows` may add its row (the binding limit is for
        // buffers; the option still splits the store, for tests).
        let texture = STORE_W as u64 * (ctx.limits.max_texture_dimension_2d as u64 - 1);
        let part_len = (opts.max_binding_bytes.unwrap_or(u64::MAX) / 16)
            .min(texture)
            .clamp(1, u32::MAX as u64 / 2) as u32;
        let item_max = (opts.max_items as u64)
            .min(device_binding / std::mem::size_of::<Partial>() as u64)
            .clamp(1, 1 << 28) as u32;
        let flag_max = ((device_binding / 4 - CTL_HEAD as u64) / 2).min(1 << 30) as u32;
        let per_query = (NBINS as u64 * 4).max(std::mem::size_of::<GQuery>() as u64);
        let max_queries = opts
            .max_queries
            .min((device_binding / per_query) as usize)
            .clamp(1, 1 << 22);
        // Half the binding: the staging buffer holds the list and the per-query results.
        let member_max = (device_binding / 8).clamp(1, 1 << 30) as u32;
        Limits {
            part_len,
            device_binding,
            item_max,
            flag_max,
            member_max,
            max_queries,
            max_x: opts.max_workgroups_x.max(1),
        }
    }
}

/// What lives on the device for the engine's whole life.
pub struct Statics {
    /// The cell table as [`CellTable`]'s blocks and their non-empty cells' first points.
    pub cell_blocks: (wgpu::Buffer, u64),
    pub cell_firsts: (wgpu::Buffer, u64),
    /// The point store's parts, each a texture ([`Context::filled_texture`]).
    pub parts: Vec<wgpu::TextureView>,
    pub dims: [u32; 3],
    /// The sorted centers' own f32 coordinates (3 words each), for the fit kernel's f64
    /// geometry; uploaded only for the device fit, and only when one binding holds them.
    pub world: Option<(wgpu::Buffer, u64)>,
    /// The sorted centers' working-set ids, for the members batches' records
    /// (`kernels/records.rs`); uploaded only with `world`, where member lists are the
    /// device's.
    pub ids: Option<(wgpu::Buffer, u64)>,
}

/// The point store's contents: every sorted center as its offset from its own cell's
/// corner in cell units (computed in f64, so the f32 keeps ~1e-7 of a cell) and its cell's
/// x index. Needs the grid, not the device: [`crate::engine::select`] computes it while the
/// device is still opening.
pub struct PointStore {
    /// The grid it was computed from.
    grid: std::sync::Weak<Grid>,
    rel: Vec<[f32; 4]>,
}

impl PointStore {
    pub fn of(grid: &std::sync::Arc<Grid>) -> PointStore {
        let mut rel = vec![[0f32; 4]; grid.points.len()];
        rel.par_chunks_mut(STORE_RUN)
            .enumerate()
            .for_each(|(k, run)| store_run(grid, k * STORE_RUN, run));
        PointStore {
            grid: std::sync::Arc::downgrade(grid),
            rel,
        }
    }
}

/// Points per piece of the point store computed at once (64 KiB: a piece is written to
/// the staging memory from a reused buffer that stays in cache).
const STORE_RUN: usize = 4096;

/// The point store's entries of the sorted points `start..start + out.len()`. Each point's
/// cell is the one whose range of the cell table holds it (the cell the grid sorted it
/// into), found once per piece and then stepped, so the cost is the offsets' arithmetic.
fn store_run(grid: &Grid, start: usize, out: &mut [[f32; 4]]) {
    let (dx, dy) = (grid.dims[0], grid.dims[1]);
    let inv = 1.0 / grid.cell;
    let starts = &grid.cell_start;
    // The last cell whose range begins at or before `start`: the cell holding it.
    let mut c = starts.partition_point(|&s| s as usize <= start) - 1;
    let mut cell = None;
    for (j, slot) in out.iter_mut().enumerate() {
        let i = start + j;
        while starts[c + 1] as usize <= i {
            c += 1;
            cell = None;
        }
        let (x, o) = *cell.get_or_insert_with(|| {
            let (x, t) = (c as u32 % dx, c as u32 / dx);
            (x, grid.cell_origin(x, t % dy, t / dy))
        });
        let r = (p64(grid.points[i]) - o) * inv;
        // w: the cell's x index mod 2^16 (exact in f32), for the kernels to move the point
        // into a neighbouring cell's frame.
        *slot = [r.x as f32, r.y as f32, r.z as f32, (x & 0xFFFF) as f32];
    }
}

/// The point store's entries of the sorted points `first..` written straight into `dst`
/// (the upload's staging memory), piece by piece in parallel: no store of its own.
fn write_store(grid: &Grid, dst: wgpu::WriteOnly<'_, [u8]>, first: usize) {
    const PIECE: usize = STORE_RUN * 16;
    let (whole, tail) = dst.into_chunks::<PIECE>();
    let pieces: Vec<wgpu::WriteOnly<'_, [u8; PIECE]>> = whole.into_iter().collect();
    let n_whole = pieces.len();
    let write = |buf: &mut Vec<[f32; 4]>, k: usize, mut piece: wgpu::WriteOnly<'_, [u8]>| {
        let run = &mut buf[..piece.len() / 16];
        store_run(grid, first + k * STORE_RUN, run);
        piece.copy_from_slice(bytemuck::cast_slice(run));
    };
    pieces.into_par_iter().enumerate().for_each_init(
        || vec![[0f32; 4]; STORE_RUN],
        |buf, (k, piece)| write(buf, k, piece.into()),
    );
    if !tail.is_empty() {
        write(&mut vec![[0f32; 4]; STORE_RUN], n_whole, tail);
    }
}

/// The bytes of `src` at the start of `dst` (mapped memory, first written here), piece
/// by piece in parallel: most of a copy into new mapped memory is the kernel's first
/// touch of its pages, which the cores then share (the upload of 10^6 Gaussians, 28 MB
/// with the centers' coordinates, took about 44 ms on one core of the development
/// machine, 22–41 ms on its two).
pub(super) fn par_copy(mut dst: wgpu::WriteOnly<'_, [u8]>, src: &[u8]) {
    const PIECE: usize = 1 << 18;
    let (whole, mut tail) = dst.slice(..src.len()).into_chunks::<PIECE>();
    let pieces: Vec<wgpu::WriteOnly<'_, [u8; PIECE]>> = whole.into_iter().collect();
    let rest = &src[pieces.len() * PIECE..];
    pieces
        .into_par_iter()
        .zip(src.par_chunks_exact(PIECE))
        .for_each(|(piece, from)| {
            let mut piece: wgpu::WriteOnly<'_, [u8]> = piece.into();
            piece.copy_from_slice(from)
        });
    tail.copy_from_slice(rest);
}

/// The grid's cell table in the form the device reads: for each block of 32 cells, a word
/// of bits (cell `32 k + j` holds points where bit `j` is set) and the number of non-empty
/// cells before the block; and each non-empty cell's first point, in cell order, then the
/// number of points. The first point of cell `c`, or of the next non-empty cell when `c`
/// is empty (the full table's `cell_start[c]`), is `firsts[rank(c)]`, `rank(c)` being the
/// non-empty cells before `c`: the block's count plus the set bits below `c` in its word.
///
/// Most cells of a grid whose cells are near the query radius are empty (the bench scene
/// at 10^6 Gaussians: 6.1 million cells, a 24.5 MB table, 123,663 of them non-empty):
/// this form is a quarter of a byte a cell and four bytes a non-empty cell (2.0 MB there),
/// so the upload writes and copies that where it wrote and copied the whole table.
pub struct CellTable {
    pub blocks: Vec<[u32; 2]>,
    pub firsts: Vec<u32>,
}

/// Blocks of the cell table made by one task.
const BLOCK_RUN: usize = 4096;

impl CellTable {
    /// The table of `cell_start` (a grid's: non-decreasing, one entry more than cells).
    pub fn of(cell_start: &[u32]) -> CellTable {
        let n_cells = cell_start.len().saturating_sub(1);
        // One block more than whole blocks: `c == n_cells` (the end) has a block too.
        let mut blocks = vec![[0u32; 2]; n_cells / 32 + 1];
        // Block `b`'s bits: which of its cells hold points (where the next cell starts
        // elsewhere: the starts never decrease). A whole block compares two slices of
        // 32 starts, with no bounds checked a cell; the last, partial one goes cell by
        // cell. Checking each cell's bounds, the table took 6.5 ms at 10^6 points (6.1
        // million cells) against 2.1 ms so (probes, not committed).
        let bits_of = |b: usize| -> u32 {
            let first = b * 32;
            match cell_start.get(first..first + 33) {
                Some(w) => {
                    let (lo, hi) = (&w[..32], &w[1..33]);
                    (0..32).fold(0u32, |acc, i| acc | ((hi[i] != lo[i]) as u32) << i)
                }
                None => (first..n_cells).fold(0u32, |acc, c| {
                    acc | ((cell_start[c + 1] > cell_start[c]) as u32) << (c - first)
                }),
            }
        };
        // Each block's bits and the non-empty cells before it in its run; each run's count.
        let counts: Vec<u32> = blocks
            .par_chunks_mut(BLOCK_RUN)
            .enumerate()
            .map(|(k, run)| {
                let mut total = 0;
                for (j, b) in run.iter_mut().enumerate() {
                    let bits = bits_of(k * BLOCK_RUN + j);
                    *b = [bits, total];
                    total += bits.count_ones();
                }
                total
            })
            .collect();
        let total: usize = counts.iter().map(|&c| c as usize).sum();
        let mut firsts = vec![0u32; total + 1];
        firsts[total] = cell_start.last().copied().unwrap_or(0);
        // Each run's share of `firsts`, and the non-empty cells before the run.
        let mut rest = &mut firsts[..total];
        let mut shares = Vec::with_capacity(counts.len());
        let mut before = 0u32;
        for &c in &counts {
            let (share, tail) = rest.split_at_mut(c as usize);
            shares.push((share, before));
            rest = tail;
            before += c;
        }
        blocks
            .par_chunks_mut(BLOCK_RUN)
            .zip(shares)
            .enumerate()
            .for_each(|(k, (run, (share, before)))| {
                let mut at = 0;
                for (j, b) in run.iter_mut().enumerate() {
                    let first = (k * BLOCK_RUN + j) * 32;
                    b[1] += before;
                    let mut bits = b[0];
                    while bits != 0 {
                        share[at] = cell_start[first + bits.trailing_zeros() as usize];
                        at += 1;
                        bits &= bits - 1;
                    }
                }
            });
        CellTable { blocks, firsts }
    }

    /// `cell_start[c]` of the table it was made of, as the walk kernel computes it.
    #[cfg(test)]
    pub fn start(&self, c: usize) -> u32 {
        let [bits, before] = self.blocks[c / 32];
        let below = bits & ((1u32 << (c % 32)) - 1);
        self.firsts[(before + below.count_ones()) as usize]
    }
}

impl Statics {
    /// Uploads the cell table and the point store (computed now unless given for this
    /// very grid); with `world`, also the centers' own coordinates where one binding holds
    /// them, and with `ids` too, their working-set ids.
    pub fn upload(
        ctx: &Context,
        grid: &std::sync::Arc<Grid>,
        store: Option<PointStore>,
        lim: &Limits,
        world: bool,
        ids: bool,
    ) -> Result<Statics, EngineError> {
        let cells = CellTable::of(&grid.cell_start);
        let block_bytes = (cells.blocks.len() * 8) as u64;
        let first_bytes = (cells.firsts.len() * 4) as u64;
        if block_bytes.max(first_bytes) > lim.device_binding {
            return Err(EngineError::Gpu(format!(
                "the grid's cell table ({block_bytes} and {first_bytes} bytes) is above the \
                 device's binding limit"
            )));
        }
        log::debug!(
            "cell table: {} cells, {} of them non-empty, {} bytes to upload (the full \
             table: {})",
            grid.cell_start.len().saturating_sub(1),
            cells.firsts.len() - 1,
            block_bytes + first_bytes,
            grid.cell_start.len() * 4
        );
        // A store computed for another grid is not used (computed here instead).
        let given = match store {
            Some(s) if std::ptr::eq(s.grid.as_ptr(), std::sync::Arc::as_ptr(grid)) => Some(s.rel),
            _ => None,
        };
        let copy = par_copy;
        ctx.scoped("uploading the Gaussians", || {
            let blocks = ctx.filled_buffer("cell blocks", block_bytes, |dst| {
                copy(dst, bytemuck::cast_slice(&cells.blocks))
            });
            let firsts = ctx.filled_buffer("cell firsts", first_bytes, |dst| {
                copy(dst, bytemuck::cast_slice(&cells.firsts))
            });
            let mut parts = Vec::new();
            let n = grid.points.len();
            let part_len = lim.part_len as usize;
            // One texture per part, at least one (an empty store is one row of padding).
            for first in (0..n.max(1)).step_by(part_len) {
                let len = part_len.min(n - first.min(n));
                // Computed straight into the staging memory unless given.
                let texture = ctx.filled_texture("points", len, |at, dst| {
                    let (from, to) = (first + at, first + at + dst.len() / 16);
                    match &given {
                        Some(rel) => copy(dst, bytemuck::cast_slice(&rel[from..to])),
                        None => write_store(grid, dst, from),
                    }
                });
                parts.push(texture.create_view(&wgpu::TextureViewDescriptor::default()));
            }
            let world_bytes = (grid.points.len() * 12).max(12) as u64;
            let world = (world && world_bytes <= lim.device_binding).then(|| {
                let buf = ctx.filled_buffer("world", world_bytes, |dst| {
                    copy(dst, bytemuck::cast_slice(&grid.points))
                });
                (buf, world_bytes)
            });
            let ids_bytes = (grid.ids.len() * 4).max(4) as u64;
            let ids = (ids && world.is_some()).then(|| {
                let buf = ctx.filled_buffer("ids", ids_bytes, |dst| {
                    copy(dst, bytemuck::cast_slice(&grid.ids))
                });
                (buf, ids_bytes)
            });
            ctx.queue.submit([]);
            Statics {
                cell_blocks: (blocks, block_bytes),
                cell_firsts: (firsts, first_bytes),
                parts,
                world,
                ids,
                dims: grid.dims,
            }
        })
    }
}

/// Per-batch buffers, reused and grown across batches, with the capacities learnt.
pub struct Buffers {
    pub params: Reusable,
    /// The batch's queries, as texels: what the walk, the evaluation and the cut read.
    pub qtex: QueryTexture,
    /// The staging buffer of the queries and frames a batch uploads.
    pub uploads: Uploads,
    pub scan: Reusable,
    pub items: Reusable,
    pub partials: Reusable,
    pub results: Reusable,
    pub ctl: Reusable,
    pub indirect: Reusable,
    /// The k-nearest histograms, or the coverage mask.
    pub aux: Reusable,
    pub plans: Reusable,
    /// Members and list batches: the member list.
    pub members: Reusable,
    /// The stages' own buffers (`sizes::BufferSpec`), in the order of the stage sequence,
    /// each made on first use.
    pub own: Vec<Reusable>,
    pub staging: Reusable,
    /// Bytes of the coverage mask in `aux` (set by `clear_mask`).
    pub aux_len: u64,
    pub item_cap: u32,
    /// Whether `item_cap` was sized for a first batch ([`super::batch::submit`]).
    pub sized: bool,
    pub flag_cap: u32,
    pub member_cap: u32,
    /// Sure members a query had, on average, in the batch that listed the most of them a
    /// query so far (members batches, the fit's and the end gaps' list batches; `None`
    /// before the first): how much of the member list the next members batch reads back
    /// with its answers ([`Self::member_back`]).
    pub members_per_query: Option<f64>,
    /// Points a query's cylinder held, on average, in the stats batch that counted the
    /// most a query so far (`None` before the first): the first listing batch's member
    /// capacity ([`Self::first_member_cap`]).
    pub count_per_query: Option<f64>,
}

impl Buffers {
    /// Bytes of a members batch of `n` queries' member list (`per_member` bytes an entry)
    /// to read back with the answers, of `cap` there are: the whole list before any batch listed members, then a quarter
    /// more than [`Self::members_per_query`] would need (and 4 KiB). Where
    /// the list is longer, [`super::batch::submit`] reads the rest in a copy of its own;
    /// reading the whole capacity read back about nine times the members on the bench
    /// scene (the capacity is the largest batch's, the fit's, not this batch's).
    pub fn member_back(&self, n: usize, cap: u64, per_member: u64) -> u64 {
        match self.members_per_query {
            Some(m) => (((n as f64 * m * 1.25) as u64 + 1024) * per_member).min(cap),
            None => cap,
        }
    }

    /// The member capacity for a listing batch of `n` queries before any batch listed
    /// members: a quarter more than [`Self::count_per_query`] says they hold (and 1,024),
    /// at most `max`; `None` without a count, or where a batch listed members before (its
    /// capacity is what they needed). The edge fit's first batch asks the segments whose
    /// cylinders the evaluation before it counted: sized from the 65,536 members of a new
    /// engine it listed a million members at 10^6 Gaussians, overran, and ran again
    /// (about 250 ms more on lavapipe, and a round trip more on any device).
    pub fn first_member_cap(&self, n: usize, max: u32) -> Option<u32> {
        if self.members_per_query.is_some() {
            return None;
        }
        let c = self.count_per_query?;
        Some(((n as f64 * c * 1.25) as u64 + 1024).min(max as u64) as u32)
    }

    /// See [`super::GpuEngine::item_capacity`].
    pub fn item_cap(&self) -> u32 {
        self.item_cap
    }

    pub fn new(_ctx: &Context, lim: &Limits) -> Buffers {
        let storage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
        Buffers {
            params: Reusable::new("params", wgpu::BufferUsages::UNIFORM),
            qtex: QueryTexture::default(),
            uploads: Uploads::default(),
            scan: Reusable::new("scan", storage),
            items: Reusable::new("items", storage),
            partials: Reusable::new("partials", storage),
            results: Reusable::new("results", storage),
            ctl: Reusable::new("ctl", storage),
            indirect: Reusable::new(
                "indirect",
                wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::INDIRECT,
            ),
            aux: Reusable::new("aux", storage),
            plans: Reusable::new("plans", storage),
            members: Reusable::new("members", storage),
            own: Vec::new(),
            staging: Reusable::new("staging", wgpu::BufferUsages::MAP_READ),
            aux_len: 4,
            item_cap: lim.item_max.min(1 << 16),
            sized: false,
            flag_cap: lim.flag_max.min(1 << 14),
            member_cap: lim.member_max.min(1 << 16),
            members_per_query: None,
            count_per_query: None,
        }
    }
}

/// Allocates and clears the coverage mask over `n` points (`b.aux`).
pub fn clear_mask(
    ctx: &Context,
    b: &mut Buffers,
    lim: &Limits,
    n: usize,
) -> Result<(), EngineError> {
    let bytes = (n.div_ceil(32) * 4) as u64;
    if bytes > lim.device_binding {
        return Err(EngineError::Gpu(format!(
            "coverage of {n} points needs a {bytes}-byte mask, above the device's binding limit"
        )));
    }
    b.aux_len = bytes;
    let aux = b.aux.get(ctx, bytes).clone();
    let mut enc = ctx.encoder();
    enc.clear_buffer(&aux, 0, Some(bytes.next_multiple_of(4)));
    ctx.queue.submit([enc.finish()]);
    Ok(())
}

/// Reads the coverage mask back: the u32 words, and the seconds spent waiting.
pub fn read_mask(ctx: &Context, b: &mut Buffers, n: usize) -> Result<(Vec<u32>, f64), EngineError> {
    let bytes = (n.div_ceil(32) * 4) as u64;
    let aux = b.aux.get(ctx, bytes).clone();
    let staging = b.staging.get(ctx, bytes).clone();
    let mut enc = ctx.encoder();
    enc.copy_buffer_to_buffer(&aux, 0, &staging, 0, bytes);
    ctx.submit_and_map(enc, &staging, bytes, bytemuck::pod_collect_to_vec)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Aabb;
    use glam::DVec3;
    use std::sync::Arc;

    /// A grid with empty cells, crowded cells and more points than a few pieces.
    fn grid() -> Arc<Grid> {
        let mut s = 5u64;
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let pts: Vec<[f32; 3]> = (0..3 * STORE_RUN + 123)
            .map(|i| {
                let t = next();
                if i % 3 == 0 {
                    // A dense line: crowded cells among empty ones.
                    [t as f32, 0.5, 0.5]
                } else {
                    [t as f32, next() as f32, next() as f32]
                }
            })
            .collect();
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        Arc::new(Grid::build(&pts, b, 0.05))
    }

    /// Each point's entry from its own cell (`cell_of`, the function the grid sorted with).
    fn by_cell_of(g: &Grid) -> Vec<[f32; 4]> {
        let (dx, dy) = (g.dims[0], g.dims[1]);
        g.points
            .iter()
            .map(|p| {
                let p = p64(*p);
                let c = g.cell_of(p);
                let r = (p - g.cell_origin(c % dx, (c / dx) % dy, c / (dx * dy))) / g.cell;
                [
                    r.x as f32,
                    r.y as f32,
                    r.z as f32,
                    ((c % dx) & 0xFFFF) as f32,
                ]
            })
            .collect()
    }

    /// Every cell's start, and the end's, from the compact table equals the full table's:
    /// on a grid's own table and on tables of the shapes at a block's edges (no cells,
    /// all empty, all full, whole blocks and one cell more, runs of blocks of its own).
    #[test]
    fn the_compact_cell_table_gives_every_cells_start() {
        let check = |starts: &[u32], what: &str| {
            let t = CellTable::of(starts);
            let full = starts.windows(2).filter(|w| w[1] > w[0]).count();
            assert_eq!(
                t.firsts.len(),
                full + 1,
                "{what}: one first point a non-empty cell"
            );
            for (c, &want) in starts.iter().enumerate() {
                assert_eq!(t.start(c), want, "{what}: cell {c}");
            }
        };
        let g = grid();
        assert!(g.cell_start.windows(2).any(|w| w[0] == w[1]), "empty cells");
        check(&g.cell_start, "grid");
        check(&[0], "no cells");
        check(&[7], "no cells after 7 points");
        check(&[0; 65], "64 empty cells");
        check(&(0..=64).collect::<Vec<u32>>(), "64 full cells");
        check(
            &(0..=33).map(|i| i * 3).collect::<Vec<u32>>(),
            "33 full cells",
        );
        // Some cells of several runs of blocks non-empty, at random, with points in
        // bursts: 3 runs of 4,096 blocks and a part.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let mut starts = vec![0u32];
        for _ in 0..(3 * BLOCK_RUN * 32 + 1000) {
            let r = next();
            let add = if r % 5 == 0 { (r >> 8) % 40 } else { 0 };
            starts.push(starts.last().unwrap() + add as u32);
        }
        check(&starts, "random runs");
    }

    #[test]
    fn the_point_store_finds_each_points_own_cell() {
        let g = grid();
        assert!(g.cell_start.windows(2).any(|w| w[0] == w[1]), "empty cells");
        let want = by_cell_of(&g);
        let rel = PointStore::of(&g).rel;
        assert_eq!(rel.len(), want.len());
        for (i, (a, b)) in rel.iter().zip(&want).enumerate() {
            // The same arithmetic up to the multiplication by 1 / cell: within an ulp.
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() <= 1e-6, "point {i}: {a:?} vs {b:?}");
            }
            assert_eq!(a[3], b[3], "point {i}: cell x index");
        }
    }

    #[test]
    fn the_store_written_into_staging_memory_is_the_computed_one() {
        let g = grid();
        let rel = PointStore::of(&g).rel;
        // From point 100 on, as a part that starts mid-grid, with a piece left over.
        let first = 100;
        let mut got = vec![[0f32; 4]; rel.len() - first];
        let bytes: &mut [u8] = bytemuck::cast_slice_mut(got.as_mut_slice());
        write_store(&g, wgpu::WriteOnly::from_mut(bytes), first);
        assert_eq!(got, &rel[first..]);
    }
}
