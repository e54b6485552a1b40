//! Shared by the tests that start the daemon with the in-process simulator
//! (`daemon_e2e`, `daemon_refine`, `geo_daemon`, `browser`): sockets bound
//! on port 0 for the daemon, and requests through the tests' one HTTP
//! client (`tests/suite/http_support`).
#![allow(dead_code)] // each test binary uses its own subset

use std::net::SocketAddr;
use std::path::Path;
use std::time::Duration;

pub(crate) use crate::http_support;

use serde_json::Value;
use tokio_util::sync::CancellationToken;

/// The bearer token the daemon tests configure and send.
pub const TOKEN: &str = "e2e";

/// The daemon's configuration for a test, and the sockets it runs on: the
/// in-process simulator's video listener and the link's UDP socket are
/// bound here on port 0 and handed to the daemon (`daemon::run_on`), so
/// their ports are known before it starts and no other test can take them;
/// the API binds its own port 0 and reports it (`Started`). [`TOKEN`] is
/// the bearer token. Validated by the caller after its own changes.
pub fn sim_config() -> (shotpilot::config::Config, shotpilot::daemon::Sockets) {
    let video = std::net::TcpListener::bind("127.0.0.1:0").expect("bind the video listener");
    let link = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind the link socket");
    let video_addr = video.local_addr().expect("video listener address");
    let link_addr = link.local_addr().expect("link socket address");
    let mut cfg = shotpilot::config::Config::default();
    cfg.sim.video_listen = video_addr.to_string();
    cfg.video.url = format!("http://{video_addr}/video.mjpg");
    cfg.sim.mavlink = format!("udpout:{link_addr}");
    cfg.link.url = format!("udpin:{link_addr}");
    cfg.server.bind = "127.0.0.1:0".into();
    cfg.server.token = Some(TOKEN.into());
    let sockets = shotpilot::daemon::Sockets {
        link: Some(link),
        sim_video: Some(video),
        ..Default::default()
    };
    (cfg, sockets)
}

/// The daemon's task: its summary, or why it failed.
pub type DaemonTask =
    tokio::task::JoinHandle<Result<shotpilot::daemon::Summary, shotpilot::daemon::DaemonError>>;

/// A daemon running on its own two-worker runtime, its API at `addr`.
pub struct Running {
    /// The runtime the daemon runs on (tests may spawn on it too).
    pub rt: tokio::runtime::Runtime,
    /// Cancels the daemon (a clean stop).
    pub cancel: CancellationToken,
    /// The daemon's task.
    pub task: DaemonTask,
    /// Where its API listens.
    pub addr: SocketAddr,
}

/// Starts the daemon with `cfg` (validated by the caller) on `sockets`,
/// its data under `base`; returns once the API listens.
pub fn start(
    cfg: shotpilot::config::Config,
    sockets: shotpilot::daemon::Sockets,
    base: &Path,
) -> Running {
    start_on(cfg, sockets, base, None)
}

/// [`start`], with the daemon's log (`info`, the georeference's `debug`;
/// the threads of its runtime)
/// written to `log`: what a failed end-to-end run looks back on.
pub fn start_logged(
    cfg: shotpilot::config::Config,
    sockets: shotpilot::daemon::Sockets,
    base: &Path,
    log: &Path,
) -> Running {
    start_on(cfg, sockets, base, Some(log_to(log)))
}

/// The daemon's log (`info`, the georeference's `debug`) written to `log`.
fn log_to(log: &Path) -> tracing::Dispatch {
    let file = std::fs::File::create(log).unwrap_or_else(|e| panic!("{}: {e}", log.display()));
    tracing::Dispatch::new(
        tracing_subscriber::fmt()
            .with_ansi(false)
            .with_writer(std::sync::Mutex::new(file))
            .with_env_filter(tracing_subscriber::EnvFilter::new(
                "info,shotpilot::geo=debug",
            ))
            .finish(),
    )
}

fn start_on(
    cfg: shotpilot::config::Config,
    sockets: shotpilot::daemon::Sockets,
    base: &Path,
    log: Option<tracing::Dispatch>,
) -> Running {
    let mut builder = tokio::runtime::Builder::new_multi_thread();
    if let Some(d) = log {
        // Each of the runtime's threads (workers and blocking) logs to it
        // for its whole life.
        builder.on_thread_start(move || std::mem::forget(tracing::dispatcher::set_default(&d)));
    }
    let rt = builder
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("a runtime");
    let cancel = CancellationToken::new();
    let (tx, rx) = tokio::sync::oneshot::channel();
    let (c, b) = (cancel.clone(), base.to_owned());
    let task =
        rt.spawn(async move { shotpilot::daemon::run_on(cfg, &b, c, Some(tx), sockets).await });
    let addr = rt.block_on(rx).expect("the daemon starts").api_addr;
    Running {
        rt,
        cancel,
        task,
        addr,
    }
}

impl Running {
    /// Cancels the daemon and waits up to `limit` for it to stop: the
    /// task's outcome, or `None` when it did not stop in time.
    pub fn stop_within(
        self,
        limit: Duration,
    ) -> Option<Result<shotpilot::daemon::Summary, shotpilot::daemon::DaemonError>> {
        self.cancel.cancel();
        let task = self.task;
        self.rt
            .block_on(async { tokio::time::timeout(limit, task).await })
            .ok()
            .map(|joined| joined.expect("the daemon task does not panic"))
    }

    /// Cancels the daemon, which must stop cleanly within `limit`; its
    /// summary.
    pub fn stop(self, limit: Duration) -> shotpilot::daemon::Summary {
        self.stop_within(limit)
            .expect("the daemon stops")
            .expect("the daemon stops cleanly")
    }
}

/// A daemon on simulated time: a current-thread tokio runtime with paused
/// time, driven by its own thread, and the in-process simulator in
/// lockstep with the SLAM (`[sim] lockstep`). The simulator's steps, the
/// daemon's timers and the test's waits ([`OnSimTime::sleep`]) are all on
/// the runtime's clock, which moves only when nothing is working: no
/// frame is skipped and no timer fires early because the machine is busy,
/// and the run goes as fast as its work allows.
pub struct OnSimTime {
    /// The runtime's handle (to block on, or spawn on).
    pub handle: tokio::runtime::Handle,
    /// Cancels the daemon (a clean stop).
    pub cancel: CancellationToken,
    /// The daemon's task.
    task: DaemonTask,
    /// Ends the driver thread once the daemon stopped.
    done: CancellationToken,
    /// The thread driving the runtime.
    driver: std::thread::JoinHandle<()>,
    /// Where its API listens.
    pub addr: SocketAddr,
}

/// Starts the daemon with `cfg` (validated by the caller; lockstep is
/// switched on here) on `sockets`, its data under `base`, on simulated
/// time; returns once the API listens.
pub fn start_on_sim_time(
    cfg: shotpilot::config::Config,
    sockets: shotpilot::daemon::Sockets,
    base: &Path,
) -> OnSimTime {
    sim_time_on(cfg, sockets, base, None)
}

/// [`start_on_sim_time`], with the daemon's log written to `log` (as
/// [`start_logged`]).
pub fn start_on_sim_time_logged(
    cfg: shotpilot::config::Config,
    sockets: shotpilot::daemon::Sockets,
    base: &Path,
    log: &Path,
) -> OnSimTime {
    sim_time_on(cfg, sockets, base, Some(log_to(log)))
}

fn sim_time_on(
    mut cfg: shotpilot::config::Config,
    sockets: shotpilot::daemon::Sockets,
    base: &Path,
    log: Option<tracing::Dispatch>,
) -> OnSimTime {
    cfg.sim.lockstep = true;
    let cancel = CancellationToken::new();
    let done = CancellationToken::new();
    let (handed, handle_rx) = std::sync::mpsc::channel();
    let (c, d, b) = (cancel.clone(), done.clone(), base.to_owned());
    let driver = std::thread::Builder::new()
        .name("sim-time".into())
        .spawn(move || {
            let mut builder = tokio::runtime::Builder::new_current_thread();
            // The driver thread and the runtime's blocking threads log to
            // it for their whole lives.
            let _logging = log.map(|d| {
                let guard = tracing::dispatcher::set_default(&d);
                builder.on_thread_start(move || {
                    std::mem::forget(tracing::dispatcher::set_default(&d))
                });
                guard
            });
            let rt = builder
                .enable_all()
                .start_paused(true)
                .build()
                .expect("a paused runtime");
            let (tx, rx) = tokio::sync::oneshot::channel();
            let task =
                rt.spawn(
                    async move { shotpilot::daemon::run_on(cfg, &b, c, Some(tx), sockets).await },
                );
            handed
                .send((rt.handle().clone(), task, rx))
                .expect("the test waits for the runtime");
            rt.block_on(d.cancelled());
        })
        .expect("the driver thread");
    let (handle, task, started) = handle_rx.recv().expect("the runtime starts");
    let addr = handle
        .block_on(started)
        .expect("the daemon starts")
        .api_addr;
    OnSimTime {
        handle,
        cancel,
        task,
        done,
        driver,
        addr,
    }
}

impl OnSimTime {
    /// Waits `d` of simulated time (the daemon and the simulator run).
    pub fn sleep(&self, d: Duration) {
        self.handle
            .block_on(async move { tokio::time::sleep(d).await });
    }

    /// The simulated clock.
    pub fn now(&self) -> tokio::time::Instant {
        self.handle.block_on(async { tokio::time::Instant::now() })
    }

    /// Polls `check` every `period` of simulated time until it gives a
    /// value or `limit` of simulated time passed (then `None`). The loop
    /// is one task on the runtime and each check runs with the clock held,
    /// so the checks fall on the same simulated instants in every run (t0,
    /// t0 + period, ...) whatever the machine's speed.
    pub fn poll<T: Send + 'static>(
        &self,
        limit: Duration,
        period: Duration,
        check: impl Fn() -> Option<T> + Send + Sync + 'static,
    ) -> Option<T> {
        let check = std::sync::Arc::new(check);
        let task = self.handle.spawn(async move {
            let t0 = tokio::time::Instant::now();
            loop {
                let c = check.clone();
                let found = tokio::task::spawn_blocking(move || c())
                    .await
                    .expect("the check does not panic");
                if found.is_some() {
                    return found;
                }
                if t0.elapsed() >= limit {
                    return None;
                }
                tokio::time::sleep(period).await;
            }
        });
        self.handle
            .block_on(task)
            .expect("the polling task does not panic")
    }

    /// Runs `f` with the simulated clock held (a blocking task keeps a
    /// paused runtime from advancing): for reads that must see one instant.
    /// `f` must not wait for anything that needs time to pass.
    pub fn held<T: Send + 'static>(&self, f: impl FnOnce() -> T + Send + 'static) -> T {
        self.handle
            .block_on(async move { tokio::task::spawn_blocking(f).await })
            .expect("the held closure does not panic")
    }

    /// Cancels the daemon, which must stop cleanly within `limit` of
    /// simulated time; its summary.
    pub fn stop(self, limit: Duration) -> shotpilot::daemon::Summary {
        self.cancel.cancel();
        let task = self.task;
        let out = self
            .handle
            .block_on(async { tokio::time::timeout(limit, task).await });
        self.done.cancel();
        self.driver.join().expect("the driver thread ends");
        out.expect("the daemon stops")
            .expect("the daemon task does not panic")
            .expect("the daemon stops cleanly")
    }
}

/// One request with [`TOKEN`] as bearer token (a daemon without a token
/// ignores it); returns the status and the body.
pub fn request(
    addr: SocketAddr,
    method: &str,
    path: &str,
    content_type: &str,
    body: &[u8],
) -> (u16, Vec<u8>) {
    let auth = format!("Bearer {TOKEN}");
    let r = http_support::send(
        addr,
        method,
        path,
        &[("authorization", &auth), ("content-type", content_type)],
        body,
        Duration::from_secs(60),
    );
    (r.status, r.body)
}

/// A request with an optional JSON body.
pub fn http(addr: SocketAddr, method: &str, path: &str, body: Option<&Value>) -> (u16, Vec<u8>) {
    let body = body.map(|b| b.to_string()).unwrap_or_default();
    request(addr, method, path, "application/json", body.as_bytes())
}

/// GET that must answer 200 with JSON.
pub fn get_json(addr: SocketAddr, path: &str) -> Value {
    let (st, b) = http(addr, "GET", path, None);
    assert_eq!(st, 200, "{path}: {}", String::from_utf8_lossy(&b));
    serde_json::from_slice(&b).unwrap()
}

/// Distance between a shot's localised camera centre and a keyframe's,
/// in map units (both as the API reports them).
pub fn centre_distance(shot: &Value, kf: &Value) -> f64 {
    let c = &shot["localisation"]["world_from_cam"]["translation"];
    let k = &kf["world_from_cam"]["translation"];
    (0..3)
        .map(|i| (c[i].as_f64().unwrap() - k[i].as_f64().unwrap()).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// The diagonal of the map trajectory's bounding box, in map units: the
/// scale that shot errors are divided by.
pub fn trajectory_extent(addr: SocketAddr) -> f64 {
    let traj: Vec<[f64; 3]> =
        serde_json::from_value(get_json(addr, "/api/v1/map")["trajectory"].clone()).unwrap();
    (0..3)
        .map(|i| {
            let (lo, hi) = traj.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
                (lo.min(p[i]), hi.max(p[i]))
            });
            (hi - lo).powi(2)
        })
        .sum::<f64>()
        .sqrt()
}
