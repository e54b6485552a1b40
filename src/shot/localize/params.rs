//! Every tunable number of the localisation: the gate, the matching, the
//! map's own error and the priors of an unknown camera.

use crate::features;
use crate::geometry::PnpParams;
use crate::optimize::{IntrinsicsUncertainty, PoseParams};
use crate::slam::matcher::MatcherParams;

/// Thresholds of the reliability gate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GateParams {
    /// Fewest inliers after refinement.
    pub min_inliers: usize,
    /// Largest RMSE of the inliers' reprojection errors, pixels.
    pub max_rmse_px: f64,
    /// Smallest fraction of the refined pairs that are inliers. 0.4: a
    /// photo 10-30 degrees round from the flown views gathers more false
    /// pairs in the search by projection while its inliers are right (real
    /// photos of teddy_100 at 0.42-0.49 were refused at 0.5, none wrong);
    /// the inlier count is the evidence of the place.
    pub min_inlier_ratio: f64,
    /// Smallest fraction of the inliers lying in front of the camera.
    pub min_in_front_fraction: f64,
    /// Largest distance between the positions of two gated candidates, as a
    /// fraction of the scene's median depth.
    pub max_disagreement_depth_fraction: f64,
    /// Largest angle between the orientations of two gated candidates, degrees.
    pub max_disagreement_deg: f64,
    /// A gated candidate that disagrees with the best but has fewer than
    /// this fraction of its inliers is dropped instead of refusing the
    /// shot: one outlying keyframe (an early keyframe a few degrees off
    /// its neighbours) does not veto a place the others agree on, while
    /// two places of comparable support stay ambiguous. 0: every
    /// disagreement refuses.
    pub drop_disagreeing_below: f64,
    /// Largest position sigma ([`PoseSigma::position_depth_fraction`]), as
    /// a fraction of the distance to the nearest scene content. 0.05: half
    /// the error at which a shot is wrong (10 % of the distance, 5
    /// degrees), so a pose within two sigma of the truth is never a wrong
    /// one; the refinement loop takes the rest from the live view.
    pub max_position_sigma_depth_fraction: f64,
    /// Largest rotation sigma ([`PoseSigma::rotation_deg`]), degrees (2.5:
    /// half of 5 degrees, as the position's).
    pub max_rotation_sigma_deg: f64,
    /// The largest distance, in sigmas (the prior's and the pose's per
    /// axis, in quadrature), between the camera found and the photo's
    /// position prior ([`LocalizeParams::position_prior`]). 4: a right
    /// place with a right tag is refused about once in 900 (the distance
    /// of a 3-D Gaussian error; once in 3000 for a horizontal prior), a
    /// look-alike 40 m away with a 5 m tag at 8 sigma.
    pub max_prior_sigmas: f64,
}

impl Default for GateParams {
    fn default() -> Self {
        GateParams {
            min_inliers: 30,
            max_rmse_px: 3.0,
            min_inlier_ratio: 0.4,
            min_in_front_fraction: 0.99,
            max_disagreement_depth_fraction: 0.05,
            max_disagreement_deg: 2.0,
            drop_disagreeing_below: 0.5,
            max_position_sigma_depth_fraction: 0.05,
            max_rotation_sigma_deg: 2.5,
            max_prior_sigmas: 4.0,
        }
    }
}

/// Every tunable number of the localisation.
#[derive(Debug, Clone, PartialEq)]
pub struct LocalizeParams {
    /// ORB settings for the shot (scale factor and levels are taken from the map).
    pub features: features::Params,
    /// Candidate keyframes kept (the most descriptor matches among those
    /// retrieved).
    pub top_k: usize,
    /// Keyframes a bag-of-words query retrieves and matches by descriptor
    /// before the best `top_k` are kept (at least `top_k`): a photo much
    /// closer or farther than the keyframes shares few words with the
    /// right ones (its fine detail is their coarse pyramid levels), so
    /// they often rank below the first few by BoW score while they still
    /// have the most matches.
    pub bow_candidates: usize,
    /// Largest Hamming distance of a descriptor match against a candidate.
    pub max_hamming: u32,
    /// Ratio test: best distance below `ratio` times the second best.
    pub ratio: f32,
    /// Fewest descriptor matches for a keyframe to be tried.
    pub min_candidate_matches: usize,
    /// Covisible keyframes of a candidate whose points (through every
    /// observation's descriptor) its PnP matches are drawn from again when
    /// its own matches give no pose the gate takes (0: the candidate's own
    /// points alone, still through every observation's descriptor); never
    /// for a photo whose camera is only assumed
    /// ([`LocalizeParams::focal_unknown`]).
    pub candidate_covisible: usize,
    /// Covisible keyframes of a candidate whose points are projected in the
    /// first projection round.
    pub covisible: usize,
    /// Largest number of keyframes whose points make the local map of the
    /// later rounds: the keyframes that observe the points matched so far,
    /// most shared points first (ORB-SLAM's local keyframes).
    pub local_keyframes: usize,
    /// Search windows (pixels at level 0) of the projection rounds.
    pub projection_radius_px: [f64; 2],
    /// Smallest cosine between the viewing ray and a point's mean viewing
    /// direction for it to be projected.
    pub min_view_cos: f64,
    /// Matcher settings for the search by projection.
    pub matcher: MatcherParams,
    /// PnP RANSAC settings.
    pub pnp: PnpParams,
    /// Motion-only bundle adjustment settings.
    pub pose: PoseParams,
    /// The reliability gate.
    pub gate: GateParams,
    /// How well the shot camera's intrinsics are known (zero: exactly, as
    /// the map camera's or the operator's; a photo's EXIF leaves the focal
    /// length and the distortion open: [`crate::shot::PhotoCamera`]).
    /// Widens the reported sigma, never changes the pose.
    pub camera_uncertainty: IntrinsicsUncertainty,
    /// The map's own error, which the pose covariance (map points held
    /// exact) does not see; added to it in quadrature.
    pub map_sigma: MapSigma,
    /// Merge the pairs of every agreeing candidate into one final pose
    /// optimisation (the union of evidence; not for an assumed camera,
    /// [`LocalizeParams::focal_unknown`]); off: the best candidate's pairs
    /// alone.
    pub union_of_evidence: bool,
    /// True when the shot camera is only assumed: a photo of another size
    /// than the map camera's, without EXIF or given intrinsics, taken with
    /// the map camera scaled ([`assumed_camera`]). Its focal length and
    /// distortion are then estimated too, and the two explanations weighed
    /// ([`UnknownFocal`]).
    pub focal_unknown: bool,
    /// The priors of that weighing.
    pub unknown_focal: UnknownFocal,
    /// For such a photo, and for one whose intrinsics are estimated with
    /// the pose (`camera_uncertainty`, an EXIF camera), projection rounds
    /// through the estimated camera after the first fit (the local map
    /// searched again with the estimated focal length and distortion, the
    /// camera estimated again on the grown pairs); 0: none.
    pub rematch_rounds: usize,
    /// Seed of the RANSAC.
    pub seed: u64,
    /// An anchors shot's pose from its keyframe's geometry.
    pub anchors: AnchorPoseParams,
    /// Where the photo was taken by an outside measurement, if known (its
    /// GPS tag through the georeference): a place found farther from it
    /// than [`GateParams::max_prior_sigmas`] is refused.
    pub position_prior: Option<PositionPrior>,
}

/// A photo's camera centre as an outside measurement gives it (the
/// photo's GPS tag through the georeference), in the map's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionPrior {
    /// The camera centre, map coordinates.
    pub centre: nalgebra::Point3<f64>,
    /// Its standard deviation per axis, map units.
    pub sigma: f64,
    /// When set, only the distance across this direction counts (the
    /// map's down: a horizontal prior, for a GPS tag whose altitude is
    /// not trusted); the bound is then on a 2-D error.
    pub down: Option<nalgebra::Unit<nalgebra::Vector3<f64>>>,
    /// Metres per map unit, when the map is georeferenced (for the
    /// refusal's words).
    pub metres_per_unit: Option<f64>,
}

impl PositionPrior {
    /// How far the camera centre `centre` lies from the prior: the distance
    /// (across [`PositionPrior::down`] when set) and that in sigmas, the
    /// prior's and `pose_sigma` (the pose's RMS position error, 3-D) per
    /// axis in quadrature.
    pub fn distance(&self, centre: &nalgebra::Point3<f64>, pose_sigma: f64) -> (f64, f64) {
        // The pose's sigma is the RMS of the centre's 3-D error: per axis
        // it is that over sqrt(3).
        let per_axis = self.sigma.hypot(pose_sigma / 3f64.sqrt());
        let off = centre - self.centre;
        let distance = match self.down {
            Some(d) => (off - d.into_inner() * d.dot(&off)).norm(),
            None => off.norm(),
        };
        (distance, distance / per_axis.max(1e-12))
    }
}

impl Default for LocalizeParams {
    fn default() -> Self {
        let features = features::Params {
            n_features: 1500,
            ..features::Params::default()
        };
        // 10 inliers for a candidate's first pose, as ORB-SLAM's
        // relocalisation: the gate's inlier count after the projection
        // rounds decides, and a photo 20 degrees round from the views
        // often has 10-11 right ones among its first matches.
        let pnp = PnpParams {
            min_inliers: 10,
            max_iterations: 2000,
            ..PnpParams::default()
        };
        LocalizeParams {
            features,
            top_k: 5,
            bow_candidates: 15,
            max_hamming: 50,
            ratio: 0.8,
            min_candidate_matches: 15,
            candidate_covisible: 5,
            covisible: 10,
            local_keyframes: 20,
            projection_radius_px: [5.0, 2.5],
            min_view_cos: 0.5,
            matcher: MatcherParams {
                th_high: 64,
                ..MatcherParams::default()
            },
            pnp,
            pose: PoseParams::default(),
            gate: GateParams::default(),
            camera_uncertainty: IntrinsicsUncertainty::default(),
            map_sigma: MapSigma::default(),
            union_of_evidence: true,
            focal_unknown: false,
            unknown_focal: UnknownFocal::default(),
            rematch_rounds: 1,
            seed: 1,
            anchors: AnchorPoseParams::default(),
            position_prior: None,
        }
    }
}

/// The map's own error as the localisation's sigma includes it, in two
/// parts. One grows with the photo's distance to what it sees (the local
/// map's orientation error, seen over that lever arm): the larger of
/// `depth_fraction` of the inliers' median depth and the spread of the
/// poses of the agreeing candidates (each refined on its own local map)
/// around the chosen one. The other does not: the map's points and
/// keyframes carry the position error they were mapped with, set by the
/// depth at which the flight saw the scene, and a photo taken closer
/// than the keyframes inherits all of it (`map_depth_fraction` of the
/// map's median keyframe depth). Both go into the position sigma in
/// quadrature with the pose covariance's, and into a focal length
/// estimated with the pose ([`MapSigma::focal_rel`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapSigma {
    /// Position, as a fraction of the median depth of the inliers.
    pub depth_fraction: f64,
    /// Rotation, degrees.
    pub rotation_deg: f64,
    /// The map's absolute position error, as a fraction of its keyframes'
    /// median depth (the median over the keyframes of each one's median
    /// scene depth).
    pub map_depth_fraction: f64,
    /// The reprojection noise (level-0 pixels,
    /// [`crate::slam::Map::reprojection_noise_px`]) of the maps the three
    /// constants above were calibrated on (0.306 px, the explore map of
    /// `tests/suite/shot_photos.rs`). A map whose own noise is larger has
    /// proportionally larger errors (a bundle adjustment's error scales
    /// with its measurements' noise), so the three, and the bounds of two
    /// candidates' agreement, are scaled by the ratio (never below 1;
    /// teddy_100's maps 0.52-0.56 px, KITTI 07's 0.32-0.34, the simulator's
    /// `field` explore map 0.34); infinite: not scaled. Real maps' errors
    /// are larger still than this explains (the README's known gaps).
    pub reference_noise_px: f64,
}

impl MapSigma {
    /// The map's error as a focal length estimated with the pose sees it
    /// (a photo known by its EXIF, or whose camera was only assumed), in
    /// the focal length's log, for a photo whose inliers lie at
    /// `median_depth` and a map whose absolute error is `absolute` (map
    /// units): a stretch of the local map across the view against along
    /// it reads as a focal length change, and the pose follows it along
    /// the optical axis. A stretch is the difference of two points' errors
    /// over a span of the order of the depth: √2 times the map's error
    /// over that depth (0.35 % for a photo as far as the keyframes were,
    /// more for a closer one). The residuals cannot show it (the focal
    /// length absorbs it), so the pose covariance gets it as a further
    /// independent error of the focal length
    /// ([`crate::optimize::PoseCovariance::with_focal_error`]).
    pub fn focal_rel(&self, absolute: f64, median_depth: f64) -> f64 {
        let relative = if median_depth > 0.0 && absolute.is_finite() {
            absolute / median_depth
        } else {
            0.0
        };
        std::f64::consts::SQRT_2 * self.depth_fraction.hypot(relative)
    }
}

impl Default for MapSigma {
    /// Calibrated on the simulator's explore map (`tests/suite/shot_photos.rs`,
    /// hidden poses of seeds 1 and 2; seed 3 held out). Photos of the map
    /// camera under the flight's light are off by 0.21 % of the distance
    /// and 0.14 degrees (medians) while their pose covariance alone says a
    /// few hundredths of that; for a 3-D Gaussian the median error is 0.89
    /// sigma. Their position errors shrink far less than their distance:
    /// 3 to 5 cm from 5 to 15 m away, 6 to 9 cm from 40 m and more, about
    /// 0.1 % of the map's median keyframe depth (40 m) for the part that
    /// does not shrink (without it 89 % to 91 % of the errors of seed 2
    /// were within 2 sigma, the misses all photos under 15 m away).
    fn default() -> Self {
        MapSigma {
            depth_fraction: 0.0025,
            rotation_deg: 0.16,
            map_depth_fraction: 0.001,
            reference_noise_px: 0.31,
        }
    }
}

/// A photo whose camera is only assumed ([`LocalizeParams::focal_unknown`])
/// has two explanations: H0, the map camera's frame resized (the assumed
/// camera exact), and H1, another camera (focal length and distortion
/// unknown, with these priors around the assumed ones). Both are fitted
/// with the pose; H0's posterior probability comes from its prior and the
/// Savage-Dickey density ratio (H1's posterior density of the intrinsics
/// at H0's values over its prior density there), and the reported sigma is
/// the second moment of the two hypotheses' mixture about the likelier
/// one's pose. When the data cannot tell the focal length (a far, shallow
/// scene) the mixture keeps H1's wide spread and the gate refuses; when
/// they pin it, the likelier camera wins and the pose is its.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UnknownFocal {
    /// Prior probability of H0 (the photo is a resized frame of the map
    /// camera).
    pub same_camera_prior: f64,
    /// H1's prior sigma of the focal length's log (0.35: a factor of 2 at
    /// 2 sigma, ultra-wide to short tele).
    pub focal_log_sigma: f64,
    /// H1's prior sigma of the radial distortion's `k1`.
    pub k1_sigma: f64,
    /// H1's prior sigma of `k2`.
    pub k2_sigma: f64,
}

impl Default for UnknownFocal {
    fn default() -> Self {
        UnknownFocal {
            same_camera_prior: 0.5,
            focal_log_sigma: 0.35,
            k1_sigma: EXIF_K1_SIGMA,
            k2_sigma: EXIF_K2_SIGMA,
        }
    }
}

/// The radial distortion an unknown lens may have, as a sigma of `k1`:
/// phone and drone cameras correct theirs in the camera to well within it.
pub const EXIF_K1_SIGMA: f64 = 0.05;
/// The same for the r⁴ coefficient `k2`.
pub const EXIF_K2_SIGMA: f64 = 0.02;

/// Tunables of an anchors shot's pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnchorPoseParams {
    /// Fewest of the keyframe's map points that must lie inside the drawn
    /// frame.
    pub min_points: usize,
}

impl Default for AnchorPoseParams {
    fn default() -> Self {
        AnchorPoseParams { min_points: 12 }
    }
}
