//! The engine's options: size limits, where member lists and the edge fit run, which
//! batches the host answers, and what the device does when it opens.

#[allow(unused_imports)] // (doc links)
use super::{Engine, GpuDevice};

/// Size limits of the engine. The defaults suit every adapter; tests lower them to cover
/// the splitting paths with small data.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GpuOptions {
    /// Largest point-store part in bytes (16 per point); `None`: what one texture of the
    /// device holds ([`STORE_W`](super::layout::STORE_W) points a row, as many rows as
    /// the device's largest texture side). Tests lower it to split the store. (The cell
    /// table and the per-batch buffers are bound whole and checked against the device's
    /// binding limit.)
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
    /// Once the device fit's iterations have at most this many segments still moving,
    /// the host takes those on to the end as the CPU engine's fit does (each
    /// neighbourhood gathered once, [`crate::engine::fit::finish_gathered`]): every
    /// iteration is a device round trip, and the last few carry a few dozen segments
    /// each (a fit of at most this many segments is the host's from its first step).
    /// 0 (the default here, so that tests run the kernel to the end): never. The
    /// commands use [`FIT_TAIL`].
    pub fit_tail: usize,
    /// Where [`Engine::members`] lists are built (the edge fit, `--split-gaps`), and so
    /// where [`Engine::extent`] walks (the end gaps: on the host with the lists, else on
    /// the device's member pass).
    pub members: MembersOn,
    /// Whether [`GpuDevice::open`] runs two small evaluation batches over a tiny grid of
    /// its own before it returns: drivers that generate a kernel's machine code at its
    /// first dispatch (lavapipe: about 40 ms for the first evaluation's kernels) then do
    /// that on the opening thread, which runs while the caller builds the grid, instead of
    /// in the first batch. The commands' choice; off here (tests open many engines).
    pub warm_up: bool,
    /// Whether, on a software adapter (whose device memory is the host's), the buffers
    /// uploaded once (cell table; the point store is a texture, always written through a
    /// staging buffer) are created mapped and written in place
    /// instead of through the queue's staging memory and a copy (lavapipe: the first
    /// batch 20 ms shorter at 10^6 Gaussians). On by default; tests turn it off to run
    /// the staging path that hardware adapters take, and so does
    /// `LINEGS_GPU_UPLOADS=staged` ([`GpuSetup::from_vars`]).
    pub mapped_uploads: bool,
    /// Whether every new buffer the kernels write is first filled with 0xFF bytes, so that
    /// a kernel that reads memory it never wrote sees NaNs and huge counts. On in debug
    /// builds; the commands turn it on with `LINEGS_GPU_GARBAGE` ([`GpuSetup::from_vars`]),
    /// the tests where `scripts/test.sh` sets that variable.
    pub fill_garbage: bool,
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

/// The commands' [`GpuOptions::fit_tail`]. On the bench scene at 10^6 Gaussians x 10^4
/// segments the device fit's iterations carried 10,000, 8,998, 7,011, 1,381 segments and
/// then 109, 43, 28, 25, 23, 22, 20 and 19: eight round trips for the last 109 segments,
/// whose 289 remaining steps the host takes in 0.5–0.65 ms on two threads (0.8–1.1 ms on
/// one), each segment's neighbourhood gathered once and every step in cache. At 10^7 x
/// 10^5 (100,000, 89,995, 70,261, 13,759, 1,294, then 474, ...) the host takes the last
/// 474 segments' 2,051 steps in 2.4 ms on two threads, where the device took the seven
/// round trips of iterations 6 to 12. The host's share stays a few milliseconds of one
/// thread.
pub const FIT_TAIL: usize = 1024;

impl GpuOptions {
    /// The options the commands use: the defaults, with batches of at most
    /// [`SMALL_BATCH`] queries on the host, member lists and the edge fit by adapter
    /// ([`MembersOn::Auto`], [`FitOn::Auto`]) and the device warmed up when it opens. The
    /// commands then apply their environment ([`GpuSetup::from_vars`]).
    pub fn for_commands() -> Self {
        GpuOptions {
            small_batch: SMALL_BATCH,
            fit_tail: FIT_TAIL,
            fit: FitOn::Auto,
            members: MembersOn::Auto,
            warm_up: true,
            ..Default::default()
        }
    }
}

/// How the GPU engine of the commands (and of [`crate::pipeline::Job`]) opens: which
/// adapter, and the engine's options. A plain value: the commands build it from their
/// environment once ([`GpuSetup::from_vars`], called in `src/cmd/`); the default is
/// [`GpuOptions::for_commands`] on wgpu's choice of adapter.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct GpuSetup {
    /// A case-insensitive part of the adapter's name; `None`: wgpu's default choice
    /// (`WGPU_POWER_PREF` honoured, as wgpu reads it). A name that matches no adapter is an
    /// error, not a fallback.
    pub adapter_name: Option<String>,
    /// The adapter at this PCI address (`0000:65:00.0`, or nvidia-smi's
    /// `00000000:65:00.0`): the GPU a scheduler bound to the job, told apart from others of
    /// the same model (scripts/slurm-batch.sh); before `adapter_name`, and for `--backend
    /// auto` too. An address that matches no adapter is an error.
    pub adapter_pci_bus_id: Option<String>,
    pub options: GpuOptions,
}

impl Default for GpuSetup {
    fn default() -> Self {
        GpuSetup {
            adapter_name: None,
            adapter_pci_bus_id: None,
            options: GpuOptions::for_commands(),
        }
    }
}

impl GpuSetup {
    /// The default setup with the variables that `var` looks up applied (the commands
    /// pass the process environment; the table is in docs/troubleshooting.md#environment):
    /// - `WGPU_ADAPTER_NAME`: [`GpuSetup::adapter_name`];
    /// - `LINEGS_GPU_PCI_BUS_ID`: [`GpuSetup::adapter_pci_bus_id`];
    /// - `LINEGS_GPU_SMALL_BATCH=N`: [`GpuOptions::small_batch`] (0 sends every batch to
    ///   the device);
    /// - `LINEGS_GPU_FIT_TAIL=N`: [`GpuOptions::fit_tail`] (0 runs every iteration of the
    ///   device fit on the device);
    /// - `LINEGS_GPU_FIT=device|host`: [`GpuOptions::fit`] (else by adapter);
    /// - `LINEGS_GPU_MEMBERS=device|host`: [`GpuOptions::members`] (else by adapter);
    /// - `LINEGS_GPU_UPLOADS=mapped|staged`: [`GpuOptions::mapped_uploads`] (`mapped`,
    ///   the default, has an effect on a software adapter only);
    /// - `LINEGS_GPU_GARBAGE` (any value): [`GpuOptions::fill_garbage`].
    ///
    /// An empty value is the same as an unset one; any other value that is not one of
    /// those accepted is an error naming the variable, its value and the accepted ones.
    pub fn from_vars(var: impl Fn(&str) -> Option<String>) -> Result<GpuSetup, GpuSetupError> {
        let set = |k: &str| var(k).filter(|v| !v.trim().is_empty());
        let bad = |var: &'static str, v: &str, accepted: &'static str| GpuSetupError::BadValue {
            var,
            value: v.to_string(),
            accepted,
        };
        // A count variable's value, where it is set.
        let whole = |var: &'static str, accepted: &'static str| {
            set(var)
                .map(|v| {
                    v.trim()
                        .parse::<usize>()
                        .map_err(|_| bad(var, &v, accepted))
                })
                .transpose()
        };
        let mut options = GpuOptions::for_commands();
        if let Some(n) = whole(
            "LINEGS_GPU_SMALL_BATCH",
            "a whole number >= 0 (0 sends every batch to the device)",
        )? {
            options.small_batch = n;
        }
        if let Some(n) = whole(
            "LINEGS_GPU_FIT_TAIL",
            "a whole number >= 0 (0 runs every iteration on the device)",
        )? {
            options.fit_tail = n;
        }
        options.fit = match set("LINEGS_GPU_FIT").as_deref().map(str::trim) {
            None => FitOn::Auto,
            Some("device") => FitOn::Device,
            Some("host") => FitOn::Host,
            Some(v) => return Err(bad("LINEGS_GPU_FIT", v, "`device` or `host`")),
        };
        options.members = match set("LINEGS_GPU_MEMBERS").as_deref().map(str::trim) {
            None => MembersOn::Auto,
            Some("device") => MembersOn::Device,
            Some("host") => MembersOn::Host,
            Some(v) => return Err(bad("LINEGS_GPU_MEMBERS", v, "`device` or `host`")),
        };
        options.mapped_uploads = match set("LINEGS_GPU_UPLOADS").as_deref().map(str::trim) {
            None | Some("mapped") => options.mapped_uploads,
            Some("staged") => false,
            Some(v) => return Err(bad("LINEGS_GPU_UPLOADS", v, "`mapped` or `staged`")),
        };
        options.fill_garbage |= var("LINEGS_GPU_GARBAGE").is_some();
        Ok(GpuSetup {
            adapter_name: var("WGPU_ADAPTER_NAME"),
            adapter_pci_bus_id: var("LINEGS_GPU_PCI_BUS_ID").filter(|v| !v.trim().is_empty()),
            options,
        })
    }
}

/// A `LINEGS_GPU_*` variable with a value that is not one of those accepted
/// ([`GpuSetup::from_vars`]).
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum GpuSetupError {
    #[error("{var}={value:?}: expected {accepted} (or unset for the default)")]
    BadValue {
        var: &'static str,
        value: String,
        accepted: &'static str,
    },
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
            fit_tail: 0,
            members: MembersOn::Device,
            warm_up: false,
            mapped_uploads: true,
            fill_garbage: cfg!(debug_assertions),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_variables_set_what_they_name() {
        let none = GpuSetup::from_vars(|_| None).unwrap();
        assert_eq!(none, GpuSetup::default());
        assert_eq!(none.options.small_batch, SMALL_BATCH);
        assert_eq!(none.options.fit_tail, FIT_TAIL);
        let vars = |k: &str| {
            match k {
                "WGPU_ADAPTER_NAME" => Some("llvmpipe"),
                "LINEGS_GPU_SMALL_BATCH" => Some(" 0 "),
                "LINEGS_GPU_FIT_TAIL" => Some("7"),
                "LINEGS_GPU_FIT" => Some("host"),
                "LINEGS_GPU_MEMBERS" => Some("device"),
                "LINEGS_GPU_UPLOADS" => Some("staged"),
                "LINEGS_GPU_GARBAGE" => Some(""),
                _ => None,
            }
            .map(String::from)
        };
        let s = GpuSetup::from_vars(vars).unwrap();
        assert_eq!(s.adapter_name.as_deref(), Some("llvmpipe"));
        assert_eq!(s.options.small_batch, 0);
        assert_eq!(s.options.fit_tail, 7);
        assert_eq!(s.options.fit, FitOn::Host);
        assert_eq!(s.options.members, MembersOn::Device);
        assert!(!s.options.mapped_uploads && none.options.mapped_uploads);
        assert!(s.options.fill_garbage && s.options.warm_up);
        // an empty value is an unset one
        let empty = GpuSetup::from_vars(|k| (k != "WGPU_ADAPTER_NAME").then(|| " ".into()));
        assert_eq!(empty.unwrap().options.fit, FitOn::Auto);
    }

    #[test]
    fn a_bad_value_is_an_error_naming_the_variable_and_the_accepted_values() {
        for (k, v, accepted) in [
            ("LINEGS_GPU_SMALL_BATCH", "x", "a whole number >= 0"),
            ("LINEGS_GPU_SMALL_BATCH", "-1", "a whole number >= 0"),
            ("LINEGS_GPU_FIT_TAIL", "many", "a whole number >= 0"),
            ("LINEGS_GPU_FIT", "gpu", "`device` or `host`"),
            ("LINEGS_GPU_MEMBERS", "Device", "`device` or `host`"),
            ("LINEGS_GPU_UPLOADS", "host", "`mapped` or `staged`"),
        ] {
            let e = GpuSetup::from_vars(|q| (q == k).then(|| v.into()))
                .unwrap_err()
                .to_string();
            assert!(
                e.starts_with(&format!("{k}=\"{v}\": expected {accepted}")),
                "{e}"
            );
        }
    }
}
