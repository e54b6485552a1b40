//! End to end: the daemon with the simulator in-process, driven over its
//! HTTP API. SLAM reaches tracking, keyframes appear with images, the map
//! grows, the vehicle is heard over MAVLink, the map is georeferenced from
//! telemetry, a shot posted by anchors is localised and converted to a
//! vehicle target, its mission is uploaded to the simulator and read back
//! item by item, and a cancellation stops everything cleanly with the map
//! saved.

use crate::daemon_support;

use daemon_support::{get_json, http, request};

use std::net::SocketAddr;
use std::path::Path;
use std::time::{Duration, Instant};

use serde_json::{Value, json};

/// POST a PNG image; returns status and body.
fn post_png(addr: SocketAddr, path: &str, img: &image::GrayImage) -> (u16, Vec<u8>) {
    let mut png = Vec::new();
    img.write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    request(addr, "POST", path, "image/png", &png)
}

#[test]
fn daemon_with_simulator_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, sockets) = daemon_support::sim_config();
    cfg.validate(Path::new("test")).unwrap();
    let cam_cfg = cfg.camera.clone();

    let daemon = daemon_support::start_on_sim_time(cfg, sockets, dir.path());
    let addr = daemon.addr;
    let t0 = Instant::now();
    let sim0 = daemon.now();

    // SLAM reaches tracking and makes keyframes.
    let status = daemon
        .poll(
            Duration::from_secs(90),
            Duration::from_millis(500),
            move || {
                let status = get_json(addr, "/api/v1/status");
                let s = &status["slam"];
                (s["state"] == "tracking"
                    && s["keyframes"].as_u64().unwrap_or(0) >= 5
                    && s["tracked"].as_u64().unwrap_or(0) >= 20)
                    .then_some(status)
            },
        )
        .unwrap_or_else(|| get_json(addr, "/api/v1/status"));
    let secs = t0.elapsed().as_secs_f64();
    eprintln!(
        "after {:.1} s simulated ({secs:.1} s wall): {status}",
        (daemon.now() - sim0).as_secs_f64()
    );
    assert_eq!(status["slam"]["state"], "tracking", "{status}");
    assert!(status["slam"]["keyframes"].as_u64().unwrap() >= 5);
    assert!(status["slam"]["points"].as_u64().unwrap() >= 200);
    let v = &status["video"]["counters"];
    assert!(v["decoded"].as_u64().unwrap() >= 20, "{v}");
    assert_eq!(v["bad"], 0, "{v}");
    // In lockstep the clock is held while a frame is processed: each
    // frame is posed at the simulated instant it was captured.
    assert!(
        status["slam"]["latency_ms_median"]
            .as_f64()
            .is_some_and(|l| l.abs() < 1.0),
        "{status}"
    );
    // The vehicle is heard over MAVLink.
    assert_eq!(status["vehicle"]["connected"], true, "{status}");

    // Keyframes with images, and the map.
    let kfs = get_json(addr, "/api/v1/keyframes");
    let n = kfs["count"].as_u64().unwrap();
    assert!(n >= 5);
    let kf = &kfs["keyframes"][(n / 2) as usize];
    let id = kf["id"].as_u64().unwrap();
    assert!(
        kf["timestamp"].as_f64().unwrap() > 1.0e9,
        "capture times are unix seconds"
    );
    let (st, jpeg) = http(
        addr,
        "GET",
        &format!("/api/v1/keyframes/{id}/image.jpg"),
        None,
    );
    assert_eq!(st, 200);
    let img = image::load_from_memory(&jpeg).unwrap();
    assert_eq!((img.width(), img.height()), (640, 480));
    // The map's trajectory has one centre per keyframe. SLAM keeps adding
    // (and culling) keyframes while the test reads, so the comparison is
    // made on a reading where the keyframe count did not change around it.
    let mut consistent = false;
    for _ in 0..10 {
        let before = get_json(addr, "/api/v1/keyframes")["count"]
            .as_u64()
            .unwrap();
        let map = get_json(addr, "/api/v1/map?max_points=500");
        let after = get_json(addr, "/api/v1/keyframes")["count"]
            .as_u64()
            .unwrap();
        assert!(map["points"].as_array().unwrap().len() <= 500);
        assert!(map["total_points"].as_u64().unwrap() >= 200);
        if before == after {
            assert_eq!(map["trajectory"].as_array().unwrap().len() as u64, before);
            consistent = true;
            break;
        }
    }
    assert!(
        consistent,
        "the keyframe count changed around every map reading"
    );

    // The georeference: refused (with a reason) until the flight has moved
    // enough, then fitted from the keyframes and telemetry.
    let mut geo = Value::Null;
    let mut reasons = std::collections::BTreeSet::new();
    while daemon.now() - sim0 < Duration::from_secs(50) {
        geo = get_json(addr, "/api/v1/status")["vehicle"]["georeference"].clone();
        if geo["state"] == "ok" {
            break;
        }
        assert!(
            geo["reason"].as_str().is_some_and(|r| !r.is_empty()),
            "{geo}"
        );
        reasons.insert(
            geo["reason"]
                .as_str()
                .unwrap_or("")
                .split(':')
                .next()
                .unwrap_or("")
                .to_owned(),
        );
        daemon.sleep(Duration::from_millis(500));
    }
    eprintln!(
        "georeference after {:.1} s simulated, {:.1} s wall (refusals seen: {reasons:?}): {geo}",
        (daemon.now() - sim0).as_secs_f64(),
        t0.elapsed().as_secs_f64()
    );
    assert_eq!(geo["state"], "ok", "{geo}");
    assert!(geo["keyframes_used"].as_u64().unwrap() >= 6, "{geo}");
    assert!(geo["rms_m"].as_f64().unwrap() < 0.5, "{geo}");
    assert!(geo["scale"].as_f64().unwrap() > 0.0);
    assert!(geo["home"]["lat_deg"].as_f64().is_some());

    // A shot by anchors on a keyframe: most of its picture, slightly
    // zoomed in. The newest keyframes first (the map around them is the
    // freshest).
    let kfs = get_json(addr, "/api/v1/keyframes");
    let ids: Vec<u64> = kfs["keyframes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|k| k["id"].as_u64().unwrap())
        .collect();
    let mut posted = 0;
    let mut localised = None;
    for &kid in ids.iter().rev().take(6) {
        let shot = json!({"keyframe_id": kid, "anchors": [[40, 30], [600, 30], [600, 450], [40, 450]], "width": 320, "height": 240});
        let (st, b) = http(addr, "POST", "/api/v1/shots", Some(&shot));
        assert_eq!(st, 201, "{}", String::from_utf8_lossy(&b));
        posted += 1;
        let shot: Value = serde_json::from_slice(&b).unwrap();
        let sid = shot["id"].as_str().unwrap().to_owned();
        let (st, b) = http(addr, "GET", &format!("/api/v1/shots/{sid}/image.jpg"), None);
        assert_eq!(st, 200);
        assert_eq!(image::load_from_memory(&b).unwrap().width(), 320);
        if shot["status"] == "localised" {
            localised = Some((sid, kid, shot));
            break;
        }
        eprintln!("shot on keyframe {kid} not localised: {}", shot["reason"]);
        let (st, _) = http(addr, "POST", &format!("/api/v1/shots/{sid}/mission"), None);
        assert_eq!(st, 409);
    }
    let (sid, kid, shot) = localised.expect("a shot by anchors is localised");
    eprintln!("shot {sid} on keyframe {kid}: {}", shot["localisation"]);

    // Photos of that keyframe from "other cameras": the map camera at half
    // size (same aspect ratio: the camera is scaled, no intrinsics needed),
    // and a square crop (another aspect ratio: refused without intrinsics,
    // localised with them). Both land near the keyframe's camera, within a
    // tenth of the map's trajectory extent.
    let (st, b) = http(
        addr,
        "GET",
        &format!("/api/v1/keyframes/{kid}/image.jpg"),
        None,
    );
    assert_eq!(st, 200);
    let kf_img = image::load_from_memory(&b).unwrap().to_luma8();
    let kf = kfs["keyframes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|k| k["id"] == kid)
        .unwrap()
        .clone();
    let extent = daemon_support::trajectory_extent(addr);
    let half = image::imageops::resize(&kf_img, 320, 240, image::imageops::FilterType::Triangle);
    let (st, b) = post_png(addr, "/api/v1/shots/photo", &half);
    assert_eq!(st, 201, "{}", String::from_utf8_lossy(&b));
    posted += 1;
    let half_shot: Value = serde_json::from_slice(&b).unwrap();
    eprintln!("half-size photo of keyframe {kid}: {half_shot}");
    assert_eq!(half_shot["status"], "localised", "{half_shot}");
    let d = daemon_support::centre_distance(&half_shot, &kf);
    eprintln!("half-size photo: {d:.3} from the keyframe's centre (trajectory extent {extent:.3})");
    assert!(d < 0.1 * extent, "{d} vs extent {extent}");
    let crop = image::imageops::crop_imm(&kf_img, 80, 0, 480, 480).to_image();
    let (st, b) = post_png(addr, "/api/v1/shots/photo", &crop);
    assert_eq!(st, 400, "{}", String::from_utf8_lossy(&b));
    let e: Value = serde_json::from_slice(&b).unwrap();
    assert_eq!(e["error"]["code"], "intrinsics_required", "{e}");
    assert!(
        e["error"]["message"]
            .as_str()
            .unwrap()
            .contains("fx, fy, cx, cy"),
        "{e}"
    );
    let c = &cam_cfg;
    let q = format!(
        "fx={}&fy={}&cx={}&cy={}&k1={}&k2={}",
        c.fx,
        c.fy,
        c.cx - 80.0,
        c.cy,
        c.k1,
        c.k2
    );
    let (st, b) = post_png(addr, &format!("/api/v1/shots/photo?{q}"), &crop);
    assert_eq!(st, 201, "{}", String::from_utf8_lossy(&b));
    posted += 1;
    let crop_shot: Value = serde_json::from_slice(&b).unwrap();
    assert_eq!(crop_shot["status"], "localised", "{crop_shot}");
    assert_eq!(crop_shot["source"]["intrinsics"]["fx"], c.fx);
    let d = daemon_support::centre_distance(&crop_shot, &kf);
    eprintln!("cropped photo with intrinsics: {d:.3} from the keyframe's centre");
    assert!(d < 0.1 * extent, "{d} vs extent {extent}");

    // The pose the target is planned from looks at what the anchors
    // enclose: its optical axis is the keyframe's ray through the anchors'
    // centre (within 5 degrees: a tenth of the camera's field of view),
    // and since the anchors zoom in (1.14x) the camera stands ahead of the
    // keyframe's along that ray, more ahead than aside.
    let kf_now = get_json(addr, "/api/v1/keyframes")["keyframes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|k| k["id"] == kid)
        .cloned()
        .unwrap_or_else(|| kf_of(&kfs, kid));
    let (kf_rot, kf_centre) = pose_of(&kf_now["world_from_cam"]);
    let (shot_rot, shot_centre) = pose_of(&shot["localisation"]["world_from_cam"]);
    let c = &cam_cfg;
    let anchors_centre = nalgebra::Vector3::new((320.0 - c.cx) / c.fx, (240.0 - c.cy) / c.fy, 1.0);
    let ray = kf_rot * anchors_centre.normalize();
    let axis = shot_rot * nalgebra::Vector3::z();
    let off_axis_deg = axis.angle(&ray).to_degrees();
    let ahead = kf_rot.inverse() * (shot_centre - kf_centre);
    eprintln!(
        "target pose: optical axis {off_axis_deg:.2} deg off the anchors' centre ray; \
         {:.3} ahead of the keyframe, {:.3} aside (map units)",
        ahead.z,
        ahead.xy().norm()
    );
    assert!(off_axis_deg < 5.0, "{off_axis_deg} deg: {shot}");
    assert!(
        ahead.z > 0.0 && ahead.z > ahead.xy().norm(),
        "the shot's camera is not ahead of keyframe {kid}'s: {ahead:?}"
    );

    // Its vehicle target: near home, inside the gimbal's range.
    let target = get_json(addr, &format!("/api/v1/shots/{sid}/target"));
    eprintln!("target: {target}");
    let t = &target["target"];
    let home = &geo["home"];
    let (dlat, dlon) = (
        t["lat_deg"].as_f64().unwrap() - home["lat_deg"].as_f64().unwrap(),
        t["lon_deg"].as_f64().unwrap() - home["lon_deg"].as_f64().unwrap(),
    );
    let north = dlat * 111_132.0;
    let east = dlon * 111_320.0 * home["lat_deg"].as_f64().unwrap().to_radians().cos();
    assert!(north.hypot(east) < 80.0, "{target}");
    let alt = t["alt_above_home_m"].as_f64().unwrap();
    assert!((2.0..60.0).contains(&alt), "{target}");
    let pitch = t["gimbal_pitch_deg"].as_f64().unwrap();
    assert!((-90.0..=30.0).contains(&pitch), "{target}");

    // Plan and upload; the vehicle's mission, downloaded again, holds the
    // planned items exactly.
    let (st, b) = http(addr, "POST", &format!("/api/v1/shots/{sid}/mission"), None);
    assert_eq!(st, 200, "{}", String::from_utf8_lossy(&b));
    let with_mission: Value = serde_json::from_slice(&b).unwrap();
    let m = &with_mission["mission"];
    eprintln!("mission: {m}");
    assert_eq!(m["state"], "uploaded");
    assert_eq!(m["details"]["verified_by_read_back"], true);
    let planned = m["details"]["planned_items"].as_array().unwrap().clone();
    assert_eq!(m["items"].as_u64().unwrap() as usize, planned.len());
    assert!(planned.len() >= 3);
    // The mission flies to the target shown, as the georeference stands
    // when it is planned: the daemon refits it as keyframes come (a local
    // CI run saw 13 keyframes for the target and 14 for the mission, the
    // latitude 0.4 mm apart), so equal within 1e-6 deg (0.11 m).
    let lla = m["target_lat_lon_alt"].as_array().unwrap();
    let (lat_mission, lat_target) = (lla[0].as_f64().unwrap(), t["lat_deg"].as_f64().unwrap());
    assert!(
        (lat_mission - lat_target).abs() < 1e-6,
        "mission latitude {lat_mission} vs target {lat_target}"
    );
    let on_vehicle = get_json(addr, "/api/v1/vehicle/mission");
    let items = on_vehicle["items"].as_array().unwrap();
    assert_eq!(items.len(), planned.len(), "{on_vehicle}");
    for (a, b) in planned.iter().zip(items) {
        assert_eq!(a, b, "planned vs on the vehicle");
    }
    // The waypoint is the target: latitude/longitude in 1e-7 degrees.
    let wp = planned
        .iter()
        .find(|i| i["command"] == 16)
        .expect("a NAV_WAYPOINT");
    let lat_e7 = wp["x"].as_i64().unwrap() as f64 / 1e7;
    assert!((lat_e7 - t["lat_deg"].as_f64().unwrap()).abs() < 2e-7);
    let stored = get_json(addr, &format!("/api/v1/shots/{sid}"));
    assert_eq!(stored["mission"]["state"], "uploaded");

    // Live video is re-served.
    let (st, snap) = http(addr, "GET", "/api/v1/snapshot.jpg", None);
    assert_eq!(st, 200);
    assert!(image::load_from_memory(&snap).is_ok());

    // Clean stop, even with endless responses open (events, video): the
    // map is saved, the shot is on disk.
    let mut open_streams = Vec::new();
    for path in ["/api/v1/events", "/api/v1/video.mjpg"] {
        let auth = format!("Bearer {}", daemon_support::TOKEN);
        let mut s =
            daemon_support::http_support::open_stream(addr, path, &[("authorization", &auth)]);
        assert_eq!(s.status, 200, "{path}");
        assert!(s.next(Duration::from_secs(10)).is_some(), "{path} answers");
        open_streams.push(s);
    }
    let t_stop = Instant::now();
    let summary = daemon.stop(Duration::from_secs(30));
    eprintln!("stopped in {:.2} s", t_stop.elapsed().as_secs_f64());
    drop(open_streams);
    eprintln!("summary: {}", serde_json::to_string(&summary).unwrap());
    let map_file = summary.map_file.expect("the map was saved");
    assert!(std::fs::metadata(&map_file).unwrap().len() > 1000);
    let loaded = shotpilot::slam::mapfile::load(&map_file).unwrap();
    assert!(loaded.keyframe_count() >= 5);
    assert!(
        dir.path()
            .join("data/shots")
            .join(format!("{sid}.json"))
            .is_file()
    );
    assert_eq!(summary.shots, posted);
    eprintln!("total {:.1} s", t0.elapsed().as_secs_f64());
}

/// A keyframe of a `/api/v1/keyframes` reply.
fn kf_of(kfs: &Value, id: u64) -> Value {
    kfs["keyframes"]
        .as_array()
        .unwrap()
        .iter()
        .find(|k| k["id"] == id)
        .cloned()
        .unwrap()
}

/// Rotation and centre of a `world_from_cam` pose in the API's JSON.
fn pose_of(p: &Value) -> (nalgebra::UnitQuaternion<f64>, nalgebra::Vector3<f64>) {
    let f = |v: &Value, i: usize| v[i].as_f64().unwrap();
    let (q, t) = (&p["rotation_xyzw"], &p["translation"]);
    (
        nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
            f(q, 3),
            f(q, 0),
            f(q, 1),
            f(q, 2),
        )),
        nalgebra::Vector3::new(f(t, 0), f(t, 1), f(t, 2)),
    )
}
