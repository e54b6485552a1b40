//! The typed tree of `config.toml`.
//!
//! Every section and key is optional in the file: a missing key takes its
//! default (the defaults run the daemon against the bundled simulator). An
//! unknown key is an error that names the key and its line, so a typo never
//! passes silently.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::camera::{Camera, CameraError, Distortion};

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
}

/// How video frames are fetched.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VideoSource {
    /// `multipart/x-mixed-replace` stream.
    Mjpeg,
    /// Poll a JPEG snapshot URL.
    Snapshot,
}

/// `[video]`: the live video source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct VideoConfig {
    /// `mjpeg` or `snapshot`.
    pub source: VideoSource,
    /// The stream or snapshot URL (plain http://).
    pub url: String,
    /// Snapshot polling rate, Hz.
    pub snapshot_hz: f64,
    /// Connect timeout, ms.
    pub connect_timeout_ms: u64,
    /// A connection silent this long is reopened, ms.
    pub read_timeout_ms: u64,
    /// First reconnect delay, ms (doubles per failure).
    pub reconnect_min_ms: u64,
    /// Largest reconnect delay, ms.
    pub reconnect_max_ms: u64,
    /// Largest accepted JPEG, bytes.
    pub max_frame_bytes: usize,
}

impl Default for VideoConfig {
    fn default() -> Self {
        let p = crate::video::mjpeg::Params::default();
        Self {
            source: VideoSource::Mjpeg,
            url: "http://127.0.0.1:8554/video.mjpg".into(),
            snapshot_hz: 5.0,
            connect_timeout_ms: p.connect_timeout_ms,
            read_timeout_ms: p.read_timeout_ms,
            reconnect_min_ms: p.reconnect_min_ms,
            reconnect_max_ms: p.reconnect_max_ms,
            max_frame_bytes: p.max_part_bytes,
        }
    }
}

impl VideoConfig {
    /// The client tunables.
    pub fn params(&self) -> crate::video::mjpeg::Params {
        crate::video::mjpeg::Params {
            connect_timeout_ms: self.connect_timeout_ms,
            read_timeout_ms: self.read_timeout_ms,
            reconnect_min_ms: self.reconnect_min_ms,
            reconnect_max_ms: self.reconnect_max_ms,
            max_part_bytes: self.max_frame_bytes,
            ..Default::default()
        }
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
    /// Status events per second on `/api/v1/events`.
    pub events_hz: f64,
    /// Most map points `/api/v1/map` returns.
    pub map_max_points: usize,
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
        }
    }
}

/// `[slam]`: the daemon's SLAM thread.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SlamConfig {
    /// Run the SLAM on the live video.
    pub enabled: bool,
    /// Map file written on shutdown (relative to `server.data_dir`).
    pub map_file: PathBuf,
    /// At start, go on with the map in `map_file` when there is one (the
    /// SLAM relocalises into it, so shots and the georeference stay in one
    /// frame); false: start a fresh map (the old file is kept under a new
    /// name).
    pub continue_map: bool,
    /// Extra time spent per frame, ms (0: none; to test that a slow SLAM
    /// never stalls the video).
    pub artificial_delay_ms: u64,
}

impl Default for SlamConfig {
    fn default() -> Self {
        Self {
            enabled: true,
            map_file: PathBuf::from("map.spmap"),
            continue_map: true,
            artificial_delay_ms: 0,
        }
    }
}

/// `[sim]`: the bundled simulator, started inside the daemon.
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
    /// Scripted flight: `explore`, `hover` or `none`.
    pub script: String,
    /// Autopilot flavour: `px4` or `ardupilot`.
    pub flavour: String,
    /// Write the simulator's ground truth (camera trajectory, video frame
    /// poses) to this folder (relative to `server.data_dir`); unset: none.
    pub truth_dir: Option<PathBuf>,
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
        }
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
        }
    }
}

impl CameraConfig {
    /// The camera this section describes (reading `calib_file` when set,
    /// relative to `base_dir`).
    pub fn camera(&self, base_dir: &Path) -> Result<Camera, CameraError> {
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
                key: "fx/fy/width/height",
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
        crate::video::mjpeg::HttpUrl::parse(&self.video.url)
            .map_err(|e| invalid("video", "url", e.to_string()))?;
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
        if self.sim.enabled {
            self.sim
                .video_listen
                .parse::<std::net::SocketAddr>()
                .map_err(|e| invalid("sim", "video_listen", e.to_string()))?;
            if !["explore", "hover", "none"].contains(&self.sim.script.as_str()) {
                return Err(invalid(
                    "sim",
                    "script",
                    format!("{:?}: use explore, hover or none", self.sim.script),
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
    }

    #[test]
    fn daemon_sections_refuse_bad_values() {
        for (text, needle) in [
            ("[server]\nbind = \"nowhere\"\n", "bind"),
            ("[video]\nurl = \"rtsp://cam/x\"\n", "url"),
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
}
