//! A rolling shutter in the reprojection error: each image row is exposed
//! at its own time, so a camera that moves during the readout sees every
//! row from its own pose (issue 35, point 3; the constant-velocity model of
//! the rolling-shutter extensions of ORB-SLAM and of Kalibr's camera).
//!
//! Row `y` is exposed `τ(y) = (y - centre_row) · line_s` seconds after the
//! frame's time (the centre row's, which is the pose being optimised). Over
//! one readout (tens of milliseconds) the camera's motion is its velocity:
//! `T(t + τ) = Exp(τ·ξ)·T(t)` with the twist `ξ = [ρ; φ]` in the camera's
//! own frame, so a world point's camera coordinates at its row are, to first
//! order in `τ` (the second order is `τ²|φ|²/2` of the depth: 10⁻⁵ at 1 rad/s
//! and a 12 ms half readout),
//!
//! `p_row = p + τ·(φ × p + ρ)`,
//!
//! and a left step `δ` of the pose moves it by `(I + τ·[φ]ₓ)·[I | -[p]ₓ]·δ`.
//! The twist is held fixed while a frame's pose is optimised (it comes from
//! the motion between frames). In bundle adjustment a keyframe's twist is
//! taken from its neighbours in time ([`PoseShutter::between`]) as the
//! poses stand at each step, so it scales with the map: a twist held fixed
//! while the map's scale is free would let the adjustment shrink the map
//! to strengthen the translation's share, and the next adjustment shrink
//! it again. The row is the observation's undistorted one:
//! the distortion moves it a few pixels at the image's edges, a few
//! hundredths of a millisecond of readout.

use nalgebra::{Isometry3, Matrix3, Vector3};

use crate::lie::skew;

/// A camera's motion during one frame's rolling-shutter readout.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RowMotion {
    /// Seconds from one row's exposure to the next (`readout / (height - 1)`).
    pub line_s: f64,
    /// The row exposed at the frame's time (`(height - 1) / 2`: the
    /// frame's time is its centre row's).
    pub centre_row: f64,
    /// `ρ`: how a fixed point's camera coordinates move per second by the
    /// camera's translation (`-R·ċ`, map units per second).
    pub linear: Vector3<f64>,
    /// `φ`: the camera's angular velocity in its own frame, rad/s.
    pub angular: Vector3<f64>,
}

impl RowMotion {
    /// The motion of a camera of `height` rows read out in `readout_s`,
    /// moving with `linear` and `angular` (see the fields). `None` for a
    /// global shutter (`readout_s` 0), a single row, or a non-finite value.
    pub fn new(
        readout_s: f64,
        height: u32,
        linear: Vector3<f64>,
        angular: Vector3<f64>,
    ) -> Option<RowMotion> {
        let finite = linear.iter().chain(angular.iter()).all(|v| v.is_finite());
        if !(readout_s > 0.0 && readout_s.is_finite()) || height < 2 || !finite {
            return None;
        }
        let rows = f64::from(height - 1);
        Some(RowMotion {
            line_s: readout_s / rows,
            centre_row: rows / 2.0,
            linear,
            angular,
        })
    }

    /// The motion of a camera that moved by `velocity` (`cam_from_world`
    /// of one frame times `world_from_cam` of the frame `dt` seconds
    /// before: a constant-velocity model) per second; `None` as
    /// [`RowMotion::new`], or for a `dt` that is not positive.
    pub fn from_velocity(
        readout_s: f64,
        height: u32,
        velocity: &Isometry3<f64>,
        dt: f64,
    ) -> Option<RowMotion> {
        if dt.is_nan() || dt <= 0.0 {
            return None;
        }
        RowMotion::new(
            readout_s,
            height,
            velocity.translation.vector / dt,
            velocity.rotation.scaled_axis() / dt,
        )
    }

    /// Seconds from the frame's time to the exposure of `row`.
    #[inline]
    pub fn time_of_row(&self, row: f64) -> f64 {
        (row - self.centre_row) * self.line_s
    }

    /// The camera coordinates `pc` (at the frame's time) of a point seen at
    /// `row`, moved to that row's exposure.
    #[inline]
    pub fn at_row(&self, row: f64, pc: &Vector3<f64>) -> Vector3<f64> {
        let tau = self.time_of_row(row);
        pc + (self.angular.cross(pc) + self.linear) * tau
    }

    /// `∂p_row/∂p` at `row` (`I + τ·[φ]ₓ`).
    #[inline]
    pub fn jacobian(&self, row: f64) -> Matrix3<f64> {
        Matrix3::identity() + skew(&self.angular) * self.time_of_row(row)
    }
}

/// A bundle-adjustment pose's rolling shutter: its row motion, and where
/// that motion comes from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseShutter {
    /// The motion over the readout (the angular and linear velocity as the
    /// poses stand).
    pub motion: RowMotion,
    /// The problem's poses the velocity is taken between (`before`,
    /// `after`: indices into the problem's poses, either may be this pose
    /// itself) and the seconds between them. `None`: `motion` held as
    /// given.
    pub between: Option<(usize, usize, f64)>,
}

/// The left twist that carries `first` to `second` in `dt` seconds, as the
/// camera `here` sees it: `(ρ, φ)` with `φ = log(R₂·R₁ᵀ)/dt` (the same
/// vector in either camera's frame: a turn leaves its axis) and
/// `ρ = -R_here·(c₂ - c₁)/dt` (`c` the cameras' centres).
pub fn twist_between(
    first: &Isometry3<f64>,
    second: &Isometry3<f64>,
    here: &Isometry3<f64>,
    dt: f64,
) -> (Vector3<f64>, Vector3<f64>) {
    let angular = (second.rotation * first.rotation.inverse()).scaled_axis() / dt;
    let c0 = first.inverse().translation.vector;
    let c1 = second.inverse().translation.vector;
    let linear = -(here.rotation * ((c1 - c0) / dt));
    (linear, angular)
}

/// The camera coordinates at the observation's row: `pc` itself without a
/// rolling shutter.
#[inline]
pub(crate) fn camera_point(
    shutter: Option<&RowMotion>,
    row: f64,
    pc: Vector3<f64>,
) -> Vector3<f64> {
    match shutter {
        Some(m) => m.at_row(row, &pc),
        None => pc,
    }
}

#[cfg(test)]
mod tests {
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    use super::*;
    use crate::lie::se3_exp;

    fn motion() -> RowMotion {
        RowMotion::new(
            0.03,
            481,
            Vector3::new(1.5, -0.4, 2.0),
            Vector3::new(0.3, -0.6, 0.9),
        )
        .unwrap()
    }

    #[test]
    fn a_row_sees_the_point_from_the_pose_the_twist_carries_the_camera_to() {
        let m = motion();
        let pose = Isometry3::from_parts(
            Translation3::new(0.4, -1.0, 3.0),
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.3),
        );
        let p_world = nalgebra::Point3::new(2.0, 1.0, 15.0);
        let pc = pose.transform_point(&p_world).coords;
        for row in [0.0, 100.0, 240.0, 480.0] {
            let tau = m.time_of_row(row);
            let mut xi = nalgebra::Vector6::zeros();
            xi.fixed_rows_mut::<3>(0).copy_from(&(m.linear * tau));
            xi.fixed_rows_mut::<3>(3).copy_from(&(m.angular * tau));
            let exact = (se3_exp(&xi) * pose).transform_point(&p_world).coords;
            let first_order = m.at_row(row, &pc);
            // Second order: τ²(|φ|²|p| + |φ||ρ|)/2 ≈ 2e-4 of 15 m here.
            assert!(
                (exact - first_order).norm() < 5e-4 * pc.norm(),
                "row {row}: {exact} vs {first_order}"
            );
        }
        assert_eq!(m.at_row(240.0, &pc), pc, "the centre row is the frame's");
        assert!((m.time_of_row(0.0) + 0.015).abs() < 1e-12);
        assert!((m.time_of_row(480.0) - 0.015).abs() < 1e-12);
    }

    #[test]
    fn the_jacobian_is_the_derivative_of_the_moved_point() {
        let m = motion();
        let pc = Vector3::new(1.0, -2.0, 12.0);
        let row = 30.0;
        let j = m.jacobian(row);
        for k in 0..3 {
            let mut d = Vector3::zeros();
            d[k] = 1e-6;
            let num = (m.at_row(row, &(pc + d)) - m.at_row(row, &(pc - d))) / 2e-6;
            assert!(
                (num - j.column(k)).norm() < 1e-8,
                "{num} vs {}",
                j.column(k)
            );
        }
    }

    #[test]
    fn a_global_shutter_or_bad_input_has_no_row_motion() {
        let v = Vector3::new(1.0, 0.0, 0.0);
        assert!(RowMotion::new(0.0, 480, v, v).is_none());
        assert!(RowMotion::new(f64::NAN, 480, v, v).is_none());
        assert!(RowMotion::new(0.02, 1, v, v).is_none());
        assert!(RowMotion::new(0.02, 480, Vector3::new(f64::INFINITY, 0.0, 0.0), v).is_none());
        let pc = Vector3::new(0.0, 0.0, 5.0);
        assert_eq!(camera_point(None, 0.0, pc), pc);
    }
}
