//! The best framing a camera can reach for a desired shot, and how far the
//! live view is from it.
//!
//! A desired shot made from anchors is a homography of a keyframe. Only
//! some homographies are views a camera of the same intrinsics can take:
//! a pan or tilt of the keyframe's camera is one; pulling the anchors in
//! (a zoom) is not, because moving closer enlarges near ground more than
//! far ground. The shot is localised at the camera pose that fits it best
//! (PnP), and a camera standing exactly there sees the desired shot up to
//! a homography `ideal ← desired` whose corner error is the shot error's
//! floor: no camera pose does much better, so a loop that waits for the
//! threshold below that floor only spends its rounds.
//!
//! The homography is fitted (RANSAC, as the shot error's) on the
//! keyframe's own map points: each lies at its keypoint's place in the
//! desired shot (through the anchors' transform) and projects into the
//! ideal view from the shot's pose. The live frame's distance to the
//! reachable framing is then the corner error of `ideal ← live =
//! (ideal ← desired) · (live ← desired)⁻¹`.

use nalgebra::{DMatrix, Isometry3, Matrix3, Point2, Point3, Vector2};

use super::{RefineError, ShotErrorParams, corner_error};
use crate::camera::Camera;
use crate::geometry::find_homography;
use crate::geometry::homography4::apply_homography;
use crate::slam::{KeyFrameId, Map};

/// The reachable framing of a desired shot.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Reachable {
    /// `ideal ← desired` (undistorted pixels, row-major): the view of a
    /// camera exactly at the shot's pose, as a homography of the shot.
    pub ideal_from_desired: [[f64; 3]; 3],
    /// Its corner error, pixels: the shot error a camera exactly at the
    /// shot's pose would measure.
    pub floor_px: f64,
    /// The same as a percentage of the image diagonal.
    pub floor_pct: f64,
    /// Keyframe map points inside the shot.
    pub points: usize,
    /// Those the homography fits.
    pub inliers: usize,
    /// Those map points (map frame) and where they lie in the desired
    /// shot (undistorted pixels), for [`Reachable::floor_at`] and
    /// [`Reachable::framing_change_pct`].
    #[serde(skip)]
    pub points_map: Vec<([f64; 3], [f64; 2])>,
}

impl Reachable {
    /// `ideal ← desired` as a matrix.
    pub fn matrix(&self) -> Matrix3<f64> {
        let h = &self.ideal_from_desired;
        Matrix3::new(
            h[0][0], h[0][1], h[0][2], h[1][0], h[1][1], h[1][2], h[2][0], h[2][1], h[2][2],
        )
    }

    /// The floor for a camera standing at `map_from_cam` instead of the
    /// shot's own pose (the pose a 2-axis gimbal reaches has no roll):
    /// the corner error (pixels, % of the diagonal) of the least-squares
    /// homography from the shot's pixels of its map points to their
    /// projections from there; None with too few points in front.
    pub fn floor_at(&self, map_from_cam: &Isometry3<f64>, camera: &Camera) -> Option<(f64, f64)> {
        let cam_from_map = map_from_cam.inverse();
        let (mut pd, mut pi) = (Vec::new(), Vec::new());
        for (x, d) in &self.points_map {
            if let Some(i) = camera.project_ideal(&(cam_from_map * Point3::from(*x)).coords) {
                pd.push(Point2::new(d[0], d[1]));
                pi.push(i);
            }
        }
        let h = fit_least_squares(&pd, &pi)?;
        corner_error(&h, camera.width, camera.height, Some(camera), 0, 0, (0, 0))
            .ok()
            .map(|r| (r.corner_error_px, r.corner_error_pct))
    }

    /// How much the framing changes (corner error of the best homography
    /// between the two views of the shot's map points, % of the image
    /// diagonal) when the camera moves from `map_from_live` to
    /// `map_from_desired`; None with too few points in front of both.
    pub fn framing_change_pct(
        &self,
        map_from_live: &Isometry3<f64>,
        map_from_desired: &Isometry3<f64>,
        camera: &Camera,
    ) -> Option<f64> {
        let (live, desired) = (map_from_live.inverse(), map_from_desired.inverse());
        let (mut pd, mut pl) = (Vec::new(), Vec::new());
        for (x, _) in &self.points_map {
            let x = Point3::from(*x);
            if let (Some(d), Some(l)) = (
                camera.project_ideal(&(desired * x).coords),
                camera.project_ideal(&(live * x).coords),
            ) {
                pd.push(d);
                pl.push(l);
            }
        }
        let h = fit_least_squares(&pd, &pl)?;
        corner_error(&h, camera.width, camera.height, Some(camera), 0, 0, (0, 0))
            .ok()
            .map(|r| r.corner_error_pct)
    }
}

/// The least-squares homography `p2 ~ H p1` (normalised DLT) of exact
/// correspondences; None with fewer than 4 or a degenerate set.
fn fit_least_squares(p1: &[Point2<f64>], p2: &[Point2<f64>]) -> Option<Matrix3<f64>> {
    if p1.len() < 4 || p1.len() != p2.len() {
        return None;
    }
    let norm = |p: &[Point2<f64>]| {
        let n = p.len() as f64;
        let c = p.iter().fold(Vector2::zeros(), |a, q| a + q.coords) / n;
        let d = p.iter().map(|q| (q.coords - c).norm()).sum::<f64>() / n;
        let s = if d > 1e-12 {
            std::f64::consts::SQRT_2 / d
        } else {
            1.0
        };
        Matrix3::new(s, 0.0, -s * c.x, 0.0, s, -s * c.y, 0.0, 0.0, 1.0)
    };
    let (t1, t2) = (norm(p1), norm(p2));
    let mut a = DMatrix::<f64>::zeros(2 * p1.len(), 9);
    for (i, (x, y)) in p1.iter().zip(p2).enumerate() {
        let x = t1 * x.to_homogeneous();
        let y = t2 * y.to_homogeneous();
        let (u, v) = (y.x / y.z, y.y / y.z);
        let (px, py, pw) = (x.x / x.z, x.y / x.z, 1.0);
        let r = 2 * i;
        a.row_mut(r)
            .copy_from_slice(&[0.0, 0.0, 0.0, -px, -py, -pw, v * px, v * py, v * pw]);
        a.row_mut(r + 1)
            .copy_from_slice(&[px, py, pw, 0.0, 0.0, 0.0, -u * px, -u * py, -u * pw]);
    }
    let ata = a.transpose() * &a;
    let eig = ata.symmetric_eigen();
    let (k, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))?;
    let h = eig.eigenvectors.column(k);
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8]);
    let out = t2.try_inverse()? * hn * t1;
    (out.iter().all(|x| x.is_finite()) && out[(2, 2)].abs() > 1e-15).then(|| out / out[(2, 2)])
}

/// The reachable framing of the desired shot made from keyframe
/// `keyframe` of `map` by `shot_to_keyframe` (`H`: shot pixel → keyframe
/// pixel, raw pixels) and localised at `map_from_desired`. The shot has
/// the map camera's size.
pub fn reachable_from_anchors(
    map: &Map,
    keyframe: KeyFrameId,
    shot_to_keyframe: &Matrix3<f64>,
    map_from_desired: &Isometry3<f64>,
    params: &ShotErrorParams,
) -> Result<Reachable, RefineError> {
    let camera = map.camera;
    let kf = map
        .keyframe(keyframe)
        .ok_or(RefineError::UnknownKeyframe { id: keyframe.0 })?;
    let keyframe_from_shot = *shot_to_keyframe;
    let shot_from_keyframe = keyframe_from_shot
        .try_inverse()
        .ok_or(RefineError::NonFinite {
            what: "anchor transform",
        })?;
    let cam_from_map = map_from_desired.inverse();
    let mut pd = Vec::new();
    let mut pi = Vec::new();
    let mut xs = Vec::new();
    for (k, pid) in kf.keypoints.iter().zip(&kf.points) {
        let Some(p) = pid.and_then(|id| map.point(id)) else {
            continue;
        };
        let a = Point2::new(f64::from(k.x), f64::from(k.y));
        let Some(d) = apply_homography(&shot_from_keyframe, &a) else {
            continue;
        };
        if !camera.contains(d, 0.0) {
            continue;
        }
        let Some(ideal) = camera.project_ideal(&(cam_from_map * p.position).coords) else {
            continue;
        };
        pd.push(camera.undistort_pixel(d));
        pi.push(ideal);
        xs.push(p.position);
    }
    let fit = find_homography(&pd, &pi, &params.homography, params.seed).map_err(|e| {
        RefineError::NoHomography {
            matches: pd.len(),
            reason: e.to_string(),
        }
    })?;
    let r = corner_error(
        &fit.h21,
        camera.width,
        camera.height,
        Some(&camera),
        fit.n_inliers,
        pd.len(),
        (pd.len(), pd.len()),
    )?;
    Ok(Reachable {
        ideal_from_desired: r.live_from_desired,
        floor_px: r.corner_error_px,
        floor_pct: r.corner_error_pct,
        points: pd.len(),
        inliers: fit.n_inliers,
        points_map: xs
            .iter()
            .zip(&pd)
            .zip(&fit.inliers)
            .filter(|(_, i)| **i)
            .map(|((x, d), _)| ([x.x, x.y, x.z], [d.x, d.y]))
            .collect(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use crate::features::KeyPoint;
    use crate::matching::FeatureGrid;
    use crate::slam::{KeyFrame, ScaleInfo};
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    fn camera() -> Camera {
        Camera::new(
            640,
            480,
            [460.0, 460.0, 319.5, 239.5],
            Distortion::default(),
        )
        .unwrap()
    }

    /// A keyframe tilted 40 deg down over flat ground 10 m below (map y
    /// down), seeing a grid of ground points; returns the map, the
    /// keyframe's id and its `map ← cam`.
    fn ground_map() -> (Map, KeyFrameId, Isometry3<f64>) {
        let cam = camera();
        let map_from_kf = Isometry3::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -40f64.to_radians()),
        );
        let mut map = Map::new(cam, ScaleInfo::new(1.2, 8));
        let mut kps = Vec::new();
        let mut pids = Vec::new();
        for i in 0..40 {
            for j in 0..40 {
                let p = Point3::new(-30.0 + 1.5 * f64::from(i), 10.0, 2.0 + 1.5 * f64::from(j));
                let Some(px) = cam.project(&(map_from_kf.inverse() * p).coords) else {
                    continue;
                };
                if !cam.contains(px, 0.0) {
                    continue;
                }
                let id = map.add_point(p, [0; 4], KeyFrameId(0));
                kps.push(KeyPoint {
                    x: px.x as f32,
                    y: px.y as f32,
                    ux: px.x as f32,
                    uy: px.y as f32,
                    ..KeyPoint::default()
                });
                pids.push(Some(id));
            }
        }
        let n = kps.len();
        let kf = map.add_keyframe(KeyFrame {
            id: KeyFrameId(0),
            frame_index: 0,
            timestamp: 0.0,
            cam_from_world: map_from_kf.inverse(),
            keypoints: kps,
            descriptors: vec![[0; 4]; n],
            points: pids,
            grid: FeatureGrid::default(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: None,
        });
        (map, kf, map_from_kf)
    }

    fn k() -> Matrix3<f64> {
        Matrix3::new(460.0, 0.0, 319.5, 0.0, 460.0, 239.5, 0.0, 0.0, 1.0)
    }

    #[test]
    fn a_pan_is_reachable_a_zoom_is_not() {
        let (map, kf, map_from_kf) = ground_map();
        let params = ShotErrorParams::default();
        // A pan of the keyframe's camera about the vertical: the shot is
        // that camera's view, the floor is zero.
        let pan = UnitQuaternion::from_axis_angle(&Vector3::y_axis(), 4f64.to_radians());
        let map_from_pan =
            Isometry3::from_parts(map_from_kf.translation, pan * map_from_kf.rotation);
        let kf_from_pan =
            (map_from_kf.rotation.inverse() * map_from_pan.rotation).to_rotation_matrix();
        let h = k() * kf_from_pan.matrix() * k().try_inverse().unwrap();
        let r = reachable_from_anchors(&map, kf, &h, &map_from_pan, &params).unwrap();
        assert!(r.floor_pct < 0.01, "{}", r.floor_pct);
        assert!(
            r.points > 300 && r.inliers == r.points,
            "{} {}",
            r.points,
            r.inliers
        );
        // A centred zoom (anchors 40 px inside the corners), the camera
        // moved forward to where the centre keeps its scale: the near
        // ground grows more than the far, and the corners are off by more
        // than the 1 % threshold; from a 1 m other place, more still.
        let s = 559.0 / 639.0;
        let zoom = Matrix3::new(
            s,
            0.0,
            319.5 * (1.0 - s),
            0.0,
            s,
            239.5 * (1.0 - s),
            0.0,
            0.0,
            1.0,
        );
        let depth = 10.0 / 40f64.to_radians().sin();
        let forward = map_from_kf.rotation * Vector3::z() * depth * (1.0 - s);
        let map_from_zoom = Isometry3::from_parts(
            Translation3::from(map_from_kf.translation.vector + forward),
            map_from_kf.rotation,
        );
        let r = reachable_from_anchors(&map, kf, &zoom, &map_from_zoom, &params).unwrap();
        assert!(r.floor_pct > 1.0, "{}", r.floor_pct);
        let cam = camera();
        let (_, at) = r.floor_at(&map_from_zoom, &cam).unwrap();
        assert!((at - r.floor_pct).abs() < 0.05, "{at} vs {}", r.floor_pct);
        let moved = Isometry3::from_parts(
            Translation3::from(map_from_zoom.translation.vector + Vector3::new(1.0, 0.0, 0.0)),
            map_from_zoom.rotation,
        );
        let (_, off) = r.floor_at(&moved, &cam).unwrap();
        assert!(off > r.floor_pct + 0.5, "{off} vs {}", r.floor_pct);
        // The framing change between two poses: none for the same pose,
        // some for a move.
        let same = r
            .framing_change_pct(&map_from_zoom, &map_from_zoom, &cam)
            .unwrap();
        assert!(same < 1e-6, "{same}");
        let change = r.framing_change_pct(&moved, &map_from_zoom, &cam).unwrap();
        assert!(change > 1.0, "{change}");
        // A keyframe that is not in the map is refused.
        assert!(matches!(
            reachable_from_anchors(&map, KeyFrameId(7), &zoom, &map_from_zoom, &params),
            Err(RefineError::UnknownKeyframe { id: 7 })
        ));
    }
}
