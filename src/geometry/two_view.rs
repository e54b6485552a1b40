//! Two-view initialisation of a monocular map, after ORB-SLAM's
//! `Initializer` (Mur-Artal, Montiel & Tardós, T-RO 2015, §IV):
//!
//! 1. In seeded RANSAC over shared 8-point sets, fit a homography (normalised
//!    DLT) and a fundamental matrix (normalised 8-point, rank 2 enforced).
//!    Each model is scored by symmetric transfer: for every match and both
//!    directions the squared error `e²/σ²` is compared with a chi-square
//!    threshold (`5.991` = 95 % with two degrees of freedom for the
//!    point-to-point H error, `3.841` = 95 % with one for the point-to-line
//!    F error); inliers add `5.991 - e²/σ²` to the score, outliers nothing.
//!    Each winner is then refitted by least squares on its consensus set
//!    (kept when the score rises; ORB-SLAM omits this, and with pixel-level
//!    noise the minimal fits are visibly off).
//! 2. Model choice by ORB-SLAM's heuristic `R_H = S_H / (S_H + S_F)`: the
//!    homography is chosen when `R_H > 0.40` (planar scenes or low parallax),
//!    the fundamental matrix otherwise.
//! 3. The chosen model is decomposed into motion hypotheses: H by Faugeras &
//!    Lustman's method (8 hypotheses), F through `E = Kᵀ·F·K` (4 hypotheses).
//! 4. Each hypothesis triangulates the inliers (linear DLT) and keeps the
//!    points that are finite, in front of both cameras (checked when the
//!    parallax is measurable), and reproject within `2σ` in both images.
//!    A hypothesis must clearly beat the others (F: no other with more than
//!    70 % of its good points; H: the second best below 75 %), reconstruct
//!    90 % of the inliers, at least `min_triangulated` points, and reach
//!    `min_parallax_deg` (ORB-SLAM's 50th-largest parallax). A hypothesis
//!    that passes all but the 90 % rule is bundle-adjusted and checked
//!    again (the minimal-fit motion is slightly off at pixel-level noise).
//!    When F is refused, the homography is tried under its own checks
//!    (`homography_fallback`: noise in both images lowers `S_H` on planes).
//!    Otherwise the initialisation is refused with a typed
//!    [`GeometryError`] carrying the counts (F's, when both fail).
//! 5. The accepted reconstruction is refined by a two-view bundle
//!    adjustment (camera 1 fixed, Huber kernel, `refine_iterations`), as
//!    ORB-SLAM does with its global BA right after initialising.
//!
//! The translation of the result has unit norm (monocular scale is free);
//! callers rescale, e.g. to unit median depth.

use nalgebra::{Isometry3, Matrix3, Point2, Point3, SMatrix, SVector, Translation3, Vector3};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::GeometryError;
use super::triangulate::triangulate_cam1;

/// Tunables of [`initialize_two_view`]. Defaults are ORB-SLAM's.
#[derive(Debug, Clone, PartialEq)]
pub struct TwoViewParams {
    /// RANSAC iterations (8-point sets shared by H and F).
    pub ransac_iterations: usize,
    /// Keypoint position noise, pixels (the level-0 sigma).
    pub sigma_px: f64,
    /// Chi-square threshold for the point-to-line F error (1 DoF, 95 %).
    pub chi2_one_dof: f64,
    /// Chi-square threshold for point-to-point errors and the score ceiling
    /// (2 DoF, 95 %).
    pub chi2_two_dof: f64,
    /// The homography is chosen when `S_H/(S_H+S_F)` exceeds this
    /// (ORB-SLAM's 0.40). The ratio depends on the real keypoint noise
    /// against `sigma_px`: on synthetic planar scenes with 0.5 px noise in
    /// both images it is 0.47-0.48, with 1 px it drops to 0.39-0.48, so
    /// noisy planar pairs can fall to F (and are then usually refused).
    pub homography_ratio_threshold: f64,
    /// Minimum parallax of the reconstruction, degrees.
    pub min_parallax_deg: f64,
    /// Rank of the parallax used for the check (ORB-SLAM uses the 50th).
    pub parallax_rank: usize,
    /// Minimum number of well-triangulated points.
    pub min_triangulated: usize,
    /// Fraction of the model's inliers the best hypothesis must triangulate.
    pub min_good_fraction: f64,
    /// F: any other hypothesis above this fraction of the best's good points
    /// makes the reconstruction ambiguous.
    pub f_similar_fraction: f64,
    /// H: the second-best hypothesis must stay below this fraction.
    pub h_second_fraction: f64,
    /// Cosine of the parallax below which a point counts as "with parallax"
    /// (0.99998 ≈ 0.36 degree).
    pub cos_parallax_with_depth: f64,
    /// Squared reprojection error bound (in σ² units) for a good point.
    pub reprojection_chi2: f64,
    /// Least-squares refits of H and F on their consensus sets after RANSAC.
    pub refit_rounds: usize,
    /// LM iterations of the two-view bundle adjustment of the result
    /// (0: none).
    pub refine_iterations: usize,
    /// When the ratio picks F and F's reconstruction is refused, try the
    /// homography's (under all its own checks) before giving up; the error
    /// returned when both fail is F's. Noise in both images lowers `S_H`
    /// on planes, so a planar pair can fall just below the ratio threshold.
    pub homography_fallback: bool,
}

impl Default for TwoViewParams {
    fn default() -> Self {
        Self {
            ransac_iterations: 200,
            sigma_px: 1.0,
            chi2_one_dof: 3.841,
            chi2_two_dof: 5.991,
            homography_ratio_threshold: 0.40,
            min_parallax_deg: 1.0,
            parallax_rank: 50,
            min_triangulated: 50,
            min_good_fraction: 0.9,
            f_similar_fraction: 0.7,
            h_second_fraction: 0.75,
            cos_parallax_with_depth: 0.99998,
            reprojection_chi2: 4.0,
            refit_rounds: 2,
            refine_iterations: 20,
            homography_fallback: true,
        }
    }
}

/// Which model explained the two views.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Model {
    /// A homography (planar scene or low parallax).
    Homography,
    /// A fundamental matrix (general scene).
    Fundamental,
}

/// A successful two-view initialisation.
#[derive(Debug, Clone)]
pub struct TwoViewResult {
    /// Motion of camera 2 relative to camera 1 (`p_cam2 = T·p_cam1`),
    /// translation of unit norm.
    pub cam2_from_cam1: Isometry3<f64>,
    /// Per match: the triangulated point in camera-1 coordinates when it is
    /// an inlier that passed every check with enough parallax.
    pub points: Vec<Option<Point3<f64>>>,
    /// The model that won the selection.
    pub model: Model,
    /// Per match: inlier of the chosen model.
    pub inliers: Vec<bool>,
    /// Homography RANSAC score `S_H`.
    pub score_h: f64,
    /// Fundamental RANSAC score `S_F`.
    pub score_f: f64,
    /// Parallax of the reconstruction, degrees.
    pub parallax_deg: f64,
    /// Good points of the best hypothesis (including low-parallax ones).
    pub n_good: usize,
    /// Good points of the second-best hypothesis.
    pub n_second: usize,
}

/// Similarity that moves the centroid to the origin and sets the mean
/// absolute deviation of each axis to one (ORB-SLAM's normalisation).
fn normalize(pts: &[[f64; 2]], out: &mut Vec<[f64; 2]>) -> Matrix3<f64> {
    let n = pts.len() as f64;
    let (mut mx, mut my) = (0.0, 0.0);
    for p in pts {
        mx += p[0];
        my += p[1];
    }
    mx /= n;
    my /= n;
    let (mut dx, mut dy) = (0.0, 0.0);
    for p in pts {
        dx += (p[0] - mx).abs();
        dy += (p[1] - my).abs();
    }
    let sx = if dx > 0.0 { n / dx } else { 1.0 };
    let sy = if dy > 0.0 { n / dy } else { 1.0 };
    out.clear();
    out.extend(pts.iter().map(|p| [(p[0] - mx) * sx, (p[1] - my) * sy]));
    Matrix3::new(sx, 0.0, -mx * sx, 0.0, sy, -my * sy, 0.0, 0.0, 1.0)
}

/// Unit eigenvector of the smallest eigenvalue of a 9×9 symmetric matrix.
fn smallest_eigvec9(ata: SMatrix<f64, 9, 9>) -> Option<SVector<f64, 9>> {
    let eig = ata.symmetric_eigen();
    let (mut best, mut val) = (0usize, f64::INFINITY);
    for (i, &v) in eig.eigenvalues.iter().enumerate() {
        if v < val {
            val = v;
            best = i;
        }
    }
    let v = eig.eigenvectors.column(best).into_owned();
    v.iter().all(|x| x.is_finite()).then_some(v)
}

/// Smallest eigenvector of a 9×9 positive semi-definite `AᵀA` built from a
/// minimal sample, by inverse iteration on `AᵀA + εI` (one Cholesky, a few
/// solves: about a microsecond against ten for the full eigensolver). The
/// iteration converges by the ratio `λ₁/λ₂` per step; when two successive
/// iterates still differ (nearly repeated smallest eigenvalues: a degenerate
/// sample) it falls back to the full eigendecomposition.
fn null_vector9(ata: SMatrix<f64, 9, 9>) -> Option<SVector<f64, 9>> {
    let tr = ata.trace();
    if !(tr.is_finite() && tr > 0.0) {
        return None;
    }
    let mut shifted = ata;
    for i in 0..9 {
        shifted[(i, i)] += 1e-12 * tr;
    }
    if let Some(ch) = shifted.cholesky() {
        let mut x =
            SVector::<f64, 9>::from([1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2]).normalize();
        for it in 0..6 {
            let mut y = ch.solve(&x);
            let n = y.norm();
            if !(n.is_finite() && n > 0.0) {
                break;
            }
            y /= n;
            let change = (y - x).norm();
            x = y;
            if it >= 1 && change < 1e-7 {
                return Some(x);
            }
        }
    }
    smallest_eigvec9(ata)
}

/// Normalised DLT homography `x2 ~ H·x1` from ≥ 4 normalised pairs.
fn compute_h21(
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    idx: &[usize],
    minimal: bool,
) -> Option<Matrix3<f64>> {
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for &i in idx {
        let (u1, v1) = (p1[i][0], p1[i][1]);
        let (u2, v2) = (p2[i][0], p2[i][1]);
        let r1 = SVector::<f64, 9>::from([0.0, 0.0, 0.0, -u1, -v1, -1.0, v2 * u1, v2 * v1, v2]);
        let r2 = SVector::<f64, 9>::from([u1, v1, 1.0, 0.0, 0.0, 0.0, -u2 * u1, -u2 * v1, -u2]);
        ata += r1 * r1.transpose() + r2 * r2.transpose();
    }
    let h = if minimal {
        null_vector9(ata)?
    } else {
        smallest_eigvec9(ata)?
    };
    Some(Matrix3::new(
        h[0], h[1], h[2], h[3], h[4], h[5], h[6], h[7], h[8],
    ))
}

/// Normalised 8-point fundamental matrix `x2ᵀ·F·x1 = 0`, rank 2 enforced.
fn compute_f21(
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    idx: &[usize],
    minimal: bool,
) -> Option<Matrix3<f64>> {
    let mut ata = SMatrix::<f64, 9, 9>::zeros();
    for &i in idx {
        let (u1, v1) = (p1[i][0], p1[i][1]);
        let (u2, v2) = (p2[i][0], p2[i][1]);
        let r = SVector::<f64, 9>::from([u2 * u1, u2 * v1, u2, v2 * u1, v2 * v1, v2, u1, v1, 1.0]);
        ata += r * r.transpose();
    }
    let f = if minimal {
        null_vector9(ata)?
    } else {
        smallest_eigvec9(ata)?
    };
    let fpre = Matrix3::new(f[0], f[1], f[2], f[3], f[4], f[5], f[6], f[7], f[8]);
    let svd = fpre.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let mut s = svd.singular_values;
    s[2] = 0.0;
    Some(u * Matrix3::from_diagonal(&s) * vt)
}

/// The best-scoring model of one kind seen so far in the RANSAC, with its
/// inlier flags.
struct BestModel {
    score: f64,
    model: Option<Matrix3<f64>>,
    inliers: Vec<bool>,
}

impl BestModel {
    fn new(n: usize) -> Self {
        Self {
            score: 0.0,
            model: None,
            inliers: vec![false; n],
        }
    }

    /// Keeps `model` when `score` beats the best; its inlier flags in `cur`
    /// then become the best's (the old best's go back as scratch).
    fn offer(&mut self, score: f64, model: Matrix3<f64>, cur: &mut Vec<bool>) {
        if score > self.score {
            self.score = score;
            self.model = Some(model);
            std::mem::swap(cur, &mut self.inliers);
        }
    }

    /// The indices of the best's inliers, into `out`.
    fn inlier_indices(&self, out: &mut Vec<usize>) {
        out.clear();
        out.extend((0..self.inliers.len()).filter(|&i| self.inliers[i]));
    }
}

/// Symmetric transfer score of a homography (ORB-SLAM `CheckHomography`).
fn score_homography(
    h21: &Matrix3<f64>,
    h12: &Matrix3<f64>,
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    inv_sigma2: f64,
    th: f64,
    inliers: &mut [bool],
) -> f64 {
    let mut score = 0.0;
    for (i, (a, b)) in p1.iter().zip(p2).enumerate() {
        let (u1, v1, u2, v2) = (a[0], a[1], b[0], b[1]);
        let mut ok = true;
        // x1 -> image 2
        let w = h21[(2, 0)] * u1 + h21[(2, 1)] * v1 + h21[(2, 2)];
        let iw = 1.0 / w;
        let u = (h21[(0, 0)] * u1 + h21[(0, 1)] * v1 + h21[(0, 2)]) * iw;
        let v = (h21[(1, 0)] * u1 + h21[(1, 1)] * v1 + h21[(1, 2)]) * iw;
        let chi = ((u - u2).powi(2) + (v - v2).powi(2)) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th - chi;
        } else {
            ok = false;
        }
        // x2 -> image 1
        let w = h12[(2, 0)] * u2 + h12[(2, 1)] * v2 + h12[(2, 2)];
        let iw = 1.0 / w;
        let u = (h12[(0, 0)] * u2 + h12[(0, 1)] * v2 + h12[(0, 2)]) * iw;
        let v = (h12[(1, 0)] * u2 + h12[(1, 1)] * v2 + h12[(1, 2)]) * iw;
        let chi = ((u - u1).powi(2) + (v - v1).powi(2)) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th - chi;
        } else {
            ok = false;
        }
        inliers[i] = ok;
    }
    score
}

/// Symmetric point-to-epipolar-line score of F (ORB-SLAM `CheckFundamental`).
fn score_fundamental(
    f21: &Matrix3<f64>,
    p1: &[[f64; 2]],
    p2: &[[f64; 2]],
    inv_sigma2: f64,
    th: f64,
    th_score: f64,
    inliers: &mut [bool],
) -> f64 {
    let mut score = 0.0;
    for (i, (a, b)) in p1.iter().zip(p2).enumerate() {
        let (u1, v1, u2, v2) = (a[0], a[1], b[0], b[1]);
        let mut ok = true;
        // Line in image 2: l2 = F·x1
        let la = f21[(0, 0)] * u1 + f21[(0, 1)] * v1 + f21[(0, 2)];
        let lb = f21[(1, 0)] * u1 + f21[(1, 1)] * v1 + f21[(1, 2)];
        let lc = f21[(2, 0)] * u1 + f21[(2, 1)] * v1 + f21[(2, 2)];
        let num = la * u2 + lb * v2 + lc;
        let chi = num * num / (la * la + lb * lb) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th_score - chi;
        } else {
            ok = false;
        }
        // Line in image 1: l1ᵀ = x2ᵀ·F
        let la = f21[(0, 0)] * u2 + f21[(1, 0)] * v2 + f21[(2, 0)];
        let lb = f21[(0, 1)] * u2 + f21[(1, 1)] * v2 + f21[(2, 1)];
        let lc = f21[(0, 2)] * u2 + f21[(1, 2)] * v2 + f21[(2, 2)];
        let num = la * u1 + lb * v1 + lc;
        let chi = num * num / (la * la + lb * lb) * inv_sigma2;
        if chi.is_finite() && chi <= th {
            score += th_score - chi;
        } else {
            ok = false;
        }
        inliers[i] = ok;
    }
    score
}

/// Outcome of triangulating all inliers under one motion hypothesis.
struct Hypothesis {
    r: Matrix3<f64>,
    t: Vector3<f64>,
    n_good: usize,
    parallax_deg: f64,
    points: Vec<Option<Point3<f64>>>,
}

/// Shared inputs of the hypothesis checks.
struct CheckCtx<'a> {
    k: &'a Matrix3<f64>,
    px1: &'a [[f64; 2]],
    px2: &'a [[f64; 2]],
    xn1: &'a [Point2<f64>],
    xn2: &'a [Point2<f64>],
    inliers: &'a [bool],
    th2: f64,
    cos_with_depth: f64,
    parallax_rank: usize,
}

#[inline]
fn project(k: &Matrix3<f64>, p: &Vector3<f64>) -> (f64, f64) {
    let iz = 1.0 / p.z;
    let x = p.x * iz;
    let y = p.y * iz;
    (
        k[(0, 0)] * x + k[(0, 1)] * y + k[(0, 2)],
        k[(1, 1)] * y + k[(1, 2)],
    )
}

/// ORB-SLAM's `CheckRT`: triangulate, then parallax, cheirality and
/// reprojection checks. Returns the hypothesis with its counts.
fn check_rt(
    ctx: &CheckCtx<'_>,
    r: Matrix3<f64>,
    t: Vector3<f64>,
    cos_buf: &mut Vec<f64>,
) -> Hypothesis {
    let n = ctx.inliers.len();
    let mut points = vec![None; n];
    let o2 = -(r.transpose() * t); // camera-2 centre in camera-1 frame
    cos_buf.clear();
    let mut n_good = 0usize;
    for (i, slot) in points.iter_mut().enumerate() {
        if !ctx.inliers[i] {
            continue;
        }
        let Some(p) = triangulate_cam1(&r, &t, &ctx.xn1[i], &ctx.xn2[i]) else {
            continue;
        };
        let p1 = p.coords;
        let n1 = p1;
        let n2 = p1 - o2;
        let d1 = n1.norm();
        let d2 = n2.norm();
        let cos_par = n1.dot(&n2) / (d1 * d2);
        if !cos_par.is_finite() {
            continue;
        }
        if p1.z <= 0.0 && cos_par < ctx.cos_with_depth {
            continue;
        }
        let p2 = r * p1 + t;
        if p2.z <= 0.0 && cos_par < ctx.cos_with_depth {
            continue;
        }
        let (u1, v1) = project(ctx.k, &p1);
        let e1 = (u1 - ctx.px1[i][0]).powi(2) + (v1 - ctx.px1[i][1]).powi(2);
        if e1.is_nan() || e1 > ctx.th2 {
            continue;
        }
        let (u2, v2) = project(ctx.k, &p2);
        let e2 = (u2 - ctx.px2[i][0]).powi(2) + (v2 - ctx.px2[i][1]).powi(2);
        if e2.is_nan() || e2 > ctx.th2 {
            continue;
        }
        cos_buf.push(cos_par);
        n_good += 1;
        if cos_par < ctx.cos_with_depth {
            *slot = Some(p);
        }
    }
    let parallax_deg = if cos_buf.is_empty() {
        0.0
    } else {
        // Ascending cosine = descending parallax; take the rank-th largest.
        let idx = ctx.parallax_rank.min(cos_buf.len() - 1);
        let (_, c, _) = cos_buf.select_nth_unstable_by(idx, |a, b| a.total_cmp(b));
        c.clamp(-1.0, 1.0).acos().to_degrees()
    };
    Hypothesis {
        r,
        t,
        n_good,
        parallax_deg,
        points,
    }
}

/// The 4 motion hypotheses of `E` (two rotations, ± translation).
fn decompose_e(e: &Matrix3<f64>) -> Option<[(Matrix3<f64>, Vector3<f64>); 4]> {
    let svd = e.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let t = u.column(2).into_owned();
    let tn = t.norm();
    if tn.is_nan() || tn <= 0.0 {
        return None;
    }
    let t = t / tn;
    let w = Matrix3::new(0.0, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0);
    let mut r1 = u * w * vt;
    if r1.determinant() < 0.0 {
        r1 = -r1;
    }
    let mut r2 = u * w.transpose() * vt;
    if r2.determinant() < 0.0 {
        r2 = -r2;
    }
    Some([(r1, t), (r2, t), (r1, -t), (r2, -t)])
}

/// The 8 motion hypotheses of a calibrated homography `A = K⁻¹·H·K`
/// (Faugeras & Lustman 1988, cases d' = ±d₂). Returns `None` when the
/// singular values coincide (no translation is observable).
pub fn decompose_h(a: &Matrix3<f64>) -> Option<Vec<(Matrix3<f64>, Vector3<f64>)>> {
    let svd = a.svd(true, true);
    let (u, vt) = (svd.u?, svd.v_t?);
    let (d1, d2, d3) = (
        svd.singular_values[0],
        svd.singular_values[1],
        svd.singular_values[2],
    );
    if d1 / d2 < 1.00001 || d2 / d3 < 1.00001 {
        return None;
    }
    let s = u.determinant() * vt.determinant();
    let (d1s, d2s, d3s) = (d1 * d1, d2 * d2, d3 * d3);
    let aux1 = ((d1s - d2s) / (d1s - d3s)).sqrt();
    let aux3 = ((d2s - d3s) / (d1s - d3s)).sqrt();
    let x1 = [aux1, aux1, -aux1, -aux1];
    let x3 = [aux3, -aux3, aux3, -aux3];
    let mut out = Vec::with_capacity(8);
    // Case d' = d2.
    let aux_st = ((d1s - d2s) * (d2s - d3s)).sqrt() / ((d1 + d3) * d2);
    let ct = (d2s + d1 * d3) / ((d1 + d3) * d2);
    let st = [aux_st, -aux_st, -aux_st, aux_st];
    for i in 0..4 {
        let rp = Matrix3::new(ct, 0.0, -st[i], 0.0, 1.0, 0.0, st[i], 0.0, ct);
        let r = u * rp * vt * s;
        let tp = Vector3::new(x1[i], 0.0, -x3[i]) * (d1 - d3);
        let t = (u * tp).normalize();
        out.push((r, t));
    }
    // Case d' = -d2.
    let aux_sp = ((d1s - d2s) * (d2s - d3s)).sqrt() / ((d1 - d3) * d2);
    let cp = (d1 * d3 - d2s) / ((d1 - d3) * d2);
    let sp = [aux_sp, -aux_sp, -aux_sp, aux_sp];
    for i in 0..4 {
        let rp = Matrix3::new(cp, 0.0, sp[i], 0.0, -1.0, 0.0, sp[i], 0.0, -cp);
        let r = u * rp * vt * s;
        let tp = Vector3::new(x1[i], 0.0, x3[i]) * (d1 + d3);
        let t = (u * tp).normalize();
        out.push((r, t));
    }
    out.iter()
        .all(|(r, t)| r.iter().all(|v| v.is_finite()) && t.iter().all(|v| v.is_finite()))
        .then_some(out)
}

/// Initialises a map from two views.
///
/// * `cam_k`: the pinhole intrinsics (no skew assumed in the reprojection).
/// * `kp1`, `kp2`: undistorted keypoint pixels of the two frames.
/// * `matches`: `(index in kp1, index in kp2)` pairs.
/// * `seed`: RANSAC seed; equal seeds give equal results.
///
/// See the module documentation for the algorithm and the refusals.
pub fn initialize_two_view(
    cam_k: &Matrix3<f64>,
    kp1: &[Point2<f64>],
    kp2: &[Point2<f64>],
    matches: &[(usize, usize)],
    params: &TwoViewParams,
    seed: u64,
) -> Result<TwoViewResult, GeometryError> {
    let n = matches.len();
    if n < 8 {
        return Err(GeometryError::NotEnoughPoints {
            found: n,
            needed: 8,
        });
    }
    let mut px1 = Vec::with_capacity(n);
    let mut px2 = Vec::with_capacity(n);
    for &(i, j) in matches {
        let a = kp1.get(i).ok_or(GeometryError::IndexOutOfRange {
            index: i,
            len: kp1.len(),
        })?;
        let b = kp2.get(j).ok_or(GeometryError::IndexOutOfRange {
            index: j,
            len: kp2.len(),
        })?;
        if !(a.x.is_finite() && a.y.is_finite() && b.x.is_finite() && b.y.is_finite()) {
            return Err(GeometryError::NonFinite);
        }
        px1.push([a.x, a.y]);
        px2.push([b.x, b.y]);
    }
    let k_inv = cam_k.try_inverse().ok_or(GeometryError::Degenerate {
        what: "singular intrinsics matrix",
    })?;

    // Normalised coordinates for the RANSAC fits.
    let mut pn1 = Vec::with_capacity(n);
    let mut pn2 = Vec::with_capacity(n);
    let t1 = normalize(&px1, &mut pn1);
    let t2 = normalize(&px2, &mut pn2);
    let t2_inv = t2.try_inverse().ok_or(GeometryError::Degenerate {
        what: "normalisation",
    })?;
    let t2_t = t2.transpose();

    let inv_sigma2 = 1.0 / (params.sigma_px * params.sigma_px);
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut pool: Vec<usize> = (0..n).collect();
    let mut cur = vec![false; n];
    let mut best_h = BestModel::new(n);
    let mut best_f = BestModel::new(n);
    let score_h = |h21: &Matrix3<f64>, cur: &mut Vec<bool>| {
        let h12 = h21.try_inverse()?;
        Some(score_homography(
            h21,
            &h12,
            &px1,
            &px2,
            inv_sigma2,
            params.chi2_two_dof,
            cur,
        ))
    };
    let score_f = |f21: &Matrix3<f64>, cur: &mut Vec<bool>| {
        score_fundamental(
            f21,
            &px1,
            &px2,
            inv_sigma2,
            params.chi2_one_dof,
            params.chi2_two_dof,
            cur,
        )
    };
    for _ in 0..params.ransac_iterations {
        for k in 0..8 {
            let j = rng.random_range(k..n);
            pool.swap(k, j);
        }
        let set = &pool[..8];
        if let Some(h21) = compute_h21(&pn1, &pn2, set, true).map(|hn| t2_inv * hn * t1)
            && let Some(s) = score_h(&h21, &mut cur)
        {
            best_h.offer(s, h21, &mut cur);
        }
        if let Some(f21) = compute_f21(&pn1, &pn2, set, true).map(|fn_| t2_t * fn_ * t1) {
            let s = score_f(&f21, &mut cur);
            best_f.offer(s, f21, &mut cur);
        }
    }
    // Least-squares refit of each model on its consensus set (Hartley &
    // Zisserman's final step, which ORB-SLAM omits): the 8-point minimal
    // fits are noisy with pixel-level noise. Kept only when the score rises.
    let mut idx_buf: Vec<usize> = Vec::with_capacity(n);
    for _ in 0..params.refit_rounds {
        best_h.inlier_indices(&mut idx_buf);
        let h_fit = (idx_buf.len() >= 8)
            .then(|| compute_h21(&pn1, &pn2, &idx_buf, false))
            .flatten()
            .map(|hn| t2_inv * hn * t1);
        if let Some(h21) = h_fit
            && let Some(s) = score_h(&h21, &mut cur)
        {
            best_h.offer(s, h21, &mut cur);
        }
        best_f.inlier_indices(&mut idx_buf);
        let f_fit = (idx_buf.len() >= 8)
            .then(|| compute_f21(&pn1, &pn2, &idx_buf, false))
            .flatten()
            .map(|fn_| t2_t * fn_ * t1);
        if let Some(f21) = f_fit {
            let s = score_f(&f21, &mut cur);
            best_f.offer(s, f21, &mut cur);
        }
    }
    let (best_sh, best_sf) = (best_h.score, best_f.score);
    let (best_h_in, best_f_in) = (best_h.inliers, best_f.inliers);
    let (best_h, best_f) = (best_h.model, best_f.model);
    if best_sh + best_sf <= 0.0 {
        return Err(GeometryError::TooFewInliers {
            found: 0,
            needed: params.min_triangulated,
        });
    }
    let rh = best_sh / (best_sh + best_sf);
    let model = if rh > params.homography_ratio_threshold {
        Model::Homography
    } else {
        Model::Fundamental
    };
    let xn1: Vec<Point2<f64>> = px1
        .iter()
        .map(|p| {
            let v = k_inv * Vector3::new(p[0], p[1], 1.0);
            Point2::new(v.x / v.z, v.y / v.z)
        })
        .collect();
    let xn2: Vec<Point2<f64>> = px2
        .iter()
        .map(|p| {
            let v = k_inv * Vector3::new(p[0], p[1], 1.0);
            Point2::new(v.x / v.z, v.y / v.z)
        })
        .collect();
    let fits = Fits {
        h: best_h,
        f: best_f,
        h_inliers: &best_h_in,
        f_inliers: &best_f_in,
        score_h: best_sh,
        score_f: best_sf,
    };
    let views = Views {
        k: cam_k,
        k_inv: &k_inv,
        px1: &px1,
        px2: &px2,
        xn1: &xn1,
        xn2: &xn2,
    };
    match reconstruct(model, &fits, &views, params) {
        // A plane with pixel-level noise in both images can score below the
        // ratio threshold and fall to F, which a plane cannot support: when
        // F fails, the homography gets its chance, under all its own checks.
        Err(e) if model == Model::Fundamental && params.homography_fallback => {
            reconstruct(Model::Homography, &fits, &views, params).map_err(|_| e)
        }
        other => other,
    }
}

/// The two models after RANSAC and refits.
struct Fits<'a> {
    h: Option<Matrix3<f64>>,
    f: Option<Matrix3<f64>>,
    h_inliers: &'a [bool],
    f_inliers: &'a [bool],
    score_h: f64,
    score_f: f64,
}

/// The matched keypoints, in pixels and normalised.
struct Views<'a> {
    k: &'a Matrix3<f64>,
    k_inv: &'a Matrix3<f64>,
    px1: &'a [[f64; 2]],
    px2: &'a [[f64; 2]],
    xn1: &'a [Point2<f64>],
    xn2: &'a [Point2<f64>],
}

/// Motion hypotheses of `model`, the best chosen and checked, then refined.
fn reconstruct(
    model: Model,
    fits: &Fits,
    views: &Views,
    params: &TwoViewParams,
) -> Result<TwoViewResult, GeometryError> {
    let Views {
        k: cam_k,
        k_inv,
        px1,
        px2,
        xn1,
        xn2,
    } = *views;
    let (best_h, best_f, best_sh, best_sf) = (fits.h, fits.f, fits.score_h, fits.score_f);
    let inliers = match model {
        Model::Homography => fits.h_inliers,
        Model::Fundamental => fits.f_inliers,
    };
    let n_inliers = inliers.iter().filter(|&&b| b).count();
    if n_inliers < params.min_triangulated {
        return Err(GeometryError::TooFewInliers {
            found: n_inliers,
            needed: params.min_triangulated,
        });
    }
    let ctx = CheckCtx {
        k: cam_k,
        px1,
        px2,
        xn1,
        xn2,
        inliers,
        th2: params.reprojection_chi2 * params.sigma_px * params.sigma_px,
        cos_with_depth: params.cos_parallax_with_depth,
        parallax_rank: params.parallax_rank,
    };
    let hyps: Vec<(Matrix3<f64>, Vector3<f64>)> = match model {
        Model::Homography => {
            let h = best_h.ok_or(GeometryError::Degenerate {
                what: "no homography",
            })?;
            decompose_h(&(k_inv * h * cam_k)).ok_or(GeometryError::NotEnoughParallax {
                parallax_deg: 0.0,
                needed_deg: params.min_parallax_deg,
            })?
        }
        Model::Fundamental => {
            let f = best_f.ok_or(GeometryError::Degenerate {
                what: "no fundamental matrix",
            })?;
            decompose_e(&(cam_k.transpose() * f * cam_k))
                .ok_or(GeometryError::Degenerate {
                    what: "essential matrix decomposition",
                })?
                .to_vec()
        }
    };
    let mut cos_buf = Vec::with_capacity(n_inliers);
    let mut best: Option<Hypothesis> = None;
    let mut second_good = 0usize;
    let mut n_similar = 0usize;
    let mut goods = Vec::with_capacity(hyps.len());
    for (r, t) in hyps {
        let h = check_rt(&ctx, r, t, &mut cos_buf);
        goods.push(h.n_good);
        match &best {
            Some(b) if b.n_good >= h.n_good => {
                second_good = second_good.max(h.n_good);
            }
            _ => {
                if let Some(b) = &best {
                    second_good = second_good.max(b.n_good);
                }
                best = Some(h);
            }
        }
    }
    let best = best.ok_or(GeometryError::Degenerate {
        what: "no motion hypothesis",
    })?;
    let max_good = best.n_good;
    for &g in &goods {
        if g as f64 > params.f_similar_fraction * max_good as f64 {
            n_similar += 1;
        }
    }
    let min_good = ((params.min_good_fraction * n_inliers as f64).ceil() as usize)
        .max(params.min_triangulated);
    // Refusals, most informative first.
    if max_good < params.min_triangulated {
        return Err(GeometryError::TooFewTriangulated {
            found: max_good,
            needed: params.min_triangulated,
        });
    }
    if best.parallax_deg < params.min_parallax_deg {
        return Err(GeometryError::NotEnoughParallax {
            parallax_deg: best.parallax_deg,
            needed_deg: params.min_parallax_deg,
        });
    }
    let ambiguous = match model {
        Model::Homography => second_good as f64 >= params.h_second_fraction * max_good as f64,
        Model::Fundamental => n_similar > 1,
    };
    if ambiguous {
        return Err(GeometryError::Ambiguous {
            best: max_good,
            second: second_good,
        });
    }
    let (best, max_good) = if max_good < min_good {
        // The 90 % rule judges the hypothesis by its triangulations, which
        // the minimal-fit motion puts a little off at pixel-level noise:
        // judge the bundle-adjusted motion of the same hypothesis instead.
        match recheck_refined(&ctx, best, params, &mut cos_buf) {
            Some(h) if h.n_good >= min_good && h.parallax_deg >= params.min_parallax_deg => {
                let g = h.n_good;
                (h, g)
            }
            _ => {
                return Err(GeometryError::TooFewTriangulated {
                    found: max_good,
                    needed: min_good,
                });
            }
        }
    } else {
        (best, max_good)
    };
    let rot = crate::lie::quaternion_from_matrix(&best.r);
    let mut cam2_from_cam1 = Isometry3::from_parts(Translation3::from(best.t), rot);
    let mut points = best.points;
    if params.refine_iterations > 0 {
        refine_two_view(cam_k, px1, px2, params, &mut cam2_from_cam1, &mut points);
    }
    Ok(TwoViewResult {
        cam2_from_cam1,
        points,
        model,
        inliers: inliers.to_vec(),
        score_h: best_sh,
        score_f: best_sf,
        parallax_deg: best.parallax_deg,
        n_good: max_good,
        n_second: second_good,
    })
}

/// The hypothesis `h` after a two-view bundle adjustment of its good
/// points, checked again on every inlier; `None` when the adjustment could
/// not run.
fn recheck_refined(
    ctx: &CheckCtx<'_>,
    h: Hypothesis,
    params: &TwoViewParams,
    cos_buf: &mut Vec<f64>,
) -> Option<Hypothesis> {
    if params.refine_iterations == 0 {
        return None;
    }
    let rot = crate::lie::quaternion_from_matrix(&h.r);
    let mut pose = Isometry3::from_parts(Translation3::from(h.t), rot);
    let before = pose;
    let mut points = h.points;
    refine_two_view(ctx.k, ctx.px1, ctx.px2, params, &mut pose, &mut points);
    if pose == before {
        return None;
    }
    Some(check_rt(
        ctx,
        pose.rotation.to_rotation_matrix().into_inner(),
        pose.translation.vector,
        cos_buf,
    ))
}

/// Two-view bundle adjustment of the initial reconstruction (ORB-SLAM runs
/// a global BA right after initialising): camera 1 fixed, camera 2 and the
/// points free, Huber kernel; then the translation is rescaled to unit norm
/// and points that no longer pass the depth and reprojection checks are
/// dropped.
fn refine_two_view(
    k: &Matrix3<f64>,
    px1: &[[f64; 2]],
    px2: &[[f64; 2]],
    params: &TwoViewParams,
    cam2_from_cam1: &mut Isometry3<f64>,
    points: &mut [Option<Point3<f64>>],
) {
    use crate::optimize::ba::{BaPose, BaProblem, Observation, bundle_adjust_lm};
    use crate::optimize::lm::LmParams;
    use crate::optimize::{Intrinsics, RobustKernel};
    let intr = Intrinsics {
        fx: k[(0, 0)],
        fy: k[(1, 1)],
        cx: k[(0, 2)],
        cy: k[(1, 2)],
    };
    let inv_sigma2 = 1.0 / (params.sigma_px * params.sigma_px);
    let mut prob = BaProblem {
        poses: vec![
            BaPose {
                cam_from_world: Isometry3::identity(),
                fixed: true,
            },
            BaPose {
                cam_from_world: *cam2_from_cam1,
                fixed: false,
            },
        ],
        points: Vec::new(),
        observations: Vec::new(),
        intrinsics: intr,
        priors: Vec::new(),
    };
    let mut which = Vec::new();
    for (i, p) in points.iter().enumerate() {
        if let Some(p) = p {
            let j = prob.points.len();
            prob.points.push(*p);
            which.push(i);
            for (pose, px) in [(0usize, px1[i]), (1usize, px2[i])] {
                prob.observations.push(Observation {
                    pose,
                    point: j,
                    uv: Point2::new(px[0], px[1]),
                    inv_sigma2,
                });
            }
        }
    }
    if prob.points.len() < params.min_triangulated {
        return;
    }
    let lm = LmParams {
        max_iterations: params.refine_iterations,
        ..LmParams::default()
    };
    let kernel = RobustKernel::Huber {
        delta: params.chi2_two_dof.sqrt(),
    };
    if bundle_adjust_lm(&mut prob, kernel, &lm).is_err() {
        return;
    }
    let t = prob.poses[1].cam_from_world.translation.vector;
    let norm = t.norm();
    if !(norm.is_finite() && norm > 0.0) {
        return;
    }
    let scale = 1.0 / norm;
    let refined = Isometry3::from_parts(
        Translation3::from(t * scale),
        prob.poses[1].cam_from_world.rotation,
    );
    let th2 = params.reprojection_chi2 * params.sigma_px * params.sigma_px;
    for (j, &i) in which.iter().enumerate() {
        let p = Point3::from(prob.points[j].coords * scale);
        let p2 = refined * p;
        let ok = p.z > 0.0 && p2.z > 0.0 && {
            let a = intr.project(&p.coords) - Point2::new(px1[i][0], px1[i][1]);
            let b = intr.project(&p2.coords) - Point2::new(px2[i][0], px2[i][1]);
            a.norm_squared() <= th2 && b.norm_squared() <= th2
        };
        points[i] = ok.then_some(p);
    }
    *cam2_from_cam1 = refined;
}

/// Tunables of [`find_homography`]. Defaults follow the two-view
/// initialiser's homography test (σ = 1 px, χ² 5.991 per direction).
#[derive(Debug, Clone, PartialEq)]
pub struct HomographyParams {
    /// RANSAC iterations (minimal samples of four pairs).
    pub ransac_iterations: usize,
    /// Standard deviation of the point positions, pixels.
    pub sigma_px: f64,
    /// Chi-square threshold (two degrees of freedom) of the symmetric
    /// transfer error of one direction.
    pub chi2_two_dof: f64,
    /// Least-squares refits on the consensus set (kept when the score rises).
    pub refit_rounds: usize,
    /// Fewest inliers accepted.
    pub min_inliers: usize,
}

impl Default for HomographyParams {
    fn default() -> Self {
        Self {
            ransac_iterations: 500,
            sigma_px: 1.0,
            chi2_two_dof: 5.991,
            refit_rounds: 3,
            min_inliers: 12,
        }
    }
}

/// A robust homography between two point sets.
#[derive(Debug, Clone, PartialEq)]
pub struct HomographyFit {
    /// `x2 ~ h21 · x1` (pixels to pixels).
    pub h21: Matrix3<f64>,
    /// Which pairs agree with it (both transfer directions).
    pub inliers: Vec<bool>,
    /// How many do.
    pub n_inliers: usize,
}

/// A homography `x2 ~ H·x1` from point pairs `(p1[i], p2[i])`, by the
/// two-view initialiser's machinery: seeded RANSAC over minimal 4-pair
/// samples (normalised DLT), symmetric-transfer scoring (ORB-SLAM's
/// `CheckHomography`), then least-squares refits on the consensus set.
pub fn find_homography(
    p1: &[Point2<f64>],
    p2: &[Point2<f64>],
    params: &HomographyParams,
    seed: u64,
) -> Result<HomographyFit, GeometryError> {
    let n = p1.len();
    if n != p2.len() {
        return Err(GeometryError::LengthMismatch {
            left: n,
            right: p2.len(),
        });
    }
    let needed = params.min_inliers.max(4);
    if n < needed {
        return Err(GeometryError::NotEnoughPoints { found: n, needed });
    }
    if p1
        .iter()
        .chain(p2)
        .any(|p| !(p.x.is_finite() && p.y.is_finite()))
    {
        return Err(GeometryError::NonFinite);
    }
    let px1: Vec<[f64; 2]> = p1.iter().map(|p| [p.x, p.y]).collect();
    let px2: Vec<[f64; 2]> = p2.iter().map(|p| [p.x, p.y]).collect();
    let mut pn1 = Vec::with_capacity(n);
    let mut pn2 = Vec::with_capacity(n);
    let t1 = normalize(&px1, &mut pn1);
    let t2 = normalize(&px2, &mut pn2);
    let t2_inv = t2.try_inverse().ok_or(GeometryError::Degenerate {
        what: "normalisation",
    })?;
    let inv_sigma2 = 1.0 / (params.sigma_px * params.sigma_px);
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut pool: Vec<usize> = (0..n).collect();
    let mut cur = vec![false; n];
    let mut best_in = vec![false; n];
    let mut best_score = 0.0f64;
    let mut best_h = None;
    let mut consider = |h21: Matrix3<f64>, cur: &mut Vec<bool>, best_in: &mut Vec<bool>| {
        if let Some(h12) = h21.try_inverse() {
            let s = score_homography(&h21, &h12, &px1, &px2, inv_sigma2, params.chi2_two_dof, cur);
            if s > best_score {
                best_score = s;
                best_h = Some(h21);
                std::mem::swap(cur, best_in);
            }
        }
    };
    for _ in 0..params.ransac_iterations {
        for k in 0..4 {
            let j = rng.random_range(k..n);
            pool.swap(k, j);
        }
        if let Some(hn) = compute_h21(&pn1, &pn2, &pool[..4], true) {
            consider(t2_inv * hn * t1, &mut cur, &mut best_in);
        }
    }
    let mut idx: Vec<usize> = Vec::with_capacity(n);
    for _ in 0..params.refit_rounds {
        idx.clear();
        idx.extend((0..n).filter(|&i| best_in[i]));
        if idx.len() < 4 {
            break;
        }
        if let Some(hn) = compute_h21(&pn1, &pn2, &idx, false) {
            consider(t2_inv * hn * t1, &mut cur, &mut best_in);
        }
    }
    let n_inliers = best_in.iter().filter(|&&b| b).count();
    match best_h {
        Some(h21) if n_inliers >= needed => Ok(HomographyFit {
            h21,
            inliers: best_in,
            n_inliers,
        }),
        _ => Err(GeometryError::TooFewInliers {
            found: n_inliers,
            needed,
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    #[test]
    fn faugeras_decomposition_contains_the_true_motion() {
        // Plane n·X = d in camera 1, motion (R, t): H = R + t·nᵀ/d.
        let r = UnitQuaternion::from_euler_angles(0.05, -0.1, 0.03)
            .to_rotation_matrix()
            .into_inner();
        let t = Vector3::new(0.3, -0.1, 0.05);
        let nrm = Vector3::new(0.1, -0.2, 1.0).normalize();
        let d = 4.0;
        let a = r + t * nrm.transpose() / d;
        let hyps = decompose_h(&(a * 1.7)).unwrap();
        assert_eq!(hyps.len(), 8);
        let tn = t.normalize();
        let found = hyps
            .iter()
            .any(|(rh, th)| (rh - r).norm() < 1e-9 && (th - tn).norm() < 1e-9);
        assert!(found, "{hyps:?}");
    }

    #[test]
    fn essential_decomposition_contains_the_true_motion() {
        let r = UnitQuaternion::from_euler_angles(-0.2, 0.1, 0.3)
            .to_rotation_matrix()
            .into_inner();
        let t = Vector3::new(-0.4, 0.2, 0.9).normalize();
        let e = crate::lie::skew(&t) * r;
        let hyps = decompose_e(&(e * -3.0)).unwrap();
        assert!(
            hyps.iter()
                .any(|(rh, th)| (rh - r).norm() < 1e-9 && (th - t).norm() < 1e-9)
        );
    }

    #[test]
    fn find_homography_recovers_a_known_one_among_outliers() {
        use rand::{Rng, SeedableRng, rngs::SmallRng};
        let h = Matrix3::new(1.05, 0.03, -12.0, -0.02, 0.98, 7.5, 1.5e-4, -8e-5, 1.0);
        let mut rng = SmallRng::seed_from_u64(9);
        let (mut p1, mut p2) = (Vec::new(), Vec::new());
        for i in 0..300 {
            let a = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
            let v = h * Vector3::new(a.x, a.y, 1.0);
            let mut b = Point2::new(v.x / v.z, v.y / v.z);
            if i % 10 < 3 {
                // 30 % outliers anywhere in the image
                b = Point2::new(rng.random_range(0.0..640.0), rng.random_range(0.0..480.0));
            } else {
                b.x += rng.random_range(-0.5..0.5);
                b.y += rng.random_range(-0.5..0.5);
            }
            p1.push(a);
            p2.push(b);
        }
        let fit = find_homography(&p1, &p2, &HomographyParams::default(), 1).unwrap();
        assert!(
            fit.n_inliers >= 200 && fit.n_inliers <= 215,
            "{}",
            fit.n_inliers
        );
        let est = fit.h21 / fit.h21[(2, 2)];
        for c in [(0.0, 0.0), (639.0, 0.0), (639.0, 479.0), (0.0, 479.0)] {
            let t = h * Vector3::new(c.0, c.1, 1.0);
            let e = est * Vector3::new(c.0, c.1, 1.0);
            let d = (t.xy() / t.z - e.xy() / e.z).norm();
            assert!(d < 0.3, "corner {c:?} off by {d} px");
        }
        assert!(matches!(
            find_homography(&p1[..5], &p2[..5], &HomographyParams::default(), 1),
            Err(GeometryError::NotEnoughPoints { .. })
        ));
        assert!(matches!(
            find_homography(&p1, &p2[..10], &HomographyParams::default(), 1),
            Err(GeometryError::LengthMismatch { .. })
        ));
        let mut bad = p1.clone();
        bad[3].x = f64::NAN;
        assert_eq!(
            find_homography(&bad, &p2, &HomographyParams::default(), 1),
            Err(GeometryError::NonFinite)
        );
    }
}
