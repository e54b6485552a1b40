//! The operator's commands in the link actor: mission transfers started (behind
//! the mission gate) and delivered (an upload read back when its final ACK was
//! lost), COMMAND_LONG sent and its ACK matched, the stop, gimbal control given
//! back after a mission.

use std::time::{Duration, Instant};

use mavlink::dialects::common::{MavCmd, MavMessage, MavMissionType, MavResult};
use tokio::sync::oneshot;
use tracing::{info, info_span, warn};

use super::pending::{PendingCommand, Reply, cmd_number, command_long};
use super::state::Actor;
use super::transfer::{DownPurpose, Next, Transfer};
use crate::clock;
use crate::mission::Flavour;
use crate::mission::upload::{Downloader, Uploader};
use crate::vehicle::command::{Command, HoldAck};
use crate::vehicle::error::LinkError;
use crate::vehicle::modes::{FlightMode, ardupilot_mode_name, mode_params, px4_mode_name};

impl Actor {
    /// Starts our transfer in the gate; false (and the command kept for
    /// later) while another station's runs.
    fn gate_or_defer(&mut self, now: Instant, cmd: Command) -> Option<Command> {
        if self.router.begin_own(now) {
            return Some(cmd);
        }
        info!("another station's mission transfer is running; ours waits for it to end");
        self.deferred.push(cmd);
        None
    }

    pub(super) fn deliver_if_done(&mut self) {
        if !self.transfer.as_ref().is_some_and(Transfer::is_done) {
            return;
        }
        let Some(t) = self.transfer.take() else {
            return;
        };
        let now = clock::now();
        let peers = self.peers().map(|(p, _)| p);
        if let Next::Verify {
            items,
            skip_home,
            report,
            reply,
            span,
            attempt,
        } = t.deliver(now, peers.is_some())
            && let Some(peers) = peers
        {
            let machine = Downloader::new(
                peers,
                MavMissionType::MAV_MISSION_TYPE_MISSION,
                self.transfer_params,
                now,
                &mut self.out,
            );
            self.transfer = Some(Transfer::Down {
                machine,
                purpose: DownPurpose::Verify {
                    items,
                    skip_home,
                    report,
                    reply,
                    attempt,
                    since: now,
                },
                span,
            });
        }
    }

    pub(super) fn on_command_ack(
        &mut self,
        command: MavCmd,
        result: MavResult,
        target_system: u8,
        now: Instant,
    ) {
        if target_system != 0 && target_system != self.params.system_id {
            return;
        }
        let timeout = Duration::from_millis(self.params.command_timeout_ms);
        // The stop and the other command never share a command id (a
        // DO_SET_MODE in flight gives way to a stop), so the ACK is theirs.
        for slot in [&mut self.stop, &mut self.command] {
            let Some(pending) = slot else {
                continue;
            };
            if pending.data.command != command {
                continue;
            }
            if result == MavResult::MAV_RESULT_IN_PROGRESS {
                pending.deadline = now + timeout;
                return;
            }
            if let Some(p) = slot.take() {
                let ok = result == MavResult::MAV_RESULT_ACCEPTED;
                info!(command = cmd_number(command), ok, "command acknowledged");
                if ok {
                    p.reply.accepted(result);
                } else {
                    p.reply.fail(LinkError::CommandRejected {
                        command: cmd_number(command),
                        result: format!("{result:?}"),
                    });
                }
            }
            return;
        }
    }

    pub(super) async fn on_command(&mut self, cmd: Command) {
        let now = clock::now();
        match cmd {
            Command::UploadMission { items, reply } => {
                if self.transfer.is_some() {
                    let _ = reply.send(Err(LinkError::Busy {
                        what: "mission transfer",
                    }));
                    return;
                }
                let Some(Command::UploadMission { items, reply }) =
                    self.gate_or_defer(now, Command::UploadMission { items, reply })
                else {
                    return;
                };
                let Some((peers, vehicle)) = self.peers() else {
                    let _ = reply.send(Err(LinkError::NoVehicle));
                    return;
                };
                let flavour = vehicle.flavour;
                let span = info_span!(
                    "mission_upload",
                    items = items.len(),
                    vehicle = peers.target_system
                );
                let made = Uploader::new(
                    &items,
                    peers,
                    MavMissionType::MAV_MISSION_TYPE_MISSION,
                    self.transfer_params,
                    now,
                    &mut self.out,
                );
                match made {
                    Ok(machine) => {
                        span.in_scope(|| info!("MISSION_COUNT sent"));
                        self.transfer = Some(Transfer::Up {
                            machine,
                            items,
                            skip_home: flavour == Some(Flavour::ArduPilot),
                            reply,
                            span,
                        });
                    }
                    Err(e) => {
                        let _ = reply.send(Err(e.into()));
                    }
                }
            }
            Command::DownloadMission { reply } => {
                if self.transfer.is_some() {
                    let _ = reply.send(Err(LinkError::Busy {
                        what: "mission transfer",
                    }));
                    return;
                }
                let Some(Command::DownloadMission { reply }) =
                    self.gate_or_defer(now, Command::DownloadMission { reply })
                else {
                    return;
                };
                let Some((peers, _)) = self.peers() else {
                    let _ = reply.send(Err(LinkError::NoVehicle));
                    return;
                };
                let span = info_span!("mission_download", vehicle = peers.target_system);
                let machine = Downloader::new(
                    peers,
                    MavMissionType::MAV_MISSION_TYPE_MISSION,
                    self.transfer_params,
                    now,
                    &mut self.out,
                );
                self.transfer = Some(Transfer::Down {
                    machine,
                    purpose: DownPurpose::Reply(reply),
                    span,
                });
            }
            Command::CancelTransfer { reply } => {
                let running = match self.transfer.take() {
                    Some(mut t) => {
                        t.cancel(now, &mut self.out);
                        t.deliver(now, false);
                        true
                    }
                    None => false,
                };
                let _ = reply.send(Ok(running));
            }
            Command::Arm { arm, reply } => {
                info!(arm, "operator: arm/disarm");
                self.start_command(
                    MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
                    [if arm { 1.0 } else { 0.0 }, 0.0, 0.0],
                    Reply::Done(reply),
                    now,
                );
            }
            Command::SetMode { mode, reply } => {
                info!(?mode, "operator: set mode");
                let flavour = self.vehicle.borrow().flavour;
                match flavour {
                    Some(f) => {
                        let (base, main, sub) = mode_params(f, mode);
                        self.start_command(
                            MavCmd::MAV_CMD_DO_SET_MODE,
                            [base, main, sub],
                            Reply::Done(reply),
                            now,
                        );
                    }
                    None => {
                        let autopilot = self.vehicle.borrow().autopilot;
                        let _ = reply.send(Err(if self.vehicle.borrow().system_id.is_none() {
                            LinkError::NoVehicle
                        } else {
                            LinkError::UnsupportedMode { mode, autopilot }
                        }));
                    }
                }
            }
            Command::Hold { reply } => self.start_stop(reply, now),
            Command::StartMission { reply } => {
                info!("operator: start mission");
                self.start_command(
                    MavCmd::MAV_CMD_MISSION_START,
                    [0.0, 0.0, 0.0],
                    Reply::Done(reply),
                    now,
                );
            }
            Command::Long {
                command,
                params,
                target_component,
                reply,
            } => {
                info!(command = cmd_number(command), ?params, "command");
                self.start_command7(command, params, target_component, Reply::Done(reply), now);
            }
            Command::Guide { setpoint, reply } => {
                self.on_guide(setpoint, reply, now);
                self.flush().await;
            }
            Command::RequestMessage {
                message_id,
                target_component,
                reply,
            } => match self.peers() {
                Some((peers, _)) => {
                    self.out.push(MavMessage::COMMAND_LONG(command_long(
                        MavCmd::MAV_CMD_REQUEST_MESSAGE,
                        [message_id as f32, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                        peers.target_system,
                        target_component,
                    )));
                    let _ = reply.send(Ok(()));
                }
                None => {
                    let _ = reply.send(Err(LinkError::NoVehicle));
                }
            },
        }
        self.flush().await;
    }

    /// Gimbal control taken for a mission goes back once the vehicle
    /// reports that mission complete (MISSION_CURRENT.mission_state 5 after
    /// 3, active). Sent once, without waiting for the ACK.
    pub(super) fn gimbal_after_mission(&mut self, state: u8) {
        const ACTIVE: u8 = 3;
        const COMPLETE: u8 = 5;
        let g = self.gimbal_control.borrow().clone();
        if !(g.held && g.for_mission) {
            return;
        }
        if state == ACTIVE && !g.mission_seen_active {
            self.gimbal_control
                .send_modify(|g| g.mission_seen_active = true);
        } else if state == COMPLETE && g.mission_seen_active {
            let Some((peers, _)) = self.peers() else {
                return;
            };
            let target = self
                .gimbal_manager
                .borrow()
                .map_or(peers.target_component, |s| s.value.manager_component);
            let p = crate::vehicle::handle::release_params(g.device_id);
            self.out.push(MavMessage::COMMAND_LONG(command_long(
                MavCmd::MAV_CMD_DO_GIMBAL_MANAGER_CONFIGURE,
                p,
                peers.target_system,
                target,
            )));
            info!("mission complete: gimbal control released");
            self.gimbal_control.send_modify(|g| {
                g.held = false;
                g.for_mission = false;
                g.mission_seen_active = false;
                g.last_event = Some("mission complete: released gimbal control".into());
            });
        }
    }

    fn start_command(&mut self, command: MavCmd, p: [f32; 3], reply: Reply, now: Instant) {
        self.start_command7(
            command,
            [p[0], p[1], p[2], 0.0, 0.0, 0.0, 0.0],
            None,
            reply,
            now,
        );
    }

    fn start_command7(
        &mut self,
        command: MavCmd,
        p: [f32; 7],
        target_component: Option<u8>,
        reply: Reply,
        now: Instant,
    ) {
        if self.command.is_some() {
            reply.fail(LinkError::Busy { what: "command" });
            return;
        }
        // Its ACK could not be told from the stop's.
        if self
            .stop
            .as_ref()
            .is_some_and(|s| s.data.command == command)
        {
            reply.fail(LinkError::Busy { what: "stop" });
            return;
        }
        let Some((peers, _)) = self.peers() else {
            reply.fail(LinkError::NoVehicle);
            return;
        };
        let data = command_long(
            command,
            p,
            peers.target_system,
            target_component.unwrap_or(peers.target_component),
        );
        self.out.push(MavMessage::COMMAND_LONG(data.clone()));
        self.command = Some(PendingCommand {
            data,
            attempts: 1,
            deadline: now + Duration::from_millis(self.params.command_timeout_ms),
            reply,
        });
    }

    /// The operator's stop: DO_SET_MODE to the hold mode, sent now whatever
    /// else waits for an ACK. A DO_SET_MODE in flight gives way (its waiter
    /// gets [`LinkError::Superseded`]): the two ACKs could not be told apart.
    fn start_stop(&mut self, reply: oneshot::Sender<Result<HoldAck, LinkError>>, now: Instant) {
        info!("operator: stop (hold)");
        if self.guided.take().is_some() {
            info!("guided setpoint stream stopped by the stop");
        }
        if self.stop.is_some() {
            let _ = reply.send(Err(LinkError::Busy { what: "stop" }));
            return;
        }
        let flavour = self.vehicle.borrow().flavour;
        let (Some(flavour), Some((peers, _))) = (flavour, self.peers()) else {
            let _ = reply.send(Err(LinkError::NoVehicle));
            return;
        };
        if self
            .command
            .as_ref()
            .is_some_and(|c| c.data.command == MavCmd::MAV_CMD_DO_SET_MODE)
            && let Some(c) = self.command.take()
        {
            warn!("a mode change in flight gives way to the stop");
            c.reply.fail(LinkError::Superseded {
                command: cmd_number(MavCmd::MAV_CMD_DO_SET_MODE),
            });
        }
        let (base, main, sub) = mode_params(flavour, FlightMode::Hold);
        let mode = match flavour {
            Flavour::Px4 => px4_mode_name(((sub as u32) << 24) | ((main as u32) << 16)),
            Flavour::ArduPilot => ardupilot_mode_name(main as u32),
        };
        let data = command_long(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [base, main, sub, 0.0, 0.0, 0.0, 0.0],
            peers.target_system,
            peers.target_component,
        );
        self.out.push(MavMessage::COMMAND_LONG(data.clone()));
        self.stop = Some(PendingCommand {
            data,
            attempts: 1,
            deadline: now + Duration::from_millis(self.params.command_timeout_ms),
            reply: Reply::Hold { mode, reply },
        });
    }
}
