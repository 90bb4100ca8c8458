//! The data recorder: captures signals of the control tick into a fixed buffer of 16-bit
//! slots, for the host to read back in chunks. Two ways to arm it share the one buffer (arming
//! either discards the previous capture):
//!
//! * **Capture** ([`Recorder::arm_capture`], protocol `Capture`): a SET of signals per
//!   captured tick ([`Channel`], a bitmask), one 16-bit value each, frame after frame in one
//!   ring buffer (`samples ≤` [`Recorder::max_frames`], about capacity / signals), with a pre-trigger
//!   count and a trigger: now, on stream start, on waveform start ([`Trigger`]). While armed
//!   the ring keeps the latest frames; at the trigger, the capture keeps `pre` frames from
//!   before it (fewer if the trigger came sooner) and records `samples − pre` more, then stops
//!   ([`CaptureState::Done`]). The host reads the window back oldest first, frame-interleaved.
//! * **Record** ([`Recorder::arm`], protocol `Record`, kept from protocol v3): `count` values
//!   of ONE signal, full Q2.30, each i32 in two slots (high half first); readable while it
//!   runs.
//!
//! # Formats of the captured values
//!
//! | channel | slot value |
//! |---------|------------|
//! | setpoint, sensor, estimate | Q1.15 normalised displacement (the top 16 bits of the Q2.30 signal, saturated at ±1: outside the model's output range it reads −32768 or 32767), the setpoint's wire format |
//! | left, right | the stack's DAC code (u16 bits) |
//! | error | setpoint − sensor, Q2.14 (the top 16 bits of the Q2.30 difference; never saturates) |
//! | triggers | bit 0 pixel, bit 1 line, bit 2 frame output, bit 3 the trigger input ([`crate::sources::scan`]) |
//!
//! # Cost per tick
//!
//! The recorder runs below the control interrupt, in the services
//! ([`crate::services::consumer::Services`]), one [`Recorder::capture`] a snapshot of a tick.
//! On a capture tick: the six values (three saturating shifts, a difference, two loads), one
//! compare to find the frame's segment (a frame never straddles the two: each segment holds
//! whole frames), one store per selected signal (at most [`CHANNELS`]), one wrap compare of
//! the write index and one countdown; on other ticks a countdown, and when idle one compare.
//! No division (the one at arming, off the tick), no allocation, no panic path (the frame is a
//! checked sub-slice). Triggers travel with the snapshots ([`Recorder::trigger`] for each of
//! a snapshot's events, before its capture).
//!
//! The buffer is whatever the board gives it ([`SampleStore`]): the firmware hands it two
//! parts, 40 KiB in SRAM and 64 KiB in the F405's CCM RAM ([`SplitStore`]); the simulator a
//! `Vec<i16>`.

use crate::control::TickReport;
use crate::services::decimation::Decimation;

/// Most recorder values one `ReadRecord` returns (one response chunk).
pub const MAX_CHUNK: usize = 64;

/// Most capture slots one `ReadCapture` returns (one response chunk): at most 3 bytes each on
/// the wire, well under a frame's body.
pub const MAX_CAPTURE_CHUNK: usize = 256;

/// Most slots one piece of a read copies ([`Recorder::read_piece`],
/// [`Recorder::read_capture_piece`]). The command handler reads a chunk piece by piece, each
/// under its own lock on the tick's resource ([`in_pieces`]), so that a tick falling due
/// waits for one piece's copy (about 200 instructions), never a whole chunk's (a chunk of 256
/// capture slots in one lock held the tick off for 8 000 instructions, 93 µs: nine ticks at
/// 100 kHz).
pub const PIECE_SLOTS: u32 = 16;

/// Most values one piece of a v3 `Record` read copies ([`Recorder::read_piece`]): each value
/// is two slots, each slot mapped through the ring and the two parts of the buffer on its own
/// (about 35 instructions a value): eight values a piece would hold the tick off for longer
/// than a capture's piece of [`PIECE_SLOTS`] slots copied as slice runs; four keep it within.
pub const RECORD_PIECE_VALUES: u32 = 4;

/// Reads a whole chunk into `out` (cleared first) piece by piece: `piece` appends the next
/// piece (the caller takes its lock around each) and says how many values it added; a piece
/// of none, or a full `out`, ends the chunk. Bounded: every piece but the last adds a value,
/// and `out` holds `N`.
///
/// ```
/// use twinstack::services::recorder::{in_pieces, Recorder, Signal, TickSignals};
/// # use twinstack::control::{TickFlags, TickReport};
/// # use twinstack::board::DacCode;
/// let mut r = Recorder::new(vec![0i16; 200]);
/// r.arm(Signal::Setpoint, 40, 1).unwrap();
/// # let report = TickReport { left: DacCode(0), right: DacCode(0), estimate: 0, measured: 0,
/// #     drive: 0, flags: TickFlags(0), triggers: 0 };
/// for k in 0..40 {
///     r.capture(&TickSignals::of(k, 0, &report), k, 0, &report);
/// }
/// let mut out = heapless::Vec::<i32, 64>::new();
/// in_pieces(&mut out, |o| r.read_piece(2, o)).unwrap();
/// assert_eq!((out.len(), out[0], out[37]), (38, 2, 39));
/// ```
pub fn in_pieces<T, const N: usize>(
    out: &mut heapless::Vec<T, N>,
    mut piece: impl FnMut(&mut heapless::Vec<T, N>) -> Result<usize, RecordError>,
) -> Result<(), RecordError> {
    out.clear();
    for _ in 0..=N {
        if piece(out)? == 0 || out.is_full() {
            break;
        }
    }
    Ok(())
}

/// Slots of the board's capture buffer: 31 744 16-bit values (62 KiB: 38 KiB of SRAM and 24
/// KiB of CCM RAM; the setpoint queue has the other 40 KiB of CCM). At 50 kHz that is 0.63 s
/// of one signal, or 0.16 s of four. The SRAM
/// part is what the learning's tables, telemetry's queue, the scan's state and trigger I/O
/// leave: the stack needs its reserve (`memory.x`, `_stack_reserve`) in every image, the
/// dual-stage board image the tightest.
pub const CAPTURE_SLOTS: usize = 31 * 1024;

/// Values of one signal a `Record` holds at most on the board: 15 872, the whole capture
/// buffer at two slots a value. An image with a smaller buffer holds what it has room for,
/// and its refusal names that figure: the QEMU image, [`EMULATOR_RECORD_CAPACITY`].
pub const RECORD_CAPACITY: usize = CAPTURE_SLOTS / 2;

/// The CCM RAM part of the board's capture buffer, slots: 12 288, 24 KiB of the 64 KiB (the
/// setpoint queue has the other 40 KiB).
pub const CCM_SLOTS: usize = 12 * 1024;

/// Values of one signal a `Record` holds at most in the QEMU image: 9 728. QEMU's
/// `netduinoplus2` models no CCM RAM, so the image has the SRAM part of [`CAPTURE_SLOTS`]
/// only, two slots a value.
pub const EMULATOR_RECORD_CAPACITY: usize = (CAPTURE_SLOTS - CCM_SLOTS) / 2;

/// Signals a v3 `Record` can capture (full Q2.30).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
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

/// Signals a capture can take, each one bit of the capture's mask (`1 << channel as u8`); in a
/// frame they come in this order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Channel {
    /// The setpoint in force, Q1.15 normalised displacement.
    Setpoint = 0,
    /// The left stack's DAC code.
    Left = 1,
    /// The right stack's DAC code.
    Right = 2,
    /// The sensor's reading, Q1.15 normalised displacement (0 without a sensor).
    Sensor = 3,
    /// The observer's estimate, Q1.15 normalised displacement.
    Estimate = 4,
    /// Setpoint − sensor, Q2.14 normalised displacement.
    Error = 5,
    /// The trigger outputs' levels (bit 0 pixel, 1 line, 2 frame) and the trigger input's
    /// (bit 3), protocol v6 ([`crate::sources::scan`]).
    Triggers = 6,
}

/// Number of [`Channel`]s (the mask's bits).
pub const CHANNELS: usize = 7;

impl Channel {
    /// Every channel, in frame order.
    pub const ALL: [Channel; CHANNELS] = [
        Channel::Setpoint,
        Channel::Left,
        Channel::Right,
        Channel::Sensor,
        Channel::Estimate,
        Channel::Error,
        Channel::Triggers,
    ];

    /// The channel's bit in a capture mask.
    pub const fn bit(self) -> u8 {
        1 << self as u8
    }

    /// The name the host uses (`setpoint`, `left`, `right`, `sensor`, `estimate`, `error`).
    pub const fn name(self) -> &'static str {
        match self {
            Channel::Setpoint => "setpoint",
            Channel::Left => "left",
            Channel::Right => "right",
            Channel::Sensor => "sensor",
            Channel::Estimate => "estimate",
            Channel::Error => "error",
            Channel::Triggers => "triggers",
        }
    }

    /// The channels of `mask`, in frame order.
    pub fn of_mask(mask: u8) -> impl Iterator<Item = Channel> {
        Channel::ALL
            .into_iter()
            .filter(move |c| mask & c.bit() != 0)
    }
}

/// One tick's seven signals, each in its slot format (the table in the module doc), in
/// [`Channel`] order: what the capture stores (its mask's channels) and what telemetry sends.
/// Computed once a tick ([`TickSignals::of`]), for both.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TickSignals(pub [i16; CHANNELS]);

impl TickSignals {
    /// The signals of a tick: `setpoint` is the setpoint in force and `sensor` the measured
    /// displacement, both Q2.30; the rest from the tick's `report`. Straight-line, no branch.
    ///
    /// ```
    /// use twinstack::board::DacCode;
    /// use twinstack::control::{TickFlags, TickReport};
    /// use twinstack::services::recorder::{Channel, TickSignals};
    /// let report = TickReport { left: DacCode(1234), right: DacCode(99), estimate: 1 << 29,
    ///     measured: 0, drive: 0, flags: TickFlags(0), triggers: 0b101 };
    /// let s = TickSignals::of(-(1 << 30), 1 << 29, &report); // setpoint −1, sensor 0.5
    /// assert_eq!(s.get(Channel::Setpoint), -32768);
    /// assert_eq!(s.get(Channel::Left), 1234);
    /// assert_eq!(s.get(Channel::Estimate), 16384);
    /// assert_eq!(s.get(Channel::Error), -24576); // −1.5, Q2.14
    /// assert_eq!(s.get(Channel::Triggers), 0b101);
    /// ```
    #[inline(always)]
    pub fn of(setpoint: i32, sensor: i32, report: &TickReport) -> Self {
        Self([
            q1_15(setpoint),
            report.left.0 as i16,
            report.right.0 as i16,
            q1_15(sensor),
            q1_15(report.estimate),
            (setpoint.saturating_sub(sensor) >> 16) as i16,
            report.triggers as i16,
        ])
    }

    /// The value of `channel`.
    pub fn get(&self, channel: Channel) -> i16 {
        self.0[channel as usize]
    }
}

/// What starts a capture's post-trigger part.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Trigger {
    /// The arming itself (no pre-trigger frames).
    Now,
    /// The next start of the setpoint stream.
    StreamStart,
    /// The next start of the waveform generator.
    WaveformStart,
    /// The next start of a scan (protocol v6; at its approach's first tick).
    ScanStart,
    /// The external trigger input's armed edge (protocol v6, [`crate::sources::scan::ExternalTrigger`]).
    External,
}

/// Where a capture is.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CaptureState {
    /// Nothing armed (or a `Record`, not a capture).
    #[default]
    Idle,
    /// Armed, capturing into the ring, waiting for the trigger.
    Armed,
    /// Triggered, capturing the post-trigger frames.
    Triggered,
    /// Complete: the window can be read.
    Done,
}

/// Why an arm or a read was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum RecordError {
    /// `count` is 0 or more than the buffer holds, or `decimation` is 0.
    BadRequest,
    /// The read offset is past the values captured so far.
    OffsetPastEnd,
    /// The signal mask is empty or names no signal (bits 6–7 set).
    BadSignals,
    /// `signals × samples` is over the capacity (or `samples` is 0).
    TooManySamples,
    /// `pre` is not below `samples`, or not 0 with [`Trigger::Now`].
    BadPreTrigger,
    /// The capture is not complete yet (or none was armed).
    NotDone,
}

/// The recorder's buffer: 16-bit slots in one or two segments (the board's SRAM and CCM RAM
/// are not contiguous). A frame (one capture tick's values) is always written within one
/// segment, so the tick finds its place with one compare per frame, not per value.
/// Implemented for any `AsRef<[i16]> + AsMut<[i16]>` (an array, a `Vec`: one segment) and for
/// two of them end to end ([`SplitStore`]).
pub trait SampleStore {
    /// Slots of the first and of the second segment.
    fn segments(&self) -> (usize, usize);
    /// The slots from `offset` to the end of the first segment (or the second, if `second`);
    /// empty past its end. The tick writes one frame at its start.
    fn tail_mut(&mut self, second: bool, offset: usize) -> &mut [i16];
    /// Slot `index`, counting the first segment's then the second's (0 past the end).
    fn get(&self, index: usize) -> i16;
    /// The slots from `index` (counted as in [`SampleStore::get`]) to the end of its
    /// segment; empty past the end.
    fn run(&self, index: usize) -> &[i16];
}

impl<T: AsRef<[i16]> + AsMut<[i16]>> SampleStore for T {
    #[inline(always)]
    fn segments(&self) -> (usize, usize) {
        (self.as_ref().len(), 0)
    }

    #[inline(always)]
    fn tail_mut(&mut self, second: bool, offset: usize) -> &mut [i16] {
        if second {
            return &mut [];
        }
        self.as_mut().get_mut(offset..).unwrap_or(&mut [])
    }

    #[inline(always)]
    fn get(&self, index: usize) -> i16 {
        self.as_ref().get(index).copied().unwrap_or(0)
    }

    fn run(&self, index: usize) -> &[i16] {
        self.as_ref().get(index..).unwrap_or(&[])
    }
}

/// Two buffers end to end: slots `0..first.len()` in `first`, the rest in `second` (on the
/// board, SRAM then CCM RAM).
///
/// ```
/// use twinstack::services::recorder::{SampleStore, SplitStore};
/// let mut s = SplitStore::new([0i16; 2], [0i16; 3]);
/// s.tail_mut(true, 1).copy_from_slice(&[7, 8]);
/// assert_eq!((s.segments(), s.get(3), s.second), ((2, 3), 7, [0, 7, 8]));
/// ```
#[derive(Debug)]
pub struct SplitStore<A, B> {
    /// The first slots.
    pub first: A,
    /// The slots after them.
    pub second: B,
}

impl<A: AsRef<[i16]>, B> SplitStore<A, B> {
    /// `first`'s slots, then `second`'s.
    pub fn new(first: A, second: B) -> Self {
        Self { first, second }
    }
}

impl<A, B> SampleStore for SplitStore<A, B>
where
    A: AsRef<[i16]> + AsMut<[i16]>,
    B: AsRef<[i16]> + AsMut<[i16]>,
{
    #[inline(always)]
    fn segments(&self) -> (usize, usize) {
        (self.first.as_ref().len(), self.second.as_ref().len())
    }

    #[inline(always)]
    fn tail_mut(&mut self, second: bool, offset: usize) -> &mut [i16] {
        let segment = if second {
            self.second.as_mut()
        } else {
            self.first.as_mut()
        };
        segment.get_mut(offset..).unwrap_or(&mut [])
    }

    #[inline(always)]
    fn get(&self, index: usize) -> i16 {
        let split = self.first.as_ref().len();
        let slot = if index < split {
            self.first.as_ref().get(index)
        } else {
            self.second.as_ref().get(index - split)
        };
        slot.copied().unwrap_or(0)
    }

    fn run(&self, index: usize) -> &[i16] {
        let split = self.first.as_ref().len();
        let run = if index < split {
            self.first.as_ref().get(index..)
        } else {
            self.second.as_ref().get(index - split..)
        };
        run.unwrap_or(&[])
    }
}

/// What a capture was armed with and where it is (the answer to `CaptureStatus`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CaptureInfo {
    /// Where the capture is.
    pub state: CaptureState,
    /// The signal mask ([`Channel::bit`]).
    pub signals: u8,
    /// Frames (values per signal) armed for, pre-trigger included.
    pub samples: u32,
    /// Pre-trigger frames armed for.
    pub pre_trigger: u32,
    /// Pre-trigger frames the window holds (fewer than `pre_trigger` if the trigger came
    /// before that many were captured); known once triggered.
    pub pre_available: u32,
    /// Frames of the window captured so far (pre-trigger included).
    pub captured: u32,
    /// Ticks per frame.
    pub decimation: u16,
    /// The trigger armed.
    pub trigger: Option<Trigger>,
}

impl CaptureInfo {
    /// Slots the complete window holds: `(pre_available + samples − pre_trigger) × signals`.
    pub fn window_slots(&self) -> u32 {
        (self.pre_available + self.samples - self.pre_trigger) * self.signals.count_ones()
    }
}

/// Which kind of capture the buffer holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    /// A v3 `Record` of one signal, two slots per value.
    Record(Signal),
    /// A multi-signal capture.
    Capture(Trigger),
}

/// The recorder and its buffer.
#[derive(Debug)]
pub struct Recorder<B> {
    buffer: B,
    kind: Kind,
    /// Signal mask (a `Record` uses none).
    mask: u8,
    /// Slots per frame.
    per_frame: u32,
    /// Frames armed for (the ring's length in frames).
    frames: u32,
    /// The ring's length in slots (`frames × per_frame`).
    ring: u32,
    /// Ring slots in the first segment: whole frames only, so no frame straddles the two.
    first_slots: u32,
    /// Slot of the second segment where the ring continues (the first segment's length).
    split: u32,
    pre: u32,
    /// The next slot written.
    pos: u32,
    /// Frames captured before the trigger (saturating at `frames`).
    before: u32,
    /// Post-trigger frames still to capture.
    post_left: u32,
    /// The slot the trigger frame was written to.
    trigger_pos: u32,
    pre_available: u32,
    /// Capturing: armed or triggered, and not done.
    active: bool,
    triggered: bool,
    /// One capture tick in every `decimation` ticks.
    decimation: Decimation,
}

impl<B: SampleStore> Recorder<B> {
    /// An idle recorder over `buffer` (its slots are the capacity).
    ///
    /// ```
    /// use twinstack::services::recorder::{Channel, Recorder, Trigger};
    /// let mut r = Recorder::new(vec![0i16; 1024]);
    /// r.arm_capture(Channel::Setpoint.bit() | Channel::Left.bit(), 512, 0, Trigger::Now, 1).unwrap();
    /// assert!(r.is_capturing());
    /// ```
    pub fn new(buffer: B) -> Self {
        Self {
            buffer,
            kind: Kind::Record(Signal::Setpoint),
            mask: 0,
            per_frame: 2,
            frames: 0,
            ring: 0,
            first_slots: 0,
            split: 0,
            pre: 0,
            pos: 0,
            before: 0,
            post_left: 0,
            trigger_pos: 0,
            pre_available: 0,
            active: false,
            triggered: false,
            decimation: Decimation::every(1),
        }
    }

    /// Slots the buffer holds.
    pub fn capacity(&self) -> usize {
        let (a, b) = self.buffer.segments();
        a + b
    }

    /// Most frames of `signals` values each a capture can hold: whole frames in each segment
    /// (`⌊first / signals⌋ + ⌊second / signals⌋`; 10 922 of six signals in 65 536 slots).
    pub fn max_frames(&self, signals: u32) -> u32 {
        let (a, b) = self.buffer.segments();
        let n = signals.max(1) as usize;
        (a / n + b / n).min(u32::MAX as usize) as u32
    }

    /// Most values a v3 `Record` can hold: [`RECORD_CAPACITY`], or what fits two slots each.
    pub fn record_capacity(&self) -> usize {
        RECORD_CAPACITY.min(self.max_frames(2) as usize)
    }

    /// Arms a v3 `Record`: `count` values of `signal`, one every `decimation` ticks, starting
    /// with the next tick; the previous capture is discarded. Refused (and nothing changed)
    /// if `count` is 0 or above [`Recorder::record_capacity`], or `decimation` is 0.
    pub fn arm(&mut self, signal: Signal, count: u32, decimation: u16) -> Result<(), RecordError> {
        if count == 0 || count as usize > self.record_capacity() || decimation == 0 {
            return Err(RecordError::BadRequest);
        }
        self.start(Kind::Record(signal), 0, 2, count, 0, decimation);
        self.fire();
        Ok(())
    }

    /// Arms a capture of the signals in `mask` ([`Channel::bit`]s): `samples` frames in all,
    /// `pre` of them from before the trigger, one every `decimation` ticks. With
    /// [`Trigger::Now`] the capture is triggered at once (and `pre` must be 0). The previous
    /// capture is discarded. Refused, with nothing changed, for an empty mask or one with
    /// bits 6–7, `samples` of 0 or `signals × samples` over the capacity, `pre ≥ samples`,
    /// or a `decimation` of 0.
    pub fn arm_capture(
        &mut self,
        mask: u8,
        samples: u32,
        pre: u32,
        trigger: Trigger,
        decimation: u16,
    ) -> Result<(), RecordError> {
        if mask == 0 || mask >> CHANNELS != 0 {
            return Err(RecordError::BadSignals);
        }
        let per_frame = mask.count_ones();
        if samples == 0 || samples > self.max_frames(per_frame) {
            return Err(RecordError::TooManySamples);
        }
        if pre >= samples || (trigger == Trigger::Now && pre != 0) {
            return Err(RecordError::BadPreTrigger);
        }
        if decimation == 0 {
            return Err(RecordError::BadRequest);
        }
        self.start(
            Kind::Capture(trigger),
            mask,
            per_frame,
            samples,
            pre,
            decimation,
        );
        if trigger == Trigger::Now {
            self.fire();
        }
        Ok(())
    }

    fn start(&mut self, kind: Kind, mask: u8, per_frame: u32, frames: u32, pre: u32, dec: u16) {
        self.kind = kind;
        self.mask = mask;
        self.per_frame = per_frame;
        self.frames = frames;
        self.ring = frames * per_frame;
        let (first, _) = self.buffer.segments();
        // Off the tick: the one division, whole frames in the first segment.
        self.first_slots = ((first as u32 / per_frame) * per_frame).min(self.ring);
        self.split = first as u32;
        self.pre = pre;
        self.pos = 0;
        self.before = 0;
        self.post_left = frames - pre;
        self.trigger_pos = 0;
        self.pre_available = 0;
        self.active = true;
        self.triggered = false;
        self.decimation = Decimation::every(dec);
    }

    /// The trigger: from the next capture tick on, the post-trigger frames.
    fn fire(&mut self) {
        self.triggered = true;
        self.trigger_pos = self.pos;
        self.pre_available = self.before.min(self.pre);
        // The trigger frame is the next tick's.
        self.decimation.restart();
    }

    /// Tells the recorder that `event` happened (the stream or the waveform generator
    /// started): an armed capture waiting for it is triggered. Called by the services with a
    /// snapshot's events, before that snapshot's capture; O(1).
    pub fn trigger(&mut self, event: Trigger) {
        if self.active && !self.triggered && self.kind == Kind::Capture(event) {
            self.fire();
        }
    }

    /// Frames were lost before they reached the recorder (the snapshot ring was full: see
    /// [`crate::services::snapshot`]): a capture or `Record` in progress ends without
    /// completing, its frames discarded (the capture's state reads idle, a `Record` holds
    /// nothing), rather than complete with a hole in its time base. O(1).
    #[cold]
    pub fn lose_frames(&mut self) {
        if self.active {
            self.active = false;
            self.triggered = false;
            self.kind = Kind::Record(Signal::Setpoint);
            self.frames = 0;
            self.pre = 0;
            self.post_left = 0;
        }
    }

    /// Whether a capture (or a `Record`) is running: armed and not complete.
    pub fn is_capturing(&self) -> bool {
        self.active
    }

    /// The running capture's (or `Record`'s) decimation: one frame every that many ticks;
    /// `None` when none runs.
    pub fn running_decimation(&self) -> Option<u16> {
        self.active.then_some(self.decimation.ticks())
    }

    /// Values a v3 `Record` holds so far (0 for a capture).
    pub fn recorded(&self) -> u32 {
        match self.kind {
            Kind::Record(_) => self.frames - self.post_left,
            Kind::Capture(_) => 0,
        }
    }

    /// The signal being (or last) recorded by a v3 `Record`.
    pub fn signal(&self) -> Signal {
        match self.kind {
            Kind::Record(s) => s,
            Kind::Capture(_) => Signal::Setpoint,
        }
    }

    /// The capture's settings and progress (an idle state if the buffer holds a `Record`).
    pub fn capture_info(&self) -> CaptureInfo {
        let Kind::Capture(trigger) = self.kind else {
            return CaptureInfo::default();
        };
        let post = self.frames - self.pre - self.post_left;
        let state = match (self.active, self.triggered) {
            (true, false) => CaptureState::Armed,
            (true, true) => CaptureState::Triggered,
            _ => CaptureState::Done,
        };
        CaptureInfo {
            state,
            signals: self.mask,
            samples: self.frames,
            pre_trigger: self.pre,
            pre_available: self.pre_available,
            captured: if self.triggered {
                self.pre_available + post
            } else {
                self.before.min(self.pre)
            },
            decimation: self.decimation.ticks(),
            trigger: Some(trigger),
        }
    }

    /// One tick: on a capture tick, stores the mask's channels of `signals` (or the
    /// `Record`'s signal, full width: `setpoint` is the setpoint in force and `sensor` the
    /// measured displacement, Q2.30; the drive and the estimate from `report`). O(1): at most
    /// [`CHANNELS`] stores, no panic path.
    #[inline(always)]
    pub fn capture(
        &mut self,
        signals: &TickSignals,
        setpoint: i32,
        sensor: i32,
        report: &TickReport,
    ) {
        if self.due() {
            self.store(signals, setpoint, sensor, report);
        }
    }

    /// One tick's countdown: whether this tick is a capture tick (a capture or a `Record`
    /// running, and its decimation's countdown at zero, which it reloads), for
    /// [`Recorder::store`] to take. [`Recorder::capture`] is both.
    #[inline(always)]
    pub fn due(&mut self) -> bool {
        self.active && self.decimation.due()
    }

    /// Ticks before the next capture tick, each of which [`Recorder::due`] would only count
    /// down (`u32::MAX` when no capture or `Record` runs): what the services may pass over
    /// at once ([`Recorder::pass`]).
    #[inline(always)]
    pub fn quiet_ticks(&self) -> u32 {
        if self.active {
            self.decimation.quiet_ticks()
        } else {
            u32::MAX
        }
    }

    /// Counts `ticks` ticks down at once, as that many [`Recorder::due`] calls returning
    /// `false` would: `ticks` is at most [`Recorder::quiet_ticks`] (more stops at the
    /// capture tick, which `due` then takes). O(1).
    #[inline(always)]
    pub fn pass(&mut self, ticks: u32) {
        if self.active {
            self.decimation.pass(ticks);
        }
    }

    /// Whether an armed or running capture keeps frames from before its trigger.
    pub fn keeps_pre_trigger(&self) -> bool {
        self.active && self.pre > 0
    }

    /// The trigger an armed capture waits for (`None` while none waits: idle, a `Record`,
    /// or already triggered): the one event [`Recorder::trigger`] acts on.
    #[inline(always)]
    pub fn awaited_trigger(&self) -> Option<Trigger> {
        match self.kind {
            Kind::Capture(trigger) if self.active && !self.triggered => Some(trigger),
            _ => None,
        }
    }

    /// Stores a capture tick's frame (after [`Recorder::due`] said it is one): the mask's
    /// channels of `signals`, or the `Record`'s signal, full width, as [`Recorder::capture`]
    /// says.
    #[inline(always)]
    pub fn store(
        &mut self,
        signals: &TickSignals,
        setpoint: i32,
        sensor: i32,
        report: &TickReport,
    ) {
        // One compare for the segment, then one store per value of the frame (at most
        // CHANNELS), straight-line: a bit test and a store for each channel.
        let (second, offset) = if self.pos < self.first_slots {
            (false, self.pos)
        } else {
            (true, self.pos - self.first_slots)
        };
        // The frame is at the start of the segment's tail: at most `per_frame` values are
        // written, and each segment holds whole frames, so they stay in the frame.
        let mut slots = self.buffer.tail_mut(second, offset as usize).iter_mut();
        let mut put = |value: i16| {
            if let Some(slot) = slots.next() {
                *slot = value;
            }
        };
        if let Kind::Record(signal) = self.kind {
            let value = match signal {
                Signal::Setpoint => setpoint,
                Signal::Drive => report.drive,
                Signal::Sensor => sensor,
                Signal::Estimate => report.estimate,
            };
            put((value >> 16) as i16);
            put(value as i16);
        } else {
            let mask = self.mask;
            let [sp, left, right, sn, estimate, error, triggers] = signals.0;
            if mask & Channel::Setpoint.bit() != 0 {
                put(sp);
            }
            if mask & Channel::Left.bit() != 0 {
                put(left);
            }
            if mask & Channel::Right.bit() != 0 {
                put(right);
            }
            if mask & Channel::Sensor.bit() != 0 {
                put(sn);
            }
            if mask & Channel::Estimate.bit() != 0 {
                put(estimate);
            }
            if mask & Channel::Error.bit() != 0 {
                put(error);
            }
            if mask & Channel::Triggers.bit() != 0 {
                put(triggers);
            }
        }
        let next = self.pos + self.per_frame;
        self.pos = if next >= self.ring { 0 } else { next };
        if self.triggered {
            if self.post_left > 1 {
                self.post_left -= 1;
            } else {
                self.post_left = 0;
                self.active = false;
            }
        } else if self.before < self.frames {
            self.before += 1;
        }
    }

    /// Copies a v3 `Record`'s values from `offset`, up to [`MAX_CHUNK`], into `out` (cleared
    /// first): [`Recorder::read_piece`] until the chunk is complete. An offset equal to the
    /// values recorded gives an empty chunk (nothing more yet); one past it is refused.
    pub fn read(
        &self,
        offset: u32,
        out: &mut heapless::Vec<i32, MAX_CHUNK>,
    ) -> Result<(), RecordError> {
        in_pieces(out, |o| self.read_piece(offset, o))
    }

    /// Appends the next piece of the chunk of a v3 `Record` that starts at `offset`: the
    /// values from `offset + out.len()`, at most [`RECORD_PIECE_VALUES`] of them (two slots
    /// each), up to what is recorded and `out`'s capacity. Returns how many it appended (0:
    /// the chunk is complete). An offset past the values recorded is refused.
    pub fn read_piece(
        &self,
        offset: u32,
        out: &mut heapless::Vec<i32, MAX_CHUNK>,
    ) -> Result<usize, RecordError> {
        let recorded = self.recorded();
        if offset > recorded {
            return Err(RecordError::OffsetPastEnd);
        }
        let from = offset.saturating_add(out.len() as u32);
        let room = (MAX_CHUNK - out.len()) as u32;
        let to = recorded.min(from.saturating_add(room.min(RECORD_PIECE_VALUES)));
        for i in from..to {
            let at = 2 * i;
            let hi = self.buffer.get(self.physical(at)) as i32;
            let lo = self.buffer.get(self.physical(at + 1)) as u16 as i32;
            // At most the room `out` has: this cannot fail.
            let _ = out.push(hi << 16 | lo);
        }
        Ok(to.saturating_sub(from) as usize)
    }

    /// Copies up to `count` (at most [`MAX_CAPTURE_CHUNK`]) slots of a complete capture's
    /// window from `offset` into `out` (cleared first): [`Recorder::read_capture_piece`]
    /// until the chunk is complete. The window is oldest frame first, each frame its signals
    /// in [`Channel`] order. An offset at the window's end gives an empty chunk; past it is
    /// refused, and so is a capture not complete.
    pub fn read_capture(
        &self,
        offset: u32,
        count: u16,
        out: &mut heapless::Vec<i16, MAX_CAPTURE_CHUNK>,
    ) -> Result<(), RecordError> {
        in_pieces(out, |o| self.read_capture_piece(offset, count, o))
    }

    /// Appends the next piece of the chunk of a complete capture's window that starts at
    /// `offset` and asks for `count` slots: the slots from `offset + out.len()`, at most
    /// [`PIECE_SLOTS`], up to the chunk's end. Returns how many it appended (0: the chunk is
    /// complete). An offset past the window is refused, and so is a capture not complete.
    pub fn read_capture_piece(
        &self,
        offset: u32,
        count: u16,
        out: &mut heapless::Vec<i16, MAX_CAPTURE_CHUNK>,
    ) -> Result<usize, RecordError> {
        let info = self.capture_info();
        if info.state != CaptureState::Done {
            return Err(RecordError::NotDone);
        }
        let len = info.window_slots();
        if offset > len {
            return Err(RecordError::OffsetPastEnd);
        }
        let end = len.min(offset.saturating_add((count as u32).min(MAX_CAPTURE_CHUNK as u32)));
        let from = offset.saturating_add(out.len() as u32);
        let to = end.min(from.saturating_add(PIECE_SLOTS));
        // The window starts `pre_available` frames before the trigger frame, in the ring.
        let back = self.pre_available * self.per_frame;
        let start = if self.trigger_pos >= back {
            self.trigger_pos - back
        } else {
            self.trigger_pos + self.ring - back
        };
        // Slice copies of contiguous runs: at most three, as the ring wraps once and passes
        // from the first segment's frames to the second segment once.
        let mut i = from;
        for _ in 0..4 {
            if i >= to {
                break;
            }
            let mut at = start + i;
            if at >= self.ring {
                at -= self.ring;
            }
            let contiguous = if at < self.first_slots {
                self.first_slots - at
            } else {
                self.ring - at
            };
            let run = self.buffer.run(self.physical(at));
            let n = ((to - i).min(contiguous) as usize).min(run.len());
            // `to − from` fits what `out` has left: the copy cannot fail.
            if n == 0 || out.extend_from_slice(&run[..n]).is_err() {
                break;
            }
            i += n as u32;
        }
        Ok(i.saturating_sub(from) as usize)
    }

    /// The buffer's index of ring slot `at`: the first segment's whole frames, then the
    /// second segment from its start.
    fn physical(&self, at: u32) -> usize {
        if at < self.first_slots {
            at as usize
        } else {
            (self.split + at - self.first_slots) as usize
        }
    }
}

/// Q2.30 → Q1.15 (the top 16 bits, truncated), saturated at ±1: the capture's and
/// telemetry's format of the setpoint, sensor and estimate.
#[inline(always)]
pub fn q1_15(v: i32) -> i16 {
    (v >> 15).clamp(i16::MIN as i32, i16::MAX as i32) as i16
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::board::DacCode;
    use crate::control::TickFlags;
    use std::vec;
    use std::vec::Vec;

    /// One tick of `r`: its signals from `setpoint`, `sensor` and `report`.
    fn tick(r: &mut Recorder<impl SampleStore>, setpoint: i32, sensor: i32, report: &TickReport) {
        r.capture(
            &TickSignals::of(setpoint, sensor, report),
            setpoint,
            sensor,
            report,
        );
    }

    fn report(k: i32) -> TickReport {
        TickReport {
            left: DacCode(k as u16),
            right: DacCode(4095 - k as u16),
            estimate: (10 * k) << 15,
            measured: 0,
            drive: 100 * k,
            flags: TickFlags(0),
            triggers: 0,
        }
    }

    /// Ticks `k` in `range` through `r`: setpoint k (Q1.15), sensor −k.
    fn run(r: &mut Recorder<impl SampleStore>, range: std::ops::Range<i32>) {
        for k in range {
            tick(r, k << 15, -k << 15, &report(k));
        }
    }

    fn window(r: &Recorder<impl SampleStore>) -> Vec<i16> {
        let mut all = Vec::new();
        let mut out = heapless::Vec::new();
        loop {
            r.read_capture(all.len() as u32, 7, &mut out).unwrap();
            if out.is_empty() {
                return all;
            }
            all.extend_from_slice(&out);
        }
    }

    #[test]
    fn captures_every_nth_tick_and_stops_when_full() {
        let mut r = Recorder::new(vec![0i16; 16]);
        r.arm(Signal::Drive, 3, 2).unwrap();
        run(&mut r, 0..10);
        assert!(!r.is_capturing());
        let mut out = heapless::Vec::new();
        r.read(0, &mut out).unwrap();
        assert_eq!(&out[..], &[0, 200, 400]);
        r.read(1, &mut out).unwrap();
        assert_eq!(&out[..], &[200, 400]);
        r.read(3, &mut out).unwrap();
        assert!(out.is_empty());
        assert_eq!(r.read(4, &mut out), Err(RecordError::OffsetPastEnd));
    }

    #[test]
    fn a_record_keeps_all_32_bits() {
        for (signal, want) in [
            (Signal::Setpoint, -0x1234_5679),
            (Signal::Drive, 0x7654_3210),
            (Signal::Estimate, i32::MIN),
            (Signal::Sensor, -5),
        ] {
            let mut r = Recorder::new(vec![0i16; 4]);
            r.arm(signal, 1, 1).unwrap();
            let mut rep = report(0);
            rep.drive = 0x7654_3210;
            rep.estimate = i32::MIN;
            tick(&mut r, -0x1234_5679, -5, &rep);
            let mut out = heapless::Vec::new();
            r.read(0, &mut out).unwrap();
            assert_eq!(&out[..], &[want], "{signal:?}");
        }
    }

    #[test]
    fn bad_arms_are_refused_and_change_nothing() {
        let mut r = Recorder::new(vec![0i16; 8]);
        r.arm(Signal::Setpoint, 2, 1).unwrap();
        tick(&mut r, 1 << 16, 0, &report(1));
        for (count, decimation) in [(0, 1), (5, 1), (2, 0)] {
            assert_eq!(
                r.arm(Signal::Drive, count, decimation),
                Err(RecordError::BadRequest)
            );
        }
        for (mask, samples, pre, trigger, dec, e) in [
            (0, 2, 0, Trigger::Now, 1, RecordError::BadSignals),
            (0x80, 2, 0, Trigger::Now, 1, RecordError::BadSignals),
            (0b11, 5, 0, Trigger::Now, 1, RecordError::TooManySamples),
            (0b11, 0, 0, Trigger::Now, 1, RecordError::TooManySamples),
            (
                0b11,
                4,
                4,
                Trigger::StreamStart,
                1,
                RecordError::BadPreTrigger,
            ),
            (0b11, 4, 1, Trigger::Now, 1, RecordError::BadPreTrigger),
            (0b11, 4, 0, Trigger::Now, 0, RecordError::BadRequest),
        ] {
            assert_eq!(r.arm_capture(mask, samples, pre, trigger, dec), Err(e));
        }
        assert_eq!((r.recorded(), r.signal()), (1, Signal::Setpoint));
        assert!(r.is_capturing());
    }

    #[test]
    fn every_channel_comes_from_its_source_in_its_format() {
        let mut r = Recorder::new(vec![0i16; 64]);
        r.arm_capture(0b11_1111, 2, 0, Trigger::Now, 1).unwrap();
        let mut rep = report(7);
        rep.estimate = i32::MAX; // 2.0: saturates
        tick(&mut r, -(1 << 30), 1 << 29, &rep); // setpoint −1, sensor 0.5
        rep.estimate = -(1 << 29);
        tick(&mut r, 1 << 29, -(1 << 30), &rep);
        assert!(!r.is_capturing());
        let w = window(&r);
        assert_eq!(
            w,
            [
                // setpoint, left, right, sensor, estimate, error (Q2.14: −1.5)
                -32768, 7, 4088, 16384, 32767, -24576, //
                16384, 7, 4088, -32768, -16384, 24576,
            ]
        );
    }

    #[test]
    fn the_ring_wraps_and_the_window_comes_out_oldest_first() {
        // 2 signals × 5 frames, 2 of them before the trigger: the ring wraps while armed.
        let mut r = Recorder::new(vec![0i16; 10]);
        r.arm_capture(
            Channel::Setpoint.bit() | Channel::Left.bit(),
            5,
            2,
            Trigger::StreamStart,
            1,
        )
        .unwrap();
        run(&mut r, 0..13); // 13 frames before the trigger: the ring went round twice
        assert_eq!(r.capture_info().state, CaptureState::Armed);
        r.trigger(Trigger::WaveformStart); // not this capture's trigger
        run(&mut r, 13..14);
        r.trigger(Trigger::StreamStart);
        assert_eq!(r.capture_info().state, CaptureState::Triggered);
        run(&mut r, 14..20);
        let info = r.capture_info();
        assert_eq!(
            (info.state, info.pre_available, info.captured),
            (CaptureState::Done, 2, 5)
        );
        // Frames 12, 13 before the trigger; 14, 15, 16 after; 17.. not captured.
        let w = window(&r);
        let setpoints: Vec<i16> = w.iter().step_by(2).copied().collect();
        let left: Vec<i16> = w.iter().skip(1).step_by(2).copied().collect();
        assert_eq!(setpoints, [12, 13, 14, 15, 16]);
        assert_eq!(left, [12, 13, 14, 15, 16]);
        let mut out = heapless::Vec::new();
        assert_eq!(
            r.read_capture(11, 1, &mut out),
            Err(RecordError::OffsetPastEnd)
        );
    }

    #[test]
    fn an_early_trigger_keeps_the_pre_trigger_frames_there_are() {
        let mut r = Recorder::new(vec![0i16; 64]);
        r.arm_capture(Channel::Sensor.bit(), 10, 6, Trigger::WaveformStart, 2)
            .unwrap();
        run(&mut r, 0..5); // frames at ticks 0, 2, 4
        let mut out = heapless::Vec::new();
        assert_eq!(r.read_capture(0, 1, &mut out), Err(RecordError::NotDone));
        r.trigger(Trigger::WaveformStart);
        // The trigger frame is the next tick's, then every second tick.
        run(&mut r, 5..20);
        let info = r.capture_info();
        assert_eq!((info.pre_available, info.window_slots()), (3, 7));
        let sensor: Vec<i16> = window(&r);
        assert_eq!(sensor, [0, -2, -4, -5, -7, -9, -11]);
    }

    #[test]
    fn trigger_now_starts_at_once_and_decimates() {
        let mut r = Recorder::new(vec![0i16; 64]);
        r.arm_capture(Channel::Setpoint.bit(), 4, 0, Trigger::Now, 3)
            .unwrap();
        assert_eq!(r.capture_info().state, CaptureState::Triggered);
        run(&mut r, 0..20);
        assert_eq!(window(&r), [0, 3, 6, 9]);
    }

    #[test]
    fn a_split_store_spans_both_halves() {
        let mut r = Recorder::new(SplitStore::new([0i16; 3], [0i16; 3]));
        r.arm_capture(Channel::Setpoint.bit(), 6, 0, Trigger::Now, 1)
            .unwrap();
        run(&mut r, 1..7);
        assert_eq!(window(&r), [1, 2, 3, 4, 5, 6]);
        assert_eq!(r.buffer.second, [4, 5, 6]);
    }

    #[test]
    fn no_frame_straddles_the_two_segments_and_the_ring_wraps_across_them() {
        // Two signals in 3 + 5 slots: one frame in the first segment, two in the second.
        let mut r = Recorder::new(SplitStore::new([0i16; 3], [0i16; 5]));
        assert_eq!(r.max_frames(2), 3);
        assert_eq!(
            r.arm_capture(0b11, 4, 0, Trigger::Now, 1),
            Err(RecordError::TooManySamples)
        );
        r.arm_capture(0b11, 3, 1, Trigger::StreamStart, 1).unwrap();
        run(&mut r, 1..6); // frames 1..5 go round the 3-frame ring
        r.trigger(Trigger::StreamStart);
        run(&mut r, 6..9);
        assert_eq!(r.buffer.first, [7, 7, 0]);
        assert_eq!(r.buffer.second, [5, 5, 6, 6, 0]);
        // One frame from before the trigger (5), then 6 and 7.
        assert_eq!(window(&r), [5, 5, 6, 6, 7, 7]);
    }

    #[test]
    fn a_piece_copies_at_most_piece_slots_and_the_pieces_make_the_chunk() {
        let mut r = Recorder::new(vec![0i16; 1024]);
        r.arm_capture(
            Channel::Setpoint.bit() | Channel::Left.bit(),
            300,
            0,
            Trigger::Now,
            1,
        )
        .unwrap();
        run(&mut r, 0..301);
        let mut piecewise = heapless::Vec::new();
        let mut pieces = 0;
        loop {
            let n = r.read_capture_piece(10, 200, &mut piecewise).unwrap();
            assert!(n as u32 <= PIECE_SLOTS, "a piece of {n} slots");
            if n == 0 {
                break;
            }
            pieces += 1;
        }
        assert_eq!(
            (piecewise.len(), pieces),
            (200, 200usize.div_ceil(PIECE_SLOTS as usize))
        );
        let mut whole = heapless::Vec::new();
        r.read_capture(10, 200, &mut whole).unwrap();
        assert_eq!(piecewise, whole);
        // Frame k holds setpoint k then left k: slot 10 is frame 5's setpoint.
        assert_eq!((whole[0], whole[1], whole[199]), (5, 5, 104));
        // A record's pieces: at most `RECORD_PIECE_VALUES` values (two slots each).
        r.arm(Signal::Setpoint, 100, 1).unwrap();
        for k in 0..100 {
            tick(&mut r, k, 0, &report(k));
        }
        let mut values = heapless::Vec::new();
        assert_eq!(
            r.read_piece(3, &mut values),
            Ok(RECORD_PIECE_VALUES as usize)
        );
        assert_eq!(
            r.read_piece(3, &mut values),
            Ok(RECORD_PIECE_VALUES as usize)
        );
        // Two pieces: the values 3 .. 3 + 2 × RECORD_PIECE_VALUES, in order.
        let want: Vec<i32> = (3..3 + 2 * RECORD_PIECE_VALUES as i32).collect();
        assert_eq!(&values[..], &want[..]);
    }

    #[test]
    fn chunks_are_at_most_max_chunk_long() {
        let mut r = Recorder::new(vec![0i16; 400]);
        r.arm(Signal::Setpoint, 200, 1).unwrap();
        for k in 0..200 {
            tick(&mut r, k, 0, &report(k));
        }
        let mut out = heapless::Vec::new();
        r.read(100, &mut out).unwrap();
        assert_eq!(out.len(), MAX_CHUNK);
        assert_eq!(out[0], 100);
        r.read(180, &mut out).unwrap();
        assert_eq!(out.len(), 20);
    }
}
