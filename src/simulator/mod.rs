//! The bundled simulator (`shotpilot-sim`) seen from shotpilot: the one
//! place outside tests where the crate imports it (floor 9, under
//! `daemon`, which runs the simulator in-process, and the command line).
//!
//! * adapters: the simulator's camera as a [`Camera`]
//!   ([`camera_from_sim`]), `[sim]` of `config.toml` as the simulator's
//!   configuration ([`sim_config`]: its GPS bias, H.264 RTP output,
//!   realism and world) and the checks of those keys ([`check`]);
//! * [`drag`]: an operator's random drag of the four anchors and its truth
//!   in the simulated world (the scenario's and the tests' anchors trials);
//! * [`scenario`]: the closed-loop experiment (`shotpilot scenario`):
//!   explore flight → SLAM map and georeference → desired shots from hidden
//!   poses → localise, plan, upload, fly, refine, run synchronously in
//!   simulated time with [`crate::refine`]'s parts.
//!
//! The core modules (camera, config, slam, shot, refine, mission, geo...)
//! never import `shotpilot_sim`; `.ci/import-circles` fails when one does
//! outside its tests.
//!
//! The whole module, the scenario harness with it, is behind the `sim`
//! cargo feature (on by default): a field build
//! (`--no-default-features`) has neither the simulator nor the harness.

pub mod drag;
pub mod scenario;

use std::path::Path;

use shotpilot_sim::app::SimConfig;
use shotpilot_sim::autopilot::{AutopilotParams, Flavour};
use shotpilot_sim::camera::SimCamera;
/// The simulator's lockstep handshake ([`shotpilot_sim::lockstep`]): the
/// daemon's SLAM acknowledges each frame on it.
pub use shotpilot_sim::lockstep::Lockstep;
use shotpilot_sim::rtp::RtpOutParams;
use shotpilot_sim::script::ScriptKind;
use shotpilot_sim::vehicle::{GpsBiasParams, VehicleParams};

use crate::camera::{Camera, CameraError, Distortion};
use crate::config::{Config, ConfigError, SimSection};

/// A `[sim]` key the simulator cannot use.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("[sim] {key} {value:?}: {reason}")]
pub struct SimKeyError {
    /// The key.
    pub key: &'static str,
    /// Its value as written.
    pub value: String,
    /// What is wrong.
    pub reason: String,
}

impl SimKeyError {
    fn new(key: &'static str, value: impl std::fmt::Debug, reason: impl ToString) -> Self {
        Self {
            key,
            value: format!("{value:?}").trim_matches('"').to_owned(),
            reason: reason.to_string(),
        }
    }
}

/// The simulator's camera model as a [`Camera`] (same intrinsics and
/// OpenCV distortion coefficients).
pub fn camera_from_sim(c: &SimCamera) -> Result<Camera, CameraError> {
    Camera::new(
        c.width,
        c.height,
        [c.fx, c.fy, c.cx, c.cy],
        Distortion {
            k1: c.k1,
            k2: c.k2,
            p1: c.p1,
            p2: c.p2,
            k3: c.k3,
        },
    )
}

/// The H.264 RTP output `[sim] rtp_out` and `rtp_bitrate_kbps` describe
/// (None: `rtp_out` unset).
pub fn rtp_out(s: &SimSection) -> Result<Option<RtpOutParams>, SimKeyError> {
    let Some(dest) = &s.rtp_out else {
        return Ok(None);
    };
    let bad = |reason: String| SimKeyError::new("rtp_out", dest, reason);
    let addr = std::net::ToSocketAddrs::to_socket_addrs(dest.as_str())
        .map_err(|e| bad(format!("expected HOST:PORT ({e})")))?
        .next()
        .ok_or_else(|| bad("no address".into()))?;
    let p = RtpOutParams {
        dest: addr,
        bitrate_bps: s.rtp_bitrate_kbps.saturating_mul(1000),
        ..Default::default()
    };
    p.check().map_err(|(field, reason)| {
        if field == "bitrate_bps" {
            SimKeyError::new("rtp_bitrate_kbps", s.rtp_bitrate_kbps, reason)
        } else {
            bad(format!("{field}: {reason}"))
        }
    })?;
    Ok(Some(p))
}

/// The vehicle's GPS bias model `[sim] gps_*` describe (its walk seeded
/// from `gps_seed`, else `seed`, mixed as the scenario mixes its own).
pub fn gps_bias(s: &SimSection) -> GpsBiasParams {
    GpsBiasParams {
        sigma_xy_m: s.gps_sigma_xy_m,
        sigma_z_m: s.gps_sigma_z_m,
        tau_s: s.gps_tau_s,
        seed: s.gps_seed.unwrap_or(s.seed) ^ 0x00b1_a5ed,
    }
}

/// The checks of `[sim]` that need the simulator (realism, world, RTP
/// output, GPS bias), when the simulator is enabled; the plain ranges are
/// [`Config::validate`]'s. `path` names the file in the error.
pub fn check(cfg: &Config, path: &Path) -> Result<(), ConfigError> {
    if !cfg.sim.enabled {
        return Ok(());
    }
    let invalid = |key: &'static str, reason: String| ConfigError::Invalid {
        path: path.to_owned(),
        section: "sim",
        key,
        reason,
    };
    let s = &cfg.sim;
    if let Err(e) = s.realism.parse::<shotpilot_sim::realism::Realism>() {
        return Err(invalid("realism", e.to_string()));
    }
    if let Err(e) = s.world.parse::<shotpilot_sim::world::WorldKind>() {
        return Err(invalid("world", e.to_string()));
    }
    if let Err(e) = rtp_out(s) {
        return Err(invalid(e.key, format!("{:?}: {}", e.value, e.reason)));
    }
    if let Err((field, reason)) = gps_bias(s).check() {
        return Err(invalid(
            match field {
                "sigma_xy_m" => "gps_sigma_xy_m",
                "sigma_z_m" => "gps_sigma_z_m",
                _ => "gps_tau_s",
            },
            reason.into(),
        ));
    }
    if s.gps_sigma_xy_m > 50.0 || s.gps_sigma_z_m > 50.0 {
        return Err(invalid(
            "gps_sigma_xy_m/gps_sigma_z_m",
            "at most 50 m".into(),
        ));
    }
    Ok(())
}

/// The in-process simulator's configuration from `[sim]`; its captures
/// and ground truth go under `data_dir`.
pub fn sim_config(cfg: &Config, data_dir: &Path) -> Result<SimConfig, SimKeyError> {
    let s = &cfg.sim;
    let video_listen = s
        .video_listen
        .parse()
        .map_err(|e| SimKeyError::new("video_listen", &s.video_listen, e))?;
    let mavlink = s
        .mavlink
        .parse()
        .map_err(|e| SimKeyError::new("mavlink", &s.mavlink, e))?;
    let script = match s.script.as_str() {
        "explore" => Some(ScriptKind::Explore),
        "hover" => Some(ScriptKind::Hover),
        "patrol" => Some(ScriptKind::Patrol),
        _ => None,
    };
    let rtp_out = rtp_out(s)?;
    let flavour = if s.flavour == "ardupilot" {
        Flavour::ArduPilot
    } else {
        Flavour::Px4
    };
    let defaults = SimConfig::default();
    let sc =
        SimConfig {
            video_listen: Some(video_listen),
            mavlink,
            video_fps: s.video_fps,
            seed: s.seed,
            script,
            autopilot: AutopilotParams {
                flavour,
                vehicle: VehicleParams {
                    gps_bias: gps_bias(s),
                    ..defaults.autopilot.vehicle
                },
                video_stream_uri: Some(s.video_stream_uri.clone().unwrap_or_else(
                    || match &rtp_out {
                        Some(r) => r.uri(),
                        None => format!("http://{video_listen}/video.mjpg"),
                    },
                )),
                ..defaults.autopilot.clone()
            },
            capture_dir: data_dir.join("captures"),
            truth_dir: s.truth_dir.as_ref().map(|d| data_dir.join(d)),
            rtp_out,
            world: s
                .world
                .parse()
                .map_err(|e| SimKeyError::new("world", &s.world, e))?,
            ..defaults
        }
        .with_realism(
            s.realism
                .parse()
                .map_err(|e| SimKeyError::new("realism", &s.realism, e))?,
        );
    Ok(sc)
}

/// Runs the simulator `cfg` describes until `cancel` fires (the daemon
/// spawns it first, so the video and the link find it), on sockets the
/// caller may have bound already: the video server's listener and the
/// MAVLink endpoint's UDP socket (each None: bound from the configuration).
pub async fn run_on(
    sc: SimConfig,
    cancel: tokio_util::sync::CancellationToken,
    video: Option<std::net::TcpListener>,
    mavlink: Option<std::net::UdpSocket>,
) -> Result<shotpilot_sim::app::RunSummary, shotpilot_sim::app::SimError> {
    let sockets = shotpilot_sim::app::Sockets { video, mavlink };
    shotpilot_sim::app::run_on(sc, cancel, sockets).await
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parsed(text: &str) -> Result<Config, ConfigError> {
        let cfg = Config::from_toml(text, Path::new("x.toml"))?;
        check(&cfg, Path::new("x.toml"))?;
        Ok(cfg)
    }

    #[test]
    fn shipped_config_has_no_gps_bias() {
        let cfg = parsed(include_str!("../../config.toml")).unwrap();
        assert!(!gps_bias(&cfg.sim).enabled());
        assert!(rtp_out(&cfg.sim).unwrap().is_none());
    }

    #[test]
    fn sim_keys_are_checked() {
        for (text, needle) in [
            ("[sim]\ngps_sigma_xy_m = -1.0\n", "[sim] gps_sigma_xy_m"),
            ("[sim]\ngps_sigma_z_m = nan\n", "[sim] gps_sigma_z_m"),
            ("[sim]\ngps_tau_s = -5.0\n", "[sim] gps_tau_s"),
            ("[sim]\ngps_sigma_xy_m = 80.0\n", "gps_sigma_xy_m"),
            ("[sim]\nrtp_out = \"nowhere\"\n", "[sim] rtp_out"),
            ("[sim]\nrtp_out = \"127.0.0.1:0\"\n", "[sim] rtp_out"),
            (
                "[sim]\nrtp_out = \"127.0.0.1:5600\"\nrtp_bitrate_kbps = 1\n",
                "rtp_bitrate_kbps",
            ),
            ("[sim]\nrealism = \"sunny\"\n", "[sim] realism"),
            ("[sim]\nrealism = \"field-fog\"\n", "[sim] realism"),
            ("[sim]\nworld = \"moon\"\n", "[sim] world"),
        ] {
            let e = parsed(text).unwrap_err().to_string();
            assert!(e.contains(needle), "{text}: {e}");
        }
        // A disabled simulator's keys are not its concern.
        assert!(parsed("[sim]\nenabled = false\nrealism = \"sunny\"\n").is_ok());
        let cfg = parsed(
            "[sim]\nseed = 7\ngps_sigma_xy_m = 1.5\ngps_sigma_z_m = 0.5\ngps_tau_s = 60.0\n",
        )
        .unwrap();
        let b = gps_bias(&cfg.sim);
        assert!(b.enabled());
        assert_eq!((b.sigma_xy_m, b.sigma_z_m, b.tau_s), (1.5, 0.5, 60.0));
        assert_eq!(b.seed, 7 ^ 0x00b1_a5ed);
    }

    #[test]
    fn sim_config_carries_the_keys() {
        let cfg = parsed(
            "[sim]\nseed = 3\nflavour = \"ardupilot\"\nrtp_out = \"127.0.0.1:5600\"\nworld = \"grass\"\n",
        )
        .unwrap();
        let sc = sim_config(&cfg, Path::new("/data")).unwrap();
        assert_eq!(sc.seed, 3);
        assert_eq!(sc.autopilot.flavour, Flavour::ArduPilot);
        assert_eq!(sc.capture_dir, Path::new("/data/captures"));
        let rtp = sc.rtp_out.expect("rtp out");
        assert_eq!(rtp.dest.port(), 5600);
        assert_eq!(sc.autopilot.video_stream_uri, Some(rtp.uri()));
        let mut bad = cfg.clone();
        bad.sim.mavlink = "carrier-pigeon".into();
        let e = sim_config(&bad, Path::new("/data")).unwrap_err();
        assert_eq!(e.key, "mavlink");
    }

    #[test]
    fn the_sim_camera_is_the_same_camera() {
        let s = SimCamera::default();
        let c = camera_from_sim(&s).unwrap();
        assert_eq!((c.width, c.height), (s.width, s.height));
        assert_eq!([c.fx, c.fy, c.cx, c.cy], [s.fx, s.fy, s.cx, s.cy]);
        assert_eq!(c.distortion.k1, s.k1);
    }
}
