//! Commands the autopilot answers with COMMAND_ACK (COMMAND_LONG and COMMAND_INT
//! unified), the legacy REQUEST_DATA_STREAM, ArduPilot's CONDITION_YAW.

use mavlink::dialects::common::{
    COMMAND_ACK_DATA, MESSAGE_INTERVAL_DATA, MavCmd, MavMessage, MavResult,
};

use super::Autopilot;
use super::flight::Exec;
use super::gimbal::gimbal_device_ok;
use super::mission::{Flavour, Peer};
use super::mode::Mode;
use crate::vehicle::wrap_pi;

/// The parameters of a COMMAND_LONG or COMMAND_INT, unified.
#[derive(Debug, Clone, Copy)]
pub(super) struct Command {
    pub(super) command: MavCmd,
    pub(super) p: [f32; 7],
}

pub(super) fn cmd_ack(to: Peer, command: MavCmd, result: MavResult) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        progress: 0,
        result_param2: 0,
        target_system: to.system,
        target_component: to.component,
    })
}

impl Autopilot {
    pub(super) fn command(
        &mut self,
        c: &Command,
        from: Peer,
        out: &mut Vec<MavMessage>,
    ) -> MavResult {
        use MavCmd::*;
        let p = c.p;
        let ardu = self.params.flavour == Flavour::ArduPilot;
        match c.command {
            MAV_CMD_COMPONENT_ARM_DISARM => {
                let force = (p[1] - 21196.0).abs() < 0.5;
                let ok = if p[0] > 0.5 {
                    self.arm()
                } else {
                    self.disarm(force)
                };
                if ok {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MAV_CMD_DO_SET_MODE => {
                let base = p[0] as u32;
                if base & 1 == 0 {
                    return MavResult::MAV_RESULT_UNSUPPORTED;
                }
                let mode = if ardu {
                    Mode::from_ardupilot(p[1] as u32)
                } else {
                    Mode::from_px4(p[1] as u32, p[2] as u32)
                };
                match mode {
                    // PX4's OFFBOARD needs a setpoint stream first (the
                    // scripted operator's, or the ground station's).
                    Some(Mode::Offboard)
                        if !ardu && self.external.is_none() && !self.offboard_stream_ready() =>
                    {
                        MavResult::MAV_RESULT_DENIED
                    }
                    Some(m) => {
                        self.set_mode(m);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    None => MavResult::MAV_RESULT_UNSUPPORTED,
                }
            }
            MAV_CMD_MISSION_START => {
                let n = self.mission.items().len();
                if n <= usize::from(self.mission.first_item()) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                let first = p[0];
                if first.is_finite() && first >= 0.0 && (first as usize) < n && first > 0.0 {
                    self.mission.set_current(first as u16);
                } else if self.exec.done {
                    self.mission.set_current(self.mission.first_item());
                }
                self.mode = Mode::Mission;
                self.exec = Exec::reset();
                if ardu && !self.armed {
                    return MavResult::MAV_RESULT_DENIED;
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_SET_MISSION_CURRENT => {
                let seq = p[0];
                if seq.is_finite()
                    && seq >= f32::from(self.mission.first_item())
                    && (seq as usize) < self.mission.items().len()
                {
                    self.mission.set_current(seq as u16);
                    self.exec = Exec::reset();
                    out.push(self.mission_current_msg());
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MAV_CMD_NAV_TAKEOFF => {
                if !self.vehicle.landed() && self.took_off {
                    return MavResult::MAV_RESULT_TEMPORARILY_REJECTED;
                }
                if p[6].is_finite() && !ardu {
                    // PX4: param7 is AMSL.
                    self.params.takeoff_alt_m =
                        (f64::from(p[6]) - self.params.vehicle.home.alt_m).max(1.0);
                } else if p[6].is_finite() && ardu {
                    self.params.takeoff_alt_m = f64::from(p[6]).max(1.0);
                }
                self.set_mode(Mode::Takeoff);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_NAV_LAND => {
                self.set_mode(Mode::Land);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_NAV_RETURN_TO_LAUNCH => {
                self.set_mode(Mode::Rtl);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                if !gimbal_device_ok(p[6]) {
                    return MavResult::MAV_RESULT_FAILED;
                }
                if (from.system, from.component) != self.gimbal_primary {
                    out.push(self.gimbal_refused_text(from));
                    return MavResult::MAV_RESULT_DENIED;
                }
                self.gimbal_pitch_yaw(p[0], p[1], p[4]);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE => {
                if !gimbal_device_ok(p[6]) {
                    return MavResult::MAV_RESULT_FAILED;
                }
                match self.gimbal_configure(&p, from) {
                    Ok(()) => {
                        out.extend(self.build(281));
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    Err(()) => MavResult::MAV_RESULT_DENIED,
                }
            }
            MAV_CMD_DO_MOUNT_CONTROL => {
                self.vehicle
                    .set_gimbal_target(f64::from(p[0]), f64::from(p[2]));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_IMAGE_START_CAPTURE => {
                if !(p[1] >= 0.0 && p[2] >= 0.0) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                self.start_capture(f64::from(p[1]), p[2] as u32);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_IMAGE_STOP_CAPTURE => {
                self.interval_capture = None;
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_DIGICAM_CONTROL => {
                if (p[4] - 1.0).abs() < 0.5 {
                    self.capture_now();
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_CONDITION_YAW if ardu => {
                let yaw = self.condition_yaw_target(&p);
                let hold = self.hold_point.map_or(self.vehicle.p_ned(), |h| h.0);
                self.hold_point = Some((hold, yaw));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_DO_CHANGE_SPEED => {
                if p[1] > 0.0 {
                    self.cruise_speed = Some(f64::from(p[1]));
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_SET_MESSAGE_INTERVAL => {
                let id = p[0] as u32;
                let us = p[1];
                let Some(s) = self.streams.iter_mut().find(|s| s.id == id) else {
                    return MavResult::MAV_RESULT_UNSUPPORTED;
                };
                let default = self.params.default_interval(id).unwrap_or(1.0);
                s.interval = if us < 0.0 {
                    None
                } else if us == 0.0 {
                    Some(default)
                } else {
                    Some((f64::from(us) * 1e-6).max(0.002))
                };
                s.next = self.now;
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_GET_MESSAGE_INTERVAL => {
                let id = p[0] as u32;
                let interval_us = self
                    .streams
                    .iter()
                    .find(|s| s.id == id)
                    .map_or(0, |s| s.interval.map_or(-1, |i| (i * 1e6).round() as i32));
                out.push(MavMessage::MESSAGE_INTERVAL(MESSAGE_INTERVAL_DATA {
                    interval_us,
                    message_id: id as u16,
                }));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_REQUEST_MESSAGE => match self.build(p[0] as u32) {
                Some(m) => {
                    out.push(m);
                    MavResult::MAV_RESULT_ACCEPTED
                }
                None => MavResult::MAV_RESULT_UNSUPPORTED,
            },
            MAV_CMD_GET_HOME_POSITION => {
                out.extend(self.build(242));
                MavResult::MAV_RESULT_ACCEPTED
            }
            MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES => {
                out.extend(self.build(148));
                MavResult::MAV_RESULT_ACCEPTED
            }
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        }
    }

    /// The legacy REQUEST_DATA_STREAM (ArduPilot ground stations send it;
    /// PX4 ignores it): a stream group at a rate in Hz, or off.
    pub(super) fn request_data_stream(&mut self, stream: u32, rate_hz: u16, start: u8) {
        if self.params.flavour != Flavour::ArduPilot {
            return;
        }
        // ArduPilot's groups, restricted to the messages we produce.
        let ids: &[u32] = match stream {
            0 => &[1, 24, 42, 30, 33, 32, 285, 2],
            2 => &[1, 24, 42],
            6 => &[33, 32],
            10 => &[30],
            12 => &[2, 285],
            _ => &[],
        };
        for s in self.streams.iter_mut().filter(|s| ids.contains(&s.id)) {
            s.interval = if start == 0 || rate_hz == 0 {
                None
            } else {
                Some(1.0 / f64::from(rate_hz))
            };
            s.next = self.now;
        }
    }

    pub(super) fn condition_yaw_target(&self, p: &[f32; 7]) -> f64 {
        let angle = f64::from(p[0]).to_radians();
        if p[3] > 0.5 {
            let dir = if p[2] < 0.0 { -1.0 } else { 1.0 };
            wrap_pi(self.vehicle.yaw() + dir * angle)
        } else {
            wrap_pi(angle)
        }
    }
}
