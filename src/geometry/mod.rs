//! Multiple-view geometry: two-view initialisation (fundamental matrix,
//! homography, their decompositions), triangulation, PnP (Lambda Twist P3P
//! and EPnP inside RANSAC, then robust refinement with [`crate::optimize`]),
//! the homography from exactly four point pairs, Umeyama alignment, and
//! the Sim(3) between two keyframes by RANSAC over three-point Umeyama
//! samples (loop closing).
//! SE(3)/Sim(3) live below both this module and `optimize`, in
//! [`crate::lie`]; [`Sim3`] is re-exported here for callers that align
//! with [`umeyama()`].
//!
//! Conventions (see `ARCHITECTURE.md`): camera axes x right, y down,
//! z forward; poses are named for what they map (`cam_from_world`).
//! "Normalised coordinates" are `K⁻¹·(u, v, 1)` restricted to `(x/z, y/z)`;
//! "pixels" are always undistorted pixels.

pub mod homography4;
pub mod pnp;
pub mod sim3_ransac;
pub mod triangulate;
pub mod two_view;
pub mod umeyama;

pub use crate::lie::Sim3;
pub use homography4::homography_from_4;
pub use pnp::{PnpParams, PnpResult, solve_pnp_ransac};
pub use sim3_ransac::{Sim3RansacParams, Sim3RansacResult, sim3_ransac};
pub use triangulate::{TriangulationChecks, TriangulationReject, triangulate, triangulate_checked};
pub use two_view::{
    HomographyFit, HomographyParams, Model, TwoViewParams, TwoViewResult, find_homography,
    initialize_two_view,
};
pub use umeyama::umeyama;

/// Every tunable number of the geometry module, grouped by algorithm.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Params {
    /// Two-view initialisation (F/H RANSAC, model selection, reconstruction).
    pub two_view: TwoViewParams,
    /// PnP RANSAC and refinement.
    pub pnp: PnpParams,
    /// Checks on newly triangulated map points.
    pub triangulation: TriangulationChecks,
}

/// Errors of the geometry module. Counts are carried so callers can log and
/// decide (for instance: try initialising again with the next frame).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeometryError {
    /// Fewer inputs than the algorithm needs.
    #[error("not enough points: found {found}, needed {needed}")]
    NotEnoughPoints {
        /// Points (or matches) given.
        found: usize,
        /// Minimum the algorithm needs.
        needed: usize,
    },
    /// Two input slices that must pair up have different lengths.
    #[error("length mismatch: {left} vs {right}")]
    LengthMismatch {
        /// Length of the first slice.
        left: usize,
        /// Length of the second slice.
        right: usize,
    },
    /// A match refers to a keypoint that does not exist.
    #[error("index {index} out of range (len {len})")]
    IndexOutOfRange {
        /// The offending index.
        index: usize,
        /// Length of the slice it indexes.
        len: usize,
    },
    /// An input value is NaN or infinite.
    #[error("non-finite input")]
    NonFinite,
    /// RANSAC found too few inliers for any model.
    #[error("too few inliers: found {found}, needed {needed}")]
    TooFewInliers {
        /// Inliers of the best model.
        found: usize,
        /// Minimum required.
        needed: usize,
    },
    /// Two motion hypotheses explain the data about equally well.
    #[error("ambiguous reconstruction: best hypothesis has {best} good points, second {second}")]
    Ambiguous {
        /// Good triangulated points of the best hypothesis.
        best: usize,
        /// Good triangulated points of the runner-up.
        second: usize,
    },
    /// The best hypothesis triangulates too few points.
    #[error("too few triangulated points: found {found}, needed {needed}")]
    TooFewTriangulated {
        /// Good points of the best hypothesis.
        found: usize,
        /// Minimum required.
        needed: usize,
    },
    /// The baseline is too short (or zero: pure rotation) for the parallax
    /// to constrain depth.
    #[error("not enough parallax: {parallax_deg:.3} deg, needed {needed_deg:.3} deg")]
    NotEnoughParallax {
        /// Parallax of the best hypothesis (degrees, ORB-SLAM's 50th-largest).
        parallax_deg: f64,
        /// Minimum required (degrees).
        needed_deg: f64,
    },
    /// Three of the four points of a homography are (nearly) collinear.
    #[error("points {i}, {j}, {k} of the {side} set are collinear")]
    Collinear {
        /// `"source"` or `"destination"`.
        side: &'static str,
        /// First point index.
        i: usize,
        /// Second point index.
        j: usize,
        /// Third point index.
        k: usize,
    },
    /// The point set spans (almost) no area or volume.
    #[error("the {side} point set is collapsed (spread {spread:e})")]
    Collapsed {
        /// `"source"` or `"destination"`.
        side: &'static str,
        /// The measured spread.
        spread: f64,
    },
    /// A linear system or decomposition had no usable solution.
    #[error("degenerate configuration: {what}")]
    Degenerate {
        /// What failed.
        what: &'static str,
    },
}

/// Checks that every coordinate of the points is finite.
pub(crate) fn all_finite2(pts: &[nalgebra::Point2<f64>]) -> bool {
    pts.iter().all(|p| p.x.is_finite() && p.y.is_finite())
}

/// Checks that every coordinate of the points is finite.
pub(crate) fn all_finite3(pts: &[nalgebra::Point3<f64>]) -> bool {
    pts.iter()
        .all(|p| p.x.is_finite() && p.y.is_finite() && p.z.is_finite())
}
