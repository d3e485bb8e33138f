//! The command line's heap on huge pages (`mem::huge_heap`), in a process of its own with
//! the command line's allocator: no test harness, so that every block comes from the main
//! heap of the main thread, as in `linegs-gpu refine`.

#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

/// Bytes on huge pages (`AnonHugePages`) in the mappings named `[heap]`.
fn heap_huge_bytes() -> u64 {
    let smaps = std::fs::read_to_string("/proc/self/smaps").expect("/proc/self/smaps");
    let mut in_heap = false;
    let mut total = 0;
    for line in smaps.lines() {
        let first = line.split_whitespace().next().unwrap_or("");
        if first.contains('-') && !first.ends_with(':') {
            in_heap = line.trim_end().ends_with("[heap]");
        } else if in_heap {
            if let Some(kb) = line.strip_prefix("AnonHugePages:") {
                total += kb
                    .trim()
                    .trim_end_matches("kB")
                    .trim()
                    .parse::<u64>()
                    .unwrap()
                    * 1024;
            }
        }
    }
    total
}

fn main() {
    // One heap for every thread on a machine of at most four threads (glibc), and the
    // engines take many small blocks on one thread then (`mem::one_heap`).
    assert!(!linegs_gpu::mem::one_heap(), "one heap before huge_heap");
    linegs_gpu::mem::huge_heap();
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    assert_eq!(
        linegs_gpu::mem::one_heap(),
        cfg!(all(target_os = "linux", target_env = "gnu")) && threads <= 4,
        "one heap with {threads} threads"
    );
    let thp =
        std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled").unwrap_or_default();
    if !cfg!(all(target_os = "linux", target_env = "gnu")) || !thp.contains("[madvise]") {
        // `never`: nothing to see; `always`: huge without the advice.
        println!("heap: skipped (transparent huge pages not in madvise mode: {thp:?})");
        return;
    }
    // Blocks of 1 MiB: far under the 4 MiB from which each block is advised on its own,
    // so only the heap's advice can put them on huge pages.
    let blocks: Vec<Vec<u8>> = (0..40).map(|i| vec![i as u8 + 1; 1 << 20]).collect();
    let huge = heap_huge_bytes();
    let sum: u64 = blocks.iter().map(|b| u64::from(b[b.len() - 1])).sum();
    assert_eq!(sum, (1..=40).sum::<u64>());
    // 40 MiB written: about 19 whole 2 MiB pages; the kernel may fail to find some free.
    assert!(
        huge >= 8 << 20,
        "{huge} bytes of the heap on huge pages, 40 MiB written"
    );
    println!("heap: ok ({} MiB of the heap on huge pages)", huge >> 20);
}
