//! The rolling shutter's readout estimated from a flight (issue 35, point
//! 3).
//!
//! How the SLAM uses a known readout: a frame being tracked takes its
//! motion over the readout from the constant-velocity model (`tracking`,
//! between two frames vision posed); a keyframe in bundle adjustment from
//! the keyframes taken just before and after it, as the poses stand at each
//! step ([`super::bundle::attach_shutters`]), so it follows every
//! correction and scaling of the map with nothing stored beside the poses,
//! and the adjustment cannot change the translation's share by rescaling
//! the map.
//!
//! The readout is the camera's (`[camera] readout_ms`); when it is not
//! known, [`estimate_readout`] finds it from a map: the bundle adjustment
//! of the whole map is run again under each readout of a grid, and the one
//! whose adjustment fits the observations best (the least robust cost) is
//! taken, refined by a parabola through its neighbours. What the readout
//! explains is the image's row-dependent shift under motion, which no pose
//! can fit; under too short or too long a readout the residuals keep it.

use crate::optimize::{self, BaParams};

use super::bundle::{attach_shutters, build_ba_problem, whole_map_gauge};
use super::map::{KeyFrameId, Map};

/// LM iterations of each of [`estimate_readout`]'s adjustments, at least.
const MIN_ITERATIONS: usize = 20;

/// One readout tried by [`estimate_readout`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ReadoutTrial {
    /// The readout, seconds.
    pub readout_s: f64,
    /// The adjustment's robust cost at its end.
    pub cost: f64,
    /// Its reprojection RMSE at the end, pixels per coordinate.
    pub rmse_px: f64,
}

/// What [`estimate_readout`] found.
#[derive(Debug, Clone, PartialEq)]
pub struct ReadoutEstimate {
    /// The estimate, seconds (the grid's best, refined by a parabola
    /// through it and its neighbours).
    pub readout_s: f64,
    /// Every readout tried, in the grid's order.
    pub trials: Vec<ReadoutTrial>,
}

/// Estimates the camera's rolling-shutter readout from a map: the bundle
/// adjustment of all its keyframes (the first of each map held) and points
/// is run under each readout of `grid_s` (seconds, increasing, at least 3,
/// equally spaced for the parabola), at least [`MIN_ITERATIONS`] LM
/// iterations, robust kernel, no outlier removal, so
/// every run weighs the same observations; the least final cost wins. The
/// map itself is not changed. `None` with fewer than 3 readouts, a map
/// with nothing to adjust, or an adjustment that fails.
pub fn estimate_readout(map: &Map, grid_s: &[f64], params: &BaParams) -> Option<ReadoutEstimate> {
    if grid_s.len() < 3 || grid_s.windows(2).any(|w| w[1].is_nan() || w[1] <= w[0]) {
        return None;
    }
    let kfs: Vec<KeyFrameId> = map.keyframes().map(|k| k.id).collect();
    let fixed = whole_map_gauge(map, &kfs);
    let setup = build_ba_problem(map, &kfs, &fixed)?;
    // Each run to convergence (or near it), so the costs compare minima.
    let params = BaParams {
        first_pass_iterations: params.first_pass_iterations.max(MIN_ITERATIONS),
        second_pass_iterations: 0,
        ..params.clone()
    };
    let mut trials = Vec::with_capacity(grid_s.len());
    for &readout_s in grid_s {
        let mut trial = setup.clone();
        attach_shutters(map, &mut trial, readout_s);
        let report = optimize::local_bundle_adjustment(&mut trial.problem, &params).ok()?;
        trials.push(ReadoutTrial {
            readout_s,
            cost: report.first_pass.final_cost,
            rmse_px: report.final_rmse_px,
        });
    }
    let best = trials
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.cost.total_cmp(&b.1.cost))
        .map(|(i, _)| i)?;
    let readout_s = if best == 0 || best + 1 == trials.len() {
        trials[best].readout_s
    } else {
        let (a, b, c) = (trials[best - 1], trials[best], trials[best + 1]);
        // The vertex of the parabola through three equally spaced points.
        let h = c.readout_s - b.readout_s;
        let curvature = a.cost - 2.0 * b.cost + c.cost;
        if curvature > 0.0 {
            b.readout_s + 0.5 * h * (a.cost - c.cost) / curvature
        } else {
            b.readout_s
        }
    };
    Some(ReadoutEstimate { readout_s, trials })
}
