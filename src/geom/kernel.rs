//! The edge fit's Gaussian kernel over a cross-section's points: `exp(-|q - c|² / 2h²)`
//! per point and the weighted sums of a mean-shift round, written so that a compiler puts
//! several points in one vector register, with the same answer on every machine.
//!
//! - [`exp_neg`] is the exponential by a fixed sequence of additions, multiplications and
//!   fused multiply-adds (no table, no branch), within 4e-16 of the true value. A fused
//!   multiply-add rounds once, by IEEE 754's rule, so it gives the same bits wherever it
//!   runs (an instruction on x86-64 with FMA and on ARM, the C library's `fma` elsewhere);
//!   its polynomial takes half the operations of separate multiplications and additions.
//!   The C library's `exp` is a call per point that no compiler vectorizes; it was 44 %
//!   of the edge fit.
//! - The sums run in [`LANES`] interleaved partial sums (point `i` into lane `i % LANES`),
//!   added together in a fixed order at the end. The order of every addition is the
//!   code's, not the instruction set's: the AVX2 copy (chosen at run time where the CPU
//!   has it, in explicit vector instructions, the kernel and the sums in one pass)
//!   computes exactly what the baseline copy does.

use glam::DVec2;

/// Points per group of partial sums.
pub const LANES: usize = 4;

/// `exp(x)` for `x <= 0`, within 4e-16 relative of the true value; 0 below -700 (where
/// the true value is below 1e-304). Range reduction `x = k ln 2 + f`, `|f| <= ln 2 / 2`,
/// then the Taylor polynomial of degree 12 of `exp(f)` by Horner's rule in fused
/// multiply-adds, and `2^k` by its exponent bits.
#[inline(always)]
pub fn exp_neg(x: f64) -> f64 {
    let xc = if x < -700.0 { -700.0 } else { x };
    let y = xc * LOG2E + SHIFT;
    let k = y - SHIFT;
    let f = (xc - k * LN2_HI) - k * LN2_LO;
    let mut p = TAYLOR[0];
    for &c in &TAYLOR[1..] {
        p = p.mul_add(f, c);
    }
    // k in [-1010, 0]: 2^k is a normal number.
    let ki = (y.to_bits() as i64).wrapping_sub(SHIFT.to_bits() as i64);
    let two_k = f64::from_bits(((ki + 1023) as u64) << 52);
    if x < -700.0 {
        0.0
    } else {
        p * two_k
    }
}

const LOG2E: f64 = std::f64::consts::LOG2_E;
/// ln 2 in two parts (the high part exact in 32 bits), so that `k ln 2` is exact.
const LN2_HI: f64 = f64::from_bits(0x3FE6_2E42_FEE0_0000);
const LN2_LO: f64 = f64::from_bits(0x3DEA_39EF_3579_3C76);
/// 1.5 x 2^52: adding it rounds to an integer, which then sits in the low mantissa bits.
const SHIFT: f64 = 6_755_399_441_055_744.0;
/// The Taylor coefficients of `exp` from degree 12 down to 0, for Horner's rule.
const TAYLOR: [f64; 13] = [
    1.0 / 479_001_600.0,
    1.0 / 39_916_800.0,
    1.0 / 3_628_800.0,
    1.0 / 362_880.0,
    1.0 / 40_320.0,
    1.0 / 5_040.0,
    1.0 / 720.0,
    1.0 / 120.0,
    1.0 / 24.0,
    1.0 / 6.0,
    0.5,
    1.0,
    1.0,
];

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
        self.clear();
        for q in q {
            self.x.push(q.x);
            self.y.push(q.y);
        }
        self.w.extend_from_slice(&pw[..n]);
        self.seal(n);
    }

    /// Empty, keeping its room.
    pub fn clear(&mut self) {
        self.x.clear();
        self.y.clear();
        self.w.clear();
        self.n = 0;
    }

    /// Adds the point `q` with weight `w` (after the first `n`, [`Columns::seal`]
    /// drops any padding first).
    #[inline]
    pub fn push(&mut self, q: DVec2, w: f64) {
        self.x.push(q.x);
        self.y.push(q.y);
        self.w.push(w);
    }

    /// Holds the first `n` points of `x`, `y` and `w`, padded.
    pub fn seal(&mut self, n: usize) {
        let m = n.div_ceil(LANES) * LANES;
        self.x.resize(n, 0.0);
        self.y.resize(n, 0.0);
        self.w.resize(n, 0.0);
        self.x.resize(m, 0.0);
        self.y.resize(m, 0.0);
        self.w.resize(m, 0.0);
        // Every kernel value is written before it is read.
        self.k.resize(m, 0.0);
        self.n = n;
    }

    /// One mean-shift round: the kernel `exp(-|q - c|² / 2h²)` of every point (padding
    /// included) into `k`, then the sums `(Σ w k, Σ w k q)` over the points.
    pub fn round(&mut self, c: DVec2, h: f64) -> (f64, DVec2) {
        let inv = 1.0 / (2.0 * h * h);
        #[cfg(target_arch = "x86_64")]
        if avx2() && std::arch::is_x86_feature_detected!("fma") {
            // SAFETY: the CPU has AVX2 and FMA.
            return unsafe { x86::round(self, c, inv) };
        }
        #[cfg(target_arch = "aarch64")]
        if std::arch::is_aarch64_feature_detected!("neon") {
            // SAFETY: the CPU has NEON (every aarch64 Linux and Apple CPU does).
            return unsafe { neon::round(self, c, inv) };
        }
        kernel_body(self, c, inv);
        sums_body(self)
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

/// The AVX2 round in explicit vector instructions: the same operations, in the same
/// order, as [`kernel_body`] and [`sums_body`] (so the same bits), on six groups of
/// [`LANES`] points at a time. The exponential is one long chain of dependent
/// multiplications and additions; independent chains side by side keep the vector
/// units busy where one waits on its own results (a compiler left to itself vectorizes
/// one group at a time).
#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{Columns, LANES, LN2_HI, LN2_LO, LOG2E, SHIFT, TAYLOR};
    use glam::DVec2;
    use std::arch::x86_64::*;

    /// Groups side by side: each step of the polynomial is a fused multiply-add, 4 cycles
    /// of latency on a Zen 3 core that starts two a cycle. Measured there (fit at
    /// 10^6 x 10^4, when each step was a multiplication then an addition): 4 groups
    /// 54.0 ms, 6 52.1 ms, 8 52.5 ms (8 chains need more than the 16 vector registers).
    const WIDE: usize = 6;

    /// [`super::exp_neg`] of `G` groups of four values, side by side.
    #[inline(always)]
    unsafe fn exp4<const G: usize>(x: [__m256d; G]) -> [__m256d; G] {
        let low = _mm256_set1_pd(-700.0);
        let shift = _mm256_set1_pd(SHIFT);
        let under = x.map(|x| _mm256_cmp_pd::<_CMP_LT_OQ>(x, low));
        let mut xc = x;
        let mut y = x;
        let mut f = x;
        let mut p = [_mm256_set1_pd(TAYLOR[0]); G];
        for g in 0..G {
            xc[g] = _mm256_blendv_pd(x[g], low, under[g]);
            y[g] = _mm256_add_pd(_mm256_mul_pd(xc[g], _mm256_set1_pd(LOG2E)), shift);
            let k = _mm256_sub_pd(y[g], shift);
            f[g] = _mm256_sub_pd(
                _mm256_sub_pd(xc[g], _mm256_mul_pd(k, _mm256_set1_pd(LN2_HI))),
                _mm256_mul_pd(k, _mm256_set1_pd(LN2_LO)),
            );
        }
        for &c in &TAYLOR[1..] {
            for g in 0..G {
                p[g] = _mm256_fmadd_pd(p[g], f[g], _mm256_set1_pd(c));
            }
        }
        let mut out = p;
        for g in 0..G {
            let ki = _mm256_sub_epi64(
                _mm256_castpd_si256(y[g]),
                _mm256_set1_epi64x(SHIFT.to_bits() as i64),
            );
            let two_k = _mm256_castsi256_pd(_mm256_slli_epi64::<52>(_mm256_add_epi64(
                ki,
                _mm256_set1_epi64x(1023),
            )));
            out[g] = _mm256_blendv_pd(_mm256_mul_pd(p[g], two_k), _mm256_setzero_pd(), under[g]);
        }
        out
    }

    /// [`super::kernel_body`] then [`super::sums_body`], fused: each group's kernel
    /// values are stored and summed while in registers.
    ///
    /// # Safety
    /// The CPU has AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    pub unsafe fn round(c: &mut Columns, at: DVec2, inv: f64) -> (f64, DVec2) {
        let n = c.k.len().min(c.x.len()).min(c.y.len()).min(c.w.len());
        // Whole groups only, as [`super::sums_body`] takes them (`fill` pads to groups).
        let n = n / LANES * LANES;
        let (xp, yp, wp, kp) = (c.x.as_ptr(), c.y.as_ptr(), c.w.as_ptr(), c.k.as_mut_ptr());
        let (ax, ay) = (_mm256_set1_pd(at.x), _mm256_set1_pd(at.y));
        let (vinv, sign) = (_mm256_set1_pd(inv), _mm256_set1_pd(-0.0));
        let arg = |i: usize| {
            let dx = _mm256_sub_pd(_mm256_loadu_pd(xp.add(i)), ax);
            let dy = _mm256_sub_pd(_mm256_loadu_pd(yp.add(i)), ay);
            let d2 = _mm256_add_pd(_mm256_mul_pd(dx, dx), _mm256_mul_pd(dy, dy));
            _mm256_mul_pd(_mm256_xor_pd(d2, sign), vinv)
        };
        let (mut sw, mut sx, mut sy) = (
            _mm256_setzero_pd(),
            _mm256_setzero_pd(),
            _mm256_setzero_pd(),
        );
        let mut add = |i: usize, k: __m256d| {
            _mm256_storeu_pd(kp.add(i), k);
            let wk = _mm256_mul_pd(_mm256_loadu_pd(wp.add(i)), k);
            sw = _mm256_add_pd(sw, wk);
            sx = _mm256_add_pd(sx, _mm256_mul_pd(_mm256_loadu_pd(xp.add(i)), wk));
            sy = _mm256_add_pd(sy, _mm256_mul_pd(_mm256_loadu_pd(yp.add(i)), wk));
        };
        let mut i = 0;
        // Blocks of G groups while they fit: six, then four, then one at a time.
        macro_rules! blocks {
            ($g:expr) => {
                while i + $g * LANES <= n {
                    let k = exp4::<{ $g }>(std::array::from_fn(|g| arg(i + g * LANES)));
                    for (g, k) in k.into_iter().enumerate() {
                        add(i + g * LANES, k);
                    }
                    i += $g * LANES;
                }
            };
        }
        blocks!(WIDE);
        blocks!(4);
        blocks!(1);
        let lanes = |v: __m256d| {
            let mut a = [0.0; LANES];
            _mm256_storeu_pd(a.as_mut_ptr(), v);
            (a[0] + a[1]) + (a[2] + a[3])
        };
        (lanes(sw), DVec2::new(lanes(sx), lanes(sy)))
    }
}

/// The NEON round (aarch64: Grace, Graviton, Apple): the same operations, in the same
/// order, as [`kernel_body`] and [`sums_body`], so the same bits, two points to a register.
/// A group of [`LANES`] points is two registers (lanes 0-1 and 2-3), so the four partial
/// sums are the baseline's, added in its order at the end; the exponential's polynomial
/// is one fused multiply-add a step (`vfmaq_f64`, one rounding, as `f64::mul_add`), and
/// three groups run side by side to keep the pipelines busy.
#[cfg(target_arch = "aarch64")]
mod neon {
    use super::{Columns, LANES, LN2_HI, LN2_LO, LOG2E, SHIFT, TAYLOR};
    use glam::DVec2;
    use std::arch::aarch64::*;

    /// Registers side by side (three groups of four points).
    const WIDE: usize = 6;

    /// [`super::exp_neg`] of `G` registers of two values, side by side.
    #[inline(always)]
    unsafe fn exp2<const G: usize>(x: [float64x2_t; G]) -> [float64x2_t; G] {
        let low = vdupq_n_f64(-700.0);
        let shift = vdupq_n_f64(SHIFT);
        let under = x.map(|x| vcltq_f64(x, low));
        let mut y = x;
        let mut f = x;
        let mut p = [vdupq_n_f64(TAYLOR[0]); G];
        for g in 0..G {
            let xc = vbslq_f64(under[g], low, x[g]);
            y[g] = vaddq_f64(vmulq_f64(xc, vdupq_n_f64(LOG2E)), shift);
            let k = vsubq_f64(y[g], shift);
            f[g] = vsubq_f64(
                vsubq_f64(xc, vmulq_f64(k, vdupq_n_f64(LN2_HI))),
                vmulq_f64(k, vdupq_n_f64(LN2_LO)),
            );
        }
        for &c in &TAYLOR[1..] {
            for g in 0..G {
                // p * f + c, rounded once
                p[g] = vfmaq_f64(vdupq_n_f64(c), p[g], f[g]);
            }
        }
        let mut out = p;
        for g in 0..G {
            let ki = vsubq_s64(
                vreinterpretq_s64_f64(y[g]),
                vdupq_n_s64(SHIFT.to_bits() as i64),
            );
            let two_k = vreinterpretq_f64_s64(vshlq_n_s64::<52>(vaddq_s64(ki, vdupq_n_s64(1023))));
            out[g] = vbslq_f64(under[g], vdupq_n_f64(0.0), vmulq_f64(p[g], two_k));
        }
        out
    }

    /// [`super::kernel_body`] then [`super::sums_body`], fused.
    ///
    /// # Safety
    /// The CPU has NEON.
    #[target_feature(enable = "neon")]
    pub unsafe fn round(c: &mut Columns, at: DVec2, inv: f64) -> (f64, DVec2) {
        let n = c.k.len().min(c.x.len()).min(c.y.len()).min(c.w.len());
        // Whole groups only, as [`super::sums_body`] takes them (`fill` pads to groups).
        let n = n / LANES * LANES;
        let (xp, yp, wp, kp) = (c.x.as_ptr(), c.y.as_ptr(), c.w.as_ptr(), c.k.as_mut_ptr());
        let (ax, ay, vinv) = (vdupq_n_f64(at.x), vdupq_n_f64(at.y), vdupq_n_f64(inv));
        // The argument of two points from `i`: -(dx dx + dy dy) * inv, as the baseline.
        let arg = |i: usize| {
            let dx = vsubq_f64(vld1q_f64(xp.add(i)), ax);
            let dy = vsubq_f64(vld1q_f64(yp.add(i)), ay);
            let d2 = vaddq_f64(vmulq_f64(dx, dx), vmulq_f64(dy, dy));
            vmulq_f64(vnegq_f64(d2), vinv)
        };
        let zero = vdupq_n_f64(0.0);
        // Lanes 0-1 and 2-3 of the baseline's four partial sums.
        let (mut sw, mut sx, mut sy) = ([zero; 2], [zero; 2], [zero; 2]);
        let mut add = |i: usize, half: usize, k: float64x2_t| {
            vst1q_f64(kp.add(i), k);
            let wk = vmulq_f64(vld1q_f64(wp.add(i)), k);
            sw[half] = vaddq_f64(sw[half], wk);
            sx[half] = vaddq_f64(sx[half], vmulq_f64(vld1q_f64(xp.add(i)), wk));
            sy[half] = vaddq_f64(sy[half], vmulq_f64(vld1q_f64(yp.add(i)), wk));
        };
        let mut i = 0;
        // Blocks of G registers (G / 2 groups) while they fit, then one group at a time.
        macro_rules! blocks {
            ($g:expr) => {
                while i + $g * 2 <= n {
                    let k = exp2::<{ $g }>(std::array::from_fn(|g| arg(i + g * 2)));
                    for (g, k) in k.into_iter().enumerate() {
                        add(i + g * 2, g % 2, k);
                    }
                    i += $g * 2;
                }
            };
        }
        blocks!(WIDE);
        blocks!(2);
        let total = |s: [float64x2_t; 2]| {
            (vgetq_lane_f64::<0>(s[0]) + vgetq_lane_f64::<1>(s[0]))
                + (vgetq_lane_f64::<0>(s[1]) + vgetq_lane_f64::<1>(s[1]))
        };
        (total(sw), DVec2::new(total(sx), total(sy)))
    }
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

    /// The vector copy of this machine (AVX2 on x86-64, NEON on aarch64) against the
    /// baseline, bit for bit, with kernel values from 1 down to the underflow below
    /// `exp(-700)` and weights of zero (padding) among them.
    #[test]
    fn the_vector_copy_is_the_baseline_to_the_bit_from_near_to_underflow() {
        let mut rng = crate::synth::Rng::new(11);
        for n in [1, 2, 3, 4, 7, 8, 11, 12, 23, 24, 25, 48, 49, 97, 1000] {
            for spread in [1e-4, 0.01, 0.1, 1.0] {
                let q: Vec<DVec2> = (0..n)
                    .map(|_| DVec2::new(rng.normal(), rng.normal()) * spread)
                    .collect();
                let pw: Vec<f64> = (0..n)
                    .map(|i| if i % 5 == 3 { 0.0 } else { rng.uniform() })
                    .collect();
                let mut c = Columns::new(q.iter().copied(), &pw);
                let (at, h) = (DVec2::new(0.003, -0.001), 0.004);
                kernel_body(&mut c, at, 1.0 / (2.0 * h * h));
                let (base, base_k) = (sums_body(&c), c.k.clone());
                c.k.iter_mut().for_each(|k| *k = f64::NAN);
                let (sw, sq) = c.round(at, h);
                for (a, b) in c.k.iter().zip(&base_k) {
                    assert_eq!(a.to_bits(), b.to_bits(), "{n} {spread}: {a} {b}");
                }
                assert_eq!(sw.to_bits(), base.0.to_bits(), "{n} {spread}");
                assert_eq!(sq.x.to_bits(), base.1.x.to_bits(), "{n} {spread}");
                assert_eq!(sq.y.to_bits(), base.1.y.to_bits(), "{n} {spread}");
                if spread >= 1.0 {
                    // far points: the kernel underflows to exactly 0 on both
                    assert!(base_k.contains(&0.0), "{n}");
                }
            }
        }
    }

    #[test]
    fn both_copies_sum_the_same_bits() {
        let mut rng = crate::synth::Rng::new(5);
        for n in [
            0, 1, 3, 4, 5, 8, 9, 12, 13, 17, 23, 24, 25, 41, 120, 121, 203,
        ] {
            let q: Vec<DVec2> = (0..n)
                .map(|_| DVec2::new(rng.normal(), rng.normal()) * 0.01)
                .collect();
            let pw: Vec<f64> = (0..n).map(|_| rng.uniform()).collect();
            let mut c = Columns::new(q.iter().copied(), &pw);
            let at = DVec2::new(0.001, -0.002);
            kernel_body(&mut c, at, 1.0 / (2.0 * 0.005f64.powi(2)));
            let (base, base_k) = (sums_body(&c), c.k.clone());
            let (sw, sq) = c.round(at, 0.005);
            assert!(c
                .k
                .iter()
                .zip(&base_k)
                .all(|(a, b)| a.to_bits() == b.to_bits()));
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
