//! Points and their observations, kept both ways (a point lists keyframe
//! `k` at keypoint `i` exactly when keyframe `k`'s slot `i` holds it):
//! points added, erased and fused ([`Map::replace_point`]), observations
//! added and removed, a point's representative descriptor, viewing
//! direction and scale range; what a keyframe's points say of it (tracked
//! points, median scene depth).

use nalgebra::{Point3, Vector3};

use crate::features::{Descriptor, hamming};

use super::ids::{KeyFrameId, PointId};
use super::keyframe::KeyFrame;
use super::point::MapPoint;
use super::store::Map;

impl KeyFrame {
    /// Number of map points observed by at least `min_obs` keyframes.
    pub fn tracked_points(&self, map: &Map, min_obs: usize) -> usize {
        self.points
            .iter()
            .flatten()
            .filter(|p| {
                map.point(**p)
                    .is_some_and(|mp| mp.observations.len() >= min_obs)
            })
            .count()
    }
}

impl Map {
    /// Insert a point with no observations yet.
    pub fn add_point(
        &mut self,
        position: Point3<f64>,
        descriptor: Descriptor,
        first_kf: KeyFrameId,
    ) -> PointId {
        let id = PointId(self.points.len() as u32);
        self.points.push(Some(Box::new(MapPoint {
            id,
            position,
            observations: Vec::with_capacity(4),
            descriptor,
            normal: Vector3::zeros(),
            min_distance: 0.0,
            max_distance: f64::INFINITY,
            first_kf,
            ref_kf: first_kf,
            visible: 1,
            found: 1,
        })));
        self.n_points += 1;
        id
    }

    /// Record that keyframe `kf` sees point `p` at keypoint `idx` (both ways).
    /// A slot already holding another point keeps it (returns false).
    pub fn add_observation(&mut self, p: PointId, kf: KeyFrameId, idx: u32) -> bool {
        let Some(mp) = self.point(p) else {
            return false;
        };
        let existing = mp.index_in(kf);
        let Some(k) = self.keyframe_mut(kf) else {
            return false;
        };
        match k.points.get(idx as usize) {
            None => return false,
            Some(Some(q)) => return *q == p,
            Some(None) => {}
        }
        k.points[idx as usize] = Some(p);
        if let Some(old) = existing {
            // Seen by this keyframe at another keypoint: one observation per
            // keyframe, the newer wins.
            if let Some(s) = k.points.get_mut(old as usize) {
                *s = None;
            }
            if let Some(mp) = self.point_mut(p)
                && let Some(o) = mp.observations.iter_mut().find(|o| o.0 == kf)
            {
                o.1 = idx;
            }
        } else if let Some(mp) = self.point_mut(p) {
            mp.observations.push((kf, idx));
        }
        true
    }

    /// Remove the observation of `p` by `kf` (both ways). A point left with
    /// fewer than 2 observations is erased. Returns true when it was erased.
    pub fn erase_observation(&mut self, p: PointId, kf: KeyFrameId) -> bool {
        let Some(mp) = self.point_mut(p) else {
            return false;
        };
        let Some(pos) = mp.observations.iter().position(|o| o.0 == kf) else {
            return false;
        };
        let (_, idx) = mp.observations.swap_remove(pos);
        let remaining = mp.observations.len();
        let ref_gone = mp.ref_kf == kf;
        if ref_gone && let Some(first) = mp.observations.first() {
            mp.ref_kf = first.0;
        }
        if let Some(k) = self.keyframe_mut(kf)
            && let Some(s) = k.points.get_mut(idx as usize)
            && *s == Some(p)
        {
            *s = None;
        }
        if remaining < 2 {
            self.erase_point(p);
            return true;
        }
        false
    }

    /// Erase a point and every reference to it.
    pub fn erase_point(&mut self, p: PointId) {
        let Some(slot) = self.points.get_mut(p.0 as usize) else {
            return;
        };
        let Some(mp) = slot.take() else {
            return;
        };
        self.n_points -= 1;
        for (kf, idx) in mp.observations {
            if let Some(k) = self.keyframe_mut(kf)
                && let Some(s) = k.points.get_mut(idx as usize)
                && *s == Some(p)
            {
                *s = None;
            }
        }
    }

    /// Replace point `old` by `new` everywhere (fusion of duplicates): the
    /// observations of `old` move to `new` where the keyframe does not
    /// already see `new`; `old` is erased.
    pub fn replace_point(&mut self, old: PointId, new: PointId) {
        if old == new || self.point(new).is_none() {
            return;
        }
        let Some(mp_old) = self.points.get_mut(old.0 as usize).and_then(Option::take) else {
            return;
        };
        self.n_points -= 1;
        let (visible, found) = (mp_old.visible, mp_old.found);
        for (kf, idx) in mp_old.observations {
            let already = self.point(new).is_some_and(|m| m.index_in(kf).is_some());
            if let Some(k) = self.keyframe_mut(kf)
                && let Some(s) = k.points.get_mut(idx as usize)
            {
                *s = None;
            }
            if !already {
                self.add_observation(new, kf, idx);
            }
        }
        if let Some(mp) = self.point_mut(new) {
            mp.visible += visible;
            mp.found += found;
        }
        self.update_point_descriptor(new);
        self.update_point_normal_and_depth(new);
    }

    /// Choose the representative descriptor of a point: the one with the
    /// least median Hamming distance to the point's other descriptors.
    pub fn update_point_descriptor(&mut self, p: PointId) {
        let Some(mp) = self.point(p) else {
            return;
        };
        let descs: Vec<Descriptor> = mp
            .observations
            .iter()
            .filter_map(|(kf, idx)| {
                self.keyframe(*kf)
                    .and_then(|k| k.descriptors.get(*idx as usize))
                    .copied()
            })
            .collect();
        if descs.is_empty() {
            return;
        }
        let n = descs.len();
        let mut best = (u32::MAX, 0usize);
        let mut row = vec![0u32; n];
        for i in 0..n {
            for j in 0..n {
                row[j] = hamming(&descs[i], &descs[j]);
            }
            row.sort_unstable();
            let median = row[(n - 1) / 2];
            if median < best.0 {
                best = (median, i);
            }
        }
        let d = descs[best.1];
        if let Some(mp) = self.point_mut(p) {
            mp.descriptor = d;
        }
    }

    /// Recompute a point's mean viewing direction and scale-invariance range.
    pub fn update_point_normal_and_depth(&mut self, p: PointId) {
        let Some(mp) = self.point(p) else {
            return;
        };
        let pos = mp.position.coords;
        let mut normal = Vector3::zeros();
        let mut n = 0;
        for (kf, _) in &mp.observations {
            if let Some(k) = self.keyframe(*kf) {
                let v = pos - k.center();
                let norm = v.norm();
                if norm > 0.0 {
                    normal += v / norm;
                    n += 1;
                }
            }
        }
        let ref_kf = if self.keyframe(mp.ref_kf).is_some() {
            mp.ref_kf
        } else {
            match mp.observations.first() {
                Some(o) => o.0,
                None => return,
            }
        };
        let Some(rk) = self.keyframe(ref_kf) else {
            return;
        };
        let Some(idx) = mp.index_in(ref_kf) else {
            return;
        };
        let dist = (pos - rk.center()).norm();
        let octave = rk
            .keypoints
            .get(idx as usize)
            .map_or(0, |k| k.octave as usize);
        let level_scale = self.scale.scale_factors.get(octave).copied().unwrap_or(1.0);
        let top = self.scale.scale_factors.last().copied().unwrap_or(1.0);
        let max_distance = dist * level_scale;
        let min_distance = max_distance / top;
        if let Some(mp) = self.point_mut(p) {
            if n > 0 {
                mp.normal = (normal / n as f64).normalize();
            }
            mp.ref_kf = ref_kf;
            mp.max_distance = max_distance;
            mp.min_distance = min_distance;
        }
    }

    /// Median depth of the keyframe's points in its camera: the lower median
    /// (nearest-rank 50 % quantile, ORB-SLAM's scene median depth); None
    /// without points.
    pub fn median_depth(&self, id: KeyFrameId) -> Option<f64> {
        let kf = self.keyframe(id)?;
        let depths: Vec<f64> = kf
            .points
            .iter()
            .flatten()
            .filter_map(|p| self.point(*p))
            .map(|mp| (kf.cam_from_world * mp.position).z)
            .collect();
        crate::stats::quantile(&depths, 0.5)
    }

    /// The map's measurement noise as its own observations show it: the
    /// per-axis standard deviation, in level-0 pixels of a level-0
    /// keypoint, of the reprojection residuals of every observation of
    /// every point (undistorted keypoint against the pinhole projection,
    /// divided by the keypoint's pyramid scale). Robust: from the median of
    /// the squared residuals (a 2-D Gaussian's is `2 ln 2 σ²`), so the
    /// few outlier observations a map keeps do not set it. None with fewer
    /// than 20 observations in front of their cameras.
    pub fn reprojection_noise_px(&self) -> Option<f64> {
        let r2 = self.scaled_squared_residuals();
        if r2.len() < 20 {
            return None;
        }
        let median = crate::stats::quantile(&r2, 0.5)?;
        Some((median / (2.0 * std::f64::consts::LN_2)).sqrt())
    }

    /// The same residuals' plain per-axis RMS, level-0 pixels: with
    /// [`Self::reprojection_noise_px`], how heavy the residuals' tail is
    /// (a Gaussian's RMS equals its robust sigma). None with fewer than 20.
    pub fn reprojection_rms_px(&self) -> Option<f64> {
        let r2 = self.scaled_squared_residuals();
        if r2.len() < 20 {
            return None;
        }
        Some((r2.iter().sum::<f64>() / (2.0 * r2.len() as f64)).sqrt())
    }

    /// Every observation's squared reprojection residual over its
    /// keypoint's pyramid scale squared (level-0 pixels²), in front of its
    /// camera.
    fn scaled_squared_residuals(&self) -> Vec<f64> {
        let mut r2 = Vec::new();
        for mp in self.points() {
            for &(kf_id, idx) in &mp.observations {
                let Some(kf) = self.keyframe(kf_id) else {
                    continue;
                };
                let Some(kp) = kf.keypoints.get(idx as usize) else {
                    continue;
                };
                let Some(uv) = self
                    .camera
                    .project_ideal(&(kf.cam_from_world * mp.position).coords)
                else {
                    continue;
                };
                let inv_s2 = self
                    .scale
                    .inv_level_sigma2
                    .get(kp.octave as usize)
                    .copied()
                    .unwrap_or(1.0);
                let d2 = (uv.x - kp.ux as f64).powi(2) + (uv.y - kp.uy as f64).powi(2);
                r2.push(d2 * inv_s2);
            }
        }
        r2
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::slam::map::testing::map_with;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    /// Keypoints put at their points' projections plus Gaussian noise of
    /// `sigma` px per axis (scaled by the level), `outliers` of every 100
    /// moved 15 px instead.
    fn noisy_map(sigma: f64, outliers: usize, octave: u8) -> Map {
        let mut m = map_with(8, 50);
        let mut rng = SmallRng::seed_from_u64(7);
        let scale = m.scale.inv_level_sigma2[octave as usize].recip().sqrt();
        let mut gauss = move || {
            // Box-Muller.
            let (u, v): (f64, f64) = (rng.random_range(1e-12..1.0), rng.random());
            (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()
        };
        let ids: Vec<KeyFrameId> = m.keyframes().map(|k| k.id).collect();
        let mut n = 0usize;
        for id in ids {
            let pose = m.keyframe(id).unwrap().cam_from_world;
            let pts = m.keyframe(id).unwrap().points.clone();
            let projected: Vec<_> = pts
                .iter()
                .map(|p| {
                    let mp = m.point(p.unwrap()).unwrap();
                    m.camera
                        .project_ideal(&(pose * mp.position).coords)
                        .unwrap()
                })
                .collect();
            let kf = m.keyframe_mut(id).unwrap();
            for (kp, uv) in kf.keypoints.iter_mut().zip(projected) {
                n += 1;
                let (dx, dy) = if n % 100 < outliers {
                    (15.0, 0.0)
                } else {
                    (gauss() * sigma * scale, gauss() * sigma * scale)
                };
                kp.ux = (uv.x + dx) as f32;
                kp.uy = (uv.y + dy) as f32;
                kp.octave = octave;
            }
        }
        m
    }

    #[test]
    fn reprojection_noise_is_the_residuals_per_axis_sigma_robust_to_outliers() {
        // 400 observations: the estimate's own spread is a few percent.
        for (sigma, octave) in [(0.3, 0), (1.0, 0), (0.5, 3)] {
            let got = noisy_map(sigma, 0, octave).reprojection_noise_px().unwrap();
            assert!(
                (got / sigma - 1.0).abs() < 0.12,
                "sigma {sigma} at level {octave}: {got}"
            );
        }
        // 5 % of the observations 15 px off move it by little.
        let got = noisy_map(0.5, 5, 0).reprojection_noise_px().unwrap();
        assert!((got / 0.5 - 1.0).abs() < 0.2, "with outliers: {got}");
        // The plain RMS: the noise alone without outliers; 5 % of
        // residuals of 15 px (a 2-D shift, so 15/√2 per axis) raise it to
        // about √(0.25 + 0.05·112.5) = 2.4 px.
        let rms = noisy_map(0.5, 0, 0).reprojection_rms_px().unwrap();
        assert!((rms / 0.5 - 1.0).abs() < 0.2, "without outliers: {rms}");
        let rms = noisy_map(0.5, 5, 0).reprojection_rms_px().unwrap();
        assert!((1.8..3.0).contains(&rms), "with outliers: {rms}");
        // Too few observations: none.
        assert_eq!(map_with(1, 10).reprojection_noise_px(), None);
    }

    #[test]
    fn observations_stay_two_way_through_edits() {
        let mut m = map_with(4, 10);
        m.check_invariants().unwrap();
        assert_eq!(m.keyframe(KeyFrameId(0)).unwrap().covisible.len(), 3);
        assert_eq!(m.keyframe(KeyFrameId(2)).unwrap().weight(KeyFrameId(1)), 10);
        // A slot already holding another point is not overwritten.
        assert!(!m.add_observation(PointId(1), KeyFrameId(0), 0));
        // Erasing observations down to one erases the point.
        for k in 0..3 {
            m.erase_observation(PointId(3), KeyFrameId(k));
        }
        assert!(m.point(PointId(3)).is_none());
        m.check_invariants().unwrap();
        // Fusion: point 4's observations move to point 5 where possible.
        m.erase_observation(PointId(5), KeyFrameId(3));
        m.replace_point(PointId(4), PointId(5));
        assert!(m.point(PointId(4)).is_none());
        assert_eq!(m.point(PointId(5)).unwrap().observations.len(), 4);
        m.check_invariants().unwrap();
        // Erasing a keyframe re-parents its children and leaves no dangling id.
        let child_of_1: Vec<KeyFrameId> = m.keyframe(KeyFrameId(1)).unwrap().children.clone();
        let pose_before = m.keyframe(KeyFrameId(1)).unwrap().cam_from_world;
        // A keyframe a shot is drawn on is kept; a missing one cannot be pinned.
        assert!(m.pin_keyframe(KeyFrameId(2)));
        assert!(!m.erase_keyframe(KeyFrameId(2)));
        assert!(!m.pin_keyframe(KeyFrameId(99)));
        assert!(m.erase_keyframe(KeyFrameId(1)));
        m.check_invariants().unwrap();
        for c in child_of_1 {
            assert_ne!(m.keyframe(c).unwrap().parent, Some(KeyFrameId(1)));
        }
        // Its pose can still be recovered through its parent.
        let pose_after = m.keyframe_pose(KeyFrameId(1)).unwrap();
        assert!((pose_after.translation.vector - pose_before.translation.vector).norm() < 1e-12);
        // The first keyframe is never erased.
        assert!(!m.erase_keyframe(KeyFrameId(0)));
        assert_eq!(m.keyframe_count(), 3);
    }
}
