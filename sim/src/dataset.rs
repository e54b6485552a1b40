//! Writing rendered datasets in the TUM RGB-D layout, and live ground truth.
//!
//! A dataset folder holds:
//!
//! - `rgb/<timestamp>.png`: 8-bit grey frames;
//! - `rgb.txt`: `timestamp rgb/<file>` per frame;
//! - `calib.txt`: one line `fx fy cx cy k1 k2 p1 p2 k3` (OpenCV order);
//! - `groundtruth.txt`: `timestamp tx ty tz qx qy qz qw`, the camera's
//!   `world_from_cam` with the quaternion scalar last;
//! - `render_info.json`: seed, path, camera, world, realism (the effects
//!   on, the codec, the stream's bitrate) and timing of the render;
//! - `telemetry.txt`: what the autopilot would report at each frame's
//!   timestamp (see [`TELEMETRY_HEADER`]): the GNSS position in local NED
//!   with the realism's GNSS error (bias, noise, the drift while the fix is
//!   lost, `fix` 0 then), the receiver's reported accuracy, the barometric
//!   altitude with the realism's drift, the body attitude and the gimbal
//!   angles (from the true camera pose: a rendered path has no body tilt;
//!   with the realism's `ahrs` the reported roll, pitch, heading and
//!   gimbal pitch carry its error). The errors come from the same processes and
//!   seed as the live vehicle's ([`crate::vehicle::SensorErrors`]); with a
//!   realism without `gps` and `baro` (e.g. `ideal`) they are exact and the
//!   reported accuracy is 0.
//!
//! With any realism effect on, frames carry their exact truth:
//! `groundtruth.txt`'s pose is the camera's at the frame's timestamp, the
//! mid-exposure of the centre row; `exposures.txt` gives each frame's
//! exposure time, gain, rolling-shutter readout and sub-exposure samples
//! (row `y` of `h` is exposed around `timestamp + (y - (h - 1) / 2) *
//! readout / (h - 1)`); with a rolling shutter, `rows.txt` gives the
//! mid-exposure pose of every 16th row and the last, and a row between two
//! knots was rendered from their interpolation (linear by row in
//! translation, slerp in rotation), so a consumer can evaluate every row
//! exactly. With compression on, frames are the stream's JPEG files
//! (`rgb/<timestamp>.jpg`, decoded exactly as the ground station decodes
//! them); otherwise PNG.
//!
//! The world frame is the local NED frame at home (x north, y east, z down,
//! metres); the headers of `rgb.txt` and `groundtruth.txt` say so.

use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

use nalgebra::Isometry3;

use crate::camera::{CameraError, SimCamera};
use crate::disturbance::{GimbalJitter, HoldSway, WindField};
use crate::imaging::Imager;
use crate::paths::{CameraPath, Params as PathParams, PathError, PathSpec, parse_tum, tum_line};
use crate::realism::{Realism, RealismError};
use crate::render::{RenderParams, Renderer};
use crate::vehicle::SensorErrors;
use crate::world::{World, WorldError, WorldKind, WorldParams};

/// The header naming the frames, written atop trajectory files.
pub const WORLD_FRAME_HEADER: &str = "# world frame: local NED at home (x north, y east, z down, metres); \
poses are world_from_cam, camera axes x right, y down, z forward";

/// The header of `telemetry.txt`.
pub const TELEMETRY_HEADER: &str = "# world frame: local NED at home (x north, y east, z down, metres)\n\
# timestamp fix gps_n gps_e gps_d h_acc v_acc baro_alt roll_deg pitch_deg yaw_deg gimbal_pitch_deg gimbal_yaw_deg\n\
# timestamp: the frame's (groundtruth.txt's); fix: 1 with a GNSS fix, 0 while it is lost (the position is then the \
estimator's drifting dead reckoning, which an autopilot does not send); gps_n gps_e gps_d: the GNSS position of the \
camera, m; h_acc v_acc: the receiver's reported 1-sigma accuracy, horizontal per axis and vertical, m (0: no error \
model); baro_alt: barometric altitude above home, m (up); roll pitch yaw: body attitude (NED, yaw from north to \
east); gimbal pitch (positive up, -90 straight down) and yaw relative to the body, degrees";

/// Errors of dataset writing.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// A file or folder could not be written.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// An image could not be encoded or saved.
    #[error("cannot save image {path}: {source}")]
    Image {
        /// The file.
        path: PathBuf,
        /// The image error.
        source: image::ImageError,
    },
    /// The camera path could not be built.
    #[error(transparent)]
    Path(#[from] PathError),
    /// The camera is unusable.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// Zero frames were asked for.
    #[error("a dataset needs at least one frame")]
    NoFrames,
    /// The realism configuration is unusable.
    #[error(transparent)]
    Realism(#[from] RealismError),
    /// The world could not be generated.
    #[error(transparent)]
    World(#[from] WorldError),
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// What [`render_dataset`] did, with its timings.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct RenderReport {
    /// Frames written.
    pub frames: usize,
    /// The dataset folder.
    pub out_dir: PathBuf,
    /// First and last timestamp, seconds of path time.
    pub time_span_s: (f64, f64),
    /// Seconds spent generating the world.
    pub world_seconds: f64,
    /// Wall-clock seconds spent rendering (excluding PNG encoding).
    pub render_seconds: f64,
    /// CPU seconds of the rendering thread spent rendering, when the OS reports them.
    pub render_cpu_seconds: Option<f64>,
    /// Wall-clock seconds spent encoding and writing files.
    pub write_seconds: f64,
    /// The realism configuration.
    pub realism: String,
    /// The world kind.
    pub world: String,
    /// Mean encoded bytes per frame (with compression).
    pub bytes_per_frame: Option<f64>,
    /// The stream's bitrate at the dataset's frame rate, bit/s (with compression).
    pub bitrate_bit_s: Option<f64>,
    /// Mean exposure time, s (realism only).
    pub mean_exposure_s: Option<f64>,
    /// Mean sub-exposure samples per frame.
    pub mean_blur_samples: f64,
    /// Rms horizontal position-hold error along the path, m (with wind).
    pub hold_error_rms_m: Option<f64>,
}

impl RenderReport {
    /// Rendered frames per wall-clock second (rendering only).
    pub fn render_fps(&self) -> f64 {
        self.frames as f64 / self.render_seconds.max(1e-9)
    }

    /// Rendered frames per CPU second of the rendering thread.
    pub fn render_fps_cpu(&self) -> Option<f64> {
        self.render_cpu_seconds
            .map(|s| self.frames as f64 / s.max(1e-9))
    }
}

/// CPU time consumed by the calling thread, seconds (Linux
/// `/proc/thread-self/schedstat`); `None` elsewhere.
pub fn thread_cpu_seconds() -> Option<f64> {
    let s = std::fs::read_to_string("/proc/thread-self/schedstat").ok()?;
    let ns: u64 = s.split_whitespace().next()?.parse().ok()?;
    Some(ns as f64 * 1e-9)
}

/// Renders `frames` frames spread evenly over the whole of `path` (its
/// time span) in the default world for `seed`, and writes a TUM-layout
/// dataset to `out_dir`. `noise_sigma` is the sensor noise in grey levels
/// (0 for none); the noise of frame `i` is seeded from `seed` and `i`.
pub fn render_dataset(
    path: PathSpec,
    frames: usize,
    out_dir: &Path,
    seed: u64,
    camera: SimCamera,
    noise_sigma: f32,
) -> Result<RenderReport, DatasetError> {
    render_job(&RenderJob {
        path,
        frames,
        out_dir: out_dir.to_path_buf(),
        seed,
        camera,
        noise_sigma,
        realism: Realism::ideal(),
        world: WorldKind::Town,
    })
}

/// Everything a dataset render needs.
#[derive(Debug, Clone)]
pub struct RenderJob {
    /// The camera path.
    pub path: PathSpec,
    /// Frames, spread evenly over the path's time span.
    pub frames: usize,
    /// The dataset folder.
    pub out_dir: PathBuf,
    /// Seed of the world, the noise and every realism process.
    pub seed: u64,
    /// The camera.
    pub camera: SimCamera,
    /// The ideal sensor noise, grey levels (0: no noise at all, whatever
    /// the realism's sensor).
    pub noise_sigma: f32,
    /// Camera, light and vehicle effects.
    pub realism: Realism,
    /// The world.
    pub world: WorldKind,
}

/// The world a realism configuration sees: `kind`, with the sun of the
/// realism's time of day (the world's fixed sun without it).
pub fn world_params_for(kind: WorldKind, realism: &Realism) -> WorldParams {
    let mut p = WorldParams {
        kind,
        ..WorldParams::default()
    };
    if let Some(sun) = &realism.lighting.sun {
        let (az, el) = sun.position();
        p.sun_azimuth_deg = az;
        p.sun_elevation_deg = el;
    }
    p
}

/// The renderer a realism configuration sees (cloud shadows seeded from `seed`).
pub fn renderer_for(
    world: Arc<World>,
    camera: SimCamera,
    params: RenderParams,
    realism: &Realism,
    seed: u64,
) -> Renderer {
    let r = Renderer::new(world, camera, params);
    match realism.lighting.clouds {
        Some(mut c) => {
            c.seed ^= crate::texture::mix64(seed ^ 0xC10D5);
            r.with_clouds(c)
        }
        None => r,
    }
}

/// Renders a dataset (see [`RenderJob`] and the module documentation).
pub fn render_job(job: &RenderJob) -> Result<RenderReport, DatasetError> {
    job.camera.validate()?;
    if job.frames == 0 {
        return Err(DatasetError::NoFrames);
    }
    job.realism.validate()?;
    let t0 = Instant::now();
    let params = world_params_for(job.world, &job.realism);
    let world = Arc::new(World::generate_with(job.seed, &params)?);
    let world_seconds = t0.elapsed().as_secs_f64();
    tracing::info!(
        seed = job.seed,
        world = %job.world,
        boxes = world.boxes.len(),
        seconds = world_seconds,
        "world generated"
    );
    let camera_path = CameraPath::from_spec(&job.path, &world, PathParams::default())?;
    let render_params = RenderParams {
        noise_sigma: job.noise_sigma,
        ..RenderParams::default()
    };
    let renderer = Arc::new(renderer_for(
        world,
        job.camera,
        render_params,
        &job.realism,
        job.seed,
    ));
    let motion = PathMotion::new(&camera_path, &job.realism, job.seed);
    let mut imager = Imager::new(renderer, job.realism.camera.clone(), &job.realism.lighting);
    let mut report = write_dataset(
        &mut imager,
        &|t| motion.world_from_cam(&camera_path, t),
        &camera_path,
        job,
        motion.hold_error_rms_m(&camera_path),
    )?;
    report.world_seconds = world_seconds;
    Ok(report)
}

/// Renders `frames` frames spread evenly over `path` with `renderer` and
/// writes the dataset (see [`render_dataset`]).
pub fn render_path_dataset(
    renderer: &Renderer,
    path: &CameraPath,
    frames: usize,
    out_dir: &Path,
    seed: u64,
    spec: &PathSpec,
) -> Result<RenderReport, DatasetError> {
    let job = RenderJob {
        path: spec.clone(),
        frames,
        out_dir: out_dir.to_path_buf(),
        seed,
        camera: *renderer.camera(),
        noise_sigma: renderer.params().noise_sigma,
        realism: Realism::ideal(),
        world: WorldKind::Town,
    };
    let realism = Realism::ideal();
    let mut imager = Imager::new(
        Arc::new(renderer.clone()),
        realism.camera.clone(),
        &realism.lighting,
    );
    write_dataset(&mut imager, &|t| path.world_from_cam(t), path, &job, None)
}

/// The true camera motion along a path under the realism's vehicle
/// effects: the wind's hold sway on the position and the gimbal's pointing
/// error on the rotation.
pub struct PathMotion {
    sway: Option<HoldSway>,
    gimbal: Option<GimbalJitter>,
}

impl PathMotion {
    /// The motion for `path` (its sway integrated over the whole path).
    pub fn new(path: &CameraPath, realism: &Realism, seed: u64) -> PathMotion {
        let vehicle = crate::vehicle::VehicleParams::default();
        let sway = realism.vehicle.wind.map(|w| {
            let wind = WindField::new(w, seed);
            HoldSway::integrate(
                &wind,
                &|t| path.world_from_cam(t).translation.vector,
                path.start() - 1.0,
                path.end() + 1.0,
                vehicle.position_gain,
                vehicle.velocity_tau_s,
            )
        });
        let gimbal = realism.vehicle.gimbal.map(|g| GimbalJitter::new(g, seed));
        PathMotion { sway, gimbal }
    }

    /// The camera's true pose at `t`.
    pub fn world_from_cam(&self, path: &CameraPath, t: f64) -> Isometry3<f64> {
        let mut pose = path.world_from_cam(t);
        if let Some(s) = &self.sway {
            pose.translation.vector += s.offset(t);
        }
        match &self.gimbal {
            Some(g) => g.apply(&pose, t),
            None => pose,
        }
    }

    /// Rms horizontal hold error over the path, m (None without wind).
    pub fn hold_error_rms_m(&self, path: &CameraPath) -> Option<f64> {
        let s = self.sway.as_ref()?;
        let n = 1000;
        let sum: f64 = (0..n)
            .map(|k| {
                s.offset(path.start() + path.duration() * k as f64 / n as f64)
                    .xy()
                    .norm_squared()
            })
            .sum();
        Some((sum / n as f64).sqrt())
    }
}

/// Writes the frames of `imager` along `path`, the camera's true pose at
/// any time given by `pose_at`.
fn write_dataset(
    imager: &mut Imager,
    pose_at: &dyn Fn(f64) -> Isometry3<f64>,
    path: &CameraPath,
    job: &RenderJob,
    hold_error_rms_m: Option<f64>,
) -> Result<RenderReport, DatasetError> {
    let (frames, out_dir, seed) = (job.frames, job.out_dir.as_path(), job.seed);
    if frames == 0 {
        return Err(DatasetError::NoFrames);
    }
    let rgb_dir = out_dir.join("rgb");
    std::fs::create_dir_all(&rgb_dir).map_err(io_err(&rgb_dir))?;
    let camera = *imager.renderer().camera();
    let calib_path = out_dir.join("calib.txt");
    std::fs::write(&calib_path, format!("{}\n", camera.calib_line()))
        .map_err(io_err(&calib_path))?;
    let rgb_txt = out_dir.join("rgb.txt");
    let gt_txt = out_dir.join("groundtruth.txt");
    let mut rgb = BufWriter::new(File::create(&rgb_txt).map_err(io_err(&rgb_txt))?);
    let mut gt = BufWriter::new(File::create(&gt_txt).map_err(io_err(&gt_txt))?);
    writeln!(rgb, "{WORLD_FRAME_HEADER}\n# timestamp filename").map_err(io_err(&rgb_txt))?;
    writeln!(gt, "{WORLD_FRAME_HEADER}\n# timestamp tx ty tz qx qy qz qw")
        .map_err(io_err(&gt_txt))?;
    let tel_txt = out_dir.join("telemetry.txt");
    let mut tel = BufWriter::new(File::create(&tel_txt).map_err(io_err(&tel_txt))?);
    writeln!(tel, "{TELEMETRY_HEADER}").map_err(io_err(&tel_txt))?;
    let mut sensors = SensorErrors::new(&crate::vehicle::VehicleDisturbances::from_realism(
        &job.realism,
        seed,
    ));
    let mut t_sensors = path.start();
    // Exposure and rolling-shutter truth, only when the camera is not ideal.
    let realistic = !job.realism.is_ideal();
    let exp_txt = out_dir.join("exposures.txt");
    let rows_txt = out_dir.join("rows.txt");
    let mut exposures = None;
    let mut rows = None;
    if realistic {
        let mut e = BufWriter::new(File::create(&exp_txt).map_err(io_err(&exp_txt))?);
        writeln!(
            e,
            "# timestamp exposure_s gain readout_s blur_samples encoded_bytes\n\
             # timestamp: the centre row's mid-exposure (groundtruth.txt's pose); row y is exposed \
             around timestamp + (y - (height - 1) / 2) * readout_s / (height - 1)"
        )
        .map_err(io_err(&exp_txt))?;
        exposures = Some(e);
        if job.realism.camera.rolling_shutter.is_some() {
            let mut r = BufWriter::new(File::create(&rows_txt).map_err(io_err(&rows_txt))?);
            writeln!(
                r,
                "{WORLD_FRAME_HEADER}\n# timestamp row row_time tx ty tz qx qy qz qw\n\
                 # the mid-exposure pose of every {}th row (and the last) of each frame; a row \
                 between two knots was rendered from their interpolation by row (linear in \
                 translation, slerp in rotation)",
                crate::imaging::ROW_KNOT_STEP
            )
            .map_err(io_err(&rows_txt))?;
            rows = Some(r);
        }
    }
    let noisy = job.noise_sigma > 0.0;
    let (mut render_s, mut write_s, mut cpu_s) = (0.0, 0.0, Some(0.0));
    let (mut bytes_total, mut exposure_total, mut samples_total) = (0usize, 0.0, 0usize);
    let step = if frames > 1 {
        path.duration() / (frames - 1) as f64
    } else {
        0.0
    };
    let mut first_last = (path.start(), path.start());
    for i in 0..frames {
        let t = path.start() + step * i as f64;
        first_last.1 = t;
        let c0 = thread_cpu_seconds();
        let w0 = Instant::now();
        let noise_seed = noisy
            .then(|| crate::texture::mix64(seed ^ (i as u64).wrapping_mul(0x2545_f491_4f6c_dd1d)));
        let shot = imager
            .capture(t, pose_at, noise_seed)
            .map_err(|e| DatasetError::Io {
                path: rgb_dir.clone(),
                source: std::io::Error::other(e.to_string()),
            })?;
        render_s += w0.elapsed().as_secs_f64();
        cpu_s = match (cpu_s, c0, thread_cpu_seconds()) {
            (Some(acc), Some(a), Some(b)) => Some(acc + (b - a)),
            _ => None,
        };
        exposure_total += shot.exposure_s;
        samples_total += shot.blur_samples;
        let w1 = Instant::now();
        if shot.encoded_kind == Some(crate::imaging::EncodedKind::H264) {
            // The stream's bytes are H.264: counted, the decoded frame saved.
            bytes_total += shot.encoded.as_ref().map_or(0, Vec::len);
        }
        let jpeg = shot
            .encoded
            .as_ref()
            .filter(|_| shot.encoded_kind == Some(crate::imaging::EncodedKind::Jpeg));
        let name = match jpeg {
            Some(bytes) => {
                // The stream's own bytes: decoding them gives `shot.image`.
                let name = format!("{t:.6}.jpg");
                let file = rgb_dir.join(&name);
                std::fs::write(&file, bytes).map_err(io_err(&file))?;
                bytes_total += bytes.len();
                name
            }
            None => {
                let name = format!("{t:.6}.png");
                let file = rgb_dir.join(&name);
                shot.image
                    .save(&file)
                    .map_err(|source| DatasetError::Image {
                        path: file.clone(),
                        source,
                    })?;
                name
            }
        };
        writeln!(rgb, "{t:.6} rgb/{name}").map_err(io_err(&rgb_txt))?;
        writeln!(gt, "{}", tum_line(t, &shot.world_from_cam)).map_err(io_err(&gt_txt))?;
        sensors.step(t, t - t_sensors);
        t_sensors = t;
        writeln!(tel, "{}", telemetry_line(t, &shot.world_from_cam, &sensors))
            .map_err(io_err(&tel_txt))?;
        if let Some(e) = exposures.as_mut() {
            writeln!(
                e,
                "{t:.6} {:.9} {:.4} {:.6} {} {}",
                shot.exposure_s,
                shot.gain,
                shot.readout_s,
                shot.blur_samples,
                shot.encoded.as_ref().map_or(0, Vec::len)
            )
            .map_err(io_err(&exp_txt))?;
        }
        if let Some(r) = rows.as_mut() {
            for k in &shot.row_knots {
                writeln!(
                    r,
                    "{t:.6} {} {}",
                    k.row,
                    tum_line(k.time_s, &k.world_from_cam)
                )
                .map_err(io_err(&rows_txt))?;
            }
        }
        write_s += w1.elapsed().as_secs_f64();
        if (i + 1) % 50 == 0 || i + 1 == frames {
            tracing::info!(
                frame = i + 1,
                of = frames,
                render_fps = (i + 1) as f64 / render_s.max(1e-9),
                "rendering"
            );
        }
    }
    rgb.flush().map_err(io_err(&rgb_txt))?;
    gt.flush().map_err(io_err(&gt_txt))?;
    tel.flush().map_err(io_err(&tel_txt))?;
    if let Some(mut e) = exposures {
        e.flush().map_err(io_err(&exp_txt))?;
    }
    if let Some(mut r) = rows {
        r.flush().map_err(io_err(&rows_txt))?;
    }
    let frame_rate = if path.duration() > 0.0 && frames > 1 {
        (frames - 1) as f64 / path.duration()
    } else {
        0.0
    };
    let bytes_per_frame = (bytes_total > 0).then(|| bytes_total as f64 / frames as f64);
    let report = RenderReport {
        frames,
        out_dir: out_dir.to_path_buf(),
        time_span_s: first_last,
        world_seconds: 0.0,
        render_seconds: render_s,
        render_cpu_seconds: cpu_s,
        write_seconds: write_s,
        realism: job.realism.name.clone(),
        world: job.world.name().to_string(),
        bytes_per_frame,
        bitrate_bit_s: bytes_per_frame.map(|b| b * 8.0 * frame_rate),
        mean_exposure_s: realistic.then(|| exposure_total / frames as f64),
        mean_blur_samples: samples_total as f64 / frames as f64,
        hold_error_rms_m,
    };
    let info_path = out_dir.join("render_info.json");
    let info = serde_json::json!({
        "seed": seed,
        "path": format!("{:?}", job.path),
        "camera": camera,
        "noise_sigma": job.noise_sigma,
        "world": job.world.name(),
        "realism": job.realism.name,
        "effects_on": job.realism.effects_on(),
        "codec": imager.codec_description(),
        "illuminance_lux": imager.illuminance_lux(),
        "world_frame": WORLD_FRAME_HEADER.trim_start_matches("# "),
        "report": &report,
    });
    let text = serde_json::to_string_pretty(&info).map_err(|e| DatasetError::Io {
        path: info_path.clone(),
        source: std::io::Error::other(e),
    })?;
    std::fs::write(&info_path, text).map_err(io_err(&info_path))?;
    Ok(report)
}

/// One line of `telemetry.txt` (see [`TELEMETRY_HEADER`]) for a camera
/// truly at `world_from_cam` with the sensors' errors now.
fn telemetry_line(t: f64, world_from_cam: &Isometry3<f64>, sensors: &SensorErrors) -> String {
    let c = world_from_cam.translation.vector;
    let gps = c - sensors.gnss_error();
    let baro_alt = -c.z + sensors.baro_error();
    let (h_acc, v_acc) = sensors.reported_accuracy();
    // The camera's forward (z) and up (-y) axes in NED: its pitch, and the
    // heading of the body (the gimbal is stabilised, the body level).
    let r = world_from_cam.rotation;
    let f = r * nalgebra::Vector3::z();
    let u = -(r * nalgebra::Vector3::y());
    let pitch = (-f.z).clamp(-1.0, 1.0).asin();
    let h = f.xy() * pitch.cos() - u.xy() * pitch.sin();
    let yaw = h.y.atan2(h.x);
    // The attitude as reported: the body's roll and pitch errors (a level
    // body), the heading's, and the gimbal's pitch error (`ahrs`).
    let e = sensors.attitude_error_deg();
    let yaw_deg = (yaw.to_degrees() + e.z + 180.0).rem_euclid(360.0) - 180.0;
    format!(
        "{t:.6} {} {:.4} {:.4} {:.4} {h_acc:.3} {v_acc:.3} {baro_alt:.4} {:.3} {:.3} {yaw_deg:.3} {:.3} 0.000",
        u8::from(sensors.fix()),
        gps.x,
        gps.y,
        gps.z,
        e.x,
        e.y,
        pitch.to_degrees() + e.y,
    )
}

/// Appends live ground truth to a folder while the simulator runs:
/// `groundtruth.txt` (the camera trajectory, TUM, world_from_cam),
/// `frames.txt` (`seq capture_time_unix_s tx ty tz qx qy qz qw` per video
/// frame) and `calib.txt`. Every line is flushed as it is written, so a
/// reader sees it at once.
#[derive(Debug)]
pub struct TruthWriter {
    dir: PathBuf,
    trajectory: BufWriter<File>,
    frames: BufWriter<File>,
}

impl TruthWriter {
    /// Creates the folder (if needed) and the files, with their headers.
    pub fn create(dir: &Path, camera: &SimCamera) -> Result<TruthWriter, DatasetError> {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        let calib = dir.join("calib.txt");
        std::fs::write(&calib, format!("{}\n", camera.calib_line())).map_err(io_err(&calib))?;
        let traj_path = dir.join("groundtruth.txt");
        let frames_path = dir.join("frames.txt");
        let mut trajectory = BufWriter::new(File::create(&traj_path).map_err(io_err(&traj_path))?);
        let mut frames = BufWriter::new(File::create(&frames_path).map_err(io_err(&frames_path))?);
        writeln!(
            trajectory,
            "{WORLD_FRAME_HEADER}\n# timestamp(unix s) tx ty tz qx qy qz qw"
        )
        .and_then(|_| trajectory.flush())
        .map_err(io_err(&traj_path))?;
        writeln!(
            frames,
            "{WORLD_FRAME_HEADER}\n# seq capture_time_unix_s tx ty tz qx qy qz qw"
        )
        .and_then(|_| frames.flush())
        .map_err(io_err(&frames_path))?;
        Ok(TruthWriter {
            dir: dir.to_path_buf(),
            trajectory,
            frames,
        })
    }

    /// The folder written to.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// Appends a camera pose to `groundtruth.txt`.
    pub fn write_pose(
        &mut self,
        timestamp: f64,
        world_from_cam: &Isometry3<f64>,
    ) -> Result<(), DatasetError> {
        let path = self.dir.join("groundtruth.txt");
        writeln!(self.trajectory, "{}", tum_line(timestamp, world_from_cam))
            .and_then(|_| self.trajectory.flush())
            .map_err(io_err(&path))
    }

    /// Appends a video frame's sequence number, capture time and camera pose to `frames.txt`.
    pub fn write_frame(
        &mut self,
        seq: u64,
        capture_time_unix_s: f64,
        world_from_cam: &Isometry3<f64>,
    ) -> Result<(), DatasetError> {
        let path = self.dir.join("frames.txt");
        writeln!(
            self.frames,
            "{seq} {}",
            tum_line(capture_time_unix_s, world_from_cam)
        )
        .and_then(|_| self.frames.flush())
        .map_err(io_err(&path))
    }
}

/// Reads a `frames.txt` written by [`TruthWriter::write_frame`]: each video
/// frame's capture time (unix seconds) and camera pose (`world_from_cam`),
/// in the order written. Errors name the file and line, as [`parse_tum`].
pub fn read_truth_frames(path: &Path) -> Result<Vec<(f64, Isometry3<f64>)>, PathError> {
    let text = std::fs::read_to_string(path).map_err(|source| PathError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    // Drop each line's leading sequence number; comments and line numbers stay.
    let tum: Vec<&str> = text
        .lines()
        .map(|l| {
            let l = l.trim();
            if l.starts_with('#') {
                l
            } else {
                l.split_once(char::is_whitespace)
                    .map_or("", |(_, rest)| rest)
            }
        })
        .collect();
    parse_tum(&tum.join("\n"), path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::paths::{look_at, read_tum};
    use crate::world::WorldParams;
    use nalgebra::Point3;

    #[test]
    fn dataset_layout_and_ground_truth_round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let world = Arc::new(World::generate_with(2, &WorldParams::tiny()).unwrap());
        let cam = SimCamera {
            width: 160,
            height: 120,
            fx: 115.0,
            fy: 115.0,
            cx: 79.5,
            cy: 59.5,
            ..SimCamera::default()
        };
        let renderer = Renderer::new(world.clone(), cam, RenderParams::default());
        let path = CameraPath::orbit(PathParams::default());
        let report =
            render_path_dataset(&renderer, &path, 5, dir.path(), 2, &PathSpec::Orbit).unwrap();
        assert_eq!(report.frames, 5);
        assert_eq!(report.time_span_s, (0.0, 60.0));
        let rgb = std::fs::read_to_string(dir.path().join("rgb.txt")).unwrap();
        let lines: Vec<&str> = rgb.lines().filter(|l| !l.starts_with('#')).collect();
        assert_eq!(lines.len(), 5);
        assert_eq!(lines[1], "15.000000 rgb/15.000000.png");
        let img = image::open(dir.path().join("rgb/15.000000.png"))
            .unwrap()
            .to_luma8();
        assert_eq!(
            img,
            renderer.render_noisy(
                &path.world_from_cam(15.0),
                crate::texture::mix64(2 ^ 0x2545_f491_4f6c_dd1d)
            )
        );
        let gt = read_tum(&dir.path().join("groundtruth.txt")).unwrap();
        assert_eq!(gt.len(), 5);
        let expected = path.world_from_cam(45.0);
        assert!((gt[3].1.translation.vector - expected.translation.vector).norm() < 1e-5);
        assert!(gt[3].1.rotation.angle_to(&expected.rotation) < 1e-8);
        assert!(
            std::fs::read_to_string(dir.path().join("groundtruth.txt"))
                .unwrap()
                .starts_with("# world frame: local NED")
        );
        let calib = std::fs::read_to_string(dir.path().join("calib.txt")).unwrap();
        let vals: Vec<f64> = calib
            .split_whitespace()
            .map(|v| v.parse().unwrap())
            .collect();
        assert_eq!(
            vals,
            vec![115.0, 115.0, 79.5, 59.5, -0.05, 0.01, 0.0005, -0.0003, 0.0]
        );
        assert!(dir.path().join("render_info.json").exists());
        // Ideal realism: the telemetry is the truth, one line per frame.
        let tel = std::fs::read_to_string(dir.path().join("telemetry.txt")).unwrap();
        let rows: Vec<Vec<f64>> = tel
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| l.split_whitespace().map(|v| v.parse().unwrap()).collect())
            .collect();
        assert_eq!(rows.len(), 5);
        for (row, (t, pose)) in rows.iter().zip(&gt) {
            assert_eq!(row.len(), 13);
            assert!((row[0] - t).abs() < 1e-6);
            assert_eq!(row[1], 1.0);
            let c = pose.translation.vector;
            assert!((nalgebra::Vector3::new(row[2], row[3], row[4]) - c).norm() < 1e-3);
            assert!((row[7] + c.z).abs() < 1e-3);
        }
    }

    #[test]
    fn telemetry_attitude_and_sensor_errors_follow_the_realism() {
        // A camera 30 m up, looking 40 degrees down towards the east: yaw
        // 90, gimbal pitch -40 (a half turn from the identity camera).
        let cam = |eye: Point3<f64>, yaw: f64, pitch: f64| {
            crate::paths::camera_from_yaw_pitch(eye, yaw.to_radians(), pitch.to_radians())
        };
        let eye = Point3::new(5.0, -3.0, -30.0);
        let pose = cam(eye, 90.0, 40.0);
        let ideal = SensorErrors::new(&crate::vehicle::VehicleDisturbances::default());
        let line = telemetry_line(1.0, &pose, &ideal);
        let v: Vec<f64> = line
            .split_whitespace()
            .map(|x| x.parse().unwrap())
            .collect();
        assert!((v[10] - 90.0).abs() < 0.01, "{line}");
        assert!((v[11] + 40.0).abs() < 0.01, "{line}");
        assert!((v[7] - 30.0).abs() < 1e-3, "{line}");
        // Straight down keeps the heading of the image's top.
        let down = cam(eye, 30.0, 90.0);
        let v: Vec<f64> = telemetry_line(1.0, &down, &ideal)
            .split_whitespace()
            .map(|x| x.parse().unwrap())
            .collect();
        assert!((v[11] + 90.0).abs() < 0.01);
        assert!((v[10] - 30.0).abs() < 0.01);
        // The field preset's GNSS: errors of its sigma over a long flight,
        // a reported accuracy of its sigmas, fix losses now and then.
        let field = Realism::field();
        let mut s = SensorErrors::new(&crate::vehicle::VehicleDisturbances::from_realism(
            &field, 7,
        ));
        let dt = 1.0 / 15.0;
        let (mut sum2, mut n, mut lost) = (0.0, 0usize, 0usize);
        for k in 1..=(15 * 7200) {
            s.step(k as f64 * dt, dt);
            sum2 += s.gnss_error().x.powi(2);
            n += 1;
            lost += usize::from(!s.fix());
        }
        let rms = (sum2 / n as f64).sqrt();
        let (h_acc, v_acc) = s.reported_accuracy();
        assert!((h_acc - 1.3f64.hypot(0.05)).abs() < 1e-9);
        assert!((v_acc - 0.8f64.hypot(0.05)).abs() < 1e-9);
        // Two hours hold 60 correlation times: the rms is the sigma to
        // about 20 %.
        assert!(rms > 0.6 * 1.3 && rms < 1.5 * 1.3, "rms {rms}");
        assert!(
            lost > 0 && (lost as f64) < 0.05 * n as f64,
            "lost {lost} of {n}"
        );
    }

    #[test]
    fn a_tum_file_path_renders_over_its_time_span() {
        let dir = tempfile::tempdir().unwrap();
        let traj = dir.path().join("traj.txt");
        let a = look_at(Point3::new(-20.0, 0.0, -15.0), Point3::new(0.0, 0.0, 0.0));
        let b = look_at(Point3::new(-10.0, 10.0, -20.0), Point3::new(0.0, 0.0, 0.0));
        std::fs::write(
            &traj,
            format!(
                "{}\n{}\n",
                crate::paths::tum_line(100.0, &a),
                crate::paths::tum_line(102.0, &b)
            ),
        )
        .unwrap();
        let world = Arc::new(World::generate_with(3, &WorldParams::tiny()).unwrap());
        let spec: PathSpec = traj.to_str().unwrap().parse().unwrap();
        let path = CameraPath::from_spec(&spec, &world, PathParams::default()).unwrap();
        let cam = SimCamera {
            width: 64,
            height: 48,
            fx: 46.0,
            fy: 46.0,
            cx: 31.5,
            cy: 23.5,
            ..SimCamera::default()
        };
        let renderer = Renderer::new(
            world,
            cam,
            RenderParams {
                noise_sigma: 0.0,
                ..RenderParams::default()
            },
        );
        let out = dir.path().join("out");
        let report = render_path_dataset(&renderer, &path, 3, &out, 0, &spec).unwrap();
        assert_eq!(report.time_span_s, (100.0, 102.0));
        let gt = read_tum(&out.join("groundtruth.txt")).unwrap();
        assert_eq!(
            gt.iter().map(|g| g.0).collect::<Vec<_>>(),
            vec![100.0, 101.0, 102.0]
        );
        assert!((gt[2].1.translation.vector - b.translation.vector).norm() < 1e-5);
        // Noise-free frames equal a direct render.
        let img = image::open(out.join("rgb/101.000000.png"))
            .unwrap()
            .to_luma8();
        assert_eq!(img, renderer.render(&path.world_from_cam(101.0)));
        // A missing file is a typed error.
        let missing: PathSpec = "/nonexistent/traj.txt".parse().unwrap();
        assert!(matches!(
            CameraPath::from_spec(&missing, renderer.world(), PathParams::default()),
            Err(PathError::Io { .. })
        ));
    }

    #[test]
    fn truth_writer_appends_readable_lines() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = TruthWriter::create(&dir.path().join("truth"), &SimCamera::default()).unwrap();
        let a = look_at(Point3::new(1.0, 2.0, -30.0), Point3::new(0.0, 0.0, 0.0));
        w.write_pose(1_700_000_000.25, &a).unwrap();
        w.write_frame(7, 1_700_000_000.5, &a).unwrap();
        // Flushed: readable before the writer is dropped.
        let gt = read_tum(&dir.path().join("truth/groundtruth.txt")).unwrap();
        assert_eq!(gt.len(), 1);
        assert!((gt[0].0 - 1_700_000_000.25).abs() < 1e-6);
        let frames = std::fs::read_to_string(dir.path().join("truth/frames.txt")).unwrap();
        let last = frames.lines().last().unwrap();
        assert!(
            last.starts_with("7 1700000000.500000 1.000000 2.000000 -30.000000"),
            "{last}"
        );
        let back = read_truth_frames(&dir.path().join("truth/frames.txt")).unwrap();
        assert_eq!(back.len(), 1);
        assert!((back[0].0 - 1_700_000_000.5).abs() < 1e-6);
        assert!((back[0].1.translation.vector - a.translation.vector).norm() < 1e-5);
        assert!(back[0].1.rotation.angle_to(&a.rotation) < 1e-5);
    }
}
