//! The hidden poses and their desired shots: a photo rendered near an
//! explore keyframe, or anchors on a keyframe (a pan and tilt of its
//! camera, or an operator's drag of the four corners), each with the true
//! camera that takes it.

use image::GrayImage;
use nalgebra::{Isometry3, Point2, UnitQuaternion, Vector3};
use rand::{Rng, rngs::SmallRng};

use crate::geo::{GimbalAngles, VehicleState, ned_from_cam};
use crate::shot::{desired_shot_from_anchors, frame_corners};
use crate::simulator::drag::{DragParams, drag_truth, random_drag};

use super::explore::Explored;
use super::params::ScenarioParams;
use super::sim::Sim;

/// A hidden pose: the vehicle state that takes it, its camera, the desired
/// shot (image, mask), its kind and, for an anchors shot, its keyframe and
/// transform (shot pixel -> keyframe pixel).
pub(super) struct Hidden {
    pub(super) p_ned: Vector3<f64>,
    pub(super) yaw: f64,
    pub(super) pitch: f64,
    pub(super) camera: Isometry3<f64>,
    pub(super) image: GrayImage,
    pub(super) mask: Option<GrayImage>,
    pub(super) kind: &'static str,
    pub(super) anchors_on: Option<(u32, nalgebra::Matrix3<f64>)>,
}

fn hover_state(p_ned: Vector3<f64>, yaw: f64, pitch: f64) -> VehicleState {
    VehicleState {
        time: 0.0,
        p_ned,
        v_ned: Vector3::zeros(),
        ned_from_body: nalgebra::UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
        gimbal: GimbalAngles { pitch, yaw: 0.0 },
    }
}

fn sym(rng: &mut SmallRng, r: f64) -> f64 {
    if r > 0.0 {
        rng.random_range(-r..r)
    } else {
        0.0
    }
}

pub(super) fn make_hidden(
    ex: &Explored,
    sim: &Sim,
    params: &ScenarioParams,
    anchors: bool,
    rng: &mut SmallRng,
) -> Option<Hidden> {
    let hp = &params.hidden;
    let mount = &params.geo.mount;
    let ids: Vec<u32> = ex.kf_truth.keys().copied().collect();
    if ids.is_empty() {
        return None;
    }
    let id = ids[rng.random_range(0..ids.len())];
    let ((p, yaw, pitch), kf_cam) = ex.kf_truth[&id];
    if anchors && let Some(drag) = hp.drags {
        return make_drag(ex, sim, &drag, params, id, rng);
    }
    if anchors {
        let kf = ex.map.keyframe(crate::slam::KeyFrameId(id))?;
        let img = kf.image.clone()?;
        // The keyframe's true camera turned about the vertical and its own
        // x axis (a pan and a tilt: a pose a 2-axis gimbal can take).
        let dyaw = sym(rng, hp.anchor_yaw_deg).to_radians();
        let dpitch = sym(rng, hp.anchor_pitch_deg).to_radians();
        let cam = Isometry3::from_parts(
            kf_cam.translation,
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), dyaw)
                * kf_cam.rotation
                * UnitQuaternion::from_axis_angle(&Vector3::x_axis(), -dpitch),
        );
        let (yaw2, pitch2) = (yaw + dyaw, pitch + dpitch);
        // The anchors: where the desired frame's corners lie in the
        // keyframe (the warp samples the keyframe at H·p, H: corner -> anchor).
        let cam_model = ex.map.camera;
        let k_from_d = kf_cam.rotation.inverse() * cam.rotation;
        let mut pts = [Point2::origin(); 4];
        for (i, c) in frame_corners(cam_model.width, cam_model.height)
            .iter()
            .enumerate()
        {
            let ray = cam_model.unproject(*c);
            pts[i] = cam_model.project(&(k_from_d * ray.into_inner()))?;
        }
        let shot = desired_shot_from_anchors(&img, &pts, &params.anchors).ok()?;
        return Some(Hidden {
            p_ned: p,
            yaw: yaw2,
            pitch: pitch2,
            camera: cam,
            image: shot.image,
            mask: Some(shot.mask),
            kind: "anchors",
            anchors_on: Some((id, shot.shot_to_source)),
        });
    }
    let ground = sim.renderer.world().height_at(p.x, p.y);
    let mut q = p + Vector3::new(
        sym(rng, hp.horizontal_m),
        sym(rng, hp.horizontal_m),
        sym(rng, hp.vertical_m),
    );
    let clearance = sim.renderer.world().max_height_near(q.x, q.y, 3.0);
    q.z = q.z.min(-(hp.min_alt_m.max(clearance - ground + 3.0)));
    let yaw2 = yaw + sym(rng, hp.yaw_deg).to_radians();
    let pitch2 = (pitch + sym(rng, hp.pitch_deg).to_radians()).clamp(
        hp.pitch_range_deg.0.to_radians(),
        hp.pitch_range_deg.1.to_radians(),
    );
    let cam = ned_from_cam(&hover_state(q, yaw2, pitch2), mount);
    let image = if params.sensor_noise {
        sim.renderer.render_noisy(&cam, rng.random())
    } else {
        sim.renderer.render(&cam)
    };
    Some(Hidden {
        p_ned: q,
        yaw: yaw2,
        pitch: pitch2,
        camera: cam,
        image,
        mask: None,
        kind: "render",
        anchors_on: None,
    })
}

/// An anchors shot dragged on keyframe `id` ([`DragParams`]), and its
/// truth: the camera that takes the drawn picture best in the true world
/// (PnP on a grid of the picture's pixels, each at the true scene point
/// the keyframe's true camera sees there through the anchors' transform),
/// with the vehicle state a 2-axis gimbal reaches it from.
fn make_drag(
    ex: &Explored,
    sim: &Sim,
    drag: &DragParams,
    params: &ScenarioParams,
    id: u32,
    rng: &mut SmallRng,
) -> Option<Hidden> {
    let ((p, _, _), kf_cam) = ex.kf_truth[&id];
    let kf = ex.map.keyframe(crate::slam::KeyFrameId(id))?;
    let img = kf.image.clone()?;
    let cam = ex.map.camera;
    let d = random_drag(rng, &cam, drag);
    let shot = desired_shot_from_anchors(&img, &d.anchors, &params.anchors).ok()?;
    let truth = drag_truth(
        sim.renderer.world(),
        &cam,
        &kf_cam,
        &shot.shot_to_source,
        &params.localize.pnp,
        &params.localize.pose,
    )?
    .world_from_cam;
    let (yaw, pitch) = crate::refine::axis_yaw_pitch(&truth);
    Some(Hidden {
        p_ned: p + (truth.translation.vector - kf_cam.translation.vector),
        yaw,
        pitch,
        camera: truth,
        image: shot.image,
        mask: Some(shot.mask),
        kind: "drag",
        anchors_on: Some((id, shot.shot_to_source)),
    })
}
