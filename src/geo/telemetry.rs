//! A bounded telemetry history and its interpolation at a frame's capture
//! time.
//!
//! Three streams arrive at their own rates, each sample with its own time
//! (seconds on the clock the caller uses for frames too: autopilot boot time
//! mapped to the local clock, or receive time): the vehicle position (local
//! NED, or WGS84 converted to it), the body attitude (world ← body, body x
//! forward, y right, z down) and the gimbal angles relative to the body.
//! [`TelemetryHistory::lookup`] interpolates each stream at the asked time:
//! position linearly, attitude by slerp, gimbal angles linearly (yaw along
//! the shorter way round). It refuses a time outside a stream's history or
//! between two samples further apart than `max_gap_s`.

use std::collections::VecDeque;

use nalgebra::{UnitQuaternion, Vector3};

use super::GeoError;
use super::wgs84::{Geodetic, LocalFrame};

/// Tunables of the history.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct HistoryParams {
    /// How much history each stream keeps, seconds: samples older than the
    /// stream's newest by more than this are dropped (a duration, so that
    /// the history spans the same time at any telemetry rate).
    pub max_age_s: f64,
    /// Largest time between the two samples an interpolation uses, seconds.
    pub max_gap_s: f64,
    /// Video latency (seconds) subtracted from a frame's receive time when
    /// the frame carries no capture timestamp (or when frame timestamps are
    /// not used).
    pub video_latency_s: f64,
    /// Use a frame's own capture timestamp (the MJPEG part's `X-Timestamp`)
    /// when it has one; false: always receive time minus `video_latency_s`
    /// (for senders whose clock is not the ground station's).
    pub use_frame_timestamps: bool,
    /// Which clock telemetry samples are timed by.
    pub telemetry_clock: TelemetryClock,
}

/// How telemetry samples are placed on the ground station's clock.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TelemetryClock {
    /// The autopilot's `time_boot_ms`, mapped to the local clock by the
    /// smallest observed `receive time - boot time` (the link's fastest
    /// delivery): transport jitter does not reach the samples' times.
    Boot,
    /// The time each message was received (every delay and jitter of the
    /// link lands on the samples).
    Received,
}

impl Default for HistoryParams {
    fn default() -> Self {
        Self {
            max_age_s: 1800.0,
            max_gap_s: 0.5,
            video_latency_s: 0.1,
            use_frame_timestamps: true,
            telemetry_clock: TelemetryClock::Boot,
        }
    }
}

/// The capture time of a frame: its own timestamp (the MJPEG part's
/// `X-Timestamp`, already on the telemetry clock) when it has one and
/// `use_frame_timestamps` is set, else its receive time minus the
/// configured video latency.
pub fn capture_time(received_s: f64, stamped_s: Option<f64>, params: &HistoryParams) -> f64 {
    match stamped_s {
        Some(t) if t.is_finite() && params.use_frame_timestamps => t,
        _ => received_s - params.video_latency_s,
    }
}

/// Gimbal angles relative to the body, radians.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GimbalAngles {
    /// Pitch, positive up (-π/2 looks straight down).
    pub pitch: f64,
    /// Yaw relative to the body's heading, positive right (clockwise seen
    /// from above).
    pub yaw: f64,
}

/// The vehicle's state at one instant, interpolated from the history.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleState {
    /// Time, seconds.
    pub time: f64,
    /// Position of the vehicle's reference point, local NED metres.
    pub p_ned: Vector3<f64>,
    /// Velocity, local NED m/s: the slope of the position samples around
    /// the time (zero when the time falls on a sample at the history's end).
    pub v_ned: Vector3<f64>,
    /// Body attitude: world (NED) ← body.
    pub ned_from_body: UnitQuaternion<f64>,
    /// Gimbal angles relative to the body.
    pub gimbal: GimbalAngles,
}

impl VehicleState {
    /// Heading (yaw of the body's x axis), radians clockwise from north.
    pub fn heading(&self) -> f64 {
        heading_of(&self.ned_from_body)
    }
}

/// Yaw of a world ← body rotation (Z-Y-X Euler), radians from north.
pub fn heading_of(ned_from_body: &UnitQuaternion<f64>) -> f64 {
    let x = ned_from_body * Vector3::x();
    // Near ±90 deg pitch the x axis is vertical: use the y axis instead.
    if x.x.hypot(x.y) > 1e-6 {
        x.y.atan2(x.x)
    } else {
        let y = ned_from_body * Vector3::y();
        (-y.x).atan2(y.y)
    }
}

/// [`crate::angle::wrap_pi`], named here too for the callers that reach it
/// through the telemetry (the daemon's georeference worker); new code
/// imports it from [`crate::angle`].
pub use crate::angle::wrap_pi;

/// One time-ordered, bounded stream.
#[derive(Debug, Clone)]
struct Stream<T> {
    name: &'static str,
    samples: VecDeque<(f64, T)>,
}

impl<T: Copy> Stream<T> {
    fn new(name: &'static str) -> Self {
        Self {
            name,
            samples: VecDeque::new(),
        }
    }

    /// Inserts in time order (late samples go to their place; an equal time
    /// replaces), dropping the samples more than `max_age` older than the
    /// newest (the newest two always stay, for an interpolation).
    fn push(&mut self, t: f64, v: T, max_age: f64) {
        let at = self.samples.partition_point(|(ts, _)| *ts < t);
        if at < self.samples.len() && self.samples[at].0 == t {
            self.samples[at].1 = v;
        } else {
            self.samples.insert(at, (t, v));
        }
        // A NaN or negative age keeps just the newest two samples.
        let max_age = if max_age.is_nan() {
            0.0
        } else {
            max_age.max(0.0)
        };
        if let Some(&(newest, _)) = self.samples.back() {
            let oldest_kept = newest - max_age;
            while self.samples.len() > 2 && self.samples.front().is_some_and(|s| s.0 < oldest_kept)
            {
                self.samples.pop_front();
            }
        }
    }

    /// The two samples around `t`, the fraction of the way from the first
    /// to the second, and the time between them (0 when `t` falls on the
    /// last sample).
    fn bracket(&self, t: f64, max_gap: f64) -> Result<(T, T, f64, f64), GeoError> {
        let (Some(first), Some(last)) = (self.samples.front(), self.samples.back()) else {
            return Err(GeoError::EmptyHistory { stream: self.name });
        };
        if t < first.0 {
            return Err(GeoError::TooOld {
                stream: self.name,
                t,
                oldest: first.0,
            });
        }
        if t > last.0 {
            return Err(GeoError::NotYet {
                stream: self.name,
                t,
                newest: last.0,
            });
        }
        let i = self.samples.partition_point(|(ts, _)| *ts <= t);
        // t >= first, so i >= 1; t <= last, so i == len only when t == last.
        let (t0, a) = self.samples[i - 1];
        if i == self.samples.len() {
            return Ok((a, a, 0.0, 0.0));
        }
        let (t1, b) = self.samples[i];
        if t1 - t0 > max_gap {
            return Err(GeoError::Gap {
                stream: self.name,
                t,
                before: t0,
                after: t1,
                max_gap_s: max_gap,
            });
        }
        Ok((a, b, (t - t0) / (t1 - t0), t1 - t0))
    }
}

/// The bounded telemetry history.
#[derive(Debug, Clone)]
pub struct TelemetryHistory {
    params: HistoryParams,
    positions: Stream<Vector3<f64>>,
    attitudes: Stream<UnitQuaternion<f64>>,
    gimbals: Stream<GimbalAngles>,
}

fn finite_time(t: f64) -> Result<(), GeoError> {
    if t.is_finite() {
        Ok(())
    } else {
        Err(GeoError::NonFinite { what: "time" })
    }
}

impl TelemetryHistory {
    /// An empty history.
    pub fn new(params: HistoryParams) -> Self {
        Self {
            params,
            positions: Stream::new("position"),
            attitudes: Stream::new("attitude"),
            gimbals: Stream::new("gimbal"),
        }
    }

    /// The parameters.
    pub fn params(&self) -> &HistoryParams {
        &self.params
    }

    /// Adds a position in local NED metres.
    pub fn push_position_ned(&mut self, t: f64, p_ned: Vector3<f64>) -> Result<(), GeoError> {
        finite_time(t)?;
        if !p_ned.iter().all(|v| v.is_finite()) {
            return Err(GeoError::NonFinite { what: "position" });
        }
        self.positions.push(t, p_ned, self.params.max_age_s);
        Ok(())
    }

    /// Adds a WGS84 position, converted to NED in `frame`.
    pub fn push_position_geodetic(
        &mut self,
        t: f64,
        g: &Geodetic,
        frame: &LocalFrame,
    ) -> Result<(), GeoError> {
        if !g.is_valid() {
            return Err(GeoError::NonFinite {
                what: "geodetic position",
            });
        }
        self.push_position_ned(t, frame.geodetic_to_ned(g))
    }

    /// Adds a body attitude (world NED ← body).
    pub fn push_attitude(
        &mut self,
        t: f64,
        ned_from_body: UnitQuaternion<f64>,
    ) -> Result<(), GeoError> {
        finite_time(t)?;
        if !ned_from_body.coords.iter().all(|v| v.is_finite()) {
            return Err(GeoError::NonFinite { what: "attitude" });
        }
        self.attitudes.push(t, ned_from_body, self.params.max_age_s);
        Ok(())
    }

    /// Adds a body attitude given as MAVLink ATTITUDE's roll, pitch, yaw
    /// (Z-Y-X Euler angles, radians).
    pub fn push_attitude_euler(
        &mut self,
        t: f64,
        roll: f64,
        pitch: f64,
        yaw: f64,
    ) -> Result<(), GeoError> {
        if !(roll.is_finite() && pitch.is_finite() && yaw.is_finite()) {
            return Err(GeoError::NonFinite { what: "attitude" });
        }
        self.push_attitude(t, UnitQuaternion::from_euler_angles(roll, pitch, yaw))
    }

    /// Adds gimbal angles relative to the body (radians).
    pub fn push_gimbal(&mut self, t: f64, gimbal: GimbalAngles) -> Result<(), GeoError> {
        finite_time(t)?;
        if !(gimbal.pitch.is_finite() && gimbal.yaw.is_finite()) {
            return Err(GeoError::NonFinite { what: "gimbal" });
        }
        self.gimbals.push(t, gimbal, self.params.max_age_s);
        Ok(())
    }

    /// Number of samples held per stream: (positions, attitudes, gimbals).
    pub fn len(&self) -> (usize, usize, usize) {
        (
            self.positions.samples.len(),
            self.attitudes.samples.len(),
            self.gimbals.samples.len(),
        )
    }

    /// True when no stream holds a sample.
    pub fn is_empty(&self) -> bool {
        self.len() == (0, 0, 0)
    }

    /// The vehicle state at time `t`, interpolated.
    pub fn lookup(&self, t: f64) -> Result<VehicleState, GeoError> {
        finite_time(t)?;
        let gap = self.params.max_gap_s;
        let (p0, p1, a, dt) = self.positions.bracket(t, gap)?;
        let (q0, q1, b, _) = self.attitudes.bracket(t, gap)?;
        let (g0, g1, c, _) = self.gimbals.bracket(t, gap)?;
        let p_ned = p0.lerp(&p1, a);
        let v_ned = if dt > 0.0 {
            (p1 - p0) / dt
        } else {
            Vector3::zeros()
        };
        // Shortest-path slerp (q and -q are the same rotation); falls back to
        // normalised lerp when the two are (almost) equal.
        let q1 = if q0.coords.dot(&q1.coords) < 0.0 {
            UnitQuaternion::new_unchecked(-q1.into_inner())
        } else {
            q1
        };
        let ned_from_body = q0
            .try_slerp(&q1, b, 1e-9)
            .unwrap_or_else(|| q0.nlerp(&q1, b));
        let gimbal = GimbalAngles {
            pitch: g0.pitch + (g1.pitch - g0.pitch) * c,
            yaw: wrap_pi(g0.yaw + wrap_pi(g1.yaw - g0.yaw) * c),
        };
        Ok(VehicleState {
            time: t,
            p_ned,
            v_ned,
            ned_from_body,
            gimbal,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_timestamps_are_used_only_when_configured() {
        let mut p = HistoryParams {
            video_latency_s: 0.2,
            ..Default::default()
        };
        assert_eq!(capture_time(10.0, Some(9.9), &p), 9.9);
        p.use_frame_timestamps = false;
        assert!((capture_time(10.0, Some(9.9), &p) - 9.8).abs() < 1e-12);
    }

    #[test]
    fn out_of_order_samples_are_placed_and_the_age_bound_holds() {
        let mut h = TelemetryHistory::new(HistoryParams {
            max_age_s: 2.0,
            ..Default::default()
        });
        h.push_position_ned(1.0, Vector3::new(1.0, 0.0, 0.0))
            .unwrap();
        h.push_position_ned(0.0, Vector3::new(0.0, 0.0, 0.0))
            .unwrap();
        h.push_position_ned(2.0, Vector3::new(2.0, 0.0, 0.0))
            .unwrap();
        assert_eq!(h.len().0, 3);
        h.push_position_ned(3.0, Vector3::new(3.0, 0.0, 0.0))
            .unwrap();
        // 0.0 is more than 2 s older than 3.0; 1.0 is exactly 2 s older and stays.
        assert_eq!(h.len().0, 3);
        assert_eq!(h.positions.samples.front().unwrap().0, 1.0);
        // A late sample older than the bound is placed and dropped at once.
        h.push_position_ned(0.5, Vector3::zeros()).unwrap();
        assert_eq!(h.positions.samples.front().unwrap().0, 1.0);
        assert!(h.push_position_ned(f64::NAN, Vector3::zeros()).is_err());
    }

    #[test]
    fn history_spans_its_duration_at_any_rate() {
        // An hour of 10 Hz attitude (5 Hz position, gimbal): the default keeps
        // 30 minutes of both, far more than a 4096-sample cap (409.6 s).
        let p = HistoryParams::default();
        assert_eq!(p.max_age_s, 1800.0);
        let mut h = TelemetryHistory::new(p);
        let n = 36_000;
        for i in 0..=n {
            let t = i as f64 * 0.1;
            h.push_attitude(t, UnitQuaternion::from_euler_angles(0.0, 0.0, 0.001 * t))
                .unwrap();
            if i % 2 == 0 {
                h.push_position_ned(t, Vector3::new(t, 0.0, -10.0)).unwrap();
                h.push_gimbal(
                    t,
                    GimbalAngles {
                        pitch: -0.5,
                        yaw: 0.0,
                    },
                )
                .unwrap();
            }
        }
        let newest = n as f64 * 0.1;
        let (pos, att, gim) = h.len();
        assert_eq!(att, 18_001, "10 Hz over 1800 s, both ends");
        assert_eq!(pos, 9_001, "5 Hz over 1800 s, both ends");
        assert_eq!(gim, 9_001, "5 Hz over 1800 s, both ends");
        // 25 minutes back is still answered, with the right values.
        let t = newest - 1500.0 + 0.05;
        let s = h.lookup(t).unwrap();
        assert!((s.p_ned.x - t).abs() < 1e-9, "{}", s.p_ned.x);
        assert!((s.heading() - wrap_pi(0.001 * t)).abs() < 1e-9);
        // Beyond 30 minutes it is gone.
        assert!(matches!(
            h.lookup(newest - 1800.5),
            Err(GeoError::TooOld { .. })
        ));
        // A non-finite age keeps the newest two samples, not everything.
        let mut tight = TelemetryHistory::new(HistoryParams {
            max_age_s: f64::NAN,
            ..Default::default()
        });
        for i in 0..100 {
            tight
                .push_gimbal(
                    i as f64,
                    GimbalAngles {
                        pitch: -0.5,
                        yaw: 0.0,
                    },
                )
                .unwrap();
        }
        assert_eq!(tight.len().2, 2);
    }
}
