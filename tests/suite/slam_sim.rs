//! The SLAM on simulator renders made in the test (`shotpilot-sim`, world
//! seed 5, the start of the `explore` survey flight at 15 frames per
//! second, as a drone's video; sensor noise on):
//!
//! - the flight starts over flat ground, so initialisation must resolve the
//!   homography's twin reconstructions; it initialises within the first
//!   second, tracks every frame after, and the ATE stays under 0.5 % of the
//!   path length;
//! - relocalisation: 30 black frames mid-flight, then the video jumps back
//!   to a part of the flight mapped seconds earlier; tracking recovers
//!   within 10 frames with the right pose (< 2 cm and 1 degree after Sim(3)
//!   alignment of the frames tracked before the loss to the ground truth).
//!
//! Scene scale: the flight test flies the path as it is, about 10 m over
//! the ground at 3.8 m/s. The relocalisation test flies it shrunk to 0.2
//! towards its start: 2-3 m over the ground at 0.8 m/s, the ground 2-6 m
//! away, about the depth of an indoor scene (at the full scale the
//! recovered poses are 4-5 cm and 0.1 degree off, 0.4 % of the height, as
//! are the frames of the first pass; at 0.3, 1-3 cm).

use std::path::Path;
use std::sync::Arc;

use nalgebra::{Isometry3, Point3};

use shotpilot::eval::{self, Trajectory};
use shotpilot::geometry;
use shotpilot::slam::{self, KeypointState, Slam, TrackState};
use shotpilot::video::dataset::Dataset;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, PathSpec};
use shotpilot_sim::world::World;
use tempfile::TempDir;

use crate::sim_support::{SEED, render, render_dir};

const FPS: f64 = 15.0;
/// Scale of the relocalisation scene: the camera 2-3 m above the ground.
const SMALL: f64 = 0.2;

/// Renders the first `seconds` of the explore flight at 15 fps into a
/// temporary folder (removed when the test ends). With `scale` < 1 the
/// camera positions shrink towards the start point (horizontal offsets and
/// height above the ground alike), the orientations stay: the same flight
/// over a scene seen `scale` times as far away.
fn render_explore(seconds: f64, scale: f64) -> TempDir {
    let dir = render_dir("slam_sim");
    let world = Arc::new(World::generate(SEED));
    let explore = CameraPath::explore(&world, PathParams::default());
    let start = explore.world_from_cam(explore.start()).translation.vector;
    let samples: Vec<(f64, Isometry3<f64>)> = (0..=(seconds * 100.0) as usize)
        .map(|i| {
            let t = i as f64 / 100.0;
            let mut pose = explore.world_from_cam(explore.start() + t);
            let p = pose.translation.vector;
            pose.translation.vector = nalgebra::Vector3::new(
                start.x + scale * (p.x - start.x),
                start.y + scale * (p.y - start.y),
                scale * p.z,
            );
            (t, pose)
        })
        .collect();
    let path = CameraPath::from_samples(samples).unwrap();
    let frames = (seconds * FPS).round() as usize + 1;
    render(world, &path, &PathSpec::Explore, frames, dir.path());
    dir
}

fn path_length(gt: &Trajectory) -> f64 {
    gt.poses
        .windows(2)
        .map(|w| {
            (w[1].world_from_cam.translation.vector - w[0].world_from_cam.translation.vector).norm()
        })
        .sum()
}

#[test]
fn explore_initialises_over_flat_ground_and_tracks_every_frame_after() {
    let dir = render_explore(12.0, 1.0);
    let ds = Dataset::open(dir.path()).unwrap();
    let n = (12.0 * FPS) as usize + 1;
    let mut s = Slam::new(
        ds.camera,
        slam::Params {
            sequential: true,
            ..Default::default()
        },
    )
    .unwrap();
    // What tracking made of each keypoint (the page's feature overlay):
    // on every frame tracked against the map, the inliers are the
    // keypoints it kept, and some matches are rejected as outliers.
    let (mut checked, mut outliers) = (0, 0);
    for i in 0..n {
        let f = ds.frame(i).unwrap();
        let (w, h) = (f.image.width() as f32, f.image.height() as f32);
        let out = s.process(i as u64, f.timestamp, Arc::new(f.image));
        assert!(!out.keypoints.is_empty(), "frame {i}: no keypoints");
        assert!(
            out.keypoints
                .iter()
                .all(|k| (0.0..w).contains(&k.x) && (0.0..h).contains(&k.y)),
            "frame {i}: a keypoint outside the image"
        );
        let count = |st: KeypointState| out.keypoints.iter().filter(|k| k.state == st).count();
        if out.cam_from_world.is_some() && !out.initialized {
            assert_eq!(count(KeypointState::Inlier), out.inliers, "frame {i}");
            outliers += count(KeypointState::Outlier);
            checked += 1;
        }
    }
    assert!(checked >= n / 2, "{checked} tracked frames of {n}");
    assert!(outliers > 0, "no match was ever rejected as an outlier");
    println!("keypoint states: {outliers} outliers over {checked} tracked frames");
    let run = s.finish();
    let init = run.initialized_at.expect("the flight initialises");
    assert!(init <= 15, "initialised at frame {init}");
    let tracked: Vec<u64> = run.records.iter().map(|r| r.index).collect();
    for i in init..n as u64 {
        assert!(tracked.contains(&i), "frame {i} not tracked");
    }
    let share = tracked.len() as f64 / n as f64;
    run.map.check_invariants().unwrap();
    let gt = ds.groundtruth.as_ref().unwrap();
    let gt_part = Trajectory {
        poses: gt.poses[..n].to_vec(),
    };
    let length = path_length(&gt_part);
    let ate = eval::evaluate(&gt_part, &run.trajectory(), &eval::Params::default()).unwrap();
    println!(
        "explore 12 s at 15 fps: init frame {init}, tracked {}/{n} ({:.1} %), ATE {:.3} m over {length:.1} m ({:.3} %)",
        tracked.len(),
        100.0 * share,
        ate.ate.rmse,
        100.0 * ate.ate.rmse / length
    );
    assert!(share >= 0.9, "tracked share {share}");
    assert!(
        ate.ate.rmse <= 0.005 * length,
        "ATE {} m over a {length} m path",
        ate.ate.rmse
    );
}

/// What a run over a whole render gave.
struct FullRun {
    /// Frames in the render.
    frames: usize,
    /// Share of them tracked.
    share: f64,
    /// ATE RMSE over the tracked frames, m.
    ate: f64,
    /// ATE RMSE over the keyframes, m.
    ate_keyframes: f64,
    /// The ground truth's path length, m.
    length: f64,
    /// The readout the run modelled, s.
    readout_s: f64,
    /// The rolling-shutter readout estimated from the final map, s (when
    /// asked).
    readout_estimate_s: Option<f64>,
}

impl FullRun {
    /// The gates: at least `min_share` of the frames tracked and the ATE
    /// within `max_ate_share` of the path length.
    fn assert_gates(&self, min_share: f64, max_ate_share: f64) {
        assert!(self.share >= min_share, "tracked share {}", self.share);
        assert!(
            self.ate <= max_ate_share * self.length,
            "ATE {} m over a {} m path",
            self.ate,
            self.length
        );
    }
}

/// Runs the SLAM (sequential) over the whole render in `dir` with the
/// dataset's camera (its rolling-shutter readout from `exposures.txt`, the
/// render's own) or, with `readout_s`, that readout instead.
fn run_full_render(dir: &Path, readout_s: Option<f64>, estimate_readout: bool) -> FullRun {
    let ds = Dataset::open(dir).unwrap();
    assert!(ds.len() >= 600, "{} frames in {}", ds.len(), dir.display());
    let mut camera = ds.camera;
    if let Some(r) = readout_s {
        camera.readout_s = r;
    }
    let mut s = Slam::new(
        camera,
        slam::Params {
            sequential: true,
            ..Default::default()
        },
    )
    .unwrap();
    for f in ds.frames() {
        let f = f.unwrap();
        s.process(f.index as u64, f.timestamp, Arc::new(f.image));
    }
    let run = s.finish();
    let gt = ds.groundtruth.as_ref().unwrap();
    let share = run.records.len() as f64 / ds.len() as f64;
    let ate = eval::evaluate(gt, &run.trajectory(), &eval::Params::default()).unwrap();
    let ate_kf = eval::evaluate(gt, &run.keyframe_trajectory(), &eval::Params::default()).unwrap();
    let length = path_length(gt);
    let readout_estimate_s = estimate_readout.then(|| {
        let grid: Vec<f64> = (0..=10).map(|i| 0.005 * f64::from(i)).collect();
        let e = slam::shutter::estimate_readout(&run.map, &grid, &Default::default())
            .expect("a readout estimate");
        println!(
            "readout estimated from the map: {:.1} ms (RMSE px per readout: {:?})",
            1000.0 * e.readout_s,
            e.trials
                .iter()
                .map(|t| (1000.0 * t.readout_s, t.rmse_px))
                .collect::<Vec<_>>()
        );
        e.readout_s
    });
    println!(
        "{} (readout {:.1} ms): {} frames, init at frame {:?}, tracked {:.2} %, ATE {:.3} m over {length:.1} m ({:.3} %), keyframes {:.3} m",
        dir.display(),
        1000.0 * camera.readout_s,
        ds.len(),
        run.initialized_at,
        100.0 * share,
        ate.ate.rmse,
        100.0 * ate.ate.rmse / length,
        ate_kf.ate.rmse,
    );
    FullRun {
        frames: ds.len(),
        share,
        ate: ate.ate.rmse,
        ate_keyframes: ate_kf.ate.rmse,
        length,
        readout_s: camera.readout_s,
        readout_estimate_s,
    }
}

/// The ATE gate on a full render named by `SHOTPILOT_SLAM_RENDER` (e.g.
/// `shotpilot-sim render --path explore --frames 1350 --seed 5`, the whole
/// survey at 15 frames per second, the ideal world): at least 99 % of the
/// frames tracked and the ATE within 0.5 % of the path length.
/// `.ci/run` makes that render and runs this test with the ignored ones.
#[test]
#[ignore = "needs a render: set SHOTPILOT_SLAM_RENDER to a render folder of >= 600 frames"]
fn a_full_explore_render_meets_the_tracking_and_ate_gates() {
    let dir = std::env::var_os("SHOTPILOT_SLAM_RENDER")
        .expect("SHOTPILOT_SLAM_RENDER names a render folder of >= 600 frames");
    run_full_render(Path::new(&dir), None, false).assert_gates(0.99, 0.005);
}

/// Issue 19's gate on the `field` world (a render named by
/// `SHOTPILOT_SLAM_RENDER_FIELD`, e.g. `shotpilot-sim render --path explore
/// --frames 1350 --seed 5 --realism field`: rolling shutter, motion blur,
/// auto-exposure, JPEG, wind, gimbal error): at least 98 % of the frames
/// tracked and the ATE within 0.2 % of the path length. `.ci/run` makes
/// that render and runs this test with the ignored ones.
///
/// And the rolling-shutter model's gain (issue 35, point 3): the same
/// render run as if its camera had a global shutter puts the keyframes
/// 1.9 times as far from the truth (0.527 against 0.276 m) and every frame
/// 1.65 times (0.475 against 0.288 m). Asserted: the keyframes and the
/// frames at most 0.75 times the global shutter's; and the readout
/// estimated from the final map within 20 % of the render's (28.0 ms of
/// 25).
#[test]
#[ignore = "needs a render: set SHOTPILOT_SLAM_RENDER_FIELD to a field render folder of >= 600 frames"]
fn a_full_field_render_meets_the_field_gates() {
    let dir = std::env::var_os("SHOTPILOT_SLAM_RENDER_FIELD")
        .expect("SHOTPILOT_SLAM_RENDER_FIELD names a render folder of >= 600 frames");
    let r = run_full_render(Path::new(&dir), None, true);
    r.assert_gates(0.98, 0.002);
    // The render's own readout (exposures.txt), estimated from the map
    // within 20 % (measured 28.0 ms of 25).
    let truth = r.readout_s;
    assert!(truth > 0.0, "a field render has a rolling shutter");
    let estimate = r.readout_estimate_s.unwrap();
    assert!(
        (estimate - truth).abs() <= 0.2 * truth,
        "readout estimated {estimate} s, the render's {truth} s"
    );
    let global = run_full_render(Path::new(&dir), Some(0.0), false);
    assert_eq!(global.frames, r.frames);
    assert!(
        r.ate_keyframes <= 0.75 * global.ate_keyframes,
        "keyframes: {} m with the rolling shutter modelled, {} m as a global shutter",
        r.ate_keyframes,
        global.ate_keyframes
    );
    assert!(
        r.ate <= 0.75 * global.ate,
        "frames: {} m with the rolling shutter modelled, {} m as a global shutter",
        r.ate,
        global.ate
    );
}

#[test]
fn after_black_frames_and_a_jump_back_tracking_recovers_with_the_right_pose() {
    let dir = render_explore(10.0, SMALL);
    let ds = Dataset::open(dir.path()).unwrap();
    let gt = ds.groundtruth.clone().unwrap();
    // The video: frames 0..=150 (10 s), 30 black frames, then frames 60..
    // again (the part of the flight 4 to 6.7 s in, mapped earlier).
    const LOST_AT: usize = 151;
    const BLACK: usize = 30;
    const JUMP_TO: usize = 60;
    let mut source: Vec<Option<usize>> = (0..LOST_AT).map(Some).collect();
    source.extend(std::iter::repeat_n(None, BLACK));
    source.extend((JUMP_TO..JUMP_TO + 40).map(Some));
    let mut s = Slam::new(
        ds.camera,
        slam::Params {
            sequential: true,
            ..Default::default()
        },
    )
    .unwrap();
    let black = Arc::new(image::GrayImage::new(ds.camera.width, ds.camera.height));
    let mut states = Vec::new();
    for (k, src) in source.iter().enumerate() {
        let image = match src {
            Some(i) => Arc::new(ds.frame(*i).unwrap().image),
            None => black.clone(),
        };
        let out = s.process(k as u64, k as f64 / FPS, image);
        states.push(out.state);
    }
    let run = s.finish();
    run.map.check_invariants().unwrap();
    assert!(run.initialized_at.is_some());
    // Black frames are not tracked.
    for (k, st) in states.iter().enumerate().skip(LOST_AT).take(BLACK) {
        assert_eq!(*st, TrackState::Lost, "black frame {k}");
    }
    // Recovery within 10 frames of the jump, and tracked from then on.
    let back = LOST_AT + BLACK;
    let first = (back..source.len())
        .find(|&k| states[k] == TrackState::Tracking)
        .expect("tracking recovers");
    assert!(
        first < back + 10,
        "recovered {} frames after the jump",
        first - back
    );
    for (k, st) in states.iter().enumerate().skip(first) {
        assert_eq!(*st, TrackState::Tracking, "frame {k} after recovery");
    }

    // Align the frames tracked before the loss to the ground truth by
    // Sim(3), then compare the recovered poses.
    let traj = run.trajectory();
    let pose_of = |k: usize| -> Option<Isometry3<f64>> {
        traj.poses
            .iter()
            .find(|p| (p.t - k as f64 / FPS).abs() < 1e-6)
            .map(|p| p.world_from_cam)
    };
    let gt_of = |k: usize| gt.poses[source[k].unwrap()].world_from_cam;
    let (mut est, mut truth) = (Vec::new(), Vec::new());
    for k in 0..LOST_AT {
        if let Some(p) = pose_of(k) {
            est.push(Point3::from(p.translation.vector));
            truth.push(Point3::from(gt_of(k).translation.vector));
        }
    }
    let sim = geometry::umeyama(&est, &truth, true).unwrap();
    // Against the ground truth, and against the pose the same source frame
    // had when it was first tracked (relocalisation's own error, free of
    // the map's drift at that place).
    let mut worst = (0.0f64, 0.0f64);
    let mut worst_rel = (0.0f64, 0.0f64);
    for (k, src) in source.iter().enumerate().skip(first).take(5) {
        let src = src.expect("recovered frames are real frames");
        let p = sim.transform_pose(&pose_of(k).expect("recovered frames have poses"));
        let g = gt_of(k);
        let dp = (p.translation.vector - g.translation.vector).norm();
        let da = p.rotation.angle_to(&g.rotation).to_degrees();
        let before = sim.transform_pose(&pose_of(src).expect("the source frame was tracked"));
        let rp = (p.translation.vector - before.translation.vector).norm();
        let ra = p.rotation.angle_to(&before.rotation).to_degrees();
        println!(
            "frame {k} (source {src}): vs ground truth {dp:.4} m {da:.3} deg; vs first pass {rp:.4} m {ra:.3} deg"
        );
        worst = (worst.0.max(dp), worst.1.max(da));
        worst_rel = (worst_rel.0.max(rp), worst_rel.1.max(ra));
    }
    println!(
        "recovered {} frames after the jump; worst of the first 5: {:.4} m, {:.3} deg vs ground truth, {:.4} m, {:.3} deg vs first pass",
        first - back,
        worst.0,
        worst.1,
        worst_rel.0,
        worst_rel.1
    );
    assert!(worst.0 < 0.02, "position error {} m", worst.0);
    assert!(worst.1 < 1.0, "rotation error {} deg", worst.1);
}
