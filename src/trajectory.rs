//! A camera trajectory: timestamped poses, as SLAM produces it and the
//! evaluation compares it, and the TUM format: lines `timestamp tx ty tz
//! qx qy qz qw`, each the camera's pose in the world (world_from_cam),
//! quaternion scalar last.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion, Vector3};

/// Errors reading or writing a trajectory.
#[derive(Debug, thiserror::Error)]
pub enum TrajectoryError {
    /// The file could not be read or written.
    #[error("cannot access trajectory {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// A line is not `timestamp tx ty tz qx qy qz qw`.
    #[error("{path}:{line}: {reason}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
}

/// One timestamped camera pose.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StampedPose {
    /// Time, seconds.
    pub t: f64,
    /// The camera's pose in the world.
    pub world_from_cam: Isometry3<f64>,
}

impl StampedPose {
    /// The camera centre in world coordinates.
    pub fn position(&self) -> Vector3<f64> {
        self.world_from_cam.translation.vector
    }
}

/// A camera trajectory, in time order as read.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Trajectory {
    /// The poses.
    pub poses: Vec<StampedPose>,
}

impl Trajectory {
    /// Parse TUM text; `path` names the source in errors. `#` starts a comment.
    pub fn parse_tum(text: &str, path: &Path) -> Result<Self, TrajectoryError> {
        let mut poses = Vec::new();
        for (i, raw) in text.lines().enumerate() {
            let line = raw.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let err = |reason: String| TrajectoryError::Parse {
                path: path.to_owned(),
                line: i + 1,
                reason,
            };
            let mut v = [0.0f64; 8];
            let mut n = 0;
            for tok in line
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|t| !t.is_empty())
            {
                if n == 8 {
                    return Err(err(
                        "more than 8 numbers (timestamp tx ty tz qx qy qz qw)".into()
                    ));
                }
                v[n] = tok
                    .parse::<f64>()
                    .ok()
                    .filter(|x| x.is_finite())
                    .ok_or_else(|| err(format!("`{tok}` is not a number")))?;
                n += 1;
            }
            if n != 8 {
                return Err(err(format!(
                    "expected 8 numbers (timestamp tx ty tz qx qy qz qw), found {n}"
                )));
            }
            let q = Quaternion::new(v[7], v[4], v[5], v[6]);
            let norm = q.norm();
            if !(0.9..=1.1).contains(&norm) {
                return Err(err(format!("quaternion norm {norm:.4} is not 1")));
            }
            poses.push(StampedPose {
                t: v[0],
                world_from_cam: Isometry3::from_parts(
                    Translation3::new(v[1], v[2], v[3]),
                    UnitQuaternion::from_quaternion(q),
                ),
            });
        }
        Ok(Trajectory { poses })
    }

    /// Read a TUM trajectory file.
    pub fn read_tum(path: &Path) -> Result<Self, TrajectoryError> {
        let text = std::fs::read_to_string(path).map_err(|source| TrajectoryError::Io {
            path: path.to_owned(),
            source,
        })?;
        Self::parse_tum(&text, path)
    }

    /// The TUM text of this trajectory (timestamps with 6 decimals, positions
    /// and quaternions with 9 significant decimals).
    pub fn to_tum(&self) -> String {
        let mut s = String::with_capacity(self.poses.len() * 96);
        s.push_str("# timestamp tx ty tz qx qy qz qw (world_from_cam)\n");
        for p in &self.poses {
            let t = p.world_from_cam.translation.vector;
            let q = p.world_from_cam.rotation.coords; // x y z w
            let _ = writeln!(
                s,
                "{:.6} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9} {:.9}",
                p.t, t.x, t.y, t.z, q.x, q.y, q.z, q.w
            );
        }
        s
    }

    /// Write a TUM trajectory file.
    pub fn write_tum(&self, path: &Path) -> Result<(), TrajectoryError> {
        std::fs::write(path, self.to_tum()).map_err(|source| TrajectoryError::Io {
            path: path.to_owned(),
            source,
        })
    }

    /// Number of poses.
    pub fn len(&self) -> usize {
        self.poses.len()
    }

    /// True when there is no pose.
    pub fn is_empty(&self) -> bool {
        self.poses.is_empty()
    }

    /// Total path length of the camera centre, metres.
    pub fn path_length(&self) -> f64 {
        self.poses
            .windows(2)
            .map(|w| (w[1].position() - w[0].position()).norm())
            .sum()
    }
}

/// Pair the poses of two trajectories by timestamp, as evo does: every pose
/// of the shorter trajectory (of `a` when both have the same length) takes
/// the pose of the other whose time is nearest, if within `max_dt` seconds;
/// an exact tie goes to the earlier pose. A pose of the longer trajectory may
/// be taken twice when the shorter one is denser somewhere. Returns index
/// pairs `(i_a, i_b)` in the order of the shorter trajectory.
pub fn associate(a: &Trajectory, b: &Trajectory, max_dt: f64) -> Vec<(usize, usize)> {
    let b_longer = b.poses.len() > a.poses.len();
    let (short, long) = if b_longer { (a, b) } else { (b, a) };
    // The longer one's times, sorted, with their indices.
    let mut sorted: Vec<(f64, usize)> = long
        .poses
        .iter()
        .enumerate()
        .map(|(i, p)| (p.t, i))
        .collect();
    sorted.sort_by(|x, y| x.0.total_cmp(&y.0));
    let mut pairs = Vec::with_capacity(short.poses.len());
    for (is, p) in short.poses.iter().enumerate() {
        let t = p.t;
        // First index with time > t; its predecessor has time <= t.
        let up = sorted.partition_point(|&(tl, _)| tl <= t);
        let d_up = sorted.get(up).map_or(f64::INFINITY, |&(tl, _)| tl - t);
        let d_lo = if up > 0 {
            t - sorted[up - 1].0
        } else {
            f64::INFINITY
        };
        let best = if d_up <= max_dt && d_up < d_lo {
            sorted[up].1
        } else if d_lo <= max_dt && d_lo <= d_up {
            sorted[up - 1].1
        } else {
            continue;
        };
        pairs.push(if b_longer { (is, best) } else { (best, is) });
    }
    pairs
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_text() {
        let text = "# c\n1.5 1 2 3 0 0 0 1\n2.5, -1, 0.5, 2, 0.5, 0.5, 0.5, 0.5\n";
        let t = Trajectory::parse_tum(text, Path::new("x")).unwrap();
        assert_eq!(t.len(), 2);
        let back = Trajectory::parse_tum(&t.to_tum(), Path::new("y")).unwrap();
        for (a, b) in t.poses.iter().zip(&back.poses) {
            assert!((a.t - b.t).abs() < 1e-9);
            assert!((a.position() - b.position()).norm() < 1e-9);
            assert!(
                a.world_from_cam
                    .rotation
                    .angle_to(&b.world_from_cam.rotation)
                    < 1e-8
            );
        }
    }

    #[test]
    fn bad_lines_name_the_line() {
        let e = Trajectory::parse_tum("1 2 3 4 0 0 0 1\n1 2 3\n", Path::new("gt.txt"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("gt.txt:2") && e.contains("found 3"), "{e}");
        let e = Trajectory::parse_tum("1 2 3 4 0 0 0 5\n", Path::new("gt.txt"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("gt.txt:1") && e.contains("quaternion"), "{e}");
    }

    #[test]
    fn association_takes_the_nearest_within_tolerance() {
        let mk = |ts: &[f64]| Trajectory {
            poses: ts
                .iter()
                .map(|&t| StampedPose {
                    t,
                    world_from_cam: Isometry3::identity(),
                })
                .collect(),
        };
        let a = mk(&[0.0, 0.1, 0.2, 0.3]);
        let b = mk(&[0.005, 0.095, 0.104, 0.5]);
        let p = associate(&a, &b, 0.02);
        // Equal lengths: each pose of b takes its nearest in a. b[1] = 0.095
        // and b[2] = 0.104 both take a[1]; b[3] = 0.5 has none within 20 ms.
        assert_eq!(p, vec![(0, 0), (1, 1), (1, 2)]);
        // An exact tie goes to the earlier pose.
        let c = mk(&[0.5]);
        let d = mk(&[0.0, 1.0]);
        assert_eq!(associate(&c, &d, 0.6), vec![(0, 0)]);
    }
}
