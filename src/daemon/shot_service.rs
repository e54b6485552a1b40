//! The daemon's shot service: anchor validation and the desired shot
//! ([`crate::shot::request::anchor_shot`]: the keyframe warped once, at its own
//! size, with [`crate::shot`]'s pixel convention) whose camera comes from
//! the keyframe's own geometry ([`crate::shot::localize_anchors`]: the
//! keyframe's observations moved through the anchors' homography, PnP, no
//! gate but what the operator can change); a photo is localised against a
//! copy of the SLAM's map with [`crate::shot::localize`] (ORB on the photo,
//! candidate keyframes, PnP RANSAC, refinement, the reliability gate). A
//! shot refused is stored as not localised with the reason.

use std::sync::{Arc, OnceLock};

use image::GrayImage;

use crate::api::SlamView;
use crate::bow::Vocabulary;
use crate::camera::Camera;
use crate::optimize::IntrinsicsUncertainty;
use crate::shot::localize::{
    BowIndex, Localization, LocalizeParams, ShotPose, assumed_camera, localize_anchors,
    localize_with_camera, nearest_keyframes,
};
use crate::shot::record::{
    Localisation, LocalisationSigma, NearKeyframeJson, PhotoIntrinsics, PoseJson,
};
use crate::shot::request::{
    NotLocalised, ShotComputation, ShotComputer, ShotRequestError, WarpOnly, anchor_shot,
};
use crate::slam::{KeyFrameId, Map};

use super::slam_shared::SlamShared;

/// Keyframes listed for a shot that was not localised.
const NEAREST_KEYFRAMES: usize = 3;

/// The built-in vocabulary, loaded once, for the nearest keyframes of a
/// shot that was not localised (None when it cannot be loaded).
fn vocabulary() -> Option<&'static Vocabulary> {
    static VOCABULARY: OnceLock<Option<Vocabulary>> = OnceLock::new();
    VOCABULARY
        .get_or_init(|| match Vocabulary::builtin() {
            Ok(v) => Some(v),
            Err(e) => {
                tracing::error!("no nearest keyframes for shots not localised: {e}");
                None
            }
        })
        .as_ref()
}

/// Desired shots warped once and localised in the SLAM map.
pub struct LocalizingShots {
    /// Anchor validation and the desired shot while there is no map yet
    /// (its tunables are used with the map too).
    pub warp: WarpOnly<Arc<dyn SlamView>>,
    /// Where the map comes from.
    pub slam: Arc<SlamShared>,
    /// Localisation tunables (the reliability gate among them).
    pub params: LocalizeParams,
    /// The georeference, through which a photo's GPS tag becomes a
    /// position prior (None: tags are not used).
    pub geo: Option<Arc<super::geo_service::GeoService>>,
}

/// A localisation as the shot record keeps it, logged.
fn outcome(
    result: Result<Localization, crate::shot::ShotError>,
) -> Result<Localisation, NotLocalised> {
    match result {
        Ok(Localization::Localized(p)) => {
            tracing::info!(
                keyframe = p.keyframe_id.0,
                inliers = p.inliers,
                rmse_px = p.reprojection_rmse_px,
                position_sigma = p.sigma.position,
                rotation_sigma_deg = p.sigma.rotation_deg,
                "shot localised"
            );
            Ok(record_of(&p))
        }
        Ok(Localization::NotLocalized { reason }) => {
            tracing::info!(%reason, "shot not localised");
            Err(NotLocalised::Rejected(reason))
        }
        Err(e) => Err(NotLocalised::Failed(e)),
    }
}

/// The shot record's localisation of a pose.
fn record_of(p: &ShotPose) -> Localisation {
    Localisation {
        world_from_cam: PoseJson::from_isometry(&p.world_from_cam),
        inliers: p.inliers,
        rms_error_px: p.reprojection_rmse_px,
        keyframe_id: Some(p.keyframe_id.0 as u64),
        sigma: Some(LocalisationSigma {
            position: p.sigma.position,
            position_fraction_of_distance: p.sigma.position_depth_fraction,
            rotation_deg: p.sigma.rotation_deg,
        }),
    }
}

impl LocalizingShots {
    fn localise(
        &self,
        map: &Map,
        camera: &Camera,
        shot: &GrayImage,
        mask: Option<&GrayImage>,
        params: &LocalizeParams,
    ) -> (Result<Localisation, NotLocalised>, Vec<NearKeyframeJson>) {
        let result = outcome(localize_with_camera(map, camera, shot, mask, None, params));
        // Not localised: the keyframes it looks most like ("fly towards
        // here"), by BoW score.
        let nearest = match (&result, vocabulary()) {
            (Err(NotLocalised::Rejected(_)), Some(v)) => {
                let index = BowIndex::build(map, v);
                nearest_keyframes(map, camera, shot, mask, &index, params, NEAREST_KEYFRAMES)
                    .unwrap_or_default()
                    .into_iter()
                    .map(|n| NearKeyframeJson {
                        keyframe_id: u64::from(n.keyframe_id.0),
                        score: n.score,
                        position: [n.position.x, n.position.y, n.position.z],
                        image_url: NearKeyframeJson::image_url_of(u64::from(n.keyframe_id.0)),
                    })
                    .collect()
            }
            _ => Vec::new(),
        };
        (result, nearest)
    }
}

impl ShotComputer for LocalizingShots {
    fn shot_from_anchors(
        &self,
        keyframe_id: u64,
        anchors: &[[f64; 2]; 4],
        size: Option<(u32, u32)>,
    ) -> Result<ShotComputation, ShotRequestError> {
        let Some(map) = self.slam.map_snapshot() else {
            let mut out = self.warp.shot_from_anchors(keyframe_id, anchors, size)?;
            out.localisation = Err(NotLocalised::NoMap);
            return Ok(out);
        };
        // The keyframe from the same snapshot the shot is localised in.
        let id = u32::try_from(keyframe_id)
            .map(KeyFrameId)
            .map_err(|_| ShotRequestError::UnknownKeyframe { id: keyframe_id })?;
        let image = map
            .keyframe(id)
            .and_then(|k| k.image.clone())
            .ok_or(ShotRequestError::UnknownKeyframe { id: keyframe_id })?;
        let shot = anchor_shot(&image, anchors, size, &self.warp.params)?;
        // The operator may ask again on this keyframe: culling keeps it.
        self.slam.pin_keyframe(keyframe_id);
        // The camera from the keyframe's own observations moved through
        // the anchors' homography: the keyframe's pose and points are
        // known, nothing is matched.
        let localisation = outcome(Ok(localize_anchors(
            &map,
            id,
            &shot.shot.shot_to_source,
            &self.params,
        )));
        Ok(ShotComputation {
            desired: Some(shot.into_picture()),
            localisation,
            nearest_keyframes: Vec::new(),
        })
    }

    fn shot_from_photo(
        &self,
        photo: &GrayImage,
        intrinsics: Option<&PhotoIntrinsics>,
        gps: Option<&crate::shot::photo::GpsTag>,
    ) -> Result<ShotComputation, ShotRequestError> {
        let given = self.warp.check_photo(photo, intrinsics)?;
        let Some(map) = self.slam.map_snapshot() else {
            return Ok(ShotComputation {
                desired: Some(photo.clone()),
                localisation: Err(NotLocalised::NoMap),
                nearest_keyframes: Vec::new(),
            });
        };
        let (w, h) = photo.dimensions();
        // Neither given nor from EXIF, at another size than the map
        // camera's: the map camera scaled is only one explanation.
        let focal_unknown = given.is_none() && (w, h) != (map.camera.width, map.camera.height);
        let camera = match given {
            Some(c) => c,
            None => assumed_camera(&map.camera, w, h).map_err(|_| {
                ShotRequestError::IntrinsicsRequired {
                    width: w,
                    height: h,
                    camera_width: map.camera.width,
                    camera_height: map.camera.height,
                }
            })?,
        };
        let uncertainty = intrinsics
            .map(|i| IntrinsicsUncertainty {
                focal_rel: i.focal_rel_sigma,
                k1: i.k1_sigma,
                k2: i.k2_sigma,
            })
            .unwrap_or_default();
        // The photo's GPS tag through the georeference: a place the map
        // finds far from it is a look-alike (or the tag is wrong).
        let prior = match (gps, &self.geo) {
            (Some(tag), Some(geo)) => match geo.photo_prior(tag) {
                Ok(p) => {
                    tracing::info!(
                        lat = tag.lat_deg,
                        lon = tag.lon_deg,
                        h_error_m = tag.h_error_m,
                        "photo shot: its GPS tag is checked against the place found"
                    );
                    Some(p)
                }
                Err(e) => {
                    tracing::info!("photo shot: its GPS tag is not used: {e}");
                    None
                }
            },
            _ => None,
        };
        let params = LocalizeParams {
            camera_uncertainty: uncertainty,
            focal_unknown,
            position_prior: prior,
            ..self.params.clone()
        };
        let (localisation, nearest_keyframes) = self.localise(&map, &camera, photo, None, &params);
        Ok(ShotComputation {
            desired: Some(photo.clone()),
            localisation,
            nearest_keyframes,
        })
    }
}
