//! The telemetry streams (their default rates, SET_MESSAGE_INTERVAL's changes)
//! and each message built from the vehicle's state.

use mavlink::dialects::common::{
    ATTITUDE_DATA, AUTOPILOT_VERSION_DATA, EXTENDED_SYS_STATE_DATA,
    GIMBAL_DEVICE_ATTITUDE_STATUS_DATA, GIMBAL_MANAGER_INFORMATION_DATA,
    GIMBAL_MANAGER_STATUS_DATA, GLOBAL_POSITION_INT_DATA, GPS_RAW_INT_DATA, GimbalDeviceErrorFlags,
    GimbalDeviceFlags, GimbalManagerCapFlags, GimbalManagerFlags, GpsFixType, HEARTBEAT_DATA,
    HOME_POSITION_DATA, LOCAL_POSITION_NED_DATA, MavAutopilot, MavLandedState, MavMessage,
    MavModeFlag, MavProtocolCapability, MavState, MavSysStatusSensor, MavSysStatusSensorExtended,
    MavType, MavVtolState, SYS_STATUS_DATA, SYSTEM_TIME_DATA,
};
use nalgebra::UnitQuaternion;

use super::Autopilot;
use super::flight::Phase;
use super::gimbal::GIMBAL_DEVICE_ID;
use super::mission::Flavour;
use super::mode::Mode;

/// Telemetry messages we can stream, with their default intervals (s).
pub(super) const STREAMS: [(u32, f64); 12] = [
    (0, 1.0),   // HEARTBEAT
    (1, 1.0),   // SYS_STATUS
    (2, 1.0),   // SYSTEM_TIME
    (24, 1.0),  // GPS_RAW_INT
    (245, 1.0), // EXTENDED_SYS_STATE
    (42, 1.0),  // MISSION_CURRENT
    (30, 0.1),  // ATTITUDE
    (33, 0.2),  // GLOBAL_POSITION_INT
    (32, 0.2),  // LOCAL_POSITION_NED
    (285, 0.2), // GIMBAL_DEVICE_ATTITUDE_STATUS
    (242, 2.0), // HOME_POSITION
    (281, 2.0), // GIMBAL_MANAGER_STATUS
];

#[derive(Debug, Clone, Copy)]
pub(super) struct Stream {
    pub(super) id: u32,
    /// None = off.
    pub(super) interval: Option<f64>,
    pub(super) next: f64,
}

pub(super) fn quat_wxyz(q: &UnitQuaternion<f64>) -> [f32; 4] {
    [q.w as f32, q.i as f32, q.j as f32, q.k as f32]
}

impl Autopilot {
    pub(super) fn base_mode(&self) -> MavModeFlag {
        let mut f = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        if self.armed {
            f |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        f |= MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED;
        match self.mode {
            Mode::Manual => f |= MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,
            Mode::Position => {
                f |= MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
            }
            Mode::Offboard => f |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED,
            _ => {
                f |= MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED
            }
        }
        f
    }

    pub(super) fn time_boot_ms(&self) -> u32 {
        (self.now * 1e3) as u32
    }

    /// Build one telemetry message by id (None if we do not produce it).
    pub fn build(&self, id: u32) -> Option<MavMessage> {
        let v = &self.vehicle;
        let p = v.p_ned();
        let vel = v.v_ned();
        let g = v.geodetic();
        let home = self.params.vehicle.home;
        let t_ms = self.time_boot_ms();
        Some(match id {
            0 => MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: match self.params.flavour {
                    Flavour::Px4 => self.mode.px4_custom_mode(),
                    Flavour::ArduPilot => self.mode.ardupilot_custom_mode(),
                },
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                autopilot: match self.params.flavour {
                    Flavour::Px4 => MavAutopilot::MAV_AUTOPILOT_PX4,
                    Flavour::ArduPilot => MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
                },
                base_mode: self.base_mode(),
                system_status: if self.armed {
                    MavState::MAV_STATE_ACTIVE
                } else {
                    MavState::MAV_STATE_STANDBY
                },
                mavlink_version: 3,
            }),
            1 => {
                let (v_full, v_empty, cap, _) = self.params.battery;
                let frac = (1.0 - self.used_mah / cap).clamp(0.0, 1.0);
                let sensors = MavSysStatusSensor::from_bits_truncate(
                    0x1 | 0x2
                        | 0x4
                        | 0x8
                        | 0x20
                        | 0x400
                        | 0x800
                        | 0x1000
                        | 0x2000
                        | 0x4000
                        | 0x8000
                        | 0x200000
                        | 0x2000000,
                );
                MavMessage::SYS_STATUS(SYS_STATUS_DATA {
                    onboard_control_sensors_present: sensors,
                    onboard_control_sensors_enabled: sensors,
                    onboard_control_sensors_health: sensors,
                    load: 250,
                    voltage_battery: ((v_empty + (v_full - v_empty) * frac) * 1e3) as u16,
                    current_battery: if self.armed {
                        (self.params.battery.3 * 100.0) as i16
                    } else {
                        50
                    },
                    drop_rate_comm: 0,
                    errors_comm: 0,
                    errors_count1: 0,
                    errors_count2: 0,
                    errors_count3: 0,
                    errors_count4: 0,
                    battery_remaining: (frac * 100.0).round() as i8,
                    onboard_control_sensors_present_extended: MavSysStatusSensorExtended::empty(),
                    onboard_control_sensors_enabled_extended: MavSysStatusSensorExtended::empty(),
                    onboard_control_sensors_health_extended: MavSysStatusSensorExtended::empty(),
                })
            }
            2 => MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
                time_unix_usec: ((self.unix_at_boot + self.now) * 1e6) as u64,
                time_boot_ms: t_ms,
            }),
            24 => MavMessage::GPS_RAW_INT(GPS_RAW_INT_DATA {
                time_usec: (self.now * 1e6) as u64,
                lat: (g.lat_deg * 1e7).round() as i32,
                lon: (g.lon_deg * 1e7).round() as i32,
                alt: (g.alt_m * 1e3).round() as i32,
                eph: 70,
                epv: 100,
                vel: (vel.x.hypot(vel.y) * 100.0) as u16,
                cog: ((vel.y.atan2(vel.x).to_degrees().rem_euclid(360.0)) * 100.0) as u16,
                fix_type: if v.gps_fix() {
                    GpsFixType::GPS_FIX_TYPE_3D_FIX
                } else {
                    GpsFixType::GPS_FIX_TYPE_NO_FIX
                },
                satellites_visible: if v.gps_fix() { 14 } else { 0 },
                alt_ellipsoid: (g.alt_m * 1e3).round() as i32,
                // The receiver's reported accuracy: the error model's
                // sigmas, never better than a plain receiver's 0.5 / 0.8 m.
                h_acc: (v.gps_reported_accuracy().0.max(0.5) * 1e3).round() as u32,
                v_acc: (v.gps_reported_accuracy().1.max(0.8) * 1e3).round() as u32,
                vel_acc: 200,
                hdg_acc: 0,
                yaw: 0,
            }),
            245 => MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
                vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
                landed_state: if v.landed() {
                    MavLandedState::MAV_LANDED_STATE_ON_GROUND
                } else if self.mode == Mode::Land
                    || matches!(self.exec.phase, Phase::Land { .. }) && self.mode == Mode::Mission
                {
                    MavLandedState::MAV_LANDED_STATE_LANDING
                } else {
                    MavLandedState::MAV_LANDED_STATE_IN_AIR
                },
            }),
            42 => self.mission_current_msg(),
            30 => {
                let (roll, pitch) = v.roll_pitch();
                MavMessage::ATTITUDE(ATTITUDE_DATA {
                    time_boot_ms: t_ms,
                    roll: roll as f32,
                    pitch: pitch as f32,
                    yaw: v.yaw() as f32,
                    rollspeed: 0.0,
                    pitchspeed: 0.0,
                    yawspeed: v.yaw_rate() as f32,
                })
            }
            // No global position while the GNSS fix is lost.
            33 if !v.gps_fix() => return None,
            33 => MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                time_boot_ms: t_ms,
                lat: (g.lat_deg * 1e7).round() as i32,
                lon: (g.lon_deg * 1e7).round() as i32,
                alt: (g.alt_m * 1e3).round() as i32,
                relative_alt: (-p.z * 1e3).round() as i32,
                vx: (vel.x * 100.0).round() as i16,
                vy: (vel.y * 100.0).round() as i16,
                vz: (vel.z * 100.0).round() as i16,
                hdg: (v.yaw().to_degrees().rem_euclid(360.0) * 100.0).round() as u16 % 36000,
            }),
            32 => MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: t_ms,
                x: p.x as f32,
                y: p.y as f32,
                z: p.z as f32,
                vx: vel.x as f32,
                vy: vel.y as f32,
                vz: vel.z as f32,
            }),
            285 => {
                let (rp, ry) = v.gimbal_rates();
                MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(GIMBAL_DEVICE_ATTITUDE_STATUS_DATA {
                    time_boot_ms: t_ms,
                    q: quat_wxyz(&v.gimbal_rotation_in_vehicle_frame()),
                    angular_velocity_x: 0.0,
                    angular_velocity_y: rp as f32,
                    angular_velocity_z: ry as f32,
                    failure_flags: GimbalDeviceErrorFlags::empty(),
                    flags: GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_ROLL_LOCK
                        | GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_PITCH_LOCK
                        | GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME,
                    target_system: 0,
                    target_component: 0,
                    delta_yaw: v.gimbal_angles().1 as f32,
                    delta_yaw_velocity: ry as f32,
                    gimbal_device_id: 1,
                })
            }
            280 => {
                let g = &self.params.vehicle.gimbal;
                MavMessage::GIMBAL_MANAGER_INFORMATION(GIMBAL_MANAGER_INFORMATION_DATA {
                    time_boot_ms: t_ms,
                    cap_flags: GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_PITCH_AXIS
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_PITCH_LOCK
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_ROLL_LOCK
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_YAW_AXIS
                        | GimbalManagerCapFlags::GIMBAL_MANAGER_CAP_FLAGS_HAS_YAW_FOLLOW,
                    roll_min: 0.0,
                    roll_max: 0.0,
                    pitch_min: g.pitch_min_deg.to_radians() as f32,
                    pitch_max: g.pitch_max_deg.to_radians() as f32,
                    yaw_min: g.yaw_min_deg.to_radians() as f32,
                    yaw_max: g.yaw_max_deg.to_radians() as f32,
                    gimbal_device_id: GIMBAL_DEVICE_ID,
                })
            }
            281 => MavMessage::GIMBAL_MANAGER_STATUS(GIMBAL_MANAGER_STATUS_DATA {
                time_boot_ms: t_ms,
                flags: GimbalManagerFlags::GIMBAL_MANAGER_FLAGS_ROLL_LOCK
                    | GimbalManagerFlags::GIMBAL_MANAGER_FLAGS_PITCH_LOCK
                    | GimbalManagerFlags::GIMBAL_MANAGER_FLAGS_YAW_IN_VEHICLE_FRAME,
                gimbal_device_id: GIMBAL_DEVICE_ID,
                primary_control_sysid: self.gimbal_primary.0,
                primary_control_compid: self.gimbal_primary.1,
                secondary_control_sysid: self.gimbal_secondary.0,
                secondary_control_compid: self.gimbal_secondary.1,
            }),
            242 => MavMessage::HOME_POSITION(HOME_POSITION_DATA {
                latitude: (home.lat_deg * 1e7).round() as i32,
                longitude: (home.lon_deg * 1e7).round() as i32,
                altitude: (home.alt_m * 1e3).round() as i32,
                x: 0.0,
                y: 0.0,
                z: 0.0,
                q: [1.0, 0.0, 0.0, 0.0],
                approach_x: 0.0,
                approach_y: 0.0,
                approach_z: 0.0,
                time_usec: (self.now * 1e6) as u64,
            }),
            148 => MavMessage::AUTOPILOT_VERSION(AUTOPILOT_VERSION_DATA {
                capabilities: MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_FLOAT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MISSION_INT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | MavProtocolCapability::MAV_PROTOCOL_CAPABILITY_MAVLINK2,
                uid: 0x5107_5107,
                flight_sw_version: 0x010f_0000,
                middleware_sw_version: 0,
                os_sw_version: 0,
                board_version: 0,
                vendor_id: 0,
                product_id: 0,
                flight_custom_version: [0; 8],
                middleware_custom_version: [0; 8],
                os_custom_version: [0; 8],
                uid2: [0; 18],
            }),
            269 => {
                use mavlink::dialects::common::{
                    VIDEO_STREAM_INFORMATION_DATA, VideoStreamEncoding, VideoStreamStatusFlags,
                    VideoStreamType,
                };
                let uri = self.params.video_stream_uri.as_deref()?;
                let (mavtype, encoding) = if uri.starts_with("rtsp://") {
                    (
                        VideoStreamType::VIDEO_STREAM_TYPE_RTSP,
                        VideoStreamEncoding::VIDEO_STREAM_ENCODING_H264,
                    )
                } else if uri.starts_with("udp://") {
                    (
                        VideoStreamType::VIDEO_STREAM_TYPE_RTPUDP,
                        VideoStreamEncoding::VIDEO_STREAM_ENCODING_H264,
                    )
                } else {
                    (
                        VideoStreamType::VIDEO_STREAM_TYPE_TCP_MPEG,
                        VideoStreamEncoding::VIDEO_STREAM_ENCODING_UNKNOWN,
                    )
                };
                MavMessage::VIDEO_STREAM_INFORMATION(VIDEO_STREAM_INFORMATION_DATA {
                    framerate: 0.0,
                    bitrate: 0,
                    flags: VideoStreamStatusFlags::VIDEO_STREAM_STATUS_FLAGS_RUNNING,
                    resolution_h: 0,
                    resolution_v: 0,
                    rotation: 0,
                    hfov: 0,
                    stream_id: 1,
                    count: 1,
                    mavtype,
                    name: "shotpilot-sim camera".into(),
                    uri: uri.into(),
                    encoding,
                    camera_device_id: 0,
                })
            }
            _ => return None,
        })
    }
}
