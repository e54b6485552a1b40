//! The georeference's refinement with orientations: the Sim(3) and the
//! mount's heading and pitch offsets fitted together to the inlier pairs'
//! positions and camera attitudes (Levenberg-Marquardt,
//! [`crate::optimize::lm`]).

use nalgebra::{Matrix3, SMatrix, SVector, UnitQuaternion, Vector3};

use super::{AlignParams, Pair};
use crate::geo::mount::MountOffset;
use crate::geometry::Sim3;
use crate::lie::skew;
use crate::optimize::lm::{LeastSquares, solve_damped_dense};
use crate::optimize::sim3::sim3_left_update;

type Mat9 = SMatrix<f64, 9, 9>;
type Vec9 = SVector<f64, 9>;

/// Joint position + rotation refinement of `ned ← map`, update
/// `S ← (e^σ·Exp(ω), υ) ∘ S` with `δ = [υ; ω; σ; ψ; θ]`, and of the mount's
/// heading and pitch offsets `ψ`, `θ`: the telemetry's camera attitude is
/// taken as `Rz(ψ)·(ned ← cam)·Rx(θ)` (a heading turn about the vertical, a
/// pitch turn about the camera's x axis: [`MountParams::yaw_offset_deg`] and
/// [`MountParams::pitch_offset_deg`] for a stabilised gimbal). The offsets
/// carry a zero-mean prior; with `free_sim` false only they move (a map
/// already in NED).
pub(super) struct Refinement<'a> {
    pairs: &'a [&'a Pair],
    pub(super) sim: Sim3,
    old: Sim3,
    /// `[ψ, θ]`, radians.
    mount: [f64; 2],
    old_mount: [f64; 2],
    /// Whether the offsets are estimated.
    free_mount: bool,
    /// Whether the similarity is estimated.
    pub(super) free_sim: bool,
    w_pos: f64,
    w_rot: f64,
    w_mount: f64,
    h: Mat9,
    g: Vec9,
    step: Vec9,
}

impl<'a> Refinement<'a> {
    pub(super) fn new(pairs: &'a [&'a Pair], sim: Sim3, params: &AlignParams) -> Self {
        let sp = params.position_sigma_m.max(1e-9);
        let sr = params.orientation_sigma_deg.to_radians().max(1e-9);
        let sm = params.mount_offset_sigma_deg.to_radians().max(1e-9);
        Self {
            pairs,
            sim,
            old: sim,
            mount: [0.0; 2],
            old_mount: [0.0; 2],
            free_mount: params.estimate_mount,
            free_sim: true,
            w_pos: 1.0 / (sp * sp),
            w_rot: 1.0 / (sr * sr),
            w_mount: 1.0 / (sm * sm),
            h: Mat9::zeros(),
            g: Vec9::zeros(),
            step: Vec9::zeros(),
        }
    }

    /// `Rz(ψ)·(ned ← cam)·Rx(θ)`: the telemetry's camera attitude with the
    /// offsets.
    fn corrected(&self, ned_cam: &UnitQuaternion<f64>) -> UnitQuaternion<f64> {
        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.mount[0])
            * ned_cam
            * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), self.mount[1])
    }

    /// Rotation residual `Log(R · (map ← cam) · (Rz(ψ)·(ned ← cam)·Rx(θ))⁻¹)`.
    fn rot_residual(&self, p: &Pair) -> Vector3<f64> {
        match p.orientations {
            Some((map_cam, ned_cam)) => {
                (self.sim.rotation * map_cam * self.corrected(&ned_cam).inverse()).scaled_axis()
            }
            None => Vector3::zeros(),
        }
    }

    /// RMS rotation residual over the pairs that carry orientations.
    pub(super) fn rotation_rms(&self) -> f64 {
        let (s, n) = self
            .pairs
            .iter()
            .filter(|p| p.orientations.is_some())
            .fold((0.0, 0usize), |(s, n), p| {
                (s + self.rot_residual(p).norm_squared(), n + 1)
            });
        (s / n.max(1) as f64).sqrt()
    }

    /// The offsets learned, when they were estimated, with their standard
    /// deviations: the marginal of `H⁻¹` at the estimate (the Sim(3)'s
    /// uncertainty included), scaled up by the residuals' reduced χ² when
    /// the pairs scatter more than the configured sigmas say.
    pub(super) fn mount_offset(&mut self) -> Option<MountOffset> {
        if !self.free_mount {
            return None;
        }
        let (cost, _) = self.linearize();
        let oriented = self
            .pairs
            .iter()
            .filter(|p| p.orientations.is_some())
            .count();
        let dof = (3 * self.pairs.len() + 3 * oriented)
            .saturating_sub(9)
            .max(1);
        let chi2 = (2.0 * cost / dof as f64).max(1.0);
        let cov = self.h.cholesky().map(|c| c.inverse());
        let sigma = |k: usize| {
            cov.as_ref()
                .map_or(f64::INFINITY, |c| (c[(k, k)] * chi2).sqrt().to_degrees())
        };
        Some(MountOffset {
            pitch_deg: self.mount[1].to_degrees(),
            yaw_deg: self.mount[0].to_degrees(),
            pitch_sigma_deg: sigma(8),
            yaw_sigma_deg: sigma(7),
            pairs: oriented,
        })
    }

    fn prior_cost(&self) -> f64 {
        if self.free_mount {
            0.5 * self.w_mount * (self.mount[0].powi(2) + self.mount[1].powi(2))
        } else {
            0.0
        }
    }
}

impl LeastSquares for Refinement<'_> {
    fn linearize(&mut self) -> (f64, f64) {
        let mut h = Mat9::zeros();
        let mut g = Vec9::zeros();
        let mut cost = self.prior_cost();
        for p in self.pairs {
            let q = self.sim.transform_point(&p.p_map).coords;
            let e = q - p.p_ned.coords;
            // ∂q/∂δ = [I | -[q]ₓ | q] (the update acts after S).
            let mut j = SMatrix::<f64, 3, 9>::zeros();
            j.fixed_view_mut::<3, 3>(0, 0)
                .copy_from(&Matrix3::identity());
            j.fixed_view_mut::<3, 3>(0, 3).copy_from(&(-skew(&q)));
            j.fixed_view_mut::<3, 1>(0, 6).copy_from(&q);
            h += j.transpose() * j * self.w_pos;
            g += j.transpose() * e * self.w_pos;
            cost += 0.5 * self.w_pos * e.norm_squared();
            // Rotation residual r = Log(E): d/dω ≈ I near the optimum;
            // E·Rz(-dψ) = Exp(-E·ẑ dψ)·E gives d/dψ ≈ -E·ẑ, and the turn
            // Rx(-dθ) after A = R·(map ← cam)·Rx(-θ) gives d/dθ ≈ -A·x̂.
            if let Some((map_cam, ned_cam)) = p.orientations {
                let rot = self.sim.rotation * map_cam;
                let err = rot * self.corrected(&ned_cam).inverse();
                let r = err.scaled_axis();
                let mut jr = SMatrix::<f64, 3, 9>::zeros();
                jr.fixed_view_mut::<3, 3>(0, 3)
                    .copy_from(&Matrix3::identity());
                if self.free_mount {
                    let a =
                        rot * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -self.mount[1]);
                    jr.fixed_view_mut::<3, 1>(0, 7)
                        .copy_from(&-(err * Vector3::z()));
                    jr.fixed_view_mut::<3, 1>(0, 8)
                        .copy_from(&-(a * Vector3::x()));
                }
                h += jr.transpose() * jr * self.w_rot;
                g += jr.transpose() * r * self.w_rot;
                cost += 0.5 * self.w_rot * r.norm_squared();
            }
        }
        if self.free_mount {
            h[(7, 7)] += self.w_mount;
            h[(8, 8)] += self.w_mount;
            g[7] += self.w_mount * self.mount[0];
            g[8] += self.w_mount * self.mount[1];
        }
        // A fixed block: its rows and columns out, a unit diagonal, no pull.
        let fixed: &[usize] = match (self.free_sim, self.free_mount) {
            (true, true) => &[],
            (true, false) => &[7, 8],
            (false, true) => &[0, 1, 2, 3, 4, 5, 6],
            (false, false) => &[0, 1, 2, 3, 4, 5, 6, 7, 8],
        };
        for &i in fixed {
            h.row_mut(i).fill(0.0);
            h.column_mut(i).fill(0.0);
            h[(i, i)] = 1.0;
            g[i] = 0.0;
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
        self.old = self.sim;
        self.old_mount = self.mount;
        let d = self.step;
        // The Sim(3)'s left update, then the two offsets.
        self.sim = sim3_left_update(&self.sim, &d.fixed_rows::<7>(0).into_owned());
        self.mount[0] += d[7];
        self.mount[1] += d[8];
    }

    fn revert_step(&mut self) {
        self.sim = self.old;
        self.mount = self.old_mount;
    }

    fn cost(&mut self) -> f64 {
        let mut cost = self.prior_cost();
        for p in self.pairs {
            let e = self.sim.transform_point(&p.p_map) - p.p_ned;
            cost += 0.5 * self.w_pos * e.norm_squared();
            cost += 0.5 * self.w_rot * self.rot_residual(p).norm_squared();
        }
        cost
    }

    fn state_norm(&self) -> f64 {
        (self.sim.translation.norm_squared()
            + self.sim.rotation.scaled_axis().norm_squared()
            + self.sim.scale.ln().powi(2)
            + self.mount[0].powi(2)
            + self.mount[1].powi(2))
        .sqrt()
    }
}
