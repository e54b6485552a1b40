//! `shotpilot slam`'s frame-time report: the tracking thread's time per
//! frame, the part of it spent waiting for the map lock, the loop closer's
//! holds of that lock, and the frames that ran during a loop's correction
//! (or a merge, or the global BA) and just after it.

use std::time::Instant;

use serde::Serialize;

use shotpilot::slam::{HoldKind, LockHold};
use shotpilot::stats;

/// One frame on the tracking thread.
#[derive(Debug, Clone, Copy)]
pub struct FrameSpan {
    /// `Slam::process` called.
    pub from: Instant,
    /// `Slam::process` returned.
    pub to: Instant,
    /// Its wall time, ms.
    pub track_ms: f64,
    /// Of it, waiting for the map lock, ms.
    pub wait_ms: f64,
}

/// Count, median, 95th percentile (nearest rank) and largest of a list of
/// milliseconds (zeros when empty).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Spread {
    /// Values.
    pub n: usize,
    /// Lower median.
    pub p50: f64,
    /// 95th percentile.
    pub p95: f64,
    /// Largest.
    pub max: f64,
}

impl Spread {
    /// The spread of `v`.
    pub fn of(v: &[f64]) -> Self {
        Spread {
            n: v.len(),
            p50: stats::quantile(v, 0.5).unwrap_or(0.0),
            p95: stats::quantile(v, 0.95).unwrap_or(0.0),
            max: v.iter().copied().fold(0.0, f64::max),
        }
    }
}

impl std::fmt::Display for Spread {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "p50 {:.2} p95 {:.2} max {:.2} ms (n {})",
            self.p50, self.p95, self.max, self.n
        )
    }
}

/// A span of the map's work that tracking may feel.
#[derive(Debug, Clone, Copy)]
pub struct Window {
    /// What ran: "loop" (from the loop closer taking the lock at the
    /// keyframe that found it to its essential graph written back), "merge"
    /// (the loop closer's hold of the lock at that keyframe) or "global_ba"
    /// (start to end, most of it without the lock).
    pub kind: &'static str,
    /// The keyframe that closed it.
    pub kf: u32,
    /// Start.
    pub from: Instant,
    /// End.
    pub to: Instant,
}

/// The frames that ran during a [`Window`] and after it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct WindowReport {
    /// [`Window::kind`].
    pub kind: &'static str,
    /// The keyframe that closed it.
    pub kf: u32,
    /// Its length, ms.
    pub ms: f64,
    /// Frames that overlapped it: their wall time.
    pub during: Spread,
    /// Frames that overlapped it: their wait for the map lock.
    pub during_wait: Spread,
    /// The frames that started after it ended (as many as
    /// [`TimingReport::after_frames`]): their wall time.
    pub after: Spread,
}

/// The report.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TimingReport {
    /// Every frame's wall time.
    pub track_ms: Spread,
    /// Every frame's wait for the map lock.
    pub lock_wait_ms: Spread,
    /// Frames that waited for the lock at all.
    pub frames_waited: usize,
    /// The loop closer's holds of the lock while searching (nothing closed).
    pub search_holds_ms: Spread,
    /// Its holds at a keyframe that closed a loop (the search, then the
    /// correction up to the essential graph built).
    pub loop_holds_ms: Spread,
    /// Its holds to write an essential graph back.
    pub graph_holds_ms: Spread,
    /// The global BA's holds of the lock (building, writing back).
    pub global_ba_holds_ms: Spread,
    /// Frames counted after each window.
    pub after_frames: usize,
    /// The loops, merges and global BAs, in order.
    pub windows: Vec<WindowReport>,
}

/// The report of `frames` against the loop closer's `holds` and the
/// `windows` (loops, merges, global BAs); `after` frames count as "after" a
/// window.
pub fn report(
    frames: &[FrameSpan],
    holds: &[LockHold],
    windows: &[Window],
    after: usize,
) -> TimingReport {
    let track: Vec<f64> = frames.iter().map(|f| f.track_ms).collect();
    let wait: Vec<f64> = frames.iter().map(|f| f.wait_ms).collect();
    let holds_of = |kind: HoldKind| -> Vec<f64> {
        holds
            .iter()
            .filter(|h| h.kind == kind)
            .map(LockHold::ms)
            .collect()
    };
    let mut spans: Vec<Window> = windows.to_vec();
    spans.sort_by_key(|w| w.from);
    let windows = spans
        .into_iter()
        .map(|Window { kind, kf, from, to }| {
            let during: Vec<&FrameSpan> = frames
                .iter()
                .filter(|f| f.from < to && f.to > from)
                .collect();
            let next: Vec<f64> = frames
                .iter()
                .filter(|f| f.from >= to)
                .take(after)
                .map(|f| f.track_ms)
                .collect();
            WindowReport {
                kind,
                kf,
                ms: (to - from).as_secs_f64() * 1e3,
                during: Spread::of(&during.iter().map(|f| f.track_ms).collect::<Vec<_>>()),
                during_wait: Spread::of(&during.iter().map(|f| f.wait_ms).collect::<Vec<_>>()),
                after: Spread::of(&next),
            }
        })
        .collect();
    TimingReport {
        track_ms: Spread::of(&track),
        lock_wait_ms: Spread::of(&wait),
        frames_waited: wait.iter().filter(|w| **w > 0.0).count(),
        search_holds_ms: Spread::of(&holds_of(HoldKind::Search)),
        loop_holds_ms: Spread::of(&holds_of(HoldKind::Loop)),
        graph_holds_ms: Spread::of(&holds_of(HoldKind::EssentialGraph)),
        global_ba_holds_ms: Spread::of(&holds_of(HoldKind::GlobalBa)),
        after_frames: after,
        windows,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn at(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    #[test]
    fn frames_are_placed_against_the_windows_they_overlap() {
        use shotpilot::slam::KeyFrameId;
        let t0 = Instant::now();
        // Ten frames of 10 ms every 100 ms; the fourth waited 40 ms.
        let frames: Vec<FrameSpan> = (0..10)
            .map(|i| {
                let (track, wait) = if i == 3 { (50.0, 40.0) } else { (10.0, 0.0) };
                FrameSpan {
                    from: at(t0, i * 100),
                    to: at(t0, i * 100 + track as u64),
                    track_ms: track,
                    wait_ms: wait,
                }
            })
            .collect();
        let hold = |kf, a, b, kind| LockHold {
            kf: KeyFrameId(kf),
            from: at(t0, a),
            to: at(t0, b),
            kind,
        };
        let holds = [
            hold(5, 20, 25, HoldKind::Search),
            hold(6, 290, 320, HoldKind::Loop),
            hold(6, 335, 340, HoldKind::EssentialGraph),
            hold(6, 600, 605, HoldKind::GlobalBa),
            hold(7, 900, 902, HoldKind::Search),
        ];
        let window = |kind, a, b| Window {
            kind,
            kf: 6,
            from: at(t0, a),
            to: at(t0, b),
        };
        // Given out of order: reported by start.
        let windows = [window("global_ba", 590, 750), window("loop", 290, 340)];
        let r = report(&frames, &holds, &windows, 2);
        assert_eq!(r.track_ms.n, 10);
        assert_eq!(r.track_ms.max, 50.0);
        assert_eq!(r.frames_waited, 1);
        assert_eq!(r.lock_wait_ms.max, 40.0);
        assert_eq!(r.search_holds_ms.n, 2);
        assert_eq!(r.loop_holds_ms.n, 1);
        assert_eq!(r.graph_holds_ms.n, 1);
        assert!((r.loop_holds_ms.max - 30.0).abs() < 1e-6);
        assert_eq!(r.global_ba_holds_ms.n, 1);
        assert_eq!(r.windows.len(), 2);
        let l = &r.windows[0];
        assert_eq!((l.kind, l.kf), ("loop", 6));
        assert!((l.ms - 50.0).abs() < 1e-6);
        // Only the fourth frame (300..350) overlaps the loop (290..340).
        assert_eq!(l.during.n, 1);
        assert_eq!(l.during.max, 50.0);
        assert_eq!(l.during_wait.max, 40.0);
        // After it: the frames at 400 and 500.
        assert_eq!(l.after.n, 2);
        assert_eq!(l.after.max, 10.0);
        let b = &r.windows[1];
        assert_eq!(b.kind, "global_ba");
        // The frames at 600 and 700 overlap 590..750.
        assert_eq!(b.during.n, 2);
        assert_eq!(b.after.n, 2);
    }

    #[test]
    fn an_empty_run_reports_zeros() {
        let r = report(&[], &[], &[], 30);
        assert_eq!(r.track_ms, Spread::default());
        assert!(r.windows.is_empty());
    }
}
