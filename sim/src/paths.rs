//! Camera paths: `world_from_cam` as a function of time.
//!
//! - [`CameraPath::explore`]: a smooth survey flight over the scene at
//!   altitudes from about 10 m to 40 m, always translating (2-6 m/s) while
//!   the camera, pitched 30-60° down, turns slowly: the parallax monocular
//!   SLAM needs to initialise and track, and never a pure rotation. The
//!   altitude rises over buildings to keep a clearance above their roofs.
//! - [`CameraPath::orbit`]: a circle around the scene centre looking at it.
//! - [`CameraPath::loop_path`] (`loop`): one lap of a rounded rectangle
//!   around the scene (about 520 m at 5 m/s and 30 m), then on over the
//!   first 60 m again with the same heading and pitch: the start is
//!   revisited after more than 400 m of travel, for loop closing.
//! - [`CameraPath::from_tum`]: a TUM trajectory file
//!   (`timestamp tx ty tz qx qy qz qw`, world_from_cam), interpolated
//!   linearly in translation and by slerp in rotation.
//!
//! World frame: local NED at home (see `world.rs`); camera axes x right,
//! y down, z forward.

use std::f64::consts::TAU;
use std::path::{Path, PathBuf};

use nalgebra::{
    Isometry3, Matrix3, Point3, Quaternion, Rotation3, Translation3, UnitQuaternion, Vector3,
};

use crate::world::World;

/// Errors of path construction and TUM parsing.
#[derive(Debug, thiserror::Error)]
pub enum PathError {
    /// The file could not be read.
    #[error("cannot read trajectory {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// A line could not be parsed.
    #[error("{path}:{line}: {reason}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// 1-based line number.
        line: usize,
        /// What is wrong.
        reason: String,
    },
    /// Too few poses to make a path.
    #[error("trajectory {path} has {found} poses, needs at least {needed}")]
    TooShort {
        /// The file.
        path: PathBuf,
        /// Poses found.
        found: usize,
        /// Poses needed.
        needed: usize,
    },
}

/// Every tunable number of the built-in paths.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Params {
    /// Duration of the explore flight, seconds.
    pub explore_duration_s: f64,
    /// Lowest nominal explore altitude, metres.
    pub explore_min_altitude_m: f64,
    /// Highest nominal explore altitude, metres.
    pub explore_max_altitude_m: f64,
    /// Half length of the explore figure of eight, metres.
    pub explore_radius_m: f64,
    /// Smallest camera pitch below the horizon, degrees.
    pub min_pitch_deg: f64,
    /// Largest camera pitch below the horizon, degrees.
    pub max_pitch_deg: f64,
    /// Clearance kept above roofs, metres.
    pub roof_clearance_m: f64,
    /// Horizontal distance at which a roof raises the path, metres.
    pub roof_margin_m: f64,
    /// Duration of one orbit, seconds.
    pub orbit_duration_s: f64,
    /// Orbit radius, metres.
    pub orbit_radius_m: f64,
    /// Orbit altitude, metres.
    pub orbit_altitude_m: f64,
    /// Loop: half extent north-south of its rounded rectangle, metres.
    pub loop_half_x_m: f64,
    /// Loop: half extent east-west, metres.
    pub loop_half_y_m: f64,
    /// Loop: nominal altitude, metres (raised over roofs).
    pub loop_altitude_m: f64,
    /// Loop: ground speed, m/s.
    pub loop_speed_m_s: f64,
    /// Loop: distance flown again past the start, metres.
    pub loop_overlap_m: f64,
    /// Loop: heading turned from the direction of travel towards the
    /// inside of the loop, degrees.
    pub loop_inward_deg: f64,
    /// Loop: camera pitch below the horizon, degrees.
    pub loop_pitch_deg: f64,
}

impl Default for Params {
    fn default() -> Self {
        Self {
            explore_duration_s: 90.0,
            explore_min_altitude_m: 10.0,
            explore_max_altitude_m: 40.0,
            explore_radius_m: 55.0,
            min_pitch_deg: 30.0,
            max_pitch_deg: 60.0,
            roof_clearance_m: 6.0,
            roof_margin_m: 4.0,
            orbit_duration_s: 60.0,
            orbit_radius_m: 60.0,
            orbit_altitude_m: 30.0,
            loop_half_x_m: 80.0,
            loop_half_y_m: 60.0,
            loop_altitude_m: 30.0,
            loop_speed_m_s: 5.0,
            loop_overlap_m: 60.0,
            loop_inward_deg: 35.0,
            loop_pitch_deg: 45.0,
        }
    }
}

/// Which path to follow (the CLI's `--path explore|orbit|FILE`).
#[derive(Debug, Clone, PartialEq)]
pub enum PathSpec {
    /// The survey flight.
    Explore,
    /// The circle around the scene centre.
    Orbit,
    /// The lap that revisits its start (loop closing).
    Loop,
    /// A TUM trajectory file.
    Tum(PathBuf),
}

impl std::str::FromStr for PathSpec {
    type Err = std::convert::Infallible;
    /// `explore`, `orbit`, or anything else as a file path.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Ok(match s {
            "explore" => PathSpec::Explore,
            "orbit" => PathSpec::Orbit,
            "loop" => PathSpec::Loop,
            other => PathSpec::Tum(PathBuf::from(other)),
        })
    }
}

#[derive(Debug, Clone)]
enum Kind {
    Explore { floor: Vec<f64> },
    Orbit,
    Loop { track: LoopTrack, floor: Vec<f64> },
    Samples(Vec<(f64, Isometry3<f64>)>),
}

/// A camera path: `world_from_cam(t)` for `t` in `[start, end]`.
#[derive(Debug, Clone)]
pub struct CameraPath {
    kind: Kind,
    params: Params,
    start: f64,
    end: f64,
}

/// The camera pose at `eye` with heading `yaw` (radians from north towards
/// east) and `pitch` below the horizon (radians), no roll.
pub fn camera_from_yaw_pitch(eye: Point3<f64>, yaw: f64, pitch: f64) -> Isometry3<f64> {
    let (sy, cy) = yaw.sin_cos();
    let (sp, cp) = pitch.sin_cos();
    let forward = Vector3::new(cp * cy, cp * sy, sp);
    let right = Vector3::new(-sy, cy, 0.0);
    let down = forward.cross(&right);
    // The columns are orthonormal by construction: the closed-form
    // conversion, not `from_matrix`'s iteration from the identity, which
    // stalls on a half-turn (yaw 90 deg looking straight down, say).
    let q = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
        Matrix3::from_columns(&[right, down, forward]),
    ));
    Isometry3::from_parts(Translation3::from(eye.coords), q)
}

/// The camera pose at `eye` looking at `target` with no roll (the image
/// x axis stays horizontal). `target` must not be straight above or below.
pub fn look_at(eye: Point3<f64>, target: Point3<f64>) -> Isometry3<f64> {
    let d = target - eye;
    let yaw = d.y.atan2(d.x);
    let pitch = d.z.atan2(d.x.hypot(d.y));
    camera_from_yaw_pitch(eye, yaw, pitch)
}

/// Number of samples of the explore roof-clearance table.
const FLOOR_SAMPLES: usize = 720;

impl CameraPath {
    /// The explore survey flight over `world`.
    pub fn explore(world: &World, params: Params) -> CameraPath {
        // Nominal path, then the roof clearance floor along it, dilated and
        // smoothed so the path climbs before a building and descends after.
        let nominal: Vec<(f64, f64, f64)> = (0..FLOOR_SAMPLES)
            .map(|i| Self::explore_nominal(&params, i as f64 / FLOOR_SAMPLES as f64))
            .collect();
        let raw: Vec<f64> = nominal
            .iter()
            .map(|&(x, y, _)| {
                let h = world.max_height_near(x, y, params.roof_margin_m);
                if h > 0.0 {
                    h + params.roof_clearance_m
                } else {
                    0.0
                }
            })
            .collect();
        let floor = dilate_and_smooth(&raw, FLOOR_SAMPLES / 48); // 1/48 of the loop on each side
        CameraPath {
            kind: Kind::Explore { floor },
            params,
            start: 0.0,
            end: params.explore_duration_s,
        }
    }

    /// The lap around the scene that revisits its start (see the module
    /// documentation); the altitude rises over roofs as the explore
    /// flight's does.
    pub fn loop_path(world: &World, params: Params) -> CameraPath {
        let track = LoopTrack::new(params.loop_half_x_m, params.loop_half_y_m);
        let n = FLOOR_SAMPLES;
        let raw: Vec<f64> = (0..n)
            .map(|i| {
                let (x, y) = track.at(track.perimeter * i as f64 / n as f64);
                let h = world.max_height_near(x, y, params.roof_margin_m);
                if h > 0.0 {
                    h + params.roof_clearance_m
                } else {
                    0.0
                }
            })
            .collect();
        let floor = dilate_and_smooth(&raw, n / 48);
        let length = track.perimeter + params.loop_overlap_m;
        CameraPath {
            end: length / params.loop_speed_m_s.max(0.1),
            kind: Kind::Loop { track, floor },
            params,
            start: 0.0,
        }
    }

    /// Distance flown along the loop's track at time `t`, metres (None for other paths).
    pub fn loop_distance_m(&self, t: f64) -> Option<f64> {
        match &self.kind {
            Kind::Loop { .. } => {
                Some((t.clamp(self.start, self.end) - self.start) * self.params.loop_speed_m_s)
            }
            _ => None,
        }
    }

    fn loop_pose(&self, track: &LoopTrack, floor: &[f64], t: f64) -> Isometry3<f64> {
        let p = &self.params;
        let s = (t - self.start) * p.loop_speed_m_s;
        let (x, y) = track.at(s);
        let (x2, y2) = track.at(s + 0.5);
        let (x1, y1) = track.at(s - 0.5);
        let travel = (y2 - y1).atan2(x2 - x1);
        let u = s.rem_euclid(track.perimeter) / track.perimeter * FLOOR_SAMPLES as f64;
        let i0 = (u.floor() as usize) % FLOOR_SAMPLES;
        let f = u - u.floor();
        let floor_alt = floor[i0] * (1.0 - f) + floor[(i0 + 1) % FLOOR_SAMPLES] * f;
        let alt = p.loop_altitude_m.max(floor_alt);
        // The inside of the loop is to the right of the direction of travel.
        let yaw = travel + p.loop_inward_deg.to_radians();
        camera_from_yaw_pitch(Point3::new(x, y, -alt), yaw, p.loop_pitch_deg.to_radians())
    }

    /// The orbit around the scene centre at the fixed `orbit_altitude_m`. It
    /// does not look at the world: a building on its circle taller than
    /// that altitude is flown through (choose the altitude above it).
    pub fn orbit(params: Params) -> CameraPath {
        CameraPath {
            kind: Kind::Orbit,
            params,
            start: 0.0,
            end: params.orbit_duration_s,
        }
    }

    /// A path through timed poses (at least two, times increasing).
    pub fn from_samples(mut samples: Vec<(f64, Isometry3<f64>)>) -> Option<CameraPath> {
        samples.retain(|(t, _)| t.is_finite());
        samples.sort_by(|a, b| a.0.total_cmp(&b.0));
        samples.dedup_by(|a, b| a.0 == b.0);
        if samples.len() < 2 {
            return None;
        }
        let start = samples[0].0;
        let end = samples[samples.len() - 1].0;
        Some(CameraPath {
            kind: Kind::Samples(samples),
            params: Params::default(),
            start,
            end,
        })
    }

    /// Reads a TUM trajectory file as a path.
    pub fn from_tum(path: &Path) -> Result<CameraPath, PathError> {
        let samples = read_tum(path)?;
        let found = samples.len();
        CameraPath::from_samples(samples).ok_or(PathError::TooShort {
            path: path.to_path_buf(),
            found,
            needed: 2,
        })
    }

    /// Builds the path a [`PathSpec`] names.
    pub fn from_spec(
        spec: &PathSpec,
        world: &World,
        params: Params,
    ) -> Result<CameraPath, PathError> {
        match spec {
            PathSpec::Explore => Ok(CameraPath::explore(world, params)),
            PathSpec::Orbit => Ok(CameraPath::orbit(params)),
            PathSpec::Loop => Ok(CameraPath::loop_path(world, params)),
            PathSpec::Tum(p) => CameraPath::from_tum(p),
        }
    }

    /// First time of the path, seconds.
    pub fn start(&self) -> f64 {
        self.start
    }

    /// Last time of the path, seconds.
    pub fn end(&self) -> f64 {
        self.end
    }

    /// `end - start`, seconds.
    pub fn duration(&self) -> f64 {
        self.end - self.start
    }

    /// Nominal explore position (x, y, altitude) at loop phase `s` ∈ [0, 1).
    fn explore_nominal(p: &Params, s: f64) -> (f64, f64, f64) {
        let a = TAU * s;
        let r = p.explore_radius_m;
        // A figure of eight through home (north lobe, then south lobe); its
        // speed never drops below half its mean (no hovering turns).
        let x = r * a.sin();
        let y = 0.5 * r * (2.0 * a).sin();
        // Low over the open ground at home, high over the lobes.
        let mid = 0.5 * (p.explore_min_altitude_m + p.explore_max_altitude_m);
        let amp = 0.5 * (p.explore_max_altitude_m - p.explore_min_altitude_m);
        let alt = mid - amp * (2.0 * a).cos();
        (x, y, alt.max(p.explore_min_altitude_m))
    }

    fn explore_pose(&self, floor: &[f64], t: f64) -> Isometry3<f64> {
        let p = &self.params;
        let s = ((t - self.start) / self.duration()).clamp(0.0, 1.0);
        let (x, y, alt) = Self::explore_nominal(p, s);
        // Interpolated roof-clearance floor.
        let fi = s * FLOOR_SAMPLES as f64;
        let i0 = (fi.floor() as usize) % FLOOR_SAMPLES;
        let i1 = (i0 + 1) % FLOOR_SAMPLES;
        let f = fi - fi.floor();
        let floor_alt = floor[i0] * (1.0 - f) + floor[i1] * f;
        let alt = alt.max(floor_alt);
        // Heading: the direction of travel (continuous: the path never
        // stops) turned towards the inside of the current lobe by a slowly
        // varying angle (the north lobe turns left, the south lobe right;
        // straight ahead when crossing home): oblique and sideways looks
        // give parallax.
        let ds = 1e-4;
        let (x2, y2, _) = Self::explore_nominal(p, s + ds);
        let (x1, y1, _) = Self::explore_nominal(p, s - ds);
        let travel = (y2 - y1).atan2(x2 - x1);
        let a = TAU * s;
        let yaw = travel - (45.0 + 20.0 * (3.0 * a).sin()).to_radians() * a.sin();
        let pitch_mid = 0.5 * (p.min_pitch_deg + p.max_pitch_deg);
        let pitch_amp = 0.5 * (p.max_pitch_deg - p.min_pitch_deg);
        let pitch = (pitch_mid + pitch_amp * (2.0 * a + 0.7).sin()).to_radians();
        camera_from_yaw_pitch(Point3::new(x, y, -alt), yaw, pitch)
    }

    fn orbit_pose(&self, t: f64) -> Isometry3<f64> {
        let p = &self.params;
        let a = TAU * (t - self.start) / self.duration();
        let eye = Point3::new(
            p.orbit_radius_m * a.cos(),
            p.orbit_radius_m * a.sin(),
            -p.orbit_altitude_m,
        );
        look_at(eye, Point3::origin())
    }

    /// The camera pose at time `t` (clamped to the path's interval).
    pub fn world_from_cam(&self, t: f64) -> Isometry3<f64> {
        let t = if t.is_finite() {
            t.clamp(self.start, self.end)
        } else {
            self.start
        };
        match &self.kind {
            Kind::Explore { floor } => self.explore_pose(floor, t),
            Kind::Orbit => self.orbit_pose(t),
            Kind::Loop { track, floor } => self.loop_pose(track, floor, t),
            Kind::Samples(samples) => interpolate(samples, t),
        }
    }
}

/// A periodic running maximum over `w` samples each side, then a running
/// mean over the same window: a floor that rises before an obstacle and
/// falls after it.
fn dilate_and_smooth(raw: &[f64], w: usize) -> Vec<f64> {
    let n = raw.len();
    let dilated: Vec<f64> = (0..n)
        .map(|i| {
            (0..=2 * w)
                .map(|k| raw[(i + n + k - w) % n])
                .fold(0.0, f64::max)
        })
        .collect();
    (0..n)
        .map(|i| {
            (0..=2 * w)
                .map(|k| dilated[(i + n + k - w) % n])
                .sum::<f64>()
                / (2 * w + 1) as f64
        })
        .collect()
}

/// The loop's track, a superellipse |x/a|^4 + |y/b|^4 = 1 (a rectangle
/// with round corners), by arc length.
#[derive(Debug, Clone)]
struct LoopTrack {
    points: Vec<(f64, f64)>,
    cumulative: Vec<f64>,
    perimeter: f64,
}

impl LoopTrack {
    fn new(a: f64, b: f64) -> LoopTrack {
        let n = 4096;
        // Start south of home, heading east (theta = -pi/2).
        let points: Vec<(f64, f64)> = (0..=n)
            .map(|i| {
                let th = -std::f64::consts::FRAC_PI_2 + TAU * i as f64 / n as f64;
                let (c, s) = (th.cos(), th.sin());
                (
                    a * c.signum() * c.abs().sqrt(),
                    b * s.signum() * s.abs().sqrt(),
                )
            })
            .collect();
        let mut cumulative = vec![0.0];
        for w in points.windows(2) {
            let d = (w[1].0 - w[0].0).hypot(w[1].1 - w[0].1);
            cumulative.push(cumulative.last().copied().unwrap_or(0.0) + d);
        }
        let perimeter = cumulative.last().copied().unwrap_or(1.0);
        LoopTrack {
            points,
            cumulative,
            perimeter,
        }
    }

    fn at(&self, s: f64) -> (f64, f64) {
        let s = s.rem_euclid(self.perimeter);
        let i = self
            .cumulative
            .partition_point(|&c| c <= s)
            .clamp(1, self.points.len() - 1);
        let (c0, c1) = (self.cumulative[i - 1], self.cumulative[i]);
        let f = if c1 > c0 { (s - c0) / (c1 - c0) } else { 0.0 };
        let (p0, p1) = (self.points[i - 1], self.points[i]);
        (p0.0 + (p1.0 - p0.0) * f, p0.1 + (p1.1 - p0.1) * f)
    }
}

fn interpolate(samples: &[(f64, Isometry3<f64>)], t: f64) -> Isometry3<f64> {
    let i = samples.partition_point(|(ts, _)| *ts <= t);
    if i == 0 {
        return samples[0].1;
    }
    if i >= samples.len() {
        return samples[samples.len() - 1].1;
    }
    let (t0, a) = &samples[i - 1];
    let (t1, b) = &samples[i];
    let f = (t - t0) / (t1 - t0);
    let tr = a.translation.vector.lerp(&b.translation.vector, f);
    let q = a
        .rotation
        .try_slerp(&b.rotation, f, 1e-9)
        .unwrap_or(a.rotation);
    Isometry3::from_parts(Translation3::from(tr), q)
}

/// Reads `timestamp tx ty tz qx qy qz qw` lines (`#` comments and blank
/// lines skipped) into timed `world_from_cam` poses.
pub fn read_tum(path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, PathError> {
    let text = std::fs::read_to_string(path).map_err(|source| PathError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_tum(&text, path)
}

/// Parses TUM trajectory text (see [`read_tum`]); `path` names it in errors.
pub fn parse_tum(text: &str, path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, PathError> {
    let mut out = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let err = |reason: String| PathError::Parse {
            path: path.to_path_buf(),
            line: n + 1,
            reason,
        };
        let vals: Vec<f64> = line
            .split_whitespace()
            .map(|f| {
                f.parse::<f64>()
                    .map_err(|e| err(format!("bad number {f:?}: {e}")))
            })
            .collect::<Result<_, _>>()?;
        if vals.len() != 8 {
            return Err(err(format!("expected 8 fields, found {}", vals.len())));
        }
        if vals.iter().any(|v| !v.is_finite()) {
            return Err(err("non-finite value".into()));
        }
        let q = Quaternion::new(vals[7], vals[4], vals[5], vals[6]);
        if q.norm() < 1e-6 {
            return Err(err("zero quaternion".into()));
        }
        let pose = Isometry3::from_parts(
            Translation3::new(vals[1], vals[2], vals[3]),
            UnitQuaternion::from_quaternion(q),
        );
        out.push((vals[0], pose));
    }
    Ok(out)
}

/// Formats one TUM line `timestamp tx ty tz qx qy qz qw` (no newline).
pub fn tum_line(timestamp: f64, world_from_cam: &Isometry3<f64>) -> String {
    let t = world_from_cam.translation.vector;
    let q = world_from_cam.rotation.quaternion();
    format!(
        "{timestamp:.6} {:.6} {:.6} {:.6} {:.9} {:.9} {:.9} {:.9}",
        t.x, t.y, t.z, q.i, q.j, q.k, q.w
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::world::WorldParams;
    use std::f64::consts::PI;

    #[test]
    fn camera_axes_follow_yaw_and_pitch_at_every_angle_including_half_turns() {
        // Straight down with yaw 90 deg is a half-turn from the identity
        // camera (right = x, down = y, forward = z): the case an iterative
        // matrix-to-quaternion fit from the identity cannot leave.
        let eye = Point3::new(1.0, 2.0, -3.0);
        let mut angles = vec![(0.5 * PI, 0.5 * PI), (PI, 0.0), (-0.5 * PI, -0.5 * PI)];
        for i in 0..24 {
            for j in -6..=6 {
                angles.push((i as f64 * PI / 12.0, j as f64 * PI / 12.0));
            }
        }
        for (yaw, pitch) in angles {
            let pose = camera_from_yaw_pitch(eye, yaw, pitch);
            let (sy, cy) = yaw.sin_cos();
            let (sp, cp) = pitch.sin_cos();
            let forward = Vector3::new(cp * cy, cp * sy, sp);
            let right = Vector3::new(-sy, cy, 0.0);
            let r = pose.rotation;
            assert!((r * Vector3::z() - forward).norm() < 1e-12, "{yaw} {pitch}");
            assert!((r * Vector3::x() - right).norm() < 1e-12, "{yaw} {pitch}");
            assert!((r * Vector3::y() - forward.cross(&right)).norm() < 1e-12);
            assert_eq!(pose.translation.vector, eye.coords);
        }
    }

    #[test]
    fn explore_is_smooth_translating_pitched_and_clear_of_roofs() {
        for seed in [1, 2, 3, 4, 5] {
            check_explore(seed);
        }
    }

    fn check_explore(seed: u64) {
        let w = World::generate_with(seed, &WorldParams::tiny()).unwrap();
        let path = CameraPath::explore(&w, Params::default());
        assert!(path.duration() >= 60.0);
        let dt = 1.0 / 30.0;
        let n = (path.duration() / dt) as usize;
        let mut prev = path.world_from_cam(0.0);
        let (mut min_alt, mut max_alt) = (f64::MAX, f64::MIN);
        let mut max_rate: f64 = 0.0;
        for i in 1..n {
            let pose = path.world_from_cam(i as f64 * dt);
            let step = (pose.translation.vector - prev.translation.vector).norm();
            let speed = step / dt;
            // Always translating: no pure rotation.
            assert!(speed > 1.0, "speed {speed} at frame {i}");
            assert!(speed < 12.0, "speed {speed} at frame {i}");
            let rate = pose.rotation.angle_to(&prev.rotation) / dt;
            max_rate = max_rate.max(rate);
            // Forward axis pitched 30-60 deg below the horizon.
            let f = pose.rotation * Vector3::z();
            let pitch = f.z.asin().to_degrees();
            assert!((29.9..=60.1).contains(&pitch), "pitch {pitch}");
            // Camera x axis stays horizontal (no roll).
            assert!((pose.rotation * Vector3::x()).z.abs() < 1e-9);
            let p = pose.translation.vector;
            let alt = -p.z;
            min_alt = min_alt.min(alt);
            max_alt = max_alt.max(alt);
            // Above every roof under it.
            assert!(
                alt > w.max_height_near(p.x, p.y, 2.0) + 2.0,
                "alt {alt} at {p:?}"
            );
            prev = pose;
        }
        assert!(
            (9.9..16.0).contains(&min_alt),
            "seed {seed}: min alt {min_alt}"
        );
        assert!(max_alt > 35.0, "max alt {max_alt}");
        assert!(
            max_rate < 40f64.to_radians(),
            "turn rate {} deg/s",
            max_rate.to_degrees()
        );
    }

    #[test]
    fn loop_revisits_its_start_after_400_m_with_the_same_view() {
        let w = World::generate_with(2, &WorldParams::tiny()).unwrap();
        let path = CameraPath::loop_path(&w, Params::default());
        let start = path.world_from_cam(path.start());
        let dt = 0.1;
        let mut travelled = 0.0;
        let mut prev = start;
        let mut revisit = None;
        let mut t = path.start() + dt;
        while t <= path.end() {
            let pose = path.world_from_cam(t);
            travelled += (pose.translation.vector - prev.translation.vector).norm();
            let d = (pose.translation.vector - start.translation.vector).norm();
            if travelled > 400.0 && d < 2.0 && revisit.is_none() {
                revisit = Some((t, pose, travelled));
            }
            // Clear of the roofs.
            let p = pose.translation.vector;
            assert!(
                -p.z > w.max_height_near(p.x, p.y, 2.0) + 2.0,
                "alt {} at {p:?}",
                -p.z
            );
            prev = pose;
            t += dt;
        }
        let (t_back, pose, len) = revisit.expect("the loop returns to its start");
        assert!(len > 400.0 && len < 700.0, "revisited after {len} m");
        assert!(
            pose.rotation.angle_to(&start.rotation) < 2f64.to_radians(),
            "same view"
        );
        // And flies on over the first stretch.
        assert!(path.end() - t_back > 8.0);
        assert_eq!(path.loop_distance_m(path.end()), Some(path.end() * 5.0));
        assert_eq!("loop".parse::<PathSpec>().unwrap(), PathSpec::Loop);
    }

    #[test]
    fn orbit_looks_at_the_centre() {
        let path = CameraPath::orbit(Params::default());
        for i in 0..10 {
            let pose = path.world_from_cam(i as f64 * 6.0);
            let p_cam = pose.inverse_transform_point(&Point3::origin());
            assert!(p_cam.x.abs() < 1e-9 && p_cam.y.abs() < 1e-9 && p_cam.z > 60.0);
        }
    }

    #[test]
    fn tum_round_trip_and_interpolation() {
        let a = look_at(Point3::new(0.0, 0.0, -10.0), Point3::new(5.0, 0.0, 0.0));
        let b = look_at(Point3::new(10.0, 2.0, -20.0), Point3::new(5.0, 8.0, 0.0));
        let text = format!(
            "# comment\n{}\n\n{}\n",
            tum_line(1.0, &a),
            tum_line(3.0, &b)
        );
        let s = parse_tum(&text, Path::new("x")).unwrap();
        assert_eq!(s.len(), 2);
        assert!((s[1].1.translation.vector - b.translation.vector).norm() < 1e-6);
        assert!(s[1].1.rotation.angle_to(&b.rotation) < 1e-8);
        let path = CameraPath::from_samples(s).unwrap();
        let mid = path.world_from_cam(2.0);
        assert!((mid.translation.vector - Vector3::new(5.0, 1.0, -15.0)).norm() < 1e-6);
        let half = a.rotation.angle_to(&b.rotation) * 0.5;
        assert!((mid.rotation.angle_to(&a.rotation) - half).abs() < 1e-6);
        // Bad lines are errors with a line number.
        match parse_tum("1 2 3\n", Path::new("f")) {
            Err(PathError::Parse { line: 1, .. }) => {}
            other => panic!("{other:?}"),
        }
        assert!(parse_tum("0 0 0 0 0 0 0 0\n", Path::new("f")).is_err());
        assert!(CameraPath::from_samples(vec![(0.0, a)]).is_none());
    }

    #[test]
    fn path_spec_parses() {
        assert_eq!("explore".parse::<PathSpec>().unwrap(), PathSpec::Explore);
        assert_eq!("orbit".parse::<PathSpec>().unwrap(), PathSpec::Orbit);
        assert_eq!(
            "a/b.txt".parse::<PathSpec>().unwrap(),
            PathSpec::Tum("a/b.txt".into())
        );
    }
}
