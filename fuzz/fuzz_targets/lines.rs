#![no_main]
//! Every line reader of the format registry, picked by content; the first byte picks the
//! file name (`io::file_names`), whose extension decides what content alone cannot.
libfuzzer_sys::fuzz_target!(|data: &[u8]| linegs_gpu_fuzz::check_picked_lines(data));
