//! The download state machine (see the module doc of [`super`]).

// The legacy MISSION_ITEM is deprecated in the dialect; autopilots send it.
#![allow(deprecated)]

use std::time::Instant;

use mavlink::MavHeader;
use mavlink::dialects::common::{
    MISSION_REQUEST_INT_DATA, MISSION_REQUEST_LIST_DATA, MavMessage, MavMissionResult,
    MavMissionType,
};

use super::wire::{item_from_legacy, item_from_wire};
use super::{Download, Machine, MissionError, Params, Peers, Stage, Transfer};
use crate::mission::plan::MissionItem;

#[derive(Debug, Clone, Copy, PartialEq)]
enum DownState {
    WaitCount,
    Receiving { count: u16 },
    Done,
}

/// The download state machine (see the module doc).
#[derive(Debug)]
pub struct Downloader {
    transfer: Transfer,
    items: Vec<MissionItem>,
    state: DownState,
    retries: u32,
    ignored: u32,
    outcome: Option<Result<Download, MissionError>>,
}

impl Downloader {
    /// Starts a download; pushes `MISSION_REQUEST_LIST` to `out`.
    pub fn new(
        peers: Peers,
        mission_type: MavMissionType,
        params: Params,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) -> Self {
        let d = Self {
            transfer: Transfer::new(peers, mission_type, params, now),
            items: Vec::new(),
            state: DownState::WaitCount,
            retries: 0,
            ignored: 0,
            outcome: None,
        };
        out.push(d.request_list());
        d
    }

    fn request_list(&self) -> MavMessage {
        let t = &self.transfer;
        MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
            target_system: t.peers.target_system,
            target_component: t.peers.target_component,
            mission_type: t.mission_type,
        })
    }

    fn request(&self, seq: u16) -> MavMessage {
        let t = &self.transfer;
        MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
            seq,
            target_system: t.peers.target_system,
            target_component: t.peers.target_component,
            mission_type: t.mission_type,
        })
    }

    /// When the machine next wants [`Self::on_timeout`].
    pub fn deadline(&self) -> Option<Instant> {
        (self.state != DownState::Done).then_some(self.transfer.deadline)
    }

    /// Whether the download has finished.
    pub fn is_done(&self) -> bool {
        self.state == DownState::Done
    }

    /// The result, once finished (taken once).
    pub fn take_outcome(&mut self) -> Option<Result<Download, MissionError>> {
        self.outcome.take()
    }

    /// All items are in: acknowledge and finish.
    fn complete(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        out.push(self.transfer.ack(MavMissionResult::MAV_MISSION_ACCEPTED));
        self.finish(Ok(()), now);
    }

    fn accept_item(
        &mut self,
        item: MissionItem,
        count: u16,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) {
        if usize::from(item.seq) != self.items.len() {
            return; // duplicate or out of order: the right one is requested again on timeout
        }
        self.items.push(item);
        self.transfer.progress(now);
        let next = self.items.len() as u16;
        if next >= count {
            self.complete(now, out);
        } else {
            out.push(self.request(next));
        }
    }

    /// Feeds one received message; pushes requests to `out`.
    pub fn on_message(
        &mut self,
        header: &MavHeader,
        msg: &MavMessage,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) {
        if self.state == DownState::Done || !self.transfer.peers.is_from_target(header) {
            return;
        }
        let t = &self.transfer;
        match (self.state, msg) {
            (DownState::WaitCount, MavMessage::MISSION_COUNT(c))
                if t.is_ours(c.mission_type, c.target_system, c.target_component) =>
            {
                self.transfer.progress(now);
                if c.count == 0 {
                    self.complete(now, out);
                } else {
                    self.items.reserve(usize::from(c.count));
                    self.state = DownState::Receiving { count: c.count };
                    out.push(self.request(0));
                }
            }
            (DownState::Receiving { count }, MavMessage::MISSION_ITEM_INT(i))
                if t.is_ours(i.mission_type, i.target_system, i.target_component) =>
            {
                self.accept_item(item_from_wire(i), count, now, out);
            }
            (DownState::Receiving { count }, MavMessage::MISSION_ITEM(i))
                if t.is_ours(i.mission_type, i.target_system, i.target_component) =>
            {
                self.accept_item(item_from_legacy(i), count, now, out);
            }
            (_, MavMessage::MISSION_ACK(a))
                if t.is_ours(a.mission_type, a.target_system, a.target_component) =>
            {
                let count = match self.state {
                    DownState::Receiving { count } => count,
                    _ => 0,
                };
                let last = self.items.len().checked_sub(1).map(|s| s as u16);
                match a.mavtype {
                    // Stale answers to an upload's repeated items (ArduPilot
                    // sends both for items outside or out of sequence) can
                    // arrive after it ended; a download that is refused
                    // shows as DENIED or as timeouts.
                    MavMissionResult::MAV_MISSION_ERROR
                    | MavMissionResult::MAV_MISSION_INVALID_SEQUENCE => self.ignored += 1,
                    other => {
                        if let Some(err) = MissionError::from_result(other, last, count) {
                            self.finish(Err(err), now);
                        }
                    }
                }
            }
            _ => {}
        }
    }

    /// Call when [`Self::deadline`] has passed: re-requests, or fails after `max_retries`.
    pub fn on_timeout(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        super::on_timeout(self, now, out);
    }

    /// Cancels the download.
    pub fn cancel(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        super::cancel(self, now, out);
    }
}

impl Machine for Downloader {
    fn transfer(&mut self) -> &mut Transfer {
        &mut self.transfer
    }

    fn is_done(&self) -> bool {
        self.state == DownState::Done
    }

    fn give_up(&self, consecutive: u32) -> Option<MissionError> {
        let retries = self.transfer.params.max_retries;
        if consecutive <= retries {
            return None;
        }
        let stage = match self.state {
            DownState::Receiving { .. } => Stage::Item {
                seq: self.items.len() as u16,
            },
            _ => Stage::Count,
        };
        Some(MissionError::Timeout { stage, retries })
    }

    fn resend(&mut self, out: &mut Vec<MavMessage>) {
        self.retries += 1;
        match self.state {
            DownState::WaitCount => out.push(self.request_list()),
            DownState::Receiving { .. } => out.push(self.request(self.items.len() as u16)),
            DownState::Done => {}
        }
    }

    fn finish(&mut self, result: Result<(), MissionError>, now: Instant) {
        self.state = DownState::Done;
        let seconds = self.transfer.seconds(now);
        let items = std::mem::take(&mut self.items);
        let (retries, ignored) = (self.retries, self.ignored);
        self.outcome = Some(result.map(|()| Download {
            items,
            retries,
            ignored,
            seconds,
        }));
    }
}
