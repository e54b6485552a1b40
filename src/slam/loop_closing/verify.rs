//! Verification, steps 3 and 4 of the module doc: for a consistent
//! candidate, BoW-guided matches between the two keyframes' points, a
//! Sim(3) by RANSAC, a guided search through it, the refinement with the
//! scale held and the scale from the inliers' 3D points
//! ([`super::robust_scale_fit`]), the candidate's neighbourhood projected
//! through the corrected pose, and (for a loop) the drift bounds. The
//! result is a [`LoopMatch`] for the correction or the merge.

use std::collections::HashSet;

use nalgebra::Point2;

use crate::features::{Descriptor, hamming};
use crate::geometry::sim3_ransac;
use crate::lie::Sim3;
use crate::matching::Bounds;
use crate::optimize::{Intrinsics, Sim3Match, Sim3Params, optimize_sim3};
use crate::slam::map::{KeyFrame, KeyFrameId, Map, PointId};
use crate::slam::matcher;

use super::log::{LoopRefusal, LoopReject};
use super::params::LoopParams;
use super::sim3::{robust_scale_fit, sim3_to_isometry};

/// A verified loop before correction.
pub(super) struct LoopMatch {
    pub(super) loop_kf: KeyFrameId,
    /// Corrected pose of the current keyframe: world → camera, a Sim(3).
    pub(super) s_cw: Sim3,
    /// Per keypoint of the current keyframe: the loop-side point matched.
    pub(super) matched: Vec<Option<PointId>>,
    /// Points of the loop keyframe and its neighbours.
    pub(super) loop_points: Vec<PointId>,
    pub(super) inliers: usize,
    pub(super) projection_matches: usize,
}

/// Steps 3 and 4: the first candidate whose Sim(3) holds; the others
/// refused before it go to `refusals`.
pub(super) fn verify(
    p: &LoopParams,
    bounds: &Bounds,
    map: &Map,
    kf: KeyFrameId,
    candidates: &[KeyFrameId],
    refusals: &mut Vec<LoopRefusal>,
) -> Option<LoopMatch> {
    for &c in candidates {
        match verify_one(p, bounds, map, kf, c, true) {
            Ok(m) => return Some(m),
            Err(why) => {
                tracing::debug!(
                    current = kf.0,
                    candidate = c.0,
                    ?why,
                    "loop candidate refused"
                );
                let t = |id| map.keyframe(id).map_or(f64::NAN, |k| k.timestamp);
                refusals.push(LoopRefusal {
                    current: kf,
                    candidate: c,
                    current_t: t(kf),
                    candidate_t: t(c),
                    reason: why,
                });
            }
        }
    }
    None
}

/// Steps 3 and 4 for one candidate; the drift bounds of step 4 only
/// when `drift_bounds` (a loop: a merge's maps have unrelated frames).
pub(super) fn verify_one(
    p: &LoopParams,
    bounds: &Bounds,
    map: &Map,
    kf: KeyFrameId,
    cand: KeyFrameId,
    drift_bounds: bool,
) -> Result<LoopMatch, LoopReject> {
    let (Some(k1), Some(k2)) = (map.keyframe(kf), map.keyframe(cand)) else {
        return Err(LoopReject::BowMatches);
    };
    let places = map.places().ok_or(LoopReject::BowMatches)?;
    let (Some(fv1), Some(fv2)) = (places.features.get(&kf), places.features.get(&cand)) else {
        return Err(LoopReject::BowMatches);
    };
    let cam = &map.camera;
    let intr = Intrinsics {
        fx: cam.fx,
        fy: cam.fy,
        cx: cam.cx,
        cy: cam.cy,
    };
    let sigma2 = &map.scale.inv_level_sigma2;
    // BoW-guided matches: keypoints of kf that hold a point, to points of cand.
    let bow = matcher::search_by_bow(
        map,
        cand,
        fv2,
        &k1.descriptors,
        &k1.keypoints,
        fv1,
        &p.matcher,
        p.bow_ratio,
    );
    let mut pairs: Vec<(usize, PointId, PointId)> = Vec::new();
    let mut used2: HashSet<PointId> = HashSet::new();
    for (i1, p2) in bow {
        if let Some(Some(p1)) = k1.points.get(i1)
            && *p1 != p2
            && map.point(*p1).is_some()
            && used2.insert(p2)
        {
            pairs.push((i1, *p1, p2));
        }
    }
    if pairs.len() < p.min_bow_matches {
        return Err(LoopReject::BowMatches);
    }
    let make = |i1: usize, p1: PointId, p2: PointId| -> Option<Sim3Match> {
        let mp1 = map.point(p1)?;
        let mp2 = map.point(p2)?;
        let i2 = mp2.index_in(cand)? as usize;
        let kp1 = k1.keypoints.get(i1)?;
        let kp2 = k2.keypoints.get(i2)?;
        Some(Sim3Match {
            x1_cam1: k1.cam_from_world * mp1.position,
            x2_cam2: k2.cam_from_world * mp2.position,
            uv1: Point2::new(kp1.ux as f64, kp1.uy as f64),
            uv2: Point2::new(kp2.ux as f64, kp2.uy as f64),
            inv_sigma2_1: *sigma2.get(kp1.octave as usize)?,
            inv_sigma2_2: *sigma2.get(kp2.octave as usize)?,
        })
    };
    let mut ms: Vec<Sim3Match> = Vec::with_capacity(pairs.len());
    let mut keep: Vec<(usize, PointId, PointId)> = Vec::with_capacity(pairs.len());
    for &(i1, p1, p2) in &pairs {
        if let Some(m) = make(i1, p1, p2) {
            ms.push(m);
            keep.push((i1, p1, p2));
        }
    }
    let seed = p
        .seed
        .wrapping_mul(0x9E37_79B9_7F4A_7C15)
        .wrapping_add(((kf.0 as u64) << 32) | cand.0 as u64);
    let ransac = sim3_ransac(&ms, &intr, &p.ransac, seed).map_err(|_| LoopReject::Ransac)?;
    // Guided search: the candidate's other points through S12 into kf.
    let s12 = ransac.s12;
    let mut taken1: HashSet<usize> = keep.iter().map(|m| m.0).collect();
    let mut taken2: HashSet<PointId> = keep.iter().map(|m| m.2).collect();
    let s_1w = s12.compose(&Sim3::from_isometry(&k2.cam_from_world));
    let iso_1w = sim3_to_isometry(&s_1w);
    let center1 = iso_1w.inverse().translation.vector;
    let mut cand_list = Vec::new();
    for p2 in k2.points.iter().flatten() {
        if taken2.contains(p2) {
            continue;
        }
        let Some(pr) =
            matcher::project_point(map, *p2, &iso_1w, &center1, bounds, matcher::MIN_VIEW_COS)
        else {
            continue;
        };
        let Some(mp2) = map.point(*p2) else { continue };
        let r = p.sim3_search_radius * map.scale.scale_factors[pr.level];
        let best = nearest_in_window(k1, &pr, r, &mp2.descriptor, &mut cand_list, |i| {
            taken1.contains(&i) || k1.points.get(i).copied().flatten().is_none()
        });
        if best.0 <= p.matcher.th_high
            && let Some(Some(p1)) = k1.points.get(best.1)
            && *p1 != *p2
            && let Some(m) = make(best.1, *p1, *p2)
        {
            taken1.insert(best.1);
            taken2.insert(*p2);
            ms.push(m);
            keep.push((best.1, *p1, *p2));
        }
    }
    // Reprojection hardly constrains the scale when the two cameras
    // nearly coincide (a revisit): points scaled about the camera
    // project to the same pixels. So the rotation and translation are
    // refined on reprojection with the scale held, the scale comes
    // from the 3D alignment (Umeyama) of the inliers, and the pose is
    // refined again at that scale.
    let fixed = Sim3Params {
        fix_scale: true,
        ..p.sim3.clone()
    };
    let first = optimize_sim3(&s12, &ms, &intr, &fixed).map_err(|_| LoopReject::Sim3Inliers)?;
    if first.n_inliers < p.min_sim3_inliers {
        return Err(LoopReject::Sim3Inliers);
    }
    let (src, dst): (Vec<_>, Vec<_>) = ms
        .iter()
        .zip(&first.inliers)
        .filter(|(_, ok)| **ok)
        .map(|(m, _)| (m.x2_cam2, m.x1_cam1))
        .unzip();
    let aligned = robust_scale_fit(&src, &dst, &first.s12).ok_or(LoopReject::Sim3Inliers)?;
    let refined =
        optimize_sim3(&aligned, &ms, &intr, &fixed).map_err(|_| LoopReject::Sim3Inliers)?;
    if refined.n_inliers < p.min_sim3_inliers {
        return Err(LoopReject::Sim3Inliers);
    }
    tracing::debug!(
        current = kf.0,
        candidate = cand.0,
        ransac_scale = s12.scale,
        ransac_inliers = ransac.n_inliers,
        refined_scale = refined.s12.scale,
        refined_inliers = refined.n_inliers,
        matches = ms.len(),
        "loop: Sim(3)"
    );
    let s_cw = refined
        .s12
        .compose(&Sim3::from_isometry(&k2.cam_from_world));
    // The loop neighbourhood's points through the corrected pose.
    let mut matched: Vec<Option<PointId>> = vec![None; k1.keypoints.len()];
    for ((i1, _, p2), ok) in keep.iter().zip(&refined.inliers) {
        if *ok {
            matched[*i1] = Some(*p2);
        }
    }
    let mut loop_points: Vec<PointId> = Vec::new();
    let mut seen: HashSet<PointId> = HashSet::new();
    for id in std::iter::once(cand).chain(k2.covisible.iter().map(|c| c.0)) {
        if let Some(k) = map.keyframe(id) {
            for pid in k.points.iter().flatten() {
                if seen.insert(*pid) {
                    loop_points.push(*pid);
                }
            }
        }
    }
    let (mut matched, mut in_view) =
        search_by_projection(p, bounds, map, k1, &loop_points, &s_cw, matched);
    let mut s_cw = s_cw;
    let mut inliers = refined.n_inliers;
    // The scale again from the larger set the projection found (ORB-SLAM
    // stops at the BoW inliers): every match whose keypoint holds a point
    // gives a 3D pair; the pose is refined on them at the scale held,
    // the scale re-fitted robustly on that refinement's inliers, the pose
    // refined at the new scale, and the projection search run once more.
    if p.refit_on_projection
        && let Some((s12, seeds, n)) =
            refit_on_projection(p, map, k1, k2, cand, &matched, &refined.s12, &intr)
    {
        s_cw = s12.compose(&Sim3::from_isometry(&k2.cam_from_world));
        (matched, in_view) = search_by_projection(p, bounds, map, k1, &loop_points, &s_cw, seeds);
        inliers = n;
    }
    let n_matched = matched.iter().flatten().count();
    if n_matched < p.min_projection_matches
        || (n_matched as f64) < p.min_projection_ratio * in_view as f64
    {
        tracing::debug!(
            current = kf.0,
            candidate = cand.0,
            n_matched,
            in_view,
            "loop: too few matches by projection"
        );
        return Err(LoopReject::Projection);
    }
    // Plausibility: the correction of the current pose.
    let corr = s_cw.compose(&Sim3::from_isometry(&k1.cam_from_world.inverse()));
    let rotation_deg = corr.rotation.angle().to_degrees();
    let moved = (sim3_to_isometry(&s_cw).inverse().translation.vector - k1.center()).norm();
    let flown = path_length(map, cand, kf);
    let max_s = p.max_scale_change.max(1.0);
    if drift_bounds
        && (!(corr.scale <= max_s && corr.scale >= 1.0 / max_s)
            || rotation_deg > p.max_rotation_deg
            || moved > p.max_translation_ratio * flown)
    {
        tracing::debug!(
            current = kf.0,
            candidate = cand.0,
            scale = corr.scale,
            rotation_deg,
            moved,
            flown,
            "loop: implausible correction"
        );
        return Err(LoopReject::Implausible);
    }
    Ok(LoopMatch {
        loop_kf: cand,
        s_cw,
        matched,
        loop_points,
        inliers,
        projection_matches: n_matched,
    })
}

/// Keypoints of `k1` matched by the loop neighbourhood's points seen
/// through `s_cw`, starting from `matched`; also how many of the points
/// were in view (the seeds count as in view).
fn search_by_projection(
    p: &LoopParams,
    bounds: &Bounds,
    map: &Map,
    k1: &KeyFrame,
    loop_points: &[PointId],
    s_cw: &Sim3,
    mut matched: Vec<Option<PointId>>,
) -> (Vec<Option<PointId>>, usize) {
    let mut cand_list = Vec::new();
    let iso_cw = sim3_to_isometry(s_cw);
    let center = iso_cw.inverse().translation.vector;
    let already: HashSet<PointId> = matched.iter().flatten().copied().collect();
    let mut in_view = 0usize;
    for pid in loop_points {
        if already.contains(pid) {
            in_view += 1;
            continue;
        }
        let Some(pr) =
            matcher::project_point(map, *pid, &iso_cw, &center, bounds, matcher::MIN_VIEW_COS)
        else {
            continue;
        };
        let Some(mp) = map.point(*pid) else { continue };
        in_view += 1;
        let r = p.projection_radius * map.scale.scale_factors[pr.level];
        let best = nearest_in_window(k1, &pr, r, &mp.descriptor, &mut cand_list, |i| {
            matched[i].is_some()
        });
        if best.0 <= p.matcher.th_low {
            matched[best.1] = Some(*pid);
        }
    }
    (matched, in_view)
}

/// The loop's Sim(3) (camera 2 → camera 1) fitted again on the
/// projection matches whose keypoint in `k1` holds a point: pose refined
/// at the scale of `s12`, scale re-fitted with [`robust_scale_fit`] on
/// that refinement's inliers, pose refined at the new scale. Returns the
/// Sim(3), its inliers as seeds of a new search, and their count; `None`
/// when too few remain (the caller keeps the BoW fit).
#[allow(clippy::too_many_arguments)]
fn refit_on_projection(
    p: &LoopParams,
    map: &Map,
    k1: &KeyFrame,
    k2: &KeyFrame,
    cand: KeyFrameId,
    matched: &[Option<PointId>],
    s12: &Sim3,
    intr: &Intrinsics,
) -> Option<(Sim3, Vec<Option<PointId>>, usize)> {
    let sigma2 = &map.scale.inv_level_sigma2;
    let mut ms: Vec<Sim3Match> = Vec::new();
    let mut keep: Vec<(usize, PointId)> = Vec::new();
    for (i1, m) in matched.iter().enumerate() {
        let Some(p2) = *m else { continue };
        let Some(Some(p1)) = k1.points.get(i1) else {
            continue;
        };
        if *p1 == p2 {
            continue;
        }
        let (Some(mp1), Some(mp2), Some(kp1)) =
            (map.point(*p1), map.point(p2), k1.keypoints.get(i1))
        else {
            continue;
        };
        let x2 = k2.cam_from_world * mp2.position;
        // The loop-side point's keypoint in the candidate if it has one,
        // else its projection there (it was seen by a neighbour).
        let (uv2, s2) = match mp2
            .index_in(cand)
            .and_then(|i2| k2.keypoints.get(i2 as usize))
        {
            Some(kp2) => (
                Point2::new(kp2.ux as f64, kp2.uy as f64),
                *sigma2.get(kp2.octave as usize)?,
            ),
            None => {
                if x2.z <= p.sim3.min_depth {
                    continue;
                }
                (
                    Point2::new(
                        intr.fx * x2.x / x2.z + intr.cx,
                        intr.fy * x2.y / x2.z + intr.cy,
                    ),
                    *sigma2.get(kp1.octave as usize)?,
                )
            }
        };
        ms.push(Sim3Match {
            x1_cam1: k1.cam_from_world * mp1.position,
            x2_cam2: x2,
            uv1: Point2::new(kp1.ux as f64, kp1.uy as f64),
            uv2,
            inv_sigma2_1: *sigma2.get(kp1.octave as usize)?,
            inv_sigma2_2: s2,
        });
        keep.push((i1, p2));
    }
    let fixed = Sim3Params {
        fix_scale: true,
        ..p.sim3.clone()
    };
    let first = optimize_sim3(s12, &ms, intr, &fixed).ok()?;
    if first.n_inliers < p.min_sim3_inliers {
        return None;
    }
    let (src, dst): (Vec<_>, Vec<_>) = ms
        .iter()
        .zip(&first.inliers)
        .filter(|(_, ok)| **ok)
        .map(|(m, _)| (m.x2_cam2, m.x1_cam1))
        .unzip();
    let aligned = robust_scale_fit(&src, &dst, &first.s12)?;
    let refit = optimize_sim3(&aligned, &ms, intr, &fixed).ok()?;
    if refit.n_inliers < p.min_sim3_inliers {
        return None;
    }
    tracing::debug!(
        bow_scale = s12.scale,
        refit_scale = refit.s12.scale,
        pairs = ms.len(),
        scale_inliers = first.n_inliers,
        refit_inliers = refit.n_inliers,
        "loop: Sim(3) refitted on the projection matches"
    );
    let mut seeds = vec![None; matched.len()];
    for ((i1, p2), ok) in keep.iter().zip(&refit.inliers) {
        if *ok {
            seeds[*i1] = Some(*p2);
        }
    }
    Some((refit.s12, seeds, refit.n_inliers))
}

/// Length of the path through the live keyframes between two keyframes
/// (by id, so by time), in map units.
fn path_length(map: &Map, from: KeyFrameId, to: KeyFrameId) -> f64 {
    let (a, b) = (from.min(to), from.max(to));
    let mut last: Option<nalgebra::Vector3<f64>> = None;
    let mut len = 0.0;
    for k in map.keyframes().filter(|k| k.id >= a && k.id <= b) {
        let c = k.center();
        if let Some(l) = last {
            len += (c - l).norm();
        }
        last = Some(c);
    }
    len
}

/// The keypoint of `k1` nearest to `descriptor` (Hamming distance, first
/// wins a tie) among those within `radius` px of the projection `pr` and
/// one pyramid level of it, skipping those `skip` names; `(u32::MAX,
/// usize::MAX)` when none. `cand` is a reused buffer.
fn nearest_in_window(
    k1: &KeyFrame,
    pr: &matcher::Projected,
    radius: f64,
    descriptor: &Descriptor,
    cand: &mut Vec<usize>,
    skip: impl Fn(usize) -> bool,
) -> (u32, usize) {
    let lvl = pr.level as i32;
    k1.grid.features_in_area(
        &k1.keypoints,
        pr.uv.x,
        pr.uv.y,
        radius,
        lvl - 1,
        lvl + 1,
        cand,
    );
    let mut best = (u32::MAX, usize::MAX);
    for &i in cand.iter() {
        if skip(i) {
            continue;
        }
        let d = hamming(descriptor, &k1.descriptors[i]);
        if d < best.0 {
            best = (d, i);
        }
    }
    best
}
