#![no_main]
//! Every Gaussian model reader of the format registry behind the dispatcher.
libfuzzer_sys::fuzz_target!(|data: &[u8]| linegs_gpu_fuzz::check_models(data));
