//! Criterion benches of `geo`: the map → NED fit (300 keyframes, 20 %
//! outliers, orientations and velocities; cold and after one added
//! keyframe) and the per-frame telemetry lookup + camera pose.

use std::hint::black_box;

use criterion::{Criterion, criterion_group, criterion_main};
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use shotpilot::geo::{
    AlignParams, Georeference, GimbalAngles, HistoryParams, MountParams, TelemetryHistory,
    ned_from_cam,
};
use shotpilot::geometry::Sim3;

fn filled_georeference(n: usize) -> Georeference {
    let mut rng = SmallRng::seed_from_u64(1);
    let truth = Sim3::new(
        UnitQuaternion::from_euler_angles(0.4, -0.7, 2.6),
        Vector3::new(12.0, -30.0, -25.0),
        12.3,
    );
    let inv = truth.inverse();
    let mut geo = Georeference::new(AlignParams::default());
    for i in 0..n {
        let u = i as f64 / n as f64;
        let lane = (u * 6.0).floor();
        let along = (u * 6.0).fract() * 60.0;
        let p = Point3::new(along - 30.0, lane * 8.0 - 20.0, -15.0 - 10.0 * u);
        let mut p_map = inv.transform_point(&p);
        if i % 5 == 2 {
            p_map += inv.transform_vector(&Vector3::new(rng.random_range(3.0..20.0), 0.0, 0.0));
        }
        let rot = UnitQuaternion::from_euler_angles(0.0, -0.5, i as f64 * 0.1);
        let noisy = p + Vector3::new(
            rng.random_range(-0.05..0.05),
            rng.random_range(-0.05..0.05),
            rng.random_range(-0.05..0.05),
        );
        geo.add_keyframe(
            i as u64,
            &Isometry3::from_parts(Translation3::from(p_map.coords), inv.rotation * rot),
            &Isometry3::from_parts(Translation3::from(noisy.coords), rot),
            Some(Vector3::new(
                if lane as i64 % 2 == 0 { 4.0 } else { -4.0 },
                0.0,
                0.0,
            )),
            i as f64,
        )
        .unwrap();
    }
    geo
}

fn bench_fit(c: &mut Criterion) {
    let geo = filled_georeference(300);
    c.bench_function("geo_fit_cold_300kf_20pct_outliers", |b| {
        b.iter(|| black_box(geo.clone()).fit())
    });
    let mut warm = geo.clone();
    warm.fit().unwrap();
    let extra = *warm.pairs().last().unwrap();
    c.bench_function("geo_fit_after_one_new_keyframe_300kf", |b| {
        b.iter(|| {
            let mut g = warm.clone();
            g.add_pair(10_000, extra.p_map, extra.p_ned, extra.time)
                .unwrap();
            g.fit()
        })
    });
}

fn bench_lookup(c: &mut Criterion) {
    let mut h = TelemetryHistory::new(HistoryParams::default());
    for i in 0..4000 {
        let t = i as f64 * 0.1;
        h.push_position_ned(t, Vector3::new(t, 0.5 * t, -10.0))
            .unwrap();
        h.push_attitude_euler(t, 0.02, -0.05, 0.01 * t).unwrap();
        h.push_gimbal(
            t,
            GimbalAngles {
                pitch: -0.5,
                yaw: 0.0,
            },
        )
        .unwrap();
    }
    let mount = MountParams::default();
    c.bench_function("geo_lookup_and_camera_pose_4096_samples", |b| {
        let mut t = 10.0;
        b.iter(|| {
            t = if t > 390.0 { 10.0 } else { t + 0.0731 };
            let s = h.lookup(black_box(t)).unwrap();
            ned_from_cam(&s, &mount)
        })
    });
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(2));
    targets = bench_fit, bench_lookup
}
criterion_main!(benches);
