//! Shot events: what happened to each shot, typed, for the `/events`
//! stream (`event: shot`) that the page's per-shot timeline is drawn from.
//!
//! [`ShotEvents`] is the hub: the API (a shot created, uploaded, started,
//! stopped) and the daemon's refinement loop (flying with the distance to
//! the target, arrived, each round with its error, the live outline of the
//! desired shot, done) publish; every `/events` client first gets the
//! kept history (milestones, and of the frequent `flying` and `overlay`
//! events only the newest per shot and round), then the live
//! events. The hub also keeps, per shot, the live frame of its last
//! refinement round ([`Achieved`]) for the before/after view.
//!
//! The `status` events of the same stream are sent as deltas: the whole
//! status document when a client connects, then only what changed
//! ([`status_patch`], a JSON merge patch, `event: status_patch`), and
//! nothing when nothing did. A client that reconnects gets the whole
//! document again, so it never builds on a patch it missed.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use image::GrayImage;
use serde::Serialize;
use serde_json::{Map, Value};
use tokio::sync::broadcast;

use crate::video::live::unix_now;

/// Milestone events kept for clients that connect later.
const KEEP_EVENTS: usize = 1000;
/// Shots whose achieved frame is kept (memory only: gone after a restart).
const KEEP_ACHIEVED: usize = 16;
/// Live events buffered per slow client before it skips.
const CHANNEL: usize = 256;

/// What happened to a shot (`kind`).
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ShotEvent {
    /// The shot was localised in the map.
    Localised {
        /// PnP inliers.
        inliers: usize,
        /// Reprojection error, pixels.
        rms_error_px: f64,
        /// The pose's position sigma, % of the distance to the nearest
        /// scene content (None: the shot reports no sigma).
        position_sigma_pct: Option<f64>,
        /// The pose's rotation sigma, degrees.
        rotation_sigma_deg: Option<f64>,
    },
    /// The shot could not be localised.
    NotLocalised {
        /// Why.
        reason: String,
    },
    /// Its pose went through the georeference to a target (at upload).
    Georeferenced {
        /// Target latitude, degrees.
        lat_deg: f64,
        /// Target longitude, degrees.
        lon_deg: f64,
        /// Target altitude above home, metres.
        alt_m: f64,
        /// Vehicle heading, degrees.
        yaw_deg: f64,
        /// Gimbal pitch, degrees.
        gimbal_pitch_deg: f64,
        /// The shot's position sigma in metres (its sigma in map units
        /// times the georeference's scale; None: no sigma reported).
        position_sigma_m: Option<f64>,
    },
    /// Its mission was uploaded (and read back).
    Uploaded {
        /// Mission items.
        items: usize,
    },
    /// Its mission was started.
    Started,
    /// The vehicle flies to the round's target (at most one a second).
    Flying {
        /// The refinement round (0: the first flight).
        round: usize,
        /// Straight-line distance to the target, metres.
        distance_m: f64,
        /// Its horizontal part, metres.
        horizontal_m: f64,
        /// Its vertical part, metres: the target's altitude less the
        /// vehicle's (positive: the target is higher).
        vertical_m: f64,
        /// The straight-line distance when this round's flight began
        /// (its first report), metres: a correction's length.
        start_m: f64,
    },
    /// On the approach, the georeference refitted in flight moved the
    /// round's target beyond a fit's noise: the moved target is flown
    /// instead (`[refine.approach]`).
    Retargeted {
        /// The refinement round.
        round: usize,
        /// How far the target moved, metres (3-D).
        shift_m: f64,
        /// Its heading's turn, degrees.
        yaw_deg: f64,
        /// Its gimbal pitch's turn, degrees.
        pitch_deg: f64,
        /// Re-targets flown on this round's approach so far.
        count: usize,
    },
    /// The vehicle reached the round's target and holds still.
    Arrived {
        /// The refinement round.
        round: usize,
    },
    /// The desired shot's outline in the live frame (the shot error's
    /// homography `live ← desired` applied to its corners), about once a
    /// second while the refinement loop runs.
    Overlay {
        /// The live frame's size, pixels.
        width: u32,
        /// The live frame's height, pixels.
        height: u32,
        /// The desired picture's corners (top-left, top-right,
        /// bottom-right, bottom-left) in the live frame, pixels; None when
        /// no homography was found.
        corners_px: Option<[[f64; 2]; 4]>,
        /// The shot error of this frame, % of the diagonal.
        shot_error_pct: Option<f64>,
        /// Homography inliers.
        inliers: Option<usize>,
        /// Why there is no outline.
        note: Option<String>,
    },
    /// A refinement round was measured.
    Round {
        /// The round.
        round: usize,
        /// Shot error (median over the round's frames), % of the diagonal.
        shot_error_pct: Option<f64>,
        /// The shot's floor, % of the diagonal, when known.
        floor_pct: Option<f64>,
        /// The decision (`correct`, `converged`, ...).
        decision: String,
        /// Why the error is missing or the loop cannot go on.
        note: Option<String>,
    },
    /// The refinement loop ended on its own (`stop`: converged, at_floor,
    /// max_rounds, ... or aborted).
    Done {
        /// Why it stopped (short name).
        stop: String,
        /// Details.
        reason: Option<String>,
    },
    /// The operator stopped the vehicle while this shot was flown.
    Stopped {
        /// Why.
        reason: String,
    },
}

impl ShotEvent {
    /// Frequent events: only the newest per shot (and round, for
    /// `flying`) is kept; this is its key.
    fn frequent_key(&self) -> Option<(u8, usize)> {
        match self {
            ShotEvent::Flying { round, .. } => Some((0, *round)),
            ShotEvent::Overlay { .. } => Some((1, 0)),
            _ => None,
        }
    }
}

/// One event as sent: its number, time and shot.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct ShotEventRecord {
    /// Increasing from 1 within a daemon run.
    pub seq: u64,
    /// When, unix seconds.
    pub at_unix: f64,
    /// The shot's id.
    pub shot: String,
    /// What happened.
    #[serde(flatten)]
    pub event: ShotEvent,
}

/// The live frame of a shot's last refinement round, for the before/after
/// view.
#[derive(Debug, Clone)]
pub struct Achieved {
    /// The live frame.
    pub frame: Arc<GrayImage>,
    /// The round it was measured in.
    pub round: usize,
    /// The round's shot error, % of the diagonal.
    pub shot_error_pct: Option<f64>,
    /// The desired picture's corners in this frame, pixels.
    pub corners_px: Option<[[f64; 2]; 4]>,
}

/// The hub (see the module's documentation).
#[derive(Debug)]
pub struct ShotEvents {
    tx: broadcast::Sender<Arc<ShotEventRecord>>,
    seq: AtomicU64,
    log: Mutex<VecDeque<Arc<ShotEventRecord>>>,
    achieved: Mutex<VecDeque<(String, Achieved)>>,
}

impl Default for ShotEvents {
    fn default() -> Self {
        Self {
            tx: broadcast::channel(CHANNEL).0,
            seq: AtomicU64::new(0),
            log: Mutex::new(VecDeque::new()),
            achieved: Mutex::new(VecDeque::new()),
        }
    }
}

impl ShotEvents {
    /// Publishes `event` about `shot`.
    pub fn publish(&self, shot: &str, event: ShotEvent) {
        let mut log = self.log.lock().unwrap_or_else(|e| e.into_inner());
        // Numbered under the log's lock: the history is in order.
        let rec = Arc::new(ShotEventRecord {
            seq: self.seq.fetch_add(1, Ordering::Relaxed) + 1,
            at_unix: unix_now(),
            shot: shot.to_owned(),
            event,
        });
        if let Some(key) = rec.event.frequent_key() {
            log.retain(|r| r.shot != shot || r.event.frequent_key() != Some(key));
        }
        log.push_back(rec.clone());
        while log.len() > KEEP_EVENTS {
            log.pop_front();
        }
        // No receiver is fine.
        let _ = self.tx.send(rec);
    }

    /// The kept history and a receiver of what comes after it.
    pub fn subscribe(
        &self,
    ) -> (
        Vec<Arc<ShotEventRecord>>,
        broadcast::Receiver<Arc<ShotEventRecord>>,
    ) {
        let log = self.log.lock().unwrap_or_else(|e| e.into_inner());
        (log.iter().cloned().collect(), self.tx.subscribe())
    }

    /// Keeps the live frame of `shot`'s latest round.
    pub fn set_achieved(&self, shot: &str, a: Achieved) {
        let mut m = self.achieved.lock().unwrap_or_else(|e| e.into_inner());
        m.retain(|(id, _)| id != shot);
        m.push_back((shot.to_owned(), a));
        while m.len() > KEEP_ACHIEVED {
            m.pop_front();
        }
    }

    /// The live frame of `shot`'s latest round, if kept.
    pub fn achieved(&self, shot: &str) -> Option<Achieved> {
        let m = self.achieved.lock().unwrap_or_else(|e| e.into_inner());
        m.iter().find(|(id, _)| id == shot).map(|(_, a)| a.clone())
    }
}

/// The JSON merge patch (RFC 7386) that turns `old` into `new`, None when
/// they are equal: objects are compared member by member (recursively),
/// anything else (numbers, strings, arrays) is sent whole when it changed.
/// A member `new` no longer has is sent as `null`; so is a member whose
/// value became `null` (a client applying the patch with
/// [`apply_status_patch`] reads both as null).
pub fn status_patch(old: &Value, new: &Value) -> Option<Value> {
    if old == new {
        return None;
    }
    match (old, new) {
        (Value::Object(o), Value::Object(n)) => {
            let mut patch = Map::new();
            for (k, nv) in n {
                match o.get(k) {
                    Some(ov) => {
                        if let Some(p) = status_patch(ov, nv) {
                            patch.insert(k.clone(), p);
                        }
                    }
                    None => {
                        patch.insert(k.clone(), nv.clone());
                    }
                }
            }
            for k in o.keys() {
                if !n.contains_key(k) {
                    patch.insert(k.clone(), Value::Null);
                }
            }
            Some(Value::Object(patch))
        }
        // An object replacing a non-object is sent whole; it is applied
        // whole (see apply_status_patch).
        _ => Some(new.clone()),
    }
}

/// Applies a [`status_patch`] to `doc` as the operator's page does: an
/// object patch onto an object merges member by member, anything else
/// replaces the value (`null` included: the member reads as null).
pub fn apply_status_patch(doc: &mut Value, patch: &Value) {
    match (doc, patch) {
        (Value::Object(d), Value::Object(p)) => {
            for (k, pv) in p {
                match d.get_mut(k) {
                    Some(dv) if dv.is_object() && pv.is_object() => apply_status_patch(dv, pv),
                    _ => {
                        d.insert(k.clone(), pv.clone());
                    }
                }
            }
        }
        (d, p) => *d = p.clone(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `v` without its null members (a member sent as null reads as absent).
    fn without_nulls(v: &Value) -> Value {
        match v {
            Value::Object(m) => Value::Object(
                m.iter()
                    .filter(|(_, x)| !x.is_null())
                    .map(|(k, x)| (k.clone(), without_nulls(x)))
                    .collect(),
            ),
            Value::Array(a) => Value::Array(a.iter().map(without_nulls).collect()),
            x => x.clone(),
        }
    }

    #[test]
    fn status_patches_carry_only_what_changed_and_rebuild_the_document() {
        use serde_json::json;
        let docs = [
            json!({"uptime_s": 1.0, "video": {"counters": {"received": 10, "bad": 0}, "width": null, "source": {"kind": "mjpeg"}},
                   "slam": {"state": "tracking", "loops": []}, "vehicle": {"configured": false}, "shots": 0}),
            // The uptime and one counter move; the width appears.
            json!({"uptime_s": 1.5, "video": {"counters": {"received": 17, "bad": 0}, "width": 640, "source": {"kind": "mjpeg"}},
                   "slam": {"state": "tracking", "loops": []}, "vehicle": {"configured": false}, "shots": 0}),
            // Nothing changed.
            json!({"uptime_s": 1.5, "video": {"counters": {"received": 17, "bad": 0}, "width": 640, "source": {"kind": "mjpeg"}},
                   "slam": {"state": "tracking", "loops": []}, "vehicle": {"configured": false}, "shots": 0}),
            // A loop closed (an array grows), the vehicle object is new,
            // the source lost a member, the width went back to null.
            json!({"uptime_s": 2.0, "video": {"counters": {"received": 17, "bad": 0}, "width": null, "source": {}},
                   "slam": {"state": "tracking", "loops": [{"current_kf": 9, "loop_kf": 1}]},
                   "vehicle": {"configured": true, "position": {"ned_m": [1.0, 2.0, -3.0]}}, "shots": 1}),
            // An object becomes a scalar and back.
            json!({"uptime_s": 2.5, "video": 7, "slam": {"state": "lost", "loops": []}, "vehicle": {"configured": true}, "shots": 1}),
            json!({"uptime_s": 3.0, "video": {"counters": {"received": 30}}, "slam": {"state": "lost", "loops": []}, "vehicle": {"configured": true}, "shots": 1}),
        ];
        let mut page = docs[0].clone();
        let mut sent = Vec::new();
        for w in docs.windows(2) {
            let p = status_patch(&w[0], &w[1]);
            if let Some(p) = &p {
                apply_status_patch(&mut page, p);
            }
            assert_eq!(without_nulls(&page), without_nulls(&w[1]), "{p:?}");
            sent.push(p);
        }
        assert_eq!(
            sent[0],
            Some(json!({"uptime_s": 1.5, "video": {"counters": {"received": 17}, "width": 640}}))
        );
        assert_eq!(sent[1], None);
        assert_eq!(
            sent[2],
            Some(
                json!({"uptime_s": 2.0, "video": {"width": null, "source": {"kind": null}},
                        "slam": {"loops": [{"current_kf": 9, "loop_kf": 1}]},
                        "vehicle": {"configured": true, "position": {"ned_m": [1.0, 2.0, -3.0]}}, "shots": 1})
            )
        );
        // A patch is applied whole where the page holds no object.
        let mut d = json!({"a": 1});
        apply_status_patch(&mut d, &json!({"a": {"b": null, "c": 2}}));
        assert_eq!(d, json!({"a": {"b": null, "c": 2}}));
    }

    #[test]
    fn history_keeps_milestones_and_only_the_newest_frequent_event() {
        let hub = ShotEvents::default();
        let (old, mut rx) = hub.subscribe();
        assert!(old.is_empty());
        hub.publish("shot-1", ShotEvent::Started);
        for d in [30.0, 20.0, 10.0] {
            hub.publish(
                "shot-1",
                ShotEvent::Flying {
                    round: 0,
                    distance_m: d,
                    horizontal_m: d,
                    vertical_m: 0.0,
                    start_m: 30.0,
                },
            );
        }
        hub.publish(
            "shot-2",
            ShotEvent::Flying {
                round: 0,
                distance_m: 5.0,
                horizontal_m: 4.9,
                vertical_m: 1.0,
                start_m: 5.0,
            },
        );
        hub.publish("shot-1", ShotEvent::Arrived { round: 0 });
        // The next round's flight is kept beside the first's.
        hub.publish(
            "shot-1",
            ShotEvent::Flying {
                round: 1,
                distance_m: 2.0,
                horizontal_m: 2.0,
                vertical_m: 0.0,
                start_m: 2.0,
            },
        );
        // Live: every event, in order.
        let mut seqs = Vec::new();
        while let Ok(r) = rx.try_recv() {
            seqs.push(r.seq);
        }
        assert_eq!(seqs, [1, 2, 3, 4, 5, 6, 7]);
        // History: the milestones and the newest flying event per shot.
        let (hist, _) = hub.subscribe();
        let kinds: Vec<(u64, &str)> = hist.iter().map(|r| (r.seq, r.shot.as_str())).collect();
        assert_eq!(
            kinds,
            [
                (1, "shot-1"),
                (4, "shot-1"),
                (5, "shot-2"),
                (6, "shot-1"),
                (7, "shot-1")
            ]
        );
        assert_eq!(
            hist[1].event,
            ShotEvent::Flying {
                round: 0,
                distance_m: 10.0,
                horizontal_m: 10.0,
                vertical_m: 0.0,
                start_m: 30.0,
            }
        );
        let json = serde_json::to_value(&*hist[3]).unwrap();
        assert_eq!(json["kind"], "arrived");
        assert_eq!(json["round"], 0);
        assert_eq!(json["shot"], "shot-1");
    }
}
