//! A scripted fake board for the link tests: a `Transport` that decodes request frames and
//! answers them like the firmware's handler would (credits, sequence check, scripted
//! refusals, garbage, silence), playing its queue while the host waits.
#![allow(dead_code)] // each test binary uses its own subset

use std::collections::{HashMap, VecDeque};
use std::io;
use std::time::Duration;
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, MAX_ENCODED};
use twinstack::protocol::messages::{
    NackReason, Request, Response, StatusReport, StreamControl, MAX_CHUNK,
};
use twinstack::refusal::{Field, ModelField, Refusal, Rule};
pub use twinstack_link::Transport;

/// A board reduced to its protocol behaviour: a setpoint queue of `capacity` played at
/// `rate` samples per second of (simulated) waiting, a sequence check, scripted refusals.
pub struct FakeBoard {
    pub decoder: FrameDecoder,
    pub out: VecDeque<u8>,
    pub queue: VecDeque<i16>,
    pub capacity: usize,
    pub rate: f64,
    pub running: bool,
    /// `Stream(Finish)` in force: stop at the end of the queue instead of underrunning.
    pub finishing: bool,
    pub expected_seq: u16,
    pub ticks: u64,
    /// Simulated time, seconds.
    pub time: f64,
    pub underruns: u32,
    pub played: Vec<i16>,
    /// Batches received (accepted or not), in order: (seq, len).
    pub batches: Vec<(u16, usize)>,
    /// Batches that asked for more than the free slots (the host broke the credit rule).
    pub over_credit: u32,
    /// Refuse the n-th Setpoints request (0-based) with this reason.
    pub refuse: HashMap<usize, NackReason>,
    pub setpoint_requests: usize,
    /// Bytes put on the line before the next response.
    pub garbage: Option<Vec<u8>>,
    /// What the status reports as the next sequence number, if not the truth.
    pub status_seq: Option<u16>,
    /// Answer this many status requests with a `Frame(BadCrc)` NACK (damaged on the line).
    pub refuse_status: u32,
    /// Status requests seen (those not refused by `refuse_status`), and which of them
    /// (0-based) to answer with a `Frame(BadCrc)` NACK.
    pub status_requests: usize,
    /// See `status_requests`.
    pub refuse_status_at: Vec<usize>,
    /// Answer nothing.
    pub mute: bool,
    /// Recorder contents.
    pub recording: Vec<i32>,
    /// Other requests, in order.
    pub log: Vec<Request>,
}

impl FakeBoard {
    pub fn new(capacity: usize, rate: f64) -> Self {
        Self {
            decoder: FrameDecoder::new(),
            out: VecDeque::new(),
            queue: VecDeque::new(),
            capacity,
            rate,
            running: false,
            finishing: false,
            expected_seq: 0,
            ticks: 0,
            time: 0.0,
            underruns: 0,
            played: Vec::new(),
            batches: Vec::new(),
            over_credit: 0,
            refuse: HashMap::new(),
            setpoint_requests: 0,
            garbage: None,
            status_seq: None,
            refuse_status: 0,
            status_requests: 0,
            refuse_status_at: Vec::new(),
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
            Request::Status
                if self.refuse_status > 0 || {
                    self.status_requests += 1;
                    self.refuse_status_at.contains(&(self.status_requests - 1))
                } =>
            {
                self.refuse_status = self.refuse_status.saturating_sub(1);
                Response::Nack {
                    reason: NackReason::Frame(twinstack::protocol::frame::FrameError::BadCrc),
                }
            }
            Request::Status => Response::Status(StatusReport {
                ticks: self.ticks as u32,
                queue_fill: self.queue.len() as u16,
                credits: self.free(),
                underruns: self.underruns,
                next_seq: self.status_seq.unwrap_or(self.expected_seq),
                tick_rate_hz: self.rate as u32,
                recorded: self.recording.len() as u32,
                flags: if self.running {
                    StatusReport::STREAMING
                } else {
                    0
                },
                ..StatusReport::default()
            }),
            Request::PackedSetpoints(b) => self.handle(Request::Setpoints(b.into())),
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
                    StreamControl::Stop => {
                        self.running = false;
                        self.finishing = false;
                    }
                    StreamControl::Finish => self.finishing = true,
                    StreamControl::Rate { divider: 0 } => {
                        return Response::Nack {
                            reason: NackReason::Refused(Refusal::new(
                                Field::Divider,
                                Rule::AtLeast(1.0),
                            )),
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
                reason: NackReason::Refused(Refusal::new(
                    Field::Compensator(ModelField::Weight(1)),
                    Rule::NotInvertible,
                )),
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
    pub fn advance(&mut self, dt: Duration) {
        // Whole ticks only; the remainder carries over to the next call.
        self.time += dt.as_secs_f64();
        let ticks = (self.time * self.rate) as u64 - self.ticks;
        for _ in 0..ticks {
            self.ticks += 1;
            if self.running {
                match self.queue.pop_front() {
                    Some(s) => self.played.push(s),
                    None if self.finishing => {
                        self.running = false;
                        self.finishing = false;
                    }
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
