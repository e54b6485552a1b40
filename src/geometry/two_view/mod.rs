//! Two-view initialisation of a monocular map, after ORB-SLAM's
//! `Initializer` (Mur-Artal, Montiel & Tardós, T-RO 2015, §IV):
//!
//! 1. In seeded RANSAC over shared 8-point sets, fit a homography (normalised
//!    DLT) and a fundamental matrix (normalised 8-point, rank 2 enforced).
//!    Each model is scored by symmetric transfer: for every match and both
//!    directions the squared error `e²/σ²` is compared with a chi-square
//!    threshold (`5.991` = 95 % with two degrees of freedom for the
//!    point-to-point H error, `3.841` = 95 % with one for the point-to-line
//!    F error); inliers add `5.991 - e²/σ²` to the score, outliers nothing.
//!    Each winner is then refitted by least squares on its consensus set
//!    (kept when the score rises; ORB-SLAM omits this, and with pixel-level
//!    noise the minimal fits are visibly off).
//! 2. Model choice by ORB-SLAM's heuristic `R_H = S_H / (S_H + S_F)`: the
//!    homography is chosen when `R_H > 0.40` (planar scenes or low parallax),
//!    the fundamental matrix otherwise.
//! 3. The chosen model is decomposed into motion hypotheses: H by Faugeras &
//!    Lustman's method (8 hypotheses), F through `E = Kᵀ·F·K` (4 hypotheses).
//! 4. Each hypothesis triangulates the inliers (linear DLT) and keeps the
//!    points that are finite, in front of both cameras (checked when the
//!    parallax is measurable), and reproject within `2σ` in both images.
//!    A hypothesis must clearly beat the others (F: no other with more than
//!    70 % of its good points; H: the second best below 75 %), reconstruct
//!    90 % of the inliers, at least `min_triangulated` points, and reach
//!    `min_parallax_deg` (ORB-SLAM's 50th-largest parallax). A hypothesis
//!    that passes all but the 90 % rule is bundle-adjusted and checked
//!    again (the minimal-fit motion is slightly off at pixel-level noise).
//!    When F is refused, the homography is tried under its own checks
//!    (`homography_fallback`: noise in both images lowers `S_H` on planes).
//!    Otherwise the initialisation is refused with a typed
//!    [`GeometryError`] carrying the counts (F's, when both fail).
//! 5. The accepted reconstruction is refined by a two-view bundle
//!    adjustment (camera 1 fixed, Huber kernel, `refine_iterations`), as
//!    ORB-SLAM does with its global BA right after initialising.
//!
//! The translation of the result has unit norm (monocular scale is free);
//! callers rescale, e.g. to unit median depth.
//!
//! The parts, one file each: `linear.rs` (the normalisation and the 9×9
//! null vector both DLT fits share), `homography.rs` (H: its fit, its
//! score, its Faugeras decomposition, and [`find_homography`]),
//! `fundamental.rs` (F: its fit and score; E's decomposition),
//! `initialize.rs` ([`initialize_two_view`]: the RANSAC, the refits and the
//! model choice), `reconstruct.rs` (the motion hypotheses triangulated and
//! checked, the best chosen or the initialisation refused) and `refine.rs`
//! (the two-view bundle adjustment of the result).
//!
//! [`GeometryError`]: super::GeometryError

mod fundamental;
mod homography;
mod initialize;
mod linear;
mod reconstruct;
mod refine;

use nalgebra::{Isometry3, Point3};

pub use homography::{HomographyFit, HomographyParams, decompose_h, find_homography};
pub use initialize::initialize_two_view;
pub use reconstruct::ranked_parallax_deg;

/// Tunables of [`initialize_two_view`]. Defaults are ORB-SLAM's.
#[derive(Debug, Clone, PartialEq)]
pub struct TwoViewParams {
    /// RANSAC iterations (8-point sets shared by H and F).
    pub ransac_iterations: usize,
    /// Keypoint position noise, pixels (the level-0 sigma).
    pub sigma_px: f64,
    /// Chi-square threshold for the point-to-line F error (1 DoF, 95 %).
    pub chi2_one_dof: f64,
    /// Chi-square threshold for point-to-point errors and the score ceiling
    /// (2 DoF, 95 %).
    pub chi2_two_dof: f64,
    /// The homography is chosen when `S_H/(S_H+S_F)` exceeds this
    /// (ORB-SLAM's 0.40). The ratio depends on the real keypoint noise
    /// against `sigma_px`: on synthetic planar scenes with 0.5 px noise in
    /// both images it is 0.47-0.48, with 1 px it drops to 0.39-0.48, so
    /// noisy planar pairs can fall to F (and are then usually refused).
    pub homography_ratio_threshold: f64,
    /// Minimum parallax of the reconstruction, degrees.
    pub min_parallax_deg: f64,
    /// Rank of the parallax used for the check (ORB-SLAM uses the 50th).
    pub parallax_rank: usize,
    /// Minimum number of well-triangulated points.
    pub min_triangulated: usize,
    /// Fraction of the model's inliers the best hypothesis must triangulate.
    pub min_good_fraction: f64,
    /// F: any other hypothesis above this fraction of the best's good points
    /// makes the reconstruction ambiguous.
    pub f_similar_fraction: f64,
    /// H: the second-best hypothesis must stay below this fraction.
    pub h_second_fraction: f64,
    /// Cosine of the parallax below which a point counts as "with parallax"
    /// (0.99998 ≈ 0.36 degree).
    pub cos_parallax_with_depth: f64,
    /// Squared reprojection error bound (in σ² units) for a good point.
    pub reprojection_chi2: f64,
    /// Least-squares refits of H and F on their consensus sets after RANSAC.
    pub refit_rounds: usize,
    /// LM iterations of the two-view bundle adjustment of the result
    /// (0: none).
    pub refine_iterations: usize,
    /// When the ratio picks F and F's reconstruction is refused, try the
    /// homography's (under all its own checks) before giving up; the error
    /// returned when both fail is F's. Noise in both images lowers `S_H`
    /// on planes, so a planar pair can fall just below the ratio threshold.
    pub homography_fallback: bool,
}

impl Default for TwoViewParams {
    fn default() -> Self {
        Self {
            ransac_iterations: 200,
            sigma_px: 1.0,
            chi2_one_dof: 3.841,
            chi2_two_dof: 5.991,
            homography_ratio_threshold: 0.40,
            min_parallax_deg: 1.0,
            parallax_rank: 50,
            min_triangulated: 50,
            min_good_fraction: 0.9,
            f_similar_fraction: 0.7,
            h_second_fraction: 0.75,
            cos_parallax_with_depth: 0.99998,
            reprojection_chi2: 4.0,
            refit_rounds: 2,
            refine_iterations: 20,
            homography_fallback: true,
        }
    }
}

/// Which model explained the two views.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    /// A homography (planar scene or low parallax).
    Homography,
    /// A fundamental matrix (general scene).
    Fundamental,
}

/// A successful two-view initialisation.
#[derive(Debug, Clone)]
pub struct TwoViewResult {
    /// Motion of camera 2 relative to camera 1 (`p_cam2 = T·p_cam1`),
    /// translation of unit norm.
    pub cam2_from_cam1: Isometry3<f64>,
    /// Per match: the triangulated point in camera-1 coordinates when it is
    /// an inlier that passed every check with enough parallax.
    pub points: Vec<Option<Point3<f64>>>,
    /// The model that won the selection.
    pub model: Model,
    /// Per match: inlier of the chosen model.
    pub inliers: Vec<bool>,
    /// Homography RANSAC score `S_H`.
    pub score_h: f64,
    /// Fundamental RANSAC score `S_F`.
    pub score_f: f64,
    /// Parallax of the reconstruction, degrees.
    pub parallax_deg: f64,
    /// Good points of the best hypothesis (including low-parallax ones).
    pub n_good: usize,
    /// Good points of the second-best hypothesis.
    pub n_second: usize,
}
