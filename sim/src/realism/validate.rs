//! What a realism may not be: the checks of every effect's numbers.

use super::effects::Compression;
use super::{Realism, RealismError};

impl Realism {
    /// Checks every number for range.
    pub fn validate(&self) -> Result<(), RealismError> {
        let bad = |name, value: f64, reason| {
            Err(RealismError::OutOfRange {
                name,
                value,
                reason,
            })
        };
        let c = &self.camera;
        let p = &c.photometry;
        if !(p.f_number > 0.0 && p.f_number.is_finite()) {
            return bad("f_number", p.f_number, "> 0");
        }
        if !(p.lens_transmission > 0.0 && p.lens_transmission <= 1.0) {
            return bad("lens_transmission", p.lens_transmission, "(0, 1]");
        }
        if !(p.saturation_lux_s > 0.0 && p.saturation_lux_s.is_finite()) {
            return bad("saturation_lux_s", p.saturation_lux_s, "> 0");
        }
        if !(p.fixed_exposure_s >= 0.0 && p.fixed_exposure_s <= 1.0) {
            return bad("fixed_exposure_s", p.fixed_exposure_s, "[0, 1] s");
        }
        if !(p.display_gamma >= 1.0 && p.display_gamma <= 3.0) {
            return bad("display_gamma", p.display_gamma, "[1, 3]");
        }
        if let Some(b) = &c.blur {
            if !(b.max_px_per_sample > 0.0 && b.max_px_per_sample.is_finite()) {
                return bad("blur.max_px_per_sample", b.max_px_per_sample, "> 0");
            }
            if !(1..=256).contains(&b.max_samples) {
                return bad("blur.max_samples", b.max_samples as f64, "1-256");
            }
        }
        if let Some(rs) = &c.rolling_shutter
            && !(rs.readout_s >= 0.0 && rs.readout_s <= 0.2)
        {
            return bad("rolling_shutter.readout_s", rs.readout_s, "[0, 0.2] s");
        }
        if let Some(ae) = &c.auto_exposure {
            if !(ae.target > 0.0 && ae.target < 1.0) {
                return bad("auto_exposure.target", ae.target, "(0, 1)");
            }
            if !(ae.tau_s >= 0.0 && ae.tau_s.is_finite()) {
                return bad("auto_exposure.tau_s", ae.tau_s, ">= 0 s");
            }
            if !(ae.min_exposure_s > 0.0 && ae.min_exposure_s <= ae.max_exposure_s) {
                return bad(
                    "auto_exposure.min_exposure_s",
                    ae.min_exposure_s,
                    "(0, max]",
                );
            }
            if ae.max_exposure_s > 1.0 || ae.max_exposure_s.is_nan() {
                return bad("auto_exposure.max_exposure_s", ae.max_exposure_s, "<= 1 s");
            }
            if !(ae.max_gain >= 1.0 && ae.max_gain <= 1024.0) {
                return bad("auto_exposure.max_gain", ae.max_gain, "[1, 1024]");
            }
        }
        if let Some(v) = &c.vignetting
            && !(v.corner > 0.0 && v.corner <= 1.0)
        {
            return bad("vignetting.corner", v.corner, "(0, 1]");
        }
        if let Some(n) = &c.noise {
            if !(n.full_well_e >= 1.0 && n.full_well_e.is_finite()) {
                return bad("noise.full_well_e", n.full_well_e, ">= 1");
            }
            if !(n.read_noise_e >= 0.0 && n.read_noise_e.is_finite()) {
                return bad("noise.read_noise_e", n.read_noise_e, ">= 0");
            }
            if !(n.photosites_per_pixel >= 1.0 && n.photosites_per_pixel <= 1e4) {
                return bad(
                    "noise.photosites_per_pixel",
                    n.photosites_per_pixel,
                    "[1, 1e4]",
                );
            }
        }
        if let Some(Compression::Jpeg { quality }) = c.compression
            && !(1..=100).contains(&quality)
        {
            return bad("compression.quality", quality as f64, "1-100");
        }
        if let Some(Compression::H264 {
            bitrate_bps,
            fps,
            idr_period,
        }) = c.compression
        {
            if !(50_000..=50_000_000).contains(&bitrate_bps) {
                return bad(
                    "compression.bitrate_bps",
                    f64::from(bitrate_bps),
                    "[5e4, 5e7]",
                );
            }
            if !(fps > 0.0 && fps <= 120.0) {
                return bad("compression.fps", fps, "(0, 120]");
            }
            if !(1..=600).contains(&idr_period) {
                return bad("compression.idr_period", f64::from(idr_period), "1-600");
            }
        }
        if let Some(s) = &self.lighting.sun {
            if !(-90.0..=90.0).contains(&s.lat_deg) {
                return bad("sun.lat_deg", s.lat_deg, "[-90, 90]");
            }
            if !(1..=366).contains(&s.day_of_year) {
                return bad("sun.day_of_year", s.day_of_year as f64, "1-366");
            }
            let (_, el) = s.position();
            if el <= 2.0 {
                return bad("sun elevation (deg)", el, "the sun must be above 2 degrees");
            }
        }
        if let Some(cl) = &self.lighting.clouds {
            for (name, v, ok) in [
                (
                    "clouds.cover",
                    cl.cover as f64,
                    (0.0..=1.0).contains(&cl.cover),
                ),
                (
                    "clouds.opacity",
                    cl.opacity as f64,
                    (0.0..=1.0).contains(&cl.opacity),
                ),
                ("clouds.scale_m", cl.scale_m as f64, cl.scale_m >= 1.0),
                (
                    "clouds.altitude_m",
                    cl.altitude_m as f64,
                    cl.altitude_m > 0.0,
                ),
            ] {
                if !ok {
                    return bad(
                        name,
                        v,
                        "cover/opacity in [0, 1], scale >= 1 m, altitude > 0",
                    );
                }
            }
        }
        let v = &self.vehicle;
        if let Some(w) = &v.wind {
            for (name, x) in [
                ("wind.mean_m_s", w.mean_m_s),
                ("wind.gust_sigma_m_s", w.gust_sigma_m_s),
                ("wind.drag_per_m", w.drag_per_m),
                ("wind.integral_gain", w.integral_gain),
            ] {
                if !(0.0..=50.0).contains(&x) {
                    return bad(name, x, "[0, 50]");
                }
            }
            if !(w.length_scale_m >= 1.0 && w.length_scale_m.is_finite()) {
                return bad("wind.length_scale_m", w.length_scale_m, ">= 1 m");
            }
        }
        if let Some(g) = &v.gimbal
            && !(g.stabilisation_deg >= 0.0
                && g.jitter_deg >= 0.0
                && g.stabilisation_deg < 10.0
                && g.jitter_deg < 10.0)
        {
            return bad(
                "gimbal",
                g.stabilisation_deg.max(g.jitter_deg),
                "[0, 10) degrees",
            );
        }
        if let Some(g) = &v.gps {
            for (name, x) in [
                ("gps.bias_sigma_xy_m", g.bias_sigma_xy_m),
                ("gps.bias_sigma_z_m", g.bias_sigma_z_m),
                ("gps.noise_sigma_m", g.noise_sigma_m),
            ] {
                if !(0.0..=50.0).contains(&x) {
                    return bad(name, x, "[0, 50] m");
                }
            }
            if !(g.bias_tau_s > 0.0 && g.noise_tau_s > 0.0) {
                return bad("gps tau", g.bias_tau_s.min(g.noise_tau_s), "> 0 s");
            }
            if !(0.0..=60.0).contains(&g.fusion_tau_s) {
                return bad("gps.fusion_tau_s", g.fusion_tau_s, "[0, 60] s");
            }
        }
        if let Some(d) = &v.gps_dropouts
            && !(d.mean_interval_s > 0.0 && d.mean_duration_s > 0.0 && d.drift_m_per_sqrt_s >= 0.0)
        {
            return bad(
                "gps_dropouts",
                d.mean_interval_s,
                "positive interval and duration",
            );
        }
        if let Some(a) = &v.ahrs {
            for (name, x) in [
                ("ahrs.tilt_sigma_deg", a.tilt_sigma_deg),
                ("ahrs.yaw_sigma_deg", a.yaw_sigma_deg),
                ("ahrs.noise_deg", a.noise_deg),
            ] {
                if !(0.0..=20.0).contains(&x) {
                    return bad(name, x, "[0, 20] degrees");
                }
            }
            if !(a.tau_s > 0.0 && a.tau_s.is_finite()) {
                return bad("ahrs.tau_s", a.tau_s, "> 0 s");
            }
        }
        if let Some(t) = &v.telemetry {
            if !(0.0..=1.0).contains(&t.drop) {
                return bad("telemetry.drop", t.drop, "[0, 1]");
            }
            if !(0.0..=10.0).contains(&t.latency_s) {
                return bad("telemetry.latency_s", t.latency_s, "[0, 10] s");
            }
        }
        if let Some(l) = &v.video_latency
            && !(l.mean_s >= 0.0 && l.mean_s <= 10.0 && l.sigma_s >= 0.0 && l.tau_s > 0.0)
        {
            return bad(
                "video_latency",
                l.mean_s,
                "mean in [0, 10] s, sigma >= 0, tau > 0",
            );
        }
        Ok(())
    }
}
