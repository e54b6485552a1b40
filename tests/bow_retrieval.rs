//! Place recognition on real images: the TUM fr3/teddy sequence (first 100
//! frames of the CC BY 4.0 TUM RGB-D benchmark, in `../shared/data`).
//! Keyframes are every 5th frame; every other frame queries the database and
//! its top-1 keyframe is checked against time and the ground-truth poses.
//! The vocabulary (k = 10, L = 4) is trained on the keyframes only, so no
//! query image is in its training set.
//!
//! Skips (with a message) when the data is absent.

use std::path::{Path, PathBuf};

use shotpilot::bow::{KeyFrameDatabase, KeyFrameId, TrainParams, Vocabulary};
use shotpilot::features::{OrbExtractor, Params};
use shotpilot::video::dataset::Dataset;

fn shared_data() -> Option<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for rel in ["../shared/data", "../../shared/data"] {
        let p = root.join(rel);
        if p.is_dir() {
            return Some(p);
        }
    }
    eprintln!("skipped: ../shared/data not present");
    None
}

#[test]
fn teddy_non_keyframes_find_nearby_keyframes() {
    let Some(data) = shared_data() else { return };
    let ds = Dataset::open(&data.join("tum_fr3_teddy_100")).unwrap();
    let gt = ds.groundtruth.clone().unwrap();
    let mut orb = OrbExtractor::new(Params::default()).unwrap();
    let descs: Vec<Vec<[u64; 4]>> = ds
        .frames()
        .map(|f| orb.extract(&f.unwrap().image, None).descriptors)
        .collect();
    let keyframes: Vec<usize> = (0..descs.len()).step_by(5).collect();
    let train: Vec<&[[u64; 4]]> = keyframes.iter().map(|&i| descs[i].as_slice()).collect();
    let params = TrainParams {
        k: 10,
        levels: 4,
        seed: 1,
        max_iterations: 25,
    };
    let voc = Vocabulary::train(&train, &params, &mut |_| {}).unwrap();
    let mut db = KeyFrameDatabase::new(voc.word_count());
    for &i in &keyframes {
        db.add(KeyFrameId(i as u64), voc.transform(&descs[i]))
            .unwrap();
    }
    // Ground-truth pose nearest in time (within 20 ms).
    let pose = |i: usize| {
        let t = ds.timestamp(i).unwrap();
        gt.poses
            .iter()
            .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
            .filter(|p| (p.t - t).abs() < 0.02)
            .map(|p| p.world_from_cam)
    };
    let (mut q, mut bracket, mut gt_near, mut with_gt) = (0, 0, 0, 0);
    for i in (0..descs.len()).filter(|i| i % 5 != 0) {
        let top = db.query(&voc.transform(&descs[i]), 3);
        let k = top[0].id.0 as usize;
        q += 1;
        // The two keyframes bracketing frame i in time.
        if k.abs_diff(i) < 5 {
            bracket += 1;
        }
        // The two keyframes nearest to frame i in ground-truth position.
        let Some(p) = pose(i) else { continue };
        let mut by_dist: Vec<(f64, usize)> = keyframes
            .iter()
            .filter_map(|&kf| {
                pose(kf).map(|pk| ((pk.translation.vector - p.translation.vector).norm(), kf))
            })
            .collect();
        by_dist.sort_by(|a, b| a.0.total_cmp(&b.0));
        with_gt += 1;
        if by_dist.iter().take(2).any(|&(_, kf)| kf == k) {
            gt_near += 1;
        }
    }
    eprintln!(
        "teddy: {} keyframes, {q} queries; top-1 brackets the query in time: {bracket}/{q}; \
         top-1 among the 2 nearest keyframes by ground truth: {gt_near}/{with_gt}",
        keyframes.len()
    );
    assert!(bracket as f64 >= 0.95 * q as f64, "{bracket}/{q}");
    assert!(
        gt_near as f64 >= 0.9 * with_gt as f64,
        "{gt_near}/{with_gt}"
    );
}
