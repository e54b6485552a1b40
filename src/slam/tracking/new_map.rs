//! A new map after a loss: started beside the old ones (after a loss, or
//! while the telemetry poses frames alone), initialised while
//! relocalisation into the old maps goes on, and, with the telemetry's aid
//! in a map in local NED, put into the old map at once
//! ([`aided::place_new_map`]) and rescaled over a longer baseline
//! ([`aided::refit_placement`]).

use std::sync::Mutex;

use nalgebra::Isometry3;

use super::super::aided;
use super::super::frame::Frame;
use super::super::initializer::InitialMap;
use super::super::map::{Map, MapId, MapMode, lock, lock_timed};
use super::{FrameOutcome, MapStart, PoseSource, TrackFailure, Tracked, Tracker};

impl Tracker {
    /// Lost for long enough: start a new map (the initializer takes the
    /// next frames; the old maps are kept and relocalisation into them is
    /// still tried).
    pub(super) fn maybe_start_new_map(&mut self, map: &Mutex<Map>, index: u64) {
        let (Some(after), Some(lost_at)) = (
            self.ctx.params.new_map_after_lost_frames,
            self.lost_since.or(self.telemetry_since),
        ) else {
            return;
        };
        if self.new_map_pending || index < lost_at + after {
            return;
        }
        if self.new_maps_need_placement && self.aid.is_none() {
            // Only a map the telemetry can put into this one (see
            // `track_or_start_new_map`).
            return;
        }
        let mut m = lock(map);
        let in_ned = m.mode() == MapMode::GpsAided;
        let id = m.start_map();
        drop(m);
        // A map the telemetry is to put into this one waits for a GNSS
        // baseline that fixes its scale.
        self.initializer
            .set_need_gnss_baseline(self.aid.is_some() && self.anchor.is_some() && in_ned);
        self.initializer.reset();
        self.new_map_pending = true;
        tracing::info!(
            lost_at,
            frame = index,
            map = id.0,
            "tracking lost: starting a new map"
        );
        self.map_starts.push(MapStart {
            lost_at,
            started_at: index + 1,
            map: id,
            initialized_at: None,
            relocalized_at: None,
            placed_by_telemetry: false,
        });
    }

    /// A frame while a new map is being initialised: relocalisation into
    /// the old maps first (success abandons the new map), else the
    /// initializer. With the telemetry's aid, the old map keeps the frames
    /// the telemetry poses meanwhile (the initializer sees them too), and
    /// a new map that initialises is put into the old one at once
    /// ([`aided::place_new_map`]).
    pub(super) fn track_or_start_new_map(
        &mut self,
        map: &Mutex<Map>,
        mut frame: Frame,
        mapping_idle: bool,
        out: &mut FrameOutcome,
    ) -> Result<Option<Tracked>, TrackFailure> {
        let index = frame.index;
        if let Some(start) = self.map_starts.last_mut()
            && start.started_at > index
        {
            start.started_at = index;
        }
        let old_map = self.anchor_map(map);
        let relocalised = {
            let mut m = lock_timed(map, &mut out.lock_wait_ms);
            if let Some(old) = old_map {
                // A keyframe of a frame tracked again goes to the old map.
                m.set_active_map(old);
            }
            self.track_frame(&mut m, &mut frame, mapping_idle)
        };
        let by_telemetry = match relocalised {
            Ok(tracked) if tracked.source != PoseSource::Telemetry => {
                out.keypoints = frame.keypoint_states();
                self.new_map_pending = false;
                self.initializer.reset();
                self.initializer.set_need_gnss_baseline(false);
                if let Some(start) = self.map_starts.last_mut() {
                    start.relocalized_at = Some(index);
                }
                tracing::info!(
                    frame = index,
                    source = tracked.source.name(),
                    "tracked again in an old map: the new map is abandoned"
                );
                return Ok(Some(tracked));
            }
            Ok(tracked) => Some(tracked),
            Err(_) => None,
        };
        frame.clear_matches();
        frame.prior = None;
        out.keypoints = frame.keypoint_states();
        if let Some(start) = self.map_starts.last() {
            // A relocalisation that then failed on the local map may have
            // switched the active map: the initializer builds the new one.
            lock(map).set_active_map(start.map);
        }
        match self.initializer.step(&self.ctx, map, frame) {
            Ok(Some(initial)) => {
                let placed = self.place_by_telemetry(map, &initial);
                let in_ned = lock(map).mode() == MapMode::GpsAided;
                if placed.is_none() && self.new_maps_need_placement && !in_ned {
                    // The old maps never reached local NED (the priors
                    // fit a map only once its fixes span a baseline): they
                    // give way to the new one, whose frame the priors
                    // will fit.
                    let mut m = lock(map);
                    let new = m.active_map();
                    let old: Vec<MapId> = m
                        .maps()
                        .into_iter()
                        .map(|(id, _)| id)
                        .filter(|id| *id != new)
                        .collect();
                    for id in &old {
                        m.discard_map(*id);
                    }
                    tracing::info!(
                        frame = initial.second.index,
                        dropped = old.len(),
                        "the old map never reached local NED: dropped for the new one"
                    );
                }
                if placed.is_none() && self.new_maps_need_placement && in_ned {
                    // A map in local NED cannot hold a map beside it in
                    // its own frame: this one is dropped and started again.
                    let mut m = lock(map);
                    let active = m.active_map();
                    m.discard_map(active);
                    let id = m.start_map();
                    if let Some(start) = self.map_starts.last_mut() {
                        start.map = id;
                    }
                    self.initializer.reset();
                    return match by_telemetry {
                        Some(t) => Ok(Some(t)),
                        None => Err(TrackFailure::RelocalizationFailed),
                    };
                }
                out.initialized = true;
                self.new_map_pending = false;
                if let Some(start) = self.map_starts.last_mut() {
                    start.initialized_at = Some(initial.second.index);
                    start.placed_by_telemetry = placed.is_some();
                }
                // The telemetry's records of the two frames give way to
                // the map's.
                let (a, b) = (initial.first.index, initial.second.index);
                self.records.retain(|r| r.index != a && r.index != b);
                let mut initial = initial;
                if let Some(pose) = placed {
                    initial.cam_from_world = pose;
                }
                Ok(Some(self.start_tracking(initial)))
            }
            Ok(None) | Err(_) if by_telemetry.is_some() => Ok(by_telemetry),
            Ok(None) => Err(TrackFailure::RelocalizationFailed),
            Err(failure) => Err(TrackFailure::Init(failure)),
        }
    }

    /// The map of the telemetry's anchor (the old map a new one is put
    /// into).
    fn anchor_map(&self, map: &Mutex<Map>) -> Option<MapId> {
        let a = self.anchor.as_ref()?;
        lock(map).map_of(a.record.reference)
    }

    /// Put a new map that just initialised into the anchor's map by the
    /// telemetry ([`aided::place_new_map`]); the second frame's pose in
    /// the merged map when done.
    fn place_by_telemetry(
        &mut self,
        map: &Mutex<Map>,
        initial: &InitialMap,
    ) -> Option<Isometry3<f64>> {
        let (aid, anchor) = (self.aid.as_ref()?, self.anchor.as_ref()?);
        let mut m = lock(map);
        let into = m.map_of(anchor.record.reference)?;
        let from = m.map_of(initial.second.keyframe)?;
        let poses = (
            m.keyframe_pose(initial.first.keyframe)?,
            m.keyframe_pose(initial.second.keyframe)?,
        );
        let placed = aided::place_new_map(
            aid,
            &m,
            anchor,
            (initial.first.timestamp, &poses.0),
            (initial.second.timestamp, &poses.1),
        );
        let sim = match placed {
            Ok(s) => s,
            Err(why) => {
                tracing::info!(
                    frame = initial.second.index,
                    why,
                    "new map not put into the old one by the telemetry"
                );
                return None;
            }
        };
        if !m.merge_maps(
            from,
            into,
            &sim,
            initial.second.keyframe,
            anchor.record.reference,
        ) {
            return None;
        }
        tracing::info!(
            frame = initial.second.index,
            from = from.0,
            into = into.0,
            scale = sim.scale,
            gap_s = initial.second.timestamp - anchor.sample.t,
            "new map put into the old one by the telemetry"
        );
        self.placement = Some(aided::Placement {
            first_kf: initial.first.keyframe,
        });
        m.keyframe_pose(initial.second.keyframe)
    }

    /// Refit the scale and place of the last map the telemetry put into
    /// the old one, once its keyframes span a long enough GNSS baseline
    /// ([`aided::refit_placement`]).
    pub(super) fn refit_placement(&mut self, map: &mut Map) {
        let (Some(aid), Some(placement)) = (self.aid.as_ref(), self.placement.as_ref()) else {
            return;
        };
        match aided::refit_placement(aid, map, placement) {
            Ok(None) => return,
            Ok(Some(sim)) => {
                tracing::info!(
                    first_kf = placement.first_kf.0,
                    scale = sim.scale,
                    moved_m = sim.translation.norm(),
                    "placed map refit to the GNSS over a longer baseline"
                );
                // The last frame follows its (moved) reference keyframe.
                self.corrections_seen = map.corrections();
                self.follow_correction(map);
            }
            Err(why) => tracing::info!(why, "placed map not refit"),
        }
        self.placement = None;
    }
}
