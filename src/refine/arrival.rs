//! When to look: the vehicle has reported the shot's waypoint reached
//! (MISSION_ITEM_REACHED) and, for a while, it hardly moves and the gimbal
//! stands at the commanded pitch. Fed with telemetry samples; the daemon
//! and the scenario use the same rule. The daemon polls the vehicle's
//! reports ([`ArrivalDetector::poll`]): a waypoint reported reached counts
//! only when the reported position is near the target too
//! ([`PositionReport`], [`Distance`]).

use nalgebra::Vector3;

use crate::geo::{Geodetic, LocalFrame};
use crate::mission::plan::Target;

/// MAVLink's MISSION_STATE_COMPLETE: the mission ran to its end.
pub const MISSION_STATE_COMPLETE: u8 = 5;

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

    /// One poll of the vehicle's reports at time `t` (seconds). The
    /// waypoint counts as reached when the vehicle reports it (`passed`,
    /// see [`waypoint_passed`]) *and* is `near` the target (within the
    /// planner's acceptance radius): the last reached item stays in the
    /// telemetry from the previous flight, and an upload to a vehicle in
    /// mission mode restarts the mission at once, so the report alone may
    /// be stale or already past. The speed counts only near the target.
    /// True once the view is steady (see [`Self::update`]).
    pub fn poll(
        &mut self,
        t: f64,
        passed: bool,
        near: bool,
        speed_m_s: f64,
        gimbal_pitch_deg: f64,
    ) -> bool {
        if passed && near {
            self.on_reached(self.waypoint_seq);
        }
        let speed = if near { speed_m_s } else { f64::NAN };
        self.update(t, speed, gimbal_pitch_deg)
    }
}

/// Whether the vehicle's mission progress (the last item reached, the
/// MISSION_STATE) says waypoint `wp` was reached: it, or a later item, or
/// the mission complete.
pub fn waypoint_passed(last_reached: Option<u16>, mission_state: Option<u8>, wp: u16) -> bool {
    last_reached.is_some_and(|r| r >= wp) || mission_state == Some(MISSION_STATE_COMPLETE)
}

/// North and east (metres, WGS84 local frame at the target) of a
/// reported position from a target.
pub fn north_east_of(t: &Target, lat_deg: f64, lon_deg: f64) -> (f64, f64) {
    let at = |lat_deg, lon_deg| Geodetic {
        lat_deg,
        lon_deg,
        alt_m: 0.0,
    };
    let ned = LocalFrame::new(at(t.lat_deg, t.lon_deg)).geodetic_to_ned(&at(lat_deg, lon_deg));
    (ned.x, ned.y)
}

/// How far a reported position is from a target, metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Distance {
    /// Horizontal.
    pub horizontal: f64,
    /// The target's altitude less the vehicle's (positive: climb).
    pub vertical: f64,
}

impl Distance {
    /// Of a reported position (relative altitude above home) from `t`.
    pub fn to(t: &Target, lat_deg: f64, lon_deg: f64, rel_alt_m: f64) -> Self {
        let (n, e) = north_east_of(t, lat_deg, lon_deg);
        Self {
            horizontal: n.hypot(e),
            vertical: t.alt_m - rel_alt_m,
        }
    }

    /// The straight-line distance.
    pub fn straight(&self) -> f64 {
        self.horizontal.hypot(self.vertical)
    }

    /// Within `radius` horizontally and vertically (never for NaN).
    pub fn within(&self, radius: f64) -> bool {
        self.horizontal <= radius && self.vertical.abs() <= radius
    }
}

/// A position the vehicle reported (GLOBAL_POSITION_INT).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PositionReport {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above home, metres.
    pub rel_alt_m: f64,
    /// Velocity north, east, down, m/s.
    pub vel_ned_m_s: [f32; 3],
    /// How old the report is, seconds.
    pub age_s: f64,
}

impl PositionReport {
    /// The 3-D speed, m/s.
    pub fn speed_m_s(&self) -> f64 {
        let v = self.vel_ned_m_s;
        f64::from(v[0])
            .hypot(f64::from(v[1]))
            .hypot(f64::from(v[2]))
    }

    /// How far it is from `t`.
    pub fn distance_to(&self, t: &Target) -> Distance {
        Distance::to(t, self.lat_deg, self.lon_deg, self.rel_alt_m)
    }

    /// In local NED at `frame` (home, whose altitude AMSL is
    /// `home_alt_amsl_m`), metres; None when not finite.
    pub fn ned(&self, frame: &LocalFrame, home_alt_amsl_m: f64) -> Option<Vector3<f64>> {
        let p = frame.geodetic_to_ned(&Geodetic {
            lat_deg: self.lat_deg,
            lon_deg: self.lon_deg,
            alt_m: home_alt_amsl_m + self.rel_alt_m,
        });
        p.iter().all(|x| x.is_finite()).then_some(p)
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

    /// A reached report counts only near the target; the speed far from
    /// it never counts as still.
    #[test]
    fn a_poll_counts_the_waypoint_only_near_the_target() {
        let mut a = ArrivalDetector::new(ArrivalParams::default(), 2, -40.0);
        assert!(!a.poll(0.0, true, false, 0.0, -40.0));
        assert!(!a.reached(), "reported, but far: a stale report");
        assert!(!a.poll(0.5, false, true, 0.0, -40.0));
        assert!(!a.reached());
        assert!(!a.poll(1.0, true, true, 0.0, -40.0));
        assert!(a.reached());
        assert!(a.poll(2.0, true, true, 0.0, -40.0));
        assert!(!a.poll(2.5, true, false, 0.0, -40.0), "drifted away");
        assert!(waypoint_passed(Some(3), None, 2));
        assert!(!waypoint_passed(Some(1), Some(3), 2));
        assert!(waypoint_passed(None, Some(MISSION_STATE_COMPLETE), 2));
        assert!(!waypoint_passed(None, None, 0));
    }

    fn target() -> Target {
        Target {
            lat_deg: 47.397,
            lon_deg: 8.545,
            alt_m: 15.0,
            yaw_deg: 30.0,
            gimbal_pitch_deg: -40.0,
            photo: true,
        }
    }

    #[test]
    fn distance_to_the_target_in_metres() {
        let t = target();
        let d = Distance::to(&t, t.lat_deg, t.lon_deg, t.alt_m);
        assert!(d.horizontal < 1e-9 && d.vertical.abs() < 1e-9);
        // 1e-5 deg of latitude is 1.11 m; 2 m lower (the target is 2 m up).
        let d = Distance::to(&t, t.lat_deg + 1e-5, t.lon_deg, t.alt_m - 2.0);
        assert!((d.horizontal - 1.111).abs() < 0.01, "{d:?}");
        assert!((d.vertical - 2.0).abs() < 1e-9);
        assert!((d.straight() - 1.111f64.hypot(2.0)).abs() < 0.01, "{d:?}");
        // 1e-5 deg of longitude at 47.4 deg is 0.754 m.
        let d = Distance::to(&t, t.lat_deg, t.lon_deg + 1e-5, t.alt_m);
        assert!((d.horizontal - 0.754).abs() < 0.01, "{d:?}");
        let d = Distance::to(&t, f64::NAN, t.lon_deg, t.alt_m);
        assert!(d.horizontal.is_nan(), "NaN never counts as near");
        assert!(!d.within(1.0));
    }

    /// A report's speed, distance and local position.
    #[test]
    fn a_position_report_in_the_targets_terms() {
        let t = target();
        let r = PositionReport {
            lat_deg: t.lat_deg + 1e-5,
            lon_deg: t.lon_deg,
            rel_alt_m: t.alt_m - 2.0,
            vel_ned_m_s: [3.0, 0.0, 4.0],
            age_s: 0.1,
        };
        assert_eq!(r.speed_m_s(), 5.0);
        assert_eq!(
            r.distance_to(&t),
            Distance::to(&t, r.lat_deg, r.lon_deg, r.rel_alt_m)
        );
        let home = Geodetic {
            lat_deg: t.lat_deg,
            lon_deg: t.lon_deg,
            alt_m: 400.0,
        };
        let p = r.ned(&LocalFrame::new(home), home.alt_m).unwrap();
        assert!((p.x - 1.111).abs() < 0.01 && p.y.abs() < 1e-6, "{p}");
        assert!((p.z + 13.0).abs() < 0.01, "13 m above home: {p}");
        let lost = PositionReport {
            lat_deg: f64::NAN,
            ..r
        };
        assert_eq!(lost.ned(&LocalFrame::new(home), home.alt_m), None);
    }
}
