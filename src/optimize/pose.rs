//! Motion-only bundle adjustment: the pose of one camera against fixed map
//! points, as ORB-SLAM's `Optimizer::PoseOptimization` does it.
//!
//! Four rounds of ten LM iterations each. After each round every
//! observation (including those set aside earlier) is classified by its
//! chi2 against `5.991` (95 %, 2 DoF); outliers take no part in the next
//! round. The first three rounds use a Huber kernel (`δ = √5.991`), the
//! last none. Unlike ORB-SLAM2, which restarts every round from the initial
//! pose, each round here continues from the previous round's estimate.

use nalgebra::{Isometry3, Matrix6, Point2, Point3, Vector6};

use super::lm::{LeastSquares, LmParams, LmSummary, levenberg_marquardt, solve_damped_dense};
use super::{Intrinsics, OptimizeError, RobustKernel, valid_obs};
use crate::lie::{se3_exp, skew};

/// A map point with its observation in the frame being optimised.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseObservation {
    /// The point, world frame (held fixed).
    pub p_world: Point3<f64>,
    /// Its undistorted pixel.
    pub uv: Point2<f64>,
    /// `1/σ²` of the keypoint's octave.
    pub inv_sigma2: f64,
}

/// Tunables of [`optimize_pose`]. Defaults are ORB-SLAM's.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseParams {
    /// Rounds of optimisation + classification.
    pub rounds: usize,
    /// Rounds (from the first) that use the Huber kernel.
    pub robust_rounds: usize,
    /// Chi2 above which an observation is an outlier (2 DoF, 95 %).
    pub chi2_threshold: f64,
    /// Huber threshold on `√chi2`.
    pub huber_delta: f64,
    /// Stop the rounds when fewer inliers than this remain.
    pub min_inliers: usize,
    /// Points closer than this (camera z) count as behind the camera.
    pub min_depth: f64,
    /// LM settings of each round (`max_iterations` = iterations per round).
    pub lm: LmParams,
}

impl Default for PoseParams {
    fn default() -> Self {
        Self {
            rounds: 4,
            robust_rounds: 3,
            chi2_threshold: 5.991,
            huber_delta: 5.991f64.sqrt(),
            min_inliers: 10,
            min_depth: 1e-6,
            lm: LmParams::default(),
        }
    }
}

/// The result of [`optimize_pose`].
#[derive(Debug, Clone, PartialEq)]
pub struct PoseReport {
    /// The optimised pose.
    pub cam_from_world: Isometry3<f64>,
    /// Per observation: inlier after the last round.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub n_inliers: usize,
    /// LM steps tried over all rounds.
    pub iterations: usize,
    /// The last round's LM summary.
    pub last_round: LmSummary,
}

/// Chi2 (`rᵀr·inv_sigma2`) of one observation, `None` behind the camera.
#[inline]
pub fn observation_chi2(
    cam_from_world: &Isometry3<f64>,
    intr: &Intrinsics,
    obs: &PoseObservation,
    min_depth: f64,
) -> Option<f64> {
    let pc = cam_from_world.transform_point(&obs.p_world).coords;
    if pc.z <= min_depth {
        return None;
    }
    let r = intr.project(&pc) - obs.uv;
    Some(r.norm_squared() * obs.inv_sigma2)
}

/// The pose-only least-squares problem (6 unknowns).
pub(crate) struct PoseProblem<'a> {
    pub obs: &'a [PoseObservation],
    pub active: &'a [bool],
    pub intr: Intrinsics,
    pub kernel: RobustKernel,
    pub min_depth: f64,
    /// Chi2 charged to an active point behind the camera (no gradient).
    pub behind_chi2: f64,
    pub cam_from_world: Isometry3<f64>,
    old: Isometry3<f64>,
    h: Matrix6<f64>,
    g: Vector6<f64>,
    step: Vector6<f64>,
}

impl<'a> PoseProblem<'a> {
    pub fn new(
        cam_from_world: Isometry3<f64>,
        obs: &'a [PoseObservation],
        active: &'a [bool],
        intr: Intrinsics,
        kernel: RobustKernel,
        min_depth: f64,
    ) -> Self {
        Self {
            obs,
            active,
            intr,
            kernel,
            min_depth,
            behind_chi2: 1e4,
            cam_from_world,
            old: cam_from_world,
            h: Matrix6::zeros(),
            g: Vector6::zeros(),
            step: Vector6::zeros(),
        }
    }
}

impl LeastSquares for PoseProblem<'_> {
    fn linearize(&mut self) -> (f64, f64) {
        let mut h = Matrix6::zeros();
        let mut g = Vector6::zeros();
        let mut cost = 0.0;
        let rot = self.cam_from_world.rotation.to_rotation_matrix();
        let t = self.cam_from_world.translation.vector;
        for (o, _) in self.obs.iter().zip(self.active).filter(|(_, a)| **a) {
            let pc = rot * o.p_world.coords + t;
            if pc.z <= self.min_depth {
                cost += 0.5 * self.kernel.eval(self.behind_chi2).0;
                continue;
            }
            let r = self.intr.project(&pc) - o.uv;
            let s = r.norm_squared() * o.inv_sigma2;
            let (rho, drho) = self.kernel.eval(s);
            cost += 0.5 * rho;
            let w = drho * o.inv_sigma2;
            let jp = self.intr.project_jacobian(&pc);
            // ∂pc/∂δ = [I | -[pc]ₓ]
            let jr = -(jp * skew(&pc));
            let mut j = nalgebra::Matrix2x6::zeros();
            j.fixed_view_mut::<2, 3>(0, 0).copy_from(&jp);
            j.fixed_view_mut::<2, 3>(0, 3).copy_from(&jr);
            let jt = j.transpose();
            h += jt * j * w;
            g += jt * r * w;
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
        self.old = self.cam_from_world;
        self.cam_from_world = se3_exp(&self.step) * self.cam_from_world;
    }

    fn revert_step(&mut self) {
        self.cam_from_world = self.old;
    }

    fn cost(&mut self) -> f64 {
        let mut cost = 0.0;
        for (o, _) in self.obs.iter().zip(self.active).filter(|(_, a)| **a) {
            let s = observation_chi2(&self.cam_from_world, &self.intr, o, self.min_depth)
                .unwrap_or(self.behind_chi2);
            cost += 0.5 * self.kernel.eval(s).0;
        }
        cost
    }

    fn state_norm(&self) -> f64 {
        (self.cam_from_world.translation.vector.norm_squared()
            + self.cam_from_world.rotation.scaled_axis().norm_squared())
        .sqrt()
    }
}

/// Refines a pose on the `active` observations with one LM run and the
/// given kernel (no outlier classification). Used by PnP.
pub fn refine_pose(
    cam_from_world: Isometry3<f64>,
    obs: &[PoseObservation],
    active: &[bool],
    intr: &Intrinsics,
    kernel: RobustKernel,
    lm: &LmParams,
) -> (Isometry3<f64>, LmSummary) {
    let mut p = PoseProblem::new(cam_from_world, obs, active, *intr, kernel, 1e-6);
    let s = levenberg_marquardt(&mut p, lm);
    (p.cam_from_world, s)
}

/// Motion-only BA (see the module documentation).
///
/// Errors: [`OptimizeError::NotEnoughObservations`] with fewer than 3
/// observations, [`OptimizeError::InvalidInput`] for a non-finite value or
/// a non-positive weight.
pub fn optimize_pose(
    cam_from_world: Isometry3<f64>,
    obs: &[PoseObservation],
    intr: &Intrinsics,
    params: &PoseParams,
) -> Result<PoseReport, OptimizeError> {
    if obs.len() < 3 {
        return Err(OptimizeError::NotEnoughObservations {
            found: obs.len(),
            needed: 3,
        });
    }
    if !intr.is_valid() {
        return Err(OptimizeError::InvalidInput {
            what: "intrinsics",
            index: 0,
        });
    }
    for (i, o) in obs.iter().enumerate() {
        let p = &o.p_world;
        if !valid_obs(&o.uv, o.inv_sigma2)
            || !p.x.is_finite()
            || !p.y.is_finite()
            || !p.z.is_finite()
        {
            return Err(OptimizeError::InvalidInput {
                what: "observation",
                index: i,
            });
        }
    }
    let mut active = vec![true; obs.len()];
    let mut pose = cam_from_world;
    let mut iterations = 0;
    let mut last = None;
    let huber = RobustKernel::Huber {
        delta: params.huber_delta,
    };
    for round in 0..params.rounds {
        let kernel = if round < params.robust_rounds {
            huber
        } else {
            RobustKernel::None
        };
        let mut problem = PoseProblem::new(pose, obs, &active, *intr, kernel, params.min_depth);
        let s = levenberg_marquardt(&mut problem, &params.lm);
        pose = problem.cam_from_world;
        iterations += s.iterations;
        last = Some(s);
        let mut n_in = 0;
        for (o, a) in obs.iter().zip(active.iter_mut()) {
            let ok = observation_chi2(&pose, intr, o, params.min_depth)
                .is_some_and(|c| c <= params.chi2_threshold);
            *a = ok;
            n_in += usize::from(ok);
        }
        if n_in < params.min_inliers {
            break;
        }
    }
    let n_inliers = active.iter().filter(|&&a| a).count();
    Ok(PoseReport {
        cam_from_world: pose,
        inliers: active,
        n_inliers,
        iterations,
        last_round: last.unwrap_or(LmSummary {
            iterations: 0,
            accepted: 0,
            initial_cost: 0.0,
            final_cost: 0.0,
            termination: super::lm::Termination::MaxIterations,
        }),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    fn intr() -> Intrinsics {
        Intrinsics {
            fx: 520.0,
            fy: 515.0,
            cx: 320.0,
            cy: 240.0,
        }
    }

    #[test]
    fn pose_jacobian_matches_finite_differences() {
        let obs = [PoseObservation {
            p_world: Point3::new(0.4, -0.3, 4.0),
            uv: Point2::new(300.0, 200.0),
            inv_sigma2: 1.0,
        }];
        let active = [true];
        let pose = Isometry3::from_parts(
            Translation3::new(0.1, 0.2, -0.3),
            UnitQuaternion::from_euler_angles(0.1, -0.05, 0.2),
        );
        let mut p = PoseProblem::new(pose, &obs, &active, intr(), RobustKernel::None, 1e-6);
        p.linearize();
        // With one observation and no kernel: g = Jᵀr, H = JᵀJ. Recover J by
        // finite differences of the residual and compare.
        let res = |t: &Isometry3<f64>| {
            let pc = t.transform_point(&obs[0].p_world).coords;
            intr().project(&pc) - obs[0].uv
        };
        let r0 = res(&pose);
        let mut jfd = nalgebra::Matrix2x6::zeros();
        for k in 0..6 {
            let mut d = Vector6::zeros();
            d[k] = 1e-7;
            let rp = res(&(se3_exp(&d) * pose));
            let rm = res(&(se3_exp(&(-d)) * pose));
            jfd.set_column(k, &((rp - rm) / 2e-7));
        }
        let h_fd = jfd.transpose() * jfd;
        let g_fd = jfd.transpose() * r0;
        assert!((h_fd - p.h).norm() < 1e-5 * p.h.norm(), "{h_fd} vs {}", p.h);
        assert!((g_fd - p.g).norm() < 1e-5 * p.g.norm().max(1.0));
    }

    /// The per-octave weights decide the classification: a 3.5 px error is
    /// an outlier at octave 0 (chi2 12.25 > 5.991) and an inlier at octave 5
    /// of a 1.2 pyramid (σ² = 1.2¹⁰ ≈ 6.19, chi2 ≈ 1.98).
    #[test]
    fn octave_weights_decide_outliers() {
        let k = intr();
        let truth = Isometry3::identity();
        let mut obs = Vec::new();
        for i in 0..60 {
            let pc = Vector3::new(
                -1.5 + 0.05 * i as f64,
                ((i * 7) % 11) as f64 * 0.2 - 1.0,
                4.0 + (i % 5) as f64,
            );
            obs.push(PoseObservation {
                p_world: Point3::from(pc),
                uv: k.project(&pc),
                inv_sigma2: 1.0,
            });
        }
        let mut probe_low = obs[0];
        probe_low.uv.x += 3.5;
        let mut probe_high = obs[1];
        probe_high.uv.x += 3.5;
        probe_high.inv_sigma2 = 1.0 / 1.2f64.powi(10);
        obs[0] = probe_low;
        obs[1] = probe_high;
        let rep = optimize_pose(truth, &obs, &k, &PoseParams::default()).unwrap();
        assert!(!rep.inliers[0], "octave-0 3.5 px error kept");
        assert!(rep.inliers[1], "octave-5 3.5 px error rejected");
        assert_eq!(rep.n_inliers, 59);
    }

    #[test]
    fn recovers_pose_and_rejects_outliers() {
        let mut rng = SmallRng::seed_from_u64(3);
        let truth = Isometry3::from_parts(
            Translation3::new(0.2, -0.1, 0.5),
            UnitQuaternion::from_euler_angles(0.05, 0.1, -0.08),
        );
        let k = intr();
        let mut obs = Vec::new();
        for i in 0..300 {
            let pc = Vector3::new(
                rng.random_range(-2.0..2.0),
                rng.random_range(-1.5..1.5),
                rng.random_range(3.0..8.0),
            );
            let pw = truth.inverse_transform_point(&Point3::from(pc));
            let mut uv = k.project(&pc);
            uv.x += rng.random_range(-1.0..1.0);
            uv.y += rng.random_range(-1.0..1.0);
            if i % 5 == 0 {
                uv.x += rng.random_range(20.0..60.0);
            }
            obs.push(PoseObservation {
                p_world: pw,
                uv,
                inv_sigma2: 1.0,
            });
        }
        let init = Isometry3::from_parts(
            Translation3::new(0.35, -0.2, 0.3),
            UnitQuaternion::from_euler_angles(0.1, 0.05, -0.02),
        );
        let rep = optimize_pose(init, &obs, &k, &PoseParams::default()).unwrap();
        let dr = rep
            .cam_from_world
            .rotation
            .angle_to(&truth.rotation)
            .to_degrees();
        let dt = (rep.cam_from_world.translation.vector - truth.translation.vector).norm();
        assert!(dr < 0.1 && dt < 0.02, "{dr} deg, {dt} m");
        // Every injected outlier is caught; few inliers lost.
        for (i, &inl) in rep.inliers.iter().enumerate() {
            if i % 5 == 0 {
                assert!(!inl, "outlier {i} kept");
            }
        }
        assert!(rep.n_inliers >= 230, "{}", rep.n_inliers);
    }
}
