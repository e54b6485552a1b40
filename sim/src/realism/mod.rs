//! Realism presets: what separates the simulator's clean world from a real
//! flight, as named, seeded, switchable effects with physical parameters.
//!
//! Three presets:
//!
//! - `ideal`: every effect off. The simulator renders exactly what it
//!   rendered before realism existed (global shutter at one instant, light
//!   Gaussian noise of 2 grey levels, the world's fixed sun), bit for bit
//!   (test `sim/tests/suite/ideal_unchanged.rs`).
//! - `field`: a calm day with a small gimbal camera of the SIYI A8 mini
//!   class (1/1.7-inch rolling-shutter CMOS, 3-axis gimbal) on a PX4
//!   quadrotor with a u-blox M9-class GNSS receiver and a SiK telemetry
//!   radio. Every number below names where it comes from.
//! - `harsh`: a gusty evening: 9 m/s wind, low sun, more cloud, a low JPEG
//!   quality, a worse gimbal, GNSS and radio.
//!
//! # Effects
//!
//! Each effect is `Option<Params>` (off or on with its physical parameters)
//! and has a short name for the command line: a preset may be followed by
//! `-NAME` (switch an effect off) or `+NAME` (switch it on with the `field`
//! preset's numbers, or `+NAME@harsh` with another preset's). For example
//! `field-blur-rolling_shutter` or `ideal+wind@harsh+gimbal`. Names:
//!
//! | name | effect | physical parameters |
//! |---|---|---|
//! | `blur` | motion blur: the image integrated over the exposure from the camera's real motion | exposure time (from `auto_exposure`, else `fixed_exposure_s`); sub-exposure samples |
//! | `rolling_shutter` | each row exposed at its own time | frame readout time, s |
//! | `auto_exposure` | exposure time and gain chase the scene's brightness with a lag; highlights and shadows clip | target, time constant, shutter and gain limits, aperture |
//! | `sun` | the sun's direction from the date and time of day (cast shadows and face lighting follow) and its illuminance | latitude, longitude, day of year, local time |
//! | `clouds` | cloud shadows drifting over the scene | cover, size, edge, opacity, altitude, drift velocity |
//! | `vignetting` | lens falloff towards the corners | relative illumination at the image corner |
//! | `noise` | sensor noise: photon shot noise (grows with the signal) and read noise | full well and read noise per photosite, photosites per pixel |
//! | `compression` | the stream's compression, JPEG per frame as the MJPEG stream sends it (see [`crate::imaging::FrameCodec`]) | JPEG quality |
//! | `wind` | wind with gusts pushing the vehicle off its setpoint | mean speed and direction, gust intensity and length scale, drag |
//! | `gimbal` | gimbal stabilisation error and jitter | low-frequency error and jitter, rms degrees |
//! | `gps` | GNSS error: a slow bias (Gauss-Markov, through the estimator's fusion) and fast noise | sigmas, correlation times, fusion time constant |
//! | `gps_dropouts` | occasional losses of the GNSS fix | mean interval and duration, drift while lost |
//! | `baro` | barometric altitude drift | drift rate |
//! | `ahrs` | the reported attitude's error (autopilot estimator and gimbal): slow per axis plus fast noise; the rendered pose is untouched | tilt and heading sigmas, correlation time, noise |
//! | `telemetry` | telemetry at a real autopilot's stream rates over a lossy radio | PX4 stream rates; drop probability, latency, baud |
//! | `video_latency` | a video latency that varies | mean, deviation, correlation time |
//!
//! `+h264[@PRESET]` switches `compression` on as H.264 instead of JPEG:
//! encoded and decoded by OpenH264, predicted pictures between IDR
//! pictures, as an RTSP/RTP camera sends ([`crate::imaging::H264Codec`];
//! bitrate and IDR period from [`Realism::h264_stream`]), e.g.
//! `field+h264` or `field+h264@harsh`; `-h264` switches it off again.
//!
//! # Sources of the `field` numbers
//!
//! - Rolling-shutter readout 25 ms: the 20-30 ms for small gimbal
//!   cameras; readouts measured for small CMOS cameras of 27-32 ms
//!   (Ringaby and Forssén, "Efficient video rectification and stabilisation
//!   for cell-phones", IJCV 2012, table of measured readout times; the
//!   Kalibr rolling-shutter table reproduces it).
//! - Exposure: ISO 100 saturation exposure 0.78 lux·s (ISO 12232
//!   saturation-based speed, S = 78 / H_sat), aperture f/2.8 and lens
//!   transmission 0.9 (typical of small fixed-focus gimbal lenses): in full
//!   sun this gives the sunny-16 exposure (about 1/4000 s at f/2.8, ISO 100).
//!   Auto-exposure time constant 0.4 s (a camera's AE settles in about
//!   half a second to a second after a step), shutter 1/10000 to 1/60 s,
//!   gain up to 16x (ISO 1600).
//! - Illuminance: the extraterrestrial solar illuminance 128 klx attenuated
//!   by a clear-sky extinction of exp(-0.21 m), m the Kasten-Young air mass,
//!   plus a sky (diffuse) term of 20 klx·sqrt(sin elevation) (clear-sky
//!   daylight models of the IES Lighting Handbook).
//! - Sun position: NOAA's solar position equations (Spencer's declination
//!   and equation of time), home at 47.3977 N 8.5456 E on 15 May at
//!   11:00 local time (UTC+2): elevation 49, azimuth 123 degrees.
//! - Vignetting: corner relative illumination 0.6 (cos^n falloff; the
//!   natural cos^4 law alone would give 0.33 at this camera's 41-degree
//!   corner, lens design recovers part of it).
//! - Sensor noise: 5500 electrons full well and 2.5 electrons read noise
//!   per 2 µm photosite (R. N. Clark, "Digital camera sensor performance
//!   summary": full well about 1400 e-/µm² and 2-3 e- read noise for
//!   modern small-pixel CMOS), 2x2 binned in the sensor's video mode
//!   (4 photosites per pixel: full well 22000 e-, read noise 5 e-).
//! - Compression: JPEG quality 50 (the IJG quality scale of ITU-T T.81's
//!   example tables), about 5 Mbit/s at 640x480 and 15 frames/s on the
//!   town; the bitrate is reported with every render.
//! - H.264 (`+h264`, in place of the JPEG): a SIYI A8 mini sends
//!   1280x720 at about 1.5 Mbit/s (issue 18), 1.63 bit per pixel and
//!   second; the same density on this 640x480 camera is 0.5 Mbit/s, at 15
//!   frames/s with an IDR picture each second (15 frames).
//! - Wind: a light-to-gentle breeze of 4 m/s at 6 m (Beaufort 3 starts at
//!   3.4 m/s) with the low-altitude Dryden turbulence model of
//!   MIL-F-8785C: sigma_u = 0.1 W20 / (0.177 + 0.000823 h)^0.4 and
//!   L_u = h / (0.177 + 0.000823 h)^1.2 (h in feet) at h = 30 m: 0.69 m/s
//!   and 152 m. Drag 0.03 /m (a 1.5 kg quadrotor leans about 17 degrees
//!   at 10 m/s airspeed).
//! - Gimbal: SIYI's ±0.01 degree angular vibration range for its 3-axis
//!   gimbals (jitter 0.007 degrees rms), plus a low-frequency
//!   stabilisation error of 0.05 degrees rms.
//! - GNSS: u-blox NEO-M9N data sheet, 1.5 m CEP horizontal (sigma per
//!   axis = CEP / 1.1774 = 1.3 m), as a Gauss-Markov bias with a 120 s
//!   correlation time, reaching the position the vehicle flies through
//!   the estimator's fusion with its IMU (a second-order low-pass of time
//!   constant 0.8 s: PX4 EKF2's default GPS and accelerometer noises);
//!   5 cm of fast noise (the estimator's output);
//!   a fix lost for 3 s every 10 minutes on average.
//! - Barometer: drift of the pressure altitude with the weather, 1 hPa in
//!   about 3 hours (8 m), about 0.05 m per minute.
//! - Attitude report (AHRS and gimbal): roll and pitch 0.3 degrees, heading
//!   1.5 degrees (a magnetometer-aided heading in a calm field), slow
//!   errors with a 60 s correlation time, plus 0.05 degrees of noise
//!   (ArduPilot's and PX4's EKF attitude accuracy on a small multicopter
//!   is quoted at 0.1-0.5 degrees in tilt and 1-3 degrees in heading).
//! - Telemetry: PX4's default stream rates on a telemetry radio
//!   (MAVLINK_MODE_NORMAL in `src/modules/mavlink/mavlink_main.cpp`:
//!   ATTITUDE 15 Hz, GLOBAL_POSITION_INT 5 Hz, GPS_RAW_INT 1 Hz,
//!   LOCAL_POSITION_NED 1 Hz, GIMBAL_DEVICE_ATTITUDE_STATUS 1 Hz,
//!   HOME_POSITION 0.5 Hz); a SiK radio at 57600 baud losing 2 % of the
//!   frames with 20 ms one-way latency.
//! - Video latency: 180 ms mean with 30 ms deviation (digital HD video
//!   links of this class advertise 150-200 ms glass to glass).
//!
//! `harsh` changes: wind 9 m/s (Beaufort 5) with sigma_u 1.55 m/s; the sun
//! at 5.7 degrees, azimuth 251 (15 October, 18:00 local); cloud cover 0.5; JPEG
//! quality 25 (H.264: 0.25 Mbit/s, half the field bitrate, as an adaptive
//! digital link such as OpenIPC / wfb-ng lowers its encoder's bitrate at
//! the edge of its range); rolling-shutter readout 33 ms; gimbal jitter 0.05 and
//! error 0.3 degrees; a u-blox M8-class 2.5 m CEP GNSS losing its fix for
//! 5 s every 2 minutes; barometer drift 0.2 m per minute; attitude report
//! errors 0.6 degrees in tilt and 3 degrees in heading, 0.1 of noise; the radio
//! losing 10 % with 50 ms latency; video latency 300 ± 80 ms.
//!
//! # Files
//!
//! `effects` the effects' parameter types; `presets` the named presets'
//! numbers; `validate` the checks of every effect's numbers; `sun` the sun's
//! position and illuminance. This file holds [`Realism`]: parsed, effects
//! switched, listed.

mod effects;
mod presets;
mod sun;
mod validate;

pub use effects::{
    AhrsError, AutoExposure, BaroDrift, CameraRealism, Compression, GimbalError, GpsDropouts,
    GpsError, LightingRealism, MotionBlur, PX4_NORMAL_STREAMS, Photometry, RollingShutter,
    SensorNoise, SunTime, Telemetry, VehicleRealism, VideoLatency, Vignetting, Wind,
};
pub use sun::{clear_sky_illuminance_lux, sun_position};

/// Errors of preset parsing.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RealismError {
    /// The preset name is not known.
    #[error("unknown realism preset {name:?}: use ideal, field or harsh")]
    UnknownPreset {
        /// The name given.
        name: String,
    },
    /// An effect name is not known.
    #[error("unknown realism effect {name:?}: use one of {known}")]
    UnknownEffect {
        /// The name given.
        name: String,
        /// The known names.
        known: String,
    },
    /// The specification could not be parsed.
    #[error("bad realism specification {spec:?}: {reason}")]
    Syntax {
        /// The whole specification.
        spec: String,
        /// What is wrong.
        reason: &'static str,
    },
    /// A parameter is out of range.
    #[error("realism parameter {name} = {value} is out of range: {reason}")]
    OutOfRange {
        /// The parameter.
        name: &'static str,
        /// Its value.
        value: f64,
        /// The valid range.
        reason: &'static str,
    },
}

/// The preset names.
pub const PRESETS: [&str; 3] = ["ideal", "field", "harsh"];

/// Every effect's short name, in documentation order.
pub const EFFECTS: [&str; 16] = [
    "blur",
    "rolling_shutter",
    "auto_exposure",
    "sun",
    "clouds",
    "vignetting",
    "noise",
    "compression",
    "wind",
    "gimbal",
    "gps",
    "gps_dropouts",
    "baro",
    "ahrs",
    "telemetry",
    "video_latency",
];

/// A realism configuration: a preset with its overrides.
#[derive(Debug, Clone, PartialEq)]
pub struct Realism {
    /// How it was specified (`field`, `field-blur`, ...).
    pub name: String,
    /// Camera effects.
    pub camera: CameraRealism,
    /// Light.
    pub lighting: LightingRealism,
    /// Vehicle and link.
    pub vehicle: VehicleRealism,
}

impl Default for Realism {
    fn default() -> Self {
        Self::ideal()
    }
}

impl Realism {
    /// A preset by name.
    pub fn preset(name: &str) -> Result<Realism, RealismError> {
        match name {
            "ideal" => Ok(Realism::ideal()),
            "field" => Ok(Realism::field()),
            "harsh" => Ok(Realism::harsh()),
            other => Err(RealismError::UnknownPreset {
                name: other.to_string(),
            }),
        }
    }

    /// Parses `PRESET`, then any number of `-EFFECT` (off) and
    /// `+EFFECT[@PRESET]` (on, with the numbers of `field` or the named
    /// preset), e.g. `field-blur` or `ideal+wind@harsh+noise`.
    pub fn parse(spec: &str) -> Result<Realism, RealismError> {
        let spec_t = spec.trim();
        let syntax = |reason| RealismError::Syntax {
            spec: spec.to_string(),
            reason,
        };
        let first = spec_t.find(['+', '-']).unwrap_or(spec_t.len());
        let mut r = Realism::preset(&spec_t[..first])?;
        let mut rest = &spec_t[first..];
        while !rest.is_empty() {
            let on = rest.starts_with('+');
            rest = &rest[1..];
            let end = rest.find(['+', '-']).unwrap_or(rest.len());
            let item = &rest[..end];
            rest = &rest[end..];
            if item.is_empty() {
                return Err(syntax("an empty effect name after + or -"));
            }
            let (name, from) = match item.split_once('@') {
                Some((n, p)) if on => (n, Realism::preset(p)?),
                Some(_) => return Err(syntax("@PRESET only follows +EFFECT")),
                None => (item, Realism::field()),
            };
            r.set_effect(name, if on { Some(&from) } else { None })?;
        }
        r.name = spec_t.to_string();
        r.validate()?;
        Ok(r)
    }

    /// Switches effect `name` off (`from` None) or on with `from`'s numbers.
    pub fn set_effect(&mut self, name: &str, from: Option<&Realism>) -> Result<(), RealismError> {
        let off = Realism::ideal();
        let src = from.unwrap_or(&off);
        match name {
            "blur" => self.camera.blur = src.camera.blur,
            "rolling_shutter" => self.camera.rolling_shutter = src.camera.rolling_shutter,
            "auto_exposure" => self.camera.auto_exposure = src.camera.auto_exposure,
            "vignetting" => self.camera.vignetting = src.camera.vignetting,
            "noise" => self.camera.noise = src.camera.noise,
            "compression" => self.camera.compression = src.camera.compression,
            "h264" => {
                self.camera.compression = match from {
                    Some(f) => Some(f.h264_stream()),
                    // Off: no compression where H.264 was on.
                    None => self
                        .camera
                        .compression
                        .filter(|c| !matches!(c, Compression::H264 { .. })),
                }
            }
            "sun" => self.lighting.sun = src.lighting.sun,
            "clouds" => self.lighting.clouds = src.lighting.clouds,
            "wind" => self.vehicle.wind = src.vehicle.wind,
            "gimbal" => self.vehicle.gimbal = src.vehicle.gimbal,
            "gps" => self.vehicle.gps = src.vehicle.gps,
            "gps_dropouts" => self.vehicle.gps_dropouts = src.vehicle.gps_dropouts,
            "baro" => self.vehicle.baro = src.vehicle.baro,
            "ahrs" => self.vehicle.ahrs = src.vehicle.ahrs,
            "telemetry" => self.vehicle.telemetry = src.vehicle.telemetry.clone(),
            "video_latency" => self.vehicle.video_latency = src.vehicle.video_latency,
            other => {
                return Err(RealismError::UnknownEffect {
                    name: other.to_string(),
                    known: EFFECTS.join(", "),
                });
            }
        }
        Ok(())
    }

    /// The H.264 stream of this preset's camera (`+h264`, see the module
    /// documentation): 0.5 Mbit/s for `field` (and `ideal`), 0.25 Mbit/s
    /// for `harsh`, 15 frames/s, an IDR picture each second.
    pub fn h264_stream(&self) -> Compression {
        let harsh = self.name.starts_with("harsh");
        Compression::H264 {
            bitrate_bps: if harsh { 250_000 } else { 500_000 },
            fps: 15.0,
            idr_period: 15,
        }
    }

    /// The names of the effects switched on.
    pub fn effects_on(&self) -> Vec<&'static str> {
        let c = &self.camera;
        let v = &self.vehicle;
        let on = [
            c.blur.is_some(),
            c.rolling_shutter.is_some(),
            c.auto_exposure.is_some(),
            self.lighting.sun.is_some(),
            self.lighting.clouds.is_some(),
            c.vignetting.is_some(),
            c.noise.is_some(),
            c.compression.is_some(),
            v.wind.is_some(),
            v.gimbal.is_some(),
            v.gps.is_some(),
            v.gps_dropouts.is_some(),
            v.baro.is_some(),
            v.ahrs.is_some(),
            v.telemetry.is_some(),
            v.video_latency.is_some(),
        ];
        EFFECTS
            .iter()
            .zip(on)
            .filter_map(|(n, o)| o.then_some(*n))
            .collect()
    }

    /// True when no effect is on (the renders are the ideal ones).
    pub fn is_ideal(&self) -> bool {
        self.effects_on().is_empty()
    }

    /// True when any camera or lighting effect is on (frames go through
    /// [`crate::imaging::Imager`]'s realistic pipeline).
    pub fn camera_is_ideal(&self) -> bool {
        let c = &self.camera;
        c.blur.is_none()
            && c.rolling_shutter.is_none()
            && c.auto_exposure.is_none()
            && c.vignetting.is_none()
            && c.noise.is_none()
            && c.compression.is_none()
            && self.lighting.sun.is_none()
            && self.lighting.clouds.is_none()
    }
}

impl std::str::FromStr for Realism {
    type Err = RealismError;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Realism::parse(s)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn presets_parse_and_overrides_switch_effects() {
        assert!(Realism::parse("ideal").unwrap().is_ideal());
        let f = Realism::parse("field").unwrap();
        assert_eq!(f.effects_on().len(), EFFECTS.len());
        let r = Realism::parse("field-blur-rolling_shutter").unwrap();
        assert!(r.camera.blur.is_none() && r.camera.rolling_shutter.is_none());
        assert!(r.camera.noise.is_some());
        assert_eq!(r.name, "field-blur-rolling_shutter");
        let r = Realism::parse("ideal+wind@harsh+noise").unwrap();
        assert_eq!(r.effects_on(), vec!["noise", "wind"]);
        assert_eq!(r.vehicle.wind, Realism::harsh().vehicle.wind);
        assert_eq!(r.camera.noise, Realism::field().camera.noise);
        assert!(matches!(
            Realism::parse("sunny"),
            Err(RealismError::UnknownPreset { .. })
        ));
        assert!(matches!(
            Realism::parse("field-fog"),
            Err(RealismError::UnknownEffect { .. })
        ));
        assert!(matches!(
            Realism::parse("field-"),
            Err(RealismError::Syntax { .. })
        ));
        assert!(Realism::parse("field-blur@harsh").is_err());
        // H.264 in place of the JPEG, at each preset's bitrate, and off.
        let h = |spec: &str| Realism::parse(spec).unwrap().camera.compression;
        assert!(matches!(
            h("field+h264"),
            Some(Compression::H264 {
                bitrate_bps: 500_000,
                idr_period: 15,
                ..
            })
        ));
        assert!(matches!(
            h("field+h264@harsh"),
            Some(Compression::H264 {
                bitrate_bps: 250_000,
                ..
            })
        ));
        assert_eq!(h("field+h264-h264"), None);
        assert_eq!(h("field-h264"), Realism::field().camera.compression);
        for name in EFFECTS {
            let mut r = Realism::ideal();
            r.set_effect(name, Some(&Realism::field())).unwrap();
            assert_eq!(r.effects_on(), vec![name]);
        }
    }
}
