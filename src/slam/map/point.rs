//! A map point ([`MapPoint`]): a 3D point with the keyframes that observe
//! it, its representative descriptor, mean viewing direction and scale
//! range, and how often tracking found it. What the map does with points is
//! in `observations.rs`.

use nalgebra::{Point3, Vector3};

use crate::features::Descriptor;

use super::ids::{KeyFrameId, PointId};

/// A 3D point of the map with the keyframes that observe it.
#[derive(Debug, Clone)]
pub struct MapPoint {
    /// Its id.
    pub id: PointId,
    /// Position in the world.
    pub position: Point3<f64>,
    /// Observations: (keyframe, keypoint index in it).
    pub observations: Vec<(KeyFrameId, u32)>,
    /// The representative descriptor: the observation with the least median
    /// distance to the others.
    pub descriptor: Descriptor,
    /// Mean viewing direction (unit, world frame), from the point to the cameras.
    pub normal: Vector3<f64>,
    /// Closest distance at which the point keeps its scale (scale invariance).
    pub min_distance: f64,
    /// Farthest distance at which the point keeps its scale.
    pub max_distance: f64,
    /// The keyframe that created it.
    pub first_kf: KeyFrameId,
    /// The keyframe used as reference for the scale range.
    pub ref_kf: KeyFrameId,
    /// Frames in whose view frustum it was.
    pub visible: u32,
    /// Frames in which it was matched.
    pub found: u32,
}

impl MapPoint {
    /// Share of the frames that saw it in view that also matched it.
    pub fn found_ratio(&self) -> f64 {
        self.found as f64 / self.visible.max(1) as f64
    }

    /// Keypoint index of this point in keyframe `kf`.
    pub fn index_in(&self, kf: KeyFrameId) -> Option<u32> {
        self.observations.iter().find(|o| o.0 == kf).map(|o| o.1)
    }
}
