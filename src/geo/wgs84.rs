//! WGS84 geodetic coordinates and the local NED tangent frame at home.
//!
//! The local frame is the plane tangent to the WGS84 ellipsoid at home:
//! origin at home (latitude, longitude, ellipsoidal height), x north,
//! y east, z down along the ellipsoid normal at home. This is the same
//! frame the simulator renders in (`sim/src/geodesy.rs`), computed by this
//! module's own code.
//!
//! Conversions go through Earth-centred Earth-fixed (ECEF) coordinates, so
//! they are exact at any distance (round trip well under a millimetre over
//! 10 km): geodetic → ECEF is closed form; ECEF → geodetic solves the
//! latitude by the fixed-point iteration `φ ← atan2(z + e²·N(φ)·sin φ, p)`,
//! whose error shrinks by a factor of about e² ≈ 0.0067 per step.
//!
//! Because the plane is flat, its z = 0 rises above the ellipsoid by about
//! d²/(2R) at distance d from home (0.8 mm at 100 m, 7.8 cm at 1 km):
//! altitudes above home reported by [`LocalFrame::ned_to_geodetic`] are
//! ellipsoidal heights minus home's, which is what an autopilot compares
//! with `GLOBAL_RELATIVE_ALT` targets. A flat-earth approximation
//! (north = Δlat·(M + h₀), east = Δlon·(N + h₀)·cos lat₀) would agree with
//! this to a few centimetres over 1 km; it is not used.

use nalgebra::{Matrix3, Vector3};

/// WGS84 semi-major axis, metres.
pub const WGS84_A: f64 = 6_378_137.0;
/// WGS84 flattening.
pub const WGS84_F: f64 = 1.0 / 298.257_223_563;
/// WGS84 first eccentricity squared.
pub const WGS84_E2: f64 = WGS84_F * (2.0 - WGS84_F);

/// A WGS84 position.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Geodetic {
    /// Latitude, degrees north.
    pub lat_deg: f64,
    /// Longitude, degrees east.
    pub lon_deg: f64,
    /// Height above the WGS84 ellipsoid, metres (autopilots report it as
    /// AMSL when they have no geoid model).
    pub alt_m: f64,
}

impl Geodetic {
    /// True when every field is finite and the angles are in range.
    pub fn is_valid(&self) -> bool {
        self.lat_deg.is_finite()
            && self.lon_deg.is_finite()
            && self.alt_m.is_finite()
            && self.lat_deg.abs() <= 90.0
            && self.lon_deg.abs() <= 360.0
    }
}

/// Prime-vertical radius of curvature `N(φ)` for `sin φ`.
#[inline]
fn prime_vertical_radius(sin_lat: f64) -> f64 {
    WGS84_A / (1.0 - WGS84_E2 * sin_lat * sin_lat).sqrt()
}

/// Geodetic → ECEF, metres.
pub fn to_ecef(g: &Geodetic) -> Vector3<f64> {
    let (sin_lat, cos_lat) = g.lat_deg.to_radians().sin_cos();
    let (sin_lon, cos_lon) = g.lon_deg.to_radians().sin_cos();
    let n = prime_vertical_radius(sin_lat);
    let r = (n + g.alt_m) * cos_lat;
    Vector3::new(
        r * cos_lon,
        r * sin_lon,
        (n * (1.0 - WGS84_E2) + g.alt_m) * sin_lat,
    )
}

/// ECEF → geodetic (fixed-point latitude iteration, converged to 1e-13 rad).
pub fn from_ecef(p: &Vector3<f64>) -> Geodetic {
    let lon = p.y.atan2(p.x);
    let rho = p.x.hypot(p.y);
    // Start from the geocentric-corrected latitude.
    let mut lat = p.z.atan2(rho * (1.0 - WGS84_E2));
    for _ in 0..12 {
        let n = prime_vertical_radius(lat.sin());
        let next = (p.z + WGS84_E2 * n * lat.sin()).atan2(rho);
        let done = (next - lat).abs() < 1e-13;
        lat = next;
        if done {
            break;
        }
    }
    let (sin_lat, cos_lat) = lat.sin_cos();
    let n = prime_vertical_radius(sin_lat);
    // Use whichever of the two height formulas is well conditioned.
    let alt = if cos_lat.abs() > 0.5 {
        rho / cos_lat - n
    } else {
        p.z / sin_lat - n * (1.0 - WGS84_E2)
    };
    Geodetic {
        lat_deg: lat.to_degrees(),
        lon_deg: lon.to_degrees(),
        alt_m: alt,
    }
}

/// The local NED tangent frame at home (see the module documentation).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LocalFrame {
    home: Geodetic,
    home_ecef: Vector3<f64>,
    /// Rows: the north, east and down unit vectors in ECEF.
    ned_from_ecef: Matrix3<f64>,
}

impl LocalFrame {
    /// The tangent frame at `home`.
    pub fn new(home: Geodetic) -> Self {
        let (sl, cl) = home.lat_deg.to_radians().sin_cos();
        let (so, co) = home.lon_deg.to_radians().sin_cos();
        let north = Vector3::new(-sl * co, -sl * so, cl);
        let east = Vector3::new(-so, co, 0.0);
        let down = Vector3::new(-cl * co, -cl * so, -sl);
        Self {
            home,
            home_ecef: to_ecef(&home),
            ned_from_ecef: Matrix3::from_rows(&[
                north.transpose(),
                east.transpose(),
                down.transpose(),
            ]),
        }
    }

    /// Home, the origin of the frame.
    pub fn home(&self) -> Geodetic {
        self.home
    }

    /// Local NED (metres) → geodetic.
    pub fn ned_to_geodetic(&self, p_ned: &Vector3<f64>) -> Geodetic {
        from_ecef(&(self.home_ecef + self.ned_from_ecef.tr_mul(p_ned)))
    }

    /// Geodetic → local NED (metres).
    pub fn geodetic_to_ned(&self, g: &Geodetic) -> Vector3<f64> {
        self.ned_from_ecef * (to_ecef(g) - self.home_ecef)
    }

    /// The rigid transform from `other`'s NED frame to this one's (exact,
    /// through ECEF): a point or camera pose in `other`'s local NED
    /// expressed in this frame. The identity when both share a home.
    pub fn ned_from_other(&self, other: &LocalFrame) -> nalgebra::Isometry3<f64> {
        let r = self.ned_from_ecef * other.ned_from_ecef.transpose();
        let t = self.ned_from_ecef * (other.home_ecef - self.home_ecef);
        let rot = nalgebra::UnitQuaternion::from_rotation_matrix(
            &nalgebra::Rotation3::from_matrix_unchecked(r),
        );
        nalgebra::Isometry3::from_parts(t.into(), rot)
    }

    /// Altitude above home (ellipsoidal height minus home's) of a NED point.
    pub fn altitude_above_home(&self, p_ned: &Vector3<f64>) -> f64 {
        self.ned_to_geodetic(p_ned).alt_m - self.home.alt_m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ned_from_other_moves_points_between_homes_exactly() {
        let a = LocalFrame::new(HOME);
        let b = LocalFrame::new(Geodetic {
            lat_deg: HOME.lat_deg + 0.01,
            lon_deg: HOME.lon_deg - 0.02,
            alt_m: HOME.alt_m + 30.0,
        });
        let b_from_a = b.ned_from_other(&a);
        for p in [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(120.0, -340.0, -55.0),
            Vector3::new(-800.0, 900.0, 10.0),
        ] {
            let via_geodetic = b.geodetic_to_ned(&a.ned_to_geodetic(&p));
            let via_transform = b_from_a * nalgebra::Point3::from(p);
            assert!((via_geodetic - via_transform.coords).norm() < 1e-6, "{p}");
        }
        // Directions turn by the rotation between the two tangent planes:
        // 0.01 deg of latitude about east, 0.02 deg of longitude about the
        // Earth's axis (perpendicular): sqrt(0.01² + 0.02²) = 0.02236 deg.
        let angle = b_from_a.rotation.angle().to_degrees();
        assert!((angle - 0.02236).abs() < 1e-4, "{angle}");
        let same = a.ned_from_other(&a);
        assert!(same.translation.vector.norm() < 1e-9 && same.rotation.angle() < 1e-12);
    }

    const HOME: Geodetic = Geodetic {
        lat_deg: 47.397_742,
        lon_deg: 8.545_594,
        alt_m: 488.0,
    };

    #[test]
    fn round_trip_is_sub_millimetre_over_10_km() {
        let f = LocalFrame::new(HOME);
        for p in [
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(1000.0, -250.0, -40.0),
            Vector3::new(-3000.0, 4000.0, 10.0),
            Vector3::new(7000.0, 7000.0, -500.0),
        ] {
            let back = f.geodetic_to_ned(&f.ned_to_geodetic(&p));
            assert!((back - p).norm() < 1e-4, "{p} -> {back}");
        }
    }

    #[test]
    fn known_lengths_and_directions() {
        // 1 deg of latitude at 45 deg N: 111 132 m along the meridian
        // (the arc; the chord differs by ~0.1 m).
        let f = LocalFrame::new(Geodetic {
            lat_deg: 44.5,
            lon_deg: 0.0,
            alt_m: 0.0,
        });
        let n = f.geodetic_to_ned(&Geodetic {
            lat_deg: 45.5,
            lon_deg: 0.0,
            alt_m: 0.0,
        });
        assert!((n.norm() - 111_132.0).abs() < 15.0, "{n}");
        assert!(n.y.abs() < 1e-6 && n.x > 0.0);
        // A point straight up from home is at z = -h and alt + h.
        let f = LocalFrame::new(HOME);
        let g = f.ned_to_geodetic(&Vector3::new(0.0, 0.0, -30.0));
        assert!((g.alt_m - 518.0).abs() < 1e-6);
        assert!((g.lat_deg - HOME.lat_deg).abs() < 1e-10);
        // East is +longitude.
        let e = f.ned_to_geodetic(&Vector3::new(0.0, 100.0, 0.0));
        assert!(e.lon_deg > HOME.lon_deg);
    }

    #[test]
    fn ecef_inverse_near_the_poles_and_equator() {
        for g in [
            Geodetic {
                lat_deg: 89.999,
                lon_deg: 12.0,
                alt_m: 100.0,
            },
            Geodetic {
                lat_deg: -0.001,
                lon_deg: -170.0,
                alt_m: -50.0,
            },
            Geodetic {
                lat_deg: -60.0,
                lon_deg: 45.0,
                alt_m: 3000.0,
            },
        ] {
            let back = from_ecef(&to_ecef(&g));
            assert!((back.lat_deg - g.lat_deg).abs() < 1e-11, "{back:?}");
            assert!((back.lon_deg - g.lon_deg).abs() < 1e-11);
            assert!((back.alt_m - g.alt_m).abs() < 1e-6);
        }
    }
}
