//! A refinement opens one GPU device, whatever engines it makes: with `--max-scale`'s
//! cut (the `default` profile on a 3DGS model with scales) the placing Gaussians' engine
//! runs on the device of the whole model's, and the segments are the CPU engine's. One
//! test alone in this binary: it counts the process's device openings.

mod common;

use linegs_gpu::engine::gpu::devices_opened;
use linegs_gpu::engine::select::Backend;
use linegs_gpu::pipeline::{Job, LoadOptions, Scene};
use linegs_gpu::refine::{Params, RadiusArg};

#[test]
fn a_run_with_the_scale_cut_opens_one_device() {
    if common::skip_gpu_tests() {
        println!("SKIPPED (LINEGS_SKIP_GPU_TESTS=1)");
        return;
    }
    let dir = common::data("real_pairs/proc");
    let scene = Scene::load(
        &dir.join("point_cloud.ply"),
        &dir.join("lines.txt"),
        &LoadOptions::default(),
    )
    .unwrap();
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
}
