//! A small deterministic PRNG: xoshiro256** seeded through SplitMix64 (Blackman & Vigna).
//!
//! Hand-written so that the synthetic scenes, and every test and benchmark built on them,
//! stay bit-identical across platforms and dependency versions. `fork` gives each parallel
//! chunk its own stream keyed by the chunk's number, never by the thread that runs it, so
//! results do not depend on the number of threads.

use glam::DVec3;

const GOLDEN_GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

/// SplitMix64 step: advances `state` and returns the next output.
pub fn splitmix64(state: &mut u64) -> u64 {
    *state = state.wrapping_add(GOLDEN_GAMMA);
    mix64(*state)
}

/// SplitMix64's output function, a bijection on `u64` that spreads every input bit.
fn mix64(x: u64) -> u64 {
    let mut z = x;
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// xoshiro256** generator with a cached second Box–Muller value.
#[derive(Clone, Debug, PartialEq)]
pub struct Rng {
    s: [u64; 4],
    spare_normal: Option<f64>,
}

impl Rng {
    /// Generator for `seed`; the four state words come from SplitMix64, as the xoshiro
    /// authors recommend, so that close seeds still give unrelated streams.
    pub fn new(seed: u64) -> Self {
        let mut sm = seed;
        let s = [
            splitmix64(&mut sm),
            splitmix64(&mut sm),
            splitmix64(&mut sm),
            splitmix64(&mut sm),
        ];
        // Four consecutive SplitMix64 outputs are distinct, so the state is never all
        // zero (the one state xoshiro cannot leave).
        Rng {
            s,
            spare_normal: None,
        }
    }

    /// Generator with the given raw state (for the reference test vectors).
    #[cfg(test)]
    fn from_state(s: [u64; 4]) -> Self {
        Rng {
            s,
            spare_normal: None,
        }
    }

    /// An independent generator for sub-stream `stream`, derived from this generator's
    /// current state without advancing it: the same parent and `stream` always give the
    /// same child, different streams give unrelated children.
    pub fn fork(&self, stream: u64) -> Rng {
        let key = self.s[0]
            ^ self.s[1].rotate_left(16)
            ^ self.s[2].rotate_left(32)
            ^ self.s[3].rotate_left(48);
        // mix64 is a bijection, so distinct streams give distinct seeds for one parent.
        Rng::new(mix64(key) ^ mix64(stream.wrapping_mul(GOLDEN_GAMMA) ^ 0x5851_F42D_4C95_7F2D))
    }

    /// Next 64 random bits.
    pub fn next_u64(&mut self) -> u64 {
        let s = &mut self.s;
        let result = s[1].wrapping_mul(5).rotate_left(7).wrapping_mul(9);
        let t = s[1] << 17;
        s[2] ^= s[0];
        s[3] ^= s[1];
        s[1] ^= s[2];
        s[0] ^= s[3];
        s[2] ^= t;
        s[3] = s[3].rotate_left(45);
        result
    }

    /// Uniform in `[0, 1)` with 53 random bits.
    pub fn uniform(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }

    /// Uniform in `[a, b)` (or `[b, a)` when `b < a`).
    pub fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.uniform()
    }

    /// Uniform integer in `0..n` (0 when `n == 0`), by Lemire's multiply-shift; its bias
    /// is below `n / 2^64`, far under anything a synthetic scene can show.
    pub fn below(&mut self, n: u64) -> u64 {
        ((self.next_u64() as u128 * n as u128) >> 64) as u64
    }

    /// Standard normal variate (Box–Muller; the second value of each pair is kept for the
    /// next call).
    pub fn normal(&mut self) -> f64 {
        if let Some(z) = self.spare_normal.take() {
            return z;
        }
        // 1 - uniform() lies in (0, 1], so the logarithm is finite.
        let u1 = 1.0 - self.uniform();
        let u2 = self.uniform();
        let r = (-2.0 * u1.ln()).sqrt();
        let (sin, cos) = (std::f64::consts::TAU * u2).sin_cos();
        self.spare_normal = Some(r * sin);
        r * cos
    }

    /// Isotropic 3D normal vector with standard deviation `sigma` per axis.
    pub fn normal3(&mut self, sigma: f64) -> DVec3 {
        DVec3::new(self.normal(), self.normal(), self.normal()) * sigma
    }

    /// Uniformly distributed unit vector.
    pub fn unit_vector(&mut self) -> DVec3 {
        // A normalized isotropic normal is uniform on the sphere; retry the (practically
        // impossible) tiny draws so the direction is well defined.
        loop {
            let v = self.normal3(1.0);
            let l = v.length();
            if l > 1e-9 {
                return v / l;
            }
        }
    }

    /// Uniformly distributed unit vector perpendicular to the unit vector `d`.
    pub fn perpendicular(&mut self, d: DVec3) -> DVec3 {
        let (a, b) = d.any_orthonormal_pair();
        let (sin, cos) = (std::f64::consts::TAU * self.uniform()).sin_cos();
        a * cos + b * sin
    }

    /// Fisher–Yates shuffle.
    pub fn shuffle<T>(&mut self, items: &mut [T]) {
        for i in (1..items.len()).rev() {
            let j = self.below(i as u64 + 1) as usize;
            items.swap(i, j);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splitmix64_matches_reference_vectors() {
        // Outputs for seed 1234567 from the reference C implementation (Vigna).
        let mut s = 1234567u64;
        let got: Vec<u64> = (0..5).map(|_| splitmix64(&mut s)).collect();
        assert_eq!(
            got,
            [
                6457827717110365317,
                3203168211198807973,
                9817491932198370423,
                4593380528125082431,
                16408922859458223821
            ]
        );
    }

    #[test]
    fn xoshiro256starstar_matches_reference_vectors() {
        // Reference outputs for the state {1, 2, 3, 4} (as in the rand_xoshiro tests).
        let mut r = Rng::from_state([1, 2, 3, 4]);
        let got: Vec<u64> = (0..10).map(|_| r.next_u64()).collect();
        assert_eq!(
            got,
            [
                11520,
                0,
                1509978240,
                1215971899390074240,
                1216172134540287360,
                607988272756665600,
                16172922978634559625,
                8476171486693032832,
                10595114339597558777,
                2904607092377533576
            ]
        );
    }

    #[test]
    fn same_seed_same_stream_other_seed_other_stream() {
        let a: Vec<u64> = {
            let mut r = Rng::new(42);
            (0..100).map(|_| r.next_u64()).collect()
        };
        let b: Vec<u64> = {
            let mut r = Rng::new(42);
            (0..100).map(|_| r.next_u64()).collect()
        };
        let c: Vec<u64> = {
            let mut r = Rng::new(43);
            (0..100).map(|_| r.next_u64()).collect()
        };
        assert_eq!(a, b);
        assert!(a.iter().zip(&c).all(|(x, y)| x != y));
    }

    #[test]
    fn uniform_and_range_stay_in_bounds_with_the_right_mean() {
        let mut r = Rng::new(7);
        let n = 200_000;
        let mut sum = 0.0;
        let (mut lo, mut hi) = (f64::MAX, f64::MIN);
        for _ in 0..n {
            let u = r.uniform();
            assert!((0.0..1.0).contains(&u));
            sum += u;
            let x = r.range(-3.0, 5.0);
            lo = lo.min(x);
            hi = hi.max(x);
            assert!((-3.0..5.0).contains(&x));
        }
        assert!((sum / n as f64 - 0.5).abs() < 0.005);
        // The extremes of 200,000 draws come within 1e-3 of the interval ends.
        assert!(lo < -2.999 && hi > 4.999);
    }

    #[test]
    fn below_covers_every_value_evenly() {
        let mut r = Rng::new(11);
        let mut hist = [0usize; 7];
        for _ in 0..70_000 {
            hist[r.below(7) as usize] += 1;
        }
        for h in hist {
            assert!((9_500..10_500).contains(&h), "{hist:?}");
        }
        assert_eq!(r.below(0), 0);
    }

    #[test]
    fn normal_has_zero_mean_unit_variance_and_gaussian_tails() {
        let mut r = Rng::new(3);
        let n = 400_000;
        let xs: Vec<f64> = (0..n).map(|_| r.normal()).collect();
        let mean = xs.iter().sum::<f64>() / n as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n as f64;
        assert!(mean.abs() < 0.01, "mean {mean}");
        assert!((var - 1.0).abs() < 0.01, "variance {var}");
        // P(|z| > 2) = 4.55 % for a normal, 0 for a uniform-like mistake.
        let tail = xs.iter().filter(|x| x.abs() > 2.0).count() as f64 / n as f64;
        assert!((tail - 0.0455).abs() < 0.002, "tail {tail}");
    }

    #[test]
    fn fork_is_reproducible_independent_and_leaves_the_parent_alone() {
        let parent = Rng::new(99);
        let before = parent.clone();
        let mut f0 = parent.fork(0);
        let mut f0_again = parent.fork(0);
        let mut f1 = parent.fork(1);
        assert_eq!(parent, before);
        let a: Vec<u64> = (0..64).map(|_| f0.next_u64()).collect();
        let b: Vec<u64> = (0..64).map(|_| f0_again.next_u64()).collect();
        let c: Vec<u64> = (0..64).map(|_| f1.next_u64()).collect();
        assert_eq!(a, b);
        assert!(a.iter().zip(&c).all(|(x, y)| x != y));
        // Forks of different parents differ for the same stream.
        let mut g0 = Rng::new(100).fork(0);
        assert_ne!(a[0], g0.next_u64());
        // Adjacent streams are uncorrelated: the correlation of 100,000 paired uniforms is
        // within a few standard errors (1/sqrt(n) = 0.003) of zero.
        let (mut s0, mut s1) = (parent.fork(5), parent.fork(6));
        let n = 100_000;
        let pairs: Vec<(f64, f64)> = (0..n).map(|_| (s0.uniform(), s1.uniform())).collect();
        let cov = pairs
            .iter()
            .map(|(x, y)| (x - 0.5) * (y - 0.5))
            .sum::<f64>()
            / n as f64;
        let corr = cov / (1.0 / 12.0);
        assert!(corr.abs() < 0.015, "correlation {corr}");
    }

    #[test]
    fn directions_are_unit_and_perpendiculars_are_perpendicular() {
        let mut r = Rng::new(5);
        let d = DVec3::new(1.0, 2.0, -0.5).normalize();
        let mut mean = DVec3::ZERO;
        for _ in 0..10_000 {
            let u = r.unit_vector();
            assert!((u.length() - 1.0).abs() < 1e-12);
            mean += u;
            let p = r.perpendicular(d);
            assert!(p.dot(d).abs() < 1e-12);
            assert!((p.length() - 1.0).abs() < 1e-12);
        }
        assert!((mean / 10_000.0).length() < 0.03);
    }

    #[test]
    fn shuffle_is_a_permutation() {
        let mut r = Rng::new(1);
        let mut v: Vec<u32> = (0..1000).collect();
        r.shuffle(&mut v);
        assert_ne!(v, (0..1000).collect::<Vec<_>>());
        let mut sorted = v.clone();
        sorted.sort();
        assert_eq!(sorted, (0..1000).collect::<Vec<_>>());
    }
}
