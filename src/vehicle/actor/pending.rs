//! A command waiting for its COMMAND_ACK: who waits for it, its resends, and the
//! COMMAND_LONG it goes out as.

use std::time::{Duration, Instant};

use mavlink::dialects::common::{COMMAND_LONG_DATA, MavCmd, MavMessage, MavResult};
use tokio::sync::oneshot;

use crate::vehicle::command::HoldAck;
use crate::vehicle::error::LinkError;
use crate::vehicle::params::Params;

pub(super) struct PendingCommand {
    pub(super) data: COMMAND_LONG_DATA,
    pub(super) attempts: u32,
    pub(super) deadline: Instant,
    pub(super) reply: Reply,
}

/// Who waits for a command's COMMAND_ACK.
pub(super) enum Reply {
    /// `Ok(())` on ACCEPTED.
    Done(oneshot::Sender<Result<(), LinkError>>),
    /// The operator's stop: the ACK itself, with the mode asked for.
    Hold {
        mode: String,
        reply: oneshot::Sender<Result<HoldAck, LinkError>>,
    },
}

impl Reply {
    pub(super) fn accepted(self, result: MavResult) {
        match self {
            Self::Done(r) => {
                let _ = r.send(Ok(()));
            }
            Self::Hold { mode, reply } => {
                let _ = reply.send(Ok(HoldAck {
                    command: "MAV_CMD_DO_SET_MODE",
                    mode,
                    result: format!("{result:?}"),
                }));
            }
        }
    }

    pub(super) fn fail(self, e: LinkError) {
        match self {
            Self::Done(r) => {
                let _ = r.send(Err(e));
            }
            Self::Hold { reply, .. } => {
                let _ = reply.send(Err(e));
            }
        }
    }
}

/// Resends a command whose ACK is late, or gives up after the link's
/// attempts (the waiter gets [`LinkError::CommandTimeout`]).
pub(super) fn retry_late(
    slot: &mut Option<PendingCommand>,
    params: &Params,
    now: Instant,
    out: &mut Vec<MavMessage>,
) {
    if slot.as_ref().is_some_and(|c| c.deadline <= now)
        && let Some(mut c) = slot.take()
    {
        if c.attempts >= params.command_attempts.max(1) {
            c.reply.fail(LinkError::CommandTimeout {
                command: cmd_number(c.data.command),
                attempts: c.attempts,
            });
        } else {
            c.attempts += 1;
            c.data.confirmation = c.data.confirmation.saturating_add(1);
            c.deadline = now + Duration::from_millis(params.command_timeout_ms);
            out.push(MavMessage::COMMAND_LONG(c.data.clone()));
            *slot = Some(c);
        }
    }
}

pub(super) fn cmd_number(c: MavCmd) -> u16 {
    c as u32 as u16
}

/// A COMMAND_LONG with its seven params in order (first transmission).
pub(super) fn command_long(
    command: MavCmd,
    p: [f32; 7],
    target_system: u8,
    target_component: u8,
) -> COMMAND_LONG_DATA {
    COMMAND_LONG_DATA {
        param1: p[0],
        param2: p[1],
        param3: p[2],
        param4: p[3],
        param5: p[4],
        param6: p[5],
        param7: p[6],
        command,
        target_system,
        target_component,
        confirmation: 0,
    }
}
