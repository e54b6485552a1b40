//! The linear algebra both DLT fits of the two-view initialisation share:
//! ORB-SLAM's normalisation of a point set, and the null vector of a 9×9
//! `AᵀA` (full eigendecomposition, or inverse iteration for minimal samples).

use nalgebra::{Matrix3, SMatrix, SVector};

/// Similarity that moves the centroid to the origin and sets the mean
/// absolute deviation of each axis to one (ORB-SLAM's normalisation).
pub(super) fn normalize(pts: &[[f64; 2]], out: &mut Vec<[f64; 2]>) -> Matrix3<f64> {
    let n = pts.len() as f64;
    let (mut mx, mut my) = (0.0, 0.0);
    for p in pts {
        mx += p[0];
        my += p[1];
    }
    mx /= n;
    my /= n;
    let (mut dx, mut dy) = (0.0, 0.0);
    for p in pts {
        dx += (p[0] - mx).abs();
        dy += (p[1] - my).abs();
    }
    let sx = if dx > 0.0 { n / dx } else { 1.0 };
    let sy = if dy > 0.0 { n / dy } else { 1.0 };
    out.clear();
    out.extend(pts.iter().map(|p| [(p[0] - mx) * sx, (p[1] - my) * sy]));
    Matrix3::new(sx, 0.0, -mx * sx, 0.0, sy, -my * sy, 0.0, 0.0, 1.0)
}

/// Unit eigenvector of the smallest eigenvalue of a 9×9 symmetric matrix.
pub(super) fn smallest_eigvec9(ata: SMatrix<f64, 9, 9>) -> Option<SVector<f64, 9>> {
    let eig = ata.symmetric_eigen();
    let (mut best, mut val) = (0usize, f64::INFINITY);
    for (i, &v) in eig.eigenvalues.iter().enumerate() {
        if v < val {
            val = v;
            best = i;
        }
    }
    let v = eig.eigenvectors.column(best).into_owned();
    v.iter().all(|x| x.is_finite()).then_some(v)
}

/// Smallest eigenvector of a 9×9 positive semi-definite `AᵀA` built from a
/// minimal sample, by inverse iteration on `AᵀA + εI` (one Cholesky, a few
/// solves: about a microsecond against ten for the full eigensolver). The
/// iteration converges by the ratio `λ₁/λ₂` per step; when two successive
/// iterates still differ (nearly repeated smallest eigenvalues: a degenerate
/// sample) it falls back to the full eigendecomposition.
pub(super) fn null_vector9(ata: SMatrix<f64, 9, 9>) -> Option<SVector<f64, 9>> {
    let tr = ata.trace();
    if !(tr.is_finite() && tr > 0.0) {
        return None;
    }
    let mut shifted = ata;
    for i in 0..9 {
        shifted[(i, i)] += 1e-12 * tr;
    }
    if let Some(ch) = shifted.cholesky() {
        let mut x =
            SVector::<f64, 9>::from([1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2]).normalize();
        for it in 0..6 {
            let mut y = ch.solve(&x);
            let n = y.norm();
            if !(n.is_finite() && n > 0.0) {
                break;
            }
            y /= n;
            let change = (y - x).norm();
            x = y;
            if it >= 1 && change < 1e-7 {
                return Some(x);
            }
        }
    }
    smallest_eigvec9(ata)
}
