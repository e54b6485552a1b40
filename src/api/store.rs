//! Shots on disk: one JSON file per shot (plus its desired-shot JPEG) in a
//! data directory, each written atomically (temp file, fsync, rename), and
//! listed again at start.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use serde::{Deserialize, Serialize};

/// Errors of the shot store.
#[derive(Debug, thiserror::Error)]
pub enum StoreError {
    /// A file could not be read or written.
    #[error("{what} {path}: {source}")]
    Io {
        /// What we were doing.
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A shot file could not be serialised.
    #[error("encoding shot {id}: {reason}")]
    Encode {
        /// The shot.
        id: String,
        /// serde's message.
        reason: String,
    },
}

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
        /// The intrinsics given with it (None: the map camera's, scaled).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        intrinsics: Option<super::shots::PhotoIntrinsics>,
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
}

/// A shot's mission on the vehicle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MissionRecord {
    /// `uploaded`, `started` (this session's actions), and as read back
    /// from the vehicle at start and at every reconnection (see
    /// `crate::daemon::reconcile`): `active`, `uploaded`, `finished`,
    /// `on_vehicle`, `replaced`, `cleared`, `unknown`; `details.vehicle`
    /// says why.
    pub state: String,
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

/// One desired shot and what became of it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Shot {
    /// Id (`shot-<n>`).
    pub id: String,
    /// Created, unix seconds.
    pub created_unix: f64,
    /// What the operator gave.
    pub source: ShotSource,
    /// `localised` or `not_localised`.
    pub status: String,
    /// The localisation, when it succeeded.
    pub localisation: Option<Localisation>,
    /// Why it did not, otherwise.
    pub reason: Option<String>,
    /// Whether a desired-shot image was stored (`GET .../image.jpg`).
    pub has_image: bool,
    /// The mission, once uploaded.
    pub mission: Option<MissionRecord>,
}

/// The shots, in memory and in `dir`.
#[derive(Debug)]
pub struct ShotStore {
    dir: PathBuf,
    shots: Mutex<BTreeMap<u64, Shot>>,
}

fn io<'a>(what: &'static str, path: &'a Path) -> impl FnOnce(std::io::Error) -> StoreError + 'a {
    move |source| StoreError::Io {
        what,
        path: path.to_owned(),
        source,
    }
}

/// Write `data` to `path` atomically: a temp file in the same directory,
/// flushed to disk, then renamed over the target.
pub fn write_atomic(path: &Path, data: &[u8]) -> Result<(), StoreError> {
    let dir = path.parent().unwrap_or(Path::new("."));
    let name = path.file_name().and_then(|n| n.to_str()).unwrap_or("file");
    let tmp = dir.join(format!(".{name}.tmp{}", std::process::id()));
    {
        let mut f = std::fs::File::create(&tmp).map_err(io("creating", &tmp))?;
        f.write_all(data).map_err(io("writing", &tmp))?;
        f.sync_all().map_err(io("syncing", &tmp))?;
    }
    std::fs::rename(&tmp, path).map_err(io("renaming to", path))?;
    Ok(())
}

/// The number in a shot id.
pub fn parse_id(id: &str) -> Option<u64> {
    id.strip_prefix("shot-")?.parse().ok()
}

impl ShotStore {
    /// Open (creating) `dir` and read every shot in it. Unreadable files
    /// are logged and skipped.
    pub fn open(dir: &Path) -> Result<Self, StoreError> {
        std::fs::create_dir_all(dir).map_err(io("creating", dir))?;
        let mut shots = BTreeMap::new();
        for entry in std::fs::read_dir(dir).map_err(io("listing", dir))? {
            let Ok(entry) = entry else { continue };
            let path = entry.path();
            if path.extension().and_then(|e| e.to_str()) != Some("json") {
                continue;
            }
            let parsed = std::fs::read(&path)
                .map_err(|e| e.to_string())
                .and_then(|b| serde_json::from_slice::<Shot>(&b).map_err(|e| e.to_string()));
            match parsed {
                Ok(shot) => match parse_id(&shot.id) {
                    Some(n) => {
                        shots.insert(n, shot);
                    }
                    None => tracing::warn!(path = %path.display(), "shot file with a bad id"),
                },
                Err(e) => tracing::warn!(path = %path.display(), "skipping shot file: {e}"),
            }
        }
        Ok(Self {
            dir: dir.to_owned(),
            shots: Mutex::new(shots),
        })
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<u64, Shot>> {
        self.shots.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The next free id.
    pub fn next_id(&self) -> String {
        let n = self.lock().keys().next_back().map_or(1, |k| k + 1);
        format!("shot-{n}")
    }

    /// Store (create or replace) a shot, and its desired-shot image if given.
    pub fn put(&self, shot: Shot, image_jpeg: Option<&[u8]>) -> Result<(), StoreError> {
        let Some(n) = parse_id(&shot.id) else {
            return Err(StoreError::Encode {
                id: shot.id.clone(),
                reason: "bad id".into(),
            });
        };
        if let Some(img) = image_jpeg {
            write_atomic(&self.dir.join(format!("{}.jpg", shot.id)), img)?;
        }
        let json = serde_json::to_vec_pretty(&shot).map_err(|e| StoreError::Encode {
            id: shot.id.clone(),
            reason: e.to_string(),
        })?;
        let mut shots = self.lock();
        write_atomic(&self.dir.join(format!("{}.json", shot.id)), &json)?;
        shots.insert(n, shot);
        Ok(())
    }

    /// Reads, changes and writes shot `id` under the store's lock, so that
    /// writers changing different parts of one record (the refinement loop
    /// its rounds, the reconciler the mission state) never undo each
    /// other's changes. Returns the shot as written; None: no such shot.
    pub fn update(
        &self,
        id: &str,
        change: impl FnOnce(&mut Shot),
    ) -> Result<Option<Shot>, StoreError> {
        let Some(n) = parse_id(id) else {
            return Ok(None);
        };
        let mut shots = self.lock();
        let Some(mut shot) = shots.get(&n).cloned() else {
            return Ok(None);
        };
        change(&mut shot);
        let json = serde_json::to_vec_pretty(&shot).map_err(|e| StoreError::Encode {
            id: shot.id.clone(),
            reason: e.to_string(),
        })?;
        write_atomic(&self.dir.join(format!("{}.json", shot.id)), &json)?;
        shots.insert(n, shot.clone());
        Ok(Some(shot))
    }

    /// A shot by id.
    pub fn get(&self, id: &str) -> Option<Shot> {
        self.lock().get(&parse_id(id)?).cloned()
    }

    /// All shots, oldest first.
    pub fn list(&self) -> Vec<Shot> {
        self.lock().values().cloned().collect()
    }

    /// A shot's desired-shot image.
    pub fn image(&self, id: &str) -> Option<Vec<u8>> {
        parse_id(id)?;
        std::fs::read(self.dir.join(format!("{id}.jpg"))).ok()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shot(id: &str) -> Shot {
        Shot {
            id: id.into(),
            created_unix: 1.5,
            source: ShotSource::Anchors {
                keyframe_id: 3,
                anchors: [[1.0, 2.0], [3.0, 2.0], [3.0, 4.0], [1.0, 4.0]],
            },
            status: "localised".into(),
            localisation: Some(Localisation {
                world_from_cam: PoseJson {
                    translation: [1.0, 2.0, 3.0],
                    rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
                },
                inliers: 42,
                rms_error_px: 0.7,
                keyframe_id: Some(3),
            }),
            reason: None,
            has_image: true,
            mission: None,
        }
    }

    #[test]
    fn shots_survive_reopen_and_ids_continue() {
        let dir = tempfile::tempdir().unwrap();
        let s = ShotStore::open(dir.path()).unwrap();
        assert_eq!(s.next_id(), "shot-1");
        s.put(shot("shot-1"), Some(&[0xFF, 0xD8, 1, 2])).unwrap();
        s.put(shot("shot-2"), None).unwrap();
        // A stray temp file and a corrupt file do not break the listing.
        std::fs::write(dir.path().join("shot-9.json"), b"{not json").unwrap();
        std::fs::write(dir.path().join(".shot-3.json.tmp1"), b"{}").unwrap();
        drop(s);
        let s = ShotStore::open(dir.path()).unwrap();
        let all = s.list();
        assert_eq!(all.len(), 2);
        assert_eq!(all[0], shot("shot-1"));
        assert_eq!(s.next_id(), "shot-3");
        assert_eq!(s.image("shot-1").unwrap(), vec![0xFF, 0xD8, 1, 2]);
        assert!(s.image("../etc/passwd").is_none());
        assert!(s.get("shot-x").is_none());
    }

    /// Two writers of one record, each from its own earlier read: with
    /// `update` neither undoes the other (the reconciler's state and the
    /// refinement loop's rounds both survive, also on disk).
    #[test]
    fn updates_of_different_parts_of_a_record_both_survive() {
        let dir = tempfile::tempdir().unwrap();
        let s = ShotStore::open(dir.path()).unwrap();
        let mut a = shot("shot-1");
        a.mission = Some(MissionRecord {
            state: "started".into(),
            items: 3,
            uploaded_unix: 1.0,
            started_unix: Some(2.0),
            target_lat_lon_alt: None,
            details: serde_json::json!({}),
        });
        s.put(a, None).unwrap();
        let seen_by_reconciler = s.get("shot-1").unwrap();
        // The loop writes its rounds after the reconciler read the list.
        s.update("shot-1", |x| {
            x.mission.as_mut().unwrap().details["refinement"] = serde_json::json!({"rounds": [1]});
        })
        .unwrap();
        let state = "active".to_string();
        assert_eq!(
            seen_by_reconciler.mission.unwrap().details["refinement"],
            serde_json::Value::Null
        );
        s.update("shot-1", |x| x.mission.as_mut().unwrap().state = state)
            .unwrap();
        assert!(
            s.update("shot-7", |_| panic!("no such shot"))
                .unwrap()
                .is_none()
        );
        drop(s);
        let s = ShotStore::open(dir.path()).unwrap();
        let m = s.get("shot-1").unwrap().mission.unwrap();
        assert_eq!(m.state, "active");
        assert_eq!(m.details["refinement"]["rounds"][0], 1);
    }
}
