//! Re-targeting on the approach. A shot's target is converted with the
//! georeference of the moment the flight starts; the GNSS bias that
//! georeference carries keeps wandering during the 5-20 s the vehicle
//! takes to get there (about 0.5 m per axis in 10 s for a field receiver),
//! so the vehicle arrives where the shot was seconds ago. While it flies,
//! the georeference keeps learning from the live frames the tracking pairs
//! with telemetry; every [`ApproachParams::period_s`] the target is
//! converted again with the newest fit and, when it moved by more than the
//! noise of a fit ([`ApproachParams::min_shift_m`],
//! [`ApproachParams::min_turn_deg`]), the new one is flown instead, at most
//! [`ApproachParams::max_per_leg`] times a leg (each costs a mission upload
//! on the radio). The daemon (`daemon/refinement_task.rs`) and the
//! scenario use the same rule ([`Approach`]).
//!
//! Only the first leg, the flight to the shot, is re-targeted. A
//! correction leg's target comes from a look: the receiver's reported
//! position against where vision put the camera, which measures the bias
//! at the look itself whatever the georeference's estimate of it; moving
//! that target by the refit's change would count the drift up to the look
//! twice (measured in the quick scenarios: finals of 1.4 and 3.1 % where the
//! first looks were 1.1 %).

use crate::angle::wrap180;
use crate::geo::{Geodetic, LocalFrame};
use crate::mission::plan::{Home, Target};

/// Every tunable number of re-targeting on the approach (`[refine.approach]`).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ApproachParams {
    /// Re-target on the approach at all.
    pub enabled: bool,
    /// The target is converted again this often while flying, s.
    pub period_s: f64,
    /// A target that moved at least this far (the vehicle's position, 3-D)
    /// is flown, m.
    pub min_shift_m: f64,
    /// A target whose heading or gimbal pitch turned at least this much is
    /// flown, degrees.
    pub min_turn_deg: f64,
    /// Re-targets per leg (one flight to one target) at most.
    pub max_per_leg: usize,
}

impl Default for ApproachParams {
    fn default() -> Self {
        Self {
            enabled: true,
            period_s: 1.0,
            min_shift_m: 0.15,
            min_turn_deg: 0.3,
            max_per_leg: 4,
        }
    }
}

impl ApproachParams {
    /// Why the parameters cannot be used, if they cannot.
    pub fn check(&self) -> Result<(), String> {
        if !(self.period_s.is_finite() && self.period_s > 0.0) {
            return Err(format!("period_s must be > 0, got {}", self.period_s));
        }
        if !(self.min_shift_m.is_finite() && self.min_shift_m > 0.0) {
            return Err(format!("min_shift_m must be > 0, got {}", self.min_shift_m));
        }
        if !(self.min_turn_deg.is_finite() && self.min_turn_deg > 0.0) {
            return Err(format!(
                "min_turn_deg must be > 0, got {}",
                self.min_turn_deg
            ));
        }
        Ok(())
    }
}

/// How far a freshly converted target is from the one being flown.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Shift {
    /// The vehicle position's move, local NED (north, east, down), m.
    pub ned_m: [f64; 3],
    /// Its length, m.
    pub position_m: f64,
    /// The heading's turn (fresh minus flown), degrees in [-180, 180).
    pub yaw_deg: f64,
    /// The gimbal pitch's turn, degrees.
    pub pitch_deg: f64,
}

/// A target's vehicle position in the local frame at home (its altitude
/// is above home).
pub fn target_ned(t: &Target, frame: &LocalFrame, home: &Home) -> nalgebra::Vector3<f64> {
    frame.geodetic_to_ned(&Geodetic {
        lat_deg: t.lat_deg,
        lon_deg: t.lon_deg,
        alt_m: home.alt_amsl_m + t.alt_m,
    })
}

impl Shift {
    /// From `flown` to `fresh`, in the local frame at home.
    pub fn between(flown: &Target, fresh: &Target, frame: &LocalFrame, home: &Home) -> Shift {
        let d = target_ned(fresh, frame, home) - target_ned(flown, frame, home);
        Shift {
            ned_m: d.into(),
            position_m: d.norm(),
            yaw_deg: wrap180(fresh.yaw_deg - flown.yaw_deg),
            pitch_deg: fresh.gimbal_pitch_deg - flown.gimbal_pitch_deg,
        }
    }

    /// `flown` moved by this shift: the fresh conversion when `flown` was
    /// the conversion the shift is measured from, with the flown target's
    /// photo flag.
    pub fn apply(&self, flown: &Target, frame: &LocalFrame, home: &Home) -> Target {
        let p = target_ned(flown, frame, home) + nalgebra::Vector3::from(self.ned_m);
        let g = frame.ned_to_geodetic(&p);
        Target {
            lat_deg: g.lat_deg,
            lon_deg: g.lon_deg,
            alt_m: g.alt_m - home.alt_amsl_m,
            yaw_deg: (flown.yaw_deg + self.yaw_deg).rem_euclid(360.0),
            gimbal_pitch_deg: flown.gimbal_pitch_deg + self.pitch_deg,
            photo: flown.photo,
        }
    }

    /// Every part finite.
    fn is_finite(&self) -> bool {
        self.position_m.is_finite() && self.yaw_deg.is_finite() && self.pitch_deg.is_finite()
    }
}

/// What to do with a freshly converted target.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Verdict {
    /// Not yet time to convert again (the last was under a period ago).
    NotDue,
    /// Converted, but within the fit's noise of the flown one: keep flying.
    Keep(Shift),
    /// Fly the fresh target instead.
    Fly(Shift),
    /// The leg has had its re-targets.
    Spent,
}

/// The re-targeting rule for one leg (one flight to one target).
#[derive(Debug, Clone, PartialEq)]
pub struct Approach {
    params: ApproachParams,
    /// When the target was last converted (None: not yet this leg), s.
    last_s: Option<f64>,
    flown: usize,
    /// The first leg (no look yet): the only one re-targeted.
    first_leg: bool,
}

impl Approach {
    /// A leg starting at `t_s` (its target was converted then);
    /// `first_leg`: the flight to the shot, before any look (a correction
    /// leg is never re-targeted).
    pub fn new(params: ApproachParams, t_s: f64, first_leg: bool) -> Self {
        Self {
            params,
            last_s: Some(t_s),
            flown: 0,
            first_leg,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &ApproachParams {
        &self.params
    }

    /// Re-targets flown this leg.
    pub fn flown(&self) -> usize {
        self.flown
    }

    /// Whether a conversion is due at `t_s` (enabled, the first leg, its
    /// budget not spent, a period since the last).
    pub fn due(&self, t_s: f64) -> bool {
        self.live()
            && self
                .last_s
                .is_none_or(|l| t_s - l >= self.params.period_s || t_s < l)
    }

    /// Enabled, on the first leg, the budget not spent.
    fn live(&self) -> bool {
        self.params.enabled && self.first_leg && self.flown < self.params.max_per_leg
    }

    /// The verdict on `shift`, the move of a target converted at `t_s`
    /// from the flown one; a [`Verdict::Fly`] counts against the leg's
    /// budget. A shift that is not finite is kept (never flown).
    pub fn judge(&mut self, t_s: f64, shift: Shift) -> Verdict {
        if !self.live() {
            return Verdict::Spent;
        }
        if !self.due(t_s) {
            return Verdict::NotDue;
        }
        self.last_s = Some(t_s);
        let p = &self.params;
        let moved = shift.position_m >= p.min_shift_m
            || shift.yaw_deg.abs() >= p.min_turn_deg
            || shift.pitch_deg.abs() >= p.min_turn_deg;
        if shift.is_finite() && moved {
            self.flown += 1;
            Verdict::Fly(shift)
        } else {
            Verdict::Keep(shift)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn home() -> Home {
        Home {
            lat_deg: 47.397,
            lon_deg: 8.545,
            alt_amsl_m: 488.0,
        }
    }

    fn frame() -> LocalFrame {
        let h = home();
        LocalFrame::new(Geodetic {
            lat_deg: h.lat_deg,
            lon_deg: h.lon_deg,
            alt_m: h.alt_amsl_m,
        })
    }

    fn target_at(n: f64, e: f64, up: f64, yaw: f64, pitch: f64) -> Target {
        let g = frame().ned_to_geodetic(&nalgebra::Vector3::new(n, e, -(up)));
        Target {
            lat_deg: g.lat_deg,
            lon_deg: g.lon_deg,
            alt_m: g.alt_m - home().alt_amsl_m,
            yaw_deg: yaw,
            gimbal_pitch_deg: pitch,
            photo: false,
        }
    }

    #[test]
    fn the_shift_is_measured_in_metres_and_degrees() {
        let a = target_at(10.0, 5.0, 20.0, 179.0, -30.0);
        let b = target_at(10.3, 4.6, 20.2, -179.5, -30.4);
        let s = Shift::between(&a, &b, &frame(), &home());
        assert!((s.ned_m[0] - 0.3).abs() < 1e-3, "{s:?}");
        assert!((s.ned_m[1] + 0.4).abs() < 1e-3, "{s:?}");
        assert!((s.ned_m[2] + 0.2).abs() < 1e-3, "{s:?}");
        assert!((s.position_m - (0.29f64).sqrt()).abs() < 1e-3, "{s:?}");
        // Across north: 1.5 deg, not 358.5.
        assert!((s.yaw_deg - 1.5).abs() < 1e-9, "{s:?}");
        assert!((s.pitch_deg + 0.4).abs() < 1e-9, "{s:?}");
        // Applied to a correction leg's target, the same move.
        let c = target_at(-3.0, 2.0, 15.0, 10.0, -45.0);
        let moved = s.apply(&c, &frame(), &home());
        let back = Shift::between(&c, &moved, &frame(), &home());
        for i in 0..3 {
            assert!((back.ned_m[i] - s.ned_m[i]).abs() < 1e-6, "{back:?}");
        }
        assert!((moved.yaw_deg - 11.5).abs() < 1e-9);
        assert!((moved.gimbal_pitch_deg + 45.4).abs() < 1e-9);
    }

    #[test]
    fn a_leg_flies_moves_beyond_the_noise_once_a_period_within_its_budget() {
        let p = ApproachParams {
            max_per_leg: 2,
            ..ApproachParams::default()
        };
        let mut a = Approach::new(p, 0.0, true);
        let small = Shift {
            ned_m: [0.1, 0.0, 0.0],
            position_m: 0.1,
            yaw_deg: 0.1,
            pitch_deg: -0.1,
        };
        let big = Shift {
            ned_m: [0.4, 0.0, 0.0],
            position_m: 0.4,
            ..small
        };
        let turned = Shift {
            pitch_deg: 0.5,
            ..small
        };
        assert!(!a.due(0.5));
        assert_eq!(a.judge(0.5, big), Verdict::NotDue);
        assert_eq!(a.judge(1.0, small), Verdict::Keep(small));
        // The period counts from the last conversion.
        assert_eq!(a.judge(1.5, big), Verdict::NotDue);
        assert_eq!(a.judge(2.0, big), Verdict::Fly(big));
        assert_eq!(a.judge(3.0, turned), Verdict::Fly(turned));
        assert_eq!(a.flown(), 2);
        assert!(!a.due(10.0));
        assert_eq!(a.judge(10.0, big), Verdict::Spent);
    }

    #[test]
    fn a_disabled_rule_or_a_non_finite_shift_never_flies() {
        let off = ApproachParams {
            enabled: false,
            ..ApproachParams::default()
        };
        let big = Shift {
            ned_m: [1.0, 0.0, 0.0],
            position_m: 1.0,
            yaw_deg: 0.0,
            pitch_deg: 0.0,
        };
        assert_eq!(
            Approach::new(off, 0.0, true).judge(5.0, big),
            Verdict::Spent
        );
        let mut a = Approach::new(ApproachParams::default(), 0.0, true);
        let nan = Shift {
            position_m: f64::NAN,
            ..big
        };
        // (NaN is not equal to itself: match the variant.)
        assert!(matches!(a.judge(5.0, nan), Verdict::Keep(_)));
        assert_eq!(a.flown(), 0);
    }

    #[test]
    fn a_correction_leg_is_never_re_targeted() {
        let big = Shift {
            ned_m: [1.0, 0.0, 0.0],
            position_m: 1.0,
            yaw_deg: 2.0,
            pitch_deg: 0.0,
        };
        let mut a = Approach::new(ApproachParams::default(), 0.0, false);
        assert!(!a.due(10.0));
        assert_eq!(a.judge(10.0, big), Verdict::Spent);
        assert_eq!(a.flown(), 0);
    }

    #[test]
    fn bad_parameters_are_named() {
        let p = ApproachParams {
            period_s: 0.0,
            ..ApproachParams::default()
        };
        assert!(p.check().unwrap_err().contains("period_s"));
        let p = ApproachParams {
            min_shift_m: f64::NAN,
            ..ApproachParams::default()
        };
        assert!(p.check().unwrap_err().contains("min_shift_m"));
        assert!(ApproachParams::default().check().is_ok());
    }
}
