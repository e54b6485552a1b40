//! What the lossy-link video tests share: the drop models of their UDP
//! proxies, each published frame's row hashes and damage marks, the
//! comparison with the lossless copy row by row, the daemon's `udp://`
//! source on a port pair bound here with a watcher that collects every
//! frame it publishes, and the simulator's explore flight.

use std::net::SocketAddr;
use std::sync::{Arc, Mutex};

use rand::{Rng, SeedableRng};
use shotpilot::config::VideoConfig;
use shotpilot::video::live::{CountersSnapshot, Frame, Ingest};
use shotpilot::video::udp::RtpSockets;
use tokio_util::sync::CancellationToken;

/// How the proxy drops packets.
#[derive(Debug, Clone, Copy)]
pub enum Loss {
    /// Each packet independently with this probability.
    Random(f64),
    /// Gilbert-Elliott: a bad state dropping every packet, entered so the
    /// mean loss is `rate`, left with probability 1 / `burst` per packet.
    Bursts { rate: f64, burst: f64 },
}

impl Loss {
    pub fn rate(self) -> f64 {
        match self {
            Loss::Random(p) | Loss::Bursts { rate: p, .. } => p,
        }
    }

    pub fn name(self) -> String {
        match self {
            Loss::Random(p) => format!("{:.0} % random", p * 100.0),
            Loss::Bursts { rate, burst } => {
                format!("{:.0} % bursts of {burst:.0}", rate * 100.0)
            }
        }
    }

    pub fn dropper(self, seed: u64) -> impl FnMut() -> bool {
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let mut bad = false;
        move || match self {
            Loss::Random(p) => rng.random::<f64>() < p,
            Loss::Bursts { rate, burst } => {
                let leave = 1.0 / burst;
                // Stationary bad share = enter / (enter + leave) = rate.
                let enter = rate * leave / (1.0 - rate);
                bad = if bad {
                    rng.random::<f64>() >= leave
                } else {
                    rng.random::<f64>() < enter
                };
                bad
            }
        }
    }
}

/// One published frame, row by row.
#[derive(Debug)]
pub struct RowHashes {
    /// Capture time (the sender's, through its RTCP reports).
    pub capture_time: f64,
    /// A hash of each row.
    pub rows: Vec<u64>,
    /// Which rows the frame marks damaged.
    pub damaged: Vec<bool>,
}

pub fn row_hashes(f: &Frame) -> RowHashes {
    use std::hash::{Hash, Hasher};
    let w = f.image.width() as usize;
    let rows = f
        .image
        .as_raw()
        .chunks(w)
        .map(|r| {
            let mut h = std::collections::hash_map::DefaultHasher::new();
            r.hash(&mut h);
            h.finish()
        })
        .collect::<Vec<_>>();
    let damaged = match &f.damage {
        Some(d) => d.rows().to_vec(),
        None => vec![false; rows.len()],
    };
    RowHashes {
        capture_time: f.timestamp(),
        rows,
        damaged,
    }
}

/// Against the lossless copy (frames matched by capture time): rows marked
/// damaged, rows that really differ, and rows that differ without being
/// marked (must be none), over the frames both copies have.
pub fn against_clean(lossy: &[RowHashes], clean: &[RowHashes]) -> (usize, usize, usize, usize) {
    let (mut rows, mut marked, mut differ, mut unmarked_differ) = (0, 0, 0, 0);
    for f in lossy {
        let Some(c) = clean
            .iter()
            .find(|c| (c.capture_time - f.capture_time).abs() < 1e-4)
        else {
            continue;
        };
        for ((a, b), d) in f.rows.iter().zip(&c.rows).zip(&f.damaged) {
            rows += 1;
            marked += usize::from(*d);
            differ += usize::from(a != b);
            unmarked_differ += usize::from(a != b && !*d);
        }
    }
    (rows, marked, differ, unmarked_differ)
}

/// Collect what `keep` takes of every frame `ingest` publishes, as it
/// comes, until it closes.
fn watch_frames_with<T: Send + 'static>(
    rt: &tokio::runtime::Runtime,
    ingest: &Arc<Ingest>,
    keep: fn(&Frame) -> T,
) -> (Arc<Mutex<Vec<T>>>, tokio::task::JoinHandle<()>) {
    let seen: Arc<Mutex<Vec<T>>> = Arc::new(Mutex::new(Vec::new()));
    let mut rx = ingest.subscribe();
    let out = seen.clone();
    let watcher = rt.spawn(async move {
        while rx.changed().await.is_ok() {
            let f = rx.borrow_and_update().clone();
            if let Some(f) = f {
                out.lock().unwrap().push(keep(&f));
            }
        }
    });
    (seen, watcher)
}

/// The simulator's explore flight as a camera sees it: 640x480 at 15 fps.
pub struct Flight {
    /// The simulated camera.
    pub sim: shotpilot_sim::camera::SimCamera,
    /// Its intrinsics as SLAM takes them.
    pub cam: shotpilot::camera::Camera,
    /// Per picture: its time (1.7e9 s + index / 15) and the true pose.
    pub gt: Vec<(f64, nalgebra::Isometry3<f64>)>,
    /// The rendered pictures (with the sensor's noise), in order.
    pub pictures: Vec<image::GrayImage>,
}

/// The first `n` pictures of the explore flight over world 5.
pub fn explore_flight(n: usize) -> Flight {
    use shotpilot_sim::paths::{CameraPath, Params as PathParams};
    use shotpilot_sim::render::{RenderParams, Renderer};
    let world = Arc::new(shotpilot_sim::world::World::generate(5));
    let path = CameraPath::explore(&world, PathParams::default());
    let sim = shotpilot_sim::camera::SimCamera::default();
    let renderer = Renderer::new(world, sim, RenderParams::default());
    let gt: Vec<(f64, nalgebra::Isometry3<f64>)> = (0..n)
        .map(|i| {
            let t = i as f64 / 15.0;
            (1.7e9 + t, path.world_from_cam(path.start() + t))
        })
        .collect();
    let pictures = gt
        .iter()
        .enumerate()
        .map(|(i, (_, p))| renderer.render_noisy(p, i as u64))
        .collect();
    let cam = shotpilot::simulator::camera_from_sim(&sim).unwrap();
    Flight {
        sim,
        cam,
        gt,
        pictures,
    }
}

/// One of the daemon's `udp://` sources on 127.0.0.1, and what it
/// published.
pub struct LiveSource<T> {
    /// Its ingest (counters, link quality).
    pub ingest: Arc<Ingest>,
    cancel: CancellationToken,
    task: tokio::task::JoinHandle<Result<(), shotpilot::video::source::SourceError>>,
    seen: Arc<Mutex<Vec<T>>>,
    watcher: tokio::task::JoinHandle<()>,
}

impl<T: Send + 'static> LiveSource<T> {
    /// Start a source with `cfg` (its URL set to the RTP port bound here)
    /// keeping what `keep` takes of each frame; returns where to send RTP.
    pub fn start(
        rt: &tokio::runtime::Runtime,
        mut cfg: VideoConfig,
        keep: fn(&Frame) -> T,
    ) -> (SocketAddr, LiveSource<T>) {
        let ingest = Arc::new(Ingest::new());
        let cancel = CancellationToken::new();
        let sockets = RtpSockets::bind_pair("127.0.0.1".parse().unwrap()).unwrap();
        let to = sockets.rtp_addr().unwrap();
        cfg.url = format!("udp://{to}");
        let task = rt.spawn(shotpilot::video::source::run_configured_on(
            cfg,
            ingest.clone(),
            cancel.clone(),
            None,
            Some(sockets),
        ));
        let (seen, watcher) = watch_frames_with(rt, &ingest, keep);
        (
            to,
            LiveSource {
                ingest,
                cancel,
                task,
                seen,
                watcher,
            },
        )
    }

    /// Stop it: its counters at the end and what it kept.
    pub fn stop(self, rt: &tokio::runtime::Runtime) -> (CountersSnapshot, Vec<T>) {
        self.cancel.cancel();
        rt.block_on(self.task).unwrap().unwrap();
        let counters = self.ingest.counters.snapshot();
        self.ingest.close();
        drop(self.ingest);
        rt.block_on(self.watcher).unwrap();
        let frames = std::mem::take(&mut *self.seen.lock().unwrap());
        (counters, frames)
    }
}

/// The tests' runtime: two workers, as the daemon runs.
pub fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap()
}
