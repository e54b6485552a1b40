//! The effects' parameters: the camera's (blur, rolling shutter, exposure,
//! photometry, vignetting, noise, compression), the lighting's (sun, clouds) and
//! the vehicle's (wind, gimbal, GNSS, dropouts, baro, telemetry, video latency).

use super::sun::sun_position;
use crate::render::CloudShadows;

/// Motion blur: the frame integrates the scene over the exposure, sampled
/// at stratified times; the number of samples follows the image motion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotionBlur {
    /// Largest image motion between two sub-exposure samples, pixels.
    pub max_px_per_sample: f64,
    /// Most sub-exposure samples per frame.
    pub max_samples: usize,
}

/// Rolling shutter: row `y` of `h` is exposed `readout_s * y / (h - 1)`
/// after the first.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RollingShutter {
    /// Time from the first row's exposure to the last's, seconds.
    pub readout_s: f64,
}

/// Auto-exposure: each frame, the exposure (time x gain) moves towards the
/// one that brings the metered brightness of the last frame to the target,
/// by `1 - exp(-frame_dt / tau)` of the (log) way; the time is used first,
/// up to `max_exposure_s`, then the gain.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AutoExposure {
    /// Target of the centre-weighted mean linear signal (0..1; 0.18 is
    /// middle grey).
    pub target: f64,
    /// Time constant of the adaptation, seconds.
    pub tau_s: f64,
    /// Shortest exposure, seconds.
    pub min_exposure_s: f64,
    /// Longest exposure, seconds.
    pub max_exposure_s: f64,
    /// Highest analogue gain (1 = base ISO).
    pub max_gain: f64,
}

/// The camera's photometry (what an exposure means in light).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Photometry {
    /// Aperture, f-number.
    pub f_number: f64,
    /// Lens transmission, 0..1.
    pub lens_transmission: f64,
    /// Sensor exposure that saturates at base gain, lux seconds (ISO 100: 0.78).
    pub saturation_lux_s: f64,
    /// Exposure time used when auto-exposure is off (for motion blur),
    /// seconds; the brightness is then the renderer's own.
    pub fixed_exposure_s: f64,
    /// Display gamma of the camera's tone curve (the renderer's grey
    /// levels are display-referred with this gamma).
    pub display_gamma: f64,
}

impl Default for Photometry {
    fn default() -> Self {
        Self {
            f_number: 2.8,
            lens_transmission: 0.9,
            saturation_lux_s: 0.78,
            fixed_exposure_s: 1.0 / 1000.0,
            display_gamma: 2.2,
        }
    }
}

/// Vignetting: relative illumination falls as cos^n of the off-axis angle,
/// `n` set so the image corner receives `corner` of the centre's light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Vignetting {
    /// Relative illumination at the image corner, 0..1.
    pub corner: f64,
}

/// Sensor noise: photon shot noise (Poisson, variance = signal in
/// electrons) and read noise, per output pixel.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorNoise {
    /// Full-well capacity of one photosite, electrons.
    pub full_well_e: f64,
    /// Read noise of one photosite, electrons rms.
    pub read_noise_e: f64,
    /// Photosites summed into one output pixel (binning).
    pub photosites_per_pixel: f64,
}

impl SensorNoise {
    /// Full well of an output pixel, electrons.
    pub fn pixel_full_well_e(&self) -> f64 {
        self.full_well_e * self.photosites_per_pixel
    }
    /// Read noise of an output pixel, electrons rms.
    pub fn pixel_read_noise_e(&self) -> f64 {
        self.read_noise_e * self.photosites_per_pixel.sqrt()
    }
}

/// The stream's compression.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Compression {
    /// Baseline JPEG per frame (the MJPEG stream), IJG quality 1-100.
    Jpeg {
        /// Quality.
        quality: u8,
    },
    /// H.264 (OpenH264, bitrate rate control): what an RTSP or RTP camera
    /// sends ([`crate::imaging::H264Codec`]).
    H264 {
        /// Target bitrate, bits per second.
        bitrate_bps: u32,
        /// The encoder's frame rate (its per-frame bit budget is
        /// `bitrate_bps / fps`).
        fps: f64,
        /// Frames between IDR pictures.
        idr_period: u32,
    },
}

/// The sun from the date and time of day.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SunTime {
    /// Latitude, degrees north.
    pub lat_deg: f64,
    /// Longitude, degrees east.
    pub lon_deg: f64,
    /// Day of the year, 1-366.
    pub day_of_year: u32,
    /// Local clock time, hours (e.g. 10.5).
    pub local_time_h: f64,
    /// Local time minus UTC, hours.
    pub utc_offset_h: f64,
}

impl SunTime {
    /// (azimuth degrees clockwise from north, elevation degrees) of the sun.
    pub fn position(&self) -> (f64, f64) {
        sun_position(
            self.lat_deg,
            self.lon_deg,
            self.day_of_year,
            self.local_time_h - self.utc_offset_h,
        )
    }
}

/// The camera effects.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraRealism {
    /// `blur`.
    pub blur: Option<MotionBlur>,
    /// `rolling_shutter`.
    pub rolling_shutter: Option<RollingShutter>,
    /// `auto_exposure`.
    pub auto_exposure: Option<AutoExposure>,
    /// `vignetting`.
    pub vignetting: Option<Vignetting>,
    /// `noise` (off: the ideal 2-grey-level Gaussian noise).
    pub noise: Option<SensorNoise>,
    /// `compression`.
    pub compression: Option<Compression>,
    /// The camera's photometry (always defined; used by the effects above).
    pub photometry: Photometry,
}

/// The light.
#[derive(Debug, Clone, PartialEq)]
pub struct LightingRealism {
    /// `sun` (off: the world's fixed sun, azimuth 150, elevation 50 degrees).
    pub sun: Option<SunTime>,
    /// `clouds`.
    pub clouds: Option<CloudShadows>,
}

/// Wind: a mean wind plus Dryden gusts (first-order longitudinal spectrum,
/// MIL-F-8785C) on each horizontal axis and a weaker vertical component,
/// realised by the spectral representation method (a sum of cosines with
/// random phases, Shinozuka and Deodatis 1991) so it can be evaluated at
/// any time; the vehicle feels quadratic drag of its airspeed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Wind {
    /// Mean wind speed, m/s.
    pub mean_m_s: f64,
    /// Direction the wind blows from, degrees clockwise from north.
    pub from_deg: f64,
    /// Gust intensity (standard deviation per horizontal axis), m/s.
    pub gust_sigma_m_s: f64,
    /// Turbulence length scale, metres (time constant = scale / mean speed).
    pub length_scale_m: f64,
    /// Quadratic drag per unit mass, 1/m (acceleration = drag |v| v).
    pub drag_per_m: f64,
    /// The velocity loop's integral gain compensating the mean wind, 1/s.
    pub integral_gain: f64,
}

/// Gimbal pointing error: a low-frequency stabilisation error and a
/// high-frequency jitter on each axis (pitch, yaw, roll), each a sum of
/// sinusoids with random phases (0.1-2 Hz and 15-60 Hz).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GimbalError {
    /// Low-frequency stabilisation error, degrees rms per axis.
    pub stabilisation_deg: f64,
    /// High-frequency jitter, degrees rms per axis.
    pub jitter_deg: f64,
}

/// GNSS error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpsError {
    /// Slow bias, horizontal sigma per axis, m.
    pub bias_sigma_xy_m: f64,
    /// Slow bias, vertical sigma, m.
    pub bias_sigma_z_m: f64,
    /// Its correlation time, s.
    pub bias_tau_s: f64,
    /// Fast noise, sigma per axis, m.
    pub noise_sigma_m: f64,
    /// Its correlation time, s.
    pub noise_tau_s: f64,
    /// Time constant (1 / natural frequency) of the autopilot's estimator
    /// fusing the receiver's fix with its IMU, s: the slow bias reaches the
    /// position the vehicle flies through this second-order low-pass
    /// (damping 1/sqrt 2), so the vehicle wanders smoothly instead of
    /// jumping with every step of the bias's random walk (0: no fusion,
    /// the receiver's bias as it is).
    pub fusion_tau_s: f64,
}

/// The attitude the autopilot's estimator (AHRS) and the gimbal report
/// against the camera's true one: a slow error (Gauss-Markov per axis:
/// roll and pitch of `tilt_sigma_deg`, heading of `yaw_sigma_deg`, which
/// the magnetometer leaves larger) plus fast noise. It touches only what
/// is reported (a rendered dataset's `telemetry.txt`), never the pose the
/// images are rendered from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AhrsError {
    /// Slow roll and pitch error, degrees sigma per axis.
    pub tilt_sigma_deg: f64,
    /// Slow heading error, degrees sigma.
    pub yaw_sigma_deg: f64,
    /// Correlation time of the slow errors, s.
    pub tau_s: f64,
    /// Fast noise, degrees sigma per axis (correlation time 0.5 s).
    pub noise_deg: f64,
}

/// Losses of the GNSS fix: they start as a Poisson process, last an
/// exponentially distributed time, and while the fix is lost the position
/// estimate drifts as a random walk (GPS_RAW_INT reports no fix and
/// GLOBAL_POSITION_INT is not sent).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpsDropouts {
    /// Mean time between losses, s.
    pub mean_interval_s: f64,
    /// Mean duration of a loss, s.
    pub mean_duration_s: f64,
    /// Random-walk drift of the estimate while lost, m per sqrt(s).
    pub drift_m_per_sqrt_s: f64,
}

/// Barometric altitude drift: the reported altitude wanders as a random
/// walk of the drift rate.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BaroDrift {
    /// Typical drift rate, m per minute.
    pub rate_m_per_min: f64,
}

/// Telemetry at a real autopilot's stream rates over a lossy radio.
#[derive(Debug, Clone, PartialEq)]
pub struct Telemetry {
    /// (MAVLink message id, interval s) overriding the simulator's defaults.
    pub stream_intervals: Vec<(u32, f64)>,
    /// Probability of losing a whole frame, each way.
    pub drop: f64,
    /// One-way latency, s.
    pub latency_s: f64,
    /// Radio bandwidth, baud (8N1).
    pub baud: u32,
}

/// A video latency that varies: mean plus a Gauss-Markov deviation.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VideoLatency {
    /// Mean latency, s.
    pub mean_s: f64,
    /// Standard deviation, s.
    pub sigma_s: f64,
    /// Correlation time, s.
    pub tau_s: f64,
}

/// The vehicle's and the link's effects.
#[derive(Debug, Clone, PartialEq)]
pub struct VehicleRealism {
    /// `wind`.
    pub wind: Option<Wind>,
    /// `gimbal`.
    pub gimbal: Option<GimbalError>,
    /// `gps`.
    pub gps: Option<GpsError>,
    /// `gps_dropouts`.
    pub gps_dropouts: Option<GpsDropouts>,
    /// `baro`.
    pub baro: Option<BaroDrift>,
    /// `ahrs`.
    pub ahrs: Option<AhrsError>,
    /// `telemetry`.
    pub telemetry: Option<Telemetry>,
    /// `video_latency`.
    pub video_latency: Option<VideoLatency>,
}

/// PX4's MAVLINK_MODE_NORMAL intervals (s) for the streams the simulator
/// sends (`src/modules/mavlink/mavlink_main.cpp`).
pub const PX4_NORMAL_STREAMS: [(u32, f64); 10] = [
    (1, 1.0),         // SYS_STATUS 1 Hz
    (2, 1.0),         // SYSTEM_TIME (sent at 1 Hz on every link)
    (24, 1.0),        // GPS_RAW_INT 1 Hz
    (245, 1.0),       // EXTENDED_SYS_STATE 1 Hz
    (30, 1.0 / 15.0), // ATTITUDE 15 Hz
    (33, 0.2),        // GLOBAL_POSITION_INT 5 Hz
    (32, 1.0),        // LOCAL_POSITION_NED 1 Hz
    (285, 1.0),       // GIMBAL_DEVICE_ATTITUDE_STATUS 1 Hz
    (242, 2.0),       // HOME_POSITION 0.5 Hz
    (42, 1.0),        // MISSION_CURRENT
];
