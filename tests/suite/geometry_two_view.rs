//! Two-view initialisation on synthetic scenes whose answer is known.

use crate::geometry_support;

use geometry_support::{CX, CY, F, TwoViewScene as Scene, motion, two_view_scene as make_scene};
use nalgebra::Matrix3;
use shotpilot::geometry::{GeometryError, Model, TwoViewParams, initialize_two_view};

fn k() -> Matrix3<f64> {
    Matrix3::new(F, 0.0, CX, 0.0, F, CY, 0.0, 0.0, 1.0)
}

/// Checks the motion and the reconstruction; returns the reconstruction
/// error (RMS of the scale-aligned point error over the mean depth).
fn check(s: &Scene, res: &shotpilot::geometry::TwoViewResult, label: &str) -> f64 {
    let rot_err = res
        .cam2_from_cam1
        .rotation
        .angle_to(&s.cam2_from_cam1.rotation)
        .to_degrees();
    let t_est = res.cam2_from_cam1.translation.vector;
    let t_true = s.cam2_from_cam1.translation.vector;
    let t_ang = t_est
        .normalize()
        .dot(&t_true.normalize())
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    // Scale-only alignment (both in the camera-1 frame).
    let (mut num, mut den) = (0.0, 0.0);
    for (p, q) in res.points.iter().zip(&s.p1) {
        if let Some(p) = p {
            num += p.coords.dot(&q.coords);
            den += p.coords.norm_squared();
        }
    }
    let scale = num / den;
    let (mut se, mut n, mut depth, mut kept_out) = (0.0, 0usize, 0.0, 0usize);
    let mut rel = Vec::new();
    for ((p, q), &o) in res.points.iter().zip(&s.p1).zip(&s.outlier) {
        if let Some(p) = p {
            if o {
                kept_out += 1;
                continue;
            }
            let e = (p.coords * scale - q.coords).norm();
            se += e * e;
            depth += q.z;
            n += 1;
            rel.push(e / q.coords.norm());
        }
    }
    let rms = (se / n as f64).sqrt() / (depth / n as f64);
    eprintln!(
        "{label}: model {:?}, R_H {:.3}, rot err {rot_err:.4} deg, t dir err {t_ang:.3} deg, \
         {n} points, parallax {:.2} deg, good {} vs second {}, reconstruction RMS {:.3} % of mean depth, \
         median per-point {:.3} %, outliers triangulated {kept_out}",
        res.model,
        res.score_h / (res.score_h + res.score_f),
        res.parallax_deg,
        res.n_good,
        res.n_second,
        rms * 100.0,
        shotpilot::stats::median(&rel).unwrap_or(f64::NAN) * 100.0
    );
    assert!(rot_err < 0.5, "{label}: rotation error {rot_err}");
    assert!(t_ang < 3.0, "{label}: translation direction error {t_ang}");
    assert!(kept_out <= 2, "{label}: {kept_out} outliers triangulated");
    rms
}

/// Runs five seeded scenes; each must pick `want`, recover the motion and
/// reconstruct with < 1 % RMS error (scale-aligned, over the mean depth).
/// Noise: 0.5 px per coordinate in both images, 10 % outlier matches.
fn five_scenes(planar: bool, want: Model, c: [f64; 3], r: [f64; 3], label: &str) {
    for seed in 0..5u64 {
        let s = make_scene(
            10 * seed + u64::from(planar),
            400,
            planar,
            motion(c, r),
            0.5,
            0.1,
        );
        let res = initialize_two_view(
            &k(),
            &s.kp1,
            &s.kp2,
            &s.matches,
            &TwoViewParams::default(),
            42 + seed,
        )
        .unwrap_or_else(|e| panic!("{label} seed {seed}: {e:?}"));
        assert_eq!(res.model, want, "{label} seed {seed}");
        let rms = check(&s, &res, &format!("{label} seed {seed}"));
        assert!(
            rms < 0.01,
            "{label} seed {seed}: reconstruction error {rms}"
        );
        assert!(res.points.iter().filter(|p| p.is_some()).count() > 300);
    }
}

#[test]
fn non_planar_scene_initialises_with_fundamental() {
    // Camera centre moves 1.6 m sideways, 0.3 m forward; depth 4-9 m.
    five_scenes(
        false,
        Model::Fundamental,
        [1.6, 0.1, 0.3],
        [0.02, -0.08, 0.01],
        "non-planar",
    );
}

#[test]
fn planar_scene_initialises_with_homography() {
    // Tilted plane at 6 m; camera centre moves 1.4 m.
    five_scenes(
        true,
        Model::Homography,
        [1.4, -0.2, 0.2],
        [-0.03, 0.1, 0.02],
        "planar",
    );
}

#[test]
fn pure_rotation_is_refused_with_a_reason() {
    let m = motion([0.0, 0.0, 0.0], [0.05, -0.1, 0.03]);
    let s = make_scene(3, 400, false, m, 1.0, 0.05);
    let res = initialize_two_view(
        &k(),
        &s.kp1,
        &s.kp2,
        &s.matches,
        &TwoViewParams::default(),
        44,
    );
    eprintln!("pure rotation: {:?}", res.as_ref().map(|r| r.model));
    match res {
        Err(GeometryError::NotEnoughParallax {
            parallax_deg,
            needed_deg,
        }) => {
            assert!(parallax_deg < needed_deg);
        }
        other => panic!("pure rotation accepted or wrong reason: {other:?}"),
    }
}

#[test]
fn tiny_baseline_is_refused_with_a_reason() {
    // 2 cm at 4-9 m: parallax ≈ 0.2 degree.
    let m = motion([0.02, 0.0, 0.0], [0.01, 0.02, 0.0]);
    let s = make_scene(4, 400, false, m, 1.0, 0.05);
    match initialize_two_view(
        &k(),
        &s.kp1,
        &s.kp2,
        &s.matches,
        &TwoViewParams::default(),
        45,
    ) {
        Err(GeometryError::NotEnoughParallax {
            parallax_deg,
            needed_deg,
        }) => {
            eprintln!("tiny baseline: parallax {parallax_deg:.3} deg < {needed_deg} deg");
            assert!(parallax_deg < 1.0);
        }
        other => panic!("tiny baseline: {other:?}"),
    }
}

#[test]
fn same_seed_same_result_and_bad_input_refused() {
    let m = motion([1.2, 0.1, 0.3], [0.02, -0.08, 0.01]);
    let s = make_scene(5, 200, false, m, 1.0, 0.0);
    let p = TwoViewParams::default();
    let a = initialize_two_view(&k(), &s.kp1, &s.kp2, &s.matches, &p, 7).unwrap();
    let b = initialize_two_view(&k(), &s.kp1, &s.kp2, &s.matches, &p, 7).unwrap();
    assert_eq!(a.cam2_from_cam1, b.cam2_from_cam1);
    assert_eq!(a.points, b.points);
    assert!(matches!(
        initialize_two_view(&k(), &s.kp1, &s.kp2, &s.matches[..5], &p, 7),
        Err(GeometryError::NotEnoughPoints {
            found: 5,
            needed: 8
        })
    ));
    let mut bad = s.matches.clone();
    bad[3] = (999, 3);
    assert!(matches!(
        initialize_two_view(&k(), &s.kp1, &s.kp2, &bad, &p, 7),
        Err(GeometryError::IndexOutOfRange { index: 999, .. })
    ));
}

/// Point error of an initialisation after Sim(3) alignment to the truth (RMS
/// over the mean depth), and the same for the noise floor: the same noisy
/// observations triangulated with the true motion. Also the camera-2 centre
/// error (after scale alignment of the unit baseline) over the mean depth.
fn errors_against_the_noise_floor(
    s: &Scene,
    res: &shotpilot::geometry::TwoViewResult,
) -> (f64, f64, f64) {
    use nalgebra::{Isometry3, Point2, Point3};
    use shotpilot::geometry::{triangulate, umeyama};
    let norm = |p: &Point2<f64>| Point2::new((p.x - CX) / F, (p.y - CY) / F);
    let (mut est, mut truth, mut floor) = (Vec::new(), Vec::new(), Vec::new());
    for (i, p) in res.points.iter().enumerate() {
        let Some(p) = p else { continue };
        if s.outlier[i] {
            continue;
        }
        let Some(o) = triangulate(
            &Isometry3::identity(),
            &s.cam2_from_cam1,
            &norm(&s.kp1[i]),
            &norm(&s.kp2[i]),
        ) else {
            continue;
        };
        est.push(*p);
        truth.push(s.p1[i]);
        floor.push(o);
    }
    let depth = truth.iter().map(|q| q.z).sum::<f64>() / truth.len() as f64;
    let rms = |a: &[Point3<f64>]| {
        (a.iter()
            .zip(&truth)
            .map(|(p, q)| (p - q).norm_squared())
            .sum::<f64>()
            / a.len() as f64)
            .sqrt()
            / depth
    };
    let sim = umeyama(&est, &truth, true).expect("well-spread points");
    let aligned: Vec<Point3<f64>> = est.iter().map(|p| sim.transform_point(p)).collect();
    let c_true = s.cam2_from_cam1.inverse().translation.vector;
    let c_est = res.cam2_from_cam1.inverse().translation.vector * c_true.norm();
    (rms(&aligned), rms(&floor), (c_est - c_true).norm() / depth)
}

/// The 1 px case. Per point, the error is bounded below by the
/// observation noise: on these scenes (baseline 1.4-1.6 m at 4-9 m, f = 500)
/// the same observations triangulated with the TRUE motion already err by
/// 1.4-1.5 % (non-planar) and 1.0 % (planar) of the mean depth, so "< 1 %"
/// per point cannot hold at 1 px for any initialiser. What the initialiser
/// controls is checked instead: the points (after its two-view bundle
/// adjustment and Sim(3) alignment) within 20 % of that floor, and the
/// motion: camera-2 centre within 1 % of the mean depth. Every scene must
/// initialise with the right model (at 1 px a planar pair's score ratio is
/// 0.399, below 0.40: F is refused and the homography fallback takes it; a
/// non-planar pair's minimal-fit motion triangulates 270 good points where
/// ORB-SLAM's 90 % rule wants 273, its bundle-adjusted motion all 303).
#[test]
fn one_px_noise_reaches_the_noise_floor() {
    for (planar, want, c, r, label) in [
        (
            false,
            Model::Fundamental,
            [1.6, 0.1, 0.3],
            [0.02, -0.08, 0.01],
            "non-planar",
        ),
        (
            true,
            Model::Homography,
            [1.4, -0.2, 0.2],
            [-0.03, 0.1, 0.02],
            "planar",
        ),
    ] {
        let mut ok = 0;
        for seed in 0..5u64 {
            let s = make_scene(
                10 * seed + u64::from(planar),
                400,
                planar,
                motion(c, r),
                1.0,
                0.1,
            );
            let res = match initialize_two_view(
                &k(),
                &s.kp1,
                &s.kp2,
                &s.matches,
                &TwoViewParams::default(),
                42 + seed,
            ) {
                Ok(res) => res,
                Err(e) => {
                    eprintln!("1 px {label} seed {seed}: refused, {e:?}");
                    continue;
                }
            };
            assert_eq!(res.model, want, "1 px {label} seed {seed}");
            check(&s, &res, &format!("1 px {label} seed {seed}"));
            let (e, e_floor, e_cam) = errors_against_the_noise_floor(&s, &res);
            eprintln!(
                "1 px {label} seed {seed}: points {:.3} % of mean depth after Sim(3) alignment, \
                 noise floor (true motion) {:.3} %, camera-2 centre {:.3} %",
                e * 100.0,
                e_floor * 100.0,
                e_cam * 100.0
            );
            assert!(e < 1.2 * e_floor, "{label} seed {seed}: {e} vs {e_floor}");
            assert!(e_cam < 0.01, "{label} seed {seed}: camera centre {e_cam}");
            ok += 1;
        }
        assert_eq!(ok, 5, "1 px {label}: only {ok}/5 initialised");
    }
}
