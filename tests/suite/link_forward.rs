//! Sharing the radio (`[link] forward`): a second ground station, written
//! with pymavlink (`tests/peers/gcs_peer.py`, standing where QGroundControl
//! would: system 255, component 190), connected through shotpilot's
//! `udpout:` forward endpoint to the simulator's PX4-like autopilot.
//!
//! Needs `pymavlink` in the Python at `$SHOTPILOT_PYTHON` (`.ci/run`
//! installs it into a venv from PyPI).

use std::io::{BufRead, BufReader, Write};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::Value;
use shotpilot::mission::plan::{self, Flavour, Home, MissionItem, Target};
use shotpilot::mission::upload;
use shotpilot::vehicle::{self, LinkHandle, Params};
use shotpilot_sim::app;
use shotpilot_sim::link::{Endpoint, RadioParams};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;

use crate::link_support;
use crate::mission_sim::{bad_radio, sim_config};

/// The pymavlink station: its process, its stdin, and its stdout's JSON
/// lines (read on a thread).
struct Station {
    child: Child,
    stdin: ChildStdin,
    lines: mpsc::UnboundedReceiver<Value>,
    port: u16,
}

impl Station {
    async fn start(args: &[&str]) -> anyhow::Result<Self> {
        let script = crate::repo_root().join("tests/peers/gcs_peer.py");
        let mut child = Command::new(crate::link_support::python())
            .arg(script)
            .arg("--port")
            .arg("0")
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()?;
        let stdout = child
            .stdout
            .take()
            .ok_or_else(|| anyhow::anyhow!("no stdout"))?;
        let stdin = child
            .stdin
            .take()
            .ok_or_else(|| anyhow::anyhow!("no stdin"))?;
        let (tx, lines) = mpsc::unbounded_channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                match serde_json::from_str::<Value>(&line) {
                    Ok(v) => {
                        if tx.send(v).is_err() {
                            break;
                        }
                    }
                    Err(_) => eprintln!("station: {line}"),
                }
            }
        });
        let mut s = Self {
            child,
            stdin,
            lines,
            port: 0,
        };
        let ready = s.expect("ready", 20).await?;
        s.port = ready["port"]
            .as_u64()
            .and_then(|p| u16::try_from(p).ok())
            .ok_or_else(|| anyhow::anyhow!("station said {ready}"))?;
        Ok(s)
    }

    /// The next line, which must be `step`.
    async fn expect(&mut self, step: &str, seconds: u64) -> anyhow::Result<Value> {
        let v = tokio::time::timeout(Duration::from_secs(seconds), self.lines.recv())
            .await
            .map_err(|_| anyhow::anyhow!("no `{step}` from the station within {seconds} s"))?
            .ok_or_else(|| anyhow::anyhow!("the station ended before `{step}`"))?;
        anyhow::ensure!(v["step"] == step, "expected `{step}`, the station said {v}");
        Ok(v)
    }

    fn tell(&mut self, what: &str) -> anyhow::Result<()> {
        writeln!(self.stdin, "{what}")?;
        self.stdin.flush()?;
        Ok(())
    }
}

impl Drop for Station {
    fn drop(&mut self) {
        let _ = writeln!(self.stdin, "quit");
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The simulator (PX4-like, behind `radio`, with or without its MAVLink
/// camera) and shotpilot's link to it, forwarding to the station at
/// `station_port` when one is given.
async fn sim_and_link(
    station_port: Option<u16>,
    radio: RadioParams,
    mavlink_camera: bool,
    dir: &std::path::Path,
    cancel: &CancellationToken,
) -> anyhow::Result<LinkHandle> {
    let (socket, addr) = link_support::bound_udp();
    let mut cfg = sim_config(Endpoint::UdpIn(addr.to_string()), Flavour::Px4, radio, dir);
    cfg.mavlink_camera = mavlink_camera;
    let sockets = app::Sockets {
        mavlink: Some(socket),
        ..Default::default()
    };
    tokio::spawn(app::run_on(cfg, cancel.child_token(), sockets));
    let p = Params {
        url: format!("udpout:{addr}"),
        forward: station_port
            .map(|p| format!("udpout:127.0.0.1:{p}"))
            .into_iter()
            .collect(),
        link_lost_after_ms: 8000,
        ..Params::default()
    };
    let (link, _task) = vehicle::spawn(p, upload::Params::default(), cancel.clone())?;
    link.wait_for_vehicle(Duration::from_secs(20)).await?;
    Ok(link)
}

fn our_mission(home: &Home, k: usize) -> anyhow::Result<Vec<MissionItem>> {
    let t = Target {
        lat_deg: home.lat_deg + 0.0002 + 1e-6 * k as f64,
        lon_deg: home.lon_deg - 0.0001,
        alt_m: 18.0,
        yaw_deg: 90.0,
        gimbal_pitch_deg: -30.0,
        photo: true,
    };
    Ok(plan::plan(
        &t,
        home,
        Flavour::Px4,
        &plan::Params::default(),
    )?)
}

/// (command, lat e7, lon e7) of each item, as the station lists them.
fn station_items(v: &Value) -> Vec<(u64, i64, i64)> {
    v.as_array()
        .map(|a| {
            a.iter()
                .map(|i| {
                    (
                        i[0].as_u64().unwrap_or(u64::MAX),
                        i[1].as_i64().unwrap_or(i64::MAX),
                        i[2].as_i64().unwrap_or(i64::MAX),
                    )
                })
                .collect()
        })
        .unwrap_or_default()
}

fn ours_as_station_items(items: &[MissionItem]) -> Vec<(u64, i64, i64)> {
    items
        .iter()
        .map(|i| (u64::from(i.command), i64::from(i.x), i64::from(i.y)))
        .collect()
}

const HEARTBEAT: u32 = 0;
const ATTITUDE: u32 = 30;
const GLOBAL_POSITION_INT: u32 = 33;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymavlink"]
async fn a_second_station_through_a_forward_endpoint() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let cancel = CancellationToken::new();
    let mut station = Station::start(&["--window", "10"]).await?;
    let link = sim_and_link(
        Some(station.port),
        RadioParams::default(),
        true,
        dir.path(),
        &cancel,
    )
    .await?;
    let v = station.expect("vehicle", 30).await?;
    assert_eq!(
        v["system"], 1,
        "the station sees the simulator's autopilot: {v}"
    );

    // Telemetry: what the station gets through shotpilot against what
    // shotpilot itself gets on its direct connection, over the same window.
    station.expect("window_start", 10).await?;
    let ids = [HEARTBEAT, ATTITUDE, GLOBAL_POSITION_INT];
    let before: Vec<u64> = ids.iter().map(|&i| link.frames_from_vehicle(i)).collect();
    let end = station.expect("window_end", 20).await?;
    let after: Vec<u64> = ids.iter().map(|&i| link.frames_from_vehicle(i)).collect();
    for ((name, b), a) in ["HEARTBEAT", "ATTITUDE", "GLOBAL_POSITION_INT"]
        .iter()
        .zip(&before)
        .zip(&after)
    {
        let direct = (a - b) as f64;
        let through = end["counts"][name].as_f64().unwrap_or(0.0);
        println!(
            "{name}: {through} through the endpoint, {direct} on shotpilot's own link in 10 s ({:.1} %)",
            100.0 * through / direct.max(1.0)
        );
        assert!(
            direct >= 5.0,
            "{name}: the vehicle sent only {direct} in 10 s"
        );
        assert!(
            through >= 0.95 * direct,
            "{name}: the station got {through} of {direct}"
        );
    }

    // The station arms and uploads its mission; shotpilot notices.
    let armed = station.expect("armed", 30).await?;
    assert_eq!(armed["result"], 0, "arming through shotpilot: {armed}");
    let mut changes = link.telemetry.mission_changes.clone();
    let seen_before = *changes.borrow_and_update();
    let up = station.expect("uploaded", 60).await?;
    assert_eq!(up["result"], "MAV_MISSION_ACCEPTED", "{up}");
    let t0 = Instant::now();
    tokio::time::timeout(
        Duration::from_secs(2),
        changes.wait_for(|n| *n > seen_before),
    )
    .await
    .map_err(|_| anyhow::anyhow!("shotpilot did not notice the station's mission within 2 s"))??;
    println!(
        "the station's upload ({} items, {} s) noticed {:.3} s after the station's ACK line",
        station_items(&up["items"]).len(),
        up["seconds"],
        t0.elapsed().as_secs_f64()
    );
    let theirs = link.download_mission().await?;
    assert_eq!(
        ours_as_station_items(&theirs.items),
        station_items(&up["items"]),
        "shotpilot reads back the station's mission"
    );

    // Then shotpilot's own upload, which the station reads back.
    let home = link_support::home_of(&link).await?;
    let items = our_mission(&home, 0)?;
    let report = link.upload_mission(items.clone()).await?;
    println!("shotpilot's upload: {report:?}");
    assert_eq!(
        *link.telemetry.mission_changes.borrow(),
        seen_before + 1,
        "shotpilot's own upload is not another station's change"
    );
    station.tell("download")?;
    let down = station.expect("downloaded", 60).await?;
    assert_eq!(
        station_items(&down["items"]),
        ours_as_station_items(&items),
        "the station reads back shotpilot's mission"
    );
    let status = link.forward_status();
    println!("forward endpoints: {status:?}");
    assert_eq!(status.len(), 1);
    assert!(status[0].frames_in > 0 && status[0].frames_out > 0 && status[0].dropped == 0);
    cancel.cancel();
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs pymavlink"]
async fn two_stations_upload_at_once_over_a_lossy_radio() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let cancel = CancellationToken::new();
    let mut station = Station::start(&["--window", "0", "--no-arm"]).await?;
    let link = sim_and_link(Some(station.port), bad_radio(11), true, dir.path(), &cancel).await?;
    station.expect("vehicle", 30).await?;
    let home = link_support::home_of(&link).await?;
    let rounds = 20;
    let mut held = 0;
    let mut station_s = Vec::new();
    let mut ours_s = Vec::new();
    for k in 0..rounds {
        let items = our_mission(&home, k)?;
        // Both start together; who goes first changes from round to round.
        station.tell("upload")?;
        tokio::time::sleep(Duration::from_millis(25 * (k as u64 % 4))).await;
        let t0 = Instant::now();
        let ours = link.upload_mission(items.clone()).await;
        ours_s.push(t0.elapsed().as_secs_f64());
        let theirs = station.expect("uploaded", 120).await?;
        let ours = ours.map_err(|e| anyhow::anyhow!("round {k}: shotpilot's upload: {e}"))?;
        anyhow::ensure!(
            theirs["result"] == "MAV_MISSION_ACCEPTED",
            "round {k}: the station's upload: {theirs}"
        );
        station_s.push(theirs["seconds"].as_f64().unwrap_or(f64::NAN));
        let now_held = link.forward_status()[0].held;
        let was_held = now_held > held;
        held = now_held;
        // The vehicle holds one of the two whole missions, not a mix.
        let d = link.download_mission().await?;
        let on_vehicle = ours_as_station_items(&d.items);
        let is_ours = on_vehicle == ours_as_station_items(&items);
        let is_theirs = on_vehicle == station_items(&theirs["items"]);
        anyhow::ensure!(
            is_ours || is_theirs,
            "round {k}: the vehicle holds neither mission: {on_vehicle:?}"
        );
        println!(
            "round {k}: both accepted ({ours:?}); the station's was {}; the vehicle holds {}",
            if was_held {
                "held until ours ended"
            } else {
                "first"
            },
            if is_ours { "ours" } else { "the station's" }
        );
    }
    let med = |v: &mut Vec<f64>| shotpilot::stats::median_max(v).unwrap_or((f64::NAN, f64::NAN));
    println!(
        "{rounds}/{rounds} rounds both uploads accepted over 30 % loss each way; upload median/max: shotpilot {:?} s, station {:?} s",
        med(&mut ours_s),
        med(&mut station_s)
    );
    cancel.cancel();
    Ok(())
}

/// A MAVLink connection on a UDP socket bound here (port 0): `udpin`,
/// answering the last sender.
async fn udp_in() -> anyhow::Result<(
    mavlink::AsyncConnection<mavlink::dialects::common::MavMessage>,
    std::net::SocketAddr,
)> {
    use mavlink::{AsyncConnectable, ConnectionAddress, UdpConfig, UdpMode};
    let (socket, addr) = link_support::bound_udp();
    let a = ConnectionAddress::Udp(UdpConfig::from_socket(socket, UdpMode::Udpin)?);
    Ok((
        a.connect_async::<mavlink::dialects::common::MavMessage>()
            .await?,
        addr,
    ))
}

/// Sends `n` SYSTEM_TIME frames at `hz` from a fake vehicle (1/1) to `to`,
/// each stamped with its send time (µs since `epoch`), after a heartbeat.
async fn stamped_burst(
    to: std::net::SocketAddr,
    n: usize,
    hz: f64,
    epoch: Instant,
) -> anyhow::Result<()> {
    use mavlink::dialects::common::*;
    use mavlink::{
        AsyncConnectable, AsyncMavConnection, ConnectionAddress, MavHeader, UdpConfig, UdpMode,
    };
    let a = ConnectionAddress::Udp(UdpConfig::new(to.to_string(), UdpMode::Udpout));
    let conn = a.connect_async::<MavMessage>().await?;
    let h = MavHeader {
        system_id: 1,
        component_id: 1,
        sequence: 0,
    };
    let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_QUADROTOR,
        autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_STANDBY,
        mavlink_version: 3,
    });
    conn.send(&h, &hb).await?;
    tokio::time::sleep(Duration::from_millis(200)).await;
    let mut tick = tokio::time::interval(Duration::from_secs_f64(1.0 / hz));
    for k in 0..n {
        tick.tick().await;
        let m = MavMessage::SYSTEM_TIME(SYSTEM_TIME_DATA {
            time_unix_usec: epoch.elapsed().as_micros() as u64,
            time_boot_ms: k as u32,
        });
        conn.send(&h, &m).await?;
    }
    Ok(())
}

/// Receives SYSTEM_TIME frames until `n` or a second of silence: the
/// latencies (µs) and how many arrived out of order.
async fn stamped_receive(
    conn: &mavlink::AsyncConnection<mavlink::dialects::common::MavMessage>,
    n: usize,
    epoch: Instant,
) -> (Vec<f64>, usize) {
    use mavlink::AsyncMavConnection;
    use mavlink::dialects::common::MavMessage;
    let mut lat = Vec::with_capacity(n);
    let mut last = None;
    let mut disorder = 0;
    while lat.len() < n {
        match tokio::time::timeout(Duration::from_secs(1), conn.recv()).await {
            Ok(Ok((_, MavMessage::SYSTEM_TIME(t)))) => {
                lat.push(epoch.elapsed().as_micros() as f64 - t.time_unix_usec as f64);
                if last.is_some_and(|l| t.time_boot_ms <= l) {
                    disorder += 1;
                }
                last = Some(t.time_boot_ms);
            }
            Ok(_) => {}
            Err(_) => break,
        }
    }
    (lat, disorder)
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v.get(((v.len() as f64 - 1.0) * p).round() as usize)
        .copied()
        .unwrap_or(f64::NAN)
}

/// What shotpilot adds to each message between the vehicle and a station:
/// a fake vehicle sends 4,000 stamped frames at 400 Hz (PX4's whole stream
/// set on a UDP link is 200-500 messages/s) to shotpilot, which forwards
/// them to a station's socket; the same burst sent straight to a socket is
/// the baseline. Timings are printed, never asserted: the frames' arrival
/// and order are.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forwarding_keeps_every_frame_in_order_at_full_telemetry_rate() -> anyhow::Result<()> {
    let n = 4000;
    let hz = 400.0;
    let epoch = Instant::now();
    // Baseline: straight to a socket.
    let (direct, direct_addr) = udp_in().await?;
    let (sent, (mut base, base_disorder)) = tokio::join!(
        stamped_burst(direct_addr, n, hz, epoch),
        stamped_receive(&direct, n, epoch)
    );
    sent?;
    // Through shotpilot: vehicle -> link (udpin) -> forward (udpout) -> station.
    let (station, station_addr) = udp_in().await?;
    let (link_socket, link_addr) = link_support::bound_udp();
    let cancel = CancellationToken::new();
    let p = Params {
        forward: vec![format!("udpout:{station_addr}")],
        ..Params::default()
    };
    let (link, _task) =
        vehicle::spawn_with_socket(p, upload::Params::default(), cancel.clone(), link_socket)?;
    let (sent, (mut routed, routed_disorder)) = tokio::join!(
        stamped_burst(link_addr, n, hz, epoch),
        stamped_receive(&station, n, epoch)
    );
    sent?;
    let (bm, b99) = (percentile(&mut base, 0.5), percentile(&mut base, 0.99));
    let (rm, r99) = (percentile(&mut routed, 0.5), percentile(&mut routed, 0.99));
    println!(
        "{n} frames at {hz} Hz: direct {} received, median {bm:.0} us, p99 {b99:.0} us; \
         through shotpilot {} received, median {rm:.0} us, p99 {r99:.0} us; \
         added: median {:.0} us, p99 {:.0} us",
        base.len(),
        routed.len(),
        rm - bm,
        r99 - b99
    );
    assert_eq!(base.len(), n, "the baseline lost frames on loopback");
    assert_eq!(base_disorder, 0);
    assert_eq!(routed.len(), n, "shotpilot dropped frames");
    assert_eq!(routed_disorder, 0, "shotpilot reordered frames");
    assert_eq!(link.forward_status()[0].dropped, 0);
    cancel.cancel();
    Ok(())
}

/// The photo by MAVLink's camera protocol: the simulator's camera
/// component (100) is discovered from its heartbeat and CAMERA_INFORMATION,
/// takes the picture on MAV_CMD_IMAGE_START_CAPTURE and reports it with
/// CAMERA_IMAGE_CAPTURED (where, when, stored where); without a camera
/// component the link falls back to DO_DIGICAM_CONTROL to the autopilot,
/// whose trigger reports the picture as component 1.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_photo_by_the_camera_protocol_and_its_fallback() -> anyhow::Result<()> {
    for camera in [true, false] {
        let dir = tempfile::tempdir()?;
        let cancel = CancellationToken::new();
        let link = sim_and_link(None, RadioParams::default(), camera, dir.path(), &cancel).await?;
        if camera {
            let mut cams = link.telemetry.cameras.clone();
            let found = tokio::time::timeout(
                Duration::from_secs(10),
                cams.wait_for(|c| c.iter().any(|c| c.component_id == 100)),
            )
            .await
            .map_err(|_| anyhow::anyhow!("no CAMERA_INFORMATION from component 100 in 10 s"))??
            .clone();
            println!("cameras: {found:?}");
            assert!(found[0].captures_images);
            assert_eq!(found[0].vendor, "shotpilot-sim");
        } else {
            // Two camera heartbeat periods: none is heard.
            tokio::time::sleep(Duration::from_secs(2)).await;
            assert!(link.telemetry.cameras.borrow().is_empty());
        }
        let here = link
            .telemetry
            .global_position
            .borrow()
            .map(|g| g.value)
            .ok_or_else(|| anyhow::anyhow!("no position"))?;
        let report = link.capture_image(Duration::from_secs(10)).await?;
        println!("camera component {camera}: {report:?}");
        let (method, component) = if camera {
            ("camera_protocol", 100)
        } else {
            ("digicam_control", 1)
        };
        assert_eq!(report.method, method);
        assert_eq!(report.component_id, component);
        let c = report
            .captured
            .ok_or_else(|| anyhow::anyhow!("no CAMERA_IMAGE_CAPTURED"))?;
        assert_eq!(c.component_id, component);
        assert!(c.ok, "the picture was stored: {c:?}");
        let path = c
            .file_url
            .strip_prefix("file://")
            .ok_or_else(|| anyhow::anyhow!("url {}", c.file_url))?;
        assert!(std::path::Path::new(path).is_file(), "{path} exists");
        // Where the camera says it was: where the vehicle said it was
        // (the vehicle stands on the ground, untouched).
        let north_m = (c.lat_deg - here.lat_deg) * 111_320.0;
        let east_m = (c.lon_deg - here.lon_deg) * 111_320.0 * here.lat_deg.to_radians().cos();
        assert!(
            north_m.hypot(east_m) < 0.5 && (c.alt_amsl_m - here.alt_amsl_m).abs() < 0.5,
            "picture at {c:?}, vehicle at {here:?}"
        );
        let qn = c.q.iter().map(|x| x * x).sum::<f32>().sqrt();
        assert!((qn - 1.0).abs() < 1e-3, "a unit quaternion: {:?}", c.q);
        cancel.cancel();
    }
    Ok(())
}

/// The daemon with a forward endpoint: its stored shot, whose mission the
/// vehicle no longer holds (`cleared` at start), becomes `replaced` within
/// 2 s of another station's upload through the endpoint; when the station
/// puts the shot's own mission back, the shot owns it again, and the
/// picture the vehicle's camera then reports is stored with it.
#[test]
#[ignore = "needs pymavlink"]
fn the_daemon_marks_its_shot_replaced_then_stores_its_photo() -> anyhow::Result<()> {
    use crate::daemon_support;
    use shotpilot::shot::record::{MissionRecord, MissionState, Shot, ShotSource, ShotStatus};
    use shotpilot::shot::store::ShotStore;
    let base = tempfile::tempdir()?;
    let (mut cfg, sockets) = daemon_support::sim_config();
    let h = shotpilot_sim::vehicle::VehicleParams::default().home;
    let home = Home {
        lat_deg: h.lat_deg,
        lon_deg: h.lon_deg,
        alt_amsl_m: h.alt_m,
    };
    let items = our_mission(&home, 0)?;
    {
        let store = ShotStore::open(&base.path().join(&cfg.server.data_dir).join("shots"))?;
        store.put(
            Shot {
                id: "shot-1".into(),
                created_unix: 0.0,
                source: ShotSource::Anchors {
                    keyframe_id: 1,
                    anchors: [[40.0, 30.0], [600.0, 30.0], [600.0, 450.0], [40.0, 450.0]],
                },
                status: ShotStatus::Localised,
                localisation: None,
                reason: None,
                nearest_keyframes: Vec::new(),
                has_image: false,
                mission: Some(MissionRecord {
                    state: MissionState::Uploaded,
                    items: items.len(),
                    uploaded_unix: 1.0,
                    started_unix: None,
                    target_lat_lon_alt: None,
                    details: serde_json::json!({ "planned_items": items }),
                }),
            },
            None,
        )?;
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()?;
    let items_file = base.path().join("shot-1-items.json");
    std::fs::write(&items_file, serde_json::to_vec(&items)?)?;
    let items_arg = items_file.display().to_string();
    let mut station = rt.block_on(Station::start(&[
        "--window",
        "0",
        "--items-json",
        &items_arg,
    ]))?;
    cfg.sim.script = "none".into();
    cfg.link.forward = vec![format!("udpout:127.0.0.1:{}", station.port)];
    cfg.validate(std::path::Path::new("test"))?;
    let running = daemon_support::start(cfg, sockets, base.path());
    let state = || {
        daemon_support::get_json(running.addr, "/api/v1/shots/shot-1")["mission"]["state"]
            .as_str()
            .unwrap_or("")
            .to_owned()
    };
    // Waits until the shot's mission state is (or, with `leave`, is no
    // longer) `want`; how long it took.
    let wait_state = |want: &str, leave: bool, limit_s: u64, what: &str| {
        let t = Instant::now();
        while (state() == want) == leave {
            anyhow::ensure!(
                t.elapsed() < Duration::from_secs(limit_s),
                "the shot is {} {limit_s} s after {what}",
                state()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
        Ok(t.elapsed())
    };
    // At start the vehicle holds no mission: the shot's is `cleared`.
    wait_state("cleared", false, 30, "start")?;
    rt.block_on(station.expect("vehicle", 30))?;
    rt.block_on(station.expect("armed", 30))?;
    let up = rt.block_on(station.expect("uploaded", 60))?;
    anyhow::ensure!(up["result"] == "MAV_MISSION_ACCEPTED", "{up}");
    let took = wait_state("replaced", false, 2, "the station's upload")?;
    println!(
        "the shot was marked replaced {:.2} s after the station's upload ended",
        took.as_secs_f64()
    );
    let shot = daemon_support::get_json(running.addr, "/api/v1/shots/shot-1");
    println!("{}", shot["mission"]["details"]["vehicle"]);

    // The station puts the shot's own mission back: the shot owns the
    // vehicle's mission again, and a picture the camera reports is stored
    // with it.
    station.tell("upload-json")?;
    let up = rt.block_on(station.expect("uploaded", 60))?;
    anyhow::ensure!(up["result"] == "MAV_MISSION_ACCEPTED", "{up}");
    wait_state("replaced", true, 2, "its own mission came back")?;
    println!("with its mission back the shot is {}", state());
    station.tell("capture 100")?;
    let cap = rt.block_on(station.expect("captured", 30))?;
    anyhow::ensure!(cap["result"] == 0, "the camera refused: {cap}");
    let t = Instant::now();
    let photos = loop {
        let shot = daemon_support::get_json(running.addr, "/api/v1/shots/shot-1");
        let p = shot["mission"]["details"]["photos"].clone();
        if p.as_array().is_some_and(|a| !a.is_empty()) {
            break p;
        }
        anyhow::ensure!(
            t.elapsed() < Duration::from_secs(5),
            "no photo stored with the shot 5 s after the capture: {}",
            shot["mission"]
        );
        std::thread::sleep(Duration::from_millis(100));
    };
    println!("photos stored with the shot: {photos}");
    assert_eq!(photos[0]["component_id"], 100);
    assert_eq!(photos[0]["ok"], true);
    let lat = photos[0]["lat_deg"].as_f64().unwrap_or(f64::NAN);
    assert!(
        (lat - h.lat_deg).abs() < 1e-5,
        "taken at home, on the ground: {lat}"
    );
    let status = daemon_support::get_json(running.addr, "/api/v1/status");
    assert_eq!(
        status["vehicle"]["forward"][0]["clients"], 1,
        "{}",
        status["vehicle"]
    );
    running.stop(Duration::from_secs(20));
    Ok(())
}
