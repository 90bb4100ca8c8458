//! The messages host and board exchange. Every request is answered by exactly one response.
//!
//! Setpoints travel as `i16`, Q1.15 fractions of the output range: the top 16 bits of the
//! tick's Q2.30 setpoint (`q2_30 = q1_15 << 15`), i.e. one LSB of a 16-bit DAC over the stroke.
//! That halves the bytes per sample, so that 2 Mbaud carries 50 000 setpoints/s with room for
//! framing and acknowledgements.

use crate::drive::{Configuration, SafeState};
use serde::{Deserialize, Serialize};

use super::frame::{FrameError, Message};

impl Message for Request {
    const VARIANTS: u32 = 10;
}

impl Message for Response {
    const VARIANTS: u32 = 4;
}

/// Most setpoints one batch carries.
pub const MAX_BATCH: usize = 96;
/// Most recorder values one chunk carries.
pub const MAX_CHUNK: usize = 64;
/// Most P–I operators a parameter message carries.
pub const MAX_PARAM_OPERATORS: usize = 32;

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
    /// Load a parameter set: validated whole, then swapped in between two ticks.
    LoadParams(ParamSet),
    /// Write the active parameters to flash.
    StoreParams,
    /// Reload the parameters stored in flash.
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
}

/// A batch of setpoints with its sequence number (wrapping), so the board can spot a lost batch.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct SetpointBatch {
    /// Sequence number; the next batch carries `seq + 1`.
    pub seq: u16,
    /// Setpoints, Q1.15 normalised displacement.
    pub samples: heapless::Vec<i16, MAX_BATCH>,
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
}

/// What the board does when the setpoint queue runs dry.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum UnderrunPolicy {
    /// Hold the last setpoint.
    Hold,
    /// Ramp to the rest position (the bias), within the slew limit.
    RampToBias,
}

/// Control mode (the settings' own enum, so a mode on the wire is a mode in the settings):
/// `Bypass` (the drive follows the setpoint linearly), `OpenLoop` (inverse-model feedforward),
/// `ClosedLoop` (feedforward plus sensor feedback).
pub use crate::settings::Mode;

/// A hysteresis model in physical units (`f32` on the wire).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum ModelParams {
    /// Prandtl–Ishlinskii: `y = a0 u + Σ w_i P_{r_i}[u] + offset`.
    PrandtlIshlinskii {
        /// Linear term, output units per volt.
        a0: f32,
        /// Output offset.
        offset: f32,
        /// Thresholds, volts.
        thresholds: heapless::Vec<f32, MAX_PARAM_OPERATORS>,
        /// Weights, output units per volt.
        weights: heapless::Vec<f32, MAX_PARAM_OPERATORS>,
    },
    /// Duhem: `ẏ = α|u̇|(βu + offset − y) + γu̇`.
    Duhem {
        /// α, per volt.
        alpha: f32,
        /// β, output units per volt.
        beta: f32,
        /// γ, output units per volt.
        gamma: f32,
        /// Offset, output units.
        offset: f32,
    },
}

/// Everything a parameter load sets.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ParamSet {
    /// The model (compensator and observer).
    pub model: ModelParams,
    /// Model input range, volts (left stack).
    pub input_range: [f32; 2],
    /// Model output range, output units.
    pub output_range: [f32; 2],
    /// Differential or unidirectional.
    pub configuration: Configuration,
    /// Bias ū, volts.
    pub bias: f32,
    /// Stack voltage limits `[min, max]`, volts (unidirectional: the right stack idles at
    /// `min`).
    pub voltage_limits: [f32; 2],
    /// Slew limit, volts per second.
    pub slew_rate: f32,
    /// Safe state on a fault.
    pub safe_state: SafeState,
    /// Sensor feedback: PI(D) gains, correction limit, notch and drift limit.
    pub feedback: Option<FeedbackParams>,
    /// Mode to enter once loaded.
    pub mode: Mode,
}

/// Sensor feedback on the wire (see `settings::FeedbackSettings`, which it becomes with the
/// board's sensor calibration). Gains in normalised units (drive fraction per displacement
/// fraction).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct FeedbackParams {
    /// Proportional gain, 0 ≤ kp < 7.5.
    pub kp: f32,
    /// Integral gain, per second (below the control rate).
    pub ki: f32,
    /// Derivative gain, seconds (0: none).
    pub kd: f32,
    /// Corner of the derivative's low pass, Hz.
    pub derivative_cutoff_hz: f32,
    /// Largest correction, fraction of the drive range (0…1].
    pub limit: f32,
    /// Notch on the error at the stage resonance, if any.
    pub notch: Option<NotchParams>,
    /// Drift limit, fraction of the output range (0…1], if the drift check is wanted.
    pub drift_limit: Option<f32>,
}

/// The resonance notch on the wire (see `notch::NotchDesign`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct NotchParams {
    /// Centre frequency, Hz.
    pub frequency_hz: f32,
    /// Quality factor (centre over −3 dB width).
    pub q: f32,
    /// Gain at the centre, 0…1.
    pub depth: f32,
}

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
}

/// Waveform shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum WaveShape {
    /// Sine.
    Sine,
    /// Symmetric triangle.
    Triangle,
}

/// Signals the recorder can capture.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Signal {
    /// The setpoint, Q2.30.
    Setpoint,
    /// The applied drive, Q2.30 model-normalised.
    Drive,
    /// The sensor reading, Q2.30.
    Sensor,
    /// The observer's estimate, Q2.30.
    Estimate,
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
}

/// Why a request was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
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
    /// A value is out of its range (rate divider 0, frequency too high, …).
    OutOfRange,
    /// The parameters were refused by validation.
    InvalidParams(crate::params::ParamError),
    /// The drive settings were refused.
    InvalidDrive(crate::drive::DriveError),
    /// The request needs something the board lacks (closed loop without a sensor, a model
    /// mode without a model, a store on a board without parameter storage, …).
    Unsupported,
    /// Not now: storing to flash stalls the tick, so it is refused while the stream or the
    /// waveform runs.
    Busy,
    /// Recall found no valid parameter set in flash (erased, damaged, or an older record).
    NothingStored,
    /// Writing the flash record failed (erase or program error, or the read-back differs).
    StoreFailed,
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
    /// Ticks that did not finish before the next.
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
    /// Values the recorder holds (of the count armed).
    pub recorded: u32,
    /// Flags, see [`StatusReport::DEFAULTS`] and the other `StatusReport` constants.
    pub flags: u16,
}

impl StatusReport {
    /// Flag: the parameters in use are the compiled-in defaults (flash record bad or absent).
    pub const DEFAULTS: u16 = 1 << 0;
    /// Flag: the setpoint stream is running (consuming the queue).
    pub const STREAMING: u16 = 1 << 1;
    /// Flag: the waveform generator is running.
    pub const WAVEFORM: u16 = 1 << 2;
    /// Flag: the recorder is capturing.
    pub const RECORDING: u16 = 1 << 3;
    /// Flag: a parameter load is waiting for the next tick.
    pub const CONFIG_PENDING: u16 = 1 << 4;
    /// Flags bits 8–9: the mode (0 bypass, 1 open loop, 2 closed loop).
    pub const MODE_SHIFT: u16 = 8;

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
}
