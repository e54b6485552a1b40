//! From the SLAM map to the world: a monocular map has no scale and no
//! north, the vehicle needs latitude, longitude, altitude, yaw and gimbal
//! pitch.
//!
//! * [`telemetry`]: a bounded telemetry history, interpolated at a frame's
//!   capture time (position linearly, attitude by slerp), refusing times
//!   outside it or across gaps;
//! * [`mount`]: the camera pose in local NED from the vehicle state
//!   (position, attitude, 2-axis gimbal, lever arm), and back;
//! * [`wgs84`]: WGS84 ↔ local NED through the tangent plane at home (ECEF,
//!   exact);
//! * [`align`]: the robust map → NED Sim(3) from keyframe pairs (Umeyama in
//!   seeded RANSAC, refit, optional orientation refinement, optionally a
//!   GNSS bias state per window so the fit follows the receiver's drift),
//!   with its quality and refusals;
//! * [`pipeline`]: [`Geo`], the parts wired together (keyframes wait for
//!   the telemetry of their capture time);
//! * [`clock`]: the autopilot's boot clock on the local clock
//!   ([`BootClock`]);
//! * [`saved`]: the georeference as saved beside the map;
//! * [`continuity`]: the saved georeference restored onto a continued map,
//!   carried to another home, checked against live pairs;
//! * [`live`]: [`LiveGeoreference`], the georeference of a run fed sample
//!   by sample (telemetry, keyframes, tracked frames, the saved pairs), its
//!   refits and its status (the daemon's worker holds one);
//! * [`status`]: [`GeoreferenceStatus`], that status typed as the API
//!   reports it;
//! * [`target`]: a target `map ← cam` as latitude/longitude/altitude/yaw/
//!   gimbal pitch, with the roll a 2-axis gimbal cannot reproduce.
//!
//! Frames: NED world x north, y east, z down; body x forward, y right,
//! z down; camera x right, y down, z forward. They agree with the
//! simulator's (`sim/src/vehicle.rs`), which `tests/suite/geo_sim.rs` checks.
//! Synchronous: no tokio, no I/O.

pub mod align;
pub mod clock;
pub mod continuity;
pub mod live;
pub mod mount;
pub mod pipeline;
pub mod saved;
pub mod status;
pub mod target;
pub mod telemetry;
pub mod wgs84;

pub use align::{AlignParams, AlignQuality, GeoAlignment, Georeference, GnssDrift, Pair};
pub use clock::BootClock;
pub use live::{LiveGeoreference, frame_pair_id};
pub use mount::{
    GimbalSolution, LeverArmFrame, MountOffset, MountParams, ned_from_cam, solve_gimbal,
};
pub use pipeline::{Geo, KeyframeStatus};
pub use status::GeoreferenceStatus;
pub use target::{GeoTarget, convert_target, target_from_ned};
pub use telemetry::{
    GimbalAngles, HistoryParams, TelemetryClock, TelemetryHistory, VehicleState, capture_time,
};
pub use wgs84::{Geodetic, LocalFrame};

use crate::geometry::GeometryError;

/// Every tunable number of the geo module (deserialisable as a config
/// section; every field optional).
#[derive(Debug, Clone, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Params {
    /// Telemetry history and time alignment.
    pub history: HistoryParams,
    /// The camera's mounting and gimbal range.
    pub mount: MountParams,
    /// The map → NED alignment.
    pub align: AlignParams,
    /// Across restarts: tracked frames as extra pairs, and the check of a
    /// saved georeference against live evidence.
    pub continuity: ContinuityParams,
}

/// How the georeference carries on across a restart (see [`live`] and
/// [`continuity`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ContinuityParams {
    /// A tracked frame is paired with telemetry at most this often, seconds
    /// (so the fit gains live evidence when the drone flies over mapped
    /// ground and adds no keyframe); 0 turns frame pairs off.
    pub frame_pair_spacing_s: f64,
    /// Frame pairs kept (the oldest go first).
    pub max_frame_pairs: usize,
    /// Live pairs (keyframes or frames of this run) needed before the saved
    /// georeference is checked against them.
    pub min_live_pairs: usize,
    /// The saved georeference disagrees with the live pairs when their
    /// median residual under it exceeds this many times its own RMS
    /// residual (and the alignment's inlier threshold): it is then dropped
    /// and the fit made from live pairs alone.
    pub disagreement_factor: f64,
}

impl Default for ContinuityParams {
    fn default() -> Self {
        Self {
            frame_pair_spacing_s: 1.0,
            max_frame_pairs: 60,
            min_live_pairs: 3,
            disagreement_factor: 3.0,
        }
    }
}

/// Errors of the geo module.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum GeoError {
    /// An input value is NaN or infinite.
    #[error("non-finite {what}")]
    NonFinite {
        /// Which input.
        what: &'static str,
    },
    /// A telemetry stream has no sample yet.
    #[error("no {stream} telemetry yet")]
    EmptyHistory {
        /// The stream.
        stream: &'static str,
    },
    /// The time is older than the stream's history.
    #[error("time {t:.3} s is before the oldest {stream} sample ({oldest:.3} s)")]
    TooOld {
        /// The stream.
        stream: &'static str,
        /// The time asked.
        t: f64,
        /// The oldest sample's time.
        oldest: f64,
    },
    /// The time is newer than the stream's newest sample (try again later).
    #[error("time {t:.3} s is after the newest {stream} sample ({newest:.3} s)")]
    NotYet {
        /// The stream.
        stream: &'static str,
        /// The time asked.
        t: f64,
        /// The newest sample's time.
        newest: f64,
    },
    /// The samples around the time are too far apart.
    #[error(
        "{stream} gap around {t:.3} s: samples at {before:.3} and {after:.3} s (max {max_gap_s} s)"
    )]
    Gap {
        /// The stream.
        stream: &'static str,
        /// The time asked.
        t: f64,
        /// The sample before.
        before: f64,
        /// The sample after.
        after: f64,
        /// The largest gap allowed, seconds.
        max_gap_s: f64,
    },
    /// Too few keyframe pairs to fit.
    #[error("not enough keyframe pairs: found {found}, needed {needed}")]
    NotEnoughPairs {
        /// Pairs held.
        found: usize,
        /// Pairs needed.
        needed: usize,
    },
    /// The camera has not moved enough to fix the scale.
    #[error("too little motion: extent {extent_m:.2} m (std dev), needed {needed_m:.2} m")]
    TooLittleMotion {
        /// Standard deviation along the main direction, metres.
        extent_m: f64,
        /// Threshold, metres.
        needed_m: f64,
    },
    /// The camera moved (almost) along a line: the rotation about it is not
    /// fixed.
    #[error(
        "motion too close to a line: lateral {lateral_m:.2} m (needed {needed_m:.2}), ratio {ratio:.3} (needed {needed_ratio:.3})"
    )]
    Collinear {
        /// Standard deviation across the main direction, metres.
        lateral_m: f64,
        /// Threshold, metres.
        needed_m: f64,
        /// Lateral over main standard deviation.
        ratio: f64,
        /// Threshold.
        needed_ratio: f64,
    },
    /// RANSAC found too few pairs agreeing on a similarity.
    #[error("too few inliers: found {found} of {pairs}, needed {needed}")]
    TooFewInliers {
        /// Inliers of the best model.
        found: usize,
        /// Inliers needed.
        needed: usize,
        /// Pairs held.
        pairs: usize,
    },
    /// The target needs a gimbal pitch outside its range.
    #[error("gimbal pitch {pitch_deg:.2} deg outside [{min_deg}, {max_deg}]")]
    PitchOutOfRange {
        /// Pitch needed, degrees.
        pitch_deg: f64,
        /// Lowest pitch, degrees.
        min_deg: f64,
        /// Highest pitch, degrees.
        max_deg: f64,
    },
    /// Home is not known yet (no HOME_POSITION).
    #[error("home position not known yet")]
    NoHome,
    /// The least-squares alignment failed.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
}
