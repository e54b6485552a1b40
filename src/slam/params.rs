//! The tunables of tracking: one flat [`TrackingParams`] that the
//! initializer, the relocalizer, local-map tracking and the keyframe
//! decision each read their numbers from.

use crate::geometry::{PnpParams, TwoViewParams};
use crate::optimize::{BaParams, PoseParams};

use super::matcher::MatcherParams;

/// Tunable numbers of tracking.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackingParams {
    /// ORB extractor for tracking.
    pub features: crate::features::Params,
    /// Features of the two initialisation frames (ORB-SLAM uses twice as many).
    pub init_features: usize,
    /// Matches needed between the initialisation frames to try.
    pub init_min_matches: usize,
    /// Search window of initialisation matching, pixels.
    pub init_window: f64,
    /// Highest pyramid level matched between the initialisation frames
    /// (ORB-SLAM: 0); a keypoint is matched with keypoints one level up or
    /// down.
    pub init_max_octave: i32,
    /// Planar scenes: the twin reconstruction is rejected when its
    /// third-view cost exceeds the chosen one's by this factor.
    pub planar_cost_ratio: f64,
    /// Planar scenes: the chosen reconstruction's third-view cost (mean
    /// squared reprojection error, pixels²) must stay below this.
    pub planar_max_cost: f64,
    /// Map points the initial map must keep after its bundle adjustment.
    pub init_min_points: usize,
    /// Search radius factor of the motion-model search, pixels at level 0
    /// (ORB-SLAM's `TrackWithMotionModel`, monocular: 15).
    pub motion_search_radius: f64,
    /// Search radius factor of the local-map search by projection, times
    /// the viewing-angle factor (`matcher::FRONTAL_RADIUS_FACTOR` or
    /// `OBLIQUE_RADIUS_FACTOR`) and the level's scale (ORB-SLAM's
    /// `SearchLocalPoints`, monocular: 1).
    pub local_map_radius: f64,
    /// The same in the frames right after a relocalisation, whose pose is
    /// rougher (ORB-SLAM's `SearchLocalPoints`: 5).
    pub local_map_radius_after_reloc: f64,
    /// Matches needed from the motion model before optimising (ORB-SLAM's
    /// `TrackWithMotionModel`: 20).
    pub min_motion_matches: usize,
    /// Inliers the motion-only BA must keep for the motion model or the
    /// reference keyframe to give the frame a pose, before the local map
    /// (ORB-SLAM's `TrackWithMotionModel` and `TrackReferenceKeyFrame`:
    /// 10).
    pub min_pose_inliers: usize,
    /// Matches needed with the reference keyframe before optimising
    /// (ORB-SLAM's `TrackReferenceKeyFrame`: 15).
    pub min_reference_matches: usize,
    /// Nearest-neighbour ratio of the matching with the reference keyframe
    /// (ORB-SLAM's `ORBmatcher(0.7, true)` in `TrackReferenceKeyFrame`).
    pub reference_ratio: f32,
    /// Inliers needed to call a frame tracked after the local map
    /// (ORB-SLAM's `TrackLocalMap`: 30).
    pub min_tracked_inliers: usize,
    /// Inliers needed in the frames right after a relocalisation
    /// (ORB-SLAM's `TrackLocalMap`: 50).
    pub min_inliers_after_reloc: usize,
    /// Frames between keyframes at most (ORB-SLAM: the frame rate).
    pub max_frames_between_keyframes: u64,
    /// Frames between keyframes at least.
    pub min_frames_between_keyframes: u64,
    /// A keyframe is due when the tracked points fall below this share of
    /// the reference keyframe's.
    pub keyframe_ref_ratio: f64,
    /// Local keyframes at most.
    pub max_local_keyframes: usize,
    /// Descriptor matching thresholds.
    pub matcher: MatcherParams,
    /// Bag of words: direct-index level and relocalisation candidates.
    pub bow: crate::bow::Params,
    /// Relocalisation tries at most this many candidate keyframes.
    pub reloc_max_candidates: usize,
    /// Matches a relocalisation candidate needs from BoW matching
    /// (ORB-SLAM's `Relocalization`: 15).
    pub reloc_min_bow_matches: usize,
    /// Nearest-neighbour ratio of relocalisation's BoW matching (ORB-SLAM's
    /// `ORBmatcher(0.75, true)` in `Relocalization`).
    pub reloc_ratio: f32,
    /// Two-view initialisation.
    pub two_view: TwoViewParams,
    /// Motion-only bundle adjustment.
    pub pose: PoseParams,
    /// PnP for relocalisation.
    pub pnp: PnpParams,
    /// Bundle adjustment of the initial map.
    pub init_ba: BaParams,
    /// After tracking is lost, relocalisation is tried for this many
    /// frames; then a new map starts at once: the initializer runs on the
    /// next frames while relocalisation into the old maps is still tried
    /// on each of them (`None`: relocalise only, forever).
    pub new_map_after_lost_frames: Option<u64>,
    /// A frame with more than this share of its pixels masked (rows a lost
    /// video packet damaged) is tracked on its intact part but never
    /// becomes a keyframe and never starts a map: a keyframe lives on in
    /// the map, and one seen through a quarter of its picture would carry
    /// few, clustered points.
    pub max_masked_share: f64,
    /// Seed of the randomised steps.
    pub seed: u64,
}

/// Drops the oldest entries of a record kept per frame or per keyframe
/// once it holds more than twice `keep` (so the cost per entry stays
/// constant); `None` keeps every entry.
pub(crate) fn bound_history<T>(v: &mut Vec<T>, keep: Option<usize>) {
    if let Some(k) = keep {
        let k = k.max(1);
        if v.len() > 2 * k {
            v.drain(..v.len() - k);
        }
    }
}

impl Default for TrackingParams {
    fn default() -> Self {
        TrackingParams {
            features: crate::features::Params::default(),
            init_features: 2000,
            init_min_matches: 100,
            init_window: 100.0,
            init_max_octave: 2,
            planar_cost_ratio: 2.0,
            planar_max_cost: 2.0,
            init_min_points: 80,
            motion_search_radius: 15.0,
            local_map_radius: 1.0,
            local_map_radius_after_reloc: 5.0,
            min_motion_matches: 20,
            min_pose_inliers: 10,
            min_reference_matches: 15,
            reference_ratio: 0.7,
            min_tracked_inliers: 30,
            min_inliers_after_reloc: 50,
            max_frames_between_keyframes: 30,
            min_frames_between_keyframes: 0,
            keyframe_ref_ratio: 0.9,
            max_local_keyframes: 80,
            matcher: MatcherParams::default(),
            bow: crate::bow::Params::default(),
            reloc_max_candidates: 30,
            reloc_min_bow_matches: 15,
            reloc_ratio: 0.75,
            two_view: TwoViewParams::default(),
            pose: PoseParams::default(),
            pnp: PnpParams::default(),
            init_ba: BaParams {
                first_pass_iterations: 20,
                second_pass_iterations: 10,
                ..BaParams::default()
            },
            new_map_after_lost_frames: Some(1),
            max_masked_share: 0.25,
            seed: 1,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::bound_history;

    #[test]
    fn a_bounded_history_keeps_the_newest_entries_within_twice_the_bound() {
        let mut v = Vec::new();
        for i in 0..1000 {
            v.push(i);
            bound_history(&mut v, Some(10));
            assert!(v.len() <= 20, "{} entries", v.len());
            assert!(v.len() >= 10.min(i + 1));
            assert_eq!(v.last(), Some(&i));
        }
        assert!(v.windows(2).all(|w| w[1] == w[0] + 1));
        let mut all: Vec<i32> = (0..100).collect();
        bound_history(&mut all, None);
        assert_eq!(all.len(), 100);
    }
}
