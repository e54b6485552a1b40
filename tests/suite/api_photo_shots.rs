//! Photos through the real router and the daemon's own shot service
//! ([`LocalizingShots`] on a [`SlamShared`] holding a real map of TUM
//! fr3/teddy): a photo of the mapped scene comes back localised with its
//! sigma; a photo the map cannot place comes back refused with the reason
//! and the nearest keyframes (ids of the map, BoW scores, camera centres,
//! picture URLs that the same server serves).
//!
//! Needs ../shared/data/tum_fr3_teddy_100 (skips with a message otherwise;
//! `.ci/run` requires it).

use crate::data_support;
use crate::http_support;

use std::io::Cursor;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use image::GrayImage;
use serde_json::Value;

use shotpilot::api::{self, ApiParams, AppState, SlamView};
use shotpilot::daemon::SlamShared;
use shotpilot::daemon::shot_service::LocalizingShots;
use shotpilot::daemon::slam_view::SlamMapSource;
use shotpilot::shot::request::WarpOnly;
use shotpilot::shot::store::ShotStore;
use shotpilot::slam::{self, KeyFrameId, Map, Slam};
use shotpilot::video::dataset::Dataset;
use shotpilot::video::live::{Ingest, unix_now};

/// Frames of teddy the map is built from.
const MAPPED: usize = 40;

fn build_map(ds: &Dataset) -> anyhow::Result<Map> {
    let params = slam::Params {
        sequential: true,
        ..slam::Params::default()
    };
    let mut system = Slam::new(ds.camera, params)?;
    for i in 0..ds.len().min(MAPPED) {
        let f = ds.frame(i)?;
        system.process(f.index as u64, f.timestamp, Arc::new(f.image));
    }
    Ok(system.finish().map)
}

struct Server {
    addr: SocketAddr,
    _rt: tokio::runtime::Runtime,
}

/// The API as the daemon serves it, with the daemon's shot service on `map`.
fn start(dir: &std::path::Path, map: Map) -> anyhow::Result<Server> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let shared = Arc::new(SlamShared::new(true));
    shared.set_source(Arc::new(SlamMapSource::new(Arc::new(Mutex::new(map)))));
    let slam_view: Arc<dyn SlamView> = shared.clone();
    let state = AppState {
        ingest: Arc::new(Ingest::new()),
        slam: slam_view.clone(),
        vehicle: None,
        shots: Arc::new(LocalizingShots {
            warp: WarpOnly {
                keyframes: slam_view,
                params: Default::default(),
            },
            slam: shared,
            params: Default::default(),
            geo: None,
        }),
        store: Arc::new(ShotStore::open(dir)?),
        params: Arc::new(ApiParams {
            body_limit: 8 << 20,
            ..Default::default()
        }),
        actions: Default::default(),
        started_unix: unix_now(),
        shutdown: Default::default(),
        events: Default::default(),
    };
    let listener = rt.block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))?;
    let addr = listener.local_addr()?;
    rt.spawn(async move {
        if let Err(e) = axum::serve(listener, api::router(state)).await {
            eprintln!("server: {e}");
        }
    });
    Ok(Server { addr, _rt: rt })
}

/// One request through the tests' HTTP client; status, lower-cased
/// header lines and body.
fn http(
    addr: SocketAddr,
    method: &str,
    path: &str,
    content_type: &str,
    body: &[u8],
) -> anyhow::Result<(u16, String, Vec<u8>)> {
    let r = http_support::send(
        addr,
        method,
        path,
        &[("content-type", content_type)],
        body,
        Duration::from_secs(60),
    );
    Ok((r.status, r.head, r.body))
}

fn png_of(img: &GrayImage) -> anyhow::Result<Vec<u8>> {
    let mut out = Vec::new();
    img.write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)?;
    Ok(out)
}

fn json_of(b: &[u8]) -> anyhow::Result<Value> {
    serde_json::from_slice(b).map_err(|e| anyhow::anyhow!("{e}: {}", String::from_utf8_lossy(b)))
}

#[test]
fn a_photo_is_localised_with_its_sigma_or_refused_with_the_reason_and_where_to_fly()
-> anyhow::Result<()> {
    let Some(dir) = data_support::shared_data("tum_fr3_teddy_100") else {
        return Ok(());
    };
    let ds = Dataset::open(&dir)?;
    let map = build_map(&ds)?;
    let tmp = tempfile::tempdir()?;
    let srv = start(tmp.path(), map.clone())?;
    let a = srv.addr;

    // A frame of the mapped stretch, as a photo of the map camera's size.
    let photo = ds.frame(MAPPED / 2 + 1)?.image;
    let r = http(
        a,
        "POST",
        "/api/v1/shots/photo",
        "image/png",
        &png_of(&photo)?,
    )?;
    assert_eq!(r.0, 201, "{}", String::from_utf8_lossy(&r.2));
    let shot = json_of(&r.2)?;
    assert_eq!(shot["status"], "localised", "{shot}");
    let loc = &shot["localisation"];
    let sigma = &loc["sigma"];
    let position = sigma["position"].as_f64().unwrap_or(f64::NAN);
    let fraction = sigma["position_fraction_of_distance"]
        .as_f64()
        .unwrap_or(f64::NAN);
    let rotation = sigma["rotation_deg"].as_f64().unwrap_or(f64::NAN);
    println!("localised: sigma {sigma}");
    // Present, positive, and within the gate that let it through.
    assert!(position > 0.0, "{shot}");
    assert!(fraction > 0.0 && fraction <= 0.02, "{shot}");
    assert!(rotation > 0.0 && rotation <= 1.0, "{shot}");
    // The position sigma is the fraction of a distance inside the scene:
    // teddy's map spans a few units, the camera stands about one from it.
    assert!(position < fraction * 10.0, "{shot}");
    let kf = loc["keyframe_id"].as_u64().unwrap_or(u64::MAX);
    assert!(
        u32::try_from(kf).is_ok_and(|k| map.keyframe(KeyFrameId(k)).is_some()),
        "{shot}"
    );
    // Stored: the same record is read back.
    let id = shot["id"].as_str().unwrap_or_default().to_owned();
    let back = http(a, "GET", &format!("/api/v1/shots/{id}"), "text/plain", b"")?;
    assert_eq!(back.0, 200);
    assert_eq!(json_of(&back.2)?["localisation"]["sigma"], *sigma);

    // A photo of something the map never saw: a grey-level texture with
    // plenty of corners.
    let other = GrayImage::from_fn(640, 480, |x, y| {
        let v = ((x / 9 + y / 7) % 2) * 150 + ((x * 31 + y * 17) % 53) + ((x * y) % 29);
        image::Luma([v.min(255) as u8])
    });
    let r = http(
        a,
        "POST",
        "/api/v1/shots/photo",
        "image/png",
        &png_of(&other)?,
    )?;
    assert_eq!(r.0, 201, "{}", String::from_utf8_lossy(&r.2));
    let shot = json_of(&r.2)?;
    println!("refused: {shot}");
    assert_eq!(shot["status"], "not_localised", "{shot}");
    assert!(shot["localisation"].is_null(), "{shot}");
    let reason = shot["reason"].as_str().unwrap_or_default();
    assert!(!reason.is_empty(), "{shot}");
    let nearest = shot["nearest_keyframes"]
        .as_array()
        .cloned()
        .unwrap_or_default();
    assert_eq!(nearest.len(), 3, "{shot}");
    // GET /keyframes: (id, camera centre, picture size) of each.
    let listed: Vec<(u64, [f64; 3], (u32, u32))> = {
        let r = http(a, "GET", "/api/v1/keyframes", "text/plain", b"")?;
        assert_eq!(r.0, 200);
        let v = json_of(&r.2)?;
        v["keyframes"]
            .as_array()
            .cloned()
            .unwrap_or_default()
            .iter()
            .map(|k| {
                let t = &k["world_from_cam"]["translation"];
                let c = |i: usize| t[i].as_f64().unwrap_or(f64::NAN);
                let size = |f: &str| k[f].as_u64().and_then(|x| u32::try_from(x).ok());
                (
                    k["id"].as_u64().unwrap_or(u64::MAX),
                    [c(0), c(1), c(2)],
                    (size("width").unwrap_or(0), size("height").unwrap_or(0)),
                )
            })
            .collect()
    };
    assert_eq!(listed.len(), map.keyframe_count());
    let mut last_score = f64::INFINITY;
    for n in &nearest {
        let id = n["keyframe_id"].as_u64().unwrap_or(u64::MAX);
        let score = n["score"].as_f64().unwrap_or(f64::NAN);
        // Best first, L1 scores in (0, 1].
        assert!(score > 0.0 && score <= 1.0 && score <= last_score, "{n}");
        last_score = score;
        // A keyframe of the map, at its camera centre.
        let (_, centre, size) = listed
            .iter()
            .find(|k| k.0 == id)
            .copied()
            .unwrap_or_else(|| panic!("keyframe {id} is not in GET /keyframes"));
        let pos: Vec<f64> = n["position"]
            .as_array()
            .map(|a| a.iter().filter_map(Value::as_f64).collect())
            .unwrap_or_default();
        assert_eq!(pos.len(), 3, "{n}");
        for (p, t) in pos.iter().zip(centre) {
            assert!((p - t).abs() < 1e-9, "{n}: centre {centre:?}");
        }
        // Its picture, served where the reply says.
        let url = n["image_url"].as_str().unwrap_or_default();
        assert_eq!(url, format!("/api/v1/keyframes/{id}/image.jpg"));
        let img = http(a, "GET", url, "text/plain", b"")?;
        assert_eq!(img.0, 200, "{url}");
        assert!(img.1.contains("content-type: image/jpeg"), "{}", img.1);
        let decoded = image::load_from_memory(&img.2)?;
        assert_eq!((decoded.width(), decoded.height()), size, "{url}");
    }
    Ok(())
}
