//! An operator's drag of the four anchors, drawn at random, and its truth
//! in the simulated world: what the scenario's and the tests' anchors
//! trials draw.
//!
//! A drag is a zoom about the frame's centre, a rotation and a pan of the
//! frame on the keyframe ([`random_drag`]). Its truth ([`drag_truth`]) is
//! the camera that takes the drawn picture best in the true world: a grid
//! of the picture's pixels, each at the true scene point the keyframe's
//! true camera sees through the anchors' transform, and the PnP of those
//! pairs (RANSAC, then motion-only BA). A drawn zoom of a scene with depth
//! is no camera's view, so that camera is the best one, not an exact one.

use nalgebra::{Isometry3, Matrix3, Point2, Point3, Rotation2, Vector2};
use rand::Rng;
use shotpilot_sim::world::World;

use crate::camera::Camera;
use crate::geometry::homography4::apply_homography;
use crate::geometry::{PnpParams, find_homography, solve_pnp_ransac};
use crate::optimize::{Intrinsics, PoseObservation, PoseParams, optimize_pose};
use crate::refine::{ShotErrorParams, corner_error};
use crate::shot::frame_corners;

/// Bounds of a random drag (each drawn uniformly up to its bound).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DragParams {
    /// Largest zoom (1: none).
    pub max_zoom: f64,
    /// Largest pan, as a fraction of the frame's width and height.
    pub max_pan_fraction: f64,
    /// Largest rotation of the frame, degrees.
    pub max_rotation_deg: f64,
}

impl Default for DragParams {
    fn default() -> Self {
        Self {
            max_zoom: 1.6,
            max_pan_fraction: 0.2,
            max_rotation_deg: 15.0,
        }
    }
}

/// One drag: what was drawn and the four anchors on the keyframe (where
/// the picture's corners (0,0), (w-1,0), (w-1,h-1), (0,h-1) go).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Drag {
    /// The zoom.
    pub zoom: f64,
    /// The rotation, degrees.
    pub rotation_deg: f64,
    /// The pan, pixels.
    pub pan_px: [f64; 2],
    /// The anchors, keyframe pixels.
    pub anchors: [Point2<f64>; 4],
}

fn sym<R: Rng>(rng: &mut R, r: f64) -> f64 {
    if r > 0.0 {
        rng.random_range(-r..r)
    } else {
        0.0
    }
}

/// A random drag on a `camera`-sized keyframe.
pub fn random_drag<R: Rng>(rng: &mut R, camera: &Camera, params: &DragParams) -> Drag {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let zoom = 1.0 + rng.random_range(0.0..1.0) * (params.max_zoom - 1.0).max(0.0);
    let rotation_deg = sym(rng, params.max_rotation_deg);
    let pan = Vector2::new(
        sym(rng, params.max_pan_fraction * w),
        sym(rng, params.max_pan_fraction * h),
    );
    let centre = Vector2::new((w - 1.0) / 2.0, (h - 1.0) / 2.0);
    let turn = Rotation2::new(rotation_deg.to_radians());
    let mut anchors = [Point2::origin(); 4];
    for (a, c) in anchors
        .iter_mut()
        .zip(frame_corners(camera.width, camera.height).iter())
    {
        *a = Point2::from(centre + pan + turn * (c.coords - centre) / zoom);
    }
    Drag {
        zoom,
        rotation_deg,
        pan_px: [pan.x, pan.y],
        anchors,
    }
}

/// The truth of a drag: the camera that takes the drawn picture best in
/// the true world, and the pairs it was fitted on (true scene points and
/// where the picture shows them).
#[derive(Debug, Clone, PartialEq)]
pub struct DragTruth {
    /// That camera, the simulator's world.
    pub world_from_cam: Isometry3<f64>,
    /// Scene points (world) and the picture's undistorted pixels showing them.
    pub pairs: Vec<(Point3<f64>, Point2<f64>)>,
}

impl DragTruth {
    /// The shot error a camera at `world_from_cam` (the simulator's world)
    /// would measure against the drawn picture, % of the diagonal: the
    /// corner error of the homography (RANSAC, as the loop's shot error)
    /// from the picture's pixels of the pairs to where that camera sees
    /// their scene points. None with too few pairs in front of it. For
    /// [`DragTruth::world_from_cam`] itself it is the drag's floor.
    pub fn shot_error_pct(
        &self,
        world_from_cam: &Isometry3<f64>,
        camera: &Camera,
        params: &ShotErrorParams,
    ) -> Option<f64> {
        let cam_from_world = world_from_cam.inverse();
        let (mut desired, mut seen) = (Vec::new(), Vec::new());
        for (x, u) in &self.pairs {
            if let Some(p) = camera.project_ideal(&(cam_from_world * x).coords) {
                desired.push(*u);
                seen.push(p);
            }
        }
        let fit = find_homography(&desired, &seen, &params.homography, params.seed).ok()?;
        let n = desired.len();
        corner_error(
            &fit.h21,
            camera.width,
            camera.height,
            Some(camera),
            fit.n_inliers,
            n,
            (n, n),
        )
        .ok()
        .map(|r| r.corner_error_pct)
    }
}

/// The truth of the picture drawn with `shot_to_keyframe` (`H`: picture
/// pixel → keyframe pixel) on a keyframe whose true camera is
/// `world_from_keyframe`, both with `camera`; see the module
/// documentation. None when fewer than 12 of the grid's pixels see the
/// scene or the PnP fails.
pub fn drag_truth(
    world: &World,
    camera: &Camera,
    world_from_keyframe: &Isometry3<f64>,
    shot_to_keyframe: &Matrix3<f64>,
    pnp: &PnpParams,
    pose: &PoseParams,
) -> Option<DragTruth> {
    let (w, h) = (f64::from(camera.width), f64::from(camera.height));
    let origin = Point3::from(world_from_keyframe.translation.vector);
    let (mut xn, mut obs) = (Vec::new(), Vec::new());
    for i in 0..24 {
        for j in 0..18 {
            let d = Point2::new(
                (f64::from(i) + 0.5) * w / 24.0,
                (f64::from(j) + 0.5) * h / 18.0,
            );
            let Some(a) = apply_homography(shot_to_keyframe, &d) else {
                continue;
            };
            if !camera.contains(a, 0.0) {
                continue;
            }
            let ray = world_from_keyframe.rotation * camera.unproject(a).into_inner();
            let Some(hit) = world.ray_cast(&origin, &ray, 5000.0) else {
                continue;
            };
            let u = camera.undistort_pixel(d);
            xn.push(Point2::new(
                (u.x - camera.cx) / camera.fx,
                (u.y - camera.cy) / camera.fy,
            ));
            obs.push(PoseObservation {
                p_world: hit.p_world,
                uv: u,
                inv_sigma2: 1.0,
            });
        }
    }
    if obs.len() < 12 {
        return None;
    }
    let intr = Intrinsics {
        fx: camera.fx,
        fy: camera.fy,
        cx: camera.cx,
        cy: camera.cy,
    };
    let pw: Vec<Point3<f64>> = obs.iter().map(|o| o.p_world).collect();
    let start = solve_pnp_ransac(&pw, &xn, camera.fx, pnp, 1)
        .map(|r| r.cam_from_world)
        .unwrap_or(world_from_keyframe.inverse());
    let fit = optimize_pose(start, &obs, &intr, pose).ok()?;
    Some(DragTruth {
        world_from_cam: fit.cam_from_world.inverse(),
        pairs: obs.iter().map(|o| (o.p_world, o.uv)).collect(),
    })
}
