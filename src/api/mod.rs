//! The HTTP API (`/api/v1`, JSON) and the operator's page.
//!
//! [`router`] builds the axum router over an [`AppState`]: the video ingest,
//! read-only views of the SLAM and the vehicle (traits, so the daemon plugs
//! in the real parts and tests plug in their own), the shot computer and
//! the shot store. Errors are JSON `{"error": {"code", "message"}}` with
//! the matching status; state-changing endpoints need `Authorization:
//! Bearer <token>` when a token is configured; bodies are size-limited.

pub mod shots;
pub mod store;

use std::future::Future;
use std::pin::Pin;
use std::sync::Arc;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::rejection::BytesRejection;
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::{HeaderMap, HeaderValue, StatusCode, header};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use image::GrayImage;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

use crate::video::live::{Ingest, unix_now};
use shots::{ShotComputer, ShotError};
use store::{MissionRecord, PoseJson, Shot, ShotSource, ShotStore};

/// A boxed future (the vehicle trait is object-safe).
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = T> + Send + 'a>>;

/// SLAM status as the API reports it.
#[derive(Debug, Clone, Default, Serialize)]
pub struct SlamStatus {
    /// Whether a SLAM runs in this daemon.
    pub available: bool,
    /// `initializing`, `tracking`, `lost`, ... (`unavailable` without SLAM).
    pub state: String,
    /// Frames processed.
    pub frames: u64,
    /// Frames tracked.
    pub tracked: u64,
    /// Keyframes in the map.
    pub keyframes: usize,
    /// Map points.
    pub points: usize,
    /// Inliers of the last tracked frame.
    pub last_inliers: usize,
    /// Processing time of the last frame, ms.
    pub last_frame_ms: f64,
    /// Median latency from capture to tracked pose over recent frames, ms.
    pub latency_ms_median: Option<f64>,
    /// 95th percentile of the same latencies, ms.
    pub latency_ms_p95: Option<f64>,
    /// Frames per second processed.
    pub fps: f64,
    /// Where the map came from at start (None before the SLAM started).
    pub map_start: Option<MapStart>,
    /// The map file last written (a checkpoint, or at shutdown).
    pub map_saved: Option<MapSaved>,
}

/// The last map file written.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MapSaved {
    /// `checkpoint` or `shutdown`.
    pub reason: String,
    /// Keyframes in it.
    pub keyframes: usize,
    /// Map points in it.
    pub points: usize,
    /// File size, bytes.
    pub bytes: u64,
    /// Pairs in the georeference written beside it (None: none written).
    pub geo_pairs: Option<usize>,
    /// When it was written, unix seconds.
    pub at_unix: f64,
}

/// Where the SLAM's map came from when the daemon started.
#[derive(Debug, Clone, Default, PartialEq, Serialize)]
pub struct MapStart {
    /// `fresh` (no saved map, or `[slam] continue_map = false`),
    /// `continued` (the saved map was loaded and is relocalised into), or
    /// `fresh_after_error` (the saved map could not be used).
    pub mode: String,
    /// Keyframes loaded from the saved map.
    pub keyframes: usize,
    /// Points loaded from the saved map.
    pub points: usize,
    /// The first frame (ingest sequence number) tracked in the loaded map.
    pub relocalised_at_frame: Option<u64>,
    /// Why the saved map was not used.
    pub error: Option<String>,
    /// Where a saved map that was not continued was moved to.
    pub set_aside: Option<std::path::PathBuf>,
}

/// A keyframe in the API.
#[derive(Debug, Clone, Serialize)]
pub struct KeyframeInfo {
    /// Id.
    pub id: u64,
    /// Timestamp, seconds.
    pub timestamp: f64,
    /// Pose.
    pub world_from_cam: PoseJson,
    /// Image width and height, pixels (0 when no image is kept).
    pub width: u32,
    /// See `width`.
    pub height: u32,
}

/// The newest tracked frame, placed relative to its reference keyframe (so
/// that it moves with it when bundle adjustment moves the keyframe): the
/// georeference pairs such frames with telemetry.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedFrame {
    /// Ingest sequence number.
    pub seq: u64,
    /// Capture time, seconds (the keyframes' clock).
    pub timestamp: f64,
    /// The reference keyframe.
    pub reference_kf: u64,
    /// `cam ← ref_cam`: the frame's camera relative to the reference
    /// keyframe's.
    pub cam_from_ref: nalgebra::Isometry3<f64>,
}

/// The map for the top view.
#[derive(Debug, Clone, Default, Serialize)]
pub struct MapView {
    /// Points (decimated), map frame.
    pub points: Vec<[f32; 3]>,
    /// Points in the map before decimation.
    pub total_points: usize,
    /// Keyframe camera centres, in id order.
    pub trajectory: Vec<[f64; 3]>,
}

impl<T: SlamView + ?Sized> shots::KeyframeImages for Arc<T> {
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>> {
        SlamView::keyframe_image(self.as_ref(), id)
    }
}

/// What the API reads from the SLAM.
pub trait SlamView: Send + Sync {
    /// The status.
    fn status(&self) -> SlamStatus;
    /// The keyframes, in id order.
    fn keyframes(&self) -> Vec<KeyframeInfo>;
    /// A keyframe's image.
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>>;
    /// The map, with at most `max_points` points.
    fn map(&self, max_points: usize) -> MapView;
    /// The newest tracked frame (None: none yet, or no SLAM).
    fn last_tracked(&self) -> Option<TrackedFrame> {
        None
    }
}

/// Errors of vehicle actions, each with its HTTP status.
#[derive(Debug, Clone, thiserror::Error)]
pub enum VehicleError {
    /// No vehicle link, or the vehicle is not heard.
    #[error("no vehicle: {reason}")]
    NoVehicle {
        /// Why.
        reason: String,
    },
    /// The map is not tied to the world yet.
    #[error("no georeference yet: {reason}")]
    NoGeoreference {
        /// Why.
        reason: String,
    },
    /// The action does not fit the shot's state.
    #[error("{reason}")]
    Conflict {
        /// Why.
        reason: String,
    },
    /// The vehicle refused or the transfer failed.
    #[error("vehicle: {reason}")]
    Failed {
        /// Why.
        reason: String,
    },
}

/// What the API asks of the vehicle.
pub trait VehicleView: Send + Sync {
    /// Link and vehicle state, as JSON.
    fn status(&self) -> Value;
    /// Plan the localised shot's mission and upload it.
    fn upload_shot<'a>(
        &'a self,
        shot: &'a Shot,
    ) -> BoxFuture<'a, Result<MissionRecord, VehicleError>>;
    /// Start the uploaded mission.
    fn start_mission(&self) -> BoxFuture<'_, Result<(), VehicleError>>;
    /// Mission progress, as JSON.
    fn progress(&self) -> Value;
    /// The vehicle target (latitude, longitude, altitude, yaw, gimbal
    /// pitch) of a localised shot, without uploading anything.
    fn shot_target(&self, shot: &Shot) -> Result<Value, VehicleError> {
        Err(VehicleError::NoGeoreference {
            reason: format!("no georeference for shot {}", shot.id),
        })
    }
    /// The mission the vehicle holds, read back over the link.
    fn download_mission(&self) -> BoxFuture<'_, Result<Value, VehicleError>> {
        Box::pin(async {
            Err(VehicleError::NoVehicle {
                reason: "this vehicle cannot be read back".into(),
            })
        })
    }
}

/// Server tunables the API needs.
#[derive(Debug, Clone, PartialEq)]
pub struct ApiParams {
    /// Bearer token for state-changing endpoints (None: open).
    pub token: Option<String>,
    /// Largest request body, bytes.
    pub body_limit: usize,
    /// Most points `GET /map` returns.
    pub map_max_points: usize,
    /// Status events per second on `/events`.
    pub events_hz: f64,
    /// JPEG quality of keyframe and shot images.
    pub jpeg_quality: u8,
}

impl Default for ApiParams {
    fn default() -> Self {
        Self {
            token: None,
            body_limit: 8 << 20,
            map_max_points: 20_000,
            events_hz: 2.0,
            jpeg_quality: 85,
        }
    }
}

/// Everything the handlers read.
#[derive(Clone)]
pub struct AppState {
    /// The video ingest.
    pub ingest: Arc<Ingest>,
    /// The SLAM.
    pub slam: Arc<dyn SlamView>,
    /// The vehicle (None: no link configured).
    pub vehicle: Option<Arc<dyn VehicleView>>,
    /// Shot computation.
    pub shots: Arc<dyn ShotComputer>,
    /// Shot persistence.
    pub store: Arc<ShotStore>,
    /// Tunables.
    pub params: Arc<ApiParams>,
    /// Serialises shot creation and mission actions.
    pub actions: Arc<tokio::sync::Mutex<()>>,
    /// Daemon start time, unix seconds.
    pub started_unix: f64,
    /// Cancelled at shutdown: ends the endless responses (events, video)
    /// so that the graceful shutdown does not wait for their clients.
    pub shutdown: tokio_util::sync::CancellationToken,
}

/// An API error: status, machine code, message.
#[derive(Debug, Clone)]
pub struct ApiError {
    /// HTTP status.
    pub status: StatusCode,
    /// Machine-readable code.
    pub code: &'static str,
    /// Human-readable message.
    pub message: String,
    /// Machine-readable details merged into the error object (e.g. which
    /// anchor check refused: `{"reason": "not_convex", "anchor": 2}`).
    pub detail: Option<serde_json::Map<String, Value>>,
}

impl ApiError {
    /// A new error.
    pub fn new(status: StatusCode, code: &'static str, message: impl Into<String>) -> Self {
        Self {
            status,
            code,
            message: message.into(),
            detail: None,
        }
    }

    /// The same error with machine-readable details.
    pub fn with_detail(mut self, detail: serde_json::Map<String, Value>) -> Self {
        self.detail = Some(detail);
        self
    }
    fn not_found(what: &str) -> Self {
        Self::new(
            StatusCode::NOT_FOUND,
            "not_found",
            format!("{what} not found"),
        )
    }
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let mut error = serde_json::Map::new();
        error.insert("code".into(), self.code.into());
        error.insert("message".into(), self.message.into());
        for (k, v) in self.detail.into_iter().flatten() {
            error.entry(k).or_insert(v);
        }
        let mut r = (self.status, Json(json!({ "error": error }))).into_response();
        if self.status == StatusCode::UNAUTHORIZED {
            r.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        r
    }
}

impl From<ShotError> for ApiError {
    fn from(e: ShotError) -> Self {
        match e {
            ShotError::UnknownKeyframe { .. } => {
                Self::new(StatusCode::NOT_FOUND, "unknown_keyframe", e.to_string())
            }
            ShotError::BadAnchors { ref source } => {
                let detail = anchor_refusal(source);
                Self::new(StatusCode::BAD_REQUEST, "bad_anchors", e.to_string()).with_detail(detail)
            }
            ShotError::BadImage { .. } => {
                Self::new(StatusCode::BAD_REQUEST, "bad_image", e.to_string())
            }
            ShotError::BadIntrinsics { .. } => {
                Self::new(StatusCode::BAD_REQUEST, "bad_intrinsics", e.to_string())
            }
            ShotError::IntrinsicsRequired { .. } => Self::new(
                StatusCode::BAD_REQUEST,
                "intrinsics_required",
                e.to_string(),
            ),
        }
    }
}

/// Which anchor check refused, as the error's `reason` (and the anchor's
/// index where one anchor is at fault).
fn anchor_refusal(e: &crate::shot::ShotError) -> serde_json::Map<String, Value> {
    use crate::shot::ShotError as R;
    let (reason, anchor) = match e {
        R::NonFiniteAnchor { index } => ("non_finite", Some(*index)),
        R::AnchorOutOfBounds { index, .. } => ("out_of_bounds", Some(*index)),
        R::Crossed { .. } => ("crossed", None),
        R::Collapsed { .. } => ("collapsed", None),
        R::MirroredWinding => ("mirrored", None),
        R::NotConvex { vertex } => ("not_convex", Some(*vertex)),
        R::NearSingular { .. } => ("near_singular", None),
        _ => ("invalid", None),
    };
    let mut m = serde_json::Map::new();
    m.insert("reason".into(), reason.into());
    if let Some(i) = anchor {
        m.insert("anchor".into(), i.into());
    }
    m
}

impl From<VehicleError> for ApiError {
    fn from(e: VehicleError) -> Self {
        let (status, code) = match &e {
            VehicleError::NoVehicle { .. } => (StatusCode::SERVICE_UNAVAILABLE, "no_vehicle"),
            VehicleError::NoGeoreference { .. } => (StatusCode::CONFLICT, "no_georeference"),
            VehicleError::Conflict { .. } => (StatusCode::CONFLICT, "conflict"),
            VehicleError::Failed { .. } => (StatusCode::BAD_GATEWAY, "vehicle_failed"),
        };
        Self::new(status, code, e.to_string())
    }
}

/// A request body that could not be read: 413 names the limit (and the
/// setting that raises it), anything else is a 400-class `bad_body`.
fn body_rejection(r: BytesRejection, limit: usize) -> ApiError {
    let status = r.status();
    if status == StatusCode::PAYLOAD_TOO_LARGE {
        let mut detail = serde_json::Map::new();
        detail.insert("limit_bytes".into(), limit.into());
        ApiError::new(
            status,
            "body_too_large",
            format!(
                "the request body is larger than the limit of {limit} bytes ({:.1} MiB; [server] body_limit_bytes)",
                limit as f64 / (1u64 << 20) as f64
            ),
        )
        .with_detail(detail)
    } else {
        ApiError::new(status, "bad_body", r.body_text())
    }
}

/// The OpenAPI document.
pub const OPENAPI: &str = include_str!("openapi.json");

/// The operator's page.
const INDEX_HTML: &str = include_str!("../../web/index.html");
const APP_JS: &str = include_str!("../../web/app.js");
const STYLE_CSS: &str = include_str!("../../web/style.css");

/// The router: `/api/v1/...` and the page at `/`.
pub fn router(state: AppState) -> Router {
    let limit = state.params.body_limit;
    let changing = Router::new()
        .route("/shots", post(create_shot))
        .route("/shots/photo", post(create_shot_from_photo))
        .route("/shots/{id}/mission", post(upload_mission))
        .route("/shots/{id}/start", post(start_mission))
        .route_layer(middleware::from_fn_with_state(state.clone(), require_token));
    let api = Router::new()
        .route("/openapi.json", get(openapi))
        .route("/status", get(status))
        .route("/events", get(events))
        .route("/video.mjpg", get(video_mjpeg))
        .route("/snapshot.jpg", get(snapshot))
        .route("/keyframes", get(keyframes))
        .route("/keyframes/{id}/image.jpg", get(keyframe_image))
        .route("/map", get(map))
        .route("/shots", get(list_shots))
        .route("/shots/{id}", get(get_shot))
        .route("/shots/{id}/image.jpg", get(shot_image))
        .route("/shots/{id}/progress", get(progress))
        .route("/shots/{id}/target", get(shot_target))
        .route("/vehicle/mission", get(vehicle_mission))
        .merge(changing)
        .fallback(|| async { ApiError::not_found("endpoint") });
    Router::new()
        .nest("/api/v1", api)
        .route(
            "/",
            get(|| async { static_file(INDEX_HTML, "text/html; charset=utf-8") }),
        )
        .route(
            "/app.js",
            get(|| async { static_file(APP_JS, "text/javascript; charset=utf-8") }),
        )
        .route(
            "/style.css",
            get(|| async { static_file(STYLE_CSS, "text/css; charset=utf-8") }),
        )
        .layer(DefaultBodyLimit::max(limit))
        .with_state(state)
}

fn static_file(body: &'static str, ct: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, ct),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        body,
    )
        .into_response()
}

/// Constant-time comparison of two byte strings.
fn ct_eq(a: &[u8], b: &[u8]) -> bool {
    if a.len() != b.len() {
        return false;
    }
    a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
}

async fn require_token(State(st): State<AppState>, req: Request, next: Next) -> Response {
    if let Some(token) = &st.params.token {
        let given = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(str::trim);
        match given {
            None => {
                return ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "unauthorized",
                    "a bearer token is required",
                )
                .into_response();
            }
            Some(g) if !ct_eq(g.as_bytes(), token.as_bytes()) => {
                return ApiError::new(
                    StatusCode::UNAUTHORIZED,
                    "unauthorized",
                    "wrong bearer token",
                )
                .into_response();
            }
            Some(_) => {}
        }
    }
    next.run(req).await
}

async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI).into_response()
}

fn status_json(st: &AppState) -> Value {
    let c = st.ingest.counters.snapshot();
    let latest = st.ingest.latest();
    json!({
        "uptime_s": unix_now() - st.started_unix,
        "video": {
            "received_fps": st.ingest.received_rate.rate(),
            "decoded_fps": st.ingest.decoded_rate.rate(),
            "consumed_fps": st.ingest.consumed_rate.rate(),
            "counters": c,
            "source": st.ingest.source_info(),
            "bitrate_kbps": st.ingest.byte_rate.bits_per_second() / 1e3,
            "width": latest.as_ref().map(|f| f.image.width()),
            "height": latest.as_ref().map(|f| f.image.height()),
            "last_frame_age_s": latest.as_ref().map(|f| f.received.elapsed().as_secs_f64()),
        },
        "slam": st.slam.status(),
        "vehicle": st.vehicle.as_ref().map_or(json!({"configured": false}), |v| v.status()),
        "shots": st.store.list().len(),
    })
}

async fn status(State(st): State<AppState>) -> Json<Value> {
    Json(status_json(&st))
}

async fn events(
    State(st): State<AppState>,
) -> Sse<impl futures_util::Stream<Item = Result<Event, std::convert::Infallible>>> {
    let period = Duration::from_secs_f64(1.0 / st.params.events_hz.clamp(0.1, 50.0));
    let stream = futures_util::stream::unfold((st, true), move |(st, first)| async move {
        if !first {
            tokio::select! {
                _ = st.shutdown.cancelled() => return None,
                _ = tokio::time::sleep(period) => {}
            }
        }
        let ev = Event::default()
            .event("status")
            .data(status_json(&st).to_string());
        Some((Ok(ev), (st, false)))
    });
    Sse::new(stream).keep_alive(KeepAlive::default())
}

const RESERVE_BOUNDARY: &str = "shotpilotapi";

async fn video_mjpeg(State(st): State<AppState>) -> Response {
    let rx = st.ingest.subscribe();
    let shutdown = st.shutdown.clone();
    let stream = futures_util::stream::unfold((rx, shutdown), |(mut rx, shutdown)| async move {
        // The newest frame each time; a slow client skips frames.
        tokio::select! {
            _ = shutdown.cancelled() => return None,
            r = rx.changed() => r.ok()?,
        }
        let frame = rx.borrow_and_update().clone();
        let frame = frame?;
        let jpeg = frame.jpeg();
        let mut part = format!(
            "--{RESERVE_BOUNDARY}\r\nContent-Type: image/jpeg\r\nContent-Length: {}\r\nX-Timestamp: {:.6}\r\n\r\n",
            jpeg.len(),
            frame.timestamp()
        )
        .into_bytes();
        part.extend_from_slice(&jpeg);
        part.extend_from_slice(b"\r\n");
        Some((
            Ok::<_, std::convert::Infallible>(Bytes::from(part)),
            (rx, shutdown),
        ))
    });
    (
        [
            (
                header::CONTENT_TYPE,
                format!("multipart/x-mixed-replace; boundary={RESERVE_BOUNDARY}"),
            ),
            (header::CACHE_CONTROL, "no-cache".to_owned()),
        ],
        Body::from_stream(stream),
    )
        .into_response()
}

async fn snapshot(State(st): State<AppState>) -> Result<Response, ApiError> {
    let f = st.ingest.latest().ok_or_else(|| {
        ApiError::new(
            StatusCode::SERVICE_UNAVAILABLE,
            "no_video",
            "no frame received yet",
        )
    })?;
    Ok(jpeg_response(f.jpeg().as_ref().clone()))
}

fn jpeg_response(bytes: Vec<u8>) -> Response {
    (
        [
            (header::CONTENT_TYPE, "image/jpeg"),
            (header::CACHE_CONTROL, "no-cache"),
        ],
        bytes,
    )
        .into_response()
}

fn encode_jpeg(img: &GrayImage, quality: u8) -> Result<Vec<u8>, ApiError> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality)
        .encode_image(img)
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "encode", e.to_string()))?;
    Ok(out)
}

async fn keyframes(State(st): State<AppState>) -> Json<Value> {
    let kfs = st.slam.keyframes();
    Json(json!({"count": kfs.len(), "keyframes": kfs}))
}

fn parse_u64(id: &str, what: &str) -> Result<u64, ApiError> {
    id.parse().map_err(|_| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad_id",
            format!("{what} id {id:?} is not a number"),
        )
    })
}

async fn keyframe_image(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let id = parse_u64(&id, "keyframe")?;
    let img = st
        .slam
        .keyframe_image(id)
        .ok_or_else(|| ApiError::not_found("keyframe"))?;
    let q = st.params.jpeg_quality;
    let jpeg = tokio::task::spawn_blocking(move || encode_jpeg(&img, q))
        .await
        .map_err(|e| {
            ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string())
        })??;
    Ok(jpeg_response(jpeg))
}

#[derive(Deserialize)]
struct MapQuery {
    max_points: Option<usize>,
}

async fn map(State(st): State<AppState>, Query(q): Query<MapQuery>) -> Json<MapView> {
    let n = q
        .max_points
        .unwrap_or(st.params.map_max_points)
        .min(st.params.map_max_points);
    Json(st.slam.map(n))
}

async fn list_shots(State(st): State<AppState>) -> Json<Value> {
    let shots = st.store.list();
    Json(json!({"count": shots.len(), "shots": shots}))
}

fn find_shot(st: &AppState, id: &str) -> Result<Shot, ApiError> {
    st.store.get(id).ok_or_else(|| ApiError::not_found("shot"))
}

async fn get_shot(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Shot>, ApiError> {
    Ok(Json(find_shot(&st, &id)?))
}

async fn shot_image(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    find_shot(&st, &id)?;
    let img = st
        .store
        .image(&id)
        .ok_or_else(|| ApiError::not_found("shot image"))?;
    Ok(jpeg_response(img))
}

/// `POST /shots` body.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShotRequest {
    /// The keyframe the anchors are on.
    pub keyframe_id: u64,
    /// Where the picture's four corner pixels go on the keyframe (top-left,
    /// top-right, bottom-right, bottom-left), pixels, pixel centres at
    /// integers (the keyframe's top-left pixel is (0, 0)).
    pub anchors: Vec<[f64; 2]>,
    /// Desired picture width, pixels (default: the keyframe's).
    pub width: Option<u32>,
    /// Desired picture height, pixels (default: the keyframe's).
    pub height: Option<u32>,
}

/// A checked shot request: keyframe id, four anchors, optional output size.
pub type ParsedShot = (u64, [[f64; 2]; 4], Option<(u32, u32)>);

/// Parse and check a shot request body (also the fuzz target's entry).
pub fn parse_shot_request(body: &[u8]) -> Result<ParsedShot, ApiError> {
    let req: ShotRequest = serde_json::from_slice(body)
        .map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, "bad_json", e.to_string()))?;
    let anchors: [[f64; 2]; 4] = req.anchors.as_slice().try_into().map_err(|_| {
        ApiError::new(
            StatusCode::BAD_REQUEST,
            "bad_anchors",
            format!("exactly 4 anchors are needed, got {}", req.anchors.len()),
        )
        .with_detail(serde_json::Map::from_iter([(
            "reason".to_owned(),
            Value::from("count"),
        )]))
    })?;
    let size = match (req.width, req.height) {
        (Some(w), Some(h)) => Some((w, h)),
        (None, None) => None,
        _ => {
            return Err(ApiError::new(
                StatusCode::BAD_REQUEST,
                "bad_size",
                "give both width and height, or neither",
            ));
        }
    };
    Ok((req.keyframe_id, anchors, size))
}

async fn store_shot(
    st: &AppState,
    source: ShotSource,
    comp: shots::ShotComputation,
) -> Result<Response, ApiError> {
    let q = st.params.jpeg_quality;
    let jpeg = match comp.desired {
        Some(img) => Some(
            tokio::task::spawn_blocking(move || encode_jpeg(&img, q))
                .await
                .map_err(|e| {
                    ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string())
                })??,
        ),
        None => None,
    };
    let _guard = st.actions.lock().await;
    let (status, localisation, reason) = match comp.localisation {
        Ok(l) => ("localised", Some(l), None),
        Err(r) => ("not_localised", None, Some(r)),
    };
    let shot = Shot {
        id: st.store.next_id(),
        created_unix: unix_now(),
        source,
        status: status.into(),
        localisation,
        reason,
        has_image: jpeg.is_some(),
        mission: None,
    };
    let store = st.store.clone();
    let saved = shot.clone();
    tokio::task::spawn_blocking(move || store.put(saved, jpeg.as_deref()))
        .await
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()))?
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "store", e.to_string()))?;
    tracing::info!(id = %shot.id, status, "shot created");
    Ok((StatusCode::CREATED, Json(shot)).into_response())
}

async fn create_shot(
    State(st): State<AppState>,
    headers: HeaderMap,
    body: Result<Bytes, BytesRejection>,
) -> Result<Response, ApiError> {
    let body = body.map_err(|r| body_rejection(r, st.params.body_limit))?;
    if let Some(ct) = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        && !ct.starts_with("application/json")
    {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "bad_content_type",
            format!("expected application/json, got {ct}"),
        ));
    }
    let (kf, anchors, size) = parse_shot_request(&body)?;
    let computer = st.shots.clone();
    let comp = tokio::task::spawn_blocking(move || computer.shot_from_anchors(kf, &anchors, size))
        .await
        .map_err(|e| {
            ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string())
        })??;
    store_shot(
        &st,
        ShotSource::Anchors {
            keyframe_id: kf,
            anchors,
        },
        comp,
    )
    .await
}

/// `POST /shots/photo` query: the photo camera's intrinsics, all four of
/// `fx fy cx cy` or none; distortion terms optional (zero when left out).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhotoQuery {
    /// Focal length x, pixels.
    pub fx: Option<f64>,
    /// Focal length y, pixels.
    pub fy: Option<f64>,
    /// Principal point x, pixels.
    pub cx: Option<f64>,
    /// Principal point y, pixels.
    pub cy: Option<f64>,
    /// Radial, r^2.
    pub k1: Option<f64>,
    /// Radial, r^4.
    pub k2: Option<f64>,
    /// Tangential, first.
    pub p1: Option<f64>,
    /// Tangential, second.
    pub p2: Option<f64>,
    /// Radial, r^6.
    pub k3: Option<f64>,
}

impl PhotoQuery {
    /// The intrinsics it gives (None: none given).
    pub fn intrinsics(&self) -> Result<Option<shots::PhotoIntrinsics>, ApiError> {
        let bad = |m: &str| ApiError::new(StatusCode::BAD_REQUEST, "bad_intrinsics", m);
        let d = [self.k1, self.k2, self.p1, self.p2, self.k3];
        match (self.fx, self.fy, self.cx, self.cy) {
            (Some(fx), Some(fy), Some(cx), Some(cy)) => {
                let z = |v: Option<f64>| v.unwrap_or(0.0);
                Ok(Some(shots::PhotoIntrinsics {
                    fx,
                    fy,
                    cx,
                    cy,
                    distortion: crate::camera::Distortion {
                        k1: z(self.k1),
                        k2: z(self.k2),
                        p1: z(self.p1),
                        p2: z(self.p2),
                        k3: z(self.k3),
                    },
                }))
            }
            (None, None, None, None) if d.iter().all(Option::is_none) => Ok(None),
            (None, None, None, None) => Err(bad("distortion without fx, fy, cx, cy")),
            _ => Err(bad("give all of fx, fy, cx, cy, or none")),
        }
    }
}

async fn create_shot_from_photo(
    State(st): State<AppState>,
    headers: HeaderMap,
    query: Result<Query<PhotoQuery>, axum::extract::rejection::QueryRejection>,
    body: Result<Bytes, BytesRejection>,
) -> Result<Response, ApiError> {
    let body = body.map_err(|r| body_rejection(r, st.params.body_limit))?;
    let intrinsics = query
        .map_err(|e| ApiError::new(StatusCode::BAD_REQUEST, "bad_intrinsics", e.body_text()))?
        .0
        .intrinsics()?;
    let ct = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    if !(ct.starts_with("image/jpeg") || ct.starts_with("image/png")) {
        return Err(ApiError::new(
            StatusCode::UNSUPPORTED_MEDIA_TYPE,
            "bad_content_type",
            format!("expected image/jpeg or image/png, got {ct:?}"),
        ));
    }
    let bytes = body.len();
    let computer = st.shots.clone();
    let (comp, w, h) = tokio::task::spawn_blocking(move || {
        // A JPEG cut short decodes to a picture grey below the cut: refused.
        if body.starts_with(&[0xFF, 0xD8])
            && let Some(reason) = shots::jpeg_truncation(&body)
        {
            return Err(ShotError::BadImage { reason });
        }
        let img = image::load_from_memory(&body).map_err(|e| ShotError::BadImage {
            reason: format!("not a readable image: {e}"),
        })?;
        let grey = img.to_luma8();
        let (w, h) = grey.dimensions();
        computer
            .shot_from_photo(&grey, intrinsics.as_ref())
            .map(|c| (c, w, h))
    })
    .await
    .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()))??;
    store_shot(
        &st,
        ShotSource::Photo {
            bytes,
            width: w,
            height: h,
            intrinsics,
        },
        comp,
    )
    .await
}

fn vehicle(st: &AppState) -> Result<Arc<dyn VehicleView>, ApiError> {
    st.vehicle.clone().ok_or_else(|| {
        VehicleError::NoVehicle {
            reason: "no vehicle link is configured".into(),
        }
        .into()
    })
}

async fn upload_mission(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Shot>, ApiError> {
    let mut shot = find_shot(&st, &id)?;
    if shot.localisation.is_none() {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "not_localised",
            format!(
                "shot {id} is not localised: {}",
                shot.reason.as_deref().unwrap_or("no localisation")
            ),
        ));
    }
    let v = vehicle(&st)?;
    let _guard = st.actions.lock().await;
    let record = v.upload_shot(&shot).await?;
    shot.mission = Some(record);
    save(&st, shot).await
}

async fn shot_target(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let shot = find_shot(&st, &id)?;
    if shot.localisation.is_none() {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "not_localised",
            format!(
                "shot {id} is not localised: {}",
                shot.reason.as_deref().unwrap_or("no localisation")
            ),
        ));
    }
    let v = vehicle(&st)?;
    Ok(Json(v.shot_target(&shot)?))
}

async fn vehicle_mission(State(st): State<AppState>) -> Result<Json<Value>, ApiError> {
    let v = vehicle(&st)?;
    let _guard = st.actions.lock().await;
    Ok(Json(v.download_mission().await?))
}

async fn save(st: &AppState, shot: Shot) -> Result<Json<Shot>, ApiError> {
    let store = st.store.clone();
    let s = shot.clone();
    tokio::task::spawn_blocking(move || store.put(s, None))
        .await
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "internal", e.to_string()))?
        .map_err(|e| ApiError::new(StatusCode::INTERNAL_SERVER_ERROR, "store", e.to_string()))?;
    Ok(Json(shot))
}

async fn start_mission(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Shot>, ApiError> {
    let mut shot = find_shot(&st, &id)?;
    let v = vehicle(&st)?;
    let Some(mut m) = shot.mission.clone() else {
        return Err(ApiError::new(
            StatusCode::CONFLICT,
            "no_mission",
            format!("shot {id} has no uploaded mission"),
        ));
    };
    let _guard = st.actions.lock().await;
    v.start_mission().await?;
    m.state = "started".into();
    m.started_unix = Some(unix_now());
    shot.mission = Some(m);
    save(&st, shot).await
}

async fn progress(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Value>, ApiError> {
    let shot = find_shot(&st, &id)?;
    let v = vehicle(&st)?;
    Ok(Json(
        json!({"shot": shot.id, "mission": shot.mission, "progress": v.progress()}),
    ))
}
