//! The link to the drone: MAVLink transports, the link actor, the telemetry cache.
//!
//! One tokio task (the *link actor*, [`spawn`]) owns the connection. It
//!
//! - connects from a URL ([`transport`]) and reconnects with exponential
//!   backoff when the device vanishes or the socket fails; a `udpin:` socket
//!   is bound once and kept (port 0: [`LinkHandle::bound_addr`] says which
//!   port), or handed in already bound ([`spawn_with_socket`]);
//! - sends the GCS `HEARTBEAT` at 1 Hz;
//! - tracks the vehicle (system id, PX4/ArduPilot from its heartbeat, mode,
//!   armed, link lost after a configurable silence) in a watch channel;
//! - asks for telemetry rates with `SET_MESSAGE_INTERVAL` whenever the vehicle
//!   (re)appears;
//! - keeps the latest position, local position, attitude, home, gimbal
//!   attitude and mission progress, each with its receive time, in watch
//!   channels ([`Telemetry`]);
//! - takes [`Command`]s with oneshot replies: mission upload/download/cancel
//!   (the [`crate::mission::upload`] state machines, driven here), and arming,
//!   mode and mission start, which are only ever sent when an operator asks;
//! - keeps one command waiting for its COMMAND_ACK at a time, and beside it
//!   the operator's stop ([`LinkHandle::hold`]), which is sent at once
//!   whatever else is in flight (a mode change in flight gives way to it);
//! - follows MAVLink's gimbal protocol v2 for every caller of the handle:
//!   before a mission that points the gimbal starts
//!   ([`LinkHandle::start_mission`]) and before a direct gimbal command
//!   ([`LinkHandle::point_gimbal`]) it reads `GIMBAL_MANAGER_STATUS`
//!   (asking for it with `MAV_CMD_REQUEST_MESSAGE` when none is fresh),
//!   notes who is in primary control, and takes control with
//!   `MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE` (our sysid/compid as primary, the
//!   manager's gimbal device id); it gives control back (param1/param2 -3,
//!   "remove control if in control") when that mission completes, when the
//!   operator switches to another mode, or on [`LinkHandle::release_gimbal`].
//!   A refusal or silence is a warning in [`GimbalControl`] and the log,
//!   never a failed mission start: PX4 missions take control themselves
//!   (their first item, see [`crate::mission::plan`]) and ArduPilot runs
//!   mission gimbal items whoever is in control.
//!
//! Shutdown: the actor ends when its `CancellationToken` is cancelled or every
//! [`LinkHandle`] is dropped.

mod actor;
mod command;
mod error;
mod handle;
mod modes;
mod params;
pub mod router;
mod telemetry;
pub mod transport;

pub use actor::{GUIDED_PERIOD, guided_setpoint_message};
pub use actor::{spawn, spawn_with_socket};
pub use command::{Command, GuidedSetpoint, HoldAck};
pub use error::LinkError;
pub use handle::{LinkHandle, PhotoReport, release_params};
pub use modes::{FlightMode, ardupilot_mode_name, mode_params, px4_mode_name};
pub use params::{Params, Rates};
pub use telemetry::{
    Attitude, CAPTURES_KEPT, CameraInfo, GimbalAttitude, GimbalControl, GimbalManagerStatus,
    GlobalPosition, GpsRaw, HomePosition, ImageCaptured, LocalPosition, MissionProgress, Stamped,
    Telemetry, VehicleState, VideoStreamInfo, quat_to_euler_deg,
};
pub use transport::{LinkUrl, Signing};
