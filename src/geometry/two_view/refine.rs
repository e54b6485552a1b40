//! The two-view bundle adjustment of an accepted (or re-checked)
//! reconstruction: camera 1 fixed, Huber kernel, the translation rescaled
//! to unit norm and the points that no longer pass the checks dropped.

use nalgebra::{Isometry3, Matrix3, Point2, Point3, Translation3};

use super::TwoViewParams;

/// Two-view bundle adjustment of the initial reconstruction (ORB-SLAM runs
/// a global BA right after initialising): camera 1 fixed, camera 2 and the
/// points free, Huber kernel; then the translation is rescaled to unit norm
/// and points that no longer pass the depth and reprojection checks are
/// dropped.
pub(super) fn refine_two_view(
    k: &Matrix3<f64>,
    px1: &[[f64; 2]],
    px2: &[[f64; 2]],
    params: &TwoViewParams,
    cam2_from_cam1: &mut Isometry3<f64>,
    points: &mut [Option<Point3<f64>>],
) {
    use crate::optimize::ba::{BaPose, BaProblem, Observation, bundle_adjust_lm};
    use crate::optimize::lm::LmParams;
    use crate::optimize::{Intrinsics, RobustKernel};
    let intr = Intrinsics {
        fx: k[(0, 0)],
        fy: k[(1, 1)],
        cx: k[(0, 2)],
        cy: k[(1, 2)],
    };
    let inv_sigma2 = 1.0 / (params.sigma_px * params.sigma_px);
    let mut prob = BaProblem {
        poses: vec![
            BaPose {
                cam_from_world: Isometry3::identity(),
                fixed: true,
                shutter: None,
            },
            BaPose {
                cam_from_world: *cam2_from_cam1,
                fixed: false,
                shutter: None,
            },
        ],
        points: Vec::new(),
        observations: Vec::new(),
        intrinsics: intr,
        priors: Vec::new(),
    };
    let mut which = Vec::new();
    for (i, p) in points.iter().enumerate() {
        if let Some(p) = p {
            let j = prob.points.len();
            prob.points.push(*p);
            which.push(i);
            for (pose, px) in [(0usize, px1[i]), (1usize, px2[i])] {
                prob.observations.push(Observation {
                    pose,
                    point: j,
                    uv: Point2::new(px[0], px[1]),
                    inv_sigma2,
                });
            }
        }
    }
    if prob.points.len() < params.min_triangulated {
        return;
    }
    let lm = LmParams {
        max_iterations: params.refine_iterations,
        ..LmParams::default()
    };
    let kernel = RobustKernel::Huber {
        delta: params.chi2_two_dof.sqrt(),
    };
    if bundle_adjust_lm(&mut prob, kernel, &lm).is_err() {
        return;
    }
    let t = prob.poses[1].cam_from_world.translation.vector;
    let norm = t.norm();
    if !(norm.is_finite() && norm > 0.0) {
        return;
    }
    let scale = 1.0 / norm;
    let refined = Isometry3::from_parts(
        Translation3::from(t * scale),
        prob.poses[1].cam_from_world.rotation,
    );
    let th2 = params.reprojection_chi2 * params.sigma_px * params.sigma_px;
    for (j, &i) in which.iter().enumerate() {
        let p = Point3::from(prob.points[j].coords * scale);
        let p2 = refined * p;
        let ok = p.z > 0.0 && p2.z > 0.0 && {
            let a = intr.project(&p.coords) - Point2::new(px1[i][0], px1[i][1]);
            let b = intr.project(&p2.coords) - Point2::new(px2[i][0], px2[i][1]);
            a.norm_squared() <= th2 && b.norm_squared() <= th2
        };
        points[i] = ok.then_some(p);
    }
    *cam2_from_cam1 = refined;
}
