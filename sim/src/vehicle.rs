//! Multicopter kinematics, a position/velocity/yaw controller with speed and
//! acceleration limits, and a 2-axis gimbal carrying the camera.
//!
//! Frames (see ARCHITECTURE.md): the world is local NED at home (x north,
//! y east, z down, ground at z = 0); the body is x forward, y right, z down;
//! the camera is x right, y down, z forward. The gimbal is stabilised: the
//! camera's orientation depends only on the body yaw and the gimbal's yaw
//! (relative to the body) and pitch (positive up, -90 deg looks straight
//! down), never on the body's roll and pitch.
//!
//! The model is kinematic with a first-order velocity loop: the position
//! controller asks for a velocity whose magnitude is limited by the speed
//! limit, a proportional gain and the braking distance sqrt(2 a d); the
//! velocity loop asks for an acceleration (v_des - v) / tau, clamped to the
//! acceleration limits, which is integrated. Roll and pitch are derived from
//! the horizontal acceleration (tilt = atan(a / g)) for telemetry.
//!
//! GPS error: the position the controller flies and the autopilot reports
//! ([`Vehicle::p_ned`]) is the vehicle's estimate. With a [`GpsBiasParams`]
//! switched on, the vehicle truly stands at that position plus a bias
//! ([`GpsBias`], a first-order Gauss-Markov process), and the camera films
//! from the true pose ([`Vehicle::true_world_from_cam`]). Off by default.
//!
//! Realism ([`VehicleDisturbances`], from a [`crate::realism::Realism`]'s
//! vehicle effects; all off by default):
//!
//! - wind ([`crate::disturbance::WindField`]): the velocity loop feels the
//!   wind's quadratic drag and compensates its mean with an integral term,
//!   so the vehicle sways around its setpoint (decimetres in a breeze); the
//!   roll and pitch follow the commanded thrust, leaning into the wind;
//! - GNSS error: the realism's slow bias and fast noise (each a first-order
//!   Gauss-Markov process) add to the true position like the bias above,
//!   the bias through the estimator's fusion with the IMU (a second-order
//!   low-pass, `gps.fusion_tau_s`), so the vehicle wanders smoothly;
//!   during a fix loss ([`Vehicle::gps_fix`] false) the estimate drifts as a
//!   random walk, and snaps back (an estimator reset) when the fix returns;
//! - barometer drift: the height the vehicle holds drifts as a random walk
//!   (PX4 and ArduPilot fly on barometric height by default), so the true
//!   height moves by the drift;
//! - gimbal error ([`crate::disturbance::GimbalJitter`]): the true camera
//!   is turned by the stabilisation error and jitter at the vehicle's clock;
//!   the gimbal's reported attitude is the commanded one.

use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use crate::disturbance::{GimbalJitter, WindField};
use crate::geodesy::{Geodetic, LocalFrame};
use crate::realism::{AhrsError, BaroDrift, GimbalError, GpsDropouts, GpsError, Realism, Wind};

/// Gravity, m/s^2.
pub const GRAVITY: f64 = 9.806_65;

/// Gimbal limits, all in degrees and degrees per second.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GimbalParams {
    /// Lowest pitch (looking down), degrees.
    pub pitch_min_deg: f64,
    /// Highest pitch (looking up), degrees.
    pub pitch_max_deg: f64,
    /// Yaw range relative to the body, degrees.
    pub yaw_min_deg: f64,
    /// Yaw range relative to the body, degrees.
    pub yaw_max_deg: f64,
    /// Maximum slew rate on each axis, degrees per second.
    pub max_rate_deg_s: f64,
}

impl Default for GimbalParams {
    fn default() -> Self {
        Self {
            pitch_min_deg: -90.0,
            pitch_max_deg: 30.0,
            yaw_min_deg: -180.0,
            yaw_max_deg: 180.0,
            max_rate_deg_s: 90.0,
        }
    }
}

/// The GPS bias: true position = reported position + bias, each axis a
/// first-order Gauss-Markov process (stationary standard deviation sigma,
/// correlation time tau) starting at zero. The same model and step as the
/// closed-loop scenario's disturbance (`shotpilot::simulator::scenario`,
/// which uses this type). Off (both sigmas zero) by default.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpsBiasParams {
    /// Horizontal standard deviation per axis (north, east), m.
    pub sigma_xy_m: f64,
    /// Vertical standard deviation, m.
    pub sigma_z_m: f64,
    /// Correlation time, s (0: the bias never moves from zero).
    pub tau_s: f64,
    /// Seed of the bias's random walk.
    pub seed: u64,
}

impl Default for GpsBiasParams {
    fn default() -> Self {
        Self {
            sigma_xy_m: 0.0,
            sigma_z_m: 0.0,
            tau_s: 120.0,
            seed: 0,
        }
    }
}

impl GpsBiasParams {
    /// True when the bias can move away from zero.
    pub fn enabled(&self) -> bool {
        (self.sigma_xy_m > 0.0 || self.sigma_z_m > 0.0) && self.tau_s > 0.0
    }

    /// Why these numbers are refused, if they are: the sigmas must be finite
    /// and >= 0, tau finite and >= 0. Returns the field and the reason.
    pub fn check(&self) -> Result<(), (&'static str, &'static str)> {
        if !(self.sigma_xy_m.is_finite() && self.sigma_xy_m >= 0.0) {
            return Err(("sigma_xy_m", "must be finite and >= 0 m"));
        }
        if !(self.sigma_z_m.is_finite() && self.sigma_z_m >= 0.0) {
            return Err(("sigma_z_m", "must be finite and >= 0 m"));
        }
        if !(self.tau_s.is_finite() && self.tau_s >= 0.0) {
            return Err(("tau_s", "must be finite and >= 0 s"));
        }
        Ok(())
    }
}

/// A GPS bias drifting as a first-order Gauss-Markov process: each step of
/// `dt` does `b += -b dt/tau + sigma sqrt(2 dt/tau) n` per axis with `n`
/// standard normal (the Euler step of `db = -b/tau dt + sigma sqrt(2/tau)
/// dW`, whose stationary deviation is sigma).
#[derive(Debug, Clone)]
pub struct GpsBias {
    params: GpsBiasParams,
    bias: Vector3<f64>,
    rng: SmallRng,
}

impl GpsBias {
    /// A bias at zero, its walk seeded by `params.seed`.
    pub fn new(params: GpsBiasParams) -> Self {
        Self {
            params,
            bias: Vector3::zeros(),
            rng: SmallRng::seed_from_u64(params.seed),
        }
    }

    /// The parameters.
    pub fn params(&self) -> &GpsBiasParams {
        &self.params
    }

    /// Advance by `dt` seconds (nothing when switched off or `dt` is not a
    /// positive finite number).
    pub fn step(&mut self, dt: f64) {
        let p = self.params;
        if !(p.enabled() && dt.is_finite() && dt > 0.0) {
            return;
        }
        let a = dt / p.tau_s;
        let k = (2.0 * a).sqrt();
        let (gx, gy, gz) = (
            gauss(&mut self.rng),
            gauss(&mut self.rng),
            gauss(&mut self.rng),
        );
        self.bias += Vector3::new(
            -self.bias.x * a + p.sigma_xy_m * k * gx,
            -self.bias.y * a + p.sigma_xy_m * k * gy,
            -self.bias.z * a + p.sigma_z_m * k * gz,
        );
    }

    /// The bias now (NED, m): true position = reported position + bias.
    pub fn bias(&self) -> Vector3<f64> {
        self.bias
    }
}

/// A standard normal draw (Box-Muller).
fn gauss(rng: &mut SmallRng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random_range(0.0..1.0);
    (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
}

/// Every tunable number of the vehicle model.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleParams {
    /// Home position (origin of the local NED frame).
    pub home: Geodetic,
    /// Horizontal speed limit, m/s (PX4 MPC_XY_CRUISE).
    pub max_speed_xy: f64,
    /// Climb speed limit, m/s (PX4 MPC_Z_VEL_MAX_UP).
    pub max_speed_up: f64,
    /// Descent speed limit, m/s (PX4 MPC_Z_VEL_MAX_DN).
    pub max_speed_down: f64,
    /// Horizontal acceleration limit, m/s^2.
    pub max_accel_xy: f64,
    /// Vertical acceleration limit, m/s^2.
    pub max_accel_z: f64,
    /// Yaw rate limit, deg/s.
    pub max_yaw_rate_deg_s: f64,
    /// Position loop gain, 1/s.
    pub position_gain: f64,
    /// Yaw loop gain, 1/s.
    pub yaw_gain: f64,
    /// Velocity loop time constant, s.
    pub velocity_tau_s: f64,
    /// Fraction of the acceleration limit used when planning to brake.
    pub braking_fraction: f64,
    /// Landing descent speed, m/s (PX4 MPC_LAND_SPEED).
    pub land_speed: f64,
    /// Camera position in the body frame (forward, right, down), metres.
    pub camera_offset_body: [f64; 3],
    /// Gimbal limits.
    pub gimbal: GimbalParams,
    /// GPS error (off by default).
    pub gps_bias: GpsBiasParams,
    /// Realism's vehicle disturbances (off by default).
    pub disturbances: VehicleDisturbances,
}

/// The vehicle effects of a [`Realism`] (see the module documentation),
/// each `None` when off, and the seed of their random processes.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct VehicleDisturbances {
    /// Wind with gusts.
    pub wind: Option<Wind>,
    /// Gimbal stabilisation error and jitter.
    pub gimbal: Option<GimbalError>,
    /// GNSS bias and noise.
    pub gps: Option<GpsError>,
    /// GNSS fix losses.
    pub gps_dropouts: Option<GpsDropouts>,
    /// Barometric height drift.
    pub baro: Option<BaroDrift>,
    /// The reported attitude's error.
    pub ahrs: Option<AhrsError>,
    /// Seed of every process above.
    pub seed: u64,
}

impl VehicleDisturbances {
    /// The vehicle effects of `realism`, seeded by `seed`.
    pub fn from_realism(realism: &Realism, seed: u64) -> Self {
        let v = &realism.vehicle;
        Self {
            wind: v.wind,
            gimbal: v.gimbal,
            gps: v.gps,
            gps_dropouts: v.gps_dropouts,
            baro: v.baro,
            ahrs: v.ahrs,
            seed,
        }
    }

    /// True when every effect is off.
    pub fn is_off(&self) -> bool {
        self.wind.is_none()
            && self.gimbal.is_none()
            && self.gps.is_none()
            && self.gps_dropouts.is_none()
            && self.baro.is_none()
            && self.ahrs.is_none()
    }
}

/// The running state of [`VehicleDisturbances`].
#[derive(Debug, Clone)]
struct DisturbanceState {
    wind: Option<WindField>,
    /// Integral of the velocity loop (m/s^2), compensating the wind.
    wind_integral: Vector3<f64>,
    gimbal: Option<GimbalJitter>,
    sensors: SensorErrors,
}

impl DisturbanceState {
    fn new(d: &VehicleDisturbances) -> Self {
        Self {
            wind: d.wind.map(|w| WindField::new(w, d.seed)),
            wind_integral: Vector3::zeros(),
            gimbal: d.gimbal.map(|g| GimbalJitter::new(g, d.seed)),
            sensors: SensorErrors::new(d),
        }
    }

    /// Advance the GNSS and barometer processes to time `t` by `dt`.
    fn step_sensors(&mut self, t: f64, dt: f64) {
        self.sensors.step(t, dt);
    }

    /// True position minus the estimate, NED m.
    fn position_error(&self) -> Vector3<f64> {
        self.sensors.gnss_error() + Vector3::new(0.0, 0.0, self.sensors.baro_error())
    }
}

/// The autopilot estimator's fusion of the receiver's fix with its IMU,
/// as seen by a slow receiver error: a second-order low-pass of natural
/// frequency `1 / tau` and damping `1 / sqrt 2` (the steady state of a
/// Kalman filter on a double integrator: PX4 EKF2's defaults, GPS position
/// noise 0.5 m at 5 Hz against accelerometer noise 0.35 m/s^2, give a
/// natural frequency near (q / r)^(1/4) = 1.25 rad/s, tau 0.8 s).
#[derive(Debug, Clone, Copy, Default)]
struct Fusion {
    /// The error the vehicle flies with, m.
    y: Vector3<f64>,
    /// Its rate, m/s.
    v: Vector3<f64>,
}

impl Fusion {
    /// Follow `x` (held over the step) for `dt` seconds: semi-implicit
    /// Euler in sub-steps of at most `tau / 20`; `tau <= 0` passes `x` on.
    fn step(&mut self, x: Vector3<f64>, tau: f64, dt: f64) {
        if !(tau > 0.0 && tau.is_finite()) {
            self.y = x;
            self.v = Vector3::zeros();
            return;
        }
        if !(dt.is_finite() && dt > 0.0) {
            return;
        }
        let w = 1.0 / tau;
        let n = (dt / (0.05 * tau)).ceil().clamp(1.0, 10_000.0) as usize;
        let h = dt / n as f64;
        for _ in 0..n {
            let a = (x - self.y) * (w * w) - self.v * (std::f64::consts::SQRT_2 * w);
            self.v += a * h;
            self.y += self.v * h;
        }
    }
}

/// The GNSS and barometer error processes of [`VehicleDisturbances`]
/// (`gps`, `gps_dropouts`, `baro`): what the vehicle flies on and what a
/// rendered dataset's `telemetry.txt` reports. Seeded by the disturbances'
/// seed, so a render and a live flight with the same seed see the same
/// errors at the same times.
#[derive(Debug, Clone)]
pub struct SensorErrors {
    d: VehicleDisturbances,
    gps_bias: Option<GpsBias>,
    /// The bias as the estimator's fusion passes it on (`gps.fusion_tau_s`).
    fused_bias: Fusion,
    gps_noise: Option<GpsBias>,
    /// Fix lost until this time (s on the vehicle's clock).
    lost_until: Option<f64>,
    /// Next fix loss starts at this time.
    next_loss: f64,
    /// Drift of the estimate while the fix is lost, m.
    drift: Vector3<f64>,
    /// Barometric height error, m (down positive: true z = estimate z + it).
    baro: f64,
    /// The reported attitude's slow error (roll, pitch, yaw), degrees.
    ahrs_slow: Option<GpsBias>,
    /// The reported attitude's fast noise (roll, pitch, yaw), degrees.
    ahrs_noise: Option<GpsBias>,
    rng: SmallRng,
}

impl SensorErrors {
    /// The processes of `d` at time zero (all errors zero).
    pub fn new(d: &VehicleDisturbances) -> Self {
        let mut rng = SmallRng::seed_from_u64(d.seed ^ 0x0DD5_EED5);
        let gm = |sxy: f64, sz: f64, tau: f64, salt: u64| {
            GpsBias::new(GpsBiasParams {
                sigma_xy_m: sxy,
                sigma_z_m: sz,
                tau_s: tau,
                seed: d.seed ^ salt,
            })
        };
        let next_loss = d
            .gps_dropouts
            .map_or(f64::INFINITY, |g| exponential(&mut rng, g.mean_interval_s));
        Self {
            d: *d,
            gps_bias: d
                .gps
                .map(|g| gm(g.bias_sigma_xy_m, g.bias_sigma_z_m, g.bias_tau_s, 0xB1A5)),
            fused_bias: Fusion::default(),
            gps_noise: d
                .gps
                .map(|g| gm(g.noise_sigma_m, g.noise_sigma_m, g.noise_tau_s, 0x4015E)),
            lost_until: None,
            next_loss,
            drift: Vector3::zeros(),
            baro: 0.0,
            // Own seeds: switching `ahrs` on leaves every other process's
            // draws as they were.
            ahrs_slow: d
                .ahrs
                .map(|a| gm(a.tilt_sigma_deg, a.yaw_sigma_deg, a.tau_s, 0xA445)),
            ahrs_noise: d
                .ahrs
                .map(|a| gm(a.noise_deg, a.noise_deg, AHRS_NOISE_TAU_S, 0xA4A5)),
            rng,
        }
    }

    /// Advance the GNSS and barometer processes to time `t` by `dt`.
    pub fn step(&mut self, t: f64, dt: f64) {
        let d = self.d;
        if let Some(b) = &mut self.gps_bias {
            b.step(dt);
            let tau = d.gps.map_or(0.0, |g| g.fusion_tau_s);
            self.fused_bias.step(b.bias(), tau, dt);
        }
        if let Some(n) = &mut self.gps_noise {
            n.step(dt);
        }
        for a in [&mut self.ahrs_slow, &mut self.ahrs_noise]
            .into_iter()
            .flatten()
        {
            a.step(dt);
        }
        if let Some(g) = d.gps_dropouts {
            match self.lost_until {
                Some(end) if t >= end => {
                    // The fix is back: the estimator resets onto it.
                    self.lost_until = None;
                    self.drift = Vector3::zeros();
                    self.next_loss = t + exponential(&mut self.rng, g.mean_interval_s);
                }
                Some(_) => {
                    let k = g.drift_m_per_sqrt_s * dt.sqrt();
                    self.drift +=
                        Vector3::new(k * gauss(&mut self.rng), k * gauss(&mut self.rng), 0.0);
                }
                None if t >= self.next_loss => {
                    self.lost_until = Some(t + exponential(&mut self.rng, g.mean_duration_s));
                }
                None => {}
            }
        }
        if let Some(b) = d.baro {
            // A random walk of `rate` metres per minute: sigma over a
            // minute is the rate.
            self.baro += b.rate_m_per_min * (dt / 60.0).sqrt() * gauss(&mut self.rng);
        }
    }

    /// True position minus the GNSS estimate, NED m: bias, noise and the
    /// drift while the fix is lost (no barometer).
    pub fn gnss_error(&self) -> Vector3<f64> {
        let mut e = self.drift;
        if self.gps_bias.is_some() {
            e += self.fused_bias.y;
        }
        if let Some(n) = &self.gps_noise {
            e += n.bias();
        }
        e
    }

    /// Barometric height error, m, down positive: true z = barometric z
    /// + it (so the reported altitude is the true one plus it).
    pub fn baro_error(&self) -> f64 {
        self.baro
    }

    /// The reported attitude minus the true one, (roll, pitch, yaw)
    /// degrees: the slow error plus the noise of `ahrs` (zero without it).
    pub fn attitude_error_deg(&self) -> Vector3<f64> {
        [&self.ahrs_slow, &self.ahrs_noise]
            .into_iter()
            .flatten()
            .map(|a| a.bias())
            .sum()
    }

    /// False while the GNSS fix is lost.
    pub fn fix(&self) -> bool {
        self.lost_until.is_none()
    }

    /// The receiver's reported 1-sigma accuracy, (horizontal per axis,
    /// vertical) m: the configured bias and noise sigmas combined (what a
    /// receiver's hAcc/vAcc estimate stands for); zero without `gps`.
    pub fn reported_accuracy(&self) -> (f64, f64) {
        self.d.gps.map_or((0.0, 0.0), |g| {
            (
                g.bias_sigma_xy_m.hypot(g.noise_sigma_m),
                g.bias_sigma_z_m.hypot(g.noise_sigma_m),
            )
        })
    }
}

/// Correlation time of the reported attitude's fast noise, s (the
/// estimator's output is filtered; also long enough against a render's
/// frame interval for the process's Euler step).
const AHRS_NOISE_TAU_S: f64 = 0.5;

/// An exponential draw of mean `mean`.
fn exponential(rng: &mut SmallRng, mean: f64) -> f64 {
    let u: f64 = rng.random_range(1e-12..1.0);
    -mean * u.ln()
}

impl Default for VehicleParams {
    fn default() -> Self {
        Self {
            home: Geodetic {
                lat_deg: 47.397_742,
                lon_deg: 8.545_594,
                alt_m: 488.0,
            },
            max_speed_xy: 5.0,
            max_speed_up: 3.0,
            max_speed_down: 1.5,
            max_accel_xy: 3.0,
            max_accel_z: 3.0,
            max_yaw_rate_deg_s: 60.0,
            position_gain: 0.95,
            yaw_gain: 2.0,
            velocity_tau_s: 0.25,
            braking_fraction: 0.7,
            land_speed: 0.7,
            camera_offset_body: [0.10, 0.0, 0.08],
            gimbal: GimbalParams::default(),
            gps_bias: GpsBiasParams::default(),
            disturbances: VehicleDisturbances::default(),
        }
    }
}

/// What the controller is asked to do.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Setpoint {
    /// Motors off (only meaningful on the ground; in the air the vehicle
    /// falls under the vertical acceleration limit until it lands).
    Idle,
    /// Fly to a NED position, optionally turning to a yaw (radians), with an
    /// optional speed limit below the vehicle's own.
    Position {
        /// Target, local NED metres.
        p_ned: Vector3<f64>,
        /// Target yaw, radians from north; `None` keeps the current yaw.
        yaw: Option<f64>,
        /// Optional horizontal speed limit, m/s.
        max_speed: Option<f64>,
    },
    /// Fly a NED velocity with a yaw rate (rad/s).
    Velocity {
        /// Velocity, local NED m/s.
        v_ned: Vector3<f64>,
        /// Yaw rate, rad/s.
        yaw_rate: f64,
    },
    /// Descend at the landing speed over the current horizontal position.
    Land,
}

/// The simulated multicopter.
#[derive(Debug, Clone)]
pub struct Vehicle {
    params: VehicleParams,
    frame: LocalFrame,
    setpoint: Setpoint,
    p_ned: Vector3<f64>,
    v_ned: Vector3<f64>,
    a_ned: Vector3<f64>,
    yaw: f64,
    yaw_rate: f64,
    landed: bool,
    land_xy: Option<(f64, f64)>,
    gimbal_pitch: f64,
    gimbal_yaw: f64,
    gimbal_target_pitch: f64,
    gimbal_target_yaw: f64,
    gimbal_rate: (f64, f64),
    gps_bias: GpsBias,
    /// The vehicle's clock (sum of steps), s.
    clock: f64,
    /// Thrust acceleration the controller commands (roll and pitch follow
    /// it), NED m/s^2; equal to `a_ned` without wind.
    a_cmd: Vector3<f64>,
    dist: DisturbanceState,
}

/// Wraps an angle in radians to `[-π, π]`: an odd multiple of π gives `-π`
/// (the daemon's `angle::wrap_pi` gives `+π`; the crates share no code).
/// The simulator's one copy, for its vehicle, autopilot and script.
pub fn wrap_pi(a: f64) -> f64 {
    let mut x = (a + std::f64::consts::PI) % std::f64::consts::TAU;
    if x < 0.0 {
        x += std::f64::consts::TAU;
    }
    x - std::f64::consts::PI
}

/// Move `x` toward `target` by at most `step`.
fn slew(x: f64, target: f64, step: f64) -> f64 {
    x + (target - x).clamp(-step, step)
}

/// The rotation taking camera axes (x right, y down, z forward) to body
/// axes (x forward, y right, z down) for a gimbal at zero angles.
fn body_from_cam_base() -> Rotation3<f64> {
    Rotation3::from_matrix_unchecked(Matrix3::new(
        0.0, 0.0, 1.0, //
        1.0, 0.0, 0.0, //
        0.0, 1.0, 0.0,
    ))
}

impl Vehicle {
    /// A vehicle landed at home, disarmed, yaw north, gimbal level.
    pub fn new(params: VehicleParams) -> Self {
        Self {
            frame: LocalFrame::new(params.home),
            params,
            setpoint: Setpoint::Idle,
            p_ned: Vector3::zeros(),
            v_ned: Vector3::zeros(),
            a_ned: Vector3::zeros(),
            yaw: 0.0,
            yaw_rate: 0.0,
            landed: true,
            land_xy: None,
            gimbal_pitch: 0.0,
            gimbal_yaw: 0.0,
            gimbal_target_pitch: 0.0,
            gimbal_target_yaw: 0.0,
            gimbal_rate: (0.0, 0.0),
            gps_bias: GpsBias::new(params.gps_bias),
            clock: 0.0,
            a_cmd: Vector3::zeros(),
            dist: DisturbanceState::new(&params.disturbances),
        }
    }

    /// The parameters.
    pub fn params(&self) -> &VehicleParams {
        &self.params
    }

    /// The local tangent frame at home.
    pub fn frame(&self) -> &LocalFrame {
        &self.frame
    }

    /// Place the vehicle (tests, scripted starts). It is landed if z >= 0.
    pub fn teleport(&mut self, p_ned: Vector3<f64>, yaw: f64) {
        self.p_ned = Vector3::new(p_ned.x, p_ned.y, p_ned.z.min(0.0));
        self.v_ned = Vector3::zeros();
        self.a_ned = Vector3::zeros();
        self.a_cmd = Vector3::zeros();
        self.yaw = wrap_pi(yaw);
        self.landed = self.p_ned.z >= 0.0;
    }

    /// Set what the controller does.
    pub fn set_setpoint(&mut self, sp: Setpoint) {
        if !matches!(sp, Setpoint::Land) {
            self.land_xy = None;
        }
        self.setpoint = sp;
    }

    /// The current setpoint.
    pub fn setpoint(&self) -> Setpoint {
        self.setpoint
    }

    /// Point the gimbal (degrees; pitch positive up, yaw relative to the
    /// body, positive right). Targets are clamped to the gimbal's ranges;
    /// NaN leaves an axis unchanged.
    pub fn set_gimbal_target(&mut self, pitch_deg: f64, yaw_deg: f64) {
        let g = &self.params.gimbal;
        if pitch_deg.is_finite() {
            self.gimbal_target_pitch = pitch_deg
                .clamp(g.pitch_min_deg, g.pitch_max_deg)
                .to_radians();
        }
        if yaw_deg.is_finite() {
            let y = wrap_pi(yaw_deg.to_radians()).to_degrees();
            self.gimbal_target_yaw = y.clamp(g.yaw_min_deg, g.yaw_max_deg).to_radians();
        }
    }

    /// Put the gimbal at an attitude at once (scripted starts, before the
    /// first frame), clamped to its ranges.
    pub fn snap_gimbal(&mut self, pitch_deg: f64, yaw_deg: f64) {
        self.set_gimbal_target(pitch_deg, yaw_deg);
        self.gimbal_pitch = self.gimbal_target_pitch;
        self.gimbal_yaw = self.gimbal_target_yaw;
        self.gimbal_rate = (0.0, 0.0);
    }

    /// Advance the model by `dt` seconds.
    pub fn step(&mut self, dt: f64) {
        if dt.is_nan() || dt <= 0.0 || !dt.is_finite() {
            return;
        }
        let p = self.params;
        let (v_des, yaw_rate_des, idle) = match self.setpoint {
            Setpoint::Idle => (Vector3::zeros(), 0.0, true),
            Setpoint::Position {
                p_ned,
                yaw,
                max_speed,
            } => {
                let v = self.position_velocity(&p_ned, max_speed);
                let yr = match yaw {
                    Some(y) => p.yaw_gain * wrap_pi(y - self.yaw),
                    None => 0.0,
                };
                (v, yr, false)
            }
            Setpoint::Velocity { v_ned, yaw_rate } => (v_ned, yaw_rate, false),
            Setpoint::Land => {
                let (x, y) = *self.land_xy.get_or_insert((self.p_ned.x, self.p_ned.y));
                let mut v = self.position_velocity(&Vector3::new(x, y, self.p_ned.z), None);
                v.z = p.land_speed;
                (v, 0.0, false)
            }
        };
        let max_yr = p.max_yaw_rate_deg_s.to_radians();
        if idle && self.landed {
            self.v_ned = Vector3::zeros();
            self.a_ned = Vector3::zeros();
            self.a_cmd = Vector3::zeros();
            self.yaw_rate = 0.0;
        } else {
            let v_des = if idle {
                // Motors off in the air: fall (limited by the vertical
                // acceleration limit, a stand-in for a crash landing).
                Vector3::new(0.0, 0.0, p.max_speed_down * 4.0)
            } else {
                v_des
            };
            let v_err = v_des - self.v_ned;
            let mut a = v_err / p.velocity_tau_s.max(1e-3);
            let a_xy = (a.x * a.x + a.y * a.y).sqrt();
            if a_xy > p.max_accel_xy {
                let s = p.max_accel_xy / a_xy;
                a.x *= s;
                a.y *= s;
            }
            a.z = a.z.clamp(-p.max_accel_z, p.max_accel_z);
            self.a_ned = a;
            self.a_cmd = a;
            if let (Some(wind), Some(w)) = (&self.dist.wind, p.disturbances.wind) {
                // The wind pushes, the loop's integral leans against it
                // (the thrust it commands on top of the limited term).
                let drag = wind.drag_accel(self.clock, &self.v_ned);
                self.a_cmd = a + self.dist.wind_integral;
                self.dist.wind_integral += v_err * (w.integral_gain * dt);
                a += self.dist.wind_integral + drag;
                self.a_ned = a;
            }
            self.v_ned += a * dt;
            self.p_ned += self.v_ned * dt;
            self.yaw_rate = yaw_rate_des.clamp(-max_yr, max_yr);
            self.yaw = wrap_pi(self.yaw + self.yaw_rate * dt);
            if self.p_ned.z >= 0.0 {
                self.p_ned.z = 0.0;
                if self.v_ned.z > 0.0 {
                    self.v_ned.z = 0.0;
                }
                // Touching the ground while not climbing: landed.
                let climbing = v_des.z < -0.05;
                if !climbing {
                    self.v_ned = Vector3::zeros();
                    self.a_ned = Vector3::zeros();
                    self.a_cmd = Vector3::zeros();
                    self.landed = true;
                }
            } else if self.p_ned.z < -0.05 {
                self.landed = false;
            }
        }
        // Gimbal.
        let step = p.gimbal.max_rate_deg_s.to_radians() * dt;
        let (op, oy) = (self.gimbal_pitch, self.gimbal_yaw);
        self.gimbal_pitch = slew(self.gimbal_pitch, self.gimbal_target_pitch, step);
        self.gimbal_yaw = slew(self.gimbal_yaw, self.gimbal_target_yaw, step);
        self.gimbal_rate = ((self.gimbal_pitch - op) / dt, (self.gimbal_yaw - oy) / dt);
        self.gps_bias.step(dt);
        self.clock += dt;
        let d = p.disturbances;
        if !d.is_off() {
            if self.landed {
                // On the ground the integrator sits converged on the wind
                // at rest, ready for take-off.
                if let Some(wind) = &self.dist.wind {
                    self.dist.wind_integral = -wind.drag_accel(self.clock, &Vector3::zeros());
                }
            }
            self.dist.step_sensors(self.clock, dt);
        }
    }

    fn position_velocity(&self, target: &Vector3<f64>, max_speed: Option<f64>) -> Vector3<f64> {
        let p = &self.params;
        let e = target - self.p_ned;
        let d_xy = (e.x * e.x + e.y * e.y).sqrt();
        let vmax_xy = max_speed.map_or(p.max_speed_xy, |m| m.min(p.max_speed_xy).max(0.1));
        let brake = |a: f64, d: f64| (2.0 * a * p.braking_fraction * d).sqrt();
        let s_xy = vmax_xy
            .min(p.position_gain * d_xy)
            .min(brake(p.max_accel_xy, d_xy));
        let mut v = if d_xy > 1e-9 {
            Vector3::new(e.x / d_xy * s_xy, e.y / d_xy * s_xy, 0.0)
        } else {
            Vector3::zeros()
        };
        let d_z = e.z.abs();
        let vmax_z = if e.z < 0.0 {
            p.max_speed_up
        } else {
            p.max_speed_down
        };
        let s_z = vmax_z
            .min(p.position_gain * d_z)
            .min(brake(p.max_accel_z, d_z));
        v.z = e.z.signum() * s_z;
        v
    }

    /// Position, local NED metres: what the controller flies and the
    /// autopilot reports (the GPS solution; the true position adds
    /// [`Self::gps_bias`]).
    pub fn p_ned(&self) -> Vector3<f64> {
        self.p_ned
    }
    /// The GPS bias now, NED metres (zero when switched off).
    pub fn gps_bias(&self) -> Vector3<f64> {
        self.gps_bias.bias()
    }
    /// Where the vehicle truly is: [`Self::p_ned`] plus the GPS bias and
    /// the realism's position error ([`Self::position_error`]).
    pub fn true_p_ned(&self) -> Vector3<f64> {
        self.p_ned + self.position_error()
    }
    /// True position minus the estimate, NED m: the GPS bias plus the
    /// realism's GNSS bias and noise, the drift during a fix loss and the
    /// barometric height drift (zero with every effect off).
    pub fn position_error(&self) -> Vector3<f64> {
        let b = self.gps_bias.bias();
        if self.params.disturbances.is_off() {
            b
        } else {
            b + self.dist.position_error()
        }
    }
    /// The receiver's reported 1-sigma accuracy, (horizontal per axis,
    /// vertical) m: the GPS bias's and the realism's GNSS error sigmas
    /// combined (zero with both off).
    pub fn gps_reported_accuracy(&self) -> (f64, f64) {
        let b = &self.params.gps_bias;
        let (h, v) = if self.params.disturbances.is_off() {
            (0.0, 0.0)
        } else {
            self.dist.sensors.reported_accuracy()
        };
        (h.hypot(b.sigma_xy_m), v.hypot(b.sigma_z_m))
    }
    /// False while the GNSS fix is lost (realism `gps_dropouts`).
    pub fn gps_fix(&self) -> bool {
        self.dist.sensors.fix()
    }
    /// The vehicle's clock: seconds of [`Self::step`] so far.
    pub fn clock(&self) -> f64 {
        self.clock
    }
    /// The wind velocity now, NED m/s (None without wind).
    pub fn wind(&self) -> Option<Vector3<f64>> {
        self.dist.wind.as_ref().map(|w| w.velocity(self.clock))
    }
    /// Velocity, local NED m/s.
    pub fn v_ned(&self) -> Vector3<f64> {
        self.v_ned
    }
    /// Commanded acceleration, local NED m/s^2.
    pub fn a_ned(&self) -> Vector3<f64> {
        self.a_ned
    }
    /// Yaw (heading), radians from north, in [-pi, pi).
    pub fn yaw(&self) -> f64 {
        self.yaw
    }
    /// Yaw rate, rad/s.
    pub fn yaw_rate(&self) -> f64 {
        self.yaw_rate
    }
    /// True when on the ground.
    pub fn landed(&self) -> bool {
        self.landed
    }
    /// Roll and pitch (radians) implied by the commanded horizontal
    /// acceleration (the thrust's tilt; into the wind when it blows).
    pub fn roll_pitch(&self) -> (f64, f64) {
        let (s, c) = self.yaw.sin_cos();
        let a_fwd = c * self.a_cmd.x + s * self.a_cmd.y;
        let a_right = -s * self.a_cmd.x + c * self.a_cmd.y;
        let roll = (a_right / GRAVITY).atan();
        let pitch = -(a_fwd / GRAVITY).atan();
        (roll, pitch)
    }
    /// Gimbal pitch and yaw (relative to the body), radians.
    pub fn gimbal_angles(&self) -> (f64, f64) {
        (self.gimbal_pitch, self.gimbal_yaw)
    }
    /// Gimbal pitch and yaw rates, rad/s.
    pub fn gimbal_rates(&self) -> (f64, f64) {
        self.gimbal_rate
    }
    /// True when the gimbal has reached its target within `tol_deg`.
    pub fn gimbal_settled(&self, tol_deg: f64) -> bool {
        let t = tol_deg.to_radians();
        (self.gimbal_pitch - self.gimbal_target_pitch).abs() <= t
            && (self.gimbal_yaw - self.gimbal_target_yaw).abs() <= t
    }

    /// Body attitude (roll, pitch, yaw) as a rotation world <- body.
    pub fn world_from_body_rotation(&self) -> UnitQuaternion<f64> {
        let (roll, pitch) = self.roll_pitch();
        UnitQuaternion::from_euler_angles(roll, pitch, self.yaw)
    }

    /// Pose of the body: maps body coordinates to local NED.
    pub fn world_from_body(&self) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::from(self.p_ned),
            self.world_from_body_rotation(),
        )
    }

    /// Gimbal attitude in the earth frame (zero roll, stabilised): the
    /// rotation world <- gimbal, where the gimbal frame is body-like
    /// (x along the optical axis, y right, z down).
    pub fn world_from_gimbal_rotation(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_euler_angles(0.0, self.gimbal_pitch, self.yaw + self.gimbal_yaw)
    }

    /// Gimbal attitude relative to the body's yaw-only frame (the quaternion
    /// GIMBAL_DEVICE_ATTITUDE_STATUS reports with the yaw in vehicle frame).
    pub fn gimbal_rotation_in_vehicle_frame(&self) -> UnitQuaternion<f64> {
        UnitQuaternion::from_euler_angles(0.0, self.gimbal_pitch, self.gimbal_yaw)
    }

    /// Pose of the camera (x right, y down, z forward) in local NED where
    /// the vehicle's GPS says it is (the true pose is
    /// [`Self::true_world_from_cam`]).
    pub fn world_from_cam(&self) -> Isometry3<f64> {
        let r = self.world_from_gimbal_rotation()
            * UnitQuaternion::from_rotation_matrix(&body_from_cam_base());
        let yaw_only = UnitQuaternion::from_euler_angles(0.0, 0.0, self.yaw);
        let o = self.params.camera_offset_body;
        let t = self.p_ned + yaw_only * Vector3::new(o[0], o[1], o[2]);
        Isometry3::from_parts(Translation3::from(t), r)
    }

    /// The camera's true pose (GPS bias included): the pose the renderer
    /// draws from.
    pub fn true_world_from_cam(&self) -> Isometry3<f64> {
        let wfc = self.true_world_from_cam_stabilised();
        match &self.dist.gimbal {
            Some(g) => g.apply(&wfc, self.clock),
            None => wfc,
        }
    }

    /// The camera's true position with the gimbal exactly where it is
    /// commanded (no pointing error): [`Self::true_world_from_cam`] is this
    /// turned by [`Self::gimbal_error`] at [`Self::clock`].
    pub fn true_world_from_cam_stabilised(&self) -> Isometry3<f64> {
        let mut wfc = self.world_from_cam();
        wfc.translation.vector += self.position_error();
        wfc
    }

    /// The gimbal's pointing error process (realism `gimbal`), if on.
    pub fn gimbal_error(&self) -> Option<&GimbalJitter> {
        self.dist.gimbal.as_ref()
    }

    /// Position in WGS84, as the GPS reports it.
    pub fn geodetic(&self) -> Geodetic {
        self.frame.ned_to_geodetic(&self.p_ned)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap_pi_at_the_edges() {
        use std::f64::consts::{PI, TAU};
        assert_eq!(wrap_pi(PI), -PI);
        assert_eq!(wrap_pi(-PI), -PI);
        assert_eq!(wrap_pi(0.0), 0.0);
        assert!(wrap_pi(f64::NAN).is_nan());
        for i in -500..500 {
            let a = f64::from(i) * 0.37;
            let w = wrap_pi(a);
            assert!((-PI..=PI).contains(&w), "{a} -> {w}");
            let turns = (a - w) / TAU;
            assert!((turns - turns.round()).abs() < 1e-12, "{a} -> {w}");
        }
    }

    fn run(v: &mut Vehicle, seconds: f64, dt: f64, mut each: impl FnMut(&Vehicle)) {
        let n = (seconds / dt).round() as usize;
        for _ in 0..n {
            v.step(dt);
            each(v);
        }
    }

    #[test]
    fn reaches_a_position_without_breaking_speed_or_acceleration_limits() {
        let mut v = Vehicle::new(VehicleParams::default());
        v.teleport(Vector3::new(0.0, 0.0, -10.0), 0.0);
        let target = Vector3::new(60.0, -30.0, -20.0);
        v.set_setpoint(Setpoint::Position {
            p_ned: target,
            yaw: Some(1.0),
            max_speed: None,
        });
        let p = *v.params();
        let mut max_xy = 0.0f64;
        let mut max_up = 0.0f64;
        let mut prev = v.v_ned();
        let mut max_a = 0.0f64;
        run(&mut v, 40.0, 0.01, |v| {
            let vel = v.v_ned();
            max_xy = max_xy.max((vel.x * vel.x + vel.y * vel.y).sqrt());
            max_up = max_up.max(-vel.z);
            let dv = (vel - prev) / 0.01;
            max_a = max_a.max((dv.x * dv.x + dv.y * dv.y).sqrt());
            prev = vel;
        });
        assert!((v.p_ned() - target).norm() < 0.05, "{}", v.p_ned());
        assert!(max_xy <= p.max_speed_xy + 1e-9 && max_xy > 0.9 * p.max_speed_xy);
        assert!(max_up <= p.max_speed_up + 1e-9);
        assert!(max_a <= p.max_accel_xy + 1e-6, "{max_a}");
        assert!((v.yaw() - 1.0).abs() < 1e-3);
    }

    #[test]
    fn takeoff_then_land_ends_landed_at_ground() {
        let mut v = Vehicle::new(VehicleParams::default());
        assert!(v.landed());
        v.set_setpoint(Setpoint::Position {
            p_ned: Vector3::new(0.0, 0.0, -5.0),
            yaw: None,
            max_speed: None,
        });
        run(&mut v, 10.0, 0.02, |_| {});
        assert!(!v.landed());
        assert!((v.p_ned().z + 5.0).abs() < 0.05);
        v.set_setpoint(Setpoint::Land);
        let mut max_down = 0.0f64;
        run(&mut v, 15.0, 0.02, |v| max_down = max_down.max(v.v_ned().z));
        assert!(v.landed());
        assert_eq!(v.p_ned().z, 0.0);
        assert!(max_down <= 0.7 + 1e-9);
    }

    #[test]
    fn gimbal_is_rate_limited_and_clamped() {
        let mut v = Vehicle::new(VehicleParams::default());
        v.set_gimbal_target(-120.0, 0.0);
        v.step(0.5);
        assert!((v.gimbal_angles().0.to_degrees() + 45.0).abs() < 1e-9);
        v.step(1.0);
        assert!((v.gimbal_angles().0.to_degrees() + 90.0).abs() < 1e-9);
        v.set_gimbal_target(f64::NAN, 30.0);
        v.step(1.0);
        assert!((v.gimbal_angles().0.to_degrees() + 90.0).abs() < 1e-9);
        assert!((v.gimbal_angles().1.to_degrees() - 30.0).abs() < 1e-9);
    }

    #[test]
    fn camera_axes_follow_yaw_and_gimbal() {
        let mut v = Vehicle::new(VehicleParams {
            camera_offset_body: [0.0; 3],
            ..Default::default()
        });
        v.teleport(Vector3::new(1.0, 2.0, -10.0), std::f64::consts::FRAC_PI_2);
        // Level gimbal, yaw east: camera z (forward) is east, x (right) is
        // south, y (down) is down.
        let r = v.world_from_cam().rotation;
        assert!((r * Vector3::z() - Vector3::y()).norm() < 1e-12);
        assert!((r * Vector3::x() + Vector3::x()).norm() < 1e-12);
        assert!((r * Vector3::y() - Vector3::z()).norm() < 1e-12);
        // Pitch -90: camera looks down, image up (-y) points east.
        v.set_setpoint(Setpoint::Position {
            p_ned: Vector3::new(1.0, 2.0, -10.0),
            yaw: None,
            max_speed: None,
        });
        v.set_gimbal_target(-90.0, 0.0);
        v.step(2.0);
        let r = v.world_from_cam().rotation;
        assert!((r * Vector3::z() - Vector3::z()).norm() < 1e-9);
        assert!((r * -Vector3::y() - Vector3::y()).norm() < 1e-9);
        // A ground point below projects to the image centre.
        let cam_from_world = v.world_from_cam().inverse();
        let p_cam = cam_from_world * nalgebra::Point3::new(1.0, 2.0, 0.0);
        assert!(p_cam.x.abs() < 1e-9 && p_cam.y.abs() < 1e-9 && (p_cam.z - 10.0).abs() < 1e-9);
    }

    #[test]
    fn acceleration_tilts_the_body_forward() {
        let mut v = Vehicle::new(VehicleParams::default());
        v.teleport(Vector3::new(0.0, 0.0, -10.0), 0.0);
        v.set_setpoint(Setpoint::Velocity {
            v_ned: Vector3::new(5.0, 0.0, 0.0),
            yaw_rate: 0.0,
        });
        v.step(0.05);
        let (roll, pitch) = v.roll_pitch();
        assert!(pitch < -0.2 && roll.abs() < 1e-9, "{roll} {pitch}");
    }

    #[test]
    fn gps_bias_is_off_by_default_and_moves_the_true_camera_only() {
        let mut v = Vehicle::new(VehicleParams::default());
        v.teleport(Vector3::new(5.0, 0.0, -10.0), 0.0);
        v.set_setpoint(Setpoint::Position {
            p_ned: Vector3::new(5.0, 0.0, -10.0),
            yaw: None,
            max_speed: None,
        });
        run(&mut v, 30.0, 0.02, |_| {});
        assert_eq!(v.gps_bias(), Vector3::zeros());
        assert_eq!(v.true_world_from_cam(), v.world_from_cam());

        let bias = GpsBiasParams {
            sigma_xy_m: 1.5,
            sigma_z_m: 0.5,
            tau_s: 120.0,
            seed: 3,
        };
        let mut v = Vehicle::new(VehicleParams {
            gps_bias: bias,
            ..Default::default()
        });
        v.teleport(Vector3::new(5.0, 0.0, -10.0), 0.0);
        v.set_setpoint(Setpoint::Position {
            p_ned: Vector3::new(5.0, 0.0, -10.0),
            yaw: None,
            max_speed: None,
        });
        run(&mut v, 30.0, 0.02, |_| {});
        // The controller holds the reported position; the camera is off by
        // the bias, which has moved from zero.
        assert!((v.p_ned() - Vector3::new(5.0, 0.0, -10.0)).norm() < 1e-3);
        let b = v.gps_bias();
        assert!(b.xy().norm() > 0.05, "{b}");
        let d = v.true_world_from_cam().translation.vector - v.world_from_cam().translation.vector;
        assert!((d - b).norm() < 1e-12);
        assert!((v.true_p_ned() - v.p_ned() - b).norm() < 1e-12);
        // Same seed, same walk.
        let mut a = GpsBias::new(bias);
        let mut c = GpsBias::new(bias);
        for _ in 0..100 {
            a.step(0.02);
            c.step(0.02);
        }
        assert_eq!(a.bias(), c.bias());
    }

    #[test]
    fn gps_bias_has_the_gauss_markov_deviation_and_correlation_time() {
        let p = GpsBiasParams {
            sigma_xy_m: 1.5,
            sigma_z_m: 0.5,
            tau_s: 10.0,
            seed: 11,
        };
        let mut b = GpsBias::new(p);
        let dt = 0.05;
        // Burn in 10 tau, then sample every second for 2000 tau (about
        // 1000 independent samples per axis: the deviation's standard error
        // is about 2 %).
        for _ in 0..(100.0 / dt) as usize {
            b.step(dt);
        }
        let mut xs = Vec::new();
        for _ in 0..20_000 {
            for _ in 0..(1.0 / dt).round() as usize {
                b.step(dt);
            }
            xs.push(b.bias());
        }
        let n = xs.len() as f64;
        let sd = |f: &dyn Fn(&Vector3<f64>) -> f64| {
            (xs.iter().map(|x| f(x).powi(2)).sum::<f64>() / n).sqrt()
        };
        let (sx, sy, sz) = (sd(&|x| x.x), sd(&|x| x.y), sd(&|x| x.z));
        assert!((sx / 1.5 - 1.0).abs() < 0.1, "{sx}");
        assert!((sy / 1.5 - 1.0).abs() < 0.1, "{sy}");
        assert!((sz / 0.5 - 1.0).abs() < 0.1, "{sz}");
        // Correlation at a lag of tau (10 samples): exp(-1) = 0.37.
        let lag = 10;
        let c: f64 = xs
            .iter()
            .zip(&xs[lag..])
            .map(|(a, b)| a.x * b.x + a.y * b.y)
            .sum::<f64>()
            / ((n - lag as f64) * (sx * sx + sy * sy));
        assert!((c - (-1f64).exp()).abs() < 0.06, "{c}");
    }

    #[test]
    fn geodetic_position_moves_north_when_flying_north() {
        let mut v = Vehicle::new(VehicleParams::default());
        v.teleport(Vector3::new(100.0, 0.0, -20.0), 0.0);
        let g = v.geodetic();
        let h = v.params().home;
        assert!((g.lat_deg - h.lat_deg - 100.0 / 111_200.0).abs() < 2e-5);
        assert!((g.alt_m - h.alt_m - 20.0).abs() < 0.01);
    }
}
