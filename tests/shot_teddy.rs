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
use std::sync::{Arc, OnceLock};

use nalgebra::{Isometry3, Point2, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use shotpilot::bow::Vocabulary;
use shotpilot::eval::{StampedPose, Trajectory, associate};
use shotpilot::geometry::{Sim3, umeyama};
use shotpilot::shot::{self, BowIndex, Localization, frame_corners};
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

fn build_map(dir: &Path, max_frames: usize) -> anyhow::Result<Map> {
    let ds = Dataset::open(dir)?;
    let params = slam::Params {
        sequential: true,
        ..slam::Params::default()
    };
    let mut system = Slam::new(ds.camera, params)?;
    for i in 0..ds.len().min(max_frames) {
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

/// The map of all 100 frames, built once for the tests of this file.
fn full_map(dir: &Path) -> anyhow::Result<&'static Map> {
    static MAP: OnceLock<Result<Map, String>> = OnceLock::new();
    MAP.get_or_init(|| build_map(dir, usize::MAX).map_err(|e| format!("{e:#}")))
        .as_ref()
        .map_err(|e| anyhow::anyhow!("{e}"))
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
    let map = full_map(&dir)?;
    let cam = map.camera;
    let mut kfs: Vec<_> = map
        .keyframes()
        .filter(|k| k.image.is_some())
        .map(|k| k.id)
        .collect();
    kfs.sort();
    assert!(kfs.len() >= 10, "only {} keyframes", kfs.len());
    let params = shot::Params::default();
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(map, &vocabulary);
    let mut failures = Vec::new();
    for (mode, bow_index) in [("descriptor ranking", None), ("bow query", Some(&index))] {
        let mut rng = StdRng::seed_from_u64(20261121);
        println!(
            "[{mode}] trial  kf  R_deg  localized  inliers  ratio  rmse_px  rot_err_deg  pos_err_%depth"
        );
        let mut worst_rot: f64 = 0.0;
        let mut worst_pos: f64 = 0.0;
        let mut ms = Vec::new();
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
            let t0 = std::time::Instant::now();
            let out = shot::localize(
                map,
                &desired.image,
                Some(&desired.mask),
                bow_index,
                &params.localize,
            )?;
            ms.push(t0.elapsed().as_secs_f64() * 1e3);
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
                    let pos_err =
                        (p.world_from_cam.translation.vector - expected.translation.vector).norm()
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
                            "[{mode}] trial {trial}: rot {rot_err:.3} deg, pos {pos_err:.3} %"
                        ));
                    }
                }
                Localization::NotLocalized { reason } => {
                    println!(
                        "{trial:5} {:3} {:6.2}  no: {reason}",
                        kf_id.0,
                        r.angle().to_degrees()
                    );
                    failures.push(format!("[{mode}] trial {trial}: not localised: {reason}"));
                }
            }
        }
        println!(
            "[{mode}] worst rotation error {worst_rot:.4} deg, worst position error {worst_pos:.3} % of median depth"
        );
        ms.sort_by(f64::total_cmp);
        println!(
            "[{mode}] localisation time median {:.1} ms, max {:.1} ms (not asserted)",
            ms[ms.len() / 2],
            ms[ms.len() - 1]
        );
    }
    assert!(failures.is_empty(), "{failures:#?}");
    Ok(())
}

/// Shots of places the map never saw (EuRoC's machine hall, cropped to the
/// map camera's size, and seeded noise) must come back "not localised".
#[test]
fn shots_outside_the_map_are_not_localised() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
        eprintln!("skipped: ../shared/data/tum_fr3_teddy_100 not present");
        return Ok(());
    };
    let Some(euroc_dir) = dir.parent().map(|p| p.join("euroc_v101_static95")) else {
        anyhow::bail!("no parent");
    };
    let map = full_map(&dir)?;
    let cam = map.camera;
    let params = shot::LocalizeParams::default();
    let mut shots = Vec::new();
    if euroc_dir.join("rgb.txt").is_file() {
        let euroc = Dataset::open(&euroc_dir)?;
        for i in [0, 30, 60, 90] {
            let f = euroc.frame(i.min(euroc.len() - 1))?;
            let (w, h) = f.image.dimensions();
            assert!(w >= cam.width && h >= cam.height);
            let x0 = (w - cam.width) / 2;
            let y0 = (h - cam.height) / 2;
            let crop =
                image::imageops::crop_imm(&f.image, x0, y0, cam.width, cam.height).to_image();
            shots.push((format!("euroc frame {i}"), crop));
        }
    } else {
        eprintln!("euroc_v101_static95 not present: noise only");
    }
    let mut rng = StdRng::seed_from_u64(7);
    let noise = image::GrayImage::from_fn(cam.width, cam.height, |_, _| {
        image::Luma([rng.random::<u8>()])
    });
    shots.push(("noise".to_string(), noise));
    let mut wrong = Vec::new();
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(map, &vocabulary);
    for (mode, bow_index) in [("descriptor ranking", None), ("bow query", Some(&index))] {
        for (name, img) in &shots {
            match shot::localize(map, img, None, bow_index, &params)? {
                Localization::Localized(p) => {
                    println!(
                        "[{mode}] {name}: LOCALISED with {} inliers (wrong)",
                        p.inliers
                    );
                    wrong.push(format!("[{mode}] {name}"));
                }
                Localization::NotLocalized { reason } => {
                    println!("[{mode}] {name}: not localised: {reason}")
                }
            }
        }
    }
    assert!(
        wrong.is_empty(),
        "localised shots of unmapped places: {wrong:?}"
    );
    Ok(())
}

/// A keyframe's pose, estimated (map frame) and true.
type PosePair = (Isometry3<f64>, Isometry3<f64>);

/// A Sim(3) map -> ground truth from the keyframes' poses, through
/// `geometry::umeyama`: each keyframe gives its centre and three points one
/// median scene depth along its camera axes, so the orientations constrain
/// the rotation too. (The centres alone come from a short, nearly straight
/// arc here, about which the rotation is poorly determined: aligned that way
/// the map's own keyframes are 3 degrees off the ground truth.)
fn align_keyframes(map: &Map, gt: &Trajectory) -> anyhow::Result<(Sim3, Vec<PosePair>)> {
    let mut kf_traj = Trajectory {
        poses: map
            .keyframes()
            .map(|k| StampedPose {
                t: k.timestamp,
                world_from_cam: k.world_from_cam(),
            })
            .collect(),
    };
    kf_traj.poses.sort_by(|a, b| a.t.total_cmp(&b.t));
    let pairs: Vec<PosePair> = associate(&kf_traj, gt, 0.02)
        .into_iter()
        .map(|(a, b)| (kf_traj.poses[a].world_from_cam, gt.poses[b].world_from_cam))
        .collect();
    let centres = |i: usize| -> Vec<Point3<f64>> {
        pairs
            .iter()
            .map(|p| Point3::from(if i == 0 { p.0 } else { p.1 }.translation.vector))
            .collect()
    };
    let coarse = umeyama(&centres(0), &centres(1), true)?;
    let mut depths: Vec<f64> = map
        .keyframes()
        .filter_map(|k| map.median_depth(k.id))
        .collect();
    depths.sort_by(f64::total_cmp);
    let d = depths.get(depths.len() / 2).copied().unwrap_or(1.0);
    let (mut src, mut dst) = (Vec::new(), Vec::new());
    for (est, truth) in &pairs {
        src.push(Point3::from(est.translation.vector));
        dst.push(Point3::from(truth.translation.vector));
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            src.push(est * Point3::from(axis * d));
            dst.push(truth * Point3::from(axis * (d * coarse.scale)));
        }
    }
    Ok((umeyama(&src, &dst, true)?, pairs))
}

/// Frames held out of the map (the map is built from the first 70 frames;
/// the queries are the later frames of the same scene, every second one) as
/// photos, against the ground truth after a Sim(3) alignment of the map's
/// keyframes ([`align_keyframes`]); once at full size with the map camera,
/// once resized to 480x360 with the camera assumed for that size
/// ([`shot::assumed_camera`]: another camera's photo).
///
/// The map's own keyframes differ from the ground truth by about 0.6 degree
/// after the best alignment (the floor of any absolute figure here: the
/// SLAM's own tracking of these frames, when they are part of the run, is no
/// closer). Asserted: nothing localised with an error over 2 degrees or 5 %
/// of the distance; at least 2/3 of the frames localised; each localised
/// frame's orientation within 0.25 degree beyond the map's worst keyframe.
/// (The 0.5 degree / 2 % is met by only a third of the frames here:
/// with the map itself up to 1-1.7 degrees off the ground truth, position
/// errors of 2-2.7 % follow; see the note of session 2.)
#[test]
fn held_out_frames_localise_against_ground_truth() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
        eprintln!("skipped: ../shared/data/tum_fr3_teddy_100 not present");
        return Ok(());
    };
    let ds = Dataset::open(&dir)?;
    let Some(gt) = ds.groundtruth.clone() else {
        anyhow::bail!("teddy has ground truth");
    };
    let map = build_map(&dir, 70)?;
    let (sim, kf_pairs) = align_keyframes(&map, &gt)?;
    let mut kf_rot: Vec<f64> = kf_pairs
        .iter()
        .map(|(est, truth)| {
            sim.transform_pose(est)
                .rotation
                .angle_to(&truth.rotation)
                .to_degrees()
        })
        .collect();
    kf_rot.sort_by(f64::total_cmp);
    let kf_rot_max = kf_rot[kf_rot.len() - 1];
    println!(
        "map: {} keyframes, {} points; keyframes vs ground truth after Sim(3) (scale {:.4}): rotation error median {:.3} deg, max {kf_rot_max:.3} deg",
        map.keyframe_count(),
        map.point_count(),
        sim.scale,
        kf_rot[kf_rot.len() / 2],
    );
    let params = shot::LocalizeParams::default();
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&map, &vocabulary);
    let small = shot::assumed_camera(&map.camera, 480, 360)?;
    let mut failures = Vec::new();
    for (mode, bow_index, photo_camera) in [
        ("descriptor ranking, 640x480", None, map.camera),
        ("bow query, 640x480", Some(&index), map.camera),
        ("bow query, 480x360 assumed camera", Some(&index), small),
    ] {
        println!(
            "[{mode}] frame  localized  inliers  rmse_px  rot_err_deg  pos_err_cm  pos_err_%dist  kf"
        );
        let (mut n_ok, mut n_loc, mut n_total) = (0, 0, 0);
        let mut rot_errs = Vec::new();
        for i in (70..ds.len()).step_by(2) {
            let f = ds.frame(i)?;
            let Some(g) = gt
                .poses
                .iter()
                .filter(|p| (p.t - f.timestamp).abs() < 0.02)
                .min_by(|a, b| {
                    (a.t - f.timestamp)
                        .abs()
                        .total_cmp(&(b.t - f.timestamp).abs())
                })
            else {
                continue;
            };
            n_total += 1;
            let photo = if photo_camera.width == f.image.width() {
                f.image
            } else {
                image::imageops::resize(
                    &f.image,
                    photo_camera.width,
                    photo_camera.height,
                    image::imageops::FilterType::Triangle,
                )
            };
            match shot::localize_with_camera(&map, &photo_camera, &photo, None, bow_index, &params)?
            {
                Localization::Localized(p) => {
                    n_loc += 1;
                    let est = sim.transform_pose(&p.world_from_cam);
                    let rot_err = est
                        .rotation
                        .angle_to(&g.world_from_cam.rotation)
                        .to_degrees();
                    // Distance to the scene: the inliers' median depth, in metres.
                    let dist = p.median_depth * sim.scale;
                    let pos_m = (est.translation.vector - g.position()).norm();
                    let pos_err = pos_m / dist * 100.0;
                    println!(
                        "{i:5}  yes       {:6}  {:7.3}  {rot_err:11.4}  {:10.2}  {pos_err:13.3}  {:3}",
                        p.inliers,
                        p.reprojection_rmse_px,
                        pos_m * 100.0,
                        p.keyframe_id.0
                    );
                    rot_errs.push(rot_err);
                    if rot_err <= 0.5 && pos_err <= 2.0 {
                        n_ok += 1;
                    }
                    if rot_err > 2.0 || pos_err > 5.0 {
                        failures.push(format!(
                            "[{mode}] frame {i}: localised {rot_err:.2} deg, {pos_err:.2} % off"
                        ));
                    } else if rot_err > kf_rot_max + 0.25 {
                        failures.push(format!("[{mode}] frame {i}: {rot_err:.3} deg (map's worst keyframe {kf_rot_max:.3}), {pos_err:.2} %"));
                    }
                }
                Localization::NotLocalized { reason } => println!("{i:5}  no: {reason}"),
            }
        }
        rot_errs.sort_by(f64::total_cmp);
        println!(
            "[{mode}] {n_loc}/{n_total} localised, {n_ok} within 0.5 deg and 2 % of the distance; rotation error median {:.3} deg",
            rot_errs
                .get(rot_errs.len() / 2)
                .copied()
                .unwrap_or(f64::NAN)
        );
        assert!(n_total >= 10, "{n_total} query frames with ground truth");
        if n_loc * 3 < n_total * 2 {
            failures.push(format!("[{mode}] only {n_loc}/{n_total} localised"));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
    Ok(())
}
