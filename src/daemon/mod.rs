//! The daemon: wires the video source, the SLAM (tracking, local mapping
//! and loop closing on three threads), the MAVLink link actor, the
//! georeference worker, the shot service, the refinement task and the HTTP
//! API with its event stream under one shutdown token, and (by default)
//! runs the bundled simulator in-process. A build without the `sim`
//! feature has no simulator and refuses `[sim] enabled = true`
//! ([`DaemonError::NoSimulator`]).
//!
//! ```text
//!  [video] url (video::source), one reader task:
//!   http://  MJPEG or snapshots -> raw slot -> JPEG decode thread ---------+
//!   rtsp://  H.264 (RTSP) ----------+                                       |
//!   udp://   RTP H.264, or an .sdp -+-> access-unit queue                   |
//!            (NACK/PLI feedback)         -> H.264 decode thread ------------+-> frame slot
//!   auto     the URL the vehicle's camera announces over MAVLink, then one of the above
//!   bundled simulator (in-process): MJPEG over HTTP; H.264 over RTP/UDP with [sim] rtp_out
//!
//!  frame slot --newest frame--> "slam" thread: tracking (FrameProcessor)
//!     --keyframes--> local mapping thread --mapped keyframes--> loop closing thread
//!     (inline after tracking in lockstep with the simulator)
//!     -> SlamShared (status, map, keyframes) -> map file (checkpoints, shutdown)
//!  autopilot (Pixhawk, SITL, simulator) <--MAVLink--> link actor (LinkHandle)
//!  link telemetry + SLAM keyframes and frames --> geo worker
//!     (GeoService: live georeference map -> NED -> WGS84, saved beside the map)
//!  geo worker --GNSS, attitude (TelemetryFeed, [slam] priors / aid)--> SLAM
//!  shot's mission started --> refinement task: arrival, re-targeting on the
//!     approach, rounds (each corrected target uploaded as a mission) and,
//!     with [refine] servo, servoing (guided setpoints); ShotEvents, rounds
//!     recorded on the shot
//!  link --> reconciler (each shot's mission state from the vehicle's), photo recorder
//!  HTTP API (/api/v1) reads Ingest, SlamShared, the vehicle view, GeoService;
//!     shots through the shot service into the store (data_dir);
//!     /events streams the status and the ShotEvents
//! ```
//!
//! Shutdown: the token is cancelled (Ctrl-C / SIGTERM in `main`); the
//! server stops, then the refinement task, the checkpoints and the memory
//! trimmer; the video reader stops, the ingest slots are closed, the decode
//! thread is joined and the SLAM thread takes no further frame, finishes
//! (mapping, map file) and is joined; the georeference is saved beside the
//! map, the link's tasks and the link actor stop; the simulator stops last.

pub mod geo_service;
pub mod memory;
pub mod persist;

mod refinement_arrival;
mod refinement_deps;
mod refinement_servo;
pub mod refinement_task;
pub mod shot_service;
pub mod slam_shared;
pub mod slam_view;
pub mod vehicle_view;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;
use tokio::sync::oneshot;
use tokio_util::sync::CancellationToken;

use crate::api::{self, ApiParams, AppState, SlamView, VehicleView};
use crate::config::Config;
use crate::shot::request::WarpOnly;
use crate::shot::store::ShotStore;
use crate::video::live::{Closed, Frame, Ingest, unix_now};
use crate::video::mjpeg;
pub use slam_shared::{ProcessOutcome, SlamShared};
pub use slam_view::FrameProcessor;

/// Errors that stop the daemon.
#[derive(Debug, thiserror::Error)]
pub enum DaemonError {
    /// A listen address could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: String,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The data directory could not be used.
    #[error("data directory: {0}")]
    Store(#[from] crate::shot::store::StoreError),
    /// The camera configuration is unusable.
    #[error("camera: {0}")]
    Camera(#[from] crate::camera::CameraError),
    /// The simulator could not start.
    #[cfg(feature = "sim")]
    #[error("simulator: {0}")]
    Sim(#[from] crate::simulator::SimKeyError),
    /// `[sim] enabled = true` in a build without the simulator (the `sim`
    /// feature off: a field build).
    #[error(
        "this build has no simulator: rebuild with the default features, or set [sim] enabled = false (`shotpilot run --no-sim`)"
    )]
    NoSimulator,
    /// The MAVLink link could not start.
    #[error("link: {0}")]
    Link(String),
    /// A thread could not be started.
    #[error("cannot start the {what} thread: {source}")]
    Thread {
        /// Which thread.
        what: &'static str,
        /// The OS error.
        #[source]
        source: std::io::Error,
    },
    /// The HTTP server failed.
    #[error("HTTP server: {0}")]
    Serve(std::io::Error),
    /// The video URL is unusable.
    #[error(transparent)]
    Video(#[from] mjpeg::MjpegError),
    /// The video source is unusable.
    #[error(transparent)]
    VideoSource(#[from] crate::video::source::SourceError),
}

/// The simulator's lockstep handshake: the SLAM thread acknowledges each
/// frame on it.
#[cfg(feature = "sim")]
type Lockstep = crate::simulator::Lockstep;

/// Without the simulator there is no lockstep: a type with no value, so
/// the SLAM loop's `Option<&Lockstep>` is always None.
#[cfg(not(feature = "sim"))]
#[derive(Debug)]
enum Lockstep {}

#[cfg(not(feature = "sim"))]
impl Lockstep {
    fn frame_done(&self, _capture_time_unix_s: f64) {
        match *self {}
    }

    fn close(&self) {
        match *self {}
    }
}

/// What the daemon reports when it stops.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// Seconds it ran.
    pub run_s: f64,
    /// Video counters at the end.
    pub video: crate::video::live::CountersSnapshot,
    /// SLAM status at the end.
    pub slam: api::SlamStatus,
    /// The map file written, if any.
    pub map_file: Option<PathBuf>,
    /// Shots in the store.
    pub shots: usize,
}

/// Handles a running daemon gives its starter.
#[derive(Debug, Clone)]
pub struct Started {
    /// The HTTP API's address.
    pub api_addr: SocketAddr,
}

/// Sockets the starter bound before the daemon starts, used instead of
/// binding the configured addresses (as mini-redis's `server::run` takes
/// its listener): a test binds port 0, keeps the socket, writes its
/// address into the configuration, and no other process can take the port
/// in between.
#[derive(Debug, Default)]
pub struct Sockets {
    /// The API's listener (else `[server] bind`).
    pub api: Option<std::net::TcpListener>,
    /// The link's UDP socket: the link listens on it as on a `udpin:` URL
    /// (else `[link] url` is opened).
    pub link: Option<std::net::UdpSocket>,
    /// The in-process simulator's video listener (else `[sim] video_listen`).
    pub sim_video: Option<std::net::TcpListener>,
    /// The in-process simulator's MAVLink UDP socket (else its `[sim]
    /// mavlink` endpoint binds its own).
    pub sim_mavlink: Option<std::net::UdpSocket>,
    /// The RTP/RTCP sockets of a `udp://` video source (else `[video]
    /// url`'s port is bound).
    pub video_rtp: Option<crate::video::udp::RtpSockets>,
}

/// Run the daemon until `cancel` fires. `base_dir` resolves relative
/// paths of the configuration; `started` receives the API address once
/// it listens.
pub async fn run(
    cfg: Config,
    base_dir: &Path,
    cancel: CancellationToken,
    started: Option<oneshot::Sender<Started>>,
) -> Result<Summary, DaemonError> {
    run_on(cfg, base_dir, cancel, started, Sockets::default()).await
}

/// [`run`] on sockets the starter has already bound.
pub async fn run_on(
    cfg: Config,
    base_dir: &Path,
    cancel: CancellationToken,
    started: Option<oneshot::Sender<Started>>,
    sockets: Sockets,
) -> Result<Summary, DaemonError> {
    // Before anything is opened or bound: without the simulator, a
    // configuration that asks for it is refused.
    #[cfg(not(feature = "sim"))]
    if cfg.sim.enabled {
        return Err(DaemonError::NoSimulator);
    }
    let t0 = Instant::now();
    let data_dir = base_dir.join(&cfg.server.data_dir);
    let store = Arc::new(ShotStore::open(&data_dir.join("shots"))?);
    // A refinement loop still running in the record: the last session
    // ended without stopping it (killed or crashed).
    for shot in store.list() {
        if let Some(s) = crate::shot::reconcile::interrupt_refinement(
            &shot,
            "the daemon ended while the loop ran (killed or crashed); start the shot's mission to refine again",
        ) {
            tracing::warn!(shot = %s.id, "refinement loop interrupted by the last session's end");
            if let Err(e) = store.put(s, None) {
                tracing::warn!("marking an interrupted refinement: {e}");
            }
        }
    }
    #[cfg_attr(not(feature = "sim"), allow(unused_mut))]
    let mut camera = cfg.camera.camera(base_dir)?;

    // The simulator, first, so the video and the link find it.
    #[cfg(feature = "sim")]
    let sim_cancel = CancellationToken::new();
    // Lockstep: the simulator holds its clock until the SLAM thread is done
    // with each frame.
    #[cfg(feature = "sim")]
    let lockstep = cfg.sim.lockstep_on().then(|| Arc::new(Lockstep::default()));
    // Without the simulator there is no lockstep (refused above).
    #[cfg(not(feature = "sim"))]
    let lockstep: Option<Arc<Lockstep>> = None;
    #[cfg(feature = "sim")]
    let sim_task = if cfg.sim.enabled {
        let mut sc = crate::simulator::sim_config(&cfg, &data_dir)?;
        sc.lockstep = lockstep.clone();
        if cfg.camera.readout_ms.is_none() {
            // The simulator's camera is the one the SLAM sees.
            camera.readout_s = sc
                .realism
                .camera
                .rolling_shutter
                .map_or(0.0, |r| r.readout_s);
        }
        let c = sim_cancel.clone();
        tracing::info!(video = %cfg.sim.video_listen, mavlink = %cfg.sim.mavlink, "starting the simulator in-process");
        let (video, mavlink) = (sockets.sim_video, sockets.sim_mavlink);
        Some(tokio::spawn(async move {
            crate::simulator::run_on(sc, c, video, mavlink).await
        }))
    } else {
        None
    };

    // Video ingest: reader task -> decode thread -> frame slot.
    let ingest = Arc::new(Ingest::new());
    let decoder = ingest
        .spawn_decoder()
        .map_err(|source| DaemonError::Thread {
            what: "decode",
            source,
        })?;
    let video_cancel = cancel.child_token();
    // The source by `[video] url` (`auto` waits for the link below).
    if let crate::video::source::VideoUrl::Http(u) =
        crate::video::source::VideoUrl::parse(&cfg.video.url)?
    {
        mjpeg::HttpUrl::parse(&u)?;
    }
    let (link_for_video, link_rx) = oneshot::channel();
    let reader = {
        let (vcfg, ing, c) = (cfg.video.clone(), ingest.clone(), video_cancel.clone());
        let rtp = sockets.video_rtp;
        tokio::spawn(async move {
            if let Err(e) =
                crate::video::source::run_configured_on(vcfg, ing, c, Some(link_rx), rtp).await
            {
                tracing::error!("video: {e}");
            }
        })
    };
    // Pictures decimated for SLAM (any source): the intrinsics follow.
    ingest
        .jpeg_downscale
        .store(cfg.video.downscale, std::sync::atomic::Ordering::Relaxed);
    let camera = crate::video::source::decimated_camera(&camera, cfg.video.downscale);
    tracing::info!(
        readout_ms = camera.readout_s * 1000.0,
        "camera {}x{}, {}",
        camera.width,
        camera.height,
        if camera.readout_s > 0.0 {
            "rolling shutter modelled"
        } else {
            "global shutter"
        }
    );

    // SLAM thread.
    // Telemetry priors and the telemetry aid of tracking: the georeference
    // worker pushes the link's GNSS and attitude samples into this feed,
    // the SLAM's mapping and tracking read them.
    let prior_feed = (cfg.slam.enabled && (cfg.slam.priors || cfg.slam.aid))
        .then(|| crate::slam::priors::TelemetryFeed::live(cfg.geo.history.max_age_s));
    let geo =
        Arc::new(geo_service::GeoService::new(cfg.geo.clone()).with_prior_feed(prior_feed.clone()));
    let shared = Arc::new(SlamShared::new(cfg.slam.enabled));
    let map_file = data_dir.join(&cfg.slam.map_file);
    persist::remove_leftovers(&data_dir, &map_file);
    // The stored shots' keyframes stay in the continued map (culling would
    // take a keyframe the operator drew a shot on and may ask again on).
    if cfg.slam.enabled && cfg.slam.continue_map && map_file.exists() {
        for shot in store.list() {
            if let crate::shot::record::ShotSource::Anchors { keyframe_id, .. } = shot.source {
                shared.pin_keyframe(keyframe_id);
            }
        }
    }
    // The georeference saved with the map: restored onto it once the SLAM
    // has loaded it (dropped if the map is not continued).
    if cfg.slam.enabled
        && cfg.slam.continue_map
        && map_file.exists()
        && let Some(saved) = persist::load_geo(&map_file)
    {
        geo.restore(saved);
    }
    let persist = Arc::new(persist::MapPersist::new(map_file, shared.clone()));
    let slam_thread = {
        let (ing, sh, g) = (ingest.clone(), shared.clone(), geo.clone());
        let delay = Duration::from_millis(cfg.slam.artificial_delay_ms);
        let cfg = cfg.clone();
        let p = persist.clone();
        let lockstep = lockstep.clone();
        let rt = tokio::runtime::Handle::current();
        std::thread::Builder::new()
            .name("slam".into())
            .spawn(move || {
                // The runtime's clock (simulated on a paused runtime).
                let _rt = rt.enter();
                // Built here: loading and indexing a saved map takes a while.
                let processor = slam_view::make_processor(&cfg, camera, sh.clone(), p, prior_feed);
                slam_loop(processor, &ing, &sh, &g, delay, lockstep.as_deref())
            })
            .map_err(|source| DaemonError::Thread {
                what: "slam",
                source,
            })?
    };

    // The MAVLink link actor.
    let link_cancel = cancel.child_token();
    let (link, link_task) = match sockets.link {
        Some(socket) => crate::vehicle::spawn_with_socket(
            cfg.link.clone(),
            cfg.mission.transfer,
            link_cancel.clone(),
            socket,
        ),
        None => crate::vehicle::spawn(cfg.link.clone(), cfg.mission.transfer, link_cancel.clone()),
    }
    .map_err(|e| DaemonError::Link(e.to_string()))?;
    let _ = link_for_video.send(link.clone());
    // The georeference worker: telemetry and keyframes in.
    let geo_task = tokio::spawn(geo.clone().run(
        link.telemetry.clone(),
        shared.clone(),
        link_cancel.clone(),
    ));
    // Checkpoints of the map and its georeference.
    let checkpoint_cancel = cancel.child_token();
    let checkpoint_task = (cfg.slam.enabled && cfg.slam.checkpoint_s > 0.0).then(|| {
        let (p, g, c) = (persist.clone(), geo.clone(), checkpoint_cancel.clone());
        let period = Duration::from_secs_f64(cfg.slam.checkpoint_s);
        tokio::spawn(async move {
            let mut tick = tokio::time::interval_at(tokio::time::Instant::now() + period, period);
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    _ = c.cancelled() => break,
                    _ = tick.tick() => {}
                }
                let (p, g) = (p.clone(), g.clone());
                let _ = tokio::task::spawn_blocking(move || p.checkpoint(&g)).await;
            }
        })
    });
    // Freed memory given back to the system over a long flight.
    let trim_cancel = cancel.child_token();
    let trim_task = tokio::spawn(memory::run_trimmer(
        memory::TRIM_PERIOD,
        trim_cancel.clone(),
    ));
    // The refinement loop: started with a shot's mission, stopped by the
    // next upload or the shutdown.
    let actions: Arc<tokio::sync::Mutex<()>> = Default::default();
    let events: Arc<api::ShotEvents> = Default::default();
    let (refine, refine_task) = refinement_task::spawn(
        refinement_task::Deps {
            store: store.clone(),
            geo: geo.clone(),
            slam: shared.clone(),
            ingest: ingest.clone(),
            link: link.clone(),
            plan: cfg.mission.plan,
            actions: actions.clone(),
            params: cfg.refine.params(),
            pictures: Default::default(),
            epoch: crate::clock::now(),
            events: events.clone(),
        },
        cancel.child_token(),
    );
    let link_vehicle = Arc::new(
        vehicle_view::LinkVehicle::new(link, cfg.mission.plan, geo.clone()).with_refine(refine),
    );
    // The vehicle's truth: each shot's mission state from the mission the
    // vehicle holds, at the first heartbeat and after every link loss.
    let reconcile_task = tokio::spawn(vehicle_view::run_reconciler(
        link_vehicle.clone(),
        store.clone(),
        actions.clone(),
        link_cancel.clone(),
    ));
    // Every picture the camera reports, stored with the shot it flies.
    let photo_task = tokio::spawn(vehicle_view::run_photo_recorder(
        link_vehicle.clone(),
        store.clone(),
        link_cancel.clone(),
    ));
    let vehicle: Arc<dyn VehicleView> = link_vehicle;

    // The API.
    let slam_view: Arc<dyn SlamView> = shared.clone();
    let state = AppState {
        ingest: ingest.clone(),
        slam: slam_view.clone(),
        vehicle: Some(vehicle),
        shots: Arc::new(shot_service::LocalizingShots {
            warp: WarpOnly {
                keyframes: slam_view,
                params: Default::default(),
            },
            slam: shared.clone(),
            params: cfg.shot.localize_params(),
            geo: Some(geo.clone()),
        }),
        store: store.clone(),
        params: Arc::new(ApiParams {
            token: cfg.server.token.clone(),
            body_limit: cfg.server.body_limit_bytes,
            map_max_points: cfg.server.map_max_points,
            features_max: cfg.server.features_max,
            events_hz: cfg.server.events_hz,
            ..Default::default()
        }),
        actions,
        started_unix: unix_now(),
        shutdown: cancel.clone(),
        events,
    };
    let bind_err = |source| DaemonError::Bind {
        addr: cfg.server.bind.clone(),
        source,
    };
    let listener = match sockets.api {
        Some(l) => {
            l.set_nonblocking(true).map_err(bind_err)?;
            tokio::net::TcpListener::from_std(l).map_err(bind_err)?
        }
        None => tokio::net::TcpListener::bind(&cfg.server.bind)
            .await
            .map_err(bind_err)?,
    };
    let api_addr = listener.local_addr().map_err(DaemonError::Serve)?;
    tracing::info!("operator page: http://{api_addr}/");
    if let Some(tx) = started {
        let _ = tx.send(Started { api_addr });
    }
    let server_cancel = cancel.clone();
    let served = axum::serve(listener, api::router(state))
        .with_graceful_shutdown(async move { server_cancel.cancelled().await })
        .await;

    // Shutdown, in order.
    tracing::info!("shutting down");
    let _ = refine_task.await;
    checkpoint_cancel.cancel();
    if let Some(t) = checkpoint_task {
        let _ = t.await;
    }
    trim_cancel.cancel();
    let _ = trim_task.await;
    video_cancel.cancel();
    let _ = reader.await;
    ingest.close();
    let summary_slam = tokio::task::spawn_blocking(move || {
        let _ = decoder.join();
        slam_thread.join().ok()
    })
    .await
    .ok()
    .flatten();
    // The georeference beside the map just written.
    if summary_slam.as_ref().is_some_and(Option::is_some) {
        let (p, g) = (persist.clone(), geo.clone());
        let _ = tokio::task::spawn_blocking(move || p.save_geo(&g)).await;
    }
    link_cancel.cancel();
    let _ = reconcile_task.await;
    let _ = photo_task.await;
    let _ = geo_task.await;
    let _ = link_task.await;
    #[cfg(feature = "sim")]
    sim_cancel.cancel();
    #[cfg(feature = "sim")]
    if let Some(t) = sim_task {
        match t.await {
            Ok(Ok(s)) => tracing::info!(
                frames = s.frames,
                skipped = s.frames_skipped,
                lockstep = ?s.lockstep,
                "simulator stopped"
            ),
            Ok(Err(e)) => tracing::warn!("simulator: {e}"),
            Err(e) => tracing::warn!("simulator task: {e}"),
        }
    }
    served.map_err(DaemonError::Serve)?;
    let wrote_map = summary_slam.flatten();
    Ok(Summary {
        run_s: t0.elapsed().as_secs_f64(),
        video: ingest.counters.snapshot(),
        slam: shared.status(),
        map_file: wrote_map,
        shots: store.list().len(),
    })
}

/// The SLAM thread: take the newest frame, process it, publish the status
/// (and, in lockstep, let the simulator go on); at the end let the
/// processor finish (mapping, map file).
fn slam_loop(
    mut processor: Box<dyn FrameProcessor>,
    ingest: &Ingest,
    shared: &SlamShared,
    geo: &geo_service::GeoService,
    delay: Duration,
    lockstep: Option<&Lockstep>,
) -> Option<PathBuf> {
    loop {
        let frame: Arc<Frame> = match ingest.take_frame(Duration::from_millis(200)) {
            Ok(Some(f)) => f,
            Ok(None) => continue,
            Err(Closed) => break,
        };
        geo.note_frame(&frame);
        let t = Instant::now();
        let outcome = processor.process(&frame);
        if !delay.is_zero() {
            std::thread::sleep(delay);
        }
        shared.record(&frame, outcome, t.elapsed().as_secs_f64() * 1e3);
        if let (Some(l), Some(at)) = (lockstep, frame.capture_time) {
            l.frame_done(at);
        }
    }
    if let Some(l) = lockstep {
        l.close();
    }
    processor.finish()
}
