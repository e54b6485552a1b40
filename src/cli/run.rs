//! `shotpilot run`: the daemon.

use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use clap::Args;

use shotpilot::config::Config;

/// Arguments of `shotpilot run`.
#[derive(Args, Debug)]
pub struct RunArgs {
    /// Listen address of the API, overriding `[server] bind`.
    #[arg(long, value_name = "ADDR:PORT")]
    pub bind: Option<String>,
    /// Do not start the simulator (overrides `[sim] enabled`).
    #[arg(long)]
    pub no_sim: bool,
    /// Print the final summary as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Runs the daemon until Ctrl-C or SIGTERM, then prints its summary.
pub fn run(args: RunArgs, mut config: Config, path: Option<&Path>) -> Result<()> {
    if let Some(b) = args.bind {
        config.server.bind = b;
    }
    if args.no_sim {
        config.sim.enabled = false;
    }
    let named = path.unwrap_or(Path::new("config.toml"));
    config.validate(named)?;
    // Without the simulator (no `sim` feature) the daemon refuses
    // `[sim] enabled = true` itself: `DaemonError::NoSimulator`.
    #[cfg(feature = "sim")]
    shotpilot::simulator::check(&config, named)?;
    let base_dir = path
        .and_then(Path::parent)
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")?;
    let summary = rt.block_on(async move {
        let cancel = tokio_util::sync::CancellationToken::new();
        let c = cancel.clone();
        tokio::spawn(async move {
            wait_for_signal().await;
            tracing::info!("signal received, stopping");
            c.cancel();
        });
        let (tx, rx) = tokio::sync::oneshot::channel();
        tokio::spawn(async move {
            if let Ok(s) = rx.await {
                let s: shotpilot::daemon::Started = s;
                eprintln!("shotpilot: operator page at http://{}/", s.api_addr);
            }
        });
        shotpilot::daemon::run(config, &base_dir, cancel, Some(tx)).await
    })?;
    if args.json {
        println!("{}", serde_json::to_string(&summary)?);
    } else {
        eprintln!(
            "shotpilot: stopped after {:.1} s; video received {} decoded {} dropped {} bad {}; SLAM frames {} keyframes {}; {} shots",
            summary.run_s,
            summary.video.received,
            summary.video.decoded,
            summary.video.dropped,
            summary.video.bad,
            summary.slam.frames,
            summary.slam.keyframes,
            summary.shots
        );
    }
    Ok(())
}

/// Ctrl-C, or SIGTERM on Unix.
async fn wait_for_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = tokio::signal::ctrl_c() => {}
                    _ = term.recv() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}
