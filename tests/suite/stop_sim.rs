//! The operator's stop against the simulator (in-process, both autopilot
//! flavours): a mission flying to a waypoint 80 m away is stopped half way
//! with [`LinkHandle::hold`]; the vehicle acknowledges, reports its hold
//! mode, and stays where it was stopped. The simulator runs without GPS
//! bias (checked), so LOCAL_POSITION_NED is its true position.

use crate::link_support::{self, home_of, wait_for};

use std::time::Duration;

use shotpilot::mission::plan::{self, Flavour, Target};
use shotpilot::mission::upload;
use shotpilot::vehicle::{self, FlightMode, LinkHandle, Params};
use shotpilot_sim::app::{self, SimConfig};
use shotpilot_sim::autopilot::Flavour as SimFlavour;
use shotpilot_sim::link::Endpoint;
use tokio_util::sync::CancellationToken;

/// One flight at a time (world generation and flight compete for CPU).
static ONE_FLIGHT: tokio::sync::Mutex<()> = tokio::sync::Mutex::const_new(());

/// The vehicle's local NED position and its autopilot time, ms.
fn local(link: &LinkHandle) -> Option<([f64; 3], u32)> {
    (*link.telemetry.local_position.borrow())
        .map(|p| (p.value.pos_ned_m.map(f64::from), p.value.time_boot_ms))
}

fn horizontal(a: [f64; 3], b: [f64; 3]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// The simulator in-process (no video, no sensor noise, no GPS bias) and
/// a link to it, the vehicle heard; cancel the token to end both.
struct Flight {
    link: LinkHandle,
    home: plan::Home,
    cancel: CancellationToken,
    _dir: tempfile::TempDir,
}

async fn sim_and_link(flavour: Flavour) -> anyhow::Result<Flight> {
    let dir = tempfile::tempdir()?;
    let cancel = CancellationToken::new();
    let (socket, addr) = link_support::bound_udp();
    let mut cfg = SimConfig::default().with_flavour(match flavour {
        Flavour::Px4 => SimFlavour::Px4,
        Flavour::ArduPilot => SimFlavour::ArduPilot,
    });
    anyhow::ensure!(
        !cfg.autopilot.vehicle.gps_bias.enabled(),
        "the reported position is the truth only without GPS bias"
    );
    cfg.mavlink = Endpoint::UdpIn(addr.to_string());
    cfg.video_listen = None;
    cfg.capture_dir = dir.path().join("captures");
    cfg.sensor_noise = false;
    let sockets = app::Sockets {
        mavlink: Some(socket),
        ..Default::default()
    };
    tokio::spawn(app::run_on(cfg, cancel.child_token(), sockets));
    let (link, _task) = vehicle::spawn(
        Params {
            url: format!("udpout:{addr}"),
            ..Params::default()
        },
        upload::Params::default(),
        cancel.clone(),
    )?;
    link.wait_for_vehicle(Duration::from_secs(60)).await?;
    let home = home_of(&link).await?;
    Ok(Flight {
        link,
        home,
        cancel,
        _dir: dir,
    })
}

/// Plans, uploads and starts the mission to `target` (arming first).
async fn fly_to(
    link: &LinkHandle,
    target: &Target,
    home: &plan::Home,
    flavour: Flavour,
) -> anyhow::Result<()> {
    let items = plan::plan(target, home, flavour, &plan::Params::default())?;
    link.upload_mission(items).await?;
    link.arm(true).await?;
    link.set_mode(FlightMode::Mission).await?;
    link.start_mission().await?;
    Ok(())
}

async fn stop_holds(flavour: Flavour) -> anyhow::Result<()> {
    let _one = ONE_FLIGHT.lock().await;
    let Flight {
        link,
        home,
        cancel,
        _dir,
    } = sim_and_link(flavour).await?;
    let target = Target {
        lat_deg: home.lat_deg + 80.0 / 111_195.0,
        lon_deg: home.lon_deg,
        alt_m: 10.0,
        yaw_deg: 0.0,
        gimbal_pitch_deg: -30.0,
        photo: false,
    };
    fly_to(&link, &target, &home, flavour).await?;
    // Half way, at speed.
    let mut lp = link.telemetry.local_position.clone();
    wait_for("the vehicle 30 m out, at speed", &mut lp, 120, |p| {
        p.is_some_and(|p| {
            let [n, e, _] = p.value.pos_ned_m;
            let [vn, ve, _] = p.value.vel_ned_m_s;
            n.hypot(e) > 30.0 && vn.hypot(ve) > 1.5
        })
    })
    .await?;
    let (before, _) = local(&link).ok_or_else(|| anyhow::anyhow!("no position"))?;
    let ack = link.hold().await?;
    let (stopped, t0) = local(&link).ok_or_else(|| anyhow::anyhow!("no position"))?;
    let want = match flavour {
        Flavour::Px4 => "AUTO.LOITER",
        Flavour::ArduPilot => "LOITER",
    };
    anyhow::ensure!(
        ack.mode == want && ack.result == "MAV_RESULT_ACCEPTED",
        "{ack:?}"
    );
    let mut state = link.telemetry.vehicle.clone();
    wait_for("the hold mode in the heartbeat", &mut state, 5, |v| {
        v.mode == want
    })
    .await?;
    // Ten seconds of the autopilot's clock, every position on the way.
    let mut track = Vec::new();
    let end = t0.saturating_add(10_000);
    tokio::time::timeout(Duration::from_secs(60), async {
        loop {
            lp.changed().await?;
            if let Some((p, t)) = local(&link) {
                track.push((t, p));
                if t >= end {
                    return anyhow::Ok(());
                }
            }
        }
    })
    .await
    .map_err(|_| anyhow::anyhow!("no 10 s of positions within 60 s"))??;
    let (_, last) = *track.last().ok_or_else(|| anyhow::anyhow!("no track"))?;
    let furthest = track
        .iter()
        .map(|(_, p)| horizontal(*p, stopped))
        .fold(0.0, f64::max);
    // The last 5 s: still.
    let settled: Vec<[f64; 3]> = track
        .iter()
        .filter(|(t, _)| *t >= t0 + 5_000)
        .map(|(_, p)| *p)
        .collect();
    let drift = settled
        .iter()
        .map(|p| horizontal(*p, last))
        .fold(0.0, f64::max);
    let off = horizontal(last, stopped);
    let dz = (last[2] - stopped[2]).abs();
    eprintln!(
        "{flavour:?}: stopped {:.1} m out (moved {:.2} m during the command), after 10 s {off:.2} m from there \
         (furthest {furthest:.2} m), drift over the last 5 s {drift:.3} m, height change {dz:.2} m",
        stopped[0].hypot(stopped[1]),
        horizontal(before, stopped),
    );
    anyhow::ensure!(
        off < 1.0,
        "{flavour:?}: {off:.2} m from where it was stopped"
    );
    anyhow::ensure!(
        drift < 0.2,
        "{flavour:?}: drifted {drift:.3} m while holding"
    );
    anyhow::ensure!(dz < 0.5, "{flavour:?}: height changed {dz:.2} m");
    cancel.cancel();
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stop_holds_px4() -> anyhow::Result<()> {
    stop_holds(Flavour::Px4).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stop_holds_ardupilot() -> anyhow::Result<()> {
    stop_holds(Flavour::ArduPilot).await
}

/// Guided control against the simulator: the setpoint stream
/// ([`LinkHandle::guide`]) flies the vehicle there once the mode is
/// switched (PX4 refuses OFFBOARD until the stream has run a second, so
/// the switch is retried), and the operator's stop ends it: the vehicle
/// holds, and PX4 refuses OFFBOARD again because the stream stopped.
async fn guided_flies_the_stream_and_the_stop_ends_it(flavour: Flavour) -> anyhow::Result<()> {
    let _one = ONE_FLIGHT.lock().await;
    let Flight {
        link,
        home,
        cancel,
        _dir,
    } = sim_and_link(flavour).await?;
    // Up to a waypoint 15 m north at 10 m, by mission.
    let deg_per_m = 1.0 / 111_195.0;
    let target = Target {
        lat_deg: home.lat_deg + 15.0 * deg_per_m,
        lon_deg: home.lon_deg,
        alt_m: 10.0,
        yaw_deg: 0.0,
        gimbal_pitch_deg: -30.0,
        photo: false,
    };
    fly_to(&link, &target, &home, flavour).await?;
    let mut lp = link.telemetry.local_position.clone();
    wait_for("the vehicle at the waypoint", &mut lp, 120, |p| {
        p.is_some_and(|p| {
            let [n, e, d] = p.value.pos_ned_m;
            (n - 15.0).hypot(e) < 1.0 && (d + 10.0).abs() < 1.0
        })
    })
    .await?;
    // The stream to 8 m east of it, 2 m higher, facing east.
    let east = 8.0 / (111_195.0 * home.lat_deg.to_radians().cos());
    let sp = vehicle::GuidedSetpoint {
        lat_deg: home.lat_deg + 15.0 * deg_per_m,
        lon_deg: home.lon_deg + east,
        alt_amsl_m: home.alt_amsl_m + 12.0,
        yaw_deg: 90.0,
    };
    link.guide(Some(sp)).await?;
    // Retried at each position report until accepted (30 s at most).
    let tries = std::time::Instant::now();
    while let Err(e) = link.set_mode(FlightMode::Guided).await {
        eprintln!("{flavour:?}: guided refused for now: {e}");
        anyhow::ensure!(
            tries.elapsed() < Duration::from_secs(30),
            "{flavour:?}: guided control never accepted"
        );
        lp.changed().await?;
    }
    wait_for("the vehicle at the setpoint", &mut lp, 60, |p| {
        p.is_some_and(|p| {
            let [n, e, d] = p.value.pos_ned_m;
            (n - 15.0).hypot(e - 8.0) < 0.3 && (d + 12.0).abs() < 0.3
        })
    })
    .await?;
    let ack = link.hold().await?;
    anyhow::ensure!(ack.result == "MAV_RESULT_ACCEPTED", "{ack:?}");
    let want = match flavour {
        Flavour::Px4 => "AUTO.LOITER",
        Flavour::ArduPilot => "LOITER",
    };
    let mut state = link.telemetry.vehicle.clone();
    wait_for("the hold mode in the heartbeat", &mut state, 5, |v| {
        v.mode == want
    })
    .await?;
    if flavour == Flavour::Px4 {
        // The stop ended the stream: two seconds on the autopilot's
        // clock later, OFFBOARD is refused.
        let (_, t0) = local(&link).ok_or_else(|| anyhow::anyhow!("no position"))?;
        tokio::time::timeout(Duration::from_secs(60), async {
            loop {
                lp.changed().await?;
                if local(&link).is_some_and(|(_, t)| t >= t0.saturating_add(2_000)) {
                    return anyhow::Ok(());
                }
            }
        })
        .await
        .map_err(|_| anyhow::anyhow!("no 2 s of positions within 60 s"))??;
        let again = link.set_mode(FlightMode::Guided).await;
        anyhow::ensure!(again.is_err(), "OFFBOARD accepted after the stop");
    }
    let (p, _) = local(&link).ok_or_else(|| anyhow::anyhow!("no position"))?;
    anyhow::ensure!(
        horizontal(p, [15.0, 8.0, 0.0]) < 0.5,
        "{flavour:?}: {p:?} after the stop"
    );
    cancel.cancel();
    Ok(())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn guided_flies_the_stream_and_the_stop_ends_it_px4() -> anyhow::Result<()> {
    guided_flies_the_stream_and_the_stop_ends_it(Flavour::Px4).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn guided_flies_the_stream_and_the_stop_ends_it_ardupilot() -> anyhow::Result<()> {
    guided_flies_the_stream_and_the_stop_ends_it(Flavour::ArduPilot).await
}
