//! Every threshold of docs/method.md#the-refinement-steps with its default, in one plain
//! struct that the JSON report serializes. The command line's options mirror it
//! (`src/cmd/params.rs`); callers without a command line build it directly or by name
//! ([`Params::set`]).

use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// `reference` reproduces the authors' published code (quirks included); `default`
/// follows the paper's intent with every **\[fix\]** of docs/method.md#profiles on.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "lowercase")]
pub enum Profile {
    #[default]
    Default,
    Reference,
}

/// Where step 4 moves each line (`--fit`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Fit {
    /// The published step: the mean offset of the nearest `translate_keep` of the points.
    /// It follows the Gaussians: use it to reproduce the paper, or to represent the
    /// Gaussians themselves.
    Paper,
    /// Onto the edge the Gaussians describe (two faces' intersection where normals exist,
    /// else the dense ridge; no move where neither is clear), iterated to convergence.
    Edge,
    /// No move.
    None,
}

impl Fit {
    pub fn name(self) -> &'static str {
        match self {
            Fit::Paper => "paper",
            Fit::Edge => "edge",
            Fit::None => "none",
        }
    }
}

/// Denominator of `R_L` (docs/method.md#evaluation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RlMode {
    /// `sum L / ln(sum N(s))`, the paper's equation.
    Paper,
    /// `sum L / ln(N_box)`, what the authors' code computes.
    Authors,
}

/// `--radius 0.03` or `--radius auto`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum RadiusArg {
    Fixed(f64),
    #[serde(with = "auto_str")]
    Auto,
}

mod auto_str {
    use serde::{Deserialize, Deserializer, Serializer};
    pub fn serialize<S: Serializer>(s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str("auto")
    }
    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<(), D::Error> {
        let s = String::deserialize(d)?;
        if s == "auto" {
            Ok(())
        } else {
            Err(serde::de::Error::custom("expected \"auto\""))
        }
    }
}

impl FromStr for RadiusArg {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.eq_ignore_ascii_case("auto") {
            return Ok(RadiusArg::Auto);
        }
        match s.parse::<f64>() {
            Ok(r) if r.is_finite() && r > 0.0 => Ok(RadiusArg::Fixed(r)),
            _ => Err(format!("expected a positive number or `auto`, got `{s}`")),
        }
    }
}

impl fmt::Display for RadiusArg {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            RadiusArg::Fixed(r) => write!(f, "{r}"),
            RadiusArg::Auto => write!(f, "auto"),
        }
    }
}

/// Value parser: a finite number above 0 (also for `eval --radii`).
pub fn positive(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("expected a positive number, got `{s}`")),
    }
}

/// Value parser: a finite number >= 0.
pub fn nonnegative(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("expected a number >= 0, got `{s}`")),
    }
}

/// Value parser: `--crop-extend`, a number in [0, 10].
pub fn extend_factor(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=10.0).contains(&v) => Ok(v),
        _ => Err(format!("expected a number in [0, 10], got `{s}`")),
    }
}

/// Value parser: `--outlier-ratio`, in [0, 1] or -1 (a ratio above 1 drops most
/// segments of any scene, one far above it all of them).
pub fn outlier_ratio(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v == -1.0 || (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("expected a number in [0, 1] or -1, got `{s}`")),
    }
}

/// Value parser: a number in [0, 1].
pub fn fraction(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("expected a number in [0, 1], got `{s}`")),
    }
}

/// Evaluation options (docs/method.md#evaluation), shared by `eval` and `refine`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EvalParams {
    /// Evaluation radius r_e of the cylinders (scene units).
    pub eval_radius: f64,
    /// Metres per scene unit, for E_rms in centimetres.
    pub unit_scale: f64,
    /// lambda of the score (the paper uses 1 for real scenes).
    pub score_lambda: f64,
    /// Denominator of R_L: `paper` (ln of summed N(s)) or `authors` (ln N_box).
    /// Default: the profile's (`paper` for default, `authors` for reference).
    pub r_l: Option<RlMode>,
}

impl Default for EvalParams {
    fn default() -> Self {
        EvalParams {
            eval_radius: 0.1,
            unit_scale: 1.0,
            score_lambda: 0.1,
            r_l: None,
        }
    }
}

/// The refinement thresholds of docs/method.md#the-refinement-steps (defaults from the
/// paper / the authors' code).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Params {
    /// `default` (the paper's intent, all fixes on) or `reference` (the authors' code,
    /// quirks included).
    pub profile: Profile,
    /// Cylinder radius r for refinement (scene units; the paper uses 0.03 for ABC-NEF and
    /// 0.05 for real scenes), or `auto`: 0.02 x the 95th-percentile distance of the working
    /// set's Gaussian centers from their centroid. Also the clustering distance scale r_c.
    pub radius: RadiusArg,

    /// Translate: fraction of the points nearest to the line whose mean offset moves it.
    pub translate_keep: f64,
    /// Step 4: `paper` (mean offset of the nearest translate-keep, the published step: to
    /// reproduce the paper, or to put the lines where the Gaussians are), `edge` (fit the
    /// edge: two faces' corner where the model has normals, else the dense ridge, iterated;
    /// to put the lines on the true edges) or `none`. Default: the profile's (`edge` for
    /// default, `paper` for reference).
    pub fit: Option<Fit>,
    /// Edge fit: most iterations (one engine batch each).
    pub fit_iterations: u32,
    /// Edge fit: largest turn of a line per iteration (degrees).
    pub fit_max_turn_deg: f64,
    /// Edge fit: largest total move of an endpoint, in units of r.
    pub fit_max_move: f64,
    /// Edge fit: final width of the ridge kernel, in units of r.
    pub fit_bandwidth: f64,
    /// Edge fit: fewest points under the kernel (or per face family) for a move; 1 or
    /// more.
    pub fit_min_points: u32,
    /// Edge fit: weight each Gaussian by its opacity (PLY `opacity`, after the sigmoid),
    /// so that faint floaters pull less; the fewest-points test still counts points. No
    /// effect where the model has no opacities or all are equal.
    pub fit_opacity_weight: bool,
    /// Edge fit: keep a segment where it is unless its Gaussians explain the move (the
    /// move gate): a corner only when both faces are thin slabs of splats and the input
    /// line lies outside one of them; a ridge only when less than a third of it is face
    /// splats. Measured in one batch of members of the fitted lines. `false`: every
    /// fitted move stands.
    pub fit_gate: bool,
    /// Leave out of the steps that place lines (the edge fit, its gate, the straightness
    /// test) every Gaussian whose largest standard deviation (`exp(max scale_i)`) exceeds
    /// this x r: a Gaussian wider than the cylinder cannot place a line within r. The
    /// steps that ask whether Gaussians are there (outliers, merges, crop, gaps) and the
    /// metrics see the whole model. Needs a 3DGS PLY with scales; 0: keep all.
    /// Default: the profile's (1 for default, 0 for reference).
    pub max_scale: Option<f64>,
    /// Drop a segment whose Gaussians' ridge bends across it by more than this x r: it
    /// follows a curve, not a line. The ridge is found (the edge fit's mean shift) in each
    /// third of the cylinder; the bend is the sagitta of the arc through the three, 9/4 of
    /// the middle one's offset from the chord through the others. A third with too few
    /// points is not judged. Runs after crop; 0: off.
    pub max_sagitta: f64,
    /// After crop, split a segment where a stretch of its cylinder holds no Gaussian
    /// (and cut an empty stretch off an end): a stretch at least r long is empty beyond
    /// chance when, at the segment's own density, the chance of so long an empty stretch
    /// among the segment's gaps (2 at the ends, N + 1 inside) is at most this. Pieces
    /// with fewer than fit-min-points points are dropped. 0: off. Default: the profile's
    /// (0.01 for default, 0 for reference).
    pub split_gaps: Option<f64>,
    /// `--split-gaps` also splits a segment at an empty interior stretch (not only cuts an
    /// empty end). Off by default: trained models leave stretches of a true edge without
    /// Gaussians (textureless faces, thinning near edges), and the chance rule, which
    /// assumes evenly spread Gaussians, split true edges there.
    pub split_interior: bool,

    /// Outliers: drop segments with density <= ratio x mean density, a ratio in [0, 1];
    /// -1 uses max(mean - 2 std, 0). Default: the profile's (0.1 for default: a trained
    /// model's density varies tenfold between its faces and its thin features; 0.2, the
    /// paper's, for reference).
    pub outlier_ratio: Option<f64>,

    /// Run the collinear merge inside input lines (Line3D++ `.txt` groups).
    pub collinear_merge: bool,

    /// Cluster: minimum similarity w of an edge.
    pub cluster_min_weight: f64,
    /// Cluster: initial per-root threshold c (thr = w + c / size after a join).
    pub cluster_c: f64,
    /// Cluster: |cos| between directions above which the length weight is non-zero.
    pub cluster_min_cos: f64,

    /// Merge: largest angle between the two directions (degrees).
    pub merge_angle_deg: f64,
    /// Merge: reject when both endpoints of the shorter are farther than this x L_long
    /// from the longer's line.
    pub merge_dist_frac: f64,
    /// Merge: reject when rho(G') < ratio x rho(G).
    pub merge_density_ratio: f64,

    /// Join: largest angle between the joined segment and each input (degrees).
    pub join_angle_deg: f64,
    /// Join: reject gaps longer than this x either length.
    pub join_gap_frac: f64,
    /// Join: the gap chord is shrunk by this fraction at each end before counting.
    pub join_chord_shrink: f64,
    /// Join (fix): the gap must hold at least this x mean density x chord length points.
    pub join_gap_density: f64,
    /// Join: reject J when rho(J) < ratio x rho of either input.
    pub join_density_ratio: f64,
    /// Join: reject J when E(J) > ratio x E of either input.
    pub join_rmse_ratio: f64,

    /// Crop: length of each end window as a fraction of L.
    pub crop_end_frac: f64,
    /// Crop: length of the middle window as a fraction of L.
    pub crop_mid_frac: f64,
    /// Crop: an end (or probe) is sparse below this x the middle density.
    pub crop_ratio: f64,
    /// Crop: half length of a binary-search probe window, as a fraction of L. Default:
    /// 0.1 with the authors' side-balance test (their `m ± 0.1 L`), 0.03 with the density
    /// test, whose window centred on the true end holds half the middle density whatever
    /// its size; a short window keeps the Gaussians of edges meeting at a corner from
    /// holding the end out past the corner.
    pub crop_probe_half: Option<f64>,
    /// Crop: also extend an end whose window is dense, along the line, while windows past
    /// it stay dense, by at most this x L (0: never extend, the paper's crop). Windows of
    /// 2 x the probe half length march outward, one batch per step, and the last is
    /// bisected; a corner stops the march, since past it the cylinder holds only the
    /// other edge's cross-section. 0 to 10; at most 256 windows an end.
    pub crop_extend: f64,
    /// Crop: most probes of the binary search, 1 to 64 (after 53 halvings an f64
    /// interval cannot shrink further, so more would only spin).
    pub crop_max_probes: u32,
    /// Crop: the binary search stops when its interval is shorter than this (a positive
    /// number; the probe limit bounds the search whatever its value).
    pub crop_min_interval: f64,

    /// Fix: cluster distance is the true 3D segment-to-segment distance (reference:
    /// lateral offset ignored when the shorter does not project inside). Default: profile.
    pub fix_cluster_distance: Option<bool>,
    /// Fix: a merge keeps the union of both extents along the kept line. Default: profile.
    pub fix_merge_extent: Option<bool>,
    /// Fix: a pair goes to the merge (not the join) when an endpoint of either projects
    /// inside the other (reference: only the shorter's endpoints inside the longer, as
    /// the authors test it). Default: profile.
    pub fix_merge_overlap: Option<bool>,
    /// Fix: join sorts endpoints by projection on the first direction (reference: by
    /// distance from its P1). Default: profile.
    pub fix_join_order: Option<bool>,
    /// Fix: join's gap test needs 0.6 x mean density x chord points, at least 1
    /// (reference: floor(mean density x chord)). Default: profile.
    pub fix_join_gap: Option<bool>,
    /// Fix: crop probes use the paper's density test (reference: side-count balance).
    /// Default: profile.
    pub fix_crop_density: Option<bool>,
    /// Fix: crop cuts an end only where the sparse stretch is at least r long (a shorter
    /// one is where the Gaussians thin out at a corner, not an overextension). Default:
    /// profile.
    pub fix_crop_min_cut: Option<bool>,
    /// Fix: crop searches an end only where its window is sparse beyond chance at the
    /// middle's density (Poisson, chance at most 0.01), so that a sparse model's few
    /// points do not cut true extent. Default: profile.
    pub fix_crop_chance: Option<bool>,
    /// Fix: a merge or join keeps every input endpoint within r/2 (the most one edge-fit
    /// step moves a line) of the line it makes, so that chords of a curve are not merged
    /// or joined across it and nearby parallel edges are not averaged. Default: profile.
    pub fix_merge_fidelity: Option<bool>,
    /// Order the endpoints of each segment so that |P1| <= |P2|, at load and for every
    /// segment a merge or join makes, as the authors' segment constructor does. Default:
    /// on for reference, off for default.
    pub order_endpoints: Option<bool>,

    #[serde(flatten)]
    pub eval: EvalParams,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            profile: Profile::Default,
            radius: RadiusArg::Fixed(0.03),
            translate_keep: 0.4,
            fit: None,
            fit_iterations: 12,
            fit_max_turn_deg: 3.0,
            fit_max_move: 2.0,
            fit_bandwidth: 0.25,
            fit_min_points: 8,
            fit_opacity_weight: false,
            fit_gate: true,
            split_interior: false,
            max_scale: None,
            max_sagitta: 0.0,
            split_gaps: None,
            outlier_ratio: None,
            collinear_merge: true,
            cluster_min_weight: 0.4,
            cluster_c: 1.5,
            cluster_min_cos: 0.5,
            merge_angle_deg: 30.0,
            merge_dist_frac: 0.2,
            merge_density_ratio: 0.6,
            join_angle_deg: 10.0,
            join_gap_frac: 0.8,
            join_chord_shrink: 0.02,
            join_gap_density: 0.6,
            join_density_ratio: 0.6,
            join_rmse_ratio: 1.1,
            crop_end_frac: 0.02,
            crop_mid_frac: 0.6,
            crop_ratio: 0.5,
            crop_probe_half: None,
            crop_extend: 0.0,
            crop_max_probes: 10,
            crop_min_interval: 1e-4,
            fix_cluster_distance: None,
            fix_merge_extent: None,
            fix_merge_overlap: None,
            fix_join_order: None,
            fix_join_gap: None,
            fix_crop_density: None,
            fix_crop_min_cut: None,
            fix_crop_chance: None,
            fix_merge_fidelity: None,
            order_endpoints: None,
            eval: EvalParams::default(),
        }
    }
}

/// The switches after the profile's defaults and the user's overrides are applied.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Fixes {
    pub cluster_distance: bool,
    pub merge_extent: bool,
    pub merge_overlap: bool,
    pub join_order: bool,
    pub join_gap: bool,
    pub crop_density: bool,
    pub crop_min_cut: bool,
    pub crop_chance: bool,
    pub merge_fidelity: bool,
    pub order_endpoints: bool,
    pub r_l: RlMode,
    pub fit: Fit,
}

/// The parameters resolved once, for one run: the profile's fixes applied and the
/// refinement radius fixed (`--radius auto` measured on the working set). Every step and
/// the evaluation take this one value, so a caller cannot pair one run's `Params` with
/// another's fixes or radius; it can only be built from a `Params`.
#[derive(Clone, Debug, PartialEq)]
pub struct Settings {
    params: Params,
    fixes: Fixes,
    radius: f64,
}

impl Settings {
    /// Resolves `params` over `working_set` (the centers refinement will see): `--radius
    /// auto` is measured there (docs/method.md#step-2-radius); a fixed radius is taken as given.
    pub fn resolve(params: Params, working_set: &[[f32; 3]]) -> Result<Settings, String> {
        let radius = match params.radius {
            RadiusArg::Fixed(r) => r,
            RadiusArg::Auto => auto_radius(working_set).ok_or_else(|| {
                "--radius auto needs Gaussian centers near the lines, and none are: are the lines and the Gaussians in one frame? (--gaussians-transform maps the model; README: Frames)".to_string()
            })?,
        };
        Ok(Settings {
            fixes: params.fixes(),
            params,
            radius,
        })
    }

    /// What the user asked for (`radius` may say `auto`).
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// The fixes in effect.
    pub fn fixes(&self) -> &Fixes {
        &self.fixes
    }

    /// The refinement radius `r` in effect (also the clustering scale `r_c`).
    pub fn radius(&self) -> f64 {
        self.radius
    }

    /// The evaluation options (docs/method.md#evaluation).
    pub fn eval(&self) -> &EvalParams {
        &self.params.eval
    }

    /// The denominator of `R_L` in effect.
    pub fn r_l(&self) -> RlMode {
        self.fixes.r_l
    }
}

/// `--radius auto` (docs/method.md#step-2-radius): `c` = centroid of the working set; keep
/// the centers closer to `c` than the 95th percentile (linear interpolation, as numpy) of the
/// distances; `r = 0.02 x` the largest kept distance.
pub fn auto_radius(points: &[[f32; 3]]) -> Option<f64> {
    if points.is_empty() {
        return None;
    }
    let n = points.len() as f64;
    let c = points
        .iter()
        .fold(glam::DVec3::ZERO, |a, p| a + crate::geom::p64(*p))
        / n;
    let mut d: Vec<f64> = points
        .iter()
        .map(|p| (crate::geom::p64(*p) - c).length())
        .collect();
    let pos = 0.95 * (d.len() - 1) as f64;
    let lo = pos.floor() as usize;
    let hi = pos.ceil() as usize;
    // The two order statistics by selection, not a sort of all (10^7 distances in a
    // large model): the `lo`-th in place, the `hi`-th the least of those above it.
    let (_, &mut d_lo, above) = d.select_nth_unstable_by(lo, f64::total_cmp);
    let d_hi = if hi == lo {
        d_lo
    } else {
        above.iter().copied().min_by(f64::total_cmp).unwrap_or(d_lo)
    };
    let p95 = d_lo + (d_hi - d_lo) * (pos - lo as f64);
    let kept = d
        .iter()
        .copied()
        .filter(|&x| x < p95)
        .fold(f64::NAN, f64::max);
    let r = 0.02 * if kept.is_nan() { p95 } else { kept };
    (r > 0.0).then_some(r)
}

impl Params {
    /// These parameters with the refinement radius fixed to `r`, resolved: what a test or a
    /// caller that already knows `r` passes to a step.
    pub fn with_radius(&self, r: f64) -> Settings {
        let params = Params {
            radius: RadiusArg::Fixed(r),
            ..self.clone()
        };
        Settings {
            fixes: params.fixes(),
            params,
            radius: r,
        }
    }

    pub fn reference() -> Self {
        Params {
            profile: Profile::Reference,
            ..Params::default()
        }
    }

    /// The crop probe half window in effect (see `crop_probe_half`).
    pub fn crop_probe_half(&self) -> f64 {
        self.crop_probe_half
            .unwrap_or(if self.fixes().crop_density { 0.03 } else { 0.1 })
    }

    /// `--max-scale` in effect: the user's, else the profile's (1 for default, 0 for
    /// reference, which keeps every Gaussian as the authors' code does).
    pub fn max_scale(&self) -> f64 {
        self.max_scale.unwrap_or(match self.profile {
            Profile::Default => 1.0,
            Profile::Reference => 0.0,
        })
    }

    /// `--outlier-ratio` in effect: the user's, else the profile's (0.1 for default, 0.2,
    /// the paper's, for reference).
    pub fn outlier_ratio(&self) -> f64 {
        self.outlier_ratio.unwrap_or(match self.profile {
            Profile::Default => 0.1,
            Profile::Reference => 0.2,
        })
    }

    /// `--split-gaps` in effect: the user's, else the profile's (0.01 for default, 0 for
    /// reference).
    pub fn split_gaps(&self) -> f64 {
        self.split_gaps.unwrap_or(match self.profile {
            Profile::Default => 0.01,
            Profile::Reference => 0.0,
        })
    }

    pub fn fixes(&self) -> Fixes {
        let on = self.profile == Profile::Default;
        Fixes {
            cluster_distance: self.fix_cluster_distance.unwrap_or(on),
            merge_extent: self.fix_merge_extent.unwrap_or(on),
            merge_overlap: self.fix_merge_overlap.unwrap_or(on),
            join_order: self.fix_join_order.unwrap_or(on),
            join_gap: self.fix_join_gap.unwrap_or(on),
            crop_density: self.fix_crop_density.unwrap_or(on),
            crop_min_cut: self.fix_crop_min_cut.unwrap_or(on),
            crop_chance: self.fix_crop_chance.unwrap_or(on),
            merge_fidelity: self.fix_merge_fidelity.unwrap_or(on),
            order_endpoints: self.order_endpoints.unwrap_or(!on),
            fit: self.fit.unwrap_or(if on { Fit::Edge } else { Fit::Paper }),
            r_l: self
                .eval
                .r_l
                .unwrap_or(if on { RlMode::Paper } else { RlMode::Authors }),
        }
    }
}

impl Params {
    /// The name of every parameter [`Params::set`] takes, in the command line's order
    /// (there `--{name}` with `-` for `_`).
    pub const NAMES: &'static [&'static str] = &[
        "profile",
        "radius",
        "translate_keep",
        "fit",
        "fit_iterations",
        "fit_max_turn_deg",
        "fit_max_move",
        "fit_bandwidth",
        "fit_min_points",
        "fit_opacity_weight",
        "fit_gate",
        "max_scale",
        "max_sagitta",
        "split_gaps",
        "split_interior",
        "outlier_ratio",
        "collinear_merge",
        "cluster_min_weight",
        "cluster_c",
        "cluster_min_cos",
        "merge_angle_deg",
        "merge_dist_frac",
        "merge_density_ratio",
        "join_angle_deg",
        "join_gap_frac",
        "join_chord_shrink",
        "join_gap_density",
        "join_density_ratio",
        "join_rmse_ratio",
        "crop_end_frac",
        "crop_mid_frac",
        "crop_ratio",
        "crop_probe_half",
        "crop_extend",
        "crop_max_probes",
        "crop_min_interval",
        "fix_cluster_distance",
        "fix_merge_extent",
        "fix_merge_overlap",
        "fix_join_order",
        "fix_join_gap",
        "fix_crop_density",
        "fix_crop_min_cut",
        "fix_crop_chance",
        "fix_merge_fidelity",
        "order_endpoints",
        "eval_radius",
        "unit_scale",
        "score_lambda",
        "r_l",
    ];

    /// Sets the parameter `name` (one of [`Params::NAMES`]) from its text, with the
    /// command line's checks: `set("radius", "auto")`, `set("fit_gate", "false")`. An
    /// unknown name or a value out of range is an error that names both.
    pub fn set(&mut self, name: &str, value: &str) -> Result<(), String> {
        let set = |this: &mut Params| -> Result<(), String> {
            match name {
                "profile" => this.profile = value.parse()?,
                "radius" => this.radius = value.parse()?,
                "translate_keep" => this.translate_keep = fraction(value)?,
                "fit" => this.fit = Some(value.parse()?),
                "fit_iterations" => this.fit_iterations = in_range(value, 0, u32::MAX)?,
                "fit_max_turn_deg" => this.fit_max_turn_deg = positive(value)?,
                "fit_max_move" => this.fit_max_move = positive(value)?,
                "fit_bandwidth" => this.fit_bandwidth = positive(value)?,
                "fit_min_points" => this.fit_min_points = in_range(value, 1, u32::MAX)?,
                "fit_opacity_weight" => this.fit_opacity_weight = boolean(value)?,
                "fit_gate" => this.fit_gate = boolean(value)?,
                "max_scale" => this.max_scale = Some(nonnegative(value)?),
                "max_sagitta" => this.max_sagitta = nonnegative(value)?,
                "split_gaps" => this.split_gaps = Some(fraction(value)?),
                "split_interior" => this.split_interior = boolean(value)?,
                "outlier_ratio" => this.outlier_ratio = Some(outlier_ratio(value)?),
                "collinear_merge" => this.collinear_merge = boolean(value)?,
                "cluster_min_weight" => this.cluster_min_weight = fraction(value)?,
                "cluster_c" => this.cluster_c = positive(value)?,
                "cluster_min_cos" => this.cluster_min_cos = fraction(value)?,
                "merge_angle_deg" => this.merge_angle_deg = positive(value)?,
                "merge_dist_frac" => this.merge_dist_frac = positive(value)?,
                "merge_density_ratio" => this.merge_density_ratio = positive(value)?,
                "join_angle_deg" => this.join_angle_deg = positive(value)?,
                "join_gap_frac" => this.join_gap_frac = positive(value)?,
                "join_chord_shrink" => this.join_chord_shrink = fraction(value)?,
                "join_gap_density" => this.join_gap_density = positive(value)?,
                "join_density_ratio" => this.join_density_ratio = positive(value)?,
                "join_rmse_ratio" => this.join_rmse_ratio = positive(value)?,
                "crop_end_frac" => this.crop_end_frac = fraction(value)?,
                "crop_mid_frac" => this.crop_mid_frac = fraction(value)?,
                "crop_ratio" => this.crop_ratio = fraction(value)?,
                "crop_probe_half" => this.crop_probe_half = Some(positive(value)?),
                "crop_extend" => this.crop_extend = extend_factor(value)?,
                "crop_max_probes" => this.crop_max_probes = in_range(value, 1, 64)?,
                "crop_min_interval" => this.crop_min_interval = positive(value)?,
                "fix_cluster_distance" => this.fix_cluster_distance = Some(boolean(value)?),
                "fix_merge_extent" => this.fix_merge_extent = Some(boolean(value)?),
                "fix_merge_overlap" => this.fix_merge_overlap = Some(boolean(value)?),
                "fix_join_order" => this.fix_join_order = Some(boolean(value)?),
                "fix_join_gap" => this.fix_join_gap = Some(boolean(value)?),
                "fix_crop_density" => this.fix_crop_density = Some(boolean(value)?),
                "fix_crop_min_cut" => this.fix_crop_min_cut = Some(boolean(value)?),
                "fix_crop_chance" => this.fix_crop_chance = Some(boolean(value)?),
                "fix_merge_fidelity" => this.fix_merge_fidelity = Some(boolean(value)?),
                "order_endpoints" => this.order_endpoints = Some(boolean(value)?),
                "eval_radius" => this.eval.eval_radius = positive(value)?,
                "unit_scale" => this.eval.unit_scale = positive(value)?,
                "score_lambda" => this.eval.score_lambda = positive(value)?,
                "r_l" => this.eval.r_l = Some(value.parse()?),
                _ => return Err(format!("unknown parameter `{name}`")),
            }
            Ok(())
        };
        set(self).map_err(|e| {
            if e.starts_with("unknown parameter") {
                e
            } else {
                format!("invalid value '{value}' for '{name}': {e}")
            }
        })
    }
}

/// A whole number in `[lo, hi]`.
fn in_range(s: &str, lo: u32, hi: u32) -> Result<u32, String> {
    match s.parse::<u32>() {
        Ok(v) if (lo..=hi).contains(&v) => Ok(v),
        Ok(v) => Err(format!("{v} is not in {lo}..={hi}")),
        Err(_) => Err(format!(
            "expected a whole number in [{lo}, {hi}], got `{s}`"
        )),
    }
}

/// `true` or `false`.
fn boolean(s: &str) -> Result<bool, String> {
    match s {
        "true" => Ok(true),
        "false" => Ok(false),
        _ => Err(format!("expected `true` or `false`, got `{s}`")),
    }
}

/// The names of an enumeration's values, for its parser's message.
fn one_of<T: Copy>(s: &str, values: &[(&str, T)]) -> Result<T, String> {
    values
        .iter()
        .find(|(n, _)| *n == s)
        .map(|(_, v)| *v)
        .ok_or_else(|| {
            let names: Vec<String> = values.iter().map(|(n, _)| format!("`{n}`")).collect();
            format!("expected {}, got `{s}`", names.join(", "))
        })
}

impl FromStr for Profile {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        one_of(
            s,
            &[
                ("default", Profile::Default),
                ("reference", Profile::Reference),
            ],
        )
    }
}

impl FromStr for Fit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        one_of(
            s,
            &[
                ("paper", Fit::Paper),
                ("edge", Fit::Edge),
                ("none", Fit::None),
            ],
        )
    }
}

impl FromStr for RlMode {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        one_of(s, &[("paper", RlMode::Paper), ("authors", RlMode::Authors)])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn profiles_switch_every_fix() {
        let d = Params::default().fixes();
        assert!(d.cluster_distance && d.merge_extent && d.join_order && d.join_gap);
        assert!(d.crop_density && !d.order_endpoints && d.r_l == RlMode::Paper);
        assert_eq!(d.fit, Fit::Edge);
        assert_eq!(Params::reference().fixes().fit, Fit::Paper);
        assert!(d.merge_overlap && !Params::reference().fixes().merge_overlap);
        let r = Params::reference().fixes();
        assert!(!r.cluster_distance && !r.merge_extent && !r.join_order && !r.join_gap);
        assert!(!r.crop_density && r.order_endpoints && r.r_l == RlMode::Authors);
        assert_eq!(Params::default().split_gaps(), 0.01);
        assert_eq!(Params::reference().split_gaps(), 0.0);
        let one = Params {
            fix_join_gap: Some(true),
            ..Params::reference()
        }
        .fixes();
        assert!(one.join_gap && !one.join_order);
    }

    #[test]
    fn auto_radius_by_selection_equals_the_sorted_percentile() {
        // numpy's linear interpolation between the sorted distances, as the docs state it.
        let by_sort = |pts: &[[f32; 3]]| {
            let n = pts.len() as f64;
            let c = pts
                .iter()
                .fold(glam::DVec3::ZERO, |a, p| a + crate::geom::p64(*p))
                / n;
            let mut d: Vec<f64> = pts
                .iter()
                .map(|p| (crate::geom::p64(*p) - c).length())
                .collect();
            d.sort_by(f64::total_cmp);
            let pos = 0.95 * (d.len() - 1) as f64;
            let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
            let p95 = d[lo] + (d[hi] - d[lo]) * (pos - lo as f64);
            let kept = d
                .iter()
                .copied()
                .filter(|&x| x < p95)
                .fold(f64::NAN, f64::max);
            0.02 * if kept.is_nan() { p95 } else { kept }
        };
        let mut rng = crate::synth::Rng::new(3);
        // 1,000 and 1,001 points: the percentile falls between two distances, or on one.
        for n in [1000, 1001, 7, 2] {
            let pts: Vec<[f32; 3]> = (0..n)
                .map(|_| rng.normal3(1.0).as_vec3().to_array())
                .collect();
            assert_eq!(
                auto_radius(&pts).unwrap().to_bits(),
                by_sort(&pts).to_bits(),
                "{n}"
            );
        }
    }

    #[test]
    fn auto_radius_is_two_percent_of_the_kept_extent() {
        // 100 points at distances 1..=100 from the centroid (on alternating sides so the
        // centroid stays at 0, plus the origin).
        let mut pts = vec![[0f32, 0.0, 0.0]];
        for i in 1..=100 {
            pts.push([i as f32, 0.0, 0.0]);
            pts.push([-(i as f32), 0.0, 0.0]);
        }
        let r = auto_radius(&pts).unwrap();
        // distances: 0, then 1,1,2,2,...,100,100 (201 values); p95 at index 190 -> 95;
        // kept < 95 -> max 94.
        assert!((r - 0.02 * 94.0).abs() < 1e-12, "{r}");
        assert_eq!(auto_radius(&[]), None);
        let auto = Params {
            radius: RadiusArg::Auto,
            ..Params::default()
        };
        let s = Settings::resolve(auto.clone(), &pts).unwrap();
        assert_eq!(s.radius(), r);
        assert_eq!(s.params().radius, RadiusArg::Auto);
        assert!(Settings::resolve(auto, &[]).is_err());
    }

    #[test]
    fn settings_carry_the_fixes_of_their_own_params() {
        let s = Params::reference().with_radius(0.05);
        assert_eq!(*s.fixes(), Params::reference().fixes());
        assert_eq!(s.radius(), 0.05);
        assert_eq!(s.params().radius, RadiusArg::Fixed(0.05));
        assert_eq!(s.r_l(), RlMode::Authors);
    }

    #[test]
    fn radius_parses_numbers_and_auto() {
        assert_eq!("auto".parse::<RadiusArg>(), Ok(RadiusArg::Auto));
        assert_eq!("0.05".parse::<RadiusArg>(), Ok(RadiusArg::Fixed(0.05)));
        assert!("-1".parse::<RadiusArg>().is_err());
        assert!("nan".parse::<RadiusArg>().is_err());
    }

    #[test]
    fn params_serialize_with_every_field() {
        let v = serde_json::to_value(Params::default()).unwrap();
        assert_eq!(v["radius"], serde_json::json!(0.03));
        assert_eq!(v["eval_radius"], serde_json::json!(0.1));
        assert_eq!(v["crop_max_probes"], serde_json::json!(10));
        let a = serde_json::to_value(RadiusArg::Auto).unwrap();
        assert_eq!(a, serde_json::json!("auto"));
    }
}
