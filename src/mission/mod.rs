//! Missions: planning (pure, [`plan`]) and the transfer protocol ([`upload`]).
//!
//! [`plan`] turns a camera target into the mission items PX4 or ArduPilot
//! accept and exports QGroundControl `.plan` files. [`upload`] holds the
//! MAVLink mission protocol as clock-driven state machines (upload, download)
//! that the link actor in [`crate::vehicle`] drives; neither imports tokio.

pub mod plan;
pub mod upload;

pub use plan::{Flavour, Home, MissionItem, PlanError, Target};
pub use upload::{Download, MissionError, UploadReport};

use serde::{Deserialize, Serialize};

/// The `[mission]` section of the configuration: planning and transfer numbers.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Planner numbers and the geofence.
    pub plan: plan::Params,
    /// Transfer timeouts and retries.
    pub transfer: upload::Params,
}
