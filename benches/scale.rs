//! The scale ladder (docs/benchmarks.md, "Scale"): `linegs-gpu bench --case ladder`, the
//! synthetic scene from 10^5 Gaussians x 10^3 segments up, 10x a row, each row with its
//! seconds, peak resident memory, growth against the row before, and the command that
//! measures it alone.
//!
//! `cargo bench --bench scale` runs it up to 10^6 Gaussians on the CPU engine (seconds);
//! options after `--` go to the command, e.g. `cargo bench --bench scale -- --max 100000000`
//! for the 10^8 row (minutes, about 8 GB) or `-- --backend cpu,gpu`. Target (issue: 10^8
//! Gaussians x 10^6 segments on the CPU engine): at most 11x the time of the 10^7 row in
//! the same run, peak resident memory at most 8 GB.
//!
//! The ladder runs in the command line's own processes (built by `cargo bench` beside this
//! bench), one a row as its command runs it (`-- --in-process`: all rows in one), so its
//! allocator and peak-memory readings are the ones users see.

use std::process::{Command, ExitCode};

/// The top row when `--max` is not given: seconds, not minutes.
const DEFAULT_MAX: &str = "1000000";

fn main() -> ExitCode {
    // `cargo bench` passes `--bench` to every bench; the rest are the user's options.
    let user: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let mut args = vec!["bench".to_string(), "--case".into(), "ladder".into()];
    if !user.iter().any(|a| a == "--max" || a.starts_with("--max=")) {
        args.extend(["--max".into(), DEFAULT_MAX.into()]);
    }
    args.extend(user);
    let exe = env!("CARGO_BIN_EXE_linegs-gpu");
    match Command::new(exe).args(&args).status() {
        Ok(s) if s.success() => ExitCode::SUCCESS,
        Ok(s) => {
            eprintln!("scale: `linegs-gpu {}` failed ({s})", args.join(" "));
            ExitCode::FAILURE
        }
        Err(e) => {
            eprintln!("scale: could not start {exe}: {e}");
            ExitCode::FAILURE
        }
    }
}
