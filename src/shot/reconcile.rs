//! The vehicle's truth wins: each stored shot's mission state is set from
//! the mission the vehicle actually holds, read back over the link at start
//! and whenever the link comes back, instead of what an earlier session
//! believed (a shot "started" yesterday is not flying now).
//!
//! A shot owns the vehicle's mission when the vehicle holds exactly the
//! items planned for it (its first upload, or the latest correction of its
//! refinement loop); when several shots would, the one uploaded last owns
//! it. The owner's state comes from MISSION_CURRENT's mission state (and
//! the last item reached); every other shot with a mission is `replaced`
//! (the vehicle holds another mission) or `cleared` (it holds none). When
//! the mission cannot be read, the states are `unknown`, with the reason.
//! Each decision is written into the mission record's `details.vehicle`.
//!
//! A mission the operator stopped (`stopped`) stays stopped while the
//! vehicle still holds it, paused or not said.
//!
//! A refinement loop that was running when the daemon stopped (its record
//! has no stop) is marked `interrupted` at start, with the reason; the
//! operator restarts it by starting the shot's mission again.

use serde_json::{Value, json};

use crate::mission::MissionItem;
use crate::mission::upload::same_mission;
use crate::shot::record::{MissionState, Shot};
use crate::vehicle::{LinkError, MissionProgress};

/// MAV_MISSION_STATE values of MISSION_CURRENT.
const STATE_NOT_STARTED: u8 = 2;
const STATE_ACTIVE: u8 = 3;
const STATE_PAUSED: u8 = 4;
const STATE_COMPLETE: u8 = 5;

/// The mission read back from the vehicle.
#[derive(Debug, Clone)]
pub struct VehicleMission {
    /// Its items.
    pub items: Vec<MissionItem>,
    /// The newest MISSION_CURRENT / MISSION_ITEM_REACHED, if any came
    /// after the link came back.
    pub progress: Option<MissionProgress>,
    /// Compare without item 0 (ArduPilot keeps home there).
    pub skip_home: bool,
}

/// The item lists that mean "this shot's mission": what was planned at
/// upload (`details.planned_items`) and, given by the caller, any replanned
/// ones (the refinement loop's latest target).
pub fn planned_items(shot: &Shot) -> Option<Vec<MissionItem>> {
    let m = shot.mission.as_ref()?;
    serde_json::from_value(m.details.get("planned_items")?.clone()).ok()
}

/// The state of the mission the vehicle holds, for the shot that owns it.
fn owner_state(v: &VehicleMission) -> (MissionState, String) {
    let n = v.items.len();
    let last = n.checked_sub(1).and_then(|l| u16::try_from(l).ok());
    let Some(p) = v.progress else {
        return (
            MissionState::OnVehicle,
            "the vehicle holds this mission and has not said how far it is".into(),
        );
    };
    let reached_last = last.is_some() && p.last_reached == last;
    match p.state {
        Some(STATE_COMPLETE) => (
            MissionState::Finished,
            "the vehicle reports it complete".into(),
        ),
        Some(STATE_ACTIVE) | Some(STATE_PAUSED) => (
            MissionState::Active,
            format!(
                "the vehicle flies it (item {} of {n})",
                p.current_seq.map_or("?".into(), |s| s.to_string())
            ),
        ),
        _ if reached_last => (
            MissionState::Finished,
            "the vehicle reached its last item".into(),
        ),
        Some(STATE_NOT_STARTED) => (
            MissionState::Uploaded,
            "the vehicle holds it, not started".into(),
        ),
        _ => (
            MissionState::OnVehicle,
            "the vehicle holds this mission and has not said how far it is".into(),
        ),
    }
}

/// Reconciles every shot that has a mission with `vehicle` (Err: why it
/// could not be read); `alternatives` gives more item lists that mean a
/// shot's mission (replanned corrections). Returns the shots whose record
/// changed (state or reason), each with `details.vehicle` written, and
/// the id of the shot that owns the vehicle's mission, if one does.
pub fn reconcile(
    shots: &[Shot],
    vehicle: &Result<VehicleMission, LinkError>,
    alternatives: impl Fn(&Shot) -> Vec<Vec<MissionItem>>,
    now_unix: f64,
) -> (Vec<Shot>, Option<String>) {
    let owns = |s: &Shot| -> bool {
        let Ok(v) = vehicle else { return false };
        if v.items.is_empty() {
            return false;
        }
        planned_items(s)
            .into_iter()
            .chain(alternatives(s))
            .any(|p| same_mission(&p, &v.items, v.skip_home))
    };
    let owner = shots
        .iter()
        .filter(|s| s.mission.is_some() && owns(s))
        .max_by(|a, b| {
            let t = |s: &Shot| s.mission.as_ref().map_or(0.0, |m| m.uploaded_unix);
            t(a).total_cmp(&t(b))
        })
        .map(|s| s.id.clone());
    let mut changed = Vec::new();
    for shot in shots {
        let Some(m) = &shot.mission else { continue };
        let (new_state, reason): (MissionState, String) = match vehicle {
            Err(why) => (
                MissionState::Unknown,
                format!("the vehicle's mission could not be read: {why}"),
            ),
            Ok(v) if owner.as_deref() == Some(shot.id.as_str()) => match owner_state(v) {
                // The operator stopped it: a held (paused) mission the
                // vehicle still holds stays stopped.
                (MissionState::Active | MissionState::OnVehicle, _)
                    if m.state == MissionState::Stopped =>
                {
                    continue;
                }
                s => s,
            },
            Ok(_) if m.state == MissionState::Finished => continue,
            Ok(v) if v.items.is_empty() => {
                (MissionState::Cleared, "the vehicle holds no mission".into())
            }
            Ok(v) => (
                MissionState::Replaced,
                format!(
                    "the vehicle holds another mission ({} items)",
                    v.items.len()
                ),
            ),
        };
        let before = m.details.get("vehicle");
        if m.state == new_state
            && before.and_then(|b| b.get("reason")).and_then(Value::as_str) == Some(&reason)
        {
            continue;
        }
        let mut shot = shot.clone();
        let Some(m) = shot.mission.as_mut() else {
            continue;
        };
        let record = json!({
            "checked_unix": now_unix,
            "previous_state": m.state,
            "reason": reason,
            "vehicle_items": vehicle.as_ref().ok().map(|v| v.items.len()),
            "progress": vehicle.as_ref().ok().and_then(|v| v.progress).map(|p| json!({
                "current_seq": p.current_seq,
                "total": p.total,
                "state": p.state,
                "last_reached": p.last_reached,
            })),
        });
        m.set_detail("vehicle", record);
        m.state = new_state;
        changed.push(shot);
    }
    (changed, owner)
}

/// The shot with its refinement loop marked `interrupted` (with `reason`)
/// when the record says the loop was still running (no stop), else None.
pub fn interrupt_refinement(shot: &Shot, reason: &str) -> Option<Shot> {
    let running = shot
        .mission
        .as_ref()?
        .details
        .get("refinement")?
        .get("stop")
        .is_none_or(Value::is_null);
    if !running {
        return None;
    }
    let mut shot = shot.clone();
    let r = shot
        .mission
        .as_mut()?
        .details
        .get_mut("refinement")?
        .as_object_mut()?;
    r.insert("stop".into(), Value::from("interrupted"));
    r.insert("reason".into(), Value::from(reason));
    r.insert("restartable".into(), Value::from(true));
    Some(shot)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shot::record::{MissionRecord, ShotSource};

    fn item(seq: u16, x: i32) -> MissionItem {
        MissionItem {
            seq,
            frame: 6,
            command: 16,
            current: false,
            autocontinue: true,
            params: [0.0; 4],
            x,
            y: 85_000_000,
            z: 20.0,
        }
    }

    fn shot(id: &str, state: &str, uploaded: f64, items: &[MissionItem]) -> Shot {
        Shot {
            id: id.into(),
            created_unix: uploaded - 5.0,
            source: ShotSource::Anchors {
                keyframe_id: 1,
                anchors: [[0.0; 2]; 4],
            },
            status: crate::shot::record::ShotStatus::Localised,
            localisation: None,
            reason: None,
            nearest_keyframes: Vec::new(),
            has_image: false,
            mission: Some(MissionRecord {
                state: serde_json::from_value(json!(state)).unwrap(),
                items: items.len(),
                uploaded_unix: uploaded,
                started_unix: None,
                target_lat_lon_alt: None,
                details: json!({"planned_items": items}),
            }),
        }
    }

    fn progress(state: u8, seq: u16, reached: Option<u16>) -> Option<MissionProgress> {
        Some(MissionProgress {
            current_seq: Some(seq),
            total: Some(3),
            state: Some(state),
            last_reached: reached,
        })
    }

    #[test]
    fn the_vehicles_mission_decides_each_shots_state() {
        let a = [item(0, 1), item(1, 2), item(2, 3)];
        let b = [item(0, 1), item(1, 5), item(2, 6)];
        let shots = vec![
            shot("shot-1", "started", 100.0, &a),
            shot("shot-2", "started", 200.0, &b),
            shot("shot-3", "uploaded", 50.0, &a),
            shot("shot-4", "finished", 10.0, &[item(0, 9)]),
        ];
        let held = |p| {
            Ok(VehicleMission {
                items: a.to_vec(),
                progress: p,
                skip_home: false,
            })
        };
        // The vehicle flies shot-1's mission (shot-3 had the same items but
        // was uploaded before it): shot-2 was replaced, shot-4 stays finished.
        let (changed, owner) = reconcile(&shots, &held(progress(3, 1, Some(0))), |_| vec![], 1e9);
        assert_eq!(owner.as_deref(), Some("shot-1"));
        let states: Vec<(&str, &str)> = changed
            .iter()
            .map(|s| (s.id.as_str(), s.mission.as_ref().unwrap().state.as_str()))
            .collect();
        assert_eq!(
            states,
            [
                ("shot-1", "active"),
                ("shot-2", "replaced"),
                ("shot-3", "replaced")
            ]
        );
        let rec = &changed[1].mission.as_ref().unwrap().details["vehicle"];
        assert_eq!(rec["previous_state"], "started");
        assert_eq!(rec["vehicle_items"], 3);
        // Done, by state or by the last item reached.
        let (c, _) = reconcile(&shots, &held(progress(5, 2, Some(2))), |_| vec![], 1e9);
        assert_eq!(c[0].mission.as_ref().unwrap().state.as_str(), "finished");
        let (c, _) = reconcile(&shots, &held(progress(0, 2, Some(2))), |_| vec![], 1e9);
        assert_eq!(c[0].mission.as_ref().unwrap().state.as_str(), "finished");
        let (c, _) = reconcile(&shots, &held(progress(2, 0, None)), |_| vec![], 1e9);
        assert_eq!(c[0].mission.as_ref().unwrap().state.as_str(), "uploaded");
        let (c, _) = reconcile(&shots, &held(None), |_| vec![], 1e9);
        assert_eq!(c[0].mission.as_ref().unwrap().state.as_str(), "on_vehicle");
        // A refinement's correction is shot-2's mission too.
        let (_, owner) = reconcile(
            &shots,
            &held(None),
            |s| {
                if s.id == "shot-2" {
                    vec![a.to_vec()]
                } else {
                    vec![]
                }
            },
            1e9,
        );
        assert_eq!(owner.as_deref(), Some("shot-2"));
        // Nothing on the vehicle; nothing readable.
        let empty = Ok(VehicleMission {
            items: vec![],
            progress: None,
            skip_home: false,
        });
        let (c, owner) = reconcile(&shots, &empty, |_| vec![], 1e9);
        assert_eq!(owner, None);
        assert!(
            c.iter()
                .all(|s| s.mission.as_ref().unwrap().state.as_str() == "cleared")
        );
        assert_eq!(c.len(), 3, "finished stays finished");
        let (c, _) = reconcile(
            &shots,
            &Err(LinkError::Timeout {
                what: "MISSION_COUNT",
                seconds: 3.0,
            }),
            |_| vec![],
            1e9,
        );
        assert_eq!(c.len(), 4);
        assert!(
            c.iter()
                .all(|s| s.mission.as_ref().unwrap().state.as_str() == "unknown")
        );
        // Reconciled again with the same truth: nothing to write.
        let again: Vec<Shot> = shots
            .iter()
            .map(|s| {
                changed
                    .iter()
                    .find(|c| c.id == s.id)
                    .cloned()
                    .unwrap_or_else(|| s.clone())
            })
            .collect();
        let (c, _) = reconcile(&again, &held(progress(3, 1, Some(0))), |_| vec![], 2e9);
        assert!(c.is_empty(), "{c:?}");
    }

    #[test]
    fn a_loop_running_at_the_stop_is_marked_interrupted() {
        let mut s = shot("shot-1", "started", 1.0, &[item(0, 1)]);
        assert!(interrupt_refinement(&s, "x").is_none(), "no loop");
        s.mission.as_mut().unwrap().details["refinement"] = json!({"rounds": [], "stop": null});
        let i = interrupt_refinement(&s, "the daemon stopped").unwrap();
        let r = &i.mission.as_ref().unwrap().details["refinement"];
        assert_eq!(r["stop"], "interrupted");
        assert_eq!(r["reason"], "the daemon stopped");
        assert!(interrupt_refinement(&i, "again").is_none(), "once");
    }
}
