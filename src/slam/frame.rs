//! What every stage of tracking works on: the frame being tracked, the
//! previous tracked frame, the tracker's fixed [`Context`] (tunables,
//! camera, scale levels, vocabulary), per-pass [`Marks`], and motion-only
//! bundle adjustment of a frame's pose on its matches (with the telemetry's
//! prior when tracking is aided), and the record of a posed frame with how
//! it was posed ([`PoseSource`]).

use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Isometry3, Point2};

use crate::bow::{BowVector, FeatureVector, Vocabulary};
use crate::camera::Camera;
use crate::features::{Descriptor, KeyPoint};
use crate::lie::renormalized;
use crate::matching::{Bounds, FeatureGrid};
use crate::optimize::{self, Intrinsics, PoseObservation};

use super::map::{KeyFrame, KeyFrameId, Map, PointId, ScaleInfo};
use super::matcher::SearchTarget;
use super::params::TrackingParams;

/// What tracking made of a keypoint of a frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeypointState {
    /// Matched to a map point and kept by the frame's pose.
    Inlier,
    /// Matched to a map point, then rejected by a pose optimisation.
    Outlier,
    /// Not matched to a map point (new ground, or tracking failed).
    Unmatched,
}

/// A keypoint of a tracked (or lost) frame, where it was detected.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedKeypoint {
    /// Column, image pixels (level 0, as detected: distorted).
    pub x: f32,
    /// Row, image pixels.
    pub y: f32,
    /// What tracking made of it.
    pub state: KeypointState,
}

/// How a frame's pose was found.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseSource {
    /// By vision alone (the motion model, the reference keyframe or
    /// relocalisation, then the local map).
    Vision,
    /// By the local map searched around the telemetry's prediction, with
    /// the prediction as a prior.
    VisionTelemetry,
    /// By the telemetry's prediction alone (vision found too little).
    Telemetry,
}

impl PoseSource {
    /// Its name in logs and reports.
    pub fn name(self) -> &'static str {
        match self {
            PoseSource::Vision => "vision",
            PoseSource::VisionTelemetry => "vision+telemetry",
            PoseSource::Telemetry => "telemetry",
        }
    }
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
    /// How the pose was found.
    pub source: PoseSource,
}

/// A frame being tracked.
pub(super) struct Frame {
    /// Frame index in the input.
    pub index: u64,
    /// Capture time, seconds.
    pub timestamp: f64,
    /// Undistorted keypoints.
    pub keypoints: Vec<KeyPoint>,
    /// Their descriptors.
    pub descriptors: Vec<Descriptor>,
    /// Keypoints by cell, for search by projection.
    pub grid: FeatureGrid,
    /// The map point matched to each keypoint.
    pub points: Vec<Option<PointId>>,
    /// The image (kept by the keyframe made from the frame).
    pub image: Arc<GrayImage>,
    /// BoW vector and direct index, computed when first needed.
    pub bow: Option<(BowVector, FeatureVector)>,
    /// Keypoints whose match a pose optimisation rejected as an outlier
    /// since the matches were last cleared (a keypoint matched again
    /// leaves it).
    pub rejected: Vec<bool>,
    /// A prior on the frame's pose in its optimisations (the telemetry's
    /// prediction when tracking is aided; `None`: vision alone).
    pub prior: Option<optimize::PosePrior>,
    /// The camera's motion over a rolling shutter's readout, from the
    /// constant-velocity model (`None`: a global shutter, or no motion
    /// model yet).
    pub shutter: Option<optimize::RowMotion>,
}

impl Frame {
    /// The frame as the matcher searches it.
    pub fn search_target(&self) -> SearchTarget<'_> {
        SearchTarget {
            keypoints: &self.keypoints,
            descriptors: &self.descriptors,
            grid: &self.grid,
            points: &self.points,
        }
    }

    /// (keypoint, point) of every matched keypoint.
    pub fn matches(&self) -> Vec<(usize, PointId)> {
        self.points
            .iter()
            .enumerate()
            .filter_map(|(i, p)| p.map(|p| (i, p)))
            .collect()
    }

    /// Forget every match (and every rejection).
    pub fn clear_matches(&mut self) {
        self.points.iter_mut().for_each(|p| *p = None);
        self.rejected.iter_mut().for_each(|r| *r = false);
    }

    /// Match the keypoints listed in `matches` (others keep theirs).
    pub fn set_matches(&mut self, matches: impl IntoIterator<Item = (usize, PointId)>) {
        for (i, p) in matches {
            self.points[i] = Some(p);
            self.rejected[i] = false;
        }
    }

    /// Match the keypoints listed in `found` that have no match yet.
    pub fn add_matches(&mut self, found: impl IntoIterator<Item = (usize, PointId)>) {
        for (i, p) in found {
            if self.points[i].is_none() {
                self.points[i] = Some(p);
                self.rejected[i] = false;
            }
        }
    }

    /// Each keypoint where it was detected (image pixels) and what
    /// tracking made of it: matched to a map point and kept by the pose
    /// (inlier), matched but rejected by a pose optimisation (outlier), or
    /// unmatched.
    pub fn keypoint_states(&self) -> Vec<TrackedKeypoint> {
        self.keypoints
            .iter()
            .enumerate()
            .map(|(i, k)| TrackedKeypoint {
                x: k.x,
                y: k.y,
                state: if self.points[i].is_some() {
                    KeypointState::Inlier
                } else if self.rejected.get(i).copied().unwrap_or(false) {
                    KeypointState::Outlier
                } else {
                    KeypointState::Unmatched
                },
            })
            .collect()
    }

    /// A keyframe made from the frame at `cam_from_world` (its id is set
    /// when the map takes it).
    pub fn to_keyframe(&self, cam_from_world: Isometry3<f64>) -> KeyFrame {
        KeyFrame {
            id: KeyFrameId(0),
            frame_index: self.index,
            timestamp: self.timestamp,
            cam_from_world,
            keypoints: self.keypoints.clone(),
            descriptors: self.descriptors.clone(),
            points: self.points.clone(),
            grid: self.grid.clone(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: Some(self.image.clone()),
        }
    }

    /// Where each keypoint is, in pixels.
    pub fn pixels(&self) -> Vec<Point2<f64>> {
        self.keypoints
            .iter()
            .map(|k| Point2::new(k.ux as f64, k.uy as f64))
            .collect()
    }
}

/// The previous tracked frame.
pub(super) struct LastFrame {
    /// Its capture time, seconds.
    pub timestamp: f64,
    /// Vision posed it (not the telemetry's prediction).
    pub by_vision: bool,
    /// Its keypoints.
    pub keypoints: Vec<KeyPoint>,
    /// Its (keypoint, point) matches.
    pub matches: Vec<(usize, PointId)>,
    /// Its pose.
    pub cam_from_world: Isometry3<f64>,
}

/// A frame pose fitted to the frame's matches.
#[derive(Debug, Clone, Copy)]
pub(super) struct PoseFit {
    /// The pose.
    pub cam_from_world: Isometry3<f64>,
    /// Matches that agree with it (outliers were dropped from the frame).
    pub inliers: usize,
}

/// What the stages of tracking share and never change: the tunables, the
/// camera and its image bounds, the extractor's scale levels, the
/// keyframe database's vocabulary.
pub(super) struct Context {
    /// Tunables.
    pub params: TrackingParams,
    /// The camera.
    pub camera: Camera,
    /// Its undistorted image bounds.
    pub bounds: Bounds,
    /// The extractor's scale levels.
    pub scale: ScaleInfo,
    /// The pinhole part of the camera, for the optimiser.
    pub intrinsics: Intrinsics,
    /// The vocabulary of the keyframe database.
    pub vocabulary: Arc<Vocabulary>,
}

impl Context {
    /// The context of a tracker for `camera`.
    pub fn new(camera: Camera, params: TrackingParams, vocabulary: Arc<Vocabulary>) -> Self {
        let scale = ScaleInfo::new(
            params.features.scale_factor as f64,
            params.features.n_levels,
        );
        Context {
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
        }
    }

    /// Optimise the frame's pose on its current matches, starting from
    /// `cam_from_world`; drop the outlier matches.
    pub fn optimize_frame_pose(
        &self,
        map: &Map,
        frame: &mut Frame,
        cam_from_world: Isometry3<f64>,
    ) -> Option<PoseFit> {
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
        let report = optimize::optimize_pose_with_prior(
            cam_from_world,
            &obs,
            &self.intrinsics,
            &self.params.pose,
            frame.prior.as_ref(),
            frame.shutter.as_ref(),
        )
        .ok()?;
        for (k, &i) in idx.iter().enumerate() {
            if !report.inliers[k] {
                frame.points[i] = None;
                frame.rejected[i] = true;
            }
        }
        Some(PoseFit {
            cam_from_world: renormalized(report.cam_from_world),
            inliers: report.n_inliers,
        })
    }

    /// The frame's BoW vector and direct index (computed once).
    pub fn frame_bow<'f>(&self, frame: &'f mut Frame) -> &'f (BowVector, FeatureVector) {
        frame.bow.get_or_insert_with(|| {
            self.vocabulary
                .transform_with_features(&frame.descriptors, self.params.bow.direct_index_level)
        })
    }

    /// Index keyframe `kf` in the keyframe database now if mapping has not yet.
    pub fn ensure_indexed(&self, map: &mut Map, kf: KeyFrameId) {
        if map.is_indexed(kf) {
            return;
        }
        let Some(k) = map.keyframe(kf) else { return };
        let (bow, fv) = self
            .vocabulary
            .transform_with_features(&k.descriptors, self.params.bow.direct_index_level);
        map.index_keyframe(kf, bow, fv, self.vocabulary.word_count());
    }
}

/// Per-pass marks on map points and keyframes, indexed by id (ORB-SLAM's
/// `mnTrackReferenceForFrame`): "seen in this pass" without building a set
/// per frame. A pass number is never reused while marks of it remain.
#[derive(Debug, Default)]
pub(super) struct Marks {
    pass: u32,
    point: Vec<u32>,
    keyframe: Vec<u32>,
    /// Shared-point count per keyframe, valid where `keyframe` holds the
    /// current pass.
    pub count: Vec<u32>,
}

impl Marks {
    /// Start a new pass: nothing is marked in it yet.
    pub fn next_pass(&mut self) {
        if self.pass == u32::MAX {
            self.point.iter_mut().for_each(|m| *m = 0);
            self.keyframe.iter_mut().for_each(|m| *m = 0);
            self.pass = 0;
        }
        self.pass += 1;
    }

    /// Mark a point in this pass; false when it already was.
    #[inline]
    pub fn mark_point(&mut self, id: PointId) -> bool {
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
    pub fn mark_keyframe(&mut self, id: KeyFrameId) -> bool {
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
