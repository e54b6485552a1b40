//! The must-show experiment of the desired shot on real data: anchors that a
//! pure camera rotation `R` would give, `anchor_i = distort(K·R·K⁻¹·undistort(corner_i))`,
//! placed on keyframes of a map of TUM fr3/teddy (100 frames). The shot they
//! describe is taken from the keyframe's position with orientation
//! `R_kf·R`; the localisation must find it within 0.5 degree and 2 % of the
//! keyframe's median scene depth, for 20 random rotations up to 15 degrees.
//!
//! Needs ../shared/data/tum_fr3_teddy_100 (skips with a message otherwise).
//! Run with `--nocapture` to see the table of errors.

use crate::data_support;

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

/// The dataset (tests/suite/data_support: required under `.ci/run`).
fn data_dir() -> Option<std::path::PathBuf> {
    data_support::shared_data("tum_fr3_teddy_100")
}

fn build_map(dir: &Path, max_frames: usize) -> anyhow::Result<Map> {
    let ds = Dataset::open(dir)?;
    build_map_with(&ds, ds.camera, max_frames)
}

/// The map of the first `max_frames` frames of `ds`, as seen through
/// `camera` (the dataset's own or altered intrinsics).
fn build_map_with(
    ds: &Dataset,
    camera: shotpilot::camera::Camera,
    max_frames: usize,
) -> anyhow::Result<Map> {
    let params = slam::Params {
        sequential: true,
        ..slam::Params::default()
    };
    let mut system = Slam::new(camera, params)?;
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

/// The anchors that draw the keyframe's view turned by `r` (`kf ← shot`):
/// where the shot's frame corners' rays, turned, meet the keyframe.
fn turn_anchors(
    cam: &shotpilot::camera::Camera,
    r: &UnitQuaternion<f64>,
) -> anyhow::Result<[Point2<f64>; 4]> {
    let corners = frame_corners(cam.width, cam.height);
    let mut anchors = [Point2::origin(); 4];
    for (a, c) in anchors.iter_mut().zip(&corners) {
        let ray = cam.unproject(*c).into_inner();
        *a = cam
            .project(&(r * ray))
            .ok_or_else(|| anyhow::anyhow!("anchor behind the camera"))?;
    }
    Ok(anchors)
}

#[test]
fn pure_rotation_anchors_localise_to_the_rotated_keyframe() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
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
            let anchors = turn_anchors(&cam, &r)?;
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

/// Anchors shots on the real map, from the keyframe's geometry: a pure
/// rotation drawn on a keyframe (a view a camera takes whatever the depths)
/// is that keyframe's camera turned, within 0.5 deg and 2 % of the depth;
/// and a drag (zoom 1.0-1.6x, pan, rotation) gives the same camera on the
/// map with 5 % of the keyframe's points culled (within 1 % of the depth
/// and 1 deg in at least 90 % of the cases), as after a restart.
#[test]
fn anchors_on_the_real_map_are_exact_for_a_turn_and_steady_for_a_drag() -> anyhow::Result<()> {
    use crate::sim_support::{pose_moved, with_points_culled};
    use shotpilot::simulator::drag::{DragParams, random_drag};
    let Some(dir) = data_dir() else {
        return Ok(());
    };
    let map = full_map(&dir)?;
    let cam = map.camera;
    let params = shot::Params::default();
    let mut kfs: Vec<_> = map
        .keyframes()
        .filter(|k| k.image.is_some())
        .map(|k| k.id)
        .collect();
    kfs.sort();
    anyhow::ensure!(kfs.len() >= 10, "only {} keyframes", kfs.len());
    let mut rng = StdRng::seed_from_u64(20261202);
    let mut cut = StdRng::seed_from_u64(35);
    let (mut worst_rot, mut worst_pos) = (0.0f64, 0.0f64);
    let (mut jumps, mut tries, mut moved) = (0, 0, Vec::new());
    for trial in 0..20 {
        let kf_id = kfs[(trial * kfs.len()) / 20];
        let kf = map
            .keyframe(kf_id)
            .ok_or_else(|| anyhow::anyhow!("keyframe vanished"))?;
        let img = kf
            .image
            .as_ref()
            .ok_or_else(|| anyhow::anyhow!("no image"))?;
        let depth = map.median_depth(kf_id).unwrap_or(f64::NAN);
        // A turn of the keyframe's camera.
        let r = random_rotation(&mut rng, 15.0);
        let turn = shot::desired_shot_from_anchors(img, &turn_anchors(&cam, &r)?, &params.anchors)?;
        let expected = kf.world_from_cam() * Isometry3::from_parts(Translation3::identity(), r);
        match shot::localize_anchors(map, kf_id, &turn.shot_to_source, &params.localize) {
            Localization::Localized(p) => {
                worst_rot = worst_rot.max(
                    p.world_from_cam
                        .rotation
                        .angle_to(&expected.rotation)
                        .to_degrees(),
                );
                worst_pos = worst_pos.max(
                    (p.world_from_cam.translation.vector - expected.translation.vector).norm()
                        / depth
                        * 100.0,
                );
            }
            Localization::NotLocalized { reason } => {
                anyhow::bail!("turn {trial} on keyframe {}: {reason}", kf_id.0)
            }
        }
        // A drag, on the map and on the map a little culled.
        let d = random_drag(&mut rng, &cam, &DragParams::default());
        let drag = shot::desired_shot_from_anchors(img, &d.anchors, &params.anchors)?;
        let Localization::Localized(p) =
            shot::localize_anchors(map, kf_id, &drag.shot_to_source, &params.localize)
        else {
            anyhow::bail!("drag {trial} on keyframe {} refused", kf_id.0);
        };
        for _ in 0..2 {
            let changed = with_points_culled(map, kf_id, 0.05, &mut cut);
            tries += 1;
            match shot::localize_anchors(&changed, kf_id, &drag.shot_to_source, &params.localize) {
                Localization::Localized(c) => {
                    let (pct, deg) = pose_moved(&p.world_from_cam, &c.world_from_cam, depth);
                    if pct > 1.0 || deg > 1.0 {
                        println!(
                            "drag {trial} (zoom {:.2}) on keyframe {}: moved {pct:.2} % / {deg:.2} deg on the culled map",
                            d.zoom, kf_id.0
                        );
                        jumps += 1;
                    }
                    moved.push(pct);
                }
                Localization::NotLocalized { reason } => {
                    println!("drag {trial}: refused on the culled map: {reason}");
                    jumps += 1;
                }
            }
        }
    }
    moved.sort_by(f64::total_cmp);
    println!(
        "turns: worst {worst_rot:.3} deg, {worst_pos:.3} % of the depth; drags on a 5 %-culled map: {jumps}/{tries} moved over 1 % or 1 deg, median {:.3} %, max {:.3} %",
        moved.get(moved.len() / 2).copied().unwrap_or(f64::NAN),
        moved.last().copied().unwrap_or(f64::NAN)
    );
    assert!(
        worst_rot < 0.5 && worst_pos < 2.0,
        "{worst_rot} deg, {worst_pos} %"
    );
    assert!(jumps * 10 <= tries, "{jumps} of {tries}");
    Ok(())
}

/// Shots of places the map never saw (EuRoC's machine hall, cropped to the
/// map camera's size, and seeded noise) must come back "not localised".
#[test]
fn shots_outside_the_map_are_not_localised() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
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

/// "Fly towards here": the keyframes a shot looks most like. A keyframe's
/// own picture lists that keyframe first, at its camera centre; the
/// scores fall from first to last.
#[test]
fn a_keyframe_picture_lists_itself_first_among_the_nearest_keyframes() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
        return Ok(());
    };
    let map = full_map(&dir)?;
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(map, &vocabulary);
    let params = shot::LocalizeParams::default();
    let mut ids: Vec<_> = map.keyframes().map(|k| k.id).collect();
    ids.sort_unstable();
    let mut checked = 0;
    for id in ids.iter().step_by(3) {
        let Some(kf) = map.keyframe(*id) else {
            continue;
        };
        let Some(img) = kf.image.as_ref() else {
            continue;
        };
        let near = shot::nearest_keyframes(map, &map.camera, img, None, &index, &params, 3)?;
        println!(
            "keyframe {}: {:?}",
            id.0,
            near.iter()
                .map(|n| (n.keyframe_id.0, (n.score * 1000.0).round() / 1000.0))
                .collect::<Vec<_>>()
        );
        assert_eq!(near.len(), 3, "keyframe {}", id.0);
        assert_eq!(near[0].keyframe_id, *id, "keyframe {}: {near:?}", id.0);
        assert!((near[0].position.coords - kf.center()).norm() < 1e-12);
        assert!(
            near.windows(2).all(|w| w[0].score >= w[1].score),
            "{near:?}"
        );
        checked += 1;
    }
    assert!(checked >= 5, "only {checked} keyframes with pictures");
    // A picture of another size than the camera's is an error, not a list.
    let small = image::GrayImage::new(map.camera.width / 2, map.camera.height / 2);
    assert!(shot::nearest_keyframes(map, &map.camera, &small, None, &index, &params, 3).is_err());
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
    Ok((align_pairs(map, &pairs)?, pairs))
}

/// The Sim(3) of [`align_keyframes`] from given (estimated, true) pose pairs.
fn align_pairs(map: &Map, pairs: &[PosePair]) -> anyhow::Result<Sim3> {
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
    for (est, truth) in pairs {
        src.push(Point3::from(est.translation.vector));
        dst.push(Point3::from(truth.translation.vector));
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            src.push(est * Point3::from(axis * d));
            dst.push(truth * Point3::from(axis * (d * coarse.scale)));
        }
    }
    Ok(umeyama(&src, &dst, true)?)
}

/// Frames held out of the map (the map is built from the first 70 frames;
/// the queries are the later frames of the same scene, every second one) as
/// photos, against the ground truth after a Sim(3) alignment of the map's
/// keyframes ([`align_keyframes`]); once at full size with the map camera,
/// once resized to 480x360 with the camera assumed for that size
/// ([`shot::assumed_camera`]: another camera's photo).
///
/// The map's own keyframes differ from the ground truth by about 0.55
/// degree (median; max 1.7) after the best alignment: the floor of any
/// absolute figure here (the SLAM's own tracking of these frames, when they
/// are part of the run, is no closer). [`orientation_floor_diagnosis`]
/// finds that neither a constant camera-from-marker rotation, nor a time
/// offset, nor other intrinsics removes it, and that the images' keypoints
/// fit the map's relative poses about as well as their own two-view optimum
/// while the ground truth's relative poses fit them twice as badly: the
/// floor is in the data (ground truth against these images), not in the
/// map's fit; no correction is applied here. Asserted: nothing localised
/// with an error over 2 degrees or 5 % of the distance; at least 2/3 of the
/// frames localised; each localised frame's orientation within 0.25 degree
/// beyond the map's worst keyframe. (The 0.5 degree / 2 % is met by
/// only 1-2 of the 15 frames here: their orientation errors are 0.8-1.0
/// degree (median) against the ground truth.)
#[test]
fn held_out_frames_localise_against_ground_truth() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
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
            // As `shotpilot shot --photo` takes a photo of another size
            // without EXIF: the map camera scaled, its focal length weighed.
            // SHOT_TEDDY_REMATCH_ROUNDS=N: the projection rounds through
            // the estimated camera (0: none, as before they were in).
            let params = shot::LocalizeParams {
                focal_unknown: photo_camera.width != map.camera.width,
                rematch_rounds: match std::env::var("SHOT_TEDDY_REMATCH_ROUNDS") {
                    Ok(n) => n.trim().parse()?,
                    Err(_) => params.rematch_rounds,
                },
                ..params.clone()
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
        // Two thirds with the map camera's size; half (8/15) for the
        // resized photo, whose focal length is weighed as unknown: 9/15
        // measured (10/15 without the projection round through the
        // estimated camera: frame 74 is now refused with a sigma of 2.01 %
        // against the 2 % gate), 4 refused as too uncertain (3.5-4.2 %: the map's own
        // error, 0.57 deg, lets another focal length fit about as well, and
        // the weighing says so), 2 failing PnP; 13/15 when the assumed
        // camera was taken as exact.
        let floor = if mode.contains("480x360") { 2 } else { 3 };
        if n_loc * floor < n_total * (floor - 1) {
            failures.push(format!("[{mode}] only {n_loc}/{n_total} localised"));
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
    Ok(())
}

/// The ground truth at time `t`: position linearly, orientation by slerp
/// between the two samples around `t` (None outside, or across a gap over
/// `max_gap` seconds).
fn gt_at(gt: &Trajectory, t: f64, max_gap: f64) -> Option<Isometry3<f64>> {
    let up = gt.poses.partition_point(|p| p.t <= t);
    if up == 0 || up >= gt.poses.len() {
        return None;
    }
    let (a, b) = (&gt.poses[up - 1], &gt.poses[up]);
    // A sample at the frame's own time (KITTI's poses are per frame, 0.1 s
    // apart) needs no interpolation.
    if (t - a.t).abs() < 1e-6 {
        return Some(a.world_from_cam);
    }
    if b.t - a.t > max_gap {
        return None;
    }
    let f = (t - a.t) / (b.t - a.t);
    let qa = a.world_from_cam.rotation;
    let mut qb = b.world_from_cam.rotation;
    if qa.coords.dot(&qb.coords) < 0.0 {
        qb = UnitQuaternion::new_unchecked(-qb.into_inner());
    }
    let q = qa.try_slerp(&qb, f, 1e-12).unwrap_or(qa);
    let p = a.position() * (1.0 - f) + b.position() * f;
    Some(Isometry3::from_parts(Translation3::from(p), q))
}

/// The rotation nearest (chordal L2) to the mean of `rs`.
fn rotation_mean(rs: &[UnitQuaternion<f64>]) -> UnitQuaternion<f64> {
    let sum: nalgebra::Matrix3<f64> = rs.iter().map(|r| r.to_rotation_matrix().into_inner()).sum();
    let svd = sum.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return UnitQuaternion::identity();
    };
    let mut d = nalgebra::Matrix3::identity();
    if (u * vt).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    UnitQuaternion::from_matrix(&(u * d * vt))
}

fn med_max(v: Vec<f64>) -> (f64, f64) {
    shotpilot::stats::median_max(&v).unwrap_or((f64::NAN, f64::NAN))
}

/// The best constant rotations `L` (left) and `X` (right) with
/// `truth ≈ L·est·X` over `pairs` (alternating chordal means); `X` is the
/// identity when `right` is false.
fn fit_left_right(
    pairs: &[(UnitQuaternion<f64>, UnitQuaternion<f64>)],
    right: bool,
) -> (UnitQuaternion<f64>, UnitQuaternion<f64>) {
    let mut x = UnitQuaternion::identity();
    let mut l = UnitQuaternion::identity();
    for _ in 0..if right { 200 } else { 1 } {
        let ls: Vec<_> = pairs
            .iter()
            .map(|(e, g)| g * x.inverse() * e.inverse())
            .collect();
        l = rotation_mean(&ls);
        if right {
            let xs: Vec<_> = pairs
                .iter()
                .map(|(e, g)| e.inverse() * l.inverse() * g)
                .collect();
            x = rotation_mean(&xs);
        }
    }
    (l, x)
}

/// Orientation residuals (degrees) of `truth ≈ L·est·X`.
fn residuals(
    pairs: &[(UnitQuaternion<f64>, UnitQuaternion<f64>)],
    l: &UnitQuaternion<f64>,
    x: &UnitQuaternion<f64>,
) -> Vec<f64> {
    pairs
        .iter()
        .map(|(e, g)| (l * e * x).angle_to(g).to_degrees())
        .collect()
}

/// The signed Sampson distance (pixels, for focal `f_px`) of the normalised
/// correspondence `x1 -> x2` under the relative pose `x2 ~ r·x1 + t`.
fn sampson_px(
    r: &UnitQuaternion<f64>,
    t: &Vector3<f64>,
    x1: &Vector3<f64>,
    x2: &Vector3<f64>,
    f_px: f64,
) -> f64 {
    let e = nalgebra::Matrix3::new(0.0, -t.z, t.y, t.z, 0.0, -t.x, -t.y, t.x, 0.0)
        * r.to_rotation_matrix().into_inner();
    let ex1 = e * x1;
    let etx2 = e.transpose() * x2;
    let den = ex1.x * ex1.x + ex1.y * ex1.y + etx2.x * etx2.x + etx2.y * etx2.y;
    if den > 0.0 {
        x2.dot(&ex1) / den.sqrt() * f_px
    } else {
        0.0
    }
}

/// The relative pose (rotation, unit translation) that minimises the
/// Huber-weighted (2 px) Sampson errors of `corr`, by Gauss-Newton with
/// numeric derivatives from `(r0, t0)`.
fn two_view_fit(
    corr: &[(Vector3<f64>, Vector3<f64>)],
    r0: UnitQuaternion<f64>,
    t0: Vector3<f64>,
    f_px: f64,
) -> (UnitQuaternion<f64>, Vector3<f64>) {
    let (mut r, mut t) = (r0, t0);
    let apply = |r: &UnitQuaternion<f64>, t: &Vector3<f64>, d: &nalgebra::Vector5<f64>| {
        let rn = UnitQuaternion::from_scaled_axis(Vector3::new(d[0], d[1], d[2])) * r;
        let a = if t.x.abs() < 0.9 {
            Vector3::x()
        } else {
            Vector3::y()
        };
        let u1 = t.cross(&a).normalize();
        let u2 = t.cross(&u1);
        (rn, (t + u1 * d[3] + u2 * d[4]).normalize())
    };
    for _ in 0..30 {
        let mut h = nalgebra::Matrix5::<f64>::zeros();
        let mut g = nalgebra::Vector5::<f64>::zeros();
        for (x1, x2) in corr {
            let e0 = sampson_px(&r, &t, x1, x2, f_px);
            let w = if e0.abs() <= 2.0 { 1.0 } else { 2.0 / e0.abs() };
            let mut j = nalgebra::Vector5::<f64>::zeros();
            for k in 0..5 {
                let mut d = nalgebra::Vector5::zeros();
                d[k] = 1e-7;
                let (rk, tk) = apply(&r, &t, &d);
                j[k] = (sampson_px(&rk, &tk, x1, x2, f_px) - e0) / 1e-7;
            }
            h += j * j.transpose() * w;
            g += j * e0 * w;
        }
        let Some(step) = h.try_inverse().map(|hi| -(hi * g)) else {
            break;
        };
        (r, t) = apply(&r, &t, &step);
        if step.norm() < 1e-10 {
            break;
        }
    }
    (r, t)
}

/// Why the map's keyframes sit about 0.6 degree off the TUM ground truth
/// after the best Sim(3) (the floor of [`held_out_frames_localise_against_ground_truth`]).
/// A diagnosis: it prints its tables and asserts nothing. The map is the
/// held-out test's (first 70 frames); the ground truth is interpolated at
/// the keyframes' times (position linearly, orientation by slerp).
///
/// * (a) hand-eye: a constant camera-from-marker rotation `X`, which a left
///   Sim(3) cannot remove, fitted with the left rotation (`truth ≈ L·est·X`)
///   on the keyframes; also leave-one-out over the keyframes, and carried
///   to the held-out frames (estimated on the keyframes only).
/// * (b) a time offset between images and ground truth, -30..30 ms.
/// * (c) intrinsics: the map rebuilt with the focal length scaled by
///   ±1..4 % and the principal point moved by 5 px.
/// * what remains: the ground truth's own sample-to-sample noise, the
///   error of the rotation between consecutive keyframes, how much of the
///   residual a slow function of time (a drift) takes, whether it lies
///   along the motion (as a timing error would), and the epipolar (Sampson)
///   error of the raw keypoints consecutive keyframes share, under the
///   map's relative pose, the ground truth's, mixtures of the two, and the
///   keypoints' own two-view optimum.
///
/// Measured (session 3, 21 keyframes with ground truth): keyframe
/// orientation residual median / max 0.546 / 1.725 deg with the held-out
/// test's Sim(3), 0.439 / 1.753 with the best left rotation, 0.366 / 1.420
/// with a right rotation too (X = 1.36 deg; leave-one-out 0.397 / 1.568;
/// carried to the held-out frames it makes them worse: median 1.03 -> 1.09
/// deg); time offsets -30..30 ms: best 0.431 at +6 ms (flat within ±6 ms);
/// focal length ±1-4 % and principal point ±5 px: 0.41-0.61; ground truth
/// noise 0.09 deg (median, 10 ms); consecutive keyframes' relative rotation
/// (2.7 deg) off by 0.36 deg (median); residual along the angular velocity
/// 0.18, across it 0.38 deg; each keyframe at its own best time shift still
/// 0.34 deg. Sampson error: map 0.63 px, keypoints' own optimum 0.59 px,
/// ground truth 1.17 px (median). None of (a), (b), (c) explains the floor.
/// Asserted: the map's epipolar error within 1.25x of the optimum and below
/// the ground truth's.
/// The localiser adds nothing to it: non-keyframe frames inside the map's
/// span localise at 0.57 deg (median) against the keyframes' 0.55; beyond
/// the span (frames 70..100) the localised frames are at 1.03 deg, and
/// SLAM's own keyframes of those frames (run over all 100, aligned on its
/// keyframes of 0..70) at 0.96 deg: the discrepancy grows with the motion.
#[test]
#[ignore = "slow (60 s): the orientation-floor diagnosis; .ci/run runs it"]
fn orientation_floor_diagnosis() -> anyhow::Result<()> {
    let Some(dir) = data_dir() else {
        return Ok(());
    };
    let ds = Dataset::open(&dir)?;
    let Some(gt) = ds.groundtruth.clone() else {
        anyhow::bail!("teddy has ground truth");
    };
    let map = build_map(&dir, 70)?;
    let mut kfs: Vec<(f64, Isometry3<f64>)> = map
        .keyframes()
        .map(|k| (k.timestamp, k.world_from_cam()))
        .collect();
    kfs.sort_by(|a, b| a.0.total_cmp(&b.0));
    let pairs_at = |dt: f64| -> Vec<(f64, PosePair)> {
        kfs.iter()
            .filter_map(|(t, e)| gt_at(&gt, t + dt, 0.05).map(|g| (*t, (*e, g))))
            .collect()
    };
    let rot_pairs = |p: &[(f64, PosePair)]| -> Vec<(UnitQuaternion<f64>, UnitQuaternion<f64>)> {
        p.iter()
            .map(|(_, (e, g))| (e.rotation, g.rotation))
            .collect()
    };
    let sim_rot = |p: &[(f64, PosePair)]| -> anyhow::Result<Vec<f64>> {
        let pp: Vec<PosePair> = p.iter().map(|x| x.1).collect();
        let sim = align_pairs(&map, &pp)?;
        Ok(pp
            .iter()
            .map(|(e, g)| {
                sim.transform_pose(e)
                    .rotation
                    .angle_to(&g.rotation)
                    .to_degrees()
            })
            .collect())
    };

    // (a) left vs left + right constant rotation, at the images' times.
    let p0 = pairs_at(0.0);
    let r0 = rot_pairs(&p0);
    let (ls, lx) = med_max(sim_rot(&p0)?);
    let (l, _) = fit_left_right(&r0, false);
    let (l_med, l_max) = med_max(residuals(&r0, &l, &UnitQuaternion::identity()));
    let (l2, x) = fit_left_right(&r0, true);
    let (lr_med, lr_max) = med_max(residuals(&r0, &l2, &x));
    let mut loo = Vec::new();
    for k in 0..r0.len() {
        let rest: Vec<_> = r0
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != k)
            .map(|(_, p)| *p)
            .collect();
        let (lk, xk) = fit_left_right(&rest, true);
        loo.extend(residuals(&r0[k..=k], &lk, &xk));
    }
    let (loo_med, loo_max) = med_max(loo);
    println!(
        "(a) {} keyframes with ground truth; orientation residual, degrees (median / max):",
        r0.len()
    );
    println!("    Sim(3) of the held-out test (centres + axis points)   {ls:.3} / {lx:.3}");
    println!("    best left rotation only                              {l_med:.3} / {l_max:.3}");
    println!(
        "    left + right constant rotation (X = {:.3} deg)        {lr_med:.3} / {lr_max:.3}",
        x.angle().to_degrees()
    );
    println!(
        "    the same, leave-one-out over the keyframes           {loo_med:.3} / {loo_max:.3}"
    );

    // (b) time offset.
    println!("(b) ground truth taken at image time + dt (interpolated):");
    println!("    dt_ms  keyframes  Sim(3) med / max   left rotation med / max");
    for dt_ms in (-30..=30).step_by(3) {
        let p = pairs_at(dt_ms as f64 * 1e-3);
        let r = rot_pairs(&p);
        let (a, b) = med_max(sim_rot(&p)?);
        let (lt, _) = fit_left_right(&r, false);
        let (c, d) = med_max(residuals(&r, &lt, &UnitQuaternion::identity()));
        println!(
            "    {dt_ms:5}  {:9}  {a:6.3} / {b:6.3}    {c:6.3} / {d:6.3}",
            p.len()
        );
    }

    // (c) intrinsics.
    println!("(c) map rebuilt with other intrinsics; keyframes' orientation residual:");
    println!("    intrinsics  keyframes  Sim(3) med / max   left rotation med / max");
    let c0 = ds.camera;
    for (name, df, dcx, dcy) in [
        ("as given", 1.0, 0.0, 0.0),
        ("f -4 %", 0.96, 0.0, 0.0),
        ("f -2 %", 0.98, 0.0, 0.0),
        ("f -1 %", 0.99, 0.0, 0.0),
        ("f +1 %", 1.01, 0.0, 0.0),
        ("f +2 %", 1.02, 0.0, 0.0),
        ("f +4 %", 1.04, 0.0, 0.0),
        ("cx +5 px", 1.0, 5.0, 0.0),
        ("cx -5 px", 1.0, -5.0, 0.0),
        ("cy +5 px", 1.0, 0.0, 5.0),
        ("cy -5 px", 1.0, 0.0, -5.0),
    ] {
        let cam = shotpilot::camera::Camera::new(
            c0.width,
            c0.height,
            [c0.fx * df, c0.fy * df, c0.cx + dcx, c0.cy + dcy],
            c0.distortion,
        )?;
        let m = build_map_with(&ds, cam, 70)?;
        let pp: Vec<PosePair> = m
            .keyframes()
            .filter_map(|k| gt_at(&gt, k.timestamp, 0.05).map(|g| (k.world_from_cam(), g)))
            .collect();
        let sim = align_pairs(&m, &pp)?;
        let (a, b) = med_max(
            pp.iter()
                .map(|(e, g)| {
                    sim.transform_pose(e)
                        .rotation
                        .angle_to(&g.rotation)
                        .to_degrees()
                })
                .collect(),
        );
        let r: Vec<_> = pp.iter().map(|(e, g)| (e.rotation, g.rotation)).collect();
        let (lt, _) = fit_left_right(&r, false);
        let (c, d) = med_max(residuals(&r, &lt, &UnitQuaternion::identity()));
        println!(
            "    {name:10}  {:9}  {a:6.3} / {b:6.3}    {c:6.3} / {d:6.3}",
            pp.len()
        );
    }

    // What remains.
    let gq: Vec<UnitQuaternion<f64>> = gt.poses.iter().map(|p| p.world_from_cam.rotation).collect();
    let noise: Vec<f64> = gq
        .windows(3)
        .map(|w| {
            let mid = w[0].try_slerp(&w[2], 0.5, 1e-12).unwrap_or(w[0]);
            mid.angle_to(&w[1]).to_degrees()
        })
        .collect();
    let (n_med, n_max) = med_max(noise);
    let rpe: Vec<(f64, f64)> = p0
        .windows(2)
        .map(|w| {
            let de = w[0].1.0.rotation.inverse() * w[1].1.0.rotation;
            let dg = w[0].1.1.rotation.inverse() * w[1].1.1.rotation;
            (de.angle_to(&dg).to_degrees(), dg.angle().to_degrees())
        })
        .collect();
    let (rpe_med, rpe_max) = med_max(rpe.iter().map(|x| x.0).collect());
    let (step_med, _) = med_max(rpe.iter().map(|x| x.1).collect());
    println!(
        "ground truth: a sample's orientation vs the midpoint of its neighbours (10 ms): median {n_med:.3}, max {n_max:.3} deg"
    );
    println!(
        "consecutive keyframes: relative rotation {step_med:.2} deg (median), its error vs ground truth median {rpe_med:.3}, max {rpe_max:.3} deg"
    );
    // A slow drift: the residual after the left rotation, in the camera
    // frame, fitted by a quadratic in time (leave-one-out).
    let t0 = p0.first().map(|p| p.0).unwrap_or(0.0);
    let res_vec: Vec<(f64, Vector3<f64>)> = p0
        .iter()
        .map(|(t, (e, g))| {
            (
                t - t0,
                (g.rotation.inverse() * l * e.rotation).scaled_axis() * 180.0
                    / std::f64::consts::PI,
            )
        })
        .collect();
    let mut drift_loo = Vec::new();
    for k in 0..res_vec.len() {
        let rows: Vec<&(f64, Vector3<f64>)> = res_vec
            .iter()
            .enumerate()
            .filter(|(j, _)| *j != k)
            .map(|(_, r)| r)
            .collect();
        let a = nalgebra::DMatrix::from_fn(rows.len(), 3, |i, c| rows[i].0.powi(c as i32));
        let b = nalgebra::DMatrix::from_fn(rows.len(), 3, |i, c| rows[i].1[c]);
        let Ok(coef) = a.clone().svd(true, true).solve(&b, 1e-12) else {
            continue;
        };
        let (tk, rk) = res_vec[k];
        let pred = Vector3::from_fn(|c, _| (0..3).map(|d| coef[(d, c)] * tk.powi(d as i32)).sum());
        drift_loo.push((rk - pred).norm());
    }
    let (d_med, d_max) = med_max(drift_loo);
    println!(
        "left-rotation residual minus a quadratic drift in time (leave-one-out): median {d_med:.3}, max {d_max:.3} deg"
    );

    // Along the motion or across it: the residual's component along the
    // ground truth's angular velocity (camera frame, over ±15 ms) is what a
    // timing error of the frame would give; the per-keyframe time shift
    // within ±30 ms that best removes the residual says how far timing alone
    // could explain each keyframe.
    let (mut along, mut across, mut shifted, mut shifts) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    for (t, r) in &res_vec {
        let t = t + t0;
        let (Some(a), Some(b)) = (gt_at(&gt, t - 0.015, 0.05), gt_at(&gt, t + 0.015, 0.05)) else {
            continue;
        };
        let w = (a.rotation.inverse() * b.rotation).scaled_axis();
        if w.norm() < 1e-9 {
            continue;
        }
        let wn = w.normalize();
        along.push(r.dot(&wn).abs());
        across.push(r.cross(&wn).norm());
        let Some(e) = kfs.iter().find(|k| k.0 == t).map(|k| k.1) else {
            continue;
        };
        let (best, dt) = (-30..=30)
            .filter_map(|ms| {
                gt_at(&gt, t + ms as f64 * 1e-3, 0.05)
                    .map(|g| ((l * e.rotation).angle_to(&g.rotation).to_degrees(), ms))
            })
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .unwrap_or((f64::NAN, 0));
        shifted.push(best);
        shifts.push((dt as f64).abs());
    }
    let (al_med, _) = med_max(along);
    let (ac_med, _) = med_max(across);
    let (sh_med, sh_max) = med_max(shifted);
    let (dt_med, dt_max) = med_max(shifts);
    println!(
        "left-rotation residual along the angular velocity: median {al_med:.3} deg; across it: median {ac_med:.3} deg"
    );
    println!(
        "each keyframe at its own best time shift (|dt| median {dt_med:.0} ms, max {dt_max:.0} ms): residual median {sh_med:.3}, max {sh_max:.3} deg"
    );

    // The images' own word, free of any alignment: the raw keypoints that
    // consecutive keyframes share (through a map point) against the
    // epipolar geometry of their relative pose, from the map and from the
    // ground truth (the translation's scale does not enter), and with the
    // rotation of one and the translation direction of the other.
    let cam = map.camera;
    let f_px = 0.5 * (cam.fx + cam.fy);
    let mut kf_sorted: Vec<_> = map
        .keyframes()
        .filter_map(|k| gt_at(&gt, k.timestamp, 0.05).map(|g| (k, g)))
        .collect();
    kf_sorted.sort_by(|a, b| a.0.timestamp.total_cmp(&b.0.timestamp));
    let mut sampson: [Vec<f64>; 5] = Default::default();
    for w in kf_sorted.windows(2) {
        let mut corr: Vec<(Vector3<f64>, Vector3<f64>)> = Vec::new();
        let ((a, ga), (b, gb)) = (&w[0], &w[1]);
        // b_from_a = cam_from_world_b · world_from_cam_a.
        let slam_rel = b.cam_from_world * a.world_from_cam();
        let gt_rel = gb.inverse() * ga;
        let norm = |v: Vector3<f64>| if v.norm() > 0.0 { v.normalize() } else { v };
        let variants = [
            (slam_rel.rotation, norm(slam_rel.translation.vector)),
            (gt_rel.rotation, norm(gt_rel.translation.vector)),
            (gt_rel.rotation, norm(slam_rel.translation.vector)),
            (slam_rel.rotation, norm(gt_rel.translation.vector)),
        ];
        for (i, slot) in a.points.iter().enumerate() {
            let Some(mp) = slot.and_then(|p| map.point(p)) else {
                continue;
            };
            let Some(&(_, j)) = mp.observations.iter().find(|(k, _)| *k == b.id) else {
                continue;
            };
            let (Some(ka), Some(kb)) = (a.keypoints.get(i), b.keypoints.get(j as usize)) else {
                continue;
            };
            let x1 = Vector3::new(
                (ka.ux as f64 - cam.cx) / cam.fx,
                (ka.uy as f64 - cam.cy) / cam.fy,
                1.0,
            );
            let x2 = Vector3::new(
                (kb.ux as f64 - cam.cx) / cam.fx,
                (kb.uy as f64 - cam.cy) / cam.fy,
                1.0,
            );
            for (v, (r, t)) in variants.iter().enumerate() {
                sampson[v].push(sampson_px(r, t, &x1, &x2, f_px).abs());
            }
            corr.push((x1, x2));
        }
        // The two-view relative pose of the keypoints alone (Sampson error,
        // Huber-weighted Gauss-Newton from the ground truth's pose).
        let (r2, t2) = two_view_fit(
            &corr,
            gt_rel.rotation,
            norm(gt_rel.translation.vector),
            f_px,
        );
        for (x1, x2) in &corr {
            sampson[4].push(sampson_px(&r2, &t2, x1, x2, f_px).abs());
        }
    }
    for (name, v) in [
        "map rotation, map translation",
        "ground-truth rotation, ground-truth translation",
        "ground-truth rotation, map translation",
        "map rotation, ground-truth translation",
        "two-view optimum of the keypoints alone",
    ]
    .iter()
    .zip(&sampson)
    {
        let (m, _) = med_max(v.clone());
        let mut s = v.clone();
        s.sort_by(f64::total_cmp);
        let p90 = s.get(s.len() * 9 / 10).copied().unwrap_or(f64::NAN);
        println!(
            "epipolar (Sampson) error of the {} shared keypoints of consecutive keyframes, {name:48}: median {m:.3} px, 90 % {p90:.3} px",
            v.len()
        );
    }

    // The claim this diagnosis supports, asserted: the images agree with the
    // map's relative poses about as well as they can (within 1.25x of the
    // keypoints' own two-view optimum) and better than with the ground
    // truth's; so the 0.5 deg floor against the ground truth is the data's.
    let med = |v: &[f64]| med_max(v.to_vec()).0;
    let (s_map, s_gt, s_opt) = (med(&sampson[0]), med(&sampson[1]), med(&sampson[4]));
    assert!(
        s_map <= 1.25 * s_opt,
        "map's epipolar error {s_map:.3} px vs the keypoints' optimum {s_opt:.3} px"
    );
    assert!(
        s_map < s_gt,
        "map's epipolar error {s_map:.3} px not below the ground truth's {s_gt:.3} px"
    );

    // (a) carried to the held-out frames: L and X from the keyframes only.
    let params = shot::LocalizeParams::default();
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&map, &vocabulary);
    let pp: Vec<PosePair> = p0.iter().map(|x| x.1).collect();
    let sim = align_pairs(&map, &pp)?;
    let (mut e_sim, mut e_l, mut e_lx) = (Vec::new(), Vec::new(), Vec::new());
    for i in (70..ds.len()).step_by(2) {
        let f = ds.frame(i)?;
        let Some(g) = gt_at(&gt, f.timestamp, 0.05) else {
            continue;
        };
        if let Localization::Localized(p) =
            shot::localize(&map, &f.image, None, Some(&index), &params)?
        {
            let r = p.world_from_cam.rotation;
            e_sim.push(
                sim.transform_pose(&p.world_from_cam)
                    .rotation
                    .angle_to(&g.rotation)
                    .to_degrees(),
            );
            e_l.push((l * r).angle_to(&g.rotation).to_degrees());
            e_lx.push((l2 * r * x).angle_to(&g.rotation).to_degrees());
        }
    }
    // The same localisation for frames inside the map's span that are not
    // keyframes: what the localiser adds to the map's own floor.
    let kf_frames: std::collections::HashSet<u64> =
        map.keyframes().map(|k| k.frame_index).collect();
    let mut inside = Vec::new();
    for i in (0..70).step_by(3) {
        let f = ds.frame(i)?;
        if kf_frames.contains(&(f.index as u64)) {
            continue;
        }
        let Some(g) = gt_at(&gt, f.timestamp, 0.05) else {
            continue;
        };
        if let Localization::Localized(p) =
            shot::localize(&map, &f.image, None, Some(&index), &params)?
        {
            inside.push(
                sim.transform_pose(&p.world_from_cam)
                    .rotation
                    .angle_to(&g.rotation)
                    .to_degrees(),
            );
        }
    }
    let n_inside = inside.len();
    let (im, ix) = med_max(inside);
    println!(
        "non-keyframe frames inside the map's span (every 3rd of 0..70), localised, orientation vs ground truth with Sim(3): median {im:.3}, max {ix:.3} deg over {n_inside}"
    );
    // SLAM itself over all 100 frames: its keyframes of frames 70..100
    // against the ground truth, with the Sim(3) of its keyframes of 0..70.
    let full = build_map(&dir, usize::MAX)?;
    let full_pairs = |early: bool| -> Vec<PosePair> {
        full.keyframes()
            .filter(|k| (k.frame_index < 70) == early)
            .filter_map(|k| gt_at(&gt, k.timestamp, 0.05).map(|g| (k.world_from_cam(), g)))
            .collect()
    };
    let (early, late) = (full_pairs(true), full_pairs(false));
    let sim_early = align_pairs(&full, &early)?;
    let err = |v: &[PosePair]| -> Vec<f64> {
        v.iter()
            .map(|(e, g)| {
                sim_early
                    .transform_pose(e)
                    .rotation
                    .angle_to(&g.rotation)
                    .to_degrees()
            })
            .collect()
    };
    let (em, ex) = med_max(err(&early));
    let (lm, lx) = med_max(err(&late));
    println!(
        "SLAM over all 100 frames, Sim(3) of its keyframes of frames 0..70: those {} keyframes median {em:.3}, max {ex:.3} deg; its {} keyframes of frames 70..100 median {lm:.3}, max {lx:.3} deg",
        early.len(),
        late.len()
    );
    let n = e_sim.len();
    let within = |v: &[f64]| v.iter().filter(|e| **e <= 0.5).count();
    for (name, v) in [
        ("Sim(3)", &e_sim),
        ("left rotation", &e_l),
        ("left + right X", &e_lx),
    ] {
        let (m, mx) = med_max(v.clone());
        println!(
            "held-out frames (bow query), orientation vs ground truth with {name:15} from the keyframes: median {m:.3}, max {mx:.3} deg, {}/{n} within 0.5 deg",
            within(v)
        );
    }
    Ok(())
}

/// SLAM's map of the frames of `ds` that `in_map` keeps, through the map
/// file format (as the daemon loads it).
fn build_map_of(ds: &Dataset, in_map: &dyn Fn(usize) -> bool) -> anyhow::Result<Map> {
    let params = slam::Params {
        sequential: true,
        ..slam::Params::default()
    };
    let mut system = Slam::new(ds.camera, params)?;
    for i in (0..ds.len()).filter(|i| in_map(*i)) {
        let f = ds.frame(i)?;
        system.process(f.index as u64, f.timestamp, Arc::new(f.image));
    }
    let run = system.finish();
    let tmp = tempfile::tempdir()?;
    let path = tmp.path().join("teddy.map");
    mapfile::save(&run.map, &path)?;
    Ok(mapfile::load(&path)?)
}

/// One held-out photo's outcome in [`held_out_photos_by_angle_band`].
struct BandRow {
    /// Angle (degrees) between its true orientation and the nearest
    /// keyframe's true orientation.
    angle: f64,
    /// Position error (% of the distance), rotation error (degrees),
    /// position error over the reported position sigma, rotation error
    /// over the rotation sigma, and both over the sigma with the
    /// reference's error added in quadrature (the keyframes' own RMS error
    /// against the ground truth, and the spread of the keyframes'
    /// alignment at the photo by a bootstrap); then the rotation error against the
    /// ground truth with its hand-eye rotation fitted on the keyframes
    /// (degrees) and that over the rotation sigma; None when refused.
    accepted: Option<[f64; 8]>,
    /// The refusal's reason.
    refusal: Option<String>,
}

/// Draws of the bootstrap of the keyframes' alignment to the ground truth
/// (the reference's own uncertainty at each photo).
const ALIGN_BOOTSTRAP: usize = 50;

/// The angle bands of the figures (degrees from the nearest keyframe).
const ANGLE_BANDS: [(f64, f64); 4] = [(0.0, 10.0), (10.0, 20.0), (20.0, 30.0), (30.0, 45.0)];

/// A photo localised further than 10 % of the distance or 5 degrees off
/// the truth: a wrong pass.
fn wrong_pass(pos_pct: f64, rot_deg: f64) -> bool {
    pos_pct > 10.0 || rot_deg > 5.0
}

/// Prints the per-band table of `rows`; returns the wrong passes.
fn print_bands(label: &str, rows: &[BandRow]) -> usize {
    println!(
        "[{label}] band      n  accepted  pos_err_% med/p90  rot_err_deg med/p90  pos<=2sig  rot<=2sig  (with the reference's error: pos, rot)  wrong  (hand-eye fitted: rot_err med/p90, rot<=2sig)"
    );
    let mut wrong_total = 0;
    for (lo, hi) in ANGLE_BANDS {
        let in_band: Vec<&BandRow> = rows
            .iter()
            .filter(|r| r.angle >= lo && r.angle < hi)
            .collect();
        if in_band.is_empty() {
            continue;
        }
        let acc: Vec<[f64; 8]> = in_band.iter().filter_map(|r| r.accepted).collect();
        let q = |v: Vec<f64>, p: f64| shotpilot::stats::quantile(&v, p).unwrap_or(f64::NAN);
        let pos: Vec<f64> = acc.iter().map(|a| a[0]).collect();
        let rot: Vec<f64> = acc.iter().map(|a| a[1]).collect();
        let rot_he: Vec<f64> = acc.iter().map(|a| a[6]).collect();
        let within = |k: usize| acc.iter().filter(|a| a[k] <= 2.0).count();
        let wrong = acc.iter().filter(|a| wrong_pass(a[0], a[1])).count();
        wrong_total += wrong;
        println!(
            "[{label}] {lo:2.0}-{hi:2.0} {:6}  {:3} ({:3.0} %)  {:6.2} / {:6.2}     {:6.2} / {:6.2}      {:3}/{:<3}   {:3}/{:<3}   {:3}/{:<3} {:3}/{:<3}                        {wrong}      {:6.2} / {:6.2}  {:3}/{:<3}",
            in_band.len(),
            acc.len(),
            100.0 * acc.len() as f64 / in_band.len() as f64,
            q(pos.clone(), 0.5),
            q(pos, 0.9),
            q(rot.clone(), 0.5),
            q(rot, 0.9),
            within(2),
            acc.len(),
            within(3),
            acc.len(),
            within(4),
            acc.len(),
            within(5),
            acc.len(),
            q(rot_he.clone(), 0.5),
            q(rot_he, 0.9),
            within(7),
            acc.len(),
        );
        let mut reasons: Vec<String> = in_band.iter().filter_map(|r| r.refusal.clone()).collect();
        reasons.sort();
        for r in reasons {
            println!("[{label}]        refused: {r}");
        }
    }
    wrong_total
}

/// Real photos beyond the map's views, per band of angle from the nearest
/// keyframe (issue 34, parts 2 and 3): splits of teddy_100 whose photos
/// are every held-out frame with ground truth (`SHOT_TEDDY_SPLITS`, e.g.
/// `0-70,60-100`, picks the maps: frames a-b; the photos are the others).
/// Per band: accepted share, position (% of the distance) and rotation
/// error median / p90 against the ground truth through the Sim(3) of the
/// keyframes ([`align_keyframes`]), the share of errors within 2 sigma,
/// wrong passes (over 10 % or 5 deg) and each refusal's reason. The
/// keyframes themselves sit about 0.7 cm / 0.7 deg off the ground truth
/// ([`orientation_floor_diagnosis`]), so the within-2-sigma share is also
/// given with that floor added to the sigma in quadrature. Asserted: no
/// wrong pass. Measured at ae29ea4 (splits 0-70, 0-60, 30-100): 0-10 deg
/// 37/38 accepted, 10-20 deg 14/46, 20-30 deg 1/11; refusals: 20 PnP
/// failed on all candidates, 22 inlier ratio 0.38-0.49; true position
/// errors within 2 sigma 2/52 (0.35-0.5 % sigma against 1.5-3 % errors);
/// 0 wrong. At ea0e108 (a candidate's PnP tried again on its
/// neighbourhood's matches): 0-10 deg 38/38, 10-20 deg 36/46 (2.78 / 4.29 %
/// and 1.21 / 1.92 deg off, median / p90), 20-30 deg 3/11; refusals: 8
/// inlier ratio 0.43-0.49, 4 PnP failed, 3 sigma 1.98-2.02 %, 2 candidates
/// disagreeing, 1 too few inliers; within 2 sigma 4/77 positions (39/77
/// with the keyframes' floor); 0 wrong. The rotation errors are also
/// given against the ground truth with a hand-eye rotation fitted on each
/// map's keyframes (a rotation in the camera's frame, which the Sim(3)
/// cannot remove): at 7acc20a it came out 0.36 / 0.30 / 0.07 deg, left the
/// keyframes 0.60-0.83 deg RMS off the truth, and moved the photos' median
/// rotation errors by under 0.2 deg (0-10 deg 0.90 -> 0.83, 10-20 deg 1.21
/// -> 1.04): the keyframes' floor is not a hand-eye rotation either.
///
/// Each map's reprojection noise is printed and each accepted photo's
/// `beyond_views_deg` (the map's own estimate of the angle beyond the
/// flown views: 1.6 / 9.0 / 17.0 / 20.2 deg where the ground truth says
/// 2.0 / 9.2 / 17.1 / 21.4). At the commit that scaled the map's error by
/// its noise (teddy 0.52-0.56 px against the rendered maps' 0.31: x1.7):
/// acceptance unchanged (38/38, 36/46, 3/11; the two refusals for
/// disagreeing candidates became "too uncertain" at 2.8 and 5.6 %: their
/// spread goes into the sigma), within 2 sigma per band 2/38, 2/36, 0/3
/// positions (unchanged) and 5/38, 5/36, 1/3 rotations (were 2/38, 4/36,
/// 0/3); with the keyframes' floor 30/38, 11/36, 0/3 positions (were
/// 28/38, 11/36, 0/3); 0 wrong. A lower inlier-ratio bound (0.4) moved 9
/// refusals to other reasons and accepted no more photos under the 2 %
/// sigma bound; a 5 % / 2.5 deg sigma bound with it accepted 38/38,
/// 41/46, 5/11 (0 wrong; the simulator's photos 97/95/95/90/89 % from
/// 93/91/92/86/84 %, 0 wrong) but let one more look-alike of the aliasing
/// world pass (11, from 10; `shot_aliasing`), so it was left at 2 %.
/// `SHOT_REAL_DATA=kitti07_first160 SHOT_TEDDY_SPLITS=0-120,40-160,0-100`
/// runs it on KITTI 07 (all 0-10 deg: 31 of 140 accepted, errors 1.50 /
/// 2.13 % and 0.43 / 0.57 deg; most refusals "PnP failed": the held-out
/// frames lie 20-60 m beyond the map along the street) and fails on one
/// wrong pass, frame 123 of the 0-100 map put 40 m off (a known gap, in
/// the README). `SHOT_PRIOR_SIGMA_M=5` gives every photo a position prior
/// as a GPS tag would (the truth moved by a seeded 5 m error per axis):
/// then frame 123 is refused 7.5 sigma from its tag, the 30 right passes
/// are kept (1.47 / 2.04 %), and the run passes.
///
/// With the map's error grown beyond the flown views (each inlier's
/// depth error over its keyframes' span, seen from the photo's angle:
/// `BeyondViews::factor`, 1.1-2.0 here), the gate's sigma bound at 5 % /
/// 2.5 deg (half a wrong shot's error), its inlier ratio at 0.4 and 10
/// PnP inliers for a candidate's first pose: 0-10 deg 38/38, 10-20 deg
/// 44/46 (2.74 / 4.09 %), 20-30 deg 6/11 (3.57 / 5.96 %), 0 wrong (was
/// 38/38, 36/46, 3/11); within 2 sigma with the reference's error (the
/// keyframes' RMS against the ground truth and the alignment's spread at
/// the photo, a bootstrap of the keyframes: 0.2-0.3 cm, 0.14-0.2 deg)
/// 36/38, 27/44, 0/6 positions and 38/38, 40/44, 4/6 rotations (was 30/38,
/// 11/36, 0/3 and 37/38, 29/36, 1/3). `SHOT_GATE=0.02,1.0,0.5` with
/// `SHOT_PNP_MIN_INLIERS=12` is the old gate on the new sigma: 38/38,
/// 36/46, 3/11 accepted, within 2 sigma with the reference's error 36/38,
/// 13/36, 0/3 positions (the growth alone, on the same photos).
///
/// `cargo test --release --test suite shot_teddy::held_out_photos_by_angle_band -- --ignored --nocapture`
/// (`RUST_LOG=shotpilot::shot=debug` adds the candidates' matches, PnP
/// inliers, projection rounds and the sigma's parts.)
#[test]
#[ignore = "slow (3 maps, ~3 min): the real-photo measurement per angle band"]
fn held_out_photos_by_angle_band() -> anyhow::Result<()> {
    let _ = tracing_subscriber::fmt()
        .with_env_filter(tracing_subscriber::EnvFilter::from_default_env())
        .with_test_writer()
        .try_init();
    // SHOT_REAL_DATA=kitti07_first160 (with SHOT_TEDDY_SPLITS=0-120,40-160,
    // say) runs the same measurement on another real sequence.
    let name = std::env::var("SHOT_REAL_DATA").unwrap_or_else(|_| "tum_fr3_teddy_100".into());
    let Some(dir) = data_support::shared_data(&name) else {
        return Ok(());
    };
    let ds = Dataset::open(&dir)?;
    let Some(gt) = ds.groundtruth.clone() else {
        anyhow::bail!("{name} has no ground truth");
    };
    let splits = std::env::var("SHOT_TEDDY_SPLITS").unwrap_or_else(|_| "0-70,0-60,30-100".into());
    let vocabulary = Vocabulary::builtin()?;
    let params = shot::LocalizeParams {
        map_sigma: crate::sim_support::map_sigma_from_env()?,
        gate: crate::sim_support::gate_from_env()?,
        pnp: crate::sim_support::pnp_from_env()?,
        ..shot::LocalizeParams::default()
    };
    // SHOT_PRIOR_SIGMA_M=5 gives each photo a position prior, as a GPS
    // tag through the georeference would: its true camera centre moved by
    // a seeded Gaussian error of that sigma per axis, in the map's frame
    // through the keyframes' Sim(3).
    let prior_sigma_m: Option<f64> = std::env::var("SHOT_PRIOR_SIGMA_M")
        .ok()
        .map(|v| v.parse())
        .transpose()?;
    let mut prior_rng = StdRng::seed_from_u64(34);
    let mut all = Vec::new();
    let mut wrong = 0;
    for split in splits.split(',') {
        let (a, b) = split
            .split_once('-')
            .ok_or_else(|| anyhow::anyhow!("split {split}: a-b"))?;
        let range: std::ops::Range<usize> = a.trim().parse()?..b.trim().parse()?;
        let in_map = |i: usize| range.contains(&i);
        let map = build_map_of(&ds, &in_map)?;
        let (sim, kf_pairs) = align_keyframes(&map, &gt)?;
        let index = BowIndex::build(&map, &vocabulary);
        // The reference's floor: the keyframes' own RMS error against the
        // ground truth after the alignment (metres, degrees).
        let n_kf = kf_pairs.len().max(1) as f64;
        let floor_m = (kf_pairs
            .iter()
            .map(|(e, t)| {
                (sim.transform_pose(e).translation.vector - t.translation.vector).norm_squared()
            })
            .sum::<f64>()
            / n_kf)
            .sqrt();
        // RMS angle (degrees) of the keyframes against the ground truth
        // turned by `offset` in the camera's frame.
        let rms_deg = |offset: &UnitQuaternion<f64>| {
            (kf_pairs
                .iter()
                .map(|(e, t)| {
                    sim.transform_pose(e)
                        .rotation
                        .angle_to(&(t.rotation * offset))
                        .to_degrees()
                        .powi(2)
                })
                .sum::<f64>()
                / n_kf)
                .sqrt()
        };
        let floor_deg = rms_deg(&UnitQuaternion::identity());
        // The alignment's own uncertainty where each photo is: the
        // Sim(3) refitted on keyframes drawn with replacement (a
        // bootstrap); a photo beyond the keyframes' arc sits on the lever
        // arm of the fit's rotation and scale error.
        let mut boot_rng = StdRng::seed_from_u64(1309);
        let boot: Vec<Sim3> = (0..ALIGN_BOOTSTRAP)
            .filter_map(|_| {
                let draw: Vec<PosePair> = (0..kf_pairs.len())
                    .map(|_| kf_pairs[boot_rng.random_range(0..kf_pairs.len())])
                    .collect();
                align_pairs(&map, &draw).ok()
            })
            .collect();
        // RMS spread (metres, degrees) of the map pose `p` through the
        // bootstrap's alignments about its image through `sim`.
        let align_spread = |p: &Isometry3<f64>| -> (f64, f64) {
            let at = sim.transform_pose(p);
            let n = boot.len().max(1) as f64;
            let (mut m2, mut d2) = (0.0, 0.0);
            for b in &boot {
                let q = b.transform_pose(p);
                m2 += (q.translation.vector - at.translation.vector).norm_squared();
                d2 += q.rotation.angle_to(&at.rotation).to_degrees().powi(2);
            }
            ((m2 / n).sqrt(), (d2 / n).sqrt())
        };
        // The ground truth's hand-eye rotation (mocap marker to camera) is
        // a rotation in the camera's frame that the Sim(3) in the world's
        // frame cannot remove: fitted on the keyframes (the map, never the
        // photos) as the mean of their camera-frame offsets.
        let offsets: Vec<UnitQuaternion<f64>> = kf_pairs
            .iter()
            .map(|(e, t)| t.rotation.inverse() * sim.transform_pose(e).rotation)
            .collect();
        let hand_eye = rotation_mean(&offsets);
        let floor_he_deg = rms_deg(&hand_eye);
        println!(
            "split map {split}: hand-eye rotation fitted on the keyframes {:.2} deg; keyframes against the ground truth through it: RMS {floor_he_deg:.2} deg",
            hand_eye.angle().to_degrees()
        );
        println!(
            "split map {split}: {} keyframes ({} with ground truth), {} points, reprojection noise {:.3} px, Sim(3) scale {:.4}; keyframes against the ground truth: RMS {:.2} cm, {floor_deg:.2} deg",
            map.keyframe_count(),
            kf_pairs.len(),
            map.point_count(),
            map.reprojection_noise_px().unwrap_or(f64::NAN),
            sim.scale,
            floor_m * 100.0,
        );
        let kf_ids: Vec<_> = map.keyframes().map(|k| k.id).collect();
        let own_rms =
            shotpilot::slam::bundle::keyframe_position_rms(&map, &kf_ids).unwrap_or(f64::NAN);
        println!(
            "split map {split}: the map's own BA says its keyframes are RMS {:.2} cm off (truth {:.2} cm); reprojection RMS {:.3} px",
            own_rms * sim.scale * 100.0,
            floor_m * 100.0,
            map.reprojection_rms_px().unwrap_or(f64::NAN)
        );
        println!("  frame  angle_deg  outcome");
        let mut rows = Vec::new();
        for i in (0..ds.len()).filter(|i| !in_map(*i)) {
            let f = ds.frame(i)?;
            let Some(g) = gt_at(&gt, f.timestamp, 0.05) else {
                continue;
            };
            let angle = kf_pairs
                .iter()
                .map(|(_, t)| t.rotation.angle_to(&g.rotation).to_degrees())
                .fold(f64::INFINITY, f64::min);
            let params = shot::LocalizeParams {
                position_prior: prior_sigma_m.map(|sigma_m| {
                    crate::sim_support::simulated_tag(
                        &g.translation.vector,
                        &sim,
                        sigma_m,
                        &mut prior_rng,
                    )
                }),
                ..params.clone()
            };
            let row = match shot::localize(&map, &f.image, None, Some(&index), &params)? {
                Localization::Localized(p) => {
                    let est = sim.transform_pose(&p.world_from_cam);
                    let rot_err = est.rotation.angle_to(&g.rotation).to_degrees();
                    let dist = p.median_depth * sim.scale;
                    let pos_m = (est.translation.vector - g.translation.vector).norm();
                    let pos_pct = pos_m / dist * 100.0;
                    let sig_m = p.sigma.position * sim.scale;
                    let pos_sig = pos_m / sig_m.max(1e-12);
                    let rot_sig = rot_err / p.sigma.rotation_deg.max(1e-12);
                    let (align_m, align_deg) = align_spread(&p.world_from_cam);
                    let pos_sig_floor = pos_m / sig_m.hypot(floor_m).hypot(align_m).max(1e-12);
                    let rot_sig_floor = rot_err
                        / p.sigma
                            .rotation_deg
                            .hypot(floor_deg)
                            .hypot(align_deg)
                            .max(1e-12);
                    let rot_he = est.rotation.angle_to(&(g.rotation * hand_eye)).to_degrees();
                    let rot_sig_he = rot_he / p.sigma.rotation_deg.max(1e-12);
                    println!(
                        "  {i:5}  {angle:9.1}  yes: {:.2} cm {pos_pct:.2} % ({pos_sig:.2} sigma, sigma {:.2} % of near, {:.2} % of median), {rot_err:.2} deg ({rot_sig:.2} sigma), beyond views {:.1} deg, {} inliers, kf {}, alignment at the photo {:.2} cm {:.2} deg{}",
                        pos_m * 100.0,
                        p.sigma.position_depth_fraction * 100.0,
                        p.sigma.position / p.median_depth * 100.0,
                        p.beyond_views_deg,
                        p.inliers,
                        p.keyframe_id.0,
                        align_m * 100.0,
                        align_deg,
                        if wrong_pass(pos_pct, rot_err) {
                            "  WRONG"
                        } else {
                            ""
                        }
                    );
                    BandRow {
                        angle,
                        accepted: Some([
                            pos_pct,
                            rot_err,
                            pos_sig,
                            rot_sig,
                            pos_sig_floor,
                            rot_sig_floor,
                            rot_he,
                            rot_sig_he,
                        ]),
                        refusal: None,
                    }
                }
                Localization::NotLocalized { reason } => {
                    println!("  {i:5}  {angle:9.1}  no: {reason}");
                    BandRow {
                        angle,
                        accepted: None,
                        refusal: Some(format!("{i}: {reason}")),
                    }
                }
            };
            rows.push(row);
        }
        wrong += print_bands(&format!("map {split}"), &rows);
        all.extend(rows);
    }
    print_bands("all splits", &all);
    assert_eq!(wrong, 0, "wrong passes");
    Ok(())
}
