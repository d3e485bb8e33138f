//! What a 3DGS model carries beyond the centers, per Gaussian: the surface normal (the
//! shortest axis of rotation `rot_0..3` = w x y z and log scales `scale_0..2`), the largest
//! and smallest scale, the opacity and the base colour (`f_dc_0..2`). Filled by the PLY reader's own walk
//! (`ply::read_gaussians_with_attributes`) and by the pass of `normals.rs`.

/// What a 3DGS PLY carries beyond the centers, per Gaussian kept by
/// [`super::read_gaussians`] with the same `min_opacity`, in the same order.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianAttributes {
    /// Unit surface normal (shortest axis; zero where the Gaussian is not flat).
    pub normals: Vec<[f32; 3]>,
    /// Largest standard deviation `exp(max scale_i)` (scene units).
    pub max_scale: Vec<f32>,
    /// Smallest standard deviation `exp(min scale_i)` (scene units): a flat Gaussian's
    /// thickness along its normal.
    pub min_scale: Vec<f32>,
    /// Opacity in `[0, 1]` (`sigmoid` of the stored logit), where the file has it.
    pub opacity: Option<Vec<f32>>,
    /// Base colour (RGB, `0.5 + C0 x f_dc_i`: the SH degree-0 terms), where the file has
    /// `f_dc_0..2`.
    pub colour: Option<Vec<[f32; 3]>>,
}

impl GaussianAttributes {
    /// Empty, with room for `n` Gaussians; opacities where `has_opacity`, colours where
    /// `has_colour`.
    pub(crate) fn with_capacity(n: usize, has_opacity: bool, has_colour: bool) -> Self {
        GaussianAttributes {
            normals: Vec::with_capacity(n),
            max_scale: Vec::with_capacity(n),
            min_scale: Vec::with_capacity(n),
            opacity: has_opacity.then(|| Vec::with_capacity(n)),
            colour: has_colour.then(|| Vec::with_capacity(n)),
        }
    }

    /// One kept Gaussian's attributes, computed already.
    pub(crate) fn push_one(&mut self, a: Attribute) {
        self.normals.push(a.normal);
        self.max_scale.push(a.max_scale);
        self.min_scale.push(a.min_scale);
        if let (Some(o), Some(a)) = (&mut self.opacity, a.opacity) {
            o.push(a);
        }
        if let (Some(c), Some(a)) = (&mut self.colour, a.colour) {
            c.push(a);
        }
    }
}

/// One Gaussian's entry of each of [`GaussianAttributes`]' columns.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Attribute {
    normal: [f32; 3],
    max_scale: f32,
    min_scale: f32,
    opacity: Option<f32>,
    colour: Option<[f32; 3]>,
}

/// The SH degree-0 basis constant: a Gaussian's base colour is `0.5 + C0 x f_dc`.
const SH_C0: f64 = 0.282_094_791_773_878_14;

impl Attribute {
    /// From its rotation (w x y z), log scales, opacity (`sigmoid` of the stored logit,
    /// where the file has one) and SH degree-0 terms `f_dc_0..2` (where it has them).
    pub(crate) fn of(
        rot: [f64; 4],
        log_scale: [f64; 3],
        alpha: Option<f64>,
        dc: Option<[f64; 3]>,
    ) -> Attribute {
        let [a, b, c] = log_scale;
        let scale = |s: f64| if s.is_nan() { f32::INFINITY } else { s as f32 };
        Attribute {
            normal: shortest_axis(rot, log_scale),
            max_scale: scale(a.max(b).max(c).exp()),
            min_scale: scale(a.min(b).min(c).exp()),
            opacity: alpha.map(|a| if a.is_nan() { 0.0 } else { a as f32 }),
            colour: dc.map(|d| d.map(|c| (0.5 + SH_C0 * c) as f32)),
        }
    }
}

/// `sigmoid` of an opacity logit as the file stores it (f32), as the attributes take it.
pub(crate) fn opacity_of(logit: f32) -> f64 {
    1.0 / (1.0 + (-(logit as f64)).exp())
}

/// The rotation's column of the smallest scale (log scales, as 3DGS stores them); zero for a
/// degenerate quaternion, or a Gaussian that is not flat (its shortest axis is not 1.5x
/// shorter than the next: no surface normal to speak of).
pub fn shortest_axis(q: [f64; 4], scale: [f64; 3]) -> [f32; 3] {
    let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if n.is_nan() || n <= 0.0 || !n.is_finite() {
        return [0.0; 3];
    }
    let [w, x, y, z] = q.map(|c| c / n);
    // The axes ordered by scale: a stable sort of three (ties keep their order), as
    // adjacent swaps of strictly greater neighbours; NaN as `total_cmp` places it.
    let mut order = [0usize, 1, 2];
    let mut swap_if_greater = |i: usize| {
        if scale[order[i]].total_cmp(&scale[order[i + 1]]).is_gt() {
            order.swap(i, i + 1);
        }
    };
    swap_if_greater(0);
    swap_if_greater(1);
    swap_if_greater(0);
    if scale[order[0]].is_nan() || scale[order[0]] + 1.5f64.ln() > scale[order[1]] {
        return [0.0; 3];
    }
    // That axis's column of the rotation matrix of (w, x, y, z).
    let col = match order[0] {
        0 => [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y + w * z),
            2.0 * (x * z - w * y),
        ],
        1 => [
            2.0 * (x * y - w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z + w * x),
        ],
        _ => [
            2.0 * (x * z + w * y),
            2.0 * (y * z - w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    };
    col.map(|c| c as f32)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The axis by a full sort and the whole rotation matrix: what `shortest_axis` must
    /// equal bit for bit.
    fn by_sort(q: [f64; 4], scale: [f64; 3]) -> [f32; 3] {
        let n = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
        if n.is_nan() || n <= 0.0 || !n.is_finite() {
            return [0.0; 3];
        }
        let [w, x, y, z] = q.map(|c| c / n);
        let cols = [
            [
                1.0 - 2.0 * (y * y + z * z),
                2.0 * (x * y + w * z),
                2.0 * (x * z - w * y),
            ],
            [
                2.0 * (x * y - w * z),
                1.0 - 2.0 * (x * x + z * z),
                2.0 * (y * z + w * x),
            ],
            [
                2.0 * (x * z + w * y),
                2.0 * (y * z - w * x),
                1.0 - 2.0 * (x * x + y * y),
            ],
        ];
        let mut order = [0usize, 1, 2];
        order.sort_by(|&a, &b| scale[a].total_cmp(&scale[b]));
        if scale[order[0]].is_nan() || scale[order[0]] + 1.5f64.ln() > scale[order[1]] {
            return [0.0; 3];
        }
        cols[order[0]].map(|c| c as f32)
    }

    #[test]
    fn the_axis_is_the_full_sorts_bit_for_bit() {
        let mut rng = crate::synth::Rng::new(3);
        let picks = [-3.0, -2.0, -1.0, 0.0, f64::NAN, -f64::NAN, f64::INFINITY];
        for i in 0..20_000 {
            let q = [0; 4].map(|_| rng.normal());
            // Ties, NaNs (of both signs) and infinities as well as spread values.
            let scale = [0; 3].map(|_| {
                if i % 3 == 0 {
                    picks[(rng.uniform() * picks.len() as f64) as usize % picks.len()]
                } else {
                    -4.0 * rng.uniform()
                }
            });
            let (a, b) = (shortest_axis(q, scale), by_sort(q, scale));
            assert_eq!(a.map(f32::to_bits), b.map(f32::to_bits), "{q:?} {scale:?}");
        }
    }

    #[test]
    fn the_normal_is_the_rotated_shortest_axis() {
        // identity: the axis of the smallest scale
        assert_eq!(
            shortest_axis([1.0, 0.0, 0.0, 0.0], [0.0, -3.0, 0.0]),
            [0.0, 1.0, 0.0]
        );
        // 90 degrees about z maps x to y
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let n = shortest_axis([h, 0.0, 0.0, h], [-5.0, 0.0, 0.0]);
        assert!((n[0]).abs() < 1e-6 && (n[1] - 1.0).abs() < 1e-6 && n[2].abs() < 1e-6);
        // unnormalized quaternions are normalized; degenerate ones give no normal
        assert_eq!(
            shortest_axis([2.0, 0.0, 0.0, 0.0], [0.0, 0.0, -1.0]),
            [0.0, 0.0, 1.0]
        );
        assert_eq!(shortest_axis([0.0; 4], [0.0, 0.0, -1.0]), [0.0; 3]);
        // a round Gaussian has no normal
        assert_eq!(
            shortest_axis([1.0, 0.0, 0.0, 0.0], [-2.0, -2.1, -2.0]),
            [0.0; 3]
        );
    }
}
