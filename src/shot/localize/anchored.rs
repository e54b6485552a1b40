//! An anchors shot's camera from the keyframe's own geometry.
//!
//! The operator drew four anchors on a keyframe whose pose the map knows,
//! and the map points that keyframe observes are known too. The anchors'
//! homography `H` (shot pixel → keyframe pixel) moves each of those
//! observations to where it lies in the desired picture, so the desired
//! picture's 2D-3D pairs are known without matching anything: the
//! desired camera is their PnP (RANSAC, then motion-only BA, the map
//! camera's intrinsics). Nothing is re-found in the map by matching a
//! warped picture, whose features a zoom or a rotation resamples.
//!
//! A homography of a keyframe is not always a view a camera can take: a
//! drawn zoom of a scene with depth asks near and far content to grow
//! alike, which no camera position does. That part is the fit's residual:
//! the shot's floor, which the refinement loop measures
//! ([`crate::refine::Reachable`]) and the operator sees, not a reason to
//! refuse. The sigma is the fit's covariance (its residual taken as the
//! noise) with the map's own error, as for any other shot.
//!
//! A drawing is refused only for what the operator can change: too few of
//! the keyframe's mapped points inside the drawn frame (draw it over more
//! of the mapped scene or choose another keyframe).

use nalgebra::{Matrix3, Point2, Point3};

use super::covariance::{MapError, beyond_views, reported_sigma};
use super::outcome::Localization;
use super::outcome::{NotLocalizedReason, ShotPose, not};
use super::params::LocalizeParams;
use super::pose_refinement::evaluate_candidate;
use super::projection::{ShotView, frustum_near_depth};
use crate::geometry::homography4::apply_homography;
use crate::geometry::solve_pnp_ransac;
use crate::matching::Bounds;
use crate::optimize::{
    Intrinsics, IntrinsicsCorrection, PoseObservation, observation_chi2, optimize_pose,
};
use crate::slam::{KeyFrameId, Map};

/// The camera that takes the desired shot drawn on keyframe `keyframe` of
/// `map` with `shot_to_keyframe` (`H`: desired-shot pixel → keyframe
/// pixel, raw pixels, the map camera's size), from the keyframe's own
/// observations moved through `H` (see the module documentation).
///
/// Not localised only with [`NotLocalizedReason::UnknownKeyframe`] or
/// [`NotLocalizedReason::AnchorsFewPoints`]; no reprojection threshold
/// and no sigma gate apply: the misfit (pairs no camera explains, near
/// content a zoom would leave behind the camera) is the shot's floor.
pub fn localize_anchors(
    map: &Map,
    keyframe: KeyFrameId,
    shot_to_keyframe: &Matrix3<f64>,
    params: &LocalizeParams,
) -> Localization {
    let a = &params.anchors;
    let Some(kf) = map.keyframe(keyframe) else {
        return not(NotLocalizedReason::UnknownKeyframe { keyframe });
    };
    let camera = &map.camera;
    let Some(shot_from_keyframe) = shot_to_keyframe
        .try_inverse()
        .filter(|m| m.iter().all(|v| v.is_finite()))
    else {
        return not(NotLocalizedReason::AnchorsFewPoints {
            keyframe,
            found: 0,
            needed: a.min_points,
            mapped: 0,
        });
    };
    let intr = Intrinsics {
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
    };
    let mut obs: Vec<PoseObservation> = Vec::new();
    let mut pw: Vec<Point3<f64>> = Vec::new();
    let mut xn: Vec<Point2<f64>> = Vec::new();
    let mut ids: Vec<Option<crate::slam::PointId>> = Vec::new();
    let mut mapped = 0usize;
    for (k, pid) in kf.keypoints.iter().zip(&kf.points) {
        let Some(p) = pid.and_then(|id| map.point(id)) else {
            continue;
        };
        mapped += 1;
        let at_keyframe = Point2::new(f64::from(k.x), f64::from(k.y));
        let Some(d) = apply_homography(&shot_from_keyframe, &at_keyframe) else {
            continue;
        };
        if !camera.contains(d, 0.0) {
            continue;
        }
        let u = camera.undistort_pixel(d);
        if !(u.x.is_finite() && u.y.is_finite()) {
            continue;
        }
        obs.push(PoseObservation {
            p_world: p.position,
            uv: u,
            inv_sigma2: map
                .scale
                .inv_level_sigma2
                .get(usize::from(k.octave))
                .copied()
                .unwrap_or(1.0),
        });
        pw.push(p.position);
        ids.push(Some(p.id));
        xn.push(Point2::new(
            (u.x - intr.cx) / intr.fx,
            (u.y - intr.cy) / intr.fy,
        ));
    }
    let few = |found| {
        not(NotLocalizedReason::AnchorsFewPoints {
            keyframe,
            found,
            needed: a.min_points,
            mapped,
        })
    };
    if obs.len() < a.min_points.max(4) {
        return few(obs.len());
    }
    // PnP RANSAC keeps the pairs one camera explains (a drawn zoom of a
    // scene with depth fits its dominant layer, and the keyframe's few
    // wrong points drop out); motion-only BA refines on those alone, as
    // content that would stand close to the desired camera pulls a
    // robust fit over all pairs off the layer. Without a consensus (a
    // deep scene's residuals all past RANSAC's threshold), from the
    // keyframe's own pose over all pairs.
    let (start, fit_on): (_, Vec<PoseObservation>) = match solve_pnp_ransac(
        &pw,
        &xn,
        intr.fx,
        &params.pnp,
        params.seed ^ u64::from(keyframe.0),
    ) {
        Ok(r) => (
            r.cam_from_world,
            obs.iter()
                .zip(&r.inliers)
                .filter(|(_, i)| **i)
                .map(|(o, _)| *o)
                .collect(),
        ),
        Err(_) => (kf.cam_from_world, obs.clone()),
    };
    let Ok(report) = optimize_pose(start, &fit_on, &intr, &params.pose) else {
        return few(fit_on.len());
    };
    // Every pair classified by the refined camera.
    let inliers: Vec<bool> = obs
        .iter()
        .map(|o| {
            observation_chi2(&report.cam_from_world, &intr, o, params.pose.min_depth)
                .is_some_and(|c| c <= params.pose.chi2_threshold)
        })
        .collect();
    let map_error = MapError::of(map, &params.map_sigma);
    let Some(fit) = evaluate_candidate(
        keyframe,
        report.cam_from_world,
        &obs,
        &inliers,
        Vec::new(),
        &intr,
        params,
        &map_error,
    ) else {
        return few(0);
    };
    let Some(pose_sigma) = fit.sigma else {
        return not(NotLocalizedReason::NoCovariance);
    };
    let view = ShotView {
        cam: camera,
        bounds: Bounds::of(camera),
        distance_factor: 1.0,
        correction: IntrinsicsCorrection::default(),
    };
    let near = frustum_near_depth(map, &view, &fit.cam_from_world)
        .map_or(fit.near_depth, |d| d.min(fit.near_depth));
    let inlier_ids: Vec<_> = ids
        .iter()
        .zip(&inliers)
        .map(|(id, i)| id.filter(|_| *i))
        .collect();
    let views = beyond_views(map, &fit.cam_from_world, &inlier_ids);
    let beyond = views.deg;
    let sigma = reported_sigma(
        &pose_sigma,
        None,
        &map_error,
        fit.median_depth,
        near,
        views.factor,
    );
    tracing::debug!(
        keyframe = keyframe.0,
        points = obs.len(),
        inliers = fit.inliers,
        rmse_px = fit.rmse,
        position_pct = sigma.position_depth_fraction * 100.0,
        rotation_deg = sigma.rotation_deg,
        beyond_views_deg = beyond,
        "anchors shot from the keyframe's geometry"
    );
    Localization::Localized(ShotPose {
        world_from_cam: fit.cam_from_world.inverse(),
        keyframe_id: keyframe,
        inliers: fit.inliers,
        matches: obs.len(),
        reprojection_rmse_px: fit.rmse,
        inlier_ratio: fit.inliers as f64 / obs.len() as f64,
        in_front_fraction: fit.in_front,
        median_depth: fit.median_depth,
        agreeing_candidates: 0,
        beyond_views_deg: beyond,
        sigma,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion};
    use crate::features::KeyPoint;
    use crate::matching::FeatureGrid;
    use crate::slam::{KeyFrame, ScaleInfo};
    use nalgebra::{Isometry3, UnitQuaternion, Vector3};

    const F: f64 = 460.0;

    /// A map with one keyframe at the origin looking along +z (its
    /// `cam_from_world` the identity) at points whose depth `depth(x, y)`
    /// gives; each point observed where the keyframe's camera projects it.
    fn map_seeing(depth: impl Fn(f64, f64) -> f64) -> (Map, KeyFrameId) {
        let cam = Camera::new(640, 480, [F, F, 319.5, 239.5], Distortion::default())
            .unwrap_or_else(|e| panic!("camera: {e}"));
        let mut map = Map::new(cam, ScaleInfo::new(1.2, 8));
        let (mut keypoints, mut points) = (Vec::new(), Vec::new());
        for i in 0..32 {
            for j in 0..24 {
                let px = Point2::new(10.0 + 20.0 * f64::from(i), 10.0 + 20.0 * f64::from(j));
                let n = cam.pixel_to_normalized(px);
                let z = depth(n.x, n.y);
                let id = map.add_point(Point3::new(n.x * z, n.y * z, z), [0; 4], KeyFrameId(0));
                keypoints.push(KeyPoint {
                    x: px.x as f32,
                    y: px.y as f32,
                    ux: px.x as f32,
                    uy: px.y as f32,
                    ..KeyPoint::default()
                });
                points.push(Some(id));
            }
        }
        let n = keypoints.len();
        let kf = map.add_keyframe(KeyFrame {
            id: KeyFrameId(0),
            frame_index: 0,
            timestamp: 0.0,
            cam_from_world: Isometry3::identity(),
            keypoints,
            descriptors: vec![[0; 4]; n],
            points,
            grid: FeatureGrid::default(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: None,
        });
        (map, kf)
    }

    /// `H` (shot → keyframe) of a centred zoom: the keyframe's pixels
    /// `a` times as far from the principal point as the shot's.
    fn zoom(a: f64) -> Matrix3<f64> {
        Matrix3::new(
            a,
            0.0,
            319.5 * (1.0 - a),
            0.0,
            a,
            239.5 * (1.0 - a),
            0.0,
            0.0,
            1.0,
        )
    }

    fn localized(l: Localization) -> ShotPose {
        match l {
            Localization::Localized(p) => p,
            Localization::NotLocalized { reason } => panic!("not localised: {reason}"),
        }
    }

    #[test]
    fn a_zoom_of_flat_ground_moves_the_camera_forward_exactly() {
        // Ground 10 units ahead, facing the camera: pulling the anchors in
        // to 0.8 of the frame is the view from 2 units closer, exactly.
        let (map, kf) = map_seeing(|_, _| 10.0);
        let p = localized(localize_anchors(
            &map,
            kf,
            &zoom(0.8),
            &LocalizeParams::default(),
        ));
        let t = p.world_from_cam.translation.vector;
        assert!((t - Vector3::new(0.0, 0.0, 2.0)).norm() < 1e-3, "{t}");
        assert!(p.world_from_cam.rotation.angle() < 1e-5);
        assert!(p.reprojection_rmse_px < 1e-3, "{}", p.reprojection_rmse_px);
        // Only the points inside the drawn frame place it: 0.8 of the
        // width and height.
        assert!(
            (0.55..0.72).contains(&(p.matches as f64 / 768.0)),
            "{}",
            p.matches
        );
        assert!(p.sigma.position.is_finite() && p.sigma.position > 0.0);
    }

    #[test]
    fn a_pan_turns_the_camera_in_place() {
        let (map, kf) = map_seeing(|x, y| 8.0 + 3.0 * x.abs() + 2.0 * y);
        // The keyframe's camera turned 5 deg about y, 3 deg about x: the
        // shot is its view whatever the depths, H = K R K⁻¹.
        let turn = UnitQuaternion::from_euler_angles(3f64.to_radians(), 5f64.to_radians(), 0.0);
        let k = map.camera.k();
        let h = k * turn.to_rotation_matrix().matrix() * map.camera.k_inv();
        let p = localized(localize_anchors(&map, kf, &h, &LocalizeParams::default()));
        assert!(p.world_from_cam.translation.vector.norm() < 1e-3);
        let angle = p.world_from_cam.rotation.angle_to(&turn).to_degrees();
        assert!(angle < 1e-3, "{angle} deg");
    }

    #[test]
    fn a_zoom_of_a_deep_scene_is_placed_on_its_dominant_layer() {
        // Near content (6 away) on the left quarter, far (18) elsewhere:
        // no camera sees a centred 1.4x zoom of both, so the camera is the
        // one that takes the far layer, most of the drawn frame, exactly;
        // the near layer's misfit is left as outliers, not a refusal.
        let (map, kf) = map_seeing(|x, _| if x < -0.25 { 6.0 } else { 18.0 });
        let a = 1.0 / 1.4;
        let p = localized(localize_anchors(
            &map,
            kf,
            &zoom(a),
            &LocalizeParams::default(),
        ));
        let t = p.world_from_cam.translation.vector;
        assert!(
            (t - Vector3::new(0.0, 0.0, 18.0 * (1.0 - a))).norm() < 1e-3,
            "{t}"
        );
        assert!((0.6..0.9).contains(&p.inlier_ratio), "{}", p.inlier_ratio);
        assert!(p.reprojection_rmse_px < 0.01, "{}", p.reprojection_rmse_px);
    }

    #[test]
    fn refusals_name_what_to_change() {
        let (map, kf) = map_seeing(|_, _| 10.0);
        let params = LocalizeParams::default();
        // A frame drawn over a corner holding 4 points: too few.
        let tiny = Matrix3::new(0.06, 0.0, 0.0, 0.0, 0.06, 0.0, 0.0, 0.0, 1.0);
        match localize_anchors(&map, kf, &tiny, &params) {
            Localization::NotLocalized {
                reason:
                    reason @ NotLocalizedReason::AnchorsFewPoints {
                        found, mapped: 768, ..
                    },
            } => {
                assert!(found < 12, "{found}");
                assert!(
                    reason
                        .to_string()
                        .contains("draw it over more of the mapped scene")
                );
            }
            other => panic!("{other:?}"),
        }
        match localize_anchors(&map, KeyFrameId(9), &zoom(0.8), &params) {
            Localization::NotLocalized {
                reason: NotLocalizedReason::UnknownKeyframe { keyframe },
            } => assert_eq!(keyframe, KeyFrameId(9)),
            other => panic!("{other:?}"),
        }
    }
}
