//! The authors' s200k shape (docs/benchmarks.md, "The authors' scene"): `linegs-gpu bench
//! --case s200k`, the box scene with planted defects (`synth s200k`: 200,000 Gaussians,
//! 318 segments) written once, then the whole `refine --backend cpu --report` process run
//! as a user runs it (a new process from start to exit), median of 7 runs, with the command
//! beside the number. Target (issue): a median of at most 0.11 s, 5,000x the authors' 559 s.
//!
//! `cargo bench --bench s200k`; options after `--` go to the command, e.g.
//! `cargo bench --bench s200k -- --repeat 15` or `-- --backend cpu,gpu`.

use std::process::{Command, ExitCode};

fn main() -> ExitCode {
    // `cargo bench` passes `--bench` to every bench; the rest are the user's options.
    let user: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| a != "--bench")
        .collect();
    let mut args = vec!["bench".to_string(), "--case".into(), "s200k".into()];
    args.extend(user);
    let exe = env!("CARGO_BIN_EXE_linegs-gpu");
    match Command::new(exe).args(&args).status() {
        Ok(s) if s.success() => ExitCode::SUCCESS,
        Ok(s) => {
            eprintln!("s200k: `linegs-gpu {}` failed ({s})", args.join(" "));
            ExitCode::FAILURE
        }
        Err(e) => {
            eprintln!("s200k: could not start {exe}: {e}");
            ExitCode::FAILURE
        }
    }
}
