//! A PX4-like (or ArduPilot-like) autopilot speaking MAVLink 2.
//!
//! [`Autopilot`] is synchronous and free of I/O: [`Autopilot::handle`] takes
//! one received message, [`Autopilot::step`] advances the simulation clock;
//! both return the messages to send. Image captures are handed out as
//! [`CaptureRequest`]s (the app renders and stores the frame) and answered
//! with [`Autopilot::capture_done`], which builds CAMERA_IMAGE_CAPTURED.
//!
//! Telemetry streams and their default rates (Hz): HEARTBEAT 1, SYS_STATUS
//! 1, SYSTEM_TIME 1, GPS_RAW_INT 1, EXTENDED_SYS_STATE 1, MISSION_CURRENT 1,
//! ATTITUDE 10, GLOBAL_POSITION_INT 5, LOCAL_POSITION_NED 5,
//! GIMBAL_DEVICE_ATTITUDE_STATUS 5, HOME_POSITION 0.5. MAV_CMD_SET_MESSAGE_INTERVAL
//! changes them (-1 stops a stream, 0 restores the default) and
//! MAV_CMD_REQUEST_MESSAGE sends one at once (also GIMBAL_MANAGER_INFORMATION,
//! which is not streamed). GIMBAL_MANAGER_STATUS streams at 0.5 Hz and is
//! sent at once when control changes. The ArduPilot flavour also
//! honours the legacy REQUEST_DATA_STREAM (groups ALL, EXTENDED_STATUS,
//! POSITION, EXTRA1, EXTRA3).
//!
//! Commands answered with COMMAND_ACK: COMPONENT_ARM_DISARM, DO_SET_MODE
//! (PX4 custom modes main_mode << 16 | sub_mode << 24, or ArduPilot copter
//! mode numbers), MISSION_START, DO_SET_MISSION_CURRENT, NAV_TAKEOFF,
//! NAV_LAND, NAV_RETURN_TO_LAUNCH, DO_GIMBAL_MANAGER_PITCHYAW,
//! DO_MOUNT_CONTROL, IMAGE_START_CAPTURE, IMAGE_STOP_CAPTURE,
//! DO_DIGICAM_CONTROL, CONDITION_YAW (ArduPilot), DO_CHANGE_SPEED,
//! SET_MESSAGE_INTERVAL, GET_MESSAGE_INTERVAL, REQUEST_MESSAGE,
//! GET_HOME_POSITION, REQUEST_AUTOPILOT_CAPABILITIES; anything else is
//! MAV_RESULT_UNSUPPORTED.
//!
//! Gimbal protocol v2: the autopilot is the gimbal manager of one
//! non-MAVLink gimbal (device id 1). DO_GIMBAL_MANAGER_CONFIGURE sets the
//! primary controller (param1/param2: a sysid/compid, 0 nobody, -1
//! unchanged, -2 the sender itself, -3 release if the sender holds it;
//! param7 device 0 or 1, else FAILED). A DO_GIMBAL_MANAGER_PITCHYAW command
//! from anyone but the primary controller is DENIED with a STATUSTEXT, as
//! PX4's gimbal manager does. In missions the autopilot is the sender: the
//! PX4 flavour takes the CONFIGURE mission item (-2 = the autopilot, PX4's
//! and MAVSDK's way) and runs a mission PITCHYAW only while the autopilot
//! holds control; the ArduPilot flavour refuses CONFIGURE as a mission item
//! (ArduPilot's AP_Mission has no handler for it) and runs a mission
//! PITCHYAW only while the autopilot or the ground station it talks to
//! holds control. That is stricter than ArduPilot (which does not check) on
//! purpose: a ground station that forgets to take control is caught. A
//! refused mission PITCHYAW leaves the gimbal where it is, says so in a
//! STATUSTEXT and the mission goes on. DO_MOUNT_CONTROL (protocol v1, for
//! older firmware) is not checked.
//!
//! Mission execution (mode AUTO.MISSION / ArduPilot AUTO, armed): items run
//! from the current one. NAV_TAKEOFF climbs over the current position (and
//! is reached at once by a vehicle already flying higher);
//! NAV_WAYPOINT flies to the point (param2 acceptance radius, default 2 m,
//! 0.8 m vertically; param4 yaw, NaN = face the direction of travel),
//! waits for the yaw, reports MISSION_ITEM_REACHED, then holds param1
//! seconds; a waypoint started on the ground climbs first, as PX4 does.
//! DO_* items act at once; IMAGE_START_CAPTURE and DO_DIGICAM_CONTROL wait
//! (up to 3 s) for the gimbal to settle so the picture is sharp. NAV_LAND
//! lands (after flying to its lat/lon if set), NAV_RETURN_TO_LAUNCH climbs
//! to the RTL altitude, flies home and lands; both disarm 2 s after touching
//! down. MISSION_CURRENT is sent at 1 Hz and whenever the item changes;
//! MISSION_ITEM_REACHED when an item is reached.

#![allow(deprecated)]
// The legacy mission messages (MISSION_ITEM, MISSION_REQUEST,
// MISSION_SET_CURRENT) and DO_MOUNT_CONTROL are deprecated in the dialect
// but still spoken by real autopilots and ground stations: we implement them
// on purpose.

pub mod mission;

use mavlink::MavHeader;
use mavlink::dialects::common::{
    ATTITUDE_DATA, AUTOPILOT_VERSION_DATA, CAMERA_IMAGE_CAPTURED_DATA, COMMAND_ACK_DATA,
    EXTENDED_SYS_STATE_DATA, GIMBAL_DEVICE_ATTITUDE_STATUS_DATA, GIMBAL_MANAGER_INFORMATION_DATA,
    GIMBAL_MANAGER_STATUS_DATA, GLOBAL_POSITION_INT_DATA, GPS_RAW_INT_DATA, GimbalDeviceErrorFlags,
    GimbalDeviceFlags, GimbalManagerCapFlags, GimbalManagerFlags, GpsFixType, HEARTBEAT_DATA,
    HOME_POSITION_DATA, LOCAL_POSITION_NED_DATA, MESSAGE_INTERVAL_DATA, MISSION_ITEM_REACHED_DATA,
    MavAutopilot, MavBool, MavCmd, MavLandedState, MavMessage, MavModeFlag, MavProtocolCapability,
    MavResult, MavSeverity, MavState, MavSysStatusSensor, MavSysStatusSensorExtended, MavType,
    MavVtolState, MissionState, STATUSTEXT_DATA, SYS_STATUS_DATA, SYSTEM_TIME_DATA,
};
use nalgebra::{Isometry3, UnitQuaternion, Vector3};

use crate::geodesy::Geodetic;
use crate::vehicle::{Setpoint, Vehicle, VehicleParams, wrap_pi};
pub use mission::{Flavour, MissionEvent, MissionItem, MissionParams, MissionProtocol, Peer};

/// Flight modes (PX4 names; the ArduPilot flavour maps them to copter modes).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Mode {
    /// PX4 MANUAL / ArduPilot STABILIZE (holds position: no RC in the sim).
    Manual,
    /// PX4 POSCTL / ArduPilot POSHOLD: hold position.
    Position,
    /// PX4 AUTO.LOITER / ArduPilot LOITER: hold position.
    Hold,
    /// PX4 AUTO.MISSION / ArduPilot AUTO.
    Mission,
    /// PX4 AUTO.TAKEOFF (ArduPilot: GUIDED takeoff).
    Takeoff,
    /// PX4 AUTO.LAND / ArduPilot LAND.
    Land,
    /// PX4 AUTO.RTL / ArduPilot RTL.
    Rtl,
    /// PX4 OFFBOARD / ArduPilot GUIDED: follows an external setpoint (the
    /// scripted operator).
    Offboard,
}

const PX4_MAIN_MANUAL: u32 = 1;
const PX4_MAIN_ALTCTL: u32 = 2;
const PX4_MAIN_POSCTL: u32 = 3;
const PX4_MAIN_AUTO: u32 = 4;
const PX4_MAIN_OFFBOARD: u32 = 6;
const PX4_MAIN_STABILIZED: u32 = 7;
const PX4_SUB_TAKEOFF: u32 = 2;
const PX4_SUB_LOITER: u32 = 3;
const PX4_SUB_MISSION: u32 = 4;
const PX4_SUB_RTL: u32 = 5;
const PX4_SUB_LAND: u32 = 6;

impl Mode {
    /// PX4 custom_mode: main_mode << 16 | sub_mode << 24.
    pub fn px4_custom_mode(self) -> u32 {
        let (main, sub) = match self {
            Mode::Manual => (PX4_MAIN_MANUAL, 0),
            Mode::Position => (PX4_MAIN_POSCTL, 0),
            Mode::Hold => (PX4_MAIN_AUTO, PX4_SUB_LOITER),
            Mode::Mission => (PX4_MAIN_AUTO, PX4_SUB_MISSION),
            Mode::Takeoff => (PX4_MAIN_AUTO, PX4_SUB_TAKEOFF),
            Mode::Land => (PX4_MAIN_AUTO, PX4_SUB_LAND),
            Mode::Rtl => (PX4_MAIN_AUTO, PX4_SUB_RTL),
            Mode::Offboard => (PX4_MAIN_OFFBOARD, 0),
        };
        main << 16 | sub << 24
    }

    /// Decode PX4 (main, sub) modes.
    pub fn from_px4(main: u32, sub: u32) -> Option<Mode> {
        Some(match (main, sub) {
            (PX4_MAIN_MANUAL | PX4_MAIN_STABILIZED, _) => Mode::Manual,
            (PX4_MAIN_ALTCTL | PX4_MAIN_POSCTL, _) => Mode::Position,
            (PX4_MAIN_AUTO, PX4_SUB_LOITER) => Mode::Hold,
            (PX4_MAIN_AUTO, PX4_SUB_MISSION) => Mode::Mission,
            (PX4_MAIN_AUTO, PX4_SUB_TAKEOFF) => Mode::Takeoff,
            (PX4_MAIN_AUTO, PX4_SUB_LAND) => Mode::Land,
            (PX4_MAIN_AUTO, PX4_SUB_RTL) => Mode::Rtl,
            (PX4_MAIN_OFFBOARD, _) => Mode::Offboard,
            _ => return None,
        })
    }

    /// ArduPilot copter mode number.
    pub fn ardupilot_custom_mode(self) -> u32 {
        match self {
            Mode::Manual => 0,    // STABILIZE
            Mode::Position => 16, // POSHOLD
            Mode::Hold => 5,      // LOITER
            Mode::Mission => 3,   // AUTO
            Mode::Takeoff => 4,   // GUIDED (takeoff)
            Mode::Land => 9,      // LAND
            Mode::Rtl => 6,       // RTL
            Mode::Offboard => 4,  // GUIDED
        }
    }

    /// Decode an ArduPilot copter mode number.
    pub fn from_ardupilot(mode: u32) -> Option<Mode> {
        Some(match mode {
            0 => Mode::Manual,
            2 | 16 => Mode::Position,
            3 => Mode::Mission,
            4 => Mode::Offboard,
            5 | 17 => Mode::Hold,
            6 | 21 => Mode::Rtl,
            9 => Mode::Land,
            _ => return None,
        })
    }
}

/// A still image the app must render and store.
#[derive(Debug, Clone)]
pub struct CaptureRequest {
    /// Image index (0, 1, 2, ... since boot).
    pub index: i32,
    /// Capture time since boot, s.
    pub time_boot_s: f64,
    /// Capture time, Unix seconds.
    pub time_unix_s: f64,
    /// Camera pose for the renderer (local NED): the true one, GPS bias
    /// included.
    pub world_from_cam: Isometry3<f64>,
    /// Camera position.
    pub geodetic: Geodetic,
    /// Height above home, m.
    pub relative_alt_m: f64,
    /// Camera orientation in NED (x along the optical axis), w x y z.
    pub q: [f32; 4],
}

/// Every tunable number of the autopilot.
#[derive(Debug, Clone)]
pub struct AutopilotParams {
    /// PX4 or ArduPilot behaviour.
    pub flavour: Flavour,
    /// Our system id.
    pub system_id: u8,
    /// Our component id (the autopilot).
    pub component_id: u8,
    /// The vehicle model.
    pub vehicle: VehicleParams,
    /// Default takeoff height above home, m (PX4 MIS_TAKEOFF_ALT).
    pub takeoff_alt_m: f64,
    /// Minimum return altitude above home, m (PX4 RTL_RETURN_ALT).
    pub rtl_alt_m: f64,
    /// Default horizontal acceptance radius, m (PX4 NAV_ACC_RAD).
    pub acceptance_radius_m: f64,
    /// Vertical acceptance, m (PX4 NAV_MC_ALT_RAD).
    pub altitude_acceptance_m: f64,
    /// Yaw acceptance, degrees (PX4 MIS_YAW_ERR).
    pub yaw_acceptance_deg: f64,
    /// Gimbal settle tolerance before a capture, degrees.
    pub gimbal_settle_deg: f64,
    /// Longest wait for the gimbal before a capture, s.
    pub capture_max_wait_s: f64,
    /// Disarm this long after landing, s (PX4 COM_DISARM_LAND).
    pub disarm_after_land_s: f64,
    /// Disarm if armed on the ground without taking off for this long, s
    /// (PX4 COM_DISARM_PRFLT).
    pub disarm_preflight_s: f64,
    /// Battery: full voltage (V), empty voltage (V), capacity (mAh),
    /// hover current (A).
    pub battery: (f64, f64, f64, f64),
    /// The camera's video stream URI, announced in VIDEO_STREAM_INFORMATION
    /// (asked for with MAV_CMD_REQUEST_MESSAGE 269); unset: not announced.
    /// `rtsp://` is typed RTSP, `udp://` RTP/UDP (both H.264), else
    /// TCP_MPEG (the simulator's own MJPEG over HTTP).
    pub video_stream_uri: Option<String>,
    /// Telemetry stream intervals (MAVLink message id, seconds) replacing
    /// the defaults listed in the module documentation (e.g. PX4's rates
    /// on a telemetry radio, [`crate::realism::PX4_NORMAL_STREAMS`]).
    pub stream_intervals: Vec<(u32, f64)>,
}

impl AutopilotParams {
    /// The default interval of stream `id`, seconds (None: not a stream).
    pub fn default_interval(&self, id: u32) -> Option<f64> {
        self.stream_intervals
            .iter()
            .chain(STREAMS.iter())
            .find(|d| d.0 == id)
            .map(|d| d.1)
    }
}

impl Default for AutopilotParams {
    fn default() -> Self {
        Self {
            flavour: Flavour::Px4,
            system_id: 1,
            component_id: 1,
            vehicle: VehicleParams::default(),
            takeoff_alt_m: 2.5,
            rtl_alt_m: 30.0,
            acceptance_radius_m: 2.0,
            altitude_acceptance_m: 0.8,
            yaw_acceptance_deg: 12.0,
            gimbal_settle_deg: 1.0,
            capture_max_wait_s: 3.0,
            disarm_after_land_s: 2.0,
            disarm_preflight_s: 10.0,
            battery: (16.8, 13.6, 5000.0, 15.0),
            video_stream_uri: None,
            stream_intervals: Vec::new(),
        }
    }
}

/// Telemetry messages we can stream, with their default intervals (s).
const STREAMS: [(u32, f64); 12] = [
    (0, 1.0),   // HEARTBEAT
    (1, 1.0),   // SYS_STATUS
    (2, 1.0),   // SYSTEM_TIME
    (24, 1.0),  // GPS_RAW_INT
    (245, 1.0), // EXTENDED_SYS_STATE
    (42, 1.0),  // MISSION_CURRENT
    (30, 0.1),  // ATTITUDE
    (33, 0.2),  // GLOBAL_POSITION_INT
    (32, 0.2),  // LOCAL_POSITION_NED
    (285, 0.2), // GIMBAL_DEVICE_ATTITUDE_STATUS
    (242, 2.0), // HOME_POSITION
    (281, 2.0), // GIMBAL_MANAGER_STATUS
];

/// The gimbal device id the autopilot's gimbal manager answers for (a
/// non-MAVLink gimbal: ids 1 to 6).
pub const GIMBAL_DEVICE_ID: u8 = 1;

#[derive(Debug, Clone, Copy)]
struct Stream {
    id: u32,
    /// None = off.
    interval: Option<f64>,
    next: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum RtlStage {
    Climb,
    Return,
    Land,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Phase {
    /// Nothing to do (DO items complete at once).
    Instant,
    Takeoff {
        z: f64,
    },
    Goto {
        target: Vector3<f64>,
        yaw: Option<f64>,
        acc: f64,
        hold: f64,
        climb_first: bool,
    },
    Land {
        xy: Option<(f64, f64)>,
    },
    Rtl(RtlStage),
    WaitYaw {
        yaw: f64,
    },
    WaitGimbal {
        since: f64,
        then_capture: bool,
    },
}

#[derive(Debug, Clone, Copy)]
struct Exec {
    seq: Option<u16>,
    phase: Phase,
    reached_at: Option<f64>,
    done: bool,
}

impl Exec {
    fn reset() -> Self {
        Self {
            seq: None,
            phase: Phase::Instant,
            reached_at: None,
            done: false,
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct IntervalCapture {
    interval: f64,
    remaining: Option<u32>,
    next: f64,
}

/// The autopilot: vehicle, modes, mission store and executor, streams.
#[derive(Debug, Clone)]
pub struct Autopilot {
    params: AutopilotParams,
    vehicle: Vehicle,
    mission: MissionProtocol,
    mode: Mode,
    armed: bool,
    now: f64,
    unix_at_boot: f64,
    streams: Vec<Stream>,
    exec: Exec,
    hold_point: Option<(Vector3<f64>, f64)>,
    rtl: RtlStage,
    external: Option<Setpoint>,
    cruise_speed: Option<f64>,
    landed_since: Option<f64>,
    armed_at: f64,
    took_off: bool,
    captures: Vec<CaptureRequest>,
    next_image_index: i32,
    interval_capture: Option<IntervalCapture>,
    gcs: Option<Peer>,
    used_mah: f64,
    /// Who holds primary gimbal control (system, component); (0, 0): nobody.
    gimbal_primary: (u8, u8),
    /// Who holds secondary gimbal control.
    gimbal_secondary: (u8, u8),
    /// Mission PITCHYAW items refused (nobody suitable in control).
    gimbal_refusals: u32,
}

fn cmd_ack(to: Peer, command: MavCmd, result: MavResult) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        progress: 0,
        result_param2: 0,
        target_system: to.system,
        target_component: to.component,
    })
}

/// Gimbal device id param (param7) addresses our gimbal: 0 (all) or ours.
fn gimbal_device_ok(v: f32) -> bool {
    v.is_finite() && (v.round() == 0.0 || v.round() == f32::from(GIMBAL_DEVICE_ID))
}

/// A STATUSTEXT (cut to the 50 bytes the message holds).
fn statustext(severity: MavSeverity, text: &str) -> MavMessage {
    let mut t = String::new();
    for ch in text.chars() {
        if t.len() + ch.len_utf8() > 50 {
            break;
        }
        t.push(ch);
    }
    MavMessage::STATUSTEXT(STATUSTEXT_DATA {
        severity,
        text: t.as_str().into(),
        id: 0,
        chunk_seq: 0,
    })
}

fn quat_wxyz(q: &UnitQuaternion<f64>) -> [f32; 4] {
    [q.w as f32, q.i as f32, q.j as f32, q.k as f32]
}

/// The parameters of a COMMAND_LONG or COMMAND_INT, unified.
#[derive(Debug, Clone, Copy)]
struct Command {
    command: MavCmd,
    p: [f32; 7],
}

impl Autopilot {
    /// A landed, disarmed vehicle at home. `unix_at_boot` is the wall-clock
    /// time (Unix seconds) of sim time 0, used for SYSTEM_TIME and capture
    /// timestamps.
    pub fn new(params: AutopilotParams, unix_at_boot: f64) -> Self {
        let mp = MissionParams {
            system_id: params.system_id,
            component_id: params.component_id,
            ..MissionParams::for_flavour(params.flavour)
        };
        let vehicle = Vehicle::new(params.vehicle);
        Self {
            mission: MissionProtocol::new(mp, params.vehicle.home),
            vehicle,
            mode: match params.flavour {
                Flavour::Px4 => Mode::Position,
                Flavour::ArduPilot => Mode::Manual,
            },
            armed: false,
            now: 0.0,
            unix_at_boot,
            streams: STREAMS
                .iter()
                .map(|&(id, iv)| Stream {
                    id,
                    interval: Some(params.default_interval(id).unwrap_or(iv)),
                    next: 0.0,
                })
                .collect(),
            exec: Exec::reset(),
            hold_point: None,
            rtl: RtlStage::Climb,
            external: None,
            cruise_speed: None,
            landed_since: Some(0.0),
            armed_at: 0.0,
            took_off: false,
            captures: Vec::new(),
            next_image_index: 0,
            interval_capture: None,
            gcs: None,
            used_mah: 0.0,
            gimbal_primary: (0, 0),
            gimbal_secondary: (0, 0),
            gimbal_refusals: 0,
            params,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &AutopilotParams {
        &self.params
    }
    /// The vehicle.
    pub fn vehicle(&self) -> &Vehicle {
        &self.vehicle
    }
    /// The vehicle, mutable (tests and scripted starts).
    pub fn vehicle_mut(&mut self) -> &mut Vehicle {
        &mut self.vehicle
    }
    /// The mission store.
    pub fn mission(&self) -> &MissionProtocol {
        &self.mission
    }
    /// The flight mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }
    /// True when armed.
    pub fn armed(&self) -> bool {
        self.armed
    }
    /// Sim time since boot, s.
    pub fn now(&self) -> f64 {
        self.now
    }
    /// True when the mission has run to its end.
    pub fn mission_finished(&self) -> bool {
        self.exec.done
    }
    /// The ground station last heard from (the target of our messages).
    pub fn gcs(&self) -> Option<Peer> {
        self.gcs
    }
    /// Who holds primary gimbal control (system, component); (0, 0) nobody.
    pub fn gimbal_primary(&self) -> (u8, u8) {
        self.gimbal_primary
    }
    /// Mission gimbal commands refused because nobody suitable held control.
    pub fn gimbal_refusals(&self) -> u32 {
        self.gimbal_refusals
    }

    /// Capture requests produced since the last call.
    pub fn take_capture_requests(&mut self) -> Vec<CaptureRequest> {
        std::mem::take(&mut self.captures)
    }

    /// Arm (as COMPONENT_ARM_DISARM would). Returns false if refused.
    pub fn arm(&mut self) -> bool {
        if self.armed {
            return true;
        }
        if !self.vehicle.landed() {
            return false;
        }
        self.armed = true;
        self.armed_at = self.now;
        self.took_off = false;
        self.used_mah = self.used_mah.max(0.0);
        self.hold_point = None;
        if self.mode == Mode::Mission {
            self.exec = Exec::reset();
        }
        true
    }

    /// Disarm (refused in the air unless `force`).
    pub fn disarm(&mut self, force: bool) -> bool {
        if !self.vehicle.landed() && !force {
            return false;
        }
        self.armed = false;
        self.vehicle.set_setpoint(Setpoint::Idle);
        true
    }

    /// Change mode (as DO_SET_MODE would).
    pub fn set_mode(&mut self, mode: Mode) {
        if mode != self.mode {
            self.hold_point = None;
            if mode == Mode::Rtl {
                self.rtl = RtlStage::Climb;
            }
            if mode == Mode::Mission {
                self.exec = Exec::reset();
            }
            self.mode = mode;
        }
    }

    /// The setpoint followed in `Mode::Offboard` (the scripted operator).
    pub fn set_external_setpoint(&mut self, sp: Option<Setpoint>) {
        self.external = sp;
    }

    /// Point the gimbal (degrees, yaw relative to the body).
    pub fn set_gimbal(&mut self, pitch_deg: f64, yaw_deg: f64) {
        self.vehicle.set_gimbal_target(pitch_deg, yaw_deg);
    }

    fn header_peer(h: &MavHeader) -> Peer {
        Peer {
            system: h.system_id.min(255) as u8,
            component: h.component_id,
        }
    }

    fn for_us(&self, target_system: u8, target_component: u8) -> bool {
        let system = target_system == 0 || target_system == self.params.system_id;
        // The autopilot answers for itself and for its camera and gimbal.
        let component = matches!(target_component, 0 | 100 | 154)
            || target_component == self.params.component_id;
        system && component
    }

    /// Handle one received message; returns the replies.
    pub fn handle(&mut self, header: &MavHeader, msg: &MavMessage) -> Vec<MavMessage> {
        let from = Self::header_peer(header);
        let mut out = Vec::new();
        if let MavMessage::HEARTBEAT(hb) = msg {
            // Remember ground stations (not other vehicles).
            if hb.mavtype == MavType::MAV_TYPE_GCS {
                self.gcs = Some(from);
            }
            return out;
        }
        let cmd = match msg {
            MavMessage::COMMAND_LONG(c) if self.for_us(c.target_system, c.target_component) => {
                Some(Command {
                    command: c.command,
                    p: [
                        c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7,
                    ],
                })
            }
            MavMessage::COMMAND_INT(c) if self.for_us(c.target_system, c.target_component) => {
                Some(Command {
                    command: c.command,
                    p: [
                        c.param1, c.param2, c.param3, c.param4, c.x as f32, c.y as f32, c.z,
                    ],
                })
            }
            _ => None,
        };
        if let Some(c) = cmd {
            self.gcs.get_or_insert(from);
            let result = self.command(&c, from, &mut out);
            out.push(cmd_ack(from, c.command, result));
            return out;
        }
        if let MavMessage::REQUEST_DATA_STREAM(r) = msg
            && self.for_us(r.target_system, r.target_component)
        {
            self.request_data_stream(r.req_stream_id as u32, r.req_message_rate, r.start_stop);
            return out;
        }
        let replies = self.mission.handle(self.now, from, msg);
        if !replies.is_empty() {
            self.gcs.get_or_insert(from);
        }
        out.extend(replies);
        self.apply_mission_events(&mut out);
        out
    }

    fn apply_mission_events(&mut self, out: &mut Vec<MavMessage>) {
        for ev in self.mission.take_events() {
            match ev {
                MissionEvent::Stored { .. } | MissionEvent::Cleared => {
                    self.exec = Exec::reset();
                }
                MissionEvent::SetCurrent(_) => {
                    self.exec = Exec::reset();
                }
            }
        }
        let _ = out;
    }

    fn command(&mut self, c: &Command, from: Peer, out: &mut Vec<MavMessage>) -> MavResult {
        use MavCmd::*;
        let p = c.p;
        let ardu = self.params.flavour == Flavour::ArduPilot;
        match c.command {
            MAV_CMD_COMPONENT_ARM_DISARM => {
                let force = (p[1] - 21196.0).abs() < 0.5;
                let ok = if p[0] > 0.5 {
                    self.arm()
                } else {
                    self.disarm(force)
                };
                if ok {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MAV_CMD_DO_SET_MODE => {
                let base = p[0] as u32;
                if base & 1 == 0 {
                    return MavResult::MAV_RESULT_UNSUPPORTED;
                }
                let mode = if ardu {
                    Mode::from_ardupilot(p[1] as u32)
                } else {
                    Mode::from_px4(p[1] as u32, p[2] as u32)
                };
                match mode {
                    // Offboard needs a setpoint stream we do not take from
                    // MAVLink.
                    Some(Mode::Offboard) if !ardu && self.external.is_none() => {
                        MavResult::MAV_RESULT_DENIED
                    }
                    Some(m) => {
                        self.set_mode(m);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    None => MavResult::MAV_RESULT_UNSUPPORTED,
                }
            }
            MAV_CMD_MISSION_START => {
                let n = self.mission.items().len();
                if n <= usize::from(self.mission.first_item()) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                let first = p[0];
                if first.is_finite() && first >= 0.0 && (first as usize) < n && first > 0.0 {
                    self.mission.set_current(first as u16);
                } else if self.exec.done {
                    self.mission.set_current(self.mission.first_item());
                }
                self.mode = Mode::Mission;
                self.exec = Exec::reset();
                if ardu && !self.armed {
                    return MavResult::MAV_RESULT_DENIED;
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_SET_MISSION_CURRENT => {
                let seq = p[0];
                if seq.is_finite()
                    && seq >= f32::from(self.mission.first_item())
                    && (seq as usize) < self.mission.items().len()
                {
                    self.mission.set_current(seq as u16);
                    self.exec = Exec::reset();
                    out.push(self.mission_current_msg());
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MAV_CMD_NAV_TAKEOFF => {
                if !self.vehicle.landed() && self.took_off {
                    return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
                }
                if p[6].is_finite() && !ardu {
                    // PX4: param7 is AMSL.
                    self.params.takeoff_alt_m =
                        (f64::from(p[6]) - self.params.vehicle.home.alt_m).max(1.0);
                } else if p[6].is_finite() && ardu {
                    self.params.takeoff_alt_m = f64::from(p[6]).max(1.0);
                }
                self.set_mode(Mode::Takeoff);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_NAV_LAND => {
                self.set_mode(Mode::Land);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_NAV_RETURN_TO_LAUNCH => {
                self.set_mode(Mode::Rtl);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                if !gimbal_device_ok(p[6]) {
                    return MavResult::MAV_RESULT_FAILED;
                }
                if (from.system, from.component) != self.gimbal_primary {
                    out.push(self.gimbal_refused_text(from));
                    return MavResult::MAV_RESULT_DENIED;
                }
                self.gimbal_pitch_yaw(p[0], p[1], p[4]);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE => {
                if !gimbal_device_ok(p[6]) {
                    return MavResult::MAV_RESULT_FAILED;
                }
                match self.gimbal_configure(&p, from) {
                    Ok(()) => {
                        out.extend(self.build(281));
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    Err(()) => MavResult::MAV_RESULT_DENIED,
                }
            }
            MAV_CMD_DO_MOUNT_CONTROL => {
                self.vehicle
                    .set_gimbal_target(f64::from(p[0]), f64::from(p[2]));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_IMAGE_START_CAPTURE => {
                if !(p[1] >= 0.0 && p[2] >= 0.0) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                self.start_capture(f64::from(p[1]), p[2] as u32);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_IMAGE_STOP_CAPTURE => {
                self.interval_capture = None;
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_DIGICAM_CONTROL => {
                if (p[4] - 1.0).abs() < 0.5 {
                    self.capture_now();
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_CONDITION_YAW if ardu => {
                let yaw = self.condition_yaw_target(&p);
                let hold = self.hold_point.map_or(self.vehicle.p_ned(), |h| h.0);
                self.hold_point = Some((hold, yaw));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_CHANGE_SPEED => {
                if p[1] > 0.0 {
                    self.cruise_speed = Some(f64::from(p[1]));
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_SET_MESSAGE_INTERVAL => {
                let id = p[0] as u32;
                let us = p[1];
                let Some(s) = self.streams.iter_mut().find(|s| s.id == id) else {
                    return MavResult::MAV_RESULT_UNSUPPORTED;
                };
                let default = self.params.default_interval(id).unwrap_or(1.0);
                s.interval = if us < 0.0 {
                    None
                } else if us == 0.0 {
                    Some(default)
                } else {
                    Some((f64::from(us) * 1e-6).max(0.002))
                };
                s.next = self.now;
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_GET_MESSAGE_INTERVAL => {
                let id = p[0] as u32;
                let interval_us = self
                    .streams
                    .iter()
                    .find(|s| s.id == id)
                    .map_or(0, |s| s.interval.map_or(-1, |i| (i * 1e6).round() as i32));
                out.push(MavMessage::MESSAGE_INTERVAL(MESSAGE_INTERVAL_DATA {
                    interval_us,
                    message_id: id as u16,
                }));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_REQUEST_MESSAGE => match self.build(p[0] as u32) {
                Some(m) => {
                    out.push(m);
                    MavResult::MAV_RESULT_ACCEPTED
                }
                None => MavResult::MAV_RESULT_UNSUPPORTED,
            },
            MAV_CMD_GET_HOME_POSITION => {
                out.extend(self.build(242));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES => {
                out.extend(self.build(148));
                MavResult::MAV_RESULT_ACCEPTED
            }
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        }
    }

    /// The legacy REQUEST_DATA_STREAM (ArduPilot ground stations send it;
    /// PX4 ignores it): a stream group at a rate in Hz, or off.
    fn request_data_stream(&mut self, stream: u32, rate_hz: u16, start: u8) {
        if self.params.flavour != Flavour::ArduPilot {
            return;
        }
        // ArduPilot's groups, restricted to the messages we produce.
        let ids: &[u32] = match stream {
            0 => &[1, 24, 42, 30, 33, 32, 285, 2],
            2 => &[1, 24, 42],
            6 => &[33, 32],
            10 => &[30],
            12 => &[2, 285],
            _ => &[],
        };
        for s in self.streams.iter_mut().filter(|s| ids.contains(&s.id)) {
            s.interval = if start == 0 || rate_hz == 0 {
                None
            } else {
                Some(1.0 / f64::from(rate_hz))
            };
            s.next = self.now;
        }
    }

    fn condition_yaw_target(&self, p: &[f32; 7]) -> f64 {
        let angle = f64::from(p[0]).to_radians();
        if p[3] > 0.5 {
            let dir = if p[2] < 0.0 { -1.0 } else { 1.0 };
            wrap_pi(self.vehicle.yaw() + dir * angle)
        } else {
            wrap_pi(angle)
        }
    }

    fn gimbal_pitch_yaw(&mut self, pitch: f32, yaw: f32, flags: f32) {
        let earth_frame = (flags as u32) & 16 != 0;
        let yaw = if earth_frame && yaw.is_finite() {
            wrap_pi(f64::from(yaw).to_radians() - self.vehicle.yaw()).to_degrees()
        } else {
            f64::from(yaw)
        };
        self.vehicle.set_gimbal_target(f64::from(pitch), yaw);
    }

    /// DO_GIMBAL_MANAGER_CONFIGURE from `from` (params as in the command):
    /// the new primary and secondary controllers. Err for a value out of range.
    fn gimbal_configure(&mut self, p: &[f32; 7], from: Peer) -> Result<(), ()> {
        let pick = |v: f32, current: u8, own: u8, held_by_sender: bool| -> Result<u8, ()> {
            if !v.is_finite() {
                return Err(());
            }
            match v.round() as i32 {
                x @ 0..=255 => Ok(x as u8),
                -1 => Ok(current),
                -2 => Ok(own),
                -3 if held_by_sender => Ok(0),
                -3 => Ok(current),
                _ => Err(()),
            }
        };
        let held = self.gimbal_primary == (from.system, from.component);
        let primary = (
            pick(p[0], self.gimbal_primary.0, from.system, held)?,
            pick(p[1], self.gimbal_primary.1, from.component, held)?,
        );
        let held2 = self.gimbal_secondary == (from.system, from.component);
        let secondary = (
            pick(p[2], self.gimbal_secondary.0, from.system, held2)?,
            pick(p[3], self.gimbal_secondary.1, from.component, held2)?,
        );
        self.gimbal_primary = primary;
        self.gimbal_secondary = secondary;
        Ok(())
    }

    /// The autopilot itself as a MAVLink peer (the sender of mission commands).
    fn own_peer(&self) -> Peer {
        Peer {
            system: self.params.system_id,
            component: self.params.component_id,
        }
    }

    /// Whether a mission gimbal command may move the gimbal (see the module
    /// documentation).
    fn mission_gimbal_allowed(&self) -> bool {
        let own = self.own_peer();
        let holder = self.gimbal_primary;
        if holder == (own.system, own.component) {
            return true;
        }
        self.params.flavour == Flavour::ArduPilot
            && holder != (0, 0)
            && self.gcs.is_some_and(|g| (g.system, g.component) == holder)
    }

    fn gimbal_refused_text(&self, from: Peer) -> MavMessage {
        let (s, c) = self.gimbal_primary;
        statustext(
            MavSeverity::MAV_SEVERITY_WARNING,
            &format!(
                "Gimbal: PITCHYAW from {}/{} denied, in control: {s}/{c}",
                from.system, from.component
            ),
        )
    }

    /// IMAGE_START_CAPTURE as a camera component takes it: `total`
    /// pictures (0: until stopped) `interval` s apart, the first now.
    pub fn start_image_capture(&mut self, interval: f64, total: u32) {
        self.start_capture(interval, total);
    }

    /// IMAGE_STOP_CAPTURE.
    pub fn stop_image_capture(&mut self) {
        self.interval_capture = None;
    }

    /// The camera's VIDEO_STREAM_INFORMATION, when it announces a stream.
    pub fn video_stream_information(&self) -> Option<MavMessage> {
        self.build(269)
    }

    fn start_capture(&mut self, interval: f64, total: u32) {
        self.capture_now();
        if total == 1 {
            self.interval_capture = None;
            return;
        }
        let interval = interval.max(0.1);
        self.interval_capture = Some(IntervalCapture {
            interval,
            remaining: if total == 0 { None } else { Some(total - 1) },
            next: self.now + interval,
        });
    }

    fn capture_now(&mut self) {
        let g = self.vehicle.geodetic();
        // The picture is taken from where the camera truly is; the position
        // reported with it is the GPS's.
        let wfc = self.vehicle.true_world_from_cam();
        let q = self.vehicle.world_from_gimbal_rotation();
        self.captures.push(CaptureRequest {
            index: self.next_image_index,
            time_boot_s: self.now,
            time_unix_s: self.unix_at_boot + self.now,
            world_from_cam: wfc,
            geodetic: g,
            relative_alt_m: -self.vehicle.p_ned().z,
            q: quat_wxyz(&q),
        });
        self.next_image_index += 1;
    }

    /// The CAMERA_IMAGE_CAPTURED for a finished capture (`file_url` None if
    /// storing failed).
    pub fn capture_done(&self, req: &CaptureRequest, file_url: Option<&str>) -> MavMessage {
        let url = file_url.unwrap_or("");
        let url: String = url.chars().take(204).collect();
        MavMessage::CAMERA_IMAGE_CAPTURED(CAMERA_IMAGE_CAPTURED_DATA {
            time_utc: (req.time_unix_s * 1e6) as u64,
            time_boot_ms: (req.time_boot_s * 1e3) as u32,
            lat: (req.geodetic.lat_deg * 1e7).round() as i32,
            lon: (req.geodetic.lon_deg * 1e7).round() as i32,
            alt: (req.geodetic.alt_m * 1e3).round() as i32,
            relative_alt: (req.relative_alt_m * 1e3).round() as i32,
            q: req.q,
            image_index: req.index,
            camera_id: 0,
            capture_result: if file_url.is_some() {
                MavBool::MAV_BOOL_TRUE
            } else {
                MavBool::MAV_BOOL_FALSE
            },
            file_url: url.as_str().into(),
        })
    }

    /// Advance the simulation to `now` (seconds since boot) by one step of
    /// `dt`; returns telemetry and mission messages to send.
    pub fn step(&mut self, now: f64, dt: f64) -> Vec<MavMessage> {
        self.now = now;
        let mut out = Vec::new();
        self.control(&mut out);
        self.vehicle.step(dt);
        self.bookkeeping(dt);
        if let Some(ic) = &mut self.interval_capture
            && now >= ic.next
        {
            ic.next += ic.interval;
            let done = match &mut ic.remaining {
                Some(0) => true,
                Some(n) => {
                    *n -= 1;
                    *n == 0
                }
                None => false,
            };
            if done {
                self.interval_capture = None;
            }
            self.capture_now();
        }
        out.extend(self.mission.tick(now));
        self.apply_mission_events(&mut out);
        for i in 0..self.streams.len() {
            let s = self.streams[i];
            if let Some(iv) = s.interval
                && now >= s.next
            {
                self.streams[i].next = if now - s.next > iv {
                    now + iv
                } else {
                    s.next + iv
                };
                out.extend(self.build(s.id));
            }
        }
        out
    }

    fn bookkeeping(&mut self, dt: f64) {
        let landed = self.vehicle.landed();
        if !landed {
            self.took_off = true;
            self.landed_since = None;
        } else if self.landed_since.is_none() {
            self.landed_since = Some(self.now);
        }
        if self.armed {
            self.used_mah += self.params.battery.3 * dt / 3.6;
            if landed {
                let since = self.landed_since.unwrap_or(self.now);
                if self.took_off && self.now - since >= self.params.disarm_after_land_s {
                    self.armed = false;
                    self.took_off = false;
                    if matches!(self.mode, Mode::Land | Mode::Rtl) {
                        self.set_mode(match self.params.flavour {
                            Flavour::Px4 => Mode::Hold,
                            Flavour::ArduPilot => Mode::Land,
                        });
                    }
                } else if !self.took_off
                    && self.now - self.armed_at >= self.params.disarm_preflight_s
                    && !self.wants_to_fly()
                {
                    self.armed = false;
                }
            }
        }
    }

    /// True when the current mode will lift off from the ground.
    fn wants_to_fly(&self) -> bool {
        match self.mode {
            Mode::Takeoff => true,
            Mode::Mission => {
                !self.exec.done
                    && self.mission.items().len() > usize::from(self.mission.first_item())
            }
            Mode::Offboard => self.external.is_some(),
            _ => false,
        }
    }

    fn hold_here(&mut self) -> Setpoint {
        let (p, yaw) = *self
            .hold_point
            .get_or_insert((self.vehicle.p_ned(), self.vehicle.yaw()));
        Setpoint::Position {
            p_ned: p,
            yaw: Some(yaw),
            max_speed: None,
        }
    }

    fn control(&mut self, out: &mut Vec<MavMessage>) {
        if !self.armed {
            self.vehicle.set_setpoint(Setpoint::Idle);
            return;
        }
        let sp = match self.mode {
            Mode::Manual | Mode::Position | Mode::Hold => {
                if self.vehicle.landed() {
                    Setpoint::Idle
                } else {
                    self.hold_here()
                }
            }
            Mode::Offboard => match self.external {
                Some(sp) => sp,
                None => self.hold_here(),
            },
            Mode::Takeoff => {
                let p = self.vehicle.p_ned();
                let z = -self.params.takeoff_alt_m;
                if (p.z - z).abs() < self.params.altitude_acceptance_m * 0.25 {
                    self.hold_point = Some((Vector3::new(p.x, p.y, z), self.vehicle.yaw()));
                    self.mode = Mode::Hold;
                    self.hold_here()
                } else {
                    Setpoint::Position {
                        p_ned: Vector3::new(p.x, p.y, z),
                        yaw: None,
                        max_speed: None,
                    }
                }
            }
            Mode::Land => Setpoint::Land,
            Mode::Rtl => self.rtl_setpoint(),
            Mode::Mission => self.mission_setpoint(out),
        };
        // Do not leave the ground in hold-type modes.
        self.vehicle.set_setpoint(sp);
    }

    fn rtl_setpoint(&mut self) -> Setpoint {
        let p = self.vehicle.p_ned();
        let rtl_z = -self.params.rtl_alt_m;
        let z = p.z.min(rtl_z);
        let speed = self.cruise_speed;
        loop {
            match self.rtl {
                RtlStage::Climb => {
                    if p.z <= rtl_z + 0.5 || (p.x.hypot(p.y) < 1.0) {
                        self.rtl = RtlStage::Return;
                        continue;
                    }
                    return Setpoint::Position {
                        p_ned: Vector3::new(p.x, p.y, rtl_z),
                        yaw: None,
                        max_speed: speed,
                    };
                }
                RtlStage::Return => {
                    if p.x.hypot(p.y) < 0.5 {
                        self.rtl = RtlStage::Land;
                        continue;
                    }
                    let yaw = if p.x.hypot(p.y) > 2.0 {
                        Some((-p.y).atan2(-p.x))
                    } else {
                        None
                    };
                    return Setpoint::Position {
                        p_ned: Vector3::new(0.0, 0.0, z),
                        yaw,
                        max_speed: speed,
                    };
                }
                RtlStage::Land => return Setpoint::Land,
            }
        }
    }

    fn item_target(&self, item: &MissionItem) -> Vector3<f64> {
        let home = self.params.vehicle.home;
        let alt = if mission::is_relative_alt(item.frame) {
            home.alt_m + f64::from(item.z)
        } else {
            f64::from(item.z)
        };
        let (lat, lon) = if item.x == 0.0 && item.y == 0.0 {
            let g = self.vehicle.geodetic();
            (g.lat_deg, g.lon_deg)
        } else {
            (item.x, item.y)
        };
        self.vehicle.frame().geodetic_to_ned(&Geodetic {
            lat_deg: lat,
            lon_deg: lon,
            alt_m: alt,
        })
    }

    fn mission_current_msg(&self) -> MavMessage {
        let n = self.mission.items().len();
        let state = if n <= usize::from(self.mission.first_item()) {
            MissionState::MISSION_STATE_NO_MISSION
        } else if self.exec.done {
            MissionState::MISSION_STATE_COMPLETE
        } else if self.mode == Mode::Mission && self.armed {
            MissionState::MISSION_STATE_ACTIVE
        } else if self.exec.seq.is_some() {
            MissionState::MISSION_STATE_PAUSED
        } else {
            MissionState::MISSION_STATE_NOT_STARTED
        };
        self.mission.mission_current(state)
    }

    fn start_item(&mut self, seq: u16, out: &mut Vec<MavMessage>) {
        let Some(item) = self.mission.items().get(usize::from(seq)).cloned() else {
            return;
        };
        use MavCmd::*;
        let p = item.params;
        let phase = match item.command {
            MAV_CMD_NAV_TAKEOFF => {
                let t = self.item_target(&item);
                Phase::Takeoff { z: t.z.min(-1.0) }
            }
            MAV_CMD_NAV_WAYPOINT => {
                let target = self.item_target(&item);
                let yaw = if p[3].is_finite() {
                    Some(wrap_pi(f64::from(p[3]).to_radians()))
                } else {
                    None
                };
                Phase::Goto {
                    target,
                    yaw,
                    acc: if p[1] > 0.0 {
                        f64::from(p[1])
                    } else {
                        self.params.acceptance_radius_m
                    },
                    hold: f64::from(p[0]).max(0.0),
                    climb_first: self.vehicle.landed(),
                }
            }
            MAV_CMD_NAV_LAND => {
                let xy = if item.x != 0.0 || item.y != 0.0 {
                    let t = self.item_target(&item);
                    Some((t.x, t.y))
                } else {
                    None
                };
                Phase::Land { xy }
            }
            MAV_CMD_NAV_RETURN_TO_LAUNCH => Phase::Rtl(RtlStage::Climb),
            MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                if self.mission_gimbal_allowed() {
                    self.gimbal_pitch_yaw(p[0], p[1], item.x as f32);
                } else {
                    self.gimbal_refusals += 1;
                    out.push(self.gimbal_refused_text(self.own_peer()));
                }
                Phase::Instant
            }
            MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE => {
                let pp = [p[0], p[1], p[2], p[3], item.x as f32, item.y as f32, item.z];
                let own = self.own_peer();
                if self.gimbal_configure(&pp, own).is_ok() {
                    out.extend(self.build(281));
                }
                Phase::Instant
            }
            MAV_CMD_DO_MOUNT_CONTROL => {
                self.vehicle
                    .set_gimbal_target(f64::from(p[0]), f64::from(p[2]));
                Phase::Instant
            }
            MAV_CMD_IMAGE_START_CAPTURE => {
                if p[2] as u32 == 1 {
                    Phase::WaitGimbal {
                        since: self.now,
                        then_capture: true,
                    }
                } else {
                    self.start_capture(f64::from(p[1]), p[2] as u32);
                    Phase::Instant
                }
            }
            MAV_CMD_IMAGE_STOP_CAPTURE => {
                self.interval_capture = None;
                Phase::Instant
            }
            MAV_CMD_DO_DIGICAM_CONTROL => {
                if (item.x - 1.0).abs() < 0.5 {
                    Phase::WaitGimbal {
                        since: self.now,
                        then_capture: true,
                    }
                } else {
                    Phase::Instant
                }
            }
            MAV_CMD_CONDITION_YAW => {
                let mut pp = [0.0f32; 7];
                pp[..4].copy_from_slice(&p);
                Phase::WaitYaw {
                    yaw: self.condition_yaw_target(&pp),
                }
            }
            MAV_CMD_DO_CHANGE_SPEED => {
                if p[1] > 0.0 {
                    self.cruise_speed = Some(f64::from(p[1]));
                }
                Phase::Instant
            }
            _ => Phase::Instant,
        };
        if matches!(phase, Phase::Rtl(_)) {
            self.rtl = RtlStage::Climb;
        }
        self.exec.seq = Some(seq);
        self.exec.phase = phase;
        self.exec.reached_at = None;
        // The position held by non-moving items.
        if !matches!(phase, Phase::Goto { .. } | Phase::Takeoff { .. }) && !self.vehicle.landed() {
            self.hold_point
                .get_or_insert((self.vehicle.p_ned(), self.vehicle.yaw()));
        }
    }

    fn mission_setpoint(&mut self, out: &mut Vec<MavMessage>) -> Setpoint {
        let n = self.mission.items().len();
        if n <= usize::from(self.mission.first_item()) || self.exec.done {
            return if self.vehicle.landed() {
                Setpoint::Idle
            } else {
                self.hold_here()
            };
        }
        let cur = self.mission.current();
        if self.exec.seq != Some(cur) {
            if usize::from(cur) >= n {
                self.exec.done = true;
                out.push(self.mission_current_msg());
                return self.hold_here();
            }
            self.start_item(cur, out);
            out.push(self.mission_current_msg());
        }
        let p = self.vehicle.p_ned();
        let yaw_ok = |target: Option<f64>, yaw: f64, tol: f64| {
            target.is_none_or(|t| wrap_pi(t - yaw).abs() <= tol.to_radians())
        };
        let (sp, complete) = match self.exec.phase {
            Phase::Instant => (self.hold_or_idle(), true),
            Phase::Takeoff { z } => {
                // As PX4: reached once at or above the takeoff altitude (a
                // vehicle already flying higher does not descend).
                let z = if self.vehicle.landed() { z } else { z.min(p.z) };
                let target = Vector3::new(p.x, p.y, z);
                let done = p.z <= z + self.params.altitude_acceptance_m;
                if done {
                    self.hold_point =
                        Some((Vector3::new(p.x, p.y, p.z.min(z)), self.vehicle.yaw()));
                }
                (
                    Setpoint::Position {
                        p_ned: target,
                        yaw: None,
                        max_speed: None,
                    },
                    done,
                )
            }
            Phase::Goto {
                target,
                yaw,
                acc,
                hold,
                climb_first,
            } => {
                if climb_first {
                    if (p.z - target.z).abs() <= self.params.altitude_acceptance_m {
                        self.exec.phase = Phase::Goto {
                            target,
                            yaw,
                            acc,
                            hold,
                            climb_first: false,
                        };
                    }
                    (
                        Setpoint::Position {
                            p_ned: Vector3::new(p.x, p.y, target.z),
                            yaw: None,
                            max_speed: None,
                        },
                        false,
                    )
                } else {
                    let d_xy = (target.x - p.x).hypot(target.y - p.y);
                    let d_z = (target.z - p.z).abs();
                    let sp_yaw = match yaw {
                        Some(y) => Some(y),
                        None if d_xy > 2.0 => Some((target.y - p.y).atan2(target.x - p.x)),
                        None => None,
                    };
                    let arrived = d_xy <= acc
                        && d_z <= self.params.altitude_acceptance_m
                        && yaw_ok(yaw, self.vehicle.yaw(), self.params.yaw_acceptance_deg);
                    if arrived && self.exec.reached_at.is_none() {
                        self.exec.reached_at = Some(self.now);
                        out.push(MavMessage::MISSION_ITEM_REACHED(
                            MISSION_ITEM_REACHED_DATA { seq: cur },
                        ));
                    }
                    let held = self.exec.reached_at.is_some_and(|t| self.now - t >= hold);
                    (
                        Setpoint::Position {
                            p_ned: target,
                            yaw: sp_yaw,
                            max_speed: self.cruise_speed,
                        },
                        held,
                    )
                }
            }
            Phase::Land { xy } => {
                if let Some((x, y)) = xy
                    && (x - p.x).hypot(y - p.y) > 0.5
                    && !self.vehicle.landed()
                {
                    (
                        Setpoint::Position {
                            p_ned: Vector3::new(x, y, p.z),
                            yaw: None,
                            max_speed: self.cruise_speed,
                        },
                        false,
                    )
                } else {
                    (Setpoint::Land, self.vehicle.landed())
                }
            }
            Phase::Rtl(_) => {
                let sp = self.rtl_setpoint();
                (sp, self.vehicle.landed() && self.rtl == RtlStage::Land)
            }
            Phase::WaitYaw { yaw } => {
                let sp = match self.hold_or_idle() {
                    Setpoint::Position {
                        p_ned, max_speed, ..
                    } => Setpoint::Position {
                        p_ned,
                        yaw: Some(yaw),
                        max_speed,
                    },
                    s => s,
                };
                let ok = yaw_ok(Some(yaw), self.vehicle.yaw(), 2.0) || self.vehicle.landed();
                if ok && let Some(h) = &mut self.hold_point {
                    h.1 = yaw;
                }
                (sp, ok)
            }
            Phase::WaitGimbal {
                since,
                then_capture,
            } => {
                let ok = self.vehicle.gimbal_settled(self.params.gimbal_settle_deg)
                    || self.now - since >= self.params.capture_max_wait_s;
                if ok && then_capture {
                    self.capture_now();
                }
                (self.hold_or_idle(), ok)
            }
        };
        if complete {
            let is_nav_goto = matches!(self.exec.phase, Phase::Goto { .. });
            if !is_nav_goto {
                out.push(MavMessage::MISSION_ITEM_REACHED(
                    MISSION_ITEM_REACHED_DATA { seq: cur },
                ));
            }
            if matches!(self.exec.phase, Phase::Goto { .. } | Phase::Takeoff { .. }) {
                let yaw = self.vehicle.yaw();
                if let Setpoint::Position { p_ned, yaw: y, .. } = sp {
                    self.hold_point = Some((p_ned, y.unwrap_or(yaw)));
                }
            }
            if usize::from(cur) + 1 < n {
                self.mission.set_current(cur + 1);
            } else {
                self.exec.done = true;
                out.push(self.mission_current_msg());
            }
        }
        sp
    }

    fn hold_or_idle(&mut self) -> Setpoint {
        if self.vehicle.landed() {
            Setpoint::Idle
        } else {
            self.hold_here()
        }
    }

    fn base_mode(&self) -> MavModeFlag {
        let mut f = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        if self.armed {
            f |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        f |= MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED;
        match self.mode {
            Mode::Manual => f |= MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,
            Mode::Position => {
                f |= MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
            }
            Mode::Offboard => f |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED,
            _ => {
                f |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED
            }
        }
        f
    }

    fn time_boot_ms(&self) -> u32 {
        (self.now * 1e3) as u32
    }

    /// Build one telemetry message by id (None if we do not produce it).
    pub fn build(&self, id: u32) -> Option<MavMessage> {
        let v = &self.vehicle;
        let p = v.p_ned();
        let vel = v.v_ned();
        let g = v.geodetic();
        let home = self.params.vehicle.home;
        let t_ms = self.time_boot_ms();
        Some(match id {
            0 => MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: match self.params.flavour {
                    Flavour::Px4 => self.mode.px4_custom_mode(),
                    Flavour::ArduPilot => self.mode.ardupilot_custom_mode(),
                },
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                autopilot: match self.params.flavour {
                    Flavour::Px4 => MavAutopilot::MAV_AUTOPILOT_PX4,
                    Flavour::ArduPilot => MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                },
                base_mode: self.base_mode(),
                system_status: if self.armed {
                    MavState::MAV_STATE_ACTIVE
                } else {
                    MavState::MAV_STATE_STANDBY
                },
                mavlink_version: 3,
            }),
            1 => {
                let (v_full, v_empty, cap, _) = self.params.battery;
                let frac = (1.0 - self.used_mah / cap).clamp(0.0, 1.0);
                let sensors = MavSysStatusSensor::from_bits_truncate(
                    0x1 | 0x2
                        | 0x4
                        | 0x8
                        | 0x20
                        | 0x400
                        | 0x800
                        | 0x1000
                        | 0x2000
                        | 0x4000
                        | 0x8000
                        | 0x200000
                        | 0x2000000,
                );
                MavMessage::SYS_STATUS(SYS_STATUS_DATA {
                    onboard_control_sensors_present: sensors,
                    onboard_control_sensors_enabled: sensors,
                    onboard_control_sensors_health: sensors,
                    load: 250,
                    voltage_battery: ((v_empty + (v_full - v_empty) * frac) * 1e3) as u16,
                    current_battery: if self.armed {
                        (self.params.battery.3 * 100.0) as i16
                    } else {
                        50
                    },
                    drop_rate_comm: 0,
                    errors_comm: 0,
                    errors_count1: 0,
                    errors_count2: 0,
                    errors_count3: 0,
                    errors_count4: 0,
                    battery_remaining: (frac * 100.0).round() as i8,
                    onboard_control_sensors_present_extended: MavSysStatusSensorExtended::empty(),
                    onboard_control_sensors_enabled_extended: MavSysStatusSensorExtended::empty(),
                    onboard_control_sensors_health_extended: MavSysStatusSensorExtended::empty(),
                })
            }
            2 => MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
                time_unix_usec: ((self.unix_at_boot + self.now) * 1e6) as u64,
                time_boot_ms: t_ms,
            }),
            24 => MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
                time_usec: (self.now * 1e6) as u64,
                lat: (g.lat_deg * 1e7).round() as i32,
                lon: (g.lon_deg * 1e7).round() as i32,
                alt: (g.alt_m * 1e3).round() as i32,
                eph: 70,
                epv: 100,
                vel: (vel.x.hypot(vel.y) * 100.0) as u16,
                cog: ((vel.y.atan2(vel.x).to_degrees().rem_euclid(360.0)) * 100.0) as u16,
                fix_type: if v.gps_fix() {
                    GpsFixType::GPS_FIX_TYPE_3D_FIX
                } else {
                    GpsFixType::GPS_FIX_TYPE_NO_FIX
                },
                satellites_visible: if v.gps_fix() { 14 } else { 0 },
                alt_ellipsoid: (g.alt_m * 1e3).round() as i32,
                // The receiver's reported accuracy: the error model's
                // sigmas, never better than a plain receiver's 0.5 / 0.8 m.
                h_acc: (v.gps_reported_accuracy().0.max(0.5) * 1e3).round() as u32,
                v_acc: (v.gps_reported_accuracy().1.max(0.8) * 1e3).round() as u32,
                vel_acc: 200,
                hdg_acc: 0,
                yaw: 0,
            }),
            245 => MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
                vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
                landed_state: if v.landed() {
                    MavLandedState::MAV_LANDED_STATE_ON_GROUND
                } else if self.mode == Mode::Land
                    || matches!(self.exec.phase, Phase::Land { .. }) && self.mode == Mode::Mission
                {
                    MavLandedState::MAV_LANDED_STATE_LANDING
                } else {
                    MavLandedState::MAV_LANDED_STATE_IN_AIR
                },
            }),
            42 => self.mission_current_msg(),
            30 => {
                let (roll, pitch) = v.roll_pitch();
                MavMessage::ATTITUDE(ATTITUDE_DATA {
                    time_boot_ms: t_ms,
                    roll: roll as f32,
                    pitch: pitch as f32,
                    yaw: v.yaw() as f32,
                    rollspeed: 0.0,
                    pitchspeed: 0.0,
                    yawspeed: v.yaw_rate() as f32,
                })
            }
            // No global position while the GNSS fix is lost.
            33 if !v.gps_fix() => return None,
            33 => MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                time_boot_ms: t_ms,
                lat: (g.lat_deg * 1e7).round() as i32,
                lon: (g.lon_deg * 1e7).round() as i32,
                alt: (g.alt_m * 1e3).round() as i32,
                relative_alt: (-p.z * 1e3).round() as i32,
                vx: (vel.x * 100.0).round() as i16,
                vy: (vel.y * 100.0).round() as i16,
                vz: (vel.z * 100.0).round() as i16,
                hdg: (v.yaw().to_degrees().rem_euclid(360.0) * 100.0).round() as u16 % 36000,
            }),
            32 => MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: t_ms,
                x: p.x as f32,
                y: p.y as f32,
                z: p.z as f32,
                vx: vel.x as f32,
                vy: vel.y as f32,
                vz: vel.z as f32,
            }),
            285 => {
                let (rp, ry) = v.gimbal_rates();
                MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(GIMBAL_DEVICE_ATTITUDE_STATUS_DATA {
                    time_boot_ms: t_ms,
                    q: quat_wxyz(&v.gimbal_rotation_in_vehicle_frame()),
                    angular_velocity_x: 0.0,
                    angular_velocity_y: rp as f32,
                    angular_velocity_z: ry as f32,
                    failure_flags: GimbalDeviceErrorFlags::empty(),
                    flags: GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_ROLL_LOCK
                        | GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_PITCH_LOCK
                        | GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME,
                    target_system: 0,
                    target_component: 0,
                    delta_yaw: v.gimbal_angles().1 as f32,
                    delta_yaw_velocity: ry as f32,
                    gimbal_device_id: 1,
                })
            }
            280 => {
                let g = &self.params.vehicle.gimbal;
                MavMessage::GIMBAL_MANAGER_INFORMATION(GIMBAL_MANAGER_INFORMATION_DATA {
                    time_boot_ms: t_ms,
                    cap_flags: GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_PITCH_AXIS
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_PITCH_LOCK
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_ROLL_LOCK
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_YAW_AXIS
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_YAW_FOLLOW,
                    roll_min: 0.0,
                    roll_max: 0.0,
                    pitch_min: g.pitch_min_deg.to_radians() as f32,
                    pitch_max: g.pitch_max_deg.to_radians() as f32,
                    yaw_min: g.yaw_min_deg.to_radians() as f32,
                    yaw_max: g.yaw_max_deg.to_radians() as f32,
                    gimbal_device_id: GIMBAL_DEVICE_ID,
                })
            }
            281 => MavMessage::GIMBAL_MANAGER_STATUS(GIMBAL_MANAGER_STATUS_DATA {
                time_boot_ms: t_ms,
                flags: GimbalManagerFlags::GIMBAL_MANAGER_FLAGS_ROLL_LOCK
                    | GimbalManagerFlags::GIMBAL_MANAGER_FLAGS_PITCH_LOCK
                    | GimbalManagerFlags::GIMBAL_MANAGER_FLAGS_YAW_IN_VEHICLE_FRAME,
                gimbal_device_id: GIMBAL_DEVICE_ID,
                primary_control_sysid: self.gimbal_primary.0,
                primary_control_compid: self.gimbal_primary.1,
                secondary_control_sysid: self.gimbal_secondary.0,
                secondary_control_compid: self.gimbal_secondary.1,
            }),
            242 => MavMessage::HOME_POSITION(HOME_POSITION_DATA {
                latitude: (home.lat_deg * 1e7).round() as i32,
                longitude: (home.lon_deg * 1e7).round() as i32,
                altitude: (home.alt_m * 1e3).round() as i32,
                x: 0.0,
                y: 0.0,
                z: 0.0,
                q: [1.0, 0.0, 0.0, 0.0],
                approach_x: 0.0,
                approach_y: 0.0,
                approach_z: 0.0,
                time_usec: (self.now * 1e6) as u64,
            }),
            148 => MavMessage::AUTOPILOT_VERSION(AUTOPILOT_VERSION_DATA {
                capabilities: MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_INT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MAVLINK2,
                uid: 0x5107_5107,
                flight_sw_version: 0x010f_0000,
                middleware_sw_version: 0,
                os_sw_version: 0,
                board_version: 0,
                vendor_id: 0,
                product_id: 0,
                flight_custom_version: [0; 8],
                middleware_custom_version: [0; 8],
                os_custom_version: [0; 8],
                uid2: [0; 18],
            }),
            269 => {
                use mavlink::dialects::common::{
                    VIDEO_STREAM_INFORMATION_DATA, VideoStreamEncoding, VideoStreamStatusFlags,
                    VideoStreamType,
                };
                let uri = self.params.video_stream_uri.as_deref()?;
                let (mavtype, encoding) = if uri.starts_with("rtsp://") {
                    (
                        VideoStreamType::VIDEO_STREAM_TYPE_RTSP,
                        VideoStreamEncoding::VIDEO_STREAM_ENCODING_H264,
                    )
                } else if uri.starts_with("udp://") {
                    (
                        VideoStreamType::VIDEO_STREAM_TYPE_RTPUDP,
                        VideoStreamEncoding::VIDEO_STREAM_ENCODING_H264,
                    )
                } else {
                    (
                        VideoStreamType::VIDEO_STREAM_TYPE_TCP_MPEG,
                        VideoStreamEncoding::VIDEO_STREAM_ENCODING_UNKNOWN,
                    )
                };
                MavMessage::VIDEO_STREAM_INFORMATION(VIDEO_STREAM_INFORMATION_DATA {
                    framerate: 0.0,
                    bitrate: 0,
                    flags: VideoStreamStatusFlags::VIDEO_STREAM_STATUS_FLAGS_RUNNING,
                    resolution_h: 0,
                    resolution_v: 0,
                    rotation: 0,
                    hfov: 0,
                    stream_id: 1,
                    count: 1,
                    mavtype,
                    name: "shotpilot-sim camera".into(),
                    uri: uri.into(),
                    encoding,
                    camera_device_id: 0,
                })
            }
            _ => return None,
        })
    }
}

#[cfg(test)]
mod tests;
