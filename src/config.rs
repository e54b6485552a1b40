//! The typed tree of `config.toml`.
//!
//! Every section and key is optional in the file: a missing key takes its
//! default (the defaults run the daemon against the bundled simulator). An
//! unknown key is an error that names the key and its line, so a typo never
//! passes silently.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::{Camera, CameraError, Distortion};
pub use crate::video::source::{VideoConfig, VideoSource};

/// Errors reading the configuration.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("cannot read config {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The file is not valid TOML for this schema; the message names the key
    /// and shows the line.
    #[error("config {path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// toml's message, with line, column and the offending key.
        message: String,
    },
    /// A value is out of its range.
    #[error("config {path}: [{section}] {key}: {reason}")]
    Invalid {
        /// The file.
        path: PathBuf,
        /// The section.
        section: &'static str,
        /// The key.
        key: &'static str,
        /// What is wrong.
        reason: String,
    },
}

/// The whole configuration.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Config {
    /// The camera that films the video the SLAM runs on.
    pub camera: CameraConfig,
    /// `[link]`: the MAVLink link to the vehicle (transport URL, ids,
    /// heartbeat, link-lost time, reconnect backoff, telemetry rates, signing).
    pub link: crate::vehicle::Params,
    /// `[mission]`: planner numbers, geofence, transfer timeouts and retries.
    pub mission: crate::mission::Params,
    /// `[video]`: where the live video comes from.
    pub video: VideoConfig,
    /// `[server]`: the HTTP API and the operator's page.
    pub server: ServerConfig,
    /// `[slam]`: the daemon's SLAM thread.
    pub slam: SlamConfig,
    /// `[sim]`: the simulator run in-process.
    pub sim: SimSection,
    /// `[geo]`: the georeference (time alignment and video latency,
    /// camera mounting, map → NED alignment).
    pub geo: crate::geo::Params,
    /// `[refine]`: the closed loop after a shot's mission is started
    /// (threshold, rounds, controller gains and steps, arrival rule,
    /// waiting limits).
    pub refine: RefineSection,
    /// `[shot]`: the localisation's confidence gate.
    pub shot: ShotSection,
}

/// `[shot]`: bounds on a localised shot's sigma (the gate refuses a pose
/// whose uncertainty exceeds them, saying so), mapped onto
/// [`crate::shot::GateParams`] by [`ShotSection::localize_params`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ShotSection {
    /// Largest position sigma, % of the distance to the nearest scene content.
    pub max_position_sigma_pct: f64,
    /// Largest rotation sigma, degrees.
    pub max_rotation_sigma_deg: f64,
}

impl Default for ShotSection {
    fn default() -> Self {
        let g = crate::shot::GateParams::default();
        Self {
            max_position_sigma_pct: g.max_position_sigma_depth_fraction * 100.0,
            max_rotation_sigma_deg: g.max_rotation_sigma_deg,
        }
    }
}

impl ShotSection {
    /// The localisation's parameters with these bounds.
    pub fn localize_params(&self) -> crate::shot::LocalizeParams {
        let mut p = crate::shot::LocalizeParams::default();
        p.gate.max_position_sigma_depth_fraction = self.max_position_sigma_pct / 100.0;
        p.gate.max_rotation_sigma_deg = self.max_rotation_sigma_deg;
        p
    }

    fn validate(&self) -> Result<(), (&'static str, String)> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !positive(self.max_position_sigma_pct) {
            return Err(("max_position_sigma_pct", "must be positive".into()));
        }
        if !(positive(self.max_rotation_sigma_deg) && self.max_rotation_sigma_deg <= 180.0) {
            return Err(("max_rotation_sigma_deg", "must be in (0, 180]".into()));
        }
        Ok(())
    }
}

/// `[server]`: the HTTP API.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ServerConfig {
    /// Listen address (`127.0.0.1:0` picks a free port).
    pub bind: String,
    /// Bearer token required on state-changing endpoints (unset: none).
    pub token: Option<String>,
    /// Largest request body, bytes.
    pub body_limit_bytes: usize,
    /// Where shots and the map are kept (relative to the config file).
    pub data_dir: PathBuf,
    /// Status updates per second on `/api/v1/events` at most (the whole
    /// status on connect, then only what changed).
    pub events_hz: f64,
    /// Most map points `/api/v1/map` returns.
    pub map_max_points: usize,
    /// Most keypoints `/api/v1/features` returns (the page's feature
    /// overlay): inliers first, then outliers, then unmatched.
    pub features_max: usize,
}

impl Default for ServerConfig {
    fn default() -> Self {
        Self {
            bind: "127.0.0.1:8080".into(),
            token: None,
            body_limit_bytes: 8 << 20,
            data_dir: PathBuf::from("data"),
            events_hz: 2.0,
            map_max_points: 20_000,
            features_max: 500,
        }
    }
}

/// `[slam]`: the daemon's SLAM thread.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SlamConfig {
    /// Run the SLAM on the live video.
    pub enabled: bool,
    /// Map file written on shutdown and at each checkpoint (relative to
    /// `server.data_dir`); the georeference it is tied to goes beside it
    /// (`<map_file>.geo.json`).
    pub map_file: PathBuf,
    /// Seconds between checkpoints of the map (and its georeference) while
    /// the daemon runs, written when the map changed, so a crash or a kill
    /// loses at most this much mapping (0: only on shutdown).
    pub checkpoint_s: f64,
    /// At start, go on with the map in `map_file` when there is one (the
    /// SLAM relocalises into it, so shots and the georeference stay in one
    /// frame); false: start a fresh map (the old file is kept under a new
    /// name).
    pub continue_map: bool,
    /// Extra time spent per frame, ms (0: none; to test that a slow SLAM
    /// never stalls the video).
    pub artificial_delay_ms: u64,
    /// Close loops: a place seen again corrects the drift of the map
    /// (on its own thread beside local mapping; see `slam::loop_closing`).
    pub loop_closing: bool,
    /// Telemetry priors: the link's GNSS fixes (GLOBAL_POSITION_INT with
    /// GPS_RAW_INT's fix and reported accuracy) put the map in local NED
    /// once enough keyframes with a fix span a baseline, and hold it there
    /// in bundle adjustment (`slam::priors`); the georeference then follows
    /// from the map. Off by default: with priors a tracking loss starts no
    /// new map (tracking relocalises instead), and a receiver that reports
    /// a better accuracy than it has pulls the map; vision-only with the
    /// after-the-fact fit is the behaviour every daemon test and figure so
    /// far was measured with.
    pub priors: bool,
    /// Telemetry-aided tracking (`slam::aided`): a frame vision cannot pose
    /// is predicted from the last one it did by the link's attitude and
    /// gimbal reports (and the GNSS once the map is in local NED), the
    /// local map searched around it, or the prediction kept for up to 10 s;
    /// a flat field's two reconstructions are told apart by the reported
    /// turn; with `priors` a new map after a loss is put into the old one
    /// as it initialises. The status counts the frames each way posed
    /// (`slam.posed_by_*`). Off by default.
    pub aid: bool,
}

impl Default for SlamConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            map_file: PathBuf::from("map.spmap"),
            checkpoint_s: 30.0,
            continue_map: true,
            artificial_delay_ms: 0,
            loop_closing: true,
            priors: false,
            aid: false,
        }
    }
}

/// `[sim]`: the bundled simulator, started inside the daemon. A build
/// without the `sim` feature parses it too (files stay valid) and refuses
/// `enabled = true` at start.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SimSection {
    /// Start the simulator.
    pub enabled: bool,
    /// Address of its MJPEG server (match `[video] url`).
    pub video_listen: String,
    /// Its video frame rate, frames per second.
    pub video_fps: f64,
    /// Its MAVLink endpoint (match `[link] url`).
    pub mavlink: String,
    /// World and noise seed.
    pub seed: u64,
    /// Scripted flight: `explore`, `hover`, `patrol` (the survey flown lap
    /// after lap until the operator takes over) or `none`.
    pub script: String,
    /// Autopilot flavour: `px4` or `ardupilot`.
    pub flavour: String,
    /// Write the simulator's ground truth (camera trajectory, video frame
    /// poses) to this folder (relative to `server.data_dir`); unset: none.
    pub truth_dir: Option<PathBuf>,
    /// GPS bias of the simulated vehicle (the true position is the reported
    /// one plus the bias, a first-order Gauss-Markov process from zero,
    /// seeded from `gps_seed` or `seed`): horizontal standard deviation per
    /// axis, m (0: no bias).
    pub gps_sigma_xy_m: f64,
    /// Its vertical standard deviation, m (0: none).
    pub gps_sigma_z_m: f64,
    /// Its correlation time, s.
    pub gps_tau_s: f64,
    /// Seed of the bias's walk (unset: `seed`, so each world has its own).
    pub gps_seed: Option<u64>,
    /// The video URI its camera announces in VIDEO_STREAM_INFORMATION (for
    /// `[video] url = "auto"`); unset: its H.264 RTP stream's
    /// `udp://HOST:PORT` when `rtp_out` is set, else its own MJPEG URL.
    pub video_stream_uri: Option<String>,
    /// Also send its camera as H.264 over RTP/UDP to `HOST:PORT` (RTCP
    /// sender reports to the next port); unset: MJPEG only.
    pub rtp_out: Option<String>,
    /// Target bitrate of the H.264 stream, kbit/s.
    pub rtp_bitrate_kbps: u32,
    /// Realism of the simulated camera, vehicle and radio: `ideal`,
    /// `field` or `harsh`, then any `-EFFECT` or `+EFFECT[@PRESET]`
    /// (see the simulator crate's `realism`), e.g. `field-blur`; checked by
    /// `crate::simulator::check`.
    pub realism: String,
    /// The simulated world: town, grass, carpark, trees, water, traffic
    /// or aliasing.
    pub world: String,
    /// Lockstep (for tests and experiments): the simulator holds its clock
    /// after each video frame until the daemon's SLAM is done with it,
    /// tracking and the mapping and loop closing it triggered (run inline),
    /// so the run no longer depends on the machine's speed; on a tokio
    /// runtime with paused time the whole run is on simulated time. Off: real
    /// time, and frames the SLAM is too busy for are skipped. Needs the
    /// simulator's MJPEG video (no `rtp_out`).
    pub lockstep: bool,
}

impl SimSection {
    /// Whether the simulator runs in lockstep: asked for, and the
    /// simulator started.
    pub fn lockstep_on(&self) -> bool {
        self.enabled && self.lockstep
    }
}

impl Default for SimSection {
    fn default() -> Self {
        Self {
            enabled: true,
            video_listen: "127.0.0.1:8554".into(),
            video_fps: 15.0,
            mavlink: "udpout:127.0.0.1:14550".into(),
            seed: 1,
            script: "explore".into(),
            flavour: "px4".into(),
            truth_dir: None,
            gps_sigma_xy_m: 0.0,
            gps_sigma_z_m: 0.0,
            gps_tau_s: 120.0,
            gps_seed: None,
            video_stream_uri: None,
            rtp_out: None,
            rtp_bitrate_kbps: 1500,
            realism: "ideal".into(),
            world: "town".into(),
            lockstep: false,
        }
    }
}

/// `[refine]`: the daemon's refinement loop, mapped onto
/// [`crate::refine::loop_params::LoopParams`] by [`RefineSection::params`];
/// numbers not listed here keep their defaults there.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RefineSection {
    /// Stop when the shot error is below this, % of the image diagonal.
    pub threshold_pct: f64,
    /// Corrections uploaded at most after the first flight.
    pub max_rounds: usize,
    /// An anchors shot stops `at_floor` within this much of its floor, %
    /// of the diagonal (or within the measurement's noise, if larger).
    pub at_floor_margin_pct: f64,
    /// Near its floor (within this many % of the diagonal) after a
    /// correction, the loop ends `at_floor`, after flying back to the best
    /// round's view if it measured worse than that by more than
    /// `at_floor_margin_pct`.
    pub stall_band_pct: f64,
    /// Fraction of the measured pose error the first correction removes,
    /// in (0, 1].
    pub gain: f64,
    /// Largest fraction the later corrections remove, in (0, 1] (each
    /// removes what the measurement supports against the drift since the
    /// last one, at most this).
    pub later_gain: f64,
    /// Growth of the variance of the vehicle's position offset (GNSS bias)
    /// per second between measurements, m²/s per axis (2σ²/τ of the
    /// receiver's bias).
    pub position_drift_m2_per_s: f64,
    /// A target change within this many standard deviations of the
    /// measurement is not flown.
    pub gate_sigmas: f64,
    /// Live frames measured per arrival.
    pub measure_frames: usize,
    /// Time between two measured frames, s.
    pub measure_spacing_s: f64,
    /// Largest horizontal or vertical move of one correction, m.
    pub max_step_m: f64,
    /// Largest yaw or pitch change of one correction, degrees.
    pub max_step_deg: f64,
    /// Arrival: largest ground speed, m/s.
    pub arrival_speed_m_s: f64,
    /// Arrival: largest gap between reported and commanded gimbal pitch,
    /// degrees.
    pub arrival_gimbal_deg: f64,
    /// Arrival: the conditions hold this long, s.
    pub arrival_dwell_s: f64,
    /// ORB features per image for the shot error.
    pub error_features: usize,
    /// Fewest homography inliers for a shot error.
    pub error_min_inliers: usize,
    /// Longest flight to one target before the loop gives up, s.
    pub max_flight_s: f64,
    /// Longest wait for a video frame received after the arrival, s.
    pub frame_wait_s: f64,
    /// Telemetry older than this counts as missing, s.
    pub max_telemetry_age_s: f64,
    /// Telemetry polling period, ms.
    pub poll_ms: u64,
    /// Servo at the shot after the first arrival (a mission leg first for
    /// a longer correction): per processed frame, guided setpoints (PX4
    /// OFFBOARD, ArduPilot GUIDED) and the photo when the error is under
    /// `servo_threshold_pct`.
    pub servo: bool,
    /// The servo's photo threshold, % of the image diagonal (after half of
    /// `servo_max_s` it rises linearly to twice this at `servo_max_s`).
    pub servo_threshold_pct: f64,
    /// Servoing time after which a frame among the best measured takes the
    /// photo (after 1.5 times this, the photo is taken where it is), s.
    pub servo_max_s: f64,
    /// Re-targeting on the approach (`[refine.approach]`): the target
    /// converted again with the georeference refitted in flight, flown
    /// when it moved beyond a fit's noise.
    pub approach: crate::refine::ApproachParams,
}

impl Default for RefineSection {
    fn default() -> Self {
        let p = crate::refine::loop_params::LoopParams::default();
        let c = &p.refine.controller;
        let a = &p.refine.arrival;
        let e = &p.refine.error;
        Self {
            threshold_pct: c.threshold_pct,
            max_rounds: c.max_rounds,
            at_floor_margin_pct: c.at_floor_margin_pct,
            stall_band_pct: c.stall_band_pct,
            gain: c.gain,
            later_gain: c.later_gain,
            position_drift_m2_per_s: c.position_drift_m2_per_s,
            gate_sigmas: c.gate_sigmas,
            measure_frames: p.refine.measure.frames,
            measure_spacing_s: p.refine.measure.spacing_s,
            max_step_m: c.max_step_m,
            max_step_deg: c.max_step_deg,
            arrival_speed_m_s: a.speed_m_s,
            arrival_gimbal_deg: a.gimbal_deg,
            arrival_dwell_s: a.dwell_s,
            error_features: e.features.n_features,
            error_min_inliers: e.homography.min_inliers,
            max_flight_s: p.max_flight.as_secs_f64(),
            frame_wait_s: p.frame_wait.as_secs_f64(),
            max_telemetry_age_s: p.max_telemetry_age.as_secs_f64(),
            poll_ms: u64::try_from(p.poll.as_millis()).unwrap_or(u64::MAX),
            servo: p.servo.is_some(),
            servo_threshold_pct: crate::refine::ServoParams::default().threshold_pct,
            servo_max_s: crate::refine::ServoParams::default().max_s,
            approach: p.refine.approach,
        }
    }
}

impl RefineSection {
    /// The loop's parameters (call after [`Config::validate`]: durations
    /// out of range are clamped, not refused, here).
    pub fn params(&self) -> crate::refine::loop_params::LoopParams {
        let mut p = crate::refine::loop_params::LoopParams::default();
        let c = &mut p.refine.controller;
        c.threshold_pct = self.threshold_pct;
        c.max_rounds = self.max_rounds;
        c.at_floor_margin_pct = self.at_floor_margin_pct;
        c.stall_band_pct = self.stall_band_pct;
        c.gain = self.gain;
        c.later_gain = self.later_gain;
        c.position_drift_m2_per_s = self.position_drift_m2_per_s;
        c.gate_sigmas = self.gate_sigmas;
        c.max_step_m = self.max_step_m;
        c.max_step_deg = self.max_step_deg;
        p.refine.measure.frames = self.measure_frames;
        p.refine.measure.spacing_s = self.measure_spacing_s;
        let a = &mut p.refine.arrival;
        a.speed_m_s = self.arrival_speed_m_s;
        a.gimbal_deg = self.arrival_gimbal_deg;
        a.dwell_s = self.arrival_dwell_s;
        p.refine.approach = self.approach;
        let e = &mut p.refine.error;
        e.features.n_features = self.error_features;
        e.homography.min_inliers = self.error_min_inliers;
        let secs = |s: f64| std::time::Duration::try_from_secs_f64(s).unwrap_or_default();
        p.max_flight = secs(self.max_flight_s);
        p.frame_wait = secs(self.frame_wait_s);
        p.max_telemetry_age = secs(self.max_telemetry_age_s);
        p.poll = std::time::Duration::from_millis(self.poll_ms);
        p.servo = self.servo.then(|| crate::refine::ServoParams {
            threshold_pct: self.servo_threshold_pct,
            max_s: self.servo_max_s,
            position_drift_m2_per_s: self.position_drift_m2_per_s,
            ..crate::refine::ServoParams::default()
        });
        p
    }

    fn validate(&self) -> Result<(), (&'static str, String)> {
        let positive = |v: f64| v.is_finite() && v > 0.0;
        if !(positive(self.threshold_pct) && self.threshold_pct < 100.0) {
            return Err(("threshold_pct", "must be in (0, 100) %".into()));
        }
        if self.max_rounds > 100 {
            return Err(("max_rounds", "must be at most 100".into()));
        }
        if !(self.at_floor_margin_pct.is_finite()
            && (0.0..=10.0).contains(&self.at_floor_margin_pct))
        {
            return Err(("at_floor_margin_pct", "must be in [0, 10] %".into()));
        }
        if !(self.stall_band_pct.is_finite() && (0.0..=10.0).contains(&self.stall_band_pct)) {
            return Err(("stall_band_pct", "must be in [0, 10] %".into()));
        }
        if !(positive(self.gain) && self.gain <= 1.0) {
            return Err(("gain", "must be in (0, 1]".into()));
        }
        if !(positive(self.later_gain) && self.later_gain <= 1.0) {
            return Err(("later_gain", "must be in (0, 1]".into()));
        }
        if !(self.position_drift_m2_per_s.is_finite() && self.position_drift_m2_per_s >= 0.0) {
            return Err(("position_drift_m2_per_s", "must be finite and >= 0".into()));
        }
        if !(self.gate_sigmas.is_finite() && (0.0..=10.0).contains(&self.gate_sigmas)) {
            return Err(("gate_sigmas", "must be in [0, 10]".into()));
        }
        if !(1..=30).contains(&self.measure_frames) {
            return Err(("measure_frames", "must be in [1, 30]".into()));
        }
        if !(self.measure_spacing_s.is_finite() && (0.0..=5.0).contains(&self.measure_spacing_s)) {
            return Err(("measure_spacing_s", "must be in [0, 5] s".into()));
        }
        if !positive(self.max_step_m) {
            return Err(("max_step_m", "must be finite and > 0 m".into()));
        }
        if !(positive(self.max_step_deg) && self.max_step_deg <= 180.0) {
            return Err(("max_step_deg", "must be in (0, 180] deg".into()));
        }
        if !positive(self.arrival_speed_m_s) {
            return Err(("arrival_speed_m_s", "must be finite and > 0 m/s".into()));
        }
        if !positive(self.arrival_gimbal_deg) {
            return Err(("arrival_gimbal_deg", "must be finite and > 0 deg".into()));
        }
        if !(self.arrival_dwell_s.is_finite() && (0.0..=60.0).contains(&self.arrival_dwell_s)) {
            return Err(("arrival_dwell_s", "must be in [0, 60] s".into()));
        }
        if !(100..=10_000).contains(&self.error_features) {
            return Err(("error_features", "must be in [100, 10000]".into()));
        }
        if !(8..=1000).contains(&self.error_min_inliers) {
            return Err(("error_min_inliers", "must be in [8, 1000]".into()));
        }
        for (key, v, max) in [
            ("max_flight_s", self.max_flight_s, 3600.0),
            ("frame_wait_s", self.frame_wait_s, 60.0),
            ("max_telemetry_age_s", self.max_telemetry_age_s, 60.0),
        ] {
            if !(positive(v) && v <= max) {
                return Err((key, format!("must be in (0, {max}] s")));
            }
        }
        if !(10..=10_000).contains(&self.poll_ms) {
            return Err(("poll_ms", "must be in [10, 10000] ms".into()));
        }
        if !(positive(self.servo_threshold_pct) && self.servo_threshold_pct < 100.0) {
            return Err(("servo_threshold_pct", "must be in (0, 100) %".into()));
        }
        if !(positive(self.servo_max_s) && self.servo_max_s <= 600.0) {
            return Err(("servo_max_s", "must be in (0, 600] s".into()));
        }
        self.approach.check().map_err(|e| ("approach", e))?;
        Ok(())
    }
}

/// `[camera]`: intrinsics of the drone's camera.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct CameraConfig {
    /// A TUM-style `calib.txt` to read instead of the numbers below.
    pub calib_file: Option<PathBuf>,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Radial distortion r^2.
    pub k1: f64,
    /// Radial distortion r^4.
    pub k2: f64,
    /// Tangential distortion 1.
    pub p1: f64,
    /// Tangential distortion 2.
    pub p2: f64,
    /// Radial distortion r^6.
    pub k3: f64,
    /// Rolling-shutter readout, ms (first row to last; 0: a global
    /// shutter). Unset: the bundled simulator's own when it runs, else 0.
    pub readout_ms: Option<f64>,
}

impl Default for CameraConfig {
    fn default() -> Self {
        // The bundled simulator's default gimbal camera.
        CameraConfig {
            calib_file: None,
            width: 640,
            height: 480,
            fx: 460.0,
            fy: 460.0,
            cx: 319.5,
            cy: 239.5,
            k1: -0.05,
            k2: 0.01,
            p1: 0.0,
            p2: 0.0,
            k3: 0.0,
            readout_ms: None,
        }
    }
}

impl CameraConfig {
    /// The camera this section describes (reading `calib_file` when set,
    /// relative to `base_dir`).
    pub fn camera(&self, base_dir: &Path) -> Result<Camera, CameraError> {
        let mut camera = self.intrinsics(base_dir)?;
        camera.readout_s = self.readout_ms.unwrap_or(0.0) / 1000.0;
        camera.validate()?;
        Ok(camera)
    }

    /// The camera's intrinsics and distortion (`calib_file`, else the keys).
    fn intrinsics(&self, base_dir: &Path) -> Result<Camera, CameraError> {
        if let Some(file) = &self.calib_file {
            return Camera::from_calib_file(&base_dir.join(file), self.width, self.height);
        }
        Camera::new(
            self.width,
            self.height,
            [self.fx, self.fy, self.cx, self.cy],
            Distortion {
                k1: self.k1,
                k2: self.k2,
                p1: self.p1,
                p2: self.p2,
                k3: self.k3,
            },
        )
    }
}

impl Config {
    /// Parse a configuration from TOML text; `path` names it in errors.
    pub fn from_toml(text: &str, path: &Path) -> Result<Self, ConfigError> {
        let cfg: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: path.to_owned(),
            message: e.to_string().trim_end().to_owned(),
        })?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Read and parse a configuration file.
    pub fn load(path: &Path) -> Result<Self, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::from_toml(&text, path)
    }

    /// Check ranges that the types cannot express.
    pub fn validate(&self, path: &Path) -> Result<(), ConfigError> {
        let c = &self.camera;
        if c.calib_file.is_none() {
            c.camera(Path::new(".")).map_err(|e| ConfigError::Invalid {
                path: path.to_owned(),
                section: "camera",
                key: "fx/fy/width/height/readout_ms",
                reason: e.to_string(),
            })?;
        }
        let invalid =
            |section: &'static str, key: &'static str, reason: String| ConfigError::Invalid {
                path: path.to_owned(),
                section,
                key,
                reason,
            };
        let url = crate::video::source::VideoUrl::parse(&self.video.url)
            .map_err(|e| invalid("video", "url", e.to_string()))?;
        if let crate::video::source::VideoUrl::Http(u) = &url {
            crate::video::mjpeg::HttpUrl::parse(u)
                .map_err(|e| invalid("video", "url", e.to_string()))?;
        }
        if !(1..=8).contains(&self.video.downscale) {
            return Err(invalid("video", "downscale", "must be 1 to 8".into()));
        }
        if self.video.decode_queue == 0 {
            return Err(invalid(
                "video",
                "decode_queue",
                "must be at least 1".into(),
            ));
        }
        if !(self.video.auto_timeout_s > 0.0 && self.video.auto_timeout_s.is_finite()) {
            return Err(invalid("video", "auto_timeout_s", "must be > 0".into()));
        }
        if !(self.video.snapshot_hz > 0.0 && self.video.snapshot_hz <= 200.0) {
            return Err(invalid(
                "video",
                "snapshot_hz",
                "must be in (0, 200]".into(),
            ));
        }
        self.server
            .bind
            .parse::<std::net::SocketAddr>()
            .map_err(|e| invalid("server", "bind", e.to_string()))?;
        if self.server.body_limit_bytes < 1024 {
            return Err(invalid(
                "server",
                "body_limit_bytes",
                "must be at least 1024".into(),
            ));
        }
        if self.server.token.as_deref().is_some_and(str::is_empty) {
            return Err(invalid(
                "server",
                "token",
                "empty; leave it unset for no token".into(),
            ));
        }
        if !(self.server.events_hz > 0.0 && self.server.events_hz <= 50.0) {
            return Err(invalid("server", "events_hz", "must be in (0, 50]".into()));
        }
        if self.geo.align.drift.is_some_and(|d| !d.is_valid()) {
            return Err(invalid(
                "geo.align.drift",
                "sigma_xy_m/sigma_z_m/tau_s/noise_xy_m/noise_z_m/window_s",
                "every one must be a positive number".into(),
            ));
        }
        if !(self.slam.checkpoint_s >= 0.0 && self.slam.checkpoint_s <= 86_400.0) {
            return Err(invalid(
                "slam",
                "checkpoint_s",
                "must be in [0, 86400] s (0: only on shutdown)".into(),
            ));
        }
        if self.sim.enabled {
            self.sim
                .video_listen
                .parse::<std::net::SocketAddr>()
                .map_err(|e| invalid("sim", "video_listen", e.to_string()))?;
            if !["explore", "hover", "patrol", "none"].contains(&self.sim.script.as_str()) {
                return Err(invalid(
                    "sim",
                    "script",
                    format!("{:?}: use explore, hover, patrol or none", self.sim.script),
                ));
            }
            if !["px4", "ardupilot"].contains(&self.sim.flavour.as_str()) {
                return Err(invalid(
                    "sim",
                    "flavour",
                    format!("{:?}: use px4 or ardupilot", self.sim.flavour),
                ));
            }
            if !(self.sim.video_fps > 0.0 && self.sim.video_fps <= 120.0) {
                return Err(invalid("sim", "video_fps", "must be in (0, 120]".into()));
            }
            if self.sim.lockstep && self.sim.rtp_out.is_some() {
                return Err(invalid(
                    "sim",
                    "lockstep",
                    "lockstep hands the SLAM the simulator's MJPEG frames: unset rtp_out".into(),
                ));
            }
            // Realism, world, RTP output and GPS bias need the simulator:
            // `crate::simulator::check`.
        }
        self.link
            .url
            .parse::<crate::vehicle::LinkUrl>()
            .map_err(|e| invalid("link", "url", e.to_string()))?;
        if let Some(s) = &self.link.signing {
            s.key()
                .map_err(|e| invalid("link.signing", "key_hex", e.to_string()))?;
        }
        if self.link.heartbeat_period_ms == 0 || self.link.link_lost_after_ms == 0 {
            return Err(invalid(
                "link",
                "heartbeat_period_ms/link_lost_after_ms",
                "must be positive".into(),
            ));
        }
        let h = &self.geo.history;
        if !(h.video_latency_s.is_finite() && (0.0..=10.0).contains(&h.video_latency_s)) {
            return Err(invalid(
                "geo.history",
                "video_latency_s",
                "must be in [0, 10] s".into(),
            ));
        }
        if !(h.max_gap_s > 0.0 && h.max_gap_s.is_finite()) {
            return Err(invalid(
                "geo.history",
                "max_gap_s",
                "must be finite and > 0 s".into(),
            ));
        }
        if !(h.max_age_s.is_finite() && h.max_age_s >= h.max_gap_s) {
            return Err(invalid(
                "geo.history",
                "max_age_s",
                "must be finite and at least max_gap_s".into(),
            ));
        }
        let m = &self.geo.mount;
        if !(m.pitch_min_deg < m.pitch_max_deg && m.lever_arm_body_m.iter().all(|v| v.is_finite()))
        {
            return Err(invalid(
                "geo.mount",
                "pitch_min_deg/pitch_max_deg/lever_arm_body_m",
                "need pitch_min_deg < pitch_max_deg and a finite lever arm".into(),
            ));
        }
        if !([m.pitch_offset_deg, m.yaw_offset_deg]
            .iter()
            .all(|v| v.is_finite() && v.abs() <= 45.0))
        {
            return Err(invalid(
                "geo.mount",
                "pitch_offset_deg/yaw_offset_deg",
                "must be finite degrees within +-45 (a calibration offset, not a mounting)".into(),
            ));
        }
        let s = self.geo.align.mount_offset_sigma_deg;
        if !(s.is_finite() && s > 0.0 && s <= 45.0) {
            return Err(invalid(
                "geo.align",
                "mount_offset_sigma_deg",
                "must be in (0, 45] degrees".into(),
            ));
        }
        let c = &self.geo.continuity;
        if !(c.frame_pair_spacing_s.is_finite() && (0.0..=3600.0).contains(&c.frame_pair_spacing_s))
        {
            return Err(invalid(
                "geo.continuity",
                "frame_pair_spacing_s",
                "must be in [0, 3600] s (0: no frame pairs)".into(),
            ));
        }
        if c.max_frame_pairs > 10_000 {
            return Err(invalid(
                "geo.continuity",
                "max_frame_pairs",
                "must be at most 10000".into(),
            ));
        }
        if !(c.disagreement_factor.is_finite() && c.disagreement_factor >= 1.0) {
            return Err(invalid(
                "geo.continuity",
                "disagreement_factor",
                "must be finite and at least 1".into(),
            ));
        }
        let fence = &self.mission.plan.fence;
        if !(fence.radius_m > 0.0 && fence.min_alt_m < fence.max_alt_m) {
            return Err(invalid(
                "mission.plan.fence",
                "radius_m/min_alt_m/max_alt_m",
                format!(
                    "need radius_m > 0 and min_alt_m < max_alt_m, got {} m, {} m, {} m",
                    fence.radius_m, fence.min_alt_m, fence.max_alt_m
                ),
            ));
        }
        self.refine
            .validate()
            .map_err(|(key, reason)| invalid("refine", key, reason))?;
        self.shot
            .validate()
            .map_err(|(key, reason)| invalid("shot", key, reason))?;
        if self.mission.transfer.retry_timeout_ms == 0 {
            return Err(invalid(
                "mission.transfer",
                "retry_timeout_ms",
                "must be positive".into(),
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shipped_config_parses_and_equals_defaults_where_unset() {
        let text = include_str!("../config.toml");
        let cfg = Config::from_toml(text, Path::new("config.toml")).unwrap();
        assert_eq!(cfg.camera, CameraConfig::default());
        assert_eq!(cfg.link, crate::vehicle::Params::default());
        assert_eq!(cfg.mission, crate::mission::Params::default());
        assert_eq!(cfg.video, VideoConfig::default());
        assert_eq!(cfg.server, ServerConfig::default());
        assert_eq!(cfg.slam, SlamConfig::default());
        assert_eq!(cfg.sim, SimSection::default());
        assert_eq!(cfg.geo, crate::geo::Params::default());
        assert_eq!(cfg.refine, RefineSection::default());
    }

    #[test]
    fn the_mount_calibration_is_configured_and_checked() {
        let cfg = Config::from_toml(
            "[geo.mount]\npitch_offset_deg = -1.5\nyaw_offset_deg = 0.5\n[geo.align]\nestimate_mount = false\n",
            Path::new("x.toml"),
        )
        .unwrap();
        assert_eq!(cfg.geo.mount.pitch_offset_deg, -1.5);
        assert_eq!(cfg.geo.mount.yaw_offset_deg, 0.5);
        assert!(!cfg.geo.align.estimate_mount);
        assert!(Config::default().geo.align.estimate_mount);
        for bad in [
            "[geo.mount]\npitch_offset_deg = 90.0\n",
            "[geo.mount]\nyaw_offset_deg = nan\n",
            "[geo.align]\nmount_offset_sigma_deg = 0.0\n",
        ] {
            let e = Config::from_toml(bad, Path::new("x.toml"));
            assert!(
                e.as_ref().is_err_and(|e| e.to_string().contains("offset")),
                "{bad}: {e:?}"
            );
        }
    }

    #[test]
    fn a_drift_model_is_configured_by_its_section() {
        let cfg = Config::from_toml(
            "[geo.align]\ninlier_threshold_m = 2.5\n[geo.align.drift]\ntau_s = 60.0\n",
            Path::new("x.toml"),
        )
        .unwrap();
        assert_eq!(
            cfg.geo.align.drift,
            Some(crate::geo::GnssDrift {
                tau_s: 60.0,
                ..crate::geo::GnssDrift::default()
            })
        );
        assert_eq!(Config::default().geo.align.drift, None);
        let bad = Config::from_toml("[geo.align.drift]\ntau = 60.0\n", Path::new("x.toml"));
        assert!(bad.is_err(), "an unknown key is refused");
        let zero = Config::from_toml("[geo.align.drift]\ntau_s = 0.0\n", Path::new("x.toml"));
        assert!(
            zero.is_err_and(|e| e.to_string().contains("geo.align.drift")),
            "a zero correlation time is refused"
        );
    }

    #[test]
    fn refine_section_maps_onto_the_loop_params() {
        let d = crate::refine::loop_params::LoopParams::default();
        let p = RefineSection::default().params();
        assert_eq!(p.refine, d.refine);
        assert_eq!(
            (p.poll, p.max_flight, p.max_telemetry_age, p.frame_wait),
            (d.poll, d.max_flight, d.max_telemetry_age, d.frame_wait)
        );
        let cfg = Config::from_toml(
            "[refine]\nthreshold_pct = 0.5\nmax_rounds = 6\nlater_gain = 0.7\narrival_dwell_s = 2.0\nerror_features = 2000\nmax_flight_s = 30.0\npoll_ms = 50\n",
            Path::new("x.toml"),
        )
        .unwrap();
        let p = cfg.refine.params();
        assert_eq!(p.refine.controller.threshold_pct, 0.5);
        assert_eq!(p.refine.controller.max_rounds, 6);
        assert_eq!(p.refine.controller.later_gain, 0.7);
        assert_eq!(p.refine.arrival.dwell_s, 2.0);
        assert_eq!(p.refine.error.features.n_features, 2000);
        assert_eq!(p.max_flight, std::time::Duration::from_secs(30));
        assert_eq!(p.poll, std::time::Duration::from_millis(50));
        let cfg = Config::from_toml(
            "[refine.approach]\nenabled = false\nmin_shift_m = 0.3\nmax_per_leg = 2\n",
            Path::new("x.toml"),
        )
        .unwrap();
        let a = cfg.refine.params().refine.approach;
        assert!(!a.enabled);
        assert_eq!((a.min_shift_m, a.max_per_leg), (0.3, 2));
        assert_eq!(
            a.period_s,
            crate::refine::ApproachParams::default().period_s
        );
    }

    #[test]
    fn refine_keys_are_checked() {
        for (text, needle) in [
            ("[refine]\nthreshold_pct = 0.0\n", "[refine] threshold_pct"),
            ("[refine]\ngain = 1.5\n", "[refine] gain"),
            ("[refine]\nlater_gain = 0.0\n", "[refine] later_gain"),
            ("[refine]\nmax_step_m = -1.0\n", "[refine] max_step_m"),
            ("[refine]\nframe_wait_s = 0.0\n", "[refine] frame_wait_s"),
            ("[refine]\npoll_ms = 0\n", "[refine] poll_ms"),
            ("[refine]\nrounds = 3\n", "rounds"),
            ("[refine.approach]\nperiod_s = 0.0\n", "period_s"),
            ("[refine.approach]\nmin_turn_deg = -1.0\n", "min_turn_deg"),
            ("[refine.approach]\nperiod = 1.0\n", "period"),
        ] {
            let e = Config::from_toml(text, Path::new("x.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
    }

    #[test]
    fn daemon_sections_refuse_bad_values() {
        for (text, needle) in [
            ("[server]\nbind = \"nowhere\"\n", "bind"),
            ("[video]\nurl = \"ftp://cam/x\"\n", "url"),
            ("[video]\nurl = \"udp://cam:5600\"\n", "url"),
            ("[video]\ndownscale = 0\n", "downscale"),
            ("[sim]\nscript = \"loop\"\n", "script"),
            ("[server]\ntoken = \"\"\n", "token"),
            ("[server]\nport = 1\n", "port"),
        ] {
            let e = Config::from_toml(text, Path::new("x.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
    }

    #[test]
    fn link_and_mission_sections_are_checked() {
        let e = Config::from_toml("[link]\nurl = \"udp:1.2.3.4\"\n", Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("[link] url"), "{e}");
        let e = Config::from_toml(
            "[mission.plan.fence]\nmin_alt_m = 50.0\nmax_alt_m = 40.0\n",
            Path::new("x.toml"),
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("min_alt_m"), "{e}");
        let e = Config::from_toml("[mission.transfer]\nretries = 3\n", Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("retries"), "{e}");
        let cfg = Config::from_toml(
            "[link]\nurl = \"serial:/dev/ttyUSB0:57600\"\n[link.signing]\nkey_hex = \"00112233445566778899aabbccddeeff00112233445566778899aabbccddeeff\"\n",
            Path::new("x.toml"),
        )
        .unwrap();
        assert_eq!(cfg.link.url, "serial:/dev/ttyUSB0:57600");
        assert_eq!(cfg.link.signing.map(|s| s.link_id), Some(0));
    }

    #[test]
    fn unknown_key_names_key_and_line() {
        let text = "[camera]\nfx = 400.0\nfocal = 3\n";
        let e = Config::from_toml(text, Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("focal"), "{e}");
        assert!(e.contains("line 3"), "{e}");
    }

    #[test]
    fn wrong_type_names_line() {
        let text = "[camera]\n\nwidth = \"wide\"\n";
        let e = Config::from_toml(text, Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 3") && e.contains("width"), "{e}");
    }

    #[test]
    fn invalid_value_is_refused() {
        let text = "[camera]\nfx = -1.0\n";
        let e = Config::from_toml(text, Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("[camera]") && e.contains("focal"), "{e}");
    }

    #[test]
    fn lockstep_needs_the_mjpeg_video() {
        let text = "[sim]\nlockstep = true\nrtp_out = \"127.0.0.1:5600\"\n";
        let e = Config::from_toml(text, Path::new("x.toml"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("lockstep") && e.contains("rtp_out"), "{e}");
        let cfg = Config::from_toml("[sim]\nlockstep = true\n", Path::new("x.toml")).unwrap();
        assert!(cfg.sim.lockstep);
    }
}
