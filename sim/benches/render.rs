//! Renderer throughput at 640x480 on one thread, for typical views of the
//! default world: a low oblique street view, the explore flight's mid
//! altitude, a high top-down view; plus JPEG encoding of a frame.

use std::hint::black_box;
use std::sync::Arc;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use nalgebra::Point3;
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, camera_from_yaw_pitch, look_at};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::video::encode_jpeg;
use shotpilot_sim::world::World;

fn bench(c: &mut Criterion) {
    let world = Arc::new(World::generate(1));
    let explore = CameraPath::explore(&world, PathParams::default());
    let renderer = Renderer::new(world, SimCamera::default(), RenderParams::default());
    let views = [
        (
            "oblique_15m",
            look_at(Point3::new(-30.0, 10.0, -15.0), Point3::new(0.0, 0.0, 0.0)),
        ),
        ("explore_t30", explore.world_from_cam(30.0)),
        ("explore_t60", explore.world_from_cam(60.0)),
        (
            "top_down_60m",
            camera_from_yaw_pitch(Point3::new(0.0, 0.0, -60.0), 0.2, 90f64.to_radians()),
        ),
    ];
    let mut g = c.benchmark_group("render_640x480");
    g.throughput(Throughput::Elements(1));
    g.sample_size(20);
    let mut img = image::GrayImage::new(640, 480);
    for (name, pose) in &views {
        g.bench_function(*name, |b| {
            b.iter(|| renderer.render_into(black_box(pose), Some(3), &mut img))
        });
    }
    g.finish();
    let frame = renderer.render_noisy(&views[1].1, 1);
    c.bench_function("encode_jpeg_640x480_q85", |b| {
        b.iter(|| encode_jpeg(black_box(&frame), 85))
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
