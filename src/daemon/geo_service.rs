//! The daemon's georeference: telemetry from the link actor and keyframes
//! from the SLAM feed one [`Geo`]; the map → NED alignment is refitted as
//! keyframes arrive, move (bundle adjustment) or go (culling); the API reads
//! its state and turns a localised shot's camera pose into a vehicle target.
//!
//! Across restarts: the telemetry side of every pair is saved beside the
//! map ([`GeoService::saved`], `<map_file>.geo.json`, written with each map
//! checkpoint and at shutdown) and restored onto the continued map's
//! keyframes ([`GeoService::restore`]), so the map is georeferenced as soon
//! as it is loaded. Tracked frames pair with live telemetry too (one per
//! [`ContinuityParams::frame_pair_spacing_s`], hung on their reference
//! keyframe), so live evidence comes in while the drone flies over mapped
//! ground and adds no keyframe; once enough of it is in, the saved pairs
//! are checked against it and dropped, with the reason in the status, when
//! they disagree beyond their own residuals (the fit is then made from
//! live pairs alone). A saved file whose home differs from the vehicle's
//! HOME_POSITION is carried to the new home exactly.
//!
//! Telemetry priors (`[slam] priors`): each GLOBAL_POSITION_INT also
//! becomes a sample of the SLAM's live [`TelemetryFeed`] (on the frames'
//! clock, as the history's): the camera's position in local NED (the
//! vehicle's plus the mount's lever arm turned by the latest attitude), a
//! fix only when the latest GPS_RAW_INT (at most [`GPS_RAW_MAX_AGE`] old)
//! reports a 3D fix and its accuracy, with that accuracy. While the SLAM's
//! map is gps-aided (in local NED, held there by the priors) the
//! georeference follows from the map: the identity to local NED at home,
//! its residuals against the pairs reported, no separate fit (the status's
//! `source`: `map`, else `fit`).
//!
//! Clocks: frames are timed by [`crate::geo::capture_time`] (the frame's
//! `X-Timestamp` when used, else receive time minus the configured video
//! latency), and the SLAM stamps its keyframes with that time. Telemetry is
//! timed per [`TelemetryClock`]: by the autopilot's `time_boot_ms` mapped to
//! the local clock by the smallest `receive - boot` seen (so the link's
//! jitter does not reach the samples), or by receive time.

use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, UnitQuaternion, Vector3};
use serde_json::{Value, json};
use tokio_util::sync::CancellationToken;

use crate::api::{KeyframeInfo, SlamView, TrackedFrame};
use crate::geo::align::fit_pairs;
use crate::geo::saved::{
    PairKind, SAVED_FORMAT, SavedFit, SavedGeoreference, SavedPair, SavedPose,
};
use crate::geo::{
    ContinuityParams, Geo, GeoAlignment, GeoError, GeoTarget, Geodetic, GimbalAngles,
    KeyframeStatus, LocalFrame, Params, TelemetryClock,
};
use crate::slam::MapMode;
use crate::slam::priors::{TelemetryFeed, TelemetrySample};
use crate::vehicle::{
    Attitude, GimbalAttitude, GlobalPosition, GpsRaw, HomePosition, Stamped, Telemetry,
};
use crate::video::live::{Frame, unix_now};

/// How often the keyframes are compared with the map and the alignment
/// refitted.
const SYNC_PERIOD: Duration = Duration::from_millis(500);
/// Frames in the video-delay median.
const DELAY_WINDOW: usize = 100;
/// A GPS_RAW_INT older than this says nothing about the fix of a position
/// sample (the message comes at 1 Hz by default).
pub const GPS_RAW_MAX_AGE: Duration = Duration::from_secs(3);
/// Frame pairs' ids: this bit set, the capture time in milliseconds below
/// (keyframe ids are small; a frame's capture time names it across runs).
pub const FRAME_PAIR_BIT: u64 = 1 << 63;

/// Maps the autopilot's boot time to the local (unix) clock: the offset is
/// the smallest `receive - boot` seen, i.e. the fastest delivery; a boot
/// time that goes back by more than a second (a reboot) starts over.
#[derive(Debug, Clone, Default)]
struct BootClock {
    offset_s: Option<f64>,
    last_boot_s: f64,
}

impl BootClock {
    fn local(&mut self, boot_s: f64, received_unix: f64) -> f64 {
        if boot_s + 1.0 < self.last_boot_s {
            self.offset_s = None;
        }
        self.last_boot_s = boot_s;
        let o = received_unix - boot_s;
        let offset = self.offset_s.map_or(o, |x| x.min(o));
        self.offset_s = Some(offset);
        boot_s + offset
    }
}

#[derive(Debug, Clone, Copy, Default, serde::Serialize)]
struct Counts {
    positions: u64,
    attitudes: u64,
    gimbals: u64,
    rejected_samples: u64,
    keyframes_seen: u64,
    keyframes_refused: u64,
    keyframes_moved: u64,
    keyframes_removed: u64,
    frame_pairs_added: u64,
    frame_pairs_refused: u64,
    fits: u64,
    prior_samples: u64,
    prior_samples_without_fix: u64,
}

/// What a pair's map side hangs from.
#[derive(Debug, Clone, Copy)]
struct Anchor {
    kind: PairKind,
    kf: u64,
    kf_time: f64,
    cam_from_kf: Isometry3<f64>,
}

/// The saved georeference of the previous run, while it is restored.
#[derive(Debug, Clone)]
struct Restore {
    /// The home the waiting pairs are expressed in.
    home: Geodetic,
    /// Pairs not restored yet (their keyframes not seen yet).
    waiting: Vec<SavedPair>,
    loaded: usize,
    restored: usize,
    unmatched: usize,
    saved_unix: f64,
    file_fit: Option<SavedFit>,
    /// Why the saved pairs were dropped, if they were.
    dropped: Option<String>,
    /// How far the vehicle's home is from the saved one, metres.
    home_moved_m: Option<f64>,
}

/// The saved pairs checked against live ones.
#[derive(Debug, Clone, serde::Serialize)]
#[serde(tag = "state", rename_all = "snake_case")]
enum Check {
    /// Not enough live pairs yet.
    Waiting { live_pairs: usize, needed: usize },
    /// The saved pairs alone give no fit.
    Unfitted { reason: String },
    /// The live pairs agree with the saved georeference.
    Agrees {
        live_pairs: usize,
        median_residual_m: f64,
        bound_m: f64,
    },
    /// They do not: the saved pairs were dropped.
    Disagrees {
        live_pairs: usize,
        median_residual_m: f64,
        bound_m: f64,
    },
}

struct State {
    geo: Geo,
    clock: BootClock,
    home: Option<HomePosition>,
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
    /// The latest GPS_RAW_INT and when it came.
    gps_raw: Option<(Instant, GpsRaw)>,
    /// The latest attitude (NED ← body), for the lever arm of prior samples.
    last_attitude: Option<UnitQuaternion<f64>>,
    /// The SLAM's map is in local NED (gps-aided): the georeference
    /// follows from it.
    map_aided: bool,
}

/// The georeference the daemon keeps, shared by its worker and the API.
pub struct GeoService {
    state: Mutex<State>,
    params: Params,
    /// The SLAM's telemetry priors' feed (None: priors off).
    prior_feed: Option<TelemetryFeed>,
}

fn received_unix(received: Instant) -> f64 {
    unix_now() - received.elapsed().as_secs_f64()
}

fn pose_key(p: &Isometry3<f64>) -> [f64; 7] {
    let t = p.translation.vector;
    let q = p.rotation.coords;
    [t.x, t.y, t.z, q.x, q.y, q.z, q.w]
}

impl GeoService {
    /// An empty georeference.
    pub fn new(params: Params) -> Self {
        Self {
            state: Mutex::new(State {
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
                gps_raw: None,
                last_attitude: None,
                map_aided: false,
            }),
            params,
            prior_feed: None,
        }
    }

    /// Feed the SLAM's telemetry priors with every position sample (None:
    /// priors off).
    pub fn with_prior_feed(mut self, feed: Option<TelemetryFeed>) -> Self {
        self.prior_feed = feed;
        self
    }

    /// Whether the SLAM's map is in local NED (gps-aided): the georeference
    /// then follows from the map instead of a fit (from the next sync).
    pub fn set_map_aided(&self, aided: bool) {
        let mut st = self.lock();
        if st.map_aided != aided {
            tracing::info!(
                aided,
                "geo: the map is {}",
                if aided {
                    "in local NED (gps-aided): the georeference follows from it"
                } else {
                    "vision-only: the georeference is fitted"
                }
            );
            st.map_aided = aided;
            st.force_fit = true;
        }
    }

    /// GPS_RAW_INT: the fix and accuracy the next position samples carry.
    pub fn on_gps_raw(&self, g: &Stamped<GpsRaw>) {
        self.lock().gps_raw = Some((g.received, g.value));
    }

    /// The priors' sample of a position at `t` (local NED `p_vehicle`):
    /// the camera's position, a fix and its accuracy from a recent
    /// GPS_RAW_INT. None before any attitude (the lever arm needs it).
    fn prior_sample(&self, st: &State, t: f64, p_vehicle: Vector3<f64>) -> Option<TelemetrySample> {
        let q = st.last_attitude?;
        let raw = st
            .gps_raw
            .filter(|(at, _)| at.elapsed() <= GPS_RAW_MAX_AGE)
            .and_then(|(_, r)| r.fix_accuracy());
        Some(TelemetrySample::from_position_report(
            t,
            p_vehicle,
            q,
            &self.params.mount,
            raw,
        ))
    }

    /// Takes the georeference saved by the previous run: its pairs are
    /// restored onto the continued map's keyframes as they appear (by id
    /// and capture time), or dropped when the map was not continued. A
    /// file of another format, or without pairs, is ignored (logged).
    pub fn restore(&self, saved: SavedGeoreference) {
        if saved.format != SAVED_FORMAT {
            tracing::warn!(
                format = saved.format,
                "geo: saved georeference of another format ignored"
            );
            return;
        }
        if !saved.home.is_valid() {
            tracing::warn!("geo: saved georeference with an invalid home ignored");
            return;
        }
        let mut st = self.lock();
        let n = saved.pairs.len();
        tracing::info!(
            pairs = n,
            rms_m = saved.fit.map(|f| f.rms_m),
            "geo: saved georeference loaded; its pairs wait for the map"
        );
        let mut restore = Restore {
            home: saved.home,
            waiting: saved.pairs,
            loaded: n,
            restored: 0,
            unmatched: 0,
            saved_unix: saved.saved_unix,
            file_fit: saved.fit,
            dropped: None,
            home_moved_m: None,
        };
        if let Some(h) = st.home {
            rebase_restore(&mut restore, home_geodetic(&h));
        }
        st.restore = Some(restore);
    }

    /// The georeference to save beside the map: every pair held (keyframe
    /// and frame pairs, restored or live) with its anchor, and the saved
    /// pairs still waiting for their keyframes. None before any home is
    /// known (no pair can exist then).
    pub fn saved(&self) -> Option<SavedGeoreference> {
        let st = self.lock();
        let home = st
            .home
            .map(|h| home_geodetic(&h))
            .or(st.restore.as_ref().map(|r| r.home))?;
        let mut pairs = Vec::new();
        for p in st.geo.georeference().pairs() {
            let (Some(a), Some((_, ned_rot))) = (st.anchors.get(&p.kf_id), p.orientations) else {
                continue;
            };
            pairs.push(SavedPair {
                id: p.kf_id,
                kind: a.kind,
                anchor_kf: a.kf,
                anchor_time: a.kf_time,
                cam_from_anchor: SavedPose::from_isometry(&a.cam_from_kf),
                time: p.time,
                ned_from_cam: SavedPose::from_isometry(&Isometry3::from_parts(
                    p.p_ned.coords.into(),
                    ned_rot,
                )),
                v_ned: p.v_ned.map(Into::into),
            });
        }
        if let Some(r) = &st.restore {
            pairs.extend(r.waiting.iter().copied());
        }
        let fit = match &st.fit {
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
            saved_unix: unix_now(),
            home,
            pairs,
            fit,
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    fn sample_time(&self, st: &mut State, boot_ms: Option<u32>, received: Instant) -> f64 {
        let recv = received_unix(received);
        match (self.params.history.telemetry_clock, boot_ms) {
            (TelemetryClock::Boot, Some(ms)) => st.clock.local(f64::from(ms) / 1e3, recv),
            _ => recv,
        }
    }

    /// HOME_POSITION: the origin of local NED (the first one heard; later
    /// ones that differ are ignored, since the history is in its frame).
    pub fn on_home(&self, home: &Stamped<HomePosition>) {
        let mut st = self.lock();
        if st.home.is_some() {
            return;
        }
        let h = home.value;
        let g = Geodetic {
            lat_deg: h.lat_deg,
            lon_deg: h.lon_deg,
            alt_m: h.alt_amsl_m,
        };
        match st.geo.set_home(g) {
            Ok(()) => {
                tracing::info!(
                    lat = h.lat_deg,
                    lon = h.lon_deg,
                    alt = h.alt_amsl_m,
                    "geo: home"
                );
                st.home = Some(h);
                self.carry_restored_to(&mut st, g);
            }
            Err(e) => tracing::warn!("geo: home refused: {e}"),
        }
    }

    /// The vehicle's home is `home`: saved pairs expressed at another home
    /// (waiting or already restored) are carried to it.
    fn carry_restored_to(&self, st: &mut State, home: Geodetic) {
        let Some(r) = st.restore.as_mut() else {
            return;
        };
        let from = LocalFrame::new(r.home);
        let moved = rebase_restore(r, home);
        if moved == 0.0 {
            return;
        }
        let to = LocalFrame::new(home);
        let to_from = to.ned_from_other(&from);
        let ids: Vec<u64> = st.restored.iter().copied().collect();
        for id in ids {
            let Some(p) = st
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
            if let Err(e) = st.geo.add_known(id, &map_from_cam, &ned, v, p.time) {
                tracing::warn!(
                    pair = id,
                    "geo: restored pair not carried to the new home: {e}"
                );
            }
        }
        st.force_fit = true;
        tracing::info!(
            moved_m = moved,
            "geo: the vehicle's home differs from the saved one; saved pairs carried to it"
        );
    }

    /// GLOBAL_POSITION_INT (needs home).
    pub fn on_position(&self, p: &Stamped<GlobalPosition>) {
        let mut st = self.lock();
        if st.home.is_none() {
            return;
        }
        let t = self.sample_time(&mut st, Some(p.value.time_boot_ms), p.received);
        let g = Geodetic {
            lat_deg: p.value.lat_deg,
            lon_deg: p.value.lon_deg,
            alt_m: p.value.alt_amsl_m,
        };
        match st.geo.push_position_geodetic(t, &g) {
            Ok(()) => st.counts.positions += 1,
            Err(_) => {
                st.counts.rejected_samples += 1;
                return;
            }
        }
        if let Some(feed) = &self.prior_feed {
            let ned = st.geo.frame().map(|f| f.geodetic_to_ned(&g));
            if let Some(sample) = ned.and_then(|p| self.prior_sample(&st, t, p))
                && feed.push(sample)
            {
                st.counts.prior_samples += 1;
                if !sample.fix {
                    st.counts.prior_samples_without_fix += 1;
                }
            }
        }
    }

    /// ATTITUDE.
    pub fn on_attitude(&self, a: &Stamped<Attitude>) {
        let mut st = self.lock();
        let t = self.sample_time(&mut st, Some(a.value.time_boot_ms), a.received);
        let v = a.value;
        st.last_heading_rad = Some(f64::from(v.yaw_rad));
        st.last_attitude = Some(UnitQuaternion::from_euler_angles(
            f64::from(v.roll_rad),
            f64::from(v.pitch_rad),
            f64::from(v.yaw_rad),
        ));
        match st.geo.history_mut().push_attitude_euler(
            t,
            f64::from(v.roll_rad),
            f64::from(v.pitch_rad),
            f64::from(v.yaw_rad),
        ) {
            Ok(()) => st.counts.attitudes += 1,
            Err(_) => st.counts.rejected_samples += 1,
        }
    }

    /// Gimbal attitude (yaw relative to the body; an earth-frame yaw is
    /// made relative with the latest heading).
    pub fn on_gimbal(&self, g: &Stamped<GimbalAttitude>) {
        let mut st = self.lock();
        let t = self.sample_time(&mut st, g.value.time_boot_ms, g.received);
        let mut yaw = f64::from(g.value.yaw_deg).to_radians();
        if g.value.yaw_absolute {
            let Some(h) = st.last_heading_rad else {
                st.counts.rejected_samples += 1;
                return;
            };
            yaw -= h;
        }
        let angles = GimbalAngles {
            pitch: f64::from(g.value.pitch_deg).to_radians(),
            yaw: crate::geo::telemetry::wrap_pi(yaw),
        };
        match st.geo.history_mut().push_gimbal(t, angles) {
            Ok(()) => st.counts.gimbals += 1,
            Err(_) => st.counts.rejected_samples += 1,
        }
    }

    /// A video frame taken by the SLAM: records the sender's delay (receive
    /// time minus `X-Timestamp`) when the frame is stamped.
    pub fn note_frame(&self, frame: &Frame) {
        if let Some(c) = frame.capture_time {
            let d = (frame.received_unix - c) * 1e3;
            if d.is_finite() {
                let mut st = self.lock();
                if st.video_delay_ms.len() == DELAY_WINDOW {
                    st.video_delay_ms.pop_front();
                }
                st.video_delay_ms.push_back(d);
                st.video_delay_sum_ms.0 += d;
                st.video_delay_sum_ms.1 += 1;
            }
        }
    }

    /// Compares the SLAM's keyframes with those fed before (see
    /// [`Self::sync`]), without a tracked frame or a decision about the
    /// saved georeference.
    pub fn sync_keyframes(&self, keyframes: &[KeyframeInfo]) {
        self.sync(keyframes, None, None);
    }

    /// One round of the worker: the saved pairs are restored onto the
    /// keyframes once the map is known to be continued (`continued`:
    /// Some(true); Some(false) drops them; None waits); new keyframes are
    /// paired with telemetry (or wait for it), moved ones take their new map
    /// pose (and so do the frame pairs hung on them), culled ones are
    /// forgotten; `frame` becomes a frame pair when the last one is old
    /// enough; the waiting pairs are retried; the saved pairs are checked
    /// against the live ones; and the alignment is refitted when anything
    /// changed.
    pub fn sync(
        &self,
        keyframes: &[KeyframeInfo],
        frame: Option<TrackedFrame>,
        continued: Option<bool>,
    ) {
        let mut st = self.lock();
        let st = &mut *st;
        let cp = &self.params.continuity;
        let mut changed = std::mem::take(&mut st.force_fit);
        let poses: HashMap<u64, (f64, Isometry3<f64>)> = keyframes
            .iter()
            .filter_map(|k| Some((k.id, (k.timestamp, k.world_from_cam.to_isometry()?))))
            .collect();
        changed |= restore_pairs(st, &poses, continued);
        let mut seen = HashSet::with_capacity(keyframes.len());
        let mut moved_kfs = HashSet::new();
        for kf in keyframes {
            seen.insert(kf.id);
            let Some(pose) = kf.world_from_cam.to_isometry() else {
                continue;
            };
            let key = pose_key(&pose);
            match st.fed.get(&kf.id) {
                None => {
                    st.counts.keyframes_seen += 1;
                    match st.geo.add_keyframe(kf.id, &pose, kf.timestamp) {
                        Ok(status) => {
                            changed |= status == KeyframeStatus::Paired;
                            st.anchors.insert(
                                kf.id,
                                Anchor {
                                    kind: PairKind::Keyframe,
                                    kf: kf.id,
                                    kf_time: kf.timestamp,
                                    cam_from_kf: Isometry3::identity(),
                                },
                            );
                        }
                        Err(e) => {
                            st.counts.keyframes_refused += 1;
                            tracing::debug!(kf = kf.id, "geo: keyframe refused: {e}");
                        }
                    }
                    st.fed.insert(kf.id, key);
                }
                Some(old) if old != &key => {
                    moved_kfs.insert(kf.id);
                    if matches!(st.geo.refresh_keyframe(kf.id, &pose), Ok(true)) {
                        st.counts.keyframes_moved += 1;
                        changed = true;
                    }
                    st.fed.insert(kf.id, key);
                }
                Some(_) => {}
            }
        }
        let gone: Vec<u64> = st
            .fed
            .keys()
            .filter(|id| !seen.contains(id))
            .copied()
            .collect();
        for id in gone {
            st.fed.remove(&id);
            if st.geo.remove_keyframe(id) {
                st.counts.keyframes_removed += 1;
                changed = true;
            }
        }
        // Frame pairs follow their keyframe, or go with it.
        let frames: Vec<(u64, Anchor)> = st
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
                        changed |= matches!(st.geo.refresh_keyframe(id, &pose), Ok(true));
                    }
                }
                _ if poses.is_empty() => {}
                _ => {
                    changed |= st.geo.remove_keyframe(id);
                    st.anchors.remove(&id);
                    st.restored.remove(&id);
                }
            }
        }
        if let Some(f) = frame {
            changed |= add_frame_pair(st, cp, &poses, &f);
        }
        if st.geo.retry_pending() > 0 {
            changed = true;
        }
        // Anchors of pairs the georeference dropped (their telemetry never
        // came) go too.
        if st.anchors.len() > st.geo.georeference().pairs().len() + st.geo.pending() {
            let geo = &st.geo;
            st.anchors.retain(|id, _| geo.knows_keyframe(*id));
            st.frame_pairs.retain(|id| geo.knows_keyframe(*id));
        }
        if changed && !st.restored.is_empty() {
            check_restored(st, &self.params);
        }
        if st.map_aided {
            if changed || st.fit.is_none() {
                st.fit = Some(Ok(GeoAlignment::of_map_in_ned(
                    st.geo.georeference().pairs(),
                )));
                st.fitted_at = Some(Instant::now());
            }
        } else if changed || st.fit.is_none() && st.geo.georeference().pairs().len() >= 3 {
            let r = st.geo.fit();
            st.counts.fits += 1;
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
            st.fit = Some(r);
            st.fitted_at = Some(Instant::now());
        }
    }

    /// The vehicle target that puts the camera at `map_from_cam` (a camera
    /// pose in the SLAM map), with the alignment it went through.
    pub fn target(
        &self,
        map_from_cam: &Isometry3<f64>,
    ) -> Result<(GeoTarget, GeoAlignment), GeoError> {
        let mut st = self.lock();
        if st.map_aided {
            let frame = *st.geo.frame().ok_or(GeoError::NoHome)?;
            let alignment = GeoAlignment::of_map_in_ned(st.geo.georeference().pairs());
            let target =
                crate::geo::convert_target(&alignment, map_from_cam, &frame, &self.params.mount)?;
            return Ok((target, alignment));
        }
        let target = st.geo.target(map_from_cam)?;
        let alignment = st.geo.fit()?;
        Ok((target, alignment))
    }

    /// Home, once known.
    pub fn home(&self) -> Option<HomePosition> {
        self.lock().home
    }

    /// The state as the API reports it: `ok` with the fit's scale,
    /// residual and keyframes used, `refused` with the reason (too little
    /// motion, too few pairs, ...), or `waiting` before any fit.
    pub fn status(&self) -> Value {
        let st = self.lock();
        let georef = st.geo.georeference();
        let delays: Vec<f64> = st.video_delay_ms.iter().copied().collect();
        let (positions, attitudes, gimbals) = st.geo.history().len();
        let mut v = json!({
            "home": st.home.map(|h| json!({
                "lat_deg": h.lat_deg, "lon_deg": h.lon_deg, "alt_amsl_m": h.alt_amsl_m,
            })),
            "pairs": georef.pairs().len(),
            "keyframes_pending": st.geo.pending(),
            "keyframes_dropped": st.geo.dropped(),
            "history": {"positions": positions, "attitudes": attitudes, "gimbals": gimbals},
            "counts": st.counts,
            "clock": {
                "telemetry": self.params.history.telemetry_clock,
                "boot_offset_unix_s": st.clock.offset_s,
                "use_frame_timestamps": self.params.history.use_frame_timestamps,
                "video_latency_s": self.params.history.video_latency_s,
                "video_delay_ms_median": crate::stats::median(&delays),
                "video_delay_ms_mean_all": (st.video_delay_sum_ms.1 > 0)
                    .then(|| st.video_delay_sum_ms.0 / st.video_delay_sum_ms.1 as f64),
            },
            "fit_age_s": st.fitted_at.map(|t| t.elapsed().as_secs_f64()),
            "evidence": {
                "restored_pairs": st.restored.len(),
                "frame_pairs": st.frame_pairs.len(),
                "live_keyframe_pairs": georef.pairs().iter().filter(|p| {
                    p.kf_id & FRAME_PAIR_BIT == 0 && !st.restored.contains(&p.kf_id)
                }).count(),
            },
            "saved": st.restore.as_ref().map(|r| json!({
                "pairs_in_file": r.loaded,
                "restored": r.restored,
                "waiting": r.waiting.len(),
                "unmatched": r.unmatched,
                "saved_unix": r.saved_unix,
                "fit_when_saved": r.file_fit,
                "home_moved_m": r.home_moved_m,
                "dropped": r.dropped,
                "check": st.check,
            })),
        });
        let fit = match &st.fit {
            None => json!({"state": "waiting", "reason": if st.home.is_none() {
                "no home position yet".to_string()
            } else {
                format!("{} keyframe pairs so far", georef.pairs().len())
            }}),
            Some(Err(e)) => {
                let dropped = st.restore.as_ref().and_then(|r| r.dropped.as_deref());
                let reason = match dropped {
                    Some(d) => format!("{e} (the saved georeference was dropped: {d})"),
                    None => e.to_string(),
                };
                json!({"state": "refused", "reason": reason, "error": format!("{e:?}")})
            }
            Some(Ok(a)) => {
                let q = &a.quality;
                let r = a.ned_from_map.rotation.coords;
                let t = a.ned_from_map.translation;
                json!({
                    "state": "ok",
                    "source": if st.map_aided { "map" } else { "fit" },
                    "held": georef.held().filter(|_| !st.map_aided).map(|e| format!(
                        "the last fit is kept: a refit now is refused ({e}) and the {} pairs held agree with it",
                        georef.pairs().len()
                    )),
                    "scale": a.ned_from_map.scale,
                    "rms_m": q.rms_m,
                    "max_residual_m": q.max_residual_m,
                    "rotation_rms_deg": q.rotation_rms_deg,
                    "time_offset_s": q.time_offset_s,
                    "keyframes_used": q.inliers,
                    "spread_m": q.spread_m2.map(f64::sqrt),
                    "ned_from_map": {
                        "scale": a.ned_from_map.scale,
                        "rotation_xyzw": [r.x, r.y, r.z, r.w],
                        "translation": [t.x, t.y, t.z],
                    },
                })
            }
        };
        if let (Value::Object(m), Value::Object(f)) = (&mut v, fit) {
            m.extend(f);
        }
        v
    }

    /// The worker: takes every telemetry sample the link publishes and,
    /// every half second, the SLAM's keyframes; stops with `cancel` or when
    /// the link actor is gone.
    pub async fn run(
        self: Arc<Self>,
        telemetry: Telemetry,
        slam: Arc<dyn SlamView>,
        cancel: CancellationToken,
    ) {
        let Telemetry {
            global_position: mut gp,
            attitude: mut att,
            gimbal: mut gim,
            mut home,
            mut gps_raw,
            ..
        } = telemetry;
        let mut tick = tokio::time::interval(SYNC_PERIOD);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        loop {
            tokio::select! {
                _ = cancel.cancelled() => break,
                r = gp.changed() => {
                    if r.is_err() { break; }
                    let v = *gp.borrow_and_update();
                    if let Some(v) = v { self.on_position(&v); }
                }
                r = att.changed() => {
                    if r.is_err() { break; }
                    let v = *att.borrow_and_update();
                    if let Some(v) = v { self.on_attitude(&v); }
                }
                r = gim.changed() => {
                    if r.is_err() { break; }
                    let v = *gim.borrow_and_update();
                    if let Some(v) = v { self.on_gimbal(&v); }
                }
                r = gps_raw.changed() => {
                    if r.is_err() { break; }
                    let v = *gps_raw.borrow_and_update();
                    if let Some(v) = v { self.on_gps_raw(&v); }
                }
                r = home.changed() => {
                    if r.is_err() { break; }
                    let v = *home.borrow_and_update();
                    if let Some(v) = v { self.on_home(&v); }
                }
                _ = tick.tick() => {
                    let (me, slam) = (self.clone(), slam.clone());
                    let _ = tokio::task::spawn_blocking(move || {
                        let status = slam.status();
                        me.set_map_aided(status.map_mode == MapMode::GpsAided.name());
                        let continued = status.map_start.map(|m| m.mode == "continued");
                        me.sync(&slam.keyframes(), slam.last_tracked(), continued);
                    })
                    .await;
                }
            }
        }
    }
}

fn home_geodetic(h: &HomePosition) -> Geodetic {
    Geodetic {
        lat_deg: h.lat_deg,
        lon_deg: h.lon_deg,
        alt_m: h.alt_amsl_m,
    }
}

/// Carries the waiting saved pairs to `home`; returns how far it moved,
/// metres (0 when it is the same home).
fn rebase_restore(r: &mut Restore, home: Geodetic) -> f64 {
    let from = LocalFrame::new(r.home);
    let to = LocalFrame::new(home);
    let moved = to.geodetic_to_ned(&r.home).norm();
    r.home_moved_m = Some(moved);
    if moved < 1e-3 {
        return 0.0;
    }
    r.waiting = r
        .waiting
        .iter()
        .filter_map(|p| p.rebased(&from, &to))
        .collect();
    r.home = home;
    moved
}

/// Restores the waiting saved pairs whose keyframes are in `poses` (once
/// the map is known to be continued); returns whether any was added.
fn restore_pairs(
    st: &mut State,
    poses: &HashMap<u64, (f64, Isometry3<f64>)>,
    continued: Option<bool>,
) -> bool {
    let Some(r) = st.restore.as_mut() else {
        return false;
    };
    if r.waiting.is_empty() {
        return false;
    }
    match continued {
        Some(false) => {
            tracing::info!(
                pairs = r.waiting.len(),
                "geo: the saved map was not continued; its saved georeference is dropped"
            );
            r.unmatched += r.waiting.len();
            r.waiting.clear();
            r.dropped = Some("the saved map was not continued".into());
            return false;
        }
        None => return false,
        Some(true) if poses.is_empty() => return false,
        Some(true) => {}
    }
    let waiting = std::mem::take(&mut r.waiting);
    let mut added = 0;
    let mut unmatched = 0;
    for p in waiting {
        let placed = poses
            .get(&p.anchor_kf)
            .filter(|(t, _)| *t == p.anchor_time)
            .and_then(|(_, world_from_kf)| p.map_from_cam(&world_from_kf.inverse()));
        let ned = p.ned_from_cam.to_isometry();
        let (Some(map_from_cam), Some(ned)) = (placed, ned) else {
            unmatched += 1;
            continue;
        };
        let v = p.v_ned.map(nalgebra::Vector3::from);
        if st
            .geo
            .add_known(p.id, &map_from_cam, &ned, v, p.time)
            .is_err()
        {
            unmatched += 1;
            continue;
        }
        let cam_from_kf = p
            .cam_from_anchor
            .to_isometry()
            .unwrap_or_else(Isometry3::identity);
        st.anchors.insert(
            p.id,
            Anchor {
                kind: p.kind,
                kf: p.anchor_kf,
                kf_time: p.anchor_time,
                cam_from_kf,
            },
        );
        st.restored.insert(p.id);
        if p.kind == PairKind::Keyframe {
            st.fed.insert(p.anchor_kf, pose_key(&map_from_cam));
        }
        added += 1;
    }
    if let Some(r) = st.restore.as_mut() {
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

/// Pairs the tracked frame `f` with telemetry when the last frame pair is
/// old enough; the oldest frame pairs go beyond the limit. Returns whether
/// a pair was added or removed.
fn add_frame_pair(
    st: &mut State,
    cp: &ContinuityParams,
    poses: &HashMap<u64, (f64, Isometry3<f64>)>,
    f: &TrackedFrame,
) -> bool {
    if !(cp.frame_pair_spacing_s > 0.0 && cp.max_frame_pairs > 0 && f.timestamp.is_finite())
        || f.timestamp < st.last_frame_pair_t + cp.frame_pair_spacing_s
    {
        return false;
    }
    let Some((kf_time, world_from_kf)) = poses.get(&f.reference_kf) else {
        return false;
    };
    let id = FRAME_PAIR_BIT | ((f.timestamp * 1e3).round().max(0.0) as u64 & !FRAME_PAIR_BIT);
    if st.geo.knows_keyframe(id) {
        return false;
    }
    let map_from_cam = (f.cam_from_ref * world_from_kf.inverse()).inverse();
    st.last_frame_pair_t = f.timestamp;
    let mut changed = false;
    match st.geo.add_keyframe(id, &map_from_cam, f.timestamp) {
        Ok(status) => {
            st.counts.frame_pairs_added += 1;
            changed |= status == KeyframeStatus::Paired;
            st.anchors.insert(
                id,
                Anchor {
                    kind: PairKind::Frame,
                    kf: f.reference_kf,
                    kf_time: *kf_time,
                    cam_from_kf: f.cam_from_ref,
                },
            );
            st.frame_pairs.push_back(id);
        }
        Err(e) => {
            st.counts.frame_pairs_refused += 1;
            tracing::debug!(frame = f.seq, "geo: frame pair refused: {e}");
        }
    }
    while st.frame_pairs.len() > cp.max_frame_pairs {
        if let Some(old) = st.frame_pairs.pop_front() {
            changed |= st.geo.remove_keyframe(old);
            st.anchors.remove(&old);
        }
    }
    changed
}

/// Checks the restored pairs against the live ones (see the module
/// documentation); drops the restored pairs when they disagree.
fn check_restored(st: &mut State, params: &Params) {
    let cp = &params.continuity;
    let (old, live): (Vec<_>, Vec<_>) = st
        .geo
        .georeference()
        .pairs()
        .iter()
        .copied()
        .partition(|p| st.restored.contains(&p.kf_id));
    if old.is_empty() {
        return;
    }
    if live.len() < cp.min_live_pairs.max(1) {
        st.check = Some(Check::Waiting {
            live_pairs: live.len(),
            needed: cp.min_live_pairs.max(1),
        });
        return;
    }
    let fit = match fit_pairs(&old, &params.align, None, params.align.seed) {
        Ok(f) => f,
        Err(e) => {
            st.check = Some(Check::Unfitted {
                reason: e.to_string(),
            });
            return;
        }
    };
    let residuals: Vec<f64> = live
        .iter()
        .map(|p| (fit.ned_from_map.transform_point(&p.p_map) - p.p_ned).norm())
        .collect();
    let Some(median) = crate::stats::median(&residuals) else {
        return;
    };
    let bound = (cp.disagreement_factor * fit.quality.rms_m).max(params.align.inlier_threshold_m);
    if median <= bound {
        st.check = Some(Check::Agrees {
            live_pairs: live.len(),
            median_residual_m: median,
            bound_m: bound,
        });
        return;
    }
    let why = format!(
        "the live pairs are {median:.2} m from it (median of {}), more than {bound:.2} m",
        live.len()
    );
    tracing::warn!(
        median_residual_m = median,
        bound_m = bound,
        live_pairs = live.len(),
        "geo: the saved georeference disagrees with live telemetry: dropped, refitting from live pairs"
    );
    let ids: Vec<u64> = st.restored.drain().collect();
    for id in ids {
        st.geo.remove_keyframe(id);
        st.anchors.remove(&id);
    }
    if let Some(r) = st.restore.as_mut() {
        r.dropped = Some(why);
        r.waiting.clear();
    }
    st.check = Some(Check::Disagrees {
        live_pairs: live.len(),
        median_residual_m: median,
        bound_m: bound,
    });
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::{LocalFrame, MountParams, ned_from_cam};
    use crate::geometry::Sim3;
    use crate::shot::record::PoseJson;
    use nalgebra::{Point3, UnitQuaternion, Vector3};

    const HOME: Geodetic = Geodetic {
        lat_deg: 47.3977,
        lon_deg: 8.5456,
        alt_m: 488.0,
    };
    const T_END: f64 = 40.0;

    /// The L-shaped flight's NED position at `t`: north, then east, at 10 m.
    fn path(t: f64) -> Vector3<f64> {
        if t < 20.0 {
            Vector3::new(t, 0.0, -10.0)
        } else {
            Vector3::new(20.0, t - 20.0, -10.0)
        }
    }

    /// Feeds home and 40 s of telemetry of the L-shaped flight (facing
    /// north, camera 30 deg down) on the boot clock, ending now; with
    /// `telemetry` false only home. Returns the boot clock's offset.
    fn feed_flight(geo: &GeoService, telemetry: bool) -> f64 {
        let frame = LocalFrame::new(HOME);
        let at = |t: f64| {
            Instant::now()
                .checked_sub(Duration::from_secs_f64(T_END - t + 0.02))
                .unwrap_or_else(Instant::now)
        };
        geo.on_home(&Stamped {
            value: HomePosition {
                lat_deg: HOME.lat_deg,
                lon_deg: HOME.lon_deg,
                alt_amsl_m: HOME.alt_m,
            },
            received: at(0.0),
        });
        if !telemetry {
            return 0.0;
        }
        for i in 0..=400 {
            let t = i as f64 * 0.1;
            let g = frame.ned_to_geodetic(&path(t));
            let ms = (t * 1e3).round() as u32;
            geo.on_position(&Stamped {
                value: GlobalPosition {
                    time_boot_ms: ms,
                    lat_deg: g.lat_deg,
                    lon_deg: g.lon_deg,
                    alt_amsl_m: g.alt_m,
                    rel_alt_m: 10.0,
                    vel_ned_m_s: [0.0; 3],
                    heading_deg: Some(0.0),
                },
                received: at(t),
            });
            geo.on_attitude(&Stamped {
                value: Attitude {
                    time_boot_ms: ms,
                    roll_rad: 0.0,
                    pitch_rad: 0.0,
                    yaw_rad: 0.0,
                },
                received: at(t),
            });
            geo.on_gimbal(&Stamped {
                value: GimbalAttitude {
                    roll_deg: 0.0,
                    pitch_deg: -30.0,
                    yaw_deg: 0.0,
                    yaw_absolute: false,
                    time_boot_ms: Some(ms),
                },
                received: at(t),
            });
        }
        geo.lock().clock.offset_s.unwrap()
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
    /// in the map from `telemetry`'s history.
    fn keyframe(telemetry: &GeoService, id: u64, t: f64, offset: f64) -> KeyframeInfo {
        let state = telemetry.lock().geo.history().lookup(t + offset).unwrap();
        let ned = ned_from_cam(&state, &MountParams::default());
        let m = map_from_ned();
        let p = m.transform_point(&Point3::from(ned.translation.vector));
        KeyframeInfo {
            id,
            timestamp: t + offset,
            world_from_cam: PoseJson::from_isometry(&Isometry3::from_parts(
                p.coords.into(),
                m.rotation * ned.rotation,
            )),
            width: 640,
            height: 480,
        }
    }

    /// An L-shaped flight at 10 m, facing north with the camera 30 deg
    /// down: telemetry on the boot clock, keyframes in a map that is NED
    /// through a known similarity. Refused while the motion is a line, then
    /// fitted with the map's scale; a keyframe culled is forgotten.
    #[test]
    fn telemetry_and_keyframes_give_the_maps_similarity() {
        let geo = GeoService::new(Params::default());
        let offset = feed_flight(&geo, true);
        // The first leg only: a line.
        let mut kfs: Vec<KeyframeInfo> = (0..8)
            .map(|i| keyframe(&geo, i, 1.0 + 2.0 * i as f64, offset))
            .collect();
        geo.sync_keyframes(&kfs);
        let s = geo.status();
        assert_eq!(s["state"], "refused", "{s}");
        assert!(s["reason"].as_str().unwrap().contains("line"), "{s}");
        // Round the corner.
        kfs.extend((8..16).map(|i| keyframe(&geo, i, 1.0 + 2.0 * i as f64, offset)));
        geo.sync_keyframes(&kfs);
        let s = geo.status();
        assert_eq!(s["state"], "ok", "{s}");
        let scale = s["scale"].as_f64().unwrap();
        assert!((scale * 0.08 - 1.0).abs() < 1e-3, "{s}");
        assert!(s["rms_m"].as_f64().unwrap() < 0.02, "{s}");
        assert_eq!(s["keyframes_used"], 16);
        // A target at a keyframe's pose is that keyframe's camera.
        let kf = &kfs[12];
        let (target, _) = geo
            .target(&kf.world_from_cam.to_isometry().unwrap())
            .unwrap();
        assert!((target.gimbal_pitch_deg + 30.0).abs() < 0.05, "{target:?}");
        assert!(
            target.yaw_deg < 0.05 || target.yaw_deg > 359.95,
            "{target:?}"
        );
        let p = path(kf.timestamp - offset);
        assert!((target.p_ned_vehicle - p).norm() < 0.02, "{target:?}");
        // Culled keyframes are forgotten.
        kfs.truncate(12);
        geo.sync_keyframes(&kfs);
        assert_eq!(geo.status()["pairs"], 12);
    }

    /// Keyframes already in NED (a gps-aided map: the map is NED itself).
    fn ned_keyframe(telemetry: &GeoService, id: u64, t: f64, offset: f64) -> KeyframeInfo {
        let state = telemetry.lock().geo.history().lookup(t + offset).unwrap();
        let ned = ned_from_cam(&state, &MountParams::default());
        KeyframeInfo {
            id,
            timestamp: t + offset,
            world_from_cam: PoseJson::from_isometry(&ned),
            width: 640,
            height: 480,
        }
    }

    /// With priors, every position becomes a sample of the feed: the
    /// camera's NED position (lever arm included), a fix with the
    /// accuracy of a recent GPS_RAW_INT, none without one or with a
    /// GPS_RAW_INT reporting no fix. A gps-aided map's georeference is the
    /// identity, from the map (`source` `map`), its targets through it.
    #[test]
    fn priors_get_the_links_samples_and_an_aided_map_is_its_own_georeference() {
        let feed = TelemetryFeed::live(1800.0);
        let geo = GeoService::new(Params::default()).with_prior_feed(Some(feed.clone()));
        // No GPS_RAW_INT yet: samples without a fix.
        let offset = feed_flight(&geo, true);
        assert!(feed.len() > 300, "{}", feed.len());
        let s = feed.newest().unwrap();
        assert!(!s.fix);
        // The camera's position: the vehicle's plus the lever arm (facing
        // north, so the arm's forward component goes north).
        let arm = MountParams::default().lever_arm_body_m;
        let expect = path(T_END) + Vector3::new(arm[0], arm[1], arm[2]);
        assert!((s.gps_ned - expect).norm() < 1e-3, "{:?}", s.gps_ned);
        assert!((s.t - (T_END + offset)).abs() < 1e-6);
        // A 3D fix with its accuracy.
        let raw = |fix_type: u8| Stamped {
            value: GpsRaw {
                time_usec: 0,
                fix_type,
                satellites: Some(12),
                h_acc_m: Some(1.3),
                v_acc_m: None,
            },
            received: Instant::now(),
        };
        let feed2 = TelemetryFeed::live(1800.0);
        let geo2 = GeoService::new(Params::default()).with_prior_feed(Some(feed2.clone()));
        geo2.on_gps_raw(&raw(3));
        feed_flight(&geo2, true);
        let s = feed2.newest().unwrap();
        assert!(s.fix && s.h_acc == 1.3 && s.v_acc == 2.6, "{s:?}");
        let feed3 = TelemetryFeed::live(1800.0);
        let geo3 = GeoService::new(Params::default()).with_prior_feed(Some(feed3.clone()));
        geo3.on_gps_raw(&raw(1));
        feed_flight(&geo3, true);
        assert!(!feed3.newest().unwrap().fix);

        // The map in NED: the identity, no fit.
        geo.set_map_aided(true);
        let kfs: Vec<KeyframeInfo> = (0..16)
            .map(|i| ned_keyframe(&geo, i, 1.0 + 2.0 * i as f64, offset))
            .collect();
        geo.sync_keyframes(&kfs);
        let st = geo.status();
        assert_eq!(st["state"], "ok", "{st}");
        assert_eq!(st["source"], "map", "{st}");
        assert_eq!(st["scale"], 1.0);
        assert_eq!(st["keyframes_used"], 16);
        assert!(st["rms_m"].as_f64().unwrap() < 1e-3, "{st}");
        let kf = &kfs[12];
        let (target, alignment) = geo
            .target(&kf.world_from_cam.to_isometry().unwrap())
            .unwrap();
        assert_eq!(alignment.ned_from_map.scale, 1.0);
        let p = path(kf.timestamp - offset);
        assert!((target.p_ned_vehicle - p).norm() < 0.02, "{target:?}");
        // Back to vision-only: fitted again.
        geo.set_map_aided(false);
        geo.sync_keyframes(&kfs);
        let st = geo.status();
        assert_eq!(st["source"], "fit", "{st}");
    }

    /// A restart: the saved pairs (through their JSON file) put the
    /// continued map's keyframes in NED with no telemetry at all, the
    /// target of a keyframe's pose is the same as before; not before the
    /// map is known to be continued, and not at all when it was not.
    #[test]
    fn a_saved_georeference_is_restored_onto_the_continued_map() {
        let before = GeoService::new(Params::default());
        let offset = feed_flight(&before, true);
        let kfs: Vec<KeyframeInfo> = (0..16)
            .map(|i| keyframe(&before, i, 1.0 + 2.0 * i as f64, offset))
            .collect();
        before.sync_keyframes(&kfs);
        assert_eq!(before.status()["state"], "ok");
        let pose = kfs[12].world_from_cam.to_isometry().unwrap();
        let (t_before, _) = before.target(&pose).unwrap();
        let saved = before.saved().unwrap();
        assert_eq!(saved.pairs.len(), 16);
        let text = serde_json::to_vec(&saved).unwrap();
        let file: SavedGeoreference = serde_json::from_slice(&text).unwrap();

        let after = GeoService::new(Params::default());
        after.restore(file.clone());
        feed_flight(&after, false);
        after.sync(&kfs, None, None);
        assert_eq!(
            after.status()["state"],
            "waiting",
            "not before the map is known"
        );
        after.sync(&kfs, None, Some(true));
        let s = after.status();
        assert_eq!(s["state"], "ok", "{s}");
        assert_eq!(s["evidence"]["restored_pairs"], 16, "{s}");
        assert!(s["rms_m"].as_f64().unwrap() < 0.02, "{s}");
        let (t_after, _) = after.target(&pose).unwrap();
        assert!((t_after.p_ned_vehicle - t_before.p_ned_vehicle).norm() < 1e-3);
        // Saved again: the same pairs.
        assert_eq!(after.saved().unwrap().pairs.len(), 16);

        let fresh = GeoService::new(Params::default());
        fresh.restore(file);
        feed_flight(&fresh, false);
        fresh.sync(&kfs, None, Some(false));
        let s = fresh.status();
        assert_ne!(s["state"], "ok", "{s}");
        assert_eq!(s["evidence"]["restored_pairs"], 0, "{s}");
    }

    /// A saved georeference that live telemetry contradicts (its NED side
    /// 5 m off, as a GPS glitch at the last session would leave it) is
    /// dropped once enough live pairs are in, and the fit is made from
    /// the live pairs alone; one that agrees is kept.
    #[test]
    fn a_saved_georeference_that_live_pairs_contradict_is_dropped() {
        let before = GeoService::new(Params::default());
        let offset = feed_flight(&before, true);
        let old: Vec<KeyframeInfo> = (0..16)
            .map(|i| keyframe(&before, i, 1.0 + 2.0 * i as f64, offset))
            .collect();
        before.sync_keyframes(&old);
        let good = before.saved().unwrap();
        let mut bad = good.clone();
        for p in &mut bad.pairs {
            p.ned_from_cam.translation[0] += 5.0;
        }
        for (file, agrees) in [(good, true), (bad, false)] {
            let after = GeoService::new(Params::default());
            after.restore(file);
            let offset = feed_flight(&after, true);
            // New keyframes of this run, paired with live telemetry.
            let mut kfs = old.clone();
            kfs.extend((0..10).map(|i| keyframe(&after, 100 + i, 2.0 + 3.8 * i as f64, offset)));
            after.sync(&kfs, None, Some(true));
            let s = after.status();
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

    #[test]
    fn boot_clock_takes_the_fastest_delivery_and_restarts_on_reboot() {
        let mut c = BootClock::default();
        assert_eq!(c.local(10.0, 1010.3), 10.0 + 1000.3);
        assert!((c.local(11.0, 1011.1) - 1011.1).abs() < 1e-9);
        // A slower delivery keeps the offset of 1000.1.
        assert!((c.local(12.0, 1012.5) - 1012.1).abs() < 1e-9);
        // Reboot: boot time restarts, offset is measured anew.
        assert!((c.local(1.0, 2000.2) - 2000.2).abs() < 1e-9);
    }
}
