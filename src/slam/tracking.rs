//! Tracking, per frame: ORB extraction, then (after initialisation) the
//! constant-velocity motion model with search by projection, the reference
//! keyframe as fallback, the local map, motion-only bundle adjustment, and
//! the keyframe decision (ORB-SLAM's criteria). States: not initialised,
//! tracking, lost; when lost, relocalisation through the keyframe database
//! (BoW candidates, BoW-guided matching, PnP RANSAC, refinement by
//! projection). Initialisation on planar scenes resolves the homography's
//! twin reconstructions with intermediate frames ([`super::planar`]).

use std::sync::{Arc, Mutex, MutexGuard};

use image::GrayImage;
use nalgebra::{Isometry3, Point2, UnitQuaternion};

use crate::bow::{BowVector, FeatureVector, Vocabulary};
use crate::camera::Camera;
use crate::features::{Descriptor, KeyPoint, OrbExtractor, hamming};
use crate::geometry::{self, PnpParams, TwoViewParams};
use crate::optimize::{
    self, BaParams, BaPose, BaProblem, Intrinsics, Observation, PoseObservation, PoseParams,
};

use super::SlamError;
use super::cpu_time::Stopwatch;
use super::map::{self, KeyFrame, KeyFrameId, Map, PointId, ScaleInfo};
use super::matcher::{self, MatcherParams, SearchTarget};
use super::planar;
use crate::matching::{Bounds, FeatureGrid};

/// Tunable numbers of tracking.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackingParams {
    /// ORB extractor for tracking.
    pub features: crate::features::Params,
    /// Features of the two initialisation frames (ORB-SLAM uses twice as many).
    pub init_features: usize,
    /// Matches needed between the initialisation frames to try.
    pub init_min_matches: usize,
    /// Search window of initialisation matching, pixels.
    pub init_window: f64,
    /// Highest pyramid level matched between the initialisation frames
    /// (ORB-SLAM: 0); a keypoint is matched with keypoints one level up or
    /// down.
    pub init_max_octave: i32,
    /// Planar scenes: the twin reconstruction is rejected when its
    /// third-view cost exceeds the chosen one's by this factor.
    pub planar_cost_ratio: f64,
    /// Planar scenes: the chosen reconstruction's third-view cost (mean
    /// squared reprojection error, pixels²) must stay below this.
    pub planar_max_cost: f64,
    /// Map points the initial map must keep after its bundle adjustment.
    pub init_min_points: usize,
    /// Search radius factor of the motion-model search, pixels at level 0.
    pub motion_search_radius: f64,
    /// Matches needed from the motion model before optimising.
    pub min_motion_matches: usize,
    /// Inliers needed to call a frame tracked after the local map.
    pub min_tracked_inliers: usize,
    /// Inliers needed in the frames right after a relocalisation.
    pub min_inliers_after_reloc: usize,
    /// Frames between keyframes at most (ORB-SLAM: the frame rate).
    pub max_frames_between_keyframes: u64,
    /// Frames between keyframes at least.
    pub min_frames_between_keyframes: u64,
    /// A keyframe is due when the tracked points fall below this share of
    /// the reference keyframe's.
    pub keyframe_ref_ratio: f64,
    /// Local keyframes at most.
    pub max_local_keyframes: usize,
    /// Descriptor matching thresholds.
    pub matcher: MatcherParams,
    /// Bag of words: direct-index level and relocalisation candidates.
    pub bow: crate::bow::Params,
    /// Relocalisation tries at most this many candidate keyframes.
    pub reloc_max_candidates: usize,
    /// Matches a relocalisation candidate needs from BoW matching.
    pub reloc_min_bow_matches: usize,
    /// Two-view initialisation.
    pub two_view: TwoViewParams,
    /// Motion-only bundle adjustment.
    pub pose: PoseParams,
    /// PnP for relocalisation.
    pub pnp: PnpParams,
    /// Bundle adjustment of the initial map.
    pub init_ba: BaParams,
    /// Seed of the randomised steps.
    pub seed: u64,
}

impl Default for TrackingParams {
    fn default() -> Self {
        TrackingParams {
            features: crate::features::Params::default(),
            init_features: 2000,
            init_min_matches: 100,
            init_window: 100.0,
            init_max_octave: 2,
            planar_cost_ratio: 2.0,
            planar_max_cost: 2.0,
            init_min_points: 80,
            motion_search_radius: 15.0,
            min_motion_matches: 20,
            min_tracked_inliers: 30,
            min_inliers_after_reloc: 50,
            max_frames_between_keyframes: 30,
            min_frames_between_keyframes: 0,
            keyframe_ref_ratio: 0.9,
            max_local_keyframes: 80,
            matcher: MatcherParams::default(),
            bow: crate::bow::Params::default(),
            reloc_max_candidates: 30,
            reloc_min_bow_matches: 15,
            two_view: TwoViewParams::default(),
            pose: PoseParams::default(),
            pnp: PnpParams::default(),
            init_ba: BaParams {
                first_pass_iterations: 20,
                second_pass_iterations: 10,
                ..BaParams::default()
            },
            seed: 1,
        }
    }
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

/// The pose record of one frame, relative to its reference keyframe (so it
/// follows the keyframe when mapping moves it).
#[derive(Debug, Clone, Copy)]
pub struct FrameRecord {
    /// Frame index in the input.
    pub index: u64,
    /// Capture time, seconds.
    pub timestamp: f64,
    /// The reference keyframe.
    pub reference: KeyFrameId,
    /// cam_from_world of the frame = `cam_from_ref` * ref.cam_from_world.
    pub cam_from_ref: Isometry3<f64>,
}

/// What tracking did with one frame.
#[derive(Debug, Clone)]
pub struct FrameOutcome {
    /// State after the frame.
    pub state: TrackState,
    /// The frame's pose when tracked.
    pub cam_from_world: Option<Isometry3<f64>>,
    /// Matched map points (inliers).
    pub inliers: usize,
    /// Keyframe created from this frame, to hand to mapping.
    pub new_keyframe: Option<KeyFrameId>,
    /// The map was just initialised with this frame.
    pub initialized: bool,
    /// Why the frame was not tracked / the map not initialised.
    pub reason: Option<String>,
    /// ORB extraction time, ms.
    pub extract_ms: f64,
    /// Whole frame time (extraction included), ms.
    pub track_ms: f64,
    /// ORB extraction, this thread's CPU ms (None without a thread clock).
    pub extract_cpu_ms: Option<f64>,
    /// Whole frame (extraction included), this thread's CPU ms.
    pub track_cpu_ms: Option<f64>,
}

/// A frame being tracked.
struct Frame {
    index: u64,
    timestamp: f64,
    keypoints: Vec<KeyPoint>,
    descriptors: Vec<Descriptor>,
    grid: FeatureGrid,
    points: Vec<Option<PointId>>,
    image: Arc<GrayImage>,
    /// BoW vector and direct index, computed when first needed.
    bow: Option<(BowVector, FeatureVector)>,
}

impl Frame {
    /// The frame as the matcher searches it.
    fn search_target(&self) -> SearchTarget<'_> {
        SearchTarget {
            keypoints: &self.keypoints,
            descriptors: &self.descriptors,
            grid: &self.grid,
            points: &self.points,
        }
    }

    fn matches(&self) -> Vec<(usize, PointId)> {
        self.points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.map(|p| (i, p)))
            .collect()
    }
}

/// The first frame of an initialisation attempt.
struct InitFrame {
    frame: Frame,
    /// Where each of its keypoints was last matched (window centre).
    prev: Vec<Point2<f64>>,
    /// Later frames matched with it, to tell planar reconstructions apart.
    third_views: Vec<planar::ThirdView>,
}

/// The previous tracked frame.
struct LastFrame {
    keypoints: Vec<KeyPoint>,
    matches: Vec<(usize, PointId)>,
    cam_from_world: Isometry3<f64>,
}

/// The tracker: owns the extractors and the motion state; works on the map
/// under its lock for short sections.
pub struct Tracker {
    params: TrackingParams,
    extractor: OrbExtractor,
    init_extractor: OrbExtractor,
    camera: Camera,
    bounds: Bounds,
    scale: ScaleInfo,
    intrinsics: Intrinsics,
    vocabulary: Arc<Vocabulary>,
    state: TrackState,
    init: Option<InitFrame>,
    last: Option<LastFrame>,
    velocity: Option<Isometry3<f64>>,
    reference_kf: Option<KeyFrameId>,
    last_kf_frame: u64,
    last_reloc_frame: Option<u64>,
    records: Vec<FrameRecord>,
    initialized_at: Option<u64>,
    last_reason: Option<String>,
    attempt: u64,
    marks: Marks,
    /// Scratch list of the local map's projected points.
    projected: Vec<matcher::Projected>,
}

/// Per-pass marks on map points and keyframes, indexed by id (ORB-SLAM's
/// `mnTrackReferenceForFrame`): "seen in this pass" without building a set
/// per frame. A pass number is never reused while marks of it remain.
#[derive(Debug, Default)]
struct Marks {
    pass: u32,
    point: Vec<u32>,
    keyframe: Vec<u32>,
    /// Shared-point count per keyframe, valid where `keyframe` holds the
    /// current pass.
    count: Vec<u32>,
}

impl Marks {
    /// Start a new pass: nothing is marked in it yet.
    fn next_pass(&mut self) {
        if self.pass == u32::MAX {
            self.point.iter_mut().for_each(|m| *m = 0);
            self.keyframe.iter_mut().for_each(|m| *m = 0);
            self.pass = 0;
        }
        self.pass += 1;
    }

    /// Mark a point in this pass; false when it already was.
    #[inline]
    fn mark_point(&mut self, id: PointId) -> bool {
        let i = id.0 as usize;
        if i >= self.point.len() {
            self.point.resize((i + 1).next_power_of_two(), 0);
        }
        let fresh = self.point[i] != self.pass;
        self.point[i] = self.pass;
        fresh
    }

    /// Mark a keyframe in this pass (its count starts at 0); false when it
    /// already was.
    #[inline]
    fn mark_keyframe(&mut self, id: KeyFrameId) -> bool {
        let i = id.0 as usize;
        if i >= self.keyframe.len() {
            let n = (i + 1).next_power_of_two();
            self.keyframe.resize(n, 0);
            self.count.resize(n, 0);
        }
        if self.keyframe[i] == self.pass {
            return false;
        }
        self.keyframe[i] = self.pass;
        self.count[i] = 0;
        true
    }
}

fn lock(map: &Mutex<Map>) -> MutexGuard<'_, Map> {
    // A panic in another thread while holding the lock leaves the map as it
    // was between two whole operations; keep going with it.
    map.lock().unwrap_or_else(|e| e.into_inner())
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
        let scale = ScaleInfo::new(
            params.features.scale_factor as f64,
            params.features.n_levels,
        );
        Ok(Tracker {
            extractor,
            init_extractor,
            bounds: Bounds::of(&camera),
            intrinsics: Intrinsics {
                fx: camera.fx,
                fy: camera.fy,
                cx: camera.cx,
                cy: camera.cy,
            },
            camera,
            scale,
            params,
            vocabulary,
            state: TrackState::NotInitialized,
            init: None,
            last: None,
            velocity: None,
            reference_kf: None,
            last_kf_frame: 0,
            last_reloc_frame: None,
            records: Vec::new(),
            initialized_at: None,
            last_reason: None,
            attempt: 0,
            marks: Marks::default(),
            projected: Vec::new(),
        })
    }

    /// Go on with an existing map (a loaded map file): the tracker starts
    /// lost, so the next frame relocalises against the map.
    pub fn start_lost(&mut self) {
        self.state = TrackState::Lost;
        self.init = None;
        self.last = None;
        self.velocity = None;
        self.reference_kf = None;
        self.last_reason = Some("continuing on a saved map: not relocalised yet".into());
    }

    /// The vocabulary of the keyframe database.
    pub fn vocabulary(&self) -> &Arc<Vocabulary> {
        &self.vocabulary
    }

    /// The scale levels of the extractor.
    pub fn scale(&self) -> &ScaleInfo {
        &self.scale
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
    pub fn last_reason(&self) -> Option<&str> {
        self.last_reason.as_deref()
    }

    /// Pose records of every tracked frame.
    pub fn records(&self) -> &[FrameRecord] {
        &self.records
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
        let t0 = Stopwatch::start();
        let initializing = self.state == TrackState::NotInitialized;
        let feats = if initializing {
            self.init_extractor.extract(&image, Some(&self.camera))
        } else {
            self.extractor.extract(&image, Some(&self.camera))
        };
        let extract_ms = t0.wall_ms();
        let extract_cpu_ms = t0.cpu_ms();
        let grid = FeatureGrid::new(&feats.keypoints, self.bounds);
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
        };
        let mut out = FrameOutcome {
            state: self.state,
            cam_from_world: None,
            inliers: 0,
            new_keyframe: None,
            initialized: false,
            reason: None,
            extract_ms,
            track_ms: 0.0,
            extract_cpu_ms,
            track_cpu_ms: None,
        };
        if initializing {
            match self.try_initialize(map, frame) {
                Ok(Some(outcome)) => {
                    out.state = TrackState::Tracking;
                    out.cam_from_world = Some(outcome.0);
                    out.inliers = outcome.1;
                    out.new_keyframe = Some(outcome.2);
                    out.initialized = true;
                }
                Ok(None) => {}
                Err(reason) => {
                    out.reason = Some(reason.clone());
                    self.last_reason = Some(reason);
                }
            }
            out.state = self.state;
            out.track_ms = t0.wall_ms();
            out.track_cpu_ms = t0.cpu_ms();
            return out;
        }

        let result = {
            let mut m = lock(map);
            self.track_frame(&mut m, &mut frame, mapping_idle)
        };
        match result {
            Ok((pose, inliers, new_kf)) => {
                self.state = TrackState::Tracking;
                out.cam_from_world = Some(pose);
                out.inliers = inliers;
                out.new_keyframe = new_kf;
            }
            Err(reason) => {
                self.state = TrackState::Lost;
                self.velocity = None;
                out.reason = Some(reason.clone());
                self.last_reason = Some(reason);
            }
        }
        out.state = self.state;
        out.track_ms = t0.wall_ms();
        out.track_cpu_ms = t0.cpu_ms();
        out
    }

    /// One initialisation step: Ok(Some) on success with (pose, points,
    /// second keyframe), Ok(None) when the frame became the first frame of a
    /// new attempt, Err(reason) while not initialised.
    fn try_initialize(
        &mut self,
        map: &Mutex<Map>,
        frame: Frame,
    ) -> Result<Option<(Isometry3<f64>, usize, KeyFrameId)>, String> {
        let Some(init) = self.init.take() else {
            if frame.keypoints.len() > self.params.init_min_matches {
                let prev = frame
                    .keypoints
                    .iter()
                    .map(|k| Point2::new(k.ux as f64, k.uy as f64))
                    .collect();
                self.init = Some(InitFrame {
                    frame,
                    prev,
                    third_views: Vec::new(),
                });
                return Ok(None);
            }
            return Err(format!(
                "frame has {} keypoints, too few to start initialisation",
                frame.keypoints.len()
            ));
        };
        let m12 = matcher::search_for_initialization(
            &init.frame.keypoints,
            &init.frame.descriptors,
            &frame.keypoints,
            &frame.descriptors,
            &frame.grid,
            &init.prev,
            self.params.init_window,
            self.params.init_max_octave,
            &self.params.matcher,
        );
        let matches: Vec<(usize, usize)> = m12
            .iter()
            .enumerate()
            .filter_map(|(i, m)| m.map(|j| (i, j)))
            .collect();
        if matches.len() < self.params.init_min_matches {
            let reason = format!(
                "only {} matches with the initialisation frame (need {}); starting over from this frame",
                matches.len(),
                self.params.init_min_matches
            );
            // Start a new attempt from this frame.
            if frame.keypoints.len() > self.params.init_min_matches {
                let prev = frame
                    .keypoints
                    .iter()
                    .map(|k| Point2::new(k.ux as f64, k.uy as f64))
                    .collect();
                self.init = Some(InitFrame {
                    frame,
                    prev,
                    third_views: Vec::new(),
                });
            }
            return Err(reason);
        }
        let mut init = init;
        for &(i, j) in &matches {
            let k = &frame.keypoints[j];
            init.prev[i] = Point2::new(k.ux as f64, k.uy as f64);
        }
        let kp1: Vec<Point2<f64>> = init
            .frame
            .keypoints
            .iter()
            .map(|k| Point2::new(k.ux as f64, k.uy as f64))
            .collect();
        let kp2: Vec<Point2<f64>> = frame
            .keypoints
            .iter()
            .map(|k| Point2::new(k.ux as f64, k.uy as f64))
            .collect();
        self.attempt += 1;
        let tv = geometry::initialize_two_view(
            &self.camera.k(),
            &kp1,
            &kp2,
            &matches,
            &self.params.two_view,
            self.params.seed.wrapping_add(self.attempt),
        );
        let tv = match tv {
            Ok(tv) => Ok(tv),
            Err(e @ geometry::GeometryError::Ambiguous { .. }) => self
                .resolve_planar(&init, &kp1, &kp2, &matches)
                .map_err(|why| format!("{e}; {why}")),
            Err(e) => Err(e.to_string()),
        };
        init.third_views.push(planar::ThirdView {
            index: frame.index,
            seen: matches.iter().map(|&(i, j)| (i, kp2[j])).collect(),
        });
        if init.third_views.len() > 64 {
            // Keep them spread over the attempt: drop every other one.
            let mut n = 0;
            init.third_views.retain(|_| {
                n += 1;
                n % 2 == 1
            });
        }
        let tv = match tv {
            Ok(tv) => tv,
            Err(e) => {
                let reason = format!(
                    "two-view initialisation refused ({} matches): {e}",
                    matches.len()
                );
                self.init = Some(init);
                return Err(reason);
            }
        };
        match self.create_initial_map(map, &init.frame, &frame, &matches, &tv) {
            Ok(r) => {
                self.initialized_at = Some(frame.index);
                self.state = TrackState::Tracking;
                self.last_reason = None;
                Ok(Some(r))
            }
            Err(reason) => {
                // The reconstruction did not hold; try again from this frame.
                let prev = frame
                    .keypoints
                    .iter()
                    .map(|k| Point2::new(k.ux as f64, k.uy as f64))
                    .collect();
                self.init = Some(InitFrame {
                    frame,
                    prev,
                    third_views: Vec::new(),
                });
                Err(reason)
            }
        }
    }

    /// A planar pair both of whose reconstructions hold: decide between
    /// them with the frames seen in between (see [`planar`]).
    fn resolve_planar(
        &self,
        init: &InitFrame,
        kp1: &[Point2<f64>],
        kp2: &[Point2<f64>],
        matches: &[(usize, usize)],
    ) -> Result<geometry::TwoViewResult, String> {
        let mut relaxed = self.params.two_view.clone();
        relaxed.h_second_fraction = f64::INFINITY;
        let tv = geometry::initialize_two_view(
            &self.camera.k(),
            kp1,
            kp2,
            matches,
            &relaxed,
            self.params.seed.wrapping_add(self.attempt),
        )
        .map_err(|e| e.to_string())?;
        if tv.model != geometry::Model::Homography {
            return Err("the motion hypotheses of F are alike".into());
        }
        let [a, b] =
            planar::twin_hypotheses(&self.camera, kp1, kp2, matches, &tv, &self.params.two_view)
                .ok_or("the homography gives no second reconstruction")?;
        let (first, last) = (
            init.frame.index,
            init.third_views.last().map_or(0, |v| v.index),
        );
        if init.third_views.is_empty() || last <= first {
            return Err("no third view yet to choose between the planar reconstructions".into());
        }
        // Third views near a quarter, half and three quarters of the way.
        let span = (last.saturating_sub(first) + 1) as f64;
        let mut picked: Vec<&planar::ThirdView> = Vec::new();
        for q in [0.25, 0.5, 0.75] {
            let target = first as f64 + q * span;
            if let Some(v) = init.third_views.iter().min_by(|x, y| {
                (x.index as f64 - target)
                    .abs()
                    .total_cmp(&(y.index as f64 - target).abs())
            }) && !picked.iter().any(|p| p.index == v.index)
            {
                picked.push(v);
            }
        }
        let (mut ca, mut cb, mut used) = (0.0, 0.0, 0usize);
        for (n, v) in picked.iter().enumerate() {
            let seed = self.params.seed.wrapping_add(v.index * 7 + n as u64);
            let (Some(x), Some(y)) = (
                planar::third_view_cost(&self.camera, &a, matches, v, &self.params.pnp, seed),
                planar::third_view_cost(&self.camera, &b, matches, v, &self.params.pnp, seed),
            ) else {
                continue;
            };
            ca += x;
            cb += y;
            used += 1;
        }
        if used == 0 {
            return Err("the third views share too few points".into());
        }
        let (ca, cb) = (ca / used as f64, cb / used as f64);
        tracing::debug!(
            frame = init.third_views.last().map_or(0, |v| v.index),
            good_a = a.n_good,
            good_b = b.n_good,
            cost_a = ca,
            cost_b = cb,
            views = used,
            "planar reconstructions"
        );
        let p = &self.params;
        let (win, lose, cw, cl) = if ca <= cb {
            (&a, &b, ca, cb)
        } else {
            (&b, &a, cb, ca)
        };
        if cl < p.planar_cost_ratio * cw || cw > p.planar_max_cost {
            return Err(format!(
                "third views do not tell the planar reconstructions apart (costs {cw:.2} and {cl:.2} px²)"
            ));
        }
        if win.parallax_deg < p.two_view.min_parallax_deg {
            return Err(format!(
                "not enough parallax: {:.3} deg, needed {:.3} deg",
                win.parallax_deg, p.two_view.min_parallax_deg
            ));
        }
        let needed = ((p.two_view.min_good_fraction
            * tv.inliers.iter().filter(|b| **b).count() as f64)
            .ceil() as usize)
            .max(p.two_view.min_triangulated);
        if win.n_good < needed {
            return Err(format!("only {} good points (need {needed})", win.n_good));
        }
        Ok(planar::as_result(&tv, win, lose.n_good))
    }

    /// The frame's BoW vector and direct index (computed once).
    fn frame_bow<'f>(&self, frame: &'f mut Frame) -> &'f (BowVector, FeatureVector) {
        frame.bow.get_or_insert_with(|| {
            self.vocabulary
                .transform_with_features(&frame.descriptors, self.params.bow.direct_index_level)
        })
    }

    /// Add a keyframe made from `frame` to the map. It is indexed in the
    /// keyframe database now when the frame's BoW vector was computed
    /// anyway; otherwise mapping indexes it (off the tracking thread).
    fn insert_keyframe(&self, map: &mut Map, frame: &mut Frame, kf: KeyFrame) -> KeyFrameId {
        let id = map.add_keyframe(kf);
        if let Some((bow, fv)) = frame.bow.take() {
            map.index_keyframe(id, bow, fv, self.vocabulary.word_count());
        }
        id
    }

    /// Index keyframe `kf` now if mapping has not yet.
    fn ensure_indexed(&self, map: &mut Map, kf: KeyFrameId) {
        if map.is_indexed(kf) {
            return;
        }
        let Some(k) = map.keyframe(kf) else { return };
        let (bow, fv) = self
            .vocabulary
            .transform_with_features(&k.descriptors, self.params.bow.direct_index_level);
        map.index_keyframe(kf, bow, fv, self.vocabulary.word_count());
    }

    fn new_keyframe_from(&self, frame: &Frame, cam_from_world: Isometry3<f64>) -> KeyFrame {
        KeyFrame {
            id: KeyFrameId(0),
            frame_index: frame.index,
            timestamp: frame.timestamp,
            cam_from_world,
            keypoints: frame.keypoints.clone(),
            descriptors: frame.descriptors.clone(),
            points: frame.points.clone(),
            grid: frame.grid.clone(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: Some(frame.image.clone()),
        }
    }

    fn create_initial_map(
        &mut self,
        map_lock: &Mutex<Map>,
        f1: &Frame,
        f2: &Frame,
        matches: &[(usize, usize)],
        tv: &geometry::TwoViewResult,
    ) -> Result<(Isometry3<f64>, usize, KeyFrameId), String> {
        let mut map = lock(map_lock);
        let mut kf1 = self.new_keyframe_from(f1, Isometry3::identity());
        let mut kf2 = self.new_keyframe_from(f2, renormalized(tv.cam2_from_cam1));
        kf1.points.iter_mut().for_each(|p| *p = None);
        kf2.points.iter_mut().for_each(|p| *p = None);
        let mut bows = [f1, f2].map(|f| {
            self.vocabulary
                .transform_with_features(&f.descriptors, self.params.bow.direct_index_level)
        });
        let id1 = map.add_keyframe(kf1);
        let id2 = map.add_keyframe(kf2);
        let words = self.vocabulary.word_count();
        for (id, (bow, fv)) in [id1, id2].into_iter().zip(bows.iter_mut()) {
            map.index_keyframe(id, std::mem::take(bow), std::mem::take(fv), words);
        }
        for (m, &(i, j)) in matches.iter().enumerate() {
            let Some(p) = tv.points.get(m).copied().flatten() else {
                continue;
            };
            let pid = map.add_point(p, f1.descriptors[i], id1);
            map.add_observation(pid, id1, i as u32);
            map.add_observation(pid, id2, j as u32);
            map.update_point_descriptor(pid);
            map.update_point_normal_and_depth(pid);
        }
        map.update_connections(id1);
        map.update_connections(id2);
        // Bundle adjustment of the two views, the first fixed.
        run_bundle_adjustment(&mut map, &[id1, id2], &[id1], &self.params.init_ba);
        let Some(median) = map.median_depth(id1) else {
            reset_map(&mut map);
            return Err("initial map has no points".into());
        };
        let n_tracked = map.keyframe(id2).map_or(0, |k| k.tracked_points(&map, 1));
        if median <= 0.0 || n_tracked < self.params.init_min_points {
            reset_map(&mut map);
            return Err(format!(
                "initial map rejected: median depth {median:.3}, {n_tracked} points (need {})",
                self.params.init_min_points
            ));
        }
        // Scale so the median scene depth is 1.
        let s = 1.0 / median;
        if let Some(k) = map.keyframe_mut(id2) {
            k.cam_from_world.translation.vector *= s;
        }
        let pids: Vec<PointId> = map.points().map(|p| p.id).collect();
        for pid in &pids {
            if let Some(mp) = map.point_mut(*pid) {
                mp.position.coords *= s;
            }
        }
        for pid in &pids {
            map.update_point_normal_and_depth(*pid);
        }
        let Some(kf2) = map.keyframe(id2) else {
            return Err("initial keyframe vanished".into());
        };
        let pose2 = kf2.cam_from_world;
        let matched: Vec<(usize, PointId)> = kf2
            .points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.map(|p| (i, p)))
            .collect();
        tracing::info!(
            frame = f2.index,
            first_frame = f1.index,
            points = matched.len(),
            model = ?tv.model,
            parallax_deg = tv.parallax_deg,
            "map initialised"
        );
        for f in [f1, f2] {
            let (r, pose) = if f.index == f1.index {
                (id1, Isometry3::identity())
            } else {
                (id2, pose2)
            };
            let _ = pose;
            self.records.push(FrameRecord {
                index: f.index,
                timestamp: f.timestamp,
                reference: r,
                cam_from_ref: Isometry3::identity(),
            });
        }
        self.last = Some(LastFrame {
            keypoints: f2.keypoints.clone(),
            matches: matched.clone(),
            cam_from_world: pose2,
        });
        self.velocity = None;
        self.reference_kf = Some(id2);
        self.last_kf_frame = f2.index;
        Ok((pose2, matched.len(), id2))
    }

    /// Track an ordinary frame against the map.
    fn track_frame(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
        mapping_idle: bool,
    ) -> Result<(Isometry3<f64>, usize, Option<KeyFrameId>), String> {
        let mut pose: Option<Isometry3<f64>> = None;
        if self.state == TrackState::Tracking {
            if let (Some(v), Some(last)) = (self.velocity, self.last.as_ref()) {
                pose = self.track_motion_model(map, frame, v * last.cam_from_world);
            }
            if pose.is_none() {
                pose = self.track_reference_keyframe(map, frame);
            }
        }
        if pose.is_none() {
            pose = self.relocalize(map, frame);
            if pose.is_some() {
                self.last_reloc_frame = Some(frame.index);
            }
        }
        let recently_relocalized = self
            .last_reloc_frame
            .is_some_and(|r| frame.index < r + self.params.max_frames_between_keyframes);
        let Some(pose) = pose else {
            return Err(if self.state == TrackState::Tracking {
                "motion model, reference keyframe and relocalisation all failed".into()
            } else {
                "relocalisation failed".into()
            });
        };
        let (pose, inliers) = self.track_local_map(map, frame, pose)?;
        let needed = if recently_relocalized {
            self.params.min_inliers_after_reloc
        } else {
            self.params.min_tracked_inliers
        };
        if inliers < needed {
            return Err(format!(
                "only {inliers} inliers after the local map (need {needed})"
            ));
        }
        // Motion model.
        if let Some(last) = &self.last {
            self.velocity = Some(renormalized(pose * last.cam_from_world.inverse()));
        }
        let reference = self.reference_kf.unwrap_or(KeyFrameId(0));
        let mut new_kf = None;
        if self.need_new_keyframe(map, frame, inliers, mapping_idle, recently_relocalized) {
            let kf = self.new_keyframe_from(frame, pose);
            let id = self.insert_keyframe(map, frame, kf);
            self.reference_kf = Some(id);
            self.last_kf_frame = frame.index;
            new_kf = Some(id);
        }
        let reference = new_kf.unwrap_or(reference);
        let ref_pose = map.keyframe(reference).map_or(pose, |k| k.cam_from_world);
        self.records.push(FrameRecord {
            index: frame.index,
            timestamp: frame.timestamp,
            reference,
            cam_from_ref: pose * ref_pose.inverse(),
        });
        self.last = Some(LastFrame {
            keypoints: frame.keypoints.clone(),
            matches: frame.matches(),
            cam_from_world: pose,
        });
        Ok((pose, inliers, new_kf))
    }

    /// Optimise the frame pose on its current matches; drop outliers.
    /// Returns the pose and the number of inliers.
    fn optimize_frame_pose(
        &self,
        map: &Map,
        frame: &mut Frame,
        pose: Isometry3<f64>,
    ) -> Option<(Isometry3<f64>, usize)> {
        let mut idx = Vec::new();
        let mut obs = Vec::new();
        for i in 0..frame.points.len() {
            let Some(pid) = frame.points[i] else { continue };
            if let Some(mp) = map.point(pid) {
                let k = &frame.keypoints[i];
                idx.push(i);
                obs.push(PoseObservation {
                    p_world: mp.position,
                    uv: Point2::new(k.ux as f64, k.uy as f64),
                    inv_sigma2: self.scale.inv_level_sigma2[k.octave as usize],
                });
            } else {
                frame.points[i] = None;
            }
        }
        if obs.len() < 3 {
            return None;
        }
        let report =
            optimize::optimize_pose(pose, &obs, &self.intrinsics, &self.params.pose).ok()?;
        for (k, &i) in idx.iter().enumerate() {
            if !report.inliers[k] {
                frame.points[i] = None;
            }
        }
        Some((renormalized(report.cam_from_world), report.n_inliers))
    }

    fn track_motion_model(
        &mut self,
        map: &Map,
        frame: &mut Frame,
        predicted: Isometry3<f64>,
    ) -> Option<Isometry3<f64>> {
        let last = self.last.as_ref()?;
        let mut th = self.params.motion_search_radius;
        let mut found = Vec::new();
        for _ in 0..2 {
            frame.points.iter_mut().for_each(|p| *p = None);
            let target = frame.search_target();
            found = matcher::search_last_frame(
                &target,
                &last.keypoints,
                &last.matches,
                map,
                &predicted,
                &self.bounds,
                th,
                &self.params.matcher,
            );
            if found.len() >= self.params.min_motion_matches {
                break;
            }
            th *= 2.0;
        }
        if found.len() < self.params.min_motion_matches {
            return None;
        }
        for (i, p) in found {
            frame.points[i] = Some(p);
        }
        let (pose, inliers) = self.optimize_frame_pose(map, frame, predicted)?;
        (inliers >= 10).then_some(pose)
    }

    /// Match the reference keyframe's points by descriptor (ratio test and
    /// rotation check) and optimise from the last pose.
    fn track_reference_keyframe(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
    ) -> Option<Isometry3<f64>> {
        let reference = self.reference_kf?;
        self.ensure_indexed(map, reference);
        let start = self.last.as_ref().map_or_else(
            || map.keyframe(reference).map(|k| k.cam_from_world),
            |l| Some(l.cam_from_world),
        )?;
        // BoW-guided when the keyframe is indexed, else by brute force.
        let matches = match map.places().and_then(|p| p.features.get(&reference)) {
            Some(kf_fv) => {
                let fv = self.frame_bow(frame).1.clone();
                matcher::search_by_bow(
                    map,
                    reference,
                    kf_fv,
                    &frame.descriptors,
                    &frame.keypoints,
                    &fv,
                    &self.params.matcher,
                    0.7,
                )
            }
            None => match_keyframe_by_descriptor(map, reference, frame, &self.params.matcher, 0.7),
        };
        if matches.len() < 15 {
            return None;
        }
        frame.points.iter_mut().for_each(|p| *p = None);
        for (i, p) in matches {
            frame.points[i] = Some(p);
        }
        let (pose, inliers) = self.optimize_frame_pose(map, frame, start)?;
        (inliers >= 10).then_some(pose)
    }

    /// Relocalise as ORB-SLAM does: candidate keyframes from the keyframe
    /// database (words in common, scores accumulated over covisibility
    /// groups), BoW-guided matching with each, PnP RANSAC, motion-only BA,
    /// and, when the inliers fall short, search by projection of the
    /// candidate's covisible points and a second optimisation.
    fn relocalize(&mut self, map: &Map, frame: &mut Frame) -> Option<Isometry3<f64>> {
        let places = map.places()?;
        let (bow, fv) = self.frame_bow(frame).clone();
        let neighbours = self.params.bow.candidates.covisible_neighbours;
        let mut candidates = places.database.detect_candidates(
            &bow,
            &self.params.bow.candidates,
            |_| false,
            |id, out| {
                if let Some(k) = map::Places::map_id(id).and_then(|id| map.keyframe(id)) {
                    out.extend(k.best_covisible(neighbours).map(map::Places::db_id));
                }
            },
        );
        candidates.truncate(self.params.reloc_max_candidates);
        let needed = self.params.min_inliers_after_reloc;
        for (ci, cand) in candidates.iter().enumerate() {
            let Some(kf) = map::Places::map_id(cand.id) else {
                continue;
            };
            let Some(kf_fv) = places.features.get(&kf) else {
                continue;
            };
            let matches = matcher::search_by_bow(
                map,
                kf,
                kf_fv,
                &frame.descriptors,
                &frame.keypoints,
                &fv,
                &self.params.matcher,
                0.75,
            );
            if matches.len() < self.params.reloc_min_bow_matches {
                continue;
            }
            let mut pts = Vec::with_capacity(matches.len());
            let mut obs = Vec::with_capacity(matches.len());
            let mut used = Vec::with_capacity(matches.len());
            for &(i, p) in &matches {
                let Some(mp) = map.point(p) else { continue };
                let k = &frame.keypoints[i];
                pts.push(mp.position);
                obs.push(Point2::new(
                    (k.ux as f64 - self.camera.cx) / self.camera.fx,
                    (k.uy as f64 - self.camera.cy) / self.camera.fy,
                ));
                used.push((i, p));
            }
            let Ok(r) = geometry::solve_pnp_ransac(
                &pts,
                &obs,
                self.camera.fx,
                &self.params.pnp,
                self.params.seed.wrapping_add(frame.index * 31 + ci as u64),
            ) else {
                continue;
            };
            frame.points.iter_mut().for_each(|p| *p = None);
            for ((i, p), ok) in used.iter().zip(&r.inliers) {
                if *ok {
                    frame.points[*i] = Some(*p);
                }
            }
            let Some((mut pose, mut inliers)) =
                self.optimize_frame_pose(map, frame, renormalized(r.cam_from_world))
            else {
                continue;
            };
            if inliers < 10 {
                continue;
            }
            // Search by projection for more matches: first wide, then
            // narrow after a second optimisation (ORB-SLAM's 10 then 3 px).
            for th in [3.0, 1.0] {
                if inliers >= needed {
                    break;
                }
                self.search_candidate_points(map, frame, kf, &pose, th);
                match self.optimize_frame_pose(map, frame, pose) {
                    Some((p, n)) => {
                        pose = p;
                        inliers = n;
                    }
                    None => break,
                }
            }
            if inliers >= needed {
                tracing::info!(
                    frame = frame.index,
                    keyframe = kf.0,
                    candidates = candidates.len(),
                    inliers,
                    "relocalised"
                );
                return Some(pose);
            }
        }
        frame.points.iter_mut().for_each(|p| *p = None);
        None
    }

    /// Project the points of keyframe `kf` and its best covisible
    /// neighbours that the frame has not matched, and match them by
    /// projection (radius factor `th`).
    fn search_candidate_points(
        &mut self,
        map: &Map,
        frame: &mut Frame,
        kf: KeyFrameId,
        pose: &Isometry3<f64>,
        th: f64,
    ) {
        let Some(k) = map.keyframe(kf) else { return };
        let center = pose.inverse().translation.vector;
        self.marks.next_pass();
        for pid in frame.points.iter().flatten() {
            self.marks.mark_point(*pid);
        }
        let mut projected = Vec::new();
        let kfs: Vec<KeyFrameId> = std::iter::once(kf).chain(k.best_covisible(10)).collect();
        for id in kfs {
            let Some(k) = map.keyframe(id) else { continue };
            for pid in k.points.iter().flatten() {
                if !self.marks.mark_point(*pid) {
                    continue;
                }
                if let Some(pr) =
                    matcher::project_point(map, *pid, pose, &center, &self.bounds, 0.5)
                {
                    projected.push(pr);
                }
            }
        }
        let found = {
            let target = frame.search_target();
            matcher::search_local_points(
                &target,
                &projected,
                map,
                &self.scale,
                th,
                &self.params.matcher,
            )
        };
        for (i, p) in found {
            if frame.points[i].is_none() {
                frame.points[i] = Some(p);
            }
        }
    }

    /// The keyframes sharing points with the frame, their best covisible
    /// neighbours, parents and children; the reference keyframe becomes the
    /// one sharing most.
    fn local_keyframes(&mut self, map: &Map, frame: &Frame) -> Vec<KeyFrameId> {
        let marks = &mut self.marks;
        marks.next_pass();
        let mut list: Vec<(KeyFrameId, u32)> = Vec::new();
        for pid in frame.points.iter().flatten() {
            if let Some(mp) = map.point(*pid) {
                for (kf, _) in &mp.observations {
                    if marks.mark_keyframe(*kf) {
                        list.push((*kf, 0));
                    }
                    marks.count[kf.0 as usize] += 1;
                }
            }
        }
        for e in &mut list {
            e.1 = marks.count[e.0.0 as usize];
        }
        list.sort_unstable_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
        if let Some(best) = list.first() {
            self.reference_kf = Some(best.0);
        }
        let mut local: Vec<KeyFrameId> = list.iter().map(|e| e.0).collect();
        let direct = local.len();
        for d in 0..direct {
            if local.len() >= self.params.max_local_keyframes {
                break;
            }
            let Some(k) = map.keyframe(local[d]) else {
                continue;
            };
            let extra = k
                .best_covisible(10)
                .chain(k.children.iter().copied())
                .chain(k.parent);
            for e in extra {
                if self.marks.mark_keyframe(e) {
                    local.push(e);
                    if local.len() >= self.params.max_local_keyframes {
                        break;
                    }
                }
            }
        }
        local
    }

    fn track_local_map(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
        pose: Isometry3<f64>,
    ) -> Result<(Isometry3<f64>, usize), String> {
        let local_kfs = self.local_keyframes(map, frame);
        let center = pose.inverse().translation.vector;
        self.marks.next_pass();
        for pid in frame.points.iter().flatten() {
            self.marks.mark_point(*pid);
        }
        // Reused from frame to frame (no allocation per frame).
        let mut projected = std::mem::take(&mut self.projected);
        projected.clear();
        for kf in &local_kfs {
            let Some(k) = map.keyframe(*kf) else { continue };
            for pid in k.points.iter().flatten() {
                if !self.marks.mark_point(*pid) {
                    continue;
                }
                if let Some(pr) =
                    matcher::project_point(map, *pid, &pose, &center, &self.bounds, 0.5)
                {
                    projected.push(pr);
                }
            }
        }
        // Points already matched count as visible too.
        for pid in frame.points.iter().flatten() {
            if let Some(mp) = map.point_mut(*pid) {
                mp.visible += 1;
            }
        }
        for pr in &projected {
            if let Some(mp) = map.point_mut(pr.id) {
                mp.visible += 1;
            }
        }
        let th = if self.last_reloc_frame.is_some_and(|r| frame.index < r + 2) {
            5.0
        } else {
            1.0
        };
        let found = {
            let target = frame.search_target();
            matcher::search_local_points(
                &target,
                &projected,
                map,
                &self.scale,
                th,
                &self.params.matcher,
            )
        };
        self.projected = projected;
        for (i, p) in found {
            if frame.points[i].is_none() {
                frame.points[i] = Some(p);
            }
        }
        let (pose, inliers) = self
            .optimize_frame_pose(map, frame, pose)
            .ok_or_else(|| "pose optimisation on the local map failed".to_string())?;
        for pid in frame.points.iter().flatten() {
            if let Some(mp) = map.point_mut(*pid) {
                mp.found += 1;
            }
        }
        Ok((pose, inliers))
    }

    fn need_new_keyframe(
        &self,
        map: &Map,
        frame: &Frame,
        inliers: usize,
        mapping_idle: bool,
        recently_relocalized: bool,
    ) -> bool {
        let n_kfs = map.keyframe_count();
        let max_frames = self.params.max_frames_between_keyframes;
        if recently_relocalized && n_kfs as u64 > max_frames {
            return false;
        }
        let min_obs = if n_kfs <= 2 { 2 } else { 3 };
        let ref_matches = self
            .reference_kf
            .and_then(|r| map.keyframe(r))
            .map_or(0, |k| k.tracked_points(map, min_obs));
        let since = frame.index.saturating_sub(self.last_kf_frame);
        let c1a = since >= max_frames;
        let c1b = since >= self.params.min_frames_between_keyframes && mapping_idle;
        let c2 =
            (inliers as f64) < ref_matches as f64 * self.params.keyframe_ref_ratio && inliers > 15;
        (c1a || c1b) && c2 && mapping_idle
    }
}

/// Match the map points of keyframe `kf` to the frame's keypoints by
/// descriptor: best under `th_high` with a ratio test, rotation check.
/// Returns (frame keypoint, point).
fn match_keyframe_by_descriptor(
    map: &Map,
    kf: KeyFrameId,
    frame: &Frame,
    params: &MatcherParams,
    ratio: f32,
) -> Vec<(usize, PointId)> {
    let Some(k) = map.keyframe(kf) else {
        return Vec::new();
    };
    let mut best_for: Vec<(u32, usize)> = vec![(u32::MAX, usize::MAX); frame.keypoints.len()];
    let mut out: Vec<(usize, PointId, f32)> = Vec::new();
    for (ki, p) in k.points.iter().enumerate() {
        let Some(pid) = p else { continue };
        if map.point(*pid).is_none() {
            continue;
        }
        let d1 = &k.descriptors[ki];
        let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
        for (fi, d2) in frame.descriptors.iter().enumerate() {
            let d = hamming(d1, d2);
            if d < b1 {
                b2 = b1;
                b1 = d;
                bi = fi;
            } else if d < b2 {
                b2 = d;
            }
        }
        if b1 <= params.th_low && (b1 as f32) < ratio * b2 as f32 && b1 < best_for[bi].0 {
            best_for[bi] = (b1, out.len());
            out.push((bi, *pid, k.keypoints[ki].angle - frame.keypoints[bi].angle));
        }
    }
    // Keep, per frame keypoint, only its best match.
    let keep: Vec<bool> = out
        .iter()
        .enumerate()
        .map(|(n, m)| best_for[m.0].1 == n)
        .collect();
    let filtered: Vec<(usize, PointId, f32)> = out
        .into_iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(m, _)| m)
        .collect();
    let rot: Vec<(usize, f32)> = filtered.iter().enumerate().map(|(n, m)| (n, m.2)).collect();
    let drop: std::collections::HashSet<usize> =
        matcher::rotation_outliers(&rot, params.histo_bins)
            .into_iter()
            .collect();
    filtered
        .into_iter()
        .enumerate()
        .filter(|(n, _)| !drop.contains(n))
        .map(|(_, m)| (m.0, m.1))
        .collect()
}

/// Empty the map (a failed initialisation).
fn reset_map(map: &mut Map) {
    *map = Map::new(map.camera, map.scale.clone());
}

/// Bundle adjustment over `kfs` (poses free unless listed in `fixed`) and
/// all points they see; keyframes outside `kfs` that see those points join
/// as fixed. Outlier observations are erased. Returns the report.
pub fn run_bundle_adjustment(
    map: &mut Map,
    kfs: &[KeyFrameId],
    fixed: &[KeyFrameId],
    params: &BaParams,
) -> Option<optimize::BaReport> {
    let problem = build_ba_problem(map, kfs, fixed)?;
    let (mut problem, pose_ids, point_ids) = problem;
    let report = optimize::local_bundle_adjustment(&mut problem, params).ok()?;
    apply_ba_result(map, &problem, &pose_ids, &point_ids, &report.outliers);
    Some(report)
}

/// The problem of a bundle adjustment: (problem, keyframe per pose, point
/// per point index).
pub type BaSetup = (BaProblem, Vec<KeyFrameId>, Vec<PointId>);

/// Build a bundle adjustment over `kfs` (free unless in `fixed`), the
/// points they see, and every other keyframe seeing those points (fixed).
pub fn build_ba_problem(map: &Map, kfs: &[KeyFrameId], fixed: &[KeyFrameId]) -> Option<BaSetup> {
    let mut pose_index: std::collections::HashMap<KeyFrameId, usize> =
        std::collections::HashMap::new();
    let mut poses = Vec::new();
    let mut pose_ids = Vec::new();
    for &kf in kfs {
        let Some(k) = map.keyframe(kf) else { continue };
        if pose_index.contains_key(&kf) {
            continue;
        }
        pose_index.insert(kf, poses.len());
        poses.push(BaPose {
            cam_from_world: k.cam_from_world,
            fixed: fixed.contains(&kf),
        });
        pose_ids.push(kf);
    }
    let mut point_index: std::collections::HashMap<PointId, usize> =
        std::collections::HashMap::new();
    let mut points = Vec::new();
    let mut point_ids = Vec::new();
    for &kf in &pose_ids.clone() {
        let Some(k) = map.keyframe(kf) else { continue };
        for pid in k.points.iter().flatten() {
            if point_index.contains_key(pid) {
                continue;
            }
            let Some(mp) = map.point(*pid) else { continue };
            point_index.insert(*pid, points.len());
            points.push(mp.position);
            point_ids.push(*pid);
        }
    }
    let mut observations = Vec::new();
    for (pi, pid) in point_ids.iter().enumerate() {
        let Some(mp) = map.point(*pid) else { continue };
        for (kf, idx) in &mp.observations {
            let Some(k) = map.keyframe(*kf) else { continue };
            let pose = match pose_index.get(kf) {
                Some(&p) => p,
                None => {
                    pose_index.insert(*kf, poses.len());
                    poses.push(BaPose {
                        cam_from_world: k.cam_from_world,
                        fixed: true,
                    });
                    pose_ids.push(*kf);
                    poses.len() - 1
                }
            };
            let Some(kp) = k.keypoints.get(*idx as usize) else {
                continue;
            };
            observations.push(Observation {
                pose,
                point: pi,
                uv: Point2::new(kp.ux as f64, kp.uy as f64),
                inv_sigma2: map.scale.inv_level_sigma2[kp.octave as usize],
            });
        }
    }
    if observations.is_empty() || !poses.iter().any(|p| !p.fixed) && points.is_empty() {
        return None;
    }
    let cam = &map.camera;
    Some((
        BaProblem {
            poses,
            points,
            observations,
            intrinsics: Intrinsics {
                fx: cam.fx,
                fy: cam.fy,
                cx: cam.cx,
                cy: cam.cy,
            },
        },
        pose_ids,
        point_ids,
    ))
}

/// Write a solved bundle adjustment back: free poses, points, and erase the
/// outlier observations.
pub fn apply_ba_result(
    map: &mut Map,
    problem: &BaProblem,
    pose_ids: &[KeyFrameId],
    point_ids: &[PointId],
    outliers: &[bool],
) {
    for (i, kf) in pose_ids.iter().enumerate() {
        if problem.poses[i].fixed {
            continue;
        }
        if let Some(k) = map.keyframe_mut(*kf) {
            k.cam_from_world = renormalized(problem.poses[i].cam_from_world);
        }
    }
    for (i, pid) in point_ids.iter().enumerate() {
        if let Some(mp) = map.point_mut(*pid) {
            mp.position = problem.points[i];
        }
    }
    for (o, obs) in problem.observations.iter().enumerate() {
        if outliers.get(o).copied().unwrap_or(false) {
            map.erase_observation(point_ids[obs.point], pose_ids[obs.pose]);
        }
    }
    for pid in point_ids {
        map.update_point_normal_and_depth(*pid);
    }
}

/// The pose with its rotation quaternion renormalised: solvers that build a
/// quaternion from a slightly non-orthonormal matrix leave it off unit
/// length, and the error grows through compositions.
pub fn renormalized(pose: Isometry3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(
        pose.translation,
        UnitQuaternion::new_normalize(*pose.rotation.quaternion()),
    )
}
