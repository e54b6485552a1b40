//! `shotpilot-sim`: run the simulated vehicle, gimbal camera and MAVLink
//! autopilot (see `shotpilot-sim --help`).

use std::net::SocketAddr;
use std::path::PathBuf;

use anyhow::{Context, Result};
use clap::{Parser, Subcommand, ValueEnum};
use shotpilot_sim::app::{SimConfig, run_announcing};
use shotpilot_sim::autopilot::Flavour;
use shotpilot_sim::camera::SimCamera;
use shotpilot_sim::dataset::{RenderJob, render_job};
use shotpilot_sim::geodesy::Geodetic;
use shotpilot_sim::link::{Endpoint, RadioDirParams, RadioParams};
use shotpilot_sim::paths::PathSpec;
use shotpilot_sim::realism::Realism;
use shotpilot_sim::render::RenderParams;
use shotpilot_sim::rtp::{H264Encoder, RtpOutParams, sdp};
use shotpilot_sim::script::ScriptKind;
use shotpilot_sim::world::WorldKind;
use tokio_util::sync::CancellationToken;

#[derive(Debug, Clone, Copy, ValueEnum)]
enum FlavourArg {
    /// PX4: MAV_AUTOPILOT_PX4 heartbeat, PX4 custom modes, PX4 mission rules.
    Px4,
    /// ArduPilot copter: ARDUPILOTMEGA heartbeat, copter modes, seq 0 = home.
    Ardupilot,
}

#[derive(Debug, Clone, Copy, ValueEnum)]
enum ScriptArg {
    /// Take off and survey the scene at several altitudes (SLAM parallax),
    /// then hover and accept missions.
    Explore,
    /// Take off and hover over home.
    Hover,
    /// Fly the survey lap after lap until the operator takes over (soak
    /// runs: a long flight that keeps revisiting mapped places).
    Patrol,
}

/// The simulated world for shotpilot: a PX4-like quadrotor with a gimbal
/// camera over a procedurally textured scene, speaking MAVLink 2 and
/// serving its camera as MJPEG.
#[derive(Debug, Parser)]
#[command(
    name = "shotpilot-sim",
    version,
    about,
    long_about = None,
    after_long_help = "World frame: the local NED tangent plane at --home (x north, y east, z down, \
metres, ground at z = 0); camera poses are world_from_cam with camera axes x right, y down, \
z forward. The render world uses the same frame (the fixed transform is the identity).\n\n\
Examples:\n  shotpilot-sim --script explore --truth-dir truth\n  \
shotpilot-sim --mavlink udpin:0.0.0.0:14550 --drop 0.3 --baud 57600 --latency-ms 80\n  \
shotpilot-sim --mavlink serial:/dev/pts/3:57600 --flavour ardupilot\n  \
shotpilot-sim --script explore --rtp-out 127.0.0.1:5600 --sdp sim.sdp\n  \
shotpilot-sim render --path orbit --frames 600 --out dataset\n\n\
A ground station (QGroundControl, MAVProxy, pymavlink) listening on UDP 14550 sees the vehicle \
with the default --mavlink."
)]
struct Cli {
    #[command(subcommand)]
    command: Option<Command>,

    /// MAVLink endpoint: udpout:HOST:PORT (send to a ground station, as PX4
    /// SITL does to 14550), udpin:ADDR:PORT (listen, reply to the last
    /// sender), tcpin:ADDR:PORT, tcpout:HOST:PORT or serial:/dev/DEVICE:BAUD
    /// (a socat pty pair works).
    #[arg(long, default_value = "udpout:127.0.0.1:14550", value_name = "URL")]
    mavlink: String,

    /// Address of the MJPEG video server (GET /video.mjpg is the
    /// multipart/x-mixed-replace stream with each frame's capture time in an
    /// X-Timestamp header, GET /snapshot.jpg one frame); "off" disables it.
    #[arg(long, default_value = "127.0.0.1:8554", value_name = "ADDR")]
    video_listen: String,

    /// Video frames per second.
    #[arg(long, default_value_t = 15.0, value_name = "N")]
    video_fps: f64,

    /// Also send the camera as H.264 over RTP/UDP to HOST:PORT (RFC 6184,
    /// RTCP sender reports to PORT+1; what an OpenIPC / wfb-ng link or a
    /// gimbal camera's raw RTP output sends). The camera then announces
    /// udp://HOST:PORT in VIDEO_STREAM_INFORMATION, so a ground station
    /// listening there (shotpilot with `[video] url = "auto"` or
    /// "udp://HOST:PORT", QGroundControl's UDP H.264 source) shows it.
    #[arg(long, value_name = "HOST:PORT")]
    rtp_out: Option<String>,

    /// H.264 target bitrate of --rtp-out, kbit/s.
    #[arg(long, default_value_t = 1500, value_name = "KBIT_S")]
    rtp_bitrate: u32,

    /// Seconds between IDR pictures of --rtp-out.
    #[arg(long, default_value_t = 1.0, value_name = "S")]
    rtp_idr_interval: f64,

    /// Largest RTP packet of --rtp-out, bytes.
    #[arg(long, default_value_t = 1200, value_name = "BYTES")]
    rtp_mtu: usize,

    /// Write the session description of --rtp-out to FILE ("-": print it
    /// on stdout) before starting, for receivers that read an SDP
    /// (shotpilot's `[video] url = "FILE.sdp"`, ffplay, VLC, GStreamer).
    #[arg(long, value_name = "FILE", requires = "rtp_out")]
    sdp: Option<String>,

    /// Which autopilot to imitate.
    #[arg(long, value_enum, default_value = "px4")]
    flavour: FlavourArg,

    /// Bad radio: probability of dropping a whole MAVLink frame, each way.
    #[arg(long, default_value_t = 0.0, value_name = "P")]
    drop: f64,

    /// Bad radio: drop probability ground -> vehicle (overrides --drop).
    #[arg(long, value_name = "P")]
    drop_up: Option<f64>,

    /// Bad radio: drop probability vehicle -> ground (overrides --drop).
    #[arg(long, value_name = "P")]
    drop_down: Option<f64>,

    /// Bad radio: probability of corrupting each byte, each way (the frame
    /// then fails its CRC at the receiver).
    #[arg(long, default_value_t = 0.0, value_name = "RATE")]
    corrupt: f64,

    /// Bad radio: bandwidth cap each way in baud (8N1: 57600 baud = 5760
    /// bytes/s); frames queue and overflow a 4 KiB buffer. 0 = no cap.
    #[arg(long, default_value_t = 0, value_name = "N")]
    baud: u32,

    /// Bad radio: added one-way latency, milliseconds.
    #[arg(long, default_value_t = 0.0, value_name = "N")]
    latency_ms: f64,

    /// Seed of the world, sensor noise and the bad radio.
    #[arg(long, default_value_t = 1, value_name = "N", global = true)]
    seed: u64,

    /// A scripted operator flies the vehicle (without one the vehicle waits
    /// on the ground for a ground station).
    #[arg(long, value_enum)]
    script: Option<ScriptArg>,

    /// Folder for IMAGE_START_CAPTURE / DO_DIGICAM_CONTROL pictures
    /// (IMG_0000.jpg, ...).
    #[arg(long, default_value = "captures", value_name = "DIR")]
    capture_dir: PathBuf,

    /// Folder for the ground truth of the video frames (TUM trajectory of
    /// world_from_cam in local NED, frame times).
    #[arg(long, value_name = "DIR")]
    truth_dir: Option<PathBuf>,

    /// Home position as LAT,LON,ALT (degrees, degrees, metres AMSL).
    #[arg(
        long,
        default_value = "47.397742,8.545594,488.0",
        value_name = "LAT,LON,ALT"
    )]
    home: String,

    /// Stop after this many seconds (default: run until Ctrl-C).
    #[arg(long, value_name = "S")]
    duration: Option<f64>,

    /// Render frames without sensor noise.
    #[arg(long, global = true)]
    no_noise: bool,
    /// No MAVLink camera component (100): the autopilot triggers the camera
    /// itself and reports CAMERA_IMAGE_CAPTURED as component 1, as a PX4
    /// with a trigger-wired camera does.
    #[arg(long)]
    no_mavlink_camera: bool,

    /// Realism: a preset (ideal, field, harsh) then any -EFFECT (off) or
    /// +EFFECT[@PRESET] (on), e.g. field-blur or ideal+wind@harsh. Effects:
    /// blur, rolling_shutter, auto_exposure, sun, clouds, vignetting, noise,
    /// compression, h264 (H.264 in place of JPEG), wind, gimbal, gps, gps_dropouts, baro, ahrs, telemetry,
    /// video_latency (see the shotpilot_sim::realism documentation).
    #[arg(long, default_value = "ideal", value_name = "PRESET", global = true)]
    realism: String,

    /// The world: town, grass, carpark, trees, water, traffic or aliasing.
    #[arg(long, default_value = "town", value_name = "NAME", global = true)]
    world: String,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Render a TUM-layout dataset (rgb/, rgb.txt, calib.txt,
    /// groundtruth.txt) along a camera path, without flying.
    Render {
        /// explore, orbit, loop (one lap revisiting its start after more
        /// than 400 m), or a TUM trajectory file (world_from_cam).
        #[arg(long, default_value = "explore")]
        path: String,
        /// Number of frames.
        #[arg(long, default_value_t = 600)]
        frames: usize,
        /// Output folder.
        #[arg(long)]
        out: PathBuf,
    },
}

fn parse_home(s: &str) -> Result<Geodetic> {
    let v: Vec<f64> = s
        .split(',')
        .map(|x| x.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .with_context(|| format!("--home {s:?}: expected LAT,LON,ALT"))?;
    anyhow::ensure!(v.len() == 3, "--home {s:?}: expected three numbers");
    anyhow::ensure!(
        (-90.0..=90.0).contains(&v[0]) && (-180.0..=180.0).contains(&v[1]),
        "--home {s:?}: latitude/longitude out of range"
    );
    Ok(Geodetic {
        lat_deg: v[0],
        lon_deg: v[1],
        alt_m: v[2],
    })
}

fn rtp_from(cli: &Cli) -> Result<Option<RtpOutParams>> {
    let Some(dest) = &cli.rtp_out else {
        return Ok(None);
    };
    let dest = std::net::ToSocketAddrs::to_socket_addrs(dest.as_str())
        .with_context(|| format!("--rtp-out {dest:?}: expected HOST:PORT"))?
        .next()
        .with_context(|| format!("--rtp-out {dest:?}: no address"))?;
    let p = RtpOutParams {
        dest,
        bitrate_bps: cli.rtp_bitrate.saturating_mul(1000),
        idr_interval_s: cli.rtp_idr_interval,
        mtu: cli.rtp_mtu,
        ..RtpOutParams::default()
    };
    p.check()
        .map_err(|(field, reason)| anyhow::anyhow!("--rtp-*: {field} {reason}"))?;
    Ok(Some(p))
}

fn config_from(cli: &Cli) -> Result<SimConfig> {
    let video_listen = if cli.video_listen == "off" {
        None
    } else {
        Some(
            cli.video_listen
                .parse::<SocketAddr>()
                .with_context(|| format!("--video-listen {:?}", cli.video_listen))?,
        )
    };
    let dir = |drop: f64| RadioDirParams {
        drop,
        corrupt: cli.corrupt,
        latency_s: cli.latency_ms / 1000.0,
        baud: (cli.baud > 0).then_some(cli.baud),
        ..RadioDirParams::default()
    };
    let defaults = SimConfig::default();
    let mut autopilot = defaults.autopilot.clone();
    autopilot.flavour = match cli.flavour {
        FlavourArg::Px4 => Flavour::Px4,
        FlavourArg::Ardupilot => Flavour::ArduPilot,
    };
    autopilot.vehicle.home = parse_home(&cli.home)?;
    Ok(SimConfig {
        mavlink: cli.mavlink.parse::<Endpoint>()?,
        video_listen,
        video_fps: cli.video_fps,
        radio: RadioParams {
            up: dir(cli.drop_up.unwrap_or(cli.drop)),
            down: dir(cli.drop_down.unwrap_or(cli.drop)),
            seed: cli.seed,
        },
        seed: cli.seed,
        script: cli.script.map(|s| match s {
            ScriptArg::Explore => ScriptKind::Explore,
            ScriptArg::Hover => ScriptKind::Hover,
            ScriptArg::Patrol => ScriptKind::Patrol,
        }),
        capture_dir: cli.capture_dir.clone(),
        truth_dir: cli.truth_dir.clone(),
        autopilot,
        sensor_noise: !cli.no_noise,
        mavlink_camera: !cli.no_mavlink_camera,
        world: cli.world.parse().context("--world")?,
        rtp_out: rtp_from(cli)?,
        ..defaults
    }
    .with_realism(cli.realism.parse().context("--realism")?))
}

/// Whether log lines carry colour: only when the stream they go to is a
/// terminal and `NO_COLOR` is unset or empty (<https://no-color.org>), so a
/// log redirected to a file or a pipe carries no escape codes (as the
/// daemon's `shotpilot` decides it).
fn colour_logs(to_terminal: bool) -> bool {
    to_terminal && std::env::var_os("NO_COLOR").is_none_or(|v| v.is_empty())
}

fn main() -> Result<()> {
    // The log goes to stdout (beside the `shotpilot-sim bound:` line), so
    // stdout decides the colour.
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info")),
        )
        .with_ansi(colour_logs(std::io::IsTerminal::is_terminal(
            &std::io::stdout(),
        )))
        .with_writer(std::io::stdout)
        .init();
    let cli = Cli::parse();
    let realism: Realism = cli.realism.parse().context("--realism")?;
    let world: WorldKind = cli.world.parse().context("--world")?;
    if let Some(Command::Render { path, frames, out }) = &cli.command {
        let spec: PathSpec = path.parse().unwrap_or(PathSpec::Explore);
        let noise = if cli.no_noise {
            0.0
        } else {
            RenderParams::default().noise_sigma
        };
        let job = RenderJob {
            path: spec,
            frames: *frames,
            out_dir: out.clone(),
            seed: cli.seed,
            camera: SimCamera::default(),
            noise_sigma: noise,
            realism,
            world,
        };
        let report =
            render_job(&job).with_context(|| format!("rendering {path} into {}", out.display()))?;
        let bitrate = report
            .bitrate_bit_s
            .map_or(String::new(), |b| format!(", stream {:.2} Mbit/s", b / 1e6));
        println!(
            "{} frames in {} ({:.1} frames/s, world {}, realism {}{bitrate})",
            report.frames,
            out.display(),
            report.render_fps(),
            report.world,
            report.realism,
        );
        return Ok(());
    }
    let config = config_from(&cli)?;
    if let (Some(rtp), Some(to)) = (&config.rtp_out, &cli.sdp) {
        let cam = &config.camera;
        let sets =
            H264Encoder::parameter_sets(cam.width, cam.height, config.video_fps, rtp.bitrate_bps)
                .context("H.264 parameter sets for the SDP")?;
        let text = sdp(rtp, config.video_fps, &sets);
        if to == "-" {
            print!("{text}");
        } else {
            std::fs::write(to, text).with_context(|| format!("writing the SDP to {to}"))?;
        }
    }
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("tokio runtime")?;
    rt.block_on(async move {
        let cancel = CancellationToken::new();
        let c2 = cancel.clone();
        let duration = cli.duration;
        tokio::spawn(async move {
            match duration {
                Some(s) => {
                    tokio::select! {
                        _ = tokio::signal::ctrl_c() => {}
                        _ = tokio::time::sleep(std::time::Duration::from_secs_f64(s.max(0.0))) => {}
                    }
                }
                None => {
                    let _ = tokio::signal::ctrl_c().await;
                }
            }
            c2.cancel();
        });
        let summary = run_announcing(config, cancel, true).await?;
        tracing::info!(
            "done: {:.1} s simulated, {} frames ({} skipped), {} captures, link {:?}",
            summary.sim_seconds,
            summary.frames,
            summary.frames_skipped,
            summary.captures,
            summary.link
        );
        if let Some(r) = summary.rtp {
            tracing::info!("RTP H.264: {r:?}");
        }
        Ok(())
    })
}
