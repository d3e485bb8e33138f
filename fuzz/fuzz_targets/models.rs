#![no_main]
//! Every Gaussian model reader behind the dispatcher: compressed PLY, SPZ, `.splat`.
libfuzzer_sys::fuzz_target!(|data: &[u8]| linegs_gpu_fuzz::check_models(data));
