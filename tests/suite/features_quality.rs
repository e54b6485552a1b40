//! Homography-warp evaluation of the extractor on real frames: teddy frames
//! warped with known homographies (rotation 0-45 degrees, zoom 0.6-1.6, mild
//! perspective, noise of 3 gray levels), 40 pairs. Measures repeatability,
//! matching precision and recall (mutual nearest, ratio 0.8, distance <= 64,
//! correct within 3 px) and spread (share of 16 x 12 cells holding a
//! keypoint).
//!
//! Needs `../shared/data` (or `SHOTPILOT_DATA`); skips with a message when
//! absent. The OpenCV comparison needs opencv-python-headless
//! (`SHOTPILOT_PYTHON`, default `python3`).

use crate::data_support;

use std::path::PathBuf;
use std::process::Command;

use shotpilot::features::{OrbExtractor, Params};
use shotpilot::features_eval::{self as eval, PairMetrics, WarpPair, WarpParams};

fn data_dir() -> Option<PathBuf> {
    data_support::shared_data("tum_fr3_teddy_100")
}

fn pairs(teddy: &std::path::Path) -> Vec<WarpPair> {
    let frames = eval::load_dataset_gray(teddy).expect("teddy frames load");
    let frames: Vec<_> = frames.into_iter().step_by(10).collect();
    assert_eq!(frames.len(), 10);
    eval::make_pairs(&frames, 4, &WarpParams::default(), 42)
}

fn ours(pairs: &[WarpPair]) -> PairMetrics {
    let mut ex = OrbExtractor::new(Params::default()).expect("valid defaults");
    let all = eval::evaluate_extractor(&mut ex, pairs, &WarpParams::default()).expect("masks fit");
    eval::mean_metrics(&all)
}

#[test]
fn homography_pairs_reach_the_measured_quality() {
    let Some(teddy) = data_dir() else {
        return;
    };
    let pairs = pairs(&teddy);
    let m = ours(&pairs);
    eprintln!("ours: {m:?}");
    // Measured: repeatability 0.827, precision 0.940, recall 0.453, spread
    // 0.372, 1002 / 952 keypoints. The floors are OpenCV ORB's figures on the
    // same pairs (0.815, 0.936, 0.443, spread 0.308; measured by
    // `homography_pairs_against_opencv`), so this run alone checks that the
    // extractor still reaches them.
    assert!(m.n_a > 950.0 && m.n_b > 900.0, "{m:?}");
    assert!(m.repeatability >= 0.815, "{m:?}");
    assert!(m.precision >= 0.936, "{m:?}");
    assert!(m.recall >= 0.443, "{m:?}");
    assert!(m.spread >= 0.35, "{m:?}");
}

#[test]
#[ignore = "needs opencv-python-headless and ../shared/data"]
fn homography_pairs_against_opencv() {
    let Some(teddy) = data_dir() else {
        return;
    };
    let pairs = pairs(&teddy);
    let dir = tempfile::tempdir().expect("temp dir");
    eval::write_pairs(dir.path(), &pairs).expect("pairs written");
    let python = std::env::var("SHOTPILOT_PYTHON").unwrap_or_else(|_| "python3".into());
    let script = crate::repo_root().join("benches/peers/orb_pairs_opencv.py");
    let st = Command::new(&python)
        .arg(&script)
        .arg(dir.path())
        .status()
        .expect("python runs");
    assert!(st.success(), "OpenCV peer failed");
    let cv =
        eval::read_peer_features(&dir.path().join("opencv_features.json")).expect("peer output");
    assert_eq!(cv.len(), pairs.len());
    let wp = WarpParams::default();
    let theirs: Vec<PairMetrics> = pairs
        .iter()
        .zip(&cv)
        .map(|(p, (a, b))| {
            eval::evaluate_pair(
                p,
                (&a.keypoints, &a.descriptors),
                (&b.keypoints, &b.descriptors),
                &wp,
            )
        })
        .collect();
    let cv = eval::mean_metrics(&theirs);
    let m = ours(&pairs);
    eprintln!("ours:   {m:?}\nopencv: {cv:?}");
    assert!(m.spread > cv.spread, "spread");
    assert!(m.repeatability >= cv.repeatability, "repeatability");
    assert!(m.precision >= cv.precision, "precision");
    assert!(m.recall >= cv.recall, "recall");
    // OpenCV returns about as many keypoints (it may return fewer than
    // asked): the comparison is not won by returning fewer.
    assert!(
        m.n_a >= 0.95 * cv.n_a && m.n_b >= 0.95 * cv.n_b,
        "keypoint counts"
    );
}
