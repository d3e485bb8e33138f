//! The edge fit's Gaussian kernel over a cross-section's points: `exp(-|q - c|² / 2h²)`
//! per point and the weighted sums of a mean-shift round, written so that a compiler puts
//! several points in one vector register, with the same answer on every machine.
//!
//! - [`exp_neg`] is the exponential by a fixed sequence of additions and multiplications
//!   (no table, no branch, no fused multiply-add), within 4e-16 of the true value.
//!   The C library's `exp` is a call per point that no compiler vectorizes; it was 44 %
//!   of the edge fit.
//! - The sums run in [`LANES`] interleaved partial sums (point `i` into lane `i % LANES`),
//!   added together in a fixed order at the end. The order of every addition is the
//!   code's, not the instruction set's: the AVX2 copy (chosen at run time where the CPU
//!   has it) computes exactly what the baseline copy does, four points at a time instead
//!   of two.

use glam::DVec2;

/// Points per group of partial sums.
pub const LANES: usize = 4;

/// `exp(x)` for `x <= 0`, within 4e-16 relative of the true value; 0 below -700 (where
/// the true value is below 1e-304). Range reduction `x = k ln 2 + f`, `|f| <= ln 2 / 2`,
/// then the Taylor polynomial of degree 12 of `exp(f)` and `2^k` by its exponent bits.
#[inline(always)]
pub fn exp_neg(x: f64) -> f64 {
    const LOG2E: f64 = std::f64::consts::LOG2_E;
    // ln 2 in two parts (the high part exact in 32 bits), so that `k ln 2` is exact.
    const LN2_HI: f64 = f64::from_bits(0x3FE6_2E42_FEE0_0000);
    const LN2_LO: f64 = f64::from_bits(0x3DEA_39EF_3579_3C76);
    // 1.5 x 2^52: adding it rounds to an integer, which then sits in the low mantissa bits.
    const SHIFT: f64 = 6_755_399_441_055_744.0;
    let xc = if x < -700.0 { -700.0 } else { x };
    let y = xc * LOG2E + SHIFT;
    let k = y - SHIFT;
    let f = (xc - k * LN2_HI) - k * LN2_LO;
    let mut p = 1.0 / 479_001_600.0;
    p = p * f + 1.0 / 39_916_800.0;
    p = p * f + 1.0 / 3_628_800.0;
    p = p * f + 1.0 / 362_880.0;
    p = p * f + 1.0 / 40_320.0;
    p = p * f + 1.0 / 5_040.0;
    p = p * f + 1.0 / 720.0;
    p = p * f + 1.0 / 120.0;
    p = p * f + 1.0 / 24.0;
    p = p * f + 1.0 / 6.0;
    p = p * f + 0.5;
    p = p * f + 1.0;
    p = p * f + 1.0;
    // k in [-1010, 0]: 2^k is a normal number.
    let ki = (y.to_bits() as i64).wrapping_sub(SHIFT.to_bits() as i64);
    let two_k = f64::from_bits(((ki + 1023) as u64) << 52);
    if x < -700.0 {
        0.0
    } else {
        p * two_k
    }
}

/// A cross-section's points in columns, padded with weight-0 points to a multiple of
/// [`LANES`]: offsets `x`, `y`, per-point weights `w`, and room for kernel values `k`.
#[derive(Clone, Debug, Default)]
pub struct Columns {
    pub x: Vec<f64>,
    pub y: Vec<f64>,
    pub w: Vec<f64>,
    pub k: Vec<f64>,
    /// Real points (the rest is padding).
    pub n: usize,
}

impl Columns {
    /// The offsets `q` with per-point weights `pw`.
    pub fn new(q: impl ExactSizeIterator<Item = DVec2>, pw: &[f64]) -> Columns {
        let mut c = Columns::default();
        c.fill(q, pw);
        c
    }

    /// Holds the offsets `q` with per-point weights `pw` instead, keeping its room (the
    /// edge fit fills one per thread, step after step).
    pub fn fill(&mut self, q: impl ExactSizeIterator<Item = DVec2>, pw: &[f64]) {
        let n = q.len();
        let m = n.div_ceil(LANES) * LANES;
        self.x.clear();
        self.y.clear();
        self.w.clear();
        for q in q {
            self.x.push(q.x);
            self.y.push(q.y);
        }
        self.w.extend_from_slice(&pw[..n]);
        self.x.resize(m, 0.0);
        self.y.resize(m, 0.0);
        self.w.resize(m, 0.0);
        // Every kernel value is written before it is read.
        self.k.resize(m, 0.0);
        self.n = n;
    }

    /// The kernel `exp(-|q - c|² / 2h²)` of every point into `k` (padding included).
    pub fn kernel(&mut self, c: DVec2, h: f64) {
        let inv = 1.0 / (2.0 * h * h);
        if avx2() {
            // SAFETY: the CPU has AVX2.
            unsafe { kernel_avx2(self, c, inv) }
        } else {
            kernel_body(self, c, inv)
        }
    }

    /// `(Σ w k, Σ w k q)` over the points, with `k` as [`Columns::kernel`] left it.
    pub fn sums(&self) -> (f64, DVec2) {
        if avx2() {
            // SAFETY: the CPU has AVX2.
            unsafe { sums_avx2(self) }
        } else {
            sums_body(self)
        }
    }

    /// One mean-shift round: the kernel around `c` with width `h`, then its sums.
    pub fn round(&mut self, c: DVec2, h: f64) -> (f64, DVec2) {
        self.kernel(c, h);
        self.sums()
    }
}

/// Whether the CPU has AVX2 (the standard library caches the answer).
#[inline(always)]
pub(crate) fn avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

#[inline(always)]
fn kernel_body(c: &mut Columns, at: DVec2, inv: f64) {
    for ((k, x), y) in c.k.iter_mut().zip(&c.x).zip(&c.y) {
        let dx = x - at.x;
        let dy = y - at.y;
        *k = exp_neg(-(dx * dx + dy * dy) * inv);
    }
}

#[inline(always)]
fn sums_body(c: &Columns) -> (f64, DVec2) {
    let mut sw = [0.0f64; LANES];
    let mut sx = [0.0f64; LANES];
    let mut sy = [0.0f64; LANES];
    for (((k, w), x), y) in
        c.k.chunks_exact(LANES)
            .zip(c.w.chunks_exact(LANES))
            .zip(c.x.chunks_exact(LANES))
            .zip(c.y.chunks_exact(LANES))
    {
        for j in 0..LANES {
            let wk = w[j] * k[j];
            sw[j] += wk;
            sx[j] += x[j] * wk;
            sy[j] += y[j] * wk;
        }
    }
    let add = |s: [f64; LANES]| (s[0] + s[1]) + (s[2] + s[3]);
    (add(sw), DVec2::new(add(sx), add(sy)))
}

/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn kernel_avx2(c: &mut Columns, at: DVec2, inv: f64) {
    kernel_body(c, at, inv)
}

/// # Safety
/// The CPU has AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn sums_avx2(c: &Columns) -> (f64, DVec2) {
    sums_body(c)
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn kernel_avx2(c: &mut Columns, at: DVec2, inv: f64) {
    kernel_body(c, at, inv)
}

#[cfg(not(target_arch = "x86_64"))]
unsafe fn sums_avx2(c: &Columns) -> (f64, DVec2) {
    sums_body(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exp_neg_is_the_exponential_to_a_few_ulp() {
        let mut worst: f64 = 0.0;
        for i in 0..=700_000 {
            let x = -(i as f64) * 1e-3 - (i % 7) as f64 * 1.3e-4;
            let (a, b) = (exp_neg(x), x.exp());
            worst = worst.max(((a - b) / b).abs());
        }
        assert!(worst < 5e-16, "{worst:e}");
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(-700.5), 0.0);
        assert_eq!(exp_neg(f64::NEG_INFINITY), 0.0);
    }

    #[test]
    fn both_copies_sum_the_same_bits() {
        let mut rng = crate::synth::Rng::new(5);
        for n in [0, 1, 3, 4, 5, 17, 120] {
            let q: Vec<DVec2> = (0..n)
                .map(|_| DVec2::new(rng.normal(), rng.normal()) * 0.01)
                .collect();
            let pw: Vec<f64> = (0..n).map(|_| rng.uniform()).collect();
            let mut c = Columns::new(q.iter().copied(), &pw);
            let at = DVec2::new(0.001, -0.002);
            kernel_body(&mut c, at, 1.0 / (2.0 * 0.005f64.powi(2)));
            let base = sums_body(&c);
            let (sw, sq) = c.round(at, 0.005);
            assert_eq!(sw.to_bits(), base.0.to_bits());
            assert_eq!(sq.x.to_bits(), base.1.x.to_bits());
            assert_eq!(sq.y.to_bits(), base.1.y.to_bits());
            // And the sums are the sums.
            let k = |q: &DVec2| (-(*q - at).length_squared() / (2.0 * 0.005f64.powi(2))).exp();
            let direct: f64 = q.iter().zip(&pw).map(|(q, w)| w * k(q)).sum();
            let dq: DVec2 = q.iter().zip(&pw).map(|(q, w)| *q * (w * k(q))).sum();
            assert!(
                (sw - direct).abs() <= 1e-14 * direct.max(1.0),
                "{n}: {sw} {direct}"
            );
            assert!(
                (sq - dq).length() <= 1e-14 * direct.max(1.0),
                "{n}: {sq} {dq}"
            );
        }
    }
}
