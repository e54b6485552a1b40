//! Nonlinear least squares for SLAM: one Levenberg-Marquardt core
//! ([`lm`]) and the problems built on it:
//!
//! * [`pose`]: motion-only bundle adjustment of one camera against fixed
//!   map points, with ORB-SLAM's four rounds of outlier rejection;
//! * [`ba`]: local bundle adjustment over keyframes and points, points
//!   eliminated by the Schur complement, the reduced camera system solved by
//!   faer's dense Cholesky, fixed keyframes as the gauge;
//! * [`shutter`]: a rolling shutter's row times in the reprojection error
//!   of both ([`RowMotion`]);
//! * [`sim3`]: the Sim(3) between two keyframes from their matched points;
//! * [`essential_graph`]: the Sim(3) pose graph of loop closing (keyframe
//!   poses only), its block-sparse normal equations solved by faer's sparse
//!   Cholesky.
//!
//! # Conventions
//!
//! * Poses are `cam_from_world` isometries; camera axes x right, y down,
//!   z forward; pixels are undistorted.
//! * **Left perturbation**: an SE(3) update is `T ← Exp(δ)·T` with
//!   `δ = [υ; ω]` (translation first), so `∂(T·p)/∂δ = [I₃ | -[T·p]ₓ]` at
//!   `δ = 0` (see [`crate::lie`]). Sim(3) updates are
//!   `S ← (e^σ·Exp(ω), υ) ∘ S` with `δ = [υ; ω; σ]`.
//! * Residuals are `r = π(p_cam) - uv` in pixels, weighted by the
//!   observation's `inv_sigma2` (ORB-SLAM's per-octave `1/σ²`); the squared
//!   weighted error `s = rᵀ·r·inv_sigma2` is the "chi2" compared against
//!   the chi-square thresholds. The cost is `½·Σ ρ(s)` with the robust
//!   kernel `ρ`.

pub mod ba;
pub mod essential_graph;
pub mod lm;
pub mod pose;
pub mod shutter;
pub mod sim3;

pub use ba::{
    BaParams, BaPose, BaProblem, BaReport, Observation, PositionPrior, aligned_centre_covariances,
    local_bundle_adjustment,
};
pub use essential_graph::{PoseGraph, PoseGraphParams, Sim3Edge, optimize_pose_graph};
pub use lm::{LmParams, LmSummary, Termination};
pub use pose::{
    IntrinsicsCorrection, IntrinsicsUncertainty, PoseCovariance, PoseObservation, PoseParams,
    PosePrior, PoseReport, observation_chi2, optimize_pose, optimize_pose_with_prior,
    pose_covariance, refine_pose_and_intrinsics, refine_pose_and_intrinsics_from,
};
pub use shutter::RowMotion;
pub use sim3::{Sim3Match, Sim3Params, Sim3Report, optimize_sim3};

use nalgebra::{Matrix2x3, Point2, Vector3};

/// Every tunable number of the optimisation module.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Params {
    /// Motion-only BA.
    pub pose: PoseParams,
    /// Local BA.
    pub ba: BaParams,
    /// Sim(3) between keyframes.
    pub sim3: Sim3Params,
}

/// Errors of the optimisation module.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum OptimizeError {
    /// Too few observations for the unknowns.
    #[error("not enough observations: found {found}, needed {needed}")]
    NotEnoughObservations {
        /// Observations given (or left after rejection).
        found: usize,
        /// Minimum needed.
        needed: usize,
    },
    /// An observation refers to a pose or point that does not exist.
    #[error("observation {observation} refers to {what} {index}, but there are {len}")]
    IndexOutOfRange {
        /// Index of the observation.
        observation: usize,
        /// `"pose"` or `"point"`.
        what: &'static str,
        /// The bad index.
        index: usize,
        /// How many exist.
        len: usize,
    },
    /// An input value is NaN or infinite (or a weight is not positive).
    #[error("non-finite or invalid input in {what} {index}")]
    InvalidInput {
        /// Which kind of input.
        what: &'static str,
        /// Its index.
        index: usize,
    },
    /// Every pose is fixed: nothing to optimise.
    #[error("every pose is fixed")]
    NothingToOptimize,
}

/// Pinhole intrinsics of undistorted pixels: `u = fx·x/z + cx`, `v = fy·y/z + cy`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Intrinsics {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
}

impl Intrinsics {
    /// Projects a camera-frame point to pixels (no depth check).
    #[inline]
    pub fn project(&self, p: &Vector3<f64>) -> Point2<f64> {
        let iz = 1.0 / p.z;
        Point2::new(self.fx * p.x * iz + self.cx, self.fy * p.y * iz + self.cy)
    }

    /// The 2×3 Jacobian of [`Intrinsics::project`] at `p`.
    #[inline]
    pub fn project_jacobian(&self, p: &Vector3<f64>) -> Matrix2x3<f64> {
        let iz = 1.0 / p.z;
        let iz2 = iz * iz;
        Matrix2x3::new(
            self.fx * iz,
            0.0,
            -self.fx * p.x * iz2,
            0.0,
            self.fy * iz,
            -self.fy * p.y * iz2,
        )
    }

    /// Checks that the numbers are finite and the focal lengths positive.
    pub fn is_valid(&self) -> bool {
        self.fx.is_finite()
            && self.fy.is_finite()
            && self.cx.is_finite()
            && self.cy.is_finite()
            && self.fx > 0.0
            && self.fy > 0.0
    }
}

/// A robust kernel `ρ(s)` applied to the squared weighted error `s`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum RobustKernel {
    /// Plain least squares, `ρ(s) = s`.
    None,
    /// Huber with threshold `delta` on the (unsquared) error:
    /// `ρ(s) = s` for `s ≤ δ²`, else `2δ√s - δ²`.
    Huber {
        /// The threshold on `√s`.
        delta: f64,
    },
    /// Cauchy with scale `c`: `ρ(s) = c²·ln(1 + s/c²)`.
    Cauchy {
        /// The scale on `√s`.
        c: f64,
    },
}

impl RobustKernel {
    /// `(ρ(s), ρ'(s))`.
    #[inline]
    pub fn eval(&self, s: f64) -> (f64, f64) {
        match *self {
            RobustKernel::None => (s, 1.0),
            RobustKernel::Huber { delta } => {
                let d2 = delta * delta;
                if s <= d2 {
                    (s, 1.0)
                } else {
                    let r = s.sqrt();
                    (2.0 * delta * r - d2, delta / r)
                }
            }
            RobustKernel::Cauchy { c } => {
                let c2 = c * c;
                let a = 1.0 + s / c2;
                (c2 * a.ln(), 1.0 / a)
            }
        }
    }
}

/// Validates a 2-D observation and its weight.
#[inline]
pub(crate) fn valid_obs(uv: &Point2<f64>, inv_sigma2: f64) -> bool {
    uv.x.is_finite() && uv.y.is_finite() && inv_sigma2.is_finite() && inv_sigma2 > 0.0
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernels_have_the_right_derivative() {
        for k in [
            RobustKernel::None,
            RobustKernel::Huber { delta: 2.0 },
            RobustKernel::Cauchy { c: 1.5 },
        ] {
            for s in [0.1, 1.0, 3.9, 4.1, 20.0] {
                let (_, d) = k.eval(s);
                let h = 1e-6;
                let fd = (k.eval(s + h).0 - k.eval(s - h).0) / (2.0 * h);
                assert!((d - fd).abs() < 1e-6, "{k:?} at {s}: {d} vs {fd}");
            }
        }
        // Huber is continuous at the threshold.
        let k = RobustKernel::Huber { delta: 2.0 };
        assert!((k.eval(4.0 - 1e-12).0 - k.eval(4.0 + 1e-12).0).abs() < 1e-9);
    }

    #[test]
    fn projection_jacobian_matches_finite_differences() {
        let k = Intrinsics {
            fx: 500.0,
            fy: 480.0,
            cx: 320.0,
            cy: 240.0,
        };
        let p = Vector3::new(0.3, -0.2, 2.5);
        let j = k.project_jacobian(&p);
        for c in 0..3 {
            let mut e = Vector3::zeros();
            e[c] = 1e-6;
            let fd = (k.project(&(p + e)) - k.project(&(p - e))) / 2e-6;
            assert!((fd - j.column(c)).norm() < 1e-4);
        }
    }
}
