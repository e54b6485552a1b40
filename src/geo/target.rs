//! A target camera pose, found in the SLAM map, as what the vehicle must
//! do: latitude, longitude, altitude above home, vehicle yaw and gimbal
//! pitch.

use nalgebra::{Isometry3, Vector3};

use super::GeoError;
use super::align::GeoAlignment;
use super::mount::{MountParams, solve_gimbal};
use super::wgs84::LocalFrame;

/// Where the vehicle must stand and how it must look.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GeoTarget {
    /// Vehicle latitude, degrees (WGS84).
    pub lat_deg: f64,
    /// Vehicle longitude, degrees (WGS84).
    pub lon_deg: f64,
    /// Vehicle altitude above home, metres (ellipsoidal height minus home's).
    pub alt_above_home_m: f64,
    /// Vehicle ellipsoidal height, metres.
    pub alt_m: f64,
    /// Vehicle heading, degrees clockwise from north, in [0, 360).
    pub yaw_deg: f64,
    /// Gimbal pitch, degrees (negative looks down).
    pub gimbal_pitch_deg: f64,
    /// Roll about the optical axis the 2-axis gimbal cannot reproduce,
    /// degrees.
    pub residual_roll_deg: f64,
    /// Angle between the target's optical axis and the reproduced one,
    /// degrees (non-zero only within the nadir tolerance).
    pub axis_error_deg: f64,
    /// Vehicle position, local NED metres.
    pub p_ned_vehicle: Vector3<f64>,
    /// The target camera pose in local NED.
    pub ned_from_cam: Isometry3<f64>,
}

impl GeoTarget {
    /// As a mission target (altitude above home).
    pub fn to_mission_target(&self, photo: bool) -> crate::mission::plan::Target {
        crate::mission::plan::Target {
            lat_deg: self.lat_deg,
            lon_deg: self.lon_deg,
            alt_m: self.alt_above_home_m,
            yaw_deg: self.yaw_deg,
            gimbal_pitch_deg: self.gimbal_pitch_deg,
            photo,
        }
    }
}

/// A target camera pose in local NED as a vehicle target.
pub fn target_from_ned(
    ned_from_cam: &Isometry3<f64>,
    frame: &LocalFrame,
    mount: &MountParams,
) -> Result<GeoTarget, GeoError> {
    let sol = solve_gimbal(ned_from_cam, mount)?;
    let g = frame.ned_to_geodetic(&sol.p_ned_vehicle);
    let yaw_deg = sol.yaw.to_degrees().rem_euclid(360.0);
    Ok(GeoTarget {
        lat_deg: g.lat_deg,
        lon_deg: g.lon_deg,
        alt_above_home_m: g.alt_m - frame.home().alt_m,
        alt_m: g.alt_m,
        yaw_deg: if yaw_deg >= 360.0 { 0.0 } else { yaw_deg },
        gimbal_pitch_deg: sol.pitch.to_degrees(),
        residual_roll_deg: sol.residual_roll.to_degrees(),
        axis_error_deg: sol.axis_error.to_degrees(),
        p_ned_vehicle: sol.p_ned_vehicle,
        ned_from_cam: *ned_from_cam,
    })
}

/// A target camera pose in the SLAM map (`map ← cam`) as a vehicle target:
/// map → NED by the alignment, then [`target_from_ned`] with the mount's
/// offsets the alignment learned ([`GeoAlignment::mount`]).
pub fn convert_target(
    alignment: &GeoAlignment,
    map_from_cam: &Isometry3<f64>,
    frame: &LocalFrame,
    mount: &MountParams,
) -> Result<GeoTarget, GeoError> {
    target_from_ned(
        &alignment.ned_from_cam(map_from_cam),
        frame,
        &alignment.mount(mount),
    )
}
