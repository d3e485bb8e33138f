//! The command line's mirror of the library's options: [`ParamsArgs`] (with
//! [`EvalParamsArgs`]) parses `--radius 0.05 --fit edge ...` and converts into
//! [`Params`]; the enumerations the commands take by name (`--profile`, `--fit`, `--r-l`,
//! `--backend`, `--protocol`, `--curves`) have a mirror here that derives `ValueEnum`.
//! Every default is the library's own (`Params::default()`), and a test checks that an
//! empty command line converts to exactly that for each profile.

use clap::{Args, ValueEnum};
use linegs_gpu::engine::select::Backend;
use linegs_gpu::eval::gt::Protocol;
use linegs_gpu::io::Curves;
use linegs_gpu::refine::params::{extend_factor, fraction, nonnegative, outlier_ratio, positive};
use linegs_gpu::refine::{EvalParams, Fit, Params, Profile, RadiusArg, RlMode};

/// A `ValueEnum` mirror of a library enumeration, converting both ways. The variants'
/// doc comments are the `--help` text of the values.
macro_rules! mirror {
    ($(#[$m:meta])* $name:ident => $lib:ident { $($(#[$vm:meta])* $v:ident,)* }) => {
        $(#[$m])*
        #[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
        pub enum $name {
            $($(#[$vm])* $v,)*
        }

        impl From<$name> for $lib {
            fn from(v: $name) -> $lib {
                match v {
                    $($name::$v => $lib::$v,)*
                }
            }
        }

        impl From<$lib> for $name {
            fn from(v: $lib) -> $name {
                match v {
                    $($lib::$v => $name::$v,)*
                }
            }
        }
    };
}

mirror! {
    /// [`Profile`].
    ProfileArg => Profile {
        Default,
        Reference,
    }
}

mirror! {
    /// [`Fit`] (`--fit`).
    FitArg => Fit {
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
}

mirror! {
    /// [`RlMode`] (`--r-l`).
    RlModeArg => RlMode {
        /// `sum L / ln(sum N(s))`, the paper's equation.
        Paper,
        /// `sum L / ln(N_box)`, what the authors' code computes.
        Authors,
    }
}

mirror! {
    /// [`Backend`] (`--backend`).
    BackendArg => Backend {
        /// A hardware GPU adapter when one exists, else the CPU engine (software adapters
        /// such as lavapipe run on the same cores, slower: only with `gpu`).
        Auto,
        /// A GPU adapter (software ones included), or an error.
        Gpu,
        /// The CPU engine (rayon).
        Cpu,
    }
}

mirror! {
    /// [`Protocol`] (`--protocol`).
    ProtocolArg => Protocol {
        /// Both sets sampled every 0.005 (both ends included), every sample scored, `<=`
        /// thresholds: continuous distances, no grid.
        Exact,
        /// EMAP's ABC-NEF evaluation, rule for rule (what the published tables report).
        Emap,
    }
}

mirror! {
    /// [`Curves`] (`--curves`).
    CurvesArg => Curves {
        /// Count them and leave them out, with a warning.
        Skip,
        /// Sample each into 16 straight segments (one group a curve).
        Polyline,
    }
}

/// Evaluation options (docs/method.md#evaluation), shared by `eval` and `refine`.
#[derive(Clone, Debug, PartialEq, Args)]
pub struct EvalParamsArgs {
    /// Evaluation radius r_e of the cylinders (scene units).
    #[arg(long, default_value_t = EvalParams::default().eval_radius, value_parser = positive)]
    pub eval_radius: f64,
    /// Metres per scene unit, for E_rms in centimetres.
    #[arg(long, default_value_t = EvalParams::default().unit_scale, value_parser = positive)]
    pub unit_scale: f64,
    /// lambda of the score (the paper uses 1 for real scenes).
    #[arg(long, default_value_t = EvalParams::default().score_lambda, value_parser = positive)]
    pub score_lambda: f64,
    /// Denominator of R_L: `paper` (ln of summed N(s)) or `authors` (ln N_box).
    /// Default: the profile's (`paper` for default, `authors` for reference).
    #[arg(long, value_enum)]
    pub r_l: Option<RlModeArg>,
}
/// The refinement thresholds of docs/method.md#the-refinement-steps (defaults from the
/// paper / the authors' code).
#[derive(Clone, Debug, PartialEq, Args)]
pub struct ParamsArgs {
    /// `default` (the paper's intent, all fixes on) or `reference` (the authors' code,
    /// quirks included).
    #[arg(long, value_enum, default_value_t = ProfileArg::from(Params::default().profile))]
    pub profile: ProfileArg,
    /// Cylinder radius r for refinement (scene units; the paper uses 0.03 for ABC-NEF and
    /// 0.05 for real scenes), or `auto`: 0.02 x the 95th-percentile distance of the working
    /// set's Gaussian centers from their centroid. Also the clustering distance scale r_c.
    #[arg(long, default_value_t = Params::default().radius)]
    pub radius: RadiusArg,

    /// Translate: fraction of the points nearest to the line whose mean offset moves it.
    #[arg(long, default_value_t = Params::default().translate_keep, value_parser = fraction)]
    pub translate_keep: f64,
    /// Step 4: `paper` (mean offset of the nearest translate-keep, the published step: to
    /// reproduce the paper, or to put the lines where the Gaussians are), `edge` (fit the
    /// edge: two faces' corner where the model has normals, else the dense ridge, iterated;
    /// to put the lines on the true edges) or `none`. Default: the profile's (`edge` for
    /// default, `paper` for reference).
    #[arg(long, value_enum)]
    pub fit: Option<FitArg>,
    /// Edge fit: most iterations (one engine batch each).
    #[arg(long, default_value_t = Params::default().fit_iterations)]
    pub fit_iterations: u32,
    /// Edge fit: largest turn of a line per iteration (degrees).
    #[arg(long, default_value_t = Params::default().fit_max_turn_deg, value_parser = positive)]
    pub fit_max_turn_deg: f64,
    /// Edge fit: largest total move of an endpoint, in units of r.
    #[arg(long, default_value_t = Params::default().fit_max_move, value_parser = positive)]
    pub fit_max_move: f64,
    /// Edge fit: final width of the ridge kernel, in units of r.
    #[arg(long, default_value_t = Params::default().fit_bandwidth, value_parser = positive)]
    pub fit_bandwidth: f64,
    /// Edge fit: fewest points under the kernel (or per face family) for a move; 1 or
    /// more.
    #[arg(long, default_value_t = Params::default().fit_min_points, value_parser = clap::value_parser!(u32).range(1..))]
    pub fit_min_points: u32,
    /// Edge fit: weight each Gaussian by its opacity (PLY `opacity`, after the sigmoid),
    /// so that faint floaters pull less; the fewest-points test still counts points. No
    /// effect where the model has no opacities or all are equal.
    #[arg(long, default_value_t = Params::default().fit_opacity_weight, action = clap::ArgAction::Set, value_name = "BOOL")]
    pub fit_opacity_weight: bool,
    /// Edge fit: keep a segment where it is unless its Gaussians explain the move (the
    /// move gate): a corner only when both faces are thin slabs of splats and the input
    /// line lies outside one of them; a ridge only when less than a third of it is face
    /// splats. Measured in one batch of members of the fitted lines. `false`: every
    /// fitted move stands.
    #[arg(long, default_value_t = Params::default().fit_gate, action = clap::ArgAction::Set, value_name = "BOOL")]
    pub fit_gate: bool,
    /// Leave out of the steps that place lines (the edge fit, its gate, the straightness
    /// test) every Gaussian whose largest standard deviation (`exp(max scale_i)`) exceeds
    /// this x r: a Gaussian wider than the cylinder cannot place a line within r. The
    /// steps that ask whether Gaussians are there (outliers, merges, crop, gaps) and the
    /// metrics see the whole model. Needs a 3DGS PLY with scales; 0: keep all.
    /// Default: the profile's (1 for default, 0 for reference).
    #[arg(long, value_parser = nonnegative)]
    pub max_scale: Option<f64>,
    /// Drop a segment whose Gaussians' ridge bends across it by more than this x r: it
    /// follows a curve, not a line. The ridge is found (the edge fit's mean shift) in each
    /// third of the cylinder; the bend is the sagitta of the arc through the three, 9/4 of
    /// the middle one's offset from the chord through the others. A third with too few
    /// points is not judged. Runs after crop; 0: off.
    #[arg(long, default_value_t = Params::default().max_sagitta, value_parser = nonnegative)]
    pub max_sagitta: f64,
    /// After crop, split a segment where a stretch of its cylinder holds no Gaussian
    /// (and cut an empty stretch off an end): a stretch at least r long is empty beyond
    /// chance when, at the segment's own density, the chance of so long an empty stretch
    /// among the segment's gaps (2 at the ends, N + 1 inside) is at most this. Pieces
    /// with fewer than fit-min-points points are dropped. 0: off. Default: the profile's
    /// (0.01 for default, 0 for reference).
    #[arg(long, value_parser = fraction)]
    pub split_gaps: Option<f64>,
    /// `--split-gaps` also splits a segment at an empty interior stretch (not only cuts an
    /// empty end). Off by default: trained models leave stretches of a true edge without
    /// Gaussians (textureless faces, thinning near edges), and the chance rule, which
    /// assumes evenly spread Gaussians, split true edges there.
    #[arg(long, default_value_t = Params::default().split_interior, action = clap::ArgAction::Set, value_name = "BOOL")]
    pub split_interior: bool,

    /// Outliers: drop segments with density <= ratio x mean density, a ratio in [0, 1];
    /// -1 uses max(mean - 2 std, 0). `default` profile: 0.1 (a trained model's density
    /// varies tenfold between its faces and its thin features); `reference`: 0.2.
    #[arg(long, value_parser = outlier_ratio, allow_hyphen_values = true)]
    pub outlier_ratio: Option<f64>,

    /// Run the collinear merge inside input lines (Line3D++ `.txt` groups).
    #[arg(long, default_value_t = Params::default().collinear_merge, action = clap::ArgAction::Set)]
    pub collinear_merge: bool,

    /// Cluster: minimum similarity w of an edge.
    #[arg(long, default_value_t = Params::default().cluster_min_weight, value_parser = fraction)]
    pub cluster_min_weight: f64,
    /// Cluster: initial per-root threshold c (thr = w + c / size after a join).
    #[arg(long, default_value_t = Params::default().cluster_c, value_parser = positive)]
    pub cluster_c: f64,
    /// Cluster: |cos| between directions above which the length weight is non-zero.
    #[arg(long, default_value_t = Params::default().cluster_min_cos, value_parser = fraction)]
    pub cluster_min_cos: f64,

    /// Merge: largest angle between the two directions (degrees).
    #[arg(long, default_value_t = Params::default().merge_angle_deg, value_parser = positive)]
    pub merge_angle_deg: f64,
    /// Merge: reject when both endpoints of the shorter are farther than this x L_long
    /// from the longer's line.
    #[arg(long, default_value_t = Params::default().merge_dist_frac, value_parser = positive)]
    pub merge_dist_frac: f64,
    /// Merge: reject when rho(G') < ratio x rho(G).
    #[arg(long, default_value_t = Params::default().merge_density_ratio, value_parser = positive)]
    pub merge_density_ratio: f64,

    /// Join: largest angle between the joined segment and each input (degrees).
    #[arg(long, default_value_t = Params::default().join_angle_deg, value_parser = positive)]
    pub join_angle_deg: f64,
    /// Join: reject gaps longer than this x either length.
    #[arg(long, default_value_t = Params::default().join_gap_frac, value_parser = positive)]
    pub join_gap_frac: f64,
    /// Join: the gap chord is shrunk by this fraction at each end before counting.
    #[arg(long, default_value_t = Params::default().join_chord_shrink, value_parser = fraction)]
    pub join_chord_shrink: f64,
    /// Join (fix): the gap must hold at least this x mean density x chord length points.
    #[arg(long, default_value_t = Params::default().join_gap_density, value_parser = positive)]
    pub join_gap_density: f64,
    /// Join: reject J when rho(J) < ratio x rho of either input.
    #[arg(long, default_value_t = Params::default().join_density_ratio, value_parser = positive)]
    pub join_density_ratio: f64,
    /// Join: reject J when E(J) > ratio x E of either input.
    #[arg(long, default_value_t = Params::default().join_rmse_ratio, value_parser = positive)]
    pub join_rmse_ratio: f64,

    /// Crop: length of each end window as a fraction of L.
    #[arg(long, default_value_t = Params::default().crop_end_frac, value_parser = fraction)]
    pub crop_end_frac: f64,
    /// Crop: length of the middle window as a fraction of L.
    #[arg(long, default_value_t = Params::default().crop_mid_frac, value_parser = fraction)]
    pub crop_mid_frac: f64,
    /// Crop: an end (or probe) is sparse below this x the middle density.
    #[arg(long, default_value_t = Params::default().crop_ratio, value_parser = fraction)]
    pub crop_ratio: f64,
    /// Crop: half length of a binary-search probe window, as a fraction of L. Default:
    /// 0.1 with the authors' side-balance test (their `m ± 0.1 L`), 0.03 with the density
    /// test, whose window centred on the true end holds half the middle density whatever
    /// its size; a short window keeps the Gaussians of edges meeting at a corner from
    /// holding the end out past the corner.
    #[arg(long, value_parser = positive)]
    pub crop_probe_half: Option<f64>,
    /// Crop: also extend an end whose window is dense, along the line, while windows past
    /// it stay dense, by at most this x L (0: never extend, the paper's crop). Windows of
    /// 2 x the probe half length march outward, one batch per step, and the last is
    /// bisected; a corner stops the march, since past it the cylinder holds only the
    /// other edge's cross-section. 0 to 10; at most 256 windows an end.
    #[arg(long, default_value_t = Params::default().crop_extend, value_parser = extend_factor)]
    pub crop_extend: f64,
    /// Crop: most probes of the binary search, 1 to 64 (after 53 halvings an f64
    /// interval cannot shrink further, so more would only spin).
    #[arg(long, default_value_t = Params::default().crop_max_probes, value_parser = clap::value_parser!(u32).range(1..=64))]
    pub crop_max_probes: u32,
    /// Crop: the binary search stops when its interval is shorter than this (a positive
    /// number; the probe limit bounds the search whatever its value).
    #[arg(long, default_value_t = Params::default().crop_min_interval, value_parser = positive)]
    pub crop_min_interval: f64,

    /// Fix: cluster distance is the true 3D segment-to-segment distance (reference:
    /// lateral offset ignored when the shorter does not project inside). Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_cluster_distance: Option<bool>,
    /// Fix: a merge keeps the union of both extents along the kept line. Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_merge_extent: Option<bool>,
    /// Fix: a pair goes to the merge (not the join) when an endpoint of either projects
    /// inside the other (reference: only the shorter's endpoints inside the longer, as
    /// the authors test it). Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_merge_overlap: Option<bool>,
    /// Fix: join sorts endpoints by projection on the first direction (reference: by
    /// distance from its P1). Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_join_order: Option<bool>,
    /// Fix: join's gap test needs 0.6 x mean density x chord points, at least 1
    /// (reference: floor(mean density x chord)). Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_join_gap: Option<bool>,
    /// Fix: crop probes use the paper's density test (reference: side-count balance).
    /// Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_crop_density: Option<bool>,
    /// Fix: crop cuts an end only where the sparse stretch is at least r long (a shorter
    /// one is where the Gaussians thin out at a corner, not an overextension). Default:
    /// profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_crop_min_cut: Option<bool>,
    /// Fix: crop searches an end only where its window is sparse beyond chance at the
    /// middle's density (Poisson, chance at most 0.01), so that a sparse model's few
    /// points do not cut true extent. Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_crop_chance: Option<bool>,
    /// Fix: a merge or join keeps every input endpoint within r/2 (the most one edge-fit
    /// step moves a line) of the line it makes, so that chords of a curve are not merged
    /// or joined across it and nearby parallel edges are not averaged. Default: profile.
    #[arg(long, value_name = "BOOL")]
    pub fix_merge_fidelity: Option<bool>,
    /// Order the endpoints of each segment so that |P1| <= |P2|, at load and for every
    /// segment a merge or join makes, as the authors' segment constructor does. Default:
    /// on for reference, off for default.
    #[arg(long, value_name = "BOOL")]
    pub order_endpoints: Option<bool>,

    #[command(flatten)]
    pub eval: EvalParamsArgs,
}

impl From<EvalParamsArgs> for EvalParams {
    fn from(a: EvalParamsArgs) -> EvalParams {
        EvalParams {
            eval_radius: a.eval_radius,
            unit_scale: a.unit_scale,
            score_lambda: a.score_lambda,
            r_l: a.r_l.map(Into::into),
        }
    }
}

impl From<ParamsArgs> for Params {
    fn from(a: ParamsArgs) -> Params {
        Params {
            profile: a.profile.into(),
            radius: a.radius,
            translate_keep: a.translate_keep,
            fit: a.fit.map(Into::into),
            fit_iterations: a.fit_iterations,
            fit_max_turn_deg: a.fit_max_turn_deg,
            fit_max_move: a.fit_max_move,
            fit_bandwidth: a.fit_bandwidth,
            fit_min_points: a.fit_min_points,
            fit_opacity_weight: a.fit_opacity_weight,
            fit_gate: a.fit_gate,
            max_scale: a.max_scale,
            max_sagitta: a.max_sagitta,
            split_gaps: a.split_gaps,
            split_interior: a.split_interior,
            outlier_ratio: a.outlier_ratio,
            collinear_merge: a.collinear_merge,
            cluster_min_weight: a.cluster_min_weight,
            cluster_c: a.cluster_c,
            cluster_min_cos: a.cluster_min_cos,
            merge_angle_deg: a.merge_angle_deg,
            merge_dist_frac: a.merge_dist_frac,
            merge_density_ratio: a.merge_density_ratio,
            join_angle_deg: a.join_angle_deg,
            join_gap_frac: a.join_gap_frac,
            join_chord_shrink: a.join_chord_shrink,
            join_gap_density: a.join_gap_density,
            join_density_ratio: a.join_density_ratio,
            join_rmse_ratio: a.join_rmse_ratio,
            crop_end_frac: a.crop_end_frac,
            crop_mid_frac: a.crop_mid_frac,
            crop_ratio: a.crop_ratio,
            crop_probe_half: a.crop_probe_half,
            crop_extend: a.crop_extend,
            crop_max_probes: a.crop_max_probes,
            crop_min_interval: a.crop_min_interval,
            fix_cluster_distance: a.fix_cluster_distance,
            fix_merge_extent: a.fix_merge_extent,
            fix_merge_overlap: a.fix_merge_overlap,
            fix_join_order: a.fix_join_order,
            fix_join_gap: a.fix_join_gap,
            fix_crop_density: a.fix_crop_density,
            fix_crop_min_cut: a.fix_crop_min_cut,
            fix_crop_chance: a.fix_crop_chance,
            fix_merge_fidelity: a.fix_merge_fidelity,
            order_endpoints: a.order_endpoints,
            eval: a.eval.into(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::{CommandFactory, FromArgMatches, Parser};

    #[derive(Parser)]
    #[command(no_binary_name = true)]
    struct Cli {
        #[command(flatten)]
        params: ParamsArgs,
    }

    fn parse(args: &[&str]) -> Params {
        let m = Cli::command()
            .try_get_matches_from(args)
            .expect("valid arguments");
        Cli::from_arg_matches(&m).expect("matches").params.into()
    }

    #[test]
    fn the_mirror_defaults_are_the_library_defaults() {
        assert_eq!(parse(&[]), Params::default());
        assert_eq!(parse(&["--profile", "reference"]), Params::reference());
        assert_eq!(parse(&["--profile", "default"]), Params::default());
    }

    #[test]
    fn every_option_is_a_library_parameter_in_the_same_order() {
        let longs: Vec<String> = Cli::command()
            .get_arguments()
            .filter_map(|a| a.get_long().map(|l| l.replace('-', "_")))
            .collect();
        assert_eq!(longs, Params::NAMES);
    }

    #[test]
    fn each_option_converts_to_what_params_set_makes() {
        // One value per parameter, none of them its default.
        let values = [
            ("profile", "reference"),
            ("radius", "auto"),
            ("translate_keep", "0.25"),
            ("fit", "none"),
            ("fit_iterations", "3"),
            ("fit_max_turn_deg", "4.5"),
            ("fit_max_move", "1.5"),
            ("fit_bandwidth", "0.5"),
            ("fit_min_points", "2"),
            ("fit_opacity_weight", "true"),
            ("fit_gate", "false"),
            ("max_scale", "2"),
            ("max_sagitta", "0.5"),
            ("split_gaps", "0.05"),
            ("split_interior", "true"),
            ("outlier_ratio", "-1"),
            ("collinear_merge", "false"),
            ("cluster_min_weight", "0.3"),
            ("cluster_c", "2.5"),
            ("cluster_min_cos", "0.7"),
            ("merge_angle_deg", "20"),
            ("merge_dist_frac", "0.3"),
            ("merge_density_ratio", "0.7"),
            ("join_angle_deg", "5"),
            ("join_gap_frac", "0.9"),
            ("join_chord_shrink", "0.05"),
            ("join_gap_density", "0.4"),
            ("join_density_ratio", "0.5"),
            ("join_rmse_ratio", "1.2"),
            ("crop_end_frac", "0.05"),
            ("crop_mid_frac", "0.5"),
            ("crop_ratio", "0.4"),
            ("crop_probe_half", "0.07"),
            ("crop_extend", "1.5"),
            ("crop_max_probes", "20"),
            ("crop_min_interval", "0.001"),
            ("fix_cluster_distance", "false"),
            ("fix_merge_extent", "false"),
            ("fix_merge_overlap", "false"),
            ("fix_join_order", "false"),
            ("fix_join_gap", "false"),
            ("fix_crop_density", "false"),
            ("fix_crop_min_cut", "false"),
            ("fix_crop_chance", "false"),
            ("fix_merge_fidelity", "false"),
            ("order_endpoints", "true"),
            ("eval_radius", "0.2"),
            ("unit_scale", "0.01"),
            ("score_lambda", "1"),
            ("r_l", "authors"),
        ];
        let names: Vec<&str> = values.iter().map(|(n, _)| *n).collect();
        assert_eq!(names, Params::NAMES);
        let mut args = Vec::new();
        let mut set = Params::default();
        for (name, value) in values {
            args.push(format!("--{}={value}", name.replace('_', "-")));
            let before = set.clone();
            set.set(name, value).unwrap();
            assert_ne!(set, before, "{name}={value} changed nothing");
        }
        let args: Vec<&str> = args.iter().map(String::as_str).collect();
        assert_eq!(parse(&args), set);
    }

    #[test]
    fn out_of_range_values_are_refused_alike() {
        for (name, value) in [
            ("translate_keep", "1.5"),
            ("fit_min_points", "0"),
            ("crop_max_probes", "65"),
            ("crop_extend", "11"),
            ("outlier_ratio", "-0.5"),
            ("radius", "-1"),
            ("fit", "ridge"),
            ("fit_gate", "maybe"),
            ("eval_radius", "0"),
        ] {
            let arg = format!("--{}={value}", name.replace('_', "-"));
            assert!(
                Cli::command().try_get_matches_from([arg.as_str()]).is_err(),
                "{arg}"
            );
            let e = Params::default().set(name, value).unwrap_err();
            assert!(e.contains(name) && e.contains(value), "{e}");
        }
        assert!(Params::default().set("translate_kep", "0.5").is_err());
    }
}
