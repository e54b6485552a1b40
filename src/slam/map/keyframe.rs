//! A keyframe ([`KeyFrame`]): a frame kept in the map with its features,
//! pose, point slots, covisible keyframes and spanning-tree links; and what
//! is kept of a culled one ([`CulledKeyFrame`]: its pose relative to its
//! parent). What the map does with keyframes is in `graph.rs` (insertion,
//! culling, covisibility) and `observations.rs` (their points).

use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Isometry3, Vector3};

use crate::features::{Descriptor, KeyPoint};
use crate::matching::FeatureGrid;

use super::ids::{KeyFrameId, PointId};

/// A keyframe: a frame kept in the map, with its features and pose.
#[derive(Debug, Clone)]
pub struct KeyFrame {
    /// Its id.
    pub id: KeyFrameId,
    /// Index of the source frame in the input stream.
    pub frame_index: u64,
    /// Capture time, seconds.
    pub timestamp: f64,
    /// Pose: world to camera.
    pub cam_from_world: Isometry3<f64>,
    /// Keypoints (level-0 pixels, distorted and undistorted).
    pub keypoints: Vec<KeyPoint>,
    /// Descriptors, one per keypoint.
    pub descriptors: Vec<Descriptor>,
    /// Per keypoint: the map point it observes.
    pub points: Vec<Option<PointId>>,
    /// Keypoints by image cell (undistorted coordinates).
    pub grid: FeatureGrid,
    /// Covisible keyframes with the number of shared points (weight >= the
    /// connection threshold), sorted by weight, largest first.
    pub covisible: Vec<(KeyFrameId, u32)>,
    /// Parent in the spanning tree (none for the first keyframe).
    pub parent: Option<KeyFrameId>,
    /// Children in the spanning tree.
    pub children: Vec<KeyFrameId>,
    /// The grayscale image (for the map file, the API and the desired shot).
    pub image: Option<Arc<GrayImage>>,
}

impl KeyFrame {
    /// The camera centre in world coordinates.
    pub fn center(&self) -> Vector3<f64> {
        self.cam_from_world.inverse().translation.vector
    }

    /// The pose as world_from_cam.
    pub fn world_from_cam(&self) -> Isometry3<f64> {
        self.cam_from_world.inverse()
    }

    /// The best `n` covisible keyframes.
    pub fn best_covisible(&self, n: usize) -> impl Iterator<Item = KeyFrameId> + '_ {
        self.covisible.iter().take(n).map(|c| c.0)
    }

    /// Weight of the edge to `other` (0 when not connected).
    pub fn weight(&self, other: KeyFrameId) -> u32 {
        self.covisible
            .iter()
            .find(|c| c.0 == other)
            .map_or(0, |c| c.1)
    }
}

/// A keyframe removed from the map, kept so frames that referred to it can
/// still be placed: their pose goes through its parent.
#[derive(Debug, Clone, Copy)]
pub struct CulledKeyFrame {
    /// Its parent when it was removed.
    pub parent: KeyFrameId,
    /// Its pose relative to the parent: cam_from_parent_cam.
    pub cam_from_parent: Isometry3<f64>,
}
