//! [`Client`]: the host's protocol engine over any [`Transport`]. It encodes requests into
//! frames, decodes the board's frames (skipping and counting corrupt ones, resynchronising at
//! the next delimiter), matches each response to its request in order, and turns a NACK into
//! a typed [`LinkError::Nack`].
//!
//! Every request is answered by exactly one response, in order, so a caller may keep several
//! requests in flight ([`Client::send`] then [`Client::receive`]); [`Client::request`] is the
//! one-at-a-time form.
//!
//! **Telemetry** (protocol v5): while it runs, the board sends unsolicited
//! [`Response::Telemetry`] frames between its responses. [`Client::receive`] sets them aside
//! (they answer no request) and returns the next response, so every request works as before
//! while telemetry flows; [`Client::take_telemetry`] hands the frames set aside over, in the
//! order they came, and [`Client::collect_telemetry`] receives for a while with no request
//! outstanding.

use super::Transport;
use std::collections::VecDeque;
use std::io;
use std::time::{Duration, Instant};
use twinstack::config::settings::Settings;
use twinstack::protocol::decoder::FrameDecoder;
use twinstack::protocol::frame::{self, FrameError, MAX_ENCODED};
use twinstack::protocol::messages::{
    AnalogRequest, AnalogStatus, CaptureRequest, CaptureStatus, CoarseStatus, Mode, NackReason,
    RecordRequest, Request, Response, SequenceRequest, SequenceStatus, StatusReport, StreamControl,
    TelemetryFrame, TelemetryRequest, Waveform, MAX_CAPTURE_CHUNK, MAX_CHUNK,
};

/// Times [`Client::request`] resends a request the board NACKed as a damaged frame.
pub const FRAME_RETRIES: u32 = 2;

/// How long a request waits for its response by default.
pub const DEFAULT_TIMEOUT: Duration = Duration::from_secs(2);

/// What went wrong talking to the board.
#[derive(Debug, thiserror::Error)]
pub enum LinkError {
    /// The transport failed (port closed, device unplugged, emulator exited).
    #[error("link: {0}")]
    Io(#[from] io::Error),
    /// No response within the timeout.
    #[error("no response to {request} within {timeout:?} ({corrupt} corrupt frames received meanwhile): is the board connected, powered and at the same baud rate? (In QEMU, boot the emulator image twinstack-emu, `cargo build-emu`: the board image twinstack-fw waits for a crystal QEMU does not model and never answers.)")]
    Timeout {
        /// The request waiting.
        request: &'static str,
        /// How long it waited.
        timeout: Duration,
        /// Corrupt frames skipped while waiting.
        corrupt: u32,
    },
    /// The board refused the request; nothing was applied.
    #[error("the board refused {request}: {}", nack_text(reason))]
    Nack {
        /// The request refused.
        request: &'static str,
        /// The board's reason.
        reason: NackReason,
    },
    /// A response of the wrong kind (a protocol mismatch between host and firmware).
    #[error("unexpected response to {request}: {got}")]
    Unexpected {
        /// The request.
        request: &'static str,
        /// What arrived.
        got: String,
    },
    /// The caller stopped the operation (the Python package's Ctrl-C during a stream).
    #[error("stopped by the caller during {request}")]
    Stopped {
        /// What was under way.
        request: &'static str,
    },
    /// The request could not be encoded (too large for a frame).
    #[error("cannot encode {request}: {reason:?}")]
    Encode {
        /// The request.
        request: &'static str,
        /// Why.
        reason: FrameError,
    },
    /// The trigger input's edge a stream was armed to start on did not come in time
    /// ([`crate::streamer::StreamOptions::start_on`]).
    #[error("the trigger input's {edge} edge did not come within {wait:?}: {after}")]
    NoEdge {
        /// `rising` or `falling`.
        edge: &'static str,
        /// How long it was waited for.
        wait: Duration,
        /// What was done and what is left on the board.
        after: String,
    },
}

/// A short name for a request, for messages.
pub fn request_name(request: &Request) -> &'static str {
    match request {
        Request::Status => "Status",
        Request::Setpoints(_) => "Setpoints",
        Request::Stream(_) => "Stream",
        Request::Mode(_) => "Mode",
        Request::LoadParams(_) => "LoadParams",
        Request::StoreParams { .. } => "StoreParams",
        Request::RecallParams => "RecallParams",
        Request::Waveform(_) => "Waveform",
        Request::Record(_) => "Record",
        Request::ReadRecord { .. } => "ReadRecord",
        Request::ReadParams => "ReadParams",
        Request::Capture(_) => "Capture",
        Request::CaptureStatus => "CaptureStatus",
        Request::ReadCapture { .. } => "ReadCapture",
        Request::Telemetry(_) => "Telemetry",
        Request::CoarseHome => "CoarseHome",
        Request::CoarseMove(_) => "CoarseMove",
        Request::CoarseJog { .. } => "CoarseJog",
        Request::CoarseStop => "CoarseStop",
        Request::CoarseStatus => "CoarseStatus",
        Request::Learn(_) => "Learn",
        Request::Scan(_) => "Scan",
        Request::Trigger(_) => "Trigger",
        Request::PackedSetpoints(_) => "Setpoints",
        Request::Sequence(_) => "Sequence",
        Request::Echo(_) => "Echo",
        Request::Analog(_) => "Analog",
        Request::WatchdogDrill => "WatchdogDrill",
        Request::CoarseRelease => "CoarseRelease",
    }
}

/// A NACK reason in words.
pub fn nack_text(reason: &NackReason) -> String {
    match reason {
        NackReason::Frame(e) => format!(
            "bad frame ({}); nothing was applied",
            match e {
                FrameError::Oversize => "oversize".to_string(),
                FrameError::Truncated => "truncated".to_string(),
                FrameError::BadStuffing => "broken COBS stuffing".to_string(),
                FrameError::BadCrc => "CRC mismatch".to_string(),
                FrameError::BadVersion { got } => format!(
                    "protocol version {got}, the board speaks {}",
                    frame::PROTOCOL_VERSION
                ),
                FrameError::UnknownType => "unknown message type".to_string(),
                FrameError::Malformed => "malformed message".to_string(),
                FrameError::TooLarge => "too large".to_string(),
            }
        ),
        NackReason::QueueFull => "setpoint queue full (more setpoints than credits)".into(),
        NackReason::OutOfSequence { expected } => {
            format!("batch out of sequence (the board expected sequence number {expected})")
        }
        NackReason::Refused(r) => format!("refused: {r}; nothing was applied"),
        NackReason::NoStorage => "this board has no parameter storage".into(),
        NackReason::Busy => {
            "busy: not now (the stream or the waveform runs: stop it first; or the coarse axis is \
             homing or braking: wait for it)"
                .into()
        }
        NackReason::NothingStored => "no valid settings are stored in flash".into(),
        NackReason::StoreFailed => "writing the flash record failed".into(),
        NackReason::Unsupported => "this build of the board cannot do it now (the emulator image has no watchdog; in a dual-stage image the coarse axis owns the piezo's setpoint: no stream, waveform, scan, sequence or analog input until `twinstack coarse release` hands it back)".into(),
        NackReason::NotOwner => "another client of the server owns the board's stream and settings (or its telemetry): this one may only read (status, records, settings)".into(),
    }
}

/// Link counters since the client was made.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LinkCounters {
    /// Frames sent.
    pub frames_sent: u64,
    /// Bytes sent (delimiters included).
    pub bytes_sent: u64,
    /// Bytes received.
    pub bytes_received: u64,
    /// Good frames received.
    pub frames_received: u64,
    /// Corrupt frames received and skipped.
    pub corrupt_frames: u64,
    /// Telemetry frames received (set aside for [`Client::take_telemetry`]).
    pub telemetry_frames: u64,
}

/// The protocol engine over a transport.
pub struct Client<T> {
    transport: T,
    decoder: FrameDecoder,
    rx: Box<[u8; 4096]>,
    rx_pos: usize,
    rx_len: usize,
    timeout: Duration,
    counters: LinkCounters,
    /// Telemetry frames received and not yet taken.
    telemetry: VecDeque<TelemetryFrame>,
    /// Wall-clock origin for transports without a clock of their own.
    born: Instant,
}

impl<T: Transport> Client<T> {
    /// A client over `transport`, with [`DEFAULT_TIMEOUT`].
    pub fn new(transport: T) -> Self {
        Self {
            transport,
            decoder: FrameDecoder::new(),
            rx: Box::new([0; 4096]),
            rx_pos: 0,
            rx_len: 0,
            timeout: DEFAULT_TIMEOUT,
            counters: LinkCounters::default(),
            telemetry: VecDeque::new(),
            born: Instant::now(),
        }
    }

    /// Sets how long [`Client::request`] waits for a response.
    pub fn set_timeout(&mut self, timeout: Duration) {
        self.timeout = timeout;
    }

    /// The response timeout.
    pub fn timeout(&self) -> Duration {
        self.timeout
    }

    /// The transport.
    pub fn transport(&self) -> &T {
        &self.transport
    }

    /// The transport, mutably.
    pub fn transport_mut(&mut self) -> &mut T {
        &mut self.transport
    }

    /// Link counters so far.
    pub fn counters(&self) -> LinkCounters {
        self.counters
    }

    /// Sends a lone delimiter (the board's decoder drops whatever partial frame it holds),
    /// then discards whatever arrives within `quiet`: a clean start after noise or after
    /// another program used the port. A line that never falls quiet (telemetry left
    /// running) is discarded for at most 20 × `quiet` (at least 200 ms).
    pub fn resync(&mut self, quiet: Duration) -> Result<(), LinkError> {
        self.send_raw(&[0])?;
        let mut sink = [0u8; 256];
        let start = self.now();
        let limit = (quiet * 20).max(Duration::from_millis(200));
        while self.transport.receive(&mut sink, quiet)? > 0
            && self.now().saturating_sub(start) < limit
        {}
        self.decoder = FrameDecoder::new();
        self.rx_pos = 0;
        self.rx_len = 0;
        Ok(())
    }

    /// Sends raw bytes (tests use it to send deliberately broken frames).
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.transport.send(bytes)?;
        self.counters.bytes_sent += bytes.len() as u64;
        Ok(())
    }

    /// Encodes `requests` and sends them in one write (one transfer through a USB adapter,
    /// so they reach the board back to back), without waiting for their responses.
    pub fn send_together(&mut self, requests: &[Request]) -> Result<(), LinkError> {
        let mut bytes = Vec::new();
        let mut buf = [0u8; MAX_ENCODED + 1];
        for request in requests {
            let n = frame::encode(request, &mut buf).map_err(|reason| LinkError::Encode {
                request: request_name(request),
                reason,
            })?;
            bytes.extend_from_slice(&buf[..n]);
        }
        self.send_raw(&bytes)?;
        self.counters.frames_sent += requests.len() as u64;
        Ok(())
    }

    /// Encodes and sends `request` without waiting for its response.
    pub fn send(&mut self, request: &Request) -> Result<(), LinkError> {
        let mut buf = [0u8; MAX_ENCODED + 1];
        let n = frame::encode(request, &mut buf).map_err(|reason| LinkError::Encode {
            request: request_name(request),
            reason,
        })?;
        self.send_raw(&buf[..n])?;
        self.counters.frames_sent += 1;
        Ok(())
    }

    /// Time on the transport's clock (simulated time for the in-process board), else
    /// wall-clock time since the client was made: what a wait's budget is measured on.
    pub fn now(&self) -> Duration {
        self.transport
            .clock()
            .unwrap_or_else(|| self.born.elapsed())
    }

    /// Telemetry frames received so far (set aside by [`Client::receive`]), oldest first;
    /// they are handed over once.
    pub fn take_telemetry(&mut self) -> Vec<TelemetryFrame> {
        self.telemetry.drain(..).collect()
    }

    /// Receives for `duration` with no request outstanding, setting telemetry frames aside
    /// (as [`Client::wait`]); returns those received so far, oldest first.
    pub fn collect_telemetry(
        &mut self,
        duration: Duration,
    ) -> Result<Vec<TelemetryFrame>, LinkError> {
        self.wait(duration)?;
        Ok(self.take_telemetry())
    }

    /// Starts telemetry of `signals` (a [`twinstack::services::recorder::Channel`] mask), one sample
    /// every `decimation` ticks; frames set aside before are dropped (they belong to an
    /// earlier run).
    pub fn start_telemetry(&mut self, signals: u8, decimation: u16) -> Result<(), LinkError> {
        self.expect_ack(&Request::Telemetry(TelemetryRequest::Start {
            signals,
            decimation,
        }))?;
        self.telemetry.clear();
        Ok(())
    }

    /// Stops telemetry; the board still sends what it holds, then the end frame.
    pub fn stop_telemetry(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::Telemetry(TelemetryRequest::Stop))
            .map(drop)
    }

    /// The next response, waiting at most `timeout` for it; `Ok(None)` when none came.
    /// Corrupt frames are skipped (and counted); the decoder resynchronises at the next
    /// delimiter. Telemetry frames are set aside ([`Client::take_telemetry`]): they answer
    /// no request.
    pub fn receive(&mut self, timeout: Duration) -> Result<Option<Response>, LinkError> {
        let start = self.now();
        loop {
            while self.rx_pos < self.rx_len {
                let byte = self.rx[self.rx_pos];
                self.rx_pos += 1;
                match self.decoder.push(byte) {
                    None => {}
                    Some(Ok(body)) => match frame::decode_body::<Response>(body) {
                        Ok(Response::Telemetry(f)) => {
                            self.counters.telemetry_frames += 1;
                            self.telemetry.push_back(f);
                        }
                        Ok(r) => {
                            self.counters.frames_received += 1;
                            return Ok(Some(r));
                        }
                        Err(_) => self.counters.corrupt_frames += 1,
                    },
                    Some(Err(_)) => self.counters.corrupt_frames += 1,
                }
            }
            // Wall-clock time left; an in-process board advances its own clock inside
            // `receive` and reports the timeout by returning 0.
            let left = timeout.saturating_sub(self.now().saturating_sub(start));
            if left.is_zero() {
                return Ok(None);
            }
            let n = self.transport.receive(&mut self.rx[..], left)?;
            if n == 0 {
                return Ok(None);
            }
            self.counters.bytes_received += n as u64;
            self.rx_pos = 0;
            self.rx_len = n;
        }
    }

    /// Lets `duration` pass on the link with no request outstanding (an in-process board
    /// runs its ticks meanwhile); a response arriving now is a protocol error.
    pub fn wait(&mut self, duration: Duration) -> Result<(), LinkError> {
        match self.receive(duration)? {
            None => Ok(()),
            Some(r) => Err(LinkError::Unexpected {
                request: "(none)",
                got: format!("{r:?} while no request was outstanding"),
            }),
        }
    }

    /// Sends `request` and waits for its response (a NACK is returned as a response here;
    /// see [`Client::expect_ack`]).
    ///
    /// A `Frame(..)` NACK means the request was damaged on the line and nothing was applied,
    /// so it is sent again, up to [`FRAME_RETRIES`] times.
    pub fn request(&mut self, request: &Request) -> Result<Response, LinkError> {
        let corrupt_before = self.counters.corrupt_frames;
        let mut attempts = 0;
        loop {
            self.send(request)?;
            let response = self
                .receive(self.timeout)?
                .ok_or_else(|| LinkError::Timeout {
                    request: request_name(request),
                    timeout: self.timeout,
                    corrupt: (self.counters.corrupt_frames - corrupt_before) as u32,
                })?;
            match response {
                Response::Nack {
                    reason: NackReason::Frame(_),
                } if attempts < FRAME_RETRIES => attempts += 1,
                other => return Ok(other),
            }
        }
    }

    /// Sends `request`, expects an ACK and returns its credits; a NACK is an error.
    pub fn expect_ack(&mut self, request: &Request) -> Result<u16, LinkError> {
        let name = request_name(request);
        match self.request(request)? {
            Response::Ack { credits } => Ok(credits),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: name,
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: name,
                got: format!("{other:?}"),
            }),
        }
    }

    /// Sends `bytes` in a [`Request::Echo`] and returns what the board answered back (the
    /// same bytes on a sound link).
    pub fn echo(&mut self, bytes: &[u8]) -> Result<Vec<u8>, LinkError> {
        let payload = heapless::Vec::from_slice(bytes).map_err(|_| LinkError::Encode {
            request: "Echo",
            reason: FrameError::TooLarge,
        })?;
        match self.request(&Request::Echo(payload))? {
            Response::Echo(back) => Ok(back.to_vec()),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "Echo",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "Echo",
                got: format!("{other:?}"),
            }),
        }
    }

    /// Reads status and telemetry.
    pub fn status(&mut self) -> Result<StatusReport, LinkError> {
        match self.request(&Request::Status)? {
            Response::Status(s) => Ok(s),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "Status",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "Status",
                got: format!("{other:?}"),
            }),
        }
    }

    /// Selects the control mode.
    pub fn set_mode(&mut self, mode: Mode) -> Result<(), LinkError> {
        self.expect_ack(&Request::Mode(mode)).map(drop)
    }

    /// Starts, stops or configures the setpoint stream.
    pub fn stream(&mut self, control: StreamControl) -> Result<(), LinkError> {
        self.expect_ack(&Request::Stream(control)).map(drop)
    }

    /// Loads settings (the board validates them whole, prepares them off the tick and swaps
    /// them in between two ticks, the drive continuous).
    pub fn load_params(&mut self, settings: &Settings) -> Result<(), LinkError> {
        self.expect_ack(&Request::LoadParams(settings.clone()))
            .map(drop)
    }

    /// Writes the settings in force to the board's flash, to boot in `boot_mode`.
    pub fn store_params(&mut self, boot_mode: Mode) -> Result<(), LinkError> {
        self.expect_ack(&Request::StoreParams { boot_mode })
            .map(drop)
    }

    /// Reads the settings in force.
    pub fn read_params(&mut self) -> Result<Settings, LinkError> {
        match self.request(&Request::ReadParams)? {
            Response::Params(s) => Ok(s),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "ReadParams",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "ReadParams",
                got: format!("{other:?}"),
            }),
        }
    }

    /// Reloads the parameters stored in flash.
    pub fn recall_params(&mut self) -> Result<(), LinkError> {
        self.expect_ack(&Request::RecallParams).map(drop)
    }

    /// Starts the waveform generator.
    pub fn waveform(&mut self, waveform: Waveform) -> Result<(), LinkError> {
        self.expect_ack(&Request::Waveform(waveform)).map(drop)
    }

    /// Arms the data recorder.
    pub fn arm_recorder(&mut self, record: RecordRequest) -> Result<(), LinkError> {
        self.expect_ack(&Request::Record(record)).map(drop)
    }

    /// Reads one chunk of recorded values from `offset`.
    pub fn read_record(&mut self, offset: u32) -> Result<Vec<i32>, LinkError> {
        match self.request(&Request::ReadRecord { offset })? {
            Response::RecordChunk { offset: o, values } if o == offset => Ok(values.to_vec()),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "ReadRecord",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "ReadRecord",
                got: format!("{other:?}"),
            }),
        }
    }

    /// Reads `count` recorded values, chunk by chunk from offset 0, resuming at the next
    /// offset after each chunk; a chunk lost to a timeout or a corrupt frame is asked for
    /// again (up to 3 times). Fails unless exactly `count` values arrive.
    pub fn read_recording(
        &mut self,
        count: u32,
        progress: impl FnMut(u32),
    ) -> Result<Vec<i32>, LinkError> {
        self.read_chunks("ReadRecord", count, MAX_CHUNK, Self::read_record, progress)
    }
    /// Arms a multi-signal capture (protocol v4).
    pub fn arm_capture(&mut self, capture: CaptureRequest) -> Result<(), LinkError> {
        self.expect_ack(&Request::Capture(capture)).map(drop)
    }

    /// Reads the capture's state and the board's conversion facts.
    pub fn capture_status(&mut self) -> Result<CaptureStatus, LinkError> {
        match self.request(&Request::CaptureStatus)? {
            Response::Capture(s) => Ok(s),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "CaptureStatus",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "CaptureStatus",
                got: format!("{other:?}"),
            }),
        }
    }

    /// The analog setpoint input's state and counts (`Analog(Status)`).
    pub fn analog_status(&mut self) -> Result<AnalogStatus, LinkError> {
        match self.request(&Request::Analog(AnalogRequest::Status))? {
            Response::Analog(s) => Ok(s),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "Analog",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "Analog",
                got: format!("{other:?}"),
            }),
        }
    }

    /// A TTL-stepped sequence's state and counts (`Sequence(Status)`).
    pub fn sequence_status(&mut self) -> Result<SequenceStatus, LinkError> {
        match self.request(&Request::Sequence(SequenceRequest::Status))? {
            Response::Sequence(s) => Ok(s),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "Sequence",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "Sequence",
                got: format!("{other:?}"),
            }),
        }
    }

    /// The coarse axis's status (dual-stage boards).
    pub fn coarse_status(&mut self) -> Result<CoarseStatus, LinkError> {
        match self.request(&Request::CoarseStatus)? {
            Response::Coarse(s) => Ok(s),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "CoarseStatus",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "CoarseStatus",
                got: format!("{other:?}"),
            }),
        }
    }

    /// Sends a coarse-axis command (home, move, jog, stop, release); `Ok` once acknowledged.
    pub fn coarse(&mut self, request: &Request) -> Result<(), LinkError> {
        self.expect_ack(request).map(|_| ())
    }

    /// Reads one chunk of a complete capture's window from `offset`.
    pub fn read_capture(&mut self, offset: u32) -> Result<Vec<i16>, LinkError> {
        let count = MAX_CAPTURE_CHUNK as u16;
        match self.request(&Request::ReadCapture { offset, count })? {
            Response::CaptureChunk { offset: o, values } if o == offset => Ok(values.to_vec()),
            Response::Nack { reason } => Err(LinkError::Nack {
                request: "ReadCapture",
                reason,
            }),
            other => Err(LinkError::Unexpected {
                request: "ReadCapture",
                got: format!("{other:?}"),
            }),
        }
    }

    /// Reads a complete capture's whole window (`slots` values), chunk by chunk; a chunk lost
    /// to a timeout is asked for again (up to 3 times). Fails unless exactly `slots` values
    /// arrive.
    pub fn read_capture_window(
        &mut self,
        slots: u32,
        progress: impl FnMut(u32),
    ) -> Result<Vec<i16>, LinkError> {
        self.read_chunks(
            "ReadCapture",
            slots,
            MAX_CAPTURE_CHUNK,
            Self::read_capture,
            progress,
        )
    }

    /// Reads `count` values chunk by chunk with `read` (one request from an offset), resuming
    /// at the next offset after each chunk; a chunk lost to a timeout or a corrupt frame is
    /// asked for again (up to 3 times, draining the line first: a late answer would be taken
    /// for the next request's). An empty chunk, or one over `max_chunk` values, fails the
    /// read: the board holds fewer values than asked for, or does not speak this protocol.
    fn read_chunks<V: Copy>(
        &mut self,
        request: &'static str,
        count: u32,
        max_chunk: usize,
        mut read: impl FnMut(&mut Self, u32) -> Result<Vec<V>, LinkError>,
        mut progress: impl FnMut(u32),
    ) -> Result<Vec<V>, LinkError> {
        let mut values = Vec::with_capacity(count as usize);
        let mut retries = 0;
        while (values.len() as u32) < count {
            let offset = values.len() as u32;
            match read(self, offset) {
                Ok(chunk) if chunk.is_empty() => {
                    return Err(LinkError::Unexpected {
                        request,
                        got: format!(
                            "an empty chunk at offset {offset}: the board holds {offset} values, {count} were asked for"
                        ),
                    })
                }
                Ok(chunk) if chunk.len() > max_chunk => {
                    return Err(LinkError::Unexpected {
                        request,
                        got: format!(
                            "a chunk of {} values at offset {offset} (at most {max_chunk})",
                            chunk.len()
                        ),
                    })
                }
                Ok(chunk) => {
                    let take = chunk.len().min(count as usize - values.len());
                    values.extend_from_slice(&chunk[..take]);
                    retries = 0;
                    progress(values.len() as u32);
                }
                Err(LinkError::Timeout { .. }) if retries < 3 => {
                    retries += 1;
                    self.resync(Duration::from_millis(50))?;
                }
                Err(e) => return Err(e),
            }
        }
        Ok(values)
    }
}

impl<T> std::fmt::Debug for Client<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client")
            .field("timeout", &self.timeout)
            .field("counters", &self.counters)
            .finish()
    }
}
