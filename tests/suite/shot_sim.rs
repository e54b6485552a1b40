//! The must-show simulator experiment of the desired shot: a SLAM map is
//! built from the simulator's render of a segment of the `explore` survey
//! flight; desired shots are rendered from hidden poses near the explored
//! area (seeded random positions and orientations whose view holds mapped
//! scene) and localised; the map is aligned to the simulator's ground truth
//! with a Sim(3) (`geometry::umeyama` on the keyframes' poses: their centres
//! and points one scene depth along their camera axes, against the true
//! ones) and each localised pose is compared with the hidden one:
//!
//! * within 1 % of the distance to the scene and 0.5 degree in at least 90 %
//!   of the trials;
//! * no trial reports "localised" with an error over 5 % or 2 degrees;
//! * shots of places the map never saw come back "not localised".
//!
//! Held-out frames (the third must-show): frames of the explore
//! flight after its mapped segment, and, on a flight that revisits its
//! scene, a second lap of the sim's orbit (on the mapped circle and off
//! it) against a map made from 75 % of the first lap
//! ([`held_out_orbit_frames_localise`]), localised as photos against the
//! true poses after the Sim(3) alignment.
//!
//! Everything is rendered in-process through the sim crate's library (no
//! files). Run with `--nocapture` to see the map's statistics and the table.

use std::sync::{Arc, OnceLock};

use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};

use shotpilot::bow::Vocabulary;
use shotpilot::camera::Camera;
use shotpilot::geometry::{Sim3, umeyama};
use shotpilot::shot::{self, BowIndex, Localization};
use shotpilot::slam::{self, KeyFrameId, Map, Slam, mapfile};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, camera_from_yaw_pitch};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::{World, WorldParams};

use crate::sim_support::{
    distance_to_scene, pose_moved, random_unit, visible_point_indices, with_points_culled,
};

/// One configuration of the experiment.
#[derive(Debug, Clone, Copy)]
struct Setup {
    /// Image size; the focal length scales with the width (the sim's default
    /// camera is 640x480 with fx = 460).
    width: u32,
    height: u32,
    /// Segment of the explore flight that makes the map: start, end, step (s).
    t0: f64,
    t1: f64,
    dt: f64,
}

fn sim_camera(width: u32, height: u32) -> SimCamera {
    let s = width as f64 / 640.0;
    let d = SimCamera::default();
    SimCamera {
        width,
        height,
        fx: d.fx * s,
        fy: d.fy * s,
        cx: (width as f64 - 1.0) / 2.0,
        cy: (height as f64 - 1.0) / 2.0,
        ..d
    }
}

fn map_camera(c: &SimCamera) -> anyhow::Result<Camera> {
    Ok(shotpilot::simulator::camera_from_sim(c)?)
}

/// The world, the renderer and the explore path.
struct Scene {
    world: Arc<World>,
    renderer: Renderer,
    path: CameraPath,
    camera: Camera,
}

fn scene(setup: &Setup, seed: u64) -> anyhow::Result<Scene> {
    scene_on(setup, seed, |world| {
        CameraPath::explore(world, PathParams::default())
    })
}

/// The world of `seed`, the renderer and the path `make_path` builds over it.
fn scene_on(
    setup: &Setup,
    seed: u64,
    make_path: impl FnOnce(&World) -> CameraPath,
) -> anyhow::Result<Scene> {
    let world = Arc::new(World::generate_with(seed, &WorldParams::default())?);
    let sc = sim_camera(setup.width, setup.height);
    let renderer = Renderer::new(world.clone(), sc, RenderParams::default());
    let path = make_path(&world);
    Ok(Scene {
        world,
        renderer,
        path,
        camera: map_camera(&sc)?,
    })
}

/// Map statistics printed with the table.
struct MapStats {
    frames: usize,
    tracked: usize,
    initialized_at: Option<u64>,
    keyframes: usize,
    points: usize,
    /// Keyframe centres vs truth after the Sim(3): RMSE, metres.
    kf_rmse_m: f64,
    /// Keyframe orientations vs truth after the Sim(3): median and max, degrees.
    kf_rot_med_deg: f64,
    kf_rot_max_deg: f64,
}

fn build_map(sc: &Scene, setup: &Setup) -> anyhow::Result<(Map, Sim3, MapStats)> {
    let params = slam::Params {
        sequential: true,
        ..slam::Params::default()
    };
    let mut system = Slam::new(sc.camera, params)?;
    let n = ((setup.t1 - setup.t0) / setup.dt).floor() as usize + 1;
    for i in 0..n {
        let t = setup.t0 + setup.dt * i as f64;
        let img = sc
            .renderer
            .render_noisy(&sc.path.world_from_cam(t), 1000 + i as u64);
        system.process(i as u64, t, Arc::new(img));
    }
    let run = system.finish();
    let map = run.map;
    let mut src = Vec::new();
    let mut dst = Vec::new();
    let mut kfs = Vec::new();
    for kf in map.keyframes() {
        src.push(Point3::from(kf.center()));
        let truth = sc.path.world_from_cam(kf.timestamp);
        dst.push(Point3::from(truth.translation.vector));
        kfs.push((kf.world_from_cam(), truth));
    }
    // The Sim(3) from the keyframes' poses: their centres first (for the
    // scale), then with three points one median scene depth along each
    // keyframe's camera axes, so the orientations constrain it too.
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
    let mut sq = 0.0;
    let mut rot: Vec<f64> = Vec::new();
    for (est, truth) in &kfs {
        let e = sim.transform_pose(est);
        sq += (e.translation.vector - truth.translation.vector).norm_squared();
        rot.push(e.rotation.angle_to(&truth.rotation).to_degrees());
    }
    rot.sort_by(f64::total_cmp);
    let stats = MapStats {
        frames: n,
        tracked: run.records.len(),
        initialized_at: run.initialized_at,
        keyframes: map.keyframe_count(),
        points: map.point_count(),
        kf_rmse_m: (sq / kfs.len().max(1) as f64).sqrt(),
        kf_rot_med_deg: rot.get(rot.len() / 2).copied().unwrap_or(f64::NAN),
        kf_rot_max_deg: rot.last().copied().unwrap_or(f64::NAN),
    };
    Ok((map, sim, stats))
}

/// One trial's outcome.
struct Trial {
    localized: bool,
    rot_err_deg: f64,
    pos_err_pct: f64,
}

/// The map of the experiment and what the trials need of it.
struct Mapped {
    sc: Scene,
    map: Map,
    sim: Sim3,
    /// The map's points in the true world frame (through `sim`).
    points_world: Vec<Point3<f64>>,
    /// Times of the keyframes along the flight.
    kf_times: Vec<f64>,
    /// For each map point (in `points_world`'s order), the true centres of
    /// the keyframes that observe it.
    point_observers: Vec<Vec<Vector3<f64>>>,
    /// Frames given to SLAM, and how many it tracked.
    frames: usize,
    tracked: usize,
}

/// The setting: a 640x480 render of the first third (30 s) of the
/// explore flight, a frame every 0.15 s.
const SETUP: Setup = Setup {
    width: 640,
    height: 480,
    t0: 0.0,
    t1: 30.0,
    dt: 0.15,
};
const SEED: u64 = 1;

/// The map, built once for the tests of this file.
fn mapped() -> anyhow::Result<&'static Mapped> {
    static MAPPED: OnceLock<Result<Mapped, String>> = OnceLock::new();
    MAPPED
        .get_or_init(|| build_mapped(SETUP, SEED).map_err(|e| format!("{e:#}")))
        .as_ref()
        .map_err(|e| anyhow::anyhow!("{e}"))
}

fn build_mapped(setup: Setup, seed: u64) -> anyhow::Result<Mapped> {
    build_mapped_on(scene(&setup, seed)?, setup, "explore")
}

/// SLAM's map of `sc`'s path over `setup`'s segment, aligned to the truth;
/// `label` names the path in the printed statistics.
fn build_mapped_on(sc: Scene, setup: Setup, label: &str) -> anyhow::Result<Mapped> {
    let t_start = std::time::Instant::now();
    let (map, sim, st) = build_map(&sc, &setup)?;
    println!(
        "map: {}x{} render, {label} t = {:.1}..{:.1} s every {:.2} s: {} frames, initialised at frame {:?}, {} tracked, {} keyframes, {} points",
        setup.width,
        setup.height,
        setup.t0,
        setup.t1,
        setup.dt,
        st.frames,
        st.initialized_at,
        st.tracked,
        st.keyframes,
        st.points
    );
    println!(
        "map vs truth after Sim(3) (scale {:.4}): keyframe centres RMSE {:.3} m, orientation median {:.3} deg, max {:.3} deg ({:.1} s to render and map)",
        sim.scale,
        st.kf_rmse_m,
        st.kf_rot_med_deg,
        st.kf_rot_max_deg,
        t_start.elapsed().as_secs_f64()
    );
    anyhow::ensure!(
        st.keyframes >= 10,
        "the map has only {} keyframes",
        st.keyframes
    );
    let points_world: Vec<Point3<f64>> = map
        .points()
        .map(|p| sim.transform_point(&p.position))
        .collect();
    let mut kf_times: Vec<f64> = map.keyframes().map(|k| k.timestamp).collect();
    kf_times.sort_by(f64::total_cmp);
    let kf_centres: std::collections::HashMap<KeyFrameId, Vector3<f64>> = map
        .keyframes()
        .map(|k| (k.id, sc.path.world_from_cam(k.timestamp).translation.vector))
        .collect();
    let point_observers = map
        .points()
        .map(|p| {
            p.observations
                .iter()
                .filter_map(|(k, _)| kf_centres.get(k).copied())
                .collect()
        })
        .collect();
    Ok(Mapped {
        sc,
        map,
        sim,
        points_world,
        kf_times,
        point_observers,
        frames: st.frames,
        tracked: st.tracked,
    })
}

/// A hidden pose near the mapped flight: a keyframe's time (± 0.5 s), the
/// position moved by up to 4 m, the orientation turned by up to 12 degrees.
/// Returns the pose, the offset (m) and the turn (degrees).
fn hidden_pose_near(m: &Mapped, rng: &mut StdRng) -> (f64, Isometry3<f64>, f64, f64) {
    let t = m.kf_times[rng.random_range(0..m.kf_times.len())] + rng.random_range(-0.5..0.5);
    let base = m.sc.path.world_from_cam(t);
    let offset = random_unit(rng).into_inner() * rng.random_range(0.0..4.0);
    let turn = UnitQuaternion::from_axis_angle(
        &random_unit(rng),
        rng.random_range(0.0..12f64).to_radians(),
    );
    let hidden = Isometry3::from_parts(
        Translation3::from(base.translation.vector + offset),
        base.rotation * turn,
    );
    (t, hidden, offset.norm(), turn.angle().to_degrees())
}

/// Localises `trials` shots rendered by `renderer` (whose camera is
/// `camera`) from hidden poses near the flight; prints the table and
/// returns the trials.
fn localise_near(
    m: &Mapped,
    renderer: &Renderer,
    camera: &Camera,
    trials: usize,
    seed: u64,
) -> anyhow::Result<Vec<Trial>> {
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&m.map, &vocabulary);
    let params = shot::LocalizeParams::default();
    let mut rng = StdRng::seed_from_u64(seed);
    let min_visible = 150;
    println!(
        "trial   t_s  offset_m  turn_deg  visible  dist_m  localized  inliers  rmse_px  rot_err_deg  pos_err_%dist"
    );
    let mut out: Vec<Trial> = Vec::new();
    let mut attempts = 0;
    while out.len() < trials {
        attempts += 1;
        anyhow::ensure!(attempts < trials * 20, "too few poses see the map");
        let (t, hidden, offset_m, turn_deg) = hidden_pose_near(m, &mut rng);
        let visible = visible_point_indices(&m.sc.world, camera, &m.points_world, &hidden).len();
        if visible < min_visible {
            continue;
        }
        let dist = distance_to_scene(&m.sc.world, &m.sc.camera, &hidden);
        let k = out.len();
        let img = renderer.render_noisy(&hidden, seed ^ (50_000 + k as u64));
        let row = format!("{k:5} {t:5.1}  {offset_m:8.2}  {turn_deg:8.2}  {visible:7}  {dist:6.1}");
        match shot::localize_with_camera(&m.map, camera, &img, None, Some(&index), &params)? {
            Localization::Localized(p) => {
                let est = m.sim.transform_pose(&p.world_from_cam);
                let rot_err = est.rotation.angle_to(&hidden.rotation).to_degrees();
                let pos_err =
                    (est.translation.vector - hidden.translation.vector).norm() / dist * 100.0;
                println!(
                    "{row}  yes        {:7}  {:7.3}  {rot_err:11.4}  {pos_err:13.3}",
                    p.inliers, p.reprojection_rmse_px,
                );
                out.push(Trial {
                    localized: true,
                    rot_err_deg: rot_err,
                    pos_err_pct: pos_err,
                });
            }
            Localization::NotLocalized { reason } => {
                println!("{row}  no: {reason}");
                out.push(Trial {
                    localized: false,
                    rot_err_deg: f64::NAN,
                    pos_err_pct: f64::NAN,
                });
            }
        }
    }
    Ok(out)
}

/// Prints the summary of `trials` and asserts the bounds: at least
/// 90 % within 1 % of the distance and 0.5 degree; none localised with an
/// error over 5 % or 2 degrees.
fn judge(name: &str, trials: &[Trial]) {
    let n = trials.len();
    let localized = trials.iter().filter(|t| t.localized).count();
    let good = trials
        .iter()
        .filter(|t| t.localized && t.rot_err_deg <= 0.5 && t.pos_err_pct <= 1.0)
        .count();
    let wrong: Vec<usize> = trials
        .iter()
        .enumerate()
        .filter(|(_, t)| t.localized && (t.rot_err_deg > 2.0 || t.pos_err_pct > 5.0))
        .map(|(i, _)| i)
        .collect();
    let sorted = |f: fn(&Trial) -> f64| {
        let mut v: Vec<f64> = trials.iter().filter(|t| t.localized).map(f).collect();
        v.sort_by(f64::total_cmp);
        v
    };
    let rot = sorted(|t| t.rot_err_deg);
    let pos = sorted(|t| t.pos_err_pct);
    println!(
        "[{name}] {localized}/{n} localised, {good}/{n} within 1 % of the distance and 0.5 deg; rotation error median {:.3} max {:.3} deg; position error median {:.3} max {:.3} %",
        rot.get(rot.len() / 2).copied().unwrap_or(f64::NAN),
        rot.last().copied().unwrap_or(f64::NAN),
        pos.get(pos.len() / 2).copied().unwrap_or(f64::NAN),
        pos.last().copied().unwrap_or(f64::NAN),
    );
    assert!(
        wrong.is_empty(),
        "[{name}] localised with errors over 2 deg or 5 %: trials {wrong:?}"
    );
    assert!(
        good * 10 >= n * 9,
        "[{name}] only {good}/{n} within 1 % and 0.5 deg"
    );
}

/// The experiment: 50 hidden poses near the mapped flight, and 10
/// places outside the map (beyond the scene's far side, looking away from
/// everything the segment saw: no mapped point in view) that must come back
/// "not localised". About 25 s in `--release` with the map.
#[test]
fn simulator_shots_localise() -> anyhow::Result<()> {
    let m = mapped()?;
    let trials = localise_near(m, &m.sc.renderer, &m.sc.camera, 50, 0x5eed)?;
    judge("map camera", &trials);

    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&m.map, &vocabulary);
    let params = shot::LocalizeParams::default();
    let mut rng = StdRng::seed_from_u64(0x0075);
    let mut outside_wrong = Vec::new();
    let (mut done, mut attempts) = (0, 0);
    while done < 10 {
        attempts += 1;
        anyhow::ensure!(attempts < 500, "no unmapped view found");
        let yaw = rng.random_range(0.0..std::f64::consts::TAU);
        let r = rng.random_range(40.0..110.0);
        let eye = Point3::new(r * yaw.cos(), r * yaw.sin(), -rng.random_range(12.0..40.0));
        let look = yaw + rng.random_range(-0.6..0.6);
        let hidden = camera_from_yaw_pitch(eye, look, rng.random_range(30f64..60.0).to_radians());
        if !visible_point_indices(&m.sc.world, &m.sc.camera, &m.points_world, &hidden).is_empty() {
            continue;
        }
        let img = m.sc.renderer.render_noisy(&hidden, 90_000 + done as u64);
        match shot::localize(&m.map, &img, None, Some(&index), &params)? {
            Localization::Localized(p) => {
                println!(
                    "outside {done}: eye ({:.0}, {:.0}, {:.0}) LOCALISED with {} inliers (wrong)",
                    eye.x, eye.y, eye.z, p.inliers
                );
                outside_wrong.push(done);
            }
            Localization::NotLocalized { reason } => println!(
                "outside {done}: eye ({:.0}, {:.0}, {:.0}) not localised: {reason}",
                eye.x, eye.y, eye.z
            ),
        }
        done += 1;
    }
    assert!(
        outside_wrong.is_empty(),
        "shots of unmapped places localised: {outside_wrong:?}"
    );
    Ok(())
}

/// A photo's position prior (its GPS tag through the georeference): a
/// place found within the prior's sigma is kept, pose unchanged; the same
/// photo with a tag 40 m away (sigma 5 m) is refused as far from its
/// prior, at the distance the map measures. Five hidden poses near the
/// flight that localise without a prior.
#[test]
fn a_position_prior_keeps_a_near_place_and_refuses_a_far_one() -> anyhow::Result<()> {
    let m = mapped()?;
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&m.map, &vocabulary);
    let to_map = m.sim.inverse();
    let mut rng = StdRng::seed_from_u64(0x9e05);
    let (mut done, mut attempts) = (0, 0);
    while done < 5 {
        attempts += 1;
        anyhow::ensure!(attempts < 100, "too few hidden poses localise");
        let (_, hidden, _, _) = hidden_pose_near(m, &mut rng);
        let img =
            m.sc.renderer
                .render_noisy(&hidden, 70_000 + attempts as u64);
        let free = shot::LocalizeParams::default();
        let Localization::Localized(p) = shot::localize(&m.map, &img, None, Some(&index), &free)?
        else {
            continue;
        };
        let with_prior = |offset: Vector3<f64>, sigma_m: f64| shot::LocalizeParams {
            position_prior: Some(shot::PositionPrior {
                centre: to_map.transform_point(&Point3::from(hidden.translation.vector + offset)),
                sigma: sigma_m / m.sim.scale,
                down: None,
                metres_per_unit: None,
            }),
            ..shot::LocalizeParams::default()
        };
        // A tag 1.5 m off with a 2 m sigma: the same pose (the first
        // candidates agree with the tag, so nothing else is tried).
        let near = with_prior(Vector3::new(1.0, -1.0, 0.5), 2.0);
        match shot::localize(&m.map, &img, None, Some(&index), &near)? {
            Localization::Localized(q) => assert_eq!(q.world_from_cam, p.world_from_cam),
            Localization::NotLocalized { reason } => {
                panic!("hidden pose {done}: refused with a near prior: {reason}")
            }
        }
        // A tag 40 m away along the ground with a 5 m sigma.
        let far = with_prior(Vector3::new(32.0, 24.0, 0.0), 5.0);
        match shot::localize(&m.map, &img, None, Some(&index), &far)? {
            Localization::NotLocalized {
                reason:
                    shot::NotLocalizedReason::FarFromPrior {
                        distance, sigmas, ..
                    },
            } => {
                let metres = distance * m.sim.scale;
                println!("hidden pose {done}: far tag refused at {metres:.2} m, {sigmas:.2} sigma");
                assert!((metres - 40.0).abs() < 1.0, "{metres} m");
                assert!((7.5..8.5).contains(&sigmas), "{sigmas}");
            }
            other => panic!("hidden pose {done}: a tag 40 m away gave {other:?}"),
        }
        done += 1;
    }
    Ok(())
}

/// Photos from another camera (the operator's own, intrinsics given):
/// 800x600, a narrower field of view (fx = 640 px, 64 degrees across), a
/// stronger barrel distortion and an off-centre principal point, rendered
/// from hidden poses near the flight and localised with those intrinsics:
/// the same bounds as the map camera's shots, over 20 trials.
#[test]
fn photos_from_another_camera_localise() -> anyhow::Result<()> {
    let m = mapped()?;
    let other = SimCamera {
        width: 800,
        height: 600,
        fx: 640.0,
        fy: 640.0,
        cx: 410.0,
        cy: 290.0,
        k1: -0.12,
        k2: 0.03,
        p1: 0.0,
        p2: 0.0,
        k3: 0.0,
    };
    let renderer = Renderer::new(m.sc.world.clone(), other, RenderParams::default());
    let camera = map_camera(&other)?;
    let trials = localise_near(m, &renderer, &camera, 20, 0xca3e)?;
    judge("800x600 camera", &trials);
    Ok(())
}

/// How far a view is from the viewpoints the map was made from: for each
/// mapped point the camera at `world_from_cam` sees (unoccluded, in the
/// image), the smallest angle between its ray to the point and the ray of a
/// keyframe that observed the point (the keyframes' TRUE centres); the
/// median over those points, degrees, with their number. Ground truth and
/// the map only: no localisation result enters it.
fn viewpoint_change(m: &Mapped, camera: &Camera, world_from_cam: &Isometry3<f64>) -> (usize, f64) {
    let visible = visible_point_indices(&m.sc.world, camera, &m.points_world, world_from_cam);
    let eye = world_from_cam.translation.vector;
    let mut angles: Vec<f64> = visible
        .iter()
        .map(|&j| {
            let p = m.points_world[j].coords;
            let ray = (p - eye).normalize();
            m.point_observers[j]
                .iter()
                .map(|c| ray.angle(&(p - c).normalize()).to_degrees())
                .fold(f64::INFINITY, f64::min)
        })
        .collect();
    angles.sort_by(f64::total_cmp);
    let median = angles.get(angles.len() / 2).copied().unwrap_or(f64::NAN);
    (visible.len(), median)
}

/// Localises `img` (a photo of the map camera) as `shotpilot shot --photo`
/// does and compares it with `truth`; prints `row` with the outcome.
fn localise_photo(
    m: &Mapped,
    map: &Map,
    index: &BowIndex<'_>,
    img: &image::GrayImage,
    truth: &Isometry3<f64>,
    row: &str,
) -> anyhow::Result<Trial> {
    let params = shot::LocalizeParams::default();
    let dist = distance_to_scene(&m.sc.world, &m.sc.camera, truth);
    Ok(
        match shot::localize_with_camera(map, &map.camera, img, None, Some(index), &params)? {
            Localization::Localized(p) => {
                let est = m.sim.transform_pose(&p.world_from_cam);
                let rot_err = est.rotation.angle_to(&truth.rotation).to_degrees();
                let pos_err =
                    (est.translation.vector - truth.translation.vector).norm() / dist * 100.0;
                println!(
                    "{row}  {dist:6.1}  yes        {:7}  {:7.3}  {rot_err:11.4}  {pos_err:13.3}",
                    p.inliers, p.reprojection_rmse_px,
                );
                Trial {
                    localized: true,
                    rot_err_deg: rot_err,
                    pos_err_pct: pos_err,
                }
            }
            Localization::NotLocalized { reason } => {
                println!("{row}  {dist:6.1}  no: {reason}");
                Trial {
                    localized: false,
                    rot_err_deg: f64::NAN,
                    pos_err_pct: f64::NAN,
                }
            }
        },
    )
}

/// Frames of the same rendered flight that were held out of the map: the
/// map is SLAM's run over the explore flight's first 30 s (a frame every
/// 0.15 s, 201 frames); the queries are the flight's LATER frames (t = 30.15
/// to 90 s on the same frame clock, with the same noise sequence; none was
/// given to SLAM), localised as photos exactly as `shotpilot shot --photo`
/// does (the map read back from its file, the map camera, no mask, BoW
/// candidates), and compared with the simulator's true poses after the
/// map's Sim(3) alignment (`judge`'s tolerances: 1 % of the distance to the
/// scene and 0.5 degree for 90 %, nothing localised beyond 5 % or 2 degrees).
///
/// Which later frames "see the same scene" is decided from the ground truth
/// and the map alone, before any localisation ([`viewpoint_change`]): a
/// frame is kept when its true view holds at least 150 mapped points (the
/// hidden-pose trials' rule) AND the median angle between its rays to those
/// points and the rays of the keyframes that observed them is no larger
/// than the largest such angle among the 50 hidden poses of
/// [`simulator_shots_localise`] (the neighbourhood of the flight that
/// experiment covers; computed here from the same generator and seed).
/// On this figure-of-eight the rule keeps the frames just after the mapped
/// segment and those where the loop closes over its start; in between, the
/// flight sees the mapped ground from 20-70 degrees away, beyond what ORB
/// descriptors match.
///
/// Those wider views are checked too, for the gate only: every 4th later
/// frame with at least 150 mapped points in view, whatever its viewpoint;
/// most come back "not localised", and none may be localised beyond 5 % or
/// 2 degrees. About 10 s in `--release` with the map.
#[test]
fn held_out_later_frames_localise() -> anyhow::Result<()> {
    let m = mapped()?;
    let tmp = tempfile::tempdir()?;
    let path = tmp.path().join("sim.map");
    mapfile::save(&m.map, &path)?;
    let map = mapfile::load(&path)?;
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&map, &vocabulary);
    let camera = map.camera;
    let min_visible = 150;

    // The envelope of the hidden-pose trials (same draws as `localise_near`).
    let mut rng = StdRng::seed_from_u64(0x5eed);
    let mut max_change: f64 = 0.0;
    let (mut drawn, mut attempts) = (0, 0);
    while drawn < 50 {
        attempts += 1;
        anyhow::ensure!(attempts < 1000, "too few poses see the map");
        let (_, hidden, _, _) = hidden_pose_near(m, &mut rng);
        let (visible, change) = viewpoint_change(m, &camera, &hidden);
        if visible < min_visible {
            continue;
        }
        max_change = max_change.max(change);
        drawn += 1;
    }

    let first = ((SETUP.t1 - SETUP.t0) / SETUP.dt).floor() as usize + 1;
    let last = ((m.sc.path.end() - SETUP.t0) / SETUP.dt).round() as usize;
    let mut kept = Vec::new();
    let mut wide = Vec::new();
    let (mut few_points, mut far_view) = (0, 0);
    for i in first..=last {
        let t = SETUP.t0 + SETUP.dt * i as f64;
        let truth = m.sc.path.world_from_cam(t);
        let (visible, change) = viewpoint_change(m, &camera, &truth);
        if visible < min_visible {
            few_points += 1;
        } else if change > max_change {
            far_view += 1;
            if (i - first).is_multiple_of(4) {
                wide.push((i, t, truth, visible, change));
            }
        } else {
            kept.push((i, t, truth, visible, change));
        }
    }
    println!(
        "held-out later frames t = {:.2}..{:.2} s: {} frames; kept {} (>= {min_visible} mapped points in view, median viewpoint change <= {max_change:.2} deg, the largest of the 50 hidden poses); excluded {} ({few_points} with fewer points in view, {far_view} seen from further away)",
        SETUP.t0 + SETUP.dt * first as f64,
        SETUP.t0 + SETUP.dt * last as f64,
        last + 1 - first,
        kept.len(),
        few_points + far_view,
    );
    let header = "frame   t_s  visible  view_change_deg  dist_m  localized  inliers  rmse_px  rot_err_deg  pos_err_%dist";
    println!("{header}");
    let mut trials = Vec::new();
    for (i, t, truth, visible, change) in &kept {
        let img = m.sc.renderer.render_noisy(truth, 1000 + *i as u64);
        let row = format!("{i:5} {t:5.2}  {visible:7}  {change:15.2}");
        trials.push(localise_photo(m, &map, &index, &img, truth, &row)?);
    }
    println!(
        "wider views (every 4th later frame with >= {min_visible} mapped points in view and a larger viewpoint change; gate check only):"
    );
    println!("{header}");
    let mut wrong = Vec::new();
    let mut wide_localised = 0;
    for (i, t, truth, visible, change) in &wide {
        let img = m.sc.renderer.render_noisy(truth, 1000 + *i as u64);
        let row = format!("{i:5} {t:5.2}  {visible:7}  {change:15.2}");
        let trial = localise_photo(m, &map, &index, &img, truth, &row)?;
        if trial.localized {
            wide_localised += 1;
            if trial.rot_err_deg > 2.0 || trial.pos_err_pct > 5.0 {
                wrong.push(*i);
            }
        }
    }
    println!(
        "[wider views] {wide_localised}/{} localised, {} of them beyond 2 deg or 5 %",
        wide.len(),
        wrong.len()
    );
    assert!(
        kept.len() >= 10,
        "only {} later frames see the mapped scene",
        kept.len()
    );
    judge("held-out later frames", &trials);
    assert!(
        wrong.is_empty(),
        "wider views localised beyond 2 deg or 5 %: frames {wrong:?}"
    );
    Ok(())
}

/// Orbit period of the held-out orbit experiment, seconds: 40 s for the
/// sim's 60 m radius at 30 m altitude (9.4 m/s, 9 degrees of azimuth a
/// second); at 10 frames per second the camera moves 0.94 m and turns 0.9
/// degree between frames, as on the explore flight at its 0.15 s step.
const ORBIT_PERIOD_S: f64 = 40.0;
/// Share of the first lap that makes the map.
const ORBIT_MAPPED_SHARE: f64 = 0.75;
/// Every how many frames a later frame is queried.
const ORBIT_QUERY_EVERY: usize = 4;

/// Frames held out of the map on a flight that revisits its scene: the
/// sim's `orbit` (radius 60 m, altitude 30 m, looking at the scene centre;
/// the lap shortened to [`ORBIT_PERIOD_S`] through `paths::Params`) flown
/// for two laps at 10 frames per second, 640x480.
///
/// The map is SLAM's run over the first 75 % of the first lap (t = 0 to
/// 30 s, 301 frames, 270 degrees of azimuth): "the first part" of the
/// flight, leaving a quarter the map never saw to test the gate on. Not the
/// whole lap: SLAM has no loop closing, so a full lap ends on a seam where
/// its drift meets its own start with duplicated points (measured with the
/// whole lap, 401 frames, as the map: keyframe centres 0.085 m RMSE against
/// 0.046 m; the second lap on the circle still 100/100, but its worst
/// position error 0.79 % of the distance against 0.30 %; 6 m in and down
/// 43/47).
///
/// The queries, fixed before any localisation: every 4th frame of the
/// flight after the map (every 8th on the off-circle laps), split by where
/// the camera truly is:
///
/// * the second lap over the mapped arc (t = 40 to 70 s, 0 to 270 degrees,
///   75 frames). The video's frame clock runs half a frame out of step with
///   the lap (t = 40.05, 40.45, ...), so no query repeats a viewpoint SLAM
///   saw: each lies midway between two frames of the first lap;
/// * the same second lap flown off the mapped circle, 6 m wider and 6 m
///   higher, then 6 m closer and 6 m lower, still looking at the centre
///   (38 frames each): viewpoints the first lap never had;
/// * the unmapped quarter of the first lap (t = 30 to 40 s, 270 to 360
///   degrees, up to 47 degrees of azimuth from any keyframe): the gate
///   only, nothing localised beyond 5 % or 2 degrees; the counts of
///   localised and refused frames are printed.
///
/// Frames are excluded by two rules from the ground truth alone, counted
/// and printed: a pose no drone can take (the camera less than 2 m above a
/// roof within 2 m, the sim's own clearance check of its flights: the orbit
/// ignores buildings) and a view that does not see the mapped scene (fewer
/// than 150 mapped points in the TRUE view, unoccluded, inside the image:
/// the hidden-pose trials' rule). On this world they exclude only 3 frames
/// of the lower lap (azimuth 195-210 degrees, the camera 0.6 m over a
/// 23.4 m roof, the scene 1.4 m away). The first rule was added after a
/// run on world 2 showed a lap inside a building. The map must also have
/// been tracked through (at most 5 of its frames untracked), or the test
/// stops with that error.
///
/// Each query is localised as `shotpilot shot --photo` does (the map read
/// back from its file, the map camera, no mask, BoW candidates) and
/// compared with the orbit's true pose after the map's Sim(3) alignment.
/// The three second laps carry the bounds ([`judge`]: at least
/// 90 % within 1 % of the distance to the scene and 0.5 degree, none
/// localised beyond 5 % or 2 degrees). Measured: on the circle 75/75
/// (rotation error median 0.046, max 0.132 degree; position median 0.087,
/// max 0.301 % of the distance); 6 m out and up 38/38 (max 0.132 degree,
/// 0.198 %); 6 m in and down 33/35 (two refused, 3 excluded; max 0.101 degree,
/// 0.509 %); the unmapped quarter 11/25 localised, the 14 others refused,
/// none beyond 2 degrees or 5 % (worst 0.21 degree and 1.5 %, 21 degrees
/// of azimuth from the nearest keyframe). About 25 s to render and map,
/// 45 s in all, in `--release`.
///
/// Other worlds (not run here; change the seed of `scene_on` below): world
/// 2, on the circle 75/75 localised, 73/75 within the bounds (two at 1.4
/// and 1.6 % of an 8-9 m distance to a wall, 0.2 degree), 6 m out and up
/// 38/38, 6 m in and down 33/33 (5 excluded: inside a 26.5 m building),
/// the unmapped quarter 13/25 localised, none wrong; world 3, the orbit's
/// circle runs through a 31.9 m building at azimuth 171-195 degrees, SLAM
/// loses track there (191 of 301 frames tracked) and the test stops on the
/// tracking check; flown at 40 m instead (`orbit_altitude_m`), 300/301
/// tracked and 75/75, 38/38, 38/38 within the bounds (worst 0.161 degree,
/// 0.249 %), the unmapped quarter 18/25 localised, none wrong.
#[test]
fn held_out_orbit_frames_localise() -> anyhow::Result<()> {
    let setup = Setup {
        width: 640,
        height: 480,
        t0: 0.0,
        t1: ORBIT_MAPPED_SHARE * ORBIT_PERIOD_S,
        dt: 0.1,
    };
    let path_params = PathParams {
        orbit_duration_s: ORBIT_PERIOD_S,
        ..PathParams::default()
    };
    let sc = scene_on(&setup, SEED, |_| CameraPath::orbit(path_params))?;
    let m = build_mapped_on(sc, setup, "orbit")?;
    let tmp = tempfile::tempdir()?;
    let file = tmp.path().join("orbit.map");
    mapfile::save(&m.map, &file)?;
    let map = mapfile::load(&file)?;
    let vocabulary = Vocabulary::builtin()?;
    let index = BowIndex::build(&map, &vocabulary);
    let camera = map.camera;
    // The orbit is one lap; the second lap is its first again (the path
    // clamps to its lap), so a time of the flight maps to the lap's time.
    let pose_at = |t: f64| m.sc.path.world_from_cam(t.rem_euclid(ORBIT_PERIOD_S));
    // Azimuth (degrees) of a camera centre around the scene centre, and its
    // distance in azimuth to the nearest keyframe's true centre.
    let azimuth = |p: &Vector3<f64>| p.y.atan2(p.x).to_degrees().rem_euclid(360.0);
    let kf_azimuths: Vec<f64> = m
        .kf_times
        .iter()
        .map(|&t| azimuth(&pose_at(t).translation.vector))
        .collect();
    let azimuth_gap = |truth: &Isometry3<f64>| {
        let a = azimuth(&truth.translation.vector);
        kf_azimuths
            .iter()
            .map(|k| {
                let d = (a - k).rem_euclid(360.0);
                d.min(360.0 - d)
            })
            .fold(f64::INFINITY, f64::min)
    };
    // SLAM must have tracked the mapped part through (the sim's orbit
    // ignores buildings: on some worlds it flies into one and SLAM loses
    // track; the experiment is about the localiser, given a map).
    anyhow::ensure!(
        m.tracked + 5 >= m.frames,
        "SLAM tracked only {} of the {} frames of the mapped part",
        m.tracked,
        m.frames
    );
    let mapped_frames = ((setup.t1 - setup.t0) / setup.dt).round() as usize + 1;
    let lap_frames = (ORBIT_PERIOD_S / setup.dt).round() as usize;
    let header = "frame    t_s  azimuth_deg  visible  kf_gap_deg  dist_m  localized  inliers  rmse_px  rot_err_deg  pos_err_%dist";

    // Renders the flight's frame `i` at the true pose `truth`, localises it
    // as a photo and prints its row.
    // A frame is excluded (None) and counted when a drone cannot take it
    // (the camera less than 2 m above a roof within 2 m: the sim's own
    // clearance check of its flights) or when its true view holds fewer
    // than `min_visible` mapped points (it does not see the mapped scene).
    let min_visible = 150;
    let query = |i: usize, t: f64, truth: Isometry3<f64>| -> anyhow::Result<Option<Trial>> {
        let visible = visible_point_indices(&m.sc.world, &camera, &m.points_world, &truth).len();
        let gap = azimuth_gap(&truth);
        let p = truth.translation.vector;
        let az = azimuth(&p);
        let row = format!("{i:5} {t:6.2}  {az:11.1}  {visible:7}  {gap:10.1}");
        let roof = m.sc.world.max_height_near(p.x, p.y, 2.0);
        if -p.z < roof + 2.0 {
            println!(
                "{row}  excluded: the camera at {:.1} m, a {roof:.1} m roof within 2 m",
                -p.z
            );
            return Ok(None);
        }
        if visible < min_visible {
            let dist = distance_to_scene(&m.sc.world, &m.sc.camera, &truth);
            println!("{row}  {dist:6.1}  excluded: fewer than {min_visible} mapped points in view");
            return Ok(None);
        }
        let img = m.sc.renderer.render_noisy(&truth, 1000 + i as u64);
        Ok(Some(localise_photo(&m, &map, &index, &img, &truth, &row)?))
    };
    // Runs `query` over `frames`; returns the trials and the number excluded.
    let run = |frames: Vec<(usize, f64, Isometry3<f64>)>| -> anyhow::Result<(Vec<Trial>, usize)> {
        let n = frames.len();
        let mut trials = Vec::new();
        for (i, t, truth) in frames {
            trials.extend(query(i, t, truth)?);
        }
        let excluded = n - trials.len();
        Ok((trials, excluded))
    };

    // The unmapped quarter of the first lap.
    println!("unmapped quarter of the first lap (gate only):");
    println!("{header}");
    let (unmapped, unmapped_excluded) = run((mapped_frames..lap_frames)
        .step_by(ORBIT_QUERY_EVERY)
        .map(|i| {
            let t = setup.t0 + setup.dt * i as f64;
            (i, t, pose_at(t))
        })
        .collect())?;

    // The second lap over the mapped arc, half a frame out of step.
    println!("second lap over the mapped arc (the issue's bounds):");
    println!("{header}");
    let (revisit, revisit_excluded) = run((0..mapped_frames - 1)
        .step_by(ORBIT_QUERY_EVERY)
        .map(|k| {
            let i = lap_frames + k;
            let t = setup.t0 + setup.dt * (i as f64 + 0.5);
            (i, t, pose_at(t))
        })
        .collect())?;

    // The second lap off the mapped circle: 6 m higher and 6 m further
    // out, then 6 m lower and 6 m closer, still looking at the centre;
    // every 8th frame over the mapped arc.
    let mut off_circle = Vec::new();
    for (dr, dh) in [(6.0, 6.0), (-6.0, -6.0)] {
        let off = CameraPath::orbit(PathParams {
            orbit_radius_m: path_params.orbit_radius_m + dr,
            orbit_altitude_m: path_params.orbit_altitude_m + dh,
            ..path_params
        });
        println!(
            "second lap {dr:+} m in radius, {dh:+} m in altitude, over the mapped arc (the issue's bounds):"
        );
        println!("{header}");
        let (trials, excluded) = run((0..mapped_frames - 1)
            .step_by(2 * ORBIT_QUERY_EVERY)
            .map(|k| {
                let i = lap_frames + k;
                let t = setup.t0 + setup.dt * (i as f64 + 0.5);
                (i, t, off.world_from_cam(t.rem_euclid(ORBIT_PERIOD_S)))
            })
            .collect())?;
        off_circle.push((
            format!("orbit second lap {dr:+} m radius {dh:+} m altitude"),
            trials,
            excluded,
        ));
    }

    let unmapped_localised = unmapped.iter().filter(|t| t.localized).count();
    let unmapped_wrong: Vec<usize> = unmapped
        .iter()
        .enumerate()
        .filter(|(_, t)| t.localized && (t.rot_err_deg > 2.0 || t.pos_err_pct > 5.0))
        .map(|(k, _)| k)
        .collect();
    let unmapped_good = unmapped
        .iter()
        .filter(|t| t.localized && t.rot_err_deg <= 0.5 && t.pos_err_pct <= 1.0)
        .count();
    println!(
        "[unmapped quarter] {unmapped_localised}/{} localised ({unmapped_good} within 1 % and 0.5 deg), {} beyond 2 deg or 5 %; {unmapped_excluded} excluded",
        unmapped.len(),
        unmapped_wrong.len()
    );
    println!("[orbit second lap] {revisit_excluded} excluded");
    judge("orbit second lap", &revisit);
    for (name, trials, excluded) in &off_circle {
        println!("[{name}] {excluded} excluded");
        judge(name, trials);
    }
    assert!(
        unmapped_wrong.is_empty(),
        "unmapped quarter localised beyond 2 deg or 5 %: {unmapped_wrong:?}"
    );
    Ok(())
}

/// Issue 34's anchors experiment: 50 random drags of the four anchors (a
/// zoom of 1.0-1.6x, a pan of up to 20 % of the frame, a rotation of up
/// to 15 deg) on 10 keyframes of the explore map. Each gets its camera
/// from the keyframe's own geometry, before and after the map is saved
/// and loaded back (a restart). The truth is the camera that takes the
/// drawn picture best in the true world
/// ([`shotpilot::simulator::drag::drag_truth`]); a drawn pan or zoom of
/// a nearly flat scene hardly tells a turn of the camera from a move
/// across, so the pose difference to it is printed, and what is judged is
/// the picture: the shot error a camera at the estimated pose (through
/// the map's Sim(3)) would measure in the true world against the drawn
/// picture, beside the same for the true camera (the drag's floor) and for
/// the keyframe's own camera (not moving). Every drag must get a pose, the
/// same after the reload; the median must lie within 3 % of the diagonal
/// of the floor (measured: 2.2 %; the map's own error and a fit on map
/// points, not on the picture's homography) and 45 of 50 must frame the
/// picture better than not moving. The old way (the warped
/// picture matched against the map) is counted beside it. About 15 s in
/// `--release` with the map.
#[test]
fn dragged_anchors_get_a_pose_from_the_keyframe_geometry() -> anyhow::Result<()> {
    use shotpilot::simulator::drag::{DragParams, drag_truth, random_drag};
    let m = mapped()?;
    let tmp = tempfile::tempdir()?;
    let path = tmp.path().join("drags.map");
    mapfile::save(&m.map, &path)?;
    let reloaded = mapfile::load(&path)?;
    let params = shot::LocalizeParams::default();
    let camera = m.map.camera;
    let error_params = shotpilot::refine::ShotErrorParams::default();
    let mut ids: Vec<(f64, KeyFrameId)> = m
        .map
        .keyframes()
        .filter(|k| k.image.is_some())
        .map(|k| (k.timestamp, k.id))
        .collect();
    ids.sort_by(|a, b| a.0.total_cmp(&b.0));
    anyhow::ensure!(ids.len() >= 10, "{} keyframes with a picture", ids.len());
    let chosen: Vec<(f64, KeyFrameId)> = (0..10).map(|i| ids[i * ids.len() / 10]).collect();
    let mut rng = StdRng::seed_from_u64(34);
    let (mut accepted, mut by_matching, mut same_after_reload) = (0, 0, 0);
    let (mut pos_err, mut rot_err, mut framing, mut floor, mut over) =
        (Vec::new(), Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let mut refused = Vec::new();
    let mut better_than_staying = 0;
    let (mut jumps, mut jump_pct, mut jump_deg) = (0, Vec::new(), Vec::new());
    // Its own generator, so the drags stay those of the seed above.
    let mut cut = StdRng::seed_from_u64(35);
    for trial in 0..50 {
        let (t, id) = chosen[trial % 10];
        let d = random_drag(&mut rng, &camera, &DragParams::default());
        let img = m
            .map
            .keyframe(id)
            .and_then(|k| k.image.clone())
            .ok_or_else(|| anyhow::anyhow!("keyframe {} has no picture", id.0))?;
        let shot =
            shot::desired_shot_from_anchors(&img, &d.anchors, &shot::AnchorParams::default())?;
        if let Localization::Localized(_) =
            shot::localize(&m.map, &shot.image, Some(&shot.mask), None, &params)?
        {
            by_matching += 1;
        }
        let Some(truth) = drag_truth(
            &m.sc.world,
            &camera,
            &m.sc.path.world_from_cam(t),
            &shot.shot_to_source,
            &params.pnp,
            &params.pose,
        ) else {
            anyhow::bail!("drag {trial} has no truth");
        };
        let drawn = format!(
            "drag {trial:2} on keyframe {:3}: zoom {:.2} rotation {:5.1} deg pan ({:4.0}, {:4.0}) px",
            id.0, d.zoom, d.rotation_deg, d.pan_px[0], d.pan_px[1]
        );
        match (
            shot::localize_anchors(&m.map, id, &shot.shot_to_source, &params),
            shot::localize_anchors(&reloaded, id, &shot.shot_to_source, &params),
        ) {
            (Localization::Localized(p), again) => {
                accepted += 1;
                if let Localization::Localized(q) = again
                    && (q.world_from_cam.translation.vector - p.world_from_cam.translation.vector)
                        .norm()
                        < 1e-9
                    && q.world_from_cam
                        .rotation
                        .angle_to(&p.world_from_cam.rotation)
                        < 1e-9
                {
                    same_after_reload += 1;
                }
                let est = m.sim.transform_pose(&p.world_from_cam);
                let dist = distance_to_scene(&m.sc.world, &camera, &truth.world_from_cam);
                let e = (est.translation.vector - truth.world_from_cam.translation.vector).norm()
                    / dist
                    * 100.0;
                let r = est
                    .rotation
                    .angle_to(&truth.world_from_cam.rotation)
                    .to_degrees();
                let f = truth
                    .shot_error_pct(&est, &camera, &error_params)
                    .unwrap_or(f64::NAN);
                let fl = truth
                    .shot_error_pct(&truth.world_from_cam, &camera, &error_params)
                    .unwrap_or(f64::NAN);
                // Not moving at all: the keyframe's own camera.
                let stay = truth
                    .shot_error_pct(&m.sc.path.world_from_cam(t), &camera, &error_params)
                    .unwrap_or(f64::NAN);
                if f < stay {
                    better_than_staying += 1;
                }
                println!(
                    "{drawn}: {} points, rmse {:.2} px, sigma {:.2} %; shot error there {f:.2} % (floor {fl:.2} %, at the keyframe {stay:.2} %); pose against the best true camera {e:.2} % / {r:.2} deg",
                    p.matches,
                    p.reprojection_rmse_px,
                    p.sigma.position_depth_fraction * 100.0
                );
                // The same drawing on the map a little changed (5 % of
                // the keyframe's points gone, as a shutdown's culling and
                // adjustment leave it): the desired camera should stay
                // where it was, not jump to another explanation.
                for _ in 0..2 {
                    let changed = with_points_culled(&m.map, id, 0.05, &mut cut);
                    match shot::localize_anchors(&changed, id, &shot.shot_to_source, &params) {
                        Localization::Localized(c) => {
                            let est_c = m.sim.transform_pose(&c.world_from_cam);
                            let (jp, jr) = pose_moved(&est, &est_c, dist);
                            if jp > 1.0 || jr > 1.0 {
                                println!(
                                    "{drawn}: the changed map moved it {jp:.2} % / {jr:.2} deg"
                                );
                                jumps += 1;
                            }
                            jump_pct.push(jp);
                            jump_deg.push(jr);
                        }
                        Localization::NotLocalized { reason } => {
                            println!("{drawn}: refused on the changed map: {reason}");
                            jumps += 1;
                        }
                    }
                }
                pos_err.push(e);
                rot_err.push(r);
                framing.push(f);
                floor.push(fl);
                over.push(f - fl);
            }
            (Localization::NotLocalized { reason }, _) => {
                println!("{drawn}: refused: {reason}");
                refused.push(trial);
            }
        }
    }
    let q = |v: &mut Vec<f64>, f: f64| {
        v.sort_by(f64::total_cmp);
        v.get(((v.len() as f64 - 1.0) * f).round() as usize)
            .copied()
            .unwrap_or(f64::NAN)
    };
    println!(
        "drags: {accepted}/50 given a pose ({same_after_reload} the same after the reload), {by_matching}/50 by matching the warped picture"
    );
    println!(
        "shot error at the pose (% of the diagonal) median {:.2} / p90 {:.2} / max {:.2}; the truth's floor median {:.2} / p90 {:.2} / max {:.2}; above the floor median {:.2} / p90 {:.2} / max {:.2}",
        q(&mut framing, 0.5),
        q(&mut framing, 0.9),
        q(&mut framing, 1.0),
        q(&mut floor, 0.5),
        q(&mut floor, 0.9),
        q(&mut floor, 1.0),
        q(&mut over, 0.5),
        q(&mut over, 0.9),
        q(&mut over, 1.0)
    );
    println!(
        "pose against the best true camera: median {:.2} % / {:.2} deg, p90 {:.2} % / {:.2} deg",
        q(&mut pos_err, 0.5),
        q(&mut rot_err, 0.5),
        q(&mut pos_err, 0.9),
        q(&mut rot_err, 0.9)
    );
    println!(
        "the pose frames the picture better than the keyframe's own camera in {better_than_staying}/50"
    );
    println!(
        "on a map with 5 % of the keyframe's points gone: {jumps}/100 moved over 1 % or 1 deg; moved median {:.3} % / {:.3} deg, p90 {:.3} % / {:.3} deg, max {:.3} % / {:.3} deg",
        q(&mut jump_pct, 0.5),
        q(&mut jump_deg, 0.5),
        q(&mut jump_pct, 0.9),
        q(&mut jump_deg, 0.9),
        q(&mut jump_pct, 1.0),
        q(&mut jump_deg, 1.0)
    );
    assert!(refused.is_empty(), "drags refused: {refused:?}");
    assert_eq!(same_after_reload, 50);
    // At the best true camera's floor (0.19 % above it, median; a chosen
    // consensus framed it 2.2 % above), and steady: 3 of 100 moved (a
    // consensus: 62).
    assert!(q(&mut over, 0.5) < 1.0, "{over:?}");
    assert!(jumps <= 10, "{jumps} of 100 moved over 1 % or 1 deg");
    assert!(better_than_staying >= 45, "{better_than_staying}");
    Ok(())
}
