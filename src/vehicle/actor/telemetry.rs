//! What the vehicle sends, read by the link actor: telemetry into the watch
//! channels, heartbeats (the vehicle tracked, cameras asked to describe
//! themselves), the message rates asked for and asked again.

use std::time::{Duration, Instant};

use mavlink::MavHeader;
use mavlink::dialects::common::{
    HEARTBEAT_DATA, MavAutopilot, MavCmd, MavMessage, MavModeFlag, MavType,
};
use tracing::{debug, info};

use super::camera::{
    CAMERA_ASK_EVERY, CAMERA_INFORMATION_ID, camera_info, image_captured, video_stream_info,
};
use super::pending::command_long;
use super::state::Actor;
use crate::clock;
use crate::mission::Flavour;
use crate::vehicle::modes::{ardupilot_mode_name, px4_mode_name};
use crate::vehicle::telemetry::{
    Attitude, GimbalAttitude, GimbalManagerStatus, GlobalPosition, GpsRaw, HomePosition,
    LocalPosition, Stamped, quat_to_euler_deg,
};

/// How often missing telemetry streams are asked for again.
const RATE_RECHECK: Duration = Duration::from_secs(5);
/// How many times, after the vehicle appears.
const RATE_ROUNDS: u32 = 5;

/// Message ids for SET_MESSAGE_INTERVAL.
mod msg_id {
    pub const ATTITUDE: u32 = 30;
    pub const LOCAL_POSITION_NED: u32 = 32;
    pub const GLOBAL_POSITION_INT: u32 = 33;
    pub const MISSION_CURRENT: u32 = 42;
    pub const HOME_POSITION: u32 = 242;
    pub const GIMBAL_DEVICE_ATTITUDE_STATUS: u32 = 285;
}

impl Actor {
    pub(super) async fn on_frame(&mut self, h: MavHeader, m: MavMessage) {
        let now = clock::now();
        if let MavMessage::HEARTBEAT(hb) = &m {
            self.on_heartbeat(&h, hb, now).await;
            return;
        }
        let tracked = self.vehicle.borrow().system_id;
        if tracked.map(u32::from) != Some(h.system_id) {
            return;
        }
        match &m {
            MavMessage::GLOBAL_POSITION_INT(d) => {
                let value = GlobalPosition {
                    time_boot_ms: d.time_boot_ms,
                    lat_deg: f64::from(d.lat) / 1e7,
                    lon_deg: f64::from(d.lon) / 1e7,
                    alt_amsl_m: f64::from(d.alt) / 1e3,
                    rel_alt_m: f64::from(d.relative_alt) / 1e3,
                    vel_ned_m_s: [
                        f32::from(d.vx) / 100.0,
                        f32::from(d.vy) / 100.0,
                        f32::from(d.vz) / 100.0,
                    ],
                    heading_deg: (d.hdg != u16::MAX).then(|| f32::from(d.hdg) / 100.0),
                };
                self.gp.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::GPS_RAW_INT(d) => {
                let value = GpsRaw::from_message(d);
                self.gps_raw.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::LOCAL_POSITION_NED(d) => {
                let value = LocalPosition {
                    time_boot_ms: d.time_boot_ms,
                    pos_ned_m: [d.x, d.y, d.z],
                    vel_ned_m_s: [d.vx, d.vy, d.vz],
                };
                self.lp.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::ATTITUDE(d) => {
                let value = Attitude {
                    time_boot_ms: d.time_boot_ms,
                    roll_rad: d.roll,
                    pitch_rad: d.pitch,
                    yaw_rad: d.yaw,
                };
                self.att.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::HOME_POSITION(d) => {
                let value = HomePosition {
                    lat_deg: f64::from(d.latitude) / 1e7,
                    lon_deg: f64::from(d.longitude) / 1e7,
                    alt_amsl_m: f64::from(d.altitude) / 1e3,
                };
                self.home.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(d) => {
                use mavlink::dialects::common::GimbalDeviceFlags as F;
                let (roll_deg, pitch_deg, yaw_deg) = quat_to_euler_deg(d.q);
                let yaw_absolute = d.flags.contains(F::GIMBAL_DEVICE_FLAGS_YAW_IN_EARTH_FRAME)
                    || (!d
                        .flags
                        .contains(F::GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME)
                        && d.flags.contains(F::GIMBAL_DEVICE_FLAGS_YAW_LOCK));
                let value = GimbalAttitude {
                    roll_deg,
                    pitch_deg,
                    yaw_deg,
                    yaw_absolute,
                    time_boot_ms: Some(d.time_boot_ms),
                };
                self.gimbal.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            // ArduPilot's legacy mounts still send it.
            #[allow(deprecated)]
            MavMessage::MOUNT_ORIENTATION(d) => {
                let value = GimbalAttitude {
                    roll_deg: d.roll,
                    pitch_deg: d.pitch,
                    yaw_deg: d.yaw,
                    yaw_absolute: false,
                    time_boot_ms: Some(d.time_boot_ms),
                };
                self.gimbal.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
            }
            MavMessage::MISSION_CURRENT(d) => {
                let mut p = self.progress.borrow().map(|s| s.value).unwrap_or_default();
                p.current_seq = Some(d.seq);
                p.total = (d.total != u16::MAX && d.total != 0).then_some(d.total);
                p.state = Some(d.mission_state as u8);
                self.progress.send_replace(Some(Stamped {
                    value: p,
                    received: now,
                }));
                self.gimbal_after_mission(d.mission_state as u8);
            }
            MavMessage::GIMBAL_MANAGER_STATUS(d) => {
                let value = GimbalManagerStatus {
                    manager_component: h.component_id,
                    gimbal_device_id: d.gimbal_device_id,
                    primary: (d.primary_control_sysid, d.primary_control_compid),
                    secondary: (d.secondary_control_sysid, d.secondary_control_compid),
                    flags: d.flags.bits(),
                };
                let before = self.gimbal_manager.borrow().map(|s| s.value.primary);
                if before.is_some_and(|b| b != value.primary) {
                    info!(
                        from = ?before,
                        to = ?value.primary,
                        "gimbal primary control changed"
                    );
                }
                // The status first, then the control it changes: a reader
                // that sees control passed finds who has it.
                self.gimbal_manager.send_replace(Some(Stamped {
                    value,
                    received: now,
                }));
                let own = (self.params.system_id, self.params.component_id);
                if self.gimbal_control.borrow().held && value.primary != own {
                    // Someone (a PX4 mission's own configure item, another
                    // ground station) took control: we no longer hold it and
                    // have nothing to give back.
                    let (s, c) = value.primary;
                    info!("gimbal control passed from us to {s}/{c}");
                    self.gimbal_control.send_modify(|g| {
                        g.held = false;
                        g.for_mission = false;
                        g.last_event = Some(format!("gimbal control passed to {s}/{c}"));
                    });
                }
            }
            MavMessage::MISSION_ITEM_REACHED(d) => {
                let mut p = self.progress.borrow().map(|s| s.value).unwrap_or_default();
                p.last_reached = Some(d.seq);
                self.progress.send_replace(Some(Stamped {
                    value: p,
                    received: now,
                }));
            }
            MavMessage::COMMAND_ACK(a) => {
                self.on_command_ack(a.command, a.result, a.target_system, now)
            }
            MavMessage::CAMERA_INFORMATION(d) => {
                let info = camera_info(h.component_id, d);
                info!(
                    component = info.component_id,
                    vendor = %info.vendor,
                    model = %info.model,
                    captures_images = info.captures_images,
                    "camera described"
                );
                self.cameras.send_modify(|v| {
                    v.retain(|c| c.component_id != info.component_id);
                    v.push(info);
                    v.sort_by_key(|c| c.component_id);
                });
            }
            MavMessage::CAMERA_IMAGE_CAPTURED(d) => {
                let c = image_captured(h.component_id, d);
                debug!(
                    component = c.component_id,
                    index = c.index,
                    "CAMERA_IMAGE_CAPTURED"
                );
                self.captures.send_modify(|v| {
                    if !v
                        .iter()
                        .any(|x| (x.component_id, x.index) == (c.component_id, c.index))
                    {
                        v.push(c);
                        if v.len() > crate::vehicle::telemetry::CAPTURES_KEPT {
                            v.remove(0);
                        }
                    }
                });
            }
            MavMessage::VIDEO_STREAM_INFORMATION(d) => {
                let info = video_stream_info(h.component_id, d);
                self.video_streams.send_modify(|v| {
                    v.retain(|x| {
                        (x.component_id, x.stream_id) != (info.component_id, info.stream_id)
                    });
                    v.push(info);
                });
            }
            _ => {}
        }
        if let Some(t) = &mut self.transfer {
            t.on_message(&h, &m, now, &mut self.out);
            self.flush().await;
            self.deliver_if_done();
        }
        self.flush().await;
    }

    /// A camera component of the vehicle's system is heard: ask it for its
    /// CAMERA_INFORMATION until it answers (every 5 s).
    async fn on_camera_heartbeat(&mut self, h: &MavHeader, now: Instant) {
        let Some(sys) = self.vehicle.borrow().system_id else {
            return;
        };
        if h.system_id != u32::from(sys) {
            return;
        }
        let comp = h.component_id;
        if self.cameras.borrow().iter().any(|c| c.component_id == comp) {
            return;
        }
        if self
            .camera_asked
            .iter()
            .any(|(c, t)| *c == comp && now.saturating_duration_since(*t) < CAMERA_ASK_EVERY)
        {
            return;
        }
        self.camera_asked.retain(|(c, _)| *c != comp);
        self.camera_asked.push((comp, now));
        info!(
            component = comp,
            "camera heard: asking for CAMERA_INFORMATION"
        );
        self.out.push(MavMessage::COMMAND_LONG(command_long(
            MavCmd::MAV_CMD_REQUEST_MESSAGE,
            [CAMERA_INFORMATION_ID as f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            sys,
            comp,
        )));
        self.flush().await;
    }

    async fn on_heartbeat(&mut self, h: &MavHeader, hb: &HEARTBEAT_DATA, now: Instant) {
        if hb.mavtype == MavType::MAV_TYPE_CAMERA {
            self.on_camera_heartbeat(h, now).await;
            return;
        }
        let is_vehicle = hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID
            && !matches!(
                hb.mavtype,
                MavType::MAV_TYPE_GCS
                    | MavType::MAV_TYPE_GIMBAL
                    | MavType::MAV_TYPE_CAMERA
                    | MavType::MAV_TYPE_ONBOARD_CONTROLLER
            );
        let Ok(sys) = u8::try_from(h.system_id) else {
            return;
        };
        if !is_vehicle || sys == self.params.system_id {
            return;
        }
        let wanted = self.params.vehicle_system_id;
        let tracked = self.vehicle.borrow().system_id;
        if (wanted != 0 && sys != wanted) || tracked.is_some_and(|t| t != sys) {
            return;
        }
        let flavour = match hb.autopilot {
            MavAutopilot::MAV_AUTOPILOT_PX4 => Some(Flavour::Px4),
            MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Some(Flavour::ArduPilot),
            _ => None,
        };
        let mode = match flavour {
            Some(Flavour::Px4) => px4_mode_name(hb.custom_mode),
            Some(Flavour::ArduPilot) => ardupilot_mode_name(hb.custom_mode),
            None => format!("{}", hb.custom_mode),
        };
        let mut appeared = false;
        self.vehicle.send_modify(|v| {
            appeared = v.system_id.is_none() || v.link_lost;
            v.system_id = Some(sys);
            v.component_id = h.component_id;
            v.flavour = flavour;
            v.autopilot = hb.autopilot as u8;
            v.mav_type = hb.mavtype as u8;
            v.base_mode = hb.base_mode.bits();
            v.custom_mode = hb.custom_mode;
            v.mode = mode;
            v.armed = hb
                .base_mode
                .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
            v.link_lost = false;
            v.last_heartbeat = Some(now);
        });
        if appeared {
            info!(
                system = sys,
                component = h.component_id,
                ?flavour,
                "vehicle heard"
            );
            self.rate_rounds = 0;
            self.request_rates(sys, h.component_id, now, false);
            self.flush().await;
        } else if self.rate_rounds < RATE_ROUNDS
            && self
                .rates_requested
                .is_some_and(|t| now.saturating_duration_since(t) >= RATE_RECHECK)
        {
            // A request lost on a bad radio leaves a stream at the vehicle's
            // default rate: ask again for the streams that are not arriving.
            self.rate_rounds += 1;
            self.request_rates(sys, h.component_id, now, true);
            self.flush().await;
        }
    }

    /// When each requested stream last arrived.
    fn last_received(&self, id: u32) -> Option<Instant> {
        match id {
            msg_id::GLOBAL_POSITION_INT => self.gp.borrow().map(|s| s.received),
            msg_id::LOCAL_POSITION_NED => self.lp.borrow().map(|s| s.received),
            msg_id::ATTITUDE => self.att.borrow().map(|s| s.received),
            msg_id::HOME_POSITION => self.home.borrow().map(|s| s.received),
            msg_id::GIMBAL_DEVICE_ATTITUDE_STATUS => self.gimbal.borrow().map(|s| s.received),
            msg_id::MISSION_CURRENT => self.progress.borrow().map(|s| s.received),
            _ => None,
        }
    }

    /// Sends SET_MESSAGE_INTERVAL for every configured stream, or with
    /// `only_stale` for those not received within three periods (at least 3 s).
    fn request_rates(&mut self, sys: u8, comp: u8, now: Instant, only_stale: bool) {
        self.rates_requested = Some(now);
        let r = self.params.rates;
        for (id, hz) in [
            (msg_id::GLOBAL_POSITION_INT, r.global_position_hz),
            (msg_id::LOCAL_POSITION_NED, r.local_position_hz),
            (msg_id::ATTITUDE, r.attitude_hz),
            (msg_id::HOME_POSITION, r.home_position_hz),
            (msg_id::GIMBAL_DEVICE_ATTITUDE_STATUS, r.gimbal_hz),
            (msg_id::MISSION_CURRENT, r.mission_current_hz),
        ] {
            if !(hz > 0.0 && hz.is_finite()) {
                continue;
            }
            if only_stale {
                let window = Duration::from_secs_f32((3.0 / hz).max(3.0));
                if self
                    .last_received(id)
                    .is_some_and(|t| now.saturating_duration_since(t) < window)
                {
                    continue;
                }
            }
            // param7 0: the response target is the requester
            self.out.push(MavMessage::COMMAND_LONG(command_long(
                MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                [id as f32, (1e6 / hz).round(), 0.0, 0.0, 0.0, 0.0, 0.0],
                sys,
                comp,
            )));
        }
    }
}
