//! The SLAM side of the daemon: the [`FrameProcessor`] the SLAM thread
//! drives, and [`SlamShared`], the status and map view the API reads.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use image::GrayImage;

use super::persist::{set_aside, unused_name};
use super::slam_shared::{MapSource, ProcessOutcome, SlamShared};
use crate::api::{KeyframeInfo, LoopInfo, MapStart, MapView, MergeInfo, TrackedFrame};
use crate::camera::Camera;
use crate::config::Config;
use crate::shot::record::PoseJson;
use crate::slam::priors::{PriorParams, Priors, TelemetryFeed};
use crate::slam::{self, KeyFrameId, Map, MapMode, Slam, TrackState};
use crate::video::live::{Frame, unix_now};

/// Something that eats frames on the SLAM thread.
pub trait FrameProcessor: Send {
    /// Process one frame (the newest available).
    fn process(&mut self, frame: &Frame) -> ProcessOutcome;
    /// The input ended: finish (mapping, final optimisation) and save;
    /// returns the map file written.
    fn finish(self: Box<Self>) -> Option<PathBuf>;
}

/// The processor of a daemon without SLAM: it takes frames (so the ingest
/// counters show what a SLAM would get) and reports `unavailable`.
pub struct NoSlam;

impl FrameProcessor for NoSlam {
    fn process(&mut self, _frame: &Frame) -> ProcessOutcome {
        ProcessOutcome {
            state: "unavailable".into(),
            ..Default::default()
        }
    }
    fn finish(self: Box<Self>) -> Option<PathBuf> {
        None
    }
}

/// Frame records, mapping reports and loop-closing records the daemon's
/// SLAM keeps (at least; at most twice as many).
const DAEMON_HISTORY: usize = 1000;

/// The processor for this configuration: the SLAM, or [`NoSlam`] when
/// `[slam] enabled = false` or the SLAM cannot start.
///
/// With `[slam] continue_map` (the default) and a map file in place, the
/// SLAM goes on with the saved map ([`Slam::from_map`]): it starts lost and
/// relocalises into the old map, so shots, keyframe ids and the
/// georeference stay in one frame across restarts. A map file that cannot
/// be used (damaged, another format, another camera or extractor) never
/// stops the daemon: it is moved aside under a new name (nothing is
/// overwritten), the reason is logged and shown in the status, and the SLAM
/// starts a fresh map. With `continue_map = false` an existing map file is
/// moved aside the same way before a fresh map starts.
///
/// With `[slam] priors` and a live telemetry `feed` (the georeference
/// worker pushes the link's GNSS samples into it), the SLAM carries
/// telemetry priors ([`slam::priors`]): the map goes to local NED once
/// enough keyframes with a fix span a baseline. A continued map keeps the
/// mode its file carries; a gps-aided map continued with priors off falls
/// back to vision-only (nothing holds it in NED any more: the georeference
/// is fitted after the fact again).
pub fn make_processor(
    cfg: &Config,
    camera: Camera,
    shared: Arc<SlamShared>,
    persist: Arc<super::persist::MapPersist>,
    feed: Option<TelemetryFeed>,
) -> Box<dyn FrameProcessor> {
    let map_file = persist.path();
    if !cfg.slam.enabled {
        return Box::new(NoSlam);
    }
    let (w, h) = (camera.width, camera.height);
    // Hours of flight: the per-frame and per-keyframe records stay bounded
    // (the daemon reads only the newest frame record).
    let mut params = slam::Params {
        history: Some(DAEMON_HISTORY),
        ..Default::default()
    };
    if !cfg.slam.loop_closing {
        params.loop_closing = None;
    }
    // In lockstep the simulator waits for the frame's whole work: mapping
    // and loop closing run inline after tracking.
    params.sequential = cfg.sim.lockstep_on();
    let feed_for_aid = feed.clone();
    let priors = match (cfg.slam.priors, feed) {
        (true, Some(feed)) => Some(Priors::with_feed(feed, prior_params(cfg))),
        (true, None) => {
            tracing::warn!("[slam] priors = true but no telemetry feed: the map stays vision-only");
            None
        }
        (false, _) => None,
    };
    params.priors = priors.clone();
    params.telemetry_aid = match (cfg.slam.aid, feed_for_aid) {
        (true, Some(feed)) => Some(slam::TelemetryAid::new(feed)),
        (true, None) => {
            tracing::warn!("[slam] aid = true but no telemetry feed: tracking is vision-only");
            None
        }
        (false, _) => None,
    };
    let vocabulary = match crate::bow::Vocabulary::builtin() {
        Ok(v) => Arc::new(v),
        Err(e) => {
            tracing::error!("SLAM cannot start: {e}");
            return Box::new(NoSlam);
        }
    };
    let mut start = MapStart {
        mode: "fresh".into(),
        ..Default::default()
    };
    let mut continued = None;
    if map_file.exists() {
        if cfg.slam.continue_map {
            match continue_on(&map_file, &camera, &params, &vocabulary) {
                Ok((slam, images)) => {
                    {
                        let map = slam.map();
                        let m = map.lock().unwrap_or_else(|e| e.into_inner());
                        persist.loaded(&m, images);
                    }
                    continued = Some(slam)
                }
                Err(reason) => {
                    start.mode = "fresh_after_error".into();
                    start.set_aside = set_aside(&map_file, "unusable");
                    tracing::error!(
                        path = %map_file.display(),
                        moved_to = ?start.set_aside,
                        "the saved map cannot be continued, starting a fresh map: {reason}"
                    );
                    start.error = Some(reason.to_string());
                }
            }
        } else {
            start.set_aside = set_aside(&map_file, "replaced");
            tracing::info!(
                path = %map_file.display(),
                moved_to = ?start.set_aside,
                "continue_map = false: starting a fresh map, the saved one is kept aside"
            );
        }
    }
    // A file that could not be moved aside is not overwritten either: the
    // new map goes next to it.
    let save_to = if map_file.exists() && continued.is_none() {
        let alt = unused_name(&map_file, "new");
        tracing::warn!(
            path = %map_file.display(),
            save_to = %alt.display(),
            "the old map file stays in place; the new map will be saved beside it"
        );
        alt
    } else {
        map_file
    };
    persist.set_path(save_to);
    let slam = match continued {
        Some(slam) => {
            let map = slam.map();
            let mut m = map.lock().unwrap_or_else(|e| e.into_inner());
            start.mode = "continued".into();
            if priors.is_none() && m.mode() == MapMode::GpsAided {
                tracing::info!(
                    "the saved map is in local NED (gps-aided) but priors are off: it continues vision-only"
                );
                m.set_mode(MapMode::VisionOnly);
            }
            start.keyframes = m.keyframe_count();
            start.points = m.point_count();
            tracing::info!(
                next_keyframe_id = m.next_keyframe_id().0,
                "continuing on saved map: {} keyframes, {} points",
                start.keyframes,
                start.points
            );
            drop(m);
            slam
        }
        None => match Slam::with_vocabulary(camera, params, vocabulary) {
            Ok(slam) => slam,
            Err(e) => {
                tracing::error!("SLAM cannot start: {e}");
                return Box::new(NoSlam);
            }
        },
    };
    let awaiting_reloc = start.mode == "continued";
    shared.set_map_start(start);
    shared.set_source(Arc::new(SlamMapSource::new(slam.map())));
    Box::new(SlamProcessor {
        next_kf: slam
            .map()
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .next_keyframe_id()
            .0,
        slam,
        persist,
        size: (w, h),
        warned_size: false,
        clock: cfg.geo.history.clone(),
        shared,
        awaiting_reloc,
        loops_seen: 0,
        merges_seen: 0,
        priors,
    })
}

/// The priors' tunables in the daemon: the link's position arrives at a
/// few hertz, slower than the video, so a keyframe takes the two samples
/// around it interpolated when they are at most `[geo.history]
/// max_gap_s` apart (the same bound the georeference interpolates with).
fn prior_params(cfg: &Config) -> PriorParams {
    PriorParams {
        interpolate_gap_s: Some(cfg.geo.history.max_gap_s),
        // The link gives no barometric altitude apart from the fused one
        // already in the position (see `GeoService::on_position`).
        baro_sigma_m: None,
        // No global BA while flying: the map is refit as a whole as the
        // fixes grow by a quarter.
        realign_growth: Some(1.25),
        ..PriorParams::default()
    }
}

/// Why a saved map cannot be continued (its Display is the status's
/// `slam.start.error`).
#[derive(Debug, thiserror::Error)]
pub enum ContinueError {
    /// The file cannot be read or is not a valid map.
    #[error(transparent)]
    File(#[from] slam::mapfile::MapFileError),
    /// The map's camera is not `[camera]`.
    #[error(
        "the map was built with another camera ({map_width}x{map_height}, fx {map_fx}) than [camera] ({width}x{height}, fx {fx})"
    )]
    OtherCamera {
        /// The map camera's width, pixels.
        map_width: u32,
        /// Its height, pixels.
        map_height: u32,
        /// Its focal length, pixels.
        map_fx: f64,
        /// `[camera]`'s width, pixels.
        width: u32,
        /// Its height, pixels.
        height: u32,
        /// Its focal length, pixels.
        fx: f64,
    },
    /// Fewer than two keyframes.
    #[error("the map holds {keyframes} keyframes, too few to relocalise in")]
    TooFewKeyframes {
        /// Keyframes in the map.
        keyframes: usize,
    },
    /// The SLAM could not start on the map.
    #[error(transparent)]
    Slam(#[from] slam::SlamError),
}

/// Load the map file and start a SLAM on it; the reason when it cannot be
/// used.
fn continue_on(
    path: &Path,
    camera: &Camera,
    params: &slam::Params,
    vocabulary: &Arc<crate::bow::Vocabulary>,
) -> Result<(Slam, slam::mapfile::KeyframeImages), ContinueError> {
    let (mut map, images) = slam::mapfile::load_with_images(path)?;
    // The file does not store the rolling-shutter readout: `[camera]`'s is
    // the camera's.
    let stored = Camera {
        readout_s: camera.readout_s,
        ..map.camera
    };
    if stored != *camera {
        return Err(ContinueError::OtherCamera {
            map_width: map.camera.width,
            map_height: map.camera.height,
            map_fx: map.camera.fx,
            width: camera.width,
            height: camera.height,
            fx: camera.fx,
        });
    }
    map.camera = stored;
    if map.keyframe_count() < 2 {
        return Err(ContinueError::TooFewKeyframes {
            keyframes: map.keyframe_count(),
        });
    }
    Ok((
        Slam::from_map(map, params.clone(), vocabulary.clone())?,
        images,
    ))
}

/// The SLAM on the SLAM thread.
pub struct SlamProcessor {
    slam: Slam,
    /// Where the map is written (and the keyframes' source JPEGs kept).
    persist: Arc<super::persist::MapPersist>,
    /// The next keyframe id not yet seen.
    next_kf: u32,
    size: (u32, u32),
    warned_size: bool,
    /// How a frame's capture time is found (its keyframes carry it, and
    /// the georeference matches them to telemetry by it).
    clock: crate::geo::HistoryParams,
    /// Where the relocalisation into a continued map is reported.
    shared: Arc<SlamShared>,
    /// A saved map was continued and no frame is tracked in it yet.
    awaiting_reloc: bool,
    /// Loops closed already passed to the status.
    loops_seen: usize,
    /// Merges already passed to the status.
    merges_seen: usize,
    /// The telemetry priors (None: off), for the map mode's reason.
    priors: Option<Priors>,
}

fn state_name(s: TrackState) -> &'static str {
    match s {
        TrackState::NotInitialized => "not_initialized",
        TrackState::Tracking => "tracking",
        TrackState::Lost => "lost",
    }
}

impl FrameProcessor for SlamProcessor {
    fn process(&mut self, frame: &Frame) -> ProcessOutcome {
        if frame.image.dimensions() != self.size {
            if !self.warned_size {
                tracing::error!(
                    frame = ?frame.image.dimensions(),
                    camera = ?self.size,
                    "video frame size differs from [camera] width/height: frames skipped"
                );
                self.warned_size = true;
            }
            return ProcessOutcome {
                state: "bad_frame_size".into(),
                ..Default::default()
            };
        }
        let t = crate::geo::capture_time(frame.received_unix, frame.capture_time, &self.clock);
        if let Some(jpeg) = frame.received_jpeg() {
            // Frames decoded from H.264 have no received JPEG: their
            // keyframes are stored from the image itself (PNG, lossless).
            self.persist.note_frame(frame.seq, &jpeg);
        }
        // Rows a lost video packet damaged are masked: no feature from them.
        let mask = frame.reliable_mask();
        let out = self
            .slam
            .process_masked(frame.seq, t, frame.image.clone(), mask.as_ref());
        // The map's lock is released before the shared status is written:
        // neither lock is ever taken inside the other. (Writing the map's
        // mode inside the map's lock, while the API pinned a shot's
        // keyframe inside the status's lock, deadlocked the daemon.)
        let (keyframes, points, mode, reason) = {
            let map = self.slam.map();
            let m = map.lock().unwrap_or_else(|e| e.into_inner());
            // New keyframes: their frames' JPEGs are what the map file
            // stores as their images.
            let next = m.next_keyframe_id().0;
            for id in self.next_kf..next {
                if let Some(k) = m.keyframe(KeyFrameId(id)) {
                    self.persist.note_keyframe(k.id, k.frame_index);
                }
            }
            self.next_kf = next;
            let mode = m.mode();
            let reason = match &self.priors {
                Some(p) => {
                    let st = p.status();
                    if st.mode == mode {
                        st.reason
                    } else if mode == MapMode::GpsAided {
                        "the map is in local NED (gps-aided)".to_string()
                    } else {
                        "waiting for keyframes with a GNSS fix".to_string()
                    }
                }
                None => "telemetry priors are off ([slam] priors = false)".to_string(),
            };
            (m.keyframe_count(), m.point_count(), mode, reason)
        };
        self.shared.set_map_mode(mode, &reason);
        // Only a frame vision posed stands for where the camera is: one the
        // telemetry helped to pose holds the telemetry's own errors, which
        // the georeference and the shot's refinement measure against.
        if out.source == Some(slam::PoseSource::Vision)
            && let Some(r) = self.slam.last_record()
            && r.index == frame.seq
        {
            self.shared.set_last_tracked(TrackedFrame {
                seq: frame.seq,
                timestamp: t,
                reference_kf: u64::from(r.reference.0),
                cam_from_ref: r.cam_from_ref,
            });
        }
        // Loops the mapping thread closed since the last frame.
        for l in self.slam.loops_since(self.loops_seen) {
            self.loops_seen += 1;
            self.shared.add_loop(LoopInfo {
                current_kf: u64::from(l.current.0),
                loop_kf: u64::from(l.loop_kf.0),
                current_t: l.current_t,
                loop_t: l.loop_t,
                inliers: l.inliers,
                projection_matches: l.projection_matches,
                scale: l.scale,
                rotation_deg: l.rotation_deg,
                fused: l.fused,
                correction_ms: l.total_ms(),
                at_unix: unix_now(),
            });
        }
        // Maps merged by the mapping thread since the last frame (the
        // same path as the loops: status `slam.merges`, the /events stream).
        for m in self.slam.merges_since(self.merges_seen) {
            self.merges_seen += 1;
            self.shared.add_merge(MergeInfo {
                current_kf: u64::from(m.current.0),
                merge_kf: u64::from(m.merge_kf.0),
                current_t: m.current_t,
                merge_t: m.merge_t,
                from_map: m.from_map.0,
                into_map: m.into_map.0,
                inliers: m.inliers,
                projection_matches: m.projection_matches,
                scale: m.scale,
                keyframes_moved: m.keyframes_moved,
                fused: m.fused,
                correction_ms: m.correction_ms,
                at_unix: unix_now(),
            });
        }
        self.shared
            .set_maps_started(self.slam.map_starts().len() as u64);
        if self.awaiting_reloc && out.state == TrackState::Tracking {
            self.awaiting_reloc = false;
            tracing::info!(
                keyframes,
                points,
                "relocalised at frame {} in the saved map",
                frame.seq
            );
            self.shared.set_relocalised(frame.seq);
        }
        ProcessOutcome {
            state: state_name(out.state).into(),
            tracked: out.cam_from_world.is_some(),
            source: out.source,
            inliers: out.inliers,
            keyframes,
            points,
            keypoints: out.keypoints,
        }
    }

    fn finish(self: Box<Self>) -> Option<PathBuf> {
        let run = self.slam.finish();
        if run.map.keyframe_count() == 0 {
            return None;
        }
        // The georeference is written by the daemon after this (its worker
        // is still running).
        match self.persist.save(&run.map, None, "shutdown") {
            Ok(_) => Some(self.persist.path()),
            Err(e) => {
                tracing::error!("saving the map: {e}");
                None
            }
        }
    }
}

/// The SLAM's map as the API sees it (the daemon's [`MapSource`]: a
/// shared map, read under its lock).
pub struct SlamMapSource {
    map: Arc<Mutex<Map>>,
}

impl SlamMapSource {
    /// The source over a shared map.
    pub fn new(map: Arc<Mutex<Map>>) -> Self {
        Self { map }
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Map> {
        self.map.lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl MapSource for SlamMapSource {
    fn pin_keyframe(&self, id: u64) -> bool {
        u32::try_from(id).is_ok_and(|id| self.lock().pin_keyframe(KeyFrameId(id)))
    }
    /// The first map's keyframes (a map started after a tracking loss is
    /// in its own frame until it is merged: it is not shown).
    fn keyframes(&self) -> Vec<KeyframeInfo> {
        let m = self.lock();
        let first = m.first_map();
        let mut v: Vec<KeyframeInfo> = m
            .keyframes()
            .filter(|k| m.map_of(k.id) == first)
            .map(|k| {
                let (width, height) = k.image.as_ref().map_or((0, 0), |i| i.dimensions());
                KeyframeInfo {
                    id: k.id.0 as u64,
                    timestamp: k.timestamp,
                    world_from_cam: PoseJson::from_isometry(&k.cam_from_world.inverse()),
                    width,
                    height,
                }
            })
            .collect();
        v.sort_by_key(|k| k.id);
        v
    }

    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>> {
        let id = u32::try_from(id).ok()?;
        self.lock().keyframe(KeyFrameId(id))?.image.clone()
    }

    fn snapshot(&self) -> Option<Map> {
        let m = self.lock();
        Some(match m.first_map() {
            Some(first) if m.maps().len() > 1 => m.only(first),
            _ => m.clone(),
        })
    }

    fn map(&self, max_points: usize) -> MapView {
        let m = self.lock();
        let first = m.first_map();
        let total = m.point_count();
        let step = total.div_ceil(max_points.max(1)).max(1);
        let points = m
            .points()
            .filter(|p| m.map_of_point(p.id) == first)
            .step_by(step)
            .take(max_points)
            .map(|p| {
                [
                    p.position.x as f32,
                    p.position.y as f32,
                    p.position.z as f32,
                ]
            })
            .collect();
        let mut kfs: Vec<_> = m
            .keyframes()
            .filter(|k| m.map_of(k.id) == first)
            .map(|k| (k.id.0, slam::center_of(&k.cam_from_world)))
            .collect();
        kfs.sort_by_key(|k| k.0);
        MapView {
            points,
            total_points: total,
            trajectory: kfs.into_iter().map(|(_, c)| [c.x, c.y, c.z]).collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::SlamView;

    fn setup() -> (tempfile::TempDir, Config, Camera, PathBuf) {
        let dir = tempfile::tempdir().unwrap();
        let cfg = Config::default();
        let camera = cfg.camera.camera(dir.path()).unwrap();
        let file = dir.path().join("map.spmap");
        (dir, cfg, camera, file)
    }

    /// Start a processor on `file`; the status it reports, the files in
    /// the folder afterwards.
    fn start(cfg: &Config, camera: Camera, file: &Path) -> (MapStart, Vec<PathBuf>) {
        let shared = Arc::new(SlamShared::new(true));
        let persist = Arc::new(super::super::persist::MapPersist::new(
            file.to_owned(),
            shared.clone(),
        ));
        let p = make_processor(cfg, camera, shared.clone(), persist, None);
        assert!(p.finish().is_none(), "nothing to save without keyframes");
        let mut files: Vec<PathBuf> = std::fs::read_dir(file.parent().unwrap())
            .unwrap()
            .map(|e| e.unwrap().path())
            .collect();
        files.sort();
        (shared.status().map_start.unwrap(), files)
    }

    #[test]
    fn no_map_file_starts_fresh() {
        let (_dir, cfg, camera, file) = setup();
        let (s, files) = start(&cfg, camera, &file);
        assert_eq!(s.mode, "fresh");
        assert!(s.error.is_none() && s.set_aside.is_none());
        assert!(files.is_empty());
    }

    #[test]
    fn a_damaged_map_file_is_set_aside_and_a_fresh_map_starts() {
        let (_dir, cfg, camera, file) = setup();
        std::fs::write(&file, b"not a map at all").unwrap();
        let (s, files) = start(&cfg, camera, &file);
        assert_eq!(s.mode, "fresh_after_error");
        assert!(s.error.as_deref().unwrap().contains("bad magic"), "{s:?}");
        let aside = s.set_aside.unwrap();
        assert_eq!(files, vec![aside.clone()]);
        assert!(aside.to_string_lossy().contains("map.spmap.unusable-"));
        assert_eq!(std::fs::read(&aside).unwrap(), b"not a map at all");
    }

    #[test]
    fn a_map_of_another_camera_is_not_continued() {
        let (_dir, cfg, camera, file) = setup();
        let mut other = camera;
        other.fx *= 1.5;
        let map = Map::new(other, slam::ScaleInfo::new(1.2, 8));
        slam::mapfile::save(&map, &file).unwrap();
        let bytes = std::fs::read(&file).unwrap();
        let (s, files) = start(&cfg, camera, &file);
        assert_eq!(s.mode, "fresh_after_error");
        assert!(
            s.error.as_deref().unwrap().contains("another camera"),
            "{s:?}"
        );
        assert_eq!(files.len(), 1);
        assert_eq!(std::fs::read(&files[0]).unwrap(), bytes);
    }

    #[test]
    fn continue_map_false_keeps_the_old_map_aside() {
        let (_dir, mut cfg, camera, file) = setup();
        cfg.slam.continue_map = false;
        std::fs::write(&file, b"old map").unwrap();
        // A name already taken is not overwritten.
        let taken = unused_name(&file, "replaced");
        std::fs::write(&taken, b"older").unwrap();
        let (s, files) = start(&cfg, camera, &file);
        assert_eq!(s.mode, "fresh");
        let aside = s.set_aside.unwrap();
        assert_ne!(aside, taken);
        assert_eq!(files.len(), 2);
        assert_eq!(std::fs::read(&aside).unwrap(), b"old map");
        assert_eq!(std::fs::read(&taken).unwrap(), b"older");
    }
}
