//! Trajectory evaluation as the literature does it: associate timestamps,
//! align the estimate to the ground truth (Umeyama, with or without scale),
//! then the absolute trajectory error (ATE) of the camera positions and the
//! relative pose error (RPE) between frames `delta` apart. The figures agree
//! with `evo_ape tum GT EST -as` (translation part, Sim(3) alignment).

pub mod plot;

use nalgebra::{Point3, Vector3};

use crate::geometry::GeometryError;
use serde::Serialize;

pub use crate::trajectory::{StampedPose, Trajectory, TrajectoryError, associate};

/// Errors of the evaluation.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// Too few timestamps matched between the two trajectories.
    #[error("only {found} poses matched within the time tolerance, need at least {needed}")]
    NotEnoughMatches {
        /// Pairs found.
        found: usize,
        /// Pairs needed.
        needed: usize,
    },
    /// The estimate's positions do not span enough to fix an alignment.
    #[error("alignment is degenerate: {reason}")]
    Degenerate {
        /// Why.
        reason: String,
    },
}

/// How to align the estimate to the ground truth before measuring.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum AlignMode {
    /// Rotation, translation and scale (Umeyama with scale): monocular SLAM.
    Sim3,
    /// Rotation and translation only.
    Se3,
    /// No alignment.
    None,
}

/// Tunable numbers of the evaluation.
#[derive(Debug, Clone, Copy)]
pub struct Params {
    /// Largest timestamp difference for a pair, seconds.
    pub max_dt: f64,
    /// Alignment before measuring.
    pub align: AlignMode,
    /// Frame distance of the relative pose error.
    pub rpe_delta: usize,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            max_dt: 0.02,
            align: AlignMode::Sim3,
            rpe_delta: 1,
        }
    }
}

/// The alignment applied to the estimate: `p -> scale * rotation * p + translation`.
pub use crate::lie::Sim3 as Similarity;

/// Umeyama's least-squares alignment `dst ~ s R src + t` (Umeyama 1991),
/// through [`crate::geometry::umeyama()`]; with `with_scale` false, `s` = 1.
pub fn umeyama(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
    with_scale: bool,
) -> Result<Similarity, EvalError> {
    let n = src.len().min(dst.len());
    let to_points =
        |v: &[Vector3<f64>]| v[..n].iter().map(|p| Point3::from(*p)).collect::<Vec<_>>();
    crate::geometry::umeyama(&to_points(src), &to_points(dst), with_scale).map_err(|e| match e {
        GeometryError::NotEnoughPoints { found, needed } => {
            EvalError::NotEnoughMatches { found, needed }
        }
        other => EvalError::Degenerate {
            reason: other.to_string(),
        },
    })
}

/// Summary statistics of a set of errors.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Stats {
    /// Root mean square.
    pub rmse: f64,
    /// Mean.
    pub mean: f64,
    /// Median.
    pub median: f64,
    /// Largest.
    pub max: f64,
    /// Standard deviation.
    pub std: f64,
}

impl Stats {
    /// Statistics of `values` (all zero when empty).
    pub fn of(values: &[f64]) -> Stats {
        if values.is_empty() {
            return Stats {
                rmse: 0.0,
                mean: 0.0,
                median: 0.0,
                max: 0.0,
                std: 0.0,
            };
        }
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let rmse = (values.iter().map(|v| v * v).sum::<f64>() / n).sqrt();
        let std = (values.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / n).sqrt();
        Stats {
            rmse,
            mean,
            median: crate::stats::median(values).unwrap_or(f64::NAN),
            max: crate::stats::quantile(values, 1.0).unwrap_or(f64::NAN),
            std,
        }
    }
}

/// The result of comparing an estimate with the ground truth.
#[derive(Debug, Clone)]
pub struct Evaluation {
    /// Number of associated pose pairs.
    pub matched: usize,
    /// The alignment applied to the estimate.
    pub alignment: Similarity,
    /// Absolute position errors after alignment, metres.
    pub ate: Stats,
    /// Relative translation errors between frames `delta` apart, metres.
    pub rpe_trans: Stats,
    /// Relative rotation errors between frames `delta` apart, degrees.
    pub rpe_rot_deg: Stats,
    /// Per pair: ground-truth time and position error, metres.
    pub errors: Vec<(f64, f64)>,
    /// Ground-truth positions of the pairs.
    pub gt_positions: Vec<Point3<f64>>,
    /// Aligned estimate positions of the pairs.
    pub est_positions: Vec<Point3<f64>>,
}

/// Associate, align and measure `est` against `gt`.
pub fn evaluate(
    gt: &Trajectory,
    est: &Trajectory,
    params: &Params,
) -> Result<Evaluation, EvalError> {
    let pairs = associate(gt, est, params.max_dt);
    let needed = if params.align == AlignMode::None {
        1
    } else {
        3
    };
    if pairs.len() < needed {
        return Err(EvalError::NotEnoughMatches {
            found: pairs.len(),
            needed,
        });
    }
    let gt_p: Vec<Vector3<f64>> = pairs.iter().map(|&(i, _)| gt.poses[i].position()).collect();
    let est_p: Vec<Vector3<f64>> = pairs
        .iter()
        .map(|&(_, j)| est.poses[j].position())
        .collect();
    let alignment = match params.align {
        AlignMode::Sim3 => umeyama(&est_p, &gt_p, true)?,
        AlignMode::Se3 => umeyama(&est_p, &gt_p, false)?,
        AlignMode::None => Similarity::identity(),
    };
    let mut errors = Vec::with_capacity(pairs.len());
    let mut est_aligned = Vec::with_capacity(pairs.len());
    for (k, &(i, _)) in pairs.iter().enumerate() {
        let e = alignment.transform_point(&Point3::from(est_p[k])).coords;
        errors.push((gt.poses[i].t, (e - gt_p[k]).norm()));
        est_aligned.push(Point3::from(e));
    }
    let ate = Stats::of(&errors.iter().map(|e| e.1).collect::<Vec<_>>());

    // Relative pose error between pairs `delta` apart (in the associated
    // sequence), with the estimate's translation scaled by the alignment.
    let delta = params.rpe_delta.max(1);
    let mut rpe_t = Vec::new();
    let mut rpe_r = Vec::new();
    for k in 0..pairs.len().saturating_sub(delta) {
        let (gi, ei) = pairs[k];
        let (gj, ej) = pairs[k + delta];
        let gt_rel = gt.poses[gi].world_from_cam.inverse() * gt.poses[gj].world_from_cam;
        let a = alignment.transform_pose(&est.poses[ei].world_from_cam);
        let b = alignment.transform_pose(&est.poses[ej].world_from_cam);
        let est_rel = a.inverse() * b;
        let err = gt_rel.inverse() * est_rel;
        rpe_t.push(err.translation.vector.norm());
        rpe_r.push(err.rotation.angle().to_degrees());
    }
    Ok(Evaluation {
        matched: pairs.len(),
        alignment,
        ate,
        rpe_trans: Stats::of(&rpe_t),
        rpe_rot_deg: Stats::of(&rpe_r),
        errors,
        gt_positions: gt_p.into_iter().map(Point3::from).collect(),
        est_positions: est_aligned,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn umeyama_recovers_known_similarity() {
        let src: Vec<Vector3<f64>> = (0..50)
            .map(|i| {
                let f = i as f64;
                Vector3::new((f * 0.37).sin() * 2.0, (f * 0.11).cos(), f * 0.05)
            })
            .collect();
        let truth = Similarity {
            rotation: UnitQuaternion::from_euler_angles(0.3, -0.7, 2.1),
            translation: Vector3::new(1.0, -2.0, 0.5),
            scale: 2.7,
        };
        let dst: Vec<_> = src
            .iter()
            .map(|p| truth.transform_point(&Point3::from(*p)).coords)
            .collect();
        let est = umeyama(&src, &dst, true).unwrap();
        assert!((est.scale - truth.scale).abs() < 1e-10);
        assert!(est.rotation.angle_to(&truth.rotation) < 1e-10);
        assert!((est.translation - truth.translation).norm() < 1e-9);
        let se3 = umeyama(&src, &src, false).unwrap();
        assert!((se3.scale - 1.0).abs() < 1e-15 && se3.translation.norm() < 1e-12);
    }

    #[test]
    fn degenerate_inputs_are_refused() {
        let p = vec![Vector3::new(1.0, 1.0, 1.0); 5];
        assert!(matches!(
            umeyama(&p, &p, true),
            Err(EvalError::Degenerate { .. })
        ));
        assert!(matches!(
            umeyama(&p[..2], &p[..2], true),
            Err(EvalError::NotEnoughMatches {
                found: 2,
                needed: 3
            })
        ));
    }

    #[test]
    fn stats_are_right() {
        let s = Stats::of(&[3.0, 4.0, 1.0, 2.0]);
        assert_eq!(s.median, 2.5);
        assert_eq!(s.max, 4.0);
        assert!((s.rmse - (30.0f64 / 4.0).sqrt()).abs() < 1e-15);
        assert_eq!(s.mean, 2.5);
    }
}
