//! The API's one error type: every way a request fails, with its status,
//! machine code and message, written by one [`IntoResponse`].

use axum::Json;
use axum::extract::rejection::BytesRejection;
use axum::http::{HeaderValue, StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Serialize;
use serde_json::Value;

use super::views::VehicleError;
use crate::shot::request::ShotRequestError;
use crate::shot::store::StoreError;

/// Every way a request fails. Each case has its HTTP status and machine
/// code ([`ApiError::status`], [`ApiError::code`]); the one
/// [`IntoResponse`] writes them all as `{"error": {"code", "message",
/// ...details}}`. Errors of the parts below (shot requests, the vehicle,
/// the shot store, blocking tasks, JPEG encoding) convert with `?`.
#[derive(Debug, thiserror::Error)]
pub enum ApiError {
    /// 404 `not_found`: no such endpoint, shot, keyframe or image.
    #[error("{what} not found")]
    NotFound {
        /// What was asked for.
        what: &'static str,
    },
    /// 400: the request is malformed (`code` says how).
    #[error("{message}")]
    BadRequest {
        /// `bad_json`, `bad_anchors`, `bad_size`, `bad_id`, `bad_intrinsics`.
        code: &'static str,
        /// What is wrong.
        message: String,
        /// Machine-readable details merged into the error object (e.g.
        /// which anchor check refused: `{"reason": "count"}`).
        detail: Option<serde_json::Map<String, Value>>,
    },
    /// 409: the request does not fit the shot's state.
    #[error("{message}")]
    Conflict {
        /// `not_localised`, `no_mission`.
        code: &'static str,
        /// Why.
        message: String,
    },
    /// 401 `unauthorized`: no or a wrong bearer token.
    #[error("{0}")]
    Unauthorized(&'static str),
    /// 415 `bad_content_type`.
    #[error("{0}")]
    UnsupportedMediaType(String),
    /// 503 `no_video`: no frame received yet.
    #[error("no frame received yet")]
    NoVideo,
    /// 413 `body_too_large`: the body is over `[server] body_limit_bytes`.
    #[error(
        "the request body is larger than the limit of {limit} bytes ({:.1} MiB; [server] body_limit_bytes)",
        *limit as f64 / (1u64 << 20) as f64
    )]
    BodyTooLarge {
        /// The limit, bytes.
        limit: usize,
    },
    /// `bad_body` with axum's status: the body could not be read.
    #[error("{message}")]
    BadBody {
        /// axum's status for it.
        status: StatusCode,
        /// axum's message.
        message: String,
    },
    /// A shot request refused (400/404, see [`ShotRequestError`]).
    #[error(transparent)]
    Shot(#[from] ShotRequestError),
    /// A vehicle action failed (409/502/503, see [`VehicleError`]).
    #[error(transparent)]
    Vehicle(#[from] VehicleError),
    /// 500 `store`: the shot could not be written.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// 500 `internal`: a blocking task panicked or was cancelled.
    #[error(transparent)]
    Task(#[from] tokio::task::JoinError),
    /// 500 `encode`: a JPEG could not be encoded.
    #[error(transparent)]
    Encode(#[from] image::ImageError),
}

impl ApiError {
    /// A 400 with `code`.
    pub fn bad_request(code: &'static str, message: impl Into<String>) -> Self {
        Self::BadRequest {
            code,
            message: message.into(),
            detail: None,
        }
    }

    pub(super) fn not_found(what: &'static str) -> Self {
        Self::NotFound { what }
    }

    /// The HTTP status.
    pub fn status(&self) -> StatusCode {
        match self {
            Self::NotFound { .. } => StatusCode::NOT_FOUND,
            Self::BadRequest { .. } => StatusCode::BAD_REQUEST,
            Self::Conflict { .. } => StatusCode::CONFLICT,
            Self::Unauthorized(_) => StatusCode::UNAUTHORIZED,
            Self::UnsupportedMediaType(_) => StatusCode::UNSUPPORTED_MEDIA_TYPE,
            Self::NoVideo => StatusCode::SERVICE_UNAVAILABLE,
            Self::BodyTooLarge { .. } => StatusCode::PAYLOAD_TOO_LARGE,
            Self::BadBody { status, .. } => *status,
            Self::Shot(ShotRequestError::UnknownKeyframe { .. }) => StatusCode::NOT_FOUND,
            Self::Shot(_) => StatusCode::BAD_REQUEST,
            Self::Vehicle(v) => match v {
                VehicleError::NoVehicle { .. } => StatusCode::SERVICE_UNAVAILABLE,
                VehicleError::NoGeoreference { .. }
                | VehicleError::Conflict { .. }
                | VehicleError::NotOnVehicle { .. } => StatusCode::CONFLICT,
                VehicleError::Failed { .. } => StatusCode::BAD_GATEWAY,
            },
            Self::Store(_) | Self::Task(_) | Self::Encode(_) => StatusCode::INTERNAL_SERVER_ERROR,
        }
    }

    /// The machine-readable code.
    pub fn code(&self) -> &'static str {
        match self {
            Self::NotFound { .. } => "not_found",
            Self::BadRequest { code, .. } | Self::Conflict { code, .. } => code,
            Self::Unauthorized(_) => "unauthorized",
            Self::UnsupportedMediaType(_) => "bad_content_type",
            Self::NoVideo => "no_video",
            Self::BodyTooLarge { .. } => "body_too_large",
            Self::BadBody { .. } => "bad_body",
            Self::Shot(e) => match e {
                ShotRequestError::UnknownKeyframe { .. } => "unknown_keyframe",
                ShotRequestError::BadAnchors { .. } => "bad_anchors",
                ShotRequestError::BadImage { .. } => "bad_image",
                ShotRequestError::BadIntrinsics { .. } => "bad_intrinsics",
                ShotRequestError::IntrinsicsRequired { .. } => "intrinsics_required",
            },
            Self::Vehicle(v) => match v {
                VehicleError::NoVehicle { .. } => "no_vehicle",
                VehicleError::NoGeoreference { .. } => "no_georeference",
                VehicleError::Conflict { .. } => "conflict",
                VehicleError::NotOnVehicle { .. } => "not_on_vehicle",
                VehicleError::Failed { .. } => "vehicle_failed",
            },
            Self::Store(_) => "store",
            Self::Task(_) => "internal",
            Self::Encode(_) => "encode",
        }
    }

    /// Machine-readable details merged into the error object.
    fn detail(&self) -> serde_json::Map<String, Value> {
        let mut m = serde_json::Map::new();
        match self {
            Self::BadRequest {
                detail: Some(d), ..
            } => m.clone_from(d),
            Self::BodyTooLarge { limit } => {
                m.insert("limit_bytes".into(), (*limit).into());
            }
            Self::Shot(ShotRequestError::BadAnchors { source }) => m = anchor_refusal(source),
            _ => {}
        }
        m
    }
}

/// The body of every error reply: `{"error": {...}}`.
#[derive(Debug, Serialize)]
struct ErrorBody {
    error: ErrorObject,
}

/// An error: its stable code, a message for people, and the details the
/// error has (e.g. `limit_bytes`, an anchor refusal's `reason` and
/// `anchor`) beside them.
#[derive(Debug, Serialize)]
struct ErrorObject {
    code: &'static str,
    message: String,
    #[serde(flatten)]
    detail: serde_json::Map<String, Value>,
}

impl IntoResponse for ApiError {
    fn into_response(self) -> Response {
        let status = self.status();
        if status.is_server_error() {
            tracing::warn!(code = self.code(), "request failed: {self}");
        }
        let mut detail = self.detail();
        detail.remove("code");
        detail.remove("message");
        let body = ErrorBody {
            error: ErrorObject {
                code: self.code(),
                message: self.to_string(),
                detail,
            },
        };
        let mut r = (status, Json(body)).into_response();
        if status == StatusCode::UNAUTHORIZED {
            r.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        r
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

/// A request body that could not be read: 413 names the limit (and the
/// setting that raises it), anything else is a 400-class `bad_body`.
pub(super) fn body_rejection(r: BytesRejection, limit: usize) -> ApiError {
    let status = r.status();
    if status == StatusCode::PAYLOAD_TOO_LARGE {
        ApiError::BodyTooLarge { limit }
    } else {
        ApiError::BadBody {
            status,
            message: r.body_text(),
        }
    }
}
