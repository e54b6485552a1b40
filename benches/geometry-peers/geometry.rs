//! Criterion benches of the geometry hot paths: PnP-RANSAC (200 points,
//! 50 % outliers, 1 px noise) and two-view initialisation (400 matches,
//! 10 % outliers), plus the small kernels they are built from. PnP-RANSAC is
//! compared in the same run with kornia-3d 0.1.14's `solve_pnp_ransac`
//! (EPnP on 5-point samples, f32, LM refinement) given the same threshold
//! and iteration cap; a one-off accuracy table over 20 scenes is printed
//! first.

#[path = "../../tests/suite/geometry_support/mod.rs"]
mod geometry_support;

use std::hint::black_box;
use std::time::Instant;

use criterion::{Criterion, criterion_group, criterion_main};
use geometry_support::{CAM_720P, CX, CY, F, motion, pnp_scene, two_view_scene};
use kornia_3d::pnp::{PnPMethod, RansacParams, solve_pnp_ransac as kornia_pnp_ransac};
use kornia_algebra::{Mat3AF32, Vec2F32, Vec3AF32};
use nalgebra::{Matrix3, Point2, Rotation3, UnitQuaternion, Vector3};
use shotpilot::geometry::pnp::{epnp, p3p_lambda_twist};
use shotpilot::geometry::{
    PnpParams, TwoViewParams, homography_from_4, initialize_two_view, solve_pnp_ransac,
};

fn kornia_inputs(s: &geometry_support::PnpScene) -> (Vec<Vec3AF32>, Vec<Vec2F32>, Mat3AF32) {
    let cam = CAM_720P;
    let w =
        s.pw.iter()
            .map(|p| Vec3AF32::new(p.x as f32, p.y as f32, p.z as f32))
            .collect();
    let i =
        s.xn.iter()
            .map(|x| {
                Vec2F32::new(
                    (x.x * cam.f + cam.w / 2.0) as f32,
                    (x.y * cam.f + cam.h / 2.0) as f32,
                )
            })
            .collect();
    let k = Mat3AF32::from_cols(
        Vec3AF32::new(cam.f as f32, 0.0, 0.0),
        Vec3AF32::new(0.0, cam.f as f32, 0.0),
        Vec3AF32::new((cam.w / 2.0) as f32, (cam.h / 2.0) as f32, 1.0),
    );
    (w, i, k)
}

fn kornia_params() -> RansacParams {
    RansacParams {
        max_iterations: 1000,
        reproj_threshold_px: 5.991f32.sqrt(),
        confidence: 0.9999,
        random_seed: Some(7),
        refine: true,
    }
}

fn kornia_rot_err(r: &Mat3AF32, truth: &nalgebra::Isometry3<f64>) -> f64 {
    let m = Matrix3::new(
        r.col(0).x as f64,
        r.col(1).x as f64,
        r.col(2).x as f64,
        r.col(0).y as f64,
        r.col(1).y as f64,
        r.col(2).y as f64,
        r.col(0).z as f64,
        r.col(1).z as f64,
        r.col(2).z as f64,
    );
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m));
    q.angle_to(&truth.rotation).to_degrees()
}

/// One-off accuracy and time table, ours against kornia-3d, 20 scenes.
fn pnp_report() {
    let params = PnpParams::default();
    let (mut ours_err, mut k_err, mut ours_t, mut k_t) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut k_fail = 0;
    for seed in 0..20u64 {
        let s = pnp_scene(seed, 200, 0.5, 1.0, CAM_720P);
        let t0 = Instant::now();
        let r = solve_pnp_ransac(&s.pw, &s.xn, CAM_720P.f, &params, 7);
        ours_t.push(t0.elapsed().as_secs_f64() * 1e3);
        if let Ok(r) = r {
            ours_err.push(
                r.cam_from_world
                    .rotation
                    .angle_to(&s.truth.rotation)
                    .to_degrees(),
            );
        }
        let (w, i, k) = kornia_inputs(&s);
        let t0 = Instant::now();
        let r = kornia_pnp_ransac(&w, &i, &k, None, PnPMethod::EPnPDefault, &kornia_params());
        k_t.push(t0.elapsed().as_secs_f64() * 1e3);
        match r {
            Ok(r) => k_err.push(kornia_rot_err(&r.pose.rotation, &s.truth)),
            Err(_) => k_fail += 1,
        }
    }
    let med = |v: &mut Vec<f64>| {
        v.sort_by(f64::total_cmp);
        if v.is_empty() {
            f64::NAN
        } else {
            v[v.len() / 2]
        }
    };
    let max = |v: &Vec<f64>| v.iter().copied().fold(0.0, f64::max);
    let (mo, mk) = (med(&mut ours_t), med(&mut k_t));
    eprintln!(
        "PnP-RANSAC 200 pts / 50 % outliers / 1 px, 20 scenes: ours median {mo:.3} ms, rot err median {:.4} max {:.4} deg; \
         kornia-3d median {mk:.3} ms, rot err median {:.4} max {:.4} deg, {k_fail} failures; time ratio kornia/ours {:.2}",
        med(&mut ours_err.clone()),
        max(&ours_err),
        med(&mut k_err.clone()),
        max(&k_err),
        mk / mo
    );
}

fn bench_pnp(c: &mut Criterion) {
    pnp_report();
    let s = pnp_scene(3, 200, 0.5, 1.0, CAM_720P);
    let params = PnpParams::default();
    c.bench_function("pnp_ransac_200pts_50pct_outliers", |b| {
        b.iter(|| solve_pnp_ransac(black_box(&s.pw), black_box(&s.xn), CAM_720P.f, &params, 7))
    });
    let (w, i, k) = kornia_inputs(&s);
    let kp = kornia_params();
    c.bench_function("kornia3d_pnp_ransac_200pts_50pct_outliers", |b| {
        b.iter(|| {
            kornia_pnp_ransac(
                black_box(&w),
                black_box(&i),
                &k,
                None,
                PnPMethod::EPnPDefault,
                &kp,
            )
            .is_ok()
        })
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
        motion([1.6, 0.1, 0.3], [0.02, -0.08, 0.01]),
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
