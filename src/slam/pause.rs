//! Holding local mapping between two keyframes while the loop closer
//! corrects the map, and the loop closer's lower scheduling priority.
//!
//! The loop closer runs on its own thread beside local mapping. Its
//! search and the first part of a correction (moving the current
//! keyframe's neighbourhood, fusing duplicates) hold the map lock; a local
//! bundle adjustment solved meanwhile (outside the lock) sees that the map
//! was corrected and drops its result. The essential graph is then solved
//! outside the lock and written back: while that happens local mapping is
//! held ([`MappingPause::hold`]) so that no other pose is written in
//! between, as ORB-SLAM stops its local mapping during a correction.
//! Tracking is never held: keyframes wait in the mapping queue.

use std::sync::{Condvar, Mutex, MutexGuard};

/// The gate between the local mapper (which maps one keyframe at a time
/// between [`MappingPause::begin`] and [`MappingPause::end`]) and the loop
/// closer (which holds it between two keyframes).
#[derive(Debug, Default)]
pub struct MappingPause {
    state: Mutex<PauseState>,
    changed: Condvar,
}

#[derive(Debug, Default)]
struct PauseState {
    /// Holds in force (the loop closer's; more than one only in tests).
    holds: usize,
    /// The mapper is mapping a keyframe.
    mapping: bool,
}

impl MappingPause {
    fn state(&self) -> MutexGuard<'_, PauseState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The mapper starts a keyframe: waits while a hold is in force.
    pub fn begin(&self) {
        let mut s = self.state();
        while s.holds > 0 {
            s = self.changed.wait(s).unwrap_or_else(|e| e.into_inner());
        }
        s.mapping = true;
    }

    /// The mapper finished its keyframe.
    pub fn end(&self) {
        self.state().mapping = false;
        self.changed.notify_all();
    }

    /// Holds local mapping: returns once the mapper is between two
    /// keyframes; it starts none until the returned guard is dropped. Must
    /// not be called with the map lock held (the mapper may need it to
    /// finish its keyframe).
    pub fn hold(&self) -> PauseGuard<'_> {
        let mut s = self.state();
        s.holds += 1;
        while s.mapping {
            s = self.changed.wait(s).unwrap_or_else(|e| e.into_inner());
        }
        PauseGuard { pause: self }
    }

    /// Whether a hold is in force or asked for (the tests' view).
    #[cfg(test)]
    fn is_held(&self) -> bool {
        self.state().holds > 0
    }
}

/// Local mapping held until dropped ([`MappingPause::hold`]).
#[derive(Debug)]
pub struct PauseGuard<'a> {
    pause: &'a MappingPause,
}

impl Drop for PauseGuard<'_> {
    fn drop(&mut self) {
        let mut s = self.pause.state();
        s.holds = s.holds.saturating_sub(1);
        drop(s);
        self.pause.changed.notify_all();
    }
}

/// The niceness the loop closer's thread runs at: when the two threads
/// that keep up with the camera (tracking, local mapping) and the loop
/// closer want more CPU than there is, the closer waits (Linux; elsewhere
/// the thread keeps the process's priority).
pub const LOOP_THREAD_NICENESS: i32 = 10;

/// Lowers the calling thread's scheduling priority to `niceness` (Linux:
/// `setpriority` on the thread's id). Returns whether it was applied.
pub fn lower_this_thread_priority(niceness: i32) -> bool {
    #[cfg(target_os = "linux")]
    {
        // SAFETY: gettid has no preconditions; setpriority with
        // PRIO_PROCESS and a thread id changes that thread only and reads
        // no memory of ours.
        let r = unsafe {
            let tid = libc::gettid();
            libc::setpriority(libc::PRIO_PROCESS, tid as libc::id_t, niceness)
        };
        r == 0
    }
    #[cfg(not(target_os = "linux"))]
    {
        let _ = niceness;
        false
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Arc;
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::mpsc::channel;

    /// A hold waits for the keyframe being mapped to end, and no keyframe
    /// starts while it is in force.
    #[test]
    fn a_hold_waits_for_the_keyframe_and_holds_the_next() {
        let pause = Arc::new(MappingPause::default());
        let mapped = Arc::new(AtomicUsize::new(0));
        let (go_tx, go_rx) = channel::<()>();
        let (started_tx, started_rx) = channel::<usize>();
        let mapper = {
            let (pause, mapped) = (pause.clone(), mapped.clone());
            std::thread::spawn(move || {
                for k in 0..2 {
                    pause.begin();
                    started_tx.send(k).unwrap();
                    go_rx.recv().unwrap();
                    mapped.fetch_add(1, Ordering::SeqCst);
                    pause.end();
                }
            })
        };
        // The first keyframe is being mapped when the closer asks to hold.
        assert_eq!(started_rx.recv().unwrap(), 0);
        let (held_tx, held_rx) = channel::<usize>();
        let (release_tx, release_rx) = channel::<()>();
        let closer = {
            let (pause, mapped) = (pause.clone(), mapped.clone());
            std::thread::spawn(move || {
                let guard = pause.hold();
                held_tx.send(mapped.load(Ordering::SeqCst)).unwrap();
                release_rx.recv().unwrap();
                drop(guard);
            })
        };
        // Once the hold is asked for (not yet granted), the first keyframe
        // ends: the hold is granted only then.
        while !pause.is_held() {
            std::thread::yield_now();
        }
        go_tx.send(()).unwrap();
        assert_eq!(
            held_rx.recv().unwrap(),
            1,
            "the hold was granted mid-keyframe"
        );
        // Held: the second keyframe does not start.
        assert!(
            started_rx.try_recv().is_err(),
            "a keyframe started during the hold"
        );
        assert_eq!(mapped.load(Ordering::SeqCst), 1);
        // Released: it starts and ends.
        release_tx.send(()).unwrap();
        assert_eq!(started_rx.recv().unwrap(), 1);
        go_tx.send(()).unwrap();
        closer.join().unwrap();
        mapper.join().unwrap();
        assert_eq!(mapped.load(Ordering::SeqCst), 2);
        assert!(!pause.is_held());
    }

    /// While held, the mapper does not start its keyframe; it starts when
    /// the hold is released.
    #[test]
    fn the_mapper_waits_while_held() {
        let pause = Arc::new(MappingPause::default());
        let guard = pause.hold();
        let (tx, rx) = channel::<()>();
        let mapper = {
            let pause = pause.clone();
            std::thread::spawn(move || {
                pause.begin();
                tx.send(()).unwrap();
                pause.end();
            })
        };
        // The mapper is blocked in begin(): nothing arrives while held.
        assert!(
            rx.recv_timeout(std::time::Duration::from_millis(200))
                .is_err(),
            "the mapper started a keyframe during a hold"
        );
        drop(guard);
        rx.recv().unwrap();
        mapper.join().unwrap();
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn the_thread_priority_is_lowered() {
        let nice = std::thread::spawn(|| {
            assert!(lower_this_thread_priority(LOOP_THREAD_NICENESS));
            // SAFETY: as above.
            unsafe { libc::getpriority(libc::PRIO_PROCESS, libc::gettid() as libc::id_t) }
        })
        .join()
        .unwrap();
        assert!(nice >= LOOP_THREAD_NICENESS, "{nice}");
    }
}
