//! The messages host and board exchange. Every request is answered by exactly one response.
//!
//! Setpoints travel as `i16`, Q1.15 fractions of the output range: the top 16 bits of the
//! tick's Q2.30 setpoint (`q2_30 = q1_15 << 15`), i.e. one LSB of a 16-bit DAC over the stroke.
//! That halves the bytes per sample, so that 2 Mbaud carries 50 000 setpoints/s with room for
//! framing and acknowledgements.

use crate::config::settings::Settings;
pub use crate::dual_stage::{CoarseState, CoarseStatus};
use crate::refusal::Refusal;
pub use crate::services::learning::{LearnSettings, LearnState, PeriodError};
pub use crate::services::recorder::{CaptureState, Signal, Trigger, MAX_CAPTURE_CHUNK, MAX_CHUNK};
pub use crate::services::telemetry::{TelemetryFrame, MAX_TELEMETRY_VALUES};
pub use crate::sources::analog_input::{AnalogInputConfig, AnalogRequest, AnalogStatus, OnFault};
pub use crate::sources::scan::{
    LissajousScan, RasterScan, ScanPattern, ScanRequest, SpiralScan, TriggerConfig, TriggerEdge,
};
pub use crate::sources::sequence::{SequenceConfig, SequenceRequest, SequenceStatus};
pub use crate::sources::setpoint_stream::UnderrunPolicy;
use serde::{Deserialize, Serialize};

use super::frame::{FrameError, Message, MAX_BODY};

impl Message for Request {
    const VARIANTS: u32 = 29;
}

impl Message for Response {
    const VARIANTS: u32 = 13;
}

/// Most setpoints one batch carries.
pub const MAX_BATCH: usize = 96;

/// Host → board.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Request {
    /// Read status and telemetry.
    Status,
    /// Queue setpoints; answered with the credits left.
    Setpoints(SetpointBatch),
    /// Start or stop the setpoint stream, or set its rate.
    Stream(StreamControl),
    /// Select the control mode.
    Mode(Mode),
    /// Load settings: validated whole, prepared off the tick, swapped in between two ticks
    /// with the drive continuous.
    LoadParams(Settings),
    /// Write the settings in force to flash, to boot in `boot_mode` (bypass unless the user
    /// asks for more).
    StoreParams {
        /// The mode the board boots into with this record.
        boot_mode: Mode,
    },
    /// Reload the settings stored in flash (in the mode stored with them).
    RecallParams,
    /// Run the built-in waveform generator instead of the stream.
    Waveform(Waveform),
    /// Arm the data recorder.
    Record(RecordRequest),
    /// Read recorded values from `offset`.
    ReadRecord {
        /// First value to read.
        offset: u32,
    },
    /// Read the settings in force (answered with [`Response::Params`]).
    ReadParams,
    /// Arm a multi-signal capture (protocol v4); the previous capture or record is discarded.
    Capture(CaptureRequest),
    /// Read the capture's state (answered with [`Response::Capture`]).
    CaptureStatus,
    /// Read up to `count` slots of a complete capture's window from `offset` (answered with
    /// [`Response::CaptureChunk`]).
    ReadCapture {
        /// First slot (frames × signals from the window's start).
        offset: u32,
        /// Most slots wanted; the board sends at most [`MAX_CAPTURE_CHUNK`].
        count: u16,
    },
    /// Start or stop continuous telemetry (protocol v5): the board then sends
    /// [`Response::Telemetry`] frames, unsolicited, between its responses.
    Telemetry(TelemetryRequest),
    /// Home the dual-actuated stage's coarse axis (protocol v5; clears a latched fault).
    /// Acknowledged when the homing starts; [`Request::CoarseStatus`] shows its progress.
    CoarseHome,
    /// Move the coarse axis to a position (homed axis, target within the travel).
    CoarseMove(CoarseMove),
    /// Jog the coarse axis toward a soft travel limit until [`Request::CoarseStop`].
    CoarseJog {
        /// Speed, mm/s; positive toward the upper limit.
        velocity_mm_s: f64,
    },
    /// Controlled stop of the coarse axis (it brakes at the move's acceleration).
    CoarseStop,
    /// Read the coarse axis's status (answered with [`Response::Coarse`]).
    CoarseStatus,
    /// Learning feedforward (protocol v6, [`crate::services::learning`]): configure, switch, reset,
    /// read its status, read or write its table.
    Learn(LearnRequest),
    /// Run a scan pattern (protocol v6, [`crate::sources::scan`]): now, or when the armed external
    /// trigger fires; stopped by `Stream(Stop)`, replaced by a stream or waveform start.
    Scan(ScanRequest),
    /// Trigger I/O settings (protocol v6): the outputs' pulse width, and the external input's
    /// edge (arming it, one shot) and whether it also starts the stream.
    Trigger(TriggerConfig),
    /// [`Request::Setpoints`] with every sample in two bytes, whatever its value
    /// ([`PackedBatch`]); answered the same way. What the host streams with.
    PackedSetpoints(PackedBatch),
    /// A TTL-stepped sequence ([`crate::sources::sequence`]): arm it over the positions queued (sent
    /// as setpoints), stop it, or read its counts (answered with [`Response::Sequence`]).
    Sequence(SequenceRequest),
    /// Answer these bytes back ([`Response::Echo`], the same bytes): what `twinstack
    /// selftest` checks the link's integrity with, frames of any content and length up to the
    /// largest. Handled as a command (the low-priority task), never on the tick.
    Echo(heapless::Vec<u8, MAX_ECHO>),
    /// The analog setpoint input ([`crate::sources::analog_input`]): start it as the setpoint source
    /// (refused with `Busy` while another source runs), stop it, or read its state (answered
    /// with [`Response::Analog`]).
    Analog(AnalogRequest),
    /// Stop feeding the watchdog, to prove it resets the board (`twinstack selftest`'s
    /// watchdog check): acknowledged, then the board resets within
    /// [`crate::board::WATCHDOG_TIMEOUT_MS`] and starts again on its stored settings (its
    /// safe state until then), reporting [`StatusReport::WATCHDOG_RESET`]. Refused with
    /// `Busy` while a setpoint source drives the outputs or the flash is written, and with
    /// `Unsupported` by an image without a watchdog (QEMU models none). Until the reset, a
    /// source start (stream, waveform, scan, sequence, analog input, or a trigger set to start
    /// the stream) is refused with `Busy` and an armed input edge starts nothing, so the
    /// reset cuts off no motion.
    WatchdogDrill,
    /// Hand the piezo's setpoint back from the dual-actuated stage's coarse axis to the
    /// piezo's own sources (the stream, the waveform, scans, sequences, the analog input): the
    /// coarse axis holds where it is (its task runs on: encoders, switches, status), and its
    /// next move, jog or homing takes the piezo again, its fine ramp leaving from where the
    /// piezo's sources left it. `Ack` (also when already handed back); `Busy` while the axis
    /// homes, moves, jogs or brakes; `Refused(CoarseAxis, NoHardware)` without a coarse axis.
    /// While the piezo is handed back, a move, jog or homing is refused with `Busy` as long as
    /// one of its sources runs or waits for the trigger input (stop it first): nothing the
    /// board accepted is cut off. [`StatusReport::COARSE`] is clear while it is handed back.
    CoarseRelease,
}

/// Most bytes one [`Request::Echo`] carries: what fills a frame body of [`MAX_BODY`]
/// (version, tag, a two-byte length, the bytes, the CRC), so an echo both ways is as large a
/// frame as the protocol sends.
///
/// ```
/// use twinstack::protocol::frame::{encode, MAX_BODY, MAX_ENCODED};
/// use twinstack::protocol::messages::{Request, Response, MAX_ECHO};
/// let bytes: heapless::Vec<u8, MAX_ECHO> = (0..MAX_ECHO).map(|i| i as u8).collect();
/// let mut out = [0u8; MAX_ENCODED + 1];
/// assert!(encode(&Request::Echo(bytes.clone()), &mut out).is_ok());
/// assert!(encode(&Response::Echo(bytes), &mut out).is_ok());
/// assert_eq!(MAX_ECHO, MAX_BODY - 8);
/// ```
pub const MAX_ECHO: usize = MAX_BODY - 8;

/// Start or stop continuous telemetry.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum TelemetryRequest {
    /// Stream the signals of `signals` (a [`crate::services::recorder::Channel`] mask, as a capture's),
    /// one sample every `decimation` ticks, until stopped; a running telemetry is restarted.
    Start {
        /// Signal mask: bit 0 setpoint, 1 left stack, 2 right stack, 3 sensor, 4 estimate,
        /// 5 error.
        signals: u8,
        /// Ticks per sample, ≥ 1 (and at least what keeps `signals × rate` within
        /// [`crate::services::telemetry::MAX_VALUES_PER_SECOND`]).
        decimation: u16,
    },
    /// Stop: the samples queued are still sent, then a frame with `end` set.
    Stop,
}

/// A coarse move: target and trapezoid, in millimetres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CoarseMove {
    /// Target position (user coordinates, relative to the home reference), mm.
    pub target_mm: f64,
    /// Cruise speed, mm/s (> 0, at most the coarse stage's limit).
    pub velocity_mm_s: f64,
    /// Acceleration, mm/s² (> 0, at most the coarse stage's limit).
    pub acceleration_mm_s2: f64,
}

/// What a [`Request::Learn`] asks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum LearnRequest {
    /// Validate and set the period, gain, robustness filter, lead and limit (the period
    /// restarts at bin 0). Refused naming the `learning.*` field.
    Configure(LearnSettings),
    /// Off, learning (needs a sensor and a configuration) or frozen (needs a configuration).
    State(LearnState),
    /// Zero the table (it plays from the next period boundary).
    Reset,
    /// Answered with [`Response::Learn`].
    Status,
    /// Read the table (Q2.30 normalised drive) from `offset`: answered with
    /// [`Response::RecordChunk`] (at most [`MAX_CHUNK`] values, up to the period's end).
    ReadTable {
        /// First bin.
        offset: u32,
    },
    /// Write table values (Q2.30, each limited to the configured limit) from bin `offset`
    /// into the task's table; [`LearnRequest::PostTable`] makes it play.
    WriteTable {
        /// First bin.
        offset: u32,
        /// Values.
        values: heapless::Vec<i32, MAX_CHUNK>,
    },
    /// Post the task's table (a recalled one): it plays from the next period boundary.
    PostTable,
}

/// The learning's state and its last period (the answer to `Learn(Status)`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LearnStatus {
    /// Off, learning, frozen.
    pub state: LearnState,
    /// Period, ticks (0: not configured).
    pub period_ticks: u16,
    /// Periods the tick completed (wrapping).
    pub periods: u32,
    /// Tables the task posted.
    pub updates: u32,
    /// Periods the task could not copy in time.
    pub missed: u32,
    /// The last period the task took: its error (Q2.30 normalised displacement, as the
    /// sensor saw it).
    pub last: PeriodError,
}

/// Arm a multi-signal capture: `samples` frames of the signals in `signals`, `pre_trigger` of
/// them from before the trigger, one frame every `decimation` ticks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CaptureRequest {
    /// Signal mask: bit 0 setpoint, 1 left stack, 2 right stack, 3 sensor, 4 estimate,
    /// 5 error ([`crate::services::recorder::Channel`]).
    pub signals: u8,
    /// Frames (values per signal), pre-trigger included; `signals × samples` ≤ the board's
    /// capture slots.
    pub samples: u32,
    /// Frames kept from before the trigger (< `samples`; 0 with [`Trigger::Now`]).
    pub pre_trigger: u32,
    /// What triggers it.
    pub trigger: Trigger,
    /// Ticks per frame, ≥ 1.
    pub decimation: u16,
}

/// A capture's state, and what the host needs to put its values in physical units.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CaptureStatus {
    /// Idle (nothing armed), armed, triggered, done.
    pub state: CaptureState,
    /// Signal mask armed.
    pub signals: u8,
    /// Frames armed for, pre-trigger included.
    pub samples: u32,
    /// Pre-trigger frames armed for.
    pub pre_trigger: u32,
    /// Pre-trigger frames the window holds (≤ `pre_trigger`: fewer if the trigger came
    /// before that many frames).
    pub pre_available: u32,
    /// Frames of the window captured so far.
    pub captured: u32,
    /// Slots the complete window holds (`(pre_available + samples − pre_trigger) ×
    /// signals`); what `ReadCapture` reaches once done.
    pub window_slots: u32,
    /// Ticks per frame.
    pub decimation: u16,
    /// Slots the board's capture buffer holds.
    pub capacity: u32,
    /// Control rate, Hz.
    pub tick_rate_hz: u32,
    /// Full-scale DAC code (a stack's volts are `code × amplifier_full_scale /
    /// dac_full_scale`).
    pub dac_full_scale: u16,
    /// Amplifier output at DAC full scale, volts.
    pub amplifier_full_scale: f32,
}

/// A batch of setpoints with its sequence number (wrapping), so the board can spot a lost batch.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SetpointBatch {
    /// Sequence number; the next batch carries `seq + 1`.
    pub seq: u16,
    /// Setpoints, Q1.15 normalised displacement.
    pub samples: heapless::Vec<i16, MAX_BATCH>,
}

/// A [`SetpointBatch`] whose samples travel as fixed two-byte little-endian words (a byte
/// string of `2 × len` bytes) instead of `Setpoints`' zigzag varints, which take three bytes
/// for any sample of magnitude 8 192 or more (three quarters of a full-range sweep). So a
/// full batch of [`MAX_BATCH`] is at most 205 bytes on the wire, 2.14 bytes a setpoint,
/// whatever the setpoints: 100 000 setpoints/s need 213 542 bytes/s, 71 % of 3 Mbaud.
///
/// ```
/// use twinstack::protocol::messages::{PackedBatch, Request};
/// let batch = PackedBatch { seq: 1, samples: heapless::Vec::from_slice(&[100, -100]).unwrap() };
/// let mut buf = [0u8; 16];
/// let bytes = postcard::to_slice(&Request::PackedSetpoints(batch.clone()), &mut buf).unwrap();
/// // tag 23, seq 1, 4 bytes: 100 and −100 little-endian.
/// assert_eq!(bytes, [23, 1, 4, 100, 0, 156, 255]);
/// assert_eq!(postcard::from_bytes::<Request>(bytes).unwrap(), Request::PackedSetpoints(batch));
/// ```
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PackedBatch {
    /// Sequence number, as [`SetpointBatch::seq`] (the two kinds share the numbering).
    pub seq: u16,
    /// Setpoints, Q1.15 normalised displacement.
    #[serde(with = "packed_samples")]
    pub samples: heapless::Vec<i16, MAX_BATCH>,
}

impl From<PackedBatch> for SetpointBatch {
    fn from(b: PackedBatch) -> Self {
        SetpointBatch {
            seq: b.seq,
            samples: b.samples,
        }
    }
}

/// Samples as a byte string of little-endian `i16`s.
mod packed_samples {
    use super::MAX_BATCH;
    use serde::de::{Error, Visitor};
    use serde::{Deserializer, Serializer};

    type Samples = heapless::Vec<i16, MAX_BATCH>;

    pub fn serialize<S: Serializer>(samples: &Samples, s: S) -> Result<S::Ok, S::Error> {
        let mut bytes = [0u8; 2 * MAX_BATCH];
        for (pair, x) in bytes.chunks_exact_mut(2).zip(samples) {
            pair.copy_from_slice(&x.to_le_bytes());
        }
        s.serialize_bytes(&bytes[..2 * samples.len()])
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Samples, D::Error> {
        struct Packed;
        impl<'de> Visitor<'de> for Packed {
            type Value = Samples;
            fn expecting(&self, f: &mut core::fmt::Formatter) -> core::fmt::Result {
                write!(f, "an even number of bytes, at most {}", 2 * MAX_BATCH)
            }
            fn visit_bytes<E: Error>(self, bytes: &[u8]) -> Result<Samples, E> {
                if bytes.len() % 2 != 0 || bytes.len() > 2 * MAX_BATCH {
                    return Err(E::invalid_length(bytes.len(), &self));
                }
                let mut out = Samples::new();
                for pair in bytes.chunks_exact(2) {
                    // At most MAX_BATCH pairs: always room.
                    let _ = out.push(i16::from_le_bytes([pair[0], pair[1]]));
                }
                Ok(out)
            }
            fn visit_borrowed_bytes<E: Error>(self, bytes: &'de [u8]) -> Result<Samples, E> {
                self.visit_bytes(bytes)
            }
        }
        d.deserialize_bytes(Packed)
    }
}

/// Stream control.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum StreamControl {
    /// Start consuming the queue.
    Start,
    /// Stop; the output holds.
    Stop,
    /// Consume one setpoint every `divider` ticks, interpolating linearly in between.
    Rate {
        /// Ticks per streamed setpoint, ≥ 1.
        divider: u16,
    },
    /// What to do when the queue runs dry.
    Underrun(UnderrunPolicy),
    /// The host has sent its last setpoint: play the queue, then stop (the output holds the
    /// last setpoint), so the ticks after the end are not counted as underruns and the
    /// underrun counter's change over a stream is exactly the stream's underruns. Sent before
    /// `Start` (a record queued whole), it holds for the stream `Start` begins; `Stop` and a
    /// waveform cancel it.
    Finish,
}

/// Control mode (the settings' own enum, so a mode on the wire is a mode in the settings):
/// `Bypass` (the drive follows the setpoint linearly), `OpenLoop` (inverse-model feedforward),
/// `ClosedLoop` (feedforward plus sensor feedback).
pub use crate::config::settings::Mode;

/// The built-in waveform generator.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Waveform {
    /// Sine or triangle.
    pub shape: WaveShape,
    /// Offset, Q1.15 normalised displacement.
    pub offset: i16,
    /// Amplitude, Q1.15 normalised displacement.
    pub amplitude: i16,
    /// Frequency, millihertz.
    pub frequency_mhz: u32,
    /// Amplitude decay per cycle (protocol v5); `None`: constant amplitude.
    pub decay: Option<WaveDecay>,
}

/// A waveform's amplitude decay ([`crate::sources::waveform::WaveformGenerator::with_decay`]): the first
/// `hold_cycles` cycles (at least one) at the full amplitude, then each cycle's amplitude is
/// the previous one's × `keep / 65536` — full-range cycles, then nested minor loops.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct WaveDecay {
    /// Cycles at full amplitude (0 counts as 1).
    pub hold_cycles: u16,
    /// Amplitude kept per cycle after them, Q0.16 (`keep / 65536`, below 1).
    pub keep: u16,
}

/// Waveform shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum WaveShape {
    /// Sine.
    Sine,
    /// Symmetric triangle.
    Triangle,
}

/// Arm the recorder: capture `ticks` ticks of `signal`, one value every `decimation` ticks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RecordRequest {
    /// What to capture.
    pub signal: Signal,
    /// How many values.
    pub count: u32,
    /// Ticks per captured value, ≥ 1.
    pub decimation: u16,
}

/// Board → host.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Response {
    /// Accepted; `credits` setpoint slots are free in the queue.
    Ack {
        /// Free queue slots: the host never sends more setpoints than this.
        credits: u16,
    },
    /// Refused; nothing was applied and nothing queued was lost.
    Nack {
        /// Why.
        reason: NackReason,
    },
    /// Status and telemetry.
    Status(StatusReport),
    /// Recorded values.
    RecordChunk {
        /// Index of the first value.
        offset: u32,
        /// Values, Q2.30.
        values: heapless::Vec<i32, MAX_CHUNK>,
    },
    /// The settings in force (the answer to [`Request::ReadParams`]).
    Params(Settings),
    /// The capture's state (the answer to [`Request::CaptureStatus`]).
    Capture(CaptureStatus),
    /// Slots of a capture's window (the answer to [`Request::ReadCapture`]).
    CaptureChunk {
        /// Index of the first slot.
        offset: u32,
        /// Slots, each in its signal's format (see [`crate::services::recorder`]).
        values: heapless::Vec<i16, MAX_CAPTURE_CHUNK>,
    },
    /// Unsolicited (protocol v5): telemetry samples, sent between responses while telemetry
    /// runs. It answers no request: a host matching responses to requests sets it aside.
    Telemetry(TelemetryFrame),
    /// The coarse axis's status (the answer to [`Request::CoarseStatus`]).
    Coarse(CoarseStatus),
    /// The learning's state (the answer to `Learn(Status)`).
    Learn(LearnStatus),
    /// A sequence's state and counts (the answer to `Sequence(Status)`).
    Sequence(SequenceStatus),
    /// The bytes of a [`Request::Echo`], as they arrived.
    Echo(heapless::Vec<u8, MAX_ECHO>),
    /// The analog input's state and counts (the answer to `Analog(Status)`).
    Analog(AnalogStatus),
}

/// Why a request was refused. Wire-stable: variants are only appended.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum NackReason {
    /// The frame itself was bad.
    Frame(FrameError),
    /// More setpoints than the credits granted.
    QueueFull,
    /// A batch's sequence number is not the one expected (a batch was lost).
    OutOfSequence {
        /// The sequence number the board expected.
        expected: u16,
    },
    /// A field of the request was refused: which, and the rule (with its limit) it broke.
    Refused(Refusal),
    /// The board has no parameter storage.
    NoStorage,
    /// Not now: storing to flash stalls the tick, so it is refused while the stream or the
    /// waveform runs; a setpoint source is refused while another one runs (the analog input
    /// and the stream, the waveform, a scan or a sequence exclude each other).
    Busy,
    /// Recall found no valid settings in flash (erased, damaged, or an older record).
    NothingStored,
    /// Writing the flash record failed (erase or program error, or the read-back differs).
    StoreFailed,
    /// Sent by a host-side server sharing the board among several clients, never by the
    /// board: another client owns what this request changes (the stream and settings, or the
    /// telemetry); this client may read.
    NotOwner,
    /// This build cannot do it: the emulator image has no watchdog to drill; a dual-stage
    /// image whose coarse axis owns the piezo's setpoint plays no other setpoint source
    /// (setpoints, the stream's start, the waveform, a scan, a sequence, the analog input, a
    /// trigger input armed to start the stream).
    Unsupported,
}

/// Status and telemetry. Counters count since start-up and wrap after 2^32 events.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StatusReport {
    /// Ticks since start-up.
    pub ticks: u32,
    /// Setpoints queued.
    pub queue_fill: u16,
    /// Free queue slots.
    pub credits: u16,
    /// Ticks the running stream found the queue empty (held or ramped, as the policy says).
    pub underruns: u32,
    /// Ticks that did not finish before the next, and ticks whose snapshot the services
    /// could not take (the snapshot ring full: [`crate::services::snapshot`]).
    pub overruns: u32,
    /// Frames refused for their CRC.
    pub crc_errors: u32,
    /// Frames refused for any other frame error (stuffing, size, version, type, fields).
    pub frame_errors: u32,
    /// Ticks a limit (range or slew) clipped the drive.
    pub limit_hits: u32,
    /// The observer's estimate, Q2.30 normalised displacement.
    pub estimate: i32,
    /// The sequence number the next setpoint batch must carry.
    pub next_seq: u16,
    /// Control rate, Hz.
    pub tick_rate_hz: u32,
    /// Values a v3 `Record` holds (of the count armed); 0 while the buffer holds a v4
    /// capture, whose progress is in [`CaptureStatus`].
    pub recorded: u32,
    /// Flags, see [`StatusReport::DEFAULTS`] and the other `StatusReport` constants.
    pub flags: u16,
    /// Ticks the drift check flagged (protocol v9): with an observer and a sensor with a drift
    /// limit, ticks whose low-passed difference between the measurement and the observer's
    /// estimate exceeded the limit — the model no longer describes the stage. Counted by the
    /// services below the tick ([`crate::services::consumer::Services::drifts`]), up to a
    /// batch of 8 ticks behind; since start-up, across loads (a load does not reset it).
    pub drifts: u32,
}

impl StatusReport {
    /// Flag: the parameters in use are the compiled-in defaults (flash record bad or absent).
    pub const DEFAULTS: u16 = 1 << 0;
    /// Flag: the setpoint stream is running (consuming the queue).
    pub const STREAMING: u16 = 1 << 1;
    /// Flag: the waveform generator is running.
    pub const WAVEFORM: u16 = 1 << 2;
    /// Flag: the recorder is capturing (a v3 record or a v4 capture, armed or triggered).
    pub const RECORDING: u16 = 1 << 3;
    /// Flag (protocol v5): telemetry is running (or sending its last frames).
    pub const TELEMETRY: u16 = 1 << 5;
    /// Flag (protocol v6): a scan runs (its approach or pattern; clear once its last frame
    /// is done, or while it waits for the trigger).
    pub const SCANNING: u16 = 1 << 6;
    /// Flag (protocol v6): the external trigger input is armed.
    pub const TRIGGER_ARMED: u16 = 1 << 7;
    /// Flag: a TTL-stepped sequence is armed (`Request::Sequence`).
    pub const SEQUENCE: u16 = 1 << 10;
    /// Flag: the analog input is the setpoint source (`Request::Analog`).
    pub const ANALOG: u16 = 1 << 11;
    /// Flag: the analog input is lost or over-range (its fault behaviour holds or ramps).
    pub const ANALOG_FAULT: u16 = 1 << 14;
    /// Flag: the board last started from a watchdog reset (its tick stopped feeding the
    /// watchdog: a hang, or a [`Request::WatchdogDrill`]); set until the next reset.
    pub const WATCHDOG_RESET: u16 = 1 << 15;
    /// Flag: the dual-actuated stage's coarse axis owns the piezo's setpoint (the dual-stage
    /// images, from the coarse task's first post until [`Request::CoarseRelease`], and again
    /// from the next coarse motion); the piezo's own sources are refused meanwhile. (Bit 4
    /// was protocol v2's "load waiting for the next tick", unused since v3.)
    pub const COARSE: u16 = 1 << 4;
    /// Flags bits 8–9: the mode (0 bypass, 1 open loop, 2 closed loop).
    pub const MODE_SHIFT: u16 = 8;
    /// Flags bits 12–13: which build answers ([`Image`]; 0 from images older than the field).
    pub const IMAGE_SHIFT: u16 = 12;

    /// The mode the flags carry.
    pub fn mode(&self) -> Mode {
        match (self.flags >> Self::MODE_SHIFT) & 0b11 {
            0 => Mode::Bypass,
            1 => Mode::OpenLoop,
            _ => Mode::ClosedLoop,
        }
    }

    /// Whether `flag` is set.
    pub fn has(&self, flag: u16) -> bool {
        self.flags & flag != 0
    }

    /// The build that sent the report (flags bits 12–13).
    pub fn image(&self) -> Image {
        Image::from_code(self.flags >> Self::IMAGE_SHIFT)
    }
}

/// Which build of the board's code answers: the board image (`twinstack-fw`), the QEMU
/// emulator image (`twinstack-emu`) or the host's simulated board (`hal-sim`). Carried in
/// [`StatusReport::flags`] (bits 12–13, [`StatusReport::IMAGE_SHIFT`]) so that the host can
/// tell an emulator image flashed onto a board, or a board image booted in QEMU, from the
/// right one.
///
/// ```
/// use twinstack::protocol::messages::{Image, StatusReport};
/// let report = StatusReport { flags: Image::Emulator.code() << StatusReport::IMAGE_SHIFT, ..Default::default() };
/// assert_eq!(report.image(), Image::Emulator);
/// assert_eq!(Image::THIS, Image::Simulator); // doc tests run on the host
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Image {
    /// Not said: an image from before the field (its bits read 0).
    Unknown,
    /// The driver board's image (`cargo build-fw`).
    Board,
    /// The QEMU `netduinoplus2` image (`cargo build-emu`).
    Emulator,
    /// The simulated board on the host (`hal-sim`, `--port sim`, `virtual-board`).
    Simulator,
}

impl Image {
    /// The build this code is compiled into: the simulator on a host, else the emulator image
    /// with the `emulator` feature, else the board image.
    pub const THIS: Image = if cfg!(not(target_os = "none")) {
        Image::Simulator
    } else if cfg!(feature = "emulator") {
        Image::Emulator
    } else {
        Image::Board
    };

    /// The 2-bit code in the status flags.
    pub const fn code(self) -> u16 {
        match self {
            Image::Unknown => 0,
            Image::Board => 1,
            Image::Emulator => 2,
            Image::Simulator => 3,
        }
    }

    /// The image of a 2-bit code (higher bits ignored).
    pub const fn from_code(code: u16) -> Image {
        match code & 0b11 {
            1 => Image::Board,
            2 => Image::Emulator,
            3 => Image::Simulator,
            _ => Image::Unknown,
        }
    }

    /// The name the host prints (`board`, `emulator`, `simulator`, `unknown`).
    pub const fn name(self) -> &'static str {
        match self {
            Image::Unknown => "unknown",
            Image::Board => "board",
            Image::Emulator => "emulator",
            Image::Simulator => "simulator",
        }
    }
}

/// The next frame of a running telemetry ([`crate::services::telemetry::TelemetryPacker::next_frame`]), encoded as a
/// complete protocol frame ([`Response::Telemetry`], delimiter included) into `out`; returns
/// its length, or `None` when no frame is due.
pub fn encode_telemetry<const N: usize>(
    packer: &mut crate::services::telemetry::TelemetryPacker,
    queue: &mut heapless::spsc::Consumer<'_, crate::services::telemetry::TelemetrySample, N>,
    out: &mut [u8],
) -> Option<usize> {
    let frame = packer.next_frame(queue)?;
    super::frame::encode(&Response::Telemetry(frame), out).ok()
}
