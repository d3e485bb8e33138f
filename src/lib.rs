//! linegs-gpu: refine noisy 3D line segments with the Gaussian centers of a 3D Gaussian
//! Splatting model (LineGS, Yang and Shi), on the CPU or on the GPU through WGSL kernels.

pub mod autoframe;
pub mod batch;
pub mod engine;
pub mod eval;
pub mod frames;
pub mod geom;
pub mod index;
pub mod io;
pub mod mem;
pub mod pipeline;
pub mod refine;
/// Pictures (PNG, SVG, HTML): only with the `cli` feature (resvg, ab_glyph).
#[cfg(feature = "cli")]
pub mod render;
pub mod report;
pub mod synth;
