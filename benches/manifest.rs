//! Reading a `batch` manifest of 10^6 scenes (77 MB of CSV, page cache): the name
//! checks are hash lookups, so the read is linear in the manifest's size. Target: <= 5 s.
//!
//! `cargo bench --bench manifest`

use std::hint::black_box;

use criterion::{criterion_group, Criterion, Throughput};
use linegs_gpu::batch::Manifest;

const ROWS: usize = 1_000_000;

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().expect("temporary folder");
    let path = dir.path().join("scenes.csv");
    let mut text = String::from("name,gaussians,lines,gt,radius,eval_radius\n");
    for i in 0..ROWS {
        text.push_str(&format!(
            "scene_{i:07},models/{i}/point_cloud.ply,lines/{i}/Line3D++.txt,,0.05,\n"
        ));
    }
    std::fs::write(&path, &text).expect("write the manifest");
    let mut g = c.benchmark_group("manifest");
    g.sample_size(10);
    g.throughput(Throughput::Bytes(text.len() as u64));
    g.bench_function("read 10^6 rows", |b| {
        b.iter(|| {
            let m = Manifest::read(black_box(&path)).expect("read");
            assert_eq!(m.entries.len(), ROWS);
            m
        })
    });
    g.finish();
}

criterion_group!(benches, bench);

fn main() {
    benches();
    Criterion::default().configure_from_args().final_summary();
}
