//! The command line's heap on huge pages (`mem::huge_heap`), in a process of its own with
//! the command line's allocator: no test harness, so that every block comes from the main
//! heap of the main thread, as in `linegs-gpu refine`.

#[global_allocator]
static ALLOCATOR: linegs_gpu::mem::HugeBlocks = linegs_gpu::mem::HugeBlocks;

/// Bytes on huge pages (`AnonHugePages`) in the mappings that `take(start, end, line)`
/// picks (`line`: the mapping's line of `/proc/self/smaps`).
fn huge_bytes(take: impl Fn(usize, usize, &str) -> bool) -> u64 {
    let smaps = std::fs::read_to_string("/proc/self/smaps").expect("/proc/self/smaps");
    let mut taken = false;
    let mut total = 0;
    for line in smaps.lines() {
        let first = line.split_whitespace().next().unwrap_or("");
        if first.contains('-') && !first.ends_with(':') {
            let (a, b) = range(line);
            taken = take(a, b, line);
        } else if taken {
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

/// Bytes on huge pages in the mappings named `[heap]` (the main heap).
fn heap_huge_bytes() -> u64 {
    huge_bytes(|_, _, line| line.trim_end().ends_with("[heap]"))
}

/// 40 blocks of 1 MiB, written: far under the 4 MiB from which each block is advised on
/// its own, so only the advice of the heap they come from can put them on huge pages.
fn blocks() -> Vec<Vec<u8>> {
    let blocks: Vec<Vec<u8>> = (0..40).map(|i| vec![i as u8 + 1; 1 << 20]).collect();
    let sum: u64 = blocks.iter().map(|b| u64::from(b[b.len() - 1])).sum();
    assert_eq!(sum, (1..=40).sum::<u64>());
    blocks
}

/// The address range a mapping's line (of `/proc/self/maps` or `smaps`) starts with.
fn range(line: &str) -> (usize, usize) {
    let (a, b) = line
        .split_whitespace()
        .next()
        .unwrap()
        .split_once('-')
        .unwrap();
    let hex = |x: &str| usize::from_str_radix(x, 16).unwrap();
    (hex(a), hex(b))
}

/// The address ranges of the mappings named `[heap]` (the main heap).
fn main_heap() -> Vec<(usize, usize)> {
    let maps = std::fs::read_to_string("/proc/self/maps").expect("/proc/self/maps");
    maps.lines()
        .filter(|l| l.trim_end().ends_with("[heap]"))
        .map(range)
        .collect()
}

/// Whether a new small block of this thread lies in the main heap.
fn small_block_in_main_heap() -> bool {
    let b = std::hint::black_box(vec![7u8; 4000]);
    let at = b.as_ptr() as usize;
    main_heap().iter().any(|&(a, e)| (a..e).contains(&at))
}

fn main() {
    linegs_gpu::mem::huge_heap();
    if cfg!(all(target_os = "linux", target_env = "gnu")) {
        // The main thread's small blocks come from the main heap (on huge pages), another
        // thread's from a heap of its own: one heap for all would put every thread's
        // allocations under one lock (the decision rule's weighing took as long on two
        // threads as on one).
        assert!(small_block_in_main_heap(), "the main thread's block");
        let other = std::thread::spawn(small_block_in_main_heap).join().unwrap();
        assert!(
            !other,
            "a worker thread's small block came from the main heap"
        );
    }
    let thp =
        std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled").unwrap_or_default();
    if !cfg!(all(target_os = "linux", target_env = "gnu")) || !thp.contains("[madvise]") {
        // `never`: nothing to see; `always`: huge without the advice.
        println!("heap: skipped (transparent huge pages not in madvise mode: {thp:?})");
        return;
    }
    let main = blocks();
    let huge = heap_huge_bytes();
    // 40 MiB written: about 19 whole 2 MiB pages; the kernel may fail to find some free.
    assert!(
        huge >= 8 << 20,
        "{huge} bytes of the heap on huge pages, 40 MiB written"
    );
    // Another thread's blocks, from its own heap: that heap on huge pages too.
    let worker = std::thread::spawn(|| {
        let b = blocks();
        let at = b[20].as_ptr() as usize;
        let huge = huge_bytes(|start, end, _| (start..end).contains(&at));
        (huge, b)
    });
    let (worker_huge, _worker_blocks) = worker.join().unwrap();
    assert!(
        worker_huge >= 8 << 20,
        "{worker_huge} bytes of a worker thread's heap on huge pages, 40 MiB written"
    );
    drop(main);
    println!(
        "heap: ok ({} MiB of the main heap and {} MiB of a worker's on huge pages)",
        huge >> 20,
        worker_huge >> 20
    );
}
