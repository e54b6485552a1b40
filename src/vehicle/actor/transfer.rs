//! A mission transfer in flight (upload or download, and the read-back that
//! confirms an upload whose final ACK was lost) and its outcome delivered to
//! whoever waits for it.

use std::time::Instant;

use mavlink::MavHeader;
use mavlink::dialects::common::MavMessage;
use tokio::sync::oneshot;
use tracing::{Span, info, warn};

use crate::mission::upload::{Downloader, MissionError, Uploader, same_mission};
use crate::mission::{Download, MissionItem, UploadReport};
use crate::vehicle::error::LinkError;

/// Read-backs of an upload whose final ACK was lost, at most: the read-back
/// crosses the same bad radio that lost the ACK, and a read-back that fails
/// (its own retries spent) says nothing about the vehicle's mission, so it
/// is tried again before the upload is reported as unconfirmed.
pub(super) const READ_BACK_ATTEMPTS: u32 = 3;

/// Why a download runs.
pub(super) enum DownPurpose {
    /// The operator asked for the mission.
    Reply(oneshot::Sender<Result<Download, LinkError>>),
    /// An upload's final ACK was lost: the read-back decides.
    Verify {
        items: Vec<MissionItem>,
        skip_home: bool,
        report: UploadReport,
        reply: oneshot::Sender<Result<UploadReport, LinkError>>,
        /// This read-back's number, from 1.
        attempt: u32,
        /// When this read-back started.
        since: Instant,
    },
}

pub(super) enum Transfer {
    Up {
        machine: Uploader,
        items: Vec<MissionItem>,
        skip_home: bool,
        reply: oneshot::Sender<Result<UploadReport, LinkError>>,
        span: Span,
    },
    Down {
        machine: Downloader,
        purpose: DownPurpose,
        span: Span,
    },
}

/// What finishing a transfer leads to.
pub(super) enum Next {
    Nothing,
    /// Read the mission back to confirm an upload whose final ACK was lost.
    Verify {
        items: Vec<MissionItem>,
        skip_home: bool,
        report: UploadReport,
        reply: oneshot::Sender<Result<UploadReport, LinkError>>,
        span: Span,
        /// The read-back's number, from 1.
        attempt: u32,
    },
}

fn log_upload(span: &Span, outcome: &Result<UploadReport, MissionError>) {
    span.in_scope(|| match outcome {
        Ok(r) => info!(
            items = r.items,
            retries = r.retries,
            repeats = r.repeats,
            seconds = r.seconds,
            verified_by_download = r.verified_by_download,
            "mission uploaded"
        ),
        Err(e) => warn!(error = %e, "mission upload failed"),
    });
}

impl Transfer {
    pub(super) fn on_message(
        &mut self,
        h: &MavHeader,
        m: &MavMessage,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) {
        match self {
            Self::Up { machine, span, .. } => span.in_scope(|| machine.on_message(h, m, now, out)),
            Self::Down { machine, span, .. } => {
                span.in_scope(|| machine.on_message(h, m, now, out))
            }
        }
    }

    pub(super) fn on_timeout(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        match self {
            Self::Up { machine, .. } => machine.on_timeout(now, out),
            Self::Down { machine, .. } => machine.on_timeout(now, out),
        }
    }

    pub(super) fn cancel(&mut self, now: Instant, out: &mut Vec<MavMessage>) {
        match self {
            Self::Up { machine, .. } => machine.cancel(now, out),
            Self::Down { machine, .. } => machine.cancel(now, out),
        }
    }

    pub(super) fn deadline(&self) -> Option<Instant> {
        match self {
            Self::Up { machine, .. } => machine.deadline(),
            Self::Down { machine, .. } => machine.deadline(),
        }
    }

    pub(super) fn is_done(&self) -> bool {
        match self {
            Self::Up { machine, .. } => machine.is_done(),
            Self::Down { machine, .. } => machine.is_done(),
        }
    }

    /// Sends the outcome of a finished transfer to whoever waits for it, or
    /// asks for a read-back when an upload's final ACK is missing and
    /// `may_verify`.
    pub(super) fn deliver(self, now: Instant, may_verify: bool) -> Next {
        match self {
            Self::Up {
                mut machine,
                items,
                skip_home,
                reply,
                span,
            } => match machine.take_outcome() {
                Some(Err(MissionError::NoFinalAck { .. })) if may_verify => {
                    span.in_scope(|| warn!("final MISSION_ACK missing; reading the mission back"));
                    Next::Verify {
                        items,
                        skip_home,
                        report: machine.report_at(now),
                        reply,
                        span,
                        attempt: 1,
                    }
                }
                Some(outcome) => {
                    log_upload(&span, &outcome);
                    let _ = reply.send(outcome.map_err(LinkError::from));
                    Next::Nothing
                }
                None => Next::Nothing,
            },
            Self::Down {
                mut machine,
                purpose,
                span,
            } => {
                let Some(outcome) = machine.take_outcome() else {
                    return Next::Nothing;
                };
                match purpose {
                    DownPurpose::Reply(reply) => {
                        span.in_scope(|| match &outcome {
                            Ok(d) => info!(
                                items = d.items.len(),
                                retries = d.retries,
                                seconds = d.seconds,
                                "mission downloaded"
                            ),
                            Err(e) => warn!(error = %e, "mission download failed"),
                        });
                        let _ = reply.send(outcome.map_err(LinkError::from));
                    }
                    DownPurpose::Verify {
                        items,
                        skip_home,
                        report,
                        reply,
                        attempt,
                        since,
                    } => {
                        let result = match outcome {
                            Err(e)
                                if !matches!(e, MissionError::Cancelled)
                                    && attempt < READ_BACK_ATTEMPTS =>
                            {
                                span.in_scope(|| {
                                    warn!(
                                        error = %e,
                                        attempt,
                                        "the read-back failed; reading the mission back again"
                                    )
                                });
                                // The failed read-back's time counts.
                                let seconds = report.seconds
                                    + now.saturating_duration_since(since).as_secs_f64();
                                return Next::Verify {
                                    items,
                                    skip_home,
                                    report: UploadReport { seconds, ..report },
                                    reply,
                                    span,
                                    attempt: attempt + 1,
                                };
                            }
                            Ok(d) if same_mission(&items, &d.items, skip_home) => {
                                Ok(UploadReport {
                                    seconds: report.seconds + d.seconds,
                                    retries: report.retries + d.retries,
                                    verified_by_download: true,
                                    ..report
                                })
                            }
                            Ok(d) => Err(MissionError::ReadBackDiffers {
                                uploaded: report.items,
                                downloaded: d.items.len(),
                            }),
                            Err(MissionError::Cancelled) => Err(MissionError::Cancelled),
                            Err(_) => Err(MissionError::NoFinalAck {
                                count: report.items,
                                retries: report.retries,
                            }),
                        };
                        log_upload(&span, &result);
                        let _ = reply.send(result.map_err(LinkError::from));
                    }
                }
                Next::Nothing
            }
        }
    }
}
