//! Mission upload against the simulator (the `shotpilot-sim` crate, run
//! in-process): its PX4-like and ArduPilot-like autopilot behind its own bad
//! radio (frame loss each way, byte corruption, a 57600 baud cap), over UDP
//! and over a serial pty pair. Every upload is read back and compared. The
//! UDP runs are on simulated time (tokio's paused clock drives the
//! simulator's steps, its radio and the link's timeouts alike); the pty
//! run, through socat, is in real time.

use crate::link_support;

use std::time::Duration;

use tokio::time::Instant;

use shotpilot::mission::plan::{self, Flavour, Home, Target};
use shotpilot::mission::upload::{self, same_mission};
use shotpilot::vehicle::{self, LinkHandle, Params};
use shotpilot_sim::app::{self, SimConfig};
use shotpilot_sim::autopilot::Flavour as SimFlavour;
use shotpilot_sim::link::{Endpoint, RadioDirParams, RadioParams};
use tokio_util::sync::CancellationToken;

pub(crate) fn bad_radio(seed: u64) -> RadioParams {
    let dir = RadioDirParams {
        drop: 0.3,
        corrupt: 1e-4,
        baud: Some(57600),
        ..RadioDirParams::default()
    };
    RadioParams {
        up: dir,
        down: dir,
        seed,
    }
}

pub(crate) fn sim_config(
    endpoint: Endpoint,
    flavour: Flavour,
    radio: RadioParams,
    dir: &std::path::Path,
) -> SimConfig {
    let mut c = SimConfig::default().with_flavour(match flavour {
        Flavour::Px4 => SimFlavour::Px4,
        Flavour::ArduPilot => SimFlavour::ArduPilot,
    });
    c.mavlink = endpoint;
    c.video_listen = None;
    c.radio = radio;
    c.capture_dir = dir.join("captures");
    c.sensor_noise = false;
    c
}

async fn home_of(link: &LinkHandle) -> anyhow::Result<Home> {
    let mut rx = link.telemetry.home.clone();
    let h = tokio::time::timeout(Duration::from_secs(30), rx.wait_for(|h| h.is_some()))
        .await??
        .map(|s| s.value)
        .ok_or_else(|| anyhow::anyhow!("no home"))?;
    Ok(Home {
        lat_deg: h.lat_deg,
        lon_deg: h.lon_deg,
        alt_amsl_m: h.alt_amsl_m,
    })
}

fn target(home: &Home, k: usize) -> Target {
    Target {
        lat_deg: home.lat_deg + 0.0003 + 2e-6 * k as f64,
        lon_deg: home.lon_deg - 0.0002,
        alt_m: 20.0 + 0.5 * k as f64,
        yaw_deg: (k * 11 % 360) as f64,
        gimbal_pitch_deg: -30.0,
        photo: true,
    }
}

struct Figures {
    items: usize,
    upload_s: Vec<f64>,
    download_s: Vec<f64>,
    retries: u32,
    read_backs: u32,
}

async fn uploads(link: &LinkHandle, flavour: Flavour, n: usize) -> anyhow::Result<Figures> {
    let home = home_of(link).await?;
    let mut f = Figures {
        items: 0,
        upload_s: Vec::new(),
        download_s: Vec::new(),
        retries: 0,
        read_backs: 0,
    };
    for k in 0..n {
        let items = plan::plan(&target(&home, k), &home, flavour, &plan::Params::default())?;
        f.items = items.len();
        let t0 = Instant::now();
        let r = link
            .upload_mission(items.clone())
            .await
            .map_err(|e| anyhow::anyhow!("upload {k}: {e}"))?;
        f.upload_s.push(t0.elapsed().as_secs_f64());
        f.retries += r.retries;
        f.read_backs += u32::from(r.verified_by_download);
        let d = link
            .download_mission()
            .await
            .map_err(|e| anyhow::anyhow!("download {k}: {e}"))?;
        f.download_s.push(d.seconds);
        anyhow::ensure!(
            same_mission(&items, &d.items, flavour == Flavour::ArduPilot),
            "upload {k}: read back {:?}\nplanned {:?}",
            d.items,
            items
        );
    }
    Ok(f)
}

fn median_max(v: &[f64]) -> (f64, f64) {
    shotpilot::stats::median_max(v).unwrap_or((f64::NAN, f64::NAN))
}

fn report(what: &str, n: usize, f: &Figures) {
    let (um, ux) = median_max(&f.upload_s);
    let (dm, dx) = median_max(&f.download_s);
    println!(
        "{what}: {n}/{n} uploads of {} items read back identical; upload median {um:.2} s, max {ux:.2} s; \
         download median {dm:.2} s, max {dx:.2} s; {} retries, {} lost final ACKs settled by read-back",
        f.items, f.retries, f.read_backs
    );
}

async fn lossy_udp(flavour: Flavour, n: usize, seed: u64) -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let (socket, addr) = link_support::bound_udp();
    let cancel = CancellationToken::new();
    let cfg = sim_config(
        Endpoint::UdpIn(addr.to_string()),
        flavour,
        bad_radio(seed),
        dir.path(),
    );
    let sockets = app::Sockets {
        mavlink: Some(socket),
        ..Default::default()
    };
    let sim = tokio::spawn(app::run_on(cfg, cancel.child_token(), sockets));
    let p = Params {
        url: format!("udpout:{addr}"),
        link_lost_after_ms: 8000,
        ..Params::default()
    };
    let (link, _task) = vehicle::spawn(p, upload::Params::default(), cancel.clone())?;
    let v = link.wait_for_vehicle(Duration::from_secs(20)).await?;
    anyhow::ensure!(v.flavour == Some(flavour), "sim says {:?}", v.flavour);
    let f = uploads(&link, flavour, n).await?;
    report(
        &format!("sim {flavour:?} UDP, 30 % loss each way, 1e-4 corruption, 57600 baud"),
        n,
        &f,
    );
    cancel.cancel();
    let summary = sim.await??;
    println!("sim link counters: {:?}", summary.link);
    Ok(())
}

#[tokio::test(start_paused = true)]
async fn sim_lossy_uploads_px4() -> anyhow::Result<()> {
    lossy_udp(Flavour::Px4, 5, 3).await
}

#[tokio::test(start_paused = true)]
async fn sim_lossy_uploads_ardupilot() -> anyhow::Result<()> {
    lossy_udp(Flavour::ArduPilot, 5, 4).await
}

#[tokio::test(start_paused = true)]
#[ignore = "slow: 2 x 50 uploads through the simulator's bad radio; run with --ignored for the figures"]
async fn sim_lossy_uploads_50_each() -> anyhow::Result<()> {
    // both flavours at once, each with its own simulator and link
    let (px4, ardupilot) = tokio::join!(
        lossy_udp(Flavour::Px4, 50, 50),
        lossy_udp(Flavour::ArduPilot, 50, 51)
    );
    px4?;
    ardupilot
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
#[ignore = "needs socat"]
async fn sim_over_serial_pty_at_57600() -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let a = dir.path().join("gcs");
    let b = dir.path().join("vehicle");
    let mut socat = std::process::Command::new("socat")
        .arg(format!("pty,raw,echo=0,link={}", a.display()))
        .arg(format!("pty,raw,echo=0,link={}", b.display()))
        .stderr(std::process::Stdio::null())
        .spawn()?;
    for _ in 0..100 {
        if a.exists() && b.exists() {
            break;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let cancel = CancellationToken::new();
    let radio = RadioParams {
        up: RadioDirParams {
            baud: Some(57600),
            ..RadioDirParams::default()
        },
        down: RadioDirParams {
            baud: Some(57600),
            ..RadioDirParams::default()
        },
        seed: 9,
    };
    let endpoint = Endpoint::Serial {
        path: b.display().to_string(),
        baud: 57600,
    };
    let cfg = sim_config(endpoint, Flavour::Px4, radio, dir.path());
    let sim = tokio::spawn(app::run(cfg, cancel.child_token()));
    let p = Params {
        url: format!("serial:{}:57600", a.display()),
        ..Params::default()
    };
    let (link, _task) = vehicle::spawn(p, upload::Params::default(), cancel.clone())?;
    link.wait_for_vehicle(Duration::from_secs(20)).await?;
    let f = uploads(&link, Flavour::Px4, 5).await?;
    report("sim Px4 over a socat pty pair, 57600 baud", 5, &f);
    cancel.cancel();
    sim.await??;
    socat.kill()?;
    socat.wait()?;
    Ok(())
}
