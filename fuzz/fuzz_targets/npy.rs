#![no_main]
//! The LIMAP `.npy` reader (its own target so its corpus stays `.npy`-shaped).
libfuzzer_sys::fuzz_target!(|data: &[u8]| linegs_gpu_fuzz::check_lines("l.npy", data));
