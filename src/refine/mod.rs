//! The refinement pipeline of SPEC 3, one file per step. Steps talk to the Gaussians only
//! through [`crate::engine::Engine`] batches.

pub mod params;

pub use params::{EvalParams, Fixes, Params, Profile, RadiusArg, RlMode};

pub mod cluster;
pub mod crop;
pub mod mergejoin;
pub mod outliers;
pub mod translate;

/// `rho = N / L` (0 when `L = 0`).
pub fn density(count: u64, length: f64) -> f64 {
    if length > 0.0 {
        count as f64 / length
    } else {
        0.0
    }
}
