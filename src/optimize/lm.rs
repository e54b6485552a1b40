//! The Levenberg-Marquardt core shared by every problem of this module.
//!
//! A problem linearises itself into Gauss-Newton normal equations
//! `H·δ = -g` (with robust IRLS weights `ρ'(s)`), and solves the damped
//! system `(H + λ·D)·δ = -g` with Marquardt's scaling `D = diag(H)`
//! (clamped to `[1e-6, 1e32]`, as Ceres does). The core owns the damping:
//!
//! * the gain ratio `ϱ = (F(x) - F(x+δ)) / (L(0) - L(δ))` compares the
//!   actual decrease with the one the quadratic model predicts,
//!   `L(0) - L(δ) = ½·δᵀ·(λ·D·δ - g)`;
//! * on success (`ϱ > 0`) the step is kept and `λ ← λ·max(1/3, 1 - (2ϱ-1)³)`,
//!   `ν ← 2` (Nielsen 1999, as in Madsen, Nielsen & Tingleff, "Methods for
//!   non-linear least squares problems", 2004, §3.2);
//! * on failure the step is undone and `λ ← λ·ν`, `ν ← 2ν`.
//!
//! Stopping rules: gradient `‖g‖∞ ≤ gradient_tolerance`; step
//! `‖δ‖ ≤ step_tolerance·(‖x‖ + step_tolerance)`; relative cost decrease
//! below `cost_tolerance`; `λ` beyond `max_lambda`; `max_iterations` steps
//! tried (accepted or not, as g2o counts them).

/// What a problem must provide to be minimised by [`levenberg_marquardt`].
pub trait LeastSquares {
    /// Linearises at the current estimate: builds `H` and `g` internally and
    /// returns `(cost, ‖g‖∞)` where `cost = ½·Σρ(s)`.
    fn linearize(&mut self) -> (f64, f64);
    /// Solves `(H + λ·D)·δ = -g` for the last linearisation and stores `δ`.
    /// Returns the predicted decrease `½·δᵀ·(λ·D·δ - g)` and `‖δ‖`, or
    /// `None` when the damped system is not positive definite.
    fn solve_damped(&mut self, lambda: f64) -> Option<(f64, f64)>;
    /// Applies the stored step, remembering the old estimate.
    fn apply_step(&mut self);
    /// Restores the estimate from before the last [`LeastSquares::apply_step`].
    fn revert_step(&mut self);
    /// Cost `½·Σρ(s)` at the current estimate (no derivatives).
    fn cost(&mut self) -> f64;
    /// Norm of the parameter vector (for the relative step test).
    fn state_norm(&self) -> f64;
}

/// Solves a small dense damped system `(H + λ·D)·δ = -g` with `D` the
/// clamped diagonal of `H` (see the module comment), for problems whose
/// normal equations fit in one dense matrix: fixed-size (`SMatrix`, the
/// pose and Sim(3) problems) or sized at run time (`DMatrix`, the pose with
/// its free intrinsics). Returns `δ` and the predicted decrease
/// `½·δᵀ·(λ·D·δ - g)`, or `None` when the damped matrix is not positive
/// definite or the step is not finite.
pub fn solve_damped_dense<D: nalgebra::Dim>(
    h: &nalgebra::OMatrix<f64, D, D>,
    g: &nalgebra::OVector<f64, D>,
    lambda: f64,
) -> Option<(nalgebra::OVector<f64, D>, f64)>
where
    nalgebra::DefaultAllocator:
        nalgebra::allocator::Allocator<D, D> + nalgebra::allocator::Allocator<D>,
{
    let mut a = h.clone();
    let mut d = g.clone();
    for i in 0..d.len() {
        d[i] = h[(i, i)].clamp(1e-6, 1e32);
        a[(i, i)] += lambda * d[i];
    }
    let step = a.cholesky()?.solve(&(-g));
    if !step.iter().all(|v| v.is_finite()) {
        return None;
    }
    let pred = 0.5 * step.dot(&(d.component_mul(&step) * lambda - g));
    Some((step, pred))
}

/// Tunables of the LM core.
#[derive(Debug, Clone, PartialEq)]
pub struct LmParams {
    /// Maximum number of steps tried.
    pub max_iterations: usize,
    /// Initial damping `λ` (Marquardt-scaled, so dimensionless).
    pub initial_lambda: f64,
    /// Stop when `‖g‖∞` falls below this.
    pub gradient_tolerance: f64,
    /// Stop when the step is this small relative to the state.
    pub step_tolerance: f64,
    /// Stop when an accepted step lowers the cost by less than this fraction.
    pub cost_tolerance: f64,
    /// Give up when `λ` grows beyond this.
    pub max_lambda: f64,
}

impl Default for LmParams {
    fn default() -> Self {
        Self {
            max_iterations: 10,
            initial_lambda: 1e-4,
            gradient_tolerance: 1e-10,
            step_tolerance: 1e-10,
            cost_tolerance: 1e-9,
            max_lambda: 1e16,
        }
    }
}

/// Why the optimisation stopped.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Termination {
    /// The gradient vanished.
    Gradient,
    /// The step became negligible.
    Step,
    /// The cost stopped decreasing.
    CostChange,
    /// The iteration budget was spent.
    MaxIterations,
    /// `λ` exceeded `max_lambda` without an acceptable step.
    Damping,
}

/// What an LM run did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LmSummary {
    /// Steps tried.
    pub iterations: usize,
    /// Steps accepted.
    pub accepted: usize,
    /// Cost `½·Σρ(s)` before.
    pub initial_cost: f64,
    /// Cost after.
    pub final_cost: f64,
    /// The stopping rule that fired.
    pub termination: Termination,
}

/// Minimises a [`LeastSquares`] problem in place.
pub fn levenberg_marquardt<P: LeastSquares + ?Sized>(
    problem: &mut P,
    params: &LmParams,
) -> LmSummary {
    let (mut cost, mut gmax) = problem.linearize();
    let initial_cost = cost;
    let mut lambda = params.initial_lambda;
    let mut nu = 2.0;
    let mut accepted = 0;
    let mut iterations = 0;
    let mut termination = Termination::MaxIterations;
    while iterations < params.max_iterations {
        if gmax <= params.gradient_tolerance {
            termination = Termination::Gradient;
            break;
        }
        if lambda > params.max_lambda {
            termination = Termination::Damping;
            break;
        }
        iterations += 1;
        let Some((predicted, step_norm)) = problem.solve_damped(lambda) else {
            lambda *= nu;
            nu *= 2.0;
            continue;
        };
        if step_norm <= params.step_tolerance * (problem.state_norm() + params.step_tolerance) {
            termination = Termination::Step;
            break;
        }
        problem.apply_step();
        let new_cost = problem.cost();
        let rho = (cost - new_cost) / predicted;
        if new_cost.is_finite() && predicted > 0.0 && rho > 0.0 {
            accepted += 1;
            let t = 2.0 * rho - 1.0;
            lambda *= (1.0 - t * t * t).max(1.0 / 3.0);
            nu = 2.0;
            let rel = (cost - new_cost) / cost.max(f64::MIN_POSITIVE);
            let (c, g) = problem.linearize();
            cost = c;
            gmax = g;
            if rel < params.cost_tolerance {
                termination = Termination::CostChange;
                break;
            }
        } else {
            problem.revert_step();
            lambda *= nu;
            nu *= 2.0;
        }
    }
    LmSummary {
        iterations,
        accepted,
        initial_cost,
        final_cost: cost,
        termination,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix2, Vector2};

    /// Rosenbrock as least squares: r = (10(y - x²), 1 - x).
    struct Rosen {
        x: Vector2<f64>,
        old: Vector2<f64>,
        h: Matrix2<f64>,
        g: Vector2<f64>,
        step: Vector2<f64>,
    }

    impl Rosen {
        fn res(x: &Vector2<f64>) -> Vector2<f64> {
            Vector2::new(10.0 * (x.y - x.x * x.x), 1.0 - x.x)
        }
    }

    impl LeastSquares for Rosen {
        fn linearize(&mut self) -> (f64, f64) {
            let r = Self::res(&self.x);
            let j = Matrix2::new(-20.0 * self.x.x, 10.0, -1.0, 0.0);
            self.h = j.transpose() * j;
            self.g = j.transpose() * r;
            (0.5 * r.norm_squared(), self.g.amax())
        }
        fn solve_damped(&mut self, lambda: f64) -> Option<(f64, f64)> {
            let (step, pred) = solve_damped_dense(&self.h, &self.g, lambda)?;
            self.step = step;
            Some((pred, step.norm()))
        }
        fn apply_step(&mut self) {
            self.old = self.x;
            self.x += self.step;
        }
        fn revert_step(&mut self) {
            self.x = self.old;
        }
        fn cost(&mut self) -> f64 {
            0.5 * Self::res(&self.x).norm_squared()
        }
        fn state_norm(&self) -> f64 {
            self.x.norm()
        }
    }

    #[test]
    fn solves_rosenbrock() {
        let mut p = Rosen {
            x: Vector2::new(-1.2, 1.0),
            old: Vector2::zeros(),
            h: Matrix2::zeros(),
            g: Vector2::zeros(),
            step: Vector2::zeros(),
        };
        let s = levenberg_marquardt(
            &mut p,
            &LmParams {
                max_iterations: 200,
                ..LmParams::default()
            },
        );
        assert!(
            (p.x - Vector2::new(1.0, 1.0)).norm() < 1e-6,
            "{:?} {s:?}",
            p.x
        );
        assert!(s.final_cost < 1e-12);
        assert!(s.accepted > 3);
    }

    #[test]
    fn the_damped_solve_is_the_same_at_fixed_and_run_time_size() {
        let j = nalgebra::Matrix3::new(2.0, -1.0, 0.5, 0.3, 4.0, -0.2, 1e-9, 0.7, 3.0);
        let h = j.transpose() * j;
        let g = nalgebra::Vector3::new(0.4, -1.3, 2.2);
        let (fixed, pred_fixed) = solve_damped_dense(&h, &g, 0.1).unwrap();
        let hd = nalgebra::DMatrix::from_column_slice(3, 3, h.as_slice());
        let gd = nalgebra::DVector::from_column_slice(g.as_slice());
        let (dynamic, pred_dynamic) = solve_damped_dense(&hd, &gd, 0.1).unwrap();
        assert_eq!(fixed.as_slice(), dynamic.as_slice());
        assert_eq!(pred_fixed, pred_dynamic);
        assert!(pred_fixed > 0.0);
        // (H + λD)δ = -g with D = diag(H).
        let mut a = h;
        for i in 0..3 {
            a[(i, i)] *= 1.1;
        }
        assert!((a * fixed + g).norm() < 1e-12);
        // Not positive definite: no step.
        let bad = -nalgebra::DMatrix::<f64>::identity(3, 3);
        assert!(solve_damped_dense(&bad, &gd, 0.1).is_none());
    }
}
