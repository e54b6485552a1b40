//! What a localisation returns: the pose with its sigma, or why not.

use nalgebra::Isometry3;

use crate::slam::KeyFrameId;

/// A localised desired shot.
#[derive(Debug, Clone, PartialEq)]
pub struct ShotPose {
    /// The camera that takes the shot, map coordinates.
    pub world_from_cam: Isometry3<f64>,
    /// The candidate keyframe the pose was found through.
    pub keyframe_id: KeyFrameId,
    /// Inlier 2D-3D pairs after refinement.
    pub inliers: usize,
    /// 2D-3D pairs that went into the refinement.
    pub matches: usize,
    /// RMSE of the inliers' reprojection errors, pixels (undistorted).
    pub reprojection_rmse_px: f64,
    /// `inliers / matches`.
    pub inlier_ratio: f64,
    /// Fraction of the inliers in front of the camera.
    pub in_front_fraction: f64,
    /// Median depth of the inliers, map units.
    pub median_depth: f64,
    /// Other candidates that passed the gate and agree with this pose.
    pub agreeing_candidates: usize,
    /// How far beyond the flown views the shot sees its inliers: the
    /// median over them of the smallest angle at the point between the
    /// shot's ray and a keyframe's, degrees.
    pub beyond_views_deg: f64,
    /// The pose's uncertainty: the final optimisation's covariance (with
    /// the camera's uncertain intrinsics marginalised) and the map's own
    /// error ([`MapSigma`]) in quadrature.
    pub sigma: PoseSigma,
}

/// The uncertainty of a localised pose: the RMS of the errors the pose
/// covariance predicts (`√trace` of the camera centre's and of the
/// rotation's 3x3 covariance). For a Gaussian error about 61 % of the true
/// errors lie within one such sigma and 99 % within two.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PoseSigma {
    /// Camera centre, map units.
    pub position: f64,
    /// Camera centre as a fraction of the distance to the nearest scene
    /// content: the smaller of the 10 % quantiles of the inliers' depths
    /// and of the depths of all map points in the shot's view (a position
    /// error moves the near content most in the picture, and the matched
    /// points may all be far).
    pub position_depth_fraction: f64,
    /// Orientation, degrees.
    pub rotation_deg: f64,
}

/// Why a shot was not localised.
#[derive(Debug, Clone, PartialEq)]
pub enum NotLocalizedReason {
    /// The shot gave too few ORB features.
    TooFewFeatures {
        /// Features found.
        found: usize,
        /// Needed.
        needed: usize,
    },
    /// The map has no keyframe with map points.
    NoCandidate,
    /// No candidate keyframe has enough descriptor matches.
    TooFewMatches {
        /// Matches of the best candidate.
        found: usize,
        /// Needed.
        needed: usize,
    },
    /// PnP found no pose with enough inliers on any candidate.
    PnpFailed {
        /// Candidates tried.
        candidates: usize,
    },
    /// The best pose has too few inliers.
    TooFewInliers {
        /// Inliers of the best pose.
        found: usize,
        /// Needed.
        needed: usize,
    },
    /// The inliers' reprojection RMSE is too large.
    HighReprojectionError {
        /// RMSE, pixels.
        rmse_px: f64,
        /// Allowed maximum.
        max_px: f64,
    },
    /// Too small a fraction of the pairs are inliers.
    LowInlierRatio {
        /// The ratio.
        ratio: f64,
        /// Required minimum.
        min: f64,
    },
    /// Inliers lie behind the camera.
    PointsBehind {
        /// Fraction in front.
        in_front_fraction: f64,
        /// Required minimum.
        min: f64,
    },
    /// The pose's sigma exceeds the configured bounds.
    Uncertain {
        /// Position sigma as a fraction of the distance to the scene.
        position_depth_fraction: f64,
        /// Its bound.
        max_position_depth_fraction: f64,
        /// Rotation sigma, degrees.
        rotation_deg: f64,
        /// Its bound.
        max_rotation_deg: f64,
        /// How far beyond the flown views the shot sees the mapped scene
        /// ([`ShotPose::beyond_views_deg`]), degrees.
        beyond_views_deg: f64,
    },
    /// The pose's covariance could not be computed (singular).
    NoCovariance,
    /// An anchors shot drawn on a keyframe the map no longer has.
    UnknownKeyframe {
        /// The keyframe.
        keyframe: KeyFrameId,
    },
    /// An anchors shot whose drawn frame holds too few of the keyframe's
    /// mapped points to place the camera.
    AnchorsFewPoints {
        /// The keyframe drawn on.
        keyframe: KeyFrameId,
        /// Its mapped points inside the drawn frame.
        found: usize,
        /// Needed.
        needed: usize,
        /// Its mapped points in all.
        mapped: usize,
    },
    /// The place found is farther from the photo's position prior (its
    /// GPS tag through the georeference) than the two can both be right
    /// about: a look-alike of another place, or a wrong tag.
    FarFromPrior {
        /// Distance between the camera found and the prior, map units.
        distance: f64,
        /// That distance over the combined sigma (the prior's and the
        /// pose's, per axis, in quadrature).
        sigmas: f64,
        /// The bound, in sigmas.
        max_sigmas: f64,
        /// The prior's sigma, map units.
        prior_sigma: f64,
        /// Metres per map unit, when known.
        metres_per_unit: Option<f64>,
    },
    /// Two candidates pass the gate with different poses.
    CandidatesDisagree {
        /// The other keyframe.
        other: KeyFrameId,
        /// Distance between the positions, as a fraction of the median depth.
        position_depth_fraction: f64,
        /// Angle between the orientations, degrees.
        angle_deg: f64,
    },
}

impl std::fmt::Display for NotLocalizedReason {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        use NotLocalizedReason::*;
        match self {
            TooFewFeatures { found, needed } => write!(f, "too few features ({found} < {needed})"),
            NoCandidate => write!(f, "no candidate keyframe"),
            TooFewMatches { found, needed } => write!(f, "too few matches ({found} < {needed})"),
            PnpFailed { candidates } => write!(f, "PnP failed on all {candidates} candidates"),
            TooFewInliers { found, needed } => write!(f, "too few inliers ({found} < {needed})"),
            HighReprojectionError { rmse_px, max_px } => {
                write!(f, "reprojection RMSE {rmse_px:.2} px > {max_px:.2} px")
            }
            LowInlierRatio { ratio, min } => write!(f, "inlier ratio {ratio:.2} < {min:.2}"),
            PointsBehind {
                in_front_fraction,
                min,
            } => {
                write!(
                    f,
                    "only {in_front_fraction:.3} of the inliers in front (< {min:.3})"
                )
            }
            Uncertain {
                position_depth_fraction,
                max_position_depth_fraction,
                rotation_deg,
                max_rotation_deg,
                beyond_views_deg,
            } => write!(
                f,
                "too uncertain: position sigma {:.2} % of the distance (max {:.2} %), rotation sigma {rotation_deg:.2} deg (max {max_rotation_deg:.2}); \
                 the photo sees the mapped scene {beyond_views_deg:.0} deg beyond the flown views: a photo from nearer the flown path, \
                 a flight round to where it was taken (to map the scene from there), or the camera's intrinsics would help",
                position_depth_fraction * 100.0,
                max_position_depth_fraction * 100.0
            ),
            NoCovariance => write!(f, "the pose's covariance is singular"),
            UnknownKeyframe { keyframe } => write!(
                f,
                "keyframe {} is no longer in the map: draw the shot on another keyframe",
                keyframe.0
            ),
            AnchorsFewPoints {
                keyframe,
                found,
                needed,
                mapped,
            } => write!(
                f,
                "the drawn frame holds {found} of keyframe {}'s {mapped} mapped points ({needed} needed): \
                 draw it over more of the mapped scene, or on a keyframe with more mapped points",
                keyframe.0
            ),
            FarFromPrior {
                distance,
                sigmas,
                max_sigmas,
                prior_sigma,
                metres_per_unit,
            } => {
                let (d, s, unit) = match metres_per_unit {
                    Some(m) => (distance * m, prior_sigma * m, " m"),
                    None => (*distance, *prior_sigma, " map units"),
                };
                write!(
                    f,
                    "the place found is {d:.1}{unit} from where the photo's position tag puts it \
                     ({sigmas:.1} sigma, at most {max_sigmas:.1}; the tag's sigma {s:.1}{unit}): a look-alike \
                     of another place, or a wrong tag; a photo with a correct tag, or from nearer the flown path, would help"
                )
            }
            CandidatesDisagree {
                other,
                position_depth_fraction,
                angle_deg,
            } => write!(
                f,
                "candidate keyframe {} disagrees by {:.3} x median depth and {angle_deg:.2} deg",
                other.0, position_depth_fraction
            ),
        }
    }
}

/// The outcome of [`localize`].
#[derive(Debug, Clone, PartialEq)]
pub enum Localization {
    /// The shot's camera pose, through the gate.
    Localized(ShotPose),
    /// Not localised, and why.
    NotLocalized {
        /// Why.
        reason: NotLocalizedReason,
    },
}

pub(super) fn not(reason: NotLocalizedReason) -> Localization {
    Localization::NotLocalized { reason }
}
