//! Pinhole camera with radial-tangential distortion (OpenCV's `k1 k2 p1 p2 k3`).
//!
//! Pixel coordinates have their origin at the centre of the top-left pixel,
//! x to the right and y down. Camera axes: x right, y down, z forward.
//!
//! The distortion model acts on normalised coordinates `(x, y) = (X/Z, Y/Z)`:
//!
//! ```text
//! r2 = x^2 + y^2
//! radial = 1 + k1 r2 + k2 r2^2 + k3 r2^3
//! xd = x radial + 2 p1 x y + p2 (r2 + 2 x^2)
//! yd = y radial + p1 (r2 + 2 y^2) + 2 p2 x y
//! u = fx xd + cx,  v = fy yd + cy
//! ```

use std::path::{Path, PathBuf};

use nalgebra::{Matrix2, Matrix3, Point2, Unit, Vector2, Vector3};
use serde::{Deserialize, Serialize};

/// Errors of the camera model and of reading a calibration.
#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    /// The calibration file could not be read.
    #[error("cannot read calibration {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A line of the calibration file does not hold the expected numbers.
    #[error("{path}:{line}: {reason}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong with it.
        reason: String,
    },
    /// The calibration holds no line with numbers.
    #[error("{path}: no calibration line (expected `fx fy cx cy k1 k2 p1 p2 k3`)")]
    Empty {
        /// The file.
        path: PathBuf,
    },
    /// The intrinsics cannot describe a camera.
    #[error("invalid intrinsics: {reason}")]
    Invalid {
        /// What is wrong.
        reason: String,
    },
}

/// Radial-tangential distortion coefficients in OpenCV order.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Distortion {
    /// Radial, r^2 term.
    pub k1: f64,
    /// Radial, r^4 term.
    pub k2: f64,
    /// Tangential, first.
    pub p1: f64,
    /// Tangential, second.
    pub p2: f64,
    /// Radial, r^6 term.
    pub k3: f64,
}

impl Distortion {
    /// True when every coefficient is zero.
    pub fn is_zero(&self) -> bool {
        self.k1 == 0.0 && self.k2 == 0.0 && self.p1 == 0.0 && self.p2 == 0.0 && self.k3 == 0.0
    }

    /// Distort normalised coordinates.
    #[inline]
    pub fn distort(&self, n: Vector2<f64>) -> Vector2<f64> {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        let xd = x * radial + 2.0 * self.p1 * x * y + self.p2 * (r2 + 2.0 * x * x);
        let yd = y * radial + self.p1 * (r2 + 2.0 * y * y) + 2.0 * self.p2 * x * y;
        Vector2::new(xd, yd)
    }

    /// Jacobian of [`Distortion::distort`] with respect to the normalised point.
    #[inline]
    pub fn jacobian(&self, n: Vector2<f64>) -> Matrix2<f64> {
        let (x, y) = (n.x, n.y);
        let r2 = x * x + y * y;
        let radial = 1.0 + r2 * (self.k1 + r2 * (self.k2 + r2 * self.k3));
        // d radial / d r2
        let dradial = self.k1 + r2 * (2.0 * self.k2 + 3.0 * r2 * self.k3);
        let dxd_dx = radial + x * dradial * 2.0 * x + 2.0 * self.p1 * y + self.p2 * 6.0 * x;
        let dxd_dy = x * dradial * 2.0 * y + 2.0 * self.p1 * x + self.p2 * 2.0 * y;
        let dyd_dx = y * dradial * 2.0 * x + self.p1 * 2.0 * x + 2.0 * self.p2 * y;
        let dyd_dy = radial + y * dradial * 2.0 * y + self.p1 * 6.0 * y + 2.0 * self.p2 * x;
        Matrix2::new(dxd_dx, dxd_dy, dyd_dx, dyd_dy)
    }

    /// Invert [`Distortion::distort`] by Gauss-Newton iterations started at the
    /// distorted point. Converges to below 1e-12 in a few iterations for any
    /// point inside the image of a real lens.
    pub fn undistort(&self, d: Vector2<f64>) -> Vector2<f64> {
        if self.is_zero() {
            return d;
        }
        let mut n = d;
        for _ in 0..30 {
            let r = self.distort(n) - d;
            if r.norm_squared() < 1e-28 {
                break;
            }
            let j = self.jacobian(n);
            let Some(inv) = j.try_inverse() else {
                break;
            };
            let step = inv * r;
            n -= step;
            if step.norm_squared() < 1e-30 {
                break;
            }
        }
        n
    }
}

/// A calibrated camera: image size, intrinsics and distortion.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Camera {
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length in x, pixels.
    pub fx: f64,
    /// Focal length in y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Lens distortion.
    #[serde(default)]
    pub distortion: Distortion,
    /// Rolling-shutter readout: seconds from the first row's exposure to
    /// the last's (0: a global shutter). A frame's time is its centre
    /// row's; the SLAM sees each row from its own pose
    /// ([`crate::optimize::RowMotion`]).
    #[serde(default)]
    pub readout_s: f64,
}

impl Camera {
    /// A camera, checked: positive size and focal lengths, finite numbers.
    pub fn new(
        width: u32,
        height: u32,
        [fx, fy, cx, cy]: [f64; 4],
        distortion: Distortion,
    ) -> Result<Self, CameraError> {
        let cam = Camera {
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            distortion,
            readout_s: 0.0,
        };
        cam.validate()?;
        Ok(cam)
    }

    /// Check that the numbers describe a camera.
    pub fn validate(&self) -> Result<(), CameraError> {
        let d = self.distortion;
        let all = [
            self.fx, self.fy, self.cx, self.cy, d.k1, d.k2, d.p1, d.p2, d.k3,
        ];
        if all.iter().any(|v| !v.is_finite()) {
            return Err(CameraError::Invalid {
                reason: "a coefficient is not a finite number".into(),
            });
        }
        if !(self.readout_s.is_finite() && (0.0..=1.0).contains(&self.readout_s)) {
            return Err(CameraError::Invalid {
                reason: format!(
                    "rolling-shutter readout {} s is not in [0, 1] s",
                    self.readout_s
                ),
            });
        }
        if self.width == 0 || self.height == 0 {
            return Err(CameraError::Invalid {
                reason: format!("image size {}x{} is empty", self.width, self.height),
            });
        }
        if self.fx <= 0.0 || self.fy <= 0.0 {
            return Err(CameraError::Invalid {
                reason: format!(
                    "focal lengths must be positive (fx {}, fy {})",
                    self.fx, self.fy
                ),
            });
        }
        Ok(())
    }

    /// Read a TUM-style `calib.txt`: one line `fx fy cx cy k1 k2 p1 p2 k3`
    /// (the distortion terms may be omitted; `#` starts a comment). The file
    /// holds no image size, so the caller gives it.
    pub fn from_calib_file(path: &Path, width: u32, height: u32) -> Result<Self, CameraError> {
        let text = std::fs::read_to_string(path).map_err(|source| CameraError::Io {
            path: path.to_owned(),
            source,
        })?;
        let parse_err = |line: usize, reason: String| CameraError::Parse {
            path: path.to_owned(),
            line,
            reason,
        };
        for (i, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let mut vals = Vec::with_capacity(9);
            for tok in line.split_whitespace() {
                let v: f64 = tok
                    .parse()
                    .map_err(|_| parse_err(i + 1, format!("`{tok}` is not a number")))?;
                vals.push(v);
            }
            if !(vals.len() == 4 || (8..=9).contains(&vals.len())) {
                return Err(parse_err(
                    i + 1,
                    format!(
                        "expected 4, 8 or 9 numbers (fx fy cx cy [k1 k2 p1 p2 [k3]]), found {}",
                        vals.len()
                    ),
                ));
            }
            let get = |k: usize| vals.get(k).copied().unwrap_or(0.0);
            let distortion = Distortion {
                k1: get(4),
                k2: get(5),
                p1: get(6),
                p2: get(7),
                k3: get(8),
            };
            return Camera::new(
                width,
                height,
                [vals[0], vals[1], vals[2], vals[3]],
                distortion,
            )
            .map_err(|e| parse_err(i + 1, e.to_string()));
        }
        Err(CameraError::Empty {
            path: path.to_owned(),
        })
    }

    /// The intrinsic matrix K.
    pub fn k(&self) -> Matrix3<f64> {
        Matrix3::new(self.fx, 0.0, self.cx, 0.0, self.fy, self.cy, 0.0, 0.0, 1.0)
    }

    /// The inverse of K.
    pub fn k_inv(&self) -> Matrix3<f64> {
        Matrix3::new(
            1.0 / self.fx,
            0.0,
            -self.cx / self.fx,
            0.0,
            1.0 / self.fy,
            -self.cy / self.fy,
            0.0,
            0.0,
            1.0,
        )
    }

    /// A copy of this camera without distortion (for undistorted keypoints).
    pub fn pinhole(&self) -> Camera {
        Camera {
            distortion: Distortion::default(),
            ..*self
        }
    }

    /// True when a pixel lies inside the image (with a border in pixels).
    #[inline]
    pub fn contains(&self, px: Point2<f64>, border: f64) -> bool {
        px.x >= -0.5 + border
            && px.y >= -0.5 + border
            && px.x <= self.width as f64 - 0.5 - border
            && px.y <= self.height as f64 - 0.5 - border
    }

    /// Project a point in camera coordinates to a (distorted) pixel.
    /// `None` when the point is not in front of the camera.
    #[inline]
    pub fn project(&self, p_cam: &Vector3<f64>) -> Option<Point2<f64>> {
        if p_cam.z <= 1e-12 {
            return None;
        }
        let n = Vector2::new(p_cam.x / p_cam.z, p_cam.y / p_cam.z);
        Some(self.normalized_to_pixel(n))
    }

    /// Project without distortion (the ideal pinhole pixel).
    #[inline]
    pub fn project_ideal(&self, p_cam: &Vector3<f64>) -> Option<Point2<f64>> {
        if p_cam.z <= 1e-12 {
            return None;
        }
        Some(Point2::new(
            self.fx * p_cam.x / p_cam.z + self.cx,
            self.fy * p_cam.y / p_cam.z + self.cy,
        ))
    }

    /// Normalised (undistorted) coordinates to a distorted pixel.
    #[inline]
    pub fn normalized_to_pixel(&self, n: Vector2<f64>) -> Point2<f64> {
        let d = self.distortion.distort(n);
        Point2::new(self.fx * d.x + self.cx, self.fy * d.y + self.cy)
    }

    /// A distorted pixel to undistorted normalised coordinates.
    #[inline]
    pub fn pixel_to_normalized(&self, px: Point2<f64>) -> Vector2<f64> {
        let d = Vector2::new((px.x - self.cx) / self.fx, (px.y - self.cy) / self.fy);
        self.distortion.undistort(d)
    }

    /// The unit bearing (camera coordinates) of the ray through a pixel.
    #[inline]
    pub fn unproject(&self, px: Point2<f64>) -> Unit<Vector3<f64>> {
        let n = self.pixel_to_normalized(px);
        Unit::new_normalize(Vector3::new(n.x, n.y, 1.0))
    }

    /// Remove distortion from a pixel: where the ray through it would land in
    /// an ideal pinhole camera with the same intrinsics.
    #[inline]
    pub fn undistort_pixel(&self, px: Point2<f64>) -> Point2<f64> {
        let n = self.pixel_to_normalized(px);
        Point2::new(self.fx * n.x + self.cx, self.fy * n.y + self.cy)
    }

    /// Add distortion to an ideal pinhole pixel (inverse of
    /// [`Camera::undistort_pixel`]).
    #[inline]
    pub fn distort_pixel(&self, ideal: Point2<f64>) -> Point2<f64> {
        let n = Vector2::new((ideal.x - self.cx) / self.fx, (ideal.y - self.cy) / self.fy);
        self.normalized_to_pixel(n)
    }
}

/// Where the calibration files of a dataset folder are found.
pub fn calib_path(dir: &Path) -> PathBuf {
    dir.join("calib.txt")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn euroc() -> Camera {
        Camera::new(
            752,
            480,
            [458.654, 457.296, 367.215, 248.375],
            Distortion {
                k1: -0.28340811,
                k2: 0.07395907,
                p1: 0.00019359,
                p2: 1.76187114e-05,
                k3: 0.0,
            },
        )
        .unwrap()
    }

    #[test]
    fn jacobian_matches_finite_differences() {
        let d = euroc().distortion;
        for &(x, y) in &[(0.1, -0.2), (-0.6, 0.4), (0.0, 0.0), (0.9, 0.5)] {
            let n = Vector2::new(x, y);
            let j = d.jacobian(n);
            let h = 1e-7;
            for c in 0..2 {
                let mut e = Vector2::zeros();
                e[c] = h;
                let fd = (d.distort(n + e) - d.distort(n - e)) / (2.0 * h);
                assert!(
                    (fd - j.column(c)).norm() < 1e-6,
                    "column {c}: {fd} vs {}",
                    j.column(c)
                );
            }
        }
    }

    #[test]
    fn project_of_unproject_is_identity_on_pixels() {
        let cam = euroc();
        let mut worst: f64 = 0.0;
        for v in (0..cam.height).step_by(4) {
            for u in (0..cam.width).step_by(4) {
                let px = Point2::new(u as f64, v as f64);
                let back = cam.project(&cam.unproject(px)).unwrap();
                worst = worst.max((back - px).norm());
            }
        }
        assert!(worst < 1e-6, "worst round trip {worst} px");
    }

    #[test]
    fn project_matches_hand_computation() {
        let cam = Camera::new(
            640,
            480,
            [500.0, 510.0, 320.0, 240.0],
            Distortion::default(),
        )
        .unwrap();
        let px = cam.project(&Vector3::new(0.2, -0.1, 2.0)).unwrap();
        assert!((px.x - 370.0).abs() < 1e-12 && (px.y - 214.5).abs() < 1e-12);
        assert!(cam.project(&Vector3::new(0.0, 0.0, -1.0)).is_none());
    }

    #[test]
    fn bad_intrinsics_are_refused() {
        assert!(Camera::new(0, 480, [500.0, 500.0, 1.0, 1.0], Distortion::default()).is_err());
        assert!(Camera::new(640, 480, [-5.0, 500.0, 1.0, 1.0], Distortion::default()).is_err());
        assert!(Camera::new(640, 480, [f64::NAN, 500.0, 1.0, 1.0], Distortion::default()).is_err());
    }

    #[test]
    fn calib_file_errors_name_file_and_line() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("calib.txt");
        std::fs::write(&p, "# comment\n535.4 539.2 x 247.6 0 0 0 0 0\n").unwrap();
        let e = Camera::from_calib_file(&p, 640, 480)
            .unwrap_err()
            .to_string();
        assert!(e.contains("calib.txt:2") && e.contains("`x`"), "{e}");
        std::fs::write(&p, "535.4 539.2 1\n").unwrap();
        let e = Camera::from_calib_file(&p, 640, 480)
            .unwrap_err()
            .to_string();
        assert!(e.contains("calib.txt:1") && e.contains("found 3"), "{e}");
        std::fs::write(&p, "# nothing\n").unwrap();
        assert!(matches!(
            Camera::from_calib_file(&p, 640, 480),
            Err(CameraError::Empty { .. })
        ));
        let missing = dir.path().join("nope.txt");
        let e = Camera::from_calib_file(&missing, 640, 480)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nope.txt"), "{e}");
    }
}
