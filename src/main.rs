//! The `linegs-gpu` command line: argument parsing and printing only; the work is in the
//! library.

// The print macros of every command, defined before the modules that use them so that they
// shadow std's: std's panic when the standard output cannot be written; these end the
// process from the write error itself (`stdio`).
macro_rules! println {
    () => {
        $crate::stdio::write(false, format_args!("\n"))
    };
    ($($t:tt)*) => {
        $crate::stdio::write(false, format_args!("{}\n", format_args!($($t)*)))
    };
}
macro_rules! print {
    ($($t:tt)*) => {
        $crate::stdio::write(false, format_args!($($t)*))
    };
}
macro_rules! eprintln {
    () => {
        $crate::stdio::write(true, format_args!("\n"))
    };
    ($($t:tt)*) => {
        $crate::stdio::write(true, format_args!("{}\n", format_args!($($t)*)))
    };
}

pub(crate) mod cmd;
pub(crate) mod oom;

/// Writing to the standard output and error, with the exit of a process that cannot: a
/// closed pipe (`linegs-gpu info m.ply | head -1`, `io::ErrorKind::BrokenPipe`) ends it
/// quietly with 141, as a Unix tool killed by SIGPIPE; any other failure (a full disk
/// behind `> file`, `> /dev/full`) with one line and 1. Every file a command writes is
/// complete before it prints about it, so the files stay valid either way.
pub(crate) mod stdio {
    use std::io::Write;

    pub fn write(to_stderr: bool, args: std::fmt::Arguments) {
        let r = if to_stderr {
            std::io::stderr().lock().write_fmt(args)
        } else {
            std::io::stdout().lock().write_fmt(args)
        };
        if let Err(e) = r {
            failed(to_stderr, &e);
        }
    }

    #[cold]
    fn failed(to_stderr: bool, e: &std::io::Error) -> ! {
        if e.kind() == std::io::ErrorKind::BrokenPipe {
            std::process::exit(141);
        }
        if !to_stderr {
            let _ = writeln!(
                std::io::stderr(),
                "error: cannot write to the standard output: {e}"
            );
        }
        std::process::exit(1);
    }
}

use clap::{Parser, Subcommand};
use std::process::ExitCode;

/// Turn noisy 3D line segments (Line3D++, ELSR, LIMAP) into a clean, compact line model
/// using the Gaussian centers of a trained 3D Gaussian Splatting model (the LineGS method),
/// with every cylinder query answered in batches by WGSL compute kernels or by the CPU.
#[derive(Parser, Debug)]
#[command(name = "linegs-gpu", version, about, long_about = None)]
#[command(after_help = "Examples:
  linegs-gpu demo
  linegs-gpu refine --gaussians point_cloud.ply --lines Line3D++.txt -o refined.obj --report report.json
  linegs-gpu eval --gaussians point_cloud.ply --lines refined.obj --radii 0.02,0.05,0.1,0.2 --plot sweep.png
  linegs-gpu info point_cloud.ply
  linegs-gpu convert model.spz -o model.ply
  linegs-gpu batch scenes.csv -o results --skip-existing

Exit codes: 0 success, 1 failure (GPU, I/O), 2 bad input or usage.")]
struct Cli {
    /// Print more (the adapter, per-stage timings, warnings in full).
    #[arg(short, long, global = true)]
    verbose: bool,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Refine line segments against the Gaussian centers and report before/after metrics.
    Refine(Box<cmd::refine::RefineArgs>),
    /// Measure line segments against the Gaussian centers (the paper's metrics).
    Eval(Box<cmd::eval::EvalArgs>),
    /// Describe a Gaussian model or line file: format, counts, bounding box, properties.
    Info(cmd::info::InfoArgs),
    /// Convert a Gaussian model to a standard PLY, or lines to another line format.
    Convert(cmd::convert::ConvertArgs),
    /// Build the synthetic toy scene, refine it, and write inputs, outputs, report,
    /// pictures and a 3D viewer to a folder.
    Demo(cmd::demo::DemoArgs),
    /// Make synthetic Gaussians (and lines): the toy scene, a mesh, or around segments.
    Synth(cmd::synth::SynthArgs),
    /// Draw Gaussian centers and one or two segment sets to a PNG (and an HTML viewer).
    Render(cmd::render::RenderArgs),
    /// Refine every scene of a manifest (CSV) into its own folder, a shard per process
    /// (Slurm array), and summarize them in the columns of the paper's Table I.
    Batch(Box<cmd::batch::BatchArgs>),
    /// Time whole runs on synthetic scenes of given sizes, per stage, CPU and GPU.
    Bench(cmd::bench::BenchArgs),
}

/// Mesa's Vulkan drivers (lavapipe included) probe for a Wayland display while the loader
/// starts them, and libwayland prints `error: XDG_RUNTIME_DIR is invalid or not set in the
/// environment.` when the variable is missing (containers, ssh logins, CI) — on runs that
/// then succeed, so a new user's first sight is an "error". When it is unset or names no
/// folder, we point it at a private folder of our own (created 0700, as the XDG base
/// directory spec requires, and removed at exit): the probe then finds no display and
/// says nothing, and no real error is hidden. Done at the start of `main`, before any
/// thread exists, since changing the environment races with threads that read it.
/// The folder is locked while the process lives, and the folders of killed runs are
/// removed (`io::clean_stale_runtime_dirs_in`). It is made in the temporary folder
/// (`TMPDIR`), or where that is missing or read-only in `/dev/shm`, `/tmp` or `/var/tmp`.
fn private_runtime_dir() -> Option<(tempfile::TempDir, Option<std::fs::File>)> {
    let current = std::env::var_os("XDG_RUNTIME_DIR");
    if current.is_some_and(|d| std::path::Path::new(&d).is_dir()) {
        return None;
    }
    let mut bases = vec![std::env::temp_dir()];
    if cfg!(unix) {
        for b in ["/dev/shm", "/tmp", "/var/tmp"] {
            if !bases.iter().any(|p| p == std::path::Path::new(b)) {
                bases.push(b.into());
            }
        }
    }
    let dir = bases.iter().find_map(|base| {
        linegs_gpu::io::clean_stale_runtime_dirs_in(base);
        tempfile::Builder::new()
            .prefix(linegs_gpu::io::RUNTIME_PREFIX)
            .tempdir_in(base)
            .ok()
    })?;
    let lock = std::fs::File::open(dir.path()).ok();
    if let Some(f) = &lock {
        let _ = linegs_gpu::io::try_lock(f);
    }
    std::env::set_var("XDG_RUNTIME_DIR", dir.path());
    Some((dir, lock))
}

/// Starts the worker threads (rayon's global pool) before any work, so that a process
/// that cannot start them (a memory limit, `ulimit -v`, or a limit on processes) ends with
/// one line and exit 1 instead of rayon's panic at the first parallel loop.
fn start_threads() -> Result<(), String> {
    // rayon's own default: RAYON_NUM_THREADS, else one a core.
    let n = std::env::var("RAYON_NUM_THREADS")
        .ok()
        .and_then(|v| v.trim().parse::<usize>().ok())
        .filter(|&n| n > 0)
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()));
    oom::doing(
        format!("starting {n} worker threads"),
        "free memory, raise the limit (ulimit -v) or start fewer threads (RAYON_NUM_THREADS=1)",
    );
    rayon::ThreadPoolBuilder::new().build_global().map_err(|e| {
        format!(
            "cannot start {n} worker threads ({e}); free memory, raise the limit (ulimit -v \
             or ulimit -u) or start fewer threads (RAYON_NUM_THREADS=1)"
        )
    })
}

/// `RUST_LOG` (`info`, `debug`, `wgpu_hal=debug,info`: env_logger's syntax) to standard
/// error: the adapter search (`linegs_gpu::engine`; `debug` lists every adapter found) and
/// what wgpu, naga and the Vulkan loader report through `log`, which is lost without a
/// logger. Unset, nothing is logged. (A second call in one process, from Python, keeps the
/// first logger.)
fn init_logger() {
    let _ = env_logger::Builder::from_env(env_logger::Env::default().default_filter_or("off"))
        .try_init();
}

#[global_allocator]
static ALLOCATOR: oom::Checked = oom::Checked;

fn main() -> ExitCode {
    ExitCode::from(run(std::env::args_os()))
}

/// The command line on `args` (the program's name first); returns the exit code. `main`,
/// and the `linegs-gpu` that `pip install .` installs (python/src/lib.rs includes this
/// file and calls it with `sys.argv`).
pub fn run(args: impl IntoIterator<Item = std::ffi::OsString>) -> u8 {
    // Before the first large block.
    linegs_gpu::mem::huge_heap();
    init_logger();
    // After parsing: clap exits the process on `--help` and usage errors, which would
    // leave the folder behind.
    let cli = Cli::parse_from(args);
    oom::command(command_name(&cli.command));
    // The library reads no environment: the pair bound of steps 6 and 8 comes from here.
    linegs_gpu::refine::mergejoin::set_max_pairs_per_segment(
        std::env::var("LINEGS_MAX_PAIRS_PER_SEGMENT").ok(),
    );
    // And the bound on the members a batch of lists holds.
    linegs_gpu::engine::bound::set_max_listed_members(
        std::env::var("LINEGS_MAX_LISTED_MEMBERS").ok(),
    );
    if let Err(e) = start_threads() {
        eprintln!("error: {e}");
        return 1;
    }
    let _runtime_dir = private_runtime_dir();
    let verbose = cli.verbose;
    // The commands that run an engine refuse bad `LINEGS_GPU_*` values before any work.
    let engine = matches!(
        cli.command,
        Command::Refine(_)
            | Command::Eval(_)
            | Command::Demo(_)
            | Command::Bench(_)
            | Command::Batch(_)
    );
    let result = if let Some(Err(e)) = engine.then(cmd::env::gpu_setup) {
        Err(e)
    } else {
        match cli.command {
            Command::Refine(a) => cmd::refine::run(*a, verbose),
            Command::Eval(a) => cmd::eval::run(*a, verbose),
            Command::Info(a) => cmd::info::run(a),
            Command::Convert(a) => cmd::convert::run(a),
            Command::Demo(a) => cmd::demo::run(a, verbose),
            Command::Synth(a) => cmd::synth::run(a),
            Command::Render(a) => cmd::render::run(a),
            Command::Bench(a) => cmd::bench::run(a, verbose),
            Command::Batch(a) => cmd::batch::run(*a, verbose),
        }
    };
    match result {
        Ok(()) => 0,
        Err(e) => {
            eprintln!("error: {e:#}");
            cmd::exit_code(&e)
        }
    }
}

/// The subcommand's name, for messages.
fn command_name(c: &Command) -> &'static str {
    match c {
        Command::Refine(_) => "refine",
        Command::Eval(_) => "eval",
        Command::Info(_) => "info",
        Command::Convert(_) => "convert",
        Command::Demo(_) => "demo",
        Command::Synth(_) => "synth",
        Command::Render(_) => "render",
        Command::Batch(_) => "batch",
        Command::Bench(_) => "bench",
    }
}

#[cfg(test)]
mod tests {
    use super::Cli;
    use clap::CommandFactory;
    use std::collections::HashMap;

    /// Every subcommand below `cmd`, with its path (`synth toy`).
    fn walk(cmd: &clap::Command, path: String, out: &mut Vec<(String, clap::Command)>) {
        for sub in cmd.get_subcommands() {
            let p = format!("{path} {}", sub.get_name()).trim().to_string();
            out.push((p.clone(), sub.clone()));
            walk(sub, p, out);
        }
    }

    fn commands() -> Vec<(String, clap::Command)> {
        let mut cmd = Cli::command();
        cmd.build();
        let mut out = vec![("linegs-gpu".to_string(), cmd.clone())];
        walk(&cmd, String::new(), &mut out);
        out
    }

    #[test]
    fn the_command_line_is_well_formed() {
        Cli::command().debug_assert();
    }

    #[test]
    fn every_option_of_every_command_has_help() {
        let mut missing = Vec::new();
        for (path, cmd) in commands() {
            for arg in cmd.get_arguments() {
                let id = arg.get_id().as_str();
                if matches!(id, "help" | "version") {
                    continue;
                }
                if arg.get_help().is_none() && arg.get_long_help().is_none() {
                    missing.push(format!("{path}: --{}", arg.get_long().unwrap_or(id)));
                }
            }
        }
        assert!(missing.is_empty(), "options without help: {missing:?}");
    }

    /// A flag name means one thing everywhere: `--gaussians` is always a file, a count is
    /// `--num-gaussians`; the same long name has the same short name and value type.
    #[test]
    fn one_meaning_per_flag_name() {
        type Seen = (String, Option<char>, clap::builder::ValueParser);
        let mut seen: HashMap<String, Seen> = HashMap::new();
        let mut clashes = Vec::new();
        for (path, cmd) in commands() {
            for arg in cmd.get_arguments() {
                let Some(long) = arg.get_long() else { continue };
                let this = (
                    path.clone(),
                    arg.get_short(),
                    arg.get_value_parser().clone(),
                );
                match seen.get(long) {
                    Some(first) if first.1 != this.1 || first.2.type_id() != this.2.type_id() => {
                        clashes.push(format!(
                            "--{long}: {} {:?} {:?} vs {} {:?} {:?}",
                            first.0,
                            first.1,
                            first.2.type_id(),
                            this.0,
                            this.1,
                            this.2.type_id()
                        ))
                    }
                    Some(_) => {}
                    None => {
                        seen.insert(long.to_string(), this);
                    }
                }
            }
        }
        assert!(clashes.is_empty(), "{clashes:#?}");
        // The counts are not the files.
        assert!(seen.contains_key("num-gaussians") && seen.contains_key("gaussians"));
    }

    /// The README and the documentation pages that quote commands.
    const DOCS: [&str; 6] = [
        include_str!("../README.md"),
        include_str!("../docs/method.md"),
        include_str!("../docs/accuracy.md"),
        include_str!("../docs/formats.md"),
        include_str!("../docs/benchmarks.md"),
        include_str!("../docs/troubleshooting.md"),
    ];

    /// The `linegs-gpu ...` commands of the README and the documentation, continuation
    /// lines joined, comments cut.
    fn readme_commands() -> Vec<String> {
        let mut out = Vec::new();
        let mut in_code = false;
        let mut pending = String::new();
        for line in DOCS.iter().flat_map(|d| d.lines()) {
            if line.trim_start().starts_with("```") {
                in_code = !in_code;
                continue;
            }
            // Commands quoted inline in the text count too.
            if !in_code {
                for (i, part) in line.split('`').enumerate() {
                    // (`linegs-gpu <command> --help` is a pattern, not a command.)
                    if i % 2 == 1 && part.starts_with("linegs-gpu ") && !part.contains('<') {
                        out.push(part.to_string());
                    }
                }
                continue;
            }
            let code = line.split(" #").next().unwrap_or("").trim();
            if pending.is_empty() && !code.starts_with("linegs-gpu") {
                continue;
            }
            if let Some(head) = code.strip_suffix('\\') {
                pending.push_str(head);
                pending.push(' ');
            } else {
                pending.push_str(code);
                out.push(std::mem::take(&mut pending));
            }
        }
        out
    }

    #[test]
    fn every_readme_command_parses() {
        use clap::Parser;
        let cmds = readme_commands();
        assert!(cmds.len() >= 8, "{cmds:#?}");
        for c in &cmds {
            let words: Vec<&str> = c.split_whitespace().collect();
            if let Err(e) = Cli::try_parse_from(&words) {
                // `--help` and `--version` are successful parses that print.
                use clap::error::ErrorKind::{DisplayHelp, DisplayVersion};
                if !matches!(e.kind(), DisplayHelp | DisplayVersion) {
                    panic!("README or docs command does not parse: {c}\n{e}");
                }
            }
        }
    }
}
