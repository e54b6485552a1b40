//! Measuring the live framing over several frames instead of one: after
//! the arrival, the loop takes a few frames a little apart, measures the
//! shot error and localises each, and combines them robustly (median of the
//! finite values, [`crate::stats::finite_median`], then
//! the mean of the values within a few robust deviations of it). The spread
//! of the frames is the measurement's own noise, which the controller uses
//! to weigh (and gate) its correction.

use image::GrayImage;
use nalgebra::Vector3;

use crate::stats::finite_median;

/// Every tunable number of the measurement on arrival.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MeasureParams {
    /// Live frames measured per arrival (1: the single-frame measure).
    pub frames: usize,
    /// Time between two measured frames, seconds (frames closer than the
    /// video's frame interval are the same frame).
    pub spacing_s: f64,
    /// A frame's value counts as an outlier beyond this many robust
    /// standard deviations (1.4826 MAD) from the median.
    pub outlier_sigmas: f64,
    /// Smallest standard deviation of one frame's localised position, m:
    /// frames of one hover share the map's local error, so their spread
    /// alone understates the measurement's noise.
    pub min_position_sigma_m: f64,
    /// The same for the heading and the gimbal pitch, degrees.
    pub min_angle_sigma_deg: f64,
}

impl Default for MeasureParams {
    fn default() -> Self {
        Self {
            frames: 5,
            spacing_s: 0.2,
            outlier_sigmas: 3.0,
            min_position_sigma_m: 0.05,
            min_angle_sigma_deg: 0.1,
        }
    }
}

/// One live frame of a measurement and what the vehicle reported when it
/// was taken.
#[derive(Debug, Clone, Copy)]
pub struct LiveFrame<'a> {
    /// The frame.
    pub image: &'a GrayImage,
    /// The vehicle's reported position when it was taken, local NED metres
    /// around home (None: not known; the loop then takes the target flown).
    pub reported_ned_m: Option<Vector3<f64>>,
}

/// A robust average of one quantity over the frames.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Robust {
    /// The mean of the values within `outlier_sigmas` of the median.
    pub mean: f64,
    /// Standard deviation of that mean (the values' spread, at least the
    /// given floor, over the square root of their count).
    pub sigma: f64,
    /// Values kept.
    pub kept: usize,
    /// Values given.
    pub of: usize,
}

/// The robust average of the finite `values`: their median, the values
/// within `outlier_sigmas` robust deviations of it (the deviation at least
/// `min_sigma`), their mean and its standard deviation. None when no value
/// is finite.
pub fn robust_mean(values: &[f64], outlier_sigmas: f64, min_sigma: f64) -> Option<Robust> {
    let finite: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    let med = finite_median(&finite)?;
    let dev: Vec<f64> = finite.iter().map(|x| (x - med).abs()).collect();
    let mad = finite_median(&dev).unwrap_or(0.0) * 1.4826;
    let scale = mad.max(min_sigma.max(0.0));
    let kept: Vec<f64> = finite
        .iter()
        .copied()
        .filter(|x| (x - med).abs() <= outlier_sigmas * scale)
        .collect();
    // The median itself is always within the band: kept is not empty.
    let n = kept.len().max(1) as f64;
    let mean = kept.iter().sum::<f64>() / n;
    let var = if kept.len() > 1 {
        kept.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    let sd = var.sqrt().max(min_sigma.max(0.0));
    Some(Robust {
        mean,
        sigma: sd / n.sqrt(),
        kept: kept.len(),
        of: finite.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_median_and_the_robust_mean_ignore_an_outlier() {
        assert_eq!(robust_mean(&[], 3.0, 0.1), None);
        assert_eq!(robust_mean(&[f64::NAN, f64::INFINITY], 3.0, 0.1), None);
        // Four frames agree within a centimetre, one is 2 m off (a wrong
        // localisation): it is dropped, the mean is the four's.
        let r = robust_mean(&[1.00, 1.01, 0.99, 1.005, 3.0], 3.0, 0.001).unwrap();
        assert_eq!((r.kept, r.of), (4, 5));
        assert!((r.mean - 1.00125).abs() < 1e-9, "{r:?}");
        assert!(r.sigma > 0.0 && r.sigma < 0.01, "{r:?}");
        // The floor: identical values still have the floor's deviation,
        // over the square root of their count.
        let r = robust_mean(&[2.0; 4], 3.0, 0.1).unwrap();
        assert!((r.mean - 2.0).abs() < 1e-12);
        assert!((r.sigma - 0.05).abs() < 1e-12, "{r:?}");
        // Non-finite values are not counted.
        let r = robust_mean(&[f64::NAN, 5.0], 3.0, 0.1).unwrap();
        assert_eq!((r.kept, r.of), (1, 1));
        assert!(robust_mean(&[f64::INFINITY], 3.0, 0.1).is_none());
    }
}
