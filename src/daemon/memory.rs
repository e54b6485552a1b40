//! Giving freed memory back to the system over a long flight.
//!
//! glibc's allocator keeps what a thread frees in that thread's arena for
//! its next allocations; it returns memory to the system only from the top
//! of an arena. The daemon's threads (video decode, tracking, local
//! mapping, loop closing, the HTTP workers, the simulator) allocate and
//! free frames, pyramids and keyframes at different rates, so the free
//! space between live blocks grows: over a 12-minute patrol the heap in
//! use levelled at 258 MiB after the first lap while the allocator held
//! 345 MiB more, freed but not returned (the soak's `heap` and `free`
//! columns), and the resident set crept up by ~2 MiB a minute with a map
//! that no longer grew. `malloc_trim(0)` gives back every whole free page
//! of every arena (`madvise(MADV_DONTNEED)`); the daemon calls it every
//! [`TRIM_PERIOD`] on a blocking worker.

use std::time::{Duration, Instant};

use tokio_util::sync::CancellationToken;

/// How often the daemon gives freed memory back.
pub const TRIM_PERIOD: Duration = Duration::from_secs(30);

/// The allocator's view of the heap, bytes (glibc's `mallinfo2`, summed
/// over its arenas).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct HeapUse {
    /// Held by the program (allocated blocks, mmapped ones included).
    pub in_use: u64,
    /// Freed by the program and kept by the allocator.
    pub free: u64,
}

/// The heap as the allocator sees it; None where the allocator does not
/// say (not glibc).
pub fn heap_use() -> Option<HeapUse> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        // SAFETY: mallinfo2 only reads the allocator's counters.
        let m = unsafe { libc::mallinfo2() };
        Some(HeapUse {
            in_use: (m.uordblks + m.hblkhd) as u64,
            free: m.fordblks as u64,
        })
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        None
    }
}

/// The process's resident set, bytes (Linux `/proc/self/statm`).
pub fn resident_bytes() -> Option<u64> {
    let s = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = s.split_whitespace().nth(1)?.parse().ok()?;
    // SAFETY: sysconf only reads a constant of the system.
    let page = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
    u64::try_from(page).ok().map(|p| pages * p)
}

/// What one trim did.
#[derive(Debug, Clone, Copy)]
pub struct Trimmed {
    /// Resident set before and after, bytes (None where unknown).
    pub resident_before: Option<u64>,
    /// After the trim.
    pub resident_after: Option<u64>,
    /// How long the trim took.
    pub took: Duration,
}

/// Gives every whole free page the allocator holds back to the system
/// (glibc `malloc_trim(0)`); None where the allocator has no such call.
pub fn trim() -> Option<Trimmed> {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let resident_before = resident_bytes();
        let t0 = Instant::now();
        // SAFETY: malloc_trim takes the arenas' locks itself; no block in
        // use is touched.
        unsafe {
            libc::malloc_trim(0);
        }
        let took = t0.elapsed();
        Some(Trimmed {
            resident_before,
            resident_after: resident_bytes(),
            took,
        })
    }
    #[cfg(not(all(target_os = "linux", target_env = "gnu")))]
    {
        None
    }
}

/// Trims every `period` until `cancel` fires, each on a blocking worker
/// (a trim walks every arena's free lists: a few milliseconds with
/// hundreds of MiB free). Logs what each gave back at debug level.
pub async fn run_trimmer(period: Duration, cancel: CancellationToken) {
    let mut tick = tokio::time::interval_at(tokio::time::Instant::now() + period, period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = cancel.cancelled() => break,
            _ = tick.tick() => {}
        }
        match tokio::task::spawn_blocking(trim).await {
            Ok(Some(t)) => {
                let mib = |b: Option<u64>| b.map_or(f64::NAN, |b| b as f64 / (1024.0 * 1024.0));
                tracing::debug!(
                    resident_before_mib = mib(t.resident_before),
                    resident_after_mib = mib(t.resident_after),
                    took_ms = t.took.as_secs_f64() * 1e3,
                    "freed memory given back"
                );
            }
            // No such call here: nothing to do on later ticks either.
            Ok(None) => break,
            Err(e) => tracing::warn!("memory trim: {e}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn freed_pages_go_back_to_the_system() {
        // Many blocks below the mmap threshold, from one thread's arena,
        // with every other one kept alive: the freed ones are holes the
        // allocator cannot give back from the top.
        let handle = std::thread::spawn(|| {
            let blocks: Vec<Vec<u8>> = (0..2048)
                .map(|i| vec![(i % 251) as u8 + 1; 64 * 1024])
                .collect();
            let kept: Vec<Vec<u8>> = blocks
                .into_iter()
                .enumerate()
                .filter(|(i, _)| i % 2 == 0)
                .map(|(_, b)| b)
                .collect();
            let before = heap_use().expect("glibc");
            let t = trim().expect("glibc");
            // The kept half stays alive through the trim.
            drop(kept);
            (before, t)
        });
        let (before, t) = handle.join().expect("thread");
        // 64 MiB were freed in holes of 64 KiB: the allocator held them.
        assert!(
            before.free >= 60 * 1024 * 1024,
            "free before the trim {} bytes",
            before.free
        );
        // The trim returns their pages (the allocator still counts them as
        // its free space) and the resident set falls by most of them.
        let (Some(b), Some(a)) = (t.resident_before, t.resident_after) else {
            panic!("no resident set");
        };
        assert!(
            b.saturating_sub(a) >= 48 * 1024 * 1024,
            "resident {b} -> {a} bytes"
        );
    }
}
