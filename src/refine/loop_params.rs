//! The tunables of the daemon's refinement loop, below the configuration
//! that fills them (`[refine]` in `config.toml`) and the daemon that runs
//! the loop.

use std::time::Duration;

use crate::shot::LocalizeParams;
use crate::shot::anchors::AnchorParams;

/// Every tunable number of the daemon's refinement loop
/// (`crate::daemon::refinement_task`; the session's own are in
/// [`crate::refine::Params`]).
#[derive(Debug, Clone)]
pub struct LoopParams {
    /// The session: shot error, controller, arrival rule.
    pub refine: crate::refine::Params,
    /// Localisation of the live frame.
    pub localize: LocalizeParams,
    /// The desired picture of an anchors shot.
    pub anchors: AnchorParams,
    /// Telemetry polling period.
    pub poll: Duration,
    /// Longest flight to one target before the loop gives up.
    pub max_flight: Duration,
    /// Telemetry older than this counts as missing.
    pub max_telemetry_age: Duration,
    /// Longest wait for a video frame received after the arrival.
    pub frame_wait: Duration,
    /// Servoing at the shot after the first arrival (None: rounds of
    /// mission legs only).
    pub servo: Option<crate::refine::ServoParams>,
}

impl Default for LoopParams {
    fn default() -> Self {
        Self {
            refine: crate::refine::Params::default(),
            localize: LocalizeParams::default(),
            anchors: AnchorParams::default(),
            poll: Duration::from_millis(100),
            max_flight: Duration::from_secs(120),
            max_telemetry_age: Duration::from_secs(2),
            frame_wait: Duration::from_secs(3),
            servo: None,
        }
    }
}
