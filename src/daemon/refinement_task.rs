//! The shot refinement's task (the loop itself is [`crate::refine`]):
//! once a shot's mission is started
//! (`POST /api/v1/shots/{id}/start`), watch the vehicle's telemetry with
//! [`ArrivalDetector`] (waypoint reached, ground speed, gimbal pitch, dwell);
//! on arrival run [`Session::on_arrival`] (on a blocking thread) with a few
//! video frames received after it ([`crate::refine::MeasureParams`], each
//! with the position the vehicle reported then), a snapshot of the SLAM map
//! and the georeference;
//! when the session asks for a correction, plan, upload (read back) and
//! start the corrected target like the first one; record each round on the
//! shot, with what the vehicle reported and the frame's timing
//! ([`Observation`]). An anchors shot carries its reachable framing
//! ([`crate::refine::reachable`], made with its desired picture while the
//! keyframe is in the map), so a zoom no camera pose reproduces stops
//! `at_floor` instead of spending its rounds. It stops on convergence, the
//! floor, the round budget or a refusal, and is cancelled by the daemon's
//! shutdown or when another shot is uploaded or started.
//!
//! While the vehicle flies to the shot (the first leg), the target is converted again with the
//! georeference refitted in flight about once a second and, when it moved
//! beyond a fit's noise, the moved target is uploaded and flown instead
//! ([`crate::refine::approach`], `[refine.approach]`): the GNSS bias keeps
//! wandering during the flight, and the pairs tracking makes on the way
//! follow it.
//!
//! It publishes the shot's progress as [`ShotEvent`]s (flying with the
//! distance to the target at most once a second, re-targeted, arrived,
//! each round, done), the desired shot's outline in the live frame about once a second
//! while it runs ([`OVERLAY_PERIOD`]), and keeps each round's live frame
//! for the before/after view ([`Achieved`]).

use std::sync::Arc;
use std::time::{Duration, Instant};

use image::GrayImage;
use nalgebra::{Isometry3, Vector3};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use super::geo_service::GeoService;
use super::refinement_arrival::{Leg, seconds_since, wait_arrival};
use crate::api::{Achieved, ShotEvent};
use crate::geo::{GeoAlignment, Geodetic, LocalFrame};
use crate::mission::plan::{self, Flavour, Home, Target, waypoint_seq};
use crate::refine::desired::{Picture, desired_picture};
use crate::refine::record::{interrupted, record_abort, record_rounds, record_stopped};
use crate::refine::round::{FrameTiming, Reports, observation, round_alignment};
use crate::refine::{
    Approach, Context, LiveFrame, Observation, Session, Step, outline_in_live, shot_error,
};
use crate::shot::record::Shot;
use crate::video::live::Frame;

pub use super::refinement_deps::{Abort, Deps, Params};
use super::refinement_deps::{position_report, reported_ned};

/// What the loop is told.
#[derive(Debug)]
enum Request {
    /// The shot's mission was started: refine it.
    Start(Box<(Shot, Target)>),
    /// Another mission replaces it: stop, and make this shot's desired
    /// picture now, while its keyframe is in the map.
    Stop(Box<Shot>),
    /// The operator stopped the vehicle: end the running loop, record it
    /// as stopped with the reason, and reply with the shot it refined.
    Halt {
        /// Why (shown on the shot).
        reason: String,
        /// The shot whose loop ran (None: none ran).
        reply: tokio::sync::oneshot::Sender<Option<String>>,
    },
}

/// The handle the vehicle view uses to start and stop the loop.
#[derive(Debug, Clone)]
pub struct RefineHandle {
    tx: mpsc::UnboundedSender<Request>,
}

impl RefineHandle {
    /// Refine `shot`, whose mission (flying `target`) was just started
    /// (stops any other).
    pub fn start(&self, shot: Shot, target: Target) {
        let _ = self.tx.send(Request::Start(Box::new((shot, target))));
    }

    /// `shot` is being uploaded: stop the running loop, if any, and keep
    /// the shot's desired picture (an anchors shot's keyframe may later
    /// leave the map).
    pub fn uploading(&self, shot: Shot) {
        let _ = self.tx.send(Request::Stop(Box::new(shot)));
    }

    /// The operator stops the vehicle: ends the running loop (it uploads
    /// and starts nothing more) and records its end as `stopped` with
    /// `reason`. Returns the shot whose loop ran, once it has ended and
    /// its record is written (None: no loop ran).
    pub async fn halt(&self, reason: String) -> Option<String> {
        let (reply, rx) = tokio::sync::oneshot::channel();
        self.tx.send(Request::Halt { reason, reply }).ok()?;
        rx.await.ok().flatten()
    }
}

/// How often the desired shot's outline in the live frame is measured
/// while a loop runs (one shot error: two ORB extractions and a RANSAC
/// homography, some 50 ms on one core).
pub const OVERLAY_PERIOD: Duration = Duration::from_secs(1);

/// Makes (or finds) the shot's desired picture and keeps it.
fn picture_of(deps: &Deps, shot: &Shot) -> Result<Picture, Abort> {
    if let Some(pic) = deps.pictures.get(&shot.id) {
        return Ok(pic);
    }
    let map = deps.slam.map_snapshot().ok_or(Abort::NoMap)?;
    let pic = desired_picture(&map, shot, &deps.params, || deps.store.image(&shot.id))?;
    deps.pictures.keep(&shot.id, pic.clone());
    Ok(pic)
}

/// Creates the handle and the loop's task body; run the future until
/// `cancel` fires.
pub fn spawn(deps: Deps, cancel: CancellationToken) -> (RefineHandle, tokio::task::JoinHandle<()>) {
    let (tx, rx) = mpsc::unbounded_channel();
    let task = tokio::spawn(run(Arc::new(deps), rx, cancel));
    (RefineHandle { tx }, task)
}

async fn run(deps: Arc<Deps>, mut rx: mpsc::UnboundedReceiver<Request>, cancel: CancellationToken) {
    let mut current: Option<(CancellationToken, tokio::task::JoinHandle<()>, String)> = None;
    loop {
        let req = tokio::select! {
            _ = cancel.cancelled() => break,
            r = rx.recv() => match r {
                Some(r) => r,
                None => break,
            },
        };
        let ended = match current.take() {
            Some((c, t, id)) => {
                let running = !t.is_finished();
                c.cancel();
                let _ = t.await;
                if running && !matches!(req, Request::Halt { .. }) {
                    deps.events.publish(
                        &id,
                        ShotEvent::Done {
                            stop: "aborted".into(),
                            reason: Some("another shot's mission replaced it".into()),
                        },
                    );
                }
                Some(id)
            }
            None => None,
        };
        if let Request::Halt { reason, reply } = req {
            if let Some(id) = &ended {
                mark_stopped(&deps, id, &reason).await;
            }
            let _ = reply.send(ended);
            continue;
        }
        if let Request::Stop(shot) = &req {
            let d = deps.clone();
            let shot = (**shot).clone();
            let made = tokio::task::spawn_blocking(move || picture_of(&d, &shot).map(|_| ()));
            if let Ok(Err(e)) = made.await {
                tracing::warn!("refinement: desired picture: {e}");
            }
        }
        if let Request::Start(start) = req {
            let (shot, target) = *start;
            let c = cancel.child_token();
            let d = deps.clone();
            let cc = c.clone();
            tracing::info!(shot = %shot.id, "refinement: started");
            let id = shot.id.clone();
            current = Some((
                c,
                tokio::spawn(async move { refine_shot(&d, shot, target, cc).await }),
                id,
            ));
        }
    }
    if let Some((c, t, id)) = current.take() {
        c.cancel();
        let _ = t.await;
        mark_interrupted(&deps, &id).await;
    }
}

/// The operator stopped `id`'s loop: the loop recorded itself as
/// cancelled (or had stopped on its own, which stays); the record says
/// `stopped`, with the operator's reason.
async fn mark_stopped(deps: &Deps, id: &str, reason: &str) {
    let (store, id, reason) = (deps.store.clone(), id.to_owned(), reason.to_owned());
    let write = move || {
        store.update(&id, |s| {
            if let Some(m) = s.mission.as_mut() {
                record_stopped(m, &reason);
            }
        })
    };
    match tokio::task::spawn_blocking(write).await {
        Ok(Ok(_)) => {}
        Ok(Err(e)) => tracing::warn!("refinement: saving the shot: {e}"),
        Err(e) => tracing::warn!("refinement: saving the shot: {e}"),
    }
}

/// The daemon stops while `id`'s loop runs: the loop recorded itself as
/// cancelled; the record says interrupted, and that it can be restarted.
async fn mark_interrupted(deps: &Deps, id: &str) {
    let Some(refinement) = deps
        .store
        .get(id)
        .and_then(|shot| interrupted(shot.mission.as_ref()?))
    else {
        return;
    };
    tracing::info!(shot = %id, "refinement: interrupted by the daemon's stop");
    let (store, id) = (deps.store.clone(), id.to_owned());
    let write = move || {
        store.update(&id, |s| {
            if let Some(m) = s.mission.as_mut() {
                m.set_detail("refinement", refinement);
            }
        })
    };
    match tokio::task::spawn_blocking(write).await {
        Ok(Ok(_)) => {}
        Ok(Err(e)) => tracing::warn!("refinement: saving the shot: {e}"),
        Err(e) => tracing::warn!("refinement: saving the shot: {e}"),
    }
}

/// Writes the session (and an abort reason, if any) into the stored shot.
async fn save_rounds(deps: &Deps, shot_id: &str, session: &Session, abort: Option<&Abort>) {
    let Some(mut shot) = deps.store.get(shot_id) else {
        tracing::warn!(shot = %shot_id, "refinement: the shot is gone");
        return;
    };
    let Some(m) = shot.mission.as_mut() else {
        tracing::warn!(shot = %shot_id, "refinement: the shot has no mission record");
        return;
    };
    record_rounds(m, session);
    if let Some(why) = abort {
        record_abort(m, &why.to_string());
        if !matches!(why, Abort::Cancelled) {
            deps.events.publish(
                shot_id,
                ShotEvent::Done {
                    stop: "aborted".into(),
                    reason: Some(why.to_string()),
                },
            );
        }
    }
    let t = session.target();
    m.target_lat_lon_alt = Some([
        t.lat_deg,
        t.lon_deg,
        m.target_lat_lon_alt.map_or(t.alt_m, |x| x[2]),
    ]);
    // Only what the loop owns is written back (its rounds and the target),
    // into the record as it is now: the reconciler may have changed the
    // mission state meanwhile.
    let refinement = m.details.get("refinement").cloned();
    let target = m.target_lat_lon_alt;
    let (store, id) = (deps.store.clone(), shot_id.to_owned());
    let write = move || {
        store.update(&id, |s| {
            if let Some(m) = s.mission.as_mut() {
                if let Some(r) = refinement {
                    m.set_detail("refinement", r);
                }
                m.target_lat_lon_alt = target;
            }
        })
    };
    match tokio::task::spawn_blocking(write).await {
        Ok(Ok(_)) => {}
        Ok(Err(e)) => tracing::warn!("refinement: saving the shot: {e}"),
        Err(e) => tracing::warn!("refinement: saving the shot: {e}"),
    }
}

fn home_of(geo: &GeoService) -> Option<Home> {
    geo.home().map(|h| Home {
        lat_deg: h.lat_deg,
        lon_deg: h.lon_deg,
        alt_amsl_m: h.alt_amsl_m,
    })
}

/// One shot's loop. Every failure ends it with a logged, recorded reason.
async fn refine_shot(deps: &Arc<Deps>, shot: Shot, first: Target, cancel: CancellationToken) {
    let id = shot.id.clone();
    let blank = Session::new(
        GrayImage::new(1, 1),
        None,
        Isometry3::identity(),
        Target {
            lat_deg: f64::NAN,
            lon_deg: f64::NAN,
            alt_m: f64::NAN,
            yaw_deg: f64::NAN,
            gimbal_pitch_deg: f64::NAN,
            photo: false,
        },
        deps.params.refine.clone(),
    );
    let mut session = match prepare(deps, &shot, first).await {
        Ok(s) => s,
        Err(why) => {
            tracing::warn!(shot = %id, "refinement: not started: {why}");
            save_rounds(deps, &id, &blank, Some(&why)).await;
            return;
        }
    };
    // The live outline, while this loop runs.
    let overlay_cancel = cancel.child_token();
    let _overlay_guard = overlay_cancel.clone().drop_guard();
    tokio::spawn(overlay_loop(deps.clone(), shot.clone(), overlay_cancel));
    let flavour = deps.link.telemetry.vehicle.borrow().flavour;
    let Some(flavour) = flavour else {
        save_rounds(deps, &id, &session, Some(&Abort::UnknownAutopilot)).await;
        return;
    };
    let Some(home) = home_of(&deps.geo) else {
        save_rounds(deps, &id, &session, Some(&Abort::NoHome)).await;
        return;
    };
    let mut wp = match plan::plan(session.target(), &home, flavour, &deps.plan)
        .map_err(Abort::from)
        .and_then(|items| waypoint_seq(&items).ok_or(Abort::NoWaypoint))
    {
        Ok(w) => w,
        Err(e) => {
            save_rounds(deps, &id, &session, Some(&e)).await;
            return;
        }
    };
    let t_loop = crate::clock::now();
    // The alignment of the last round, for a round whose refit is refused.
    let mut last_alignment = None;
    loop {
        let t_fly = crate::clock::now();
        let mut approach = Approach::new(
            deps.params.refine.approach,
            seconds_since(deps, t_fly),
            session.rounds().is_empty(),
        );
        let arrived_at = loop {
            let leg = tokio::select! {
                _ = cancel.cancelled() => {
                    tracing::info!(shot = %id, "refinement: cancelled");
                    save_rounds(deps, &id, &session, Some(&Abort::Cancelled)).await;
                    return;
                }
                a = wait_arrival(
                    deps,
                    wp,
                    (&session, &home, last_alignment.as_ref()),
                    &mut approach,
                    (&id, session.rounds().len()),
                ) => a,
            };
            match leg {
                Ok(Leg::Arrived(t)) => break t,
                Ok(Leg::Retarget(r)) => {
                    let r = *r;
                    let started = tokio::select! {
                        _ = cancel.cancelled() => {
                            save_rounds(deps, &id, &session, Some(&Abort::Cancelled)).await;
                            return;
                        }
                        r = fly(deps, &r.target, &home, flavour, &cancel) => r,
                    };
                    match started {
                        Ok(w) => wp = w,
                        Err(Abort::Plan(e)) => {
                            // The moved target is refused (fence, altitude):
                            // the one uploaded is still flown.
                            tracing::warn!(shot = %id, "refinement: re-target refused: {e}");
                            continue;
                        }
                        Err(why) => {
                            tracing::warn!(shot = %id, "refinement: re-target: {why}");
                            save_rounds(deps, &id, &session, Some(&why)).await;
                            return;
                        }
                    }
                    let sh = r.shift;
                    tracing::info!(
                        shot = %id,
                        round = session.rounds().len(),
                        shift_m = sh.position_m,
                        north_m = sh.ned_m[0],
                        east_m = sh.ned_m[1],
                        down_m = sh.ned_m[2],
                        yaw_deg = sh.yaw_deg,
                        pitch_deg = sh.pitch_deg,
                        "refinement: re-targeted on the approach (georeference refitted in flight)"
                    );
                    session.retarget(r.target, sh);
                    last_alignment = Some(r.alignment);
                    deps.events.publish(
                        &id,
                        ShotEvent::Retargeted {
                            round: session.rounds().len(),
                            shift_m: sh.position_m,
                            yaw_deg: sh.yaw_deg,
                            pitch_deg: sh.pitch_deg,
                            count: approach.flown(),
                        },
                    );
                }
                Err(why) => {
                    tracing::warn!(shot = %id, "refinement: {why}");
                    save_rounds(deps, &id, &session, Some(&why)).await;
                    return;
                }
            }
        };
        let target = *session.target();
        let flight_s = crate::clock::since(t_fly).as_secs_f64();
        deps.events.publish(
            &id,
            ShotEvent::Arrived {
                round: session.rounds().len(),
            },
        );
        let before = session.clone();
        let step = tokio::select! {
            _ = cancel.cancelled() => {
                save_rounds(deps, &id, &before, Some(&Abort::Cancelled)).await;
                return;
            }
            s = look(deps, session, &shot, &home, arrived_at, &mut last_alignment) => s,
        };
        let (s, step) = step;
        let step = match step {
            Ok(x) => x,
            Err(why) => {
                tracing::warn!(shot = %id, "refinement: {why}");
                save_rounds(deps, &id, &s, Some(&why)).await;
                return;
            }
        };
        session = s;
        if let Some(r) = session.rounds().last() {
            tracing::info!(
                shot = %id,
                round = r.round,
                shot_error_pct = r.shot_error_pct,
                shot_error_px = r.shot_error_px,
                inliers = r.inliers,
                decision = ?r.decision,
                flight_s,
                note = r.note.as_deref().unwrap_or(""),
                "refinement: round"
            );
            deps.events.publish(
                &id,
                ShotEvent::Round {
                    round: r.round,
                    shot_error_pct: r.shot_error_pct,
                    floor_pct: r.floor_pct,
                    decision: serde_json::to_value(r.decision)
                        .ok()
                        .and_then(|v| v.as_str().map(str::to_owned))
                        .unwrap_or_else(|| format!("{:?}", r.decision)),
                    note: r.note.clone(),
                },
            );
        }
        save_rounds(deps, &id, &session, None).await;
        if let Some(sp) = deps.params.servo
            && crate::refine::servo::takes_over(
                &step,
                session.rounds().last().and_then(|r| r.shot_error_pct),
                &target,
                &home,
                &sp,
            )
        {
            servo_and_finish(deps, &mut session, &shot, target, &home, sp, &cancel).await;
            return;
        }
        let next = match step {
            Step::Done(stop) => {
                tracing::info!(
                    shot = %id,
                    stop = stop.name(),
                    rounds = session.rounds().len(),
                    seconds = crate::clock::since(t_loop).as_secs_f64(),
                    "refinement: done"
                );
                let reason = match &stop {
                    crate::refine::Stop::LiveNotLocalised(r)
                    | crate::refine::Stop::CorrectionRefused(r) => Some(r.clone()),
                    _ => None,
                };
                deps.events.publish(
                    &id,
                    ShotEvent::Done {
                        stop: stop.name().into(),
                        reason,
                    },
                );
                return;
            }
            Step::Upload(t) => t,
        };
        let started = tokio::select! {
            _ = cancel.cancelled() => {
                save_rounds(deps, &id, &session, Some(&Abort::Cancelled)).await;
                return;
            }
            r = fly(deps, &next, &home, flavour, &cancel) => r,
        };
        match started {
            Ok(w) => wp = w,
            Err(why) => {
                tracing::warn!(shot = %id, "refinement: corrected mission: {why}");
                save_rounds(deps, &id, &session, Some(&why)).await;
                return;
            }
        }
    }
}

/// Servoing at the shot after a round ([`super::refinement_servo`]): the
/// outcome noted on the last round, the shot's record saved and its
/// `done` event published (`servo_<stop>`).
async fn servo_and_finish(
    deps: &Arc<Deps>,
    session: &mut Session,
    shot: &Shot,
    holding: Target,
    home: &Home,
    params: crate::refine::ServoParams,
    cancel: &CancellationToken,
) {
    let id = &shot.id;
    let outcome =
        super::refinement_servo::servo_at_shot(deps, session, shot, holding, home, params, cancel)
            .await;
    match outcome {
        Ok(o) => {
            session.annotate(&o.note());
            save_rounds(deps, id, session, None).await;
            super::refinement_servo::save_servo(deps, id, &o).await;
            let reason = match &o.stop {
                crate::refine::ServoStop::LiveLost(r) | crate::refine::ServoStop::Refused(r) => {
                    Some(r.clone())
                }
                _ => None,
            };
            deps.events.publish(
                id,
                ShotEvent::Done {
                    stop: format!("servo_{}", o.stop.name()),
                    reason,
                },
            );
        }
        Err(why) => {
            tracing::warn!(shot = %id, "refinement: servo: {why}");
            save_rounds(deps, id, session, Some(&why)).await;
        }
    }
}

/// The session of a started shot: its pose, desired picture and the
/// target its mission flies.
async fn prepare(deps: &Arc<Deps>, shot: &Shot, target: Target) -> Result<Session, Abort> {
    let map_from_desired = shot
        .localisation
        .as_ref()
        .and_then(|l| l.world_from_cam.to_isometry())
        .ok_or_else(|| Abort::NotLocalised {
            shot: shot.id.clone(),
        })?;
    let (d, s) = (deps.clone(), shot.clone());
    let picture = tokio::task::spawn_blocking(move || picture_of(&d, &s)).await??;
    let (image, mask, reachable) = picture;
    let session = Session::new(
        image,
        mask,
        map_from_desired,
        target,
        deps.params.refine.clone(),
    );
    Ok(match reachable {
        Some(r) => session.with_reachable(r),
        None => session,
    })
}

/// The session after the round, and the step or why there was none.
type Looked = (Session, Result<Step, Abort>);

/// The live frames of one measurement: `measure.frames` frames received
/// after the arrival, at least `measure.spacing_s` apart, each with the
/// position the vehicle reported when it came. Fewer when the video stalls
/// (none: an error).
async fn collect_frames(
    deps: &Deps,
    frame_ltp: &LocalFrame,
    home: &Home,
    arrived: Instant,
) -> Result<Vec<(Arc<Frame>, Option<Vector3<f64>>)>, Abort> {
    let p = &deps.params;
    let m = p.refine.measure;
    let want = m.frames.max(1);
    let spacing = Duration::try_from_secs_f64(m.spacing_s.max(0.0)).unwrap_or_default();
    let t0 = crate::clock::now();
    let mut frames: Vec<(Arc<Frame>, Option<Vector3<f64>>)> = Vec::with_capacity(want);
    let mut after = arrived;
    while frames.len() < want {
        match deps.ingest.latest() {
            Some(f) if f.received > after => {
                after = f.received + spacing;
                let reported = reported_ned(deps, frame_ltp, home);
                frames.push((f, reported));
            }
            // Each frame has its own wait, so a slow video still gives
            // what it can.
            _ if crate::clock::since(t0) > p.frame_wait + spacing * (frames.len() as u32) => break,
            _ => tokio::time::sleep(Duration::from_millis(20)).await,
        }
    }
    if frames.is_empty() {
        return Err(Abort::NoFrame);
    }
    Ok(frames)
}

/// The arrival: a few frames received after it, a map snapshot and the
/// georeference, then the session's round on a blocking thread.
async fn look(
    deps: &Arc<Deps>,
    session: Session,
    shot: &Shot,
    home: &Home,
    arrived: Instant,
    last: &mut Option<GeoAlignment>,
) -> Looked {
    let p = &deps.params;
    let frame_ltp = LocalFrame::new(Geodetic {
        lat_deg: home.lat_deg,
        lon_deg: home.lon_deg,
        alt_m: home.alt_amsl_m,
    });
    let frames = match collect_frames(deps, &frame_ltp, home, arrived).await {
        Ok(f) => f,
        Err(e) => return (session, Err(e)),
    };
    let t_s = frames.last().map_or(0.0, |(f, _)| {
        f.received.duration_since(deps.epoch).as_secs_f64()
    });
    let observed = observe(deps, session.target(), &frames[0].0, arrived);
    let Some(map_from_desired) = shot
        .localisation
        .as_ref()
        .and_then(|l| l.world_from_cam.to_isometry())
    else {
        return (
            session,
            Err(Abort::NotLocalised {
                shot: shot.id.clone(),
            }),
        );
    };
    let (alignment, kept_note) =
        match round_alignment(deps.geo.target(&map_from_desired).map(|(_, a)| a), last) {
            Ok(a) => a,
            Err(e) => return (session, Err(Abort::Georeference(e))),
        };
    let mount = deps.geo.params().mount.clone();
    let fence = deps.plan.fence;
    let localize = p.localize.clone();
    let slam = deps.slam.clone();
    let home = *home;
    let backup = session.clone();
    let (d, s) = (deps.clone(), shot.clone());
    let joined = tokio::task::spawn_blocking(move || {
        let mut session = session;
        let Some(map) = slam.map_snapshot() else {
            return (session, Err(Abort::NoMap));
        };
        let ctx = Context {
            map: &map,
            alignment: &alignment,
            frame: &frame_ltp,
            mount: &mount,
            home: &home,
            fence: &fence,
            localize: &localize,
        };
        let camera = map.camera;
        let live: Vec<LiveFrame<'_>> = frames
            .iter()
            .map(|(f, r)| LiveFrame {
                image: &f.image,
                reported_ned_m: *r,
            })
            .collect();
        let step = session.on_arrival(&live, t_s, Some(&camera), &ctx);
        session.observe(observed);
        if let Some(n) = &kept_note {
            session.annotate(n);
        }
        // The round's first frame, with the desired outline, for the
        // before/after view; its error is the round's.
        if let (Some(r), Some((f, _))) = (session.rounds().last(), frames.first()) {
            let corners_px = picture_of(&d, &s).ok().and_then(|(img, mask, _)| {
                let rep = shot_error(
                    &f.image,
                    &img,
                    mask.as_ref(),
                    Some(&camera),
                    &d.params.refine.error,
                )
                .ok()?;
                outline_in_live(&rep, img.width(), img.height(), Some(&camera))
            });
            d.events.set_achieved(
                &s.id,
                Achieved {
                    frame: f.image.clone(),
                    round: r.round,
                    shot_error_pct: r.shot_error_pct,
                    corners_px,
                },
            );
        }
        (session, Ok(step))
    })
    .await;
    match joined {
        Ok(r) => r,
        Err(e) => (backup, Err(Abort::Task(e))),
    }
}

/// Publishes the desired shot's outline in the newest live frame every
/// [`OVERLAY_PERIOD`] until `cancel`.
async fn overlay_loop(deps: Arc<Deps>, shot: Shot, cancel: CancellationToken) {
    let d = deps.clone();
    let camera = tokio::task::spawn_blocking(move || d.slam.map_snapshot().map(|m| m.camera))
        .await
        .ok()
        .flatten();
    let mut tick = tokio::time::interval(OVERLAY_PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut last_seq = None;
    loop {
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = tick.tick() => {}
        }
        let Some(frame) = deps.ingest.latest() else {
            continue;
        };
        if last_seq == Some(frame.seq) {
            continue;
        }
        last_seq = Some(frame.seq);
        let (d, s) = (deps.clone(), shot.clone());
        let measured = tokio::task::spawn_blocking(move || {
            let (w, h) = frame.image.dimensions();
            let (img, mask, _) = picture_of(&d, &s)?;
            let ev = match shot_error(
                &frame.image,
                &img,
                mask.as_ref(),
                camera.as_ref(),
                &d.params.refine.error,
            ) {
                Ok(rep) => ShotEvent::Overlay {
                    width: w,
                    height: h,
                    corners_px: outline_in_live(&rep, img.width(), img.height(), camera.as_ref()),
                    shot_error_pct: Some(rep.corner_error_pct),
                    inliers: Some(rep.inliers),
                    note: None,
                },
                Err(e) => ShotEvent::Overlay {
                    width: w,
                    height: h,
                    corners_px: None,
                    shot_error_pct: None,
                    inliers: None,
                    note: Some(e.to_string()),
                },
            };
            Ok::<_, Abort>(ev)
        })
        .await;
        match measured {
            Ok(Ok(ev)) if !cancel.is_cancelled() => deps.events.publish(&shot.id, ev),
            Ok(Err(e)) => {
                tracing::debug!("refinement: overlay: {e}");
                return;
            }
            _ => {}
        }
    }
}

/// The vehicle's report and the frame's timing when `frame` is taken for
/// the round flying `target` that arrived at `arrived`.
fn observe(deps: &Deps, target: &Target, frame: &Frame, arrived: Instant) -> Observation {
    let tel = &deps.link.telemetry;
    let timing = FrameTiming {
        capture_unix: frame.capture_time,
        received_unix: frame.received_unix,
        received_after_arrival_s: frame
            .received
            .checked_duration_since(arrived)
            .map_or(0.0, |d| d.as_secs_f64()),
    };
    let reports = Reports {
        position: (*tel.global_position.borrow()).map(|g| position_report(&g)),
        yaw_deg: (*tel.attitude.borrow()).map(|a| f64::from(a.value.yaw_rad).to_degrees()),
        gimbal_pitch_deg: (*tel.gimbal.borrow()).map(|g| f64::from(g.value.pitch_deg)),
    };
    observation(target, &timing, &reports)
}

/// Plans, uploads (with read-back) and starts the corrected target; the
/// planner's geofence and altitude checks apply as to the first target.
/// Returns the waypoint's sequence number.
async fn fly(
    deps: &Deps,
    target: &Target,
    home: &Home,
    flavour: Flavour,
    cancel: &CancellationToken,
) -> Result<u16, Abort> {
    let items = plan::plan(target, home, flavour, &deps.plan)?;
    let wp = waypoint_seq(&items).ok_or(Abort::NoWaypoint)?;
    let _guard = deps.actions.lock().await;
    if cancel.is_cancelled() {
        return Err(Abort::Cancelled);
    }
    deps.link
        .upload_verified(&items, flavour)
        .await
        .map_err(Abort::Upload)?;
    deps.link.start_mission().await.map_err(Abort::Start)?;
    tracing::info!(
        lat = target.lat_deg,
        lon = target.lon_deg,
        alt_m = target.alt_m,
        yaw_deg = target.yaw_deg,
        pitch_deg = target.gimbal_pitch_deg,
        "refinement: corrected mission started"
    );
    Ok(wp)
}
