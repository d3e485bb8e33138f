#![no_main]
//! Every line reader, picked by content; the first byte picks the file name, whose
//! extension decides what content alone cannot (a broken binary STL, an OBJ).
const NAMES: [&str; 6] = ["l.txt", "l.obj", "l.stl", "l.ply", "l.npy", "l"];
libfuzzer_sys::fuzz_target!(|data: &[u8]| {
    if let Some((&k, rest)) = data.split_first() {
        linegs_gpu_fuzz::check_lines(NAMES[k as usize % NAMES.len()], rest);
    }
});
