//! Launcher of `shaders/stats.wgsl`: per work item, the count, side count and sums of its
//! members.

use super::device::{encode, head, Context, Params};
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
            pipeline: ctx.pipeline("stats", include_str!("../../../shaders/stats.wgsl")),
        }
    }

    /// One partial per item of `job`.
    pub fn run(
        &self,
        ctx: &Context,
        s: &mut Scratch,
        job: &Job<'_>,
    ) -> Result<Vec<Partial>, EngineError> {
        let params = Params {
            n_groups: job.groups.len() as u32,
            part_base: job.part.base as u32,
            ..Default::default()
        };
        let item_bytes = std::mem::size_of_val(job.items) as u64;
        let group_bytes = std::mem::size_of_val(job.groups) as u64;
        let out_bytes = (job.items.len() * std::mem::size_of::<Partial>()) as u64;
        ctx.queue
            .write_buffer(&s.params, 0, bytemuck::bytes_of(&params));
        let items_buf = s.items.get(ctx, item_bytes);
        ctx.queue
            .write_buffer(items_buf, 0, bytemuck::cast_slice(job.items));
        let groups_buf = s.groups.get(ctx, group_bytes);
        ctx.queue
            .write_buffer(groups_buf, 0, bytemuck::cast_slice(job.groups));
        let out = s.out.get(ctx, out_bytes);
        let group = ctx.bind(
            &self.pipeline,
            &[
                s.params.as_entire_binding(),
                wgpu::BindingResource::TextureView(&job.part.view),
                head(items_buf, item_bytes),
                head(groups_buf, group_bytes),
                head(out, out_bytes),
            ],
        );
        let encoder = encode(ctx, &self.pipeline, &group, job.groups.len(), job.max_x);
        let bytes = ctx.read_back(encoder, out, s.staging.get(ctx, out_bytes), out_bytes)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }
}
