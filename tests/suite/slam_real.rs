//! The SLAM on the real sequences in `../shared/data` (skipped with a message
//! when that folder is absent): teddy initialises early, tracks every frame
//! after, and meets the accuracy gates; a camera standing still (EuRoC)
//! does not initialise and says why; the map keeps its invariants and a
//! saved map loads back equal; damaged map files are refused.

use crate::cli_support::run_ok;
use crate::data_support;

use std::path::PathBuf;
use std::sync::Arc;

use shotpilot::eval;
use shotpilot::slam::{self, Map, Slam, SlamRun, mapfile};
use shotpilot::video::dataset::Dataset;

fn shared(name: &str) -> Option<PathBuf> {
    data_support::shared_data(name)
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

/// A map loaded from file has no keyframe database (the file holds
/// descriptors, not BoW vectors); `Slam::from_map` rebuilds it, so frames
/// that were not keyframes relocalise against the reloaded map, each from
/// scratch, within 2 cm and 1 degree of the ground truth (after the Sim(3)
/// that aligns the run's trajectory to it) and close to the pose they had
/// when tracked in sequence.
fn relocalises_on_the_reloaded_map(ds: &Dataset, run: &SlamRun, loaded: &Map) {
    assert!(loaded.places().is_none(), "the file stores no BoW index");
    let vocabulary = Arc::new(shotpilot::bow::Vocabulary::builtin().unwrap());
    let params = slam::Params {
        sequential: true,
        ..Default::default()
    };
    let tracked = run.trajectory();
    let gt = ds.groundtruth.as_ref().unwrap();
    let sim = eval::evaluate(gt, &tracked, &eval::Params::default())
        .unwrap()
        .alignment;
    let gt_at = |t: f64| {
        gt.poses
            .iter()
            .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
            .map(|p| (p.t, p.world_from_cam))
            .unwrap()
    };
    let kf_frames: Vec<u64> = loaded.keyframes().map(|k| k.frame_index).collect();
    let mut tried = 0;
    for target in [35usize, 60, 90] {
        // The nearest frame at or after `target` that is not a keyframe.
        let Some(i) = (target..ds.len()).find(|i| !kf_frames.contains(&(*i as u64))) else {
            continue;
        };
        let f = ds.frame(i).unwrap();
        let want = tracked
            .poses
            .iter()
            .find(|p| p.t == f.timestamp)
            .expect("frame tracked in the run")
            .world_from_cam;
        let mut s = Slam::from_map(loaded.clone(), params.clone(), vocabulary.clone()).unwrap();
        {
            let m = s.map();
            let m = m.lock().unwrap();
            let places = m.places().expect("keyframe database rebuilt");
            assert_eq!(places.features.len(), loaded.keyframe_count());
            m.check_invariants().unwrap();
        }
        assert_eq!(s.state(), slam::TrackState::Lost);
        let out = s.process(i as u64, f.timestamp, Arc::new(f.image));
        assert_eq!(
            out.state,
            slam::TrackState::Tracking,
            "frame {i} not relocalised: {:?}",
            out.reason
        );
        let got = out.cam_from_world.unwrap().inverse();
        let (a, b) = (sim.transform_pose(&got), sim.transform_pose(&want));
        let (tg, g) = gt_at(f.timestamp);
        assert!(
            (tg - f.timestamp).abs() < 0.02,
            "no ground truth near frame {i}"
        );
        let dp = (a.translation.vector - g.translation.vector).norm();
        let da = a.rotation.angle_to(&g.rotation).to_degrees();
        // The tracked pose's own rotation error: the ground truth's
        // orientation is aligned by positions only (the same rotation for
        // every frame), so a constant offset of a degree or two remains.
        let db = b.rotation.angle_to(&g.rotation).to_degrees();
        let rp = (a.translation.vector - b.translation.vector).norm();
        let ra = a.rotation.angle_to(&b.rotation).to_degrees();
        println!(
            "reloaded map: frame {i} relocalised with {} inliers: vs ground truth {:.1} mm {da:.3} deg (tracked in sequence: {db:.3} deg); vs tracked in sequence {:.1} mm {ra:.3} deg",
            out.inliers,
            dp * 1e3,
            rp * 1e3
        );
        assert!(dp < 0.02, "frame {i}: {dp} m from the ground truth");
        assert!(ra < 1.0, "frame {i}: {ra} deg from its tracked pose");
        assert!(da < db + 1.0, "frame {i}: {da} deg from the ground truth");
        assert!(rp < 0.01, "frame {i}: {rp} m from its tracked pose");
        tried += 1;
    }
    assert_eq!(tried, 3);
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
    relocalises_on_the_reloaded_map(&ds, &run, &back);

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
    let reason = run.last_reason.map(|r| r.to_string()).unwrap_or_default();
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
    let out = run_ok(
        std::process::Command::new(env!("CARGO_BIN_EXE_shotpilot"))
            .args(["slam", "--sequential", "--json", "--out"])
            .arg(tmp.path())
            .arg(&dir),
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
