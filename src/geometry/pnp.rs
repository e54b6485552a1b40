//! Perspective-n-Point: Lambda Twist P3P (Persson & Nordberg, ECCV 2018)
//! as the minimal solver inside seeded RANSAC with an adaptive iteration
//! count, EPnP (Lepetit, Moreno-Noguer & Fua, IJCV 2009) on the consensus
//! set, then Levenberg-Marquardt refinement of the pose on the inliers with
//! a Huber kernel ([`crate::optimize::pose::refine_pose`]).
//!
//! Inputs are world points and their observations as **normalised image
//! coordinates** `(x/z, y/z)` (undistorted pixel premultiplied by `K⁻¹`);
//! thresholds are given in pixels and converted with `focal_px`.

use nalgebra::{
    Isometry3, Matrix3, Point2, Point3, SMatrix, SVector, Translation3, Vector3, Vector4,
};
use rand::{Rng, SeedableRng, rngs::SmallRng};

use super::{GeometryError, all_finite2, all_finite3, umeyama};
use crate::optimize::lm::LmParams;
use crate::optimize::pose::{PoseObservation, refine_pose};
use crate::optimize::{Intrinsics, RobustKernel};

/// Tunables of [`solve_pnp_ransac`].
#[derive(Debug, Clone, PartialEq)]
pub struct PnpParams {
    /// Observation noise, pixels.
    pub sigma_px: f64,
    /// Inlier test: squared reprojection error ≤ `inlier_chi2·σ²`
    /// (5.991: 95 % with 2 DoF, ORB-SLAM's PnP threshold).
    pub inlier_chi2: f64,
    /// Required probability that one sample was outlier-free.
    pub confidence: f64,
    /// Minimum RANSAC iterations.
    pub min_iterations: usize,
    /// Maximum RANSAC iterations.
    pub max_iterations: usize,
    /// Fewest inliers accepted.
    pub min_inliers: usize,
    /// Huber threshold of the refinement, pixels.
    pub huber_px: f64,
    /// Refinement rounds at most (refine, re-collect inliers, until stable).
    pub refine_rounds: usize,
    /// Inlier test after each refinement: squared reprojection error ≤
    /// `refined_inlier_chi2·σ²`. The refined pose is accurate to a fraction
    /// of the noise, so a wider bound than RANSAC's (9.21: 99 % with 2 DoF)
    /// keeps the tail of the true inliers that 5.991 drops (one in twenty),
    /// whose loss otherwise costs precision; outliers spread over the image
    /// rarely land that close.
    pub refined_inlier_chi2: f64,
    /// LM iterations per refinement round.
    pub refine_iterations: usize,
}

impl Default for PnpParams {
    fn default() -> Self {
        Self {
            sigma_px: 1.0,
            inlier_chi2: 5.991,
            confidence: 0.9999,
            min_iterations: 10,
            max_iterations: 1000,
            min_inliers: 10,
            huber_px: 5.991f64.sqrt(),
            refine_rounds: 4,
            refined_inlier_chi2: 9.21,
            refine_iterations: 10,
        }
    }
}

/// Result of [`solve_pnp_ransac`].
#[derive(Debug, Clone, PartialEq)]
pub struct PnpResult {
    /// The camera pose.
    pub cam_from_world: Isometry3<f64>,
    /// Per correspondence: inlier of the final pose.
    pub inliers: Vec<bool>,
    /// Number of inliers.
    pub n_inliers: usize,
    /// RANSAC iterations run.
    pub iterations: usize,
}

/// A pose `(R, t)` with `p_cam = R·p_world + t`.
pub type RotTrans = (Matrix3<f64>, Vector3<f64>);

/// Real roots of `a·x³ + b·x² + c·x + d` (falls back to the quadratic when
/// `a` vanishes), each polished by two Newton steps.
fn cubic_roots(a: f64, b: f64, c: f64, d: f64) -> ([f64; 3], usize) {
    let mut out = [0.0; 3];
    let scale = a.abs().max(b.abs()).max(c.abs()).max(d.abs());
    if scale == 0.0 || !scale.is_finite() {
        return (out, 0);
    }
    if a.abs() < 1e-14 * scale {
        return quadratic_roots3(b, c, d);
    }
    let (b, c, d) = (b / a, c / a, d / a);
    let q = (3.0 * c - b * b) / 9.0;
    let r = (9.0 * b * c - 27.0 * d - 2.0 * b * b * b) / 54.0;
    let disc = q * q * q + r * r;
    let shift = -b / 3.0;
    let n = if disc >= 0.0 {
        let sq = disc.sqrt();
        let s = (r + sq).cbrt();
        let t = (r - sq).cbrt();
        out[0] = shift + s + t;
        1
    } else {
        let theta = (r / (-q * q * q).sqrt()).clamp(-1.0, 1.0).acos();
        let m = 2.0 * (-q).sqrt();
        for (k, o) in out.iter_mut().enumerate() {
            *o = shift + m * ((theta + 2.0 * std::f64::consts::PI * k as f64) / 3.0).cos();
        }
        3
    };
    for x in out.iter_mut().take(n) {
        for _ in 0..2 {
            let f = ((*x + b) * *x + c) * *x + d;
            let df = (3.0 * *x + 2.0 * b) * *x + c;
            if df.abs() > 1e-300 {
                *x -= f / df;
            }
        }
    }
    (out, n)
}

fn quadratic_roots3(a: f64, b: f64, c: f64) -> ([f64; 3], usize) {
    let (r, n) = quadratic_roots(a, b, c);
    ([r[0], r[1], 0.0], n)
}

/// Real roots of `a·x² + b·x + c` (numerically stable form).
fn quadratic_roots(a: f64, b: f64, c: f64) -> ([f64; 2], usize) {
    let scale = a.abs().max(b.abs()).max(c.abs());
    if scale == 0.0 {
        return ([0.0; 2], 0);
    }
    if a.abs() < 1e-14 * scale {
        if b.abs() < 1e-300 {
            return ([0.0; 2], 0);
        }
        return ([-c / b, 0.0], 1);
    }
    let disc = b * b - 4.0 * a * c;
    if disc < 0.0 {
        return ([0.0; 2], 0);
    }
    let sq = disc.sqrt();
    let q = -0.5 * (b + b.signum() * sq);
    if q == 0.0 {
        return ([0.0, 0.0], 1);
    }
    ([q / a, c / q], 2)
}

#[inline]
fn det_cols(a: &Vector3<f64>, b: &Vector3<f64>, c: &Vector3<f64>) -> f64 {
    a.dot(&b.cross(c))
}

/// Lambda Twist P3P: the poses that map the three world points `x` onto the
/// three unit bearings `y`. Returns up to four solutions.
pub fn p3p_lambda_twist(y: &[Vector3<f64>; 3], x: &[Vector3<f64>; 3]) -> ([RotTrans; 4], usize) {
    let mut sols = [(Matrix3::zeros(), Vector3::zeros()); 4];
    let mut ns = 0usize;
    let b12 = -2.0 * y[0].dot(&y[1]);
    let b13 = -2.0 * y[0].dot(&y[2]);
    let b23 = -2.0 * y[1].dot(&y[2]);
    let d12 = x[0] - x[1];
    let d13 = x[0] - x[2];
    let d23 = x[1] - x[2];
    let a12 = d12.norm_squared();
    let a13 = d13.norm_squared();
    let a23 = d23.norm_squared();
    // λᵀ·M_ij·λ = a_ij; D1 = a23·M12 - a12·M23, D2 = a23·M13 - a13·M23.
    let m12 = Matrix3::new(1.0, 0.5 * b12, 0.0, 0.5 * b12, 1.0, 0.0, 0.0, 0.0, 0.0);
    let m13 = Matrix3::new(1.0, 0.0, 0.5 * b13, 0.0, 0.0, 0.0, 0.5 * b13, 0.0, 1.0);
    let m23 = Matrix3::new(0.0, 0.0, 0.0, 0.0, 1.0, 0.5 * b23, 0.0, 0.5 * b23, 1.0);
    let d1 = m12 * a23 - m23 * a12;
    let d2 = m13 * a23 - m23 * a13;
    // det(D1 + γ·D2) = c3·γ³ + c2·γ² + c1·γ + c0
    let (p0, p1, p2) = (
        d1.column(0).into_owned(),
        d1.column(1).into_owned(),
        d1.column(2).into_owned(),
    );
    let (q0, q1, q2) = (
        d2.column(0).into_owned(),
        d2.column(1).into_owned(),
        d2.column(2).into_owned(),
    );
    let c0 = det_cols(&p0, &p1, &p2);
    let c3 = det_cols(&q0, &q1, &q2);
    let c1 = det_cols(&q0, &p1, &p2) + det_cols(&p0, &q1, &p2) + det_cols(&p0, &p1, &q2);
    let c2 = det_cols(&p0, &q1, &q2) + det_cols(&q0, &p1, &q2) + det_cols(&q0, &q1, &p2);
    let (roots, nr) = cubic_roots(c3, c2, c1, c0);
    // Pick a root that makes D0 indefinite (two lines through the origin).
    let mut chosen = None;
    for &gamma in roots.iter().take(nr) {
        let d0 = d1 + d2 * gamma;
        if let Some(c) = split_degenerate_conic(&d0) {
            chosen = Some(c);
            break;
        }
    }
    let Some((u1, u2, s)) = chosen else {
        return (sols, 0);
    };
    // X matrix for the pose recovery (shared by all solutions).
    let xmat = Matrix3::from_columns(&[d12, d13, d12.cross(&d13)]);
    let Some(xinv) = xmat.try_inverse() else {
        return (sols, 0);
    };
    for sign in [1.0, -1.0] {
        let n = u1 - u2 * (s * sign);
        if n.x.abs() < 1e-12 * n.norm() {
            continue;
        }
        let w0 = -n.y / n.x;
        let w1 = -n.z / n.x;
        // a23·[(w0τ+w1)² + b13(w0τ+w1) + 1] = a13·[τ² + b23τ + 1]
        let qa = a23 * w0 * w0 - a13;
        let qb = a23 * (2.0 * w0 * w1 + b13 * w0) - a13 * b23;
        let qc = a23 * (w1 * w1 + b13 * w1 + 1.0) - a13;
        let (taus, nt) = quadratic_roots(qa, qb, qc);
        for &tau in taus.iter().take(nt) {
            if tau.is_nan() || tau <= 0.0 {
                continue;
            }
            let den = tau * tau + b23 * tau + 1.0;
            if den.is_nan() || den <= 0.0 {
                continue;
            }
            let l3 = (a23 / den).sqrt();
            let l2 = tau * l3;
            let l1 = w0 * l2 + w1 * l3;
            if l1.is_nan() || l1 <= 0.0 {
                continue;
            }
            let mut l = Vector3::new(l1, l2, l3);
            refine_lambdas(&mut l, b12, b13, b23, a12, a13, a23);
            if !(l.x > 0.0 && l.y > 0.0 && l.z > 0.0) {
                continue;
            }
            let z1 = y[0] * l.x - y[1] * l.y;
            let z2 = y[0] * l.x - y[2] * l.z;
            let ymat = Matrix3::from_columns(&[z1, z2, z1.cross(&z2)]);
            let r = ymat * xinv;
            let t = y[0] * l.x - r * x[0];
            if r.iter().all(|v| v.is_finite()) && t.iter().all(|v| v.is_finite()) && ns < 4 {
                sols[ns] = (r, t);
                ns += 1;
            }
        }
    }
    (sols, ns)
}

/// For a symmetric 3×3 `D` of rank 2 (one eigenvalue ~0), returns the
/// eigenvectors of the two others and `s = √(-σ₂/σ₁)`, or `None` when they
/// have the same sign (the conic `λᵀDλ = 0` is then not a line pair).
/// Closed form: `σ₁,₂` are the roots of `σ² - tr(D)·σ + m₂ = 0` (`m₂` the sum
/// of the principal 2×2 minors, since `det D = 0`), eigenvectors from the
/// largest cross product of two rows of `D - σI`.
fn split_degenerate_conic(d: &Matrix3<f64>) -> Option<(Vector3<f64>, Vector3<f64>, f64)> {
    let tr = d[(0, 0)] + d[(1, 1)] + d[(2, 2)];
    let m2 = d[(0, 0)] * d[(1, 1)] - d[(0, 1)] * d[(1, 0)] + d[(0, 0)] * d[(2, 2)]
        - d[(0, 2)] * d[(2, 0)]
        + d[(1, 1)] * d[(2, 2)]
        - d[(1, 2)] * d[(2, 1)];
    if m2 >= 0.0 {
        return None;
    }
    let sq = (tr * tr - 4.0 * m2).sqrt();
    let s1 = 0.5 * (tr + sq);
    let s2 = 0.5 * (tr - sq);
    let eigvec = |sigma: f64| -> Option<Vector3<f64>> {
        let a = d - Matrix3::identity() * sigma;
        let (r0, r1, r2) = (
            a.row(0).transpose(),
            a.row(1).transpose(),
            a.row(2).transpose(),
        );
        let c = [r0.cross(&r1), r0.cross(&r2), r1.cross(&r2)];
        let best = c
            .iter()
            .max_by(|x, y| x.norm_squared().total_cmp(&y.norm_squared()))?;
        let n = best.norm();
        (n > 0.0 && n.is_finite()).then(|| best / n)
    };
    let (u1, u2) = (eigvec(s1)?, eigvec(s2)?);
    Some((u1, u2, (-s2 / s1).sqrt()))
}

/// Gauss-Newton on the three law-of-cosines equations.
fn refine_lambdas(
    l: &mut Vector3<f64>,
    b12: f64,
    b13: f64,
    b23: f64,
    a12: f64,
    a13: f64,
    a23: f64,
) {
    for _ in 0..5 {
        let (l1, l2, l3) = (l.x, l.y, l.z);
        let r = Vector3::new(
            l1 * l1 + l2 * l2 + b12 * l1 * l2 - a12,
            l1 * l1 + l3 * l3 + b13 * l1 * l3 - a13,
            l2 * l2 + l3 * l3 + b23 * l2 * l3 - a23,
        );
        if r.amax() < 1e-15 * (a12 + a13 + a23) {
            break;
        }
        let j = Matrix3::new(
            2.0 * l1 + b12 * l2,
            2.0 * l2 + b12 * l1,
            0.0,
            2.0 * l1 + b13 * l3,
            0.0,
            2.0 * l3 + b13 * l1,
            0.0,
            2.0 * l2 + b23 * l3,
            2.0 * l3 + b23 * l2,
        );
        let Some(ji) = j.try_inverse() else { break };
        *l -= ji * r;
    }
}

/// EPnP on the correspondences `idx` (≥ 4, ≥ 6 recommended): control points
/// from the centroid and principal axes, the 12×12 `MᵀM` null space, the
/// N = 1, 2, 3 approximations of the betas each refined by Gauss-Newton, and
/// the best (least reprojection error) solution.
pub fn epnp(pw: &[Point3<f64>], xn: &[Point2<f64>], idx: &[usize]) -> Option<RotTrans> {
    let n = idx.len();
    if n < 4 {
        return None;
    }
    // Control points.
    let mut c0 = Vector3::zeros();
    for &i in idx {
        c0 += pw[i].coords;
    }
    c0 /= n as f64;
    let mut cov = Matrix3::zeros();
    for &i in idx {
        let d = pw[i].coords - c0;
        cov += d * d.transpose();
    }
    let eig = cov.symmetric_eigen();
    let mut ctrl = [c0; 4];
    for k in 0..3 {
        let sd = (eig.eigenvalues[k].max(0.0) / n as f64).sqrt();
        if sd.is_nan() || sd <= 1e-12 * (1.0 + c0.norm()) {
            return None; // planar-degenerate along an axis is handled by PCA > 0; a line is not.
        }
        ctrl[k + 1] = c0 + eig.eigenvectors.column(k) * sd;
    }
    let basis = Matrix3::from_columns(&[ctrl[1] - c0, ctrl[2] - c0, ctrl[3] - c0]);
    let binv = basis.try_inverse()?;
    let mut alphas = Vec::with_capacity(n);
    // MᵀM has 3×3 blocks (j, k) = Σ αⱼαₖ·[[1, 0, -u], [0, 1, -v], [-u, -v, u²+v²]]:
    // accumulate the four sums per block pair instead of 24-wide outer products.
    let mut acc = [[0.0f64; 4]; 10];
    for &i in idx {
        let a = binv * (pw[i].coords - c0);
        let al = Vector4::new(1.0 - a.x - a.y - a.z, a.x, a.y, a.z);
        alphas.push(al);
        let (u, v) = (xn[i].x, xn[i].y);
        let w = u * u + v * v;
        let mut p = 0;
        for j in 0..4 {
            for k in j..4 {
                let aa = al[j] * al[k];
                acc[p][0] += aa;
                acc[p][1] += aa * u;
                acc[p][2] += aa * v;
                acc[p][3] += aa * w;
                p += 1;
            }
        }
    }
    let mut mtm = SMatrix::<f64, 12, 12>::zeros();
    let mut p = 0;
    for j in 0..4 {
        for k in j..4 {
            let [s, su, sv, sw] = acc[p];
            p += 1;
            let blk = Matrix3::new(s, 0.0, -su, 0.0, s, -sv, -su, -sv, sw);
            mtm.fixed_view_mut::<3, 3>(3 * j, 3 * k).copy_from(&blk);
            if k != j {
                mtm.fixed_view_mut::<3, 3>(3 * k, 3 * j)
                    .copy_from(&blk.transpose());
            }
        }
    }
    let e = mtm.symmetric_eigen();
    let mut order: [usize; 12] = std::array::from_fn(|i| i);
    order.sort_by(|&a, &b| e.eigenvalues[a].total_cmp(&e.eigenvalues[b]));
    // v[k]: the k-th smallest eigenvector, as 4 control points.
    let v: [[Vector3<f64>; 4]; 4] = std::array::from_fn(|k| {
        let col = e.eigenvectors.column(order[k]);
        std::array::from_fn(|j| Vector3::new(col[3 * j], col[3 * j + 1], col[3 * j + 2]))
    });
    const PAIRS: [(usize, usize); 6] = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)];
    let mut rho = SVector::<f64, 6>::zeros();
    let mut l = SMatrix::<f64, 6, 10>::zeros();
    for (p, &(a, b)) in PAIRS.iter().enumerate() {
        rho[p] = (ctrl[a] - ctrl[b]).norm_squared();
        let dv: [Vector3<f64>; 4] = std::array::from_fn(|k| v[k][a] - v[k][b]);
        l[(p, 0)] = dv[0].dot(&dv[0]);
        l[(p, 1)] = 2.0 * dv[0].dot(&dv[1]);
        l[(p, 2)] = dv[1].dot(&dv[1]);
        l[(p, 3)] = 2.0 * dv[0].dot(&dv[2]);
        l[(p, 4)] = 2.0 * dv[1].dot(&dv[2]);
        l[(p, 5)] = dv[2].dot(&dv[2]);
        l[(p, 6)] = 2.0 * dv[0].dot(&dv[3]);
        l[(p, 7)] = 2.0 * dv[1].dot(&dv[3]);
        l[(p, 8)] = 2.0 * dv[2].dot(&dv[3]);
        l[(p, 9)] = dv[3].dot(&dv[3]);
    }
    let lsq = |cols: &[usize]| -> Option<Vec<f64>> {
        let m = cols.len();
        let a = nalgebra::DMatrix::from_fn(6, m, |r, c| l[(r, cols[c])]);
        let ata = a.transpose() * &a;
        let atb = a.transpose() * nalgebra::DVector::from_column_slice(rho.as_slice());
        let sol = ata.cholesky()?.solve(&atb);
        Some(sol.iter().copied().collect())
    };
    let mut candidates: Vec<Vector4<f64>> = Vec::with_capacity(3);
    // N = 4 approximation (betas 11, 12, 13, 14).
    if let Some(b) = lsq(&[0, 1, 3, 6]) {
        let (b1, sgn) = if b[0] < 0.0 {
            ((-b[0]).sqrt(), -1.0)
        } else {
            (b[0].sqrt(), 1.0)
        };
        if b1 > 0.0 {
            candidates.push(Vector4::new(
                b1,
                sgn * b[1] / b1,
                sgn * b[2] / b1,
                sgn * b[3] / b1,
            ));
        }
    }
    // N = 2 approximation (betas 11, 12, 22).
    if let Some(b) = lsq(&[0, 1, 2]) {
        let (mut b1, mut b2) = (b[0].abs().sqrt(), b[2].abs().sqrt());
        if b[1] < 0.0 {
            b2 = -b2;
        }
        if b[0] < 0.0 {
            b1 = -b1;
            b2 = -b2;
        }
        candidates.push(Vector4::new(b1, b2, 0.0, 0.0));
    }
    // N = 3 approximation (betas 11, 12, 22, 13, 23).
    if let Some(b) = lsq(&[0, 1, 2, 3, 4]) {
        let (mut b1, mut b2) = (b[0].abs().sqrt(), b[2].abs().sqrt());
        if b[1] < 0.0 {
            b2 = -b2;
        }
        if b[0] < 0.0 {
            b1 = -b1;
            b2 = -b2;
        }
        let b3 = if b1.abs() > 0.0 { b[3] / b1 } else { 0.0 };
        candidates.push(Vector4::new(b1, b2, b3, 0.0));
    }
    let mut best: Option<(f64, RotTrans)> = None;
    let mut pc = Vec::with_capacity(n);
    let pwv: Vec<Point3<f64>> = idx.iter().map(|&i| pw[i]).collect();
    for mut beta in candidates {
        gauss_newton_betas(&l, &rho, &mut beta);
        let cc: [Vector3<f64>; 4] = std::array::from_fn(|j| {
            v[0][j] * beta[0] + v[1][j] * beta[1] + v[2][j] * beta[2] + v[3][j] * beta[3]
        });
        pc.clear();
        for al in &alphas {
            pc.push(Point3::from(
                cc[0] * al[0] + cc[1] * al[1] + cc[2] * al[2] + cc[3] * al[3],
            ));
        }
        // Points must lie in front: flip the global sign if needed.
        let neg = pc.iter().filter(|p| p.z < 0.0).count();
        if neg * 2 > n {
            for p in pc.iter_mut() {
                p.coords = -p.coords;
            }
        }
        let Ok(sim) = umeyama(&pwv, &pc, false) else {
            continue;
        };
        let r = sim.rotation.to_rotation_matrix().into_inner();
        let t = sim.translation;
        let mut err = 0.0;
        for &i in idx {
            let q = r * pw[i].coords + t;
            let iz = 1.0 / q.z;
            // Sum of squared errors: the selection needs an order, not a mean.
            err += (q.x * iz - xn[i].x).powi(2) + (q.y * iz - xn[i].y).powi(2);
        }
        if err.is_finite() && best.as_ref().is_none_or(|(e, _)| err < *e) {
            best = Some((err, (r, t)));
        }
    }
    best.map(|(_, rt)| rt)
}

/// Gauss-Newton on the 6 distance constraints `L·b(β) = ρ`.
fn gauss_newton_betas(l: &SMatrix<f64, 6, 10>, rho: &SVector<f64, 6>, beta: &mut Vector4<f64>) {
    for _ in 0..5 {
        let (b1, b2, b3, b4) = (beta[0], beta[1], beta[2], beta[3]);
        let bb = SVector::<f64, 10>::from([
            b1 * b1,
            b1 * b2,
            b2 * b2,
            b1 * b3,
            b2 * b3,
            b3 * b3,
            b1 * b4,
            b2 * b4,
            b3 * b4,
            b4 * b4,
        ]);
        let mut a = SMatrix::<f64, 6, 4>::zeros();
        let mut r = SVector::<f64, 6>::zeros();
        for p in 0..6 {
            let lr = l.row(p);
            a[(p, 0)] = 2.0 * lr[0] * b1 + lr[1] * b2 + lr[3] * b3 + lr[6] * b4;
            a[(p, 1)] = lr[1] * b1 + 2.0 * lr[2] * b2 + lr[4] * b3 + lr[7] * b4;
            a[(p, 2)] = lr[3] * b1 + lr[4] * b2 + 2.0 * lr[5] * b3 + lr[8] * b4;
            a[(p, 3)] = lr[6] * b1 + lr[7] * b2 + lr[8] * b3 + 2.0 * lr[9] * b4;
            r[p] = rho[p] - lr.dot(&bb.transpose());
        }
        // Least squares via QR-free normal equations (4×4, well-scaled).
        let ata = a.transpose() * a;
        let Some(ch) = ata.cholesky() else { break };
        let d = ch.solve(&(a.transpose() * r));
        if !d.iter().all(|x| x.is_finite()) {
            break;
        }
        *beta += d;
    }
}

/// Counts inliers of a pose (and fills `mask`): in front of the camera and
/// squared normalised reprojection error ≤ `th2`.
fn count_inliers(
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    pw: &[Point3<f64>],
    xn: &[Point2<f64>],
    th2: f64,
    mask: &mut [bool],
) -> usize {
    let mut n = 0;
    for ((p, x), m) in pw.iter().zip(xn).zip(mask.iter_mut()) {
        let q = r * p.coords + t;
        let ok = q.z > 0.0 && {
            let iz = 1.0 / q.z;
            let dx = q.x * iz - x.x;
            let dy = q.y * iz - x.y;
            dx * dx + dy * dy <= th2
        };
        *m = ok;
        n += usize::from(ok);
    }
    n
}

/// As [`count_inliers`], but gives up (`None`) as soon as the hypothesis
/// can no longer beat `best` inliers: most RANSAC hypotheses are wrong and
/// are dropped after about `n - best` points.
#[allow(clippy::too_many_arguments)]
fn count_inliers_beating(
    r: &Matrix3<f64>,
    t: &Vector3<f64>,
    pw: &[Point3<f64>],
    xn: &[Point2<f64>],
    th2: f64,
    best: usize,
    mask: &mut [bool],
) -> Option<usize> {
    let n = pw.len();
    let mut c = 0;
    for (i, ((p, x), m)) in pw.iter().zip(xn).zip(mask.iter_mut()).enumerate() {
        let q = r * p.coords + t;
        let ok = q.z > 0.0 && {
            let iz = 1.0 / q.z;
            let dx = q.x * iz - x.x;
            let dy = q.y * iz - x.y;
            dx * dx + dy * dy <= th2
        };
        *m = ok;
        c += usize::from(ok);
        // Points left after this one: n - i - 1.
        if c + (n - i - 1) <= best {
            return None;
        }
    }
    Some(c)
}

fn to_iso(r: &Matrix3<f64>, t: &Vector3<f64>) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::from(*t),
        crate::lie::quaternion_from_matrix(r),
    )
}

/// Robust PnP: P3P-RANSAC, EPnP on the consensus set, Huber-LM refinement.
///
/// * `points_world`: 3-D points, world frame.
/// * `obs_normalized`: their observations as normalised coordinates.
/// * `focal_px`: focal length used to express the pixel thresholds.
/// * `seed`: RANSAC seed.
///
/// Errors: [`GeometryError::LengthMismatch`], [`GeometryError::NotEnoughPoints`]
/// (fewer than 4), [`GeometryError::NonFinite`],
/// [`GeometryError::TooFewInliers`].
pub fn solve_pnp_ransac(
    points_world: &[Point3<f64>],
    obs_normalized: &[Point2<f64>],
    focal_px: f64,
    params: &PnpParams,
    seed: u64,
) -> Result<PnpResult, GeometryError> {
    let n = points_world.len();
    if n != obs_normalized.len() {
        return Err(GeometryError::LengthMismatch {
            left: n,
            right: obs_normalized.len(),
        });
    }
    let needed = params.min_inliers.max(4);
    if n < needed {
        return Err(GeometryError::NotEnoughPoints { found: n, needed });
    }
    if !all_finite3(points_world)
        || !all_finite2(obs_normalized)
        || !focal_px.is_finite()
        || focal_px <= 0.0
    {
        return Err(GeometryError::NonFinite);
    }
    let th2 = params.inlier_chi2 * params.sigma_px * params.sigma_px / (focal_px * focal_px);
    let bearings: Vec<Vector3<f64>> = obs_normalized
        .iter()
        .map(|x| Vector3::new(x.x, x.y, 1.0).normalize())
        .collect();
    let mut rng = SmallRng::seed_from_u64(seed);
    let mut pool: Vec<usize> = (0..n).collect();
    let mut mask = vec![false; n];
    let mut best_mask = vec![false; n];
    let mut best_n = 0usize;
    let mut best_rt: Option<RotTrans> = None;
    let mut max_iter = params.max_iterations;
    let mut it = 0;
    let log_fail = (1.0 - params.confidence).max(1e-300).ln();
    while it
        < max_iter
            .max(params.min_iterations)
            .min(params.max_iterations)
    {
        it += 1;
        for k in 0..3 {
            let j = rng.random_range(k..n);
            pool.swap(k, j);
        }
        let (i0, i1, i2) = (pool[0], pool[1], pool[2]);
        let y = [bearings[i0], bearings[i1], bearings[i2]];
        let x = [
            points_world[i0].coords,
            points_world[i1].coords,
            points_world[i2].coords,
        ];
        let (sols, ns) = p3p_lambda_twist(&y, &x);
        for (r, t) in sols.iter().take(ns) {
            let Some(c) =
                count_inliers_beating(r, t, points_world, obs_normalized, th2, best_n, &mut mask)
            else {
                continue;
            };
            if c > best_n {
                best_n = c;
                best_rt = Some((*r, *t));
                std::mem::swap(&mut mask, &mut best_mask);
                let w = best_n as f64 / n as f64;
                let denom = (1.0 - w * w * w).max(1e-300).ln();
                let need = if denom < 0.0 {
                    (log_fail / denom).ceil()
                } else {
                    0.0
                };
                max_iter = if need.is_finite() && need < params.max_iterations as f64 {
                    need as usize
                } else {
                    params.max_iterations
                };
            }
        }
    }
    let Some(mut rt) = best_rt else {
        return Err(GeometryError::TooFewInliers { found: 0, needed });
    };
    if best_n < needed {
        return Err(GeometryError::TooFewInliers {
            found: best_n,
            needed,
        });
    }
    // EPnP on the consensus set; keep it if it does at least as well.
    let inl: Vec<usize> = (0..n).filter(|&i| best_mask[i]).collect();
    if let Some((r, t)) = epnp(points_world, obs_normalized, &inl) {
        let c = count_inliers(&r, &t, points_world, obs_normalized, th2, &mut mask);
        if c >= best_n {
            best_n = c;
            rt = (r, t);
            std::mem::swap(&mut mask, &mut best_mask);
        }
    }
    // Huber-LM refinement in pixel units (f·normalised).
    let intr = Intrinsics {
        fx: focal_px,
        fy: focal_px,
        cx: 0.0,
        cy: 0.0,
    };
    let obs: Vec<PoseObservation> = points_world
        .iter()
        .zip(obs_normalized)
        .map(|(p, x)| PoseObservation {
            p_world: *p,
            uv: Point2::new(x.x * focal_px, x.y * focal_px),
            inv_sigma2: 1.0 / (params.sigma_px * params.sigma_px),
        })
        .collect();
    let mut pose = to_iso(&rt.0, &rt.1);
    let lm = LmParams {
        max_iterations: params.refine_iterations,
        ..LmParams::default()
    };
    // Refine on the inliers, re-collect them, and repeat until the set is
    // stable: the pose returned is then the Huber/ML pose of the mask
    // returned.
    let kernel = RobustKernel::Huber {
        delta: params.huber_px / params.sigma_px,
    };
    let th2_refined =
        params.refined_inlier_chi2 * params.sigma_px * params.sigma_px / (focal_px * focal_px);
    for _ in 0..params.refine_rounds {
        let (p, _) = refine_pose(pose, &obs, &best_mask, &intr, kernel, &lm);
        let r = p.rotation.to_rotation_matrix().into_inner();
        let c = count_inliers(
            &r,
            &p.translation.vector,
            points_world,
            obs_normalized,
            th2_refined,
            &mut mask,
        );
        // The refined pose is the better estimate; a collapse of the
        // consensus (a diverged refinement) is the only reason to refuse it.
        if c * 10 < best_n * 9 {
            break;
        }
        pose = p;
        best_n = c;
        let stable = mask == best_mask;
        std::mem::swap(&mut mask, &mut best_mask);
        if stable {
            break;
        }
    }
    if best_n < needed {
        return Err(GeometryError::TooFewInliers {
            found: best_n,
            needed,
        });
    }
    Ok(PnpResult {
        cam_from_world: pose,
        inliers: best_mask,
        n_inliers: best_n,
        iterations: it,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;

    fn scene() -> (Isometry3<f64>, Vec<Point3<f64>>) {
        let pose = Isometry3::from_parts(
            Translation3::new(0.3, -0.2, 1.0),
            UnitQuaternion::from_euler_angles(0.2, -0.3, 0.1),
        );
        let pts = vec![
            Point3::new(0.5, 0.2, 4.0),
            Point3::new(-1.0, 0.7, 5.0),
            Point3::new(0.8, -0.9, 6.0),
            Point3::new(-0.3, -0.4, 3.5),
            Point3::new(1.2, 1.1, 7.0),
            Point3::new(-1.5, -1.2, 4.5),
            Point3::new(0.1, 1.4, 5.5),
            Point3::new(0.9, -0.1, 3.2),
        ];
        (
            pose,
            pts.into_iter()
                .map(|p| pose.inverse_transform_point(&p))
                .collect(),
        )
    }

    #[test]
    fn lambda_twist_finds_the_true_pose() {
        let (pose, pw) = scene();
        let r_true = pose.rotation.to_rotation_matrix().into_inner();
        let y: [Vector3<f64>; 3] = std::array::from_fn(|i| (pose * pw[i]).coords.normalize());
        let x: [Vector3<f64>; 3] = std::array::from_fn(|i| pw[i].coords);
        let (sols, n) = p3p_lambda_twist(&y, &x);
        assert!(n >= 1);
        let ok = sols.iter().take(n).any(|(r, t)| {
            (r - r_true).norm() < 1e-8 && (t - pose.translation.vector).norm() < 1e-8
        });
        assert!(ok, "{:?}", &sols[..n]);
        // Every returned solution reproduces the three bearings.
        for (r, t) in sols.iter().take(n) {
            for i in 0..3 {
                let b = (r * x[i] + t).normalize();
                assert!((b - y[i]).norm() < 1e-8);
            }
        }
    }

    #[test]
    fn epnp_is_exact_on_exact_data() {
        let (pose, pw) = scene();
        let xn: Vec<Point2<f64>> = pw
            .iter()
            .map(|p| {
                let q = pose * p;
                Point2::new(q.x / q.z, q.y / q.z)
            })
            .collect();
        let idx: Vec<usize> = (0..pw.len()).collect();
        let (r, t) = epnp(&pw, &xn, &idx).unwrap();
        assert!((r - pose.rotation.to_rotation_matrix().into_inner()).norm() < 1e-6);
        assert!((t - pose.translation.vector).norm() < 1e-6);
    }

    #[test]
    fn cubic_roots_are_roots() {
        let (r, n) = cubic_roots(2.0, -4.0, -22.0, 24.0); // 2(x-1)(x+3)(x-4)
        assert_eq!(n, 3);
        let mut v = r.to_vec();
        v.sort_by(f64::total_cmp);
        assert!(
            (v[0] + 3.0).abs() < 1e-12 && (v[1] - 1.0).abs() < 1e-12 && (v[2] - 4.0).abs() < 1e-12
        );
        let (r, n) = cubic_roots(1.0, 0.0, 1.0, -2.0); // (x-1)(x²+x+2)
        assert_eq!(n, 1);
        assert!((r[0] - 1.0).abs() < 1e-12);
    }
}
