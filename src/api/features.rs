//! The SLAM's keypoints of a recent frame, for the page's feature overlay:
//! what tracking made of each keypoint (inlier, outlier, unmatched), at
//! most `[server] features_max` of them packed in a few bytes each
//! ([`pack`]), served by `GET /features` beside the frame they were found
//! in (`GET /features/{seq}/frame.jpg`), so the page draws them on that
//! frame and not on whichever the live video shows.

use std::sync::Arc;

use base64::Engine as _;
use serde::Serialize;

use crate::slam::{KeypointState, TrackedKeypoint};
use crate::video::live::Frame;

/// A frame the SLAM processed and what tracking made of its keypoints.
#[derive(Debug, Clone)]
pub struct TrackedFeatures {
    /// The frame: its ingest sequence number, picture and JPEG.
    pub frame: Arc<Frame>,
    /// The tracking state after it (`tracking`, `lost`, `not_initialized`).
    pub state: String,
    /// Its keypoints.
    pub keypoints: Arc<[TrackedKeypoint]>,
}

/// Keypoints per state.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct StateCounts {
    /// Matched to a map point and kept by the pose.
    pub inlier: usize,
    /// Matched, then rejected by a pose optimisation.
    pub outlier: usize,
    /// Not matched.
    pub unmatched: usize,
}

impl StateCounts {
    /// The counts of `points`.
    pub fn of(points: &[TrackedKeypoint]) -> Self {
        let mut c = Self::default();
        for p in points {
            *c.slot(p.state) += 1;
        }
        c
    }

    fn slot(&mut self, s: KeypointState) -> &mut usize {
        match s {
            KeypointState::Inlier => &mut self.inlier,
            KeypointState::Outlier => &mut self.outlier,
            KeypointState::Unmatched => &mut self.unmatched,
        }
    }

    /// All of them.
    pub fn total(&self) -> usize {
        self.inlier + self.outlier + self.unmatched
    }
}

/// Bytes per keypoint in the packed form.
pub const BYTES_PER_POINT: usize = 5;
/// The packed coordinates' unit: 1/8 pixel.
pub const SUBPIXEL: f32 = 8.0;
/// The packed form, as the reply describes it.
pub const ENCODING: &str = "base64 of 5 bytes per keypoint: column and row as little-endian \
    u16 in 1/8 pixels, then the state (0 inlier, 1 outlier, 2 unmatched)";

fn state_code(s: KeypointState) -> u8 {
    match s {
        KeypointState::Inlier => 0,
        KeypointState::Outlier => 1,
        KeypointState::Unmatched => 2,
    }
}

/// At most `max` of `points`: the inliers first, then the outliers, then
/// the unmatched (the states that say most about tracking come first);
/// where a state's share must be cut, its keypoints are taken evenly
/// through the extractor's order (level by level, cell by cell), so that
/// they still cover the frame.
pub fn select(points: &[TrackedKeypoint], max: usize) -> Vec<TrackedKeypoint> {
    let mut out = Vec::with_capacity(points.len().min(max));
    for state in [
        KeypointState::Inlier,
        KeypointState::Outlier,
        KeypointState::Unmatched,
    ] {
        let these: Vec<&TrackedKeypoint> = points.iter().filter(|p| p.state == state).collect();
        let room = max - out.len();
        let n = these.len();
        if n <= room {
            out.extend(these.into_iter().copied());
        } else {
            // `room` indices spread evenly over 0..n.
            out.extend((0..room).map(|k| *these[k * n / room]));
        }
    }
    out
}

/// `points` packed ([`ENCODING`]): coordinates clamped to what a u16 of
/// 1/8 pixels holds (8191.875 px).
pub fn pack(points: &[TrackedKeypoint]) -> String {
    let mut bytes = Vec::with_capacity(points.len() * BYTES_PER_POINT);
    let fixed = |v: f32| {
        let q = (v * SUBPIXEL).round();
        if q.is_finite() {
            q.clamp(0.0, f32::from(u16::MAX)) as u16
        } else {
            0
        }
    };
    for p in points {
        bytes.extend_from_slice(&fixed(p.x).to_le_bytes());
        bytes.extend_from_slice(&fixed(p.y).to_le_bytes());
        bytes.push(state_code(p.state));
    }
    base64::engine::general_purpose::STANDARD.encode(bytes)
}

/// The keypoints of a packed string (None: not base64, a partial
/// record or an unknown state).
pub fn unpack(text: &str) -> Option<Vec<TrackedKeypoint>> {
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(text)
        .ok()?;
    if bytes.len() % BYTES_PER_POINT != 0 {
        return None;
    }
    bytes
        .chunks_exact(BYTES_PER_POINT)
        .map(|c| {
            let state = match c[4] {
                0 => KeypointState::Inlier,
                1 => KeypointState::Outlier,
                2 => KeypointState::Unmatched,
                _ => return None,
            };
            Some(TrackedKeypoint {
                x: f32::from(u16::from_le_bytes([c[0], c[1]])) / SUBPIXEL,
                y: f32::from(u16::from_le_bytes([c[2], c[3]])) / SUBPIXEL,
                state,
            })
        })
        .collect()
}

/// The reply of `GET /features`.
#[derive(Debug, Clone, Serialize)]
pub struct FeaturesView {
    /// The frame's ingest sequence number.
    pub seq: u64,
    /// Its capture time (else its receive time), unix seconds.
    pub timestamp: f64,
    /// Seconds since it was received.
    pub age_s: f64,
    /// The tracking state after it.
    pub state: String,
    /// The frame's width, pixels.
    pub width: u32,
    /// Its height, pixels.
    pub height: u32,
    /// Every keypoint of the frame, per state.
    pub counts: StateCounts,
    /// The keypoints in `points`, per state.
    pub shown: StateCounts,
    /// How `points` is packed.
    pub encoding: &'static str,
    /// The keypoints shown, packed.
    pub points: String,
    /// Where the frame's picture is (`/api/v1/features/{seq}/frame.jpg`).
    pub frame_url: String,
}

impl FeaturesView {
    /// The view of `f` with at most `max` keypoints.
    pub fn of(f: &TrackedFeatures, max: usize) -> Self {
        let shown = select(&f.keypoints, max);
        let (width, height) = f.frame.image.dimensions();
        Self {
            seq: f.frame.seq,
            timestamp: f.frame.timestamp(),
            age_s: crate::clock::since(f.frame.received).as_secs_f64(),
            state: f.state.clone(),
            width,
            height,
            counts: StateCounts::of(&f.keypoints),
            shown: StateCounts::of(&shown),
            encoding: ENCODING,
            points: pack(&shown),
            frame_url: format!("/api/v1/features/{}/frame.jpg", f.frame.seq),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(x: f32, y: f32, state: KeypointState) -> TrackedKeypoint {
        TrackedKeypoint { x, y, state }
    }

    #[test]
    fn packing_keeps_positions_to_a_sixteenth_of_a_pixel_and_states() {
        let pts = vec![
            kp(0.0, 0.0, KeypointState::Inlier),
            kp(639.94, 479.3, KeypointState::Outlier),
            kp(123.456, 78.9, KeypointState::Unmatched),
        ];
        let text = pack(&pts);
        assert_eq!(
            base64::engine::general_purpose::STANDARD
                .decode(&text)
                .unwrap()
                .len(),
            pts.len() * BYTES_PER_POINT
        );
        let back = unpack(&text).unwrap();
        assert_eq!(back.len(), pts.len());
        for (a, b) in pts.iter().zip(&back) {
            assert!((a.x - b.x).abs() <= 0.5 / SUBPIXEL, "{a:?} {b:?}");
            assert!((a.y - b.y).abs() <= 0.5 / SUBPIXEL, "{a:?} {b:?}");
            assert_eq!(a.state, b.state);
        }
        // Outside what the packing holds: clamped, never wrapped.
        let back = unpack(&pack(&[kp(-3.0, 9000.0, KeypointState::Inlier)])).unwrap();
        assert_eq!(
            (back[0].x, back[0].y),
            (0.0, f32::from(u16::MAX) / SUBPIXEL)
        );
        // Damaged input is refused.
        assert!(unpack("not base64!").is_none());
        assert!(unpack(&base64::engine::general_purpose::STANDARD.encode([1, 2, 3])).is_none());
        assert!(
            unpack(&base64::engine::general_purpose::STANDARD.encode([0, 0, 0, 0, 7])).is_none()
        );
    }

    #[test]
    fn selection_is_bounded_inliers_first_and_spread() {
        // 100 inliers, 20 outliers, 1000 unmatched along a line.
        let mut pts = Vec::new();
        for i in 0..1120 {
            let s = if i % 56 < 5 {
                KeypointState::Inlier
            } else if i % 56 == 5 {
                KeypointState::Outlier
            } else {
                KeypointState::Unmatched
            };
            pts.push(kp(i as f32, 0.0, s));
        }
        let c = StateCounts::of(&pts);
        assert_eq!((c.inlier, c.outlier, c.unmatched), (100, 20, 1000));
        // Room for all: all, in state order.
        assert_eq!(select(&pts, 5000).len(), 1120);
        // Room for the inliers, the outliers and 380 of the unmatched,
        // spread over the whole line.
        let s = select(&pts, 500);
        let sc = StateCounts::of(&s);
        assert_eq!((sc.inlier, sc.outlier, sc.unmatched), (100, 20, 380));
        let xs: Vec<f32> = s
            .iter()
            .filter(|p| p.state == KeypointState::Unmatched)
            .map(|p| p.x)
            .collect();
        assert!(xs[0] < 10.0 && *xs.last().unwrap() > 1100.0, "{xs:?}");
        // Less room than inliers: inliers only, spread.
        let s = select(&pts, 10);
        assert_eq!(StateCounts::of(&s).inlier, 10);
        assert!(s.last().unwrap().x > 1000.0);
        assert!(select(&pts, 0).is_empty());
    }
}
