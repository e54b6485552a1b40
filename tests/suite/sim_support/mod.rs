//! Simulator renders made by the tests (the `slam_*` subjects), and the
//! ground-truth lookups they share (the `slam_*` and `shot_*` subjects).
//!
//! A render lives in a temporary folder that is removed when the test that
//! made it ends (pass or fail), so a test run leaves nothing in the
//! system's temporary folder. Set `SHOTPILOT_KEEP_RENDERS=1` to keep them
//! for a look after a failure (the folder is printed).

use std::path::Path;
use std::sync::Arc;

use nalgebra::{Isometry3, Point2, Point3, Unit, Vector3};
use rand::Rng;
use rand::rngs::StdRng;
use shotpilot::camera::Camera;
use shotpilot::eval::Trajectory;
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::dataset::render_path_dataset;
use shotpilot_sim::paths::{CameraPath, Params as PathParams, PathSpec};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::world::{World, WorldKind, WorldParams};
use tempfile::TempDir;

/// The world's seed of the simulator renders made here.
pub const SEED: u64 = 5;
/// Frames of a lap ([`render_lap`]): about 116 s at 6.5 frames per second,
/// the camera moving about 0.8 m between frames.
pub const LAP_FRAMES: usize = 750;

/// A temporary folder for a render, named after the test (`prefix`);
/// removed when dropped unless `SHOTPILOT_KEEP_RENDERS` is set.
pub fn render_dir(prefix: &str) -> TempDir {
    let mut dir = tempfile::Builder::new().prefix(prefix).tempdir().unwrap();
    if std::env::var_os("SHOTPILOT_KEEP_RENDERS").is_some() {
        dir.disable_cleanup(true);
        eprintln!("{prefix}: the render stays in {}", dir.path().display());
    }
    dir
}

/// Renders `frames` frames of `path` over `world` (seed [`SEED`], the
/// default camera, sensor noise on) into `dir`.
pub fn render(world: Arc<World>, path: &CameraPath, spec: &PathSpec, frames: usize, dir: &Path) {
    let renderer = Renderer::new(world, SimCamera::default(), RenderParams::default());
    render_path_dataset(&renderer, path, frames, dir, SEED, spec).unwrap();
}

/// One lap of the `loop` path over a world of `kind` (seed [`SEED`]):
/// about 520 m around the scene at 5 m/s and 30 m, then 60 m over its start
/// again, [`LAP_FRAMES`] frames.
pub fn render_lap(kind: WorldKind, prefix: &str) -> TempDir {
    let dir = render_dir(prefix);
    let world = Arc::new(
        World::generate_with(
            SEED,
            &WorldParams {
                kind,
                ..WorldParams::default()
            },
        )
        .unwrap(),
    );
    let path = CameraPath::loop_path(&world, PathParams::default());
    render(world, &path, &PathSpec::Loop, LAP_FRAMES, dir.path());
    dir
}

/// The ground truth's position nearest in time to `t`.
pub fn gt_position(gt: &Trajectory, t: f64) -> nalgebra::Vector3<f64> {
    gt.poses
        .iter()
        .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
        .unwrap()
        .position()
}

/// Indices of `points_world` (in the true world frame) that `camera` at
/// `world_from_cam` sees unoccluded inside its image (a ray cast in the
/// true world).
pub fn visible_point_indices(
    world: &World,
    camera: &Camera,
    points_world: &[Point3<f64>],
    world_from_cam: &Isometry3<f64>,
) -> Vec<usize> {
    let cam_from_world = world_from_cam.inverse();
    let eye = Point3::from(world_from_cam.translation.vector);
    let (w, h) = (camera.width as f64, camera.height as f64);
    points_world
        .iter()
        .enumerate()
        .filter(|(_, p)| {
            let pc = cam_from_world * **p;
            let Some(px) = camera.project(&pc.coords) else {
                return false;
            };
            if !(px.x >= 0.0 && px.y >= 0.0 && px.x <= w - 1.0 && px.y <= h - 1.0) {
                return false;
            }
            let d = **p - eye;
            let dist = d.norm();
            match world.ray_cast(&eye, &(d / dist), dist * 1.1) {
                Some(hit) => hit.t > dist * 0.97,
                None => true,
            }
        })
        .map(|(i, _)| i)
        .collect()
}

/// Median distance from `camera` at `world_from_cam` to the scene over a
/// 7x7 grid of pixels (ray cast in the true world), metres; NaN when no
/// ray hits.
pub fn distance_to_scene(world: &World, camera: &Camera, world_from_cam: &Isometry3<f64>) -> f64 {
    let eye = Point3::from(world_from_cam.translation.vector);
    let (w, h) = (camera.width as f64, camera.height as f64);
    let mut d = Vec::new();
    for j in 0..7 {
        for i in 0..7 {
            let px = Point2::new((i as f64 + 0.5) * w / 7.0, (j as f64 + 0.5) * h / 7.0);
            let ray = world_from_cam.rotation * camera.unproject(px).into_inner();
            if let Some(hit) = world.ray_cast(&eye, &ray, 2000.0) {
                d.push(hit.t);
            }
        }
    }
    d.sort_by(f64::total_cmp);
    d.get(d.len() / 2).copied().unwrap_or(f64::NAN)
}

/// A direction drawn uniformly on the unit sphere.
pub fn random_unit(rng: &mut StdRng) -> Unit<Vector3<f64>> {
    loop {
        let v = Vector3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        );
        let n: f64 = v.norm();
        if n > 0.1 && n <= 1.0 {
            return Unit::new_normalize(v);
        }
    }
}

/// The map-error constants of a photo's sigma, with
/// `SHOT_MAP_NOISE_REF=PX` setting the reference reprojection noise they
/// are scaled by (`inf`: not scaled), for a before/after of the scaling.
pub fn map_sigma_from_env() -> anyhow::Result<shotpilot::shot::MapSigma> {
    let mut s = shotpilot::shot::MapSigma::default();
    if let Ok(v) = std::env::var("SHOT_MAP_NOISE_REF") {
        s.reference_noise_px = v.trim().parse()?;
    }
    Ok(s)
}

/// A photo's position prior as its GPS tag would give it: the true camera
/// centre `truth` (the ground truth's frame, metres) moved by a Gaussian
/// error of `sigma_m` per axis drawn from `rng` (Box-Muller, x then y then
/// z), into the map's frame through `map_to_truth`.
pub fn simulated_tag(
    truth: &Vector3<f64>,
    map_to_truth: &shotpilot::geometry::Sim3,
    sigma_m: f64,
    rng: &mut StdRng,
) -> shotpilot::shot::PositionPrior {
    let mut normal = || -> f64 {
        let (u1, u2): (f64, f64) = (rng.random::<f64>().max(1e-300), rng.random());
        (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
    };
    let noise = Vector3::new(normal(), normal(), normal()) * sigma_m;
    shotpilot::shot::PositionPrior {
        centre: map_to_truth
            .inverse()
            .transform_point(&Point3::from(truth + noise)),
        sigma: sigma_m / map_to_truth.scale,
        down: None,
        metres_per_unit: Some(map_to_truth.scale),
    }
}

/// The localisation's PnP RANSAC settings, with `SHOT_PNP_MIN_INLIERS=N`
/// setting the fewest inliers of a candidate's first pose, for a
/// before/after.
pub fn pnp_from_env() -> anyhow::Result<shotpilot::geometry::PnpParams> {
    let mut p = shotpilot::shot::LocalizeParams::default().pnp;
    if let Ok(v) = std::env::var("SHOT_PNP_MIN_INLIERS") {
        p.min_inliers = v.trim().parse()?;
    }
    Ok(p)
}

/// The localisation's gate, with `SHOT_GATE=POS,ROT,RATIO` setting its
/// largest position sigma (fraction of the distance), largest rotation
/// sigma (degrees) and smallest inlier ratio, for a before/after.
pub fn gate_from_env() -> anyhow::Result<shotpilot::shot::GateParams> {
    let mut g = shotpilot::shot::GateParams::default();
    if let Ok(v) = std::env::var("SHOT_GATE") {
        let parts: Vec<f64> = v
            .split(',')
            .map(|p| p.trim().parse::<f64>())
            .collect::<Result<_, _>>()?;
        let [pos, rot, ratio] = parts[..] else {
            anyhow::bail!("SHOT_GATE=POS,ROT,RATIO");
        };
        g.max_position_sigma_depth_fraction = pos;
        g.max_rotation_sigma_deg = rot;
        g.min_inlier_ratio = ratio;
    }
    Ok(g)
}

/// `map` with each map point keyframe `kf` observes erased with
/// probability `share` (roughly what a shutdown's culling and adjustment
/// do): for checking that a result does not hang on a few points.
pub fn with_points_culled(
    map: &shotpilot::slam::Map,
    kf: shotpilot::slam::KeyFrameId,
    share: f64,
    rng: &mut StdRng,
) -> shotpilot::slam::Map {
    let mut changed = map.clone();
    let points: Vec<_> = map
        .keyframe(kf)
        .map(|k| k.points.iter().flatten().copied().collect())
        .unwrap_or_default();
    for p in points {
        if rng.random_bool(share) {
            changed.erase_point(p);
        }
    }
    changed
}

/// How far camera `b` stands from camera `a`: the centres' distance as a
/// percentage of `scale`, and the angle between them, degrees.
pub fn pose_moved(a: &Isometry3<f64>, b: &Isometry3<f64>, scale: f64) -> (f64, f64) {
    (
        (b.translation.vector - a.translation.vector).norm() / scale * 100.0,
        b.rotation.angle_to(&a.rotation).to_degrees(),
    )
}
