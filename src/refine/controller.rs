//! The refinement controller: once the vehicle stands at its target and the
//! view is steady, the live frame is localised in the map; the difference
//! between the desired camera pose and the live one, both carried through
//! the same georeference, is the correction added to the current target.
//!
//! Errors the georeference makes in the same way for both poses (a scale
//! or heading error of the map → NED fit, a mounting offset, the vehicle's
//! own position bias) cancel in the difference, so the loop converges where
//! one open-loop estimate does not. Every corrected target passes the same
//! checks as the first ([`crate::mission::plan::check_target`]: geofence and
//! altitude band) and the gimbal's pitch range.

use nalgebra::{Isometry3, Vector3};

use super::RefineError;
use crate::geo::{GeoAlignment, GeoTarget, Geodetic, LocalFrame, MountParams, convert_target};
use crate::mission::plan::{self, Fence, Home, Target};

/// Every tunable number of the controller.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ControllerParams {
    /// Stop when the shot error is below this percentage of the image
    /// diagonal.
    pub threshold_pct: f64,
    /// Corrections uploaded at most (rounds after the first flight).
    pub max_rounds: usize,
    /// Fraction of the measured error corrected per round (1: all of it).
    pub gain: f64,
    /// Largest horizontal or vertical move of one correction, metres.
    pub max_step_m: f64,
    /// Largest yaw or pitch change of one correction, degrees.
    pub max_step_deg: f64,
}

impl Default for ControllerParams {
    fn default() -> Self {
        Self {
            threshold_pct: 1.0,
            max_rounds: 4,
            gain: 1.0,
            max_step_m: 10.0,
            max_step_deg: 20.0,
        }
    }
}

/// Why the loop ends (or that it goes on).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Decision {
    /// The shot error is under the threshold.
    Converged,
    /// The round budget is spent.
    MaxRounds,
    /// Upload a correction.
    Correct,
}

/// Whether to correct again after a measured shot error (percent of the
/// diagonal; `None` when it could not be measured) with `rounds_done`
/// corrections already flown.
pub fn decide(
    shot_error_pct: Option<f64>,
    rounds_done: usize,
    params: &ControllerParams,
) -> Decision {
    match shot_error_pct {
        Some(e) if e < params.threshold_pct => Decision::Converged,
        _ if rounds_done >= params.max_rounds => Decision::MaxRounds,
        _ => Decision::Correct,
    }
}

/// A corrected target and what it changed.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Correction {
    /// The new target (checked).
    pub target: Target,
    /// Vehicle position change, local NED metres.
    pub step_ned_m: [f64; 3],
    /// Yaw change, degrees.
    pub yaw_step_deg: f64,
    /// Gimbal pitch change, degrees.
    pub pitch_step_deg: f64,
    /// The step was shortened to the per-round limits.
    pub limited: bool,
}

fn wrap180(d: f64) -> f64 {
    let x = (d + 180.0).rem_euclid(360.0) - 180.0;
    if x <= -180.0 { x + 360.0 } else { x }
}

/// The corrected target from the desired and the live camera poses, both
/// already converted to vehicle targets by the same georeference:
/// `current + gain · (desired − live)` in position (local NED around home),
/// yaw and gimbal pitch, limited per round, then checked like the first.
pub fn correct_targets(
    desired: &GeoTarget,
    live: &GeoTarget,
    current: &Target,
    home: &Home,
    fence: &Fence,
    mount: &MountParams,
    params: &ControllerParams,
) -> Result<Correction, RefineError> {
    if !(params.gain.is_finite() && params.gain > 0.0 && params.gain <= 1.0) {
        return Err(RefineError::InvalidParams {
            name: "gain",
            reason: "must be in (0, 1]",
        });
    }
    plan::check_target(current, home, fence).map_err(RefineError::Target)?;
    let mut step = (desired.p_ned_vehicle - live.p_ned_vehicle) * params.gain;
    let mut dyaw = wrap180(desired.yaw_deg - live.yaw_deg) * params.gain;
    let mut dpitch = (desired.gimbal_pitch_deg - live.gimbal_pitch_deg) * params.gain;
    if !(step.iter().all(|x| x.is_finite()) && dyaw.is_finite() && dpitch.is_finite()) {
        return Err(RefineError::NonFinite { what: "correction" });
    }
    let mut limited = false;
    let horiz = step.xy().norm();
    if horiz > params.max_step_m {
        let s = params.max_step_m / horiz;
        step.x *= s;
        step.y *= s;
        limited = true;
    }
    if step.z.abs() > params.max_step_m {
        step.z = step.z.signum() * params.max_step_m;
        limited = true;
    }
    for d in [&mut dyaw, &mut dpitch] {
        if d.abs() > params.max_step_deg {
            *d = d.signum() * params.max_step_deg;
            limited = true;
        }
    }
    let frame = LocalFrame::new(Geodetic {
        lat_deg: home.lat_deg,
        lon_deg: home.lon_deg,
        alt_m: home.alt_amsl_m,
    });
    let cur_ned = frame.geodetic_to_ned(&Geodetic {
        lat_deg: current.lat_deg,
        lon_deg: current.lon_deg,
        alt_m: home.alt_amsl_m + current.alt_m,
    });
    let new_ned = cur_ned + Vector3::new(step.x, step.y, step.z);
    let g = frame.ned_to_geodetic(&new_ned);
    let pitch = current.gimbal_pitch_deg + dpitch;
    if pitch < mount.pitch_min_deg || pitch > mount.pitch_max_deg {
        return Err(RefineError::PitchOutOfRange {
            pitch_deg: pitch,
            min_deg: mount.pitch_min_deg,
            max_deg: mount.pitch_max_deg,
        });
    }
    let target = Target {
        lat_deg: g.lat_deg,
        lon_deg: g.lon_deg,
        alt_m: g.alt_m - home.alt_amsl_m,
        yaw_deg: (current.yaw_deg + dyaw).rem_euclid(360.0),
        gimbal_pitch_deg: pitch,
        photo: current.photo,
    };
    plan::check_target(&target, home, fence).map_err(RefineError::Target)?;
    Ok(Correction {
        target,
        step_ned_m: [step.x, step.y, step.z],
        yaw_step_deg: dyaw,
        pitch_step_deg: dpitch,
        limited,
    })
}

/// The corrected target from the desired and the live camera poses in the
/// map (`map ← cam`), converted through the georeference `alignment`
/// (see [`correct_targets`]).
#[allow(clippy::too_many_arguments)]
pub fn correct(
    alignment: &GeoAlignment,
    frame: &LocalFrame,
    mount: &MountParams,
    map_from_desired: &Isometry3<f64>,
    map_from_live: &Isometry3<f64>,
    current: &Target,
    home: &Home,
    fence: &Fence,
    params: &ControllerParams,
) -> Result<Correction, RefineError> {
    let desired =
        convert_target(alignment, map_from_desired, frame, mount).map_err(RefineError::Geo)?;
    let live = convert_target(alignment, map_from_live, frame, mount).map_err(RefineError::Geo)?;
    correct_targets(&desired, &live, current, home, fence, mount, params)
}
