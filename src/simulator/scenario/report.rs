//! What a scenario run returns: the explore flight's report, each trial's
//! with its measurements on arrival, and the whole scenario's summary.

use serde::Serialize;

use crate::refine::RoundRecord;

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
    /// The mount's offsets the fit learned (the scenario's camera is
    /// mounted [`super::Disturbances::gimbal_pitch_offset_deg`] and
    /// [`super::Disturbances::camera_yaw_offset_deg`] off).
    pub mount_offset: Option<crate::geo::MountOffset>,
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
    /// Live frames localised and paired with telemetry before the
    /// departure (with a drift model, [`crate::geo::AlignParams::drift`]).
    pub departure_pairs: usize,
    /// Of those, the ones the refitted georeference took as inliers.
    pub departure_inliers: usize,
    /// The GNSS bias the georeference estimated at its newest pair, NED m
    /// (with a drift model).
    pub gnss_bias_m: Option<[f64; 3]>,
    /// The mount's offsets learned by the georeference the shot was flown
    /// with.
    pub mount_offset: Option<crate::geo::MountOffset>,
    /// Localisation error of the desired shot (through the georeference)
    /// against the hidden camera, m. A georeference that follows the drift
    /// maps into the NED the receiver reads now, so this includes the
    /// GNSS bias of the moment (the vehicle flies in that NED too).
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
    /// Simulated seconds from the first arrival at the shot to the photo
    /// (servoing) or to the loop's last measurement (rounds).
    pub arrival_to_photo_s: Option<f64>,
    /// Servoing at the shot, when it ran.
    /// Targets flown instead on the approaches, converted again with the
    /// georeference refitted in flight ([`crate::refine::approach`]).
    pub retargets: usize,
    pub servo: Option<super::servo::ServoReport>,
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
    /// Trials that converged under the threshold: the rounds stopped
    /// `converged`, or the servo's photo is under it.
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
    /// Servoing at the shot was on (`servo_*` stops).
    pub servo: bool,
    /// Trials whose servoing settled under its threshold.
    pub servo_settled: usize,
    /// Median simulated seconds from the first arrival to the photo.
    pub median_arrival_to_photo_s: Option<f64>,
    /// The explore flight.
    pub explore: ExploreReport,
    /// Every trial.
    pub trial_reports: Vec<TrialReport>,
    /// Wall seconds of everything.
    pub wall_s: f64,
}
