//! Local bundle adjustment on a synthetic scene whose answer is known:
//! 10 keyframes, 2000 points, 8000 observations, 1 px noise, poses and
//! points perturbed.

use crate::geometry_support;

use std::time::Instant;

use geometry_support::ba_scene;
use shotpilot::optimize::ba::{bundle_adjust_lm, reprojection_rmse};
use shotpilot::optimize::lm::LmParams;
use shotpilot::optimize::{
    BaParams, Observation, OptimizeError, RobustKernel, local_bundle_adjustment,
};

#[test]
fn local_ba_converges_to_the_noise_level() {
    let scene = ba_scene(17, 10, 2000, 4, 1.0, 1.0, 0.1, 0.3);
    assert_eq!(scene.truth.observations.len(), 8000);
    let rmse_truth = reprojection_rmse(&scene.truth, None);
    let mut problem = scene.perturbed.clone();
    let rmse_start = reprojection_rmse(&problem, None);
    let t0 = Instant::now();
    let rep = local_bundle_adjustment(&mut problem, &BaParams::default()).unwrap();
    let dt = t0.elapsed().as_secs_f64();
    let iters = rep.first_pass.iterations + rep.second_pass.map_or(0, |s| s.iterations);
    let rmse_all = reprojection_rmse(&problem, None);
    // The optimum the noise allows on the same (inlier) observations: plain
    // LM started at the truth, run to convergence.
    let mut optimum = scene.truth.clone();
    optimum.observations = optimum
        .observations
        .iter()
        .zip(&rep.outliers)
        .filter(|(_, o)| !**o)
        .map(|(ob, _)| *ob)
        .collect();
    bundle_adjust_lm(
        &mut optimum,
        RobustKernel::None,
        &LmParams {
            max_iterations: 50,
            ..LmParams::default()
        },
    )
    .unwrap();
    let rmse_opt = reprojection_rmse(&optimum, None);
    let pose_err = |a: &shotpilot::optimize::BaProblem, b: &shotpilot::optimize::BaProblem| {
        let mut worst_rot: f64 = 0.0;
        let mut worst_c: f64 = 0.0;
        for (p, t) in a.poses.iter().zip(&b.poses) {
            worst_rot = worst_rot.max(
                p.cam_from_world
                    .rotation
                    .angle_to(&t.cam_from_world.rotation)
                    .to_degrees(),
            );
            let c = p.cam_from_world.inverse().translation.vector
                - t.cam_from_world.inverse().translation.vector;
            worst_c = worst_c.max(c.norm());
        }
        (worst_rot, worst_c)
    };
    let (rot_truth, c_truth) = pose_err(&problem, &scene.truth);
    let (rot_opt, c_opt) = pose_err(&problem, &optimum);
    let (rot_opt_truth, c_opt_truth) = pose_err(&optimum, &scene.truth);
    eprintln!(
        "BA 10 kf / 2000 pts / 8000 obs: RMSE start {rmse_start:.2} px -> final {:.4} px on inliers, {rmse_all:.4} px on all \
         (at truth {rmse_truth:.4} px on all; optimum on the same inliers {rmse_opt:.4} px), {iters} iterations ({} + {:?}), {} outliers, \
         total {:.1} ms ({:.2} ms/iteration); worst pose error vs truth {rot_truth:.4} deg / {:.2} mm \
         (optimum vs truth {rot_opt_truth:.4} deg / {:.2} mm), vs optimum {rot_opt:.5} deg / {:.3} mm",
        rep.final_rmse_px,
        rep.first_pass.iterations,
        rep.second_pass.map(|s| s.iterations),
        rep.n_outliers,
        dt * 1e3,
        dt * 1e3 / iters as f64,
        c_truth * 1e3,
        c_opt_truth * 1e3,
        c_opt * 1e3,
    );
    assert!(
        rmse_start > 15.0,
        "perturbation too small to mean anything: {rmse_start}"
    );
    // Least squares with 16000 residuals and 6048 unknowns leaves
    // σ·√(1 - 6048/16000) ≈ 0.79 px: the fit must reach the optimum's RMSE
    // (over all observations) and that is below the RMSE at the truth.
    assert!(
        rep.final_rmse_px < rmse_opt * 1.001 + 1e-4,
        "{} vs optimum {rmse_opt}",
        rep.final_rmse_px
    );
    assert!(rmse_all < rmse_truth);
    assert!(rep.final_rmse_px > 0.6 && rep.final_rmse_px < 1.0);
    // 2-DoF chi2 above 5.991 happens to 5 % of Gaussian residuals at the truth.
    assert!(
        rep.n_outliers < 400,
        "{} outliers with Gaussian noise only",
        rep.n_outliers
    );
    // Same optimum as the run started at the truth.
    assert!(
        rot_opt < 0.01 && c_opt < 0.003,
        "{rot_opt} deg, {c_opt} m from the optimum"
    );
}

#[test]
fn local_ba_reports_gross_outliers() {
    let scene = ba_scene(5, 6, 400, 4, 1.0, 0.3, 0.03, 0.05);
    let mut problem = scene.perturbed.clone();
    let mut bad = Vec::new();
    for (k, o) in problem.observations.iter_mut().enumerate() {
        if k % 37 == 5 {
            o.uv.x += 30.0;
            o.uv.y -= 25.0;
            bad.push(k);
        }
    }
    let rep = local_bundle_adjustment(&mut problem, &BaParams::default()).unwrap();
    for &k in &bad {
        assert!(rep.outliers[k], "gross outlier {k} not reported");
    }
    let n = problem.observations.len();
    assert!(
        rep.n_outliers < bad.len() + n / 20,
        "{} reported for {} injected",
        rep.n_outliers,
        bad.len()
    );
    assert!(rep.final_rmse_px < 1.0, "{}", rep.final_rmse_px);
}

#[test]
fn plain_lm_with_cauchy_also_converges() {
    let scene = ba_scene(8, 5, 300, 3, 0.5, 0.3, 0.03, 0.05);
    let rmse_truth = reprojection_rmse(&scene.truth, None);
    let mut problem = scene.perturbed.clone();
    let s = bundle_adjust_lm(
        &mut problem,
        RobustKernel::Cauchy { c: 3.0 },
        &LmParams {
            max_iterations: 50,
            ..LmParams::default()
        },
    )
    .unwrap();
    let rmse = reprojection_rmse(&problem, None);
    assert!(rmse < rmse_truth * 1.01, "{rmse} vs {rmse_truth} ({s:?})");
}

#[test]
fn bad_input_is_refused() {
    let scene = ba_scene(1, 4, 50, 3, 1.0, 0.1, 0.01, 0.01);
    let mut p = scene.perturbed.clone();
    p.observations.push(Observation {
        pose: 9,
        point: 0,
        uv: p.observations[0].uv,
        inv_sigma2: 1.0,
    });
    assert!(matches!(
        local_bundle_adjustment(&mut p, &BaParams::default()),
        Err(OptimizeError::IndexOutOfRange {
            what: "pose",
            index: 9,
            ..
        })
    ));
    let mut p = scene.perturbed.clone();
    p.points[3].x = f64::NAN;
    assert!(matches!(
        local_bundle_adjustment(&mut p, &BaParams::default()),
        Err(OptimizeError::InvalidInput {
            what: "point",
            index: 3
        })
    ));
}
