//! The SLAM side of the daemon: the [`FrameProcessor`] the SLAM thread
//! drives, and [`SlamShared`], the status and map view the API reads.

use std::collections::VecDeque;
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use image::GrayImage;

use crate::api::store::PoseJson;
use crate::api::{KeyframeInfo, MapView, SlamStatus, SlamView};
use crate::camera::Camera;
use crate::config::Config;
use crate::slam::{self, KeyFrameId, Map, Slam, TrackState};
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
    /// A copy of the whole map (for shot localisation, which must not hold
    /// the SLAM's lock while it works).
    fn snapshot(&self) -> Option<Map> {
        None
    }
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

/// The processor for this configuration: the SLAM, or [`NoSlam`] when
/// `[slam] enabled = false` or the SLAM cannot start.
pub fn make_processor(
    cfg: &Config,
    camera: Camera,
    shared: Arc<SlamShared>,
    map_file: PathBuf,
) -> Box<dyn FrameProcessor> {
    if !cfg.slam.enabled {
        return Box::new(NoSlam);
    }
    let (w, h) = (camera.width, camera.height);
    match Slam::new(camera, slam::Params::default()) {
        Ok(slam) => {
            shared.set_source(Arc::new(SlamMapSource { map: slam.map() }));
            Box::new(SlamProcessor {
                slam,
                map_file,
                size: (w, h),
                warned_size: false,
                clock: cfg.geo.history.clone(),
            })
        }
        Err(e) => {
            tracing::error!("SLAM cannot start: {e}");
            Box::new(NoSlam)
        }
    }
}

/// The SLAM on the SLAM thread.
pub struct SlamProcessor {
    slam: Slam,
    map_file: PathBuf,
    size: (u32, u32),
    warned_size: bool,
    /// How a frame's capture time is found (its keyframes carry it, and
    /// the georeference matches them to telemetry by it).
    clock: crate::geo::HistoryParams,
}

fn state_name(s: TrackState) -> &'static str {
    match s {
        TrackState::NotInitialized => "not_initialized",
        TrackState::Tracking => "tracking",
        TrackState::Lost => "lost",
    }
}

impl FrameProcessor for SlamProcessor {
    fn process(&mut self, frame: &Frame) -> ProcessOutcome {
        if frame.image.dimensions() != self.size {
            if !self.warned_size {
                tracing::error!(
                    frame = ?frame.image.dimensions(),
                    camera = ?self.size,
                    "video frame size differs from [camera] width/height: frames skipped"
                );
                self.warned_size = true;
            }
            return ProcessOutcome {
                state: "bad_frame_size".into(),
                ..Default::default()
            };
        }
        let t = crate::geo::capture_time(frame.received_unix, frame.capture_time, &self.clock);
        let out = self.slam.process(frame.seq, t, frame.image.clone());
        let (keyframes, points) = {
            let map = self.slam.map();
            let m = map.lock().unwrap_or_else(|e| e.into_inner());
            (m.keyframe_count(), m.point_count())
        };
        ProcessOutcome {
            state: state_name(out.state).into(),
            tracked: out.cam_from_world.is_some(),
            inliers: out.inliers,
            keyframes,
            points,
        }
    }

    fn finish(self: Box<Self>) -> Option<PathBuf> {
        let run = self.slam.finish();
        if run.map.keyframe_count() == 0 {
            return None;
        }
        if let Some(dir) = self.map_file.parent() {
            let _ = std::fs::create_dir_all(dir);
        }
        match slam::mapfile::save(&run.map, &self.map_file) {
            Ok(()) => {
                tracing::info!(
                    path = %self.map_file.display(),
                    keyframes = run.map.keyframe_count(),
                    points = run.map.point_count(),
                    "map saved"
                );
                Some(self.map_file)
            }
            Err(e) => {
                tracing::error!("saving the map: {e}");
                None
            }
        }
    }
}

/// The SLAM's map as the API sees it.
struct SlamMapSource {
    map: Arc<Mutex<Map>>,
}

impl SlamMapSource {
    fn lock(&self) -> std::sync::MutexGuard<'_, Map> {
        self.map.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl MapSource for SlamMapSource {
    fn keyframes(&self) -> Vec<KeyframeInfo> {
        let m = self.lock();
        let mut v: Vec<KeyframeInfo> = m
            .keyframes()
            .map(|k| {
                let (width, height) = k.image.as_ref().map_or((0, 0), |i| i.dimensions());
                KeyframeInfo {
                    id: k.id.0 as u64,
                    timestamp: k.timestamp,
                    world_from_cam: PoseJson::from_isometry(&k.cam_from_world.inverse()),
                    width,
                    height,
                }
            })
            .collect();
        v.sort_by_key(|k| k.id);
        v
    }

    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>> {
        let id = u32::try_from(id).ok()?;
        self.lock().keyframe(KeyFrameId(id))?.image.clone()
    }

    fn snapshot(&self) -> Option<Map> {
        Some(self.lock().clone())
    }

    fn map(&self, max_points: usize) -> MapView {
        let m = self.lock();
        let total = m.point_count();
        let step = total.div_ceil(max_points.max(1)).max(1);
        let points = m
            .points()
            .step_by(step)
            .take(max_points)
            .map(|p| {
                [
                    p.position.x as f32,
                    p.position.y as f32,
                    p.position.z as f32,
                ]
            })
            .collect();
        let mut kfs: Vec<_> = m
            .keyframes()
            .map(|k| (k.id.0, slam::center_of(&k.cam_from_world)))
            .collect();
        kfs.sort_by_key(|k| k.0);
        MapView {
            points,
            total_points: total,
            trajectory: kfs.into_iter().map(|(_, c)| [c.x, c.y, c.z]).collect(),
        }
    }
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
