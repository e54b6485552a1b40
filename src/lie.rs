//! SO(3)/SE(3)/Sim(3), the rigid and similarity transforms that
//! [`crate::geometry`] and [`crate::optimize`] both build on (it imports
//! neither): the skew matrix, the SE(3) exponential used for
//! left-perturbation updates, quaternion renormalisation, and the [`Sim3`]
//! type.
//!
//! Tangent vectors of SE(3) are ordered `δ = [υ; ω]` (translation first,
//! then rotation). An update is a *left* perturbation:
//! `T ← Exp(δ) · T`, so for `p' = T·p` the derivative at `δ = 0` is
//! `∂p'/∂δ = [ I₃ | -[p']ₓ ]`.

use nalgebra::{Isometry3, Matrix3, Point3, Translation3, UnitQuaternion, Vector3, Vector6};

/// The unit quaternion of a (nearly) orthonormal rotation matrix. nalgebra's
/// `from_rotation_matrix` assumes an exact rotation and returns a quaternion
/// off unit length otherwise (seen at 3 % after a noisy solve), which then
/// makes quaternion and matrix forms of the same pose disagree; this
/// renormalises.
pub fn quaternion_from_matrix(r: &Matrix3<f64>) -> UnitQuaternion<f64> {
    let q = UnitQuaternion::from_rotation_matrix(&nalgebra::Rotation3::from_matrix_unchecked(*r));
    UnitQuaternion::new_normalize(q.into_inner())
}

/// The pose with its rotation quaternion renormalised: solvers that build a
/// quaternion from a slightly non-orthonormal matrix leave it off unit
/// length, and the error grows through compositions.
pub fn renormalized(pose: Isometry3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(
        pose.translation,
        UnitQuaternion::new_normalize(*pose.rotation.quaternion()),
    )
}

/// The skew-symmetric matrix `[v]ₓ` with `[v]ₓ·w = v × w`.
#[inline]
pub fn skew(v: &Vector3<f64>) -> Matrix3<f64> {
    Matrix3::new(0.0, -v.z, v.y, v.z, 0.0, -v.x, -v.y, v.x, 0.0)
}

/// The SE(3) exponential of `δ = [υ; ω]`: rotation `Exp(ω)` and translation
/// `V(ω)·υ` with the left Jacobian `V` of SO(3).
pub fn se3_exp(delta: &Vector6<f64>) -> Isometry3<f64> {
    let v = Vector3::new(delta[0], delta[1], delta[2]);
    let w = Vector3::new(delta[3], delta[4], delta[5]);
    let theta2 = w.norm_squared();
    let wx = skew(&w);
    let (b, c) = if theta2 < 1e-10 {
        // Taylor: (1-cos)/θ² ≈ 1/2 - θ²/24, (θ - sin)/θ³ ≈ 1/6 - θ²/120
        (0.5 - theta2 / 24.0, 1.0 / 6.0 - theta2 / 120.0)
    } else {
        let theta = theta2.sqrt();
        (
            (1.0 - theta.cos()) / theta2,
            (theta - theta.sin()) / (theta2 * theta),
        )
    };
    let vmat = Matrix3::identity() + wx * b + wx * wx * c;
    Isometry3::from_parts(
        Translation3::from(vmat * v),
        UnitQuaternion::from_scaled_axis(w),
    )
}

/// A similarity transform `p ↦ s·R·p + t` (Sim(3)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3 {
    /// Rotation `R`.
    pub rotation: UnitQuaternion<f64>,
    /// Translation `t`.
    pub translation: Vector3<f64>,
    /// Scale `s` (> 0).
    pub scale: f64,
}

impl Default for Sim3 {
    fn default() -> Self {
        Self::identity()
    }
}

impl Sim3 {
    /// The identity similarity.
    pub fn identity() -> Self {
        Self {
            rotation: UnitQuaternion::identity(),
            translation: Vector3::zeros(),
            scale: 1.0,
        }
    }

    /// Builds a similarity from its parts.
    pub fn new(rotation: UnitQuaternion<f64>, translation: Vector3<f64>, scale: f64) -> Self {
        Self {
            rotation,
            translation,
            scale,
        }
    }

    /// A rigid transform seen as a similarity of scale 1.
    pub fn from_isometry(iso: &Isometry3<f64>) -> Self {
        Self::new(iso.rotation, iso.translation.vector, 1.0)
    }

    /// The rigid part `(R, t)`, dropping the scale (not `(R, t/s)`).
    pub fn to_isometry(&self) -> Isometry3<f64> {
        Isometry3::from_parts(Translation3::from(self.translation), self.rotation)
    }

    /// Applies the similarity to a point: `s·R·p + t`.
    #[inline]
    pub fn transform_point(&self, p: &Point3<f64>) -> Point3<f64> {
        Point3::from(self.rotation * p.coords * self.scale + self.translation)
    }

    /// Applies the linear part to a vector: `s·R·v`.
    #[inline]
    pub fn transform_vector(&self, v: &Vector3<f64>) -> Vector3<f64> {
        self.rotation * v * self.scale
    }

    /// A camera pose moved by this similarity: the orientation rotated, the
    /// centre transformed (the scale does not apply to the orientation).
    pub fn transform_pose(&self, world_from_cam: &Isometry3<f64>) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(
                self.transform_vector(&world_from_cam.translation.vector) + self.translation,
            ),
            self.rotation * world_from_cam.rotation,
        )
    }

    /// The inverse similarity `p ↦ (1/s)·Rᵀ·(p - t)`.
    pub fn inverse(&self) -> Self {
        let rinv = self.rotation.inverse();
        let sinv = 1.0 / self.scale;
        Self::new(rinv, -(rinv * self.translation) * sinv, sinv)
    }

    /// Composition `self ∘ other` (apply `other` first).
    pub fn compose(&self, other: &Sim3) -> Self {
        Self::new(
            self.rotation * other.rotation,
            self.rotation * other.translation * self.scale + self.translation,
            self.scale * other.scale,
        )
    }

    /// The 3×3 linear part `s·R`.
    pub fn linear(&self) -> Matrix3<f64> {
        self.rotation.to_rotation_matrix().into_inner() * self.scale
    }
}

impl std::ops::Mul for Sim3 {
    type Output = Sim3;
    fn mul(self, rhs: Sim3) -> Sim3 {
        self.compose(&rhs)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn se3_exp_matches_first_order_and_rotation() {
        let d = Vector6::new(0.1, -0.2, 0.3, 0.01, 0.02, -0.03);
        let t = se3_exp(&d);
        let axis = Vector3::new(0.01, 0.02, -0.03);
        assert!((t.rotation.scaled_axis() - axis).norm() < 1e-12);
        // For small ω translation ≈ υ + ω×υ/2
        let v = Vector3::new(0.1, -0.2, 0.3);
        let approx = v + axis.cross(&v) * 0.5;
        assert!((t.translation.vector - approx).norm() < 1e-4);
        // Pure translation
        let t0 = se3_exp(&Vector6::new(1.0, 2.0, 3.0, 0.0, 0.0, 0.0));
        assert!((t0.translation.vector - Vector3::new(1.0, 2.0, 3.0)).norm() < 1e-12);
        // exp(δ)·exp(-δ) = I
        let back = se3_exp(&d) * se3_exp(&(-d));
        assert!(back.translation.vector.norm() < 1e-12 && back.rotation.angle() < 1e-12);
    }

    #[test]
    fn sim3_inverse_and_compose() {
        let s = Sim3::new(
            UnitQuaternion::from_euler_angles(0.3, -0.2, 1.1),
            Vector3::new(1.0, -2.0, 0.5),
            2.5,
        );
        let p = Point3::new(0.3, 0.7, -1.2);
        let q = s.transform_point(&p);
        let back = s.inverse().transform_point(&q);
        assert!((back - p).norm() < 1e-12);
        let id = s.compose(&s.inverse());
        assert!((id.scale - 1.0).abs() < 1e-12 && id.translation.norm() < 1e-12);
        let s2 = Sim3::new(
            UnitQuaternion::from_euler_angles(-0.1, 0.4, 0.2),
            Vector3::new(0.0, 1.0, 2.0),
            0.5,
        );
        let lhs = (s * s2).transform_point(&p);
        let rhs = s.transform_point(&s2.transform_point(&p));
        assert!((lhs - rhs).norm() < 1e-12);
    }
}
