//! The telemetry the link keeps: each message's latest value with its receive
//! time, the vehicle tracked, cameras, captures, video streams and gimbal
//! control, one watch channel each ([`Telemetry`]).

use std::time::Instant;

use serde::Serialize;
use tokio::sync::watch;

use crate::mission::Flavour;

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

/// CAMERA_IMAGE_CAPTURED messages kept in [`Telemetry::captures`].
pub const CAPTURES_KEPT: usize = 32;

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
}
