//! The closed-loop scenario: the simulator's `explore` flight builds the
//! SLAM map and the georeference; then, trial after trial, a desired shot is
//! made from a hidden camera pose in the explored area (rendered from it, or
//! from four anchors on a keyframe that a small pan/tilt of that keyframe's
//! camera would give), localised in the map, converted to a vehicle target,
//! planned, uploaded to the simulated autopilot and flown; on arrival, once
//! the view is steady, a few live frames ([`crate::refine::MeasureParams`], each
//! with the position the vehicle reports then) are compared with the
//! desired shot ([`crate::refine::shot_error`]), localised, and a corrected mission is uploaded
//! ([`crate::refine::correct`]) until the shot error is under the threshold or the
//! round budget is spent.
//!
//! Everything runs synchronously in simulated time, with the daemon's own
//! pieces: the SLAM ([`crate::slam::Slam`], sequential), the georeference
//! ([`crate::geo::Geo`], fed with the autopilot's telemetry messages as the
//! link actor parses them), shot localisation ([`crate::shot::localize`]),
//! planning ([`crate::mission::plan`]) and the upload state machine
//! ([`crate::mission::upload::Uploader`]) talking MAVLink messages to the
//! simulator's autopilot in-process (no sockets, no radio losses). The hidden
//! poses and the simulator's vehicle are the judges.
//!
//! The parts, one file each: `params.rs` (every tunable number,
//! [`ScenarioParams`]), `error.rs` ([`ScenarioError`], [`FlightError`]),
//! `report.rs` (what a run returns, [`ScenarioReport`]), `sim.rs` (the
//! simulated world stepped with its autopilot: telemetry, rendering, the
//! in-process upload), `approach.rs` (a leg flown until the view is steady,
//! re-targeted on the approach), `localise.rs` (a live frame localised
//! and paired with telemetry), `explore.rs` (the explore
//! flight: the SLAM map and its georeference), `hidden.rs` (the hidden
//! poses and their desired shots), `trial.rs` (one trial: localise, plan,
//! upload, fly, refine); [`run`], here, sets the simulator up and runs them.

mod approach;
mod error;
mod explore;
mod hidden;
mod localise;
mod params;
mod report;
mod servo;
mod sim;
mod trial;

use std::sync::Arc;
use std::time::Instant;

use mavlink::MavHeader;
use mavlink::dialects::common::MavMessage;
use rand::{SeedableRng, rngs::SmallRng};

use shotpilot_sim::autopilot::{Autopilot, AutopilotParams};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::dataset::renderer_for;
use shotpilot_sim::imaging::Imager;
use shotpilot_sim::live::PoseHistory;
use shotpilot_sim::render::RenderParams;
use shotpilot_sim::vehicle::{GpsBiasParams, VehicleDisturbances};
use shotpilot_sim::world::World;

use crate::mission::plan::Home;
use crate::stats::finite_quantile;

use explore::explore;
use sim::Sim;
use trial::run_trial;

pub use super::drag::DragParams;
pub use error::{FlightError, ScenarioError};
pub use params::{Disturbances, HiddenParams, ScenarioParams, ServoDriverParams, SteadyParams};
pub use report::{ExploreReport, RoundReport, ScenarioReport, TrialReport};
pub use servo::ServoReport;

/// Runs the scenario: the explore flight, then `params.trials` trials.
/// `progress` is called after each trial.
pub fn run(
    params: &ScenarioParams,
    progress: &mut dyn FnMut(&TrialReport),
) -> Result<ScenarioReport, ScenarioError> {
    if !(params.step_hz >= 10.0 && params.slam_fps > 0.0 && params.slam_fps <= params.step_hz) {
        return Err(ScenarioError::InvalidParams {
            name: "step_hz/slam_fps",
            reason: "need step_hz >= 10 and 0 < slam_fps <= step_hz",
        });
    }
    let wall = Instant::now();
    let realism = &params.realism;
    realism.validate()?;
    let mut world_params = params.world.clone();
    if let Some(sun) = &realism.lighting.sun {
        let (az, el) = sun.position();
        world_params.sun_azimuth_deg = az;
        world_params.sun_elevation_deg = el;
    }
    let world = World::generate_with(params.seed, &world_params)
        .map_err(|e| ScenarioError::World(e.to_string()))?;
    let renderer = renderer_for(
        Arc::new(world),
        SimCamera::default(),
        RenderParams::default(),
        realism,
        params.seed,
    );
    let imager = (!realism.camera_is_ideal()).then(|| {
        Imager::new(
            Arc::new(renderer.clone()),
            realism.camera.clone(),
            &realism.lighting,
        )
    });
    let mut ap_params = AutopilotParams::default();
    ap_params.vehicle.disturbances =
        VehicleDisturbances::from_realism(realism, params.seed ^ 0x5EA1_0000);
    if let Some(tel) = &realism.vehicle.telemetry {
        ap_params.stream_intervals = tel.stream_intervals.clone();
    }
    // The GPS bias is the simulator vehicle's own model (true position =
    // reported position + bias), seeded from the scenario's seed; the
    // realism's GNSS error replaces it.
    let d = &params.disturbances;
    let gps_off = realism.vehicle.gps.is_some();
    ap_params.vehicle.gps_bias = GpsBiasParams {
        sigma_xy_m: if gps_off { 0.0 } else { d.gps_sigma_xy_m },
        sigma_z_m: if gps_off { 0.0 } else { d.gps_sigma_z_m },
        tau_s: d.gps_tau_s,
        seed: params.seed ^ 0x00b1_a5ed,
    };
    if let Err((name, reason)) = ap_params.vehicle.gps_bias.check() {
        return Err(ScenarioError::InvalidParams { name, reason });
    }
    let h = ap_params.vehicle.home;
    let mut ap = Autopilot::new(ap_params, 0.0);
    if realism.vehicle.telemetry.is_some() {
        // The autopilot starts at its own stream rates; the daemon asks
        // for its rates with SET_MESSAGE_INTERVAL, as on a real link.
        let r = crate::vehicle::Rates::default();
        for (id, hz) in [
            (33u32, r.global_position_hz),
            (32, r.local_position_hz),
            (30, r.attitude_hz),
            (242, r.home_position_hz),
            (285, r.gimbal_hz),
            (42, r.mission_current_hz),
        ] {
            if hz > 0.0 {
                let _ = ap.handle(
                    &MavHeader {
                        system_id: 255,
                        component_id: 190,
                        sequence: 0,
                    },
                    &MavMessage::COMMAND_LONG(mavlink::dialects::common::COMMAND_LONG_DATA {
                        param1: id as f32,
                        param2: 1e6 / hz,
                        command: mavlink::dialects::common::MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                        target_system: 1,
                        target_component: 1,
                        ..Default::default()
                    }),
                );
            }
        }
    }
    let mut sim = Sim {
        ap,
        renderer,
        t: 0.0,
        dt: 1.0 / params.step_hz,
        k: 0,
        noise_seed: params.seed.wrapping_mul(1_000_003),
        sensor_noise: params.sensor_noise,
        reached: None,
        home: Home {
            lat_deg: h.lat_deg,
            lon_deg: h.lon_deg,
            alt_amsl_m: h.alt_m,
        },
        fence: params.plan.fence,
        fence_ok: true,
        disturb: params.disturbances.clone(),
        imager,
        history: PoseHistory::new(),
        telemetry_drop: realism
            .vehicle
            .telemetry
            .as_ref()
            .filter(|t| t.drop > 0.0)
            .map(|t| (t.drop, SmallRng::seed_from_u64(params.seed ^ 0xD20F))),
        priors: None,
        geo: None,
    };
    let mut ex = explore(&mut sim, params)?;
    if params.restart {
        let bytes = crate::slam::mapfile::encode(&ex.map)?;
        ex.map = crate::slam::mapfile::decode(&bytes, std::path::Path::new("scenario restart"))?;
        tracing::info!(
            bytes = bytes.len(),
            keyframes = ex.map.keyframes().count(),
            "scenario: the explored map saved and loaded back (restart)"
        );
    }
    let mut rng = SmallRng::seed_from_u64(params.seed ^ 0x7e57_5407);
    let mut trials = Vec::with_capacity(params.trials);
    for i in 0..params.trials {
        let r = run_trial(i, &ex, &mut sim, params, &mut rng);
        progress(&r);
        trials.push(r);
    }
    let flown: Vec<&TrialReport> = trials
        .iter()
        .filter(|t| t.final_shot_error_pct.is_some())
        .collect();
    let fin: Vec<f64> = flown
        .iter()
        .filter_map(|t| t.final_shot_error_pct)
        .collect();
    let first: Vec<f64> = flown
        .iter()
        .filter_map(|t| t.first_shot_error_pct)
        .collect();
    let pos: Vec<f64> = flown.iter().filter_map(|t| t.position_error_m).collect();
    let pos0: Vec<f64> = flown
        .iter()
        .filter_map(|t| t.first_position_error_m)
        .collect();
    let yaw: Vec<f64> = flown
        .iter()
        .filter_map(|t| t.yaw_error_deg.map(f64::abs))
        .collect();
    let pitch: Vec<f64> = flown
        .iter()
        .filter_map(|t| t.pitch_error_deg.map(f64::abs))
        .collect();
    let n = flown.len();
    Ok(ScenarioReport {
        seed: params.seed,
        realism: params.realism.name.clone(),
        restart: params.restart,
        trials: trials.len(),
        flown: n,
        converged: trials
            .iter()
            .filter(|t| {
                // The rounds stop `converged`; a servo's photo converged
                // when its error is under the loop's threshold too.
                t.stop == "converged"
                    || (t.stop.starts_with("servo_")
                        && t.final_shot_error_pct
                            .is_some_and(|e| e <= params.refine.controller.threshold_pct))
            })
            .count(),
        within_noise: trials.iter().filter(|t| t.stop == "within_noise").count(),
        threshold_pct: params.refine.controller.threshold_pct,
        median_final_shot_error_pct: finite_quantile(&fin, 0.5),
        p90_final_shot_error_pct: finite_quantile(&fin, 0.9),
        median_first_shot_error_pct: finite_quantile(&first, 0.5),
        p90_first_shot_error_pct: finite_quantile(&first, 0.9),
        median_position_error_m: finite_quantile(&pos, 0.5),
        median_first_position_error_m: finite_quantile(&pos0, 0.5),
        median_yaw_error_deg: finite_quantile(&yaw, 0.5),
        median_pitch_error_deg: finite_quantile(&pitch, 0.5),
        fraction_final_within_2pct: (n > 0)
            .then(|| fin.iter().filter(|&&e| e <= 2.0).count() as f64 / n as f64),
        mean_rounds: (n > 0).then(|| flown.iter().map(|t| t.rounds as f64).sum::<f64>() / n as f64),
        fence_violations: trials.iter().filter(|t| !t.inside_fence).count(),
        servo: params.servo.is_some(),
        servo_settled: trials.iter().filter(|t| t.stop == "servo_settled").count(),
        median_arrival_to_photo_s: finite_quantile(
            &flown
                .iter()
                .filter_map(|t| t.arrival_to_photo_s)
                .collect::<Vec<_>>(),
            0.5,
        ),
        explore: ex.report.clone(),
        trial_reports: trials,
        wall_s: wall.elapsed().as_secs_f64(),
    })
}
