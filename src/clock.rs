//! The daemon's clock: the tokio runtime's, so that on a runtime with
//! paused time (the tests' simulated time, with the in-process simulator in
//! lockstep) every timer, age and timestamp the daemon's behaviour depends
//! on is simulated, and in a normal run it is the system's.
//!
//! Use [`now`] and [`since`] for instants that decide something (a
//! telemetry sample's age, a flight's timeout, a fit's age) and [`unix_now`]
//! for wall-clock stamps; keep `std::time::Instant` for measuring how long
//! computation took. Outside a runtime (and on threads that did not enter
//! one) these are the system's clocks.

use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

/// The runtime's clock now, as a std instant.
pub fn now() -> Instant {
    tokio::time::Instant::now().into_std()
}

/// How long ago `t` (an instant of [`now`]) was; zero if it is ahead.
pub fn since(t: Instant) -> Duration {
    now().saturating_duration_since(t)
}

/// The current time as unix seconds: the system's, moved by how far the
/// runtime's clock is from the system's monotonic clock (zero unless time
/// is paused).
pub fn unix_now() -> f64 {
    let wall = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64());
    let (runtime, system) = (now(), Instant::now());
    let ahead = match runtime.checked_duration_since(system) {
        Some(d) => d.as_secs_f64(),
        None => -system.saturating_duration_since(runtime).as_secs_f64(),
    };
    wall + ahead
}

/// The unix time of `t`, an instant of [`now`] (a message's receive
/// stamp, say).
pub fn unix_at(t: Instant) -> f64 {
    unix_now() - since(t).as_secs_f64()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn outside_a_paused_runtime_it_is_the_system_clock() {
        let sys = SystemTime::now()
            .duration_since(UNIX_EPOCH)
            .unwrap()
            .as_secs_f64();
        assert!((unix_now() - sys).abs() < 0.05);
        let t = now();
        assert!(since(t) < Duration::from_secs(1));
        assert!((unix_at(t) - sys).abs() < 0.05);
    }

    #[tokio::test(start_paused = true)]
    async fn on_paused_time_it_is_the_simulated_clock() {
        let (u0, t0) = (unix_now(), now());
        tokio::time::sleep(Duration::from_secs(3600)).await;
        // An hour passed on the runtime's clock, not on the system's.
        assert!((since(t0).as_secs_f64() - 3600.0).abs() < 1e-3);
        assert!((unix_now() - u0 - 3600.0).abs() < 0.05);
        // An instant an hour back is an hour back in unix time too.
        assert!((unix_at(t0) - u0).abs() < 0.05);
    }
}
