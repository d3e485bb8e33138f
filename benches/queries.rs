//! CPU engine versus GPU engine on batches of cylinder queries:
//! `cargo bench --bench queries`. Scenes are the tests' random scenes (centers in the unit
//! cube, denser along a few lines), grid cell = query radius = 0.03.
//! The GPU side is whatever adapter wgpu picks (`WGPU_ADAPTER_NAME=llvmpipe` for lavapipe);
//! without one only the CPU is measured.

#[path = "../tests/common/mod.rs"]
mod common;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use linegs_gpu::engine::cpu::CpuEngine;
use linegs_gpu::engine::gpu::GpuEngine;
use linegs_gpu::engine::{Engine, Want};
use std::sync::Arc;
use std::time::Duration;

/// The command line's huge-page advice for large blocks, so that the numbers are its own.
#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

const RADIUS: f64 = 0.03;

fn bench_queries(c: &mut Criterion) {
    for n_points in [100_000usize, 1_000_000] {
        let pts = common::random_scene(n_points, 7);
        let grid = Arc::new(common::grid_of(&pts, RADIUS));
        let mut engines: Vec<Box<dyn Engine>> = vec![Box::new(CpuEngine::new(grid.clone()))];
        match GpuEngine::new(grid.clone()) {
            Ok(g) => {
                eprintln!("GPU adapter: {}", g.adapter());
                engines.push(Box::new(g));
            }
            Err(e) => eprintln!("no GPU engine ({e}); measuring the CPU only"),
        }
        for n_queries in [1_000usize, 10_000] {
            let qs = common::random_queries(n_queries, 11, RADIUS);
            let counts = engines[0].stats(&qs, Want::COUNT).unwrap();
            let ks: Vec<u64> = counts.iter().map(|s| s.count * 2 / 5).collect();
            let mut group = c.benchmark_group(format!("{n_points}pts_{n_queries}q"));
            group.sample_size(10);
            group.warm_up_time(Duration::from_millis(500));
            group.measurement_time(Duration::from_secs(3));
            for e in &engines {
                let name = e.backend();
                group.bench_function(BenchmarkId::new("stats", name), |b| {
                    b.iter(|| e.stats(&qs, Want::ALL).unwrap())
                });
                group.bench_function(BenchmarkId::new("nearest", name), |b| {
                    b.iter(|| e.nearest(&qs, &ks).unwrap())
                });
                group.bench_function(BenchmarkId::new("coverage", name), |b| {
                    b.iter(|| e.coverage(&qs).unwrap())
                });
            }
            group.finish();
        }
    }
}

criterion_group!(benches, bench_queries);
criterion_main!(benches);
