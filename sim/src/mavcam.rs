//! The simulated vehicle's MAVLink camera: component 100
//! (MAV_COMP_ID_CAMERA) of the vehicle's system, as a SIYI, Gremsy/Sony
//! payload or PX4's camera manager presents itself.
//!
//! - HEARTBEAT at 1 Hz, MAV_TYPE_CAMERA, autopilot INVALID;
//! - MAV_CMD_REQUEST_MESSAGE for CAMERA_INFORMATION (259) answers with the
//!   gimbal camera's resolution, focal length and sensor size and
//!   CAMERA_CAP_FLAGS_CAPTURE_IMAGE; for VIDEO_STREAM_INFORMATION (269)
//!   with the autopilot's stream announcement;
//! - MAV_CMD_IMAGE_START_CAPTURE (param2 interval, param3 total) and
//!   MAV_CMD_IMAGE_STOP_CAPTURE drive the autopilot's capture machinery
//!   (the picture is rendered from where the camera truly is); the
//!   CAMERA_IMAGE_CAPTURED of every picture, whoever asked for it (a
//!   mission's IMAGE_START_CAPTURE item too, which PX4 forwards to its
//!   camera), goes out from this component;
//! - every command gets its COMMAND_ACK from this component; an unknown
//!   one is UNSUPPORTED.
//!
//! Off (`SimConfig::mavlink_camera` false), the autopilot triggers the
//! camera itself and sends CAMERA_IMAGE_CAPTURED as component 1, as a
//! PX4 with a trigger-wired camera does; a ground station must then use
//! the mission's or the autopilot's DO_DIGICAM_CONTROL.

use mavlink::MavHeader;
use mavlink::dialects::common::{
    CAMERA_INFORMATION_DATA, COMMAND_ACK_DATA, CameraCapFlags, HEARTBEAT_DATA, MavAutopilot,
    MavCmd, MavMessage, MavModeFlag, MavResult, MavState, MavType,
};

use crate::autopilot::Autopilot;
use crate::camera::SimCamera;

/// MAV_COMP_ID_CAMERA.
pub const CAMERA_COMPONENT: u8 = 100;
/// The simulated sensor's width, mm (a 1/2.3" sensor, as on SIYI's cameras).
const SENSOR_W_MM: f64 = 6.17;

/// The camera component.
#[derive(Debug, Clone)]
pub struct MavCamera {
    system_id: u8,
    camera: SimCamera,
    next_heartbeat: f64,
}

fn ack(to: (u8, u8), command: MavCmd, result: MavResult) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        progress: 0,
        result_param2: 0,
        target_system: to.0,
        target_component: to.1,
    })
}

fn text<const N: usize>(s: &str) -> [u8; N] {
    let mut out = [0u8; N];
    for (o, b) in out.iter_mut().zip(s.bytes()) {
        *o = b;
    }
    out
}

impl MavCamera {
    /// The camera of system `system_id` with the gimbal camera's model.
    pub fn new(system_id: u8, camera: SimCamera) -> Self {
        Self {
            system_id,
            camera,
            next_heartbeat: 0.0,
        }
    }

    /// Whether a message is addressed to this camera.
    pub fn is_for_me(&self, msg: &MavMessage) -> bool {
        let (s, c) = match msg {
            MavMessage::COMMAND_LONG(c) => (c.target_system, c.target_component),
            MavMessage::COMMAND_INT(c) => (c.target_system, c.target_component),
            _ => return false,
        };
        s == self.system_id && c == CAMERA_COMPONENT
    }

    /// CAMERA_INFORMATION.
    pub fn information(&self, time_boot_ms: u32) -> MavMessage {
        let focal_mm = self.camera.fx / f64::from(self.camera.width) * SENSOR_W_MM;
        let sensor_h_mm =
            SENSOR_W_MM * f64::from(self.camera.height) / f64::from(self.camera.width);
        MavMessage::CAMERA_INFORMATION(CAMERA_INFORMATION_DATA {
            time_boot_ms,
            firmware_version: 1,
            focal_length: focal_mm as f32,
            sensor_size_h: SENSOR_W_MM as f32,
            sensor_size_v: sensor_h_mm as f32,
            flags: CameraCapFlags::CAMERA_CAP_FLAGS_CAPTURE_IMAGE
                | CameraCapFlags::CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM,
            resolution_h: self.camera.width.min(65535) as u16,
            resolution_v: self.camera.height.min(65535) as u16,
            cam_definition_version: 0,
            vendor_name: text("shotpilot-sim"),
            model_name: text("gimbal camera"),
            lens_id: 0,
            cam_definition_uri: "".into(),
            gimbal_device_id: 1,
            camera_device_id: 0,
        })
    }

    /// A command addressed to this camera (see [`MavCamera::is_for_me`]):
    /// the replies, its COMMAND_ACK last.
    pub fn handle(
        &mut self,
        ap: &mut Autopilot,
        h: &MavHeader,
        msg: &MavMessage,
    ) -> Vec<MavMessage> {
        let (command, p) = match msg {
            MavMessage::COMMAND_LONG(c) => (
                c.command,
                [
                    c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7,
                ],
            ),
            MavMessage::COMMAND_INT(c) => (
                c.command,
                [
                    c.param1, c.param2, c.param3, c.param4, c.x as f32, c.y as f32, c.z,
                ],
            ),
            _ => return Vec::new(),
        };
        let from = (h.system_id.min(255) as u8, h.component_id);
        let mut out = Vec::new();
        let result = match command {
            MavCmd::MAV_CMD_IMAGE_START_CAPTURE => {
                if p[1] >= 0.0 && p[2] >= 0.0 && p[1].is_finite() && p[2].is_finite() {
                    ap.start_image_capture(f64::from(p[1]), p[2] as u32);
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_IMAGE_STOP_CAPTURE => {
                ap.stop_image_capture();
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_REQUEST_MESSAGE => match p[0] as u32 {
                259 => {
                    out.push(self.information((ap.now() * 1e3) as u32));
                    MavResult::MAV_RESULT_ACCEPTED
                }
                269 => match ap.video_stream_information() {
                    Some(m) => {
                        out.push(m);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    None => MavResult::MAV_RESULT_DENIED,
                },
                _ => MavResult::MAV_RESULT_UNSUPPORTED,
            },
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        };
        out.push(ack(from, command, result));
        out
    }

    /// Its heartbeat when one is due at `now` (seconds since boot).
    pub fn step(&mut self, now: f64) -> Option<MavMessage> {
        if now < self.next_heartbeat {
            return None;
        }
        self.next_heartbeat = now + 1.0;
        Some(MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0,
            mavtype: MavType::MAV_TYPE_CAMERA,
            autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
            base_mode: MavModeFlag::empty(),
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn information_describes_the_gimbal_camera() {
        let cam = SimCamera::default();
        let c = MavCamera::new(1, cam);
        let MavMessage::CAMERA_INFORMATION(i) = c.information(5) else {
            panic!("not CAMERA_INFORMATION");
        };
        assert_eq!(u32::from(i.resolution_h), cam.width);
        assert_eq!(u32::from(i.resolution_v), cam.height);
        assert!(
            i.flags
                .contains(CameraCapFlags::CAMERA_CAP_FLAGS_CAPTURE_IMAGE)
        );
        // f = fx / width * sensor width
        let f = cam.fx / f64::from(cam.width) * SENSOR_W_MM;
        assert!((f64::from(i.focal_length) - f).abs() < 1e-3);
        assert_eq!(&i.vendor_name[..13], b"shotpilot-sim");
    }

    #[test]
    fn heartbeats_once_a_second() {
        let mut c = MavCamera::new(1, SimCamera::default());
        assert!(c.step(0.0).is_some());
        assert!(c.step(0.5).is_none());
        assert!(c.step(1.0).is_some());
    }
}
