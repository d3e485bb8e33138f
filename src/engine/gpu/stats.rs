//! Launcher of `shaders/stats.wgsl`: per work item, the count, side count and sums of its
//! members.

use super::device::Context;
use super::{Job, Scratch};
use crate::engine::EngineError;
use bytemuck::{Pod, Zeroable};

/// `struct Partial` of the shader.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Pod, Zeroable)]
pub struct Partial {
    pub count: u32,
    pub side_pos: u32,
    pub sum_d2: f32,
    pub off: [f32; 3],
}

pub struct Stats {
    pipeline: wgpu::ComputePipeline,
}

impl Stats {
    pub fn new(ctx: &Context) -> Self {
        Stats {
            pipeline: ctx.pipeline(
                "stats",
                &super::kernel_source(include_str!("../../../shaders/stats.wgsl")),
            ),
        }
    }

    /// Runs the kernel over the slice of `job` and hands `f` one partial per item, in the
    /// slice's build order.
    pub fn run<R>(
        &self,
        ctx: &Context,
        s: &mut Scratch,
        job: &Job<'_>,
        f: impl FnOnce(&[Partial]) -> R,
    ) -> Result<R, EngineError> {
        let bytes = (job.items.len() * std::mem::size_of::<Partial>()) as u64;
        let out = s.out.get(ctx, bytes).clone();
        s.submit(ctx, &self.pipeline, job, 0, &[(&out, bytes)]);
        let staging = s.staging.get(ctx, bytes).clone();
        ctx.read_back(ctx.encoder(), &out, &staging, bytes, |b| {
            f(&super::device::pods(b))
        })
    }
}
