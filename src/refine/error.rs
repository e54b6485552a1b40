//! The shot error: how far the live view's framing is from the desired
//! shot's, measured on the images alone.
//!
//! ORB features of the desired shot (its black fill masked) and of the live
//! frame are matched (brute force, ratio test, cross-check) and a homography
//! `live ← desired` is fitted by RANSAC ([`crate::geometry::find_homography`]).
//! The shot error is the mean distance the desired shot's four corners move
//! under it: 0 when the framing is identical. With a camera the keypoints and
//! the corners are taken undistorted, so a pure camera rotation is exactly a
//! homography.

use image::GrayImage;
use nalgebra::{Isometry3, Matrix3, Point2, Vector3};

use super::RefineError;
use crate::camera::Camera;
use crate::features::{self, Features, OrbExtractor};
use crate::geometry::homography4::apply_homography;
use crate::geometry::{HomographyParams, find_homography};
use crate::matching::{self, match_brute_force};
use crate::shot::frame_corners;

/// Every tunable number of the shot error.
#[derive(Debug, Clone, PartialEq)]
pub struct ShotErrorParams {
    /// The ORB extractor (both images).
    pub features: features::Params,
    /// Descriptor matching (desired shot → live frame).
    pub matching: matching::Params,
    /// The robust homography fit.
    pub homography: HomographyParams,
    /// Seed of the RANSAC.
    pub seed: u64,
}

impl Default for ShotErrorParams {
    fn default() -> Self {
        Self {
            features: features::Params {
                n_features: 1500,
                ..features::Params::default()
            },
            matching: matching::Params {
                max_distance: 64,
                ratio: 0.8,
                cross_check: true,
            },
            homography: HomographyParams {
                sigma_px: 1.5,
                min_inliers: 15,
                ..HomographyParams::default()
            },
            seed: 0x5107,
        }
    }
}

/// How far the live framing is from the desired shot.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ShotErrorReport {
    /// Mean displacement of the four image corners under the homography,
    /// pixels.
    pub corner_error_px: f64,
    /// The same as a percentage of the image diagonal.
    pub corner_error_pct: f64,
    /// Each corner's displacement (top-left, top-right, bottom-right,
    /// bottom-left), pixels.
    pub corner_displacements_px: [f64; 4],
    /// `live ← desired` (pixels; undistorted pixels with a camera), row-major.
    pub live_from_desired: [[f64; 3]; 3],
    /// Homography inliers.
    pub inliers: usize,
    /// Descriptor matches tried.
    pub matches: usize,
    /// Features found in the desired shot and in the live frame.
    pub features: (usize, usize),
}

/// The difference between two camera poses in a world whose z axis points
/// down (NED): distance between the optical centres, the rotation between
/// them, and the differences of the optical axis' heading and elevation.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct PoseDifference {
    /// Distance between the camera centres, metres (world units).
    pub position_m: f64,
    /// Angle of the relative rotation, degrees.
    pub rotation_deg: f64,
    /// Angle between the two optical axes, degrees.
    pub axis_deg: f64,
    /// Heading of `b`'s optical axis minus `a`'s, degrees in (-180, 180].
    pub yaw_deg: f64,
    /// Elevation of `b`'s optical axis minus `a`'s, degrees.
    pub pitch_deg: f64,
}

/// Heading (clockwise from north, radians) and elevation (up positive) of a
/// camera's optical axis in NED.
pub fn axis_yaw_pitch(ned_from_cam: &Isometry3<f64>) -> (f64, f64) {
    let z = ned_from_cam.rotation * Vector3::z();
    (z.y.atan2(z.x), (-z.z).atan2(z.x.hypot(z.y)))
}

/// `b` relative to `a`, both `world_from_cam` with the world in NED (see
/// [`PoseDifference`]).
pub fn pose_difference(a: &Isometry3<f64>, b: &Isometry3<f64>) -> PoseDifference {
    let (ya, pa) = axis_yaw_pitch(a);
    let (yb, pb) = axis_yaw_pitch(b);
    let za = a.rotation * Vector3::z();
    let zb = b.rotation * Vector3::z();
    let dyaw = crate::angle::wrap_pi(yb - ya);
    PoseDifference {
        position_m: (b.translation.vector - a.translation.vector).norm(),
        rotation_deg: a.rotation.angle_to(&b.rotation).to_degrees(),
        axis_deg: za.angle(&zb).to_degrees(),
        yaw_deg: dyaw.to_degrees(),
        pitch_deg: (pb - pa).to_degrees(),
    }
}

/// The image points where the corners are measured: the frame corners,
/// undistorted with a camera.
fn corners(width: u32, height: u32, camera: Option<&Camera>) -> [Point2<f64>; 4] {
    let c = frame_corners(width, height);
    match camera {
        Some(cam) => c.map(|p| cam.undistort_pixel(p)),
        None => c,
    }
}

/// The desired picture's corners (top-left, top-right, bottom-right,
/// bottom-left) in the live frame's pixels: the report's homography
/// `live ← desired` applied to them (in undistorted pixels with `camera`,
/// then distorted again, as the frame is shown). None when a corner maps
/// to infinity.
pub fn outline_in_live(
    report: &ShotErrorReport,
    width: u32,
    height: u32,
    camera: Option<&Camera>,
) -> Option<[[f64; 2]; 4]> {
    let h = Matrix3::from_row_slice(&report.live_from_desired.concat());
    let mut out = [[0.0; 2]; 4];
    for (o, c) in out.iter_mut().zip(corners(width, height, camera)) {
        let m = apply_homography(&h, &c)?;
        let p = camera.map_or(m, |cam| cam.distort_pixel(m));
        if !(p.x.is_finite() && p.y.is_finite()) {
            return None;
        }
        *o = [p.x, p.y];
    }
    Some(out)
}

/// The shot error of `live` against `desired` (whose pixels where
/// `desired_mask` is 0 are black fill and yield no feature). Both images
/// have the same size; with `camera` the keypoints and corners are
/// undistorted first.
pub fn shot_error(
    live: &GrayImage,
    desired: &GrayImage,
    desired_mask: Option<&GrayImage>,
    camera: Option<&Camera>,
    params: &ShotErrorParams,
) -> Result<ShotErrorReport, RefineError> {
    ShotErrorMeter::new(desired, desired_mask, camera, params)?.measure(live)
}

/// [`shot_error`] against one desired shot, frame after frame: the desired
/// picture's features are extracted once, and the extractor and the live
/// frame's feature buffers are kept (a servo measures every frame against
/// the same picture; extracting it again cost 3.6 of the 13.4 ms of a
/// frame's shot error in `benches/shot.rs`).
#[derive(Debug, Clone)]
pub struct ShotErrorMeter {
    params: ShotErrorParams,
    /// Undistorts the keypoints of both pictures.
    camera: Option<Camera>,
    orb: OrbExtractor,
    desired: Features,
    live: Features,
    width: u32,
    height: u32,
}

impl ShotErrorMeter {
    /// The meter of `desired` (no features where `mask` is 0), its
    /// keypoints undistorted with `camera`.
    pub fn new(
        desired: &GrayImage,
        mask: Option<&GrayImage>,
        camera: Option<&Camera>,
        params: &ShotErrorParams,
    ) -> Result<Self, RefineError> {
        let features = |e: crate::features::FeatureError| RefineError::Features {
            message: e.to_string(),
        };
        let mut orb = OrbExtractor::new(params.features).map_err(features)?;
        let mut d = Features::default();
        if let Some(m) = mask
            && m.dimensions() != desired.dimensions()
        {
            return Err(RefineError::ImageSize {
                live: m.dimensions(),
                desired: desired.dimensions(),
            });
        }
        orb.extract_into(desired, mask, camera, &mut d)
            .map_err(features)?;
        Ok(Self {
            params: params.clone(),
            camera: camera.copied(),
            orb,
            desired: d,
            live: Features::default(),
            width: desired.width(),
            height: desired.height(),
        })
    }

    /// The shot error of `live` (the desired picture's size), undistorted
    /// with the camera the meter was made with.
    pub fn measure(&mut self, live: &GrayImage) -> Result<ShotErrorReport, RefineError> {
        let camera = self.camera.as_ref();
        let desired = (self.width, self.height);
        if live.dimensions() != desired || live.width() == 0 || live.height() == 0 {
            return Err(RefineError::ImageSize {
                live: live.dimensions(),
                desired,
            });
        }
        self.orb
            .extract_into(live, None, camera, &mut self.live)
            .map_err(|e| RefineError::Features {
                message: e.to_string(),
            })?;
        let params = &self.params;
        let (fd, fl) = (&self.desired, &self.live);
        let matches = match_brute_force(&fd.descriptors, &fl.descriptors, &params.matching)
            .map_err(|e| RefineError::Matching {
                message: e.to_string(),
            })?;
        let pd: Vec<Point2<f64>> = matches
            .iter()
            .map(|m| {
                let k = fd.keypoints[m.query];
                Point2::new(f64::from(k.ux), f64::from(k.uy))
            })
            .collect();
        let pl: Vec<Point2<f64>> = matches
            .iter()
            .map(|m| {
                let k = fl.keypoints[m.train];
                Point2::new(f64::from(k.ux), f64::from(k.uy))
            })
            .collect();
        let fit = find_homography(&pd, &pl, &params.homography, params.seed).map_err(|e| {
            RefineError::NoHomography {
                matches: matches.len(),
                reason: e.to_string(),
            }
        })?;
        corner_error(
            &fit.h21,
            self.width,
            self.height,
            camera,
            fit.n_inliers,
            matches.len(),
            (fd.len(), fl.len()),
        )
    }
}

/// The corner error of a known homography `live ← desired` (the measure of
/// [`shot_error`] once the homography is fitted).
pub fn corner_error(
    live_from_desired: &Matrix3<f64>,
    width: u32,
    height: u32,
    camera: Option<&Camera>,
    inliers: usize,
    matches: usize,
    features: (usize, usize),
) -> Result<ShotErrorReport, RefineError> {
    let mut d = [0.0; 4];
    for (i, c) in corners(width, height, camera).iter().enumerate() {
        let moved = apply_homography(live_from_desired, c).ok_or(RefineError::NoHomography {
            matches,
            reason: "a corner maps to infinity".into(),
        })?;
        d[i] = (moved - c).norm();
    }
    let mean = d.iter().sum::<f64>() / 4.0;
    let diag = f64::from(width).hypot(f64::from(height));
    let h = live_from_desired / live_from_desired[(2, 2)];
    if !mean.is_finite() || !h.iter().all(|x| x.is_finite()) {
        return Err(RefineError::NoHomography {
            matches,
            reason: "non-finite homography".into(),
        });
    }
    Ok(ShotErrorReport {
        corner_error_px: mean,
        corner_error_pct: 100.0 * mean / diag,
        corner_displacements_px: d,
        live_from_desired: [
            [h[(0, 0)], h[(0, 1)], h[(0, 2)]],
            [h[(1, 0)], h[(1, 1)], h[(1, 2)]],
            [h[(2, 0)], h[(2, 1)], h[(2, 2)]],
        ],
        inliers,
        matches,
        features,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shot::warp_perspective;
    use nalgebra::{Point3, UnitQuaternion};
    use shotpilot_sim::camera::SimCamera;
    use shotpilot_sim::paths::camera_from_yaw_pitch;
    use shotpilot_sim::render::{RenderParams, Renderer};
    use shotpilot_sim::world::{World, WorldParams};
    use std::sync::Arc;

    fn renderer(sim_cam: SimCamera) -> Renderer {
        let world = World::generate_with(7, &WorldParams::small()).unwrap();
        Renderer::new(Arc::new(world), sim_cam, RenderParams::default())
    }

    fn camera_of(c: &SimCamera) -> Camera {
        crate::simulator::camera_from_sim(c).unwrap()
    }

    fn view() -> Isometry3<f64> {
        camera_from_yaw_pitch(Point3::new(-8.0, 3.0, -14.0), 0.4, 45f64.to_radians())
    }

    #[test]
    fn a_known_warp_gives_its_corner_error() {
        let r = renderer(SimCamera::default());
        let live = r.render(&view());
        let (w, h) = live.dimensions();
        // desired(x) = live(H⁻¹ x): a point at p in the live frame is at H p
        // in the desired shot, so live ← desired is H⁻¹.
        let hm = Matrix3::new(1.03, 0.02, -9.0, -0.015, 1.01, 6.0, 2e-5, -1e-5, 1.0);
        let inv = hm.try_inverse().unwrap();
        let (desired, mask) = warp_perspective(&live, &inv, w, h);
        let expected = corner_error(&inv, w, h, None, 0, 0, (0, 0)).unwrap();
        let got = shot_error(
            &live,
            &desired,
            Some(&mask),
            None,
            &ShotErrorParams::default(),
        )
        .unwrap();
        println!(
            "known warp: expected {:.2} px, measured {:.2} px ({} inliers of {})",
            expected.corner_error_px, got.corner_error_px, got.inliers, got.matches
        );
        assert!(expected.corner_error_px > 8.0);
        assert!(
            (got.corner_error_px - expected.corner_error_px).abs() < 0.5,
            "{} vs {}",
            got.corner_error_px,
            expected.corner_error_px
        );
        for i in 0..4 {
            assert!(
                (got.corner_displacements_px[i] - expected.corner_displacements_px[i]).abs() < 1.0
            );
        }
        assert!(got.inliers >= 100, "{} inliers", got.inliers);
        // The desired picture's outline in the live frame: its corners
        // through the known live ← desired.
        let outline = outline_in_live(&got, w, h, None).unwrap();
        for (o, c) in outline.iter().zip(frame_corners(w, h)) {
            let want = apply_homography(&inv, &c).unwrap();
            let d = (o[0] - want.x).hypot(o[1] - want.y);
            assert!(d < 1.0, "outline corner {o:?} vs {want}: {d:.2} px");
        }
    }

    #[test]
    fn the_outline_is_in_distorted_pixels() {
        // A barrel lens; the same framing (identity in undistorted pixels)
        // outlines the frame's own corners, not the undistorted ones.
        let cam = Camera::new(
            640,
            480,
            [500.0, 500.0, 320.0, 240.0],
            crate::camera::Distortion {
                k1: -0.2,
                k2: 0.05,
                ..Default::default()
            },
        )
        .unwrap();
        let rep = corner_error(&Matrix3::identity(), 640, 480, Some(&cam), 0, 0, (0, 0)).unwrap();
        let outline = outline_in_live(&rep, 640, 480, Some(&cam)).unwrap();
        for (o, c) in outline.iter().zip(frame_corners(640, 480)) {
            let d = (o[0] - c.x).hypot(o[1] - c.y);
            assert!(d < 0.05, "{o:?} vs {c}: {d} px");
            let u = cam.undistort_pixel(c);
            assert!(
                (u - c).norm() > 5.0,
                "the lens moves the corner: {u} vs {c}"
            );
        }
    }

    #[test]
    fn the_same_view_has_no_error() {
        let r = renderer(SimCamera::default());
        let a = r.render_noisy(&view(), 1);
        let b = r.render_noisy(&view(), 2);
        let e = shot_error(&a, &b, None, None, &ShotErrorParams::default()).unwrap();
        assert!(e.corner_error_px < 0.5, "{e:?}");
        assert!(e.corner_error_pct < 0.07);
    }

    #[test]
    fn a_camera_rotation_is_the_homography_k_r_k_inverse() {
        // A distorted camera; the error is measured on undistorted points,
        // where a pure rotation R is exactly K R K⁻¹.
        let sim_cam = SimCamera::default();
        let cam = camera_of(&sim_cam);
        let r = renderer(sim_cam);
        let desired_pose = view();
        for (yaw_deg, pitch_deg) in [(2.0, 0.0), (0.0, -1.5), (3.0, 2.0)] {
            // The live camera turned about the world vertical and its own x axis.
            let q = UnitQuaternion::from_axis_angle(&Vector3::z_axis(), f64::to_radians(yaw_deg))
                * desired_pose.rotation
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), f64::to_radians(pitch_deg));
            let live_pose = Isometry3::from_parts(desired_pose.translation, q);
            let desired = r.render(&desired_pose);
            let live = r.render(&live_pose);
            // x_live ~ K · (live ← desired rotation) · K⁻¹ x_desired
            let rot = (live_pose.rotation.inverse() * desired_pose.rotation).to_rotation_matrix();
            let h = cam.k() * rot.matrix() * cam.k_inv();
            let (w, hh) = desired.dimensions();
            let expected = corner_error(&h, w, hh, Some(&cam), 0, 0, (0, 0)).unwrap();
            let got = shot_error(
                &live,
                &desired,
                None,
                Some(&cam),
                &ShotErrorParams::default(),
            )
            .unwrap();
            println!(
                "rotation yaw {yaw_deg} pitch {pitch_deg}: expected {:.2} px, measured {:.2} px",
                expected.corner_error_px, got.corner_error_px
            );
            assert!(expected.corner_error_px > 10.0);
            assert!(
                (got.corner_error_px - expected.corner_error_px).abs()
                    < 0.03 * expected.corner_error_px + 0.5,
                "{} vs {}",
                got.corner_error_px,
                expected.corner_error_px
            );
        }
    }

    #[test]
    fn refusals() {
        let flat = GrayImage::from_pixel(320, 240, image::Luma([128]));
        let small = GrayImage::from_pixel(160, 120, image::Luma([128]));
        assert!(matches!(
            shot_error(&flat, &small, None, None, &ShotErrorParams::default()),
            Err(RefineError::ImageSize { .. })
        ));
        assert!(matches!(
            shot_error(
                &flat,
                &flat,
                Some(&small),
                None,
                &ShotErrorParams::default()
            ),
            Err(RefineError::ImageSize { .. })
        ));
        assert!(matches!(
            shot_error(&flat, &flat, None, None, &ShotErrorParams::default()),
            Err(RefineError::NoHomography { .. })
        ));
    }

    #[test]
    fn pose_difference_in_ned() {
        let a = camera_from_yaw_pitch(Point3::new(0.0, 0.0, -10.0), 0.3, 0.5);
        let b = camera_from_yaw_pitch(Point3::new(3.0, 4.0, -10.0), 0.3 + 0.1, 0.5 - 0.05);
        let d = pose_difference(&a, &b);
        assert!((d.position_m - 5.0).abs() < 1e-12);
        assert!((d.yaw_deg - 0.1f64.to_degrees()).abs() < 1e-9);
        // pitch below the horizon grew less: elevation rose by 0.05 rad
        assert!((d.pitch_deg - 0.05f64.to_degrees()).abs() < 1e-9);
        assert!(d.axis_deg > 0.0 && d.axis_deg <= d.rotation_deg + 1e-9);
        // wrap-around of the heading
        let c = camera_from_yaw_pitch(Point3::origin(), 3.1, 0.2);
        let e = camera_from_yaw_pitch(Point3::origin(), -3.1, 0.2);
        let d = pose_difference(&c, &e);
        assert!((d.yaw_deg - (std::f64::consts::TAU - 6.2).to_degrees()).abs() < 1e-9);
    }
}
