//! `shotpilot eval` against evo (`evo_ape tum GT EST -as`), the tool the
//! literature uses, on three pairs built from the TUM teddy ground truth: a
//! copy moved by a known Sim(3) plus known noise, a copy with timestamps
//! offset by 5 ms, and a subsampled copy. Needs evo on PATH (`.ci/run`
//! installs it from PyPI into a venv) and `../shared/data`.

use std::path::Path;
use std::process::Command;

use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use shotpilot::eval::{self, Trajectory};

fn evo_ape(gt: &Path, est: &Path, max_dt: f64) -> (f64, f64) {
    let out = Command::new("evo_ape")
        .args([
            "tum",
            gt.to_str().unwrap(),
            est.to_str().unwrap(),
            "-as",
            "--t_max_diff",
        ])
        .arg(max_dt.to_string())
        .output()
        .expect("evo_ape runs (pip install evo)");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "evo_ape failed: {text}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let field = |name: &str| -> f64 {
        text.lines()
            .find_map(|l| {
                let mut it = l.split_whitespace();
                (it.next() == Some(name))
                    .then(|| it.next().and_then(|v| v.parse().ok()))
                    .flatten()
            })
            .unwrap_or_else(|| panic!("no `{name}` in evo output: {text}"))
    };
    (field("rmse"), field("max"))
}

#[test]
#[ignore = "needs evo (pip install evo) and ../shared/data"]
fn eval_agrees_with_evo_on_three_pairs() {
    let gt_path = crate::repo_root().join("../shared/data/tum_fr3_teddy_100/groundtruth.txt");
    let gt = Trajectory::read_tum(&gt_path).unwrap();
    let dir = tempfile::tempdir().unwrap();

    let rot = UnitQuaternion::from_euler_angles(0.2, 0.5, -1.0);
    let (scale, trans) = (0.45, Vector3::new(-0.3, 1.2, 0.7));
    let moved_with_noise = |sigma: f64| {
        let mut moved = gt.clone();
        for (i, p) in moved.poses.iter_mut().enumerate() {
            let f = i as f64;
            let n = Vector3::new((f * 1.7).sin(), (f * 2.3).cos(), (f * 0.9).sin()) * sigma;
            let c = rot.inverse() * (p.world_from_cam.translation.vector + n - trans) / scale;
            p.world_from_cam = Isometry3::from_parts(
                Translation3::from(c),
                rot.inverse() * p.world_from_cam.rotation,
            );
        }
        moved
    };
    let moved = moved_with_noise(0.003);
    let moved_fine = moved_with_noise(1e-6);
    let mut offset = gt.clone();
    for p in &mut offset.poses {
        p.t += 0.005;
    }
    let sub = Trajectory {
        poses: gt.poses.iter().step_by(4).copied().collect(),
    };

    let max_dt = 0.02;
    for (name, est) in [
        ("sim3+3mm noise", &moved),
        ("sim3+1um noise", &moved_fine),
        ("offset 5 ms", &offset),
        ("subsampled 1/4", &sub),
    ] {
        let est_path = dir.path().join("est.txt");
        est.write_tum(&est_path).unwrap();
        let est_read = Trajectory::read_tum(&est_path).unwrap();
        let ours = eval::evaluate(
            &gt,
            &est_read,
            &eval::Params {
                max_dt,
                ..Default::default()
            },
        )
        .unwrap();
        let (evo_rmse, evo_max) = evo_ape(&gt_path, &est_path, max_dt);
        println!(
            "{name:>15}: shotpilot rmse {:.7} max {:.7} scale {:.7} matched {} | evo rmse {:.7} max {:.7}",
            ours.ate.rmse, ours.ate.max, ours.alignment.scale, ours.matched, evo_rmse, evo_max
        );
        assert!(
            (ours.ate.rmse - evo_rmse).abs() < 1e-4,
            "{name}: {} vs evo {}",
            ours.ate.rmse,
            evo_rmse
        );
        assert!(
            (ours.ate.max - evo_max).abs() < 1e-4,
            "{name}: max {} vs evo {}",
            ours.ate.max,
            evo_max
        );
        if name.starts_with("sim3") {
            // 3 mm noise: scale within 1e-3; 1 um noise: within 1e-6.
            let tol = if name.contains("3mm") { 1e-3 } else { 1e-6 };
            assert!(
                (ours.alignment.scale - scale).abs() < tol * scale,
                "{name}: scale {}",
                ours.alignment.scale
            );
        }
    }
}
