//! The shot refinement, closing the loop: fly to the shot, look, and
//! correct until the live view matches the desired shot. (Not the pose
//! refinement inside a localisation, `shot::localize::pose_refinement`;
//! the daemon's task that drives this loop is `daemon::refinement_task`.)
//!
//! * [`error`]: the shot error between a live frame and the desired shot
//!   (ORB matches, RANSAC homography, mean displacement of the four image
//!   corners, pixels and % of the diagonal) and the pose difference when
//!   both poses are known.
//! * [`arrival`]: when to look (waypoint reached, vehicle still, gimbal at
//!   its commanded pitch, for a dwell time); how far a reported position is
//!   from the target.
//! * [`measure`]: the live framing over several frames (robust average,
//!   outliers rejected, the spread as the measurement's noise).
//! * [`controller`]: the correction that moves the camera from the
//!   localised live pose to the desired pose through the georeference,
//!   checked like the first target; when to stop.
//! * [`reachable`]: the best framing a camera can reach for a desired shot
//!   made from anchors (a zoom is no camera's view), the shot error's floor.
//! * [`session`]: one shot's loop as a state machine (arrival → measure
//!   the live frames → decide → localise them → filtered offset → corrected
//!   target), whose rounds are the record the API shows. The offset is
//!   measured through the round's georeference; a refit between rounds
//!   carries the filtered estimate along by the change it makes at the
//!   desired pose, so a refit is never corrected as if the camera had moved.
//! * [`desired`]: the desired picture a session compares live frames with
//!   (an anchors shot warped again from its keyframe, or the stored one).
//! * [`round`]: what a round is given besides its frames: the alignment
//!   it works with, the vehicle's reports as its observation.
//! * [`record`]: the rounds on the shot's mission record, and how the
//!   record ends when the loop is ended from outside.
//! * [`loop_params`]: the daemon's loop's tunables.
//! * [`approach`]: re-targeting on the approach, when the georeference
//!   refitted in flight moves the target by more than a fit's noise.
//!
//! Everything here is synchronous (no tokio) and knows nothing of the
//! simulator: the closed-loop experiment in it (`shotpilot scenario`) is
//! `crate::simulator::scenario`, an upper floor that drives these parts.

pub mod approach;
pub mod arrival;
pub mod controller;
pub mod desired;
pub mod error;
pub mod loop_params;
pub mod measure;
pub mod reachable;
pub mod record;
pub mod round;
pub mod servo;
pub mod session;

pub use approach::{Approach, ApproachParams, Shift, Verdict};
pub use arrival::{ArrivalDetector, ArrivalParams, Distance, PositionReport};
pub use controller::{ControllerParams, Correction, Decision, correct, correct_targets, decide};
pub use error::{
    PoseDifference, ShotErrorMeter, ShotErrorParams, ShotErrorReport, axis_yaw_pitch, corner_error,
    outline_in_live, pose_difference, shot_error,
};
pub use measure::{LiveFrame, MeasureParams};
pub use reachable::{Reachable, reachable_from_anchors};
pub use servo::{Servo, ServoFrame, ServoParams, ServoSample, ServoStep, ServoStop};
pub use session::{
    Context, Observation, OffsetRecord, RoundRecord, Session, Step, Stop, World, median_noise_pct,
};

/// Every tunable number of the refinement.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Params {
    /// The shot error measure.
    pub error: ShotErrorParams,
    /// The correction loop.
    pub controller: ControllerParams,
    /// When the view counts as steady on arrival.
    pub arrival: ArrivalParams,
    /// The measurement over several frames on arrival.
    pub measure: MeasureParams,
    /// Re-targeting on the approach.
    pub approach: ApproachParams,
}

/// Errors of the refinement.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RefineError {
    /// The two images (or an image and its mask) differ in size.
    #[error("image sizes differ: {live:?} vs desired {desired:?}")]
    ImageSize {
        /// Size of the live frame (or the mask).
        live: (u32, u32),
        /// Size of the desired shot.
        desired: (u32, u32),
    },
    /// The feature extractor refused.
    #[error("feature extraction: {message}")]
    Features {
        /// Its message.
        message: String,
    },
    /// The matcher refused.
    #[error("matching: {message}")]
    Matching {
        /// Its message.
        message: String,
    },
    /// No homography between the live frame and the desired shot.
    #[error("no homography from {matches} matches: {reason}")]
    NoHomography {
        /// Descriptor matches available.
        matches: usize,
        /// Why the fit failed.
        reason: String,
    },
    /// A corrected target fails the planner's checks (geofence, altitude).
    #[error("corrected target refused: {0}")]
    Target(crate::mission::plan::PlanError),
    /// The georeference could not convert a pose.
    #[error("georeference: {0}")]
    Geo(crate::geo::GeoError),
    /// The corrected gimbal pitch is outside the gimbal's range.
    #[error("corrected gimbal pitch {pitch_deg:.1} deg outside [{min_deg}, {max_deg}]")]
    PitchOutOfRange {
        /// The pitch asked.
        pitch_deg: f64,
        /// The gimbal's lowest pitch.
        min_deg: f64,
        /// The gimbal's highest pitch.
        max_deg: f64,
    },
    /// The desired shot's keyframe is not in the map.
    #[error("keyframe {id} is not in the map")]
    UnknownKeyframe {
        /// Its id.
        id: u32,
    },
    /// A computed value is NaN or infinite.
    #[error("non-finite {what}")]
    NonFinite {
        /// Which value.
        what: &'static str,
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
