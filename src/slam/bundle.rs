//! The bundle-adjustment glue between the map and [`crate::optimize`]:
//! gather a set of keyframes, the points they see and the other keyframes
//! observing those points into a [`BaProblem`], and write the solution
//! back (poses, points, outlier observations erased). Initialisation,
//! local mapping and the final optimisation of a run all go through it.
//! Under a rolling shutter each keyframe's motion over its readout follows
//! the keyframes just before and after it ([`attach_shutters`]).

use std::collections::HashMap;

use nalgebra::{Point2, Vector3};

use crate::lie::renormalized;
use crate::optimize::shutter::PoseShutter;
use crate::optimize::{self, BaParams, BaPose, BaProblem, Intrinsics, Observation, RowMotion};

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
            shutter: None,
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
                        shutter: None,
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
    let mut setup = BaSetup {
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
    };
    attach_shutters(map, &mut setup, cam.readout_s);
    Some(setup)
}

/// Keyframes further apart in time than this do not give each other's
/// velocity (a drone's motion changes within a second or two).
const MAX_NEIGHBOUR_GAP_S: f64 = 1.5;

/// The keyframes a bundle adjustment of the whole map `kfs` holds fixed as
/// the gauge without priors: each map's first keyframe (maps never merged
/// are separate problems in one), else the first of `kfs`.
pub fn whole_map_gauge(map: &Map, kfs: &[KeyFrameId]) -> Vec<KeyFrameId> {
    let roots: Vec<KeyFrameId> = map
        .maps()
        .iter()
        .filter_map(|(id, _)| map.root_of(*id))
        .collect();
    if roots.is_empty() {
        kfs.first().copied().into_iter().collect()
    } else {
        roots
    }
}

/// A keyframe and its time, seconds.
type TimedKeyFrame = (f64, KeyFrameId);

/// The keyframes taken just before and just after `kf` (each with its
/// time), among its covisible and spanning-tree neighbours within
/// [`MAX_NEIGHBOUR_GAP_S`].
fn time_neighbours(map: &Map, kf: KeyFrameId) -> (Option<TimedKeyFrame>, Option<TimedKeyFrame>) {
    let Some(k) = map.keyframe(kf) else {
        return (None, None);
    };
    let t = k.timestamp;
    let mut before: Option<TimedKeyFrame> = None;
    let mut after: Option<TimedKeyFrame> = None;
    let neighbours = k
        .covisible
        .iter()
        .map(|c| c.0)
        .chain(k.parent)
        .chain(k.children.iter().copied());
    for n in neighbours {
        let Some(nk) = map.keyframe(n) else { continue };
        let dt = nk.timestamp - t;
        if !dt.is_finite() || dt == 0.0 || dt.abs() > MAX_NEIGHBOUR_GAP_S {
            continue;
        }
        let slot = if dt < 0.0 { &mut before } else { &mut after };
        if slot.is_none_or(|(best, _)| dt.abs() < (best - t).abs()) {
            *slot = Some((nk.timestamp, n));
        }
    }
    (before, after)
}

/// Gives every pose of `setup` a rolling shutter of `readout_s` (none when
/// it is 0): its motion over the readout taken between the keyframes just
/// before and just after it (a central difference; one-sided at the newest
/// or oldest; [`crate::optimize::shutter::PoseShutter::between`]), so it
/// follows the poses as the adjustment moves them. A neighbour not in the
/// problem joins it, held fixed. A keyframe with no neighbour in time gets
/// no motion.
pub fn attach_shutters(map: &Map, setup: &mut BaSetup, readout_s: f64) {
    let mut index: HashMap<KeyFrameId, usize> = setup
        .keyframes
        .iter()
        .enumerate()
        .map(|(i, k)| (*k, i))
        .collect();
    let n = setup.keyframes.len();
    for i in 0..n {
        let kf = setup.keyframes[i];
        let Some(motion) = RowMotion::new(
            readout_s,
            map.camera.height,
            Vector3::zeros(),
            Vector3::zeros(),
        ) else {
            setup.problem.poses[i].shutter = None;
            continue;
        };
        let Some(t) = map.keyframe(kf).map(|k| k.timestamp) else {
            continue;
        };
        let (before, after) = time_neighbours(map, kf);
        let mut place = |found: Option<TimedKeyFrame>| -> (f64, usize) {
            let Some((tn, id)) = found else { return (t, i) };
            let Some(k) = map.keyframe(id) else {
                return (t, i);
            };
            let at = *index.entry(id).or_insert_with(|| {
                setup.problem.poses.push(BaPose {
                    cam_from_world: k.cam_from_world,
                    fixed: true,
                    shutter: None,
                });
                setup.keyframes.push(id);
                setup.problem.poses.len() - 1
            });
            (tn, at)
        };
        let (t0, a) = place(before);
        let (t1, b) = place(after);
        setup.problem.poses[i].shutter = (t1 > t0).then_some(PoseShutter {
            motion,
            between: Some((a, b, t1 - t0)),
        });
    }
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
