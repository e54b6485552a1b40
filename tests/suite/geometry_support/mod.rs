//! Synthetic scenes shared by the geometry tests and benches
//! (`#[path]`-included by `benches/`).
#![allow(dead_code)]

use nalgebra::{Isometry3, Point2, Point3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};
use shotpilot::optimize::{BaPose, BaProblem, Intrinsics, Observation};

/// Standard normal sample (Box-Muller).
pub fn gauss(rng: &mut SmallRng) -> f64 {
    let u1: f64 = rng.random_range(f64::EPSILON..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
}

/// A bundle-adjustment scene: the truth and a perturbed copy to optimise.
pub struct BaScene {
    /// Ground truth poses and points; observations carry the noise.
    pub truth: BaProblem,
    /// The same with poses (except the fixed ones) and points perturbed.
    pub perturbed: BaProblem,
}

/// `n_kf` keyframes on a sideways track looking +z, `n_points` points each
/// seen by `obs_per_point` consecutive keyframes, pixel noise `noise_px`.
/// The first two keyframes are fixed (gauge and scale). Perturbations:
/// rotation `rot_deg` and translation `trans_m` per free pose, `point_m`
/// per point coordinate (all Gaussian).
#[allow(clippy::too_many_arguments)]
pub fn ba_scene(
    seed: u64,
    n_kf: usize,
    n_points: usize,
    obs_per_point: usize,
    noise_px: f64,
    rot_deg: f64,
    trans_m: f64,
    point_m: f64,
) -> BaScene {
    let mut rng = SmallRng::seed_from_u64(seed);
    let intr = Intrinsics {
        fx: 500.0,
        fy: 500.0,
        cx: 320.0,
        cy: 240.0,
    };
    let poses: Vec<BaPose> = (0..n_kf)
        .map(|i| {
            let centre = Vector3::new(
                0.4 * i as f64,
                0.05 * (i as f64 * 0.7).sin(),
                0.03 * i as f64,
            );
            let rot = UnitQuaternion::from_euler_angles(
                0.01 * i as f64,
                -0.02 * i as f64,
                0.005 * i as f64,
            );
            // cam_from_world = (R, -R·c)
            BaPose {
                cam_from_world: Isometry3::from_parts(Translation3::from(-(rot * centre)), rot),
                fixed: i < 2,
                shutter: None,
            }
        })
        .collect();
    let mut points = Vec::with_capacity(n_points);
    let mut observations = Vec::with_capacity(n_points * obs_per_point);
    while points.len() < n_points {
        let first = rng.random_range(0..=(n_kf - obs_per_point));
        // A point in front of the middle keyframe of its track.
        let mid = &poses[first + obs_per_point / 2].cam_from_world;
        let pc = Vector3::new(
            rng.random_range(-4.0..4.0),
            rng.random_range(-3.0..3.0),
            rng.random_range(6.0..14.0),
        );
        let pw = mid.inverse_transform_point(&Point3::from(pc));
        let mut obs = Vec::with_capacity(obs_per_point);
        for (k, kf) in poses.iter().enumerate().skip(first).take(obs_per_point) {
            let q = kf.cam_from_world.transform_point(&pw).coords;
            if q.z < 0.5 {
                break;
            }
            let uv = intr.project(&q);
            if !(0.0..640.0).contains(&uv.x) || !(0.0..480.0).contains(&uv.y) {
                break;
            }
            obs.push((k, uv));
        }
        if obs.len() < obs_per_point {
            continue;
        }
        let j = points.len();
        points.push(pw);
        for (k, uv) in obs {
            observations.push(Observation {
                pose: k,
                point: j,
                uv: Point2::new(
                    uv.x + noise_px * gauss(&mut rng),
                    uv.y + noise_px * gauss(&mut rng),
                ),
                inv_sigma2: 1.0 / (noise_px * noise_px).max(1e-12),
            });
        }
    }
    let truth = BaProblem {
        poses,
        points,
        observations,
        intrinsics: intr,
        priors: Vec::new(),
    };
    let mut perturbed = truth.clone();
    let r = rot_deg.to_radians();
    for p in perturbed.poses.iter_mut().filter(|p| !p.fixed) {
        let dr = UnitQuaternion::from_scaled_axis(
            Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * r,
        );
        let dt = Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * trans_m;
        p.cam_from_world = Isometry3::from_parts(Translation3::from(dt), dr) * p.cam_from_world;
    }
    for p in perturbed.points.iter_mut() {
        p.coords += Vector3::new(gauss(&mut rng), gauss(&mut rng), gauss(&mut rng)) * point_m;
    }
    BaScene { truth, perturbed }
}

/// Focal length of the synthetic 640×480 camera.
pub const F: f64 = 500.0;
/// Principal point x.
pub const CX: f64 = 320.0;
/// Principal point y.
pub const CY: f64 = 240.0;

/// A PnP trial: truth, world points, normalised observations.
pub struct PnpScene {
    /// The true pose.
    pub truth: Isometry3<f64>,
    /// World points.
    pub pw: Vec<Point3<f64>>,
    /// Observations, normalised coordinates.
    pub xn: Vec<Point2<f64>>,
    /// Which observations were replaced by random pixels.
    pub outlier: Vec<bool>,
    /// Mean depth of the points.
    pub mean_depth: f64,
}

/// A pinhole camera for the PnP scenes: width, height, focal (pixels).
#[derive(Clone, Copy, Debug)]
pub struct Cam {
    /// Image width.
    pub w: f64,
    /// Image height.
    pub h: f64,
    /// Focal length.
    pub f: f64,
}

/// 1280×720 with a 70° horizontal field of view: a drone's video.
pub const CAM_720P: Cam = Cam {
    w: 1280.0,
    h: 720.0,
    f: 900.0,
};
/// 640×480 with a 65° horizontal field of view (TUM-like).
pub const CAM_VGA: Cam = Cam {
    w: 640.0,
    h: 480.0,
    f: 500.0,
};

/// `n` points over the whole image at depth 4-12 m, a random pose, Gaussian
/// pixel noise, and the first `outlier_ratio·n` observations replaced by
/// random pixels.
pub fn pnp_scene(seed: u64, n: usize, outlier_ratio: f64, noise_px: f64, cam: Cam) -> PnpScene {
    let mut rng = SmallRng::seed_from_u64(seed);
    let truth = Isometry3::from_parts(
        Translation3::new(
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
            rng.random_range(-1.0..1.0),
        ),
        UnitQuaternion::from_euler_angles(
            rng.random_range(-0.5..0.5),
            rng.random_range(-0.5..0.5),
            rng.random_range(-3.1..3.1),
        ),
    );
    let (cx, cy, f) = (cam.w / 2.0, cam.h / 2.0, cam.f);
    let mut s = PnpScene {
        truth,
        pw: Vec::with_capacity(n),
        xn: Vec::with_capacity(n),
        outlier: Vec::with_capacity(n),
        mean_depth: 0.0,
    };
    for i in 0..n {
        let u = rng.random_range(0.0..cam.w);
        let v = rng.random_range(0.0..cam.h);
        let z = rng.random_range(4.0..12.0);
        let pc = Vector3::new((u - cx) / f * z, (v - cy) / f * z, z);
        s.mean_depth += z / n as f64;
        s.pw.push(truth.inverse_transform_point(&Point3::from(pc)));
        let is_out = (i as f64) < outlier_ratio * n as f64;
        let (uo, vo) = if is_out {
            (rng.random_range(0.0..cam.w), rng.random_range(0.0..cam.h))
        } else {
            (
                u + noise_px * gauss(&mut rng),
                v + noise_px * gauss(&mut rng),
            )
        };
        s.xn.push(Point2::new((uo - cx) / f, (vo - cy) / f));
        s.outlier.push(is_out);
    }
    s
}

/// Two views of a scene.
pub struct TwoViewScene {
    /// True motion.
    pub cam2_from_cam1: Isometry3<f64>,
    /// True points, camera-1 frame.
    pub p1: Vec<Point3<f64>>,
    /// Keypoints of view 1 (pixels).
    pub kp1: Vec<Point2<f64>>,
    /// Keypoints of view 2 (pixels).
    pub kp2: Vec<Point2<f64>>,
    /// Matches `(i, i)`.
    pub matches: Vec<(usize, usize)>,
    /// Which matches are outliers.
    pub outlier: Vec<bool>,
}

fn project_in_image(p: &Point3<f64>) -> Option<Point2<f64>> {
    if p.z <= 0.1 {
        return None;
    }
    let u = F * p.x / p.z + CX;
    let v = F * p.y / p.z + CY;
    ((0.0..640.0).contains(&u) && (0.0..480.0).contains(&v)).then_some(Point2::new(u, v))
}

/// `cam2_from_cam1` for a camera centre displaced by `c` (camera-1 frame)
/// and rotated by the Euler angles `r`.
pub fn motion(c: [f64; 3], r: [f64; 3]) -> Isometry3<f64> {
    let rot = UnitQuaternion::from_euler_angles(r[0], r[1], r[2]);
    Isometry3::from_parts(
        Translation3::from(-(rot * Vector3::new(c[0], c[1], c[2]))),
        rot,
    )
}

/// `planar`: points on the plane `n·X = 6` (tilted); else depth 4-9 m.
/// `outliers`: fraction of matches whose second keypoint is random.
pub fn two_view_scene(
    seed: u64,
    n: usize,
    planar: bool,
    cam2_from_cam1: Isometry3<f64>,
    noise: f64,
    outliers: f64,
) -> TwoViewScene {
    let mut rng = SmallRng::seed_from_u64(seed);
    let normal = Vector3::new(0.15, -0.1, 1.0).normalize();
    let mut s = TwoViewScene {
        cam2_from_cam1,
        p1: Vec::new(),
        kp1: Vec::new(),
        kp2: Vec::new(),
        matches: Vec::new(),
        outlier: Vec::new(),
    };
    while s.p1.len() < n {
        let u = rng.random_range(0.0..640.0);
        let v = rng.random_range(0.0..480.0);
        let ray = Vector3::new((u - CX) / F, (v - CY) / F, 1.0);
        let z = if planar {
            6.0 / normal.dot(&ray)
        } else {
            rng.random_range(4.0..9.0)
        };
        let p = Point3::from(ray * z);
        let Some(x2) = project_in_image(&(cam2_from_cam1 * p)) else {
            continue;
        };
        let i = s.p1.len();
        let is_out = (i as f64) < outliers * n as f64;
        let x1 = Point2::new(u + noise * gauss(&mut rng), v + noise * gauss(&mut rng));
        let x2 = if is_out {
            Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0))
        } else {
            Point2::new(
                x2.x + noise * gauss(&mut rng),
                x2.y + noise * gauss(&mut rng),
            )
        };
        s.p1.push(p);
        s.kp1.push(x1);
        s.kp2.push(x2);
        s.matches.push((i, i));
        s.outlier.push(is_out);
    }
    s
}
