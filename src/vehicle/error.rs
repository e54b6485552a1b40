//! LinkError: what the link and its commands fail with.

use super::modes::FlightMode;
use crate::mission::MissionError;

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
    /// A guided setpoint with a non-finite or out-of-range coordinate.
    #[error(
        "invalid guided setpoint: latitude, longitude, altitude and heading must be finite and in range"
    )]
    InvalidSetpoint,
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
