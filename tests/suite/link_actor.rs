//! The link actor against the in-test fake autopilot over real UDP/TCP
//! sockets. The tests run in tokio's paused time: the actor's timers
//! (heartbeats, link loss, rate requests, retries) advance with the
//! runtime's clock, so nothing waits in real time and every duration below
//! is the protocol's own.

use crate::link_support;

use std::time::Duration;

use link_support::{FakeConfig, HOME, Habit, linked, start_fake};
use mavlink::MavlinkVersion;
use mavlink::dialects::common::MavCmd;
use shotpilot::mission::{Flavour, upload};
use shotpilot::vehicle::{self, FlightMode, LinkError, Params};
use tokio_util::sync::CancellationToken;

fn params(url: String) -> Params {
    Params {
        url,
        link_lost_after_ms: 1500,
        reconnect_min_ms: 50,
        reconnect_max_ms: 400,
        ..Params::default()
    }
}

#[tokio::test(start_paused = true)]
async fn tracks_vehicle_and_caches_telemetry() -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    let (addr, fake) = start_fake(FakeConfig::clean(Habit::Px4), &cancel);
    let (link, task) = vehicle::spawn(
        params(format!("udpout:{addr}")),
        upload::Params::default(),
        cancel.clone(),
    )?;
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.system_id, Some(1));
    assert_eq!(v.flavour, Some(Flavour::Px4));
    assert_eq!(v.mode, "AUTO.LOITER");
    assert!(!v.armed);
    assert!(v.connected);
    let mut gp = link.telemetry.global_position.clone();
    let pos = tokio::time::timeout(Duration::from_secs(3), gp.wait_for(|p| p.is_some()))
        .await??
        .expect("some");
    assert!((pos.value.lat_deg - HOME.0).abs() < 1e-6);
    assert!((pos.value.rel_alt_m - 10.0).abs() < 1e-9);
    assert_eq!(pos.value.vel_ned_m_s, [1.0, -0.5, 0.0]);
    assert_eq!(pos.value.heading_deg, Some(90.0));
    // stamped when it came, on the actor's clock: at most one telemetry
    // period (100 ms) ago
    let age = tokio::time::Instant::now()
        .into_std()
        .saturating_duration_since(pos.received);
    assert!(age <= Duration::from_millis(100), "{age:?}");
    let mut att = link.telemetry.attitude.clone();
    let a = tokio::time::timeout(Duration::from_secs(3), att.wait_for(|p| p.is_some()))
        .await??
        .expect("some");
    assert_eq!(a.value.yaw_rad, 1.5);
    let mut gimbal = link.telemetry.gimbal.clone();
    let g = tokio::time::timeout(Duration::from_secs(3), gimbal.wait_for(|p| p.is_some()))
        .await??
        .expect("some");
    assert!((g.value.pitch_deg + 30.0).abs() < 1e-3, "{:?}", g.value);
    assert!(g.value.roll_deg.abs() < 1e-3 && g.value.yaw_deg.abs() < 1e-3);
    assert!(!g.value.yaw_absolute);
    let mut home = link.telemetry.home.clone();
    let h = tokio::time::timeout(Duration::from_secs(3), home.wait_for(|p| p.is_some()))
        .await??
        .expect("some");
    assert!((h.value.alt_amsl_m - HOME.2).abs() < 1e-3);
    // heartbeats at 1 Hz reach the vehicle: three in three seconds;
    // telemetry rates were requested once
    let hb0 = fake.lock().expect("lock").gcs_heartbeats;
    tokio::time::sleep(Duration::from_millis(3000)).await;
    let (hb1, cmds) = {
        let s = fake.lock().expect("lock");
        (s.gcs_heartbeats, s.commands.clone())
    };
    assert_eq!(hb1 - hb0, 3, "heartbeats in 3 s");
    // the six streams were asked for once when the vehicle appeared ...
    let ids: Vec<f32> = cmds.iter().take(6).map(|(_, id)| *id).collect();
    assert_eq!(ids, [33.0, 32.0, 30.0, 242.0, 285.0, 42.0], "{cmds:?}");
    // ... and only LOCAL_POSITION_NED, which this vehicle never sends, is
    // asked for again (5 s later); nothing else (no arming, no mode change)
    // is ever sent on the link's own initiative
    tokio::time::sleep(Duration::from_millis(3000)).await;
    let cmds = fake.lock().expect("lock").commands.clone();
    assert!(
        cmds.iter()
            .all(|(c, _)| *c == MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL),
        "{cmds:?}"
    );
    assert!(cmds.len() >= 7, "{cmds:?}");
    assert!(cmds[6..].iter().all(|(_, id)| *id == 32.0), "{cmds:?}");
    cancel.cancel();
    tokio::time::timeout(Duration::from_secs(2), task).await??;
    Ok(())
}

#[tokio::test(start_paused = true)]
async fn link_lost_after_silence_and_regained() -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    let fake_cancel = CancellationToken::new();
    // The port stays ours for the second vehicle: each fake gets a
    // duplicate of one socket bound here.
    let socket = std::net::UdpSocket::bind("127.0.0.1:0")?;
    let addr = socket.local_addr()?;
    let state = std::sync::Arc::new(std::sync::Mutex::new(link_support::FakeState::default()));
    tokio::spawn(link_support::run_fake_on(
        socket.try_clone()?,
        FakeConfig::clean(Habit::ArduPilot),
        state,
        fake_cancel.child_token(),
    ));
    let (link, _task) = vehicle::spawn(
        params(format!("udpout:{addr}")),
        upload::Params::default(),
        cancel.clone(),
    )?;
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.flavour, Some(Flavour::ArduPilot));
    assert_eq!(v.mode, "LOITER");
    fake_cancel.cancel();
    let mut rx = link.telemetry.vehicle.clone();
    let lost = tokio::time::timeout(Duration::from_secs(4), rx.wait_for(|v| v.link_lost))
        .await??
        .clone();
    // declared lost link_lost_after_ms (1.5 s) after the last heartbeat
    // heard, on the actor's clock, and not before
    let now = tokio::time::Instant::now().into_std();
    let last = lost.last_heartbeat.expect("heartbeats were heard");
    let silence = now.saturating_duration_since(last);
    assert!(
        silence >= Duration::from_millis(1500) && silence <= Duration::from_millis(1510),
        "lost after {silence:?} of silence"
    );
    assert_eq!(
        link.arm(true).await,
        Err(LinkError::NoVehicle),
        "no commands to a lost vehicle"
    );
    // a new vehicle process on the same port: the link comes back
    let cfg = FakeConfig::clean(Habit::ArduPilot);
    let state = std::sync::Arc::new(std::sync::Mutex::new(link_support::FakeState::default()));
    tokio::spawn(link_support::run_fake_on(
        socket,
        cfg,
        state,
        cancel.child_token(),
    ));
    link.wait_for_vehicle(Duration::from_secs(4)).await?;
    cancel.cancel();
    Ok(())
}

/// A guided setpoint stream running when the link is lost: the actor keeps
/// its period (it used to leave the stream's due time in the past and wake
/// at once, again and again, starving its commands: the stream's own stop
/// never came through and, on paused time, the clock stood still; the
/// daemon's lost-link servo test hung on it); the stop is served and
/// commands are refused for want of a vehicle, all within the protocol's
/// own times.
#[tokio::test(start_paused = true)]
async fn a_guided_stream_over_a_lost_link_keeps_the_actor_responsive() -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    let fake_cancel = CancellationToken::new();
    let (addr, _) = start_fake(FakeConfig::clean(Habit::ArduPilot), &fake_cancel);
    let (link, _task) = linked(params(format!("udpout:{addr}")), &cancel).await?;
    link.guide(Some(vehicle::GuidedSetpoint {
        lat_deg: HOME.0,
        lon_deg: HOME.1,
        alt_amsl_m: HOME.2 + 10.0,
        yaw_deg: 0.0,
    }))
    .await?;
    fake_cancel.cancel();
    let mut rx = link.telemetry.vehicle.clone();
    tokio::time::timeout(Duration::from_secs(4), rx.wait_for(|v| v.link_lost)).await??;
    // Time passes for the actor as for everyone (a spinning actor holds
    // a paused clock still).
    tokio::time::timeout(
        Duration::from_secs(2),
        tokio::time::sleep(Duration::from_secs(1)),
    )
    .await?;
    tokio::time::timeout(Duration::from_millis(100), link.guide(None)).await??;
    assert_eq!(
        tokio::time::timeout(Duration::from_millis(100), link.arm(true)).await?,
        Err(LinkError::NoVehicle)
    );
    cancel.cancel();
    Ok(())
}

#[tokio::test(start_paused = true)]
async fn accepts_mavlink1_vehicle() -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    let cfg = FakeConfig {
        version: MavlinkVersion::V1,
        ..FakeConfig::clean(Habit::ArduPilot)
    };
    let (addr, _fake) = start_fake(cfg, &cancel);
    let (link, _task) = vehicle::spawn(
        params(format!("udpout:{addr}")),
        upload::Params::default(),
        cancel.clone(),
    )?;
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.flavour, Some(Flavour::ArduPilot));
    let mut gp = link.telemetry.global_position.clone();
    tokio::time::timeout(Duration::from_secs(3), gp.wait_for(|p| p.is_some())).await??;
    cancel.cancel();
    Ok(())
}

#[tokio::test(start_paused = true)]
async fn mission_upload_over_mavlink1_both_ways() -> anyhow::Result<()> {
    use shotpilot::mission::plan::{self, Home, Target};
    let cancel = CancellationToken::new();
    let cfg = FakeConfig {
        version: MavlinkVersion::V1,
        ..FakeConfig::clean(Habit::ArduPilot)
    };
    let (addr, fake) = start_fake(cfg, &cancel);
    let p = Params {
        mavlink1: true,
        ..params(format!("udpout:{addr}"))
    };
    let (link, _task) = vehicle::spawn(p, upload::Params::default(), cancel.clone())?;
    link.wait_for_vehicle(Duration::from_secs(5)).await?;
    let home = Home {
        lat_deg: HOME.0,
        lon_deg: HOME.1,
        alt_amsl_m: HOME.2,
    };
    let t = Target {
        lat_deg: HOME.0 + 0.0002,
        lon_deg: HOME.1,
        alt_m: 12.0,
        yaw_deg: 90.0,
        gimbal_pitch_deg: -45.0,
        photo: true,
    };
    let items = plan::plan(&t, &home, Flavour::ArduPilot, &plan::Params::default())?;
    link.upload_mission(items.clone()).await?;
    let d = link.download_mission().await?;
    assert!(upload::same_mission(&items, &d.items, true));
    assert_eq!(fake.lock().expect("lock").uploads, 1);
    cancel.cancel();
    Ok(())
}

#[tokio::test(start_paused = true)]
async fn operator_commands_are_acknowledged() -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    let (addr, fake) = start_fake(FakeConfig::clean(Habit::Px4), &cancel);
    let (link, _task) = linked(params(format!("udpout:{addr}")), &cancel).await?;
    link.arm(true).await?;
    link.set_mode(FlightMode::Mission).await?;
    link.start_mission().await?;
    let cmds = fake.lock().expect("lock").commands.clone();
    let ops: Vec<_> = cmds
        .iter()
        .filter(|(c, _)| *c != MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL)
        .cloned()
        .collect();
    assert_eq!(
        ops,
        [
            (MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0),
            (MavCmd::MAV_CMD_DO_SET_MODE, 1.0),
            (MavCmd::MAV_CMD_MISSION_START, 0.0)
        ]
    );
    cancel.cancel();
    Ok(())
}

/// `udpin:127.0.0.1:0`: the link binds a port the kernel picks and tells
/// it (no port is guessed); a vehicle sending there is heard, and the
/// link's answers reach it (a mission upload completes both ways).
#[tokio::test(start_paused = true)]
async fn udpin_on_port_zero_reports_the_bound_port() -> anyhow::Result<()> {
    use shotpilot::mission::plan::{self, Home, Target};
    let cancel = CancellationToken::new();
    let (link, _task) = vehicle::spawn(
        params("udpin:127.0.0.1:0".into()),
        upload::Params::default(),
        cancel.clone(),
    )?;
    let bound = link.bound_addr(Duration::from_secs(5)).await?;
    assert_eq!(bound.ip(), std::net::Ipv4Addr::LOCALHOST);
    assert_ne!(bound.port(), 0);
    let state = std::sync::Arc::new(std::sync::Mutex::new(link_support::FakeState::default()));
    tokio::spawn(link_support::run_fake(
        format!("udpout:{bound}"),
        FakeConfig::clean(Habit::Px4),
        state.clone(),
        cancel.child_token(),
    ));
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.flavour, Some(Flavour::Px4));
    let home = Home {
        lat_deg: HOME.0,
        lon_deg: HOME.1,
        alt_amsl_m: HOME.2,
    };
    let t = Target {
        lat_deg: HOME.0 + 0.0002,
        lon_deg: HOME.1,
        alt_m: 12.0,
        yaw_deg: 90.0,
        gimbal_pitch_deg: -45.0,
        photo: true,
    };
    let items = plan::plan(&t, &home, Flavour::Px4, &plan::Params::default())?;
    link.upload_mission(items.clone()).await?;
    let (uploads, received) = {
        let s = state.lock().expect("lock");
        (s.uploads, s.received.len())
    };
    assert_eq!((uploads, received), (1, items.len()));
    cancel.cancel();
    Ok(())
}

/// `spawn_with_socket`: the link listens on a socket the caller bound,
/// reports that socket's address at once, and keeps it when the vehicle
/// restarts from another port (the reply address is learnt again).
#[tokio::test(start_paused = true)]
async fn listens_on_a_socket_the_caller_bound() -> anyhow::Result<()> {
    let cancel = CancellationToken::new();
    let socket = std::net::UdpSocket::bind("127.0.0.1:0")?;
    let addr = socket.local_addr()?;
    // The URL's address is never bound: the socket's is used.
    let (link, _task) = vehicle::spawn_with_socket(
        params("udpin:127.0.0.1:9".into()),
        upload::Params::default(),
        cancel.clone(),
        socket,
    )?;
    assert_eq!(link.bound_addr(Duration::ZERO).await?, addr);
    let fake_cancel = cancel.child_token();
    let state = std::sync::Arc::new(std::sync::Mutex::new(link_support::FakeState::default()));
    tokio::spawn(link_support::run_fake(
        format!("udpout:{addr}"),
        FakeConfig::clean(Habit::ArduPilot),
        state,
        fake_cancel.clone(),
    ));
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.flavour, Some(Flavour::ArduPilot));
    fake_cancel.cancel();
    let mut rx = link.telemetry.vehicle.clone();
    tokio::time::timeout(Duration::from_secs(4), rx.wait_for(|v| v.link_lost)).await??;
    // The next vehicle sends from a new port: heard, and answered there
    // (its upload completes).
    let state = std::sync::Arc::new(std::sync::Mutex::new(link_support::FakeState::default()));
    tokio::spawn(link_support::run_fake(
        format!("udpout:{addr}"),
        FakeConfig::clean(Habit::Px4),
        state.clone(),
        cancel.child_token(),
    ));
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.flavour, Some(Flavour::Px4));
    assert_eq!(link.bound_addr(Duration::ZERO).await?, addr);
    let n = link.download_mission().await?.items.len();
    assert_eq!(n, 0, "the new vehicle holds no mission");
    cancel.cancel();
    Ok(())
}

#[tokio::test(start_paused = true)]
async fn reconnects_when_tcp_peer_goes_away() -> anyhow::Result<()> {
    use mavlink::dialects::common::*;
    use mavlink::{AsyncConnectable, AsyncMavConnection, ConnectionAddress, MavHeader, TcpConfig};
    // The vehicle's port, bound here but not yet listening: connecting is
    // refused until the server below listens.
    let socket = tokio::net::TcpSocket::new_v4()?;
    socket.bind("127.0.0.1:0".parse()?)?;
    let addr = socket.local_addr()?;
    let cancel = CancellationToken::new();
    // a vehicle that accepts, sends two heartbeats and hangs up, twice
    let server = tokio::spawn(async move {
        let listener = socket.listen(4)?;
        for _ in 0..2 {
            let (stream, _) = listener.accept().await?;
            let conn = ConnectionAddress::Tcp(TcpConfig::from_stream(stream.into_std()?)?)
                .connect_async::<MavMessage>()
                .await?;
            let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                custom_mode: 0,
                mavtype: MavType::MAV_TYPE_QUADROTOR,
                autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
                base_mode: MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED,
                system_status: MavState::MAV_STATE_ACTIVE,
                mavlink_version: 3,
            });
            let h = MavHeader {
                system_id: 7,
                component_id: 1,
                sequence: 0,
            };
            for _ in 0..2 {
                conn.send(&h, &hb).await?;
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
        anyhow::Ok(())
    });
    // the link starts before the server listens: first attempts fail, backoff retries
    let (link, _task) = vehicle::spawn(
        params(format!("tcpout:{addr}")),
        upload::Params::default(),
        cancel.clone(),
    )?;
    let v = link.wait_for_vehicle(Duration::from_secs(5)).await?;
    assert_eq!(v.system_id, Some(7));
    assert!(v.armed);
    let mut rx = link.telemetry.vehicle.clone();
    let v = tokio::time::timeout(Duration::from_secs(5), rx.wait_for(|v| v.connections >= 2))
        .await??
        .clone();
    assert!(v.connections >= 2);
    server.await??;
    cancel.cancel();
    Ok(())
}

/// The operator's stop: DO_SET_MODE to each flavour's hold mode (PX4
/// AUTO.LOITER = custom main 4 / sub 3, ArduPilot LOITER = 5), answered
/// only once the vehicle's COMMAND_ACK came, with what was acknowledged.
#[tokio::test(start_paused = true)]
async fn stop_is_a_hold_acknowledged_by_the_vehicle() -> anyhow::Result<()> {
    for (habit, mode, want) in [
        (Habit::Px4, "AUTO.LOITER", [1.0, 4.0, 3.0]),
        (Habit::ArduPilot, "LOITER", [1.0, 5.0, 0.0]),
    ] {
        let cancel = CancellationToken::new();
        let (addr, fake) = start_fake(FakeConfig::clean(habit), &cancel);
        let (link, _task) = linked(params(format!("udpout:{addr}")), &cancel).await?;
        let ack = link.hold().await?;
        assert_eq!(ack.command, "MAV_CMD_DO_SET_MODE");
        assert_eq!(ack.mode, mode, "{habit:?}");
        assert_eq!(ack.result, "MAV_RESULT_ACCEPTED");
        let sent: Vec<[f32; 7]> = fake
            .lock()
            .expect("lock")
            .command_params
            .iter()
            .filter(|(c, _)| *c == MavCmd::MAV_CMD_DO_SET_MODE)
            .map(|(_, p)| *p)
            .collect();
        assert_eq!(sent.len(), 1, "{habit:?}: {sent:?}");
        assert_eq!(sent[0][..3], want, "{habit:?}");
        cancel.cancel();
    }
    Ok(())
}

/// A stop is never held up by another command in flight: with a gimbal
/// command the vehicle never answers, the stop's DO_SET_MODE goes out at
/// once (before the gimbal command's first retry), comes back with the
/// vehicle's ACK, and the gimbal command runs out its own retries.
#[tokio::test(start_paused = true)]
async fn stop_goes_out_while_another_command_waits() -> anyhow::Result<()> {
    static SILENT: [(MavCmd, Option<mavlink::dialects::common::MavResult>); 1] =
        [(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW, None)];
    let cancel = CancellationToken::new();
    let cfg = FakeConfig {
        command_results: &SILENT,
        ..FakeConfig::clean(Habit::Px4)
    };
    let (addr, fake) = start_fake(cfg, &cancel);
    let (link, _task) = linked(params(format!("udpout:{addr}")), &cancel).await?;
    let gimbal = {
        let link = link.clone();
        tokio::spawn(async move {
            link.command_long(
                MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
                [-30.0, 0.0, f32::NAN, f32::NAN, 0.0, 0.0, 0.0],
                None,
            )
            .await
        })
    };
    let seen = |c: MavCmd| {
        fake.lock()
            .map(|s| s.commands.iter().filter(|(k, _)| *k == c).count())
            .unwrap_or(0)
    };
    let mut waited = 0;
    while seen(MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW) == 0 {
        anyhow::ensure!(waited < 100, "the gimbal command never reached the vehicle");
        tokio::time::sleep(Duration::from_millis(5)).await;
        waited += 1;
    }
    let ack = link.hold().await?;
    assert_eq!(ack.command, "MAV_CMD_DO_SET_MODE");
    assert_eq!(ack.mode, "AUTO.LOITER");
    assert_eq!(ack.result, "MAV_RESULT_ACCEPTED");
    let r = gimbal.await?;
    let Err(LinkError::CommandTimeout { command, attempts }) = r else {
        panic!("the unanswered gimbal command times out by itself: {r:?}");
    };
    assert_eq!(command, 1000);
    assert!(attempts >= 2, "{attempts}");
    let order: Vec<MavCmd> = fake
        .lock()
        .expect("lock")
        .commands
        .iter()
        .map(|(c, _)| *c)
        .filter(|c| {
            matches!(
                c,
                MavCmd::MAV_CMD_DO_SET_MODE | MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW
            )
        })
        .collect();
    assert_eq!(
        order
            .iter()
            .filter(|c| **c == MavCmd::MAV_CMD_DO_SET_MODE)
            .count(),
        1,
        "{order:?}"
    );
    assert_eq!(
        order[..2],
        [
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            MavCmd::MAV_CMD_DO_SET_MODE
        ],
        "the stop went out before the gimbal command's first retry: {order:?}"
    );
    cancel.cancel();
    Ok(())
}

/// A stop the vehicle refuses, or never acknowledges, is an error naming
/// the command and the result (never a silent success).
#[tokio::test(start_paused = true)]
async fn stop_refused_or_unacknowledged_is_an_error() -> anyhow::Result<()> {
    use mavlink::dialects::common::MavResult;
    static DENIED: [(MavCmd, Option<MavResult>); 1] = [(
        MavCmd::MAV_CMD_DO_SET_MODE,
        Some(MavResult::MAV_RESULT_DENIED),
    )];
    static SILENT: [(MavCmd, Option<MavResult>); 1] = [(MavCmd::MAV_CMD_DO_SET_MODE, None)];
    for (results, denied) in [(&DENIED[..], true), (&SILENT[..], false)] {
        let cancel = CancellationToken::new();
        let cfg = FakeConfig {
            command_results: results,
            ..FakeConfig::clean(Habit::Px4)
        };
        let (addr, fake) = start_fake(cfg, &cancel);
        let (link, _task) = linked(params(format!("udpout:{addr}")), &cancel).await?;
        let err = link.hold().await.expect_err("no hold without an ACCEPTED");
        let sends = fake
            .lock()
            .expect("lock")
            .commands
            .iter()
            .filter(|(c, _)| *c == MavCmd::MAV_CMD_DO_SET_MODE)
            .count();
        if denied {
            assert_eq!(
                err,
                LinkError::CommandRejected {
                    command: 176,
                    result: "MAV_RESULT_DENIED".into()
                }
            );
            assert_eq!(sends, 1);
        } else {
            let LinkError::CommandTimeout { command, attempts } = err else {
                panic!("expected a timeout, got {err:?}");
            };
            assert_eq!(command, 176);
            assert_eq!(sends as u32, attempts);
            assert!(attempts >= 2, "retried: {attempts}");
        }
        cancel.cancel();
    }
    Ok(())
}
