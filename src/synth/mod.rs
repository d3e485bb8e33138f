//! Synthetic scenes with known answers, for tests, the `demo` command and the benchmarks.
//!
//! Every generator is deterministic for its seed and independent of the thread count.

pub mod rng;

pub use rng::Rng;
