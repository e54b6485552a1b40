//! Measuring the extractor: timing over a folder of frames, and the
//! homography-warp evaluation (repeatability, matching precision and recall,
//! spread) shared by the tests, the benches and the peer comparison.

use std::path::{Path, PathBuf};
use std::time::Instant;

use image::GrayImage;
use nalgebra::{Matrix3, Vector3};
use rand::{Rng, SeedableRng, rngs::StdRng};

use crate::camera::Camera;
use crate::features::{Descriptor, FeatureError, Features, KeyPoint, OrbExtractor};
use crate::matching;
use crate::video::dataset::Dataset;

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

/// Every frame of a dataset folder (TUM or EuRoC layout, read by
/// [`crate::video::dataset::Dataset`]), as gray images, in order.
pub fn load_dataset_gray(dir: &Path) -> Result<Vec<GrayImage>, EvalError> {
    let ds = Dataset::open(dir).map_err(|e| EvalError::Format {
        path: dir.to_owned(),
        reason: e.to_string(),
    })?;
    ds.frames()
        .map(|f| {
            f.map(|f| f.image).map_err(|e| EvalError::Format {
                path: dir.to_owned(),
                reason: e.to_string(),
            })
        })
        .collect()
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

/// Time `extractor` on every frame (after `warmup` untimed extractions of
/// the first frame): milliseconds and keypoint count per frame.
pub fn time_frames(
    extractor: &mut OrbExtractor,
    frames: &[GrayImage],
    camera: Option<&Camera>,
    warmup: usize,
) -> Vec<(f64, usize)> {
    let mut feats = Features::default();
    if let Some(first) = frames.first() {
        for _ in 0..warmup {
            let _ = extractor.extract_into(first, None, camera, &mut feats);
        }
    }
    frames
        .iter()
        .map(|f| {
            let t = Instant::now();
            let _ = extractor.extract_into(f, None, camera, &mut feats);
            (t.elapsed().as_secs_f64() * 1e3, feats.len())
        })
        .collect()
}

/// Median, 95th percentile and mean keypoints of per-frame timings.
pub fn summarize(timings: &[(f64, usize)]) -> TimingReport {
    let ms: Vec<f64> = timings.iter().map(|t| t.0).collect();
    let kps: usize = timings.iter().map(|t| t.1).sum();
    TimingReport {
        frames: timings.len(),
        median_ms: crate::stats::median(&ms).unwrap_or(0.0),
        p95_ms: crate::stats::quantile(&ms, 0.95).unwrap_or(0.0),
        mean_keypoints: if timings.is_empty() {
            0.0
        } else {
            kps as f64 / timings.len() as f64
        },
    }
}

/// [`time_frames`] without a camera, summarized.
pub fn time_extraction(
    extractor: &mut OrbExtractor,
    frames: &[GrayImage],
    warmup: usize,
) -> TimingReport {
    summarize(&time_frames(extractor, frames, None, warmup))
}

/// One synthetic view change: a homography about the image centre.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct WarpSpec {
    /// In-plane rotation, degrees.
    pub rotation_deg: f64,
    /// Zoom (> 1 enlarges).
    pub scale: f64,
    /// Perspective terms `(h31, h32)` in centred pixel coordinates.
    pub perspective: (f64, f64),
    /// Shift, pixels.
    pub translation: (f64, f64),
    /// Standard deviation of the added Gaussian noise, gray levels.
    pub noise_sigma: f64,
}

/// Ranges the evaluation draws its warps from.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WarpParams {
    /// Largest rotation, degrees (drawn in `[0, max]`, either sign).
    pub max_rotation_deg: f64,
    /// Smallest zoom.
    pub min_scale: f64,
    /// Largest zoom.
    pub max_scale: f64,
    /// Largest `|h31|`, `|h32|`.
    pub max_perspective: f64,
    /// Largest shift, pixels.
    pub max_translation: f64,
    /// Noise standard deviation, gray levels.
    pub noise_sigma: f64,
    /// Distance within which a keypoint counts as the same point, pixels.
    pub match_radius: f64,
    /// Cells of the spread measure, across and down.
    pub spread_cells: (usize, usize),
}

impl Default for WarpParams {
    fn default() -> Self {
        WarpParams {
            max_rotation_deg: 45.0,
            min_scale: 0.6,
            max_scale: 1.6,
            max_perspective: 2e-4,
            max_translation: 20.0,
            noise_sigma: 3.0,
            match_radius: 3.0,
            spread_cells: (16, 12),
        }
    }
}

/// Draw `n` warps with `seed`: rotations spread evenly over `[0, max]` with
/// random sign, zooms log-uniform in `[min, max]`, the rest uniform.
pub fn draw_warps(n: usize, params: &WarpParams, seed: u64) -> Vec<WarpSpec> {
    let mut rng = StdRng::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let frac = if n > 1 {
                i as f64 / (n - 1) as f64
            } else {
                0.5
            };
            let sign = if rng.random::<bool>() { 1.0 } else { -1.0 };
            let ls = rng.random_range(params.min_scale.ln()..=params.max_scale.ln());
            let p = params.max_perspective;
            let t = params.max_translation;
            WarpSpec {
                rotation_deg: sign * frac * params.max_rotation_deg,
                scale: ls.exp(),
                perspective: (rng.random_range(-p..=p), rng.random_range(-p..=p)),
                translation: (rng.random_range(-t..=t), rng.random_range(-t..=t)),
                noise_sigma: params.noise_sigma,
            }
        })
        .collect()
}

/// The homography of `spec` for a `w` x `h` image: pixel `a` of the source
/// goes to `H a` of the warped image.
pub fn homography(spec: &WarpSpec, w: u32, h: u32) -> Matrix3<f64> {
    let (cx, cy) = ((w as f64 - 1.0) / 2.0, (h as f64 - 1.0) / 2.0);
    let (s, c) = spec.rotation_deg.to_radians().sin_cos();
    let k = spec.scale;
    let to_centre = Matrix3::new(1.0, 0.0, -cx, 0.0, 1.0, -cy, 0.0, 0.0, 1.0);
    let rot_scale = Matrix3::new(k * c, -k * s, 0.0, k * s, k * c, 0.0, 0.0, 0.0, 1.0);
    let persp = Matrix3::new(
        1.0,
        0.0,
        0.0,
        0.0,
        1.0,
        0.0,
        spec.perspective.0,
        spec.perspective.1,
        1.0,
    );
    let back = Matrix3::new(
        1.0,
        0.0,
        cx + spec.translation.0,
        0.0,
        1.0,
        cy + spec.translation.1,
        0.0,
        0.0,
        1.0,
    );
    back * persp * rot_scale * to_centre
}

/// Apply a homography to a pixel; `None` at infinity.
pub fn apply(h: &Matrix3<f64>, x: f64, y: f64) -> Option<(f64, f64)> {
    let p = h * Vector3::new(x, y, 1.0);
    if p.z.abs() < 1e-12 {
        return None;
    }
    Some((p.x / p.z, p.y / p.z))
}

/// Warp `src` by `h` (bilinear, destination of the same size), add seeded
/// Gaussian noise; returns the image and its mask (255 where the source
/// covers the pixel, 0 on the black fill).
pub fn warp_image(
    src: &GrayImage,
    h: &Matrix3<f64>,
    noise_sigma: f64,
    seed: u64,
) -> (GrayImage, GrayImage) {
    let (w, ht) = src.dimensions();
    let mut out = GrayImage::new(w, ht);
    let mut mask = GrayImage::new(w, ht);
    let Some(inv) = h.try_inverse() else {
        return (out, mask);
    };
    let mut rng = StdRng::seed_from_u64(seed);
    let raw = src.as_raw();
    let (wu, hu) = (w as usize, ht as usize);
    for v in 0..ht {
        for u in 0..w {
            let Some((x, y)) = apply(&inv, u as f64, v as f64) else {
                continue;
            };
            if !(x >= 0.0 && y >= 0.0 && x <= (wu - 1) as f64 && y <= (hu - 1) as f64) {
                continue;
            }
            let (x0, y0) = (x.floor() as usize, y.floor() as usize);
            let (x1, y1) = ((x0 + 1).min(wu - 1), (y0 + 1).min(hu - 1));
            let (fx, fy) = (x - x0 as f64, y - y0 as f64);
            let p = |xx: usize, yy: usize| raw[yy * wu + xx] as f64;
            let val = (1.0 - fy) * ((1.0 - fx) * p(x0, y0) + fx * p(x1, y0))
                + fy * ((1.0 - fx) * p(x0, y1) + fx * p(x1, y1));
            // Box-Muller.
            let u1: f64 = rng.random_range(f64::EPSILON..1.0);
            let u2: f64 = rng.random();
            let n = (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos();
            out.put_pixel(
                u,
                v,
                image::Luma([(val + noise_sigma * n).round().clamp(0.0, 255.0) as u8]),
            );
            mask.put_pixel(u, v, image::Luma([255]));
        }
    }
    (out, mask)
}

/// One evaluation pair: a frame, its warped copy and the homography.
#[derive(Debug, Clone)]
pub struct WarpPair {
    /// The original frame.
    pub a: GrayImage,
    /// The warped, noisy frame.
    pub b: GrayImage,
    /// 255 where `b` shows the frame, 0 on the fill.
    pub mask_b: GrayImage,
    /// `b = H a`.
    pub h_ab: Matrix3<f64>,
    /// What was drawn.
    pub spec: WarpSpec,
}

/// Make `warps_per_frame` pairs from every frame of `frames` (seeded).
pub fn make_pairs(
    frames: &[GrayImage],
    warps_per_frame: usize,
    params: &WarpParams,
    seed: u64,
) -> Vec<WarpPair> {
    let specs = draw_warps(frames.len() * warps_per_frame, params, seed);
    let mut pairs = Vec::with_capacity(specs.len());
    for (i, spec) in specs.iter().enumerate() {
        let a = &frames[i % frames.len().max(1)];
        let h = homography(spec, a.width(), a.height());
        let (b, mask_b) = warp_image(a, &h, spec.noise_sigma, seed ^ (i as u64 + 1));
        pairs.push(WarpPair {
            a: a.clone(),
            b,
            mask_b,
            h_ab: h,
            spec: *spec,
        });
    }
    pairs
}

/// Write pairs as `a_NNN.png`, `b_NNN.png`, `mask_NNN.png` and `pairs.json`
/// (`[{"a", "b", "mask", "h": [row-major 9], "spec"}]`), for peers.
pub fn write_pairs(dir: &Path, pairs: &[WarpPair]) -> Result<(), EvalError> {
    std::fs::create_dir_all(dir).map_err(|source| EvalError::Io {
        path: dir.to_owned(),
        source,
    })?;
    let mut index = Vec::new();
    for (i, p) in pairs.iter().enumerate() {
        let names = [
            format!("a_{i:03}.png"),
            format!("b_{i:03}.png"),
            format!("mask_{i:03}.png"),
        ];
        for (name, img) in names.iter().zip([&p.a, &p.b, &p.mask_b]) {
            let path = dir.join(name);
            img.save(&path)
                .map_err(|source| EvalError::Image { path, source })?;
        }
        let h: Vec<f64> = (0..9).map(|k| p.h_ab[(k / 3, k % 3)]).collect();
        index.push(serde_json::json!({
            "a": names[0], "b": names[1], "mask": names[2], "h": h, "spec": p.spec,
        }));
    }
    let path = dir.join("pairs.json");
    let text = serde_json::to_string_pretty(&index).map_err(|e| EvalError::Format {
        path: path.clone(),
        reason: e.to_string(),
    })?;
    std::fs::write(&path, text).map_err(|source| EvalError::Io { path, source })
}

/// Figures of one pair (or their mean over pairs).
#[derive(Debug, Clone, Copy, PartialEq, Default, serde::Serialize)]
pub struct PairMetrics {
    /// Keypoints in image a / b.
    pub n_a: f64,
    /// Keypoints in image b.
    pub n_b: f64,
    /// Share of the keypoints seen by both images that have a counterpart
    /// within the radius (`min(rep_a, rep_b) / min(n_a', n_b')`).
    pub repeatability: f64,
    /// Correct matches / matches (mutual nearest, ratio 0.8, distance <= 64).
    pub precision: f64,
    /// Correct matches / keypoints of a with a counterpart in b.
    pub recall: f64,
    /// Share of the 16 x 12 cells holding a keypoint, mean of a and b.
    pub spread: f64,
}

fn spread(kps: &[KeyPoint], w: u32, h: u32, (cols, rows): (usize, usize)) -> f64 {
    if cols == 0 || rows == 0 {
        return 0.0;
    }
    let mut occ = vec![false; cols * rows];
    for k in kps {
        let cx = (k.x as f64 * cols as f64 / w as f64).floor();
        let cy = (k.y as f64 * rows as f64 / h as f64).floor();
        if cx >= 0.0 && cy >= 0.0 && (cx as usize) < cols && (cy as usize) < rows {
            occ[cy as usize * cols + cx as usize] = true;
        }
    }
    occ.iter().filter(|&&o| o).count() as f64 / occ.len() as f64
}

/// Measure one pair's features against the true homography.
pub fn evaluate_pair(
    pair: &WarpPair,
    fa: (&[KeyPoint], &[Descriptor]),
    fb: (&[KeyPoint], &[Descriptor]),
    params: &WarpParams,
) -> PairMetrics {
    let (w, h) = pair.a.dimensions();
    let r2 = params.match_radius * params.match_radius;
    let Some(h_ba) = pair.h_ab.try_inverse() else {
        return PairMetrics::default();
    };
    let in_b = |x: f64, y: f64| -> bool {
        x >= 0.0
            && y >= 0.0
            && x < w as f64
            && y < h as f64
            && pair.mask_b.get_pixel(x as u32, y as u32)[0] != 0
    };
    // a's keypoints seen in b, mapped; b's keypoints seen in a.
    let a_in: Vec<(usize, (f64, f64))> =
        fa.0.iter()
            .enumerate()
            .filter_map(|(i, k)| apply(&pair.h_ab, k.x as f64, k.y as f64).map(|p| (i, p)))
            .filter(|(_, (x, y))| in_b(*x, *y))
            .collect();
    let b_in: Vec<usize> = (0..fb.0.len())
        .filter(|&j| {
            let k = &fb.0[j];
            apply(&h_ba, k.x as f64, k.y as f64)
                .is_some_and(|(x, y)| x >= 0.0 && y >= 0.0 && x < w as f64 && y < h as f64)
        })
        .collect();
    let near = |(x, y): (f64, f64), k: &KeyPoint| {
        let (dx, dy) = (k.x as f64 - x, k.y as f64 - y);
        dx * dx + dy * dy <= r2
    };
    let rep_a = a_in
        .iter()
        .filter(|(_, p)| b_in.iter().any(|&j| near(*p, &fb.0[j])))
        .count();
    let rep_b = b_in
        .iter()
        .filter(|&&j| a_in.iter().any(|(_, p)| near(*p, &fb.0[j])))
        .count();
    let denom = a_in.len().min(b_in.len());
    let repeatability = if denom == 0 {
        0.0
    } else {
        rep_a.min(rep_b) as f64 / denom as f64
    };
    let mp = matching::Params {
        max_distance: 64,
        ratio: 0.8,
        cross_check: true,
    };
    let matches = matching::match_brute_force(fa.1, fb.1, &mp).unwrap_or_default();
    let correct = matches
        .iter()
        .filter(|m| {
            let (ka, kb) = (&fa.0[m.query], &fb.0[m.train]);
            apply(&pair.h_ab, ka.x as f64, ka.y as f64).is_some_and(|p| near(p, kb))
        })
        .count();
    PairMetrics {
        n_a: fa.0.len() as f64,
        n_b: fb.0.len() as f64,
        repeatability,
        precision: if matches.is_empty() {
            0.0
        } else {
            correct as f64 / matches.len() as f64
        },
        recall: if rep_a == 0 {
            0.0
        } else {
            correct as f64 / rep_a as f64
        },
        spread: 0.5
            * (spread(fa.0, w, h, params.spread_cells) + spread(fb.0, w, h, params.spread_cells)),
    }
}

/// Mean of per-pair figures.
pub fn mean_metrics(all: &[PairMetrics]) -> PairMetrics {
    let n = all.len().max(1) as f64;
    let mut m = PairMetrics::default();
    for p in all {
        m.n_a += p.n_a / n;
        m.n_b += p.n_b / n;
        m.repeatability += p.repeatability / n;
        m.precision += p.precision / n;
        m.recall += p.recall / n;
        m.spread += p.spread / n;
    }
    m
}

/// Run `extractor` on every pair (b with its mask) and measure.
pub fn evaluate_extractor(
    extractor: &mut OrbExtractor,
    pairs: &[WarpPair],
    params: &WarpParams,
) -> Result<Vec<PairMetrics>, FeatureError> {
    let mut out = Vec::with_capacity(pairs.len());
    for p in pairs {
        let fa = extractor.extract(&p.a, None);
        let fb = extractor.extract_masked(&p.b, &p.mask_b, None)?;
        out.push(evaluate_pair(
            p,
            (&fa.keypoints, &fa.descriptors),
            (&fb.keypoints, &fb.descriptors),
            params,
        ));
    }
    Ok(out)
}

/// Features computed by a peer, read from the JSON its script writes:
/// `[{"a": {"kps": [[x, y, angle, octave, response, size], ..], "desc": ["hex64", ..]}, "b": {..}}]`.
pub fn read_peer_features(path: &Path) -> Result<Vec<(Features, Features)>, EvalError> {
    let text = std::fs::read_to_string(path).map_err(|source| EvalError::Io {
        path: path.to_owned(),
        source,
    })?;
    let bad = |reason: String| EvalError::Format {
        path: path.to_owned(),
        reason,
    };
    let v: serde_json::Value = serde_json::from_str(&text).map_err(|e| bad(e.to_string()))?;
    let arr = v.as_array().ok_or_else(|| bad("not a list".into()))?;
    let side = |s: &serde_json::Value| -> Result<Features, EvalError> {
        let kps = s["kps"]
            .as_array()
            .ok_or_else(|| bad("kps missing".into()))?;
        let desc = s["desc"]
            .as_array()
            .ok_or_else(|| bad("desc missing".into()))?;
        if kps.len() != desc.len() {
            return Err(bad("kps and desc differ in length".into()));
        }
        let mut f = Features::default();
        for (k, d) in kps.iter().zip(desc) {
            let n: Vec<f64> = k
                .as_array()
                .ok_or_else(|| bad("keypoint not a list".into()))?
                .iter()
                .map(|x| x.as_f64().unwrap_or(f64::NAN))
                .collect();
            if n.len() != 6 || n.iter().any(|x| !x.is_finite()) {
                return Err(bad(format!("bad keypoint {k}")));
            }
            let (x, y) = (n[0] as f32, n[1] as f32);
            f.keypoints.push(KeyPoint {
                x,
                y,
                ux: x,
                uy: y,
                angle: n[2] as f32,
                octave: n[3] as u8,
                response: n[4] as f32,
                size: n[5] as f32,
            });
            let hex = d
                .as_str()
                .ok_or_else(|| bad("descriptor not a string".into()))?;
            f.descriptors.push(
                parse_hex_descriptor(hex).ok_or_else(|| bad(format!("bad descriptor {hex}")))?,
            );
        }
        Ok(f)
    };
    arr.iter()
        .map(|p| Ok((side(&p["a"])?, side(&p["b"])?)))
        .collect()
}

/// Parse 32 bytes of hex (OpenCV's byte order: byte `i` holds tests
/// `8 i .. 8 i + 7`, lowest bit first) into a [`Descriptor`].
pub fn parse_hex_descriptor(hex: &str) -> Option<Descriptor> {
    if hex.len() != 64 || !hex.is_ascii() {
        return None;
    }
    let mut d: Descriptor = [0; 4];
    for i in 0..32 {
        let byte = u8::from_str_radix(&hex[2 * i..2 * i + 2], 16).ok()?;
        d[i / 8] |= (byte as u64) << (8 * (i % 8));
    }
    Some(d)
}
