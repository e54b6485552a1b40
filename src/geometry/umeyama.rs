//! Umeyama's closed-form least-squares alignment of two point sets
//! (S. Umeyama, "Least-squares estimation of transformation parameters
//! between two point patterns", PAMI 1991): rotation from the SVD of the
//! cross-covariance with the reflection fix, scale from the singular values.

use nalgebra::{Matrix3, Point3, Vector3};

use super::{GeometryError, all_finite3};
use crate::lie::Sim3;

/// Finds the similarity (or, with `with_scale == false`, the rigid motion)
/// minimising `Σ |dst_i - (s·R·src_i + t)|²`.
///
/// Needs at least three non-collinear pairs. Errors: [`GeometryError::LengthMismatch`],
/// [`GeometryError::NotEnoughPoints`], [`GeometryError::NonFinite`],
/// [`GeometryError::Collapsed`] (a set without spread), [`GeometryError::Degenerate`]
/// (collinear points: rotation about the line is unobservable).
pub fn umeyama(
    src: &[Point3<f64>],
    dst: &[Point3<f64>],
    with_scale: bool,
) -> Result<Sim3, GeometryError> {
    if src.len() != dst.len() {
        return Err(GeometryError::LengthMismatch {
            left: src.len(),
            right: dst.len(),
        });
    }
    let n = src.len();
    if n < 3 {
        return Err(GeometryError::NotEnoughPoints {
            found: n,
            needed: 3,
        });
    }
    if !all_finite3(src) || !all_finite3(dst) {
        return Err(GeometryError::NonFinite);
    }
    let inv_n = 1.0 / n as f64;
    let mu_s: Vector3<f64> = src.iter().map(|p| p.coords).sum::<Vector3<f64>>() * inv_n;
    let mu_d: Vector3<f64> = dst.iter().map(|p| p.coords).sum::<Vector3<f64>>() * inv_n;
    let mut cov = Matrix3::zeros();
    let mut var_s = 0.0;
    let mut var_d = 0.0;
    for (s, d) in src.iter().zip(dst) {
        let a = s.coords - mu_s;
        let b = d.coords - mu_d;
        cov += b * a.transpose();
        var_s += a.norm_squared();
        var_d += b.norm_squared();
    }
    cov *= inv_n;
    var_s *= inv_n;
    var_d *= inv_n;
    let scale_ref = mu_s.norm().max(mu_d.norm()).max(1.0);
    if var_s <= 1e-20 * scale_ref * scale_ref {
        return Err(GeometryError::Collapsed {
            side: "source",
            spread: var_s,
        });
    }
    if var_d <= 1e-20 * scale_ref * scale_ref {
        return Err(GeometryError::Collapsed {
            side: "destination",
            spread: var_d,
        });
    }
    let svd = cov.svd(true, true);
    let (Some(u), Some(v_t)) = (svd.u, svd.v_t) else {
        return Err(GeometryError::Degenerate {
            what: "SVD of the cross-covariance",
        });
    };
    // nalgebra's SVD sorts singular values in decreasing order.
    let d = svd.singular_values;
    if d[1] <= 1e-12 * d[0].max(f64::MIN_POSITIVE) {
        return Err(GeometryError::Degenerate {
            what: "collinear point sets",
        });
    }
    let mut s_diag = Vector3::new(1.0, 1.0, 1.0);
    if (u.determinant() * v_t.determinant()) < 0.0 {
        s_diag[2] = -1.0;
    }
    let r = u * Matrix3::from_diagonal(&s_diag) * v_t;
    let scale = if with_scale {
        d.dot(&s_diag) / var_s
    } else {
        1.0
    };
    let rotation = crate::lie::quaternion_from_matrix(&r);
    let translation = mu_d - rotation * mu_s * scale;
    Ok(Sim3::new(rotation, translation, scale))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    #[test]
    fn recovers_known_similarity_and_rigid_motion() {
        let mut rng = SmallRng::seed_from_u64(7);
        let truth = Sim3::new(
            UnitQuaternion::from_euler_angles(0.4, -1.0, 2.2),
            Vector3::new(3.0, -1.0, 0.25),
            1.7,
        );
        let src: Vec<Point3<f64>> = (0..50)
            .map(|_| {
                Point3::new(
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-2.0..2.0),
                )
            })
            .collect();
        let dst: Vec<Point3<f64>> = src.iter().map(|p| truth.transform_point(p)).collect();
        let est = umeyama(&src, &dst, true).unwrap();
        assert!((est.scale - 1.7).abs() < 1e-10);
        assert!(est.rotation.angle_to(&truth.rotation) < 1e-10);
        assert!((est.translation - truth.translation).norm() < 1e-10);

        let rigid = Sim3 {
            scale: 1.0,
            ..truth
        };
        let dst2: Vec<Point3<f64>> = src.iter().map(|p| rigid.transform_point(p)).collect();
        let est2 = umeyama(&src, &dst2, false).unwrap();
        assert_eq!(est2.scale, 1.0);
        assert!(est2.rotation.angle_to(&truth.rotation) < 1e-10);
        assert!((est2.translation - truth.translation).norm() < 1e-10);
    }

    #[test]
    fn refuses_bad_input() {
        let p = [Point3::new(0.0, 0.0, 0.0), Point3::new(1.0, 0.0, 0.0)];
        assert!(matches!(
            umeyama(&p, &p, true),
            Err(GeometryError::NotEnoughPoints {
                found: 2,
                needed: 3
            })
        ));
        let same = [Point3::new(1.0, 1.0, 1.0); 4];
        assert!(matches!(
            umeyama(&same, &same, true),
            Err(GeometryError::Collapsed { .. })
        ));
        let line: Vec<Point3<f64>> = (0..5).map(|i| Point3::new(i as f64, 0.0, 0.0)).collect();
        assert!(matches!(
            umeyama(&line, &line, true),
            Err(GeometryError::Degenerate { .. })
        ));
        assert!(matches!(
            umeyama(&line, &line[..4], true),
            Err(GeometryError::LengthMismatch { .. })
        ));
    }
}
