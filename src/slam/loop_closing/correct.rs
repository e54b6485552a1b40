//! The correction of a verified loop, under the map lock: the current
//! keyframe's neighbourhood moved by the loop's Sim(3) with its points, the
//! loop's points fused in ([`super::fuse`]), the loop edge recorded, and
//! the essential graph built ([`super::graph`]) to be solved without the
//! lock; the loop's [`LoopEvent`] (its trajectory after and its times are
//! filled in when the graph is written back).

use std::collections::{HashMap, HashSet};
use std::time::Instant;

use crate::lie::Sim3;
use crate::matching::Bounds;
use crate::slam::map::{KeyFrameId, Map, PointId};
use crate::trajectory::Trajectory;

use super::fuse::fuse_and_link;
use super::graph::EssentialGraph;
use super::log::{LoopEvent, LoopSummary, keyframe_trajectory};
use super::params::LoopParams;
use super::sim3::sim3_to_isometry;
use super::verify::LoopMatch;

/// The correction under the map lock (see the module doc): the
/// neighbourhood corrected, the points fused, and the essential graph
/// built; the loop's event (its trajectory after and its time filled
/// in when the graph is applied) and the graph, to be solved without
/// the lock.
pub(super) fn correct(
    p: &LoopParams,
    bounds: &Bounds,
    map: &mut Map,
    kf: KeyFrameId,
    lm: LoopMatch,
) -> Option<(LoopEvent, EssentialGraph)> {
    let started = Instant::now();
    let before = keyframe_trajectory(map);
    map.update_connections(kf);
    let k = map.keyframe(kf)?;
    let current_t = k.timestamp;
    let t_wc = k.cam_from_world.inverse();
    let center_before = k.center();
    let mut connected: Vec<KeyFrameId> = vec![kf];
    connected.extend(k.covisible.iter().map(|c| c.0));
    // Poses: corrected and as they were.
    let mut corrected: HashMap<KeyFrameId, Sim3> = HashMap::new();
    let mut uncorrected: HashMap<KeyFrameId, Sim3> = HashMap::new();
    for &id in &connected {
        let Some(ki) = map.keyframe(id) else { continue };
        let s_ic = Sim3::from_isometry(&(ki.cam_from_world * t_wc));
        corrected.insert(id, s_ic.compose(&lm.s_cw));
        uncorrected.insert(id, Sim3::from_isometry(&ki.cam_from_world));
    }
    // Points of the neighbourhood follow their keyframe.
    let mut corrected_by: HashMap<PointId, KeyFrameId> = HashMap::new();
    for &id in &connected {
        let (Some(s_new), Some(s_old)) = (corrected.get(&id), uncorrected.get(&id)) else {
            continue;
        };
        let s_move = s_new.inverse().compose(s_old);
        let pids: Vec<PointId> = map
            .keyframe(id)
            .map(|k| k.points.iter().flatten().copied().collect())
            .unwrap_or_default();
        for pid in pids {
            if corrected_by.contains_key(&pid) {
                continue;
            }
            if let Some(mp) = map.point_mut(pid) {
                mp.position = s_move.transform_point(&mp.position);
                corrected_by.insert(pid, id);
            }
        }
    }
    for (&id, s) in &corrected {
        if let Some(ki) = map.keyframe_mut(id) {
            ki.cam_from_world = sim3_to_isometry(s);
        }
    }
    for pid in corrected_by.keys().copied().collect::<Vec<_>>() {
        map.update_point_normal_and_depth(pid);
    }
    let (fused, loop_links) = fuse_and_link(map, kf, &connected, &lm, bounds, p);
    map.add_loop_edge(kf, lm.loop_kf);
    let graph_kfs: Vec<KeyFrameId> = match map.map_of(kf) {
        Some(id) => map.keyframes_in(id).map(|k| k.id).collect(),
        None => map.keyframes().map(|k| k.id).collect(),
    };
    let graph = EssentialGraph::build(
        map,
        graph_kfs,
        &HashSet::from([lm.loop_kf]),
        lm.loop_kf,
        kf,
        &corrected,
        &uncorrected,
        corrected_by,
        &loop_links,
        p,
        started,
    );
    // The neighbourhood moved already: tracking re-places its frame.
    map.note_correction();
    let corr = lm.s_cw.compose(&Sim3::from_isometry(&t_wc));
    let center_after = sim3_to_isometry(&lm.s_cw).inverse().translation.vector;
    let loop_t = map.keyframe(lm.loop_kf).map_or(0.0, |k| k.timestamp);
    let event = LoopEvent {
        summary: LoopSummary {
            current: kf,
            loop_kf: lm.loop_kf,
            current_t,
            loop_t,
            inliers: lm.inliers,
            projection_matches: lm.projection_matches,
            scale: corr.scale,
            rotation_deg: corr.rotation.angle().to_degrees(),
            translation: (center_after - center_before).norm(),
            fused,
            correction_ms: 0.0,
            global_ba_ms: None,
        },
        graph_edges: graph.edges,
        keyframes_before: before,
        keyframes_after: Trajectory { poses: Vec::new() },
        global_ba_rmse_px: None,
        global_ba_window: None,
        correction_window: None,
    };
    Some((event, graph))
}
