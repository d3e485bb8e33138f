//! The environment, read here and nowhere in the library: the variables that choose and
//! tune the GPU engine become a [`GpuSetup`] value that the commands pass down
//! (docs/troubleshooting.md#environment lists every variable).

use linegs_gpu::engine::gpu::{GpuSetup, GpuSetupError};
use linegs_gpu::engine::select::Backend;
use linegs_gpu::pipeline::Job;
use linegs_gpu::refine::Params;
use std::sync::OnceLock;

/// The GPU engine's adapter and options from `WGPU_ADAPTER_NAME` and `LINEGS_GPU_*`, read
/// once per process; a bad value is an input error (exit 2) naming the variable.
pub fn gpu_setup() -> anyhow::Result<&'static GpuSetup> {
    static SETUP: OnceLock<Result<GpuSetup, GpuSetupError>> = OnceLock::new();
    SETUP
        .get_or_init(|| GpuSetup::from_vars(|k| std::env::var(k).ok()))
        .as_ref()
        .map_err(|e| super::input_error(e.to_string()))
}

/// The job with `params` on `backend`, its GPU engine set up from the environment.
pub fn job(params: Params, backend: Backend) -> anyhow::Result<Job> {
    Ok(Job {
        gpu: gpu_setup()?.clone(),
        ..Job::new(params, backend)
    })
}
