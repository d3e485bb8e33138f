#![no_main]
//! Gaussian PLY reader (ASCII, both binary byte orders, the 3DGS fast path).
libfuzzer_sys::fuzz_target!(|data: &[u8]| linegs_gpu_fuzz::check_gaussians(data));
