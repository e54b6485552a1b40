//! The live frame localised in the map as the daemon localises it (a
//! desired shot: an anchors shot by its keyframe's geometry, a photo by
//! matching), and paired with the telemetry as the daemon's tracking pairs
//! its frames.

use image::GrayImage;
use nalgebra::Isometry3;

use crate::geo::frame_pair_id;
use crate::shot::request::NotLocalised;
use crate::shot::{Localization, LocalizeParams, localize, localize_anchors};
use crate::slam::Map;

use super::explore::Explored;
use super::params::ScenarioParams;
use super::sim::Sim;

/// The desired shot's camera: an anchors shot's from its keyframe's
/// geometry (as the daemon does), a photo's by localisation.
pub(super) fn localise(
    map: &Map,
    img: &GrayImage,
    mask: Option<&GrayImage>,
    anchors_on: Option<(u32, nalgebra::Matrix3<f64>)>,
    by_matching: bool,
    p: &LocalizeParams,
) -> Result<Isometry3<f64>, NotLocalised> {
    let found = match anchors_on {
        Some((id, h)) if !by_matching => {
            Ok(localize_anchors(map, crate::slam::KeyFrameId(id), &h, p))
        }
        _ => localize(map, img, mask, None, p),
    };
    match found {
        Ok(Localization::Localized(s)) => Ok(s.world_from_cam),
        Ok(Localization::NotLocalized { reason }) => Err(NotLocalised::Rejected(reason)),
        Err(e) => Err(NotLocalised::Failed(e)),
    }
}

/// Live frames are paired this often in flight, s (the daemon's frame
/// pairs are half a second apart).
pub(super) const PAIR_SPACING_S: f64 = 0.5;

/// Localises the frame the camera sees now and pairs it with the
/// telemetry (paired once telemetry past its time has come). Its pair id,
/// or None when it was not localised or not paired.
pub(super) fn pair_live_frame(
    ex: &Explored,
    sim: &mut Sim,
    params: &ScenarioParams,
) -> Option<u64> {
    sim.geo.as_ref()?;
    let image = sim.render();
    let t = sim.t;
    let map_from_cam = localise(&ex.map, &image, None, None, false, &params.localize).ok()?;
    let g = sim.geo.as_mut()?;
    let id = frame_pair_id(t);
    match g.add_keyframe(id, &map_from_cam, t) {
        Ok(_) => Some(id),
        Err(e) => {
            tracing::debug!("scenario: live frame not paired: {e}");
            None
        }
    }
}
