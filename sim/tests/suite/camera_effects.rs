//! Every camera effect of the realism presets, measured in renders: motion
//! blur length against speed x exposure / ground sampling distance,
//! rolling-shutter skew against the readout time, the auto-exposure's lag
//! and clipping, noise variance against brightness, vignetting falloff,
//! compression artefacts, cloud shadows drifting with their wind, and the
//! ground truth of a rolling-shutter frame reproducing where a marker is.

use std::sync::Arc;

use image::GrayImage;
use nalgebra::{Isometry3, Point2, Point3};
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::imaging::{Imager, interpolate_knots};
use shotpilot_sim::paths::camera_from_yaw_pitch;
use shotpilot_sim::realism::{
    AutoExposure, CameraRealism, Compression, LightingRealism, MotionBlur, Realism, RollingShutter,
    SensorNoise, Vignetting,
};
use shotpilot_sim::render::{CloudShadows, RenderParams, Renderer};
use shotpilot_sim::world::{World, WorldParams};

/// A flat world: a uniform square of `bg` 120 m across at home, no
/// buildings, no detail texture.
fn flat_world(bg: f32) -> World {
    let params = WorldParams {
        ground_texture_size: 2048,
        ground_extent_m: 128.0,
        detail_gain_a: 0.0,
        detail_gain_b: 0.0,
        detail_gain_close: 0.0,
        building_count: 0,
        object_count: 0,
        ..WorldParams::tiny()
    };
    let mut w = World::generate_with(11, &params).unwrap();
    w.paint_ground_rect(0.0, 0.0, 60.0, 60.0, bg);
    w
}

fn renderer(world: World) -> Arc<Renderer> {
    Arc::new(Renderer::new(
        Arc::new(world),
        SimCamera::default(),
        RenderParams {
            noise_sigma: 0.0,
            ..RenderParams::default()
        },
    ))
}

/// Every camera effect off, linear tone curve (so grey levels are signal).
fn plain_camera() -> CameraRealism {
    let mut c = Realism::ideal().camera;
    c.photometry.display_gamma = 1.0;
    c
}

fn no_light() -> LightingRealism {
    Realism::ideal().lighting
}

/// Straight down from `altitude` over ground point (x, y) (image x east, image y south).
fn down(x: f64, y: f64, altitude: f64) -> Isometry3<f64> {
    camera_from_yaw_pitch(Point3::new(x, y, -altitude), 0.0, 90f64.to_radians())
}

fn f() -> f64 {
    SimCamera::default().fx
}

/// Intensity-weighted variance of the bright blob along image y, over a
/// window around the image centre, its background (the median of the
/// window's border) subtracted.
fn y_variance(img: &GrayImage, half: u32) -> f64 {
    let (cx, cy) = (img.width() / 2, img.height() / 2);
    let mut border: Vec<u8> = (cx - half..cx + half)
        .flat_map(|x| {
            [
                img.get_pixel(x, cy - half).0[0],
                img.get_pixel(x, cy + half).0[0],
            ]
        })
        .collect();
    border.sort_unstable();
    let bg = border[border.len() / 2] as f64;
    let (mut w, mut m1, mut m2) = (0.0, 0.0, 0.0);
    for y in cy - half..cy + half {
        for x in cx - half..cx + half {
            let v = (img.get_pixel(x, y).0[0] as f64 - bg).max(0.0);
            w += v;
            m1 += v * y as f64;
            m2 += v * (y as f64) * (y as f64);
        }
    }
    let mean = m1 / w;
    m2 / w - mean * mean
}

#[test]
fn motion_blur_length_is_speed_times_exposure_over_the_ground_sampling_distance() {
    let mut world = flat_world(40.0);
    world.paint_ground_marker(0.0, 0.0, 0.3, 230.0, 5.0, 40.0);
    let r = renderer(world);
    let (altitude, exposure) = (20.0, 0.02);
    for speed in [6.0, 15.0] {
        // Flying north: the ground moves down the image (+y).
        let pose_at = move |t: f64| down(speed * t, 0.0, altitude);
        let mut cam = plain_camera();
        cam.photometry.fixed_exposure_s = exposure;
        let mut sharp = Imager::new(r.clone(), cam.clone(), &no_light());
        cam.blur = Some(MotionBlur {
            max_px_per_sample: 0.25,
            max_samples: 64,
        });
        let mut blurred = Imager::new(r.clone(), cam, &no_light());
        let a = sharp.capture(0.0, &pose_at, None).unwrap();
        let b = blurred.capture(0.0, &pose_at, None).unwrap();
        assert!(b.blur_samples > 4, "{} samples", b.blur_samples);
        // A box kernel of length L adds L^2 / 12 to the variance.
        let dv = y_variance(&b.image, 40) - y_variance(&a.image, 40);
        let measured = (12.0 * dv).sqrt();
        let expected = speed * exposure * f() / altitude;
        eprintln!("speed {speed} m/s: blur {measured:.2} px, expected {expected:.2} px");
        assert!(
            (measured / expected - 1.0).abs() < 0.1,
            "blur {measured} px, expected {expected} px"
        );
    }
}

/// Sub-pixel column where the row crosses `level` going right, first
/// crossing after `from`.
fn edge_in_row(img: &GrayImage, y: u32, level: f64, from: u32) -> Option<f64> {
    for x in from..img.width() - 1 {
        let (a, b) = (
            img.get_pixel(x, y).0[0] as f64,
            img.get_pixel(x + 1, y).0[0] as f64,
        );
        if a < level && b >= level {
            return Some(x as f64 + (level - a) / (b - a));
        }
    }
    None
}

#[test]
fn rolling_shutter_skews_a_vertical_edge_by_speed_times_readout() {
    let mut world = flat_world(40.0);
    // A north-south strip: a vertical band in the image.
    world.paint_ground_rect(0.0, 1.0, 40.0, 1.0, 220.0);
    let r = renderer(world);
    let (altitude, speed, readout) = (20.0, 10.0, 0.03);
    // Flying east: the ground moves left in the image (-x).
    let pose_at = move |t: f64| down(0.0, speed * t, altitude);
    let mut cam = plain_camera();
    cam.rolling_shutter = Some(RollingShutter { readout_s: readout });
    let mut imager = Imager::new(r, cam, &no_light());
    let shot = imager.capture(0.0, &pose_at, None).unwrap();
    // Fit the edge column against the row over the central rows.
    let (mut sy, mut sx, mut syy, mut sxy, mut n) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for y in (60..420).step_by(4) {
        let x = edge_in_row(&shot.image, y, 130.0, 200).expect("edge");
        sy += y as f64;
        sx += x;
        syy += (y * y) as f64;
        sxy += x * y as f64;
        n += 1.0;
    }
    let slope = (n * sxy - sx * sy) / (n * syy - sy * sy);
    let skew = slope * 479.0;
    // Row y is exposed later by readout * y / 479: the camera is further
    // east, so the strip appears further left.
    let expected = -speed * readout * f() / altitude;
    eprintln!("skew over the frame {skew:.2} px, expected {expected:.2} px");
    assert!(
        (skew / expected - 1.0).abs() < 0.1,
        "skew {skew}, expected {expected}"
    );
    assert_eq!(shot.readout_s, readout);
}

#[test]
fn auto_exposure_lags_a_brightness_step_with_its_time_constant_and_clips_meanwhile() {
    let mut world = flat_world(60.0);
    world.paint_ground_rect(0.0, 40.0, 15.0, 15.0, 200.0);
    world.paint_ground_rect(0.0, -40.0, 15.0, 15.0, 30.0);
    let r = renderer(world);
    let tau = 0.5;
    let mut cam = plain_camera();
    cam.auto_exposure = Some(AutoExposure {
        target: 0.18,
        tau_s: tau,
        min_exposure_s: 1e-5,
        max_exposure_s: 1.0,
        max_gain: 1.0,
    });
    let mut imager = Imager::new(r, cam, &no_light());
    let dt = 1.0 / 15.0;
    let mean = |img: &GrayImage| {
        let c = image::imageops::crop_imm(img, 220, 140, 200, 200).to_image();
        c.as_raw().iter().map(|&v| v as f64).sum::<f64>() / c.as_raw().len() as f64 / 255.0
    };
    // Settle over the bright square, then cut to the dark one.
    let bright = |_t: f64| down(0.0, 40.0, 15.0);
    let dark = |_t: f64| down(0.0, -40.0, 15.0);
    for k in 0..60 {
        imager.capture(k as f64 * dt, &bright, None).unwrap();
    }
    let settled = mean(&imager.capture(60.0 * dt, &bright, None).unwrap().image);
    assert!((settled / 0.18 - 1.0).abs() < 0.05, "settled at {settled}");
    let mut log_gap = Vec::new();
    for k in 0..60 {
        let shot = imager.capture((61 + k) as f64 * dt, &dark, None).unwrap();
        log_gap.push((mean(&shot.image) / 0.18).ln());
    }
    // Just after the cut the frame is 200/30 too dark, then recovers
    // exponentially: the log gap halves in tau ln 2.
    assert!(log_gap[0] < -1.5, "first dark frame {}", log_gap[0]);
    let half = log_gap
        .iter()
        .position(|g| *g > log_gap[0] * 0.5)
        .expect("recovers");
    // Interpolate the crossing between frames.
    let (a, b) = (log_gap[half - 1], log_gap[half]);
    let frac = (log_gap[0] * 0.5 - a) / (b - a);
    let t_half = (half as f64 - 1.0 + frac) * dt;
    let tau_measured = t_half / std::f64::consts::LN_2;
    eprintln!("auto-exposure time constant {tau_measured:.3} s (set {tau} s)");
    assert!((tau_measured / tau - 1.0).abs() < 0.15, "{tau_measured}");
    assert!(log_gap[59].abs() < 0.05, "converged to {}", log_gap[59]);
    // Back to the bright square: the first frames clip to white.
    let shot = imager.capture(122.0 * dt, &bright, None).unwrap();
    let white = shot.image.as_raw().iter().filter(|&&v| v == 255).count() as f64
        / shot.image.as_raw().len() as f64;
    assert!(white > 0.9, "clipped share {white}");
    for k in 0..60 {
        imager
            .capture((123 + k) as f64 * dt, &bright, None)
            .unwrap();
    }
    let shot = imager.capture(190.0 * dt, &bright, None).unwrap();
    let white = shot.image.as_raw().iter().filter(|&&v| v == 255).count();
    assert_eq!(white, 0, "still clipping after settling");
}

#[test]
fn sensor_noise_variance_grows_with_brightness_as_shot_noise_plus_read_noise() {
    let levels = [25.0f32, 70.0, 120.0, 170.0, 220.0];
    let mut world = flat_world(0.0);
    for (k, &v) in levels.iter().enumerate() {
        world.paint_ground_rect(0.0, -40.0 + 20.0 * k as f64, 8.0, 8.0, v);
    }
    let r = renderer(world);
    let noise = SensorNoise {
        full_well_e: 1000.0,
        read_noise_e: 6.0,
        photosites_per_pixel: 1.0,
    };
    let mut cam = plain_camera();
    cam.noise = Some(noise);
    let mut imager = Imager::new(r, cam, &no_light());
    let fw = noise.pixel_full_well_e();
    let mut points = Vec::new();
    for (k, _) in levels.iter().enumerate() {
        let pose = down(0.0, -40.0 + 20.0 * k as f64, 10.0);
        let shot = imager.capture(0.0, &|_| pose, Some(77 + k as u64)).unwrap();
        let c = image::imageops::crop_imm(&shot.image, 220, 140, 200, 200).to_image();
        let n = c.as_raw().len() as f64;
        let mean = c.as_raw().iter().map(|&v| v as f64).sum::<f64>() / n;
        let var = c
            .as_raw()
            .iter()
            .map(|&v| (v as f64 - mean).powi(2))
            .sum::<f64>()
            / n;
        // Shot noise (variance = electrons) and read noise, in grey levels,
        // plus the 8-bit rounding's 1/12.
        let expected =
            255.0 * mean / fw + (255.0 * noise.pixel_read_noise_e() / fw).powi(2) + 1.0 / 12.0;
        eprintln!("mean {mean:.1}: variance {var:.2}, expected {expected:.2}");
        assert!((var / expected - 1.0).abs() < 0.1, "{var} vs {expected}");
        points.push((mean, var));
    }
    // Brighter is noisier in absolute terms.
    assert!(points.windows(2).all(|w| w[1].1 > w[0].1));
}

#[test]
fn vignetting_dims_the_corners_to_the_set_relative_illumination() {
    let r = renderer(flat_world(150.0));
    let pose = down(0.0, 0.0, 40.0);
    let plain = Imager::new(r.clone(), plain_camera(), &no_light())
        .capture(0.0, &|_| pose, None)
        .unwrap()
        .image;
    let mut cam = plain_camera();
    cam.vignetting = Some(Vignetting { corner: 0.6 });
    let vignetted = Imager::new(r, cam, &no_light())
        .capture(0.0, &|_| pose, None)
        .unwrap()
        .image;
    let ratio =
        |x: u32, y: u32| vignetted.get_pixel(x, y).0[0] as f64 / plain.get_pixel(x, y).0[0] as f64;
    for (x, y) in [(0, 0), (639, 0), (0, 479), (639, 479)] {
        let r = ratio(x, y);
        assert!((r - 0.6).abs() < 0.02, "corner ({x}, {y}): {r}");
    }
    assert!((ratio(320, 240) - 1.0).abs() < 0.01);
    // Monotone falloff along the diagonal.
    let along: Vec<f64> = (0..8).map(|k| ratio(320 + 40 * k, 240 + 30 * k)).collect();
    assert!(along.windows(2).all(|w| w[1] <= w[0] + 0.01), "{along:?}");
}

/// Mean absolute step across 8x8 block boundaries over the mean step
/// inside blocks (1 for an image without blocking).
fn blockiness(img: &GrayImage) -> f64 {
    let (mut edge, mut ne, mut inner, mut ni) = (0.0, 0.0, 0.0, 0.0);
    for y in 0..img.height() {
        for x in 0..img.width() - 1 {
            let d = (img.get_pixel(x + 1, y).0[0] as f64 - img.get_pixel(x, y).0[0] as f64).abs();
            if x % 8 == 7 {
                edge += d;
                ne += 1.0;
            } else {
                inner += d;
                ni += 1.0;
            }
        }
    }
    (edge / ne) / (inner / ni)
}

#[test]
fn compression_at_a_low_quality_leaves_blocking_and_costs_fewer_bits() {
    let world = Arc::new(World::generate_with(3, &WorldParams::small()).unwrap());
    let r = Arc::new(Renderer::new(
        world,
        SimCamera::default(),
        RenderParams::default(),
    ));
    let pose = camera_from_yaw_pitch(Point3::new(-40.0, 10.0, -30.0), 0.3, 45f64.to_radians());
    let capture = |q: Option<u8>| {
        let mut cam = Realism::ideal().camera;
        cam.compression = q.map(|quality| Compression::Jpeg { quality });
        Imager::new(r.clone(), cam, &no_light())
            .capture(0.0, &|_| pose, Some(5))
            .unwrap()
    };
    let raw = capture(None);
    assert!(raw.encoded.is_none());
    let q90 = capture(Some(90));
    let q25 = capture(Some(25));
    // The frame is exactly what decoding the stream's bytes gives.
    let decoded = image::load_from_memory(q25.encoded.as_ref().unwrap())
        .unwrap()
        .to_luma8();
    assert_eq!(decoded, q25.image);
    let (b90, b25) = (
        q90.encoded.as_ref().unwrap().len(),
        q25.encoded.as_ref().unwrap().len(),
    );
    let (k_raw, k90, k25) = (
        blockiness(&raw.image),
        blockiness(&q90.image),
        blockiness(&q25.image),
    );
    eprintln!("bytes q90 {b90} q25 {b25}; blockiness raw {k_raw:.3} q90 {k90:.3} q25 {k25:.3}");
    assert!(b25 * 2 < b90);
    assert!((k_raw - 1.0).abs() < 0.05);
    assert!(k25 > 1.15 && k25 > k90 + 0.08, "q25 {k25} q90 {k90}");
}

/// H.264 through OpenH264: the stream's bytes decode to exactly the frame
/// the imager returns, the bitrate follows the target, and the harsh
/// preset's lower bitrate leaves a worse picture than the field's.
#[test]
fn h264_compression_decodes_to_the_frame_at_its_bitrate() {
    let world = Arc::new(World::generate_with(3, &WorldParams::small()).unwrap());
    let r = Arc::new(Renderer::new(
        world,
        SimCamera::default(),
        RenderParams::default(),
    ));
    let run = |spec: &str| {
        let realism = Realism::parse(spec).unwrap();
        let mut cam = Realism::ideal().camera;
        cam.compression = realism.camera.compression;
        let mut imager = Imager::new(r.clone(), cam, &no_light());
        let mut dec = openh264::decoder::Decoder::new().unwrap();
        let (mut bytes, mut err) = (0usize, 0.0f64);
        const N: usize = 30;
        for k in 0..N {
            // Panning half a degree per frame.
            let pose = camera_from_yaw_pitch(
                Point3::new(-40.0, 10.0, -30.0),
                0.3 + 0.5f64.to_radians() * k as f64,
                45f64.to_radians(),
            );
            let raw = r.render_noisy(&pose, k as u64);
            let shot = imager.capture(0.0, &|_| pose, Some(k as u64)).unwrap();
            let au = shot.encoded.as_ref().unwrap();
            bytes += au.len();
            // The ground station's decoder, fed the same bytes, shows the
            // same picture.
            use openh264::formats::YUVSource;
            let yuv = dec.decode(au).unwrap().unwrap();
            let (w, h) = yuv.dimensions();
            let stride = yuv.strides().0;
            let luma: Vec<u8> = (0..h)
                .flat_map(|y| yuv.y()[y * stride..y * stride + w].to_vec())
                .collect();
            assert_eq!(luma, *shot.image.as_raw(), "frame {k}");
            err += shot
                .image
                .as_raw()
                .iter()
                .zip(raw.as_raw())
                .map(|(a, b)| (f64::from(*a) - f64::from(*b)).abs())
                .sum::<f64>()
                / raw.as_raw().len() as f64;
        }
        let kbit_s = bytes as f64 * 8.0 / (N as f64 / 15.0) / 1e3;
        (kbit_s, err / N as f64)
    };
    let (field_kbps, field_err) = run("field+h264");
    let (harsh_kbps, harsh_err) = run("field+h264@harsh");
    eprintln!(
        "H.264 field {field_kbps:.0} kbit/s, mean abs error {field_err:.2}; harsh {harsh_kbps:.0} kbit/s, {harsh_err:.2}"
    );
    // Rate control over two seconds: within 40 % of the target.
    assert!((300.0..700.0).contains(&field_kbps), "{field_kbps}");
    assert!((150.0..350.0).contains(&harsh_kbps), "{harsh_kbps}");
    assert!(harsh_err > field_err, "{harsh_err} {field_err}");
}

#[test]
fn cloud_shadows_drift_with_their_wind_and_take_their_share_of_the_sunlight() {
    let world = flat_world(150.0);
    let ambient = world.params.ambient as f64;
    let clouds = CloudShadows {
        cover: 0.5,
        scale_m: 20.0,
        edge_m: 2.0,
        opacity: 0.8,
        altitude_m: 300.0,
        velocity_m_s: [3.0, 0.0],
        seed: 9,
    };
    let r = Arc::new(
        Renderer::new(
            Arc::new(world),
            SimCamera::default(),
            RenderParams {
                noise_sigma: 0.0,
                ..RenderParams::default()
            },
        )
        .with_clouds(clouds),
    );
    let altitude = 30.0;
    let pose = down(0.0, 0.0, altitude);
    let mut imager = Imager::new(r, plain_camera(), &no_light());
    let a = imager.capture(0.0, &|_| pose, None).unwrap().image;
    let b = imager.capture(1.0, &|_| pose, None).unwrap().image;
    // Lit and shadowed levels: a full cloud removes opacity of the direct light.
    let mut values: Vec<u8> = a.as_raw().clone();
    values.sort_unstable();
    let (dark, lit) = (
        values[values.len() / 50] as f64,
        values[values.len() * 49 / 50] as f64,
    );
    let expected = 1.0 - (1.0 - ambient) * 0.8;
    assert!(
        (dark / lit - expected).abs() < 0.05,
        "{dark} / {lit} vs {expected}"
    );
    // The clouds drift north at 3 m/s: in one second the shadows move
    // 3 m up the image (image y is south).
    let shift_expected = 3.0 * f() / altitude;
    let (mut best, mut best_d) = (f64::MAX, 0i32);
    for d in 0..80 {
        let mut sum = 0.0;
        for y in 100..380 - 80 {
            for x in (100..540).step_by(2) {
                let va = a.get_pixel(x, (y + d) as u32).0[0] as f64;
                let vb = b.get_pixel(x, y as u32).0[0] as f64;
                sum += (va - vb).powi(2);
            }
        }
        if sum < best {
            best = sum;
            best_d = d;
        }
    }
    eprintln!("cloud shadow shift {best_d} px in 1 s, expected {shift_expected:.1}");
    assert!(
        (best_d as f64 - shift_expected).abs() <= (0.1 * shift_expected).max(1.0),
        "{best_d} vs {shift_expected}"
    );
}

/// Intensity-weighted centroid of the bright blob near `guess`.
fn centroid(img: &GrayImage, guess: Point2<f64>, half: i64, bg: f64) -> Point2<f64> {
    let (cx, cy) = (guess.x.round() as i64, guess.y.round() as i64);
    let (mut sw, mut sx, mut sy) = (0.0, 0.0, 0.0);
    for y in cy - half..=cy + half {
        for x in cx - half..=cx + half {
            let w = (img.get_pixel(x as u32, y as u32).0[0] as f64 - bg - 5.0).max(0.0);
            sw += w;
            sx += w * x as f64;
            sy += w * y as f64;
        }
    }
    assert!(sw > 500.0, "no blob near {guess:?}");
    Point2::new(sx / sw, sy / sw)
}

#[test]
fn rolling_shutter_truth_puts_every_marker_where_its_row_pose_projects_it() {
    let markers = [
        (4.0, -5.0),
        (-3.5, 4.5),
        (3.0, 5.0),
        (-4.5, -4.0),
        (0.5, 0.0),
    ];
    let mut world = flat_world(30.0);
    for &(x, y) in &markers {
        world.paint_ground_marker(x, y, 0.25, 235.0, 0.6, 30.0);
    }
    let r = renderer(world);
    let cam = *r.camera();
    // Moving and turning fast: rows see very different poses.
    let pose_at = |t: f64| {
        let s = t - 0.2;
        camera_from_yaw_pitch(
            Point3::new(8.0 * s, 5.0 * s, -18.0),
            0.4 + 0.8 * s,
            (88.0 - 20.0 * s).to_radians(),
        )
    };
    let mut c = plain_camera();
    c.rolling_shutter = Some(RollingShutter { readout_s: 0.033 });
    let shot = Imager::new(r, c, &no_light())
        .capture(0.2, &pose_at, None)
        .unwrap();
    assert!(!shot.row_knots.is_empty());
    let mut worst: f64 = 0.0;
    let mut worst_global: f64 = 0.0;
    for &(x, y) in &markers {
        let p = Point3::new(x, y, 0.0);
        let project = |pose: &Isometry3<f64>| {
            cam.project(&pose.inverse_transform_point(&p).coords)
                .unwrap()
        };
        // The row that sees the marker: iterate row -> pose -> projection.
        let mut px = project(&shot.world_from_cam);
        for _ in 0..5 {
            let row = px.y.round().clamp(0.0, 479.0) as usize;
            px = project(&interpolate_knots(&shot.row_knots, row).unwrap());
        }
        let measured = centroid(&shot.image, px, 8, 30.0);
        worst = worst.max((measured - px).norm());
        worst_global = worst_global.max((measured - project(&shot.world_from_cam)).norm());
    }
    eprintln!(
        "marker error with the row poses {worst:.3} px, with the frame pose {worst_global:.2} px"
    );
    assert!(worst < 0.15, "{worst} px");
    // The frame pose alone would be off by pixels: the rows matter.
    assert!(worst_global > 1.0);
    // The frame's pose is the centre row's.
    let centre = shot.row_pose(240);
    assert!(
        (centre.translation.vector - pose_at(0.2 + 0.5 / 479.0 * 0.033).translation.vector).norm()
            < 1e-3
    );
}

#[test]
fn ideal_camera_captures_are_the_plain_renders() {
    let world = Arc::new(World::generate_with(3, &WorldParams::small()).unwrap());
    let r = Arc::new(Renderer::new(
        world,
        SimCamera::default(),
        RenderParams::default(),
    ));
    let pose = camera_from_yaw_pitch(Point3::new(-30.0, 10.0, -25.0), 0.3, 40f64.to_radians());
    let ideal = Realism::ideal();
    let mut imager = Imager::new(r.clone(), ideal.camera.clone(), &ideal.lighting);
    let shot = imager.capture(3.0, &|_| pose, Some(42)).unwrap();
    assert_eq!(shot.image, r.render_noisy(&pose, 42));
    assert!(shot.row_knots.is_empty() && shot.encoded.is_none());
    // A realistic camera with its effects switched off one by one down to
    // none: each on its own changes the frame.
    let field = Realism::field();
    for name in [
        "blur",
        "rolling_shutter",
        "auto_exposure",
        "vignetting",
        "noise",
        "compression",
    ] {
        let mut r1 = Realism::ideal();
        r1.set_effect(name, Some(&field)).unwrap();
        let moving = |t: f64| {
            camera_from_yaw_pitch(
                Point3::new(-30.0 + 5.0 * t, 10.0, -25.0),
                0.3 + t,
                40f64.to_radians(),
            )
        };
        let mut im = Imager::new(r.clone(), r1.camera.clone(), &r1.lighting);
        let a = im.capture(3.0, &moving, Some(42)).unwrap();
        let plain = r.render_noisy(&moving(3.0), 42);
        assert_ne!(a.image, plain, "{name} changes nothing");
    }
}
