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
//!
//! # Layout (each file points down to the ones below it)
//!
//! | file | what it holds |
//! |---|---|
//! | `mod.rs` | the [`LoopCloser`]: per keyframe, a merge or a loop searched under the map lock, the essential graph solved without it and written back, the global BA; the re-exports |
//! | `merge.rs` | merge detection (candidates in other maps, agreement of consecutive similarities) and the merge |
//! | `correct.rs` | a loop's correction up to its essential graph |
//! | `global_ba.rs` | the global BA after a loop |
//! | `graph.rs` | the essential graph: built, solved, written back |
//! | `fuse.rs` | a verified place's points fused into the current side |
//! | `verify.rs` | a candidate's Sim(3) verified (`LoopMatch`) |
//! | `detect.rs` | BoW candidates and their consistency |
//! | `sim3.rs` | [`sim3_to_isometry`], [`robust_scale_fit`] |
//! | `log.rs` | events, summaries, logs, refusals, lock holds |
//! | `params.rs` | [`LoopParams`] |

mod correct;
mod detect;
mod fuse;
mod global_ba;
mod graph;
mod log;
mod merge;
mod params;
mod sim3;
mod verify;

use std::collections::HashSet;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use crate::lie::Sim3;
use crate::matching::Bounds;

use super::map::{KeyFrameId, Map, MapId, lock};
use super::params::bound_history;
use super::pause::{self, MappingPause};

pub use self::log::{
    HoldKind, LockHold, LoopEvent, LoopLog, LoopRefusal, LoopReject, LoopSummary, MergeEvent,
    MergeLog, MergeSummary,
};
pub use self::params::LoopParams;
pub use self::sim3::{robust_scale_fit, sim3_to_isometry};

use self::correct::correct;
use self::detect::detect;
use self::global_ba::global_bundle_adjustment;
use self::graph::EssentialGraph;
use self::log::keyframe_trajectory;
use self::merge::look_for_merge;
use self::verify::verify;

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

    /// The loop closer's thread: each keyframe local mapping finished
    /// (`rx`), in order, at a lower priority than tracking and mapping
    /// ([`pause::LOOP_THREAD_NICENESS`]); gives the closer back when `rx`
    /// closes.
    pub(crate) fn spawn(
        mut self,
        rx: std::sync::mpsc::Receiver<KeyFrameId>,
        map: Arc<Mutex<Map>>,
    ) -> std::io::Result<std::thread::JoinHandle<LoopCloser>> {
        std::thread::Builder::new()
            .name("slam-loop".into())
            .spawn(move || {
                if !pause::lower_this_thread_priority(pause::LOOP_THREAD_NICENESS) {
                    tracing::debug!("loop closing runs at the process's priority");
                }
                while let Ok(kf) = rx.recv() {
                    self.process_keyframe(&map, kf);
                }
                self
            })
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
        if self.params.merging && self.try_merge(m, kf) {
            return (HoldKind::Merge, None);
        }
        let candidates = detect(&self.params, self.last_loop, &mut self.groups, m, kf, false);
        if candidates.is_empty() {
            return (HoldKind::Search, None);
        }
        let Some(found) = verify(
            &self.params,
            &self.bounds,
            m,
            kf,
            &candidates,
            &mut self.refusals,
        ) else {
            return (HoldKind::Search, None);
        };
        let event = correct(&self.params, &self.bounds, m, kf, found);
        let kind = if event.is_some() {
            HoldKind::Loop
        } else {
            HoldKind::Search
        };
        (kind, event)
    }

    /// Look for a place of another map at `kf` and merge the maps
    /// ([`merge::look_for_merge`]); a merge made is logged and recorded,
    /// and both searches start over. True when the maps were merged.
    fn try_merge(&mut self, map: &mut Map, kf: KeyFrameId) -> bool {
        let Some(event) = look_for_merge(
            &self.params,
            &self.bounds,
            map,
            kf,
            &mut self.merge_groups,
            &mut self.pending_merge,
            &mut self.merge_refusals,
        ) else {
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
}
