//! Lockstep: the simulator's clock held while its consumer works, as PX4's
//! SITL lockstep holds the simulation until the autopilot consumed its
//! step.
//!
//! With a [`Lockstep`] in [`crate::app::SimConfig::lockstep`], the
//! simulator publishes a video frame and then waits, its clock held, until
//! the consumer (the shotpilot daemon's SLAM) says it is done with that
//! frame ([`Lockstep::frame_done`]) or no longer takes frames
//! ([`Lockstep::close`]). Frames are rendered one at a time, captures are
//! written before the next step, and a frame's video latency is counted in
//! simulation steps, so what the consumer sees no longer depends on how
//! fast the machine is.
//!
//! The wait runs on a blocking thread (`spawn_blocking`): on a tokio
//! runtime with paused time, a running blocking task keeps the clock from
//! auto-advancing, so the whole run (the simulator's steps, the daemon's
//! timers) is on simulated time and goes as fast as the work allows. A wait
//! longer than [`Lockstep::limit`] of wall time is a hang guard: logged,
//! counted, and the simulator goes on.

use std::sync::{Condvar, Mutex};
use std::time::{Duration, Instant};

/// Wall time a frame may wait for its consumer before the simulator goes
/// on anyway (a consumer that stopped without closing, a frame lost on its
/// way): the guard against a hang, not a pace.
pub const DEFAULT_LIMIT: Duration = Duration::from_secs(120);

/// A frame's capture time and a consumer's report are the same frame
/// within this (the MJPEG header carries microseconds).
const SAME_FRAME_S: f64 = 5e-6;

/// The handshake between the simulator and the consumer of its frames.
#[derive(Debug)]
pub struct Lockstep {
    state: Mutex<State>,
    changed: Condvar,
    limit: Duration,
}

#[derive(Debug, Default)]
struct State {
    /// The newest capture time (unix seconds) the consumer is done with.
    done_up_to: Option<f64>,
    /// The consumer takes no more frames: nothing is waited for.
    closed: bool,
    /// Frames acknowledged, and waits given up by the guard.
    acknowledged: u64,
    timed_out: u64,
}

/// How a wait for a frame ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Wait {
    /// The consumer is done with the frame (or a later one).
    Done,
    /// The consumer takes no more frames.
    Closed,
    /// The guard's wall-time limit passed first.
    TimedOut,
}

/// What a lockstep run counted.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct LockstepStats {
    /// Frames the consumer acknowledged.
    pub acknowledged: u64,
    /// Waits the hang guard gave up.
    pub timed_out: u64,
}

impl Default for Lockstep {
    fn default() -> Self {
        Self::with_limit(DEFAULT_LIMIT)
    }
}

impl Lockstep {
    /// A lockstep whose waits give up after `limit` of wall time.
    pub fn with_limit(limit: Duration) -> Self {
        Self {
            state: Mutex::new(State::default()),
            changed: Condvar::new(),
            limit,
        }
    }

    /// The hang guard's wall-time limit per frame.
    pub fn limit(&self) -> Duration {
        self.limit
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The consumer is done with the frame captured at `capture_time_unix_s`
    /// (and so with every earlier one): the simulator may go on.
    pub fn frame_done(&self, capture_time_unix_s: f64) {
        if !capture_time_unix_s.is_finite() {
            return;
        }
        let mut s = self.lock();
        s.done_up_to = Some(
            s.done_up_to
                .map_or(capture_time_unix_s, |d| d.max(capture_time_unix_s)),
        );
        s.acknowledged += 1;
        drop(s);
        self.changed.notify_all();
    }

    /// The consumer takes no more frames (it is stopping): no wait holds
    /// the simulator from now on.
    pub fn close(&self) {
        self.lock().closed = true;
        self.changed.notify_all();
    }

    /// Whether [`Lockstep::close`] was called.
    pub fn is_closed(&self) -> bool {
        self.lock().closed
    }

    /// Blocks until the consumer is done with the frame captured at
    /// `capture_time_unix_s`, has closed, or [`Lockstep::limit`] passed.
    /// Call it from a blocking thread.
    pub fn wait_for(&self, capture_time_unix_s: f64) -> Wait {
        let deadline = Instant::now() + self.limit;
        let mut s = self.lock();
        loop {
            if s.closed {
                return Wait::Closed;
            }
            if s.done_up_to
                .is_some_and(|d| d + SAME_FRAME_S >= capture_time_unix_s)
            {
                return Wait::Done;
            }
            let now = Instant::now();
            if now >= deadline {
                s.timed_out += 1;
                return Wait::TimedOut;
            }
            s = self
                .changed
                .wait_timeout(s, deadline - now)
                .unwrap_or_else(|p| p.into_inner())
                .0;
        }
    }

    /// What was counted so far.
    pub fn stats(&self) -> LockstepStats {
        let s = self.lock();
        LockstepStats {
            acknowledged: s.acknowledged,
            timed_out: s.timed_out,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;

    #[test]
    fn a_wait_ends_when_the_frame_or_a_later_one_is_done() {
        let l = Arc::new(Lockstep::with_limit(Duration::from_secs(30)));
        let l2 = l.clone();
        let waiter = std::thread::spawn(move || l2.wait_for(100.0));
        std::thread::sleep(Duration::from_millis(20));
        // An earlier frame does not release the wait.
        l.frame_done(99.9);
        std::thread::sleep(Duration::from_millis(20));
        assert!(!waiter.is_finished());
        l.frame_done(100.0 - 1e-6);
        assert_eq!(waiter.join().unwrap(), Wait::Done);
        // A later frame covers an earlier one.
        l.frame_done(105.0);
        assert_eq!(l.wait_for(104.0), Wait::Done);
        assert_eq!(
            l.stats(),
            LockstepStats {
                acknowledged: 3,
                timed_out: 0
            }
        );
    }

    #[test]
    fn closing_releases_every_wait_and_the_guard_counts_a_timeout() {
        let l = Lockstep::with_limit(Duration::from_millis(30));
        assert_eq!(l.wait_for(1.0), Wait::TimedOut);
        assert_eq!(l.stats().timed_out, 1);
        let l = Arc::new(Lockstep::with_limit(Duration::from_secs(30)));
        let l2 = l.clone();
        let waiter = std::thread::spawn(move || l2.wait_for(1.0));
        l.close();
        assert_eq!(waiter.join().unwrap(), Wait::Closed);
        assert!(l.is_closed());
        // Non-finite reports are ignored.
        l.frame_done(f64::NAN);
        assert_eq!(l.stats().acknowledged, 0);
    }
}
