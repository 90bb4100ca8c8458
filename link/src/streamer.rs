//! [`stream_setpoints`]: sends a setpoint record to the board's queue in batches, within the
//! credits the board grants, keeping several batches in flight.
//!
//! Rules it keeps (each checked by the tests with a scripted board):
//! * **credits**: every ACK (and every status report) carries the queue's free slots at the
//!   moment the board handled that request; the host subtracts what it has sent since, and
//!   never sends a batch larger than what is left. With nothing in flight and too few credits
//!   it waits for the board to play some samples, then asks ([`Request::Status`]);
//! * **sequence numbers**: batches are numbered consecutively (wrapping `u16`) from the
//!   `next_seq` the board reports; the first batch goes alone, and if the board expects another
//!   number (`OutOfSequence { expected }`) the stream continues from that number;
//! * **refusals**: a NACKed batch was not queued, and neither is any batch sent after it (they
//!   are out of sequence), so the streamer waits for their answers, asks for the credits and
//!   resends from the refused batch (go-back-N). Line damage (`Frame(..)`), `QueueFull` and
//!   `OutOfSequence` are retried up to [`StreamOptions::max_retries`] times in a row; any other
//!   reason ends the stream with an error that says how many setpoints were accepted.
//!
//! * **the end**: right behind the last batch goes `Stream(Finish)`: the board plays what is
//!   queued and then stops by itself, so it counts no underrun after the last setpoint, and
//!   the change of its underrun counter over the stream ([`StreamReport::underruns_during_stream`]) is
//!   exactly the stream's underruns;
//! * **a record in parts**: a call with [`StreamOptions::more`] sends no `Finish`, and the next
//!   with [`StreamOptions::continues`] queues its setpoints behind the ones still playing
//!   instead of stopping them, so the parts play as one stream with no pause between them.
//!
//! Setpoints are Q1.15 normalised displacement (the wire format,
//! [`twinstack::protocol::messages`]), sent as [`Request::PackedSetpoints`]: two bytes a
//! setpoint whatever its value.

use super::client::{request_name, Client, LinkCounters, LinkError};
use super::Transport;
use std::collections::VecDeque;
use std::time::Duration;
use twinstack::protocol::messages::{
    NackReason, PackedBatch, Request, Response, StatusReport, StreamControl, TriggerConfig,
    TriggerEdge, UnderrunPolicy, MAX_BATCH,
};

/// How a record is streamed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StreamOptions {
    /// Ticks per streamed setpoint (the board interpolates linearly in between), ≥ 1.
    pub divider: u16,
    /// Underrun policy to set first (`None`: leave the board's).
    pub underrun: Option<UnderrunPolicy>,
    /// The board's control rate, Hz, if its status does not report one: paces the waits for
    /// credits.
    pub tick_rate_hz: f64,
    /// Largest batch, ≤ [`MAX_BATCH`].
    pub batch: usize,
    /// After the last batch, wait until the board has played the queue, then stop the stream
    /// (the output holds the last setpoint).
    pub drain: bool,
    /// Refused batches in a row before giving up.
    pub max_retries: u32,
    /// Most setpoints to keep queued on the board (`None`: its whole queue). Smaller queues
    /// show what a board with less RAM would do (the streaming chapter's comparison).
    pub queue_limit: Option<usize>,
    /// Send [`Request::Setpoints`] (zigzag varints, up to three bytes a setpoint) instead of
    /// [`Request::PackedSetpoints`]: for comparisons, and boards that predate packing.
    pub varint: bool,
    /// More setpoints follow in another call, which continues this stream: no
    /// `Stream(Finish)` behind the last batch, so the board plays on (counting an underrun
    /// for each tick its queue is empty before the next call's setpoints come) and
    /// [`Self::drain`] does not apply.
    pub more: bool,
    /// Continue the stream a call with [`Self::more`] left playing: its setpoints are queued
    /// behind the ones still playing, with no `Stop` and no new `Start` (and the stream's
    /// divider and underrun policy stay those its first call set). Without it, a stream left
    /// running is stopped first. Where the board is not streaming, it starts as any stream.
    pub continues: bool,
    /// Start on the trigger input's edge instead of at once: the queue is primed, then the
    /// input is armed to start the stream (`Trigger { start_stream: true }`), and the stream
    /// plays from the tick the edge comes (a camera's frame, a delay generator). Not with a
    /// stream continued that is playing already.
    pub start_on: Option<StartOn>,
}

/// A stream started by the trigger input's edge ([`StreamOptions::start_on`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StartOn {
    /// The edge (`Rising` or `Falling`; `Off` starts at once, as with no `StartOn`).
    pub edge: TriggerEdge,
    /// The trigger outputs' pulse width the arming sets, ticks (the `Trigger` request sets
    /// both; a stream pulses no output, a later scan sets its own).
    pub pulse_ticks: u16,
    /// How long to wait for the edge before giving up (the input is then disarmed, and the
    /// setpoints accepted stay queued).
    pub wait: Duration,
}

impl Default for StreamOptions {
    fn default() -> Self {
        Self {
            divider: 1,
            underrun: None,
            tick_rate_hz: 50_000.0,
            batch: MAX_BATCH,
            drain: true,
            max_retries: 8,
            queue_limit: None,
            varint: false,
            more: false,
            continues: false,
            start_on: None,
        }
    }
}

/// What a stream did.
#[derive(Clone, Debug, PartialEq)]
pub struct StreamReport {
    /// Setpoints accepted by the board (all of them, on success).
    pub accepted: usize,
    /// Batches accepted.
    pub batches: u64,
    /// Batches sent again after a refusal.
    pub resent_batches: u64,
    /// Refusals met (each retried).
    pub nacks: Vec<NackReason>,
    /// Status requests sent to learn the credits.
    pub credit_probes: u64,
    /// Most setpoints sent but not yet acknowledged at any time.
    pub max_unacked: usize,
    /// Queue capacity (fill + credits at the start).
    pub capacity: usize,
    /// The whole record was in the board's queue before the stream was started (a record no
    /// longer than the free queue): the queue cannot run dry until its last setpoint.
    pub primed_whole: bool,
    /// Status before streaming.
    pub before: StatusReport,
    /// Status right after the last batch was acknowledged.
    pub after_last_batch: StatusReport,
    /// Status once the queue had drained (with [`StreamOptions::drain`]).
    pub drained: Option<StatusReport>,
    /// Link counters during the stream.
    pub link: LinkCounters,
}

impl StreamReport {
    /// Underruns of the stream: the change of the board's underrun counter from the status
    /// before the stream to the status after its last batch and its `Finish` were answered.
    /// Exact: the stream was stopped when the first status was taken (nothing counted
    /// before its start), and once `Finish` is in force the board stops at the end of the
    /// queue instead of counting (nothing counted after the last setpoint), so every tick
    /// counted between the two ran dry while setpoints were still to come. A stream in parts
    /// ([`StreamOptions::more`], [`StreamOptions::continues`]) plays on between the calls, and
    /// what it counts there is in neither call's figure: its caller takes the board's counter
    /// before the first part and after the last.
    pub fn underruns_during_stream(&self) -> u32 {
        self.after_last_batch
            .underruns
            .wrapping_sub(self.before.underruns)
    }

    /// The stream ran dry while it still had setpoints to deliver.
    pub fn underran(&self) -> bool {
        self.underruns_during_stream() != 0
    }
}

/// Why a stream stopped.
#[derive(Debug, thiserror::Error)]
#[error(
    "{source} (stream stopped after {accepted} of {total} setpoints were accepted by the board)"
)]
pub struct StreamError {
    /// The cause.
    #[source]
    pub source: LinkError,
    /// Setpoints the board accepted before the failure (they stay queued).
    pub accepted: usize,
    /// Setpoints in the record.
    pub total: usize,
}

enum InFlight {
    Batch {
        first: usize,
        len: usize,
        seq: u16,
    },
    Probe,
    /// A `Stream` request, answered with an ACK.
    Control,
}

/// Whether the armed input's edge has come: the input no longer armed (it is one-shot), or
/// the stream playing.
fn edge_came(s: &StatusReport) -> bool {
    !s.has(StatusReport::TRIGGER_ARMED) || s.has(StatusReport::STREAMING)
}

/// The edge did not come within its wait: the input is disarmed (so that a late edge starts
/// nothing the caller no longer waits for), and the error says what is left on the board.
fn no_edge<T: Transport>(client: &mut Client<T>, on: &StartOn, accepted: usize) -> LinkError {
    // The answers to anything in flight are dropped with the line's state: the disarming is
    // what matters, and its own answer is awaited.
    let disarmed = client.expect_ack(&Request::Trigger(TriggerConfig {
        pulse_ticks: on.pulse_ticks,
        input: TriggerEdge::Off,
        start_stream: false,
    }));
    LinkError::NoEdge {
        edge: match on.edge {
            TriggerEdge::Falling => "falling",
            _ => "rising",
        },
        wait: on.wait,
        after: format!(
            "{}; the {accepted} setpoints accepted stay queued (`Stream(Start)` plays them)",
            match disarmed {
                Ok(_) => "the input is disarmed".to_string(),
                Err(e) =>
                    format!("disarming the input failed ({e}): it may still start the stream"),
            }
        ),
    }
}

fn retryable(reason: &NackReason) -> bool {
    matches!(
        reason,
        NackReason::Frame(_) | NackReason::QueueFull | NackReason::OutOfSequence { .. }
    )
}

/// Streams `samples` (Q1.15) to the board behind `client`: sets the rate divider and the
/// underrun policy, fills the queue, starts the stream, keeps the queue topped up within the
/// credits, and (with [`StreamOptions::drain`]) waits for it to play out and stops.
/// `progress` is called with the number of setpoints accepted so far.
pub fn stream_setpoints<T: Transport>(
    client: &mut Client<T>,
    samples: &[i16],
    options: &StreamOptions,
    progress: impl FnMut(usize),
) -> Result<StreamReport, StreamError> {
    stream_setpoints_until(client, samples, options, progress, || false)
}

/// [`stream_setpoints`] that asks `stop` between two steps (each batch answered, each wait
/// for credits or for the queue to drain) whether to give up: when it returns `true` the
/// stream ends with [`LinkError::Stopped`] at once, with the board's stream left as it is
/// (the caller tells it to stop: `StreamControl::Stop`). The Python package's Ctrl-C.
pub fn stream_setpoints_until<T: Transport>(
    client: &mut Client<T>,
    samples: &[i16],
    options: &StreamOptions,
    mut progress: impl FnMut(usize),
    mut stop: impl FnMut() -> bool,
) -> Result<StreamReport, StreamError> {
    let mut accepted = 0usize;
    let total = samples.len();
    run(
        client,
        samples,
        options,
        &mut accepted,
        &mut progress,
        &mut stop,
    )
    .map_err(|source| StreamError {
        source,
        accepted,
        total,
    })
}

fn stopped(stop: &mut impl FnMut() -> bool) -> Result<(), LinkError> {
    if stop() {
        Err(LinkError::Stopped {
            request: "Setpoints",
        })
    } else {
        Ok(())
    }
}

fn run<T: Transport>(
    client: &mut Client<T>,
    samples: &[i16],
    options: &StreamOptions,
    accepted: &mut usize,
    progress: &mut impl FnMut(usize),
    stop: &mut impl FnMut() -> bool,
) -> Result<StreamReport, LinkError> {
    let link_before = client.counters();
    let mut before = client.status()?;
    let joined = options.continues && before.flags & StatusReport::STREAMING != 0;
    if before.flags & StatusReport::STREAMING != 0 && !joined {
        // A stream left running (one not finished): stop it, so that the board counts no
        // underrun of it against this one.
        client.stream(StreamControl::Stop)?;
        before = client.status()?;
    }
    let board_capacity = before.queue_fill as usize + before.credits as usize;
    let capacity = options
        .queue_limit
        .map_or(board_capacity, |l| l.min(board_capacity));
    // Credits beyond the limit are not used.
    let reserve = board_capacity - capacity;
    if capacity == 0 {
        return Err(LinkError::Unexpected {
            request: "Status",
            got: "a setpoint queue of capacity 0".into(),
        });
    }
    if !joined {
        client.stream(StreamControl::Rate {
            divider: options.divider,
        })?;
        if let Some(policy) = options.underrun {
            client.stream(StreamControl::Underrun(policy))?;
        }
    }
    let batch_max = options.batch.clamp(1, MAX_BATCH).min(capacity);
    // The board's own rate when it reports one.
    let tick_rate = if before.tick_rate_hz > 0 {
        before.tick_rate_hz as f64
    } else {
        options.tick_rate_hz
    };
    let tick = 1.0 / tick_rate.max(1.0);
    let mut report = StreamReport {
        accepted: 0,
        batches: 0,
        resent_batches: 0,
        nacks: Vec::new(),
        credit_probes: 0,
        max_unacked: 0,
        capacity,
        primed_whole: false,
        before,
        after_last_batch: before,
        drained: None,
        link: LinkCounters::default(),
    };

    let mut granted = (before.credits as usize).saturating_sub(reserve);
    let mut in_flight: VecDeque<InFlight> = VecDeque::new();
    let mut unacked = 0usize; // samples in in-flight batches
    let mut next = 0usize; // next sample to send
    let mut seq: u16 = before.next_seq;
    let mut handshaken = false; // a batch has been accepted: the sequence number is agreed
    let mut rewinding = false; // a batch was refused: waiting out the ones sent after it
    let mut retries = 0u32;
    // A stream continued is playing already: it is not started again.
    let mut started = joined;
    // `Stream(Finish)` sent behind the last batch (sent again if that batch is resent); with
    // more to come, never sent, and the stream is done once its batches are.
    let mut finish_sent = options.more;
    // Waiting for room without a batch accepted: bounded by the response timeout plus twice
    // the time the board needs to play a full queue.
    let mut stalled = Duration::ZERO;
    let stall_limit = client.timeout()
        + Duration::from_secs_f64(2.0 * capacity as f64 * options.divider as f64 * tick);
    let mut sent_ever = vec![false; samples.len().div_ceil(batch_max.max(1)) + 1];
    // The input armed to start the stream, its edge not seen yet (the status's
    // `TRIGGER_ARMED` still set, the stream not playing): the wait for credits is bounded by
    // the wait for the edge instead.
    let start_on = options
        .start_on
        .filter(|on| on.edge != TriggerEdge::Off && !joined);
    let mut waiting_edge = false;

    loop {
        if stop() {
            // The answers to the batches in flight, so that the line is clean for the
            // caller's next request (its `Stop`).
            for _ in 0..in_flight.len() {
                client.receive(client.timeout())?;
            }
            stopped(&mut || true)?;
        }
        // Done once everything is acknowledged *and* the stream has been started: a record
        // no longer than the free queue is acknowledged in full before it is ever blocked,
        // and must still be started (the `Start` below) rather than left queued.
        if next == samples.len()
            && in_flight.is_empty()
            && ((started && finish_sent) || samples.is_empty())
        {
            break;
        }
        // Send what the credits allow.
        let mut blocked = false;
        while !rewinding && next < samples.len() && (handshaken || in_flight.is_empty()) {
            let want = batch_max.min(samples.len() - next);
            if granted.saturating_sub(unacked) < want {
                blocked = true;
                break;
            }
            let batch = PackedBatch {
                seq,
                samples: heapless::Vec::from_slice(&samples[next..next + want]).map_err(|_| {
                    LinkError::Encode {
                        request: "Setpoints",
                        reason: twinstack::protocol::frame::FrameError::TooLarge,
                    }
                })?,
            };
            let batch = if options.varint {
                Request::Setpoints(batch.into())
            } else {
                Request::PackedSetpoints(batch)
            };
            let last = next + want == samples.len();
            if last && started && !finish_sent {
                // The last batch and `Finish` in one write: they reach the board together.
                client.send_together(&[batch, Request::Stream(StreamControl::Finish)])?;
            } else {
                client.send(&batch)?;
            }
            let slot = next / batch_max;
            if sent_ever.get(slot).copied().unwrap_or(false) {
                report.resent_batches += 1;
            }
            if let Some(s) = sent_ever.get_mut(slot) {
                *s = true;
            }
            in_flight.push_back(InFlight::Batch {
                first: next,
                len: want,
                seq,
            });
            unacked += want;
            report.max_unacked = report.max_unacked.max(unacked);
            next += want;
            seq = seq.wrapping_add(1);
            if last && started && !finish_sent {
                in_flight.push_back(InFlight::Control);
                finish_sent = true;
            }
        }
        // The queue is primed (full, or the whole record is in it): start playing.
        if !started
            && !samples.is_empty()
            && in_flight.is_empty()
            && !rewinding
            && (blocked || next == samples.len())
        {
            // Not waited for. With the whole record queued, `Finish` goes first, in the same
            // write: it is in force before the stream starts.
            report.primed_whole = next == samples.len();
            // Started now, or by the input's edge (armed here; the board starts the stream
            // on the edge's tick, from the queue primed).
            let start = match start_on {
                Some(on) => {
                    waiting_edge = true;
                    stalled = Duration::ZERO;
                    Request::Trigger(TriggerConfig {
                        pulse_ticks: on.pulse_ticks,
                        input: on.edge,
                        start_stream: true,
                    })
                }
                None => Request::Stream(StreamControl::Start),
            };
            if report.primed_whole && !options.more {
                client.send_together(&[Request::Stream(StreamControl::Finish), start])?;
                in_flight.push_back(InFlight::Control);
                in_flight.push_back(InFlight::Control);
                finish_sent = true;
            } else {
                client.send(&start)?;
                in_flight.push_back(InFlight::Control);
            }
            started = true;
        }
        // Everything is sent and the stream plays: the board is to stop at the end of the
        // queue rather than count its empty ticks as underruns.
        if started && !finish_sent && !rewinding && next == samples.len() {
            client.send(&Request::Stream(StreamControl::Finish))?;
            in_flight.push_back(InFlight::Control);
            finish_sent = true;
        }
        if in_flight.is_empty() {
            // Out of credits with nothing to wait for: let the board play a batch's worth,
            // then ask how much room there is.
            let wait = Duration::from_secs_f64(batch_max as f64 * options.divider as f64 * tick);
            if waiting_edge {
                if let Some(on) = start_on.filter(|on| stalled > on.wait) {
                    return Err(no_edge(client, &on, *accepted));
                }
            } else if stalled > stall_limit {
                return Err(LinkError::Unexpected {
                    request: "Status",
                    got: format!(
                        "no room in the queue for {stalled:?}: the board is not playing the stream"
                    ),
                });
            }
            client.wait(wait)?;
            stalled += wait;
            client.send(&Request::Status)?;
            report.credit_probes += 1;
            in_flight.push_back(InFlight::Probe);
        }
        let head = in_flight.pop_front().expect("not empty");
        let name = match head {
            InFlight::Batch { .. } => "Setpoints",
            InFlight::Probe => request_name(&Request::Status),
            InFlight::Control => "Stream",
        };
        let response = client
            .receive(client.timeout())?
            .ok_or(LinkError::Timeout {
                request: name,
                timeout: client.timeout(),
                corrupt: 0,
            })?;
        match (head, response) {
            (InFlight::Batch { len, .. }, Response::Ack { credits }) if !rewinding => {
                unacked -= len;
                granted = (credits as usize).saturating_sub(reserve);
                *accepted += len;
                report.batches += 1;
                handshaken = true;
                retries = 0;
                stalled = Duration::ZERO;
                progress(*accepted);
            }
            (InFlight::Batch { first, len, seq: s }, Response::Nack { reason }) => {
                unacked -= len;
                if !rewinding {
                    if !retryable(&reason) || retries >= options.max_retries {
                        return Err(LinkError::Nack {
                            request: "Setpoints",
                            reason,
                        });
                    }
                    report.nacks.push(reason);
                    retries += 1;
                    rewinding = true;
                    // The batches from the refused one are sent again, and `Finish` after
                    // the last of them (none with more to come).
                    finish_sent = options.more;
                    next = first;
                    seq = match reason {
                        NackReason::OutOfSequence { expected } => expected,
                        _ => s,
                    };
                }
            }
            (InFlight::Probe, Response::Status(s)) => {
                granted = (s.credits as usize).saturating_sub(reserve);
                waiting_edge &= !edge_came(&s);
            }
            (InFlight::Control, Response::Ack { .. }) => {}
            (InFlight::Control, Response::Nack { reason }) => {
                return Err(LinkError::Nack {
                    request: "Stream",
                    reason,
                })
            }
            // A status request damaged on the line: nothing happened, ask again.
            (
                InFlight::Probe,
                Response::Nack {
                    reason: NackReason::Frame(e),
                },
            ) if retries < options.max_retries => {
                report.nacks.push(NackReason::Frame(e));
                retries += 1;
                client.send(&Request::Status)?;
                report.credit_probes += 1;
                in_flight.push_back(InFlight::Probe);
            }
            (_, other) => {
                return Err(LinkError::Unexpected {
                    request: name,
                    got: format!("{other:?}"),
                })
            }
        }
        if rewinding && in_flight.is_empty() {
            // Everything after the refused batch has been answered: learn the credits afresh.
            rewinding = false;
            client.send(&Request::Status)?;
            report.credit_probes += 1;
            in_flight.push_back(InFlight::Probe);
        }
    }
    report.accepted = *accepted;
    report.after_last_batch = client.status()?;
    if let Some(on) = start_on.filter(|_| waiting_edge) {
        // The whole record is queued and the input armed: wait for its edge, polling the
        // status, before the stream's end is looked for.
        let step = Duration::from_millis(2);
        let mut waited = Duration::ZERO;
        while !edge_came(&report.after_last_batch) {
            stopped(stop)?;
            if waited > on.wait {
                return Err(no_edge(client, &on, *accepted));
            }
            client.wait(step)?;
            waited += step;
            report.after_last_batch = client.status()?;
        }
    }
    let end = report.after_last_batch;
    if end.flags & StatusReport::STREAMING == 0 && end.queue_fill > 0 {
        // A `Finish` in force while a refused batch was resent let the queue end early.
        return Err(LinkError::Unexpected {
            request: "Status",
            got: format!(
                "the stream stopped with {} setpoints still queued (its end came before a resent batch)",
                end.queue_fill
            ),
        });
    }
    if options.drain && !options.more {
        // Bounded wait: the queue plays in fill × divider ticks; allow twice that plus a
        // second before deciding the board is not playing it.
        let mut status = report.after_last_batch;
        let budget = status.queue_fill as f64 * options.divider as f64 * tick * 2.0 + 1.0;
        // Measured on the link's clock, round trips and all.
        let start = client.now();
        while status.queue_fill > 0 || status.flags & StatusReport::STREAMING != 0 {
            stopped(stop)?;
            let waited = client.now().saturating_sub(start).as_secs_f64();
            if waited > budget {
                return Err(LinkError::Unexpected {
                    request: "Status",
                    got: format!(
                        "{} setpoints still queued after {waited:.1} s: the stream is not playing",
                        status.queue_fill
                    ),
                });
            }
            // Wait for what is left to play (the last setpoint's hold while the queue is
            // empty), at most a batch's time: three setpoints at 10 Hz drain in 0.3 s, not
            // in a whole batch's 9.6 s.
            let left = (status.queue_fill as usize).clamp(1, batch_max) as f64;
            let step = (left * options.divider as f64 * tick).max(1e-3);
            client.wait(Duration::from_secs_f64(step))?;
            status = client.status()?;
        }
        client.stream(StreamControl::Stop)?;
        report.drained = Some(status);
    }
    let after = client.counters();
    report.link = LinkCounters {
        frames_sent: after.frames_sent - link_before.frames_sent,
        bytes_sent: after.bytes_sent - link_before.bytes_sent,
        bytes_received: after.bytes_received - link_before.bytes_received,
        frames_received: after.frames_received - link_before.frames_received,
        corrupt_frames: after.corrupt_frames - link_before.corrupt_frames,
        telemetry_frames: after.telemetry_frames - link_before.telemetry_frames,
    };
    Ok(report)
}
