//! `--backend auto|gpu|cpu` (docs/architecture.md#the-engine-contract): which engine
//! answers the queries.

use super::cpu::CpuEngine;
use super::gpu::{GpuDevice, GpuEngine, GpuSetup, PointStore};
use super::{Engine, EngineError};
use crate::index::Grid;
use std::sync::Arc;
use std::time::Instant;

/// Which engine to use.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// A hardware GPU adapter when one exists, else the CPU engine (software adapters
    /// such as lavapipe run on the same cores, slower: only with `gpu`).
    #[default]
    Auto,
    /// A GPU adapter (software ones included), or an error.
    Gpu,
    /// The CPU engine (rayon).
    Cpu,
}

impl Backend {
    pub fn as_str(&self) -> &'static str {
        match self {
            Backend::Auto => "auto",
            Backend::Gpu => "gpu",
            Backend::Cpu => "cpu",
        }
    }
}

/// A backend name that is not `auto`, `gpu` or `cpu`.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum BackendError {
    #[error("backend `{0}`: expected `auto`, `gpu` or `cpu`")]
    Unknown(String),
}

impl std::str::FromStr for Backend {
    type Err = BackendError;
    /// `auto`, `gpu` or `cpu`, in any case.
    fn from_str(s: &str) -> Result<Self, BackendError> {
        [Backend::Auto, Backend::Gpu, Backend::Cpu]
            .into_iter()
            .find(|b| b.as_str().eq_ignore_ascii_case(s))
            .ok_or_else(|| BackendError::Unknown(s.to_string()))
    }
}

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The engine for `backend` over `grid` (a GPU engine opened as `gpu` says), with the
/// messages the user should see: for `auto`, which adapter it picked, or why it chose the
/// CPU engine.
pub fn make_engine(
    backend: Backend,
    gpu: &GpuSetup,
    grid: Arc<Grid>,
) -> Result<(Box<dyn Engine>, Vec<String>), EngineError> {
    prepare(backend, gpu).finish(grid)
}

/// The error `e` once more, for the next engine of a device that did not open.
fn again(e: &EngineError) -> EngineError {
    match e {
        EngineError::NoAdapter(why) => EngineError::NoAdapter(why.clone()),
        EngineError::OutOfMemory { phase, why } => EngineError::OutOfMemory {
            phase: phase.clone(),
            why: why.clone(),
        },
        e => EngineError::Gpu(e.to_string()),
    }
}

/// The engine of a backend in the making ([`prepare`]).
pub struct Pending {
    backend: Backend,
    /// The opening thread: the device (or why not) and when the opening ended.
    device: Option<std::thread::JoinHandle<(Result<GpuDevice, EngineError>, Instant)>>,
    /// When the opening started ([`prepare`]).
    started: Instant,
    /// The opening's result once waited for ([`Pending::wait`]), for the first engine.
    waited: Option<Result<GpuDevice, EngineError>>,
    /// The opened device once an engine was made of it ([`Pending::engine`]), for the
    /// next: its clone shares the device and the kernels; or why it did not open.
    opened: Option<Result<GpuDevice, EngineError>>,
    /// When the opening ended, once its thread was joined.
    ended: Option<Instant>,
}

/// Starts making the engine of `backend`: for `gpu` and `auto` the adapter is picked and
/// opened and the kernels compiled on a thread of their own, which needs no Gaussians, so
/// that it runs while the caller builds the grid; [`Pending::finish`] uploads the grid.
/// `gpu` says how: for `auto` its options on the hardware adapter found (its adapter name
/// is not consulted), for `gpu` its adapter and options.
pub fn prepare(backend: Backend, gpu: &GpuSetup) -> Pending {
    let gpu = gpu.clone();
    let open = move || match backend {
        Backend::Auto => {
            let adapters = crate::engine::gpu::enumerate_adapters();
            let infos: Vec<wgpu::AdapterInfo> = adapters.iter().map(|a| a.get_info()).collect();
            // The GPU the scheduler bound to the job, whatever its kind.
            let pick = match &gpu.adapter_pci_bus_id {
                Some(bus) => match crate::engine::gpu::find_pci_bus_id(&infos, bus) {
                    Ok(i) => Pick::Hardware(i),
                    Err(why) => Pick::None(why.to_string()),
                },
                None => auto_pick(&infos),
            };
            match pick {
                Pick::Hardware(i) => {
                    log::info!(
                        "adapter picked: {}",
                        crate::engine::gpu::describe_adapter(&infos[i])
                    );
                    GpuDevice::open(&adapters[i], gpu.options)
                }
                Pick::None(why) | Pick::SoftwareOnly(why) => {
                    log::info!("--backend auto takes the CPU engine: {why}");
                    Err(EngineError::NoAdapter(why))
                }
            }
        }
        _ => GpuDevice::open_setup(&gpu),
    };
    let timed = move || {
        let d = open();
        (d, Instant::now())
    };
    Pending {
        backend,
        started: Instant::now(),
        device: (backend != Backend::Cpu).then(|| std::thread::spawn(timed)),
        waited: None,
        opened: None,
        ended: None,
    }
}

impl Pending {
    /// The engine over `grid`, with the messages the user should see: for `auto`, which
    /// adapter it picked, or why it chose the CPU engine.
    pub fn finish(
        mut self,
        grid: Arc<Grid>,
    ) -> Result<(Box<dyn Engine>, Vec<String>), EngineError> {
        self.engine(grid)
    }

    /// [`Pending::finish`] that keeps the device for more engines: every call after the
    /// first makes its engine on the same device and kernels (a second grid of the same
    /// run: `--max-scale`'s placing Gaussians), with the same messages, and opens nothing.
    pub fn engine(
        &mut self,
        grid: Arc<Grid>,
    ) -> Result<(Box<dyn Engine>, Vec<String>), EngineError> {
        // While the device is still opening (drivers and kernel compilers take a good
        // part of a second), the point store it will upload is computed here.
        let store = self
            .device
            .as_ref()
            .filter(|h| !h.is_finished())
            .map(|_| PointStore::of(&grid));
        // The device for this engine: the one opened for the first, and a clone of it (or
        // the same error) kept for the next.
        let share = |d: &Result<GpuDevice, EngineError>| match d {
            Ok(d) => Ok(d.clone()),
            Err(e) => Err(again(e)),
        };
        let device = match self.join().or_else(|| self.waited.take()) {
            Some(d) => {
                self.opened = Some(share(&d));
                Some(d)
            }
            None => self.opened.as_ref().map(share),
        };
        choose(self.backend, grid, |g| match device {
            Some(d) => d?.engine_with(g, store).map(Some),
            None => Err(EngineError::NoAdapter("no adapter was opened".into())),
        })
    }
}

impl Pending {
    /// Waits for the opening thread (none for the CPU engine) and keeps its device for
    /// the engines to come. Returns the seconds from [`prepare`] to the end of the
    /// opening, and of those the ones this call waited (`None` when nothing was opened;
    /// after the first call the wait is 0). `bench` waits so that no opening runs beside
    /// a timed run.
    pub fn wait(&mut self) -> Option<(f64, f64)> {
        let now = Instant::now();
        if let Some(d) = self.join() {
            self.waited = Some(d);
        }
        let ended = self.ended?;
        Some((
            ended.duration_since(self.started).as_secs_f64(),
            ended.saturating_duration_since(now).as_secs_f64(),
        ))
    }

    /// The opening thread's device, joined now (`None`: no thread, or joined before).
    fn join(&mut self) -> Option<Result<GpuDevice, EngineError>> {
        let h = self.device.take()?;
        let (d, ended) = h.join().unwrap_or_else(|p| std::panic::resume_unwind(p));
        self.ended = Some(ended);
        Some(d)
    }
}

impl Drop for Pending {
    /// Not finished (the grid could not be built): the opening thread is waited for, so
    /// that no driver is still starting while the process exits.
    fn drop(&mut self) {
        if let Some(h) = self.device.take() {
            let _ = h.join();
        }
    }
}

/// What `auto` found among the adapters.
#[derive(Debug, PartialEq, Eq)]
pub enum Pick {
    /// The adapter at this index: a hardware GPU (discrete first, then integrated,
    /// virtual, other).
    Hardware(usize),
    /// Only software adapters (`DeviceType::Cpu`), listed in the reason.
    SoftwareOnly(String),
    /// No adapter at all.
    None(String),
}

/// `auto`'s choice: the best hardware adapter; software adapters never.
pub fn auto_pick(infos: &[wgpu::AdapterInfo]) -> Pick {
    use wgpu::DeviceType as D;
    let rank = |t: D| match t {
        D::DiscreteGpu => Some(0),
        D::IntegratedGpu => Some(1),
        D::VirtualGpu => Some(2),
        D::Other => Some(3),
        D::Cpu => None,
    };
    if let Some((i, _)) = infos
        .iter()
        .enumerate()
        .filter_map(|(i, a)| rank(a.device_type).map(|r| (i, r)))
        .min_by_key(|&(i, r)| (r, i))
    {
        return Pick::Hardware(i);
    }
    if infos.is_empty() {
        return Pick::None("no GPU adapter found".into());
    }
    let names: Vec<&str> = infos.iter().map(|a| a.name.as_str()).collect();
    Pick::SoftwareOnly(format!(
        "only software adapters ({}), which run on the same cores as the CPU engine and slower; \
         --backend gpu uses them",
        names.join(", ")
    ))
}

fn choose(
    backend: Backend,
    grid: Arc<Grid>,
    gpu: impl FnOnce(Arc<Grid>) -> Result<Option<GpuEngine>, EngineError>,
) -> Result<(Box<dyn Engine>, Vec<String>), EngineError> {
    match backend {
        Backend::Cpu => Ok((Box::new(CpuEngine::new(grid)), Vec::new())),
        Backend::Gpu => match gpu(grid)? {
            Some(e) => Ok((Box::new(e), Vec::new())),
            None => Err(EngineError::NoAdapter("none".into())),
        },
        Backend::Auto => match gpu(grid.clone()) {
            Ok(Some(e)) => {
                let note = format!(
                    "backend auto: using the GPU engine on the hardware adapter {}",
                    e.adapter()
                );
                Ok((Box::new(e), vec![note]))
            }
            Ok(None) => unreachable!("auto gets an engine or a reason"),
            Err(why) => {
                let cpu = CpuEngine::new(grid);
                let why = match why {
                    EngineError::NoAdapter(w) => w,
                    other => other.to_string(),
                };
                let note = format!(
                    "backend auto: using the CPU engine, {}: {why}",
                    cpu.adapter()
                );
                Ok((Box::new(cpu), vec![note]))
            }
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geom::Aabb;
    use glam::DVec3;

    fn grid() -> Arc<Grid> {
        let b = Aabb {
            min: DVec3::ZERO,
            max: DVec3::ONE,
        };
        Arc::new(Grid::build(&[[0.5, 0.5, 0.5]], b, 0.1))
    }

    fn no_gpu(_: Arc<Grid>) -> Result<Option<GpuEngine>, EngineError> {
        Err(EngineError::NoAdapter("none in this test".into()))
    }

    fn info(name: &str, device_type: wgpu::DeviceType) -> wgpu::AdapterInfo {
        let mut a = wgpu::AdapterInfo::new(device_type, wgpu::Backend::Vulkan);
        a.name = name.into();
        a
    }

    #[test]
    fn the_pci_address_picks_one_of_two_identical_gpus() {
        use crate::engine::gpu::{find_pci_bus_id, parse_pci_bus_id};
        // nvidia-smi's eight-digit domain and wgpu's four are the same address
        assert_eq!(parse_pci_bus_id("00000000:65:00.0"), Some([0, 0x65, 0, 0]));
        assert_eq!(
            parse_pci_bus_id("0000:65:00.0"),
            parse_pci_bus_id("00000000:65:00.0")
        );
        assert_eq!(parse_pci_bus_id("65:00.0"), Some([0, 0x65, 0, 0]));
        assert_eq!(parse_pci_bus_id("0000:b3:1f.7"), Some([0, 0xb3, 0x1f, 7]));
        assert_eq!(parse_pci_bus_id("GPU-5a1c"), None);
        let mut infos = Vec::new();
        for bus in ["0000:3b:00.0", "0000:d8:00.0", ""] {
            let mut a = info("NVIDIA H100 80GB HBM3", wgpu::DeviceType::DiscreteGpu);
            a.device_pci_bus_id = bus.into();
            infos.push(a);
        }
        assert_eq!(find_pci_bus_id(&infos, "00000000:D8:00.0"), Ok(1));
        assert_eq!(find_pci_bus_id(&infos, "0000:3b:00.0"), Ok(0));
        let none = find_pci_bus_id(&infos, "0000:5e:00.0")
            .unwrap_err()
            .to_string();
        assert!(
            none.contains("matches none of")
                && none.contains("at 0000:d8:00.0")
                && none.contains("at no PCI address"),
            "{none}"
        );
        let bad = find_pci_bus_id(&infos, "3").unwrap_err().to_string();
        assert!(bad.contains("expected a PCI address"), "{bad}");
    }

    #[test]
    fn auto_never_picks_a_software_adapter() {
        use wgpu::DeviceType as D;
        let lavapipe = info("llvmpipe (LLVM 15.0.6, 256 bits)", D::Cpu);
        match auto_pick(std::slice::from_ref(&lavapipe)) {
            Pick::SoftwareOnly(why) => {
                assert!(why.contains("llvmpipe"), "{why}");
                assert!(why.contains("--backend gpu"), "{why}");
            }
            other => panic!("{other:?}"),
        }
        assert!(matches!(auto_pick(&[]), Pick::None(_)));
        let igpu = info("Intel(R) UHD", D::IntegratedGpu);
        let dgpu = info("NVIDIA H200", D::DiscreteGpu);
        assert_eq!(
            auto_pick(&[lavapipe.clone(), igpu.clone()]),
            Pick::Hardware(1)
        );
        assert_eq!(auto_pick(&[igpu, lavapipe, dgpu]), Pick::Hardware(2));
    }

    #[test]
    fn auto_falls_back_to_the_cpu_and_says_so() {
        let (e, notes) = choose(Backend::Auto, grid(), no_gpu).unwrap();
        assert_eq!(e.backend(), "cpu");
        assert_eq!(notes.len(), 1);
        assert!(notes[0].contains("using the CPU engine"), "{}", notes[0]);
        assert!(notes[0].contains("none in this test"), "{}", notes[0]);
    }

    #[test]
    fn gpu_without_an_adapter_is_an_error_that_says_what_to_do() {
        let err = choose(Backend::Gpu, grid(), no_gpu)
            .err()
            .expect("must fail");
        let msg = err.to_string();
        assert!(msg.contains("no GPU adapter"), "{msg}");
        assert!(msg.contains("--backend cpu"), "{msg}");
    }

    #[test]
    fn cpu_is_always_the_cpu_engine() {
        let (e, notes) = make_engine(Backend::Cpu, &GpuSetup::default(), grid()).unwrap();
        assert_eq!(e.backend(), "cpu");
        assert!(notes.is_empty());
    }

    #[test]
    fn backend_names_round_trip_through_serde_and_text() {
        for b in [Backend::Auto, Backend::Gpu, Backend::Cpu] {
            let json = serde_json::to_string(&b).unwrap();
            assert_eq!(json, format!("\"{}\"", b.as_str()));
            assert_eq!(serde_json::from_str::<Backend>(&json).unwrap(), b);
            assert_eq!(b.as_str().parse::<Backend>().unwrap(), b);
            assert_eq!(b.as_str().to_uppercase().parse::<Backend>().unwrap(), b);
        }
        assert_eq!(
            "tpu".parse::<Backend>().unwrap_err().to_string(),
            "backend `tpu`: expected `auto`, `gpu` or `cpu`"
        );
    }
}
