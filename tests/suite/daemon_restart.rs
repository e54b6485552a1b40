//! The daemon continues on its saved map across a restart, with the
//! simulator in-process: run 1 builds a map and localises a shot by
//! anchors, then stops (the map is saved); run 2 on the same data
//! directory loads the map, relocalises into it (the old keyframes keep
//! their ids, capture times and poses), adds new keyframes with new ids, and
//! the same shot localises again to the pose it had before the restart.
//! Run 3 finds the map file damaged: the daemon serves anyway with a fresh
//! map, and the damaged file is kept under a new name, byte for byte.

use crate::daemon_support;

use daemon_support::{get_json, http, request};

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};
use serde_json::{Value, json};
use shotpilot::slam::KeyFrameId;

/// The daemon on simulated time (the simulator in lockstep).
fn start(base: &Path) -> daemon_support::OnSimTime {
    let (cfg, sockets) = daemon_support::sim_config();
    assert!(cfg.slam.continue_map, "continuing is the default");
    cfg.validate(Path::new("test")).unwrap();
    daemon_support::start_on_sim_time(cfg, sockets, base)
}

/// Poll the status every 300 ms of simulated time until `done` holds (or
/// `secs` of simulated time ran out); returns the last status.
fn wait_status(
    d: &daemon_support::OnSimTime,
    secs: u64,
    done: impl Fn(SocketAddr, &Value) -> bool + Send + Sync + 'static,
) -> Value {
    let addr = d.addr;
    d.poll(
        Duration::from_secs(secs),
        Duration::from_millis(300),
        move || {
            let status = get_json(addr, "/api/v1/status");
            done(addr, &status).then_some(status)
        },
    )
    .unwrap_or_else(|| get_json(addr, "/api/v1/status"))
}

fn pose(v: &Value) -> Isometry3<f64> {
    let t: [f64; 3] = serde_json::from_value(v["translation"].clone()).unwrap();
    let q: [f64; 4] = serde_json::from_value(v["rotation_xyzw"].clone()).unwrap();
    Isometry3::from_parts(
        Translation3::new(t[0], t[1], t[2]),
        UnitQuaternion::from_quaternion(Quaternion::new(q[3], q[0], q[1], q[2])),
    )
}

/// Keyframes by id: (capture time, world_from_cam).
fn keyframes(addr: SocketAddr) -> BTreeMap<u64, (f64, Isometry3<f64>)> {
    get_json(addr, "/api/v1/keyframes")["keyframes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|k| {
            (
                k["id"].as_u64().unwrap(),
                (k["timestamp"].as_f64().unwrap(), pose(&k["world_from_cam"])),
            )
        })
        .collect()
}

/// Diagonal of the keyframe centres' bounding box.
fn extent(kfs: &BTreeMap<u64, (f64, Isometry3<f64>)>) -> f64 {
    (0..3)
        .map(|i| {
            let (lo, hi) = kfs.values().fold((f64::MAX, f64::MIN), |(lo, hi), (_, p)| {
                let c = p.translation.vector[i];
                (lo.min(c), hi.max(c))
            });
            (hi - lo).powi(2)
        })
        .sum::<f64>()
        .sqrt()
}

/// Position and rotation (degrees) differences of two camera poses.
fn differ(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    (
        (a.translation.vector - b.translation.vector).norm(),
        a.rotation.angle_to(&b.rotation).to_degrees(),
    )
}

const ANCHORS: [[u32; 2]; 4] = [[40, 30], [600, 30], [600, 450], [40, 450]];

/// Post the anchors shot on `kid`; its localised pose, if localised.
/// `None` when the keyframe is gone: the mapper culls redundant keyframes
/// of a young map, so one listed a moment ago may no longer exist (404).
fn anchors_shot(addr: SocketAddr, kid: u64) -> Option<(String, Option<Isometry3<f64>>, Value)> {
    let body = json!({"keyframe_id": kid, "anchors": ANCHORS, "width": 320, "height": 240});
    let (st, b) = http(addr, "POST", "/api/v1/shots", Some(&body));
    if st == 404 {
        eprintln!("keyframe {kid} culled since it was listed");
        return None;
    }
    assert_eq!(st, 201, "{}", String::from_utf8_lossy(&b));
    let shot: Value = serde_json::from_slice(&b).unwrap();
    let id = shot["id"].as_str().unwrap().to_owned();
    let p = (shot["status"] == "localised").then(|| pose(&shot["localisation"]["world_from_cam"]));
    Some((id, p, shot))
}

/// A keyframe's image from the middle of the map, sent as a picture: its
/// id and JPEG bytes. Tries the keyframes from the middle outwards, since
/// one listed may be culled before its image is asked for (404).
fn middle_keyframe_image(addr: SocketAddr) -> (u64, Vec<u8>) {
    let ids: Vec<u64> = keyframes(addr).keys().copied().collect();
    let mid = ids.len() / 2;
    let mut order: Vec<usize> = (0..ids.len()).collect();
    order.sort_by_key(|&i| i.abs_diff(mid));
    for i in order {
        let (st, jpeg) = http(
            addr,
            "GET",
            &format!("/api/v1/keyframes/{}/image.jpg", ids[i]),
            None,
        );
        match st {
            200 => return (ids[i], jpeg),
            404 => eprintln!("keyframe {} culled since it was listed", ids[i]),
            _ => panic!("keyframe image: HTTP {st}"),
        }
    }
    panic!("no keyframe image among {ids:?}");
}

/// Post a photo (JPEG bytes, the map camera's size); its id and localised
/// pose, if localised.
fn photo_shot(addr: SocketAddr, jpeg: &[u8]) -> (String, Option<Isometry3<f64>>) {
    let (st, b) = request(addr, "POST", "/api/v1/shots/photo", "image/jpeg", jpeg);
    assert_eq!(st, 201, "{}", String::from_utf8_lossy(&b));
    let shot: Value = serde_json::from_slice(&b).unwrap();
    let p = (shot["status"] == "localised").then(|| pose(&shot["localisation"]["world_from_cam"]));
    if p.is_none() {
        eprintln!("photo not localised: {}", shot["reason"]);
    }
    (shot["id"].as_str().unwrap().to_owned(), p)
}

#[test]
fn the_daemon_continues_on_its_saved_map() {
    let dir = tempfile::tempdir().unwrap();
    let base = dir.path().to_owned();

    // Run 1: a fresh map, tracked for a while, and a shot localised in it.
    let t0 = Instant::now();
    let d = start(&base);
    let status = wait_status(&d, 90, |_, s| {
        let s = &s["slam"];
        s["state"] == "tracking"
            && s["keyframes"].as_u64().unwrap_or(0) >= 8
            && s["tracked"].as_u64().unwrap_or(0) >= 60
    });
    eprintln!(
        "run 1 after {:.1} s: {}",
        t0.elapsed().as_secs_f64(),
        status["slam"]
    );
    assert_eq!(status["slam"]["state"], "tracking", "{status}");
    assert_eq!(status["slam"]["map_start"]["mode"], "fresh", "{status}");
    let mut shot1 = None;
    let ids: Vec<u64> = keyframes(d.addr).keys().copied().collect();
    for &kid in ids.iter().rev().take(6) {
        let Some((sid, p, shot)) = anchors_shot(d.addr, kid) else {
            continue;
        };
        if let Some(p) = p {
            shot1 = Some((sid, kid, p));
            break;
        }
        eprintln!("shot on keyframe {kid} not localised: {}", shot["reason"]);
    }
    let (sid, kid, shot1_pose) = shot1.expect("a shot is localised in run 1");
    // A photo: a keyframe from the middle of the map, sent as a picture.
    let (pkid, photo) = middle_keyframe_image(d.addr);
    let (psid, photo1_pose) = photo_shot(d.addr, &photo);
    let photo1_pose = photo1_pose.expect("the photo is localised in run 1");
    let summary1 = d.stop(Duration::from_secs(60));
    let map_file = summary1.map_file.clone().expect("run 1 saved its map");
    let saved = shotpilot::slam::mapfile::load(&map_file).unwrap();
    let old: BTreeMap<u64, (f64, Isometry3<f64>)> = saved
        .keyframes()
        .map(|k| (k.id.0 as u64, (k.timestamp, k.world_from_cam())))
        .collect();
    assert!(old.contains_key(&kid), "the shot's keyframe is in the file");
    let old_max = *old.keys().max().unwrap();
    let old_extent = extent(&old);
    eprintln!(
        "run 1: {} keyframes (ids up to {old_max}), {} points, extent {old_extent:.3}; shot {sid} on keyframe {kid}",
        saved.keyframe_count(),
        saved.point_count()
    );

    // Run 2 on the same data directory: the saved map is continued.
    let t1 = Instant::now();
    let d = start(&base);
    // Until it has relocalised and made three keyframes of its own.
    let status = wait_status(&d, 90, move |addr, s| {
        let s = &s["slam"];
        !s["map_start"]["relocalised_at_frame"].is_null()
            && s["state"] == "tracking"
            && keyframes(addr).keys().filter(|&&id| id > old_max).count() >= 3
    });
    eprintln!(
        "run 2 after {:.1} s: {}",
        t1.elapsed().as_secs_f64(),
        status["slam"]
    );
    let start2 = &status["slam"]["map_start"];
    assert_eq!(start2["mode"], "continued", "{status}");
    assert_eq!(start2["keyframes"].as_u64().unwrap() as usize, old.len());
    assert_eq!(
        start2["points"].as_u64().unwrap() as usize,
        saved.point_count()
    );
    assert!(start2["relocalised_at_frame"].is_u64(), "{status}");
    assert_eq!(status["slam"]["state"], "tracking", "{status}");

    // The old keyframes are still there, with their capture times and (up
    // to the bundle adjustments that run since) their poses; the new ones
    // got new ids.
    let now = keyframes(d.addr);
    let kept: Vec<u64> = old
        .keys()
        .filter(|id| now.contains_key(id))
        .copied()
        .collect();
    let new: Vec<u64> = now.keys().filter(|&&id| id > old_max).copied().collect();
    eprintln!(
        "run 2: {} keyframes, {} of the {} old ones kept, {} new (ids {:?}..)",
        now.len(),
        kept.len(),
        old.len(),
        new.len(),
        new.first()
    );
    assert!(kept.len() * 10 >= old.len() * 8, "most old keyframes kept");
    assert!(kept.contains(&kid), "the shot's keyframe is kept");
    assert!(new.len() >= 3, "new keyframes are added after the old ids");
    assert!(
        now.keys().all(|id| old.contains_key(id) || *id > old_max),
        "no old id is reused"
    );
    let mut worst_kf = (0.0f64, 0.0f64);
    for id in &kept {
        let (t_old, p_old) = &old[id];
        let (t_now, p_now) = &now[id];
        assert_eq!(t_old, t_now, "keyframe {id} is the same keyframe");
        let (dp, da) = differ(p_old, p_now);
        worst_kf = (worst_kf.0.max(dp / old_extent), worst_kf.1.max(da));
    }
    eprintln!(
        "old keyframes moved at most {:.4} of the extent, {:.3} deg",
        worst_kf.0, worst_kf.1
    );
    // Run 1's final bundle adjustment and run 2's local ones nudge the old
    // keyframes (seen: at most 0.05-0.2 % of the extent, 0.02-0.05 deg); a
    // fresh map has its own origin and scale (run 1's extent after the
    // same flight time came out anywhere from 0.6 to 1.8 in five runs).
    assert!(worst_kf.0 < 0.01 && worst_kf.1 < 0.5, "{worst_kf:?}");

    // The shots from before the restart are listed with their poses, and
    // they localise again where they did.
    // The stored poses are the ones the missions were planned from: they
    // come back as they were.
    for (id, before) in [(&sid, &shot1_pose), (&psid, &photo1_pose)] {
        let listed = get_json(d.addr, &format!("/api/v1/shots/{id}"));
        assert_eq!(listed["status"], "localised", "{listed}");
        let (dp, da) = differ(before, &pose(&listed["localisation"]["world_from_cam"]));
        assert!(dp < 1e-9 && da < 1e-6, "shot {id} listed {dp} {da} off");
    }
    let (_, photo2_pose) = photo_shot(d.addr, &photo);
    let photo2_pose = photo2_pose.expect("the photo localises after the restart");
    let (dp, da) = differ(&photo1_pose, &photo2_pose);
    eprintln!(
        "photo shot {psid} (keyframe {pkid}) before vs after the restart: {dp:.4} ({:.4} of the extent), {da:.3} deg",
        dp / old_extent
    );
    // Tolerance: the same picture against the same map, so what can move
    // it is the map itself, whose old keyframes moved by at most
    // `worst_kf` (0.05-0.2 % of the extent, 0.02-0.04 deg seen), and the
    // matching's randomness. 0.5 % of the extent and 0.25 deg: a fresh
    // map (its own origin, scale and axes) would be off by a large part of
    // the extent.
    assert!(dp < 0.005 * old_extent && da < 0.25, "{dp} {da}");
    // The shot's keyframe is pinned (a shot was made on it): never culled.
    let (_, again, shot) = anchors_shot(d.addr, kid).expect("the shot's keyframe is kept");
    let again = again.unwrap_or_else(|| panic!("the shot localises after the restart: {shot}"));
    let (dp, da) = differ(&shot1_pose, &again);
    eprintln!(
        "anchors shot {sid} (keyframe {kid}) before vs after the restart: {dp:.4} ({:.4} of the extent), {da:.3} deg",
        dp / old_extent
    );
    // An anchors shot is a homography of a keyframe, which no camera pose
    // reproduces exactly when the scene has depth: a drawn zoom asks near
    // and far content to grow alike, and the camera comes from the depth
    // layer of the keyframe's points that the PnP's consensus keeps. The
    // keyframe has gained points since (run 2 maps around it), so the
    // consensus may keep another layer: seen 2.5-14 % of the extent
    // (0.7-3.2 deg) over four runs at 3d55722, against a move of 12.5 %
    // of the keyframe's median depth that this zoom (1.143x) asks for.
    // Bound: less than that move, and 5 deg (a known weakness: the
    // camera of a drawn zoom should not hinge on one layer).
    let zoom_move =
        (1.0 - 560.0 / 640.0) * saved.median_depth(KeyFrameId(kid as u32)).unwrap_or(0.0);
    eprintln!("the zoom's own move: {zoom_move:.4}");
    assert!(
        dp < zoom_move && da < 5.0,
        "{dp} {da} (zoom move {zoom_move})"
    );
    let summary2 = d.stop(Duration::from_secs(60));
    eprintln!(
        "run 2 summary: {}",
        serde_json::to_string(&summary2).unwrap()
    );
    let map_file2 = summary2.map_file.expect("run 2 saved its map");
    assert_eq!(
        map_file2, map_file,
        "the continued map replaces the old file"
    );
    let resaved = shotpilot::slam::mapfile::load(&map_file2).unwrap();
    assert!(resaved.keyframe_count() > old.len());

    // Run 3: a damaged map file. The daemon serves with a fresh map and
    // keeps the damaged file under a new name.
    let mut bytes = std::fs::read(&map_file).unwrap();
    let mid = bytes.len() / 2;
    bytes[mid] ^= 0xff;
    std::fs::write(&map_file, &bytes).unwrap();
    let d = start(&base);
    let status = wait_status(&d, 30, |_, s| !s["slam"]["map_start"].is_null());
    let start3 = &status["slam"]["map_start"];
    eprintln!("run 3: {start3}");
    assert_eq!(start3["mode"], "fresh_after_error", "{status}");
    assert!(
        start3["error"].as_str().unwrap().contains("checksum"),
        "{status}"
    );
    let aside = PathBuf::from(start3["set_aside"].as_str().unwrap());
    assert_eq!(
        std::fs::read(&aside).unwrap(),
        bytes,
        "the damaged file is kept"
    );
    assert!(!map_file.exists(), "the damaged file was moved, not copied");
    let status = wait_status(&d, 60, |_, s| s["slam"]["state"] == "tracking");
    assert_eq!(status["slam"]["state"], "tracking", "a fresh map: {status}");
    let shots = get_json(d.addr, "/api/v1/shots")["count"].as_u64().unwrap() as usize;
    assert_eq!(
        shots,
        summary1.shots + 2,
        "the shots of runs 1 and 2 are listed"
    );
    d.stop(Duration::from_secs(60));
    eprintln!("total {:.1} s", t0.elapsed().as_secs_f64());
}
