//! What the engine knows of a kernel without knowing which kernels there are: its
//! pipelines' description ([`KernelSpec`]), a kernel over the member lists
//! ([`ListKernel`]), which launcher answers which query ([`Routes`]) and the compiled
//! pipelines ([`Kernels`]), made from the registry of `kernels/mod.rs` when the device
//! opens. The launchers (`kernels/`) sit above this and the batch machinery; nothing here
//! names them.

use super::device::Context;
use super::layout;
use super::resources::Buffers;
use super::GpuEngine;
use crate::engine::{EngineError, Extent, FitAnswer, FitAsk, Query};
use crate::geom::fit::{FitPoints, FitSpec};
use std::sync::OnceLock;

/// When a kernel's pipeline is compiled.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum When {
    /// When the device opens: every refinement uses it.
    Open,
    /// On first use: a run that never sends its kind of batch never compiles it.
    OnUse,
    /// When the device opens with the device fit wanted and f64 in shaders, in its own
    /// error scope (a driver that cannot compile it costs the device fit, not the
    /// engine); never later.
    F64,
}

/// One pipeline of a kernel.
#[derive(Debug)]
pub struct KernelSpec {
    /// The name `kernels_compiled_on_use` reports (shared by the entry points of one
    /// kernel that compile together, such as `members`).
    pub name: &'static str,
    /// Its file under `shaders/`.
    pub shader: &'static str,
    /// Its full source, as compiled.
    pub source: fn() -> String,
    pub entry: &'static str,
    pub when: When,
    /// The structs it shares with the host beyond those of the common and list preludes
    /// (its launcher's own, in its source), for the layout test.
    pub structs: &'static [layout::Layout],
}

impl KernelSpec {
    /// Whether it needs `SHADER_F64` (and reads the f64 structs).
    pub fn f64(&self) -> bool {
        self.when == When::F64
    }

    fn label(&self) -> String {
        match self.entry {
            "main" => self.name.to_string(),
            e => format!("{} {e}", self.name),
        }
    }
}

/// A kernel over the member lists: its pipeline (a [`When::F64`] entry of the
/// kernel registry, `kernels::KERNELS`) and the bytes of its output a query.
#[derive(Debug)]
pub struct ListKernel {
    pub spec: &'static KernelSpec,
    pub out: u64,
}

impl PartialEq for ListKernel {
    fn eq(&self, other: &Self) -> bool {
        std::ptr::eq(self, other)
    }
}

impl Eq for ListKernel {}

/// A list kernel that answers one of the engine's queries in place of the member lists:
/// the kernel, and its launcher's function that answers a batch of that query (the
/// queries in the order the device gets them). It answers where the kernel is compiled
/// and the centers' coordinates are on the device.
pub struct Route<F> {
    pub kernel: &'static ListKernel,
    pub answer: F,
}

/// [`crate::engine::Engine::axial`] of a batch on the device.
pub type AxialFn = fn(&GpuEngine, &mut Buffers, &[Query]) -> Result<Vec<Vec<f64>>, EngineError>;
/// [`crate::engine::Engine::extent`] of a batch on the device.
pub type ExtentFn = fn(&GpuEngine, &mut Buffers, &[Query]) -> Result<Vec<Extent>, EngineError>;
/// [`crate::engine::Engine::fit_lines`] of a batch on the device.
pub type FitLinesFn =
    fn(&GpuEngine, &mut Buffers, &[Query], &FitAsk<'_>) -> Result<Vec<FitAnswer>, EngineError>;

/// The edge fit's route: a [`Route`] that answers only the fits it `takes` (a kernel for
/// the plain ridge leaves the two-face and weighted fits to the host).
pub struct FitRoute {
    pub route: Route<FitLinesFn>,
    pub takes: fn(&GpuEngine, &FitSpec, &FitPoints<'_>) -> bool,
}

/// Which launcher answers each query that the GPU engine otherwise answers from its
/// member lists (`None`: the member lists, measured on the host): the GPU engine's
/// `Engine` methods ask this, so a kernel that takes over a query is its shader, its
/// launcher and its line in `kernels::ROUTES`.
pub struct Routes {
    pub axial: Option<&'static Route<AxialFn>>,
    pub extent: Option<&'static Route<ExtentFn>>,
    pub fit_lines: Option<&'static FitRoute>,
}

/// The compiled pipelines, one slot per entry of the registry they were made from (a
/// clone shares them).
#[derive(Clone)]
pub struct Kernels {
    specs: Vec<&'static KernelSpec>,
    pipes: Vec<OnceLock<wgpu::ComputePipeline>>,
}

impl Kernels {
    /// For every kernel of `registry` (`kernels::kernel_specs`), compiles those of
    /// [`When::Open`], and with `f64` (and f64 on the device) those of [`When::F64`].
    pub fn new(
        ctx: &Context,
        registry: impl Iterator<Item = &'static KernelSpec>,
        f64: bool,
    ) -> Kernels {
        let specs: Vec<&'static KernelSpec> = registry.collect();
        let pipes = specs
            .iter()
            .map(|s| {
                let cell = OnceLock::new();
                let compiled = match s.when {
                    When::Open => Some(ctx.pipeline(&s.label(), &(s.source)(), s.entry)),
                    When::F64 if f64 && ctx.f64 => ctx
                        .scoped(&format!("compiling the {} kernel", s.name), || {
                            ctx.pipeline(&s.label(), &(s.source)(), s.entry)
                        })
                        .ok(),
                    _ => None,
                };
                if let Some(p) = compiled {
                    let _ = cell.set(p);
                }
                cell
            })
            .collect();
        Kernels { specs, pipes }
    }

    fn slot(&self, spec: &KernelSpec) -> usize {
        self.specs
            .iter()
            .position(|s| std::ptr::eq(*s, spec))
            .unwrap_or_else(|| panic!("kernel `{}` is not in the registry", spec.label()))
    }

    /// The pipeline of `spec` where it is compiled (a [`When::F64`] kernel the device
    /// could not take is not).
    pub fn compiled(&self, spec: &KernelSpec) -> Option<&wgpu::ComputePipeline> {
        self.pipes[self.slot(spec)].get()
    }

    /// The pipeline of `spec`, compiled now (in its own error scope) if this is the
    /// first use of a [`When::OnUse`] kernel.
    pub fn get(
        &self,
        ctx: &Context,
        spec: &KernelSpec,
    ) -> Result<&wgpu::ComputePipeline, EngineError> {
        let cell = &self.pipes[self.slot(spec)];
        if let Some(p) = cell.get() {
            return Ok(p);
        }
        if spec.when != When::OnUse {
            return Err(EngineError::Gpu(format!(
                "the {} kernel is not compiled on this device",
                spec.label()
            )));
        }
        let p = ctx.scoped(&format!("compiling the {} kernel", spec.name), || {
            ctx.pipeline(&spec.label(), &(spec.source)(), spec.entry)
        })?;
        Ok(cell.get_or_init(|| p))
    }

    /// The kernels compiled on first use that have been so far, by name in the order of
    /// the registry (a name once all its entry points are): `eval sides`, `eval sides
    /// cover`, `eval histogram`, `eval below`, `eval members`, `cut`, `members`.
    pub fn compiled_on_use(&self) -> Vec<String> {
        let mut out: Vec<String> = Vec::new();
        for (i, s) in self.specs.iter().enumerate() {
            if s.when != When::OnUse || out.last().is_some_and(|n| n == s.name) {
                continue;
            }
            let all = self
                .specs
                .iter()
                .zip(&self.pipes)
                .filter(|(t, _)| t.name == s.name)
                .all(|(_, p)| p.get().is_some());
            if all && self.pipes[i].get().is_some() {
                out.push(s.name.to_string());
            }
        }
        out
    }
}
