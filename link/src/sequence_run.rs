//! Runs a TTL-stepped sequence ([`twinstack::sources::sequence`]) from the host: reads the positions
//! file, fills the board's setpoint queue with them, arms the sequence, keeps the queue topped
//! up as edges consume it (so a sequence may be longer than the queue), and reports the
//! steps, early and missed edges. Optionally captures the first edge and measures the
//! trigger-to-motion latency ([`EdgeTiming`]). What `twinstack sequence` and the Python
//! package's `Board.sequence` run.
//!
//! The positions file is the stream's setpoint CSV ([`crate::setpoint_file`]): a header naming
//! a `setpoint` column (normalised, −1…1) or `x` (output units, with the parameter file);
//! every bad row — not a number, NaN, out of range — is refused naming its line.

use std::ops::ControlFlow;
use std::time::Duration;

use crate::capture::{wait_and_read, CaptureError};
use crate::client::{Client, LinkError};
use crate::Transport;
use twinstack::protocol::messages::{
    CaptureRequest, NackReason, PackedBatch, Request, Response, SequenceConfig, SequenceRequest,
    SequenceStatus, StatusReport, StreamControl, Trigger, TriggerConfig, TriggerEdge, MAX_BATCH,
};
use twinstack::services::recorder::Channel;
use twinstack::sources::scan::INPUT;

/// How a sequence is run.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SequenceOptions {
    /// The board's settings for it (edge, settle window, settle ticks).
    pub config: SequenceConfig,
    /// Give up when no edge has advanced the sequence for this long (the camera stopped).
    pub idle: Duration,
    /// Pause between two status polls while waiting for edges.
    pub poll: Duration,
    /// Capture the first edge and measure the trigger-to-motion latency ([`EdgeTiming`]);
    /// this arms the external trigger input (one shot) for the capture.
    pub timing: bool,
}

/// The trigger-to-motion latency of the first edge, from a capture of the left DAC code and
/// the trigger input (one sample a tick).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct EdgeTiming {
    /// Ticks from the tick that sampled the edge to the first tick whose DAC code differs from
    /// the one before the edge (0: the edge's own tick wrote the moved sample).
    pub ticks_to_motion: u32,
    /// The DAC code before the edge and on the first moved tick.
    pub codes: (i16, i16),
}

/// What a sequence did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SequenceReport {
    /// Positions sent (all of them on success).
    pub sent: usize,
    /// The board's counts at the end (the sequence disarmed: the stage holds the last
    /// position reached).
    pub status: SequenceStatus,
    /// Whether every position was reached.
    pub complete: bool,
    /// The first edge's latency (with [`SequenceOptions::timing`]).
    pub timing: Option<EdgeTiming>,
}

/// Why a sequence run failed.
#[derive(Debug, thiserror::Error)]
pub enum SequenceError {
    /// The link or the board refused.
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The timing capture failed.
    #[error("the timing capture: {0}")]
    Capture(#[from] CaptureError),
    /// No positions.
    #[error("no positions to sequence")]
    Empty,
    /// The caller stopped the wait ([`run_sequence`]'s `progress` answered
    /// [`ControlFlow::Break`]); the sequence was disarmed.
    #[error("stopped after {steps} positions")]
    Stopped {
        /// Positions reached.
        steps: u32,
    },
}

/// Runs `positions` (Q1.15) as a sequence on the board behind `client` (see the module doc);
/// `progress` sees the positions reached so far, and its [`ControlFlow::Break`] stops the
/// wait ([`SequenceError::Stopped`]). Ends when every position is reached, or when no edge has
/// come for [`SequenceOptions::idle`] (on the link's clock); either way the sequence is then
/// disarmed.
pub fn run_sequence<T: Transport>(
    client: &mut Client<T>,
    positions: &[i16],
    options: &SequenceOptions,
    mut progress: impl FnMut(&SequenceStatus) -> ControlFlow<()>,
) -> Result<SequenceReport, SequenceError> {
    if positions.is_empty() {
        return Err(SequenceError::Empty);
    }
    options.config.check().map_err(|r| LinkError::Nack {
        request: "Sequence",
        reason: NackReason::Refused(r),
    })?;
    // Whatever ran stops; setpoints a stream left queued would be taken as positions, so
    // they are refused here rather than sequenced.
    client.expect_ack(&Request::Stream(StreamControl::Stop))?;
    let mut status = client.status()?;
    if status.queue_fill > 0 {
        return Err(LinkError::Unexpected {
            request: "Status",
            got: format!(
                "{} setpoints still queued from a stream: play them out (twinstack stream) before a sequence",
                status.queue_fill
            ),
        }
        .into());
    }
    let mut seq = status.next_seq;
    let mut sent = 0usize;
    let mut credits = status.credits as usize;
    // Fill the queue first: the first edges then find their positions however slow the link.
    send_positions(client, positions, &mut sent, &mut seq, &mut credits)?;
    if options.timing {
        client.arm_capture(CaptureRequest {
            signals: Channel::Left.bit() | Channel::Triggers.bit(),
            samples: 64,
            pre_trigger: PRE_TRIGGER,
            trigger: Trigger::External,
            decimation: 1,
        })?;
        client.expect_ack(&Request::Trigger(TriggerConfig {
            pulse_ticks: 1,
            input: options.config.edge,
            start_stream: false,
        }))?;
    }
    client.expect_ack(&Request::Sequence(SequenceRequest::Arm(options.config)))?;
    let mut last_steps = 0u32;
    let mut since = client.now();
    let end = loop {
        let s = client.sequence_status()?;
        if progress(&s).is_break() {
            client.expect_ack(&Request::Sequence(SequenceRequest::Stop))?;
            return Err(SequenceError::Stopped { steps: s.steps });
        }
        if s.steps as usize >= positions.len() {
            break s;
        }
        if s.steps != last_steps {
            last_steps = s.steps;
            since = client.now();
        } else if client.now().saturating_sub(since) >= options.idle {
            break s;
        }
        if sent < positions.len() {
            status = client.status()?;
            credits = status.credits as usize;
            send_positions(client, positions, &mut sent, &mut seq, &mut credits)?;
        }
        client.wait(options.poll)?;
    };
    // The last position's settling is what the caller waits for; the counts are final.
    client.expect_ack(&Request::Sequence(SequenceRequest::Stop))?;
    let status = client.sequence_status()?;
    let timing = if options.timing && status.steps.wrapping_add(status.missed) > 0 {
        let (_, window) = wait_and_read(client, Duration::from_secs(1), |_, _| {})?;
        edge_timing(
            &window,
            PRE_TRIGGER as usize,
            options.config.edge != TriggerEdge::Falling,
        )
    } else {
        None
    };
    Ok(SequenceReport {
        sent,
        status,
        complete: end.steps as usize >= positions.len(),
        timing,
    })
}

/// Sends what the credits allow, batch by batch, each answered before the next.
fn send_positions<T: Transport>(
    client: &mut Client<T>,
    positions: &[i16],
    sent: &mut usize,
    seq: &mut u16,
    credits: &mut usize,
) -> Result<(), LinkError> {
    while *sent < positions.len() && *credits > 0 {
        let n = MAX_BATCH.min(*credits).min(positions.len() - *sent);
        let batch = PackedBatch {
            seq: *seq,
            samples: heapless::Vec::from_slice(&positions[*sent..*sent + n]).map_err(|_| {
                LinkError::Encode {
                    request: "Setpoints",
                    reason: twinstack::protocol::frame::FrameError::TooLarge,
                }
            })?,
        };
        match client.request(&Request::PackedSetpoints(batch))? {
            Response::Ack { credits: c } => {
                *sent += n;
                *seq = seq.wrapping_add(1);
                *credits = c as usize;
            }
            Response::Nack { reason } => {
                return Err(LinkError::Nack {
                    request: "Setpoints",
                    reason,
                })
            }
            other => {
                return Err(LinkError::Unexpected {
                    request: "Setpoints",
                    got: format!("{other:?}"),
                })
            }
        }
    }
    Ok(())
}

/// Frames the timing capture keeps before the edge that triggers it.
const PRE_TRIGGER: u32 = 8;

/// The latency of the edge (`rising` or falling) nearest frame `pre` in a capture of
/// `[left, triggers]` frames: `None` without such an edge in it, or without a DAC change
/// after it and before the next such edge (a position where the stage already is moves
/// nothing, and a later edge's motion is not this one's).
///
/// ```
/// use twinstack_link::sequence_run::edge_timing;
/// use twinstack::sources::scan::INPUT;
/// let i = INPUT as i16;
/// // left, triggers: the edge on the third frame, the DAC moving on the same frame.
/// let w = [100, 0, 100, 0, 120, i, 140, i];
/// let t = edge_timing(&w, 2, true).unwrap();
/// assert_eq!((t.ticks_to_motion, t.codes), (0, (100, 120)));
/// assert!(edge_timing(&w, 2, false).is_none());
/// // The first edge steps to where the stage is; the motion comes with the next edge.
/// let w = [100, 0, 100, i, 100, 0, 120, i];
/// assert!(edge_timing(&w, 1, true).is_none());
/// ```
pub fn edge_timing(window: &[i16], pre: usize, rising: bool) -> Option<EdgeTiming> {
    let frames: Vec<(i16, bool)> = window
        .chunks_exact(2)
        .map(|f| (f[0], f[1] as u8 & INPUT != 0))
        .collect();
    let edge = (1..frames.len())
        .filter(|&k| frames[k].1 == rising && frames[k - 1].1 != rising)
        .min_by_key(|&k| k.abs_diff(pre))?;
    let before = frames[edge - 1].0;
    let next_edge = (edge + 1..frames.len())
        .find(|&k| frames[k].1 == rising && frames[k - 1].1 != rising)
        .unwrap_or(frames.len());
    let moved = (edge..next_edge).find(|&k| frames[k].0 != before)?;
    Some(EdgeTiming {
        ticks_to_motion: (moved - edge) as u32,
        codes: (before, frames[moved].0),
    })
}

/// Whether a status report shows a sequence armed.
pub fn is_sequencing(status: &StatusReport) -> bool {
    status.has(StatusReport::SEQUENCE)
}
