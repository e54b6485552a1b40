//! Fusion of a verified place into the current side (a loop's correction
//! and a merge both do it): the loop side's matched points replace the
//! current keyframe's, the loop neighbourhood's points are fused into the
//! current neighbourhood, connections are updated, and the new
//! covisibility links between the two sides are returned for the
//! essential graph.

use std::collections::{HashMap, HashSet};

use crate::matching::Bounds;
use crate::slam::map::{KeyFrameId, Map, PointId};
use crate::slam::matcher;

use super::params::LoopParams;
use super::verify::LoopMatch;

/// Fuse a verified place's points into the current side: the matched
/// loop-side points replace the current keyframe's (or are added to it),
/// the loop neighbourhood's points are fused into every keyframe of
/// `connected`, whose connections are then updated. Returns the points
/// fused and the new covisibility links between the two sides.
pub(super) fn fuse_and_link(
    map: &mut Map,
    kf: KeyFrameId,
    connected: &[KeyFrameId],
    lm: &LoopMatch,
    bounds: &Bounds,
    p: &LoopParams,
) -> (usize, Vec<(KeyFrameId, KeyFrameId)>) {
    let neighbours_before: HashMap<KeyFrameId, HashSet<KeyFrameId>> = connected
        .iter()
        .filter_map(|id| {
            map.keyframe(*id)
                .map(|k| (*id, k.covisible.iter().map(|c| c.0).collect()))
        })
        .collect();
    // Fuse the loop's matched points into the current keyframe.
    let mut fused = 0;
    for (i, m) in lm.matched.iter().enumerate() {
        let Some(lp) = m else { continue };
        if map.point(*lp).is_none() {
            continue;
        }
        let existing = map
            .keyframe(kf)
            .and_then(|k| k.points.get(i).copied().flatten());
        match existing {
            Some(cp) if cp != *lp => {
                map.replace_point(cp, *lp);
                fused += 1;
            }
            Some(_) => {}
            None => {
                if map.add_observation(*lp, kf, i as u32) {
                    fused += 1;
                }
            }
        }
        map.update_point_descriptor(*lp);
    }
    // And the loop neighbourhood's points into the current neighbourhood.
    let loop_points: Vec<PointId> = lm
        .loop_points
        .iter()
        .copied()
        .filter(|p| map.point(*p).is_some())
        .collect();
    for &id in connected {
        fused += matcher::fuse(map, id, &loop_points, p.fuse_radius, bounds, &p.matcher);
    }
    for &id in connected {
        map.update_connections(id);
    }
    // New links between the two sides.
    let connected_set: HashSet<KeyFrameId> = connected.iter().copied().collect();
    let mut loop_links: Vec<(KeyFrameId, KeyFrameId)> = Vec::new();
    for &id in connected {
        let Some(ki) = map.keyframe(id) else { continue };
        let before = neighbours_before.get(&id);
        for (o, _) in &ki.covisible {
            if connected_set.contains(o) || before.is_some_and(|b| b.contains(o)) {
                continue;
            }
            loop_links.push((id, *o));
        }
    }
    (fused, loop_links)
}
