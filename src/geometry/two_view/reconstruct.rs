//! The reconstruction of the chosen model: its motion hypotheses (H's
//! eight, E's four), each triangulating the inliers under ORB-SLAM's
//! `CheckRT` (parallax, cheirality, reprojection), the best chosen or the
//! initialisation refused (too few points, too little parallax, ambiguous),
//! and the accepted one refined.

use nalgebra::{Isometry3, Matrix3, Point2, Point3, Translation3, Vector3};

use super::fundamental::decompose_e;
use super::homography::decompose_h;
use super::refine::refine_two_view;
use super::{Model, TwoViewParams, TwoViewResult};
use crate::geometry::GeometryError;
use crate::geometry::triangulate::triangulate_cam1;

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

/// The `rank`-th largest parallax (0: the largest), degrees, of the
/// triangulated points whose parallax cosines are `cos` (reordered); the
/// smallest when there are fewer points, 0 without any. ORB-SLAM's
/// two-view check takes the 50th largest, so that a few wide-angle points
/// do not pass a reconstruction whose bulk has none.
pub fn ranked_parallax_deg(cos: &mut [f64], rank: usize) -> f64 {
    if cos.is_empty() {
        return 0.0;
    }
    // Ascending cosine = descending parallax.
    let idx = rank.min(cos.len() - 1);
    let (_, c, _) = cos.select_nth_unstable_by(idx, |a, b| a.total_cmp(b));
    c.clamp(-1.0, 1.0).acos().to_degrees()
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
    let parallax_deg = ranked_parallax_deg(cos_buf, ctx.parallax_rank);
    Hypothesis {
        r,
        t,
        n_good,
        parallax_deg,
        points,
    }
}

/// The two models after RANSAC and refits.
pub(super) struct Fits<'a> {
    pub(super) h: Option<Matrix3<f64>>,
    pub(super) f: Option<Matrix3<f64>>,
    pub(super) h_inliers: &'a [bool],
    pub(super) f_inliers: &'a [bool],
    pub(super) score_h: f64,
    pub(super) score_f: f64,
}

/// The matched keypoints, in pixels and normalised.
pub(super) struct Views<'a> {
    pub(super) k: &'a Matrix3<f64>,
    pub(super) k_inv: &'a Matrix3<f64>,
    pub(super) px1: &'a [[f64; 2]],
    pub(super) px2: &'a [[f64; 2]],
    pub(super) xn1: &'a [Point2<f64>],
    pub(super) xn2: &'a [Point2<f64>],
}

/// Motion hypotheses of `model`, the best chosen and checked, then refined.
pub(super) fn reconstruct(
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
