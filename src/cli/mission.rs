//! `shotpilot mission`: plan, upload, download and start missions.

use std::path::PathBuf;
use std::time::Duration;

use anyhow::{Context, Result, anyhow, bail};
use clap::{Args, Subcommand};
use serde_json::json;
use tokio_util::sync::CancellationToken;

use shotpilot::config::Config;
use shotpilot::mission::plan::{self, Flavour, Home, Target};
use shotpilot::mission::upload::same_mission;
use shotpilot::vehicle::{self, FlightMode, LinkHandle};

/// The `shotpilot mission` subcommands.
#[derive(Subcommand, Debug)]
pub enum MissionCommand {
    /// Plan the mission that takes the camera to a target, upload it, and
    /// read it back to verify. Never arms, changes mode or starts the mission.
    Upload(UploadArgs),
    /// Download the vehicle's mission.
    Download(LinkArgs),
    /// Plan a mission offline (no vehicle: `--home` is required) and export
    /// it as a QGroundControl `.plan` file.
    Plan(PlanArgs),
    /// Operator action: (optionally arm, then) start the uploaded mission.
    Start(StartArgs),
}

/// How to reach the vehicle, and the output format.
#[derive(Args, Debug)]
pub struct LinkArgs {
    /// Link URL (serial:/dev/ttyUSB0:57600, udpin:0.0.0.0:14550,
    /// udpout:HOST:PORT, tcpout:HOST:PORT). Default: `[link] url` of the config.
    #[arg(long, value_name = "URL")]
    pub link: Option<String>,
    /// How long to wait for the vehicle's heartbeat, seconds.
    #[arg(long, default_value_t = 10.0, value_name = "S")]
    pub wait: f64,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Autopilot flavour on the command line.
#[derive(clap::ValueEnum, Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlavourArg {
    /// From the vehicle's heartbeat.
    Auto,
    /// PX4.
    Px4,
    /// ArduPilot.
    Ardupilot,
}

/// The camera target of a mission.
#[derive(Args, Debug)]
pub struct TargetArgs {
    /// The camera target: latitude and longitude (degrees), altitude above
    /// home (m), heading (degrees from north), gimbal pitch (degrees, negative down).
    #[arg(
        long,
        value_name = "LAT,LON,ALT,YAW_DEG,PITCH_DEG",
        allow_hyphen_values = true
    )]
    pub target: String,
    /// Take a photo on arrival.
    #[arg(long)]
    pub photo: bool,
}

/// Arguments of `shotpilot mission upload`.
#[derive(Args, Debug)]
pub struct UploadArgs {
    #[command(flatten)]
    pub link: LinkArgs,
    #[command(flatten)]
    pub target: TargetArgs,
    /// Home (latitude, longitude, altitude AMSL) for the geofence and the
    /// relative altitudes. Default: the vehicle's HOME_POSITION.
    #[arg(long, value_name = "LAT,LON,ALT_AMSL", allow_hyphen_values = true)]
    pub home: Option<String>,
    /// Which autopilot's items to plan.
    #[arg(long, value_enum, default_value = "auto")]
    pub flavour: FlavourArg,
    /// Skip reading the mission back after the upload.
    #[arg(long)]
    pub no_verify: bool,
}

/// Arguments of `shotpilot mission plan`.
#[derive(Args, Debug)]
pub struct PlanArgs {
    #[command(flatten)]
    pub target: TargetArgs,
    /// Home (latitude, longitude, altitude AMSL) for the geofence and the
    /// relative altitudes. Required: offline there is no vehicle to ask.
    #[arg(long, value_name = "LAT,LON,ALT_AMSL", allow_hyphen_values = true)]
    pub home: String,
    /// Which autopilot's items to plan (`auto` means PX4 offline).
    #[arg(long, value_enum, default_value = "px4")]
    pub flavour: FlavourArg,
    /// Write the QGroundControl plan here.
    #[arg(long, value_name = "FILE")]
    pub qgc_plan: PathBuf,
    /// Print exactly one JSON object on stdout instead of text.
    #[arg(long)]
    pub json: bool,
}

/// Arguments of `shotpilot mission start`.
#[derive(Args, Debug)]
pub struct StartArgs {
    #[command(flatten)]
    pub link: LinkArgs,
    /// Arm the vehicle before starting (an explicit operator decision).
    #[arg(long)]
    pub arm: bool,
}

/// Runs one mission subcommand against the vehicle (or offline for `plan`).
pub fn run(cmd: MissionCommand, config: &Config) -> Result<()> {
    match cmd {
        MissionCommand::Plan(args) => cmd_plan(args, config),
        MissionCommand::Upload(args) => block_on(cmd_upload(args, config)),
        MissionCommand::Download(args) => block_on(cmd_download(args, config)),
        MissionCommand::Start(args) => block_on(cmd_start(args, config)),
    }
}

fn block_on<F: std::future::Future<Output = Result<()>>>(f: F) -> Result<()> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?
        .block_on(f)
}

fn numbers(text: &str, n: usize, what: &str) -> Result<Vec<f64>> {
    let v: Vec<f64> = text
        .split(',')
        .map(|s| s.trim().parse::<f64>())
        .collect::<std::result::Result<_, _>>()
        .with_context(|| format!("{what} `{text}`: not numbers"))?;
    if v.len() != n {
        bail!(
            "{what} `{text}`: expected {n} comma-separated numbers, got {}",
            v.len()
        );
    }
    Ok(v)
}

fn target(args: &TargetArgs) -> Result<Target> {
    let v = numbers(&args.target, 5, "--target")?;
    Ok(Target {
        lat_deg: v[0],
        lon_deg: v[1],
        alt_m: v[2],
        yaw_deg: v[3],
        gimbal_pitch_deg: v[4],
        photo: args.photo,
    })
}

fn home_arg(text: &str) -> Result<Home> {
    let v = numbers(text, 3, "--home")?;
    Ok(Home {
        lat_deg: v[0],
        lon_deg: v[1],
        alt_amsl_m: v[2],
    })
}

fn cmd_plan(args: PlanArgs, config: &Config) -> Result<()> {
    let t = target(&args.target)?;
    let home = home_arg(&args.home)?;
    let flavour = match args.flavour {
        FlavourArg::Ardupilot => Flavour::ArduPilot,
        FlavourArg::Px4 | FlavourArg::Auto => Flavour::Px4,
    };
    let p = &config.mission.plan;
    let items = plan::plan(&t, &home, flavour, p)?;
    let doc = plan::to_qgc_plan(&items, &home, flavour, p)?;
    std::fs::write(&args.qgc_plan, serde_json::to_string_pretty(&doc)? + "\n")
        .with_context(|| format!("writing {}", args.qgc_plan.display()))?;
    if args.json {
        println!(
            "{}",
            json!({ "items": items, "flavour": flavour, "qgc_plan": args.qgc_plan })
        );
    } else {
        println!(
            "{} items for {flavour:?} written to {}",
            items.len(),
            args.qgc_plan.display()
        );
    }
    Ok(())
}

async fn connect(
    args: &LinkArgs,
    config: &Config,
    cancel: &CancellationToken,
) -> Result<(LinkHandle, vehicle::VehicleState)> {
    let mut p = config.link.clone();
    if let Some(url) = &args.link {
        p.url = url.clone();
    }
    let (link, _task) = vehicle::spawn(p, config.mission.transfer, cancel.clone())?;
    let v = link
        .wait_for_vehicle(Duration::from_secs_f64(args.wait.max(0.0)))
        .await?;
    tracing::info!(system = ?v.system_id, flavour = ?v.flavour, mode = %v.mode, "vehicle");
    Ok((link, v))
}

async fn cmd_upload(args: UploadArgs, config: &Config) -> Result<()> {
    let cancel = CancellationToken::new();
    let t = target(&args.target)?;
    let (link, v) = connect(&args.link, config, &cancel).await?;
    let flavour = match args.flavour {
        FlavourArg::Px4 => Flavour::Px4,
        FlavourArg::Ardupilot => Flavour::ArduPilot,
        FlavourArg::Auto => v.flavour.ok_or_else(|| {
            anyhow!(
                "autopilot {} is neither PX4 nor ArduPilot: pass --flavour",
                v.autopilot
            )
        })?,
    };
    let home = match args.home.as_deref().map(home_arg).transpose()? {
        Some(h) => h,
        None => {
            let mut rx = link.telemetry.home.clone();
            let h = tokio::time::timeout(Duration::from_secs(5), rx.wait_for(|h| h.is_some()))
                .await
                .map_err(|_| anyhow!("no HOME_POSITION from the vehicle within 5 s: pass --home"))??
                .map(|s| s.value)
                .ok_or_else(|| anyhow!("no home"))?;
            Home {
                lat_deg: h.lat_deg,
                lon_deg: h.lon_deg,
                alt_amsl_m: h.alt_amsl_m,
            }
        }
    };
    let items = plan::plan(&t, &home, flavour, &config.mission.plan)?;
    let upload = tokio::select! {
        r = link.upload_mission(items.clone()) => r,
        _ = tokio::signal::ctrl_c() => {
            link.cancel_transfer().await.ok();
            bail!("cancelled by the operator");
        }
    };
    let report = match upload {
        Ok(r) => r,
        Err(e) => {
            if args.link.json {
                println!(
                    "{}",
                    json!({ "result": "error", "error": e.to_string(), "items": items.len() })
                );
            }
            cancel.cancel();
            return Err(e.into());
        }
    };
    let verified = if args.no_verify {
        None
    } else {
        let d = link.download_mission().await?;
        Some((
            same_mission(&items, &d.items, flavour == Flavour::ArduPilot),
            d.seconds,
        ))
    };
    cancel.cancel();
    if args.link.json {
        println!(
            "{}",
            json!({
                "result": "accepted",
                "items": report.items,
                "seconds": report.seconds,
                "retries": report.retries,
                "repeats": report.repeats,
                "ack_lost_verified_by_download": report.verified_by_download,
                "flavour": flavour,
                "vehicle_system_id": v.system_id,
                "verified": verified.map(|v| v.0),
                "download_seconds": verified.map(|v| v.1),
            })
        );
    } else {
        println!(
            "uploaded {} items to vehicle {:?} ({flavour:?}) in {:.2} s with {} retries{}",
            report.items,
            v.system_id,
            report.seconds,
            report.retries,
            match verified {
                Some((true, s)) => format!("; read back identical in {s:.2} s"),
                Some((false, _)) => "; READ BACK DIFFERENT".into(),
                None => String::new(),
            }
        );
    }
    if verified.is_some_and(|v| !v.0) {
        bail!("the vehicle's mission differs from the one uploaded");
    }
    Ok(())
}

async fn cmd_download(args: LinkArgs, config: &Config) -> Result<()> {
    let cancel = CancellationToken::new();
    let (link, v) = connect(&args, config, &cancel).await?;
    let d = link.download_mission().await?;
    cancel.cancel();
    if args.json {
        println!(
            "{}",
            json!({ "items": d.items, "count": d.items.len(), "seconds": d.seconds, "retries": d.retries, "vehicle_system_id": v.system_id })
        );
    } else {
        println!(
            "{} items from vehicle {:?} in {:.2} s ({} retries)",
            d.items.len(),
            v.system_id,
            d.seconds,
            d.retries
        );
        for i in &d.items {
            println!(
                "{:3} cmd {:5} frame {:2} params {:?} x {} y {} z {}",
                i.seq, i.command, i.frame, i.params, i.x, i.y, i.z
            );
        }
    }
    Ok(())
}

async fn cmd_start(args: StartArgs, config: &Config) -> Result<()> {
    let cancel = CancellationToken::new();
    let (link, _v) = connect(&args.link, config, &cancel).await?;
    if args.arm {
        link.arm(true).await?;
    }
    link.set_mode(FlightMode::Mission).await?;
    link.start_mission().await?;
    cancel.cancel();
    if args.link.json {
        println!(
            "{}",
            json!({ "result": "started", "armed_by_us": args.arm })
        );
    } else {
        println!("mission started{}", if args.arm { " (armed)" } else { "" });
    }
    Ok(())
}
