//! The bundle-adjustment glue between the map and [`crate::optimize`]:
//! gather a set of keyframes, the points they see and the other keyframes
//! observing those points into a [`BaProblem`], and write the solution
//! back (poses, points, outlier observations erased). Initialisation,
//! local mapping and the final optimisation of a run all go through it.

use std::collections::HashMap;

use nalgebra::Point2;

use crate::lie::renormalized;
use crate::optimize::{self, BaParams, BaPose, BaProblem, Intrinsics, Observation};

use super::map::{KeyFrameId, Map, PointId};

/// Bundle adjustment over `kfs` (poses free unless listed in `fixed`) and
/// all points they see; keyframes outside `kfs` that see those points join
/// as fixed. Outlier observations are erased. Returns the report.
pub fn run_bundle_adjustment(
    map: &mut Map,
    kfs: &[KeyFrameId],
    fixed: &[KeyFrameId],
    params: &BaParams,
) -> Option<optimize::BaReport> {
    run_bundle_adjustment_with(map, kfs, fixed, params, |_, _| Vec::new())
}

/// [`run_bundle_adjustment`] with position priors on its keyframes, chosen
/// by `priors` once the problem is built (telemetry priors:
/// [`super::priors::Priors::priors_for`]).
pub fn run_bundle_adjustment_with(
    map: &mut Map,
    kfs: &[KeyFrameId],
    fixed: &[KeyFrameId],
    params: &BaParams,
    priors: impl FnOnce(&Map, &BaSetup) -> Vec<optimize::PositionPrior>,
) -> Option<optimize::BaReport> {
    let mut setup = build_ba_problem(map, kfs, fixed)?;
    setup.problem.priors = priors(map, &setup);
    let report = optimize::local_bundle_adjustment(&mut setup.problem, params).ok()?;
    apply_ba_result(map, &setup, &report.outliers);
    Some(report)
}

/// A bundle adjustment over part of the map: the problem and which
/// keyframe and map point each of its poses and points stands for.
#[derive(Debug, Clone)]
pub struct BaSetup {
    /// The problem (poses are `cam_from_world`).
    pub problem: BaProblem,
    /// The keyframe of each pose.
    pub keyframes: Vec<KeyFrameId>,
    /// The map point of each point.
    pub points: Vec<PointId>,
}

/// Build a bundle adjustment over `kfs` (free unless in `fixed`), the
/// points they see, and every other keyframe seeing those points (fixed).
pub fn build_ba_problem(map: &Map, kfs: &[KeyFrameId], fixed: &[KeyFrameId]) -> Option<BaSetup> {
    let mut pose_index: HashMap<KeyFrameId, usize> = HashMap::new();
    let mut poses = Vec::new();
    let mut pose_ids = Vec::new();
    for &kf in kfs {
        let Some(k) = map.keyframe(kf) else { continue };
        if pose_index.contains_key(&kf) {
            continue;
        }
        pose_index.insert(kf, poses.len());
        poses.push(BaPose {
            cam_from_world: k.cam_from_world,
            fixed: fixed.contains(&kf),
        });
        pose_ids.push(kf);
    }
    let mut point_index: HashMap<PointId, usize> = HashMap::new();
    let mut points = Vec::new();
    let mut point_ids = Vec::new();
    for &kf in &pose_ids.clone() {
        let Some(k) = map.keyframe(kf) else { continue };
        for pid in k.points.iter().flatten() {
            if point_index.contains_key(pid) {
                continue;
            }
            let Some(mp) = map.point(*pid) else { continue };
            point_index.insert(*pid, points.len());
            points.push(mp.position);
            point_ids.push(*pid);
        }
    }
    let mut observations = Vec::new();
    for (pi, pid) in point_ids.iter().enumerate() {
        let Some(mp) = map.point(*pid) else { continue };
        for (kf, idx) in &mp.observations {
            let Some(k) = map.keyframe(*kf) else { continue };
            let pose_index_of_kf = match pose_index.get(kf) {
                Some(&p) => p,
                None => {
                    pose_index.insert(*kf, poses.len());
                    poses.push(BaPose {
                        cam_from_world: k.cam_from_world,
                        fixed: true,
                    });
                    pose_ids.push(*kf);
                    poses.len() - 1
                }
            };
            let Some(kp) = k.keypoints.get(*idx as usize) else {
                continue;
            };
            observations.push(Observation {
                pose: pose_index_of_kf,
                point: pi,
                uv: Point2::new(kp.ux as f64, kp.uy as f64),
                inv_sigma2: map.scale.inv_level_sigma2[kp.octave as usize],
            });
        }
    }
    if observations.is_empty() || !poses.iter().any(|p| !p.fixed) && points.is_empty() {
        return None;
    }
    let cam = &map.camera;
    Some(BaSetup {
        problem: BaProblem {
            poses,
            points,
            observations,
            intrinsics: Intrinsics {
                fx: cam.fx,
                fy: cam.fy,
                cx: cam.cx,
                cy: cam.cy,
            },
            priors: Vec::new(),
        },
        keyframes: pose_ids,
        points: point_ids,
    })
}

/// The position error of the keyframes `kfs` that the map's own bundle
/// adjustment implies ([`optimize::aligned_centre_covariances`]: its
/// information at the current solution, the map's reprojection noise
/// [`Map::reprojection_noise_px`], after a similarity alignment of their
/// centres, as an error against the truth is measured): the RMS over the
/// keyframes of their centres' error, map units (comparable with an ATE's
/// RMS over the keyframes). Keyframes outside `kfs` seeing their points
/// hold still. None for fewer than three keyframes, a map without a noise
/// estimate, or a degenerate problem.
pub fn keyframe_position_rms(map: &Map, kfs: &[KeyFrameId]) -> Option<f64> {
    let noise = map.reprojection_noise_px()?;
    let mut setup = build_ba_problem(map, kfs, &[])?;
    let covs = optimize::aligned_centre_covariances(&mut setup.problem, noise)?;
    let mean_trace = covs.iter().map(|c| c.trace()).sum::<f64>() / covs.len().max(1) as f64;
    Some(mean_trace.max(0.0).sqrt())
}

/// Write a solved bundle adjustment back: free poses, points, and erase the
/// outlier observations.
pub fn apply_ba_result(map: &mut Map, setup: &BaSetup, outliers: &[bool]) {
    let BaSetup {
        problem,
        keyframes: pose_ids,
        points: point_ids,
    } = setup;
    for (i, kf) in pose_ids.iter().enumerate() {
        if problem.poses[i].fixed {
            continue;
        }
        if let Some(k) = map.keyframe_mut(*kf) {
            k.cam_from_world = renormalized(problem.poses[i].cam_from_world);
        }
    }
    for (i, pid) in point_ids.iter().enumerate() {
        if let Some(mp) = map.point_mut(*pid) {
            mp.position = problem.points[i];
        }
    }
    for (o, obs) in problem.observations.iter().enumerate() {
        if outliers.get(o).copied().unwrap_or(false) {
            map.erase_observation(point_ids[obs.point], pose_ids[obs.pose]);
        }
    }
    for pid in point_ids {
        map.update_point_normal_and_depth(*pid);
    }
}
