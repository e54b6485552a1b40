//! Criterion benches of the geometry hot paths: PnP-RANSAC (200 points,
//! 50 % outliers, 1 px noise) and two-view initialisation (400 matches,
//! 10 % outliers), plus the small kernels they are built from.

#[path = "../tests/geometry_support/mod.rs"]
mod geometry_support;

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use geometry_support::{CAM_720P, CX, CY, F, motion, pnp_scene, two_view_scene};
use nalgebra::{Matrix3, Point2, Vector3};
use shotpilot::geometry::pnp::{epnp, p3p_lambda_twist};
use shotpilot::geometry::{
    PnpParams, TwoViewParams, homography_from_4, initialize_two_view, solve_pnp_ransac,
};

fn bench_pnp(c: &mut Criterion) {
    let s = pnp_scene(3, 200, 0.5, 1.0, CAM_720P);
    let params = PnpParams::default();
    c.bench_function("pnp_ransac_200pts_50pct_outliers", |b| {
        b.iter(|| solve_pnp_ransac(black_box(&s.pw), black_box(&s.xn), CAM_720P.f, &params, 7))
    });
    let clean = pnp_scene(4, 200, 0.0, 1.0, CAM_720P);
    let idx: Vec<usize> = (0..200).collect();
    c.bench_function("epnp_200pts", |b| {
        b.iter(|| epnp(black_box(&clean.pw), black_box(&clean.xn), &idx))
    });
    let y: [Vector3<f64>; 3] =
        std::array::from_fn(|i| Vector3::new(clean.xn[i].x, clean.xn[i].y, 1.0).normalize());
    let x: [Vector3<f64>; 3] = std::array::from_fn(|i| clean.pw[i].coords);
    c.bench_function("p3p_lambda_twist", |b| {
        b.iter(|| p3p_lambda_twist(black_box(&y), black_box(&x)))
    });
}

fn bench_two_view(c: &mut Criterion) {
    let k = Matrix3::new(F, 0.0, CX, 0.0, F, CY, 0.0, 0.0, 1.0);
    let s = two_view_scene(
        1,
        400,
        false,
        motion([1.2, 0.1, 0.3], [0.02, -0.08, 0.01]),
        1.0,
        0.1,
    );
    let params = TwoViewParams::default();
    c.bench_function("two_view_init_400_matches", |b| {
        b.iter(|| {
            initialize_two_view(
                &k,
                black_box(&s.kp1),
                black_box(&s.kp2),
                &s.matches,
                &params,
                42,
            )
        })
    });
    let src = [
        Point2::new(10.0, 20.0),
        Point2::new(600.0, 40.0),
        Point2::new(580.0, 430.0),
        Point2::new(30.0, 460.0),
    ];
    let dst = [
        Point2::new(15.0, 22.0),
        Point2::new(590.0, 60.0),
        Point2::new(570.0, 410.0),
        Point2::new(40.0, 470.0),
    ];
    c.bench_function("homography_from_4", |b| {
        b.iter(|| homography_from_4(black_box(&src), black_box(&dst)))
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(3));
    targets = bench_pnp, bench_two_view
}
criterion_main!(benches);
