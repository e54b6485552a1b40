//! The sun's position from the date, time and place, and the clear sky's
//! illuminance at its elevation.

/// The sun's (azimuth, elevation) in degrees (azimuth clockwise from
/// north) at a place and UTC time, by NOAA's solar position equations
/// (fractional-year Fourier series for the declination and the equation of
/// time, after Spencer 1971); accurate to a fraction of a degree.
pub fn sun_position(lat_deg: f64, lon_deg: f64, day_of_year: u32, utc_hours: f64) -> (f64, f64) {
    use std::f64::consts::PI;
    let gamma = 2.0 * PI / 365.0 * (day_of_year as f64 - 1.0 + (utc_hours - 12.0) / 24.0);
    let eqtime = 229.18
        * (0.000075 + 0.001868 * gamma.cos()
            - 0.032077 * gamma.sin()
            - 0.014615 * (2.0 * gamma).cos()
            - 0.040849 * (2.0 * gamma).sin());
    let decl = 0.006918 - 0.399912 * gamma.cos() + 0.070257 * gamma.sin()
        - 0.006758 * (2.0 * gamma).cos()
        + 0.000907 * (2.0 * gamma).sin()
        - 0.002697 * (3.0 * gamma).cos()
        + 0.00148 * (3.0 * gamma).sin();
    // True solar time, minutes, and the hour angle.
    let tst = utc_hours * 60.0 + eqtime + 4.0 * lon_deg;
    let ha = (tst / 4.0 - 180.0).to_radians();
    let lat = lat_deg.to_radians();
    let cos_zen = (lat.sin() * decl.sin() + lat.cos() * decl.cos() * ha.cos()).clamp(-1.0, 1.0);
    let zen = cos_zen.acos();
    let el = 90.0 - zen.to_degrees();
    // Azimuth clockwise from north.
    let az = (ha.sin()).atan2(ha.cos() * lat.sin() - decl.tan() * lat.cos());
    let az = (az.to_degrees() + 180.0).rem_euclid(360.0);
    (az, el)
}

/// Horizontal illuminance (lux) of a clear sky with the sun at `el_deg`:
/// direct sun (128 klx outside the atmosphere, extinction exp(-0.21 m)
/// with the Kasten-Young air mass m) plus the sky's diffuse light
/// (20 klx sqrt(sin el)).
pub fn clear_sky_illuminance_lux(el_deg: f64) -> f64 {
    if el_deg <= 0.0 {
        return 0.0;
    }
    let s = el_deg.to_radians().sin();
    let air_mass = 1.0 / (s + 0.50572 * (el_deg + 6.07995).powf(-1.6364));
    128_000.0 * (-0.21 * air_mass).exp() * s + 20_000.0 * s.sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::realism::Realism;

    #[test]
    fn sun_position_matches_known_values() {
        // Solar noon at the June solstice: elevation 90 - lat + 23.44.
        let (lat, lon) = (47.4, 8.55);
        // Local solar noon in UTC: 12 h - lon/15 - equation of time (~ -1.7 min on 21 June).
        let noon_utc = 12.0 - lon / 15.0 + 1.7 / 60.0;
        let (az, el) = sun_position(lat, lon, 172, noon_utc);
        assert!((el - (90.0 - lat + 23.44)).abs() < 0.3, "el {el}");
        assert!((az - 180.0).abs() < 2.0, "az {az}");
        // Equinox: sun rises due east, elevation near 0 around 6 h solar time.
        let (az, el) = sun_position(0.0, 0.0, 80, 6.1);
        assert!(el.abs() < 2.0 && (az - 90.0).abs() < 3.0, "{az} {el}");
        // The presets' suns.
        let (_, el) = Realism::field().lighting.sun.unwrap().position();
        assert!((45.0..60.0).contains(&el), "field sun {el}");
        let (_, el) = Realism::harsh().lighting.sun.unwrap().position();
        assert!((3.0..10.0).contains(&el), "harsh sun {el}");
    }

    #[test]
    fn clear_sky_illuminance_is_in_the_daylight_range() {
        let high = clear_sky_illuminance_lux(60.0);
        assert!((80_000.0..120_000.0).contains(&high), "{high}");
        let low = clear_sky_illuminance_lux(6.0);
        assert!((3_000.0..15_000.0).contains(&low), "{low}");
        assert_eq!(clear_sky_illuminance_lux(-1.0), 0.0);
    }
}
