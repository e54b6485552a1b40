//! The MAVLink mission protocol as pure state machines: messages and a clock
//! in, messages out. The link actor (`vehicle`) drives them; tests drive them
//! with scripted vehicles and a fake clock.
//!
//! Upload ([`Uploader`]), following <https://mavlink.io/en/services/mission.html>
//! and what PX4 and ArduPilot actually do:
//!
//! - send `MISSION_COUNT`; resend it while no request arrives;
//! - answer `MISSION_REQUEST_INT` *and* the legacy `MISSION_REQUEST` with
//!   `MISSION_ITEM_INT`; answer repeated requests again (the item was lost);
//! - accept only messages from the target system/component, addressed to us
//!   (or broadcast), for our `mission_type`;
//! - ignore `MAV_MISSION_INVALID_SEQUENCE` (ArduPilot sends it for the
//!   duplicate items that the retries above produce);
//! - when the final `MISSION_ACK` is late, re-send the last item: PX4
//!   answers a repeated last item with a new ACK (ArduPilot with an error,
//!   see below);
//! - give up after `max_retries` timeouts in a row without progress;
//! - once every item went out and something was re-sent, a generic
//!   `MAV_MISSION_ERROR` is ambiguous (ArduPilot answers every item after
//!   it stored the mission so, PX4 a stale one) and is ignored; a final ACK
//!   still missing after `final_ack_retries` resends ends in
//!   [`MissionError::NoFinalAck`], which the link actor settles by reading
//!   the mission back;
//! - every other `MAV_MISSION_RESULT` ends the upload with its own
//!   [`MissionError`] variant; an ACCEPTED that arrives before the last item
//!   was sent is stale (a previous transfer's) and is ignored.
//!
//! Download ([`Downloader`]): `MISSION_REQUEST_LIST` -> `MISSION_COUNT`, then
//! `MISSION_REQUEST_INT` for each item in order (re-requested on timeout),
//! `MISSION_ACK` at the end.
//!
//! # Layout
//!
//! - [`wire`]: planned items to and from `MISSION_ITEM_INT` / the legacy
//!   `MISSION_ITEM`, and comparing a read-back with the plan;
//! - [`Uploader`] and [`Downloader`]: the two state machines, which share
//!   their clock, timeouts, addressing and cancellation here.

// The legacy MISSION_REQUEST / MISSION_ITEM are deprecated in the dialect,
// and answering them is exactly what real autopilots need.
#![allow(deprecated)]

mod downloader;
mod uploader;
pub mod wire;

#[cfg(test)]
mod tests;

use std::time::{Duration, Instant};

use mavlink::MavHeader;
use mavlink::dialects::common::{MISSION_ACK_DATA, MavMessage, MavMissionResult, MavMissionType};
use serde::{Deserialize, Serialize};

use super::plan::MissionItem;

pub use downloader::Downloader;
pub use uploader::Uploader;
pub use wire::{item_from_legacy, item_from_wire, item_to_wire, same_mission};

/// Timeouts and retries of mission transfers.
///
/// Sized for a 57600 baud telemetry radio: a `MISSION_ITEM_INT` frame is 51
/// bytes, 8.9 ms on the air at 5760 bytes/s; SiK radios add 20-80 ms of
/// latency each way and share the air with telemetry. A request/item round
/// trip is therefore 100-250 ms; the default timeout leaves room for that
/// while keeping a lossy link (30 % loss each way) moving.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Time to wait for the vehicle's next message before resending, ms.
    pub retry_timeout_ms: u64,
    /// Timeouts in a row without progress before the transfer fails.
    pub max_retries: u32,
    /// Resends of the last item while the final ACK is missing, before the
    /// upload ends with [`MissionError::NoFinalAck`] (the link actor then
    /// reads the mission back: ArduPilot answers a repeated last item with
    /// an error once it has stored the mission, PX4 ACKs it again).
    pub final_ack_retries: u32,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            retry_timeout_ms: 400,
            max_retries: 15,
            final_ack_retries: 3,
        }
    }
}

impl Params {
    fn timeout(&self) -> Duration {
        Duration::from_millis(self.retry_timeout_ms.max(1))
    }
}

/// Which step of a transfer timed out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Stage {
    /// Upload: waiting for the first request after `MISSION_COUNT`.
    FirstRequest,
    /// Upload: waiting for a request for `seq + 1` or the final ACK after sending item `seq`.
    AfterItem {
        /// The last item sent.
        seq: u16,
    },
    /// Download: waiting for `MISSION_COUNT`.
    Count,
    /// Download: waiting for item `seq`.
    Item {
        /// The item requested.
        seq: u16,
    },
}

/// Errors of mission transfers: one variant per `MAV_MISSION_RESULT` the
/// vehicle can answer with, and the ground side's own failures.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MissionError {
    /// MAV_MISSION_ERROR: generic error.
    #[error("vehicle reports a generic mission error (last item {last_seq:?})")]
    VehicleError {
        /// The last item sent when the answer came.
        last_seq: Option<u16>,
    },
    /// MAV_MISSION_UNSUPPORTED_FRAME.
    #[error("vehicle does not support the coordinate frame (last item {last_seq:?})")]
    UnsupportedFrame {
        /// The last item sent.
        last_seq: Option<u16>,
    },
    /// MAV_MISSION_UNSUPPORTED: a command is not supported.
    #[error("vehicle does not support a command (last item {last_seq:?})")]
    UnsupportedCommand {
        /// The last item sent.
        last_seq: Option<u16>,
    },
    /// MAV_MISSION_NO_SPACE: the mission does not fit.
    #[error("vehicle has no space for {count} items")]
    NoSpace {
        /// Items offered.
        count: u16,
    },
    /// MAV_MISSION_INVALID: an item's parameters are invalid.
    #[error("vehicle rejects an item as invalid (last item {last_seq:?})")]
    InvalidItem {
        /// The last item sent.
        last_seq: Option<u16>,
    },
    /// MAV_MISSION_INVALID_PARAM1..7: one parameter is out of range.
    #[error("vehicle rejects param{param} (last item {last_seq:?})")]
    InvalidParam {
        /// 1..=7 (5 is x/latitude, 6 y/longitude, 7 z/altitude).
        param: u8,
        /// The last item sent.
        last_seq: Option<u16>,
    },
    /// MAV_MISSION_INVALID_SEQUENCE, when it ends a download (during an
    /// upload it is ignored, see the module doc).
    #[error("vehicle reports an out-of-sequence item")]
    InvalidSequence,
    /// MAV_MISSION_DENIED: the vehicle refuses missions now (e.g. flying one).
    #[error("vehicle denies the mission operation")]
    Denied,
    /// MAV_MISSION_OPERATION_CANCELLED, sent by the vehicle.
    #[error("vehicle cancelled the transfer")]
    CancelledByVehicle,
    /// The transfer made no progress for `retries` timeouts in a row.
    #[error("mission transfer timed out at {stage:?} after {retries} retries")]
    Timeout {
        /// Where it stalled.
        stage: Stage,
        /// Consecutive timeouts.
        retries: u32,
    },
    /// Every item was sent but the final ACK never came, through
    /// `retries` resends of the last item (or a generic error came that may
    /// answer a stale repeated item). The vehicle may hold the mission:
    /// reading it back decides.
    #[error("all {count} items sent, no final MISSION_ACK after {retries} resends of the last")]
    NoFinalAck {
        /// Items sent.
        count: u16,
        /// Resends of the last item.
        retries: u32,
    },
    /// The mission read back after a missing final ACK differs from the one sent.
    #[error("the mission read back ({downloaded} items) differs from the {uploaded} items sent")]
    ReadBackDiffers {
        /// Items sent.
        uploaded: u16,
        /// Items read back.
        downloaded: usize,
    },
    /// The operator cancelled the transfer.
    #[error("mission transfer cancelled")]
    Cancelled,
    /// A planned item holds a command or frame number MAVLink's common dialect lacks.
    #[error("item {seq}: unknown {what} {value}")]
    UnknownNumber {
        /// Item index.
        seq: u16,
        /// "command" or "frame".
        what: &'static str,
        /// The number.
        value: u32,
    },
    /// More items than MAVLink can count (65535).
    #[error("{count} items is more than a mission can hold")]
    TooManyItems {
        /// Items offered.
        count: usize,
    },
    /// Planned items are not numbered 0, 1, 2, ...
    #[error("item at index {index} has seq {seq}")]
    BadNumbering {
        /// Position in the list.
        index: usize,
        /// Its seq.
        seq: u16,
    },
}

impl MissionError {
    /// Maps a `MAV_MISSION_RESULT` to its error; `None` for ACCEPTED.
    pub fn from_result(
        result: MavMissionResult,
        last_seq: Option<u16>,
        count: u16,
    ) -> Option<Self> {
        use MavMissionResult as R;
        Some(match result {
            R::MAV_MISSION_ACCEPTED => return None,
            R::MAV_MISSION_ERROR => Self::VehicleError { last_seq },
            R::MAV_MISSION_UNSUPPORTED_FRAME => Self::UnsupportedFrame { last_seq },
            R::MAV_MISSION_UNSUPPORTED => Self::UnsupportedCommand { last_seq },
            R::MAV_MISSION_NO_SPACE => Self::NoSpace { count },
            R::MAV_MISSION_INVALID => Self::InvalidItem { last_seq },
            R::MAV_MISSION_INVALID_PARAM1 => Self::InvalidParam { param: 1, last_seq },
            R::MAV_MISSION_INVALID_PARAM2 => Self::InvalidParam { param: 2, last_seq },
            R::MAV_MISSION_INVALID_PARAM3 => Self::InvalidParam { param: 3, last_seq },
            R::MAV_MISSION_INVALID_PARAM4 => Self::InvalidParam { param: 4, last_seq },
            R::MAV_MISSION_INVALID_PARAM5_X => Self::InvalidParam { param: 5, last_seq },
            R::MAV_MISSION_INVALID_PARAM6_Y => Self::InvalidParam { param: 6, last_seq },
            R::MAV_MISSION_INVALID_PARAM7 => Self::InvalidParam { param: 7, last_seq },
            R::MAV_MISSION_INVALID_SEQUENCE => Self::InvalidSequence,
            R::MAV_MISSION_DENIED => Self::Denied,
            R::MAV_MISSION_OPERATION_CANCELLED => Self::CancelledByVehicle,
        })
    }
}

/// Who we are and whom we talk to.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Peers {
    /// Our system id.
    pub own_system: u8,
    /// Our component id.
    pub own_component: u8,
    /// The vehicle's system id.
    pub target_system: u8,
    /// The autopilot's component id (0: any component of the system).
    pub target_component: u8,
}

impl Peers {
    /// Whether a message came from the vehicle.
    fn is_from_target(&self, header: &MavHeader) -> bool {
        header.system_id == u32::from(self.target_system)
            && (self.target_component == 0 || header.component_id == self.target_component)
    }

    /// Whether a message's target fields address us (0 is broadcast).
    fn addressed_to_us(&self, system: u8, component: u8) -> bool {
        (system == 0 || system == self.own_system)
            && (component == 0 || component == self.own_component)
    }
}

/// What an upload did.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct UploadReport {
    /// Items uploaded.
    pub items: u16,
    /// Timeouts that made us resend (COUNT or an item).
    pub retries: u32,
    /// Requests for an item already sent, answered again.
    pub repeats: u32,
    /// Messages from the vehicle ignored (stale ACKs, INVALID_SEQUENCE, out-of-range requests).
    pub ignored: u32,
    /// Wall time from MISSION_COUNT to the ACK (or to the end of the
    /// read-back that replaced a lost ACK), seconds.
    pub seconds: f64,
    /// The final ACK was lost and the upload was confirmed by reading the
    /// mission back.
    pub verified_by_download: bool,
}

/// What a download did.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Download {
    /// The items, in order.
    pub items: Vec<MissionItem>,
    /// Timeouts that made us re-request.
    pub retries: u32,
    /// Stale error ACKs ignored (answers to an earlier upload's repeats).
    pub ignored: u32,
    /// Wall time, seconds.
    pub seconds: f64,
}

/// What the upload and the download share: whom they talk to, for which
/// mission type, and their retry clock.
#[derive(Debug)]
struct Transfer {
    peers: Peers,
    mission_type: MavMissionType,
    params: Params,
    started: Instant,
    deadline: Instant,
    consecutive_timeouts: u32,
}

impl Transfer {
    fn new(peers: Peers, mission_type: MavMissionType, params: Params, now: Instant) -> Self {
        Self {
            peers,
            mission_type,
            params,
            started: now,
            deadline: now + params.timeout(),
            consecutive_timeouts: 0,
        }
    }

    /// Whether a mission message with these fields is ours: our mission
    /// type, addressed to us (or broadcast).
    fn is_ours(&self, mission_type: MavMissionType, system: u8, component: u8) -> bool {
        mission_type == self.mission_type && self.peers.addressed_to_us(system, component)
    }

    /// The vehicle answered: the timeouts in a row start over.
    fn progress(&mut self, now: Instant) {
        self.consecutive_timeouts = 0;
        self.rearm(now);
    }

    /// Wait one timeout from `now`.
    fn rearm(&mut self, now: Instant) {
        self.deadline = now + self.params.timeout();
    }

    /// Seconds since the start.
    fn seconds(&self, now: Instant) -> f64 {
        now.saturating_duration_since(self.started).as_secs_f64()
    }

    /// A `MISSION_ACK` with `result` for the vehicle.
    fn ack(&self, result: MavMissionResult) -> MavMessage {
        MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: self.peers.target_system,
            target_component: self.peers.target_component,
            mavtype: result,
            mission_type: self.mission_type,
            opaque_id: 0,
        })
    }
}

/// The part of a transfer that differs between upload and download when
/// a timeout passes or the operator cancels; [`on_timeout`] and [`cancel`]
/// are the rest, written once.
trait Machine {
    fn transfer(&mut self) -> &mut Transfer;
    fn is_done(&self) -> bool;
    /// The error that ends the transfer after `consecutive` timeouts in a
    /// row, if this one ends it.
    fn give_up(&self, consecutive: u32) -> Option<MissionError>;
    /// Count a retry and resend what the vehicle should answer.
    fn resend(&mut self, out: &mut Vec<MavMessage>);
    fn finish(&mut self, result: Result<(), MissionError>, now: Instant);
}

/// A timeout of `m`: resend, or give up.
fn on_timeout(m: &mut impl Machine, now: Instant, out: &mut Vec<MavMessage>) {
    if m.is_done() || now < m.transfer().deadline {
        return;
    }
    let t = m.transfer();
    t.consecutive_timeouts += 1;
    let consecutive = t.consecutive_timeouts;
    if let Some(err) = m.give_up(consecutive) {
        m.finish(Err(err), now);
        return;
    }
    m.resend(out);
    m.transfer().rearm(now);
}

/// Cancel `m`: `MISSION_ACK(OPERATION_CANCELLED)` to the vehicle and
/// [`MissionError::Cancelled`] as the outcome.
fn cancel(m: &mut impl Machine, now: Instant, out: &mut Vec<MavMessage>) {
    if m.is_done() {
        return;
    }
    out.push(
        m.transfer()
            .ack(MavMissionResult::MAV_MISSION_OPERATION_CANCELLED),
    );
    m.finish(Err(MissionError::Cancelled), now);
}
