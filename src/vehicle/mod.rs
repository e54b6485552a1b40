//! The link to the drone: MAVLink transports, the link actor, the telemetry cache.
//!
//! One tokio task (the *link actor*, [`spawn`]) owns the connection. It
//!
//! - connects from a URL ([`transport`]) and reconnects with exponential
//!   backoff when the device vanishes or the socket fails; a `udpin:` socket
//!   is bound once and kept (port 0: [`LinkHandle::bound_addr`] says which
//!   port), or handed in already bound ([`spawn_with_socket`]);
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
//!   mode and mission start, which are only ever sent when an operator asks;
//! - keeps one command waiting for its COMMAND_ACK at a time, and beside it
//!   the operator's stop ([`LinkHandle::hold`]), which is sent at once
//!   whatever else is in flight (a mode change in flight gives way to it);
//! - follows MAVLink's gimbal protocol v2 for every caller of the handle:
//!   before a mission that points the gimbal starts
//!   ([`LinkHandle::start_mission`]) and before a direct gimbal command
//!   ([`LinkHandle::point_gimbal`]) it reads `GIMBAL_MANAGER_STATUS`
//!   (asking for it with `MAV_CMD_REQUEST_MESSAGE` when none is fresh),
//!   notes who is in primary control, and takes control with
//!   `MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE` (our sysid/compid as primary, the
//!   manager's gimbal device id); it gives control back (param1/param2 -3,
//!   "remove control if in control") when that mission completes, when the
//!   operator switches to another mode, or on [`LinkHandle::release_gimbal`].
//!   A refusal or silence is a warning in [`GimbalControl`] and the log,
//!   never a failed mission start: PX4 missions take control themselves
//!   (their first item, see [`crate::mission::plan`]) and ArduPilot runs
//!   mission gimbal items whoever is in control.
//!
//! Shutdown: the actor ends when its `CancellationToken` is cancelled or every
//! [`LinkHandle`] is dropped.

mod actor;
pub mod router;
pub mod transport;

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use tokio::sync::{mpsc, oneshot, watch};
use tracing::{info, warn};

use crate::mission::{Download, Flavour, MissionError, MissionItem, UploadReport};

pub use actor::{spawn, spawn_with_socket};
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
    /// A command in flight gave way to the operator's stop (a DO_SET_MODE
    /// whose ACK the stop's could not be told apart from).
    #[error("command {command} was superseded by a stop")]
    Superseded {
        /// MAV_CMD number.
        command: u16,
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
    /// Our component id (191 by default: not 190, MAV_COMP_ID_MISSIONPLANNER,
    /// which QGroundControl and Mission Planner use, so that a ground station
    /// sharing the link through [`Params::forward`] and shotpilot are told
    /// apart by the vehicle's mission and command protocols).
    pub component_id: u8,
    /// Forward endpoints for other ground stations (see [`router`]), in
    /// MAVProxy's and mavlink-router's URL syntax: `udpout:HOST:PORT`,
    /// `udpin:ADDR:PORT`, `tcpin:ADDR:PORT`, `tcpout:HOST:PORT`.
    pub forward: Vec<String>,
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
            component_id: 191,
            forward: Vec::new(),
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

/// GPS_RAW_INT: the receiver's fix and its reported accuracy.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GpsRaw {
    /// Timestamp as sent (UNIX or since boot, the autopilot's choice), µs.
    pub time_usec: u64,
    /// MAVLink `GPS_FIX_TYPE` (0 or 1: no fix, 2: 2D, 3: 3D, 4 and up:
    /// DGPS, RTK, ...).
    pub fix_type: u8,
    /// Satellites visible (None when unknown).
    pub satellites: Option<u8>,
    /// Reported 1-sigma horizontal position accuracy, m (None when the
    /// receiver does not report it: 0 in the message).
    pub h_acc_m: Option<f64>,
    /// Reported 1-sigma vertical position accuracy, m (None when not
    /// reported).
    pub v_acc_m: Option<f64>,
}

impl GpsRaw {
    /// From the message (an accuracy of 0 or `u32::MAX` is not reported:
    /// an older receiver or message version).
    pub fn from_message(d: &mavlink::dialects::common::GPS_RAW_INT_DATA) -> Self {
        let acc = |mm: u32| (mm != 0 && mm != u32::MAX).then(|| f64::from(mm) / 1e3);
        GpsRaw {
            time_usec: d.time_usec,
            fix_type: d.fix_type as u8,
            satellites: (d.satellites_visible != u8::MAX).then_some(d.satellites_visible),
            h_acc_m: acc(d.h_acc),
            v_acc_m: acc(d.v_acc),
        }
    }

    /// A 3D fix or better.
    pub fn has_3d_fix(&self) -> bool {
        self.fix_type >= 3
    }

    /// The reported accuracy of a 3D fix, metres: horizontal, and vertical
    /// when reported; None without a 3D fix or a horizontal accuracy.
    pub fn fix_accuracy(&self) -> Option<(f64, Option<f64>)> {
        self.has_3d_fix()
            .then_some(self.h_acc_m)
            .flatten()
            .map(|h| (h, self.v_acc_m))
    }
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

/// A MAVLink camera component as its CAMERA_INFORMATION describes it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct CameraInfo {
    /// Its component id (100 for the first camera).
    pub component_id: u8,
    /// Vendor name.
    pub vendor: String,
    /// Model name.
    pub model: String,
    /// Focal length, mm.
    pub focal_length_mm: f32,
    /// Sensor size (horizontal, vertical), mm.
    pub sensor_size_mm: [f32; 2],
    /// Image resolution (horizontal, vertical), pixels.
    pub resolution: [u16; 2],
    /// It takes still images (CAMERA_CAP_FLAGS_CAPTURE_IMAGE).
    pub captures_images: bool,
}

/// A picture the vehicle's camera took (CAMERA_IMAGE_CAPTURED).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ImageCaptured {
    /// The component that reported it (100: a MAVLink camera; 1: the
    /// autopilot's camera trigger).
    pub component_id: u8,
    /// Image index since the camera's boot.
    pub index: i32,
    /// Capture time, UTC microseconds (0: unknown).
    pub time_utc_us: u64,
    /// Where it was taken: latitude, longitude (deg), altitude AMSL (m).
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude AMSL, m.
    pub alt_amsl_m: f64,
    /// Altitude above home, m.
    pub relative_alt_m: f64,
    /// The camera's attitude quaternion (w, x, y, z), NED frame.
    pub q: [f32; 4],
    /// The picture was stored.
    pub ok: bool,
    /// Where the camera stored it, as it says.
    pub file_url: String,
}

/// How a picture was asked for ([`LinkHandle::capture_image`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhotoReport {
    /// `camera_protocol` (MAV_CMD_IMAGE_START_CAPTURE to the camera
    /// component) or `digicam_control` (MAV_CMD_DO_DIGICAM_CONTROL to the
    /// autopilot, where no MAVLink camera answered).
    pub method: &'static str,
    /// The component asked.
    pub component_id: u8,
    /// Its CAMERA_IMAGE_CAPTURED, when one came within the wait.
    pub captured: Option<ImageCaptured>,
}

/// GIMBAL_MANAGER_STATUS: who controls the gimbal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct GimbalManagerStatus {
    /// The component that runs the gimbal manager (the autopilot, usually).
    pub manager_component: u8,
    /// The gimbal device this manager is responsible for.
    pub gimbal_device_id: u8,
    /// (system, component) in primary control; (0, 0) nobody.
    pub primary: (u8, u8),
    /// (system, component) in secondary control; (0, 0) nobody.
    pub secondary: (u8, u8),
    /// GIMBAL_MANAGER_FLAGS bits.
    pub flags: u32,
}

/// What the link did about gimbal control, for the status and the log.
#[derive(Debug, Clone, PartialEq, Eq, Default, Serialize)]
pub struct GimbalControl {
    /// Our DO_GIMBAL_MANAGER_CONFIGURE was accepted and not yet released.
    pub held: bool,
    /// We took control for a mission (released when it completes).
    pub for_mission: bool,
    /// The running mission was seen active since we took control.
    pub mission_seen_active: bool,
    /// The gimbal device id we configured (0: all).
    pub device_id: u8,
    /// The primary controller before we took control ((0, 0) nobody; None
    /// when no GIMBAL_MANAGER_STATUS was heard).
    pub previous: Option<(u8, u8)>,
    /// The last uploaded mission points the gimbal with DO_GIMBAL_MANAGER_PITCHYAW.
    pub mission_points_gimbal: bool,
    /// The last uploaded mission makes the autopilot take gimbal control
    /// itself (PX4's configure item): control it holds is the mission's and
    /// is never taken back for that mission.
    pub mission_takes_control: bool,
    /// What happened last, in words.
    pub last_event: Option<String>,
    /// The last refusal or missing answer, in words (cleared on success).
    pub warning: Option<String>,
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

/// The vehicle's acknowledgement of a stop ([`LinkHandle::hold`]).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct HoldAck {
    /// The command sent.
    pub command: &'static str,
    /// The mode asked for, as the autopilot names it (`AUTO.LOITER`, `LOITER`).
    pub mode: String,
    /// The COMMAND_ACK's result, as the vehicle sent it.
    pub result: String,
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
    /// GPS_RAW_INT.
    pub gps_raw: watch::Receiver<Option<Stamped<GpsRaw>>>,
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
    /// GIMBAL_MANAGER_STATUS from the vehicle's gimbal manager.
    pub gimbal_manager: watch::Receiver<Option<Stamped<GimbalManagerStatus>>>,
    /// Gimbal control as the link handled it.
    pub gimbal_control: watch::Receiver<GimbalControl>,
    /// MAVLink cameras of the vehicle (from CAMERA_INFORMATION, asked for
    /// when a camera's heartbeat is first heard).
    pub cameras: watch::Receiver<Vec<CameraInfo>>,
    /// The last pictures the vehicle's cameras reported (newest last, at
    /// most [`CAPTURES_KEPT`]).
    pub captures: watch::Receiver<Vec<ImageCaptured>>,
    /// Missions other ground stations stored on or cleared from the vehicle
    /// through the forward endpoints (a count; see [`router`]).
    pub mission_changes: watch::Receiver<u64>,
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
    /// The operator's stop: DO_SET_MODE to the hold mode, sent at once even
    /// while another command waits for its ACK (a DO_SET_MODE in flight is
    /// superseded). Replies with the vehicle's COMMAND_ACK.
    Hold {
        /// The outcome.
        reply: oneshot::Sender<Result<HoldAck, LinkError>>,
    },
    /// MAV_CMD_MISSION_START. Operator action only.
    StartMission {
        /// The outcome.
        reply: oneshot::Sender<Result<(), LinkError>>,
    },
    /// A COMMAND_LONG with retries until COMMAND_ACK (gimbal commands).
    Long {
        /// The command.
        command: mavlink::dialects::common::MavCmd,
        /// param1..param7.
        params: [f32; 7],
        /// The component addressed (None: the autopilot).
        target_component: Option<u8>,
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
    gimbal: std::sync::Arc<watch::Sender<GimbalControl>>,
    own: (u8, u8),
    command_timeout: Duration,
    /// The `udpin:` socket's address once bound.
    bound: watch::Receiver<Option<std::net::SocketAddr>>,
    router: std::sync::Arc<router::Router>,
}

/// CAMERA_IMAGE_CAPTURED messages kept in [`Telemetry::captures`].
pub const CAPTURES_KEPT: usize = 32;

/// MAVLink message id of GIMBAL_MANAGER_STATUS.
const GIMBAL_MANAGER_STATUS_ID: u32 = 281;
/// A GIMBAL_MANAGER_STATUS younger than this is read as is; older, it is asked for.
const GIMBAL_STATUS_FRESH: Duration = Duration::from_secs(3);
/// GIMBAL_MANAGER_FLAGS_ROLL_LOCK | PITCH_LOCK | YAW_IN_VEHICLE_FRAME.
const GIMBAL_PITCHYAW_FLAGS: f32 = (4 | 8 | 32) as f32;

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
        let points = crate::mission::plan::points_gimbal_v2(&items);
        let takes = crate::mission::plan::takes_gimbal_control(&items);
        let report = self
            .call(|reply| Command::UploadMission { items, reply })
            .await?;
        self.gimbal.send_modify(|g| {
            g.mission_points_gimbal = points;
            g.mission_takes_control = takes;
        });
        Ok(report)
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

    /// Changes flight mode (operator action). Switching to the mission
    /// mode starts the mission on an armed vehicle, so gimbal control is
    /// taken first as in [`LinkHandle::start_mission`]; leaving the mission
    /// for another mode gives back gimbal control taken for it.
    pub async fn set_mode(&self, mode: FlightMode) -> Result<(), LinkError> {
        if mode == FlightMode::Mission {
            self.acquire_for_mission().await;
        }
        self.call(|reply| Command::SetMode { mode, reply }).await?;
        let release =
            mode != FlightMode::Mission && self.telemetry.gimbal_control.borrow().for_mission;
        if release && let Err(e) = self.release_gimbal().await {
            warn!(error = %e, "gimbal release after the mode change failed");
        }
        Ok(())
    }

    /// Stops the vehicle where it is (operator action): `MAV_CMD_DO_SET_MODE`
    /// to hold (PX4 AUTO.LOITER, ArduPilot LOITER), which pauses the
    /// mission. Replies once the vehicle's COMMAND_ACK came, with that ACK:
    /// ACCEPTED is `Ok`; any other result is [`LinkError::CommandRejected`],
    /// no ACK after the link's retries [`LinkError::CommandTimeout`]. A stop
    /// is never held up by another command in flight (a gimbal command,
    /// say): the actor sends it at once beside it. Gimbal control taken for
    /// a mission is given back after, as on any mode change.
    pub async fn hold(&self) -> Result<HoldAck, LinkError> {
        let ack = self.call(|reply| Command::Hold { reply }).await?;
        if self.telemetry.gimbal_control.borrow().for_mission
            && let Err(e) = self.release_gimbal().await
        {
            warn!(error = %e, "gimbal release after the stop failed");
        }
        Ok(ack)
    }

    /// Starts the uploaded mission (operator action). When the mission
    /// points the gimbal with the gimbal manager, takes gimbal control first
    /// ([`LinkHandle::acquire_gimbal`]); a refusal is a warning in
    /// [`GimbalControl`], not a failed start.
    pub async fn start_mission(&self) -> Result<(), LinkError> {
        self.acquire_for_mission().await;
        self.call(|reply| Command::StartMission { reply }).await
    }

    /// Takes gimbal control for the uploaded mission when it points the
    /// gimbal; a failure is logged and kept in [`GimbalControl::warning`].
    ///
    /// Not when the autopilot already holds control and the mission is one
    /// that takes it itself: on PX4, switching an armed vehicle to the
    /// mission mode starts the mission, whose first item makes the
    /// autopilot the primary controller; taking control back then (the
    /// operator's `start` after the mode change) would get the mission's
    /// own PITCHYAW denied.
    async fn acquire_for_mission(&self) {
        {
            let g = self.telemetry.gimbal_control.borrow();
            if !g.mission_points_gimbal || (g.held && g.for_mission) {
                return;
            }
            let takes_itself = g.mission_takes_control;
            drop(g);
            let vehicle = self.telemetry.vehicle.borrow().clone();
            let primary = self
                .telemetry
                .gimbal_manager
                .borrow()
                .map(|s| s.value.primary);
            if takes_itself
                && vehicle
                    .system_id
                    .is_some_and(|s| primary == Some((s, vehicle.component_id)))
            {
                info!("gimbal: the running mission holds control itself; not taking it back");
                self.note(
                    "the mission's own configure item holds gimbal control".into(),
                    None,
                );
                return;
            }
        }
        match self.acquire_gimbal().await {
            Ok(_) => self.gimbal.send_modify(|g| {
                g.for_mission = true;
                g.mission_seen_active = false;
            }),
            Err(e) => warn!(error = %e, "gimbal control not taken; starting the mission anyway"),
        }
    }

    fn note(&self, event: String, warning: Option<String>) {
        self.gimbal.send_modify(|g| {
            g.last_event = Some(event);
            g.warning = warning;
        });
    }

    /// Sends one COMMAND_LONG with the link's retries and waits for its ACK.
    pub async fn command_long(
        &self,
        command: mavlink::dialects::common::MavCmd,
        params: [f32; 7],
        target_component: Option<u8>,
    ) -> Result<(), LinkError> {
        self.call(|reply| Command::Long {
            command,
            params,
            target_component,
            reply,
        })
        .await
    }

    /// Takes one picture: with MAV_CMD_IMAGE_START_CAPTURE (one image) to
    /// the first MAVLink camera that said it captures images, else with
    /// MAV_CMD_DO_DIGICAM_CONTROL (shoot) to the autopilot; then waits up
    /// to `wait` for the CAMERA_IMAGE_CAPTURED that reports it (a camera
    /// trigger wired to the autopilot may never send one: `captured` is
    /// then None). A refused or unacknowledged command is an error.
    pub async fn capture_image(&self, wait: Duration) -> Result<PhotoReport, LinkError> {
        use mavlink::dialects::common::MavCmd;
        let camera = self
            .telemetry
            .cameras
            .borrow()
            .iter()
            .find(|c| c.captures_images)
            .map(|c| c.component_id);
        let mut captures = self.telemetry.captures.clone();
        let seen: Vec<(u8, i32)> = captures
            .borrow()
            .iter()
            .map(|c| (c.component_id, c.index))
            .collect();
        let (method, component_id) = match camera {
            Some(c) => {
                // param1 camera id 0 (all), param2 interval 0, param3 one
                // image, param4 sequence 0
                self.command_long(
                    MavCmd::MAV_CMD_IMAGE_START_CAPTURE,
                    [0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
                    Some(c),
                )
                .await?;
                ("camera_protocol", c)
            }
            None => {
                // param5 1: shoot
                self.command_long(
                    MavCmd::MAV_CMD_DO_DIGICAM_CONTROL,
                    [0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0],
                    None,
                )
                .await?;
                let autopilot = self.telemetry.vehicle.borrow().component_id;
                ("digicam_control", autopilot)
            }
        };
        info!(method, component = component_id, "picture asked for");
        let fresh = |v: &Vec<ImageCaptured>| {
            v.iter()
                .rev()
                .find(|c| {
                    c.component_id == component_id && !seen.contains(&(c.component_id, c.index))
                })
                .cloned()
        };
        let captured =
            match tokio::time::timeout(wait, captures.wait_for(|v| fresh(v).is_some())).await {
                Ok(Ok(v)) => fresh(&v),
                _ => None,
            };
        match &captured {
            Some(c) => info!(index = c.index, ok = c.ok, url = %c.file_url, "picture reported"),
            None => warn!(
                method,
                wait_s = wait.as_secs_f64(),
                "no CAMERA_IMAGE_CAPTURED for the picture"
            ),
        }
        Ok(PhotoReport {
            method,
            component_id,
            captured,
        })
    }

    /// The vehicle's GIMBAL_MANAGER_STATUS: the last one when younger than
    /// 3 s, else asked for with MAV_CMD_REQUEST_MESSAGE (three tries, one
    /// command timeout each).
    pub async fn gimbal_manager_status(&self) -> Result<GimbalManagerStatus, LinkError> {
        let mut rx = self.telemetry.gimbal_manager.clone();
        let now = tokio::time::Instant::now().into_std();
        if let Some(s) = *rx.borrow_and_update()
            && now.saturating_duration_since(s.received) < GIMBAL_STATUS_FRESH
        {
            return Ok(s.value);
        }
        let component = self.telemetry.vehicle.borrow().component_id;
        for _ in 0..3 {
            self.request_message(GIMBAL_MANAGER_STATUS_ID, component)
                .await?;
            match tokio::time::timeout(self.command_timeout, rx.changed()).await {
                Ok(Ok(())) => {
                    if let Some(s) = *rx.borrow_and_update() {
                        return Ok(s.value);
                    }
                }
                Ok(Err(_)) => return Err(LinkError::ActorGone),
                Err(_) => {}
            }
        }
        Err(LinkError::Timeout {
            what: "GIMBAL_MANAGER_STATUS",
            seconds: 3.0 * self.command_timeout.as_secs_f64(),
        })
    }

    /// Takes primary gimbal control (gimbal protocol v2): reads
    /// GIMBAL_MANAGER_STATUS, notes (and logs) who holds control, and sends
    /// MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE with our sysid/compid as primary
    /// for the manager's gimbal device. Without a status (an old autopilot)
    /// it still tries, for all devices. Does nothing when we already hold
    /// control. Errors are also recorded in [`GimbalControl::warning`].
    pub async fn acquire_gimbal(&self) -> Result<GimbalControl, LinkError> {
        let current = self.telemetry.gimbal_control.borrow().clone();
        if current.held {
            return Ok(current);
        }
        let status = match self.gimbal_manager_status().await {
            Ok(s) => Some(s),
            Err(LinkError::Timeout { .. }) => {
                warn!("no GIMBAL_MANAGER_STATUS from the vehicle; configuring all gimbals");
                None
            }
            Err(e) => return Err(e),
        };
        let (device, target, previous) = match status {
            Some(s) => (
                s.gimbal_device_id,
                Some(s.manager_component),
                Some(s.primary),
            ),
            None => (0, None, None),
        };
        let vehicle = self.telemetry.vehicle.borrow().clone();
        match previous {
            Some(p) if p == self.own => info!("gimbal: we already hold primary control"),
            Some((0, 0)) | None => info!(device, "gimbal: taking primary control"),
            Some((s, c)) if Some(s) == vehicle.system_id && c == vehicle.component_id => {
                info!(device, "gimbal: taking primary control from the autopilot")
            }
            Some((s, c)) => warn!(
                device,
                "gimbal: taking primary control from {s}/{c} (another controller)"
            ),
        }
        let params = [
            f32::from(self.own.0),
            f32::from(self.own.1),
            crate::mission::plan::GIMBAL_CONTROL_UNCHANGED,
            crate::mission::plan::GIMBAL_CONTROL_UNCHANGED,
            0.0,
            0.0,
            f32::from(device),
        ];
        use mavlink::dialects::common::MavCmd;
        match self
            .command_long(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, params, target)
            .await
        {
            Ok(()) => {
                let from = previous.map_or("unknown".to_string(), |(s, c)| format!("{s}/{c}"));
                let event = format!("took gimbal control (device {device}) from {from}");
                info!("{event}");
                self.gimbal.send_modify(|g| {
                    g.held = true;
                    g.device_id = device;
                    g.previous = previous;
                    g.last_event = Some(event);
                    g.warning = None;
                });
                Ok(self.telemetry.gimbal_control.borrow().clone())
            }
            Err(e) => {
                let w = format!("gimbal control not taken: {e}");
                warn!("{w}");
                self.note("DO_GIMBAL_MANAGER_CONFIGURE failed".into(), Some(w));
                Err(e)
            }
        }
    }

    /// Gives gimbal control back (DO_GIMBAL_MANAGER_CONFIGURE with -3/-3,
    /// "remove control if in control", so a controller that took over
    /// meanwhile keeps it). Returns false when we did not hold control.
    pub async fn release_gimbal(&self) -> Result<bool, LinkError> {
        let current = self.telemetry.gimbal_control.borrow().clone();
        if !current.held {
            return Ok(false);
        }
        let target = self
            .telemetry
            .gimbal_manager
            .borrow()
            .map(|s| s.value.manager_component);
        let params = release_params(current.device_id);
        use mavlink::dialects::common::MavCmd;
        let r = self
            .command_long(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE, params, target)
            .await;
        // Whatever the answer, we no longer count on holding control.
        self.gimbal.send_modify(|g| {
            g.held = false;
            g.for_mission = false;
        });
        match r {
            Ok(()) => {
                info!("released gimbal control");
                self.note("released gimbal control".into(), None);
                Ok(true)
            }
            Err(e) => {
                let w = format!("gimbal release not acknowledged: {e}");
                warn!("{w}");
                self.note("release sent".into(), Some(w));
                Err(e)
            }
        }
    }

    /// Points the gimbal now (DO_GIMBAL_MANAGER_PITCHYAW; pitch positive
    /// up, yaw relative to the vehicle, degrees), taking control first.
    pub async fn point_gimbal(&self, pitch_deg: f32, yaw_deg: f32) -> Result<(), LinkError> {
        let g = self.acquire_gimbal().await?;
        let target = self
            .telemetry
            .gimbal_manager
            .borrow()
            .map(|s| s.value.manager_component);
        use mavlink::dialects::common::MavCmd;
        self.command_long(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            [
                pitch_deg,
                yaw_deg,
                f32::NAN,
                f32::NAN,
                GIMBAL_PITCHYAW_FLAGS,
                0.0,
                f32::from(g.device_id),
            ],
            target,
        )
        .await
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

    /// The local address of a `udpin:` link's socket (the kernel's port for
    /// `udpin:HOST:0`), waiting up to `timeout` for the bind. A link of
    /// another scheme never binds one: it times out.
    pub async fn bound_addr(&self, timeout: Duration) -> Result<std::net::SocketAddr, LinkError> {
        let mut rx = self.bound.clone();
        match tokio::time::timeout(timeout, rx.wait_for(Option::is_some)).await {
            Ok(Ok(addr)) => (*addr).ok_or(LinkError::ActorGone),
            Ok(Err(_)) => Err(LinkError::ActorGone),
            Err(_) => Err(LinkError::Timeout {
                what: "the link's UDP socket",
                seconds: timeout.as_secs_f64(),
            }),
        }
    }

    /// The forward endpoints' state (`[link] forward`).
    pub fn forward_status(&self) -> Vec<router::ForwardStatus> {
        self.router.status()
    }

    /// Frames of MAVLink message `id` received from the vehicle (counted
    /// only while forward endpoints are configured).
    pub fn frames_from_vehicle(&self, id: u32) -> u64 {
        self.router.frames_from_vehicle(id)
    }

    /// The address forward endpoint `i` (in `[link] forward`'s order) is
    /// bound to, once bound (`udpin:` and `tcpin:`, port 0 included).
    pub fn forward_bound(&self, i: usize) -> Option<std::net::SocketAddr> {
        self.router.bound(i)
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

/// DO_GIMBAL_MANAGER_CONFIGURE params that give control back for `device`.
pub fn release_params(device: u8) -> [f32; 7] {
    use crate::mission::plan::{GIMBAL_CONTROL_RELEASE, GIMBAL_CONTROL_UNCHANGED};
    [
        GIMBAL_CONTROL_RELEASE,
        GIMBAL_CONTROL_RELEASE,
        GIMBAL_CONTROL_UNCHANGED,
        GIMBAL_CONTROL_UNCHANGED,
        0.0,
        0.0,
        f32::from(device),
    ]
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
