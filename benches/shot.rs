//! Desired-shot hot path: the perspective warp of a 640x480 keyframe
//! (inverse mapping, bilinear) and the anchor checks + 4-point solve; and
//! the servo's per-frame shot error on two teddy frames (needs
//! `../shared/data` or `SHOTPILOT_DATA`, else a synthetic texture), with the
//! desired picture's features extracted each frame (as before) against
//! kept once per servo with the extractor's buffers (`ShotErrorMeter`): the
//! ratio of the two is the saving.

use criterion::{Criterion, criterion_group, criterion_main};
use image::{GrayImage, Luma};
use nalgebra::Point2;
use std::hint::black_box;

use shotpilot::refine::{ShotErrorMeter, ShotErrorParams, shot_error};
use shotpilot::shot::{AnchorParams, desired_shot_from_anchors, homography_from_anchors};

/// Two teddy frames half a second apart (the desired picture and a live
/// frame), or a synthetic texture and its shift.
fn pair() -> (GrayImage, GrayImage) {
    let dir = std::env::var_os("SHOTPILOT_DATA")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|| {
            std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data")
        })
        .join("tum_fr3_teddy_100");
    match shotpilot::features_eval::load_dataset_gray(&dir) {
        Ok(f) if f.len() > 15 => (f[0].clone(), f[15].clone()),
        _ => {
            eprintln!(
                "no teddy frames under {}: a synthetic texture instead",
                dir.display()
            );
            let tex = |dx: u32| {
                GrayImage::from_fn(640, 480, move |x, y| {
                    let x = x + dx;
                    Luma([(((x * 7919 + y * 104729) ^ (x * y)) % 251) as u8])
                })
            };
            (tex(0), tex(6))
        }
    }
}

fn bench_shot(c: &mut Criterion) {
    let img = GrayImage::from_fn(640, 480, |x, y| Luma([((x * 7 + y * 13) % 251) as u8]));
    let anchors = [
        Point2::new(40.0, 25.0),
        Point2::new(610.0, 5.0),
        Point2::new(630.0, 470.0),
        Point2::new(15.0, 455.0),
    ];
    let params = AnchorParams::default();
    c.bench_function("shot/anchors_homography", |b| {
        b.iter(|| homography_from_anchors(640, 480, black_box(&anchors), &params))
    });
    c.bench_function("shot/desired_shot_640x480", |b| {
        b.iter(|| desired_shot_from_anchors(black_box(&img), black_box(&anchors), &params))
    });
}

fn bench_servo_error(c: &mut Criterion) {
    let (desired, live) = pair();
    let params = ShotErrorParams::default();
    let mut group = c.benchmark_group("servo_shot_error");
    group.sample_size(20);
    group.bench_function("desired_extracted_each_frame", |b| {
        b.iter(|| shot_error(black_box(&live), &desired, None, None, &params).ok())
    });
    let mut kept = match ShotErrorMeter::new(&desired, None, None, &params) {
        Ok(k) => k,
        Err(e) => panic!("the desired picture's features: {e}"),
    };
    group.bench_function("desired_kept", |b| {
        b.iter(|| kept.measure(black_box(&live)).ok())
    });
    group.finish();
}

criterion_group!(benches, bench_shot, bench_servo_error);
criterion_main!(benches);
