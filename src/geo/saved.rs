//! The georeference as it is saved beside the map, so that a continued map
//! is georeferenced at start: the telemetry side of every pair (the camera
//! pose in local NED at the pair's capture time, its velocity) and what
//! the pair's map side hangs from (a keyframe, by id and capture time, and
//! the camera's pose relative to it). The map side itself is not saved: it
//! is read from the loaded map's keyframes, so a bundle adjustment that
//! moved them (the final one at shutdown, those of the next run) moves the
//! pairs with them.
//!
//! NED is the tangent frame at the saved home; [`SavedPair::rebased`]
//! carries a pair to another home exactly (through ECEF), for a vehicle
//! whose HOME_POSITION changed between the sessions.

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};
use serde::{Deserialize, Serialize};

use super::wgs84::{Geodetic, LocalFrame};

/// The file format this build writes and reads.
pub const SAVED_FORMAT: u32 = 1;

/// A pose as saved: translation and quaternion (x, y, z, w).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SavedPose {
    /// Translation.
    pub translation: [f64; 3],
    /// Rotation quaternion, scalar last.
    pub rotation_xyzw: [f64; 4],
}

impl SavedPose {
    /// From an isometry.
    pub fn from_isometry(p: &Isometry3<f64>) -> Self {
        let t = p.translation.vector;
        let q = p.rotation.coords;
        Self {
            translation: [t.x, t.y, t.z],
            rotation_xyzw: [q.x, q.y, q.z, q.w],
        }
    }

    /// Back to an isometry; None when a number is not finite or the
    /// quaternion is far from unit.
    pub fn to_isometry(&self) -> Option<Isometry3<f64>> {
        let [x, y, z, w] = self.rotation_xyzw;
        let q = Quaternion::new(w, x, y, z);
        let ok = self
            .translation
            .iter()
            .chain(&self.rotation_xyzw)
            .all(|v| v.is_finite())
            && (q.norm() - 1.0).abs() < 1e-3;
        ok.then(|| {
            Isometry3::from_parts(
                Translation3::from(Vector3::from(self.translation)),
                UnitQuaternion::from_quaternion(q),
            )
        })
    }
}

/// What a pair is made of.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PairKind {
    /// A keyframe paired with the telemetry of its capture time.
    Keyframe,
    /// A tracked frame (placed relative to its reference keyframe) paired
    /// with the telemetry of its capture time.
    Frame,
}

/// One pair as saved.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SavedPair {
    /// The pair's id in the georeference (a keyframe's id, or a frame's).
    pub id: u64,
    /// Keyframe or tracked frame.
    pub kind: PairKind,
    /// The keyframe the map side hangs from.
    pub anchor_kf: u64,
    /// That keyframe's capture time (identifies it: the pair is only
    /// restored onto a keyframe with this id and this time).
    pub anchor_time: f64,
    /// The camera relative to the anchor keyframe (`cam ← kf_cam`; the
    /// identity for a keyframe's own pair).
    pub cam_from_anchor: SavedPose,
    /// Capture time of the pair, seconds (unix).
    pub time: f64,
    /// The camera pose in local NED at `time`, from telemetry.
    pub ned_from_cam: SavedPose,
    /// The camera's NED velocity at `time`, m/s.
    pub v_ned: Option<[f64; 3]>,
}

impl SavedPair {
    /// The pair in the NED frame of `to` instead of `from`.
    pub fn rebased(&self, from: &LocalFrame, to: &LocalFrame) -> Option<SavedPair> {
        let to_from = to.ned_from_other(from);
        let ned = self.ned_from_cam.to_isometry()?;
        Some(SavedPair {
            ned_from_cam: SavedPose::from_isometry(&(to_from * ned)),
            v_ned: self
                .v_ned
                .map(|v| (to_from.rotation * Vector3::from(v)).into()),
            ..*self
        })
    }

    /// The map side, given the anchor keyframe's `cam_from_world`.
    pub fn map_from_cam(&self, anchor_cam_from_world: &Isometry3<f64>) -> Option<Isometry3<f64>> {
        let cam_from_anchor = self.cam_from_anchor.to_isometry()?;
        Some((cam_from_anchor * anchor_cam_from_world).inverse())
    }
}

/// The fit when the file was written (for the record; the fit at start is
/// made again from the pairs).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SavedFit {
    /// Scale of `ned ← map`.
    pub scale: f64,
    /// RMS of the inliers' position residuals, metres.
    pub rms_m: f64,
    /// Inliers.
    pub inliers: usize,
    /// Pairs.
    pub pairs: usize,
}

/// The georeference file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SavedGeoreference {
    /// [`SAVED_FORMAT`].
    pub format: u32,
    /// When it was written, unix seconds.
    pub saved_unix: f64,
    /// Home: the origin of the NED frame of the pairs.
    pub home: Geodetic,
    /// The pairs.
    pub pairs: Vec<SavedPair>,
    /// The fit at the time of writing, if there was one.
    pub fit: Option<SavedFit>,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_rebased_pair_is_the_same_place_and_a_file_round_trips() {
        let home = Geodetic {
            lat_deg: 47.397742,
            lon_deg: 8.545594,
            alt_m: 488.0,
        };
        let other = Geodetic {
            lat_deg: 47.3981,
            lon_deg: 8.5449,
            alt_m: 491.5,
        };
        let (a, b) = (LocalFrame::new(home), LocalFrame::new(other));
        let ned = Isometry3::from_parts(
            Translation3::new(12.0, -30.0, -15.0),
            UnitQuaternion::from_euler_angles(0.1, -0.7, 2.0),
        );
        let pair = SavedPair {
            id: 7,
            kind: PairKind::Keyframe,
            anchor_kf: 7,
            anchor_time: 1.7e9,
            cam_from_anchor: SavedPose::from_isometry(&Isometry3::identity()),
            time: 1.7e9,
            ned_from_cam: SavedPose::from_isometry(&ned),
            v_ned: Some([1.0, 2.0, 0.5]),
        };
        let moved = pair.rebased(&a, &b).unwrap();
        let p_b = moved.ned_from_cam.to_isometry().unwrap().translation.vector;
        let g = b.ned_to_geodetic(&p_b);
        let g0 = a.ned_to_geodetic(&ned.translation.vector);
        assert!((g.lat_deg - g0.lat_deg).abs() < 1e-10 && (g.alt_m - g0.alt_m).abs() < 1e-6);
        let v: Vector3<f64> = Vector3::from(moved.v_ned.unwrap());
        let v0: Vector3<f64> = Vector3::new(1.0, 2.0, 0.5);
        assert!((v.norm() - v0.norm()).abs() < 1e-12);
        let back = moved.rebased(&b, &a).unwrap();
        let d = back.ned_from_cam.to_isometry().unwrap().inverse() * ned;
        assert!(d.translation.vector.norm() < 1e-6 && d.rotation.angle() < 1e-9);
        let file = SavedGeoreference {
            format: SAVED_FORMAT,
            saved_unix: 1.7e9,
            home,
            pairs: vec![pair, moved],
            fit: None,
        };
        let text = serde_json::to_string(&file).unwrap();
        let read: SavedGeoreference = serde_json::from_str(&text).unwrap();
        // serde_json's default float parsing may differ from the written
        // number in the last bit: the same file to within that.
        assert_eq!(
            (read.format, read.home.lat_deg),
            (file.format, file.home.lat_deg)
        );
        assert_eq!(read.pairs.len(), 2);
        for (r, w) in read.pairs.iter().zip(&file.pairs) {
            let d = r.ned_from_cam.to_isometry().unwrap().inverse()
                * w.ned_from_cam.to_isometry().unwrap();
            assert!(d.translation.vector.norm() < 1e-9 && d.rotation.angle() < 1e-12);
            assert_eq!((r.id, r.kind, r.anchor_kf), (w.id, w.kind, w.anchor_kf));
        }
        // A broken pose is refused, not trusted.
        let bad = SavedPose {
            translation: [0.0; 3],
            rotation_xyzw: [0.0, 0.0, 0.0, 0.2],
        };
        assert!(bad.to_isometry().is_none());
    }
}
