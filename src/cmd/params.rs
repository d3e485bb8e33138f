//! The command line's options of the library's parameters: [`ParamsArgs`] (with
//! [`EvalParamsArgs`]) parses `--radius 0.05 --fit edge ...` into [`Params`], its options
//! made from the parameters the steps declare ([`Group::PARAMS`]: name, doc, default,
//! check), so a step's new parameter is an option without an edit here. The other
//! enumerations the commands take by name (`--profile` of `eval` and `bench`,
//! `--backend`, `--protocol`, `--curves`) have a mirror here that derives `ValueEnum`.

use clap::builder::{BoolValueParser, PossibleValue, PossibleValuesParser, TypedValueParser};
use clap::error::ErrorKind;
use clap::parser::ValueSource;
use clap::{value_parser, Arg, ArgAction, ArgMatches, Args, Command, FromArgMatches, ValueEnum};
use linegs_gpu::engine::select::Backend;
use linegs_gpu::eval::gt::Protocol;
use linegs_gpu::io::Curves;
use linegs_gpu::refine::params::{Check, Choice, Group, Param, ParamError, Value};
use linegs_gpu::refine::{EvalParams, Params, RadiusArg};
use std::collections::HashMap;
use std::sync::{Mutex, OnceLock};

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

/// A library [`Group`] of parameters as command-line options: `--{name}` (with `-` for
/// `_`) for each of its [`Group::PARAMS`], help, default, value name and check taken from
/// the parameter, and the values given turned into the group by [`Group::set_param`].
/// [`ParamsArgs`] is `refine`'s and `batch`'s, [`EvalParamsArgs`] `eval`'s.
#[derive(Clone, Debug, PartialEq)]
pub struct Options<G>(pub G);

/// The refinement parameters ([`Params`]) as options.
pub type ParamsArgs = Options<Params>;
/// The evaluation options ([`EvalParams`]) as options.
pub type EvalParamsArgs = Options<EvalParams>;

impl From<ParamsArgs> for Params {
    fn from(a: ParamsArgs) -> Params {
        a.0
    }
}

impl From<EvalParamsArgs> for EvalParams {
    fn from(a: EvalParamsArgs) -> EvalParams {
        a.0
    }
}

/// A doc comment as clap's derive makes it a help line: the lines trimmed and joined,
/// without a final period.
fn help_of(doc: &str) -> String {
    let mut s = doc
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(" ");
    if s.ends_with('.') && !s.ends_with("..") {
        s.pop();
    }
    s
}

/// The texts of a parameter's option that clap keeps for the process (`--{long}`, its
/// value's name, its default), made once.
fn texts(p: &'static Param) -> (&'static str, &'static str, Option<&'static str>) {
    type Texts = (&'static str, &'static str, Option<&'static str>);
    static MADE: OnceLock<Mutex<HashMap<&'static str, Texts>>> = OnceLock::new();
    let leak = |s: String| -> &'static str { Box::leak(s.into_boxed_str()) };
    *MADE
        .get_or_init(Default::default)
        .lock()
        .unwrap_or_else(|e| e.into_inner())
        .entry(p.name)
        .or_insert_with(|| {
            (
                leak(p.name.replace('_', "-")),
                leak(p.name.to_uppercase()),
                (p.shown_default)().map(leak),
            )
        })
}

/// The text of a value its check accepts (the check's message otherwise).
fn text_of<T: Value>(s: &str, check: Check) -> Result<String, ParamError> {
    T::parse(s, check).map(|_| s.to_string())
}

/// The parser of a value taken by name from `choices` (the name as text), each with its
/// doc comment as help: for the parameters, and for the options of the commands that
/// take one such value beside them (`eval --profile`).
pub fn choices(choices: &'static [Choice]) -> PossibleValuesParser {
    PossibleValuesParser::new(choices.iter().map(|c| {
        let help = help_of(c.doc);
        let v = PossibleValue::new(c.name);
        if help.is_empty() {
            v
        } else {
            v.help(help)
        }
    }))
}

/// A name [`choices`] accepted, as its enumeration.
pub fn chosen<T: std::str::FromStr>(name: &str) -> T {
    name.parse()
        .unwrap_or_else(|_| unreachable!("`{name}` is one of the names the parser accepts"))
}

/// The option of one parameter, as clap's derive made it from a field.
fn arg_of(p: &'static Param) -> Arg {
    let (long, value_name, default) = texts(p);
    let mut arg = Arg::new(p.name)
        .long(long)
        .help(help_of(p.doc))
        .action(ArgAction::Set)
        .value_name(value_name);
    if let Some(d) = default {
        arg = arg.default_value(d);
    }
    let bool_text = || BoolValueParser::new().map(|v| v.to_string());
    match p.check {
        Check::Whole { lo, hi } => {
            let whole = value_parser!(u32);
            let whole = if lo == 0 && hi == u32::MAX {
                whole
            } else if hi == u32::MAX {
                whole.range(i64::from(lo)..)
            } else {
                whole.range(i64::from(lo)..=i64::from(hi))
            };
            arg.value_parser(whole.map(|v| v.to_string()))
        }
        Check::Bool => arg.value_parser(bool_text()),
        Check::Switch => arg.value_name("BOOL").value_parser(bool_text()),
        Check::Choice(c) => arg.value_parser(choices(c)),
        Check::Radius => arg.value_parser(move |s: &str| text_of::<RadiusArg>(s, p.check)),
        Check::OutlierRatio => arg
            .allow_hyphen_values(true)
            .value_parser(move |s: &str| text_of::<f64>(s, p.check)),
        Check::Positive | Check::NonNegative | Check::Fraction | Check::ExtendFactor => {
            arg.value_parser(move |s: &str| text_of::<f64>(s, p.check))
        }
    }
}

impl<G: Group + Clone + Send + Sync + 'static> Args for Options<G> {
    fn augment_args(cmd: Command) -> Command {
        G::PARAMS.iter().fold(cmd, |cmd, p| cmd.arg(arg_of(p)))
    }

    fn augment_args_for_update(cmd: Command) -> Command {
        Self::augment_args(cmd)
    }
}

impl<G: Group> FromArgMatches for Options<G> {
    fn from_arg_matches(m: &ArgMatches) -> Result<Self, clap::Error> {
        let mut o = Options(G::default());
        o.update_from_arg_matches(m)?;
        Ok(o)
    }

    fn update_from_arg_matches(&mut self, m: &ArgMatches) -> Result<(), clap::Error> {
        for p in G::PARAMS {
            if m.value_source(p.name) != Some(ValueSource::CommandLine) {
                continue;
            }
            let Some(text) = m.get_one::<String>(p.name) else {
                continue;
            };
            match self.0.set_param(p.name, text) {
                Some(Ok(())) => {}
                Some(Err(e)) => return Err(clap::Error::raw(ErrorKind::ValueValidation, e)),
                None => unreachable!("{} is a parameter of the group", p.name),
            }
        }
        Ok(())
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
        // One value per parameter, none of them its default: the first of a few its
        // check accepts that changes the parameters.
        let values: Vec<(&str, String)> = <Params as Group>::PARAMS
            .iter()
            .map(|p| {
                let candidates: Vec<String> = match p.check {
                    Check::Whole { lo, .. } => vec![(lo + 1).to_string(), (lo + 2).to_string()],
                    Check::Bool | Check::Switch => vec!["true".into(), "false".into()],
                    Check::Radius => vec!["auto".into()],
                    Check::Choice(c) => c.iter().map(|c| c.name.to_string()).collect(),
                    Check::OutlierRatio => vec!["-1".into()],
                    _ => vec!["0.25".into(), "0.5".into()],
                };
                let value = candidates
                    .into_iter()
                    .find(|v| {
                        let mut q = Params::default();
                        q.set(p.name, v).is_ok() && q != Params::default()
                    })
                    .unwrap_or_else(|| panic!("no value changes {}", p.name));
                (p.name, value)
            })
            .collect();
        let names: Vec<&str> = values.iter().map(|(n, _)| *n).collect();
        assert_eq!(names, Params::NAMES);
        let mut args = Vec::new();
        let mut set = Params::default();
        for (name, value) in &values {
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
            let e = e.to_string();
            assert!(e.contains(name) && e.contains(value), "{e}");
        }
        assert!(Params::default().set("translate_kep", "0.5").is_err());
    }
}
