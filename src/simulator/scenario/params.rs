//! The scenario's parameters: how the hidden poses are drawn, the flight
//! limits of a round, the disturbances the daemon does not know about, and
//! [`ScenarioParams`], every tunable number of the scenario.

use shotpilot_sim::realism::Realism;
use shotpilot_sim::script::{Level, ScriptParams};
use shotpilot_sim::world::WorldParams;

use crate::geo::{self, LeverArmFrame, MountParams};
use crate::mission::plan;
use crate::refine::Params;
use crate::shot::{AnchorParams, LocalizeParams};
use crate::simulator::drag::DragParams;
use crate::slam;

/// How the hidden poses are drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct HiddenParams {
    /// Horizontal offset from an explore keyframe's vehicle position, up to, m.
    pub horizontal_m: f64,
    /// Vertical offset, up to, m.
    pub vertical_m: f64,
    /// Heading offset, up to, degrees.
    pub yaw_deg: f64,
    /// Gimbal pitch offset, up to, degrees.
    pub pitch_deg: f64,
    /// Gimbal pitch range of the hidden poses, degrees.
    pub pitch_range_deg: (f64, f64),
    /// Lowest hidden altitude above home, m.
    pub min_alt_m: f64,
    /// Anchor trials: heading change of the keyframe's camera, up to, degrees.
    pub anchor_yaw_deg: f64,
    /// Anchor trials: pitch change of the keyframe's camera, up to, degrees.
    pub anchor_pitch_deg: f64,
    /// Anchor trials drawn as an operator drags the four corners (a zoom,
    /// a pan and a rotation of the frame: [`DragParams`]) instead of a pan
    /// and tilt of the keyframe's camera.
    pub drags: Option<DragParams>,
}

impl Default for HiddenParams {
    fn default() -> Self {
        Self {
            horizontal_m: 3.0,
            vertical_m: 2.0,
            yaw_deg: 15.0,
            pitch_deg: 8.0,
            pitch_range_deg: (-80.0, -20.0),
            min_alt_m: 6.0,
            anchor_yaw_deg: 6.0,
            anchor_pitch_deg: 4.0,
            drags: None,
        }
    }
}

/// Flight limits of a round.
#[derive(Debug, Clone, PartialEq)]
pub struct SteadyParams {
    /// Longest flight of one round before giving up, s.
    pub max_flight_s: f64,
}

impl Default for SteadyParams {
    fn default() -> Self {
        Self {
            max_flight_s: 120.0,
        }
    }
}

/// What the daemon does not know about the vehicle: the errors that make a
/// single open-loop estimate miss and that the loop must correct.
#[derive(Debug, Clone, PartialEq)]
pub struct Disturbances {
    /// GPS bias (the vehicle stands at its reported position plus this
    /// bias, which drifts as a first-order Gauss-Markov process starting at
    /// zero; the simulator's [`shotpilot_sim::vehicle::GpsBias`]):
    /// horizontal standard deviation per axis, m.
    pub gps_sigma_xy_m: f64,
    /// Its vertical standard deviation, m.
    pub gps_sigma_z_m: f64,
    /// Its correlation time, s.
    pub gps_tau_s: f64,
    /// Gimbal pitch calibration error: the camera looks this much lower
    /// than the gimbal reports, degrees (the georeference learns it as a
    /// negative [`crate::geo::MountParams::pitch_offset_deg`]).
    pub gimbal_pitch_offset_deg: f64,
    /// Camera heading error (mounting/compass), degrees.
    pub camera_yaw_offset_deg: f64,
}

impl Default for Disturbances {
    fn default() -> Self {
        Self {
            gps_sigma_xy_m: 1.0,
            gps_sigma_z_m: 0.5,
            gps_tau_s: 120.0,
            gimbal_pitch_offset_deg: 1.0,
            camera_yaw_offset_deg: 0.7,
        }
    }
}

impl Disturbances {
    /// No disturbance: the vehicle is exactly where telemetry says.
    pub fn none() -> Self {
        Self {
            gps_sigma_xy_m: 0.0,
            gps_sigma_z_m: 0.0,
            gps_tau_s: 120.0,
            gimbal_pitch_offset_deg: 0.0,
            camera_yaw_offset_deg: 0.0,
        }
    }
}

/// Every tunable number of the scenario.
#[derive(Debug, Clone, PartialEq)]
pub struct ScenarioParams {
    /// Trials after the explore flight.
    pub trials: usize,
    /// Seeds the world, the sensor noise and the hidden poses.
    pub seed: u64,
    /// The world's texture sizes (the layout comes from the seed).
    pub world: WorldParams,
    /// The explore flight.
    pub script: ScriptParams,
    /// Simulation steps per second.
    pub step_hz: f64,
    /// Frames per second given to the SLAM during the explore flight.
    pub slam_fps: f64,
    /// Add the simulator's sensor noise to every frame.
    pub sensor_noise: bool,
    /// Every `anchor_every`-th trial (1-based) makes its desired shot from
    /// anchors on a keyframe (0: never).
    pub anchor_every: usize,
    /// Localise an anchors shot as a photo is (its warped picture matched
    /// against the map), as before the keyframe's geometry placed it: for
    /// comparison only.
    pub anchors_by_matching: bool,
    /// Hidden poses.
    pub hidden: HiddenParams,
    /// Errors the daemon does not know about.
    pub disturbances: Disturbances,
    /// Arrival.
    pub steady: SteadyParams,
    /// The SLAM (run sequentially, so runs repeat).
    pub slam: slam::Params,
    /// Telemetry priors in the explore flight's SLAM (as the daemon's
    /// `[slam] priors`): the map goes to local NED once the fixes span a
    /// baseline, and its georeference is then the identity instead of a
    /// Sim(3) fitted after the flight.
    pub priors: bool,
    /// Save the explored map and load it back before the trials, as a
    /// daemon restart does: the desired shots are localised (and the live
    /// frames too) on the map read from its file.
    pub restart: bool,
    /// Shot localisation (desired shots and live frames).
    pub localize: LocalizeParams,
    /// Anchor checks.
    pub anchors: AnchorParams,
    /// Georeference.
    pub geo: geo::Params,
    /// Mission planning (geofence).
    pub plan: plan::Params,
    /// Shot error and correction loop.
    pub refine: Params,
    /// Servoing at the shot after the first arrival (None: rounds of
    /// mission legs only).
    pub servo: Option<ServoDriverParams>,
    /// The simulator's realism (`ideal`: none): its camera effects on every
    /// live frame (the desired photo stays a clean render), its vehicle
    /// effects on the vehicle (its GNSS error then replaces
    /// `disturbances`' GPS bias), its telemetry rates and frame losses on
    /// the telemetry the georeference sees.
    pub realism: Realism,
}

impl Default for ScenarioParams {
    fn default() -> Self {
        let vehicle = shotpilot_sim::vehicle::VehicleParams::default();
        Self {
            trials: 20,
            seed: 1,
            world: WorldParams::default(),
            script: ScriptParams::default(),
            step_hz: 50.0,
            slam_fps: 5.0,
            sensor_noise: true,
            anchor_every: 4,
            anchors_by_matching: false,
            hidden: HiddenParams::default(),
            disturbances: Disturbances::default(),
            steady: SteadyParams::default(),
            slam: slam::Params {
                sequential: true,
                ..slam::Params::default()
            },
            priors: false,
            restart: false,
            localize: LocalizeParams::default(),
            anchors: AnchorParams::default(),
            geo: geo::Params {
                history: geo::HistoryParams {
                    // The scenario keeps its whole simulated flight.
                    max_age_s: 86_400.0,
                    ..geo::HistoryParams::default()
                },
                mount: MountParams {
                    lever_arm_body_m: vehicle.camera_offset_body,
                    lever_arm_frame: LeverArmFrame::Heading,
                    stabilised: true,
                    pitch_min_deg: vehicle.gimbal.pitch_min_deg,
                    pitch_max_deg: vehicle.gimbal.pitch_max_deg,
                    ..MountParams::default()
                },
                // GPS-grade positions: metre-level errors are inliers.
                align: geo::AlignParams {
                    inlier_threshold_m: 2.5,
                    position_sigma_m: 1.0,
                    // The bias estimated per window: the georeference is
                    // kept after the survey, fed the telemetry and live
                    // frames paired in a short hover before each departure
                    // (the daemon's tracking pairs frames the same way),
                    // and refitted for each shot, so a target is where the
                    // receiver reads it now (None: the survey's fit flies
                    // every trial, the bias averaged over the survey).
                    drift: Some(geo::GnssDrift::default()),
                    ..geo::AlignParams::default()
                },
                continuity: geo::ContinuityParams::default(),
            },
            plan: plan::Params {
                hold_time_s: 15.0,
                acceptance_radius_m: 0.5,
                ..plan::Params::default()
            },
            refine: Params::default(),
            servo: None,
            realism: Realism::ideal(),
        }
    }
}

impl ScenarioParams {
    /// A short scenario for tests: a smaller world texture and one level
    /// of a smaller survey.
    pub fn quick(trials: usize, seed: u64) -> Self {
        Self {
            trials,
            seed,
            world: WorldParams::small(),
            script: ScriptParams {
                half_extent_m: 15.0,
                passes: 3,
                levels: vec![
                    Level {
                        alt_m: 12.0,
                        gimbal_pitch_deg: -40.0,
                        yaw_deg: 0.0,
                    },
                    Level {
                        alt_m: 18.0,
                        gimbal_pitch_deg: -55.0,
                        yaw_deg: 90.0,
                    },
                ],
                ..ScriptParams::default()
            },
            ..Self::default()
        }
    }
}

/// The servo's driver in the scenario.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoDriverParams {
    /// The servo itself.
    pub servo: crate::refine::ServoParams,
    /// Time between two processed frames, s (the daemon's processing rate).
    pub frame_s: f64,
    /// Time from a frame's capture to its setpoint reaching the autopilot
    /// (measurement and link), s.
    pub latency_s: f64,
}

impl Default for ServoDriverParams {
    fn default() -> Self {
        Self {
            servo: crate::refine::ServoParams::default(),
            frame_s: 0.2,
            latency_s: 0.15,
        }
    }
}
