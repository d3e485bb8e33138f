pub mod geom;
pub mod synth;
