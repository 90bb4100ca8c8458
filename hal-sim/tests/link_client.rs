//! The host's protocol client and streamer against a scripted fake board (a `Transport` that
//! decodes request frames and answers them like the firmware's handler): credits are never
//! exceeded, batches are numbered in order, refusals become typed errors or go-back-N
//! resends, timeouts are reported, garbage on the line is skipped.

use hal_sim::link::client::{Client, LinkError};
use hal_sim::link::streamer::{stream_setpoints, StreamOptions};
use hal_sim::link::Transport;
use std::collections::{HashMap, VecDeque};
use std::io;
use std::time::Duration;
use twinstack::params::ParamError;
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::{
    NackReason, Request, Response, StatusReport, StreamControl, UnderrunPolicy, MAX_CHUNK,
};

/// A board reduced to its protocol behaviour: a setpoint queue of `capacity` played at
/// `rate` samples per second of (simulated) waiting, a sequence check, scripted refusals.
struct FakeBoard {
    decoder: FrameDecoder,
    out: VecDeque<u8>,
    queue: VecDeque<i16>,
    capacity: usize,
    rate: f64,
    running: bool,
    expected_seq: u16,
    ticks: u64,
    underruns: u32,
    played: Vec<i16>,
    /// Batches received (accepted or not), in order: (seq, len).
    batches: Vec<(u16, usize)>,
    /// Batches that asked for more than the free slots (the host broke the credit rule).
    over_credit: u32,
    /// Refuse the n-th Setpoints request (0-based) with this reason.
    refuse: HashMap<usize, NackReason>,
    setpoint_requests: usize,
    /// Bytes put on the line before the next response.
    garbage: Option<Vec<u8>>,
    /// Answer nothing.
    mute: bool,
    /// Recorder contents.
    recording: Vec<i32>,
    /// Other requests, in order.
    log: Vec<Request>,
}

impl FakeBoard {
    fn new(capacity: usize, rate: f64) -> Self {
        Self {
            decoder: FrameDecoder::new(),
            out: VecDeque::new(),
            queue: VecDeque::new(),
            capacity,
            rate,
            running: false,
            expected_seq: 0,
            ticks: 0,
            underruns: 0,
            played: Vec::new(),
            batches: Vec::new(),
            over_credit: 0,
            refuse: HashMap::new(),
            setpoint_requests: 0,
            garbage: None,
            mute: false,
            recording: Vec::new(),
            log: Vec::new(),
        }
    }

    fn free(&self) -> u16 {
        (self.capacity - self.queue.len()) as u16
    }

    fn respond(&mut self, r: &Response) {
        if self.mute {
            return;
        }
        if let Some(g) = self.garbage.take() {
            self.out.extend(g);
        }
        let mut buf = [0u8; MAX_ENCODED + 1];
        let n = frame::encode(r, &mut buf).unwrap();
        self.out.extend(&buf[..n]);
    }

    fn handle(&mut self, request: Request) -> Response {
        match request {
            Request::Status => Response::Status(StatusReport {
                ticks: self.ticks as u32,
                queue_fill: self.queue.len() as u16,
                credits: self.free(),
                underruns: self.underruns,
                ..StatusReport::default()
            }),
            Request::Setpoints(b) => {
                let n = self.setpoint_requests;
                self.setpoint_requests += 1;
                self.batches.push((b.seq, b.samples.len()));
                if let Some(reason) = self.refuse.remove(&n) {
                    return Response::Nack { reason };
                }
                if b.seq != self.expected_seq {
                    return Response::Nack {
                        reason: NackReason::OutOfSequence {
                            expected: self.expected_seq,
                        },
                    };
                }
                if b.samples.len() > self.free() as usize {
                    self.over_credit += 1;
                    return Response::Nack {
                        reason: NackReason::QueueFull,
                    };
                }
                self.expected_seq = self.expected_seq.wrapping_add(1);
                self.queue.extend(b.samples.iter());
                Response::Ack {
                    credits: self.free(),
                }
            }
            Request::Stream(c) => {
                match c {
                    StreamControl::Start => self.running = true,
                    StreamControl::Stop => self.running = false,
                    StreamControl::Rate { divider: 0 } => {
                        return Response::Nack {
                            reason: NackReason::OutOfRange,
                        }
                    }
                    _ => {}
                }
                self.log.push(Request::Stream(c));
                Response::Ack {
                    credits: self.free(),
                }
            }
            Request::LoadParams(_) => Response::Nack {
                reason: NackReason::InvalidParams(ParamError::FirstWeightNotPositive),
            },
            Request::ReadRecord { offset } => {
                let start = (offset as usize).min(self.recording.len());
                let end = (start + MAX_CHUNK).min(self.recording.len());
                Response::RecordChunk {
                    offset,
                    values: heapless::Vec::from_slice(&self.recording[start..end]).unwrap(),
                }
            }
            other => {
                self.log.push(other);
                Response::Ack {
                    credits: self.free(),
                }
            }
        }
    }

    /// Plays the queue for `dt` seconds.
    fn advance(&mut self, dt: Duration) {
        let ticks = (dt.as_secs_f64() * self.rate).round() as u64;
        for _ in 0..ticks {
            self.ticks += 1;
            if self.running {
                match self.queue.pop_front() {
                    Some(s) => self.played.push(s),
                    None => self.underruns += 1,
                }
            }
        }
    }
}

impl Transport for FakeBoard {
    fn send(&mut self, bytes: &[u8]) -> io::Result<()> {
        for &b in bytes {
            let decoded = match self.decoder.push(b) {
                None => continue,
                Some(Ok(body)) => frame::decode_body::<Request>(body),
                Some(Err(e)) => Err(e),
            };
            let r = match decoded {
                Ok(req) => self.handle(req),
                Err(e) => Response::Nack {
                    reason: NackReason::Frame(e),
                },
            };
            self.respond(&r);
        }
        Ok(())
    }

    fn receive(&mut self, buf: &mut [u8], timeout: Duration) -> io::Result<usize> {
        if self.out.is_empty() {
            self.advance(timeout);
            return Ok(0);
        }
        let n = buf.len().min(self.out.len());
        for b in buf.iter_mut().take(n) {
            *b = self.out.pop_front().unwrap();
        }
        Ok(n)
    }
}

fn ramp(n: usize) -> Vec<i16> {
    (0..n).map(|i| ((i * 37) % 60_000) as i16).collect()
}

#[test]
fn the_streamer_never_exceeds_its_credits_and_everything_plays_in_order() {
    // A queue that is no multiple of the batch size, played at 50 kHz.
    let mut client = Client::new(FakeBoard::new(250, 50_000.0));
    let samples = ramp(20_000);
    let report =
        stream_setpoints(&mut client, &samples, &StreamOptions::default(), |_| {}).expect("stream");
    let board = client.transport();
    assert_eq!(board.over_credit, 0, "a batch exceeded the credits");
    assert_eq!(
        board.played, samples,
        "every setpoint played once, in order"
    );
    assert_eq!(report.accepted, samples.len());
    assert_eq!(report.underruns_during_stream(), Some(0), "{report:?}");
    assert!(report.max_unacked <= 250);
    // Consecutive sequence numbers from 0, and more than one batch in flight at times.
    for (i, (seq, _)) in board.batches.iter().enumerate() {
        assert_eq!(*seq as usize, i);
    }
    assert!(
        report.max_unacked > 96,
        "batches were pipelined: {report:?}"
    );
    // Started once the queue was primed, stopped after the drain.
    assert_eq!(
        board.log,
        vec![
            Request::Stream(StreamControl::Rate { divider: 1 }),
            Request::Stream(StreamControl::Start),
            Request::Stream(StreamControl::Stop),
        ]
    );
    assert_eq!(report.drained.map(|s| s.queue_fill), Some(0));
}

#[test]
fn the_first_batch_adopts_the_sequence_number_the_board_expects() {
    let mut board = FakeBoard::new(400, 50_000.0);
    board.expected_seq = 65_530; // and it wraps on the way
    let mut client = Client::new(board);
    let samples = ramp(3000);
    let options = StreamOptions {
        underrun: Some(UnderrunPolicy::Hold),
        ..StreamOptions::default()
    };
    let report = stream_setpoints(&mut client, &samples, &options, |_| {}).expect("stream");
    let board = client.transport();
    assert_eq!(board.played, samples);
    assert_eq!(board.over_credit, 0);
    // One refused probe-batch, then one in flight only until the first ACK.
    assert_eq!(
        report.nacks,
        vec![NackReason::OutOfSequence { expected: 65_530 }]
    );
    assert_eq!(board.batches[1].0, 65_530);
    assert_eq!(board.batches.last().unwrap().0, 65_530u16.wrapping_add(31));
    assert!(board.log.contains(&Request::Stream(StreamControl::Underrun(
        UnderrunPolicy::Hold
    ))));
}

#[test]
fn a_batch_damaged_on_the_line_is_resent_with_those_after_it_and_nothing_is_lost_or_doubled() {
    let mut board = FakeBoard::new(1000, 50_000.0);
    board
        .refuse
        .insert(4, NackReason::Frame(FrameError::BadCrc));
    board.refuse.insert(12, NackReason::QueueFull);
    let mut client = Client::new(board);
    let samples = ramp(6000);
    let report =
        stream_setpoints(&mut client, &samples, &StreamOptions::default(), |_| {}).expect("stream");
    let board = client.transport();
    assert_eq!(board.played, samples, "nothing lost, nothing doubled");
    assert_eq!(report.nacks.len(), 2, "{:?}", report.nacks);
    assert!(report.resent_batches >= 2, "{report:?}");
    assert_eq!(report.underruns_during_stream(), Some(0));
}

#[test]
fn a_refusal_that_cannot_be_retried_ends_the_stream_with_what_was_accepted() {
    let mut board = FakeBoard::new(300, 50_000.0);
    board.refuse.insert(3, NackReason::OutOfRange);
    let mut client = Client::new(board);
    let err = stream_setpoints(&mut client, &ramp(2000), &StreamOptions::default(), |_| {})
        .expect_err("refused");
    assert!(matches!(
        err.source,
        LinkError::Nack {
            reason: NackReason::OutOfRange,
            ..
        }
    ));
    assert_eq!(err.accepted, 3 * 96);
    let text = err.to_string();
    assert!(text.contains("288 of 2000"), "{text}");
}

#[test]
fn endless_refusals_give_up_after_the_retry_limit() {
    let mut board = FakeBoard::new(300, 50_000.0);
    for i in 0..100 {
        board
            .refuse
            .insert(i, NackReason::Frame(FrameError::BadCrc));
    }
    let mut client = Client::new(board);
    let options = StreamOptions {
        max_retries: 5,
        ..StreamOptions::default()
    };
    let err = stream_setpoints(&mut client, &ramp(500), &options, |_| {}).expect_err("gives up");
    assert_eq!(err.accepted, 0);
    assert_eq!(client.transport().setpoint_requests, 6);
}

#[test]
fn a_nack_is_a_typed_error_that_names_the_request_and_the_reason() {
    let mut client = Client::new(FakeBoard::new(100, 1000.0));
    let set = twinstack::protocol::messages::ParamSet {
        model: twinstack::protocol::messages::ModelParams::Duhem {
            alpha: 1.0,
            beta: 1.0,
            gamma: 1.0,
            offset: 0.0,
        },
        input_range: [0.0, 1.0],
        output_range: [0.0, 1.0],
        configuration: twinstack::drive::Configuration::Differential,
        bias: 0.5,
        voltage_limits: [0.0, 1.0],
        slew_rate: 1.0,
        safe_state: twinstack::drive::SafeState::Bias,
        feedback: None,
        mode: twinstack::protocol::messages::Mode::OpenLoop,
    };
    let err = client.load_params(&set).expect_err("refused");
    assert!(matches!(
        err,
        LinkError::Nack {
            request: "LoadParams",
            reason: NackReason::InvalidParams(ParamError::FirstWeightNotPositive)
        }
    ));
    assert!(err.to_string().contains("not invertible"), "{err}");
    let err = client
        .stream(StreamControl::Rate { divider: 0 })
        .expect_err("refused");
    assert!(err.to_string().contains("out of its range"), "{err}");
}

#[test]
fn a_silent_board_is_a_timeout_not_a_hang() {
    let mut board = FakeBoard::new(100, 1000.0);
    board.mute = true;
    let mut client = Client::new(board);
    client.set_timeout(Duration::from_millis(20));
    let err = client.status().expect_err("times out");
    assert!(
        matches!(
            err,
            LinkError::Timeout {
                request: "Status",
                ..
            }
        ),
        "{err}"
    );
}

#[test]
fn garbage_on_the_line_is_skipped_and_the_next_frame_decodes() {
    let mut board = FakeBoard::new(100, 1000.0);
    // Noise ending in a delimiter, a frame with a flipped bit, a lone delimiter.
    let mut bad = [0u8; MAX_ENCODED + 1];
    let n = frame::encode(&Response::Ack { credits: 7 }, &mut bad).unwrap();
    bad[2] ^= 0x10;
    let mut garbage = b"twinstack status ticks=1\n\x00".to_vec();
    garbage.extend_from_slice(&bad[..n]);
    garbage.push(0);
    board.garbage = Some(garbage);
    board.queue.extend([1, 2, 3]);
    let mut client = Client::new(board);
    let s = client.status().expect("status after the garbage");
    assert_eq!(s.queue_fill, 3);
    assert_eq!(client.counters().corrupt_frames, 2);
}

#[test]
fn the_recording_is_read_in_chunks_and_its_length_is_checked() {
    let mut board = FakeBoard::new(100, 1000.0);
    board.recording = (0..300).map(|i| i * 1000 - 7).collect();
    let mut client = Client::new(board);
    let mut seen = Vec::new();
    let values = client
        .read_recording(300, |n| seen.push(n))
        .expect("read back");
    assert_eq!(values, client.transport().recording);
    assert_eq!(seen, vec![64, 128, 192, 256, 300]);
    // Fewer values on the board than asked for: an error, not a short file.
    let err = client.read_recording(301, |_| {}).expect_err("short");
    assert!(err.to_string().contains("holds 300 values"), "{err}");
}
