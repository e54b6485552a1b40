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
    fn parallel_rays_give_none() {
        let c1 = Isometry3::identity();
        let x = Point2::new(0.1, 0.2);
        assert!(triangulate(&c1, &c1, &x, &x).is_none());
    }
}
