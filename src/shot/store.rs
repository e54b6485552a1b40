//! Shots on disk: one JSON file per shot (plus its desired-shot JPEG) in a
//! data directory, each written atomically (temp file, fsync, rename), and
//! listed again at start.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

use super::record::Shot;

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

/// A shot write that failed.
#[derive(Debug, Clone, PartialEq)]
pub struct WriteFault {
    /// The shot.
    pub id: String,
    /// The error.
    pub message: String,
    /// When, unix seconds.
    pub at_unix: f64,
}

/// The shots, in memory and in `dir`.
#[derive(Debug)]
pub struct ShotStore {
    dir: PathBuf,
    shots: Mutex<BTreeMap<u64, Shot>>,
    /// The last write that failed, until a write succeeds again.
    fault: Mutex<Option<WriteFault>>,
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
            fault: Mutex::new(None),
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

    /// The last write that failed, while no write has succeeded since
    /// (the daemon's status shows it).
    pub fn write_error(&self) -> Option<WriteFault> {
        self.fault.lock().unwrap_or_else(|e| e.into_inner()).clone()
    }

    /// Remembers how a write of shot `id` ended.
    fn note<T>(&self, id: &str, r: Result<T, StoreError>) -> Result<T, StoreError> {
        let mut f = self.fault.lock().unwrap_or_else(|e| e.into_inner());
        match &r {
            Ok(_) => *f = None,
            Err(e) => {
                tracing::error!(shot = id, "writing the shot: {e}");
                *f = Some(WriteFault {
                    id: id.to_owned(),
                    message: e.to_string(),
                    at_unix: std::time::SystemTime::now()
                        .duration_since(std::time::UNIX_EPOCH)
                        .map_or(0.0, |d| d.as_secs_f64()),
                });
            }
        }
        r
    }

    /// Store (create or replace) a shot, and its desired-shot image if given.
    pub fn put(&self, shot: Shot, image_jpeg: Option<&[u8]>) -> Result<(), StoreError> {
        let id = shot.id.clone();
        let r = self.put_inner(shot, image_jpeg);
        self.note(&id, r)
    }

    fn put_inner(&self, shot: Shot, image_jpeg: Option<&[u8]>) -> Result<(), StoreError> {
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
        let r = self.update_inner(id, change);
        self.note(id, r)
    }

    fn update_inner(
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
    use crate::shot::record::{
        Localisation, MissionRecord, MissionState, PoseJson, ShotSource, ShotStatus,
    };

    fn shot(id: &str) -> Shot {
        Shot {
            id: id.into(),
            created_unix: 1.5,
            source: ShotSource::Anchors {
                keyframe_id: 3,
                anchors: [[1.0, 2.0], [3.0, 2.0], [3.0, 4.0], [1.0, 4.0]],
            },
            status: ShotStatus::Localised,
            localisation: Some(Localisation {
                sigma: None,
                world_from_cam: PoseJson {
                    translation: [1.0, 2.0, 3.0],
                    rotation_xyzw: [0.0, 0.0, 0.0, 1.0],
                },
                inliers: 42,
                rms_error_px: 0.7,
                keyframe_id: Some(3),
            }),
            reason: None,
            nearest_keyframes: Vec::new(),
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

    /// A write that fails (the data directory is gone) is remembered until
    /// a write succeeds again, and the record in memory is not changed.
    #[test]
    fn a_failed_write_is_remembered_until_a_write_succeeds() {
        let dir = tempfile::tempdir().unwrap();
        let data = dir.path().join("shots");
        let s = ShotStore::open(&data).unwrap();
        s.put(shot("shot-1"), None).unwrap();
        assert_eq!(s.write_error(), None);
        std::fs::remove_dir_all(&data).unwrap();
        assert!(s.put(shot("shot-2"), None).is_err());
        let f = s.write_error().expect("the failure is remembered");
        assert_eq!(f.id, "shot-2");
        assert!(f.message.contains("shot-2.json"), "{}", f.message);
        assert!(s.update("shot-1", |x| x.has_image = false).is_err());
        assert_eq!(s.write_error().unwrap().id, "shot-1");
        assert!(s.get("shot-1").unwrap().has_image);
        assert!(s.get("shot-2").is_none());
        std::fs::create_dir_all(&data).unwrap();
        s.put(shot("shot-2"), None).unwrap();
        assert_eq!(s.write_error(), None);
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
            state: MissionState::Started,
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
        let state = MissionState::Active;
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
        assert_eq!(m.state, MissionState::Active);
        assert_eq!(m.details["refinement"]["rounds"][0], 1);
    }
}
