//! Telling apart the two reconstructions of a planar scene.
//!
//! Two views of a plane fix a homography, and a calibrated homography has
//! two physically valid decompositions (Faugeras & Lustman): the true
//! motion and plane, and a twin whose plane normal lies near the direction
//! of travel. Both put every point in front of both cameras with the same
//! reprojection error, so ORB-SLAM refuses such pairs as ambiguous and
//! waits; over ground seen from a drone it can wait for a long time.
//!
//! The twin's normal depends on the baseline (for a camera displaced by
//! `s·c` from the reference it moves with `s`), while the true normal does
//! not. So a third view, taken between the reference and the current frame,
//! decides: place it by PnP against each reconstruction's points; the true
//! one explains it to the keypoint noise, the twin leaves a systematic
//! residual. Nothing is decided while the residuals stay alike
//! ([`choose_reconstruction`]).

use nalgebra::{Isometry3, Matrix3, Point2, Point3, Translation3, Vector3};

use crate::camera::Camera;
use crate::geometry::{self, GeometryError, PnpParams, TwoViewParams, TwoViewResult};

use super::aided::RelativeMotion;
use super::params::TrackingParams;

/// One motion hypothesis of a planar pair with its triangulation.
#[derive(Debug, Clone)]
pub struct PlanarHypothesis {
    /// Camera 2 from camera 1, translation of unit norm.
    pub cam2_from_cam1: Isometry3<f64>,
    /// Per match: the point in camera-1 coordinates when it passed the
    /// depth and reprojection checks with enough parallax.
    pub points: Vec<Option<Point3<f64>>>,
    /// Points passing the depth and reprojection checks.
    pub n_good: usize,
    /// Parallax at the rank ORB-SLAM uses, degrees.
    pub parallax_deg: f64,
}

/// Where the matched keypoints of the initialisation frame were seen in an
/// intermediate frame: (keypoint of the initialisation frame, pixel).
#[derive(Debug, Clone)]
pub struct ThirdView {
    /// Frame index.
    pub index: u64,
    /// Correspondences.
    pub seen: Vec<(usize, Point2<f64>)>,
}

fn normalized(camera: &Camera, p: &Point2<f64>) -> Point2<f64> {
    Point2::new((p.x - camera.cx) / camera.fx, (p.y - camera.cy) / camera.fy)
}

fn reprojection_error2(camera: &Camera, p_cam: &Vector3<f64>, px: &Point2<f64>) -> f64 {
    let u = camera.fx * p_cam.x / p_cam.z + camera.cx;
    let v = camera.fy * p_cam.y / p_cam.z + camera.cy;
    (u - px.x).powi(2) + (v - px.y).powi(2)
}

/// Triangulate the inlier matches under one motion and count the points
/// that pass ORB-SLAM's checks (in front of both cameras, reprojection
/// within `reprojection_chi2·σ²` in both).
#[allow(clippy::too_many_arguments)]
fn check_motion(
    camera: &Camera,
    kp1: &[Point2<f64>],
    kp2: &[Point2<f64>],
    matches: &[(usize, usize)],
    inliers: &[bool],
    cam2_from_cam1: &Isometry3<f64>,
    params: &TwoViewParams,
) -> PlanarHypothesis {
    let th2 = params.reprojection_chi2 * params.sigma_px * params.sigma_px;
    let id = Isometry3::identity();
    let o2 = cam2_from_cam1.inverse().translation.vector;
    let mut points = vec![None; matches.len()];
    let mut cos_list = Vec::new();
    for (m, &(i, j)) in matches.iter().enumerate() {
        if !inliers.get(m).copied().unwrap_or(false) {
            continue;
        }
        let (Some(a), Some(b)) = (kp1.get(i), kp2.get(j)) else {
            continue;
        };
        let Some(p) = geometry::triangulate(
            &id,
            cam2_from_cam1,
            &normalized(camera, a),
            &normalized(camera, b),
        ) else {
            continue;
        };
        let p1 = p.coords;
        let p2 = cam2_from_cam1 * p;
        if p1.z <= 0.0 || p2.z <= 0.0 {
            continue;
        }
        if reprojection_error2(camera, &p1, a) > th2
            || reprojection_error2(camera, &p2.coords, b) > th2
        {
            continue;
        }
        let cos_par = p1.dot(&(p1 - o2)) / (p1.norm() * (p1 - o2).norm());
        if !cos_par.is_finite() {
            continue;
        }
        cos_list.push(cos_par);
        if cos_par < params.cos_parallax_with_depth {
            points[m] = Some(p);
        }
    }
    let n_good = cos_list.len();
    let parallax_deg = geometry::two_view::ranked_parallax_deg(&mut cos_list, params.parallax_rank);
    PlanarHypothesis {
        cam2_from_cam1: *cam2_from_cam1,
        points,
        n_good,
        parallax_deg,
    }
}

/// The two best distinct decompositions of the homography behind `tv` (a
/// planar reconstruction): the plane is fitted to `tv`'s points, the
/// calibrated homography `R + t·nᵀ/d` rebuilt and decomposed again.
/// Returns them best first, or `None` when the points do not fix a plane.
pub fn twin_hypotheses(
    camera: &Camera,
    kp1: &[Point2<f64>],
    kp2: &[Point2<f64>],
    matches: &[(usize, usize)],
    tv: &TwoViewResult,
    params: &TwoViewParams,
) -> Option<[PlanarHypothesis; 2]> {
    let pts: Vec<Vector3<f64>> = tv.points.iter().flatten().map(|p| p.coords).collect();
    if pts.len() < 3 {
        return None;
    }
    let c = pts.iter().sum::<Vector3<f64>>() / pts.len() as f64;
    let mut cov = Matrix3::zeros();
    for p in &pts {
        let d = p - c;
        cov += d * d.transpose();
    }
    let eig = cov.symmetric_eigen();
    let (imin, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let mut n = eig.eigenvectors.column(imin).into_owned();
    let mut d = n.dot(&c);
    if d < 0.0 {
        n = -n;
        d = -d;
    }
    if d.is_nan() || d <= 1e-12 {
        return None;
    }
    let r = tv.cam2_from_cam1.rotation.to_rotation_matrix().into_inner();
    let t = tv.cam2_from_cam1.translation.vector;
    let a = r + t * n.transpose() / d;
    let hyps = geometry::two_view::decompose_h(&a)?;
    let mut checked: Vec<PlanarHypothesis> = hyps
        .into_iter()
        .map(|(r, t)| {
            let cam2_from_cam1 = Isometry3::from_parts(
                Translation3::from(t),
                crate::lie::quaternion_from_matrix(&r),
            );
            check_motion(
                camera,
                kp1,
                kp2,
                matches,
                &tv.inliers,
                &cam2_from_cam1,
                params,
            )
        })
        .collect();
    checked.sort_by_key(|h| std::cmp::Reverse(h.n_good));
    let best = checked.first()?.clone();
    // The twin: the best hypothesis that is a different motion.
    let twin = checked.iter().skip(1).find(|h| {
        let dr = h
            .cam2_from_cam1
            .rotation
            .angle_to(&best.cam2_from_cam1.rotation);
        let dt = h
            .cam2_from_cam1
            .translation
            .vector
            .angle(&best.cam2_from_cam1.translation.vector);
        dr > 0.2f64.to_radians() || dt > 2f64.to_radians()
    })?;
    Some([best, twin.clone()])
}

/// How well a reconstruction explains a third view: the view is placed by
/// PnP RANSAC on the reconstruction's points, and the cost is the mean of
/// the squared reprojection errors (pixels², each capped at the PnP inlier
/// bound). `None` when too few points are shared.
pub fn third_view_cost(
    camera: &Camera,
    hypothesis: &PlanarHypothesis,
    matches: &[(usize, usize)],
    view: &ThirdView,
    pnp: &PnpParams,
    seed: u64,
) -> Option<f64> {
    let mut by_ref: std::collections::HashMap<usize, Point3<f64>> =
        std::collections::HashMap::new();
    for (m, &(i, _)) in matches.iter().enumerate() {
        if let Some(p) = hypothesis.points.get(m).copied().flatten() {
            by_ref.insert(i, p);
        }
    }
    let mut pts = Vec::new();
    let mut obs = Vec::new();
    let mut px = Vec::new();
    for (i, uv) in &view.seen {
        if let Some(p) = by_ref.get(i) {
            pts.push(*p);
            obs.push(normalized(camera, uv));
            px.push(*uv);
        }
    }
    if pts.len() < 20 {
        return None;
    }
    let r = geometry::solve_pnp_ransac(&pts, &obs, camera.fx, pnp, seed).ok()?;
    let cap = pnp.inlier_chi2 * pnp.sigma_px * pnp.sigma_px;
    let mut sum = 0.0;
    for (p, uv) in pts.iter().zip(&px) {
        let pc = r.cam_from_world * p;
        let e2 = if pc.z > 0.0 {
            reprojection_error2(camera, &pc.coords, uv)
        } else {
            cap
        };
        sum += e2.min(cap);
    }
    Some(sum / pts.len() as f64)
}

/// A [`TwoViewResult`] carrying `h` in place of `tv`'s reconstruction.
pub fn as_result(tv: &TwoViewResult, h: &PlanarHypothesis, second: usize) -> TwoViewResult {
    TwoViewResult {
        cam2_from_cam1: h.cam2_from_cam1,
        points: h.points.clone(),
        model: tv.model,
        inliers: tv.inliers.clone(),
        score_h: tv.score_h,
        score_f: tv.score_f,
        parallax_deg: h.parallax_deg,
        n_good: h.n_good,
        n_second: second,
    }
}

/// Why the planar reconstructions could not be told apart (yet).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PlanarFailure {
    /// The relaxed two-view solve failed.
    #[error(transparent)]
    Geometry(#[from] GeometryError),
    /// The relaxed solve chose the fundamental matrix, whose hypotheses are alike.
    #[error("the motion hypotheses of F are alike")]
    FundamentalAmbiguous,
    /// The homography has no second valid decomposition.
    #[error("the homography gives no second reconstruction")]
    NoTwin,
    /// No frame between the two initialisation frames was seen yet.
    #[error("no third view yet to choose between the planar reconstructions")]
    NoThirdView,
    /// No third view shares enough points with the reconstructions.
    #[error("the third views share too few points")]
    ThirdViewsShareTooFew,
    /// The third views explain both reconstructions about equally well (or
    /// neither well).
    #[error(
        "third views do not tell the planar reconstructions apart (costs {best_cost:.2} and {other_cost:.2} px²)"
    )]
    Undecided {
        /// Mean squared reprojection error of the better one, pixels².
        best_cost: f64,
        /// That of the other, pixels².
        other_cost: f64,
    },
    /// The chosen reconstruction has too little parallax.
    #[error("not enough parallax: {parallax_deg:.3} deg, needed {needed_deg:.3} deg")]
    NotEnoughParallax {
        /// Its parallax, degrees.
        parallax_deg: f64,
        /// The minimum, degrees.
        needed_deg: f64,
    },
    /// The chosen reconstruction triangulates too few good points.
    #[error("only {found} good points (need {needed})")]
    TooFewGoodPoints {
        /// Good points.
        found: usize,
        /// The minimum.
        needed: usize,
    },
}

/// How far a two-view motion (`cam2 ← cam1`, translation up to scale) is
/// from the telemetry's, in the telemetry's sigmas: the larger of the
/// rotation's and (when known) the direction of travel's.
pub fn telemetry_distance(cam2_from_cam1: &Isometry3<f64>, m: &RelativeMotion) -> f64 {
    let rot = cam2_from_cam1.rotation.angle_to(&m.rotation) / m.rotation_sigma.max(1e-9);
    let dir = m.direction.map_or(0.0, |d| {
        // Camera 2's centre in camera 1's axes.
        let c = -(cam2_from_cam1.rotation.inverse() * cam2_from_cam1.translation.vector);
        c.angle(&d) / m.direction_sigma.max(1e-9)
    });
    rot.max(dir)
}

/// Which of a planar pair's two reconstructions the telemetry's relative
/// motion supports (0: `a`, 1: `b`): the one within
/// [`TELEMETRY_AGREE_SIGMAS`] of it when the other is beyond
/// [`TELEMETRY_REFUTE_SIGMAS`]; `None` when the motion cannot tell (both
/// agree, as over a short baseline, or neither does).
pub fn telemetry_choice(
    a: &PlanarHypothesis,
    b: &PlanarHypothesis,
    motion: &RelativeMotion,
) -> Option<usize> {
    let (da, db) = (
        telemetry_distance(&a.cam2_from_cam1, motion),
        telemetry_distance(&b.cam2_from_cam1, motion),
    );
    tracing::debug!(
        sigmas_a = da,
        sigmas_b = db,
        "planar reconstructions against the telemetry"
    );
    if da <= TELEMETRY_AGREE_SIGMAS && db >= TELEMETRY_REFUTE_SIGMAS {
        Some(0)
    } else if db <= TELEMETRY_AGREE_SIGMAS && da >= TELEMETRY_REFUTE_SIGMAS {
        Some(1)
    } else {
        None
    }
}

/// A reconstruction agrees with the telemetry within this many sigmas.
pub const TELEMETRY_AGREE_SIGMAS: f64 = 3.0;

/// The other is refuted beyond this many.
pub const TELEMETRY_REFUTE_SIGMAS: f64 = 6.0;

/// A planar pair both of whose reconstructions hold: decide between them
/// by the telemetry's relative motion between the two frames when it can
/// tell ([`telemetry_choice`]), else with the frames seen in between
/// (`third_views`, from the attempt that started at frame `first_index`).
/// `attempt` seeds the relaxed two-view solve as the refused one was
/// seeded.
#[allow(clippy::too_many_arguments)]
pub fn choose_reconstruction(
    camera: &Camera,
    params: &TrackingParams,
    kp1: &[Point2<f64>],
    kp2: &[Point2<f64>],
    matches: &[(usize, usize)],
    first_index: u64,
    third_views: &[ThirdView],
    attempt: u64,
    telemetry: Option<&RelativeMotion>,
) -> Result<TwoViewResult, PlanarFailure> {
    let mut relaxed = params.two_view.clone();
    relaxed.h_second_fraction = f64::INFINITY;
    let tv = geometry::initialize_two_view(
        &camera.k(),
        kp1,
        kp2,
        matches,
        &relaxed,
        params.seed.wrapping_add(attempt),
    )?;
    if tv.model != geometry::Model::Homography {
        return Err(PlanarFailure::FundamentalAmbiguous);
    }
    let [a, b] = twin_hypotheses(camera, kp1, kp2, matches, &tv, &params.two_view)
        .ok_or(PlanarFailure::NoTwin)?;
    if let Some(pick) = telemetry.and_then(|m| telemetry_choice(&a, &b, m)) {
        let (win, lose) = if pick == 0 { (&a, &b) } else { (&b, &a) };
        return accept_choice(params, &tv, win, lose);
    }
    let (first, last) = (first_index, third_views.last().map_or(0, |v| v.index));
    if third_views.is_empty() || last <= first {
        return Err(PlanarFailure::NoThirdView);
    }
    // Third views near a quarter, half and three quarters of the way.
    let span = (last.saturating_sub(first) + 1) as f64;
    let mut picked: Vec<&ThirdView> = Vec::new();
    for q in [0.25, 0.5, 0.75] {
        let target = first as f64 + q * span;
        if let Some(v) = third_views.iter().min_by(|x, y| {
            (x.index as f64 - target)
                .abs()
                .total_cmp(&(y.index as f64 - target).abs())
        }) && !picked.iter().any(|p| p.index == v.index)
        {
            picked.push(v);
        }
    }
    let (mut ca, mut cb, mut used) = (0.0, 0.0, 0usize);
    for (n, v) in picked.iter().enumerate() {
        let seed = params.seed.wrapping_add(v.index * 7 + n as u64);
        let (Some(x), Some(y)) = (
            third_view_cost(camera, &a, matches, v, &params.pnp, seed),
            third_view_cost(camera, &b, matches, v, &params.pnp, seed),
        ) else {
            continue;
        };
        ca += x;
        cb += y;
        used += 1;
    }
    if used == 0 {
        return Err(PlanarFailure::ThirdViewsShareTooFew);
    }
    let (ca, cb) = (ca / used as f64, cb / used as f64);
    tracing::debug!(
        frame = last,
        good_a = a.n_good,
        good_b = b.n_good,
        cost_a = ca,
        cost_b = cb,
        views = used,
        "planar reconstructions"
    );
    let (win, lose, cw, cl) = if ca <= cb {
        (&a, &b, ca, cb)
    } else {
        (&b, &a, cb, ca)
    };
    if cl < params.planar_cost_ratio * cw || cw > params.planar_max_cost {
        return Err(PlanarFailure::Undecided {
            best_cost: cw,
            other_cost: cl,
        });
    }
    accept_choice(params, &tv, win, lose)
}

/// The chosen reconstruction, when it has the parallax and the good points
/// an initialisation needs.
fn accept_choice(
    params: &TrackingParams,
    tv: &TwoViewResult,
    win: &PlanarHypothesis,
    lose: &PlanarHypothesis,
) -> Result<TwoViewResult, PlanarFailure> {
    if win.parallax_deg < params.two_view.min_parallax_deg {
        return Err(PlanarFailure::NotEnoughParallax {
            parallax_deg: win.parallax_deg,
            needed_deg: params.two_view.min_parallax_deg,
        });
    }
    let needed = ((params.two_view.min_good_fraction
        * tv.inliers.iter().filter(|b| **b).count() as f64)
        .ceil() as usize)
        .max(params.two_view.min_triangulated);
    if win.n_good < needed {
        return Err(PlanarFailure::TooFewGoodPoints {
            found: win.n_good,
            needed,
        });
    }
    Ok(as_result(tv, win, lose.n_good))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::camera::Distortion;
    use nalgebra::UnitQuaternion;
    use rand::{Rng, SeedableRng, rngs::SmallRng};

    fn project(camera: &Camera, cam_from_world: &Isometry3<f64>, p: &Point3<f64>) -> Point2<f64> {
        let c = cam_from_world * p;
        Point2::new(
            camera.fx * c.x / c.z + camera.cx,
            camera.fy * c.y / c.z + camera.cy,
        )
    }

    /// A tilted plane seen by a camera moving across it (a baseline of
    /// about half the plane's distance): the two decompositions of its
    /// homography, and a third view halfway along the baseline (as tracking
    /// picks them) that tells them apart. With a baseline a fifth of the
    /// distance the costs are still alike (0.26 and 0.30 px²): tracking
    /// then waits for more frames.
    #[test]
    fn the_third_view_picks_the_true_plane_and_motion() {
        let camera = Camera::new(
            640,
            480,
            [460.0, 460.0, 319.5, 239.5],
            Distortion::default(),
        )
        .unwrap();
        let mut rng = SmallRng::seed_from_u64(3);
        // A plane through (0, 0, 10) tilted 50 degrees about the x axis.
        let u = Vector3::x();
        let v = Vector3::new(0.0, 50f64.to_radians().cos(), 50f64.to_radians().sin());
        let world: Vec<Point3<f64>> = (0..300)
            .map(|_| {
                let a = rng.random_range(-6.0..6.0);
                let b = rng.random_range(-5.0..5.0);
                Point3::from(Vector3::new(0.0, 0.0, 10.0) + a * u + b * v)
            })
            .collect();
        let cam1 = Isometry3::identity();
        let motion = |s: f64| {
            let rot = UnitQuaternion::from_euler_angles(0.02 * s, -0.05 * s, 0.03 * s);
            let center = Vector3::new(3.5, 0.6, 1.0) * s;
            Isometry3::from_parts(Translation3::from(-(rot * center)), rot)
        };
        let (cam3, cam2) = (motion(0.5), motion(1.0));
        let noisy = |cam: &Isometry3<f64>, rng: &mut SmallRng| -> Vec<Point2<f64>> {
            world
                .iter()
                .map(|p| {
                    let q = project(&camera, cam, p);
                    Point2::new(
                        q.x + rng.random_range(-0.5..0.5),
                        q.y + rng.random_range(-0.5..0.5),
                    )
                })
                .collect()
        };
        let kp1 = noisy(&cam1, &mut rng);
        let kp2 = noisy(&cam2, &mut rng);
        let kp3 = noisy(&cam3, &mut rng);
        let matches: Vec<(usize, usize)> = (0..world.len()).map(|i| (i, i)).collect();
        let params = TwoViewParams::default();
        // Both reconstructions, with the tie let through.
        let relaxed = TwoViewParams {
            h_second_fraction: f64::INFINITY,
            ..params.clone()
        };
        let tv =
            geometry::initialize_two_view(&camera.k(), &kp1, &kp2, &matches, &relaxed, 1).unwrap();
        let [a, b] = twin_hypotheses(&camera, &kp1, &kp2, &matches, &tv, &params).unwrap();
        let dir = cam2.translation.vector.normalize();
        let error = |h: &PlanarHypothesis| {
            (
                h.cam2_from_cam1
                    .rotation
                    .angle_to(&cam2.rotation)
                    .to_degrees(),
                h.cam2_from_cam1.translation.vector.angle(&dir).to_degrees(),
            )
        };
        let (ea, eb) = (error(&a), error(&b));
        let (truth, twin) = if ea.0 + ea.1 < eb.0 + eb.1 {
            (&a, &b)
        } else {
            (&b, &a)
        };
        let et = error(truth);
        assert!(et.0 < 0.5 && et.1 < 2.0, "true motion off by {et:?}");
        let ew = error(twin);
        assert!(
            ew.0 > 2.0 || ew.1 > 10.0,
            "the twin is the same motion: {ew:?}"
        );

        let view = ThirdView {
            index: 1,
            seen: kp3.iter().enumerate().map(|(i, p)| (i, *p)).collect(),
        };
        let pnp = PnpParams::default();
        let ct = third_view_cost(&camera, truth, &matches, &view, &pnp, 7).unwrap();
        let cw = third_view_cost(&camera, twin, &matches, &view, &pnp, 7).unwrap();
        println!(
            "third-view costs: true {ct:.3} px², twin {cw:.3} px²; twin good points {}",
            twin.n_good
        );
        // Uniform noise of ±0.5 px: 1/6 px² per point on average.
        assert!(ct < 0.5, "true reconstruction's cost {ct}");
        assert!(cw > 2.0 * ct, "twin's cost {cw} against {ct}");

        let result = as_result(&tv, truth, twin.n_good);
        assert_eq!(result.cam2_from_cam1, truth.cam2_from_cam1);
        assert_eq!(result.n_second, twin.n_good);

        // The telemetry's motion tells them apart without a third view: a
        // turn known to 0.3 degrees and a direction of travel to 3.
        let truth_index = if std::ptr::eq(truth, &a) { 0 } else { 1 };
        let motion = RelativeMotion {
            rotation: cam2.rotation,
            rotation_sigma: 0.3f64.to_radians(),
            direction: Some(cam2.inverse().translation.vector.normalize()),
            direction_sigma: 3f64.to_radians(),
        };
        assert_eq!(telemetry_choice(&a, &b, &motion), Some(truth_index));
        // A motion that says nothing sharp decides nothing.
        let vague = RelativeMotion {
            rotation_sigma: 20f64.to_radians(),
            direction: None,
            ..motion
        };
        assert_eq!(telemetry_choice(&a, &b, &vague), None);
        // The initialisation takes the reconstruction the telemetry
        // supports, with no third view at all.
        let without_views = |m: Option<&RelativeMotion>| {
            choose_reconstruction(
                &camera,
                &TrackingParams::default(),
                &kp1,
                &kp2,
                &matches,
                0,
                &[],
                1,
                m,
            )
        };
        let chosen = without_views(Some(&motion)).unwrap();
        assert!(
            chosen
                .cam2_from_cam1
                .rotation
                .angle_to(&cam2.rotation)
                .to_degrees()
                < 0.5
        );
        assert_eq!(without_views(None).unwrap_err(), PlanarFailure::NoThirdView);
    }
}
