//! The SLAM side of the daemon: the [`FrameProcessor`] the SLAM thread
//! drives, and [`SlamShared`], the status and map view the API reads.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use image::GrayImage;

use crate::api::{KeyframeInfo, MapView, SlamStatus, SlamView};
use crate::camera::Camera;
use crate::config::Config;
use crate::video::live::{Frame, RateMeter, unix_now};

/// What processing one frame gave.
#[derive(Debug, Clone, Default)]
pub struct ProcessOutcome {
    /// `not_initialized`, `tracking`, `lost`, `unavailable`.
    pub state: String,
    /// The frame's pose was estimated.
    pub tracked: bool,
    /// Inliers of the pose.
    pub inliers: usize,
    /// Keyframes in the map after the frame.
    pub keyframes: usize,
    /// Points in the map after the frame.
    pub points: usize,
}

/// The map as the API sees it (provided by the SLAM adapter).
pub trait MapSource: Send + Sync {
    /// Keyframes in id order.
    fn keyframes(&self) -> Vec<KeyframeInfo>;
    /// A keyframe's image.
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>>;
    /// Points (at most `max_points`) and trajectory.
    fn map(&self, max_points: usize) -> MapView;
}

/// Something that eats frames on the SLAM thread.
pub trait FrameProcessor: Send {
    /// Process one frame (the newest available).
    fn process(&mut self, frame: &Frame) -> ProcessOutcome;
    /// The input ended: finish (mapping, final optimisation) and save;
    /// returns the map file written.
    fn finish(self: Box<Self>) -> Option<PathBuf>;
}

/// The processor of a daemon without SLAM: it takes frames (so the ingest
/// counters show what a SLAM would get) and reports `unavailable`.
pub struct NoSlam;

impl FrameProcessor for NoSlam {
    fn process(&mut self, _frame: &Frame) -> ProcessOutcome {
        ProcessOutcome {
            state: "unavailable".into(),
            ..Default::default()
        }
    }
    fn finish(self: Box<Self>) -> Option<PathBuf> {
        None
    }
}

/// The processor for this build and configuration.
pub fn make_processor(
    cfg: &Config,
    _camera: Camera,
    _shared: Arc<SlamShared>,
    _map_file: PathBuf,
) -> Box<dyn FrameProcessor> {
    if cfg.slam.enabled {
        tracing::warn!("this build has no SLAM module yet: frames are taken but not tracked");
    }
    Box::new(NoSlam)
}

#[derive(Default)]
struct Inner {
    status: SlamStatus,
    latencies_ms: VecDeque<f64>,
    source: Option<Arc<dyn MapSource>>,
}

/// Status and map view shared by the SLAM thread and the API.
pub struct SlamShared {
    inner: Mutex<Inner>,
    rate: RateMeter,
}

/// Frames in the latency median.
const LATENCY_WINDOW: usize = 100;

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

    /// Attach the SLAM's map.
    pub fn set_source(&self, source: Arc<dyn MapSource>) {
        self.lock().source = Some(source);
    }

    /// Record one processed frame.
    pub fn record(&self, frame: &Frame, outcome: &ProcessOutcome, ms: f64) {
        self.rate.tick();
        let mut g = self.lock();
        let s = &mut g.status;
        s.state = outcome.state.clone();
        s.available = outcome.state != "unavailable";
        s.frames += 1;
        s.last_frame_ms = ms;
        s.last_inliers = outcome.inliers;
        s.keyframes = outcome.keyframes;
        s.points = outcome.points;
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
        if g.latencies_ms.is_empty() {
            return None;
        }
        let mut v: Vec<f64> = g.latencies_ms.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        Some(v[v.len() / 2])
    }
}

impl SlamView for SlamShared {
    fn status(&self) -> SlamStatus {
        let g = self.lock();
        let mut s = g.status.clone();
        s.latency_ms_median = Self::latency_median(&g);
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
}
