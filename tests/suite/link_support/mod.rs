//! An in-test fake autopilot for the link and mission tests.
//!
//! It speaks the vehicle side of the mission protocol the way PX4 or
//! ArduPilot do (PX4: MISSION_REQUEST_INT, a repeated last item gets a new
//! ACK; ArduPilot: legacy MISSION_REQUEST, INVALID_SEQUENCE for unexpected
//! items, item 0 replaced by home), sends heartbeats and telemetry, and
//! drops and duplicates frames in both directions with a seeded generator.
#![allow(dead_code)]
#![allow(deprecated)]

use std::sync::{Arc, Mutex};
use std::time::Duration;

use mavlink::dialects::common::*;
use mavlink::{
    AsyncConnectable, AsyncMavConnection, ConnectionAddress, MavHeader, MavlinkVersion, UdpConfig,
    UdpMode,
};
use rand::rngs::StdRng;
use rand::{Rng, SeedableRng};
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;

/// Which autopilot habits to mimic.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Habit {
    /// PX4.
    Px4,
    /// ArduPilot.
    ArduPilot,
}

/// How the fake behaves.
#[derive(Debug, Clone, Copy)]
pub struct FakeConfig {
    /// Habits.
    pub habit: Habit,
    /// System id.
    pub system_id: u8,
    /// Probability of dropping each received frame.
    pub drop_in: f64,
    /// Probability of dropping each sent frame.
    pub drop_out: f64,
    /// Probability of sending a frame twice.
    pub duplicate: f64,
    /// Seed.
    pub seed: u64,
    /// MAVLink version of what the fake sends.
    pub version: MavlinkVersion,
    /// Re-request timeout of the vehicle side.
    pub rerequest: Duration,
    /// Answer to send instead of ACCEPTED at the end of an upload (None: accept).
    pub final_result: Option<MavMissionResult>,
    /// Send heartbeats at all.
    pub heartbeats: bool,
    /// Drop the first final ACCEPTED of each upload.
    pub lose_final_ack: bool,
    /// MISSION_REQUEST_LISTs left unanswered first (a read-back the radio
    /// loses whole).
    pub ignore_request_lists: u32,
    /// Answers to particular commands instead of ACCEPTED (None: no
    /// COMMAND_ACK at all).
    pub command_results: &'static [(MavCmd, Option<MavResult>)],
}

impl FakeConfig {
    /// A clean link.
    pub fn clean(habit: Habit) -> Self {
        Self {
            habit,
            system_id: 1,
            drop_in: 0.0,
            drop_out: 0.0,
            duplicate: 0.0,
            seed: 1,
            version: MavlinkVersion::V2,
            // ArduPilot re-requests after 1 s (plus stream slowdown); PX4 sooner
            rerequest: Duration::from_millis(if habit == Habit::ArduPilot { 1000 } else { 300 }),
            final_result: None,
            heartbeats: true,
            lose_final_ack: false,
            ignore_request_lists: 0,
            command_results: &[],
        }
    }
}

/// What the fake saw, shared with the test.
#[derive(Debug, Default)]
pub struct FakeState {
    /// The stored mission, as received (before ArduPilot's home rewrite).
    pub received: Vec<MISSION_ITEM_INT_DATA>,
    /// Completed uploads.
    pub uploads: u32,
    /// Frames dropped (both directions).
    pub dropped: u32,
    /// Frames duplicated.
    pub duplicated: u32,
    /// GCS heartbeats heard.
    pub gcs_heartbeats: u32,
    /// Commands received (command numbers).
    pub commands: Vec<(MavCmd, f32)>,
    /// Commands received with all seven parameters.
    pub command_params: Vec<(MavCmd, [f32; 7])>,
    /// Mission transfer messages that carried a wrong mission_type or target.
    pub misaddressed: u32,
    /// Every frame that arrived (dropped by `drop_in` or not), by message id.
    pub heard: std::collections::HashMap<u32, u32>,
}

pub const HOME: (f64, f64, f64) = (47.397742, 8.545594, 488.0);

enum Rx {
    Idle,
    Receiving {
        count: u16,
        next: u16,
        items: Vec<MISSION_ITEM_INT_DATA>,
        last_rx: Instant,
        tries: u32,
    },
}

/// Runs the fake autopilot on a mavlink-crate address (`serial:PATH:BAUD`)
/// until `cancel`, or until its serial device vanishes.
pub async fn run_fake(
    url: String,
    cfg: FakeConfig,
    state: Arc<Mutex<FakeState>>,
    cancel: CancellationToken,
) {
    let address = match ConnectionAddress::parse_address(&url) {
        Ok(a) => a,
        Err(e) => panic!("fake autopilot: bad address {url}: {e}"),
    };
    run_fake_at(address, cfg, state, cancel).await
}

/// [`run_fake`] listening on a UDP socket the caller bound (replies go to
/// the last sender), so the caller knows its port before the fake runs.
pub async fn run_fake_on(
    socket: std::net::UdpSocket,
    cfg: FakeConfig,
    state: Arc<Mutex<FakeState>>,
    cancel: CancellationToken,
) {
    let address = match UdpConfig::from_socket(socket, UdpMode::Udpin) {
        Ok(c) => ConnectionAddress::Udp(c),
        Err(e) => panic!("fake autopilot: unusable socket: {e}"),
    };
    run_fake_at(address, cfg, state, cancel).await
}

async fn run_fake_at(
    address: ConnectionAddress,
    cfg: FakeConfig,
    state: Arc<Mutex<FakeState>>,
    cancel: CancellationToken,
) {
    let mut conn = match address.connect_async::<MavMessage>().await {
        Ok(c) => c,
        Err(e) => panic!("fake autopilot cannot open {address}: {e}"),
    };
    conn.set_protocol_version(cfg.version);
    conn.set_allow_recv_any_version(true);
    let conn = Arc::new(conn);
    let mut rng = StdRng::seed_from_u64(cfg.seed);
    let header = MavHeader {
        system_id: u32::from(cfg.system_id),
        component_id: 1,
        sequence: 0,
    };
    let mut mission: Vec<MISSION_ITEM_INT_DATA> = Vec::new();
    let mut rx = Rx::Idle;
    let mut request_lists_ignored = 0u32;
    let mut gcs: Option<(u8, u8)> = None;
    let mut hb = tokio::time::interval(Duration::from_millis(1000));
    let mut telem = tokio::time::interval(Duration::from_millis(100));
    let mut tick = tokio::time::interval(Duration::from_millis(50));
    let autopilot = match cfg.habit {
        Habit::Px4 => MavAutopilot::MAV_AUTOPILOT_PX4,
        Habit::ArduPilot => MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
    };
    let mut t_ms: u32 = 0;
    // mission execution: the current item while flying (None on the ground)
    let mut flying: Option<u16> = None;
    loop {
        let mut out: Vec<MavMessage> = Vec::new();
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = hb.tick() => {
                if cfg.heartbeats {
                    out.push(MavMessage::HEARTBEAT(HEARTBEAT_DATA {
                        custom_mode: if cfg.habit == Habit::Px4 { (4 << 16) | (3 << 24) } else { 5 },
                        mavtype: MavType::MAV_TYPE_QUADROTOR,
                        autopilot,
                        base_mode: MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED,
                        system_status: MavState::MAV_STATE_STANDBY,
                        mavlink_version: 3,
                    }));
                }
            }
            _ = telem.tick() => {
                t_ms += 100;
                out.push(MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                    time_boot_ms: t_ms,
                    lat: (HOME.0 * 1e7) as i32,
                    lon: (HOME.1 * 1e7) as i32,
                    alt: (HOME.2 * 1e3) as i32 + 10_000,
                    relative_alt: 10_000,
                    vx: 100, vy: -50, vz: 0,
                    hdg: 9000,
                }));
                out.push(MavMessage::ATTITUDE(ATTITUDE_DATA {
                    time_boot_ms: t_ms, roll: 0.01, pitch: -0.02, yaw: 1.5,
                    rollspeed: 0.0, pitchspeed: 0.0, yawspeed: 0.0,
                }));
                // gimbal pitched 30 deg down: q = (cos(-15 deg), 0, sin(-15 deg), 0)
                let h = (-15f32).to_radians();
                out.push(MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(GIMBAL_DEVICE_ATTITUDE_STATUS_DATA {
                    time_boot_ms: t_ms,
                    q: [h.cos(), 0.0, h.sin(), 0.0],
                    flags: GimbalDeviceFlags::GIMBAL_DEVICE_FLAGS_YAW_IN_VEHICLE_FRAME,
                    ..Default::default()
                }));
                // flying a mission: one item every 200 ms
                if let Some(seq) = flying && t_ms.is_multiple_of(200) {
                    out.push(MavMessage::MISSION_ITEM_REACHED(MISSION_ITEM_REACHED_DATA { seq }));
                    flying = (usize::from(seq) + 1 < mission.len()).then_some(seq + 1);
                }
                if t_ms.is_multiple_of(500) {
                    out.push(MavMessage::MISSION_CURRENT(MISSION_CURRENT_DATA {
                        seq: flying.unwrap_or(0),
                        total: mission.len() as u16,
                        mission_state: if flying.is_some() { MissionState::MISSION_STATE_ACTIVE } else { MissionState::MISSION_STATE_NOT_STARTED },
                        ..Default::default()
                    }));
                }
                if t_ms.is_multiple_of(1000) {
                    out.push(MavMessage::HOME_POSITION(HOME_POSITION_DATA {
                        latitude: (HOME.0 * 1e7) as i32,
                        longitude: (HOME.1 * 1e7) as i32,
                        altitude: (HOME.2 * 1e3) as i32,
                        ..Default::default()
                    }));
                }
            }
            _ = tick.tick() => {
                // the vehicle side re-requests on its own timeout
                if let (Rx::Receiving { next, last_rx, tries, .. }, Some((gs, gc))) = (&mut rx, gcs)
                    && last_rx.elapsed() >= cfg.rerequest
                {
                    *tries += 1;
                    *last_rx = Instant::now();
                    if *tries > 20 {
                        out.push(ack(gs, gc, MavMissionResult::MAV_MISSION_ERROR));
                        rx = Rx::Idle;
                    } else {
                        out.push(request(cfg.habit, gs, gc, *next));
                    }
                }
            }
            r = conn.try_recv() => {
                let (h, msg) = match r {
                    Ok(x) => x,
                    Err(mavlink::error::MessageReadError::Io(_)) => return,
                    Err(_) => continue,
                };
                state
                    .lock()
                    .map(|mut s| *s.heard.entry(mavlink::Message::message_id(&msg)).or_default() += 1)
                    .ok();
                if rng.random_bool(cfg.drop_in) {
                    state.lock().map(|mut s| s.dropped += 1).ok();
                    continue;
                }
                let (gs, gc) = (h.system_id as u8, h.component_id);
                match msg {
                    MavMessage::HEARTBEAT(_) => {
                        gcs = Some((gs, gc));
                        state.lock().map(|mut s| s.gcs_heartbeats += 1).ok();
                    }
                    MavMessage::COMMAND_LONG(c) if c.target_system == cfg.system_id => {
                        state.lock().map(|mut s| {
                            s.commands.push((c.command, c.param1));
                            s.command_params.push((c.command, [c.param1, c.param2, c.param3, c.param4, c.param5, c.param6, c.param7]));
                        }).ok();
                        let scripted = cfg.command_results.iter().find(|(k, _)| *k == c.command).map(|(_, r)| *r);
                        if scripted == Some(None) {
                            continue;
                        }
                        if c.command == MavCmd::MAV_CMD_MISSION_START && !mission.is_empty() {
                            flying = Some(0);
                        }
                        // No gimbal manager here (an autopilot without a
                        // gimbal, or older firmware).
                        let gimbal_manager = matches!(
                            c.command,
                            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE
                                | MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW
                        );
                        out.push(MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
                            command: c.command,
                            result: if let Some(Some(r)) = scripted {
                                r
                            } else if gimbal_manager {
                                MavResult::MAV_RESULT_UNSUPPORTED
                            } else {
                                MavResult::MAV_RESULT_ACCEPTED
                            },
                            target_system: gs,
                            target_component: gc,
                            ..Default::default()
                        }));
                    }
                    MavMessage::MISSION_COUNT(c) => {
                        gcs = Some((gs, gc));
                        if c.target_system != cfg.system_id || c.mission_type != MavMissionType::MAV_MISSION_TYPE_MISSION {
                            state.lock().map(|mut s| s.misaddressed += 1).ok();
                            continue;
                        }
                        match &mut rx {
                            // ArduPilot restarts an upload on a new COUNT from the same GCS
                            Rx::Receiving { .. } if cfg.habit == Habit::ArduPilot => {
                                rx = Rx::Receiving { count: c.count, next: 0, items: Vec::new(), last_rx: Instant::now(), tries: 0 };
                                out.push(request(cfg.habit, gs, gc, 0));
                            }
                            Rx::Receiving { count, next, last_rx, .. } if *count == c.count && *next == 0 => {
                                // our first request was lost: ask again
                                *last_rx = Instant::now();
                                out.push(request(cfg.habit, gs, gc, 0));
                            }
                            Rx::Receiving { .. } => {}
                            Rx::Idle => {
                                if c.count == 0 {
                                    mission.clear();
                                    out.push(ack(gs, gc, MavMissionResult::MAV_MISSION_ACCEPTED));
                                } else {
                                    rx = Rx::Receiving { count: c.count, next: 0, items: Vec::new(), last_rx: Instant::now(), tries: 0 };
                                    out.push(request(cfg.habit, gs, gc, 0));
                                }
                            }
                        }
                    }
                    MavMessage::MISSION_ITEM_INT(item) => {
                        if item.target_system != cfg.system_id || item.mission_type != MavMissionType::MAV_MISSION_TYPE_MISSION {
                            state.lock().map(|mut s| s.misaddressed += 1).ok();
                            continue;
                        }
                        match &mut rx {
                            Rx::Receiving { count, next, items, last_rx, tries } => {
                                if item.seq == *next {
                                    items.push(item);
                                    *next += 1;
                                    *last_rx = Instant::now();
                                    *tries = 0;
                                    if *next == *count {
                                        let result = cfg.final_result.unwrap_or(MavMissionResult::MAV_MISSION_ACCEPTED);
                                        if !cfg.lose_final_ack {
                                            out.push(ack(gs, gc, result));
                                        }
                                        if result == MavMissionResult::MAV_MISSION_ACCEPTED {
                                            mission = std::mem::take(items);
                                            if let Ok(mut s) = state.lock() {
                                                s.received = mission.clone();
                                                s.uploads += 1;
                                            }
                                            if cfg.habit == Habit::ArduPilot && !mission.is_empty() {
                                                mission[0].x = (HOME.0 * 1e7) as i32;
                                                mission[0].y = (HOME.1 * 1e7) as i32;
                                                mission[0].z = HOME.2 as f32;
                                            }
                                        }
                                        rx = Rx::Idle;
                                    } else {
                                        out.push(request(cfg.habit, gs, gc, *next));
                                    }
                                } else if cfg.habit == Habit::ArduPilot {
                                    out.push(ack(gs, gc, MavMissionResult::MAV_MISSION_INVALID_SEQUENCE));
                                }
                            }
                            Rx::Idle => {
                                // a repeated last item after completion: PX4
                                // ACKs again, ArduPilot has dropped the transfer
                                if cfg.habit == Habit::Px4 && !mission.is_empty() && usize::from(item.seq) + 1 == mission.len() {
                                    out.push(ack(gs, gc, MavMissionResult::MAV_MISSION_ACCEPTED));
                                } else {
                                    // PX4 "no transfer in progress"; ArduPilot
                                    // answers every item outside an upload so
                                    out.push(ack(gs, gc, MavMissionResult::MAV_MISSION_ERROR));
                                }
                            }
                        }
                    }
                    // ArduPilot refuses downloads while an upload runs
                    MavMessage::MISSION_REQUEST_LIST(_) | MavMessage::MISSION_REQUEST_INT(_)
                        if cfg.habit == Habit::ArduPilot && matches!(rx, Rx::Receiving { .. }) =>
                    {
                        out.push(ack(gs, gc, MavMissionResult::MAV_MISSION_DENIED));
                    }
                    MavMessage::MISSION_REQUEST_LIST(l)
                        if l.target_system == cfg.system_id
                            && request_lists_ignored < cfg.ignore_request_lists =>
                    {
                        request_lists_ignored += 1;
                    }
                    MavMessage::MISSION_REQUEST_LIST(l) if l.target_system == cfg.system_id => {
                        out.push(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                            count: mission.len() as u16,
                            target_system: gs,
                            target_component: gc,
                            mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
                            opaque_id: 0,
                        }));
                    }
                    MavMessage::MISSION_REQUEST_INT(r) if r.target_system == cfg.system_id => {
                        if let Some(item) = mission.get(usize::from(r.seq)) {
                            let mut it = item.clone();
                            it.target_system = gs;
                            it.target_component = gc;
                            out.push(MavMessage::MISSION_ITEM_INT(it));
                        }
                    }
                    _ => {}
                }
            }
        }
        for m in out {
            if cfg.version == MavlinkVersion::V1 && mavlink::Message::message_id(&m) > 255 {
                continue; // no 16-bit message ids in MAVLink 1
            }
            if rng.random_bool(cfg.drop_out) {
                state.lock().map(|mut s| s.dropped += 1).ok();
                continue;
            }
            let _ = conn.send(&header, &m).await;
            if rng.random_bool(cfg.duplicate) {
                state.lock().map(|mut s| s.duplicated += 1).ok();
                let _ = conn.send(&header, &m).await;
            }
        }
    }
}

fn ack(gs: u8, gc: u8, result: MavMissionResult) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: gs,
        target_component: gc,
        mavtype: result,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        opaque_id: 0,
    })
}

fn request(habit: Habit, gs: u8, gc: u8, seq: u16) -> MavMessage {
    match habit {
        Habit::Px4 => MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system: gs,
            target_component: gc,
            mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        }),
        Habit::ArduPilot => MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
            seq,
            target_system: gs,
            target_component: gc,
            mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        }),
    }
}

/// A UDP socket bound on 127.0.0.1 port 0 and its address: the caller
/// keeps the socket (hands it to whatever listens), so the port is known
/// and no other process can take it.
pub fn bound_udp() -> (std::net::UdpSocket, std::net::SocketAddr) {
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind a UDP socket");
    let addr = socket.local_addr().expect("its address");
    (socket, addr)
}

/// Starts a fake on a socket bound here on port 0; returns its address
/// and shared state.
pub fn start_fake(cfg: FakeConfig, cancel: &CancellationToken) -> (String, Arc<Mutex<FakeState>>) {
    let (socket, addr) = bound_udp();
    let addr = addr.to_string();
    let state = Arc::new(Mutex::new(FakeState::default()));
    tokio::spawn(run_fake_on(
        socket,
        cfg,
        state.clone(),
        cancel.child_token(),
    ));
    (addr, state)
}

/// A link to `params.url` (with the default transfer parameters), once
/// it has heard the vehicle (within 5 s); cancelled by `cancel`.
pub async fn linked(
    params: shotpilot::vehicle::Params,
    cancel: &CancellationToken,
) -> anyhow::Result<(shotpilot::vehicle::LinkHandle, tokio::task::JoinHandle<()>)> {
    let (link, task) = shotpilot::vehicle::spawn(
        params,
        shotpilot::mission::upload::Params::default(),
        cancel.clone(),
    )?;
    link.wait_for_vehicle(Duration::from_secs(5)).await?;
    Ok((link, task))
}

/// A bad radio between two UDP peers: drops datagrams, flips bits, and
/// serialises bytes at a baud rate (8N1: 10 bits a byte), each direction
/// with its own seeded generator.
#[derive(Debug, Clone, Copy)]
pub struct Radio {
    /// Probability of dropping a datagram.
    pub drop: f64,
    /// Probability of corrupting each byte (one random bit flipped).
    pub corrupt_per_byte: f64,
    /// Line rate, bits per second (0: unlimited).
    pub baud: u32,
    /// Seed.
    pub seed: u64,
}

/// Counters of a radio proxy.
#[derive(Debug, Default)]
pub struct RadioStats {
    /// Datagrams forwarded.
    pub forwarded: u64,
    /// Datagrams dropped.
    pub dropped: u64,
    /// Bytes corrupted.
    pub corrupted: u64,
    /// Bytes forwarded.
    pub bytes: u64,
}

/// Starts a radio proxy: the ground station talks to the returned address,
/// the proxy talks to `vehicle` (a UDP address).
pub async fn start_radio(
    vehicle: String,
    radio: Radio,
    cancel: &CancellationToken,
) -> (String, Arc<Mutex<RadioStats>>) {
    use tokio::net::UdpSocket;
    let gcs_side = Arc::new(UdpSocket::bind("127.0.0.1:0").await.expect("bind"));
    let veh_side = Arc::new(UdpSocket::bind("127.0.0.1:0").await.expect("bind"));
    veh_side.connect(&vehicle).await.expect("connect");
    let addr = gcs_side.local_addr().expect("addr").to_string();
    let stats = Arc::new(Mutex::new(RadioStats::default()));
    let gcs_peer: Arc<Mutex<Option<std::net::SocketAddr>>> = Arc::new(Mutex::new(None));

    #[allow(clippy::too_many_arguments)]
    async fn pump(
        from: Arc<tokio::net::UdpSocket>,
        to: Arc<tokio::net::UdpSocket>,
        up: bool,
        gcs_peer: Arc<Mutex<Option<std::net::SocketAddr>>>,
        radio: Radio,
        seed: u64,
        stats: Arc<Mutex<RadioStats>>,
        cancel: CancellationToken,
    ) {
        let mut rng = StdRng::seed_from_u64(seed);
        let mut buf = vec![0u8; 65536];
        let mut busy_until = Instant::now();
        loop {
            let r = tokio::select! {
                _ = cancel.cancelled() => return,
                r = from.recv_from(&mut buf) => r,
            };
            let Ok((n, src)) = r else { continue };
            if up {
                gcs_peer.lock().map(|mut p| *p = Some(src)).ok();
            }
            if rng.random_bool(radio.drop) {
                stats.lock().map(|mut s| s.dropped += 1).ok();
                continue;
            }
            let mut data = buf[..n].to_vec();
            let mut corrupted = 0;
            for b in data.iter_mut() {
                if rng.random_bool(radio.corrupt_per_byte) {
                    *b ^= 1 << rng.random_range(0..8);
                    corrupted += 1;
                }
            }
            if radio.baud > 0 {
                let air = Duration::from_secs_f64(n as f64 * 10.0 / f64::from(radio.baud));
                busy_until = busy_until.max(Instant::now()) + air;
                tokio::select! {
                    _ = cancel.cancelled() => return,
                    _ = tokio::time::sleep_until(busy_until) => {}
                }
            }
            let sent = if up {
                to.send(&data).await
            } else {
                let peer = gcs_peer.lock().ok().and_then(|p| *p);
                match peer {
                    Some(p) => to.send_to(&data, p).await,
                    None => continue,
                }
            };
            if sent.is_ok()
                && let Ok(mut s) = stats.lock()
            {
                s.forwarded += 1;
                s.corrupted += corrupted;
                s.bytes += n as u64;
            }
        }
    }

    tokio::spawn(pump(
        gcs_side.clone(),
        veh_side.clone(),
        true,
        gcs_peer.clone(),
        radio,
        radio.seed,
        stats.clone(),
        cancel.child_token(),
    ));
    tokio::spawn(pump(
        veh_side,
        gcs_side,
        false,
        gcs_peer,
        radio,
        radio.seed.wrapping_add(0x9e37_79b9),
        stats.clone(),
        cancel.child_token(),
    ));
    (addr, stats)
}

/// Waits up to `seconds` for `f` to hold on what `rx` watches; the error
/// names `what` it waited for.
pub async fn wait_for<T>(
    what: &str,
    rx: &mut tokio::sync::watch::Receiver<T>,
    seconds: u64,
    f: impl FnMut(&T) -> bool,
) -> anyhow::Result<()> {
    tokio::time::timeout(Duration::from_secs(seconds), rx.wait_for(f))
        .await
        .map_err(|_| anyhow::anyhow!("timed out after {seconds} s waiting for {what}"))??;
    Ok(())
}

/// The vehicle's home as its HOME_POSITION gives it (waits up to 30 s).
pub async fn home_of(
    link: &shotpilot::vehicle::LinkHandle,
) -> anyhow::Result<shotpilot::mission::plan::Home> {
    let mut home_rx = link.telemetry.home.clone();
    wait_for("HOME_POSITION", &mut home_rx, 30, Option::is_some).await?;
    let h = (*home_rx.borrow())
        .map(|s| s.value)
        .ok_or_else(|| anyhow::anyhow!("no home"))?;
    Ok(shotpilot::mission::plan::Home {
        lat_deg: h.lat_deg,
        lon_deg: h.lon_deg,
        alt_amsl_m: h.alt_amsl_m,
    })
}

/// The Python with the peers' packages (pymavlink, mavsdk):
/// `$SHOTPILOT_PYTHON`, else `/work/venv/bin/python` when it exists, else
/// `python3`.
pub fn python() -> String {
    std::env::var("SHOTPILOT_PYTHON").unwrap_or_else(|_| {
        if std::path::Path::new("/work/venv/bin/python").exists() {
            "/work/venv/bin/python".into()
        } else {
            "python3".into()
        }
    })
}
