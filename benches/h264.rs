//! H.264 decode cost, ms per frame, on the simulator's renders encoded by
//! OpenH264 at the bitrates cameras send: 1280x720 at 1.5 Mbit/s and 30 fps
//! (a SIYI A8 mini's main stream), 640x480 at 1 Mbit/s; one IDR per second.
//! Each iteration decodes one whole GOP in order to the luma plane SLAM
//! takes (what the decode thread does per picture), so the figure is
//! `time / 30`. With `ffmpeg` on the PATH, FFmpeg's H.264 decoder on the
//! same bitstream (one thread, `-benchmark` user time, to a null sink) is
//! printed beside it as the peer, with the ratio.
//!
//! `decode_loop_gop30` runs the decode thread's whole step (`DecodeLoop`:
//! decoding, damage tracking, and the vertical motion measurement that
//! follows damage) with and without the motion measurement, so the ratio
//! says what following the motion costs per frame.

use std::hint::black_box;
use std::sync::Arc;
use std::time::Instant;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use image::GrayImage;
use shotpilot::video::decode_loop::{DecodeLoop, DecodeParams, Decoded};
use shotpilot::video::h264::{AccessUnit, GrayEncoder, LumaDecoder};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::{World, WorldParams};

const GOP: usize = 30;

fn stream(w: u32, h: u32, bitrate: u32) -> Vec<Vec<u8>> {
    let world = Arc::new(World::generate_with(5, &WorldParams::small()).expect("world"));
    let path = CameraPath::explore(&world, PathParams::default());
    let cam = SimCamera::with_size(w, h);
    let r = Renderer::new(world, cam, RenderParams::default());
    let frames: Vec<GrayImage> = (0..GOP)
        .map(|i| {
            r.render_noisy(
                &path.world_from_cam(path.start() + 5.0 + i as f64 / 30.0),
                i as u64,
            )
        })
        .collect();
    let mut enc = GrayEncoder::new(w, h, 30.0, bitrate, GOP as u32).expect("encoder");
    frames
        .iter()
        .map(|f| enc.encode(f).expect("encode"))
        .collect()
}

fn decode_all(aus: &[Vec<u8>]) -> usize {
    let mut d = LumaDecoder::new().expect("decoder");
    let mut n = 0;
    for a in aus {
        if let Some(img) = d.decode(a).expect("decode") {
            n += black_box(img).width() as usize;
        }
    }
    n
}

/// FFmpeg's user time per frame on the same bitstream, ms.
fn ffmpeg_ms_per_frame(aus: &[Vec<u8>]) -> Option<f64> {
    let dir = tempfile::tempdir().ok()?;
    let f = dir.path().join("s.264");
    // Ten GOPs, so process start-up weighs little.
    let mut data = Vec::new();
    for _ in 0..10 {
        for a in aus {
            data.extend_from_slice(a);
        }
    }
    std::fs::write(&f, &data).ok()?;
    let out = std::process::Command::new("ffmpeg")
        .args([
            "-hide_banner",
            "-nostdin",
            "-threads",
            "1",
            "-benchmark",
            "-f",
            "h264",
            "-i",
        ])
        .arg(&f)
        .args(["-f", "null", "-"])
        .output()
        .ok()?;
    let err = String::from_utf8_lossy(&out.stderr);
    let utime: f64 = err
        .split("utime=")
        .nth(1)?
        .split('s')
        .next()?
        .parse()
        .ok()?;
    Some(utime * 1e3 / (10 * aus.len()) as f64)
}

fn bench_decode(c: &mut Criterion) {
    let cases = [
        ("1280x720@1.5Mbps", 1280, 720, 1_500_000),
        ("640x480@1Mbps", 640, 480, 1_000_000),
    ];
    let mut peer_lines = Vec::new();
    let mut group = c.benchmark_group("h264_decode_gop30");
    group.sample_size(20);
    for (name, w, h, bps) in cases {
        let aus = stream(w, h, bps);
        let bytes: usize = aus.iter().map(Vec::len).sum();
        eprintln!(
            "{name}: {} bytes per GOP of {GOP} ({:.2} Mbit/s at 30 fps)",
            bytes,
            bytes as f64 * 8.0 * 30.0 / GOP as f64 / 1e6
        );
        group.throughput(Throughput::Elements(GOP as u64));
        group.bench_function(name, |b| b.iter(|| decode_all(&aus)));
        if let Some(peer) = ffmpeg_ms_per_frame(&aus) {
            // Ours over the same repetition, for the ratio in this run.
            let mut times = Vec::new();
            for _ in 0..10 {
                let t = Instant::now();
                black_box(decode_all(&aus));
                times.push(t.elapsed().as_secs_f64() * 1e3 / GOP as f64);
            }
            times.sort_by(f64::total_cmp);
            let ours = times[times.len() / 2];
            peer_lines.push(format!(
                "{name}: shotpilot (OpenH264 + luma copy) {ours:.3} ms/frame, FFmpeg 1 thread {peer:.3} ms/frame, ratio {:.2}",
                ours / peer
            ));
        }
    }
    group.finish();
    for l in peer_lines {
        println!("peer: {l}");
    }
}

fn step_all(aus: &[Vec<u8>], follow_motion: bool) -> usize {
    let mut params = DecodeParams::default();
    params.damage.follow_motion = follow_motion;
    let mut dl = DecodeLoop::new(params).expect("decoder");
    let now = Instant::now();
    let mut n = 0;
    for a in aus {
        let unit = AccessUnit {
            data: a.clone(),
            capture_time: None,
            received: now,
            received_unix: 0.0,
            lost: 0,
            gaps: vec![],
        };
        if let Decoded::Frame(f) = dl.step(&unit, false) {
            n += black_box(f).image.width() as usize;
        }
    }
    n
}

fn bench_decode_loop(c: &mut Criterion) {
    let mut group = c.benchmark_group("decode_loop_gop30");
    group.sample_size(20);
    for (name, w, h, bps) in [
        ("1280x720@1.5Mbps", 1280, 720, 1_500_000),
        ("640x480@1Mbps", 640, 480, 1_000_000),
    ] {
        let aus = stream(w, h, bps);
        group.throughput(Throughput::Elements(GOP as u64));
        group.bench_function(format!("{name} motion followed"), |b| {
            b.iter(|| step_all(&aus, true))
        });
        group.bench_function(format!("{name} motion bound"), |b| {
            b.iter(|| step_all(&aus, false))
        });
    }
    group.finish();
}

criterion_group!(benches, bench_decode, bench_decode_loop);
criterion_main!(benches);
