//! The camera's mounting: where it sits on the vehicle and how the gimbal
//! turns it. From a [`VehicleState`] to the camera's pose in local NED
//! (`ned_from_cam`), and back from a camera pose to the vehicle yaw,
//! gimbal pitch and vehicle position that reproduce it.
//!
//! Frames: NED world (x north, y east, z down); body x forward, y right,
//! z down; camera x right, y down, z forward. At gimbal pitch 0 and yaw 0
//! the camera looks along the body's x axis with image-right along the
//! body's y axis: `body ← cam` maps cam z → body x, cam x → body y, cam y →
//! body z. Gimbal pitch is positive up (-90 deg looks straight down), gimbal
//! yaw is relative to the body, positive right.
//!
//! A stabilised 2-axis gimbal (the default, and the simulator's) holds the
//! camera level whatever the body's roll and pitch:
//! `ned ← cam = Rz(heading + gimbal_yaw) · Ry(gimbal_pitch) · (body ← cam)`.
//! A body-fixed gimbal follows the whole attitude:
//! `ned ← cam = (ned ← body) · Rz(gimbal_yaw) · Ry(gimbal_pitch) · (body ← cam)`.
//!
//! The camera's optical centre sits at a lever arm from the vehicle's
//! reference point, given in the body frame and turned by the full attitude
//! (physically right for a camera on the airframe) or by the heading alone
//! (the simulator's model, which keeps the camera mount level). The two
//! differ by |lever arm|·tilt: 3 cm for 10 cm at 17 deg of tilt.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};

use super::GeoError;
use super::telemetry::{VehicleState, heading_of};
use crate::angle::wrap_pi;

/// How the lever arm turns with the vehicle.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LeverArmFrame {
    /// The lever arm turns with the full body attitude.
    Attitude,
    /// The lever arm turns with the heading only (level mount).
    Heading,
}

/// Every number of the mounting.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MountParams {
    /// Optical centre in the body frame (forward, right, down), metres.
    pub lever_arm_body_m: [f64; 3],
    /// How the lever arm turns.
    pub lever_arm_frame: LeverArmFrame,
    /// The gimbal cancels body roll and pitch (2-axis stabilised gimbal).
    pub stabilised: bool,
    /// Lowest gimbal pitch, degrees.
    pub pitch_min_deg: f64,
    /// Highest gimbal pitch, degrees.
    pub pitch_max_deg: f64,
    /// A target optical axis within this angle of straight up/down takes its
    /// heading from the image's right axis (the optical axis alone does not
    /// fix one), degrees.
    pub nadir_tolerance_deg: f64,
    /// Pitch calibration: the camera looks this much higher than the gimbal
    /// reports, degrees. The georeference learns the rest in flight
    /// ([`crate::geo::AlignParams::estimate_mount`]) and adds it to this.
    pub pitch_offset_deg: f64,
    /// Heading calibration: the camera looks this much to the right of the
    /// reported heading plus gimbal yaw, degrees (about the vertical for a
    /// stabilised gimbal, the body's z axis for a body-fixed one).
    pub yaw_offset_deg: f64,
}

/// A correction to the mount's calibration learned in flight: the camera's
/// attitude in the georeferenced map against the attitude telemetry and the
/// gimbal report ([`crate::geo::GeoAlignment::mount_offset`]).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize, serde::Deserialize)]
pub struct MountOffset {
    /// Added to [`MountParams::pitch_offset_deg`], degrees.
    pub pitch_deg: f64,
    /// Added to [`MountParams::yaw_offset_deg`], degrees.
    pub yaw_deg: f64,
    /// Standard deviation of `pitch_deg`, degrees.
    pub pitch_sigma_deg: f64,
    /// Standard deviation of `yaw_deg`, degrees.
    pub yaw_sigma_deg: f64,
    /// Oriented pairs it was learned from.
    pub pairs: usize,
}

impl MountParams {
    /// This mounting with a learned correction added.
    pub fn corrected(&self, offset: &MountOffset) -> Self {
        Self {
            pitch_offset_deg: self.pitch_offset_deg + offset.pitch_deg,
            yaw_offset_deg: self.yaw_offset_deg + offset.yaw_deg,
            ..self.clone()
        }
    }
}

impl Default for MountParams {
    fn default() -> Self {
        Self {
            lever_arm_body_m: [0.10, 0.0, 0.08],
            lever_arm_frame: LeverArmFrame::Attitude,
            stabilised: true,
            pitch_min_deg: -90.0,
            pitch_max_deg: 30.0,
            nadir_tolerance_deg: 0.01,
            pitch_offset_deg: 0.0,
            yaw_offset_deg: 0.0,
        }
    }
}

/// `body ← cam` at zero gimbal angles (cam z → body x, cam x → body y,
/// cam y → body z).
pub fn body_from_cam_zero() -> UnitQuaternion<f64> {
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(Matrix3::new(
        0.0, 0.0, 1.0, //
        1.0, 0.0, 0.0, //
        0.0, 1.0, 0.0,
    )))
}

/// `Rz(yaw) · Ry(pitch)`: the gimbal's turn (yaw then pitch, roll zero).
fn yaw_pitch(yaw: f64, pitch: f64) -> UnitQuaternion<f64> {
    UnitQuaternion::from_euler_angles(0.0, pitch, yaw)
}

/// The camera pose in local NED for a vehicle state.
pub fn ned_from_cam(state: &VehicleState, mount: &MountParams) -> Isometry3<f64> {
    let heading = state.heading();
    let g = state.gimbal;
    let yaw = g.yaw + mount.yaw_offset_deg.to_radians();
    let pitch = g.pitch + mount.pitch_offset_deg.to_radians();
    let rotation = if mount.stabilised {
        yaw_pitch(heading + yaw, pitch) * body_from_cam_zero()
    } else {
        state.ned_from_body * yaw_pitch(yaw, pitch) * body_from_cam_zero()
    };
    let arm = Vector3::from(mount.lever_arm_body_m);
    let arm_ned = match mount.lever_arm_frame {
        LeverArmFrame::Attitude => state.ned_from_body * arm,
        LeverArmFrame::Heading => UnitQuaternion::from_euler_angles(0.0, 0.0, heading) * arm,
    };
    Isometry3::from_parts(Translation3::from(state.p_ned + arm_ned), rotation)
}

/// What a 2-axis gimbal on a hovering vehicle must do to reproduce a camera
/// pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GimbalSolution {
    /// Vehicle heading, radians clockwise from north, in (-π, π].
    pub yaw: f64,
    /// Gimbal pitch, radians, positive up.
    pub pitch: f64,
    /// Roll about the optical axis the gimbal cannot reproduce: the target
    /// camera is turned by this angle (radians, right-handed about cam z)
    /// from the reproduced one.
    pub residual_roll: f64,
    /// Angle between the target's optical axis and the reproduced one,
    /// radians (0 except within the nadir tolerance).
    pub axis_error: f64,
    /// Position of the vehicle's reference point, local NED metres (the
    /// camera position minus the lever arm, the vehicle level at `yaw`).
    pub p_ned_vehicle: Vector3<f64>,
}

/// The vehicle yaw and gimbal pitch (gimbal yaw held at zero) that put the
/// camera's optical axis along the target's, for a vehicle hovering level,
/// the mount's calibration offsets taken off what is commanded; refuses a
/// commanded pitch outside the gimbal's range.
pub fn solve_gimbal(
    ned_from_cam_target: &Isometry3<f64>,
    mount: &MountParams,
) -> Result<GimbalSolution, GeoError> {
    let r = ned_from_cam_target.rotation;
    let c = ned_from_cam_target.translation.vector;
    if !(r.coords.iter().all(|v| v.is_finite()) && c.iter().all(|v| v.is_finite())) {
        return Err(GeoError::NonFinite {
            what: "target pose",
        });
    }
    let axis = r * Vector3::z();
    let horizontal = axis.x.hypot(axis.y);
    let pitch = (-axis.z).atan2(horizontal);
    let yaw = if horizontal > mount.nadir_tolerance_deg.to_radians().sin() {
        axis.y.atan2(axis.x)
    } else {
        // Looking (almost) straight up or down: the heading that keeps the
        // image's right axis where the target has it.
        let right = r * Vector3::x();
        (-right.x).atan2(right.y)
    };
    // What is commanded: the camera's angles less the mount's offsets.
    let pitch_deg = pitch.to_degrees() - mount.pitch_offset_deg;
    let heading = yaw - mount.yaw_offset_deg.to_radians();
    let eps = 1e-9;
    if pitch_deg < mount.pitch_min_deg - eps || pitch_deg > mount.pitch_max_deg + eps {
        return Err(GeoError::PitchOutOfRange {
            pitch_deg,
            min_deg: mount.pitch_min_deg,
            max_deg: mount.pitch_max_deg,
        });
    }
    let reproduced = yaw_pitch(yaw, pitch) * body_from_cam_zero();
    let diff = reproduced.inverse() * r;
    let axis_error = (diff * Vector3::z()).z.clamp(-1.0, 1.0).acos();
    let x = diff * Vector3::x();
    let residual_roll = x.y.atan2(x.x);
    // Hovering level at `yaw`: both lever-arm models agree.
    let arm = UnitQuaternion::from_euler_angles(0.0, 0.0, heading)
        * Vector3::from(mount.lever_arm_body_m);
    Ok(GimbalSolution {
        yaw: wrap_pi(heading),
        pitch: pitch_deg.to_radians(),
        residual_roll,
        axis_error,
        p_ned_vehicle: c - arm,
    })
}

/// Heading of a camera pose's body-like frame (for reports): the yaw of
/// `ned ← cam · (body ← cam)⁻¹`.
pub fn camera_heading(ned_from_cam: &Isometry3<f64>) -> f64 {
    heading_of(&(ned_from_cam.rotation * body_from_cam_zero().inverse()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::telemetry::GimbalAngles;

    fn state(yaw: f64, pitch: f64, gyaw: f64) -> VehicleState {
        VehicleState {
            time: 0.0,
            p_ned: Vector3::new(10.0, -5.0, -20.0),
            v_ned: Vector3::zeros(),
            ned_from_body: UnitQuaternion::from_euler_angles(0.0, 0.0, yaw),
            gimbal: GimbalAngles { pitch, yaw: gyaw },
        }
    }

    #[test]
    fn level_gimbal_heading_north_looks_north_with_right_east() {
        let m = MountParams {
            lever_arm_body_m: [0.0; 3],
            ..Default::default()
        };
        let p = ned_from_cam(&state(0.0, 0.0, 0.0), &m);
        let r = p.rotation;
        assert!((r * Vector3::z() - Vector3::x()).norm() < 1e-12);
        assert!((r * Vector3::x() - Vector3::y()).norm() < 1e-12);
        assert!((r * Vector3::y() - Vector3::z()).norm() < 1e-12);
        // Pitch -90 looks down with image-up along the heading (north).
        let r = ned_from_cam(&state(0.0, -std::f64::consts::FRAC_PI_2, 0.0), &m).rotation;
        assert!((r * Vector3::z() - Vector3::z()).norm() < 1e-12);
        assert!((r * -Vector3::y() - Vector3::x()).norm() < 1e-12);
    }

    #[test]
    fn solve_inverts_the_forward_model() {
        for m in [
            MountParams::default(),
            MountParams::default().corrected(&MountOffset {
                pitch_deg: 1.5,
                yaw_deg: -0.8,
                ..Default::default()
            }),
        ] {
            inverts(&m);
        }
    }

    fn inverts(m: &MountParams) {
        for (yaw, pitch) in [
            (0.3, -0.4),
            (-2.9, 0.2),
            (3.0, -1.5),
            (1.0, -std::f64::consts::FRAC_PI_2),
        ] {
            let s = state(yaw, pitch, 0.0);
            let p = ned_from_cam(&s, m);
            let sol = solve_gimbal(&p, m).unwrap();
            assert!((sol.pitch - pitch).abs() < 1e-9, "{sol:?}");
            assert!(wrap_pi(sol.yaw - yaw).abs() < 1e-9, "{sol:?}");
            assert!(sol.residual_roll.abs() < 1e-9);
            assert!((sol.p_ned_vehicle - s.p_ned).norm() < 1e-12);
        }
    }

    #[test]
    fn offsets_turn_the_camera_the_way_their_docs_say() {
        let plain = MountParams::default();
        let off = plain.corrected(&MountOffset {
            pitch_deg: 2.0,
            yaw_deg: 3.0,
            ..Default::default()
        });
        let s = state(0.4, -0.5, 0.0);
        let a = ned_from_cam(&s, &plain).rotation * Vector3::z();
        let b = ned_from_cam(&s, &off).rotation * Vector3::z();
        let pitch = |v: Vector3<f64>| (-v.z).atan2(v.xy().norm()).to_degrees();
        let heading = |v: Vector3<f64>| v.y.atan2(v.x).to_degrees();
        // Higher by the pitch offset, to the right by the yaw offset.
        assert!((pitch(b) - pitch(a) - 2.0).abs() < 1e-9);
        assert!((heading(b) - heading(a) - 3.0).abs() < 1e-9);
        // What is commanded for a camera pose leaves the offsets out.
        let sol = solve_gimbal(&ned_from_cam(&s, &off), &off).unwrap();
        assert!((sol.pitch - -0.5).abs() < 1e-12);
        assert!((sol.yaw - 0.4).abs() < 1e-12);
    }
}
