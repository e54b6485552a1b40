//! Mission planning: from a camera target to the mission items each autopilot
//! flavour accepts, the geofence check, and QGroundControl `.plan` export.
//!
//! Pure code: no I/O, no clock, no tokio. Items are plain numbers
//! ([`MissionItem`]) in the layout of MAVLink's `MISSION_ITEM_INT`, so they
//! compare exactly after a round trip through an autopilot.
//!
//! What each flavour gets for one target (`seq` numbers in brackets):
//!
//! | PX4 | ArduPilot |
//! |---|---|
//! | [0] `DO_GIMBAL_MANAGER_CONFIGURE` (-2/-2: the autopilot takes primary control) | [0] home placeholder `NAV_WAYPOINT` (the autopilot overwrites it) |
//! | [1] `DO_GIMBAL_MANAGER_PITCHYAW` | [1] `NAV_WAYPOINT`, relative-altitude frame |
//! | [2] `NAV_WAYPOINT`, relative-altitude frame, yaw in param4, acceptance radius in param2 | [2] `CONDITION_YAW` (absolute) |
//! | [3] `IMAGE_START_CAPTURE` (with `photo`) | [3] `DO_GIMBAL_MANAGER_PITCHYAW` |
//! | [last] `DO_GIMBAL_MANAGER_CONFIGURE` (-3/-3: release control) | [4] `DO_DIGICAM_CONTROL` (with `photo`) |
//!
//! Gimbal protocol v2 (MAVLink's gimbal manager). PX4 runs mission DO items
//! as commands from the autopilot itself and its gimbal manager denies a
//! `DO_GIMBAL_MANAGER_PITCHYAW` from anyone not in primary control, so a
//! PX4 mission first makes the autopilot the primary controller with the
//! `DO_GIMBAL_MANAGER_CONFIGURE` mission item (param1/param2 -2, "set
//! itself in control", as MAVSDK's missions do) and gives control up at the
//! end (-3, "remove control if in control"). ArduPilot (4.3+) executes a
//! mission `DO_GIMBAL_MANAGER_PITCHYAW` without checking who is in control
//! and has no handler for `DO_GIMBAL_MANAGER_CONFIGURE` as a mission item,
//! so its missions carry only the PITCHYAW. The ground station's own
//! control (taken with the command before the mission starts) is the link
//! layer's job: see [`crate::vehicle::LinkHandle::start_mission`].
//!
//! With [`GimbalCommand::MountControl`] (older firmware: PX4 before the
//! gimbal manager, ArduPilot before 4.3) both flavours get the legacy
//! `DO_MOUNT_CONTROL` in place of the PITCHYAW and no configure items.
//!
//! PX4 runs the gimbal command before flying, so the camera is already
//! pitched on arrival; the capture follows the waypoint's hold time.

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

/// Mean Earth radius (IUGG), metres.
const EARTH_RADIUS_M: f64 = 6_371_008.8;

/// `MAV_CMD` numbers used by the planner.
pub mod cmd {
    /// MAV_CMD_NAV_WAYPOINT
    pub const NAV_WAYPOINT: u16 = 16;
    /// MAV_CMD_CONDITION_YAW
    pub const CONDITION_YAW: u16 = 115;
    /// MAV_CMD_DO_DIGICAM_CONTROL
    pub const DO_DIGICAM_CONTROL: u16 = 203;
    /// MAV_CMD_DO_MOUNT_CONTROL
    pub const DO_MOUNT_CONTROL: u16 = 205;
    /// MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW
    pub const DO_GIMBAL_MANAGER_PITCHYAW: u16 = 1000;
    /// MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE
    pub const DO_GIMBAL_MANAGER_CONFIGURE: u16 = 1001;
    /// MAV_CMD_IMAGE_START_CAPTURE
    pub const IMAGE_START_CAPTURE: u16 = 2000;
}

/// `MAV_FRAME` numbers used by the planner.
pub mod frame {
    /// MAV_FRAME_GLOBAL: WGS84, altitude above mean sea level.
    pub const GLOBAL: u8 = 0;
    /// MAV_FRAME_MISSION: the item is not a position (a command).
    pub const MISSION: u8 = 2;
    /// MAV_FRAME_GLOBAL_RELATIVE_ALT: WGS84, altitude above home (QGC files use it).
    pub const GLOBAL_RELATIVE_ALT: u8 = 3;
    /// MAV_FRAME_GLOBAL_INT: like GLOBAL, with integer latitude/longitude (deg * 1e7).
    pub const GLOBAL_INT: u8 = 5;
    /// MAV_FRAME_GLOBAL_RELATIVE_ALT_INT: altitude above home, integer lat/lon.
    pub const GLOBAL_RELATIVE_ALT_INT: u8 = 6;
}

/// GIMBAL_MANAGER_FLAGS_ROLL_LOCK
const GIMBAL_FLAG_ROLL_LOCK: i32 = 4;
/// GIMBAL_MANAGER_FLAGS_PITCH_LOCK (pitch relative to the horizon)
const GIMBAL_FLAG_PITCH_LOCK: i32 = 8;
/// GIMBAL_MANAGER_FLAGS_YAW_IN_VEHICLE_FRAME
const GIMBAL_FLAG_YAW_IN_VEHICLE_FRAME: i32 = 32;
/// MAV_MOUNT_MODE_MAVLINK_TARGETING
const MOUNT_MODE_MAVLINK_TARGETING: f32 = 2.0;

/// Errors of planning and of the geofence.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanError {
    /// A target field is not a finite number in its range.
    #[error("invalid target {field} = {value}: {reason}")]
    InvalidTarget {
        /// Which field.
        field: &'static str,
        /// Its value.
        value: f64,
        /// The allowed range.
        reason: &'static str,
    },
    /// The target is farther from home than the fence radius.
    #[error("target is {distance_m:.1} m from home, outside the {radius_m:.1} m geofence")]
    OutsideFence {
        /// Horizontal distance from home, metres.
        distance_m: f64,
        /// Fence radius, metres.
        radius_m: f64,
    },
    /// The target is lower than the fence floor.
    #[error("target altitude {alt_m:.1} m is below the geofence floor {min_m:.1} m")]
    BelowMinAltitude {
        /// Target altitude above home, metres.
        alt_m: f64,
        /// Floor, metres above home.
        min_m: f64,
    },
    /// The target is higher than the fence ceiling.
    #[error("target altitude {alt_m:.1} m is above the geofence ceiling {max_m:.1} m")]
    AboveMaxAltitude {
        /// Target altitude above home, metres.
        alt_m: f64,
        /// Ceiling, metres above home.
        max_m: f64,
    },
    /// A mission cannot be exported (for example, it holds no items).
    #[error("cannot export plan: {reason}")]
    Export {
        /// Why.
        reason: &'static str,
    },
}

/// The autopilot family, which decides the items the planner emits.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Flavour {
    /// PX4 (MAV_AUTOPILOT_PX4).
    Px4,
    /// ArduPilot (MAV_AUTOPILOT_ARDUPILOTMEGA).
    #[serde(rename = "ardupilot")]
    ArduPilot,
}

impl Flavour {
    /// The MAV_AUTOPILOT number, as QGroundControl writes `firmwareType`.
    pub fn mav_autopilot(self) -> u8 {
        match self {
            Flavour::Px4 => 12,
            Flavour::ArduPilot => 3,
        }
    }
}

/// Which command points the gimbal (both flavours).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum GimbalCommand {
    /// MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW (gimbal protocol v2: PX4, ArduPilot 4.3+).
    GimbalManager,
    /// MAV_CMD_DO_MOUNT_CONTROL (older firmware: ArduPilot before 4.3, old PX4 mounts).
    MountControl,
}

/// `DO_GIMBAL_MANAGER_CONFIGURE` param1/param2: "set itself in control"
/// (the autopilot running the mission).
pub const GIMBAL_CONTROL_SELF: f32 = -2.0;
/// `DO_GIMBAL_MANAGER_CONFIGURE` param1/param2: "remove control if
/// currently in control".
pub const GIMBAL_CONTROL_RELEASE: f32 = -3.0;
/// `DO_GIMBAL_MANAGER_CONFIGURE` param1..param4: "leave unchanged".
pub const GIMBAL_CONTROL_UNCHANGED: f32 = -1.0;

/// A circular geofence around home with an altitude band.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Fence {
    /// Largest horizontal distance from home, metres.
    pub radius_m: f64,
    /// Lowest altitude above home, metres.
    pub min_alt_m: f64,
    /// Highest altitude above home, metres.
    pub max_alt_m: f64,
}

impl Default for Fence {
    fn default() -> Self {
        Self {
            radius_m: 300.0,
            min_alt_m: 2.0,
            max_alt_m: 120.0,
        }
    }
}

/// Every tunable number of the planner.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Waypoint acceptance radius, metres (PX4 param2).
    pub acceptance_radius_m: f32,
    /// Hold time at the waypoint before the next item, seconds (param1).
    pub hold_time_s: f32,
    /// Yaw rate for ArduPilot's CONDITION_YAW, deg/s.
    pub yaw_rate_deg_s: f32,
    /// Gimbal command, both flavours (`px4_gimbal` is its old name).
    #[serde(alias = "px4_gimbal")]
    pub gimbal: GimbalCommand,
    /// The geofence every target must lie in.
    pub fence: Fence,
    /// Cruise speed written to `.plan` files, m/s.
    pub cruise_speed_m_s: f64,
    /// Hover speed written to `.plan` files, m/s.
    pub hover_speed_m_s: f64,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            acceptance_radius_m: 1.0,
            hold_time_s: 3.0,
            yaw_rate_deg_s: 30.0,
            gimbal: GimbalCommand::GimbalManager,
            fence: Fence::default(),
            cruise_speed_m_s: 15.0,
            hover_speed_m_s: 5.0,
        }
    }
}

/// Where the camera must stand and look.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Target {
    /// Latitude, degrees (WGS84).
    pub lat_deg: f64,
    /// Longitude, degrees (WGS84).
    pub lon_deg: f64,
    /// Altitude above home, metres.
    pub alt_m: f64,
    /// Vehicle heading, degrees clockwise from north.
    pub yaw_deg: f64,
    /// Gimbal pitch, degrees (negative looks down, -90 straight down).
    pub gimbal_pitch_deg: f64,
    /// Take one photo on arrival.
    pub photo: bool,
}

/// Home: the origin of relative altitudes and the centre of the fence.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Home {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, metres.
    pub alt_amsl_m: f64,
}

/// A float as JSON writes NaN (`null`, as serde_json and QGroundControl
/// do) read back as NaN.
fn nan_from_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<f32, D::Error> {
    Ok(Option::<f32>::deserialize(d)?.unwrap_or(f32::NAN))
}

/// [`nan_from_null`] for the four params.
fn params_nan_from_null<'de, D: serde::Deserializer<'de>>(d: D) -> Result<[f32; 4], D::Error> {
    let p = <[Option<f32>; 4]>::deserialize(d)?;
    Ok(p.map(|x| x.unwrap_or(f32::NAN)))
}

/// One mission item, laid out as MAVLink's `MISSION_ITEM_INT`.
///
/// For global frames `x`/`y` are latitude/longitude in degrees * 1e7; for
/// other frames they carry param5/param6 as integers. `z` is param7. In
/// JSON a NaN param (PX4's "unchanged") is `null` and reads back as NaN.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MissionItem {
    /// Index in the mission.
    pub seq: u16,
    /// MAV_FRAME number.
    pub frame: u8,
    /// MAV_CMD number.
    pub command: u16,
    /// The "current" flag (false for uploaded items).
    pub current: bool,
    /// Continue to the next item when this one completes.
    pub autocontinue: bool,
    /// param1..param4.
    #[serde(deserialize_with = "params_nan_from_null")]
    pub params: [f32; 4],
    /// param5 / latitude * 1e7.
    pub x: i32,
    /// param6 / longitude * 1e7.
    pub y: i32,
    /// param7 / altitude, metres.
    #[serde(deserialize_with = "nan_from_null")]
    pub z: f32,
}

impl MissionItem {
    /// Whether `x`/`y` hold a latitude/longitude.
    pub fn is_global(&self) -> bool {
        matches!(
            self.frame,
            frame::GLOBAL
                | frame::GLOBAL_RELATIVE_ALT
                | frame::GLOBAL_INT
                | frame::GLOBAL_RELATIVE_ALT_INT
        ) || (self.frame == 10 || self.frame == 11) // GLOBAL_TERRAIN_ALT(_INT)
    }

    /// The same item with every field an autopilot should store unchanged;
    /// for comparing a planned mission with a downloaded one.
    pub fn same_content(&self, other: &MissionItem) -> bool {
        let p = |a: f32, b: f32| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan());
        self.seq == other.seq
            && self.frame == other.frame
            && self.command == other.command
            && self.autocontinue == other.autocontinue
            && self
                .params
                .iter()
                .zip(other.params.iter())
                .all(|(a, b)| p(*a, *b))
            && self.x == other.x
            && self.y == other.y
            && p(self.z, other.z)
    }
}

/// The `seq` of the last `NAV_WAYPOINT` ([`cmd::NAV_WAYPOINT`]) of a
/// mission: the shot's waypoint in a mission from [`plan`] (ArduPilot's
/// home placeholder at `seq` 0 is a `NAV_WAYPOINT` too, so the first would
/// be the wrong one). `None` when the mission has no waypoint.
pub fn waypoint_seq(items: &[MissionItem]) -> Option<u16> {
    items
        .iter()
        .rev()
        .find(|i| i.command == cmd::NAV_WAYPOINT)
        .map(|i| i.seq)
}

#[cfg(test)]
mod json_tests {
    use super::*;

    /// A PX4 mission's NaN params survive the shot record: the reconciler
    /// reads `planned_items` back to know which shot owns the vehicle's
    /// mission, and NaN is written as `null`.
    #[test]
    fn nan_params_survive_json() {
        let item = MissionItem {
            seq: 3,
            frame: 2,
            command: 1000,
            current: false,
            autocontinue: true,
            params: [-30.0, 0.0, f32::NAN, f32::NAN],
            x: 44,
            y: 0,
            z: f32::NAN,
        };
        let text = serde_json::to_string(&[item]).unwrap();
        assert!(text.contains("null"), "{text}");
        let back: Vec<MissionItem> = serde_json::from_str(&text).unwrap();
        assert!(back[0].same_content(&item));
    }
}

/// Degrees to MAVLink's integer degrees * 1e7, rounded.
pub fn deg_to_e7(deg: f64) -> i32 {
    (deg * 1e7).round().clamp(i32::MIN as f64, i32::MAX as f64) as i32
}

/// Great-circle (haversine) distance between two WGS84 points, metres.
pub fn distance_m(lat1_deg: f64, lon1_deg: f64, lat2_deg: f64, lon2_deg: f64) -> f64 {
    let (p1, p2) = (lat1_deg.to_radians(), lat2_deg.to_radians());
    let dp = p2 - p1;
    let dl = (lon2_deg - lon1_deg).to_radians();
    let a = (dp / 2.0).sin().powi(2) + p1.cos() * p2.cos() * (dl / 2.0).sin().powi(2);
    2.0 * EARTH_RADIUS_M * a.sqrt().min(1.0).asin()
}

/// Wraps an angle to [0, 360) degrees.
fn wrap_360(deg: f64) -> f64 {
    let w = deg.rem_euclid(360.0);
    if w >= 360.0 { 0.0 } else { w }
}

fn check_field(
    field: &'static str,
    value: f64,
    lo: f64,
    hi: f64,
    reason: &'static str,
) -> Result<(), PlanError> {
    if value.is_finite() && value >= lo && value <= hi {
        Ok(())
    } else {
        Err(PlanError::InvalidTarget {
            field,
            value,
            reason,
        })
    }
}

/// Checks a target's numbers and the geofence around `home`.
pub fn check_target(target: &Target, home: &Home, fence: &Fence) -> Result<(), PlanError> {
    check_field(
        "lat_deg",
        target.lat_deg,
        -90.0,
        90.0,
        "latitude in [-90, 90]",
    )?;
    check_field(
        "lon_deg",
        target.lon_deg,
        -180.0,
        180.0,
        "longitude in [-180, 180]",
    )?;
    check_field("alt_m", target.alt_m, -1e4, 1e5, "finite altitude")?;
    check_field("yaw_deg", target.yaw_deg, -1e6, 1e6, "finite yaw")?;
    check_field(
        "gimbal_pitch_deg",
        target.gimbal_pitch_deg,
        -90.0,
        30.0,
        "pitch in [-90, 30]",
    )?;
    check_field(
        "home.lat_deg",
        home.lat_deg,
        -90.0,
        90.0,
        "latitude in [-90, 90]",
    )?;
    check_field(
        "home.lon_deg",
        home.lon_deg,
        -180.0,
        180.0,
        "longitude in [-180, 180]",
    )?;
    let distance = distance_m(home.lat_deg, home.lon_deg, target.lat_deg, target.lon_deg);
    if distance.is_nan() || distance > fence.radius_m {
        return Err(PlanError::OutsideFence {
            distance_m: distance,
            radius_m: fence.radius_m,
        });
    }
    if target.alt_m < fence.min_alt_m {
        return Err(PlanError::BelowMinAltitude {
            alt_m: target.alt_m,
            min_m: fence.min_alt_m,
        });
    }
    if target.alt_m > fence.max_alt_m {
        return Err(PlanError::AboveMaxAltitude {
            alt_m: target.alt_m,
            max_m: fence.max_alt_m,
        });
    }
    Ok(())
}

fn command_item(command: u16, params: [f32; 4], x: i32, y: i32, z: f32) -> MissionItem {
    MissionItem {
        seq: 0,
        frame: frame::MISSION,
        command,
        current: false,
        autocontinue: true,
        params,
        x,
        y,
        z,
    }
}

/// Whether a mission points the gimbal with the gimbal manager (protocol
/// v2), so the ground station should take gimbal control before starting it.
pub fn points_gimbal_v2(items: &[MissionItem]) -> bool {
    items
        .iter()
        .any(|i| i.command == cmd::DO_GIMBAL_MANAGER_PITCHYAW)
}

/// Whether a mission makes the autopilot itself the gimbal's primary
/// controller (a `DO_GIMBAL_MANAGER_CONFIGURE` item with param1
/// [`GIMBAL_CONTROL_SELF`], as PX4 missions get): once that item ran, the
/// mission's own gimbal items need the autopilot in control, and a ground
/// station taking control back would get them denied.
pub fn takes_gimbal_control(items: &[MissionItem]) -> bool {
    items.iter().any(|i| {
        i.command == cmd::DO_GIMBAL_MANAGER_CONFIGURE && i.params[0] == GIMBAL_CONTROL_SELF
    })
}

/// Plans the mission that takes the camera to `target` for `flavour`.
///
/// Refuses targets outside the fence. Items come numbered from 0.
pub fn plan(
    target: &Target,
    home: &Home,
    flavour: Flavour,
    params: &Params,
) -> Result<Vec<MissionItem>, PlanError> {
    check_target(target, home, &params.fence)?;
    let yaw = wrap_360(target.yaw_deg) as f32;
    let pitch = target.gimbal_pitch_deg as f32;
    let lat = deg_to_e7(target.lat_deg);
    let lon = deg_to_e7(target.lon_deg);
    let alt = target.alt_m as f32;
    let gimbal = match params.gimbal {
        GimbalCommand::GimbalManager => command_item(
            cmd::DO_GIMBAL_MANAGER_PITCHYAW,
            // pitch, yaw (relative to the vehicle), rates unset
            [pitch, 0.0, f32::NAN, f32::NAN],
            GIMBAL_FLAG_ROLL_LOCK | GIMBAL_FLAG_PITCH_LOCK | GIMBAL_FLAG_YAW_IN_VEHICLE_FRAME,
            0,
            0.0, // gimbal device id: all
        ),
        GimbalCommand::MountControl => command_item(
            cmd::DO_MOUNT_CONTROL,
            [pitch, 0.0, 0.0, 0.0],
            0,
            0,
            MOUNT_MODE_MAVLINK_TARGETING,
        ),
    };
    let v2 = params.gimbal == GimbalCommand::GimbalManager;
    // primary sysid/compid, secondary unchanged, device id 0 (all)
    let configure = |who: f32| {
        command_item(
            cmd::DO_GIMBAL_MANAGER_CONFIGURE,
            [who, who, GIMBAL_CONTROL_UNCHANGED, GIMBAL_CONTROL_UNCHANGED],
            0,
            0,
            0.0,
        )
    };
    let mut items = Vec::with_capacity(6);
    match flavour {
        Flavour::Px4 => {
            if v2 {
                items.push(configure(GIMBAL_CONTROL_SELF));
            }
            items.push(gimbal);
            items.push(MissionItem {
                seq: 0,
                frame: frame::GLOBAL_RELATIVE_ALT_INT,
                command: cmd::NAV_WAYPOINT,
                current: false,
                autocontinue: true,
                params: [params.hold_time_s, params.acceptance_radius_m, 0.0, yaw],
                x: lat,
                y: lon,
                z: alt,
            });
            if target.photo {
                // camera id 0 (all), interval 0, one image, capture sequence 1
                items.push(command_item(
                    cmd::IMAGE_START_CAPTURE,
                    [0.0, 0.0, 1.0, 1.0],
                    0,
                    0,
                    f32::NAN,
                ));
            }
            if v2 {
                items.push(configure(GIMBAL_CONTROL_RELEASE));
            }
        }
        Flavour::ArduPilot => {
            items.push(MissionItem {
                seq: 0,
                frame: frame::GLOBAL,
                command: cmd::NAV_WAYPOINT,
                current: false,
                autocontinue: true,
                params: [0.0; 4],
                x: deg_to_e7(home.lat_deg),
                y: deg_to_e7(home.lon_deg),
                z: home.alt_amsl_m as f32,
            });
            items.push(MissionItem {
                seq: 0,
                frame: frame::GLOBAL_RELATIVE_ALT_INT,
                command: cmd::NAV_WAYPOINT,
                current: false,
                autocontinue: true,
                params: [params.hold_time_s, 0.0, 0.0, 0.0],
                x: lat,
                y: lon,
                z: alt,
            });
            // angle, rate, direction (0: shortest), absolute
            items.push(command_item(
                cmd::CONDITION_YAW,
                [yaw, params.yaw_rate_deg_s, 0.0, 0.0],
                0,
                0,
                0.0,
            ));
            items.push(gimbal);
            if target.photo {
                // session, zoom, zoom step, focus lock, shoot = 1, command id, shot id
                items.push(command_item(cmd::DO_DIGICAM_CONTROL, [0.0; 4], 1, 0, 0.0));
            }
        }
    }
    for (seq, item) in items.iter_mut().enumerate() {
        item.seq = seq as u16;
    }
    Ok(items)
}

fn json_f32(v: f32) -> Value {
    if v.is_finite() {
        json!(f64::from(v))
    } else {
        Value::Null
    }
}

/// The seven params of an item as QGroundControl writes them (NaN as null,
/// latitude/longitude in degrees for global frames).
fn qgc_params(item: &MissionItem) -> [Value; 7] {
    let (x, y) = if item.is_global() {
        (
            json!(f64::from(item.x) / 1e7),
            json!(f64::from(item.y) / 1e7),
        )
    } else {
        (json!(item.x), json!(item.y))
    };
    [
        json_f32(item.params[0]),
        json_f32(item.params[1]),
        json_f32(item.params[2]),
        json_f32(item.params[3]),
        x,
        y,
        json_f32(item.z),
    ]
}

/// QGroundControl's frame for a MISSION_ITEM_INT frame (QGC files use the
/// float frames).
fn qgc_frame(frame_int: u8) -> u8 {
    match frame_int {
        frame::GLOBAL_INT => frame::GLOBAL,
        frame::GLOBAL_RELATIVE_ALT_INT => frame::GLOBAL_RELATIVE_ALT,
        11 => 10, // GLOBAL_TERRAIN_ALT_INT -> GLOBAL_TERRAIN_ALT
        f => f,
    }
}

/// Exports a planned mission as a QGroundControl `.plan` document (JSON).
///
/// Follows QGC's documented format: `fileType` "Plan", `version` 1, a
/// `mission` (version 2) of `SimpleItem`s, `plannedHomePosition`, the fence as
/// an inclusion circle in `geoFence`, and empty `rallyPoints`. ArduPilot's
/// home placeholder (seq 0) is not an item in QGC files: QGC writes home as
/// `plannedHomePosition` and inserts it on upload.
pub fn to_qgc_plan(
    items: &[MissionItem],
    home: &Home,
    flavour: Flavour,
    params: &Params,
) -> Result<Value, PlanError> {
    let skip = usize::from(flavour == Flavour::ArduPilot);
    let body: Vec<&MissionItem> = items.iter().skip(skip).collect();
    if body.is_empty() {
        return Err(PlanError::Export {
            reason: "a QGroundControl plan needs at least one mission item",
        });
    }
    let mut out = Vec::with_capacity(body.len());
    for (i, item) in body.iter().enumerate() {
        let mut obj = serde_json::Map::new();
        obj.insert("type".into(), json!("SimpleItem"));
        obj.insert("autoContinue".into(), json!(item.autocontinue));
        obj.insert("command".into(), json!(item.command));
        obj.insert("doJumpId".into(), json!(i + 1));
        obj.insert("frame".into(), json!(qgc_frame(item.frame)));
        obj.insert("params".into(), Value::Array(qgc_params(item).to_vec()));
        if item.is_global() {
            obj.insert("AMSLAltAboveTerrain".into(), Value::Null);
            obj.insert("Altitude".into(), json_f32(item.z));
            // 1: relative to home, 2: AMSL
            let mode = if matches!(item.frame, frame::GLOBAL | frame::GLOBAL_INT) {
                2
            } else {
                1
            };
            obj.insert("AltitudeMode".into(), json!(mode));
        }
        out.push(Value::Object(obj));
    }
    Ok(json!({
        "fileType": "Plan",
        "version": 1,
        "groundStation": "shotpilot",
        "mission": {
            "version": 2,
            "firmwareType": flavour.mav_autopilot(),
            "vehicleType": 2, // MAV_TYPE_QUADROTOR
            "cruiseSpeed": params.cruise_speed_m_s,
            "hoverSpeed": params.hover_speed_m_s,
            "globalPlanAltitudeMode": 1,
            "items": out,
            "plannedHomePosition": [home.lat_deg, home.lon_deg, home.alt_amsl_m],
        },
        "geoFence": {
            "version": 2,
            "circles": [{
                "circle": { "center": [home.lat_deg, home.lon_deg], "radius": params.fence.radius_m },
                "inclusion": true,
                "version": 1,
            }],
            "polygons": [],
        },
        "rallyPoints": { "version": 2, "points": [] },
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOME: Home = Home {
        lat_deg: 47.397742,
        lon_deg: 8.545594,
        alt_amsl_m: 488.0,
    };

    /// A point `north_m`, `east_m` from home (small-offset approximation good
    /// to millimetres at these distances).
    fn offset(north_m: f64, east_m: f64) -> (f64, f64) {
        let dlat = north_m / EARTH_RADIUS_M;
        let dlon = east_m / (EARTH_RADIUS_M * HOME.lat_deg.to_radians().cos());
        (
            HOME.lat_deg + dlat.to_degrees(),
            HOME.lon_deg + dlon.to_degrees(),
        )
    }

    fn target(north_m: f64, east_m: f64, alt_m: f64, photo: bool) -> Target {
        let (lat, lon) = offset(north_m, east_m);
        Target {
            lat_deg: lat,
            lon_deg: lon,
            alt_m,
            yaw_deg: -90.0,
            gimbal_pitch_deg: -30.0,
            photo,
        }
    }

    #[test]
    fn the_shot_waypoint_is_the_last_nav_waypoint() {
        let p = Params::default();
        let t = target(40.0, 30.0, 25.0, true);
        for (flavour, want) in [(Flavour::Px4, 2), (Flavour::ArduPilot, 1)] {
            let items = plan(&t, &HOME, flavour, &p).expect("inside fence");
            let seq = waypoint_seq(&items).expect("a waypoint");
            assert_eq!(seq, want, "{flavour:?}");
            let item = items[usize::from(seq)];
            assert_eq!(item.command, cmd::NAV_WAYPOINT);
            // The shot's position, not ArduPilot's home placeholder.
            assert_eq!(item.x, (t.lat_deg * 1e7).round() as i32, "{flavour:?}");
        }
        assert_eq!(waypoint_seq(&[]), None);
        let items = plan(&t, &HOME, Flavour::Px4, &p).expect("inside fence");
        let no_waypoint: Vec<MissionItem> = items
            .into_iter()
            .filter(|i| i.command != cmd::NAV_WAYPOINT)
            .collect();
        assert_eq!(waypoint_seq(&no_waypoint), None);
    }

    #[test]
    fn px4_items() {
        let p = Params::default();
        let t = target(40.0, 30.0, 25.0, true);
        let items = plan(&t, &HOME, Flavour::Px4, &p).expect("inside fence");
        let cmds: Vec<u16> = items.iter().map(|i| i.command).collect();
        assert_eq!(
            cmds,
            [
                cmd::DO_GIMBAL_MANAGER_CONFIGURE,
                cmd::DO_GIMBAL_MANAGER_PITCHYAW,
                cmd::NAV_WAYPOINT,
                cmd::IMAGE_START_CAPTURE,
                cmd::DO_GIMBAL_MANAGER_CONFIGURE,
            ]
        );
        assert!(points_gimbal_v2(&items));
        assert!(
            takes_gimbal_control(&items),
            "the PX4 mission configures itself"
        );
        assert_eq!(
            items.iter().map(|i| i.seq).collect::<Vec<_>>(),
            [0, 1, 2, 3, 4]
        );
        let take = items[0];
        assert_eq!(take.frame, frame::MISSION);
        assert_eq!(
            take.params,
            [-2.0, -2.0, -1.0, -1.0],
            "autopilot takes control"
        );
        assert_eq!(take.z, 0.0, "all gimbal devices");
        assert_eq!(
            items[4].params,
            [-3.0, -3.0, -1.0, -1.0],
            "released at the end"
        );
        let wp = items[2];
        assert_eq!(wp.frame, frame::GLOBAL_RELATIVE_ALT_INT);
        assert_eq!(wp.params[3], 270.0, "yaw wrapped into [0, 360) in param4");
        assert_eq!(wp.params[1], p.acceptance_radius_m);
        assert_eq!(wp.params[0], p.hold_time_s);
        assert_eq!(wp.x, deg_to_e7(t.lat_deg));
        assert_eq!(wp.y, deg_to_e7(t.lon_deg));
        assert_eq!(wp.z, 25.0);
        let g = items[1];
        assert_eq!(g.frame, frame::MISSION);
        assert_eq!(g.params[0], -30.0);
        assert_eq!(g.params[1], 0.0);
        assert_eq!(g.x, 4 | 8 | 32);
        assert_eq!(items[3].params[2], 1.0, "one image");
        // without photo, and with the mount command by configuration
        let p2 = Params {
            gimbal: GimbalCommand::MountControl,
            ..p
        };
        let items =
            plan(&target(40.0, 30.0, 25.0, false), &HOME, Flavour::Px4, &p2).expect("inside");
        let cmds: Vec<u16> = items.iter().map(|i| i.command).collect();
        assert_eq!(cmds, [cmd::DO_MOUNT_CONTROL, cmd::NAV_WAYPOINT]);
        assert!(!points_gimbal_v2(&items));
        assert_eq!(items[0].params[0], -30.0);
        assert_eq!(items[0].z, 2.0, "mount mode MAVLINK_TARGETING");
    }

    #[test]
    fn ardupilot_items() {
        let p = Params::default();
        let t = target(-60.0, 10.0, 40.0, true);
        let items = plan(&t, &HOME, Flavour::ArduPilot, &p).expect("inside fence");
        let cmds: Vec<u16> = items.iter().map(|i| i.command).collect();
        assert_eq!(
            cmds,
            [
                cmd::NAV_WAYPOINT,
                cmd::NAV_WAYPOINT,
                cmd::CONDITION_YAW,
                cmd::DO_GIMBAL_MANAGER_PITCHYAW,
                cmd::DO_DIGICAM_CONTROL
            ]
        );
        assert!(points_gimbal_v2(&items));
        assert!(
            !takes_gimbal_control(&items),
            "ArduPilot's mission leaves control to the ground station"
        );
        assert_eq!(
            items[0].frame,
            frame::GLOBAL,
            "home placeholder in AMSL frame"
        );
        assert_eq!(items[0].x, deg_to_e7(HOME.lat_deg));
        assert_eq!(items[0].z, 488.0);
        assert_eq!(items[1].frame, frame::GLOBAL_RELATIVE_ALT_INT);
        assert_eq!(items[1].z, 40.0);
        assert_eq!(items[2].params[0], 270.0);
        assert_eq!(items[2].params[1], p.yaw_rate_deg_s);
        assert_eq!(items[2].params[3], 0.0, "absolute heading");
        assert_eq!(items[3].params[0], -30.0);
        assert_eq!(items[3].x, 4 | 8 | 32, "yaw in the vehicle frame");
        assert_eq!(items[4].x, 1, "shoot");
        assert_eq!(
            items.iter().map(|i| i.seq).collect::<Vec<_>>(),
            [0, 1, 2, 3, 4]
        );
        // older firmware: the legacy mount command behind the switch
        let legacy = Params {
            gimbal: GimbalCommand::MountControl,
            ..p
        };
        let items = plan(&t, &HOME, Flavour::ArduPilot, &legacy).expect("inside fence");
        assert_eq!(items[3].command, cmd::DO_MOUNT_CONTROL);
        assert_eq!(items[3].params[0], -30.0);
        assert_eq!(items[3].z, 2.0, "mount mode MAVLINK_TARGETING");
        assert!(!points_gimbal_v2(&items));
    }

    #[test]
    fn gimbal_switch_reads_its_old_name() {
        let p: Params = toml::from_str("px4_gimbal = \"mount_control\"").expect("old name");
        assert_eq!(p.gimbal, GimbalCommand::MountControl);
        let p: Params = toml::from_str("gimbal = \"gimbal_manager\"").expect("new name");
        assert_eq!(p.gimbal, GimbalCommand::GimbalManager);
    }

    #[test]
    fn fence_refusals() {
        let p = Params::default(); // 300 m, 2..120 m
        assert!(plan(&target(200.0, 200.0, 30.0, false), &HOME, Flavour::Px4, &p).is_ok()); // 282.8 m
        match plan(&target(250.0, 200.0, 30.0, false), &HOME, Flavour::Px4, &p) {
            Err(PlanError::OutsideFence {
                distance_m,
                radius_m,
            }) => {
                assert!((distance_m - 320.16).abs() < 0.05, "{distance_m}");
                assert_eq!(radius_m, 300.0);
            }
            other => panic!("expected OutsideFence, got {other:?}"),
        }
        assert_eq!(
            plan(
                &target(10.0, 0.0, 1.0, false),
                &HOME,
                Flavour::ArduPilot,
                &p
            ),
            Err(PlanError::BelowMinAltitude {
                alt_m: 1.0,
                min_m: 2.0
            })
        );
        assert_eq!(
            plan(&target(10.0, 0.0, 150.0, false), &HOME, Flavour::Px4, &p),
            Err(PlanError::AboveMaxAltitude {
                alt_m: 150.0,
                max_m: 120.0
            })
        );
        let mut bad = target(10.0, 0.0, 30.0, false);
        bad.lat_deg = f64::NAN;
        assert!(matches!(
            plan(&bad, &HOME, Flavour::Px4, &p),
            Err(PlanError::InvalidTarget {
                field: "lat_deg",
                ..
            })
        ));
        let mut bad = target(10.0, 0.0, 30.0, false);
        bad.gimbal_pitch_deg = -120.0;
        assert!(matches!(
            plan(&bad, &HOME, Flavour::Px4, &p),
            Err(PlanError::InvalidTarget {
                field: "gimbal_pitch_deg",
                ..
            })
        ));
    }

    #[test]
    fn haversine_matches_known_distance() {
        // One degree of latitude on the mean sphere: pi R / 180.
        let d = distance_m(0.0, 0.0, 1.0, 0.0);
        assert!((d - 111_195.08).abs() < 0.1, "{d}");
        let (lat, lon) = offset(300.0, 400.0);
        assert!((distance_m(HOME.lat_deg, HOME.lon_deg, lat, lon) - 500.0).abs() < 0.01);
    }

    #[test]
    fn qgc_plan_document() {
        let p = Params::default();
        let t = target(40.0, 30.0, 25.0, true);
        for flavour in [Flavour::Px4, Flavour::ArduPilot] {
            let items = plan(&t, &HOME, flavour, &p).expect("inside");
            let doc = to_qgc_plan(&items, &HOME, flavour, &p).expect("export");
            let text = serde_json::to_string_pretty(&doc).expect("serialise");
            let back: Value = serde_json::from_str(&text).expect("valid JSON");
            assert_eq!(back["fileType"], "Plan");
            assert_eq!(back["version"], 1);
            assert_eq!(back["mission"]["version"], 2);
            assert_eq!(back["mission"]["firmwareType"], flavour.mav_autopilot());
            assert_eq!(back["mission"]["plannedHomePosition"][2], 488.0);
            assert_eq!(
                back["rallyPoints"]["points"].as_array().map(Vec::len),
                Some(0)
            );
            assert_eq!(back["geoFence"]["circles"][0]["circle"]["radius"], 300.0);
            let qitems = back["mission"]["items"].as_array().expect("items");
            let expected = if flavour == Flavour::ArduPilot {
                items.len() - 1
            } else {
                items.len()
            };
            assert_eq!(qitems.len(), expected);
            for (i, q) in qitems.iter().enumerate() {
                assert_eq!(q["type"], "SimpleItem");
                assert_eq!(q["doJumpId"], i + 1);
                assert_eq!(q["params"].as_array().map(Vec::len), Some(7));
                assert!(q["autoContinue"].is_boolean());
            }
            let wp = qitems
                .iter()
                .find(|q| q["command"] == cmd::NAV_WAYPOINT)
                .expect("a waypoint");
            assert_eq!(
                wp["frame"], 3,
                "QGC writes the float relative-altitude frame"
            );
            assert_eq!(wp["Altitude"], 25.0);
            assert_eq!(wp["AltitudeMode"], 1);
            let lat = wp["params"][4].as_f64().expect("lat");
            assert!((lat - t.lat_deg).abs() < 1e-7);
        }
        assert!(matches!(
            to_qgc_plan(&[], &HOME, Flavour::Px4, &p),
            Err(PlanError::Export { .. })
        ));
    }
}
