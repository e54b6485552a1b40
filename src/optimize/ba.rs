//! Local bundle adjustment over keyframes and points.
//!
//! Each LM step solves the damped normal equations
//!
//! ```text
//! [ A   W ] [δc]   [-g_c]        A: 6×6 blocks per free pose (block-diagonal)
//! [ Wᵀ  C ] [δp] = [-g_p]        C: 3×3 blocks per point (block-diagonal)
//! ```
//!
//! by eliminating the points (Schur complement):
//! `S = A - Σ_j W_j·C_j⁻¹·W_jᵀ`, `S·δc = -g_c + Σ_j W_j·C_j⁻¹·g_p,j`,
//! solved by faer's dense Cholesky (`llt`), then back-substituting
//! `δp_j = C_j⁻¹·(-g_p,j - W_jᵀ·δc)`. `W` is never formed as a matrix: the
//! 6×3 block of each observation is kept beside it and the pairs of
//! observations sharing a point fill `S`. Fixed keyframes carry no
//! unknowns (the gauge); their observations still constrain the points.
//!
//! The schedule is ORB-SLAM's `LocalBundleAdjustment`: a first pass with
//! the Huber kernel (5 iterations), then observations with chi2 above
//! `5.991` or behind the camera are set aside, and a second pass without
//! kernel (10 iterations) refines on the rest; the observations that are
//! outliers at the end are reported so the map can drop them.
//!
//! Position priors ([`PositionPrior`], e.g. a GNSS fix and a barometric
//! altitude) pull a free keyframe's camera centre `c = -Rᵀt` towards a
//! measured position with an information matrix `Ω`: the residual
//! `c - c_meas` costs `ρ(rᵀΩr)` under [`BaParams::prior_kernel`] (Huber by
//! default, so a fix far off weighs linearly) in both passes. Under the
//! left perturbation `T ← exp(δ)·T`, `∂c/∂δ = [-Rᵀ, 0]`: a prior adds
//! `R·Ω·Rᵀ` to the translation block of its pose and nothing to the points.

use faer::prelude::Solve;
use faer::{Col, Mat, Side};
use nalgebra::{
    Isometry3, Matrix2x3, Matrix3, Matrix6, Matrix6x3, Point2, Point3, Vector2, Vector3, Vector6,
};

use super::lm::{LeastSquares, LmParams, LmSummary, levenberg_marquardt};
use super::shutter::{PoseShutter, RowMotion, camera_point, twist_between};
use super::{Intrinsics, OptimizeError, RobustKernel, valid_obs};
use crate::lie::{se3_exp, skew};

/// A keyframe pose in the problem.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaPose {
    /// The keyframe's pose.
    pub cam_from_world: Isometry3<f64>,
    /// Held fixed (gauge, or a keyframe outside the local window).
    pub fixed: bool,
    /// The camera's motion over a rolling shutter's readout (none: a
    /// global shutter): each observation is seen from its row's pose
    /// ([`super::shutter`]), the motion following the poses it is taken
    /// between at every step.
    pub shutter: Option<PoseShutter>,
}

/// Takes every pose's rolling-shutter motion again from the poses it
/// follows ([`PoseShutter::between`]), as they stand: when a problem is
/// set up for solving and wherever a step moves the poses (taken or
/// reverted), so the motions always match the poses the cost is read at.
fn follow_shutters(problem: &mut BaProblem) {
    for i in 0..problem.poses.len() {
        let Some(PoseShutter {
            motion,
            between: Some((a, b, dt)),
        }) = problem.poses[i].shutter
        else {
            continue;
        };
        let (Some(first), Some(second)) = (problem.poses.get(a), problem.poses.get(b)) else {
            continue;
        };
        let (linear, angular) = twist_between(
            &first.cam_from_world,
            &second.cam_from_world,
            &problem.poses[i].cam_from_world,
            dt,
        );
        if linear.iter().chain(angular.iter()).all(|v| v.is_finite()) {
            problem.poses[i].shutter = Some(PoseShutter {
                motion: RowMotion {
                    linear,
                    angular,
                    ..motion
                },
                between: Some((a, b, dt)),
            });
        }
    }
}

/// The pose's row motion, if it has a rolling shutter.
#[inline]
fn row_motion(pose: &BaPose) -> Option<&RowMotion> {
    pose.shutter.as_ref().map(|s| &s.motion)
}

/// One observation of a point by a keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Observation {
    /// Index into [`BaProblem::poses`].
    pub pose: usize,
    /// Index into [`BaProblem::points`].
    pub point: usize,
    /// Undistorted pixel.
    pub uv: Point2<f64>,
    /// `1/σ²` of the keypoint's octave.
    pub inv_sigma2: f64,
}

/// A prior on a keyframe's camera centre: `information` is the inverse
/// covariance of `centre` (metres, world frame); a singular one constrains
/// only some directions (a barometric altitude: `diag(0, 0, 1/σ²)`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionPrior {
    /// Index into [`BaProblem::poses`] (ignored when that pose is fixed).
    pub pose: usize,
    /// The measured camera centre, world frame.
    pub centre: Point3<f64>,
    /// Its information matrix (symmetric, positive semi-definite).
    pub information: Matrix3<f64>,
}

/// A bundle-adjustment problem; optimised in place.
#[derive(Debug, Clone, PartialEq)]
pub struct BaProblem {
    /// Keyframe poses (`cam_from_world`), some fixed.
    pub poses: Vec<BaPose>,
    /// Map points, world frame.
    pub points: Vec<Point3<f64>>,
    /// Observations.
    pub observations: Vec<Observation>,
    /// Pinhole intrinsics shared by all keyframes.
    pub intrinsics: Intrinsics,
    /// Priors on camera centres (empty: vision only).
    pub priors: Vec<PositionPrior>,
}

/// Tunables of [`local_bundle_adjustment`]. Defaults are ORB-SLAM's.
#[derive(Debug, Clone, PartialEq)]
pub struct BaParams {
    /// LM iterations of the robust first pass.
    pub first_pass_iterations: usize,
    /// LM iterations of the second pass (0: no second pass).
    pub second_pass_iterations: usize,
    /// Robust kernel of the first pass.
    pub kernel: RobustKernel,
    /// Chi2 above which an observation is an outlier (2 DoF, 95 %).
    pub outlier_chi2: f64,
    /// Points closer than this (camera z) count as behind the camera.
    pub min_depth: f64,
    /// LM settings (its `max_iterations` is overridden by the passes).
    pub lm: LmParams,
    /// Robust kernel of the position priors (both passes), on `rᵀΩr`.
    pub prior_kernel: RobustKernel,
}

impl Default for BaParams {
    fn default() -> Self {
        Self {
            first_pass_iterations: 5,
            second_pass_iterations: 10,
            kernel: RobustKernel::Huber {
                delta: 5.991f64.sqrt(),
            },
            outlier_chi2: 5.991,
            min_depth: 1e-6,
            lm: LmParams::default(),
            // 3 DoF, 95 %.
            prior_kernel: RobustKernel::Huber {
                delta: 7.815f64.sqrt(),
            },
        }
    }
}

/// What [`local_bundle_adjustment`] did.
#[derive(Debug, Clone, PartialEq)]
pub struct BaReport {
    /// Per observation: outlier at the end (chi2 above the threshold or
    /// behind the camera). The caller should erase these from the map.
    pub outliers: Vec<bool>,
    /// Number of outliers.
    pub n_outliers: usize,
    /// Reprojection RMSE (pixels, per coordinate) over all observations in
    /// front of the camera, before.
    pub initial_rmse_px: f64,
    /// The same over the final inliers, after.
    pub final_rmse_px: f64,
    /// The first pass.
    pub first_pass: LmSummary,
    /// The second pass, if run.
    pub second_pass: Option<LmSummary>,
}

/// Per-observation linearisation.
#[derive(Clone, Copy)]
struct ObsLin {
    /// Weighted residual `w·r`.
    wr: Vector2<f64>,
    /// Pose Jacobian (2×6), rows premultiplied by nothing.
    jc: nalgebra::Matrix2x6<f64>,
    /// `W_ij = Jcᵀ·w·Jp` (6×3).
    wblock: Matrix6x3<f64>,
    /// Free-pose index of the observing keyframe (`usize::MAX` if fixed).
    free_pose: usize,
    /// Contributes derivatives (active and in front of the camera).
    live: bool,
}

/// The BA least-squares problem with its Schur-complement solver.
struct BaLs<'a> {
    problem: &'a mut BaProblem,
    active: Vec<bool>,
    kernel: RobustKernel,
    prior_kernel: RobustKernel,
    min_depth: f64,
    behind_chi2: f64,
    /// Free-pose index per pose.
    free: Vec<Option<usize>>,
    n_free: usize,
    /// Observations sorted by point (CSR).
    by_point_start: Vec<usize>,
    by_point: Vec<usize>,
    lin: Vec<ObsLin>,
    a_blocks: Vec<Matrix6<f64>>,
    g_c: Vec<Vector6<f64>>,
    c_blocks: Vec<Matrix3<f64>>,
    g_p: Vec<Vector3<f64>>,
    c_inv: Vec<Matrix3<f64>>,
    step_c: Vec<Vector6<f64>>,
    step_p: Vec<Vector3<f64>>,
    old_poses: Vec<Isometry3<f64>>,
    old_points: Vec<Point3<f64>>,
    sbuf: Vec<f64>,
    s: Mat<f64>,
    rhs: Col<f64>,
}

impl<'a> BaLs<'a> {
    fn new(
        problem: &'a mut BaProblem,
        active: Vec<bool>,
        kernel: RobustKernel,
        min_depth: f64,
    ) -> Self {
        follow_shutters(problem);
        let mut free = vec![None; problem.poses.len()];
        let mut n_free = 0;
        for (f, p) in free.iter_mut().zip(&problem.poses) {
            if !p.fixed {
                *f = Some(n_free);
                n_free += 1;
            }
        }
        let np = problem.points.len();
        let mut counts = vec![0usize; np + 1];
        for o in &problem.observations {
            counts[o.point + 1] += 1;
        }
        for i in 0..np {
            counts[i + 1] += counts[i];
        }
        let mut fill = counts.clone();
        let mut by_point = vec![0usize; problem.observations.len()];
        for (k, o) in problem.observations.iter().enumerate() {
            by_point[fill[o.point]] = k;
            fill[o.point] += 1;
        }
        let nobs = problem.observations.len();
        let zero_lin = ObsLin {
            wr: Vector2::zeros(),
            jc: nalgebra::Matrix2x6::zeros(),
            wblock: Matrix6x3::zeros(),
            free_pose: usize::MAX,
            live: false,
        };
        Self {
            active,
            kernel,
            prior_kernel: BaParams::default().prior_kernel,
            min_depth,
            behind_chi2: 1e4,
            free,
            n_free,
            by_point_start: counts,
            by_point,
            lin: vec![zero_lin; nobs],
            a_blocks: vec![Matrix6::zeros(); n_free],
            g_c: vec![Vector6::zeros(); n_free],
            c_blocks: vec![Matrix3::zeros(); np],
            g_p: vec![Vector3::zeros(); np],
            c_inv: vec![Matrix3::zeros(); np],
            step_c: vec![Vector6::zeros(); n_free],
            step_p: vec![Vector3::zeros(); np],
            old_poses: problem.poses.iter().map(|p| p.cam_from_world).collect(),
            old_points: problem.points.clone(),
            sbuf: Vec::new(),
            s: Mat::zeros(6 * n_free, 6 * n_free),
            rhs: Col::zeros(6 * n_free),
            problem,
        }
    }
}

impl BaLs<'_> {
    /// The reduced camera system at damping `lambda`: `S` (both triangles,
    /// in `self.s`) and its right-hand side (`self.rhs`), the points
    /// eliminated (their `C⁻¹` kept in `self.c_inv`). None when a point's
    /// block cannot be inverted.
    fn fill_schur(&mut self, lambda: f64) -> Option<()> {
        let dim = 6 * self.n_free;
        // Upper block triangle of S, row-major, in a plain buffer (no
        // bounds-checked faer indexing in the hot loop).
        let sbuf = &mut self.sbuf;
        sbuf.clear();
        sbuf.resize(dim * dim, 0.0);
        self.rhs.fill(0.0);
        // Camera diagonal blocks, damped.
        for (fi, a) in self.a_blocks.iter().enumerate() {
            for r in 0..6 {
                let row = (6 * fi + r) * dim + 6 * fi;
                for c in 0..6 {
                    sbuf[row + c] = a[(r, c)];
                }
                sbuf[row + r] += lambda * a[(r, r)].clamp(1e-6, 1e32);
                self.rhs[6 * fi + r] = -self.g_c[fi][r];
            }
        }
        // Eliminate the points.
        for j in 0..self.problem.points.len() {
            let mut c = self.c_blocks[j];
            let mut any = false;
            for i in 0..3 {
                c[(i, i)] += lambda * c[(i, i)].clamp(1e-6, 1e32);
                any |= self.c_blocks[j][(i, i)] > 0.0;
            }
            if !any {
                self.c_inv[j] = Matrix3::zeros();
                continue;
            }
            let cinv = inverse_spd3(&c)?;
            self.c_inv[j] = cinv;
            let obs_j = &self.by_point[self.by_point_start[j]..self.by_point_start[j + 1]];
            let gpj = self.g_p[j];
            for &ka in obs_j {
                let la = &self.lin[ka];
                let fa = la.free_pose;
                if !la.live || fa == usize::MAX {
                    continue;
                }
                let y = la.wblock * cinv;
                // rhs_a -= Y·(-g_p), i.e. rhs_a += Y·g_p
                let yg = y * gpj;
                for r in 0..6 {
                    self.rhs[6 * fa + r] += yg[r];
                }
                for &kb in obs_j {
                    let lb = &self.lin[kb];
                    let fb = lb.free_pose;
                    if !lb.live || fb == usize::MAX || fb < fa {
                        continue;
                    }
                    let blk = y * lb.wblock.transpose();
                    for r in 0..6 {
                        let row = (6 * fa + r) * dim + 6 * fb;
                        let dst = &mut sbuf[row..row + 6];
                        for (c2, d) in dst.iter_mut().enumerate() {
                            *d -= blk[(r, c2)];
                        }
                    }
                }
            }
        }
        let sbuf = &self.sbuf;
        self.s = Mat::from_fn(dim, dim, |r, c| {
            if r <= c {
                sbuf[r * dim + c]
            } else {
                sbuf[c * dim + r]
            }
        });
        Some(())
    }
}

impl LeastSquares for BaLs<'_> {
    fn linearize(&mut self) -> (f64, f64) {
        for a in &mut self.a_blocks {
            *a = Matrix6::zeros();
        }
        for g in &mut self.g_c {
            *g = Vector6::zeros();
        }
        for c in &mut self.c_blocks {
            *c = Matrix3::zeros();
        }
        for g in &mut self.g_p {
            *g = Vector3::zeros();
        }
        let intr = self.problem.intrinsics;
        let rots: Vec<Matrix3<f64>> = self
            .problem
            .poses
            .iter()
            .map(|p| p.cam_from_world.rotation.to_rotation_matrix().into_inner())
            .collect();
        let mut cost = 0.0;
        for (k, o) in self.problem.observations.iter().enumerate() {
            let lin = &mut self.lin[k];
            lin.live = false;
            lin.free_pose = self.free[o.pose].unwrap_or(usize::MAX);
            if !self.active[k] {
                continue;
            }
            let ba_pose = &self.problem.poses[o.pose];
            let pose = &ba_pose.cam_from_world;
            let r_cw = &rots[o.pose];
            let pc = r_cw * self.problem.points[o.point].coords + pose.translation.vector;
            let prow = camera_point(row_motion(ba_pose), o.uv.y, pc);
            if prow.z <= self.min_depth {
                cost += 0.5 * self.kernel.eval(self.behind_chi2).0;
                continue;
            }
            let r = intr.project(&prow) - o.uv;
            let s = r.norm_squared() * o.inv_sigma2;
            let (rho, drho) = self.kernel.eval(s);
            cost += 0.5 * rho;
            let w = drho * o.inv_sigma2;
            // ∂π/∂pc, through the row's motion under a rolling shutter.
            let mut jproj: Matrix2x3<f64> = intr.project_jacobian(&prow);
            if let Some(m) = row_motion(ba_pose) {
                jproj *= m.jacobian(o.uv.y);
            }
            let jp: Matrix2x3<f64> = jproj * r_cw;
            let jpt = jp.transpose();
            self.c_blocks[o.point] += jpt * jp * w;
            self.g_p[o.point] += jpt * r * w;
            lin.live = true;
            lin.wr = r * w;
            if let Some(fi) = self.free[o.pose] {
                let jr = -(jproj * skew(&pc));
                let mut jc = nalgebra::Matrix2x6::zeros();
                jc.fixed_view_mut::<2, 3>(0, 0).copy_from(&jproj);
                jc.fixed_view_mut::<2, 3>(0, 3).copy_from(&jr);
                let jct = jc.transpose();
                self.a_blocks[fi] += jct * jc * w;
                self.g_c[fi] += jct * r * w;
                lin.jc = jc;
                lin.wblock = jct * jp * w;
            }
        }
        for pr in &self.problem.priors {
            let Some(fi) = self.free.get(pr.pose).copied().flatten() else {
                continue;
            };
            let r_cw = &rots[pr.pose];
            let (r, chi2) = prior_residual(&self.problem.poses[pr.pose].cam_from_world, pr);
            let (rho, drho) = self.prior_kernel.eval(chi2);
            cost += 0.5 * rho;
            // J = [-Rᵀ, 0]: JᵀΩJ = RΩRᵀ, JᵀΩr = -RΩr.
            let h = r_cw * pr.information * r_cw.transpose() * drho;
            let g = -(r_cw * (pr.information * r)) * drho;
            let a = &mut self.a_blocks[fi];
            for i in 0..3 {
                for j in 0..3 {
                    a[(i, j)] += h[(i, j)];
                }
                self.g_c[fi][i] += g[i];
            }
        }
        let mut gmax: f64 = 0.0;
        for g in &self.g_c {
            gmax = gmax.max(g.amax());
        }
        for g in &self.g_p {
            gmax = gmax.max(g.amax());
        }
        (cost, gmax)
    }

    fn solve_damped(&mut self, lambda: f64) -> Option<(f64, f64)> {
        let nf = self.n_free;
        let dim = 6 * nf;
        self.fill_schur(lambda)?;
        if dim > 0 {
            let llt = self.s.llt(Side::Lower).ok()?;
            llt.solve_in_place(self.rhs.as_mut());
        }
        let mut pred = 0.0;
        let mut norm2 = 0.0;
        for fi in 0..nf {
            let mut d = Vector6::zeros();
            for r in 0..6 {
                d[r] = self.rhs[6 * fi + r];
            }
            if !d.iter().all(|v| v.is_finite()) {
                return None;
            }
            self.step_c[fi] = d;
            let a = &self.a_blocks[fi];
            for r in 0..6 {
                pred += d[r] * (lambda * a[(r, r)].clamp(1e-6, 1e32) * d[r] - self.g_c[fi][r]);
            }
            norm2 += d.norm_squared();
        }
        // Back-substitution for the points.
        for j in 0..self.problem.points.len() {
            let mut b = -self.g_p[j];
            let obs_j = &self.by_point[self.by_point_start[j]..self.by_point_start[j + 1]];
            for &ka in obs_j {
                if !self.lin[ka].live {
                    continue;
                }
                if let Some(fa) = self.free[self.problem.observations[ka].pose] {
                    b -= self.lin[ka].wblock.transpose() * self.step_c[fa];
                }
            }
            let dp = self.c_inv[j] * b;
            if !dp.iter().all(|v| v.is_finite()) {
                return None;
            }
            self.step_p[j] = dp;
            let c = &self.c_blocks[j];
            for r in 0..3 {
                pred += dp[r] * (lambda * c[(r, r)].clamp(1e-6, 1e32) * dp[r] - self.g_p[j][r]);
            }
            norm2 += dp.norm_squared();
        }
        Some((0.5 * pred, norm2.sqrt()))
    }

    fn apply_step(&mut self) {
        for (i, p) in self.problem.poses.iter_mut().enumerate() {
            self.old_poses[i] = p.cam_from_world;
            if let Some(fi) = self.free[i] {
                p.cam_from_world = se3_exp(&self.step_c[fi]) * p.cam_from_world;
            }
        }
        for (j, p) in self.problem.points.iter_mut().enumerate() {
            self.old_points[j] = *p;
            *p += self.step_p[j];
        }
        follow_shutters(self.problem);
    }

    fn revert_step(&mut self) {
        for (p, o) in self.problem.poses.iter_mut().zip(&self.old_poses) {
            p.cam_from_world = *o;
        }
        self.problem.points.copy_from_slice(&self.old_points);
        follow_shutters(self.problem);
    }

    fn cost(&mut self) -> f64 {
        let mut cost = 0.0;
        for (k, o) in self.problem.observations.iter().enumerate() {
            if !self.active[k] {
                continue;
            }
            let s = obs_chi2(self.problem, o, self.min_depth).unwrap_or(self.behind_chi2);
            cost += 0.5 * self.kernel.eval(s).0;
        }
        for pr in &self.problem.priors {
            if self.free.get(pr.pose).copied().flatten().is_none() {
                continue;
            }
            let (_, chi2) = prior_residual(&self.problem.poses[pr.pose].cam_from_world, pr);
            cost += 0.5 * self.prior_kernel.eval(chi2).0;
        }
        cost
    }

    fn state_norm(&self) -> f64 {
        let mut n2 = 0.0;
        for p in &self.problem.poses {
            n2 += p.cam_from_world.translation.vector.norm_squared()
                + p.cam_from_world.rotation.scaled_axis().norm_squared();
        }
        for p in &self.problem.points {
            n2 += p.coords.norm_squared();
        }
        n2.sqrt()
    }
}

/// A prior's residual `c - c_meas` (c the camera centre) and its `rᵀΩr`.
#[inline]
fn prior_residual(cam_from_world: &Isometry3<f64>, prior: &PositionPrior) -> (Vector3<f64>, f64) {
    let c = -(cam_from_world.rotation.inverse() * cam_from_world.translation.vector);
    let r = c - prior.centre.coords;
    (r, r.dot(&(prior.information * r)))
}

/// Inverse of a symmetric positive-definite 3×3 matrix by cofactors;
/// `None` unless all leading minors are positive.
#[inline]
fn inverse_spd3(m: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    let (a, b, c) = (m[(0, 0)], m[(0, 1)], m[(0, 2)]);
    let (d, e, f) = (m[(1, 1)], m[(1, 2)], m[(2, 2)]);
    let c00 = d * f - e * e;
    let c01 = c * e - b * f;
    let c02 = b * e - c * d;
    let det = a * c00 + b * c01 + c * c02;
    let minor2 = a * d - b * b;
    if a <= 0.0 || minor2 <= 0.0 || det <= 0.0 || !det.is_finite() {
        return None;
    }
    let c11 = a * f - c * c;
    let c12 = b * c - a * e;
    let inv = 1.0 / det;
    Some(Matrix3::new(c00, c01, c02, c01, c11, c12, c02, c12, minor2) * inv)
}

/// The observed point in its camera's coordinates at the observation's
/// row (the pose's own under a global shutter).
#[inline]
fn observed_point(problem: &BaProblem, o: &Observation) -> nalgebra::Vector3<f64> {
    let pose = &problem.poses[o.pose];
    let pc = pose
        .cam_from_world
        .transform_point(&problem.points[o.point])
        .coords;
    camera_point(row_motion(pose), o.uv.y, pc)
}

/// Chi2 of one observation, `None` when the point is behind the camera.
#[inline]
fn obs_chi2(problem: &BaProblem, o: &Observation, min_depth: f64) -> Option<f64> {
    let pc = observed_point(problem, o);
    if pc.z <= min_depth {
        return None;
    }
    let r = problem.intrinsics.project(&pc) - o.uv;
    Some(r.norm_squared() * o.inv_sigma2)
}

/// Reprojection RMSE in pixels per coordinate over observations in front of
/// the camera, restricted to `mask` when given.
pub fn reprojection_rmse(problem: &BaProblem, mask: Option<&[bool]>) -> f64 {
    let mut sum = 0.0;
    let mut n = 0usize;
    for (k, o) in problem.observations.iter().enumerate() {
        if mask.is_some_and(|m| !m[k]) {
            continue;
        }
        let pc = observed_point(problem, o);
        if pc.z <= 0.0 {
            continue;
        }
        sum += (problem.intrinsics.project(&pc) - o.uv).norm_squared();
        n += 1;
    }
    if n == 0 {
        0.0
    } else {
        (sum / (2 * n) as f64).sqrt()
    }
}

fn validate(problem: &BaProblem) -> Result<(), OptimizeError> {
    if !problem.intrinsics.is_valid() {
        return Err(OptimizeError::InvalidInput {
            what: "intrinsics",
            index: 0,
        });
    }
    for (i, p) in problem.points.iter().enumerate() {
        if !(p.x.is_finite() && p.y.is_finite() && p.z.is_finite()) {
            return Err(OptimizeError::InvalidInput {
                what: "point",
                index: i,
            });
        }
    }
    for (i, p) in problem.priors.iter().enumerate() {
        if p.pose >= problem.poses.len()
            || !p.centre.coords.iter().all(|v| v.is_finite())
            || !p.information.iter().all(|v| v.is_finite())
        {
            return Err(OptimizeError::InvalidInput {
                what: "position prior",
                index: i,
            });
        }
    }
    for (i, p) in problem.poses.iter().enumerate() {
        let t = &p.cam_from_world.translation.vector;
        let q = &p.cam_from_world.rotation;
        if !(t.iter().all(|v| v.is_finite()) && q.coords.iter().all(|v| v.is_finite())) {
            return Err(OptimizeError::InvalidInput {
                what: "pose",
                index: i,
            });
        }
        if let Some(PoseShutter {
            between: Some((a, b, dt)),
            ..
        }) = p.shutter
            && (a >= problem.poses.len() || b >= problem.poses.len() || dt.is_nan() || dt <= 0.0)
        {
            return Err(OptimizeError::InvalidInput {
                what: "rolling-shutter neighbours",
                index: i,
            });
        }
    }
    for (k, o) in problem.observations.iter().enumerate() {
        if o.pose >= problem.poses.len() {
            return Err(OptimizeError::IndexOutOfRange {
                observation: k,
                what: "pose",
                index: o.pose,
                len: problem.poses.len(),
            });
        }
        if o.point >= problem.points.len() {
            return Err(OptimizeError::IndexOutOfRange {
                observation: k,
                what: "point",
                index: o.point,
                len: problem.points.len(),
            });
        }
        if !valid_obs(&o.uv, o.inv_sigma2) {
            return Err(OptimizeError::InvalidInput {
                what: "observation",
                index: k,
            });
        }
    }
    if problem.poses.iter().all(|p| p.fixed) && problem.points.is_empty() {
        return Err(OptimizeError::NothingToOptimize);
    }
    Ok(())
}

/// Runs local bundle adjustment in place (see the module documentation)
/// and reports the outlier observations.
///
/// Errors: [`OptimizeError::IndexOutOfRange`], [`OptimizeError::InvalidInput`],
/// [`OptimizeError::NothingToOptimize`].
pub fn local_bundle_adjustment(
    problem: &mut BaProblem,
    params: &BaParams,
) -> Result<BaReport, OptimizeError> {
    validate(problem)?;
    let nobs = problem.observations.len();
    let (initial_rmse_px, first_pass) = {
        let mut ls = BaLs::new(problem, vec![true; nobs], params.kernel, params.min_depth);
        let initial = reprojection_rmse(ls.problem, None);
        ls.prior_kernel = params.prior_kernel;
        let summary = levenberg_marquardt(
            &mut ls,
            &LmParams {
                max_iterations: params.first_pass_iterations,
                ..params.lm.clone()
            },
        );
        (initial, summary)
    };
    let classify = |problem: &BaProblem| -> Vec<bool> {
        problem
            .observations
            .iter()
            .map(|o| {
                obs_chi2(problem, o, params.min_depth).is_some_and(|c| c <= params.outlier_chi2)
            })
            .collect()
    };
    let mut inliers = classify(problem);
    let second_pass = if params.second_pass_iterations > 0 {
        let mut ls = BaLs::new(
            problem,
            inliers.clone(),
            RobustKernel::None,
            params.min_depth,
        );
        ls.prior_kernel = params.prior_kernel;
        let s = levenberg_marquardt(
            &mut ls,
            &LmParams {
                max_iterations: params.second_pass_iterations,
                ..params.lm.clone()
            },
        );
        inliers = classify(problem);
        Some(s)
    } else {
        None
    };
    let outliers: Vec<bool> = inliers.iter().map(|&i| !i).collect();
    let n_outliers = outliers.iter().filter(|&&o| o).count();
    Ok(BaReport {
        final_rmse_px: reprojection_rmse(problem, Some(&inliers)),
        outliers,
        n_outliers,
        initial_rmse_px,
        first_pass,
        second_pass,
    })
}

/// The free poses' camera-centre covariances after a similarity alignment
/// of those centres (what an absolute trajectory error against the truth
/// measures, after its Sim(3) fit), for observations whose pixel error is
/// `noise_px` at the keypoints' octave-0 scale: the bundle adjustment's
/// Gauss-Newton information at the current solution (observations with
/// chi2 above [`BaParams::outlier_chi2`] or behind the camera left out),
/// the points eliminated (the reduced camera system `S`), its
/// pseudo-inverse over the directions the data fix (the 7 smallest
/// eigenvalues, a monocular map's similarity gauge, left out when no pose
/// is fixed), taken to the centres (`δc = -Rᵀ·δt`) and projected off the
/// centres' own similarity motions (translation, rotation about and scale
/// from their mean). One 3×3 block per free pose, in problem order. None
/// without a free pose, with fewer than three, or when a point's block or
/// the eigendecomposition fails.
pub fn aligned_centre_covariances(
    problem: &mut BaProblem,
    noise_px: f64,
) -> Option<Vec<Matrix3<f64>>> {
    validate(problem).ok()?;
    let params = BaParams::default();
    let active: Vec<bool> = problem
        .observations
        .iter()
        .map(|o| obs_chi2(problem, o, params.min_depth).is_some_and(|c| c <= params.outlier_chi2))
        .collect();
    let any_fixed = problem.poses.iter().any(|p| p.fixed);
    let mut ls = BaLs::new(problem, active, RobustKernel::None, params.min_depth);
    let n = ls.n_free;
    if n < 3 {
        return None;
    }
    // A point seen once (or from one place) has no depth: its
    // observations say nothing of the cameras and leave its block
    // singular; they are left out.
    ls.linearize();
    let singular: Vec<usize> = (0..ls.problem.points.len())
        .filter(|&j| {
            let e = ls.c_blocks[j].symmetric_eigenvalues();
            let conditioned = e.min() > 1e-9 * e.max();
            !conditioned
        })
        .collect();
    if !singular.is_empty() {
        for &j in &singular {
            for &k in &ls.by_point[ls.by_point_start[j]..ls.by_point_start[j + 1]] {
                ls.active[k] = false;
            }
        }
        ls.linearize();
    }
    ls.fill_schur(0.0)?;
    let evd = ls.s.self_adjoint_eigen(Side::Lower).ok()?;
    let (u, lambdas) = (evd.U(), evd.S().column_vector());
    let dim = 6 * n;
    // Sorted nondecreasing: the largest is the last.
    let top = if dim > 0 { lambdas[dim - 1] } else { 0.0 };
    let skip = if any_fixed { 0 } else { 7 };
    // The centres' rows of U, turned into the world frame: M = J_c·U.
    let free_rots: Vec<Matrix3<f64>> = ls
        .problem
        .poses
        .iter()
        .filter(|p| !p.fixed)
        .map(|p| p.cam_from_world.rotation.to_rotation_matrix().into_inner())
        .collect();
    let centres: Vec<Vector3<f64>> = ls
        .problem
        .poses
        .iter()
        .filter(|p| !p.fixed)
        .map(|p| p.cam_from_world.inverse().translation.vector)
        .collect();
    let mut m = nalgebra::DMatrix::<f64>::zeros(3 * n, dim);
    let mut kept = 0;
    for k in skip..dim {
        let l = lambdas[k];
        let kept_direction = l > top * 1e-12;
        if !kept_direction {
            continue;
        }
        let w = (noise_px * noise_px / l).sqrt();
        for (i, r) in free_rots.iter().enumerate() {
            let t = Vector3::new(u[(6 * i, k)], u[(6 * i + 1, k)], u[(6 * i + 2, k)]);
            let c = -(r.transpose() * t) * w;
            for a in 0..3 {
                m[(3 * i + a, kept)] = c[a];
            }
        }
        kept += 1;
    }
    let m = m.columns(0, kept).into_owned();
    // The centres' similarity motions, G (3n × 7), and Q = I - G·G⁺.
    let mean = centres.iter().sum::<Vector3<f64>>() / n as f64;
    let mut g = nalgebra::DMatrix::<f64>::zeros(3 * n, 7);
    for (i, c) in centres.iter().enumerate() {
        let d = c - mean;
        let rot = -skew(&d);
        for a in 0..3 {
            g[(3 * i + a, a)] = 1.0;
            for b in 0..3 {
                g[(3 * i + a, 3 + b)] = rot[(a, b)];
            }
            g[(3 * i + a, 6)] = d[a];
        }
    }
    let pinv = g.clone().pseudo_inverse(1e-12).ok()?;
    let qm = &m - &g * (&pinv * &m);
    // Only each centre's own block of Q·M·Mᵀ·Qᵀ.
    Some(
        (0..n)
            .map(|i| {
                let rows = qm.rows(3 * i, 3);
                let block = rows * rows.transpose();
                Matrix3::from_fn(|r, c| block[(r, c)])
            })
            .collect(),
    )
}

/// Runs plain LM (no outlier passes) with the given kernel until a stopping
/// rule fires; returns the summary. Useful for batch refinement and tests.
pub fn bundle_adjust_lm(
    problem: &mut BaProblem,
    kernel: RobustKernel,
    lm: &LmParams,
) -> Result<LmSummary, OptimizeError> {
    validate(problem)?;
    let nobs = problem.observations.len();
    let mut ls = BaLs::new(problem, vec![true; nobs], kernel, 1e-6);
    Ok(levenberg_marquardt(&mut ls, lm))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn spd3_inverse_is_an_inverse_and_refuses_indefinite() {
        let m = Matrix3::new(4.0, 1.0, 0.5, 1.0, 3.0, -0.2, 0.5, -0.2, 2.0);
        let inv = inverse_spd3(&m).unwrap();
        assert!((m * inv - Matrix3::identity()).norm() < 1e-12);
        let bad = Matrix3::new(1.0, 2.0, 0.0, 2.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        assert!(inverse_spd3(&bad).is_none());
    }

    /// A survey strip seen from 30 m straight down: the true poses and
    /// ground points, and the observations with a deterministic pixel noise.
    fn survey_strip() -> (BaProblem, Vec<Vector3<f64>>) {
        let intr = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        };
        // Camera x east, y south, z down.
        let r_wc = nalgebra::Rotation3::from_matrix_unchecked(Matrix3::new(
            0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0,
        ));
        let centres: Vec<Vector3<f64>> = (0..10)
            .map(|k| {
                let k = k as f64;
                Vector3::new(5.0 * k, 0.3 * k * k, -30.0 - 0.5 * k)
            })
            .collect();
        let poses: Vec<BaPose> = centres
            .iter()
            .enumerate()
            .map(|(i, c)| BaPose {
                cam_from_world: Isometry3::from_parts(
                    Translation3::from(*c),
                    UnitQuaternion::from_rotation_matrix(&r_wc),
                )
                .inverse(),
                fixed: i == 0,
                shutter: None,
            })
            .collect();
        let mut points = Vec::new();
        for a in 0..30 {
            for b in 0..14 {
                let (x, y) = (
                    -15.0 + 2.3 * a as f64,
                    -14.0 + 2.9 * b as f64 + 0.3 * a as f64,
                );
                let h = -((a * 7 + b * 13) % 11) as f64;
                points.push(Point3::new(x, y, h));
            }
        }
        let mut observations = Vec::new();
        for (i, p) in poses.iter().enumerate() {
            for (j, x) in points.iter().enumerate() {
                let pc = p.cam_from_world.transform_point(x).coords;
                let uv = intr.project(&pc);
                if pc.z <= 0.0 || !(0.0..640.0).contains(&uv.x) || !(0.0..480.0).contains(&uv.y) {
                    continue;
                }
                let n = ((i * 31 + j * 17) % 9) as f64 / 8.0 - 0.5;
                let m = ((i * 13 + j * 29) % 7) as f64 / 6.0 - 0.5;
                observations.push(Observation {
                    pose: i,
                    point: j,
                    uv: Point2::new(uv.x + n, uv.y + m),
                    inv_sigma2: 1.0,
                });
            }
        }
        let problem = BaProblem {
            poses,
            points,
            observations,
            intrinsics: intr,
            priors: Vec::new(),
        };
        (problem, centres)
    }

    /// The centres' covariance a solved strip reports is what its error
    /// against the truth is after a Sim(3) fit, over many draws of the
    /// pixel noise (Monte Carlo; all poses free, so the gauge is the
    /// similarity the fit removes).
    #[test]
    fn aligned_centre_covariances_predict_the_aligned_error() {
        use rand::{Rng, SeedableRng, rngs::SmallRng};
        let (truth, centres) = survey_strip();
        let sigma_px = 1.0;
        let mut rng = SmallRng::seed_from_u64(7);
        let mut gauss = move || {
            let (u, v): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let trials = 40;
        let (mut err2, mut n) = (0.0, 0usize);
        let mut predicted = Vec::new();
        for _ in 0..trials {
            let mut p = truth.clone();
            for pose in p.poses.iter_mut() {
                pose.fixed = false;
            }
            for o in p.observations.iter_mut() {
                let pc = p.poses[o.pose]
                    .cam_from_world
                    .transform_point(&p.points[o.point]);
                let uv = p.intrinsics.project(&pc.coords);
                o.uv = Point2::new(uv.x + sigma_px * gauss(), uv.y + sigma_px * gauss());
            }
            bundle_adjust_lm(
                &mut p,
                RobustKernel::None,
                &LmParams {
                    max_iterations: 30,
                    ..LmParams::default()
                },
            )
            .unwrap();
            let est: Vec<Point3<f64>> = p.poses.iter().map(|q| Point3::from(centre(q))).collect();
            let tru: Vec<Point3<f64>> = centres.iter().map(|c| Point3::from(*c)).collect();
            let sim = crate::geometry::umeyama(&est, &tru, true).unwrap();
            for (e, t) in est.iter().zip(&tru) {
                // In the estimate's units, as the covariance is.
                err2 += ((sim.transform_point(e) - t) / sim.scale).norm_squared();
                n += 1;
            }
            let covs = aligned_centre_covariances(&mut p, sigma_px).unwrap();
            assert_eq!(covs.len(), 10);
            predicted.push(covs.iter().map(|c| c.trace()).sum::<f64>() / covs.len() as f64);
        }
        let measured = (err2 / n as f64).sqrt();
        let predicted = (predicted.iter().sum::<f64>() / trials as f64).sqrt();
        let ratio = predicted / measured;
        assert!(
            (0.8..1.25).contains(&ratio),
            "predicted {predicted} measured {measured}"
        );
        // A fixed pose holds the gauge but for the scale: the other nine
        // centres' error once aligned is about what the free problem says
        // of them (it is gauge-free; the fixed one's own error is gone;
        // measured 0.96 times).
        let mut free = truth.clone();
        for pose in free.poses.iter_mut() {
            pose.fixed = false;
        }
        let all = aligned_centre_covariances(&mut free, sigma_px).unwrap();
        let mut p = truth.clone();
        let fixed = aligned_centre_covariances(&mut p, sigma_px).unwrap();
        assert_eq!(fixed.len(), 9);
        let rms =
            |c: &[Matrix3<f64>]| (c.iter().map(|c| c.trace()).sum::<f64>() / c.len() as f64).sqrt();
        let (held, loose) = (rms(&fixed), rms(&all[1..]));
        assert!(
            (0.85..1.15).contains(&(held / loose)),
            "one pose fixed {held}, none {loose}"
        );
    }

    fn centre(p: &BaPose) -> Vector3<f64> {
        p.cam_from_world.inverse().translation.vector
    }

    /// The strip as monocular vision leaves it: every pose and point
    /// scaled by `s` about the first (fixed) camera.
    fn scaled(problem: &BaProblem, c0: &Vector3<f64>, s: f64) -> BaProblem {
        let mut out = problem.clone();
        for p in out.poses.iter_mut() {
            let c = c0 + (centre(p) - c0) * s;
            let r = p.cam_from_world.rotation;
            p.cam_from_world = Isometry3::from_parts(Translation3::from(-(r * c)), r);
        }
        for x in out.points.iter_mut() {
            *x = Point3::from(c0 + (x.coords - c0) * s);
        }
        out
    }

    fn gnss_priors(centres: &[Vector3<f64>], bias: Vector3<f64>, sigma: f64) -> Vec<PositionPrior> {
        centres
            .iter()
            .enumerate()
            .map(|(i, c)| PositionPrior {
                pose: i,
                centre: Point3::from(c + bias),
                information: Matrix3::identity() / (sigma * sigma),
            })
            .collect()
    }

    /// A map 5 % too long: without priors BA keeps the wrong scale (vision
    /// cannot see it); GNSS priors on every camera (which then fix the
    /// gauge: no pose is held) pull it back within 0.5 %; a biased GNSS
    /// leaves every camera within its bias of the truth, not worse, and the
    /// scale still right.
    #[test]
    fn position_priors_restore_the_metric_scale() {
        let (truth, centres) = survey_strip();
        assert!(truth.observations.len() > 500);
        let params = BaParams {
            first_pass_iterations: 20,
            second_pass_iterations: 20,
            ..BaParams::default()
        };
        let length = |p: &BaProblem| (centre(&p.poses[9]) - centre(&p.poses[0])).norm();
        let true_length = (centres[9] - centres[0]).norm();

        let mut vision = scaled(&truth, &centres[0], 1.05);
        local_bundle_adjustment(&mut vision, &params).unwrap();
        let scale = length(&vision) / true_length;
        assert!((scale - 1.05).abs() < 0.005, "vision-only scale {scale}");

        let free = |mut p: BaProblem| {
            for pose in p.poses.iter_mut() {
                pose.fixed = false;
            }
            p
        };
        let mut aided = free(scaled(&truth, &centres[0], 1.05));
        aided.priors = gnss_priors(&centres, Vector3::zeros(), 0.1);
        let report = local_bundle_adjustment(&mut aided, &params).unwrap();
        let scale = length(&aided) / true_length;
        assert!((scale - 1.0).abs() < 0.005, "aided scale {scale}");
        assert!(report.final_rmse_px < 0.5, "{report:?}");

        let bias = Vector3::new(1.0, -0.6, 0.4);
        let mut biased = free(scaled(&truth, &centres[0], 1.05));
        biased.priors = gnss_priors(&centres, bias, 1.3);
        local_bundle_adjustment(&mut biased, &params).unwrap();
        for (i, p) in biased.poses.iter().enumerate() {
            let e = (centre(p) - centres[i]).norm();
            assert!(
                e <= bias.norm() + 0.05,
                "camera {i}: error {e} m, bias {}",
                bias.norm()
            );
        }
        let scale = length(&biased) / true_length;
        assert!((scale - 1.0).abs() < 0.005, "biased scale {scale}");
    }

    /// The Schur solve equals a dense solve of the full damped system, and
    /// the analytic Jacobians match finite differences through it.
    #[test]
    fn schur_solve_matches_dense_and_finite_differences() {
        schur_solve_check(None);
    }

    /// The same with a rolling shutter: every pose moving during its
    /// readout (the Jacobians through each row's motion).
    #[test]
    fn schur_solve_matches_finite_differences_under_a_rolling_shutter() {
        let m = RowMotion::new(
            0.03,
            480,
            Vector3::new(-4.0, 0.5, 1.5),
            Vector3::new(0.2, 0.6, -0.3),
        );
        schur_solve_check(Some(PoseShutter {
            motion: m.unwrap(),
            between: None,
        }));
    }

    /// A strip of 6 keyframes 0.1 s apart, moving 5 units a second and
    /// turning, over 40 points 8-12 units ahead, each with a rolling
    /// shutter whose motion follows its neighbours in time.
    fn rolling_strip() -> BaProblem {
        let intr = Intrinsics {
            fx: 460.0,
            fy: 460.0,
            cx: 319.5,
            cy: 239.5,
        };
        let n: usize = 6;
        let poses: Vec<BaPose> = (0..n)
            .map(|i| {
                let t = i as f64 * 0.1;
                let world_from_cam = Isometry3::from_parts(
                    Translation3::new(5.0 * t, 0.3 * t, 0.0),
                    UnitQuaternion::from_euler_angles(0.02, 0.4 * t, 0.1 * t),
                );
                let (a, b) = (i.saturating_sub(1), (i + 1).min(n - 1));
                BaPose {
                    cam_from_world: world_from_cam.inverse(),
                    fixed: i == 0,
                    shutter: Some(PoseShutter {
                        motion: RowMotion::new(0.03, 480, Vector3::zeros(), Vector3::zeros())
                            .unwrap(),
                        between: Some((a, b, (b - a) as f64 * 0.1)),
                    }),
                }
            })
            .collect();
        let points: Vec<Point3<f64>> = (0..40)
            .map(|j| {
                let j = j as f64;
                Point3::new(
                    -3.0 + 0.2 * j,
                    (j * 0.7).sin() * 2.0,
                    8.0 + (j * 1.3).cos() * 2.0,
                )
            })
            .collect();
        let mut observations = Vec::new();
        for (i, p) in poses.iter().enumerate() {
            for (j, x) in points.iter().enumerate() {
                let pc = p.cam_from_world.transform_point(x).coords;
                let uv = intr.project(&pc);
                observations.push(Observation {
                    pose: i,
                    point: j,
                    uv: uv + Vector2::new(0.3 * ((i + j) % 3) as f64, -0.2 * (j % 4) as f64),
                    inv_sigma2: 1.0,
                });
            }
        }
        BaProblem {
            poses,
            points,
            observations,
            intrinsics: intr,
            priors: Vec::new(),
        }
    }

    fn cost_of(p: &BaProblem) -> f64 {
        let mut p = p.clone();
        let n = p.observations.len();
        BaLs::new(&mut p, vec![true; n], RobustKernel::None, 1e-6).cost()
    }

    /// A keyframe's rolling-shutter motion follows its neighbours' poses,
    /// so the cost does not change when the whole map is scaled (a
    /// monocular map's scale is free in its bundle adjustment). With the
    /// motion held as first computed, halving the map changes the cost:
    /// the adjustment could then shrink the map to strengthen the
    /// translation's share, and the next adjustment, taking the motion
    /// again from the shrunk poses, shrink it further (a 600-frame
    /// carpark flight's map shrank 300-fold in its first 6 frames so).
    #[test]
    fn a_rolling_shutter_cost_does_not_depend_on_the_map_scale() {
        let strip = rolling_strip();
        let base = cost_of(&strip);
        for s in [0.5, 3.0] {
            let c = cost_of(&scaled(&strip, &Vector3::zeros(), s));
            assert!(
                (c - base).abs() <= 1e-9 * base,
                "scale {s}: cost {c} against {base}"
            );
        }
        // The motions as the unscaled poses give them, then held.
        let mut held = strip.clone();
        follow_shutters(&mut held);
        for p in &mut held.poses {
            if let Some(sh) = &mut p.shutter {
                sh.between = None;
            }
        }
        let held_base = cost_of(&held);
        assert!((held_base - base).abs() <= 1e-9 * base);
        let halved = cost_of(&scaled(&held, &Vector3::zeros(), 0.5));
        assert!(
            (halved - held_base).abs() > 0.01 * held_base,
            "held motions: {halved} against {held_base}"
        );
    }

    fn schur_solve_check(shutter: Option<PoseShutter>) {
        let intr = Intrinsics {
            fx: 500.0,
            fy: 500.0,
            cx: 320.0,
            cy: 240.0,
        };
        let poses: Vec<BaPose> = (0..3)
            .map(|i| BaPose {
                cam_from_world: Isometry3::from_parts(
                    Translation3::new(-0.3 * i as f64, 0.05 * i as f64, 0.1),
                    UnitQuaternion::from_euler_angles(0.02 * i as f64, -0.03 * i as f64, 0.01),
                ),
                fixed: i == 0,
                shutter,
            })
            .collect();
        let points: Vec<Point3<f64>> = (0..6)
            .map(|j| {
                Point3::new(
                    -1.0 + 0.4 * j as f64,
                    0.3 * (j % 3) as f64 - 0.3,
                    4.0 + 0.5 * (j % 2) as f64,
                )
            })
            .collect();
        let mut observations = Vec::new();
        for (i, p) in poses.iter().enumerate() {
            for (j, x) in points.iter().enumerate() {
                let pc = p.cam_from_world.transform_point(x).coords;
                let mut uv = intr.project(&pc);
                uv.x += ((i * 7 + j * 3) % 5) as f64 - 2.0;
                uv.y += ((i * 3 + j * 5) % 7) as f64 - 3.0;
                observations.push(Observation {
                    pose: i,
                    point: j,
                    uv,
                    inv_sigma2: 1.0 + 0.1 * j as f64,
                });
            }
        }
        // Priors on the free poses' centres (one full, one vertical only),
        // off their true centres.
        let info = Matrix3::from_diagonal(&Vector3::new(4.0, 1.0, 9.0));
        let priors = vec![
            PositionPrior {
                pose: 1,
                centre: Point3::from(
                    poses[1].cam_from_world.inverse().translation.vector
                        + Vector3::new(0.2, -0.1, 0.3),
                ),
                information: info,
            },
            PositionPrior {
                pose: 2,
                centre: Point3::from(
                    poses[2].cam_from_world.inverse().translation.vector
                        + Vector3::new(0.0, 0.0, -0.25),
                ),
                information: Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, 16.0)),
            },
            // On the fixed pose: ignored.
            PositionPrior {
                pose: 0,
                centre: Point3::new(5.0, 5.0, 5.0),
                information: info,
            },
        ];
        let mut problem = BaProblem {
            poses,
            points,
            observations,
            intrinsics: intr,
            priors,
        };
        let base = problem.clone();
        // Residual vector (weighted by sqrt(inv_sigma2)) as a function of the
        // free parameters [δc(pose1), δc(pose2), δp(0..6)].
        let nvar = 12 + 18;
        let residuals = |x: &nalgebra::DVector<f64>| -> nalgebra::DVector<f64> {
            let mut p = base.clone();
            for f in 0..2 {
                let d = Vector6::from_iterator(x.rows(6 * f, 6).iter().copied());
                p.poses[f + 1].cam_from_world = se3_exp(&d) * p.poses[f + 1].cam_from_world;
            }
            for j in 0..6 {
                p.points[j] += Vector3::new(x[12 + 3 * j], x[13 + 3 * j], x[14 + 3 * j]);
            }
            let nobs = p.observations.len();
            let mut out = nalgebra::DVector::zeros(2 * nobs + 6);
            for (k, o) in p.observations.iter().enumerate() {
                let pc = observed_point(&p, o);
                let r = (intr.project(&pc) - o.uv) * o.inv_sigma2.sqrt();
                out[2 * k] = r.x;
                out[2 * k + 1] = r.y;
            }
            // The priors on free poses, whitened (diagonal information).
            for (m, pr) in p.priors.iter().take(2).enumerate() {
                let (r, _) = prior_residual(&p.poses[pr.pose].cam_from_world, pr);
                for a in 0..3 {
                    out[2 * nobs + 3 * m + a] = r[a] * pr.information[(a, a)].sqrt();
                }
            }
            out
        };
        let x0 = nalgebra::DVector::zeros(nvar);
        let r0 = residuals(&x0);
        let mut jfd = nalgebra::DMatrix::zeros(r0.len(), nvar);
        for v in 0..nvar {
            let mut xp = x0.clone();
            xp[v] = 1e-6;
            let mut xm = x0.clone();
            xm[v] = -1e-6;
            jfd.set_column(v, &((residuals(&xp) - residuals(&xm)) / 2e-6));
        }
        let h = jfd.transpose() * &jfd;
        let g = jfd.transpose() * &r0;
        let lambda = 1e-3;
        let mut hd = h.clone();
        for i in 0..nvar {
            hd[(i, i)] += lambda * h[(i, i)].clamp(1e-6, 1e32);
        }
        let dense = hd.cholesky().unwrap().solve(&(-&g));

        let mut ls = BaLs::new(&mut problem, vec![true; 18], RobustKernel::None, 1e-6);
        ls.prior_kernel = RobustKernel::None;
        let (cost, _) = ls.linearize();
        assert!((cost - 0.5 * r0.norm_squared()).abs() < 1e-9 * cost.max(1.0));
        ls.solve_damped(lambda).unwrap();
        let mut schur = nalgebra::DVector::zeros(nvar);
        for f in 0..2 {
            schur.rows_mut(6 * f, 6).copy_from(&ls.step_c[f]);
        }
        for j in 0..6 {
            schur.rows_mut(12 + 3 * j, 3).copy_from(&ls.step_p[j]);
        }
        let err = (&schur - &dense).norm() / dense.norm();
        assert!(err < 1e-5, "relative difference {err}\n{schur}\n{dense}");
    }
}
