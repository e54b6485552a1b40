//! The camera's video over HTTP: an MJPEG stream and a snapshot endpoint.
//!
//! - `GET /video.mjpg`: `multipart/x-mixed-replace; boundary=shotpilotframe`.
//!   Each part carries `Content-Type: image/jpeg`, `Content-Length`,
//!   `X-Timestamp: <capture time, unix seconds with microseconds>` and
//!   `X-Sequence: <frame number>`. A client first receives the current
//!   frame, then each new frame once; a client slower than the camera skips
//!   to the latest frame (nothing queues up).
//! - `GET /snapshot.jpg`: the latest frame as one JPEG with the same
//!   headers, or 503 before the first frame.
//!
//! Frames arrive through a `tokio::sync::watch` channel; the stream of
//! every client ends when the cancellation token fires or the sender is
//! dropped, so shutdown does not wait on open streams.

use std::convert::Infallible;
use std::sync::Arc;

use axum::Router;
use axum::body::{Body, Bytes};
use axum::extract::State;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::get;
use image::GrayImage;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

/// The multipart boundary of the MJPEG stream.
pub const BOUNDARY: &str = "shotpilotframe";

/// Errors of the video module.
#[derive(Debug, thiserror::Error)]
pub enum VideoError {
    /// JPEG encoding failed (zero-sized or oversized image).
    #[error("cannot encode a {width}x{height} image as JPEG: {source}")]
    Encode {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// The encoder's error.
        source: image::ImageError,
    },
    /// H.264 encoding or its RTP output failed.
    #[error("H.264: {reason}")]
    H264 {
        /// What failed.
        reason: String,
    },
}

/// Every tunable number of the video module.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Params {
    /// JPEG quality, 1-100.
    pub jpeg_quality: u8,
}

impl Default for Params {
    fn default() -> Self {
        Self { jpeg_quality: 85 }
    }
}

/// One encoded camera frame.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoFrame {
    /// The JPEG file.
    pub jpeg: Vec<u8>,
    /// When the frame was captured, unix seconds.
    pub capture_time_unix_s: f64,
    /// Frame number, increasing.
    pub seq: u64,
}

impl VideoFrame {
    /// Encodes `img` as a frame.
    pub fn encode(
        img: &GrayImage,
        quality: u8,
        capture_time_unix_s: f64,
        seq: u64,
    ) -> Result<VideoFrame, VideoError> {
        Ok(VideoFrame {
            jpeg: try_encode_jpeg(img, quality)?,
            capture_time_unix_s,
            seq,
        })
    }
}

/// Encodes a grey image as a baseline JPEG (quality clamped to 1-100).
pub fn try_encode_jpeg(img: &GrayImage, quality: u8) -> Result<Vec<u8>, VideoError> {
    let mut out = Vec::with_capacity(img.as_raw().len() / 4);
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality.clamp(1, 100))
        .encode_image(img)
        .map_err(|source| VideoError::Encode {
            width: img.width(),
            height: img.height(),
            source,
        })?;
    Ok(out)
}

/// Encodes a grey image as JPEG; an image JPEG cannot hold (zero-sized,
/// or a side over 65535 pixels) gives an empty vector and a warning. Use
/// [`try_encode_jpeg`] to handle the error.
pub fn encode_jpeg(img: &GrayImage, quality: u8) -> Vec<u8> {
    match try_encode_jpeg(img, quality) {
        Ok(v) => v,
        Err(e) => {
            tracing::warn!(error = %e, "JPEG encoding failed");
            Vec::new()
        }
    }
}

type FrameRx = watch::Receiver<Option<Arc<VideoFrame>>>;

#[derive(Clone)]
struct VideoState {
    frames: FrameRx,
    cancel: CancellationToken,
}

/// The video routes (`/video.mjpg`, `/snapshot.jpg`), for serving alone
/// ([`serve_video`]) or merged into another router.
pub fn router(frames: FrameRx, cancel: CancellationToken) -> Router {
    Router::new()
        .route("/video.mjpg", get(mjpeg))
        .route("/snapshot.jpg", get(snapshot))
        .with_state(VideoState { frames, cancel })
}

/// Serves the video routes on `listener` until `cancel` fires.
pub async fn serve_video(
    listener: tokio::net::TcpListener,
    frames: FrameRx,
    cancel: CancellationToken,
) -> std::io::Result<()> {
    if let Ok(addr) = listener.local_addr() {
        tracing::info!(%addr, "video server listening");
    }
    let app = router(frames, cancel.clone());
    axum::serve(listener, app)
        .with_graceful_shutdown(cancel.cancelled_owned())
        .await
}

fn frame_headers(frame: &VideoFrame) -> [(header::HeaderName, HeaderValue); 3] {
    let ts = HeaderValue::from_str(&format!("{:.6}", frame.capture_time_unix_s))
        .unwrap_or(HeaderValue::from_static("0"));
    [
        (header::HeaderName::from_static("x-timestamp"), ts),
        (
            header::HeaderName::from_static("x-sequence"),
            HeaderValue::from(frame.seq),
        ),
        (header::CACHE_CONTROL, HeaderValue::from_static("no-cache")),
    ]
}

/// One multipart part: boundary, headers, JPEG, CRLF.
fn part(frame: &VideoFrame) -> Bytes {
    let head = format!(
        "--{BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\nX-Timestamp: {:.6}\r\nX-Sequence: {}\r\n\r\n",
        frame.jpeg.len(),
        frame.capture_time_unix_s,
        frame.seq
    );
    let mut buf = Vec::with_capacity(head.len() + frame.jpeg.len() + 2);
    buf.extend_from_slice(head.as_bytes());
    buf.extend_from_slice(&frame.jpeg);
    buf.extend_from_slice(b"\r\n");
    Bytes::from(buf)
}

async fn snapshot(State(state): State<VideoState>) -> Response {
    let latest = state.frames.borrow().clone();
    match latest {
        Some(frame) => {
            let mut resp = (StatusCode::OK, frame.jpeg.clone()).into_response();
            let h = resp.headers_mut();
            h.insert(header::CONTENT_TYPE, HeaderValue::from_static("image/jpeg"));
            for (k, v) in frame_headers(&frame) {
                h.insert(k, v);
            }
            resp
        }
        None => (StatusCode::SERVICE_UNAVAILABLE, "no frame yet\n").into_response(),
    }
}

async fn mjpeg(State(state): State<VideoState>) -> Response {
    let mut rx = state.frames.clone();
    // The current frame goes out first; then each change once.
    let first = rx.borrow_and_update().clone();
    let cancel = state.cancel.clone();
    let stream = futures_util::stream::unfold(
        (rx, first, cancel),
        |(mut rx, pending, cancel)| async move {
            let frame = match pending {
                Some(f) => f,
                None => loop {
                    tokio::select! {
                        _ = cancel.cancelled() => return None,
                        changed = rx.changed() => if changed.is_err() { return None },
                    }
                    if let Some(f) = rx.borrow_and_update().clone() {
                        break f;
                    }
                },
            };
            Some((Ok::<Bytes, Infallible>(part(&frame)), (rx, None, cancel)))
        },
    );
    let mut resp = Response::new(Body::from_stream(stream));
    let h = resp.headers_mut();
    h.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static(concat!(
            "multipart/x-mixed-replace; boundary=",
            "shotpilotframe"
        )),
    );
    h.insert(header::CACHE_CONTROL, HeaderValue::from_static("no-cache"));
    resp
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn jpeg_round_trip_and_errors() {
        let mut img = GrayImage::new(64, 48);
        for (i, p) in img.pixels_mut().enumerate() {
            p.0[0] = (i % 251) as u8;
        }
        let jpeg = encode_jpeg(&img, 90);
        assert_eq!(&jpeg[..2], &[0xFF, 0xD8]);
        let back = image::load_from_memory(&jpeg).unwrap().to_luma8();
        assert_eq!(back.dimensions(), (64, 48));
        let err: f64 = img
            .as_raw()
            .iter()
            .zip(back.as_raw())
            .map(|(a, b)| (*a as f64 - *b as f64).abs())
            .sum::<f64>()
            / (64.0 * 48.0);
        assert!(err < 8.0, "mean abs error {err}");
        assert!(try_encode_jpeg(&GrayImage::new(0, 0), 90).is_err());
        assert!(encode_jpeg(&GrayImage::new(0, 10), 90).is_empty());
    }

    #[test]
    fn concat_boundary_matches_the_constant() {
        assert_eq!(
            concat!("multipart/x-mixed-replace; boundary=", "shotpilotframe"),
            format!("multipart/x-mixed-replace; boundary={BOUNDARY}")
        );
    }
}
