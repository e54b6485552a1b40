//! The homography from exactly four point pairs: the 8×8 linear system with
//! `h₃₃ = 1`, solved on Hartley-normalised coordinates, after checking that
//! no three points of either set are collinear and no two coincide.

use nalgebra::{Matrix3, Point2, SMatrix, SVector};

use super::GeometryError;

/// Relative tolerance for the collinearity test: twice a triangle's area
/// divided by its longest squared edge (the sine of its smallest angle,
/// roughly) below this is called collinear.
pub const COLLINEAR_TOL: f64 = 1e-3;

/// Relative tolerance for two points coinciding, against the set's spread.
pub const COLLAPSE_TOL: f64 = 1e-9;

/// Similarity that moves the centroid to the origin and the mean distance
/// to √2 (Hartley). Returns `None` when the points have no spread.
fn hartley4(pts: &[Point2<f64>; 4]) -> Option<(Matrix3<f64>, [Point2<f64>; 4])> {
    let cx = pts.iter().map(|p| p.x).sum::<f64>() / 4.0;
    let cy = pts.iter().map(|p| p.y).sum::<f64>() / 4.0;
    let mean_d = pts
        .iter()
        .map(|p| ((p.x - cx).powi(2) + (p.y - cy).powi(2)).sqrt())
        .sum::<f64>()
        / 4.0;
    if mean_d <= 0.0 || !mean_d.is_finite() {
        return None;
    }
    let s = std::f64::consts::SQRT_2 / mean_d;
    let t = Matrix3::new(s, 0.0, -s * cx, 0.0, s, -s * cy, 0.0, 0.0, 1.0);
    let out = pts.map(|p| Point2::new(s * (p.x - cx), s * (p.y - cy)));
    Some((t, out))
}

fn check_set(pts: &[Point2<f64>; 4], side: &'static str) -> Result<(), GeometryError> {
    if pts.iter().any(|p| !p.x.is_finite() || !p.y.is_finite()) {
        return Err(GeometryError::NonFinite);
    }
    let mut max_d2: f64 = 0.0;
    for i in 0..4 {
        for j in i + 1..4 {
            max_d2 = max_d2.max((pts[i] - pts[j]).norm_squared());
        }
    }
    for i in 0..4 {
        for j in i + 1..4 {
            let d2 = (pts[i] - pts[j]).norm_squared();
            if d2 <= COLLAPSE_TOL * COLLAPSE_TOL * max_d2 || max_d2 == 0.0 {
                return Err(GeometryError::Collapsed {
                    side,
                    spread: d2.sqrt(),
                });
            }
        }
    }
    const TRIPLES: [(usize, usize, usize); 4] = [(0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3)];
    for (i, j, k) in TRIPLES {
        let a = pts[j] - pts[i];
        let b = pts[k] - pts[i];
        let c = pts[k] - pts[j];
        let area2 = (a.x * b.y - a.y * b.x).abs();
        let longest = a.norm_squared().max(b.norm_squared()).max(c.norm_squared());
        if area2 <= COLLINEAR_TOL * longest {
            return Err(GeometryError::Collinear { side, i, j, k });
        }
    }
    Ok(())
}

/// The homography `H` with `dst_i ~ H·src_i` for exactly four pairs, scaled
/// so that `h₃₃ = 1`.
///
/// Errors: [`GeometryError::Collapsed`] when two points of a set coincide,
/// [`GeometryError::Collinear`] when any three of a set's four points are
/// collinear, [`GeometryError::Degenerate`] when the linear system is
/// singular anyway, [`GeometryError::NonFinite`] on NaN/inf input.
pub fn homography_from_4(
    src: &[Point2<f64>; 4],
    dst: &[Point2<f64>; 4],
) -> Result<Matrix3<f64>, GeometryError> {
    check_set(src, "source")?;
    check_set(dst, "destination")?;
    let (Some((ts, s)), Some((td, d))) = (hartley4(src), hartley4(dst)) else {
        return Err(GeometryError::Collapsed {
            side: "source",
            spread: 0.0,
        });
    };
    // For each pair: u = (h0 x + h1 y + h2) / (h6 x + h7 y + 1), same for v.
    let mut a = SMatrix::<f64, 8, 8>::zeros();
    let mut b = SVector::<f64, 8>::zeros();
    for i in 0..4 {
        let (x, y) = (s[i].x, s[i].y);
        let (u, v) = (d[i].x, d[i].y);
        let r = 2 * i;
        a[(r, 0)] = x;
        a[(r, 1)] = y;
        a[(r, 2)] = 1.0;
        a[(r, 6)] = -u * x;
        a[(r, 7)] = -u * y;
        b[r] = u;
        a[(r + 1, 3)] = x;
        a[(r + 1, 4)] = y;
        a[(r + 1, 5)] = 1.0;
        a[(r + 1, 6)] = -v * x;
        a[(r + 1, 7)] = -v * y;
        b[r + 1] = v;
    }
    let h = a.lu().solve(&b).ok_or(GeometryError::Degenerate {
        what: "singular 8x8 homography system",
    })?;
    let hn = Matrix3::new(h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], 1.0);
    let td_inv = td.try_inverse().ok_or(GeometryError::Degenerate {
        what: "normalisation",
    })?;
    let full = td_inv * hn * ts;
    let h33 = full[(2, 2)];
    if !h33.is_finite() || h33.abs() < 1e-14 * full.norm() {
        return Err(GeometryError::Degenerate {
            what: "homography maps the source centroid to infinity",
        });
    }
    let out = full / h33;
    if out.iter().any(|v| !v.is_finite()) {
        return Err(GeometryError::NonFinite);
    }
    Ok(out)
}

/// Applies a homography to a point; `None` if it maps to infinity.
pub fn apply_homography(h: &Matrix3<f64>, p: &Point2<f64>) -> Option<Point2<f64>> {
    let w = h[(2, 0)] * p.x + h[(2, 1)] * p.y + h[(2, 2)];
    if w.abs() < 1e-15 {
        return None;
    }
    Some(Point2::new(
        (h[(0, 0)] * p.x + h[(0, 1)] * p.y + h[(0, 2)]) / w,
        (h[(1, 0)] * p.x + h[(1, 1)] * p.y + h[(1, 2)]) / w,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recovers_a_known_homography_exactly() {
        let h_true = Matrix3::new(1.2, 0.1, 30.0, -0.05, 0.9, -12.0, 1e-4, -2e-4, 1.0);
        let src = [
            Point2::new(10.0, 20.0),
            Point2::new(600.0, 40.0),
            Point2::new(580.0, 430.0),
            Point2::new(30.0, 460.0),
        ];
        let dst = src.map(|p| apply_homography(&h_true, &p).unwrap());
        let h = homography_from_4(&src, &dst).unwrap();
        assert!((h - h_true).norm() < 1e-9, "{h}");
        // An interior point also maps right.
        let q = Point2::new(300.0, 250.0);
        let a = apply_homography(&h, &q).unwrap();
        let b = apply_homography(&h_true, &q).unwrap();
        assert!((a - b).norm() < 1e-8);
    }

    #[test]
    fn refuses_collinear_and_collapsed_sets() {
        let good = [
            Point2::new(0.0, 0.0),
            Point2::new(1.0, 0.0),
            Point2::new(1.0, 1.0),
            Point2::new(0.0, 1.0),
        ];
        let collinear = [
            Point2::new(0.0, 0.0),
            Point2::new(1.0, 1.0),
            Point2::new(0.3, 0.9),
            Point2::new(2.0, 2.0),
        ];
        match homography_from_4(&good, &collinear) {
            Err(GeometryError::Collinear {
                side: "destination",
                i: 0,
                j: 1,
                k: 3,
            }) => {}
            other => panic!("{other:?}"),
        }
        let collapsed = [
            Point2::new(0.0, 0.0),
            Point2::new(0.0, 0.0),
            Point2::new(1.0, 1.0),
            Point2::new(0.0, 1.0),
        ];
        assert!(matches!(
            homography_from_4(&collapsed, &good),
            Err(GeometryError::Collapsed { side: "source", .. })
        ));
        let nan = [Point2::new(f64::NAN, 0.0), good[1], good[2], good[3]];
        assert!(matches!(
            homography_from_4(&nan, &good),
            Err(GeometryError::NonFinite)
        ));
    }
}
