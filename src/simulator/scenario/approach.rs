//! A leg flown as the daemon flies it: to the waypoint until the view is
//! steady, and meanwhile, with a georeference that follows the GNSS drift
//! (`sim.geo`), live frames localised and paired with telemetry every
//! half second (as the daemon's tracking pairs its frames) and the target
//! converted again with the refitted georeference each period, flown
//! instead when it moved beyond a fit's noise
//! ([`crate::refine::approach`]).

use nalgebra::Isometry3;

use shotpilot_sim::autopilot::Mode;

use crate::geo::{GeoAlignment, convert_target};
use crate::mission::plan::{self, Flavour};
use crate::refine::{Approach, ArrivalDetector, Session, Shift, Verdict};

use super::error::FlightError;
use super::explore::Explored;
use super::localise::{PAIR_SPACING_S, pair_live_frame};
use super::params::ScenarioParams;
use super::sim::Sim;

/// Flies the session's target (waypoint `wp`, uploaded) until the view is
/// steady; re-targets on the approach (`params.refine.approach`) when the
/// georeference follows the drift, replacing `alignment` by the fit the
/// flown target was converted with. The flight's time, s.
pub(super) fn fly_leg(
    sim: &mut Sim,
    session: &mut Session,
    ex: &Explored,
    params: &ScenarioParams,
    mut wp: u16,
    alignment: &mut GeoAlignment,
) -> Result<f64, FlightError> {
    let t0 = sim.t;
    let steady = &params.steady;
    let arrival = &params.refine.arrival;
    let retargeting = sim.geo.is_some() && params.refine.approach.enabled;
    let mut rule = Approach::new(params.refine.approach, t0, session.rounds().is_empty());
    let mut det = ArrivalDetector::new(*arrival, wp, session.target().gimbal_pitch_deg);
    let mut next_pair = t0 + PAIR_SPACING_S;
    while sim.t - t0 < steady.max_flight_s {
        sim.step_fed();
        if let Some(seq) = sim.reached.take() {
            det.on_reached(seq);
        }
        let v = sim.ap.vehicle();
        let pitch = v.gimbal_angles().0.to_degrees();
        if det.update(sim.t, v.v_ned().norm(), pitch) {
            return Ok(sim.t - t0);
        }
        if !retargeting || sim.t + 0.5 * sim.dt < next_pair {
            continue;
        }
        next_pair += PAIR_SPACING_S;
        pair_live_frame(ex, sim, params);
        if !rule.due(sim.t) {
            continue;
        }
        let Some(fresh) = refit_target(sim, session, ex, params, alignment) else {
            continue;
        };
        let (a, shift) = fresh;
        if let Verdict::Fly(shift) = rule.judge(sim.t, shift) {
            let target = shift.apply(session.target(), &ex.frame, &sim.home);
            let items = match plan::plan(&target, &sim.home, Flavour::Px4, &params.plan) {
                Ok(i) => i,
                Err(e) => {
                    tracing::debug!("scenario: re-target refused by the planner: {e}");
                    continue;
                }
            };
            let Some(new_wp) = plan::waypoint_seq(&items) else {
                continue;
            };
            sim.upload(&items)?;
            if sim.ap.mode() != Mode::Mission {
                sim.ap.set_mode(Mode::Mission);
            }
            wp = new_wp;
            det = ArrivalDetector::new(*arrival, wp, target.gimbal_pitch_deg);
            session.retarget(target, shift);
            *alignment = a;
        }
    }
    Err(FlightError::NoArrival {
        waypoint: wp,
        waited_s: steady.max_flight_s,
    })
}

/// The georeference refitted with what it has been given, and the move
/// it makes to the shot's target: the desired pose converted with it
/// against the same pose converted with `flown_with`, the fit the flown
/// target relates to.
fn refit_target(
    sim: &mut Sim,
    session: &Session,
    ex: &Explored,
    params: &ScenarioParams,
    flown_with: &GeoAlignment,
) -> Option<(GeoAlignment, Shift)> {
    let g = sim.geo.as_mut()?;
    g.retry_pending();
    let a = g
        .fit()
        .map_err(|e| tracing::debug!("scenario: refit in flight refused: {e}"))
        .ok()?;
    let goal: &Isometry3<f64> = session.map_from_desired();
    let convert = |al: &GeoAlignment| {
        convert_target(al, goal, &ex.frame, &params.geo.mount)
            .map_err(|e| tracing::debug!("scenario: re-target not converted: {e}"))
            .ok()
            .map(|t| t.to_mission_target(false))
    };
    let shift = Shift::between(&convert(flown_with)?, &convert(&a)?, &ex.frame, &sim.home);
    Some((a, shift))
}
