//! The upload and download machines against scripted vehicles on a fake
//! clock.

#![allow(deprecated)]

use std::time::{Duration, Instant};

use mavlink::MavHeader;
use mavlink::dialects::common::{
    MISSION_ACK_DATA, MISSION_COUNT_DATA, MISSION_ITEM_DATA, MISSION_ITEM_INT_DATA,
    MISSION_REQUEST_DATA, MISSION_REQUEST_INT_DATA, MavCmd, MavFrame, MavMessage, MavMissionResult,
    MavMissionType,
};

use super::*;
use crate::mission::plan::{Flavour, Home, MissionItem, Target, plan};

const GCS: (u8, u8) = (255, 190);
const VEH: (u8, u8) = (1, 1);

fn peers() -> Peers {
    Peers {
        own_system: GCS.0,
        own_component: GCS.1,
        target_system: VEH.0,
        target_component: VEH.1,
    }
}

fn hdr(sys: u8, comp: u8) -> MavHeader {
    MavHeader {
        system_id: u32::from(sys),
        component_id: comp,
        sequence: 0,
    }
}

fn vh() -> MavHeader {
    hdr(VEH.0, VEH.1)
}

fn items() -> Vec<MissionItem> {
    let home = Home {
        lat_deg: 47.0,
        lon_deg: 8.0,
        alt_amsl_m: 400.0,
    };
    let t = Target {
        lat_deg: 47.0003,
        lon_deg: 8.0002,
        alt_m: 20.0,
        yaw_deg: 45.0,
        gimbal_pitch_deg: -20.0,
        photo: true,
    };
    plan(
        &t,
        &home,
        Flavour::ArduPilot,
        &crate::mission::plan::Params::default(),
    )
    .expect("plan")
}

fn req_int(seq: u16) -> MavMessage {
    MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
        seq,
        target_system: GCS.0,
        target_component: GCS.1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
    })
}

fn req_legacy(seq: u16) -> MavMessage {
    MavMessage::MISSION_REQUEST(MISSION_REQUEST_DATA {
        seq,
        target_system: GCS.0,
        target_component: GCS.1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
    })
}

fn vack(result: MavMissionResult) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: GCS.0,
        target_component: GCS.1,
        mavtype: result,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        opaque_id: 0,
    })
}

fn sent_item_seq(out: &[MavMessage]) -> Vec<u16> {
    out.iter()
        .filter_map(|m| match m {
            MavMessage::MISSION_ITEM_INT(i) => Some(i.seq),
            _ => None,
        })
        .collect()
}

fn start(now: Instant) -> (Uploader, Vec<MavMessage>) {
    let mut out = Vec::new();
    let up = Uploader::new(
        &items(),
        peers(),
        MavMissionType::MAV_MISSION_TYPE_MISSION,
        Params::default(),
        now,
        &mut out,
    )
    .expect("valid mission");
    (up, out)
}

#[test]
fn happy_path_with_both_request_kinds() {
    let t0 = Instant::now();
    let (mut up, out) = start(t0);
    assert!(
        matches!(&out[..], [MavMessage::MISSION_COUNT(c)] if c.count == 5 && c.target_system == 1)
    );
    let planned = items();
    let mut got = Vec::new();
    for seq in 0..5u16 {
        let mut out = Vec::new();
        let msg = if seq % 2 == 0 {
            req_int(seq)
        } else {
            req_legacy(seq)
        };
        up.on_message(&vh(), &msg, t0, &mut out);
        assert_eq!(out.len(), 1);
        match &out[0] {
            MavMessage::MISSION_ITEM_INT(i) => got.push(item_from_wire(i)),
            other => panic!("expected MISSION_ITEM_INT, got {other:?}"),
        }
    }
    assert!(same_mission(&planned, &got, false));
    let mut out = Vec::new();
    up.on_message(
        &vh(),
        &vack(MavMissionResult::MAV_MISSION_ACCEPTED),
        t0 + Duration::from_millis(50),
        &mut out,
    );
    let report = up.take_outcome().expect("done").expect("accepted");
    assert_eq!(report.items, 5);
    assert_eq!(report.retries, 0);
    assert_eq!(report.repeats, 0);
    assert!((report.seconds - 0.05).abs() < 1e-9);
    assert!(up.deadline().is_none());
}

#[test]
fn repeats_filters_and_invalid_sequence() {
    let t0 = Instant::now();
    let (mut up, _) = start(t0);
    let mut out = Vec::new();
    // wrong sender system, wrong component, wrong target, wrong mission type: all ignored
    up.on_message(&hdr(2, 1), &req_int(0), t0, &mut out);
    up.on_message(&hdr(1, 154), &req_int(0), t0, &mut out);
    let mut other_target = req_int(0);
    if let MavMessage::MISSION_REQUEST_INT(r) = &mut other_target {
        r.target_system = 42;
    }
    up.on_message(&vh(), &other_target, t0, &mut out);
    let mut fence = req_int(0);
    if let MavMessage::MISSION_REQUEST_INT(r) = &mut fence {
        r.mission_type = MavMissionType::MAV_MISSION_TYPE_FENCE;
    }
    up.on_message(&vh(), &fence, t0, &mut out);
    assert!(out.is_empty(), "{out:?}");
    // repeated requests are answered again
    up.on_message(&vh(), &req_int(0), t0, &mut out);
    up.on_message(&vh(), &req_int(0), t0, &mut out);
    up.on_message(&vh(), &req_int(1), t0, &mut out);
    up.on_message(&vh(), &req_int(1), t0, &mut out);
    assert_eq!(sent_item_seq(&out), [0, 0, 1, 1]);
    // ArduPilot's INVALID_SEQUENCE for a duplicate item does not end the upload
    up.on_message(
        &vh(),
        &vack(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE),
        t0,
        &mut out,
    );
    // a stale ACCEPTED before the last item is ignored
    up.on_message(
        &vh(),
        &vack(MavMissionResult::MAV_MISSION_ACCEPTED),
        t0,
        &mut out,
    );
    assert!(!up.is_done());
    // out-of-range request ignored
    out.clear();
    up.on_message(&vh(), &req_int(9), t0, &mut out);
    assert!(out.is_empty());
    for s in 2..5 {
        up.on_message(&vh(), &req_int(s), t0, &mut out);
    }
    up.on_message(
        &vh(),
        &vack(MavMissionResult::MAV_MISSION_ACCEPTED),
        t0,
        &mut out,
    );
    let r = up.take_outcome().expect("done").expect("accepted");
    assert_eq!(r.repeats, 2);
    assert_eq!(r.ignored, 3);
}

#[test]
fn late_final_ack_resends_last_item_and_timeouts_fail() {
    let t0 = Instant::now();
    let p = Params::default();
    let step = Duration::from_millis(p.retry_timeout_ms);
    let (mut up, _) = start(t0);
    let mut out = Vec::new();
    // no request: COUNT is resent at each timeout
    up.on_timeout(t0 + step / 2, &mut out);
    assert!(out.is_empty(), "not due yet");
    up.on_timeout(t0 + step, &mut out);
    assert!(matches!(&out[..], [MavMessage::MISSION_COUNT(_)]));
    out.clear();
    let mut now = t0 + step;
    for s in 0..5 {
        up.on_message(&vh(), &req_int(s), now, &mut out);
    }
    out.clear();
    // the final ACK is late: the last item goes again, every timeout
    for k in 1..=3 {
        now += step;
        up.on_timeout(now, &mut out);
        assert_eq!(sent_item_seq(&out), vec![4; k]);
    }
    up.on_message(
        &vh(),
        &vack(MavMissionResult::MAV_MISSION_ACCEPTED),
        now,
        &mut out,
    );
    let r = up.take_outcome().expect("done").expect("ok");
    assert_eq!(r.retries, 4, "one COUNT + three last-item resends");
    assert!(!r.verified_by_download);

    // the final ACK never comes: after final_ack_retries resends, NoFinalAck
    let (mut up, _) = start(t0);
    let mut now = t0;
    for s in 0..5 {
        up.on_message(&vh(), &req_int(s), now, &mut out);
    }
    out.clear();
    while !up.is_done() {
        now += step;
        up.on_timeout(now, &mut out);
    }
    assert_eq!(sent_item_seq(&out), vec![4; p.final_ack_retries as usize]);
    assert_eq!(
        up.take_outcome(),
        Some(Err(MissionError::NoFinalAck {
            count: 5,
            retries: p.final_ack_retries
        }))
    );
    assert_eq!(up.report_at(now).retries, p.final_ack_retries);

    // silence: fails after max_retries timeouts
    let (mut up, _) = start(t0);
    let mut now = t0;
    let mut sent = 0;
    while !up.is_done() {
        now += step;
        let mut out = Vec::new();
        up.on_timeout(now, &mut out);
        sent += out.len();
    }
    assert_eq!(sent, p.max_retries as usize);
    assert_eq!(
        up.take_outcome(),
        Some(Err(MissionError::Timeout {
            stage: Stage::FirstRequest,
            retries: p.max_retries
        }))
    );
}

#[test]
fn every_result_is_a_typed_error() {
    use MavMissionResult as R;
    let all = [
        R::MAV_MISSION_ERROR,
        R::MAV_MISSION_UNSUPPORTED_FRAME,
        R::MAV_MISSION_UNSUPPORTED,
        R::MAV_MISSION_NO_SPACE,
        R::MAV_MISSION_INVALID,
        R::MAV_MISSION_INVALID_PARAM1,
        R::MAV_MISSION_INVALID_PARAM2,
        R::MAV_MISSION_INVALID_PARAM3,
        R::MAV_MISSION_INVALID_PARAM4,
        R::MAV_MISSION_INVALID_PARAM5_X,
        R::MAV_MISSION_INVALID_PARAM6_Y,
        R::MAV_MISSION_INVALID_PARAM7,
        R::MAV_MISSION_DENIED,
        R::MAV_MISSION_OPERATION_CANCELLED,
    ];
    let t0 = Instant::now();
    let mut seen = Vec::new();
    for r in all {
        let (mut up, _) = start(t0);
        let mut out = Vec::new();
        up.on_message(&vh(), &req_int(0), t0, &mut out);
        up.on_message(&vh(), &req_int(1), t0, &mut out);
        up.on_message(&vh(), &vack(r), t0, &mut out);
        let err = up.take_outcome().expect("finished").expect_err("an error");
        match (&r, &err) {
            (R::MAV_MISSION_NO_SPACE, MissionError::NoSpace { count: 5 }) => {}
            (R::MAV_MISSION_DENIED, MissionError::Denied) => {}
            (R::MAV_MISSION_OPERATION_CANCELLED, MissionError::CancelledByVehicle) => {}
            (_, MissionError::VehicleError { last_seq: Some(1) })
            | (_, MissionError::UnsupportedFrame { last_seq: Some(1) })
            | (_, MissionError::UnsupportedCommand { last_seq: Some(1) })
            | (_, MissionError::InvalidItem { last_seq: Some(1) })
            | (
                _,
                MissionError::InvalidParam {
                    last_seq: Some(1), ..
                },
            ) => {}
            _ => panic!("{r:?} -> {err:?}"),
        }
        assert!(!seen.contains(&err), "{err:?} maps two results");
        seen.push(err);
    }
    assert_eq!(
        MissionError::from_result(R::MAV_MISSION_ACCEPTED, None, 0),
        None
    );
    assert_eq!(
        MissionError::from_result(R::MAV_MISSION_INVALID_SEQUENCE, None, 0),
        Some(MissionError::InvalidSequence)
    );
    let params: Vec<u8> = seen
        .iter()
        .filter_map(|e| match e {
            MissionError::InvalidParam { param, .. } => Some(*param),
            _ => None,
        })
        .collect();
    assert_eq!(params, [1, 2, 3, 4, 5, 6, 7]);
}

#[test]
fn generic_error_after_repeats_is_ambiguous() {
    let t0 = Instant::now();
    // all items out, one of them twice: a generic error may answer the
    // stale copy after the vehicle stored the mission
    let (mut up, _) = start(t0);
    let mut out = Vec::new();
    for s in [0, 1, 2, 2, 3, 4] {
        up.on_message(&vh(), &req_int(s), t0, &mut out);
    }
    up.on_message(
        &vh(),
        &vack(MavMissionResult::MAV_MISSION_ERROR),
        t0,
        &mut out,
    );
    assert!(!up.is_done(), "ambiguous: keep waiting");
    let mut now = t0;
    while !up.is_done() {
        now += Duration::from_millis(Params::default().retry_timeout_ms);
        up.on_timeout(now, &mut out);
    }
    assert!(matches!(
        up.take_outcome(),
        Some(Err(MissionError::NoFinalAck { count: 5, .. }))
    ));
    // a clean transfer's error is the vehicle's verdict
    let (mut up, _) = start(t0);
    for s in 0..5 {
        up.on_message(&vh(), &req_int(s), t0, &mut out);
    }
    up.on_message(
        &vh(),
        &vack(MavMissionResult::MAV_MISSION_ERROR),
        t0,
        &mut out,
    );
    assert_eq!(
        up.take_outcome(),
        Some(Err(MissionError::VehicleError { last_seq: Some(4) }))
    );
}

#[test]
fn cancel_sends_ack_cancelled() {
    let t0 = Instant::now();
    let (mut up, _) = start(t0);
    let mut out = Vec::new();
    up.cancel(t0, &mut out);
    assert!(matches!(&out[..], [MavMessage::MISSION_ACK(a)]
        if a.mavtype == MavMissionResult::MAV_MISSION_OPERATION_CANCELLED && a.target_system == 1));
    assert_eq!(up.take_outcome(), Some(Err(MissionError::Cancelled)));
    out.clear();
    up.on_message(&vh(), &req_int(0), t0, &mut out);
    assert!(out.is_empty(), "finished machines stay quiet");
}

#[test]
fn bad_missions_are_refused() {
    let t0 = Instant::now();
    let mut out = Vec::new();
    let mut it = items();
    it[2].seq = 7;
    let e = Uploader::new(
        &it,
        peers(),
        MavMissionType::MAV_MISSION_TYPE_MISSION,
        Params::default(),
        t0,
        &mut out,
    );
    assert_eq!(
        e.err(),
        Some(MissionError::BadNumbering { index: 2, seq: 7 })
    );
    let mut it = items();
    it[1].command = 65000;
    let e = Uploader::new(
        &it,
        peers(),
        MavMissionType::MAV_MISSION_TYPE_MISSION,
        Params::default(),
        t0,
        &mut out,
    );
    assert!(matches!(
        e,
        Err(MissionError::UnknownNumber {
            seq: 1,
            what: "command",
            ..
        })
    ));
    assert!(out.is_empty());
}

fn vcount(n: u16) -> MavMessage {
    MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
        count: n,
        target_system: GCS.0,
        target_component: GCS.1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
        opaque_id: 0,
    })
}

#[test]
fn download_in_order_with_retries_and_duplicates() {
    let t0 = Instant::now();
    let step = Duration::from_millis(Params::default().retry_timeout_ms);
    let planned = items();
    let mut out = Vec::new();
    let mut d = Downloader::new(
        peers(),
        MavMissionType::MAV_MISSION_TYPE_MISSION,
        Params::default(),
        t0,
        &mut out,
    );
    assert!(matches!(&out[..], [MavMessage::MISSION_REQUEST_LIST(_)]));
    out.clear();
    let mut now = t0 + step;
    d.on_timeout(now, &mut out);
    assert!(matches!(&out[..], [MavMessage::MISSION_REQUEST_LIST(_)]));
    out.clear();
    d.on_message(&vh(), &vcount(planned.len() as u16), now, &mut out);
    assert!(matches!(&out[..], [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == 0));
    let wire: Vec<MavMessage> = planned
        .iter()
        .map(|i| {
            let mut w =
                item_to_wire(i, &peers(), MavMissionType::MAV_MISSION_TYPE_MISSION).expect("wire");
            w.target_system = GCS.0;
            w.target_component = GCS.1;
            MavMessage::MISSION_ITEM_INT(w)
        })
        .collect();
    d.on_message(&vh(), &wire[0], now, &mut out);
    d.on_message(&vh(), &wire[0], now, &mut out); // duplicate: ignored
    d.on_message(&vh(), &wire[2], now, &mut out); // out of order: ignored
    now += step;
    out.clear();
    d.on_timeout(now, &mut out);
    assert!(matches!(&out[..], [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == 1));
    for w in &wire[1..] {
        d.on_message(&vh(), w, now, &mut out);
    }
    assert!(
        matches!(out.last(), Some(MavMessage::MISSION_ACK(a)) if a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    let got = d.take_outcome().expect("done").expect("ok");
    assert_eq!(got.retries, 2);
    assert!(same_mission(&planned, &got.items, false));
    // and an empty mission
    let mut d = Downloader::new(
        peers(),
        MavMissionType::MAV_MISSION_TYPE_MISSION,
        Params::default(),
        t0,
        &mut out,
    );
    d.on_message(&vh(), &vcount(0), t0, &mut out);
    assert_eq!(
        d.take_outcome().map(|r| r.map(|d| d.items.len())),
        Some(Ok(0))
    );
}

#[test]
fn legacy_item_conversion() {
    let legacy = MISSION_ITEM_DATA {
        param1: 1.0,
        param2: 2.0,
        param3: 0.0,
        param4: 90.0,
        x: 47.123_456,
        y: 8.5,
        z: 30.0,
        seq: 3,
        command: MavCmd::MAV_CMD_NAV_WAYPOINT,
        target_system: GCS.0,
        target_component: GCS.1,
        frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
        current: 0,
        autocontinue: 1,
        mission_type: MavMissionType::MAV_MISSION_TYPE_MISSION,
    };
    let i = item_from_legacy(&legacy);
    assert_eq!(i.seq, 3);
    assert_eq!(i.command, 16);
    assert_eq!(i.frame, 3);
    // f32 holds ~7 significant digits: the latitude survives to ~4e-6 deg
    assert!((f64::from(i.x) / 1e7 - 47.123_456).abs() < 5e-6);
    assert_eq!(i.y, 85_000_000);
}

/// A pure model of an autopilot's side of the upload for the seeded
/// discrete-event runs below: PX4 asks with MISSION_REQUEST_INT and
/// re-ACKs a repeated last item; ArduPilot asks with the legacy
/// MISSION_REQUEST and answers unexpected items with INVALID_SEQUENCE.
struct ModelVehicle {
    ardupilot: bool,
    count: Option<u16>,
    items: Vec<MISSION_ITEM_INT_DATA>,
    stored: Vec<MISSION_ITEM_INT_DATA>,
    last_rx: Duration,
    tries: u32,
}

impl ModelVehicle {
    const REREQUEST: Duration = Duration::from_millis(250);

    fn request(&self, seq: u16) -> MavMessage {
        if self.ardupilot {
            req_legacy(seq)
        } else {
            req_int(seq)
        }
    }

    fn on_message(&mut self, m: &MavMessage, t: Duration, out: &mut Vec<MavMessage>) {
        match m {
            MavMessage::MISSION_COUNT(c) => match self.count {
                None => {
                    self.count = Some(c.count);
                    self.items.clear();
                    self.last_rx = t;
                    self.tries = 0;
                    out.push(self.request(0));
                }
                Some(_) if self.items.is_empty() => out.push(self.request(0)),
                Some(_) => {}
            },
            MavMessage::MISSION_ITEM_INT(i) => match self.count {
                Some(n) if usize::from(i.seq) == self.items.len() => {
                    self.items.push(i.clone());
                    self.last_rx = t;
                    self.tries = 0;
                    if self.items.len() == usize::from(n) {
                        self.stored = std::mem::take(&mut self.items);
                        self.count = None;
                        out.push(vack(MavMissionResult::MAV_MISSION_ACCEPTED));
                    } else {
                        out.push(self.request(self.items.len() as u16));
                    }
                }
                Some(_) => {
                    if self.ardupilot {
                        out.push(vack(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE));
                    }
                }
                None => {
                    // PX4 ACKs a repeated last item again; otherwise
                    // PX4 says "no transfer in progress", and ArduPilot
                    // answers every item outside an upload so.
                    if !self.ardupilot
                        && !self.stored.is_empty()
                        && usize::from(i.seq) + 1 == self.stored.len()
                    {
                        out.push(vack(MavMissionResult::MAV_MISSION_ACCEPTED));
                    } else {
                        out.push(vack(MavMissionResult::MAV_MISSION_ERROR));
                    }
                }
            },
            _ => {}
        }
    }

    fn deadline(&self) -> Option<Duration> {
        self.count.map(|_| self.last_rx + Self::REREQUEST)
    }

    fn on_timeout(&mut self, t: Duration, out: &mut Vec<MavMessage>) {
        self.tries += 1;
        self.last_rx = t;
        if self.tries > 20 {
            self.count = None;
            out.push(vack(MavMissionResult::MAV_MISSION_ERROR));
        } else {
            out.push(self.request(self.items.len() as u16));
        }
    }
}

/// One upload through a seeded lossy channel (latency 20-60 ms, `loss`
/// each way, 5 % duplicates) on a virtual clock. Returns the outcome,
/// the virtual duration and what the vehicle stored.
fn lossy_upload(
    ardupilot: bool,
    loss: f64,
    seed: u64,
) -> (
    Result<UploadReport, MissionError>,
    Duration,
    Vec<MISSION_ITEM_INT_DATA>,
) {
    use rand::rngs::StdRng;
    use rand::{Rng, SeedableRng};
    use std::cmp::Reverse;
    use std::collections::BinaryHeap;

    let mut rng = StdRng::seed_from_u64(seed);
    let base = Instant::now();
    let planned = items();
    let mut out = Vec::new();
    let mut up = Uploader::new(
        &planned,
        peers(),
        MavMissionType::MAV_MISSION_TYPE_MISSION,
        Params::default(),
        base,
        &mut out,
    )
    .expect("valid");
    let mut veh = ModelVehicle {
        ardupilot,
        count: None,
        items: Vec::new(),
        stored: Vec::new(),
        last_rx: Duration::ZERO,
        tries: 0,
    };
    // (arrival time, tie-break, to vehicle?, message)
    let mut heap: BinaryHeap<Reverse<(Duration, u64, bool, usize)>> = BinaryHeap::new();
    let mut msgs: Vec<MavMessage> = Vec::new();
    let mut n = 0u64;
    let mut send = |t: Duration,
                    to_vehicle: bool,
                    batch: &mut Vec<MavMessage>,
                    heap: &mut BinaryHeap<Reverse<(Duration, u64, bool, usize)>>,
                    msgs: &mut Vec<MavMessage>,
                    rng: &mut StdRng| {
        for m in batch.drain(..) {
            let copies = if rng.random_bool(0.05) { 2 } else { 1 };
            for _ in 0..copies {
                if rng.random_bool(loss) {
                    continue;
                }
                let latency = Duration::from_millis(rng.random_range(20..60));
                msgs.push(m.clone());
                n += 1;
                heap.push(Reverse((t + latency, n, to_vehicle, msgs.len() - 1)));
            }
        }
    };
    let mut t = Duration::ZERO;
    send(t, true, &mut out, &mut heap, &mut msgs, &mut rng);
    while !up.is_done() {
        assert!(t < Duration::from_secs(300), "seed {seed}: no end");
        let gcs_d = up.deadline().map(|d| d - base).unwrap_or(Duration::MAX);
        let veh_d = veh.deadline().unwrap_or(Duration::MAX);
        let msg_d = heap
            .peek()
            .map(|Reverse((a, ..))| *a)
            .unwrap_or(Duration::MAX);
        let mut batch = Vec::new();
        if msg_d <= gcs_d && msg_d <= veh_d {
            let Some(Reverse((at, _, to_vehicle, idx))) = heap.pop() else {
                break;
            };
            t = at;
            if to_vehicle {
                veh.on_message(&msgs[idx], t, &mut batch);
                send(t, false, &mut batch, &mut heap, &mut msgs, &mut rng);
            } else {
                up.on_message(&vh(), &msgs[idx], base + t, &mut batch);
                send(t, true, &mut batch, &mut heap, &mut msgs, &mut rng);
            }
        } else if gcs_d <= veh_d {
            t = gcs_d;
            up.on_timeout(base + t, &mut batch);
            send(t, true, &mut batch, &mut heap, &mut msgs, &mut rng);
        } else {
            t = veh_d;
            veh.on_timeout(t, &mut batch);
            send(t, false, &mut batch, &mut heap, &mut msgs, &mut rng);
        }
    }
    let outcome = up.take_outcome().expect("finished");
    (outcome, t, veh.stored)
}

#[test]
fn seeded_lossy_uploads_complete_and_deliver_exact_items() {
    let planned = items();
    for ardupilot in [false, true] {
        let mut times = Vec::new();
        let mut retries = 0;
        let mut no_final_ack = 0;
        for seed in 0..300 {
            let (outcome, t, stored) = lossy_upload(ardupilot, 0.3, seed);
            match outcome {
                Ok(report) => retries += report.retries,
                // the vehicle stored the mission but its ACK was lost:
                // the actor reads the mission back (checked just below)
                Err(MissionError::NoFinalAck { count: 5, .. }) => no_final_ack += 1,
                Err(e) => panic!("ardupilot={ardupilot} seed {seed}: {e}"),
            }
            let got: Vec<MissionItem> = stored.iter().map(item_from_wire).collect();
            assert!(
                same_mission(&planned, &got, false),
                "seed {seed}: vehicle holds other items"
            );
            times.push(t.as_secs_f64());
        }
        let (median, max) = crate::stats::median_max(&times).expect("300 uploads timed");
        println!(
            "ardupilot={ardupilot}: 300/300 seeded uploads stored, {no_final_ack} without final ACK; \
             virtual median {median:.2} s, max {max:.2} s, {retries} retries"
        );
        // PX4 re-ACKs a repeated last item, so three resends lose the ACK
        // only with p = 0.51^4 (7 %) after the first was lost (30 %);
        // ArduPilot never re-ACKs: about 30 % of uploads need the read-back.
        if ardupilot {
            assert!((50..=130).contains(&no_final_ack), "{no_final_ack}");
        } else {
            assert!(no_final_ack < 40, "{no_final_ack}");
        }
        // 5 items, 30 % loss each way: a few round trips of 40-120 ms plus
        // 250-400 ms timeouts; these bounds would catch a stall or a
        // retry storm.
        assert!(
            median < 2.5 && max < 12.0,
            "median {median:.2} s, max {max:.2} s"
        );
        assert!(retries > 0);
    }
    // and a clean channel never retries
    let (outcome, t, _) = lossy_upload(false, 0.0, 1);
    let r = outcome.expect("clean");
    assert_eq!(r.retries, 0);
    assert!(t < Duration::from_millis(700), "{t:?}");
}
