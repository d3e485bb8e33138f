//! The wgpu side of the GPU engine: adapter choice, device limits, error scopes, buffers
//! and read-back. Kernels' launchers (`stats.rs`, ...) use only what is here.

use super::super::EngineError;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};

/// A device, its queue and what the engine needs to know about them.
pub struct Context {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    /// Errors that escaped every error scope, and device loss; checked after each batch
    /// so that they come back as `EngineError::Gpu` instead of the default handler's panic.
    stray: Arc<Mutex<Option<String>>>,
}

/// Picks the adapter: `WGPU_ADAPTER_NAME` (a case-insensitive substring of the adapter
/// name) when set, else wgpu's default choice (`WGPU_POWER_PREF` honoured); `WGPU_BACKEND`
/// restricts the backends in both cases. Unlike `wgpu::util::initialize_adapter_from_env`,
/// a name that matches nothing is an error, not a panic.
pub fn pick_adapter() -> Result<wgpu::Adapter, EngineError> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let backends = wgpu::Backends::from_env().unwrap_or(wgpu::Backends::all());
    if let Ok(name) = std::env::var("WGPU_ADAPTER_NAME") {
        let want = name.to_lowercase();
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        let names: Vec<String> = adapters.iter().map(|a| a.get_info().name).collect();
        return adapters
            .into_iter()
            .find(|a| a.get_info().name.to_lowercase().contains(&want))
            .ok_or_else(|| {
                EngineError::NoAdapter(format!(
                    "WGPU_ADAPTER_NAME={name} matches none of [{}]",
                    names.join(", ")
                ))
            });
    }
    let options = wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::from_env()
            .unwrap_or(wgpu::PowerPreference::HighPerformance),
        ..Default::default()
    };
    pollster::block_on(instance.request_adapter(&options))
        .map_err(|e| EngineError::NoAdapter(e.to_string()))
}

impl Context {
    /// Opens a device on `adapter` with the limits the engine needs raised to what the
    /// adapter offers: large storage bindings, buffers and textures, up to 8 storage buffers
    /// per stage.
    pub fn new(adapter: &wgpu::Adapter) -> Result<Context, EngineError> {
        let offered = adapter.limits();
        let mut limits = wgpu::Limits::downlevel_defaults();
        limits.max_storage_buffer_binding_size = offered.max_storage_buffer_binding_size;
        limits.max_buffer_size = offered.max_buffer_size;
        limits.max_storage_buffers_per_shader_stage =
            offered.max_storage_buffers_per_shader_stage.min(8);
        limits.max_compute_workgroups_per_dimension = offered.max_compute_workgroups_per_dimension;
        limits.max_texture_dimension_2d = offered.max_texture_dimension_2d;
        if limits.max_storage_buffers_per_shader_stage < 6 {
            return Err(EngineError::Gpu(format!(
                "adapter {} offers {} storage buffers per shader stage, the kernels need 6",
                adapter.get_info().name,
                limits.max_storage_buffers_per_shader_stage
            )));
        }
        let desc = wgpu::DeviceDescriptor {
            label: Some("linegs"),
            required_features: wgpu::Features::empty(),
            required_limits: limits.clone(),
            ..Default::default()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&desc))
            .map_err(|e| EngineError::Gpu(format!("cannot open the device: {e}")))?;
        let stray = Arc::new(Mutex::new(None));
        let sink = stray.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let mut s = sink.lock().unwrap_or_else(|p| p.into_inner());
            s.get_or_insert_with(|| e.to_string());
        }));
        let sink = stray.clone();
        device.set_device_lost_callback(move |reason, msg| {
            let mut s = sink.lock().unwrap_or_else(|p| p.into_inner());
            s.get_or_insert_with(|| format!("device lost ({reason:?}): {msg}"));
        });
        Ok(Context {
            device,
            queue,
            info: adapter.get_info(),
            limits,
            stray,
        })
    }

    /// `name (driver info, backend)`.
    pub fn describe(&self) -> String {
        let i = &self.info;
        let driver = [i.driver.as_str(), i.driver_info.as_str()]
            .iter()
            .filter(|s| !s.is_empty())
            .copied()
            .collect::<Vec<_>>()
            .join(" ");
        if driver.is_empty() {
            format!("{} ({:?})", i.name, i.backend)
        } else {
            format!("{} ({driver}, {:?})", i.name, i.backend)
        }
    }

    /// Runs `f` inside out-of-memory, validation and internal error scopes and turns the
    /// first captured error (or one that escaped earlier) into `EngineError::Gpu`.
    pub fn scoped<T>(&self, what: &str, f: impl FnOnce() -> T) -> Result<T, EngineError> {
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let validation = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let internal = self.device.push_error_scope(wgpu::ErrorFilter::Internal);
        let out = f();
        let errors = [
            pollster::block_on(internal.pop()),
            pollster::block_on(validation.pop()),
            pollster::block_on(oom.pop()),
        ];
        if let Some(e) = errors.into_iter().flatten().next() {
            return Err(EngineError::Gpu(format!("{what}: {e}")));
        }
        self.check_stray(what)?;
        Ok(out)
    }

    fn check_stray(&self, what: &str) -> Result<(), EngineError> {
        let s = self.stray.lock().unwrap_or_else(|p| p.into_inner());
        match &*s {
            Some(e) => Err(EngineError::Gpu(format!("{what}: {e}"))),
            None => Ok(()),
        }
    }

    /// A storage buffer of `size` bytes. In debug builds (tests) it is filled with 0xFF
    /// bytes, so a kernel that reads memory it never wrote sees NaNs and huge counts.
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        let size = size.max(4).next_multiple_of(4);
        let buf = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: usage | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        if fill_garbage() && !usage.contains(wgpu::BufferUsages::MAP_READ) {
            let garbage = vec![0xFFu8; size as usize];
            self.queue.write_buffer(&buf, 0, &garbage);
        }
        buf
    }

    /// Submits `encoder` with a copy of the first `size` bytes of `src` into `staging` (a
    /// MAP_READ buffer of at least `size` bytes), waits, and hands the bytes to `f` where
    /// they lie, without copying them out.
    pub fn read_back<R>(
        &self,
        mut encoder: wgpu::CommandEncoder,
        src: &wgpu::Buffer,
        staging: &wgpu::Buffer,
        size: u64,
        f: impl FnOnce(&[u8]) -> R,
    ) -> Result<R, EngineError> {
        if size == 0 {
            self.queue.submit([encoder.finish()]);
            return Ok(f(&[]));
        }
        encoder.copy_buffer_to_buffer(src, 0, staging, 0, size);
        self.queue.submit([encoder.finish()]);
        let slice = staging.slice(..size);
        let (tx, rx) = mpsc::channel();
        slice.map_async(wgpu::MapMode::Read, move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| EngineError::Gpu(format!("waiting for the device: {e}")))?;
        rx.recv()
            .map_err(|_| EngineError::Gpu("read-back never completed".into()))?
            .map_err(|e| EngineError::Gpu(format!("read-back failed: {e}")))?;
        let out = {
            let view = slice
                .get_mapped_range()
                .map_err(|e| EngineError::Gpu(format!("read-back failed: {e}")))?;
            f(&view)
        };
        staging.unmap();
        Ok(out)
    }

    /// A fresh command encoder.
    pub fn encoder(&self) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default())
    }

    /// Compute pipeline with its layout derived from the shader.
    pub fn pipeline(&self, label: &str, wgsl: &str) -> wgpu::ComputePipeline {
        let module = self
            .device
            .create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some(label),
                source: wgpu::ShaderSource::Wgsl(wgsl.into()),
            });
        self.device
            .create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(label),
                layout: None,
                module: &module,
                entry_point: Some("main"),
                compilation_options: Default::default(),
                cache: None,
            })
    }

    /// Bind group 0 of `pipeline` with `buffers` bound in order (binding 0, 1, ...).
    pub fn bind(
        &self,
        pipeline: &wgpu::ComputePipeline,
        buffers: &[wgpu::BindingResource<'_>],
    ) -> wgpu::BindGroup {
        let entries: Vec<wgpu::BindGroupEntry<'_>> = buffers
            .iter()
            .enumerate()
            .map(|(i, r)| wgpu::BindGroupEntry {
                binding: i as u32,
                resource: r.clone(),
            })
            .collect();
        self.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &entries,
        })
    }
}

/// A buffer kept between batches and grown on demand, so that a batch does not pay for
/// allocating (and wgpu for zeroing) its scratch memory.
pub struct Reusable {
    label: &'static str,
    usage: wgpu::BufferUsages,
    buf: Option<wgpu::Buffer>,
}

impl Reusable {
    pub fn new(label: &'static str, usage: wgpu::BufferUsages) -> Self {
        Reusable {
            label,
            usage,
            buf: None,
        }
    }

    /// A buffer of at least `size` bytes (never empty).
    pub fn get(&mut self, ctx: &Context, size: u64) -> &wgpu::Buffer {
        let size = size.max(64).next_multiple_of(256);
        if self.buf.as_ref().is_none_or(|b| b.size() < size) {
            // Grow by half again so that slowly rising batches do not reallocate each time.
            let grown = self.buf.as_ref().map_or(0, |b| b.size() + b.size() / 2);
            let cap = ctx
                .limits
                .max_buffer_size
                .min(size.max(grown).next_multiple_of(256));
            self.buf = Some(ctx.buffer(self.label, cap.max(size), self.usage));
        }
        self.buf.as_ref().expect("just created")
    }
}

/// Texels per row of every table texture (`ROW` in the shaders).
pub const ROW: usize = 4096;

/// A table of `[u32; 4]` rows kept in an `Rgba32Uint` texture of `ROW`-texel rows: the
/// kernels read their inputs with `textureLoad`, which lavapipe turns into SIMD gathers,
/// where a storage-buffer load costs one branchy scalar load per lane and component.
pub struct Table {
    label: &'static str,
    texture: Option<(wgpu::Texture, wgpu::TextureView)>,
}

impl Table {
    pub fn new(label: &'static str) -> Self {
        Table {
            label,
            texture: None,
        }
    }

    /// Rows a table of `n` texels needs.
    pub fn rows(n: usize) -> u32 {
        n.div_ceil(ROW).max(1) as u32
    }

    /// A texture for `rows` rows, reused when large enough.
    fn reserve(&mut self, ctx: &Context, rows: u32) -> &(wgpu::Texture, wgpu::TextureView) {
        if self.texture.as_ref().is_none_or(|(t, _)| t.height() < rows) {
            let grown = self.texture.as_ref().map_or(0, |(t, _)| t.height() * 3 / 2);
            let height = rows
                .max(grown)
                .min(ctx.limits.max_texture_dimension_2d)
                .max(rows);
            self.texture = Some(table_texture(ctx, self.label, height));
        }
        self.texture.as_ref().expect("just created")
    }

    /// Uploads `texels` (row-major from texel 0) and returns the view to bind.
    pub fn write(&mut self, ctx: &Context, texels: &[[u32; 4]]) -> wgpu::TextureView {
        let (texture, view) = self.reserve(ctx, Table::rows(texels.len()));
        write_texels(ctx, texture, texels);
        view.clone()
    }
}

/// An `Rgba32Uint` texture of `height` rows of `ROW` texels.
pub fn table_texture(
    ctx: &Context,
    label: &str,
    height: u32,
) -> (wgpu::Texture, wgpu::TextureView) {
    let texture = ctx.device.create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width: ROW as u32,
            height,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format: wgpu::TextureFormat::Rgba32Uint,
        usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST,
        view_formats: &[],
    });
    let view = texture.create_view(&wgpu::TextureViewDescriptor::default());
    (texture, view)
}

/// Writes `texels` from texel 0 of `texture`: the full rows in one copy, the last partial
/// row in another (no padded copy of the data).
pub fn write_texels(ctx: &Context, texture: &wgpu::Texture, texels: &[[u32; 4]]) {
    let full = texels.len() / ROW;
    let copy = |origin_y: u32, data: &[[u32; 4]], width: u32, height: u32| {
        ctx.queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: 0,
                origin: wgpu::Origin3d {
                    x: 0,
                    y: origin_y,
                    z: 0,
                },
                aspect: wgpu::TextureAspect::All,
            },
            bytemuck::cast_slice(data),
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some((ROW * 16) as u32),
                rows_per_image: Some(height),
            },
            wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            },
        );
    };
    if full > 0 {
        copy(0, &texels[..full * ROW], ROW as u32, full as u32);
    }
    let rest = &texels[full * ROW..];
    if !rest.is_empty() {
        copy(full as u32, rest, rest.len() as u32, 1);
    }
}

/// Binds the first `size` bytes of `buf` (at least 4).
pub fn head(buf: &wgpu::Buffer, size: u64) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer: buf,
        offset: 0,
        size: std::num::NonZeroU64::new(size.max(4).next_multiple_of(4)),
    })
}

/// Item groups per workgroup (`GROUPS_PER_WORKGROUP` in the shaders; 64 invocations).
const GROUPS_PER_WORKGROUP: u64 = 8;

/// `struct Params` of the shaders: the uniform every kernel reads.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, bytemuck::Pod, bytemuck::Zeroable)]
pub struct Params {
    /// Groups (workgroups) in the dispatch.
    pub n_groups: u32,
    /// Sorted index of the first point of the bound part.
    pub part_base: u32,
    pub mode: u32,
    /// First group of the dispatch in the slice's group list.
    pub group_base: u32,
}

/// Records one dispatch of `pipeline` over `n_groups` item groups, `GROUPS_PER_WORKGROUP`
/// per workgroup.
pub fn encode(
    ctx: &Context,
    pipeline: &wgpu::ComputePipeline,
    group: &wgpu::BindGroup,
    n_groups: usize,
    max_x: u32,
) -> wgpu::CommandEncoder {
    let mut encoder = ctx
        .device
        .create_command_encoder(&wgpu::CommandEncoderDescriptor::default());
    {
        let mut pass = encoder.begin_compute_pass(&wgpu::ComputePassDescriptor::default());
        pass.set_pipeline(pipeline);
        pass.set_bind_group(0, group, &[]);
        let (x, y) = tiles(n_groups as u64, GROUPS_PER_WORKGROUP, max_x);
        pass.dispatch_workgroups(x, y, 1);
    }
    encoder
}

/// `bytes` as a slice of `T`, in place when aligned (mapped memory always is).
pub fn pods<T: bytemuck::Pod>(bytes: &[u8]) -> std::borrow::Cow<'_, [T]> {
    match bytemuck::try_cast_slice(bytes) {
        Ok(s) => std::borrow::Cow::Borrowed(s),
        Err(_) => std::borrow::Cow::Owned(bytemuck::pod_collect_to_vec(bytes)),
    }
}

/// Test builds fill new buffers with garbage (also on request: `LINEGS_GPU_GARBAGE=1`).
pub fn fill_garbage() -> bool {
    cfg!(debug_assertions) || std::env::var_os("LINEGS_GPU_GARBAGE").is_some()
}

/// Workgroups for `n` invocations of `workgroup` each, tiled in 2D when more than
/// `max_x` are needed (the kernels rebuild the linear index from `num_workgroups`).
pub fn tiles(n: u64, workgroup: u64, max_x: u32) -> (u32, u32) {
    let groups = n.div_ceil(workgroup).max(1);
    let x = groups.min(max_x as u64);
    (x as u32, groups.div_ceil(x) as u32)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A device, or `None` (with a notice) where there is no adapter and `CI` is not `true`.
    fn context() -> Option<Context> {
        match pick_adapter() {
            Ok(a) => Some(Context::new(&a).expect("device")),
            Err(e) if std::env::var("CI").is_ok_and(|v| v == "true") => panic!("{e}"),
            Err(e) => {
                eprintln!("SKIPPED: {e}");
                None
            }
        }
    }

    #[test]
    fn wgpu_validation_errors_come_back_as_engine_errors() {
        let Some(ctx) = context() else { return };
        // MAP_READ may only be combined with COPY_DST: a validation error, not a panic.
        let r = ctx.scoped("bad buffer", || {
            ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: None,
                size: 64,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::STORAGE,
                mapped_at_creation: false,
            })
        });
        match r {
            Err(EngineError::Gpu(msg)) => assert!(msg.starts_with("bad buffer"), "{msg}"),
            other => panic!("expected a GPU error, got {:?}", other.map(|_| ())),
        }
        // The device stays usable and a clean scope reports nothing.
        assert!(ctx
            .scoped("good buffer", || ctx.buffer(
                "ok",
                64,
                wgpu::BufferUsages::STORAGE
            ))
            .is_ok());
    }

    #[test]
    fn new_buffers_hold_garbage_in_test_builds() {
        let Some(ctx) = context() else { return };
        let buf = ctx.buffer(
            "garbage",
            256,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let staging = ctx.buffer("staging", 256, wgpu::BufferUsages::MAP_READ);
        let enc = ctx.device.create_command_encoder(&Default::default());
        let all_ff = ctx
            .read_back(enc, &buf, &staging, 256, |b| b.iter().all(|&x| x == 0xFF))
            .unwrap();
        assert!(all_ff);
    }

    #[test]
    fn dispatch_tiles_cover_every_item_within_the_limit() {
        assert_eq!(tiles(64, 64, 65_535), (1, 1));
        assert_eq!(tiles(65, 64, 65_535), (2, 1));
        assert_eq!(tiles(65_535 * 64 + 1, 64, 65_535), (65_535, 2));
        let (x, y) = tiles(1000 * 64, 64, 7);
        assert_eq!((x, y), (7, 143));
        assert!(x as u64 * y as u64 >= 1000);
    }
}
