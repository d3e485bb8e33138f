//! Scene builders and brute-force answers shared by the engine tests.
#![allow(dead_code)]

use glam::DVec3;
use linegs_gpu::engine::{CylStats, Query};
use linegs_gpu::geom::{p64, Aabb, Cylinder, Segment};
use linegs_gpu::index::Grid;

use linegs_gpu::synth::Rng;

/// The tests' random numbers: the library's generator ([`Rng`], xoshiro256** seeded
/// through SplitMix64), with the two draws the tests take.
pub struct TestRng(Rng);

impl TestRng {
    pub fn new(seed: u64) -> TestRng {
        TestRng(Rng::new(seed))
    }
    /// Uniform in `[0, 1)`.
    pub fn f(&mut self) -> f64 {
        self.0.uniform()
    }
    /// Uniform in the unit cube.
    pub fn v(&mut self) -> DVec3 {
        DVec3::new(self.f(), self.f(), self.f())
    }
}

pub fn grid_of(points: &[[f32; 3]], cell: f64) -> Grid {
    let mut b = Aabb::empty();
    for p in points {
        b.extend(p64(*p));
    }
    Grid::build(points, b, cell)
}

/// Random centers in the unit cube, denser along a few lines like a trained 3DGS model.
pub fn random_scene(n: usize, seed: u64) -> Vec<[f32; 3]> {
    let mut r = TestRng::new(seed);
    let lines: Vec<(DVec3, DVec3)> = (0..6).map(|_| (r.v(), r.v())).collect();
    (0..n)
        .map(|i| {
            let p = if i % 3 == 0 {
                r.v()
            } else {
                let (a, b) = lines[i % lines.len()];
                a + (b - a) * r.f() + (r.v() - 0.5) * 0.02
            };
            [p.x as f32, p.y as f32, p.z as f32]
        })
        .collect()
}

pub fn random_queries(n: usize, seed: u64, r: f64) -> Vec<Query> {
    let mut g = TestRng::new(seed);
    (0..n)
        .map(|_| {
            let a = g.v() * 1.2 - 0.1;
            let b = a + (g.v() - 0.5) * 0.6;
            let s = Segment::new(a, b);
            let rr = r * (0.5 + g.f());
            Query::with_plane(s, rr, s.point_at(s.length() * g.f()))
        })
        .collect()
}

/// Brute force over the grid's sorted points (the same order the CPU engine sums in).
pub fn brute_stats(grid: &Grid, q: &Query) -> (CylStats, Vec<usize>) {
    let mut s = CylStats::default();
    let mut members = Vec::new();
    if !q.seg.is_valid() {
        return (s, members);
    }
    let cyl = Cylinder::new(&q.seg, q.r);
    let d = q.seg.dir();
    for (i, p) in grid.points.iter().enumerate() {
        let p = p64(*p);
        if q.seg.cylinder_contains(p, q.r) {
            let (_, v) = cyl.test(p).unwrap();
            s.count += 1;
            s.sum_d2 += v.length_squared();
            s.sum_offset += v;
            if (p - q.plane).dot(d) > 0.0 {
                s.side_pos += 1;
            }
            members.push(i);
        }
    }
    (s, members)
}

/// Brute-force k nearest: sort members by (distance², index).
pub fn brute_nearest(grid: &Grid, q: &Query, k: usize) -> (u64, DVec3, f64) {
    let (_, members) = brute_stats(grid, q);
    let mut m: Vec<(f64, usize, DVec3)> = members
        .iter()
        .map(|&i| {
            let v = q.seg.perp_offset(p64(grid.points[i]));
            (v.length_squared(), i, v)
        })
        .collect();
    m.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let k = k.min(m.len());
    let mut off = DVec3::ZERO;
    let mut d2 = 0.0;
    for x in &m[..k] {
        off += x.2;
        d2 += x.0;
    }
    (k as u64, off, d2)
}

/// Points exactly on the cylinder's boundaries (binary fractions, exact in f32 and f64).
pub fn boundary_scene() -> (Vec<[f32; 3]>, Vec<Query>) {
    let mut pts = Vec::new();
    for i in 0..=16 {
        let x = i as f32 / 16.0;
        pts.push([x, 0.25, 0.0]);
        pts.push([x, 0.0, -0.25]);
        pts.push([x, 0.0, 0.0]);
        pts.push([x, 0.125, 0.125]);
    }
    pts.push([0.0, 0.0, 0.0]);
    pts.push([1.0, 0.0, 0.0]);
    pts.push([-0.0625, 0.0, 0.0]);
    pts.push([1.0625, 0.0, 0.0]);
    pts.push([0.5, 0.25 + 1.0 / 1024.0, 0.0]);
    let s = Segment::new(DVec3::ZERO, DVec3::new(1.0, 0.0, 0.0));
    let q = vec![
        Query::with_plane(s, 0.25, DVec3::new(0.5, 0.0, 0.0)),
        Query::with_plane(s.reversed(), 0.25, DVec3::new(0.5, 0.0, 0.0)),
        Query::with_plane(s, 0.125, DVec3::new(0.25, 0.0, 0.0)),
    ];
    (pts, q)
}

/// `n` centers along `seg` (uniform) with isotropic normal noise `sigma` — a dense edge
/// of a trained 3DGS model.
pub fn edge_points(seg: &Segment, n: usize, sigma: f64, rng: &mut TestRng) -> Vec<[f32; 3]> {
    (0..n)
        .map(|_| {
            let mut g = || {
                // Box–Muller
                let u1 = rng.f().max(1e-300);
                let u2 = rng.f();
                (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
            };
            let noise = DVec3::new(g(), g(), g()) * sigma;
            let p = seg.point_at(seg.length() * rng.f()) + noise;
            [p.x as f32, p.y as f32, p.z as f32]
        })
        .collect()
}

pub fn seg(a: [f64; 3], b: [f64; 3]) -> Segment {
    Segment::from_arrays(a, b)
}

/// A CPU engine over the working set of `points` for `segments` (the centers in the
/// segments' bounding box grown by 0.1, `WorkingSet::new`).
pub fn cpu_engine(
    points: &[[f32; 3]],
    segments: &[Segment],
    cell: f64,
) -> linegs_gpu::engine::cpu::CpuEngine {
    let ws = linegs_gpu::index::WorkingSet::new(points, segments);
    let grid = Grid::build(&ws.points, ws.bounds, cell);
    linegs_gpu::engine::cpu::CpuEngine::new(std::sync::Arc::new(grid))
}

/// `LINEGS_SKIP_GPU_TESTS=1`: GPU tests on a machine without an adapter skip (with a
/// notice) instead of failing.
pub fn skip_gpu_tests() -> bool {
    std::env::var("LINEGS_SKIP_GPU_TESTS").is_ok_and(|v| v == "1")
}

/// Whether a run of the binary that failed for want of a GPU adapter (its standard error
/// `err` names the adapter) is to be skipped: only where the environment opts out with
/// `LINEGS_SKIP_GPU_TESTS=1`, and then the skip is printed.
pub fn no_adapter_skip(o: &std::process::Output, err: &str) -> bool {
    let skip = !o.status.success() && err.contains("adapter") && skip_gpu_tests();
    if skip {
        eprintln!("SKIPPED (LINEGS_SKIP_GPU_TESTS=1): no GPU adapter ({err})");
    }
    skip
}

/// The GPU setup of the tests' environment, as the commands read theirs: the adapter of
/// `WGPU_ADAPTER_NAME`, new buffers filled with garbage where `LINEGS_GPU_GARBAGE` is set
/// (scripts/test.sh sets it), and `opts` otherwise.
pub fn gpu_setup(opts: linegs_gpu::engine::gpu::GpuOptions) -> linegs_gpu::engine::gpu::GpuSetup {
    let env = linegs_gpu::engine::gpu::GpuSetup::from_vars(|k| std::env::var(k).ok())
        .unwrap_or_else(|e| panic!("{e}"));
    linegs_gpu::engine::gpu::GpuSetup {
        options: linegs_gpu::engine::gpu::GpuOptions {
            fill_garbage: opts.fill_garbage || env.options.fill_garbage,
            ..opts
        },
        ..env
    }
}

/// The GPU engine with `opts` in the tests' environment ([`gpu_setup`]). Without an
/// adapter this fails the test, unless the environment opts out with
/// `LINEGS_SKIP_GPU_TESTS=1`: then `None`, and the skip is printed (`cargo test` shows it
/// with the test's output, and in the summary of a failing run).
pub fn gpu_engine(
    grid: std::sync::Arc<Grid>,
    opts: linegs_gpu::engine::gpu::GpuOptions,
) -> Option<linegs_gpu::engine::gpu::GpuEngine> {
    let opened = linegs_gpu::engine::gpu::GpuDevice::open_setup(&gpu_setup(opts));
    match opened.and_then(|d| d.engine(grid)) {
        Ok(e) => Some(e),
        Err(linegs_gpu::engine::EngineError::NoAdapter(why)) => {
            if skip_gpu_tests() {
                // println! is captured per test; eprintln! reaches the terminal at once.
                eprintln!("SKIPPED (LINEGS_SKIP_GPU_TESTS=1): no GPU adapter ({why})");
                println!("SKIPPED (LINEGS_SKIP_GPU_TESTS=1): no GPU adapter ({why})");
                return None;
            }
            panic!(
                "no GPU adapter ({why}): install mesa-vulkan-drivers for lavapipe, or set \
                 LINEGS_SKIP_GPU_TESTS=1 to skip the GPU tests"
            )
        }
        Err(e) => panic!("GPU engine failed to start: {e}"),
    }
}

// ------------------------------------------------------ the binary, as a user runs it

/// A file of `tests/data/` (real files from other tools, with their licences).
pub fn data(rel: &str) -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data")
        .join(rel)
}

/// The trained pair `real_pairs/<pair>` of tests/data: its Gaussians and Line3D++ lines.
pub fn pair_scene(pair: &str) -> linegs_gpu::pipeline::Scene {
    let dir = data(&format!("real_pairs/{pair}"));
    linegs_gpu::pipeline::Scene::load(
        &dir.join("point_cloud.ply"),
        &dir.join("lines.txt"),
        &linegs_gpu::pipeline::LoadOptions::default(),
    )
    .unwrap()
}

/// The `linegs-gpu` binary, for runs that need more than arguments (environment, stdin).
pub fn linegs() -> std::process::Command {
    std::process::Command::new(env!("CARGO_BIN_EXE_linegs-gpu"))
}

/// Runs `linegs-gpu args` and waits for it.
pub fn run(args: &[&str]) -> std::process::Output {
    linegs().args(args).output().unwrap()
}

pub fn stderr(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

pub fn stdout(o: &std::process::Output) -> String {
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The toy scene of `n` Gaussians made by the CLI itself (`synth toy`):
/// `dir/g.ply` and its input lines `dir/l.obj`.
pub fn synth_toy(dir: &std::path::Path, n: usize) -> (std::path::PathBuf, std::path::PathBuf) {
    let g = dir.join("g.ply");
    let l = dir.join("l.obj");
    let n = n.to_string();
    let o = run(&[
        "synth",
        "toy",
        "-o",
        g.to_str().unwrap(),
        "--lines-out",
        l.to_str().unwrap(),
        "-n",
        &n,
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    (g, l)
}
