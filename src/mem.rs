//! Process memory as Linux reports it, for benchmarks that check the memory bounds of
//! docs/formats.md (elsewhere every function answers `None`/`false`), large blocks on
//! huge pages, and (the command line's) a heap on huge pages that keeps what it frees.

/// A `kB` field of `/proc/self/status`, in bytes.
fn status_field(name: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(name))?;
    let kb: u64 = line[name.len()..]
        .trim()
        .trim_start_matches(':')
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024)
}

/// Peak resident set size of this process (`VmHWM`).
pub fn peak_rss_bytes() -> Option<u64> {
    status_field("VmHWM")
}

/// Current resident set size (`VmRSS`).
pub fn current_rss_bytes() -> Option<u64> {
    status_field("VmRSS")
}

/// The process's address-space limit in bytes (`ulimit -v`, `RLIMIT_AS`), or `None`
/// where there is none (or the system has no such limit).
pub fn address_space_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut r = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit writes the struct it is given and nothing else.
        if unsafe { libc::getrlimit(libc::RLIMIT_AS, &mut r) } == 0
            && r.rlim_cur != libc::RLIM_INFINITY
        {
            // rlim_t is u64 here, u32 on some 32-bit systems.
            #[allow(clippy::unnecessary_cast)]
            return Some(r.rlim_cur as u64);
        }
    }
    None
}

/// Resets the peak to the current RSS (`echo 5 > /proc/self/clear_refs`), so a benchmark
/// can measure the peak of one phase; `false` where the kernel does not allow it.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}

/// Blocks of at least this size ask for transparent huge pages.
const HUGE_FROM: usize = 4 << 20;

/// Asks the kernel to back the 2 MiB-aligned interior of a new block of `size` bytes at
/// `p` with transparent huge pages (Linux, where THP is `madvise`, Debian's and Ubuntu's
/// default, or `always`; elsewhere, for small blocks, or when refused, nothing changes).
/// A pass over the cylinders reads the point and cell arrays (hundreds of MiB at 10^7
/// Gaussians) at random; on 4 KiB pages nearly every such read misses the TLB as well as
/// the cache. Called by [`HugeBlocks`].
#[inline]
pub fn advise_huge(p: *mut u8, size: usize) {
    #[cfg(target_os = "linux")]
    if size >= HUGE_FROM && !p.is_null() {
        let start = (p as usize).next_multiple_of(HUGE_PAGE);
        let end = (p as usize).saturating_add(size) & !(HUGE_PAGE - 1);
        // The range lies inside the block just allocated.
        advise_range(start, end);
    }
    #[cfg(not(target_os = "linux"))]
    let _ = (p, size);
}

/// Size of a transparent huge page on x86-64 and most 64-bit Arm kernels.
#[cfg(target_os = "linux")]
const HUGE_PAGE: usize = 2 << 20;

/// `madvise(MADV_HUGEPAGE)` on `start..end` (nothing when empty). The caller passes memory
/// of this process's own, mapped; the advice changes how its pages are backed, never
/// their contents, and a refusal is harmless.
#[cfg(target_os = "linux")]
#[inline]
fn advise_range(start: usize, end: usize) {
    if end > start {
        // SAFETY: as above: our own mapped range; only its backing changes.
        unsafe {
            libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
        }
    }
}

/// The main heap's start of the part not yet advised ([`huge_heap`]); 0 while off.
static HEAP_FROM: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// The command line's heap (Linux with glibc): every block under 32 MiB from the main
/// heap, which grows 64 MiB at a time, keeps up to 256 MiB it freed for the next blocks
/// instead of handing it back, and lies on transparent huge pages ([`HugeBlocks`] advises
/// each part as the heap grows; larger blocks are mapped on their own and advised by
/// [`advise_huge`]). Other threads keep glibc's heaps of their own, each advised whole
/// as a thread first allocates from it ([`advise_thread_heap`]): one heap for every
/// thread would put each allocation of every thread under one lock, and parallel work
/// that takes many small blocks would queue on it. The decision rule's weighing of the
/// moved segments (its cross-sections, a few small blocks a segment) took as long on two
/// threads as on one that way (0.070 s on one and 0.085 s on two at 10^6 x 10^4, against
/// 0.037 s on two threads with a heap each), and the CPU engine's whole run took 0.32–0.34 s against
/// 0.27–0.29 s (`linegs-gpu bench -n 1000000 --num-segments 10000 --backend cpu`, three
/// interleaved pairs on the 2-core development machine). The thread heaps' advice took
/// the s200k-like process (`bash benches/s200k.sh 15`, interleaved) from 2–12 % slower
/// than under one heap back to 0.89–1.02 of its time, and the whole run at 10^6 x 10^4 to
/// 0.26–0.27 s.
///
/// A run is short and touches most pages once: on 4 KiB pages the kernel's page faults
/// took about a quarter of the s200k-like scene's CPU time (8,500 faults in a 0.13 s run;
/// 700 with this). The settings are glibc's `mallopt` knobs, the same as its tunables
/// `glibc.malloc.top_pad`, `trim_threshold`, `mmap_threshold` and `hugetlb=1`, which
/// only the environment can set. Call it first thing in `main`, once; elsewhere (another
/// C library, another system) nothing changes.
pub fn huge_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallopt changes how later blocks are placed, never live ones; sbrk(0)
        // only reads the current end of the heap.
        unsafe {
            libc::mallopt(libc::M_MMAP_THRESHOLD, 32 << 20);
            libc::mallopt(libc::M_TOP_PAD, 64 << 20);
            libc::mallopt(libc::M_TRIM_THRESHOLD, 256 << 20);
            let end = libc::sbrk(0) as usize;
            if end != usize::MAX {
                // The main heap's start: its mapping's, where it has one already.
                let start = main_heap_start().unwrap_or(end).min(end);
                MAIN_FROM.store(start.max(1), std::sync::atomic::Ordering::Relaxed);
                HEAP_FROM.store(
                    end.next_multiple_of(HUGE_PAGE),
                    std::sync::atomic::Ordering::Relaxed,
                );
            }
        }
    }
}

/// The start of the mapping named `[heap]` (the main heap), from `/proc/self/maps`.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn main_heap_start() -> Option<usize> {
    let maps = std::fs::read_to_string("/proc/self/maps").ok()?;
    let line = maps.lines().find(|l| l.trim_end().ends_with("[heap]"))?;
    let (start, _) = line.split_whitespace().next()?.split_once('-')?;
    usize::from_str_radix(start, 16).ok()
}

/// After an allocation: advises the main heap's whole 2 MiB pages that it grew by since
/// the last advice ([`huge_heap`]; nothing while it is off). A heap that shrank is
/// advised again as it grows back.
#[inline]
fn advise_heap_growth() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        use std::sync::atomic::Ordering::Relaxed;
        let from = HEAP_FROM.load(Relaxed);
        if from == 0 {
            return;
        }
        // SAFETY: sbrk(0) reads the current end of the heap and changes nothing.
        let to = unsafe { libc::sbrk(0) } as usize & !(HUGE_PAGE - 1);
        if to != from
            && HEAP_FROM
                .compare_exchange(from, to, Relaxed, Relaxed)
                .is_ok()
        {
            // The heap's own part between the last advice and its end (empty when the
            // heap shrank).
            advise_range(from, to);
        }
    }
}

/// The main heap's start ([`huge_heap`]; 0 while off): blocks from `MAIN_FROM` to the
/// heap's end are the main heap's, which [`advise_heap_growth`] advises.
static MAIN_FROM: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);

/// The size and alignment of glibc's heaps for threads other than the main one
/// (`HEAP_MAX_SIZE` on 64-bit targets): each is a reservation of its own, made readable
/// and writable as it grows.
#[cfg(all(target_os = "linux", target_env = "gnu", target_pointer_width = "64"))]
const THREAD_HEAP: usize = 64 << 20;

#[cfg(all(target_os = "linux", target_env = "gnu", target_pointer_width = "64"))]
thread_local! {
    /// The thread heap this thread advised last ([`advise_thread_heap`]).
    static ADVISED: std::cell::Cell<usize> = const { std::cell::Cell::new(0) };
}

/// After an allocation of `size` bytes at `p` outside the main heap: advises the whole
/// glibc thread heap holding it onto huge pages, once per thread and heap ([`huge_heap`];
/// nothing while it is off), as glibc's `hugetlb=1` tunable would (which only the
/// environment can set). Threads other than the main one allocate from heaps of their
/// own, which the main heap's advice does not reach: on 4 KiB pages a short run pays a
/// page fault for each page its workers touch. Blocks of [`HUGE_FROM`] and more are
/// advised on their own.
#[inline]
fn advise_thread_heap(p: *mut u8, size: usize) {
    #[cfg(all(target_os = "linux", target_env = "gnu", target_pointer_width = "64"))]
    {
        use std::sync::atomic::Ordering::Relaxed;
        let main = MAIN_FROM.load(Relaxed);
        if main == 0 || p.is_null() || size >= HUGE_FROM {
            return;
        }
        let at = p as usize;
        let base = at & !(THREAD_HEAP - 1);
        // `try_with`: nothing while the thread's locals are being torn down.
        let _ = ADVISED.try_with(|last| {
            if last.get() == base {
                return;
            }
            last.set(base);
            // SAFETY: sbrk(0) reads the current end of the heap and changes nothing.
            let end = unsafe { libc::sbrk(0) } as usize;
            if (main..end).contains(&at) {
                return;
            }
            // SAFETY: `base..base + THREAD_HEAP` is the thread heap glibc reserved for the
            // block (mapped whole, aligned to its size); the advice changes how its pages
            // are backed, never their contents, and a refusal is harmless.
            unsafe {
                libc::madvise(base as *mut libc::c_void, THREAD_HEAP, libc::MADV_HUGEPAGE);
            }
        });
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu", target_pointer_width = "64")))]
    let _ = (p, size);
}

/// The system allocator with large blocks on huge pages ([`advise_huge`]), and the heap
/// too once [`huge_heap`] is called: the Python module's and the benchmarks' global
/// allocator, and the one the command line's wraps with an out-of-memory message.
pub struct HugeBlocks;

// SAFETY: every call is passed to `System` unchanged; the advice never changes contents.
unsafe impl std::alloc::GlobalAlloc for HugeBlocks {
    unsafe fn alloc(&self, layout: std::alloc::Layout) -> *mut u8 {
        let p = unsafe { std::alloc::System.alloc(layout) };
        advise_huge(p, layout.size());
        advise_heap_growth();
        advise_thread_heap(p, layout.size());
        p
    }

    unsafe fn alloc_zeroed(&self, layout: std::alloc::Layout) -> *mut u8 {
        let p = unsafe { std::alloc::System.alloc_zeroed(layout) };
        advise_huge(p, layout.size());
        advise_heap_growth();
        advise_thread_heap(p, layout.size());
        p
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: std::alloc::Layout, new: usize) -> *mut u8 {
        let p = unsafe { std::alloc::System.realloc(ptr, layout, new) };
        advise_huge(p, new);
        advise_heap_growth();
        advise_thread_heap(p, new);
        p
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: std::alloc::Layout) {
        unsafe { std::alloc::System.dealloc(ptr, layout) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    #[cfg(target_os = "linux")]
    fn peak_grows_with_a_touched_allocation() {
        let current = current_rss_bytes().unwrap();
        let peak = peak_rss_bytes().unwrap();
        assert!(peak >= current && current > 0, "{current} > {peak}");
        // 64 MiB written page by page must show up in the resident size and the peak.
        // Absolute bounds only: the other tests of this process allocate and free at the
        // same time, so "before + 64 MiB" fails when they free more than we add.
        let v = vec![1u8; 64 << 20];
        let now = current_rss_bytes().unwrap();
        let after = peak_rss_bytes().unwrap();
        assert!(now >= 60 << 20, "resident {now} with 64 MiB touched");
        assert!(after >= now, "peak {after} below resident {now}");
        assert_eq!(v.iter().map(|&b| b as usize).sum::<usize>(), 64 << 20);
    }

    /// `AnonHugePages` (bytes) of the mapping of this process that holds `addr`.
    #[cfg(target_os = "linux")]
    fn huge_bytes_at(addr: usize) -> Option<u64> {
        let smaps = std::fs::read_to_string("/proc/self/smaps").ok()?;
        let mut inside = false;
        for line in smaps.lines() {
            let first = line.split_whitespace().next().unwrap_or("");
            if let Some((a, b)) = first.split_once('-') {
                if let (Ok(a), Ok(b)) = (usize::from_str_radix(a, 16), usize::from_str_radix(b, 16))
                {
                    inside = a <= addr && addr < b;
                    continue;
                }
            }
            if inside {
                if let Some(kb) = line.strip_prefix("AnonHugePages:") {
                    return kb
                        .trim()
                        .trim_end_matches("kB")
                        .trim()
                        .parse::<u64>()
                        .ok()
                        .map(|k| k * 1024);
                }
            }
        }
        None
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn large_blocks_are_backed_by_huge_pages_where_the_kernel_offers_them() {
        use std::alloc::{GlobalAlloc, Layout};
        let thp = std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled")
            .unwrap_or_default();
        if !thp.contains("[madvise]") {
            // `never`: nothing to see; `always`: huge without the advice.
            eprintln!("skipped: transparent huge pages are not in madvise mode ({thp:?})");
            return;
        }
        let size = 32 << 20;
        let layout = Layout::from_size_align(size, 64).unwrap();
        // SAFETY: a non-zero size; written within bounds, freed with its layout.
        unsafe {
            let p = HugeBlocks.alloc(layout);
            assert!(!p.is_null());
            std::ptr::write_bytes(p, 7, size);
            let huge = huge_bytes_at(p as usize + size / 2).expect("the block's mapping");
            assert_eq!(*p.add(size - 1), 7);
            HugeBlocks.dealloc(p, layout);
            // 15 whole 2 MiB pages lie inside; the kernel may fail to find some free.
            assert!(huge >= 2 << 20, "{huge} bytes on huge pages of {size}");
        }
    }
}
