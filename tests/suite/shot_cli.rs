//! `shotpilot shot` end to end: a map made by `shotpilot slam --save-map`
//! on TUM fr3/teddy (first 40 frames), then the desired shot from anchors
//! and from a photo, as JSON. Skips with a message when ../shared/data is absent.

use crate::data_support;

use std::path::PathBuf;
use std::process::Command;

use nalgebra::{Quaternion, UnitQuaternion, Vector3};
use serde_json::Value;

use shotpilot::slam::{KeyFrameId, mapfile};

fn data_dir() -> Option<PathBuf> {
    data_support::shared_data("tum_fr3_teddy_100")
}

fn shotpilot(args: &[&str]) -> anyhow::Result<(bool, String, String)> {
    let out = Command::new(env!("CARGO_BIN_EXE_shotpilot"))
        .args(args)
        .arg("--log")
        .arg("warn")
        .output()?;
    Ok((
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    ))
}

#[test]
fn shot_cli_anchors_photo_and_refusal() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
        return Ok(());
    };
    let tmp = tempfile::tempdir()?;
    let map_path = tmp.path().join("teddy.map");
    let map_s = map_path.to_string_lossy().into_owned();
    let dir_s = dir.to_string_lossy().into_owned();
    let (ok, _, err) = shotpilot(&[
        "slam",
        &dir_s,
        "--sequential",
        "--max-frames",
        "40",
        "--save-map",
        &map_s,
        "--json",
    ])?;
    assert!(ok, "slam failed: {err}");
    let map = mapfile::load(&map_path)?;
    let kf0 = map
        .keyframe(KeyFrameId(0))
        .ok_or_else(|| anyhow::anyhow!("no keyframe 0"))?;
    let depth = map.median_depth(KeyFrameId(0)).unwrap_or(f64::NAN);

    // Anchors on the corners themselves: the shot is keyframe 0.
    let out_dir = tmp.path().join("out");
    let out_s = out_dir.to_string_lossy().into_owned();
    let (ok, stdout, err) = shotpilot(&[
        "shot",
        "--map",
        &map_s,
        "--keyframe",
        "0",
        "--anchors",
        "0,0,639,0,639,479,0,479",
        "--out",
        &out_s,
        "--json",
    ])?;
    assert!(ok, "shot failed: {err}");
    let v: Value = serde_json::from_str(stdout.trim())?;
    for key in [
        "localized",
        "reason",
        "position",
        "quaternion",
        "inliers",
        "reprojection_rmse_px",
        "keyframe_id",
    ] {
        assert!(v.get(key).is_some(), "missing key {key} in {v}");
    }
    assert_eq!(v["localized"], Value::Bool(true), "{v}");
    assert!(out_dir.join("desired_shot.png").is_file());
    let num = |x: &Value| x.as_f64().unwrap_or(f64::NAN);
    let p = Vector3::new(
        num(&v["position"][0]),
        num(&v["position"][1]),
        num(&v["position"][2]),
    );
    let q = UnitQuaternion::from_quaternion(Quaternion::new(
        num(&v["quaternion"][3]),
        num(&v["quaternion"][0]),
        num(&v["quaternion"][1]),
        num(&v["quaternion"][2]),
    ));
    let want = kf0.world_from_cam();
    let pos_err = (p - want.translation.vector).norm() / depth;
    let rot_err = q.angle_to(&want.rotation).to_degrees();
    println!(
        "identity anchors: position error {:.4} of median depth, rotation error {rot_err:.4} deg",
        pos_err
    );
    assert!(
        pos_err < 0.02 && rot_err < 0.5,
        "pos {pos_err}, rot {rot_err}"
    );
    // The keyframe's own view is within the flown views: every inlier is
    // seen from (nearly) where the keyframe saw it.
    let beyond = num(&v["beyond_views_deg"]);
    assert!(beyond < 0.5, "beyond the flown views: {beyond} deg");

    // Mirrored anchors are refused with their own message.
    let (ok, _, err) = shotpilot(&[
        "shot",
        "--map",
        &map_s,
        "--keyframe",
        "0",
        "--anchors",
        "639,0,0,0,0,479,639,479",
        "--json",
    ])?;
    assert!(!ok);
    assert!(err.contains("mirrored"), "{err}");

    // A later frame of the sequence as a photo.
    let rgb = std::fs::read_to_string(dir.join("rgb.txt"))?;
    let Some(line) = rgb.lines().filter(|l| !l.starts_with('#')).nth(45) else {
        anyhow::bail!("rgb.txt too short");
    };
    let Some(rel) = line.split_whitespace().nth(1) else {
        anyhow::bail!("bad rgb.txt line");
    };
    let photo = dir.join(rel).to_string_lossy().into_owned();
    let (ok, stdout, err) = shotpilot(&["shot", "--map", &map_s, "--photo", &photo, "--json"])?;
    assert!(ok, "shot --photo failed: {err}");
    let v: Value = serde_json::from_str(stdout.trim())?;
    println!("photo frame 45: {v}");
    assert!(v["localized"].is_boolean());
    if v["localized"] == Value::Bool(false) {
        assert!(v["reason"].is_string() && v["position"].is_null());
    }

    // The same photo from "another camera": resized to 480x360, once with
    // the camera assumed for that size, once with its intrinsics given
    // (the map camera's, scaled by 3/4): both localise where the full-size
    // photo does (within 3 % of the scene depth).
    let small = image::imageops::resize(
        &image::open(&photo)?.to_luma8(),
        480,
        360,
        image::imageops::FilterType::Triangle,
    );
    let small_path = tmp.path().join("small.png");
    small.save(&small_path)?;
    let small_s = small_path.to_string_lossy().into_owned();
    let c = map.camera;
    let given = format!(
        "{},{},{},{}",
        c.fx * 0.75,
        c.fy * 0.75,
        0.75 * (c.cx + 0.5) - 0.5,
        0.75 * (c.cy + 0.5) - 0.5
    );
    let position = |v: &Value| -> Option<nalgebra::Vector3<f64>> {
        let p = v["position"].as_array()?;
        Some(nalgebra::Vector3::new(
            p.first()?.as_f64()?,
            p.get(1)?.as_f64()?,
            p.get(2)?.as_f64()?,
        ))
    };
    for extra in [vec![], vec!["--photo-intrinsics", given.as_str()]] {
        let mut a = vec!["shot", "--map", &map_s, "--photo", &small_s, "--json"];
        a.extend(extra.iter().copied());
        let (ok, stdout, err) = shotpilot(&a)?;
        assert!(ok, "shot --photo (480x360) failed: {err}");
        let vs: Value = serde_json::from_str(stdout.trim())?;
        println!("photo frame 45 at 480x360 {extra:?}: {vs}");
        assert_eq!(vs["localized"], Value::Bool(true), "{vs}");
        if let (Some(full), Some(p), Some(depth)) =
            (position(&v), position(&vs), vs["median_depth"].as_f64())
        {
            let d = (full - p).norm() / depth;
            assert!(
                d < 0.03,
                "480x360 photo {d:.4} x depth from the full-size one"
            );
        }
    }
    // Another aspect ratio without intrinsics is refused with a hint.
    let odd_path = tmp.path().join("odd.png");
    image::imageops::resize(&small, 500, 300, image::imageops::FilterType::Triangle)
        .save(&odd_path)?;
    let odd_s = odd_path.to_string_lossy().into_owned();
    let (ok, _, err) = shotpilot(&["shot", "--map", &map_s, "--photo", &odd_s, "--json"])?;
    assert!(!ok);
    assert!(err.contains("--photo-intrinsics"), "{err}");
    Ok(())
}
