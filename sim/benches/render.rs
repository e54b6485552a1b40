//! Renderer throughput at 640x480 on one thread, for typical views of the
//! default world: a close oblique view, two explore-flight poses and a high
//! top-down view; plus JPEG encoding of a frame.
//!
//! A third group, `capture_640x480_cpu`, exposes consecutive explore-flight
//! frames (15 frames/s) through the realistic camera
//! ([`shotpilot_sim::imaging::Imager`]) for the presets `ideal`, `field`
//! and `harsh`, in CPU time: what realism costs per frame against `ideal`.
//!
//! Two groups: `render_640x480` in wall-clock time (criterion's default)
//! and `render_640x480_cpu` in CPU time of the benchmarking thread (Linux
//! `/proc/thread-self/schedstat`), which is what "frames per second on one
//! core" means on a machine shared with other jobs, where wall-clock time
//! includes waiting for the CPU.

use std::hint::black_box;
use std::sync::Arc;

use criterion::measurement::{Measurement, ValueFormatter};
use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use nalgebra::{Isometry3, Point3};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::dataset::{PathMotion, renderer_for, world_params_for};
use shotpilot_sim::imaging::Imager;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, camera_from_yaw_pitch, look_at};
use shotpilot_sim::realism::Realism;
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::video::encode_jpeg;
use shotpilot_sim::world::World;
use shotpilot_sim::world::WorldKind;

/// CPU time of the calling thread, nanoseconds (0 where unavailable).
fn thread_cpu_ns() -> u64 {
    std::fs::read_to_string("/proc/thread-self/schedstat")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or(0)
}

/// Criterion measurement: CPU time of the benchmarking thread.
struct ThreadCpuTime;

/// Formats nanoseconds as ms (or µs) and throughput as elements/s.
struct CpuFormatter;

impl ValueFormatter for CpuFormatter {
    fn scale_values(&self, typical: f64, values: &mut [f64]) -> &'static str {
        let (div, unit) = if typical >= 1e6 {
            (1e6, "ms cpu")
        } else {
            (1e3, "µs cpu")
        };
        values.iter_mut().for_each(|v| *v /= div);
        unit
    }

    fn scale_throughputs(
        &self,
        _typical: f64,
        throughput: &Throughput,
        values: &mut [f64],
    ) -> &'static str {
        let per = match throughput {
            Throughput::Elements(n) | Throughput::Bytes(n) | Throughput::BytesDecimal(n) => {
                *n as f64
            }
            _ => 1.0,
        };
        values.iter_mut().for_each(|v| *v = per * 1e9 / *v);
        "elem/s (cpu)"
    }

    fn scale_for_machines(&self, _values: &mut [f64]) -> &'static str {
        "ns"
    }
}

impl Measurement for ThreadCpuTime {
    type Intermediate = u64;
    type Value = u64;

    fn start(&self) -> u64 {
        thread_cpu_ns()
    }

    fn end(&self, i: u64) -> u64 {
        thread_cpu_ns().saturating_sub(i)
    }

    fn add(&self, a: &u64, b: &u64) -> u64 {
        a + b
    }

    fn zero(&self) -> u64 {
        0
    }

    fn to_f64(&self, v: &u64) -> f64 {
        *v as f64
    }

    fn formatter(&self) -> &dyn ValueFormatter {
        &CpuFormatter
    }
}

fn setup() -> (Renderer, Vec<(&'static str, Isometry3<f64>)>) {
    let world = Arc::new(World::generate(1));
    let explore = CameraPath::explore(&world, PathParams::default());
    let renderer = Renderer::new(world, SimCamera::default(), RenderParams::default());
    let views = vec![
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
    (renderer, views)
}

fn bench_wall(c: &mut Criterion) {
    let (renderer, views) = setup();
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

fn bench_cpu(c: &mut Criterion<ThreadCpuTime>) {
    let (renderer, views) = setup();
    let mut g = c.benchmark_group("render_640x480_cpu");
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
    c.bench_function("encode_jpeg_640x480_q85_cpu", |b| {
        b.iter(|| encode_jpeg(black_box(&frame), 85))
    });
}

fn bench_capture(c: &mut Criterion<ThreadCpuTime>) {
    let mut g = c.benchmark_group("capture_640x480_cpu");
    g.throughput(Throughput::Elements(1));
    g.sample_size(20);
    for name in ["ideal", "field", "harsh"] {
        let realism = Realism::preset(name).expect("preset");
        let params = world_params_for(WorldKind::Town, &realism);
        let world = Arc::new(World::generate_with(1, &params).expect("world"));
        let path = CameraPath::explore(&world, PathParams::default());
        let renderer = Arc::new(renderer_for(
            world,
            SimCamera::default(),
            RenderParams::default(),
            &realism,
            1,
        ));
        let motion = PathMotion::new(&path, &realism, 1);
        let mut imager = Imager::new(renderer, realism.camera.clone(), &realism.lighting);
        let mut k = 0u64;
        g.bench_function(name, |b| {
            b.iter(|| {
                // Consecutive frames of the flight's busy middle.
                let t = 20.0 + (k % 600) as f64 / 15.0;
                k += 1;
                imager
                    .capture(t, &|s| motion.world_from_cam(&path, s), Some(k))
                    .expect("capture")
            })
        });
    }
    g.finish();
}

criterion_group!(wall, bench_wall);
criterion_group! {
    name = capture;
    config = Criterion::default().with_measurement(ThreadCpuTime);
    targets = bench_capture
}
criterion_group! {
    name = cpu;
    config = Criterion::default().with_measurement(ThreadCpuTime);
    targets = bench_cpu
}
criterion_main!(wall, cpu, capture);
