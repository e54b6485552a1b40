//! Map merging (ORB-SLAM3's welding merge, monocular; see the module doc):
//! at a keyframe of the active map, consistent candidates in the other maps
//! ([`super::detect`]), verified like loops without the drift bounds
//! ([`super::verify`]), and a map similarity that consecutive keyframes
//! agree on; then the merge: the active map moved into the old one
//! ([`crate::slam::map::Map::merge_maps`]), the place's points fused, a
//! welding bundle adjustment (the old side fixed), and the merged map's
//! essential graph with the old map's keyframes fixed.

use std::collections::{HashMap, HashSet};
use std::time::Instant;

use crate::lie::Sim3;
use crate::matching::Bounds;
use crate::slam::bundle::run_bundle_adjustment;
use crate::slam::map::{KeyFrame, KeyFrameId, Map, MapId, PointId};

use super::detect::detect;
use super::fuse::fuse_and_link;
use super::graph::optimize_essential_graph;
use super::log::{LoopRefusal, LoopReject, MergeEvent, MergeSummary, map_trajectory};
use super::params::LoopParams;
use super::verify::{LoopMatch, verify_one};

/// Merge detection at `kf` (see the module doc): consistent BoW
/// candidates in other maps (`groups`: the previous keyframe's), verified
/// like loops (refusals to `refusals`), and a map similarity that
/// consecutive keyframes agree on (`pending`: the previous keyframe's);
/// then the merge. The merge made, if any.
pub(super) fn look_for_merge(
    p: &LoopParams,
    bounds: &Bounds,
    map: &mut Map,
    kf: KeyFrameId,
    groups: &mut Vec<(HashSet<KeyFrameId>, usize)>,
    pending: &mut Option<(MapId, Sim3, usize)>,
    refusals: &mut Vec<LoopRefusal>,
) -> Option<MergeEvent> {
    if map.map_of(kf) != Some(map.active_map()) {
        groups.clear();
        *pending = None;
        return None;
    }
    let candidates = detect(p, None, groups, map, kf, true);
    let mut verified = None;
    for &c in &candidates {
        match verify_one(p, bounds, map, kf, c, false) {
            Ok(m) => {
                verified = Some(m);
                break;
            }
            Err(why) => refuse(map, kf, c, why, refusals),
        }
    }
    let Some(lm) = verified else {
        *pending = None;
        return None;
    };
    let (Some(k1), Some(other)) = (map.keyframe(kf), map.map_of(lm.loop_kf)) else {
        return None;
    };
    // The map similarity: old world <- active world.
    let s = lm
        .s_cw
        .inverse()
        .compose(&Sim3::from_isometry(&k1.cam_from_world));
    let agreed = match *pending {
        Some((m, prev, n)) if m == other => {
            if similarities_agree(p, map, &prev, &s, k1, lm.loop_kf) {
                n + 1
            } else {
                refuse(map, kf, lm.loop_kf, LoopReject::Disagreement, refusals);
                0
            }
        }
        _ => 0,
    };
    if agreed < p.merge_confirmations {
        *pending = Some((other, s, agreed));
        return None;
    }
    *pending = None;
    merge(p, bounds, map, kf, other, &s, lm)
}

/// Record a merge candidate refused.
fn refuse(
    map: &Map,
    kf: KeyFrameId,
    c: KeyFrameId,
    why: LoopReject,
    refusals: &mut Vec<LoopRefusal>,
) {
    tracing::debug!(
        current = kf.0,
        candidate = c.0,
        ?why,
        "merge candidate refused"
    );
    let t = |id| map.keyframe(id).map_or(f64::NAN, |k| k.timestamp);
    refusals.push(LoopRefusal {
        current: kf,
        candidate: c,
        current_t: t(kf),
        candidate_t: t(c),
        reason: why,
    });
}

/// Whether two map similarities (old ← active) found at consecutive
/// keyframes agree: scale, rotation, and where they put the current
/// camera (relative to the old keyframe's scene depth).
fn similarities_agree(
    p: &LoopParams,
    map: &Map,
    a: &Sim3,
    b: &Sim3,
    k1: &KeyFrame,
    old_kf: KeyFrameId,
) -> bool {
    let ratio = a.scale / b.scale;
    let max_r = p.merge_max_scale_ratio.max(1.0);
    let rot = (a.rotation.inverse() * b.rotation).angle().to_degrees();
    let c = nalgebra::Point3::from(k1.center());
    let shift = (a.transform_point(&c) - b.transform_point(&c)).norm();
    let depth = map.median_depth(old_kf).unwrap_or(0.0);
    let ok = ratio <= max_r
        && ratio >= 1.0 / max_r
        && rot <= p.merge_max_rotation_deg
        && shift <= p.merge_max_shift_ratio * depth;
    tracing::debug!(ratio, rot, shift, depth, ok, "merge: similarities compared");
    ok
}

/// The merge (see the module doc): the active map moved by `s` into
/// `other`, the common place's points fused, the weld bundle-adjusted,
/// the essential graph of the merged map optimised with the old map
/// anchored.
fn merge(
    p: &LoopParams,
    bounds: &Bounds,
    map: &mut Map,
    kf: KeyFrameId,
    other: MapId,
    s: &Sim3,
    lm: LoopMatch,
) -> Option<MergeEvent> {
    let t0 = Instant::now();
    let from = map.map_of(kf)?;
    let old_map_before = map_trajectory(map, other);
    let new_map_before = map_trajectory(map, from);
    let anchored: HashSet<KeyFrameId> = map.keyframes_in(other).map(|k| k.id).collect();
    let keyframes_moved = map.keyframes_in(from).count();
    if !map.merge_maps(from, other, s, kf, lm.loop_kf) {
        return None;
    }
    map.update_connections(kf);
    let k = map.keyframe(kf)?;
    let current_t = k.timestamp;
    let mut connected: Vec<KeyFrameId> = vec![kf];
    connected.extend(
        k.covisible
            .iter()
            .map(|c| c.0)
            .filter(|id| !anchored.contains(id)),
    );
    let (fused, loop_links) = fuse_and_link(map, kf, &connected, &lm, bounds, p);
    map.add_loop_edge(kf, lm.loop_kf);
    // Weld: the current neighbourhood free, the old side fixed.
    let before_ba: HashMap<KeyFrameId, Sim3> = connected
        .iter()
        .filter_map(|id| {
            map.keyframe(*id)
                .map(|k| (*id, Sim3::from_isometry(&k.cam_from_world)))
        })
        .collect();
    let mut weld: Vec<KeyFrameId> = connected.clone();
    let old_side: Vec<KeyFrameId> = std::iter::once(lm.loop_kf)
        .chain(
            map.keyframe(lm.loop_kf)
                .map_or_else(Vec::new, |k| k.covisible.iter().map(|c| c.0).collect()),
        )
        .filter(|id| anchored.contains(id))
        .collect();
    weld.extend(old_side.iter().copied());
    let report = run_bundle_adjustment(map, &weld, &old_side, &p.merge_ba);
    if let Some(r) = &report {
        tracing::debug!(
            before = r.initial_rmse_px,
            after = r.final_rmse_px,
            outliers = r.n_outliers,
            "merge: welding BA"
        );
    }
    let after_ba: HashMap<KeyFrameId, Sim3> = connected
        .iter()
        .filter_map(|id| {
            map.keyframe(*id)
                .map(|k| (*id, Sim3::from_isometry(&k.cam_from_world)))
        })
        .collect();
    let mut corrected_by: HashMap<PointId, KeyFrameId> = HashMap::new();
    for &id in &connected {
        if let Some(k) = map.keyframe(id) {
            for pid in k.points.iter().flatten() {
                corrected_by.entry(*pid).or_insert(id);
            }
        }
    }
    let graph_kfs: Vec<KeyFrameId> = map.keyframes_in(other).map(|k| k.id).collect();
    let graph_edges = optimize_essential_graph(
        map,
        graph_kfs,
        &anchored,
        lm.loop_kf,
        kf,
        &after_ba,
        &before_ba,
        corrected_by,
        &loop_links,
        p,
    );
    map.note_correction();
    Some(MergeEvent {
        summary: MergeSummary {
            current: kf,
            merge_kf: lm.loop_kf,
            current_t,
            merge_t: map.keyframe(lm.loop_kf).map_or(0.0, |k| k.timestamp),
            from_map: from,
            into_map: other,
            inliers: lm.inliers,
            projection_matches: lm.projection_matches,
            scale: s.scale,
            keyframes_moved,
            fused,
            correction_ms: t0.elapsed().as_secs_f64() * 1e3,
        },
        graph_edges,
        old_map_before,
        new_map_before,
        keyframes_after: map_trajectory(map, other),
    })
}
