//! The named presets' numbers (ideal, field, harsh), each with where it comes from.

use super::Realism;
use super::effects::{
    AhrsError, AutoExposure, BaroDrift, CameraRealism, Compression, GimbalError, GpsDropouts,
    GpsError, LightingRealism, MotionBlur, PX4_NORMAL_STREAMS, Photometry, RollingShutter,
    SensorNoise, SunTime, Telemetry, VehicleRealism, VideoLatency, Vignetting, Wind,
};
use crate::render::CloudShadows;

impl Realism {
    /// Every effect off: today's simulator.
    pub fn ideal() -> Realism {
        Realism {
            name: "ideal".into(),
            camera: CameraRealism {
                blur: None,
                rolling_shutter: None,
                auto_exposure: None,
                vignetting: None,
                noise: None,
                compression: None,
                photometry: Photometry::default(),
            },
            lighting: LightingRealism {
                sun: None,
                clouds: None,
            },
            vehicle: VehicleRealism {
                wind: None,
                gimbal: None,
                gps: None,
                gps_dropouts: None,
                baro: None,
                ahrs: None,
                telemetry: None,
                video_latency: None,
            },
        }
    }

    /// A calm day with a SIYI-class camera (see the module documentation
    /// for the source of every number).
    pub fn field() -> Realism {
        Realism {
            name: "field".into(),
            camera: CameraRealism {
                blur: Some(MotionBlur {
                    max_px_per_sample: 0.5,
                    max_samples: 24,
                }),
                rolling_shutter: Some(RollingShutter { readout_s: 0.025 }),
                auto_exposure: Some(AutoExposure {
                    target: 0.18,
                    tau_s: 0.4,
                    min_exposure_s: 1e-4,
                    max_exposure_s: 1.0 / 60.0,
                    max_gain: 16.0,
                }),
                vignetting: Some(Vignetting { corner: 0.6 }),
                noise: Some(SensorNoise {
                    full_well_e: 5500.0,
                    read_noise_e: 2.5,
                    photosites_per_pixel: 4.0,
                }),
                compression: Some(Compression::Jpeg { quality: 50 }),
                photometry: Photometry::default(),
            },
            lighting: LightingRealism {
                sun: Some(SunTime {
                    lat_deg: 47.397_742,
                    lon_deg: 8.545_594,
                    day_of_year: 135,
                    local_time_h: 11.0,
                    utc_offset_h: 2.0,
                }),
                clouds: Some(CloudShadows {
                    cover: 0.3,
                    scale_m: 300.0,
                    edge_m: 40.0,
                    opacity: 0.75,
                    altitude_m: 1500.0,
                    velocity_m_s: [3.0, 5.2],
                    seed: 0,
                }),
            },
            vehicle: VehicleRealism {
                wind: Some(Wind {
                    mean_m_s: 4.0,
                    from_deg: 240.0,
                    gust_sigma_m_s: 0.69,
                    length_scale_m: 152.0,
                    drag_per_m: 0.03,
                    integral_gain: 0.4,
                }),
                gimbal: Some(GimbalError {
                    stabilisation_deg: 0.05,
                    jitter_deg: 0.007,
                }),
                gps: Some(GpsError {
                    bias_sigma_xy_m: 1.3,
                    bias_sigma_z_m: 0.8,
                    bias_tau_s: 120.0,
                    noise_sigma_m: 0.05,
                    noise_tau_s: 1.0,
                    fusion_tau_s: 0.8,
                }),
                gps_dropouts: Some(GpsDropouts {
                    mean_interval_s: 600.0,
                    mean_duration_s: 3.0,
                    drift_m_per_sqrt_s: 0.3,
                }),
                baro: Some(BaroDrift {
                    rate_m_per_min: 0.05,
                }),
                ahrs: Some(AhrsError {
                    tilt_sigma_deg: 0.3,
                    yaw_sigma_deg: 1.5,
                    tau_s: 60.0,
                    noise_deg: 0.05,
                }),
                telemetry: Some(Telemetry {
                    stream_intervals: PX4_NORMAL_STREAMS.to_vec(),
                    drop: 0.02,
                    latency_s: 0.02,
                    baud: 57_600,
                }),
                video_latency: Some(VideoLatency {
                    mean_s: 0.18,
                    sigma_s: 0.03,
                    tau_s: 2.0,
                }),
            },
        }
    }

    /// A gusty evening (see the module documentation).
    pub fn harsh() -> Realism {
        let mut r = Realism::field();
        r.name = "harsh".into();
        let c = &mut r.camera;
        c.rolling_shutter = Some(RollingShutter { readout_s: 0.033 });
        c.compression = Some(Compression::Jpeg { quality: 25 });
        r.lighting.sun = Some(SunTime {
            lat_deg: 47.397_742,
            lon_deg: 8.545_594,
            day_of_year: 288,
            local_time_h: 18.0,
            utc_offset_h: 2.0,
        });
        r.lighting.clouds = Some(CloudShadows {
            cover: 0.5,
            scale_m: 250.0,
            edge_m: 30.0,
            opacity: 0.8,
            altitude_m: 1200.0,
            velocity_m_s: [8.0, 9.0],
            seed: 0,
        });
        let v = &mut r.vehicle;
        v.wind = Some(Wind {
            mean_m_s: 9.0,
            from_deg: 250.0,
            gust_sigma_m_s: 1.55,
            length_scale_m: 152.0,
            drag_per_m: 0.03,
            integral_gain: 0.4,
        });
        v.gimbal = Some(GimbalError {
            stabilisation_deg: 0.3,
            jitter_deg: 0.05,
        });
        v.gps = Some(GpsError {
            bias_sigma_xy_m: 2.1,
            bias_sigma_z_m: 1.5,
            bias_tau_s: 120.0,
            noise_sigma_m: 0.15,
            noise_tau_s: 1.0,
            fusion_tau_s: 0.8,
        });
        v.gps_dropouts = Some(GpsDropouts {
            mean_interval_s: 120.0,
            mean_duration_s: 5.0,
            drift_m_per_sqrt_s: 0.5,
        });
        v.baro = Some(BaroDrift {
            rate_m_per_min: 0.2,
        });
        v.ahrs = Some(AhrsError {
            tilt_sigma_deg: 0.6,
            yaw_sigma_deg: 3.0,
            tau_s: 60.0,
            noise_deg: 0.1,
        });
        v.telemetry = Some(Telemetry {
            stream_intervals: PX4_NORMAL_STREAMS.to_vec(),
            drop: 0.10,
            latency_s: 0.05,
            baud: 57_600,
        });
        v.video_latency = Some(VideoLatency {
            mean_s: 0.30,
            sigma_s: 0.08,
            tau_s: 2.0,
        });
        r
    }
}
