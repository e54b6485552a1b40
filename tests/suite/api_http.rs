//! The HTTP API over real sockets: every endpoint, the bad-input cases
//! (each with its 4xx while the server keeps serving), and shots that
//! survive a restart.

use crate::http_support;

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use image::{GrayImage, Luma};
use serde_json::{Value, json};
use shotpilot::api::{
    self, AlignmentView, ApiParams, AppState, BoxFuture, KeyframeInfo, LoopInfo, MapView,
    MergeInfo, MissionProgressView, ShotTarget, SlamStatus, SlamView, StopOutcome, TargetView,
    TrackedFeatures, VehicleError, VehicleMissionView, VehicleStatus, VehicleView,
};
use shotpilot::shot::record::{
    Localisation, MissionRecord, MissionState, PhotoIntrinsics, PoseJson, Shot,
};
use shotpilot::shot::request::{ShotComputation, ShotComputer, ShotRequestError, WarpOnly};
use shotpilot::shot::store::ShotStore;
use shotpilot::slam::{KeypointState, TrackedKeypoint};
use shotpilot::video::live::{Frame, Ingest, RawPart, unix_now};

fn kf_image() -> GrayImage {
    GrayImage::from_fn(640, 480, |x, y| {
        Luma([((x / 8 + y / 8) % 2 * 200 + (x % 50)) as u8])
    })
}

/// [`kf_image`] as a PNG file's bytes (a photo upload's body).
fn kf_png() -> Vec<u8> {
    let mut png = Vec::new();
    kf_image()
        .write_to(&mut std::io::Cursor::new(&mut png), image::ImageFormat::Png)
        .unwrap();
    png
}

struct FakeSlam {
    img: Arc<GrayImage>,
}

/// The sequence number of the one processed frame the fake SLAM keeps.
const FEATURES_SEQ: u64 = 7;

/// 600 keypoints over the frame: every 10th an outlier, every 3rd of the
/// others an inlier, the rest unmatched (60, 180, 360).
fn fake_keypoints() -> Vec<TrackedKeypoint> {
    (0..600u32)
        .map(|i| TrackedKeypoint {
            x: (i * 7 % 600) as f32 + 20.25,
            y: (i * 13 % 440) as f32 + 20.5,
            state: if i % 10 == 0 {
                KeypointState::Outlier
            } else if i % 3 == 0 {
                KeypointState::Inlier
            } else {
                KeypointState::Unmatched
            },
        })
        .collect()
}

impl SlamView for FakeSlam {
    fn status(&self) -> SlamStatus {
        SlamStatus {
            available: true,
            state: "tracking".into(),
            keyframes: 2,
            points: 3,
            loops_closed: 1,
            loops: vec![LoopInfo {
                current_kf: 1,
                loop_kf: 0,
                current_t: 1.0,
                loop_t: 0.0,
                inliers: 91,
                projection_matches: 203,
                scale: 0.98,
                rotation_deg: 0.35,
                fused: 280,
                correction_ms: 80.0,
                at_unix: 1.0e9,
            }],
            maps_started: 1,
            merges_made: 1,
            merges: vec![MergeInfo {
                current_kf: 304,
                merge_kf: 3,
                current_t: 99.7,
                merge_t: 1.3,
                from_map: 1,
                into_map: 0,
                inliers: 302,
                projection_matches: 493,
                scale: 0.97,
                keyframes_moved: 118,
                fused: 1006,
                correction_ms: 150.0,
                at_unix: 1.0e9,
            }],
            map_mode: "gps_aided".into(),
            map_mode_reason: "put in local NED by 8 keyframes with a fix".into(),
            ..Default::default()
        }
    }
    fn keyframes(&self) -> Vec<KeyframeInfo> {
        (0..2)
            .map(|id| KeyframeInfo {
                id,
                timestamp: id as f64,
                world_from_cam: PoseJson {
                    translation: [id as f64, 0.0, 0.0],
                    rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
                },
                width: 640,
                height: 480,
            })
            .collect()
    }
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>> {
        (id < 2).then(|| self.img.clone())
    }
    fn features(&self, seq: Option<u64>) -> Option<Arc<TrackedFeatures>> {
        seq.is_none_or(|s| s == FEATURES_SEQ).then(|| {
            Arc::new(TrackedFeatures {
                frame: Arc::new(Frame::from_image(
                    FEATURES_SEQ,
                    Some(1.0e9),
                    std::time::Instant::now(),
                    1.0e9,
                    self.img.clone(),
                )),
                state: "tracking".into(),
                keypoints: fake_keypoints().into(),
            })
        })
    }
    fn map(&self, max_points: usize) -> MapView {
        let pts = vec![[0.0f32, 1.0, 2.0]; 3];
        MapView {
            points: pts.into_iter().take(max_points).collect(),
            total_points: 3,
            trajectory: vec![[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],
        }
    }
}

/// Warps like the real default, and localises shots on keyframe 1.
struct LocalisingOnKf1(WarpOnly<Arc<FakeSlam>>);

impl ShotComputer for LocalisingOnKf1 {
    fn shot_from_anchors(
        &self,
        kf: u64,
        a: &[[f64; 2]; 4],
        size: Option<(u32, u32)>,
    ) -> Result<ShotComputation, ShotRequestError> {
        let mut c = self.0.shot_from_anchors(kf, a, size)?;
        if kf == 1 {
            c.localisation = Ok(Localisation {
                sigma: None,
                world_from_cam: PoseJson {
                    translation: [1.0, 2.0, -3.0],
                    rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
                },
                inliers: 80,
                rms_error_px: 0.9,
                keyframe_id: Some(1),
            });
        }
        Ok(c)
    }
    fn shot_from_photo(
        &self,
        p: &GrayImage,
        i: Option<&PhotoIntrinsics>,
        g: Option<&shotpilot::shot::photo::GpsTag>,
    ) -> Result<ShotComputation, ShotRequestError> {
        self.0.shot_from_photo(p, i, g)
    }
}

/// A vehicle that holds the mission of the shot uploaded last, and starts
/// only that one (as the daemon's link vehicle does).
#[derive(Default)]
struct FakeVehicle {
    uploads: Mutex<Vec<String>>,
    started: Mutex<Vec<String>>,
    /// Answer a stop with MAV_RESULT_DENIED.
    refuse_stop: std::sync::atomic::AtomicBool,
    stops: Mutex<u32>,
}

impl VehicleView for FakeVehicle {
    fn status(&self) -> VehicleStatus {
        VehicleStatus {
            configured: true,
            connected: true,
            ..Default::default()
        }
    }
    fn upload_shot<'a>(
        &'a self,
        shot: &'a Shot,
    ) -> BoxFuture<'a, Result<MissionRecord, VehicleError>> {
        Box::pin(async move {
            self.uploads.lock().unwrap().push(shot.id.clone());
            Ok(MissionRecord {
                state: MissionState::Uploaded,
                items: 3,
                uploaded_unix: unix_now(),
                started_unix: None,
                target_lat_lon_alt: None,
                details: json!({}),
            })
        })
    }
    fn start_mission<'a>(&'a self, shot: &'a Shot) -> BoxFuture<'a, Result<(), VehicleError>> {
        Box::pin(async move {
            let holder = self.uploads.lock().unwrap().last().cloned();
            if holder.as_deref() != Some(shot.id.as_str()) {
                return Err(VehicleError::NotOnVehicle {
                    shot: shot.id.clone(),
                    holder,
                });
            }
            self.started.lock().unwrap().push(shot.id.clone());
            Ok(())
        })
    }
    fn download_mission(&self) -> BoxFuture<'_, Result<VehicleMissionView, VehicleError>> {
        Box::pin(async {
            let item = |seq: u16, command: u16| shotpilot::mission::MissionItem {
                seq,
                frame: 6,
                command,
                current: seq == 0,
                autocontinue: true,
                params: [0.0, 2.0, 0.0, 90.0],
                x: 473_977_000,
                y: 85_456_000,
                z: 15.0,
            };
            Ok(VehicleMissionView {
                count: 2,
                items: vec![item(0, 22), item(1, 16)],
                retries: 0,
                seconds: 0.2,
            })
        })
    }
    fn stop<'a>(&'a self, _reason: &'a str) -> BoxFuture<'a, Result<StopOutcome, VehicleError>> {
        Box::pin(async move {
            *self.stops.lock().unwrap() += 1;
            if self.refuse_stop.load(std::sync::atomic::Ordering::SeqCst) {
                return Err(VehicleError::Failed {
                    reason:
                        "the vehicle did not hold: vehicle rejected command 176: MAV_RESULT_DENIED"
                            .into(),
                });
            }
            let flying = self.started.lock().unwrap().last().cloned();
            Ok(StopOutcome {
                ack: shotpilot::vehicle::HoldAck {
                    command: "MAV_CMD_DO_SET_MODE",
                    mode: "AUTO.LOITER".into(),
                    result: "MAV_RESULT_ACCEPTED".into(),
                },
                refinement_cancelled: flying.clone(),
                flying,
            })
        })
    }
    fn shot_target(&self, shot: &Shot) -> Result<ShotTarget, VehicleError> {
        Ok(ShotTarget {
            shot: shot.id.clone(),
            target: TargetView {
                lat_deg: 47.3977,
                lon_deg: 8.5456,
                alt_above_home_m: 15.0,
                alt_m: 503.0,
                yaw_deg: 90.0,
                gimbal_pitch_deg: -30.0,
                residual_roll_deg: 0.4,
                axis_error_deg: 0.1,
                p_ned_vehicle: [3.0, 4.0, -15.0],
                camera_ned: PoseJson {
                    translation: [3.0, 4.0, -15.0],
                    rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
                },
            },
            georeference: AlignmentView {
                scale: 2.5,
                rms_m: 0.3,
                keyframes_used: 12,
                pairs: 14,
                time_offset_s: None,
            },
            position_sigma_m: Some(0.2),
        })
    }
    fn progress(&self) -> Option<MissionProgressView> {
        Some(MissionProgressView {
            current_seq: Some(1),
            total: Some(3),
            state: Some(3),
            last_reached: None,
            age_s: 0.1,
        })
    }
}

struct Server {
    addr: SocketAddr,
    ingest: Arc<Ingest>,
    vehicle: Arc<FakeVehicle>,
    _rt: tokio::runtime::Runtime,
}

fn start(dir: &std::path::Path, token: Option<&str>, with_vehicle: bool) -> Server {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let slam = Arc::new(FakeSlam {
        img: Arc::new(kf_image()),
    });
    let ingest = Arc::new(Ingest::new());
    let vehicle = Arc::new(FakeVehicle::default());
    let state = AppState {
        ingest: ingest.clone(),
        slam: slam.clone(),
        vehicle: with_vehicle.then(|| vehicle.clone() as Arc<dyn VehicleView>),
        shots: Arc::new(LocalisingOnKf1(WarpOnly {
            keyframes: slam.clone(),
            params: Default::default(),
        })),
        store: Arc::new(ShotStore::open(dir).unwrap()),
        params: Arc::new(ApiParams {
            token: token.map(str::to_owned),
            body_limit: 1 << 20,
            events_hz: 10.0,
            ..Default::default()
        }),
        actions: Default::default(),
        started_unix: unix_now(),
        shutdown: Default::default(),
        events: Default::default(),
    };
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let addr = listener.local_addr().unwrap();
    rt.spawn(async move { axum::serve(listener, api::router(state)).await.unwrap() });
    Server {
        addr,
        ingest,
        vehicle,
        _rt: rt,
    }
}

/// One request through the tests' HTTP client; returns the status, the
/// lower-cased header lines and the body.
fn http(
    addr: SocketAddr,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &[u8],
) -> (u16, String, Vec<u8>) {
    let r = http_support::send(addr, method, path, headers, body, Duration::from_secs(20));
    (r.status, r.head, r.body)
}

fn json_of(b: &[u8]) -> Value {
    serde_json::from_slice(b).unwrap_or_else(|e| panic!("{e}: {}", String::from_utf8_lossy(b)))
}

/// A bad-anchors error with its check's `reason`.
fn assert_anchor_refusal(r: &(u16, String, Vec<u8>), reason: &str) {
    assert_error(r, 400, "bad_anchors");
    let v = json_of(&r.2);
    assert_eq!(v["error"]["reason"], reason, "{v}");
}

fn assert_error(r: &(u16, String, Vec<u8>), status: u16, code: &str) {
    assert_eq!(r.0, status, "{}", String::from_utf8_lossy(&r.2));
    assert!(r.1.contains("content-type: application/json"), "{}", r.1);
    let v = json_of(&r.2);
    assert_eq!(v["error"]["code"], code, "{v}");
    assert!(
        v["error"]["message"]
            .as_str()
            .is_some_and(|m| !m.is_empty())
    );
}

const TOKEN: &str = "s3cret";
const AUTH: (&str, &str) = ("Authorization", "Bearer s3cret");
const JSON_CT: (&str, &str) = ("Content-Type", "application/json");

/// The 200 x 150 crop at (100, 100): anchors are where the picture's corner
/// pixels go (pixel centres at integers).
fn good_shot(kf: u64) -> Vec<u8> {
    json!({"keyframe_id": kf, "anchors": [[100, 100], [299, 100], [299, 249], [100, 249]], "width": 200, "height": 150})
        .to_string()
        .into_bytes()
}

/// A recent frame's keypoints: counts per state, at most `features_max`
/// (or `max`) of them packed, inliers first; the frame's picture beside
/// them; a frame not kept, or a bad number, is refused.
#[test]
fn the_features_of_a_processed_frame_are_bounded_packed_and_have_their_picture() {
    let dir = tempfile::tempdir().unwrap();
    let srv = start(dir.path(), None, false);
    let a = srv.addr;
    let all = fake_keypoints();
    let r = http(a, "GET", "/api/v1/features", &[], b"");
    assert_eq!(r.0, 200, "{}", String::from_utf8_lossy(&r.2));
    let f = json_of(&r.2);
    assert_eq!(f["seq"], FEATURES_SEQ);
    assert_eq!(
        (f["width"].as_u64(), f["height"].as_u64()),
        (Some(640), Some(480))
    );
    assert_eq!(f["state"], "tracking");
    assert_eq!(
        f["counts"],
        json!({"inlier": 180, "outlier": 60, "unmatched": 360})
    );
    // The default bound (500): every inlier and outlier, 260 unmatched.
    let limit = ApiParams::default().features_max;
    assert_eq!(limit, 500);
    assert_eq!(
        f["shown"],
        json!({"inlier": 180, "outlier": 60, "unmatched": 260})
    );
    let shown = api::unpack(f["points"].as_str().unwrap()).expect("packed keypoints");
    assert_eq!(shown.len(), limit);
    for p in &shown {
        // Each is one of the frame's, at its place to 1/16 pixel.
        assert!(
            all.iter().any(|k| k.state == p.state
                && (k.x - p.x).abs() <= 1.0 / 16.0
                && (k.y - p.y).abs() <= 1.0 / 16.0),
            "{p:?}"
        );
    }
    // Fewer asked for: the inliers first.
    let f = json_of(&http(a, "GET", "/api/v1/features?max=100", &[], b"").2);
    assert_eq!(
        f["shown"],
        json!({"inlier": 100, "outlier": 0, "unmatched": 0})
    );
    // More than the bound asked for: the bound.
    let f = json_of(&http(a, "GET", "/api/v1/features?max=100000&seq=7", &[], b"").2);
    assert_eq!(
        api::unpack(f["points"].as_str().unwrap()).unwrap().len(),
        limit
    );
    // The frame's picture, where the reply says.
    let url = f["frame_url"].as_str().unwrap();
    assert_eq!(url, format!("/api/v1/features/{FEATURES_SEQ}/frame.jpg"));
    let r = http(a, "GET", url, &[], b"");
    assert_eq!(r.0, 200);
    assert!(r.1.contains("content-type: image/jpeg"), "{}", r.1);
    let img = image::load_from_memory(&r.2).unwrap();
    assert_eq!((img.width(), img.height()), (640, 480));
    // A frame no longer kept, and a bad number.
    assert_error(
        &http(a, "GET", "/api/v1/features?seq=8", &[], b""),
        404,
        "not_found",
    );
    assert_error(
        &http(a, "GET", "/api/v1/features/8/frame.jpg", &[], b""),
        404,
        "not_found",
    );
    assert_error(
        &http(a, "GET", "/api/v1/features/x/frame.jpg", &[], b""),
        400,
        "bad_id",
    );
}

#[test]
fn endpoints_and_bad_input() {
    let dir = tempfile::tempdir().unwrap();
    let srv = start(dir.path(), Some(TOKEN), true);
    let a = srv.addr;

    let r = http(a, "GET", "/api/v1/status", &[], b"");
    assert_eq!(r.0, 200);
    let st = json_of(&r.2);
    assert_eq!(st["slam"]["state"], "tracking");
    assert_eq!(st["video"]["counters"]["received"], 0);
    assert_eq!(st["vehicle"]["connected"], true);

    let r = http(a, "GET", "/api/v1/openapi.json", &[], b"");
    assert_eq!(r.0, 200);
    let doc = json_of(&r.2);
    assert_eq!(doc["openapi"], "3.1.0");
    assert!(doc["paths"]["/shots"]["post"].is_object());

    let r = http(a, "GET", "/", &[], b"");
    assert_eq!(r.0, 200);
    assert!(String::from_utf8_lossy(&r.2).contains("<html"));

    let kfs = json_of(&http(a, "GET", "/api/v1/keyframes", &[], b"").2);
    assert_eq!(kfs["count"], 2);
    let r = http(a, "GET", "/api/v1/keyframes/1/image.jpg", &[], b"");
    assert_eq!(r.0, 200);
    let img = image::load_from_memory(&r.2).unwrap();
    assert_eq!((img.width(), img.height()), (640, 480));
    assert_error(
        &http(a, "GET", "/api/v1/keyframes/7/image.jpg", &[], b""),
        404,
        "not_found",
    );
    assert_error(
        &http(a, "GET", "/api/v1/keyframes/x/image.jpg", &[], b""),
        400,
        "bad_id",
    );
    let m = json_of(&http(a, "GET", "/api/v1/map?max_points=2", &[], b"").2);
    assert_eq!(m["points"].as_array().unwrap().len(), 2);
    assert_eq!(m["total_points"], 3);
    assert_error(
        &http(a, "GET", "/api/v1/nothing", &[], b""),
        404,
        "not_found",
    );

    // Bad input on POST /shots.
    assert_error(
        &http(a, "POST", "/api/v1/shots", &[JSON_CT], &good_shot(0)),
        401,
        "unauthorized",
    );
    assert_error(
        &http(
            a,
            "POST",
            "/api/v1/shots",
            &[JSON_CT, ("Authorization", "Bearer nope")],
            &good_shot(0),
        ),
        401,
        "unauthorized",
    );
    assert_error(
        &http(
            a,
            "POST",
            "/api/v1/shots",
            &[AUTH, JSON_CT],
            b"{\"keyframe_id\": 0, \"anch",
        ),
        400,
        "bad_json",
    );
    let three =
        json!({"keyframe_id": 0, "anchors": [[100, 100], [300, 100], [300, 250]]}).to_string();
    assert_anchor_refusal(
        &http(
            a,
            "POST",
            "/api/v1/shots",
            &[AUTH, JSON_CT],
            three.as_bytes(),
        ),
        "count",
    );
    // Each anchor check answers with its own reason.
    for (anchors, reason) in [
        (
            // A bow tie: crossed, said as such (not "collapsed" or "not convex").
            json!([[0, 0], [300, 0], [30, 200], [250, 150]]),
            "crossed",
        ),
        (
            json!([[300, 100], [100, 100], [100, 250], [300, 250]]),
            "mirrored",
        ),
        (
            json!([[0, 0], [300, 100], [150, 120], [0, 250]]),
            "not_convex",
        ),
        (
            json!([[100, 100], [110, 100], [110, 105], [100, 105]]),
            "collapsed",
        ),
        (
            json!([[-2000, 100], [300, 100], [300, 250], [100, 250]]),
            "out_of_bounds",
        ),
    ] {
        let body = json!({"keyframe_id": 0, "anchors": anchors}).to_string();
        let r = http(
            a,
            "POST",
            "/api/v1/shots",
            &[AUTH, JSON_CT],
            body.as_bytes(),
        );
        assert_anchor_refusal(&r, reason);
    }
    let tiny = json!({"keyframe_id": 0, "anchors": [[100, 100], [299, 100], [299, 249], [100, 249]], "width": 1, "height": 150}).to_string();
    assert_error(
        &http(
            a,
            "POST",
            "/api/v1/shots",
            &[AUTH, JSON_CT],
            tiny.as_bytes(),
        ),
        400,
        "bad_image",
    );
    assert_error(
        &http(a, "POST", "/api/v1/shots", &[AUTH, JSON_CT], &good_shot(9)),
        404,
        "unknown_keyframe",
    );
    assert_error(
        &http(
            a,
            "POST",
            "/api/v1/shots",
            &[AUTH, ("Content-Type", "text/plain")],
            &good_shot(0),
        ),
        415,
        "bad_content_type",
    );
    // A 50 MiB upload: the server answers once it has more than its limit
    // (1 MiB here), without waiting for the rest.
    let r = http_support::send_partial(
        a,
        "POST",
        "/api/v1/shots",
        &[AUTH, JSON_CT],
        50 << 20,
        2 << 20,
        Duration::from_secs(20),
    );
    let r = (r.status, r.head, r.body);
    assert_error(&r, 413, "body_too_large");
    // The answer names the limit (and the setting that raises it).
    let e = &json_of(&r.2)["error"];
    let limit = e["limit_bytes"].as_u64().expect("the limit");
    assert!(limit < 50 << 20, "{e}");
    let message = e["message"].as_str().unwrap();
    assert!(
        message.contains(&limit.to_string()) && message.contains("body_limit_bytes"),
        "{e}"
    );
    assert_error(
        &http(
            a,
            "POST",
            "/api/v1/shots/photo",
            &[AUTH, ("Content-Type", "text/plain")],
            b"hello",
        ),
        415,
        "bad_content_type",
    );
    assert_error(
        &http(
            a,
            "POST",
            "/api/v1/shots/photo",
            &[AUTH, ("Content-Type", "image/jpeg")],
            b"not a jpeg at all",
        ),
        400,
        "bad_image",
    );
    assert_error(
        &http(a, "GET", "/api/v1/shots/shot-99", &[], b""),
        404,
        "not_found",
    );
    assert_error(
        &http(a, "GET", "/api/v1/shots/../../etc", &[], b""),
        404,
        "not_found",
    );
    assert_error(
        &http(a, "POST", "/api/v1/shots/shot-99/mission", &[AUTH], b""),
        404,
        "not_found",
    );
    // Still serving, nothing stored.
    assert_eq!(http(a, "GET", "/api/v1/status", &[], b"").0, 200);
    assert_eq!(
        json_of(&http(a, "GET", "/api/v1/shots", &[], b"").2)["count"],
        0
    );

    // A good shot on keyframe 0: created, warped, not localised -> 409 on mission.
    let r = http(a, "POST", "/api/v1/shots", &[AUTH, JSON_CT], &good_shot(0));
    assert_eq!(r.0, 201, "{}", String::from_utf8_lossy(&r.2));
    let s0 = json_of(&r.2);
    assert_eq!(s0["id"], "shot-1");
    assert_eq!(s0["status"], "not_localised");
    let r = http(a, "GET", "/api/v1/shots/shot-1/image.jpg", &[], b"");
    assert_eq!(r.0, 200);
    let warped = image::load_from_memory(&r.2).unwrap().to_luma8();
    assert_eq!(warped.dimensions(), (200, 150));
    // The crop of the keyframe at (100,100): compare means (JPEG both ways).
    let src = kf_image();
    let mut err = 0.0;
    for y in 0..150 {
        for x in 0..200 {
            err += (warped.get_pixel(x, y).0[0] as f64
                - src.get_pixel(100 + x, 100 + y).0[0] as f64)
                .abs();
        }
    }
    let mae = err / (200.0 * 150.0);
    assert!(mae < 12.0, "mean abs difference to the crop {mae}");
    assert_error(
        &http(a, "POST", "/api/v1/shots/shot-1/mission", &[AUTH], b""),
        409,
        "not_localised",
    );

    // A photo shot.
    // A JPEG cut short in transfer (it would decode to a picture grey
    // below the cut): refused, saying so.
    let mut jpeg = Vec::new();
    kf_image()
        .write_to(
            &mut std::io::Cursor::new(&mut jpeg),
            image::ImageFormat::Jpeg,
        )
        .unwrap();
    let r = http(
        a,
        "POST",
        "/api/v1/shots/photo",
        &[AUTH, ("Content-Type", "image/jpeg")],
        &jpeg[..jpeg.len() * 2 / 3],
    );
    assert_error(&r, 400, "bad_image");
    let message = json_of(&r.2)["error"]["message"]
        .as_str()
        .unwrap()
        .to_owned();
    assert!(message.contains("truncated"), "{message}");
    let png = kf_png();
    let r = http(
        a,
        "POST",
        "/api/v1/shots/photo",
        &[AUTH, ("Content-Type", "image/png")],
        &png,
    );
    assert_eq!(r.0, 201, "{}", String::from_utf8_lossy(&r.2));
    assert_eq!(json_of(&r.2)["source"]["kind"], "photo");
    // A photo from another camera, with its intrinsics: kept with the shot.
    let r = http(
        a,
        "POST",
        "/api/v1/shots/photo?fx=500&fy=510.5&cx=319.5&cy=239.5&k1=-0.05",
        &[AUTH, ("Content-Type", "image/png")],
        &png,
    );
    assert_eq!(r.0, 201, "{}", String::from_utf8_lossy(&r.2));
    let src = &json_of(&r.2)["source"];
    assert_eq!(src["intrinsics"]["fy"], 510.5, "{src}");
    assert_eq!(src["intrinsics"]["distortion"]["k1"], -0.05, "{src}");
    assert_eq!(src["intrinsics"]["distortion"]["k2"], 0.0, "{src}");
    // Incomplete, impossible or unknown intrinsics: 400, nothing stored.
    for q in [
        "fx=500",
        "fx=500&fy=500&cx=319.5",
        "k1=0.1",
        "fx=-500&fy=500&cx=319.5&cy=239.5",
        "fx=500&fy=500&cx=319.5&cy=nan",
        "fx=500&fy=500&cx=319.5&cy=239.5&focal=3",
        "fx=five&fy=500&cx=319.5&cy=239.5",
    ] {
        let r = http(
            a,
            "POST",
            &format!("/api/v1/shots/photo?{q}"),
            &[AUTH, ("Content-Type", "image/png")],
            &png,
        );
        assert_error(&r, 400, "bad_intrinsics");
    }

    // A localised shot: upload, start, progress.
    let r = http(a, "POST", "/api/v1/shots", &[AUTH, JSON_CT], &good_shot(1));
    assert_eq!(r.0, 201);
    let s = json_of(&r.2);
    assert_eq!(s["status"], "localised");
    let id = s["id"].as_str().unwrap().to_owned();
    assert_error(
        &http(
            a,
            "POST",
            &format!("/api/v1/shots/{id}/start"),
            &[AUTH],
            b"",
        ),
        409,
        "no_mission",
    );
    assert_error(
        &http(a, "POST", &format!("/api/v1/shots/{id}/mission"), &[], b""),
        401,
        "unauthorized",
    );
    let r = http(
        a,
        "POST",
        &format!("/api/v1/shots/{id}/mission"),
        &[AUTH],
        b"",
    );
    assert_eq!(r.0, 200, "{}", String::from_utf8_lossy(&r.2));
    assert_eq!(json_of(&r.2)["mission"]["state"], "uploaded");
    assert_eq!(*srv.vehicle.uploads.lock().unwrap(), vec![id.clone()]);
    let r = http(
        a,
        "POST",
        &format!("/api/v1/shots/{id}/start"),
        &[AUTH],
        b"",
    );
    assert_eq!(r.0, 200);
    let started = json_of(&r.2);
    assert_eq!(started["id"], id.as_str());
    assert_eq!(started["mission"]["state"], "started");
    assert!(started["mission"]["started_unix"].as_f64().is_some());
    assert_eq!(*srv.vehicle.started.lock().unwrap(), vec![id.clone()]);
    let p = json_of(&http(a, "GET", &format!("/api/v1/shots/{id}/progress"), &[], b"").2);
    assert_eq!(p["progress"]["current_seq"], 1);
    assert_eq!(
        json_of(&http(a, "GET", "/api/v1/shots", &[], b"").2)["count"],
        4
    );

    // A second shot uploaded: the vehicle holds its mission now. Starting
    // the first shot again starts nothing (the vehicle would fly the
    // second's); starting the second starts and refines the second.
    let r = http(a, "POST", "/api/v1/shots", &[AUTH, JSON_CT], &good_shot(1));
    assert_eq!(r.0, 201);
    let id2 = json_of(&r.2)["id"].as_str().unwrap().to_owned();
    let r = http(
        a,
        "POST",
        &format!("/api/v1/shots/{id2}/mission"),
        &[AUTH],
        b"",
    );
    assert_eq!(r.0, 200, "{}", String::from_utf8_lossy(&r.2));
    let r = http(
        a,
        "POST",
        &format!("/api/v1/shots/{id}/start"),
        &[AUTH],
        b"",
    );
    assert_error(&r, 409, "not_on_vehicle");
    assert!(
        json_of(&r.2)["error"]["message"]
            .as_str()
            .is_some_and(|m| m.contains(&id2)),
        "{}",
        String::from_utf8_lossy(&r.2)
    );
    assert_eq!(*srv.vehicle.started.lock().unwrap(), vec![id.clone()]);
    let r = http(
        a,
        "POST",
        &format!("/api/v1/shots/{id2}/start"),
        &[AUTH],
        b"",
    );
    assert_eq!(r.0, 200, "{}", String::from_utf8_lossy(&r.2));
    assert_eq!(json_of(&r.2)["id"], id2.as_str());
    assert_eq!(
        *srv.vehicle.started.lock().unwrap(),
        vec![id.clone(), id2.clone()]
    );
    // The first shot's record still says what happened to it.
    let first = json_of(&http(a, "GET", &format!("/api/v1/shots/{id}"), &[], b"").2);
    assert_eq!(first["mission"]["state"], "started");
}

#[test]
fn no_vehicle_is_503_and_shots_survive_a_restart() {
    let dir = tempfile::tempdir().unwrap();
    {
        let srv = start(dir.path(), None, false);
        // No token configured: POST needs none.
        let r = http(srv.addr, "POST", "/api/v1/shots", &[JSON_CT], &good_shot(1));
        assert_eq!(r.0, 201);
        assert_error(
            &http(srv.addr, "POST", "/api/v1/shots/shot-1/mission", &[], b""),
            503,
            "no_vehicle",
        );
        let r = http(srv.addr, "POST", "/api/v1/shots", &[JSON_CT], &good_shot(0));
        assert_eq!(r.0, 201);
    }
    let srv = start(dir.path(), None, true);
    let list = json_of(&http(srv.addr, "GET", "/api/v1/shots", &[], b"").2);
    assert_eq!(list["count"], 2);
    assert_eq!(list["shots"][0]["id"], "shot-1");
    assert_eq!(list["shots"][0]["status"], "localised");
    assert_eq!(
        http(srv.addr, "GET", "/api/v1/shots/shot-2/image.jpg", &[], b"").0,
        200
    );
    // Ids continue after the restart.
    let r = http(srv.addr, "POST", "/api/v1/shots", &[JSON_CT], &good_shot(0));
    assert_eq!(json_of(&r.2)["id"], "shot-3");
}

#[test]
fn events_and_video_are_served() {
    let dir = tempfile::tempdir().unwrap();
    let srv = start(dir.path(), None, false);
    // SSE: the first status event arrives at once.
    let mut s = http_support::open_stream(srv.addr, "/api/v1/events", &[]);
    assert_eq!(s.status, 200);
    assert!(
        s.head.contains("content-type: text/event-stream"),
        "{}",
        s.head
    );
    let mut got = Vec::new();
    // Up to the end of the first event (its data is one chunk).
    let first_event = |got: &[u8]| {
        let text = String::from_utf8_lossy(got).into_owned();
        let start = text.find("data:")? + 5;
        let len = text[start..].find("\n\n")?;
        Some(text[start..start + len].trim().to_owned())
    };
    while first_event(&got).is_none() {
        let chunk = s
            .next(Duration::from_secs(5))
            .expect("the event stream goes on");
        got.extend_from_slice(&chunk);
    }
    let text = String::from_utf8_lossy(&got);
    assert!(text.contains("event: status"), "{text}");
    // The page sees the loops closed in the event stream.
    let status = json_of(first_event(&got).unwrap().as_bytes());
    assert_eq!(status["slam"]["loops_closed"], 1, "{status:#}");
    assert_eq!(status["slam"]["loops"][0]["current_kf"], 1, "{status:#}");
    assert_eq!(status["slam"]["loops"][0]["loop_kf"], 0, "{status:#}");
    assert_eq!(status["slam"]["loops"][0]["scale"], 0.98, "{status:#}");
    // And the maps merged after a tracking loss, on the same path.
    assert_eq!(status["slam"]["maps_started"], 1, "{status:#}");
    assert_eq!(status["slam"]["merges_made"], 1, "{status:#}");
    assert_eq!(status["slam"]["merges"][0]["current_kf"], 304, "{status:#}");
    assert_eq!(status["slam"]["merges"][0]["from_map"], 1, "{status:#}");
    assert_eq!(status["slam"]["merges"][0]["into_map"], 0, "{status:#}");

    // Video: frames pushed into the ingest come out of /video.mjpg, read by
    // the daemon's own MJPEG client.
    srv.ingest.spawn_decoder().unwrap();
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let reader = Arc::new(Ingest::new());
    reader.spawn_decoder().unwrap();
    let cancel = tokio_util::sync::CancellationToken::new();
    let url = format!("http://{}/api/v1/video.mjpg", srv.addr);
    let (r2, c2) = (reader.clone(), cancel.clone());
    rt.spawn(
        async move { shotpilot::video::mjpeg::run_mjpeg(&url, &Default::default(), r2, c2).await },
    );
    let mut jpeg = Vec::new();
    image::codecs::jpeg::JpegEncoder::new(&mut jpeg)
        .encode_image(&kf_image())
        .unwrap();
    let jpeg = Arc::new(jpeg);
    for i in 0..40 {
        srv.ingest.push_raw(RawPart {
            jpeg: jpeg.clone(),
            capture_time: Some(100.0 + i as f64),
            received: std::time::Instant::now(),
            received_unix: unix_now(),
        });
        std::thread::sleep(Duration::from_millis(25));
        if reader.counters.snapshot().decoded >= 5 {
            break;
        }
    }
    let c = reader.counters.snapshot();
    assert!(c.decoded >= 5, "{c:?}");
    let f = reader.latest().unwrap();
    assert_eq!(f.image.dimensions(), (640, 480));
    assert!(f.capture_time.unwrap() >= 100.0);
    let snap = http(srv.addr, "GET", "/api/v1/snapshot.jpg", &[], b"");
    assert_eq!(snap.0, 200);
    assert_eq!(snap.2, *jpeg);
    cancel.cancel();
}

/// A shot that cannot be written (the data directory is gone): the request
/// fails with 500 `store`, and the status carries the failed write (the
/// page shows it) until a write succeeds again.
#[test]
fn a_failed_shot_write_is_in_the_status_until_a_write_succeeds() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("shots");
    let srv = start(&data, None, true);
    let a = srv.addr;
    let status = || json_of(&http(a, "GET", "/api/v1/status", &[], b"").2);
    assert_eq!(status()["errors"], json!([]));
    std::fs::remove_dir_all(&data).unwrap();
    let r = http(a, "POST", "/api/v1/shots", &[JSON_CT], &good_shot(1));
    assert_error(&r, 500, "store");
    let s = status();
    let errors = s["errors"].as_array().unwrap();
    assert_eq!(errors.len(), 1, "{s}");
    assert_eq!(errors[0]["what"], "shot");
    assert!(
        errors[0]["message"]
            .as_str()
            .is_some_and(|m| m.contains("shot-1")),
        "{s}"
    );
    assert!(errors[0]["at_unix"].as_f64().is_some_and(|t| t > 0.0));
    std::fs::create_dir_all(&data).unwrap();
    let r = http(a, "POST", "/api/v1/shots", &[JSON_CT], &good_shot(1));
    assert_eq!(r.0, 201, "{}", String::from_utf8_lossy(&r.2));
    assert_eq!(status()["errors"], json!([]));
}

/// Checks `v` against `schema` of the OpenAPI document `doc` (the subset
/// the document uses: `$ref`, `type` (one or a list), `required`,
/// `properties`, `items`, `enum`, `oneOf`, `minItems`, `maxItems`);
/// the first mismatch, with its JSON path.
fn check_schema(doc: &Value, schema: &Value, v: &Value, at: &str) -> Result<(), String> {
    if let Some(r) = schema["$ref"].as_str() {
        let name = r
            .strip_prefix("#/components/schemas/")
            .ok_or_else(|| format!("{at}: unknown $ref {r}"))?;
        let target = &doc["components"]["schemas"][name];
        if target.is_null() {
            return Err(format!("{at}: $ref {r} is not in the document"));
        }
        return check_schema(doc, target, v, at);
    }
    if let Some(alts) = schema["oneOf"].as_array() {
        let ok = alts
            .iter()
            .filter(|s| check_schema(doc, s, v, at).is_ok())
            .count();
        return if ok == 1 {
            Ok(())
        } else {
            Err(format!("{at}: {v} matches {ok} of oneOf's {}", alts.len()))
        };
    }
    let kind_ok = |t: &str| match t {
        "null" => v.is_null(),
        "boolean" => v.is_boolean(),
        "object" => v.is_object(),
        "array" => v.is_array(),
        "string" => v.is_string(),
        "number" => v.is_number(),
        "integer" => v.is_i64() || v.is_u64(),
        _ => false,
    };
    let types: Vec<&str> = match &schema["type"] {
        Value::String(t) => vec![t.as_str()],
        Value::Array(ts) => ts.iter().filter_map(Value::as_str).collect(),
        _ => vec![],
    };
    if !types.is_empty() && !types.iter().any(|t| kind_ok(t)) {
        return Err(format!("{at}: {v} is not of type {types:?}"));
    }
    if let Some(e) = schema["enum"].as_array()
        && !e.contains(v)
    {
        return Err(format!("{at}: {v} is not one of {e:?}"));
    }
    if let Some(o) = v.as_object() {
        for key in schema["required"].as_array().into_iter().flatten() {
            let key = key.as_str().unwrap_or_default();
            if !o.contains_key(key) {
                return Err(format!("{at}: the reply has no {key:?} (required)"));
            }
        }
        if let Some(props) = schema["properties"].as_object() {
            for (key, sub) in props {
                if let Some(x) = o.get(key) {
                    check_schema(doc, sub, x, &format!("{at}.{key}"))?;
                }
            }
            // A closed object: every field the reply has is documented.
            if schema["additionalProperties"] == false
                && let Some(k) = o.keys().find(|k| !props.contains_key(*k))
            {
                return Err(format!(
                    "{at}: the reply has {k:?}, which is not documented"
                ));
            }
        }
    }
    if let Some(a) = v.as_array() {
        if let Some(min) = schema["minItems"].as_u64()
            && (a.len() as u64) < min
        {
            return Err(format!("{at}: {} items, at least {min}", a.len()));
        }
        if let Some(max) = schema["maxItems"].as_u64()
            && (a.len() as u64) > max
        {
            return Err(format!("{at}: {} items, at most {max}", a.len()));
        }
        for (i, x) in a.iter().enumerate() {
            check_schema(doc, &schema["items"], x, &format!("{at}[{i}]"))?;
        }
    }
    Ok(())
}

/// The (method, path) pairs `api::router` serves under `/api/v1`, read
/// from its source (axum cannot list a router's routes).
fn router_routes() -> std::collections::BTreeSet<(String, String)> {
    let src = include_str!("../../src/api/mod.rs");
    let body = &src[src.find("pub fn router(").expect("api::router")..];
    let body = &body[..body.find(".nest(\"/api/v1\"").expect("the /api/v1 nest")];
    let mut out = std::collections::BTreeSet::new();
    for part in body.split(".route(").skip(1) {
        let rest = part.trim_start().strip_prefix('"').expect("a literal path");
        let (path, rest) = rest.split_once('"').unwrap();
        let rest = rest.trim_start().trim_start_matches(',').trim_start();
        let method = &rest[..rest.find('(').unwrap()];
        out.insert((method.to_owned(), path.to_owned()));
    }
    out
}

/// The events of `/events` (name, JSON data), from the first, read until
/// `enough` says so (each read bounded by a 10 s timeout).
fn sse_events(
    addr: SocketAddr,
    enough: impl Fn(&[(String, Value)]) -> bool,
) -> Vec<(String, Value)> {
    let mut s = http_support::open_stream(addr, "/api/v1/events", &[]);
    assert_eq!(s.status, 200);
    let mut got = Vec::new();
    loop {
        let text = String::from_utf8_lossy(&got);
        // Whole events only: each ends with an empty line.
        let whole = text.rfind("\n\n").map_or("", |end| &text[..end]);
        let events: Vec<(String, Value)> = whole
            .split("\n\n")
            .filter_map(|block| {
                let name = block.lines().find_map(|l| l.strip_prefix("event: "))?;
                let data = block.lines().find_map(|l| l.strip_prefix("data: "))?;
                Some((name.to_owned(), serde_json::from_str(data).ok()?))
            })
            .collect();
        if enough(&events) {
            return events;
        }
        let chunk = s
            .next(Duration::from_secs(10))
            .unwrap_or_else(|| panic!("the event stream ended: {text}"));
        got.extend_from_slice(&chunk);
    }
}

/// The `shot` events of `/events` (their JSON data), read until `enough`
/// says so.
fn shot_events(addr: SocketAddr, enough: impl Fn(&[Value]) -> bool) -> Vec<Value> {
    let shots = |evs: &[(String, Value)]| -> Vec<Value> {
        evs.iter()
            .filter(|(n, _)| n == "shot")
            .map(|(_, v)| v.clone())
            .collect()
    };
    shots(&sse_events(addr, |evs| enough(&shots(evs))))
}

/// The document served at /openapi.json has every route the router
/// serves and no other, and real replies (status, keyframes, the map,
/// shots list and one shot, a shot's target and progress, the vehicle's
/// mission, a shot created from anchors or a photo, uploaded, started,
/// and the vehicle stopped) have the fields and types its schemas say,
/// and no field a closed schema does not name.
#[test]
fn the_openapi_document_matches_the_router_and_the_replies() {
    let dir = tempfile::tempdir().unwrap();
    let srv = start(dir.path(), Some(TOKEN), true);
    let a = srv.addr;
    let r = http(a, "GET", "/api/v1/openapi.json", &[], b"");
    assert_eq!(r.0, 200);
    let doc = json_of(&r.2);

    let served = router_routes();
    assert!(served.len() >= 17, "{served:?}");
    let documented: std::collections::BTreeSet<(String, String)> = doc["paths"]
        .as_object()
        .unwrap()
        .iter()
        .flat_map(|(p, ops)| {
            ops.as_object()
                .unwrap()
                .keys()
                .map(move |m| (m.clone(), p.clone()))
        })
        .collect();
    let undocumented: Vec<_> = served.difference(&documented).collect();
    let unserved: Vec<_> = documented.difference(&served).collect();
    assert!(
        undocumented.is_empty() && unserved.is_empty(),
        "routes the document lacks: {undocumented:?}; documented routes not served: {unserved:?}"
    );

    let reply_schema = |method: &str, path: &str, code: &str| {
        let s =
            doc["paths"][path][method]["responses"][code]["content"]["application/json"]["schema"]
                .clone();
        assert!(s.is_object(), "{method} {path} {code} has no schema");
        s
    };
    let check = |method: &str, path: &str, code: &str, reply: &Value| {
        check_schema(&doc, &reply_schema(method, path, code), reply, "$")
            .unwrap_or_else(|e| panic!("{method} {path}: {e}\n{reply:#}"));
    };
    let created = http(a, "POST", "/api/v1/shots", &[AUTH, JSON_CT], &good_shot(1));
    assert_eq!(created.0, 201);
    let shot = json_of(&created.2);
    check("post", "/shots", "201", &shot);
    assert_eq!(shot["status"], "localised");
    let id = shot["id"].as_str().unwrap().to_owned();
    let other = http(a, "POST", "/api/v1/shots", &[AUTH, JSON_CT], &good_shot(0));
    assert_eq!(other.0, 201);
    assert_eq!(json_of(&other.2)["status"], "not_localised");
    check("post", "/shots", "201", &json_of(&other.2));
    // A photo shot's reply is a shot too.
    let png = kf_png();
    let photo = http(
        a,
        "POST",
        "/api/v1/shots/photo",
        &[AUTH, ("Content-Type", "image/png")],
        &png,
    );
    assert_eq!(photo.0, 201, "{}", String::from_utf8_lossy(&photo.2));
    check("post", "/shots/photo", "201", &json_of(&photo.2));
    for (path, doc_path) in [
        ("/api/v1/status".to_owned(), "/status"),
        ("/api/v1/keyframes".to_owned(), "/keyframes"),
        ("/api/v1/shots".to_owned(), "/shots"),
        (format!("/api/v1/shots/{id}"), "/shots/{id}"),
        ("/api/v1/vehicle/mission".to_owned(), "/vehicle/mission"),
        ("/api/v1/features".to_owned(), "/features"),
        ("/api/v1/map?max_points=2".to_owned(), "/map"),
        (format!("/api/v1/shots/{id}/target"), "/shots/{id}/target"),
        (
            format!("/api/v1/shots/{id}/progress"),
            "/shots/{id}/progress",
        ),
    ] {
        let r = http(a, "GET", &path, &[], b"");
        assert_eq!(r.0, 200, "{path}: {}", String::from_utf8_lossy(&r.2));
        check("get", doc_path, "200", &json_of(&r.2));
    }
    for action in ["mission", "start"] {
        let path = format!("/api/v1/shots/{id}/{action}");
        let r = http(a, "POST", &path, &[AUTH], b"");
        assert_eq!(r.0, 200, "{path}: {}", String::from_utf8_lossy(&r.2));
        check(
            "post",
            &format!("/shots/{{id}}/{action}"),
            "200",
            &json_of(&r.2),
        );
    }

    // The shot events on /events: each as its schema says, this shot's
    // in the order they happened (history replayed to a late client).
    // After the upload the progress has the mission record too.
    let r = http(a, "GET", &format!("/api/v1/shots/{id}/progress"), &[], b"");
    let progress = json_of(&r.2);
    assert!(progress["mission"].is_object(), "{progress}");
    check("get", "/shots/{id}/progress", "200", &progress);
    let r = http(a, "POST", "/api/v1/vehicle/stop", &[AUTH], b"");
    assert_eq!(r.0, 200, "{}", String::from_utf8_lossy(&r.2));
    check("post", "/vehicle/stop", "200", &json_of(&r.2));
    // A field the document does not name fails a closed schema.
    let mut undocumented = json_of(&r.2);
    undocumented["extra"] = json!(1);
    assert!(
        check_schema(
            &doc,
            &reply_schema("post", "/vehicle/stop", "200"),
            &undocumented,
            "$"
        )
        .is_err()
    );
    let events = shot_events(a, |evs| {
        evs.iter()
            .any(|e| e["kind"] == "stopped" && e["shot"] == id.as_str())
    });
    let event_schema = json!({"$ref": "#/components/schemas/ShotEvent"});
    for e in &events {
        check_schema(&doc, &event_schema, e, "$").unwrap_or_else(|err| panic!("{err}\n{e:#}"));
    }
    let kinds: Vec<&str> = events
        .iter()
        .filter(|e| e["shot"] == id.as_str())
        .map(|e| e["kind"].as_str().unwrap())
        .filter(|k| *k != "georeferenced")
        .collect();
    assert_eq!(
        kinds,
        ["localised", "uploaded", "started", "stopped"],
        "{events:?}"
    );
    assert!(
        events.iter().any(|e| e["kind"] == "not_localised"),
        "{events:?}"
    );
    let seqs: Vec<u64> = events.iter().map(|e| e["seq"].as_u64().unwrap()).collect();
    assert!(seqs.windows(2).all(|w| w[0] < w[1]), "{seqs:?}");
    // A variant without a required field does not pass.
    let mut bad = events[0].clone();
    bad.as_object_mut().unwrap().remove("shot");
    assert!(check_schema(&doc, &event_schema, &bad, "$").is_err());

    // The status as deltas: the whole document first, then patches with
    // only what changed; applied in order they give documents of the
    // Status schema, the last one the daemon's status now.
    let status_schema = reply_schema("get", "/status", "200");
    let evs = sse_events(a, |evs| {
        evs.iter().filter(|(n, _)| n == "status_patch").count() >= 4
    });
    let statuses: Vec<&(String, Value)> = evs
        .iter()
        .filter(|(n, _)| n.starts_with("status"))
        .collect();
    assert_eq!(statuses[0].0, "status", "{statuses:?}");
    let whole = statuses[0].1.to_string().len();
    let mut page = statuses[0].1.clone();
    check_schema(&doc, &status_schema, &page, "$").unwrap_or_else(|e| panic!("{e}\n{page:#}"));
    let patch_schema = json!({"$ref": "#/components/schemas/StatusPatch"});
    for (name, patch) in &statuses[1..] {
        assert_eq!(name, "status_patch", "one whole status per connection");
        check_schema(&doc, &patch_schema, patch, "$").unwrap_or_else(|e| panic!("{e}\n{patch:#}"));
        // Only what changed: the vehicle, slam and shot counts of this
        // server stand still; the uptime moves.
        let len = patch.to_string().len();
        assert!(
            len * 4 < whole,
            "a patch of {len} bytes against the whole {whole}: {patch}"
        );
        assert!(patch["uptime_s"].is_f64(), "{patch}");
        // The daemon's clock moves with it: this server's is the system's.
        let sys = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap()
            .as_secs_f64();
        let clock = patch["now_unix"].as_f64().unwrap_or(f64::NAN);
        assert!((clock - sys).abs() < 30.0, "now_unix {clock} against {sys}");
        assert!(patch.get("shots").is_none(), "{patch}");
        let before = page["uptime_s"].as_f64().unwrap();
        shotpilot::api::apply_status_patch(&mut page, patch);
        assert!(page["uptime_s"].as_f64().unwrap() > before, "{patch}");
        check_schema(&doc, &status_schema, &page, "$").unwrap_or_else(|e| panic!("{e}\n{page:#}"));
    }
    let now = json_of(&http(a, "GET", "/api/v1/status", &[], b"").2);
    assert_eq!(page["shots"], now["shots"]);
    assert_eq!(page["slam"], now["slam"]);
    assert_eq!(page["video"]["counters"], now["video"]["counters"]);

    // The check can fail: a reply without a documented field, or with a
    // field of another type, does not pass.
    let mut kfs = json_of(&http(a, "GET", "/api/v1/keyframes", &[], b"").2);
    let schema = reply_schema("get", "/keyframes", "200");
    assert!(check_schema(&doc, &schema, &kfs, "$").is_ok());
    kfs["keyframes"][0]["world_from_cam"]
        .as_object_mut()
        .unwrap()
        .remove("translation");
    assert!(check_schema(&doc, &schema, &kfs, "$").is_err());
    let mut st = json_of(&http(a, "GET", "/api/v1/status", &[], b"").2);
    st["slam"]["keyframes"] = json!("two");
    assert!(check_schema(&doc, &reply_schema("get", "/status", "200"), &st, "$").is_err());
}

/// `POST /vehicle/stop`: needs the token; a refusal is 502 and changes no
/// shot; an acknowledged stop marks the started shot `stopped` with the
/// reason and the acknowledgement; without a vehicle, 503.
#[test]
fn stop_holds_and_marks_the_flown_shot_stopped() {
    let dir = tempfile::tempdir().unwrap();
    let srv = start(dir.path(), Some("sekrit"), true);
    let a = srv.addr;
    let auth = ("Authorization", "Bearer sekrit");
    let ct = ("Content-Type", "application/json");
    assert_error(
        &http(a, "POST", "/api/v1/vehicle/stop", &[], b""),
        401,
        "unauthorized",
    );
    assert_eq!(*srv.vehicle.stops.lock().unwrap(), 0);
    let r = http(a, "POST", "/api/v1/shots", &[auth, ct], &good_shot(1));
    assert_eq!(r.0, 201);
    let id = json_of(&r.2)["id"].as_str().unwrap().to_owned();
    for step in ["mission", "start"] {
        let r = http(
            a,
            "POST",
            &format!("/api/v1/shots/{id}/{step}"),
            &[auth],
            b"",
        );
        assert_eq!(r.0, 200, "{step}: {}", String::from_utf8_lossy(&r.2));
    }
    // Refused: an error naming the result; the shot is still started.
    srv.vehicle
        .refuse_stop
        .store(true, std::sync::atomic::Ordering::SeqCst);
    let r = http(a, "POST", "/api/v1/vehicle/stop", &[auth], b"");
    assert_error(&r, 502, "vehicle_failed");
    assert!(String::from_utf8_lossy(&r.2).contains("MAV_RESULT_DENIED"));
    let s = json_of(&http(a, "GET", &format!("/api/v1/shots/{id}"), &[], b"").2);
    assert_eq!(s["mission"]["state"], "started");
    // Acknowledged.
    srv.vehicle
        .refuse_stop
        .store(false, std::sync::atomic::Ordering::SeqCst);
    let r = http(a, "POST", "/api/v1/vehicle/stop", &[auth], b"");
    assert_eq!(r.0, 200, "{}", String::from_utf8_lossy(&r.2));
    let v = json_of(&r.2);
    assert_eq!(v["stopped"], true);
    assert_eq!(v["ack"], "MAV_RESULT_ACCEPTED");
    assert_eq!(v["mode"], "AUTO.LOITER");
    assert_eq!(v["shot"], id.as_str());
    assert_eq!(v["refinement_cancelled"], id.as_str());
    let s = json_of(&http(a, "GET", &format!("/api/v1/shots/{id}"), &[], b"").2);
    assert_eq!(s["mission"]["state"], "stopped", "{s}");
    let stop = &s["mission"]["details"]["stop"];
    assert_eq!(stop["reason"], "stopped by the operator");
    assert_eq!(stop["ack"], "MAV_RESULT_ACCEPTED");
    assert_eq!(stop["at_unix"], v["at_unix"]);
    // A second stop holds again but marks nothing new.
    let v = json_of(&http(a, "POST", "/api/v1/vehicle/stop", &[auth], b"").2);
    assert!(v["shot"].is_null(), "{v}");
    assert_eq!(*srv.vehicle.stops.lock().unwrap(), 3);
    // No vehicle link: 503.
    let dir2 = tempfile::tempdir().unwrap();
    let srv2 = start(dir2.path(), None, false);
    assert_error(
        &http(srv2.addr, "POST", "/api/v1/vehicle/stop", &[], b""),
        503,
        "no_vehicle",
    );
}

/// Keys of `v` that the schema's `properties` do not name, at every level
/// the schema describes (`$ref` and `oneOf` followed).
fn undocumented(doc: &Value, schema: &Value, v: &Value, at: &str, out: &mut Vec<String>) {
    if let Some(r) = schema["$ref"].as_str() {
        let name = r.trim_start_matches("#/components/schemas/");
        return undocumented(doc, &doc["components"]["schemas"][name], v, at, out);
    }
    if let Some(alts) = schema["oneOf"].as_array() {
        for s in alts {
            if check_schema(doc, s, v, at).is_ok() {
                undocumented(doc, s, v, at, out);
            }
        }
        return;
    }
    if let (Some(o), Some(props)) = (v.as_object(), schema["properties"].as_object()) {
        for (k, x) in o {
            match props.get(k) {
                Some(sub) => undocumented(doc, sub, x, &format!("{at}.{k}"), out),
                None => out.push(format!("{at}.{k}")),
            }
        }
    }
}

/// `/status`'s `vehicle.georeference` is typed
/// (`shotpilot::geo::GeoreferenceStatus`) and the OpenAPI document's
/// `GeoreferenceStatus` schema says every field of it, in each of its
/// states (waiting, refused, a fit with a saved georeference beside it):
/// the required fields there with their types, and no field the document
/// does not name.
#[test]
fn the_georeference_status_is_documented_field_by_field() {
    use shotpilot::geo::continuity::{Check, SavedStatus};
    use shotpilot::geo::saved::SavedFit;
    use shotpilot::geo::status::{
        ClockStatus, Evidence, FitState, FitView, GeoreferenceStatus, HistoryCounts, HomeView,
        SimView,
    };
    let doc: Value = serde_json::from_str(shotpilot::api::OPENAPI).expect("the document parses");
    let base = GeoreferenceStatus {
        home: Some(HomeView {
            lat_deg: 47.4,
            lon_deg: 8.5,
            alt_amsl_m: 488.0,
        }),
        pairs: 12,
        keyframes_pending: 1,
        keyframes_dropped: 0,
        history: HistoryCounts {
            positions: 500,
            attitudes: 500,
            gimbals: 100,
        },
        counts: Default::default(),
        clock: ClockStatus {
            telemetry: shotpilot::geo::TelemetryClock::Boot,
            boot_offset_unix_s: Some(1.7e9),
            use_frame_timestamps: true,
            video_latency_s: 0.1,
            video_delay_ms_median: Some(80.0),
            video_delay_ms_mean_all: None,
        },
        fit_age_s: None,
        evidence: Evidence {
            restored_pairs: 0,
            frame_pairs: 3,
            live_keyframe_pairs: 9,
        },
        saved: None,
        fit: FitState::Waiting {
            reason: "12 keyframe pairs so far".into(),
        },
    };
    let refused = GeoreferenceStatus {
        fit: FitState::Refused {
            reason: "too little motion".into(),
            error: "TooLittleMotion".into(),
        },
        ..base.clone()
    };
    let fitted = GeoreferenceStatus {
        fit_age_s: Some(0.5),
        saved: Some(SavedStatus {
            pairs_in_file: 40,
            restored: 38,
            waiting: 0,
            unmatched: 2,
            saved_unix: 1.7e9,
            fit_when_saved: Some(SavedFit {
                scale: 11.0,
                rms_m: 0.4,
                inliers: 38,
                pairs: 40,
            }),
            home_moved_m: None,
            dropped: None,
            check: Some(Check::Waiting {
                live_pairs: 2,
                needed: 6,
            }),
        }),
        fit: FitState::Ok(Box::new(FitView {
            source: "fit",
            held: None,
            scale: 11.0,
            rms_m: 0.3,
            max_residual_m: 0.9,
            rotation_rms_deg: Some(0.4),
            time_offset_s: None,
            keyframes_used: 11,
            older_pairs_set_aside: 0,
            gnss_bias_m: Some([0.3, -0.2, 0.1]),
            mount_offset: Some(shotpilot::geo::MountOffset {
                pitch_deg: -0.9,
                yaw_deg: 0.6,
                pitch_sigma_deg: 0.05,
                yaw_sigma_deg: 0.08,
                pairs: 11,
            }),
            recent: None,
            spread_m: [8.0, 5.0, 0.5],
            ned_from_map: SimView {
                scale: 11.0,
                rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
                translation: [1.0, 2.0, 3.0],
            },
        })),
        ..base.clone()
    };
    let schema = json!({"$ref": "#/components/schemas/GeoreferenceStatus"});
    for st in [base, refused, fitted] {
        let v = serde_json::to_value(&st).expect("serialises");
        check_schema(&doc, &schema, &v, "$").unwrap_or_else(|e| panic!("{e}\n{v:#}"));
        let mut extra = Vec::new();
        undocumented(&doc, &schema, &v, "$", &mut extra);
        assert!(
            extra.is_empty(),
            "fields the document does not name: {extra:?}\n{v:#}"
        );
    }
}
