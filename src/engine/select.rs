//! `--backend auto|gpu|cpu` (SPEC 4): which engine answers the queries.

use super::cpu::CpuEngine;
use super::gpu::GpuEngine;
use super::{Engine, EngineError};
use crate::index::Grid;
use std::sync::Arc;

/// Which engine to use.
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    clap::ValueEnum,
    serde::Serialize,
    serde::Deserialize,
)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// A GPU adapter when one exists (lavapipe counts), else the CPU.
    #[default]
    Auto,
    /// A GPU adapter, or an error.
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

impl std::fmt::Display for Backend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// The engine for `backend` over `grid`, with the messages the user should see: for
/// `auto`, which adapter it picked or why it fell back to the CPU.
pub fn make_engine(
    backend: Backend,
    grid: Arc<Grid>,
) -> Result<(Box<dyn Engine>, Vec<String>), EngineError> {
    choose(backend, grid, GpuEngine::new)
}

fn choose(
    backend: Backend,
    grid: Arc<Grid>,
    gpu: impl FnOnce(Arc<Grid>) -> Result<GpuEngine, EngineError>,
) -> Result<(Box<dyn Engine>, Vec<String>), EngineError> {
    match backend {
        Backend::Cpu => Ok((Box::new(CpuEngine::new(grid)), Vec::new())),
        Backend::Gpu => {
            let e = gpu(grid)?;
            Ok((Box::new(e), Vec::new()))
        }
        Backend::Auto => match gpu(grid.clone()) {
            Ok(e) => {
                let note = format!("backend auto: using the GPU adapter {}", e.adapter());
                Ok((Box::new(e), vec![note]))
            }
            Err(why) => {
                let cpu = CpuEngine::new(grid);
                let note = format!(
                    "backend auto: no usable GPU ({why}); falling back to the CPU engine, {}",
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

    fn no_gpu(_: Arc<Grid>) -> Result<GpuEngine, EngineError> {
        Err(EngineError::NoAdapter("none in this test".into()))
    }

    #[test]
    fn auto_falls_back_to_the_cpu_and_says_so() {
        let (e, notes) = choose(Backend::Auto, grid(), no_gpu).unwrap();
        assert_eq!(e.backend(), "cpu");
        assert_eq!(notes.len(), 1);
        assert!(notes[0].contains("falling back to the CPU"), "{}", notes[0]);
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
        let (e, notes) = make_engine(Backend::Cpu, grid()).unwrap();
        assert_eq!(e.backend(), "cpu");
        assert!(notes.is_empty());
    }

    #[test]
    fn backend_names_round_trip_through_serde_and_clap() {
        use clap::ValueEnum;
        for b in [Backend::Auto, Backend::Gpu, Backend::Cpu] {
            let json = serde_json::to_string(&b).unwrap();
            assert_eq!(json, format!("\"{}\"", b.as_str()));
            assert_eq!(serde_json::from_str::<Backend>(&json).unwrap(), b);
            assert_eq!(Backend::from_str(b.as_str(), false).unwrap(), b);
        }
    }
}
