//! Image captures: the requests the app renders and stores (CaptureRequest),
//! interval captures, CAMERA_IMAGE_CAPTURED once stored, the video stream's
//! information.

use mavlink::dialects::common::{CAMERA_IMAGE_CAPTURED_DATA, MavBool, MavMessage};
use nalgebra::Isometry3;

use super::Autopilot;
use super::telemetry::quat_wxyz;
use crate::geodesy::Geodetic;

/// A still image the app must render and store.
#[derive(Debug, Clone)]
pub struct CaptureRequest {
    /// Image index (0, 1, 2, ... since boot).
    pub index: i32,
    /// Capture time since boot, s.
    pub time_boot_s: f64,
    /// Capture time, Unix seconds.
    pub time_unix_s: f64,
    /// Camera pose for the renderer (local NED): the true one, GPS bias
    /// included.
    pub world_from_cam: Isometry3<f64>,
    /// Camera position.
    pub geodetic: Geodetic,
    /// Height above home, m.
    pub relative_alt_m: f64,
    /// Camera orientation in NED (x along the optical axis), w x y z.
    pub q: [f32; 4],
}

#[derive(Debug, Clone, Copy)]
pub(super) struct IntervalCapture {
    pub(super) interval: f64,
    pub(super) remaining: Option<u32>,
    pub(super) next: f64,
}

impl Autopilot {
    /// IMAGE_START_CAPTURE as a camera component takes it: `total`
    /// pictures (0: until stopped) `interval` s apart, the first now.
    pub fn start_image_capture(&mut self, interval: f64, total: u32) {
        self.start_capture(interval, total);
    }

    /// IMAGE_STOP_CAPTURE.
    pub fn stop_image_capture(&mut self) {
        self.interval_capture = None;
    }

    /// The camera's VIDEO_STREAM_INFORMATION, when it announces a stream.
    pub fn video_stream_information(&self) -> Option<MavMessage> {
        self.build(269)
    }

    pub(super) fn start_capture(&mut self, interval: f64, total: u32) {
        self.capture_now();
        if total == 1 {
            self.interval_capture = None;
            return;
        }
        let interval = interval.max(0.1);
        self.interval_capture = Some(IntervalCapture {
            interval,
            remaining: if total == 0 { None } else { Some(total - 1) },
            next: self.now + interval,
        });
    }

    pub(super) fn capture_now(&mut self) {
        let g = self.vehicle.geodetic();
        // The picture is taken from where the camera truly is; the position
        // reported with it is the GPS's.
        let wfc = self.vehicle.true_world_from_cam();
        let q = self.vehicle.world_from_gimbal_rotation();
        self.captures.push(CaptureRequest {
            index: self.next_image_index,
            time_boot_s: self.now,
            time_unix_s: self.unix_at_boot + self.now,
            world_from_cam: wfc,
            geodetic: g,
            relative_alt_m: -self.vehicle.p_ned().z,
            q: quat_wxyz(&q),
        });
        self.next_image_index += 1;
    }

    /// The CAMERA_IMAGE_CAPTURED for a finished capture (`file_url` None if
    /// storing failed).
    pub fn capture_done(&self, req: &CaptureRequest, file_url: Option<&str>) -> MavMessage {
        let url = file_url.unwrap_or("");
        let url: String = url.chars().take(204).collect();
        MavMessage::CAMERA_IMAGE_CAPTURED(CAMERA_IMAGE_CAPTURED_DATA {
            time_utc: (req.time_unix_s * 1e6) as u64,
            time_boot_ms: (req.time_boot_s * 1e3) as u32,
            lat: (req.geodetic.lat_deg * 1e7).round() as i32,
            lon: (req.geodetic.lon_deg * 1e7).round() as i32,
            alt: (req.geodetic.alt_m * 1e3).round() as i32,
            relative_alt: (req.relative_alt_m * 1e3).round() as i32,
            q: req.q,
            image_index: req.index,
            camera_id: 0,
            capture_result: if file_url.is_some() {
                MavBool::MAV_BOOL_TRUE
            } else {
                MavBool::MAV_BOOL_FALSE
            },
            file_url: url.as_str().into(),
        })
    }
}
