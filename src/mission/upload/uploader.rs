//! The upload state machine (see the module doc of [`super`]).

// The legacy MISSION_REQUEST is deprecated in the dialect; ArduPilot sends it.
#![allow(deprecated)]

use std::time::Instant;

use mavlink::MavHeader;
use mavlink::dialects::common::{
    MISSION_COUNT_DATA, MISSION_ITEM_INT_DATA, MavMessage, MavMissionResult, MavMissionType,
};

use super::wire::item_to_wire;
use super::{Machine, MissionError, Params, Peers, Stage, Transfer, UploadReport};
use crate::mission::plan::MissionItem;

#[derive(Debug, Clone, Copy, PartialEq)]
enum UpState {
    WaitFirstRequest,
    Sending { last_sent: u16 },
    Done,
}

/// The upload state machine (see the module doc).
#[derive(Debug)]
pub struct Uploader {
    transfer: Transfer,
    items: Vec<MISSION_ITEM_INT_DATA>,
    sent: Vec<bool>,
    state: UpState,
    report: UploadReport,
    outcome: Option<Result<UploadReport, MissionError>>,
}

impl Uploader {
    /// Starts an upload; pushes `MISSION_COUNT` (or nothing for a bad mission, whose error is the outcome) to `out`.
    pub fn new(
        items: &[MissionItem],
        peers: Peers,
        mission_type: MavMissionType,
        params: Params,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) -> Result<Self, MissionError> {
        let count = u16::try_from(items.len())
            .map_err(|_| MissionError::TooManyItems { count: items.len() })?;
        if count == u16::MAX {
            return Err(MissionError::TooManyItems { count: items.len() });
        }
        let mut wire = Vec::with_capacity(items.len());
        for (index, item) in items.iter().enumerate() {
            if usize::from(item.seq) != index {
                return Err(MissionError::BadNumbering {
                    index,
                    seq: item.seq,
                });
            }
            wire.push(item_to_wire(item, &peers, mission_type)?);
        }
        let up = Self {
            transfer: Transfer::new(peers, mission_type, params, now),
            sent: vec![false; wire.len()],
            items: wire,
            state: UpState::WaitFirstRequest,
            report: UploadReport {
                items: count,
                retries: 0,
                repeats: 0,
                ignored: 0,
                seconds: 0.0,
                verified_by_download: false,
            },
            outcome: None,
        };
        out.push(up.count_message());
        Ok(up)
    }

    fn count_message(&self) -> MavMessage {
        let t = &self.transfer;
        MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: self.report.items,
            target_system: t.peers.target_system,
            target_component: t.peers.target_component,
            mission_type: t.mission_type,
            opaque_id: 0,
        })
    }

    /// When the machine next wants [`Self::on_timeout`] (None once finished).
    pub fn deadline(&self) -> Option<Instant> {
        (self.state != UpState::Done).then_some(self.transfer.deadline)
    }

    /// Whether the upload has finished (the outcome may already be taken).
    pub fn is_done(&self) -> bool {
        self.state == UpState::Done
    }

    /// The result, once finished (taken once).
    pub fn take_outcome(&mut self) -> Option<Result<UploadReport, MissionError>> {
        self.outcome.take()
    }

    /// The counters so far (after a failure too), with the time since the start.
    pub fn report_at(&self, now: Instant) -> UploadReport {
        UploadReport {
            seconds: self.transfer.seconds(now),
            ..self.report
        }
    }

    fn last_seq(&self) -> Option<u16> {
        match self.state {
            UpState::Sending { last_sent } => Some(last_sent),
            _ => None,
        }
    }

    /// Whether every item went out at least once.
    fn all_sent(&self) -> bool {
        self.sent.last().copied().unwrap_or(false)
    }

    fn answer_request(&mut self, seq: u16, now: Instant, out: &mut Vec<MavMessage>) {
        let Some(item) = self.items.get(usize::from(seq)) else {
            self.report.ignored += 1;
            return;
        };
        out.push(MavMessage::MISSION_ITEM_INT(item.clone()));
        let idx = usize::from(seq);
        if self.sent[idx] {
            self.report.repeats += 1;
        }
        self.sent[idx] = true;
        self.state = UpState::Sending { last_sent: seq };
        self.transfer.progress(now);
    }

    /// Feeds one received message; pushes replies to `out`.
    pub fn on_message(
        &mut self,
        header: &MavHeader,
        msg: &MavMessage,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) {
        if self.state == UpState::Done || !self.transfer.peers.is_from_target(header) {
            return;
        }
        let t = &self.transfer;
        match msg {
            MavMessage::MISSION_REQUEST_INT(r)
                if t.is_ours(r.mission_type, r.target_system, r.target_component) =>
            {
                self.answer_request(r.seq, now, out);
            }
            MavMessage::MISSION_REQUEST(r)
                if t.is_ours(r.mission_type, r.target_system, r.target_component) =>
            {
                self.answer_request(r.seq, now, out);
            }
            MavMessage::MISSION_ACK(a)
                if t.is_ours(a.mission_type, a.target_system, a.target_component) =>
            {
                let count = self.report.items;
                match a.mavtype {
                    MavMissionResult::MAV_MISSION_ACCEPTED => {
                        if count == 0 || self.all_sent() {
                            self.finish(Ok(()), now);
                        } else {
                            self.report.ignored += 1;
                        }
                    }
                    MavMissionResult::MAV_MISSION_INVALID_SEQUENCE => self.report.ignored += 1,
                    // Once every item went out and something was sent twice,
                    // a generic error is most likely the autopilot answering
                    // a repeated item after it stored the mission (ArduPilot
                    // always, PX4 for a stale one), possibly while its
                    // ACCEPTED was lost. Keep waiting: the timeouts end in
                    // NoFinalAck and the read-back decides.
                    MavMissionResult::MAV_MISSION_ERROR
                        if self.all_sent()
                            && (self.report.repeats > 0 || self.report.retries > 0) =>
                    {
                        self.report.ignored += 1;
                    }
                    other => {
                        let last = self.last_seq();
                        if let Some(err) = MissionError::from_result(other, last, count) {
                            self.finish(Err(err), now);
                        }
                    }
                }
            }
            _ => {}
        }
    }

    /// Call when [`Self::deadline`] has passed: resends, or fails after `max_retries`.
    pub fn on_timeout(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        super::on_timeout(self, now, out);
    }

    /// Cancels the upload: the outcome becomes [`MissionError::Cancelled`] and
    /// `MISSION_ACK(OPERATION_CANCELLED)` goes to the vehicle.
    pub fn cancel(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        super::cancel(self, now, out);
    }
}

impl Machine for Uploader {
    fn transfer(&mut self) -> &mut Transfer {
        &mut self.transfer
    }

    fn is_done(&self) -> bool {
        self.state == UpState::Done
    }

    fn give_up(&self, consecutive: u32) -> Option<MissionError> {
        let params = &self.transfer.params;
        let final_stage = self.all_sent()
            && matches!(self.state, UpState::Sending { last_sent } if usize::from(last_sent) + 1 == self.items.len());
        if final_stage && consecutive > params.final_ack_retries {
            return Some(MissionError::NoFinalAck {
                count: self.report.items,
                retries: params.final_ack_retries,
            });
        }
        if consecutive > params.max_retries {
            let stage = match self.state {
                UpState::Sending { last_sent } => Stage::AfterItem { seq: last_sent },
                _ => Stage::FirstRequest,
            };
            return Some(MissionError::Timeout {
                stage,
                retries: params.max_retries,
            });
        }
        None
    }

    fn resend(&mut self, out: &mut Vec<MavMessage>) {
        self.report.retries += 1;
        match self.state {
            UpState::WaitFirstRequest => out.push(self.count_message()),
            UpState::Sending { last_sent } => {
                if let Some(item) = self.items.get(usize::from(last_sent)) {
                    out.push(MavMessage::MISSION_ITEM_INT(item.clone()));
                }
            }
            UpState::Done => {}
        }
    }

    fn finish(&mut self, result: Result<(), MissionError>, now: Instant) {
        self.report.seconds = self.transfer.seconds(now);
        self.state = UpState::Done;
        self.outcome = Some(result.map(|()| self.report));
    }
}
