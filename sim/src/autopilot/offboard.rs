//! Guided control from a ground station: SET_POSITION_TARGET_LOCAL_NED and
//! SET_POSITION_TARGET_GLOBAL_INT, with the real autopilots' rules.
//!
//! - **PX4 (OFFBOARD)**: setpoints are "proof of life". The mode is
//!   accepted only after a stream of them has lasted at least
//!   [`super::AutopilotParams::offboard_proof_s`] with gaps shorter than
//!   [`super::AutopilotParams::offboard_loss_s`] (PX4: > 2 Hz for more than
//!   a second before the switch); in OFFBOARD, a gap longer than the loss
//!   time (PX4's `COM_OF_LOSS_T`, 1 s) ends the mode: the vehicle holds
//!   where it is (PX4's offboard-loss failsafe to a position-holding mode)
//!   and a STATUSTEXT says why. Setpoints are taken in any mode (a stream
//!   must run before the switch) and flown only in OFFBOARD.
//! - **ArduPilot (GUIDED)**: a position target is taken only in GUIDED and
//!   held until the next one (no stream needed: ArduPilot's guided
//!   position controller keeps its last target).
//!
//! Frames: LOCAL_NED (the autopilot's local frame, origin at home) for the
//! local message; GLOBAL (AMSL; its deprecated synonym GLOBAL_INT) and
//! GLOBAL_RELATIVE_ALT (and _INT) for the global one. Position and yaw are flown; a message whose
//! type mask ignores the position is taken as proof of life only (PX4)
//! and otherwise ignored: the simulator's guided control flies positions.

use mavlink::dialects::common::{MavFrame, MavMessage, MavSeverity, PositionTargetTypemask};
use nalgebra::Vector3;

use super::gimbal::statustext;
use super::{Autopilot, Mode};
use crate::geodesy::Geodetic;
use crate::vehicle::Setpoint;

/// What the ground station streamed last.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct OffboardStream {
    /// The position setpoint to fly (None: none received yet).
    pub(super) setpoint: Option<Setpoint>,
    /// When the current unbroken stream began, seconds since boot.
    pub(super) since: Option<f64>,
    /// When the last setpoint message arrived.
    pub(super) last: Option<f64>,
}

const POSITION_IGNORED: PositionTargetTypemask =
    PositionTargetTypemask::POSITION_TARGET_TYPEMASK_X_IGNORE
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Y_IGNORE)
        .union(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_Z_IGNORE);

impl Autopilot {
    /// Takes a SET_POSITION_TARGET_* message addressed to us; false when
    /// `msg` is not one.
    pub(super) fn guided_setpoint(&mut self, msg: &MavMessage) -> bool {
        let ardu = self.params.flavour == super::Flavour::ArduPilot;
        let (position, yaw, mask) = match msg {
            MavMessage::SET_POSITION_TARGET_LOCAL_NED(d)
                if self.for_us(d.target_system, d.target_component) =>
            {
                let p = match d.coordinate_frame {
                    MavFrame::MAV_FRAME_LOCAL_NED => {
                        Some(Vector3::new(f64::from(d.x), f64::from(d.y), f64::from(d.z)))
                    }
                    // Body frames and the rest: not flown here.
                    _ => None,
                };
                (p, d.yaw, d.type_mask)
            }
            MavMessage::SET_POSITION_TARGET_GLOBAL_INT(d)
                if self.for_us(d.target_system, d.target_component) =>
            {
                let home_alt = self.params.vehicle.home.alt_m;
                let alt = match d.coordinate_frame {
                    #[allow(deprecated)]
                    MavFrame::MAV_FRAME_GLOBAL_INT | MavFrame::MAV_FRAME_GLOBAL => {
                        Some(f64::from(d.alt))
                    }
                    #[allow(deprecated)]
                    MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
                    | MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT => Some(f64::from(d.alt) + home_alt),
                    _ => None,
                };
                let p = alt.map(|alt_m| {
                    self.vehicle.frame().geodetic_to_ned(&Geodetic {
                        lat_deg: f64::from(d.lat_int) / 1e7,
                        lon_deg: f64::from(d.lon_int) / 1e7,
                        alt_m,
                    })
                });
                (p, d.yaw, d.type_mask)
            }
            _ => return false,
        };
        if ardu && self.mode != Mode::Offboard {
            // ArduPilot takes guided targets in GUIDED only.
            return true;
        }
        let now = self.now;
        let gap_ok = self
            .offboard
            .last
            .is_some_and(|t| now - t <= self.params.offboard_loss_s);
        if !gap_ok {
            self.offboard.since = Some(now);
        }
        self.offboard.last = Some(now);
        let finite = position.is_some_and(|p| p.iter().all(|x| x.is_finite()));
        if let Some(p) = position.filter(|_| finite && !mask.intersects(POSITION_IGNORED)) {
            let yaw = (!mask.contains(PositionTargetTypemask::POSITION_TARGET_TYPEMASK_YAW_IGNORE)
                && yaw.is_finite())
            .then_some(f64::from(yaw));
            self.offboard.setpoint = Some(Setpoint::Position {
                p_ned: p,
                yaw,
                max_speed: None,
            });
        }
        true
    }

    /// PX4: a stream of setpoints has run long enough, without a gap
    /// longer than the loss time, for OFFBOARD to be engaged.
    pub(super) fn offboard_stream_ready(&self) -> bool {
        match (self.offboard.since, self.offboard.last) {
            (Some(since), Some(last)) => {
                self.now - last <= self.params.offboard_loss_s
                    && last - since >= self.params.offboard_proof_s
                    && self.offboard.setpoint.is_some()
            }
            _ => false,
        }
    }

    /// The setpoint OFFBOARD / GUIDED flies now: the scripted operator's,
    /// else the ground station's. PX4 leaves OFFBOARD for a position hold
    /// when the ground station's stream stopped (`out` gets the
    /// STATUSTEXT); None: nothing to fly (hold here).
    pub(super) fn guided_flown(&mut self, out: &mut Vec<MavMessage>) -> Option<Setpoint> {
        if let Some(sp) = self.external {
            return Some(sp);
        }
        let ardu = self.params.flavour == super::Flavour::ArduPilot;
        if !ardu {
            let lost = self
                .offboard
                .last
                .is_none_or(|t| self.now - t > self.params.offboard_loss_s);
            if lost {
                self.offboard = OffboardStream::default();
                self.set_mode(Mode::Hold);
                out.push(statustext(
                    MavSeverity::MAV_SEVERITY_WARNING,
                    "Offboard control lost: holding position",
                ));
                return None;
            }
        }
        self.offboard.setpoint
    }

    /// Forget the ground station's setpoints (a mode change away from
    /// GUIDED on ArduPilot: a later GUIDED starts from a hold).
    pub(super) fn clear_guided_target(&mut self) {
        self.offboard.setpoint = None;
    }
}
