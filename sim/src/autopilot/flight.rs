//! Mission execution and what the vehicle flies: each item started, its
//! setpoint and when it is reached, RTL's stages, holding, the mode's control.

use mavlink::dialects::common::{MISSION_ITEM_REACHED_DATA, MavCmd, MavMessage, MissionState};
use nalgebra::Vector3;

use super::Autopilot;
use super::mission::MissionItem;
use super::mode::Mode;
use crate::geodesy::Geodetic;
use crate::vehicle::{Setpoint, wrap_pi};

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum RtlStage {
    Climb,
    Return,
    Land,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) enum Phase {
    /// Nothing to do (DO items complete at once).
    Instant,
    Takeoff {
        z: f64,
    },
    Goto {
        target: Vector3<f64>,
        yaw: Option<f64>,
        acc: f64,
        hold: f64,
        climb_first: bool,
    },
    Land {
        xy: Option<(f64, f64)>,
    },
    Rtl(RtlStage),
    WaitYaw {
        yaw: f64,
    },
    WaitGimbal {
        since: f64,
        then_capture: bool,
    },
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Exec {
    pub(super) seq: Option<u16>,
    pub(super) phase: Phase,
    reached_at: Option<f64>,
    pub(super) done: bool,
}

impl Exec {
    pub(super) fn reset() -> Self {
        Self {
            seq: None,
            phase: Phase::Instant,
            reached_at: None,
            done: false,
        }
    }
}

impl Autopilot {
    /// True when the current mode will lift off from the ground.
    pub(super) fn wants_to_fly(&self) -> bool {
        match self.mode {
            Mode::Takeoff => true,
            Mode::Mission => {
                !self.exec.done
                    && self.mission.items().len() > usize::from(self.mission.first_item())
            }
            Mode::Offboard => self.external.is_some() || self.offboard.setpoint.is_some(),
            _ => false,
        }
    }

    fn hold_here(&mut self) -> Setpoint {
        let (p, yaw) = *self
            .hold_point
            .get_or_insert((self.vehicle.p_ned(), self.vehicle.yaw()));
        Setpoint::Position {
            p_ned: p,
            yaw: Some(yaw),
            max_speed: None,
        }
    }

    pub(super) fn control(&mut self, out: &mut Vec<MavMessage>) {
        if !self.armed {
            self.vehicle.set_setpoint(Setpoint::Idle);
            return;
        }
        let sp = match self.mode {
            Mode::Manual | Mode::Position | Mode::Hold => {
                if self.vehicle.landed() {
                    Setpoint::Idle
                } else {
                    self.hold_here()
                }
            }
            Mode::Offboard => match self.guided_flown(out) {
                Some(sp) => sp,
                None => self.hold_here(),
            },
            Mode::Takeoff => {
                let p = self.vehicle.p_ned();
                let z = -self.params.takeoff_alt_m;
                if (p.z - z).abs() < self.params.altitude_acceptance_m * 0.25 {
                    self.hold_point = Some((Vector3::new(p.x, p.y, z), self.vehicle.yaw()));
                    self.mode = Mode::Hold;
                    self.hold_here()
                } else {
                    Setpoint::Position {
                        p_ned: Vector3::new(p.x, p.y, z),
                        yaw: None,
                        max_speed: None,
                    }
                }
            }
            Mode::Land => Setpoint::Land,
            Mode::Rtl => self.rtl_setpoint(),
            Mode::Mission => self.mission_setpoint(out),
        };
        // Do not leave the ground in hold-type modes.
        self.vehicle.set_setpoint(sp);
    }

    fn rtl_setpoint(&mut self) -> Setpoint {
        let p = self.vehicle.p_ned();
        let rtl_z = -self.params.rtl_alt_m;
        let z = p.z.min(rtl_z);
        let speed = self.cruise_speed;
        loop {
            match self.rtl {
                RtlStage::Climb => {
                    if p.z <= rtl_z + 0.5 || (p.x.hypot(p.y) < 1.0) {
                        self.rtl = RtlStage::Return;
                        continue;
                    }
                    return Setpoint::Position {
                        p_ned: Vector3::new(p.x, p.y, rtl_z),
                        yaw: None,
                        max_speed: speed,
                    };
                }
                RtlStage::Return => {
                    if p.x.hypot(p.y) < 0.5 {
                        self.rtl = RtlStage::Land;
                        continue;
                    }
                    let yaw = if p.x.hypot(p.y) > 2.0 {
                        Some((-p.y).atan2(-p.x))
                    } else {
                        None
                    };
                    return Setpoint::Position {
                        p_ned: Vector3::new(0.0, 0.0, z),
                        yaw,
                        max_speed: speed,
                    };
                }
                RtlStage::Land => return Setpoint::Land,
            }
        }
    }

    fn item_target(&self, item: &MissionItem) -> Vector3<f64> {
        let home = self.params.vehicle.home;
        let alt = if super::mission::is_relative_alt(item.frame) {
            home.alt_m + f64::from(item.z)
        } else {
            f64::from(item.z)
        };
        let (lat, lon) = if item.x == 0.0 && item.y == 0.0 {
            let g = self.vehicle.geodetic();
            (g.lat_deg, g.lon_deg)
        } else {
            (item.x, item.y)
        };
        self.vehicle.frame().geodetic_to_ned(&Geodetic {
            lat_deg: lat,
            lon_deg: lon,
            alt_m: alt,
        })
    }

    pub(super) fn mission_current_msg(&self) -> MavMessage {
        let n = self.mission.items().len();
        let state = if n <= usize::from(self.mission.first_item()) {
            MissionState::MISSION_STATE_NO_MISSION
        } else if self.exec.done {
            MissionState::MISSION_STATE_COMPLETE
        } else if self.mode == Mode::Mission && self.armed {
            MissionState::MISSION_STATE_ACTIVE
        } else if self.exec.seq.is_some() {
            MissionState::MISSION_STATE_PAUSED
        } else {
            MissionState::MISSION_STATE_NOT_STARTED
        };
        self.mission.mission_current(state)
    }

    fn start_item(&mut self, seq: u16, out: &mut Vec<MavMessage>) {
        let Some(item) = self.mission.items().get(usize::from(seq)).cloned() else {
            return;
        };
        use MavCmd::*;
        let p = item.params;
        let phase = match item.command {
            MAV_CMD_NAV_TAKEOFF => {
                let t = self.item_target(&item);
                Phase::Takeoff { z: t.z.min(-1.0) }
            }
            MAV_CMD_NAV_WAYPOINT => {
                let target = self.item_target(&item);
                let yaw = if p[3].is_finite() {
                    Some(wrap_pi(f64::from(p[3]).to_radians()))
                } else {
                    None
                };
                Phase::Goto {
                    target,
                    yaw,
                    acc: if p[1] > 0.0 {
                        f64::from(p[1])
                    } else {
                        self.params.acceptance_radius_m
                    },
                    hold: f64::from(p[0]).max(0.0),
                    climb_first: self.vehicle.landed(),
                }
            }
            MAV_CMD_NAV_LAND => {
                let xy = if item.x != 0.0 || item.y != 0.0 {
                    let t = self.item_target(&item);
                    Some((t.x, t.y))
                } else {
                    None
                };
                Phase::Land { xy }
            }
            MAV_CMD_NAV_RETURN_TO_LAUNCH => Phase::Rtl(RtlStage::Climb),
            MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW => {
                if self.mission_gimbal_allowed() {
                    self.gimbal_pitch_yaw(p[0], p[1], item.x as f32);
                } else {
                    self.gimbal_refusals += 1;
                    out.push(self.gimbal_refused_text(self.own_peer()));
                }
                Phase::Instant
            }
            MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE => {
                let pp = [p[0], p[1], p[2], p[3], item.x as f32, item.y as f32, item.z];
                let own = self.own_peer();
                if self.gimbal_configure(&pp, own).is_ok() {
                    out.extend(self.build(281));
                }
                Phase::Instant
            }
            MAV_CMD_DO_MOUNT_CONTROL => {
                self.vehicle
                    .set_gimbal_target(f64::from(p[0]), f64::from(p[2]));
                Phase::Instant
            }
            MAV_CMD_IMAGE_START_CAPTURE => {
                if p[2] as u32 == 1 {
                    Phase::WaitGimbal {
                        since: self.now,
                        then_capture: true,
                    }
                } else {
                    self.start_capture(f64::from(p[1]), p[2] as u32);
                    Phase::Instant
                }
            }
            MAV_CMD_IMAGE_STOP_CAPTURE => {
                self.interval_capture = None;
                Phase::Instant
            }
            MAV_CMD_DO_DIGICAM_CONTROL => {
                if (item.x - 1.0).abs() < 0.5 {
                    Phase::WaitGimbal {
                        since: self.now,
                        then_capture: true,
                    }
                } else {
                    Phase::Instant
                }
            }
            MAV_CMD_CONDITION_YAW => {
                let mut pp = [0.0f32; 7];
                pp[..4].copy_from_slice(&p);
                Phase::WaitYaw {
                    yaw: self.condition_yaw_target(&pp),
                }
            }
            MAV_CMD_DO_CHANGE_SPEED => {
                if p[1] > 0.0 {
                    self.cruise_speed = Some(f64::from(p[1]));
                }
                Phase::Instant
            }
            _ => Phase::Instant,
        };
        if matches!(phase, Phase::Rtl(_)) {
            self.rtl = RtlStage::Climb;
        }
        self.exec.seq = Some(seq);
        self.exec.phase = phase;
        self.exec.reached_at = None;
        // The position held by non-moving items.
        if !matches!(phase, Phase::Goto { .. } | Phase::Takeoff { .. }) && !self.vehicle.landed() {
            self.hold_point
                .get_or_insert((self.vehicle.p_ned(), self.vehicle.yaw()));
        }
    }

    fn mission_setpoint(&mut self, out: &mut Vec<MavMessage>) -> Setpoint {
        let n = self.mission.items().len();
        if n <= usize::from(self.mission.first_item()) || self.exec.done {
            return if self.vehicle.landed() {
                Setpoint::Idle
            } else {
                self.hold_here()
            };
        }
        let cur = self.mission.current();
        if self.exec.seq != Some(cur) {
            if usize::from(cur) >= n {
                self.exec.done = true;
                out.push(self.mission_current_msg());
                return self.hold_here();
            }
            self.start_item(cur, out);
            out.push(self.mission_current_msg());
        }
        let p = self.vehicle.p_ned();
        let yaw_ok = |target: Option<f64>, yaw: f64, tol: f64| {
            target.is_none_or(|t| wrap_pi(t - yaw).abs() <= tol.to_radians())
        };
        let (sp, complete) = match self.exec.phase {
            Phase::Instant => (self.hold_or_idle(), true),
            Phase::Takeoff { z } => {
                // As PX4: reached once at or above the takeoff altitude (a
                // vehicle already flying higher does not descend).
                let z = if self.vehicle.landed() { z } else { z.min(p.z) };
                let target = Vector3::new(p.x, p.y, z);
                let done = p.z <= z + self.params.altitude_acceptance_m;
                if done {
                    self.hold_point =
                        Some((Vector3::new(p.x, p.y, p.z.min(z)), self.vehicle.yaw()));
                }
                (
                    Setpoint::Position {
                        p_ned: target,
                        yaw: None,
                        max_speed: None,
                    },
                    done,
                )
            }
            Phase::Goto {
                target,
                yaw,
                acc,
                hold,
                climb_first,
            } => {
                if climb_first {
                    if (p.z - target.z).abs() <= self.params.altitude_acceptance_m {
                        self.exec.phase = Phase::Goto {
                            target,
                            yaw,
                            acc,
                            hold,
                            climb_first: false,
                        };
                    }
                    (
                        Setpoint::Position {
                            p_ned: Vector3::new(p.x, p.y, target.z),
                            yaw: None,
                            max_speed: None,
                        },
                        false,
                    )
                } else {
                    let d_xy = (target.x - p.x).hypot(target.y - p.y);
                    let d_z = (target.z - p.z).abs();
                    let sp_yaw = match yaw {
                        Some(y) => Some(y),
                        None if d_xy > 2.0 => Some((target.y - p.y).atan2(target.x - p.x)),
                        None => None,
                    };
                    let arrived = d_xy <= acc
                        && d_z <= self.params.altitude_acceptance_m
                        && yaw_ok(yaw, self.vehicle.yaw(), self.params.yaw_acceptance_deg);
                    if arrived && self.exec.reached_at.is_none() {
                        self.exec.reached_at = Some(self.now);
                        out.push(MavMessage::MISSION_ITEM_REACHED(
                            MISSION_ITEM_REACHED_DATA { seq: cur },
                        ));
                    }
                    let held = self.exec.reached_at.is_some_and(|t| self.now - t >= hold);
                    (
                        Setpoint::Position {
                            p_ned: target,
                            yaw: sp_yaw,
                            max_speed: self.cruise_speed,
                        },
                        held,
                    )
                }
            }
            Phase::Land { xy } => {
                if let Some((x, y)) = xy
                    && (x - p.x).hypot(y - p.y) > 0.5
                    && !self.vehicle.landed()
                {
                    (
                        Setpoint::Position {
                            p_ned: Vector3::new(x, y, p.z),
                            yaw: None,
                            max_speed: self.cruise_speed,
                        },
                        false,
                    )
                } else {
                    (Setpoint::Land, self.vehicle.landed())
                }
            }
            Phase::Rtl(_) => {
                let sp = self.rtl_setpoint();
                (sp, self.vehicle.landed() && self.rtl == RtlStage::Land)
            }
            Phase::WaitYaw { yaw } => {
                let sp = match self.hold_or_idle() {
                    Setpoint::Position {
                        p_ned, max_speed, ..
                    } => Setpoint::Position {
                        p_ned,
                        yaw: Some(yaw),
                        max_speed,
                    },
                    s => s,
                };
                let ok = yaw_ok(Some(yaw), self.vehicle.yaw(), 2.0) || self.vehicle.landed();
                if ok && let Some(h) = &mut self.hold_point {
                    h.1 = yaw;
                }
                (sp, ok)
            }
            Phase::WaitGimbal {
                since,
                then_capture,
            } => {
                let ok = self.vehicle.gimbal_settled(self.params.gimbal_settle_deg)
                    || self.now - since >= self.params.capture_max_wait_s;
                if ok && then_capture {
                    self.capture_now();
                }
                (self.hold_or_idle(), ok)
            }
        };
        if complete {
            let is_nav_goto = matches!(self.exec.phase, Phase::Goto { .. });
            if !is_nav_goto {
                out.push(MavMessage::MISSION_ITEM_REACHED(
                    MISSION_ITEM_REACHED_DATA { seq: cur },
                ));
            }
            if matches!(self.exec.phase, Phase::Goto { .. } | Phase::Takeoff { .. }) {
                let yaw = self.vehicle.yaw();
                if let Setpoint::Position { p_ned, yaw: y, .. } = sp {
                    self.hold_point = Some((p_ned, y.unwrap_or(yaw)));
                }
            }
            if usize::from(cur) + 1 < n {
                self.mission.set_current(cur + 1);
            } else {
                self.exec.done = true;
                out.push(self.mission_current_msg());
            }
        }
        sp
    }

    fn hold_or_idle(&mut self) -> Setpoint {
        if self.vehicle.landed() {
            Setpoint::Idle
        } else {
            self.hold_here()
        }
    }
}
