//! PnP on synthetic scenes whose answer is known: 200 points, 1 px
//! Gaussian noise, 50 % outliers, 100 seeded trials.

mod geometry_support;

use std::time::Instant;

use geometry_support::{F, pnp_scene};

use nalgebra::{Point2, Point3};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use shotpilot::geometry::{GeometryError, PnpParams, solve_pnp_ransac};

#[test]
fn pnp_200_points_1px_50pct_outliers_100_trials() {
    let params = PnpParams::default();
    let mut ok = 0;
    let mut times = Vec::new();
    let mut worst_rot: f64 = 0.0;
    let mut worst_trans: f64 = 0.0;
    let mut rots = Vec::new();
    let mut iters = Vec::new();
    for seed in 0..100u64 {
        let t = pnp_scene(seed, 200, 0.5, 1.0);
        let start = Instant::now();
        let res = solve_pnp_ransac(&t.pw, &t.xn, F, &params, 1000 + seed);
        times.push(start.elapsed().as_secs_f64());
        let Ok(res) = res else {
            eprintln!("trial {seed}: {res:?}");
            continue;
        };
        let rot_deg = res.cam_from_world.rotation.angle_to(&t.truth.rotation).to_degrees();
        // Camera-centre error relative to the mean depth.
        let c_est = res.cam_from_world.inverse().translation.vector;
        let c_true = t.truth.inverse().translation.vector;
        let trans_rel = (c_est - c_true).norm() / t.mean_depth;
        worst_rot = worst_rot.max(rot_deg);
        worst_trans = worst_trans.max(trans_rel);
        rots.push(rot_deg);
        iters.push(res.iterations);
        // The inlier mask separates the injected outliers well.
        let wrong = res.inliers.iter().zip(&t.outlier).filter(|(i, o)| **i && **o).count();
        if rot_deg < 0.1 && trans_rel < 0.005 && wrong <= 3 {
            ok += 1;
        } else {
            eprintln!("trial {seed}: rot {rot_deg:.4} deg, trans {:.4} %, outliers kept {wrong}", trans_rel * 100.0);
        }
    }
    times.sort_by(f64::total_cmp);
    rots.sort_by(f64::total_cmp);
    iters.sort();
    eprintln!(
        "PnP: {ok}/100 within bounds; median rot err {:.4} deg, worst rot {:.4} deg, worst trans {:.4} % of mean depth; \
         median RANSAC iterations {}; median time {:.3} ms, max {:.3} ms",
        rots[rots.len() / 2],
        worst_rot,
        worst_trans * 100.0,
        iters[iters.len() / 2],
        times[50] * 1e3,
        times[99] * 1e3
    );
    assert!(ok >= 99, "only {ok}/100 trials within bounds");
}

#[test]
fn pnp_is_deterministic_for_a_seed_and_refuses_garbage() {
    let t = pnp_scene(5, 100, 0.3, 1.0);
    let a = solve_pnp_ransac(&t.pw, &t.xn, F, &PnpParams::default(), 9).unwrap();
    let b = solve_pnp_ransac(&t.pw, &t.xn, F, &PnpParams::default(), 9).unwrap();
    assert_eq!(a, b);
    // Pure noise: no consensus.
    let mut rng = SmallRng::seed_from_u64(1);
    let xn: Vec<Point2<f64>> = (0..100).map(|_| Point2::new(rng.random_range(-0.6..0.6), rng.random_range(-0.5..0.5))).collect();
    let pw: Vec<Point3<f64>> = (0..100)
        .map(|_| Point3::new(rng.random_range(-3.0..3.0), rng.random_range(-3.0..3.0), rng.random_range(4.0..9.0)))
        .collect();
    match solve_pnp_ransac(&pw, &xn, F, &PnpParams::default(), 3) {
        Err(GeometryError::TooFewInliers { found, needed: 10 }) => assert!(found < 10),
        other => panic!("{other:?}"),
    }
    assert!(matches!(
        solve_pnp_ransac(&pw[..5], &xn[..5], F, &PnpParams::default(), 3),
        Err(GeometryError::NotEnoughPoints { found: 5, needed: 10 })
    ));
    assert!(matches!(
        solve_pnp_ransac(&pw, &xn[..50], F, &PnpParams::default(), 3),
        Err(GeometryError::LengthMismatch { .. })
    ));
}
