//! The SLAM's descriptor matching: for initialisation (window search), by
//! projection of map points into a frame, along epipolar lines for
//! triangulation, and fusion of duplicate points. Hamming distance on ORB
//! descriptors with ORB-SLAM's thresholds and rotation-consistency check.

use nalgebra::{Isometry3, Matrix3, Point2, Point3, Vector3};

use crate::bow::FeatureVector;
use crate::camera::Camera;
use crate::features::{Descriptor, KeyPoint, hamming};
use crate::matching::{Bounds, FeatureGrid, RotationHistogram};

use super::map::{KeyFrameId, Map, MapPoint, PointId, ScaleInfo};

/// Tunable numbers of the matcher. Defaults are ORB-SLAM's (`ORBmatcher`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MatcherParams {
    /// Largest Hamming distance (of 256 bits) for a match by projection:
    /// the last frame's points and the local map's (ORB-SLAM's `TH_HIGH`,
    /// 100).
    pub th_high: u32,
    /// Largest Hamming distance for initialisation, triangulation, fusion
    /// and BoW matching (ORB-SLAM's `TH_LOW`, 50).
    pub th_low: u32,
    /// Bins of the rotation-consistency histogram, 12 degrees each
    /// (ORB-SLAM's `HISTO_LENGTH`, 30).
    pub histo_bins: usize,
    /// Nearest-neighbour ratio of initialisation matching: the best
    /// distance must be below this share of the second best (ORB-SLAM's
    /// `ORBmatcher(0.9, true)` in `Tracking::MonocularInitialization`).
    pub init_ratio: f32,
    /// Nearest-neighbour ratio of triangulation matching. ORB-SLAM2's
    /// `SearchForTriangulation` keeps the closest under `TH_LOW` on the
    /// epipolar line with no ratio test; here the search runs over every
    /// unmatched keypoint (not per vocabulary node), and the initialisation
    /// ratio keeps its ambiguous matches out.
    pub triangulation_ratio: f32,
    /// Ratio test of the local-map search by projection, applied only when
    /// the two best candidates are on the same pyramid level (ORB-SLAM's
    /// `ORBmatcher(0.8)` in `Tracking::SearchLocalPoints`).
    pub local_map_ratio: f32,
}

impl Default for MatcherParams {
    fn default() -> Self {
        MatcherParams {
            th_high: 100,
            th_low: 50,
            histo_bins: 30,
            init_ratio: 0.9,
            triangulation_ratio: 0.9,
            local_map_ratio: 0.8,
        }
    }
}

/// Search radius factor (times the caller's radius and the level's scale)
/// for a point seen nearly head-on, `view_cos` above
/// [`FRONTAL_VIEW_COS`] (ORB-SLAM's `RadiusByViewingCos`: 2.5).
pub const FRONTAL_RADIUS_FACTOR: f64 = 2.5;

/// Search radius factor for a point seen obliquely (ORB-SLAM's
/// `RadiusByViewingCos`: 4.0).
pub const OBLIQUE_RADIUS_FACTOR: f64 = 4.0;

/// Cosine between the viewing ray and the point's mean viewing direction
/// above which the view counts as head-on (about 3.6 degrees; ORB-SLAM's
/// `RadiusByViewingCos`: 0.998).
pub const FRONTAL_VIEW_COS: f64 = 0.998;

/// Smallest cosine between a viewing ray and a point's mean viewing
/// direction for the point to be searched (60 degrees; ORB-SLAM's
/// `isInFrustum` and `Fuse`: 0.5).
pub const MIN_VIEW_COS: f64 = 0.5;

/// A point is searched from distances down to this share of its nearest
/// observed distance (ORB-SLAM's `MapPoint::GetMinDistanceInvariance`:
/// 0.8).
pub const MIN_DISTANCE_MARGIN: f64 = 0.8;

/// ... and up to this multiple of its farthest (ORB-SLAM's
/// `MapPoint::GetMaxDistanceInvariance`: 1.2).
pub const MAX_DISTANCE_MARGIN: f64 = 1.2;

/// Chi-square of 1 degree of freedom at 95 %: the largest squared distance
/// of a keypoint from its epipolar line, in units of its level's σ²
/// (ORB-SLAM's `CheckDistEpipolarLine`: 3.84).
pub const CHI2_1DOF_95: f64 = 3.84;

/// Chi-square of 2 degrees of freedom at 95 %: the largest squared
/// reprojection error of a fused point, in units of the level's σ²
/// (ORB-SLAM's `Fuse`: 5.99).
pub const CHI2_2DOF_95: f64 = 5.99;

/// A triangulation match is refused when the keypoint lies within
/// `√(this · scale factor)` pixels of the epipole (a point there is close
/// to the baseline: no parallax; ORB-SLAM's `SearchForTriangulation`:
/// 100 times the level's scale factor, in squared pixels).
pub const MIN_EPIPOLE_DISTANCE2_PER_SCALE: f64 = 100.0;

/// ORB-SLAM's rotation-consistency filter: the orientation differences of
/// the matches go in a histogram; matches outside the three largest bins
/// (bins under a tenth of the largest do not count) are dropped; the
/// histogram is [`RotationHistogram`]. `rot` holds
/// per candidate match `(match id, angle difference in degrees)`. Returns the
/// ids to drop.
pub fn rotation_outliers(rot: &[(usize, f32)], bins: usize) -> Vec<usize> {
    let mut h = RotationHistogram::new(bins);
    for &(id, d) in rot {
        h.add(d, 0.0, id);
    }
    h.rejected()
}

/// Matches between two frames for initialisation: every keypoint of the
/// first up to level `max_octave` is searched for within `window` pixels of
/// `prev` (its position in the frame matched last) in the second, among
/// keypoints one level up or down (only level 0 when `max_octave` is 0),
/// among the pairs `(i1, i2)` that `accept` lets through (all of them, or
/// for a search guided by a predicted motion those near the epipolar line
/// it gives). Returns, per keypoint of the first frame, the matched
/// keypoint of the second.
#[allow(clippy::too_many_arguments)]
pub fn search_for_initialization(
    kps1: &[KeyPoint],
    desc1: &[Descriptor],
    kps2: &[KeyPoint],
    desc2: &[Descriptor],
    grid2: &FeatureGrid,
    prev: &[Point2<f64>],
    window: f64,
    max_octave: i32,
    params: &MatcherParams,
    accept: impl Fn(usize, usize) -> bool,
) -> Vec<Option<usize>> {
    let mut m12: Vec<Option<usize>> = vec![None; kps1.len()];
    let mut m21_dist: Vec<(Option<usize>, u32)> = vec![(None, u32::MAX); kps2.len()];
    let mut cand = Vec::new();
    for (i1, k1) in kps1.iter().enumerate() {
        let oct = k1.octave as i32;
        if oct > max_octave {
            continue;
        }
        let p = prev
            .get(i1)
            .copied()
            .unwrap_or(Point2::new(k1.ux as f64, k1.uy as f64));
        let lo = (oct - 1).max(0);
        let hi = if max_octave == 0 { 0 } else { oct + 1 };
        grid2.features_in_area(kps2, p.x, p.y, window, lo, hi, &mut cand);
        let (mut best, mut best2, mut best_i) = (u32::MAX, u32::MAX, usize::MAX);
        for &i2 in &cand {
            if !accept(i1, i2) {
                continue;
            }
            let d = hamming(&desc1[i1], &desc2[i2]);
            if m21_dist[i2].1 <= d {
                continue;
            }
            if d < best {
                best2 = best;
                best = d;
                best_i = i2;
            } else if d < best2 {
                best2 = d;
            }
        }
        if best <= params.th_low && (best as f32) < params.init_ratio * best2 as f32 {
            if let Some(old) = m21_dist[best_i].0 {
                m12[old] = None;
            }
            m12[i1] = Some(best_i);
            m21_dist[best_i] = (Some(i1), best);
        }
    }
    // Rotation consistency.
    let rot: Vec<(usize, f32)> = m12
        .iter()
        .enumerate()
        .filter_map(|(i1, m)| m.map(|i2| (i1, kps1[i1].angle - kps2[i2].angle)))
        .collect();
    for i1 in rotation_outliers(&rot, params.histo_bins) {
        m12[i1] = None;
    }
    m12
}

/// A map point prepared for projection into one frame.
#[derive(Debug, Clone, Copy)]
pub struct Projected {
    /// The point.
    pub id: PointId,
    /// Undistorted pixel where it projects.
    pub uv: Point2<f64>,
    /// Predicted pyramid level.
    pub level: usize,
    /// Cosine between the viewing ray and the point's mean viewing direction.
    pub view_cos: f64,
}

/// Whether a point is in the frustum of a camera (in front, inside the
/// undistorted bounds, within its scale range, seen from within 60 degrees of
/// its mean viewing direction). On success, where and at which level.
pub fn project_point(
    map: &Map,
    id: PointId,
    cam_from_world: &Isometry3<f64>,
    center: &Vector3<f64>,
    bounds: &Bounds,
    min_view_cos: f64,
) -> Option<Projected> {
    let mp = map.point(id)?;
    let pc = cam_from_world * mp.position;
    if pc.z <= 0.0 {
        return None;
    }
    let cam = &map.camera;
    let u = cam.fx * pc.x / pc.z + cam.cx;
    let v = cam.fy * pc.y / pc.z + cam.cy;
    if !bounds.contains(u, v) {
        return None;
    }
    within_scale_and_view(map, id, mp, Point2::new(u, v), center, 1.0, min_view_cos)
}

/// The frustum test's tail, once the point is in front and inside the
/// bounds at `uv`: within its scale range (the distance from `center`
/// times `distance_factor`, which puts another camera's distance in the
/// map camera's terms; 1 for the map camera) and seen from within
/// `min_view_cos` of its mean viewing direction.
pub fn within_scale_and_view(
    map: &Map,
    id: PointId,
    mp: &MapPoint,
    uv: Point2<f64>,
    center: &Vector3<f64>,
    distance_factor: f64,
    min_view_cos: f64,
) -> Option<Projected> {
    let po = mp.position.coords - center;
    let dist = po.norm();
    let d_map = dist * distance_factor;
    if d_map < MIN_DISTANCE_MARGIN * mp.min_distance
        || d_map > MAX_DISTANCE_MARGIN * mp.max_distance
    {
        return None;
    }
    let view_cos = po.dot(&mp.normal) / dist;
    if view_cos < min_view_cos {
        return None;
    }
    Some(Projected {
        id,
        uv,
        level: map.scale.predict_level(mp.max_distance, d_map),
        view_cos,
    })
}

/// What a search by projection needs of the frame it searches in.
pub struct SearchTarget<'a> {
    /// Keypoints.
    pub keypoints: &'a [KeyPoint],
    /// Descriptors.
    pub descriptors: &'a [Descriptor],
    /// Grid index of the keypoints.
    pub grid: &'a FeatureGrid,
    /// Already matched slots (skipped when `Some` and observed by a keyframe).
    pub points: &'a [Option<PointId>],
}

/// Match projected local-map points into a frame (ORB-SLAM's
/// SearchByProjection for the local map): radius `th` times the level scale,
/// widened for oblique views; best match under `th_high` with a ratio test
/// when the two best are on the same level. Returns (keypoint, point) pairs.
pub fn search_local_points(
    target: &SearchTarget<'_>,
    projected: &[Projected],
    map: &Map,
    scale: &ScaleInfo,
    th: f64,
    params: &MatcherParams,
) -> Vec<(usize, PointId)> {
    let mut out = Vec::new();
    let mut taken = vec![false; target.keypoints.len()];
    let mut cand = Vec::new();
    for pr in projected {
        let Some(mp) = map.point(pr.id) else {
            continue;
        };
        let factor = if pr.view_cos > FRONTAL_VIEW_COS {
            FRONTAL_RADIUS_FACTOR
        } else {
            OBLIQUE_RADIUS_FACTOR
        };
        let r = factor * th * scale.scale_factors[pr.level];
        let lvl = pr.level as i32;
        target.grid.features_in_area(
            target.keypoints,
            pr.uv.x,
            pr.uv.y,
            r,
            lvl - 1,
            lvl,
            &mut cand,
        );
        let (mut best, mut best2) = (u32::MAX, u32::MAX);
        let (mut best_lvl, mut best_lvl2) = (-1i32, -1i32);
        let mut best_i = usize::MAX;
        for &i in &cand {
            if taken[i] {
                continue;
            }
            if let Some(p) = target.points[i]
                && map.point(p).is_some_and(|m| !m.observations.is_empty())
            {
                continue;
            }
            let d = hamming(&mp.descriptor, &target.descriptors[i]);
            let o = target.keypoints[i].octave as i32;
            if d < best {
                best2 = best;
                best_lvl2 = best_lvl;
                best = d;
                best_lvl = o;
                best_i = i;
            } else if d < best2 {
                best_lvl2 = o;
                best2 = d;
            }
        }
        if best <= params.th_high {
            if best_lvl == best_lvl2 && best as f32 > params.local_map_ratio * best2 as f32 {
                continue;
            }
            taken[best_i] = true;
            out.push((best_i, pr.id));
        }
    }
    out
}

/// Match the points of the previous frame into the current one by
/// projection with the predicted pose (ORB-SLAM's motion-model search):
/// radius `th` times the keypoint's level scale, levels around the previous
/// keypoint's, rotation-consistency check. `last` holds the previous frame's
/// (keypoint, point) pairs. Returns (keypoint of current, point) pairs.
#[allow(clippy::too_many_arguments)]
pub fn search_last_frame(
    target: &SearchTarget<'_>,
    last_keypoints: &[KeyPoint],
    last: &[(usize, PointId)],
    map: &Map,
    cam_from_world: &Isometry3<f64>,
    bounds: &Bounds,
    th: f64,
    params: &MatcherParams,
) -> Vec<(usize, PointId)> {
    let cam = &map.camera;
    let mut out: Vec<(usize, PointId)> = Vec::new();
    let mut taken = vec![false; target.keypoints.len()];
    let mut rot = Vec::new();
    let mut cand = Vec::new();
    let n_levels = map.scale.n_levels() as i32;
    for &(li, pid) in last {
        let Some(mp) = map.point(pid) else {
            continue;
        };
        let pc = cam_from_world * mp.position;
        if pc.z <= 0.0 {
            continue;
        }
        let u = cam.fx * pc.x / pc.z + cam.cx;
        let v = cam.fy * pc.y / pc.z + cam.cy;
        if !bounds.contains(u, v) {
            continue;
        }
        let Some(lk) = last_keypoints.get(li) else {
            continue;
        };
        let lo = lk.octave as i32;
        let r = th * map.scale.scale_factors[lk.octave as usize];
        target.grid.features_in_area(
            target.keypoints,
            u,
            v,
            r,
            (lo - 1).max(0),
            (lo + 1).min(n_levels - 1),
            &mut cand,
        );
        let (mut best, mut best_i) = (u32::MAX, usize::MAX);
        for &i in &cand {
            if taken[i] {
                continue;
            }
            let d = hamming(&mp.descriptor, &target.descriptors[i]);
            if d < best {
                best = d;
                best_i = i;
            }
        }
        if best <= params.th_high {
            taken[best_i] = true;
            rot.push((out.len(), lk.angle - target.keypoints[best_i].angle));
            out.push((best_i, pid));
        }
    }
    let drop = rotation_outliers(&rot, params.histo_bins);
    if !drop.is_empty() {
        let mut keep = vec![true; out.len()];
        for d in drop {
            keep[d] = false;
        }
        let mut k = 0;
        out.retain(|_| {
            let r = keep[k];
            k += 1;
            r
        });
    }
    out
}

/// The fundamental matrix from keyframe 2 to keyframe 1 (x1ᵀ F12 x2 = 0 in
/// undistorted pixels).
pub fn fundamental_12(
    cam: &Camera,
    cam1_from_world: &Isometry3<f64>,
    cam2_from_world: &Isometry3<f64>,
) -> Matrix3<f64> {
    let c1_from_c2 = cam1_from_world * cam2_from_world.inverse();
    let r = c1_from_c2.rotation.to_rotation_matrix().into_inner();
    let t = c1_from_c2.translation.vector;
    let tx = Matrix3::new(0.0, -t.z, t.y, t.z, 0.0, -t.x, -t.y, t.x, 0.0);
    let k_inv = cam.k_inv();
    k_inv.transpose() * tx * r * k_inv
}

/// Matches for triangulation between two keyframes: unmatched keypoints of
/// the first against unmatched keypoints of the second, under `th_low`,
/// with a ratio test, on the epipolar line (within the chi-square bound for
/// the level) and away from the epipole; rotation-consistency check.
/// Returns (index in kf1, index in kf2).
#[allow(clippy::too_many_arguments)]
pub fn search_for_triangulation(
    map: &Map,
    kf1: KeyFrameId,
    kf2: KeyFrameId,
    f12: &Matrix3<f64>,
    params: &MatcherParams,
) -> Vec<(usize, usize)> {
    let (Some(k1), Some(k2)) = (map.keyframe(kf1), map.keyframe(kf2)) else {
        return Vec::new();
    };
    let cam = &map.camera;
    // Epipole of camera 1 in image 2.
    let c1_in_2 = k2.cam_from_world * Point3::from(k1.center());
    let (ex, ey) = if c1_in_2.z.abs() > 1e-12 {
        (
            cam.fx * c1_in_2.x / c1_in_2.z + cam.cx,
            cam.fy * c1_in_2.y / c1_in_2.z + cam.cy,
        )
    } else {
        (f64::INFINITY, f64::INFINITY)
    };
    let free2: Vec<usize> = (0..k2.keypoints.len())
        .filter(|&i| k2.points[i].is_none())
        .collect();
    let mut matched2 = vec![false; k2.keypoints.len()];
    let mut out = Vec::new();
    let mut rot = Vec::new();
    for i1 in 0..k1.keypoints.len() {
        if k1.points[i1].is_some() {
            continue;
        }
        let kp1 = &k1.keypoints[i1];
        let d1 = &k1.descriptors[i1];
        // Epipolar line in image 2: l2 = F12ᵀ x1.
        let x1 = Vector3::new(kp1.ux as f64, kp1.uy as f64, 1.0);
        let l = f12.transpose() * x1;
        let den = l.x * l.x + l.y * l.y;
        if den < 1e-18 {
            continue;
        }
        let (mut best, mut best2, mut best_i) = (params.th_low + 1, u32::MAX, usize::MAX);
        for &i2 in &free2 {
            if matched2[i2] {
                continue;
            }
            let d = hamming(d1, &k2.descriptors[i2]);
            if d > params.th_low || d >= best2 {
                continue;
            }
            let kp2 = &k2.keypoints[i2];
            let (u2, v2) = (kp2.ux as f64, kp2.uy as f64);
            let num = l.x * u2 + l.y * v2 + l.z;
            let dist2 = num * num / den;
            let sigma2 = 1.0 / map.scale.inv_level_sigma2[kp2.octave as usize];
            if dist2 >= CHI2_1DOF_95 * sigma2 {
                continue;
            }
            let (dx, dy) = (ex - u2, ey - v2);
            if dx * dx + dy * dy
                < MIN_EPIPOLE_DISTANCE2_PER_SCALE * map.scale.scale_factors[kp2.octave as usize]
            {
                continue;
            }
            if d < best {
                best2 = best;
                best = d;
                best_i = i2;
            } else {
                best2 = d;
            }
        }
        if best_i != usize::MAX && (best as f32) < params.triangulation_ratio * best2 as f32 {
            matched2[best_i] = true;
            rot.push((out.len(), kp1.angle - k2.keypoints[best_i].angle));
            out.push((i1, best_i));
        }
    }
    let drop = rotation_outliers(&rot, params.histo_bins);
    if !drop.is_empty() {
        let mut keep = vec![true; out.len()];
        for d in drop {
            keep[d] = false;
        }
        let mut k = 0;
        out.retain(|_| {
            let r = keep[k];
            k += 1;
            r
        });
    }
    out
}

/// Project `points` into keyframe `kf` and fuse each with the keypoint it
/// matches: a keypoint already holding another point is merged with it (the
/// one with more observations stays), a free keypoint gains the observation.
/// Returns the number of fusions.
pub fn fuse(
    map: &mut Map,
    kf: KeyFrameId,
    points: &[PointId],
    th: f64,
    bounds: &Bounds,
    params: &MatcherParams,
) -> usize {
    let Some(k) = map.keyframe(kf) else {
        return 0;
    };
    let cam_from_world = k.cam_from_world;
    let center = k.center();
    let mut actions: Vec<(PointId, usize)> = Vec::new();
    let mut cand = Vec::new();
    for &pid in points {
        let Some(mp) = map.point(pid) else {
            continue;
        };
        if mp.index_in(kf).is_some() {
            continue;
        }
        let Some(pr) = project_point(map, pid, &cam_from_world, &center, bounds, MIN_VIEW_COS)
        else {
            continue;
        };
        let r = th * map.scale.scale_factors[pr.level];
        k.grid
            .features_in_area(&k.keypoints, pr.uv.x, pr.uv.y, r, 0, i32::MAX, &mut cand);
        let (mut best, mut best_i) = (u32::MAX, usize::MAX);
        for &i in &cand {
            let kp = &k.keypoints[i];
            let lvl = kp.octave as usize;
            if lvl + 1 < pr.level || lvl > pr.level {
                continue;
            }
            let (ex, ey) = (pr.uv.x - kp.ux as f64, pr.uv.y - kp.uy as f64);
            if (ex * ex + ey * ey) * map.scale.inv_level_sigma2[lvl] > CHI2_2DOF_95 {
                continue;
            }
            let d = hamming(&mp.descriptor, &k.descriptors[i]);
            if d < best {
                best = d;
                best_i = i;
            }
        }
        if best <= params.th_low {
            actions.push((pid, best_i));
        }
    }
    let mut n = 0;
    for (pid, i) in actions {
        if map.point(pid).is_none() {
            continue;
        }
        let existing = map
            .keyframe(kf)
            .and_then(|k| k.points.get(i).copied().flatten());
        match existing {
            Some(other) if other != pid => {
                let (n_other, n_this) = (
                    map.point(other).map_or(0, |m| m.observations.len()),
                    map.point(pid).map_or(0, |m| m.observations.len()),
                );
                if n_other >= n_this {
                    map.replace_point(pid, other);
                } else {
                    map.replace_point(other, pid);
                }
                n += 1;
            }
            Some(_) => {}
            None => {
                if map.add_observation(pid, kf, i as u32) {
                    n += 1;
                }
            }
        }
    }
    n
}

/// ORB-SLAM's SearchByBoW: match the map points of keyframe `kf` to a
/// frame's keypoints, comparing only features under the same vocabulary
/// node (`kf_features` and `features` are the two direct indices): the best
/// under `th_low` with the ratio test, one match per frame keypoint (the
/// closest wins), then the rotation-consistency filter. Returns (frame
/// keypoint, point) pairs.
#[allow(clippy::too_many_arguments)]
pub fn search_by_bow(
    map: &Map,
    kf: KeyFrameId,
    kf_features: &FeatureVector,
    descriptors: &[Descriptor],
    keypoints: &[KeyPoint],
    features: &FeatureVector,
    params: &MatcherParams,
    ratio: f32,
) -> Vec<(usize, PointId)> {
    let Some(k) = map.keyframe(kf) else {
        return Vec::new();
    };
    // Per frame keypoint: (distance, kf keypoint) of its current match.
    let mut best_for: Vec<Option<(u32, usize)>> = vec![None; keypoints.len()];
    for (_, kf_idx, frame_idx) in kf_features.common_nodes(features) {
        for ki in kf_idx.iter() {
            let ki = ki as usize;
            let Some(Some(pid)) = k.points.get(ki) else {
                continue;
            };
            if map.point(*pid).is_none() {
                continue;
            }
            let Some(d1) = k.descriptors.get(ki) else {
                continue;
            };
            let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
            for fi in frame_idx.iter() {
                let fi = fi as usize;
                let Some(d2) = descriptors.get(fi) else {
                    continue;
                };
                let d = hamming(d1, d2);
                if d < b1 {
                    b2 = b1;
                    b1 = d;
                    bi = fi;
                } else if d < b2 {
                    b2 = d;
                }
            }
            if bi == usize::MAX || b1 > params.th_low || (b1 as f32) >= ratio * b2 as f32 {
                continue;
            }
            if best_for[bi].is_none_or(|(d, _)| b1 < d) {
                best_for[bi] = Some((b1, ki));
            }
        }
    }
    let found: Vec<(usize, usize)> = best_for
        .iter()
        .enumerate()
        .filter_map(|(fi, m)| m.map(|(_, ki)| (fi, ki)))
        .collect();
    let rot: Vec<(usize, f32)> = found
        .iter()
        .enumerate()
        .map(|(n, &(fi, ki))| (n, k.keypoints[ki].angle - keypoints[fi].angle))
        .collect();
    let drop: std::collections::HashSet<usize> = rotation_outliers(&rot, params.histo_bins)
        .into_iter()
        .collect();
    found
        .into_iter()
        .enumerate()
        .filter(|(n, _)| !drop.contains(n))
        .filter_map(|(_, (fi, ki))| k.points[ki].map(|p| (fi, p)))
        .collect()
}

/// Match the map points of keyframe `kf` to a frame's keypoints by
/// descriptor, by brute force (the fallback of [`search_by_bow`] when the
/// keyframe is not indexed yet): best under `th_low` with a ratio test,
/// one match per frame keypoint, rotation check. Returns (frame keypoint,
/// point).
pub fn search_keyframe_by_descriptor(
    map: &Map,
    kf: KeyFrameId,
    keypoints: &[KeyPoint],
    descriptors: &[Descriptor],
    params: &MatcherParams,
    ratio: f32,
) -> Vec<(usize, PointId)> {
    let Some(k) = map.keyframe(kf) else {
        return Vec::new();
    };
    let mut best_for: Vec<(u32, usize)> = vec![(u32::MAX, usize::MAX); keypoints.len()];
    let mut out: Vec<(usize, PointId, f32)> = Vec::new();
    for (ki, p) in k.points.iter().enumerate() {
        let Some(pid) = p else { continue };
        if map.point(*pid).is_none() {
            continue;
        }
        let d1 = &k.descriptors[ki];
        let (mut b1, mut b2, mut bi) = (u32::MAX, u32::MAX, usize::MAX);
        for (fi, d2) in descriptors.iter().enumerate() {
            let d = hamming(d1, d2);
            if d < b1 {
                b2 = b1;
                b1 = d;
                bi = fi;
            } else if d < b2 {
                b2 = d;
            }
        }
        if b1 <= params.th_low && (b1 as f32) < ratio * b2 as f32 && b1 < best_for[bi].0 {
            best_for[bi] = (b1, out.len());
            out.push((bi, *pid, k.keypoints[ki].angle - keypoints[bi].angle));
        }
    }
    // Keep, per frame keypoint, only its best match.
    let keep: Vec<bool> = out
        .iter()
        .enumerate()
        .map(|(n, m)| best_for[m.0].1 == n)
        .collect();
    let filtered: Vec<(usize, PointId, f32)> = out
        .into_iter()
        .zip(keep)
        .filter(|(_, k)| *k)
        .map(|(m, _)| m)
        .collect();
    let rot: Vec<(usize, f32)> = filtered.iter().enumerate().map(|(n, m)| (n, m.2)).collect();
    let drop: std::collections::HashSet<usize> = rotation_outliers(&rot, params.histo_bins)
        .into_iter()
        .collect();
    filtered
        .into_iter()
        .enumerate()
        .filter(|(n, _)| !drop.contains(n))
        .map(|(_, m)| (m.0, m.1))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rotation_filter_keeps_the_three_main_bins() {
        let mut rot = Vec::new();
        for i in 0..50 {
            rot.push((i, 10.0));
        }
        for i in 50..70 {
            rot.push((i, 22.0));
        }
        for i in 70..75 {
            rot.push((i, 200.0));
        }
        rot.push((75, 300.0));
        let drop = rotation_outliers(&rot, 30);
        // Bins: 10deg (50), 22deg (20), 200deg (5), 300deg (1 < 10% of 50).
        assert_eq!(drop, vec![75]);
    }
}
