//! [`initialize_two_view`]: the checked inputs, the shared 8-point RANSAC
//! of H and F with their least-squares refits, the model choice by
//! `R_H = S_H / (S_H + S_F)`, and the reconstruction of the chosen model
//! (with the homography fallback when F is refused).

use nalgebra::{Matrix3, Point2, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::fundamental::{compute_f21, score_fundamental};
use super::homography::{compute_h21, score_homography};
use super::linear::normalize;
use super::reconstruct::{Fits, Views, reconstruct};
use super::{Model, TwoViewParams, TwoViewResult};
use crate::geometry::GeometryError;

/// The best-scoring model of one kind seen so far in the RANSAC, with its
/// inlier flags.
struct BestModel {
    score: f64,
    model: Option<Matrix3<f64>>,
    inliers: Vec<bool>,
}

impl BestModel {
    fn new(n: usize) -> Self {
        Self {
            score: 0.0,
            model: None,
            inliers: vec![false; n],
        }
    }

    /// Keeps `model` when `score` beats the best; its inlier flags in `cur`
    /// then become the best's (the old best's go back as scratch).
    fn offer(&mut self, score: f64, model: Matrix3<f64>, cur: &mut Vec<bool>) {
        if score > self.score {
            self.score = score;
            self.model = Some(model);
            std::mem::swap(cur, &mut self.inliers);
        }
    }

    /// The indices of the best's inliers, into `out`.
    fn inlier_indices(&self, out: &mut Vec<usize>) {
        out.clear();
        out.extend((0..self.inliers.len()).filter(|&i| self.inliers[i]));
    }
}

/// Initialises a map from two views.
///
/// * `cam_k`: the pinhole intrinsics (no skew assumed in the reprojection).
/// * `kp1`, `kp2`: undistorted keypoint pixels of the two frames.
/// * `matches`: `(index in kp1, index in kp2)` pairs.
/// * `seed`: RANSAC seed; equal seeds give equal results.
///
/// See the module documentation for the algorithm and the refusals.
pub fn initialize_two_view(
    cam_k: &Matrix3<f64>,
    kp1: &[Point2<f64>],
    kp2: &[Point2<f64>],
    matches: &[(usize, usize)],
    params: &TwoViewParams,
    seed: u64,
) -> Result<TwoViewResult, GeometryError> {
    let n = matches.len();
    if n < 8 {
        return Err(GeometryError::NotEnoughPoints {
            found: n,
            needed: 8,
        });
    }
    let mut px1 = Vec::with_capacity(n);
    let mut px2 = Vec::with_capacity(n);
    for &(i, j) in matches {
        let a = kp1.get(i).ok_or(GeometryError::IndexOutOfRange {
            index: i,
            len: kp1.len(),
        })?;
        let b = kp2.get(j).ok_or(GeometryError::IndexOutOfRange {
            index: j,
            len: kp2.len(),
        })?;
        if !(a.x.is_finite() && a.y.is_finite() && b.x.is_finite() && b.y.is_finite()) {
            return Err(GeometryError::NonFinite);
        }
        px1.push([a.x, a.y]);
        px2.push([b.x, b.y]);
    }
    let k_inv = cam_k.try_inverse().ok_or(GeometryError::Degenerate {
        what: "singular intrinsics matrix",
    })?;

    // Normalised coordinates for the RANSAC fits.
    let mut pn1 = Vec::with_capacity(n);
    let mut pn2 = Vec::with_capacity(n);
    let t1 = normalize(&px1, &mut pn1);
    let t2 = normalize(&px2, &mut pn2);
    let t2_inv = t2.try_inverse().ok_or(GeometryError::Degenerate {
        what: "normalisation",
    })?;
    let t2_t = t2.transpose();

    let inv_sigma2 = 1.0 / (params.sigma_px * params.sigma_px);
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut pool: Vec<usize> = (0..n).collect();
    let mut cur = vec![false; n];
    let mut best_h = BestModel::new(n);
    let mut best_f = BestModel::new(n);
    let score_h = |h21: &Matrix3<f64>, cur: &mut Vec<bool>| {
        let h12 = h21.try_inverse()?;
        Some(score_homography(
            h21,
            &h12,
            &px1,
            &px2,
            inv_sigma2,
            params.chi2_two_dof,
            cur,
        ))
    };
    let score_f = |f21: &Matrix3<f64>, cur: &mut Vec<bool>| {
        score_fundamental(
            f21,
            &px1,
            &px2,
            inv_sigma2,
            params.chi2_one_dof,
            params.chi2_two_dof,
            cur,
        )
    };
    for _ in 0..params.ransac_iterations {
        for k in 0..8 {
            let j = rng.random_range(k..n);
            pool.swap(k, j);
        }
        let set = &pool[..8];
        if let Some(h21) = compute_h21(&pn1, &pn2, set, true).map(|hn| t2_inv * hn * t1)
            && let Some(s) = score_h(&h21, &mut cur)
        {
            best_h.offer(s, h21, &mut cur);
        }
        if let Some(f21) = compute_f21(&pn1, &pn2, set, true).map(|fn_| t2_t * fn_ * t1) {
            let s = score_f(&f21, &mut cur);
            best_f.offer(s, f21, &mut cur);
        }
    }
    // Least-squares refit of each model on its consensus set (Hartley &
    // Zisserman's final step, which ORB-SLAM omits): the 8-point minimal
    // fits are noisy with pixel-level noise. Kept only when the score rises.
    let mut idx_buf: Vec<usize> = Vec::with_capacity(n);
    for _ in 0..params.refit_rounds {
        best_h.inlier_indices(&mut idx_buf);
        let h_fit = (idx_buf.len() >= 8)
            .then(|| compute_h21(&pn1, &pn2, &idx_buf, false))
            .flatten()
            .map(|hn| t2_inv * hn * t1);
        if let Some(h21) = h_fit
            && let Some(s) = score_h(&h21, &mut cur)
        {
            best_h.offer(s, h21, &mut cur);
        }
        best_f.inlier_indices(&mut idx_buf);
        let f_fit = (idx_buf.len() >= 8)
            .then(|| compute_f21(&pn1, &pn2, &idx_buf, false))
            .flatten()
            .map(|fn_| t2_t * fn_ * t1);
        if let Some(f21) = f_fit {
            let s = score_f(&f21, &mut cur);
            best_f.offer(s, f21, &mut cur);
        }
    }
    let (best_sh, best_sf) = (best_h.score, best_f.score);
    let (best_h_in, best_f_in) = (best_h.inliers, best_f.inliers);
    let (best_h, best_f) = (best_h.model, best_f.model);
    if best_sh + best_sf <= 0.0 {
        return Err(GeometryError::TooFewInliers {
            found: 0,
            needed: params.min_triangulated,
        });
    }
    let rh = best_sh / (best_sh + best_sf);
    let model = if rh > params.homography_ratio_threshold {
        Model::Homography
    } else {
        Model::Fundamental
    };
    let xn1: Vec<Point2<f64>> = px1
        .iter()
        .map(|p| {
            let v = k_inv * Vector3::new(p[0], p[1], 1.0);
            Point2::new(v.x / v.z, v.y / v.z)
        })
        .collect();
    let xn2: Vec<Point2<f64>> = px2
        .iter()
        .map(|p| {
            let v = k_inv * Vector3::new(p[0], p[1], 1.0);
            Point2::new(v.x / v.z, v.y / v.z)
        })
        .collect();
    let fits = Fits {
        h: best_h,
        f: best_f,
        h_inliers: &best_h_in,
        f_inliers: &best_f_in,
        score_h: best_sh,
        score_f: best_sf,
    };
    let views = Views {
        k: cam_k,
        k_inv: &k_inv,
        px1: &px1,
        px2: &px2,
        xn1: &xn1,
        xn2: &xn2,
    };
    match reconstruct(model, &fits, &views, params) {
        // A plane with pixel-level noise in both images can score below the
        // ratio threshold and fall to F, which a plane cannot support: when
        // F fails, the homography gets its chance, under all its own checks.
        Err(e) if model == Model::Fundamental && params.homography_fallback => {
            reconstruct(Model::Homography, &fits, &views, params).map_err(|_| e)
        }
        other => other,
    }
}
