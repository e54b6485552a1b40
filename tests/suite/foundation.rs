//! Foundation checks on real data and with known answers: the datasets in
//! `../shared/data` read completely, bad inputs name file and line, the
//! camera round trip holds on both calibrations, and `eval` recovers a known
//! Sim(3).
//!
//! Tests that need `../shared/data` skip (with a message) when it is absent,
//! so a clone without it still runs; `.ci/run` runs them with the data.

use crate::data_support;

use std::path::PathBuf;

use nalgebra::{Isometry3, Point2, Translation3, UnitQuaternion, Vector3};
use shotpilot::eval::{self, AlignMode, StampedPose, Trajectory};
use shotpilot::video::dataset::{Dataset, DatasetError, Layout};

fn shared_data() -> Option<PathBuf> {
    data_support::shared_data("")
}

#[test]
fn both_shared_datasets_read_completely() {
    let Some(data) = shared_data() else { return };
    let tum = Dataset::open(&data.join("tum_fr3_teddy_100")).unwrap();
    assert_eq!(tum.layout, Layout::Tum);
    assert_eq!(tum.len(), 100);
    assert_eq!((tum.camera.width, tum.camera.height), (640, 480));
    assert_eq!(tum.camera.fx, 535.4);
    let gt = tum.groundtruth.as_ref().unwrap();
    assert!(gt.len() > 300);
    let mut n = 0;
    for f in tum.frames() {
        let f = f.unwrap();
        assert_eq!(f.image.dimensions(), (640, 480));
        n += 1;
    }
    assert_eq!(n, 100);

    let euroc = Dataset::open(&data.join("euroc_v101_static95")).unwrap();
    assert_eq!(euroc.len(), 95);
    assert_eq!((euroc.camera.width, euroc.camera.height), (752, 480));
    assert!((euroc.camera.distortion.k1 + 0.28340811).abs() < 1e-12);
    assert_eq!(euroc.frames().filter(|f| f.is_ok()).count(), 95);
    // Timestamps are strictly increasing at about 20 Hz.
    for i in 1..euroc.len() {
        let dt = euroc.timestamp(i).unwrap() - euroc.timestamp(i - 1).unwrap();
        assert!((dt - 0.05).abs() < 0.005, "frame {i}: dt {dt}");
    }
}

#[test]
fn euroc_asl_layout_built_from_the_shared_files_reads() {
    // Build the original ASL layout (mav0/cam0/data.csv + sensor.yaml) from
    // the shared EuRoC frames and its original sensor.yaml.
    let Some(data) = shared_data() else { return };
    let src = data.join("euroc_v101_static95");
    let tmp = tempfile::tempdir().unwrap();
    let cam0 = tmp.path().join("mav0/cam0");
    std::fs::create_dir_all(cam0.join("data")).unwrap();
    std::fs::copy(
        src.join("euroc_yaml/cam0_sensor.yaml"),
        cam0.join("sensor.yaml"),
    )
    .unwrap();
    let tum = Dataset::open(&src).unwrap();
    let mut csv = String::from("#timestamp [ns],filename\n");
    for i in 0..5 {
        let p = tum.image_path(i).unwrap();
        let name = p.file_name().unwrap().to_str().unwrap();
        std::fs::copy(p, cam0.join("data").join(name)).unwrap();
        csv.push_str(&format!("{},{}\n", name.trim_end_matches(".png"), name));
    }
    std::fs::write(cam0.join("data.csv"), csv).unwrap();
    let ds = Dataset::open(tmp.path()).unwrap();
    assert_eq!(ds.layout, Layout::Euroc);
    assert_eq!(ds.len(), 5);
    assert_eq!(ds.camera, tum.camera);
    for i in 0..5 {
        assert!((ds.timestamp(i).unwrap() - tum.timestamp(i).unwrap()).abs() < 1e-6);
        assert_eq!(ds.frame(i).unwrap().image, tum.frame(i).unwrap().image);
    }
}

#[test]
fn bad_dataset_inputs_name_file_and_line() {
    let tmp = tempfile::tempdir().unwrap();
    // A path that does not exist.
    let e = Dataset::open(&tmp.path().join("nowhere")).unwrap_err();
    assert!(e.to_string().contains("nowhere"), "{e}");
    // A folder that is no dataset.
    let e = Dataset::open(tmp.path()).unwrap_err();
    assert!(matches!(e, DatasetError::UnknownLayout { .. }), "{e}");

    let dir = tmp.path().join("ds");
    std::fs::create_dir_all(dir.join("rgb")).unwrap();
    image::GrayImage::new(16, 12)
        .save(dir.join("rgb/1.png"))
        .unwrap();
    std::fs::write(dir.join("rgb.txt"), "# t file\n1.0 rgb/1.png\n").unwrap();
    // Missing calib.txt.
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("calib.txt"), "{e}");
    // Malformed calib line.
    std::fs::write(dir.join("calib.txt"), "# c\n100 100 8 6 0.1 zero 0 0 0\n").unwrap();
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("calib.txt:2") && e.contains("zero"), "{e}");
    // Malformed rgb.txt line.
    std::fs::write(dir.join("calib.txt"), "100 100 8 6 0 0 0 0 0\n").unwrap();
    std::fs::write(dir.join("rgb.txt"), "1.0 rgb/1.png\n2.0\n").unwrap();
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("rgb.txt:2"), "{e}");
    // Malformed ground truth line.
    std::fs::write(dir.join("rgb.txt"), "1.0 rgb/1.png\n").unwrap();
    std::fs::write(
        dir.join("groundtruth.txt"),
        "1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 1\n",
    )
    .unwrap();
    let e = Dataset::open(&dir).unwrap_err().to_string();
    assert!(e.contains("groundtruth.txt:2"), "{e}");
    // A listed image that is missing.
    std::fs::remove_file(dir.join("groundtruth.txt")).unwrap();
    std::fs::write(dir.join("rgb.txt"), "1.0 rgb/1.png\n2.0 rgb/2.png\n").unwrap();
    let ds = Dataset::open(&dir).unwrap();
    let e = ds.frame(1).unwrap_err().to_string();
    assert!(e.contains("2.png"), "{e}");
}

#[test]
fn distortion_round_trip_on_both_shared_calibrations() {
    let Some(data) = shared_data() else { return };
    for name in ["tum_fr3_teddy_100", "euroc_v101_static95"] {
        let cam = Dataset::open(&data.join(name)).unwrap().camera;
        let mut worst: f64 = 0.0;
        for v in (0..cam.height).step_by(4) {
            for u in (0..cam.width).step_by(4) {
                let px = Point2::new(u as f64, v as f64);
                let back = cam.project(&cam.unproject(px).into_inner()).unwrap();
                worst = worst.max((back - px).norm());
                let ideal = cam.undistort_pixel(px);
                worst = worst.max((cam.distort_pixel(ideal) - px).norm());
            }
        }
        assert!(worst < 1e-6, "{name}: worst round trip {worst} px");
    }
}

/// A deterministic pseudo-random sequence in [-1, 1] (no RNG dependency).
fn noise(i: usize, k: usize) -> f64 {
    let x = ((i * 7919 + k * 104729) as f64 * 0.618_033_988_75).fract();
    2.0 * x - 1.0
}

fn synthetic_gt() -> Trajectory {
    Trajectory {
        poses: (0..300)
            .map(|i| {
                let t = i as f64 * 0.01;
                let a = t * 1.3;
                StampedPose {
                    t: 100.0 + t,
                    world_from_cam: Isometry3::from_parts(
                        Translation3::new(1.5 * a.cos(), 0.8 * a.sin(), 0.3 * (2.0 * a).sin()),
                        UnitQuaternion::from_euler_angles(0.1 * a, -0.2 * a, a),
                    ),
                }
            })
            .collect(),
    }
}

#[test]
fn eval_recovers_a_known_sim3_with_known_noise() {
    let gt = synthetic_gt();
    // est = S^-1 (gt + noise): aligning est back must recover S.
    let rot = UnitQuaternion::from_euler_angles(0.4, -0.3, 1.2);
    let (scale, trans) = (0.37, Vector3::new(2.0, -1.0, 0.25));
    let sigma = 0.002;
    let mut est = gt.clone();
    let mut noise_sq = 0.0;
    for (i, p) in est.poses.iter_mut().enumerate() {
        let n = Vector3::new(noise(i, 0), noise(i, 1), noise(i, 2)) * sigma;
        noise_sq += n.norm_squared();
        let world = p.world_from_cam.translation.vector + n;
        let moved = rot.inverse() * (world - trans) / scale;
        p.world_from_cam = Isometry3::from_parts(
            Translation3::from(moved),
            rot.inverse() * p.world_from_cam.rotation,
        );
    }
    let ev = eval::evaluate(&gt, &est, &eval::Params::default()).unwrap();
    assert_eq!(ev.matched, 300);
    assert!(
        (ev.alignment.scale - scale).abs() / scale < 1e-3,
        "scale {}",
        ev.alignment.scale
    );
    assert!(ev.alignment.rotation.angle_to(&rot) < 1e-3);
    // The residual can only be smaller than the injected noise (the fit
    // absorbs its mean and a little more), and not much smaller.
    let noise_rms = (noise_sq / 300.0).sqrt();
    assert!(
        ev.ate.rmse <= noise_rms + 1e-12,
        "{} vs {}",
        ev.ate.rmse,
        noise_rms
    );
    assert!(
        ev.ate.rmse > 0.9 * noise_rms,
        "{} vs {}",
        ev.ate.rmse,
        noise_rms
    );

    // Noise-free: the scale to 1e-6 and the error to zero.
    let mut exact = gt.clone();
    for p in &mut exact.poses {
        let moved = rot.inverse() * (p.world_from_cam.translation.vector - trans) / scale;
        p.world_from_cam = Isometry3::from_parts(
            Translation3::from(moved),
            rot.inverse() * p.world_from_cam.rotation,
        );
    }
    let ev = eval::evaluate(&gt, &exact, &eval::Params::default()).unwrap();
    assert!((ev.alignment.scale - scale).abs() < 1e-6);
    assert!(ev.ate.rmse < 1e-9 && ev.rpe_trans.rmse < 1e-9 && ev.rpe_rot_deg.rmse < 1e-6);
    // SE(3) cannot fix the scale: the error is then large.
    let se3 = eval::evaluate(
        &gt,
        &exact,
        &eval::Params {
            align: AlignMode::Se3,
            ..Default::default()
        },
    )
    .unwrap();
    assert!(se3.ate.rmse > 0.1);
}

#[test]
fn eval_associates_offset_and_subsampled_copies() {
    let gt = synthetic_gt();
    // Offset by 5 ms: every pose pairs with its twin (spacing 10 ms).
    let mut off = gt.clone();
    for p in &mut off.poses {
        p.t += 0.005;
    }
    let ev = eval::evaluate(&gt, &off, &eval::Params::default()).unwrap();
    assert_eq!(ev.matched, 300);
    assert!(ev.ate.rmse < 1e-9);
    // With a tolerance below the offset nothing matches.
    let e = eval::evaluate(
        &gt,
        &off,
        &eval::Params {
            max_dt: 0.004,
            ..Default::default()
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("only 0 poses matched"), "{e}");
    // Subsampled every 3rd pose.
    let sub = Trajectory {
        poses: gt.poses.iter().step_by(3).copied().collect(),
    };
    let ev = eval::evaluate(&gt, &sub, &eval::Params::default()).unwrap();
    assert_eq!(ev.matched, 100);
    assert!(ev.ate.rmse < 1e-9);
}
