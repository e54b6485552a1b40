//! The operator's shot request: anchor validation, the anchor shot (the
//! keyframe warped), photo checks, and the computation behind a trait
//! ([`ShotComputer`]) that the API calls and the daemon implements.
//!
//! One pixel convention throughout, [`crate::shot::anchors`]'s: pixel
//! centres at integer coordinates (the camera model's), so the four anchors
//! are where the desired picture's corner pixels (0,0), (w-1,0), (w-1,h-1),
//! (0,h-1) go on the keyframe. Anchors are validated and warped by
//! [`crate::shot::homography_from_anchors`] and
//! [`crate::shot::warp_perspective`]; each refusal keeps its own
//! [`crate::shot::ShotError`] case.
//!
//! The keyframe is warped once, at its own size: that shot (with its mask)
//! is both the picture and what localisation matches. Only when the
//! operator asks for a picture of another size is the keyframe warped at
//! that size as well (straight from the keyframe, not from the first warp).

use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Matrix3, Point2};

use super::record::{Localisation, PhotoIntrinsics};
use crate::camera::Camera;
use crate::shot::{AnchorParams, DesiredShot, homography_from_anchors, warp_perspective};

/// Why a shot request cannot be computed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShotRequestError {
    /// No keyframe with this id.
    #[error("no keyframe {id}")]
    UnknownKeyframe {
        /// The id asked for.
        id: u64,
    },
    /// The anchors do not describe a picture; `source` says which check
    /// refused them (not finite, out of bounds, collapsed, mirrored, not
    /// convex, near-singular).
    #[error("bad anchors: {source}")]
    BadAnchors {
        /// The refusal of [`crate::shot::homography_from_anchors`].
        source: crate::shot::ShotError,
    },
    /// The picture is unusable (size, content).
    #[error("bad image: {reason}")]
    BadImage {
        /// What is wrong.
        reason: String,
    },
    /// The photo's intrinsics do not describe a camera.
    #[error("bad intrinsics: {reason}")]
    BadIntrinsics {
        /// What is wrong.
        reason: String,
    },
    /// A photo whose aspect ratio is not the map camera's: the map camera
    /// cannot be scaled to it, so its intrinsics must be given.
    #[error(
        "the photo is {width}x{height}, not the map camera's aspect ratio ({camera_width}x{camera_height}): \
         give its intrinsics as query parameters fx, fy, cx, cy (pixels, for this photo's size, \
         pixel centres at integers) and optionally k1, k2, p1, p2, k3"
    )]
    IntrinsicsRequired {
        /// Photo width, pixels.
        width: u32,
        /// Photo height, pixels.
        height: u32,
        /// Map camera width, pixels.
        camera_width: u32,
        /// Map camera height, pixels.
        camera_height: u32,
    },
}

/// Why a JPEG is not whole, if it is not: walks the segments from SOI
/// (skipping each marker segment by its length, so an EXIF thumbnail's
/// own end marker is not mistaken for the image's) and the entropy-coded
/// data of every scan, and wants the end-of-image marker before the bytes
/// run out. A file cut short in transfer decodes to a picture whose lower
/// part is grey, which would be localised as if it were the scene.
pub fn jpeg_truncation(bytes: &[u8]) -> Option<String> {
    let n = bytes.len();
    if n < 2 || bytes[0] != 0xFF || bytes[1] != 0xD8 {
        return Some("no JPEG start-of-image marker".into());
    }
    let cut = |at: usize, what: &str| {
        Some(format!(
            "the JPEG is truncated: {what} at byte {at} of {n}, no end-of-image marker"
        ))
    };
    let mut i = 2;
    loop {
        // Fill bytes (0xFF) may precede a marker.
        while i < n && bytes[i] == 0xFF && i + 1 < n && bytes[i + 1] == 0xFF {
            i += 1;
        }
        if i + 1 >= n {
            return cut(i, "the data ends between segments");
        }
        if bytes[i] != 0xFF {
            return Some(format!("the JPEG is damaged: no marker at byte {i} of {n}"));
        }
        let marker = bytes[i + 1];
        i += 2;
        match marker {
            0xD9 => return None,
            0x01 | 0xD0..=0xD7 => continue,
            _ => {}
        }
        if i + 2 > n {
            return cut(i, "a segment header is cut");
        }
        let len = usize::from(u16::from_be_bytes([bytes[i], bytes[i + 1]]));
        if len < 2 || i + len > n {
            return cut(i, "a segment is cut");
        }
        i += len;
        if marker == 0xDA {
            // Entropy-coded data up to the next marker that is neither a
            // stuffed zero nor a restart marker.
            loop {
                if i + 1 >= n {
                    return cut(n, "the scan data ends");
                }
                if bytes[i] == 0xFF && !matches!(bytes[i + 1], 0x00 | 0xD0..=0xD7 | 0xFF) {
                    break;
                }
                i += 1;
            }
        }
    }
}

/// What a shot computation produces.
#[derive(Debug, Clone)]
pub struct ShotComputation {
    /// The desired-shot image (the picture the operator asked for).
    pub desired: Option<GrayImage>,
    /// The localisation, or why there is none.
    pub localisation: Result<Localisation, NotLocalised>,
    /// When not localised: the keyframes the shot looks most like
    /// ([`crate::shot::nearest_keyframes`]); may be empty.
    pub nearest_keyframes: Vec<crate::shot::record::NearKeyframeJson>,
}

/// Why a shot has no localisation; its Display is the shot's `reason` in
/// the API.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum NotLocalised {
    /// This computer only makes the desired picture ([`WarpOnly`]).
    #[error("shot localisation is not available in this build")]
    Unavailable,
    /// The SLAM has no map yet.
    #[error("not localised: no map yet")]
    NoMap,
    /// Localisation ran and found no reliable pose.
    #[error("not localised: {0}")]
    Rejected(crate::shot::NotLocalizedReason),
    /// Localisation refused its input.
    #[error("not localised: {0}")]
    Failed(crate::shot::ShotError),
}

/// Computes desired shots. The daemon plugs the real shot service in
/// (`crate::shot`: desired shot -> BoW query -> PnP -> target pose).
pub trait ShotComputer: Send + Sync {
    /// A shot described by four anchors on a keyframe; `size` is the
    /// desired picture's width and height, pixels (None: the keyframe's).
    fn shot_from_anchors(
        &self,
        keyframe_id: u64,
        anchors: &[[f64; 2]; 4],
        size: Option<(u32, u32)>,
    ) -> Result<ShotComputation, ShotRequestError>;
    /// A shot given as a photograph, with its camera's intrinsics when it
    /// is not the map camera's (None: the map camera, scaled to the photo's
    /// size when that has the same aspect ratio), and its GPS tag when it
    /// has one (a place found far from it is refused, once the map is
    /// georeferenced).
    fn shot_from_photo(
        &self,
        photo: &GrayImage,
        intrinsics: Option<&PhotoIntrinsics>,
        gps: Option<&crate::shot::photo::GpsTag>,
    ) -> Result<ShotComputation, ShotRequestError>;
}

/// Tunables of the anchor shot.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    /// The anchor checks (bounds, area, convexity, conditioning).
    pub anchors: AnchorParams,
    /// Largest desired-picture side, pixels.
    pub max_output_side: u32,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            anchors: AnchorParams::default(),
            max_output_side: 4096,
        }
    }
}

fn points(anchors: &[[f64; 2]; 4]) -> [Point2<f64>; 4] {
    anchors.map(|a| Point2::new(a[0], a[1]))
}

/// Check four anchors on a `width` x `height` keyframe with
/// [`crate::shot::homography_from_anchors`] (integer pixel centres; order
/// top-left, top-right, bottom-right, bottom-left, image axes x right, y
/// down). Each refusal is its own [`crate::shot::ShotError`] case inside
/// [`ShotRequestError::BadAnchors`].
pub fn validate_anchors(
    anchors: &[[f64; 2]; 4],
    width: u32,
    height: u32,
    params: &Params,
) -> Result<(), ShotRequestError> {
    homography_from_anchors(width, height, &points(anchors), &params.anchors)
        .map(|_| ())
        .map_err(|source| ShotRequestError::BadAnchors { source })
}

/// The desired shot of four anchors on a keyframe: the keyframe warped once
/// at its own size, plus the picture at another size when one is asked for.
#[derive(Debug, Clone)]
pub struct AnchorShot {
    /// The shot at the keyframe's size, its mask and `H` (shot pixel ->
    /// keyframe pixel): what localisation matches.
    pub shot: DesiredShot,
    /// The picture at the requested size when that differs from the
    /// keyframe's (None: `shot.image` is the picture).
    pub resized: Option<GrayImage>,
}

impl AnchorShot {
    /// The picture the operator asked for.
    pub fn picture(&self) -> &GrayImage {
        self.resized.as_ref().unwrap_or(&self.shot.image)
    }

    /// The picture, by value.
    pub fn into_picture(self) -> GrayImage {
        self.resized.unwrap_or(self.shot.image)
    }
}

/// Validate the anchors on `keyframe` and warp it (see the module
/// documentation). `size` is the picture's size (None: the keyframe's);
/// each side must be in `2..=max_output_side`.
pub fn anchor_shot(
    keyframe: &GrayImage,
    anchors: &[[f64; 2]; 4],
    size: Option<(u32, u32)>,
    params: &Params,
) -> Result<AnchorShot, ShotRequestError> {
    let (kw, kh) = keyframe.dimensions();
    let max = params.max_output_side;
    if let Some((w, h)) = size
        && !((2..=max).contains(&w) && (2..=max).contains(&h))
    {
        return Err(ShotRequestError::BadImage {
            reason: format!("output size {w}x{h} outside 2..={max}"),
        });
    }
    let hm =
        homography_from_anchors(kw, kh, &points(anchors), &params.anchors).map_err(|source| {
            match source {
                crate::shot::ShotError::ImageSize { width, height, .. } => {
                    ShotRequestError::BadImage {
                        reason: format!("keyframe image of {width}x{height} is too small to warp"),
                    }
                }
                source => ShotRequestError::BadAnchors { source },
            }
        })?;
    let (image, mask) = warp_perspective(keyframe, &hm, kw, kh);
    let resized = size.filter(|&s| s != (kw, kh)).map(|(w, h)| {
        // Picture pixel -> keyframe-size shot pixel, corner centres onto
        // corner centres, then through H.
        let sx = (kw - 1) as f64 / (w - 1) as f64;
        let sy = (kh - 1) as f64 / (h - 1) as f64;
        let scale = Matrix3::new(sx, 0.0, 0.0, 0.0, sy, 0.0, 0.0, 0.0, 1.0);
        warp_perspective(keyframe, &(hm * scale), w, h).0
    });
    Ok(AnchorShot {
        shot: DesiredShot {
            image,
            mask,
            shot_to_source: hm,
        },
        resized,
    })
}

/// A source of keyframe images, by id.
pub trait KeyframeImages: Send + Sync {
    /// The keyframe's grey image.
    fn keyframe_image(&self, id: u64) -> Option<Arc<GrayImage>>;
}

/// The shot computer without a map: it validates anchors and renders the
/// desired shot, and reports every shot as not localised with the reason.
pub struct WarpOnly<K> {
    /// Keyframe images.
    pub keyframes: K,
    /// Anchor-shot tunables.
    pub params: Params,
}

impl<K: KeyframeImages> WarpOnly<K> {
    /// The anchor shot of a keyframe (see [`anchor_shot`]).
    pub fn anchor_shot(
        &self,
        keyframe_id: u64,
        anchors: &[[f64; 2]; 4],
        size: Option<(u32, u32)>,
    ) -> Result<AnchorShot, ShotRequestError> {
        let img = self
            .keyframes
            .keyframe_image(keyframe_id)
            .ok_or(ShotRequestError::UnknownKeyframe { id: keyframe_id })?;
        anchor_shot(&img, anchors, size, &self.params)
    }

    /// Check a photo's size (at least 32 x 32 pixels) and its intrinsics
    /// when given; returns the camera they describe.
    pub fn check_photo(
        &self,
        photo: &GrayImage,
        intrinsics: Option<&PhotoIntrinsics>,
    ) -> Result<Option<Camera>, ShotRequestError> {
        if photo.width() < 32 || photo.height() < 32 {
            return Err(ShotRequestError::BadImage {
                reason: format!("{}x{} is too small", photo.width(), photo.height()),
            });
        }
        intrinsics
            .map(|i| {
                i.camera(photo.width(), photo.height()).map_err(|e| {
                    ShotRequestError::BadIntrinsics {
                        reason: e.to_string(),
                    }
                })
            })
            .transpose()
    }
}

impl<K: KeyframeImages> ShotComputer for WarpOnly<K> {
    fn shot_from_anchors(
        &self,
        keyframe_id: u64,
        anchors: &[[f64; 2]; 4],
        size: Option<(u32, u32)>,
    ) -> Result<ShotComputation, ShotRequestError> {
        let shot = self.anchor_shot(keyframe_id, anchors, size)?;
        Ok(ShotComputation {
            desired: Some(shot.into_picture()),
            localisation: Err(NotLocalised::Unavailable),
            nearest_keyframes: Vec::new(),
        })
    }

    fn shot_from_photo(
        &self,
        photo: &GrayImage,
        intrinsics: Option<&PhotoIntrinsics>,
        _gps: Option<&crate::shot::photo::GpsTag>,
    ) -> Result<ShotComputation, ShotRequestError> {
        self.check_photo(photo, intrinsics)?;
        Ok(ShotComputation {
            desired: Some(photo.clone()),
            localisation: Err(NotLocalised::Unavailable),
            nearest_keyframes: Vec::new(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::shot::ShotError as Refusal;
    use image::Luma;

    /// Corner-pixel anchors of the 200 x 150 crop at (100, 100).
    const SQ: [[f64; 2]; 4] = [
        [100.0, 100.0],
        [299.0, 100.0],
        [299.0, 249.0],
        [100.0, 249.0],
    ];

    #[test]
    fn each_bad_anchor_case_keeps_its_own_error() {
        let p = Params::default();
        assert!(validate_anchors(&SQ, 640, 480, &p).is_ok());
        let refusal = |a: [[f64; 2]; 4]| match validate_anchors(&a, 640, 480, &p) {
            Err(ShotRequestError::BadAnchors { source }) => source,
            other => panic!("{a:?}: {other:?}"),
        };
        let nan = [[f64::NAN, 0.0], SQ[1], SQ[2], SQ[3]];
        assert_eq!(refusal(nan), Refusal::NonFiniteAnchor { index: 0 });
        let far = [[-1000.0, 0.0], SQ[1], SQ[2], SQ[3]];
        assert!(matches!(
            refusal(far),
            Refusal::AnchorOutOfBounds { index: 0, .. }
        ));
        let sliver = [[0.0, 0.0], [300.0, 0.0], [300.0, 1.0], [0.0, 1.0]];
        assert!(matches!(refusal(sliver), Refusal::Collapsed { .. }));
        let mirrored = [SQ[1], SQ[0], SQ[3], SQ[2]];
        assert_eq!(refusal(mirrored), Refusal::MirroredWinding);
        let bowtie = [SQ[0], SQ[1], SQ[3], SQ[2]];
        assert!(matches!(refusal(bowtie), Refusal::Crossed { .. }));
        let dart = [[0.0, 0.0], [300.0, 0.0], [100.0, 80.0], [0.0, 230.0]];
        assert_eq!(refusal(dart), Refusal::NotConvex { vertex: 2 });
    }

    #[test]
    fn a_truncated_jpeg_is_told_from_a_whole_one() {
        let img = GrayImage::from_fn(96, 64, |x, y| Luma([((x * 5 + y * 11) % 253) as u8]));
        let mut jpeg = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut jpeg, 90)
            .encode_image(&img)
            .unwrap();
        assert_eq!(jpeg_truncation(&jpeg), None);
        // Trailing bytes after the end marker (some cameras append data).
        let mut trailer = jpeg.clone();
        trailer.extend_from_slice(b"trailer");
        assert_eq!(jpeg_truncation(&trailer), None);
        // Every cut, in the headers or in the scan, is found.
        for keep in [3, 10, 100, jpeg.len() / 2, jpeg.len() - 2, jpeg.len() - 1] {
            let r = jpeg_truncation(&jpeg[..keep]);
            assert!(
                r.as_deref().is_some_and(|m| m.contains("truncated")),
                "{keep}: {r:?}"
            );
        }
        assert!(jpeg_truncation(b"\x89PNG").is_some());
    }

    #[test]
    fn one_warp_at_keyframe_size_and_an_exact_crop_at_another() {
        let src = GrayImage::from_fn(640, 480, |x, y| Luma([((x * 7 + y * 3) % 251) as u8]));
        // The requested size: the crop itself, pixel for pixel.
        let s = anchor_shot(&src, &SQ, Some((200, 150)), &Params::default()).unwrap();
        let out = s.picture();
        assert_eq!(out.dimensions(), (200, 150));
        for (x, y) in [(0, 0), (57, 33), (199, 149), (120, 80)] {
            assert_eq!(
                out.get_pixel(x, y),
                src.get_pixel(100 + x, 100 + y),
                "({x},{y})"
            );
        }
        // The localisation's shot is the keyframe's size, fully covered.
        assert_eq!(s.shot.image.dimensions(), (640, 480));
        assert!(s.shot.mask.pixels().all(|m| m[0] == 255));
        // No size, or the keyframe's: the single warp is the picture.
        for size in [None, Some((640, 480))] {
            let s = anchor_shot(&src, &SQ, size, &Params::default()).unwrap();
            assert!(s.resized.is_none());
            assert_eq!(s.picture().dimensions(), (640, 480));
        }
        for bad in [(1, 150), (200, 0), (5000, 10)] {
            assert!(matches!(
                anchor_shot(&src, &SQ, Some(bad), &Params::default()),
                Err(ShotRequestError::BadImage { .. })
            ));
        }
    }
}
