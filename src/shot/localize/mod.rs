//! Localisation of a desired shot in the map: which camera pose
//! (`world_from_cam`, map coordinates) takes it.
//!
//! 1. ORB on the shot, with the validity mask (the black fill never yields a
//!    feature).
//! 2. Candidate keyframes: with a [`BowIndex`], the first
//!    [`LocalizeParams::bow_candidates`] of a bag-of-words query of the shot
//!    against the keyframe database; without one, every keyframe (one
//!    brute-force pass per keyframe, fine for maps of up to a few hundred
//!    keyframes). Each one's map points are matched by descriptor (nearest
//!    neighbour under a Hamming bound, ratio test, one-to-one), and the top
//!    k by matches are the candidates.
//! 3. Per candidate: PnP RANSAC on its matches; then the local map (the
//!    points of the candidate, its best covisible keyframes and the keyframes
//!    that observe the points matched so far, most shared points first) is
//!    projected with that pose and matched in the shot (search by
//!    projection), and motion-only bundle adjustment (Huber, then outliers
//!    dropped) refines the pose on all pairs; twice, the second time with the
//!    local map regrown from the refined matches and a tighter window.
//!
//! An anchors shot does not go through these steps: its camera comes from
//! the keyframe's own 2D-3D observations moved through the anchors'
//! homography ([`localize_anchors`], `anchored.rs`).
//!
//! The shot may come from another camera ([`localize_with_camera`]): its
//! own intrinsics and distortion are used for the features, the PnP, the
//! projection (with the predicted pyramid level corrected for the focal
//! length ratio) and the refinement; [`assumed_camera`] gives the camera of
//! a resized photo when the intrinsics are not known, and then the map
//! camera resized and another camera (focal length and distortion fitted
//! with the pose) are weighed as two hypotheses ([`UnknownFocal`]); the
//! local map is then searched again through the camera the weighing chose
//! and both are weighed again on the grown pairs
//! ([`LocalizeParams::rematch_rounds`]).
//! 4. A reliability gate: enough inliers, a small reprojection RMSE, a high
//!    inlier ratio, the inliers in front of the camera, and agreement with
//!    every other candidate that passes the gate too. The pairs of all
//!    agreeing candidates then go into one final pose optimisation (the
//!    union of evidence), kept when it passes the gate too. Failing it gives
//!    [`Localization::NotLocalized`] with the reason; no pose is returned then.

mod anchored;
mod candidates;
mod covariance;
mod focal;
mod gate;
mod outcome;
mod params;
mod pose_refinement;
mod projection;

use image::GrayImage;

pub use self::anchored::localize_anchors;
pub use self::candidates::{BowIndex, NearKeyframe, nearest_keyframes};
pub use self::focal::assumed_camera;
pub use self::outcome::{Localization, NotLocalizedReason, PoseSigma, ShotPose};
pub use self::params::{
    AnchorPoseParams, EXIF_K1_SIGMA, EXIF_K2_SIGMA, GateParams, LocalizeParams, MapSigma,
    PositionPrior, UnknownFocal,
};

use self::candidates::{extract_shot_features, neighbourhood_matches, rank_candidates};
use self::covariance::{MapError, beyond_views, reported_sigma};
use self::gate::{agreement, gate_reason, union_of_evidence};
use self::outcome::not;
use self::pose_refinement::{CandidatePose, refine_candidate};
use self::projection::{ShotView, frustum_near_depth};
use crate::camera::Camera;
use crate::matching::{Bounds, FeatureGrid};
use crate::optimize::{Intrinsics, IntrinsicsCorrection};
use crate::shot::ShotError;
use crate::slam::{KeyFrameId, Map, PointId};

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
    let feats = extract_shot_features(map, cam, shot, mask, params)?;
    let needed = params.min_candidate_matches.max(params.gate.min_inliers);
    if feats.len() < needed {
        return Ok(not(NotLocalizedReason::TooFewFeatures {
            found: feats.len(),
            needed,
        }));
    }
    let (ranked, near_prior) = match rank_candidates(map, &feats, bow_index, params) {
        Ok(r) => r,
        Err(reason) => return Ok(not(reason)),
    };

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
        correction: IntrinsicsCorrection::default(),
    };
    let map_error = MapError::of(map, &params.map_sigma);
    let mut poses: Vec<CandidatePose> = Vec::new();
    let mut tried = 0;
    let g = &params.gate;
    // With a position prior (the photo's GPS tag): a candidate's pose near
    // it (always true without one).
    let near_prior_pose = |c: &CandidatePose| {
        params.position_prior.is_none_or(|prior| {
            let centre = nalgebra::Point3::from(c.cam_from_world.inverse().translation.vector);
            let pose_sigma = c.sigma.map_or(0.0, |s| s.position);
            prior.distance(&centre, pose_sigma).1 <= g.max_prior_sigmas
        })
    };
    // ... and passing the gate.
    let gated_near_prior = |poses: &[CandidatePose]| {
        poses
            .iter()
            .any(|c| gate_reason(c, g).is_none() && near_prior_pose(c))
    };
    let mut try_candidate =
        |kf_id: KeyFrameId, matches: &[(usize, PointId)], poses: &mut Vec<CandidatePose>| {
            if matches.len() < params.min_candidate_matches {
                return;
            }
            tried += 1;
            // The candidate's own matches first; where they give no pose the
            // gate takes, its neighbourhood's (every observation's descriptor
            // of the points of its covisible keyframes): a photo far round
            // from the flown views that the direct matching misses. Not for a
            // photo whose camera is only assumed: its focal length and
            // distortion are fitted too, and the wider, noisier matches let
            // a wrong camera fit them (teddy's last held-out frame, resized:
            // 2.5 deg off where the map camera's photo is 1.9 deg off).
            let own = refine_candidate(
                map, kf_id, matches, &feats, &grid, &view, &intr, params, &map_error,
            );
            if params.focal_unknown
                || own
                    .as_ref()
                    .is_some_and(|c| gate_reason(c, &params.gate).is_none())
            {
                poses.extend(own);
                return;
            }
            let wide = neighbourhood_matches(map, kf_id, &feats, params);
            let again = (wide.len() > matches.len())
                .then(|| {
                    refine_candidate(
                        map, kf_id, &wide, &feats, &grid, &view, &intr, params, &map_error,
                    )
                })
                .flatten();
            tracing::debug!(
                keyframe = kf_id.0,
                own = matches.len(),
                own_pose = own.as_ref().map(|c| c.inliers),
                neighbourhood = wide.len(),
                neighbourhood_pose = again.as_ref().map(|c| c.inliers),
                "shot candidate: its own matches gave no pose the gate takes; its neighbourhood's"
            );
            match (own, again) {
                (_, Some(c)) if gate_reason(&c, &params.gate).is_none() => poses.push(c),
                (Some(c), _) | (None, Some(c)) => poses.push(c),
                (None, None) => {}
            }
        };
    for (kf_id, matches) in &ranked {
        try_candidate(*kf_id, matches, &mut poses);
    }
    // The keyframes near the prior, when the first candidates gave no
    // pose near it that the gate takes: a look-alike place that outranks
    // the right one by its descriptors does not keep the right one from
    // being tried (and when the first candidates agree with the prior,
    // nothing changes).
    if !near_prior.is_empty() && !gated_near_prior(&poses) {
        tracing::debug!(
            candidates = near_prior.len(),
            "no candidate near the photo's position prior: the keyframes near it tried"
        );
        let first = poses.len();
        for (kf_id, matches) in &near_prior {
            try_candidate(*kf_id, matches, &mut poses);
        }
        // None of them near it either: the photo is refused as far from
        // its prior on the first candidates' evidence alone.
        if !gated_near_prior(&poses[first..]) {
            poses.truncate(first);
        }
    }
    if poses.is_empty() {
        return Ok(not(NotLocalizedReason::PnpFailed { candidates: tried }));
    }
    poses.sort_by(|a, b| b.inliers.cmp(&a.inliers).then(a.rmse.total_cmp(&b.rmse)));
    // With a position prior (the photo's GPS tag), the candidates' poses
    // far from it are a look-alike place: left out when a pose near it
    // remains, so the place the tag confirms is the one chosen (and the
    // others neither win nor veto it as disagreeing). When none is near,
    // all stay, and the best is refused as far from the prior below.
    if params.position_prior.is_some() && gated_near_prior(&poses) {
        let before = poses.len();
        poses.retain(|c| near_prior_pose(c));
        tracing::debug!(
            kept = poses.len(),
            left_out = before - poses.len(),
            "shot candidates far from the photo's position prior left out"
        );
    }
    if let Some(reason) = gate_reason(&poses[0], g) {
        return Ok(not(reason));
    }
    // Two candidates, each refined on its own local map, differ by the
    // map's error: on a noisier map than the reference the bounds of
    // their agreement widen with it, as the map's sigma does.
    let agreement_gate = GateParams {
        max_disagreement_depth_fraction: g.max_disagreement_depth_fraction * map_error.noise_factor,
        max_disagreement_deg: g.max_disagreement_deg * map_error.noise_factor,
        ..*g
    };
    let agreeing = match agreement(&poses, &agreement_gate) {
        Ok(a) => a,
        Err(reason) => return Ok(not(reason)),
    };
    let merged = union_of_evidence(map, &feats, &poses[0], &agreeing, &intr, params, &map_error);
    let best = merged.as_ref().unwrap_or(&poses[0]);
    let best_wfc = best.cam_from_world.inverse();
    let Some(pose_sigma) = best.sigma else {
        return Ok(not(NotLocalizedReason::NoCovariance));
    };
    // The nearest scene content: the matched points may all be far while
    // nearer mapped content (unmatched from this view) is in the picture.
    let near = frustum_near_depth(map, &view, &best.cam_from_world)
        .map_or(best.near_depth, |d| d.min(best.near_depth));
    let views = beyond_views(map, &best.cam_from_world, &best.slots);
    let beyond = views.deg;
    let sigma = reported_sigma(
        &pose_sigma,
        agreeing.rms_spread(),
        &map_error,
        best.median_depth,
        near,
        views.factor,
    );
    tracing::debug!(
        keyframe = best.kf.0,
        inliers = best.inliers,
        agreeing = agreeing.count,
        pose_position = pose_sigma.position,
        pose_rotation_deg = pose_sigma.rotation_deg,
        spread = ?agreeing.rms_spread(),
        map_absolute = map_error.absolute,
        median_depth = best.median_depth,
        near,
        position = sigma.position,
        position_pct = sigma.position_depth_fraction * 100.0,
        rotation_deg = sigma.rotation_deg,
        beyond_views_deg = beyond,
        view_factor = views.factor,
        "shot sigma"
    );
    if let Some(prior) = &params.position_prior {
        let (distance, sigmas) = prior.distance(
            &nalgebra::Point3::from(best_wfc.translation.vector),
            sigma.position,
        );
        tracing::debug!(
            distance,
            sigmas,
            prior_sigma = prior.sigma,
            "shot against its position prior"
        );
        if sigmas.is_nan() || sigmas > g.max_prior_sigmas {
            return Ok(not(NotLocalizedReason::FarFromPrior {
                distance,
                sigmas,
                max_sigmas: g.max_prior_sigmas,
                prior_sigma: prior.sigma,
                metres_per_unit: prior.metres_per_unit,
            }));
        }
    }
    if !(sigma.position_depth_fraction <= g.max_position_sigma_depth_fraction
        && sigma.rotation_deg <= g.max_rotation_sigma_deg)
    {
        return Ok(not(NotLocalizedReason::Uncertain {
            position_depth_fraction: sigma.position_depth_fraction,
            max_position_depth_fraction: g.max_position_sigma_depth_fraction,
            rotation_deg: sigma.rotation_deg,
            max_rotation_deg: g.max_rotation_sigma_deg,
            beyond_views_deg: beyond,
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
        agreeing_candidates: agreeing.count,
        beyond_views_deg: beyond,
        sigma,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::Point2;

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
