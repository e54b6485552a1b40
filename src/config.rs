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
