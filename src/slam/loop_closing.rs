//! Loop closing (ORB-SLAM's `LoopClosing`, as stella_vslam's
//! `loop_detector` and `graph_optimizer` modules): after local mapping has
//! processed a keyframe, look for a place seen long before, check it
//! geometrically, and spread the correction over the map.
//!
//! Detection, per keyframe:
//! 1. BoW candidates from the keyframe database outside the keyframe's
//!    covisibility neighbourhood, scoring at least the lowest score
//!    between the keyframe and its own covisible keyframes
//!    ([`crate::bow::KeyFrameDatabase::detect_candidates`]);
//! 2. consistency: each candidate with its covisible keyframes forms a
//!    group; a group must overlap a group of the previous keyframe's,
//!    `consistency` keyframes in a row (ORB-SLAM's rule of three);
//! 3. for each consistent candidate: BoW-guided matches between the two
//!    keyframes' map points, a Sim(3) by RANSAC over three-point Umeyama
//!    samples ([`crate::geometry::sim3_ransac`]), a guided search by
//!    projection through that Sim(3) for more matches, the robust
//!    refinement ([`crate::optimize::optimize_sim3`]) of rotation and
//!    translation with the scale held, the scale from the inliers' 3D
//!    points (median ratio of pairwise distances, [`robust_scale_fit`]:
//!    reprojection barely sees the scale when the two cameras
//!    nearly coincide, as at a revisit: ORB-SLAM's free-scale refinement
//!    drifted 10 % there on the simulator), a second refinement at that
//!    scale and its inlier count, then the candidate's and its neighbours' points projected
//!    through the corrected pose must match enough keypoints of the
//!    keyframe, and a fair share of those that land in the image;
//! 4. plausibility: the correction the loop implies (the current pose
//!    moved to where the loop puts it) stays within monocular drift
//!    bounds: scale, rotation, and translation relative to the path flown
//!    since the loop keyframe.
//!
//! Correction: the Sim(3) is propagated to the current keyframe's
//! covisible keyframes and their points, the loop's matched points are
//! fused into the current neighbourhood (duplicates merged), connections
//! are updated, and the essential graph (spanning tree, covisibility edges
//! of weight ≥ `essential_min_weight`, all loop edges, the new loop
//! connections) is optimised in Sim(3) with the loop keyframe fixed
//! ([`crate::optimize::optimize_pose_graph`]); every point then follows
//! the keyframe it was corrected with (or its reference keyframe). Loops
//! are looked for inside the keyframe's own map only.
//!
//! The map lock: detection, verification, propagation, fusion and the
//! building of the essential graph run under it (tracking waits for it
//! meanwhile); the graph is then solved on its own copy of the poses
//! without the lock (tracking goes on in the corrected neighbourhood), and
//! written back under the lock again (keyframes added meanwhile keep their
//! pose relative to the keyframe they follow). Each hold is recorded
//! ([`LockHold`]), so a run can set the tracking thread's frame times
//! against them.
//!
//! The thread: the closer runs on its own thread (`slam-loop`, at a lower
//! priority than tracking and mapping), fed each keyframe local mapping
//! finished; in sequential mode it runs after local mapping on the same
//! thread, so runs repeat. Local mapping goes on beside the search; a
//! local BA solved while a correction moved the map drops its result (the
//! map's correction count changed), and local mapping is held between two
//! keyframes while the essential graph and a global BA are solved and
//! written back ([`super::pause`]).
//!
//! Map merging (ORB-SLAM3's "welding" merge, monocular): after a tracking
//! loss tracking starts a new map ([`super::tracking`]); the map holds
//! every map of the atlas ([`super::map::MapId`]). Before looking for a
//! loop at a keyframe of the active map, the closer looks for a place of
//! another map:
//! 1. BoW candidates in the other maps only, by normalised score without
//!    the loop's score floor or words-in-common pre-filter (a young map's
//!    keyframes resemble each other far more than any view of the old map,
//!    and the old map's two initialisation keyframes, with twice the
//!    features, share the most words with anything);
//! 2. the same consistency over `consistency` keyframes, the same Sim(3)
//!    RANSAC, guided search, refinement and projection check as a loop,
//!    but not the drift bounds (two maps' frames and scales are unrelated);
//! 3. agreement: the map similarity (old world ← active world) found at
//!    this keyframe must agree with the one found at the previous keyframe
//!    (`merge_confirmations` in a row: scale ratio, rotation, and where
//!    both put the current camera relative to the old keyframe's scene
//!    depth); a look-alike place gives a similarity that the next keyframe
//!    does not confirm.
//!
//! The merge: the whole active map (keyframes, culled keyframes, points)
//! is moved by the similarity into the old map's frame and becomes part of
//! it ([`Map::merge_maps`]: its spanning tree hangs from the old keyframe
//! through the current one); the place's points are fused as for a loop;
//! a bundle adjustment welds the current keyframe's neighbourhood to the
//! old keyframe's (the old side fixed); then the essential graph of the
//! merged map is optimised with every keyframe of the old map fixed, so
//! the weld's correction spreads over the new part. Tracking follows:
//! its records and its motion model on the moved keyframes scale with the
//! similarity ([`super::Tracker::follow_merges`]). Each merge's summary
//! goes to a shared [`MergeLog`], which the daemon reports as loops.

use std::collections::{HashMap, HashSet};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use nalgebra::{Isometry3, Point2, Translation3};

use crate::bow::CandidateParams;
use crate::eval::{StampedPose, Trajectory};
use crate::features::{Descriptor, hamming};
use crate::geometry::{Sim3RansacParams, sim3_ransac};
use crate::lie::Sim3;
use crate::matching::Bounds;
use crate::optimize::{
    BaParams, Intrinsics, PoseGraph, PoseGraphParams, Sim3Edge, Sim3Match, Sim3Params,
    optimize_pose_graph, optimize_sim3,
};

use super::bundle::run_bundle_adjustment;
use super::bundle::{apply_ba_result, build_ba_problem};
use super::map::{KeyFrame, KeyFrameId, Map, MapId, Places, PointId, lock};
use super::matcher::{self, MatcherParams};
use super::params::bound_history;
use super::pause::MappingPause;

/// Tunable numbers of loop closing.
#[derive(Debug, Clone, PartialEq)]
pub struct LoopParams {
    /// Look for loops only once the map holds this many keyframes, and
    /// this many keyframes after the last loop (ORB-SLAM: 10).
    pub min_keyframes: usize,
    /// Consecutive keyframes whose candidate groups must overlap (3).
    pub consistency: usize,
    /// Covisible neighbours that form a candidate's group.
    pub group_neighbours: usize,
    /// BoW-guided matches a candidate needs before RANSAC (20).
    pub min_bow_matches: usize,
    /// Ratio test of the BoW-guided matching (0.75).
    pub bow_ratio: f32,
    /// RANSAC of the Sim(3).
    pub ransac: Sim3RansacParams,
    /// Refinement of the Sim(3).
    pub sim3: Sim3Params,
    /// Inliers the refined Sim(3) needs (20).
    pub min_sim3_inliers: usize,
    /// Radius of the guided search through the Sim(3), pixels at level 0.
    pub sim3_search_radius: f64,
    /// Radius of the search of the loop neighbourhood's points through the
    /// corrected pose, pixels at level 0 (ORB-SLAM: 10).
    pub projection_radius: f64,
    /// Keypoints of the keyframe the loop neighbourhood's points must
    /// match through the corrected pose (ORB-SLAM: 40).
    pub min_projection_matches: usize,
    /// Of the loop neighbourhood's points that project into the keyframe
    /// at a plausible scale and angle, the share that must match.
    pub min_projection_ratio: f64,
    /// Largest scale change a loop may imply (`1/x ..= x`).
    pub max_scale_change: f64,
    /// Largest rotation a loop may imply, degrees.
    pub max_rotation_deg: f64,
    /// Largest move of the current camera a loop may imply, as a share of
    /// the path flown (keyframe to keyframe) since the loop keyframe.
    pub max_translation_ratio: f64,
    /// Radius of the fusion of the loop's points, pixels at level 0 (4).
    pub fuse_radius: f64,
    /// Covisibility edges of the essential graph need this weight (100).
    pub essential_min_weight: u32,
    /// The essential graph's optimisation.
    pub pose_graph: PoseGraphParams,
    /// The matcher's thresholds.
    pub matcher: MatcherParams,
    /// Seed of the RANSAC (mixed with the keyframe ids).
    pub seed: u64,
    /// Bundle adjustment over all keyframes and points after the essential
    /// graph (the map's first keyframe fixed); `None` (default): none. It
    /// runs on the loop closer's thread beside local mapping, the solve
    /// without the map lock, and is written back with local mapping held.
    /// Off by default: on the simulator renders it did not help (README).
    pub global_ba: Option<BaParams>,
    /// Fit the loop's Sim(3) again on the matches the projection search
    /// found whose keypoint holds a point, and search once more. Off by
    /// default: on the simulator renders it did not help (README).
    pub refit_on_projection: bool,
    /// Merge the active map into an inactive one (left after a tracking
    /// loss) when a place common to both is found.
    pub merging: bool,
    /// Keyframes the active map needs before merges are looked for.
    pub merge_min_keyframes: usize,
    /// Consecutive keyframes whose verified map similarities must agree
    /// before a merge (the first one plus this many more; 1).
    pub merge_confirmations: usize,
    /// Largest scale ratio between two agreeing merge similarities
    /// (`1/x ..= x`).
    pub merge_max_scale_ratio: f64,
    /// Largest rotation between two agreeing merge similarities, degrees.
    pub merge_max_rotation_deg: f64,
    /// Largest distance between where two agreeing merge similarities put
    /// the current camera, as a share of the old keyframe's median scene
    /// depth.
    pub merge_max_shift_ratio: f64,
    /// The bundle adjustment that welds the two maps at the merge (the
    /// current keyframe's neighbourhood free, the old map's side fixed).
    pub merge_ba: BaParams,
}

impl Default for LoopParams {
    fn default() -> Self {
        LoopParams {
            min_keyframes: 10,
            consistency: 3,
            group_neighbours: 10,
            min_bow_matches: 20,
            bow_ratio: 0.75,
            ransac: Sim3RansacParams::default(),
            sim3: Sim3Params::default(),
            min_sim3_inliers: 20,
            sim3_search_radius: 7.5,
            projection_radius: 10.0,
            min_projection_matches: 40,
            min_projection_ratio: 0.25,
            max_scale_change: 2.0,
            max_rotation_deg: 30.0,
            max_translation_ratio: 0.5,
            fuse_radius: 4.0,
            essential_min_weight: 100,
            pose_graph: PoseGraphParams::default(),
            matcher: MatcherParams::default(),
            seed: 1,
            refit_on_projection: false,
            global_ba: None,
            merging: true,
            merge_min_keyframes: 5,
            merge_confirmations: 1,
            merge_max_scale_ratio: 1.15,
            merge_max_rotation_deg: 5.0,
            merge_max_shift_ratio: 0.25,
            merge_ba: BaParams::default(),
        }
    }
}

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
/// reports while the SLAM runs ([`LoopCloser::log`]).
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
/// ([`LoopCloser::merge_log`]).
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

/// The merges a [`LoopCloser`] made, shared like [`LoopLog`].
pub type MergeLog = std::sync::Arc<Mutex<Vec<MergeSummary>>>;

/// The loops a [`LoopCloser`] closed, shared with whoever reports them
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

/// A verified loop before correction.
struct LoopMatch {
    loop_kf: KeyFrameId,
    /// Corrected pose of the current keyframe: world → camera, a Sim(3).
    s_cw: Sim3,
    /// Per keypoint of the current keyframe: the loop-side point matched.
    matched: Vec<Option<PointId>>,
    /// Points of the loop keyframe and its neighbours.
    loop_points: Vec<PointId>,
    inliers: usize,
    projection_matches: usize,
}

/// The loop closer (runs after local mapping, on its own thread or after
/// it in sequential mode).
pub struct LoopCloser {
    params: LoopParams,
    bounds: Bounds,
    /// Candidate groups of the previous keyframe with their consistency.
    groups: Vec<(HashSet<KeyFrameId>, usize)>,
    last_loop: Option<KeyFrameId>,
    /// Loops closed.
    pub events: Vec<LoopEvent>,
    /// Consistent candidates refused, in order.
    pub refusals: Vec<LoopRefusal>,
    log: LoopLog,
    /// Merge candidate groups of the previous keyframe.
    merge_groups: Vec<(HashSet<KeyFrameId>, usize)>,
    /// The previous keyframe's verified merge: the other map, the map
    /// similarity (other ← active), how many keyframes in a row agreed.
    pending_merge: Option<(MapId, Sim3, usize)>,
    /// Maps merged.
    pub merges: Vec<MergeEvent>,
    /// Consistent merge candidates refused, in order.
    pub merge_refusals: Vec<LoopRefusal>,
    merge_log: MergeLog,
    /// Each span it held the map lock, in order.
    pub holds: Vec<LockHold>,
    /// Holds and refusals kept ([`LoopCloser::set_history`]).
    keep: Option<usize>,
    /// Local mapping's pause, when the closer runs on its own thread
    /// ([`LoopCloser::set_pause`]).
    pause: Option<Arc<MappingPause>>,
}

impl LoopCloser {
    /// A loop closer for images bounded by `bounds`.
    pub fn new(params: LoopParams, bounds: Bounds) -> Self {
        LoopCloser {
            params,
            bounds,
            groups: Vec::new(),
            last_loop: None,
            events: Vec::new(),
            refusals: Vec::new(),
            log: LoopLog::default(),
            merge_groups: Vec::new(),
            pending_merge: None,
            merges: Vec::new(),
            merge_refusals: Vec::new(),
            merge_log: MergeLog::default(),
            holds: Vec::new(),
            keep: None,
            pause: None,
        }
    }

    /// Run beside local mapping: hold it through `pause` while a
    /// correction's essential graph and global BA are written back.
    pub fn set_pause(&mut self, pause: Arc<MappingPause>) {
        self.pause = Some(pause);
    }

    /// Keep at least the newest `keep` lock holds and refusals (of loops,
    /// of merges) and at most twice as many (`None`: all).
    pub fn set_history(&mut self, keep: Option<usize>) {
        self.keep = keep;
        self.bound();
    }

    fn bound(&mut self) {
        bound_history(&mut self.holds, self.keep);
        bound_history(&mut self.refusals, self.keep);
        bound_history(&mut self.merge_refusals, self.keep);
    }

    /// The summaries of the loops closed, shared: it fills as loops close.
    pub fn log(&self) -> LoopLog {
        self.log.clone()
    }

    /// The summaries of the merges, shared: it fills as maps merge.
    pub fn merge_log(&self) -> MergeLog {
        self.merge_log.clone()
    }

    /// Look for a place of another map at keyframe `kf` (mapped already)
    /// and merge the maps; else look for a loop and close it. Returns the
    /// loop closed, if any (merges go to [`LoopCloser::merges`]).
    pub fn process_keyframe(&mut self, map: &Mutex<Map>, kf: KeyFrameId) -> Option<LoopEvent> {
        let mut m = lock(map);
        let from = Instant::now();
        let (kind, found) = self.search(&mut m, kf);
        let corrections = m.corrections();
        drop(m);
        self.holds.push(LockHold {
            kf,
            from,
            to: Instant::now(),
            kind,
        });
        // The essential graph is solved without the lock (tracking goes
        // on with the corrected neighbourhood), then written back; local
        // mapping, on its own thread, is held meanwhile.
        // A clone: `self.bound()` below needs `self` whole.
        let pause = self.pause.clone();
        let mut event = found.map(|(mut e, mut graph)| {
            let held = pause.as_deref().map(MappingPause::hold);
            // Before the hold was granted, local mapping may have moved
            // the whole map (telemetry priors rescale or refit it): the
            // graph, built on the poses before, would put them back. The
            // neighbourhood's correction stays; the rest is left to local
            // BA and the next loop.
            let overtaken = lock(map).corrections() != corrections;
            if overtaken {
                tracing::warn!(
                    kf = kf.0,
                    "loop's essential graph not written back: the map was moved while it was built"
                );
            }
            let solved = !overtaken && graph.solve(&self.params.pose_graph);
            let mut m = lock(map);
            let applied = Instant::now();
            if solved {
                graph.apply(&mut m);
                m.note_correction();
            }
            e.keyframes_after = keyframe_trajectory(&m);
            drop(m);
            drop(held);
            let end = Instant::now();
            self.holds.push(LockHold {
                kf,
                from: applied,
                to: end,
                kind: HoldKind::EssentialGraph,
            });
            e.summary.correction_ms = (end - graph.started).as_secs_f64() * 1e3;
            e.correction_window = Some((from, end));
            e
        });
        self.bound();
        if let (Some(e), Some(ba)) = (&mut event, &self.params.global_ba) {
            let t1 = Instant::now();
            let pause = pause.as_deref();
            if let Some(rmse) = global_bundle_adjustment(map, kf, ba, pause, &mut self.holds) {
                e.global_ba_rmse_px = Some(rmse);
                e.keyframes_after = keyframe_trajectory(&lock(map));
            }
            e.summary.global_ba_ms = Some(t1.elapsed().as_secs_f64() * 1e3);
            e.global_ba_window = Some((t1, Instant::now()));
        }
        if let Some(e) = &event {
            let l = &e.summary;
            tracing::info!(
                current = l.current.0,
                loop_kf = l.loop_kf.0,
                inliers = l.inliers,
                projection_matches = l.projection_matches,
                scale = l.scale,
                rotation_deg = l.rotation_deg,
                fused = l.fused,
                edges = e.graph_edges,
                ms = l.correction_ms,
                "loop closed"
            );
            self.events.push(e.clone());
            self.log
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .push(e.summary.clone());
            self.last_loop = Some(kf);
            self.groups.clear();
        }
        event
    }

    /// Under the map lock: a merge at `kf`, else a loop found, verified
    /// and corrected up to its essential graph; what was done, and the
    /// loop with its graph to solve.
    fn search(
        &mut self,
        m: &mut Map,
        kf: KeyFrameId,
    ) -> (HoldKind, Option<(LoopEvent, EssentialGraph)>) {
        if self.params.merging && self.look_for_merge(m, kf) {
            return (HoldKind::Merge, None);
        }
        let candidates = Self::detect(&self.params, self.last_loop, &mut self.groups, m, kf, false);
        if candidates.is_empty() {
            return (HoldKind::Search, None);
        }
        let Some(found) = self.verify(m, kf, &candidates) else {
            return (HoldKind::Search, None);
        };
        let event = self.correct(m, kf, found);
        let kind = if event.is_some() {
            HoldKind::Loop
        } else {
            HoldKind::Search
        };
        (kind, event)
    }

    /// Merge detection at `kf` (see the module doc): consistent BoW
    /// candidates in other maps, verified like loops, and a map similarity
    /// that consecutive keyframes agree on; then the merge. True when the
    /// maps were merged.
    fn look_for_merge(&mut self, map: &mut Map, kf: KeyFrameId) -> bool {
        if map.map_of(kf) != Some(map.active_map()) {
            self.merge_groups.clear();
            self.pending_merge = None;
            return false;
        }
        let candidates = Self::detect(&self.params, None, &mut self.merge_groups, map, kf, true);
        let mut verified = None;
        for &c in &candidates {
            match self.verify_one(map, kf, c, false) {
                Ok(m) => {
                    verified = Some(m);
                    break;
                }
                Err(why) => self.refuse_merge(map, kf, c, why),
            }
        }
        let Some(lm) = verified else {
            self.pending_merge = None;
            return false;
        };
        let (Some(k1), Some(other)) = (map.keyframe(kf), map.map_of(lm.loop_kf)) else {
            return false;
        };
        // The map similarity: old world <- active world.
        let s = lm
            .s_cw
            .inverse()
            .compose(&Sim3::from_isometry(&k1.cam_from_world));
        let agreed = match self.pending_merge {
            Some((m, prev, n)) if m == other => {
                if self.similarities_agree(map, &prev, &s, k1, lm.loop_kf) {
                    n + 1
                } else {
                    self.refuse_merge(map, kf, lm.loop_kf, LoopReject::Disagreement);
                    0
                }
            }
            _ => 0,
        };
        if agreed < self.params.merge_confirmations {
            self.pending_merge = Some((other, s, agreed));
            return false;
        }
        self.pending_merge = None;
        let t0 = Instant::now();
        let Some(event) = self.merge(map, kf, other, &s, lm, t0) else {
            return false;
        };
        let l = &event.summary;
        tracing::info!(
            current = l.current.0,
            merge_kf = l.merge_kf.0,
            from_map = l.from_map.0,
            into_map = l.into_map.0,
            inliers = l.inliers,
            projection_matches = l.projection_matches,
            scale = l.scale,
            moved = l.keyframes_moved,
            fused = l.fused,
            ms = l.correction_ms,
            "maps merged"
        );
        self.merge_log
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(event.summary.clone());
        self.merges.push(event);
        self.merge_groups.clear();
        self.groups.clear();
        self.last_loop = Some(kf);
        true
    }

    fn refuse_merge(&mut self, map: &Map, kf: KeyFrameId, c: KeyFrameId, why: LoopReject) {
        tracing::debug!(
            current = kf.0,
            candidate = c.0,
            ?why,
            "merge candidate refused"
        );
        let t = |id| map.keyframe(id).map_or(f64::NAN, |k| k.timestamp);
        self.merge_refusals.push(LoopRefusal {
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
        &self,
        map: &Map,
        a: &Sim3,
        b: &Sim3,
        k1: &KeyFrame,
        old_kf: KeyFrameId,
    ) -> bool {
        let p = &self.params;
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
        &mut self,
        map: &mut Map,
        kf: KeyFrameId,
        other: MapId,
        s: &Sim3,
        lm: LoopMatch,
        t0: Instant,
    ) -> Option<MergeEvent> {
        let p = &self.params;
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
        let (fused, loop_links) = fuse_and_link(map, kf, &connected, &lm, &self.bounds, p);
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

    /// Steps 1 and 2: the candidates consistent over enough keyframes;
    /// loop candidates in `kf`'s own map, merge candidates (`merge`) in
    /// the other maps. `groups` are the previous keyframe's candidate
    /// groups of that kind.
    fn detect(
        p: &LoopParams,
        last_loop: Option<KeyFrameId>,
        groups: &mut Vec<(HashSet<KeyFrameId>, usize)>,
        map: &Map,
        kf: KeyFrameId,
        merge: bool,
    ) -> Vec<KeyFrameId> {
        let Some(k) = map.keyframe(kf) else {
            return Vec::new();
        };
        let Some(places) = map.places() else {
            return Vec::new();
        };
        let Some(bow) = places.database.bow(Places::db_id(kf)) else {
            return Vec::new();
        };
        let my_map = map.map_of(kf);
        let in_my_map = my_map.map_or(0, |id| map.keyframes_in(id).count());
        let too_early = if merge {
            in_my_map < p.merge_min_keyframes || map.maps().len() < 2
        } else {
            in_my_map < p.min_keyframes
                || last_loop.is_some_and(|l| (kf.0 as usize) < l.0 as usize + p.min_keyframes)
        };
        if too_early {
            groups.clear();
            return Vec::new();
        }
        let connected: HashSet<KeyFrameId> = k.covisible.iter().map(|c| c.0).collect();
        let mut min_score = f32::INFINITY;
        for c in &connected {
            if let Some(b) = places.database.bow(Places::db_id(*c)) {
                min_score = min_score.min(bow.l1_score(b));
            }
        }
        if !min_score.is_finite() {
            groups.clear();
            return Vec::new();
        }
        // A merge looks into other maps: a young map's few keyframes
        // resemble each other far more than any view of another map does,
        // so the loop's score floor would hide every candidate (ORB-SLAM3
        // takes the best groups for merges, without the floor). Nor are
        // keyframes pre-filtered by words in common: the old map's two
        // initialisation keyframes (twice the features) share the most
        // words with anything and would be the only ones scored; the
        // normalised score does not favour them.
        let cp = if merge {
            CandidateParams {
                min_score: 0.0,
                min_common_words_ratio: 0.0,
                ..CandidateParams::default()
            }
        } else {
            CandidateParams {
                min_score,
                ..CandidateParams::default()
            }
        };
        let neighbours = cp.covisible_neighbours;
        let candidates = places.database.detect_candidates(
            bow,
            &cp,
            |id| {
                Places::map_id(id).is_none_or(|id| {
                    let same = map.map_of(id) == my_map;
                    id == kf || connected.contains(&id) || same == merge
                })
            },
            |id, out| {
                if let Some(k) = Places::map_id(id).and_then(|id| map.keyframe(id)) {
                    out.extend(k.best_covisible(neighbours).map(Places::db_id));
                }
            },
        );
        // Consistency with the previous keyframe's groups.
        let mut current_groups: Vec<(HashSet<KeyFrameId>, usize)> = Vec::new();
        let mut extended = vec![false; groups.len()];
        let mut consistent = Vec::new();
        for c in candidates {
            let Some(cid) = Places::map_id(c.id) else {
                continue;
            };
            let Some(ck) = map.keyframe(cid) else {
                continue;
            };
            let group: HashSet<KeyFrameId> = std::iter::once(cid)
                .chain(ck.best_covisible(p.group_neighbours))
                .collect();
            let mut enough = false;
            let mut consistent_for_some = false;
            for (g, (prev, n)) in groups.iter().enumerate() {
                if prev.is_disjoint(&group) {
                    continue;
                }
                consistent_for_some = true;
                let count = n + 1;
                if !extended[g] {
                    current_groups.push((group.clone(), count));
                    extended[g] = true;
                }
                if count >= p.consistency && !enough {
                    consistent.push(cid);
                    enough = true;
                }
            }
            if !consistent_for_some {
                current_groups.push((group, 0));
            }
        }
        *groups = current_groups;
        consistent
    }

    /// Step 3 and 4: the first candidate whose Sim(3) holds.
    fn verify(
        &mut self,
        map: &Map,
        kf: KeyFrameId,
        candidates: &[KeyFrameId],
    ) -> Option<LoopMatch> {
        for &c in candidates {
            match self.verify_one(map, kf, c, true) {
                Ok(m) => return Some(m),
                Err(why) => {
                    tracing::debug!(
                        current = kf.0,
                        candidate = c.0,
                        ?why,
                        "loop candidate refused"
                    );
                    let t = |id| map.keyframe(id).map_or(f64::NAN, |k| k.timestamp);
                    self.refusals.push(LoopRefusal {
                        current: kf,
                        candidate: c,
                        current_t: t(kf),
                        candidate_t: t(c),
                        reason: why,
                    });
                }
            }
        }
        None
    }

    /// Steps 3 and 4 for one candidate; the drift bounds of step 4 only
    /// when `drift_bounds` (a loop: a merge's maps have unrelated frames).
    fn verify_one(
        &self,
        map: &Map,
        kf: KeyFrameId,
        cand: KeyFrameId,
        drift_bounds: bool,
    ) -> Result<LoopMatch, LoopReject> {
        let p = &self.params;
        let (Some(k1), Some(k2)) = (map.keyframe(kf), map.keyframe(cand)) else {
            return Err(LoopReject::BowMatches);
        };
        let places = map.places().ok_or(LoopReject::BowMatches)?;
        let (Some(fv1), Some(fv2)) = (places.features.get(&kf), places.features.get(&cand)) else {
            return Err(LoopReject::BowMatches);
        };
        let cam = &map.camera;
        let intr = Intrinsics {
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
        };
        let sigma2 = &map.scale.inv_level_sigma2;
        // BoW-guided matches: keypoints of kf that hold a point, to points of cand.
        let bow = matcher::search_by_bow(
            map,
            cand,
            fv2,
            &k1.descriptors,
            &k1.keypoints,
            fv1,
            &p.matcher,
            p.bow_ratio,
        );
        let mut pairs: Vec<(usize, PointId, PointId)> = Vec::new();
        let mut used2: HashSet<PointId> = HashSet::new();
        for (i1, p2) in bow {
            if let Some(Some(p1)) = k1.points.get(i1)
                && *p1 != p2
                && map.point(*p1).is_some()
                && used2.insert(p2)
            {
                pairs.push((i1, *p1, p2));
            }
        }
        if pairs.len() < p.min_bow_matches {
            return Err(LoopReject::BowMatches);
        }
        let make = |i1: usize, p1: PointId, p2: PointId| -> Option<Sim3Match> {
            let mp1 = map.point(p1)?;
            let mp2 = map.point(p2)?;
            let i2 = mp2.index_in(cand)? as usize;
            let kp1 = k1.keypoints.get(i1)?;
            let kp2 = k2.keypoints.get(i2)?;
            Some(Sim3Match {
                x1_cam1: k1.cam_from_world * mp1.position,
                x2_cam2: k2.cam_from_world * mp2.position,
                uv1: Point2::new(kp1.ux as f64, kp1.uy as f64),
                uv2: Point2::new(kp2.ux as f64, kp2.uy as f64),
                inv_sigma2_1: *sigma2.get(kp1.octave as usize)?,
                inv_sigma2_2: *sigma2.get(kp2.octave as usize)?,
            })
        };
        let mut ms: Vec<Sim3Match> = Vec::with_capacity(pairs.len());
        let mut keep: Vec<(usize, PointId, PointId)> = Vec::with_capacity(pairs.len());
        for &(i1, p1, p2) in &pairs {
            if let Some(m) = make(i1, p1, p2) {
                ms.push(m);
                keep.push((i1, p1, p2));
            }
        }
        let seed = p
            .seed
            .wrapping_mul(0x9E37_79B9_7F4A_7C15)
            .wrapping_add(((kf.0 as u64) << 32) | cand.0 as u64);
        let ransac = sim3_ransac(&ms, &intr, &p.ransac, seed).map_err(|_| LoopReject::Ransac)?;
        // Guided search: the candidate's other points through S12 into kf.
        let s12 = ransac.s12;
        let mut taken1: HashSet<usize> = keep.iter().map(|m| m.0).collect();
        let mut taken2: HashSet<PointId> = keep.iter().map(|m| m.2).collect();
        let s_1w = s12.compose(&Sim3::from_isometry(&k2.cam_from_world));
        let iso_1w = sim3_to_isometry(&s_1w);
        let center1 = iso_1w.inverse().translation.vector;
        let mut cand_list = Vec::new();
        for p2 in k2.points.iter().flatten() {
            if taken2.contains(p2) {
                continue;
            }
            let Some(pr) = matcher::project_point(map, *p2, &iso_1w, &center1, &self.bounds, 0.5)
            else {
                continue;
            };
            let Some(mp2) = map.point(*p2) else { continue };
            let r = p.sim3_search_radius * map.scale.scale_factors[pr.level];
            let best = nearest_in_window(k1, &pr, r, &mp2.descriptor, &mut cand_list, |i| {
                taken1.contains(&i) || k1.points.get(i).copied().flatten().is_none()
            });
            if best.0 <= p.matcher.th_high
                && let Some(Some(p1)) = k1.points.get(best.1)
                && *p1 != *p2
                && let Some(m) = make(best.1, *p1, *p2)
            {
                taken1.insert(best.1);
                taken2.insert(*p2);
                ms.push(m);
                keep.push((best.1, *p1, *p2));
            }
        }
        // Reprojection hardly constrains the scale when the two cameras
        // nearly coincide (a revisit): points scaled about the camera
        // project to the same pixels. So the rotation and translation are
        // refined on reprojection with the scale held, the scale comes
        // from the 3D alignment (Umeyama) of the inliers, and the pose is
        // refined again at that scale.
        let fixed = Sim3Params {
            fix_scale: true,
            ..p.sim3.clone()
        };
        let first = optimize_sim3(&s12, &ms, &intr, &fixed).map_err(|_| LoopReject::Sim3Inliers)?;
        if first.n_inliers < p.min_sim3_inliers {
            return Err(LoopReject::Sim3Inliers);
        }
        let (src, dst): (Vec<_>, Vec<_>) = ms
            .iter()
            .zip(&first.inliers)
            .filter(|(_, ok)| **ok)
            .map(|(m, _)| (m.x2_cam2, m.x1_cam1))
            .unzip();
        let aligned = robust_scale_fit(&src, &dst, &first.s12).ok_or(LoopReject::Sim3Inliers)?;
        let refined =
            optimize_sim3(&aligned, &ms, &intr, &fixed).map_err(|_| LoopReject::Sim3Inliers)?;
        if refined.n_inliers < p.min_sim3_inliers {
            return Err(LoopReject::Sim3Inliers);
        }
        tracing::debug!(
            current = kf.0,
            candidate = cand.0,
            ransac_scale = s12.scale,
            ransac_inliers = ransac.n_inliers,
            refined_scale = refined.s12.scale,
            refined_inliers = refined.n_inliers,
            matches = ms.len(),
            "loop: Sim(3)"
        );
        let s_cw = refined
            .s12
            .compose(&Sim3::from_isometry(&k2.cam_from_world));
        // The loop neighbourhood's points through the corrected pose.
        let mut matched: Vec<Option<PointId>> = vec![None; k1.keypoints.len()];
        for ((i1, _, p2), ok) in keep.iter().zip(&refined.inliers) {
            if *ok {
                matched[*i1] = Some(*p2);
            }
        }
        let mut loop_points: Vec<PointId> = Vec::new();
        let mut seen: HashSet<PointId> = HashSet::new();
        for id in std::iter::once(cand).chain(k2.covisible.iter().map(|c| c.0)) {
            if let Some(k) = map.keyframe(id) {
                for pid in k.points.iter().flatten() {
                    if seen.insert(*pid) {
                        loop_points.push(*pid);
                    }
                }
            }
        }
        let (mut matched, mut in_view) =
            self.search_by_projection(map, k1, &loop_points, &s_cw, matched);
        let mut s_cw = s_cw;
        let mut inliers = refined.n_inliers;
        // The scale again from the larger set the projection found (ORB-SLAM
        // stops at the BoW inliers): every match whose keypoint holds a point
        // gives a 3D pair; the pose is refined on them at the scale held,
        // the scale re-fitted robustly on that refinement's inliers, the pose
        // refined at the new scale, and the projection search run once more.
        if p.refit_on_projection
            && let Some((s12, seeds, n)) =
                self.refit_on_projection(map, k1, k2, cand, &matched, &refined.s12, &intr)
        {
            s_cw = s12.compose(&Sim3::from_isometry(&k2.cam_from_world));
            (matched, in_view) = self.search_by_projection(map, k1, &loop_points, &s_cw, seeds);
            inliers = n;
        }
        let n_matched = matched.iter().flatten().count();
        if n_matched < p.min_projection_matches
            || (n_matched as f64) < p.min_projection_ratio * in_view as f64
        {
            tracing::debug!(
                current = kf.0,
                candidate = cand.0,
                n_matched,
                in_view,
                "loop: too few matches by projection"
            );
            return Err(LoopReject::Projection);
        }
        // Plausibility: the correction of the current pose.
        let corr = s_cw.compose(&Sim3::from_isometry(&k1.cam_from_world.inverse()));
        let rotation_deg = corr.rotation.angle().to_degrees();
        let moved = (sim3_to_isometry(&s_cw).inverse().translation.vector - k1.center()).norm();
        let flown = path_length(map, cand, kf);
        let max_s = p.max_scale_change.max(1.0);
        if drift_bounds
            && (!(corr.scale <= max_s && corr.scale >= 1.0 / max_s)
                || rotation_deg > p.max_rotation_deg
                || moved > p.max_translation_ratio * flown)
        {
            tracing::debug!(
                current = kf.0,
                candidate = cand.0,
                scale = corr.scale,
                rotation_deg,
                moved,
                flown,
                "loop: implausible correction"
            );
            return Err(LoopReject::Implausible);
        }
        Ok(LoopMatch {
            loop_kf: cand,
            s_cw,
            matched,
            loop_points,
            inliers,
            projection_matches: n_matched,
        })
    }

    /// Keypoints of `k1` matched by the loop neighbourhood's points seen
    /// through `s_cw`, starting from `matched`; also how many of the points
    /// were in view (the seeds count as in view).
    fn search_by_projection(
        &self,
        map: &Map,
        k1: &KeyFrame,
        loop_points: &[PointId],
        s_cw: &Sim3,
        mut matched: Vec<Option<PointId>>,
    ) -> (Vec<Option<PointId>>, usize) {
        let p = &self.params;
        let mut cand_list = Vec::new();
        let iso_cw = sim3_to_isometry(s_cw);
        let center = iso_cw.inverse().translation.vector;
        let already: HashSet<PointId> = matched.iter().flatten().copied().collect();
        let mut in_view = 0usize;
        for pid in loop_points {
            if already.contains(pid) {
                in_view += 1;
                continue;
            }
            let Some(pr) = matcher::project_point(map, *pid, &iso_cw, &center, &self.bounds, 0.5)
            else {
                continue;
            };
            let Some(mp) = map.point(*pid) else { continue };
            in_view += 1;
            let r = p.projection_radius * map.scale.scale_factors[pr.level];
            let best = nearest_in_window(k1, &pr, r, &mp.descriptor, &mut cand_list, |i| {
                matched[i].is_some()
            });
            if best.0 <= p.matcher.th_low {
                matched[best.1] = Some(*pid);
            }
        }
        (matched, in_view)
    }

    /// The loop's Sim(3) (camera 2 → camera 1) fitted again on the
    /// projection matches whose keypoint in `k1` holds a point: pose refined
    /// at the scale of `s12`, scale re-fitted with [`robust_scale_fit`] on
    /// that refinement's inliers, pose refined at the new scale. Returns the
    /// Sim(3), its inliers as seeds of a new search, and their count; `None`
    /// when too few remain (the caller keeps the BoW fit).
    #[allow(clippy::too_many_arguments)]
    fn refit_on_projection(
        &self,
        map: &Map,
        k1: &KeyFrame,
        k2: &KeyFrame,
        cand: KeyFrameId,
        matched: &[Option<PointId>],
        s12: &Sim3,
        intr: &Intrinsics,
    ) -> Option<(Sim3, Vec<Option<PointId>>, usize)> {
        let p = &self.params;
        let sigma2 = &map.scale.inv_level_sigma2;
        let mut ms: Vec<Sim3Match> = Vec::new();
        let mut keep: Vec<(usize, PointId)> = Vec::new();
        for (i1, m) in matched.iter().enumerate() {
            let Some(p2) = *m else { continue };
            let Some(Some(p1)) = k1.points.get(i1) else {
                continue;
            };
            if *p1 == p2 {
                continue;
            }
            let (Some(mp1), Some(mp2), Some(kp1)) =
                (map.point(*p1), map.point(p2), k1.keypoints.get(i1))
            else {
                continue;
            };
            let x2 = k2.cam_from_world * mp2.position;
            // The loop-side point's keypoint in the candidate if it has one,
            // else its projection there (it was seen by a neighbour).
            let (uv2, s2) = match mp2
                .index_in(cand)
                .and_then(|i2| k2.keypoints.get(i2 as usize))
            {
                Some(kp2) => (
                    Point2::new(kp2.ux as f64, kp2.uy as f64),
                    *sigma2.get(kp2.octave as usize)?,
                ),
                None => {
                    if x2.z <= p.sim3.min_depth {
                        continue;
                    }
                    (
                        Point2::new(
                            intr.fx * x2.x / x2.z + intr.cx,
                            intr.fy * x2.y / x2.z + intr.cy,
                        ),
                        *sigma2.get(kp1.octave as usize)?,
                    )
                }
            };
            ms.push(Sim3Match {
                x1_cam1: k1.cam_from_world * mp1.position,
                x2_cam2: x2,
                uv1: Point2::new(kp1.ux as f64, kp1.uy as f64),
                uv2,
                inv_sigma2_1: *sigma2.get(kp1.octave as usize)?,
                inv_sigma2_2: s2,
            });
            keep.push((i1, p2));
        }
        let fixed = Sim3Params {
            fix_scale: true,
            ..p.sim3.clone()
        };
        let first = optimize_sim3(s12, &ms, intr, &fixed).ok()?;
        if first.n_inliers < p.min_sim3_inliers {
            return None;
        }
        let (src, dst): (Vec<_>, Vec<_>) = ms
            .iter()
            .zip(&first.inliers)
            .filter(|(_, ok)| **ok)
            .map(|(m, _)| (m.x2_cam2, m.x1_cam1))
            .unzip();
        let aligned = robust_scale_fit(&src, &dst, &first.s12)?;
        let refit = optimize_sim3(&aligned, &ms, intr, &fixed).ok()?;
        if refit.n_inliers < p.min_sim3_inliers {
            return None;
        }
        tracing::debug!(
            bow_scale = s12.scale,
            refit_scale = refit.s12.scale,
            pairs = ms.len(),
            scale_inliers = first.n_inliers,
            refit_inliers = refit.n_inliers,
            "loop: Sim(3) refitted on the projection matches"
        );
        let mut seeds = vec![None; matched.len()];
        for ((i1, p2), ok) in keep.iter().zip(&refit.inliers) {
            if *ok {
                seeds[*i1] = Some(*p2);
            }
        }
        Some((refit.s12, seeds, refit.n_inliers))
    }

    /// The correction under the map lock (see the module doc): the
    /// neighbourhood corrected, the points fused, and the essential graph
    /// built; the loop's event (its trajectory after and its time filled
    /// in when the graph is applied) and the graph, to be solved without
    /// the lock.
    fn correct(
        &mut self,
        map: &mut Map,
        kf: KeyFrameId,
        lm: LoopMatch,
    ) -> Option<(LoopEvent, EssentialGraph)> {
        let started = Instant::now();
        let p = &self.params;
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
        let (fused, loop_links) = fuse_and_link(map, kf, &connected, &lm, &self.bounds, p);
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
}

/// Fuse a verified place's points into the current side: the matched
/// loop-side points replace the current keyframe's (or are added to it),
/// the loop neighbourhood's points are fused into every keyframe of
/// `connected`, whose connections are then updated. Returns the points
/// fused and the new covisibility links between the two sides.
fn fuse_and_link(
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

/// Bundle adjustment over every keyframe and point of `kf`'s map, the
/// map's first keyframe fixed: the problem is built and written back under the map
/// lock, solved without it (keyframes added meanwhile keep their poses).
/// Returns the final reprojection RMSE, px.
fn global_bundle_adjustment(
    map: &Mutex<Map>,
    kf: KeyFrameId,
    params: &BaParams,
    pause: Option<&MappingPause>,
    holds: &mut Vec<LockHold>,
) -> Option<f64> {
    let mut setup = {
        let m = lock(map);
        let from = Instant::now();
        let _hold = HoldGuard {
            holds: &mut *holds,
            kf,
            from,
        };
        let id = m.map_of(kf)?;
        let kfs: Vec<KeyFrameId> = m.keyframes_in(id).map(|k| k.id).collect();
        let fixed: Vec<KeyFrameId> = m.root_of(id).into_iter().collect();
        if kfs.len() < 2 {
            return None;
        }
        build_ba_problem(&m, &kfs, &fixed)?
    };
    let report = crate::optimize::local_bundle_adjustment(&mut setup.problem, params).ok()?;
    tracing::debug!(
        keyframes = setup.keyframes.len(),
        points = setup.points.len(),
        before = report.initial_rmse_px,
        after = report.final_rmse_px,
        outliers = report.n_outliers,
        "loop: global BA"
    );
    // Solved beside local mapping; written back with it held (its
    // adjustments made meanwhile give way to the global solution).
    let held = pause.map(MappingPause::hold);
    let mut m = lock(map);
    let from = Instant::now();
    apply_ba_result(&mut m, &setup, &report.outliers);
    m.note_correction();
    drop(m);
    drop(held);
    holds.push(LockHold {
        kf,
        from,
        to: Instant::now(),
        kind: HoldKind::GlobalBa,
    });
    Some(report.final_rmse_px)
}

/// Records a global BA's lock hold when dropped (every return of the
/// block that builds the problem).
struct HoldGuard<'a> {
    holds: &'a mut Vec<LockHold>,
    kf: KeyFrameId,
    from: Instant,
}

impl Drop for HoldGuard<'_> {
    fn drop(&mut self) {
        self.holds.push(LockHold {
            kf: self.kf,
            from: self.from,
            to: Instant::now(),
            kind: HoldKind::GlobalBa,
        });
    }
}

/// The similarity mapping `src` onto `dst` with the rotation of `guess`,
/// the scale the median of the ratios of distances between point pairs
/// (each point with the one half the list away): unlike a least-squares
/// fit, noise on either side's depths does not pull it towards zero and a
/// few bad depths do not move it. The translation aligns the centroids.
pub fn robust_scale_fit(
    src: &[nalgebra::Point3<f64>],
    dst: &[nalgebra::Point3<f64>],
    guess: &Sim3,
) -> Option<Sim3> {
    let n = src.len().min(dst.len());
    if n < 3 {
        return None;
    }
    let logs: Vec<f64> = (0..n)
        .filter_map(|i| {
            let j = (i + n / 2) % n;
            let a = (dst[i] - dst[j]).norm();
            let b = (src[i] - src[j]).norm();
            (a > 0.0 && b > 0.0).then(|| (a / b).ln())
        })
        .filter(|v| v.is_finite())
        .collect();
    let scale = crate::stats::quantile(&logs, 0.5)?.exp();
    let c_src = src.iter().map(|p| p.coords).sum::<nalgebra::Vector3<f64>>() / n as f64;
    let c_dst = dst.iter().map(|p| p.coords).sum::<nalgebra::Vector3<f64>>() / n as f64;
    let t = c_dst - guess.rotation * c_src * scale;
    Some(Sim3::new(guess.rotation, t, scale))
}

/// The rigid pose of a similarity `S_cw` (world → camera): the same
/// camera, `(R, t/s)`.
pub fn sim3_to_isometry(s: &Sim3) -> Isometry3<f64> {
    Isometry3::from_parts(Translation3::from(s.translation / s.scale), s.rotation)
}

/// Length of the path through the live keyframes between two keyframes
/// (by id, so by time), in map units.
fn path_length(map: &Map, from: KeyFrameId, to: KeyFrameId) -> f64 {
    let (a, b) = (from.min(to), from.max(to));
    let mut last: Option<nalgebra::Vector3<f64>> = None;
    let mut len = 0.0;
    for k in map.keyframes().filter(|k| k.id >= a && k.id <= b) {
        let c = k.center();
        if let Some(l) = last {
            len += (c - l).norm();
        }
        last = Some(c);
    }
    len
}

/// The live keyframes of map `id` (world_from_cam), by time.
fn map_trajectory(map: &Map, id: MapId) -> Trajectory {
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

fn keyframe_trajectory(map: &Map) -> Trajectory {
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

/// The essential graph in Sim(3) over the keyframes `graph_kfs` (one
/// map's), those in `anchored` fixed (a loop: the loop keyframe; a merge:
/// the old map's keyframes); keyframe poses and the points of those
/// keyframes updated. Returns the number of edges.
#[allow(clippy::too_many_arguments)]
fn optimize_essential_graph(
    map: &mut Map,
    graph_kfs: Vec<KeyFrameId>,
    anchored: &HashSet<KeyFrameId>,
    loop_kf: KeyFrameId,
    current: KeyFrameId,
    corrected: &HashMap<KeyFrameId, Sim3>,
    uncorrected: &HashMap<KeyFrameId, Sim3>,
    corrected_by: HashMap<PointId, KeyFrameId>,
    loop_links: &[(KeyFrameId, KeyFrameId)],
    p: &LoopParams,
) -> usize {
    let mut eg = EssentialGraph::build(
        map,
        graph_kfs,
        anchored,
        loop_kf,
        current,
        corrected,
        uncorrected,
        corrected_by,
        loop_links,
        p,
        Instant::now(),
    );
    if eg.solve(&p.pose_graph) {
        eg.apply(map);
    }
    eg.edges
}

/// The essential graph of a correction: built from the map (under its
/// lock), solved on its own copy of the poses (a loop's without the lock:
/// tracking goes on meanwhile), then written back (under the lock again).
struct EssentialGraph {
    /// The keyframes of the graph, in vertex order.
    ids: Vec<KeyFrameId>,
    /// Vertex of each keyframe.
    index: HashMap<KeyFrameId, usize>,
    /// The largest id in it (keyframes added later follow a vertex).
    max_id: KeyFrameId,
    /// The keyframe that closed the loop (or made the merge).
    current: KeyFrameId,
    graph: PoseGraph,
    /// The poses before the solve (corrected where the loop corrected them).
    initial: Vec<Sim3>,
    /// Points corrected with a keyframe of the loop's neighbourhood: they
    /// follow that keyframe.
    corrected_by: HashMap<PointId, KeyFrameId>,
    /// Its edges.
    edges: usize,
    /// When the correction it belongs to started.
    started: Instant,
}

impl EssentialGraph {
    /// The graph of the keyframes `graph_kfs` (the live ones): spanning
    /// tree, loop edges, strong covisibility, the new links of the loop
    /// (measured with the corrected poses), and `anchored` held fixed (the
    /// first vertex when none is).
    #[allow(clippy::too_many_arguments)]
    fn build(
        map: &Map,
        graph_kfs: Vec<KeyFrameId>,
        anchored: &HashSet<KeyFrameId>,
        loop_kf: KeyFrameId,
        current: KeyFrameId,
        corrected: &HashMap<KeyFrameId, Sim3>,
        uncorrected: &HashMap<KeyFrameId, Sim3>,
        corrected_by: HashMap<PointId, KeyFrameId>,
        loop_links: &[(KeyFrameId, KeyFrameId)],
        p: &LoopParams,
        started: Instant,
    ) -> Self {
        let ids: Vec<KeyFrameId> = graph_kfs
            .into_iter()
            .filter(|id| map.keyframe(*id).is_some())
            .collect();
        let index: HashMap<KeyFrameId, usize> =
            ids.iter().enumerate().map(|(i, id)| (*id, i)).collect();
        let mut poses = Vec::with_capacity(ids.len());
        let mut plain = Vec::with_capacity(ids.len());
        for id in &ids {
            let Some(k) = map.keyframe(*id) else { continue };
            let s = corrected
                .get(id)
                .copied()
                .unwrap_or_else(|| Sim3::from_isometry(&k.cam_from_world));
            poses.push(s);
            plain.push(uncorrected.get(id).copied().unwrap_or(s));
        }
        let mut fixed: Vec<bool> = ids.iter().map(|id| anchored.contains(id)).collect();
        if !fixed.iter().any(|f| *f)
            && let Some(f) = fixed.first_mut()
        {
            *f = true;
        }
        let mut edges: Vec<Sim3Edge> = Vec::new();
        let mut have: HashSet<(usize, usize)> = HashSet::new();
        let mut push = |i: usize, j: usize, s_ji: Sim3, edges: &mut Vec<Sim3Edge>| {
            let key = (i.min(j), i.max(j));
            if i != j && have.insert(key) {
                edges.push(Sim3Edge {
                    i,
                    j,
                    s_ji,
                    weight: 1.0,
                });
            }
        };
        // New loop links, measured with the corrected poses.
        for (a, b) in loop_links {
            let (Some(&i), Some(&j)) = (index.get(a), index.get(b)) else {
                continue;
            };
            let w = map.keyframe(*a).map_or(0, |k| k.weight(*b));
            let is_loop = (*a == current && *b == loop_kf) || (*b == current && *a == loop_kf);
            if !is_loop && w < p.essential_min_weight {
                continue;
            }
            push(i, j, poses[j].compose(&poses[i].inverse()), &mut edges);
        }
        // The closing edge itself, measured with the corrected poses.
        if let (Some(&i), Some(&j)) = (index.get(&current), index.get(&loop_kf)) {
            push(i, j, poses[j].compose(&poses[i].inverse()), &mut edges);
        }
        for (i, id) in ids.iter().enumerate() {
            let Some(k) = map.keyframe(*id) else { continue };
            let s_wi = plain[i].inverse();
            if let Some(parent) = k.parent
                && let Some(&j) = index.get(&parent)
            {
                push(i, j, plain[j].compose(&s_wi), &mut edges);
            }
            for (a, b) in map.loop_edges() {
                let other = if *a == *id {
                    *b
                } else if *b == *id {
                    *a
                } else {
                    continue;
                };
                if let Some(&j) = index.get(&other) {
                    push(i, j, plain[j].compose(&s_wi), &mut edges);
                }
            }
            for (o, w) in &k.covisible {
                if *w < p.essential_min_weight {
                    break;
                }
                if let Some(&j) = index.get(o) {
                    push(i, j, plain[j].compose(&s_wi), &mut edges);
                }
            }
        }
        let n_edges = edges.len();
        EssentialGraph {
            max_id: ids.iter().copied().max().unwrap_or(current),
            ids,
            index,
            current,
            initial: poses.clone(),
            graph: PoseGraph {
                poses,
                fixed,
                edges,
            },
            corrected_by,
            edges: n_edges,
            started,
        }
    }

    /// Optimise the poses (the map is not touched); false when the
    /// optimisation failed (logged; nothing to apply).
    fn solve(&mut self, params: &PoseGraphParams) -> bool {
        match optimize_pose_graph(&mut self.graph, params) {
            Ok(summary) => {
                tracing::debug!(?summary, edges = self.edges, "essential graph optimised");
                true
            }
            Err(e) => {
                tracing::warn!("essential graph not optimised: {e}");
                false
            }
        }
    }

    /// The similarity that moves what vertex `i` carries (world_new ←
    /// world_old).
    fn point_move(&self, i: usize) -> Sim3 {
        self.graph.poses[i].inverse().compose(&self.initial[i])
    }

    /// Write the optimised poses back: the graph's keyframes take theirs;
    /// keyframes of the same map added since the graph was built keep
    /// their pose relative to their parent's vertex (the current
    /// keyframe's when their parent is not in the graph); every point
    /// moves with the keyframe it was corrected by, else its reference
    /// keyframe, else any observer in the graph.
    fn apply(&self, map: &mut Map) {
        let my_map = map.map_of(self.current);
        let added: Vec<(KeyFrameId, usize)> = map
            .keyframes()
            .filter(|k| k.id > self.max_id && map.map_of(k.id) == my_map)
            .filter_map(|k| {
                let follow = k
                    .parent
                    .and_then(|p| self.index.get(&p))
                    .or_else(|| self.index.get(&self.current))?;
                Some((k.id, *follow))
            })
            .collect();
        for (id, i) in added {
            if let Some(k) = map.keyframe_mut(id) {
                let s = Sim3::from_isometry(&k.cam_from_world)
                    .compose(&self.initial[i].inverse())
                    .compose(&self.graph.poses[i]);
                k.cam_from_world = sim3_to_isometry(&s);
            }
        }
        for (i, id) in self.ids.iter().enumerate() {
            if let Some(k) = map.keyframe_mut(*id) {
                k.cam_from_world = sim3_to_isometry(&self.graph.poses[i]);
            }
        }
        let pids: Vec<PointId> = map.points().map(|mp| mp.id).collect();
        for pid in pids {
            let Some(mp) = map.point(pid) else { continue };
            let r = self
                .corrected_by
                .get(&pid)
                .copied()
                .filter(|r| self.index.contains_key(r))
                .or_else(|| Some(mp.ref_kf).filter(|r| self.index.contains_key(r)))
                .or_else(|| {
                    mp.observations
                        .iter()
                        .map(|o| o.0)
                        .find(|r| self.index.contains_key(r))
                });
            let Some(r) = r else { continue };
            let s_move = self.point_move(self.index[&r]);
            if let Some(mp) = map.point_mut(pid) {
                mp.position = s_move.transform_point(&mp.position);
            }
            map.update_point_normal_and_depth(pid);
        }
    }
}

/// The keypoint of `k1` nearest to `descriptor` (Hamming distance, first
/// wins a tie) among those within `radius` px of the projection `pr` and
/// one pyramid level of it, skipping those `skip` names; `(u32::MAX,
/// usize::MAX)` when none. `cand` is a reused buffer.
fn nearest_in_window(
    k1: &KeyFrame,
    pr: &matcher::Projected,
    radius: f64,
    descriptor: &Descriptor,
    cand: &mut Vec<usize>,
    skip: impl Fn(usize) -> bool,
) -> (u32, usize) {
    let lvl = pr.level as i32;
    k1.grid.features_in_area(
        &k1.keypoints,
        pr.uv.x,
        pr.uv.y,
        radius,
        lvl - 1,
        lvl + 1,
        cand,
    );
    let mut best = (u32::MAX, usize::MAX);
    for &i in cand.iter() {
        if skip(i) {
            continue;
        }
        let d = hamming(descriptor, &k1.descriptors[i]);
        if d < best.0 {
            best = (d, i);
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Point3, UnitQuaternion, Vector3};
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    /// Two monocular maps of one scene seen from one place: each point's
    /// depth along its ray is off by up to ±15 % on each side,
    /// independently. The least-squares (Umeyama) scale is pulled down by
    /// the noise on the source side; the median of pairwise distance
    /// ratios stays within 2 % of the truth.
    #[test]
    fn robust_scale_is_not_pulled_by_depth_noise() {
        let truth = Sim3::new(
            UnitQuaternion::from_euler_angles(0.01, -0.02, 0.03),
            Vector3::new(0.1, -0.05, 0.2),
            1.25,
        );
        let mut rng = SmallRng::seed_from_u64(4);
        let noisy_depth = |p: Point3<f64>, rng: &mut SmallRng| -> Point3<f64> {
            let f = 1.0 + rng.random_range(-0.15..0.15);
            Point3::from(p.coords * f)
        };
        let (mut src, mut dst) = (Vec::new(), Vec::new());
        for _ in 0..300 {
            let x2 = Point3::new(
                rng.random_range(-20.0..20.0),
                rng.random_range(-15.0..15.0),
                rng.random_range(30.0..50.0),
            );
            let x1 = truth.transform_point(&x2);
            src.push(noisy_depth(x2, &mut rng));
            dst.push(noisy_depth(x1, &mut rng));
        }
        let guess = Sim3::new(truth.rotation, Vector3::zeros(), 1.0);
        let robust = robust_scale_fit(&src, &dst, &guess).unwrap();
        let ls = crate::geometry::umeyama(&src, &dst, true).unwrap();
        assert!(
            (robust.scale / truth.scale - 1.0).abs() < 0.02,
            "robust scale {}",
            robust.scale
        );
        assert!(
            ls.scale / truth.scale < 0.95,
            "least squares scale {}: the test needs its bias",
            ls.scale
        );
        assert!(robust_scale_fit(&src[..2], &dst[..2], &guess).is_none());
    }
}

#[cfg(test)]
mod graph_tests {
    use super::*;
    use crate::camera::{Camera, Distortion};
    use crate::features::KeyPoint;
    use crate::matching::FeatureGrid;
    use nalgebra::Point3;

    /// Keypoint slots of each keyframe.
    const SLOTS: usize = 60;

    fn keyframe(x: f64) -> KeyFrame {
        KeyFrame {
            id: KeyFrameId(0),
            frame_index: 0,
            timestamp: x,
            cam_from_world: Isometry3::translation(-x, 0.0, 0.0),
            keypoints: vec![KeyPoint::default(); SLOTS],
            descriptors: vec![[0; 4]; SLOTS],
            points: vec![None; SLOTS],
            grid: FeatureGrid::default(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: None,
        }
    }

    /// Four keyframes along x in a chain: each shares points with the one
    /// before it (30, 25, 20: fewer further on, so each one's strongest
    /// neighbour, its parent, is the one before).
    fn chain() -> Map {
        let cam = Camera::new(
            640,
            480,
            [500.0, 500.0, 320.0, 240.0],
            Distortion::default(),
        )
        .unwrap();
        let mut m = Map::new(cam, crate::slam::ScaleInfo::new(1.2, 8));
        let ids: Vec<KeyFrameId> = (0..4).map(|i| m.add_keyframe(keyframe(i as f64))).collect();
        let mut next_slot = [0u32; 4];
        for b in 1..4 {
            for j in 0..(35 - 5 * b) {
                let p = m.add_point(
                    Point3::new(b as f64 + j as f64 * 0.02, 0.0, 5.0),
                    [j as u64; 4],
                    ids[b - 1],
                );
                for k in [b - 1, b] {
                    assert!(m.add_observation(p, ids[k], next_slot[k]));
                    next_slot[k] += 1;
                }
            }
        }
        for &k in &ids {
            m.update_connections(k);
        }
        for k in 1..4 {
            assert_eq!(m.keyframe(ids[k]).unwrap().parent, Some(ids[k - 1]));
        }
        m
    }

    /// The loop's graph is solved without the map lock, so tracking may
    /// add a keyframe meanwhile: written back, the graph moves it with
    /// the keyframe that closed the loop (its pose relative to it kept,
    /// the translation scaled as the graph scaled that keyframe's
    /// surroundings), and the loop keyframe stays where it was.
    #[test]
    fn a_keyframe_added_while_the_graph_is_solved_follows_the_current_keyframe() {
        let mut m = chain();
        let (first, current) = (KeyFrameId(0), KeyFrameId(3));
        let plain = Sim3::from_isometry(&m.keyframe(current).unwrap().cam_from_world);
        // The loop puts the current keyframe half a unit further along x
        // (the drift it corrects), as the correction's first step does.
        let fixed_pose = Isometry3::translation(-3.5, 0.0, 0.0);
        m.keyframe_mut(current).unwrap().cam_from_world = fixed_pose;
        let corrected = HashMap::from([(current, Sim3::from_isometry(&fixed_pose))]);
        let uncorrected = HashMap::from([(current, plain)]);
        let ids: Vec<KeyFrameId> = m.keyframes().map(|k| k.id).collect();
        let p = LoopParams::default();
        let mut graph = EssentialGraph::build(
            &m,
            ids,
            &HashSet::from([first]),
            first,
            current,
            &corrected,
            &uncorrected,
            HashMap::new(),
            &[(current, first)],
            &p,
            Instant::now(),
        );
        assert!(graph.edges >= 4, "{} edges", graph.edges);
        // Tracking adds a keyframe just past the current one meanwhile.
        let added = m.add_keyframe(keyframe(3.7));
        let before = m.keyframe(added).unwrap().cam_from_world
            * m.keyframe(current).unwrap().cam_from_world.inverse();
        let first_before = m.keyframe(first).unwrap().cam_from_world;
        let middle_before = m.keyframe(KeyFrameId(2)).unwrap().cam_from_world;
        assert!(graph.solve(&p.pose_graph));
        graph.apply(&mut m);
        let i = graph.index[&current];
        let scale = graph.graph.poses[i].scale / graph.initial[i].scale;
        let after = m.keyframe(added).unwrap().cam_from_world
            * m.keyframe(current).unwrap().cam_from_world.inverse();
        assert!(
            (after.translation.vector * scale - before.translation.vector).norm() < 1e-9,
            "{after:?} {before:?} scale {scale}"
        );
        assert!(after.rotation.angle_to(&before.rotation) < 1e-9);
        assert_eq!(m.keyframe(first).unwrap().cam_from_world, first_before);
        // The correction spread along the chain: the keyframe before the
        // current one moved too.
        let moved = (m
            .keyframe(KeyFrameId(2))
            .unwrap()
            .cam_from_world
            .translation
            .vector
            - middle_before.translation.vector)
            .norm();
        assert!(moved > 0.05, "moved {moved}");
        m.check_invariants().unwrap();
    }
}
