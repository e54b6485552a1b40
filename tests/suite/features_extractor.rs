//! The ORB extractor on synthetic images whose answer is known: rotation
//! invariance of the descriptors, level-0 coordinates of every octave,
//! repeatable output, degenerate inputs, masks and undistortion.

use image::GrayImage;
use rand::{Rng, SeedableRng, rngs::StdRng};
use shotpilot::camera::{Camera, Distortion};
use shotpilot::features::{FeatureError, Features, OrbExtractor, Params, hamming};

/// Smooth random texture: random blobs of random brightness on a gradient.
fn texture(w: u32, h: u32, seed: u64) -> GrayImage {
    let mut rng = StdRng::seed_from_u64(seed);
    let mut f = vec![0f32; (w * h) as usize];
    for (i, v) in f.iter_mut().enumerate() {
        let (x, y) = ((i as u32 % w) as f32, (i as u32 / w) as f32);
        *v = 60.0 + 0.1 * x + 0.05 * y;
    }
    for _ in 0..900 {
        let (cx, cy) = (
            rng.random_range(0.0..w as f32),
            rng.random_range(0.0..h as f32),
        );
        let r = rng.random_range(2.0..14.0f32);
        let a = rng.random_range(-90.0..90.0f32);
        let (x0, x1) = ((cx - r).max(0.0) as u32, ((cx + r) as u32 + 1).min(w));
        let (y0, y1) = ((cy - r).max(0.0) as u32, ((cy + r) as u32 + 1).min(h));
        for y in y0..y1 {
            for x in x0..x1 {
                let d2 = (x as f32 - cx).powi(2) + (y as f32 - cy).powi(2);
                if d2 < r * r {
                    f[(y * w + x) as usize] += a * (1.0 - d2 / (r * r));
                }
            }
        }
    }
    GrayImage::from_fn(w, h, |x, y| {
        image::Luma([f[(y * w + x) as usize].clamp(0.0, 255.0) as u8])
    })
}

fn extractor(n: usize, threads: usize) -> OrbExtractor {
    OrbExtractor::new(Params {
        n_features: n,
        threads,
        ..Params::default()
    })
    .expect("default parameters are valid")
}

/// Rotate a square image by 90 degrees clockwise: (x, y) -> (n - 1 - y, x).
fn rotate90(img: &GrayImage) -> GrayImage {
    let n = img.width();
    GrayImage::from_fn(n, n, |x, y| *img.get_pixel(y, n - 1 - x))
}

#[test]
fn rotated_image_gives_the_same_descriptors() {
    let img = texture(400, 400, 1);
    let rot = rotate90(&img);
    let mut ex = extractor(800, 1);
    let a = ex.extract(&img, None);
    let b = ex.extract(&rot, None);
    assert!(a.len() > 500, "{} features", a.len());
    let n = img.width() as f32;
    let (mut pairs, mut close, mut angle_ok) = (0, 0, 0);
    let mut dists = Vec::new();
    for (ka, da) in a.keypoints.iter().zip(&a.descriptors) {
        let (tx, ty) = (n - 1.0 - ka.y, ka.x);
        let Some((j, _)) = b
            .keypoints
            .iter()
            .enumerate()
            .filter(|(_, kb)| kb.octave == ka.octave)
            .map(|(j, kb)| (j, (kb.x - tx).powi(2) + (kb.y - ty).powi(2)))
            .filter(|&(_, d2)| d2 < 1.0)
            .min_by(|x, y| x.1.total_cmp(&y.1))
        else {
            continue;
        };
        pairs += 1;
        let d = hamming(da, &b.descriptors[j]);
        dists.push(d);
        if d <= 20 {
            close += 1;
        }
        let dang = (b.keypoints[j].angle - ka.angle - 90.0).rem_euclid(360.0);
        if dang.min(360.0 - dang) < 3.0 {
            angle_ok += 1;
        }
    }
    dists.sort_unstable();
    // The same corners are found (the pyramid is exactly rotation-equivariant
    // for a square image) ...
    assert!(
        pairs as f32 > 0.8 * a.len() as f32,
        "{pairs} of {} re-found",
        a.len()
    );
    // ... with the orientation turned by 90 degrees ...
    assert!(
        angle_ok as f32 > 0.9 * pairs as f32,
        "{angle_ok} of {pairs} angles"
    );
    // ... and descriptors within a few bits for most of them.
    assert!(
        close as f32 > 0.85 * pairs as f32,
        "{close} of {pairs} within 20 bits"
    );
    assert!(
        dists[dists.len() / 2] <= 6,
        "median distance {}",
        dists[dists.len() / 2]
    );
}

/// Bright 40 px squares on a dark background: every corner of every square
/// is a FAST corner at every level; the true corner lies half a pixel outside
/// the square's first pixel.
#[test]
fn octave_coordinates_map_to_level_zero() {
    let (w, h) = (640u32, 480u32);
    let mut squares = Vec::new();
    for gy in 0..5 {
        for gx in 0..7 {
            squares.push((40 + gx * 84 + (gy * 13) % 17, 30 + gy * 88 + (gx * 7) % 11));
        }
    }
    let img = GrayImage::from_fn(w, h, |x, y| {
        let inside = squares
            .iter()
            .any(|&(sx, sy)| x >= sx && x < sx + 40 && y >= sy && y < sy + 40);
        image::Luma([if inside { 200 } else { 30 }])
    });
    let mut corners = Vec::new();
    for &(sx, sy) in &squares {
        for (cx, cy) in [(sx, sy), (sx + 40, sy), (sx, sy + 40), (sx + 40, sy + 40)] {
            corners.push((cx as f32 - 0.5, cy as f32 - 0.5));
        }
    }
    let mut ex = extractor(2000, 1);
    let f = ex.extract(&img, None);
    let scales = ex.scale_factors().to_vec();
    let mut checked_levels = 0;
    for (l, &s) in scales.iter().enumerate() {
        let errs: Vec<(f32, f32)> = f
            .keypoints
            .iter()
            .filter(|k| k.octave as usize == l)
            .map(|k| {
                corners
                    .iter()
                    .map(|&(cx, cy)| (k.x - cx, k.y - cy))
                    .min_by(|a, b| (a.0.hypot(a.1)).total_cmp(&b.0.hypot(b.1)))
                    .unwrap_or((f32::MAX, f32::MAX))
            })
            .collect();
        if errs.len() < 20 {
            continue;
        }
        checked_levels += 1;
        let n = errs.len() as f32;
        let mean_dx = errs.iter().map(|e| e.0).sum::<f32>() / n;
        let mean_dy = errs.iter().map(|e| e.1).sum::<f32>() / n;
        let max = errs.iter().map(|e| e.0.hypot(e.1)).fold(0.0, f32::max);
        // Each keypoint lies within about one level pixel of a true corner,
        // and the offsets of the four corner kinds cancel: no scaling bias.
        eprintln!(
            "level {l}: {} keypoints, bias ({mean_dx:.2}, {mean_dy:.2}), max {max:.2}",
            errs.len()
        );
        assert!(max < 2.5 * s + 0.5, "level {l}: max error {max}");
        assert!(
            mean_dx.abs() < 0.3 * s && mean_dy.abs() < 0.3 * s,
            "level {l}: bias ({mean_dx}, {mean_dy})"
        );
        // The reported size is the patch diameter at that level.
        let k = f
            .keypoints
            .iter()
            .find(|k| k.octave as usize == l)
            .map(|k| k.size);
        assert_eq!(k, Some(31.0 * s));
    }
    assert!(
        checked_levels >= 6,
        "only {checked_levels} levels had corners"
    );
}

#[test]
fn identical_input_gives_identical_output() {
    let img = texture(640, 480, 2);
    let mut one = extractor(1000, 1);
    let a = one.extract(&img, None);
    let b = one.extract(&img, None);
    let c = extractor(1000, 1).extract(&img, None);
    let d = extractor(1000, 2).extract(&img, None);
    assert!(a.len() > 900);
    assert_eq!(a, b, "same extractor, same frame");
    assert_eq!(a, c, "fresh extractor");
    assert_eq!(a, d, "two threads give the one-thread result");
}

#[test]
fn degenerate_images_give_few_features_and_no_panic() {
    let mut ex = extractor(1000, 2);
    for (w, h, most) in [
        (0, 0, 0),
        (1, 1, 0),
        (7, 3, 0),
        (38, 38, 0),
        (40, 40, 2),
        (64, 64, 30),
    ] {
        let f = ex.extract(&texture(w.max(1), h.max(1), 3), None);
        assert!(f.len() <= most, "{w}x{h}: {}", f.len());
        let f = ex.extract(&GrayImage::new(w, h), None);
        assert!(f.is_empty());
    }
    let black = GrayImage::new(640, 480);
    let white = GrayImage::from_pixel(640, 480, image::Luma([255]));
    for img in [&black, &white] {
        let f = ex.extract(img, None);
        assert!(f.is_empty(), "{} features on a flat image", f.len());
    }
    // Flat image with one small square: only its few corners.
    let mut one = GrayImage::new(640, 480);
    for y in 200..230 {
        for x in 300..330 {
            one.put_pixel(x, y, image::Luma([255]));
        }
    }
    let f = ex.extract(&one, None);
    assert!(!f.is_empty() && f.len() <= 40, "{}", f.len());
    // Pure noise: features, no panic, within the budget.
    let mut rng = StdRng::seed_from_u64(4);
    let noise = GrayImage::from_fn(640, 480, |_, _| image::Luma([rng.random()]));
    let f = ex.extract(&noise, None);
    assert!(f.len() > 500 && f.len() <= 1010, "{}", f.len());
}

#[test]
fn masked_pixels_never_yield_features() {
    let img = texture(640, 480, 5);
    // Black fill on the right third, as around a warped desired shot.
    let mut filled = img.clone();
    let mut mask = GrayImage::from_pixel(640, 480, image::Luma([255]));
    for y in 0..480 {
        for x in 420..640 {
            filled.put_pixel(x, y, image::Luma([0]));
            mask.put_pixel(x, y, image::Luma([0]));
        }
    }
    let mut ex = extractor(1000, 1);
    let f = ex
        .extract_masked(&filled, &mask, None)
        .expect("sizes agree");
    assert!(f.len() > 300, "{}", f.len());
    for k in &f.keypoints {
        // The whole patch (radius 15 level pixels, 18 with margin) stays left of the fill.
        let reach = 18.0 * ex.scale_factors()[k.octave as usize];
        assert!(
            k.x + reach < 420.5,
            "keypoint at {} octave {}",
            k.x,
            k.octave
        );
    }
    let small = GrayImage::new(10, 10);
    assert!(matches!(
        ex.extract_masked(&img, &small, None),
        Err(FeatureError::MaskSize { mask_width: 10, .. })
    ));
}

#[test]
fn undistorted_coordinates_follow_the_camera() {
    let img = texture(640, 480, 6);
    let cam = Camera::new(
        640,
        480,
        [500.0, 500.0, 320.0, 240.0],
        Distortion {
            k1: -0.2,
            k2: 0.05,
            p1: 0.001,
            p2: -0.001,
            k3: 0.0,
        },
    )
    .expect("valid camera");
    let mut ex = extractor(500, 1);
    let plain: Features = ex.extract(&img, None);
    let with_cam = ex.extract(&img, Some(&cam));
    assert_eq!(plain.len(), with_cam.len());
    for (p, c) in plain.keypoints.iter().zip(&with_cam.keypoints) {
        assert_eq!((p.x, p.y), (c.x, c.y));
        assert_eq!((p.ux, p.uy), (p.x, p.y));
        let want = cam.undistort_pixel(nalgebra::Point2::new(c.x as f64, c.y as f64));
        assert!((c.ux as f64 - want.x).abs() < 1e-3 && (c.uy as f64 - want.y).abs() < 1e-3);
        // Barrel distortion: undistorted points lie farther from the centre.
        let r_d = ((c.x - 320.0).powi(2) + (c.y - 240.0).powi(2)).sqrt();
        let r_u = ((c.ux - 320.0).powi(2) + (c.uy - 240.0).powi(2)).sqrt();
        assert!(r_u >= r_d - 1e-3);
    }
}

#[test]
fn invalid_parameters_are_refused() {
    for p in [
        Params {
            n_levels: 0,
            ..Params::default()
        },
        Params {
            edge_threshold: 10,
            ..Params::default()
        },
        Params {
            min_th_fast: 30,
            ..Params::default()
        },
    ] {
        assert!(matches!(
            OrbExtractor::new(p),
            Err(FeatureError::InvalidParams { .. })
        ));
    }
}
