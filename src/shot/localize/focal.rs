//! A photo whose camera is only assumed: the assumed camera (the map
//! camera scaled), another camera fitted with the pose (focal length and
//! distortion), and the probability that the assumed one is right
//! ([`super::UnknownFocal`]).

use nalgebra::Isometry3;

use super::covariance::{Hypothesis, MapError, inlier_median_depth};
use super::params::LocalizeParams;
use crate::camera::Camera;
use crate::optimize::{
    Intrinsics, IntrinsicsCorrection, IntrinsicsUncertainty, PoseObservation, optimize_pose,
    pose_covariance, refine_pose_and_intrinsics_from,
};
use crate::shot::ShotError;

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

/// Focal scales the search for another camera's focal length starts from
/// (with the pose re-optimised at each): the joint fit from the assumed
/// focal length alone stays where the pose has already traded distance
/// for focal length.
const FOCAL_STARTS: [f64; 7] = [0.6, 0.72, 0.85, 1.0, 1.18, 1.4, 1.66];

/// H1 of [`UnknownFocal`]: pose, focal length and distortion fitted from
/// several focal lengths ([`FOCAL_STARTS`]: the pose by motion-only BA with
/// the scaled camera on all of `obs`, then all together with the priors
/// `wide`), the start whose robust cost (chi2 capped at the inlier
/// threshold, plus the prior) is least kept.
pub(super) fn fit_other_camera(
    cam_from_world: Isometry3<f64>,
    obs: &[PoseObservation],
    intr: &Intrinsics,
    wide: &IntrinsicsUncertainty,
    params: &LocalizeParams,
    map_error: &MapError,
) -> Hypothesis {
    let th = params.pose.chi2_threshold;
    let mut best: Option<(f64, Isometry3<f64>, IntrinsicsCorrection, Vec<bool>)> = None;
    for s in FOCAL_STARTS {
        let scaled = Intrinsics {
            fx: intr.fx * s,
            fy: intr.fy * s,
            ..*intr
        };
        let Ok(r) = optimize_pose(cam_from_world, obs, &scaled, &params.pose) else {
            continue;
        };
        let start = IntrinsicsCorrection {
            focal_scale: s,
            ..IntrinsicsCorrection::default()
        };
        let (pose, corr) =
            refine_pose_and_intrinsics_from(r.cam_from_world, start, obs, &r.inliers, intr, wide);
        let mut cost = 0.0;
        let inliers: Vec<bool> = obs
            .iter()
            .map(|o| {
                let chi2 = corr
                    .project(intr, &(pose * o.p_world).coords)
                    .map_or(f64::INFINITY, |uv| {
                        (uv - o.uv).norm_squared() * o.inv_sigma2
                    });
                cost += chi2.min(th);
                chi2 <= th
            })
            .collect();
        cost += (corr.focal_scale.ln() / wide.focal_rel).powi(2)
            + (corr.k1 / wide.k1).powi(2)
            + (corr.k2 / wide.k2).powi(2);
        if cost.is_finite() && best.as_ref().is_none_or(|b| cost < b.0) {
            best = Some((cost, pose, corr, inliers));
        }
    }
    let Some((_, pose, corr, inliers)) = best else {
        return Hypothesis {
            cam_from_world,
            correction: IntrinsicsCorrection::default(),
            inliers: vec![false; obs.len()],
            cov: None,
        };
    };
    // The covariance at the fit, with the intrinsics marginalised.
    let cov = pose_covariance(&pose, obs, &inliers, intr, th, None, wide, &corr).map(|c| {
        c.with_focal_error(map_error.focal_rel(inlier_median_depth(&pose, obs, &inliers)))
    });
    Hypothesis {
        cam_from_world: pose,
        correction: corr,
        inliers,
        cov,
    }
}

/// H0's posterior probability ([`UnknownFocal`]): `prior·B / (prior·B + 1 −
/// prior)` with the Savage-Dickey Bayes factor `B = p(θ = 0 | data, H1) /
/// p(θ = 0 | H1)`, θ the intrinsics' corrections (focal scale's log, `k1`,
/// `k2`) with H1's Gaussian prior `wide` and its Laplace posterior. 0 when
/// H1 has no covariance (the data say nothing usable about H0 then).
pub(super) fn same_camera_probability(
    h1: &Hypothesis,
    wide: &IntrinsicsUncertainty,
    prior: f64,
) -> f64 {
    let Some(cov) = h1.cov else {
        return 0.0;
    };
    let mu = [
        h1.correction.focal_scale.ln(),
        h1.correction.k1,
        h1.correction.k2,
    ];
    let prior_sd = [wide.focal_rel, wide.k1, wide.k2];
    // Only the intrinsics H1 frees (a zero prior sigma holds one fixed).
    let free: Vec<usize> = (0..3)
        .filter(|&k| prior_sd[k] > 0.0 && prior_sd[k].is_finite())
        .collect();
    if free.is_empty() {
        return prior.clamp(0.0, 1.0);
    }
    let n = free.len();
    let post = nalgebra::DMatrix::from_fn(n, n, |a, b| cov.intrinsics[(free[a], free[b])]);
    let mu = nalgebra::DVector::from_fn(n, |a, _| mu[free[a]]);
    let Some(chol) = post.cholesky() else {
        return 0.0;
    };
    // ln N(0; μ, Σ_post) − ln N(0; 0, Σ_prior), the 2π terms cancel.
    let maha = mu.dot(&chol.solve(&mu));
    let log_det_post = chol
        .l()
        .diagonal()
        .iter()
        .map(|d| 2.0 * d.ln())
        .sum::<f64>();
    let log_det_prior = free.iter().map(|&k| 2.0 * prior_sd[k].ln()).sum::<f64>();
    let log_b = -0.5 * maha - 0.5 * log_det_post + 0.5 * log_det_prior;
    let prior = prior.clamp(0.0, 1.0);
    if prior <= 0.0 {
        return 0.0;
    }
    // p0 = 1 / (1 + (1 − prior) / (prior·B)), in logs.
    let log_odds = log_b + prior.ln() - (1.0 - prior).max(1e-300).ln();
    if !log_odds.is_finite() {
        return if log_odds > 0.0 { 1.0 } else { 0.0 };
    }
    1.0 / (1.0 + (-log_odds).exp())
}

#[cfg(test)]
mod tests {
    use nalgebra::{Point2, Point3};

    use super::*;
    use crate::shot::localize::UnknownFocal;
    use crate::shot::localize::covariance::{MapError, fit_hypothesis, mixture_sigma};

    /// Observations of random points (x, y in ±half the depth's span, z in
    /// `depths`) by a camera at the origin whose focal length is
    /// `focal_scale` times `intr`'s, with 0.5 px of noise; deterministic.
    fn synthetic_obs(
        intr: &Intrinsics,
        focal_scale: f64,
        depths: (f64, f64),
        seed: u64,
    ) -> Vec<PoseObservation> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand::rngs::SmallRng::seed_from_u64(seed);
        let mut obs = Vec::new();
        while obs.len() < 150 {
            let z = rng.random_range(depths.0..depths.1);
            let x = rng.random_range(-0.55..0.55) * z;
            let y = rng.random_range(-0.4..0.4) * z;
            let u = intr.cx + focal_scale * intr.fx * x / z + rng.random_range(-0.5..0.5);
            let v = intr.cy + focal_scale * intr.fy * y / z + rng.random_range(-0.5..0.5);
            if !(0.0..640.0).contains(&u) || !(0.0..480.0).contains(&v) {
                continue;
            }
            obs.push(PoseObservation {
                p_world: Point3::new(x, y, z),
                uv: Point2::new(u, v),
                inv_sigma2: 1.0,
            });
        }
        obs
    }

    /// H0 and H1 of [`UnknownFocal`] on `obs`: H0's probability, the
    /// reported camera centre and the mixture's position sigma.
    fn weigh(intr: &Intrinsics, obs: &[PoseObservation]) -> (f64, Point3<f64>, f64, f64) {
        let params = LocalizeParams::default();
        // No absolute part: a map of these points alone.
        let map_error = MapError {
            sigma: params.map_sigma,
            absolute: 0.0,
            noise_factor: 1.0,
            noise_px: None,
        };
        let start = Isometry3::translation(0.05, -0.03, 0.1);
        let r = optimize_pose(start, obs, intr, &params.pose).unwrap_or_else(|e| panic!("{e}"));
        let h0 = fit_hypothesis(
            r.cam_from_world,
            obs,
            &r.inliers,
            intr,
            &IntrinsicsUncertainty::default(),
            &params,
            &map_error,
        );
        let u = UnknownFocal::default();
        let wide = IntrinsicsUncertainty {
            focal_rel: u.focal_log_sigma,
            k1: u.k1_sigma,
            k2: u.k2_sigma,
        };
        let h1 = fit_other_camera(r.cam_from_world, obs, intr, &wide, &params, &map_error);
        let p0 = same_camera_probability(&h1, &wide, u.same_camera_prior);
        let (pos_sigma, _) = mixture_sigma(&h0, &h1, p0).unwrap_or((f64::INFINITY, 0.0));
        let chosen = if p0 >= 0.5 { &h0 } else { &h1 };
        let centre = Point3::from(chosen.cam_from_world.inverse().translation.vector);
        (p0, centre, pos_sigma, h1.correction.focal_scale)
    }

    #[test]
    fn an_unknown_focal_length_is_found_or_widens_the_sigma() {
        let intr = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 319.5,
            cy: 239.5,
        };
        // A deep scene (4 to 12 m) tells the focal length.
        for seed in 1..4 {
            // The map camera's own frame resized: H0, tight.
            let (p0, c, sigma, _) = weigh(&intr, &synthetic_obs(&intr, 1.0, (4.0, 12.0), seed));
            assert!(p0 > 0.9, "seed {seed}: same camera p0 {p0}");
            assert!(c.coords.norm() < 0.02, "seed {seed}: centre {c}");
            assert!(sigma < 0.02 * 4.0, "seed {seed}: sigma {sigma}");
            // Another camera, 17 % shorter focal length: H1 finds it.
            let (p0, c, _, f) = weigh(&intr, &synthetic_obs(&intr, 0.83, (4.0, 12.0), seed));
            assert!(p0 < 0.01, "seed {seed}: other camera p0 {p0}");
            assert!((f - 0.83).abs() < 0.02, "seed {seed}: focal scale {f}");
            assert!(c.coords.norm() < 0.05, "seed {seed}: centre {c}");
        }
        // A flat far scene (a 2 cm slab at 50 m) cannot tell the focal
        // length from the distance: whichever pose is reported, the sigma
        // covers its error (or is over the gate's 2 %, which refuses).
        for seed in 1..4 {
            let (p0, c, sigma, f) = weigh(&intr, &synthetic_obs(&intr, 0.83, (49.99, 50.01), seed));
            let err = c.coords.norm();
            println!(
                "flat scene, seed {seed}: p0 {p0:.3}, focal scale {f:.3}, error {err:.2} m, sigma {sigma:.2} m"
            );
            assert!(
                err < 2.0 * sigma || sigma > 0.02 * 49.99,
                "seed {seed}: error {err:.2} m with sigma {sigma:.2} m"
            );
        }
    }
}
