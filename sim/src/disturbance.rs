//! Continuous-time disturbances of the vehicle and its camera: the wind
//! field, the gimbal's pointing error, and the position-hold sway the wind
//! causes along a prescribed camera path.
//!
//! The random processes are realised by the spectral representation method
//! (Shinozuka and Deodatis, "Simulation of stochastic processes by spectral
//! representation", Appl. Mech. Rev. 1991): a sum of cosines whose
//! amplitudes follow the process's spectrum, with seeded random phases.
//! They can be evaluated at any time (row exposure times, sub-exposure
//! samples) without stepping a state, and repeat for a seed.

use std::f64::consts::{PI, TAU};

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use rand::rngs::SmallRng;
use rand::{Rng, SeedableRng};

use crate::realism::{GimbalError, VideoLatency, Wind};

/// A sum of cosines `sum a_i cos(w_i t + phi_i)`.
#[derive(Debug, Clone, PartialEq)]
struct Spectral {
    /// (amplitude, angular frequency rad/s, phase).
    terms: Vec<(f64, f64, f64)>,
}

impl Spectral {
    /// A first-order Gauss-Markov process (Dryden's longitudinal form) of
    /// deviation `sigma` and time constant `tau`: one-sided spectrum
    /// `S(w) = sigma^2 (2 tau / pi) / (1 + (w tau)^2)`, sampled at `n`
    /// log-spaced frequencies from `0.01 / tau` to `w_max`.
    fn first_order(sigma: f64, tau: f64, w_max: f64, n: usize, rng: &mut SmallRng) -> Spectral {
        let tau = tau.max(1e-3);
        let (lo, hi) = ((0.01 / tau).ln(), w_max.max(0.02 / tau).ln());
        let step = (hi - lo) / n as f64;
        let spectrum = |w: f64| sigma * sigma * (2.0 * tau / PI) / (1.0 + (w * tau).powi(2));
        let mut terms: Vec<(f64, f64, f64)> = (0..n)
            .map(|i| {
                let (a, b) = (
                    (lo + step * i as f64).exp(),
                    (lo + step * (i + 1) as f64).exp(),
                );
                let w = (a * b).sqrt();
                (
                    (2.0 * spectrum(w) * (b - a)).sqrt(),
                    w,
                    rng.random_range(0.0..TAU),
                )
            })
            .collect();
        // The band misses a little variance below 0.01/tau and above w_max:
        // scale to exactly sigma.
        let var: f64 = terms.iter().map(|t| t.0 * t.0 * 0.5).sum();
        if var > 0.0 {
            let k = sigma / var.sqrt();
            terms.iter_mut().for_each(|t| t.0 *= k);
        }
        Spectral { terms }
    }

    /// Equal-amplitude tones at `n` log-spaced frequencies in `[f_lo, f_hi]`
    /// Hz with total deviation `sigma`.
    fn band(sigma: f64, f_lo: f64, f_hi: f64, n: usize, rng: &mut SmallRng) -> Spectral {
        let a = sigma * (2.0 / n as f64).sqrt();
        let terms = (0..n)
            .map(|i| {
                let f =
                    f_lo * (f_hi / f_lo).powf((i as f64 + rng.random_range(0.0..1.0)) / n as f64);
                (a, TAU * f, rng.random_range(0.0..TAU))
            })
            .collect();
        Spectral { terms }
    }

    fn at(&self, t: f64) -> f64 {
        self.terms
            .iter()
            .map(|&(a, w, p)| a * (w * t + p).cos())
            .sum()
    }
}

/// The wind: a mean wind plus Dryden gusts (see [`Wind`]).
#[derive(Debug, Clone, PartialEq)]
pub struct WindField {
    params: Wind,
    mean: Vector3<f64>,
    /// Unit vectors along and across the mean wind (horizontal).
    along: Vector3<f64>,
    across: Vector3<f64>,
    u: Spectral,
    v: Spectral,
    w: Spectral,
}

impl WindField {
    /// The wind field for `params`, its gusts seeded by `seed`.
    pub fn new(params: Wind, seed: u64) -> WindField {
        let mut rng = SmallRng::seed_from_u64(seed ^ 0x3137_D00D);
        // Blowing from `from_deg`: the air moves towards from + 180.
        let to = (params.from_deg + 180.0).to_radians();
        let along = Vector3::new(to.cos(), to.sin(), 0.0);
        let across = Vector3::new(-to.sin(), to.cos(), 0.0);
        let tau = params.length_scale_m / params.mean_m_s.max(1.0);
        // Gusts up to 10 Hz (a small multicopter's attitude loop cannot
        // follow faster ones).
        let w_max = TAU * 10.0;
        let sigma = params.gust_sigma_m_s;
        WindField {
            mean: along * params.mean_m_s,
            along,
            across,
            u: Spectral::first_order(sigma, tau, w_max, 48, &mut rng),
            v: Spectral::first_order(sigma, tau, w_max, 48, &mut rng),
            // Vertical gusts are weaker near the ground (Dryden, low altitude: sigma_w = 0.58 sigma_u at 30 m).
            w: Spectral::first_order(0.58 * sigma, tau * 0.5, w_max, 48, &mut rng),
            params,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &Wind {
        &self.params
    }

    /// The mean wind velocity (NED, m/s).
    pub fn mean(&self) -> Vector3<f64> {
        self.mean
    }

    /// The wind velocity at time `t` (NED, m/s).
    pub fn velocity(&self, t: f64) -> Vector3<f64> {
        self.mean
            + self.along * self.u.at(t)
            + self.across * self.v.at(t)
            + Vector3::new(0.0, 0.0, self.w.at(t))
    }

    /// Drag acceleration on a vehicle moving at `v` (NED m/s) at time `t`:
    /// `drag |a| a` with `a` the air's velocity relative to the vehicle.
    pub fn drag_accel(&self, t: f64, v: &Vector3<f64>) -> Vector3<f64> {
        let air = self.velocity(t) - v;
        air * (self.params.drag_per_m * air.norm())
    }
}

/// The gimbal's pointing error about the camera's axes (a low-frequency
/// stabilisation error, 0.1-2 Hz, and a jitter, 15-60 Hz, on each axis).
#[derive(Debug, Clone, PartialEq)]
pub struct GimbalJitter {
    params: GimbalError,
    axes: [(Spectral, Spectral); 3],
}

impl GimbalJitter {
    /// The pointing error for `params`, seeded by `seed`.
    pub fn new(params: GimbalError, seed: u64) -> GimbalJitter {
        let mut rng = SmallRng::seed_from_u64(seed ^ 0x61B_BA1);
        let stab = params.stabilisation_deg.to_radians();
        let jit = params.jitter_deg.to_radians();
        let mut axis = || {
            (
                Spectral::band(stab, 0.1, 2.0, 8, &mut rng),
                Spectral::band(jit, 15.0, 60.0, 8, &mut rng),
            )
        };
        GimbalJitter {
            axes: [axis(), axis(), axis()],
            params,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &GimbalError {
        &self.params
    }

    /// The error at time `t` as a rotation vector in camera axes (x right:
    /// tilt, y down: pan, z forward: roll), radians.
    pub fn error(&self, t: f64) -> Vector3<f64> {
        let e = |k: usize| self.axes[k].0.at(t) + self.axes[k].1.at(t);
        Vector3::new(e(0), e(1), e(2))
    }

    /// `world_from_cam` turned by the error at time `t`.
    pub fn apply(&self, world_from_cam: &Isometry3<f64>, t: f64) -> Isometry3<f64> {
        let mut p = *world_from_cam;
        p.rotation *= UnitQuaternion::from_scaled_axis(self.error(t));
        p
    }
}

/// A video latency that varies (see [`VideoLatency`]): the mean plus a
/// first-order Gauss-Markov deviation, never below zero.
#[derive(Debug, Clone, PartialEq)]
pub struct LatencyProcess {
    params: VideoLatency,
    deviation: Spectral,
}

impl LatencyProcess {
    /// The latency for `params`, seeded by `seed`.
    pub fn new(params: VideoLatency, seed: u64) -> LatencyProcess {
        let mut rng = SmallRng::seed_from_u64(seed ^ 0x1A7E_0C1D);
        LatencyProcess {
            deviation: Spectral::first_order(params.sigma_s, params.tau_s, TAU * 5.0, 32, &mut rng),
            params,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &VideoLatency {
        &self.params
    }

    /// The latency of a frame captured at `t`, seconds.
    pub fn at(&self, t: f64) -> f64 {
        (self.params.mean_s + self.deviation.at(t)).max(0.0)
    }
}

/// The position-hold loop's deviation from a prescribed path under wind,
/// tabulated at a fixed step: the vehicle flies the path with the
/// simulator's own controller (position gain, velocity-loop time constant)
/// plus the wind's integral compensation, and the wind's drag pushes it.
#[derive(Debug, Clone, PartialEq)]
pub struct HoldSway {
    start: f64,
    step: f64,
    offsets: Vec<Vector3<f64>>,
}

impl HoldSway {
    /// Integrates the deviation over `[start, end]` for a path whose
    /// position is `position(t)`, with the vehicle's `position_gain` (1/s)
    /// and `velocity_tau_s`.
    pub fn integrate(
        wind: &WindField,
        position: &dyn Fn(f64) -> Vector3<f64>,
        start: f64,
        end: f64,
        position_gain: f64,
        velocity_tau_s: f64,
    ) -> HoldSway {
        let step = 0.005;
        let n = (((end - start) / step).ceil() as usize).max(1) + 1;
        let velocity = |t: f64| (position(t + 0.01) - position(t - 0.01)) / 0.02;
        let ki = wind.params().integral_gain;
        let mut e = Vector3::zeros();
        let mut de = Vector3::zeros();
        // The integrator starts converged on the drag at the start.
        let mut integral = -wind.drag_accel(start, &velocity(start));
        let mut offsets = Vec::with_capacity(n);
        let inv_tau = 1.0 / velocity_tau_s.max(1e-3);
        for k in 0..n {
            let t = start + k as f64 * step;
            offsets.push(e);
            // Semi-implicit Euler on the error dynamics.
            let v = velocity(t) + de;
            let v_err = -position_gain * e - de;
            let a = v_err * inv_tau + integral + wind.drag_accel(t, &v);
            integral += v_err * (ki * step);
            de += a * step;
            e += de * step;
        }
        HoldSway {
            start,
            step,
            offsets,
        }
    }

    /// The deviation (NED, m) at time `t` (linear between samples, clamped).
    pub fn offset(&self, t: f64) -> Vector3<f64> {
        let x = ((t - self.start) / self.step).max(0.0);
        let i = (x.floor() as usize).min(self.offsets.len().saturating_sub(2));
        let f = (x - i as f64).min(1.0);
        match (self.offsets.get(i), self.offsets.get(i + 1)) {
            (Some(a), Some(b)) => a + (b - a) * f,
            (Some(a), None) => *a,
            _ => Vector3::zeros(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::realism::Realism;

    fn stats(xs: &[f64]) -> (f64, f64) {
        let n = xs.len() as f64;
        let m = xs.iter().sum::<f64>() / n;
        (
            m,
            (xs.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n).sqrt(),
        )
    }

    #[test]
    fn wind_has_its_mean_and_gust_intensity() {
        let p = Realism::field().vehicle.wind.unwrap();
        let sigmas: Vec<f64> = (0..8)
            .map(|seed| {
                let w = WindField::new(p, seed);
                // The mean wind blows from 240 degrees: towards 60 (north-east).
                assert!((w.mean().norm() - p.mean_m_s).abs() < 1e-9);
                assert!(w.mean().x > 0.0 && w.mean().y > 0.0);
                let along: Vec<f64> = (0..20_000)
                    .map(|k| (w.velocity(k as f64 * 0.5) - w.mean()).dot(&w.along))
                    .collect();
                stats(&along).1
            })
            .collect();
        let (m, _) = stats(&sigmas);
        assert!((m / p.gust_sigma_m_s - 1.0).abs() < 0.1, "gust sigma {m}");
    }

    #[test]
    fn gimbal_jitter_has_its_rms() {
        let p = GimbalError {
            stabilisation_deg: 0.3,
            jitter_deg: 0.05,
        };
        let g = GimbalJitter::new(p, 4);
        let xs: Vec<f64> = (0..200_000).map(|k| g.error(k as f64 * 0.0013).x).collect();
        let (_, sd) = stats(&xs);
        let expected = (0.3f64.powi(2) + 0.05f64.powi(2)).sqrt().to_radians();
        assert!((sd / expected - 1.0).abs() < 0.1, "{} vs {}", sd, expected);
    }

    #[test]
    fn video_latency_varies_around_its_mean() {
        let p = Realism::field().vehicle.video_latency.unwrap();
        let l = LatencyProcess::new(p, 3);
        let xs: Vec<f64> = (0..20_000).map(|k| l.at(k as f64 * 0.1)).collect();
        let (m, sd) = stats(&xs);
        assert!((m - p.mean_s).abs() < 0.2 * p.sigma_s, "mean {m}");
        assert!((sd / p.sigma_s - 1.0).abs() < 0.15, "sd {sd}");
        // Correlated over a fraction of tau, decorrelated well beyond it.
        let corr = |lag: usize| {
            let n = xs.len() - lag;
            (0..n).map(|i| (xs[i] - m) * (xs[i + lag] - m)).sum::<f64>() / n as f64 / (sd * sd)
        };
        assert!(corr(2) > 0.8, "{}", corr(2));
        assert!(corr(200) < 0.2, "{}", corr(200));
    }

    #[test]
    fn hold_sway_is_decimetres_in_strong_wind_and_centimetres_in_calm() {
        let hover = |_t: f64| Vector3::new(0.0, 0.0, -30.0);
        let rms = |wind: Wind| {
            let (mut sum, mut n) = (0.0, 0);
            for seed in 0..4 {
                let w = WindField::new(wind, seed);
                let s = HoldSway::integrate(&w, &hover, 0.0, 300.0, 0.95, 0.25);
                for k in 200..3000 {
                    sum += s.offset(k as f64 * 0.1).xy().norm_squared();
                    n += 1;
                }
            }
            (sum / n as f64).sqrt()
        };
        let harsh = rms(Realism::harsh().vehicle.wind.unwrap());
        let field = rms(Realism::field().vehicle.wind.unwrap());
        eprintln!("hold error rms: field {field:.3} m, harsh {harsh:.3} m");
        assert!((0.1..1.0).contains(&harsh), "harsh {harsh}");
        assert!(field < harsh / 3.0, "field {field} harsh {harsh}");
    }
}
