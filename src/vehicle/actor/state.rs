//! The link actor's state: its watch channels, the transfer and commands in
//! flight, its clock, and what every part of it uses (the header it sends
//! with, the flush of its queued messages, the vehicle's peers).

use std::sync::Arc;
use std::time::Instant;

use mavlink::dialects::common::MavMessage;
use mavlink::{AsyncMavConnection, MavHeader, Message};
use tokio::sync::watch;
use tracing::{debug, warn};

use super::pending::PendingCommand;
use super::transfer::Transfer;
use crate::mission::upload::{self, Peers};
use crate::vehicle::command::Command;
use crate::vehicle::params::Params;
use crate::vehicle::router::Router;
use crate::vehicle::telemetry::{
    Attitude, GimbalAttitude, GimbalControl, GimbalManagerStatus, GlobalPosition, GpsRaw,
    HomePosition, LocalPosition, MissionProgress, Stamped, VehicleState,
};
use crate::vehicle::transport::Connection;

/// The guided setpoint stream's state in the actor (`guided.rs` sends it).
#[derive(Debug, Clone, Copy)]
pub(super) struct GuidedStream {
    /// The setpoint sent.
    pub(super) setpoint: crate::vehicle::command::GuidedSetpoint,
    /// When it is sent next.
    pub(super) next: Instant,
}

pub(super) struct Actor {
    pub(super) params: Params,
    pub(super) transfer_params: upload::Params,
    pub(super) conn: Option<Arc<Connection>>,
    pub(super) vehicle: watch::Sender<VehicleState>,
    pub(super) gp: watch::Sender<Option<Stamped<GlobalPosition>>>,
    pub(super) lp: watch::Sender<Option<Stamped<LocalPosition>>>,
    pub(super) gps_raw: watch::Sender<Option<Stamped<GpsRaw>>>,
    pub(super) att: watch::Sender<Option<Stamped<Attitude>>>,
    pub(super) home: watch::Sender<Option<Stamped<HomePosition>>>,
    pub(super) gimbal: watch::Sender<Option<Stamped<GimbalAttitude>>>,
    pub(super) progress: watch::Sender<Option<Stamped<MissionProgress>>>,
    pub(super) video_streams: watch::Sender<Vec<crate::vehicle::telemetry::VideoStreamInfo>>,
    pub(super) cameras: watch::Sender<Vec<crate::vehicle::telemetry::CameraInfo>>,
    pub(super) captures: watch::Sender<Vec<crate::vehicle::telemetry::ImageCaptured>>,
    /// Camera components asked for CAMERA_INFORMATION, and when.
    pub(super) camera_asked: Vec<(u8, Instant)>,
    pub(super) gimbal_manager: watch::Sender<Option<Stamped<GimbalManagerStatus>>>,
    pub(super) gimbal_control: Arc<watch::Sender<GimbalControl>>,
    pub(super) transfer: Option<Transfer>,
    pub(super) command: Option<PendingCommand>,
    /// The operator's stop, beside any other command in flight.
    pub(super) stop: Option<PendingCommand>,
    pub(super) next_heartbeat: Instant,
    pub(super) rates_requested: Option<Instant>,
    pub(super) rate_rounds: u32,
    pub(super) connect_failure_logged: bool,
    pub(super) out: Vec<MavMessage>,
    /// The forward endpoints' router and its mission gate.
    pub(super) router: Arc<Router>,
    /// Mission transfers waiting for another station's to end.
    pub(super) deferred: Vec<Command>,
    /// The guided setpoint stream, while one runs.
    pub(super) guided: Option<GuidedStream>,
}

impl Actor {
    fn header(&self) -> MavHeader {
        MavHeader {
            system_id: u32::from(self.params.system_id),
            component_id: self.params.component_id,
            sequence: 0,
        }
    }

    /// Sends everything queued in `out`. Without a connection the messages
    /// are dropped: the protocol machines resend on their own timeouts.
    pub(super) async fn flush(&mut self) {
        if self.out.is_empty() {
            return;
        }
        let header = self.header();
        if let Some(conn) = &self.conn {
            for m in self.out.drain(..) {
                // MAVLink 1 has 8-bit message ids (and the crate panics on
                // larger ones): such messages cannot go out on a v1 link.
                if self.params.mavlink1 && m.message_id() > 255 {
                    warn!(
                        id = m.message_id(),
                        "message id does not fit MAVLink 1; not sent"
                    );
                    continue;
                }
                if let Err(e) = conn.send(&header, &m).await {
                    debug!(error = %e, "send failed");
                }
            }
        } else {
            self.out.clear();
        }
    }

    /// The vehicle's peers for a transfer, if one is heard.
    pub(super) fn peers(&self) -> Option<(Peers, VehicleState)> {
        let v = self.vehicle.borrow().clone();
        let sys = v.system_id?;
        if v.link_lost {
            return None;
        }
        Some((
            Peers {
                own_system: self.params.system_id,
                own_component: self.params.component_id,
                target_system: sys,
                target_component: v.component_id,
            },
            v,
        ))
    }
}
