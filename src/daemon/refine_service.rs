//! The daemon's side of the refinement loop ([`crate::refine`]): a shot's
//! rounds go into its mission record, `details.refinement`, so that
//! `GET /api/v1/shots/{id}` and the operator's page show each round (shot
//! error, decision, correction, why it stopped).
//!
//! The loop itself is [`crate::refine::Session`], driven on arrival
//! ([`crate::refine::ArrivalDetector`] fed with MISSION_ITEM_REACHED, the
//! ground speed and the gimbal pitch from telemetry) with the newest frame,
//! a map snapshot and the georeference; each corrected target is planned
//! and uploaded like the first. `shotpilot scenario` drives the same
//! session and arrival rule against the simulator in simulated time.

use serde_json::{Value, json};

use crate::refine::Session;
use crate::shot::record::MissionRecord;

/// The session's rounds and end as JSON: `{"rounds": [...], "stop": ...,
/// "reason": ...}` (`stop` is null while the loop goes on).
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
    set_detail(mission, "refinement", refinement_json(session));
}

/// Sets `details[key]` of the mission record (details that are not an
/// object become `{"previous": ..}`, null becomes `{}`).
pub fn set_detail(mission: &mut MissionRecord, key: &str, value: Value) {
    if !mission.details.is_object() {
        let previous = std::mem::take(&mut mission.details);
        mission.details = if previous.is_null() {
            json!({})
        } else {
            json!({ "previous": previous })
        };
    }
    if let Some(obj) = mission.details.as_object_mut() {
        obj.insert(key.into(), value);
    }
}

/// Marks the recorded refinement as ended by the daemon rather than by
/// the session (no arrival, an upload failed, shutdown, another shot):
/// `stop` becomes `aborted` (when the session had not stopped) and
/// `reason` says why. Call after [`record_rounds`].
pub fn record_abort(mission: &mut MissionRecord, reason: &str) {
    let Some(r) = mission
        .details
        .get_mut("refinement")
        .and_then(Value::as_object_mut)
    else {
        return;
    };
    if r.get("stop").is_none_or(Value::is_null) {
        r.insert("stop".into(), Value::from("aborted"));
        r.insert("reason".into(), Value::from(reason));
    } else {
        r.insert("daemon_note".into(), Value::from(reason));
    }
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
    }
}
