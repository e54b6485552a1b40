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

use std::collections::BTreeMap;
use std::sync::Arc;
use std::time::Instant;

use image::GrayImage;
use mavlink::MavHeader;
use mavlink::dialects::common::{MavMessage, MavMissionType};
use nalgebra::{Isometry3, Point2, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use serde::Serialize;

use shotpilot_sim::autopilot::{Autopilot, AutopilotParams, Mode};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::dataset::renderer_for;
use shotpilot_sim::imaging::Imager;
use shotpilot_sim::live::{LIVE_EXPOSURE_LAG_S, PoseHistory};
use shotpilot_sim::realism::Realism;
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::script::{Level, Script, ScriptKind, ScriptParams};
use shotpilot_sim::vehicle::{GpsBiasParams, VehicleDisturbances};
use shotpilot_sim::world::{World, WorldParams};

use crate::camera::Camera;
use crate::geo::{
    self, GeoAlignment, Geodetic, GimbalAngles, LeverArmFrame, LocalFrame, MountParams,
    VehicleState, convert_target, ned_from_cam,
};
use crate::mission::plan::{self, Flavour, Home, MissionItem};
use crate::mission::upload::{self, Peers, Uploader};
use crate::refine::{
    ArrivalDetector, ArrivalParams, Context, LiveFrame, Params, RoundRecord, Session, Step, Stop,
    pose_difference,
};
use crate::shot::request::NotLocalised;
use crate::shot::{
    AnchorParams, Localization, LocalizeParams, desired_shot_from_anchors, frame_corners, localize,
    localize_anchors,
};
use crate::slam::priors::{PriorParams, Priors, TelemetryFeed, TelemetrySample};
use crate::slam::{self, Map, MapMode, Slam};
use crate::stats::finite_quantile;

pub use super::drag::DragParams;
use super::drag::{drag_truth, random_drag};

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
    /// Gimbal pitch calibration error: the camera looks this much higher
    /// than the gimbal reports, degrees.
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

/// Why a trial's flight failed (the trial's `reason`, a result).
#[derive(Debug, thiserror::Error)]
pub enum FlightError {
    /// The mission upload state machine failed.
    #[error("upload: {0}")]
    Upload(#[from] crate::mission::upload::MissionError),
    /// The upload did not finish within its message budget.
    #[error("upload: did not finish")]
    UploadUnfinished,
    /// The vehicle did not reach the waypoint and hold still in time.
    #[error("waypoint {waypoint} not reached and steady within {waited_s} s")]
    NoArrival {
        /// The waypoint's sequence number.
        waypoint: u16,
        /// Simulated seconds waited.
        waited_s: f64,
    },
}

/// Errors that stop the scenario (a failing trial is a result, not an error).
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// Invalid parameters.
    #[error("invalid parameter {name}: {reason}")]
    InvalidParams {
        /// Which parameter.
        name: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// The world could not be generated.
    #[error("world: {0}")]
    World(String),
    /// The realism configuration is unusable.
    #[error("realism: {0}")]
    Realism(#[from] shotpilot_sim::realism::RealismError),
    /// The camera is unusable.
    #[error("camera: {0}")]
    Camera(#[from] crate::camera::CameraError),
    /// The SLAM could not start.
    #[error("SLAM: {0}")]
    Slam(#[from] crate::slam::SlamError),
    /// The explore flight did not give a map.
    /// The explored map could not be saved and read back (`restart`).
    #[error("map file: {0}")]
    MapFile(#[from] crate::slam::mapfile::MapFileError),
    #[error("the explore flight gave no usable map: {keyframes} keyframes")]
    NoMap {
        /// Keyframes in the map.
        keyframes: usize,
    },
    /// The georeference could not be fitted.
    #[error("georeference: {0}")]
    Geo(#[from] crate::geo::GeoError),
    /// The explore flight did not finish in time.
    #[error("the explore flight did not finish within {seconds} s")]
    ExploreTimeout {
        /// The limit, s.
        seconds: f64,
    },
}

/// What the explore flight gave.
#[derive(Debug, Clone, Serialize)]
pub struct ExploreReport {
    /// Simulated seconds.
    pub sim_s: f64,
    /// Frames given to the SLAM.
    pub frames: u64,
    /// Frames it tracked.
    pub tracked: u64,
    /// Keyframes in the final map.
    pub keyframes: usize,
    /// Points in the final map.
    pub points: usize,
    /// Keyframes paired with telemetry.
    pub geo_pairs: usize,
    /// Inliers of the map → NED fit.
    pub geo_inliers: usize,
    /// RMS residual of the fit, m.
    pub geo_rms_m: f64,
    /// Scale of the fit (metres per map unit).
    pub geo_scale: f64,
    /// The map's mode at the end of the flight (`vision_only`,
    /// `gps_aided`): with a gps-aided map the georeference is the identity
    /// and `geo_rms_m` the keyframes' distance to their fixes.
    pub map_mode: &'static str,
    /// Wall seconds.
    pub wall_s: f64,
}

/// One measurement on arrival (the loop's record) and the judge's figures.
#[derive(Debug, Clone, Serialize)]
pub struct RoundReport {
    /// What the loop measured and did.
    #[serde(flatten)]
    pub record: RoundRecord,
    /// Camera position error against the hidden pose, m (the judge).
    pub position_error_m: f64,
    /// Heading error of the optical axis, degrees.
    pub yaw_error_deg: f64,
    /// Elevation error of the optical axis, degrees.
    pub pitch_error_deg: f64,
    /// Angle of the whole rotation error (roll about the optical axis
    /// included), degrees.
    pub rotation_error_deg: f64,
    /// The vehicle's true position minus the reported one (GNSS bias and
    /// noise, barometric drift), local NED m: what the loop's measured
    /// offset estimates, up to the georeference's own constant error.
    pub true_offset_ned_m: [f64; 3],
    /// Simulated seconds of this round's flight.
    pub flight_s: f64,
}

/// One trial.
#[derive(Debug, Clone, Serialize)]
pub struct TrialReport {
    /// Trial number (0-based).
    pub trial: usize,
    /// `render` (a photo from the hidden pose) or `anchors` (on a keyframe).
    pub kind: &'static str,
    /// The hidden vehicle position, local NED m.
    pub hidden_p_ned: [f64; 3],
    /// The hidden heading, degrees.
    pub hidden_yaw_deg: f64,
    /// The hidden gimbal pitch, degrees.
    pub hidden_pitch_deg: f64,
    /// The desired shot was localised and flown.
    pub flown: bool,
    /// Why not, when it was not.
    pub reason: Option<String>,
    /// Localisation error of the desired shot (through the georeference)
    /// against the hidden camera, m.
    pub desired_localisation_error_m: Option<f64>,
    /// Shot error of the first flight, % of the diagonal.
    pub first_shot_error_pct: Option<f64>,
    /// Shot error at the end, % of the diagonal.
    pub final_shot_error_pct: Option<f64>,
    /// Camera position error of the first flight, m.
    pub first_position_error_m: Option<f64>,
    /// Camera position error at the end, m.
    pub position_error_m: Option<f64>,
    /// Optical-axis heading error at the end, degrees.
    pub yaw_error_deg: Option<f64>,
    /// Optical-axis elevation error at the end, degrees.
    pub pitch_error_deg: Option<f64>,
    /// Corrections flown.
    pub rounds: usize,
    /// How the loop ended: converged, max_rounds, or the reason it stopped.
    pub stop: String,
    /// Simulated seconds of the trial.
    pub sim_s: f64,
    /// Wall seconds of the trial.
    pub wall_s: f64,
    /// The vehicle stayed inside the geofence all along.
    pub inside_fence: bool,
    /// Every measurement.
    pub round_reports: Vec<RoundReport>,
}

/// The whole scenario.
#[derive(Debug, Clone, Serialize)]
pub struct ScenarioReport {
    /// Seed.
    pub seed: u64,
    /// The realism (`ideal`, `field`, ...).
    pub realism: String,
    /// The trials ran on the explored map saved and loaded back.
    pub restart: bool,
    /// Trials run.
    pub trials: usize,
    /// Trials whose desired shot was localised and flown.
    pub flown: usize,
    /// Trials that converged under the threshold.
    pub converged: usize,
    /// Trials that stopped above the threshold because the correction was
    /// within the measurement's noise (`within_noise`).
    pub within_noise: usize,
    /// Threshold of the loop, % of the diagonal.
    pub threshold_pct: f64,
    /// Median final shot error over the flown trials, %.
    pub median_final_shot_error_pct: Option<f64>,
    /// 90th percentile of the final shot error, %.
    pub p90_final_shot_error_pct: Option<f64>,
    /// Median first-flight shot error, %.
    pub median_first_shot_error_pct: Option<f64>,
    /// 90th percentile of the first-flight shot error, %.
    pub p90_first_shot_error_pct: Option<f64>,
    /// Median final camera position error, m.
    pub median_position_error_m: Option<f64>,
    /// Median first-flight camera position error, m.
    pub median_first_position_error_m: Option<f64>,
    /// Median final optical-axis heading error (absolute), degrees.
    pub median_yaw_error_deg: Option<f64>,
    /// Median final optical-axis elevation error (absolute), degrees.
    pub median_pitch_error_deg: Option<f64>,
    /// Fraction of flown trials with a final shot error <= 2 %.
    pub fraction_final_within_2pct: Option<f64>,
    /// Mean corrections per flown trial.
    pub mean_rounds: Option<f64>,
    /// Trials in which the vehicle left the geofence.
    pub fence_violations: usize,
    /// The explore flight.
    pub explore: ExploreReport,
    /// Every trial.
    pub trial_reports: Vec<TrialReport>,
    /// Wall seconds of everything.
    pub wall_s: f64,
}

fn camera_of(c: &SimCamera) -> Result<Camera, crate::camera::CameraError> {
    super::camera_from_sim(c)
}

const GCS: MavHeader = MavHeader {
    system_id: 255,
    component_id: 190,
    sequence: 0,
};

/// The simulated world, its autopilot and the telemetry the daemon sees.
struct Sim {
    ap: Autopilot,
    renderer: Renderer,
    t: f64,
    dt: f64,
    k: u64,
    noise_seed: u64,
    sensor_noise: bool,
    /// Most recent MISSION_ITEM_REACHED seq since the last upload.
    reached: Option<u16>,
    home: Home,
    fence: plan::Fence,
    fence_ok: bool,
    disturb: Disturbances,
    /// The realistic camera (None: the plain renderer).
    imager: Option<Imager>,
    /// The true camera poses of the last steps (for `imager`).
    history: PoseHistory,
    /// Telemetry frame loss: probability and its dice.
    telemetry_drop: Option<(f64, SmallRng)>,
    /// The telemetry priors' feed, filled as the daemon's georeference
    /// worker fills it (None: vision only).
    priors: Option<PriorTap>,
}

/// What the priors' feed is filled from: each position report as the
/// camera's position with the latest attitude and GPS_RAW_INT.
struct PriorTap {
    feed: TelemetryFeed,
    mount: MountParams,
    attitude: Option<nalgebra::UnitQuaternion<f64>>,
    /// The latest GPS_RAW_INT.
    gps: Option<crate::vehicle::GpsRaw>,
}

impl Sim {
    /// One simulation step; telemetry goes to `geo` when given.
    fn step(&mut self, geo: Option<&mut geo::Geo>) {
        self.k += 1;
        self.t = self.k as f64 * self.dt;
        let mut out = self.ap.step(self.t, self.dt);
        let _ = self.ap.take_capture_requests();
        if self.imager.is_some() {
            let wfc = self.misaligned(&self.ap.vehicle().true_world_from_cam_stabilised());
            self.history.push(self.t, wfc);
        }
        if let Some((p, rng)) = &mut self.telemetry_drop {
            // The radio loses whole frames of the telemetry streams.
            out.retain(|m| {
                !matches!(
                    m,
                    MavMessage::GLOBAL_POSITION_INT(_)
                        | MavMessage::ATTITUDE(_)
                        | MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(_)
                ) || rng.random::<f64>() >= *p
            });
        }
        let mut geo = geo;
        for m in &out {
            match m {
                MavMessage::MISSION_ITEM_REACHED(r) => self.reached = Some(r.seq),
                MavMessage::GLOBAL_POSITION_INT(d) => {
                    if let Some(g) = geo.as_deref_mut() {
                        let t = f64::from(d.time_boot_ms) / 1e3;
                        let p = Geodetic {
                            lat_deg: f64::from(d.lat) / 1e7,
                            lon_deg: f64::from(d.lon) / 1e7,
                            alt_m: f64::from(d.alt) / 1e3,
                        };
                        let _ = g.push_position_geodetic(t, &p);
                        if let Some(tap) = &self.priors
                            && let (Some(frame), Some(q)) = (g.frame(), tap.attitude)
                        {
                            tap.feed.push(TelemetrySample::from_position_report(
                                t,
                                frame.geodetic_to_ned(&p),
                                q,
                                &tap.mount,
                                tap.gps.and_then(|r| r.fix_accuracy()),
                            ));
                        }
                    }
                }
                MavMessage::GPS_RAW_INT(d) => {
                    if let Some(tap) = &mut self.priors {
                        tap.gps = Some(crate::vehicle::GpsRaw::from_message(d));
                    }
                }
                MavMessage::ATTITUDE(d) => {
                    if let Some(tap) = &mut self.priors {
                        tap.attitude = Some(nalgebra::UnitQuaternion::from_euler_angles(
                            f64::from(d.roll),
                            f64::from(d.pitch),
                            f64::from(d.yaw),
                        ));
                    }
                    if let Some(g) = geo.as_deref_mut() {
                        let _ = g.history_mut().push_attitude_euler(
                            f64::from(d.time_boot_ms) / 1e3,
                            f64::from(d.roll),
                            f64::from(d.pitch),
                            f64::from(d.yaw),
                        );
                    }
                }
                MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(d) => {
                    if let Some(g) = geo.as_deref_mut() {
                        let (_, pitch, yaw) = crate::vehicle::quat_to_euler_deg(d.q);
                        let _ = g.history_mut().push_gimbal(
                            f64::from(d.time_boot_ms) / 1e3,
                            GimbalAngles {
                                pitch: f64::from(pitch).to_radians(),
                                yaw: f64::from(yaw).to_radians(),
                            },
                        );
                    }
                }
                _ => {}
            }
        }
        let v = self.ap.vehicle();
        if !v.landed() {
            let p = v.true_p_ned();
            let alt = -p.z;
            if p.xy().norm() > self.fence.radius_m || alt > self.fence.max_alt_m {
                self.fence_ok = false;
            }
        }
    }

    /// The camera pose the vehicle really has (GPS bias, which the
    /// simulator's vehicle carries, and misalignment included).
    fn true_camera(&self) -> Isometry3<f64> {
        self.misaligned(&self.ap.vehicle().true_world_from_cam())
    }

    /// `nominal` turned by the camera's mounting errors.
    fn misaligned(&self, nominal: &Isometry3<f64>) -> Isometry3<f64> {
        let d = &self.disturb;
        let rotation = UnitQuaternion::from_axis_angle(
            &Vector3::z_axis(),
            d.camera_yaw_offset_deg.to_radians(),
        ) * nominal.rotation
            // the camera's x axis points right: a negative turn about it looks up
            * UnitQuaternion::from_axis_angle(
                &Vector3::x_axis(),
                -d.gimbal_pitch_offset_deg.to_radians(),
            );
        Isometry3::from_parts(nominal.translation, rotation)
    }

    fn render(&mut self) -> GrayImage {
        let noise = self.sensor_noise.then(|| {
            self.noise_seed = self.noise_seed.wrapping_add(1);
            self.noise_seed
        });
        if let Some(imager) = &mut self.imager {
            // Exposed a moment back, over the true motion around then.
            let t = self.t - LIVE_EXPOSURE_LAG_S;
            let window = self.history.window(
                t - 0.12,
                t + 0.12,
                self.ap.vehicle().gimbal_error().cloned(),
            );
            match imager.capture(t, &|s| window.world_from_cam(s), noise) {
                Ok(shot) => return shot.image,
                Err(e) => tracing::warn!("realistic frame: {e}"),
            }
        }
        let wfc = self.true_camera();
        if let Some(seed) = noise {
            self.renderer.render_noisy(&wfc, seed)
        } else {
            self.renderer.render(&wfc)
        }
    }

    /// Uploads a mission through the upload state machine, in-process.
    fn upload(&mut self, items: &[MissionItem]) -> Result<upload::UploadReport, FlightError> {
        let peers = Peers {
            own_system: 255,
            own_component: 190,
            target_system: self.ap.params().system_id,
            target_component: self.ap.params().component_id,
        };
        let ap_header = MavHeader {
            system_id: u32::from(peers.target_system),
            component_id: peers.target_component,
            sequence: 0,
        };
        let mut out = Vec::new();
        let mut up = Uploader::new(
            items,
            peers,
            MavMissionType::MAV_MISSION_TYPE_MISSION,
            upload::Params::default(),
            Instant::now(),
            &mut out,
        )?;
        for _ in 0..10_000 {
            if up.is_done() {
                break;
            }
            let msgs = std::mem::take(&mut out);
            if msgs.is_empty() {
                // Nothing in flight without a lossy link; a timeout would be a bug.
                up.on_timeout(
                    Instant::now() + std::time::Duration::from_secs(3600),
                    &mut out,
                );
                continue;
            }
            for m in msgs {
                for r in self.ap.handle(&GCS, &m) {
                    up.on_message(&ap_header, &r, Instant::now(), &mut out);
                }
            }
        }
        self.reached = None;
        match up.take_outcome() {
            Some(Ok(r)) => Ok(r),
            Some(Err(e)) => Err(e.into()),
            None => Err(FlightError::UploadUnfinished),
        }
    }

    /// Lets `seconds` of simulated time pass (hovering where it is).
    fn advance(&mut self, seconds: f64) {
        let end = self.t + seconds;
        while self.t + 0.5 * self.dt < end {
            self.step(None);
        }
    }

    /// Flies until the waypoint `wp_seq` is reached and the view is steady
    /// by the daemon's arrival rule, fed with what telemetry reports.
    fn fly_until_steady(
        &mut self,
        wp_seq: u16,
        gimbal_pitch_deg: f64,
        arrival: &ArrivalParams,
        p: &SteadyParams,
    ) -> Result<f64, FlightError> {
        let t0 = self.t;
        let mut det = ArrivalDetector::new(*arrival, wp_seq, gimbal_pitch_deg);
        while self.t - t0 < p.max_flight_s {
            self.step(None);
            if let Some(seq) = self.reached.take() {
                det.on_reached(seq);
            }
            let v = self.ap.vehicle();
            let pitch = v.gimbal_angles().0.to_degrees();
            if det.update(self.t, v.v_ned().norm(), pitch) {
                return Ok(self.t - t0);
            }
        }
        Err(FlightError::NoArrival {
            waypoint: wp_seq,
            waited_s: p.max_flight_s,
        })
    }
}

/// The truth of one explore frame: the vehicle position (NED), heading and
/// gimbal pitch (radians) as reported, and the camera pose it really had.
type FrameTruth = ((Vector3<f64>, f64, f64), Isometry3<f64>);

/// The explore flight and what it built.
struct Explored {
    map: Map,
    alignment: GeoAlignment,
    frame: LocalFrame,
    /// Truth per keyframe id: (vehicle position NED, heading rad, gimbal
    /// pitch rad) as reported, and the true camera pose.
    kf_truth: BTreeMap<u32, FrameTruth>,
    report: ExploreReport,
}

fn explore(sim: &mut Sim, params: &ScenarioParams) -> Result<Explored, ScenarioError> {
    let wall = Instant::now();
    let camera = camera_of(sim.renderer.camera())?;
    let mut slam_params = params.slam.clone();
    if params.priors {
        let feed = TelemetryFeed::live(params.geo.history.max_age_s);
        slam_params.priors = Some(Priors::with_feed(feed.clone(), PriorParams::default()));
        sim.priors = Some(PriorTap {
            feed,
            mount: params.geo.mount.clone(),
            attitude: None,
            gps: None,
        });
    }
    let mut slam = Slam::new(camera, slam_params)?;
    let home = sim.ap.params().vehicle.home;
    let mut g = geo::Geo::new(params.geo.clone());
    g.set_home(Geodetic {
        lat_deg: home.lat_deg,
        lon_deg: home.lon_deg,
        alt_m: home.alt_m,
    })?;
    let world = sim.renderer.world().clone();
    let mut script = Script::new(
        ScriptKind::Explore,
        params.script.clone(),
        &move |x, y, r| world.max_height_near(x, y, r),
    );
    let every = ((params.step_hz / params.slam_fps).round() as u64).max(1);
    let limit_s = 3.0 * script.length_m() / params.script.speed.max(0.1) + 120.0;
    let mut truth_by_frame: BTreeMap<u64, FrameTruth> = BTreeMap::new();
    let (mut frames, mut tracked) = (0u64, 0u64);
    while !script.finished() {
        if sim.t > limit_s {
            return Err(ScenarioError::ExploreTimeout { seconds: limit_s });
        }
        script.step(&mut sim.ap, sim.t + sim.dt);
        sim.step(Some(&mut g));
        if sim.k.is_multiple_of(every) && !sim.ap.vehicle().landed() {
            let image = Arc::new(sim.render());
            let v = sim.ap.vehicle();
            truth_by_frame.insert(
                frames,
                ((v.p_ned(), v.yaw(), v.gimbal_angles().0), sim.true_camera()),
            );
            let outcome = slam.process(frames, sim.t, image);
            frames += 1;
            if outcome.cam_from_world.is_some() {
                tracked += 1;
            }
        }
    }
    // A little more telemetry so the last keyframes are covered.
    for _ in 0..50 {
        sim.step(Some(&mut g));
    }
    let run = slam.finish();
    let map = run.map;
    let mut kf_truth = BTreeMap::new();
    for kf in map.keyframes() {
        // As the daemon does: a keyframe the georeference refuses (its
        // time in a telemetry gap) is left out, the rest go on.
        if let Err(e) = g.add_keyframe(u64::from(kf.id.0), &kf.world_from_cam(), kf.timestamp) {
            tracing::debug!(kf = kf.id.0, "geo: keyframe refused: {e}");
            continue;
        }
        if let Some(t) = truth_by_frame.get(&kf.frame_index) {
            kf_truth.insert(kf.id.0, *t);
        }
    }
    g.retry_pending();
    let keyframes = map.keyframes().count();
    if keyframes < 5 {
        return Err(ScenarioError::NoMap { keyframes });
    }
    // A map the priors put in local NED is georeferenced by itself (the
    // daemon's `source: map`); else the Sim(3) fitted after the flight.
    let map_mode = map.mode();
    let alignment = if map_mode == MapMode::GpsAided {
        GeoAlignment::of_map_in_ned(g.georeference().pairs())
    } else {
        g.fit()?
    };
    sim.priors = None;
    let frame = *g.frame().ok_or(crate::geo::GeoError::NoHome)?;
    let report = ExploreReport {
        sim_s: sim.t,
        frames,
        tracked,
        keyframes,
        points: map.points().count(),
        geo_pairs: alignment.quality.pairs,
        geo_inliers: alignment.quality.inliers,
        geo_rms_m: alignment.quality.rms_m,
        geo_scale: alignment.ned_from_map.scale,
        map_mode: map_mode.name(),
        wall_s: wall.elapsed().as_secs_f64(),
    };
    Ok(Explored {
        map,
        alignment,
        frame,
        kf_truth,
        report,
    })
}

/// A hidden pose: the vehicle state that takes it, its camera, the desired
/// shot (image, mask), its kind and, for an anchors shot, its keyframe and
/// transform (shot pixel -> keyframe pixel).
struct Hidden {
    p_ned: Vector3<f64>,
    yaw: f64,
    pitch: f64,
    camera: Isometry3<f64>,
    image: GrayImage,
    mask: Option<GrayImage>,
    kind: &'static str,
    anchors_on: Option<(u32, nalgebra::Matrix3<f64>)>,
}

fn hover_state(p_ned: Vector3<f64>, yaw: f64, pitch: f64) -> VehicleState {
    VehicleState {
        time: 0.0,
        p_ned,
        v_ned: Vector3::zeros(),
        ned_from_body: nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        gimbal: GimbalAngles { pitch, yaw: 0.0 },
    }
}

fn sym(rng: &mut SmallRng, r: f64) -> f64 {
    if r > 0.0 {
        rng.random_range(-r..r)
    } else {
        0.0
    }
}

fn make_hidden(
    ex: &Explored,
    sim: &Sim,
    params: &ScenarioParams,
    anchors: bool,
    rng: &mut SmallRng,
) -> Option<Hidden> {
    let hp = &params.hidden;
    let mount = &params.geo.mount;
    let ids: Vec<u32> = ex.kf_truth.keys().copied().collect();
    if ids.is_empty() {
        return None;
    }
    let id = ids[rng.random_range(0..ids.len())];
    let ((p, yaw, pitch), kf_cam) = ex.kf_truth[&id];
    if anchors && let Some(drag) = hp.drags {
        return make_drag(ex, sim, &drag, params, id, rng);
    }
    if anchors {
        let kf = ex.map.keyframe(crate::slam::KeyFrameId(id))?;
        let img = kf.image.clone()?;
        // The keyframe's true camera turned about the vertical and its own
        // x axis (a pan and a tilt: a pose a 2-axis gimbal can take).
        let dyaw = sym(rng, hp.anchor_yaw_deg).to_radians();
        let dpitch = sym(rng, hp.anchor_pitch_deg).to_radians();
        let cam = Isometry3::from_parts(
            kf_cam.translation,
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), dyaw)
                * kf_cam.rotation
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -dpitch),
        );
        let (yaw2, pitch2) = (yaw + dyaw, pitch + dpitch);
        // The anchors: where the desired frame's corners lie in the
        // keyframe (the warp samples the keyframe at H·p, H: corner -> anchor).
        let cam_model = ex.map.camera;
        let k_from_d = kf_cam.rotation.inverse() * cam.rotation;
        let mut pts = [Point2::origin(); 4];
        for (i, c) in frame_corners(cam_model.width, cam_model.height)
            .iter()
            .enumerate()
        {
            let ray = cam_model.unproject(*c);
            pts[i] = cam_model.project(&(k_from_d * ray.into_inner()))?;
        }
        let shot = desired_shot_from_anchors(&img, &pts, &params.anchors).ok()?;
        return Some(Hidden {
            p_ned: p,
            yaw: yaw2,
            pitch: pitch2,
            camera: cam,
            image: shot.image,
            mask: Some(shot.mask),
            kind: "anchors",
            anchors_on: Some((id, shot.shot_to_source)),
        });
    }
    let ground = sim.renderer.world().height_at(p.x, p.y);
    let mut q = p + Vector3::new(
        sym(rng, hp.horizontal_m),
        sym(rng, hp.horizontal_m),
        sym(rng, hp.vertical_m),
    );
    let clearance = sim.renderer.world().max_height_near(q.x, q.y, 3.0);
    q.z = q.z.min(-(hp.min_alt_m.max(clearance - ground + 3.0)));
    let yaw2 = yaw + sym(rng, hp.yaw_deg).to_radians();
    let pitch2 = (pitch + sym(rng, hp.pitch_deg).to_radians()).clamp(
        hp.pitch_range_deg.0.to_radians(),
        hp.pitch_range_deg.1.to_radians(),
    );
    let cam = ned_from_cam(&hover_state(q, yaw2, pitch2), mount);
    let image = if params.sensor_noise {
        sim.renderer.render_noisy(&cam, rng.random())
    } else {
        sim.renderer.render(&cam)
    };
    Some(Hidden {
        p_ned: q,
        yaw: yaw2,
        pitch: pitch2,
        camera: cam,
        image,
        mask: None,
        kind: "render",
        anchors_on: None,
    })
}

/// The desired shot's camera: an anchors shot's from its keyframe's
/// geometry (as the daemon does), a photo's by localisation.
/// An anchors shot dragged on keyframe `id` ([`DragParams`]), and its
/// truth: the camera that takes the drawn picture best in the true world
/// (PnP on a grid of the picture's pixels, each at the true scene point
/// the keyframe's true camera sees there through the anchors' transform),
/// with the vehicle state a 2-axis gimbal reaches it from.
fn make_drag(
    ex: &Explored,
    sim: &Sim,
    drag: &DragParams,
    params: &ScenarioParams,
    id: u32,
    rng: &mut SmallRng,
) -> Option<Hidden> {
    let ((p, _, _), kf_cam) = ex.kf_truth[&id];
    let kf = ex.map.keyframe(crate::slam::KeyFrameId(id))?;
    let img = kf.image.clone()?;
    let cam = ex.map.camera;
    let d = random_drag(rng, &cam, drag);
    let shot = desired_shot_from_anchors(&img, &d.anchors, &params.anchors).ok()?;
    let truth = drag_truth(
        sim.renderer.world(),
        &cam,
        &kf_cam,
        &shot.shot_to_source,
        &params.localize.pnp,
        &params.localize.pose,
    )?
    .world_from_cam;
    let (yaw, pitch) = crate::refine::axis_yaw_pitch(&truth);
    Some(Hidden {
        p_ned: p + (truth.translation.vector - kf_cam.translation.vector),
        yaw,
        pitch,
        camera: truth,
        image: shot.image,
        mask: Some(shot.mask),
        kind: "drag",
        anchors_on: Some((id, shot.shot_to_source)),
    })
}

fn localise(
    map: &Map,
    img: &GrayImage,
    mask: Option<&GrayImage>,
    anchors_on: Option<(u32, nalgebra::Matrix3<f64>)>,
    by_matching: bool,
    p: &LocalizeParams,
) -> Result<Isometry3<f64>, NotLocalised> {
    let found = match anchors_on {
        Some((id, h)) if !by_matching => {
            Ok(localize_anchors(map, crate::slam::KeyFrameId(id), &h, p))
        }
        _ => localize(map, img, mask, None, p),
    };
    match found {
        Ok(Localization::Localized(s)) => Ok(s.world_from_cam),
        Ok(Localization::NotLocalized { reason }) => Err(NotLocalised::Rejected(reason)),
        Err(e) => Err(NotLocalised::Failed(e)),
    }
}

fn run_trial(
    trial: usize,
    ex: &Explored,
    sim: &mut Sim,
    params: &ScenarioParams,
    rng: &mut SmallRng,
) -> TrialReport {
    let wall = Instant::now();
    let t0 = sim.t;
    let anchors = params.anchor_every > 0 && (trial + 1).is_multiple_of(params.anchor_every);
    let mut rep = TrialReport {
        trial,
        kind: if anchors { "anchors" } else { "render" },
        hidden_p_ned: [0.0; 3],
        hidden_yaw_deg: 0.0,
        hidden_pitch_deg: 0.0,
        flown: false,
        reason: None,
        desired_localisation_error_m: None,
        first_shot_error_pct: None,
        final_shot_error_pct: None,
        first_position_error_m: None,
        position_error_m: None,
        yaw_error_deg: None,
        pitch_error_deg: None,
        rounds: 0,
        stop: String::new(),
        sim_s: 0.0,
        wall_s: 0.0,
        inside_fence: true,
        round_reports: Vec::new(),
    };
    let finish = |mut rep: TrialReport, sim: &Sim, stop: String| {
        rep.stop = stop;
        rep.sim_s = sim.t - t0;
        rep.wall_s = wall.elapsed().as_secs_f64();
        rep.inside_fence = sim.fence_ok;
        rep
    };
    let Some(hidden) = make_hidden(ex, sim, params, anchors, rng) else {
        rep.reason = Some("no hidden pose could be made".into());
        return finish(rep, sim, "no_shot".into());
    };
    rep.kind = hidden.kind;
    rep.hidden_p_ned = hidden.p_ned.into();
    rep.hidden_yaw_deg = hidden.yaw.to_degrees();
    rep.hidden_pitch_deg = hidden.pitch.to_degrees();
    let mount = &params.geo.mount;
    let desired_map = match localise(
        &ex.map,
        &hidden.image,
        hidden.mask.as_ref(),
        hidden.anchors_on,
        params.anchors_by_matching,
        &params.localize,
    ) {
        Ok(p) => p,
        Err(e) => {
            rep.reason = Some(e.to_string());
            return finish(rep, sim, "not_localised".into());
        }
    };
    rep.desired_localisation_error_m = Some(
        (ex.alignment.ned_from_cam(&desired_map).translation.vector
            - hidden.camera.translation.vector)
            .norm(),
    );
    let target = match convert_target(&ex.alignment, &desired_map, &ex.frame, mount) {
        Ok(t) => t.to_mission_target(false),
        Err(e) => {
            rep.reason = Some(format!("no target: {e}"));
            return finish(rep, sim, "no_target".into());
        }
    };
    let flavour = Flavour::Px4;
    let cam_model = ex.map.camera;
    let mut session = Session::new(
        hidden.image.clone(),
        hidden.mask.clone(),
        desired_map,
        target,
        params.refine.clone(),
    );
    // An anchors shot knows its floor, as in the daemon.
    if let Some((id, h)) = hidden.anchors_on
        && let Ok(r) = crate::refine::reachable_from_anchors(
            &ex.map,
            crate::slam::KeyFrameId(id),
            &h,
            &desired_map,
            &params.refine.error,
        )
    {
        session = session.with_reachable(r);
    }
    let home = sim.home;
    let ctx = Context {
        map: &ex.map,
        alignment: &ex.alignment,
        frame: &ex.frame,
        mount,
        home: &home,
        fence: &params.plan.fence,
        localize: &params.localize,
    };
    sim.fence_ok = true;
    loop {
        let target = *session.target();
        let items = match plan::plan(&target, &sim.home, flavour, &params.plan) {
            Ok(i) => i,
            Err(e) => {
                rep.reason = Some(format!("plan refused: {e}"));
                return finish(rep, sim, "plan_refused".into());
            }
        };
        let Some(wp) = plan::waypoint_seq(&items) else {
            return finish(rep, sim, "no_waypoint".into());
        };
        if let Err(e) = sim.upload(&items) {
            rep.reason = Some(e.to_string());
            return finish(rep, sim, "upload_failed".into());
        }
        if sim.ap.mode() != Mode::Mission {
            sim.ap.set_mode(Mode::Mission);
        }
        let _ = sim.ap.arm();
        let flight_s = match sim.fly_until_steady(
            wp,
            target.gimbal_pitch_deg,
            &params.refine.arrival,
            &params.steady,
        ) {
            Ok(s) => s,
            Err(e) => {
                rep.reason = Some(e.to_string());
                return finish(rep, sim, "not_arrived".into());
            }
        };
        rep.flown = true;
        // The measurement: a few frames a little apart, each with the
        // position the vehicle reports then (and the judge's pose error).
        let m = params.refine.measure;
        let mut images = Vec::new();
        let mut reported = Vec::new();
        let mut judged = Vec::new();
        let mut true_offset = Vector3::zeros();
        for i in 0..m.frames.max(1) {
            if i > 0 {
                sim.advance(m.spacing_s);
            }
            judged.push(pose_difference(&hidden.camera, &sim.true_camera()));
            true_offset += sim.ap.vehicle().position_error() / m.frames.max(1) as f64;
            images.push(sim.render());
            reported.push(sim.ap.vehicle().p_ned());
        }
        let frames: Vec<LiveFrame<'_>> = images
            .iter()
            .zip(&reported)
            .map(|(image, r)| LiveFrame {
                image,
                reported_ned_m: Some(*r),
            })
            .collect();
        let step = session.on_arrival(&frames, sim.t, Some(&cam_model), &ctx);
        let Some(record) = session.rounds().last().cloned() else {
            return finish(rep, sim, "no_round".into());
        };
        let judge = |f: &dyn Fn(&crate::refine::PoseDifference) -> f64| {
            crate::stats::finite_median(&judged.iter().map(f).collect::<Vec<_>>())
                .unwrap_or(f64::NAN)
        };
        let (position_m, yaw_deg, pitch_deg, rotation_deg) = (
            judge(&|d| d.position_m),
            judge(&|d| d.yaw_deg),
            judge(&|d| d.pitch_deg),
            judge(&|d| d.rotation_deg),
        );
        if record.round == 0 {
            rep.first_shot_error_pct = record.shot_error_pct;
            rep.first_position_error_m = Some(position_m);
        }
        rep.final_shot_error_pct = record.shot_error_pct;
        rep.position_error_m = Some(position_m);
        rep.yaw_error_deg = Some(yaw_deg);
        rep.pitch_error_deg = Some(pitch_deg);
        rep.rounds = record.round;
        rep.round_reports.push(RoundReport {
            record,
            position_error_m: position_m,
            yaw_error_deg: yaw_deg,
            pitch_error_deg: pitch_deg,
            rotation_error_deg: rotation_deg,
            true_offset_ned_m: true_offset.into(),
            flight_s,
        });
        if let Step::Done(stop) = step {
            if let Stop::LiveNotLocalised(r) | Stop::CorrectionRefused(r) = &stop {
                rep.reason = Some(r.clone());
            }
            return finish(rep, sim, stop.name().into());
        }
    }
}

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
        converged: trials.iter().filter(|t| t.stop == "converged").count(),
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
        explore: ex.report.clone(),
        trial_reports: trials,
        wall_s: wall.elapsed().as_secs_f64(),
    })
}
