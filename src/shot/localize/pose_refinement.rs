//! The pose refinement of a localisation (not the shot refinement of
//! [`crate::refine`]): one candidate keyframe's pose by PnP RANSAC on its
//! descriptor matches, projection rounds with motion-only BA, the camera's
//! hypotheses fitted and weighed, and for an assumed camera the local map
//! searched again through the camera the weighing chose.

use nalgebra::{Isometry3, Point2, Point3};

use super::covariance::{Hypothesis, MapError, fit_hypothesis, mixture_sigma};
use super::focal::{fit_other_camera, same_camera_probability};
use super::outcome::PoseSigma;
use super::params::LocalizeParams;
use super::projection::{ShotView, search_by_projection};
use crate::features;
use crate::geometry::solve_pnp_ransac;
use crate::matching::FeatureGrid;
use crate::optimize::{
    Intrinsics, IntrinsicsCorrection, IntrinsicsUncertainty, PoseObservation, optimize_pose,
};
use crate::slam::{KeyFrameId, Map, PointId};

/// One candidate's refined pose and its statistics (before the gate).
pub(super) struct CandidatePose {
    pub(super) kf: KeyFrameId,
    pub(super) cam_from_world: Isometry3<f64>,
    pub(super) inliers: usize,
    pub(super) matches: usize,
    pub(super) rmse: f64,
    pub(super) in_front: f64,
    pub(super) median_depth: f64,
    pub(super) near_depth: f64,
    pub(super) sigma: Option<PoseSigma>,
    /// Keypoint -> map point after the last round (outliers dropped).
    pub(super) slots: Vec<Option<PointId>>,
    /// The chosen camera's correction of the shot camera (identity unless
    /// the focal length was weighed and another camera won).
    pub(super) correction: IntrinsicsCorrection,
    /// The chosen camera's inliers among the pairs the pose was fitted on.
    pub(super) obs_inliers: Vec<bool>,
}

/// PnP on a candidate's matches, then projection rounds with motion-only BA.
#[allow(clippy::too_many_arguments)]
pub(super) fn refine_candidate(
    map: &Map,
    kf_id: KeyFrameId,
    matches: &[(usize, PointId)],
    feats: &features::Features,
    grid: &FeatureGrid,
    view: &ShotView<'_>,
    intr: &Intrinsics,
    params: &LocalizeParams,
    map_error: &MapError,
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
    let pnp = match solve_pnp_ransac(&pw, &xn, intr.fx, &params.pnp, params.seed ^ kf_id.0 as u64) {
        Ok(p) => p,
        Err(e) => {
            tracing::debug!(keyframe = kf_id.0, matches = pairs.len(), error = %e, "shot candidate: PnP failed");
            return None;
        }
    };
    tracing::debug!(
        keyframe = kf_id.0,
        matches = pairs.len(),
        pnp_inliers = pnp.inliers.iter().filter(|x| **x).count(),
        "shot candidate: PnP"
    );
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
        let found = search_by_projection(
            map,
            kf_id,
            view,
            &cam_from_world,
            &slots,
            (feats, grid),
            radius,
            params,
        );
        let n_found = found.len();
        for (i, p) in found {
            slots[i] = Some(p);
        }
        let (r, obs, obs_slot, matched) =
            refit_on_slots(map, feats, &mut slots, cam_from_world, intr, params)?;
        tracing::debug!(
            keyframe = kf_id.0,
            radius,
            found = n_found,
            pairs = obs.len(),
            inliers = r.inliers.iter().filter(|x| **x).count(),
            "shot candidate: projection round"
        );
        cam_from_world = r.cam_from_world;
        report = Some((r, obs, obs_slot, matched));
    }
    let (r, obs, obs_slot, matched) = report?;
    let cand = evaluate_candidate(
        kf_id,
        r.cam_from_world,
        &obs,
        &r.inliers,
        slots,
        intr,
        params,
        map_error,
    )?;
    let estimated =
        params.focal_unknown || params.camera_uncertainty != IntrinsicsUncertainty::default();
    if !estimated {
        return Some(cand);
    }
    let fitted = Fitted {
        cand,
        h0_pose: r.cam_from_world,
        obs_slot,
        matched,
    };
    Some(rematch_with_estimated_camera(
        map, kf_id, fitted, feats, grid, view, intr, params, map_error,
    ))
}

/// A candidate's pose with what a further projection round starts from.
struct Fitted {
    /// The pose, its statistics and the chosen camera.
    cand: CandidatePose,
    /// The pose fitted with the assumed camera (H0 of [`UnknownFocal`]).
    h0_pose: Isometry3<f64>,
    /// The keypoint of each pair the pose was fitted on.
    obs_slot: Vec<usize>,
    /// Keypoint -> map point of those pairs (outliers included).
    matched: Vec<Option<PointId>>,
}

/// For a photo whose focal length was weighed
/// ([`LocalizeParams::focal_unknown`]) or estimated with the pose (a
/// camera known by its EXIF, [`LocalizeParams::camera_uncertainty`]): the
/// local map searched again by projection through the estimated camera
/// (the one the weighing chose: its focal length and distortion, and the
/// pyramid level predicted with that focal length), seeded with that
/// camera's inliers; then the nominal camera's pose re-optimised on the
/// grown pairs and the camera estimated (and weighed) again on them
/// ([`evaluate_candidate`]). The first rounds matched through the nominal
/// camera alone, which misses the points its wrong focal length or
/// missing distortion projects off (an EXIF gives no distortion and a
/// rounded focal length); more pairs also pin the focal length, so the
/// weighing decides where it could not. [`LocalizeParams::rematch_rounds`] times at most,
/// fewer when a round finds no new pair.
#[allow(clippy::too_many_arguments)]
fn rematch_with_estimated_camera(
    map: &Map,
    kf_id: KeyFrameId,
    mut fitted: Fitted,
    feats: &features::Features,
    grid: &FeatureGrid,
    view: &ShotView<'_>,
    intr: &Intrinsics,
    params: &LocalizeParams,
    map_error: &MapError,
) -> CandidatePose {
    let radius = params.projection_radius_px.last().copied().unwrap_or(2.5);
    for _ in 0..params.rematch_rounds {
        let cand = &fitted.cand;
        let mut slots = fitted.chosen_slots();
        let est_view = ShotView {
            correction: cand.correction,
            distance_factor: view.distance_factor / cand.correction.focal_scale.max(1e-6),
            ..*view
        };
        let found = search_by_projection(
            map,
            kf_id,
            &est_view,
            &cand.cam_from_world,
            &slots,
            (feats, grid),
            radius,
            params,
        );
        if found.is_empty() {
            break;
        }
        for (i, p) in found {
            slots[i] = Some(p);
        }
        let Some((r, obs, obs_slot, matched)) =
            refit_on_slots(map, feats, &mut slots, fitted.h0_pose, intr, params)
        else {
            break;
        };
        let Some(next) = evaluate_candidate(
            kf_id,
            r.cam_from_world,
            &obs,
            &r.inliers,
            slots,
            intr,
            params,
            map_error,
        ) else {
            break;
        };
        fitted = Fitted {
            cand: next,
            h0_pose: r.cam_from_world,
            obs_slot,
            matched,
        };
    }
    fitted.into_candidate()
}

impl Fitted {
    /// Keypoint -> map point of the chosen camera's inliers (the nominal
    /// camera's refit dropped from the candidate's slots the pairs only
    /// the estimated camera explains).
    fn chosen_slots(&self) -> Vec<Option<PointId>> {
        let mut slots: Vec<Option<PointId>> = vec![None; self.cand.slots.len()];
        for (k, &i) in self.obs_slot.iter().enumerate() {
            if self.cand.obs_inliers.get(k).copied().unwrap_or(false)
                && let (Some(slot), Some(p)) = (slots.get_mut(i), self.matched.get(i))
            {
                *slot = *p;
            }
        }
        slots
    }

    /// The candidate with the chosen camera's inliers as its slots, as its
    /// pose and inlier count are.
    fn into_candidate(self) -> CandidatePose {
        let slots = self.chosen_slots();
        CandidatePose { slots, ..self.cand }
    }
}

/// What [`refit_on_slots`] returns: the report, the observations, the
/// keypoint of each, and the slots as they were fitted (outliers included).
type Refit = (
    crate::optimize::PoseReport,
    Vec<PoseObservation>,
    Vec<usize>,
    Vec<Option<PointId>>,
);

/// Motion-only BA from `start` on the pairs in `slots`; the outliers are
/// then dropped from `slots` so a later round can match their keypoints
/// again.
fn refit_on_slots(
    map: &Map,
    feats: &features::Features,
    slots: &mut [Option<PointId>],
    start: Isometry3<f64>,
    intr: &Intrinsics,
    params: &LocalizeParams,
) -> Option<Refit> {
    let (obs, obs_slot) = observations(map, feats, slots);
    let r = optimize_pose(start, &obs, intr, &params.pose).ok()?;
    let matched = slots.to_vec();
    for (k, &i) in obs_slot.iter().enumerate() {
        if !r.inliers[k] {
            slots[i] = None;
        }
    }
    Some((r, obs, obs_slot, matched))
}

/// The 2D-3D pairs of `slots` (keypoint -> map point) as observations, and
/// the keypoint of each.
pub(super) fn observations(
    map: &Map,
    feats: &features::Features,
    slots: &[Option<PointId>],
) -> (Vec<PoseObservation>, Vec<usize>) {
    let mut obs = Vec::new();
    let mut obs_slot = Vec::new();
    for (i, s) in slots.iter().enumerate() {
        if let Some(p) = s
            && let Some(mp) = map.point(*p)
            && let Some(k) = feats.keypoints.get(i)
        {
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
    (obs, obs_slot)
}

/// A candidate's pose from motion-only BA on `obs` (`inliers` its
/// classification): the camera's hypotheses fitted and weighed, the
/// statistics the gate reads and the sigma.
#[allow(clippy::too_many_arguments)]
pub(super) fn evaluate_candidate(
    kf_id: KeyFrameId,
    cam_from_world: Isometry3<f64>,
    obs: &[PoseObservation],
    inliers: &[bool],
    slots: Vec<Option<PointId>>,
    intr: &Intrinsics,
    params: &LocalizeParams,
    map_error: &MapError,
) -> Option<CandidatePose> {
    // A camera known only by its EXIF: its focal length and distortion
    // are estimated with the pose, the inliers classified again.
    let h0 = fit_hypothesis(
        cam_from_world,
        obs,
        inliers,
        intr,
        &params.camera_uncertainty,
        params,
        map_error,
    );
    let (chosen, sigma) = if params.focal_unknown {
        let u = &params.unknown_focal;
        let wide = IntrinsicsUncertainty {
            focal_rel: u.focal_log_sigma,
            k1: u.k1_sigma,
            k2: u.k2_sigma,
        };
        let h1 = fit_other_camera(cam_from_world, obs, intr, &wide, params, map_error);
        let p0 = same_camera_probability(&h1, &wide, u.same_camera_prior);
        let sigma = mixture_sigma(&h0, &h1, p0);
        let chosen = if p0 >= 0.5 { h0 } else { h1 };
        (chosen, sigma)
    } else {
        let sigma = h0.cov.map(|c| (c.position_sigma(), c.rotation_sigma()));
        (h0, sigma)
    };
    let Hypothesis {
        cam_from_world,
        correction,
        inliers,
        ..
    } = chosen;
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
    let sigma = sigma.map(|(position, rotation)| PoseSigma {
        position,
        position_depth_fraction: position / near_depth,
        rotation_deg: rotation.to_degrees(),
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
        slots,
        correction,
        obs_inliers: inliers,
    })
}
