//! The daemon's georeference worker: telemetry from the link actor and
//! keyframes from the SLAM feed one [`LiveGeoreference`] (`geo::live`: the
//! map → NED alignment refitted as keyframes arrive, move or go; the saved
//! georeference restored, carried to another home and checked against
//! live pairs; the boot clock), held under a lock the API reads through;
//! the API turns a localised shot's camera pose into a vehicle target with
//! it. Across restarts the georeference is saved beside the map with each
//! map checkpoint and at shutdown ([`GeoService::saved`],
//! `<map_file>.geo.json`) and restored at start ([`GeoService::restore`]).
//!
//! Telemetry priors (`[slam] priors`): each GLOBAL_POSITION_INT also
//! becomes a sample of the SLAM's live [`TelemetryFeed`] (on the frames'
//! clock, as the history's): the camera's position in local NED (the
//! vehicle's plus the mount's lever arm turned by the latest attitude), a
//! fix only when the latest GPS_RAW_INT (at most [`GPS_RAW_MAX_AGE`] old)
//! reports a 3D fix and its accuracy, with that accuracy.
//!
//! Clocks: frames are timed by [`crate::geo::capture_time`] (the frame's
//! `X-Timestamp` when used, else receive time minus the configured video
//! latency), and the SLAM stamps its keyframes with that time. Telemetry is
//! timed per [`crate::geo::TelemetryClock`] ([`crate::geo::clock`]); this
//! worker hands it each message's receive time on the unix clock.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use nalgebra::{Isometry3, Vector3};
use tokio_util::sync::CancellationToken;

use crate::api::{KeyframeInfo, SlamView, TrackedFrame};
use crate::geo::live::{LiveGeoreference, MapKeyframe, TrackedPose};
use crate::geo::saved::SavedGeoreference;
use crate::geo::{GeoAlignment, GeoError, GeoTarget, Geodetic, Params};
use crate::slam::MapMode;
use crate::slam::priors::{TelemetryFeed, TelemetrySample};
use crate::vehicle::{
    Attitude, GimbalAttitude, GlobalPosition, GpsRaw, HomePosition, Stamped, Telemetry,
};
use crate::video::live::{Frame, unix_now};

/// A photo's GPS tag without its horizontal error: a phone's fix
/// outdoors, metres (1 sigma).
pub const PHOTO_TAG_SIGMA_M: f64 = 10.0;

/// How often the keyframes are compared with the map and the alignment
/// refitted.
const SYNC_PERIOD: Duration = Duration::from_millis(500);
/// A GPS_RAW_INT older than this says nothing about the fix of a position
/// sample (the message comes at 1 Hz by default).
pub const GPS_RAW_MAX_AGE: Duration = Duration::from_secs(3);

/// A prior sample carries the camera's attitude only with a gimbal report
/// at most this old, s (PX4 streams GIMBAL_DEVICE_ATTITUDE_STATUS at 1 Hz
/// by default; an older one may miss a pitch the gimbal was commanded to).
pub const GIMBAL_MAX_AGE_S: f64 = 2.5;

struct State {
    live: LiveGeoreference,
    /// The latest GPS_RAW_INT and when it came.
    gps_raw: Option<(Instant, GpsRaw)>,
}

/// The georeference the daemon keeps, shared by its worker and the API.
pub struct GeoService {
    state: Mutex<State>,
    params: Params,
    /// The SLAM's telemetry priors' feed (None: priors off).
    prior_feed: Option<TelemetryFeed>,
}

impl GeoService {
    /// An empty georeference.
    pub fn new(params: Params) -> Self {
        Self {
            state: Mutex::new(State {
                live: LiveGeoreference::new(params.clone()),
                gps_raw: None,
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
        self.lock().live.set_map_aided(aided);
    }

    /// GPS_RAW_INT: the fix and accuracy the next position samples carry.
    pub fn on_gps_raw(&self, g: &Stamped<GpsRaw>) {
        self.lock().gps_raw = Some((g.received, g.value));
    }

    /// The priors' sample of a position at `t` (local NED `p_vehicle`):
    /// the camera's position, a fix and its accuracy from a recent
    /// GPS_RAW_INT, and the camera's attitude (the latest ATTITUDE and a
    /// gimbal report at most [`GIMBAL_MAX_AGE_S`] old; the telemetry aid
    /// of tracking reads it). None before any attitude (the lever arm
    /// needs it).
    fn prior_sample(&self, st: &State, t: f64, p_vehicle: Vector3<f64>) -> Option<TelemetrySample> {
        let q = st.live.last_attitude()?;
        let raw = st
            .gps_raw
            .filter(|(at, _)| crate::clock::since(*at) <= GPS_RAW_MAX_AGE)
            .and_then(|(_, r)| r.fix_accuracy());
        let mut sample =
            TelemetrySample::from_position_report(t, p_vehicle, q, &self.params.mount, raw);
        sample.ned_from_cam = st
            .live
            .last_gimbal()
            .filter(|(tg, _)| (t - tg).abs() <= GIMBAL_MAX_AGE_S)
            .map(|(_, gimbal)| {
                let state = crate::geo::VehicleState {
                    time: t,
                    p_ned: p_vehicle,
                    v_ned: Vector3::zeros(),
                    ned_from_body: q,
                    gimbal,
                };
                crate::geo::ned_from_cam(&state, &self.params.mount).rotation
            });
        Some(sample)
    }

    /// Takes the georeference saved by the previous run (see
    /// [`LiveGeoreference::restore`]).
    pub fn restore(&self, saved: SavedGeoreference) {
        self.lock().live.restore(saved);
    }

    /// The georeference to save beside the map (see
    /// [`LiveGeoreference::saved`]); None before any home is known.
    pub fn saved(&self) -> Option<SavedGeoreference> {
        self.lock().live.saved(unix_now())
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// The parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// HOME_POSITION: the origin of local NED (the first one heard).
    pub fn on_home(&self, home: &Stamped<HomePosition>) {
        let h = home.value;
        self.lock().live.on_home(Geodetic {
            lat_deg: h.lat_deg,
            lon_deg: h.lon_deg,
            alt_m: h.alt_amsl_m,
        });
    }

    /// GLOBAL_POSITION_INT (needs home); with priors, also a sample of the
    /// SLAM's feed.
    pub fn on_position(&self, p: &Stamped<GlobalPosition>) {
        let g = Geodetic {
            lat_deg: p.value.lat_deg,
            lon_deg: p.value.lon_deg,
            alt_m: p.value.alt_amsl_m,
        };
        let mut st = self.lock();
        let Some((t, ned)) =
            st.live
                .on_position(p.value.time_boot_ms, crate::clock::unix_at(p.received), &g)
        else {
            return;
        };
        if let Some(feed) = &self.prior_feed
            && let Some(sample) = self.prior_sample(&st, t, ned)
            && feed.push(sample)
        {
            st.live.note_prior_sample(sample.fix);
        }
    }

    /// ATTITUDE.
    pub fn on_attitude(&self, a: &Stamped<Attitude>) {
        let v = a.value;
        self.lock().live.on_attitude(
            v.time_boot_ms,
            crate::clock::unix_at(a.received),
            (
                f64::from(v.roll_rad),
                f64::from(v.pitch_rad),
                f64::from(v.yaw_rad),
            ),
        );
    }

    /// Gimbal attitude (yaw relative to the body; an earth-frame yaw is
    /// made relative with the latest heading).
    pub fn on_gimbal(&self, g: &Stamped<GimbalAttitude>) {
        let v = g.value;
        self.lock().live.on_gimbal(
            v.time_boot_ms,
            crate::clock::unix_at(g.received),
            (f64::from(v.pitch_deg), f64::from(v.yaw_deg), v.yaw_absolute),
        );
    }

    /// A video frame taken by the SLAM: records the sender's delay (receive
    /// time minus `X-Timestamp`) when the frame is stamped.
    pub fn note_frame(&self, frame: &Frame) {
        if frame.capture_time.is_some() {
            self.lock()
                .live
                .note_frame(frame.capture_time, frame.received_unix);
        }
    }

    /// Compares the SLAM's keyframes with those fed before (see
    /// [`Self::sync`]), without a tracked frame or a decision about the
    /// saved georeference.
    pub fn sync_keyframes(&self, keyframes: &[KeyframeInfo]) {
        self.sync(keyframes, None, None);
    }

    /// One round of the worker (see [`LiveGeoreference::sync`]): the
    /// SLAM's keyframes, its newest tracked frame and whether its map was
    /// continued.
    pub fn sync(
        &self,
        keyframes: &[KeyframeInfo],
        frame: Option<TrackedFrame>,
        continued: Option<bool>,
    ) {
        let keyframes: Vec<MapKeyframe> = keyframes
            .iter()
            .map(|k| MapKeyframe {
                id: k.id,
                timestamp: k.timestamp,
                world_from_cam: k.world_from_cam.to_isometry(),
            })
            .collect();
        let frame = frame.map(|f| TrackedPose {
            seq: f.seq,
            timestamp: f.timestamp,
            reference_kf: f.reference_kf,
            cam_from_ref: f.cam_from_ref,
        });
        self.lock().live.sync(&keyframes, frame, continued);
    }

    /// The vehicle target that puts the camera at `map_from_cam` (a camera
    /// pose in the SLAM map), with the alignment it went through.
    pub fn target(
        &self,
        map_from_cam: &Isometry3<f64>,
    ) -> Result<(GeoTarget, GeoAlignment), GeoError> {
        self.lock().live.target(map_from_cam)
    }

    /// A photo's GPS tag as a horizontal position prior in the map's frame
    /// (a tag's altitude is not trusted: phones write ellipsoid, geoid or
    /// barometric heights), its sigma the tag's horizontal error (10 m
    /// when it gives none) and the georeference's residual in quadrature.
    pub fn photo_prior(
        &self,
        tag: &crate::shot::photo::GpsTag,
    ) -> Result<crate::shot::PositionPrior, GeoError> {
        let mut live = self.lock();
        let home = live.live.home().ok_or(GeoError::NoHome)?;
        let g = Geodetic {
            lat_deg: tag.lat_deg,
            lon_deg: tag.lon_deg,
            alt_m: home.alt_m,
        };
        let (centre, alignment) = live.live.map_point_of(&g)?;
        let s = alignment.ned_from_map.scale;
        if !(s.is_finite() && s > 0.0) {
            return Err(GeoError::NonFinite {
                what: "georeference scale",
            });
        }
        let sigma_m = tag
            .h_error_m
            .unwrap_or(PHOTO_TAG_SIGMA_M)
            .hypot(alignment.quality.rms_m);
        // NED's down in the map: p_ned = s R p_map + t.
        let down = alignment.ned_from_map.rotation.inverse() * nalgebra::Vector3::z();
        Ok(crate::shot::PositionPrior {
            centre,
            sigma: sigma_m / s,
            down: Some(nalgebra::Unit::new_normalize(down)),
            metres_per_unit: Some(s),
        })
    }

    /// Home, once known.
    pub fn home(&self) -> Option<HomePosition> {
        self.lock().live.home().map(|h| HomePosition {
            lat_deg: h.lat_deg,
            lon_deg: h.lon_deg,
            alt_amsl_m: h.alt_m,
        })
    }

    /// The state as the API reports it (see [`LiveGeoreference::status`]).
    pub fn status(&self) -> crate::geo::GeoreferenceStatus {
        self.lock().live.status()
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::{LocalFrame, MountParams, ned_from_cam};
    use crate::shot::record::PoseJson;

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
    /// north, camera 30 deg down) as the link publishes it, on the boot
    /// clock, ending now. Returns the boot clock's offset.
    fn feed_flight(geo: &GeoService) -> f64 {
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
        geo.lock().live.boot_offset_s().unwrap()
    }

    /// Keyframes already in NED (a gps-aided map: the map is NED itself),
    /// as the SLAM reports them.
    fn ned_keyframe(telemetry: &GeoService, id: u64, t: f64, offset: f64) -> KeyframeInfo {
        let state = telemetry
            .lock()
            .live
            .geo()
            .history()
            .lookup(t + offset)
            .unwrap();
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
    /// camera's NED position (lever arm included) and attitude (the
    /// attitude with the latest gimbal report), a fix with the
    /// accuracy of a recent GPS_RAW_INT, none without one or with a
    /// GPS_RAW_INT reporting no fix. The link's messages and the SLAM's
    /// keyframes reach the georeference: home, the boot clock, and a
    /// gps-aided map's georeference is the identity, its targets through
    /// it.
    #[test]
    fn priors_get_the_links_samples_and_an_aided_map_is_its_own_georeference() {
        let feed = TelemetryFeed::live(1800.0);
        let geo = GeoService::new(Params::default()).with_prior_feed(Some(feed.clone()));
        // No GPS_RAW_INT yet: samples without a fix.
        let offset = feed_flight(&geo);
        assert!(feed.len() > 300, "{}", feed.len());
        let s = feed.newest().unwrap();
        assert!(!s.fix);
        // The camera's position: the vehicle's plus the lever arm (facing
        // north, so the arm's forward component goes north).
        let arm = MountParams::default().lever_arm_body_m;
        let expect = path(T_END) + Vector3::new(arm[0], arm[1], arm[2]);
        assert!((s.gps_ned - expect).norm() < 1e-3, "{:?}", s.gps_ned);
        assert!((s.t - (T_END + offset)).abs() < 1e-6);
        // The camera's attitude, for the tracking aid: facing north, the
        // gimbal 30 degrees down (its report 0.1 s older than the sample).
        let forward = s
            .ned_from_cam
            .expect("an attitude with a recent gimbal report")
            * Vector3::z();
        let down30 = Vector3::new(30f64.to_radians().cos(), 0.0, 30f64.to_radians().sin());
        assert!((forward - down30).norm() < 1e-9, "{forward}");
        let st = serde_json::to_value(geo.status()).unwrap();
        assert_eq!(st["counts"]["prior_samples"], feed.len(), "{st}");
        assert_eq!(st["counts"]["prior_samples_without_fix"], feed.len());
        assert_eq!(geo.home().map(|h| h.alt_amsl_m), Some(HOME.alt_m));
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
        feed_flight(&geo2);
        let s = feed2.newest().unwrap();
        assert!(s.fix && s.h_acc == 1.3 && s.v_acc == 2.6, "{s:?}");
        let feed3 = TelemetryFeed::live(1800.0);
        let geo3 = GeoService::new(Params::default()).with_prior_feed(Some(feed3.clone()));
        geo3.on_gps_raw(&raw(1));
        feed_flight(&geo3);
        assert!(!feed3.newest().unwrap().fix);

        // The map in NED: the identity, no fit.
        geo.set_map_aided(true);
        let kfs: Vec<KeyframeInfo> = (0..16)
            .map(|i| ned_keyframe(&geo, i, 1.0 + 2.0 * i as f64, offset))
            .collect();
        geo.sync_keyframes(&kfs);
        let st = serde_json::to_value(geo.status()).unwrap();
        assert_eq!(st["state"], "ok", "{st}");
        assert_eq!(st["source"], "map", "{st}");
        assert_eq!(st["keyframes_used"], 16);
        let kf = &kfs[12];
        let (target, alignment) = geo
            .target(&kf.world_from_cam.to_isometry().unwrap())
            .unwrap();
        assert_eq!(alignment.ned_from_map.scale, 1.0);
        let p = path(kf.timestamp - offset);
        assert!((target.p_ned_vehicle - p).norm() < 0.02, "{target:?}");
        // Saved with the home heard.
        let saved = geo.saved().unwrap();
        assert_eq!(saved.pairs.len(), 16);
        assert_eq!(saved.home, HOME);
    }
}
