//! Linear (DLT) triangulation of one point seen by two cameras.
//!
//! Each view contributes the two rows `x·P₃ - P₁` and `y·P₃ - P₂` of the DLT
//! system `A·X = 0` (Hartley & Zisserman §12.2). With `X = (X, Y, Z, 1)` this
//! is the inhomogeneous linear least-squares problem `A₁₋₃·X = -A₄`, solved
//! through its 3×3 normal equations: no SVD, no allocation. Points at
//! infinity (no parallax) make the system singular and give `None`; callers
//! then apply parallax, cheirality and reprojection checks.

use nalgebra::{Isometry3, Matrix3, Point2, Point3, Vector3};

/// Accumulates the two DLT rows of one view into the normal equations.
#[inline]
fn add_view(
    ata: &mut Matrix3<f64>,
    atb: &mut Vector3<f64>,
    cam_from_world: &Isometry3<f64>,
    x: &Point2<f64>,
) {
    let r = cam_from_world.rotation.to_rotation_matrix();
    let r = r.matrix();
    let t = &cam_from_world.translation.vector;
    // Row for x: x·(r3·X + t3) - (r1·X + t1) = 0
    for (coord, row) in [(x.x, 0usize), (x.y, 1usize)] {
        let a = Vector3::new(
            coord * r[(2, 0)] - r[(row, 0)],
            coord * r[(2, 1)] - r[(row, 1)],
            coord * r[(2, 2)] - r[(row, 2)],
        );
        let b = t[row] - coord * t[2];
        *ata += a * a.transpose();
        *atb += a * b;
    }
}

/// Triangulates the world point seen at normalised coordinates `x1` by
/// `cam1_from_world` and `x2` by `cam2_from_world` (linear DLT).
///
/// Returns `None` when the rays are (nearly) parallel or the result is not
/// finite. No cheirality check is made here.
pub fn triangulate(
    cam1_from_world: &Isometry3<f64>,
    cam2_from_world: &Isometry3<f64>,
    x1: &Point2<f64>,
    x2: &Point2<f64>,
) -> Option<Point3<f64>> {
    let mut ata = Matrix3::zeros();
    let mut atb = Vector3::zeros();
    add_view(&mut ata, &mut atb, cam1_from_world, x1);
    add_view(&mut ata, &mut atb, cam2_from_world, x2);
    let chol = ata.cholesky()?;
    let p = chol.solve(&atb);
    // Conditioning guard: the smallest pivot relative to the largest.
    let l = chol.l_dirty();
    let dmin = l[(0, 0)].min(l[(1, 1)]).min(l[(2, 2)]);
    let dmax = l[(0, 0)].max(l[(1, 1)]).max(l[(2, 2)]);
    if dmin.is_nan() || dmin <= 1e-6 * dmax || !p.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(Point3::from(p))
}

/// Triangulates with the first camera at the origin (`cam1_from_world = I`)
/// and the second at `(r, t)`: the two-view initialiser's case, returned in
/// camera-1 coordinates.
#[inline]
pub fn triangulate_cam1(
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    x1: &Point2<f64>,
    x2: &Point2<f64>,
) -> Option<Point3<f64>> {
    // View 1 (identity): rows (-1, 0, x1) and (0, -1, y1), right side 0.
    let a1 = Vector3::new(-1.0, 0.0, x1.x);
    let a2 = Vector3::new(0.0, -1.0, x1.y);
    let mut ata = a1 * a1.transpose() + a2 * a2.transpose();
    let mut atb = Vector3::zeros();
    for (coord, row) in [(x2.x, 0usize), (x2.y, 1usize)] {
        let a = Vector3::new(
            coord * r[(2, 0)] - r[(row, 0)],
            coord * r[(2, 1)] - r[(row, 1)],
            coord * r[(2, 2)] - r[(row, 2)],
        );
        let b = t[row] - coord * t[2];
        ata += a * a.transpose();
        atb += a * b;
    }
    let chol = ata.cholesky()?;
    let l = chol.l_dirty();
    let dmin = l[(0, 0)].min(l[(1, 1)]).min(l[(2, 2)]);
    let dmax = l[(0, 0)].max(l[(1, 1)]).max(l[(2, 2)]);
    if dmin.is_nan() || dmin <= 1e-6 * dmax {
        return None;
    }
    let p = chol.solve(&atb);
    if !p.iter().all(|v| v.is_finite()) {
        return None;
    }
    Some(Point3::from(p))
}

/// Why [`triangulate_checked`] refused a point.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum TriangulationReject {
    /// The rays are too close to parallel (`cos` of the parallax given).
    LowParallax {
        /// Cosine of the angle between the two viewing rays.
        cos_parallax: f64,
    },
    /// The linear system was singular.
    Singular,
    /// The point is behind camera 1 or 2 (`which` is 1 or 2).
    BehindCamera {
        /// The camera.
        which: u8,
    },
    /// The reprojection chi2 in camera 1 or 2 exceeds the threshold.
    Reprojection {
        /// The camera.
        which: u8,
        /// The chi2 (`e²·inv_sigma2`).
        chi2: f64,
    },
}

/// Thresholds of [`triangulate_checked`] (ORB-SLAM's `CreateNewMapPoints`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TriangulationChecks {
    /// Rays with `cos(parallax)` above this are refused (0.9998 ≈ 1.15°).
    pub max_cos_parallax: f64,
    /// Reprojection chi2 bound in each view (5.991: 95 %, 2 DoF).
    pub max_chi2: f64,
}

impl Default for TriangulationChecks {
    fn default() -> Self {
        Self {
            max_cos_parallax: 0.9998,
            max_chi2: 5.991,
        }
    }
}

/// Triangulates a new map point from two keyframes and applies the
/// parallax, cheirality and reprojection checks. `uv1`, `uv2` are
/// undistorted pixels, `intr` the pinhole intrinsics, `inv_sigma2_*` the
/// keypoints' octave weights. Returns the world point.
#[allow(clippy::too_many_arguments)]
pub fn triangulate_checked(
    cam1_from_world: &Isometry3<f64>,
    cam2_from_world: &Isometry3<f64>,
    uv1: &Point2<f64>,
    uv2: &Point2<f64>,
    intr: &crate::optimize::Intrinsics,
    inv_sigma2_1: f64,
    inv_sigma2_2: f64,
    checks: &TriangulationChecks,
) -> Result<Point3<f64>, TriangulationReject> {
    let x1 = Point2::new((uv1.x - intr.cx) / intr.fx, (uv1.y - intr.cy) / intr.fy);
    let x2 = Point2::new((uv2.x - intr.cx) / intr.fx, (uv2.y - intr.cy) / intr.fy);
    // Rays in world coordinates.
    let r1 = cam1_from_world.rotation.inverse() * Vector3::new(x1.x, x1.y, 1.0);
    let r2 = cam2_from_world.rotation.inverse() * Vector3::new(x2.x, x2.y, 1.0);
    let cos_parallax = r1.dot(&r2) / (r1.norm() * r2.norm());
    if cos_parallax.is_nan() || cos_parallax > checks.max_cos_parallax {
        return Err(TriangulationReject::LowParallax { cos_parallax });
    }
    let pw = triangulate(cam1_from_world, cam2_from_world, &x1, &x2)
        .ok_or(TriangulationReject::Singular)?;
    for (which, cam, uv, w) in [
        (1u8, cam1_from_world, uv1, inv_sigma2_1),
        (2u8, cam2_from_world, uv2, inv_sigma2_2),
    ] {
        let pc = cam.transform_point(&pw).coords;
        if pc.z <= 0.0 {
            return Err(TriangulationReject::BehindCamera { which });
        }
        let chi2 = (intr.project(&pc) - uv).norm_squared() * w;
        if chi2.is_nan() || chi2 > checks.max_chi2 {
            return Err(TriangulationReject::Reprojection { which, chi2 });
        }
    }
    Ok(pw)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn exact_data_triangulates_exactly() {
        let c1 = Isometry3::from_parts(
            Translation3::new(0.1, -0.2, 0.3),
            UnitQuaternion::from_euler_angles(0.05, -0.1, 0.02),
        );
        let c2 = Isometry3::from_parts(
            Translation3::new(-0.5, 0.1, 0.2),
            UnitQuaternion::from_euler_angles(-0.03, 0.12, 0.0),
        );
        let pw = Point3::new(0.4, -0.3, 5.0);
        let proj = |c: &Isometry3<f64>| {
            let p = c * pw;
            Point2::new(p.x / p.z, p.y / p.z)
        };
        let est = triangulate(&c1, &c2, &proj(&c1), &proj(&c2)).unwrap();
        assert!((est - pw).norm() < 1e-9);

        let rel = c2 * c1.inverse();
        let r = rel.rotation.to_rotation_matrix().into_inner();
        let e1 = triangulate_cam1(&r, &rel.translation.vector, &proj(&c1), &proj(&c2)).unwrap();
        assert!((e1 - c1 * pw).norm() < 1e-9);
    }

    #[test]
    fn checked_triangulation_accepts_good_and_names_bad_points() {
        let intr = crate::optimize::Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        };
        let c1 = Isometry3::identity();
        // Camera 2 one metre to the right: cam2_from_world translation -1.
        let c2 = Isometry3::translation(-1.0, 0.0, 0.0);
        let pw = Point3::new(0.3, -0.2, 6.0);
        let uv = |c: &Isometry3<f64>, p: &Point3<f64>| intr.project(&(c * p).coords);
        let checks = TriangulationChecks::default();
        let got = triangulate_checked(
            &c1,
            &c2,
            &uv(&c1, &pw),
            &uv(&c2, &pw),
            &intr,
            1.0,
            1.0,
            &checks,
        )
        .unwrap();
        assert!((got - pw).norm() < 1e-9);
        // Far point: parallax below 1.15 degrees.
        let far = Point3::new(0.3, -0.2, 200.0);
        assert!(matches!(
            triangulate_checked(
                &c1,
                &c2,
                &uv(&c1, &far),
                &uv(&c2, &far),
                &intr,
                1.0,
                1.0,
                &checks
            ),
            Err(TriangulationReject::LowParallax { .. })
        ));
        // Inconsistent vertical coordinate: reprojection error.
        let mut bad = uv(&c2, &pw);
        bad.y += 8.0;
        assert!(matches!(
            triangulate_checked(&c1, &c2, &uv(&c1, &pw), &bad, &intr, 1.0, 1.0, &checks),
            Err(TriangulationReject::Reprojection { .. })
        ));
        // Rays that meet behind the cameras.
        let behind_1 = intr.project(&Vector3::new(0.1, 0.0, 1.0));
        let behind_2 = intr.project(&Vector3::new(0.3, 0.0, 1.0));
        assert!(matches!(
            triangulate_checked(&c1, &c2, &behind_1, &behind_2, &intr, 1.0, 1.0, &checks),
            Err(TriangulationReject::BehindCamera { .. })
        ));
    }

    #[test]
    fn parallel_rays_give_none() {
        let c1 = Isometry3::identity();
        let x = Point2::new(0.1, 0.2);
        assert!(triangulate(&c1, &c1, &x, &x).is_none());
    }
}
