//! The guided setpoint stream: SET_POSITION_TARGET_GLOBAL_INT sent at
//! [`GUIDED_PERIOD`] while a setpoint is set, as PX4's OFFBOARD needs (a
//! stream of more than 2 Hz before the switch and all along; PX4 leaves the
//! mode when it stops). The operator's stop ends the stream.

use std::time::{Duration, Instant};

use mavlink::dialects::common::{
    MavFrame, MavMessage, PositionTargetTypemask, SET_POSITION_TARGET_GLOBAL_INT_DATA,
};
use tokio::sync::oneshot;
use tracing::info;

use super::state::{Actor, GuidedStream};
use crate::vehicle::command::GuidedSetpoint;
use crate::vehicle::error::LinkError;

/// How often a guided setpoint is sent again: 10 Hz, five times PX4's
/// 2 Hz minimum.
pub const GUIDED_PERIOD: Duration = Duration::from_millis(100);

/// The message for `sp` to the vehicle `(system, component)`; position and
/// heading, the rest ignored (what [`crate::vehicle::LinkHandle::guide`]
/// streams).
pub fn guided_setpoint_message(sp: &GuidedSetpoint, target: (u8, u8)) -> MavMessage {
    let mask = PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VX_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VY_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_VZ_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AX_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AY_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_AZ_IGNORE
        | PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE;
    MavMessage::SET_POSITION_TARGET_GLOBAL_INT(SET_POSITION_TARGET_GLOBAL_INT_DATA {
        lat_int: (sp.lat_deg * 1e7).round() as i32,
        lon_int: (sp.lon_deg * 1e7).round() as i32,
        alt: sp.alt_amsl_m as f32,
        yaw: crate::angle::wrap180(sp.yaw_deg).to_radians() as f32,
        type_mask: mask,
        target_system: target.0,
        target_component: target.1,
        coordinate_frame: MavFrame::MAV_FRAME_GLOBAL,
        ..Default::default()
    })
}

fn finite(sp: &GuidedSetpoint) -> bool {
    sp.lat_deg.is_finite()
        && sp.lon_deg.is_finite()
        && sp.alt_amsl_m.is_finite()
        && sp.yaw_deg.is_finite()
        && sp.lat_deg.abs() <= 90.0
        && sp.lon_deg.abs() <= 180.0
}

impl Actor {
    /// [`crate::vehicle::Command::Guide`].
    pub(super) fn on_guide(
        &mut self,
        setpoint: Option<GuidedSetpoint>,
        reply: oneshot::Sender<Result<(), LinkError>>,
        now: Instant,
    ) {
        let Some(sp) = setpoint else {
            if self.guided.take().is_some() {
                info!("guided setpoint stream stopped");
            }
            let _ = reply.send(Ok(()));
            return;
        };
        if !finite(&sp) {
            let _ = reply.send(Err(LinkError::InvalidSetpoint));
            return;
        }
        if self.peers().is_none() {
            let _ = reply.send(Err(LinkError::NoVehicle));
            return;
        }
        if self.guided.is_none() {
            info!(?sp, "guided setpoint stream started");
        }
        self.guided = Some(GuidedStream {
            setpoint: sp,
            next: now,
        });
        self.stream_guided(now);
        let _ = reply.send(Ok(()));
    }

    /// Queues the guided setpoint when it is due.
    pub(super) fn stream_guided(&mut self, now: Instant) {
        let Some(g) = self.guided else {
            return;
        };
        if now < g.next {
            return;
        }
        // With no vehicle to send to (the link lost), the period still
        // passes: a due time left in the past would wake the actor at once,
        // again and again, and starve its commands (the stop among them).
        if let Some((peers, _)) = self.peers() {
            self.out.push(guided_setpoint_message(
                &g.setpoint,
                (peers.target_system, peers.target_component),
            ));
        }
        let mut next = g.next + GUIDED_PERIOD;
        if next <= now {
            next = now + GUIDED_PERIOD;
        }
        self.guided = Some(GuidedStream { next, ..g });
    }
}
