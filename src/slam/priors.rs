//! Telemetry priors: a monocular map made metric in local NED by the
//! drone's own GNSS fixes and barometric altitude (issue 20, point 3).
//!
//! The map starts [`MapMode::VisionOnly`]. Once enough keyframes with a
//! GNSS fix span a baseline that fixes a Sim(3) (the checks of
//! [`crate::geo::align`]: extent, not a line), the map→NED Sim(3) is
//! fitted robustly ([`fit_pairs`]) and the whole map is re-expressed in NED
//! ([`Map::apply_sim3`]); the map is then [`MapMode::GpsAided`]. From then
//! on every bundle adjustment (local mapping's and the final one) carries,
//! per free keyframe with a fix, a prior on its camera centre with the
//! receiver's reported covariance (floored at
//! [`PriorParams::min_sigma_m`]) and a barometric-altitude prior on its
//! height, both under the BA's robust prior kernel (Huber), so the map
//! keeps the metric scale vision alone cannot see. Samples flagged as
//! dropouts (no fix) give no GNSS prior.
//!
//! The telemetry is a [`TelemetryFeed`]: a [`TelemetryLog`] read whole
//! from a dataset's `telemetry.txt` (the simulator's `render` writes it;
//! its header is `shotpilot_sim::dataset::TELEMETRY_HEADER`), or a live
//! one that grows while the SLAM runs (the daemon pushes the link's
//! samples into it, on the frames' clock). A keyframe takes the sample
//! nearest its time, or (with [`PriorParams::interpolate_gap_s`], for
//! telemetry slower than the video) the two around it interpolated.
//!
//! [`Priors::status`] says which mode the map is in and why: what the map
//! still waits for while vision-only (keyframes with a fix, the baseline),
//! the fit once aided.

use std::path::Path;
use std::sync::{Arc, Mutex, RwLock};

use nalgebra::{Matrix3, Point3, UnitQuaternion, Vector3};

use crate::geo::align::{AlignParams, Pair, fit_pairs};
use crate::lie::Sim3;
use crate::optimize::PositionPrior;

use super::bundle::BaSetup;
use super::map::{Map, MapMode};

/// One telemetry sample at a frame's time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TelemetrySample {
    /// Time, seconds (the frames' clock).
    pub t: f64,
    /// A GNSS fix (false: the position is dead reckoning, not used).
    pub fix: bool,
    /// GNSS position of the camera, local NED, m.
    pub gps_ned: Vector3<f64>,
    /// Reported 1-sigma horizontal accuracy per axis, m.
    pub h_acc: f64,
    /// Reported 1-sigma vertical accuracy, m.
    pub v_acc: f64,
    /// Barometric altitude above home, m (up).
    pub baro_alt: Option<f64>,
    /// The camera's reported attitude, `ned ← cam` (the autopilot's
    /// attitude and the gimbal's angles; `None`: not reported). Tracking
    /// takes the turn between two frames from it when vision cannot
    /// ([`super::aided`]).
    pub ned_from_cam: Option<UnitQuaternion<f64>>,
}

impl TelemetrySample {
    /// The sample of a live position report at `t`: the camera's position
    /// (the vehicle's `p_vehicle` in local NED plus the mount's lever arm
    /// turned by the attitude `ned_from_body`), with a fix and its
    /// accuracy when the receiver reports a 3D fix (`fix`: the horizontal
    /// and vertical accuracy of the latest GPS_RAW_INT,
    /// `vehicle::GpsRaw::fix_accuracy`; None: no fix). Without a vertical
    /// accuracy the horizontal one doubled (a receiver's vertical is
    /// typically 1.5 to 2 times worse).
    /// No barometric altitude: GLOBAL_POSITION_INT's altitude is the
    /// autopilot's fused one (barometer and GNSS), already the position's
    /// down axis, and a second prior on it would count it twice.
    pub fn from_position_report(
        t: f64,
        p_vehicle: Vector3<f64>,
        ned_from_body: nalgebra::UnitQuaternion<f64>,
        mount: &crate::geo::MountParams,
        fix: Option<(f64, Option<f64>)>,
    ) -> TelemetrySample {
        let state = crate::geo::VehicleState {
            time: t,
            p_ned: p_vehicle,
            v_ned: Vector3::zeros(),
            ned_from_body,
            gimbal: crate::geo::GimbalAngles {
                pitch: 0.0,
                yaw: 0.0,
            },
        };
        let p_cam = crate::geo::ned_from_cam(&state, mount).translation.vector;
        let acc = fix.map(|(h, v)| (h, v.unwrap_or(2.0 * h)));
        TelemetrySample {
            t,
            fix: acc.is_some(),
            gps_ned: p_cam,
            h_acc: acc.map_or(0.0, |a| a.0),
            v_acc: acc.map_or(0.0, |a| a.1),
            baro_alt: None,
            ned_from_cam: None,
        }
    }

    /// The camera's attitude from a telemetry line's body attitude
    /// (`roll pitch yaw`) and gimbal angles (`pitch yaw` relative to the
    /// body), radians, on a stabilised gimbal mount
    /// ([`crate::geo::ned_from_cam`]).
    pub fn camera_attitude(
        roll: f64,
        pitch: f64,
        yaw: f64,
        gimbal_pitch: f64,
        gimbal_yaw: f64,
    ) -> UnitQuaternion<f64> {
        let state = crate::geo::VehicleState {
            time: 0.0,
            p_ned: Vector3::zeros(),
            v_ned: Vector3::zeros(),
            ned_from_body: UnitQuaternion::from_euler_angles(roll, pitch, yaw),
            gimbal: crate::geo::GimbalAngles {
                pitch: gimbal_pitch,
                yaw: gimbal_yaw,
            },
        };
        let mount = crate::geo::MountParams {
            stabilised: true,
            pitch_offset_deg: 0.0,
            yaw_offset_deg: 0.0,
            ..crate::geo::MountParams::default()
        };
        crate::geo::ned_from_cam(&state, &mount).rotation
    }
}

/// Errors of reading a telemetry file.
#[derive(Debug, thiserror::Error)]
pub enum TelemetryError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: String,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A line is not `timestamp fix n e d h_acc v_acc baro_alt ...`.
    #[error("{path} line {line}: {what}")]
    Parse {
        /// The file.
        path: String,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        what: String,
    },
}

/// Telemetry samples sorted by time.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TelemetryLog {
    samples: Vec<TelemetrySample>,
}

impl TelemetryLog {
    /// A log of `samples` (sorted here; non-finite ones dropped).
    pub fn new(mut samples: Vec<TelemetrySample>) -> Self {
        samples.retain(|s| {
            s.t.is_finite()
                && s.gps_ned.iter().all(|v| v.is_finite())
                && s.h_acc.is_finite()
                && s.v_acc.is_finite()
                && s.h_acc >= 0.0
                && s.v_acc >= 0.0
        });
        samples.sort_by(|a, b| a.t.total_cmp(&b.t));
        TelemetryLog { samples }
    }

    /// Reads `telemetry.txt` (`#` lines are comments): `timestamp fix
    /// gps_n gps_e gps_d h_acc v_acc baro_alt`, then optionally `roll_deg
    /// pitch_deg yaw_deg gimbal_pitch_deg gimbal_yaw_deg` (the camera's
    /// attitude, [`TelemetrySample::camera_attitude`]); more columns are
    /// ignored.
    pub fn read(path: &Path) -> Result<Self, TelemetryError> {
        let text = std::fs::read_to_string(path).map_err(|source| TelemetryError::Io {
            path: path.display().to_string(),
            source,
        })?;
        Self::parse(&text, &path.display().to_string())
    }

    /// Parses the text of a telemetry file (`name` for errors).
    pub fn parse(text: &str, name: &str) -> Result<Self, TelemetryError> {
        let mut samples = Vec::new();
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') {
                continue;
            }
            let err = |what: String| TelemetryError::Parse {
                path: name.to_string(),
                line: i + 1,
                what,
            };
            let v: Vec<f64> = line
                .split_whitespace()
                .take(13)
                .map(|x| x.parse::<f64>())
                .collect::<Result<_, _>>()
                .map_err(|e| err(format!("not a number: {e}")))?;
            if v.len() < 8 {
                return Err(err(format!("{} columns, need 8", v.len())));
            }
            if !v.iter().all(|x| x.is_finite()) {
                return Err(err("non-finite value".into()));
            }
            if v[5] < 0.0 || v[6] < 0.0 {
                return Err(err("negative accuracy".into()));
            }
            samples.push(TelemetrySample {
                t: v[0],
                fix: v[1] != 0.0,
                gps_ned: Vector3::new(v[2], v[3], v[4]),
                h_acc: v[5],
                v_acc: v[6],
                baro_alt: Some(v[7]),
                // The attitude columns: all five or none.
                ned_from_cam: match v.get(8..13) {
                    Some(&[roll, pitch, yaw, g_pitch, g_yaw]) => {
                        Some(TelemetrySample::camera_attitude(
                            roll.to_radians(),
                            pitch.to_radians(),
                            yaw.to_radians(),
                            g_pitch.to_radians(),
                            g_yaw.to_radians(),
                        ))
                    }
                    _ if v.len() > 8 => {
                        return Err(err(format!(
                            "{} columns: 8, or 13 with the attitude",
                            v.len()
                        )));
                    }
                    _ => None,
                },
            });
        }
        Ok(Self::new(samples))
    }

    /// The samples, by time.
    pub fn samples(&self) -> &[TelemetrySample] {
        &self.samples
    }

    /// Adds one sample in time order (a sample at a time already held
    /// replaces it); a non-finite or negative-accuracy one is refused
    /// (false). Samples older than the newest by more than `max_age_s` are
    /// dropped, so a live log stays bounded.
    pub fn push(&mut self, s: TelemetrySample, max_age_s: f64) -> bool {
        let ok = s.t.is_finite()
            && s.gps_ned.iter().all(|v| v.is_finite())
            && s.h_acc.is_finite()
            && s.v_acc.is_finite()
            && s.h_acc >= 0.0
            && s.v_acc >= 0.0
            && s.baro_alt.is_none_or(f64::is_finite);
        if !ok {
            return false;
        }
        let i = self.samples.partition_point(|x| x.t < s.t);
        if self.samples.get(i).is_some_and(|x| x.t == s.t) {
            self.samples[i] = s;
        } else {
            self.samples.insert(i, s);
        }
        if let Some(newest) = self.samples.last().map(|x| x.t) {
            let keep_from = newest - max_age_s.max(0.0);
            let old = self.samples.partition_point(|x| x.t < keep_from);
            if old > 0 {
                self.samples.drain(..old);
            }
        }
        true
    }

    /// The sample nearest `t` within `max_dt` seconds.
    pub fn at(&self, t: f64, max_dt: f64) -> Option<&TelemetrySample> {
        let i = self.samples.partition_point(|s| s.t < t);
        let before = i.checked_sub(1).and_then(|j| self.samples.get(j));
        let after = self.samples.get(i);
        [before, after]
            .into_iter()
            .flatten()
            .filter(|s| (s.t - t).abs() <= max_dt)
            .min_by(|a, b| (a.t - t).abs().total_cmp(&(b.t - t).abs()))
    }

    /// The sample at `t`: the nearest within `max_dt`, else (with
    /// `interpolate_gap` Some) the two samples around `t`, at most that
    /// far apart, interpolated linearly (a fix only when both have one;
    /// the larger accuracy of the two; an altitude only when both have
    /// one). `None` when neither.
    pub fn sample_at(
        &self,
        t: f64,
        max_dt: f64,
        interpolate_gap: Option<f64>,
    ) -> Option<TelemetrySample> {
        if let Some(s) = self.at(t, max_dt) {
            return Some(*s);
        }
        let gap = interpolate_gap?;
        let i = self.samples.partition_point(|s| s.t < t);
        let a = self.samples.get(i.checked_sub(1)?)?;
        let b = self.samples.get(i)?;
        let dt = b.t - a.t;
        if !(dt > 0.0 && dt <= gap) {
            return None;
        }
        let f = (t - a.t) / dt;
        Some(TelemetrySample {
            t,
            fix: a.fix && b.fix,
            gps_ned: a.gps_ned + (b.gps_ned - a.gps_ned) * f,
            h_acc: a.h_acc.max(b.h_acc),
            v_acc: a.v_acc.max(b.v_acc),
            baro_alt: match (a.baro_alt, b.baro_alt) {
                (Some(x), Some(y)) => Some(x + (y - x) * f),
                _ => None,
            },
            ned_from_cam: match (a.ned_from_cam, b.ned_from_cam) {
                (Some(x), Some(y)) => Some(x.slerp(&y, f)),
                _ => None,
            },
        })
    }
}

/// Where the priors' telemetry comes from: a log read whole (a dataset's
/// `telemetry.txt`) or a live one that grows while the SLAM runs (the
/// daemon pushes the link's samples with [`TelemetryFeed::push`]). Clones
/// share the log.
#[derive(Debug, Clone)]
pub struct TelemetryFeed {
    log: Arc<RwLock<TelemetryLog>>,
    /// Samples older than the newest by more than this are dropped, s.
    max_age_s: f64,
}

impl PartialEq for TelemetryFeed {
    /// The same feed (clones of one).
    fn eq(&self, other: &Self) -> bool {
        Arc::ptr_eq(&self.log, &other.log)
    }
}

impl TelemetryFeed {
    /// A feed over a whole log (nothing is ever dropped).
    pub fn fixed(log: TelemetryLog) -> Self {
        TelemetryFeed {
            log: Arc::new(RwLock::new(log)),
            max_age_s: f64::INFINITY,
        }
    }

    /// An empty live feed keeping `max_age_s` seconds of samples.
    pub fn live(max_age_s: f64) -> Self {
        TelemetryFeed {
            log: Arc::new(RwLock::new(TelemetryLog::default())),
            max_age_s,
        }
    }

    /// Adds a sample (see [`TelemetryLog::push`]); false when refused.
    pub fn push(&self, s: TelemetrySample) -> bool {
        let mut g = self.log.write().unwrap_or_else(|e| e.into_inner());
        g.push(s, self.max_age_s)
    }

    /// Samples held.
    pub fn len(&self) -> usize {
        self.read().samples().len()
    }

    /// No sample yet.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The newest sample.
    pub fn newest(&self) -> Option<TelemetrySample> {
        self.read().samples().last().copied()
    }

    /// The sample at `t` (see [`TelemetryLog::sample_at`]).
    pub fn sample_at(
        &self,
        t: f64,
        max_dt: f64,
        interpolate_gap: Option<f64>,
    ) -> Option<TelemetrySample> {
        self.read().sample_at(t, max_dt, interpolate_gap)
    }

    fn read(&self) -> std::sync::RwLockReadGuard<'_, TelemetryLog> {
        self.log.read().unwrap_or_else(|e| e.into_inner())
    }
}

/// Root mean square of `v` (0 for none).
fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (sum, n) = v.fold((0.0, 0usize), |(s, n), x| (s + x * x, n + 1));
    if n == 0 { 0.0 } else { (sum / n as f64).sqrt() }
}

/// Tunables of the telemetry priors.
#[derive(Debug, Clone, PartialEq)]
pub struct PriorParams {
    /// A keyframe takes the sample nearest its time within this, s.
    pub max_dt_s: f64,
    /// Fewest keyframes with a fix before the map is put in NED.
    pub min_keyframes: usize,
    /// The map→NED fit (its motion checks decide when the baseline is enough).
    pub align: AlignParams,
    /// Floor of a reported accuracy, m (a receiver reporting 0 is not exact,
    /// and a prior must not outweigh every pixel).
    pub min_sigma_m: f64,
    /// Standard deviation of the barometric altitude, m (`None`: no
    /// altitude prior).
    pub baro_sigma_m: Option<f64>,
    /// Interpolate between the two samples around a keyframe's time when
    /// none is within `max_dt_s` and they are at most this far apart, s
    /// (`None`: nearest sample only; telemetry slower than the video
    /// needs it).
    pub interpolate_gap_s: Option<f64>,
    /// Once aided, refit the map→NED Sim(3) on all keyframes with a fix
    /// whenever their number has grown by this factor since the last fit,
    /// and apply it when it fits the fixes clearly better than the map as
    /// it stands ([`Priors::try_realign`]): local BA holds only its window
    /// to the priors, so a rotation or scale error of the first fit (made
    /// on a short baseline) or the map's drift outside the window is
    /// corrected as a whole (`None`: never; a run ending in a global BA
    /// with priors does not need it).
    pub realign_growth: Option<f64>,
}

impl Default for PriorParams {
    fn default() -> Self {
        PriorParams {
            max_dt_s: 0.05,
            min_keyframes: 8,
            align: AlignParams {
                // The GNSS bias is common to nearby keyframes; what differs
                // between them is noise and the map's drift.
                inlier_threshold_m: 2.0,
                refine_with_orientations: false,
                estimate_time_offset: false,
                ..AlignParams::default()
            },
            min_sigma_m: 0.1,
            baro_sigma_m: Some(0.5),
            interpolate_gap_s: None,
            realign_growth: None,
        }
    }
}

/// The telemetry priors of a SLAM run: the feed and its tunables. Clones
/// share the feed and the [`PriorStatus`].
#[derive(Debug, Clone)]
pub struct Priors {
    /// Tunables.
    pub params: PriorParams,
    /// The telemetry.
    pub log: TelemetryFeed,
    status: Arc<Mutex<PriorStatus>>,
}

impl PartialEq for Priors {
    fn eq(&self, other: &Self) -> bool {
        self.params == other.params && self.log == other.log
    }
}

/// Which mode the map is in and why, as the mapping thread last saw it.
#[derive(Debug, Clone, PartialEq)]
pub struct PriorStatus {
    /// The map's mode.
    pub mode: MapMode,
    /// Why: what a vision-only map waits for, or how it was put in NED.
    pub reason: String,
    /// Keyframes with a fix at the last look.
    pub keyframes_with_fix: usize,
    /// The fit that put the map in NED (this run), if it did.
    pub georeferenced: Option<Georeferenced>,
    /// Refits applied since ([`Priors::try_realign`]).
    pub realigned: usize,
    /// Keyframes with a fix at the last fit (put in NED or refit).
    pub fitted_with: usize,
}

impl Default for PriorStatus {
    fn default() -> Self {
        PriorStatus {
            mode: MapMode::VisionOnly,
            reason: "no keyframe yet".into(),
            keyframes_with_fix: 0,
            georeferenced: None,
            realigned: 0,
            fitted_with: 0,
        }
    }
}

/// What putting the map in NED did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Georeferenced {
    /// The Sim(3) applied (NED ← old map).
    pub ned_from_map: Sim3,
    /// Keyframes with a fix used.
    pub pairs: usize,
    /// Their inliers.
    pub inliers: usize,
    /// Residual RMS of the fit, m.
    pub rms_m: f64,
}

impl Priors {
    /// Priors from `log` with default tunables.
    pub fn new(log: TelemetryLog) -> Self {
        Self::with_feed(TelemetryFeed::fixed(log), PriorParams::default())
    }

    /// Priors over `feed` (a live one grows while the SLAM runs).
    pub fn with_feed(feed: TelemetryFeed, params: PriorParams) -> Self {
        Priors {
            params,
            log: feed,
            status: Arc::default(),
        }
    }

    /// The map's mode and why, as last seen (shared by clones).
    pub fn status(&self) -> PriorStatus {
        self.status
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .clone()
    }

    fn set_status(&self, s: PriorStatus) {
        *self.status.lock().unwrap_or_else(|e| e.into_inner()) = s;
    }

    /// The sample at a keyframe's time (nearest or interpolated).
    fn sample_at(&self, t: f64) -> Option<TelemetrySample> {
        self.log
            .sample_at(t, self.params.max_dt_s, self.params.interpolate_gap_s)
    }

    /// The keyframe's sample with a fix, if any.
    fn fix_at(&self, t: f64) -> Option<TelemetrySample> {
        self.sample_at(t).filter(|s| s.fix)
    }

    /// While the map is vision-only: when enough keyframes with a fix span
    /// a baseline, fit the map→NED Sim(3), apply it to the whole map and
    /// switch the map to [`MapMode::GpsAided`]. `None` while not yet (or
    /// when the map is already aided).
    pub fn try_georeference(&self, map: &mut Map) -> Option<Georeferenced> {
        if map.mode() != MapMode::VisionOnly {
            if self.status().mode != map.mode() {
                self.set_status(PriorStatus {
                    mode: map.mode(),
                    reason: "the map was already in local NED (a continued map)".into(),
                    ..PriorStatus::default()
                });
            }
            return None;
        }
        let waiting = |n: usize, why: String| PriorStatus {
            mode: MapMode::VisionOnly,
            reason: why,
            keyframes_with_fix: n,
            ..PriorStatus::default()
        };
        let pairs = self.pairs(map);
        let n = pairs.len();
        if n < self.params.min_keyframes {
            let why = if self.log.is_empty() {
                "no telemetry yet".to_string()
            } else if self.log.newest().is_some_and(|s| !s.fix) {
                format!(
                    "no GNSS fix now; waiting for {} keyframes with a fix spanning a baseline ({n} so far)",
                    self.params.min_keyframes
                )
            } else {
                format!(
                    "waiting for {} keyframes with a fix spanning a baseline ({n} so far)",
                    self.params.min_keyframes
                )
            };
            self.set_status(waiting(n, why));
            return None;
        }
        let fit = match fit_pairs(&pairs, &self.params.align, None, self.params.align.seed) {
            Ok(f) => f,
            Err(e) => {
                self.set_status(waiting(
                    n,
                    format!("no NED fit yet: {e} ({n} keyframes with a fix)"),
                ));
                return None;
            }
        };
        let s = fit.ned_from_map;
        if !(s.scale.is_finite() && s.scale > 0.0) {
            self.set_status(waiting(
                n,
                format!("no NED fit yet: a degenerate fit ({n} keyframes with a fix)"),
            ));
            return None;
        }
        map.apply_sim3(&s);
        map.set_mode(MapMode::GpsAided);
        let g = Georeferenced {
            ned_from_map: s,
            pairs: fit.quality.pairs,
            inliers: fit.quality.inliers,
            rms_m: fit.quality.rms_m,
        };
        self.set_status(PriorStatus {
            mode: MapMode::GpsAided,
            reason: format!(
                "put in local NED by {} keyframes with a fix ({} inliers, residual RMS {:.2} m); held by GNSS priors",
                g.pairs, g.inliers, g.rms_m
            ),
            keyframes_with_fix: n,
            georeferenced: Some(g),
            realigned: 0,
            fitted_with: n,
        });
        Some(g)
    }

    /// The keyframes with a fix as map/NED pairs.
    fn pairs(&self, map: &Map) -> Vec<Pair> {
        map.keyframes()
            .filter_map(|k| {
                let s = self.fix_at(k.timestamp)?;
                Some(Pair {
                    kf_id: k.id.0 as u64,
                    p_map: Point3::from(k.center()),
                    p_ned: Point3::from(s.gps_ned),
                    time: k.timestamp,
                    orientations: None,
                    v_ned: None,
                })
            })
            .collect()
    }

    /// While the map is aided, with [`PriorParams::realign_growth`]: once
    /// the keyframes with a fix have grown by that factor since the last
    /// fit, refit the map→NED Sim(3) on all of them and apply it to the
    /// whole map when it fits the fixes clearly better than the map as it
    /// stands (the RMS of the fit's inliers at least a fifth lower, and by
    /// more than [`PriorParams::min_sigma_m`]). `None` when not refit or
    /// not applied.
    pub fn try_realign(&self, map: &mut Map) -> Option<Georeferenced> {
        let growth = self.params.realign_growth?;
        if map.mode() != MapMode::GpsAided {
            return None;
        }
        let st = self.status();
        let pairs = self.pairs(map);
        let n = pairs.len();
        if st.fitted_with > 0 && (n as f64) < st.fitted_with as f64 * growth.max(1.0) {
            return None;
        }
        let fit = fit_pairs(&pairs, &self.params.align, None, self.params.align.seed).ok();
        let mut st = st;
        st.fitted_with = n;
        let applied = fit.and_then(|fit| {
            let s = fit.ned_from_map;
            let inliers: std::collections::HashSet<u64> = fit.inlier_ids.iter().copied().collect();
            let as_is = rms(pairs
                .iter()
                .filter(|p| inliers.contains(&p.kf_id))
                .map(|p| (p.p_ned - p.p_map).norm()));
            let better = s.scale.is_finite()
                && s.scale > 0.0
                && fit.quality.rms_m < 0.8 * as_is
                && as_is - fit.quality.rms_m > self.params.min_sigma_m;
            better.then(|| {
                map.apply_sim3(&s);
                (
                    Georeferenced {
                        ned_from_map: s,
                        pairs: fit.quality.pairs,
                        inliers: fit.quality.inliers,
                        rms_m: fit.quality.rms_m,
                    },
                    as_is,
                )
            })
        });
        if let Some((g, before)) = applied {
            st.realigned += 1;
            st.georeferenced = Some(g);
            st.keyframes_with_fix = n;
            st.reason = format!(
                "in local NED by {} keyframes with a fix, refit {} times (last: residual RMS {:.2} m -> {:.2} m over {} inliers); held by GNSS priors",
                g.pairs, st.realigned, before, g.rms_m, g.inliers
            );
            self.set_status(st);
            return Some(g);
        }
        self.set_status(st);
        None
    }

    /// The priors of `setup`'s free keyframes (nothing unless the map is
    /// [`MapMode::GpsAided`]): a GNSS position prior per keyframe with a
    /// fix, a barometric altitude prior per keyframe with a baro sample.
    pub fn priors_for(&self, map: &Map, setup: &BaSetup) -> Vec<PositionPrior> {
        let mut out = Vec::new();
        if map.mode() != MapMode::GpsAided {
            return out;
        }
        let floor = self.params.min_sigma_m.max(1e-6);
        for (i, kf) in setup.keyframes.iter().enumerate() {
            if setup.problem.poses.get(i).is_none_or(|p| p.fixed) {
                continue;
            }
            let Some(k) = map.keyframe(*kf) else { continue };
            let Some(s) = self.sample_at(k.timestamp) else {
                continue;
            };
            if s.fix {
                let h = s.h_acc.max(floor);
                let v = s.v_acc.max(floor);
                out.push(PositionPrior {
                    pose: i,
                    centre: Point3::from(s.gps_ned),
                    information: Matrix3::from_diagonal(&Vector3::new(
                        1.0 / (h * h),
                        1.0 / (h * h),
                        1.0 / (v * v),
                    )),
                });
            }
            if let (Some(alt), Some(sb)) = (s.baro_alt, self.params.baro_sigma_m) {
                let sb = sb.max(floor);
                out.push(PositionPrior {
                    pose: i,
                    centre: Point3::new(0.0, 0.0, -alt),
                    information: Matrix3::from_diagonal(&Vector3::new(0.0, 0.0, 1.0 / (sb * sb))),
                });
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion};
    use crate::matching::FeatureGrid;
    use crate::slam::map::{KeyFrame, KeyFrameId, ScaleInfo};
    use nalgebra::{Isometry3, Translation3, UnitQuaternion};

    #[test]
    fn telemetry_files_parse_and_refuse_bad_lines() {
        let text = "# header\n\
                    0.0 1 1.0 2.0 -30.0 1.3 0.8 30.1 0 0 90 -45 0\n\
                    \n\
                    0.2 0 9.0 9.0 -9.0 1.3 0.8 30.2 0 0 90 -45 0\n\
                    0.1 1 1.5 2.0 -30.0 0 0 30.0\n";
        let log = TelemetryLog::parse(text, "t").unwrap();
        assert_eq!(log.samples().len(), 3);
        // Sorted by time; the nearest within the bound.
        assert_eq!(log.samples()[1].t, 0.1);
        let s = log.at(0.12, 0.05).unwrap();
        assert_eq!(s.t, 0.1);
        assert!(s.fix);
        assert!(!log.at(0.19, 0.05).unwrap().fix);
        assert!(log.at(0.5, 0.05).is_none());
        // The attitude columns: heading 90 (east), gimbal 45 down. The
        // camera looks east and down, its image's right is south.
        let q = log.samples()[0].ned_from_cam.unwrap();
        let forward = q * Vector3::z();
        let h = std::f64::consts::FRAC_1_SQRT_2;
        assert!(
            (forward - Vector3::new(0.0, h, h)).norm() < 1e-9,
            "{forward}"
        );
        assert!((q * Vector3::x() - Vector3::new(-1.0, 0.0, 0.0)).norm() < 1e-9);
        assert!(log.samples()[1].ned_from_cam.is_none(), "8 columns: none");
        // Interpolated half-way between two attitudes: half the turn.
        let turned = TelemetryLog::parse(
            "0 1 0 0 -30 1 1 30 0 0 0 -90 0\n1 1 0 0 -30 1 1 30 0 0 20 -90 0\n",
            "t",
        )
        .unwrap();
        let mid = turned.sample_at(0.5, 0.05, Some(2.0)).unwrap();
        let a = turned.samples()[0].ned_from_cam.unwrap();
        let turn = (a.inverse() * mid.ned_from_cam.unwrap()).angle();
        assert!(
            (turn.to_degrees() - 10.0).abs() < 1e-9,
            "{}",
            turn.to_degrees()
        );
        for (bad, what) in [
            ("0.0 1 1.0 2.0\n", "columns"),
            ("0.0 1 1 2 3 1 1 1 0 0 90\n", "13 with the attitude"),
            ("0.0 1 x 2.0 3 1 1 1\n", "not a number"),
            ("0.0 1 1 2 3 -1 1 1\n", "negative"),
            ("0.0 1 1 2 inf 1 1 1\n", "non-finite"),
        ] {
            let e = TelemetryLog::parse(&format!("# h\n{bad}"), "t").unwrap_err();
            let msg = e.to_string();
            assert!(msg.contains("line 2") && msg.contains(what), "{msg}");
        }
    }

    fn keyframe(t: f64, world_from_cam: Isometry3<f64>) -> KeyFrame {
        KeyFrame {
            id: KeyFrameId(0),
            frame_index: 0,
            timestamp: t,
            cam_from_world: world_from_cam.inverse(),
            keypoints: Vec::new(),
            descriptors: Vec::new(),
            points: Vec::new(),
            grid: FeatureGrid::default(),
            covisible: Vec::new(),
            parent: None,
            children: Vec::new(),
            image: None,
        }
    }

    /// Keyframes along an L (north, then east) at 30 m, seen by a map whose
    /// frame is an unknown similarity of NED; telemetry with the true
    /// positions except during a dropout, where the positions are wrong.
    fn flight(n: usize) -> (Map, TelemetryLog, Sim3, Vec<Vector3<f64>>) {
        let cam = Camera::new(
            640,
            480,
            [500.0, 500.0, 320.0, 240.0],
            Distortion::default(),
        )
        .unwrap();
        let mut map = Map::new(cam, ScaleInfo::new(1.2, 8));
        let map_from_ned = Sim3::new(
            UnitQuaternion::from_euler_angles(0.4, 0.1, -1.2),
            Vector3::new(0.3, -0.2, 1.0),
            1.0 / 37.0,
        );
        let mut samples = Vec::new();
        let mut truth = Vec::new();
        for i in 0..n {
            let t = i as f64;
            let (x, y) = if i < n / 2 {
                (4.0 * t, 0.0)
            } else {
                (4.0 * (n / 2) as f64, 4.0 * (t - (n / 2) as f64))
            };
            let c = Vector3::new(x, y, -30.0 - 0.2 * t);
            truth.push(c);
            let ned_from_cam =
                Isometry3::from_parts(Translation3::from(c), UnitQuaternion::identity());
            map.add_keyframe(keyframe(t, map_from_ned.transform_pose(&ned_from_cam)));
            let dropout = i == 3 || i == n - 2;
            samples.push(TelemetrySample {
                t,
                fix: !dropout,
                gps_ned: if dropout {
                    c + Vector3::new(40.0, -25.0, 3.0)
                } else {
                    c
                },
                h_acc: 1.3,
                v_acc: 0.8,
                baro_alt: Some(-c.z),
                ned_from_cam: None,
            });
        }
        (map, TelemetryLog::new(samples), map_from_ned, truth)
    }

    #[test]
    fn the_map_goes_to_ned_once_the_fixes_span_a_baseline() {
        let priors = Priors::new(flight(12).1);
        // Too few keyframes with a fix: vision-only still.
        let (mut short, ..) = flight(6);
        assert!(priors.try_georeference(&mut short).is_none());
        assert_eq!(short.mode(), MapMode::VisionOnly);

        let (mut map, log, map_from_ned, truth) = flight(12);
        let priors = Priors::new(log);
        let g = priors.try_georeference(&mut map).unwrap();
        assert_eq!(map.mode(), MapMode::GpsAided);
        assert_eq!(g.pairs, 10, "the two dropouts are not used");
        assert!((g.ned_from_map.scale * map_from_ned.scale - 1.0).abs() < 1e-9);
        for (k, c) in map.keyframes().zip(&truth) {
            assert!((k.center() - c).norm() < 1e-6);
        }
        assert_eq!(map.scale_applied(), g.ned_from_map.scale);
        // Once aided, not again.
        assert!(priors.try_georeference(&mut map).is_none());
    }

    fn sample(t: f64, fix: bool, n: f64) -> TelemetrySample {
        TelemetrySample {
            t,
            fix,
            gps_ned: Vector3::new(n, 0.0, -30.0),
            h_acc: 0.5,
            v_acc: 0.8,
            baro_alt: None,
            ned_from_cam: None,
        }
    }

    #[test]
    fn a_live_feed_grows_in_order_stays_bounded_and_interpolates() {
        let feed = TelemetryFeed::live(10.0);
        assert!(feed.is_empty());
        // Out of order, a repeat replaces, a bad one is refused.
        assert!(feed.push(sample(1.0, true, 1.0)));
        assert!(feed.push(sample(0.0, true, 0.0)));
        assert!(feed.push(sample(1.0, true, 2.0)));
        let mut bad = sample(2.0, true, 0.0);
        bad.h_acc = f64::NAN;
        assert!(!feed.push(bad));
        assert_eq!(feed.len(), 2);
        assert_eq!(feed.newest().unwrap().gps_ned.x, 2.0);
        // Clones share the log.
        let priors = Priors::with_feed(
            feed.clone(),
            PriorParams {
                interpolate_gap_s: Some(1.5),
                ..PriorParams::default()
            },
        );
        assert!(feed.push(sample(2.0, false, 4.0)));
        // Between two fixes: interpolated; next to the sample without a
        // fix: no fix.
        let s = priors.sample_at(0.25).unwrap();
        assert!(s.fix && (s.gps_ned.x - 0.5).abs() < 1e-12 && s.t == 0.25);
        assert!(priors.fix_at(0.25).is_some());
        assert!(priors.sample_at(1.5).is_some_and(|s| !s.fix));
        assert!(priors.fix_at(1.5).is_none());
        // Nearest within max_dt wins over interpolation.
        assert_eq!(priors.sample_at(1.02).unwrap().gps_ned.x, 2.0);
        // Samples further apart than the gap (a dropout): nothing.
        assert!(feed.push(sample(5.0, true, 9.0)));
        assert!(priors.sample_at(3.0).is_none());
        // Without interpolation only the nearest within max_dt.
        let nearest = Priors::with_feed(feed.clone(), PriorParams::default());
        assert!(nearest.sample_at(0.25).is_none());
        // Older than max_age behind the newest: dropped.
        assert!(feed.push(sample(10.5, true, 10.0)));
        assert_eq!(feed.len(), 4, "the sample before 0.5 s dropped");
        assert!(priors.sample_at(0.0).is_none());
    }

    #[test]
    fn the_status_says_what_the_map_waits_for() {
        let (_, log, ..) = flight(12);
        let feed = TelemetryFeed::live(f64::INFINITY);
        let priors = Priors::with_feed(feed.clone(), PriorParams::default());
        let (mut map, ..) = flight(12);
        assert!(priors.try_georeference(&mut map).is_none());
        assert_eq!(priors.status().reason, "no telemetry yet");
        // The telemetry arrives while the map grows: all of it now.
        for s in log.samples() {
            feed.push(*s);
        }
        let (mut short, ..) = flight(6);
        assert!(priors.try_georeference(&mut short).is_none());
        let st = priors.status();
        assert_eq!(st.mode, MapMode::VisionOnly);
        assert_eq!(st.keyframes_with_fix, 5);
        assert!(
            st.reason.contains("waiting for 8 keyframes"),
            "{}",
            st.reason
        );
        // A clone (the mapper's) shares the status.
        let g = priors.clone().try_georeference(&mut map).unwrap();
        let st = priors.status();
        assert_eq!(st.mode, MapMode::GpsAided);
        assert_eq!(st.georeferenced, Some(g));
        assert!(st.reason.contains("put in local NED"), "{}", st.reason);
    }

    /// A map put in NED slightly wrong (as a first fit on a short
    /// baseline can be): the refit on all fixes puts it right; a map that
    /// fits already is left alone.
    #[test]
    fn an_aided_map_is_refit_as_a_whole_when_it_fits_clearly_better() {
        let (mut map, log, _, truth) = flight(12);
        let priors = Priors::with_feed(
            TelemetryFeed::fixed(log),
            PriorParams {
                realign_growth: Some(1.0),
                ..PriorParams::default()
            },
        );
        assert!(priors.try_realign(&mut map).is_none(), "not aided yet");
        priors.try_georeference(&mut map).unwrap();
        assert!(priors.try_realign(&mut map).is_none(), "fits already");
        let off = Sim3::new(
            UnitQuaternion::from_euler_angles(0.04, -0.03, 0.02),
            Vector3::new(0.5, -0.3, 0.2),
            1.03,
        );
        map.apply_sim3(&off);
        let g = priors.try_realign(&mut map).unwrap();
        assert_eq!(g.pairs, 10);
        for (k, c) in map.keyframes().zip(&truth) {
            assert!((k.center() - c).norm() < 1e-6);
        }
        let st = priors.status();
        assert_eq!((st.realigned, st.mode), (1, MapMode::GpsAided));
        assert!(st.reason.contains("refit 1 times"), "{}", st.reason);
        // Not again before the fixes grow (by 1.25 here).
        let slow = Priors::with_feed(
            priors.log.clone(),
            PriorParams {
                realign_growth: Some(1.25),
                ..PriorParams::default()
            },
        );
        let (mut map2, ..) = flight(12);
        slow.try_georeference(&mut map2).unwrap();
        map2.apply_sim3(&off);
        assert!(
            slow.try_realign(&mut map2).is_none(),
            "10 fixes, 10 at the fit"
        );
    }

    #[test]
    fn priors_go_on_free_keyframes_with_their_accuracy() {
        let (mut map, log, ..) = flight(12);
        let priors = Priors::new(log);
        let all: Vec<KeyFrameId> = map.keyframes().map(|k| k.id).collect();
        let setup = BaSetup {
            problem: crate::optimize::BaProblem {
                poses: all
                    .iter()
                    .map(|&k| crate::optimize::BaPose {
                        cam_from_world: map.keyframe(k).unwrap().cam_from_world,
                        fixed: k.0 == 0,
                        shutter: None,
                    })
                    .collect(),
                points: Vec::new(),
                observations: Vec::new(),
                intrinsics: crate::optimize::Intrinsics {
                    fx: 500.0,
                    fy: 500.0,
                    cx: 320.0,
                    cy: 240.0,
                },
                priors: Vec::new(),
            },
            keyframes: all.clone(),
            points: Vec::new(),
        };
        // Vision-only: no priors.
        assert!(priors.priors_for(&map, &setup).is_empty());
        priors.try_georeference(&mut map).unwrap();
        let p = priors.priors_for(&map, &setup);
        // 11 free keyframes, two without a fix: 9 GNSS + 11 baro priors.
        let gnss: Vec<&PositionPrior> = p.iter().filter(|p| p.information[(0, 0)] > 0.0).collect();
        assert_eq!(gnss.len(), 9);
        assert_eq!(p.len() - gnss.len(), 11);
        assert!(p.iter().all(|p| p.pose != 0));
        assert!((gnss[0].information[(0, 0)] - 1.0 / 1.69).abs() < 1e-12);
        assert!((gnss[0].information[(2, 2)] - 1.0 / 0.64).abs() < 1e-12);
        let baro = p.iter().find(|p| p.information[(0, 0)] == 0.0).unwrap();
        assert!((baro.information[(2, 2)] - 4.0).abs() < 1e-12);
    }
}
