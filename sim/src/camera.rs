//! The simulator's own camera model: pinhole + radial-tangential distortion.
//!
//! This is deliberately independent code from the daemon's `camera.rs`, so
//! the two check each other. Conventions (the OpenCV ones):
//!
//! - camera axes: x right, y down, z forward;
//! - normalized coordinates `x = X/Z`, `y = Y/Z`;
//! - distortion with coefficients in OpenCV order `k1 k2 p1 p2 k3`:
//!   `r² = x² + y²`, `radial = 1 + k1 r² + k2 r⁴ + k3 r⁶`,
//!   `x_d = x·radial + 2 p1 x y + p2 (r² + 2x²)`,
//!   `y_d = y·radial + p1 (r² + 2y²) + 2 p2 x y`;
//! - pixel `u = fx x_d + cx`, `v = fy y_d + cy`, where integer pixel
//!   coordinates are pixel *centres* (pixel `(0, 0)` covers `[-0.5, 0.5]²`).

use nalgebra::{Point2, Vector2, Vector3};

/// Errors of the camera model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraError {
    /// The point is behind (or on) the camera's image plane.
    #[error("point is not in front of the camera (z = {z})")]
    BehindCamera {
        /// The camera-frame depth of the point.
        z: f64,
    },
    /// Iterative undistortion of a pixel did not converge.
    #[error("undistortion of pixel ({u}, {v}) did not converge after {iterations} iterations")]
    UndistortDiverged {
        /// Pixel column.
        u: f64,
        /// Pixel row.
        v: f64,
        /// Iterations spent.
        iterations: usize,
    },
    /// The intrinsics are unusable (non-positive size or focal length, NaN).
    #[error("invalid camera intrinsics: {reason}")]
    InvalidIntrinsics {
        /// What is wrong.
        reason: &'static str,
    },
}

/// Tunables of the iterative undistortion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Params {
    /// Maximum Newton iterations when undistorting a pixel.
    pub undistort_max_iterations: usize,
    /// Convergence threshold on the residual, in normalized units.
    pub undistort_tolerance: f64,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            undistort_max_iterations: 30,
            undistort_tolerance: 1e-12,
        }
    }
}

/// A pinhole camera with radial-tangential distortion (OpenCV order).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct SimCamera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point column, pixels.
    pub cx: f64,
    /// Principal point row, pixels.
    pub cy: f64,
    /// Radial coefficient of r².
    pub k1: f64,
    /// Radial coefficient of r⁴.
    pub k2: f64,
    /// First tangential coefficient.
    pub p1: f64,
    /// Second tangential coefficient.
    pub p2: f64,
    /// Radial coefficient of r⁶.
    pub k3: f64,
}

impl Default for SimCamera {
    /// 640x480, about 69° horizontal field of view, a small barrel
    /// distortion and a slight decentering, like a small gimbal camera.
    fn default() -> Self {
        Self {
            width: 640,
            height: 480,
            fx: 460.0,
            fy: 460.0,
            cx: 319.5,
            cy: 239.5,
            k1: -0.05,
            k2: 0.01,
            p1: 0.0005,
            p2: -0.0003,
            k3: 0.0,
        }
    }
}

impl SimCamera {
    /// The default camera's lens (same horizontal field of view and
    /// distortion) on a `width` x `height` sensor, the principal point
    /// at its centre: e.g. a 1280x720 stream of the same camera.
    pub fn with_size(width: u32, height: u32) -> Self {
        let s = f64::from(width) / 640.0;
        let d = Self::default();
        Self {
            width,
            height,
            fx: d.fx * s,
            fy: d.fy * s,
            cx: f64::from(width) / 2.0 - 0.5,
            cy: f64::from(height) / 2.0 - 0.5,
            ..d
        }
    }

    /// Checks that the intrinsics can be used.
    pub fn validate(&self) -> Result<(), CameraError> {
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::InvalidIntrinsics {
                reason: "zero image size",
            });
        }
        let all = [
            self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, self.p1, self.p2, self.k3,
        ];
        if all.iter().any(|v| !v.is_finite()) {
            return Err(CameraError::InvalidIntrinsics {
                reason: "non-finite coefficient",
            });
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(CameraError::InvalidIntrinsics {
                reason: "non-positive focal length",
            });
        }
        Ok(())
    }

    /// Applies the distortion to normalized coordinates.
    pub fn distort(&self, n: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        Vector2::new(xd, yd)
    }

    /// Jacobian of [`Self::distort`] at `n`, row-major `[[dxd/dx, dxd/dy], [dyd/dx, dyd/dy]]`.
    fn distort_jacobian(&self, n: Vector2<f64>) -> [[f64; 2]; 2] {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d radial / d r2
        let dradial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * self.k3 * r2);
        let dxdx = radial + x * dradial * 2.0 * x + 2.0 * self.p1 * y + self.p2 * 6.0 * x;
        let dxdy = x * dradial * 2.0 * y + 2.0 * self.p1 * x + self.p2 * 2.0 * y;
        let dydx = y * dradial * 2.0 * x + self.p1 * 2.0 * x + 2.0 * self.p2 * y;
        let dydy = radial + y * dradial * 2.0 * y + self.p1 * 6.0 * y + 2.0 * self.p2 * x;
        [[dxdx, dxdy], [dydx, dydy]]
    }

    /// Projects a camera-frame point to a distorted pixel.
    pub fn project(&self, p_cam: &Vector3<f64>) -> Result<Point2<f64>, CameraError> {
        if p_cam.z.is_nan() || p_cam.z <= 1e-12 {
            return Err(CameraError::BehindCamera { z: p_cam.z });
        }
        let n = Vector2::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z);
        let d = self.distort(n);
        Ok(Point2::new(
            self.fx * d.x + self.cx,
            self.fy * d.y + self.cy,
        ))
    }

    /// Inverts the distortion of normalized coordinates by Newton iteration.
    pub fn undistort_normalized(
        &self,
        d: Vector2<f64>,
        params: &Params,
    ) -> Result<Vector2<f64>, CameraError> {
        let mut n = d;
        for _ in 0..params.undistort_max_iterations {
            let r = self.distort(n) - d;
            if r.norm() < params.undistort_tolerance {
                return Ok(n);
            }
            let j = self.distort_jacobian(n);
            let det = j[0][0] * j[1][1] - j[0][1] * j[1][0];
            if !det.is_finite() || det.abs() < 1e-12 {
                break;
            }
            let dx = (j[1][1] * r.x - j[0][1] * r.y) / det;
            let dy = (-j[1][0] * r.x + j[0][0] * r.y) / det;
            n -= Vector2::new(dx, dy);
            if !n.x.is_finite() || !n.y.is_finite() {
                break;
            }
        }
        // A last check: converged exactly on the last step.
        if (self.distort(n) - d).norm() < params.undistort_tolerance.max(1e-10) {
            return Ok(n);
        }
        Err(CameraError::UndistortDiverged {
            u: self.fx * d.x + self.cx,
            v: self.fy * d.y + self.cy,
            iterations: params.undistort_max_iterations,
        })
    }

    /// The unit ray (camera frame) through a distorted pixel.
    pub fn pixel_to_ray(
        &self,
        pixel: Point2<f64>,
        params: &Params,
    ) -> Result<Vector3<f64>, CameraError> {
        let d = Vector2::new((pixel.x - self.cx) / self.fx, (pixel.y - self.cy) / self.fy);
        let n = self.undistort_normalized(d, params)?;
        Ok(Vector3::new(n.x, n.y, 1.0).normalize())
    }

    /// `fx fy cx cy k1 k2 p1 p2 k3` on one line, the `calib.txt` format.
    pub fn calib_line(&self) -> String {
        format!(
            "{} {} {} {} {} {} {} {} {}",
            self.fx, self.fy, self.cx, self.cy, self.k1, self.k2, self.p1, self.p2, self.k3
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn distortion_round_trip_over_the_image() {
        let cam = SimCamera::default();
        let params = Params::default();
        let mut worst: f64 = 0.0;
        for v in (0..cam.height).step_by(7) {
            for u in (0..cam.width).step_by(7) {
                let px = Point2::new(u as f64, v as f64);
                let ray = cam.pixel_to_ray(px, &params).unwrap();
                let back = cam.project(&(ray * 7.3)).unwrap();
                worst = worst.max((back - px).norm());
            }
        }
        // Include the far corner explicitly.
        let px = Point2::new(639.0, 479.0);
        let back = cam
            .project(&cam.pixel_to_ray(px, &params).unwrap())
            .unwrap();
        worst = worst.max((back - px).norm());
        assert!(worst < 1e-8, "round trip error {worst} px");
    }

    #[test]
    fn distortion_moves_corners_and_not_the_centre() {
        let cam = SimCamera::default();
        let ideal = SimCamera {
            k1: 0.0,
            k2: 0.0,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
            ..cam
        };
        let p = Vector3::new(0.0, 0.0, 5.0);
        assert!((cam.project(&p).unwrap() - ideal.project(&p).unwrap()).norm() < 1e-12);
        // Barrel distortion (k1 < 0) pulls the corner inwards by pixels.
        let corner = Vector3::new(0.69, 0.52, 1.0);
        let a = cam.project(&corner).unwrap();
        let b = ideal.project(&corner).unwrap();
        let shift = (a - b).norm();
        assert!(shift > 5.0 && shift < 40.0, "corner shift {shift}");
        assert!(
            (a - Point2::new(cam.cx, cam.cy)).norm() < (b - Point2::new(cam.cx, cam.cy)).norm()
        );
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let cam = SimCamera {
            k3: 0.002,
            ..SimCamera::default()
        };
        let n = Vector2::new(0.4, -0.3);
        let j = cam.distort_jacobian(n);
        let h = 1e-7;
        let dx = (cam.distort(n + Vector2::new(h, 0.0)) - cam.distort(n - Vector2::new(h, 0.0)))
            / (2.0 * h);
        let dy = (cam.distort(n + Vector2::new(0.0, h)) - cam.distort(n - Vector2::new(0.0, h)))
            / (2.0 * h);
        assert!((j[0][0] - dx.x).abs() < 1e-6 && (j[1][0] - dx.y).abs() < 1e-6);
        assert!((j[0][1] - dy.x).abs() < 1e-6 && (j[1][1] - dy.y).abs() < 1e-6);
    }

    #[test]
    fn behind_camera_is_an_error() {
        let cam = SimCamera::default();
        assert!(matches!(
            cam.project(&Vector3::new(1.0, 0.0, -1.0)),
            Err(CameraError::BehindCamera { .. })
        ));
        assert!(cam.project(&Vector3::new(1.0, 0.0, f64::NAN)).is_err());
    }

    #[test]
    fn invalid_intrinsics_are_rejected() {
        let cam = SimCamera {
            fx: 0.0,
            ..SimCamera::default()
        };
        assert!(cam.validate().is_err());
        assert!(SimCamera::default().validate().is_ok());
    }
}
