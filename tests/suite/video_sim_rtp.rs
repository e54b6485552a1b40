//! The simulator's H.264 RTP output (`shotpilot_sim::rtp`, its own
//! encoder, packetiser and RTCP) received by the daemon's raw RTP source
//! (`shotpilot::video::udp`, its own depacketiser and RTP clock): two
//! independent implementations of RFC 6184 / RFC 3550 checking each other.
//!
//! Rendered pictures go out at 15 frames/s; every picture must arrive
//! (loopback loses nothing), decode close to what was rendered, and carry
//! the capture time it was sent with once the first sender report is in.
//! The SDP the simulator writes is read back by the daemon's SDP parser.

use std::sync::Arc;
use std::time::{Duration, Instant};

use image::GrayImage;
use shotpilot::config::VideoConfig;
use shotpilot::video::live::{Ingest, unix_now};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::rtp::{H264Encoder, RtpOutParams, RtpSender, sdp};
use shotpilot_sim::world::World;
use tokio_util::sync::CancellationToken;

fn psnr(a: &GrayImage, b: &GrayImage) -> f64 {
    let mse = a
        .as_raw()
        .iter()
        .zip(b.as_raw())
        .map(|(x, y)| (f64::from(*x) - f64::from(*y)).powi(2))
        .sum::<f64>()
        / a.as_raw().len() as f64;
    10.0 * (255.0f64 * 255.0 / mse.max(1e-9)).log10()
}

/// Polls `cond` every 5 ms up to `limit` (a guard against hangs).
fn poll(limit: Duration, cond: impl Fn() -> bool) -> bool {
    let t = Instant::now();
    while t.elapsed() < limit {
        if cond() {
            return true;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    cond()
}

#[test]
fn simulator_rtp_reaches_the_daemon_with_capture_times_and_quality() {
    const N: usize = 45;
    const FPS: f64 = 15.0;
    let world = Arc::new(World::generate(3));
    let path = CameraPath::explore(&world, PathParams::default());
    let renderer = Renderer::new(world, SimCamera::default(), RenderParams::default());
    let pictures: Vec<Arc<GrayImage>> = (0..N)
        .map(|i| {
            let t = path.start() + 20.0 + i as f64 / FPS;
            Arc::new(renderer.render_noisy(&path.world_from_cam(t), i as u64))
        })
        .collect();

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let cfg = VideoConfig {
        // Port 0: the source binds an RTP port the kernel picks, with its
        // RTCP port beside it, and shows it in its URL.
        url: "udp://127.0.0.1:0".into(),
        decode_queue: 64,
        ..Default::default()
    };
    let ingest = Arc::new(Ingest::new());
    let cancel = CancellationToken::new();
    let task = rt.spawn(shotpilot::video::source::run_configured(
        cfg,
        ingest.clone(),
        cancel.clone(),
        None,
    ));
    let bound = || {
        ingest
            .source_info()
            .url
            .strip_prefix("udp://")
            .and_then(|a| a.parse::<std::net::SocketAddr>().ok())
            .filter(|a| a.port() != 0)
    };
    assert!(poll(Duration::from_secs(10), || bound().is_some()));
    let port = bound().map(|a| a.port()).unwrap_or(0);
    // Every decoded frame: (decoded frame number, capture time, image).
    let mut rx = ingest.subscribe();
    let seen = rt.spawn(async move {
        let mut seen = Vec::new();
        while rx.changed().await.is_ok() {
            let f = rx.borrow_and_update().clone();
            if let Some(f) = f {
                seen.push((f.seq, f.capture_time, f.image.clone()));
            }
        }
        seen
    });

    let params = RtpOutParams {
        dest: format!("127.0.0.1:{port}").parse().unwrap(),
        ..Default::default()
    };
    let sender = RtpSender::start(params, FPS, 7).unwrap();
    // Capture times a little in the past, as a camera's are.
    let t0 = unix_now() - 0.1;
    let mut sent = Vec::new();
    for (i, pic) in pictures.iter().enumerate() {
        let t = t0 + i as f64 / FPS;
        assert!(sender.offer(pic.clone(), t), "the queue has room");
        sent.push(t);
        // One picture at a time: each is encoded and sent before the next
        // (the decoder then sees every one).
        assert!(poll(Duration::from_secs(10), || sender.stats().pictures
            > i as u64));
        assert!(poll(Duration::from_secs(10), || ingest
            .counters
            .snapshot()
            .decoded
            > i as u64));
        if i == 0 {
            // The sender reports after its first picture; the pictures
            // after it are timed by the report once the receiver has it
            // (RTCP comes on its own socket, in either order with RTP).
            assert!(poll(Duration::from_secs(10), || ingest
                .counters
                .snapshot()
                .sender_reports
                >= 1));
        }
    }
    let stats = sender.stats();
    drop(sender);
    cancel.cancel();
    rt.block_on(task).unwrap().unwrap();
    let counters = ingest.counters.snapshot();
    ingest.close();
    drop(ingest);
    let seen = rt.block_on(seen).unwrap();
    let kbit_s = stats.payload_bytes as f64 * 8.0 / (N as f64 / FPS) / 1e3;
    eprintln!(
        "sender {stats:?} ({kbit_s:.0} kbit/s); receiver {counters:?}; {} frames seen",
        seen.len()
    );
    assert_eq!(stats.pictures, N as u64);
    assert_eq!(stats.idr, 3, "an IDR picture each second");
    assert!(stats.sender_reports >= 1);
    assert_eq!(counters.lost_packets, 0);
    assert_eq!(counters.bad, 0);
    assert_eq!(counters.skipped, 0);
    assert_eq!(counters.decoded, N as u64);
    // Each frame seen is one of the pictures sent: its capture time is
    // the one it was sent with (to the 90 kHz tick) once the sender report
    // is in (it goes out after the first picture; before it, times are
    // mapped from arrival), and it decodes close to the picture.
    assert!(seen.len() >= N / 2, "{}", seen.len());
    let mut psnrs = Vec::new();
    for (k, (seq, capture, img)) in seen.iter().enumerate() {
        // Pictures go out one at a time, each decoded before the next: the
        // decoded frame number is the picture's.
        let i = *seq as usize;
        let capture = capture.expect("RTP frames carry a capture time");
        let dt = (capture - sent[i]).abs();
        if i >= 1 {
            assert!(dt < 2.0 / 90_000.0, "frame {k} (picture {i}) off by {dt} s");
        } else {
            assert!(dt < 0.5, "picture {i} (before the report) off by {dt} s");
        }
        psnrs.push((i, psnr(img, &pictures[i])));
    }
    let mean = psnrs.iter().map(|p| p.1).sum::<f64>() / psnrs.len() as f64;
    let worst = psnrs.iter().map(|p| p.1).fold(f64::INFINITY, f64::min);
    eprintln!("PSNR of the decoded pictures: mean {mean:.1} dB, worst {worst:.1} dB");
    // 1.5 Mbit/s at 640x480 and 15 frames/s: 37-40 dB measured; 30 dB is
    // where blocking starts to show.
    assert!(worst > 33.0, "{psnrs:?}");
    assert!(mean > 35.0, "{psnrs:?}");
}

#[test]
fn the_simulators_sdp_is_what_the_daemon_reads() {
    let cam = SimCamera::default();
    let params = RtpOutParams {
        dest: "127.0.0.1:5602".parse().unwrap(),
        ..Default::default()
    };
    let sets =
        H264Encoder::parameter_sets(cam.width, cam.height, 15.0, params.bitrate_bps).unwrap();
    let text = sdp(&params, 15.0, &sets);
    let v = shotpilot::video::rtp::sdp::parse(&text).unwrap();
    assert_eq!(v.port, 5602);
    assert_eq!(v.address.as_deref(), Some("127.0.0.1"));
    assert_eq!(v.payload_type, 96);
    assert_eq!(v.codec, "H264");
    assert_eq!(v.clock_rate, 90_000);
    assert_eq!(v.param_sets, sets);
    assert_eq!(v.param_sets.len(), 2);
}
