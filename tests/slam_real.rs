//! The SLAM on the real sequences in `../shared/data` (skipped with a message
//! when that folder is absent): teddy initialises early, tracks every frame
//! after, and meets the accuracy gates; a camera standing still (EuRoC)
//! does not initialise and says why; the map keeps its invariants and a
//! saved map loads back equal; damaged map files are refused.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use shotpilot::eval;
use shotpilot::slam::{self, Map, Slam, SlamRun, mapfile};
use shotpilot::video::dataset::Dataset;

fn shared(name: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data")
        .join(name);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!("skipped: {} not present", p.display());
        None
    }
}

fn run_sequential(ds: &Dataset, seed: u64) -> SlamRun {
    let mut params = slam::Params {
        sequential: true,
        ..Default::default()
    };
    params.tracking.seed = seed;
    let mut s = Slam::new(ds.camera, params).unwrap();
    for f in ds.frames() {
        let f = f.unwrap();
        s.process(f.index as u64, f.timestamp, Arc::new(f.image));
    }
    s.finish()
}

fn assert_maps_equal(a: &Map, b: &Map) {
    assert_eq!(a.camera, b.camera);
    assert_eq!(a.keyframe_count(), b.keyframe_count());
    assert_eq!(a.point_count(), b.point_count());
    for (ka, kb) in a.keyframes().zip(b.keyframes()) {
        assert_eq!(ka.id, kb.id);
        assert_eq!(ka.frame_index, kb.frame_index);
        assert_eq!(ka.cam_from_world, kb.cam_from_world);
        assert_eq!(ka.keypoints, kb.keypoints);
        assert_eq!(ka.descriptors, kb.descriptors);
        assert_eq!(ka.points, kb.points);
        assert_eq!(ka.covisible, kb.covisible);
        assert_eq!(ka.parent, kb.parent);
        assert_eq!(ka.children, kb.children);
        let (ia, ib) = (ka.image.as_ref().unwrap(), kb.image.as_ref().unwrap());
        assert_eq!(ia.dimensions(), ib.dimensions());
        // JPEG at quality 90: the mean absolute difference stays small.
        let mad: f64 = ia
            .pixels()
            .zip(ib.pixels())
            .map(|(p, q)| (p.0[0] as f64 - q.0[0] as f64).abs())
            .sum::<f64>()
            / (ia.width() * ia.height()) as f64;
        assert!(
            mad < 3.0,
            "keyframe {:?} image differs by {mad} grey levels on average",
            ka.id
        );
    }
    for (pa, pb) in a.points().zip(b.points()) {
        assert_eq!(pa.id, pb.id);
        assert_eq!(pa.position, pb.position);
        assert_eq!(pa.observations, pb.observations);
        assert_eq!(pa.descriptor, pb.descriptor);
        assert_eq!(pa.normal, pb.normal);
        assert_eq!(
            (pa.min_distance, pa.max_distance),
            (pb.min_distance, pb.max_distance)
        );
    }
}

#[test]
fn teddy_initialises_tracks_and_meets_the_accuracy_gates() {
    let Some(dir) = shared("tum_fr3_teddy_100") else {
        return;
    };
    let ds = Dataset::open(&dir).unwrap();
    let run = run_sequential(&ds, 1);
    let init = run.initialized_at.expect("teddy initialises");
    assert!(init < 30, "initialised at frame {init}");
    // Every frame after initialisation is tracked.
    let tracked: Vec<u64> = run.records.iter().map(|r| r.index).collect();
    for i in init..ds.len() as u64 {
        assert!(tracked.contains(&i), "frame {i} not tracked");
    }
    run.map.check_invariants().unwrap();
    let gt = ds.groundtruth.as_ref().unwrap();
    let all = eval::evaluate(gt, &run.trajectory(), &eval::Params::default()).unwrap();
    let kfs = eval::evaluate(gt, &run.keyframe_trajectory(), &eval::Params::default()).unwrap();
    println!(
        "teddy: init frame {init}, {} frames, {} keyframes, {} points, ATE all {:.4} m, keyframes {:.4} m",
        all.matched,
        run.map.keyframe_count(),
        run.map.point_count(),
        all.ate.rmse,
        kfs.ate.rmse
    );
    assert!(all.ate.rmse <= 0.015, "ATE all frames {} m", all.ate.rmse);
    assert!(kfs.ate.rmse <= 0.010, "ATE keyframes {} m", kfs.ate.rmse);

    // The map file round trip.
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("teddy.map");
    mapfile::save(&run.map, &path).unwrap();
    let back = mapfile::load(&path).unwrap();
    assert_maps_equal(&run.map, &back);

    // Damaged files are refused with their own errors.
    let bytes = std::fs::read(&path).unwrap();
    let mut flipped = bytes.clone();
    let mid = flipped.len() / 2;
    flipped[mid] ^= 0x40;
    assert!(matches!(
        mapfile::decode(&flipped, &path),
        Err(mapfile::MapFileError::Corrupt { .. })
    ));
    assert!(matches!(
        mapfile::decode(&bytes[..bytes.len() - 10], &path),
        Err(mapfile::MapFileError::Corrupt { .. })
    ));
    let mut other_version = bytes.clone();
    other_version[8] = 99;
    assert!(matches!(
        mapfile::decode(&other_version, &path),
        Err(mapfile::MapFileError::Version { found: 99, .. })
    ));
    assert!(matches!(
        mapfile::decode(b"PNG not a map at all........", &path),
        Err(mapfile::MapFileError::BadMagic { .. })
    ));
}

#[test]
fn a_camera_standing_still_does_not_initialise_and_says_why() {
    let Some(dir) = shared("euroc_v101_static95") else {
        return;
    };
    let ds = Dataset::open(&dir).unwrap();
    let run = run_sequential(&ds, 1);
    assert_eq!(run.initialized_at, None);
    assert_eq!(run.map.keyframe_count(), 0);
    let reason = run.last_reason.unwrap_or_default();
    assert!(
        reason.contains("parallax") || reason.contains("matches"),
        "reason: {reason}"
    );
}

#[test]
fn the_cli_reports_json_on_teddy() {
    let Some(dir) = shared("tum_fr3_teddy_100") else {
        return;
    };
    let tmp = tempfile::tempdir().unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_shotpilot"))
        .args(["slam", "--sequential", "--json", "--out"])
        .arg(tmp.path())
        .arg(&dir)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    for key in [
        "frames",
        "tracked_frames",
        "initialized_at_frame",
        "keyframes",
        "map_points",
        "median_track_ms",
        "p95_track_ms",
        "ate_rmse_m",
        "ate_keyframes_rmse_m",
    ] {
        assert!(!v[key].is_null(), "missing {key}: {v}");
    }
    assert_eq!(v["frames"], 100);
    let traj = eval::Trajectory::read_tum(&tmp.path().join("trajectory.txt")).unwrap();
    assert_eq!(traj.len() as u64, v["tracked_frames"].as_u64().unwrap());
    assert!(tmp.path().join("keyframes.txt").is_file());
}
