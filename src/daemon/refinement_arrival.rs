//! The refinement's flight to a target: the vehicle's telemetry polled
//! for the arrival ([`ArrivalDetector`]: waypoint reached near the
//! target, still, gimbal at its pitch, for a dwell), the `flying` events on
//! the way and, on the flight to the shot, re-targeting on the approach
//! ([`crate::refine::approach`]): the shot converted again with the
//! georeference refitted in flight, the moved target handed back to the
//! task (`refinement_task.rs`) to upload.

use std::time::{Duration, Instant};

use super::refinement_deps::{Abort, Deps, position_report};
use crate::api::ShotEvent;
use crate::geo::{GeoAlignment, Geodetic, LocalFrame};
use crate::mission::plan::{Home, Target};
use crate::refine::arrival::waypoint_passed;
use crate::refine::{Approach, ArrivalDetector, Distance, Session, Shift, Verdict};

/// How often a `flying` event is published at most.
const FLYING_PERIOD: Duration = Duration::from_secs(1);

/// The `flying` event of `round` at distance `d`, whose flight began
/// `start_m` away. The distance shown is the straight line: a correction
/// that is mostly vertical (a GNSS altitude bias) is not "0.0 m" away.
fn flying_event(d: &Distance, round: usize, start_m: f64) -> ShotEvent {
    ShotEvent::Flying {
        round,
        distance_m: d.straight(),
        horizontal_m: d.horizontal,
        vertical_m: d.vertical,
        start_m,
    }
}

/// Waits for the vehicle to reach waypoint `wp` of the mission flying
/// `target` and hold still with the gimbal at the target's pitch.
///
/// The waypoint counts as reached when the vehicle reports it (or reports
/// a later item, or the mission complete) *and* its position is within the
/// planner's acceptance radius of the target: the last reached item stays
/// in the telemetry from the previous flight, and an upload to a vehicle
/// in mission mode restarts the mission at once, so the report alone may
/// be stale or already past. Returns the arrival time.
pub(super) async fn wait_arrival(
    deps: &Deps,
    wp: u16,
    (session, home, flown_with): (&Session, &Home, Option<&GeoAlignment>),
    approach: &mut Approach,
    (shot, round): (&str, usize),
) -> Result<Leg, Abort> {
    let target = session.target();
    let p = &deps.params;
    let tel = &deps.link.telemetry;
    let mut det = ArrivalDetector::new(p.refine.arrival, wp, target.gimbal_pitch_deg);
    let t0 = crate::clock::now();
    let radius = f64::from(deps.plan.acceptance_radius_m).max(0.1);
    let mut tick = tokio::time::interval(p.poll);
    let mut last_flying: Option<Instant> = None;
    // The distance at this round's first report.
    let mut start_m: Option<f64> = None;
    loop {
        tick.tick().await;
        if crate::clock::since(t0) > p.max_flight {
            return Err(Abort::NoArrival {
                waypoint: wp,
                waited_s: p.max_flight.as_secs_f64(),
            });
        }
        let fresh = |r: Instant| crate::clock::since(r) <= p.max_telemetry_age;
        let passed = (*tel.progress.borrow())
            .is_some_and(|pr| waypoint_passed(pr.value.last_reached, pr.value.state, wp));
        let gp = (*tel.global_position.borrow())
            .filter(|g| fresh(g.received))
            .map(|g| position_report(&g));
        let dist = gp.map(|g| g.distance_to(target));
        let near = dist.is_some_and(|d| d.within(radius));
        if let Some(d) = dist
            && d.straight().is_finite()
            && last_flying.is_none_or(|t| crate::clock::since(t) >= FLYING_PERIOD)
        {
            last_flying = Some(crate::clock::now());
            let start_m = *start_m.get_or_insert(d.straight());
            deps.events.publish(shot, flying_event(&d, round, start_m));
        }
        let speed = gp.map_or(f64::NAN, |g| g.speed_m_s());
        let pitch = (*tel.gimbal.borrow())
            .filter(|g| fresh(g.received))
            .map_or(f64::NAN, |g| f64::from(g.value.pitch_deg));
        if det.poll(
            crate::clock::since(t0).as_secs_f64(),
            passed,
            near,
            speed,
            pitch,
        ) {
            return Ok(Leg::Arrived(crate::clock::now()));
        }
        let now_s = seconds_since(deps, crate::clock::now());
        if approach.due(now_s)
            && let Some(r) = refitted_target(deps, session, home, flown_with)
            && let Verdict::Fly(shift) = approach.judge(now_s, r.shift)
        {
            return Ok(Leg::Retarget(Box::new(Retarget { shift, ..r })));
        }
    }
}

/// How a wait for the arrival ended.
pub(super) enum Leg {
    /// Arrived, at this time.
    Arrived(Instant),
    /// The georeference refitted in flight moved the target: fly this one.
    Retarget(Box<Retarget>),
}

/// A target moved by the georeference refitted in flight.
pub(super) struct Retarget {
    /// The moved target.
    pub(super) target: Target,
    /// Its move from the one flown.
    pub(super) shift: Shift,
    /// The fit it was converted with.
    pub(super) alignment: GeoAlignment,
}

/// Seconds from the daemon's epoch to `t`.
pub(super) fn seconds_since(deps: &Deps, t: Instant) -> f64 {
    t.checked_duration_since(deps.epoch)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// The georeference refitted with the pairs it has now, and the move it
/// makes to the flown target: the desired pose converted with it against
/// the same pose converted with `flown_with`, the fit of the last
/// re-target; before the first, against the flown target itself. None when the refit is
/// refused (logged at debug: the flown target stands).
fn refitted_target(
    deps: &Deps,
    session: &Session,
    home: &Home,
    flown_with: Option<&GeoAlignment>,
) -> Option<Retarget> {
    let goal = session.map_from_desired();
    let (fresh, alignment) = deps
        .geo
        .target(goal)
        .map_err(|e| tracing::debug!("refinement: refit in flight refused: {e}"))
        .ok()?;
    let frame = LocalFrame::new(Geodetic {
        lat_deg: home.lat_deg,
        lon_deg: home.lon_deg,
        alt_m: home.alt_amsl_m,
    });
    let flown = session.target();
    let before = match flown_with {
        Some(a) => crate::geo::convert_target(a, goal, &frame, &deps.geo.params().mount)
            .map_err(|e| tracing::debug!("refinement: flown target not converted again: {e}"))
            .ok()?
            .to_mission_target(flown.photo),
        None => *flown,
    };
    let fresh = fresh.to_mission_target(flown.photo);
    let shift = Shift::between(&before, &fresh, &frame, home);
    Some(Retarget {
        target: shift.apply(flown, &frame, home),
        shift,
        alignment,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

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

    /// A correction of 0.6 m straight up (a GNSS altitude bias), seen as
    /// the correction's flight begins with the vehicle where the last
    /// round measured: the timeline said "flying, 0.0 m to the target"
    /// (the horizontal part only); the event's distance is 0.6 m.
    #[test]
    fn a_vertical_correction_is_flown_its_length() {
        let here = target();
        let next = Target {
            alt_m: here.alt_m + 0.6,
            ..here
        };
        let d = Distance::to(&next, here.lat_deg, here.lon_deg, here.alt_m);
        assert!(d.within(1.0), "inside the acceptance radius");
        match flying_event(&d, 1, d.straight()) {
            ShotEvent::Flying {
                round,
                distance_m,
                horizontal_m,
                vertical_m,
                start_m,
            } => {
                assert_eq!(round, 1);
                assert!((distance_m - 0.6).abs() < 1e-9, "{distance_m}");
                assert!(horizontal_m < 1e-9, "{horizontal_m}");
                assert!((vertical_m - 0.6).abs() < 1e-9, "climb 0.6 m: {vertical_m}");
                assert_eq!(start_m, distance_m);
            }
            e => panic!("{e:?}"),
        }
        // Half way up: 0.3 m to go of a 0.6 m flight.
        let d = Distance::to(&next, here.lat_deg, here.lon_deg, here.alt_m + 0.3);
        let json = serde_json::to_value(flying_event(&d, 1, 0.6)).unwrap();
        assert!(
            (json["distance_m"].as_f64().unwrap() - 0.3).abs() < 1e-9,
            "{json}"
        );
        assert_eq!(json["start_m"], 0.6);
        assert_eq!(json["kind"], "flying");
    }
}
