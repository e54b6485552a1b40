//! The scripted operator: `--script explore` and `--script hover`.
//!
//! `explore` arms, takes off straight up over home, then flies a lawn-mower
//! pattern over the scene at several altitudes with the camera pitched down,
//! which gives monocular SLAM the lateral translation it needs to
//! initialise and map. Yaw and gimbal pitch change only while the vehicle
//! translates (they are interpolated along each leg by the leg's progress),
//! so the camera never turns on the spot. Each leg's altitude is raised to
//! clear the buildings near it (a clearance function supplied by the app).
//! At the end the vehicle hovers in AUTO.LOITER (ArduPilot: LOITER) and
//! accepts missions.
//!
//! `hover` arms, climbs to the hover altitude over home with the camera
//! pitched down and holds there in AUTO.LOITER.
//!
//! `patrol` flies the `explore` route, then back over home and round it
//! again, lap after lap, until the operator takes over: a long flight that
//! keeps revisiting mapped places (loops) for soak runs.
//!
//! The script flies in OFFBOARD (ArduPilot: GUIDED) through
//! [`Autopilot::set_external_setpoint`]; if the operator changes the mode
//! (starts a mission, lands, returns) the script stops at once.

use nalgebra::Vector3;

use crate::autopilot::{Autopilot, Mode};
use crate::vehicle::{Setpoint, wrap_pi};

/// Which script to run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ScriptKind {
    /// The SLAM-friendly survey.
    Explore,
    /// Climb and hover.
    Hover,
    /// The survey flown again and again until the operator takes over.
    Patrol,
}

/// One level of the exploration pattern.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Level {
    /// Height above ground, m.
    pub alt_m: f64,
    /// Gimbal pitch, degrees (negative down).
    pub gimbal_pitch_deg: f64,
    /// Vehicle yaw during the level, degrees.
    pub yaw_deg: f64,
}

/// Every tunable number of the scripts.
#[derive(Debug, Clone, PartialEq)]
pub struct ScriptParams {
    /// Hover altitude for `hover` and the first climb, m.
    pub hover_alt_m: f64,
    /// Gimbal pitch while hovering, degrees.
    pub hover_gimbal_pitch_deg: f64,
    /// Half the side of the square surveyed, m (centred on home).
    pub half_extent_m: f64,
    /// Number of passes per level.
    pub passes: usize,
    /// Survey speed, m/s.
    pub speed: f64,
    /// Clearance above the tallest building within `clearance_radius_m`, m.
    pub clearance_m: f64,
    /// Radius searched for buildings along a leg, m.
    pub clearance_radius_m: f64,
    /// Wait after start before arming, s.
    pub start_delay_s: f64,
    /// The levels flown by `explore`.
    pub levels: Vec<Level>,
    /// Distance at which a leg counts as done, m.
    pub leg_tolerance_m: f64,
    /// Legs are flown in segments of about this length, each at its own
    /// safe altitude, m.
    pub segment_m: f64,
}

impl Default for ScriptParams {
    fn default() -> Self {
        Self {
            hover_alt_m: 10.0,
            hover_gimbal_pitch_deg: -30.0,
            half_extent_m: 30.0,
            passes: 3,
            speed: 2.5,
            clearance_m: 5.0,
            clearance_radius_m: 6.0,
            start_delay_s: 2.0,
            levels: vec![
                Level {
                    alt_m: 12.0,
                    gimbal_pitch_deg: -35.0,
                    yaw_deg: 0.0,
                },
                Level {
                    alt_m: 22.0,
                    gimbal_pitch_deg: -50.0,
                    yaw_deg: 90.0,
                },
                Level {
                    alt_m: 35.0,
                    gimbal_pitch_deg: -65.0,
                    yaw_deg: 180.0,
                },
            ],
            leg_tolerance_m: 0.5,
            segment_m: 10.0,
        }
    }
}

/// One straight leg: end point (NED), yaw and gimbal pitch at its end.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Leg {
    /// End of the leg, local NED.
    pub to: Vector3<f64>,
    /// Yaw at the end, radians.
    pub yaw: f64,
    /// Gimbal pitch at the end, degrees.
    pub gimbal_pitch_deg: f64,
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum State {
    Waiting,
    Flying,
    Done,
}

/// A running script.
#[derive(Debug, Clone)]
pub struct Script {
    params: ScriptParams,
    kind: ScriptKind,
    legs: Vec<Leg>,
    laps: usize,
    idx: usize,
    leg_from: Vector3<f64>,
    yaw_from: f64,
    pitch_from: f64,
    state: State,
}

impl Script {
    /// Build a script. `clearance(x, y, r)` is the height (m, positive up)
    /// of the tallest obstacle within `r` of ground point (x, y).
    pub fn new(
        kind: ScriptKind,
        params: ScriptParams,
        clearance: &dyn Fn(f64, f64, f64) -> f64,
    ) -> Self {
        let legs = match kind {
            ScriptKind::Hover => {
                let alt = params
                    .hover_alt_m
                    .max(clearance(0.0, 0.0, params.clearance_radius_m) + params.clearance_m);
                vec![Leg {
                    to: Vector3::new(0.0, 0.0, -alt),
                    yaw: 0.0,
                    gimbal_pitch_deg: params.hover_gimbal_pitch_deg,
                }]
            }
            ScriptKind::Explore | ScriptKind::Patrol => Self::explore_legs(&params, clearance),
        };
        Self {
            params,
            kind,
            legs,
            laps: 0,
            idx: 0,
            leg_from: Vector3::zeros(),
            yaw_from: 0.0,
            pitch_from: 0.0,
            state: State::Waiting,
        }
    }

    fn explore_legs(p: &ScriptParams, clearance: &dyn Fn(f64, f64, f64) -> f64) -> Vec<Leg> {
        let h = p.half_extent_m;
        let mut legs = Vec::new();
        // Straight up over home first.
        let first = p.levels.first().copied().unwrap_or(Level {
            alt_m: p.hover_alt_m,
            gimbal_pitch_deg: p.hover_gimbal_pitch_deg,
            yaw_deg: 0.0,
        });
        let safe_alt = |x: f64, y: f64, alt: f64| {
            alt.max(clearance(x, y, p.clearance_radius_m) + p.clearance_m)
        };
        let climb = safe_alt(0.0, 0.0, first.alt_m);
        legs.push(Leg {
            to: Vector3::new(0.0, 0.0, -climb),
            yaw: first.yaw_deg.to_radians(),
            gimbal_pitch_deg: first.gimbal_pitch_deg,
        });
        let passes = p.passes.max(2);
        // The route after the climb: the lawn-mower corners of each level,
        // then a last point west of home looking down at the scene.
        let mut corners: Vec<((f64, f64), Level)> = Vec::new();
        for (li, level) in p.levels.iter().enumerate() {
            // Alternate the sweep direction per level: passes run east-west
            // on even levels, north-south on odd ones.
            let mut pts = Vec::new();
            for k in 0..passes {
                let a = -h + 2.0 * h * k as f64 / (passes - 1) as f64;
                let (s, e) = if k % 2 == 0 { (-h, h) } else { (h, -h) };
                if li % 2 == 0 {
                    pts.push((a, s));
                    pts.push((a, e));
                } else {
                    pts.push((s, a));
                    pts.push((e, a));
                }
            }
            if li % 2 == 1 {
                pts.reverse();
            }
            corners.extend(pts.into_iter().map(|q| (q, *level)));
        }
        let last = p.levels.last().copied().unwrap_or(first);
        corners.push((
            (-h * 0.5, 0.0),
            Level {
                gimbal_pitch_deg: -45.0,
                yaw_deg: 0.0,
                ..last
            },
        ));
        // Cut the route into segments of about `segment_m`. Each segment
        // flies at its level's altitude unless a roof near it needs more;
        // a point's altitude also covers the next segment, so the vehicle
        // climbs before it reaches a building and descends after it.
        let mut pts: Vec<((f64, f64), Level)> = vec![((0.0, 0.0), first)];
        for &(c, level) in &corners {
            let Some(&(prev, _)) = pts.last() else { break };
            let len = (c.0 - prev.0).hypot(c.1 - prev.1);
            let n = ((len / p.segment_m).ceil() as usize).max(1);
            for i in 1..=n {
                let f = i as f64 / n as f64;
                pts.push((
                    (prev.0 + (c.0 - prev.0) * f, prev.1 + (c.1 - prev.1) * f),
                    level,
                ));
            }
        }
        let seg_alt = |i: usize| -> f64 {
            let (a, level) = pts[i - 1];
            let (b, _) = pts[i];
            let mid = ((a.0 + b.0) / 2.0, (a.1 + b.1) / 2.0);
            [a, mid, b]
                .iter()
                .map(|q| safe_alt(q.0, q.1, level.alt_m))
                .fold(level.alt_m, f64::max)
        };
        let n = pts.len();
        for (i, &(q, level)) in pts.iter().enumerate().skip(1) {
            let mut alt = seg_alt(i);
            if i + 1 < n {
                alt = alt.max(seg_alt(i + 1));
            }
            legs.push(Leg {
                to: Vector3::new(q.0, q.1, -alt),
                yaw: level.yaw_deg.to_radians(),
                gimbal_pitch_deg: level.gimbal_pitch_deg,
            });
        }
        // The climb over home also clears the first segment.
        if n > 1
            && let Some(l0) = legs.first_mut()
        {
            l0.to.z = l0.to.z.min(-seg_alt(1));
        }
        legs
    }

    /// The legs flown.
    pub fn legs(&self) -> &[Leg] {
        &self.legs
    }

    /// Total path length, m.
    pub fn length_m(&self) -> f64 {
        let mut from = Vector3::zeros();
        let mut total = 0.0;
        for l in &self.legs {
            total += (l.to - from).norm();
            from = l.to;
        }
        total
    }

    /// True once the script has handed the vehicle over (finished or
    /// interrupted by the operator).
    pub fn finished(&self) -> bool {
        self.state == State::Done
    }

    /// Index of the leg being flown.
    pub fn leg_index(&self) -> usize {
        self.idx
    }

    /// Laps of the route completed (`patrol` starts the next one over
    /// home; the others finish after one).
    pub fn laps(&self) -> usize {
        self.laps
    }

    /// Advance the script at sim time `now`.
    pub fn step(&mut self, ap: &mut Autopilot, now: f64) {
        match self.state {
            State::Done => {}
            State::Waiting => {
                // The camera starts pitched as the first leg wants it, so
                // the video never shows the gimbal turning on the spot.
                if let Some(first) = self.legs.first() {
                    let pitch = first.gimbal_pitch_deg;
                    if (ap.vehicle().gimbal_angles().0.to_degrees() - pitch).abs() > 1e-6 {
                        ap.vehicle_mut().snap_gimbal(pitch, 0.0);
                    }
                }
                if now < self.params.start_delay_s {
                    return;
                }
                let v = ap.vehicle();
                self.leg_from = v.p_ned();
                self.yaw_from = v.yaw();
                self.pitch_from = v.gimbal_angles().0.to_degrees();
                ap.set_external_setpoint(Some(Setpoint::Position {
                    p_ned: self.leg_from,
                    yaw: Some(self.yaw_from),
                    max_speed: Some(self.params.speed),
                }));
                ap.set_mode(Mode::Offboard);
                if !ap.arm() {
                    // Already flying (or refused): hand over.
                    ap.set_external_setpoint(None);
                    self.state = State::Done;
                    return;
                }
                self.state = State::Flying;
            }
            State::Flying => {
                if ap.mode() != Mode::Offboard || !ap.armed() {
                    // The operator took over.
                    ap.set_external_setpoint(None);
                    self.state = State::Done;
                    return;
                }
                let p = ap.vehicle().p_ned();
                let Some(leg) = self.legs.get(self.idx).copied() else {
                    self.finish(ap);
                    return;
                };
                if (leg.to - p).norm() <= self.params.leg_tolerance_m {
                    self.idx += 1;
                    self.leg_from = leg.to;
                    self.yaw_from = leg.yaw;
                    self.pitch_from = leg.gimbal_pitch_deg;
                    if self.idx >= self.legs.len() {
                        self.laps += 1;
                        if self.kind == ScriptKind::Patrol {
                            // Back over home (the first leg ends there at
                            // the climb's altitude) and round again.
                            self.idx = 0;
                        } else {
                            self.finish(ap);
                        }
                    }
                    return;
                }
                // Progress along the leg drives yaw and gimbal pitch.
                let span = (leg.to - self.leg_from).norm();
                let frac = if span > 1e-6 {
                    ((p - self.leg_from).dot(&(leg.to - self.leg_from)) / (span * span))
                        .clamp(0.0, 1.0)
                } else {
                    1.0
                };
                let yaw = wrap_pi(self.yaw_from + wrap_pi(leg.yaw - self.yaw_from) * frac);
                let pitch = self.pitch_from + (leg.gimbal_pitch_deg - self.pitch_from) * frac;
                ap.set_gimbal(pitch, 0.0);
                ap.set_external_setpoint(Some(Setpoint::Position {
                    p_ned: leg.to,
                    yaw: Some(yaw),
                    max_speed: Some(self.params.speed),
                }));
            }
        }
    }

    fn finish(&mut self, ap: &mut Autopilot) {
        ap.set_external_setpoint(None);
        ap.set_mode(Mode::Hold);
        self.state = State::Done;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::autopilot::AutopilotParams;

    type Trace = Vec<(f64, Vector3<f64>, f64, f64)>;

    fn fly(kind: ScriptKind, params: ScriptParams, seconds: f64) -> (Autopilot, Script, Trace) {
        let mut ap = Autopilot::new(AutopilotParams::default(), 0.0);
        let mut s = Script::new(kind, params, &|x, y, _r| {
            if x.abs() < 5.0 && y.abs() < 5.0 {
                15.0
            } else {
                0.0
            }
        });
        let dt = 0.02;
        let mut t = 0.0;
        let mut trace = Vec::new();
        while t < seconds {
            t += dt;
            s.step(&mut ap, t);
            ap.step(t, dt);
            let v = ap.vehicle();
            trace.push((t, v.p_ned(), v.yaw(), v.gimbal_angles().0));
            if s.finished() {
                break;
            }
        }
        (ap, s, trace)
    }

    #[test]
    fn patrol_flies_the_survey_lap_after_lap_until_the_operator_takes_over() {
        let (_, explore, trace) = fly(ScriptKind::Explore, ScriptParams::default(), 900.0);
        assert!(explore.finished());
        let lap_s = trace.last().map_or(0.0, |t| t.0);
        let (mut ap, mut s, trace) = fly(ScriptKind::Patrol, ScriptParams::default(), 2.5 * lap_s);
        assert!(!s.finished(), "patrol never hands over by itself");
        assert_eq!(s.laps(), 2, "two laps in 2.5 lap times");
        assert_eq!(s.legs(), explore.legs(), "the same route as explore");
        // The second lap passes over the first lap's corners again.
        let near = |p: &Vector3<f64>, from: f64, to: f64| {
            trace
                .iter()
                .filter(|x| x.0 >= from && x.0 < to)
                .map(|x| (x.1 - p).norm())
                .fold(f64::INFINITY, f64::min)
        };
        for leg in s.legs().iter().step_by(7) {
            assert!(near(&leg.to, 0.0, lap_s) < 1.0);
            assert!(near(&leg.to, lap_s, 2.5 * lap_s) < 1.0, "{:?}", leg.to);
        }
        // The operator takes over: the script lets go at once.
        ap.set_mode(Mode::Hold);
        s.step(&mut ap, 2.5 * lap_s + 0.02);
        assert!(s.finished());
    }

    #[test]
    fn explore_translates_at_several_altitudes_without_turning_on_the_spot() {
        let (ap, s, trace) = fly(ScriptKind::Explore, ScriptParams::default(), 900.0);
        assert!(
            s.finished(),
            "not finished after 900 s, leg {}",
            s.leg_index()
        );
        assert_eq!(ap.mode(), Mode::Hold);
        assert!(ap.armed() && !ap.vehicle().landed());
        // Covers the square and three altitude bands.
        let max_n = trace.iter().map(|t| t.1.x).fold(f64::MIN, f64::max);
        let min_e = trace.iter().map(|t| t.1.y).fold(f64::MAX, f64::min);
        assert!(max_n > 29.0 && min_e < -29.0);
        for alt in [12.0, 22.0, 35.0] {
            let near = trace.iter().filter(|t| (-t.1.z - alt).abs() < 0.5).count();
            assert!(near > 500, "little time near {alt} m: {near}");
        }
        // The climb over home clears the 15 m building there.
        assert!(trace.iter().all(|t| !(t.1.x.abs() < 4.0
            && t.1.y.abs() < 4.0
            && t.1.x.hypot(t.1.y) > 0.1
            && -t.1.z > 2.0
            && -t.1.z < 15.0)
            || t.0 < 20.0));
        // No pure rotation: whenever yaw changes faster than 5 deg/s, the
        // vehicle moves at more than 0.5 m/s.
        for w in trace.windows(2) {
            let dt = w[1].0 - w[0].0;
            let yaw_rate = wrap_pi(w[1].2 - w[0].2).abs() / dt;
            let speed = (w[1].1 - w[0].1).norm() / dt;
            if yaw_rate > 5f64.to_radians() {
                assert!(
                    speed > 0.5,
                    "rotation at {:.1} s with speed {speed}",
                    w[0].0
                );
            }
        }
        // Camera pitched down throughout.
        assert!(trace.iter().all(|t| t.3.to_degrees() < -30.0));
        assert!(s.length_m() > 400.0);
    }

    #[test]
    fn hover_climbs_and_holds() {
        let (ap, s, trace) = fly(
            ScriptKind::Hover,
            ScriptParams {
                hover_alt_m: 8.0,
                ..Default::default()
            },
            60.0,
        );
        assert!(s.finished());
        let p = ap.vehicle().p_ned();
        // The 15 m building over home raises the hover height to 20 m.
        assert!((p.z + 20.0).abs() < 0.6, "{p}");
        assert_eq!(ap.mode(), Mode::Hold);
        assert!(
            trace
                .last()
                .is_some_and(|t| (t.3.to_degrees() + 30.0).abs() < 1.0)
        );
    }

    #[test]
    fn operator_mode_change_stops_the_script() {
        let mut ap = Autopilot::new(AutopilotParams::default(), 0.0);
        let mut s = Script::new(ScriptKind::Explore, ScriptParams::default(), &|_, _, _| 0.0);
        let dt = 0.02;
        let mut t = 0.0;
        while t < 15.0 {
            t += dt;
            s.step(&mut ap, t);
            ap.step(t, dt);
        }
        assert!(!s.finished());
        ap.set_mode(Mode::Hold);
        s.step(&mut ap, t + dt);
        assert!(s.finished());
        assert_eq!(ap.mode(), Mode::Hold);
    }

    /// In the default world the survey keeps clear of every roof and still
    /// spends time low over open ground.
    #[test]
    fn explore_clears_the_roofs_of_the_default_world() {
        let world = crate::world::World::generate(1);
        let mut ap = Autopilot::new(AutopilotParams::default(), 0.0);
        let mut s = Script::new(ScriptKind::Explore, ScriptParams::default(), &|x, y, r| {
            world.max_height_near(x, y, r)
        });
        let (dt, mut t) = (0.02, 0.0);
        let mut min_margin = f64::INFINITY;
        let mut low = 0usize;
        while t < 900.0 && !s.finished() {
            t += dt;
            s.step(&mut ap, t);
            ap.step(t, dt);
            let p = ap.vehicle().p_ned();
            let roof = world.max_height_near(p.x, p.y, 1.0);
            if roof > 0.0 {
                min_margin = min_margin.min(-p.z - roof);
            }
            if -p.z < 16.0 && -p.z > 10.0 {
                low += 1;
            }
        }
        assert!(s.finished());
        eprintln!(
            "explore: {t:.0} s, {:.0} m path, closest roof {min_margin:.2} m, {:.0} s below 16 m",
            s.length_m(),
            low as f64 * dt
        );
        assert!(min_margin > 2.0, "came within {min_margin} m of a roof");
        assert!(
            low as f64 * dt > 20.0,
            "only {} s below 16 m",
            low as f64 * dt
        );
    }
}
