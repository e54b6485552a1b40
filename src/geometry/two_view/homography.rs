//! The homography `x2 ~ H·x1`: its normalised DLT fit, its symmetric
//! transfer score, its Faugeras & Lustman decomposition into motion
//! hypotheses (used by the two-view initialisation), and [`find_homography`],
//! a robust homography between two point sets on the same machinery.

use nalgebra::{Matrix3, Point2, SMatrix, SVector, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::linear::{normalize, null_vector9, smallest_eigvec9};
use crate::geometry::GeometryError;

/// Normalised DLT homography `x2 ~ H·x1` from ≥ 4 normalised pairs.
pub(super) fn compute_h21(
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    idx: &[usize],
    minimal: bool,
) -> Option<Matrix3<f64>> {
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for &i in idx {
        let (u1, v1) = (p1[i][0], p1[i][1]);
        let (u2, v2) = (p2[i][0], p2[i][1]);
        let r1 = SVector::<f64, 9>::from([0.0, 0.0, 0.0, -u1, -v1, -1.0, v2 * u1, v2 * v1, v2]);
        let r2 = SVector::<f64, 9>::from([u1, v1, 1.0, 0.0, 0.0, 0.0, -u2 * u1, -u2 * v1, -u2]);
        ata += r1 * r1.transpose() + r2 * r2.transpose();
    }
    let h = if minimal {
        null_vector9(ata)?
    } else {
        smallest_eigvec9(ata)?
    };
    Some(Matrix3::new(
        h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8],
    ))
}

/// Symmetric transfer score of a homography (ORB-SLAM `CheckHomography`).
pub(super) fn score_homography(
    h21: &Matrix3<f64>,
    h12: &Matrix3<f64>,
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    inv_sigma2: f64,
    th: f64,
    inliers: &mut [bool],
) -> f64 {
    let mut score = 0.0;
    for (i, (a, b)) in p1.iter().zip(p2).enumerate() {
        let (u1, v1, u2, v2) = (a[0], a[1], b[0], b[1]);
        let mut ok = true;
        // x1 -> image 2
        let w = h21[(2, 0)] * u1 + h21[(2, 1)] * v1 + h21[(2, 2)];
        let iw = 1.0 / w;
        let u = (h21[(0, 0)] * u1 + h21[(0, 1)] * v1 + h21[(0, 2)]) * iw;
        let v = (h21[(1, 0)] * u1 + h21[(1, 1)] * v1 + h21[(1, 2)]) * iw;
        let chi = ((u - u2).powi(2) + (v - v2).powi(2)) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th - chi;
        } else {
            ok = false;
        }
        // x2 -> image 1
        let w = h12[(2, 0)] * u2 + h12[(2, 1)] * v2 + h12[(2, 2)];
        let iw = 1.0 / w;
        let u = (h12[(0, 0)] * u2 + h12[(0, 1)] * v2 + h12[(0, 2)]) * iw;
        let v = (h12[(1, 0)] * u2 + h12[(1, 1)] * v2 + h12[(1, 2)]) * iw;
        let chi = ((u - u1).powi(2) + (v - v1).powi(2)) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th - chi;
        } else {
            ok = false;
        }
        inliers[i] = ok;
    }
    score
}

/// The 8 motion hypotheses of a calibrated homography `A = K⁻¹·H·K`
/// (Faugeras & Lustman 1988, cases d' = ±d₂). Returns `None` when the
/// singular values coincide (no translation is observable).
pub fn decompose_h(a: &Matrix3<f64>) -> Option<Vec<(Matrix3<f64>, Vector3<f64>)>> {
    let svd = a.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let (d1, d2, d3) = (
        svd.singular_values[0],
        svd.singular_values[1],
        svd.singular_values[2],
    );
    if d1 / d2 < 1.00001 || d2 / d3 < 1.00001 {
        return None;
    }
    let s = u.determinant() * vt.determinant();
    let (d1s, d2s, d3s) = (d1 * d1, d2 * d2, d3 * d3);
    let aux1 = ((d1s - d2s) / (d1s - d3s)).sqrt();
    let aux3 = ((d2s - d3s) / (d1s - d3s)).sqrt();
    let x1 = [aux1, aux1, -aux1, -aux1];
    let x3 = [aux3, -aux3, aux3, -aux3];
    let mut out = Vec::with_capacity(8);
    // Case d' = d2.
    let aux_st = ((d1s - d2s) * (d2s - d3s)).sqrt() / ((d1 + d3) * d2);
    let ct = (d2s + d1 * d3) / ((d1 + d3) * d2);
    let st = [aux_st, -aux_st, -aux_st, aux_st];
    for i in 0..4 {
        let rp = Matrix3::new(ct, 0.0, -st[i], 0.0, 1.0, 0.0, st[i], 0.0, ct);
        let r = u * rp * vt * s;
        let tp = Vector3::new(x1[i], 0.0, -x3[i]) * (d1 - d3);
        let t = (u * tp).normalize();
        out.push((r, t));
    }
    // Case d' = -d2.
    let aux_sp = ((d1s - d2s) * (d2s - d3s)).sqrt() / ((d1 - d3) * d2);
    let cp = (d1 * d3 - d2s) / ((d1 - d3) * d2);
    let sp = [aux_sp, -aux_sp, -aux_sp, aux_sp];
    for i in 0..4 {
        let rp = Matrix3::new(cp, 0.0, sp[i], 0.0, -1.0, 0.0, sp[i], 0.0, -cp);
        let r = u * rp * vt * s;
        let tp = Vector3::new(x1[i], 0.0, x3[i]) * (d1 + d3);
        let t = (u * tp).normalize();
        out.push((r, t));
    }
    out.iter()
        .all(|(r, t)| r.iter().all(|v| v.is_finite()) && t.iter().all(|v| v.is_finite()))
        .then_some(out)
}

/// Tunables of [`find_homography`]. Defaults follow the two-view
/// initialiser's homography test (σ = 1 px, χ² 5.991 per direction).
#[derive(Debug, Clone, PartialEq)]
pub struct HomographyParams {
    /// RANSAC iterations (minimal samples of four pairs).
    pub ransac_iterations: usize,
    /// Standard deviation of the point positions, pixels.
    pub sigma_px: f64,
    /// Chi-square threshold (two degrees of freedom) of the symmetric
    /// transfer error of one direction.
    pub chi2_two_dof: f64,
    /// Least-squares refits on the consensus set (kept when the score rises).
    pub refit_rounds: usize,
    /// Fewest inliers accepted.
    pub min_inliers: usize,
}

impl Default for HomographyParams {
    fn default() -> Self {
        Self {
            ransac_iterations: 500,
            sigma_px: 1.0,
            chi2_two_dof: 5.991,
            refit_rounds: 3,
            min_inliers: 12,
        }
    }
}

/// A robust homography between two point sets.
#[derive(Debug, Clone, PartialEq)]
pub struct HomographyFit {
    /// `x2 ~ h21 · x1` (pixels to pixels).
    pub h21: Matrix3<f64>,
    /// Which pairs agree with it (both transfer directions).
    pub inliers: Vec<bool>,
    /// How many do.
    pub n_inliers: usize,
}

/// A homography `x2 ~ H·x1` from point pairs `(p1[i], p2[i])`, by the
/// two-view initialiser's machinery: seeded RANSAC over minimal 4-pair
/// samples (normalised DLT), symmetric-transfer scoring (ORB-SLAM's
/// `CheckHomography`), then least-squares refits on the consensus set.
pub fn find_homography(
    p1: &[Point2<f64>],
    p2: &[Point2<f64>],
    params: &HomographyParams,
    seed: u64,
) -> Result<HomographyFit, GeometryError> {
    let n = p1.len();
    if n != p2.len() {
        return Err(GeometryError::LengthMismatch {
            left: n,
            right: p2.len(),
        });
    }
    let needed = params.min_inliers.max(4);
    if n < needed {
        return Err(GeometryError::NotEnoughPoints { found: n, needed });
    }
    if p1
        .iter()
        .chain(p2)
        .any(|p| !(p.x.is_finite() && p.y.is_finite()))
    {
        return Err(GeometryError::NonFinite);
    }
    let px1: Vec<[f64; 2]> = p1.iter().map(|p| [p.x, p.y]).collect();
    let px2: Vec<[f64; 2]> = p2.iter().map(|p| [p.x, p.y]).collect();
    let mut pn1 = Vec::with_capacity(n);
    let mut pn2 = Vec::with_capacity(n);
    let t1 = normalize(&px1, &mut pn1);
    let t2 = normalize(&px2, &mut pn2);
    let t2_inv = t2.try_inverse().ok_or(GeometryError::Degenerate {
        what: "normalisation",
    })?;
    let inv_sigma2 = 1.0 / (params.sigma_px * params.sigma_px);
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut pool: Vec<usize> = (0..n).collect();
    let mut cur = vec![false; n];
    let mut best_in = vec![false; n];
    let mut best_score = 0.0f64;
    let mut best_h = None;
    let mut consider = |h21: Matrix3<f64>, cur: &mut Vec<bool>, best_in: &mut Vec<bool>| {
        if let Some(h12) = h21.try_inverse() {
            let s = score_homography(&h21, &h12, &px1, &px2, inv_sigma2, params.chi2_two_dof, cur);
            if s > best_score {
                best_score = s;
                best_h = Some(h21);
                std::mem::swap(cur, best_in);
            }
        }
    };
    for _ in 0..params.ransac_iterations {
        for k in 0..4 {
            let j = rng.random_range(k..n);
            pool.swap(k, j);
        }
        if let Some(hn) = compute_h21(&pn1, &pn2, &pool[..4], true) {
            consider(t2_inv * hn * t1, &mut cur, &mut best_in);
        }
    }
    let mut idx: Vec<usize> = Vec::with_capacity(n);
    for _ in 0..params.refit_rounds {
        idx.clear();
        idx.extend((0..n).filter(|&i| best_in[i]));
        if idx.len() < 4 {
            break;
        }
        if let Some(hn) = compute_h21(&pn1, &pn2, &idx, false) {
            consider(t2_inv * hn * t1, &mut cur, &mut best_in);
        }
    }
    let n_inliers = best_in.iter().filter(|&&b| b).count();
    match best_h {
        Some(h21) if n_inliers >= needed => Ok(HomographyFit {
            h21,
            inliers: best_in,
            n_inliers,
        }),
        _ => Err(GeometryError::TooFewInliers {
            found: n_inliers,
            needed,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn faugeras_decomposition_contains_the_true_motion() {
        // Plane n·X = d in camera 1, motion (R, t): H = R + t·nᵀ/d.
        let r = UnitQuaternion::from_euler_angles(0.05, -0.1, 0.03)
            .to_rotation_matrix()
            .into_inner();
        let t = Vector3::new(0.3, -0.1, 0.05);
        let nrm = Vector3::new(0.1, -0.2, 1.0).normalize();
        let d = 4.0;
        let a = r + t * nrm.transpose() / d;
        let hyps = decompose_h(&(a * 1.7)).unwrap();
        assert_eq!(hyps.len(), 8);
        let tn = t.normalize();
        let found = hyps
            .iter()
            .any(|(rh, th)| (rh - r).norm() < 1e-9 && (th - tn).norm() < 1e-9);
        assert!(found, "{hyps:?}");
    }
    #[test]
    fn find_homography_recovers_a_known_one_among_outliers() {
        use rand::{Rng, SeedableRng, rngs::SmallRng};
        let h = Matrix3::new(1.05, 0.03, -12.0, -0.02, 0.98, 7.5, 1.5e-4, -8e-5, 1.0);
        let mut rng = SmallRng::seed_from_u64(9);
        let (mut p1, mut p2) = (Vec::new(), Vec::new());
        for i in 0..300 {
            let a = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
            let v = h * Vector3::new(a.x, a.y, 1.0);
            let mut b = Point2::new(v.x / v.z, v.y / v.z);
            if i % 10 < 3 {
                // 30 % outliers anywhere in the image
                b = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
            } else {
                b.x += rng.random_range(-0.5..0.5);
                b.y += rng.random_range(-0.5..0.5);
            }
            p1.push(a);
            p2.push(b);
        }
        let fit = find_homography(&p1, &p2, &HomographyParams::default(), 1).unwrap();
        assert!(
            fit.n_inliers >= 200 && fit.n_inliers <= 215,
            "{}",
            fit.n_inliers
        );
        let est = fit.h21 / fit.h21[(2, 2)];
        for c in [(0.0, 0.0), (639.0, 0.0), (639.0, 479.0), (0.0, 479.0)] {
            let t = h * Vector3::new(c.0, c.1, 1.0);
            let e = est * Vector3::new(c.0, c.1, 1.0);
            let d = (t.xy() / t.z - e.xy() / e.z).norm();
            assert!(d < 0.3, "corner {c:?} off by {d} px");
        }
        assert!(matches!(
            find_homography(&p1[..5], &p2[..5], &HomographyParams::default(), 1),
            Err(GeometryError::NotEnoughPoints { .. })
        ));
        assert!(matches!(
            find_homography(&p1, &p2[..10], &HomographyParams::default(), 1),
            Err(GeometryError::LengthMismatch { .. })
        ));
        let mut bad = p1.clone();
        bad[3].x = f64::NAN;
        assert_eq!(
            find_homography(&bad, &p2, &HomographyParams::default(), 1),
            Err(GeometryError::NonFinite)
        );
    }
}
