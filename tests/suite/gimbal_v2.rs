//! Gimbal protocol v2 against the simulator (in-process, both autopilot
//! flavours), through a UDP relay that records every MAVLink frame each way:
//!
//! - a planned mission (`DO_GIMBAL_MANAGER_PITCHYAW`) flown through the link
//!   handle: the daemon reads GIMBAL_MANAGER_STATUS, sends
//!   DO_GIMBAL_MANAGER_CONFIGURE before the mission starts, the gimbal ends
//!   at the planned pitch (within 1 deg), and control is given back;
//! - a direct gimbal command: configure first, then PITCHYAW;
//! - the simulator denies a PITCHYAW from a ground station not in control,
//!   so a missing configure fails these tests.

use crate::link_support::{self, home_of, wait_for};

use std::sync::{Arc, Mutex};
use std::time::Duration;

use mavlink::dialects::common::{MavCmd, MavMessage, MavResult};
use shotpilot::mission::plan::{self, Flavour, Target};
use shotpilot::mission::upload;
use shotpilot::vehicle::{self, FlightMode, LinkError, LinkHandle, Params};
use shotpilot_sim::app::{self, SimConfig};
use shotpilot_sim::autopilot::Flavour as SimFlavour;
use shotpilot_sim::link::Endpoint;
use tokio::net::UdpSocket;
use tokio_util::sync::CancellationToken;

/// One recorded frame: sent by the ground station (`up`) or the vehicle.
#[derive(Debug, Clone)]
struct Frame {
    up: bool,
    msg: MavMessage,
}

type Trace = Arc<Mutex<Vec<Frame>>>;

fn decode(data: &[u8]) -> Vec<MavMessage> {
    let mut r = mavlink::MavlinkReader::new(data);
    let mut out = Vec::new();
    while let Ok((_, m)) = r.read_any_message::<MavMessage>() {
        out.push(m);
    }
    out
}

/// A relay between the link (which talks to the returned address) and the
/// simulator at `vehicle`, recording both directions.
async fn start_relay(
    vehicle: String,
    cancel: &CancellationToken,
) -> anyhow::Result<(String, Trace)> {
    let gcs_side = Arc::new(UdpSocket::bind("127.0.0.1:0").await?);
    let veh_side = Arc::new(UdpSocket::bind("127.0.0.1:0").await?);
    veh_side.connect(&vehicle).await?;
    let addr = gcs_side.local_addr()?.to_string();
    let trace: Trace = Arc::new(Mutex::new(Vec::new()));
    let peer: Arc<Mutex<Option<std::net::SocketAddr>>> = Arc::new(Mutex::new(None));
    {
        let (g, v, t, p, c) = (
            gcs_side.clone(),
            veh_side.clone(),
            trace.clone(),
            peer.clone(),
            cancel.clone(),
        );
        tokio::spawn(async move {
            let mut buf = vec![0u8; 65536];
            loop {
                let r = tokio::select! {
                    _ = c.cancelled() => return,
                    r = g.recv_from(&mut buf) => r,
                };
                let Ok((n, src)) = r else { continue };
                p.lock().map(|mut p| *p = Some(src)).ok();
                if let Ok(mut t) = t.lock() {
                    t.extend(
                        decode(&buf[..n])
                            .into_iter()
                            .map(|msg| Frame { up: true, msg }),
                    );
                }
                let _ = v.send(&buf[..n]).await;
            }
        });
    }
    {
        let (g, v, t, p, c) = (gcs_side, veh_side, trace.clone(), peer, cancel.clone());
        tokio::spawn(async move {
            let mut buf = vec![0u8; 65536];
            loop {
                let r = tokio::select! {
                    _ = c.cancelled() => return,
                    r = v.recv(&mut buf) => r,
                };
                let Ok(n) = r else { continue };
                if let Ok(mut t) = t.lock() {
                    t.extend(
                        decode(&buf[..n])
                            .into_iter()
                            .map(|msg| Frame { up: false, msg }),
                    );
                }
                let to = p.lock().ok().and_then(|p| *p);
                if let Some(to) = to {
                    let _ = g.send_to(&buf[..n], to).await;
                }
            }
        });
    }
    Ok((addr, trace))
}

fn snapshot(trace: &Trace) -> Vec<Frame> {
    trace.lock().map(|t| t.clone()).unwrap_or_default()
}

/// Index of the first frame matching `f` at or after `from`.
fn find(frames: &[Frame], from: usize, f: impl Fn(&Frame) -> bool) -> Option<usize> {
    frames.iter().skip(from).position(f).map(|i| i + from)
}

fn is_command(fr: &Frame, cmd: MavCmd) -> bool {
    fr.up && matches!(&fr.msg, MavMessage::COMMAND_LONG(c) if c.command == cmd)
}

fn is_take(fr: &Frame) -> bool {
    fr.up
        && matches!(&fr.msg, MavMessage::COMMAND_LONG(c)
            if c.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE
                && c.param1 == 255.0 && c.param2 == 191.0)
}

fn is_release(fr: &Frame) -> bool {
    fr.up
        && matches!(&fr.msg, MavMessage::COMMAND_LONG(c)
            if c.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE
                && c.param1 == -3.0 && c.param2 == -3.0)
}

async fn gimbal_pitch_reaches(link: &LinkHandle, pitch: f64, seconds: u64) -> anyhow::Result<f64> {
    let mut rx = link.telemetry.gimbal.clone();
    wait_for("the gimbal pitch", &mut rx, seconds, |g| {
        g.is_some_and(|g| (f64::from(g.value.pitch_deg) - pitch).abs() < 1.0)
    })
    .await?;
    let g = (*rx.borrow()).map(|g| f64::from(g.value.pitch_deg));
    g.ok_or_else(|| anyhow::anyhow!("no gimbal attitude"))
}

/// One flight at a time: each test runs a simulator whose world generation
/// takes seconds of CPU. The flights run on simulated time (a paused
/// runtime: the simulator's steps, the link's timers and the test's
/// timeouts on one clock), so a busy machine makes them slower, never
/// different; one at a time keeps them from slowing each other.
static ONE_FLIGHT: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

async fn fly(flavour: Flavour) -> anyhow::Result<()> {
    let _one = ONE_FLIGHT.lock().await;
    let dir = tempfile::tempdir()?;
    let cancel = CancellationToken::new();
    let (socket, addr) = link_support::bound_udp();
    let mut cfg = SimConfig::default().with_flavour(match flavour {
        Flavour::Px4 => SimFlavour::Px4,
        Flavour::ArduPilot => SimFlavour::ArduPilot,
    });
    cfg.mavlink = Endpoint::UdpIn(addr.to_string());
    cfg.video_listen = None;
    cfg.capture_dir = dir.path().join("captures");
    cfg.sensor_noise = false;
    let sockets = app::Sockets {
        mavlink: Some(socket),
        ..Default::default()
    };
    let sim = tokio::spawn(app::run_on(cfg, cancel.child_token(), sockets));
    let (relay, trace) = start_relay(addr.to_string(), &cancel).await?;
    let (link, _task) = vehicle::spawn(
        Params {
            url: format!("udpout:{relay}"),
            ..Params::default()
        },
        upload::Params::default(),
        cancel.clone(),
    )?;
    // The simulator builds its world first: seconds, more on a loaded machine.
    let v = link.wait_for_vehicle(Duration::from_secs(60)).await?;
    anyhow::ensure!(v.flavour == Some(flavour), "sim says {:?}", v.flavour);
    let home = home_of(&link).await?;
    let target = Target {
        lat_deg: home.lat_deg + 12.0 / 111_195.0,
        lon_deg: home.lon_deg,
        alt_m: 8.0,
        yaw_deg: 0.0,
        gimbal_pitch_deg: -37.0,
        photo: false,
    };
    let items = plan::plan(&target, &home, flavour, &plan::Params::default())?;
    anyhow::ensure!(plan::points_gimbal_v2(&items));
    link.upload_mission(items).await?;
    anyhow::ensure!(link.telemetry.gimbal_control.borrow().mission_points_gimbal);

    // Operator: arm, mission mode, start (as `shotpilot mission start --arm`).
    link.arm(true).await?;
    link.set_mode(FlightMode::Mission).await?;
    if flavour == Flavour::Px4 {
        // On PX4 the mode change starts the armed vehicle's mission, whose
        // first item makes the autopilot the gimbal's primary controller.
        // Start only once the link has heard that, the order in which a
        // ground station that takes control again for `start` gets the
        // mission's own PITCHYAW denied (seen in CI as a flake).
        let autopilot = (v.system_id.unwrap_or(1), v.component_id);
        let mut manager = link.telemetry.gimbal_manager.clone();
        wait_for("the mission's configure item", &mut manager, 20, |m| {
            m.is_some_and(|m| m.value.primary == autopilot)
        })
        .await?;
    }
    link.start_mission().await?;
    let pitch = match gimbal_pitch_reaches(&link, target.gimbal_pitch_deg, 60).await {
        Ok(p) => p,
        Err(e) => {
            // What the vehicle said, to tell a refused gimbal item from a
            // mission that never ran (a preflight disarm, say).
            let said: Vec<String> = snapshot(&trace)
                .iter()
                .filter_map(|f| match &f.msg {
                    MavMessage::STATUSTEXT(t) if !f.up => {
                        Some(t.text.to_str().unwrap_or("(not UTF-8)").to_owned())
                    }
                    _ => None,
                })
                .collect();
            // The commands each way, in order, to tell which CONFIGURE put
            // whom in control when a mission PITCHYAW is denied.
            let commands: Vec<String> = snapshot(&trace)
                .iter()
                .filter_map(|f| match &f.msg {
                    MavMessage::COMMAND_LONG(c) if f.up => Some(format!(
                        "up {:?} p1 {} p2 {} p7 {} conf {}",
                        c.command, c.param1, c.param2, c.param7, c.confirmation
                    )),
                    MavMessage::COMMAND_ACK(a) if !f.up => {
                        Some(format!("down ACK {:?} {:?}", a.command, a.result))
                    }
                    MavMessage::MISSION_CURRENT(m) if !f.up => {
                        Some(format!("down MISSION_CURRENT {}", m.seq))
                    }
                    _ => None,
                })
                .fold(Vec::new(), |mut v: Vec<String>, line| {
                    // MISSION_CURRENT repeats at its rate: keep changes only.
                    if v.last() != Some(&line) {
                        v.push(line);
                    }
                    v
                });
            anyhow::bail!(
                "{flavour:?}: {e}; vehicle {:?}; gimbal control {:?}; mission progress {:?}; STATUSTEXT {said:?}; commands {commands:?}",
                *link.telemetry.vehicle.borrow(),
                *link.telemetry.gimbal_control.borrow(),
                *link.telemetry.progress.borrow(),
            );
        }
    };
    let mut progress = link.telemetry.progress.clone();
    wait_for("the mission to complete", &mut progress, 90, |p| {
        p.is_some_and(|p| p.value.state == Some(5))
    })
    .await?;
    // Control is given back: by us (ArduPilot) or by the PX4 mission's own
    // release item after it took control itself; either way we hold none.
    let mut control = link.telemetry.gimbal_control.clone();
    wait_for("gimbal control released", &mut control, 10, |g| !g.held).await?;
    let mut manager = link.telemetry.gimbal_manager.clone();
    wait_for("nobody in gimbal control", &mut manager, 10, |m| {
        m.is_some_and(|m| m.value.primary == (0, 0))
    })
    .await?;
    let final_pitch = (*link.telemetry.gimbal.borrow())
        .map(|g| f64::from(g.value.pitch_deg))
        .ok_or_else(|| anyhow::anyhow!("no gimbal attitude"))?;
    anyhow::ensure!(
        (final_pitch - target.gimbal_pitch_deg).abs() < 1.0,
        "{flavour:?}: gimbal at {final_pitch:.2} deg after the mission, planned {}",
        target.gimbal_pitch_deg
    );

    let frames = snapshot(&trace);
    let status_read = find(&frames, 0, |f| {
        !f.up && matches!(f.msg, MavMessage::GIMBAL_MANAGER_STATUS(_))
    })
    .ok_or_else(|| anyhow::anyhow!("no GIMBAL_MANAGER_STATUS heard"))?;
    let take = find(&frames, 0, is_take)
        .ok_or_else(|| anyhow::anyhow!("{flavour:?}: no DO_GIMBAL_MANAGER_CONFIGURE sent"))?;
    let mode = find(&frames, 0, |f| is_command(f, MavCmd::MAV_CMD_DO_SET_MODE))
        .ok_or_else(|| anyhow::anyhow!("no DO_SET_MODE"))?;
    let start = find(&frames, 0, |f| is_command(f, MavCmd::MAV_CMD_MISSION_START))
        .ok_or_else(|| anyhow::anyhow!("no MISSION_START"))?;
    anyhow::ensure!(
        status_read < take && take < mode && take < start,
        "{flavour:?}: status at frame {status_read}, configure {take}, mode {mode}, start {start}"
    );
    let acked = find(&frames, take, |f| {
        !f.up
            && matches!(&f.msg, MavMessage::COMMAND_ACK(a)
                if a.command == MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE
                    && a.result == MavResult::MAV_RESULT_ACCEPTED)
    });
    anyhow::ensure!(
        acked.is_some_and(|a| a < mode),
        "configure not accepted before the mode change"
    );
    let configures = frames
        .iter()
        .filter(|f| is_command(f, MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE))
        .count();
    // Control is taken once for the mission: never again while it runs (on
    // PX4 that would take it from the mission's own configure item).
    let takes = frames[..start].iter().filter(|f| is_take(f)).count();
    anyhow::ensure!(
        takes == 1,
        "{flavour:?}: {takes} CONFIGURE (255/191) before MISSION_START, expected 1"
    );
    if flavour == Flavour::ArduPilot {
        let release = find(&frames, start, is_release).ok_or_else(|| {
            anyhow::anyhow!("ArduPilot: control not given back after the mission")
        })?;
        anyhow::ensure!(release > start);
    }
    println!(
        "{flavour:?} mission: GIMBAL_MANAGER_STATUS at frame {status_read}, CONFIGURE (255/191) at {take}, \
         DO_SET_MODE at {mode}, MISSION_START at {start}; {configures} configure commands in all; \
         gimbal reached {pitch:.2} deg, {final_pitch:.2} deg after the mission (planned {:.1})",
        target.gimbal_pitch_deg
    );

    // A PITCHYAW from us without control is denied by the simulator ...
    let denied = link
        .command_long(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            [-10.0, 0.0, f32::NAN, f32::NAN, 44.0, 0.0, 0.0],
            None,
        )
        .await;
    anyhow::ensure!(
        matches!(&denied, Err(LinkError::CommandRejected { result, .. }) if result.contains("DENIED")),
        "{flavour:?}: unconfigured PITCHYAW answered {denied:?}"
    );
    // ... and the handle's direct gimbal command configures first.
    let before = snapshot(&trace).len();
    link.point_gimbal(-12.0, 0.0).await?;
    let pitch = gimbal_pitch_reaches(&link, -12.0, 20).await?;
    let frames = snapshot(&trace);
    let take = find(&frames, before, is_take).ok_or_else(|| anyhow::anyhow!("no configure"))?;
    let point = find(&frames, before, |f| {
        is_command(f, MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW)
    })
    .ok_or_else(|| anyhow::anyhow!("no PITCHYAW"))?;
    anyhow::ensure!(take < point, "configure at {take}, PITCHYAW at {point}");
    anyhow::ensure!(link.release_gimbal().await?, "release: we held no control");
    wait_for("nobody in gimbal control", &mut manager, 10, |m| {
        m.is_some_and(|m| m.value.primary == (0, 0))
    })
    .await?;
    println!(
        "{flavour:?} direct command: CONFIGURE before PITCHYAW, gimbal at {pitch:.2} deg (asked -12)"
    );
    cancel.cancel();
    let _ = sim.await?;
    Ok(())
}

#[tokio::test(start_paused = true)]
async fn px4_gimbal_configure_before_mission_and_command() -> anyhow::Result<()> {
    fly(Flavour::Px4).await
}

#[tokio::test(start_paused = true)]
async fn ardupilot_gimbal_configure_before_mission_and_command() -> anyhow::Result<()> {
    fly(Flavour::ArduPilot).await
}
