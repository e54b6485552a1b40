//! The extractor's scale levels as the map needs them ([`ScaleInfo`]): each
//! level's scale factor and keypoint position uncertainty, and the level at
//! which a point should appear at a distance (ORB-SLAM's PredictScale).

/// Scale information of the extractor that the map needs.
#[derive(Debug, Clone, PartialEq)]
pub struct ScaleInfo {
    /// Scale factor between levels.
    pub scale_factor: f64,
    /// Per level: `scale_factor^level`.
    pub scale_factors: Vec<f64>,
    /// Per level: `1 / sigma^2` of a keypoint's position (level 0: 1 px).
    pub inv_level_sigma2: Vec<f64>,
}

impl ScaleInfo {
    /// Scale factors for `n_levels` levels of `scale_factor`.
    pub fn new(scale_factor: f64, n_levels: usize) -> Self {
        let scale_factors: Vec<f64> = (0..n_levels.max(1))
            .map(|l| scale_factor.powi(l as i32))
            .collect();
        let inv_level_sigma2 = scale_factors.iter().map(|s| 1.0 / (s * s)).collect();
        ScaleInfo {
            scale_factor,
            scale_factors,
            inv_level_sigma2,
        }
    }

    /// Number of levels.
    pub fn n_levels(&self) -> usize {
        self.scale_factors.len()
    }

    /// The level at which a point at `dist` whose scale range ends at
    /// `max_distance` should appear (ORB-SLAM's PredictScale).
    pub fn predict_level(&self, max_distance: f64, dist: f64) -> usize {
        let ratio = max_distance / dist.max(1e-9);
        let level = (ratio.ln() / self.scale_factor.ln()).ceil();
        if level.is_finite() {
            (level.max(0.0) as usize).min(self.n_levels() - 1)
        } else {
            0
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn scale_prediction_matches_orb_slam() {
        let s = ScaleInfo::new(1.2, 8);
        assert_eq!(s.predict_level(10.0, 10.0), 0);
        assert_eq!(s.predict_level(10.0, 10.0 / 1.2 / 1.2 * 1.01), 2);
        assert_eq!(s.predict_level(10.0, 0.001), 7);
        assert_eq!(s.predict_level(10.0, 20.0), 0);
    }
}
