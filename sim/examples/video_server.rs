//! Serves the rendered camera flying the explore path as MJPEG until the
//! `shotpilot-sim` CLI wires its own video: `cargo run --release -p
//! shotpilot-sim --example video_server -- [ADDR] [FPS] [SECONDS]`.
//! Then `curl http://ADDR/video.mjpg` or open `/snapshot.jpg`.

use std::sync::Arc;
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::paths::{CameraPath, Params as PathParams};
use shotpilot_sim::render::{RenderParams, Renderer};
use shotpilot_sim::video::{Params as VideoParams, VideoFrame, serve_video};
use shotpilot_sim::world::World;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env().unwrap_or_else(|_| "info".into()),
        )
        .init();
    let args: Vec<String> = std::env::args().collect();
    let addr = args
        .get(1)
        .cloned()
        .unwrap_or_else(|| "127.0.0.1:8554".into());
    let fps: f64 = args.get(2).map(|s| s.parse()).transpose()?.unwrap_or(30.0);
    let seconds: f64 = args.get(3).map(|s| s.parse()).transpose()?.unwrap_or(60.0);
    let world = Arc::new(World::generate(1));
    let path = CameraPath::explore(&world, PathParams::default());
    let renderer = Renderer::new(world, SimCamera::default(), RenderParams::default());
    let (tx, rx) = watch::channel(None);
    let cancel = CancellationToken::new();
    let listener = tokio::net::TcpListener::bind(&addr).await?;
    let server = tokio::spawn(serve_video(listener, rx, cancel.clone()));
    // The camera runs on its own thread at the configured rate.
    let cam_cancel = cancel.clone();
    let camera = std::thread::spawn(move || {
        let period = Duration::from_secs_f64(1.0 / fps);
        let start = Instant::now();
        let mut img = image::GrayImage::new(1, 1);
        let mut seq = 0u64;
        let mut due = start;
        while !cam_cancel.is_cancelled() && start.elapsed().as_secs_f64() < seconds {
            if let Some(wait) = due.checked_duration_since(Instant::now()) {
                std::thread::sleep(wait);
            }
            // A camera that falls behind drops frames instead of bursting.
            due = (due + period).max(Instant::now());
            let t = start.elapsed().as_secs_f64();
            let capture = SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0.0, |d| d.as_secs_f64());
            renderer.render_into(
                &path.world_from_cam(t % path.duration()),
                Some(seq),
                &mut img,
            );
            match VideoFrame::encode(&img, VideoParams::default().jpeg_quality, capture, seq) {
                Ok(f) => {
                    tx.send_replace(Some(Arc::new(f)));
                }
                Err(e) => tracing::error!(error = %e, "encode failed"),
            }
            seq += 1;
        }
        cam_cancel.cancel();
        seq
    });
    let frames = tokio::task::spawn_blocking(move || camera.join())
        .await?
        .map_err(|_| anyhow::anyhow!("camera thread panicked"))?;
    server.await??;
    println!("served {frames} frames");
    Ok(())
}
