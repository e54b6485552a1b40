//! What a round of the shot refinement is given besides its frames: the
//! georeference alignment it works with ([`round_alignment`]: the fit
//! now, or the last round's when a refit is refused) and what the vehicle
//! reported when its frame was taken ([`observation`], the round's
//! [`Observation`]).

use crate::geo::{GeoAlignment, GeoError};
use crate::mission::plan::Target;

use super::arrival::{PositionReport, north_east_of};
use super::session::Observation;

/// The alignment a round works with: the georeference's fit now, or,
/// when a refit is refused after an earlier round had one, that round's
/// (`last`), with a note for the round saying so. Under a drifting GNSS
/// bias the pairs of a long flight stop agreeing with one similarity (the
/// share of inliers falls under `min_inlier_ratio`); the loop measures its
/// error in the images and corrects it, so it goes on with the alignment
/// it has rather than abort the shot. Refused before any round had one:
/// the refusal.
pub fn round_alignment(
    fit: Result<GeoAlignment, GeoError>,
    last: &mut Option<GeoAlignment>,
) -> Result<(GeoAlignment, Option<String>), GeoError> {
    match fit {
        Ok(a) => {
            *last = Some(a.clone());
            Ok((a, None))
        }
        Err(e) => match last {
            Some(a) => {
                let note = format!(
                    "georeference refit refused ({e}): this round kept the last round's alignment"
                );
                tracing::warn!("refinement: {note}");
                Ok((a.clone(), Some(note)))
            }
            None => Err(e),
        },
    }
}

/// The timing of the frame a round measures.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FrameTiming {
    /// Its capture time, unix seconds, when the source sent one.
    pub capture_unix: Option<f64>,
    /// When it was received, unix seconds.
    pub received_unix: f64,
    /// How long after the arrival it was received, seconds (0 when before).
    pub received_after_arrival_s: f64,
}

/// What the vehicle reported when a round's frame was taken.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Reports {
    /// The latest position.
    pub position: Option<PositionReport>,
    /// The latest heading (ATTITUDE's yaw), degrees.
    pub yaw_deg: Option<f64>,
    /// The latest gimbal pitch, degrees.
    pub gimbal_pitch_deg: Option<f64>,
}

/// The vehicle's report and the frame's timing when the frame is taken for
/// the round flying `target`: offsets from the target, speed, the frame's
/// capture relative to the arrival and its latency.
pub fn observation(target: &Target, frame: &FrameTiming, reports: &Reports) -> Observation {
    let arrived_unix = frame.received_unix - frame.received_after_arrival_s;
    let mut o = Observation {
        frame_capture_unix: frame.capture_unix,
        capture_after_arrival_s: frame.capture_unix.map(|c| c - arrived_unix),
        frame_latency_s: frame.capture_unix.map(|c| frame.received_unix - c),
        ..Observation::default()
    };
    if let Some(p) = &reports.position {
        let (n, e) = north_east_of(target, p.lat_deg, p.lon_deg);
        o.vehicle_offset_ned_m = Some([n, e, target.alt_m - p.rel_alt_m]);
        o.speed_m_s = Some(p.speed_m_s());
        o.position_age_s = Some(p.age_s);
    }
    if let Some(yaw) = reports.yaw_deg {
        o.yaw_error_deg = Some(crate::angle::wrap180(yaw - target.yaw_deg));
    }
    if let Some(pitch) = reports.gimbal_pitch_deg {
        o.gimbal_pitch_error_deg = Some(pitch - target.gimbal_pitch_deg);
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::lie::Sim3;
    use nalgebra::Vector3;

    /// A refit refused mid-loop (a drifting GNSS bias leaves too few pairs
    /// agreeing) keeps the last round's alignment; refused before any round
    /// had one, the refusal stands; a later fit replaces the kept one.
    #[test]
    fn a_refused_refit_keeps_the_last_rounds_alignment() {
        let refused = || {
            Err(GeoError::TooFewInliers {
                found: 23,
                needed: 24,
                pairs: 48,
            })
        };
        let fit = |x: f64| {
            GeoAlignment::given(Sim3::new(
                nalgebra::UnitQuaternion::identity(),
                Vector3::new(x, 0.0, 0.0),
                1.0,
            ))
        };
        let mut last = None;
        assert!(matches!(
            round_alignment(refused(), &mut last),
            Err(GeoError::TooFewInliers { found: 23, .. })
        ));
        let (a, note) = round_alignment(Ok(fit(1.0)), &mut last).unwrap();
        assert_eq!(a.ned_from_map.translation.x, 1.0);
        assert_eq!(note, None);
        // The round that kept an alignment says so, with the refusal.
        let (kept, note) = round_alignment(refused(), &mut last).unwrap();
        assert_eq!(kept.ned_from_map.translation.x, 1.0);
        let note = note.unwrap();
        assert!(
            note.contains("refit refused") && note.contains("23") && note.contains("kept"),
            "{note}"
        );
        let (b, note) = round_alignment(Ok(fit(2.0)), &mut last).unwrap();
        assert_eq!(b.ned_from_map.translation.x, 2.0);
        assert_eq!(note, None);
        let (kept, _) = round_alignment(refused(), &mut last).unwrap();
        assert_eq!(kept.ned_from_map.translation.x, 2.0);
    }

    /// The offsets are the vehicle's less the target's (the heading
    /// wrapped to ±180°), the capture is timed from the arrival.
    #[test]
    fn an_observation_is_the_reports_less_the_target() {
        let target = Target {
            lat_deg: 47.397,
            lon_deg: 8.545,
            alt_m: 15.0,
            yaw_deg: 350.0,
            gimbal_pitch_deg: -40.0,
            photo: true,
        };
        let frame = FrameTiming {
            capture_unix: Some(100.2),
            received_unix: 100.5,
            received_after_arrival_s: 0.4,
        };
        let reports = Reports {
            position: Some(PositionReport {
                lat_deg: target.lat_deg + 1e-5,
                lon_deg: target.lon_deg,
                rel_alt_m: 14.0,
                vel_ned_m_s: [0.0, 0.3, 0.4],
                age_s: 0.25,
            }),
            yaw_deg: Some(5.0),
            gimbal_pitch_deg: Some(-41.0),
        };
        let o = observation(&target, &frame, &reports);
        assert_eq!(o.frame_capture_unix, Some(100.2));
        assert!((o.capture_after_arrival_s.unwrap() - 0.1).abs() < 1e-9);
        assert!((o.frame_latency_s.unwrap() - 0.3).abs() < 1e-9);
        let [n, e, d] = o.vehicle_offset_ned_m.unwrap();
        assert!((n - 1.111).abs() < 0.01 && e.abs() < 1e-6 && (d - 1.0).abs() < 1e-9);
        assert!((o.speed_m_s.unwrap() - 0.5).abs() < 1e-6);
        assert_eq!(o.position_age_s, Some(0.25));
        assert!((o.yaw_error_deg.unwrap() - 15.0).abs() < 1e-9);
        assert_eq!(o.gimbal_pitch_error_deg, Some(-1.0));
        let blind = observation(&target, &frame, &Reports::default());
        assert_eq!(blind.vehicle_offset_ned_m, None);
        assert_eq!(blind.yaw_error_deg, None);
    }
}
