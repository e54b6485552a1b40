//! The shot model: one desired shot and what became of it (where it came
//! from, its localisation in the map, its mission on the vehicle), as the
//! shot store keeps it on disk and the API returns it.

use serde::{Deserialize, Serialize};

use crate::camera::{Camera, CameraError, Distortion};

/// A camera pose as JSON: `world_from_cam` translation and rotation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PoseJson {
    /// Camera centre in the map frame.
    pub translation: [f64; 3],
    /// Rotation quaternion (x, y, z, w) of `world_from_cam`.
    pub rotation_xyzw: [f64; 4],
}

impl PoseJson {
    /// From an isometry (`world_from_cam`).
    pub fn from_isometry(world_from_cam: &nalgebra::Isometry3<f64>) -> Self {
        let t = world_from_cam.translation.vector;
        let q = world_from_cam.rotation.coords;
        Self {
            translation: [t.x, t.y, t.z],
            rotation_xyzw: [q.x, q.y, q.z, q.w],
        }
    }

    /// Back to an isometry (`world_from_cam`); None when a number is not
    /// finite or the quaternion is (nearly) zero. The quaternion is
    /// normalised.
    pub fn to_isometry(&self) -> Option<nalgebra::Isometry3<f64>> {
        let [x, y, z, w] = self.rotation_xyzw;
        let q = nalgebra::Quaternion::new(w, x, y, z);
        let t = nalgebra::Vector3::from(self.translation);
        if !(q.coords.iter().all(|v| v.is_finite()) && t.iter().all(|v| v.is_finite()))
            || q.norm() < 1e-9
        {
            return None;
        }
        Some(nalgebra::Isometry3::from_parts(
            t.into(),
            nalgebra::UnitQuaternion::from_quaternion(q),
        ))
    }
}

/// Where a desired shot came from.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum ShotSource {
    /// Four anchors on a keyframe (pixels, clockwise from top-left of the
    /// desired picture).
    Anchors {
        /// The keyframe.
        keyframe_id: u64,
        /// The corners of the desired picture in the keyframe, pixels.
        anchors: [[f64; 2]; 4],
    },
    /// An uploaded photograph.
    Photo {
        /// Its size in bytes.
        bytes: usize,
        /// Width, pixels.
        width: u32,
        /// Height, pixels.
        height: u32,
        /// The intrinsics given with it, or read from its EXIF (then with
        /// their sigmas); None: the map camera's, scaled.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        intrinsics: Option<PhotoIntrinsics>,
    },
}

/// The localisation of a desired shot: the camera pose that takes it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Localisation {
    /// The target camera pose in the map frame.
    pub world_from_cam: PoseJson,
    /// PnP inliers.
    pub inliers: usize,
    /// RMS reprojection error of the inliers, pixels.
    pub rms_error_px: f64,
    /// The keyframe the match went through.
    pub keyframe_id: Option<u64>,
    /// The pose's uncertainty (absent in shot files written before it was
    /// reported).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub sigma: Option<LocalisationSigma>,
}

/// The uncertainty of a localisation: the RMS errors its covariance
/// predicts (about 61 % of true errors within one, 99 % within two).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LocalisationSigma {
    /// Camera centre, map units.
    pub position: f64,
    /// Camera centre as a fraction of the distance to the nearest scene
    /// content (the smaller of the 10 % quantiles of the inliers' depths
    /// and of the depths of the map points in the shot's view).
    pub position_fraction_of_distance: f64,
    /// Orientation, degrees.
    pub rotation_deg: f64,
}

/// Whether a desired shot was localised in the map.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShotStatus {
    /// The camera pose that takes it was found (`localisation`).
    Localised,
    /// It was not (`reason` says why).
    NotLocalised,
}

impl ShotStatus {
    /// The name the API and the shot files use.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Localised => "localised",
            Self::NotLocalised => "not_localised",
        }
    }
}

/// The state of a shot's mission: `Uploaded` and `Started` by this
/// daemon's actions, and every state as read back from the vehicle at
/// start and at every reconnection (the daemon's reconciler).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MissionState {
    /// Uploaded (and confirmed), not started; or the vehicle holds it, not
    /// started.
    Uploaded,
    /// Started by the operator in this session.
    Started,
    /// The vehicle flies it.
    Active,
    /// The vehicle flew it to its last item.
    Finished,
    /// The vehicle holds it but does not say how far it is.
    OnVehicle,
    /// The vehicle holds another mission.
    Replaced,
    /// The vehicle holds no mission.
    Cleared,
    /// The vehicle's mission could not be read.
    Unknown,
    /// The operator stopped the vehicle (held in place) while it flew this
    /// mission; `details.stop` says why and what the vehicle acknowledged.
    Stopped,
}

impl MissionState {
    /// The name the API and the shot files use.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Uploaded => "uploaded",
            Self::Started => "started",
            Self::Active => "active",
            Self::Finished => "finished",
            Self::OnVehicle => "on_vehicle",
            Self::Replaced => "replaced",
            Self::Cleared => "cleared",
            Self::Unknown => "unknown",
            Self::Stopped => "stopped",
        }
    }
}

impl std::fmt::Display for MissionState {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.as_str())
    }
}

/// A shot's mission on the vehicle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MissionRecord {
    /// What became of it (see [`MissionState`]); `details.vehicle` says
    /// why when the vehicle's mission set it.
    pub state: MissionState,
    /// Mission items uploaded.
    pub items: usize,
    /// Upload confirmed (unix seconds).
    pub uploaded_unix: f64,
    /// Started (unix seconds).
    pub started_unix: Option<f64>,
    /// Target position, WGS84 degrees and metres AMSL, when georeferenced.
    pub target_lat_lon_alt: Option<[f64; 3]>,
    /// Free-form details from the planner/uploader.
    pub details: serde_json::Value,
}

impl MissionRecord {
    /// Sets `details[key]` (details that are not an object become
    /// `{"previous": ..}`, null becomes `{}`; other keys are kept).
    pub fn set_detail(&mut self, key: &str, value: serde_json::Value) {
        if !self.details.is_object() {
            let previous = std::mem::take(&mut self.details);
            self.details = if previous.is_null() {
                serde_json::json!({})
            } else {
                serde_json::json!({ "previous": previous })
            };
        }
        if let Some(obj) = self.details.as_object_mut() {
            obj.insert(key.into(), value);
        }
    }

    /// The target this mission flies now: its refinement loop's latest
    /// correction (`details.refinement.target`), else the target of its
    /// upload (`details.target`); None when the details hold neither.
    pub fn flown_target(&self) -> Option<crate::mission::plan::Target> {
        let d = &self.details;
        if let Some(t) = d
            .get("refinement")
            .and_then(|r| r.get("target"))
            .and_then(|t| serde_json::from_value(t.clone()).ok())
        {
            return Some(t);
        }
        let t = d.get("target")?;
        let f = |k: &str| t.get(k).and_then(serde_json::Value::as_f64);
        Some(crate::mission::plan::Target {
            lat_deg: f("lat_deg")?,
            lon_deg: f("lon_deg")?,
            alt_m: f("alt_above_home_m")?,
            yaw_deg: f("yaw_deg")?,
            gimbal_pitch_deg: f("gimbal_pitch_deg")?,
            photo: true,
        })
    }

    /// Adds a picture the vehicle's camera reported (`details.photos`, at
    /// most [`PHOTOS_KEPT`], newest last; a picture already there, by
    /// camera and index, is not added again): its index, the position and
    /// attitude the camera gave, where it stored it.
    pub fn record_photo(&mut self, photo: &crate::vehicle::ImageCaptured) {
        let mut photos = self
            .details
            .get("photos")
            .and_then(|p| p.as_array().cloned())
            .unwrap_or_default();
        let entry = serde_json::to_value(photo).unwrap_or_default();
        if photos
            .iter()
            .any(|p| p["component_id"] == entry["component_id"] && p["index"] == entry["index"])
        {
            return;
        }
        photos.push(entry);
        if photos.len() > PHOTOS_KEPT {
            photos.remove(0);
        }
        self.set_detail("photos", serde_json::Value::Array(photos));
    }
}

/// Photos kept in a mission record (`details.photos`), newest last.
pub const PHOTOS_KEPT: usize = 50;

/// One desired shot and what became of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Shot {
    /// Id (`shot-<n>`).
    pub id: String,
    /// Created, unix seconds.
    pub created_unix: f64,
    /// What the operator gave.
    pub source: ShotSource,
    /// Whether it was localised.
    pub status: ShotStatus,
    /// The localisation, when it succeeded.
    pub localisation: Option<Localisation>,
    /// Why it did not, otherwise.
    pub reason: Option<String>,
    /// Whether a desired-shot image was stored (`GET .../image.jpg`).
    pub has_image: bool,
    /// The mission, once uploaded.
    pub mission: Option<MissionRecord>,
    /// When it was not localised: the keyframes the shot looks most like,
    /// best first, with where they are ("fly towards here"); empty
    /// otherwise (and in shot files written before it was reported).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub nearest_keyframes: Vec<NearKeyframeJson>,
}

/// A keyframe a shot that was not localised looks like.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NearKeyframeJson {
    /// The keyframe (`GET /keyframes/{id}/image.jpg` shows it).
    pub keyframe_id: u64,
    /// Bag-of-words similarity to the shot, 0 to 1.
    pub score: f64,
    /// The keyframe's camera centre, map frame.
    pub position: [f64; 3],
    /// Where its picture is served (`/api/v1/keyframes/{id}/image.jpg`;
    /// empty in shot files written before it was reported).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub image_url: String,
}

impl NearKeyframeJson {
    /// The API path of keyframe `id`'s picture.
    pub fn image_url_of(id: u64) -> String {
        format!("/api/v1/keyframes/{id}/image.jpg")
    }
}

/// The intrinsics of a photo from another camera (pinhole with OpenCV's
/// radial-tangential distortion, pixel centres at integers, for the photo's
/// own size).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhotoIntrinsics {
    /// Focal length x, pixels.
    pub fx: f64,
    /// Focal length y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Distortion (zero when not given).
    #[serde(default)]
    pub distortion: Distortion,
    /// How well the focal length is known, as a fraction of it: 0 for
    /// intrinsics the operator gave; set when they were read from the
    /// photo's EXIF (the pose is then estimated with the focal length and
    /// `k1`, and its sigma includes what they leave open).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub focal_rel_sigma: f64,
    /// How well `k1` is known (0: given; EXIF gives no distortion).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub k1_sigma: f64,
    /// How well `k2` is known.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub k2_sigma: f64,
}

fn is_zero(v: &f64) -> bool {
    *v == 0.0
}

impl PhotoIntrinsics {
    /// The camera of a `width` x `height` photo with these intrinsics.
    pub fn camera(&self, width: u32, height: u32) -> Result<Camera, CameraError> {
        Camera::new(
            width,
            height,
            [self.fx, self.fy, self.cx, self.cy],
            self.distortion,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A started mission's record with these details.
    fn started(details: serde_json::Value) -> MissionRecord {
        MissionRecord {
            state: MissionState::Started,
            items: 5,
            uploaded_unix: 0.0,
            started_unix: None,
            target_lat_lon_alt: None,
            details,
        }
    }

    #[test]
    fn photos_are_kept_once_each_and_bounded() {
        let photo = |index: i32| crate::vehicle::ImageCaptured {
            component_id: 100,
            index,
            time_utc_us: 1_700_000_000_000_000,
            lat_deg: 47.397_742,
            lon_deg: 8.545_594,
            alt_amsl_m: 508.0,
            relative_alt_m: 20.0,
            q: [1.0, 0.0, 0.0, 0.0],
            ok: true,
            file_url: format!("file:///captures/{index}.jpg"),
        };
        let mut m = started(serde_json::json!({"planned_items": []}));
        m.record_photo(&photo(0));
        m.record_photo(&photo(0));
        m.record_photo(&photo(1));
        let photos = m.details["photos"].as_array().unwrap();
        assert_eq!(photos.len(), 2, "one entry per picture");
        assert_eq!(photos[1]["index"], 1);
        assert_eq!(photos[1]["lat_deg"], 47.397_742);
        assert_eq!(photos[1]["file_url"], "file:///captures/1.jpg");
        assert!(
            m.details.get("planned_items").is_some(),
            "other details kept"
        );
        for i in 2..80 {
            m.record_photo(&photo(i));
        }
        let photos = m.details["photos"].as_array().unwrap();
        assert_eq!(photos.len(), PHOTOS_KEPT);
        assert_eq!(photos.last().unwrap()["index"], 79);
    }

    /// The refinement's latest correction wins over the uploaded target;
    /// without either there is none.
    #[test]
    fn the_flown_target_is_the_latest_correction_else_the_upload() {
        let mut m = started(serde_json::json!({}));
        assert!(m.flown_target().is_none());
        m.set_detail(
            "target",
            serde_json::json!({"lat_deg": 47.1, "lon_deg": 8.5, "alt_above_home_m": 20.0,
                "alt_m": 520.0, "yaw_deg": 90.0, "gimbal_pitch_deg": -30.0}),
        );
        let t = m.flown_target().unwrap();
        assert_eq!(
            (t.lat_deg, t.alt_m, t.yaw_deg, t.photo),
            (47.1, 20.0, 90.0, true)
        );
        let corrected = crate::mission::plan::Target { lat_deg: 47.2, ..t };
        m.set_detail(
            "refinement",
            serde_json::json!({"target": serde_json::to_value(corrected).unwrap()}),
        );
        assert_eq!(m.flown_target().unwrap().lat_deg, 47.2);
    }

    /// The API and the page read these names; shot files written before
    /// the enums carry them too.
    #[test]
    fn states_serialise_to_the_names_the_api_uses() {
        for s in [
            MissionState::Uploaded,
            MissionState::Started,
            MissionState::Active,
            MissionState::Finished,
            MissionState::OnVehicle,
            MissionState::Replaced,
            MissionState::Cleared,
            MissionState::Unknown,
        ] {
            let j = serde_json::to_value(s).unwrap();
            assert_eq!(j, s.as_str());
            assert_eq!(serde_json::from_value::<MissionState>(j).unwrap(), s);
        }
        for s in [ShotStatus::Localised, ShotStatus::NotLocalised] {
            assert_eq!(serde_json::to_value(s).unwrap(), s.as_str());
        }
        assert_eq!(MissionState::OnVehicle.as_str(), "on_vehicle");
        assert_eq!(ShotStatus::NotLocalised.as_str(), "not_localised");
        assert!(serde_json::from_value::<MissionState>("flying".into()).is_err());
    }

    #[test]
    fn a_detail_is_set_beside_the_others() {
        let mut m = MissionRecord {
            state: MissionState::Started,
            items: 3,
            uploaded_unix: 1.0,
            started_unix: None,
            target_lat_lon_alt: None,
            details: serde_json::Value::Null,
        };
        m.set_detail("a", 1.into());
        m.set_detail("b", 2.into());
        assert_eq!(m.details, serde_json::json!({"a": 1, "b": 2}));
        m.details = "uploaded".into();
        m.set_detail("a", 3.into());
        assert_eq!(
            m.details,
            serde_json::json!({"previous": "uploaded", "a": 3})
        );
    }
}
