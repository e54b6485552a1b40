//! Localisation of a desired shot in the map: which camera pose
//! (`world_from_cam`, map coordinates) takes it.
//!
//! 1. ORB on the shot, with the validity mask (the black fill never yields a
//!    feature).
//! 2. Candidate keyframes: with a [`BowIndex`], the top k of a bag-of-words
//!    query of the shot against the keyframe database; without one, every
//!    keyframe is ranked by descriptor matching (one brute-force pass per
//!    keyframe, fine for maps of up to a few hundred keyframes). Each
//!    candidate's map points are matched by descriptor (nearest neighbour
//!    under a Hamming bound, ratio test, one-to-one).
//! 3. Per candidate: PnP RANSAC on its matches; then the local map (the
//!    points of the candidate, its best covisible keyframes and the keyframes
//!    that observe the points matched so far, most shared points first) is
//!    projected with that pose and matched in the shot (search by
//!    projection), and motion-only bundle adjustment (Huber, then outliers
//!    dropped) refines the pose on all pairs; twice, the second time with the
//!    local map regrown from the refined matches and a tighter window.
//!
//! The shot may come from another camera ([`localize_with_camera`]): its
//! own intrinsics and distortion are used for the features, the PnP, the
//! projection (with the predicted pyramid level corrected for the focal
//! length ratio) and the refinement; [`assumed_camera`] gives the camera of
//! a resized photo when the intrinsics are not known.
//! 4. A reliability gate: enough inliers, a small reprojection RMSE, a high
//!    inlier ratio, the inliers in front of the camera, and agreement with
//!    every other candidate that passes the gate too. Failing it gives
//!    [`Localization::NotLocalized`] with the reason; no pose is returned then.

use std::collections::HashSet;

use image::GrayImage;
use nalgebra::{Isometry3, Point2, Point3};

use super::ShotError;
use crate::bow::{self, BowVector, KeyFrameDatabase, Vocabulary};
use crate::camera::Camera;
use crate::features::{self, Descriptor, OrbExtractor, hamming};
use crate::geometry::{PnpParams, solve_pnp_ransac};
use crate::matching::{Bounds, FeatureGrid};
use crate::optimize::{
    Intrinsics, IntrinsicsCorrection, IntrinsicsUncertainty, PoseObservation, PoseParams,
    optimize_pose, pose_covariance, refine_pose_and_intrinsics,
};
use crate::slam::matcher::{MatcherParams, Projected, SearchTarget, search_local_points};
use crate::slam::{KeyFrameId, Map, PointId};

/// Thresholds of the reliability gate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GateParams {
    /// Fewest inliers after refinement.
    pub min_inliers: usize,
    /// Largest RMSE of the inliers' reprojection errors, pixels.
    pub max_rmse_px: f64,
    /// Smallest fraction of the refined pairs that are inliers.
    pub min_inlier_ratio: f64,
    /// Smallest fraction of the inliers lying in front of the camera.
    pub min_in_front_fraction: f64,
    /// Largest distance between the positions of two gated candidates, as a
    /// fraction of the scene's median depth.
    pub max_disagreement_depth_fraction: f64,
    /// Largest angle between the orientations of two gated candidates, degrees.
    pub max_disagreement_deg: f64,
    /// Largest position sigma ([`PoseSigma::position_depth_fraction`]), as
    /// a fraction of the distance to the nearest scene content (10 %
    /// quantile of the inliers' depths).
    pub max_position_sigma_depth_fraction: f64,
    /// Largest rotation sigma ([`PoseSigma::rotation_deg`]), degrees.
    pub max_rotation_sigma_deg: f64,
}

impl Default for GateParams {
    fn default() -> Self {
        GateParams {
            min_inliers: 30,
            max_rmse_px: 3.0,
            min_inlier_ratio: 0.5,
            min_in_front_fraction: 0.99,
            max_disagreement_depth_fraction: 0.05,
            max_disagreement_deg: 2.0,
            max_position_sigma_depth_fraction: 0.02,
            max_rotation_sigma_deg: 1.0,
        }
    }
}

/// Every tunable number of the localisation.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalizeParams {
    /// ORB settings for the shot (scale factor and levels are taken from the map).
    pub features: features::Params,
    /// Candidate keyframes kept.
    pub top_k: usize,
    /// Largest Hamming distance of a descriptor match against a candidate.
    pub max_hamming: u32,
    /// Ratio test: best distance below `ratio` times the second best.
    pub ratio: f32,
    /// Fewest descriptor matches for a keyframe to be tried.
    pub min_candidate_matches: usize,
    /// Covisible keyframes of a candidate whose points are projected in the
    /// first projection round.
    pub covisible: usize,
    /// Largest number of keyframes whose points make the local map of the
    /// later rounds: the keyframes that observe the points matched so far,
    /// most shared points first (ORB-SLAM's local keyframes).
    pub local_keyframes: usize,
    /// Search windows (pixels at level 0) of the projection rounds.
    pub projection_radius_px: [f64; 2],
    /// Smallest cosine between the viewing ray and a point's mean viewing
    /// direction for it to be projected.
    pub min_view_cos: f64,
    /// Matcher settings for the search by projection.
    pub matcher: MatcherParams,
    /// PnP RANSAC settings.
    pub pnp: PnpParams,
    /// Motion-only bundle adjustment settings.
    pub pose: PoseParams,
    /// The reliability gate.
    pub gate: GateParams,
    /// How well the shot camera's intrinsics are known (zero: exactly, as
    /// the map camera's or the operator's; a photo's EXIF leaves the focal
    /// length and the distortion open: [`crate::shot::PhotoCamera`]).
    /// Widens the reported sigma, never changes the pose.
    pub camera_uncertainty: IntrinsicsUncertainty,
    /// The map's own error, which the pose covariance (map points held
    /// exact) does not see; added to it in quadrature.
    pub map_sigma: MapSigma,
    /// Seed of the RANSAC.
    pub seed: u64,
}

impl Default for LocalizeParams {
    fn default() -> Self {
        let features = features::Params {
            n_features: 1500,
            ..features::Params::default()
        };
        let pnp = PnpParams {
            min_inliers: 12,
            max_iterations: 2000,
            ..PnpParams::default()
        };
        LocalizeParams {
            features,
            top_k: 5,
            max_hamming: 50,
            ratio: 0.8,
            min_candidate_matches: 15,
            covisible: 10,
            local_keyframes: 20,
            projection_radius_px: [5.0, 2.5],
            min_view_cos: 0.5,
            matcher: MatcherParams {
                th_high: 64,
                ..MatcherParams::default()
            },
            pnp,
            pose: PoseParams::default(),
            gate: GateParams::default(),
            camera_uncertainty: IntrinsicsUncertainty::default(),
            map_sigma: MapSigma::default(),
            seed: 1,
        }
    }
}

/// The map's own error as the localisation's sigma includes it: the larger
/// of this floor and the spread of the poses of the agreeing candidates
/// (each refined on its own local map) around the chosen one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapSigma {
    /// Position, as a fraction of the median depth of the inliers.
    pub depth_fraction: f64,
    /// Rotation, degrees.
    pub rotation_deg: f64,
}

impl Default for MapSigma {
    /// Calibrated on the simulator's explore map (`tests/shot_photos.rs`):
    /// photos of the map camera under the flight's light are off by 0.21 %
    /// of the distance and 0.14 degrees (medians) while their pose
    /// covariance alone says a few hundredths of that; for a 3-D Gaussian
    /// the median error is 0.89 sigma.
    fn default() -> Self {
        MapSigma {
            depth_fraction: 0.0025,
            rotation_deg: 0.16,
        }
    }
}

/// A localised desired shot.
#[derive(Debug, Clone, PartialEq)]
pub struct ShotPose {
    /// The camera that takes the shot, map coordinates.
    pub world_from_cam: Isometry3<f64>,
    /// The candidate keyframe the pose was found through.
    pub keyframe_id: KeyFrameId,
    /// Inlier 2D-3D pairs after refinement.
    pub inliers: usize,
    /// 2D-3D pairs that went into the refinement.
    pub matches: usize,
    /// RMSE of the inliers' reprojection errors, pixels (undistorted).
    pub reprojection_rmse_px: f64,
    /// `inliers / matches`.
    pub inlier_ratio: f64,
    /// Fraction of the inliers in front of the camera.
    pub in_front_fraction: f64,
    /// Median depth of the inliers, map units.
    pub median_depth: f64,
    /// Other candidates that passed the gate and agree with this pose.
    pub agreeing_candidates: usize,
    /// The pose's uncertainty: the final optimisation's covariance (with
    /// the camera's uncertain intrinsics marginalised) and the map's own
    /// error ([`MapSigma`]) in quadrature.
    pub sigma: PoseSigma,
}

/// The uncertainty of a localised pose: the RMS of the errors the pose
/// covariance predicts (`√trace` of the camera centre's and of the
/// rotation's 3x3 covariance). For a Gaussian error about 61 % of the true
/// errors lie within one such sigma and 99 % within two.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseSigma {
    /// Camera centre, map units.
    pub position: f64,
    /// Camera centre as a fraction of the distance to the nearest scene
    /// content: the 10 % quantile of the inliers' depths (a position error
    /// moves the near content most in the picture).
    pub position_depth_fraction: f64,
    /// Orientation, degrees.
    pub rotation_deg: f64,
}

/// Why a shot was not localised.
#[derive(Debug, Clone, PartialEq)]
pub enum NotLocalizedReason {
    /// The shot gave too few ORB features.
    TooFewFeatures {
        /// Features found.
        found: usize,
        /// Needed.
        needed: usize,
    },
    /// The map has no keyframe with map points.
    NoCandidate,
    /// No candidate keyframe has enough descriptor matches.
    TooFewMatches {
        /// Matches of the best candidate.
        found: usize,
        /// Needed.
        needed: usize,
    },
    /// PnP found no pose with enough inliers on any candidate.
    PnpFailed {
        /// Candidates tried.
        candidates: usize,
    },
    /// The best pose has too few inliers.
    TooFewInliers {
        /// Inliers of the best pose.
        found: usize,
        /// Needed.
        needed: usize,
    },
    /// The inliers' reprojection RMSE is too large.
    HighReprojectionError {
        /// RMSE, pixels.
        rmse_px: f64,
        /// Allowed maximum.
        max_px: f64,
    },
    /// Too small a fraction of the pairs are inliers.
    LowInlierRatio {
        /// The ratio.
        ratio: f64,
        /// Required minimum.
        min: f64,
    },
    /// Inliers lie behind the camera.
    PointsBehind {
        /// Fraction in front.
        in_front_fraction: f64,
        /// Required minimum.
        min: f64,
    },
    /// The pose's sigma exceeds the configured bounds.
    Uncertain {
        /// Position sigma as a fraction of the distance to the scene.
        position_depth_fraction: f64,
        /// Its bound.
        max_position_depth_fraction: f64,
        /// Rotation sigma, degrees.
        rotation_deg: f64,
        /// Its bound.
        max_rotation_deg: f64,
    },
    /// The pose's covariance could not be computed (singular).
    NoCovariance,
    /// Two candidates pass the gate with different poses.
    CandidatesDisagree {
        /// The other keyframe.
        other: KeyFrameId,
        /// Distance between the positions, as a fraction of the median depth.
        position_depth_fraction: f64,
        /// Angle between the orientations, degrees.
        angle_deg: f64,
    },
}

impl std::fmt::Display for NotLocalizedReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use NotLocalizedReason::*;
        match self {
            TooFewFeatures { found, needed } => write!(f, "too few features ({found} < {needed})"),
            NoCandidate => write!(f, "no candidate keyframe"),
            TooFewMatches { found, needed } => write!(f, "too few matches ({found} < {needed})"),
            PnpFailed { candidates } => write!(f, "PnP failed on all {candidates} candidates"),
            TooFewInliers { found, needed } => write!(f, "too few inliers ({found} < {needed})"),
            HighReprojectionError { rmse_px, max_px } => {
                write!(f, "reprojection RMSE {rmse_px:.2} px > {max_px:.2} px")
            }
            LowInlierRatio { ratio, min } => write!(f, "inlier ratio {ratio:.2} < {min:.2}"),
            PointsBehind {
                in_front_fraction,
                min,
            } => {
                write!(
                    f,
                    "only {in_front_fraction:.3} of the inliers in front (< {min:.3})"
                )
            }
            Uncertain {
                position_depth_fraction,
                max_position_depth_fraction,
                rotation_deg,
                max_rotation_deg,
            } => write!(
                f,
                "too uncertain: position sigma {:.2} % of the distance (max {:.2} %), rotation sigma {rotation_deg:.2} deg (max {max_rotation_deg:.2}); \
                 a photo from nearer the flown path, or the camera's intrinsics, would help",
                position_depth_fraction * 100.0,
                max_position_depth_fraction * 100.0
            ),
            NoCovariance => write!(f, "the pose's covariance is singular"),
            CandidatesDisagree {
                other,
                position_depth_fraction,
                angle_deg,
            } => write!(
                f,
                "candidate keyframe {} disagrees by {:.3} x median depth and {angle_deg:.2} deg",
                other.0, position_depth_fraction
            ),
        }
    }
}

/// The outcome of [`localize`].
#[derive(Debug, Clone, PartialEq)]
pub enum Localization {
    /// The shot's camera pose, through the gate.
    Localized(ShotPose),
    /// Not localised, and why.
    NotLocalized {
        /// Why.
        reason: NotLocalizedReason,
    },
}

/// A bag-of-words index of a map's keyframes: the vocabulary and a database
/// holding every keyframe's BoW vector.
pub struct BowIndex<'v> {
    vocabulary: &'v Vocabulary,
    database: KeyFrameDatabase,
}

impl<'v> BowIndex<'v> {
    /// Indexes every keyframe of `map` (its descriptors through `vocabulary`).
    pub fn build(map: &Map, vocabulary: &'v Vocabulary) -> Self {
        let mut database = KeyFrameDatabase::new(vocabulary.word_count());
        for kf in map.keyframes() {
            let v: BowVector = vocabulary.transform(&kf.descriptors);
            // Ids are unique in a map, so adding cannot collide.
            let _ = database.add(bow::KeyFrameId(kf.id.0 as u64), v);
        }
        BowIndex {
            vocabulary,
            database,
        }
    }

    /// Keyframes indexed.
    pub fn len(&self) -> usize {
        self.database.len()
    }

    /// True when no keyframe is indexed.
    pub fn is_empty(&self) -> bool {
        self.database.is_empty()
    }
}

/// For every shot descriptor, its best match among `cand` (point, descriptor)
/// under `max_d` and the ratio test; one-to-one on points (the closest wins).
fn match_descriptors(
    shot: &[Descriptor],
    cand: &[(PointId, Descriptor)],
    max_d: u32,
    ratio: f32,
) -> Vec<(usize, PointId)> {
    let mut m: Vec<(u32, usize, PointId)> = Vec::new();
    for (i, d) in shot.iter().enumerate() {
        let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
        for (j, (_, c)) in cand.iter().enumerate() {
            let h = hamming(d, c);
            if h < b1 {
                b2 = b1;
                b1 = h;
                bi = j;
            } else if h < b2 {
                b2 = h;
            }
        }
        if b1 <= max_d && (b2 == u32::MAX || (b1 as f32) < ratio * b2 as f32) {
            m.push((b1, i, cand[bi].0));
        }
    }
    m.sort_unstable_by_key(|x| x.0);
    let mut used = HashSet::new();
    m.into_iter()
        .filter(|(_, _, p)| used.insert(*p))
        .map(|(_, i, p)| (i, p))
        .collect()
}

/// One candidate's refined pose and its statistics (before the gate).
struct CandidatePose {
    kf: KeyFrameId,
    cam_from_world: Isometry3<f64>,
    inliers: usize,
    matches: usize,
    rmse: f64,
    in_front: f64,
    median_depth: f64,
    near_depth: f64,
    sigma: Option<PoseSigma>,
}

/// Localises a desired shot taken with the map's camera (see the module
/// documentation). `mask` (same size as the shot, 0 = no data) keeps
/// features off the black fill.
///
/// Errors: [`ShotError::ImageSize`] when the shot or the mask does not have
/// the map camera's size; [`ShotError::Features`] when the extractor refuses
/// the settings.
pub fn localize(
    map: &Map,
    shot: &GrayImage,
    mask: Option<&GrayImage>,
    bow_index: Option<&BowIndex<'_>>,
    params: &LocalizeParams,
) -> Result<Localization, ShotError> {
    localize_with_camera(map, &map.camera, shot, mask, bow_index, params)
}

/// The camera assumed for a photo of `width` x `height` whose intrinsics
/// are not known: the map camera's field of view and distortion (in
/// normalised coordinates) scaled to the photo's size, as for a resized or
/// re-encoded frame of the same camera.
///
/// Errors: [`ShotError::ImageSize`] for an empty photo or one whose aspect
/// ratio differs from the map camera's by more than 2 %, where the scaling
/// would be a guess.
pub fn assumed_camera(map_camera: &Camera, width: u32, height: u32) -> Result<Camera, ShotError> {
    let size_err = || ShotError::ImageSize {
        width,
        height,
        expected_width: map_camera.width,
        expected_height: map_camera.height,
    };
    if width == 0 || height == 0 {
        return Err(size_err());
    }
    let sx = width as f64 / map_camera.width as f64;
    let sy = height as f64 / map_camera.height as f64;
    if (sx / sy - 1.0).abs() > 0.02 {
        return Err(size_err());
    }
    // Pixel centres at integers: x' = s·(x + 0.5) − 0.5.
    Camera::new(
        width,
        height,
        [
            map_camera.fx * sx,
            map_camera.fy * sy,
            sx * (map_camera.cx + 0.5) - 0.5,
            sy * (map_camera.cy + 0.5) - 0.5,
        ],
        map_camera.distortion,
    )
    .map_err(|_| size_err())
}

/// Localises a desired shot taken with `camera` (any intrinsics and size:
/// a photo from another camera) against `map`; otherwise as [`localize`].
///
/// Errors: [`ShotError::ImageSize`] when the shot or the mask does not have
/// `camera`'s size; [`ShotError::Features`] when the extractor refuses the
/// settings.
pub fn localize_with_camera(
    map: &Map,
    camera: &Camera,
    shot: &GrayImage,
    mask: Option<&GrayImage>,
    bow_index: Option<&BowIndex<'_>>,
    params: &LocalizeParams,
) -> Result<Localization, ShotError> {
    let cam = camera;
    for img in std::iter::once(shot).chain(mask) {
        if img.dimensions() != (cam.width, cam.height) {
            return Err(ShotError::ImageSize {
                width: img.width(),
                height: img.height(),
                expected_width: cam.width,
                expected_height: cam.height,
            });
        }
    }
    let mut fparams = params.features;
    fparams.scale_factor = map.scale.scale_factor as f32;
    fparams.n_levels = map.scale.n_levels();
    let mut extractor = OrbExtractor::new(fparams).map_err(|e| ShotError::Features {
        message: e.to_string(),
    })?;
    let feats = match mask {
        Some(m) => {
            extractor
                .extract_masked(shot, m, Some(cam))
                .map_err(|e| ShotError::Features {
                    message: e.to_string(),
                })?
        }
        None => extractor.extract(shot, Some(cam)),
    };
    let needed = params.min_candidate_matches.max(params.gate.min_inliers);
    if feats.len() < needed {
        return Ok(not(NotLocalizedReason::TooFewFeatures {
            found: feats.len(),
            needed,
        }));
    }

    // Candidates by descriptor matching against each keyframe's map points.
    let mut ranked: Vec<(KeyFrameId, Vec<(usize, PointId)>)> = Vec::new();
    let mut pts: Vec<(PointId, Descriptor)> = Vec::new();
    let candidates: Vec<KeyFrameId> = match bow_index {
        Some(index) => {
            let q = index.vocabulary.transform(&feats.descriptors);
            index
                .database
                .query(&q, params.top_k.max(1))
                .into_iter()
                .filter_map(|r| u32::try_from(r.id.0).ok().map(KeyFrameId))
                .collect()
        }
        None => map.keyframes().map(|k| k.id).collect(),
    };
    for kf in candidates.iter().filter_map(|id| map.keyframe(*id)) {
        pts.clear();
        for p in kf.points.iter().flatten() {
            if let Some(mp) = map.point(*p) {
                pts.push((*p, mp.descriptor));
            }
        }
        if pts.is_empty() {
            continue;
        }
        let m = match_descriptors(&feats.descriptors, &pts, params.max_hamming, params.ratio);
        ranked.push((kf.id, m));
    }
    if ranked.is_empty() {
        return Ok(not(NotLocalizedReason::NoCandidate));
    }
    ranked.sort_by(|a, b| b.1.len().cmp(&a.1.len()).then(a.0.cmp(&b.0)));
    ranked.truncate(params.top_k.max(1));
    let best_count = ranked[0].1.len();
    if best_count < params.min_candidate_matches {
        return Ok(not(NotLocalizedReason::TooFewMatches {
            found: best_count,
            needed: params.min_candidate_matches,
        }));
    }

    let intr = Intrinsics {
        fx: cam.fx,
        fy: cam.fy,
        cx: cam.cx,
        cy: cam.cy,
    };
    let bounds = Bounds::of(cam);
    let grid = FeatureGrid::new(&feats.keypoints, bounds);
    // A point at distance d looks, to the shot camera, as it would to the
    // map camera at d·f_map/f_shot (for the predicted pyramid level).
    let view = ShotView {
        cam,
        bounds,
        distance_factor: (map.camera.fx + map.camera.fy) / (cam.fx + cam.fy),
    };
    let mut poses: Vec<CandidatePose> = Vec::new();
    let mut tried = 0;
    for (kf_id, matches) in &ranked {
        if matches.len() < params.min_candidate_matches {
            continue;
        }
        tried += 1;
        if let Some(c) = refine_candidate(map, *kf_id, matches, &feats, &grid, &view, &intr, params)
        {
            poses.push(c);
        }
    }
    if poses.is_empty() {
        return Ok(not(NotLocalizedReason::PnpFailed { candidates: tried }));
    }
    poses.sort_by(|a, b| b.inliers.cmp(&a.inliers).then(a.rmse.total_cmp(&b.rmse)));
    let g = &params.gate;
    let gate = |c: &CandidatePose| -> Option<NotLocalizedReason> {
        let ratio = c.inliers as f64 / c.matches.max(1) as f64;
        if c.inliers < g.min_inliers {
            Some(NotLocalizedReason::TooFewInliers {
                found: c.inliers,
                needed: g.min_inliers,
            })
        } else if c.rmse.is_nan() || c.rmse > g.max_rmse_px {
            Some(NotLocalizedReason::HighReprojectionError {
                rmse_px: c.rmse,
                max_px: g.max_rmse_px,
            })
        } else if ratio < g.min_inlier_ratio {
            Some(NotLocalizedReason::LowInlierRatio {
                ratio,
                min: g.min_inlier_ratio,
            })
        } else if c.in_front < g.min_in_front_fraction {
            Some(NotLocalizedReason::PointsBehind {
                in_front_fraction: c.in_front,
                min: g.min_in_front_fraction,
            })
        } else {
            None
        }
    };
    let best = &poses[0];
    if let Some(reason) = gate(best) {
        return Ok(not(reason));
    }
    let best_wfc = best.cam_from_world.inverse();
    let mut agreeing = 0;
    let (mut spread_pos2, mut spread_rot2) = (0.0, 0.0);
    for other in poses.iter().skip(1) {
        if gate(other).is_some() {
            continue;
        }
        let owfc = other.cam_from_world.inverse();
        let dist = (owfc.translation.vector - best_wfc.translation.vector).norm()
            / best.median_depth.max(1e-12);
        let ang = owfc.rotation.angle_to(&best_wfc.rotation).to_degrees();
        let agrees = dist <= g.max_disagreement_depth_fraction && ang <= g.max_disagreement_deg;
        if !agrees {
            return Ok(not(NotLocalizedReason::CandidatesDisagree {
                other: other.kf,
                position_depth_fraction: dist,
                angle_deg: ang,
            }));
        }
        agreeing += 1;
        spread_pos2 += dist * dist;
        spread_rot2 += ang * ang;
    }
    let Some(pose_sigma) = best.sigma else {
        return Ok(not(NotLocalizedReason::NoCovariance));
    };
    // The map's error: the floor, or the agreeing candidates' spread.
    let (map_pos, map_rot) = if agreeing > 0 {
        (
            (spread_pos2 / agreeing as f64)
                .sqrt()
                .max(params.map_sigma.depth_fraction),
            (spread_rot2 / agreeing as f64)
                .sqrt()
                .max(params.map_sigma.rotation_deg),
        )
    } else {
        (
            params.map_sigma.depth_fraction,
            params.map_sigma.rotation_deg,
        )
    };
    let position = pose_sigma.position.hypot(map_pos * best.median_depth);
    let sigma = PoseSigma {
        position,
        position_depth_fraction: position / best.near_depth.max(1e-12),
        rotation_deg: pose_sigma.rotation_deg.hypot(map_rot),
    };
    if !(sigma.position_depth_fraction <= g.max_position_sigma_depth_fraction
        && sigma.rotation_deg <= g.max_rotation_sigma_deg)
    {
        return Ok(not(NotLocalizedReason::Uncertain {
            position_depth_fraction: sigma.position_depth_fraction,
            max_position_depth_fraction: g.max_position_sigma_depth_fraction,
            rotation_deg: sigma.rotation_deg,
            max_rotation_deg: g.max_rotation_sigma_deg,
        }));
    }
    Ok(Localization::Localized(ShotPose {
        world_from_cam: best_wfc,
        keyframe_id: best.kf,
        inliers: best.inliers,
        matches: best.matches,
        reprojection_rmse_px: best.rmse,
        inlier_ratio: best.inliers as f64 / best.matches.max(1) as f64,
        in_front_fraction: best.in_front,
        median_depth: best.median_depth,
        agreeing_candidates: agreeing,
        sigma,
    }))
}

fn not(reason: NotLocalizedReason) -> Localization {
    Localization::NotLocalized { reason }
}

/// The shot's camera as the projection of map points into it needs it.
struct ShotView<'c> {
    cam: &'c Camera,
    bounds: Bounds,
    distance_factor: f64,
}

/// Whether map point `id` is in the shot camera's frustum (in front, inside
/// the undistorted bounds, within its scale range, seen from within
/// `min_view_cos` of its mean viewing direction); where and at which level.
fn project_into_shot(
    map: &Map,
    view: &ShotView<'_>,
    id: PointId,
    cam_from_world: &Isometry3<f64>,
    center: &nalgebra::Vector3<f64>,
    min_view_cos: f64,
) -> Option<Projected> {
    let mp = map.point(id)?;
    let pc = cam_from_world * mp.position;
    if pc.z <= 0.0 {
        return None;
    }
    let u = view.cam.fx * pc.x / pc.z + view.cam.cx;
    let v = view.cam.fy * pc.y / pc.z + view.cam.cy;
    if !view.bounds.contains(u, v) {
        return None;
    }
    let po = mp.position.coords - center;
    let dist = po.norm();
    // The scale range, in the map camera's terms.
    let d_map = dist * view.distance_factor;
    if d_map < 0.8 * mp.min_distance || d_map > 1.2 * mp.max_distance {
        return None;
    }
    let view_cos = po.dot(&mp.normal) / dist;
    if view_cos < min_view_cos {
        return None;
    }
    Some(Projected {
        id,
        uv: Point2::new(u, v),
        level: map.scale.predict_level(mp.max_distance, d_map),
        view_cos,
    })
}

/// The local map of a shot: the points of the keyframes that observe the
/// points matched so far (most shared points first, at most `max_kfs`),
/// with the candidate keyframe and its best covisible ones always in.
fn local_points(
    map: &Map,
    kf_id: KeyFrameId,
    slots: &[Option<PointId>],
    params: &LocalizeParams,
) -> Vec<PointId> {
    let mut counts: std::collections::HashMap<KeyFrameId, usize> = std::collections::HashMap::new();
    for p in slots.iter().flatten() {
        if let Some(mp) = map.point(*p) {
            for (k, _) in &mp.observations {
                *counts.entry(*k).or_default() += 1;
            }
        }
    }
    let mut kfs: Vec<(KeyFrameId, usize)> = counts.into_iter().collect();
    kfs.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut chosen: Vec<KeyFrameId> = Vec::new();
    let mut seen_kf: HashSet<KeyFrameId> = HashSet::new();
    let candidate = map.keyframe(kf_id);
    let base = std::iter::once(kf_id).chain(
        candidate
            .into_iter()
            .flat_map(|k| k.best_covisible(params.covisible)),
    );
    for id in base.chain(kfs.iter().map(|x| x.0)) {
        if chosen.len() >= params.covisible + 1 + params.local_keyframes {
            break;
        }
        if seen_kf.insert(id) {
            chosen.push(id);
        }
    }
    let mut local: Vec<PointId> = Vec::new();
    let mut seen: HashSet<PointId> = HashSet::new();
    for id in chosen {
        if let Some(k) = map.keyframe(id) {
            for p in k.points.iter().flatten() {
                if seen.insert(*p) {
                    local.push(*p);
                }
            }
        }
    }
    local
}

/// PnP on a candidate's matches, then projection rounds with motion-only BA.
#[allow(clippy::too_many_arguments)]
fn refine_candidate(
    map: &Map,
    kf_id: KeyFrameId,
    matches: &[(usize, PointId)],
    feats: &features::Features,
    grid: &FeatureGrid,
    view: &ShotView<'_>,
    intr: &Intrinsics,
    params: &LocalizeParams,
) -> Option<CandidatePose> {
    map.keyframe(kf_id)?;
    let mut pw: Vec<Point3<f64>> = Vec::with_capacity(matches.len());
    let mut xn: Vec<Point2<f64>> = Vec::with_capacity(matches.len());
    let mut pairs: Vec<(usize, PointId)> = Vec::with_capacity(matches.len());
    for &(i, p) in matches {
        let Some(mp) = map.point(p) else { continue };
        let k = &feats.keypoints[i];
        pw.push(mp.position);
        xn.push(Point2::new(
            (k.ux as f64 - intr.cx) / intr.fx,
            (k.uy as f64 - intr.cy) / intr.fy,
        ));
        pairs.push((i, p));
    }
    let pnp =
        solve_pnp_ransac(&pw, &xn, intr.fx, &params.pnp, params.seed ^ kf_id.0 as u64).ok()?;
    let mut cam_from_world = pnp.cam_from_world;
    // Slots: keypoint -> point, seeded with the PnP inliers.
    let mut slots: Vec<Option<PointId>> = vec![None; feats.len()];
    for (k, &(i, p)) in pairs.iter().enumerate() {
        if pnp.inliers[k] {
            slots[i] = Some(p);
        }
    }
    let mut report = None;
    for &radius in &params.projection_radius_px {
        // The local map, grown from the keyframes that see the matched points.
        let local = local_points(map, kf_id, &slots, params);
        let used: HashSet<PointId> = slots.iter().flatten().copied().collect();
        let center = cam_from_world.inverse().translation.vector;
        let projected: Vec<_> = local
            .iter()
            .filter(|p| !used.contains(p))
            .filter_map(|p| {
                project_into_shot(map, view, *p, &cam_from_world, &center, params.min_view_cos)
            })
            .collect();
        let target = SearchTarget {
            keypoints: &feats.keypoints,
            descriptors: &feats.descriptors,
            grid,
            points: &slots,
        };
        let found = search_local_points(
            &target,
            &projected,
            map,
            &map.scale,
            radius,
            &params.matcher,
        );
        for (i, p) in found {
            slots[i] = Some(p);
        }
        let mut obs = Vec::new();
        let mut obs_slot = Vec::new();
        for (i, s) in slots.iter().enumerate() {
            if let Some(p) = s
                && let Some(mp) = map.point(*p)
            {
                let k = &feats.keypoints[i];
                obs.push(PoseObservation {
                    p_world: mp.position,
                    uv: Point2::new(k.ux as f64, k.uy as f64),
                    inv_sigma2: map
                        .scale
                        .inv_level_sigma2
                        .get(k.octave as usize)
                        .copied()
                        .unwrap_or(1.0),
                });
                obs_slot.push(i);
            }
        }
        let r = optimize_pose(cam_from_world, &obs, intr, &params.pose).ok()?;
        cam_from_world = r.cam_from_world;
        // Drop the outliers from the slots so the next round can re-match them.
        for (k, &i) in obs_slot.iter().enumerate() {
            if !r.inliers[k] {
                slots[i] = None;
            }
        }
        report = Some((r, obs));
    }
    let (r, obs) = report?;
    // A camera known only by its EXIF: its focal length and distortion
    // are estimated with the pose, the inliers classified again.
    let (cam_from_world, correction, inliers) =
        if params.camera_uncertainty == IntrinsicsUncertainty::default() {
            (cam_from_world, IntrinsicsCorrection::default(), r.inliers)
        } else {
            let (pose, corr) = refine_pose_and_intrinsics(
                cam_from_world,
                &obs,
                &r.inliers,
                intr,
                &params.camera_uncertainty,
            );
            let inliers = obs
                .iter()
                .map(|o| {
                    corr.project(intr, &(pose * o.p_world).coords)
                        .is_some_and(|uv| {
                            (uv - o.uv).norm_squared() * o.inv_sigma2 <= params.pose.chi2_threshold
                        })
                })
                .collect();
            (pose, corr, inliers)
        };
    let mut sq = 0.0;
    let mut n_in = 0usize;
    let mut in_front = 0usize;
    let mut depths = Vec::new();
    for (o, inl) in obs.iter().zip(&inliers) {
        if !inl {
            continue;
        }
        n_in += 1;
        let pc = cam_from_world * o.p_world;
        if let Some(uv) = correction.project(intr, &pc.coords) {
            in_front += 1;
            sq += (uv - o.uv).norm_squared();
            depths.push(pc.z);
        } else {
            sq += f64::INFINITY;
        }
    }
    if n_in == 0 {
        return None;
    }
    // The lower median (nearest-rank 50 % quantile).
    let median_depth = crate::stats::quantile(&depths, 0.5).unwrap_or(f64::NAN);
    let near_depth = crate::stats::quantile(&depths, 0.1).unwrap_or(f64::NAN);
    let sigma = pose_covariance(
        &cam_from_world,
        &obs,
        &inliers,
        intr,
        params.pose.chi2_threshold,
        None,
        &params.camera_uncertainty,
        &correction,
    )
    .map(|c| PoseSigma {
        position: c.position_sigma(),
        position_depth_fraction: c.position_sigma() / near_depth,
        rotation_deg: c.rotation_sigma().to_degrees(),
    });
    Some(CandidatePose {
        kf: kf_id,
        cam_from_world,
        inliers: n_in,
        matches: obs.len(),
        rmse: (sq / n_in as f64).sqrt(),
        in_front: in_front as f64 / n_in as f64,
        median_depth,
        near_depth,
        sigma,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion};
    use crate::slam::ScaleInfo;

    fn empty_map() -> Map {
        let cam = Camera::new(
            320,
            240,
            [300.0, 300.0, 160.0, 120.0],
            Distortion::default(),
        )
        .unwrap_or_else(|e| panic!("camera: {e}"));
        Map::new(cam, ScaleInfo::new(1.2, 8))
    }

    /// A textured image with plenty of corners.
    fn checker(w: u32, h: u32) -> GrayImage {
        GrayImage::from_fn(w, h, |x, y| {
            let v = ((x / 9 + y / 7) % 2) as u8 * 180 + ((x * 31 + y * 17) % 37) as u8;
            image::Luma([v])
        })
    }

    #[test]
    fn wrong_sizes_are_errors() {
        let map = empty_map();
        let p = LocalizeParams::default();
        assert!(matches!(
            localize(&map, &checker(640, 480), None, None, &p),
            Err(ShotError::ImageSize { width: 640, .. })
        ));
        let mask = GrayImage::from_pixel(100, 100, image::Luma([255]));
        assert!(matches!(
            localize(&map, &checker(320, 240), Some(&mask), None, &p),
            Err(ShotError::ImageSize { width: 100, .. })
        ));
    }

    #[test]
    fn assumed_camera_scales_the_map_camera_and_refuses_other_aspects() {
        let map = empty_map();
        let c = assumed_camera(&map.camera, 640, 480).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!((c.width, c.height), (640, 480));
        assert!((c.fx - 600.0).abs() < 1e-12 && (c.fy - 600.0).abs() < 1e-12);
        // Pixel centres: (160 + 0.5)·2 − 0.5.
        assert!((c.cx - 320.5).abs() < 1e-12 && (c.cy - 240.5).abs() < 1e-12);
        // The same ray through corresponding pixels.
        let r0 = map.camera.unproject(Point2::new(10.0, 20.0)).into_inner();
        let r1 = c.unproject(Point2::new(20.5, 40.5)).into_inner();
        assert!((r0 - r1).norm() < 1e-12, "{r0} vs {r1}");
        assert!(matches!(
            assumed_camera(&map.camera, 400, 240),
            Err(ShotError::ImageSize { width: 400, .. })
        ));
        assert!(assumed_camera(&map.camera, 0, 0).is_err());
        // A shot must have the size of the camera it is localised with.
        let p = LocalizeParams::default();
        assert!(matches!(
            localize_with_camera(&map, &c, &checker(320, 240), None, None, &p),
            Err(ShotError::ImageSize {
                expected_width: 640,
                ..
            })
        ));
        assert_eq!(
            localize_with_camera(&map, &c, &checker(640, 480), None, None, &p),
            Ok(Localization::NotLocalized {
                reason: NotLocalizedReason::NoCandidate
            })
        );
    }

    #[test]
    fn empty_map_gives_no_candidate_and_blank_shot_too_few_features() {
        let map = empty_map();
        let p = LocalizeParams::default();
        assert_eq!(
            localize(&map, &checker(320, 240), None, None, &p),
            Ok(Localization::NotLocalized {
                reason: NotLocalizedReason::NoCandidate
            })
        );
        // A fully masked shot yields no feature at all.
        let mask = GrayImage::new(320, 240);
        assert!(matches!(
            localize(&map, &checker(320, 240), Some(&mask), None, &p),
            Ok(Localization::NotLocalized {
                reason: NotLocalizedReason::TooFewFeatures { found: 0, .. }
            })
        ));
    }
}
