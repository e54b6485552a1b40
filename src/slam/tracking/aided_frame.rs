//! A frame vision could not pose, posed with the telemetry's help: the
//! local map searched around the telemetry's prediction and the pose
//! optimised with it as a prior (vision + telemetry), or the prediction
//! itself (telemetry); see [`super::super::aided`].

use super::super::aided;
use super::super::frame::{Frame, PoseSource};
use super::super::map::Map;
use super::super::priors::TelemetrySample;
use super::{Accepted, Tracked, Tracker};

impl Tracker {
    /// Vision failed and the telemetry predicts the frame: the local map
    /// searched around the prediction, the pose optimised with it as a
    /// prior (vision + telemetry), or the prediction itself when vision
    /// finds too little (telemetry).
    pub(super) fn track_aided(
        &mut self,
        map: &mut Map,
        frame: &mut Frame,
        prediction: aided::Prediction,
        sample: Option<TelemetrySample>,
        mapping_idle: bool,
    ) -> Tracked {
        let params = self
            .aid
            .as_ref()
            .map(|a| a.params.clone())
            .unwrap_or_default();
        frame.clear_matches();
        frame.prior = Some(prediction.prior);
        let predicted = prediction.prior.cam_from_world;
        let local = self.local_map.track(
            &self.ctx,
            &mut self.marks,
            map,
            frame,
            predicted,
            params.search_radius,
            self.reference_kf,
        );
        let fit = local.fit.filter(|f| f.inliers >= params.min_inliers);
        if fit.is_some()
            && let Some(best) = local.reference
        {
            self.reference_kf = Some(best);
        }
        let accepted = match fit {
            Some(fit) => Accepted {
                cam_from_world: fit.cam_from_world,
                inliers: fit.inliers,
                source: PoseSource::VisionTelemetry,
                recently_relocalized: false,
                sample,
            },
            None => {
                frame.clear_matches();
                Accepted {
                    cam_from_world: predicted,
                    inliers: 0,
                    source: PoseSource::Telemetry,
                    recently_relocalized: false,
                    sample,
                }
            }
        };
        // How far the telemetry's prediction is from the constant-velocity
        // model's (for the logs).
        let (turn_deg, moved) = match (&self.velocity, &self.last) {
            (Some(v), Some(l)) if tracing::enabled!(tracing::Level::DEBUG) => {
                let cv = v * l.cam_from_world;
                (
                    (cv.rotation.inverse() * predicted.rotation)
                        .angle()
                        .to_degrees(),
                    (cv.inverse().translation.vector - predicted.inverse().translation.vector)
                        .norm(),
                )
            }
            _ => (f64::NAN, f64::NAN),
        };
        tracing::debug!(
            frame = frame.index,
            source = accepted.source.name(),
            inliers = accepted.inliers,
            local_inliers = local.fit.map_or(0, |f| f.inliers),
            gnss = prediction.from_gnss,
            turn_from_velocity_deg = turn_deg,
            anchor = self.anchor.as_ref().map_or(0, |a| a.record.index),
            turn_from_anchor_deg = self
                .anchor
                .as_ref()
                .and_then(|a| a.cam_from_world(map))
                .map_or(f64::NAN, |a| (a.rotation.inverse() * predicted.rotation)
                    .angle()
                    .to_degrees()),
            velocity_turn_deg = self
                .velocity
                .map_or(f64::NAN, |v| v.rotation.angle().to_degrees()),
            off_velocity = moved,
            "frame posed with the telemetry's help"
        );
        self.accept(map, frame, accepted, mapping_idle)
    }
}
