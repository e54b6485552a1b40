//! An uploaded photo: decoded, turned upright by its EXIF orientation, and
//! the camera it was taken with, from the operator's intrinsics, else its
//! EXIF (focal length with the focal-plane resolution, or the 35 mm
//! equivalent focal length), else the map camera scaled to its size.
//!
//! EXIF is read with `kamadak-exif`. A photo whose EXIF cannot be parsed
//! still decodes: the EXIF is ignored with a warning in the log and on the
//! [`Photo`] ([`Photo::exif_warning`]); it never fails the upload.
//!
//! EXIF gives no distortion and no principal point: a camera from EXIF is
//! a pinhole with its principal point at the image centre. Its focal length
//! from the 35 mm equivalent uses the standard's diagonal (43.27 mm of a
//! 36x24 mm frame) against the photo's pixel diagonal, which holds for a
//! resized photo too; the 35 mm equivalent is a whole number of mm, so a
//! wide lens's focal length is only known to about 2 %. The focal-plane
//! resolution (px per unit of the sensor) is exact but describes the
//! sensor's full-size image: it is used only when the EXIF's pixel size
//! (when present) is the photo's.

use std::io::Cursor;

use image::GrayImage;
use image::metadata::Orientation;

use super::ShotError;
use super::localize::assumed_camera;
use crate::camera::{Camera, Distortion};
use crate::optimize::IntrinsicsUncertainty;

/// Diagonal of the 36 x 24 mm frame the 35 mm equivalent refers to, mm.
pub const FRAME_35MM_DIAGONAL_MM: f64 = 43.266_615_305_567_87;

/// What a photo's EXIF says about its camera (only the fields used).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PhotoExif {
    /// FocalLength, mm.
    pub focal_length_mm: Option<f64>,
    /// FocalLengthIn35mmFilm, mm (0 = unknown is read as None).
    pub focal_length_35mm: Option<f64>,
    /// FocalPlaneXResolution and FocalPlaneYResolution in pixels per mm
    /// (converted from FocalPlaneResolutionUnit).
    pub focal_plane_px_per_mm: Option<(f64, f64)>,
    /// PixelXDimension and PixelYDimension.
    pub pixel_size: Option<(u32, u32)>,
    /// Orientation (1..=8), 1 when absent.
    pub orientation: u8,
    /// Where the photo was taken, by its GPS tag (when it has a valid one).
    pub gps: Option<GpsTag>,
}

/// A photo's GPS tag: GPSLatitude/GPSLongitude (with their N/S and E/W
/// references), GPSAltitude (with its above/below sea level reference)
/// and GPSHPositioningError, the receiver's horizontal error.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GpsTag {
    /// Latitude, degrees (south negative).
    pub lat_deg: f64,
    /// Longitude, degrees (west negative).
    pub lon_deg: f64,
    /// Altitude above sea level, metres, when tagged.
    pub alt_m: Option<f64>,
    /// Horizontal positioning error, metres, when tagged.
    pub h_error_m: Option<f64>,
}

/// A decoded photo.
#[derive(Debug, Clone)]
pub struct Photo {
    /// Grey levels, turned upright by the EXIF orientation.
    pub image: GrayImage,
    /// Its EXIF, when it has readable EXIF.
    pub exif: Option<PhotoExif>,
    /// Why the photo's EXIF was ignored, when it was.
    pub exif_warning: Option<String>,
}

/// Where a photo's camera came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum IntrinsicsSource {
    /// The operator gave them.
    Given,
    /// Focal length and focal-plane resolution of the EXIF.
    ExifFocalPlane,
    /// The EXIF's 35 mm equivalent focal length.
    Exif35mm,
    /// The map camera scaled to the photo's size.
    MapCamera,
}

impl IntrinsicsSource {
    /// The name the CLI and the API print.
    pub fn as_str(self) -> &'static str {
        match self {
            Self::Given => "given",
            Self::ExifFocalPlane => "exif_focal_plane",
            Self::Exif35mm => "exif_35mm",
            Self::MapCamera => "map_camera",
        }
    }
}

/// A photo's camera and where it came from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PhotoCamera {
    /// The camera (the upright photo's size).
    pub camera: Camera,
    /// Where its intrinsics came from.
    pub source: IntrinsicsSource,
    /// How well they are known: zero for given ones and the map camera's;
    /// from EXIF, the focal length to the 35 mm equivalent's whole mm (and
    /// 1 % for the equivalence's convention) or 1 % from the focal plane,
    /// and an unknown lens's distortion ([`EXIF_K1_SIGMA`], [`EXIF_K2_SIGMA`]).
    pub uncertainty: IntrinsicsUncertainty,
    /// True when the camera is only assumed: a photo of another size than
    /// the map camera's with neither given intrinsics nor an EXIF focal
    /// length, taken as the map camera scaled ([`assumed_camera`]); the
    /// localisation then weighs another camera too
    /// ([`crate::shot::localize::UnknownFocal`]).
    pub focal_unknown: bool,
}

/// The distortion sigmas of an unknown lens, defined beside the
/// localisation that weighs them (this module sits above it).
pub use super::localize::{EXIF_K1_SIGMA, EXIF_K2_SIGMA};

/// Why a photo's EXIF was ignored, or could not be written.
#[derive(Debug, thiserror::Error)]
pub enum ExifError {
    /// The EXIF block is there but cannot be parsed.
    #[error("unreadable EXIF: {0}")]
    Unreadable(exif::Error),
    /// The orientation tag holds a value outside the standard's 1-8.
    #[error("EXIF orientation {0} is not 1-8")]
    BadOrientation(u32),
    /// The EXIF writer refused the fields.
    #[error("EXIF not written: {0}")]
    Write(exif::Error),
}

/// Decodes a JPEG or PNG photo, reads its EXIF and turns it upright.
///
/// Errors: [`ShotError::BadPhoto`] when the bytes are not a readable image.
pub fn decode_photo(bytes: &[u8]) -> Result<Photo, ShotError> {
    let img = image::load_from_memory(bytes).map_err(|e| ShotError::BadPhoto {
        reason: format!("not a readable image: {e}"),
    })?;
    let (exif, exif_warning) = match read_exif(bytes) {
        Ok(e) => (e, None),
        Err(w) => {
            tracing::warn!("photo EXIF ignored: {w}");
            (None, Some(w.to_string()))
        }
    };
    let mut img = img;
    if let Some(o) = exif.and_then(|e| Orientation::from_exif(e.orientation)) {
        img.apply_orientation(o);
    }
    Ok(Photo {
        image: img.to_luma8(),
        exif,
        exif_warning,
    })
}

/// The EXIF fields of `bytes` (None when the container has no EXIF; an
/// error when it has EXIF that cannot be parsed or is nonsense).
pub fn read_exif(bytes: &[u8]) -> Result<Option<PhotoExif>, ExifError> {
    let exif = match exif::Reader::new().read_from_container(&mut Cursor::new(bytes)) {
        Ok(e) => e,
        Err(exif::Error::NotFound(_)) => return Ok(None),
        Err(e) => return Err(ExifError::Unreadable(e)),
    };
    let field = |t: exif::Tag| exif.get_field(t, exif::In::PRIMARY);
    let rational = |t: exif::Tag| -> Option<f64> {
        match &field(t)?.value {
            exif::Value::Rational(v) => v.first().map(|r| r.to_f64()),
            exif::Value::SRational(v) => v.first().map(|r| r.to_f64()),
            v => v.get_uint(0).map(f64::from),
        }
    };
    let uint = |t: exif::Tag| field(t).and_then(|f| f.value.get_uint(0));
    let positive = |v: Option<f64>| v.filter(|x| x.is_finite() && *x > 0.0);
    let orientation = match uint(exif::Tag::Orientation) {
        None => 1,
        Some(o @ 1..=8) => o as u8,
        Some(o) => return Err(ExifError::BadOrientation(o)),
    };
    // FocalPlaneResolutionUnit: 2 inch (the default), 3 cm, 4 mm, 5 µm.
    let unit_mm = match uint(exif::Tag::FocalPlaneResolutionUnit).unwrap_or(2) {
        2 => Some(25.4),
        3 => Some(10.0),
        4 => Some(1.0),
        5 => Some(0.001),
        _ => None,
    };
    let focal_plane_px_per_mm = match (
        positive(rational(exif::Tag::FocalPlaneXResolution)),
        positive(rational(exif::Tag::FocalPlaneYResolution)),
        unit_mm,
    ) {
        (Some(x), y, Some(u)) => Some((x / u, y.unwrap_or(x) / u)),
        _ => None,
    };
    let pixel_size = match (
        uint(exif::Tag::PixelXDimension),
        uint(exif::Tag::PixelYDimension),
    ) {
        (Some(w), Some(h)) if w > 0 && h > 0 => Some((w, h)),
        _ => None,
    };
    // Degrees, minutes, seconds, and the hemisphere's letter.
    let dms = |t: exif::Tag| -> Option<f64> {
        match &field(t)?.value {
            exif::Value::Rational(v) if v.len() >= 3 => {
                Some(v[0].to_f64() + v[1].to_f64() / 60.0 + v[2].to_f64() / 3600.0)
            }
            _ => None,
        }
    };
    let letter = |t: exif::Tag| -> Option<u8> {
        match &field(t)?.value {
            exif::Value::Ascii(v) => v.first()?.first().copied(),
            _ => None,
        }
    };
    let gps = match (dms(exif::Tag::GPSLatitude), dms(exif::Tag::GPSLongitude)) {
        (Some(lat), Some(lon)) => {
            let lat = if letter(exif::Tag::GPSLatitudeRef) == Some(b'S') {
                -lat
            } else {
                lat
            };
            let lon = if letter(exif::Tag::GPSLongitudeRef) == Some(b'W') {
                -lon
            } else {
                lon
            };
            let alt = rational(exif::Tag::GPSAltitude)
                .filter(|a| a.is_finite())
                .map(|a| {
                    if uint(exif::Tag::GPSAltitudeRef) == Some(1) {
                        -a
                    } else {
                        a
                    }
                });
            // A tag at 0, 0 is a receiver without a fix more often than
            // a photo in the Gulf of Guinea.
            (lat.abs() <= 90.0 && lon.abs() <= 180.0 && (lat, lon) != (0.0, 0.0)).then_some(
                GpsTag {
                    lat_deg: lat,
                    lon_deg: lon,
                    alt_m: alt,
                    h_error_m: positive(rational(exif::Tag::GPSHPositioningError)),
                },
            )
        }
        _ => None,
    };
    Ok(Some(PhotoExif {
        focal_length_mm: positive(rational(exif::Tag::FocalLength)),
        focal_length_35mm: positive(rational(exif::Tag::FocalLengthIn35mmFilm)),
        focal_plane_px_per_mm,
        pixel_size,
        orientation,
        gps,
    }))
}

/// A TIFF block (for a JPEG's APP1 `Exif` segment) holding a GPS tag
/// alone: what the tests and tools write into a photo.
///
/// Errors: [`ExifError::Write`] when the writer refuses the fields.
pub fn exif_tiff_gps(gps: &GpsTag) -> Result<Vec<u8>, ExifError> {
    use exif::{Field, In, Rational, Tag, Value};
    // Degrees, minutes, and seconds to a thousandth (3 cm).
    let dms = |v: f64| {
        let v = v.abs();
        let d = v.floor();
        let m = ((v - d) * 60.0).floor();
        let sec = (v - d - m / 60.0) * 3600.0;
        Value::Rational(vec![
            Rational::from((d as u32, 1)),
            Rational::from((m as u32, 1)),
            Rational::from(((sec * 1000.0).round() as u32, 1000)),
        ])
    };
    let ascii = |c: &str| Value::Ascii(vec![c.as_bytes().to_vec()]);
    let field = |tag, value| Field {
        tag,
        ifd_num: In::PRIMARY,
        value,
    };
    let mut fields = vec![
        field(
            Tag::GPSLatitudeRef,
            ascii(if gps.lat_deg < 0.0 { "S" } else { "N" }),
        ),
        field(Tag::GPSLatitude, dms(gps.lat_deg)),
        field(
            Tag::GPSLongitudeRef,
            ascii(if gps.lon_deg < 0.0 { "W" } else { "E" }),
        ),
        field(Tag::GPSLongitude, dms(gps.lon_deg)),
    ];
    if let Some(a) = gps.alt_m {
        fields.push(field(
            Tag::GPSAltitudeRef,
            Value::Byte(vec![u8::from(a < 0.0)]),
        ));
        fields.push(field(
            Tag::GPSAltitude,
            Value::Rational(vec![Rational::from((
                (a.abs() * 100.0).round() as u32,
                100,
            ))]),
        ));
    }
    if let Some(e) = gps.h_error_m {
        fields.push(field(
            Tag::GPSHPositioningError,
            Value::Rational(vec![Rational::from(((e * 100.0).round() as u32, 100))]),
        ));
    }
    write_tiff(&fields)
}

/// Whether the EXIF orientation turns the stored image by 90 degrees.
fn swaps_axes(orientation: u8) -> bool {
    (5..=8).contains(&orientation)
}

/// The camera of an upright `width` x `height` photo from its EXIF: a
/// pinhole with the principal point at the centre; None when the EXIF
/// holds no usable focal length.
pub fn exif_camera(exif: &PhotoExif, width: u32, height: u32) -> Option<PhotoCamera> {
    let (cx, cy) = ((width as f64 - 1.0) / 2.0, (height as f64 - 1.0) / 2.0);
    let make = |fx: f64, fy: f64, source, focal_rel: f64| {
        Camera::new(width, height, [fx, fy, cx, cy], Distortion::default())
            .ok()
            .map(|camera| PhotoCamera {
                camera,
                source,
                uncertainty: IntrinsicsUncertainty {
                    focal_rel,
                    k1: EXIF_K1_SIGMA,
                    k2: EXIF_K2_SIGMA,
                },
                focal_unknown: false,
            })
    };
    // The stored (not yet upright) size, which the focal plane refers to.
    let swapped = swaps_axes(exif.orientation);
    let stored = if swapped {
        (height, width)
    } else {
        (width, height)
    };
    if let (Some(f), Some((rx, ry))) = (exif.focal_length_mm, exif.focal_plane_px_per_mm)
        && exif.pixel_size.is_none_or(|s| s == stored)
    {
        let (fx, fy) = if swapped {
            (f * ry, f * rx)
        } else {
            (f * rx, f * ry)
        };
        if let Some(c) = make(fx, fy, IntrinsicsSource::ExifFocalPlane, 0.01) {
            return Some(c);
        }
    }
    let f35 = exif.focal_length_35mm?;
    let diag = (width as f64).hypot(height as f64);
    let f = f35 / FRAME_35MM_DIAGONAL_MM * diag;
    make(f, f, IntrinsicsSource::Exif35mm, (0.5 / f35).hypot(0.01))
}

/// The camera of `photo`: `given` when the operator gave one, else from
/// its EXIF, else the map camera (exact for a photo of its size; scaled
/// by [`assumed_camera`] and marked [`PhotoCamera::focal_unknown`] for
/// another size).
///
/// Errors: [`ShotError::ImageSize`] when none applies (no usable EXIF and
/// an aspect ratio other than the map camera's).
pub fn photo_camera(
    map_camera: &Camera,
    photo: &Photo,
    given: Option<Camera>,
) -> Result<PhotoCamera, ShotError> {
    let (w, h) = photo.image.dimensions();
    if let Some(camera) = given {
        return Ok(PhotoCamera {
            camera,
            source: IntrinsicsSource::Given,
            uncertainty: IntrinsicsUncertainty::default(),
            focal_unknown: false,
        });
    }
    if let Some(c) = photo.exif.as_ref().and_then(|e| exif_camera(e, w, h)) {
        return Ok(c);
    }
    if (w, h) == (map_camera.width, map_camera.height) {
        return Ok(PhotoCamera {
            camera: *map_camera,
            source: IntrinsicsSource::MapCamera,
            uncertainty: IntrinsicsUncertainty::default(),
            focal_unknown: false,
        });
    }
    Ok(PhotoCamera {
        camera: assumed_camera(map_camera, w, h)?,
        source: IntrinsicsSource::MapCamera,
        uncertainty: IntrinsicsUncertainty::default(),
        focal_unknown: true,
    })
}

/// The TIFF bytes of an EXIF block (for a JPEG's APP1 segment) with the
/// given fields; for tests and tools that write photos. `focal_plane` is
/// (x, y) resolution in pixels per mm.
pub fn exif_tiff(
    focal_length_mm: Option<f64>,
    focal_length_35mm: Option<u16>,
    focal_plane_px_per_mm: Option<(f64, f64)>,
    orientation: Option<u16>,
) -> Result<Vec<u8>, ExifError> {
    use exif::{Field, In, Rational, Tag, Value};
    let rational = |v: f64| {
        let denom = 1000u32;
        Rational::from(((v * denom as f64).round() as u32, denom))
    };
    let mut fields: Vec<Field> = Vec::new();
    if let Some(f) = focal_length_mm {
        fields.push(Field {
            tag: Tag::FocalLength,
            ifd_num: In::PRIMARY,
            value: Value::Rational(vec![rational(f)]),
        });
    }
    if let Some(f) = focal_length_35mm {
        fields.push(Field {
            tag: Tag::FocalLengthIn35mmFilm,
            ifd_num: In::PRIMARY,
            value: Value::Short(vec![f]),
        });
    }
    if let Some((x, y)) = focal_plane_px_per_mm {
        for (tag, v) in [
            (Tag::FocalPlaneXResolution, x),
            (Tag::FocalPlaneYResolution, y),
        ] {
            fields.push(Field {
                tag,
                ifd_num: In::PRIMARY,
                value: Value::Rational(vec![rational(v)]),
            });
        }
        fields.push(Field {
            tag: Tag::FocalPlaneResolutionUnit,
            ifd_num: In::PRIMARY,
            value: Value::Short(vec![4]),
        });
    }
    if let Some(o) = orientation {
        fields.push(Field {
            tag: Tag::Orientation,
            ifd_num: In::PRIMARY,
            value: Value::Short(vec![o]),
        });
    }
    write_tiff(&fields)
}

/// The fields as a TIFF block (little-endian), for a JPEG's APP1 segment.
fn write_tiff(fields: &[exif::Field]) -> Result<Vec<u8>, ExifError> {
    let mut w = exif::experimental::Writer::new();
    for f in fields {
        w.push_field(f);
    }
    let mut out = Cursor::new(Vec::new());
    w.write(&mut out, false).map_err(ExifError::Write)?;
    Ok(out.into_inner())
}

/// A grey picture as a JPEG (quality 95) with `tiff` (from [`exif_tiff`]
/// or [`exif_tiff_gps`]) as its EXIF: a photo as a camera writes one, for
/// the tests and tools.
///
/// Errors: the encoder's, as [`ShotError::BadPhoto`].
pub fn grey_jpeg_with_exif(img: &GrayImage, tiff: Option<Vec<u8>>) -> Result<Vec<u8>, ShotError> {
    use image::ImageEncoder;
    let bad = |e: &dyn std::fmt::Display| ShotError::BadPhoto {
        reason: e.to_string(),
    };
    let mut out = Vec::new();
    let mut enc = image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 95);
    if let Some(t) = tiff {
        enc.set_exif_metadata(t).map_err(|e| bad(&e))?;
    }
    enc.write_image(
        img.as_raw(),
        img.width(),
        img.height(),
        image::ExtendedColorType::L8,
    )
    .map_err(|e| bad(&e))?;
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use image::Luma;

    fn jpeg(img: &GrayImage, tiff: Option<Vec<u8>>) -> Vec<u8> {
        grey_jpeg_with_exif(img, tiff).unwrap()
    }

    /// A 64x48 picture, black except a white top-left 8x8 block.
    fn marked() -> GrayImage {
        GrayImage::from_fn(64, 48, |x, y| Luma([if x < 8 && y < 8 { 255 } else { 0 }]))
    }

    fn map_camera() -> Camera {
        Camera::new(
            640,
            480,
            [460.0, 460.0, 319.5, 239.5],
            Distortion::default(),
        )
        .unwrap()
    }

    #[test]
    fn focal_length_from_35mm_equivalent_and_focal_plane() {
        // 26 mm equivalent on a 4000x3000 photo: f = 26/43.2666 * 5000 px.
        let t = exif_tiff(Some(4.25), Some(26), None, None).unwrap();
        let bytes = jpeg(&GrayImage::new(400, 300), Some(t));
        let p = decode_photo(&bytes).unwrap();
        let e = p.exif.unwrap();
        assert_eq!(e.focal_length_35mm, Some(26.0));
        assert!((e.focal_length_mm.unwrap() - 4.25).abs() < 1e-9);
        let c = photo_camera(&map_camera(), &p, None).unwrap();
        assert_eq!(c.source, IntrinsicsSource::Exif35mm);
        let f = 26.0 / FRAME_35MM_DIAGONAL_MM * 500.0;
        assert!((c.camera.fx - f).abs() < 1e-9 && (c.camera.fy - f).abs() < 1e-9);
        assert!((c.camera.cx - 199.5).abs() < 1e-12 && (c.camera.cy - 149.5).abs() < 1e-12);
        // Focal plane: 4.25 mm at 100 px/mm = 425 px exactly.
        let t = exif_tiff(Some(4.25), Some(26), Some((100.0, 100.0)), None).unwrap();
        let p = decode_photo(&jpeg(&GrayImage::new(400, 300), Some(t))).unwrap();
        let c = photo_camera(&map_camera(), &p, None).unwrap();
        assert_eq!(c.source, IntrinsicsSource::ExifFocalPlane);
        assert!((c.camera.fx - 425.0).abs() < 1e-9);
        // Explicit intrinsics win over EXIF.
        let given = Camera::new(
            400,
            300,
            [300.0, 300.0, 200.0, 150.0],
            Distortion::default(),
        )
        .unwrap();
        let c = photo_camera(&map_camera(), &p, Some(given)).unwrap();
        assert_eq!(c.source, IntrinsicsSource::Given);
        assert_eq!(c.camera.fx, 300.0);
    }

    #[test]
    fn no_exif_falls_back_to_the_map_camera() {
        let p = decode_photo(&jpeg(&GrayImage::new(320, 240), None)).unwrap();
        assert!(p.exif.is_none() && p.exif_warning.is_none());
        let c = photo_camera(&map_camera(), &p, None).unwrap();
        assert_eq!(c.source, IntrinsicsSource::MapCamera);
        assert!((c.camera.fx - 230.0).abs() < 1e-9);
        // Focal length alone (no sensor size) gives no camera.
        let t = exif_tiff(Some(4.25), None, None, None).unwrap();
        let p = decode_photo(&jpeg(&GrayImage::new(320, 240), Some(t))).unwrap();
        assert!(p.exif.is_some());
        let c = photo_camera(&map_camera(), &p, None).unwrap();
        assert_eq!(c.source, IntrinsicsSource::MapCamera);
        // Another aspect ratio without EXIF: an error, not a guess.
        let p = decode_photo(&jpeg(&GrayImage::new(300, 300), None)).unwrap();
        assert!(matches!(
            photo_camera(&map_camera(), &p, None),
            Err(ShotError::ImageSize { .. })
        ));
    }

    #[test]
    fn orientation_turns_the_photo_upright() {
        // Orientation 6: the stored image must be turned 90 degrees
        // clockwise; its top-left corner goes to the top-right.
        let t = exif_tiff(None, Some(28), None, Some(6)).unwrap();
        let p = decode_photo(&jpeg(&marked(), Some(t))).unwrap();
        assert_eq!(p.image.dimensions(), (48, 64));
        assert!(p.image.get_pixel(44, 3)[0] > 200, "top-right is white");
        assert!(p.image.get_pixel(3, 3)[0] < 50, "top-left is black");
        let c = photo_camera(&map_camera(), &p, None).unwrap();
        assert_eq!((c.camera.width, c.camera.height), (48, 64));
        // Orientation 3: turned 180 degrees.
        let t = exif_tiff(None, None, None, Some(3)).unwrap();
        let p = decode_photo(&jpeg(&marked(), Some(t))).unwrap();
        assert_eq!(p.image.dimensions(), (64, 48));
        assert!(p.image.get_pixel(60, 44)[0] > 200);
        // Focal plane of a turned photo: x and y resolutions swap.
        let t = exif_tiff(Some(2.0), None, Some((100.0, 50.0)), Some(6)).unwrap();
        let p = decode_photo(&jpeg(&marked(), Some(t))).unwrap();
        let c = photo_camera(&map_camera(), &p, None).unwrap();
        assert_eq!(c.source, IntrinsicsSource::ExifFocalPlane);
        assert!((c.camera.fx - 100.0).abs() < 1e-9 && (c.camera.fy - 200.0).abs() < 1e-9);
    }

    #[test]
    fn a_gps_tag_is_read_back_with_its_hemispheres() {
        let img = marked();
        for tag in [
            GpsTag {
                lat_deg: 47.397_742_1,
                lon_deg: 8.545_594_3,
                alt_m: Some(488.25),
                h_error_m: Some(4.5),
            },
            GpsTag {
                lat_deg: -33.856_784,
                lon_deg: -151.215_297,
                alt_m: Some(-12.5),
                h_error_m: None,
            },
            GpsTag {
                lat_deg: 0.000_5,
                lon_deg: 179.999,
                alt_m: None,
                h_error_m: None,
            },
        ] {
            let bytes = jpeg(&img, Some(exif_tiff_gps(&tag).unwrap()));
            let got = read_exif(&bytes).unwrap().unwrap().gps.unwrap();
            // Seconds to a thousandth: 3 cm, 3e-7 degrees.
            assert!(
                (got.lat_deg - tag.lat_deg).abs() < 3e-7,
                "{got:?} vs {tag:?}"
            );
            assert!(
                (got.lon_deg - tag.lon_deg).abs() < 3e-7,
                "{got:?} vs {tag:?}"
            );
            assert_eq!(got.alt_m, tag.alt_m);
            assert_eq!(got.h_error_m, tag.h_error_m);
            // And through the upload's decoding.
            assert_eq!(decode_photo(&bytes).unwrap().exif.unwrap().gps, Some(got));
        }
        // A receiver without a fix writes 0, 0: no tag.
        let zero = GpsTag {
            lat_deg: 0.0,
            lon_deg: 0.0,
            alt_m: None,
            h_error_m: None,
        };
        let bytes = jpeg(&img, Some(exif_tiff_gps(&zero).unwrap()));
        assert_eq!(read_exif(&bytes).unwrap().unwrap().gps, None);
    }

    #[test]
    fn bad_exif_is_ignored_with_a_warning_never_a_crash() {
        let img = marked();
        // An orientation out of range.
        let t = exif_tiff(None, Some(28), None, Some(9)).unwrap();
        let p = decode_photo(&jpeg(&img, Some(t))).unwrap();
        assert!(p.exif.is_none());
        assert!(p.exif_warning.as_deref().unwrap().contains("orientation 9"));
        assert_eq!(p.image.dimensions(), (64, 48));
        // Garbage in the APP1 segment, and every truncation of a real block.
        let good = exif_tiff(Some(4.0), Some(28), Some((10.0, 10.0)), Some(6)).unwrap();
        let mut cases: Vec<Vec<u8>> = vec![b"II*\0garbage".to_vec(), vec![0xff; 40]];
        for cut in [2, 8, 10, 20, good.len() / 2, good.len() - 1] {
            cases.push(good[..cut].to_vec());
        }
        for t in cases {
            let p = decode_photo(&jpeg(&img, Some(t))).unwrap();
            if let Some(e) = p.exif {
                assert!((1..=8).contains(&e.orientation));
            }
            let _ = photo_camera(&map_camera(), &p, None);
        }
        // Not an image at all.
        assert!(matches!(
            decode_photo(b"not an image"),
            Err(ShotError::BadPhoto { .. })
        ));
    }
}
