//! The requests the handle sends to the link actor, each with its reply
//! channel, and the stop's acknowledgement.

use serde::Serialize;
use tokio::sync::oneshot;

use crate::mission::{Download, MissionItem, UploadReport};

use super::error::LinkError;
use super::modes::FlightMode;

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

/// A position setpoint for guided control (PX4 OFFBOARD, ArduPilot
/// GUIDED), sent as SET_POSITION_TARGET_GLOBAL_INT with an AMSL altitude:
/// a ground station does not know PX4's LOCAL_NED origin (the EKF's), and
/// 1e-7 degrees are about a centimetre.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct GuidedSetpoint {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, metres.
    pub alt_amsl_m: f64,
    /// Heading, degrees clockwise from north.
    pub yaw_deg: f64,
}

impl GuidedSetpoint {
    /// The setpoint of a planned target (its altitude is above `home`).
    pub fn at_target(t: &crate::mission::plan::Target, home: &crate::mission::plan::Home) -> Self {
        Self {
            lat_deg: t.lat_deg,
            lon_deg: t.lon_deg,
            alt_amsl_m: home.alt_amsl_m + t.alt_m,
            yaw_deg: t.yaw_deg,
        }
    }
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
    /// Start (Some), move or stop (None) the guided setpoint stream: the
    /// setpoint is sent at once and then every
    /// [`crate::vehicle::GUIDED_PERIOD`] until replaced or stopped (the
    /// operator's stop ends it too). Replies once the first is queued.
    Guide {
        /// The setpoint, or None to stop the stream.
        setpoint: Option<GuidedSetpoint>,
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
