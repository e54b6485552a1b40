//! The running simulator: a fixed-step real-time clock driving the
//! autopilot (and the scripted operator), the MAVLink link, captures
//! rendered to files, and video frames rendered at the video rate.
//!
//! [`run`] is the library entry: the `shotpilot-sim` binary calls it, and
//! the shotpilot daemon can call it to start the world in-process.
//!
//! Realism ([`SimConfig::with_realism`]): the vehicle effects live in the
//! vehicle ([`crate::vehicle::VehicleDisturbances`]); telemetry follows the
//! preset's stream rates over its radio; with any camera effect on, video
//! frames go through [`crate::imaging::Imager`], exposed over the true
//! motion of the last steps ([`crate::live`]) and timed
//! [`crate::live::LIVE_EXPOSURE_LAG_S`] behind the clock (their
//! X-Timestamp and truth are the centre row's mid-exposure; the per-row
//! poses of a rolling shutter are written by `render` datasets only, in
//! `rows.txt`); with a video
//! latency, each frame is published its latency after its capture time.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use image::GrayImage;
use mavlink::dialects::common::MavMessage;
use tokio::sync::{mpsc, watch};
use tokio_util::sync::CancellationToken;

use crate::autopilot::{Autopilot, AutopilotParams, CaptureRequest, Flavour};
use crate::camera::SimCamera;
use crate::clock::unix_now;
use crate::dataset::{TruthWriter, renderer_for, world_params_for};
use crate::disturbance::LatencyProcess;
use crate::imaging::Imager;
use crate::link::{
    Endpoint, LinkError, LinkParams, LinkStats, Outgoing, RadioParams, spawn_link_on,
};
use crate::live::{LIVE_EXPOSURE_LAG_S, PoseHistory};
use crate::lockstep::{Lockstep, LockstepStats, Wait};
use crate::mavcam::{CAMERA_COMPONENT, MavCamera};
use crate::realism::Realism;
use crate::render::{RenderParams, Renderer};
use crate::rtp::{RtpOutParams, RtpSender};
use crate::script::{Script, ScriptKind, ScriptParams};
use crate::vehicle::VehicleDisturbances;
use crate::video::{VideoFrame, serve_video, try_encode_jpeg};
use crate::world::{World, WorldKind};

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
    /// The realism configuration is unusable.
    #[error(transparent)]
    Realism(#[from] crate::realism::RealismError),
    /// The world could not be generated.
    #[error(transparent)]
    World(#[from] crate::world::WorldError),
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
    /// Realism (`ideal`: none). Set it with [`SimConfig::with_realism`],
    /// which also moves its vehicle and telemetry effects into
    /// `autopilot` and `radio`.
    pub realism: Realism,
    /// The world.
    pub world: WorldKind,
    /// The camera's H.264 stream over RTP/UDP ([`crate::rtp`]), beside the
    /// MJPEG server (None: off). With it on and no
    /// `autopilot.video_stream_uri` set, the camera announces it
    /// (`udp://HOST:PORT`) in VIDEO_STREAM_INFORMATION.
    pub rtp_out: Option<RtpOutParams>,
    /// A MAVLink camera component (100) beside the autopilot
    /// ([`crate::mavcam`]); off, the autopilot triggers the camera itself.
    pub mavlink_camera: bool,
    /// Lockstep with the consumer of the video ([`crate::lockstep`]): each
    /// frame is rendered at its step and the clock is held until the
    /// consumer is done with it (None: real time, frames skipped when
    /// rendering cannot keep up).
    pub lockstep: Option<Arc<Lockstep>>,
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
            realism: Realism::ideal(),
            world: WorldKind::Town,
            rtp_out: None,
            mavlink_camera: true,
            lockstep: None,
        }
    }
}

impl SimConfig {
    /// The flavour shortcut.
    pub fn with_flavour(mut self, flavour: Flavour) -> Self {
        self.autopilot.flavour = flavour;
        self
    }

    /// Applies `realism`: its vehicle effects (seeded from `self.seed`:
    /// set the seed first), its telemetry stream rates, and its radio
    /// (drop, latency and baud; a worse radio already configured stays).
    pub fn with_realism(mut self, realism: Realism) -> Self {
        self.autopilot.vehicle.disturbances =
            VehicleDisturbances::from_realism(&realism, self.seed ^ 0x5EA1_0000);
        if let Some(tel) = &realism.vehicle.telemetry {
            self.autopilot.stream_intervals = tel.stream_intervals.clone();
            for d in [&mut self.radio.up, &mut self.radio.down] {
                d.drop = d.drop.max(tel.drop);
                d.latency_s = d.latency_s.max(tel.latency_s);
                d.baud = Some(d.baud.map_or(tel.baud, |b| b.min(tel.baud)));
            }
        }
        self.realism = realism;
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
        if let Some(r) = &self.rtp_out
            && let Err((field, reason)) = r.check()
        {
            return bad("rtp_out", format!("{field} ({r:?})"), reason);
        }
        self.realism.validate()?;
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
    /// The H.264 RTP output's counters at the end (None: off).
    pub rtp: Option<crate::rtp::RtpStatsSnapshot>,
    /// Lockstep's counters at the end (None: real time).
    pub lockstep: Option<LockstepStats>,
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
    run_on(config, cancel, Sockets::default()).await
}

/// Sockets a caller bound before starting the simulator (as mini-redis's
/// `server::run` takes its listener): a test binds port 0, keeps the
/// socket, knows the port, and no other process can take it meanwhile.
#[derive(Debug, Default)]
pub struct Sockets {
    /// The video server's listener, used instead of binding
    /// `video_listen` (the server runs even if `video_listen` is None).
    pub video: Option<std::net::TcpListener>,
    /// The MAVLink endpoint's UDP socket: a `udpin:` endpoint listens on
    /// it, a `udpout:` one sends from it (its own address is not bound).
    pub mavlink: Option<std::net::UdpSocket>,
}

/// [`run`] on sockets the caller has already bound.
pub async fn run_on(
    config: SimConfig,
    cancel: CancellationToken,
    sockets: Sockets,
) -> Result<RunSummary, SimError> {
    run_bound(config, cancel, sockets, false).await
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
    run_bound(config, cancel, Sockets::default(), announce).await
}

async fn run_bound(
    mut config: SimConfig,
    cancel: CancellationToken,
    sockets: Sockets,
    announce: bool,
) -> Result<RunSummary, SimError> {
    config.validate()?;
    let (video_tx, video_rx) = watch::channel(None);
    let mut video_bound = None;
    let video_err = |addr: String| {
        move |source| SimError::Io {
            what: "binding the video server on",
            path: PathBuf::from(addr),
            source,
        }
    };
    let listener = match (sockets.video, config.video_listen) {
        (Some(l), _) => {
            let named = l
                .local_addr()
                .map_or_else(|_| "a given listener".into(), |a| a.to_string());
            l.set_nonblocking(true).map_err(video_err(named.clone()))?;
            Some(tokio::net::TcpListener::from_std(l).map_err(video_err(named))?)
        }
        (None, Some(addr)) => Some(
            tokio::net::TcpListener::bind(addr)
                .await
                .map_err(video_err(addr.to_string()))?,
        ),
        (None, None) => None,
    };
    if let Some(listener) = listener {
        video_bound = listener.local_addr().ok();
        // Without an RTP stream, the camera announces its MJPEG stream.
        if config.rtp_out.is_none()
            && config.autopilot.video_stream_uri.is_none()
            && let Some(a) = video_bound
        {
            config.autopilot.video_stream_uri = Some(format!("http://{a}/video.mjpg"));
        }
        let c = cancel.clone();
        tokio::spawn(async move {
            if let Err(e) = serve_video(listener, video_rx, c).await {
                tracing::error!("video server: {e}");
            }
        });
    } else {
        drop(video_rx);
    }
    run_inner(
        config,
        cancel,
        video_tx,
        sockets.mavlink,
        announce.then_some(video_bound),
    )
    .await
}

/// [`run`] without its video server: frames are published on `video_tx`
/// (rendered only while someone holds a receiver, or truth is written).
/// The shotpilot daemon uses this to run the world in-process.
pub async fn run_with(
    config: SimConfig,
    cancel: CancellationToken,
    video_tx: watch::Sender<Option<Arc<VideoFrame>>>,
) -> Result<RunSummary, SimError> {
    run_inner(config, cancel, video_tx, None, None).await
}

/// The simulation; `announce` (Some: the video server's bound address)
/// prints the bound addresses once the link is open.
async fn run_inner(
    config: SimConfig,
    cancel: CancellationToken,
    video_tx: watch::Sender<Option<Arc<VideoFrame>>>,
    mavlink_socket: Option<std::net::UdpSocket>,
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
    let realism = config.realism.clone();
    let world = if realism.lighting.sun.is_none() && config.world == WorldKind::Town {
        World::generate(config.seed)
    } else {
        World::generate_with(config.seed, &world_params_for(config.world, &realism))?
    };
    let world = Arc::new(world);
    let renderer = Arc::new(renderer_for(
        world.clone(),
        config.camera,
        config.render,
        &realism,
        config.seed,
    ));
    // The realistic camera (None: the plain renderer, as before realism;
    // a world that moves needs each frame's scene time).
    let imager = (!realism.camera_is_ideal() || !world.is_static()).then(|| {
        Arc::new(std::sync::Mutex::new(Imager::new(
            renderer.clone(),
            realism.camera.clone(),
            &realism.lighting,
        )))
    });
    let latency = realism
        .vehicle
        .video_latency
        .map(|l| LatencyProcess::new(l, config.seed));
    let mut history = PoseHistory::new();
    if !realism.is_ideal() {
        tracing::info!(
            "realism {}: effects {}",
            realism.name,
            realism.effects_on().join(", ")
        );
    }
    let mut link = spawn_link_on(
        LinkParams {
            endpoint: config.mavlink.clone(),
            radio: config.radio,
            system_id: config.autopilot.system_id,
            component_id: config.autopilot.component_id,
        },
        mavlink_socket,
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
    // The camera's H.264 stream, encoded on its own thread.
    let rtp = match config.rtp_out {
        Some(p) => Some(Arc::new(
            RtpSender::start(p, config.video_fps, config.seed).map_err(|e| SimError::Io {
                what: "starting the RTP output to",
                path: PathBuf::from(p.dest.to_string()),
                source: std::io::Error::other(e.to_string()),
            })?,
        )),
        None => None,
    };
    let mut ap_params = config.autopilot.clone();
    if ap_params.video_stream_uri.is_none() {
        ap_params.video_stream_uri = config.rtp_out.map(|r| r.uri());
    }
    // The first step runs at once, with the clock at `dt`.
    let unix_at_boot = unix_now() - 1.0 / config.step_hz;
    let mut ap = Autopilot::new(ap_params, unix_at_boot);
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
    let clock_start = tokio::time::Instant::now();
    // In lockstep a held clock does not catch up afterwards: the
    // simulation stays behind the wall clock by what it was held.
    let lockstep = config.lockstep.clone();
    ticker.set_missed_tick_behavior(if lockstep.is_some() {
        tokio::time::MissedTickBehavior::Delay
    } else {
        tokio::time::MissedTickBehavior::Burst
    });
    // Lockstep: frames rendered and waiting for their publication time
    // (capture time plus the video latency), in that order.
    let mut pending: std::collections::VecDeque<PendingFrame> = Default::default();
    let (cap_tx, mut cap_rx) = mpsc::channel::<(CaptureRequest, Option<String>)>(64);
    let (frame_done_tx, mut frame_done_rx) = mpsc::channel::<()>(16);
    let mut renders_in_flight = 0usize;
    // Frames may finish out of order when two render at once: only a newer
    // frame replaces the published one.
    let newest_published = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let mut next_frame_t = 0.0;
    let mut summary = RunSummary::default();
    let mut k: u64 = 0;
    let mut camera = config
        .mavlink_camera
        .then(|| MavCamera::new(config.autopilot.system_id, config.camera));
    let camera_on = camera.is_some();
    let send_as = |link: &crate::link::LinkHandle, component: Option<u8>, msgs: Vec<MavMessage>| {
        for msg in msgs {
            if link.to_link.try_send(Outgoing { component, msg }).is_err() {
                tracing::debug!("link outbox full: message dropped");
            }
        }
    };
    let send = |link: &crate::link::LinkHandle, msgs: Vec<MavMessage>| send_as(link, None, msgs);
    'run: loop {
        tokio::select! {
            _ = cancel.cancelled() => break,
            _ = ticker.tick() => {}
        }
        k += 1;
        let t = k as f64 * dt;
        while let Ok((h, m)) = link.from_link.try_recv() {
            match &mut camera {
                Some(c) if c.is_for_me(&m) => {
                    let replies = c.handle(&mut ap, &h, &m);
                    send_as(&link, Some(CAMERA_COMPONENT), replies);
                }
                _ => {
                    let replies = ap.handle(&h, &m);
                    send(&link, replies);
                }
            }
        }
        if let Some(hb) = camera.as_mut().and_then(|c| c.step(t)) {
            send_as(&link, Some(CAMERA_COMPONENT), vec![hb]);
        }
        if let Some(s) = &mut script {
            s.step(&mut ap, t);
        }
        let out = ap.step(t, dt);
        send(&link, out);
        if imager.is_some() {
            history.push(t, ap.vehicle().true_world_from_cam_stabilised());
        }
        for req in ap.take_capture_requests() {
            let renderer = renderer.clone();
            let dir = config.capture_dir.clone();
            let q = config.jpeg_quality;
            let tx = cap_tx.clone();
            let noise = config
                .sensor_noise
                .then_some(config.seed ^ 0xCA9 ^ req.index as u64);
            let written = tokio::task::spawn_blocking(move || {
                let url = match write_capture(&renderer, &req, &dir, q, noise) {
                    Ok(p) => Some(format!("file://{}", p.display())),
                    Err(e) => {
                        tracing::warn!("capture {}: {e}", req.index);
                        None
                    }
                };
                let _ = tx.blocking_send((req, url));
            });
            // In lockstep the picture is reported at the step it was taken.
            if lockstep.is_some() {
                let _ = written.await;
            }
        }
        while let Ok((req, url)) = cap_rx.try_recv() {
            if url.is_some() {
                summary.captures += 1;
            }
            let msg = ap.capture_done(&req, url.as_deref());
            // The camera reports its pictures; without one, the autopilot.
            send_as(&link, camera_on.then_some(CAMERA_COMPONENT), vec![msg]);
        }
        while frame_done_rx.try_recv().is_ok() {
            renders_in_flight = renders_in_flight.saturating_sub(1);
        }
        let want_frames =
            video_tx.receiver_count() > 0 || config.truth_dir.is_some() || rtp.is_some();
        if want_frames && t + 1e-9 >= next_frame_t {
            next_frame_t += frame_dt;
            if next_frame_t < t {
                next_frame_t = t + frame_dt;
            }
            // The true pose (GPS bias included): what the camera films and
            // what the truth files record. A realistic camera exposes the
            // frame a moment back, over the poses around it.
            let (t_frame, window) = match &imager {
                Some(_) => {
                    let tf = t - LIVE_EXPOSURE_LAG_S;
                    let g = ap.vehicle().gimbal_error().cloned();
                    (tf, Some(history.window(tf - 0.12, tf + 0.12, g)))
                }
                None => (t, None),
            };
            let wfc = match &window {
                Some(w) => w.world_from_cam(t_frame),
                None => ap.vehicle().true_world_from_cam(),
            };
            let capture_time = unix_at_boot + t_frame;
            if let Some(w) = &mut truth
                && let Err(e) = w.write_pose(capture_time, &wfc)
            {
                tracing::warn!("truth: {e}");
            }
            if lockstep.is_none() && renders_in_flight >= config.max_renders_in_flight.max(1) {
                summary.frames_skipped += 1;
            } else {
                summary.frames += 1;
                let seq = summary.frames - 1;
                if let Some(w) = &mut truth
                    && let Err(e) = w.write_frame(seq, capture_time, &wfc)
                {
                    tracing::warn!("truth: {e}");
                }
                let renderer = renderer.clone();
                let imager = imager.clone();
                let tx = video_tx.clone();
                let done = frame_done_tx.clone();
                let newest = newest_published.clone();
                let q = config.jpeg_quality;
                let noise = config
                    .sensor_noise
                    .then_some(config.seed ^ seq.wrapping_mul(0x9E37_79B9));
                // Published this long after the capture (None: at once).
                let latency_s = latency.as_ref().map(|l| l.at(t_frame));
                let publish_at = latency_s
                    .map(|l| clock_start + Duration::from_secs_f64((t_frame + l).max(0.0)));
                let rtp = rtp.clone();
                // The frame and the picture it shows (for the H.264 stream).
                let render = move || -> Option<(VideoFrame, GrayImage)> {
                    let result = match (&imager, &window) {
                        (Some(imager), Some(window)) => {
                            let mut imager = imager.lock().unwrap_or_else(|p| p.into_inner());
                            imager
                                .capture(t_frame, &|s| window.world_from_cam(s), noise)
                                .and_then(|shot| {
                                    let jpeg = shot.encoded.filter(|_| {
                                        shot.encoded_kind == Some(crate::imaging::EncodedKind::Jpeg)
                                    });
                                    let frame = match jpeg {
                                        // The stream's own bytes.
                                        Some(jpeg) => VideoFrame {
                                            jpeg,
                                            capture_time_unix_s: capture_time,
                                            seq,
                                        },
                                        None => {
                                            VideoFrame::encode(&shot.image, q, capture_time, seq)?
                                        }
                                    };
                                    Ok((frame, shot.image))
                                })
                        }
                        _ => {
                            let img = match noise {
                                Some(s) => renderer.render_noisy(&wfc, s),
                                None => renderer.render(&wfc),
                            };
                            VideoFrame::encode(&img, q, capture_time, seq).map(|f| (f, img))
                        }
                    };
                    result.map_err(|e| tracing::warn!("video frame: {e}")).ok()
                };
                // Whether the frame was published (not overtaken by a newer one).
                let publish = move |(frame, img): (VideoFrame, GrayImage)| -> bool {
                    tx.send_if_modified(|slot| {
                        use std::sync::atomic::Ordering;
                        if seq == 0 || newest.fetch_max(seq, Ordering::AcqRel) < seq {
                            if let Some(rtp) = &rtp {
                                rtp.offer(Arc::new(img), frame.capture_time_unix_s);
                            }
                            *slot = Some(Arc::new(frame));
                            true
                        } else {
                            false
                        }
                    })
                };
                if lockstep.is_some() {
                    // Rendered at its step; published when its latency has
                    // passed in simulated time (below).
                    if let Some(frame) = tokio::task::spawn_blocking(render).await.ok().flatten() {
                        let due = t_frame + latency_s.unwrap_or(0.0);
                        let at = pending.partition_point(|p| p.due <= due);
                        pending.insert(
                            at,
                            PendingFrame {
                                due,
                                capture_time,
                                publish: Box::new(move || publish(frame)),
                            },
                        );
                    }
                } else {
                    renders_in_flight += 1;
                    match publish_at {
                        None => {
                            tokio::task::spawn_blocking(move || {
                                if let Some(frame) = render() {
                                    publish(frame);
                                }
                                let _ = done.blocking_send(());
                            });
                        }
                        Some(at) => {
                            tokio::spawn(async move {
                                let frame =
                                    tokio::task::spawn_blocking(render).await.ok().flatten();
                                let _ = done.send(()).await;
                                if let Some(frame) = frame {
                                    tokio::time::sleep_until(at).await;
                                    publish(frame);
                                }
                            });
                        }
                    }
                }
            }
        }
        // Lockstep: the frames due are published, each held until the
        // consumer is done with it.
        if let Some(ls) = &lockstep {
            while pending.front().is_some_and(|p| p.due <= t + 1e-9) {
                let Some(p) = pending.pop_front() else { break };
                if !(p.publish)() {
                    continue;
                }
                let (l, ct) = (ls.clone(), p.capture_time);
                let waited = tokio::select! {
                    _ = cancel.cancelled() => {
                        ls.close();
                        break 'run;
                    }
                    w = tokio::task::spawn_blocking(move || l.wait_for(ct)) => w,
                };
                if waited.is_ok_and(|w| w == Wait::TimedOut) {
                    tracing::warn!(
                        capture_time = ct,
                        "lockstep: the consumer did not take the frame in {:?}; going on",
                        ls.limit()
                    );
                }
            }
        }
        summary.sim_seconds = t;
    }
    summary.link = *link.stats.borrow();
    summary.rtp = rtp.map(|r| r.stats());
    summary.lockstep = lockstep.map(|l| l.stats());
    Ok(summary)
}

/// A lockstep frame rendered and waiting for its publication.
struct PendingFrame {
    /// Simulated time it is published at (capture time plus latency).
    due: f64,
    /// Its capture time (unix seconds): what the consumer acknowledges.
    capture_time: f64,
    /// Publishes it; false when a newer frame was published first.
    publish: Box<dyn FnOnce() -> bool + Send>,
}
