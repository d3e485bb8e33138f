//! The whole job of docs/method.md#the-refinement-steps, behind one entry point that every
//! caller uses (the CLI's `refine`, `eval`, `demo`, `bench` and `batch`, the Python
//! package, the tests):
//!
//! 1. a [`Scene`]: the Gaussian centers and the lines, loaded from files
//!    ([`Scene::load`]) or taken as arrays ([`Scene::from_arrays`]);
//! 2. a [`Job`]: the parameters, the backend and what to measure beyond the paper's
//!    metrics (a radius sweep, ground truth);
//! 3. [`Job::refine`] or [`Job::evaluate`]: builds the working set, resolves the
//!    [`Settings`](crate::refine::Settings) once, builds the grid and the engine once (a [`Refiner`]), runs the
//!    steps and the evaluations, and returns one [`Report`](crate::report::Report)
//!    (docs/formats.md#the-report) — the same shape for refine, eval and demo.
//!
//! The parts: `load.rs` (a [`Scene`] from files or arrays), `run.rs` (the [`Job`] and the
//! [`Refiner`] that runs it), `write.rs` (the [`Outputs`] of a refinement).

mod frame;
mod load;
mod run;
mod write;

pub use frame::FrameFound;
pub use load::{read_gaussians, read_gaussians_and_attributes, LoadOptions, Scene};
pub use run::{grid_cell, Job, Outcome, Refined, Refiner};
pub use write::{LinesOut, Outputs, AFTER_COLOR, BEFORE_COLOR};

use crate::engine::EngineError;
use crate::io;

pub use crate::refine::auto_radius;
pub use crate::report::Stage;

#[derive(thiserror::Error, Debug)]
pub enum RunError {
    #[error(transparent)]
    Engine(#[from] EngineError),
    #[error(transparent)]
    Io(#[from] io::Error),
    /// The input or the options cannot work together (exit code 2).
    #[error("{0}")]
    Input(String),
    /// The lines and the Gaussians are not in one frame ([`Job::check_frames`]; exit
    /// code 2): the message says why and what fixes it.
    #[error("{0}")]
    FrameMismatch(String),
}

impl RunError {
    /// Whether the user's input is at fault (exit code 2) rather than the machine.
    pub fn is_input_error(&self) -> bool {
        match self {
            RunError::Input(_) | RunError::FrameMismatch(_) => true,
            RunError::Io(e) => e.is_input_error(),
            RunError::Engine(_) => false,
        }
    }
}

/// A small scene for the parts' tests: 1,000 Gaussians along the x axis from 0 to 1
/// (on it, evenly spaced), and one segment over them 0.01 above it in y.
#[cfg(test)]
fn axis_scene() -> Scene {
    use crate::geom::{LineSet, Segment};
    let gaussians = (0..1000)
        .map(|i| [(i as f32 + 0.5) / 1000.0, 0.0, 0.0])
        .collect();
    let lines = LineSet::new(vec![Segment::from_arrays(
        [0.0, 0.01, 0.0],
        [1.0, 0.01, 0.0],
    )]);
    Scene::from_arrays(gaussians, lines).expect("a valid scene")
}
