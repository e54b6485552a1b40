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
use crate::angle::wrap180;
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
    /// Fraction of the measured error corrected by the first correction
    /// (1: all of it; the first error is mostly systematic).
    pub gain: f64,
    /// Largest fraction corrected by the later ones. Each later
    /// correction removes the share of the measured offset that the
    /// measurement supports against what is already known (per axis, the
    /// Kalman gain `P / (P + R)`: `P` the offset's variance, grown by the
    /// drift since the last measurement, `R` the measurement's own), at
    /// most this (1: the filter alone decides).
    pub later_gain: f64,
    /// Growth of the variance of the vehicle's position offset (true minus
    /// reported position) per second between two measurements, m²/s per
    /// axis. A GNSS bias of deviation σ and correlation time τ drifts by
    /// 2σ²/τ per second: 0.028 for the `field` receiver (1.3 m, 120 s),
    /// 0.017 for 1 m and 120 s.
    pub position_drift_m2_per_s: f64,
    /// The same for the heading and gimbal pitch offsets (mounting and
    /// compass errors hardly drift), deg²/s.
    pub angle_drift_deg2_per_s: f64,
    /// A change of the target smaller than this many standard deviations
    /// of the measurement (per axis) is not flown: it is noise.
    pub gate_sigmas: f64,
    /// Largest horizontal or vertical move of one correction, metres.
    pub max_step_m: f64,
    /// Largest yaw or pitch change of one correction, degrees.
    pub max_step_deg: f64,
    /// A shot whose floor is known stops `at_floor` when its error is
    /// within this many percent of the diagonal of the floor (or within
    /// twice the measured error's own noise, if larger): what a correction
    /// could still gain is then within what the measurement can tell, and
    /// a loop that flies on chases noise.
    pub at_floor_margin_pct: f64,
    /// Near its floor (the error within this many percent of it) after a
    /// correction, the loop ends `at_floor`: the floor estimate sits a few
    /// tenths under what the vehicle reaches (browser whole-shot runs
    /// measured 0.3-0.7 % above it round after round) and the GNSS drift
    /// between two looks moves the view by as much, so a further round
    /// chases noise. It stops on the view it measures when the correction
    /// gained or came within [`Self::at_floor_margin_pct`] of the best
    /// round; when it measured worse than that, the vehicle first flies
    /// back to the best round's view (a correction toward the live camera
    /// pose measured then, through the offset measured now: the same
    /// target would not do, the GNSS bias drifts between rounds). Only for
    /// a shot whose floor is not more than the margin under the
    /// threshold: one that can converge flies on toward it.
    pub stall_band_pct: f64,
}

impl Default for ControllerParams {
    fn default() -> Self {
        Self {
            threshold_pct: 1.0,
            max_rounds: 4,
            gain: 1.0,
            later_gain: 1.0,
            position_drift_m2_per_s: 0.02,
            angle_drift_deg2_per_s: 0.002,
            gate_sigmas: 2.0,
            max_step_m: 10.0,
            max_step_deg: 20.0,
            at_floor_margin_pct: 0.3,
            stall_band_pct: 1.0,
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
    /// The shot error is above the threshold, but the correction the
    /// measurement asks for is within its own noise on every axis: the
    /// camera stands where the localisation can tell, nothing to fly.
    WithinNoise,
    /// The shot error is at the shot's own floor (no camera pose can
    /// reproduce the desired shot better; see [`super::reachable`]): the
    /// live view is within the threshold of the reachable framing.
    AtFloor,
    /// Upload a correction.
    Correct,
    /// Near the floor, the last correction measured worse than an earlier
    /// round: fly back to that round's view and stop there (`at_floor`).
    ReturnToBest,
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
    /// What the step corrects: the desired minus the live vehicle
    /// position (local NED metres) through the georeference, before the
    /// gain and the limits.
    pub error_ned_m: [f64; 3],
    /// The desired minus the live heading, degrees, before the gain.
    pub yaw_error_deg: f64,
    /// The desired minus the live gimbal pitch, degrees, before the gain.
    pub pitch_error_deg: f64,
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
    if !(params.later_gain.is_finite() && params.later_gain > 0.0 && params.later_gain <= 1.0) {
        return Err(RefineError::InvalidParams {
            name: "later_gain",
            reason: "must be in (0, 1]",
        });
    }
    if !(params.gain.is_finite() && params.gain > 0.0 && params.gain <= 1.0) {
        return Err(RefineError::InvalidParams {
            name: "gain",
            reason: "must be in (0, 1]",
        });
    }
    plan::check_target(current, home, fence).map_err(RefineError::Target)?;
    let error = desired.p_ned_vehicle - live.p_ned_vehicle;
    let yaw_error = wrap180(desired.yaw_deg - live.yaw_deg);
    let pitch_error = desired.gimbal_pitch_deg - live.gimbal_pitch_deg;
    let mut step = error * params.gain;
    let mut dyaw = yaw_error * params.gain;
    let mut dpitch = pitch_error * params.gain;
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
        error_ned_m: error.into(),
        yaw_error_deg: yaw_error,
        pitch_error_deg: pitch_error,
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::{GimbalAngles, VehicleState, ned_from_cam};
    use crate::geometry::Sim3;
    use nalgebra::{Point3, Translation3, UnitQuaternion};

    const HOME: Home = Home {
        lat_deg: 47.397742,
        lon_deg: 8.545594,
        alt_amsl_m: 488.0,
    };

    fn frame() -> LocalFrame {
        LocalFrame::new(Geodetic {
            lat_deg: HOME.lat_deg,
            lon_deg: HOME.lon_deg,
            alt_m: HOME.alt_amsl_m,
        })
    }

    fn alignment(ned_from_map: Sim3) -> GeoAlignment {
        GeoAlignment::given(ned_from_map)
    }

    /// The camera pose (NED) of a vehicle hovering exactly at `target`.
    fn fly(target: &Target, mount: &MountParams) -> Isometry3<f64> {
        let p = frame().geodetic_to_ned(&Geodetic {
            lat_deg: target.lat_deg,
            lon_deg: target.lon_deg,
            alt_m: HOME.alt_amsl_m + target.alt_m,
        });
        let state = VehicleState {
            time: 0.0,
            p_ned: p,
            v_ned: Vector3::zeros(),
            ned_from_body: UnitQuaternion::from_euler_angles(0.0, 0.0, target.yaw_deg.to_radians()),
            gimbal: GimbalAngles {
                pitch: target.gimbal_pitch_deg.to_radians(),
                yaw: 0.0,
            },
        };
        ned_from_cam(&state, mount)
    }

    fn map_pose(map_from_ned: &Sim3, ned_from_cam: &Isometry3<f64>) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(
                map_from_ned
                    .transform_point(&Point3::from(ned_from_cam.translation.vector))
                    .coords,
            ),
            map_from_ned.rotation * ned_from_cam.rotation,
        )
    }

    #[test]
    fn a_wrong_georeference_is_corrected_in_a_few_rounds() {
        let mount = MountParams::default();
        let fence = Fence::default();
        // The true map ← NED and an estimate 3 % off in scale, 2 deg off in
        // heading and 1.5 m off in position.
        let ned_from_map = Sim3::new(
            UnitQuaternion::from_euler_angles(0.7, -0.3, 1.9),
            Vector3::new(4.0, -7.0, -3.0),
            8.0,
        );
        let map_from_ned = ned_from_map.inverse();
        let estimate = alignment(
            Sim3::new(
                UnitQuaternion::from_euler_angles(0.0, 0.0, 2f64.to_radians()),
                Vector3::new(1.0, -1.0, 0.5),
                1.03,
            )
            .compose(&ned_from_map),
        );
        let truth = crate::geo::target_from_ned(
            &fly(
                &Target {
                    lat_deg: HOME.lat_deg + 2e-4,
                    lon_deg: HOME.lon_deg - 3e-4,
                    alt_m: 18.0,
                    yaw_deg: 250.0,
                    gimbal_pitch_deg: -40.0,
                    photo: false,
                },
                &mount,
            ),
            &frame(),
            &mount,
        )
        .unwrap();
        let desired_ned = truth.ned_from_cam;
        let desired_map = map_pose(&map_from_ned, &desired_ned);
        let mut target = convert_target(&estimate, &desired_map, &frame(), &mount)
            .unwrap()
            .to_mission_target(false);
        let mut errors = Vec::new();
        for _round in 0..5 {
            let live_ned = fly(&target, &mount);
            let d = crate::refine::pose_difference(&desired_ned, &live_ned);
            errors.push((d.position_m, d.rotation_deg));
            let live_map = map_pose(&map_from_ned, &live_ned);
            let c = correct(
                &estimate,
                &frame(),
                &mount,
                &desired_map,
                &live_map,
                &target,
                &HOME,
                &fence,
                &ControllerParams::default(),
            )
            .unwrap();
            target = c.target;
        }
        println!("position / rotation error per round: {errors:?}");
        assert!(errors[0].0 > 1.0 && errors[0].1 > 1.5, "{:?}", errors[0]);
        // Each round shrinks the error by about the georeference's relative
        // error (a few percent): centimetres after two rounds.
        assert!(errors[2].0 < 0.02 && errors[2].1 < 0.05, "{:?}", errors[2]);
        assert!(errors[4].0 < 1e-3 && errors[4].1 < 1e-3, "{:?}", errors[4]);
    }

    fn geo_target(p: Vector3<f64>, yaw_deg: f64, pitch_deg: f64) -> GeoTarget {
        GeoTarget {
            lat_deg: 0.0,
            lon_deg: 0.0,
            alt_above_home_m: -p.z,
            alt_m: 0.0,
            yaw_deg,
            gimbal_pitch_deg: pitch_deg,
            residual_roll_deg: 0.0,
            axis_error_deg: 0.0,
            p_ned_vehicle: p,
            ned_from_cam: Isometry3::identity(),
        }
    }

    fn current() -> Target {
        Target {
            lat_deg: HOME.lat_deg,
            lon_deg: HOME.lon_deg,
            alt_m: 20.0,
            yaw_deg: 355.0,
            gimbal_pitch_deg: -30.0,
            photo: true,
        }
    }

    #[test]
    fn steps_are_added_wrapped_and_limited() {
        let p = ControllerParams::default();
        let desired = geo_target(Vector3::new(3.0, -4.0, -21.0), 5.0, -33.0);
        let live = geo_target(Vector3::new(0.0, 0.0, -20.0), 355.0, -30.0);
        let c = correct_targets(
            &desired,
            &live,
            &current(),
            &HOME,
            &Fence::default(),
            &MountParams::default(),
            &p,
        )
        .unwrap();
        assert!(!c.limited);
        assert!((c.yaw_step_deg - 10.0).abs() < 1e-9);
        assert!((c.target.yaw_deg - 5.0).abs() < 1e-9);
        assert!((c.target.gimbal_pitch_deg + 33.0).abs() < 1e-9);
        assert!((c.target.alt_m - 21.0).abs() < 1e-4, "{}", c.target.alt_m);
        let back = frame().geodetic_to_ned(&Geodetic {
            lat_deg: c.target.lat_deg,
            lon_deg: c.target.lon_deg,
            alt_m: HOME.alt_amsl_m,
        });
        assert!(
            (back.x - 3.0).abs() < 1e-4 && (back.y + 4.0).abs() < 1e-4,
            "{back:?}"
        );
        assert!(c.target.photo);
        // A 50 m jump is cut to the 10 m limit; 40 deg to 20 deg.
        let far = geo_target(Vector3::new(30.0, 40.0, -20.0), 35.0, -30.0);
        let c = correct_targets(
            &far,
            &live,
            &current(),
            &HOME,
            &Fence::default(),
            &MountParams::default(),
            &p,
        )
        .unwrap();
        assert!(c.limited);
        assert!((Vector3::from(c.step_ned_m).norm() - 10.0).abs() < 1e-9);
        assert!((c.yaw_step_deg - 20.0).abs() < 1e-9);
    }

    #[test]
    fn corrections_pass_the_fence_altitude_and_gimbal_checks() {
        let p = ControllerParams::default();
        let mount = MountParams::default();
        let live = geo_target(Vector3::new(0.0, 0.0, -20.0), 355.0, -30.0);
        let fence = Fence {
            radius_m: 5.0,
            min_alt_m: 19.5,
            max_alt_m: 20.5,
        };
        let out = geo_target(Vector3::new(6.0, 0.0, -20.0), 355.0, -30.0);
        assert!(matches!(
            correct_targets(&out, &live, &current(), &HOME, &fence, &mount, &p),
            Err(RefineError::Target(plan::PlanError::OutsideFence { .. }))
        ));
        let low = geo_target(Vector3::new(0.0, 0.0, -19.0), 355.0, -30.0);
        assert!(matches!(
            correct_targets(&low, &live, &current(), &HOME, &fence, &mount, &p),
            Err(RefineError::Target(
                plan::PlanError::BelowMinAltitude { .. }
            ))
        ));
        let high = geo_target(Vector3::new(0.0, 0.0, -21.0), 355.0, -30.0);
        assert!(matches!(
            correct_targets(&high, &live, &current(), &HOME, &fence, &mount, &p),
            Err(RefineError::Target(
                plan::PlanError::AboveMaxAltitude { .. }
            ))
        ));
        let mut steep = current();
        steep.gimbal_pitch_deg = -85.0;
        let down = geo_target(Vector3::new(0.0, 0.0, -20.0), 355.0, -40.0);
        assert!(matches!(
            correct_targets(&down, &live, &steep, &HOME, &Fence::default(), &mount, &p),
            Err(RefineError::PitchOutOfRange { .. })
        ));
        let nan = geo_target(Vector3::new(f64::NAN, 0.0, -20.0), 355.0, -30.0);
        assert!(matches!(
            correct_targets(
                &nan,
                &live,
                &current(),
                &HOME,
                &Fence::default(),
                &mount,
                &p
            ),
            Err(RefineError::NonFinite { .. })
        ));
        let bad_gain = ControllerParams { gain: 0.0, ..p };
        assert!(matches!(
            correct_targets(
                &live,
                &live,
                &current(),
                &HOME,
                &Fence::default(),
                &mount,
                &bad_gain
            ),
            Err(RefineError::InvalidParams { name: "gain", .. })
        ));
    }

    #[test]
    fn the_loop_stops_on_the_threshold_or_the_budget() {
        let p = ControllerParams::default();
        assert_eq!(decide(Some(0.5), 0, &p), Decision::Converged);
        assert_eq!(decide(Some(1.5), 0, &p), Decision::Correct);
        assert_eq!(decide(None, 1, &p), Decision::Correct);
        assert_eq!(decide(Some(1.5), p.max_rounds, &p), Decision::MaxRounds);
        assert_eq!(decide(Some(0.99), p.max_rounds, &p), Decision::Converged);
    }
}
