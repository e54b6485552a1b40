//! The reliability gate on a candidate's pose, the agreement of the gated
//! candidates, and the union of evidence: the pairs of every agreeing
//! candidate in one final pose optimisation.

use std::collections::HashSet;

use super::covariance::MapError;
use super::outcome::NotLocalizedReason;
use super::params::{GateParams, LocalizeParams};
use super::pose_refinement::{CandidatePose, evaluate_candidate, observations};
use crate::features;
use crate::optimize::{Intrinsics, optimize_pose};
use crate::slam::{Map, PointId};

/// Why the gate refuses `c` (too few inliers, a high reprojection RMSE, a
/// low inlier ratio, inliers behind the camera), None when it passes.
pub(super) fn gate_reason(c: &CandidatePose, g: &GateParams) -> Option<NotLocalizedReason> {
    let ratio = c.inliers as f64 / c.matches.max(1) as f64;
    if c.inliers < g.min_inliers {
        Some(NotLocalizedReason::TooFewInliers {
            found: c.inliers,
            needed: g.min_inliers,
        })
    } else if c.rmse.is_nan() || c.rmse > g.max_rmse_px {
        Some(NotLocalizedReason::HighReprojectionError {
            rmse_px: c.rmse,
            max_px: g.max_rmse_px,
        })
    } else if ratio < g.min_inlier_ratio {
        Some(NotLocalizedReason::LowInlierRatio {
            ratio,
            min: g.min_inlier_ratio,
        })
    } else if c.in_front < g.min_in_front_fraction {
        Some(NotLocalizedReason::PointsBehind {
            in_front_fraction: c.in_front,
            min: g.min_in_front_fraction,
        })
    } else {
        None
    }
}

/// The other candidates that pass the gate, all agreeing with the best.
pub(super) struct Agreement<'a> {
    /// How many.
    pub(super) count: usize,
    /// Their pairs (keypoint -> map point).
    pub(super) slots: Vec<&'a [Option<PointId>]>,
    /// Sum of their squared position offsets from the best, as fractions
    /// of its median depth.
    spread_pos2: f64,
    /// Sum of their squared angles to the best, degrees².
    spread_rot2: f64,
}

impl Agreement<'_> {
    /// The RMS offset of the agreeing candidates from the best: position
    /// as a fraction of the median depth, rotation in degrees; None
    /// without any.
    pub(super) fn rms_spread(&self) -> Option<(f64, f64)> {
        (self.count > 0).then(|| {
            (
                (self.spread_pos2 / self.count as f64).sqrt(),
                (self.spread_rot2 / self.count as f64).sqrt(),
            )
        })
    }
}

/// The gated candidates after the best (`poses[0]`, which passed the
/// gate) that agree with it within the gate's bounds, when none of
/// comparable support disagrees; the first such otherwise. A disagreeing
/// candidate with fewer than [`GateParams::drop_disagreeing_below`] of
/// the best's inliers is left out (logged), not a veto.
pub(super) fn agreement<'a>(
    poses: &'a [CandidatePose],
    g: &GateParams,
) -> Result<Agreement<'a>, NotLocalizedReason> {
    let mut out = Agreement {
        count: 0,
        slots: Vec::new(),
        spread_pos2: 0.0,
        spread_rot2: 0.0,
    };
    let Some(best) = poses.first() else {
        return Ok(out);
    };
    let best_wfc = best.cam_from_world.inverse();
    for other in poses.iter().skip(1) {
        if gate_reason(other, g).is_some() {
            continue;
        }
        let owfc = other.cam_from_world.inverse();
        let dist = (owfc.translation.vector - best_wfc.translation.vector).norm()
            / best.median_depth.max(1e-12);
        let ang = owfc.rotation.angle_to(&best_wfc.rotation).to_degrees();
        let agrees = dist <= g.max_disagreement_depth_fraction && ang <= g.max_disagreement_deg;
        if !agrees && (other.inliers as f64) < g.drop_disagreeing_below * best.inliers as f64 {
            tracing::debug!(
                keyframe = other.kf.0,
                inliers = other.inliers,
                best_inliers = best.inliers,
                position_depth_fraction = dist,
                angle_deg = ang,
                "a disagreeing candidate with far fewer inliers than the best left out"
            );
            continue;
        }
        if !agrees {
            return Err(NotLocalizedReason::CandidatesDisagree {
                other: other.kf,
                position_depth_fraction: dist,
                angle_deg: ang,
            });
        }
        out.count += 1;
        out.slots.push(&other.slots);
        out.spread_pos2 += dist * dist;
        out.spread_rot2 += ang * ang;
    }
    Ok(out)
}

/// The union of evidence: the pairs of every agreeing candidate (a
/// keypoint or a point already paired by a better candidate keeps that
/// pair) in one final optimisation from the best pose; kept when it passes
/// the gate too and has a covariance. None without agreeing candidates,
/// with [`LocalizeParams::union_of_evidence`] off, or for an assumed camera
/// ([`LocalizeParams::focal_unknown`]): the other candidates' pairs were
/// matched through its focal length, and merged they bias the other
/// camera's fit (shot_photos, no EXIF: median error 0.47 -> 1.83 %, true
/// errors within 2 sigma 91 -> 23 %).
pub(super) fn union_of_evidence(
    map: &Map,
    feats: &features::Features,
    best: &CandidatePose,
    agreeing: &Agreement<'_>,
    intr: &Intrinsics,
    params: &LocalizeParams,
    map_error: &MapError,
) -> Option<CandidatePose> {
    if agreeing.slots.is_empty() || !params.union_of_evidence || params.focal_unknown {
        return None;
    }
    let mut slots = best.slots.clone();
    let mut used: HashSet<PointId> = slots.iter().flatten().copied().collect();
    for other in &agreeing.slots {
        for (i, s) in other.iter().enumerate() {
            if let Some(p) = s
                && let Some(slot) = slots.get_mut(i)
                && slot.is_none()
                && used.insert(*p)
            {
                *slot = Some(*p);
            }
        }
    }
    let (obs, _) = observations(map, feats, &slots);
    optimize_pose(best.cam_from_world, &obs, intr, &params.pose)
        .ok()
        .and_then(|r| {
            evaluate_candidate(
                best.kf,
                r.cam_from_world,
                &obs,
                &r.inliers,
                slots,
                intr,
                params,
                map_error,
            )
        })
        .filter(|c| gate_reason(c, &params.gate).is_none() && c.sigma.is_some())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optimize::IntrinsicsCorrection;
    use crate::slam::KeyFrameId;
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    /// A candidate through keyframe `kf` with `inliers` of 1.1x as many
    /// pairs, its camera `dx` (median depth 10) and `deg` about y from the
    /// origin.
    fn cand(kf: u32, inliers: usize, dx: f64, deg: f64) -> CandidatePose {
        let world_from_cam = Isometry3::from_parts(
            Translation3::new(dx, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, deg.to_radians(), 0.0),
        );
        CandidatePose {
            kf: KeyFrameId(kf),
            cam_from_world: world_from_cam.inverse(),
            inliers,
            matches: inliers * 11 / 10,
            rmse: 1.0,
            in_front: 1.0,
            median_depth: 10.0,
            near_depth: 8.0,
            sigma: None,
            slots: Vec::new(),
            correction: IntrinsicsCorrection::default(),
            obs_inliers: Vec::new(),
        }
    }

    #[test]
    fn a_weak_outlying_candidate_is_left_out_a_strong_one_refuses() {
        let g = GateParams::default();
        // The best, one that agrees (0.1 units, 0.5 deg), one 4 deg off
        // with a quarter of the best's inliers: left out.
        let poses = [
            cand(1, 200, 0.0, 0.0),
            cand(2, 150, 0.1, 0.5),
            cand(3, 50, 0.7, 4.0),
        ];
        let a = agreement(&poses, &g).unwrap_or_else(|r| panic!("{r}"));
        assert_eq!(a.count, 1);
        let (pos, rot) = a.rms_spread().unwrap_or_default();
        assert!(
            (pos - 0.01).abs() < 1e-9 && (rot - 0.5).abs() < 1e-6,
            "{pos} {rot}"
        );
        // With comparable support the place is ambiguous: refused, naming
        // the other keyframe.
        let poses = [
            cand(1, 200, 0.0, 0.0),
            cand(2, 150, 0.1, 0.5),
            cand(3, 120, 0.7, 4.0),
        ];
        match agreement(&poses, &g) {
            Err(NotLocalizedReason::CandidatesDisagree {
                other, angle_deg, ..
            }) => {
                assert_eq!(other, KeyFrameId(3));
                assert!((angle_deg - 4.0).abs() < 1e-6);
            }
            Err(r) => panic!("{r}"),
            Ok(a) => panic!("agreed with {} candidates", a.count),
        }
        // Dropping off: every disagreement refuses, as before.
        let strict = GateParams {
            drop_disagreeing_below: 0.0,
            ..g
        };
        let poses = [cand(1, 200, 0.0, 0.0), cand(3, 50, 0.7, 4.0)];
        assert!(agreement(&poses, &strict).is_err());
        // A candidate that fails the gate itself is not counted at all.
        let poses = [cand(1, 200, 0.0, 0.0), cand(4, 20, 5.0, 30.0)];
        assert_eq!(agreement(&poses, &strict).map(|a| a.count).ok(), Some(0));
    }
}
