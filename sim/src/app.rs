//! The running simulator: a fixed-step real-time clock driving the
//! autopilot (and the scripted operator), the MAVLink link, captures
//! rendered to files, and video frames rendered at the video rate.
//!
//! [`run`] is the library entry: the `shotpilot-sim` binary calls it, and
//! the shotpilot daemon can call it to start the world in-process.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use mavlink::dialects::common::MavMessage;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use crate::autopilot::{Autopilot, AutopilotParams, CaptureRequest, Flavour};
use crate::camera::SimCamera;
use crate::dataset::TruthWriter;
use crate::link::{Endpoint, LinkError, LinkParams, LinkStats, RadioParams, spawn_link};
use crate::render::{RenderParams, Renderer};
use crate::script::{Script, ScriptKind, ScriptParams};
use crate::video::{VideoFrame, serve_video, try_encode_jpeg};
use crate::world::World;

/// Errors that stop the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The MAVLink link could not be opened.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// A directory could not be created or a file written.
    #[error("{what} {path}: {source}")]
    Io {
        /// What we were doing.
        what: &'static str,
        /// The path.
        path: PathBuf,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// A configuration value is out of range.
    #[error("bad configuration: {field} = {value}: {reason}")]
    Config {
        /// The field.
        field: &'static str,
        /// Its value.
        value: String,
        /// Why it is refused.
        reason: &'static str,
    },
}

/// Everything the simulator needs. `Default` is the documented default of
/// every command-line flag.
#[derive(Debug, Clone)]
pub struct SimConfig {
    /// The MAVLink endpoint (default `udpout:127.0.0.1:14550`, where PX4
    /// SITL sends and ground stations listen).
    pub mavlink: Endpoint,
    /// Address of the MJPEG video server (None: no video server).
    pub video_listen: Option<SocketAddr>,
    /// Video frame rate, frames per second.
    pub video_fps: f64,
    /// JPEG quality of video frames and captures (1-100).
    pub jpeg_quality: u8,
    /// The bad radio.
    pub radio: RadioParams,
    /// World seed (also seeds sensor noise).
    pub seed: u64,
    /// The scripted operator, if any.
    pub script: Option<ScriptKind>,
    /// Script tunables.
    pub script_params: ScriptParams,
    /// Where IMAGE_START_CAPTURE pictures go.
    pub capture_dir: PathBuf,
    /// Where the ground-truth trajectory of the video frames goes (None:
    /// not written).
    pub truth_dir: Option<PathBuf>,
    /// Autopilot, vehicle and flavour.
    pub autopilot: AutopilotParams,
    /// Simulation steps per second.
    pub step_hz: f64,
    /// The gimbal camera.
    pub camera: SimCamera,
    /// The renderer.
    pub render: RenderParams,
    /// Add sensor noise to frames.
    pub sensor_noise: bool,
    /// Video frames rendered at the same time (on blocking threads); a
    /// frame falling due while this many are rendering is skipped.
    pub max_renders_in_flight: usize,
}

impl Default for SimConfig {
    fn default() -> Self {
        Self {
            mavlink: Endpoint::UdpOut("127.0.0.1:14550".into()),
            video_listen: Some(SocketAddr::from(([127, 0, 0, 1], 8554))),
            video_fps: 15.0,
            jpeg_quality: 90,
            radio: RadioParams::default(),
            seed: 1,
            script: None,
            script_params: ScriptParams::default(),
            capture_dir: PathBuf::from("captures"),
            truth_dir: None,
            autopilot: AutopilotParams::default(),
            step_hz: 50.0,
            camera: SimCamera::default(),
            render: RenderParams::default(),
            sensor_noise: true,
            max_renders_in_flight: 2,
        }
    }
}

impl SimConfig {
    /// The flavour shortcut.
    pub fn with_flavour(mut self, flavour: Flavour) -> Self {
        self.autopilot.flavour = flavour;
        self
    }

    fn validate(&self) -> Result<(), SimError> {
        let bad = |field, value: String, reason| {
            Err(SimError::Config {
                field,
                value,
                reason,
            })
        };
        if !(self.video_fps > 0.0 && self.video_fps <= 120.0) {
            return bad(
                "video_fps",
                self.video_fps.to_string(),
                "must be in (0, 120]",
            );
        }
        if !(self.step_hz >= 10.0 && self.step_hz <= 1000.0) {
            return bad("step_hz", self.step_hz.to_string(), "must be in [10, 1000]");
        }
        if !(1..=100).contains(&self.jpeg_quality) {
            return bad(
                "jpeg_quality",
                self.jpeg_quality.to_string(),
                "must be 1-100",
            );
        }
        if let Err((field, reason)) = self.autopilot.vehicle.gps_bias.check() {
            let b = &self.autopilot.vehicle.gps_bias;
            return bad(
                "gps_bias",
                format!(
                    "{field} (sigma_xy_m {}, sigma_z_m {}, tau_s {})",
                    b.sigma_xy_m, b.sigma_z_m, b.tau_s
                ),
                reason,
            );
        }
        for (name, p) in [
            ("drop up", self.radio.up.drop),
            ("drop down", self.radio.down.drop),
            ("corrupt up", self.radio.up.corrupt),
            ("corrupt down", self.radio.down.corrupt),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return bad(
                    "radio",
                    format!("{name} {p}"),
                    "probability must be in [0, 1]",
                );
            }
        }
        for (name, l) in [
            ("latency up", self.radio.up.latency_s),
            ("latency down", self.radio.down.latency_s),
        ] {
            if !(0.0..=60.0).contains(&l) {
                return bad(
                    "radio",
                    format!("{name} {l}"),
                    "latency must be in [0, 60] s",
                );
            }
        }
        Ok(())
    }
}

/// What a finished run reports.
#[derive(Debug, Clone, Default)]
pub struct RunSummary {
    /// Simulated seconds.
    pub sim_seconds: f64,
    /// Video frames rendered.
    pub frames: u64,
    /// Video frames skipped because rendering could not keep up.
    pub frames_skipped: u64,
    /// Captures written.
    pub captures: u64,
    /// Link counters at the end.
    pub link: LinkStats,
}

fn unix_now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

fn write_capture(
    renderer: &Renderer,
    req: &CaptureRequest,
    dir: &Path,
    quality: u8,
    noise_seed: Option<u64>,
) -> Result<PathBuf, SimError> {
    let img = match noise_seed {
        Some(s) => renderer.render_noisy(&req.world_from_cam, s),
        None => renderer.render(&req.world_from_cam),
    };
    std::fs::create_dir_all(dir).map_err(|source| SimError::Io {
        what: "creating capture dir",
        path: dir.to_path_buf(),
        source,
    })?;
    let path = dir.join(format!("IMG_{:04}.jpg", req.index));
    let jpeg = try_encode_jpeg(&img, quality).map_err(|e| SimError::Io {
        what: "encoding",
        path: path.clone(),
        source: std::io::Error::other(e.to_string()),
    })?;
    std::fs::write(&path, jpeg).map_err(|source| SimError::Io {
        what: "writing",
        path: path.clone(),
        source,
    })?;
    Ok(std::path::absolute(&path).unwrap_or(path))
}

/// Run the simulator until `cancel` fires, serving video on
/// `config.video_listen` (if set).
pub async fn run(config: SimConfig, cancel: CancellationToken) -> Result<RunSummary, SimError> {
    run_announcing(config, cancel, false).await
}

/// [`run`]; with `announce`, once the video server and the MAVLink
/// endpoint are open, one line on stdout gives their bound addresses
/// (`shotpilot-sim bound: video=ADDR mavlink=ADDR`, `-` for none), so a
/// caller that asked for port 0 knows where to connect.
pub async fn run_announcing(
    config: SimConfig,
    cancel: CancellationToken,
    announce: bool,
) -> Result<RunSummary, SimError> {
    config.validate()?;
    let (video_tx, video_rx) = watch::channel(None);
    let mut video_bound = None;
    if let Some(addr) = config.video_listen {
        let listener = tokio::net::TcpListener::bind(addr)
            .await
            .map_err(|source| SimError::Io {
                what: "binding the video server on",
                path: PathBuf::from(addr.to_string()),
                source,
            })?;
        video_bound = listener.local_addr().ok();
        let c = cancel.clone();
        tokio::spawn(async move {
            if let Err(e) = serve_video(listener, video_rx, c).await {
                tracing::error!("video server: {e}");
            }
        });
    } else {
        drop(video_rx);
    }
    run_inner(config, cancel, video_tx, announce.then_some(video_bound)).await
}

/// [`run`] without its video server: frames are published on `video_tx`
/// (rendered only while someone holds a receiver, or truth is written).
/// The shotpilot daemon uses this to run the world in-process.
pub async fn run_with(
    config: SimConfig,
    cancel: CancellationToken,
    video_tx: watch::Sender<Option<Arc<VideoFrame>>>,
) -> Result<RunSummary, SimError> {
    run_inner(config, cancel, video_tx, None).await
}

/// The simulation; `announce` (Some: the video server's bound address)
/// prints the bound addresses once the link is open.
async fn run_inner(
    config: SimConfig,
    cancel: CancellationToken,
    video_tx: watch::Sender<Option<Arc<VideoFrame>>>,
    announce: Option<Option<SocketAddr>>,
) -> Result<RunSummary, SimError> {
    config.validate()?;
    let mut truth = match &config.truth_dir {
        Some(dir) => Some(
            TruthWriter::create(dir, &config.camera).map_err(|e| SimError::Io {
                what: "creating truth files in",
                path: dir.clone(),
                source: std::io::Error::other(e.to_string()),
            })?,
        ),
        None => None,
    };
    let world = Arc::new(World::generate(config.seed));
    let renderer = Arc::new(Renderer::new(world.clone(), config.camera, config.render));
    let mut link = spawn_link(
        LinkParams {
            endpoint: config.mavlink.clone(),
            radio: config.radio,
            system_id: config.autopilot.system_id,
            component_id: config.autopilot.component_id,
        },
        cancel.clone(),
    )
    .await?;
    if let Some(video) = announce {
        let show = |a: Option<SocketAddr>| a.map_or("-".to_string(), |a| a.to_string());
        println!(
            "shotpilot-sim bound: video={} mavlink={}",
            show(video),
            show(link.local_addr)
        );
        use std::io::Write as _;
        let _ = std::io::stdout().flush();
    }
    tracing::info!(
        "shotpilot-sim: MAVLink on {}, flavour {:?}, radio {:?}",
        config.mavlink,
        config.autopilot.flavour,
        config.radio
    );
    let unix_at_boot = unix_now();
    let mut ap = Autopilot::new(config.autopilot.clone(), unix_at_boot);
    let mut script = config.script.map(|kind| {
        let w = world.clone();
        Script::new(kind, config.script_params.clone(), &move |x, y, r| {
            w.max_height_near(x, y, r)
        })
    });
    if let Some(s) = &script {
        tracing::info!("script: {} legs, {:.0} m", s.legs().len(), s.length_m());
    }

    let dt = 1.0 / config.step_hz;
    let frame_dt = 1.0 / config.video_fps;
    let mut ticker = tokio::time::interval(Duration::from_secs_f64(dt));
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Burst);
    let (cap_tx, mut cap_rx) = mpsc::channel::<(CaptureRequest, Option<String>)>(64);
    let (frame_done_tx, mut frame_done_rx) = mpsc::channel::<()>(16);
    let mut renders_in_flight = 0usize;
    // Frames may finish out of order when two render at once: only a newer
    // frame replaces the published one.
    let newest_published = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let mut next_frame_t = 0.0;
    let mut summary = RunSummary::default();
    let mut k: u64 = 0;
    let send = |link: &crate::link::LinkHandle, msgs: Vec<MavMessage>| {
        for m in msgs {
            if link.to_link.try_send(m).is_err() {
                tracing::debug!("link outbox full: message dropped");
            }
        }
    };
    loop {
        tokio::select! {
            _ = cancel.cancelled() => break,
            _ = ticker.tick() => {}
        }
        k += 1;
        let t = k as f64 * dt;
        while let Ok((h, m)) = link.from_link.try_recv() {
            let replies = ap.handle(&h, &m);
            send(&link, replies);
        }
        if let Some(s) = &mut script {
            s.step(&mut ap, t);
        }
        let out = ap.step(t, dt);
        send(&link, out);
        for req in ap.take_capture_requests() {
            let renderer = renderer.clone();
            let dir = config.capture_dir.clone();
            let q = config.jpeg_quality;
            let tx = cap_tx.clone();
            let noise = config
                .sensor_noise
                .then_some(config.seed ^ 0xCA9 ^ req.index as u64);
            tokio::task::spawn_blocking(move || {
                let url = match write_capture(&renderer, &req, &dir, q, noise) {
                    Ok(p) => Some(format!("file://{}", p.display())),
                    Err(e) => {
                        tracing::warn!("capture {}: {e}", req.index);
                        None
                    }
                };
                let _ = tx.blocking_send((req, url));
            });
        }
        while let Ok((req, url)) = cap_rx.try_recv() {
            if url.is_some() {
                summary.captures += 1;
            }
            let msg = ap.capture_done(&req, url.as_deref());
            send(&link, vec![msg]);
        }
        while frame_done_rx.try_recv().is_ok() {
            renders_in_flight = renders_in_flight.saturating_sub(1);
        }
        let want_frames = video_tx.receiver_count() > 0 || config.truth_dir.is_some();
        if want_frames && t + 1e-9 >= next_frame_t {
            next_frame_t += frame_dt;
            if next_frame_t < t {
                next_frame_t = t + frame_dt;
            }
            // The true pose (GPS bias included): what the camera films and
            // what the truth files record.
            let wfc = ap.vehicle().true_world_from_cam();
            let capture_time = unix_at_boot + t;
            if let Some(w) = &mut truth
                && let Err(e) = w.write_pose(capture_time, &wfc)
            {
                tracing::warn!("truth: {e}");
            }
            if renders_in_flight >= config.max_renders_in_flight.max(1) {
                summary.frames_skipped += 1;
            } else {
                renders_in_flight += 1;
                summary.frames += 1;
                let seq = summary.frames - 1;
                if let Some(w) = &mut truth
                    && let Err(e) = w.write_frame(seq, capture_time, &wfc)
                {
                    tracing::warn!("truth: {e}");
                }
                let renderer = renderer.clone();
                let tx = video_tx.clone();
                let done = frame_done_tx.clone();
                let newest = newest_published.clone();
                let q = config.jpeg_quality;
                let noise = config
                    .sensor_noise
                    .then_some(config.seed ^ seq.wrapping_mul(0x9E37_79B9));
                tokio::task::spawn_blocking(move || {
                    let img = match noise {
                        Some(s) => renderer.render_noisy(&wfc, s),
                        None => renderer.render(&wfc),
                    };
                    match VideoFrame::encode(&img, q, capture_time, seq) {
                        Ok(frame) => {
                            tx.send_if_modified(|slot| {
                                use std::sync::atomic::Ordering;
                                if seq == 0 || newest.fetch_max(seq, Ordering::AcqRel) < seq {
                                    *slot = Some(Arc::new(frame));
                                    true
                                } else {
                                    false
                                }
                            });
                        }
                        Err(e) => tracing::warn!("video frame: {e}"),
                    }
                    let _ = done.blocking_send(());
                });
            }
        }
        summary.sim_seconds = t;
    }
    summary.link = *link.stats.borrow();
    Ok(summary)
}
