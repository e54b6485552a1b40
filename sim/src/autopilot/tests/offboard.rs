//! Guided control (`offboard.rs`): PX4's OFFBOARD stream rules and
//! ArduPilot's GUIDED target.

use super::*;
use mavlink::dialects::common::{
    PositionTargetTypemask, SET_POSITION_TARGET_GLOBAL_INT_DATA, SET_POSITION_TARGET_LOCAL_NED_DATA,
};

fn local_target(n: f32, e: f32, d: f32, yaw: f32) -> MavMessage {
    MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
        x: n,
        y: e,
        z: d,
        yaw,
        type_mask: PositionTargetTypemask::from_bits_truncate(0b0000_1001_1111_1000),
        target_system: 1,
        target_component: 1,
        coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
        ..Default::default()
    })
}

fn statustexts(out: &[(f64, MavMessage)]) -> Vec<String> {
    out.iter()
        .filter_map(|(_, m)| match m {
            MavMessage::STATUSTEXT(t) => Some(t.text.to_str().unwrap_or("").to_string()),
            _ => None,
        })
        .collect()
}

/// Streams `msg` at 10 Hz for `seconds`; returns what the autopilot sent.
fn stream(s: &mut Sim, msg: &MavMessage, seconds: f64) -> Vec<(f64, MavMessage)> {
    let mut out = Vec::new();
    for _ in 0..(seconds * 10.0).round() as usize {
        s.send(msg.clone());
        out.extend(s.run(0.1));
    }
    out
}

const PX4_OFFBOARD: [f32; 7] = [1.0, 6.0, 0.0, 0.0, 0.0, 0.0, 0.0];

#[test]
fn px4_offboard_needs_a_setpoint_stream_and_holds_when_it_stops() {
    let mut s = Sim::new(Flavour::Px4);
    s.take_off(488.0 + 5.0, 8.0);
    assert_eq!(s.ap.mode(), Mode::Hold);
    let target = local_target(3.0, 2.0, -6.0, 0.5);
    // No stream, then a stream of half a second: refused, as PX4 does.
    assert_eq!(
        s.command(MavCmd::MAV_CMD_DO_SET_MODE, PX4_OFFBOARD),
        MavResult::MAV_RESULT_DENIED
    );
    stream(&mut s, &target, 0.5);
    assert_eq!(
        s.command(MavCmd::MAV_CMD_DO_SET_MODE, PX4_OFFBOARD),
        MavResult::MAV_RESULT_DENIED
    );
    // Setpoints before the switch are not flown.
    let p = s.ap.vehicle().p_ned();
    assert!(
        p.x.abs() < 0.3 && p.y.abs() < 0.3,
        "moved before OFFBOARD: {p}"
    );
    stream(&mut s, &target, 0.7);
    assert_eq!(
        s.command(MavCmd::MAV_CMD_DO_SET_MODE, PX4_OFFBOARD),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(s.ap.mode(), Mode::Offboard);
    let out = stream(&mut s, &target, 8.0);
    assert!(statustexts(&out).is_empty());
    let p = s.ap.vehicle().p_ned();
    assert!(
        (p - Vector3::new(3.0, 2.0, -6.0)).norm() < 0.15,
        "not at the setpoint: {p}"
    );
    assert!((s.ap.vehicle().yaw() - 0.5).abs() < 0.03);
    // The stream stops: after the loss time the vehicle holds where it is.
    let out = s.run(0.8);
    assert_eq!(s.ap.mode(), Mode::Offboard, "left before the loss time");
    assert!(statustexts(&out).is_empty());
    let out = s.run(0.5);
    assert_eq!(s.ap.mode(), Mode::Hold);
    assert!(
        statustexts(&out)
            .iter()
            .any(|t| t.contains("Offboard control lost")),
        "{:?}",
        statustexts(&out)
    );
    s.run(5.0);
    let q = s.ap.vehicle().p_ned();
    assert!((q - p).norm() < 0.2, "did not hold: {p} -> {q}");
    // Back to OFFBOARD needs a new stream.
    assert_eq!(
        s.command(MavCmd::MAV_CMD_DO_SET_MODE, PX4_OFFBOARD),
        MavResult::MAV_RESULT_DENIED
    );
}

#[test]
fn ardupilot_guided_takes_a_global_target_only_in_guided_and_keeps_it() {
    let mut s = Sim::new(Flavour::ArduPilot);
    assert_eq!(
        s.command(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [1.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        ),
        MavResult::MAV_RESULT_ACCEPTED
    );
    s.take_off(5.0, 8.0);
    // LOITER: a guided target is ignored.
    assert_eq!(
        s.command(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [1.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        ),
        MavResult::MAV_RESULT_ACCEPTED
    );
    let (lat, lon) = latlon(-4.0, 3.0);
    let target = MavMessage::SET_POSITION_TARGET_GLOBAL_INT(SET_POSITION_TARGET_GLOBAL_INT_DATA {
        lat_int: lat,
        lon_int: lon,
        alt: 7.0,
        type_mask: PositionTargetTypemask::from_bits_truncate(0b0000_1101_1111_1000),
        target_system: 1,
        target_component: 1,
        coordinate_frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
        ..Default::default()
    });
    let p0 = s.ap.vehicle().p_ned();
    s.send(target.clone());
    s.run(5.0);
    assert!((s.ap.vehicle().p_ned() - p0).norm() < 0.2, "flew in LOITER");
    // GUIDED: one target is flown and kept, no stream needed.
    assert_eq!(
        s.command(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [1.0, 4.0, 0.0, 0.0, 0.0, 0.0, 0.0]
        ),
        MavResult::MAV_RESULT_ACCEPTED
    );
    s.send(target);
    s.run(12.0);
    assert_eq!(s.ap.mode(), Mode::Offboard);
    let p = s.ap.vehicle().p_ned();
    assert!(
        (p - Vector3::new(-4.0, 3.0, -7.0)).norm() < 0.15,
        "not at the target: {p}"
    );
}
