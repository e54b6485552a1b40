//! What the loop closer records: each loop closed ([`LoopEvent`], its
//! [`LoopSummary`] shared through a [`LoopLog`]) and each merge
//! ([`MergeEvent`], [`MergeSummary`], [`MergeLog`]), the candidates refused
//! and why ([`LoopRefusal`], [`LoopReject`]), its holds of the map lock
//! ([`LockHold`], [`HoldKind`]), and the keyframe trajectories the events
//! carry.

use std::sync::Mutex;
use std::time::Instant;

use crate::slam::map::{KeyFrameId, Map, MapId};
use crate::trajectory::{StampedPose, Trajectory};

/// A loop closed: the two keyframes, the evidence, the correction, and the
/// keyframe trajectory just before and just after it.
#[derive(Debug, Clone)]
pub struct LoopEvent {
    /// What the daemon's status reports of it (keyframes, evidence,
    /// correction, times).
    pub summary: LoopSummary,
    /// Edges of the essential graph.
    pub graph_edges: usize,
    /// Keyframe poses (world_from_cam) before the correction.
    pub keyframes_before: Trajectory,
    /// Keyframe poses after it (after the global BA when one ran).
    pub keyframes_after: Trajectory,
    /// Reprojection RMSE after the global BA, px (`None`: none ran).
    pub global_ba_rmse_px: Option<f64>,
    /// When the global BA started and ended (`None`: none ran).
    pub global_ba_window: Option<(Instant, Instant)>,
    /// When the correction started (the loop closer took the map lock for
    /// the keyframe that found the loop) and ended (its essential graph
    /// written back).
    pub correction_window: Option<(Instant, Instant)>,
}

/// What the loop closer was doing while it held the map lock.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum HoldKind {
    /// Looking for a loop or a merge at a keyframe (detection and the
    /// verification of its candidates), nothing closed.
    Search,
    /// The same, then a loop's correction up to its essential graph
    /// (propagation, fusion, the graph built).
    Loop,
    /// The same, then a merge.
    Merge,
    /// Writing a loop's essential graph back (solved without the lock).
    EssentialGraph,
    /// The global BA after a loop: building its problem, or writing its
    /// result back (it solves without the lock).
    GlobalBa,
}

/// One span of the loop closer holding the map lock (tracking waits for
/// the lock meanwhile).
#[derive(Debug, Clone, Copy)]
pub struct LockHold {
    /// The keyframe being processed.
    pub kf: KeyFrameId,
    /// Lock taken.
    pub from: Instant,
    /// Lock released.
    pub to: Instant,
    /// What was done.
    pub kind: HoldKind,
}

impl LockHold {
    /// Its length, ms.
    pub fn ms(&self) -> f64 {
        (self.to - self.from).as_secs_f64() * 1e3
    }
}

/// A loop closed, without the trajectories: what the daemon's status
/// reports while the SLAM runs ([`super::LoopCloser::log`]).
#[derive(Debug, Clone, PartialEq)]
pub struct LoopSummary {
    /// The keyframe that saw the old place again.
    pub current: KeyFrameId,
    /// The old keyframe it matched.
    pub loop_kf: KeyFrameId,
    /// Timestamp of the current keyframe, seconds.
    pub current_t: f64,
    /// Timestamp of the loop keyframe, seconds.
    pub loop_t: f64,
    /// Inliers of the refined Sim(3).
    pub inliers: usize,
    /// Keypoints of the current keyframe matched by the loop
    /// neighbourhood's points through the corrected pose.
    pub projection_matches: usize,
    /// Scale of the correction (the current side's drift, loop / current).
    pub scale: f64,
    /// Rotation of the correction, degrees.
    pub rotation_deg: f64,
    /// Move of the current camera, in map units.
    pub translation: f64,
    /// Points fused.
    pub fused: usize,
    /// Time of the correction (propagation, fusion, essential graph), ms.
    pub correction_ms: f64,
    /// Time of the global BA after it, ms (`None`: none ran).
    pub global_ba_ms: Option<f64>,
}

impl LoopSummary {
    /// Time of the whole correction, the global BA included, ms.
    pub fn total_ms(&self) -> f64 {
        self.correction_ms + self.global_ba_ms.unwrap_or(0.0)
    }
}

/// Two maps merged: the keyframes, the evidence, the similarity, and the
/// keyframe trajectories just before and just after it.
#[derive(Debug, Clone)]
pub struct MergeEvent {
    /// What the daemon's status reports of it.
    pub summary: MergeSummary,
    /// Edges of the essential graph.
    pub graph_edges: usize,
    /// The old map's keyframes (world_from_cam) before the merge.
    pub old_map_before: Trajectory,
    /// The merged map's keyframes before the merge, in their own frame.
    pub new_map_before: Trajectory,
    /// The merged map's keyframes after it (both maps).
    pub keyframes_after: Trajectory,
}

/// A merge, without the trajectories: what the daemon's status reports
/// ([`super::LoopCloser::merge_log`]).
#[derive(Debug, Clone, PartialEq)]
pub struct MergeSummary {
    /// The keyframe of the active map that saw the old place.
    pub current: KeyFrameId,
    /// The old map's keyframe it matched.
    pub merge_kf: KeyFrameId,
    /// Timestamp of the current keyframe, seconds.
    pub current_t: f64,
    /// Timestamp of the old keyframe, seconds.
    pub merge_t: f64,
    /// The map merged (it no longer exists).
    pub from_map: MapId,
    /// The map it joined (the old one; the active one now).
    pub into_map: MapId,
    /// Inliers of the refined Sim(3).
    pub inliers: usize,
    /// Keypoints of the current keyframe matched by the old
    /// neighbourhood's points through the Sim(3).
    pub projection_matches: usize,
    /// Scale of the similarity (old map units per new map unit).
    pub scale: f64,
    /// Live keyframes moved into the old map.
    pub keyframes_moved: usize,
    /// Points fused.
    pub fused: usize,
    /// Time of the merge (transform, fusion, welding BA, essential graph), ms.
    pub correction_ms: f64,
}

/// The merges a [`super::LoopCloser`] made, shared like [`LoopLog`].
pub type MergeLog = std::sync::Arc<Mutex<Vec<MergeSummary>>>;

/// The loops a [`super::LoopCloser`] closed, shared with whoever reports them
/// while it runs on its thread (one summary per loop, in order).
pub type LoopLog = std::sync::Arc<Mutex<Vec<LoopSummary>>>;

/// Why a consistent candidate was refused (for logs and counts).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum LoopReject {
    /// Too few BoW-guided matches.
    BowMatches,
    /// RANSAC found no Sim(3).
    Ransac,
    /// The refined Sim(3) kept too few inliers.
    Sim3Inliers,
    /// Too few matches by projection through the corrected pose.
    Projection,
    /// The implied correction is beyond the drift bounds.
    Implausible,
    /// A merge: the map similarity of this keyframe disagrees with the
    /// previous keyframe's.
    Disagreement,
}

/// A consistent candidate that was refused.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LoopRefusal {
    /// The keyframe looking for a loop.
    pub current: KeyFrameId,
    /// The candidate.
    pub candidate: KeyFrameId,
    /// Timestamp of the current keyframe, seconds.
    pub current_t: f64,
    /// Timestamp of the candidate, seconds.
    pub candidate_t: f64,
    /// The check it failed.
    pub reason: LoopReject,
}

/// The live keyframes of map `id` (world_from_cam), by time.
pub(super) fn map_trajectory(map: &Map, id: MapId) -> Trajectory {
    let mut poses: Vec<StampedPose> = map
        .keyframes_in(id)
        .map(|k| StampedPose {
            t: k.timestamp,
            world_from_cam: k.world_from_cam(),
        })
        .collect();
    poses.sort_by(|a, b| a.t.total_cmp(&b.t));
    Trajectory { poses }
}

/// The live keyframes of every map (world_from_cam), by time.
pub(super) fn keyframe_trajectory(map: &Map) -> Trajectory {
    let mut poses: Vec<StampedPose> = map
        .keyframes()
        .map(|k| StampedPose {
            t: k.timestamp,
            world_from_cam: k.world_from_cam(),
        })
        .collect();
    poses.sort_by(|a, b| a.t.total_cmp(&b.t));
    Trajectory { poses }
}
