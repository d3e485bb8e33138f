//! The wgpu side of the GPU engine: adapter choice, device limits, error scopes, buffers
//! and read-back. Kernels' launchers (`stats.rs`, ...) use only what is here.

use super::super::EngineError;
use std::sync::mpsc;
use std::sync::{Arc, Mutex};

/// A device, its queue and what the engine needs to know about them. A clone shares the
/// device (wgpu's handles are shared), so that two engines of one run use one device.
#[derive(Clone)]
pub struct Context {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    pub limits: wgpu::Limits,
    /// Whether the device runs f64 in shaders (`SHADER_F64`, requested where the adapter
    /// has it): the edge fit's kernel needs it.
    pub f64: bool,
    /// Whether storage buffers can be created mapped for writing (`MAPPABLE_PRIMARY_BUFFERS`,
    /// requested on software adapters, whose device memory is the host's): the data
    /// uploaded once is then written in place, without a staging copy.
    pub map_primary: bool,
    /// Whether new buffers are filled with garbage ([`super::GpuOptions::fill_garbage`]).
    fill_garbage: bool,
    /// Errors that escaped every error scope, and device loss; checked after each batch
    /// so that they come back as `EngineError::Gpu` instead of the default handler's panic.
    stray: Arc<Mutex<Option<String>>>,
}

/// The phase of an adapter search, for [`EngineError::under_memory_limit`].
const SEARCH: &str = "looking for a GPU adapter";

/// Picks the adapter: the first whose name contains `name` (case-insensitive; the
/// commands' `WGPU_ADAPTER_NAME`) when given, else wgpu's default choice (`WGPU_POWER_PREF`
/// honoured); `WGPU_BACKEND` restricts the backends in both cases ([`default_backends`]).
/// Unlike `wgpu::util::initialize_adapter_from_env`, a name that matches nothing is an
/// error, not a panic.
pub fn pick_adapter(name: Option<&str>) -> Result<wgpu::Adapter, EngineError> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let backends = default_backends();
    if let Some(name) = name {
        log::info!(
            "adapter search: backends {backends:?}, the first named like WGPU_ADAPTER_NAME={name}"
        );
        let want = name.to_lowercase();
        let adapters = pollster::block_on(instance.enumerate_adapters(backends));
        log_adapters(&adapters);
        let names: Vec<String> = adapters.iter().map(|a| a.get_info().name).collect();
        let found = adapters
            .into_iter()
            .find(|a| a.get_info().name.to_lowercase().contains(&want))
            .ok_or_else(|| {
                let e = EngineError::NoAdapter(format!(
                    "WGPU_ADAPTER_NAME={name} matches none of [{}]",
                    names.join(", ")
                ));
                if names.is_empty() {
                    e.under_memory_limit(SEARCH)
                } else {
                    e
                }
            });
        if let Ok(a) = &found {
            log::info!("adapter picked: {}", describe(&a.get_info()));
        }
        return found;
    }
    let options = wgpu::RequestAdapterOptions {
        power_preference: wgpu::PowerPreference::from_env()
            .unwrap_or(wgpu::PowerPreference::HighPerformance),
        ..Default::default()
    };
    log::info!(
        "adapter search: backends {backends:?}, wgpu's choice for {:?}",
        options.power_preference
    );
    let found = pollster::block_on(instance.request_adapter(&options))
        .map_err(|e| EngineError::NoAdapter(e.to_string()).under_memory_limit(SEARCH));
    match &found {
        Ok(a) => log::info!("adapter picked: {}", describe(&a.get_info())),
        Err(e) => log::info!("adapter search found none: {e}"),
    }
    found
}

/// The adapter at the PCI address `bus` (the GPU a scheduler bound to the job;
/// [`super::GpuSetup::adapter_pci_bus_id`]); `WGPU_BACKEND` restricts the backends.
pub fn pick_adapter_at(bus: &str) -> Result<wgpu::Adapter, EngineError> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let backends = default_backends();
    log::info!("adapter search: backends {backends:?}, the one at PCI address {bus}");
    let adapters = pollster::block_on(instance.enumerate_adapters(backends));
    log_adapters(&adapters);
    let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
    let i = find_pci_bus_id(&infos, bus).map_err(|e| {
        let e = EngineError::NoAdapter(e.to_string());
        if infos.is_empty() {
            e.under_memory_limit(SEARCH)
        } else {
            e
        }
    })?;
    log::info!("adapter picked: {}", describe(&infos[i]));
    Ok(adapters.into_iter().nth(i).expect("an index of the list"))
}

/// A PCI address `domain:bus:device.function` in hex as numbers; the domain may be
/// missing (0) or as wide as nvidia-smi writes it (`00000000:65:00.0`).
pub fn parse_pci_bus_id(s: &str) -> Option<[u32; 4]> {
    let (rest, function) = s.trim().rsplit_once('.')?;
    let parts: Vec<&str> = rest.split(':').collect();
    let (domain, bus, device) = match parts[..] {
        [d, b, v] => (d, b, v),
        [b, v] => ("0", b, v),
        _ => return None,
    };
    let hex = |x: &str| u32::from_str_radix(x, 16).ok();
    Some([hex(domain)?, hex(bus)?, hex(device)?, hex(function)?])
}

/// Why `LINEGS_GPU_PCI_BUS_ID` names no adapter ([`find_pci_bus_id`]).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PciBusError {
    /// The value is not a PCI address.
    #[error("LINEGS_GPU_PCI_BUS_ID={0}: expected a PCI address domain:bus:device.function in hex, e.g. 0000:65:00.0")]
    Malformed(String),
    /// No adapter is at that address; `seen` lists each adapter and its address.
    #[error("LINEGS_GPU_PCI_BUS_ID={bus} matches none of [{seen}]")]
    NoMatch { bus: String, seen: String },
}

/// The index of the adapter among `infos` at the PCI address `bus`, or why none is.
pub fn find_pci_bus_id(infos: &[wgpu::AdapterInfo], bus: &str) -> Result<usize, PciBusError> {
    let want = parse_pci_bus_id(bus).ok_or_else(|| PciBusError::Malformed(bus.to_string()))?;
    infos
        .iter()
        .position(|i| parse_pci_bus_id(&i.device_pci_bus_id) == Some(want))
        .ok_or_else(|| {
            let seen: Vec<String> = infos
                .iter()
                .map(|i| {
                    let at = if i.device_pci_bus_id.is_empty() {
                        "no PCI address"
                    } else {
                        &i.device_pci_bus_id
                    };
                    format!("{} at {at}", i.name)
                })
                .collect();
            PciBusError::NoMatch {
                bus: bus.to_string(),
                seen: seen.join(", "),
            }
        })
}

/// One adapter in a line of the log: name, type, backend, driver, PCI ids.
pub fn describe(i: &wgpu::AdapterInfo) -> String {
    format!(
        "{} ({:?}, {:?}; driver {} {}; vendor {:#06x}, device {:#06x}; PCI {})",
        i.name,
        i.device_type,
        i.backend,
        i.driver,
        i.driver_info,
        i.vendor,
        i.device,
        if i.device_pci_bus_id.is_empty() {
            "-"
        } else {
            &i.device_pci_bus_id
        }
    )
}

/// Every adapter found, at `debug` (`RUST_LOG=debug`).
fn log_adapters(adapters: &[wgpu::Adapter]) {
    log::debug!("adapters found: {}", adapters.len());
    for (k, a) in adapters.iter().enumerate() {
        log::debug!("adapter {k}: {}", describe(&a.get_info()));
    }
}

/// `WGPU_BACKEND`, else the primary backends (Vulkan, Metal, DX12): probing OpenGL/EGL as
/// well costs tens of milliseconds at every start and gives no adapter the engine wants
/// (`WGPU_BACKEND=gl` still asks for it).
fn default_backends() -> wgpu::Backends {
    wgpu::Backends::from_env().unwrap_or(wgpu::Backends::PRIMARY)
}

/// Every adapter wgpu offers (`WGPU_BACKEND` restricts the backends), for `--backend auto`.
pub fn enumerate_adapters() -> Vec<wgpu::Adapter> {
    let instance =
        wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle_from_env());
    let backends = default_backends();
    log::info!("adapter search: backends {backends:?}, every adapter (--backend auto)");
    let adapters = pollster::block_on(instance.enumerate_adapters(backends));
    log_adapters(&adapters);
    adapters
}

impl Context {
    /// Opens a device on `adapter` with the limits the engine needs raised to what the
    /// adapter offers: large storage bindings, buffers and textures, up to 8 storage buffers
    /// per stage; on a software adapter also [`Context::map_primary`], unless
    /// `mapped_uploads` is false (every upload then goes through the queue's staging
    /// memory, as on a hardware adapter). With `fill_garbage`, [`Context::buffer`] fills
    /// each new buffer with 0xFF bytes.
    pub fn new(
        adapter: &wgpu::Adapter,
        mapped_uploads: bool,
        fill_garbage: bool,
    ) -> Result<Context, EngineError> {
        let offered = adapter.limits();
        let mut limits = wgpu::Limits::downlevel_defaults();
        limits.max_storage_buffer_binding_size = offered.max_storage_buffer_binding_size;
        limits.max_buffer_size = offered.max_buffer_size;
        limits.max_storage_buffers_per_shader_stage =
            offered.max_storage_buffers_per_shader_stage.min(8);
        limits.max_compute_workgroups_per_dimension = offered.max_compute_workgroups_per_dimension;
        limits.max_texture_dimension_2d = offered.max_texture_dimension_2d;
        if limits.max_texture_dimension_2d < super::layout::STORE_W {
            return Err(EngineError::Gpu(format!(
                "adapter {} offers 2D textures of {} texels a side, the point store needs {}",
                adapter.get_info().name,
                limits.max_texture_dimension_2d,
                super::layout::STORE_W
            )));
        }
        if limits.max_storage_buffers_per_shader_stage < 7 {
            return Err(EngineError::Gpu(format!(
                "adapter {} offers {} storage buffers per shader stage, the kernels need 7",
                adapter.get_info().name,
                limits.max_storage_buffers_per_shader_stage
            )));
        }
        let downlevel = adapter.get_downlevel_capabilities();
        if !downlevel
            .flags
            .contains(wgpu::DownlevelFlags::INDIRECT_EXECUTION)
        {
            return Err(EngineError::Gpu(format!(
                "adapter {} cannot dispatch indirectly, which the kernels need",
                adapter.get_info().name
            )));
        }
        let f64 = adapter.features().contains(wgpu::Features::SHADER_F64);
        let map_primary = mapped_uploads
            && adapter.get_info().device_type == wgpu::DeviceType::Cpu
            && adapter
                .features()
                .contains(wgpu::Features::MAPPABLE_PRIMARY_BUFFERS);
        let mut features = wgpu::Features::empty();
        if f64 {
            features |= wgpu::Features::SHADER_F64;
        }
        if map_primary {
            features |= wgpu::Features::MAPPABLE_PRIMARY_BUFFERS;
        }
        let desc = wgpu::DeviceDescriptor {
            label: Some("linegs"),
            required_features: features,
            required_limits: limits.clone(),
            ..Default::default()
        };
        let (device, queue) = pollster::block_on(adapter.request_device(&desc)).map_err(|e| {
            EngineError::Gpu(format!("cannot open the device: {e}")).under_memory_limit(&format!(
                "opening the GPU device {}",
                adapter.get_info().name
            ))
        })?;
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
            f64,
            map_primary,
            fill_garbage,
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
            return Err(match e {
                wgpu::Error::OutOfMemory { .. } => EngineError::OutOfMemory {
                    phase: what.to_string(),
                    why: format!("the GPU device's memory is full ({e})"),
                },
                _ => EngineError::Gpu(format!("{what}: {e}")),
            });
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

    /// A storage buffer of `size` bytes (a multiple of 4, not 0) whose contents `fill`
    /// writes once: in place where the device allows it ([`Self::map_primary`]), else into
    /// the queue's staging memory, copied over at the next submit.
    pub fn filled_buffer(
        &self,
        label: &str,
        size: u64,
        fill: impl FnOnce(wgpu::WriteOnly<'_, [u8]>),
    ) -> wgpu::Buffer {
        let usage = wgpu::BufferUsages::STORAGE;
        if self.map_primary {
            let buf = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size,
                usage: usage | wgpu::BufferUsages::MAP_WRITE,
                mapped_at_creation: true,
            });
            if let Ok(mut view) = buf.slice(..).get_mapped_range_mut() {
                fill(view.slice(..));
            }
            buf.unmap();
            return buf;
        }
        let buf = self.buffer(label, size, usage);
        // `None`: a validation error, which the caller's scope reports.
        if let Some(mut view) =
            std::num::NonZeroU64::new(size).and_then(|s| self.queue.write_buffer_with(&buf, 0, s))
        {
            fill(view.slice(..));
        }
        buf
    }

    /// A texture of `points` texels of 16 bytes (`Rgba32Float`), `STORE_W` a row (the last
    /// row padded), whose contents `fill(first, dst)` writes: the texels `first..` into
    /// `dst`, the mapped memory of a staging buffer of at most 256 rows (32 MiB), copied
    /// into the texture at a submit of its own (so that each staging buffer can go as soon
    /// as its copy is done).
    pub fn filled_texture(
        &self,
        label: &str,
        points: usize,
        fill: impl FnMut(usize, wgpu::WriteOnly<'_, [u8]>),
    ) -> wgpu::Texture {
        // 32 MiB of staging memory at a time.
        self.filled_texture_by(label, points, 256, fill)
    }

    /// [`Self::filled_texture`] with staging buffers of `upload_rows` rows.
    fn filled_texture_by(
        &self,
        label: &str,
        points: usize,
        upload_rows: u32,
        mut fill: impl FnMut(usize, wgpu::WriteOnly<'_, [u8]>),
    ) -> wgpu::Texture {
        use super::layout::STORE_W;
        let w = STORE_W as usize;
        let rows = store_rows(points);
        let texture = self.texture(
            label,
            rows,
            wgpu::TextureFormat::Rgba32Float,
            wgpu::TextureUsages::COPY_SRC,
        );
        for row in (0..rows).step_by(upload_rows.max(1) as usize) {
            let height = upload_rows.max(1).min(rows - row);
            let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: height as u64 * w as u64 * 16,
                usage: wgpu::BufferUsages::MAP_WRITE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: true,
            });
            let first = row as usize * w;
            let n = (points - first.min(points)).min(height as usize * w);
            if let Ok(mut view) = staging.slice(..).get_mapped_range_mut() {
                if n > 0 {
                    fill(first, view.slice(..n * 16));
                }
            }
            staging.unmap();
            let mut enc = self.encoder();
            enc.copy_buffer_to_texture(
                wgpu::TexelCopyBufferInfo {
                    buffer: &staging,
                    layout: wgpu::TexelCopyBufferLayout {
                        offset: 0,
                        bytes_per_row: Some(STORE_W * 16),
                        rows_per_image: Some(height),
                    },
                },
                wgpu::TexelCopyTextureInfo {
                    texture: &texture,
                    mip_level: 0,
                    origin: wgpu::Origin3d { x: 0, y: row, z: 0 },
                    aspect: wgpu::TextureAspect::All,
                },
                wgpu::Extent3d {
                    width: STORE_W,
                    height,
                    depth_or_array_layers: 1,
                },
            );
            self.queue.submit([enc.finish()]);
        }
        texture
    }

    /// A texture of `STORE_W` texels a row and `rows` rows, which kernels read and copies
    /// write (and whatever `usage` adds).
    fn texture(
        &self,
        label: &str,
        rows: u32,
        format: wgpu::TextureFormat,
        usage: wgpu::TextureUsages,
    ) -> wgpu::Texture {
        self.device.create_texture(&wgpu::TextureDescriptor {
            label: Some(label),
            size: wgpu::Extent3d {
                width: super::layout::STORE_W,
                height: rows,
                depth_or_array_layers: 1,
            },
            mip_level_count: 1,
            sample_count: 1,
            dimension: wgpu::TextureDimension::D2,
            format,
            usage: wgpu::TextureUsages::TEXTURE_BINDING | wgpu::TextureUsages::COPY_DST | usage,
            view_formats: &[],
        })
    }

    /// A storage buffer of `size` bytes. With [`super::GpuOptions::fill_garbage`] it is
    /// filled with 0xFF bytes, so a kernel that reads memory it never wrote sees NaNs and
    /// huge counts.
    pub fn buffer(&self, label: &str, size: u64, usage: wgpu::BufferUsages) -> wgpu::Buffer {
        let size = size.max(4).next_multiple_of(4);
        let buf = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size,
            usage: usage | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        if self.fill_garbage && !usage.contains(wgpu::BufferUsages::MAP_READ) {
            let garbage = vec![0xFFu8; size as usize];
            self.queue.write_buffer(&buf, 0, &garbage);
        }
        buf
    }

    /// Submits `encoder` with a copy of the first `size` bytes of `src` into `staging` (a
    /// MAP_READ buffer of at least `size` bytes), waits, and hands the bytes to `f` where
    /// they lie, without copying them out.
    #[cfg(test)]
    pub fn read_back<R>(
        &self,
        mut encoder: wgpu::CommandEncoder,
        src: &wgpu::Buffer,
        staging: &wgpu::Buffer,
        size: u64,
        f: impl FnOnce(&[u8]) -> R,
    ) -> Result<R, EngineError> {
        if size > 0 {
            encoder.copy_buffer_to_buffer(src, 0, staging, 0, size);
        }
        Ok(self.submit_and_map(encoder, staging, size, f)?.0)
    }

    /// Submits `encoder` (which copies what the host needs into `staging`, a MAP_READ
    /// buffer), waits for the device, and hands the first `size` bytes of `staging` to `f`
    /// where they lie. Returns `f`'s result and the seconds spent waiting.
    pub fn submit_and_map<R>(
        &self,
        encoder: wgpu::CommandEncoder,
        staging: &wgpu::Buffer,
        size: u64,
        f: impl FnOnce(&[u8]) -> R,
    ) -> Result<(R, f64), EngineError> {
        let (bytes, waited) = self.submit_mapped(encoder, staging, size)?;
        Ok((f(&bytes), waited))
    }

    /// [`Self::submit_and_map`] that hands back the first `size` bytes of `staging`
    /// themselves, still mapped: the host reads them in place for as long as it holds
    /// them, and `staging` is unmapped when they are dropped (before its next use).
    pub fn submit_mapped(
        &self,
        encoder: wgpu::CommandEncoder,
        staging: &wgpu::Buffer,
        size: u64,
    ) -> Result<(Mapped, f64), EngineError> {
        let t = std::time::Instant::now();
        self.queue.submit([encoder.finish()]);
        if size == 0 {
            return Ok((Mapped::default(), t.elapsed().as_secs_f64()));
        }
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
        let waited = t.elapsed().as_secs_f64();
        wake_workers();
        let view = match slice.get_mapped_range() {
            Ok(v) => v,
            Err(e) => {
                staging.unmap();
                return Err(EngineError::Gpu(format!("read-back failed: {e}")));
            }
        };
        let len = view.len();
        let mapped = Mapped {
            view: Some(Arc::new(MappedView {
                view: Some(view),
                buffer: staging.clone(),
            })),
            range: 0..len,
        };
        Ok((mapped, waited))
    }

    /// A fresh command encoder.
    pub fn encoder(&self) -> wgpu::CommandEncoder {
        self.device
            .create_command_encoder(&wgpu::CommandEncoderDescriptor::default())
    }

    /// Compute pipeline of entry point `entry`, with its layout derived from the shader.
    pub fn pipeline(&self, label: &str, wgsl: &str, entry: &str) -> wgpu::ComputePipeline {
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
                entry_point: Some(entry),
                compilation_options: Default::default(),
                cache: None,
            })
    }

    /// Bind group 0 of `pipeline` with `buffers` bound in order (binding 0, 1, ...).
    /// A bind group holds the buffers alive, so batches may drop theirs afterwards.
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

/// Rows of a point-store texture of `points` texels: enough for them, at least 3 and
/// never a power of two. Drivers may specialise a kernel on whether a texture's sides are
/// powers of two (llvmpipe does, and generates its machine code at the first dispatch
/// with each new shape class): keeping the class fixed lets the kernels compiled at the
/// device's opening (and its warm-up on a tiny grid) serve every store.
pub fn store_rows(points: usize) -> u32 {
    let rows = points.div_ceil(super::layout::STORE_W as usize).max(3) as u32;
    rows + rows.is_power_of_two() as u32
}

/// A texture of `STORE_W` texels a row holding a batch's queries ([`GQuery`]'s words,
/// `QUERY_TEXELS` texels each), kept between batches and grown on demand like
/// [`Reusable`]; its rows follow [`store_rows`], so that its shape class never changes.
///
/// [`GQuery`]: super::layout::GQuery
#[derive(Default)]
pub struct QueryTexture {
    tex: Option<(wgpu::Texture, wgpu::TextureView)>,
}

impl QueryTexture {
    /// The texture, grown first where `n` queries do not fit.
    pub fn holding(&mut self, ctx: &Context, n: usize) -> &wgpu::Texture {
        use super::layout::{QUERY_TEXELS, STORE_W};
        let w = STORE_W as usize;
        let texels = n * QUERY_TEXELS as usize;
        let rows = texels.div_ceil(w) as u32;
        if self.tex.as_ref().is_none_or(|(t, _)| t.height() < rows) {
            // Grow by half again, like the buffers.
            let grown = self
                .tex
                .as_ref()
                .map_or(0, |(t, _)| t.height() as usize * 3 / 2);
            // (Queries per sub-batch are bounded far below the largest side.)
            let most = ctx.limits.max_texture_dimension_2d as usize - 2;
            let tex = ctx.texture(
                "queries",
                store_rows(texels.max(grown.min(most) * w)),
                wgpu::TextureFormat::Rgba32Uint,
                wgpu::TextureUsages::empty(),
            );
            let view = tex.create_view(&wgpu::TextureViewDescriptor::default());
            self.tex = Some((tex, view));
        }
        &self.tex.as_ref().expect("just made").0
    }

    /// Writes `queries` at the texture's start (grown first when they do not fit) through
    /// the queue: where [`Uploads::stage`] could not map its buffer.
    pub fn write(&mut self, ctx: &Context, queries: &[super::layout::GQuery]) {
        let texels = queries.len() * super::layout::QUERY_TEXELS as usize;
        let tex = self.holding(ctx, queries.len());
        let bytes: &[u8] = bytemuck::cast_slice(queries);
        for (y, extent, from) in row_pieces(texels as u32) {
            ctx.queue.write_texture(
                texture_at(tex, y),
                &bytes[from as usize..],
                wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some(ROW_BYTES),
                    rows_per_image: Some(extent.height),
                },
                extent,
            );
        }
    }

    /// The texture as last written.
    pub fn view(&self) -> Option<&wgpu::TextureView> {
        self.tex.as_ref().map(|(_, v)| v)
    }
}

/// A batch's uploads (its queries, the fit's frames) through one mapped staging buffer
/// kept between batches: every thread copies a part of them into memory touched before
/// (`resources::par_copy`; wgpu zeroes the buffer only when it grows), and the batch's
/// encoder copies them into place before its pass ([`Uploads::record`]).
/// `Queue::write_texture` and `write_buffer` copy on one thread into a new staging
/// allocation each call: the uploads of a run at 10^6 x 10^4 took 4.5 ms of host time on
/// one thread of the development machine and 4.3 ms on two that way, 5.4 and 4.0 ms so
/// (probes, not committed; the difference is the polls of the mapping and the copies'
/// split).
#[derive(Default)]
pub struct Uploads {
    buf: Option<wgpu::Buffer>,
    /// Copies from `buf` that the next batch's encoder records.
    pending: Vec<(u64, Target)>,
}

/// Where a staged upload goes.
enum Target {
    Buffer(wgpu::Buffer, u64),
    /// The texture and the texels (from its start, `STORE_W` a row).
    Texture(wgpu::Texture, u32),
}

impl Uploads {
    /// Stages `parts` (each its destination and bytes) at 256-byte offsets; `false` (and
    /// nothing staged) where the staging buffer could not be mapped, for the caller to
    /// write them otherwise.
    pub fn stage(&mut self, ctx: &Context, parts: &[(Upload, Source)]) -> bool {
        // Copies staged for a batch that never recorded them (it failed) are dropped: this
        // stage overwrites their bytes.
        self.pending.clear();
        let parts: Vec<&(Upload, Source)> = parts.iter().filter(|p| p.1.len() > 0).collect();
        let place = |n: usize| (n as u64).next_multiple_of(256);
        let total: u64 = parts.iter().map(|(_, b)| place(b.len())).sum();
        if total == 0 {
            return true;
        }
        if self.buf.as_ref().is_none_or(|b| b.size() < total) {
            let grown = self.buf.as_ref().map_or(0, |b| b.size() + b.size() / 2);
            self.buf = Some(ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("uploads"),
                size: total.max(grown).min(ctx.limits.max_buffer_size).max(total),
                usage: wgpu::BufferUsages::MAP_WRITE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }));
        }
        let buf = self.buf.as_ref().expect("just made");
        // Every batch before this one was waited for: the buffer is idle, and the map
        // completes at the first poll.
        let slice = buf.slice(..total);
        let (tx, rx) = mpsc::channel();
        slice.map_async(wgpu::MapMode::Write, move |r| {
            let _ = tx.send(r);
        });
        let mapped = ctx.device.poll(wgpu::PollType::wait_indefinitely()).is_ok()
            && rx.recv().is_ok_and(|r| r.is_ok());
        if !mapped {
            return false;
        }
        let Ok(mut view) = slice.get_mapped_range_mut() else {
            buf.unmap();
            return false;
        };
        let mut at = 0u64;
        for (to, from) in parts {
            let n = from.len() as u64;
            let dst = view.slice(at as usize..(at + n) as usize);
            match *from {
                Source::Bytes(bytes) => super::resources::par_copy(dst, bytes),
                Source::Fill { unit, fill, .. } => par_fill(dst, unit, fill),
            }
            let target = match to {
                Upload::Buffer(b) => Target::Buffer((*b).clone(), n),
                Upload::Texture(t) => Target::Texture((*t).clone(), (n / 16) as u32),
            };
            self.pending.push((at, target));
            at += place(from.len());
        }
        drop(view);
        buf.unmap();
        true
    }

    /// Records the staged copies into `enc` (before anything that reads them).
    pub fn record(&mut self, enc: &mut wgpu::CommandEncoder) {
        let Some(buf) = self.buf.as_ref() else {
            return;
        };
        for (at, target) in self.pending.drain(..) {
            match target {
                Target::Buffer(dst, n) => enc.copy_buffer_to_buffer(buf, at, &dst, 0, n),
                Target::Texture(tex, texels) => {
                    for (y, extent, from) in row_pieces(texels) {
                        enc.copy_buffer_to_texture(
                            wgpu::TexelCopyBufferInfo {
                                buffer: buf,
                                layout: wgpu::TexelCopyBufferLayout {
                                    offset: at + from,
                                    bytes_per_row: Some(ROW_BYTES),
                                    rows_per_image: Some(extent.height),
                                },
                            },
                            texture_at(&tex, y),
                            extent,
                        );
                    }
                }
            }
        }
    }
}

/// Bytes of a row of a `STORE_W`-wide texture of 16-byte texels.
const ROW_BYTES: u32 = super::layout::STORE_W * 16;

/// The pieces that put `texels` packed texels at the start of a `STORE_W`-wide texture:
/// the whole rows, then what is left in one more row; each its first row, its extent and
/// where its bytes start among the packed ones.
fn row_pieces(texels: u32) -> impl Iterator<Item = (u32, wgpu::Extent3d, u64)> {
    let w = super::layout::STORE_W;
    let (full, rest) = (texels / w, texels % w);
    [(0, w, full), (full, rest, 1)]
        .into_iter()
        .filter(|&(_, width, height)| width > 0 && height > 0)
        .map(|(y, width, height)| {
            let extent = wgpu::Extent3d {
                width,
                height,
                depth_or_array_layers: 1,
            };
            (y, extent, u64::from(y) * u64::from(ROW_BYTES))
        })
}

/// Row `y` of `texture` (from its first column), as a copy's destination.
fn texture_at(texture: &wgpu::Texture, y: u32) -> wgpu::TexelCopyTextureInfo<'_> {
    wgpu::TexelCopyTextureInfo {
        texture,
        mip_level: 0,
        origin: wgpu::Origin3d { x: 0, y, z: 0 },
        aspect: wgpu::TextureAspect::All,
    }
}

/// What one part of [`Uploads::stage`] writes: bytes to copy, or `len` bytes that
/// `fill(at, dst)` writes itself, piece by piece in parallel (`dst` the piece, `at` its
/// offset in the part, both multiples of `unit` bytes).
#[derive(Clone, Copy)]
pub enum Source<'a> {
    Bytes(&'a [u8]),
    Fill {
        len: usize,
        unit: usize,
        fill: &'a Fill<'a>,
    },
}

/// [`Source::Fill`]'s writer.
pub type Fill<'a> = dyn Fn(usize, wgpu::WriteOnly<'_, [u8]>) + Sync + 'a;

impl Source<'_> {
    /// Bytes the part writes.
    pub fn len(&self) -> usize {
        match self {
            Source::Bytes(b) => b.len(),
            Source::Fill { len, .. } => *len,
        }
    }
}

/// Bytes of a piece of [`par_fill`]: a whole number of queries (96 bytes) and of texels
/// (16), small enough that a batch of a few thousand queries is shared by the threads.
pub const FILL_PIECE: usize = 96 * 512;

/// `fill` over `dst` piece by piece in parallel ([`Source::Fill`]; `unit` divides
/// [`FILL_PIECE`]).
fn par_fill(dst: wgpu::WriteOnly<'_, [u8]>, unit: usize, fill: &Fill<'_>) {
    use rayon::prelude::*;
    assert!(
        unit > 0 && FILL_PIECE.is_multiple_of(unit),
        "a fill's unit divides its pieces"
    );
    // (Pieces of a fixed size: wgpu's `WriteOnly` of an unsized slice is not `Send`.)
    let (whole, tail) = dst.into_chunks::<FILL_PIECE>();
    let pieces: Vec<wgpu::WriteOnly<'_, [u8; FILL_PIECE]>> = whole.into_iter().collect();
    let n = pieces.len();
    pieces
        .into_par_iter()
        .enumerate()
        .for_each(|(k, p)| fill(k * FILL_PIECE, p.into()));
    if !tail.is_empty() {
        fill(n * FILL_PIECE, tail);
    }
}

/// The destination of one part of [`Uploads::stage`]: a buffer (from its start), or a
/// texture of `STORE_W` texels a row (16 bytes a texel, from its first row).
#[derive(Clone, Copy)]
pub enum Upload<'a> {
    Buffer(&'a wgpu::Buffer),
    Texture(&'a wgpu::Texture),
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

/// Binds the first `size` bytes of `buf` (at least 4).
pub fn head(buf: &wgpu::Buffer, size: u64) -> wgpu::BindingResource<'_> {
    wgpu::BindingResource::Buffer(wgpu::BufferBinding {
        buffer: buf,
        offset: 0,
        size: std::num::NonZeroU64::new(size.max(4).next_multiple_of(4)),
    })
}

/// Bytes read back from the device where they lie, in a staging buffer that stays mapped
/// until they are dropped ([`Context::submit_mapped`]): a batch's answers are read from
/// there, not from a copy (a copy was fresh memory each batch, 22 MB of member records
/// over the bench scene's decisions at 10^6 Gaussians).
#[derive(Default)]
pub struct Mapped {
    /// The mapping (none for an empty read-back), shared by the parts taken of it
    /// ([`Mapped::part`]).
    view: Option<Arc<MappedView>>,
    /// The part of the view these bytes are.
    range: std::ops::Range<usize>,
}

/// A staging buffer's mapped range, unmapped when the last [`Mapped`] of it is dropped.
struct MappedView {
    /// (Taken only by `drop`.)
    view: Option<wgpu::BufferView>,
    buffer: wgpu::Buffer,
}

impl Drop for MappedView {
    fn drop(&mut self) {
        // The view first: a buffer with a view still open cannot be unmapped.
        drop(self.view.take());
        self.buffer.unmap();
    }
}

impl Mapped {
    /// The bytes from `at` on (clamped to the end), still in place.
    pub fn from(mut self, at: usize) -> Mapped {
        self.range.start = (self.range.start + at).min(self.range.end);
        self
    }

    /// The bytes `range` of these (clamped to their end), in place: the mapping stays
    /// until both are dropped.
    pub fn part(&self, range: std::ops::Range<usize>) -> Mapped {
        let end = (self.range.start + range.end).min(self.range.end);
        Mapped {
            view: self.view.clone(),
            range: (self.range.start + range.start).min(end)..end,
        }
    }
}

impl std::ops::Deref for Mapped {
    type Target = [u8];
    fn deref(&self) -> &[u8] {
        self.view
            .as_ref()
            .and_then(|v| v.view.as_ref())
            .map_or(&[], |v| &v[self.range.clone()])
    }
}

/// Wakes the thread pool's workers (asleep through the device's work) without waiting
/// for them, so that they are awake when the host's answers start their parallel work:
/// the first parallel loop after a wait of some 100 ms took about 100 us more than
/// the loops after it on the development machine, the time the workers took to wake.
/// The host reads the batch's counters and flags meanwhile.
pub(super) fn wake_workers() {
    if rayon::current_num_threads() > 1 {
        rayon::spawn_broadcast(|_| {});
    }
}

/// `bytes` as a slice of `T`, in place when aligned (mapped memory always is).
pub fn pods<T: bytemuck::Pod>(bytes: &[u8]) -> std::borrow::Cow<'_, [T]> {
    match bytemuck::try_cast_slice(bytes) {
        Ok(s) => std::borrow::Cow::Borrowed(s),
        Err(_) => std::borrow::Cow::Owned(bytemuck::pod_collect_to_vec(bytes)),
    }
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

    /// A device (without mapped uploads: with them a software adapter accepts buffer
    /// usages that the validation test needs to be errors); without an adapter a failure,
    /// unless `LINEGS_SKIP_GPU_TESTS=1` (then `None`, with a notice).
    fn context() -> Option<Context> {
        let name = std::env::var("WGPU_ADAPTER_NAME").ok();
        match pick_adapter(name.as_deref()) {
            Ok(a) => Some(Context::new(&a, false, true).expect("device")),
            Err(e) if std::env::var("LINEGS_SKIP_GPU_TESTS").is_ok_and(|v| v == "1") => {
                eprintln!("SKIPPED (LINEGS_SKIP_GPU_TESTS=1): {e}");
                None
            }
            Err(e) => panic!("{e} (set LINEGS_SKIP_GPU_TESTS=1 to skip the GPU tests)"),
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
    fn new_buffers_hold_garbage_when_asked() {
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
    fn store_rows_hold_the_points_and_are_never_a_power_of_two() {
        let w = super::super::layout::STORE_W as usize;
        for n in [
            0,
            1,
            w - 1,
            w,
            2 * w,
            3 * w + 1,
            4 * w,
            4 * w + 1,
            1 << 20,
            10_000_000,
        ] {
            let rows = store_rows(n) as usize;
            assert!(rows * w >= n && rows >= 3, "{n}: {rows}");
            assert!(!rows.is_power_of_two(), "{n}: {rows}");
            // At most one row beyond what the points need (or the three of a tiny store).
            assert!(rows <= n.div_ceil(w).max(3) + 1, "{n}: {rows}");
        }
    }

    #[test]
    fn a_texture_uploaded_in_pieces_holds_every_point_where_the_kernels_look() {
        let Some(ctx) = context() else { return };
        let w = super::super::layout::STORE_W as usize;
        // Three whole rows and five points: four rows, a power of two, so five rows,
        // uploaded one row per staging buffer.
        let n = 3 * w + 5;
        let value = |i: usize| [i as f32, -(i as f32), 0.5 * i as f32, (i % 7) as f32];
        let mut calls = Vec::new();
        let tex = ctx
            .scoped("upload", || {
                ctx.filled_texture_by("probe", n, 1, |first, mut dst| {
                    calls.push((first, dst.len() / 16));
                    let v: Vec<[f32; 4]> = (first..first + dst.len() / 16).map(value).collect();
                    dst.copy_from_slice(bytemuck::cast_slice(&v));
                })
            })
            .unwrap();
        assert_eq!(calls, [(0, w), (w, w), (2 * w, w), (3 * w, 5)]);
        assert_eq!(tex.height(), 5);
        let bytes = (5 * w * 16) as u64;
        let out = ctx.buffer(
            "out",
            bytes,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let staging = ctx.buffer("staging", bytes, wgpu::BufferUsages::MAP_READ);
        let mut enc = ctx.encoder();
        enc.copy_texture_to_buffer(
            tex.as_image_copy(),
            wgpu::TexelCopyBufferInfo {
                buffer: &out,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: 0,
                    bytes_per_row: Some((w * 16) as u32),
                    rows_per_image: Some(5),
                },
            },
            tex.size(),
        );
        let got: Vec<[f32; 4]> = ctx
            .read_back(enc, &out, &staging, bytes, bytemuck::pod_collect_to_vec)
            .unwrap();
        // Point i at texel (i mod STORE_W, i / STORE_W), as eval.wgsl reads it.
        for i in 0..n {
            assert_eq!(got[(i / w) * w + i % w], value(i), "point {i}");
        }
    }

    #[test]
    fn every_query_field_comes_back_from_the_query_texture_as_the_host_wrote_it() {
        use super::super::layout::GQuery;
        let Some(ctx) = context() else { return };
        let n_words = std::mem::size_of::<GQuery>() / 4;
        // Word i of query j: distinct in every query and field, and a normal f32, so that
        // it passes through an f32 unchanged.
        let word = |j: u32, i: u32| 0x3F00_0000 + (j << 16) + (i << 8) + 1;
        let queries: Vec<GQuery> = (0..3)
            .map(|j| {
                let w: Vec<u32> = (0..n_words as u32).map(|i| word(j, i)).collect();
                bytemuck::pod_read_unaligned(bytemuck::cast_slice(&w))
            })
            .collect();
        // A kernel that reads query 1 with the generated accessor and writes each field
        // back at its own word.
        let mut kernel = String::from(
            "@group(0) @binding(1) var queries: texture_2d<u32>;\n\
             @group(0) @binding(2) var<storage, read_write> out: array<u32>;\n\
             @compute @workgroup_size(1)\nfn main() {\n    let q = query_of(queries, 1u);\n",
        );
        for &(name, offset) in GQuery::FIELDS {
            kernel += &format!("    out[{}] = bitcast<u32>(q.{name});\n", offset / 4);
        }
        kernel += "}\n";
        let pipeline = ctx.pipeline("query_of", &super::super::kernel_source(&kernel), "main");
        let mut tex = QueryTexture::default();
        tex.write(&ctx, &queries);
        let bytes = (n_words * 4) as u64;
        let out = ctx.buffer(
            "out",
            bytes,
            wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC,
        );
        let staging = ctx.buffer("staging", bytes, wgpu::BufferUsages::MAP_READ);
        let group = ctx.device.create_bind_group(&wgpu::BindGroupDescriptor {
            label: None,
            layout: &pipeline.get_bind_group_layout(0),
            entries: &[
                wgpu::BindGroupEntry {
                    binding: 1,
                    resource: wgpu::BindingResource::TextureView(tex.view().unwrap()),
                },
                wgpu::BindGroupEntry {
                    binding: 2,
                    resource: out.as_entire_binding(),
                },
            ],
        });
        let mut enc = ctx.encoder();
        {
            let mut pass = enc.begin_compute_pass(&Default::default());
            pass.set_pipeline(&pipeline);
            pass.set_bind_group(0, &group, &[]);
            pass.dispatch_workgroups(1, 1, 1);
        }
        let got: Vec<u32> = ctx
            .read_back(enc, &out, &staging, bytes, bytemuck::pod_collect_to_vec)
            .unwrap();
        let want: Vec<u32> = (0..n_words as u32).map(|i| word(1, i)).collect();
        assert_eq!(got, want);
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
