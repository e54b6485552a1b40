//! [`Geo`]: the module's parts wired together the way the daemon uses them.
//! Telemetry goes into the history; each keyframe (its `map ← cam` and
//! capture time) is matched to telemetry, waiting while the telemetry for
//! its time has not arrived yet; the alignment is refitted on demand; a
//! target `map ← cam` becomes a vehicle target once home is known.

use std::collections::VecDeque;

use nalgebra::Isometry3;

use super::align::{GeoAlignment, Georeference};
use super::mount::ned_from_cam;
use super::target::{GeoTarget, convert_target};
use super::telemetry::TelemetryHistory;
use super::wgs84::{Geodetic, LocalFrame};
use super::{GeoError, Params};

/// What became of a keyframe handed to [`Geo::add_keyframe`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum KeyframeStatus {
    /// Paired with telemetry.
    Paired,
    /// Waiting for telemetry that covers its capture time.
    Pending,
}

/// Telemetry history, keyframe pairs, home and mounting in one place.
#[derive(Debug, Clone)]
pub struct Geo {
    params: Params,
    frame: Option<LocalFrame>,
    history: TelemetryHistory,
    georef: Georeference,
    pending: VecDeque<(u64, Isometry3<f64>, f64)>,
    dropped: u64,
}

impl Geo {
    /// An empty georeference with no home yet.
    pub fn new(params: Params) -> Self {
        Self {
            frame: None,
            history: TelemetryHistory::new(params.history.clone()),
            georef: Georeference::new(params.align.clone()),
            pending: VecDeque::new(),
            dropped: 0,
            params,
        }
    }

    /// The parameters.
    pub fn params(&self) -> &Params {
        &self.params
    }

    /// Sets home (HOME_POSITION), the origin of local NED. Positions already
    /// in the history stay in the NED frame they were given in, so set home
    /// before feeding WGS84 positions.
    pub fn set_home(&mut self, home: Geodetic) -> Result<(), GeoError> {
        if !home.is_valid() {
            return Err(GeoError::NonFinite { what: "home" });
        }
        self.frame = Some(LocalFrame::new(home));
        Ok(())
    }

    /// The local frame at home, once known.
    pub fn frame(&self) -> Option<&LocalFrame> {
        self.frame.as_ref()
    }

    /// The telemetry history.
    pub fn history(&self) -> &TelemetryHistory {
        &self.history
    }

    /// The telemetry history, to push samples into.
    pub fn history_mut(&mut self) -> &mut TelemetryHistory {
        &mut self.history
    }

    /// Adds a WGS84 position sample (needs home).
    pub fn push_position_geodetic(&mut self, t: f64, g: &Geodetic) -> Result<(), GeoError> {
        let frame = self.frame.ok_or(GeoError::NoHome)?;
        self.history.push_position_geodetic(t, g, &frame)
    }

    /// The keyframe pairs.
    pub fn georeference(&self) -> &Georeference {
        &self.georef
    }

    /// Keyframes waiting for telemetry.
    pub fn pending(&self) -> usize {
        self.pending.len()
    }

    /// Keyframes dropped because their telemetry never came (older than the
    /// history, or across a gap).
    pub fn dropped(&self) -> u64 {
        self.dropped
    }

    /// Pairs a keyframe (its camera pose in the map and capture time) with
    /// the camera pose from telemetry at that time; keeps it pending while
    /// telemetry has not reached its time (keyframes more than
    /// `history.max_age_s` older than the newest waiting one are dropped,
    /// as the telemetry history would have dropped their samples). Refusals other than
    /// "not yet" are returned.
    pub fn add_keyframe(
        &mut self,
        kf_id: u64,
        map_from_cam: &Isometry3<f64>,
        capture_time: f64,
    ) -> Result<KeyframeStatus, GeoError> {
        match self.history.lookup(capture_time) {
            Ok(state) => {
                let ned = ned_from_cam(&state, &self.params.mount);
                self.georef.add_keyframe(
                    kf_id,
                    map_from_cam,
                    &ned,
                    Some(state.v_ned),
                    capture_time,
                )?;
                Ok(KeyframeStatus::Paired)
            }
            Err(GeoError::NotYet { .. }) | Err(GeoError::EmptyHistory { .. }) => {
                self.pending.push_back((kf_id, *map_from_cam, capture_time));
                let newest = self
                    .pending
                    .iter()
                    .map(|p| p.2)
                    .fold(capture_time, f64::max);
                let max_age = self.params.history.max_age_s;
                let before = self.pending.len();
                self.pending.retain(|p| {
                    (newest - p.2).partial_cmp(&max_age) != Some(std::cmp::Ordering::Greater)
                });
                self.dropped += (before - self.pending.len()) as u64;
                Ok(KeyframeStatus::Pending)
            }
            Err(e) => Err(e),
        }
    }

    /// Adds (or replaces) a pair whose telemetry side is already known (a
    /// saved pair restored onto the loaded map, or one carried to another
    /// home): no history lookup.
    pub fn add_known(
        &mut self,
        kf_id: u64,
        map_from_cam: &Isometry3<f64>,
        ned_from_cam: &Isometry3<f64>,
        v_ned: Option<nalgebra::Vector3<f64>>,
        capture_time: f64,
    ) -> Result<(), GeoError> {
        self.pending.retain(|(id, _, _)| *id != kf_id);
        self.georef
            .add_keyframe(kf_id, map_from_cam, ned_from_cam, v_ned, capture_time)
    }

    /// A keyframe's map pose changed (bundle adjustment): the pair keeps its
    /// telemetry side and takes the new map side; a keyframe still waiting
    /// for telemetry takes the new pose too. Returns whether it was known.
    pub fn refresh_keyframe(
        &mut self,
        kf_id: u64,
        map_from_cam: &Isometry3<f64>,
    ) -> Result<bool, GeoError> {
        if self.georef.update_map_pose(kf_id, map_from_cam)? {
            return Ok(true);
        }
        match self.pending.iter_mut().find(|(id, _, _)| *id == kf_id) {
            Some(p) => {
                p.1 = *map_from_cam;
                Ok(true)
            }
            None => Ok(false),
        }
    }

    /// Forgets a keyframe (culled by the map), paired or pending. Returns
    /// whether it was known.
    pub fn remove_keyframe(&mut self, kf_id: u64) -> bool {
        let before = self.pending.len();
        self.pending.retain(|(id, _, _)| *id != kf_id);
        self.georef.remove(kf_id) || self.pending.len() != before
    }

    /// Whether a keyframe is paired or pending.
    pub fn knows_keyframe(&self, kf_id: u64) -> bool {
        self.georef.contains(kf_id) || self.pending.iter().any(|(id, _, _)| *id == kf_id)
    }

    /// Retries the pending keyframes (call after telemetry arrives); returns
    /// how many were paired.
    pub fn retry_pending(&mut self) -> usize {
        let mut paired = 0;
        let waiting = std::mem::take(&mut self.pending);
        for (id, pose, t) in waiting {
            match self.history.lookup(t) {
                Ok(state) => {
                    let ned = ned_from_cam(&state, &self.params.mount);
                    if self
                        .georef
                        .add_keyframe(id, &pose, &ned, Some(state.v_ned), t)
                        .is_ok()
                    {
                        paired += 1;
                    } else {
                        self.dropped += 1;
                    }
                }
                Err(GeoError::NotYet { .. }) | Err(GeoError::EmptyHistory { .. }) => {
                    self.pending.push_back((id, pose, t))
                }
                Err(_) => self.dropped += 1,
            }
        }
        paired
    }

    /// Refits (or returns the unchanged) map → NED alignment.
    pub fn fit(&mut self) -> Result<GeoAlignment, GeoError> {
        self.georef.fit()
    }

    /// A target camera pose in the map as a vehicle target (needs home and
    /// a successful fit).
    pub fn target(&mut self, map_from_cam: &Isometry3<f64>) -> Result<GeoTarget, GeoError> {
        let frame = self.frame.ok_or(GeoError::NoHome)?;
        let alignment = self.georef.fit()?;
        convert_target(&alignment, map_from_cam, &frame, &self.params.mount)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geo::GimbalAngles;
    use nalgebra::{UnitQuaternion, Vector3};

    #[test]
    fn keyframes_wait_for_telemetry_and_targets_need_home() {
        let mut geo = Geo::new(Params::default());
        let g = Geodetic {
            lat_deg: 47.0,
            lon_deg: 8.0,
            alt_m: 400.0,
        };
        assert_eq!(geo.push_position_geodetic(0.0, &g), Err(GeoError::NoHome));
        assert_eq!(geo.target(&Isometry3::identity()), Err(GeoError::NoHome));
        geo.set_home(g).unwrap();
        let pose = Isometry3::identity();
        assert_eq!(geo.add_keyframe(1, &pose, 0.5), Ok(KeyframeStatus::Pending));
        for i in 0..=10 {
            let t = i as f64 * 0.1;
            geo.push_position_geodetic(t, &g).unwrap();
            let h = geo.history_mut();
            h.push_attitude(t, UnitQuaternion::identity()).unwrap();
            h.push_gimbal(
                t,
                GimbalAngles {
                    pitch: 0.0,
                    yaw: 0.0,
                },
            )
            .unwrap();
        }
        assert_eq!(geo.retry_pending(), 1);
        assert_eq!((geo.pending(), geo.dropped()), (0, 0));
        let p = geo.georeference().pairs()[0];
        assert!((p.p_ned.coords - Vector3::new(0.10, 0.0, 0.08)).norm() < 1e-6);
        // Older than the history: refused at once.
        assert!(matches!(
            geo.add_keyframe(2, &pose, -1.0),
            Err(GeoError::TooOld { .. })
        ));
        // Too few pairs to fit.
        assert!(matches!(
            geo.target(&pose),
            Err(GeoError::NotEnoughPairs { .. })
        ));
    }
}
