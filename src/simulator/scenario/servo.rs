//! Servoing at the shot in the scenario: the vehicle holding at the shot
//! is switched to guided control over MAVLink as a ground station would
//! (gimbal control taken with DO_GIMBAL_MANAGER_CONFIGURE, a setpoint
//! stream of SET_POSITION_TARGET_GLOBAL_INT before DO_SET_MODE to PX4's
//! OFFBOARD, the stream kept up on every frame), the [`crate::refine::Servo`]
//! fed one frame per `frame_s` with the measurement's latency, and the
//! photo taken when it settles.
//!
//! Positions go as GLOBAL_INT (AMSL) on both autopilots: the daemon's
//! local frame is centred on home and PX4's LOCAL_NED on its EKF origin,
//! which a ground station does not know; latitude and longitude in 1e-7
//! degrees are about a centimetre.

use mavlink::MavHeader;
use mavlink::dialects::common::{COMMAND_LONG_DATA, MavCmd, MavMessage, MavResult};
use nalgebra::Isometry3;
use serde::Serialize;

use crate::camera::Camera;
use crate::mission::plan::{Home, Target};
use crate::refine::{
    Context, PoseDifference, ServoFrame, ServoSample, ServoStep, ServoStop, Session,
    pose_difference, shot_error,
};

use super::params::ServoDriverParams;
use super::sim::Sim;

const GCS: MavHeader = MavHeader {
    system_id: 255,
    component_id: 190,
    sequence: 0,
};

/// What servoing did in one trial.
#[derive(Debug, Clone, Serialize)]
pub struct ServoReport {
    /// How it ended (`settled`, `best_available`, `timeout`, `live_lost`,
    /// `refused`, or
    /// `not_engaged` when the autopilot refused guided control).
    pub stop: String,
    /// Why, when it did not settle or time out.
    pub reason: Option<String>,
    /// Simulated seconds of servoing (from the switch to the photo).
    pub seconds: f64,
    /// Frames processed.
    pub frames: usize,
    /// Setpoints moved.
    pub moves: usize,
    /// The photo's shot error, % of the diagonal (measured on it).
    pub photo_shot_error_pct: Option<f64>,
    /// The photo's camera against the hidden pose (the judge).
    pub photo_position_error_m: Option<f64>,
    /// Every frame.
    pub samples: Vec<ServoSample>,
    /// The judge, per frame: the vehicle's true position minus the
    /// reported one (what the offset estimate follows, up to the
    /// georeference's constant error), NED m.
    pub true_offset_ned_m: Vec<[f64; 3]>,
    /// The judge, per frame: the camera's distance from the hidden pose, m.
    pub true_position_error_m: Vec<f64>,
}

fn command(sim: &mut Sim, command: MavCmd, p: [f32; 7]) -> MavResult {
    let out = sim.ap.handle(
        &GCS,
        &MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: p[0],
            param2: p[1],
            param3: p[2],
            param4: p[3],
            param5: p[4],
            param6: p[5],
            param7: p[6],
            command,
            target_system: sim.ap.params().system_id,
            target_component: sim.ap.params().component_id,
            confirmation: 0,
        }),
    );
    out.iter()
        .find_map(|m| match m {
            MavMessage::COMMAND_ACK(a) if a.command == command => Some(a.result),
            _ => None,
        })
        .unwrap_or(MavResult::MAV_RESULT_FAILED)
}

fn send_setpoint(sim: &mut Sim, t: &Target, home: &Home) {
    // The daemon's own message (what LinkHandle::guide streams).
    let m = crate::vehicle::guided_setpoint_message(
        &crate::vehicle::GuidedSetpoint::at_target(t, home),
        (sim.ap.params().system_id, sim.ap.params().component_id),
    );
    let _ = sim.ap.handle(&GCS, &m);
}

fn point_gimbal(sim: &mut Sim, pitch_deg: f64) -> MavResult {
    command(
        sim,
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_PITCHYAW,
        [pitch_deg as f32, 0.0, f32::NAN, f32::NAN, 0.0, 0.0, 0.0],
    )
}

/// Servoes from `holding` (the target the vehicle holds at) until the
/// servo stops; the photo is judged against `hidden` (the true camera of
/// the desired shot).
#[allow(clippy::too_many_arguments)]
pub(super) fn servo_at_shot(
    sim: &mut Sim,
    session: &Session,
    holding: Target,
    ctx: &Context<'_>,
    camera: &Camera,
    hidden: &Isometry3<f64>,
    p: &ServoDriverParams,
) -> (ServoReport, Option<PoseDifference>) {
    let home = *ctx.home;
    let mut rep = ServoReport {
        stop: String::new(),
        reason: None,
        seconds: 0.0,
        frames: 0,
        moves: 0,
        photo_shot_error_pct: None,
        photo_position_error_m: None,
        samples: Vec::new(),
        true_offset_ned_m: Vec::new(),
        true_position_error_m: Vec::new(),
    };
    // Gimbal control for this ground station (the mission's own items
    // hand it to the autopilot).
    let gimbal = command(
        sim,
        MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
        [-2.0, -2.0, -1.0, -1.0, 0.0, 0.0, 0.0],
    ) == MavResult::MAV_RESULT_ACCEPTED;
    // A stream of the held setpoint before the switch, as PX4 needs.
    let lead = sim.ap.params().offboard_proof_s + 2.0 * p.frame_s;
    let mut waited = 0.0;
    while waited < lead {
        send_setpoint(sim, &holding, &home);
        sim.advance(p.frame_s);
        waited += p.frame_s;
    }
    send_setpoint(sim, &holding, &home);
    let mode = shotpilot_sim::autopilot::Mode::Offboard;
    let (base, custom, sub) = match sim.ap.params().flavour {
        shotpilot_sim::autopilot::Flavour::Px4 => (1.0, 6.0, 0.0),
        shotpilot_sim::autopilot::Flavour::ArduPilot => (1.0, 4.0, 0.0),
    };
    let r = command(
        sim,
        MavCmd::MAV_CMD_DO_SET_MODE,
        [base, custom, sub, 0.0, 0.0, 0.0, 0.0],
    );
    if r != MavResult::MAV_RESULT_ACCEPTED || sim.ap.mode() != mode {
        rep.stop = "not_engaged".into();
        rep.reason = Some(format!("guided control refused: {r:?}"));
        return (rep, None);
    }
    let mut servo = session.servo(holding, p.servo);
    let t0 = sim.t;
    let mut pitch_sent = holding.gimbal_pitch_deg;
    let stop = loop {
        let image = sim.render();
        let v = sim.ap.vehicle();
        let frame_t = sim.t;
        let reported = v.p_ned();
        let yaw = v.yaw().to_degrees();
        let pitch = v.gimbal_angles().0.to_degrees();
        let speed = v.v_ned().norm();
        rep.true_offset_ned_m.push(v.position_error().into());
        rep.true_position_error_m
            .push(pose_difference(hidden, &sim.true_camera()).position_m);
        // The measurement takes its time; the vehicle flies on meanwhile.
        sim.advance(p.latency_s);
        send_setpoint(sim, servo.setpoint(), &home);
        let step = servo.on_frame(
            &ServoFrame {
                image: &image,
                t_s: frame_t,
                reported_ned_m: Some(reported),
                reported_yaw_deg: Some(yaw),
                reported_pitch_deg: Some(pitch),
                reported_speed_m_s: Some(speed),
            },
            Some(camera),
            ctx,
        );
        rep.frames += 1;
        match step {
            ServoStep::Hold => send_setpoint(sim, servo.setpoint(), &home),
            ServoStep::Move(t) => {
                rep.moves += 1;
                send_setpoint(sim, &t, &home);
                if gimbal && (t.gimbal_pitch_deg - pitch_sent).abs() > 0.01 {
                    point_gimbal(sim, t.gimbal_pitch_deg);
                    pitch_sent = t.gimbal_pitch_deg;
                }
            }
            ServoStep::Done(s) => break s,
        }
        sim.advance((p.frame_s - p.latency_s).max(sim.dt));
    };
    rep.seconds = sim.t - t0;
    rep.stop = stop.name().into();
    let judged = match &stop {
        ServoStop::Settled | ServoStop::BestAvailable | ServoStop::Timeout => {
            // The photo, now.
            let photo = sim.render();
            rep.photo_shot_error_pct = shot_error(
                &photo,
                session.desired_picture(),
                session.desired_mask(),
                Some(camera),
                &session.params().error,
            )
            .ok()
            .map(|e| e.corner_error_pct);
            let d = pose_difference(hidden, &sim.true_camera());
            rep.photo_position_error_m = Some(d.position_m);
            Some(d)
        }
        ServoStop::LiveLost(r) | ServoStop::Refused(r) => {
            rep.reason = Some(r.clone());
            None
        }
    };
    rep.samples = servo.samples().to_vec();
    // Back to a position hold where it is.
    let _ = command(
        sim,
        MavCmd::MAV_CMD_DO_SET_MODE,
        hold_mode(sim.ap.params().flavour),
    );
    (rep, judged)
}

fn hold_mode(f: shotpilot_sim::autopilot::Flavour) -> [f32; 7] {
    match f {
        // AUTO (4) . LOITER (3)
        shotpilot_sim::autopilot::Flavour::Px4 => [1.0, 4.0, 3.0, 0.0, 0.0, 0.0, 0.0],
        // LOITER
        shotpilot_sim::autopilot::Flavour::ArduPilot => [1.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    }
}
