//! The desired shot from four anchors (the paper's method).
//!
//! The operator places four anchors on a keyframe where the frame's corners
//! (0,0), (w-1,0), (w-1,h-1), (0,h-1) should go. The homography `H` with
//! `anchor_i ~ H·corner_i` maps a pixel of the desired shot to the keyframe
//! pixel it shows, so the shot is the keyframe resampled at `H·p` (inverse
//! mapping, bilinear), the same size as the frame, black where `H·p` has no
//! source; a mask marks the pixels that had one.

use image::GrayImage;
use nalgebra::{Matrix3, Point2};

use super::{ShotError, frame_corners};
use crate::geometry::homography_from_4;

/// Tunables of the anchor checks.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AnchorParams {
    /// How far an anchor may lie outside the image, as a multiple of the
    /// image size along each axis (1.0: up to one width left or right of the
    /// image, one height above or below it).
    pub max_outside_factor: f64,
    /// Smallest area of the anchor quadrilateral, as a fraction of the image area.
    pub min_area_fraction: f64,
    /// Largest condition number (ratio of extreme singular values) of the
    /// transform expressed in image-size units (corners mapped to the unit square).
    pub max_condition: f64,
}

impl Default for AnchorParams {
    fn default() -> Self {
        AnchorParams {
            max_outside_factor: 1.0,
            min_area_fraction: 0.01,
            max_condition: 1e4,
        }
    }
}

impl AnchorParams {
    fn validate(&self) -> Result<(), ShotError> {
        if !self.max_outside_factor.is_finite() || self.max_outside_factor < 0.0 {
            return Err(ShotError::InvalidParams {
                name: "max_outside_factor",
                reason: "must be finite and >= 0",
            });
        }
        if !self.min_area_fraction.is_finite() || self.min_area_fraction < 0.0 {
            return Err(ShotError::InvalidParams {
                name: "min_area_fraction",
                reason: "must be finite and >= 0",
            });
        }
        if self.max_condition.is_nan() || self.max_condition <= 1.0 {
            return Err(ShotError::InvalidParams {
                name: "max_condition",
                reason: "must be > 1",
            });
        }
        Ok(())
    }
}

/// A desired shot: the warped image, its validity mask and the transform.
#[derive(Debug, Clone)]
pub struct DesiredShot {
    /// The shot, the frame's size; black where no source pixel exists.
    pub image: GrayImage,
    /// 255 where the shot has a source pixel, 0 in the black fill.
    pub mask: GrayImage,
    /// `H`: shot pixel -> keyframe pixel (`anchor_i ~ H·corner_i`), `h33 = 1`.
    pub shot_to_source: Matrix3<f64>,
}

/// Signed turn at vertex `i` of the quadrilateral: z of `(p_i - p_{i-1}) x (p_{i+1} - p_i)`.
fn turn(q: &[Point2<f64>; 4], i: usize) -> f64 {
    let a = q[i] - q[(i + 3) % 4];
    let b = q[(i + 1) % 4] - q[i];
    a.x * b.y - a.y * b.x
}

/// `z` of `(b - a) x (c - a)`: positive when `c` is left of `a -> b`.
fn orient(a: &Point2<f64>, b: &Point2<f64>, c: &Point2<f64>) -> f64 {
    (b.x - a.x) * (c.y - a.y) - (b.y - a.y) * (c.x - a.x)
}

/// The two opposite edges that cross, if any (`(a, b, c, d)`: the edge
/// from anchor a to b crosses the one from c to d). Only a proper crossing
/// counts; touching or collinear edges are left to the area and convexity
/// checks.
fn crossing_edges(q: &[Point2<f64>; 4]) -> Option<(usize, usize, usize, usize)> {
    for (a, b, c, d) in [(0, 1, 2, 3), (1, 2, 3, 0)] {
        let (o1, o2) = (orient(&q[a], &q[b], &q[c]), orient(&q[a], &q[b], &q[d]));
        let (o3, o4) = (orient(&q[c], &q[d], &q[a]), orient(&q[c], &q[d], &q[b]));
        if o1 * o2 < 0.0 && o3 * o4 < 0.0 {
            return Some((a, b, c, d));
        }
    }
    None
}

/// Signed (shoelace) area; positive for the corners' winding in image
/// coordinates (y down: top-left, top-right, bottom-right, bottom-left).
fn signed_area(q: &[Point2<f64>; 4]) -> f64 {
    let mut s = 0.0;
    for i in 0..4 {
        let (p, n) = (q[i], q[(i + 1) % 4]);
        s += p.x * n.y - n.x * p.y;
    }
    0.5 * s
}

/// Checks the anchors and solves the transform `H` (corner -> anchor, `h33 = 1`)
/// for a `width`x`height` frame.
///
/// Refusals, in this order: [`ShotError::NonFiniteAnchor`],
/// [`ShotError::AnchorOutOfBounds`], [`ShotError::Crossed`] (a bow tie,
/// whose lobes' areas cancel in the signed area), [`ShotError::Collapsed`],
/// [`ShotError::MirroredWinding`], [`ShotError::NotConvex`],
/// [`ShotError::NearSingular`].
pub fn homography_from_anchors(
    width: u32,
    height: u32,
    anchors: &[Point2<f64>; 4],
    params: &AnchorParams,
) -> Result<Matrix3<f64>, ShotError> {
    params.validate()?;
    if width < 2 || height < 2 {
        return Err(ShotError::ImageSize {
            width,
            height,
            expected_width: width.max(2),
            expected_height: height.max(2),
        });
    }
    let (w, h) = (width as f64, height as f64);
    for (index, a) in anchors.iter().enumerate() {
        if !a.x.is_finite() || !a.y.is_finite() {
            return Err(ShotError::NonFiniteAnchor { index });
        }
    }
    let (mx, my) = (params.max_outside_factor * w, params.max_outside_factor * h);
    for (index, a) in anchors.iter().enumerate() {
        if a.x < -mx || a.x > w - 1.0 + mx || a.y < -my || a.y > h - 1.0 + my {
            return Err(ShotError::AnchorOutOfBounds {
                index,
                x: a.x,
                y: a.y,
                limit_px: mx.max(my),
            });
        }
    }
    if let Some((a, b, c, d)) = crossing_edges(anchors) {
        return Err(ShotError::Crossed { a, b, c, d });
    }
    let area = signed_area(anchors);
    let min_area = params.min_area_fraction * w * h;
    if area.abs() < min_area || area == 0.0 {
        return Err(ShotError::Collapsed {
            area_px2: area.abs(),
            min_area_px2: min_area,
        });
    }
    let turns = [
        turn(anchors, 0),
        turn(anchors, 1),
        turn(anchors, 2),
        turn(anchors, 3),
    ];
    if turns.iter().all(|t| *t < 0.0) {
        return Err(ShotError::MirroredWinding);
    }
    if let Some(vertex) = turns.iter().position(|t| *t <= 0.0) {
        return Err(ShotError::NotConvex { vertex });
    }
    let corners = frame_corners(width, height);
    let singular = |condition: f64| ShotError::NearSingular {
        condition,
        max_condition: params.max_condition,
    };
    let hm = homography_from_4(&corners, anchors).map_err(|_| singular(f64::INFINITY))?;
    // Condition in image-size units: S^-1 H S with S scaling the unit square to the frame.
    let s = Matrix3::new(w - 1.0, 0.0, 0.0, 0.0, h - 1.0, 0.0, 0.0, 0.0, 1.0);
    let s_inv = Matrix3::new(
        1.0 / (w - 1.0),
        0.0,
        0.0,
        0.0,
        1.0 / (h - 1.0),
        0.0,
        0.0,
        0.0,
        1.0,
    );
    let hn = s_inv * hm * s;
    let sv = hn.singular_values();
    let (smax, smin) = (sv.max(), sv.min());
    let condition = if smin > 0.0 {
        smax / smin
    } else {
        f64::INFINITY
    };
    if !condition.is_finite() || condition > params.max_condition {
        return Err(singular(condition));
    }
    Ok(hm)
}

/// Fractional bits of the bilinear weights.
const WBITS: u32 = 11;
/// One in fixed point.
const WONE: u32 = 1 << WBITS;

/// Resamples `src` at `h·p` for every pixel `p` of a `width`x`height`
/// output (bilinear). Pixels whose source (with its bilinear support) lies
/// outside `src`, or behind the transform's horizon, are black with mask 0.
/// Returns `(image, mask)`.
pub fn warp_perspective(
    src: &GrayImage,
    h: &Matrix3<f64>,
    width: u32,
    height: u32,
) -> (GrayImage, GrayImage) {
    let (sw, sh) = (src.width() as usize, src.height() as usize);
    let (ow, oh) = (width as usize, height as usize);
    let mut out = vec![0u8; ow * oh];
    let mut mask = vec![0u8; ow * oh];
    let s = src.as_raw();
    if sw >= 2 && sh >= 2 {
        let (xmax, ymax) = ((sw - 1) as f64, (sh - 1) as f64);
        let (dnx, dny, dd) = (h[(0, 0)], h[(1, 0)], h[(2, 0)]);
        for y in 0..oh {
            let yf = y as f64;
            // Numerators and denominator are affine in x along a row.
            let (mut nx, mut ny, mut d) = (
                h[(0, 1)] * yf + h[(0, 2)],
                h[(1, 1)] * yf + h[(1, 2)],
                h[(2, 1)] * yf + h[(2, 2)],
            );
            let out_row = &mut out[y * ow..(y + 1) * ow];
            let mask_row = &mut mask[y * ow..(y + 1) * ow];
            for (o, m) in out_row.iter_mut().zip(mask_row.iter_mut()) {
                if d > 1e-12 {
                    let inv = 1.0 / d;
                    let sx = nx * inv;
                    let sy = ny * inv;
                    if sx >= 0.0 && sy >= 0.0 && sx <= xmax && sy <= ymax {
                        let x0 = (sx as usize).min(sw - 2);
                        let y0 = (sy as usize).min(sh - 2);
                        // Fixed-point bilinear weights (WBITS fractional bits).
                        let fx = ((sx - x0 as f64) * WONE as f64 + 0.5) as u32;
                        let fy = ((sy - y0 as f64) * WONE as f64 + 0.5) as u32;
                        let i = y0 * sw + x0;
                        let top = s[i] as u32 * (WONE - fx) + s[i + 1] as u32 * fx;
                        let bot = s[i + sw] as u32 * (WONE - fx) + s[i + sw + 1] as u32 * fx;
                        let v =
                            (top * (WONE - fy) + bot * fy + (1 << (2 * WBITS - 1))) >> (2 * WBITS);
                        *o = v.min(255) as u8;
                        *m = 255;
                    }
                }
                nx += dnx;
                ny += dny;
                d += dd;
            }
        }
    }
    // Buffers have exactly width*height bytes, so these cannot fail.
    let image =
        GrayImage::from_raw(width, height, out).unwrap_or_else(|| GrayImage::new(width, height));
    let mask =
        GrayImage::from_raw(width, height, mask).unwrap_or_else(|| GrayImage::new(width, height));
    (image, mask)
}

/// The desired shot of a keyframe image from four anchors (see the module
/// documentation). Errors as [`homography_from_anchors`].
pub fn desired_shot_from_anchors(
    image: &GrayImage,
    anchors: &[Point2<f64>; 4],
    params: &AnchorParams,
) -> Result<DesiredShot, ShotError> {
    let (w, h) = image.dimensions();
    let hm = homography_from_anchors(w, h, anchors, params)?;
    let (img, mask) = warp_perspective(image, &hm, w, h);
    Ok(DesiredShot {
        image: img,
        mask,
        shot_to_source: hm,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const W: u32 = 320;
    const H: u32 = 240;

    fn p(x: f64, y: f64) -> Point2<f64> {
        Point2::new(x, y)
    }

    fn solve(a: [Point2<f64>; 4]) -> Result<Matrix3<f64>, ShotError> {
        homography_from_anchors(W, H, &a, &AnchorParams::default())
    }

    #[test]
    fn identity_anchors_give_identity() {
        let hm = solve(frame_corners(W, H)).unwrap();
        assert!((hm - Matrix3::identity()).abs().max() < 1e-9, "{hm}");
    }

    #[test]
    fn each_bad_case_has_its_own_error() {
        let good = [
            p(20.0, 10.0),
            p(300.0, 30.0),
            p(290.0, 220.0),
            p(10.0, 230.0),
        ];
        assert!(solve(good).is_ok());
        let mut nan = good;
        nan[2].x = f64::NAN;
        assert_eq!(solve(nan), Err(ShotError::NonFiniteAnchor { index: 2 }));
        let mut far = good;
        far[1] = p(319.0 + 321.0, 30.0);
        assert!(matches!(
            solve(far),
            Err(ShotError::AnchorOutOfBounds { index: 1, .. })
        ));
        // Just inside the bound is fine.
        let mut near = good;
        near[1] = p(319.0 + 319.0, 30.0);
        assert!(solve(near).is_ok());
        let tiny = [
            p(100.0, 100.0),
            p(110.0, 100.0),
            p(110.0, 107.0),
            p(100.0, 107.0),
        ];
        assert!(matches!(solve(tiny), Err(ShotError::Collapsed { .. })));
        let point = [p(100.0, 100.0); 4];
        assert!(matches!(solve(point), Err(ShotError::Collapsed { .. })));
        // Left-right mirror of the corners.
        let mirrored = [good[1], good[0], good[3], good[2]];
        assert_eq!(solve(mirrored), Err(ShotError::MirroredWinding));
        // An arrowhead: the bottom-right anchor pushed inside the triangle of the others.
        let dart = [p(0.0, 0.0), p(300.0, 0.0), p(100.0, 80.0), p(0.0, 230.0)];
        assert_eq!(solve(dart), Err(ShotError::NotConvex { vertex: 2 }));
        // A bow tie with unequal lobes (self-intersecting): crossed, not
        // "collapsed" although its lobes' signed areas nearly cancel.
        let bowtie = [p(0.0, 0.0), p(300.0, 0.0), p(0.0, 200.0), p(200.0, 230.0)];
        assert_eq!(
            solve(bowtie),
            Err(ShotError::Crossed {
                a: 1,
                b: 2,
                c: 3,
                d: 0
            })
        );
        // Nearly collinear but above a (lowered) area minimum: the transform is singular.
        let sliver = [
            p(0.0, 100.0),
            p(300.0, 100.0),
            p(300.0, 100.05),
            p(0.0, 100.04),
        ];
        let loose = AnchorParams {
            min_area_fraction: 0.0,
            ..AnchorParams::default()
        };
        assert!(matches!(
            homography_from_anchors(W, H, &sliver, &loose),
            Err(ShotError::NearSingular { .. })
        ));
    }

    #[test]
    fn degenerate_image_and_bad_params_have_their_own_errors() {
        let good = [
            p(20.0, 10.0),
            p(300.0, 30.0),
            p(290.0, 220.0),
            p(10.0, 230.0),
        ];
        // An image too small to warp (empty, or one pixel wide).
        for (w, h) in [(0, 0), (1, 240), (320, 1)] {
            let img = GrayImage::new(w, h);
            assert!(
                matches!(
                    desired_shot_from_anchors(&img, &good, &AnchorParams::default()),
                    Err(ShotError::ImageSize { width, height, .. }) if width == w && height == h
                ),
                "{w}x{h}"
            );
        }
        let bad = [
            (
                AnchorParams {
                    max_outside_factor: -1.0,
                    ..AnchorParams::default()
                },
                "max_outside_factor",
            ),
            (
                AnchorParams {
                    min_area_fraction: f64::NAN,
                    ..AnchorParams::default()
                },
                "min_area_fraction",
            ),
            (
                AnchorParams {
                    max_condition: 0.5,
                    ..AnchorParams::default()
                },
                "max_condition",
            ),
        ];
        for (params, which) in bad {
            assert!(
                matches!(
                    homography_from_anchors(W, H, &good, &params),
                    Err(ShotError::InvalidParams { name, .. }) if name == which
                ),
                "{which}"
            );
        }
    }

    #[test]
    fn crossed_anchors_are_reported_as_crossed() {
        let bowtie = [p(0.0, 0.0), p(300.0, 0.0), p(30.0, 200.0), p(250.0, 150.0)];
        assert!(matches!(solve(bowtie), Err(ShotError::Crossed { .. })));
        // Equal lobes: the signed area is exactly zero, which the area
        // check alone called "collapsed: area 0 px²".
        let x = [
            p(100.0, 100.0),
            p(300.0, 300.0),
            p(300.0, 100.0),
            p(100.0, 300.0),
        ];
        let e = solve(x).unwrap_err();
        assert_eq!(
            e,
            ShotError::Crossed {
                a: 0,
                b: 1,
                c: 2,
                d: 3
            }
        );
        assert!(e.to_string().contains("cross"), "{e}");
        // Top and bottom swapped (0-1 crosses 2-3 instead).
        let swapped = [
            p(100.0, 100.0),
            p(300.0, 100.0),
            p(100.0, 300.0),
            p(300.0, 300.0),
        ];
        assert!(matches!(
            solve(swapped),
            Err(ShotError::Crossed { a: 1, b: 2, .. })
        ));
    }

    /// A smooth test pattern, exactly evaluable anywhere.
    fn pattern(x: f64, y: f64) -> f64 {
        128.0 + 60.0 * (x / 17.0).sin() * (y / 23.0).cos() + 40.0 * ((x + y) / 41.0).sin()
    }

    #[test]
    fn warp_reproduces_a_known_homography_within_one_grey_level() {
        // The source image is the pattern sampled on the pixel grid; the shot of
        // anchors `H·corner` must equal the pattern at `H·p` (bilinear error of a
        // smooth pattern is well below a grey level), away from the borders.
        let src = GrayImage::from_fn(W, H, |x, y| {
            image::Luma([pattern(x as f64, y as f64).round().clamp(0.0, 255.0) as u8])
        });
        let truth = Matrix3::new(0.8, 0.06, 30.0, -0.04, 0.85, 20.0, 2e-4, -1e-4, 1.0);
        let corners = frame_corners(W, H);
        let anchors =
            corners.map(|c| crate::geometry::homography4::apply_homography(&truth, &c).unwrap());
        let shot = desired_shot_from_anchors(&src, &anchors, &AnchorParams::default()).unwrap();
        let hn = shot.shot_to_source / shot.shot_to_source[(2, 2)];
        assert!((hn - truth).abs().max() < 1e-6, "{hn}");
        let mut worst = 0i32;
        let mut sum = 0.0;
        let mut checked = 0;
        for y in 3..H - 3 {
            for x in 3..W - 3 {
                let q =
                    crate::geometry::homography4::apply_homography(&truth, &p(x as f64, y as f64))
                        .unwrap();
                if q.x < 2.0 || q.y < 2.0 || q.x > W as f64 - 3.0 || q.y > H as f64 - 3.0 {
                    continue;
                }
                assert_eq!(shot.mask.get_pixel(x, y)[0], 255);
                let got = shot.image.get_pixel(x, y)[0] as i32;
                let want = pattern(q.x, q.y).round().clamp(0.0, 255.0) as i32;
                worst = worst.max((got - want).abs());
                sum += (got - want).abs() as f64;
                checked += 1;
            }
        }
        assert!(checked > (W * H / 2) as usize, "{checked}");
        let mean = sum / checked as f64;
        assert!(worst <= 1, "worst difference {worst} grey levels");
        assert!(mean < 0.3, "mean difference {mean} grey levels");
    }

    #[test]
    fn fill_outside_the_source_is_black_and_masked() {
        let src = GrayImage::from_pixel(W, H, image::Luma([200]));
        // Zoom out: the keyframe covers the middle of the shot only.
        let anchors = [
            p(-80.0, -60.0),
            p(399.0, -60.0),
            p(399.0, 299.0),
            p(-80.0, 299.0),
        ];
        let shot = desired_shot_from_anchors(&src, &anchors, &AnchorParams::default()).unwrap();
        assert_eq!(shot.image.get_pixel(0, 0)[0], 0);
        assert_eq!(shot.mask.get_pixel(0, 0)[0], 0);
        assert_eq!(shot.image.get_pixel(W / 2, H / 2)[0], 200);
        assert_eq!(shot.mask.get_pixel(W / 2, H / 2)[0], 255);
        let valid = shot.mask.pixels().filter(|m| m[0] == 255).count() as f64;
        // Source spans (W-1)/(W-1+160) of the shot's width and similarly in height.
        let expect = (W as f64) * (319.0 / 479.0) * (H as f64) * (239.0 / 359.0);
        assert!(
            (valid - expect).abs() / expect < 0.02,
            "{valid} vs {expect}"
        );
    }
}
