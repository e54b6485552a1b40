//! A shot's desired picture as the shot refinement compares live frames
//! with it: an anchors shot's keyframe image warped again through its
//! anchors (with the mask of its valid pixels and the reachable framing,
//! [`super::reachable`]), or the picture stored with the shot (a photo, or
//! an anchors shot whose keyframe left the map), at the camera's size; and
//! the few made last, kept by shot ([`Pictures`]).

use std::sync::Mutex;

use image::GrayImage;
use nalgebra::Point2;

use super::loop_params::LoopParams;
use super::reachable::{Reachable, reachable_from_anchors};
use crate::shot::anchors::desired_shot_from_anchors;
use crate::shot::record::{Shot, ShotSource};
use crate::slam::{KeyFrameId, Map};

/// A desired picture, the mask of its valid pixels and, for a shot made
/// from anchors, the best framing a camera can reach (the shot error's
/// floor; None when it could not be computed).
pub type Picture = (GrayImage, Option<GrayImage>, Option<Reachable>);

/// Why a shot has no desired picture; its Display is the reason recorded
/// on the shot.
#[derive(Debug, thiserror::Error)]
pub enum PictureError {
    /// A photo shot (or an anchors shot whose keyframe left the map) has
    /// no stored picture.
    #[error("shot {shot} has no stored image")]
    NoStoredImage {
        /// The shot's id.
        shot: String,
    },
    /// The stored picture does not decode.
    #[error("shot image: {0}")]
    StoredImage(#[from] image::ImageError),
    /// The stored picture is not of the camera's size.
    #[error(
        "the shot's picture is {width}x{height}, the camera's images are {camera_width}x{camera_height}"
    )]
    PictureSize {
        /// Its width, pixels.
        width: u32,
        /// Its height, pixels.
        height: u32,
        /// The camera's width, pixels.
        camera_width: u32,
        /// The camera's height, pixels.
        camera_height: u32,
    },
    /// An anchors shot's keyframe left the map and its stored picture
    /// cannot stand in.
    #[error("keyframe {keyframe} has no image in the map, and {stored}")]
    KeyframeGone {
        /// The keyframe the anchors were drawn on.
        keyframe: u64,
        /// Why the stored picture cannot be used.
        stored: Box<PictureError>,
    },
    /// The anchors no longer make a desired picture.
    #[error("desired shot: {0}")]
    DesiredShot(#[from] crate::shot::ShotError),
}

/// The desired picture (and the mask of its valid pixels) at the camera's
/// size: an anchors shot is warped again from its keyframe, with its
/// reachable framing from the keyframe's map points; a photo is the
/// stored image (`stored`: the JPEG kept with the shot, read only when
/// needed).
pub fn desired_picture(
    map: &Map,
    shot: &Shot,
    params: &LoopParams,
    stored: impl FnOnce() -> Option<Vec<u8>>,
) -> Result<Picture, PictureError> {
    let anchors = &params.anchors;
    match &shot.source {
        ShotSource::Anchors {
            keyframe_id,
            anchors: a,
        } => {
            let Some(image) = u32::try_from(*keyframe_id)
                .ok()
                .and_then(|id| map.keyframe(KeyFrameId(id)))
                .and_then(|k| k.image.clone())
            else {
                // The keyframe left the map (culled, or not in the map
                // continued after a restart): the desired picture stored
                // with the shot when it was made stands in for it.
                let stored =
                    stored_picture(map, shot, stored).map_err(|e| PictureError::KeyframeGone {
                        keyframe: *keyframe_id,
                        stored: Box::new(e),
                    })?;
                tracing::warn!(
                    shot = %shot.id,
                    keyframe = keyframe_id,
                    "refinement: the shot's keyframe is not in the map; using its stored desired picture"
                );
                return Ok(stored);
            };
            let pts = a.map(|p| Point2::new(p[0], p[1]));
            let s = desired_shot_from_anchors(&image, &pts, anchors)?;
            let reachable = shot
                .localisation
                .as_ref()
                .and_then(|l| l.world_from_cam.to_isometry())
                .and_then(|map_from_desired| {
                    let id = KeyFrameId(u32::try_from(*keyframe_id).ok()?);
                    reachable_from_anchors(
                        map,
                        id,
                        &s.shot_to_source,
                        &map_from_desired,
                        &params.refine.error,
                    )
                    .map_err(|e| tracing::warn!("refinement: reachable framing: {e}"))
                    .ok()
                });
            if let Some(r) = &reachable {
                tracing::info!(
                    shot = %shot.id,
                    floor_pct = r.floor_pct,
                    points = r.points,
                    inliers = r.inliers,
                    "refinement: the shot's reachable framing"
                );
            }
            Ok((s.image, Some(s.mask), reachable))
        }
        ShotSource::Photo { .. } => stored_picture(map, shot, stored),
    }
}

/// The desired picture stored with the shot (a photo, or the picture an
/// anchors shot made), at the camera's size.
fn stored_picture(
    map: &Map,
    shot: &Shot,
    stored: impl FnOnce() -> Option<Vec<u8>>,
) -> Result<Picture, PictureError> {
    let jpeg = stored().ok_or_else(|| PictureError::NoStoredImage {
        shot: shot.id.clone(),
    })?;
    let img = image::load_from_memory(&jpeg)?.to_luma8();
    if img.dimensions() != (map.camera.width, map.camera.height) {
        return Err(PictureError::PictureSize {
            width: img.width(),
            height: img.height(),
            camera_width: map.camera.width,
            camera_height: map.camera.height,
        });
    }
    Ok((img, None, None))
}

/// Desired pictures kept at most.
const KEEP_PICTURES: usize = 8;

/// The desired pictures made last, by shot id (at most [`KEEP_PICTURES`],
/// the oldest go first): an anchors shot's picture is made while its
/// keyframe is in the map and kept for its loop.
#[derive(Default)]
pub struct Pictures {
    kept: Mutex<Vec<(String, Picture)>>,
}

impl Pictures {
    /// The picture kept for `shot_id`.
    pub fn get(&self, shot_id: &str) -> Option<Picture> {
        let kept = self.kept.lock().ok()?;
        kept.iter()
            .find(|(id, _)| id == shot_id)
            .map(|(_, p)| p.clone())
    }

    /// Keeps `picture` for `shot_id` (replacing an older one).
    pub fn keep(&self, shot_id: &str, picture: Picture) {
        if let Ok(mut p) = self.kept.lock() {
            p.retain(|(id, _)| id != shot_id);
            p.push((shot_id.to_owned(), picture));
            let n = p.len();
            if n > KEEP_PICTURES {
                p.drain(..n - KEEP_PICTURES);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Distortion};
    use crate::shot::record::ShotStatus;
    use crate::slam::ScaleInfo;

    fn map(width: u32, height: u32) -> Map {
        let camera = Camera::new(
            width,
            height,
            [50.0, 50.0, f64::from(width) / 2.0, f64::from(height) / 2.0],
            Distortion::default(),
        )
        .unwrap();
        Map::new(camera, ScaleInfo::new(1.2, 8))
    }

    fn shot(source: ShotSource) -> Shot {
        Shot {
            id: "shot-1".into(),
            created_unix: 1.0,
            source,
            status: ShotStatus::NotLocalised,
            localisation: None,
            reason: None,
            has_image: true,
            mission: None,
            nearest_keyframes: Vec::new(),
        }
    }

    fn jpeg(width: u32, height: u32) -> Vec<u8> {
        let mut out = std::io::Cursor::new(Vec::new());
        GrayImage::from_pixel(width, height, image::Luma([90]))
            .write_to(&mut out, image::ImageFormat::Jpeg)
            .unwrap();
        out.into_inner()
    }

    /// A photo is its stored picture at the camera's size; another size,
    /// none stored, and an anchors shot whose keyframe left the map
    /// without a stored picture are refused, each saying why.
    #[test]
    fn a_stored_picture_stands_in_at_the_cameras_size() {
        let photo = shot(ShotSource::Photo {
            bytes: 1000,
            width: 64,
            height: 48,
            intrinsics: None,
        });
        let params = LoopParams::default();
        let (img, mask, reachable) =
            desired_picture(&map(64, 48), &photo, &params, || Some(jpeg(64, 48))).unwrap();
        assert_eq!(img.dimensions(), (64, 48));
        assert!(mask.is_none() && reachable.is_none());
        let e = desired_picture(&map(64, 48), &photo, &params, || Some(jpeg(32, 24)));
        assert!(
            matches!(e, Err(PictureError::PictureSize { width: 32, .. })),
            "{e:?}"
        );
        let e = desired_picture(&map(64, 48), &photo, &params, || None).unwrap_err();
        assert_eq!(e.to_string(), "shot shot-1 has no stored image");
        let anchors = shot(ShotSource::Anchors {
            keyframe_id: 3,
            anchors: [[0.0, 0.0], [63.0, 0.0], [63.0, 47.0], [0.0, 47.0]],
        });
        let e = desired_picture(&map(64, 48), &anchors, &params, || None).unwrap_err();
        assert_eq!(
            e.to_string(),
            "keyframe 3 has no image in the map, and shot shot-1 has no stored image"
        );
        let (img, ..) =
            desired_picture(&map(64, 48), &anchors, &params, || Some(jpeg(64, 48))).unwrap();
        assert_eq!(img.dimensions(), (64, 48));
    }

    #[test]
    fn the_last_pictures_are_kept() {
        let pictures = Pictures::default();
        let pic = |v: u8| (GrayImage::from_pixel(2, 2, image::Luma([v])), None, None);
        for i in 0..10u8 {
            pictures.keep(&format!("shot-{i}"), pic(i));
        }
        assert!(pictures.get("shot-1").is_none(), "the oldest went");
        assert_eq!(
            pictures.get("shot-9").map(|p| p.0.get_pixel(0, 0)[0]),
            Some(9)
        );
        pictures.keep("shot-9", pic(42));
        assert_eq!(
            pictures.get("shot-9").map(|p| p.0.get_pixel(0, 0)[0]),
            Some(42)
        );
    }
}
