//! Monocular visual SLAM: initialise, track, map and close loops on three
//! threads.
//!
//! [`Slam`] owns the map (behind a mutex), the tracker (on the caller's
//! thread) and the local mapper (on its own thread, fed keyframes over a
//! bounded channel; or inline after each keyframe in sequential mode, so
//! runs repeat exactly). Tracking never waits for mapping: it only inserts a
//! keyframe when mapping is idle, and mapping solves its bundle adjustment
//! outside the map lock. Loop closing ([`loop_closing`]) runs on a third
//! thread at a lower priority, fed each mapped keyframe (inline after
//! mapping in sequential mode); a local BA that a correction overtook
//! drops its result, and mapping is held while the essential graph is
//! solved and written back ([`pause`]). The correction holds the map lock,
//! as ORB-SLAM's holds the map-update mutex, except while the essential
//! graph is solved (on a copy of the poses), and tracking re-places its
//! last frame on the corrected reference keyframe. [`Params::history`] bounds
//! what is recorded per frame and per keyframe for a long flight. After a tracking loss a new
//! map is started beside the old one (the [`Map`] is an atlas) and the
//! loop closer merges them when it finds a common place; with telemetry
//! priors no new map is started (tracking relocalises) unless tracking is
//! aided by the telemetry, which puts the new map into the old one as soon
//! as it initialises ([`aided`]).
//!
//! # Layout
//!
//! | module | what it holds |
//! |---|---|
//! | [`tracking`] | the [`Tracker`]: per frame, extraction, motion model, reference keyframe, states |
//! | [`aided`] | telemetry-aided tracking: a frame vision cannot pose predicted from the last one it did by the reported attitude and GNSS |
//! | [`initializer`] | two-view initialisation and the initial map |
//! | [`planar`] | deciding between the twin reconstructions of a planar scene |
//! | `relocalizer` | BoW candidates, PnP RANSAC, search by projection for a lost frame |
//! | `local_map` | local keyframes, search of their points by projection, pose on all matches |
//! | `keyframe_decision` | whether a tracked frame becomes a keyframe |
//! | `frame` | the frame being tracked (with its rolling-shutter motion from the motion model), the tracker's context, motion-only BA of a frame |
//! | [`params`] | [`TrackingParams`], the tunables of all of the above |
//! | [`mapping`] | the [`LocalMapper`]: triangulation, fusion, local BA, keyframe culling |
//! | [`priors`] | telemetry priors (a log read whole or a live feed): the map put in local NED, GNSS and altitude priors in BA |
//! | [`loop_closing`] | the [`LoopCloser`]: loop detection, Sim(3) check, correction, essential graph |
//! | [`pause`] | holding local mapping while the loop closer writes a correction back; the closer's priority |
//! | [`bundle`] | the map ↔ [`crate::optimize`] glue of every bundle adjustment |
//! | [`shutter`] | a rolling shutter's readout estimated from a map (each keyframe's motion over its readout is [`bundle`]'s) |
//! | [`matcher`] | descriptor matching for each of the stages |
//! | [`map`] | keyframes and points in arenas, covisibility, spanning tree, place index |
//! | [`mapfile`] | the versioned binary map file |

pub mod aided;
pub mod bundle;
pub mod cpu_time;
mod frame;
pub mod initializer;
mod keyframe_decision;
mod local_map;
pub mod loop_closing;
pub mod map;
pub mod mapfile;
pub mod mapping;
pub mod matcher;
pub mod params;
pub mod pause;
pub mod planar;
pub mod priors;
mod relocalizer;
pub mod shutter;
pub mod tracking;

use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::mpsc::{Receiver, SyncSender, TrySendError, sync_channel};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

use image::GrayImage;
use nalgebra::Isometry3;

use crate::camera::Camera;
use crate::optimize::BaParams;
use crate::trajectory::{StampedPose, Trajectory};

pub use aided::{AidParams, PoseSource, TelemetryAid};
pub use initializer::InitFailure;
pub use loop_closing::{
    HoldKind, LockHold, LoopCloser, LoopEvent, LoopLog, LoopParams, LoopRefusal, LoopReject,
    LoopSummary, MergeEvent, MergeLog, MergeSummary,
};
pub use map::{
    Footprint, KeyFrame, KeyFrameId, Map, MapId, MapMode, MapPoint, MergeRecord, PointId, ScaleInfo,
};
pub use mapping::{LocalMapper, MappingParams, MappingReport};
pub use tracking::{
    FrameOutcome, FrameRecord, KeypointState, MapStart, TrackFailure, TrackState, TrackedKeypoint,
    Tracker, TrackingParams,
};

/// Errors of the SLAM.
#[derive(Debug, thiserror::Error)]
pub enum SlamError {
    /// The feature extractor refused its parameters.
    #[error(transparent)]
    Features(#[from] crate::features::FeatureError),
    /// The mapping or loop closing thread could not be started.
    #[error("cannot start a SLAM thread: {0}")]
    Thread(std::io::Error),
    /// A map file could not be read or written.
    #[error(transparent)]
    MapFile(#[from] mapfile::MapFileError),
    /// The built-in vocabulary could not be loaded.
    #[error(transparent)]
    Vocabulary(#[from] crate::bow::BowError),
    /// A saved map does not fit the extractor's scale levels.
    #[error(
        "the map was built with {map_levels} levels at scale {map_scale}, the extractor has {levels} at {scale}"
    )]
    ScaleMismatch {
        /// Levels in the map.
        map_levels: usize,
        /// Scale factor in the map.
        map_scale: f64,
        /// Levels of the extractor.
        levels: usize,
        /// Scale factor of the extractor.
        scale: f64,
    },
}

/// Every tunable of the SLAM.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// Tracking.
    pub tracking: TrackingParams,
    /// Local mapping.
    pub mapping: MappingParams,
    /// Run mapping inline after each keyframe (repeatable runs).
    pub sequential: bool,
    /// Keyframes waiting for mapping at most.
    pub keyframe_queue: usize,
    /// Bundle adjustment over all keyframes when the run finishes.
    pub final_ba: Option<BaParams>,
    /// Loop closing (`None`: off).
    pub loop_closing: Option<LoopParams>,
    /// Telemetry priors (`None`: vision only, the default).
    pub priors: Option<priors::Priors>,
    /// Telemetry-aided tracking (`None`: vision only, the default).
    pub telemetry_aid: Option<aided::TelemetryAid>,
    /// Records kept per frame or per keyframe (the tracker's frame
    /// records, the mapper's reports, the loop closer's lock holds and
    /// refusals): at least the newest this many, at most twice as many
    /// (`None`, the default: all, for a run's trajectory and report; the
    /// daemon flies for hours and keeps a bounded history).
    pub history: Option<usize>,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            tracking: TrackingParams::default(),
            mapping: MappingParams::default(),
            sequential: false,
            keyframe_queue: 4,
            final_ba: Some(BaParams {
                first_pass_iterations: 15,
                second_pass_iterations: 15,
                ..BaParams::default()
            }),
            loop_closing: Some(LoopParams::default()),
            priors: None,
            telemetry_aid: None,
            history: None,
        }
    }
}

/// The local mapper and where the keyframes it mapped go next.
struct Mappers {
    mapper: LocalMapper,
    closer: Closing,
}

/// The loop closer, after local mapping.
enum Closing {
    /// Loop closing off.
    Off,
    /// Run after each mapped keyframe on the same thread (sequential mode).
    Inline(Box<LoopCloser>),
    /// On its own thread: each mapped keyframe is sent to it
    /// ([`Mappers::hand_over`]).
    Thread(SyncSender<KeyFrameId>),
}

/// Keyframes mapped but not yet looked at by the loop closer, at most: a
/// closer that far behind holds mapping (and so new keyframes) back.
const LOOP_QUEUE: usize = 64;

impl Mappers {
    /// Maps `kf`, and looks for a loop at it when the closer runs inline.
    fn process(&mut self, map: &Mutex<Map>, kf: KeyFrameId, more_waiting: bool) {
        self.mapper.process_keyframe(map, kf, more_waiting);
        if let Closing::Inline(c) = &mut self.closer {
            c.process_keyframe(map, kf);
        }
    }

    /// Sends the mapped `kf` to the closer's thread. Called between two
    /// keyframes (never while the mapper counts as mapping): a full queue
    /// then waits for a closer that may itself be waiting to hold mapping.
    fn hand_over(&self, kf: KeyFrameId) {
        if let Closing::Thread(tx) = &self.closer {
            // The closer is joined after the mapper: a send can only fail
            // if its thread panicked.
            if tx.send(kf).is_err() {
                tracing::warn!(
                    kf = kf.0,
                    "loop closing thread gone; keyframe not checked for loops"
                );
            }
        }
    }
}

enum Mapping {
    Inline(Box<Mappers>),
    Thread {
        tx: Option<SyncSender<KeyFrameId>>,
        handle: Option<JoinHandle<Mappers>>,
        /// The loop closer's thread (loop closing on).
        closer: Option<JoinHandle<LoopCloser>>,
        busy: Arc<AtomicBool>,
        queued: Arc<AtomicUsize>,
    },
}

/// The SLAM system.
pub struct Slam {
    map: Arc<Mutex<Map>>,
    tracker: Tracker,
    mapping: Mapping,
    params: Params,
    frames: u64,
    /// The loop closer's summaries (None: loop closing off).
    loop_log: Option<LoopLog>,
    /// The loop closer's merge summaries (None: loop closing off).
    merge_log: Option<MergeLog>,
}

/// The result of a finished run.
pub struct SlamRun {
    /// The map after the final optimisation.
    pub map: Map,
    /// Pose records of every tracked frame (the newest only when
    /// [`Params::history`] bounds them).
    pub records: Vec<FrameRecord>,
    /// Mapping reports, one per keyframe processed.
    pub mapping: Vec<MappingReport>,
    /// Frame index of initialisation.
    pub initialized_at: Option<u64>,
    /// Frames given.
    pub frames: u64,
    /// The last reason for not tracking / not initialising.
    pub last_reason: Option<TrackFailure>,
    /// Loops closed, in order.
    pub loops: Vec<LoopEvent>,
    /// Consistent loop candidates refused, in order.
    pub loop_refusals: Vec<LoopRefusal>,
    /// New maps started after tracking losses, in order.
    pub map_starts: Vec<MapStart>,
    /// Maps merged, in order.
    pub merges: Vec<MergeEvent>,
    /// Consistent merge candidates refused, in order.
    pub merge_refusals: Vec<LoopRefusal>,
    /// Each span the loop closer held the map lock, in order.
    pub loop_holds: Vec<LockHold>,
    /// When telemetry put the map in local NED: the keyframe it happened
    /// at and the fit (the map's mode is [`Map::mode`]).
    pub georeferenced: Option<(KeyFrameId, priors::Georeferenced)>,
}

impl SlamRun {
    /// Every tracked frame's pose (world_from_cam), placed relative to its
    /// reference keyframe as the map stands now, in the first map (the
    /// one the first posed frame is in; maps merged into it included).
    /// Frames in a map never merged into it are left out
    /// ([`SlamRun::trajectory_in`] gives them).
    pub fn trajectory(&self) -> Trajectory {
        match self.first_map() {
            Some(id) => self.trajectory_in(id),
            None => Trajectory { poses: Vec::new() },
        }
    }

    /// The map of the first record whose keyframe is still there (a map
    /// the telemetry's aid dropped for a newer one is not).
    pub fn first_map(&self) -> Option<MapId> {
        self.records
            .iter()
            .filter(|r| self.map.keyframe_pose(r.reference).is_some())
            .find_map(|r| self.map.map_of(r.reference))
    }

    /// The tracked frames whose reference keyframe is in map `id`.
    pub fn trajectory_in(&self, id: MapId) -> Trajectory {
        let mut poses = Vec::with_capacity(self.records.len());
        for r in self
            .records
            .iter()
            .filter(|r| self.map.map_of(r.reference) == Some(id))
        {
            if let Some(ref_pose) = self.map.keyframe_pose(r.reference) {
                let cam_from_world = r.cam_from_ref * ref_pose;
                poses.push(StampedPose {
                    t: r.timestamp,
                    world_from_cam: cam_from_world.inverse(),
                });
            }
        }
        Trajectory { poses }
    }

    /// The live keyframes' poses (world_from_cam) of the first map (as
    /// [`SlamRun::trajectory`]), by time.
    pub fn keyframe_trajectory(&self) -> Trajectory {
        let first = self.first_map();
        let mut poses: Vec<StampedPose> = self
            .map
            .keyframes()
            .filter(|k| first.is_none_or(|f| self.map.map_of(k.id) == Some(f)))
            .map(|k| StampedPose {
                t: k.timestamp,
                world_from_cam: k.world_from_cam(),
            })
            .collect();
        poses.sort_by(|a, b| a.t.total_cmp(&b.t));
        Trajectory { poses }
    }
}

impl Slam {
    /// A SLAM for `camera` with the built-in vocabulary; starts the mapping
    /// thread unless sequential.
    pub fn new(camera: Camera, params: Params) -> Result<Self, SlamError> {
        let vocabulary = Arc::new(crate::bow::Vocabulary::builtin()?);
        Self::with_vocabulary(camera, params, vocabulary)
    }

    /// A SLAM for `camera` whose keyframe database uses `vocabulary`.
    pub fn with_vocabulary(
        camera: Camera,
        params: Params,
        vocabulary: Arc<crate::bow::Vocabulary>,
    ) -> Result<Self, SlamError> {
        let tracker = Tracker::new(camera, tracking_params(&params), vocabulary)?;
        let map = Map::new(camera, tracker.scale().clone());
        Self::start(tracker, map, params)
    }

    /// A SLAM that goes on with a saved map ([`mapfile::load`]) seen by the
    /// same camera: the map's keyframes are indexed in the keyframe
    /// database with `vocabulary` (the file stores descriptors, not BoW
    /// vectors) and tracking starts lost, so the first frames relocalise
    /// against the map; new keyframes extend it.
    pub fn from_map(
        mut map: Map,
        params: Params,
        vocabulary: Arc<crate::bow::Vocabulary>,
    ) -> Result<Self, SlamError> {
        let mut tracker = Tracker::new(map.camera, tracking_params(&params), vocabulary.clone())?;
        let scale = tracker.scale();
        if scale.n_levels() != map.scale.n_levels()
            || (scale.scale_factor - map.scale.scale_factor).abs() > 1e-6
        {
            return Err(SlamError::ScaleMismatch {
                map_levels: map.scale.n_levels(),
                map_scale: map.scale.scale_factor,
                levels: scale.n_levels(),
                scale: scale.scale_factor,
            });
        }
        let indexed = map.index_keyframes(&vocabulary, params.tracking.bow.direct_index_level);
        tracing::info!(
            keyframes = map.keyframe_count(),
            points = map.point_count(),
            indexed,
            "continuing on a saved map"
        );
        tracker.start_lost();
        Self::start(tracker, map, params)
    }

    fn start(mut tracker: Tracker, map: Map, params: Params) -> Result<Self, SlamError> {
        tracker.set_history(params.history);
        tracker.set_telemetry_aid(params.telemetry_aid.clone());
        tracker.set_new_maps_need_placement(params.priors.is_some());
        let camera = map.camera;
        let map = Arc::new(Mutex::new(map));
        let bounds = crate::matching::Bounds::of(&camera);
        let mut mapper = LocalMapper::new(
            params.mapping.clone(),
            bounds,
            tracker.vocabulary().clone(),
            params.tracking.bow.direct_index_level,
        );
        mapper.set_priors(params.priors.clone());
        mapper.set_history(params.history);
        let closer = params.loop_closing.clone().map(|p| {
            let mut c = LoopCloser::new(p, bounds);
            c.set_history(params.history);
            c
        });
        let loop_log = closer.as_ref().map(LoopCloser::log);
        let merge_log = closer.as_ref().map(LoopCloser::merge_log);
        let mapping = if params.sequential {
            let closer = closer.map_or(Closing::Off, |c| Closing::Inline(Box::new(c)));
            Mapping::Inline(Box::new(Mappers { mapper, closer }))
        } else {
            let pause = Arc::new(pause::MappingPause::default());
            let (closing, closer) = match closer {
                Some(mut c) => {
                    c.set_pause(pause.clone());
                    let (tx, rx) = sync_channel::<KeyFrameId>(LOOP_QUEUE);
                    let handle = c.spawn(rx, map.clone()).map_err(SlamError::Thread)?;
                    (Closing::Thread(tx), Some(handle))
                }
                None => (Closing::Off, None),
            };
            let mappers = Mappers {
                mapper,
                closer: closing,
            };
            let (tx, rx) = sync_channel::<KeyFrameId>(params.keyframe_queue.max(1));
            let busy = Arc::new(AtomicBool::new(false));
            let queued = Arc::new(AtomicUsize::new(0));
            let handle = spawn_mapper(
                mappers,
                rx,
                map.clone(),
                busy.clone(),
                queued.clone(),
                pause,
            )?;
            Mapping::Thread {
                tx: Some(tx),
                handle: Some(handle),
                closer,
                busy,
                queued,
            }
        };
        Ok(Slam {
            map,
            tracker,
            mapping,
            params,
            frames: 0,
            loop_log,
            merge_log,
        })
    }

    /// The loops closed so far after the first `n` (all with `n` = 0), in
    /// order; they come from the loop closing thread as it closes them.
    pub fn loops_since(&self, n: usize) -> Vec<LoopSummary> {
        self.loop_log.as_ref().map_or_else(Vec::new, |log| {
            let g = log.lock().unwrap_or_else(|e| e.into_inner());
            g.get(n..).map_or_else(Vec::new, <[LoopSummary]>::to_vec)
        })
    }

    /// The merges made so far after the first `n` (all with `n` = 0), in
    /// order; they come from the loop closing thread as it makes them.
    pub fn merges_since(&self, n: usize) -> Vec<MergeSummary> {
        self.merge_log.as_ref().map_or_else(Vec::new, |log| {
            let g = log.lock().unwrap_or_else(|e| e.into_inner());
            g.get(n..).map_or_else(Vec::new, <[MergeSummary]>::to_vec)
        })
    }

    /// The new maps started after tracking losses so far.
    pub fn map_starts(&self) -> &[MapStart] {
        self.tracker.map_starts()
    }

    /// The shared map (read it under the lock; the API takes snapshots).
    pub fn map(&self) -> Arc<Mutex<Map>> {
        self.map.clone()
    }

    /// State of tracking.
    pub fn state(&self) -> TrackState {
        self.tracker.state()
    }

    /// Frame records the tracker holds.
    pub fn records_len(&self) -> usize {
        self.tracker.records().len()
    }

    /// The newest frame's pose record (the frame last tracked).
    pub fn last_record(&self) -> Option<&FrameRecord> {
        self.tracker.records().last()
    }

    /// Track one frame (and map its keyframe inline in sequential mode).
    pub fn process(&mut self, index: u64, timestamp: f64, image: Arc<GrayImage>) -> FrameOutcome {
        self.process_masked(index, timestamp, image, None)
    }

    /// [`Slam::process`] on the pixels where `mask` is not 0 (see
    /// [`Tracker::track_masked`](tracking::Tracker::track_masked)).
    pub fn process_masked(
        &mut self,
        index: u64,
        timestamp: f64,
        image: Arc<GrayImage>,
        mask: Option<&GrayImage>,
    ) -> FrameOutcome {
        self.frames += 1;
        let idle = match &self.mapping {
            Mapping::Inline(_) => true,
            Mapping::Thread { busy, queued, .. } => {
                !busy.load(Ordering::Acquire) && queued.load(Ordering::Acquire) == 0
            }
        };
        let outcome = self
            .tracker
            .track_masked(&self.map, index, timestamp, image, mask, idle);
        if let Some(kf) = outcome.new_keyframe {
            match &mut self.mapping {
                Mapping::Inline(mappers) => {
                    mappers.process(&self.map, kf, false);
                }
                Mapping::Thread { tx, queued, .. } => {
                    if let Some(tx) = tx {
                        queued.fetch_add(1, Ordering::AcqRel);
                        match tx.try_send(kf) {
                            Ok(()) => {}
                            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                                queued.fetch_sub(1, Ordering::AcqRel);
                                tracing::warn!(
                                    kf = kf.0,
                                    "mapping queue full; keyframe kept without local mapping"
                                );
                            }
                        }
                    }
                }
            }
        }
        outcome
    }

    /// Stop mapping (it finishes its queue), run the final optimisation and
    /// return the map and the frame records.
    pub fn finish(mut self) -> SlamRun {
        let mappers = match &mut self.mapping {
            Mapping::Inline(m) => {
                let closer = match std::mem::replace(&mut m.closer, Closing::Off) {
                    Closing::Inline(c) => Some(*c),
                    _ => None,
                };
                Some((
                    std::mem::take(&mut m.mapper.reports),
                    closer,
                    m.mapper.georeferenced,
                ))
            }
            Mapping::Thread {
                tx, handle, closer, ..
            } => {
                // Mapping finishes its queue and drops its sender to the
                // closer, which then finishes its own queue.
                drop(tx.take());
                let mapped = match handle.take().map(|h| h.join()) {
                    Some(Ok(m)) => Some((m.mapper.reports, m.mapper.georeferenced)),
                    _ => None,
                };
                let closer = match closer.take().map(|h| h.join()) {
                    Some(Ok(c)) => Some(c),
                    Some(Err(_)) => {
                        tracing::error!("the loop closing thread panicked; its loops are lost");
                        None
                    }
                    None => None,
                };
                mapped.map(|(reports, georeferenced)| (reports, closer, georeferenced))
            }
        };
        let (reports, closer, georeferenced) = mappers.unwrap_or_default();
        let (loops, loop_refusals, merges, merge_refusals, loop_holds) = match closer {
            Some(c) => (c.events, c.refusals, c.merges, c.merge_refusals, c.holds),
            None => Default::default(),
        };
        let mut map = {
            let guard = self.map.lock().unwrap_or_else(|e| e.into_inner());
            guard.clone()
        };
        // Merges made after the last frame: the records follow them.
        self.tracker.follow_merges(&map);
        if let Some(ba) = &self.params.final_ba {
            let kfs: Vec<KeyFrameId> = map.keyframes().map(|k| k.id).collect();
            if kfs.len() >= 2 {
                let aided = (map.mode() == MapMode::GpsAided)
                    .then_some(self.params.priors.as_ref())
                    .flatten();
                // With priors the priors fix the gauge: no keyframe is held.
                // Else each map's first keyframe (maps never merged are
                // separate problems in one).
                let fixed = if aided.is_some() {
                    Vec::new()
                } else {
                    bundle::whole_map_gauge(&map, &kfs)
                };
                let solved =
                    bundle::run_bundle_adjustment_with(&mut map, &kfs, &fixed, ba, |m, s| {
                        aided.map_or_else(Vec::new, |p| p.priors_for(m, s))
                    });
                if let Some(r) = solved {
                    tracing::info!(
                        keyframes = kfs.len(),
                        rmse_before = r.initial_rmse_px,
                        rmse_after = r.final_rmse_px,
                        outliers = r.n_outliers,
                        first_pass = ?r.first_pass,
                        "final bundle adjustment"
                    );
                }
            }
        }
        SlamRun {
            map,
            records: self.tracker.records().to_vec(),
            mapping: reports,
            initialized_at: self.tracker.initialized_at(),
            frames: self.frames,
            last_reason: self.tracker.last_reason().cloned(),
            loops,
            loop_refusals,
            map_starts: self.tracker.map_starts().to_vec(),
            merges,
            merge_refusals,
            loop_holds,
            georeferenced,
        }
    }
}

/// The tracking parameters as the SLAM uses them: with telemetry priors
/// and without the telemetry's aid no new map is started after a loss (a
/// new map has to start in local NED, which only the aid's placement does,
/// [`aided::place_new_map`]): tracking relocalises.
fn tracking_params(params: &Params) -> TrackingParams {
    let mut t = params.tracking.clone();
    if params.priors.is_some() && params.telemetry_aid.is_none() {
        t.new_map_after_lost_frames = None;
    }
    t
}

/// The mapping thread: tells tracking whether it is mapping (`busy`) and
/// how many keyframes wait (`queued`); the loop closer holds it through
/// `pause`.
fn spawn_mapper(
    mut mappers: Mappers,
    rx: Receiver<KeyFrameId>,
    map: Arc<Mutex<Map>>,
    busy: Arc<AtomicBool>,
    queued: Arc<AtomicUsize>,
    pause: Arc<pause::MappingPause>,
) -> Result<JoinHandle<Mappers>, SlamError> {
    std::thread::Builder::new()
        .name("slam-mapping".into())
        .spawn(move || {
            while let Ok(kf) = rx.recv() {
                // Held while the loop closer writes a correction back.
                pause.begin();
                busy.store(true, Ordering::Release);
                queued.fetch_sub(1, Ordering::AcqRel);
                let more = queued.load(Ordering::Acquire) > 0;
                mappers.process(&map, kf, more);
                busy.store(false, Ordering::Release);
                pause.end();
                mappers.hand_over(kf);
            }
            mappers
        })
        .map_err(SlamError::Thread)
}

/// A pose's camera centre, for logs.
pub fn center_of(cam_from_world: &Isometry3<f64>) -> nalgebra::Vector3<f64> {
    cam_from_world.inverse().translation.vector
}
