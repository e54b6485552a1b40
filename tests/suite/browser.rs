//! The operator's page in a real browser: the daemon runs with the simulator
//! in-process, and headless Chromium (Debian's `chromium`, driven by npm's
//! `playwright-core` from `tests/browser/node_modules`) opens the page, sees
//! live video and keyframes, drags the four anchors of a desired shot on a
//! keyframe, submits it and sees the result; the shots panel shows each
//! shot's refinement rounds and stop reason (two refined shots are in the
//! data directory before the daemon starts), and the status line says the
//! damaged map file found there was not used; once georeferenced, the world
//! map draws the vehicle within 1 m of the simulator's truth, a keyframe
//! clicked on the map opens in the editor, and Stop during the scripted
//! flight is acknowledged and the vehicle holds (the truth). The whole
//! shot's first flight lands off its target by what the simulated GNSS
//! altitude drifted since the georeference (seeded); its timeline shows
//! the rounds, the localisation's sigma and, unless the loop judged the
//! first look already at the shot's floor, a correction flown and a
//! smaller error after it. The daemon runs on simulated time (the
//! simulator in lockstep with the SLAM), the page in Chromium's real time. The keyframe gallery is
//! bounded (3 newest and those shots use, here); the loops-closed badge,
//! the map's loops and its list of map events follow the status. The
//! tracked-features toggle (by keyboard) draws a tracked frame's keypoints
//! on that frame in their states' colours, as many per state as the API
//! says of the same frame. Each correction's flight on the timeline began
//! the correction's length away. A screenshot of each stage is saved
//! beside the main one.
//!
//! Needs `node`, `npm ci` in `tests/browser` and Chromium; `.ci/run` sets
//! them up. Environment: `SHOTPILOT_CHROMIUM` (default `/usr/bin/chromium`),
//! `SHOTPILOT_NODE` (default `node`), `SHOTPILOT_SCREENSHOT` (default
//! `<target>/tmp/browser/operator_page.png`).

use crate::daemon_support;

use daemon_support::{TOKEN, get_json};

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use serde_json::{Value, json};
use shotpilot::mission::plan::Target;
use shotpilot::refine::record::record_abort;
use shotpilot::refine::{Correction, Decision, RoundRecord};
use shotpilot::shot::record::{
    Localisation, MissionRecord, MissionState, PoseJson, Shot, ShotSource, ShotStatus,
};
use shotpilot::shot::store::ShotStore;

/// The simulated GNSS's vertical bias (`[sim] gps_*`): a Gauss-Markov walk
/// of this deviation, m, ...
const GPS_SIGMA_Z_M: f64 = 2.0;
/// ... correlation time, s, ...
const GPS_TAU_S: f64 = 300.0;
/// ... and seed.
const GPS_SEED: u64 = 2658;

/// A refinement round as the daemon records it.
fn round(
    n: usize,
    pct: Option<f64>,
    decision: Decision,
    step: Option<[f64; 3]>,
    note: Option<&str>,
) -> Value {
    let target = Target {
        lat_deg: 47.397742,
        lon_deg: 8.545594,
        alt_m: 12.0,
        yaw_deg: 90.0,
        gimbal_pitch_deg: -30.0,
        photo: false,
    };
    let r = RoundRecord {
        round: n,
        target,
        shot_error_pct: pct,
        shot_error_px: pct.map(|p| p / 100.0 * 800.0),
        inliers: pct.map(|_| 212 + n),
        frames: 5,
        frames_with_error: if pct.is_some() { 5 } else { 0 },
        shot_error_spread_pct: pct.map(|p| p / 10.0),
        floor_pct: pct.map(|p| p / 4.0),
        pose_framing_pct: None,
        decision,
        live_map_position: None,
        offset: None,
        correction: step.map(|s| Correction {
            target,
            step_ned_m: s,
            error_ned_m: s.map(|v| 2.0 * v),
            yaw_error_deg: 2.5,
            pitch_error_deg: -1.0,
            yaw_step_deg: 1.25,
            pitch_step_deg: -0.5,
            limited: false,
        }),
        note: note.map(str::to_owned),
        observed: None,
    };
    serde_json::to_value(r).unwrap()
}

/// Two shots whose started missions were refined, written into the shot
/// store before the daemon starts: `shot-1` converged after one correction,
/// `shot-2` was aborted by the daemon after a round without a shot error.
/// Returns their ids.
fn seed_refined_shots(dir: &Path) -> Vec<String> {
    let store = ShotStore::open(dir).unwrap();
    let mut ids = Vec::new();
    for (i, (rounds, stop, abort)) in [
        (
            vec![
                round(
                    0,
                    Some(3.214),
                    Decision::Correct,
                    Some([1.5, -0.25, 0.75]),
                    None,
                ),
                round(1, Some(0.642), Decision::Converged, None, None),
            ],
            json!("converged"),
            None,
        ),
        (
            vec![round(
                0,
                None,
                Decision::Correct,
                None,
                Some("live frame: not enough matches"),
            )],
            Value::Null,
            Some("no arrival at the waypoint within 120 s"),
        ),
    ]
    .into_iter()
    .enumerate()
    {
        let mut mission = MissionRecord {
            state: MissionState::Started,
            items: 4,
            uploaded_unix: 1.7e9,
            started_unix: Some(1.7e9 + 1.0),
            target_lat_lon_alt: Some([47.397742, 8.545594, 500.0]),
            details: json!({"refinement": {"rounds": rounds, "stop": stop, "reason": null}}),
        };
        if let Some(why) = abort {
            record_abort(&mut mission, why);
        }
        let shot = Shot {
            id: store.next_id(),
            created_unix: 1.7e9 + i as f64,
            source: ShotSource::Anchors {
                keyframe_id: 0,
                anchors: [[40.0, 30.0], [600.0, 30.0], [600.0, 450.0], [40.0, 450.0]],
            },
            status: ShotStatus::Localised,
            localisation: Some(Localisation {
                sigma: None,
                world_from_cam: PoseJson {
                    translation: [0.1, -0.2, 0.3],
                    rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
                },
                inliers: 300,
                rms_error_px: 1.5,
                keyframe_id: Some(0),
            }),
            reason: None,
            nearest_keyframes: Vec::new(),
            has_image: false,
            mission: Some(mission),
        };
        ids.push(shot.id.clone());
        store.put(shot, None).unwrap();
    }
    ids
}

/// The page's card of a refined shot shows the stored rounds (error,
/// decision, correction, note, floor) and the stop reason.
fn check_refinement_card(card: &Value, rf: &Value) {
    let rows = card["rounds"].as_array().unwrap();
    let rounds = rf["rounds"].as_array().unwrap();
    assert_eq!(rows.len(), rounds.len(), "{card} vs {rf}");
    for (row, r) in rows.iter().zip(rounds) {
        let cell = |i: usize| row[i].as_str().unwrap().to_owned();
        assert_eq!(cell(0), r["round"].to_string());
        let pct = r["shot_error_pct"]
            .as_f64()
            .map_or("–".to_string(), |p| format!("{p:.2}"));
        assert_eq!(cell(1), pct, "{row}");
        assert_eq!(cell(4), r["decision"].as_str().unwrap(), "{row}");
        match r["correction"]["step_ned_m"].as_array() {
            Some(step) => {
                let s: Vec<String> = step
                    .iter()
                    .map(|v| format!("{:.2}", v.as_f64().unwrap()))
                    .collect();
                assert_eq!(cell(5), s.join(", "), "{row}");
            }
            None => assert_eq!(cell(5), "–", "{row}"),
        }
        assert_eq!(cell(8), r["note"].as_str().unwrap_or(""), "{row}");
        let floor = r["floor_pct"]
            .as_f64()
            .map_or("–".to_string(), |p| format!("{p:.2}"));
        assert_eq!(cell(9), floor, "{row}");
    }
    let stop = rf["stop"].as_str().unwrap();
    assert_eq!(card["stop"]["key"], stop, "{card}");
    let text = card["stop"]["text"].as_str().unwrap();
    assert!(text.contains(stop), "{text}");
    if let Some(reason) = rf["reason"].as_str() {
        assert!(text.contains(reason), "{text} vs {reason}");
    }
}

/// The page's timeline of the whole shot shows what the daemon stored
/// (each round's shot error, how it ended), the outline overlay was drawn
/// with four finite corners inside a frame's reach and a shot error, and
/// the downloaded before/after PNG is the three panels of the camera's
/// frame.
fn check_whole_shot(addr: std::net::SocketAddr, seen: &Value) {
    let a = seen["shot_a"]["id"].as_str().unwrap();
    let stored = get_json(addr, &format!("/api/v1/shots/{a}"));
    let rf = &stored["mission"]["details"]["refinement"];
    let rounds = rf["rounds"].as_array().expect("rounds recorded");
    let tl = seen["timeline_a"].as_array().unwrap();
    eprintln!("timeline of {a}:");
    for l in tl {
        eprintln!("  {}", l["text"].as_str().unwrap_or(""));
    }
    let kinds: Vec<&str> = tl.iter().map(|l| l["kind"].as_str().unwrap()).collect();
    let pos = |k: &str| kinds.iter().position(|x| *x == k);
    let order = [
        "localised",
        "georeferenced",
        "uploaded",
        "started",
        "flying",
        "arrived",
        "round",
    ];
    let at: Vec<Option<usize>> = order.iter().map(|k| pos(k)).collect();
    assert!(
        at.iter().all(Option::is_some) && at.windows(2).all(|w| w[0] < w[1]),
        "the timeline of {a} is out of order or lacks a step: {kinds:?}"
    );
    let shown: Vec<&Value> = tl.iter().filter(|l| l["kind"] == "round").collect();
    assert_eq!(shown.len(), rounds.len(), "{kinds:?} vs {rf}");
    let pct = |r: &Value| r["shot_error_pct"].as_f64();
    eprintln!(
        "refinement of {a}: shot error per round {:?} %, stop {}",
        rounds.iter().map(pct).collect::<Vec<_>>(),
        rf["stop"]
    );
    let first = pct(&rounds[0]).unwrap_or_else(|| panic!("round 0 without a shot error: {rf}"));
    let margin = shotpilot::refine::ControllerParams::default().at_floor_margin_pct;
    // The loop ends where the measurement says it can do no better
    // (under the threshold, or near the shot's floor without gaining).
    let stop = rf["stop"].as_str().unwrap_or("");
    assert!(
        stop == "converged" || stop == "at_floor",
        "the loop ended {stop}, not converged or at_floor: {rf}"
    );
    // The vertical GPS bias drifts between the georeference's fit and the
    // first arrival, by how much depends on when (in simulated time) the
    // page started the shot. A first flight the loop judges already at
    // the shot's floor stops there, flying nothing (a correction then
    // would chase the drift): its error within the at_floor margin of the
    // floor (or twice the measurement's noise), or the live camera within
    // the threshold's framing of the shot's pose and its error within the
    // threshold of the floor (the session's rules, unit-tested in
    // `refine::session`). Measured on simulated time: 10 of 14 runs
    // stopped so (first looks 2.89-3.68 % against floors 2.58-3.23 %, the
    // live camera 0.46-0.92 % of framing from the shot's pose), 4 flew one
    // correction and gained 0.09-0.39 %.
    let r0 = &rounds[0];
    let floor = r0["floor_pct"].as_f64().unwrap_or(f64::NAN);
    let noise = shotpilot::refine::median_noise_pct(
        r0["shot_error_spread_pct"].as_f64(),
        r0["frames_with_error"].as_u64().unwrap_or(1) as usize,
    );
    if rounds.len() == 1 {
        let threshold = shotpilot::refine::ControllerParams::default().threshold_pct;
        let framing = r0["pose_framing_pct"].as_f64();
        let at_floor = first <= floor + margin.max(noise) + 1e-9
            || (framing.is_some_and(|f| f < threshold) && first <= floor + threshold);
        assert!(
            (stop == "converged" && first <= threshold) || (stop == "at_floor" && at_floor),
            "the loop stopped after its first flight ({first} %, floor {floor} %, framing {framing:?} %) as {stop}: {rf}"
        );
    } else {
        // The first flight landed off: a correction is uploaded and flown,
        // and the shot error it measures there is smaller. The GPS bias
        // keeps drifting while the corrections are flown, so one round may
        // measure worse than the one before; the corrections must still
        // reach a framing better than the first flight's.
        assert_eq!(rounds[0]["decision"], "correct", "{rf}");
        assert!(rounds[0]["correction"].is_object(), "{rf}");
        let best = rounds[1..]
            .iter()
            .map(|r| pct(r).unwrap_or_else(|| panic!("a round without a shot error: {rf}")))
            .fold(f64::INFINITY, f64::min);
        // A first flight only just over the at_floor margin is corrected,
        // but no correction can then gain what the loop counts as a gain
        // (the margin) beyond the noise of a look: one that measures
        // within it stops at_floor. That noise is more than one round's
        // spread over its frames (0.06-0.11 %): the GNSS bias moves the
        // holding vehicle between two looks, and in 13 runs the second
        // look differed from the first by -0.49 to +0.19 % (0.2 % RMS)
        // after corrections of about 0.6 m that left the framing as it
        // was (first flights 2.94-3.51 % against floors 2.60-3.05 %; seen
        // failing before this allowance: 3.37 -> 3.42 % against 3.05 %,
        // 3.00 -> 3.08 % against 2.64 %).
        const LOOK_TO_LOOK_PCT: f64 = 0.2;
        let just_over = stop == "at_floor"
            && first <= floor + margin + noise.hypot(2.0 * LOOK_TO_LOOK_PCT) + 1e-9;
        assert!(
            best < first || just_over,
            "no correction improved on the first flight's {first} % (floor {floor} %, noise {noise} %): {rf}"
        );
    }
    // The loop ends on a view no worse than its first flight's: near the
    // floor it stops on its best round, flying back to it if the last
    // measured worse.
    let last = rounds
        .last()
        .and_then(pct)
        .unwrap_or_else(|| panic!("the last round without a shot error: {rf}"));
    // No worse within the at_floor margin (0.3 %), the difference the loop
    // treats as equal: a first flight near the floor is itself the best
    // round, and a correction that lands within the margin of it stops
    // there (seen: 3.35 then 3.51 %); what must not happen is a loop that
    // flies on and ends clearly worse (seen before the near-floor stop:
    // 3.66 then 4.17 %).
    assert!(
        last <= first + margin,
        "the loop ended at {last} %, worse than its first flight's {first} % by more than {margin} %: {rf}"
    );
    // The localisation's sigma on the timeline: % of the distance and
    // degrees at `localised`, metres (through the georeference's scale)
    // at `georeferenced`.
    let sigma = &stored["localisation"]["sigma"];
    let at = |k: &str| tl.iter().find(|l| l["kind"] == k).unwrap();
    let close = |a: &Value, b: f64| (a.as_f64().unwrap() - b).abs() <= 1e-9 * b.abs().max(1.0);
    if let Some(f) = sigma["position_fraction_of_distance"].as_f64() {
        let l = at("localised");
        assert!(close(&l["sigma_pct"], 100.0 * f), "{l} vs {sigma}");
        assert!(
            close(&l["sigma_deg"], sigma["rotation_deg"].as_f64().unwrap()),
            "{l} vs {sigma}"
        );
        assert!(l["text"].as_str().unwrap().contains("sigma"), "{l}");
        let scale = stored["mission"]["details"]["georeference"]["scale"]
            .as_f64()
            .unwrap();
        let g = at("georeferenced");
        let m = sigma["position"].as_f64().unwrap() * scale;
        assert!(close(&g["sigma_m"], m), "{g} vs {sigma} x {scale}");
        assert!(
            g["text"].as_str().unwrap().contains("position sigma"),
            "{g}"
        );
    } else {
        panic!("the shot reports no sigma: {stored}");
    }
    // Each correction's flight on the timeline began its length away (the
    // straight line: the simulated GNSS bias is vertical, so a correction
    // is mostly vertical and its horizontal part about 0). The vehicle
    // held the last round's target, by its own report, when it began.
    for w in rounds.windows(2) {
        let Some(step) = w[0]["correction"]["step_ned_m"].as_array() else {
            continue;
        };
        let len = step
            .iter()
            .map(|v| v.as_f64().unwrap().powi(2))
            .sum::<f64>()
            .sqrt();
        let r = w[1]["round"].as_u64().unwrap();
        let fl = tl
            .iter()
            .find(|l| l["kind"] == "flying" && l["round"].as_u64() == Some(r))
            .unwrap_or_else(|| panic!("no flying line for round {r}: {kinds:?}"));
        let start = fl["start"].as_f64().unwrap();
        eprintln!("round {r}: correction of {len:.3} m, flight began {start:.3} m away");
        assert!(
            (start - len).abs() <= (0.3 * len).max(0.3),
            "round {r}'s flight began {start} m away for a correction of {len} m: {fl}"
        );
    }
    for (l, r) in shown.iter().zip(rounds) {
        assert_eq!(l["round"], r["round"], "{l} vs {r}");
        match r["shot_error_pct"].as_f64() {
            Some(e) => {
                let got = l["error"].as_f64().unwrap();
                assert!((got - e).abs() < 1e-9, "{l} vs {r}");
            }
            None => assert!(l["error"].is_null(), "{l} vs {r}"),
        }
    }
    let last = tl.last().unwrap();
    assert_eq!(last["kind"], "done", "{kinds:?}");
    let stop = rf["stop"].as_str().unwrap();
    assert!(
        last["text"]
            .as_str()
            .unwrap()
            .contains(&format!("done: {stop}")),
        "{last} vs {rf}"
    );

    let ov = &seen["overlay"];
    assert_eq!(ov["shot"], a, "{ov}");
    assert!(ov["visible"].as_bool().unwrap(), "{ov}");
    let corners = ov["corners"].as_array().unwrap();
    assert_eq!(corners.len(), 4, "{ov}");
    for c in corners {
        for k in 0..2 {
            let v = c[k].as_f64().unwrap();
            // Finite, and within a frame's width of the 640x480 frame.
            assert!((-640.0..1280.0).contains(&v), "{ov}");
        }
    }
    let err = ov["error"].as_f64().unwrap();
    assert!((0.0..100.0).contains(&err), "{ov}");
    assert!(ov["info"].as_str().unwrap().contains("shot error"), "{ov}");

    let ba = &seen["before_after"];
    assert_eq!(ba["state"], "ready", "{ba}");
    for wh in ba["images"].as_array().unwrap() {
        assert_eq!(wh, &serde_json::json!([640, 480]), "{ba}");
    }
    // The final error shown is the last round's.
    let final_err = rounds.last().and_then(|r| r["shot_error_pct"].as_f64());
    let shown = ba["error"].as_str().and_then(|e| e.parse::<f64>().ok());
    match (final_err, shown) {
        (Some(e), Some(s)) => assert!((e - s).abs() < 1e-9, "{ba} vs {e}"),
        (None, None) => {}
        (e, s) => panic!("final error {e:?}, the page shows {s:?}: {ba}"),
    }
    assert!(
        ba["title"].as_str().unwrap().contains("final shot error"),
        "{ba}"
    );
    let png = seen["before_after_png"].as_str().unwrap();
    let img = image::open(png).unwrap_or_else(|e| panic!("{png}: {e}"));
    // Three 640x480 panels 8 px apart under a 27 px band of text.
    assert_eq!(
        (img.width(), img.height()),
        (3 * 640 + 16, 480 + 27),
        "{png}"
    );
    eprintln!("before/after PNG: {png}");
}

#[test]
#[ignore = "needs chromium and playwright-core"]
fn operator_page_in_headless_chromium() {
    let root = crate::repo_root();
    let script = root.join("tests/browser/page_test.js");
    assert!(
        root.join("tests/browser/node_modules/playwright-core")
            .is_dir(),
        "run `npm ci` in tests/browser first"
    );
    let chromium =
        std::env::var("SHOTPILOT_CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        Path::new(&chromium).is_file(),
        "no Chromium at {chromium} (SHOTPILOT_CHROMIUM)"
    );
    let node = std::env::var("SHOTPILOT_NODE").unwrap_or_else(|_| "node".into());
    let shot_png = std::env::var("SHOTPILOT_SCREENSHOT")
        .map(PathBuf::from)
        .unwrap_or_else(|_| {
            Path::new(env!("CARGO_TARGET_TMPDIR")).join("browser/operator_page.png")
        });
    if let Some(d) = shot_png.parent() {
        std::fs::create_dir_all(d).unwrap();
    }
    let _ = std::fs::remove_file(&shot_png);

    let dir = tempfile::tempdir().unwrap();
    let seeded = seed_refined_shots(&dir.path().join("data/shots"));
    // A damaged map file: the daemon starts a fresh map, keeps the file
    // aside, and the page says so.
    std::fs::write(dir.path().join("data/map.spmap"), b"not a map").unwrap();
    let (mut cfg, sockets) = daemon_support::sim_config();
    // The simulator's truth: camera poses (local NED at home) per frame.
    cfg.sim.truth_dir = Some("truth".into());
    // A GNSS whose altitude drifts (a Gauss-Markov bias, seeded): the
    // vehicle truly flies higher or lower than it reports, so the whole
    // shot's first flight lands off its target by what the bias moved
    // since the georeference was fitted, and the refinement loop corrects
    // it when that is more than the shot's floor allows. Vertical only: the map's vehicle marker (horizontal) is checked
    // against the truth within 1 m. Walk GPS_SEED ... (see GPS_*).
    cfg.sim.gps_sigma_z_m = GPS_SIGMA_Z_M;
    cfg.sim.gps_tau_s = GPS_TAU_S;
    cfg.sim.gps_seed = Some(GPS_SEED);
    cfg.validate(Path::new("test")).unwrap();
    let truth_dir = dir.path().join(&cfg.server.data_dir).join("truth");

    let log = shot_png.with_file_name("daemon.log");
    eprintln!("the daemon's log: {}", log.display());
    // On simulated time (the simulator in lockstep with the SLAM): no
    // frame is dropped and no timer fires early because the machine is
    // busy. The page itself runs in Chromium's real time: its waits are
    // for states the daemon reaches, with generous limits.
    let daemon = daemon_support::start_on_sim_time_logged(cfg, sockets, dir.path(), &log);
    let addr = daemon.addr;
    let (t0, sim0) = (Instant::now(), daemon.now());

    // SLAM tracks and has keyframes before the page is opened.
    let ready = daemon.poll(
        Duration::from_secs(90),
        Duration::from_millis(500),
        move || {
            let status = get_json(addr, "/api/v1/status");
            let s = &status["slam"];
            (s["state"] == "tracking" && s["keyframes"].as_u64().unwrap_or(0) >= 5).then_some(())
        },
    );
    assert!(
        ready.is_some(),
        "not tracking with 5 keyframes after 90 s simulated: {}",
        get_json(addr, "/api/v1/status")
    );
    eprintln!(
        "SLAM ready after {:.1} s simulated ({:.1} s wall)",
        (daemon.now() - sim0).as_secs_f64(),
        t0.elapsed().as_secs_f64()
    );

    let t_page = Instant::now();
    let out = Command::new(&node)
        .arg(&script)
        .env("SHOTPILOT_URL", format!("http://{addr}"))
        .env("SHOTPILOT_TOKEN", TOKEN)
        .env("SHOTPILOT_CHROMIUM", &chromium)
        .env("SHOTPILOT_SCREENSHOT", &shot_png)
        .output()
        .unwrap_or_else(|e| panic!("cannot run {node}: {e}"));
    let page_secs = t_page.elapsed().as_secs_f64();
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.success(),
        "page test failed ({}):\n{stderr}\n{stdout}",
        out.status
    );
    let seen: Value = serde_json::from_str(stdout.trim().lines().last().unwrap_or("")).unwrap();
    eprintln!("the page saw: {seen}");
    eprintln!(
        "page test took {page_secs:.1} s; screenshot: {}",
        shot_png.display()
    );

    // What the page showed is what the daemon holds.
    assert!(seen["keyframes_listed"].as_u64().unwrap() >= 3);
    // The tracked features (the page compared them with the API's reply
    // for the frame drawn): a tracked frame has inliers, and at most
    // `[server] features_max` keypoints were drawn.
    let fl = &seen["features"];
    eprintln!("tracked features drawn: {fl}");
    assert!(fl["counts"]["inlier"].as_u64().unwrap() > 0, "{fl}");
    let drawn: u64 = ["inlier", "outlier", "unmatched"]
        .iter()
        .map(|k| fl["drawn"][k].as_u64().unwrap())
        .sum();
    assert!(drawn > 0 && drawn <= 500, "{fl}");
    // The gallery is bounded: the newest 3 and those shots use (the page
    // compared them with the daemon's lists), fewer than the map holds.
    let g = &seen["gallery"];
    let shown = g["shown"].as_array().unwrap().len();
    assert!(
        shown <= 3 + g["pins"].as_array().unwrap().len()
            && (shown as u64) < g["total"].as_u64().unwrap(),
        "{g}"
    );
    // Loops closed: the badge counts them, the map joins the keyframes
    // each closed (those still in the map).
    let lp = &seen["loops"];
    let n = lp["status"]["loops_closed"].as_u64().unwrap();
    let m = lp["status"]["merges_made"].as_u64().unwrap();
    let merged = match m {
        0 => String::new(),
        1 => " · 1 map merged".to_string(),
        m => format!(" · {m} maps merged"),
    };
    assert_eq!(
        lp["badge"],
        format!("{n} loop{} closed{merged}", if n == 1 { "" } else { "s" }),
        "{lp}"
    );
    let pairs = lp["status"]["loops"].as_array().unwrap();
    for d in lp["drawn"].as_array().unwrap() {
        assert!(pairs.contains(d), "drawn {d}, closed {pairs:?}");
    }
    // The map's events list every loop the status lists, newest first.
    let listed: Vec<&Value> = lp["events"].as_array().unwrap().iter().collect();
    let newest_first: Vec<&Value> = pairs.iter().rev().collect();
    assert_eq!(listed, newest_first, "{lp}");
    // And every merge the status lists (a flight with a tracking loss).
    let merges = lp["status"]["merges"].as_array().unwrap();
    let listed: Vec<&Value> = lp["merge_events"].as_array().unwrap().iter().collect();
    let newest_first: Vec<&Value> = merges.iter().rev().collect();
    assert_eq!(listed, newest_first, "{lp}");
    eprintln!("loops and merges: {lp}");
    let shots = get_json(addr, "/api/v1/shots");
    // The first shot, then the whole shot's, then the second shot (which
    // may have taken a few keyframes to localise).
    assert!(
        shots["count"].as_u64().unwrap() >= 3 + seeded.len() as u64,
        "{shots}"
    );
    let id = seen["shot"]["id"].as_str().unwrap();
    let shot = get_json(addr, &format!("/api/v1/shots/{id}"));
    assert_eq!(shot["status"], seen["shot"]["state"], "{shot}");
    assert_eq!(shot["source"]["keyframe_id"], seen["keyframe"], "{shot}");
    let sent = shot["source"]["anchors"].as_array().unwrap();
    let dragged = seen["anchors"].as_array().unwrap();
    for (a, b) in sent.iter().zip(dragged) {
        for k in 0..2 {
            let (x, y) = (a[k].as_f64().unwrap(), b[k].as_f64().unwrap());
            assert!((x - y).abs() <= 0.051, "sent {a} vs dragged {b}");
        }
    }
    // The page shows the daemon's numbers: pose and inliers, or the reason.
    let text = seen["shot"]["text"].as_str().unwrap();
    if shot["status"] == "localised" {
        let l = &shot["localisation"];
        let t: Vec<String> = l["world_from_cam"]["translation"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| format!("{:.3}", v.as_f64().unwrap()))
            .collect();
        assert!(
            text.contains(&format!("camera at ({})", t.join(", "))),
            "{text} vs {l}"
        );
        assert!(
            text.contains(&format!("inliers {}", l["inliers"])),
            "{text} vs {l}"
        );
    } else {
        let reason = shot["reason"].as_str().unwrap();
        assert!(
            !reason.is_empty() && text.contains(reason),
            "{text} vs {reason}"
        );
    }
    let line = seen["status_line"].as_str().unwrap();
    assert!(
        line.contains("saved map not used") && line.contains("bad magic"),
        "{line}"
    );
    let kept = std::fs::read_dir(dir.path().join("data"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| p.to_string_lossy().contains("map.spmap.unusable-"))
        .expect("the damaged map file is kept aside");
    assert_eq!(std::fs::read(&kept).unwrap(), b"not a map");
    // The shots panel: every shot, newest first, and each refined shot's
    // rounds and stop reason as the daemon stores them.
    let panel = seen["shots_panel"].as_array().unwrap();
    let ids: Vec<&str> = panel.iter().map(|c| c["id"].as_str().unwrap()).collect();
    assert_eq!(ids, [id, "shot-2", "shot-1"], "{panel:?}");
    for sid in &seeded {
        let stored = get_json(addr, &format!("/api/v1/shots/{sid}"));
        let rf = &stored["mission"]["details"]["refinement"];
        let card = panel.iter().find(|c| c["id"] == *sid).unwrap();
        check_refinement_card(card, rf);
    }
    let new_card = &panel[0];
    assert!(new_card["rounds"].as_array().unwrap().is_empty());
    assert!(new_card["stop"].is_null(), "{new_card}");
    // The desired shot is the keyframe's size (no size was given).
    assert_eq!(seen["shot_image"], serde_json::json!([640, 480]));
    let png = std::fs::metadata(&shot_png).expect("the screenshot was saved");
    assert!(png.len() > 10_000, "screenshot of {} bytes", png.len());
    for st in seen["stages"].as_array().unwrap() {
        let p = st.as_str().unwrap();
        let len = std::fs::metadata(p).map_or(0, |m| m.len());
        assert!(len > 10_000, "stage screenshot {p}: {len} bytes");
        eprintln!("stage screenshot: {p}");
    }

    // The whole shot: its timeline as the daemon recorded it, the outline
    // overlay and the before/after PNG.
    check_whole_shot(addr, &seen);

    // The map's vehicle marker against the simulator's truth (the camera's
    // centre, 13 cm from the vehicle's), each sample at the truth frame
    // nearest its time.
    let truth = shotpilot_sim::dataset::read_truth_frames(&truth_dir.join("frames.txt"))
        .expect("the simulator's truth frames");
    let at = |t: f64| -> [f64; 2] {
        let (_, p) = truth
            .iter()
            .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
            .expect("truth frames");
        [p.translation.vector.x, p.translation.vector.y]
    };
    let samples = seen["vehicle_samples"].as_array().unwrap();
    eprintln!(
        "the map's vehicle marker was missing at: {}",
        seen["vehicle_missing"]
    );
    assert!(samples.len() >= 4, "{samples:?}");
    let mut worst: f64 = 0.0;
    for smp in samples {
        let t = smp["t"].as_f64().unwrap();
        let [n, e] = at(t);
        let d = (smp["n"].as_f64().unwrap() - n).hypot(smp["e"].as_f64().unwrap() - e);
        worst = worst.max(d);
    }
    let last_t = samples.last().unwrap()["t"].as_f64().unwrap();
    let d_last = {
        let s = samples.last().unwrap();
        let [n, e] = at(last_t);
        (s["n"].as_f64().unwrap() - n).hypot(s["e"].as_f64().unwrap() - e)
    };
    // Held: where the truth is when the page stopped sampling (at least
    // 8 s after the stop, once the marker kept still for 4 s, or after
    // about 40 s) against where it was when the stop was acknowledged, and
    // its drift over the last 4 s. Judged at the last marker sample
    // instead, a run whose marker went missing early (the map in the SLAM
    // view) measured the braking: 3.7 m in the 4 s up to 5.2 s after the
    // stop. Every time here is on the daemon's clock, as the truth is: the
    // page's own clock is not (on simulated time the daemon ran 0.55 m of
    // flight before the stop into a hold judged on the page's clock).
    let stop_t = seen["stop"]["at_unix"].as_f64().unwrap();
    let end_t = seen["hold_end_unix"].as_f64().unwrap_or(last_t).max(last_t);
    let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    let from_stop = dist(at(end_t), at(stop_t));
    let drift = dist(at(end_t), at(end_t - 4.0));
    // The speed when the stop was acknowledged (truth over 0.4 s), and the
    // distance a braking at half the vehicle's 3 m/s² limit needs from it:
    // the vehicle may brake that far, plus 0.5 m, and no further.
    let v_stop = dist(at(stop_t + 0.2), at(stop_t - 0.2)) / 0.4;
    let braking_m = 0.5 + v_stop * v_stop / (2.0 * 1.5);
    eprintln!(
        "map marker vs truth: last {d_last:.2} m, worst of {} samples over {:.1} s after the stop {worst:.2} m; \
         truth {:.1} s after the stop: {from_stop:.2} m from where it was at the stop's ACK (speed then {v_stop:.2} m/s, \
         braking allowance {braking_m:.2} m), drift over the last 4 s {drift:.3} m",
        samples.len(),
        last_t - stop_t,
        end_t - stop_t
    );
    assert!(
        d_last < 1.0,
        "the map's vehicle is {d_last:.2} m from the truth"
    );
    assert!(drift < 0.2, "the vehicle drifts {drift:.3} m while holding");
    assert!(
        from_stop < braking_m,
        "the vehicle holds {from_stop:.2} m from where it was when the stop was acknowledged \
         at {v_stop:.2} m/s (braking allowance {braking_m:.2} m)"
    );
    // The stopped flight is the second shot's: the hold mode is in the
    // status, and the shot is marked stopped.
    let st = get_json(addr, "/api/v1/status");
    let mode = st["vehicle"]["mode"].as_str().unwrap_or("");
    assert!(
        mode == "AUTO.LOITER" || mode == "LOITER",
        "vehicle mode after the stop: {mode}"
    );
    let b = seen["shot_b"]["id"].as_str().unwrap();
    let shot_b = get_json(addr, &format!("/api/v1/shots/{b}"));
    assert_eq!(shot_b["mission"]["state"], "stopped", "{shot_b}");
    let kinds: Vec<&str> = seen["timeline_b"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["kind"].as_str().unwrap())
        .collect();
    for k in ["localised", "uploaded", "started", "flying", "stopped"] {
        assert!(kinds.contains(&k), "{b}'s timeline lacks {k}: {kinds:?}");
    }

    daemon.stop(Duration::from_secs(30));
}
