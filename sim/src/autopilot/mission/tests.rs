//! One test per protocol rule.

use super::*;
use mavlink::dialects::common::{
    MISSION_CLEAR_ALL_DATA, MISSION_REQUEST_LIST_DATA, MISSION_SET_CURRENT_DATA,
};

const GCS: Peer = Peer {
    system: 255,
    component: 190,
};
const OTHER: Peer = Peer {
    system: 254,
    component: 1,
};
const HOME: Geodetic = Geodetic {
    lat_deg: 47.397_742,
    lon_deg: 8.545_594,
    alt_m: 488.0,
};

fn px4() -> MissionProtocol {
    MissionProtocol::new(MissionParams::px4(), HOME)
}
fn ardu() -> MissionProtocol {
    MissionProtocol::new(MissionParams::ardupilot(), HOME)
}

fn count(n: u16) -> MavMessage {
    MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: n,
        target_system: 1,
        target_component: 1,
        mission_type: MISSION,
        opaque_id: 0,
    })
}

fn wp(seq: u16) -> MISSION_ITEM_INT_DATA {
    MISSION_ITEM_INT_DATA {
        param1: 0.0,
        param2: 2.0,
        param3: 0.0,
        param4: 0.0,
        x: 473_977_420 + i32::from(seq) * 1000,
        y: 85_455_940 + i32::from(seq) * 700,
        z: 20.0 + f32::from(seq),
        seq,
        command: MavCmd::MAV_CMD_NAV_WAYPOINT,
        target_system: 1,
        target_component: 1,
        frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        current: 0,
        autocontinue: 1,
        mission_type: MISSION,
    }
}

fn int(m: MISSION_ITEM_INT_DATA) -> MavMessage {
    MavMessage::MISSION_ITEM_INT(m)
}

fn legacy(m: &MISSION_ITEM_INT_DATA) -> MavMessage {
    let mut f = MissionItem::from_int(m).to_float(Peer {
        system: 1,
        component: 1,
    });
    f.seq = m.seq;
    MavMessage::MISSION_ITEM(f)
}

fn request_seq(m: &MavMessage) -> Option<(u16, bool)> {
    match m {
        MavMessage::MISSION_REQUEST(r) => Some((r.seq, false)),
        MavMessage::MISSION_REQUEST_INT(r) => Some((r.seq, true)),
        _ => None,
    }
}

fn ack_code(m: &MavMessage) -> Option<MavMissionResult> {
    match m {
        MavMessage::MISSION_ACK(a) => Some(a.mavtype),
        _ => None,
    }
}

/// Upload `items` as MISSION_ITEM_INT with no losses; returns the final ACK.
fn upload(p: &mut MissionProtocol, t: f64, items: &[MISSION_ITEM_INT_DATA]) -> MavMissionResult {
    let out = p.handle(t, GCS, &count(items.len() as u16));
    assert_eq!(request_seq(&out[0]).map(|r| r.0), Some(0));
    for it in items {
        let out = p.handle(t, GCS, &int(it.clone()));
        if let Some(code) = out.iter().find_map(ack_code) {
            return code;
        }
    }
    panic!("no ACK after the last item");
}

#[test]
fn first_request_is_legacy_until_an_item_int_arrives() {
    let mut p = px4();
    let out = p.handle(0.0, GCS, &count(3));
    assert_eq!(out.len(), 1);
    assert_eq!(request_seq(&out[0]), Some((0, false)));
    let out = p.handle(0.1, GCS, &int(wp(0)));
    assert_eq!(request_seq(&out[0]), Some((1, true)));
    // A legacy item switches back to legacy requests.
    let out = p.handle(0.2, GCS, &legacy(&wp(1)));
    assert_eq!(request_seq(&out[0]), Some((2, false)));
    // And a new upload starts legacy again.
    let out = p.handle(0.3, GCS, &int(wp(2)));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    let out = p.handle(1.0, GCS, &count(1));
    assert_eq!(request_seq(&out[0]), Some((0, false)));
}

#[test]
fn pending_request_is_resent_every_250_ms() {
    let mut p = px4();
    p.handle(0.0, GCS, &count(2));
    assert!(p.tick(0.2).is_empty());
    let out = p.tick(0.25);
    assert_eq!(request_seq(&out[0]), Some((0, false)));
    assert!(p.tick(0.3).is_empty());
    assert_eq!(request_seq(&p.tick(0.5)[0]), Some((0, false)));
    p.handle(0.6, GCS, &int(wp(0)));
    assert!(p.tick(0.8).is_empty());
    assert_eq!(request_seq(&p.tick(0.85)[0]), Some((1, true)));
}

#[test]
fn transfer_is_abandoned_after_5_s_of_silence_and_old_mission_kept() {
    let mut p = px4();
    assert_eq!(
        upload(&mut p, 0.0, &[wp(0)]),
        MavMissionResult::MAV_MISSION_ACCEPTED
    );
    p.handle(10.0, GCS, &count(3));
    p.handle(10.5, GCS, &int(wp(0)));
    // Re-requests go on until 5 s after the last message heard.
    let mut t = 10.5;
    let mut cancelled_at = None;
    while t < 17.0 {
        t += 0.01;
        let out = p.tick(t);
        if out.iter().find_map(ack_code) == Some(MavMissionResult::MAV_MISSION_OPERATION_CANCELLED)
        {
            cancelled_at = Some(t);
            break;
        }
    }
    let at = cancelled_at.expect("no cancel");
    assert!((at - 15.5).abs() < 0.02, "cancelled at {at}");
    assert!(!p.busy());
    assert_eq!(p.items().len(), 1);
    assert!(p.tick(20.0).is_empty());
}

#[test]
fn storage_is_atomic_old_mission_stays_until_new_one_complete() {
    let mut p = px4();
    upload(&mut p, 0.0, &[wp(0), wp(1)]);
    p.take_events();
    let old = p.items().to_vec();
    p.handle(1.0, GCS, &count(3));
    let mut a = wp(0);
    a.z = 99.0;
    p.handle(1.1, GCS, &int(a.clone()));
    p.handle(1.2, GCS, &int(wp(1)));
    assert_eq!(p.items(), &old[..]);
    assert!(p.take_events().is_empty());
    let out = p.handle(1.3, GCS, &int(wp(2)));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    assert_eq!(p.items().len(), 3);
    assert_eq!(p.items()[0].z, 99.0);
    assert_eq!(p.take_events(), vec![MissionEvent::Stored { count: 3 }]);
}

#[test]
fn unsupported_frame_is_acked_and_ends_the_transfer() {
    let mut p = px4();
    let mut bad = wp(1);
    bad.frame = MavFrame::MAV_FRAME_LOCAL_NED;
    p.handle(0.0, GCS, &count(2));
    p.handle(0.0, GCS, &int(wp(0)));
    let out = p.handle(0.0, GCS, &int(bad));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME)
    );
    assert!(!p.busy());
    assert!(p.items().is_empty());
    // A nav command in the MISSION frame is also an unsupported frame.
    let mut nav = wp(0);
    nav.frame = MavFrame::MAV_FRAME_MISSION;
    p.handle(1.0, GCS, &count(1));
    let out = p.handle(1.0, GCS, &int(nav));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME)
    );
}

#[test]
fn unsupported_command_is_acked() {
    let mut p = px4();
    let mut bad = wp(0);
    bad.command = MavCmd::MAV_CMD_NAV_LOITER_TURNS;
    p.handle(0.0, GCS, &count(1));
    let out = p.handle(0.0, GCS, &int(bad.clone()));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_UNSUPPORTED)
    );
    // CONDITION_YAW is ArduPilot-only.
    bad.command = MavCmd::MAV_CMD_CONDITION_YAW;
    bad.frame = MavFrame::MAV_FRAME_MISSION;
    p.handle(1.0, GCS, &count(1));
    let out = p.handle(1.0, GCS, &int(bad));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_UNSUPPORTED)
    );
}

#[test]
fn bad_params_are_acked_with_the_parameter_code() {
    type Edit = Box<dyn Fn(&mut MISSION_ITEM_INT_DATA)>;
    let cases: Vec<(Edit, MavMissionResult)> = vec![
        (
            Box::new(|m| m.param1 = -1.0),
            MavMissionResult::MAV_MISSION_INVALID_PARAM1,
        ),
        (
            Box::new(|m| m.param2 = -3.0),
            MavMissionResult::MAV_MISSION_INVALID_PARAM2,
        ),
        (
            Box::new(|m| m.x = 950_000_000),
            MavMissionResult::MAV_MISSION_INVALID_PARAM5_X,
        ),
        (
            Box::new(|m| m.y = -1_850_000_000),
            MavMissionResult::MAV_MISSION_INVALID_PARAM6_Y,
        ),
        (
            Box::new(|m| m.z = f32::NAN),
            MavMissionResult::MAV_MISSION_INVALID_PARAM7,
        ),
        (
            Box::new(|m| {
                m.command = MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW;
                m.frame = MavFrame::MAV_FRAME_MISSION;
                m.param1 = -200.0;
            }),
            MavMissionResult::MAV_MISSION_INVALID_PARAM1,
        ),
        (
            Box::new(|m| {
                m.command = MavCmd::MAV_CMD_IMAGE_START_CAPTURE;
                m.frame = MavFrame::MAV_FRAME_MISSION;
                m.param2 = 0.0;
                m.param3 = -1.0;
            }),
            MavMissionResult::MAV_MISSION_INVALID_PARAM3,
        ),
    ];
    for (i, (edit, code)) in cases.into_iter().enumerate() {
        let mut p = px4();
        let mut m = wp(0);
        edit(&mut m);
        p.handle(0.0, GCS, &count(1));
        let out = p.handle(0.0, GCS, &int(m));
        assert_eq!(out.iter().find_map(ack_code), Some(code), "case {i}");
        assert!(p.items().is_empty());
    }
}

#[test]
fn clear_all_empties_the_mission() {
    let mut p = px4();
    upload(&mut p, 0.0, &[wp(0), wp(1)]);
    p.take_events();
    let out = p.handle(
        1.0,
        GCS,
        &MavMessage::MISSION_CLEAR_ALL(MISSION_CLEAR_ALL_DATA {
            target_system: 1,
            target_component: 1,
            mission_type: MISSION,
        }),
    );
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    assert!(p.items().is_empty());
    assert_eq!(p.take_events(), vec![MissionEvent::Cleared]);
    // MISSION_COUNT 0 clears too.
    upload(&mut p, 2.0, &[wp(0)]);
    let out = p.handle(3.0, GCS, &count(0));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    assert!(p.items().is_empty());
}

#[test]
fn set_current_jumps_and_reports_or_refuses() {
    let mut p = px4();
    upload(&mut p, 0.0, &[wp(0), wp(1), wp(2)]);
    p.take_events();
    let set = |seq| {
        MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
            seq,
            target_system: 1,
            target_component: 1,
        })
    };
    let out = p.handle(1.0, GCS, &set(2));
    match &out[0] {
        MavMessage::MISSION_CURRENT(c) => assert_eq!((c.seq, c.total), (2, 3)),
        m => panic!("{m:?}"),
    }
    assert_eq!(p.current(), 2);
    assert_eq!(p.take_events(), vec![MissionEvent::SetCurrent(2)]);
    let out = p.handle(1.0, GCS, &set(3));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE)
    );
    assert_eq!(p.current(), 2);
}

#[test]
fn duplicate_of_the_last_item_is_re_acked() {
    let mut p = px4();
    upload(&mut p, 0.0, &[wp(0), wp(1)]);
    let out = p.handle(1.0, GCS, &int(wp(1)));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    // ...but not any other item, nor from another peer.
    assert!(p.handle(1.0, GCS, &int(wp(0))).is_empty());
    assert!(p.handle(1.0, OTHER, &int(wp(1))).is_empty());
    assert_eq!(p.items().len(), 2);
}

#[test]
fn out_of_sequence_item_is_ignored_by_px4() {
    let mut p = px4();
    p.handle(0.0, GCS, &count(3));
    assert!(p.handle(0.1, GCS, &int(wp(1))).is_empty());
    let out = p.handle(0.2, GCS, &int(wp(0)));
    assert_eq!(request_seq(&out[0]), Some((1, true)));
}

#[test]
fn repeated_count_before_item_0_re_requests_then_busy() {
    let mut p = px4();
    p.handle(0.0, GCS, &count(3));
    let out = p.handle(0.5, GCS, &count(3));
    assert_eq!(request_seq(&out[0]), Some((0, false)));
    p.handle(0.6, GCS, &int(wp(0)));
    let out = p.handle(0.7, GCS, &count(3));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ERROR)
    );
    // The transfer itself goes on.
    let out = p.handle(0.8, GCS, &int(wp(1)));
    assert_eq!(request_seq(&out[0]), Some((2, true)));
}

#[test]
fn items_from_another_peer_do_not_disturb_a_transfer() {
    let mut p = px4();
    p.handle(0.0, GCS, &count(2));
    assert!(p.handle(0.1, OTHER, &int(wp(0))).is_empty());
    let out = p.handle(0.1, OTHER, &count(1));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ERROR)
    );
    assert_eq!(
        upload_rest(&mut p, &[wp(0), wp(1)]),
        MavMissionResult::MAV_MISSION_ACCEPTED
    );
}

fn upload_rest(p: &mut MissionProtocol, items: &[MISSION_ITEM_INT_DATA]) -> MavMissionResult {
    for it in items {
        if let Some(c) = p
            .handle(0.2, GCS, &int(it.clone()))
            .iter()
            .find_map(ack_code)
        {
            return c;
        }
    }
    panic!("no ack");
}

#[test]
fn too_many_items_is_no_space() {
    let mut p = px4();
    let out = p.handle(0.0, GCS, &count(501));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_NO_SPACE)
    );
    assert!(!p.busy());
}

#[test]
fn download_returns_the_uploaded_items_identically() {
    let mut p = px4();
    let mut items = vec![wp(0), wp(1), wp(2)];
    items[2].param4 = f32::NAN; // "no yaw change" survives the round trip
    items[1].command = MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW;
    items[1].frame = MavFrame::MAV_FRAME_MISSION;
    items[1].param1 = -45.0;
    items[1].x = 0;
    items[1].y = 0;
    upload(&mut p, 0.0, &items);
    let out = p.handle(
        1.0,
        GCS,
        &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: 1,
            target_component: 1,
            mission_type: MISSION,
        }),
    );
    match &out[0] {
        MavMessage::MISSION_COUNT(c) => assert_eq!(c.count, 3),
        m => panic!("{m:?}"),
    }
    for (i, sent) in items.iter().enumerate() {
        let out = p.handle(
            1.1,
            GCS,
            &MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                seq: i as u16,
                target_system: 1,
                target_component: 1,
                mission_type: MISSION,
            }),
        );
        let MavMessage::MISSION_ITEM_INT(got) = &out[0] else {
            panic!("{:?}", out[0])
        };
        let mut want = sent.clone();
        want.target_system = GCS.system;
        want.target_component = GCS.component;
        // NaN != NaN: compare bit patterns of the params.
        assert_eq!(got.param4.to_bits(), want.param4.to_bits());
        let mut got = got.clone();
        want.param4 = 0.0;
        got.param4 = 0.0;
        assert_eq!(got, want);
    }
    // Legacy request -> legacy item.
    let out = p.handle(
        1.2,
        GCS,
        &MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
            seq: 0,
            target_system: 1,
            target_component: 1,
            mission_type: MISSION,
        }),
    );
    let MavMessage::MISSION_ITEM(f) = &out[0] else {
        panic!()
    };
    assert!((f64::from(f.x) - 47.397_742).abs() < 1e-5);
    p.handle(
        1.3,
        GCS,
        &MavMessage::MISSION_ACK(MISSION_ACK_DATA {
            target_system: 1,
            target_component: 1,
            mavtype: MavMissionResult::MAV_MISSION_ACCEPTED,
            mission_type: MISSION,
            opaque_id: 0,
        }),
    );
    assert!(!p.busy());
}

#[test]
fn download_count_is_resent_until_the_first_request() {
    let mut p = px4();
    upload(&mut p, 0.0, &[wp(0)]);
    let list = MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
        target_system: 1,
        target_component: 1,
        mission_type: MISSION,
    });
    p.handle(1.0, GCS, &list);
    let out = p.tick(1.25);
    assert!(matches!(out[0], MavMessage::MISSION_COUNT(ref c) if c.count == 1));
    // Fence and rally lists are empty.
    let out = p.handle(
        1.3,
        GCS,
        &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: 1,
            target_component: 1,
            mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
        }),
    );
    assert!(matches!(out[0], MavMessage::MISSION_COUNT(ref c) if c.count == 0));
    // The download ends by timeout when the partner goes silent.
    p.tick(6.3);
    assert!(!p.busy());
}

#[test]
fn messages_for_another_system_are_ignored() {
    let mut p = px4();
    let MavMessage::MISSION_COUNT(mut c) = count(2) else {
        unreachable!()
    };
    c.target_system = 7;
    assert!(p.handle(0.0, GCS, &MavMessage::MISSION_COUNT(c)).is_empty());
    assert!(!p.busy());
}

#[test]
fn ardupilot_requests_stay_legacy_and_retry_every_second() {
    let mut p = ardu();
    let out = p.handle(0.0, GCS, &count(3));
    assert_eq!(request_seq(&out[0]), Some((0, false)));
    let out = p.handle(0.1, GCS, &int(wp(0)));
    assert_eq!(request_seq(&out[0]), Some((1, false)));
    assert!(p.tick(0.6).is_empty());
    assert!(p.tick(1.05).is_empty());
    assert_eq!(request_seq(&p.tick(1.1)[0]), Some((1, false)));
}

#[test]
fn ardupilot_out_of_order_item_is_invalid_sequence_and_transfer_continues() {
    let mut p = ardu();
    p.handle(0.0, GCS, &count(3));
    p.handle(0.1, GCS, &int(wp(0)));
    let out = p.handle(0.2, GCS, &int(wp(2)));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE)
    );
    assert!(p.busy());
    let out = p.handle(0.3, GCS, &int(wp(1)));
    assert_eq!(request_seq(&out[0]), Some((2, false)));
}

#[test]
fn ardupilot_seq_0_is_home() {
    let mut p = ardu();
    assert_eq!(p.items().len(), 1);
    assert_eq!(p.first_item(), 1);
    let mut fake_home = wp(0);
    fake_home.x = 0;
    fake_home.y = 0;
    upload(&mut p, 0.0, &[fake_home, wp(1), wp(2)]);
    assert_eq!(p.items().len(), 3);
    assert_eq!(p.current(), 1);
    let home = &p.items()[0];
    assert!((home.x - HOME.lat_deg).abs() < 1e-9 && (home.y - HOME.lon_deg).abs() < 1e-9);
    // CONDITION_YAW and DO_DIGICAM_CONTROL are accepted.
    let mut yaw = wp(1);
    yaw.command = MavCmd::MAV_CMD_CONDITION_YAW;
    yaw.frame = MavFrame::MAV_FRAME_MISSION;
    yaw.param1 = 90.0;
    let mut cam = wp(2);
    cam.command = MavCmd::MAV_CMD_DO_DIGICAM_CONTROL;
    cam.frame = MavFrame::MAV_FRAME_MISSION;
    assert_eq!(
        upload(&mut p, 1.0, &[wp(0), yaw, cam]),
        MavMissionResult::MAV_MISSION_ACCEPTED
    );
}

#[test]
fn upload_from_the_download_partner_ends_a_download_whose_ack_was_lost() {
    let mut p = px4();
    upload(&mut p, 0.0, &[wp(0)]);
    p.handle(
        1.0,
        GCS,
        &MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: 1,
            target_component: 1,
            mission_type: MISSION,
        }),
    );
    p.handle(
        1.1,
        GCS,
        &MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq: 0,
            target_system: 1,
            target_component: 1,
            mission_type: MISSION,
        }),
    );
    assert!(p.busy());
    // Another station is refused while the download runs...
    let out = p.handle(1.2, OTHER, &count(2));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_ERROR)
    );
    // ...but the download partner's new upload goes ahead.
    let out = p.handle(1.3, GCS, &count(2));
    assert_eq!(request_seq(&out[0]), Some((0, false)));
}

/// The link maps commands and frames unknown to the dialect to reserved
/// placeholders; they are refused with the proper codes.
#[test]
fn link_placeholders_for_unknown_commands_and_frames_are_refused() {
    let mut p = px4();
    let mut m = wp(0);
    m.command = MavCmd::MAV_CMD_USER_5;
    p.handle(0.0, GCS, &count(1));
    let out = p.handle(0.0, GCS, &int(m));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_UNSUPPORTED)
    );
    let mut m = wp(0);
    m.frame = MavFrame::MAV_FRAME_RESERVED_19;
    p.handle(1.0, GCS, &count(1));
    let out = p.handle(1.0, GCS, &int(m));
    assert_eq!(
        out.iter().find_map(ack_code),
        Some(MavMissionResult::MAV_MISSION_UNSUPPORTED_FRAME)
    );
}

#[test]
fn mission_current_names_the_stored_plan() {
    for mut p in [px4(), ardu()] {
        let id = |p: &MissionProtocol| match p
            .mission_current(MissionState::MISSION_STATE_NOT_STARTED)
        {
            MavMessage::MISSION_CURRENT(c) => c.mission_id,
            _ => unreachable!(),
        };
        assert_eq!(id(&p), 0, "no mission: id 0");
        let a: Vec<_> = (0..3).map(wp).collect();
        let mut b = a.clone();
        b[2].z += 1.0;
        assert_eq!(
            upload(&mut p, 0.0, &a),
            MavMissionResult::MAV_MISSION_ACCEPTED
        );
        let id_a = id(&p);
        assert_ne!(id_a, 0);
        assert_eq!(
            upload(&mut p, 10.0, &b),
            MavMissionResult::MAV_MISSION_ACCEPTED
        );
        assert_ne!(id(&p), id_a, "another plan, another id");
        assert_eq!(
            upload(&mut p, 20.0, &a),
            MavMissionResult::MAV_MISSION_ACCEPTED
        );
        assert_eq!(id(&p), id_a, "the same plan, the same id");
    }
}
