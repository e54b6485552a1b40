//! The calling thread's CPU time, for timing figures that other processes
//! on a loaded machine do not inflate (wall time counts their turns too).

/// CPU time consumed by the calling thread so far, seconds; `None` where
/// the platform has no per-thread CPU clock.
#[cfg(unix)]
pub fn thread_cpu_seconds() -> Option<f64> {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec for the call's duration;
    // clock_gettime writes only into it and reports failure by its result.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    (rc == 0).then_some(ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9)
}

/// CPU time consumed by the calling thread so far, seconds; `None` where
/// the platform has no per-thread CPU clock.
#[cfg(not(unix))]
pub fn thread_cpu_seconds() -> Option<f64> {
    None
}

/// A stopwatch over the calling thread's CPU time and the wall clock.
#[derive(Debug, Clone, Copy)]
pub struct Stopwatch {
    wall: std::time::Instant,
    cpu: Option<f64>,
}

impl Stopwatch {
    /// Start now.
    pub fn start() -> Self {
        Stopwatch {
            wall: std::time::Instant::now(),
            cpu: thread_cpu_seconds(),
        }
    }

    /// Wall milliseconds since the start.
    pub fn wall_ms(&self) -> f64 {
        self.wall.elapsed().as_secs_f64() * 1e3
    }

    /// This thread's CPU milliseconds since the start (`None` without a
    /// per-thread CPU clock).
    pub fn cpu_ms(&self) -> Option<f64> {
        let (a, b) = (self.cpu?, thread_cpu_seconds()?);
        Some((b - a).max(0.0) * 1e3)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn thread_cpu_time_grows_with_work_and_not_with_sleep() {
        let Some(t0) = thread_cpu_seconds() else {
            return;
        };
        std::thread::sleep(std::time::Duration::from_millis(30));
        let slept = thread_cpu_seconds().unwrap() - t0;
        assert!(slept < 0.02, "sleeping cost {slept} s of CPU");
        let sw = Stopwatch::start();
        let mut x = 0u64;
        while sw.wall_ms() < 20.0 {
            x = std::hint::black_box(x.wrapping_mul(6364136223846793005).wrapping_add(1));
        }
        let cpu = sw.cpu_ms().unwrap();
        assert!(
            cpu > 0.0 && cpu <= sw.wall_ms() + 1.0,
            "busy loop: {cpu} ms CPU"
        );
    }
}
