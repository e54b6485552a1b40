//! One trial: the desired shot localised and converted to a vehicle target,
//! then planned, uploaded and flown, measured on arrival and corrected
//! until the loop stops; the trial's report with the judge's figures.

use std::time::Instant;

use nalgebra::Vector3;
use rand::rngs::SmallRng;

use shotpilot_sim::autopilot::Mode;

use crate::geo::{GeoAlignment, convert_target};
use crate::mission::plan::{self, Flavour};
use crate::refine::{Context, LiveFrame, Session, Step, Stop, pose_difference};

use super::approach::fly_leg;
use super::explore::Explored;
use super::hidden::make_hidden;
use super::localise::{PAIR_SPACING_S, localise, pair_live_frame};
use super::params::ScenarioParams;
use super::report::{RoundReport, TrialReport};
use super::servo::servo_at_shot;
use super::sim::Sim;

/// Live frames localised and paired with telemetry in the hover before a
/// departure.
const DEPARTURE_FRAMES: usize = 3;

/// The georeference a trial's shot is flown with: with a drift model
/// ([`crate::geo::AlignParams::drift`]), the kept one, given the live frames
/// localised in a short hover where the vehicle is (as the daemon's
/// tracking pairs its frames) and refitted; else, or when the refit is
/// refused, the explore's fit. Also the frame pairs added, and how many of
/// them the fit took as inliers.
fn current_alignment(
    ex: &Explored,
    sim: &mut Sim,
    params: &ScenarioParams,
) -> (GeoAlignment, usize, usize) {
    if sim.geo.is_none() {
        return (ex.alignment.clone(), 0, 0);
    }
    let mut ids = Vec::new();
    for i in 0..DEPARTURE_FRAMES {
        if i > 0 {
            sim.advance(PAIR_SPACING_S);
        }
        ids.extend(pair_live_frame(ex, sim, params));
    }
    // Telemetry past the last frame's time, so a pending pair is made.
    sim.advance(0.2);
    let paired = ids.len();
    let Some(g) = sim.geo.as_mut() else {
        return (ex.alignment.clone(), paired, 0);
    };
    g.retry_pending();
    match g.fit() {
        Ok(a) => {
            let inliers = ids.iter().filter(|id| a.inlier_ids.contains(id)).count();
            (a, paired, inliers)
        }
        Err(e) => {
            tracing::debug!("scenario: georeference refit refused ({e}); the explore's fit flies");
            (ex.alignment.clone(), paired, 0)
        }
    }
}

pub(super) fn run_trial(
    trial: usize,
    ex: &Explored,
    sim: &mut Sim,
    params: &ScenarioParams,
    rng: &mut SmallRng,
) -> TrialReport {
    let wall = Instant::now();
    let t0 = sim.t;
    let anchors = params.anchor_every > 0 && (trial + 1).is_multiple_of(params.anchor_every);
    let mut rep = TrialReport {
        trial,
        kind: if anchors { "anchors" } else { "render" },
        hidden_p_ned: [0.0; 3],
        hidden_yaw_deg: 0.0,
        hidden_pitch_deg: 0.0,
        flown: false,
        reason: None,
        desired_localisation_error_m: None,
        first_shot_error_pct: None,
        final_shot_error_pct: None,
        first_position_error_m: None,
        position_error_m: None,
        yaw_error_deg: None,
        pitch_error_deg: None,
        rounds: 0,
        stop: String::new(),
        sim_s: 0.0,
        wall_s: 0.0,
        inside_fence: true,
        round_reports: Vec::new(),
        arrival_to_photo_s: None,
        servo: None,
        departure_pairs: 0,
        departure_inliers: 0,
        gnss_bias_m: None,
        mount_offset: None,
        retargets: 0,
    };
    let finish = |mut rep: TrialReport, sim: &Sim, stop: String| {
        rep.stop = stop;
        rep.sim_s = sim.t - t0;
        rep.wall_s = wall.elapsed().as_secs_f64();
        rep.inside_fence = sim.fence_ok;
        rep
    };
    let Some(hidden) = make_hidden(ex, sim, params, anchors, rng) else {
        rep.reason = Some("no hidden pose could be made".into());
        return finish(rep, sim, "no_shot".into());
    };
    rep.kind = hidden.kind;
    rep.hidden_p_ned = hidden.p_ned.into();
    rep.hidden_yaw_deg = hidden.yaw.to_degrees();
    rep.hidden_pitch_deg = hidden.pitch.to_degrees();
    let mount = &params.geo.mount;
    let (mut alignment, departure_pairs, departure_inliers) = current_alignment(ex, sim, params);
    rep.departure_pairs = departure_pairs;
    rep.departure_inliers = departure_inliers;
    rep.gnss_bias_m = alignment.quality.gnss_bias_m;
    rep.mount_offset = alignment.mount_offset;
    let desired_map = match localise(
        &ex.map,
        &hidden.image,
        hidden.mask.as_ref(),
        hidden.anchors_on,
        params.anchors_by_matching,
        &params.localize,
    ) {
        Ok(p) => p,
        Err(e) => {
            rep.reason = Some(e.to_string());
            return finish(rep, sim, "not_localised".into());
        }
    };
    rep.desired_localisation_error_m = Some(
        (alignment.ned_from_cam(&desired_map).translation.vector
            - hidden.camera.translation.vector)
            .norm(),
    );
    let target = match convert_target(&alignment, &desired_map, &ex.frame, mount) {
        Ok(t) => t.to_mission_target(false),
        Err(e) => {
            rep.reason = Some(format!("no target: {e}"));
            return finish(rep, sim, "no_target".into());
        }
    };
    let flavour = Flavour::Px4;
    let cam_model = ex.map.camera;
    let mut session = Session::new(
        hidden.image.clone(),
        hidden.mask.clone(),
        desired_map,
        target,
        params.refine.clone(),
    );
    // An anchors shot knows its floor, as in the daemon.
    if let Some((id, h)) = hidden.anchors_on
        && let Ok(r) = crate::refine::reachable_from_anchors(
            &ex.map,
            crate::slam::KeyFrameId(id),
            &h,
            &desired_map,
            &params.refine.error,
        )
    {
        session = session.with_reachable(r);
    }
    let home = sim.home;
    sim.fence_ok = true;
    let mut first_arrival: Option<f64> = None;
    loop {
        let target = *session.target();
        let items = match plan::plan(&target, &sim.home, flavour, &params.plan) {
            Ok(i) => i,
            Err(e) => {
                rep.reason = Some(format!("plan refused: {e}"));
                return finish(rep, sim, "plan_refused".into());
            }
        };
        let Some(wp) = plan::waypoint_seq(&items) else {
            return finish(rep, sim, "no_waypoint".into());
        };
        if let Err(e) = sim.upload(&items) {
            rep.reason = Some(e.to_string());
            return finish(rep, sim, "upload_failed".into());
        }
        if sim.ap.mode() != Mode::Mission {
            sim.ap.set_mode(Mode::Mission);
        }
        let _ = sim.ap.arm();
        let flight_s = match fly_leg(sim, &mut session, ex, params, wp, &mut alignment) {
            Ok(s) => s,
            Err(e) => {
                rep.reason = Some(e.to_string());
                return finish(rep, sim, "not_arrived".into());
            }
        };
        rep.flown = true;
        rep.retargets = session.retargets().len();
        let target = *session.target();
        let ctx = Context {
            map: &ex.map,
            alignment: &alignment,
            frame: &ex.frame,
            mount,
            home: &home,
            fence: &params.plan.fence,
            localize: &params.localize,
        };
        let arrived_at = *first_arrival.get_or_insert(sim.t);
        // The measurement: a few frames a little apart, each with the
        // position the vehicle reports then (and the judge's pose error).
        let m = params.refine.measure;
        let mut images = Vec::new();
        let mut reported = Vec::new();
        let mut judged = Vec::new();
        let mut true_offset = Vector3::zeros();
        for i in 0..m.frames.max(1) {
            if i > 0 {
                sim.advance(m.spacing_s);
            }
            judged.push(pose_difference(&hidden.camera, &sim.true_camera()));
            true_offset += sim.ap.vehicle().position_error() / m.frames.max(1) as f64;
            images.push(sim.render());
            reported.push(sim.ap.vehicle().p_ned());
        }
        let frames: Vec<LiveFrame<'_>> = images
            .iter()
            .zip(&reported)
            .map(|(image, r)| LiveFrame {
                image,
                reported_ned_m: Some(*r),
            })
            .collect();
        let step = session.on_arrival(&frames, sim.t, Some(&cam_model), &ctx);
        let Some(record) = session.rounds().last().cloned() else {
            return finish(rep, sim, "no_round".into());
        };
        let judge = |f: &dyn Fn(&crate::refine::PoseDifference) -> f64| {
            crate::stats::finite_median(&judged.iter().map(f).collect::<Vec<_>>())
                .unwrap_or(f64::NAN)
        };
        let (position_m, yaw_deg, pitch_deg, rotation_deg) = (
            judge(&|d| d.position_m),
            judge(&|d| d.yaw_deg),
            judge(&|d| d.pitch_deg),
            judge(&|d| d.rotation_deg),
        );
        if record.round == 0 {
            rep.first_shot_error_pct = record.shot_error_pct;
            rep.first_position_error_m = Some(position_m);
        }
        rep.final_shot_error_pct = record.shot_error_pct;
        rep.position_error_m = Some(position_m);
        rep.yaw_error_deg = Some(yaw_deg);
        rep.pitch_error_deg = Some(pitch_deg);
        rep.rounds = record.round;
        rep.round_reports.push(RoundReport {
            record,
            position_error_m: position_m,
            yaw_error_deg: yaw_deg,
            pitch_error_deg: pitch_deg,
            rotation_error_deg: rotation_deg,
            true_offset_ned_m: true_offset.into(),
            flight_s,
        });
        rep.arrival_to_photo_s = Some(sim.t - arrived_at);
        // Servoing takes over from a short correction, or from a loop that
        // stopped above the servo's threshold for want of a better look.
        if let Some(sp) = &params.servo {
            let servo_now = crate::refine::servo::takes_over(
                &step,
                rep.final_shot_error_pct,
                &target,
                &sim.home,
                &sp.servo,
            );
            if servo_now {
                let (report, judged) =
                    servo_at_shot(sim, &session, target, &ctx, &cam_model, &hidden.camera, sp);
                let stop = format!("servo_{}", report.stop);
                if let Some(d) = judged {
                    rep.final_shot_error_pct = report.photo_shot_error_pct;
                    rep.position_error_m = Some(d.position_m);
                    rep.yaw_error_deg = Some(d.yaw_deg);
                    rep.pitch_error_deg = Some(d.pitch_deg);
                } else {
                    rep.reason = report.reason.clone();
                }
                rep.arrival_to_photo_s = Some(sim.t - arrived_at);
                rep.servo = Some(report);
                return finish(rep, sim, stop);
            }
        }
        if let Step::Done(stop) = step {
            if let Stop::LiveNotLocalised(r) | Stop::CorrectionRefused(r) = &stop {
                rep.reason = Some(r.clone());
            }
            return finish(rep, sim, stop.name().into());
        }
    }
}
