//! The parameters of the refinement (docs/method.md#the-refinement-steps): each step
//! declares its own in its file with [`group!`] (a struct with each field's doc, default
//! and check), and [`Params`] gathers them, flattened, so that the JSON report, the
//! command line (`src/cmd/params.rs` builds its options from [`Group::PARAMS`]) and
//! [`Params::set`] see one flat list of names. Callers without a command line build
//! `Params` directly or by name.

use super::Params;
use serde::{Deserialize, Serialize};
use std::fmt;
use std::str::FromStr;

/// A parameter's text that its check refuses, or a name no parameter has.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ParamError {
    #[error("expected a positive number or `auto`, got `{0}`")]
    Radius(String),
    #[error("expected a positive number, got `{0}`")]
    NotPositive(String),
    #[error("expected a number >= 0, got `{0}`")]
    Negative(String),
    #[error("expected a number in [0, 10], got `{0}`")]
    NotExtendFactor(String),
    #[error("expected a number in [0, 1] or -1, got `{0}`")]
    NotOutlierRatio(String),
    #[error("expected a number in [0, 1], got `{0}`")]
    NotFraction(String),
    #[error("{value} is not in {lo}..={hi}")]
    OutOfRange { value: u32, lo: u32, hi: u32 },
    #[error("expected a whole number in [{lo}, {hi}], got `{text}`")]
    NotWhole { text: String, lo: u32, hi: u32 },
    #[error("expected `true` or `false`, got `{0}`")]
    NotBool(String),
    #[error("expected {expected}, got `{text}`")]
    NotOneOf { expected: String, text: String },
    #[error("unknown parameter `{0}`")]
    Unknown(String),
    #[error("invalid value '{value}' for '{name}': {error}")]
    Invalid {
        name: String,
        value: String,
        error: Box<ParamError>,
    },
    #[error("--radius auto needs Gaussian centers near the lines, and none are: are the lines and the Gaussians in one frame? (--gaussians-transform maps the model; README: Frames)")]
    NoCentersForAuto,
}

/// How a parameter's text is read and checked, by [`Params::set`] and the command line
/// alike.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Check {
    /// A finite number above 0 ([`positive`]).
    Positive,
    /// A finite number >= 0 ([`nonnegative`]).
    NonNegative,
    /// A number in [0, 1] ([`fraction`]).
    Fraction,
    /// A number in [0, 1] or -1 ([`outlier_ratio`]; the option takes `-1`).
    OutlierRatio,
    /// A number in [0, 10] ([`extend_factor`]).
    ExtendFactor,
    /// A whole number in `[lo, hi]`.
    Whole { lo: u32, hi: u32 },
    /// `true` or `false`; the option's value is named after the parameter.
    Bool,
    /// `true` or `false`; the option's value is named `BOOL`.
    Switch,
    /// A positive number or `auto` ([`RadiusArg`]).
    Radius,
    /// One of these names.
    Choice(&'static [Choice]),
}

/// One value of an enumeration a parameter takes by name, with its doc comment.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Choice {
    pub name: &'static str,
    pub doc: &'static str,
}

/// One parameter: its name (the field's, and the option `--{name}` with `-` for `_`), its
/// doc comment (the option's help), its check, and its default as `--help` shows it
/// (none where the profile decides).
#[derive(Clone, Copy, Debug)]
pub struct Param {
    pub name: &'static str,
    pub doc: &'static str,
    pub check: Check,
    pub shown_default: fn() -> Option<String>,
}

/// A struct of parameters made by [`group!`]: every parameter in it and in the groups it
/// flattens, in order, and setting one by name.
pub trait Group: Default {
    const PARAMS: &'static [Param];
    /// Sets the parameter `name` from its text; `None` when no parameter of this group
    /// has that name.
    fn set_param(&mut self, name: &str, value: &str) -> Option<Result<(), ParamError>>;
}

/// A parameter's type: read from text under a [`Check`], and shown as a default.
pub trait Value: Sized {
    fn parse(text: &str, check: Check) -> Result<Self, ParamError>;
    /// The default `--help` shows (`None`: none shown).
    fn shown(&self) -> Option<String>;
}

impl Value for f64 {
    fn parse(text: &str, check: Check) -> Result<f64, ParamError> {
        match check {
            Check::Positive => positive(text),
            Check::NonNegative => nonnegative(text),
            Check::Fraction => fraction(text),
            Check::OutlierRatio => outlier_ratio(text),
            Check::ExtendFactor => extend_factor(text),
            _ => unreachable!("a number parameter with the check {check:?}"),
        }
    }
    fn shown(&self) -> Option<String> {
        Some(self.to_string())
    }
}

impl Value for u32 {
    fn parse(text: &str, check: Check) -> Result<u32, ParamError> {
        match check {
            Check::Whole { lo, hi } => in_range(text, lo, hi),
            _ => unreachable!("a whole-number parameter with the check {check:?}"),
        }
    }
    fn shown(&self) -> Option<String> {
        Some(self.to_string())
    }
}

impl Value for bool {
    fn parse(text: &str, _: Check) -> Result<bool, ParamError> {
        boolean(text)
    }
    fn shown(&self) -> Option<String> {
        Some(self.to_string())
    }
}

impl<T: Value> Value for Option<T> {
    fn parse(text: &str, check: Check) -> Result<Option<T>, ParamError> {
        T::parse(text, check).map(Some)
    }
    fn shown(&self) -> Option<String> {
        None
    }
}

impl Value for RadiusArg {
    fn parse(text: &str, _: Check) -> Result<RadiusArg, ParamError> {
        text.parse()
    }
    fn shown(&self) -> Option<String> {
        Some(self.to_string())
    }
}

/// The parameters of `parts`, one after the other, as one array (for [`Group::PARAMS`]).
pub const fn concat<const N: usize>(parts: &[&[Param]]) -> [Param; N] {
    const NONE: Param = Param {
        name: "",
        doc: "",
        check: Check::Bool,
        shown_default: || None,
    };
    let mut out = [NONE; N];
    let (mut i, mut k) = (0, 0);
    while i < parts.len() {
        let mut j = 0;
        while j < parts[i].len() {
            out[k] = parts[i][j];
            k += 1;
            j += 1;
        }
        i += 1;
    }
    assert!(k == N, "the parameters do not fill the array");
    out
}

/// How many names (for [`group!`]'s count of its own fields).
pub const fn count(names: &[&str]) -> usize {
    names.len()
}

/// Declares a struct of parameters: each field with its doc comment (the option's help),
/// its default and its [`Check`], then the groups it flattens (`..name: Type,`). Makes the
/// struct (serialized flat: a flattened group's fields sit among the others), its
/// `Default` and its [`Group`] implementation.
///
/// ```ignore
/// group! {
///     /// The crop step's parameters.
///     pub struct CropParams {
///         /// Crop: length of each end window as a fraction of L.
///         crop_end_frac: f64 = 0.02, Check::Fraction;
///     }
/// }
/// ```
macro_rules! group {
    (
        $(#[$meta:meta])*
        pub struct $name:ident {
            $(
                $(#[doc = $doc:expr])*
                $field:ident: $ty:ty = $default:expr, $check:expr;
            )*
            $(
                ..$group:ident: $gty:ty,
            )*
        }
    ) => {
        $(#[$meta])*
        #[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
        pub struct $name {
            $(
                $(#[doc = $doc])*
                pub $field: $ty,
            )*
            $(
                #[doc = concat!("The parameters of `", stringify!($gty), "`, flattened.")]
                #[serde(flatten)]
                pub $group: $gty,
            )*
        }

        impl Default for $name {
            fn default() -> Self {
                $name {
                    $($field: $default,)*
                    $($group: Default::default(),)*
                }
            }
        }

        impl $crate::refine::params::Group for $name {
            const PARAMS: &'static [$crate::refine::params::Param] =
                &$crate::refine::params::concat::<
                    {
                        $crate::refine::params::count(&[$(stringify!($field)),*])
                            $(+ <$gty as $crate::refine::params::Group>::PARAMS.len())*
                    },
                >(&[
                    &[$($crate::refine::params::Param {
                        name: stringify!($field),
                        doc: concat!($($doc, "\n",)*),
                        check: $check,
                        shown_default: || {
                            $crate::refine::params::Value::shown(
                                &<$name as Default>::default().$field,
                            )
                        },
                    },)*],
                    $(<$gty as $crate::refine::params::Group>::PARAMS,)*
                ]);

            #[allow(unused_variables)]
            fn set_param(
                &mut self,
                name: &str,
                value: &str,
            ) -> Option<Result<(), $crate::refine::params::ParamError>> {
                $(
                    if name == stringify!($field) {
                        return Some(
                            $crate::refine::params::Value::parse(value, $check)
                                .map(|v| self.$field = v),
                        );
                    }
                )*
                $(
                    if let Some(r) =
                        $crate::refine::params::Group::set_param(&mut self.$group, name, value)
                    {
                        return Some(r);
                    }
                )*
                None
            }
        }
    };
}
pub(crate) use group;

/// An enumeration a parameter takes by name: the variants with their doc comments and
/// names (also their serialized form), [`Choice`]s, `name()` and `FromStr`.
macro_rules! named {
    (
        $(#[$meta:meta])*
        pub enum $name:ident {
            $(
                $(#[doc = $doc:expr])*
                $variant:ident = $text:literal,
            )*
        }
    ) => {
        $(#[$meta])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
        #[serde(rename_all = "lowercase")]
        pub enum $name {
            $(
                $(#[doc = $doc])*
                $variant,
            )*
        }

        impl $name {
            /// Every value's name and doc comment.
            pub const CHOICES: &'static [Choice] =
                &[$(Choice { name: $text, doc: concat!($($doc, "\n",)*) },)*];

            pub fn name(self) -> &'static str {
                match self {
                    $($name::$variant => $text,)*
                }
            }
        }

        impl FromStr for $name {
            type Err = ParamError;
            fn from_str(s: &str) -> Result<Self, ParamError> {
                one_of(s, &[$(($text, $name::$variant)),*])
            }
        }

        impl Value for $name {
            fn parse(text: &str, _: Check) -> Result<Self, ParamError> {
                text.parse()
            }
            fn shown(&self) -> Option<String> {
                Some(self.name().to_string())
            }
        }
    };
}

named! {
    /// `reference` reproduces the authors' published code (quirks included); `default`
    /// follows the paper's intent with every **\[fix\]** of docs/method.md#profiles on.
    pub enum Profile {
        Default = "default",
        Reference = "reference",
    }
}

// `named!` derives no `Default`: the default variant is named here.
#[allow(clippy::derivable_impls)]
impl Default for Profile {
    fn default() -> Self {
        Profile::Default
    }
}

named! {
    /// Where step 4 moves each line (`--fit`).
    pub enum Fit {
        /// The published step: the mean offset of the nearest `translate_keep` of the points.
        /// It follows the Gaussians: use it to reproduce the paper, or to represent the
        /// Gaussians themselves.
        Paper = "paper",
        /// Onto the edge the Gaussians describe (two faces' intersection where normals exist,
        /// else the dense ridge; no move where neither is clear), iterated to convergence.
        Edge = "edge",
        /// No move.
        None = "none",
    }
}

named! {
    /// Denominator of `R_L` (docs/method.md#evaluation).
    pub enum RlMode {
        /// `sum L / ln(sum N(s))`, the paper's equation.
        Paper = "paper",
        /// `sum L / ln(N_box)`, what the authors' code computes.
        Authors = "authors",
    }
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
    type Err = ParamError;
    fn from_str(s: &str) -> Result<Self, ParamError> {
        if s.eq_ignore_ascii_case("auto") {
            return Ok(RadiusArg::Auto);
        }
        match s.parse::<f64>() {
            Ok(r) if r.is_finite() && r > 0.0 => Ok(RadiusArg::Fixed(r)),
            _ => Err(ParamError::Radius(s.to_string())),
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
pub fn positive(s: &str) -> Result<f64, ParamError> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(ParamError::NotPositive(s.to_string())),
    }
}

/// Value parser: a finite number >= 0.
pub fn nonnegative(s: &str) -> Result<f64, ParamError> {
    match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(ParamError::Negative(s.to_string())),
    }
}

/// Value parser: `--crop-extend`, a number in [0, 10].
pub fn extend_factor(s: &str) -> Result<f64, ParamError> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=10.0).contains(&v) => Ok(v),
        _ => Err(ParamError::NotExtendFactor(s.to_string())),
    }
}

/// Value parser: `--outlier-ratio`, in [0, 1] or -1 (a ratio above 1 drops most
/// segments of any scene, one far above it all of them).
pub fn outlier_ratio(s: &str) -> Result<f64, ParamError> {
    match s.parse::<f64>() {
        Ok(v) if v == -1.0 || (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(ParamError::NotOutlierRatio(s.to_string())),
    }
}

/// Value parser: a number in [0, 1].
pub fn fraction(s: &str) -> Result<f64, ParamError> {
    match s.parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(ParamError::NotFraction(s.to_string())),
    }
}

group! {
    /// Evaluation options (docs/method.md#evaluation), shared by `eval` and `refine`.
    pub struct EvalParams {
        /// Evaluation radius r_e of the cylinders (scene units).
        eval_radius: f64 = 0.1, Check::Positive;
        /// Metres per scene unit, for E_rms in centimetres.
        unit_scale: f64 = 1.0, Check::Positive;
        /// lambda of the score (the paper uses 1 for real scenes).
        score_lambda: f64 = 0.1, Check::Positive;
        /// Denominator of R_L: `paper` (ln of summed N(s)) or `authors` (ln N_box).
        /// Default: the profile's (`paper` for default, `authors` for reference).
        r_l: Option<RlMode> = None, Check::Choice(RlMode::CHOICES);
    }
}

group! {
    /// The profile's fixes: each switches one rule of a step between the paper's intent
    /// (`default`) and the authors' code (`reference`); unset, the profile decides.
    pub struct FixParams {
        /// Fix: cluster distance is the true 3D segment-to-segment distance (reference:
        /// lateral offset ignored when the shorter does not project inside). Default: profile.
        fix_cluster_distance: Option<bool> = None, Check::Switch;
        /// Fix: a merge keeps the union of both extents along the kept line. Default: profile.
        fix_merge_extent: Option<bool> = None, Check::Switch;
        /// Fix: a pair goes to the merge (not the join) when an endpoint of either projects
        /// inside the other (reference: only the shorter's endpoints inside the longer, as
        /// the authors test it). Default: profile.
        fix_merge_overlap: Option<bool> = None, Check::Switch;
        /// Fix: join sorts endpoints by projection on the first direction (reference: by
        /// distance from its P1). Default: profile.
        fix_join_order: Option<bool> = None, Check::Switch;
        /// Fix: join's gap test needs 0.6 x mean density x chord points, at least 1
        /// (reference: floor(mean density x chord)). Default: profile.
        fix_join_gap: Option<bool> = None, Check::Switch;
        /// Fix: crop probes use the paper's density test (reference: side-count balance).
        /// Default: profile.
        fix_crop_density: Option<bool> = None, Check::Switch;
        /// Fix: crop cuts an end only where the sparse stretch is at least r long (a shorter
        /// one is where the Gaussians thin out at a corner, not an overextension). Default:
        /// profile.
        fix_crop_min_cut: Option<bool> = None, Check::Switch;
        /// Fix: crop searches an end only where its window is sparse beyond chance at the
        /// middle's density (Poisson, chance at most 0.01), so that a sparse model's few
        /// points do not cut true extent. Default: profile.
        fix_crop_chance: Option<bool> = None, Check::Switch;
        /// Fix: crop cuts an end only where the whole stretch it would cut is sparse (below
        /// crop-ratio x the middle density and, with fix-crop-chance, beyond chance), not
        /// only the probe where the search stopped: on a model whose density along an edge
        /// comes in clumps, the search can stop at any gap between two clumps. Default:
        /// profile.
        fix_crop_stretch: Option<bool> = None, Check::Switch;
        /// Fix: a merge or join keeps every input endpoint within r/2 (the most one edge-fit
        /// step moves a line) of the line it makes, so that chords of a curve are not merged
        /// or joined across it and nearby parallel edges are not averaged. Default: profile.
        fix_merge_fidelity: Option<bool> = None, Check::Switch;
        /// Order the endpoints of each segment so that |P1| <= |P2|, at load and for every
        /// segment a merge or join makes, as the authors' segment constructor does. Default:
        /// on for reference, off for default.
        order_endpoints: Option<bool> = None, Check::Switch;
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
    pub crop_stretch: bool,
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
    pub fn resolve(params: Params, working_set: &[[f32; 3]]) -> Result<Settings, ParamError> {
        let radius = match params.radius {
            RadiusArg::Fixed(r) => r,
            RadiusArg::Auto => auto_radius(working_set).ok_or(ParamError::NoCentersForAuto)?,
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

    /// The fixes in effect: each set one, else the profile's.
    pub fn fixes(&self) -> Fixes {
        let on = self.profile == Profile::Default;
        let f = &self.switches;
        Fixes {
            cluster_distance: f.fix_cluster_distance.unwrap_or(on),
            merge_extent: f.fix_merge_extent.unwrap_or(on),
            merge_overlap: f.fix_merge_overlap.unwrap_or(on),
            join_order: f.fix_join_order.unwrap_or(on),
            join_gap: f.fix_join_gap.unwrap_or(on),
            crop_density: f.fix_crop_density.unwrap_or(on),
            crop_min_cut: f.fix_crop_min_cut.unwrap_or(on),
            crop_chance: f.fix_crop_chance.unwrap_or(on),
            crop_stretch: f.fix_crop_stretch.unwrap_or(on),
            merge_fidelity: f.fix_merge_fidelity.unwrap_or(on),
            order_endpoints: f.order_endpoints.unwrap_or(!on),
            fit: self
                .fit
                .fit
                .unwrap_or(if on { Fit::Edge } else { Fit::Paper }),
            r_l: self
                .eval
                .r_l
                .unwrap_or(if on { RlMode::Paper } else { RlMode::Authors }),
        }
    }
}

impl Params {
    /// The name of every parameter [`Params::set`] takes, in the command line's order
    /// (there `--{name}` with `-` for `_`): those of [`Group::PARAMS`].
    pub const NAMES: &'static [&'static str] =
        &names::<{ <Params as Group>::PARAMS.len() }>(<Params as Group>::PARAMS);

    /// Sets the parameter `name` (one of [`Params::NAMES`]) from its text, with the
    /// command line's checks: `set("radius", "auto")`, `set("fit_gate", "false")`. An
    /// unknown name or a value out of range is an error that names both.
    pub fn set(&mut self, name: &str, value: &str) -> Result<(), ParamError> {
        match self.set_param(name, value) {
            None => Err(ParamError::Unknown(name.to_string())),
            Some(r) => r.map_err(|e| ParamError::Invalid {
                name: name.to_string(),
                value: value.to_string(),
                error: Box::new(e),
            }),
        }
    }
}

/// The names of `params`, as one array.
const fn names<const N: usize>(params: &[Param]) -> [&'static str; N] {
    let mut out = [""; N];
    let mut i = 0;
    while i < N {
        out[i] = params[i].name;
        i += 1;
    }
    out
}

/// A whole number in `[lo, hi]`.
fn in_range(s: &str, lo: u32, hi: u32) -> Result<u32, ParamError> {
    match s.parse::<u32>() {
        Ok(v) if (lo..=hi).contains(&v) => Ok(v),
        Ok(v) => Err(ParamError::OutOfRange { value: v, lo, hi }),
        Err(_) => Err(ParamError::NotWhole {
            text: s.to_string(),
            lo,
            hi,
        }),
    }
}

/// `true` or `false`.
fn boolean(s: &str) -> Result<bool, ParamError> {
    match s {
        "true" => Ok(true),
        "false" => Ok(false),
        _ => Err(ParamError::NotBool(s.to_string())),
    }
}

/// The names of an enumeration's values, for its parser's message.
fn one_of<T: Copy>(s: &str, values: &[(&str, T)]) -> Result<T, ParamError> {
    values
        .iter()
        .find(|(n, _)| *n == s)
        .map(|(_, v)| *v)
        .ok_or_else(|| {
            let names: Vec<String> = values.iter().map(|(n, _)| format!("`{n}`")).collect();
            ParamError::NotOneOf {
                expected: names.join(", "),
                text: s.to_string(),
            }
        })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_names_are_those_of_the_declarations_in_order() {
        let params: Vec<&str> = <Params as Group>::PARAMS.iter().map(|p| p.name).collect();
        assert_eq!(Params::NAMES, params);
        let mut unique = params.clone();
        unique.sort_unstable();
        unique.dedup();
        assert_eq!(unique.len(), params.len(), "a name declared twice");
    }

    #[test]
    fn the_report_lists_the_parameters_flat_in_the_order_of_names() {
        let json = serde_json::to_string(&Params::default()).unwrap();
        let at: Vec<usize> = Params::NAMES
            .iter()
            .map(|n| {
                json.find(&format!("\"{n}\":"))
                    .unwrap_or_else(|| panic!("{n}: {json}"))
            })
            .collect();
        assert!(at.windows(2).all(|w| w[0] < w[1]), "{json}");
        let back: Params = serde_json::from_str(&json).unwrap();
        assert_eq!(back, Params::default());
    }

    #[test]
    fn each_shown_default_reads_back_as_the_default_and_bad_text_is_refused() {
        for p in <Params as Group>::PARAMS {
            let mut q = Params::default();
            if let Some(text) = (p.shown_default)() {
                q.set(p.name, &text).unwrap();
                assert_eq!(q, Params::default(), "{}={text}", p.name);
            }
            let e = q.set(p.name, "x1").unwrap_err().to_string();
            assert!(
                e.starts_with(&format!("invalid value 'x1' for '{}': ", p.name)),
                "{e}"
            );
        }
    }

    #[test]
    fn the_messages_are_those_of_before() {
        let e = |n: &str, v: &str| Params::default().set(n, v).unwrap_err().to_string();
        assert_eq!(
            e("translate_keep", "1.5"),
            "invalid value '1.5' for 'translate_keep': expected a number in [0, 1], got `1.5`"
        );
        assert_eq!(
            e("crop_max_probes", "65"),
            "invalid value '65' for 'crop_max_probes': 65 is not in 1..=64"
        );
        assert_eq!(
            e("fit", "ridge"),
            "invalid value 'ridge' for 'fit': expected `paper`, `edge`, `none`, got `ridge`"
        );
        assert_eq!(
            e("radius", "-1"),
            "invalid value '-1' for 'radius': expected a positive number or `auto`, got `-1`"
        );
        assert_eq!(
            e("translate_kep", "0.5"),
            "unknown parameter `translate_kep`"
        );
        let mut p = Params::default();
        p.set("crop_extend", "2.5").unwrap();
        p.set("fix_join_gap", "false").unwrap();
        p.set("r_l", "authors").unwrap();
        assert_eq!(p.crop.crop_extend, 2.5);
        assert_eq!(p.switches.fix_join_gap, Some(false));
        assert_eq!(p.eval.r_l, Some(RlMode::Authors));
    }

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
        assert_eq!(
            Params::default().gaps.split_gaps_for(Profile::Default),
            0.01
        );
        assert_eq!(
            Params::reference().gaps.split_gaps_for(Profile::Reference),
            0.0
        );
        let mut one = Params::reference();
        one.switches.fix_join_gap = Some(true);
        let one = one.fixes();
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
