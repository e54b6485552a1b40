//! When to look: the vehicle has reported the shot's waypoint reached
//! (MISSION_ITEM_REACHED) and, for a while, it hardly moves and the gimbal
//! stands at the commanded pitch. Fed with telemetry samples; the daemon
//! and the scenario use the same rule.

/// Every tunable number of the arrival rule.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ArrivalParams {
    /// Largest ground speed (3-D), m/s.
    pub speed_m_s: f64,
    /// Largest difference between the reported and the commanded gimbal
    /// pitch, degrees.
    pub gimbal_deg: f64,
    /// The conditions hold this long, seconds.
    pub dwell_s: f64,
}

impl Default for ArrivalParams {
    fn default() -> Self {
        Self {
            speed_m_s: 0.05,
            gimbal_deg: 0.2,
            dwell_s: 1.0,
        }
    }
}

/// The arrival rule for one flight to one waypoint.
#[derive(Debug, Clone, PartialEq)]
pub struct ArrivalDetector {
    params: ArrivalParams,
    waypoint_seq: u16,
    gimbal_pitch_deg: f64,
    reached: bool,
    steady_since: Option<f64>,
}

impl ArrivalDetector {
    /// For the mission item `waypoint_seq` flown with the gimbal commanded
    /// to `gimbal_pitch_deg`.
    pub fn new(params: ArrivalParams, waypoint_seq: u16, gimbal_pitch_deg: f64) -> Self {
        Self {
            params,
            waypoint_seq,
            gimbal_pitch_deg,
            reached: false,
            steady_since: None,
        }
    }

    /// A MISSION_ITEM_REACHED for item `seq`.
    pub fn on_reached(&mut self, seq: u16) {
        if seq == self.waypoint_seq {
            self.reached = true;
        }
    }

    /// Whether the waypoint has been reported reached.
    pub fn reached(&self) -> bool {
        self.reached
    }

    /// A telemetry sample at time `t` (seconds): ground speed (m/s) and the
    /// reported gimbal pitch (degrees). True once the view is steady.
    /// Non-finite samples count as not steady.
    pub fn update(&mut self, t: f64, speed_m_s: f64, gimbal_pitch_deg: f64) -> bool {
        let still = speed_m_s.is_finite()
            && speed_m_s < self.params.speed_m_s
            && gimbal_pitch_deg.is_finite()
            && (gimbal_pitch_deg - self.gimbal_pitch_deg).abs() < self.params.gimbal_deg;
        if !(self.reached && still && t.is_finite()) {
            self.steady_since = None;
            return false;
        }
        let since = *self.steady_since.get_or_insert(t);
        t - since >= self.params.dwell_s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn steady_only_after_the_waypoint_and_the_dwell() {
        let mut a = ArrivalDetector::new(ArrivalParams::default(), 1, -40.0);
        // Still, but the waypoint is not reached yet.
        assert!(!a.update(0.0, 0.0, -40.0));
        a.on_reached(0); // another item
        assert!(!a.reached());
        a.on_reached(1);
        assert!(a.reached());
        assert!(!a.update(1.0, 0.01, -40.05));
        assert!(!a.update(1.5, 0.01, -40.05));
        // A gust resets the dwell.
        assert!(!a.update(1.8, 0.3, -40.05));
        assert!(!a.update(2.0, 0.01, -40.05));
        assert!(!a.update(2.9, 0.01, -40.05));
        assert!(a.update(3.0, 0.01, -40.05));
        // The gimbal still turning is not steady.
        assert!(!a.update(3.1, 0.0, -41.0));
        assert!(!a.update(3.2, f64::NAN, -40.0));
    }
}
