//! The live simulator with realism: `SimConfig::with_realism` moves the
//! preset's vehicle, telemetry and radio effects into the configuration,
//! and frames rendered through the realistic camera flow at the video rate
//! with their truth recorded (the pose at the centre row's mid-exposure,
//! a moment behind the clock).

use std::sync::Arc;

use shotpilot_sim::app::{SimConfig, run_with};
use shotpilot_sim::link::Endpoint;
use shotpilot_sim::realism::Realism;
use shotpilot_sim::script::ScriptKind;
use shotpilot_sim::video::VideoFrame;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

#[test]
fn with_realism_configures_vehicle_telemetry_and_radio() {
    let c = SimConfig {
        seed: 4,
        ..SimConfig::default()
    }
    .with_realism(Realism::harsh());
    let h = Realism::harsh();
    let tel = h.vehicle.telemetry.clone().unwrap();
    assert_eq!(c.autopilot.stream_intervals, tel.stream_intervals);
    assert_eq!(c.radio.up.drop, tel.drop);
    assert_eq!(c.radio.down.latency_s, tel.latency_s);
    assert_eq!(c.radio.down.baud, Some(tel.baud));
    let d = c.autopilot.vehicle.disturbances;
    assert_eq!(d.wind, h.vehicle.wind);
    assert_eq!(d.gps_dropouts, h.vehicle.gps_dropouts);
    // Ideal leaves everything as it was.
    let i = SimConfig::default().with_realism(Realism::ideal());
    let base = SimConfig::default();
    assert_eq!(i.radio, base.radio);
    assert!(i.autopilot.vehicle.disturbances.is_off());
    assert!(i.autopilot.stream_intervals.is_empty());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn realistic_frames_flow_with_their_truth() {
    let dir = tempfile::tempdir().unwrap();
    let config = SimConfig {
        // A local UDP port nobody listens on: telemetry goes nowhere.
        mavlink: Endpoint::UdpIn("127.0.0.1:0".into()),
        video_listen: None,
        script: Some(ScriptKind::Hover),
        truth_dir: Some(dir.path().to_path_buf()),
        seed: 2,
        ..SimConfig::default()
    }
    .with_realism(Realism::field());
    let (tx, mut rx) = watch::channel::<Option<Arc<VideoFrame>>>(None);
    let cancel = CancellationToken::new();
    let task = tokio::spawn(run_with(config, cancel.clone(), tx));
    let mut frames: Vec<Arc<VideoFrame>> = Vec::new();
    while frames.len() < 12 {
        rx.changed().await.expect("the simulator stopped early");
        if let Some(f) = rx.borrow_and_update().clone() {
            frames.push(f);
        }
    }
    cancel.cancel();
    let summary = task.await.unwrap().unwrap();
    assert!(summary.frames >= 12);
    // Published in order, each a decodable 640x480 JPEG.
    for w in frames.windows(2) {
        assert!(w[1].seq > w[0].seq && w[1].capture_time_unix_s > w[0].capture_time_unix_s);
    }
    for f in &frames {
        let img = image::load_from_memory(&f.jpeg).unwrap();
        assert_eq!((img.width(), img.height()), (640, 480));
    }
    // Each published frame's capture time and pose are in frames.txt.
    let text = std::fs::read_to_string(dir.path().join("frames.txt")).unwrap();
    let rows: Vec<Vec<f64>> = text
        .lines()
        .filter(|l| !l.starts_with('#'))
        .map(|l| l.split_whitespace().map(|x| x.parse().unwrap()).collect())
        .collect();
    for f in &frames {
        let row = rows
            .iter()
            .find(|r| r[0] as u64 == f.seq)
            .expect("frame in frames.txt");
        assert!((row[1] - f.capture_time_unix_s).abs() < 1e-6);
        // A camera on a hovering vehicle: finite, at the take-off spot.
        assert!(row[2].hypot(row[3]) < 5.0, "{row:?}");
    }
}
