//! Small maps for the map's unit tests: a keyframe along x, and keyframes
//! that all see the same points.

use nalgebra::{Isometry3, Point3, Translation3};

use crate::camera::{Camera, Distortion};
use crate::features::KeyPoint;
use crate::matching::FeatureGrid;

use super::{KeyFrame, KeyFrameId, Map, ScaleInfo};

pub(super) fn kf(n: usize, x: f64) -> KeyFrame {
    KeyFrame {
        id: KeyFrameId(0),
        frame_index: 0,
        timestamp: x,
        cam_from_world: Isometry3::from_parts(Translation3::new(-x, 0.0, 0.0), Default::default()),
        keypoints: vec![KeyPoint::default(); n],
        descriptors: vec![[0; 4]; n],
        points: vec![None; n],
        grid: FeatureGrid::default(),
        covisible: Vec::new(),
        parent: None,
        children: Vec::new(),
        image: None,
    }
}

pub(crate) fn map_with(n_kf: usize, n_pts: usize) -> Map {
    let cam = Camera::new(
        640,
        480,
        [500.0, 500.0, 320.0, 240.0],
        Distortion::default(),
    )
    .unwrap();
    let mut m = Map::new(cam, ScaleInfo::new(1.2, 8));
    m.covisibility_threshold = 2;
    let ids: Vec<KeyFrameId> = (0..n_kf)
        .map(|i| m.add_keyframe(kf(n_pts, i as f64 * 0.1)))
        .collect();
    for j in 0..n_pts {
        let p = m.add_point(
            Point3::new(j as f64 * 0.01, 0.0, 2.0),
            [j as u64; 4],
            ids[0],
        );
        for &k in &ids {
            assert!(m.add_observation(p, k, j as u32));
        }
        m.update_point_normal_and_depth(p);
    }
    for &k in &ids {
        m.update_connections(k);
    }
    m
}
