//! Pose-graph optimisation in Sim(3): ORB-SLAM's `OptimizeEssentialGraph`
//! after a loop closure (spanning tree, strong covisibility and loop edges
//! between keyframe poses; no map points).
//!
//! Each vertex is a keyframe's `S_iw` (world → camera i, a similarity: a
//! monocular map's scale drifts). An edge `i → j` holds the measured
//! relative similarity `S_ji` (camera i → camera j) and the error transform
//! `E = S_ji ∘ S_iw ∘ S_jw⁻¹`, identity when the two poses agree with the
//! measurement. The residual is `r = [t_E; ω_E; ln s_E]` (translation,
//! rotation vector, log scale of `E`): zero exactly at the identity and
//! equal to Sim(3)'s logarithm to first order, so the minimiser is the
//! same. Edges weigh `w·|r|²` (ORB-SLAM uses identity information, weight 1).
//!
//! Updates are the Sim(3) left update of [`super::sim3`]
//! (`S ← (e^σ·Exp(ω), υ) ∘ S`); the Jacobians are central differences (as
//! g2o's `EdgeSim3`, which has no analytic Jacobian, computes them for
//! ORB-SLAM). The damped normal equations are block-sparse (7×7 blocks,
//! one per vertex pair joined by an edge) and solved with faer's sparse
//! Cholesky inside the crate's one LM core ([`super::lm`]). Fixed vertices
//! fix the gauge (ORB-SLAM fixes the loop keyframe).

use faer::Side;
use faer::prelude::Solve;
use faer::sparse::{SparseColMat, Triplet};
use nalgebra::{SMatrix, SVector};

use super::OptimizeError;
use super::lm::{LeastSquares, LmParams, LmSummary, levenberg_marquardt};
use super::sim3::sim3_left_update;
use crate::lie::Sim3;

type Vec7 = SVector<f64, 7>;
type Mat7 = SMatrix<f64, 7, 7>;

/// One relative-pose constraint between vertices `i` and `j`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sim3Edge {
    /// The first vertex.
    pub i: usize,
    /// The second vertex.
    pub j: usize,
    /// The measured `S_ji`: camera-i coordinates to camera-j coordinates.
    pub s_ji: Sim3,
    /// Weight of the squared residual (1 for ORB-SLAM's identity information).
    pub weight: f64,
}

/// A Sim(3) pose graph: vertices `S_iw`, which are fixed, and edges.
#[derive(Debug, Clone, PartialEq)]
pub struct PoseGraph {
    /// Per vertex: `S_iw` (world → camera), updated in place.
    pub poses: Vec<Sim3>,
    /// Per vertex: held fixed (at least one must be, for the gauge).
    pub fixed: Vec<bool>,
    /// The constraints.
    pub edges: Vec<Sim3Edge>,
}

/// Tunables of [`optimize_pose_graph`].
#[derive(Debug, Clone, PartialEq)]
pub struct PoseGraphParams {
    /// LM settings (ORB-SLAM runs 20 iterations).
    pub lm: LmParams,
    /// Step of the central differences.
    pub diff_step: f64,
}

impl Default for PoseGraphParams {
    fn default() -> Self {
        PoseGraphParams {
            lm: LmParams {
                max_iterations: 20,
                ..LmParams::default()
            },
            diff_step: 1e-6,
        }
    }
}

/// The residual of one edge at the given poses (see the module doc).
pub fn edge_residual(s_ji: &Sim3, s_iw: &Sim3, s_jw: &Sim3) -> Vec7 {
    let e = s_ji.compose(s_iw).compose(&s_jw.inverse());
    let w = e.rotation.scaled_axis();
    Vec7::from_column_slice(&[
        e.translation.x,
        e.translation.y,
        e.translation.z,
        w.x,
        w.y,
        w.z,
        e.scale.ln(),
    ])
}

struct GraphLs<'a> {
    graph: &'a mut PoseGraph,
    /// Vertex → index among the free vertices.
    free_index: Vec<Option<usize>>,
    n_free: usize,
    diff_step: f64,
    /// Upper-and-lower blocks of H: (row block, column block, block).
    blocks: Vec<(usize, usize, Mat7)>,
    g: Vec<f64>,
    step: Vec<f64>,
    old: Vec<Sim3>,
}

impl GraphLs<'_> {
    /// Residual and the two Jacobians (w.r.t. the left updates of `S_iw`
    /// and `S_jw`) of one edge.
    fn linearize_edge(&self, e: &Sim3Edge) -> (Vec7, Mat7, Mat7) {
        let p = &self.graph.poses;
        let r = edge_residual(&e.s_ji, &p[e.i], &p[e.j]);
        let h = self.diff_step;
        let mut ji = Mat7::zeros();
        let mut jj = Mat7::zeros();
        for k in 0..7 {
            let mut d = Vec7::zeros();
            d[k] = h;
            if self.free_index[e.i].is_some() {
                let plus = edge_residual(&e.s_ji, &sim3_left_update(&p[e.i], &d), &p[e.j]);
                let minus = edge_residual(&e.s_ji, &sim3_left_update(&p[e.i], &(-d)), &p[e.j]);
                ji.set_column(k, &((plus - minus) / (2.0 * h)));
            }
            if self.free_index[e.j].is_some() {
                let plus = edge_residual(&e.s_ji, &p[e.i], &sim3_left_update(&p[e.j], &d));
                let minus = edge_residual(&e.s_ji, &p[e.i], &sim3_left_update(&p[e.j], &(-d)));
                jj.set_column(k, &((plus - minus) / (2.0 * h)));
            }
        }
        (r, ji, jj)
    }
}

impl LeastSquares for GraphLs<'_> {
    fn linearize(&mut self) -> (f64, f64) {
        let mut diag: Vec<Mat7> = vec![Mat7::zeros(); self.n_free];
        let mut off: std::collections::HashMap<(usize, usize), Mat7> =
            std::collections::HashMap::new();
        let mut g = vec![0.0; 7 * self.n_free];
        let mut cost = 0.0;
        for e in &self.graph.edges {
            let (r, ji, jj) = self.linearize_edge(e);
            cost += 0.5 * e.weight * r.norm_squared();
            let (a, b) = (self.free_index[e.i], self.free_index[e.j]);
            if let Some(a) = a {
                diag[a] += ji.transpose() * ji * e.weight;
                let ga = ji.transpose() * r * e.weight;
                for k in 0..7 {
                    g[7 * a + k] += ga[k];
                }
            }
            if let Some(b) = b {
                diag[b] += jj.transpose() * jj * e.weight;
                let gb = jj.transpose() * r * e.weight;
                for k in 0..7 {
                    g[7 * b + k] += gb[k];
                }
            }
            if let (Some(a), Some(b)) = (a, b)
                && a != b
            {
                let hab = ji.transpose() * jj * e.weight;
                let key = (a.min(b), a.max(b));
                let blk = if a < b { hab } else { hab.transpose() };
                *off.entry(key).or_insert_with(Mat7::zeros) += blk;
            }
        }
        let mut blocks: Vec<(usize, usize, Mat7)> = diag
            .into_iter()
            .enumerate()
            .map(|(a, m)| (a, a, m))
            .collect();
        let mut off: Vec<((usize, usize), Mat7)> = off.into_iter().collect();
        off.sort_by_key(|(k, _)| *k);
        blocks.extend(off.into_iter().map(|((a, b), m)| (a, b, m)));
        self.blocks = blocks;
        let gmax = g.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        self.g = g;
        (cost, gmax)
    }

    fn solve_damped(&mut self, lambda: f64) -> Option<(f64, f64)> {
        let n = 7 * self.n_free;
        let mut d = vec![0.0; n];
        let mut triplets: Vec<Triplet<usize, usize, f64>> =
            Vec::with_capacity(self.blocks.len() * 49);
        for (a, b, m) in &self.blocks {
            // Only the lower triangle is read by the factorisation.
            for r in 0..7 {
                for c in 0..7 {
                    let (row, col) = (7 * b + r, 7 * a + c);
                    if a == b {
                        if row < col {
                            continue;
                        }
                        let mut v = m[(r, c)];
                        if r == c {
                            d[row] = v.clamp(1e-6, 1e32);
                            v += lambda * d[row];
                        }
                        triplets.push(Triplet::new(row, col, v));
                    } else {
                        // Block (a, b) with a < b sits above the diagonal;
                        // its transpose (b, a) is below it.
                        triplets.push(Triplet::new(row, col, m[(c, r)]));
                    }
                }
            }
        }
        let h = SparseColMat::<usize, f64>::try_new_from_triplets(n, n, &triplets).ok()?;
        let llt = h.sp_cholesky(Side::Lower).ok()?;
        let rhs = faer::Col::<f64>::from_fn(n, |i| -self.g[i]);
        let step = llt.solve(&rhs);
        let step: Vec<f64> = (0..n).map(|i| step[i]).collect();
        if !step.iter().all(|v| v.is_finite()) {
            return None;
        }
        let pred = 0.5
            * step
                .iter()
                .zip(&d)
                .zip(&self.g)
                .map(|((s, d), g)| s * (lambda * d * s - g))
                .sum::<f64>();
        let norm = step.iter().map(|v| v * v).sum::<f64>().sqrt();
        self.step = step;
        Some((pred, norm))
    }

    fn apply_step(&mut self) {
        self.old.clone_from(&self.graph.poses);
        for (v, idx) in self.free_index.iter().enumerate() {
            if let Some(a) = idx {
                let d = Vec7::from_column_slice(&self.step[7 * a..7 * a + 7]);
                self.graph.poses[v] = sim3_left_update(&self.graph.poses[v], &d);
            }
        }
    }

    fn revert_step(&mut self) {
        self.graph.poses.clone_from(&self.old);
    }

    fn cost(&mut self) -> f64 {
        let p = &self.graph.poses;
        self.graph
            .edges
            .iter()
            .map(|e| 0.5 * e.weight * edge_residual(&e.s_ji, &p[e.i], &p[e.j]).norm_squared())
            .sum()
    }

    fn state_norm(&self) -> f64 {
        self.graph
            .poses
            .iter()
            .map(|s| {
                s.translation.norm_squared()
                    + s.rotation.scaled_axis().norm_squared()
                    + s.scale.ln().powi(2)
            })
            .sum::<f64>()
            .sqrt()
    }
}

/// Optimises the free poses of `graph` in place (see the module doc).
///
/// Errors: [`OptimizeError::InvalidInput`] for an edge naming a missing
/// vertex, a non-finite or non-positive pose or measurement, a bad weight,
/// or no fixed vertex (the gauge would be free).
pub fn optimize_pose_graph(
    graph: &mut PoseGraph,
    params: &PoseGraphParams,
) -> Result<LmSummary, OptimizeError> {
    let n = graph.poses.len();
    if graph.fixed.len() != n {
        return Err(OptimizeError::InvalidInput {
            what: "fixed flags",
            index: graph.fixed.len(),
        });
    }
    if !graph.fixed.iter().any(|f| *f) {
        return Err(OptimizeError::InvalidInput {
            what: "gauge (no fixed vertex)",
            index: 0,
        });
    }
    let finite = |s: &Sim3| {
        s.scale.is_finite()
            && s.scale > 0.0
            && s.translation.iter().all(|v| v.is_finite())
            && s.rotation.coords.iter().all(|v| v.is_finite())
    };
    for (k, s) in graph.poses.iter().enumerate() {
        if !finite(s) {
            return Err(OptimizeError::InvalidInput {
                what: "pose",
                index: k,
            });
        }
    }
    for (k, e) in graph.edges.iter().enumerate() {
        if e.i >= n
            || e.j >= n
            || e.i == e.j
            || !finite(&e.s_ji)
            || !(e.weight.is_finite() && e.weight > 0.0)
        {
            return Err(OptimizeError::InvalidInput {
                what: "edge",
                index: k,
            });
        }
    }
    let mut free_index = vec![None; n];
    let mut n_free = 0;
    for (v, f) in graph.fixed.iter().enumerate() {
        if !f {
            free_index[v] = Some(n_free);
            n_free += 1;
        }
    }
    let mut ls = GraphLs {
        old: graph.poses.clone(),
        graph,
        free_index,
        n_free,
        diff_step: params.diff_step,
        blocks: Vec::new(),
        g: Vec::new(),
        step: Vec::new(),
    };
    Ok(levenberg_marquardt(&mut ls, &params.lm))
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{UnitQuaternion, Vector3};

    fn sim(rx: f64, ry: f64, rz: f64, t: [f64; 3], s: f64) -> Sim3 {
        Sim3::new(
            UnitQuaternion::from_euler_angles(rx, ry, rz),
            Vector3::new(t[0], t[1], t[2]),
            s,
        )
    }

    fn dist(a: &Sim3, b: &Sim3) -> f64 {
        edge_residual(&Sim3::identity(), a, b).norm()
    }

    /// A ring of poses: odometry edges from the truth, the chain's poses
    /// drifted in scale and rotation, one loop edge; the optimisation
    /// brings the drifted end back while the fixed first pose stays.
    #[test]
    fn loop_edge_removes_accumulated_drift() {
        let n = 24;
        let truth: Vec<Sim3> = (0..n)
            .map(|k| {
                let a = std::f64::consts::TAU * k as f64 / n as f64;
                // world → camera: camera on a circle of radius 10, yawing.
                let wc = sim(0.0, 0.0, a, [10.0 * a.cos(), 10.0 * a.sin(), 0.0], 1.0);
                wc.inverse()
            })
            .collect();
        let mut edges = Vec::new();
        for k in 0..n {
            let j = (k + 1) % n;
            edges.push(Sim3Edge {
                i: k,
                j,
                s_ji: truth[j].compose(&truth[k].inverse()),
                weight: 1.0,
            });
        }
        // Drifted estimate: each step picks up a little scale and yaw.
        let mut poses = vec![truth[0]];
        let drift = sim(0.0, 0.0, 0.01, [0.05, 0.0, 0.0], 1.02);
        for k in 1..n {
            let rel = truth[k].compose(&truth[k - 1].inverse());
            let prev = poses[k - 1];
            poses.push(drift.compose(&rel).compose(&prev));
        }
        let before = dist(&poses[n - 1], &truth[n - 1]);
        assert!(before > 0.3, "the test needs drift: {before}");
        let mut fixed = vec![false; n];
        fixed[0] = true;
        let mut graph = PoseGraph {
            poses,
            fixed,
            edges,
        };
        let summary = optimize_pose_graph(&mut graph, &PoseGraphParams::default()).unwrap();
        assert!(summary.final_cost < 1e-10, "{summary:?}");
        for (k, (est, t)) in graph.poses.iter().zip(&truth).enumerate() {
            let d = dist(est, t);
            assert!(d < 1e-4, "vertex {k}: {d}");
        }
    }

    #[test]
    fn refuses_graphs_without_gauge_or_with_bad_edges() {
        let mut g = PoseGraph {
            poses: vec![Sim3::identity(); 2],
            fixed: vec![false; 2],
            edges: vec![Sim3Edge {
                i: 0,
                j: 1,
                s_ji: Sim3::identity(),
                weight: 1.0,
            }],
        };
        assert!(optimize_pose_graph(&mut g, &PoseGraphParams::default()).is_err());
        g.fixed[0] = true;
        g.edges[0].j = 5;
        assert!(optimize_pose_graph(&mut g, &PoseGraphParams::default()).is_err());
        g.edges[0].j = 1;
        g.edges[0].s_ji.scale = 0.0;
        assert!(optimize_pose_graph(&mut g, &PoseGraphParams::default()).is_err());
        g.edges[0].s_ji.scale = 1.0;
        assert!(optimize_pose_graph(&mut g, &PoseGraphParams::default()).is_ok());
    }
}
