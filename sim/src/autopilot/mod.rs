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
//! Guided control (`offboard`): SET_POSITION_TARGET_LOCAL_NED and
//! SET_POSITION_TARGET_GLOBAL_INT flown in OFFBOARD (PX4: only after a
//! setpoint stream of a second, left for a hold when the stream stops for
//! `offboard_loss_s`) or GUIDED (ArduPilot: the last target held).
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
//!
//! The files: `mode` the flight modes; `commands` the commands answered;
//! `gimbal` the gimbal manager; `camera` image captures; `offboard` guided control;
//! `flight` mission execution and the setpoints flown; `telemetry` the streams and the messages
//! built; `mission` the mission protocol. This file holds the parameters, the
//! autopilot's state, the received messages dispatched and the clock stepped.

#![allow(deprecated)]
// The legacy mission messages (MISSION_ITEM, MISSION_REQUEST,
// MISSION_SET_CURRENT) and DO_MOUNT_CONTROL are deprecated in the dialect
// but still spoken by real autopilots and ground stations: we implement them
// on purpose.

mod camera;
mod commands;
mod flight;
mod gimbal;
pub mod mission;
mod mode;
mod offboard;
mod telemetry;

use mavlink::MavHeader;
use mavlink::dialects::common::{MavMessage, MavType};
use nalgebra::Vector3;

use self::camera::IntervalCapture;
use self::commands::{Command, cmd_ack};
use self::flight::{Exec, RtlStage};
use self::offboard::OffboardStream;
use self::telemetry::{STREAMS, Stream};
use crate::vehicle::{Setpoint, Vehicle, VehicleParams};
pub use camera::CaptureRequest;
pub use gimbal::GIMBAL_DEVICE_ID;
pub use mission::{Flavour, MissionEvent, MissionItem, MissionParams, MissionProtocol, Peer};
pub use mode::Mode;

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
    /// PX4: a gap in the ground station's setpoint stream longer than
    /// this ends OFFBOARD (COM_OF_LOSS_T), seconds.
    pub offboard_loss_s: f64,
    /// PX4: how long the setpoint stream must have run before OFFBOARD is
    /// accepted, seconds.
    pub offboard_proof_s: f64,
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
            offboard_loss_s: 1.0,
            offboard_proof_s: 1.0,
        }
    }
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
    /// The ground station's guided setpoints (SET_POSITION_TARGET_*).
    offboard: OffboardStream,
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
            offboard: OffboardStream::default(),
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
            if self.mode == Mode::Offboard {
                self.clear_guided_target();
            }
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
        if self.guided_setpoint(msg) {
            self.gcs.get_or_insert(from);
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
}

#[cfg(test)]
mod tests;
