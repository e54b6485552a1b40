//! The desired shot's intake: `POST /shots` (anchors on a keyframe, its
//! body parsed by [`parse_shot_request`]) and `POST /shots/photo` (an
//! uploaded photograph, its EXIF's orientation, intrinsics and GPS tag,
//! with [`PhotoQuery`]'s intrinsics), each computed off the runtime and
//! stored as a shot.

use axum::Json;
use axum::body::Bytes;
use axum::extract::rejection::BytesRejection;
use axum::extract::{Query, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use serde_json::Value;

use super::error::body_rejection;
use super::{ApiError, AppState, ShotEvent, encode_jpeg};
use crate::shot::record::{PhotoIntrinsics, Shot, ShotSource, ShotStatus};
use crate::shot::request::{self as shots, ShotRequestError};
use crate::video::live::unix_now;

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
        .map_err(|e| ApiError::bad_request("bad_json", e.to_string()))?;
    let anchors: [[f64; 2]; 4] =
        req.anchors
            .as_slice()
            .try_into()
            .map_err(|_| ApiError::BadRequest {
                code: "bad_anchors",
                message: format!("exactly 4 anchors are needed, got {}", req.anchors.len()),
                detail: Some(serde_json::Map::from_iter([(
                    "reason".to_owned(),
                    Value::from("count"),
                )])),
            })?;
    let size = match (req.width, req.height) {
        (Some(w), Some(h)) => Some((w, h)),
        (None, None) => None,
        _ => {
            return Err(ApiError::bad_request(
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
        Some(img) => Some(tokio::task::spawn_blocking(move || encode_jpeg(&img, q)).await??),
        None => None,
    };
    let _guard = st.actions.lock().await;
    let nearest_keyframes = comp.nearest_keyframes;
    let (status, localisation, reason) = match comp.localisation {
        Ok(l) => (ShotStatus::Localised, Some(l), None),
        Err(r) => (ShotStatus::NotLocalised, None, Some(r.to_string())),
    };
    let shot = Shot {
        id: st.store.next_id(),
        created_unix: unix_now(),
        source,
        status,
        localisation,
        reason,
        has_image: jpeg.is_some(),
        mission: None,
        nearest_keyframes,
    };
    let store = st.store.clone();
    let saved = shot.clone();
    tokio::task::spawn_blocking(move || store.put(saved, jpeg.as_deref())).await??;
    tracing::info!(id = %shot.id, status = status.as_str(), "shot created");
    st.events.publish(
        &shot.id,
        match (&shot.localisation, &shot.reason) {
            (Some(l), _) => ShotEvent::Localised {
                inliers: l.inliers,
                rms_error_px: l.rms_error_px,
                position_sigma_pct: l.sigma.map(|s| s.position_fraction_of_distance * 100.0),
                rotation_sigma_deg: l.sigma.map(|s| s.rotation_deg),
            },
            (None, r) => ShotEvent::NotLocalised {
                reason: r.clone().unwrap_or_default(),
            },
        },
    );
    Ok((StatusCode::CREATED, Json(shot)).into_response())
}

pub(super) async fn create_shot(
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
        return Err(ApiError::UnsupportedMediaType(format!(
            "expected application/json, got {ct}"
        )));
    }
    let (kf, anchors, size) = parse_shot_request(&body)?;
    let computer = st.shots.clone();
    let comp = tokio::task::spawn_blocking(move || computer.shot_from_anchors(kf, &anchors, size))
        .await??;
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
    pub fn intrinsics(&self) -> Result<Option<PhotoIntrinsics>, ApiError> {
        let bad = |m: &str| ApiError::bad_request("bad_intrinsics", m);
        let d = [self.k1, self.k2, self.p1, self.p2, self.k3];
        match (self.fx, self.fy, self.cx, self.cy) {
            (Some(fx), Some(fy), Some(cx), Some(cy)) => {
                let z = |v: Option<f64>| v.unwrap_or(0.0);
                Ok(Some(PhotoIntrinsics {
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
                    focal_rel_sigma: 0.0,
                    k1_sigma: 0.0,
                    k2_sigma: 0.0,
                }))
            }
            (None, None, None, None) if d.iter().all(Option::is_none) => Ok(None),
            (None, None, None, None) => Err(bad("distortion without fx, fy, cx, cy")),
            _ => Err(bad("give all of fx, fy, cx, cy, or none")),
        }
    }
}

pub(super) async fn create_shot_from_photo(
    State(st): State<AppState>,
    headers: HeaderMap,
    query: Result<Query<PhotoQuery>, axum::extract::rejection::QueryRejection>,
    body: Result<Bytes, BytesRejection>,
) -> Result<Response, ApiError> {
    let body = body.map_err(|r| body_rejection(r, st.params.body_limit))?;
    let intrinsics = query
        .map_err(|e| ApiError::bad_request("bad_intrinsics", e.body_text()))?
        .0
        .intrinsics()?;
    let ct = headers
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .unwrap_or("");
    if !(ct.starts_with("image/jpeg") || ct.starts_with("image/png")) {
        return Err(ApiError::UnsupportedMediaType(format!(
            "expected image/jpeg or image/png, got {ct:?}"
        )));
    }
    let bytes = body.len();
    let computer = st.shots.clone();
    let (comp, w, h, intrinsics) = tokio::task::spawn_blocking(move || {
        // A JPEG cut short decodes to a picture grey below the cut: refused.
        if body.starts_with(&[0xFF, 0xD8])
            && let Some(reason) = shots::jpeg_truncation(&body)
        {
            return Err(ShotRequestError::BadImage { reason });
        }
        // Turned upright by its EXIF orientation; its EXIF focal length
        // stands in for intrinsics the operator did not give.
        let photo = crate::shot::photo::decode_photo(&body).map_err(|e| match e {
            crate::shot::ShotError::BadPhoto { reason } => ShotRequestError::BadImage { reason },
            e => ShotRequestError::BadImage {
                reason: e.to_string(),
            },
        })?;
        let grey = photo.image;
        let gps = photo.exif.as_ref().and_then(|e| e.gps);
        let (w, h) = grey.dimensions();
        let intrinsics = intrinsics.or_else(|| {
            let c = crate::shot::photo::exif_camera(photo.exif.as_ref()?, w, h)?;
            Some(PhotoIntrinsics {
                fx: c.camera.fx,
                fy: c.camera.fy,
                cx: c.camera.cx,
                cy: c.camera.cy,
                distortion: c.camera.distortion,
                focal_rel_sigma: c.uncertainty.focal_rel,
                k1_sigma: c.uncertainty.k1,
                k2_sigma: c.uncertainty.k2,
            })
        });
        computer
            .shot_from_photo(&grey, intrinsics.as_ref(), gps.as_ref())
            .map(|c| (c, w, h, intrinsics))
    })
    .await??;
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
