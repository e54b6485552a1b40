//! The tunable numbers of loop closing and map merging ([`LoopParams`]).

use crate::geometry::Sim3RansacParams;
use crate::optimize::{BaParams, PoseGraphParams, Sim3Params};
use crate::slam::matcher::MatcherParams;

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
    /// Off by default: on the simulator renders it did not help (docs/FIGURES.md).
    pub global_ba: Option<BaParams>,
    /// Fit the loop's Sim(3) again on the matches the projection search
    /// found whose keypoint holds a point, and search once more. Off by
    /// default: on the simulator renders it did not help (docs/FIGURES.md).
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
