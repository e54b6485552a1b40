//! The fundamental matrix `x2ᵀ·F·x1 = 0` (its normalised 8-point fit with
//! rank 2 enforced, its symmetric point-to-epipolar-line score) and the
//! decomposition of the essential matrix `E = Kᵀ·F·K` into its four motion
//! hypotheses.

use nalgebra::{Matrix3, SMatrix, SVector, Vector3};

use super::linear::{null_vector9, smallest_eigvec9};

/// Normalised 8-point fundamental matrix `x2ᵀ·F·x1 = 0`, rank 2 enforced.
pub(super) fn compute_f21(
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    idx: &[usize],
    minimal: bool,
) -> Option<Matrix3<f64>> {
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for &i in idx {
        let (u1, v1) = (p1[i][0], p1[i][1]);
        let (u2, v2) = (p2[i][0], p2[i][1]);
        let r = SVector::<f64, 9>::from([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, 1.0]);
        ata += r * r.transpose();
    }
    let f = if minimal {
        null_vector9(ata)?
    } else {
        smallest_eigvec9(ata)?
    };
    let fpre = Matrix3::new(f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8]);
    let svd = fpre.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut s = svd.singular_values;
    s[2] = 0.0;
    Some(u * Matrix3::from_diagonal(&s) * vt)
}

/// Symmetric point-to-epipolar-line score of F (ORB-SLAM `CheckFundamental`).
pub(super) fn score_fundamental(
    f21: &Matrix3<f64>,
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    inv_sigma2: f64,
    th: f64,
    th_score: f64,
    inliers: &mut [bool],
) -> f64 {
    let mut score = 0.0;
    for (i, (a, b)) in p1.iter().zip(p2).enumerate() {
        let (u1, v1, u2, v2) = (a[0], a[1], b[0], b[1]);
        let mut ok = true;
        // Line in image 2: l2 = F·x1
        let la = f21[(0, 0)] * u1 + f21[(0, 1)] * v1 + f21[(0, 2)];
        let lb = f21[(1, 0)] * u1 + f21[(1, 1)] * v1 + f21[(1, 2)];
        let lc = f21[(2, 0)] * u1 + f21[(2, 1)] * v1 + f21[(2, 2)];
        let num = la * u2 + lb * v2 + lc;
        let chi = num * num / (la * la + lb * lb) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th_score - chi;
        } else {
            ok = false;
        }
        // Line in image 1: l1ᵀ = x2ᵀ·F
        let la = f21[(0, 0)] * u2 + f21[(1, 0)] * v2 + f21[(2, 0)];
        let lb = f21[(0, 1)] * u2 + f21[(1, 1)] * v2 + f21[(2, 1)];
        let lc = f21[(0, 2)] * u2 + f21[(1, 2)] * v2 + f21[(2, 2)];
        let num = la * u1 + lb * v1 + lc;
        let chi = num * num / (la * la + lb * lb) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th_score - chi;
        } else {
            ok = false;
        }
        inliers[i] = ok;
    }
    score
}

/// The 4 motion hypotheses of `E` (two rotations, ± translation).
pub(super) fn decompose_e(e: &Matrix3<f64>) -> Option<[(Matrix3<f64>, Vector3<f64>); 4]> {
    let svd = e.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let t = u.column(2).into_owned();
    let tn = t.norm();
    if tn.is_nan() || tn <= 0.0 {
        return None;
    }
    let t = t / tn;
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let mut r1 = u * w * vt;
    if r1.determinant() < 0.0 {
        r1 = -r1;
    }
    let mut r2 = u * w.transpose() * vt;
    if r2.determinant() < 0.0 {
        r2 = -r2;
    }
    Some([(r1, t), (r2, t), (r1, -t), (r2, -t)])
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn essential_decomposition_contains_the_true_motion() {
        let r = UnitQuaternion::from_euler_angles(-0.2, 0.1, 0.3)
            .to_rotation_matrix()
            .into_inner();
        let t = Vector3::new(-0.4, 0.2, 0.9).normalize();
        let e = crate::lie::skew(&t) * r;
        let hyps = decompose_e(&(e * -3.0)).unwrap();
        assert!(
            hyps.iter()
                .any(|(rh, th)| (rh - r).norm() < 1e-9 && (th - t).norm() < 1e-9)
        );
    }
}
