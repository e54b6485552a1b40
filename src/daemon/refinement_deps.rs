//! What the shot refinement's task and its servo phase share (below both
//! of them): the task's dependencies ([`Deps`]), why a refinement ends
//! early ([`Abort`]), and the vehicle's reported position as the loop
//! reads it.

use std::sync::Arc;
use std::time::Instant;

use nalgebra::Vector3;

use super::geo_service::GeoService;
use super::slam_shared::SlamShared;
use crate::api::ShotEvents;
use crate::geo::LocalFrame;
use crate::mission::plan::{self, Home};
use crate::refine::PositionReport;
use crate::refine::desired::{PictureError, Pictures};
use crate::shot::store::ShotStore;
use crate::vehicle::{GlobalPosition, LinkHandle, Stamped};
use crate::video::live::Ingest;

/// The loop's tunables.
pub use crate::refine::loop_params::LoopParams as Params;

/// What the loop reads and drives.
pub struct Deps {
    /// The shots (rounds are recorded here).
    pub store: Arc<ShotStore>,
    /// The georeference.
    pub geo: Arc<GeoService>,
    /// The SLAM map.
    pub slam: Arc<SlamShared>,
    /// The newest video frame.
    pub ingest: Arc<Ingest>,
    /// The vehicle.
    pub link: LinkHandle,
    /// Mission planning (its geofence checks every target).
    pub plan: plan::Params,
    /// Serialises mission actions with the API.
    pub actions: Arc<tokio::sync::Mutex<()>>,
    /// Tunables.
    pub params: Params,
    /// Desired pictures (and masks) by shot id, made at upload.
    pub pictures: Pictures,
    /// The loop's clock origin (measurement times are seconds since it).
    pub epoch: Instant,
    /// Where the shot's progress is published.
    pub events: Arc<ShotEvents>,
}

/// Why the loop stopped a shot's refinement early; its Display is the
/// `reason` recorded on the shot's mission (`details.refinement`).
#[derive(Debug, thiserror::Error)]
pub enum Abort {
    /// The SLAM has no map.
    #[error("no SLAM map")]
    NoMap,
    /// The shot has no pose in the map.
    #[error("shot {shot} is not localised")]
    NotLocalised {
        /// The shot's id.
        shot: String,
    },
    /// The shot has no desired picture.
    #[error(transparent)]
    Picture(#[from] PictureError),
    /// A blocking task of the loop panicked or was cancelled.
    #[error("the round failed: {0}")]
    Task(#[from] tokio::task::JoinError),
    /// The autopilot's flavour is not known.
    #[error("the autopilot is neither PX4 nor ArduPilot")]
    UnknownAutopilot,
    /// No home position to plan from.
    #[error("home position not known")]
    NoHome,
    /// The planner refused the (corrected) target.
    #[error("plan: {0}")]
    Plan(#[from] plan::PlanError),
    /// The plan has no waypoint to wait for.
    #[error("the plan has no waypoint")]
    NoWaypoint,
    /// The vehicle did not reach the waypoint and hold still in time.
    #[error("waypoint {waypoint} not reached and steady within {waited_s:.0} s")]
    NoArrival {
        /// The waypoint's sequence number.
        waypoint: u16,
        /// How long the loop waited, s.
        waited_s: f64,
    },
    /// No video frame came after the arrival.
    #[error("no video frame after the arrival")]
    NoFrame,
    /// No georeference to turn the map pose into a target.
    #[error("georeference: {0}")]
    Georeference(#[from] crate::geo::GeoError),
    /// The uploaded mission was not read back intact.
    #[error("{0}")]
    Upload(crate::vehicle::LinkError),
    /// The vehicle refused to start the mission.
    #[error("start: {0}")]
    Start(crate::vehicle::LinkError),
    /// The daemon stopped the loop (shutdown, another shot).
    #[error("cancelled")]
    Cancelled,
    /// The vehicle refused guided control (the servo's setpoints or mode).
    #[error("guided control: {0}")]
    Guided(crate::vehicle::LinkError),
    /// The link to the vehicle was lost while servoing: the setpoint
    /// stream stopped, and the autopilot's own failsafe (PX4: offboard
    /// loss; ArduPilot: the GCS failsafe) decides what it flies.
    #[error(
        "the link to the vehicle was lost (no heartbeat for {after_s:.1} s): servoing stopped, the autopilot's failsafe flies it"
    )]
    LinkLost {
        /// The age of the last heartbeat when the loss was declared, s.
        after_s: f64,
    },
}

/// A position report as the refinement reads it.
pub(super) fn position_report(g: &Stamped<GlobalPosition>) -> PositionReport {
    PositionReport {
        lat_deg: g.value.lat_deg,
        lon_deg: g.value.lon_deg,
        rel_alt_m: g.value.rel_alt_m,
        vel_ned_m_s: g.value.vel_ned_m_s,
        age_s: crate::clock::since(g.received).as_secs_f64(),
    }
}

/// The vehicle's reported position now (fresh telemetry only), local NED
/// metres around home.
pub(super) fn reported_ned(deps: &Deps, frame: &LocalFrame, home: &Home) -> Option<Vector3<f64>> {
    let max_age = deps.params.max_telemetry_age;
    (*deps.link.telemetry.global_position.borrow())
        .filter(|g| crate::clock::since(g.received) <= max_age)
        .and_then(|g| position_report(&g).ned(frame, home.alt_amsl_m))
}
