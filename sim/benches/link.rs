//! The link's hot paths: MAVLink frame parsing from a byte stream (with and
//! without corruption), the bad radio, frame encoding, and one autopilot
//! step (controller, mission executor and telemetry streams).

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use mavlink::MavHeader;
use mavlink::dialects::common::MavMessage;
use shotpilot_sim::autopilot::{Autopilot, AutopilotParams};
use shotpilot_sim::link::{FrameParser, RadioDir, RadioDirParams, decode_frame, encode_v2};

/// One second of default telemetry, as the autopilot sends it.
fn telemetry_stream() -> Vec<u8> {
    let mut ap = Autopilot::new(AutopilotParams::default(), 0.0);
    let mut bytes = Vec::new();
    let mut seq = 0u8;
    for k in 1..=50 {
        for m in ap.step(k as f64 * 0.02, 0.02) {
            let h = MavHeader {
                system_id: 1,
                component_id: 1,
                sequence: seq,
            };
            seq = seq.wrapping_add(1);
            bytes.extend(encode_v2(h, &m));
        }
    }
    bytes
}

fn bench(c: &mut Criterion) {
    let stream = telemetry_stream();
    let n_frames = {
        let mut p = FrameParser::new();
        p.push(&stream);
        std::iter::from_fn(|| p.next_frame()).count()
    };
    let mut g = c.benchmark_group("link");
    g.throughput(Throughput::Bytes(stream.len() as u64));
    g.bench_function(format!("parse_and_decode_{n_frames}_frames"), |b| {
        b.iter(|| {
            let mut p = FrameParser::new();
            let mut n = 0;
            for chunk in stream.chunks(64) {
                p.push(chunk);
                while let Some(f) = p.next_frame() {
                    if decode_frame(black_box(&f)).is_ok() {
                        n += 1;
                    }
                }
            }
            assert_eq!(n, n_frames);
        })
    });
    // 1% of bytes corrupted: the parser resynchronises at every bad frame.
    let mut radio = RadioDir::new(
        RadioDirParams {
            corrupt: 0.01,
            ..Default::default()
        },
        5,
    );
    radio.push(0.0, stream.clone());
    let corrupted = radio.pop_ready(0.0).unwrap_or_default();
    g.bench_function("parse_with_1pct_byte_corruption", |b| {
        b.iter(|| {
            let mut p = FrameParser::new();
            p.push(black_box(&corrupted));
            std::iter::from_fn(|| p.next_frame_complete()).count()
        })
    });
    g.throughput(Throughput::Elements(n_frames as u64));
    let frames: Vec<Vec<u8>> = {
        let mut p = FrameParser::new();
        p.push(&stream);
        std::iter::from_fn(|| p.next_frame()).collect()
    };
    g.bench_function("radio_drop_corrupt_baud", |b| {
        b.iter(|| {
            let mut r = RadioDir::new(
                RadioDirParams {
                    drop: 0.3,
                    corrupt: 1e-3,
                    latency_s: 0.05,
                    baud: Some(57600),
                    max_queue_bytes: 1 << 20,
                },
                9,
            );
            for (i, f) in frames.iter().enumerate() {
                r.push(i as f64 * 0.001, f.clone());
            }
            let mut n = 0;
            while let Some(t) = r.next_due() {
                if r.pop_ready(t).is_some() {
                    n += 1;
                }
            }
            n
        })
    });
    let msgs: Vec<MavMessage> = frames
        .iter()
        .filter_map(|f| decode_frame(f).ok().map(|d| d.1))
        .collect();
    g.bench_function("encode_v2", |b| {
        b.iter(|| {
            let h = MavHeader::default();
            msgs.iter()
                .map(|m| encode_v2(h, black_box(m)).len())
                .sum::<usize>()
        })
    });
    g.finish();

    let mut ap = Autopilot::new(AutopilotParams::default(), 0.0);
    let mut t = 0.0;
    c.bench_function("autopilot_step_50hz", |b| {
        b.iter(|| {
            t += 0.02;
            black_box(ap.step(t, 0.02).len())
        })
    });
}

criterion_group!(benches, bench);
criterion_main!(benches);
