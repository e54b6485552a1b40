//! The autopilot as the gimbal manager (gimbal protocol v2): who holds control,
//! DO_GIMBAL_MANAGER_CONFIGURE and PITCHYAW from the ground and in missions, the
//! refusals said in a STATUSTEXT.

use mavlink::dialects::common::{MavMessage, MavSeverity, STATUSTEXT_DATA};

use super::Autopilot;
use super::mission::{Flavour, Peer};
use crate::vehicle::wrap_pi;

/// The gimbal device id the autopilot's gimbal manager answers for (a
/// non-MAVLink gimbal: ids 1 to 6).
pub const GIMBAL_DEVICE_ID: u8 = 1;

/// Gimbal device id param (param7) addresses our gimbal: 0 (all) or ours.
pub(super) fn gimbal_device_ok(v: f32) -> bool {
    v.is_finite() && (v.round() == 0.0 || v.round() == f32::from(GIMBAL_DEVICE_ID))
}

/// A STATUSTEXT (cut to the 50 bytes the message holds).
pub(super) fn statustext(severity: MavSeverity, text: &str) -> MavMessage {
    let mut t = String::new();
    for ch in text.chars() {
        if t.len() + ch.len_utf8() > 50 {
            break;
        }
        t.push(ch);
    }
    MavMessage::STATUSTEXT(STATUSTEXT_DATA {
        severity,
        text: t.as_str().into(),
        id: 0,
        chunk_seq: 0,
    })
}

impl Autopilot {
    pub(super) fn gimbal_pitch_yaw(&mut self, pitch: f32, yaw: f32, flags: f32) {
        let earth_frame = (flags as u32) & 16 != 0;
        let yaw = if earth_frame && yaw.is_finite() {
            wrap_pi(f64::from(yaw).to_radians() - self.vehicle.yaw()).to_degrees()
        } else {
            f64::from(yaw)
        };
        self.vehicle.set_gimbal_target(f64::from(pitch), yaw);
    }

    /// DO_GIMBAL_MANAGER_CONFIGURE from `from` (params as in the command):
    /// the new primary and secondary controllers. Err for a value out of range.
    pub(super) fn gimbal_configure(&mut self, p: &[f32; 7], from: Peer) -> Result<(), ()> {
        let pick = |v: f32, current: u8, own: u8, held_by_sender: bool| -> Result<u8, ()> {
            if !v.is_finite() {
                return Err(());
            }
            match v.round() as i32 {
                x @ 0..=255 => Ok(x as u8),
                -1 => Ok(current),
                -2 => Ok(own),
                -3 if held_by_sender => Ok(0),
                -3 => Ok(current),
                _ => Err(()),
            }
        };
        let held = self.gimbal_primary == (from.system, from.component);
        let primary = (
            pick(p[0], self.gimbal_primary.0, from.system, held)?,
            pick(p[1], self.gimbal_primary.1, from.component, held)?,
        );
        let held2 = self.gimbal_secondary == (from.system, from.component);
        let secondary = (
            pick(p[2], self.gimbal_secondary.0, from.system, held2)?,
            pick(p[3], self.gimbal_secondary.1, from.component, held2)?,
        );
        self.gimbal_primary = primary;
        self.gimbal_secondary = secondary;
        Ok(())
    }

    /// The autopilot itself as a MAVLink peer (the sender of mission commands).
    pub(super) fn own_peer(&self) -> Peer {
        Peer {
            system: self.params.system_id,
            component: self.params.component_id,
        }
    }

    /// Whether a mission gimbal command may move the gimbal (see the module
    /// documentation).
    pub(super) fn mission_gimbal_allowed(&self) -> bool {
        let own = self.own_peer();
        let holder = self.gimbal_primary;
        if holder == (own.system, own.component) {
            return true;
        }
        self.params.flavour == Flavour::ArduPilot
            && holder != (0, 0)
            && self.gcs.is_some_and(|g| (g.system, g.component) == holder)
    }

    pub(super) fn gimbal_refused_text(&self, from: Peer) -> MavMessage {
        let (s, c) = self.gimbal_primary;
        statustext(
            MavSeverity::MAV_SEVERITY_WARNING,
            &format!(
                "Gimbal: PITCHYAW from {}/{} denied, in control: {s}/{c}",
                from.system, from.component
            ),
        )
    }
}
