//! Desired-shot hot path: the perspective warp of a 640x480 keyframe
//! (inverse mapping, bilinear) and the anchor checks + 4-point solve.

use criterion::{Criterion, criterion_group, criterion_main};
use image::{GrayImage, Luma};
use nalgebra::Point2;
use std::hint::black_box;

use shotpilot::shot::{AnchorParams, desired_shot_from_anchors, homography_from_anchors};

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

criterion_group!(benches, bench_shot);
criterion_main!(benches);
