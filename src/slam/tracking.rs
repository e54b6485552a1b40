//! Tracking, per frame: ORB extraction, then (after initialisation) the
//! constant-velocity motion model with search by projection, the reference
//! keyframe as fallback, the local map (`slam/local_map.rs`), motion-only
//! bundle adjustment, and the keyframe decision
//! (`slam/keyframe_decision.rs`). States: not initialised
//! ([`super::initializer`] builds the map), tracking, lost (the
//! relocaliser, `slam/relocalizer.rs`, finds the frame again through the
//! keyframe database, in any map of the atlas). Lost for
//! [`TrackingParams::new_map_after_lost_frames`] frames after tracking, a
//! new map starts at once: the initializer takes the next frames while
//! relocalisation into the old maps is still tried on each (success
//! abandons the new map); loop closing merges it back later
//! ([`super::loop_closing`]). A map loaded from a file starts lost and only
//! relocalises until its first tracked frame.

use std::sync::{Arc, Mutex};

use image::GrayImage;
use nalgebra::Isometry3;

use crate::optimize;

use crate::bow::Vocabulary;
use crate::camera::Camera;
use crate::features::OrbExtractor;
use crate::lie::renormalized;
use crate::matching::FeatureGrid;

use super::SlamError;
use super::aided::{self, Anchor, PoseSource, TelemetryAid};
use super::cpu_time::Stopwatch;
use super::frame::{Context, Frame, LastFrame, Marks, PoseFit};
pub use super::frame::{FrameRecord, KeypointState, TrackedKeypoint};
use super::initializer::{InitFailure, InitialMap, Initializer};
use super::keyframe_decision::{KeyFrameCandidate, need_new_keyframe};
use super::local_map::LocalMapTracker;
use super::map::{KeyFrameId, Map, MapId, MapMode, ScaleInfo, lock_timed};
use super::matcher;
use super::params::bound_history;
use super::priors::TelemetrySample;
use super::relocalizer::relocalize;

pub use super::params::TrackingParams;

mod aided_frame;
mod new_map;

/// Searches of the motion model: at [`TrackingParams::motion_search_radius`],
/// then once more, wider, when too few matches came back (ORB-SLAM's
/// `TrackWithMotionModel`: two).
const MOTION_SEARCH_TRIES: usize = 2;

/// The motion model's radius grows by this factor for its second search
/// (ORB-SLAM's `TrackWithMotionModel`: `2*th`).
const MOTION_SEARCH_WIDENING: f64 = 2.0;

/// Frames, counted from the relocalised one, whose local-map search runs
/// with [`TrackingParams::local_map_radius_after_reloc`] (ORB-SLAM's
/// `SearchLocalPoints`: `th = 5` while
/// `mCurrentFrame.mnId < mnLastRelocFrameId + 2`).
const JUST_RELOCALIZED_FRAMES: u64 = 2;

/// Why a frame was not tracked, or the map not initialised.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TrackFailure {
    /// The map is not initialised yet.
    #[error(transparent)]
    Init(#[from] InitFailure),
    /// Going on with a saved map: no frame relocalised in it yet.
    #[error("continuing on a saved map: not relocalised yet")]
    NotRelocalizedYet,
    /// While tracking, the motion model, the reference keyframe and
    /// relocalisation all failed.
    #[error("motion model, reference keyframe and relocalisation all failed")]
    Lost,
    /// While lost, relocalisation failed.
    #[error("relocalisation failed")]
    RelocalizationFailed,
    /// The pose optimisation on the local map failed.
    #[error("pose optimisation on the local map failed")]
    LocalMapOptimization,
    /// Too few inliers after the local map.
    #[error("only {found} inliers after the local map (need {needed})")]
    NotEnoughInliers {
        /// Inliers found.
        found: usize,
        /// Inliers needed.
        needed: usize,
    },
    /// Too much of the frame is masked (damaged video) to start a map on.
    #[error(
        "{masked_pct} % of the frame is masked (damaged video); a map starts on at most {max_pct} %"
    )]
    TooDamaged {
        /// Masked share of the frame, percent.
        masked_pct: u32,
        /// The most a frame may have masked to start a map or be a keyframe.
        max_pct: u32,
    },
}

/// The state of tracking.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TrackState {
    /// No map yet.
    NotInitialized,
    /// The last frame was tracked.
    Tracking,
    /// The last frame could not be tracked.
    Lost,
}

/// A new map started after a tracking loss (see
/// [`TrackingParams::new_map_after_lost_frames`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct MapStart {
    /// The first frame tracking failed on (the loss).
    pub lost_at: u64,
    /// The first frame given to the initializer for the new map.
    pub started_at: u64,
    /// The new map's id.
    pub map: MapId,
    /// The frame the new map was initialised with (`None`: not yet, or
    /// abandoned).
    pub initialized_at: Option<u64>,
    /// The frame that relocalised into an old map before the new one was
    /// initialised (the new map abandoned).
    pub relocalized_at: Option<u64>,
    /// The new map was put into the old one by the telemetry as soon as it
    /// initialised ([`super::aided::place_new_map`]).
    pub placed_by_telemetry: bool,
}

/// What tracking did with one frame.
#[derive(Debug, Clone)]
pub struct FrameOutcome {
    /// State after the frame.
    pub state: TrackState,
    /// The frame's pose when tracked.
    pub cam_from_world: Option<Isometry3<f64>>,
    /// How the pose was found (`None`: not posed).
    pub source: Option<PoseSource>,
    /// Matched map points (inliers).
    pub inliers: usize,
    /// Keyframe created from this frame, to hand to mapping.
    pub new_keyframe: Option<KeyFrameId>,
    /// The map was just initialised with this frame.
    pub initialized: bool,
    /// Why the frame was not tracked / the map not initialised.
    pub reason: Option<TrackFailure>,
    /// ORB extraction time, ms.
    pub extract_ms: f64,
    /// Whole frame time (extraction included), ms.
    pub track_ms: f64,
    /// Of `track_ms`, the wall time spent waiting for the map lock while
    /// another thread (local mapping, loop closing) held it, ms.
    pub lock_wait_ms: f64,
    /// ORB extraction, this thread's CPU ms (None without a thread clock).
    pub extract_cpu_ms: Option<f64>,
    /// Whole frame (extraction included), this thread's CPU ms.
    pub track_cpu_ms: Option<f64>,
    /// The frame's keypoints and what tracking made of each (all
    /// unmatched while the map is being initialised).
    pub keypoints: Vec<TrackedKeypoint>,
}

/// A tracked frame.
struct Tracked {
    /// Its pose.
    cam_from_world: Isometry3<f64>,
    /// Its inliers.
    inliers: usize,
    /// The keyframe made from it.
    new_keyframe: Option<KeyFrameId>,
    /// How the pose was found.
    source: PoseSource,
}

/// A frame's pose as one of tracking's ways found it, before
/// [`Tracker::accept`] takes it.
struct Accepted {
    cam_from_world: Isometry3<f64>,
    inliers: usize,
    source: PoseSource,
    recently_relocalized: bool,
    /// The frame's telemetry sample (with an attitude), if any.
    sample: Option<TelemetrySample>,
}

/// The tracker: owns the extractors and the motion state; works on the map
/// under its lock for short sections.
pub struct Tracker {
    ctx: Context,
    extractor: OrbExtractor,
    init_extractor: OrbExtractor,
    state: TrackState,
    initializer: Initializer,
    local_map: LocalMapTracker,
    last: Option<LastFrame>,
    /// `cam_from_world` of this frame times `world_from_cam` of the last
    /// (the constant-velocity model).
    velocity: Option<Isometry3<f64>>,
    /// Seconds between the two frames of `velocity` when vision posed both
    /// (0 otherwise: no rolling-shutter motion from it).
    velocity_dt: f64,
    reference_kf: Option<KeyFrameId>,
    last_kf_frame: u64,
    last_reloc_frame: Option<u64>,
    records: Vec<FrameRecord>,
    /// Records kept ([`super::Params::history`]).
    keep_records: Option<usize>,
    initialized_at: Option<u64>,
    last_reason: Option<TrackFailure>,
    marks: Marks,
    /// The map's loop corrections when the last frame was tracked.
    corrections_seen: u64,
    /// The map's [`Map::scale_applied`] when the last frame was tracked.
    scale_seen: f64,
    /// The map's merges already followed ([`Map::merges`]).
    merges_seen: usize,
    /// The frame tracking was lost at (reset when tracked again).
    lost_since: Option<u64>,
    /// A new map is being initialised (its entry is the last of
    /// `map_starts`).
    new_map_pending: bool,
    /// The new maps started, in order.
    map_starts: Vec<MapStart>,
    /// Share of the current frame's pixels masked (0: none).
    masked_share: f64,
    /// Telemetry-aided tracking (`None`: vision only).
    aid: Option<TelemetryAid>,
    /// The last frame vision posed, with its telemetry (for the aid).
    anchor: Option<Anchor>,
    /// The first frame of the current run posed by the telemetry alone.
    telemetry_since: Option<u64>,
    /// New maps must be put into the old one by the telemetry (the map is
    /// in local NED with telemetry priors): none is started otherwise.
    new_maps_need_placement: bool,
    /// The last new map put into the old one, until its scale is refit.
    placement: Option<aided::Placement>,
}

impl Tracker {
    /// A tracker for `camera`; `vocabulary` indexes keyframes and frames
    /// for relocalisation and BoW-guided matching.
    pub fn new(
        camera: Camera,
        params: TrackingParams,
        vocabulary: Arc<Vocabulary>,
    ) -> Result<Self, SlamError> {
        let extractor = OrbExtractor::new(params.features)?;
        let init_extractor = OrbExtractor::new(crate::features::Params {
            n_features: params.init_features,
            ..params.features
        })?;
        Ok(Tracker {
            ctx: Context::new(camera, params, vocabulary),
            extractor,
            init_extractor,
            state: TrackState::NotInitialized,
            initializer: Initializer::default(),
            local_map: LocalMapTracker::default(),
            last: None,
            velocity: None,
            velocity_dt: 0.0,
            reference_kf: None,
            last_kf_frame: 0,
            last_reloc_frame: None,
            records: Vec::new(),
            keep_records: None,
            initialized_at: None,
            last_reason: None,
            marks: Marks::default(),
            corrections_seen: 0,
            scale_seen: 1.0,
            merges_seen: 0,
            lost_since: None,
            new_map_pending: false,
            map_starts: Vec::new(),
            masked_share: 0.0,
            aid: None,
            anchor: None,
            telemetry_since: None,
            new_maps_need_placement: false,
            placement: None,
        })
    }

    /// Aid tracking with telemetry (see [`super::aided`]; `None`: vision
    /// only).
    pub fn set_telemetry_aid(&mut self, aid: Option<TelemetryAid>) {
        self.initializer.set_aid(aid.clone());
        self.aid = aid;
        self.anchor = None;
    }

    /// Start new maps after a loss only where the telemetry can put them
    /// into the old map at once (a map with telemetry priors is in local
    /// NED, and a map beside it in its own frame would break the priors).
    pub fn set_new_maps_need_placement(&mut self, need: bool) {
        self.new_maps_need_placement = need;
    }

    /// Go on with an existing map (a loaded map file): the tracker starts
    /// lost, so the next frame relocalises against the map.
    pub fn start_lost(&mut self) {
        self.state = TrackState::Lost;
        self.initializer.reset();
        self.last = None;
        self.velocity = None;
        self.reference_kf = None;
        self.last_reason = Some(TrackFailure::NotRelocalizedYet);
    }

    /// The vocabulary of the keyframe database.
    pub fn vocabulary(&self) -> &Arc<Vocabulary> {
        &self.ctx.vocabulary
    }

    /// The scale levels of the extractor.
    pub fn scale(&self) -> &ScaleInfo {
        &self.ctx.scale
    }

    /// State after the last frame.
    pub fn state(&self) -> TrackState {
        self.state
    }

    /// Frame index at which the map was initialised.
    pub fn initialized_at(&self) -> Option<u64> {
        self.initialized_at
    }

    /// The last reason a frame was not tracked or the map not initialised.
    pub fn last_reason(&self) -> Option<&TrackFailure> {
        self.last_reason.as_ref()
    }

    /// Keep at least the newest `keep` frame records and at most twice as
    /// many (`None`: all).
    pub fn set_history(&mut self, keep: Option<usize>) {
        self.keep_records = keep;
        bound_history(&mut self.records, keep);
    }

    /// Pose records of the tracked frames (every one unless
    /// [`Tracker::set_history`] bounds them).
    pub fn records(&self) -> &[FrameRecord] {
        &self.records
    }

    /// The new maps started after tracking losses, in order.
    pub fn map_starts(&self) -> &[MapStart] {
        &self.map_starts
    }

    /// Follow the map's merges not followed yet: the records placed on a
    /// merged map's keyframes (and the constant-velocity model when the
    /// last frame was) scale their translations as the merge scaled that
    /// map. Tracking does it before each frame; [`super::Slam::finish`]
    /// once more at the end.
    pub fn follow_merges(&mut self, map: &Map) {
        let merges = map.merges();
        if merges.len() < self.merges_seen {
            // The map was emptied (a failed first initialisation).
            self.merges_seen = merges.len();
        }
        for m in &merges[self.merges_seen..] {
            let moved: std::collections::HashSet<KeyFrameId> =
                m.keyframes.iter().copied().collect();
            let k = m.sim3.scale;
            if let Some(last) = self.records.last()
                && moved.contains(&last.reference)
                && let Some(v) = &mut self.velocity
            {
                v.translation.vector *= k;
            }
            if let Some(a) = &mut self.anchor
                && moved.contains(&a.record.reference)
            {
                a.scale(k);
            }
            for r in &mut self.records {
                if moved.contains(&r.reference) {
                    r.cam_from_ref.translation.vector *= k;
                }
            }
        }
        self.merges_seen = merges.len();
    }

    /// Track one frame. `mapping_idle` says whether mapping can take a
    /// keyframe now (tracking never waits for it).
    pub fn track(
        &mut self,
        map: &Mutex<Map>,
        index: u64,
        timestamp: f64,
        image: Arc<GrayImage>,
        mapping_idle: bool,
    ) -> FrameOutcome {
        self.track_masked(map, index, timestamp, image, None, mapping_idle)
    }

    /// [`Tracker::track`] on the pixels where `mask` is not 0 (the rows a
    /// lost video packet left intact): no feature is extracted whose patch
    /// reaches a masked pixel, and a frame masked beyond
    /// [`TrackingParams::max_masked_share`] neither becomes a keyframe nor
    /// starts a map; a frame masked whole is passed over (the state stays,
    /// it does not count as lost). A mask of another size than the image
    /// masks it all.
    pub fn track_masked(
        &mut self,
        map: &Mutex<Map>,
        index: u64,
        timestamp: f64,
        image: Arc<GrayImage>,
        mask: Option<&GrayImage>,
        mapping_idle: bool,
    ) -> FrameOutcome {
        let t0 = Stopwatch::start();
        let initializing = self.state == TrackState::NotInitialized || self.new_map_pending;
        self.masked_share = mask.map_or(0.0, |m| {
            if m.dimensions() != image.dimensions() {
                return 1.0;
            }
            let raw = m.as_raw();
            raw.iter().filter(|v| **v == 0).count() as f64 / raw.len().max(1) as f64
        });
        let extractor = if initializing {
            &mut self.init_extractor
        } else {
            &mut self.extractor
        };
        let mut feats = crate::features::Features::default();
        if let Err(e) = extractor.extract_into(&image, mask, Some(&self.ctx.camera), &mut feats) {
            // Only a mask of the wrong size fails: no pixel is trusted.
            tracing::warn!("frame {index}: {e}");
            feats = crate::features::Features::default();
        }
        let extract_ms = t0.wall_ms();
        let extract_cpu_ms = t0.cpu_ms();
        let grid = FeatureGrid::new(&feats.keypoints, self.ctx.bounds);
        let n = feats.keypoints.len();
        let mut frame = Frame {
            index,
            timestamp,
            keypoints: feats.keypoints,
            descriptors: feats.descriptors,
            grid,
            points: vec![None; n],
            image,
            bow: None,
            rejected: vec![false; n],
            prior: None,
            shutter: None,
        };
        let mut out = FrameOutcome {
            state: self.state,
            cam_from_world: None,
            source: None,
            inliers: 0,
            new_keyframe: None,
            initialized: false,
            reason: None,
            extract_ms,
            track_ms: 0.0,
            lock_wait_ms: 0.0,
            extract_cpu_ms,
            track_cpu_ms: None,
            keypoints: Vec::new(),
        };
        let max_masked = self.ctx.params.max_masked_share;
        if self.masked_share >= 1.0 {
            // Nothing of the frame can be trusted: it is passed over, not
            // lost (a lost frame would start a new map).
            out.reason = Some(TrackFailure::TooDamaged {
                masked_pct: 100,
                max_pct: (max_masked * 100.0).round() as u32,
            });
            out.track_ms = t0.wall_ms();
            out.track_cpu_ms = t0.cpu_ms();
            return out;
        }
        let result = if initializing && self.masked_share > max_masked {
            out.keypoints = frame.keypoint_states();
            Err(TrackFailure::TooDamaged {
                masked_pct: (self.masked_share * 100.0).round() as u32,
                max_pct: (max_masked * 100.0).round() as u32,
            })
        } else if self.new_map_pending {
            self.track_or_start_new_map(map, frame, mapping_idle, &mut out)
        } else if initializing {
            out.keypoints = frame.keypoint_states();
            match self.initializer.step(&self.ctx, map, frame) {
                Ok(Some(initial)) => {
                    out.initialized = true;
                    Ok(Some(self.start_tracking(initial)))
                }
                Ok(None) => Ok(None),
                Err(failure) => Err(TrackFailure::Init(failure)),
            }
        } else {
            let mut m = lock_timed(map, &mut out.lock_wait_ms);
            let r = self.track_frame(&mut m, &mut frame, mapping_idle).map(Some);
            out.keypoints = frame.keypoint_states();
            r
        };
        match result {
            Ok(Some(tracked)) => {
                self.state = TrackState::Tracking;
                self.lost_since = None;
                if tracked.source == PoseSource::Telemetry {
                    self.telemetry_since.get_or_insert(index);
                    self.maybe_start_new_map(map, index);
                } else {
                    self.telemetry_since = None;
                }
                out.cam_from_world = Some(tracked.cam_from_world);
                out.source = Some(tracked.source);
                out.inliers = tracked.inliers;
                out.new_keyframe = tracked.new_keyframe;
            }
            Ok(None) => {}
            Err(failure) => {
                // A frame the telemetry can no longer pose while a new map
                // is started is lost as any other.
                let lost_while_starting =
                    self.new_map_pending && self.state == TrackState::Tracking;
                if !initializing || lost_while_starting {
                    if self.state == TrackState::Tracking {
                        self.lost_since = Some(index);
                    }
                    self.state = TrackState::Lost;
                    self.velocity = None;
                    self.telemetry_since = None;
                    self.maybe_start_new_map(map, index);
                }
                out.reason = Some(failure.clone());
                self.last_reason = Some(failure);
            }
        }
        bound_history(&mut self.records, self.keep_records);
        out.state = self.state;
        out.track_ms = t0.wall_ms();
        out.track_cpu_ms = t0.cpu_ms();
        out
    }

    /// Start tracking on a new initial map: both frames are recorded at
    /// their keyframes, the second is the last frame and the reference.
    fn start_tracking(&mut self, initial: InitialMap) -> Tracked {
        if self.initialized_at.is_none() {
            self.initialized_at = Some(initial.second.index);
        }
        self.state = TrackState::Tracking;
        self.last_reason = None;
        self.initializer.set_need_gnss_baseline(false);
        for f in [initial.first, initial.second] {
            self.records.push(FrameRecord {
                index: f.index,
                timestamp: f.timestamp,
                reference: f.keyframe,
                cam_from_ref: Isometry3::identity(),
                source: PoseSource::Vision,
            });
        }
        let inliers = initial.matches.len();
        self.last = Some(LastFrame {
            timestamp: initial.second.timestamp,
            by_vision: true,
            keypoints: initial.keypoints,
            matches: initial.matches,
            cam_from_world: initial.cam_from_world,
        });
        self.velocity = None;
        self.reference_kf = Some(initial.second.keyframe);
        self.last_kf_frame = initial.second.index;
        self.anchor = None;
        Tracked {
            cam_from_world: initial.cam_from_world,
            inliers,
            new_keyframe: Some(initial.second.keyframe),
            source: PoseSource::Vision,
        }
    }

    /// Track an ordinary frame against the map.
    fn track_frame(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
        mapping_idle: bool,
    ) -> Result<Tracked, TrackFailure> {
        if map.scale_applied() != self.scale_seen {
            // The whole map was scaled (put in NED by telemetry): the
            // relative poses (records, constant-velocity model) scale too.
            let k = map.scale_applied() / self.scale_seen;
            self.scale_seen = map.scale_applied();
            for r in &mut self.records {
                r.cam_from_ref.translation.vector *= k;
            }
            if let Some(v) = &mut self.velocity {
                v.translation.vector *= k;
            }
            if let Some(a) = &mut self.anchor {
                a.scale(k);
            }
        }
        self.follow_merges(map);
        if map.corrections() != self.corrections_seen {
            self.corrections_seen = map.corrections();
            self.follow_correction(map);
        }
        // The camera's motion over this frame's readout: the
        // constant-velocity model per second (none for a global shutter).
        frame.shutter = self.velocity.and_then(|v| {
            let cam = &self.ctx.camera;
            optimize::RowMotion::from_velocity(cam.readout_s, cam.height, &v, self.velocity_dt)
        });
        // The telemetry's prediction of this frame, when vision may need it.
        let sample = self.aid.as_ref().and_then(|a| a.sample(frame.timestamp));
        let prediction = match (&self.aid, &self.anchor, &sample) {
            (Some(aid), Some(anchor), Some(now)) if self.state == TrackState::Tracking => {
                aided::predict(&aid.params, map, anchor, now)
            }
            _ => None,
        };
        let tracked = self.track_posed(map, frame, prediction, sample, mapping_idle);
        if let Ok(t) = &tracked
            && t.new_keyframe.is_some()
        {
            self.refit_placement(map);
        }
        tracked
    }

    /// [`Tracker::track_frame`] after the follow-ups: vision, else the
    /// telemetry's prediction.
    fn track_posed(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
        prediction: Option<aided::Prediction>,
        sample: Option<TelemetrySample>,
        mapping_idle: bool,
    ) -> Result<Tracked, TrackFailure> {
        match self.track_vision(map, frame, prediction.is_none(), sample.as_ref()) {
            Ok((cam_from_world, inliers, recently_relocalized)) => Ok(self.accept(
                map,
                frame,
                Accepted {
                    cam_from_world,
                    inliers,
                    source: PoseSource::Vision,
                    recently_relocalized,
                    sample,
                },
                mapping_idle,
            )),
            Err(failure) => {
                let Some(prediction) = prediction else {
                    return Err(failure);
                };
                Ok(self.track_aided(map, frame, prediction, sample, mapping_idle))
            }
        }
    }

    /// Vision alone: the motion model, the reference keyframe, then (when
    /// `relocalise`, or not tracking) relocalisation, then the local map.
    /// The pose, its inliers and whether the frame is soon after a
    /// relocalisation.
    fn track_vision(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
        relocalise: bool,
        sample: Option<&TelemetrySample>,
    ) -> Result<(Isometry3<f64>, usize, bool), TrackFailure> {
        let mut cam_from_world: Option<Isometry3<f64>> = None;
        if self.state == TrackState::Tracking {
            if let (Some(v), Some(last)) = (self.velocity, self.last.as_ref()) {
                let predicted = v * last.cam_from_world;
                cam_from_world = self.track_motion_model(map, frame, predicted);
            }
            if cam_from_world.is_none() {
                cam_from_world = self.track_reference_keyframe(map, frame);
            }
        }
        if cam_from_world.is_none() && (relocalise || self.state != TrackState::Tracking) {
            cam_from_world =
                relocalize(&self.ctx, &mut self.marks, map, frame).map(|fit| fit.cam_from_world);
            // In a map in local NED a relocalisation far from where the
            // GNSS puts the camera is a place that looks alike (rows of
            // trees, a lawn's stripes): refused.
            if let (Some(pose), Some(aid), Some(s)) = (cam_from_world, &self.aid, sample)
                && map.mode() == MapMode::GpsAided
                && let Some(off) = aided::gnss_disagreement(&aid.params, &pose, s)
            {
                tracing::info!(
                    frame = frame.index,
                    off_m = off,
                    "relocalisation refused: too far from the GNSS position"
                );
                frame.clear_matches();
                cam_from_world = None;
            }
            if cam_from_world.is_some() {
                self.last_reloc_frame = Some(frame.index);
                // Relocalised into whichever map it found: that one is
                // extended from now on.
                if let Some(m) = frame
                    .points
                    .iter()
                    .flatten()
                    .find_map(|p| map.map_of_point(*p))
                {
                    map.set_active_map(m);
                }
            }
        }
        let p = &self.ctx.params;
        let recently_relocalized = self
            .last_reloc_frame
            .is_some_and(|r| frame.index < r + p.max_frames_between_keyframes);
        let Some(cam_from_world) = cam_from_world else {
            return Err(if self.state == TrackState::Tracking {
                TrackFailure::Lost
            } else {
                TrackFailure::RelocalizationFailed
            });
        };
        let just_relocalized = self
            .last_reloc_frame
            .is_some_and(|r| frame.index < r + JUST_RELOCALIZED_FRAMES);
        let radius = if just_relocalized {
            p.local_map_radius_after_reloc
        } else {
            p.local_map_radius
        };
        let local = self.local_map.track(
            &self.ctx,
            &mut self.marks,
            map,
            frame,
            cam_from_world,
            radius,
            None,
        );
        if let Some(best) = local.reference {
            self.reference_kf = Some(best);
        }
        let PoseFit {
            cam_from_world,
            inliers,
        } = local.fit.ok_or(TrackFailure::LocalMapOptimization)?;
        let p = &self.ctx.params;
        let needed = if recently_relocalized {
            p.min_inliers_after_reloc
        } else {
            p.min_tracked_inliers
        };
        if inliers < needed {
            return Err(TrackFailure::NotEnoughInliers {
                found: inliers,
                needed,
            });
        }
        Ok((cam_from_world, inliers, recently_relocalized))
    }

    /// A frame posed: the motion model, the keyframe decision (only for a
    /// frame vision supports), its record, the last frame, and (for one
    /// vision posed) the telemetry's anchor.
    fn accept(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
        a: Accepted,
        mapping_idle: bool,
    ) -> Tracked {
        let Accepted {
            cam_from_world,
            inliers,
            source,
            recently_relocalized,
            sample,
        } = a;
        // Motion model.
        if let Some(last) = &self.last {
            self.velocity = Some(renormalized(cam_from_world * last.cam_from_world.inverse()));
            // The rolling shutter takes the motion only between two frames
            // vision posed: a telemetry-helped pose's error would be read
            // as the camera's velocity.
            self.velocity_dt = if source == PoseSource::Vision && last.by_vision {
                frame.timestamp - last.timestamp
            } else {
                0.0
            };
        }
        let reference = self.reference_kf.unwrap_or(KeyFrameId(0));
        let mut new_keyframe = None;
        let p = &self.ctx.params;
        let candidate = KeyFrameCandidate {
            frame_index: frame.index,
            last_keyframe_frame: self.last_kf_frame,
            inliers,
            mapping_idle,
            recently_relocalized,
            reference: self.reference_kf,
        };
        let supported = source == PoseSource::Vision || inliers >= p.min_tracked_inliers;
        if supported
            && self.masked_share <= p.max_masked_share
            && need_new_keyframe(p, map, &candidate)
        {
            let id = self.insert_keyframe(map, frame, cam_from_world);
            self.reference_kf = Some(id);
            self.last_kf_frame = frame.index;
            new_keyframe = Some(id);
        }
        let reference = new_keyframe.unwrap_or(reference);
        let ref_from_world = map
            .keyframe(reference)
            .map_or(cam_from_world, |k| k.cam_from_world);
        let record = FrameRecord {
            index: frame.index,
            timestamp: frame.timestamp,
            reference,
            cam_from_ref: cam_from_world * ref_from_world.inverse(),
            source,
        };
        self.records.push(record);
        if source == PoseSource::Telemetry {
            frame.clear_matches();
        } else {
            self.anchor = sample.map(|sample| {
                let velocity_cam = self.anchor.as_ref().and_then(|old| {
                    let dt = frame.timestamp - old.record.timestamp;
                    let before = old.cam_from_world(map)?;
                    let moved = cam_from_world.inverse().translation.vector
                        - before.inverse().translation.vector;
                    (dt > 0.0).then(|| cam_from_world.rotation * (moved / dt))
                });
                Anchor {
                    record,
                    sample,
                    velocity_cam,
                }
            });
        }
        tracing::trace!(
            frame = frame.index,
            source = source.name(),
            inliers,
            keyframe = new_keyframe.map(|k| k.0),
            "frame posed"
        );
        self.last = Some(LastFrame {
            timestamp: frame.timestamp,
            by_vision: source == PoseSource::Vision,
            keypoints: frame.keypoints.clone(),
            matches: frame.matches(),
            cam_from_world,
        });
        Tracked {
            cam_from_world,
            inliers,
            new_keyframe,
            source,
        }
    }

    /// A loop correction moved the keyframes: the last frame follows its
    /// reference keyframe (the constant-velocity model is relative and
    /// stays).
    fn follow_correction(&mut self, map: &Map) {
        let (Some(last), Some(rec)) = (self.last.as_mut(), self.records.last()) else {
            return;
        };
        if let Some(ref_pose) = map.keyframe_pose(rec.reference) {
            last.cam_from_world = renormalized(rec.cam_from_ref * ref_pose);
        }
    }

    /// Add a keyframe made from `frame` to the map. It is indexed in the
    /// keyframe database now when the frame's BoW vector was computed
    /// anyway; otherwise mapping indexes it (off the tracking thread).
    fn insert_keyframe(
        &self,
        map: &mut Map,
        frame: &mut Frame,
        cam_from_world: Isometry3<f64>,
    ) -> KeyFrameId {
        let id = map.add_keyframe(frame.to_keyframe(cam_from_world));
        if let Some((bow, fv)) = frame.bow.take() {
            map.index_keyframe(id, bow, fv, self.ctx.vocabulary.word_count());
        }
        id
    }

    /// Search the last frame's points around where the constant-velocity
    /// model puts them (`predicted`), widening once, and optimise.
    fn track_motion_model(
        &mut self,
        map: &Map,
        frame: &mut Frame,
        predicted: Isometry3<f64>,
    ) -> Option<Isometry3<f64>> {
        let last = self.last.as_ref()?;
        let p = &self.ctx.params;
        let mut th = p.motion_search_radius;
        let mut found = Vec::new();
        for _ in 0..MOTION_SEARCH_TRIES {
            frame.clear_matches();
            found = matcher::search_last_frame(
                &frame.search_target(),
                &last.keypoints,
                &last.matches,
                map,
                &predicted,
                &self.ctx.bounds,
                th,
                &p.matcher,
            );
            if found.len() >= p.min_motion_matches {
                break;
            }
            th *= MOTION_SEARCH_WIDENING;
        }
        if found.len() < p.min_motion_matches {
            return None;
        }
        frame.set_matches(found);
        let fit = self.ctx.optimize_frame_pose(map, frame, predicted)?;
        (fit.inliers >= self.ctx.params.min_pose_inliers).then_some(fit.cam_from_world)
    }

    /// Match the reference keyframe's points by descriptor (ratio test and
    /// rotation check) and optimise from the last pose.
    fn track_reference_keyframe(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
    ) -> Option<Isometry3<f64>> {
        let reference = self.reference_kf?;
        self.ctx.ensure_indexed(map, reference);
        let start = self.last.as_ref().map_or_else(
            || map.keyframe(reference).map(|k| k.cam_from_world),
            |l| Some(l.cam_from_world),
        )?;
        let p = &self.ctx.params;
        // BoW-guided when the keyframe is indexed, else by brute force.
        let matches = match map.places().and_then(|pl| pl.features.get(&reference)) {
            Some(kf_fv) => {
                let fv = self.ctx.frame_bow(frame).1.clone();
                matcher::search_by_bow(
                    map,
                    reference,
                    kf_fv,
                    &frame.descriptors,
                    &frame.keypoints,
                    &fv,
                    &p.matcher,
                    p.reference_ratio,
                )
            }
            None => matcher::search_keyframe_by_descriptor(
                map,
                reference,
                &frame.keypoints,
                &frame.descriptors,
                &p.matcher,
                p.reference_ratio,
            ),
        };
        if matches.len() < p.min_reference_matches {
            return None;
        }
        frame.clear_matches();
        frame.set_matches(matches);
        let fit = self.ctx.optimize_frame_pose(map, frame, start)?;
        (fit.inliers >= self.ctx.params.min_pose_inliers).then_some(fit.cam_from_world)
    }
}
