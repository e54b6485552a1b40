//! Measurement (not a gate, run by hand): where does a reloaded map lose
//! anchors-shot quality? One SLAM run over a rendered dataset, then the
//! same anchors shot on a spread of keyframes against: the live map, the
//! map after the final bundle adjustment of `finish` (what the daemon
//! saves at shutdown), that map reloaded as format version 1 stored it
//! (keyframe images re-encoded as JPEG, quality 90: one generation per
//! save), reloaded five times so, reloaded as version 2 stores it
//! (lossless), and continued (SLAM on the reloaded map over mapped
//! ground, as after a restart).
//!
//! ```sh
//! PROBE_DATA=DIR cargo test --release --test suite map_reload_probe:: -- --ignored --nocapture
//! ```

use std::path::{Path, PathBuf};
use std::sync::Arc;

use image::GrayImage;
use nalgebra::Point2;
use shotpilot::shot::anchors::{AnchorParams, desired_shot_from_anchors};
use shotpilot::shot::localize::{Localization, LocalizeParams, localize};
use shotpilot::slam::{self, KeyFrameId, Map, Slam};
use shotpilot::video::dataset::Dataset;

const ANCHORS: [[f64; 2]; 4] = [[40.0, 30.0], [600.0, 30.0], [600.0, 450.0], [40.0, 450.0]];

/// Inliers and reprojection RMSE of the anchors shot on `kf` (the
/// keyframe's image taken from `img_from`), or why it was refused.
fn shot(map: &Map, img_from: &Map, kf: KeyFrameId) -> Result<(usize, f64), String> {
    let image = img_from
        .keyframe(kf)
        .and_then(|k| k.image.clone())
        .ok_or("no image")?;
    let pts = ANCHORS.map(|p| Point2::new(p[0], p[1]));
    let s = desired_shot_from_anchors(&image, &pts, &AnchorParams::default())
        .map_err(|e| e.to_string())?;
    match localize(
        map,
        &s.image,
        Some(&s.mask),
        None,
        &LocalizeParams::default(),
    )
    .map_err(|e| e.to_string())?
    {
        Localization::Localized(p) => Ok((p.inliers, p.reprojection_rmse_px)),
        Localization::NotLocalized { reason } => Err(reason.to_string()),
    }
}

/// Saved and loaded as this build does (version 2).
fn reload_v2(map: &Map) -> Map {
    let bytes = slam::mapfile::encode(map).unwrap();
    slam::mapfile::decode(&bytes, Path::new("mem")).unwrap()
}

/// Saved and loaded as version 1 did: every keyframe image re-encoded as
/// JPEG at quality 90 (the rest of the file is lossless in both versions).
fn reload_v1(map: &Map) -> Map {
    let mut out = reload_v2(map);
    let ids: Vec<KeyFrameId> = out.keyframes().map(|k| k.id).collect();
    for id in ids {
        let kf = out.keyframe_mut(id).unwrap();
        if let Some(img) = kf.image.clone() {
            let mut jpeg = Vec::new();
            image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
                .encode_image(img.as_ref())
                .unwrap();
            let back: GrayImage = slam::mapfile::decode_image(&jpeg).unwrap();
            kf.image = Some(Arc::new(back));
        }
    }
    out
}

fn continued(map: Map, ds: &Dataset, from: usize, n: usize) -> (Map, usize) {
    let params = slam::Params {
        sequential: true,
        ..Default::default()
    };
    let vocab = Arc::new(shotpilot::bow::Vocabulary::builtin().unwrap());
    let mut cont = Slam::from_map(map, params, vocab).unwrap();
    let mut tracked = 0;
    for i in from..(from + n).min(ds.len()) {
        let f = ds.frame(i).unwrap();
        let o = cont.process(100_000 + i as u64, f.timestamp + 1000.0, Arc::new(f.image));
        tracked += usize::from(o.cam_from_world.is_some());
    }
    let m = cont.map().lock().unwrap().clone();
    (m, tracked)
}

#[test]
#[ignore = "measurement, by hand: PROBE_DATA=DIR (a rendered dataset)"]
fn where_a_reloaded_map_loses_shot_quality() {
    let dir = PathBuf::from(std::env::var("PROBE_DATA").expect("PROBE_DATA=DIR"));
    let n: usize = std::env::var("PROBE_FRAMES").map_or(900, |v| v.parse().unwrap());
    let ds = Dataset::open(&dir).unwrap();
    let params = slam::Params {
        sequential: true,
        ..Default::default()
    };
    let mut system = Slam::new(ds.camera, params).unwrap();
    for i in 0..n.min(ds.len()) {
        let f = ds.frame(i).unwrap();
        system.process(i as u64, f.timestamp, Arc::new(f.image));
    }
    let live = system.map().lock().unwrap().clone();
    let fin = system.finish().map;
    let v1 = reload_v1(&fin);
    let mut v1x5 = fin.clone();
    for _ in 0..5 {
        v1x5 = reload_v1(&v1x5);
    }
    let v2 = reload_v2(&fin);
    // Over mapped ground after the restart: frames from the middle.
    let (cont_v1, t1) = continued(v1.clone(), &ds, n / 2, 150);
    let (cont_v2, t2) = continued(v2.clone(), &ds, n / 2, 150);
    eprintln!("continued 150 frames: v1 tracked {t1}, v2 tracked {t2}");
    let names = [
        "live",
        "final BA",
        "v1 reload",
        "v1 reload x5",
        "v2 reload",
        "continued v1",
        "continued v2",
    ];
    let maps = [&live, &fin, &v1, &v1x5, &v2, &cont_v1, &cont_v2];
    eprintln!("kf  | {}", names.join(" | "));
    let ids: Vec<KeyFrameId> = fin.keyframes().map(|k| k.id).collect();
    let step = (ids.len() / 16).max(1);
    let mut sums = [(0usize, 0f64, 0usize); 7];
    for &k in ids.iter().step_by(step) {
        if live.keyframe(k).is_none() {
            continue;
        }
        let mut cells = Vec::new();
        for (m, s) in maps.iter().zip(sums.iter_mut()) {
            match shot(m, m, k) {
                Ok((i, e)) => {
                    s.0 += i;
                    s.1 += e;
                    s.2 += 1;
                    cells.push(format!("{i:4} {e:.3}"));
                }
                Err(why) => cells.push(format!("-- {why}")),
            }
        }
        eprintln!("{:3} | {}", k.0, cells.join(" | "));
    }
    for (name, s) in names.iter().zip(sums) {
        let c = s.2.max(1) as f64;
        eprintln!(
            "{name}: localised {} mean inliers {:.1} mean rmse {:.3} px",
            s.2,
            s.0 as f64 / c,
            s.1 / c
        );
    }
}
