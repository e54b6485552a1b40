//! The simulator started in-process through the library entry
//! (`shotpilot_sim::app::run`), driven over a real UDP socket by a minimal
//! ground station written with the crate's own frame parser: heartbeat and
//! position arrive, a mission uploads (PX4 rules: legacy request first,
//! then MISSION_REQUEST_INT), the vehicle arms, flies it, and a capture is
//! written and announced.

#![allow(deprecated)] // the legacy MISSION_REQUEST is part of what is tested

use std::time::Duration;

use mavlink::MavHeader;
use mavlink::dialects::common::{
    COMMAND_LONG_DATA, HEARTBEAT_DATA, MISSION_COUNT_DATA, MISSION_ITEM_INT_DATA, MavAutopilot,
    MavCmd, MavFrame, MavMessage, MavMissionResult, MavMissionType, MavResult, MavType,
    MissionState,
};
use shotpilot_sim::app::{SimConfig, Sockets, run_on};
use shotpilot_sim::geodesy::LocalFrame;
use shotpilot_sim::link::{Endpoint, FrameParser, decode_frame, encode_v2};
use tokio::net::UdpSocket;
use tokio_util::sync::CancellationToken;

struct Gcs {
    sock: UdpSocket,
    seq: u8,
    parser: FrameParser,
    buf: Vec<u8>,
}

impl Gcs {
    async fn send(&mut self, msg: MavMessage) {
        let h = MavHeader {
            system_id: 255,
            component_id: 190,
            sequence: self.seq,
        };
        self.seq = self.seq.wrapping_add(1);
        self.sock.send(&encode_v2(h, &msg)).await.expect("send");
    }
    async fn recv_until(
        &mut self,
        secs: f64,
        mut f: impl FnMut(&MavMessage) -> bool,
    ) -> Option<MavMessage> {
        let end = tokio::time::Instant::now() + Duration::from_secs_f64(secs);
        loop {
            while let Some(fr) = self.parser.next_frame_complete() {
                if let Ok((_, m, _)) = decode_frame(&fr)
                    && f(&m)
                {
                    return Some(m);
                }
            }
            match tokio::time::timeout_at(end, self.sock.recv(&mut self.buf)).await {
                Err(_) => return None,
                Ok(Ok(n)) => self.parser.push(&self.buf[..n]),
                // Connection refused (ICMP) while the sim is still starting.
                Ok(Err(_)) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    }
}

fn item(
    seq: u16,
    command: MavCmd,
    frame: MavFrame,
    p: [f32; 4],
    x: i32,
    y: i32,
    z: f32,
) -> MavMessage {
    MavMessage::MISSION_ITEM_INT(MISSION_ITEM_INT_DATA {
        param1: p[0],
        param2: p[1],
        param3: p[2],
        param4: p[3],
        x,
        y,
        z,
        seq,
        command,
        target_system: 1,
        target_component: 1,
        frame,
        current: 0,
        autocontinue: 1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
    })
}

fn command(cmd: MavCmd, p1: f32) -> MavMessage {
    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: p1,
        command: cmd,
        target_system: 1,
        target_component: 1,
        ..Default::default()
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn in_process_sim_flies_an_uploaded_mission_and_captures() {
    // The simulator's socket, bound here (port 0) and handed over: the
    // port is known and stays taken.
    let socket = std::net::UdpSocket::bind("127.0.0.1:0").expect("bind");
    let addr = socket.local_addr().expect("addr");
    let dir = tempfile::tempdir().expect("tempdir");
    let config = SimConfig {
        mavlink: Endpoint::UdpIn(addr.to_string()),
        video_listen: None,
        capture_dir: dir.path().join("captures"),
        ..SimConfig::default()
    };
    let home = config.autopilot.vehicle.home;
    let cancel = CancellationToken::new();
    let sockets = Sockets {
        mavlink: Some(socket),
        ..Default::default()
    };
    let sim = tokio::spawn(run_on(config, cancel.clone(), sockets));

    let sock = UdpSocket::bind("127.0.0.1:0").await.expect("bind");
    sock.connect(addr).await.expect("connect");
    let mut g = Gcs {
        sock,
        seq: 0,
        parser: FrameParser::new(),
        buf: vec![0; 65536],
    };
    // udpin: the sim answers whoever spoke last, so speak first (world
    // generation takes a few seconds: keep saying hello).
    let hb = MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        mavtype: MavType::MAV_TYPE_GCS,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        ..Default::default()
    });
    let mut got_hb = None;
    for _ in 0..60 {
        g.send(hb.clone()).await;
        got_hb = g
            .recv_until(1.0, |m| matches!(m, MavMessage::HEARTBEAT(h) if h.autopilot == MavAutopilot::MAV_AUTOPILOT_PX4))
            .await;
        if got_hb.is_some() {
            break;
        }
    }
    let Some(MavMessage::HEARTBEAT(h)) = got_hb else {
        panic!("no heartbeat")
    };
    assert_eq!(h.mavtype, MavType::MAV_TYPE_QUADROTOR);
    let pos = g
        .recv_until(2.0, |m| matches!(m, MavMessage::GLOBAL_POSITION_INT(_)))
        .await;
    let Some(MavMessage::GLOBAL_POSITION_INT(p)) = pos else {
        panic!("no position")
    };
    assert_eq!(p.lat, (home.lat_deg * 1e7).round() as i32);

    // Takeoff to 6 m, a waypoint 12 m north, look down, capture.
    let f = LocalFrame::new(home);
    let wp = f.ned_to_geodetic(&nalgebra::Vector3::new(12.0, 0.0, 0.0));
    let (lat, lon) = (
        (wp.lat_deg * 1e7).round() as i32,
        (wp.lon_deg * 1e7).round() as i32,
    );
    let rel = MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT;
    let items = [
        item(0, MavCmd::MAV_CMD_NAV_TAKEOFF, rel, [0.0; 4], 0, 0, 6.0),
        item(
            1,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            rel,
            [0.0, 1.0, 0.0, f32::NAN],
            lat,
            lon,
            6.0,
        ),
        // Gimbal protocol v2 as PX4 runs it: the mission makes the autopilot
        // the gimbal's primary controller (-2) before pointing it.
        item(
            2,
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
            MavFrame::MAV_FRAME_MISSION,
            [-2.0, -2.0, -1.0, -1.0],
            0,
            0,
            0.0,
        ),
        item(
            3,
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            MavFrame::MAV_FRAME_MISSION,
            [-90.0, 0.0, f32::NAN, f32::NAN],
            0,
            0,
            0.0,
        ),
        item(
            4,
            MavCmd::MAV_CMD_IMAGE_START_CAPTURE,
            MavFrame::MAV_FRAME_MISSION,
            [0.0, 0.0, 1.0, 0.0],
            0,
            0,
            0.0,
        ),
    ];
    g.send(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: items.len() as u16,
        target_system: 1,
        target_component: 1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        opaque_id: 0,
    }))
    .await;
    let mut kinds = Vec::new();
    let ack = loop {
        let m = g
            .recv_until(3.0, |m| {
                matches!(
                    m,
                    MavMessage::MISSION_REQUEST(_)
                        | MavMessage::MISSION_REQUEST_INT(_)
                        | MavMessage::MISSION_ACK(_)
                )
            })
            .await
            .expect("request or ack");
        let seq = match &m {
            MavMessage::MISSION_REQUEST(r) => {
                kinds.push(("legacy", r.seq));
                r.seq
            }
            MavMessage::MISSION_REQUEST_INT(r) => {
                kinds.push(("int", r.seq));
                r.seq
            }
            MavMessage::MISSION_ACK(a) => break a.mavtype,
            _ => unreachable!(),
        };
        g.send(items[usize::from(seq)].clone()).await;
    };
    assert_eq!(ack, MavMissionResult::MAV_MISSION_ACCEPTED);
    assert_eq!(
        kinds,
        vec![
            ("legacy", 0),
            ("int", 1),
            ("int", 2),
            ("int", 3),
            ("int", 4)
        ]
    );

    for (cmd, p1) in [
        (MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0),
        (MavCmd::MAV_CMD_MISSION_START, 0.0),
    ] {
        g.send(command(cmd, p1)).await;
        let a = g
            .recv_until(
                2.0,
                |m| matches!(m, MavMessage::COMMAND_ACK(a) if a.command == cmd),
            )
            .await;
        assert!(
            matches!(a, Some(MavMessage::COMMAND_ACK(ref a)) if a.result == MavResult::MAV_RESULT_ACCEPTED),
            "{cmd:?}: {a:?}"
        );
    }
    let mut captured = None;
    let mut complete = false;
    let mut last_local = None;
    let mut texts = Vec::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    while tokio::time::Instant::now() < deadline && !(complete && captured.is_some()) {
        let Some(m) = g.recv_until(1.0, |_| true).await else {
            continue;
        };
        match m {
            MavMessage::CAMERA_IMAGE_CAPTURED(c) => captured = Some(c),
            MavMessage::MISSION_CURRENT(c)
                if c.mission_state == MissionState::MISSION_STATE_COMPLETE =>
            {
                complete = true
            }
            MavMessage::LOCAL_POSITION_NED(l) => last_local = Some(l),
            MavMessage::STATUSTEXT(t) => texts.push(t.text.to_str().unwrap_or("").to_string()),
            _ => {}
        }
    }
    let c = captured.expect("CAMERA_IMAGE_CAPTURED");
    let url = c.file_url.to_str().unwrap_or("").to_string();
    let path = url.strip_prefix("file://").unwrap_or(&url).to_string();
    let meta = std::fs::metadata(&path).expect("capture file exists");
    assert!(meta.len() > 10_000, "{} bytes", meta.len());
    assert!((c.relative_alt - 6000).abs() < 900, "{}", c.relative_alt);
    assert!(complete);
    assert!(
        !texts.iter().any(|t| t.contains("denied")),
        "the mission's gimbal item was refused: {texts:?}"
    );
    let l = last_local.expect("local position");
    assert!(
        (l.x - 12.0).abs() < 1.2 && l.y.abs() < 1.0 && (l.z + 6.0).abs() < 0.8,
        "{l:?}"
    );
    cancel.cancel();
    let summary = sim.await.expect("join").expect("run");
    assert_eq!(summary.captures, 1);
}
