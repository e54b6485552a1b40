//! The Sim(3) between two keyframes from matched map points, as ORB-SLAM's
//! `Optimizer::OptimizeSim3` does it (loop closing).
//!
//! The unknown `S₁₂` maps camera-2 coordinates to camera-1 coordinates.
//! Each match contributes two residuals: the point of keyframe 2 (`X₂`,
//! camera-2 frame) mapped by `S₁₂` and projected into keyframe 1 against
//! its keypoint there, and the point of keyframe 1 (`X₁`) mapped by
//! `S₁₂⁻¹` into keyframe 2. A first pass of 5 LM iterations with a Huber
//! kernel (`δ = √th2`), then matches whose chi2 exceeds `th2` in either
//! direction are dropped, and a second pass (10 iterations if any were
//! dropped, else 5) refines on the rest.
//!
//! Update: `S ← (e^σ·Exp(ω), υ) ∘ S`, `δ = [υ; ω; σ]`, so for `q = S·X₂`:
//! `∂q/∂δ = [I | -[q]ₓ | q]`, and for `q' = S⁻¹·X₁`:
//! `∂q'/∂δ = (1/s)·Rᵀ·[-I | [X₁]ₓ | -X₁]`. With `fix_scale` the scale is
//! held (stereo/RGB-D).

use nalgebra::{Matrix2x3, Point2, Point3, SMatrix, SVector, UnitQuaternion, Vector3};

use super::lm::{LeastSquares, LmParams, LmSummary, levenberg_marquardt, solve_damped_dense};
use super::{Intrinsics, OptimizeError, RobustKernel, valid_obs};
use crate::lie::Sim3;
use crate::lie::skew;

type Mat7 = SMatrix<f64, 7, 7>;
type Vec7 = SVector<f64, 7>;
type Mat2x7 = SMatrix<f64, 2, 7>;

/// One matched pair of map points between keyframes 1 and 2.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3Match {
    /// The keyframe-1 point in camera-1 coordinates.
    pub x1_cam1: Point3<f64>,
    /// The keyframe-2 point in camera-2 coordinates.
    pub x2_cam2: Point3<f64>,
    /// Keypoint of the keyframe-1 point in keyframe 1 (undistorted px).
    pub uv1: Point2<f64>,
    /// Keypoint of the keyframe-2 point in keyframe 2 (undistorted px).
    pub uv2: Point2<f64>,
    /// `1/σ²` of `uv1`'s octave.
    pub inv_sigma2_1: f64,
    /// `1/σ²` of `uv2`'s octave.
    pub inv_sigma2_2: f64,
}

/// Tunables of [`optimize_sim3`]. Defaults are ORB-SLAM's loop closing.
#[derive(Debug, Clone, PartialEq)]
pub struct Sim3Params {
    /// Chi2 threshold `th2` (ORB-SLAM passes 10 from loop closing).
    pub chi2_threshold: f64,
    /// Iterations of the robust first pass.
    pub first_pass_iterations: usize,
    /// Iterations of the second pass when matches were dropped.
    pub second_pass_iterations_after_drop: usize,
    /// Iterations of the second pass when none were.
    pub second_pass_iterations: usize,
    /// Hold the scale (stereo / RGB-D).
    pub fix_scale: bool,
    /// Points closer than this count as behind the camera.
    pub min_depth: f64,
    /// Base LM settings.
    pub lm: LmParams,
}

impl Default for Sim3Params {
    fn default() -> Self {
        Self {
            chi2_threshold: 10.0,
            first_pass_iterations: 5,
            second_pass_iterations_after_drop: 10,
            second_pass_iterations: 5,
            fix_scale: false,
            min_depth: 1e-6,
            lm: LmParams::default(),
        }
    }
}

/// Result of [`optimize_sim3`].
#[derive(Debug, Clone, PartialEq)]
pub struct Sim3Report {
    /// The optimised `S₁₂` (camera 2 → camera 1).
    pub s12: Sim3,
    /// Per match: inlier at the end (both directions within `th2`).
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub n_inliers: usize,
    /// First pass summary.
    pub first_pass: LmSummary,
    /// Second pass summary.
    pub second_pass: LmSummary,
}

struct Sim3Ls<'a> {
    matches: &'a [Sim3Match],
    active: &'a [bool],
    intr: Intrinsics,
    kernel: RobustKernel,
    min_depth: f64,
    fix_scale: bool,
    s12: Sim3,
    old: Sim3,
    h: Mat7,
    g: Vec7,
    step: Vec7,
}

/// Chi2 of both directions of one match (`None` for behind the camera).
fn match_chi2(
    s12: &Sim3,
    s21: &Sim3,
    intr: &Intrinsics,
    m: &Sim3Match,
    min_depth: f64,
) -> (Option<f64>, Option<f64>) {
    let q1 = s12.transform_point(&m.x2_cam2).coords;
    let c1 =
        (q1.z > min_depth).then(|| (intr.project(&q1) - m.uv1).norm_squared() * m.inv_sigma2_1);
    let q2 = s21.transform_point(&m.x1_cam1).coords;
    let c2 =
        (q2.z > min_depth).then(|| (intr.project(&q2) - m.uv2).norm_squared() * m.inv_sigma2_2);
    (c1, c2)
}

/// Applies the left update `(e^σ·Exp(ω), υ) ∘ S`.
pub fn sim3_left_update(s: &Sim3, d: &Vec7) -> Sim3 {
    let dq = UnitQuaternion::from_scaled_axis(Vector3::new(d[3], d[4], d[5]));
    let es = d[6].exp();
    Sim3::new(
        dq * s.rotation,
        dq * s.translation * es + Vector3::new(d[0], d[1], d[2]),
        s.scale * es,
    )
}

const BEHIND_CHI2: f64 = 1e4;

impl Sim3Ls<'_> {
    /// Residuals and Jacobians of one match (direction 1→ then 2).
    fn terms(
        &self,
        m: &Sim3Match,
        s21: &Sim3,
        lin_r: &nalgebra::Matrix3<f64>,
    ) -> [Option<(nalgebra::Vector2<f64>, Mat2x7, f64)>; 2] {
        let mut out = [None, None];
        let q1 = self.s12.transform_point(&m.x2_cam2).coords;
        if q1.z > self.min_depth {
            let r = self.intr.project(&q1) - m.uv1;
            let jp = self.intr.project_jacobian(&q1);
            let mut dq = SMatrix::<f64, 3, 7>::zeros();
            dq.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&nalgebra::Matrix3::identity());
            dq.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-skew(&q1)));
            dq.fixed_view_mut::<3, 1>(0, 6).copy_from(&q1);
            out[0] = Some((r, jp * dq, m.inv_sigma2_1));
        }
        let q2 = s21.transform_point(&m.x1_cam1).coords;
        if q2.z > self.min_depth {
            let r = self.intr.project(&q2) - m.uv2;
            let jp: Matrix2x3<f64> = self.intr.project_jacobian(&q2);
            let x1 = m.x1_cam1.coords;
            let mut dg = SMatrix::<f64, 3, 7>::zeros();
            dg.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&(-nalgebra::Matrix3::identity()));
            dg.fixed_view_mut::<3, 3>(0, 3).copy_from(&skew(&x1));
            dg.fixed_view_mut::<3, 1>(0, 6).copy_from(&(-x1));
            // (1/s)·Rᵀ = linear part of S⁻¹
            out[1] = Some((r, jp * lin_r * dg, m.inv_sigma2_2));
        }
        out
    }
}

impl LeastSquares for Sim3Ls<'_> {
    fn linearize(&mut self) -> (f64, f64) {
        let s21 = self.s12.inverse();
        let lin_inv = s21.linear();
        let mut h = Mat7::zeros();
        let mut g = Vec7::zeros();
        let mut cost = 0.0;
        for (m, _) in self.matches.iter().zip(self.active).filter(|(_, a)| **a) {
            for t in self.terms(m, &s21, &lin_inv) {
                match t {
                    Some((r, mut j, is2)) => {
                        if self.fix_scale {
                            j.column_mut(6).fill(0.0);
                        }
                        let s = r.norm_squared() * is2;
                        let (rho, drho) = self.kernel.eval(s);
                        cost += 0.5 * rho;
                        let w = drho * is2;
                        let jt = j.transpose();
                        h += jt * j * w;
                        g += jt * r * w;
                    }
                    None => cost += 0.5 * self.kernel.eval(BEHIND_CHI2).0,
                }
            }
        }
        if self.fix_scale {
            h[(6, 6)] = 1.0;
        }
        self.h = h;
        self.g = g;
        (cost, g.amax())
    }

    fn solve_damped(&mut self, lambda: f64) -> Option<(f64, f64)> {
        let (step, pred) = solve_damped_dense(&self.h, &self.g, lambda)?;
        self.step = step;
        Some((pred, step.norm()))
    }

    fn apply_step(&mut self) {
        self.old = self.s12;
        self.s12 = sim3_left_update(&self.s12, &self.step);
    }

    fn revert_step(&mut self) {
        self.s12 = self.old;
    }

    fn cost(&mut self) -> f64 {
        let s21 = self.s12.inverse();
        let mut cost = 0.0;
        for (m, _) in self.matches.iter().zip(self.active).filter(|(_, a)| **a) {
            let (c1, c2) = match_chi2(&self.s12, &s21, &self.intr, m, self.min_depth);
            cost += 0.5 * self.kernel.eval(c1.unwrap_or(BEHIND_CHI2)).0;
            cost += 0.5 * self.kernel.eval(c2.unwrap_or(BEHIND_CHI2)).0;
        }
        cost
    }

    fn state_norm(&self) -> f64 {
        (self.s12.translation.norm_squared()
            + self.s12.rotation.scaled_axis().norm_squared()
            + self.s12.scale.ln().powi(2))
        .sqrt()
    }
}

/// Refines `S₁₂` from matched points (see the module documentation).
///
/// Errors: [`OptimizeError::NotEnoughObservations`] with fewer than 3
/// matches, [`OptimizeError::InvalidInput`] for non-finite values.
pub fn optimize_sim3(
    s12_init: &Sim3,
    matches: &[Sim3Match],
    intr: &Intrinsics,
    params: &Sim3Params,
) -> Result<Sim3Report, OptimizeError> {
    if matches.len() < 3 {
        return Err(OptimizeError::NotEnoughObservations {
            found: matches.len(),
            needed: 3,
        });
    }
    if !intr.is_valid() {
        return Err(OptimizeError::InvalidInput {
            what: "intrinsics",
            index: 0,
        });
    }
    for (i, m) in matches.iter().enumerate() {
        let fin = |p: &Point3<f64>| p.x.is_finite() && p.y.is_finite() && p.z.is_finite();
        if !(fin(&m.x1_cam1)
            && fin(&m.x2_cam2)
            && valid_obs(&m.uv1, m.inv_sigma2_1)
            && valid_obs(&m.uv2, m.inv_sigma2_2))
        {
            return Err(OptimizeError::InvalidInput {
                what: "match",
                index: i,
            });
        }
    }
    if !(s12_init.scale.is_finite() && s12_init.scale > 0.0) {
        return Err(OptimizeError::InvalidInput {
            what: "initial scale",
            index: 0,
        });
    }
    let mut active = vec![true; matches.len()];
    let huber = RobustKernel::Huber {
        delta: params.chi2_threshold.sqrt(),
    };
    let run = |s: Sim3, active: &[bool], kernel: RobustKernel, iters: usize| {
        let mut ls = Sim3Ls {
            matches,
            active,
            intr: *intr,
            kernel,
            min_depth: params.min_depth,
            fix_scale: params.fix_scale,
            s12: s,
            old: s,
            h: Mat7::zeros(),
            g: Vec7::zeros(),
            step: Vec7::zeros(),
        };
        let sum = levenberg_marquardt(
            &mut ls,
            &LmParams {
                max_iterations: iters,
                ..params.lm.clone()
            },
        );
        (ls.s12, sum)
    };
    let (s1, first_pass) = run(*s12_init, &active, huber, params.first_pass_iterations);
    let classify = |s: &Sim3, active: &mut [bool]| -> usize {
        let s21 = s.inverse();
        let mut bad = 0;
        for (m, a) in matches.iter().zip(active.iter_mut()) {
            let (c1, c2) = match_chi2(s, &s21, intr, m, params.min_depth);
            let ok = c1.is_some_and(|c| c <= params.chi2_threshold)
                && c2.is_some_and(|c| c <= params.chi2_threshold);
            if !ok {
                bad += usize::from(*a);
            }
            *a = ok;
        }
        bad
    };
    let n_bad = classify(&s1, &mut active);
    let iters = if n_bad > 0 {
        params.second_pass_iterations_after_drop
    } else {
        params.second_pass_iterations
    };
    // ORB-SLAM keeps the Huber kernel in the second pass.
    let (s2, second_pass) = run(s1, &active, huber, iters);
    classify(&s2, &mut active);
    let n_inliers = active.iter().filter(|&&a| a).count();
    Ok(Sim3Report {
        s12: s2,
        inliers: active,
        n_inliers,
        first_pass,
        second_pass,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    fn intr() -> Intrinsics {
        Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        }
    }

    #[test]
    fn jacobians_match_finite_differences() {
        let s = Sim3::new(
            UnitQuaternion::from_euler_angles(0.1, -0.2, 0.05),
            Vector3::new(0.3, -0.1, 0.2),
            1.3,
        );
        let m = Sim3Match {
            x1_cam1: Point3::new(0.2, 0.1, 3.0),
            x2_cam2: Point3::new(-0.3, 0.2, 2.5),
            uv1: Point2::new(300.0, 250.0),
            uv2: Point2::new(330.0, 220.0),
            inv_sigma2_1: 1.0,
            inv_sigma2_2: 1.0,
        };
        let ms = [m];
        let act = [true];
        let ls = Sim3Ls {
            matches: &ms,
            active: &act,
            intr: intr(),
            kernel: RobustKernel::None,
            min_depth: 1e-6,
            fix_scale: false,
            s12: s,
            old: s,
            h: Mat7::zeros(),
            g: Vec7::zeros(),
            step: Vec7::zeros(),
        };
        let s21 = s.inverse();
        let terms = ls.terms(&m, &s21, &s21.linear());
        let res = |sx: &Sim3| {
            let q1 = sx.transform_point(&m.x2_cam2).coords;
            let q2 = sx.inverse().transform_point(&m.x1_cam1).coords;
            (intr().project(&q1) - m.uv1, intr().project(&q2) - m.uv2)
        };
        for k in 0..7 {
            let mut d = Vec7::zeros();
            d[k] = 1e-7;
            let (a1, a2) = res(&sim3_left_update(&s, &d));
            let (b1, b2) = res(&sim3_left_update(&s, &(-d)));
            let fd1 = (a1 - b1) / 2e-7;
            let fd2 = (a2 - b2) / 2e-7;
            let j1 = terms[0].unwrap().1.column(k).into_owned();
            let j2 = terms[1].unwrap().1.column(k).into_owned();
            assert!(
                (fd1 - j1).norm() < 1e-4 * (1.0 + j1.norm()),
                "col {k}: {fd1} vs {j1}"
            );
            assert!(
                (fd2 - j2).norm() < 1e-4 * (1.0 + j2.norm()),
                "col {k}: {fd2} vs {j2}"
            );
        }
    }

    #[test]
    fn fixed_scale_is_held() {
        let truth = Sim3::new(
            UnitQuaternion::from_euler_angles(0.02, -0.1, 0.05),
            Vector3::new(-0.3, 0.1, 0.2),
            1.0,
        );
        let k = intr();
        let mut rng = SmallRng::seed_from_u64(2);
        let ms: Vec<Sim3Match> = (0..60)
            .map(|_| {
                let x1 = Point3::new(
                    rng.random_range(-2.0..2.0),
                    rng.random_range(-1.5..1.5),
                    rng.random_range(3.0..7.0),
                );
                let x2 = truth.inverse().transform_point(&x1);
                Sim3Match {
                    x1_cam1: x1,
                    x2_cam2: x2,
                    uv1: k.project(&x1.coords),
                    uv2: k.project(&x2.coords),
                    inv_sigma2_1: 1.0,
                    inv_sigma2_2: 1.0,
                }
            })
            .collect();
        let init = Sim3::new(
            UnitQuaternion::from_euler_angles(0.04, -0.08, 0.03),
            Vector3::new(-0.2, 0.05, 0.25),
            1.0,
        );
        let params = Sim3Params {
            fix_scale: true,
            ..Sim3Params::default()
        };
        let rep = optimize_sim3(&init, &ms, &k, &params).unwrap();
        assert_eq!(rep.s12.scale, 1.0);
        assert!(rep.s12.rotation.angle_to(&truth.rotation) < 1e-6);
        assert!((rep.s12.translation - truth.translation).norm() < 1e-6);
        assert_eq!(rep.n_inliers, 60);
    }

    #[test]
    fn recovers_sim3_and_drops_bad_matches() {
        let mut rng = SmallRng::seed_from_u64(11);
        let truth = Sim3::new(
            UnitQuaternion::from_euler_angles(0.05, 0.2, -0.1),
            Vector3::new(0.5, -0.2, 0.3),
            0.8,
        );
        let k = intr();
        let mut ms = Vec::new();
        for i in 0..150 {
            let x1 = Point3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-1.5..1.5),
                rng.random_range(3.0..7.0),
            );
            let x2 = truth.inverse().transform_point(&x1);
            let mut uv1 = k.project(&x1.coords);
            let mut uv2 = k.project(&x2.coords);
            uv1.x += rng.random_range(-1.0..1.0);
            uv2.y += rng.random_range(-1.0..1.0);
            if i % 10 == 0 {
                uv2.x += 40.0;
            }
            ms.push(Sim3Match {
                x1_cam1: x1,
                x2_cam2: x2,
                uv1,
                uv2,
                inv_sigma2_1: 1.0,
                inv_sigma2_2: 1.0,
            });
        }
        let init = Sim3::new(
            UnitQuaternion::from_euler_angles(0.08, 0.17, -0.12),
            Vector3::new(0.6, -0.1, 0.2),
            0.9,
        );
        let rep = optimize_sim3(&init, &ms, &k, &Sim3Params::default()).unwrap();
        assert!((rep.s12.scale - 0.8).abs() < 0.01, "{}", rep.s12.scale);
        assert!(rep.s12.rotation.angle_to(&truth.rotation).to_degrees() < 0.2);
        assert!((rep.s12.translation - truth.translation).norm() < 0.03);
        for (i, &inl) in rep.inliers.iter().enumerate() {
            if i % 10 == 0 {
                assert!(!inl);
            }
        }
        assert!(rep.n_inliers >= 125);
    }
}
