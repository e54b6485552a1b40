//! Angles wrapped to one turn: headings and their differences.
//!
//! One home for the wrapping every module needs (the refinement loop's yaw
//! errors in degrees, the georeference's headings in radians), so no module
//! keeps a private copy. Both wrap to the half-open interval that keeps
//! +180° (+π) and maps -180° (-π) onto it; a NaN passes through as NaN (an
//! unknown heading stays unknown) and an infinity becomes NaN.

use std::f64::consts::{PI, TAU};

/// Wraps an angle in degrees to `(-180, 180]`: the signed difference the
/// shorter way round when `d` is a difference of headings.
pub fn wrap180(d: f64) -> f64 {
    let x = (d + 180.0).rem_euclid(360.0) - 180.0;
    if x <= -180.0 { x + 360.0 } else { x }
}

/// Wraps an angle in radians to `(-π, π]`.
pub fn wrap_pi(a: f64) -> f64 {
    let w = (a + PI).rem_euclid(TAU) - PI;
    if w <= -PI { w + TAU } else { w }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn wrap180_at_the_edges() {
        assert_eq!(wrap180(180.0), 180.0);
        assert_eq!(wrap180(-180.0), 180.0);
        assert_eq!(wrap180(540.0), 180.0);
        assert_eq!(wrap180(-540.0), 180.0);
        assert_eq!(wrap180(360.0), 0.0);
        assert_eq!(wrap180(-360.0), 0.0);
        assert_eq!(wrap180(0.0), 0.0);
        assert_eq!(wrap180(190.0), -170.0);
        assert_eq!(wrap180(-190.0), 170.0);
        assert_eq!(wrap180(179.5), 179.5);
        assert_eq!(wrap180(-179.5), -179.5);
        assert_eq!(wrap180(725.0), 5.0);
        // Just below -180 comes out just below +180, never at -180.
        let w = wrap180(-180.0 - 1e-9);
        assert!(w > 179.9 && w <= 180.0, "{w}");
        let w = wrap180(-180.0 + 1e-9);
        assert!(w > -180.0 && w < -179.9, "{w}");
        assert!(wrap180(f64::NAN).is_nan());
        assert!(wrap180(f64::INFINITY).is_nan());
        assert!(wrap180(f64::NEG_INFINITY).is_nan());
    }

    #[test]
    fn wrap180_keeps_the_angle_modulo_a_turn() {
        for i in -2000..2000 {
            let d = f64::from(i) * 0.73;
            let w = wrap180(d);
            assert!(w > -180.0 && w <= 180.0, "{d} -> {w}");
            let turns = (d - w) / 360.0;
            assert!((turns - turns.round()).abs() < 1e-12, "{d} -> {w}");
        }
    }

    #[test]
    fn wrap_pi_is_in_range() {
        assert_eq!(wrap_pi(PI), PI);
        assert_eq!(wrap_pi(-PI), PI);
        assert_eq!(wrap_pi(0.0), 0.0);
        assert!(wrap_pi(f64::NAN).is_nan());
        for a in [-10.0, -PI, 0.0, 3.0, PI, 7.0] {
            let w = wrap_pi(a);
            assert!(w > -PI && w <= PI, "{a} -> {w}");
            let turns = (a - w) / TAU;
            assert!((turns - turns.round()).abs() < 1e-12, "{a} -> {w}");
        }
    }
}
