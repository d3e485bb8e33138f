//! Read throughput of a 3DGS `point_cloud.ply` (10^6 Gaussians, all 62 float properties,
//! binary little endian) from the page cache, and the memory the read needs beyond the
//! centers it returns. Targets: >= 1 GB/s, < 40 MB beyond the centers.
//!
//! `cargo bench --bench ply_read`

use std::hint::black_box;
use std::path::Path;

use criterion::{criterion_group, Criterion, Throughput};
use linegs_gpu::io::{read_gaussians, write_gaussians_3dgs, PlyOptions};
use linegs_gpu::mem;

/// The command line's huge-page advice for large blocks, so that the numbers are its own.
#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

const N: usize = 1_000_000;

/// Deterministic centers in a 10 m box (xorshift), with opacity logits around 0.
fn scene(n: usize) -> (Vec<[f32; 3]>, Vec<f32>) {
    let mut s = 0x9e37_79b9_7f4a_7c15u64;
    let mut next = move || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        (s >> 40) as f32 / (1u64 << 24) as f32
    };
    let centers = (0..n)
        .map(|_| [next() * 10.0, next() * 10.0, next() * 10.0])
        .collect();
    let logits = (0..n).map(|_| next() * 8.0 - 4.0).collect();
    (centers, logits)
}

fn mib(b: u64) -> f64 {
    b as f64 / (1u64 << 20) as f64
}

/// Set in the child process that measures memory: the path of the file to read.
const MEMORY_CHILD: &str = "LINEGS_PLY_READ_MEMORY_CHILD";

/// Peak RSS growth of one read, split into the returned centers and everything else. Runs
/// in a fresh child process: in this one, the allocator keeps pages from earlier phases
/// resident and reuses them, which would hide the read's own peak.
fn report_memory(path: &Path) {
    let out = std::process::Command::new(std::env::current_exe().expect("own path"))
        .env(MEMORY_CHILD, path)
        .output()
        .expect("run the memory child");
    eprint!("{}", String::from_utf8_lossy(&out.stderr));
}

fn measure_memory_here(path: &Path) {
    let before = mem::current_rss_bytes();
    let reset = mem::reset_peak_rss();
    let cloud = read_gaussians(path, &PlyOptions::default()).expect("read");
    let peak = mem::peak_rss_bytes();
    let (Some(before), Some(peak)) = (before, peak) else {
        eprintln!("ply_read: peak RSS not available on this platform");
        return;
    };
    let centers = (cloud.centers.capacity() * std::mem::size_of::<[f32; 3]>()) as u64;
    let growth = peak.saturating_sub(before);
    eprintln!(
        "ply_read: peak RSS growth while reading {} Gaussians: {:.1} MiB = centers {:.1} MiB + {:.1} MiB beyond{}",
        cloud.centers.len(),
        mib(growth),
        mib(centers),
        mib(growth.saturating_sub(centers)),
        if reset {
            ""
        } else {
            " (peak could not be reset: includes the process start)"
        }
    );
}

fn ply_read(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("gaussians_1e6.ply");
    {
        let (centers, logits) = scene(N);
        write_gaussians_3dgs(&path, &centers, Some(&logits)).expect("write");
    }
    let bytes = std::fs::metadata(&path).expect("metadata").len();
    // Just written, so the file is in the page cache for the memory child and the timings.
    report_memory(&path);

    let mut group = c.benchmark_group("ply_read");
    group.throughput(Throughput::Bytes(bytes));
    group.sample_size(20);
    group.bench_function("3dgs_62_properties_1e6", |b| {
        b.iter(|| read_gaussians(black_box(&path), &PlyOptions::default()).expect("read"))
    });
    let opts = PlyOptions {
        min_opacity: Some(0.5),
        strict: false,
    };
    group.bench_function("3dgs_62_properties_1e6_min_opacity", |b| {
        b.iter(|| read_gaussians(black_box(&path), &opts).expect("read"))
    });
    group.finish();
}

criterion_group!(benches, ply_read);

fn main() {
    if let Some(path) = std::env::var_os(MEMORY_CHILD) {
        measure_memory_here(Path::new(&path));
        return;
    }
    benches();
    Criterion::default().configure_from_args().final_summary();
}
