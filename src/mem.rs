//! Process memory as Linux reports it, for benchmarks that check the memory bounds of
//! docs/formats.md. Elsewhere every function answers `None`/`false`.

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

/// Resets the peak to the current RSS (`echo 5 > /proc/self/clear_refs`), so a benchmark
/// can measure the peak of one phase; `false` where the kernel does not allow it.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
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
}
