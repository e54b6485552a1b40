//! Servoing at the shot in the daemon (the servo itself is
//! [`crate::refine::servo`]): gimbal control taken, the guided setpoint
//! stream started at the held target and, a moment later, the vehicle
//! switched to guided control (PX4 OFFBOARD needs the stream first); then
//! each new video frame is measured on a blocking thread, its setpoint
//! sent (and the gimbal pointed when its pitch changes), until the servo
//! stops; the photo is taken, the stream stopped and the vehicle put back
//! in hold. The operator's stop ends the stream in the link actor at once
//! and cancels this task; any other cancellation stops the stream (PX4
//! then falls back to a hold by itself). A lost link (the link actor's
//! heartbeat timeout) ends servoing the moment it is declared: the stream
//! stops and the autopilot's own failsafe takes over.

use std::sync::Arc;
use std::time::Duration;

use tokio_util::sync::CancellationToken;

use super::refinement_deps::{Abort, Deps, position_report, reported_ned};
use crate::geo::{Geodetic, LocalFrame};
use crate::mission::plan::{Home, Target};
use crate::refine::{ServoFrame, ServoParams, ServoStep, ServoStop, Session, World};
use crate::shot::record::Shot;
use crate::vehicle::{FlightMode, GUIDED_PERIOD, GuidedSetpoint};

/// How long the setpoint stream runs before the switch to guided control:
/// PX4 wants more than a second of it.
const GUIDED_LEAD: Duration = Duration::from_millis(1500);

/// The photo at the end of servoing.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub(super) struct PhotoOutcome {
    /// The camera (or the autopilot's trigger) took it.
    pub(super) taken: bool,
    /// Its CAMERA_IMAGE_CAPTURED's index, when one came.
    pub(super) image_index: Option<i32>,
    /// Why not, when it was not.
    pub(super) error: Option<String>,
}

/// What servoing did (recorded on the shot as `refinement.servo`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub(super) struct ServoOutcome {
    /// Why it ended.
    #[serde(flatten)]
    pub(super) stop: ServoStop,
    /// Frames measured.
    pub(super) frames: usize,
    /// Setpoints moved.
    pub(super) moves: usize,
    /// Seconds from the switch to the end.
    pub(super) seconds: f64,
    /// The last frame's shot error, %.
    pub(super) last_error_pct: Option<f64>,
    /// The photo, when one was due.
    pub(super) photo: Option<PhotoOutcome>,
    /// Median time from a frame's arrival to its setpoint queued on the
    /// link (the daemon's clock: simulated in the lockstep tests, real in
    /// the field), ms.
    pub(super) latency_ms_median: Option<f64>,
    /// Median wall time of one frame's measurement (shot error and
    /// localisation on a blocking thread), ms.
    pub(super) compute_ms_median: Option<f64>,
}

impl ServoOutcome {
    /// The note recorded on the shot's last round.
    pub(super) fn note(&self) -> String {
        let photo = match &self.photo {
            Some(PhotoOutcome {
                image_index: Some(i),
                ..
            }) => format!("photo taken (image {i})"),
            Some(PhotoOutcome { taken: true, .. }) => {
                "photo triggered (no capture report)".to_string()
            }
            Some(PhotoOutcome { error, .. }) => {
                format!("photo failed: {}", error.as_deref().unwrap_or("?"))
            }
            None => "no photo".to_string(),
        };
        let ms = |v: Option<f64>| v.map_or_else(|| "-".to_string(), |x| format!("{x:.0} ms"));
        format!(
            "servo: {} after {:.1} s, {} frames ({} each to measure, {} from frame to setpoint), {} setpoints moved, last shot error {}; {photo}",
            self.stop.name(),
            self.seconds,
            self.frames,
            ms(self.compute_ms_median),
            ms(self.latency_ms_median),
            self.moves,
            self.last_error_pct
                .map_or_else(|| "-".to_string(), |e| format!("{e:.2} %")),
        )
    }
}

/// Writes the servo's outcome into the shot's recorded refinement: its
/// `servo` object, `stop` = `servo_<stop>` and, for a lost view or a
/// refused setpoint, `reason`.
pub(super) async fn save_servo(deps: &Deps, shot_id: &str, o: &ServoOutcome) {
    let value = match serde_json::to_value(o) {
        Ok(v) => v,
        Err(e) => {
            tracing::warn!(shot = %shot_id, "servo: recording: {e}");
            return;
        }
    };
    let stop = format!("servo_{}", o.stop.name());
    let reason = match &o.stop {
        ServoStop::LiveLost(r) | ServoStop::Refused(r) => Some(r.clone()),
        _ => None,
    };
    let (store, id) = (deps.store.clone(), shot_id.to_owned());
    let write = move || {
        store.update(&id, |s| {
            let refinement = s
                .mission
                .as_mut()
                .and_then(|m| m.details.get_mut("refinement"))
                .and_then(serde_json::Value::as_object_mut);
            if let Some(r) = refinement {
                r.insert("servo".into(), value);
                r.insert("stop".into(), stop.into());
                if let Some(why) = reason {
                    r.insert("reason".into(), why.into());
                }
            }
        })
    };
    match tokio::task::spawn_blocking(write).await {
        Ok(Ok(_)) => {}
        Ok(Err(e)) => tracing::warn!("servo: saving the shot: {e}"),
        Err(e) => tracing::warn!("servo: saving the shot: {e}"),
    }
}

/// Servoes from `holding` (the target the vehicle holds at) until the
/// servo stops, `cancel` fires, or the link refuses guided control.
pub(super) async fn servo_at_shot(
    deps: &Arc<Deps>,
    session: &Session,
    shot: &Shot,
    holding: Target,
    home: &Home,
    params: ServoParams,
    cancel: &CancellationToken,
) -> Result<ServoOutcome, Abort> {
    let r = tokio::select! {
        _ = cancel.cancelled() => Err(Abort::Cancelled),
        why = link_lost(deps) => Err(why),
        r = run(deps, session, shot, holding, home, params) => r,
    };
    // The stream ends however servoing ended.
    if let Err(e) = deps.link.guide(None).await {
        tracing::warn!(shot = %shot.id, "servo: stopping the setpoint stream: {e}");
    }
    // Back to a hold where it is (not after a cancellation: the stop
    // already holds, another shot's mission flies on; not over a lost
    // link: nothing would hear it).
    if !matches!(r, Err(Abort::Cancelled | Abort::LinkLost { .. }))
        && let Err(e) = deps.link.set_mode(FlightMode::Hold).await
    {
        tracing::warn!(shot = %shot.id, "servo: back to hold: {e}");
    }
    if let Ok(o) = &r {
        tracing::info!(shot = %shot.id, "{}", o.note());
    }
    r
}

async fn run(
    deps: &Arc<Deps>,
    session: &Session,
    shot: &Shot,
    holding: Target,
    home: &Home,
    params: ServoParams,
) -> Result<ServoOutcome, Abort> {
    let map_from_desired = shot
        .localisation
        .as_ref()
        .and_then(|l| l.world_from_cam.to_isometry())
        .ok_or_else(|| Abort::NotLocalised {
            shot: shot.id.clone(),
        })?;
    let (_, alignment) = deps.geo.target(&map_from_desired)?;
    let frame_ltp = LocalFrame::new(Geodetic {
        lat_deg: home.lat_deg,
        lon_deg: home.lon_deg,
        alt_m: home.alt_amsl_m,
    });
    let gimbal = match deps.link.acquire_gimbal().await {
        Ok(_) => true,
        Err(e) => {
            tracing::warn!(shot = %shot.id, "servo: no gimbal control, the pitch stays: {e}");
            false
        }
    };
    deps.link
        .guide(Some(GuidedSetpoint::at_target(&holding, home)))
        .await
        .map_err(Abort::Guided)?;
    tokio::time::sleep(GUIDED_LEAD).await;
    deps.link
        .set_mode(FlightMode::Guided)
        .await
        .map_err(Abort::Guided)?;
    tracing::info!(shot = %shot.id, "servo: guided control engaged");
    // One map snapshot for the whole servo, as one per look in the
    // rounds: the map hardly changes over a hover, and a snapshot copies it.
    let slam = deps.slam.clone();
    let map = tokio::task::spawn_blocking(move || slam.map_snapshot())
        .await?
        .ok_or(Abort::NoMap)?;
    let world = Arc::new(World {
        map,
        alignment,
        frame: frame_ltp,
        mount: deps.geo.params().mount.clone(),
        home: *home,
        fence: deps.plan.fence,
        localize: deps.params.localize.clone(),
    });
    let t0 = crate::clock::now();
    let mut servo = session.servo(holding, params);
    let mut out = ServoOutcome {
        stop: ServoStop::Timeout,
        frames: 0,
        moves: 0,
        seconds: 0.0,
        last_error_pct: None,
        photo: None,
        latency_ms_median: None,
        compute_ms_median: None,
    };
    let (mut latency_ms, mut compute_ms) = (Vec::new(), Vec::new());
    let mut after = t0;
    let mut pitch_sent = holding.gimbal_pitch_deg;
    let stop = loop {
        let f = next_frame(deps, after).await?;
        after = f.received;
        let tel = &deps.link.telemetry;
        let fresh = |r: std::time::Instant| crate::clock::since(r) <= deps.params.max_telemetry_age;
        let reported = reported_ned(deps, &frame_ltp, home);
        let yaw = (*tel.attitude.borrow())
            .filter(|a| fresh(a.received))
            .map(|a| f64::from(a.value.yaw_rad).to_degrees());
        let pitch = (*tel.gimbal.borrow())
            .filter(|g| fresh(g.received))
            .map(|g| f64::from(g.value.pitch_deg));
        let speed = (*tel.global_position.borrow())
            .filter(|g| fresh(g.received))
            .map(|g| position_report(&g).speed_m_s());
        let t_s = f.received.duration_since(deps.epoch).as_secs_f64();
        let world = world.clone();
        let mut moving = servo;
        let wall = std::time::Instant::now();
        let step = tokio::task::spawn_blocking(move || {
            let ctx = world.ctx();
            let step = moving.on_frame(
                &ServoFrame {
                    image: &f.image,
                    t_s,
                    reported_ned_m: reported,
                    reported_yaw_deg: yaw,
                    reported_pitch_deg: pitch,
                    reported_speed_m_s: speed,
                },
                Some(&world.map.camera),
                &ctx,
            );
            (moving, step)
        })
        .await?;
        let (back, step) = step;
        servo = back;
        compute_ms.push(wall.elapsed().as_secs_f64() * 1e3);
        out.frames += 1;
        out.last_error_pct = servo.samples().last().and_then(|s| s.shot_error_pct);
        match step {
            ServoStep::Hold => {}
            ServoStep::Move(t) => {
                out.moves += 1;
                deps.link
                    .guide(Some(GuidedSetpoint::at_target(&t, home)))
                    .await
                    .map_err(Abort::Guided)?;
                latency_ms.push(crate::clock::since(after).as_secs_f64() * 1e3);
                if gimbal && (t.gimbal_pitch_deg - pitch_sent).abs() > 0.05 {
                    pitch_sent = t.gimbal_pitch_deg;
                    if let Err(e) = deps.link.point_gimbal(t.gimbal_pitch_deg as f32, 0.0).await {
                        tracing::warn!(shot = %shot.id, "servo: gimbal: {e}");
                    }
                }
            }
            ServoStep::Done(s) => break s,
        }
    };
    out.seconds = crate::clock::since(t0).as_secs_f64();
    out.latency_ms_median = crate::stats::finite_median(&latency_ms);
    out.compute_ms_median = crate::stats::finite_median(&compute_ms);
    if matches!(
        stop,
        ServoStop::Settled | ServoStop::BestAvailable | ServoStop::Timeout
    ) {
        out.photo = Some(
            match deps.link.capture_image(Duration::from_secs(5)).await {
                Ok(p) => PhotoOutcome {
                    taken: true,
                    image_index: p.captured.map(|c| c.index),
                    error: None,
                },
                Err(e) => PhotoOutcome {
                    taken: false,
                    image_index: None,
                    error: Some(e.to_string()),
                },
            },
        );
    }
    out.stop = stop;
    Ok(out)
}

/// Resolves when the link actor declares the link lost (no heartbeat for
/// its `link_lost_after_ms`; [`Abort::LinkLost`] with the last heartbeat's
/// age) or is gone ([`Abort::Guided`] with `ActorGone`): the servo ends at
/// that moment, whatever frame it is measuring.
async fn link_lost(deps: &Deps) -> Abort {
    let mut rx = deps.link.telemetry.vehicle.clone();
    match rx.wait_for(|v| v.link_lost).await {
        Ok(v) => Abort::LinkLost {
            after_s: v
                .last_heartbeat
                .map_or(0.0, |t| crate::clock::since(t).as_secs_f64()),
        },
        Err(_) => Abort::Guided(crate::vehicle::LinkError::ActorGone),
    }
}

/// The first video frame received after `after` (waiting up to the loop's
/// `frame_wait`, checking every stream period).
async fn next_frame(
    deps: &Deps,
    after: std::time::Instant,
) -> Result<Arc<crate::video::live::Frame>, Abort> {
    let t0 = crate::clock::now();
    loop {
        if let Some(f) = deps.ingest.latest()
            && f.received > after
        {
            return Ok(f);
        }
        if crate::clock::since(t0) > deps.params.frame_wait {
            return Err(Abort::NoFrame);
        }
        tokio::time::sleep(GUIDED_PERIOD / 5).await;
    }
}
