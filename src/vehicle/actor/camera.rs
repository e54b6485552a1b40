//! The camera protocol's messages (CAMERA_INFORMATION, CAMERA_IMAGE_CAPTURED,
//! VIDEO_STREAM_INFORMATION) read into the handle's types.

use std::time::Duration;

/// MAVLink message id of CAMERA_INFORMATION.
pub(super) const CAMERA_INFORMATION_ID: u32 = 259;
/// How often a silent camera is asked again for CAMERA_INFORMATION.
pub(super) const CAMERA_ASK_EVERY: Duration = Duration::from_secs(5);

fn c_string(bytes: &[u8]) -> String {
    let end = bytes.iter().position(|b| *b == 0).unwrap_or(bytes.len());
    String::from_utf8_lossy(&bytes[..end]).into_owned()
}

pub(super) fn camera_info(
    component_id: u8,
    d: &mavlink::dialects::common::CAMERA_INFORMATION_DATA,
) -> crate::vehicle::telemetry::CameraInfo {
    use mavlink::dialects::common::CameraCapFlags;
    crate::vehicle::telemetry::CameraInfo {
        component_id,
        vendor: c_string(&d.vendor_name),
        model: c_string(&d.model_name),
        focal_length_mm: d.focal_length,
        sensor_size_mm: [d.sensor_size_h, d.sensor_size_v],
        resolution: [d.resolution_h, d.resolution_v],
        captures_images: d
            .flags
            .contains(CameraCapFlags::CAMERA_CAP_FLAGS_CAPTURE_IMAGE),
    }
}

pub(super) fn image_captured(
    component_id: u8,
    d: &mavlink::dialects::common::CAMERA_IMAGE_CAPTURED_DATA,
) -> crate::vehicle::telemetry::ImageCaptured {
    crate::vehicle::telemetry::ImageCaptured {
        component_id,
        index: d.image_index,
        time_utc_us: d.time_utc,
        lat_deg: f64::from(d.lat) / 1e7,
        lon_deg: f64::from(d.lon) / 1e7,
        alt_amsl_m: f64::from(d.alt) / 1e3,
        relative_alt_m: f64::from(d.relative_alt) / 1e3,
        q: d.q,
        ok: d.capture_result == mavlink::dialects::common::MavBool::MAV_BOOL_TRUE,
        file_url: d.file_url.to_str().unwrap_or("").to_string(),
    }
}

pub(super) fn video_stream_info(
    component_id: u8,
    d: &mavlink::dialects::common::VIDEO_STREAM_INFORMATION_DATA,
) -> crate::vehicle::telemetry::VideoStreamInfo {
    use mavlink::dialects::common::{VideoStreamEncoding as E, VideoStreamType as T};
    let text = |b: &[u8]| {
        let end = b.iter().position(|&c| c == 0).unwrap_or(b.len());
        String::from_utf8_lossy(&b[..end]).trim().to_owned()
    };
    crate::vehicle::telemetry::VideoStreamInfo {
        component_id,
        stream_id: d.stream_id,
        count: d.count,
        kind: match d.mavtype {
            T::VIDEO_STREAM_TYPE_RTSP => "rtsp",
            T::VIDEO_STREAM_TYPE_RTPUDP => "rtpudp",
            T::VIDEO_STREAM_TYPE_TCP_MPEG => "tcp_mpeg",
            T::VIDEO_STREAM_TYPE_MPEG_TS => "mpeg_ts",
            T::VIDEO_STREAM_TYPE_WHEP => "whep",
        }
        .into(),
        encoding: match d.encoding {
            E::VIDEO_STREAM_ENCODING_H264 => "h264",
            E::VIDEO_STREAM_ENCODING_H265 => "h265",
            E::VIDEO_STREAM_ENCODING_UNKNOWN => "unknown",
        }
        .into(),
        name: text(&d.name[..]),
        uri: text(&d.uri[..]),
        framerate: d.framerate,
        width: d.resolution_h,
        height: d.resolution_v,
        bitrate: d.bitrate,
    }
}
