//! The must-show experiment of the desired shot on real data: anchors that a
//! pure camera rotation `R` would give, `anchor_i = distort(K·R·K⁻¹·undistort(corner_i))`,
//! placed on keyframes of a map of TUM fr3/teddy (100 frames). The shot they
//! describe is taken from the keyframe's position with orientation
//! `R_kf·R`; the localisation must find it within 0.5 degree and 2 % of the
//! keyframe's median scene depth, for 20 random rotations up to 15 degrees.
//!
//! Needs ../shared/data/tum_fr3_teddy_100 (skips with a message otherwise).
//! Run with `--nocapture` to see the table of errors.

use std::path::Path;
use std::sync::Arc;

use nalgebra::{Isometry3, Point2, Translation3, Unit, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use shotpilot::shot::{self, Localization, frame_corners};
use shotpilot::slam::{self, Map, Slam, mapfile};
use shotpilot::video::dataset::Dataset;

/// The dataset, relative to the repository (a worktree sits one level deeper).
fn data_dir() -> Option<std::path::PathBuf> {
    ["../shared/data", "../../shared/data"]
        .iter()
        .map(|rel| {
            Path::new(env!("CARGO_MANIFEST_DIR"))
                .join(rel)
                .join("tum_fr3_teddy_100")
        })
        .find(|d| d.join("rgb.txt").is_file())
}

fn build_map(dir: &Path) -> anyhow::Result<Map> {
    let ds = Dataset::open(dir)?;
    let params = slam::Params {
        sequential: true,
        ..slam::Params::default()
    };
    let mut system = Slam::new(ds.camera, params)?;
    for i in 0..ds.len() {
        let f = ds.frame(i)?;
        system.process(f.index as u64, f.timestamp, Arc::new(f.image));
    }
    let run = system.finish();
    // Through the map file, as the CLI reads it (JPEG keyframe images).
    let tmp = tempfile::tempdir()?;
    let path = tmp.path().join("teddy.map");
    mapfile::save(&run.map, &path)?;
    Ok(mapfile::load(&path)?)
}

/// A rotation with a uniformly random axis and an angle uniform in [0, max].
fn random_rotation(rng: &mut StdRng, max_deg: f64) -> UnitQuaternion<f64> {
    loop {
        let v = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n = v.norm();
        if n > 0.1 && n <= 1.0 {
            let angle = rng.random_range(0.0..max_deg).to_radians();
            return UnitQuaternion::from_axis_angle(&Unit::new_normalize(v), angle);
        }
    }
}

#[test]
fn pure_rotation_anchors_localise_to_the_rotated_keyframe() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
        eprintln!("skipped: ../shared/data/tum_fr3_teddy_100 not present");
        return Ok(());
    };
    let map = build_map(&dir)?;
    let cam = map.camera;
    let mut kfs: Vec<_> = map
        .keyframes()
        .filter(|k| k.image.is_some())
        .map(|k| k.id)
        .collect();
    kfs.sort();
    assert!(kfs.len() >= 10, "only {} keyframes", kfs.len());
    let params = shot::Params::default();
    let mut rng = StdRng::seed_from_u64(20261121);
    println!("trial  kf  R_deg  localized  inliers  ratio  rmse_px  rot_err_deg  pos_err_%depth");
    let mut worst_rot: f64 = 0.0;
    let mut worst_pos: f64 = 0.0;
    let mut failures = Vec::new();
    for trial in 0..20 {
        let kf_id = kfs[(trial * kfs.len()) / 20];
        let Some(kf) = map.keyframe(kf_id) else {
            anyhow::bail!("keyframe vanished");
        };
        let Some(img) = kf.image.as_ref() else {
            anyhow::bail!("no image");
        };
        let r = random_rotation(&mut rng, 15.0);
        // kf_from_shot = R: the shot's ray d is R·d in the keyframe.
        let corners = frame_corners(cam.width, cam.height);
        let mut anchors = [Point2::origin(); 4];
        for (a, c) in anchors.iter_mut().zip(&corners) {
            let ray = cam.unproject(*c).into_inner();
            let Some(px) = cam.project(&(r * ray)) else {
                anyhow::bail!("anchor behind the camera");
            };
            *a = px;
        }
        let desired = shot::desired_shot_from_anchors(img, &anchors, &params.anchors)?;
        let out = shot::localize(&map, &desired.image, Some(&desired.mask), &params.localize)?;
        let world_from_kf = kf.world_from_cam();
        let expected = world_from_kf * Isometry3::from_parts(Translation3::identity(), r);
        let depth = map.median_depth(kf_id).unwrap_or(f64::NAN);
        match out {
            Localization::Localized(p) => {
                let rot_err = p
                    .world_from_cam
                    .rotation
                    .angle_to(&expected.rotation)
                    .to_degrees();
                let pos_err = (p.world_from_cam.translation.vector - expected.translation.vector)
                    .norm()
                    / depth
                    * 100.0;
                println!(
                    "{trial:5} {:3} {:6.2}  yes       {:6}  {:5.2}  {:7.3}  {:11.4}  {:14.3}",
                    kf_id.0,
                    r.angle().to_degrees(),
                    p.inliers,
                    p.inlier_ratio,
                    p.reprojection_rmse_px,
                    rot_err,
                    pos_err
                );
                worst_rot = worst_rot.max(rot_err);
                worst_pos = worst_pos.max(pos_err);
                if rot_err > 0.5 || pos_err > 2.0 {
                    failures.push(format!(
                        "trial {trial}: rot {rot_err:.3} deg, pos {pos_err:.3} %"
                    ));
                }
            }
            Localization::NotLocalized { reason } => {
                println!(
                    "{trial:5} {:3} {:6.2}  no: {reason}",
                    kf_id.0,
                    r.angle().to_degrees()
                );
                failures.push(format!("trial {trial}: not localised: {reason}"));
            }
        }
    }
    println!(
        "worst rotation error {worst_rot:.4} deg, worst position error {worst_pos:.3} % of median depth"
    );
    assert!(failures.is_empty(), "{failures:#?}");
    Ok(())
}
