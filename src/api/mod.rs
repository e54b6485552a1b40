//! The HTTP API (`/api/v1`, JSON) and the operator's page.
//!
//! [`router`] builds the axum router over an [`AppState`]: the video ingest,
//! read-only views of the SLAM and the vehicle (traits, so the daemon plugs
//! in the real parts and tests plug in their own), the shot computer and
//! the shot store. Errors are JSON `{"error": {"code", "message"}}` with
//! the matching status; state-changing endpoints need `Authorization:
//! Bearer <token>` when a token is configured; bodies are size-limited.

mod before_after;
mod error;
mod events;
mod features;
mod shot_intake;
mod views;

pub use before_after::compose_before_after;
pub use error::ApiError;
pub use events::{
    Achieved, ShotEvent, ShotEventRecord, ShotEvents, apply_status_patch, status_patch,
};
pub use features::{FeaturesView, StateCounts, TrackedFeatures, pack, select, unpack};
pub use shot_intake::{ParsedShot, PhotoQuery, ShotRequest, parse_shot_request};
use shot_intake::{create_shot, create_shot_from_photo};
pub use views::{
    AlignmentView, BoxFuture, GimbalManagerView, KeyframeInfo, KeyframeList, LoopInfo, MapSaved,
    MapStart, MapView, MergeInfo, MissionProgressView, ProgressView, ShotList, ShotTarget,
    SlamStatus, SlamView, StatusView, StopOutcome, StopView, TargetView, TrackedFrame,
    VehicleError, VehicleGimbal, VehicleMissionView, VehiclePosition, VehicleStatus,
    VehicleStatusView, VehicleView, VideoStatusView, WriteFailure,
};

use std::sync::Arc;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::header;
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use image::GrayImage;
use serde::Deserialize;
use serde_json::{Value, json};

use crate::shot::record::{MissionState, Shot};
use crate::shot::request::ShotComputer;
use crate::shot::store::ShotStore;
use crate::video::live::{Ingest, unix_now};

/// Server tunables the API needs.
#[derive(Debug, Clone, PartialEq)]
pub struct ApiParams {
    /// Bearer token for state-changing endpoints (None: open).
    pub token: Option<String>,
    /// Largest request body, bytes.
    pub body_limit: usize,
    /// Most points `GET /map` returns.
    pub map_max_points: usize,
    /// Status updates per second on `/events` at most (patches; none
    /// while nothing changed).
    pub events_hz: f64,
    /// JPEG quality of keyframe and shot images.
    pub jpeg_quality: u8,
    /// Most keypoints `GET /features` returns.
    pub features_max: usize,
}

impl Default for ApiParams {
    fn default() -> Self {
        Self {
            token: None,
            body_limit: 8 << 20,
            map_max_points: 20_000,
            events_hz: 2.0,
            jpeg_quality: 85,
            features_max: 500,
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
    /// Shot events (the `shot` events of `/events`) and achieved frames.
    pub events: Arc<ShotEvents>,
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
        .route("/vehicle/stop", post(stop_vehicle))
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
        .route("/features", get(features_of))
        .route("/features/{seq}/frame.jpg", get(features_frame))
        .route("/shots", get(list_shots))
        .route("/shots/{id}", get(get_shot))
        .route("/shots/{id}/image.jpg", get(shot_image))
        .route("/shots/{id}/progress", get(progress))
        .route("/shots/{id}/target", get(shot_target))
        .route("/shots/{id}/achieved.jpg", get(achieved_image))
        .route("/shots/{id}/before_after.png", get(before_after_png))
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
                return ApiError::Unauthorized("a bearer token is required").into_response();
            }
            Some(g) if !ct_eq(g.as_bytes(), token.as_bytes()) => {
                return ApiError::Unauthorized("wrong bearer token").into_response();
            }
            Some(_) => {}
        }
    }
    next.run(req).await
}

async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI).into_response()
}

fn status_view(st: &AppState) -> StatusView {
    let c = st.ingest.counters.snapshot();
    let slam = st.slam.status();
    // Writes that failed and are not repaired yet: the page shows them.
    let errors: Vec<WriteFailure> = slam
        .map_save_error
        .clone()
        .into_iter()
        .chain(st.store.write_error().map(|f| WriteFailure {
            what: "shot",
            message: f.message,
            at_unix: f.at_unix,
        }))
        .collect();
    let latest = st.ingest.latest();
    let now = unix_now();
    StatusView {
        uptime_s: now - st.started_unix,
        now_unix: now,
        video: VideoStatusView {
            received_fps: st.ingest.received_rate.rate(),
            decoded_fps: st.ingest.decoded_rate.rate(),
            consumed_fps: st.ingest.consumed_rate.rate(),
            counters: c,
            link: st.ingest.link.report(),
            source: st.ingest.source_info(),
            bitrate_kbps: st.ingest.byte_rate.bits_per_second() / 1e3,
            width: latest.as_ref().map(|f| f.image.width()),
            height: latest.as_ref().map(|f| f.image.height()),
            last_frame_age_s: latest
                .as_ref()
                .map(|f| crate::clock::since(f.received).as_secs_f64()),
        },
        slam,
        vehicle: st
            .vehicle
            .as_ref()
            .map_or(VehicleStatusView::Absent { configured: false }, |v| {
                VehicleStatusView::Configured(Box::new(v.status()))
            }),
        shots: st.store.list().len(),
        errors,
    }
}

/// The status as a JSON document, for the `/events` stream's patches.
fn status_json(st: &AppState) -> Value {
    serde_json::to_value(status_view(st)).unwrap_or_else(|e| {
        tracing::error!(error = %e, "the status could not be written as JSON");
        Value::Null
    })
}

async fn status(State(st): State<AppState>) -> Json<StatusView> {
    Json(status_view(&st))
}

/// The `/events` stream's state: the history still to send, the live
/// shot events, the next status time, the status document last sent.
struct EventsState {
    st: AppState,
    replay: std::collections::VecDeque<Arc<ShotEventRecord>>,
    rx: tokio::sync::broadcast::Receiver<Arc<ShotEventRecord>>,
    next_status: tokio::time::Instant,
    period: Duration,
    sent_status: Option<Value>,
}

fn shot_event(r: &ShotEventRecord) -> Event {
    Event::default()
        .event("shot")
        .data(serde_json::to_string(r).unwrap_or_else(|_| "{}".into()))
}

/// The status as deltas: a `status` event (the whole /status document) at
/// once, then at most `events_hz` times a second a `status_patch` event
/// with what changed since the last one sent ([`status_patch`]), none when
/// nothing did; and `shot` events ([`ShotEventRecord`]): first the kept
/// history, then each as it happens.
async fn events(
    State(st): State<AppState>,
) -> Sse<impl futures_util::Stream<Item = Result<Event, std::convert::Infallible>>> {
    let period = Duration::from_secs_f64(1.0 / st.params.events_hz.clamp(0.1, 50.0));
    let (history, rx) = st.events.subscribe();
    let state = EventsState {
        st,
        replay: history.into(),
        rx,
        next_status: tokio::time::Instant::now(),
        period,
        sent_status: None,
    };
    let stream = futures_util::stream::unfold(state, |mut s| async move {
        use tokio::sync::broadcast::error::RecvError;
        loop {
            let now = tokio::time::Instant::now();
            if s.next_status <= now {
                s.next_status = (s.next_status + s.period).max(now);
                let doc = status_json(&s.st);
                let ev = match &s.sent_status {
                    None => Some(Event::default().event("status").data(doc.to_string())),
                    Some(old) => status_patch(old, &doc)
                        .map(|p| Event::default().event("status_patch").data(p.to_string())),
                };
                s.sent_status = Some(doc);
                if let Some(ev) = ev {
                    return Some((Ok(ev), s));
                }
            }
            if let Some(r) = s.replay.pop_front() {
                return Some((Ok(shot_event(&r)), s));
            }
            tokio::select! {
                _ = s.st.shutdown.cancelled() => return None,
                _ = tokio::time::sleep_until(s.next_status) => {}
                r = s.rx.recv() => match r {
                    Ok(r) => return Some((Ok(shot_event(&r)), s)),
                    // A slow client skips what it missed.
                    Err(RecvError::Lagged(_)) => {}
                    Err(RecvError::Closed) => return None,
                },
            }
        }
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
    let f = st.ingest.latest().ok_or_else(|| ApiError::NoVideo)?;
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
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, quality).encode_image(img)?;
    Ok(out)
}

async fn keyframes(State(st): State<AppState>) -> Json<KeyframeList> {
    let keyframes = st.slam.keyframes();
    Json(KeyframeList {
        count: keyframes.len(),
        keyframes,
    })
}

fn parse_u64(id: &str, what: &str) -> Result<u64, ApiError> {
    id.parse()
        .map_err(|_| ApiError::bad_request("bad_id", format!("{what} id {id:?} is not a number")))
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
    let jpeg = tokio::task::spawn_blocking(move || encode_jpeg(&img, q)).await??;
    Ok(jpeg_response(jpeg))
}

#[derive(Deserialize)]
struct FeaturesQuery {
    /// Most keypoints (at most `[server] features_max`).
    max: Option<usize>,
    /// The frame (default: the newest processed).
    seq: Option<u64>,
}

/// The keypoints of a recent frame and what tracking made of them.
async fn features_of(
    State(st): State<AppState>,
    Query(q): Query<FeaturesQuery>,
) -> Result<Json<FeaturesView>, ApiError> {
    let f = st
        .slam
        .features(q.seq)
        .ok_or_else(|| ApiError::not_found("tracked frame"))?;
    let max = q
        .max
        .unwrap_or(st.params.features_max)
        .min(st.params.features_max);
    Ok(Json(FeaturesView::of(&f, max)))
}

/// The picture of a frame `GET /features` described.
async fn features_frame(
    State(st): State<AppState>,
    Path(seq): Path<String>,
) -> Result<Response, ApiError> {
    let seq = parse_u64(&seq, "frame")?;
    let f = st
        .slam
        .features(Some(seq))
        .ok_or_else(|| ApiError::not_found("tracked frame"))?;
    let frame = f.frame.clone();
    let jpeg = tokio::task::spawn_blocking(move || frame.jpeg()).await?;
    Ok(jpeg_response(jpeg.as_ref().clone()))
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

async fn list_shots(State(st): State<AppState>) -> Json<ShotList> {
    let shots = st.store.list();
    Json(ShotList {
        count: shots.len(),
        shots,
    })
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
/// 409 `not_localised` for a shot without a localisation.
fn not_localised(shot: &Shot) -> Result<(), ApiError> {
    if shot.localisation.is_some() {
        return Ok(());
    }
    Err(ApiError::Conflict {
        code: "not_localised",
        message: format!(
            "shot {} is not localised: {}",
            shot.id,
            shot.reason.as_deref().unwrap_or("no localisation")
        ),
    })
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
    let shot = find_shot(&st, &id)?;
    not_localised(&shot)?;
    let v = vehicle(&st)?;
    let _guard = st.actions.lock().await;
    let record = v.upload_shot(&shot).await?;
    let target = &record.details["target"];
    let num = |k: &str| target[k].as_f64();
    let position_sigma_m = shot
        .localisation
        .as_ref()
        .and_then(|l| l.sigma)
        .zip(record.details["georeference"]["scale"].as_f64())
        .map(|(s, scale)| s.position * scale);
    if let (Some(lat_deg), Some(lon_deg), Some(alt_m), Some(yaw_deg), Some(gimbal_pitch_deg)) = (
        num("lat_deg"),
        num("lon_deg"),
        num("alt_above_home_m"),
        num("yaw_deg"),
        num("gimbal_pitch_deg"),
    ) {
        st.events.publish(
            &id,
            ShotEvent::Georeferenced {
                lat_deg,
                lon_deg,
                alt_m,
                yaw_deg,
                gimbal_pitch_deg,
                position_sigma_m,
            },
        );
    }
    let items = record.items;
    let store = st.store.clone();
    let sid = id.clone();
    let shot =
        tokio::task::spawn_blocking(move || store.update(&sid, |s| s.mission = Some(record)))
            .await??
            .ok_or(ApiError::not_found("shot"))?;
    st.events.publish(&id, ShotEvent::Uploaded { items });
    Ok(Json(shot))
}

async fn shot_target(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<ShotTarget>, ApiError> {
    let shot = find_shot(&st, &id)?;
    not_localised(&shot)?;
    let v = vehicle(&st)?;
    Ok(Json(v.shot_target(&shot)?))
}

/// The vehicle's mission, read back. Written through `serde_json::Value`
/// (as the shot's `details.planned_items` are), so an item's `f32`
/// parameters read the same in both and compare equal.
async fn vehicle_mission(State(st): State<AppState>) -> Result<Json<Value>, ApiError> {
    let v = vehicle(&st)?;
    let _guard = st.actions.lock().await;
    let mission: VehicleMissionView = v.download_mission().await?;
    Ok(Json(json!(mission)))
}

/// Starts the mission of THE shot asked for: 409 `no_mission` when it has
/// none uploaded, 409 `not_on_vehicle` when the vehicle holds another
/// shot's mission (the vehicle view checks; its refinement loop refines
/// this shot).
async fn start_mission(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<Shot>, ApiError> {
    let shot = find_shot(&st, &id)?;
    let v = vehicle(&st)?;
    if shot.mission.is_none() {
        return Err(ApiError::Conflict {
            code: "no_mission",
            message: format!("shot {id} has no uploaded mission"),
        });
    }
    let _guard = st.actions.lock().await;
    v.start_mission(&shot).await?;
    let started = unix_now();
    st.events.publish(&id, ShotEvent::Started);
    let store = st.store.clone();
    let shot = tokio::task::spawn_blocking(move || {
        store.update(&id, |s| {
            if let Some(m) = s.mission.as_mut() {
                m.state = MissionState::Started;
                m.started_unix = Some(started);
            }
        })
    })
    .await??
    .ok_or(ApiError::not_found("shot"))?;
    Ok(Json(shot))
}

async fn progress(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Json<ProgressView>, ApiError> {
    let shot = find_shot(&st, &id)?;
    let v = vehicle(&st)?;
    Ok(Json(ProgressView {
        shot: shot.id,
        mission: shot.mission,
        progress: v.progress(),
    }))
}

/// The reason a stop records on the shot.
const STOP_REASON: &str = "stopped by the operator";

/// Stops the vehicle where it is (hold), cancels the refinement loop, and
/// marks the shot it was flying `stopped`. Replies after the vehicle's
/// COMMAND_ACK; a refused or unacknowledged command is a 502 `vehicle_failed`.
/// Not serialised behind other mission actions: a stop never waits for an
/// upload.
async fn stop_vehicle(State(st): State<AppState>) -> Result<Json<StopView>, ApiError> {
    let v = vehicle(&st)?;
    let out = v.stop(STOP_REASON).await?;
    let at = unix_now();
    let ack = json!({
        "reason": STOP_REASON,
        "at_unix": at,
        "command": out.ack.command,
        "mode": out.ack.mode,
        "ack": out.ack.result,
    });
    // The shot flown: the one whose loop ran, else the one started last.
    let flown = out.refinement_cancelled.clone().or(out.flying.clone());
    let mut marked = None;
    if let Some(id) = flown {
        let store = st.store.clone();
        let (shot, changed) = tokio::task::spawn_blocking(move || {
            let mut changed = false;
            let shot = store.update(&id, |s| {
                if let Some(m) = s.mission.as_mut()
                    && matches!(
                        m.state,
                        MissionState::Started | MissionState::Active | MissionState::OnVehicle
                    )
                {
                    m.state = MissionState::Stopped;
                    m.set_detail("stop", ack);
                    changed = true;
                }
            })?;
            Ok::<_, crate::shot::store::StoreError>((shot, changed))
        })
        .await??;
        // Only a shot this stop changed (a second stop marks nothing new).
        marked = shot.filter(|_| changed).map(|s| s.id);
    }
    tracing::info!(shot = ?marked, mode = %out.ack.mode, "vehicle stopped by the operator");
    if let Some(id) = marked.as_ref().or(out.refinement_cancelled.as_ref()) {
        st.events.publish(
            id,
            ShotEvent::Stopped {
                reason: STOP_REASON.to_owned(),
            },
        );
    }
    Ok(Json(StopView {
        stopped: true,
        command: out.ack.command,
        mode: out.ack.mode,
        ack: out.ack.result,
        refinement_cancelled: out.refinement_cancelled,
        shot: marked,
        reason: STOP_REASON.to_owned(),
        at_unix: at,
    }))
}

/// The live frame of the shot's last refinement round (JPEG); 404 when
/// no round was measured in this daemon run.
async fn achieved_image(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    find_shot(&st, &id)?;
    let a = st
        .events
        .achieved(&id)
        .ok_or_else(|| ApiError::not_found("achieved frame"))?;
    let q = st.params.jpeg_quality;
    let jpeg = tokio::task::spawn_blocking(move || encode_jpeg(&a.frame, q)).await??;
    Ok(jpeg_response(jpeg))
}

/// One PNG of a refined shot: the desired picture, the achieved live
/// frame with the desired outline, and the two blended, under a line with
/// the final shot error ([`compose_before_after`]).
async fn before_after_png(
    State(st): State<AppState>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    find_shot(&st, &id)?;
    let a = st
        .events
        .achieved(&id)
        .ok_or_else(|| ApiError::not_found("achieved frame"))?;
    let jpeg = st
        .store
        .image(&id)
        .ok_or_else(|| ApiError::not_found("shot image"))?;
    let png = tokio::task::spawn_blocking(move || -> Result<Vec<u8>, ApiError> {
        let desired = image::load_from_memory(&jpeg)?.to_luma8();
        let img = compose_before_after(&desired, &a);
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Png)?;
        Ok(out.into_inner())
    })
    .await??;
    Ok((
        [
            (header::CONTENT_TYPE, "image/png".to_owned()),
            (header::CACHE_CONTROL, "no-cache".to_owned()),
            (
                header::CONTENT_DISPOSITION,
                format!("attachment; filename=\"{id}_before_after.png\""),
            ),
        ],
        png,
    )
        .into_response())
}
