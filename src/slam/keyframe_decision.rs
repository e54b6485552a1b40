//! The keyframe decision (ORB-SLAM's `NeedNewKeyFrame`, stella_vslam's
//! keyframe inserter): a tracked frame becomes a keyframe when mapping is
//! idle, enough frames passed since the last keyframe (or mapping is idle
//! and the minimum passed), and the frame tracks clearly fewer points than
//! its reference keyframe while still tracking some.

use super::map::{KeyFrameId, Map};
use super::params::TrackingParams;

/// What the decision looks at besides the map.
#[derive(Debug, Clone, Copy)]
pub(super) struct KeyFrameCandidate {
    /// Index of the tracked frame.
    pub frame_index: u64,
    /// Index of the frame the last keyframe was made from.
    pub last_keyframe_frame: u64,
    /// The frame's inliers after the local map.
    pub inliers: usize,
    /// Whether mapping can take a keyframe now.
    pub mapping_idle: bool,
    /// Whether the frame comes shortly after a relocalisation.
    pub recently_relocalized: bool,
    /// The frame's reference keyframe.
    pub reference: Option<KeyFrameId>,
}

/// Whether the frame should become a keyframe.
pub(super) fn need_new_keyframe(
    params: &TrackingParams,
    map: &Map,
    candidate: &KeyFrameCandidate,
) -> bool {
    // The active map's keyframes (a new map after a loss starts small).
    let active = map.active_map();
    let n_kfs = map.keyframes_in(active).count();
    let max_frames = params.max_frames_between_keyframes;
    if candidate.recently_relocalized && n_kfs as u64 > max_frames {
        return false;
    }
    let reference = candidate.reference.and_then(|r| map.keyframe(r));
    // A young map's points are seen by two keyframes: so are those of a
    // new map just put into an old one by the telemetry, whose reference
    // keyframe has one covisible neighbour however many the map has.
    let young = n_kfs <= 2 || reference.is_some_and(|k| k.covisible.len() < 2);
    let min_obs = if young { 2 } else { 3 };
    let ref_matches = reference.map_or(0, |k| k.tracked_points(map, min_obs));
    let since = candidate
        .frame_index
        .saturating_sub(candidate.last_keyframe_frame);
    let c1a = since >= max_frames;
    let c1b = since >= params.min_frames_between_keyframes && candidate.mapping_idle;
    let inliers = candidate.inliers;
    let c2 = (inliers as f64) < ref_matches as f64 * params.keyframe_ref_ratio && inliers > 15;
    (c1a || c1b) && c2 && candidate.mapping_idle
}
