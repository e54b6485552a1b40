//! What the daemon keeps on disk besides the shots: the map file and, beside
//! it, the georeference tied to it (`<map_file>.geo.json`).
//!
//! Both are written at shutdown (the map after the final bundle
//! adjustment) and at checkpoints while the daemon runs
//! (`[slam] checkpoint_s`, when the map changed), each atomically (a
//! temporary file flushed to disk, then renamed), so a crash or a kill
//! loses at most one checkpoint period of mapping and never leaves a
//! half-written file in place. Keyframe images are stored as the bytes the
//! video delivered ([`KeyframeImages`]): a reloaded keyframe is the same
//! picture, so a shot on it is the same shot. At start, temporary files
//! that an interrupted write left behind are removed.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, MutexGuard};

use super::geo_service::GeoService;
use super::slam_shared::SlamShared;
use crate::api::MapSaved;
use crate::geo::saved::SavedGeoreference;
use crate::shot::store::write_atomic;
use crate::slam::mapfile::{self, KeyframeImages, MapFileError};
use crate::slam::{KeyFrameId, Map};
use crate::video::live::unix_now;

/// The georeference file beside a map file.
pub fn geo_path(map_file: &Path) -> PathBuf {
    mapfile::beside(map_file, ".geo.json")
}

/// Reads the georeference saved beside `map_file`: None when there is
/// none; a file that cannot be read is moved aside (logged) and None.
pub fn load_geo(map_file: &Path) -> Option<SavedGeoreference> {
    let path = geo_path(map_file);
    let bytes = match std::fs::read(&path) {
        Ok(b) => b,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return None,
        Err(e) => {
            tracing::warn!(path = %path.display(), "cannot read the saved georeference: {e}");
            return None;
        }
    };
    match serde_json::from_slice::<SavedGeoreference>(&bytes) {
        Ok(s) => Some(s),
        Err(e) => {
            let aside = set_aside(&path, "unusable");
            tracing::warn!(
                path = %path.display(),
                moved_to = ?aside,
                "the saved georeference is unreadable and was set aside: {e}"
            );
            None
        }
    }
}

/// Removes the temporary files an interrupted write left in `data_dir`
/// (the map's `<map_file>.tmp`, and `.<name>.tmp<pid>` files of the shot
/// store and the georeference); returns what was removed.
pub fn remove_leftovers(data_dir: &Path, map_file: &Path) -> Vec<PathBuf> {
    let mut removed = Vec::new();
    let map_tmp = mapfile::temp_path(map_file);
    let mut dirs = vec![data_dir.to_owned(), data_dir.join("shots")];
    if let Some(d) = map_file.parent() {
        dirs.push(d.to_owned());
    }
    dirs.sort();
    dirs.dedup();
    for dir in dirs {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let path = e.path();
            let name = e.file_name().to_string_lossy().into_owned();
            if path == map_tmp || is_atomic_temp(&name) {
                match std::fs::remove_file(&path) {
                    Ok(()) => {
                        tracing::warn!(path = %path.display(), "removed a file an interrupted write left");
                        removed.push(path);
                    }
                    Err(err) => {
                        tracing::warn!(path = %path.display(), "cannot remove a leftover file: {err}")
                    }
                }
            }
        }
    }
    removed
}

/// `.<name>.tmp<digits>`: [`write_atomic`]'s temporary files.
fn is_atomic_temp(name: &str) -> bool {
    name.starts_with('.')
        && name
            .rsplit_once(".tmp")
            .is_some_and(|(_, pid)| !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit()))
}

/// Frames whose JPEG is kept until the keyframe made from them is known
/// (the initialisation's first keyframe comes from a frame seconds old).
const RECENT_FRAMES: usize = 128;

/// The map file and the georeference beside it: who writes them, with
/// which keyframe images, and what was written last.
pub struct MapPersist {
    path: Mutex<PathBuf>,
    images: Mutex<KeyframeImages>,
    /// JPEGs of recent frames by ingest sequence number.
    recent: Mutex<VecDeque<(u64, Arc<Vec<u8>>)>>,
    /// Keyframes whose source JPEG is offered at the next save.
    offered: Mutex<Vec<(KeyFrameId, Arc<Vec<u8>>)>>,
    /// Serialises the writes.
    writing: Mutex<()>,
    /// Keyframes, points and next keyframe id of the map last written.
    written: Mutex<Option<(usize, usize, u32)>>,
    shared: Arc<SlamShared>,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

impl MapPersist {
    /// Writes to `map_file`; reports to `shared`'s status.
    pub fn new(map_file: PathBuf, shared: Arc<SlamShared>) -> Self {
        Self {
            path: Mutex::new(map_file),
            images: Mutex::new(KeyframeImages::default()),
            recent: Mutex::new(VecDeque::new()),
            offered: Mutex::new(Vec::new()),
            writing: Mutex::new(()),
            written: Mutex::new(None),
            shared,
        }
    }

    /// The map file.
    pub fn path(&self) -> PathBuf {
        lock(&self.path).clone()
    }

    /// Writes to another file from now on (the old one could not be moved
    /// aside).
    pub fn set_path(&self, path: PathBuf) {
        *lock(&self.path) = path;
    }

    /// A map was loaded from the file with these stored images: they are
    /// written again as they are, and the map is not rewritten until it
    /// changes.
    pub fn loaded(&self, map: &Map, images: KeyframeImages) {
        *lock(&self.images) = images;
        *lock(&self.written) = Some(signature(map));
    }

    /// A frame went to the SLAM: its JPEG is kept a while, in case it
    /// becomes a keyframe.
    pub fn note_frame(&self, seq: u64, jpeg: &Arc<Vec<u8>>) {
        let mut r = lock(&self.recent);
        if r.len() == RECENT_FRAMES {
            r.pop_front();
        }
        r.push_back((seq, jpeg.clone()));
    }

    /// A keyframe was made from frame `seq`: its JPEG is offered as the
    /// keyframe image's stored form.
    pub fn note_keyframe(&self, id: KeyFrameId, seq: u64) {
        let jpeg = lock(&self.recent)
            .iter()
            .find(|(s, _)| *s == seq)
            .map(|(_, j)| j.clone());
        if let Some(j) = jpeg {
            lock(&self.offered).push((id, j));
        }
    }

    /// Whether `map` differs (keyframes, points, ids) from the map last
    /// written or loaded.
    pub fn changed(&self, map: &Map) -> bool {
        *lock(&self.written) != Some(signature(map))
    }

    /// Writes `map` (atomically) and, when `geo` is given, the
    /// georeference beside it; records what was written in the status.
    pub fn save(
        &self,
        map: &Map,
        geo: Option<&GeoService>,
        reason: &str,
    ) -> Result<MapSaved, MapFileError> {
        let r = self.save_map(map, geo, reason);
        if let Err(e) = &r {
            self.shared
                .set_map_save_error("map", Some(format!("{}: {e}", self.path().display())));
        }
        r
    }

    fn save_map(
        &self,
        map: &Map,
        geo: Option<&GeoService>,
        reason: &str,
    ) -> Result<MapSaved, MapFileError> {
        let _w = lock(&self.writing);
        let path = self.path();
        if let Some(dir) = path.parent() {
            let _ = std::fs::create_dir_all(dir);
        }
        let mut images = lock(&self.images);
        for (id, jpeg) in std::mem::take(&mut *lock(&self.offered)) {
            if let Some(img) = map.keyframe(id).and_then(|k| k.image.as_ref())
                && !images.offer(id, jpeg, img)
            {
                tracing::debug!(
                    kf = id.0,
                    "keyframe image is not its frame's JPEG: stored as PNG"
                );
            }
        }
        images.retain_in(map);
        mapfile::save_with(map, &path, &mut images)?;
        drop(images);
        *lock(&self.written) = Some(signature(map));
        let bytes = std::fs::metadata(&path).map_or(0, |m| m.len());
        let geo_pairs = geo.and_then(|g| self.save_geo(g));
        let saved = MapSaved {
            reason: reason.into(),
            keyframes: map.keyframe_count(),
            points: map.point_count(),
            bytes,
            geo_pairs,
            at_unix: unix_now(),
        };
        tracing::info!(
            path = %path.display(),
            reason,
            keyframes = saved.keyframes,
            points = saved.points,
            bytes,
            geo_pairs,
            "map saved"
        );
        self.shared.set_map_saved(saved.clone());
        Ok(saved)
    }

    /// Writes the georeference beside the map file; the pairs written.
    pub fn save_geo(&self, geo: &GeoService) -> Option<usize> {
        let saved = geo.saved()?;
        let path = geo_path(&self.path());
        let n = saved.pairs.len();
        let written = serde_json::to_vec_pretty(&saved)
            .map_err(|e| format!("encoding the georeference: {e}"))
            .and_then(|text| write_atomic(&path, &text).map_err(|e| e.to_string()));
        match written {
            Ok(()) => {
                self.shared.set_map_save_error("georeference", None);
                Some(n)
            }
            Err(e) => {
                tracing::error!("saving the georeference: {e}");
                self.shared.set_map_save_error("georeference", Some(e));
                None
            }
        }
    }

    /// One checkpoint: the SLAM's current map, when it has keyframes and
    /// changed since the last write, and the georeference.
    pub fn checkpoint(&self, geo: &GeoService) {
        let Some(map) = self.shared.map_snapshot() else {
            return;
        };
        if map.keyframe_count() == 0 {
            return;
        }
        if !self.changed(&map) {
            // The map is as written; the georeference may have grown.
            self.save_geo(geo);
            return;
        }
        if let Err(e) = self.save(&map, Some(geo), "checkpoint") {
            tracing::error!("map checkpoint: {e}");
        }
    }
}

fn signature(map: &Map) -> (usize, usize, u32) {
    (
        map.keyframe_count(),
        map.point_count(),
        map.next_keyframe_id().0,
    )
}

/// A name beside `path` that is not taken: `<name>.<tag>-<unix seconds>`,
/// with `-2`, `-3`, ... appended when needed.
pub fn unused_name(path: &Path, tag: &str) -> PathBuf {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "map".into());
    let stamp = unix_now().max(0.0) as u64;
    let base = path.with_file_name(format!("{name}.{tag}-{stamp}"));
    let mut candidate = base.clone();
    let mut n = 2;
    while candidate.exists() {
        candidate = path.with_file_name(format!("{name}.{tag}-{stamp}-{n}"));
        n += 1;
    }
    candidate
}

/// Move `path` to an unused name beside it; the new path, or None (logged)
/// when it cannot be moved. A map file takes the georeference saved beside
/// it along (same tag).
pub fn set_aside(path: &Path, tag: &str) -> Option<PathBuf> {
    let geo = geo_path(path);
    if path.extension().is_some_and(|e| e != "json") && geo.exists() {
        let to = unused_name(&geo, tag);
        if let Err(e) = std::fs::rename(&geo, &to) {
            tracing::error!(path = %geo.display(), "cannot move the saved georeference aside: {e}");
        }
    }
    let to = unused_name(path, tag);
    match std::fs::rename(path, &to) {
        Ok(()) => Some(to),
        Err(e) => {
            tracing::error!(
                path = %path.display(),
                to = %to.display(),
                "cannot move the map file aside: {e}"
            );
            None
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn leftovers_of_interrupted_writes_are_removed_and_nothing_else() {
        let dir = tempfile::tempdir().unwrap();
        let d = dir.path();
        std::fs::create_dir_all(d.join("shots")).unwrap();
        let map = d.join("map.spmap");
        let keep = [
            map.clone(),
            geo_path(&map),
            d.join("shots/shot-1.json"),
            d.join("shots/shot-1.jpg"),
            d.join("map.spmap.unusable-1700000000"),
            d.join(".hidden"),
            d.join("notes.tmp"),
        ];
        let gone = [
            mapfile::temp_path(&map),
            d.join(".map.spmap.geo.json.tmp4242"),
            d.join("shots/.shot-2.json.tmp17"),
            d.join("shots/.shot-2.jpg.tmp17"),
        ];
        for f in keep.iter().chain(&gone) {
            std::fs::write(f, b"x").unwrap();
        }
        let mut removed = remove_leftovers(d, &map);
        removed.sort();
        let mut expected = gone.to_vec();
        expected.sort();
        assert_eq!(removed, expected);
        for f in &keep {
            assert!(f.exists(), "{}", f.display());
        }
        assert_eq!(geo_path(&map), d.join("map.spmap.geo.json"));
    }

    /// A map file that cannot be written (its folder is a file) shows in
    /// the status as `map_save_error` until a write succeeds.
    #[test]
    fn a_failed_map_save_is_in_the_status_until_a_save_succeeds() {
        use crate::api::SlamView;
        use crate::camera::{Camera, Distortion};
        use crate::slam::ScaleInfo;
        let dir = tempfile::tempdir().unwrap();
        let blocker = dir.path().join("not-a-folder");
        std::fs::write(&blocker, b"x").unwrap();
        let shared = Arc::new(SlamShared::new(true));
        let persist = MapPersist::new(blocker.join("map.spmap"), shared.clone());
        let camera = Camera::new(64, 48, [50.0, 50.0, 31.5, 23.5], Distortion::default()).unwrap();
        let map = Map::new(camera, ScaleInfo::new(1.2, 8));
        assert!(persist.save(&map, None, "checkpoint").is_err());
        let e = shared
            .status()
            .map_save_error
            .expect("the failure is reported");
        assert_eq!(e.what, "map");
        assert!(e.message.contains("not-a-folder"), "{}", e.message);
        assert!(shared.status().map_saved.is_none());
        persist.set_path(dir.path().join("map.spmap"));
        let saved = persist.save(&map, None, "checkpoint").unwrap();
        assert_eq!(shared.status().map_saved, Some(saved));
        assert_eq!(shared.status().map_save_error, None);
    }
}
