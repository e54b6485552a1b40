//! The simulator's wall-clock stamps on the tokio runtime's clock: on a
//! runtime with paused time (lockstep on simulated time) the frames'
//! capture times and the RTP stream's clock run on the same clock as a
//! daemon on that runtime; in a normal run, and on threads outside a
//! runtime, it is the system's time.

use std::time::{Instant, SystemTime, UNIX_EPOCH};

/// Unix seconds: the system's, moved by how far the runtime's clock is from
/// the system's monotonic clock (zero unless time is paused).
pub fn unix_now() -> f64 {
    let wall = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let (runtime, system) = (tokio::time::Instant::now().into_std(), Instant::now());
    let ahead = match runtime.checked_duration_since(system) {
        Some(d) => d.as_secs_f64(),
        None => -system.saturating_duration_since(runtime).as_secs_f64(),
    };
    wall + ahead
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn on_paused_time_it_follows_the_runtime() {
        let u0 = unix_now();
        tokio::time::sleep(std::time::Duration::from_secs(600)).await;
        assert!((unix_now() - u0 - 600.0).abs() < 0.05);
    }
}
