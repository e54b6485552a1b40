use super::*;
use mavlink::dialects::common::{
    COMMAND_LONG_DATA, GIMBAL_MANAGER_STATUS_DATA, MISSION_COUNT_DATA, MISSION_ITEM_INT_DATA,
    MavAutopilot, MavBool, MavCmd, MavFrame, MavMissionResult, MavMissionType, MavModeFlag,
    MavResult, MavSeverity,
};
use nalgebra::UnitQuaternion;

const DT: f64 = 0.02;

fn gcs_header() -> MavHeader {
    MavHeader {
        system_id: 255,
        component_id: 190,
        sequence: 0,
    }
}

struct Sim {
    ap: Autopilot,
    t: f64,
}

impl Sim {
    fn new(flavour: Flavour) -> Self {
        Self {
            ap: Autopilot::new(
                AutopilotParams {
                    flavour,
                    ..AutopilotParams::default()
                },
                1.7e9,
            ),
            t: 0.0,
        }
    }
    fn send(&mut self, msg: MavMessage) -> Vec<MavMessage> {
        self.ap.handle(&gcs_header(), &msg)
    }
    fn run(&mut self, seconds: f64) -> Vec<(f64, MavMessage)> {
        let mut out = Vec::new();
        let n = (seconds / DT).round() as usize;
        for _ in 0..n {
            self.t += DT;
            for m in self.ap.step(self.t, DT) {
                out.push((self.t, m));
            }
        }
        out
    }
    fn command(&mut self, command: MavCmd, p: [f32; 7]) -> MavResult {
        let out = self.send(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: p[0],
            param2: p[1],
            param3: p[2],
            param4: p[3],
            param5: p[4],
            param6: p[5],
            param7: p[6],
            command,
            target_system: 1,
            target_component: 1,
            confirmation: 0,
        }));
        match out.last() {
            Some(MavMessage::COMMAND_ACK(a)) => {
                assert_eq!(a.command, command);
                a.result
            }
            other => panic!("no ack: {other:?}"),
        }
    }
    /// Arms and takes off with NAV_TAKEOFF (`alt`: AMSL on PX4, above
    /// home on ArduPilot), then flies `seconds`.
    fn take_off(&mut self, alt: f32, seconds: f64) {
        self.command(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        self.command(
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, alt],
        );
        self.run(seconds);
    }
    fn upload(&mut self, items: Vec<MISSION_ITEM_INT_DATA>) {
        let out = self.send(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: items.len() as u16,
            target_system: 1,
            target_component: 1,
            mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
            opaque_id: 0,
        }));
        assert!(!out.is_empty());
        let mut last = Vec::new();
        for it in items {
            last = self.send(MavMessage::MISSION_ITEM_INT(it));
        }
        assert!(matches!(
            last.last(),
            Some(MavMessage::MISSION_ACK(a)) if a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED
        ));
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
) -> MISSION_ITEM_INT_DATA {
    MISSION_ITEM_INT_DATA {
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
    }
}

/// Lat/lon (1e7 deg) of a NED offset from the default home.
fn latlon(north: f64, east: f64) -> (i32, i32) {
    let f = crate::geodesy::LocalFrame::new(VehicleParams::default().home);
    let g = f.ned_to_geodetic(&Vector3::new(north, east, 0.0));
    (
        (g.lat_deg * 1e7).round() as i32,
        (g.lon_deg * 1e7).round() as i32,
    )
}

const REL: MavFrame = MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT;

#[test]
fn heartbeat_encodes_px4_custom_modes() {
    let mut s = Sim::new(Flavour::Px4);
    let r = s.command(
        MavCmd::MAV_CMD_DO_SET_MODE,
        [1.0, 4.0, 4.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
    let Some(MavMessage::HEARTBEAT(hb)) = s.ap.build(0) else {
        panic!()
    };
    assert_eq!(hb.custom_mode, 4 << 16 | 4 << 24);
    assert_eq!(hb.autopilot, MavAutopilot::MAV_AUTOPILOT_PX4);
    assert_eq!(hb.mavtype, MavType::MAV_TYPE_QUADROTOR);
    assert!(
        hb.base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED)
    );
    assert!(
        !hb.base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED)
    );
    // Unknown main mode.
    let r = s.command(
        MavCmd::MAV_CMD_DO_SET_MODE,
        [1.0, 12.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(r, MavResult::MAV_RESULT_UNSUPPORTED);
    assert_eq!(s.ap.mode(), Mode::Mission);
}

#[test]
fn ardupilot_heartbeat_and_modes() {
    let mut s = Sim::new(Flavour::ArduPilot);
    let r = s.command(
        MavCmd::MAV_CMD_DO_SET_MODE,
        [1.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
    let Some(MavMessage::HEARTBEAT(hb)) = s.ap.build(0) else {
        panic!()
    };
    assert_eq!(hb.autopilot, MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
    assert_eq!(hb.custom_mode, 5);
    assert_eq!(s.ap.mode(), Mode::Hold);
}

#[test]
fn default_stream_rates_and_set_message_interval() {
    let mut s = Sim::new(Flavour::Px4);
    let count = |msgs: &[(f64, MavMessage)], id: u32| {
        msgs.iter().filter(|(_, m)| m.message_id() == id).count()
    };
    use mavlink::Message;
    let out = s.run(10.0);
    assert!(
        (9..=11).contains(&count(&out, 0)),
        "heartbeat {}",
        count(&out, 0)
    );
    assert!(
        (49..=51).contains(&count(&out, 33)),
        "gpi {}",
        count(&out, 33)
    );
    assert!((99..=101).contains(&count(&out, 30)));
    assert!((4..=6).contains(&count(&out, 242)));
    let r = s.command(
        MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        [33.0, 50_000.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
    let r = s.command(
        MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        [30.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
    let out = s.run(10.0);
    assert!(
        (199..=201).contains(&count(&out, 33)),
        "gpi {}",
        count(&out, 33)
    );
    assert_eq!(count(&out, 30), 0);
    // 0 restores the default.
    s.command(
        MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        [33.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    let out = s.run(10.0);
    assert!((49..=51).contains(&count(&out, 33)));
    let r = s.command(
        MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
        [9999.0, 1e5, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(r, MavResult::MAV_RESULT_UNSUPPORTED);
    // REQUEST_MESSAGE sends one at once.
    let out = s.send(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
        param1: 242.0,
        command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
        target_system: 1,
        target_component: 1,
        ..Default::default()
    }));
    assert!(matches!(out[0], MavMessage::HOME_POSITION(_)));
}

#[test]
fn flies_a_mission_with_takeoff_waypoints_gimbal_capture_and_rtl() {
    let mut s = Sim::new(Flavour::Px4);
    let (la, lo) = latlon(30.0, 10.0);
    let (lb, lob) = latlon(30.0, -15.0);
    s.upload(vec![
        item(
            0,
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            REL,
            [0.0, 0.0, 0.0, f32::NAN],
            0,
            0,
            12.0,
        ),
        item(
            1,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            REL,
            [2.0, 1.0, 0.0, 90.0],
            la,
            lo,
            15.0,
        ),
        item(
            2,
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            MavFrame::MAV_FRAME_MISSION,
            [-90.0, 0.0, f32::NAN, f32::NAN],
            0,
            0,
            0.0,
        ),
        item(
            3,
            MavCmd::MAV_CMD_IMAGE_START_CAPTURE,
            MavFrame::MAV_FRAME_MISSION,
            [0.0, 0.0, 1.0, 0.0],
            0,
            0,
            0.0,
        ),
        item(
            4,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            REL,
            [0.0, 0.0, 0.0, f32::NAN],
            lb,
            lob,
            15.0,
        ),
        item(
            5,
            MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH,
            MavFrame::MAV_FRAME_MISSION,
            [0.0; 4],
            0,
            0,
            0.0,
        ),
    ]);
    // The mission's gimbal item runs as the autopilot (1/1): give it control.
    assert_eq!(
        s.command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
            [1.0, 1.0, -1.0, -1.0, 0.0, 0.0, 0.0]
        ),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(
        s.command(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        ),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(
        s.command(MavCmd::MAV_CMD_MISSION_START, [0.0; 7]),
        MavResult::MAV_RESULT_ACCEPTED
    );
    let mut reached = Vec::new();
    let mut currents = Vec::new();
    let mut at_wp1 = None;
    let mut max_alt = 0.0f64;
    let mut captures = Vec::new();
    for _ in 0..(180.0 / DT) as usize {
        for (t, m) in s.run(DT) {
            match m {
                MavMessage::MISSION_ITEM_REACHED(r) => {
                    if r.seq == 1 {
                        at_wp1 = Some((t, s.ap.vehicle().p_ned(), s.ap.vehicle().yaw()));
                    }
                    reached.push(r.seq)
                }
                MavMessage::MISSION_CURRENT(c) if currents.last() != Some(&c.seq) => {
                    currents.push(c.seq)
                }
                _ => {}
            }
        }
        max_alt = max_alt.max(-s.ap.vehicle().p_ned().z);
        captures.extend(s.ap.take_capture_requests());
        if !s.ap.armed() && s.t > 10.0 {
            break;
        }
    }
    assert_eq!(reached, vec![0, 1, 2, 3, 4, 5]);
    assert_eq!(currents, vec![0, 1, 2, 3, 4, 5]);
    let (_, p1, yaw1) = at_wp1.expect("wp1");
    assert!(
        (p1 - Vector3::new(30.0, 10.0, -15.0)).norm() < 1.0 + 0.8,
        "{p1}"
    );
    assert!((yaw1.to_degrees() - 90.0).abs() < 12.0);
    assert!((max_alt - 30.0).abs() < 1.0, "RTL altitude {max_alt}");
    // Landed at home and disarmed.
    let p = s.ap.vehicle().p_ned();
    assert!(p.x.hypot(p.y) < 0.6 && p.z == 0.0, "{p}");
    assert!(!s.ap.armed());
    // One capture, taken looking straight down at waypoint 1.
    assert_eq!(captures.len(), 1);
    let c = &captures[0];
    let fwd = c.world_from_cam.rotation * Vector3::z();
    assert!(fwd.z > 0.999, "{fwd}");
    assert!((c.world_from_cam.translation.vector - Vector3::new(30.0, 10.0, -15.0)).norm() < 1.5);
    let msg = s.ap.capture_done(c, Some("file:///tmp/img_0000.jpg"));
    let MavMessage::CAMERA_IMAGE_CAPTURED(m) = msg else {
        panic!()
    };
    assert_eq!(m.capture_result, MavBool::MAV_BOOL_TRUE);
    assert_eq!(m.file_url.to_str().ok(), Some("file:///tmp/img_0000.jpg"));
    assert!((m.relative_alt - 15_000).abs() < 1000);
}

#[test]
fn waypoint_started_on_the_ground_climbs_first_and_hold_time_is_kept() {
    let mut s = Sim::new(Flavour::Px4);
    let (la, lo) = latlon(20.0, 0.0);
    let (lb, lob) = latlon(20.0, 20.0);
    s.upload(vec![
        item(
            0,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            REL,
            [3.0, 0.0, 0.0, f32::NAN],
            la,
            lo,
            10.0,
        ),
        item(
            1,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            REL,
            [0.0, 0.0, 0.0, f32::NAN],
            lb,
            lob,
            10.0,
        ),
    ]);
    s.command(
        MavCmd::MAV_CMD_DO_SET_MODE,
        [1.0, 4.0, 4.0, 0.0, 0.0, 0.0, 0.0],
    );
    s.command(
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    let mut reached_t = Vec::new();
    let mut min_alt_at_5m_north = f64::INFINITY;
    for _ in 0..(60.0 / DT) as usize {
        for (t, m) in s.run(DT) {
            if let MavMessage::MISSION_ITEM_REACHED(r) = m {
                reached_t.push((r.seq, t));
            }
        }
        let p = s.ap.vehicle().p_ned();
        if p.x > 1.0 {
            min_alt_at_5m_north = min_alt_at_5m_north.min(-p.z);
        }
    }
    assert!(
        min_alt_at_5m_north > 9.0,
        "did not climb first: {min_alt_at_5m_north}"
    );
    assert_eq!(reached_t.len(), 2);
    // The second leg (20 m at 5 m/s) starts after the 3 s hold.
    let dt = reached_t[1].1 - reached_t[0].1;
    assert!(dt > 3.0 + 20.0 / 5.0 - 0.5, "{dt}");
    assert!(s.ap.mission_finished());
}

#[test]
fn disarm_in_the_air_is_denied_unless_forced() {
    let mut s = Sim::new(Flavour::Px4);
    s.command(
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(
        s.command(
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, 488.0 + 5.0]
        ),
        MavResult::MAV_RESULT_ACCEPTED
    );
    s.run(8.0);
    assert!((s.ap.vehicle().p_ned().z + 5.0).abs() < 0.3);
    assert_eq!(s.ap.mode(), Mode::Hold);
    assert_eq!(
        s.command(MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, [0.0; 7]),
        MavResult::MAV_RESULT_DENIED
    );
    assert!(s.ap.armed());
    assert_eq!(
        s.command(MavCmd::MAV_CMD_NAV_LAND, [0.0; 7]),
        MavResult::MAV_RESULT_ACCEPTED
    );
    s.run(12.0);
    assert!(s.ap.vehicle().landed());
    assert!(!s.ap.armed(), "auto-disarm after landing");
}

#[test]
fn preflight_arm_times_out() {
    let mut s = Sim::new(Flavour::Px4);
    s.command(
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    s.run(9.0);
    assert!(s.ap.armed());
    s.run(2.0);
    assert!(!s.ap.armed());
}

#[test]
fn unknown_commands_are_unsupported_and_mission_start_needs_a_mission() {
    let mut s = Sim::new(Flavour::Px4);
    assert_eq!(
        s.command(MavCmd::MAV_CMD_DO_SET_SERVO, [0.0; 7]),
        MavResult::MAV_RESULT_UNSUPPORTED
    );
    assert_eq!(
        s.command(MavCmd::MAV_CMD_MISSION_START, [0.0; 7]),
        MavResult::MAV_RESULT_DENIED
    );
}

#[test]
fn ardupilot_mission_starts_after_home_and_condition_yaw_turns() {
    let mut s = Sim::new(Flavour::ArduPilot);
    let (la, lo) = latlon(10.0, 0.0);
    s.upload(vec![
        item(
            0,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            MavFrame::MAV_FRAME_GLOBAL,
            [0.0; 4],
            0,
            0,
            0.0,
        ),
        item(1, MavCmd::MAV_CMD_NAV_TAKEOFF, REL, [0.0; 4], 0, 0, 8.0),
        item(
            2,
            MavCmd::MAV_CMD_CONDITION_YAW,
            MavFrame::MAV_FRAME_MISSION,
            [135.0, 30.0, 1.0, 0.0],
            0,
            0,
            0.0,
        ),
        item(
            3,
            MavCmd::MAV_CMD_DO_DIGICAM_CONTROL,
            MavFrame::MAV_FRAME_MISSION,
            [0.0; 4],
            1,
            0,
            0.0,
        ),
        item(
            4,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            REL,
            [0.0, 0.0, 0.0, f32::NAN],
            la,
            lo,
            8.0,
        ),
    ]);
    // ArduPilot refuses MISSION_START while disarmed.
    assert_eq!(
        s.command(MavCmd::MAV_CMD_MISSION_START, [0.0; 7]),
        MavResult::MAV_RESULT_DENIED
    );
    s.command(
        MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
        [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    );
    assert_eq!(
        s.command(MavCmd::MAV_CMD_MISSION_START, [0.0; 7]),
        MavResult::MAV_RESULT_ACCEPTED
    );
    let mut reached = Vec::new();
    let mut yaw_at_capture = None;
    for _ in 0..(40.0 / DT) as usize {
        for (_, m) in s.run(DT) {
            if let MavMessage::MISSION_ITEM_REACHED(r) = m {
                reached.push(r.seq);
            }
        }
        if let Some(c) = s.ap.take_capture_requests().first() {
            let fwd = c.world_from_cam.rotation * Vector3::z();
            yaw_at_capture = Some(fwd.y.atan2(fwd.x).to_degrees());
        }
    }
    assert_eq!(reached, vec![1, 2, 3, 4]);
    let y = yaw_at_capture.expect("capture");
    assert!((y - 135.0).abs() < 2.5, "{y}");
    assert!((s.ap.vehicle().p_ned() - Vector3::new(10.0, 0.0, -8.0)).norm() < 2.0);
}

#[test]
fn takeoff_item_is_reached_at_once_when_already_higher() {
    let mut s = Sim::new(Flavour::Px4);
    s.take_off(488.0 + 20.0, 12.0);
    assert!((s.ap.vehicle().p_ned().z + 20.0).abs() < 0.3);
    s.upload(vec![item(
        0,
        MavCmd::MAV_CMD_NAV_TAKEOFF,
        REL,
        [0.0; 4],
        0,
        0,
        8.0,
    )]);
    s.command(MavCmd::MAV_CMD_MISSION_START, [0.0; 7]);
    let out = s.run(2.0);
    assert!(
        out.iter()
            .any(|(_, m)| matches!(m, MavMessage::MISSION_ITEM_REACHED(r) if r.seq == 0))
    );
    assert!(
        (s.ap.vehicle().p_ned().z + 20.0).abs() < 0.3,
        "descended: {}",
        s.ap.vehicle().p_ned()
    );
}

#[test]
fn ardupilot_honours_request_data_stream_and_px4_ignores_it() {
    use mavlink::Message;
    use mavlink::dialects::common::{MavDataStream, REQUEST_DATA_STREAM_DATA};
    let req = MavMessage::REQUEST_DATA_STREAM(REQUEST_DATA_STREAM_DATA {
        req_message_rate: 20,
        target_system: 1,
        target_component: 1,
        req_stream_id: MavDataStream::MAV_DATA_STREAM_POSITION,
        start_stop: 1,
    });
    let count = |msgs: &[(f64, MavMessage)], id: u32| {
        msgs.iter().filter(|(_, m)| m.message_id() == id).count()
    };
    let mut a = Sim::new(Flavour::ArduPilot);
    a.send(req.clone());
    let out = a.run(5.0);
    assert!((99..=101).contains(&count(&out, 33)), "{}", count(&out, 33));
    assert!((99..=101).contains(&count(&out, 32)));
    let mut p = Sim::new(Flavour::Px4);
    p.send(req);
    let out = p.run(5.0);
    assert!((24..=26).contains(&count(&out, 33)));
}

#[test]
fn mount_control_moves_the_gimbal_and_the_status_reports_it() {
    let mut s = Sim::new(Flavour::Px4);
    let r = s.command(
        MavCmd::MAV_CMD_DO_MOUNT_CONTROL,
        [-45.0, 0.0, 30.0, 0.0, 0.0, 0.0, 2.0],
    );
    assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
    s.run(1.0);
    let (pitch, yaw) = s.ap.vehicle().gimbal_angles();
    assert!((pitch.to_degrees() + 45.0).abs() < 1e-6 && (yaw.to_degrees() - 30.0).abs() < 1e-6);
    let Some(MavMessage::GIMBAL_DEVICE_ATTITUDE_STATUS(g)) = s.ap.build(285) else {
        panic!()
    };
    let q = UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(
        f64::from(g.q[0]),
        f64::from(g.q[1]),
        f64::from(g.q[2]),
        f64::from(g.q[3]),
    ));
    let (_, p, y) = q.euler_angles();
    assert!((p.to_degrees() + 45.0).abs() < 1e-3 && (y.to_degrees() - 30.0).abs() < 1e-3);
    // Earth-frame yaw (YAW_LOCK flag) is converted to body-relative.
    s.ap.vehicle_mut()
        .teleport(Vector3::new(0.0, 0.0, 0.0), 90f64.to_radians());
    s.command(
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
        [-2.0, -2.0, -1.0, -1.0, 0.0, 0.0, 0.0],
    );
    s.command(
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
        [-10.0, 120.0, f32::NAN, f32::NAN, 16.0, 0.0, 0.0],
    );
    s.run(2.0);
    let (_, yaw) = s.ap.vehicle().gimbal_angles();
    assert!(
        (yaw.to_degrees() - 30.0).abs() < 1e-6,
        "{}",
        yaw.to_degrees()
    );
}

/// The flavours, for tests that run on both.
const FLAVOURS: [Flavour; 2] = [Flavour::Px4, Flavour::ArduPilot];

fn manager_status(s: &Sim) -> GIMBAL_MANAGER_STATUS_DATA {
    match s.ap.build(281) {
        Some(MavMessage::GIMBAL_MANAGER_STATUS(d)) => d,
        other => panic!("no GIMBAL_MANAGER_STATUS: {other:?}"),
    }
}

#[test]
fn gimbal_manager_denies_pitchyaw_until_configured_and_releases() {
    for flavour in FLAVOURS {
        let mut s = Sim::new(flavour);
        // Discovery: GIMBAL_MANAGER_INFORMATION on request, status streamed.
        let out = s.send(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: 280.0,
            command: MavCmd::MAV_CMD_REQUEST_MESSAGE,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        }));
        let Some(MavMessage::GIMBAL_MANAGER_INFORMATION(info)) = out.first() else {
            panic!("{out:?}")
        };
        assert_eq!(info.gimbal_device_id, GIMBAL_DEVICE_ID);
        assert!((info.pitch_min.to_degrees() + 90.0).abs() < 1e-3);
        use mavlink::Message;
        let streamed = s.run(4.1);
        let n = streamed
            .iter()
            .filter(|(_, m)| m.message_id() == 281)
            .count();
        assert!((2..=3).contains(&n), "{flavour:?}: {n} statuses in 4 s");
        assert_eq!(
            manager_status(&s).primary_control_sysid,
            0,
            "nobody at boot"
        );

        // Not in control: denied with a STATUSTEXT, the gimbal stays.
        let out = s.send(MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: -40.0,
            param2: 0.0,
            param3: f32::NAN,
            param4: f32::NAN,
            param5: 44.0,
            command: MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        }));
        assert!(
            out.iter()
                .any(|m| matches!(m, MavMessage::STATUSTEXT(t) if t.severity == MavSeverity::MAV_SEVERITY_WARNING)),
            "{out:?}"
        );
        assert!(matches!(
            out.last(),
            Some(MavMessage::COMMAND_ACK(a)) if a.result == MavResult::MAV_RESULT_DENIED
        ));
        s.run(2.0);
        assert!(s.ap.vehicle().gimbal_angles().0.to_degrees().abs() < 1e-6);

        // Configure: the GCS (255/190) takes primary control, the status says so.
        let r = s.command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
            [
                255.0,
                190.0,
                -1.0,
                -1.0,
                0.0,
                0.0,
                f32::from(GIMBAL_DEVICE_ID),
            ],
        );
        assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
        let st = manager_status(&s);
        assert_eq!(
            (st.primary_control_sysid, st.primary_control_compid),
            (255, 190)
        );
        assert_eq!(st.gimbal_device_id, GIMBAL_DEVICE_ID);
        let r = s.command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            [-40.0, 0.0, f32::NAN, f32::NAN, 44.0, 0.0, 0.0],
        );
        assert_eq!(r, MavResult::MAV_RESULT_ACCEPTED);
        s.run(3.0);
        let pitch = s.ap.vehicle().gimbal_angles().0.to_degrees();
        assert!((pitch + 40.0).abs() < 0.5, "{flavour:?}: pitch {pitch}");

        // Another gimbal device, a bad value: refused, control unchanged.
        let r = s.command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
            [0.0, 0.0, -1.0, -1.0, 0.0, 0.0, 155.0],
        );
        assert_eq!(r, MavResult::MAV_RESULT_FAILED);
        let r = s.command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
            [-7.0, 0.0, -1.0, -1.0, 0.0, 0.0, 0.0],
        );
        assert_eq!(r, MavResult::MAV_RESULT_DENIED);
        assert_eq!(s.ap.gimbal_primary(), (255, 190));

        // Release (-3) from someone else does nothing; from the holder it frees.
        let other = MavHeader {
            system_id: 1,
            component_id: 191,
            sequence: 0,
        };
        let release = MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: -3.0,
            param2: -3.0,
            param3: -1.0,
            param4: -1.0,
            command: MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
            target_system: 1,
            target_component: 1,
            ..Default::default()
        });
        s.ap.handle(&other, &release);
        assert_eq!(s.ap.gimbal_primary(), (255, 190));
        s.send(release);
        assert_eq!(s.ap.gimbal_primary(), (0, 0));
        let r = s.command(
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
            [-10.0, 0.0, f32::NAN, f32::NAN, 44.0, 0.0, 0.0],
        );
        assert_eq!(r, MavResult::MAV_RESULT_DENIED);
    }
}

/// A one-waypoint mission 20 m north at 10 m with a gimbal item; the
/// gimbal pitch at the end.
fn fly_gimbal_mission(s: &mut Sim, configure_item: bool) -> f64 {
    let ardu = s.ap.params().flavour == Flavour::ArduPilot;
    let (la, lo) = latlon(20.0, 0.0);
    let mut items = Vec::new();
    if ardu {
        items.push(item(
            0,
            MavCmd::MAV_CMD_NAV_WAYPOINT,
            MavFrame::MAV_FRAME_GLOBAL,
            [0.0; 4],
            la,
            lo,
            0.0,
        ));
    }
    if configure_item {
        items.push(item(
            0,
            MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
            MavFrame::MAV_FRAME_MISSION,
            [-2.0, -2.0, -1.0, -1.0],
            0,
            0,
            0.0,
        ));
    }
    items.push(item(
        0,
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
        MavFrame::MAV_FRAME_MISSION,
        [-55.0, 0.0, f32::NAN, f32::NAN],
        44,
        0,
        0.0,
    ));
    items.push(item(
        0,
        MavCmd::MAV_CMD_NAV_WAYPOINT,
        REL,
        [1.0, 1.0, 0.0, 0.0],
        la,
        lo,
        10.0,
    ));
    for (i, it) in items.iter_mut().enumerate() {
        it.seq = i as u16;
    }
    s.upload(items);
    assert_eq!(
        s.command(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        ),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(
        s.command(MavCmd::MAV_CMD_MISSION_START, [0.0; 7]),
        MavResult::MAV_RESULT_ACCEPTED
    );
    for _ in 0..(60.0 / DT) as usize {
        s.run(DT);
        if s.ap.mission_finished() {
            break;
        }
    }
    assert!(s.ap.mission_finished());
    s.run(3.0);
    s.ap.vehicle().gimbal_angles().0.to_degrees()
}

#[test]
fn mission_gimbal_items_need_control_on_both_flavours() {
    // PX4: the mission's own CONFIGURE item (-2) makes the autopilot the
    // controller; without it the PITCHYAW item is refused.
    let mut s = Sim::new(Flavour::Px4);
    let pitch = fly_gimbal_mission(&mut s, true);
    assert!(
        (pitch + 55.0).abs() < 1.0,
        "PX4 with configure item: {pitch}"
    );
    assert_eq!(s.ap.gimbal_primary(), (1, 1));
    assert_eq!(s.ap.gimbal_refusals(), 0);
    let mut s = Sim::new(Flavour::Px4);
    let pitch = fly_gimbal_mission(&mut s, false);
    assert!(
        pitch.abs() < 1e-6,
        "PX4 without configure: gimbal moved to {pitch}"
    );
    assert_eq!(s.ap.gimbal_refusals(), 1);
    // PX4: the GCS holding control is not the autopilot: still refused.
    let mut s = Sim::new(Flavour::Px4);
    s.command(
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
        [-2.0, -2.0, -1.0, -1.0, 0.0, 0.0, 0.0],
    );
    let pitch = fly_gimbal_mission(&mut s, false);
    assert!(pitch.abs() < 1e-6, "{pitch}");

    // ArduPilot: no CONFIGURE mission item; the GCS's control lets the item run.
    let mut s = Sim::new(Flavour::ArduPilot);
    let pitch = fly_gimbal_mission(&mut s, false);
    assert!(
        pitch.abs() < 1e-6,
        "ArduPilot, nobody in control: gimbal moved to {pitch}"
    );
    assert_eq!(s.ap.gimbal_refusals(), 1);
    let mut s = Sim::new(Flavour::ArduPilot);
    s.command(
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
        [255.0, 190.0, -1.0, -1.0, 0.0, 0.0, 0.0],
    );
    let pitch = fly_gimbal_mission(&mut s, false);
    assert!(
        (pitch + 55.0).abs() < 1.0,
        "ArduPilot with GCS control: {pitch}"
    );
    assert_eq!(s.ap.gimbal_refusals(), 0);
}

#[test]
fn ardupilot_refuses_the_configure_mission_item() {
    let mut s = Sim::new(Flavour::ArduPilot);
    let _ = s.send(MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: 2,
        target_system: 1,
        target_component: 1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        opaque_id: 0,
    }));
    let _ = s.send(MavMessage::MISSION_ITEM_INT(item(
        0,
        MavCmd::MAV_CMD_NAV_WAYPOINT,
        MavFrame::MAV_FRAME_GLOBAL,
        [0.0; 4],
        0,
        0,
        0.0,
    )));
    let out = s.send(MavMessage::MISSION_ITEM_INT(item(
        1,
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
        MavFrame::MAV_FRAME_MISSION,
        [-2.0, -2.0, -1.0, -1.0],
        0,
        0,
        0.0,
    )));
    assert!(
        out.iter().any(|m| matches!(m, MavMessage::MISSION_ACK(a) if a.mavtype == MavMissionResult::MAV_MISSION_UNSUPPORTED)),
        "{out:?}"
    );
}

mod offboard;
