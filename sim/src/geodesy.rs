//! WGS84 <-> local NED at home.
//!
//! The local frame is the **tangent plane** at home: origin at home
//! (latitude, longitude, ellipsoidal height), x north, y east, z down along
//! the ellipsoid normal at home. Conversions go through Earth-centred
//! Earth-fixed (ECEF) coordinates on the WGS84 ellipsoid, so they are exact
//! (to well under a millimetre) at any distance: a point is converted to
//! ECEF, rotated into the tangent frame, and back with an iterated
//! (Bowring-style) geodetic latitude.
//!
//! Because the plane is flat and the Earth is not, the simulator's ground
//! (z = 0 everywhere) rises above the ellipsoid by about d^2 / (2 R): 7.8 cm
//! at 1 km from home, 0.8 mm at 100 m. Altitudes reported as "AMSL" are
//! WGS84 ellipsoidal heights (the simulator has no geoid model).
//!
//! A flat-earth approximation (north = dlat * (M + h0), east =
//! dlon * (N + h0) cos lat0, with the WGS84 meridian and prime-vertical
//! radii M, N at home and home's height h0) agrees with this to within
//! the second-order terms (e^2 / 2 + |n e|) tan(lat0) / R for a
//! displacement (n, e): 8.5 cm at 1 km east of a home
//! at 47 deg N (a parallel of latitude curves away from the plane), 2 mm
//! at 1 km north; the test below checks that. This module is exact, so it
//! is the reference. (Leaving out h0 costs h0 / R of the distance: 7.7 cm
//! per km at 488 m.)

use nalgebra::{Matrix3, Vector3};

/// WGS84 semi-major axis in metres.
pub const WGS84_A: f64 = 6_378_137.0;
/// WGS84 flattening.
pub const WGS84_F: f64 = 1.0 / 298.257_223_563;
const WGS84_E2: f64 = WGS84_F * (2.0 - WGS84_F);

/// A geodetic position: latitude and longitude in degrees, ellipsoidal
/// height in metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Geodetic {
    /// Latitude, degrees north.
    pub lat_deg: f64,
    /// Longitude, degrees east.
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid, metres (reported as AMSL).
    pub alt_m: f64,
}

/// Geodetic -> ECEF.
pub fn geodetic_to_ecef(g: &Geodetic) -> Vector3<f64> {
    let lat = g.lat_deg.to_radians();
    let lon = g.lon_deg.to_radians();
    let (sl, cl) = lat.sin_cos();
    let n = WGS84_A / (1.0 - WGS84_E2 * sl * sl).sqrt();
    Vector3::new(
        (n + g.alt_m) * cl * lon.cos(),
        (n + g.alt_m) * cl * lon.sin(),
        (n * (1.0 - WGS84_E2) + g.alt_m) * sl,
    )
}

/// ECEF -> geodetic (iterated latitude; converges to < 1e-9 rad in a few
/// steps for points near the Earth's surface).
pub fn ecef_to_geodetic(p: &Vector3<f64>) -> Geodetic {
    let lon = p.y.atan2(p.x);
    let r = (p.x * p.x + p.y * p.y).sqrt();
    let mut lat = p.z.atan2(r * (1.0 - WGS84_E2));
    let mut alt = 0.0;
    for _ in 0..6 {
        let sl = lat.sin();
        let n = WGS84_A / (1.0 - WGS84_E2 * sl * sl).sqrt();
        alt = if lat.cos().abs() > 1e-9 {
            r / lat.cos() - n
        } else {
            p.z.abs() - n * (1.0 - WGS84_E2)
        };
        lat = p.z.atan2(r * (1.0 - WGS84_E2 * n / (n + alt)));
    }
    Geodetic {
        lat_deg: lat.to_degrees(),
        lon_deg: lon.to_degrees(),
        alt_m: alt,
    }
}

/// The local NED tangent frame at a home position.
#[derive(Debug, Clone, Copy)]
pub struct LocalFrame {
    home: Geodetic,
    home_ecef: Vector3<f64>,
    /// Rows are north, east, down unit vectors in ECEF.
    ned_from_ecef: Matrix3<f64>,
}

impl LocalFrame {
    /// The tangent frame at `home`.
    pub fn new(home: Geodetic) -> Self {
        let lat = home.lat_deg.to_radians();
        let lon = home.lon_deg.to_radians();
        let (sl, cl) = lat.sin_cos();
        let (so, co) = lon.sin_cos();
        let ned_from_ecef = Matrix3::new(
            -sl * co,
            -sl * so,
            cl,
            -so,
            co,
            0.0,
            -cl * co,
            -cl * so,
            -sl,
        );
        Self {
            home,
            home_ecef: geodetic_to_ecef(&home),
            ned_from_ecef,
        }
    }

    /// The home position.
    pub fn home(&self) -> Geodetic {
        self.home
    }

    /// Local NED (metres) -> geodetic.
    pub fn ned_to_geodetic(&self, p_ned: &Vector3<f64>) -> Geodetic {
        let ecef = self.home_ecef + self.ned_from_ecef.transpose() * p_ned;
        ecef_to_geodetic(&ecef)
    }

    /// Geodetic -> local NED (metres).
    pub fn geodetic_to_ned(&self, g: &Geodetic) -> Vector3<f64> {
        self.ned_from_ecef * (geodetic_to_ecef(g) - self.home_ecef)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOME: Geodetic = Geodetic {
        lat_deg: 47.397_742,
        lon_deg: 8.545_594,
        alt_m: 488.0,
    };

    #[test]
    fn round_trip_is_sub_millimetre_over_5_km() {
        let f = LocalFrame::new(HOME);
        for p in [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1000.0, -250.0, -40.0),
            Vector3::new(-3000.0, 4000.0, 10.0),
            Vector3::new(12.5, 7.25, -120.0),
        ] {
            let g = f.ned_to_geodetic(&p);
            let back = f.geodetic_to_ned(&g);
            assert!((back - p).norm() < 1e-3, "{p} -> {back}");
        }
    }

    #[test]
    fn home_maps_to_origin_and_axes_point_the_right_way() {
        let f = LocalFrame::new(HOME);
        assert!(f.geodetic_to_ned(&HOME).norm() < 1e-6);
        let north = f.ned_to_geodetic(&Vector3::new(100.0, 0.0, 0.0));
        assert!(north.lat_deg > HOME.lat_deg);
        assert!((north.lon_deg - HOME.lon_deg).abs() < 1e-9);
        let east = f.ned_to_geodetic(&Vector3::new(0.0, 100.0, 0.0));
        assert!(east.lon_deg > HOME.lon_deg);
        let up = f.ned_to_geodetic(&Vector3::new(0.0, 0.0, -30.0));
        assert!((up.alt_m - (HOME.alt_m + 30.0)).abs() < 1e-6);
    }

    /// The flat-earth formula with local WGS84 radii agrees to the
    /// second-order terms (e^2/2 + |n e|) tan(lat0) / R (+1 cm) at 1 km.
    #[test]
    fn flat_earth_agrees_to_centimetres_over_one_kilometre() {
        let f = LocalFrame::new(HOME);
        let lat0 = HOME.lat_deg.to_radians();
        let s2 = lat0.sin().powi(2);
        let m = WGS84_A * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s2).powf(1.5);
        let n = WGS84_A / (1.0 - WGS84_E2 * s2).sqrt();
        for (dn, de) in [(1000.0, 0.0), (0.0, 1000.0), (-700.0, 700.0)] {
            let g = f.ned_to_geodetic(&Vector3::new(dn, de, 0.0));
            let north = (g.lat_deg - HOME.lat_deg).to_radians() * (m + HOME.alt_m);
            let east = (g.lon_deg - HOME.lon_deg).to_radians() * (n + HOME.alt_m) * lat0.cos();
            let err = ((north - dn).powi(2) + (east - de).powi(2)).sqrt();
            let bound = (de * de / 2.0 + (dn * de).abs()) * lat0.tan() / WGS84_A + 0.01;
            assert!(err < bound, "flat-earth error {err} m at ({dn},{de})");
        }
    }

    /// A known point: 1 degree of latitude at 45 deg is ~111.13 km.
    #[test]
    fn one_degree_of_latitude_has_the_known_length() {
        let home = Geodetic {
            lat_deg: 44.5,
            lon_deg: 0.0,
            alt_m: 0.0,
        };
        let a = geodetic_to_ecef(&home);
        let b = geodetic_to_ecef(&Geodetic {
            lat_deg: 45.5,
            ..home
        });
        let chord = (b - a).norm();
        assert!((chord - 111_132.0).abs() < 15.0, "{chord}");
    }
}
