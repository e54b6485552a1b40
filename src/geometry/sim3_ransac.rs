//! The similarity between two keyframes from matched map points, by RANSAC
//! over minimal three-point samples (ORB-SLAM's `Sim3Solver`): each sample
//! is aligned in closed form by [`umeyama()`] (Horn's / Umeyama's
//! absolute orientation with scale), and a match is an inlier when both
//! reprojections (keyframe-2 point into image 1 through `S₁₂`, keyframe-1
//! point into image 2 through `S₁₂⁻¹`) fall within `chi2` of the keypoint
//! at its octave's `σ`. The best hypothesis is re-fitted on all its inliers.
//! [`crate::optimize::optimize_sim3`] refines the result.

use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::GeometryError;
use super::umeyama::umeyama;
use crate::lie::Sim3;
use crate::optimize::{Intrinsics, Sim3Match};

/// Tunables of [`sim3_ransac`]. Defaults are ORB-SLAM's loop closing
/// (`SetRansacParameters(0.99, 20, 300)`, 9.21 = χ²₂ at 99 %).
#[derive(Debug, Clone, PartialEq)]
pub struct Sim3RansacParams {
    /// Hypotheses at most.
    pub max_iterations: usize,
    /// Stop early once this confidence of having drawn an all-inlier
    /// sample is reached.
    pub confidence: f64,
    /// Inliers the best hypothesis needs.
    pub min_inliers: usize,
    /// Inlier threshold on the squared reprojection error over `σ²`.
    pub chi2: f64,
}

impl Default for Sim3RansacParams {
    fn default() -> Self {
        Sim3RansacParams {
            max_iterations: 300,
            confidence: 0.99,
            min_inliers: 20,
            chi2: 9.21,
        }
    }
}

/// The result of [`sim3_ransac`].
#[derive(Debug, Clone, PartialEq)]
pub struct Sim3RansacResult {
    /// `S₁₂`: camera-2 coordinates to camera-1 coordinates.
    pub s12: Sim3,
    /// Per match: inlier of `s12`.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub n_inliers: usize,
}

/// Whether match `m` fits `s12` (and its inverse `s21`) in both images.
pub fn sim3_inlier(s12: &Sim3, s21: &Sim3, intr: &Intrinsics, m: &Sim3Match, chi2: f64) -> bool {
    let q1 = s12.transform_point(&m.x2_cam2).coords;
    let q2 = s21.transform_point(&m.x1_cam1).coords;
    if q1.z <= 0.0 || q2.z <= 0.0 {
        return false;
    }
    let e1 = (intr.project(&q1) - m.uv1).norm_squared() * m.inv_sigma2_1;
    let e2 = (intr.project(&q2) - m.uv2).norm_squared() * m.inv_sigma2_2;
    e1 <= chi2 && e2 <= chi2
}

fn count(
    s12: &Sim3,
    matches: &[Sim3Match],
    intr: &Intrinsics,
    chi2: f64,
    mask: &mut [bool],
) -> usize {
    let s21 = s12.inverse();
    let mut n = 0;
    for (m, ok) in matches.iter().zip(mask.iter_mut()) {
        *ok = sim3_inlier(s12, &s21, intr, m, chi2);
        n += usize::from(*ok);
    }
    n
}

/// RANSAC for `S₁₂` (see the module doc); `seed` makes runs repeat.
///
/// Errors: [`GeometryError::NotEnoughPoints`] below 3 matches,
/// [`GeometryError::NonFinite`] for non-finite input,
/// [`GeometryError::TooFewInliers`] when the best hypothesis has fewer
/// than `min_inliers`.
pub fn sim3_ransac(
    matches: &[Sim3Match],
    intr: &Intrinsics,
    params: &Sim3RansacParams,
    seed: u64,
) -> Result<Sim3RansacResult, GeometryError> {
    let n = matches.len();
    if n < 3 {
        return Err(GeometryError::NotEnoughPoints {
            found: n,
            needed: 3,
        });
    }
    let fin = |p: &nalgebra::Point3<f64>| p.iter().all(|v| v.is_finite());
    if !matches.iter().all(|m| {
        fin(&m.x1_cam1)
            && fin(&m.x2_cam2)
            && m.uv1.iter().chain(m.uv2.iter()).all(|v| v.is_finite())
            && m.inv_sigma2_1.is_finite()
            && m.inv_sigma2_2.is_finite()
    }) || !intr.is_valid()
    {
        return Err(GeometryError::NonFinite);
    }
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut pool: Vec<usize> = (0..n).collect();
    let mut mask = vec![false; n];
    let mut best_mask = vec![false; n];
    let mut best: Option<(Sim3, usize)> = None;
    let mut max_iter = params.max_iterations;
    let log_fail = (1.0 - params.confidence).max(1e-300).ln();
    let mut it = 0;
    while it < max_iter {
        it += 1;
        for k in 0..3 {
            let j = rng.random_range(k..n);
            pool.swap(k, j);
        }
        let src = [
            matches[pool[0]].x2_cam2,
            matches[pool[1]].x2_cam2,
            matches[pool[2]].x2_cam2,
        ];
        let dst = [
            matches[pool[0]].x1_cam1,
            matches[pool[1]].x1_cam1,
            matches[pool[2]].x1_cam1,
        ];
        let Ok(s12) = umeyama(&src, &dst, true) else {
            continue;
        };
        if !(s12.scale.is_finite() && s12.scale > 0.0) {
            continue;
        }
        let c = count(&s12, matches, intr, params.chi2, &mut mask);
        if best.is_none_or(|(_, b)| c > b) {
            best = Some((s12, c));
            std::mem::swap(&mut mask, &mut best_mask);
            let w = c as f64 / n as f64;
            let denom = (1.0 - w * w * w).max(1e-300).ln();
            if denom < 0.0 {
                let need = (log_fail / denom).ceil();
                if need.is_finite() && need < max_iter as f64 {
                    max_iter = (need as usize).max(it);
                }
            }
        }
    }
    let Some((mut s12, mut n_best)) = best else {
        return Err(GeometryError::TooFewInliers {
            found: 0,
            needed: params.min_inliers,
        });
    };
    if n_best < params.min_inliers {
        return Err(GeometryError::TooFewInliers {
            found: n_best,
            needed: params.min_inliers,
        });
    }
    // Re-fit on every inlier; keep it when it does not lose inliers.
    let src: Vec<_> = (0..n)
        .filter(|&i| best_mask[i])
        .map(|i| matches[i].x2_cam2)
        .collect();
    let dst: Vec<_> = (0..n)
        .filter(|&i| best_mask[i])
        .map(|i| matches[i].x1_cam1)
        .collect();
    if let Ok(refit) = umeyama(&src, &dst, true) {
        let c = count(&refit, matches, intr, params.chi2, &mut mask);
        if c >= n_best {
            s12 = refit;
            n_best = c;
            std::mem::swap(&mut mask, &mut best_mask);
        }
    }
    Ok(Sim3RansacResult {
        s12,
        inliers: best_mask,
        n_inliers: n_best,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, UnitQuaternion, Vector3};

    fn intr() -> Intrinsics {
        Intrinsics {
            fx: 460.0,
            fy: 460.0,
            cx: 320.0,
            cy: 240.0,
        }
    }

    /// Points seen by camera 1; camera 2 sees the same points through the
    /// inverse of `truth` (both in front of both cameras).
    fn scene(truth: &Sim3, n: usize, outliers: usize, seed: u64) -> Vec<Sim3Match> {
        let k = intr();
        let mut rng = SmallRng::seed_from_u64(seed);
        let s21 = truth.inverse();
        let mut out = Vec::new();
        while out.len() < n + outliers {
            let x1 = Point3::new(
                rng.random_range(-8.0..8.0),
                rng.random_range(-6.0..6.0),
                rng.random_range(10.0..30.0),
            );
            let mut x2 = s21.transform_point(&x1);
            if x2.z <= 1.0 {
                continue;
            }
            let uv1 = k.project(&x1.coords);
            let uv2 = k.project(&x2.coords);
            if out.len() >= n {
                // An outlier: a wrong point, its keypoint where it projects
                // in image 2 only.
                x2 = Point3::new(
                    rng.random_range(-8.0..8.0),
                    rng.random_range(-6.0..6.0),
                    rng.random_range(10.0..30.0),
                );
            }
            out.push(Sim3Match {
                x1_cam1: x1,
                x2_cam2: x2,
                uv1,
                uv2,
                inv_sigma2_1: 1.0,
                inv_sigma2_2: 1.0,
            });
        }
        out
    }

    #[test]
    fn finds_the_similarity_among_outliers() {
        let truth = Sim3::new(
            UnitQuaternion::from_euler_angles(0.05, -0.3, 0.1),
            Vector3::new(1.5, -0.4, 2.0),
            1.35,
        );
        let ms = scene(&truth, 60, 40, 3);
        let r = sim3_ransac(&ms, &intr(), &Sim3RansacParams::default(), 11).unwrap();
        assert!((r.s12.scale - 1.35).abs() < 1e-6, "{:?}", r.s12);
        assert!(r.s12.rotation.angle_to(&truth.rotation) < 1e-6);
        assert!((r.s12.translation - truth.translation).norm() < 1e-5);
        // Every true match is in, every wrong one out.
        assert_eq!(r.n_inliers, 60);
        assert!(r.inliers[..60].iter().all(|b| *b));
        assert!(r.inliers[60..].iter().all(|b| !*b));
    }

    #[test]
    fn refuses_matches_without_a_common_similarity() {
        let truth = Sim3::identity();
        // Only outliers: the best hypothesis explains a handful at most.
        let mut ms = scene(&truth, 0, 80, 5);
        let p = Sim3RansacParams::default();
        assert!(matches!(
            sim3_ransac(&ms, &intr(), &p, 1),
            Err(GeometryError::TooFewInliers { .. })
        ));
        ms.truncate(2);
        assert!(matches!(
            sim3_ransac(&ms, &intr(), &p, 1),
            Err(GeometryError::NotEnoughPoints { .. })
        ));
        ms = scene(&truth, 10, 0, 5);
        ms[3].x1_cam1.x = f64::NAN;
        assert!(matches!(
            sim3_ransac(&ms, &intr(), &p, 1),
            Err(GeometryError::NonFinite)
        ));
    }
}
