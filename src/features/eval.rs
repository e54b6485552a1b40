//! Measuring the extractor: timing over a folder of frames, and the
//! homography-warp evaluation (repeatability, matching precision and recall,
//! spread) shared by the tests, the benches and the peer comparison.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::GrayImage;

use super::{Features, OrbExtractor};

/// Errors of the evaluation helpers.
#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    /// A file could not be read or written.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// An image could not be decoded or encoded.
    #[error("{path}: {source}")]
    Image {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: image::ImageError,
    },
    /// A file does not hold what it should.
    #[error("{path}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// Convert RGB to gray with the weights OpenCV's `cvtColor(.., RGB2GRAY)`
/// uses (0.299, 0.587, 0.114), rounded.
pub fn rgb_to_gray(img: &image::RgbImage) -> GrayImage {
    let (w, h) = img.dimensions();
    let mut out = GrayImage::new(w, h);
    for (o, p) in out.iter_mut().zip(img.as_raw().chunks_exact(3)) {
        let v = 4899 * p[0] as u32 + 9617 * p[1] as u32 + 1868 * p[2] as u32;
        *o = ((v + 8192) >> 14) as u8;
    }
    out
}

/// Read an image file as gray (color images converted with [`rgb_to_gray`]).
pub fn load_gray(path: &Path) -> Result<GrayImage, EvalError> {
    let img = image::open(path).map_err(|source| EvalError::Image {
        path: path.to_owned(),
        source,
    })?;
    Ok(match img {
        image::DynamicImage::ImageLuma8(g) => g,
        other => rgb_to_gray(&other.to_rgb8()),
    })
}

/// The image paths listed by a TUM-layout folder's `rgb.txt`, in order.
pub fn tum_image_paths(dir: &Path) -> Result<Vec<PathBuf>, EvalError> {
    let list = dir.join("rgb.txt");
    let text = std::fs::read_to_string(&list).map_err(|source| EvalError::Io {
        path: list.clone(),
        source,
    })?;
    let paths: Vec<PathBuf> = text
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty() && !l.starts_with('#'))
        .filter_map(|l| l.split_whitespace().nth(1))
        .map(|rel| dir.join(rel))
        .collect();
    if paths.is_empty() {
        return Err(EvalError::Format {
            path: list,
            reason: "no image lines".into(),
        });
    }
    Ok(paths)
}

/// Every frame of a TUM-layout folder, as gray images.
pub fn load_tum_gray(dir: &Path) -> Result<Vec<GrayImage>, EvalError> {
    tum_image_paths(dir)?.iter().map(|p| load_gray(p)).collect()
}

/// Timing of extraction over a sequence of frames.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct TimingReport {
    /// Frames timed.
    pub frames: usize,
    /// Median milliseconds per frame.
    pub median_ms: f64,
    /// 95th percentile milliseconds per frame.
    pub p95_ms: f64,
    /// Mean keypoints per frame.
    pub mean_keypoints: f64,
}

/// Time `extractor` on every frame (after `warmup` untimed passes over the
/// first frame), one timing per frame.
pub fn time_extraction(
    extractor: &mut OrbExtractor,
    frames: &[GrayImage],
    warmup: usize,
) -> TimingReport {
    let mut feats = Features::default();
    if let Some(first) = frames.first() {
        for _ in 0..warmup {
            let _ = extractor.extract_into(first, None, None, &mut feats);
        }
    }
    let mut ms = Vec::with_capacity(frames.len());
    let mut kps = 0usize;
    for f in frames {
        let t = Instant::now();
        let _ = extractor.extract_into(f, None, None, &mut feats);
        ms.push(t.elapsed().as_secs_f64() * 1e3);
        kps += feats.len();
    }
    ms.sort_by(f64::total_cmp);
    let pick = |q: f64| -> f64 {
        if ms.is_empty() {
            return 0.0;
        }
        let i = ((ms.len() - 1) as f64 * q).round() as usize;
        ms[i.min(ms.len() - 1)]
    };
    TimingReport {
        frames: frames.len(),
        median_ms: pick(0.5),
        p95_ms: pick(0.95),
        mean_keypoints: if frames.is_empty() {
            0.0
        } else {
            kps as f64 / frames.len() as f64
        },
    }
}
