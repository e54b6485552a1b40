//! The georeference kept live over a run: telemetry samples and the
//! SLAM's keyframes feed one [`Geo`]; the map → NED alignment is refitted
//! as keyframes arrive, move (bundle adjustment) or go (culling).
//!
//! Across restarts: the telemetry side of every pair is saved beside the
//! map ([`LiveGeoreference::saved`]) and restored onto the continued map's
//! keyframes ([`LiveGeoreference::restore`]), so the map is georeferenced
//! as soon as it is loaded. Tracked frames pair with live telemetry too
//! (one per [`ContinuityParams::frame_pair_spacing_s`], hung on their
//! reference keyframe), so live evidence comes in while the drone flies
//! over mapped ground and adds no keyframe; once enough of it is in, the
//! saved pairs are checked against it and dropped, with the reason in the
//! status, when they disagree beyond their own residuals (the fit is then
//! made from live pairs alone). A saved file whose home differs from the
//! vehicle's HOME_POSITION is carried to the new home exactly. The parts
//! of that are in [`super::continuity`].
//!
//! While the SLAM's map is gps-aided (in local NED, held there by the
//! telemetry priors) the georeference follows from the map: the identity
//! to local NED at home, its residuals against the pairs reported, no
//! separate fit (the status's `source`: `map`, else `fit`).
//!
//! Clocks: telemetry is timed per [`super::TelemetryClock`] by a [`BootClock`]
//! (the autopilot's `time_boot_ms` mapped to the local clock), or by
//! receive time. Synchronous: the daemon's worker (`daemon::geo_service`)
//! holds it under a lock and feeds it from the link and the SLAM.

use std::collections::{HashMap, HashSet, VecDeque};
use std::time::Instant;

use nalgebra::{Isometry3, UnitQuaternion, Vector3};

use super::align::GeoAlignment;
use super::clock::BootClock;
use super::continuity::{Anchor, Check, KeyframePoses, Restore, check_saved, place};
use super::pipeline::{Geo, KeyframeStatus};
use super::saved::{PairKind, SAVED_FORMAT, SavedFit, SavedGeoreference};
use super::status::{
    ClockStatus, Counts, Evidence, FitState, FitView, GeoreferenceStatus, HistoryCounts, HomeView,
    SimView,
};
use super::target::{GeoTarget, convert_target};
use super::telemetry::{GimbalAngles, wrap_pi};
use super::wgs84::{Geodetic, LocalFrame};
use super::{ContinuityParams, GeoError, Params};

/// Frames in the video-delay median.
const DELAY_WINDOW: usize = 100;
/// Frame pairs' ids: this bit set, the capture time in milliseconds below
/// (keyframe ids are small; a frame's capture time names it across runs).
pub const FRAME_PAIR_BIT: u64 = 1 << 63;

/// The pair id of a frame captured at `t` seconds: [`FRAME_PAIR_BIT`] with
/// the capture time in milliseconds below it.
pub fn frame_pair_id(t: f64) -> u64 {
    FRAME_PAIR_BIT | ((t * 1e3).round().max(0.0) as u64 & !FRAME_PAIR_BIT)
}

/// A keyframe of the SLAM's map as the georeference reads it.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MapKeyframe {
    /// Its id.
    pub id: u64,
    /// Capture time, seconds (the telemetry's clock).
    pub timestamp: f64,
    /// `map ← cam` (None: the map's pose is not sound; the keyframe is
    /// still there, but not paired or moved).
    pub world_from_cam: Option<Isometry3<f64>>,
}

/// The newest tracked frame, placed relative to its reference keyframe.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrackedPose {
    /// Ingest sequence number.
    pub seq: u64,
    /// Capture time, seconds (the keyframes' clock).
    pub timestamp: f64,
    /// The reference keyframe.
    pub reference_kf: u64,
    /// `cam ← ref_cam`.
    pub cam_from_ref: Isometry3<f64>,
}

/// The georeference of one run, fed sample by sample (see the module
/// documentation).
#[derive(Debug)]
pub struct LiveGeoreference {
    params: Params,
    geo: Geo,
    clock: BootClock,
    home: Option<Geodetic>,
    /// Poses last fed per keyframe id (translation, quaternion xyzw).
    fed: HashMap<u64, [f64; 7]>,
    fit: Option<Result<GeoAlignment, GeoError>>,
    fitted_at: Option<Instant>,
    last_heading_rad: Option<f64>,
    counts: Counts,
    video_delay_ms: VecDeque<f64>,
    /// Sum and count of every frame's delay (the whole run's mean).
    video_delay_sum_ms: (f64, u64),
    /// Every pair (held or waiting for telemetry) by id: what its map side
    /// hangs from.
    anchors: HashMap<u64, Anchor>,
    /// Live frame pairs, oldest first.
    frame_pairs: VecDeque<u64>,
    /// Capture time of the newest frame pair.
    last_frame_pair_t: f64,
    /// Pairs restored from the saved georeference (held).
    restored: HashSet<u64>,
    /// The saved georeference being restored.
    restore: Option<Restore>,
    /// The saved pairs checked against the live ones.
    check: Option<Check>,
    /// Refit at the next sync even if no pair changed.
    force_fit: bool,
    /// The latest attitude (NED ← body).
    last_attitude: Option<UnitQuaternion<f64>>,
    /// The latest gimbal angles and their time (the frames' clock).
    last_gimbal: Option<(f64, GimbalAngles)>,
    /// The SLAM's map is in local NED (gps-aided): the georeference
    /// follows from it.
    map_aided: bool,
}

fn pose_key(p: &Isometry3<f64>) -> [f64; 7] {
    let t = p.translation.vector;
    let q = p.rotation.coords;
    [t.x, t.y, t.z, q.x, q.y, q.z, q.w]
}

impl LiveGeoreference {
    /// An empty georeference.
    pub fn new(params: Params) -> Self {
        Self {
            geo: Geo::new(params.clone()),
            clock: BootClock::default(),
            home: None,
            fed: HashMap::new(),
            fit: None,
            fitted_at: None,
            last_heading_rad: None,
            counts: Counts::default(),
            video_delay_ms: VecDeque::new(),
            video_delay_sum_ms: (0.0, 0),
            anchors: HashMap::new(),
            frame_pairs: VecDeque::new(),
            last_frame_pair_t: f64::NEG_INFINITY,
            restored: HashSet::new(),
            restore: None,
            check: None,
            force_fit: false,
            last_attitude: None,
            last_gimbal: None,
            map_aided: false,
            params,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// The parts: telemetry history, pairs, home.
    pub fn geo(&self) -> &Geo {
        &self.geo
    }

    /// The boot clock's offset (`local - boot`, seconds), once known.
    pub fn boot_offset_s(&self) -> Option<f64> {
        self.clock.offset_s()
    }

    /// Whether the SLAM's map is in local NED (gps-aided): the georeference
    /// then follows from the map instead of a fit (from the next sync).
    pub fn set_map_aided(&mut self, aided: bool) {
        if self.map_aided != aided {
            tracing::info!(
                aided,
                "geo: the map is {}",
                if aided {
                    "in local NED (gps-aided): the georeference follows from it"
                } else {
                    "vision-only: the georeference is fitted"
                }
            );
            self.map_aided = aided;
            self.force_fit = true;
        }
    }

    /// Takes the georeference saved by the previous run: its pairs are
    /// restored onto the continued map's keyframes as they appear (by id
    /// and capture time), or dropped when the map was not continued. A
    /// file of another format, or without a valid home, is ignored
    /// (logged).
    pub fn restore(&mut self, saved: SavedGeoreference) {
        let Some(mut restore) = Restore::from_saved(saved) else {
            return;
        };
        if let Some(h) = self.home {
            restore.rebase(h);
        }
        self.restore = Some(restore);
    }

    /// The georeference to save beside the map (written at `now_unix`):
    /// every pair held (keyframe and frame pairs, restored or live) with
    /// its anchor, and the saved pairs still waiting for their keyframes.
    /// None before any home is known (no pair can exist then).
    pub fn saved(&self, now_unix: f64) -> Option<SavedGeoreference> {
        let home = self.home.or(self.restore.as_ref().map(|r| r.home))?;
        let mut pairs: Vec<_> = self
            .geo
            .georeference()
            .pairs()
            .iter()
            .filter_map(|p| self.anchors.get(&p.kf_id)?.saved_pair(p))
            .collect();
        if let Some(r) = &self.restore {
            pairs.extend(r.waiting.iter().copied());
        }
        let fit = match &self.fit {
            Some(Ok(a)) => Some(SavedFit {
                scale: a.ned_from_map.scale,
                rms_m: a.quality.rms_m,
                inliers: a.quality.inliers,
                pairs: a.quality.pairs,
            }),
            _ => None,
        };
        Some(SavedGeoreference {
            format: SAVED_FORMAT,
            saved_unix: now_unix,
            home,
            pairs,
            fit,
        })
    }

    fn sample_time(&mut self, boot_ms: Option<u32>, received_unix: f64) -> f64 {
        self.clock
            .sample_time(self.params.history.telemetry_clock, boot_ms, received_unix)
    }

    /// HOME_POSITION: the origin of local NED (the first one heard; later
    /// ones are ignored, since the history is in its frame). Saved pairs
    /// expressed at another home are carried to it.
    pub fn on_home(&mut self, g: Geodetic) {
        if self.home.is_some() {
            return;
        }
        match self.geo.set_home(g) {
            Ok(()) => {
                tracing::info!(lat = g.lat_deg, lon = g.lon_deg, alt = g.alt_m, "geo: home");
                self.home = Some(g);
                self.carry_restored_to(g);
            }
            Err(e) => tracing::warn!("geo: home refused: {e}"),
        }
    }

    /// Home, once known.
    pub fn home(&self) -> Option<Geodetic> {
        self.home
    }

    /// The vehicle's home is `home`: saved pairs expressed at another home
    /// (waiting or already restored) are carried to it.
    fn carry_restored_to(&mut self, home: Geodetic) {
        let Some(r) = self.restore.as_mut() else {
            return;
        };
        let from = LocalFrame::new(r.home);
        let moved = r.rebase(home);
        if moved == 0.0 {
            return;
        }
        let to = LocalFrame::new(home);
        let to_from = to.ned_from_other(&from);
        let ids: Vec<u64> = self.restored.iter().copied().collect();
        for id in ids {
            let Some(p) = self
                .geo
                .georeference()
                .pairs()
                .iter()
                .find(|p| p.kf_id == id)
                .copied()
            else {
                continue;
            };
            let Some((map_rot, ned_rot)) = p.orientations else {
                continue;
            };
            let map_from_cam = Isometry3::from_parts(p.p_map.coords.into(), map_rot);
            let ned = to_from * Isometry3::from_parts(p.p_ned.coords.into(), ned_rot);
            let v = p.v_ned.map(|v| to_from.rotation * v);
            if let Err(e) = self.geo.add_known(id, &map_from_cam, &ned, v, p.time) {
                tracing::warn!(
                    pair = id,
                    "geo: restored pair not carried to the new home: {e}"
                );
            }
        }
        self.force_fit = true;
        tracing::info!(
            moved_m = moved,
            "geo: the vehicle's home differs from the saved one; saved pairs carried to it"
        );
    }

    /// GLOBAL_POSITION_INT (ignored before home): the sample's time (by
    /// its boot time `boot_ms`, received at `received_unix`) and its local
    /// NED position, when the history took it.
    pub fn on_position(
        &mut self,
        boot_ms: u32,
        received_unix: f64,
        g: &Geodetic,
    ) -> Option<(f64, Vector3<f64>)> {
        self.home?;
        let t = self.sample_time(Some(boot_ms), received_unix);
        match self.geo.push_position_geodetic(t, g) {
            Ok(()) => self.counts.positions += 1,
            Err(_) => {
                self.counts.rejected_samples += 1;
                return None;
            }
        }
        Some((t, self.geo.frame()?.geodetic_to_ned(g)))
    }

    /// ATTITUDE (radians; timed by `boot_ms`, received at `received_unix`).
    pub fn on_attitude(
        &mut self,
        boot_ms: u32,
        received_unix: f64,
        (roll, pitch, yaw): (f64, f64, f64),
    ) {
        let t = self.sample_time(Some(boot_ms), received_unix);
        self.last_heading_rad = Some(yaw);
        self.last_attitude = Some(UnitQuaternion::from_euler_angles(roll, pitch, yaw));
        match self
            .geo
            .history_mut()
            .push_attitude_euler(t, roll, pitch, yaw)
        {
            Ok(()) => self.counts.attitudes += 1,
            Err(_) => self.counts.rejected_samples += 1,
        }
    }

    /// The latest attitude (NED ← body), once one came.
    pub fn last_attitude(&self) -> Option<UnitQuaternion<f64>> {
        self.last_attitude
    }

    /// The latest gimbal angles (relative to the body) and their time (the
    /// frames' clock), once one came.
    pub fn last_gimbal(&self) -> Option<(f64, GimbalAngles)> {
        self.last_gimbal
    }

    /// Gimbal attitude: pitch and yaw in degrees, the yaw relative to the
    /// body or, with `yaw_absolute`, to north (made relative with the
    /// latest heading; refused before one).
    pub fn on_gimbal(
        &mut self,
        boot_ms: Option<u32>,
        received_unix: f64,
        (pitch_deg, yaw_deg, yaw_absolute): (f64, f64, bool),
    ) {
        let t = self.sample_time(boot_ms, received_unix);
        let mut yaw = yaw_deg.to_radians();
        if yaw_absolute {
            let Some(h) = self.last_heading_rad else {
                self.counts.rejected_samples += 1;
                return;
            };
            yaw -= h;
        }
        let angles = GimbalAngles {
            pitch: pitch_deg.to_radians(),
            yaw: wrap_pi(yaw),
        };
        self.last_gimbal = Some((t, angles));
        match self.geo.history_mut().push_gimbal(t, angles) {
            Ok(()) => self.counts.gimbals += 1,
            Err(_) => self.counts.rejected_samples += 1,
        }
    }

    /// A sample went to the SLAM's telemetry priors (`fix`: with a fix).
    pub fn note_prior_sample(&mut self, fix: bool) {
        self.counts.prior_samples += 1;
        if !fix {
            self.counts.prior_samples_without_fix += 1;
        }
    }

    /// A video frame taken by the SLAM: records the sender's delay (receive
    /// time minus its capture time) when the frame is stamped.
    pub fn note_frame(&mut self, capture_time: Option<f64>, received_unix: f64) {
        if let Some(c) = capture_time {
            let d = (received_unix - c) * 1e3;
            if d.is_finite() {
                if self.video_delay_ms.len() == DELAY_WINDOW {
                    self.video_delay_ms.pop_front();
                }
                self.video_delay_ms.push_back(d);
                self.video_delay_sum_ms.0 += d;
                self.video_delay_sum_ms.1 += 1;
            }
        }
    }

    /// One round: the saved pairs are restored onto the keyframes once the
    /// map is known to be continued (`continued`: Some(true); Some(false)
    /// drops them; None waits); new keyframes are paired with telemetry
    /// (or wait for it), moved ones take their new map pose (and so do the
    /// frame pairs hung on them), culled ones are forgotten; `frame`
    /// becomes a frame pair when the last one is old enough; the waiting
    /// pairs are retried; the saved pairs are checked against the live
    /// ones; and the alignment is refitted when anything changed.
    pub fn sync(
        &mut self,
        keyframes: &[MapKeyframe],
        frame: Option<TrackedPose>,
        continued: Option<bool>,
    ) {
        let mut changed = std::mem::take(&mut self.force_fit);
        let poses: KeyframePoses = keyframes
            .iter()
            .filter_map(|k| Some((k.id, (k.timestamp, k.world_from_cam?))))
            .collect();
        changed |= self.restore_pairs(&poses, continued);
        let mut seen = HashSet::with_capacity(keyframes.len());
        let mut moved_kfs = HashSet::new();
        for kf in keyframes {
            seen.insert(kf.id);
            let Some(pose) = kf.world_from_cam else {
                continue;
            };
            let key = pose_key(&pose);
            match self.fed.get(&kf.id) {
                None => {
                    self.counts.keyframes_seen += 1;
                    match self.geo.add_keyframe(kf.id, &pose, kf.timestamp) {
                        Ok(status) => {
                            changed |= status == KeyframeStatus::Paired;
                            self.anchors
                                .insert(kf.id, Anchor::keyframe(kf.id, kf.timestamp));
                        }
                        Err(e) => {
                            self.counts.keyframes_refused += 1;
                            tracing::debug!(kf = kf.id, "geo: keyframe refused: {e}");
                        }
                    }
                    self.fed.insert(kf.id, key);
                }
                Some(old) if old != &key => {
                    moved_kfs.insert(kf.id);
                    if matches!(self.geo.refresh_keyframe(kf.id, &pose), Ok(true)) {
                        self.counts.keyframes_moved += 1;
                        changed = true;
                    }
                    self.fed.insert(kf.id, key);
                }
                Some(_) => {}
            }
        }
        let gone: Vec<u64> = self
            .fed
            .keys()
            .filter(|id| !seen.contains(id))
            .copied()
            .collect();
        for id in gone {
            self.fed.remove(&id);
            if self.geo.remove_keyframe(id) {
                self.counts.keyframes_removed += 1;
                changed = true;
            }
        }
        changed |= self.follow_frame_pairs(&poses, &moved_kfs);
        if let Some(f) = frame {
            changed |= self.add_frame_pair(&poses, &f);
        }
        if self.geo.retry_pending() > 0 {
            changed = true;
        }
        // Anchors of pairs the georeference dropped (their telemetry never
        // came) go too.
        if self.anchors.len() > self.geo.georeference().pairs().len() + self.geo.pending() {
            let geo = &self.geo;
            self.anchors.retain(|id, _| geo.knows_keyframe(*id));
            self.frame_pairs.retain(|id| geo.knows_keyframe(*id));
        }
        if changed && !self.restored.is_empty() {
            self.check_restored();
        }
        self.refit(changed);
    }

    /// Frame pairs follow their keyframe when it moved, or go with it.
    /// Returns whether any pair changed.
    fn follow_frame_pairs(&mut self, poses: &KeyframePoses, moved_kfs: &HashSet<u64>) -> bool {
        let mut changed = false;
        let frames: Vec<(u64, Anchor)> = self
            .anchors
            .iter()
            .filter(|(_, a)| a.kind == PairKind::Frame)
            .map(|(id, a)| (*id, *a))
            .collect();
        for (id, a) in frames {
            match poses.get(&a.kf) {
                Some((t, kf_pose)) if *t == a.kf_time => {
                    if moved_kfs.contains(&a.kf) {
                        let pose = (a.cam_from_kf * kf_pose.inverse()).inverse();
                        changed |= matches!(self.geo.refresh_keyframe(id, &pose), Ok(true));
                    }
                }
                _ if poses.is_empty() => {}
                _ => {
                    changed |= self.geo.remove_keyframe(id);
                    self.anchors.remove(&id);
                    self.restored.remove(&id);
                }
            }
        }
        changed
    }

    /// Refits after a change (or before the first fit); a gps-aided map's
    /// alignment is the identity.
    fn refit(&mut self, changed: bool) {
        if self.map_aided {
            if changed || self.fit.is_none() {
                self.fit = Some(Ok(GeoAlignment::of_map_in_ned(
                    self.geo.georeference().pairs(),
                    self.geo.georeference().params(),
                )));
                self.fitted_at = Some(crate::clock::now());
            }
        } else if changed || self.fit.is_none() && self.geo.georeference().pairs().len() >= 3 {
            let r = self.geo.fit();
            self.counts.fits += 1;
            match &r {
                Ok(a) => tracing::debug!(
                    scale = a.ned_from_map.scale,
                    rms_m = a.quality.rms_m,
                    inliers = a.quality.inliers,
                    pairs = a.quality.pairs,
                    "geo: fitted"
                ),
                Err(e) => tracing::debug!("geo: not fitted: {e}"),
            }
            self.fit = Some(r);
            self.fitted_at = Some(crate::clock::now());
        }
    }

    /// Restores the waiting saved pairs whose keyframes are in `poses` (once
    /// the map is known to be continued); returns whether any was added.
    fn restore_pairs(&mut self, poses: &KeyframePoses, continued: Option<bool>) -> bool {
        let Some(waiting) = self
            .restore
            .as_mut()
            .and_then(|r| r.take_waiting(continued, !poses.is_empty()))
        else {
            return false;
        };
        let mut added = 0;
        let mut unmatched = 0;
        for p in waiting {
            let Some((map_from_cam, ned)) = place(&p, poses) else {
                unmatched += 1;
                continue;
            };
            let v = p.v_ned.map(Vector3::from);
            if self
                .geo
                .add_known(p.id, &map_from_cam, &ned, v, p.time)
                .is_err()
            {
                unmatched += 1;
                continue;
            }
            self.anchors.insert(p.id, Anchor::of_saved(&p));
            self.restored.insert(p.id);
            if p.kind == PairKind::Keyframe {
                self.fed.insert(p.anchor_kf, pose_key(&map_from_cam));
            }
            added += 1;
        }
        if let Some(r) = self.restore.as_mut() {
            r.restored += added;
            r.unmatched += unmatched;
        }
        tracing::info!(
            restored = added,
            unmatched,
            "geo: saved georeference restored onto the continued map"
        );
        added > 0
    }

    /// Pairs the tracked frame `f` with telemetry when the last frame pair
    /// is old enough; the oldest frame pairs go beyond the limit. Returns
    /// whether a pair was added or removed.
    fn add_frame_pair(&mut self, poses: &KeyframePoses, f: &TrackedPose) -> bool {
        let cp: &ContinuityParams = &self.params.continuity;
        if !(cp.frame_pair_spacing_s > 0.0 && cp.max_frame_pairs > 0 && f.timestamp.is_finite())
            || f.timestamp < self.last_frame_pair_t + cp.frame_pair_spacing_s
        {
            return false;
        }
        let max_frame_pairs = cp.max_frame_pairs;
        let Some((kf_time, world_from_kf)) = poses.get(&f.reference_kf) else {
            return false;
        };
        let id = frame_pair_id(f.timestamp);
        if self.geo.knows_keyframe(id) {
            return false;
        }
        let map_from_cam = (f.cam_from_ref * world_from_kf.inverse()).inverse();
        self.last_frame_pair_t = f.timestamp;
        let mut changed = false;
        match self.geo.add_keyframe(id, &map_from_cam, f.timestamp) {
            Ok(status) => {
                self.counts.frame_pairs_added += 1;
                changed |= status == KeyframeStatus::Paired;
                self.anchors.insert(
                    id,
                    Anchor {
                        kind: PairKind::Frame,
                        kf: f.reference_kf,
                        kf_time: *kf_time,
                        cam_from_kf: f.cam_from_ref,
                    },
                );
                self.frame_pairs.push_back(id);
            }
            Err(e) => {
                self.counts.frame_pairs_refused += 1;
                tracing::debug!(frame = f.seq, "geo: frame pair refused: {e}");
            }
        }
        while self.frame_pairs.len() > max_frame_pairs {
            if let Some(old) = self.frame_pairs.pop_front() {
                changed |= self.geo.remove_keyframe(old);
                self.anchors.remove(&old);
            }
        }
        changed
    }

    /// Checks the restored pairs against the live ones (see
    /// [`check_saved`]); drops the restored pairs when they disagree.
    fn check_restored(&mut self) {
        let (old, live): (Vec<_>, Vec<_>) = self
            .geo
            .georeference()
            .pairs()
            .iter()
            .copied()
            .partition(|p| self.restored.contains(&p.kf_id));
        let Some(check) = check_saved(&old, &live, &self.params) else {
            return;
        };
        if let Check::Disagrees {
            live_pairs,
            median_residual_m,
            bound_m,
        } = check
        {
            tracing::warn!(
                median_residual_m,
                bound_m,
                live_pairs,
                "geo: the saved georeference disagrees with live telemetry: dropped, refitting from live pairs"
            );
            let ids: Vec<u64> = self.restored.drain().collect();
            for id in ids {
                self.geo.remove_keyframe(id);
                self.anchors.remove(&id);
            }
            if let (Some(r), Some(why)) = (self.restore.as_mut(), check.dropped_reason()) {
                r.drop_all(why);
            }
        }
        self.check = Some(check);
    }

    /// The vehicle target that puts the camera at `map_from_cam` (a camera
    /// pose in the SLAM map), with the alignment it went through.
    pub fn target(
        &mut self,
        map_from_cam: &Isometry3<f64>,
    ) -> Result<(GeoTarget, GeoAlignment), GeoError> {
        let frame = *self.geo.frame().ok_or(GeoError::NoHome)?;
        let alignment = self.alignment()?;
        let target = convert_target(&alignment, map_from_cam, &frame, &self.params.mount)?;
        Ok((target, alignment))
    }

    /// The map -> NED alignment in use: the identity of a gps-aided map's
    /// pairs, else the (re)fitted one.
    fn alignment(&mut self) -> Result<GeoAlignment, GeoError> {
        if self.map_aided {
            Ok(GeoAlignment::of_map_in_ned(
                self.geo.georeference().pairs(),
                self.geo.georeference().params(),
            ))
        } else {
            self.geo.fit()
        }
    }

    /// A geodetic position (a photo's GPS tag, at the altitude the caller
    /// trusts) in the map's frame: the point, and the alignment it went
    /// through (its scale turns metres into map units; its rotation gives
    /// the map's down).
    pub fn map_point_of(
        &mut self,
        g: &super::Geodetic,
    ) -> Result<(nalgebra::Point3<f64>, GeoAlignment), GeoError> {
        let frame = *self.geo.frame().ok_or(GeoError::NoHome)?;
        let alignment = self.alignment()?;
        let ned = nalgebra::Point3::from(frame.geodetic_to_ned(g));
        Ok((
            alignment.ned_from_map.inverse().transform_point(&ned),
            alignment,
        ))
    }

    /// The state as the API reports it: `ok` with the fit's scale,
    /// residual and keyframes used, `refused` with the reason (too little
    /// motion, too few pairs, ...), or `waiting` before any fit; the
    /// evidence, the clocks and the saved georeference beside it.
    pub fn status(&self) -> GeoreferenceStatus {
        let georef = self.geo.georeference();
        let delays: Vec<f64> = self.video_delay_ms.iter().copied().collect();
        let (positions, attitudes, gimbals) = self.geo.history().len();
        GeoreferenceStatus {
            home: self.home.map(|h| HomeView {
                lat_deg: h.lat_deg,
                lon_deg: h.lon_deg,
                alt_amsl_m: h.alt_m,
            }),
            pairs: georef.pairs().len(),
            keyframes_pending: self.geo.pending(),
            keyframes_dropped: self.geo.dropped(),
            history: HistoryCounts {
                positions,
                attitudes,
                gimbals,
            },
            counts: self.counts,
            clock: ClockStatus {
                telemetry: self.params.history.telemetry_clock,
                boot_offset_unix_s: self.clock.offset_s(),
                use_frame_timestamps: self.params.history.use_frame_timestamps,
                video_latency_s: self.params.history.video_latency_s,
                video_delay_ms_median: crate::stats::median(&delays),
                video_delay_ms_mean_all: (self.video_delay_sum_ms.1 > 0)
                    .then(|| self.video_delay_sum_ms.0 / self.video_delay_sum_ms.1 as f64),
            },
            fit_age_s: self.fitted_at.map(|t| crate::clock::since(t).as_secs_f64()),
            evidence: Evidence {
                restored_pairs: self.restored.len(),
                frame_pairs: self.frame_pairs.len(),
                live_keyframe_pairs: georef
                    .pairs()
                    .iter()
                    .filter(|p| p.kf_id & FRAME_PAIR_BIT == 0 && !self.restored.contains(&p.kf_id))
                    .count(),
            },
            saved: self.restore.as_ref().map(|r| r.status(self.check.as_ref())),
            fit: self.fit_status(),
        }
    }

    /// The fit's part of [`Self::status`].
    fn fit_status(&self) -> FitState {
        let georef = self.geo.georeference();
        match &self.fit {
            None => FitState::Waiting {
                reason: if self.home.is_none() {
                    "no home position yet".to_string()
                } else {
                    format!("{} keyframe pairs so far", georef.pairs().len())
                },
            },
            Some(Err(e)) => {
                let dropped = self.restore.as_ref().and_then(|r| r.dropped.as_deref());
                let reason = match dropped {
                    Some(d) => format!("{e} (the saved georeference was dropped: {d})"),
                    None => e.to_string(),
                };
                FitState::Refused {
                    reason,
                    error: format!("{e:?}"),
                }
            }
            Some(Ok(a)) => {
                let q = &a.quality;
                let r = a.ned_from_map.rotation.coords;
                let t = a.ned_from_map.translation;
                FitState::Ok(Box::new(FitView {
                    source: if self.map_aided { "map" } else { "fit" },
                    held: georef.held().filter(|_| !self.map_aided).map(|e| {
                        format!(
                            "the last fit is kept: a refit now is refused ({e}) and the {} pairs held agree with it",
                            georef.pairs().len()
                        )
                    }),
                    scale: a.ned_from_map.scale,
                    rms_m: q.rms_m,
                    max_residual_m: q.max_residual_m,
                    rotation_rms_deg: q.rotation_rms_deg,
                    time_offset_s: q.time_offset_s,
                    keyframes_used: q.inliers,
                    older_pairs_set_aside: q.set_aside,
                    gnss_bias_m: q.gnss_bias_m,
                    mount_offset: a.mount_offset,
                    recent: (q.set_aside > 0).then(|| {
                        format!(
                            "fitted on the newest {} pairs: the {} older ones disagree with them (a GNSS bias that drifted, or a map that bent)",
                            q.pairs, q.set_aside
                        )
                    }),
                    spread_m: q.spread_m2.map(f64::sqrt),
                    ned_from_map: SimView {
                        scale: a.ned_from_map.scale,
                        rotation_xyzw: [r.x, r.y, r.z, r.w],
                        translation: [t.x, t.y, t.z],
                    },
                }))
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::{MountParams, ned_from_cam};
    use crate::geometry::Sim3;
    use nalgebra::Point3;

    const HOME: Geodetic = Geodetic {
        lat_deg: 47.3977,
        lon_deg: 8.5456,
        alt_m: 488.0,
    };
    /// The local clock at boot: every sample is received 20 ms after it
    /// was taken, so the boot clock's offset is this.
    const BOOT_UNIX: f64 = 1.7e9 + 0.02;

    /// The L-shaped flight's NED position at `t`: north, then east, at 10 m.
    fn path(t: f64) -> Vector3<f64> {
        if t < 20.0 {
            Vector3::new(t, 0.0, -10.0)
        } else {
            Vector3::new(20.0, t - 20.0, -10.0)
        }
    }

    /// Feeds home and 40 s of telemetry of the L-shaped flight (facing
    /// north, camera 30 deg down) on the boot clock; with `telemetry`
    /// false only home. Returns the boot clock's offset.
    fn feed_flight(geo: &mut LiveGeoreference, telemetry: bool) -> f64 {
        let frame = LocalFrame::new(HOME);
        geo.on_home(HOME);
        if !telemetry {
            return 0.0;
        }
        for i in 0..=400 {
            let t = i as f64 * 0.1;
            let ms = (t * 1e3).round() as u32;
            let received = BOOT_UNIX + t;
            geo.on_position(ms, received, &frame.ned_to_geodetic(&path(t)));
            geo.on_attitude(ms, received, (0.0, 0.0, 0.0));
            geo.on_gimbal(Some(ms), received, (-30.0, 0.0, false));
        }
        geo.boot_offset_s().unwrap()
    }

    /// The map: NED through a known similarity (a monocular map's scale).
    fn map_from_ned() -> Sim3 {
        Sim3::new(
            UnitQuaternion::from_euler_angles(0.3, -1.0, 2.0),
            Vector3::new(1.0, -2.0, 0.5),
            0.08,
        )
    }

    /// Keyframe `id` at flight time `t` (local clock `t + offset`), posed
    /// in the map (through `map`: None, the map is NED itself) from
    /// `telemetry`'s history.
    fn keyframe(
        telemetry: &LiveGeoreference,
        id: u64,
        t: f64,
        offset: f64,
        map: Option<Sim3>,
    ) -> MapKeyframe {
        let state = telemetry.geo().history().lookup(t + offset).unwrap();
        let ned = ned_from_cam(&state, &MountParams::default());
        let world_from_cam = match map {
            Some(m) => {
                let p = m.transform_point(&Point3::from(ned.translation.vector));
                Isometry3::from_parts(p.coords.into(), m.rotation * ned.rotation)
            }
            None => ned,
        };
        MapKeyframe {
            id,
            timestamp: t + offset,
            world_from_cam: Some(world_from_cam),
        }
    }

    fn keyframes(
        geo: &LiveGeoreference,
        ids: std::ops::Range<u64>,
        offset: f64,
    ) -> Vec<MapKeyframe> {
        ids.map(|i| keyframe(geo, i, 1.0 + 2.0 * i as f64, offset, Some(map_from_ned())))
            .collect()
    }

    /// An L-shaped flight at 10 m, facing north with the camera 30 deg
    /// down: telemetry on the boot clock, keyframes in a map that is NED
    /// through a known similarity. Refused while the motion is a line, then
    /// fitted with the map's scale; a keyframe culled is forgotten.
    #[test]
    fn telemetry_and_keyframes_give_the_maps_similarity() {
        let mut geo = LiveGeoreference::new(Params::default());
        let offset = feed_flight(&mut geo, true);
        assert!((offset - BOOT_UNIX).abs() < 1e-6, "{offset}");
        // The first leg only: a line.
        let mut kfs = keyframes(&geo, 0..8, offset);
        geo.sync(&kfs, None, None);
        let s = serde_json::to_value(geo.status()).unwrap();
        assert_eq!(s["state"], "refused", "{s}");
        assert!(s["reason"].as_str().unwrap().contains("line"), "{s}");
        // Round the corner.
        kfs.extend(keyframes(&geo, 8..16, offset));
        geo.sync(&kfs, None, None);
        let s = serde_json::to_value(geo.status()).unwrap();
        assert_eq!(s["state"], "ok", "{s}");
        assert_eq!(s["source"], "fit", "{s}");
        let scale = s["scale"].as_f64().unwrap();
        assert!((scale * 0.08 - 1.0).abs() < 1e-3, "{s}");
        assert!(s["rms_m"].as_f64().unwrap() < 0.02, "{s}");
        assert_eq!(s["keyframes_used"], 16);
        assert_eq!(s["counts"]["positions"], 401);
        // A target at a keyframe's pose is that keyframe's camera.
        let kf = &kfs[12];
        let (target, _) = geo.target(&kf.world_from_cam.unwrap()).unwrap();
        assert!((target.gimbal_pitch_deg + 30.0).abs() < 0.05, "{target:?}");
        assert!(
            target.yaw_deg < 0.05 || target.yaw_deg > 359.95,
            "{target:?}"
        );
        let p = path(kf.timestamp - offset);
        assert!((target.p_ned_vehicle - p).norm() < 0.02, "{target:?}");
        // Culled keyframes are forgotten.
        kfs.truncate(12);
        geo.sync(&kfs, None, None);
        assert_eq!(serde_json::to_value(geo.status()).unwrap()["pairs"], 12);
    }

    /// A gps-aided map's georeference is the identity, from the map
    /// (`source` `map`), its targets through it; back to vision-only, it
    /// is fitted again.
    #[test]
    fn an_aided_map_is_its_own_georeference() {
        let mut geo = LiveGeoreference::new(Params::default());
        let offset = feed_flight(&mut geo, true);
        geo.set_map_aided(true);
        let kfs: Vec<MapKeyframe> = (0..16)
            .map(|i| keyframe(&geo, i, 1.0 + 2.0 * i as f64, offset, None))
            .collect();
        geo.sync(&kfs, None, None);
        let st = serde_json::to_value(geo.status()).unwrap();
        assert_eq!(st["state"], "ok", "{st}");
        assert_eq!(st["source"], "map", "{st}");
        assert_eq!(st["scale"], 1.0);
        assert_eq!(st["keyframes_used"], 16);
        assert!(st["rms_m"].as_f64().unwrap() < 1e-3, "{st}");
        let kf = &kfs[12];
        let (target, alignment) = geo.target(&kf.world_from_cam.unwrap()).unwrap();
        assert_eq!(alignment.ned_from_map.scale, 1.0);
        let p = path(kf.timestamp - offset);
        assert!((target.p_ned_vehicle - p).norm() < 0.02, "{target:?}");
        geo.set_map_aided(false);
        geo.sync(&kfs, None, None);
        assert_eq!(serde_json::to_value(geo.status()).unwrap()["source"], "fit");
    }

    /// A restart: the saved pairs (through their JSON file) put the
    /// continued map's keyframes in NED with no telemetry at all, the
    /// target of a keyframe's pose is the same as before; not before the
    /// map is known to be continued, and not at all when it was not.
    #[test]
    fn a_saved_georeference_is_restored_onto_the_continued_map() {
        let mut before = LiveGeoreference::new(Params::default());
        let offset = feed_flight(&mut before, true);
        let kfs = keyframes(&before, 0..16, offset);
        before.sync(&kfs, None, None);
        assert_eq!(
            serde_json::to_value(before.status()).unwrap()["state"],
            "ok"
        );
        let pose = kfs[12].world_from_cam.unwrap();
        let (t_before, _) = before.target(&pose).unwrap();
        let saved = before.saved(2e9).unwrap();
        assert_eq!(saved.pairs.len(), 16);
        assert_eq!(saved.saved_unix, 2e9);
        let text = serde_json::to_vec(&saved).unwrap();
        let file: SavedGeoreference = serde_json::from_slice(&text).unwrap();

        let mut after = LiveGeoreference::new(Params::default());
        after.restore(file.clone());
        feed_flight(&mut after, false);
        after.sync(&kfs, None, None);
        assert_eq!(
            serde_json::to_value(after.status()).unwrap()["state"],
            "waiting",
            "not before the map is known"
        );
        after.sync(&kfs, None, Some(true));
        let s = serde_json::to_value(after.status()).unwrap();
        assert_eq!(s["state"], "ok", "{s}");
        assert_eq!(s["evidence"]["restored_pairs"], 16, "{s}");
        assert!(s["rms_m"].as_f64().unwrap() < 0.02, "{s}");
        let (t_after, _) = after.target(&pose).unwrap();
        assert!((t_after.p_ned_vehicle - t_before.p_ned_vehicle).norm() < 1e-3);
        // Saved again: the same pairs.
        assert_eq!(after.saved(2e9).unwrap().pairs.len(), 16);

        let mut fresh = LiveGeoreference::new(Params::default());
        fresh.restore(file);
        feed_flight(&mut fresh, false);
        fresh.sync(&kfs, None, Some(false));
        let s = serde_json::to_value(fresh.status()).unwrap();
        assert_ne!(s["state"], "ok", "{s}");
        assert_eq!(s["evidence"]["restored_pairs"], 0, "{s}");
    }

    /// A saved georeference that live telemetry contradicts (its NED side
    /// 5 m off, as a GPS glitch at the last session would leave it) is
    /// dropped once enough live pairs are in, and the fit is made from
    /// the live pairs alone; one that agrees is kept.
    #[test]
    fn a_saved_georeference_that_live_pairs_contradict_is_dropped() {
        let mut before = LiveGeoreference::new(Params::default());
        let offset = feed_flight(&mut before, true);
        let old = keyframes(&before, 0..16, offset);
        before.sync(&old, None, None);
        let good = before.saved(2e9).unwrap();
        let mut bad = good.clone();
        for p in &mut bad.pairs {
            p.ned_from_cam.translation[0] += 5.0;
        }
        for (file, agrees) in [(good, true), (bad, false)] {
            let mut after = LiveGeoreference::new(Params::default());
            after.restore(file);
            let offset = feed_flight(&mut after, true);
            // New keyframes of this run, paired with live telemetry.
            let mut kfs = old.clone();
            kfs.extend((0..10).map(|i| {
                keyframe(
                    &after,
                    100 + i,
                    2.0 + 3.8 * i as f64,
                    offset,
                    Some(map_from_ned()),
                )
            }));
            after.sync(&kfs, None, Some(true));
            let s = serde_json::to_value(after.status()).unwrap();
            assert_eq!(s["state"], "ok", "{s}");
            let check = &s["saved"]["check"];
            if agrees {
                assert_eq!(check["state"], "agrees", "{s}");
                assert_eq!(s["evidence"]["restored_pairs"], 16, "{s}");
            } else {
                assert_eq!(check["state"], "disagrees", "{s}");
                let m = check["median_residual_m"].as_f64().unwrap();
                assert!((m - 5.0).abs() < 0.5, "{s}");
                assert!(s["saved"]["dropped"].as_str().is_some(), "{s}");
                assert_eq!(s["evidence"]["restored_pairs"], 0, "{s}");
                assert_eq!(s["keyframes_used"], 10, "{s}");
            }
            assert!(s["rms_m"].as_f64().unwrap() < 0.05, "{s}");
        }
    }

    /// A tracked frame becomes a pair hung on its reference keyframe, at
    /// most once per spacing, and follows the keyframe when it moves.
    #[test]
    fn tracked_frames_pair_with_telemetry_and_follow_their_keyframe() {
        let mut geo = LiveGeoreference::new(Params::default());
        let offset = feed_flight(&mut geo, true);
        let mut kfs = keyframes(&geo, 0..16, offset);
        geo.sync(&kfs, None, None);
        let kf = kfs[12];
        let frame = |dt: f64| TrackedPose {
            seq: 1,
            timestamp: kf.timestamp + dt,
            reference_kf: kf.id,
            cam_from_ref: Isometry3::identity(),
        };
        geo.sync(&kfs, Some(frame(0.1)), None);
        geo.sync(&kfs, Some(frame(0.5)), None);
        let s = serde_json::to_value(geo.status()).unwrap();
        assert_eq!(s["evidence"]["frame_pairs"], 1, "one per spacing: {s}");
        assert_eq!(s["counts"]["frame_pairs_added"], 1, "{s}");
        let id = frame_pair_id(kf.timestamp + 0.1);
        assert!(geo.geo().knows_keyframe(id));
        // The keyframe moves: the frame pair moves with it.
        let moved = Isometry3::translation(0.5, 0.0, 0.0) * kf.world_from_cam.unwrap();
        kfs[12].world_from_cam = Some(moved);
        geo.sync(&kfs, None, None);
        let p = geo
            .geo()
            .georeference()
            .pairs()
            .iter()
            .find(|p| p.kf_id == id)
            .copied()
            .unwrap();
        assert!((p.p_map.coords - moved.translation.vector).norm() < 1e-9);
        // It is culled: the frame pair goes with it.
        kfs.remove(12);
        geo.sync(&kfs, None, None);
        assert!(!geo.geo().knows_keyframe(id));
    }
}
