//! The desired shot: from four anchors (or a photo) to the camera pose that
//! takes it.
//!
//! * [`anchors`]: the operator places four anchors on a keyframe, where the
//!   frame's corners should go; the perspective transform from the corners
//!   to the anchors warps the keyframe into the desired shot (with a mask of
//!   the pixels that had a source).
//! * [`localize`]: the desired shot's ORB features are matched against the
//!   map (candidate keyframes, their map points, then by projection of the
//!   covisible keyframes' points), PnP RANSAC + motion-only refinement gives
//!   `world_from_cam`, and a reliability gate refuses doubtful answers with a
//!   typed reason.
//! * [`reconcile`]: each shot's mission state from the mission the vehicle
//!   holds (read back at start and whenever the link returns).

pub mod anchors;
pub mod localize;
pub mod photo;
pub mod reconcile;
pub mod record;
pub mod request;
pub mod store;

pub use anchors::{
    AnchorParams, DesiredShot, desired_shot_from_anchors, homography_from_anchors, warp_perspective,
};
pub use localize::{
    AnchorPoseParams, BowIndex, GateParams, Localization, LocalizeParams, MapSigma, NearKeyframe,
    NotLocalizedReason, PoseSigma, PositionPrior, ShotPose, UnknownFocal, assumed_camera, localize,
    localize_anchors, localize_with_camera, nearest_keyframes,
};
pub use photo::{
    IntrinsicsSource, Photo, PhotoCamera, PhotoExif, decode_photo, exif_camera, photo_camera,
};

use nalgebra::Point2;

/// Every tunable number of the desired-shot module.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Params {
    /// Anchor checks.
    pub anchors: AnchorParams,
    /// Localisation and its reliability gate.
    pub localize: LocalizeParams,
}

/// Errors of the desired-shot module (refusals of the operator's input).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShotError {
    /// An anchor coordinate is NaN or infinite.
    #[error("anchor {index} is not a finite point")]
    NonFiniteAnchor {
        /// Which anchor (0..4: top-left, top-right, bottom-right, bottom-left).
        index: usize,
    },
    /// An anchor lies too far outside the image.
    #[error("anchor {index} at ({x:.1}, {y:.1}) is more than {limit_px:.0} px outside the image")]
    AnchorOutOfBounds {
        /// Which anchor.
        index: usize,
        /// Its column.
        x: f64,
        /// Its row.
        y: f64,
        /// The allowed distance beyond the border, pixels (the larger of the two axes).
        limit_px: f64,
    },
    /// Two opposite edges of the quadrilateral cross (a bow tie): the
    /// anchors are not in the order of the frame's corners.
    #[error(
        "anchors cross: the edge from anchor {a} to anchor {b} crosses the edge from anchor {c} to anchor {d}; \
         place them in order top-left, top-right, bottom-right, bottom-left"
    )]
    Crossed {
        /// First edge's start anchor.
        a: usize,
        /// First edge's end anchor.
        b: usize,
        /// Second edge's start anchor.
        c: usize,
        /// Second edge's end anchor.
        d: usize,
    },
    /// The quadrilateral's area is below the minimum.
    #[error(
        "anchor quadrilateral collapsed: area {area_px2:.1} px² < minimum {min_area_px2:.1} px²"
    )]
    Collapsed {
        /// Its (unsigned) area, pixels².
        area_px2: f64,
        /// The minimum area, pixels².
        min_area_px2: f64,
    },
    /// The anchors wind the other way round from the frame's corners (a mirrored shot).
    #[error("anchors are mirrored: they wind the opposite way from the frame's corners")]
    MirroredWinding,
    /// The quadrilateral is not convex (or self-intersecting).
    #[error("anchor quadrilateral is not convex at anchor {vertex}")]
    NotConvex {
        /// The anchor at which the turn goes the wrong way.
        vertex: usize,
    },
    /// The perspective transform is singular or too badly conditioned.
    #[error(
        "perspective transform is near-singular (condition {condition:.3e}, max {max_condition:.3e})"
    )]
    NearSingular {
        /// Ratio of the largest to the smallest singular value of the
        /// transform in image-size units (infinite when it could not be solved).
        condition: f64,
        /// The allowed maximum.
        max_condition: f64,
    },
    /// The keyframe image is empty or its size differs from the camera's.
    #[error("image of {width}x{height} does not fit (expected {expected_width}x{expected_height})")]
    ImageSize {
        /// Width of the given image.
        width: u32,
        /// Height of the given image.
        height: u32,
        /// Expected width.
        expected_width: u32,
        /// Expected height.
        expected_height: u32,
    },
    /// The keyframe has no image to warp.
    #[error("keyframe {id} has no image")]
    NoImage {
        /// The keyframe id.
        id: u32,
    },
    /// The keyframe does not exist in the map.
    #[error("keyframe {id} is not in the map")]
    UnknownKeyFrame {
        /// The keyframe id.
        id: u32,
    },
    /// The feature extractor refused the image or the settings.
    #[error("feature extraction: {message}")]
    Features {
        /// The extractor's message.
        message: String,
    },
    /// A photo that is not a readable image.
    #[error("bad photo: {reason}")]
    BadPhoto {
        /// Why.
        reason: String,
    },
    /// Invalid parameters.
    #[error("invalid parameter {name}: {reason}")]
    InvalidParams {
        /// Which parameter.
        name: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
}

/// The frame's four corners in anchor order: (0,0), (w-1,0), (w-1,h-1), (0,h-1).
pub fn frame_corners(width: u32, height: u32) -> [Point2<f64>; 4] {
    let (w, h) = (width as f64 - 1.0, height as f64 - 1.0);
    [
        Point2::new(0.0, 0.0),
        Point2::new(w, 0.0),
        Point2::new(w, h),
        Point2::new(0.0, h),
    ]
}
