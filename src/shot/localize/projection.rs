//! Search by projection: the local map of a shot (the keyframes that see
//! its matched points), its points projected into the shot camera (with the
//! pyramid level predicted from the distance) and matched to the shot's
//! keypoints; and the distance to the nearest scene content in its view.

use std::collections::HashSet;

use nalgebra::{Isometry3, Point2};

use super::params::LocalizeParams;
use crate::camera::Camera;
use crate::features;
use crate::matching::{Bounds, FeatureGrid};
use crate::optimize::{Intrinsics, IntrinsicsCorrection};
use crate::slam::matcher::{Projected, SearchTarget, search_local_points, within_scale_and_view};
use crate::slam::{KeyFrameId, Map, PointId};

/// The 10 % quantile of the depths of all map points in the shot's view
/// from `cam_from_world` (in front, inside the image; occlusion ignored: a
/// hidden point lies behind nearer content, so the quantile never
/// overstates the distance to the nearest content); None with fewer than
/// 10 such points.
pub(super) fn frustum_near_depth(
    map: &Map,
    view: &ShotView<'_>,
    cam_from_world: &Isometry3<f64>,
) -> Option<f64> {
    let depths: Vec<f64> = map
        .points()
        .filter_map(|p| {
            let pc = cam_from_world * p.position;
            if pc.z <= 0.0 {
                return None;
            }
            let u = view.cam.fx * pc.x / pc.z + view.cam.cx;
            let v = view.cam.fy * pc.y / pc.z + view.cam.cy;
            view.bounds.contains(u, v).then_some(pc.z)
        })
        .collect();
    if depths.len() < 10 {
        return None;
    }
    crate::stats::quantile(&depths, 0.1)
}

/// The shot's camera as the projection of map points into it needs it.
#[derive(Clone, Copy)]
pub(super) struct ShotView<'c> {
    pub(super) cam: &'c Camera,
    pub(super) bounds: Bounds,
    pub(super) distance_factor: f64,
    /// The estimated camera's correction of `cam` (identity but for a
    /// photo whose focal length was weighed, [`rematch_with_estimated_camera`]).
    pub(super) correction: IntrinsicsCorrection,
}

/// Whether map point `id` is in the shot camera's frustum (in front, inside
/// the undistorted bounds, within its scale range, seen from within
/// `min_view_cos` of its mean viewing direction); where and at which level.
fn project_into_shot(
    map: &Map,
    view: &ShotView<'_>,
    id: PointId,
    cam_from_world: &Isometry3<f64>,
    center: &nalgebra::Vector3<f64>,
    min_view_cos: f64,
) -> Option<Projected> {
    let mp = map.point(id)?;
    let pc = cam_from_world * mp.position;
    if pc.z <= 0.0 {
        return None;
    }
    let (u, v) = if view.correction == IntrinsicsCorrection::default() {
        (
            view.cam.fx * pc.x / pc.z + view.cam.cx,
            view.cam.fy * pc.y / pc.z + view.cam.cy,
        )
    } else {
        let intr = Intrinsics {
            fx: view.cam.fx,
            fy: view.cam.fy,
            cx: view.cam.cx,
            cy: view.cam.cy,
        };
        let uv = view.correction.project(&intr, &pc.coords)?;
        (uv.x, uv.y)
    };
    if !view.bounds.contains(u, v) {
        return None;
    }
    within_scale_and_view(
        map,
        id,
        mp,
        Point2::new(u, v),
        center,
        view.distance_factor,
        min_view_cos,
    )
}

/// The local map of a shot: the points of the keyframes that observe the
/// points matched so far (most shared points first, at most `max_kfs`),
/// with the candidate keyframe and its best covisible ones always in.
fn local_points(
    map: &Map,
    kf_id: KeyFrameId,
    slots: &[Option<PointId>],
    params: &LocalizeParams,
) -> Vec<PointId> {
    let mut counts: std::collections::HashMap<KeyFrameId, usize> = std::collections::HashMap::new();
    for p in slots.iter().flatten() {
        if let Some(mp) = map.point(*p) {
            for (k, _) in &mp.observations {
                *counts.entry(*k).or_default() += 1;
            }
        }
    }
    let mut kfs: Vec<(KeyFrameId, usize)> = counts.into_iter().collect();
    kfs.sort_by(|a, b| b.1.cmp(&a.1).then(a.0.cmp(&b.0)));
    let mut chosen: Vec<KeyFrameId> = Vec::new();
    let mut seen_kf: HashSet<KeyFrameId> = HashSet::new();
    let candidate = map.keyframe(kf_id);
    let base = std::iter::once(kf_id).chain(
        candidate
            .into_iter()
            .flat_map(|k| k.best_covisible(params.covisible)),
    );
    for id in base.chain(kfs.iter().map(|x| x.0)) {
        if chosen.len() >= params.covisible + 1 + params.local_keyframes {
            break;
        }
        if seen_kf.insert(id) {
            chosen.push(id);
        }
    }
    let mut local: Vec<PointId> = Vec::new();
    let mut seen: HashSet<PointId> = HashSet::new();
    for id in chosen {
        if let Some(k) = map.keyframe(id) {
            for p in k.points.iter().flatten() {
                if seen.insert(*p) {
                    local.push(*p);
                }
            }
        }
    }
    local
}

/// One search by projection: the points of the keyframe's local map not
/// yet in `slots`, projected into the photo through `cam_from_world` and
/// `view`'s camera, matched to the photo's keypoints within `radius` px.
/// Returns (keypoint, point) pairs for keypoints still free.
#[allow(clippy::too_many_arguments)]
pub(super) fn search_by_projection(
    map: &Map,
    kf_id: KeyFrameId,
    view: &ShotView<'_>,
    cam_from_world: &Isometry3<f64>,
    slots: &[Option<PointId>],
    (feats, grid): (&features::Features, &FeatureGrid),
    radius: f64,
    params: &LocalizeParams,
) -> Vec<(usize, PointId)> {
    let local = local_points(map, kf_id, slots, params);
    let used: HashSet<PointId> = slots.iter().flatten().copied().collect();
    let center = cam_from_world.inverse().translation.vector;
    let projected: Vec<_> = local
        .iter()
        .filter(|p| !used.contains(p))
        .filter_map(|p| {
            project_into_shot(map, view, *p, cam_from_world, &center, params.min_view_cos)
        })
        .collect();
    let target = SearchTarget {
        keypoints: &feats.keypoints,
        descriptors: &feats.descriptors,
        grid,
        points: slots,
    };
    search_local_points(
        &target,
        &projected,
        map,
        &map.scale,
        radius,
        &params.matcher,
    )
}
