//! The scenario's errors: why a trial's flight failed ([`FlightError`], a
//! result of the trial) and what stops the whole scenario
//! ([`ScenarioError`]).

/// Why a trial's flight failed (the trial's `reason`, a result).
#[derive(Debug, thiserror::Error)]
pub enum FlightError {
    /// The mission upload state machine failed.
    #[error("upload: {0}")]
    Upload(#[from] crate::mission::upload::MissionError),
    /// The upload did not finish within its message budget.
    #[error("upload: did not finish")]
    UploadUnfinished,
    /// The vehicle did not reach the waypoint and hold still in time.
    #[error("waypoint {waypoint} not reached and steady within {waited_s} s")]
    NoArrival {
        /// The waypoint's sequence number.
        waypoint: u16,
        /// Simulated seconds waited.
        waited_s: f64,
    },
}

/// Errors that stop the scenario (a failing trial is a result, not an error).
#[derive(Debug, thiserror::Error)]
pub enum ScenarioError {
    /// Invalid parameters.
    #[error("invalid parameter {name}: {reason}")]
    InvalidParams {
        /// Which parameter.
        name: &'static str,
        /// What is wrong with it.
        reason: &'static str,
    },
    /// The world could not be generated.
    #[error("world: {0}")]
    World(String),
    /// The realism configuration is unusable.
    #[error("realism: {0}")]
    Realism(#[from] shotpilot_sim::realism::RealismError),
    /// The camera is unusable.
    #[error("camera: {0}")]
    Camera(#[from] crate::camera::CameraError),
    /// The SLAM could not start.
    #[error("SLAM: {0}")]
    Slam(#[from] crate::slam::SlamError),
    /// The explored map could not be saved and read back (`restart`).
    #[error("map file: {0}")]
    MapFile(#[from] crate::slam::mapfile::MapFileError),
    /// The explore flight did not give a map.
    #[error("the explore flight gave no usable map: {keyframes} keyframes")]
    NoMap {
        /// Keyframes in the map.
        keyframes: usize,
    },
    /// The georeference could not be fitted.
    #[error("georeference: {0}")]
    Geo(#[from] crate::geo::GeoError),
    /// The explore flight did not finish in time.
    #[error("the explore flight did not finish within {seconds} s")]
    ExploreTimeout {
        /// The limit, s.
        seconds: f64,
    },
}
