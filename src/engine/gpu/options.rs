//! The engine's options: size limits, where member lists and the edge fit run, which
//! batches the host answers, and what the device does when it opens.

#[allow(unused_imports)] // (doc links)
use super::{Engine, GpuDevice};

/// Size limits of the engine. The defaults suit every adapter; tests lower them to cover
/// the splitting paths with small data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Largest point-store part and per-batch buffer binding in bytes (16 per point);
    /// `None`: the device's `max_storage_buffer_binding_size`. Never above the device's
    /// limit. (The cell table is bound whole and only checked against the device.)
    pub max_binding_bytes: Option<u64>,
    /// Most work items per submit; a sub-batch needing more is split.
    pub max_items: usize,
    /// Most workgroups along x before a dispatch is tiled in 2D (65,535 in WebGPU).
    pub max_workgroups_x: u32,
    /// Most queries per sub-batch (bounds the per-query buffers).
    pub max_queries: usize,
    /// Where `--fit edge`'s ridge runs: on the device (`fit.wgsl`, in f64, over the
    /// member lists the batch leaves there) or as the host's step over member lists.
    pub fit: FitOn,
    /// Batches of at most this many queries are answered by the CPU engine's code over
    /// the same grid, on the host: a device round trip (submit, wait, read back) costs more
    /// than such a batch. 0 (the default here, so that tests exercise the kernels with
    /// any batch): never. The commands use [`SMALL_BATCH`].
    pub small_batch: usize,
    /// Where [`Engine::members`] lists are built (the edge fit, `--split-gaps`).
    pub members: MembersOn,
    /// Whether [`GpuDevice::open`] runs two small evaluation batches over a tiny grid of
    /// its own before it returns: drivers that generate a kernel's machine code at its
    /// first dispatch (lavapipe: about 40 ms for the first evaluation's kernels) then do
    /// that on the opening thread, which runs while the caller builds the grid, instead of
    /// in the first batch. The commands' choice; off here (tests open many engines).
    pub warm_up: bool,
    /// Whether, on a software adapter (whose device memory is the host's), the buffers
    /// uploaded once (cell table, point store) are created mapped and written in place
    /// instead of through the queue's staging memory and a copy (lavapipe: the first
    /// batch 20 ms shorter at 10^6 Gaussians). On by default; tests turn it off to run
    /// the staging path that hardware adapters take.
    pub mapped_uploads: bool,
}

/// Where the GPU engine builds per-point member lists.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum MembersOn {
    /// On the device (walk, exact test, compaction; the host measures each member in f64
    /// and sorts): the default here, so that tests exercise the kernels.
    #[default]
    Device,
    /// On the host, by the CPU engine's code over the same grid.
    Host,
    /// The device on a hardware adapter; the host on a software one (lavapipe, WARP,
    /// SwiftShader), whose "device" is the host's own cores: there the member passes and
    /// their readback cost about four times the host's walk (1.1 s against 0.3 s at 10^6
    /// Gaussians x 10^4 segments, README). The commands' choice.
    Auto,
}

/// Where the GPU engine runs the edge fit's ridge.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum FitOn {
    /// On the device where it can: an adapter with f64 in shaders (`SHADER_F64`: Vulkan
    /// on NVIDIA, AMD, lavapipe; not Metal), the plain ridge (no normals, no opacity
    /// weights) and the Gaussians' coordinates within one storage binding; the host's step
    /// otherwise. The default here, so that tests exercise the kernel.
    #[default]
    Device,
    /// The host's step over the member lists ([`GpuOptions::members`]).
    Host,
    /// The device on a hardware adapter, the host on a software one (on lavapipe the f64
    /// kernel runs on the host's own cores, slower than the host's step). The commands'
    /// choice.
    Auto,
}

/// The commands' [`GpuOptions::small_batch`]: the tail rounds of merge/join and crop ask
/// a few queries at a time, which the host answers in microseconds; a device round trip
/// costs a fraction of a millisecond on a real GPU (about one on lavapipe).
pub const SMALL_BATCH: usize = 16;

impl GpuOptions {
    /// The options the commands use: the defaults, with batches of at most
    /// [`SMALL_BATCH`] queries on the host (`LINEGS_GPU_SMALL_BATCH=N` sets another bound;
    /// 0 sends every batch to the device), member lists and the edge fit by adapter
    /// ([`MembersOn::Auto`], [`FitOn::Auto`]; `LINEGS_GPU_MEMBERS=device|host` and
    /// `LINEGS_GPU_FIT=device|host` choose).
    pub fn for_commands() -> Self {
        let small_batch = std::env::var("LINEGS_GPU_SMALL_BATCH")
            .ok()
            .and_then(|v| v.trim().parse().ok())
            .unwrap_or(SMALL_BATCH);
        let fit = match std::env::var("LINEGS_GPU_FIT").as_deref() {
            Ok("device") => FitOn::Device,
            Ok("host") => FitOn::Host,
            _ => FitOn::Auto,
        };
        let members = match std::env::var("LINEGS_GPU_MEMBERS").as_deref() {
            Ok("device") => MembersOn::Device,
            Ok("host") => MembersOn::Host,
            _ => MembersOn::Auto,
        };
        GpuOptions {
            small_batch,
            fit,
            members,
            warm_up: true,
            ..Default::default()
        }
    }
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            max_binding_bytes: None,
            max_items: 1 << 24,
            max_workgroups_x: 65_535,
            max_queries: 1 << 16,
            fit: FitOn::Device,
            small_batch: 0,
            members: MembersOn::Device,
            warm_up: false,
            mapped_uploads: true,
        }
    }
}
