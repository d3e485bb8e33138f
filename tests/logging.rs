//! The command line's logger (`RUST_LOG`, src/main.rs): the adapter search and what
//! wgpu reports through `log` reach standard error; nothing without `RUST_LOG`.

use std::path::Path;
use std::process::{Command, Output};

fn run(dir: &Path, args: &[&str], rust_log: Option<&str>) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_linegs-gpu"));
    c.args(args).current_dir(dir).env_remove("RUST_LOG");
    if let Some(l) = rust_log {
        c.env("RUST_LOG", l);
    }
    let o = c.output().unwrap();
    assert!(
        o.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    o
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn rust_log_shows_the_adapter_search_and_wgpu() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    run(
        d,
        &[
            "synth",
            "toy",
            "-o",
            "g.ply",
            "--lines-out",
            "l.txt",
            "-n",
            "3000",
        ],
        None,
    );
    let refine = |backend: &str, log: Option<&str>| {
        stderr(&run(
            d,
            &[
                "refine",
                "-g",
                "g.ply",
                "-l",
                "l.txt",
                "-o",
                "r.obj",
                "--backend",
                backend,
            ],
            log,
        ))
    };
    // Without RUST_LOG: not a line of the log.
    let quiet = refine("auto", None);
    assert!(!quiet.contains("adapter search"), "{quiet}");
    assert!(!quiet.contains("] "), "{quiet}");

    // info: the search and its outcome, not the list.
    let info = refine("auto", Some("info"));
    assert!(
        info.contains("INFO  linegs_gpu::engine::gpu::device] adapter search: backends"),
        "{info}"
    );
    let outcome = info.contains("linegs_gpu::engine::select] adapter picked: ")
        || info.contains("linegs_gpu::engine::select] --backend auto takes the CPU engine: ");
    assert!(outcome, "{info}");
    assert!(!info.contains("adapter 0: "), "{info}");

    // debug: every adapter found, by name, type and driver; and wgpu's own messages
    // (wgpu_core, wgpu_hal), which have no other way out.
    let debug = refine("auto", Some("debug"));
    let found = debug
        .lines()
        .find_map(|l| l.split("adapters found: ").nth(1))
        .and_then(|n| n.trim().parse::<usize>().ok())
        .expect("the number of adapters");
    let listed = debug
        .lines()
        .filter(|l| l.contains("] adapter ") && l.contains(": ") && l.contains("; driver "))
        .count();
    assert_eq!(listed, found, "{debug}");
    let gpu = refine("gpu", Some("debug"));
    assert!(gpu.contains("adapter picked: "), "{gpu}");
    assert!(
        gpu.lines()
            .any(|l| l.starts_with("[") && (l.contains(" wgpu_core") || l.contains(" wgpu_hal"))),
        "no message of wgpu in the debug log: {gpu}"
    );
    // a filter by target, env_logger's syntax: wgpu only
    let only = refine("gpu", Some("wgpu_core=debug,wgpu_hal=debug"));
    assert!(!only.contains("adapter search"), "{only}");
}
