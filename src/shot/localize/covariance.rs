//! The pose's uncertainty: a hypothesis' covariance (the camera's
//! uncertain intrinsics marginalised), the mixture of two hypotheses, and
//! the sigma reported with the map's own error.

use nalgebra::Isometry3;

use super::outcome::PoseSigma;
use super::params::{LocalizeParams, MapSigma};
use crate::optimize::{
    Intrinsics, IntrinsicsCorrection, IntrinsicsUncertainty, PoseObservation, pose_covariance,
    refine_pose_and_intrinsics,
};
use crate::slam::Map;

/// The map's own error for one localisation: [`MapSigma`] with its
/// absolute part in the map's units.
#[derive(Debug, Clone, Copy)]
pub(super) struct MapError {
    pub(super) sigma: MapSigma,
    /// The map's absolute position error, map units
    /// ([`MapSigma::map_depth_fraction`] of its keyframes' median depth).
    pub(super) absolute: f64,
    /// The factor `sigma` was scaled by: the map's reprojection noise over
    /// [`MapSigma::reference_noise_px`], at least 1.
    pub(super) noise_factor: f64,
    /// The map's reprojection noise ([`Map::reprojection_noise_px`]),
    /// level-0 pixels; None for a map with too few observations.
    pub(super) noise_px: Option<f64>,
}

impl MapError {
    /// `sigma` on `map`: scaled by the map's reprojection noise over the
    /// reference's ([`MapSigma::reference_noise_px`], never below 1); the
    /// median over the keyframes of each one's median scene depth sets the
    /// absolute part (0 for a map without any).
    pub(super) fn of(map: &Map, sigma: &MapSigma) -> MapError {
        let depths: Vec<f64> = map
            .keyframes()
            .filter_map(|k| map.median_depth(k.id))
            .filter(|d| d.is_finite() && *d > 0.0)
            .collect();
        let depth = crate::stats::quantile(&depths, 0.5).unwrap_or(0.0);
        let noise = map.reprojection_noise_px();
        let factor = noise
            .map(|n| n / sigma.reference_noise_px)
            .filter(|f| f.is_finite())
            .unwrap_or(1.0)
            .max(1.0);
        tracing::debug!(noise_px = ?noise, factor, "the map's reprojection noise");
        let scaled = MapSigma {
            depth_fraction: sigma.depth_fraction * factor,
            rotation_deg: sigma.rotation_deg * factor,
            map_depth_fraction: sigma.map_depth_fraction * factor,
            ..*sigma
        };
        MapError {
            sigma: scaled,
            absolute: scaled.map_depth_fraction * depth,
            noise_factor: factor,
            noise_px: noise,
        }
    }

    /// The focal length's extra error (log) for a photo whose inliers lie
    /// at `median_depth` ([`MapSigma::focal_rel`]).
    pub(super) fn focal_rel(&self, median_depth: f64) -> f64 {
        self.sigma.focal_rel(self.absolute, median_depth)
    }
}

/// Median depth of the inliers of `obs` in front of the camera at
/// `cam_from_world` (NaN without any).
pub(super) fn inlier_median_depth(
    cam_from_world: &Isometry3<f64>,
    obs: &[PoseObservation],
    inliers: &[bool],
) -> f64 {
    let depths: Vec<f64> = obs
        .iter()
        .zip(inliers)
        .filter(|(_, a)| **a)
        .map(|(o, _)| (cam_from_world * o.p_world).z)
        .filter(|z| *z > 0.0)
        .collect();
    crate::stats::quantile(&depths, 0.5).unwrap_or(f64::NAN)
}

/// How far beyond the flown views a pose sees its points, and what that
/// does to the map's error seen from there ([`beyond_views`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct BeyondViews {
    /// Per point, the smallest angle at the point between the ray to this
    /// camera and the rays to the keyframes that observe it; the median
    /// over the points, degrees (0 without any).
    pub(super) deg: f64,
    /// The factor the map's error grows by, seen from this camera rather
    /// than from the edge of the flown views ([`view_error_factor`]): the
    /// median over the points, at least 1 (1 without any).
    pub(super) factor: f64,
}

/// The smallest span, radians, taken for a point's observations in
/// [`view_error_factor`] (a point seen along nearly one ray has no
/// meaningful depth; its factor is bounded by this).
const MIN_SPAN_RAD: f64 = 1.0_f64.to_radians();

/// How much larger a triangulated point's position error looks from a
/// camera `beyond` radians round from the nearest of its observing rays,
/// which span `span` radians, than from the edge of that span. Across the
/// rays its error is `s`, along them (its depth) `s / tan(span / 2)`; seen
/// at an angle `phi` from the span's middle the error across the new ray is
/// `s·sqrt(cos²phi + sin²phi / tan²(span/2))`, with `phi = span/2 + beyond`
/// (at most 90 degrees). Normalised by its value at the edge (`beyond` =
/// 0), where the map's constants were calibrated; never below 1. A point
/// seen over a wide span barely changes; one seen over a narrow span from
/// far round shows its depth error.
pub(super) fn view_error_factor(span: f64, beyond: f64) -> f64 {
    let half = (span.max(MIN_SPAN_RAD) / 2.0).min(std::f64::consts::FRAC_PI_2 - 1e-6);
    let phi = (half + beyond.max(0.0)).min(std::f64::consts::FRAC_PI_2);
    let seen = |a: f64| a.cos().powi(2) + a.sin().powi(2) / half.tan().powi(2);
    (seen(phi) / seen(half)).sqrt().max(1.0)
}

/// How far beyond the flown views the pose at `cam_from_world` sees its
/// inlier points (`slots`), and the factor the map's error grows by there:
/// per point, the smallest angle at the point between the ray to this
/// camera and the rays to the keyframes that observe it, and the span of
/// those rays (the largest angle between two of them) through
/// [`view_error_factor`]; medians over the points.
pub(super) fn beyond_views(
    map: &Map,
    cam_from_world: &Isometry3<f64>,
    slots: &[Option<crate::slam::PointId>],
) -> BeyondViews {
    let center = cam_from_world.inverse().translation.vector;
    let mut angles = Vec::new();
    let mut factors = Vec::new();
    let mut rays: Vec<nalgebra::Vector3<f64>> = Vec::new();
    for id in slots.iter().flatten() {
        let Some(mp) = map.point(*id) else { continue };
        let Some(to_cam) = (center - mp.position.coords).try_normalize(1e-12) else {
            continue;
        };
        rays.clear();
        rays.extend(mp.observations.iter().filter_map(|(kf, _)| {
            (map.keyframe(*kf)?.center() - mp.position.coords).try_normalize(1e-12)
        }));
        let angle = |a: &nalgebra::Vector3<f64>, b: &nalgebra::Vector3<f64>| {
            a.dot(b).clamp(-1.0, 1.0).acos()
        };
        let Some(beyond) = rays
            .iter()
            .map(|r| angle(&to_cam, r))
            .min_by(f64::total_cmp)
        else {
            continue;
        };
        let mut span: f64 = 0.0;
        for (i, a) in rays.iter().enumerate() {
            for b in &rays[i + 1..] {
                span = span.max(angle(a, b));
            }
        }
        angles.push(beyond);
        factors.push(view_error_factor(span, beyond));
    }
    BeyondViews {
        deg: crate::stats::quantile(&angles, 0.5).map_or(0.0, f64::to_degrees),
        factor: crate::stats::quantile(&factors, 0.5).map_or(1.0, |f| f.max(1.0)),
    }
}

/// One explanation of a candidate's matches: the pose with the intrinsics'
/// corrections estimated with it, its inliers and its covariance.
pub(super) struct Hypothesis {
    pub(super) cam_from_world: Isometry3<f64>,
    pub(super) correction: IntrinsicsCorrection,
    pub(super) inliers: Vec<bool>,
    pub(super) cov: Option<crate::optimize::PoseCovariance>,
}

/// Fits the pose from motion-only BA together with the intrinsics that
/// `uncertain` leaves open (none: the pose as it is), classifies the
/// inliers again and takes the covariance with those intrinsics
/// marginalised (an estimated focal length with the map's error,
/// [`MapError::focal_rel`], too).
pub(super) fn fit_hypothesis(
    cam_from_world: Isometry3<f64>,
    obs: &[PoseObservation],
    inliers: &[bool],
    intr: &Intrinsics,
    uncertain: &IntrinsicsUncertainty,
    params: &LocalizeParams,
    map_error: &MapError,
) -> Hypothesis {
    let (cam_from_world, correction, inliers) = if *uncertain == IntrinsicsUncertainty::default() {
        (
            cam_from_world,
            IntrinsicsCorrection::default(),
            inliers.to_vec(),
        )
    } else {
        let (pose, corr) =
            refine_pose_and_intrinsics(cam_from_world, obs, inliers, intr, uncertain);
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
    let cov = pose_covariance(
        &cam_from_world,
        obs,
        &inliers,
        intr,
        params.pose.chi2_threshold,
        None,
        uncertain,
        &correction,
    )
    .map(|c| {
        c.with_focal_error(map_error.focal_rel(inlier_median_depth(&cam_from_world, obs, &inliers)))
    });
    Hypothesis {
        cam_from_world,
        correction,
        inliers,
        cov,
    }
}

/// The RMS position and rotation (radians) errors of the two hypotheses'
/// mixture (`p0`, `1 − p0`) about the likelier one's pose: each one's
/// covariance, plus the other's squared offset weighted by its
/// probability. None when a hypothesis with weight has no covariance.
pub(super) fn mixture_sigma(h0: &Hypothesis, h1: &Hypothesis, p0: f64) -> Option<(f64, f64)> {
    let p1 = 1.0 - p0;
    // Each hypothesis' own second moments, weighted.
    let own = |h: &Hypothesis, p: f64| -> Option<(f64, f64)> {
        if p <= 0.0 {
            return Some((0.0, 0.0));
        }
        let c = h.cov?;
        Some((
            p * c.center.trace().max(0.0),
            p * c.cam_from_world.fixed_view::<3, 3>(3, 3).trace().max(0.0),
        ))
    };
    let (a_pos, a_rot) = own(h0, p0)?;
    let (b_pos, b_rot) = own(h1, p1)?;
    // The other hypothesis' offset from the reported one.
    let w0 = h0.cam_from_world.inverse();
    let w1 = h1.cam_from_world.inverse();
    let d_pos = (w0.translation.vector - w1.translation.vector).norm_squared();
    let d_rot = w0.rotation.angle_to(&w1.rotation).powi(2);
    let other = p0.min(p1);
    Some((
        (a_pos + b_pos + other * d_pos).sqrt(),
        (a_rot + b_rot + other * d_rot).sqrt(),
    ))
}

/// The sigma reported for the final pose: its covariance's (`pose`) and
/// the map's own error in quadrature, the latter the larger of the floor
/// of `map_error` and the RMS `spread` of the agreeing candidates around
/// the chosen pose (position as a fraction of `median_depth`, rotation in
/// degrees), and for the position the map's absolute error too; the floor
/// and the absolute error times `view_factor` (how much larger the map's
/// error looks from this camera than from the flown views,
/// [`BeyondViews::factor`]); the position also as a fraction of `near`,
/// the distance to the nearest scene content.
pub(super) fn reported_sigma(
    pose: &PoseSigma,
    spread: Option<(f64, f64)>,
    map_error: &MapError,
    median_depth: f64,
    near: f64,
    view_factor: f64,
) -> PoseSigma {
    let map_sigma = &map_error.sigma;
    let f = view_factor.max(1.0);
    // The agreeing candidates' spread already shows the map's error from
    // this camera (each candidate's local map seen from here): not scaled.
    let (floor_pos, floor_rot) = (f * map_sigma.depth_fraction, f * map_sigma.rotation_deg);
    let (map_pos, map_rot) = match spread {
        Some((pos, rot)) => (pos.max(floor_pos), rot.max(floor_rot)),
        None => (floor_pos, floor_rot),
    };
    let position = pose
        .position
        .hypot(map_pos * median_depth)
        .hypot(f * map_error.absolute);
    PoseSigma {
        position,
        position_depth_fraction: position / near.max(1e-12),
        rotation_deg: pose.rotation_deg.hypot(map_rot),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::slam::map::testing::map_with;

    #[test]
    fn beyond_views_is_the_angle_to_the_nearest_keyframe_ray() {
        // Keyframes along x from 0 to 0.3 at z = 0 looking down +z, all
        // seeing 50 points along x at z = 2.
        let map = map_with(4, 50);
        let slots: Vec<Option<crate::slam::PointId>> = map
            .keyframes()
            .next()
            .map(|k| k.points.clone())
            .unwrap_or_default();
        assert_eq!(slots.iter().flatten().count(), 50);
        // At a keyframe: 0.
        let at_kf = Isometry3::translation(-0.2, 0.0, 0.0);
        let at = beyond_views(&map, &at_kf, &slots);
        assert!(at.deg < 1e-6 && (at.factor - 1.0).abs() < 1e-9, "{at:?}");
        // Between keyframes: 0 too (rays on both sides, the nearest is
        // under 1.5 deg away).
        let between = Isometry3::translation(-0.15, 0.0, 0.0);
        assert!(beyond_views(&map, &between, &slots).deg < 1.5);
        // 1 m beyond the first keyframe: for the median point (x about
        // 0.245) atan((0.245 + 1)/2) - atan(0.245/2) = 24.9 deg.
        let beyond = Isometry3::translation(1.0, 0.0, 0.0);
        let got = beyond_views(&map, &beyond, &slots);
        assert!((got.deg - 24.9).abs() < 0.5, "{got:?}");
        // The median point's rays span atan(0.245/2) - atan((0.245 -
        // 0.3)/2) = 8.55 deg: its depth error is 13.4x its error across,
        // and seen 24.9 deg further round the error grows by 4.7.
        let expected = view_error_factor(8.56_f64.to_radians(), 24.9_f64.to_radians());
        assert!((expected - 4.67).abs() < 0.01, "{expected}");
        assert!((got.factor / expected - 1.0).abs() < 0.15, "{got:?}");
        // No points: 0, and no growth.
        let none = beyond_views(&map, &beyond, &[]);
        assert_eq!((none.deg, none.factor), (0.0, 1.0));
    }

    #[test]
    fn the_view_error_factor_grows_with_the_angle_beyond_over_the_span() {
        let d = f64::to_radians;
        // At the edge of the views: 1.
        assert!((view_error_factor(d(19.0), 0.0) - 1.0).abs() < 1e-12);
        // A point seen over 19 deg, from 10 and 20 deg further round:
        // sqrt((cos²phi + sin²phi / tan²(9.5°)) / (2 cos²(9.5°))).
        let expect = |beyond: f64| {
            let (h, phi) = (d(9.5), d(9.5 + beyond));
            ((phi.cos().powi(2) + phi.sin().powi(2) / h.tan().powi(2)) / (2.0 * h.cos().powi(2)))
                .sqrt()
        };
        for beyond in [10.0, 20.0] {
            let got = view_error_factor(d(19.0), d(beyond));
            assert!((got - expect(beyond)).abs() < 1e-12, "{got}");
        }
        assert!((expect(10.0) - 1.58).abs() < 0.01 && (expect(20.0) - 2.20).abs() < 0.01);
        // A wide span barely grows; a narrow one grows fast; a degenerate
        // span is bounded, and the factor never falls below 1.
        assert!(view_error_factor(d(90.0), d(20.0)) < 1.01);
        assert!(view_error_factor(d(5.0), d(20.0)) > 5.0);
        assert!(view_error_factor(0.0, d(90.0)).is_finite());
        assert!(view_error_factor(d(40.0), -1.0) >= 1.0);
    }
}
