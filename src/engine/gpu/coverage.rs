//! Launcher of `shaders/coverage.wgsl`: ORs the members of every item into a u32 mask over
//! the sorted points. The caller clears the mask once per batch and reads it back once.

use super::device::Context;
use super::{Job, Scratch};

pub struct Coverage {
    pipeline: wgpu::ComputePipeline,
}

impl Coverage {
    pub fn new(ctx: &Context) -> Self {
        Coverage {
            pipeline: ctx.pipeline(
                "coverage",
                &super::kernel_source(include_str!("../../../shaders/coverage.wgsl")),
            ),
        }
    }

    /// Submits the kernel over the slice of `job`, into `mask` (`mask_bytes` long).
    pub fn run(
        &self,
        ctx: &Context,
        s: &mut Scratch,
        job: &Job<'_>,
        mask: &wgpu::Buffer,
        mask_bytes: u64,
    ) {
        s.submit(ctx, &self.pipeline, job, 0, &[(mask, mask_bytes)]);
    }
}
