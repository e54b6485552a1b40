//! The MAVLink mission protocol (upload, download, clear, set current) as a
//! pure state machine: it is driven by received messages and a clock and
//! returns the messages to send. No I/O, so every rule is a unit test.
//!
//! Rules (PX4 flavour, after PX4's `MavlinkMissionManager`):
//! - Upload: MISSION_COUNT starts a transfer; the vehicle requests item 0.
//!   Requests are the legacy MISSION_REQUEST until a MISSION_ITEM_INT
//!   arrives, then MISSION_REQUEST_INT (a MISSION_ITEM switches back). The
//!   mode is reset to legacy at each MISSION_COUNT.
//! - The pending request is re-sent every 250 ms without an answer; after
//!   5 s of silence from the partner the transfer is abandoned (MISSION_ACK
//!   OPERATION_CANCELLED is sent) and the stored mission is unchanged.
//! - Storage is atomic: the old mission stays (for execution and download)
//!   until the last item of the new one has arrived and been accepted.
//! - Each item is checked: unsupported frame -> MAV_MISSION_UNSUPPORTED_FRAME,
//!   unsupported command -> MAV_MISSION_UNSUPPORTED, bad parameters ->
//!   MAV_MISSION_INVALID_PARAMn; an error ends the transfer.
//! - An item out of sequence is ignored (the re-request fetches the right
//!   one). A repeated MISSION_COUNT before item 0 arrived re-sends request 0;
//!   after that it is refused with MAV_MISSION_ERROR (busy).
//! - After a completed upload, a duplicate of the last item (the partner
//!   missed our ACK) is answered with MISSION_ACK ACCEPTED again.
//! - MISSION_COUNT 0 and MISSION_CLEAR_ALL clear the mission (ACK ACCEPTED).
//! - MISSION_SET_CURRENT jumps to an item (answered by MISSION_CURRENT); an
//!   out-of-range sequence gets MISSION_ACK INVALID_SEQUENCE.
//! - Download: MISSION_REQUEST_LIST -> MISSION_COUNT, then each
//!   MISSION_REQUEST_INT / MISSION_REQUEST is answered by MISSION_ITEM_INT /
//!   MISSION_ITEM; the partner's MISSION_ACK ends it. MISSION_COUNT is
//!   re-sent every retry period until the first request arrives. If the
//!   partner's final ACK is lost, a MISSION_COUNT from the same partner
//!   ends the download and starts its upload (another partner gets
//!   MAV_MISSION_ERROR, busy).
//! - Fence and rally plans are not supported: their lists download empty,
//!   an empty upload is accepted, anything else is MAV_MISSION_UNSUPPORTED.
//!
//! ArduPilot flavour differences: requests are always the legacy
//! MISSION_REQUEST, re-sent every 1 s, an 8 s timeout; item 0 is home (an
//! uploaded item 0 is replaced by the home position, downloads report
//! home); an item out of sequence is answered with MISSION_ACK
//! MAV_MISSION_INVALID_SEQUENCE; CONDITION_YAW is a supported command.

use mavlink::dialects::common::{
    MISSION_ACK_DATA, MISSION_COUNT_DATA, MISSION_CURRENT_DATA, MISSION_ITEM_DATA,
    MISSION_ITEM_INT_DATA, MISSION_REQUEST_DATA, MISSION_REQUEST_INT_DATA, MavCmd, MavFrame,
    MavMessage, MavMissionResult, MavMissionType, MissionState,
};

use crate::geodesy::Geodetic;

/// Which autopilot the protocol imitates.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Flavour {
    /// PX4 rules (the default).
    #[default]
    Px4,
    /// ArduPilot rules.
    ArduPilot,
}

/// Every tunable number of the mission protocol.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MissionParams {
    /// Rules to follow.
    pub flavour: Flavour,
    /// Re-send the pending request after this long without an answer, s.
    pub retry_s: f64,
    /// Abandon a transfer after this long without hearing the partner, s.
    pub timeout_s: f64,
    /// Largest mission accepted (items).
    pub max_items: u16,
    /// Our system id (messages for other systems are ignored).
    pub system_id: u8,
    /// Our component id.
    pub component_id: u8,
}

impl MissionParams {
    /// PX4's numbers: 250 ms retries, 5 s timeout.
    pub fn px4() -> Self {
        Self {
            flavour: Flavour::Px4,
            retry_s: 0.25,
            timeout_s: 5.0,
            max_items: 500,
            system_id: 1,
            component_id: 1,
        }
    }
    /// ArduPilot's numbers: 1 s retries, 8 s timeout.
    pub fn ardupilot() -> Self {
        Self {
            flavour: Flavour::ArduPilot,
            retry_s: 1.0,
            timeout_s: 8.0,
            ..Self::px4()
        }
    }
    /// The parameters for a flavour.
    pub fn for_flavour(flavour: Flavour) -> Self {
        match flavour {
            Flavour::Px4 => Self::px4(),
            Flavour::ArduPilot => Self::ardupilot(),
        }
    }
}

impl Default for MissionParams {
    fn default() -> Self {
        Self::px4()
    }
}

/// The other end of a transfer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Peer {
    /// Sender system id.
    pub system: u8,
    /// Sender component id.
    pub component: u8,
}

/// One stored mission item. `x` and `y` are degrees for global frames and
/// the raw parameter 5 / 6 value otherwise.
#[derive(Debug, Clone, PartialEq)]
pub struct MissionItem {
    /// Position in the mission.
    pub seq: u16,
    /// Coordinate frame.
    pub frame: MavFrame,
    /// Command.
    pub command: MavCmd,
    /// The "current" flag as uploaded.
    pub current: u8,
    /// Autocontinue flag.
    pub autocontinue: u8,
    /// Parameters 1..4.
    pub params: [f32; 4],
    /// Latitude (deg) or parameter 5.
    pub x: f64,
    /// Longitude (deg) or parameter 6.
    pub y: f64,
    /// Altitude (m) or parameter 7.
    pub z: f32,
}

/// Frames whose x/y are latitude/longitude.
pub fn is_global(frame: MavFrame) -> bool {
    matches!(
        frame,
        MavFrame::MAV_FRAME_GLOBAL
            | MavFrame::MAV_FRAME_GLOBAL_INT
            | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT
            | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    )
}

/// Frames whose altitude is relative to home.
pub fn is_relative_alt(frame: MavFrame) -> bool {
    matches!(
        frame,
        MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
    )
}

fn is_nav(cmd: MavCmd) -> bool {
    matches!(
        cmd,
        MavCmd::MAV_CMD_NAV_WAYPOINT | MavCmd::MAV_CMD_NAV_TAKEOFF | MavCmd::MAV_CMD_NAV_LAND
    )
}

impl MissionItem {
    /// From a MISSION_ITEM_INT.
    pub fn from_int(m: &MISSION_ITEM_INT_DATA) -> Self {
        let (x, y) = if is_global(m.frame) {
            (f64::from(m.x) * 1e-7, f64::from(m.y) * 1e-7)
        } else {
            (f64::from(m.x), f64::from(m.y))
        };
        Self {
            seq: m.seq,
            frame: m.frame,
            command: m.command,
            current: m.current,
            autocontinue: m.autocontinue,
            params: [m.param1, m.param2, m.param3, m.param4],
            x,
            y,
            z: m.z,
        }
    }

    /// From a legacy MISSION_ITEM (float coordinates).
    pub fn from_float(m: &MISSION_ITEM_DATA) -> Self {
        Self {
            seq: m.seq,
            frame: m.frame,
            command: m.command,
            current: m.current,
            autocontinue: m.autocontinue,
            params: [m.param1, m.param2, m.param3, m.param4],
            x: f64::from(m.x),
            y: f64::from(m.y),
            z: m.z,
        }
    }

    /// As a MISSION_ITEM_INT addressed to `to`.
    pub fn to_int(&self, to: Peer) -> MISSION_ITEM_INT_DATA {
        let (x, y) = if is_global(self.frame) {
            ((self.x * 1e7).round() as i32, (self.y * 1e7).round() as i32)
        } else {
            (self.x.round() as i32, self.y.round() as i32)
        };
        MISSION_ITEM_INT_DATA {
            param1: self.params[0],
            param2: self.params[1],
            param3: self.params[2],
            param4: self.params[3],
            x,
            y,
            z: self.z,
            seq: self.seq,
            command: self.command,
            target_system: to.system,
            target_component: to.component,
            frame: self.frame,
            current: self.current,
            autocontinue: self.autocontinue,
            mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        }
    }

    /// As a legacy MISSION_ITEM addressed to `to`.
    pub fn to_float(&self, to: Peer) -> MISSION_ITEM_DATA {
        MISSION_ITEM_DATA {
            param1: self.params[0],
            param2: self.params[1],
            param3: self.params[2],
            param4: self.params[3],
            x: self.x as f32,
            y: self.y as f32,
            z: self.z,
            seq: self.seq,
            command: self.command,
            target_system: to.system,
            target_component: to.component,
            frame: self.frame,
            current: self.current,
            autocontinue: self.autocontinue,
            mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        }
    }
}

/// Something the executor must know about.
#[derive(Debug, Clone, PartialEq)]
pub enum MissionEvent {
    /// A new mission was stored (it replaces the old one).
    Stored {
        /// Number of items.
        count: u16,
    },
    /// The mission was cleared.
    Cleared,
    /// The partner set the current item.
    SetCurrent(u16),
}

#[derive(Debug, Clone)]
enum Transfer {
    Idle,
    Receiving {
        peer: Peer,
        count: u16,
        next: u16,
        items: Vec<MissionItem>,
        last_rx: f64,
        last_tx: f64,
    },
    Sending {
        peer: Peer,
        requested: bool,
        last_rx: f64,
        last_tx: f64,
    },
}

/// The mission store and its transfer protocol.
#[derive(Debug, Clone)]
pub struct MissionProtocol {
    params: MissionParams,
    items: Vec<MissionItem>,
    current: u16,
    int_mode: bool,
    transfer: Transfer,
    /// (peer, count) of the last completed upload, for duplicate re-ACKs.
    last_upload: Option<(Peer, u16)>,
    events: Vec<MissionEvent>,
    home: Geodetic,
}

fn ack(to: Peer, result: MavMissionResult, mission_type: MavMissionType) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: to.system,
        target_component: to.component,
        mavtype: result,
        mission_type,
        opaque_id: 0,
    })
}

const MISSION: MavMissionType = MavMissionType::MAV_MISSION_TYPE_MISSION;

impl MissionProtocol {
    /// An empty store. `home` is reported as item 0 in the ArduPilot flavour.
    pub fn new(params: MissionParams, home: Geodetic) -> Self {
        let mut s = Self {
            params,
            items: Vec::new(),
            current: 0,
            int_mode: false,
            transfer: Transfer::Idle,
            last_upload: None,
            events: Vec::new(),
            home,
        };
        if params.flavour == Flavour::ArduPilot {
            s.items.push(s.home_item());
            s.current = 1;
        }
        s
    }

    fn home_item(&self) -> MissionItem {
        MissionItem {
            seq: 0,
            frame: MavFrame::MAV_FRAME_GLOBAL,
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            current: 0,
            autocontinue: 1,
            params: [0.0; 4],
            x: self.home.lat_deg,
            y: self.home.lon_deg,
            z: self.home.alt_m as f32,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &MissionParams {
        &self.params
    }

    /// The stored mission (in the ArduPilot flavour item 0 is home).
    pub fn items(&self) -> &[MissionItem] {
        &self.items
    }

    /// Index of the first item to execute (1 for ArduPilot, where 0 is home).
    pub fn first_item(&self) -> u16 {
        match self.params.flavour {
            Flavour::Px4 => 0,
            Flavour::ArduPilot => 1,
        }
    }

    /// The current item.
    pub fn current(&self) -> u16 {
        self.current
    }

    /// Set by the executor as it advances.
    pub fn set_current(&mut self, seq: u16) {
        self.current = seq;
    }

    /// True while an upload or download is in progress.
    pub fn busy(&self) -> bool {
        !matches!(self.transfer, Transfer::Idle)
    }

    /// Events since the last call.
    pub fn take_events(&mut self) -> Vec<MissionEvent> {
        std::mem::take(&mut self.events)
    }

    /// A MISSION_CURRENT for the present state.
    pub fn mission_current(&self, state: MissionState) -> MavMessage {
        MavMessage::MISSION_CURRENT(MISSION_CURRENT_DATA {
            seq: self.current,
            total: self.items.len() as u16,
            mission_state: state,
            mission_mode: 0,
            mission_id: self.plan_id(),
            fence_id: 0,
            rally_points_id: 0,
        })
    }

    /// The stored plan's id as MISSION_CURRENT reports it (PX4 sends a
    /// CRC32 of the plan; here a 32-bit FNV-1a hash of the items): ground
    /// stations sharing the link see that the mission changed, and
    /// read it again. 0 for no mission, as MAVLink says for "none".
    pub fn plan_id(&self) -> u32 {
        let first = usize::from(self.first_item());
        if self.items.len() <= first {
            return 0;
        }
        let mut h: u32 = 0x811c_9dc5;
        let mut eat = |bytes: &[u8]| {
            for b in bytes {
                h ^= u32::from(*b);
                h = h.wrapping_mul(0x0100_0193);
            }
        };
        for it in &self.items[first..] {
            eat(&(it.frame as u32).to_le_bytes());
            eat(&(it.command as u32).to_le_bytes());
            eat(&[it.autocontinue]);
            for p in it.params {
                eat(&p.to_bits().to_le_bytes());
            }
            eat(&it.x.to_bits().to_le_bytes());
            eat(&it.y.to_bits().to_le_bytes());
            eat(&it.z.to_bits().to_le_bytes());
        }
        h.max(1)
    }

    fn addressed_to_us(&self, target_system: u8) -> bool {
        target_system == 0 || target_system == self.params.system_id
    }

    fn request(&self, to: Peer, seq: u16) -> MavMessage {
        if self.int_mode && self.params.flavour == Flavour::Px4 {
            MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                seq,
                target_system: to.system,
                target_component: to.component,
                mission_type: MISSION,
            })
        } else {
            MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
                seq,
                target_system: to.system,
                target_component: to.component,
                mission_type: MISSION,
            })
        }
    }

    fn count_msg(&self, to: Peer, count: u16, mission_type: MavMissionType) -> MavMessage {
        MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count,
            target_system: to.system,
            target_component: to.component,
            mission_type,
            opaque_id: 0,
        })
    }

    /// Check one item against what the executor supports.
    pub fn validate(&self, item: &MissionItem) -> Result<(), MavMissionResult> {
        use MavCmd::*;
        use MavMissionResult::*;
        let ardu = self.params.flavour == Flavour::ArduPilot;
        if ardu && item.seq == 0 {
            return Ok(()); // home: replaced by ours
        }
        let supported = matches!(
            item.command,
            MAV_CMD_NAV_WAYPOINT
                | MAV_CMD_NAV_TAKEOFF
                | MAV_CMD_NAV_LAND
                | MAV_CMD_NAV_RETURN_TO_LAUNCH
                | MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW
                | MAV_CMD_DO_MOUNT_CONTROL
                | MAV_CMD_IMAGE_START_CAPTURE
                | MAV_CMD_IMAGE_STOP_CAPTURE
                | MAV_CMD_DO_DIGICAM_CONTROL
                | MAV_CMD_DO_CHANGE_SPEED
        ) || (ardu && item.command == MAV_CMD_CONDITION_YAW)
            // PX4 runs it as a command from the autopilot; ArduPilot's
            // mission has no handler for it.
            || (!ardu && item.command == MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE);
        if !supported {
            return Err(MAV_MISSION_UNSUPPORTED);
        }
        if !(is_global(item.frame) || item.frame == MavFrame::MAV_FRAME_MISSION) {
            return Err(MAV_MISSION_UNSUPPORTED_FRAME);
        }
        if is_nav(item.command) {
            if !is_global(item.frame) {
                return Err(MAV_MISSION_UNSUPPORTED_FRAME);
            }
            // Takeoff and land may leave lat/lon at 0 (here / current).
            let latlon_optional = item.command != MAV_CMD_NAV_WAYPOINT;
            let zero = item.x == 0.0 && item.y == 0.0;
            if !(latlon_optional && zero) {
                if !(item.x.is_finite() && (-90.0..=90.0).contains(&item.x)) {
                    return Err(MAV_MISSION_INVALID_PARAM5_X);
                }
                if !(item.y.is_finite() && (-180.0..=180.0).contains(&item.y)) {
                    return Err(MAV_MISSION_INVALID_PARAM6_Y);
                }
            }
            if !item.z.is_finite() {
                return Err(MAV_MISSION_INVALID_PARAM7);
            }
        }
        let p = item.params;
        match item.command {
            MAV_CMD_NAV_WAYPOINT => {
                if !(p[0].is_finite() && p[0] >= 0.0) {
                    return Err(MAV_MISSION_INVALID_PARAM1);
                }
                if !(p[1].is_finite() && p[1] >= 0.0) {
                    return Err(MAV_MISSION_INVALID_PARAM2);
                }
            }
            MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE => {
                let ok = |v: f32| v.is_finite() && (-3.0..=255.0).contains(&v);
                let errs = [
                    MAV_MISSION_INVALID_PARAM1,
                    MAV_MISSION_INVALID_PARAM2,
                    MAV_MISSION_INVALID_PARAM3,
                    MAV_MISSION_INVALID_PARAM4,
                ];
                if let Some(i) = p.iter().position(|v| !ok(*v)) {
                    return Err(errs[i]);
                }
            }
            MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                if p[0].is_finite() && !(-180.0..=180.0).contains(&p[0]) {
                    return Err(MAV_MISSION_INVALID_PARAM1);
                }
                if p[1].is_finite() && !(-360.0..=360.0).contains(&p[1]) {
                    return Err(MAV_MISSION_INVALID_PARAM2);
                }
            }
            MAV_CMD_DO_MOUNT_CONTROL => {
                if p[0].is_finite() && !(-180.0..=180.0).contains(&p[0]) {
                    return Err(MAV_MISSION_INVALID_PARAM1);
                }
                if p[2].is_finite() && !(-360.0..=360.0).contains(&p[2]) {
                    return Err(MAV_MISSION_INVALID_PARAM3);
                }
            }
            MAV_CMD_IMAGE_START_CAPTURE => {
                if !(p[1].is_finite() && p[1] >= 0.0) {
                    return Err(MAV_MISSION_INVALID_PARAM2);
                }
                if !(p[2].is_finite() && p[2] >= 0.0) {
                    return Err(MAV_MISSION_INVALID_PARAM3);
                }
            }
            MAV_CMD_CONDITION_YAW if !(p[0].is_finite() && (-360.0..=360.0).contains(&p[0])) => {
                return Err(MAV_MISSION_INVALID_PARAM1);
            }
            _ => {}
        }
        Ok(())
    }

    /// Handle one received message from `from`; returns what to send.
    pub fn handle(&mut self, now: f64, from: Peer, msg: &MavMessage) -> Vec<MavMessage> {
        let mut out = Vec::new();
        match msg {
            MavMessage::MISSION_COUNT(m) if self.addressed_to_us(m.target_system) => {
                self.on_count(now, from, m, &mut out)
            }
            MavMessage::MISSION_ITEM_INT(m)
                if self.addressed_to_us(m.target_system) && m.mission_type == MISSION =>
            {
                self.int_mode = true;
                self.on_item(now, from, MissionItem::from_int(m), &mut out);
            }
            MavMessage::MISSION_ITEM(m)
                if self.addressed_to_us(m.target_system) && m.mission_type == MISSION =>
            {
                self.int_mode = false;
                self.on_item(now, from, MissionItem::from_float(m), &mut out);
            }
            MavMessage::MISSION_REQUEST_LIST(m) if self.addressed_to_us(m.target_system) => {
                self.on_request_list(now, from, m.mission_type, &mut out)
            }
            MavMessage::MISSION_REQUEST_INT(m)
                if self.addressed_to_us(m.target_system) && m.mission_type == MISSION =>
            {
                self.on_request(now, from, m.seq, true, &mut out)
            }
            MavMessage::MISSION_REQUEST(m)
                if self.addressed_to_us(m.target_system) && m.mission_type == MISSION =>
            {
                self.on_request(now, from, m.seq, false, &mut out)
            }
            MavMessage::MISSION_ACK(m) if self.addressed_to_us(m.target_system) => {
                if let Transfer::Sending { peer, .. } = self.transfer
                    && peer == from
                {
                    self.transfer = Transfer::Idle;
                }
            }
            MavMessage::MISSION_CLEAR_ALL(m) if self.addressed_to_us(m.target_system) => {
                if m.mission_type != MISSION
                    && m.mission_type != MavMissionType::MAV_MISSION_TYPE_ALL
                {
                    out.push(ack(
                        from,
                        MavMissionResult::MAV_MISSION_ACCEPTED,
                        m.mission_type,
                    ));
                } else if self.busy() {
                    out.push(ack(
                        from,
                        MavMissionResult::MAV_MISSION_ERROR,
                        m.mission_type,
                    ));
                } else {
                    self.clear();
                    out.push(ack(
                        from,
                        MavMissionResult::MAV_MISSION_ACCEPTED,
                        m.mission_type,
                    ));
                }
            }
            MavMessage::MISSION_SET_CURRENT(m) if self.addressed_to_us(m.target_system) => {
                if m.seq >= self.first_item() && usize::from(m.seq) < self.items.len() {
                    self.current = m.seq;
                    self.events.push(MissionEvent::SetCurrent(m.seq));
                    out.push(self.mission_current(MissionState::MISSION_STATE_NOT_STARTED));
                } else {
                    out.push(ack(
                        from,
                        MavMissionResult::MAV_MISSION_INVALID_SEQUENCE,
                        MISSION,
                    ));
                }
            }
            _ => {}
        }
        out
    }

    fn clear(&mut self) {
        self.items.clear();
        self.current = 0;
        if self.params.flavour == Flavour::ArduPilot {
            self.items.push(self.home_item());
            self.current = 1;
        }
        self.last_upload = None;
        self.events.push(MissionEvent::Cleared);
    }

    fn on_count(
        &mut self,
        now: f64,
        from: Peer,
        m: &MISSION_COUNT_DATA,
        out: &mut Vec<MavMessage>,
    ) {
        if m.mission_type != MISSION {
            let r = if m.count == 0 {
                MavMissionResult::MAV_MISSION_ACCEPTED
            } else {
                MavMissionResult::MAV_MISSION_UNSUPPORTED
            };
            out.push(ack(from, r, m.mission_type));
            return;
        }
        match &mut self.transfer {
            Transfer::Idle => {}
            Transfer::Receiving {
                peer,
                next,
                count,
                last_rx,
                last_tx,
                ..
            } => {
                if *peer == from && *next == 0 {
                    // Our first request was lost: ask again (the count may
                    // have changed).
                    *count = m.count;
                    *last_rx = now;
                    *last_tx = now;
                    out.push(self.request(from, 0));
                } else {
                    out.push(ack(from, MavMissionResult::MAV_MISSION_ERROR, MISSION));
                }
                return;
            }
            Transfer::Sending { peer, .. } => {
                if *peer != from {
                    out.push(ack(from, MavMissionResult::MAV_MISSION_ERROR, MISSION));
                    return;
                }
                // The download partner has moved on (its final ACK was
                // lost): the download is over, the upload starts.
                self.transfer = Transfer::Idle;
            }
        }
        let ardu = self.params.flavour == Flavour::ArduPilot;
        if m.count == 0 || (ardu && m.count == 1) {
            self.clear();
            self.last_upload = None;
            out.push(ack(from, MavMissionResult::MAV_MISSION_ACCEPTED, MISSION));
            return;
        }
        if m.count > self.params.max_items {
            out.push(ack(from, MavMissionResult::MAV_MISSION_NO_SPACE, MISSION));
            return;
        }
        self.int_mode = false;
        self.transfer = Transfer::Receiving {
            peer: from,
            count: m.count,
            next: 0,
            items: Vec::with_capacity(usize::from(m.count)),
            last_rx: now,
            last_tx: now,
        };
        out.push(self.request(from, 0));
    }

    fn on_item(&mut self, now: f64, from: Peer, item: MissionItem, out: &mut Vec<MavMessage>) {
        let ardu = self.params.flavour == Flavour::ArduPilot;
        let (peer, count, next) = match &mut self.transfer {
            Transfer::Receiving {
                peer,
                count,
                next,
                last_rx,
                ..
            } if *peer == from => {
                *last_rx = now;
                (*peer, *count, *next)
            }
            Transfer::Receiving { .. } | Transfer::Sending { .. } => return,
            Transfer::Idle => {
                // A duplicate of the last item of the upload we just
                // completed means the partner missed our ACK.
                if let Some((p, n)) = self.last_upload
                    && p == from
                    && u32::from(item.seq) + 1 == u32::from(n)
                {
                    out.push(ack(from, MavMissionResult::MAV_MISSION_ACCEPTED, MISSION));
                }
                return;
            }
        };
        if item.seq != next {
            if ardu {
                out.push(ack(
                    from,
                    MavMissionResult::MAV_MISSION_INVALID_SEQUENCE,
                    MISSION,
                ));
            }
            return;
        }
        if let Err(code) = self.validate(&item) {
            self.transfer = Transfer::Idle;
            out.push(ack(from, code, MISSION));
            return;
        }
        let item = if ardu && item.seq == 0 {
            self.home_item()
        } else {
            item
        };
        let req = self.request(from, next + 1);
        let Transfer::Receiving {
            next,
            items,
            last_tx,
            ..
        } = &mut self.transfer
        else {
            return;
        };
        items.push(item);
        *next += 1;
        if *next == count {
            let new_items = std::mem::take(items);
            self.transfer = Transfer::Idle;
            self.items = new_items;
            self.current = self.first_item();
            self.last_upload = Some((peer, count));
            self.events.push(MissionEvent::Stored { count });
            out.push(ack(from, MavMissionResult::MAV_MISSION_ACCEPTED, MISSION));
        } else {
            *last_tx = now;
            out.push(req);
        }
    }

    fn on_request_list(
        &mut self,
        now: f64,
        from: Peer,
        mission_type: MavMissionType,
        out: &mut Vec<MavMessage>,
    ) {
        if mission_type != MISSION {
            out.push(self.count_msg(from, 0, mission_type));
            return;
        }
        match self.transfer {
            Transfer::Receiving { .. } => {
                out.push(ack(from, MavMissionResult::MAV_MISSION_ERROR, MISSION));
                return;
            }
            Transfer::Sending { peer, .. } if peer != from => {
                out.push(ack(from, MavMissionResult::MAV_MISSION_ERROR, MISSION));
                return;
            }
            _ => {}
        }
        let n = self.items.len() as u16;
        out.push(self.count_msg(from, n, MISSION));
        self.transfer = if n == 0 {
            Transfer::Idle
        } else {
            Transfer::Sending {
                peer: from,
                requested: false,
                last_rx: now,
                last_tx: now,
            }
        };
    }

    fn on_request(&mut self, now: f64, from: Peer, seq: u16, int: bool, out: &mut Vec<MavMessage>) {
        match &mut self.transfer {
            Transfer::Receiving { .. } => return,
            Transfer::Sending { peer, .. } if *peer != from => return,
            Transfer::Sending {
                requested,
                last_rx,
                last_tx,
                ..
            } => {
                *requested = true;
                *last_rx = now;
                *last_tx = now;
            }
            Transfer::Idle => {
                // A late repeat of a request after the transfer ended:
                // answer it, as PX4 does, and wait for the ACK again.
                self.transfer = Transfer::Sending {
                    peer: from,
                    requested: true,
                    last_rx: now,
                    last_tx: now,
                };
            }
        }
        self.int_mode = int;
        match self.items.get(usize::from(seq)) {
            Some(item) => out.push(if int {
                MavMessage::MISSION_ITEM_INT(item.to_int(from))
            } else {
                MavMessage::MISSION_ITEM(item.to_float(from))
            }),
            None => {
                self.transfer = Transfer::Idle;
                out.push(ack(
                    from,
                    MavMissionResult::MAV_MISSION_INVALID_SEQUENCE,
                    MISSION,
                ));
            }
        }
    }

    /// Advance the clock: re-requests and timeouts.
    pub fn tick(&mut self, now: f64) -> Vec<MavMessage> {
        let mut out = Vec::new();
        let retry = self.params.retry_s;
        let timeout = self.params.timeout_s;
        match &mut self.transfer {
            Transfer::Idle => {}
            Transfer::Receiving {
                peer,
                next,
                last_rx,
                last_tx,
                ..
            } => {
                let (peer, next) = (*peer, *next);
                if now - *last_rx >= timeout {
                    self.transfer = Transfer::Idle;
                    out.push(ack(
                        peer,
                        MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
                        MISSION,
                    ));
                } else if now - *last_tx >= retry {
                    *last_tx = now;
                    out.push(self.request(peer, next));
                }
            }
            Transfer::Sending {
                peer,
                requested,
                last_rx,
                last_tx,
            } => {
                let peer = *peer;
                if now - *last_rx >= timeout {
                    self.transfer = Transfer::Idle;
                } else if !*requested && now - *last_tx >= retry {
                    *last_tx = now;
                    let n = self.items.len() as u16;
                    out.push(self.count_msg(peer, n, MISSION));
                }
            }
        }
        out
    }
}

#[cfg(test)]
mod tests;
