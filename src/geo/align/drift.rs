//! A GNSS bias that drifts, estimated in the georeference fit (issue 36,
//! points 2 and 3): the fit's translation follows the receiver's bias as
//! it reads at the newest pair, not its average over the flight.
//!
//! A receiver's error is mostly a slowly wandering bias (multipath,
//! atmosphere, satellite geometry) with a little white noise on top. It is
//! modelled as a first-order Gauss-Markov process per axis with the
//! stationary standard deviation `σ` and correlation time `τ`:
//! `b(t + Δ) = φ·b(t) + w`, `φ = exp(-Δ/τ)`, `Var w = σ²·(1 - φ²)`. The
//! inlier pairs are grouped in windows of [`GnssDrift::window_s`], one bias
//! state per window, and the fit minimises
//!
//! ```text
//! Σ_i |p_i - (s·R·m_i + t + b_k(i))|²/σ_n²  +  b_0²/σ²  +  Σ_k (b_k+1 - φ_k·b_k)²/(σ²·(1 - φ_k²))
//! ```
//!
//! (`m_i` the camera centre in the map, `p_i` the GNSS camera position, per
//! axis with the horizontal or vertical `σ_n` and `σ`) by alternating
//! Umeyama on `p_i - b_k(i)` (scale, rotation, translation) with the exact
//! solve of the translation and every bias for that scale and rotation:
//! per axis a tridiagonal system bordered by the translation, solved by
//! two Thomas sweeps in time linear in the windows. The translation and
//! the biases' mean are told apart only by the bias prior (a constant bias
//! is invisible to a georeference); what is observable, and what the vehicle
//! needs, is their sum at the newest window: the returned map → NED
//! similarity has the translation `t + b_newest`, so it maps the map into
//! the NED the receiver reads now, the frame the vehicle flies in.
//!
//! Independent per-pair residuals (a plain Umeyama over a long flight)
//! instead average the bias over every pair, and one pair from now weighs
//! no more than one from five minutes ago.

use nalgebra::{Point3, Vector3};

use super::Pair;
use crate::geometry::{Sim3, umeyama};

/// The receiver's error model for [`fit_with_drift`].
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GnssDrift {
    /// Stationary standard deviation of the horizontal bias, per axis, m.
    pub sigma_xy_m: f64,
    /// Stationary standard deviation of the vertical bias, m.
    pub sigma_z_m: f64,
    /// Correlation time of the bias, s.
    pub tau_s: f64,
    /// White noise of one pair, horizontal per axis, m (the receiver's
    /// noise about its bias and the map's local error together).
    pub noise_xy_m: f64,
    /// White noise of one pair, vertical, m.
    pub noise_z_m: f64,
    /// One bias state per this much time, s.
    pub window_s: f64,
    /// Most alternations of Umeyama and the bias solve.
    pub iterations: usize,
}

impl Default for GnssDrift {
    fn default() -> Self {
        // A single-frequency receiver of the kind on a camera drone: metres
        // of bias wandering over minutes, decimetres of noise about it.
        Self {
            sigma_xy_m: 1.0,
            sigma_z_m: 1.0,
            tau_s: 120.0,
            noise_xy_m: 0.3,
            noise_z_m: 0.5,
            window_s: 2.0,
            iterations: 20,
        }
    }
}

impl GnssDrift {
    /// Whether every number is usable (positive and finite).
    pub fn is_valid(&self) -> bool {
        [
            self.sigma_xy_m,
            self.sigma_z_m,
            self.tau_s,
            self.noise_xy_m,
            self.noise_z_m,
            self.window_s,
        ]
        .iter()
        .all(|v| v.is_finite() && *v > 0.0)
    }
}

/// What [`fit_with_drift`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct DriftFit {
    /// `ned ← map` in the receiver's frame at the newest window: `s·R·m +
    /// t + b_newest`.
    pub ned_from_map: Sim3,
    /// The bias estimated at the newest window, NED, m.
    pub newest_bias: Vector3<f64>,
    /// Per pair (in the order given): the residual after its window's bias,
    /// m.
    pub residuals: Vec<f64>,
    /// Bias windows.
    pub windows: usize,
    /// Each window's mean time, s, in order.
    pub window_times: Vec<f64>,
    /// Each window's bias, NED, m.
    pub biases: Vec<Vector3<f64>>,
}

impl DriftFit {
    /// The bias the model predicts at `t` from the nearest window (decayed
    /// towards zero by the process, `φ·b`) and its standard deviation per
    /// axis, `σ·√(1 - φ²)`, from the walk since that window.
    pub fn predict(&self, t: f64, drift: &GnssDrift) -> (Vector3<f64>, Vector3<f64>) {
        let Some((k, dt)) = self
            .window_times
            .iter()
            .map(|w| (t - w).abs())
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
        else {
            return (
                Vector3::zeros(),
                Vector3::new(drift.sigma_xy_m, drift.sigma_xy_m, drift.sigma_z_m),
            );
        };
        let phi = (-dt / drift.tau_s).exp();
        let walk = (1.0 - phi * phi).max(0.0).sqrt();
        (
            self.biases[k] * phi,
            Vector3::new(drift.sigma_xy_m, drift.sigma_xy_m, drift.sigma_z_m) * walk,
        )
    }
}

/// [`fit_with_drift`] on `inliers`, then the pairs a single Sim(3) called
/// outliers (`others`) readmitted where the drift explains them: a pair
/// whose distance from the model plus the bias predicted at its time
/// ([`DriftFit::predict`]) is within `threshold_m` plus three standard
/// deviations of the walk since the nearest window. A bias that wandered
/// further than the threshold from the flight's mean since the survey
/// otherwise makes the newest pairs outliers, and the fit never follows
/// it; a keyframe far off where the pairs are dense is still out. Refits
/// until no pair is readmitted (at most three rounds). Returns the fit and
/// the pairs it used.
pub fn fit_with_drift_readmitting<'a>(
    inliers: Vec<&'a Pair>,
    mut others: Vec<&'a Pair>,
    model: Sim3,
    drift: &GnssDrift,
    keep_rotation: bool,
    threshold_m: f64,
) -> Option<(DriftFit, Vec<&'a Pair>)> {
    let mut used = inliers;
    let mut fit = fit_with_drift(&used, model, drift, keep_rotation)?;
    for _ in 0..3 {
        let mut base = fit.ned_from_map;
        base.translation -= fit.newest_bias;
        let (back, out): (Vec<&Pair>, Vec<&Pair>) = others.iter().partition(|p| {
            let (bias, sd) = fit.predict(p.time, drift);
            let e = p.p_ned.coords - base.transform_point(&p.p_map).coords - bias;
            e.norm() <= threshold_m + 3.0 * sd.norm()
        });
        if back.is_empty() {
            break;
        }
        let mut trial = used.clone();
        trial.extend(back);
        match fit_with_drift(&trial, model, drift, keep_rotation) {
            Some(f) => {
                fit = f;
                used = trial;
                others = out;
            }
            None => break,
        }
    }
    Some((fit, used))
}

/// Fits the map → NED similarity with one GNSS bias state per window (see
/// the module documentation), starting from `model`. With
/// `keep_rotation`, the scale and rotation of `model` are kept (a fit
/// already refined with orientations) and only the translation and the
/// biases are solved. `None` for fewer than three pairs, an invalid drift
/// model, a degenerate Umeyama or a result that is not a finite
/// similarity with a positive scale.
pub fn fit_with_drift(
    pairs: &[&Pair],
    model: Sim3,
    drift: &GnssDrift,
    keep_rotation: bool,
) -> Option<DriftFit> {
    if pairs.len() < 3 || !drift.is_valid() {
        return None;
    }
    // Windows in time order; the pairs' window indices.
    let mut order: Vec<usize> = (0..pairs.len()).collect();
    order.sort_by(|&a, &b| pairs[a].time.total_cmp(&pairs[b].time));
    let mut window_of = vec![0usize; pairs.len()];
    let mut window_t: Vec<(f64, usize)> = Vec::new(); // (sum of times, count)
    let mut start = f64::NAN;
    for &i in &order {
        let t = pairs[i].time;
        if window_t.is_empty() || t - start >= drift.window_s {
            window_t.push((0.0, 0));
            start = t;
        }
        let k = window_t.len() - 1;
        window_t[k].0 += t;
        window_t[k].1 += 1;
        window_of[i] = k;
    }
    let times: Vec<f64> = window_t.iter().map(|(s, n)| s / *n as f64).collect();
    let counts: Vec<f64> = window_t.iter().map(|(_, n)| *n as f64).collect();
    let w = times.len();
    // φ_k between window k and k+1.
    let phi: Vec<f64> = times
        .windows(2)
        .map(|t| (-(t[1] - t[0]).max(0.0) / drift.tau_s).exp())
        .collect();

    let src: Vec<Point3<f64>> = pairs.iter().map(|p| p.p_map).collect();
    let mut model = model;
    let mut bias = vec![Vector3::<f64>::zeros(); w];
    // The translation of the last bias solve (Umeyama moves the model's).
    let mut t_prev = model.translation;
    for _ in 0..drift.iterations.max(1) {
        if !keep_rotation {
            let dst: Vec<Point3<f64>> = pairs
                .iter()
                .zip(&window_of)
                .map(|(p, &k)| p.p_ned - bias[k])
                .collect();
            model = umeyama(&src, &dst, true).ok()?;
        }
        // What the translation and the biases must explain.
        let mut sums = vec![Vector3::<f64>::zeros(); w];
        for (p, &k) in pairs.iter().zip(&window_of) {
            let e = p.p_ned.coords - (model.transform_point(&p.p_map).coords - model.translation);
            sums[k] += e;
        }
        let mut moved: f64 = 0.0;
        let mut t_new = Vector3::zeros();
        for axis in 0..3 {
            let (sigma, noise) = if axis < 2 {
                (drift.sigma_xy_m, drift.noise_xy_m)
            } else {
                (drift.sigma_z_m, drift.noise_z_m)
            };
            let s: Vec<f64> = sums.iter().map(|v| v[axis]).collect();
            let (t_axis, b_axis) = solve_axis(&s, &counts, &phi, sigma, noise)?;
            t_new[axis] = t_axis;
            for (b, v) in bias.iter_mut().zip(&b_axis) {
                moved = moved.max((b[axis] - v).abs());
                b[axis] = *v;
            }
        }
        moved = moved.max((t_new - t_prev).amax());
        t_prev = t_new;
        model.translation = t_new;
        if moved < 1e-5 {
            break;
        }
    }
    let residuals = pairs
        .iter()
        .zip(&window_of)
        .map(|(p, &k)| (model.transform_point(&p.p_map).coords + bias[k] - p.p_ned.coords).norm())
        .collect();
    let newest_bias = bias[w - 1];
    let mut ned_from_map = model;
    ned_from_map.translation += newest_bias;
    let ok = ned_from_map.scale.is_finite()
        && ned_from_map.scale > 0.0
        && ned_from_map.translation.iter().all(|v| v.is_finite())
        && newest_bias.iter().all(|v| v.is_finite());
    ok.then_some(DriftFit {
        ned_from_map,
        newest_bias,
        residuals,
        windows: w,
        window_times: times,
        biases: bias,
    })
}

/// One axis: minimises `Σ_k Σ_{i∈k} (t + b_k - e_i)²/σ_n² + b_0²/σ² +
/// Σ_k (b_{k+1} - φ_k·b_k)²/(σ²·(1 - φ_k²))` given per window the sum of
/// `e_i` (`sums`) and the count (`counts`). The normal equations are a
/// symmetric tridiagonal `A` in the biases bordered by `t`: `b = A⁻¹(r -
/// c·t)` and `t` from its Schur complement.
fn solve_axis(
    sums: &[f64],
    counts: &[f64],
    phi: &[f64],
    sigma: f64,
    noise: f64,
) -> Option<(f64, Vec<f64>)> {
    let w = sums.len();
    let wn = 1.0 / (noise * noise);
    let wb = 1.0 / (sigma * sigma);
    let mut diag: Vec<f64> = counts.iter().map(|n| n * wn).collect();
    let mut off = vec![0.0; w.saturating_sub(1)];
    diag[0] += wb;
    for k in 0..w.saturating_sub(1) {
        let q = (1.0 - phi[k] * phi[k]).max(1e-12) / wb;
        diag[k] += phi[k] * phi[k] / q;
        diag[k + 1] += 1.0 / q;
        off[k] = -phi[k] / q;
    }
    let c: Vec<f64> = counts.iter().map(|n| n * wn).collect();
    let r: Vec<f64> = sums.iter().map(|s| s * wn).collect();
    let a_inv_r = thomas(&diag, &off, &r)?;
    let a_inv_c = thomas(&diag, &off, &c)?;
    let n_total: f64 = counts.iter().sum::<f64>() * wn;
    let r_t: f64 = r.iter().sum();
    let schur = n_total - c.iter().zip(&a_inv_c).map(|(a, b)| a * b).sum::<f64>();
    let rhs = r_t - c.iter().zip(&a_inv_r).map(|(a, b)| a * b).sum::<f64>();
    if !(schur.is_finite() && schur > 0.0) {
        return None;
    }
    let t = rhs / schur;
    let b = a_inv_r
        .iter()
        .zip(&a_inv_c)
        .map(|(x, y)| x - y * t)
        .collect();
    Some((t, b))
}

/// Solves the symmetric tridiagonal system (diagonal `d`, off-diagonal
/// `e`) for `r` by the Thomas algorithm; `None` on a zero pivot.
fn thomas(d: &[f64], e: &[f64], r: &[f64]) -> Option<Vec<f64>> {
    let n = d.len();
    let mut cp = vec![0.0; n];
    let mut x = vec![0.0; n];
    let mut den = d[0];
    if den.abs() < 1e-300 {
        return None;
    }
    cp[0] = if n > 1 { e[0] / den } else { 0.0 };
    x[0] = r[0] / den;
    for i in 1..n {
        den = d[i] - e[i - 1] * cp[i - 1];
        if den.abs() < 1e-300 {
            return None;
        }
        cp[i] = if i + 1 < n { e[i] / den } else { 0.0 };
        x[i] = (r[i] - e[i - 1] * x[i - 1]) / den;
    }
    for i in (0..n.saturating_sub(1)).rev() {
        x[i] -= cp[i] * x[i + 1];
    }
    Some(x)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    /// A standard normal sample (Box-Muller).
    fn gauss(rng: &mut SmallRng) -> f64 {
        let u: f64 = rng.random::<f64>().max(1e-300);
        let v: f64 = rng.random();
        (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
    }

    /// A flight over `secs` at 2 pairs a second across a 60 m square, its
    /// GNSS with a Gauss-Markov bias (σ 1 m, τ 120 s) and 0.2 m noise; the
    /// map a scaled, turned, shifted copy of the truth.
    fn flight(seed: u64, secs: f64) -> (Vec<Pair>, Sim3, Vector3<f64>) {
        let mut rng = SmallRng::seed_from_u64(seed);
        let truth = Sim3 {
            scale: 4.0,
            rotation: UnitQuaternion::from_euler_angles(0.1, -0.2, 1.0),
            translation: Vector3::new(3.0, -7.0, 1.0),
        };
        let map_from_ned = truth.inverse();
        let dt = 0.5;
        let phi: f64 = (-dt / 120.0f64).exp();
        let mut b = Vector3::from_fn(|_, _| gauss(&mut rng));
        let mut pairs = Vec::new();
        let mut t = 0.0;
        let mut b_newest = b;
        while t < secs {
            let true_ned = Point3::new(
                30.0 * (t * 0.05).sin(),
                30.0 * (t * 0.031).cos(),
                -20.0 - 3.0 * (t * 0.1).sin(),
            );
            let noise = Vector3::from_fn(|_, _| 0.2 * gauss(&mut rng));
            pairs.push(Pair {
                kf_id: pairs.len() as u64,
                p_map: map_from_ned.transform_point(&true_ned),
                p_ned: true_ned + b + noise,
                time: t,
                orientations: None,
                v_ned: None,
            });
            b_newest = b;
            let q = (1.0 - phi * phi).sqrt();
            b = b * phi + Vector3::from_fn(|_, _| q * gauss(&mut rng));
            t += dt;
        }
        (pairs, truth, b_newest)
    }

    /// The error of a fit's prediction of where the receiver reads the
    /// newest map point now (its true position plus the bias `b` then,
    /// without the pair's noise): what a shot's target inherits.
    fn now_error(fit: &Sim3, truth: &Sim3, pairs: &[Pair], b: &Vector3<f64>) -> f64 {
        let m = pairs.last().unwrap().p_map;
        (fit.transform_point(&m).coords - truth.transform_point(&m).coords - b).norm()
    }

    #[test]
    fn the_fit_follows_the_bias_the_receiver_reads_now() {
        let (mut plain_err, mut drift_err) = (Vec::new(), Vec::new());
        for seed in 0..20 {
            let (pairs, truth, b) = flight(seed, 300.0);
            let refs: Vec<&Pair> = pairs.iter().collect();
            let src: Vec<_> = pairs.iter().map(|p| p.p_map).collect();
            let dst: Vec<_> = pairs.iter().map(|p| p.p_ned).collect();
            let plain = umeyama(&src, &dst, true).unwrap();
            let fit = fit_with_drift(&refs, plain, &GnssDrift::default(), false).unwrap();
            assert_eq!(fit.windows, 150);
            // The bias is a translation: scale and rotation are no worse
            // than a plain fit's (both carry what a metre of wander over a
            // 60 m flight does to them).
            let scale_err = |f: &Sim3| (f.scale / truth.scale - 1.0).abs();
            let rot_err = |f: &Sim3| (f.rotation.inverse() * truth.rotation).angle().to_degrees();
            assert!(
                scale_err(&fit.ned_from_map) < scale_err(&plain) + 0.003,
                "scale {:.4} vs {:.4}",
                scale_err(&fit.ned_from_map),
                scale_err(&plain)
            );
            assert!(
                rot_err(&fit.ned_from_map) < rot_err(&plain) + 0.3,
                "rotation {:.2} vs {:.2} deg",
                rot_err(&fit.ned_from_map),
                rot_err(&plain)
            );
            plain_err.push(now_error(&plain, &truth, &pairs, &b));
            drift_err.push(now_error(&fit.ned_from_map, &truth, &pairs, &b));
        }
        let med = |v: &mut Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v[v.len() / 2]
        };
        let (p, d) = (med(&mut plain_err), med(&mut drift_err));
        println!(
            "where the receiver reads the map now, median of 20: plain {p:.2} m, drift {d:.2} m"
        );
        // Over five minutes the bias wanders about a metre: the plain fit
        // misses where the receiver reads now by that, the drift fit by
        // the noise of the newest windows.
        assert!(p > 0.5, "plain {p:.2} m");
        assert!(d < 0.4, "drift {d:.2} m");
        assert!(d < 0.5 * p, "drift {d:.2} m vs plain {p:.2} m");
    }

    #[test]
    fn kept_rotation_solves_only_the_translation_and_the_biases() {
        let (pairs, truth, b_newest) = flight(7, 120.0);
        let refs: Vec<&Pair> = pairs.iter().collect();
        let fit = fit_with_drift(&refs, truth, &GnssDrift::default(), true).unwrap();
        assert_eq!(fit.ned_from_map.scale, truth.scale);
        assert_eq!(fit.ned_from_map.rotation, truth.rotation);
        // The newest bias plus the translation is what the receiver reads:
        // within the noise of a few windows.
        let off = fit.ned_from_map.translation - (truth.translation + b_newest);
        assert!(off.norm() < 0.4, "{off:?}");
        // What is left after each window's bias is the pairs' noise (0.2 m
        // per axis, 0.35 m as a distance), not the bias's wander.
        let rms =
            (fit.residuals.iter().map(|r| r * r).sum::<f64>() / fit.residuals.len() as f64).sqrt();
        let plain = (pairs
            .iter()
            .map(|p| (truth.transform_point(&p.p_map) - p.p_ned).norm_squared())
            .sum::<f64>()
            / pairs.len() as f64)
            .sqrt();
        println!(
            "residual RMS after the window biases {rms:.3} m, of the truth without them {plain:.3} m"
        );
        assert!(rms < 0.4 && rms < 0.5 * plain, "{rms:.3} m vs {plain:.3} m");
    }

    /// Through the georeference's own fit (RANSAC, refit, orientations
    /// off): with a drift model its quality reports the newest bias and
    /// the fit maps into the NED the receiver reads at the newest pair.
    #[test]
    fn the_georeference_fit_estimates_the_bias_with_a_drift_model() {
        let params = |drift| super::super::AlignParams {
            inlier_threshold_m: 3.0,
            refine_with_orientations: false,
            estimate_time_offset: false,
            drift,
            ..super::super::AlignParams::default()
        };
        let (mut plain_err, mut drift_err) = (Vec::new(), Vec::new());
        for seed in 100..110 {
            let (pairs, truth, b) = flight(seed, 300.0);
            let plain = super::super::fit_pairs(&pairs, &params(None), None, 1).unwrap();
            let with =
                super::super::fit_pairs(&pairs, &params(Some(GnssDrift::default())), None, 1)
                    .unwrap();
            assert!(plain.quality.gnss_bias_m.is_none());
            assert!(with.quality.gnss_bias_m.is_some());
            // Residuals after each window's bias: the noise, not the wander.
            assert!(with.quality.rms_m < 0.6 && with.quality.rms_m < plain.quality.rms_m);
            plain_err.push(now_error(&plain.ned_from_map, &truth, &pairs, &b));
            drift_err.push(now_error(&with.ned_from_map, &truth, &pairs, &b));
        }
        plain_err.sort_by(f64::total_cmp);
        drift_err.sort_by(f64::total_cmp);
        let (p, d) = (plain_err[5], drift_err[5]);
        println!("through fit_pairs, median of 10: plain {p:.2} m, drift {d:.2} m");
        assert!(d < 0.4 && d < 0.5 * p, "drift {d:.2} m vs plain {p:.2} m");
    }

    #[test]
    fn bad_input_gives_none() {
        let (pairs, truth, _) = flight(1, 5.0);
        let refs: Vec<&Pair> = pairs.iter().take(2).collect();
        assert!(fit_with_drift(&refs, truth, &GnssDrift::default(), false).is_none());
        let refs: Vec<&Pair> = pairs.iter().collect();
        let bad = GnssDrift {
            tau_s: 0.0,
            ..GnssDrift::default()
        };
        assert!(fit_with_drift(&refs, truth, &bad, false).is_none());
    }

    #[test]
    fn pairs_the_drift_explains_are_readmitted_and_a_gross_error_is_not() {
        let (mut pairs, truth, b_newest) = flight(3, 300.0);
        // A keyframe 10 m off in the middle of the survey, where the pairs
        // are dense.
        pairs[300].p_ned += Vector3::new(6.0, -8.0, 0.0);
        // Two minutes later, three frames where the bias has wandered 2.6 m
        // from the survey's newest (beyond the 0.5 m threshold).
        let moved = b_newest + Vector3::new(2.0, -1.5, 0.5);
        let late: Vec<Pair> = (0..3)
            .map(|i| {
                let true_ned = Point3::new(5.0 + i as f64, -3.0, -20.0);
                Pair {
                    kf_id: 10_000 + i,
                    p_map: truth.inverse().transform_point(&true_ned),
                    p_ned: true_ned + moved,
                    time: 420.0 + 0.4 * i as f64,
                    orientations: None,
                    v_ned: None,
                }
            })
            .collect();
        let inliers: Vec<&Pair> = pairs.iter().filter(|p| p.kf_id != 300).collect();
        let mut others: Vec<&Pair> = late.iter().collect();
        others.push(&pairs[300]);
        let drift = GnssDrift::default();
        let (fit, used) =
            fit_with_drift_readmitting(inliers.clone(), others, truth, &drift, false, 0.5).unwrap();
        let without = fit_with_drift(&inliers, truth, &drift, false).unwrap();
        let ids: Vec<u64> = used.iter().map(|p| p.kf_id).collect();
        assert!(
            ids.contains(&10_000) && ids.contains(&10_002),
            "the late frames are back"
        );
        assert!(!ids.contains(&300), "the gross error stays out");
        // Where the receiver reads a late frame's map point now.
        let m = late[1].p_map;
        let miss = |f: &DriftFit| {
            (f.ned_from_map.transform_point(&m).coords - truth.transform_point(&m).coords - moved)
                .norm()
        };
        println!(
            "a late frame read off where the receiver reads it by {:.2} m readmitting, {:.2} m without",
            miss(&fit),
            miss(&without)
        );
        assert!(miss(&fit) < 0.5, "{:.2}", miss(&fit));
        assert!(miss(&without) > 1.5, "{:.2}", miss(&without));
    }
}
