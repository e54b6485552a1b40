//! Issue 21's measurement: desired photos from hidden poses AROUND the
//! flown path (0 to 10 m and more off it, 0.5x to 2x the keyframes'
//! distance to the scene, rolled), under the flight's light, with the sun
//! moved by 30 and 60 degrees (another time of day: the world's shading and
//! cast shadows move; its layout does not), and from another camera (other
//! size, focal length and distortion; its focal length only in the EXIF the
//! test writes into the JPEG).
//!
//! The map is SLAM's run over a rendered segment of the simulator's explore
//! flight, aligned to the truth with a Sim(3) on the keyframes (as in
//! `tests/suite/shot_sim.rs`). Every photo goes through the path of
//! `shotpilot shot --photo`: JPEG bytes, [`shot::photo_camera`] (explicit
//! intrinsics, else EXIF, else the map camera scaled), localisation with
//! the BoW candidates. Errors are against the hidden pose after the Sim(3):
//! position as % of the distance to the scene, rotation in degrees.
//!
//! Printed per condition and per band (distance from the flown path; ratio
//! of the distance to the scene to that of the keyframe the pose was made
//! from): localised share, error median / p90, the share of localised
//! photos whose true error lies within 1 and 2 reported sigma, and the
//! count of photos the gate passed with an error over 10 % of the distance
//! or 5 degrees (0 in every condition: asserted).
//!
//! `SHOT_PHOTOS_SEED=N` draws another set of hidden poses;
//! `SHOT_PHOTOS_ASSUME_MAP_FOCAL=1` takes the assumed camera of a photo
//! without EXIF as exact, `SHOT_PHOTOS_NO_UNION=1` localises on the best
//! candidate's pairs alone, `SHOT_PHOTOS_REMATCH_ROUNDS=0` skips the
//! projection rounds through the estimated camera of a photo whose focal
//! length was weighed or estimated from its EXIF (each as before it was
//! in, for a before/after).
//! `SHOT_MAP_NOISE_REF=PX` sets the reprojection noise the map's error is
//! scaled against (`inf`: not scaled) and `SHOT_GATE=POS,ROT,RATIO` the
//! gate's sigma and inlier-ratio bounds (both also read by
//! `shot_teddy::held_out_photos_by_angle_band`, `SHOT_GATE` by
//! `shot_aliasing`). The map's reprojection noise is printed (0.306 px:
//! the reference of `MapSigma::reference_noise_px`).
//! `SHOT_PHOTOS_DEBUG=1` prints a line per photo: where the keyframe its
//! pose was made from ranks in the bag-of-words query (-1: not at all), and
//! the error, sigma and error in the camera's frame (x right, y down, z
//! along the optical axis; % of the distance) and how far beyond the flown
//! views the map says it is (degrees), or why it was refused.
//!
//! `cargo test --release --test suite shot_photos:: -- --nocapture` (about 2 min).

use std::io::Cursor;
use std::sync::Arc;

use nalgebra::{Isometry3, Point3, Translation3, Unit, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use shotpilot::bow::Vocabulary;
use shotpilot::camera::Camera;
use shotpilot::geometry::{Sim3, umeyama};
use shotpilot::shot::{self, BowIndex, Localization};
use shotpilot::slam::{self, Map, Slam};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::{World, WorldParams};

use crate::sim_support::{distance_to_scene, random_unit, visible_point_indices};

const SEED: u64 = 1;
/// The mapped segment of the explore flight: start, end, step (s).
const T0: f64 = 0.0;
const T1: f64 = 30.0;
const DT: f64 = 0.15;
const PHOTOS: usize = 100;

/// The map, its alignment to the truth and what the sampling needs.
struct Mapped {
    world: Arc<World>,
    path: CameraPath,
    camera: Camera,
    map: Map,
    sim: Sim3,
    points_world: Vec<Point3<f64>>,
    kf_times: Vec<f64>,
    /// The flown path's camera centres over the mapped segment.
    flown: Vec<Vector3<f64>>,
}

fn build(world: Arc<World>) -> anyhow::Result<Mapped> {
    let sc = SimCamera::default();
    let renderer = Renderer::new(world.clone(), sc, RenderParams::default());
    let path = CameraPath::explore(&world, PathParams::default());
    let camera = shotpilot::simulator::camera_from_sim(&sc)?;
    let params = slam::Params {
        sequential: true,
        ..slam::Params::default()
    };
    let mut system = Slam::new(camera, params)?;
    let n = ((T1 - T0) / DT).floor() as usize + 1;
    let mut flown = Vec::new();
    for i in 0..n {
        let t = T0 + DT * i as f64;
        let pose = path.world_from_cam(t);
        flown.push(pose.translation.vector);
        system.process(
            i as u64,
            t,
            Arc::new(renderer.render_noisy(&pose, 1000 + i as u64)),
        );
    }
    let map = system.finish().map;
    anyhow::ensure!(map.keyframe_count() >= 10, "too few keyframes");
    // Sim(3): keyframe centres, then points one median depth along their axes.
    let mut src = Vec::new();
    let mut dst = Vec::new();
    let mut kfs = Vec::new();
    for kf in map.keyframes() {
        let truth = path.world_from_cam(kf.timestamp);
        src.push(Point3::from(kf.center()));
        dst.push(Point3::from(truth.translation.vector));
        kfs.push((kf.world_from_cam(), truth));
    }
    let coarse = umeyama(&src, &dst, true)?;
    let mut depths: Vec<f64> = map
        .keyframes()
        .filter_map(|k| map.median_depth(k.id))
        .collect();
    depths.sort_by(f64::total_cmp);
    let d = depths.get(depths.len() / 2).copied().unwrap_or(1.0);
    for (est, truth) in &kfs {
        for axis in [Vector3::x(), Vector3::y(), Vector3::z()] {
            src.push(est * Point3::from(axis * d));
            dst.push(truth * Point3::from(axis * (d * coarse.scale)));
        }
    }
    let sim = umeyama(&src, &dst, true)?;
    let mut rot: Vec<f64> = kfs
        .iter()
        .map(|(e, t)| {
            sim.transform_pose(e)
                .rotation
                .angle_to(&t.rotation)
                .to_degrees()
        })
        .collect();
    rot.sort_by(f64::total_cmp);
    println!(
        "map: explore t = {T0}..{T1} s every {DT} s, {} keyframes, {} points; keyframe orientation vs truth median {:.3} deg; Sim(3) scale {:.4}",
        map.keyframe_count(),
        map.point_count(),
        rot[rot.len() / 2],
        sim.scale
    );
    println!(
        "map: reprojection noise {:.3} px (RMS {:.3} px)",
        map.reprojection_noise_px().unwrap_or(f64::NAN),
        map.reprojection_rms_px().unwrap_or(f64::NAN)
    );
    // The keyframes' error against the truth after a Sim(3) of their
    // centres, and what the map's own bundle adjustment says it is.
    let truth_rms = (src
        .iter()
        .zip(&dst)
        .take(kfs.len())
        .map(|(e, t)| (coarse.transform_point(e) - t).norm_squared())
        .sum::<f64>()
        / kfs.len() as f64)
        .sqrt();
    let ids: Vec<_> = map.keyframes().map(|k| k.id).collect();
    let own_rms = shotpilot::slam::bundle::keyframe_position_rms(&map, &ids).unwrap_or(f64::NAN);
    println!(
        "map: keyframes against the truth RMS {:.3} m; the map's own bundle adjustment says {:.3} m",
        truth_rms,
        own_rms * coarse.scale
    );
    let points_world = map
        .points()
        .map(|p| sim.transform_point(&p.position))
        .collect();
    let mut kf_times: Vec<f64> = map.keyframes().map(|k| k.timestamp).collect();
    kf_times.sort_by(f64::total_cmp);
    Ok(Mapped {
        world,
        path,
        camera,
        map,
        sim,
        points_world,
        kf_times,
        flown,
    })
}

/// One hidden pose.
#[derive(Debug, Clone, Copy)]
struct Hidden {
    pose: Isometry3<f64>,
    /// Distance of the camera centre from the flown path, metres.
    off_path_m: f64,
    /// Its distance to the scene over that of the keyframe it was made from.
    scale: f64,
    /// Distance to the scene, metres.
    dist_m: f64,
    /// Timestamp of the keyframe it was made from.
    kf_time: f64,
}

/// `n` hidden poses: from a keyframe's true pose, the camera moves up to
/// 10 m in a random direction, then along the ray to the scene point on
/// its old optical axis to 0.5x..2x (log-uniform) of the keyframe's
/// distance to it, turns to look at that point, rolls by up to ±20 degrees
/// and turns by up to 5 degrees more. Kept when the camera is in the open
/// (above 2 m, nothing between it and the point) and sees at least 60
/// mapped points.
fn hidden_poses(m: &Mapped, n: usize, seed: u64) -> Vec<Hidden> {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut out = Vec::new();
    let mut attempts = 0;
    while out.len() < n {
        attempts += 1;
        assert!(attempts < n * 50, "too few poses see the map");
        let t = m.kf_times[rng.random_range(0..m.kf_times.len())];
        let base = m.path.world_from_cam(t);
        let eye = Point3::from(base.translation.vector);
        let axis = base.rotation * Vector3::z();
        let Some(hit) = m.world.ray_cast(&eye, &axis, 2000.0) else {
            continue;
        };
        let target = eye + axis * hit.t;
        let moved = eye + random_unit(&mut rng).into_inner() * rng.random_range(0.0..10.0);
        let scale = (rng.random_range(0.5f64.ln()..2f64.ln())).exp();
        let dir = (moved - target).normalize();
        let new_eye = target + dir * (hit.t * scale);
        if new_eye.z > -2.0 {
            continue;
        }
        let view = -dir;
        match m.world.ray_cast(&new_eye, &view, hit.t * scale * 1.1) {
            Some(h) if h.t < hit.t * scale * 0.98 => continue,
            _ => {}
        }
        let align = UnitQuaternion::rotation_between(&axis, &view).unwrap_or_default();
        let roll = UnitQuaternion::from_axis_angle(
            &Unit::new_normalize(Vector3::z()),
            rng.random_range(-20f64..20.0).to_radians(),
        );
        let turn = UnitQuaternion::from_axis_angle(
            &random_unit(&mut rng),
            rng.random_range(0.0..5f64).to_radians(),
        );
        let pose = Isometry3::from_parts(
            Translation3::from(new_eye.coords),
            align * base.rotation * roll * turn,
        );
        if visible_point_indices(&m.world, &m.camera, &m.points_world, &pose).len() < 60 {
            continue;
        }
        let off_path_m = m
            .flown
            .iter()
            .map(|c| (c - new_eye.coords).norm())
            .fold(f64::INFINITY, f64::min);
        out.push(Hidden {
            pose,
            off_path_m,
            scale,
            dist_m: distance_to_scene(&m.world, &m.camera, &pose),
            kf_time: t,
        });
    }
    out
}

/// One photo's outcome.
#[derive(Debug, Clone, Copy)]
struct Outcome {
    hidden: Hidden,
    localized: bool,
    pos_err_pct: f64,
    rot_err_deg: f64,
    /// Reported position sigma as % of the distance, rotation sigma in
    /// degrees (NaN when none is reported).
    pos_sigma_pct: f64,
    rot_sigma_deg: f64,
    /// Refused by the gate for its sigma.
    uncertain: bool,
}

/// A rendered photo as the operator would upload it: JPEG, with the given
/// EXIF (TIFF bytes of an APP1 segment) when there is one.
fn jpeg_of(img: &image::GrayImage, exif_tiff: Option<&[u8]>) -> Vec<u8> {
    let mut out = Vec::new();
    let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(Cursor::new(&mut out), 92);
    if let Some(tiff) = exif_tiff {
        use image::ImageEncoder;
        enc.set_exif_metadata(tiff.to_vec())
            .unwrap_or_else(|e| panic!("exif: {e}"));
    }
    enc.encode_image(img)
        .unwrap_or_else(|e| panic!("jpeg: {e}"));
    out
}

/// Renders, encodes and localises every hidden pose through `renderer`.
fn run_condition(
    m: &Mapped,
    index: &BowIndex<'_>,
    renderer: &Renderer,
    exif_tiff: Option<&[u8]>,
    hidden: &[Hidden],
    seed: u64,
) -> anyhow::Result<Vec<Outcome>> {
    let mut out = Vec::new();
    for (k, h) in hidden.iter().enumerate() {
        let img = renderer.render_noisy(&h.pose, seed ^ (70_000 + k as u64));
        let bytes = jpeg_of(&img, exif_tiff);
        let photo = shot::decode_photo(&bytes)?;
        let camera = shot::photo_camera(&m.map.camera, &photo, None)?;
        let params = shot::LocalizeParams {
            camera_uncertainty: camera.uncertainty,
            // SHOT_PHOTOS_ASSUME_MAP_FOCAL=1: the assumed camera taken as
            // exact, as before the focal length was weighed (a before/after).
            // SHOT_PHOTOS_NO_UNION=1: the best candidate's pairs alone.
            union_of_evidence: std::env::var_os("SHOT_PHOTOS_NO_UNION").is_none(),
            focal_unknown: camera.focal_unknown
                && std::env::var_os("SHOT_PHOTOS_ASSUME_MAP_FOCAL").is_none(),
            // SHOT_PHOTOS_REMATCH_ROUNDS=N: projection rounds through the
            // estimated camera (0: none, as before they were in).
            rematch_rounds: match std::env::var("SHOT_PHOTOS_REMATCH_ROUNDS") {
                Ok(n) => n.trim().parse()?,
                Err(_) => shot::LocalizeParams::default().rematch_rounds,
            },
            map_sigma: crate::sim_support::map_sigma_from_env()?,
            gate: crate::sim_support::gate_from_env()?,
            pnp: crate::sim_support::pnp_from_env()?,
            ..shot::LocalizeParams::default()
        };
        let debug = std::env::var_os("SHOT_PHOTOS_DEBUG").is_some();
        let rank = if debug {
            let near = shot::nearest_keyframes(
                &m.map,
                &camera.camera,
                &photo.image,
                None,
                index,
                &params,
                m.map.keyframe_count(),
            )?;
            near.iter()
                .position(|n| {
                    m.map
                        .keyframe(n.keyframe_id)
                        .is_some_and(|kf| kf.timestamp == h.kf_time)
                })
                .map_or(-1, |r| r as i64)
        } else {
            -1
        };
        let res = shot::localize_with_camera(
            &m.map,
            &camera.camera,
            &photo.image,
            None,
            Some(index),
            &params,
        )?;
        if debug {
            let mut line = format!(
                "PHOTO {k} off {:.1} scale {:.2} dist {:.1} rank {rank}",
                h.off_path_m, h.scale, h.dist_m
            );
            match &res {
                Localization::Localized(p) => {
                    let est = m.sim.transform_pose(&p.world_from_cam);
                    let d = est.translation.vector - h.pose.translation.vector;
                    let ec = h.pose.rotation.inverse() * d / h.dist_m * 100.0;
                    line += &format!(
                        " LOC perr {:.3} rerr {:.3} psig {:.3} rsig {:.3} ecam [{:.3} {:.3} {:.3}] inl {} agree {} beyond {:.1}",
                        d.norm() / h.dist_m * 100.0,
                        est.rotation.angle_to(&h.pose.rotation).to_degrees(),
                        p.sigma.position * m.sim.scale / h.dist_m * 100.0,
                        p.sigma.rotation_deg,
                        ec.x,
                        ec.y,
                        ec.z,
                        p.inliers,
                        p.agreeing_candidates,
                        p.beyond_views_deg
                    );
                }
                Localization::NotLocalized { reason } => line += &format!(" NOT {reason:?}"),
            }
            println!("{line}");
        }
        let o = match res {
            Localization::Localized(p) => {
                let est = m.sim.transform_pose(&p.world_from_cam);
                let (ps, rs) = (
                    p.sigma.position * m.sim.scale / h.dist_m * 100.0,
                    p.sigma.rotation_deg,
                );
                Outcome {
                    hidden: *h,
                    localized: true,
                    pos_err_pct: (est.translation.vector - h.pose.translation.vector).norm()
                        / h.dist_m
                        * 100.0,
                    rot_err_deg: est.rotation.angle_to(&h.pose.rotation).to_degrees(),
                    pos_sigma_pct: ps,
                    rot_sigma_deg: rs,
                    uncertain: false,
                }
            }
            Localization::NotLocalized { reason } => Outcome {
                uncertain: matches!(reason, shot::NotLocalizedReason::Uncertain { .. }),
                hidden: *h,
                localized: false,
                pos_err_pct: f64::NAN,
                rot_err_deg: f64::NAN,
                pos_sigma_pct: f64::NAN,
                rot_sigma_deg: f64::NAN,
            },
        };
        out.push(o);
    }
    Ok(out)
}

fn quantile(v: &mut [f64], q: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len()) - 1;
    v[i]
}

/// What a table row counts: the photos localised with an error over 10 %
/// of the distance or 5 degrees, and the share (%) of the localised ones
/// whose true errors lie within 2 reported sigma (NaN without any).
#[derive(Debug, Clone, Copy)]
struct RowStats {
    wrong: usize,
    within2: f64,
}

/// Prints one table row for the outcomes in `sel`; returns its counts.
fn row(label: &str, sel: &[&Outcome]) -> RowStats {
    let n = sel.len();
    let loc: Vec<&&Outcome> = sel.iter().filter(|o| o.localized).collect();
    let mut pos: Vec<f64> = loc.iter().map(|o| o.pos_err_pct).collect();
    let mut rot: Vec<f64> = loc.iter().map(|o| o.rot_err_deg).collect();
    let with_sigma: Vec<&&&Outcome> = loc
        .iter()
        .filter(|o| o.pos_sigma_pct.is_finite() && o.rot_sigma_deg.is_finite())
        .collect();
    let within = |k: f64| {
        if with_sigma.is_empty() {
            return f64::NAN;
        }
        let c = with_sigma
            .iter()
            .filter(|o| {
                o.pos_err_pct <= k * o.pos_sigma_pct && o.rot_err_deg <= k * o.rot_sigma_deg
            })
            .count();
        100.0 * c as f64 / with_sigma.len() as f64
    };
    let wrong = loc
        .iter()
        .filter(|o| o.pos_err_pct > 10.0 || o.rot_err_deg > 5.0)
        .count();
    let uncertain = sel.iter().filter(|o| o.uncertain).count();
    println!(
        "{label:<18} {n:4} {:5.0} %  {:7.2} {:7.2}  {:7.3} {:7.3}  {:5.0} % {:5.0} %  {wrong:5}  {uncertain:5}",
        if n == 0 {
            f64::NAN
        } else {
            100.0 * loc.len() as f64 / n as f64
        },
        quantile(&mut pos.clone(), 0.5),
        quantile(&mut pos, 0.9),
        quantile(&mut rot.clone(), 0.5),
        quantile(&mut rot, 0.9),
        within(1.0),
        within(2.0),
    );
    RowStats {
        wrong,
        within2: within(2.0),
    }
}

/// Prints the condition's table (and appends its photos to the CSV in the
/// temporary directory); returns the counts of its row of all photos.
fn table(name: &str, out: &[Outcome]) -> RowStats {
    use std::io::Write;
    let csv = std::env::temp_dir().join("shot_photos.csv");
    if let Ok(mut f) = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(&csv)
    {
        for (k, o) in out.iter().enumerate() {
            let _ = writeln!(
                f,
                "{name},{k},{:.2},{:.3},{:.1},{},{:.4},{:.4},{:.4},{:.4}",
                o.hidden.off_path_m,
                o.hidden.scale,
                o.hidden.dist_m,
                o.localized,
                o.pos_err_pct,
                o.rot_err_deg,
                o.pos_sigma_pct,
                o.rot_sigma_deg
            );
        }
    }
    println!("\n[{name}]");
    println!(
        "band                  n   loc.   pos %dist        rot deg       within    within  wrong  refused"
    );
    println!(
        "                                med     p90      med     p90   1 sigma   2 sigma  >10%|>5d by sigma"
    );
    let all: Vec<&Outcome> = out.iter().collect();
    let stats = row("all", &all);
    for (lo, hi) in [(0.0, 2.5), (2.5, 5.0), (5.0, 10.0), (10.0, f64::INFINITY)] {
        let sel: Vec<&Outcome> = out
            .iter()
            .filter(|o| o.hidden.off_path_m >= lo && o.hidden.off_path_m < hi)
            .collect();
        row(&format!("off path {lo}-{hi} m"), &sel);
    }
    for (lo, hi) in [(0.5, 0.71), (0.71, 1.41), (1.41, 2.01)] {
        let sel: Vec<&Outcome> = out
            .iter()
            .filter(|o| o.hidden.scale >= lo && o.hidden.scale < hi)
            .collect();
        row(&format!("scale {lo}-{hi}x"), &sel);
    }
    stats
}

#[test]
fn photos_around_the_flight_under_other_light_and_cameras() -> anyhow::Result<()> {
    let t_start = std::time::Instant::now();
    let wp = WorldParams::default();
    let world = Arc::new(World::generate_with(SEED, &wp)?);
    let m = build(world.clone())?;
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&m.map, &vocabulary);
    // SHOT_PHOTOS_SEED draws another set of hidden poses and noise (a
    // check that a change is not tuned to the default set).
    let pose_seed = match std::env::var("SHOT_PHOTOS_SEED") {
        Ok(s) => s.trim().parse::<u64>()?,
        Err(_) => 0x9407,
    };
    let hidden = hidden_poses(&m, PHOTOS, pose_seed);
    println!("hidden-pose seed {pose_seed}");
    // The render noise's seeds: 1, 2, 3 for the default set.
    let noise = |k: u64| {
        if pose_seed == 0x9407 {
            k
        } else {
            pose_seed.wrapping_mul(16) + k
        }
    };
    println!(
        "{} hidden poses: off the flown path {:.1}..{:.1} m, scale {:.2}..{:.2}x, distance to the scene {:.0}..{:.0} m ({:.0} s so far)",
        hidden.len(),
        hidden
            .iter()
            .map(|h| h.off_path_m)
            .fold(f64::INFINITY, f64::min),
        hidden.iter().map(|h| h.off_path_m).fold(0.0, f64::max),
        hidden.iter().map(|h| h.scale).fold(f64::INFINITY, f64::min),
        hidden.iter().map(|h| h.scale).fold(0.0, f64::max),
        hidden
            .iter()
            .map(|h| h.dist_m)
            .fold(f64::INFINITY, f64::min),
        hidden.iter().map(|h| h.dist_m).fold(0.0, f64::max),
        t_start.elapsed().as_secs_f64()
    );
    let mut wrong = 0;

    let renderer = Renderer::new(world.clone(), SimCamera::default(), RenderParams::default());
    let out = run_condition(&m, &index, &renderer, None, &hidden, noise(1))?;
    let mut calibration = Vec::new();
    let stats = table("flight's light, map camera", &out);
    wrong += stats.wrong;
    calibration.push(("flight's light", stats.within2));

    for moved in [30.0, 60.0] {
        let p = WorldParams {
            sun_azimuth_deg: wp.sun_azimuth_deg + moved,
            ..wp.clone()
        };
        let w = Arc::new(World::generate_with(SEED, &p)?);
        anyhow::ensure!(w.boxes == world.boxes, "the sun changed the layout");
        let r = Renderer::new(w, SimCamera::default(), RenderParams::default());
        let out = run_condition(&m, &index, &r, None, &hidden, noise(2))?;
        let stats = table(&format!("sun azimuth +{moved} deg"), &out);
        wrong += stats.wrong;
        calibration.push(("sun moved", stats.within2));
    }

    // Another camera: 800x600, wider (fx 480 px against the map's 460 at
    // 640), barrel distortion, its focal length only in the EXIF.
    let other = SimCamera {
        width: 800,
        height: 600,
        fx: 480.0,
        fy: 480.0,
        cx: 399.5,
        cy: 299.5,
        k1: -0.06,
        k2: 0.01,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    };
    // A phone's EXIF: the focal length and its 35 mm equivalent (whole
    // mm, by the frame diagonal), no sensor size.
    let f35 = other.fx * shot::photo::FRAME_35MM_DIAGONAL_MM
        / (other.width as f64).hypot(other.height as f64);
    let exif = shot::photo::exif_tiff(Some(4.0), Some(f35.round() as u16), None, None)
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    println!(
        "\nother camera: 800x600, fx {} px, k1 {}, k2 {}; EXIF 35 mm equivalent {} mm (exact {f35:.2})",
        other.fx,
        other.k1,
        other.k2,
        f35.round()
    );
    let r = Renderer::new(world.clone(), other, RenderParams::default());
    let out = run_condition(&m, &index, &r, None, &hidden, noise(3))?;
    // Without EXIF the map camera scaled is assumed (fx 575 px for the
    // true 480: 20 % too long), and another camera weighed against it
    // (shot::UnknownFocal): where the data pin the focal length the other
    // camera wins with it, else the sigma covers both and the gate refuses.
    let stats = table("800x600 camera, no EXIF (map camera's field of view)", &out);
    let wrong_no_exif = stats.wrong;
    calibration.push(("other camera, no EXIF", stats.within2));
    let loc_no_exif = out.iter().filter(|o| o.localized).count();
    let out = run_condition(&m, &index, &r, Some(&exif), &hidden, noise(3))?;
    let stats = table("800x600 camera, EXIF focal length", &out);
    let wrong_exif = stats.wrong;
    calibration.push(("other camera, EXIF", stats.within2));

    println!("\n{:.0} s in all", t_start.elapsed().as_secs_f64());
    assert_eq!(
        wrong, 0,
        "photos passed by the gate with an error over 10 % of the distance or 5 deg"
    );
    assert_eq!(
        wrong_no_exif, 0,
        "photos without EXIF passed by the gate with an error over 10 % or 5 deg"
    );
    // Not by refusing them all: the other camera's focal length is found
    // and the local map searched again through it (85 % localised on the
    // default poses, 86 % with SHOT_PHOTOS_SEED=2, 0.45 % median error;
    // 67 % and 70 % without that search).
    assert!(
        loc_no_exif >= 75,
        "only {loc_no_exif} of the photos without EXIF localised"
    );
    // The nearest scene content is also judged from the map points in the
    // photo's view, not only the matched ones (which may all be far).
    assert_eq!(
        wrong_exif, 0,
        "EXIF-camera photos passed by the gate with an error over 10 % or 5 deg"
    );
    // The confidence is honest: the true errors lie within 2 reported sigma
    // for 90 % of the localised photos in every condition. An estimated
    // focal length carries the map's own error too (MapSigma::focal_rel):
    // without it the other camera's photos were at 86 % and 89 % on the
    // default poses, 79 % and 77 % with SHOT_PHOTOS_SEED=2. The map's
    // error that does not shrink with the distance
    // (MapSigma::map_depth_fraction) took seed 2 from 91, 91, 89, 87, 87 %
    // to 99, 99, 99, 94, 93 % (held-out seed 3: 97, 94, 94, 86, 89 % to
    // 100, 97, 97, 94, 93 %).
    for (condition, within2) in calibration {
        assert!(
            within2 >= 90.0,
            "{condition}: only {within2:.0} % of the true errors within 2 sigma"
        );
    }
    Ok(())
}
