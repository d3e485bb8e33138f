//! The kernels, one unit each: its WGSL under `shaders/` and one launcher file here that
//! declares its pipelines ([`KernelSpec`]: source, entry point, when it compiles) and owns
//! its bindings, dispatch sizing and read-back. [`KERNELS`] is the one list of them: the
//! device opening compiles from it (`pipelines::Kernels::new`), the rest on first use, and the
//! shader tests validate every entry of it (docs/contributing.md, "Adding a kernel").
//!
//! Each source is assembled from the generated prelude, `common.wgsl` and the kernel
//! (WGSL has no include); the kernels over the member lists also get the f64 prelude and
//! `lists.wgsl` ([`lists`]).

mod args;
mod cut;
mod eval;
mod extent;
mod fit;
mod lists;
mod members;
pub(super) mod records;
mod reduce;
mod scan;
mod walk;

use super::layout;
use super::pipelines::{KernelSpec, Routes};
use super::stages::StageSpec;

/// Every kernel, launcher by launcher (each launcher's `KERNELS`: its pipelines), which the
/// device opening hands to [`super::pipelines::Kernels::new`]. Adding a kernel is one line
/// here (with its `mod`), its launcher file and its shader.
pub static KERNELS: &[&[KernelSpec]] = &[
    &walk::KERNELS,
    &scan::KERNELS,
    &args::KERNELS,
    &eval::KERNELS,
    &cut::KERNELS,
    &members::KERNELS,
    &reduce::KERNELS,
    &fit::KERNELS,
    &extent::KERNELS,
    &records::KERNELS,
];

/// The stages of a device batch, in the order a try records them: each a launcher's
/// [`StageSpec`], which says the kinds of batch it runs in, its own buffers and what comes
/// back (`stages::Sequence`, which the batches iterate). A stage kernel is one line here.
pub static STAGES: &[&StageSpec] = &[
    &walk::COUNT,
    &scan::STAGE,
    &args::STAGE,
    &walk::EMIT,
    &eval::STAGE,
    &members::STAGE,
    &cut::STAGE,
    &reduce::STAGE,
    &records::STAGE,
    &lists::STAGE,
];

/// Which launcher answers each query the GPU engine can take over from its member lists
/// (`None`: the member lists answer it): the GPU engine's `Engine` methods ask this, so a
/// kernel that takes over a query is one line here.
pub static ROUTES: Routes = Routes {
    axial: None,
    extent: Some(&extent::ROUTE),
    fit_lines: Some(&fit::ROUTE),
};

/// Every pipeline of [`KERNELS`], in order.
pub fn kernel_specs() -> impl Iterator<Item = &'static KernelSpec> {
    KERNELS.iter().flat_map(|k| k.iter())
}

/// The layouts and helpers every kernel shares: the prelude generated from `layout.rs`,
/// `shaders/common.wgsl`, then the query accessor generated from `GQuery`'s fields
/// ([`layout::query_of_wgsl`]).
pub fn common_wgsl() -> String {
    format!(
        "{}\n{}\n{}",
        layout::prelude(),
        include_str!("../../../../shaders/common.wgsl"),
        layout::query_of_wgsl()
    )
}

/// A kernel's full source: the shared prelude, then the kernel (WGSL has no include).
pub fn kernel_source(kernel: &str) -> String {
    format!("{}\n{kernel}", common_wgsl())
}

/// An f64 kernel's full source: the shared prelude, the f64 prelude of the list kernels
/// ([`layout::list_prelude`]), then the kernel.
pub fn f64_kernel_source(kernel: &str) -> String {
    kernel_source(&format!("{}\n{kernel}", layout::list_prelude()))
}

/// A kernel over the member lists (`fit.wgsl`, `extent.wgsl`, after their launcher's own
/// structs and constants): the f64 kernel source of `lists.wgsl` (their shared bindings
/// and helpers) and the kernel.
pub fn list_kernel_source(kernel: &str) -> String {
    f64_kernel_source(&format!(
        "{}\n{kernel}",
        include_str!("../../../../shaders/lists.wgsl")
    ))
}
