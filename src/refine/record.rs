//! The shot refinement's record on the shot ([`crate::refine`]'s rounds
//! in the shot's mission record, `details.refinement`), so that
//! `GET /api/v1/shots/{id}` and the operator's page show each round (shot
//! error, decision, correction, why it stopped), and how the record ends
//! when the loop is ended from outside the session: aborted (no arrival,
//! an upload failed, another shot), stopped by the operator, or
//! interrupted by the daemon's stop.
//!
//! The loop itself is [`crate::refine::Session`], driven on arrival
//! ([`crate::refine::ArrivalDetector`] fed with MISSION_ITEM_REACHED, the
//! ground speed and the gimbal pitch from telemetry) with the newest frame,
//! a map snapshot and the georeference; the daemon's task
//! (`daemon::refinement_task`) and `shotpilot scenario` drive it.

use serde_json::{Value, json};

use crate::refine::Session;
use crate::shot::record::MissionRecord;

/// The session's rounds and end as JSON: `{"rounds": [...], "stop": ...,
/// "reason": ..., "target": ..., "retargets": [...], "reachable": ...}`
/// (`stop` is null while the loop goes on; `retargets`: the moves flown on
/// the approaches, [`crate::refine::Shift`]).
pub fn refinement_json(session: &Session) -> Value {
    let (stop, reason) = match session.stop() {
        Some(s) => (
            Value::from(s.name()),
            match s {
                crate::refine::Stop::LiveNotLocalised(r)
                | crate::refine::Stop::CorrectionRefused(r) => Value::from(r.as_str()),
                _ => Value::Null,
            },
        ),
        None => (Value::Null, Value::Null),
    };
    json!({
        "rounds": serde_json::to_value(session.rounds()).unwrap_or(Value::Null),
        "stop": stop,
        "reason": reason,
        "target": serde_json::to_value(session.target()).unwrap_or(Value::Null),
        "retargets": serde_json::to_value(session.retargets()).unwrap_or(Value::Null),
        "reachable": session.reachable().map_or(Value::Null, |r| json!({
            "floor_pct": r.floor_pct,
            "floor_px": r.floor_px,
            "points": r.points,
            "inliers": r.inliers,
        })),
    })
}

/// Writes the session into the mission record's `details.refinement`
/// (other details are kept; details that are not an object become
/// `{"previous": ..}`).
pub fn record_rounds(mission: &mut MissionRecord, session: &Session) {
    mission.set_detail("refinement", refinement_json(session));
}

/// The recorded refinement's object, if the mission has one.
fn refinement_mut(mission: &mut MissionRecord) -> Option<&mut serde_json::Map<String, Value>> {
    mission
        .details
        .get_mut("refinement")
        .and_then(Value::as_object_mut)
}

/// Marks the recorded refinement as ended by the daemon rather than by
/// the session (no arrival, an upload failed, shutdown, another shot):
/// `stop` becomes `aborted` (when the session had not stopped) and
/// `reason` says why. Call after [`record_rounds`].
pub fn record_abort(mission: &mut MissionRecord, reason: &str) {
    let Some(r) = refinement_mut(mission) else {
        return;
    };
    if r.get("stop").is_none_or(Value::is_null) {
        r.insert("stop".into(), Value::from("aborted"));
        r.insert("reason".into(), Value::from(reason));
    } else {
        r.insert("daemon_note".into(), Value::from(reason));
    }
}

/// Whether the recorded refinement ended because its task was cancelled
/// (`stop` aborted, `reason` cancelled).
fn was_cancelled(r: &serde_json::Map<String, Value>) -> bool {
    r.get("stop").and_then(Value::as_str) == Some("aborted")
        && r.get("reason").and_then(Value::as_str) == Some("cancelled")
}

/// The operator stopped the loop: a refinement recorded as cancelled (or
/// not stopped yet) becomes `stopped` with the operator's `reason`; one
/// that had stopped on its own stays, with the reason as `daemon_note`.
pub fn record_stopped(mission: &mut MissionRecord, reason: &str) {
    let Some(r) = refinement_mut(mission) else {
        return;
    };
    if was_cancelled(r) || r.get("stop").is_none_or(Value::is_null) {
        r.insert("stop".into(), "stopped".into());
        r.insert("reason".into(), reason.into());
    } else {
        r.insert("daemon_note".into(), reason.into());
    }
}

/// The daemon stopped while the loop ran: the refinement record to write
/// when the loop recorded itself as cancelled (`stop` interrupted, the
/// reason, `restartable`); None when it had ended otherwise (or there is
/// none).
pub fn interrupted(mission: &MissionRecord) -> Option<Value> {
    let mut r = mission
        .details
        .get("refinement")
        .and_then(Value::as_object)
        .filter(|r| was_cancelled(r))?
        .clone();
    r.insert("stop".into(), "interrupted".into());
    r.insert(
        "reason".into(),
        "the daemon stopped while the loop ran; start the shot's mission to refine again".into(),
    );
    r.insert("restartable".into(), true.into());
    Some(r.into())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion};
    use crate::geo::{GeoAlignment, Geodetic, LocalFrame, MountParams};
    use crate::geometry::Sim3;
    use crate::mission::plan::{Fence, Home, Target};
    use crate::refine::{Context, Params, Step, Stop};
    use crate::shot::LocalizeParams;
    use crate::shot::record::MissionState;
    use crate::slam::{Map, ScaleInfo};
    use image::GrayImage;
    use nalgebra::Isometry3;

    #[test]
    fn rounds_land_in_the_mission_details() {
        let home = Home {
            lat_deg: 47.0,
            lon_deg: 8.0,
            alt_amsl_m: 400.0,
        };
        let target = Target {
            lat_deg: 47.0,
            lon_deg: 8.0,
            alt_m: 15.0,
            yaw_deg: 0.0,
            gimbal_pitch_deg: -45.0,
            photo: false,
        };
        // A blank desired shot: no homography, no round left -> max_rounds,
        // with the shot error's failure noted.
        let blank = GrayImage::from_pixel(64, 48, image::Luma([90]));
        let mut params = Params::default();
        params.controller.max_rounds = 0;
        let mut s = Session::new(blank.clone(), None, Isometry3::identity(), target, params);
        let camera = Camera::new(64, 48, [50.0, 50.0, 32.0, 24.0], Distortion::default()).unwrap();
        let map = Map::new(camera, ScaleInfo::new(1.2, 8));
        let alignment = GeoAlignment::given(Sim3::identity());
        let frame = LocalFrame::new(Geodetic {
            lat_deg: 47.0,
            lon_deg: 8.0,
            alt_m: 400.0,
        });
        let ctx = Context {
            map: &map,
            alignment: &alignment,
            frame: &frame,
            mount: &MountParams::default(),
            home: &home,
            fence: &Fence::default(),
            localize: &LocalizeParams::default(),
        };
        assert_eq!(
            s.on_arrival(
                &[crate::refine::LiveFrame {
                    image: &blank,
                    reported_ned_m: None,
                }],
                0.0,
                None,
                &ctx
            ),
            Step::Done(Stop::MaxRounds)
        );
        let mut m = MissionRecord {
            state: MissionState::Started,
            items: 3,
            uploaded_unix: 1.0,
            started_unix: Some(2.0),
            target_lat_lon_alt: None,
            details: json!({"planner": "px4"}),
        };
        record_rounds(&mut m, &s);
        assert_eq!(m.details["planner"], "px4");
        let r = &m.details["refinement"];
        assert_eq!(r["stop"], "max_rounds");
        assert_eq!(r["rounds"].as_array().map(Vec::len), Some(1));
        assert_eq!(r["rounds"][0]["decision"], "max_rounds");
        assert!(r["rounds"][0]["shot_error_pct"].is_null());
        assert!(
            r["rounds"][0]["note"]
                .as_str()
                .is_some_and(|n| n.contains("shot error"))
        );
        // The daemon's own end is noted beside the session's stop.
        let mut aborted = m.clone();
        record_abort(&mut aborted, "cancelled");
        assert_eq!(aborted.details["refinement"]["stop"], "max_rounds");
        assert_eq!(aborted.details["refinement"]["daemon_note"], "cancelled");
        // Details that are not an object are kept beside it.
        m.details = json!("uploaded by read-back");
        record_rounds(&mut m, &s);
        assert_eq!(m.details["previous"], "uploaded by read-back");
        assert_eq!(m.details["refinement"]["stop"], "max_rounds");
        // The record survives the store's JSON round trip.
        let back: MissionRecord =
            serde_json::from_str(&serde_json::to_string(&m).unwrap()).unwrap();
        assert_eq!(back, m);
        // A session that had not stopped is marked aborted, with the reason.
        let blank_target = *s.target();
        let open = Session::new(
            blank,
            None,
            Isometry3::identity(),
            blank_target,
            Params::default(),
        );
        record_rounds(&mut m, &open);
        assert!(m.details["refinement"]["stop"].is_null());
        record_abort(&mut m, "waypoint 1 not reached and steady within 120 s");
        assert_eq!(m.details["refinement"]["stop"], "aborted");
        assert!(
            m.details["refinement"]["reason"]
                .as_str()
                .is_some_and(|r| r.contains("not reached"))
        );
        assert_eq!(m.details["refinement"]["rounds"], json!([]));
        // The operator's stop: an open or cancelled refinement says
        // stopped; one ended on its own keeps its end and notes it.
        let mut stopped = m.clone();
        record_rounds(&mut stopped, &open);
        record_stopped(&mut stopped, "operator stop");
        assert_eq!(stopped.details["refinement"]["stop"], "stopped");
        assert_eq!(stopped.details["refinement"]["reason"], "operator stop");
        let mut cancelled = m.clone();
        record_rounds(&mut cancelled, &open);
        record_abort(&mut cancelled, "cancelled");
        assert_eq!(interrupted(&m), None, "aborted for another reason");
        let r = interrupted(&cancelled).unwrap();
        assert_eq!(r["stop"], "interrupted");
        assert_eq!(r["restartable"], true);
        record_stopped(&mut cancelled, "operator stop");
        assert_eq!(cancelled.details["refinement"]["stop"], "stopped");
        let mut done = m.clone();
        record_rounds(&mut done, &s);
        record_stopped(&mut done, "operator stop");
        assert_eq!(done.details["refinement"]["stop"], "max_rounds");
        assert_eq!(done.details["refinement"]["daemon_note"], "operator stop");
        assert_eq!(interrupted(&done), None);
    }
}
