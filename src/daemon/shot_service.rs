//! The daemon's shot service: the API's desired-shot rendering and anchor
//! validation ([`WarpOnly`]), then localisation of the shot against a copy
//! of the SLAM's map with [`crate::shot::localize`] (ORB on the shot with its
//! black fill masked, candidate keyframes, PnP RANSAC, refinement, the
//! reliability gate). A shot that fails the gate is stored as not localised
//! with the gate's reason.

use std::sync::Arc;

use image::GrayImage;
use nalgebra::Point2;

use crate::api::SlamView;
use crate::api::shots::{ShotComputation, ShotComputer, ShotError, WarpOnly};
use crate::api::store::{Localisation, PoseJson};
use crate::shot::anchors::{AnchorParams, desired_shot_from_anchors};
use crate::shot::localize::{Localization, LocalizeParams, localize};
use crate::slam::{KeyFrameId, Map};

use super::slam_view::SlamShared;

/// Desired shots rendered by the API's warp and localised in the SLAM map.
pub struct LocalizingShots {
    /// Anchor validation and the desired-shot picture.
    pub warp: WarpOnly<Arc<dyn SlamView>>,
    /// Where the map comes from.
    pub slam: Arc<SlamShared>,
    /// Localisation tunables (the reliability gate among them).
    pub params: LocalizeParams,
    /// Anchor tunables of the localisation's own warp (keyframe size).
    pub anchors: AnchorParams,
}

impl LocalizingShots {
    fn localise(
        &self,
        map: &Map,
        shot: &GrayImage,
        mask: Option<&GrayImage>,
    ) -> Result<Localisation, String> {
        match localize(map, shot, mask, None, &self.params) {
            Ok(Localization::Localized(p)) => {
                tracing::info!(
                    keyframe = p.keyframe_id.0,
                    inliers = p.inliers,
                    rmse_px = p.reprojection_rmse_px,
                    "shot localised"
                );
                Ok(Localisation {
                    world_from_cam: PoseJson::from_isometry(&p.world_from_cam),
                    inliers: p.inliers,
                    rms_error_px: p.reprojection_rmse_px,
                    keyframe_id: Some(p.keyframe_id.0 as u64),
                })
            }
            Ok(Localization::NotLocalized { reason }) => {
                tracing::info!(%reason, "shot not localised");
                Err(format!("not localised: {reason}"))
            }
            Err(e) => Err(format!("not localised: {e}")),
        }
    }
}

impl ShotComputer for LocalizingShots {
    fn shot_from_anchors(
        &self,
        keyframe_id: u64,
        anchors: &[[f64; 2]; 4],
        size: (u32, u32),
    ) -> Result<ShotComputation, ShotError> {
        let mut out = self.warp.shot_from_anchors(keyframe_id, anchors, size)?;
        let Some(map) = self.slam.map_snapshot() else {
            out.localisation = Err("not localised: no map yet".into());
            return Ok(out);
        };
        let image = u32::try_from(keyframe_id)
            .ok()
            .and_then(|id| map.keyframe(KeyFrameId(id)))
            .and_then(|k| k.image.clone());
        let Some(image) = image else {
            return Err(ShotError::UnknownKeyframe { id: keyframe_id });
        };
        let pts = anchors.map(|a| Point2::new(a[0], a[1]));
        out.localisation = match desired_shot_from_anchors(&image, &pts, &self.anchors) {
            Ok(shot) => self.localise(&map, &shot.image, Some(&shot.mask)),
            Err(e) => Err(format!("not localised: {e}")),
        };
        Ok(out)
    }

    fn shot_from_photo(&self, photo: &GrayImage) -> Result<ShotComputation, ShotError> {
        let mut out = self.warp.shot_from_photo(photo)?;
        let Some(map) = self.slam.map_snapshot() else {
            out.localisation = Err("not localised: no map yet".into());
            return Ok(out);
        };
        let (w, h) = (map.camera.width, map.camera.height);
        out.localisation = if photo.dimensions() == (w, h) {
            self.localise(&map, photo, None)
        } else {
            Err(format!(
                "not localised: the photo is {}x{}, the camera's images are {w}x{h}",
                photo.width(),
                photo.height()
            ))
        };
        Ok(out)
    }
}
