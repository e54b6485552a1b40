//! The link to the drone: MAVLink transports, the link actor, the telemetry cache.
//!
//! One tokio task (the *link actor*, [`spawn`]) owns the connection. It
//!
//! - connects from a URL ([`transport`]) and reconnects with exponential
//!   backoff when the device vanishes or the socket fails;
//! - sends the GCS `HEARTBEAT` at 1 Hz;
//! - tracks the vehicle (system id, PX4/ArduPilot from its heartbeat, mode,
//!   armed, link lost after a configurable silence) in a watch channel;
//! - asks for telemetry rates with `SET_MESSAGE_INTERVAL` whenever the vehicle
//!   (re)appears;
//! - keeps the latest position, local position, attitude, home, gimbal
//!   attitude and mission progress, each with its receive time, in watch
//!   channels ([`Telemetry`]);
//! - takes [`Command`]s with oneshot replies: mission upload/download/cancel
//!   (the [`crate::mission::upload`] state machines, driven here), and arming,
//!   mode and mission start, which are only ever sent when an operator asks.
//!
//! Shutdown: the actor ends when its `CancellationToken` is cancelled or every
//! [`LinkHandle`] is dropped.

mod actor;
pub mod transport;

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, oneshot, watch};

use crate::mission::{Download, Flavour, MissionError, MissionItem, UploadReport};

pub use actor::spawn;
pub use transport::{LinkUrl, Signing};

/// Errors of the link.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LinkError {
    /// The link URL cannot be parsed.
    #[error("bad link URL `{url}`: {reason}")]
    BadUrl {
        /// The URL.
        url: String,
        /// What is wrong.
        reason: String,
    },
    /// The signing key cannot be decoded.
    #[error("bad signing key: {reason}")]
    BadSigningKey {
        /// What is wrong.
        reason: String,
    },
    /// No vehicle heartbeat has been heard (or the link is lost).
    #[error("no vehicle on the link")]
    NoVehicle,
    /// Another operation of the same kind is running.
    #[error("busy: a {what} is already running")]
    Busy {
        /// What runs.
        what: &'static str,
    },
    /// A mission transfer failed.
    #[error(transparent)]
    Mission(#[from] MissionError),
    /// The vehicle answered a command with something else than ACCEPTED.
    #[error("vehicle rejected command {command}: {result}")]
    CommandRejected {
        /// MAV_CMD number.
        command: u16,
        /// MAV_RESULT name.
        result: String,
    },
    /// The vehicle did not acknowledge a command.
    #[error("no COMMAND_ACK for command {command} after {attempts} attempts")]
    CommandTimeout {
        /// MAV_CMD number.
        command: u16,
        /// Sends.
        attempts: u32,
    },
    /// The requested mode is not known for the vehicle's autopilot.
    #[error("mode {mode:?} is not available for autopilot {autopilot}")]
    UnsupportedMode {
        /// The mode.
        mode: FlightMode,
        /// MAV_AUTOPILOT number.
        autopilot: u8,
    },
    /// The mission read back after an upload is not the one uploaded.
    #[error("the mission read back from the vehicle differs from the one uploaded")]
    ReadBackDiffers,
    /// The link actor has stopped.
    #[error("the link actor has stopped")]
    ActorGone,
    /// Waiting for something timed out.
    #[error("timed out after {seconds:.1} s waiting for {what}")]
    Timeout {
        /// What was awaited.
        what: &'static str,
        /// How long.
        seconds: f64,
    },
}

/// Telemetry rates requested with SET_MESSAGE_INTERVAL, Hz (0: leave as is).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Rates {
    /// GLOBAL_POSITION_INT.
    pub global_position_hz: f32,
    /// LOCAL_POSITION_NED.
    pub local_position_hz: f32,
    /// ATTITUDE.
    pub attitude_hz: f32,
    /// HOME_POSITION.
    pub home_position_hz: f32,
    /// GIMBAL_DEVICE_ATTITUDE_STATUS.
    pub gimbal_hz: f32,
    /// MISSION_CURRENT.
    pub mission_current_hz: f32,
}

impl Default for Rates {
    fn default() -> Self {
        // About 1.2 kB/s of telemetry: a fifth of a 57600 baud radio.
        Self {
            global_position_hz: 5.0,
            local_position_hz: 5.0,
            attitude_hz: 10.0,
            home_position_hz: 0.5,
            gimbal_hz: 5.0,
            mission_current_hz: 1.0,
        }
    }
}

/// The `[link]` section of the configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Where the vehicle is (see [`transport`]).
    pub url: String,
    /// Our MAVLink system id (255: the GCS convention).
    pub system_id: u8,
    /// Our component id (190: MAV_COMP_ID_MISSIONPLANNER).
    pub component_id: u8,
    /// Talk only to this vehicle system id; 0 takes the first autopilot heard.
    pub vehicle_system_id: u8,
    /// Send MAVLink 1 frames (old radios); MAVLink 1 and 2 are always received.
    pub mavlink1: bool,
    /// GCS heartbeat period, ms.
    pub heartbeat_period_ms: u64,
    /// The link counts as lost after this long without a vehicle heartbeat, ms.
    pub link_lost_after_ms: u64,
    /// First reconnect delay, ms (doubles up to the maximum).
    pub reconnect_min_ms: u64,
    /// Longest reconnect delay, ms.
    pub reconnect_max_ms: u64,
    /// COMMAND_LONG retry timeout, ms.
    pub command_timeout_ms: u64,
    /// COMMAND_LONG sends before giving up.
    pub command_attempts: u32,
    /// Telemetry rates to ask for.
    pub rates: Rates,
    /// MAVLink 2 signing (none: unsigned).
    pub signing: Option<Signing>,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            url: "udpin:0.0.0.0:14550".into(),
            system_id: 255,
            component_id: 190,
            vehicle_system_id: 0,
            mavlink1: false,
            heartbeat_period_ms: 1000,
            link_lost_after_ms: 3000,
            reconnect_min_ms: 250,
            reconnect_max_ms: 5000,
            command_timeout_ms: 1000,
            command_attempts: 3,
            rates: Rates::default(),
            signing: None,
        }
    }
}

/// A value with the time it was received.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stamped<T> {
    /// The value.
    pub value: T,
    /// When it arrived.
    pub received: Instant,
}

/// GLOBAL_POSITION_INT in SI units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GlobalPosition {
    /// Autopilot boot time, ms.
    pub time_boot_ms: u32,
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, metres.
    pub alt_amsl_m: f64,
    /// Altitude above home, metres.
    pub rel_alt_m: f64,
    /// Velocity north, east, down, m/s.
    pub vel_ned_m_s: [f32; 3],
    /// Heading, degrees (None when unknown).
    pub heading_deg: Option<f32>,
}

/// LOCAL_POSITION_NED.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LocalPosition {
    /// Autopilot boot time, ms.
    pub time_boot_ms: u32,
    /// Position north, east, down, metres.
    pub pos_ned_m: [f32; 3],
    /// Velocity north, east, down, m/s.
    pub vel_ned_m_s: [f32; 3],
}

/// ATTITUDE (body frame relative to NED).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Attitude {
    /// Autopilot boot time, ms.
    pub time_boot_ms: u32,
    /// Roll, rad.
    pub roll_rad: f32,
    /// Pitch, rad.
    pub pitch_rad: f32,
    /// Yaw, rad.
    pub yaw_rad: f32,
}

/// HOME_POSITION.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HomePosition {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, metres.
    pub alt_amsl_m: f64,
}

/// The gimbal's attitude, degrees.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GimbalAttitude {
    /// Roll, degrees.
    pub roll_deg: f32,
    /// Pitch, degrees (negative: down).
    pub pitch_deg: f32,
    /// Yaw, degrees.
    pub yaw_deg: f32,
    /// Whether yaw is relative to north (true) or to the vehicle's heading.
    pub yaw_absolute: bool,
    /// Autopilot boot time of the sample, ms (when the message carries it).
    pub time_boot_ms: Option<u32>,
}

/// Mission progress from MISSION_CURRENT and MISSION_ITEM_REACHED.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize)]
pub struct MissionProgress {
    /// The item being executed.
    pub current_seq: Option<u16>,
    /// Items in the mission (MISSION_CURRENT.total; None when not sent).
    pub total: Option<u16>,
    /// MISSION_STATE number (0 unknown, 1 none, 2 not started, 3 active, 4 paused, 5 complete).
    pub state: Option<u8>,
    /// The last item reached.
    pub last_reached: Option<u16>,
}

/// What the link knows about the vehicle.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct VehicleState {
    /// The transport is open.
    pub connected: bool,
    /// Transport (re)connections so far.
    pub connections: u32,
    /// The vehicle's system id, once heard.
    pub system_id: Option<u8>,
    /// The autopilot's component id.
    pub component_id: u8,
    /// PX4 or ArduPilot (None for other autopilots).
    pub flavour: Option<Flavour>,
    /// MAV_AUTOPILOT number.
    pub autopilot: u8,
    /// MAV_TYPE number.
    pub mav_type: u8,
    /// HEARTBEAT base_mode bits.
    pub base_mode: u8,
    /// HEARTBEAT custom_mode.
    pub custom_mode: u32,
    /// Human name of the flight mode.
    pub mode: String,
    /// Motors armed.
    pub armed: bool,
    /// No heartbeat for longer than `link_lost_after_ms` (true before the first).
    pub link_lost: bool,
    /// When the last vehicle heartbeat arrived.
    pub last_heartbeat: Option<Instant>,
}

/// Flight modes an operator may ask for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FlightMode {
    /// Fly the uploaded mission (PX4 AUTO.MISSION, ArduPilot AUTO).
    Mission,
    /// Hold position (PX4 AUTO.LOITER, ArduPilot LOITER).
    Hold,
    /// Return to launch.
    Rtl,
}

/// The latest telemetry, one watch channel each.
#[derive(Debug, Clone)]
pub struct Telemetry {
    /// Vehicle tracking.
    pub vehicle: watch::Receiver<VehicleState>,
    /// GLOBAL_POSITION_INT.
    pub global_position: watch::Receiver<Option<Stamped<GlobalPosition>>>,
    /// LOCAL_POSITION_NED.
    pub local_position: watch::Receiver<Option<Stamped<LocalPosition>>>,
    /// ATTITUDE.
    pub attitude: watch::Receiver<Option<Stamped<Attitude>>>,
    /// HOME_POSITION.
    pub home: watch::Receiver<Option<Stamped<HomePosition>>>,
    /// Gimbal attitude (GIMBAL_DEVICE_ATTITUDE_STATUS or MOUNT_ORIENTATION).
    pub gimbal: watch::Receiver<Option<Stamped<GimbalAttitude>>>,
    /// Mission progress.
    pub progress: watch::Receiver<Option<Stamped<MissionProgress>>>,
    /// VIDEO_STREAM_INFORMATION from the vehicle's camera, newest last
    /// (one entry per stream id).
    pub video_streams: watch::Receiver<Vec<VideoStreamInfo>>,
}

/// A video stream a camera component announced (VIDEO_STREAM_INFORMATION).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct VideoStreamInfo {
    /// The component that sent it (100 for a MAVLink camera).
    pub component_id: u8,
    /// Stream id (1-based).
    pub stream_id: u8,
    /// Streams the camera has.
    pub count: u8,
    /// `rtsp`, `rtpudp`, `tcp_mpeg`, `mpeg_ts` or `whep`.
    pub kind: String,
    /// `h264`, `h265` or `unknown`.
    pub encoding: String,
    /// The stream's name.
    pub name: String,
    /// The stream's URI as sent.
    pub uri: String,
    /// Frames per second.
    pub framerate: f32,
    /// Horizontal resolution, pixels.
    pub width: u16,
    /// Vertical resolution, pixels.
    pub height: u16,
    /// Bit rate, bit/s.
    pub bitrate: u32,
}

/// A request to the link actor; each carries its reply channel.
#[derive(Debug)]
pub enum Command {
    /// Upload a mission (items numbered from 0).
    UploadMission {
        /// The items.
        items: Vec<MissionItem>,
        /// The outcome.
        reply: oneshot::Sender<Result<UploadReport, LinkError>>,
    },
    /// Download the vehicle's mission.
    DownloadMission {
        /// The outcome.
        reply: oneshot::Sender<Result<Download, LinkError>>,
    },
    /// Cancel the running transfer; replies whether one was running.
    CancelTransfer {
        /// The outcome.
        reply: oneshot::Sender<Result<bool, LinkError>>,
    },
    /// Arm (true) or disarm (false). Operator action only.
    Arm {
        /// Arm or disarm.
        arm: bool,
        /// The outcome.
        reply: oneshot::Sender<Result<(), LinkError>>,
    },
    /// Change flight mode. Operator action only.
    SetMode {
        /// The mode.
        mode: FlightMode,
        /// The outcome.
        reply: oneshot::Sender<Result<(), LinkError>>,
    },
    /// MAV_CMD_MISSION_START. Operator action only.
    StartMission {
        /// The outcome.
        reply: oneshot::Sender<Result<(), LinkError>>,
    },
    /// MAV_CMD_REQUEST_MESSAGE to one component of the vehicle's system
    /// (sent once; the answer arrives on the telemetry channels). Replies
    /// once sent.
    RequestMessage {
        /// The message id wanted.
        message_id: u32,
        /// The component asked (100: the camera).
        target_component: u8,
        /// The outcome.
        reply: oneshot::Sender<Result<(), LinkError>>,
    },
}

/// The handle other tasks hold: sends commands, reads telemetry. Cheap to clone.
#[derive(Debug, Clone)]
pub struct LinkHandle {
    tx: mpsc::Sender<Command>,
    /// The telemetry watch channels.
    pub telemetry: Telemetry,
}

impl LinkHandle {
    async fn call<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<Result<T, LinkError>>) -> Command,
    ) -> Result<T, LinkError> {
        let (reply, rx) = oneshot::channel();
        self.tx
            .send(make(reply))
            .await
            .map_err(|_| LinkError::ActorGone)?;
        rx.await.map_err(|_| LinkError::ActorGone)?
    }

    /// Uploads a mission and waits for the vehicle's ACK.
    pub async fn upload_mission(&self, items: Vec<MissionItem>) -> Result<UploadReport, LinkError> {
        self.call(|reply| Command::UploadMission { items, reply })
            .await
    }

    /// Uploads `items`, then reads the vehicle's mission back and compares
    /// (without item 0 for ArduPilot, which keeps home there): `Some(true)`
    /// when it holds exactly the items, `None` when the read-back failed
    /// (logged). A read-back that differs is [`LinkError::ReadBackDiffers`].
    pub async fn upload_verified(
        &self,
        items: &[MissionItem],
        flavour: Flavour,
    ) -> Result<(UploadReport, Option<bool>), LinkError> {
        let report = self.upload_mission(items.to_vec()).await?;
        let verified = match self.download_mission().await {
            Ok(d) => Some(crate::mission::upload::same_mission(
                items,
                &d.items,
                flavour == Flavour::ArduPilot,
            )),
            Err(e) => {
                tracing::warn!("mission read-back failed: {e}");
                None
            }
        };
        if verified == Some(false) {
            return Err(LinkError::ReadBackDiffers);
        }
        Ok((report, verified))
    }

    /// Downloads the vehicle's mission.
    pub async fn download_mission(&self) -> Result<Download, LinkError> {
        self.call(|reply| Command::DownloadMission { reply }).await
    }

    /// Cancels the running transfer; true if one was running.
    pub async fn cancel_transfer(&self) -> Result<bool, LinkError> {
        self.call(|reply| Command::CancelTransfer { reply }).await
    }

    /// Arms or disarms (operator action).
    pub async fn arm(&self, arm: bool) -> Result<(), LinkError> {
        self.call(|reply| Command::Arm { arm, reply }).await
    }

    /// Changes flight mode (operator action).
    pub async fn set_mode(&self, mode: FlightMode) -> Result<(), LinkError> {
        self.call(|reply| Command::SetMode { mode, reply }).await
    }

    /// Starts the uploaded mission (operator action).
    pub async fn start_mission(&self) -> Result<(), LinkError> {
        self.call(|reply| Command::StartMission { reply }).await
    }

    /// Asks `target_component` of the vehicle's system for one message
    /// (MAV_CMD_REQUEST_MESSAGE); the answer arrives on the telemetry.
    pub async fn request_message(
        &self,
        message_id: u32,
        target_component: u8,
    ) -> Result<(), LinkError> {
        self.call(|reply| Command::RequestMessage {
            message_id,
            target_component,
            reply,
        })
        .await
    }

    /// Waits until a vehicle heartbeat has been heard and the link is up.
    pub async fn wait_for_vehicle(&self, timeout: Duration) -> Result<VehicleState, LinkError> {
        let mut rx = self.telemetry.vehicle.clone();
        let wait = rx.wait_for(|v| v.system_id.is_some() && !v.link_lost);
        match tokio::time::timeout(timeout, wait).await {
            Ok(Ok(state)) => Ok(state.clone()),
            Ok(Err(_)) => Err(LinkError::ActorGone),
            Err(_) => Err(LinkError::Timeout {
                what: "a vehicle heartbeat",
                seconds: timeout.as_secs_f64(),
            }),
        }
    }
}

/// PX4's custom_mode: main mode in bits 16..24, sub mode in bits 24..32.
pub fn px4_mode_name(custom_mode: u32) -> String {
    let main = (custom_mode >> 16) & 0xff;
    let sub = (custom_mode >> 24) & 0xff;
    let name = match (main, sub) {
        (1, _) => "MANUAL",
        (2, _) => "ALTCTL",
        (3, _) => "POSCTL",
        (4, 1) => "AUTO.READY",
        (4, 2) => "AUTO.TAKEOFF",
        (4, 3) => "AUTO.LOITER",
        (4, 4) => "AUTO.MISSION",
        (4, 5) => "AUTO.RTL",
        (4, 6) => "AUTO.LAND",
        (4, 8) => "AUTO.FOLLOW_TARGET",
        (4, 9) => "AUTO.PRECLAND",
        (4, _) => "AUTO",
        (5, _) => "ACRO",
        (6, _) => "OFFBOARD",
        (7, _) => "STABILIZED",
        _ => return format!("PX4({main}.{sub})"),
    };
    name.to_string()
}

/// ArduCopter's custom_mode numbers.
pub fn ardupilot_mode_name(custom_mode: u32) -> String {
    let name = match custom_mode {
        0 => "STABILIZE",
        1 => "ACRO",
        2 => "ALT_HOLD",
        3 => "AUTO",
        4 => "GUIDED",
        5 => "LOITER",
        6 => "RTL",
        7 => "CIRCLE",
        9 => "LAND",
        16 => "POSHOLD",
        17 => "BRAKE",
        21 => "SMART_RTL",
        _ => return format!("MODE({custom_mode})"),
    };
    name.to_string()
}

/// DO_SET_MODE parameters (base mode, custom main mode, custom sub mode) for a flavour.
pub fn mode_params(flavour: Flavour, mode: FlightMode) -> (f32, f32, f32) {
    const CUSTOM: f32 = 1.0; // MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    match (flavour, mode) {
        (Flavour::Px4, FlightMode::Mission) => (CUSTOM, 4.0, 4.0),
        (Flavour::Px4, FlightMode::Hold) => (CUSTOM, 4.0, 3.0),
        (Flavour::Px4, FlightMode::Rtl) => (CUSTOM, 4.0, 5.0),
        (Flavour::ArduPilot, FlightMode::Mission) => (CUSTOM, 3.0, 0.0),
        (Flavour::ArduPilot, FlightMode::Hold) => (CUSTOM, 5.0, 0.0),
        (Flavour::ArduPilot, FlightMode::Rtl) => (CUSTOM, 6.0, 0.0),
    }
}

/// Quaternion (w, x, y, z) to roll, pitch, yaw (ZYX), degrees.
pub fn quat_to_euler_deg(q: [f32; 4]) -> (f32, f32, f32) {
    let [w, x, y, z] = q.map(f64::from);
    let roll = (2.0 * (w * x + y * z)).atan2(1.0 - 2.0 * (x * x + y * y));
    let pitch = (2.0 * (w * y - z * x)).clamp(-1.0, 1.0).asin();
    let yaw = (2.0 * (w * z + x * y)).atan2(1.0 - 2.0 * (y * y + z * z));
    (
        roll.to_degrees() as f32,
        pitch.to_degrees() as f32,
        yaw.to_degrees() as f32,
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn mode_names() {
        assert_eq!(px4_mode_name((4 << 16) | (4 << 24)), "AUTO.MISSION");
        assert_eq!(px4_mode_name(3 << 16), "POSCTL");
        assert_eq!(px4_mode_name(99 << 16), "PX4(99.0)");
        assert_eq!(ardupilot_mode_name(3), "AUTO");
        assert_eq!(ardupilot_mode_name(5), "LOITER");
        // the mode we set is the mode we then read back
        let (_, main, sub) = mode_params(Flavour::Px4, FlightMode::Mission);
        assert_eq!(
            px4_mode_name(((main as u32) << 16) | ((sub as u32) << 24)),
            "AUTO.MISSION"
        );
        let (_, m, _) = mode_params(Flavour::ArduPilot, FlightMode::Rtl);
        assert_eq!(ardupilot_mode_name(m as u32), "RTL");
    }

    #[test]
    fn quaternion_euler() {
        // pitch -30 deg about y: q = (cos(-15), 0, sin(-15), 0)
        let h = (-15f32).to_radians();
        let (r, p, y) = quat_to_euler_deg([h.cos(), 0.0, h.sin(), 0.0]);
        assert!(
            r.abs() < 1e-4 && (p + 30.0).abs() < 1e-4 && y.abs() < 1e-4,
            "{r} {p} {y}"
        );
        // yaw 90 deg
        let h = 45f32.to_radians();
        let (r, p, y) = quat_to_euler_deg([h.cos(), 0.0, 0.0, h.sin()]);
        assert!(r.abs() < 1e-4 && p.abs() < 1e-4 && (y - 90.0).abs() < 1e-4);
    }

    #[test]
    fn params_round_trip_toml() {
        let text = r#"
            url = "serial:/dev/ttyUSB0:57600"
            vehicle_system_id = 1
            [rates]
            attitude_hz = 4.0
            [signing]
            key_hex = "0000000000000000000000000000000000000000000000000000000000000001"
        "#;
        let p: Params = toml::from_str(text).expect("parses");
        assert_eq!(p.url, "serial:/dev/ttyUSB0:57600");
        assert_eq!(p.rates.attitude_hz, 4.0);
        assert_eq!(p.rates.global_position_hz, 5.0);
        assert_eq!(p.heartbeat_period_ms, 1000);
        assert_eq!(p.signing.as_ref().map(|s| s.link_id), Some(0));
        assert!(
            toml::from_str::<Params>("bogus = 1").is_err(),
            "unknown fields refused"
        );
    }
}
