//! The daemon's georeference: telemetry from the link actor and keyframes
//! from the SLAM feed one [`Geo`]; the map → NED alignment is refitted as
//! keyframes arrive, move (bundle adjustment) or go (culling); the API reads
//! its state and turns a localised shot's camera pose into a vehicle target.
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

use nalgebra::Isometry3;
use serde_json::{Value, json};
use tokio_util::sync::CancellationToken;

use crate::api::{KeyframeInfo, SlamView};
use crate::geo::{
    Geo, GeoAlignment, GeoError, GeoTarget, Geodetic, GimbalAngles, KeyframeStatus, Params,
    TelemetryClock,
};
use crate::vehicle::{Attitude, GimbalAttitude, GlobalPosition, HomePosition, Stamped, Telemetry};
use crate::video::live::{Frame, unix_now};

/// How often the keyframes are compared with the map and the alignment
/// refitted.
const SYNC_PERIOD: Duration = Duration::from_millis(500);
/// Frames in the video-delay median.
const DELAY_WINDOW: usize = 100;

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
    fits: u64,
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
}

/// The georeference the daemon keeps, shared by its worker and the API.
pub struct GeoService {
    state: Mutex<State>,
    params: Params,
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
            }),
            params,
        }
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
            }
            Err(e) => tracing::warn!("geo: home refused: {e}"),
        }
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
            Err(_) => st.counts.rejected_samples += 1,
        }
    }

    /// ATTITUDE.
    pub fn on_attitude(&self, a: &Stamped<Attitude>) {
        let mut st = self.lock();
        let t = self.sample_time(&mut st, Some(a.value.time_boot_ms), a.received);
        let v = a.value;
        st.last_heading_rad = Some(f64::from(v.yaw_rad));
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

    /// Compares the SLAM's keyframes with those fed before: new ones are
    /// paired with telemetry (or wait for it), moved ones take their new
    /// map pose, culled ones are forgotten; then the waiting ones are
    /// retried and the alignment refitted when anything changed.
    pub fn sync_keyframes(&self, keyframes: &[KeyframeInfo]) {
        let mut st = self.lock();
        let st = &mut *st;
        let mut changed = false;
        let mut seen = HashSet::with_capacity(keyframes.len());
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
                        Ok(KeyframeStatus::Paired) => changed = true,
                        Ok(KeyframeStatus::Pending) => {}
                        Err(e) => {
                            st.counts.keyframes_refused += 1;
                            tracing::debug!(kf = kf.id, "geo: keyframe refused: {e}");
                        }
                    }
                    st.fed.insert(kf.id, key);
                }
                Some(old) if old != &key => {
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
        if st.geo.retry_pending() > 0 {
            changed = true;
        }
        if changed || st.fit.is_none() && st.geo.georeference().pairs().len() >= 3 {
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
        });
        let fit = match &st.fit {
            None => json!({"state": "waiting", "reason": if st.home.is_none() {
                "no home position yet".to_string()
            } else {
                format!("{} keyframe pairs so far", georef.pairs().len())
            }}),
            Some(Err(e)) => {
                json!({"state": "refused", "reason": e.to_string(), "error": format!("{e:?}")})
            }
            Some(Ok(a)) => {
                let q = &a.quality;
                let r = a.ned_from_map.rotation.coords;
                let t = a.ned_from_map.translation;
                json!({
                    "state": "ok",
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
                r = home.changed() => {
                    if r.is_err() { break; }
                    let v = *home.borrow_and_update();
                    if let Some(v) = v { self.on_home(&v); }
                }
                _ = tick.tick() => {
                    let (me, slam) = (self.clone(), slam.clone());
                    let _ = tokio::task::spawn_blocking(move || {
                        me.sync_keyframes(&slam.keyframes());
                    })
                    .await;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::api::store::PoseJson;
    use crate::geo::{LocalFrame, MountParams, ned_from_cam};
    use crate::geometry::Sim3;
    use nalgebra::{Point3, UnitQuaternion, Vector3};

    /// An L-shaped flight at 10 m, facing north with the camera 30 deg
    /// down: telemetry on the boot clock, keyframes in a map that is NED
    /// through a known similarity. Refused while the motion is a line, then
    /// fitted with the map's scale; a keyframe culled is forgotten.
    #[test]
    fn telemetry_and_keyframes_give_the_maps_similarity() {
        let geo = GeoService::new(Params::default());
        let home = Geodetic {
            lat_deg: 47.3977,
            lon_deg: 8.5456,
            alt_m: 488.0,
        };
        let frame = LocalFrame::new(home);
        let t_end = 40.0;
        let at = |t: f64| {
            Instant::now()
                .checked_sub(Duration::from_secs_f64(t_end - t + 0.02))
                .unwrap_or_else(Instant::now)
        };
        let path = |t: f64| {
            if t < 20.0 {
                Vector3::new(t, 0.0, -10.0)
            } else {
                Vector3::new(20.0, t - 20.0, -10.0)
            }
        };
        geo.on_home(&Stamped {
            value: HomePosition {
                lat_deg: home.lat_deg,
                lon_deg: home.lon_deg,
                alt_amsl_m: home.alt_m,
            },
            received: at(0.0),
        });
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
        let offset = geo.lock().clock.offset_s.unwrap();
        let map_from_ned = Sim3::new(
            UnitQuaternion::from_euler_angles(0.3, -1.0, 2.0),
            Vector3::new(1.0, -2.0, 0.5),
            0.08,
        );
        let keyframe = |id: u64, t: f64| {
            let state = geo.lock().geo.history().lookup(t + offset).unwrap();
            let ned = ned_from_cam(&state, &MountParams::default());
            let p = map_from_ned.transform_point(&Point3::from(ned.translation.vector));
            KeyframeInfo {
                id,
                timestamp: t + offset,
                world_from_cam: PoseJson::from_isometry(&Isometry3::from_parts(
                    p.coords.into(),
                    map_from_ned.rotation * ned.rotation,
                )),
                width: 640,
                height: 480,
            }
        };
        // The first leg only: a line.
        let mut kfs: Vec<KeyframeInfo> =
            (0..8).map(|i| keyframe(i, 1.0 + 2.0 * i as f64)).collect();
        geo.sync_keyframes(&kfs);
        let s = geo.status();
        assert_eq!(s["state"], "refused", "{s}");
        assert!(s["reason"].as_str().unwrap().contains("line"), "{s}");
        // Round the corner.
        kfs.extend((8..16).map(|i| keyframe(i, 1.0 + 2.0 * i as f64)));
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
