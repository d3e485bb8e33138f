//! A cylinder query as the kernels read it: in cell units, its start split into an integer
//! cell and an f32 fraction, its direction split 12 + 12 bits, with the f32 error bounds
//! within which the host decides a point instead ([`GQuery`]); and a result back in scene
//! units.

use super::layout::*;
use crate::engine::{CylStats, Query};
use crate::index::Grid;
use glam::DVec3;

/// The f32 error bounds of the kernels for a query of axial length `len` and radius `r`
/// (cell units). The axis point a kernel starts from is accurate to a few roundings of
/// its own size (a few cells); the caps carry the rounding of `len` and of `len - t`, and
/// the direction's rounding over the length: all within 2 roundings of relative 2^-24 of
/// `len + 2 r + 8`, and the bound allows 8. A squared distance of at most `(r + eps)^2`
/// then errs by at most `4 eps (r + eps)` plus its own rounding.
pub fn error_bounds(len: f64, r: f64) -> (f64, f64) {
    let eps = (len + 2.0 * r + 8.0) * (2f64).powi(-21);
    let e2 = 4.0 * eps * (r + eps) + r * r * (2f64).powi(-20);
    (eps, e2)
}

/// `x` with its 12 leading significant bits (toward zero), as the kernels' `bits12`.
fn bits12(x: f32) -> f32 {
    f32::from_bits(x.to_bits() & 0xFFFF_F000)
}

/// The `e2` bound the kernels use for `q` (cell units, as rounded to f32).
pub fn e2_of(grid: &Grid, q: &Query) -> f64 {
    let inv = 1.0 / grid.cell;
    error_bounds(q.seg.length() * inv, q.r * inv).1 as f32 as f64
}

/// Cells from the grid's origin beyond which a query goes to the host (f32 integers stay
/// exact far beyond).
const FAR: f64 = (1u64 << 22) as f64;

pub fn gquery(grid: &Grid, q: &Query, k: u64) -> GQuery {
    let s = &q.seg;
    let valid = !grid.is_empty()
        && s.is_valid()
        && s.p1.is_finite()
        && s.p2.is_finite()
        && q.r.is_finite()
        && q.r >= 0.0
        && q.plane.is_finite();
    if !valid {
        return GQuery {
            r2: -1.0,
            ..Default::default()
        };
    }
    let inv = 1.0 / grid.cell;
    let a = (s.p1 - grid.origin) * inv;
    if a.abs().max_element() > FAR || s.length() * inv > FAR {
        // Integer cells beyond f32's exact range: the host answers the query.
        return GQuery {
            r2: -2.0,
            ..Default::default()
        };
    }
    let i = a.floor();
    let f = (a - i).as_vec3();
    let d = s.dir();
    let df = d.as_vec3();
    let dh =
        glam::Vec3::new(bits12(df.x.abs()), bits12(df.y.abs()), bits12(df.z.abs())) * df.signum();
    let dl = (d - dh.as_dvec3()).as_vec3();
    let len = s.length() * inv;
    let r = q.r * inv;
    let (eps, e2) = error_bounds(len, r);
    GQuery {
        ix: i.x as i32,
        iy: i.y as i32,
        iz: i.z as i32,
        len: len as f32,
        fx: f.x,
        fy: f.y,
        fz: f.z,
        r2: (r * r) as f32,
        dx: df.x,
        dy: df.y,
        dz: df.z,
        mid: ((q.plane - s.p1).dot(d) * inv) as f32,
        dhx: dh.x,
        dhy: dh.y,
        dhz: dh.z,
        r: r as f32,
        dlx: dl.x,
        dly: dl.y,
        dlz: dl.z,
        eps: eps as f32,
        e2: e2 as f32,
        k: k.min(u32::MAX as u64) as u32,
        pad0: 0,
        pad1: 0,
    }
}

/// A sub-batch's queries as the kernels read them ([`gquery`], query `i` with `ks[i]`,
/// 0 past its end), made where they are uploaded: straight into the staging memory
/// ([`Self::fill`]), not into a vector first and copied.
pub struct GQueries<'a> {
    pub grid: &'a Grid,
    pub qs: &'a [Query],
    pub ks: &'a [u64],
}

/// Queries [`GQueries::fill`] makes at a time, in a buffer of its own (6 KiB) that it
/// then copies to the staging memory in one piece.
const FILL_RUN: usize = 64;

impl GQueries<'_> {
    /// Bytes of one query.
    pub const SIZE: usize = std::mem::size_of::<GQuery>();

    pub fn len(&self) -> usize {
        self.qs.len()
    }

    /// Query `first + j` in `out[j]`.
    fn write(&self, first: usize, out: &mut [GQuery]) {
        for (j, g) in out.iter_mut().enumerate() {
            let i = first + j;
            *g = gquery(self.grid, &self.qs[i], self.ks.get(i).copied().unwrap_or(0));
        }
    }

    /// Every query, in a vector (for an upload through the queue).
    pub fn to_vec(&self) -> Vec<GQuery> {
        let mut out = vec![GQuery::default(); self.len()];
        self.write(0, &mut out);
        out
    }

    /// The queries' bytes from byte `at` (a whole query) into `dst` (whole queries): a
    /// [`super::device::Source::Fill`] writer.
    pub fn fill(&self, at: usize, mut dst: wgpu::WriteOnly<'_, [u8]>) {
        let mut run = [GQuery::default(); FILL_RUN];
        let (first, n) = (at / Self::SIZE, dst.len() / Self::SIZE);
        let mut j = 0;
        while j < n {
            let m = FILL_RUN.min(n - j);
            self.write(first + j, &mut run[..m]);
            dst.slice(j * Self::SIZE..(j + m) * Self::SIZE)
                .copy_from_slice(bytemuck::cast_slice(&run[..m]));
            j += m;
        }
    }
}

/// A query's device result in scene units.
pub fn stats_of(r: &QResult, cell: f64) -> CylStats {
    let pair = |a: f32, b: f32| a as f64 + b as f64;
    CylStats {
        count: r.count as u64,
        side_pos: r.side as u64,
        sum_d2: pair(r.d2, r.d2_c) * cell * cell,
        sum_offset: DVec3::new(pair(r.ox, r.ox_c), pair(r.oy, r.oy_c), pair(r.oz, r.oz_c)) * cell,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::{p64, Aabb, Segment};

    /// A grid of a few points and `n` queries of different lengths and directions, with
    /// their `k`s.
    fn setup(n: usize) -> (Grid, Vec<Query>, Vec<u64>) {
        let pts: Vec<[f32; 3]> = (0..500)
            .map(|i| {
                let t = i as f32 * 0.01;
                [t, (3.0 * t).sin(), (2.0 * t).cos()]
            })
            .collect();
        let mut b = Aabb::empty();
        for p in &pts {
            b.extend(p64(*p));
        }
        let grid = Grid::build(&pts, b, 0.1);
        let qs = (0..n)
            .map(|i| {
                let a = i as f64 * 0.37;
                let p1 = DVec3::new(a.sin(), a.cos(), 0.1 * a);
                let p2 = p1 + DVec3::new(0.3, 0.1 * a.cos(), -0.2) * (1.0 + 0.01 * i as f64);
                Query::new(Segment::new(p1, p2), 0.02 + 0.001 * (i % 7) as f64)
            })
            .collect();
        let ks = (0..n as u64).map(|i| i * 3 + 1).collect();
        (grid, qs, ks)
    }

    #[test]
    fn queries_filled_in_place_are_the_queries_made_one_by_one() {
        // 1,000 queries: pieces of 512 and a tail, written through `Source::Fill`'s
        // offsets; the last queries have no `k` (0).
        let (grid, qs, mut ks) = setup(1000);
        ks.truncate(990);
        let gq = GQueries {
            grid: &grid,
            qs: &qs,
            ks: &ks,
        };
        let want: Vec<GQuery> = (0..qs.len())
            .map(|i| gquery(&grid, &qs[i], ks.get(i).copied().unwrap_or(0)))
            .collect();
        assert_eq!(gq.to_vec(), want);
        let mut bytes = vec![0u8; qs.len() * GQueries::SIZE];
        let piece = super::super::device::FILL_PIECE;
        for (k, chunk) in bytes.chunks_mut(piece).enumerate() {
            gq.fill(k * piece, wgpu::WriteOnly::from(chunk));
        }
        let got: Vec<GQuery> = bytemuck::pod_collect_to_vec(&bytes);
        assert_eq!(got, want);
        assert!(got[995].k == 0 && got[5].k == 16 && got[5] != got[6]);
    }
}
