//! What the SLAM thread and the API share: the SLAM's status (state,
//! counts, latencies, where the map came from, the last map write or its
//! failure) and the map as the API reads it ([`MapSource`]), behind
//! [`SlamShared`], which implements the API's [`SlamView`].

use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use image::GrayImage;

use crate::api::{
    KeyframeInfo, LoopInfo, MapSaved, MapStart, MapView, MergeInfo, SlamStatus, SlamView,
    TrackedFeatures, TrackedFrame, WriteFailure,
};
use crate::slam::{Map, TrackedKeypoint};
use crate::video::live::{Frame, RateMeter, unix_now};

/// What processing one frame gave.
#[derive(Debug, Clone, Default)]
pub struct ProcessOutcome {
    /// `not_initialized`, `tracking`, `lost`, `unavailable`.
    pub state: String,
    /// The frame's pose was estimated.
    pub tracked: bool,
    /// How (`None`: not posed).
    pub source: Option<crate::slam::PoseSource>,
    /// Inliers of the pose.
    pub inliers: usize,
    /// Keyframes in the map after the frame.
    pub keyframes: usize,
    /// Points in the map after the frame.
    pub points: usize,
    /// The frame's keypoints and what tracking made of each (none
    /// without a SLAM).
    pub keypoints: Vec<TrackedKeypoint>,
}

/// The map as the API sees it (provided by the SLAM adapter).
pub trait MapSource: Send + Sync {
    /// Keyframes in id order.
    fn keyframes(&self) -> Vec<KeyframeInfo>;
    /// A keyframe's image.
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>>;
    /// Points (at most `max_points`) and trajectory.
    fn map(&self, max_points: usize) -> MapView;
    /// A copy of the whole map (for shot localisation, which must not hold
    /// the SLAM's lock while it works).
    fn snapshot(&self) -> Option<Map> {
        None
    }
    /// Keeps keyframe `id` from culling (a shot is drawn on it); false when
    /// the map has no such keyframe.
    fn pin_keyframe(&self, _id: u64) -> bool {
        false
    }
}

#[derive(Default)]
struct Inner {
    status: SlamStatus,
    latencies_ms: VecDeque<f64>,
    /// Processing times of recent frames, ms.
    frame_ms: VecDeque<f64>,
    source: Option<Arc<dyn MapSource>>,
    last_tracked: Option<TrackedFrame>,
    /// Keyframes shots are drawn on, pinned again in every new source.
    pinned: Vec<u64>,
    /// The keypoints of the latest processed frames, oldest first (at
    /// most [`FEATURE_FRAMES`]).
    features: VecDeque<Arc<TrackedFeatures>>,
}

/// Status and map view shared by the SLAM thread and the API.
pub struct SlamShared {
    inner: Mutex<Inner>,
    rate: RateMeter,
}

/// Frames in the latency median.
const LATENCY_WINDOW: usize = 100;

/// Processed frames whose keypoints (and picture) are kept for
/// `GET /features`: about a second of video, so that a page that read a
/// frame's keypoints still finds its picture when it asks next.
pub const FEATURE_FRAMES: usize = 16;

impl SlamShared {
    /// A view; `available` says whether a SLAM runs.
    pub fn new(available: bool) -> Self {
        let status = SlamStatus {
            available,
            state: if available {
                "waiting_for_video"
            } else {
                "disabled"
            }
            .into(),
            map_mode: crate::slam::MapMode::VisionOnly.name().into(),
            map_mode_reason: "no map yet".into(),
            ..Default::default()
        };
        Self {
            inner: Mutex::new(Inner {
                status,
                ..Default::default()
            }),
            rate: RateMeter::new(Duration::from_secs(2)),
        }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Inner> {
        self.inner.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Record where the map came from at start.
    pub fn set_map_start(&self, start: MapStart) {
        self.lock().status.map_start = Some(start);
    }

    /// Record the first frame tracked in a continued map.
    pub fn set_relocalised(&self, seq: u64) {
        if let Some(s) = self.lock().status.map_start.as_mut() {
            s.relocalised_at_frame = Some(seq);
        }
    }

    /// Record a loop closed: counted, and listed among the latest
    /// [`SlamStatus::MAX_LOOPS`].
    pub fn add_loop(&self, info: LoopInfo) {
        let mut g = self.lock();
        g.status.loops_closed += 1;
        let loops = &mut g.status.loops;
        loops.push(info);
        if loops.len() > SlamStatus::MAX_LOOPS {
            let extra = loops.len() - SlamStatus::MAX_LOOPS;
            loops.drain(..extra);
        }
    }

    /// Record a merge: counted, and listed among the latest
    /// [`SlamStatus::MAX_MERGES`].
    pub fn add_merge(&self, info: MergeInfo) {
        let mut g = self.lock();
        g.status.merges_made += 1;
        let merges = &mut g.status.merges;
        merges.push(info);
        if merges.len() > SlamStatus::MAX_MERGES {
            let extra = merges.len() - SlamStatus::MAX_MERGES;
            merges.drain(..extra);
        }
    }

    /// Record the map's mode and why.
    pub fn set_map_mode(&self, mode: crate::slam::MapMode, reason: &str) {
        let mut g = self.lock();
        if g.status.map_mode != mode.name() {
            g.status.map_mode = mode.name().into();
        }
        if g.status.map_mode_reason != reason {
            g.status.map_mode_reason = reason.into();
        }
    }

    /// Record how many new maps tracking started after losses.
    pub fn set_maps_started(&self, n: u64) {
        self.lock().status.maps_started = n;
    }

    /// Record the newest tracked frame.
    pub fn set_last_tracked(&self, frame: TrackedFrame) {
        self.lock().last_tracked = Some(frame);
    }

    /// Record the map file last written (a failure of the map file before
    /// it is repaired).
    pub fn set_map_saved(&self, saved: MapSaved) {
        let mut g = self.lock();
        g.status.map_saved = Some(saved);
        g.status.map_save_error = None;
    }

    /// Record a failed write of the map file or the georeference (`what`),
    /// or (None) that writes of `what` succeed again.
    pub fn set_map_save_error(&self, what: &'static str, message: Option<String>) {
        let mut g = self.lock();
        match message {
            Some(message) => {
                g.status.map_save_error = Some(WriteFailure {
                    what,
                    message,
                    at_unix: unix_now(),
                })
            }
            None => {
                if g.status
                    .map_save_error
                    .as_ref()
                    .is_some_and(|e| e.what == what)
                {
                    g.status.map_save_error = None;
                }
            }
        }
    }

    /// Attach the SLAM's map.
    ///
    /// Lock order: this state's lock is never held while the map source is
    /// called (the source takes the map's lock, and the SLAM thread, which
    /// holds the map's lock while it works, reports here). The pinned list
    /// is read and the source set in one critical section, so a keyframe
    /// pinned meanwhile is pinned either here or by [`Self::pin_keyframe`].
    pub fn set_source(&self, source: Arc<dyn MapSource>) {
        let pinned = {
            let mut g = self.lock();
            g.source = Some(source.clone());
            g.pinned.clone()
        };
        for id in pinned {
            if !source.pin_keyframe(id) {
                tracing::warn!(keyframe = id, "a shot's keyframe is not in the map");
            }
        }
    }

    /// Keeps keyframe `id` in the map (an operator's shot is drawn on it):
    /// in the running SLAM's map now and in any map set later (a restart
    /// pins its stored shots' keyframes before the map is loaded). The map
    /// source is called outside this state's lock (see [`Self::set_source`]).
    pub fn pin_keyframe(&self, id: u64) {
        let source = {
            let mut g = self.lock();
            if !g.pinned.contains(&id) {
                g.pinned.push(id);
            }
            g.source.clone()
        };
        if let Some(s) = source {
            s.pin_keyframe(id);
        }
    }

    /// Record one processed frame (and keep its keypoints, when it has
    /// any, among the [`FEATURE_FRAMES`] latest).
    pub fn record(&self, frame: &Arc<Frame>, outcome: ProcessOutcome, ms: f64) {
        self.rate.tick();
        let mut g = self.lock();
        if ms.is_finite() {
            if g.frame_ms.len() == LATENCY_WINDOW {
                g.frame_ms.pop_front();
            }
            g.frame_ms.push_back(ms);
        }
        if !outcome.keypoints.is_empty() {
            if g.features.len() == FEATURE_FRAMES {
                g.features.pop_front();
            }
            g.features.push_back(Arc::new(TrackedFeatures {
                frame: frame.clone(),
                state: outcome.state.clone(),
                keypoints: outcome.keypoints.into(),
            }));
        }
        let s = &mut g.status;
        s.state = outcome.state.clone();
        s.available = outcome.state != "unavailable";
        s.frames += 1;
        s.last_frame_ms = ms;
        s.last_inliers = outcome.inliers;
        s.keyframes = outcome.keyframes;
        s.points = outcome.points;
        s.last_source = outcome.source.map(|p| p.name().to_string());
        match outcome.source {
            Some(crate::slam::PoseSource::Vision) => s.posed_by_vision += 1,
            Some(crate::slam::PoseSource::VisionTelemetry) => s.posed_by_vision_telemetry += 1,
            Some(crate::slam::PoseSource::Telemetry) => s.posed_by_telemetry += 1,
            None => {}
        }
        if outcome.tracked {
            s.tracked += 1;
            let latency = (unix_now() - frame.timestamp()) * 1e3;
            if latency.is_finite() {
                if g.latencies_ms.len() == LATENCY_WINDOW {
                    g.latencies_ms.pop_front();
                }
                g.latencies_ms.push_back(latency);
            }
        }
    }

    /// Median of recent capture-to-pose latencies, ms.
    fn latency_median(g: &Inner) -> Option<f64> {
        let v: Vec<f64> = g.latencies_ms.iter().copied().collect();
        crate::stats::median(&v)
    }
}

/// The 95th percentile of `v` (the nearest rank), `None` when empty.
fn p95(v: &VecDeque<f64>) -> Option<f64> {
    let v: Vec<f64> = v.iter().copied().collect();
    crate::stats::quantile(&v, 0.95)
}

impl SlamShared {
    /// A copy of the SLAM's map, when a SLAM runs.
    pub fn map_snapshot(&self) -> Option<Map> {
        let src = self.lock().source.clone();
        src.and_then(|s| s.snapshot())
    }
}

impl SlamView for SlamShared {
    fn status(&self) -> SlamStatus {
        let g = self.lock();
        let mut s = g.status.clone();
        s.latency_ms_median = Self::latency_median(&g);
        s.latency_ms_p95 = p95(&g.latencies_ms);
        s.frame_ms_p95 = p95(&g.frame_ms);
        drop(g);
        s.fps = self.rate.rate();
        s
    }
    fn keyframes(&self) -> Vec<KeyframeInfo> {
        let src = self.lock().source.clone();
        src.map(|s| s.keyframes()).unwrap_or_default()
    }
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>> {
        let src = self.lock().source.clone();
        src.and_then(|s| s.keyframe_image(id))
    }
    fn map(&self, max_points: usize) -> MapView {
        let src = self.lock().source.clone();
        src.map(|s| s.map(max_points)).unwrap_or_default()
    }
    fn last_tracked(&self) -> Option<TrackedFrame> {
        self.lock().last_tracked
    }
    fn features(&self, seq: Option<u64>) -> Option<Arc<TrackedFeatures>> {
        let g = self.lock();
        match seq {
            None => g.features.back().cloned(),
            Some(seq) => g
                .features
                .iter()
                .rev()
                .find(|f| f.frame.seq == seq)
                .cloned(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn info(current_kf: u64) -> LoopInfo {
        LoopInfo {
            current_kf,
            loop_kf: 0,
            current_t: current_kf as f64,
            loop_t: 0.0,
            inliers: 91,
            projection_matches: 203,
            scale: 0.98,
            rotation_deg: 0.35,
            fused: 280,
            correction_ms: 80.0,
            at_unix: 1.0e9 + current_kf as f64,
        }
    }

    #[test]
    fn the_latest_frames_keypoints_are_kept_by_sequence_number() {
        use crate::slam::KeypointState;
        let shared = SlamShared::new(true);
        assert!(shared.features(None).is_none());
        let frame = |seq: u64| {
            Arc::new(Frame::from_image(
                seq,
                None,
                std::time::Instant::now(),
                unix_now(),
                Arc::new(GrayImage::new(64, 48)),
            ))
        };
        let outcome = |n: usize| ProcessOutcome {
            state: "tracking".into(),
            tracked: true,
            keypoints: (0..n)
                .map(|i| TrackedKeypoint {
                    x: i as f32,
                    y: 1.0,
                    state: KeypointState::Inlier,
                })
                .collect(),
            ..Default::default()
        };
        for seq in 0..(FEATURE_FRAMES as u64 + 4) {
            shared.record(&frame(seq), outcome(seq as usize + 1), 1.0);
        }
        // A frame without keypoints (no SLAM) is counted, not kept.
        shared.record(&frame(1000), ProcessOutcome::default(), 1.0);
        let newest = shared.features(None).unwrap();
        assert_eq!(newest.frame.seq, FEATURE_FRAMES as u64 + 3);
        assert_eq!(newest.keypoints.len(), FEATURE_FRAMES + 4);
        let f = shared.features(Some(10)).unwrap();
        assert_eq!(
            (f.frame.seq, f.keypoints.len(), f.state.as_str()),
            (10, 11, "tracking")
        );
        // The oldest went, and a frame never processed is not there.
        assert!(shared.features(Some(3)).is_none());
        assert!(shared.features(Some(4)).is_some());
        assert!(shared.features(Some(1000)).is_none());
        assert_eq!(shared.status().frames, FEATURE_FRAMES as u64 + 5);
    }

    #[test]
    fn loops_closed_are_counted_and_the_latest_listed() {
        let shared = SlamShared::new(true);
        assert_eq!(shared.status().loops_closed, 0);
        assert!(shared.status().loops.is_empty());
        shared.add_loop(info(224));
        let s = shared.status();
        assert_eq!(s.loops_closed, 1);
        assert_eq!(s.loops, vec![info(224)]);
        let v = serde_json::to_value(&s).unwrap();
        assert_eq!(v["loops"][0]["current_kf"], 224);
        assert_eq!(v["loops"][0]["loop_kf"], 0);
        assert_eq!(v["loops_closed"], 1);
        // Many loops: the count goes on, the list keeps the newest.
        for k in 0..30 {
            shared.add_loop(info(300 + k));
        }
        let s = shared.status();
        assert_eq!(s.loops_closed, 31);
        assert_eq!(s.loops.len(), SlamStatus::MAX_LOOPS);
        assert_eq!(s.loops.first().unwrap().current_kf, 310);
        assert_eq!(s.loops.last().unwrap().current_kf, 329);
    }

    #[test]
    fn merges_are_counted_and_the_latest_listed() {
        let shared = SlamShared::new(true);
        let merge = |current_kf: u64| MergeInfo {
            current_kf,
            merge_kf: 3,
            current_t: 99.7,
            merge_t: 1.3,
            from_map: 1,
            into_map: 0,
            inliers: 302,
            projection_matches: 493,
            scale: 0.97,
            keyframes_moved: 118,
            fused: 1006,
            correction_ms: 150.0,
            at_unix: 1.0,
        };
        let s = shared.status();
        assert_eq!((s.maps_started, s.merges_made), (0, 0));
        shared.set_maps_started(1);
        shared.add_merge(merge(304));
        let v = serde_json::to_value(shared.status()).unwrap();
        assert_eq!(v["maps_started"], 1);
        assert_eq!(v["merges_made"], 1);
        assert_eq!(v["merges"][0]["current_kf"], 304);
        assert_eq!(v["merges"][0]["from_map"], 1);
        assert_eq!(v["merges"][0]["into_map"], 0);
        for k in 0..25 {
            shared.add_merge(merge(400 + k));
        }
        let s = shared.status();
        assert_eq!(s.merges_made, 26);
        assert_eq!(s.merges.len(), SlamStatus::MAX_MERGES);
        assert_eq!(s.merges.last().unwrap().current_kf, 424);
    }

    /// A map source whose calls take the map's lock, as the SLAM's does,
    /// and say when a call has started.
    struct LockedSource {
        map_lock: Arc<Mutex<()>>,
        entered: std::sync::mpsc::Sender<u64>,
    }

    impl MapSource for LockedSource {
        fn keyframes(&self) -> Vec<KeyframeInfo> {
            Vec::new()
        }
        fn keyframe_image(&self, _id: u64) -> Option<Arc<GrayImage>> {
            None
        }
        fn map(&self, _max_points: usize) -> MapView {
            MapView {
                points: Vec::new(),
                total_points: 0,
                trajectory: Vec::new(),
            }
        }
        fn pin_keyframe(&self, id: u64) -> bool {
            let _ = self.entered.send(id);
            let _map = self.map_lock.lock().unwrap();
            true
        }
    }

    /// The SLAM thread writes the status while it holds the map's lock; a
    /// shot pins its keyframe in the map meanwhile. Neither may wait for
    /// the other (the pin once held the status's lock while it waited for
    /// the map's: the daemon froze, its API and SLAM with it).
    #[test]
    fn pinning_a_keyframe_while_the_slam_holds_the_map_never_deadlocks() {
        use std::sync::mpsc::channel;
        let shared = Arc::new(SlamShared::new(true));
        let map_lock = Arc::new(Mutex::new(()));
        let (entered_tx, entered) = channel();
        let source = Arc::new(LockedSource {
            map_lock: map_lock.clone(),
            entered: entered_tx,
        });
        // The SLAM holds the map while the source is attached and a shot
        // pins its keyframe: both wait in the source for the map.
        let slam_holds_map = map_lock.lock().unwrap();
        shared.pin_keyframe(3); // no source yet: only remembered
        let attach = {
            let (shared, source) = (shared.clone(), source.clone());
            std::thread::spawn(move || shared.set_source(source))
        };
        assert_eq!(
            entered.recv().unwrap(),
            3,
            "set_source pins what was pinned"
        );
        let pin = {
            let shared = shared.clone();
            std::thread::spawn(move || shared.pin_keyframe(7))
        };
        assert_eq!(entered.recv().unwrap(), 7);
        // Still holding the map, the SLAM writes the status: it must not
        // wait for the pins (a bound only to turn a deadlock into a
        // failure; the writes take microseconds).
        let (done_tx, done) = channel();
        {
            let shared = shared.clone();
            std::thread::spawn(move || {
                shared.set_map_mode(crate::slam::MapMode::VisionOnly, "test");
                shared.set_relocalised(1);
                let _ = done_tx.send(shared.status().map_mode);
            });
        }
        let mode = done.recv_timeout(Duration::from_secs(20));
        drop(slam_holds_map);
        attach.join().unwrap();
        pin.join().unwrap();
        assert!(
            mode.is_ok(),
            "the status writes waited for the map's lock: deadlock"
        );
        assert_eq!(shared.lock().pinned, vec![3, 7]);
    }
}
