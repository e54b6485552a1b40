//! Shot computation behind a trait, anchor validation, and the desired-shot
//! warp (the keyframe seen through the homography of the four anchors).

use std::sync::Arc;

use image::{GrayImage, Luma};
use nalgebra::{Matrix3, Point2};

use super::store::Localisation;
use crate::geometry::homography4::{apply_homography, homography_from_4};

/// Why a shot request cannot be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShotError {
    /// No keyframe with this id.
    #[error("no keyframe {id}")]
    UnknownKeyframe {
        /// The id asked for.
        id: u64,
    },
    /// The anchors do not describe a picture.
    #[error("bad anchors: {reason}")]
    BadAnchors {
        /// What is wrong.
        reason: String,
    },
    /// The picture is unusable (size, content).
    #[error("bad image: {reason}")]
    BadImage {
        /// What is wrong.
        reason: String,
    },
}

/// What a shot computation produces.
#[derive(Debug, Clone)]
pub struct ShotComputation {
    /// The desired-shot image (the picture the operator asked for).
    pub desired: Option<GrayImage>,
    /// The localisation, or why there is none.
    pub localisation: Result<Localisation, String>,
}

/// Computes desired shots. The daemon plugs the real shot service in
/// (`crate::shot`: desired shot -> BoW query -> PnP -> target pose).
pub trait ShotComputer: Send + Sync {
    /// A shot described by four anchors on a keyframe; `size` is the
    /// desired picture's width and height, pixels.
    fn shot_from_anchors(
        &self,
        keyframe_id: u64,
        anchors: &[[f64; 2]; 4],
        size: (u32, u32),
    ) -> Result<ShotComputation, ShotError>;
    /// A shot given as a photograph.
    fn shot_from_photo(&self, photo: &GrayImage) -> Result<ShotComputation, ShotError>;
}

/// Tunables of anchor validation.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// How far outside the keyframe an anchor may lie, as a fraction of the
    /// keyframe's size.
    pub max_outside_fraction: f64,
    /// Smallest area of the anchor quadrilateral, pixels^2.
    pub min_area_px2: f64,
    /// Largest desired-shot side, pixels.
    pub max_output_side: u32,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            max_outside_fraction: 0.5,
            min_area_px2: 400.0,
            max_output_side: 4096,
        }
    }
}

/// Check four anchors on a `width` x `height` keyframe: finite, not too far
/// outside, a convex quadrilateral in clockwise order (image axes: x right,
/// y down; top-left, top-right, bottom-right, bottom-left) of a useful area.
pub fn validate_anchors(
    anchors: &[[f64; 2]; 4],
    width: u32,
    height: u32,
    params: &Params,
) -> Result<(), ShotError> {
    let bad = |reason: String| Err(ShotError::BadAnchors { reason });
    let (w, h) = (width as f64, height as f64);
    let mx = w * params.max_outside_fraction;
    let my = h * params.max_outside_fraction;
    for (i, a) in anchors.iter().enumerate() {
        if !a[0].is_finite() || !a[1].is_finite() {
            return bad(format!("anchor {i} is not finite"));
        }
        if a[0] < -mx || a[0] > w + mx || a[1] < -my || a[1] > h + my {
            return bad(format!(
                "anchor {i} ({:.1}, {:.1}) is too far outside the {width}x{height} keyframe",
                a[0], a[1]
            ));
        }
    }
    // Cross products of consecutive edges: all positive for a convex,
    // clockwise-on-screen (y down) quadrilateral.
    let mut area2 = 0.0;
    for i in 0..4 {
        let p = anchors[i];
        let q = anchors[(i + 1) % 4];
        let r = anchors[(i + 2) % 4];
        let cross = (q[0] - p[0]) * (r[1] - q[1]) - (q[1] - p[1]) * (r[0] - q[0]);
        if cross <= 0.0 {
            return bad(format!(
                "the anchors must form a convex quadrilateral in the order top-left, top-right, bottom-right, bottom-left (turn at anchor {} is not clockwise)",
                (i + 1) % 4
            ));
        }
        area2 += p[0] * q[1] - q[0] * p[1];
    }
    let area = area2.abs() / 2.0;
    if area < params.min_area_px2 {
        return bad(format!(
            "the anchors enclose {area:.0} px^2, less than {:.0}",
            params.min_area_px2
        ));
    }
    Ok(())
}

/// The homography taking desired-shot pixels to keyframe pixels.
pub fn shot_to_keyframe(
    anchors: &[[f64; 2]; 4],
    size: (u32, u32),
) -> Result<Matrix3<f64>, ShotError> {
    let (w, h) = (size.0 as f64, size.1 as f64);
    let corners = [
        Point2::new(0.0, 0.0),
        Point2::new(w, 0.0),
        Point2::new(w, h),
        Point2::new(0.0, h),
    ];
    let dst = anchors.map(|a| Point2::new(a[0], a[1]));
    homography_from_4(&corners, &dst).map_err(|e| ShotError::BadAnchors {
        reason: e.to_string(),
    })
}

/// Warp `src` through `h` (output pixel -> source pixel, pixel centres at
/// +0.5) into a `size` image with bilinear sampling; outside is black.
pub fn warp(src: &GrayImage, h: &Matrix3<f64>, size: (u32, u32)) -> GrayImage {
    let (sw, sh) = (src.width() as f64, src.height() as f64);
    let raw = src.as_raw();
    let stride = src.width() as usize;
    GrayImage::from_fn(size.0, size.1, |x, y| {
        let p = Point2::new(x as f64 + 0.5, y as f64 + 0.5);
        let Some(q) = apply_homography(h, &p) else {
            return Luma([0]);
        };
        let (fx, fy) = (q.x - 0.5, q.y - 0.5);
        if !(fx >= 0.0 && fy >= 0.0 && fx <= sw - 1.0 && fy <= sh - 1.0) {
            return Luma([0]);
        }
        let (x0, y0) = (fx.floor() as usize, fy.floor() as usize);
        let x1 = (x0 + 1).min(stride - 1);
        let y1 = (y0 + 1).min(src.height() as usize - 1);
        let (ax, ay) = (fx - x0 as f64, fy - y0 as f64);
        let g = |xx: usize, yy: usize| raw[yy * stride + xx] as f64;
        let v = (1.0 - ay) * ((1.0 - ax) * g(x0, y0) + ax * g(x1, y0))
            + ay * ((1.0 - ax) * g(x0, y1) + ax * g(x1, y1));
        Luma([v.round().clamp(0.0, 255.0) as u8])
    })
}

/// A source of keyframe images, by id.
pub trait KeyframeImages: Send + Sync {
    /// The keyframe's grey image.
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>>;
}

/// The shot computer used until the shot localisation (`crate::shot`) is
/// wired in: it validates anchors and renders the desired shot, and reports
/// every shot as not localised with the reason.
pub struct WarpOnly<K> {
    /// Keyframe images.
    pub keyframes: K,
    /// Validation tunables.
    pub params: Params,
}

impl<K: KeyframeImages> ShotComputer for WarpOnly<K> {
    fn shot_from_anchors(
        &self,
        keyframe_id: u64,
        anchors: &[[f64; 2]; 4],
        size: (u32, u32),
    ) -> Result<ShotComputation, ShotError> {
        let img = self
            .keyframes
            .keyframe_image(keyframe_id)
            .ok_or(ShotError::UnknownKeyframe { id: keyframe_id })?;
        validate_anchors(anchors, img.width(), img.height(), &self.params)?;
        let max = self.params.max_output_side;
        if size.0 == 0 || size.1 == 0 || size.0 > max || size.1 > max {
            return Err(ShotError::BadImage {
                reason: format!("output size {}x{} outside 1..={max}", size.0, size.1),
            });
        }
        let h = shot_to_keyframe(anchors, size)?;
        Ok(ShotComputation {
            desired: Some(warp(&img, &h, size)),
            localisation: Err("shot localisation is not available in this build".into()),
        })
    }

    fn shot_from_photo(&self, photo: &GrayImage) -> Result<ShotComputation, ShotError> {
        if photo.width() < 32 || photo.height() < 32 {
            return Err(ShotError::BadImage {
                reason: format!("{}x{} is too small", photo.width(), photo.height()),
            });
        }
        Ok(ShotComputation {
            desired: Some(photo.clone()),
            localisation: Err("shot localisation is not available in this build".into()),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const SQ: [[f64; 2]; 4] = [
        [100.0, 100.0],
        [300.0, 100.0],
        [300.0, 250.0],
        [100.0, 250.0],
    ];

    #[test]
    fn anchors_validation() {
        let p = Params::default();
        assert!(validate_anchors(&SQ, 640, 480, &p).is_ok());
        // Counter-clockwise order, a bow tie, a sliver, NaN, far outside.
        let mut ccw = SQ;
        ccw.reverse();
        let bowtie = [SQ[0], SQ[1], SQ[3], SQ[2]];
        let sliver = [[0.0, 0.0], [300.0, 0.0], [300.0, 1.0], [0.0, 1.0]];
        let nan = [[f64::NAN, 0.0], SQ[1], SQ[2], SQ[3]];
        let far = [[-1000.0, 0.0], SQ[1], SQ[2], SQ[3]];
        for bad in [ccw, bowtie, sliver, nan, far] {
            assert!(
                matches!(
                    validate_anchors(&bad, 640, 480, &p),
                    Err(ShotError::BadAnchors { .. })
                ),
                "{bad:?}"
            );
        }
    }

    #[test]
    fn warp_of_an_axis_aligned_rectangle_is_a_crop() {
        let src = GrayImage::from_fn(640, 480, |x, y| Luma([((x * 7 + y * 3) % 251) as u8]));
        let h = shot_to_keyframe(&SQ, (200, 150)).unwrap();
        let out = warp(&src, &h, (200, 150));
        for (x, y) in [(0, 0), (57, 33), (199, 149), (120, 80)] {
            assert_eq!(
                out.get_pixel(x, y),
                src.get_pixel(100 + x, 100 + y),
                "({x},{y})"
            );
        }
    }
}
