//! A refinement opens one GPU device, whatever engines it makes: with `--max-scale`'s
//! cut (the `default` profile on a 3DGS model with scales) the placing Gaussians' engine
//! runs on the device of the whole model's, and the segments are the CPU engine's; a
//! `batch` opens one for all its scenes. One test alone in this binary: it counts the
//! process's device openings.

mod common;

use linegs_gpu::engine::gpu::devices_opened;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::pipeline::Job;
use linegs_gpu::refine::{Params, RadiusArg};

#[test]
fn a_run_with_the_scale_cut_and_a_batch_open_one_device_each() {
    if common::skip_gpu_tests() {
        println!("SKIPPED (LINEGS_SKIP_GPU_TESTS=1)");
        return;
    }
    let scene = common::pair_scene("proc");
    let params = Params {
        radius: RadiusArg::Fixed(0.03),
        ..Default::default()
    };
    let run = |backend| {
        Job {
            gpu: common::gpu_setup(linegs_gpu::engine::gpu::GpuOptions::for_commands()),
            ..Job::new(params.clone(), backend)
        }
        .refine(&scene, |_| {})
        .unwrap()
    };
    let before = devices_opened();
    let gpu = run(Backend::Gpu);
    assert_eq!(devices_opened() - before, 1, "devices opened by one run");
    let cut = gpu.report.refine.as_ref().unwrap().scale_cut;
    assert!(
        cut.is_some_and(|n| n > 0),
        "the scale cut left nothing out: {cut:?}"
    );
    let cpu = run(Backend::Cpu);
    assert_eq!(
        devices_opened() - before,
        1,
        "the CPU engine opened a device"
    );
    assert_eq!(gpu.lines.segments, cpu.lines.segments);

    // A batch of three scenes (the trained pairs) on the GPU engine: one device.
    let out = std::env::temp_dir().join(format!("linegs-one-device-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let manifest = out.join("manifest.csv");
    std::fs::create_dir_all(&out).unwrap();
    let pairs = common::data("real_pairs");
    let rows: String = ["proc", "proc_gsplat", "abc00000006"]
        .iter()
        .map(|p| {
            let d = pairs.join(p);
            format!(
                "{p},{},{},,0.03,0.1\n",
                d.join("point_cloud.ply").display(),
                d.join("lines.txt").display()
            )
        })
        .collect();
    std::fs::write(
        &manifest,
        format!("name,gaussians,lines,gt,radius,eval_radius\n{rows}"),
    )
    .unwrap();
    let m = linegs_gpu::batch::Manifest::read(&manifest).unwrap();
    let opts = linegs_gpu::batch::BatchOptions {
        params: Params::default(),
        backend: Backend::Gpu,
        gpu: common::gpu_setup(linegs_gpu::engine::gpu::GpuOptions::for_commands()),
        shard: Default::default(),
        skip_existing: false,
        format: "obj".into(),
        protocol: Default::default(),
        summary: false,
    };
    let before = devices_opened();
    let done = linegs_gpu::batch::run(&m, &out.join("results"), &opts, |_, _| {}).unwrap();
    assert_eq!(
        devices_opened() - before,
        1,
        "devices opened by a batch of 3"
    );
    assert!(
        done.iter()
            .all(|(_, s)| matches!(s, linegs_gpu::batch::Status::Done { .. })),
        "{done:?}"
    );
    // Each scene's segments are its own run's (the device's earlier grids are gone).
    let alone = Job::new(Params::default(), Backend::Cpu);
    for p in ["proc", "proc_gsplat", "abc00000006"] {
        let scene = common::pair_scene(p);
        let want = alone.refine(&scene, |_| {}).unwrap().lines.segments.len();
        let got = linegs_gpu::io::read_lines(&out.join("results").join(p).join("refined.obj"))
            .unwrap()
            .lines
            .segments
            .len();
        assert_eq!(got, want, "{p}");
    }
    let _ = std::fs::remove_dir_all(&out);
}
