//! ORB features as ORB-SLAM extracts them.
//!
//! The extractor ([`OrbExtractor`]) builds an image pyramid (default 8 levels,
//! scale 1.2), detects FAST-9 corners per level in 30-pixel cells (threshold 24,
//! falling back to a lower one, 5 times the image's noise deviation but at
//! least 7, in cells where 24 finds nothing), gives each level a share
//! of the wanted features in geometric proportion, spreads each level's corners
//! with ORB-SLAM's quadtree (the strongest corner per node), orients each
//! keypoint by the intensity centroid of a circular patch of radius 15 and
//! describes it with steered BRIEF (the learned 256-pair ORB pattern) on the
//! level blurred by a 7x7 Gaussian of sigma 2. Keypoints are reported in level-0
//! pixels, with their undistorted position when a camera model is given.
//!
//! | module | what |
//! |---|---|
//! | [`pyramid`] | bilinear downscaling between pyramid levels |
//! | [`fast`] | FAST-9 detection with score and 3x3 non-maximum suppression |
//! | [`quadtree`] | ORB-SLAM's quadtree distribution |
//! | [`noise`] | noise level, for the noise-adaptive fallback threshold |
//! | [`orientation`] | intensity-centroid angle |
//! | [`brief`] | Gaussian blur and steered BRIEF |
//! | [`pattern`] | the learned ORB test pattern |
//! | [`extractor`] | [`OrbExtractor`], putting it together (optionally on 2 threads) |
//!
//! Its homography-warp evaluation (repeatability, matching, spread) is
//! [`crate::features_eval`], above both this module and [`crate::matching`].

pub mod brief;
pub mod extractor;
pub mod fast;
pub mod noise;
pub mod orientation;
pub mod pattern;
pub mod pyramid;
pub mod quadtree;

pub use extractor::OrbExtractor;

/// A 256-bit binary descriptor; bit `i` is the result of pattern test `i`
/// (word `i / 64`, bit `i % 64`).
pub type Descriptor = [u64; 4];

/// Hamming distance between two descriptors (number of differing bits).
///
/// Uses the CPU's popcount instruction: directly when the build targets it,
/// else after a (cached) runtime check. Loops over many pairs are faster
/// still inside a function compiled for it, as
/// [`crate::matching::match_brute_force_into`] does.
#[inline]
pub fn hamming(a: &Descriptor, b: &Descriptor) -> u32 {
    #[cfg(all(target_arch = "x86_64", not(target_feature = "popcnt")))]
    {
        if std::arch::is_x86_feature_detected!("popcnt") {
            // SAFETY: the CPU has POPCNT, checked just above.
            return unsafe { hamming_popcnt(a, b) };
        }
    }
    hamming_portable(a, b)
}

#[cfg(all(target_arch = "x86_64", not(target_feature = "popcnt")))]
#[target_feature(enable = "popcnt")]
fn hamming_popcnt(a: &Descriptor, b: &Descriptor) -> u32 {
    hamming_portable(a, b)
}

/// [`hamming`] as plain Rust (`count_ones`), inlined into callers compiled
/// for the CPU.
#[inline(always)]
pub fn hamming_portable(a: &Descriptor, b: &Descriptor) -> u32 {
    (a[0] ^ b[0]).count_ones()
        + (a[1] ^ b[1]).count_ones()
        + (a[2] ^ b[2]).count_ones()
        + (a[3] ^ b[3]).count_ones()
}

/// A detected keypoint.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct KeyPoint {
    /// Column in level-0 pixels, as detected (distorted image).
    pub x: f32,
    /// Row in level-0 pixels, as detected (distorted image).
    pub y: f32,
    /// Undistorted column (camera model); equals `x` without a camera.
    pub ux: f32,
    /// Undistorted row (camera model); equals `y` without a camera.
    pub uy: f32,
    /// Pyramid level the keypoint was detected on (0 = full resolution).
    pub octave: u8,
    /// Orientation in degrees, `[0, 360)`, measured from +x towards +y (down).
    pub angle: f32,
    /// Diameter of the described patch in level-0 pixels.
    pub size: f32,
    /// FAST score: the largest threshold at which the point is still a corner.
    pub response: f32,
}

/// Keypoints and their descriptors, index for index.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Features {
    /// The keypoints, grouped by octave (level 0 first).
    pub keypoints: Vec<KeyPoint>,
    /// One descriptor per keypoint.
    pub descriptors: Vec<Descriptor>,
}

impl Features {
    /// Number of features.
    pub fn len(&self) -> usize {
        self.keypoints.len()
    }

    /// True when there are no features.
    pub fn is_empty(&self) -> bool {
        self.keypoints.is_empty()
    }
}

/// Every tunable number of the extractor.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Features wanted per image (over all levels).
    pub n_features: usize,
    /// Scale between consecutive pyramid levels (> 1).
    pub scale_factor: f32,
    /// Number of pyramid levels (1..=32).
    pub n_levels: usize,
    /// FAST threshold tried first in every cell.
    pub ini_th_fast: u8,
    /// FAST threshold used in cells where `ini_th_fast` finds no corner.
    pub min_th_fast: u8,
    /// Side of the detection cells, level pixels.
    pub cell_size: usize,
    /// Margin (level pixels) kept free of keypoints at the image border; at
    /// least 19 so that the rotated descriptor pattern stays inside the level.
    pub edge_threshold: usize,
    /// Diameter of the orientation patch (odd, 7..=31); the descriptor pattern
    /// is the learned one for 31.
    pub patch_size: usize,
    /// How the features are shared among levels: level `l` gets a share
    /// proportional to `scale_factor^(-level_weight_exponent * l)`. 2 shares by
    /// the level's area; 1 is ORB-SLAM's and OpenCV's choice (by side length).
    pub level_weight_exponent: f32,
    /// Worker threads for one image (1 or 2): levels are split among them.
    pub threads: usize,
    /// Noise-adaptive fallback threshold: the threshold used in cells where
    /// `ini_th_fast` finds nothing is `max(min_th_fast, k * noise)`, capped at
    /// `ini_th_fast`, with `noise` the image's estimated noise deviation
    /// ([`noise::estimate_noise_sigma`]); so noise does not turn flat cells
    /// into random corners. 0 disables (ORB-SLAM's fixed `min_th_fast`).
    pub noise_threshold_factor: f32,
    /// When true, the quadtree first spreads the corners found with
    /// `ini_th_fast` over the level's quota, and the fallback corners (cells
    /// where `ini_th_fast` found nothing) only fill what is left of it, with
    /// a quadtree of their own. When false, all corners share one quadtree
    /// (ORB-SLAM), which spreads more but lets weak, less repeatable fallback
    /// corners displace strong ones.
    pub fallback_fills_only: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            n_features: 1000,
            scale_factor: 1.2,
            n_levels: 8,
            ini_th_fast: 24,
            min_th_fast: 7,
            cell_size: 30,
            edge_threshold: 19,
            patch_size: 31,
            level_weight_exponent: 1.0,
            threads: 1,
            noise_threshold_factor: 5.0,
            fallback_fills_only: true,
        }
    }
}

/// Errors of the feature extractor.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FeatureError {
    /// A parameter is out of its range.
    #[error("invalid parameter {name} = {value}: {reason}")]
    InvalidParams {
        /// The parameter.
        name: &'static str,
        /// Its value, printed.
        value: String,
        /// The allowed range.
        reason: &'static str,
    },
    /// The mask does not have the image's size.
    #[error("mask is {mask_width}x{mask_height}, image is {width}x{height}")]
    MaskSize {
        /// Image width.
        width: u32,
        /// Image height.
        height: u32,
        /// Mask width.
        mask_width: u32,
        /// Mask height.
        mask_height: u32,
    },
}

impl Params {
    /// Check every number; the extractor refuses parameters that fail.
    pub fn validate(&self) -> Result<(), FeatureError> {
        let bad = |name, value: String, reason| {
            Err(FeatureError::InvalidParams {
                name,
                value,
                reason,
            })
        };
        if !(self.scale_factor > 1.0 && self.scale_factor <= 4.0) {
            return bad(
                "scale_factor",
                self.scale_factor.to_string(),
                "must be in (1, 4]",
            );
        }
        if self.n_levels == 0 || self.n_levels > 32 {
            return bad("n_levels", self.n_levels.to_string(), "must be in 1..=32");
        }
        if self.min_th_fast == 0 || self.min_th_fast > self.ini_th_fast {
            return bad(
                "min_th_fast",
                self.min_th_fast.to_string(),
                "must be in 1..=ini_th_fast",
            );
        }
        if self.cell_size < 8 || self.cell_size > 1024 {
            return bad(
                "cell_size",
                self.cell_size.to_string(),
                "must be in 8..=1024",
            );
        }
        if self.edge_threshold < 19 || self.edge_threshold > 256 {
            return bad(
                "edge_threshold",
                self.edge_threshold.to_string(),
                "must be in 19..=256",
            );
        }
        if self.patch_size < 7 || self.patch_size > 31 || self.patch_size.is_multiple_of(2) {
            return bad(
                "patch_size",
                self.patch_size.to_string(),
                "must be odd, in 7..=31",
            );
        }
        if !(0.0..=4.0).contains(&self.level_weight_exponent) {
            return bad(
                "level_weight_exponent",
                self.level_weight_exponent.to_string(),
                "must be in [0, 4]",
            );
        }
        if !(0.0..=50.0).contains(&self.noise_threshold_factor) {
            return bad(
                "noise_threshold_factor",
                self.noise_threshold_factor.to_string(),
                "must be in [0, 50]",
            );
        }
        if self.threads == 0 || self.threads > 2 {
            return bad("threads", self.threads.to_string(), "must be 1 or 2");
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hamming_counts_bits() {
        let a: Descriptor = [0, 0, 0, 0];
        let b: Descriptor = [1, 3, u64::MAX, 1 << 63];
        assert_eq!(hamming(&a, &b), 1 + 2 + 64 + 1);
        assert_eq!(hamming(&b, &b), 0);
    }

    #[test]
    fn params_validate() {
        assert!(Params::default().validate().is_ok());
        let p = Params {
            scale_factor: 1.0,
            ..Params::default()
        };
        assert!(matches!(
            p.validate(),
            Err(FeatureError::InvalidParams {
                name: "scale_factor",
                ..
            })
        ));
        let p = Params {
            threads: 3,
            ..Params::default()
        };
        assert!(p.validate().is_err());
    }
}
