//! Realism for a camera on a live (stepped) vehicle: the true camera pose
//! over time kept as a short history, so a frame can be exposed over its
//! real motion (motion blur, rolling shutter) a moment after its time.
//!
//! The simulator steps the vehicle at 50 Hz; the camera's rows and
//! sub-exposure samples need poses in between and around the frame's
//! time. [`PoseHistory`] keeps the true camera pose of every step (GNSS and
//! wind errors included, the gimbal's pointing error not), and
//! [`PoseWindow::world_from_cam`] interpolates it (linear in translation,
//! slerp in rotation) and adds the gimbal error at the exact time. Frames
//! are therefore exposed [`LIVE_EXPOSURE_LAG_S`] behind the simulation
//! clock: the whole exposure, readout included, lies in the past.

use std::collections::VecDeque;

use nalgebra::Isometry3;

use crate::disturbance::GimbalJitter;

/// How far behind the simulation clock a live frame's time lies, seconds:
/// more than half the longest exposure (1/60 s) plus half the longest
/// readout (0.2 s / 2 is refused; presets use at most 33 ms).
pub const LIVE_EXPOSURE_LAG_S: f64 = 0.06;

/// The true camera pose of each simulation step over the last second.
#[derive(Debug, Clone, Default)]
pub struct PoseHistory {
    poses: VecDeque<(f64, Isometry3<f64>)>,
}

/// Seconds of history kept.
const KEEP_S: f64 = 1.0;

impl PoseHistory {
    /// An empty history.
    pub fn new() -> Self {
        Self::default()
    }

    /// Records the pose at time `t` (times must increase; older poses than
    /// a second are forgotten).
    pub fn push(&mut self, t: f64, world_from_cam: Isometry3<f64>) {
        if self.poses.back().is_some_and(|b| b.0 >= t) {
            return;
        }
        self.poses.push_back((t, world_from_cam));
        while self.poses.front().is_some_and(|f| f.0 < t - KEEP_S) {
            self.poses.pop_front();
        }
    }

    /// Time of the newest pose.
    pub fn latest(&self) -> Option<f64> {
        self.poses.back().map(|b| b.0)
    }

    /// The poses covering `[t0, t1]` (one beyond each end when there are),
    /// with the gimbal error to add.
    pub fn window(&self, t0: f64, t1: f64, gimbal: Option<GimbalJitter>) -> PoseWindow {
        let start = self.poses.partition_point(|p| p.0 <= t0).saturating_sub(1);
        let end = (self.poses.partition_point(|p| p.0 < t1) + 1).min(self.poses.len());
        PoseWindow {
            poses: self.poses.range(start..end.max(start)).copied().collect(),
            gimbal,
        }
    }
}

/// A stretch of [`PoseHistory`] to expose a frame from (owned, so it can
/// go to a render thread).
#[derive(Debug, Clone)]
pub struct PoseWindow {
    poses: Vec<(f64, Isometry3<f64>)>,
    gimbal: Option<GimbalJitter>,
}

impl PoseWindow {
    /// The true camera pose at `t`: interpolated between the steps around
    /// it (clamped at the window's ends), turned by the gimbal's error at
    /// `t`. Identity for an empty window.
    pub fn world_from_cam(&self, t: f64) -> Isometry3<f64> {
        let nominal = match self.poses.len() {
            0 => Isometry3::identity(),
            _ => {
                let i = self.poses.partition_point(|p| p.0 <= t);
                if i == 0 {
                    self.poses[0].1
                } else if i >= self.poses.len() {
                    self.poses[self.poses.len() - 1].1
                } else {
                    let (a, b) = (&self.poses[i - 1], &self.poses[i]);
                    let f = ((t - a.0) / (b.0 - a.0).max(1e-12)).clamp(0.0, 1.0);
                    crate::imaging::lerp_pose(&a.1, &b.1, f)
                }
            }
        };
        match &self.gimbal {
            Some(g) => g.apply(&nominal, t),
            None => nominal,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    #[test]
    fn window_interpolates_between_steps_and_forgets_old_poses() {
        let mut h = PoseHistory::new();
        for k in 0..200 {
            let t = k as f64 * 0.02;
            let pose = Isometry3::from_parts(
                Translation3::new(5.0 * t, 0.0, -30.0),
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), 0.5 * t),
            );
            h.push(t, pose);
        }
        assert_eq!(h.latest(), Some(199.0 * 0.02));
        let w = h.window(3.5, 3.6, None);
        let p = w.world_from_cam(3.537);
        assert!((p.translation.x - 5.0 * 3.537).abs() < 1e-9);
        let angle = p.rotation.angle();
        assert!((angle - 0.5 * 3.537).abs() < 1e-9, "{angle}");
        // Older than a second: gone, the window clamps at its oldest pose.
        let w = h.window(1.0, 1.1, None);
        assert!((w.world_from_cam(1.0).translation.x - 5.0 * 2.98).abs() < 1e-9);
    }
}
