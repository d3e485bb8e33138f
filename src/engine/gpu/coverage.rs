//! Launcher of `shaders/coverage.wgsl`: ORs the members of every item into a u32 mask over
//! the sorted points. The caller clears the mask once per batch and reads it back once.

use super::device::{encode, head, Context, Params};
use super::{Job, Scratch};

pub struct Coverage {
    pipeline: wgpu::ComputePipeline,
}

impl Coverage {
    pub fn new(ctx: &Context) -> Self {
        Coverage {
            pipeline: ctx.pipeline("coverage", include_str!("../../../shaders/coverage.wgsl")),
        }
    }

    /// Submits the kernel over `job` into `mask` (`mask_bytes` long).
    pub fn run(
        &self,
        ctx: &Context,
        s: &mut Scratch,
        job: &Job<'_>,
        mask: &wgpu::Buffer,
        mask_bytes: u64,
    ) {
        let params = Params {
            n_groups: job.groups.len() as u32,
            part_base: job.part.base as u32,
            ..Default::default()
        };
        let item_bytes = std::mem::size_of_val(job.items) as u64;
        let group_bytes = std::mem::size_of_val(job.groups) as u64;
        ctx.queue
            .write_buffer(&s.params, 0, bytemuck::bytes_of(&params));
        let items_buf = s.items.get(ctx, item_bytes);
        ctx.queue
            .write_buffer(items_buf, 0, bytemuck::cast_slice(job.items));
        let groups_buf = s.groups.get(ctx, group_bytes);
        ctx.queue
            .write_buffer(groups_buf, 0, bytemuck::cast_slice(job.groups));
        let group = ctx.bind(
            &self.pipeline,
            &[
                s.params.as_entire_binding(),
                wgpu::BindingResource::TextureView(&job.part.view),
                head(items_buf, item_bytes),
                head(groups_buf, group_bytes),
                head(mask, mask_bytes),
            ],
        );
        let encoder = encode(ctx, &self.pipeline, &group, job.groups.len(), job.max_x);
        ctx.queue.submit([encoder.finish()]);
    }
}
