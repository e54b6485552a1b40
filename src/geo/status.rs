//! The georeference's state as the API reports it (`/status`'s
//! `vehicle.georeference`), typed: [`GeoreferenceStatus`] is made by
//! [`super::LiveGeoreference::status`] and serialised as it stands, so the
//! OpenAPI document's `GeoreferenceStatus` schema and this file describe
//! one thing (the saved georeference's part is
//! [`super::continuity::SavedStatus`]).

use serde::Serialize;

use super::continuity::SavedStatus;
use super::telemetry::TelemetryClock;

/// The georeference's state, its evidence and its clocks.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct GeoreferenceStatus {
    /// The vehicle's home (HOME_POSITION), once known.
    pub home: Option<HomeView>,
    /// Pairs held (keyframes, frames and restored pairs).
    pub pairs: usize,
    /// Keyframes waiting for their telemetry.
    pub keyframes_pending: usize,
    /// Keyframes dropped while waiting (their telemetry never came).
    pub keyframes_dropped: u64,
    /// Samples in the telemetry history.
    pub history: HistoryCounts,
    /// What came in and what became of it.
    pub counts: Counts,
    /// How telemetry is put on the frames' clock.
    pub clock: ClockStatus,
    /// Seconds since the last fit (None: none yet).
    pub fit_age_s: Option<f64>,
    /// Where the pairs came from.
    pub evidence: Evidence,
    /// The georeference saved beside a continued map (None: none loaded).
    pub saved: Option<SavedStatus>,
    /// The fit: `state` and what goes with it.
    #[serde(flatten)]
    pub fit: FitState,
}

/// A home position.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HomeView {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, m.
    pub alt_amsl_m: f64,
}

/// Samples in the telemetry history.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HistoryCounts {
    /// Position samples.
    pub positions: usize,
    /// Attitude samples.
    pub attitudes: usize,
    /// Gimbal samples.
    pub gimbals: usize,
}

/// The clocks.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ClockStatus {
    /// How telemetry samples are timed.
    pub telemetry: TelemetryClock,
    /// The autopilot's boot time on the local clock, Unix s (None: not yet
    /// known).
    pub boot_offset_unix_s: Option<f64>,
    /// Frames carry their own capture times.
    pub use_frame_timestamps: bool,
    /// The video's latency assumed, s.
    pub video_latency_s: f64,
    /// Median delay of the last frames from capture to arrival, ms.
    pub video_delay_ms_median: Option<f64>,
    /// Mean delay over every frame, ms.
    pub video_delay_ms_mean_all: Option<f64>,
}

/// Where the pairs came from.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Evidence {
    /// Pairs restored from the saved georeference.
    pub restored_pairs: usize,
    /// Tracked frames paired with telemetry.
    pub frame_pairs: usize,
    /// Keyframes of this run paired with telemetry.
    pub live_keyframe_pairs: usize,
}

/// The fit's state.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
pub enum FitState {
    /// No fit tried yet.
    Waiting {
        /// For what.
        reason: String,
    },
    /// The fit is refused.
    Refused {
        /// Why, for the operator.
        reason: String,
        /// The error, for the developer.
        error: String,
    },
    /// A fit.
    Ok(Box<FitView>),
}

/// A fit as reported.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FitView {
    /// `map` (the SLAM's map is in local NED: the identity) or `fit` (a
    /// Sim(3) fitted to the pairs).
    pub source: &'static str,
    /// Why the last fit is kept, when a refit is refused for thin evidence
    /// and the pairs held still agree with it.
    pub held: Option<String>,
    /// Map units to metres.
    pub scale: f64,
    /// RMS of the inliers' residuals, m.
    pub rms_m: f64,
    /// Largest inlier residual, m.
    pub max_residual_m: f64,
    /// RMS of the rotation residuals, degrees (when orientations were used).
    pub rotation_rms_deg: Option<f64>,
    /// Capture-time offset estimated, s.
    pub time_offset_s: Option<f64>,
    /// Inlier pairs.
    pub keyframes_used: usize,
    /// Older pairs left out because they disagreed with the newest.
    pub older_pairs_set_aside: usize,
    /// With `[geo.align.drift]`: the GNSS bias at the newest pair, NED m.
    pub gnss_bias_m: Option<[f64; 3]>,
    /// The mount's pitch and heading offsets learned from the keyframes'
    /// attitudes (`[geo.align] estimate_mount`), added to `[geo.mount]`'s.
    pub mount_offset: Option<crate::geo::MountOffset>,
    /// Said when older pairs were set aside.
    pub recent: Option<String>,
    /// Standard deviations of the inliers' positions along their main
    /// axes, m.
    pub spread_m: [f64; 3],
    /// The similarity.
    pub ned_from_map: SimView,
}

/// A map → NED similarity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SimView {
    /// Scale.
    pub scale: f64,
    /// Rotation quaternion, `[x, y, z, w]`.
    pub rotation_xyzw: [f64; 4],
    /// Translation, m.
    pub translation: [f64; 3],
}

/// What came in and what became of it (the status's `counts`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Counts {
    /// Position samples taken.
    pub positions: u64,
    /// Attitude samples taken.
    pub attitudes: u64,
    /// Gimbal samples taken.
    pub gimbals: u64,
    /// Samples the history refused.
    pub rejected_samples: u64,
    /// Keyframes seen.
    pub keyframes_seen: u64,
    /// Keyframes the georeference refused.
    pub keyframes_refused: u64,
    /// Keyframes whose map pose moved.
    pub keyframes_moved: u64,
    /// Keyframes culled from the map.
    pub keyframes_removed: u64,
    /// Tracked frames paired.
    pub frame_pairs_added: u64,
    /// Tracked frames refused.
    pub frame_pairs_refused: u64,
    /// Fits made.
    pub fits: u64,
    /// Samples given to the SLAM's telemetry priors.
    pub prior_samples: u64,
    /// Of those, samples without a fix.
    pub prior_samples_without_fix: u64,
}
