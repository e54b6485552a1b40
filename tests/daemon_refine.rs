//! The daemon's own refinement loop, end to end with the simulator
//! in-process: a shot by anchors is localised, its mission uploaded and
//! started over the API; the daemon watches the telemetry for the arrival,
//! measures the shot error on the live video, corrects and re-uploads,
//! and records each round on the shot until the loop stops.

mod daemon_support;

use daemon_support::{free_tcp_port, free_udp_port, get_json, http, request};

use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use shotpilot::config::Config;
use tokio_util::sync::CancellationToken;

fn post_jpeg(addr: SocketAddr, path: &str, jpeg: &[u8]) -> (u16, Vec<u8>) {
    request(addr, "POST", path, "image/jpeg", jpeg)
}

/// Uploads and starts the shot's mission, then waits for the daemon's
/// loop to stop; returns the recorded refinement and the seconds it took.
fn refine(addr: SocketAddr, sid: &str) -> (Value, f64) {
    let (st, b) = http(addr, "POST", &format!("/api/v1/shots/{sid}/mission"), None);
    assert_eq!(st, 200, "{}", String::from_utf8_lossy(&b));
    let (st, b) = http(addr, "POST", &format!("/api/v1/shots/{sid}/start"), None);
    assert_eq!(st, 200, "{}", String::from_utf8_lossy(&b));
    let t_start = Instant::now();
    let mut refinement = Value::Null;
    while t_start.elapsed() < Duration::from_secs(200) {
        let shot = get_json(addr, &format!("/api/v1/shots/{sid}"));
        refinement = shot["mission"]["details"]["refinement"].clone();
        if !refinement["stop"].is_null() {
            break;
        }
        std::thread::sleep(Duration::from_millis(500));
    }
    let loop_s = t_start.elapsed().as_secs_f64();
    eprintln!("shot {sid}: refinement after {loop_s:.1} s");
    for r in refinement["rounds"].as_array().into_iter().flatten() {
        eprintln!(
            "  round {} shot error {} % ({} px, {} inliers) -> {}, step {}",
            r["round"],
            r["shot_error_pct"],
            r["shot_error_px"],
            r["inliers"],
            r["decision"],
            r["correction"]["step_ned_m"]
        );
    }
    eprintln!("  stop: {} ({})", refinement["stop"], refinement["reason"]);
    check_rounds(&refinement);
    (refinement, loop_s)
}

/// Every round measured the shot error, the loop ended for one of the
/// session's reasons, rounds before the last carry a correction.
fn check_rounds(refinement: &Value) {
    let rounds = refinement["rounds"].as_array().expect("rounds recorded");
    assert!(!rounds.is_empty(), "{refinement}");
    for r in rounds {
        let pct = r["shot_error_pct"].as_f64();
        assert!(
            pct.is_some_and(|p| p.is_finite() && (0.0..100.0).contains(&p)),
            "round without a shot error: {r}"
        );
        assert!(r["shot_error_px"].as_f64().is_some_and(|p| p >= 0.0), "{r}");
    }
    let stop = refinement["stop"].as_str().unwrap_or("");
    assert!(
        [
            "converged",
            "max_rounds",
            "live_not_localised",
            "correction_refused"
        ]
        .contains(&stop),
        "{refinement}"
    );
    for r in &rounds[..rounds.len() - 1] {
        assert_eq!(r["decision"], "correct", "{r}");
        assert!(r["correction"].is_object(), "{r}");
    }
    if stop == "converged" {
        let last = rounds.last().unwrap()["shot_error_pct"].as_f64().unwrap();
        assert!(last <= 1.0, "{refinement}");
    }
}

#[test]
fn started_mission_is_refined_by_the_daemon() {
    let dir = tempfile::tempdir().unwrap();
    let video_port = free_tcp_port();
    let mav_port = free_udp_port();
    let mut cfg = Config::default();
    cfg.sim.video_listen = format!("127.0.0.1:{video_port}");
    cfg.video.url = format!("http://127.0.0.1:{video_port}/video.mjpg");
    cfg.sim.mavlink = format!("udpout:127.0.0.1:{mav_port}");
    cfg.link.url = format!("udpin:127.0.0.1:{mav_port}");
    cfg.server.bind = "127.0.0.1:0".into();
    cfg.server.token = Some("e2e".into());
    cfg.validate(Path::new("test")).unwrap();

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let cancel = CancellationToken::new();
    let (tx, rx) = tokio::sync::oneshot::channel();
    let base = dir.path().to_owned();
    let c = cancel.clone();
    let daemon = rt.spawn(async move { shotpilot::daemon::run(cfg, &base, c, Some(tx)).await });
    let addr = rt.block_on(rx).expect("the daemon starts").api_addr;
    let t0 = Instant::now();

    // Tracking, then the georeference.
    let mut geo = Value::Null;
    let mut photos = Vec::new();
    while t0.elapsed() < Duration::from_secs(90) {
        let status = get_json(addr, "/api/v1/status");
        if status["slam"]["state"] == "tracking" {
            let (st, jpeg) = http(addr, "GET", "/api/v1/snapshot.jpg", None);
            if st == 200 {
                photos.push(jpeg);
            }
        }
        geo = status["vehicle"]["georeference"].clone();
        if status["slam"]["state"] == "tracking"
            && status["slam"]["keyframes"].as_u64().unwrap_or(0) >= 5
            && geo["state"] == "ok"
        {
            break;
        }
        std::thread::sleep(Duration::from_millis(500));
    }
    eprintln!(
        "georeferenced after {:.1} s: {geo}",
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(geo["state"], "ok", "{geo}");

    // A shot by anchors on one of the newest keyframes, localised.
    let kfs = get_json(addr, "/api/v1/keyframes");
    let ids: Vec<u64> = kfs["keyframes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|k| k["id"].as_u64().unwrap())
        .collect();
    let mut sid = None;
    for &kid in ids.iter().rev().take(6) {
        let shot = json!({"keyframe_id": kid, "anchors": [[40, 30], [600, 30], [600, 450], [40, 450]], "width": 320, "height": 240});
        let (st, b) = http(addr, "POST", "/api/v1/shots", Some(&shot));
        assert_eq!(st, 201, "{}", String::from_utf8_lossy(&b));
        let shot: Value = serde_json::from_slice(&b).unwrap();
        if shot["status"] == "localised" {
            sid = Some(shot["id"].as_str().unwrap().to_owned());
            break;
        }
    }
    let sid = sid.expect("a shot by anchors is localised");
    photos.reverse();

    // Upload and start: the daemon's loop takes over.
    let (anchors, _) = refine(addr, &sid);
    let first = anchors["rounds"][0]["shot_error_pct"].as_f64().unwrap();
    assert!(first > 0.0);

    // A photograph the camera took during the exploration: a view that can
    // be reproduced exactly (an anchors shot is a zoom, which no camera
    // position reproduces without parallax).
    let mut photo_sid = None;
    for jpeg in &photos {
        let (st, b) = post_jpeg(addr, "/api/v1/shots/photo", jpeg);
        assert_eq!(st, 201, "{}", String::from_utf8_lossy(&b));
        let shot: Value = serde_json::from_slice(&b).unwrap();
        if shot["status"] == "localised" {
            photo_sid = Some(shot["id"].as_str().unwrap().to_owned());
            break;
        }
    }
    let photo_sid = photo_sid.expect("a photograph is localised");
    let (photo, _) = refine(addr, &photo_sid);
    let rounds = photo["rounds"].as_array().unwrap();
    let last = rounds.last().unwrap()["shot_error_pct"].as_f64().unwrap();
    eprintln!(
        "photo shot: first {} %, last {last} %",
        rounds[0]["shot_error_pct"]
    );
    // A reproducible view ends under the threshold (1 % of the diagonal).
    assert_eq!(photo["stop"], "converged", "{photo}");
    assert!(last <= 1.0, "{photo}");

    // Another shot's upload cancels a running loop: the anchors shot again,
    // interrupted after its first round by the photograph's mission.
    let (st, b) = http(addr, "POST", &format!("/api/v1/shots/{sid}/mission"), None);
    assert_eq!(st, 200, "{}", String::from_utf8_lossy(&b));
    let (st, b) = http(addr, "POST", &format!("/api/v1/shots/{sid}/start"), None);
    assert_eq!(st, 200, "{}", String::from_utf8_lossy(&b));
    let t1 = Instant::now();
    let mut r = Value::Null;
    while t1.elapsed() < Duration::from_secs(60) {
        r = get_json(addr, &format!("/api/v1/shots/{sid}"))["mission"]["details"]["refinement"]
            .clone();
        if r["rounds"].as_array().is_some_and(|a| !a.is_empty()) || !r["stop"].is_null() {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    assert!(r["stop"].is_null(), "the loop goes on after one round: {r}");
    let (st, b) = http(
        addr,
        "POST",
        &format!("/api/v1/shots/{photo_sid}/mission"),
        None,
    );
    assert_eq!(st, 200, "{}", String::from_utf8_lossy(&b));
    let t2 = Instant::now();
    while t2.elapsed() < Duration::from_secs(10) {
        r = get_json(addr, &format!("/api/v1/shots/{sid}"))["mission"]["details"]["refinement"]
            .clone();
        if !r["stop"].is_null() {
            break;
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    eprintln!("interrupted: stop {} ({})", r["stop"], r["reason"]);
    assert_eq!(r["stop"], "aborted", "{r}");
    assert_eq!(r["reason"], "cancelled", "{r}");

    cancel.cancel();
    rt.block_on(async { tokio::time::timeout(Duration::from_secs(30), daemon).await })
        .expect("the daemon stops")
        .unwrap()
        .unwrap();
    eprintln!("total {:.1} s", t0.elapsed().as_secs_f64());
}
