//! Continuous telemetry: chosen signals of every tick (or every `decimation`-th), streamed to
//! the host over the UART while the board runs — beside the setpoint stream, without
//! stopping anything.
//!
//! Three pieces:
//!
//! * **In the services** (below the tick, [`crate::services::consumer::Services`], one call
//!   a snapshot of a tick), [`TelemetryTap::push`] takes the tick's seven signals ([`TickSignals`]: the recorder's channels, [`Channel`], each
//!   one quantity in one form, the capture's slot format, computed once for both) into one
//!   [`TelemetrySample`] and puts it on a bounded lock-free single-producer single-consumer
//!   queue ([`TelemetryQueue`], `heapless::spsc`); the packer sends the mask's. Constant
//!   time: a countdown on the ticks between samples; on a sample tick one enqueue. A full
//!   queue never blocks the services: the sample is dropped and counted
//!   ([`TelemetryTap::overflows`]), and so are the samples of ticks whose snapshot was lost
//!   ([`TelemetryTap::lose_ticks`]). No
//!   allocation, no division, no panic path.
//! * **Off the tick**, [`TelemetryPacker`] (owned by the command handler, run where the board
//!   sends its frames) takes queued samples and makes protocol frames
//!   ([`TelemetryFrame`], sent as the unsolicited [`Response::Telemetry`](crate::protocol::messages::Response::Telemetry)): a frame sequence
//!   number, the index of its first sample, the signal mask, the samples. Samples are
//!   indexed on the tick (every sample, sent or dropped, takes the next index), so a sample
//!   lost to a full queue leaves a gap the packer sees: the frame after it starts at the
//!   next index that exists and its `lost` counts every sample skipped since the start. Once
//!   telemetry is stopped the packer sends what is queued, then a frame with `end` set whose
//!   `first` is the number of samples the run produced: nothing the host does not get
//!   goes unannounced, even at the tail.
//! * **The line**: the board hands frames to a [`FrameLink`] (the board's USART1 TX by DMA,
//!   double-buffered; the emulator's polled TX; the simulator's modelled line). Responses to
//!   requests go first; telemetry fills the line in between.
//!
//! The packer waits for [`TelemetryPacker::target_samples`] samples before it makes a frame
//! (5 ms of samples, at most a full frame, at least one): few bytes of framing per value at
//! high rates, a bounded delay at low ones.
//!
//! ```
//! use twinstack::control::{TickFlags, TickReport};
//! use twinstack::board::DacCode;
//! use twinstack::protocol::frame;
//! use twinstack::protocol::messages::Response;
//! use twinstack::services::recorder::{Channel, TickSignals};
//! use twinstack::services::telemetry::{TelemetryPacker, TelemetryQueue, TelemetryTap};
//!
//! let mut queue = TelemetryQueue::new();
//! let (mut producer, mut consumer) = queue.split();
//! let mut tap = TelemetryTap::new();
//! let mut packer = TelemetryPacker::new();
//! let mask = Channel::Setpoint.bit() | Channel::Left.bit();
//! let first = tap.start(mask, 5).unwrap(); // one sample every 5 ticks
//! packer.start(mask, 5, first, 50_000);
//! let report = TickReport {
//!     left: DacCode(1234), right: DacCode(0), estimate: 0, measured: 0, drive: 0, flags: TickFlags(0), triggers: 0,
//! };
//! for _ in 0..500 {
//!     tap.push(&mut producer, &TickSignals::of(1 << 29, 0, &report)); // setpoint 0.5 (Q2.30)
//! }
//! let mut out = [0u8; 600];
//! let n = twinstack::protocol::messages::encode_telemetry(&mut packer, &mut consumer, &mut out).unwrap();
//! let mut decoder = twinstack::protocol::decoder::FrameDecoder::new();
//! let (&delimiter, body) = out[..n].split_last().unwrap();
//! body.iter().for_each(|&b| assert!(decoder.push(b).is_none()));
//! let body = decoder.push(delimiter).unwrap().unwrap();
//! let Response::Telemetry(f) = frame::decode_body::<Response>(body).unwrap() else { panic!() };
//! assert_eq!((f.first, f.lost, f.values[0], f.values[1]), (0, 0, 16384, 1234));
//! ```

use heapless::spsc::{Consumer, Producer, Queue};
use serde::{Deserialize, Serialize};

use crate::refusal::{Field, Refusal, Rule};
use crate::services::decimation::Decimation;
use crate::services::recorder::{Channel, TickSignals, CHANNELS};

/// Slots of the telemetry queue (`heapless` keeps one free): 447 samples, 8.8 KiB; at 10 kHz
/// it holds 45 ms of samples, at 50 kHz 9 ms. Sized with the snapshot ring
/// ([`crate::services::snapshot::SNAPSHOT_RING_LEN`]) so that every image's static RAM leaves
/// the stack its reserve (`memory.x`).
pub const TELEMETRY_QUEUE_LEN: usize = 448;

/// The queue between the tick (producer) and the packer (consumer).
pub type TelemetryQueue = Queue<TelemetrySample, TELEMETRY_QUEUE_LEN>;

/// Most values (samples × signals) per second telemetry may ask for: what the board's
/// 2 Mbaud line carries at the worst case of 3 bytes a value, with its framing, beside the
/// acknowledgements of a 50 000 setpoints/s stream (measured in the simulation:
/// `hal-sim/tests/telemetry.rs`, and `docs/src/results/throughput.md`).
pub const MAX_VALUES_PER_SECOND: u32 = 50_000;

/// How much time's worth of samples the packer waits for before it makes a frame, seconds
/// (unless a full frame comes first).
pub const FRAME_LATENCY_S: f64 = 0.005;

/// One sample of the tick: all seven signals ([`TickSignals`]), in [`Channel`] order, each in
/// its slot format (Q1.15, DAC code, Q2.14: see [`crate::services::recorder`]); the packer sends the
/// mask's.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TelemetrySample {
    /// The sample's index: every sample the tap takes counts, sent or dropped.
    pub index: u32,
    /// The values.
    pub values: [i16; CHANNELS],
}

/// The tick's side: which signals, how often, and the sample counter.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct TelemetryTap {
    enabled: bool,
    mask: u8,
    /// One sample tick in every `decimation` ticks.
    decimation: Decimation,
    /// The next sample's index (never reset: samples of an earlier start stay before it).
    next: u32,
    overflows: u32,
    /// Samples between two wakes of the packer: the samples a frame waits for
    /// ([`frame_target`]).
    wake: u16,
    /// Samples queued since the last wake.
    since_wake: u16,
}

impl TelemetryTap {
    /// A tap that takes nothing.
    ///
    /// ```
    /// use twinstack::services::telemetry::TelemetryTap;
    /// let mut tap = TelemetryTap::new();
    /// assert!(!tap.is_running());
    /// assert_eq!(tap.start(0b1001, 5), Some(0)); // setpoint and sensor, every 5th tick
    /// assert_eq!(tap.start(0, 5), None); // no signal: refused
    /// ```
    pub const fn new() -> Self {
        Self {
            enabled: false,
            mask: 0,
            decimation: Decimation::every(1),
            next: 0,
            overflows: 0,
            wake: 1,
            since_wake: 0,
        }
    }

    /// Wakes the packer every `samples` samples queued (at least 1): what a frame waits for
    /// ([`frame_target`]), so that the packer runs once a frame, not once a tick. A packer
    /// that keeps up empties the queue each time, so this is the queue's fill level at which
    /// a frame is due; one that falls behind is woken again a frame later, whatever it left.
    pub fn wake_at(&mut self, samples: u16) {
        self.wake = samples.max(1);
        self.since_wake = 0;
    }

    /// Takes the signals of `mask` from the next tick on, one sample every `decimation`
    /// ticks; returns the index the first sample will carry. `None` (and nothing changed)
    /// for an empty mask, one with bits 6–7, or a decimation of 0.
    pub fn start(&mut self, mask: u8, decimation: u16) -> Option<u32> {
        if mask == 0 || mask >> CHANNELS != 0 || decimation == 0 {
            return None;
        }
        self.enabled = true;
        self.mask = mask;
        self.decimation = Decimation::every(decimation);
        Some(self.next)
    }

    /// Stops taking samples; returns the index the next sample would have carried (the
    /// run's end).
    pub fn stop(&mut self) -> u32 {
        self.enabled = false;
        self.next
    }

    /// Whether samples are being taken.
    pub fn is_running(&self) -> bool {
        self.enabled
    }

    /// The running tap's decimation: one sample every that many ticks; `None` when stopped.
    pub fn running_decimation(&self) -> Option<u16> {
        self.enabled.then_some(self.decimation.ticks())
    }

    /// `ticks` ticks were lost before they reached the tap (the snapshot ring was full: see
    /// [`crate::services::snapshot`]): the samples they would have given count as dropped,
    /// their indices skipped, so that the host sees the gap where it is. Off the tick (one
    /// division).
    #[cold]
    pub fn lose_ticks(&mut self, ticks: u32) {
        if !self.enabled || ticks == 0 {
            return;
        }
        let lost = self.decimation.skip(ticks);
        self.next = self.next.wrapping_add(lost);
        self.overflows = self.overflows.wrapping_add(lost);
    }

    /// Samples dropped because the queue was full (since power-up, wrapping).
    pub fn overflows(&self) -> u32 {
        self.overflows
    }

    /// One tick: on a sample tick, the tick's `signals` onto `queue` (all seven: the packer
    /// takes the mask's), or counted as an overflow if it is full. Returns whether to wake
    /// the packer: a frame's worth of samples taken since the last wake
    /// ([`TelemetryTap::wake_at`]), queued or dropped alike (a full queue does not wake it on
    /// every sample tick). O(1), no branch per signal, no panic path.
    #[inline(always)]
    pub fn push<const N: usize>(
        &mut self,
        queue: &mut Producer<'_, TelemetrySample, N>,
        signals: &TickSignals,
    ) -> bool {
        self.due() && self.queue(queue, signals)
    }

    /// One tick's countdown: whether this tick is a sample tick (telemetry running, and its
    /// decimation's countdown at zero, which it reloads), for [`TelemetryTap::queue`] to
    /// take. [`TelemetryTap::push`] is both.
    #[inline(always)]
    pub fn due(&mut self) -> bool {
        self.enabled && self.decimation.due()
    }

    /// Ticks before the next sample tick, each of which [`TelemetryTap::due`] would only
    /// count down (`u32::MAX` when stopped): what the services may pass over at once
    /// ([`TelemetryTap::pass`]).
    #[inline(always)]
    pub fn quiet_ticks(&self) -> u32 {
        if self.enabled {
            self.decimation.quiet_ticks()
        } else {
            u32::MAX
        }
    }

    /// Counts `ticks` ticks down at once, as that many [`TelemetryTap::due`] calls returning
    /// `false` would: `ticks` is at most [`TelemetryTap::quiet_ticks`] (more stops at the
    /// sample tick, which `due` then takes). O(1).
    #[inline(always)]
    pub fn pass(&mut self, ticks: u32) {
        if self.enabled {
            self.decimation.pass(ticks);
        }
    }

    /// Queues a sample tick's `signals` (after [`TelemetryTap::due`] said it is one), as
    /// [`TelemetryTap::push`] says; whether to wake the packer.
    #[inline(always)]
    pub fn queue<const N: usize>(
        &mut self,
        queue: &mut Producer<'_, TelemetrySample, N>,
        signals: &TickSignals,
    ) -> bool {
        let sample = TelemetrySample {
            index: self.next,
            values: signals.0,
        };
        self.next = self.next.wrapping_add(1);
        if queue.enqueue(sample).is_err() {
            self.overflows = self.overflows.wrapping_add(1);
        }
        // A dropped sample counts as a queued one: a packer that cannot keep up is woken a
        // frame's worth of samples later, not on every sample tick while the queue is full.
        self.since_wake += 1;
        let wake = self.since_wake >= self.wake;
        if wake {
            self.since_wake = 0;
        }
        wake
    }
}

/// Checks a telemetry request against the board's control rate: a mask of 1–6 signals
/// (bits 0–5) and a decimation of at least the least one whose values per second fit
/// [`MAX_VALUES_PER_SECOND`] (and at least 1) — refused, naming the field and that least
/// decimation, otherwise (a decimation of 0 included).
///
/// ```
/// use twinstack::refusal::{Field, Rule};
/// use twinstack::services::telemetry::check_request;
/// assert!(check_request(0b1001, 5, 50_000).is_ok()); // 2 signals at 10 kHz
/// let r = check_request(0b11_1111, 1, 50_000).unwrap_err(); // 300 000 values/s
/// assert_eq!((r.field, r.rule), (Field::TelemetryDecimation, Rule::AtLeast(6.0)));
/// let r = check_request(0b11_1111, 0, 50_000).unwrap_err(); // 0: the same least decimation
/// assert_eq!((r.field, r.rule), (Field::TelemetryDecimation, Rule::AtLeast(6.0)));
/// ```
pub fn check_request(signals: u8, decimation: u16, tick_rate_hz: u32) -> Result<(), Refusal> {
    if signals == 0 {
        return Err(Refusal::new(Field::TelemetrySignals, Rule::AtLeast(1.0)));
    }
    if signals >> CHANNELS != 0 {
        // Bit 7 names no signal: the mask is at most 0b111_1111.
        return Err(Refusal::new(Field::TelemetrySignals, Rule::AtMost(127.0)));
    }
    // The least decimation whose values per second fit the link (at least 1): a decimation
    // of 0 is refused with that same limit, as is any other below it.
    let per_tick = signals.count_ones() as u64 * tick_rate_hz as u64;
    let least = per_tick.div_ceil(MAX_VALUES_PER_SECOND as u64).max(1);
    if (decimation as u64) < least {
        return Err(Refusal::new(
            Field::TelemetryDecimation,
            Rule::AtLeast(least as f64),
        ));
    }
    Ok(())
}

/// Samples a telemetry frame of `mask` waits for at `decimation` and `tick_rate_hz`:
/// [`FRAME_LATENCY_S`]'s worth, at least 1 and at most a full frame. The packer makes a frame
/// at this fill level, and the tap wakes it there ([`TelemetryTap::wake_at`]).
///
/// ```
/// use twinstack::services::telemetry::frame_target;
/// assert_eq!(frame_target(0b11, 5, 50_000), 50); // 10 kHz: 5 ms is 50 samples
/// assert_eq!(frame_target(0b11_1111, 6, 50_000), 20); // a full frame: 120 values
/// ```
pub fn frame_target(mask: u8, decimation: u16, tick_rate_hz: u32) -> usize {
    let per_sample = (mask.count_ones() as usize).max(1);
    let capacity = (MAX_TELEMETRY_VALUES / per_sample).max(1);
    let samples_per_s = tick_rate_hz as f64 / decimation.max(1) as f64;
    let target = (samples_per_s * FRAME_LATENCY_S) as usize;
    target.clamp(1, capacity)
}

/// The packer's side: turns queued samples into frames (see the module doc). Runs off the
/// tick, where the board sends its frames.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct TelemetryPacker {
    /// Started, and the end frame not sent yet.
    running: bool,
    /// The run's end index, once stopped.
    stopping: Option<u32>,
    mask: u8,
    /// Values per sample.
    per_sample: usize,
    /// The run's first index.
    start: u32,
    /// The index of the next sample expected.
    expected: u32,
    lost: u32,
    seq: u16,
    /// Samples a frame waits for.
    target: usize,
    /// Most samples in a frame.
    capacity: usize,
}

impl TelemetryPacker {
    /// A packer with nothing to send.
    ///
    /// ```
    /// use twinstack::services::telemetry::{TelemetryPacker, TelemetryQueue};
    /// let mut queue = TelemetryQueue::new();
    /// let (_, mut samples) = queue.split();
    /// let mut packer = TelemetryPacker::new();
    /// assert!(!packer.is_active() && packer.next_frame(&mut samples).is_none());
    /// packer.start(0b11, 5, 0, 50_000); // 2 signals at 10 kHz: 5 ms is 50 samples
    /// assert_eq!(packer.target_samples(), 50);
    /// packer.stop(0); // stopped before any sample: the end frame says 0 were taken
    /// let end = packer.next_frame(&mut samples).unwrap();
    /// assert!(end.end && end.first == 0 && end.lost == 0);
    /// ```
    pub const fn new() -> Self {
        Self {
            running: false,
            stopping: None,
            mask: 0,
            per_sample: 0,
            start: 0,
            expected: 0,
            lost: 0,
            seq: 0,
            target: 1,
            capacity: 1,
        }
    }

    /// A run starts: samples of `mask` every `decimation` ticks at `tick_rate_hz`, the
    /// first carrying index `first` ([`TelemetryTap::start`]). Queued samples from before
    /// `first` are dropped unsent; frame and sample numbers restart at 0.
    pub fn start(&mut self, mask: u8, decimation: u16, first: u32, tick_rate_hz: u32) {
        let per_sample = (mask.count_ones() as usize).max(1);
        let capacity = (MAX_TELEMETRY_VALUES / per_sample).max(1);
        let target = frame_target(mask, decimation, tick_rate_hz);
        *self = Self {
            running: true,
            stopping: None,
            mask,
            per_sample,
            start: first,
            expected: first,
            lost: 0,
            seq: 0,
            target,
            capacity,
        };
    }

    /// The run was stopped at `end` ([`TelemetryTap::stop`]): what is queued is still
    /// sent, then the end frame. Nothing happens if telemetry is not running.
    pub fn stop(&mut self, end: u32) {
        if self.running {
            self.stopping = Some(end);
        }
    }

    /// Whether telemetry is running or its last frames are still to be sent.
    pub fn is_active(&self) -> bool {
        self.running
    }

    /// Samples a frame waits for (see the module doc).
    pub fn target_samples(&self) -> usize {
        self.target
    }

    /// Samples lost since the start, as far as the frames made so far tell.
    pub fn lost(&self) -> u32 {
        self.lost
    }

    /// Whether a frame is due: enough samples are queued, or the run was stopped and
    /// its last frames are to go.
    pub fn due<const N: usize>(&self, queue: &Consumer<'_, TelemetrySample, N>) -> bool {
        self.running && (self.stopping.is_some() || queue.len() >= self.target)
    }

    /// The next frame from the queue: consecutive samples (at most a frame's worth; a gap
    /// ends the frame), or, once stopped and drained, the end frame. `None` when there is
    /// nothing to send. Bounded: at most `N` samples looked at.
    pub fn next_frame<const N: usize>(
        &mut self,
        queue: &mut Consumer<'_, TelemetrySample, N>,
    ) -> Option<TelemetryFrame> {
        if !self.running {
            return None;
        }
        let mut frame = TelemetryFrame {
            seq: self.seq,
            first: 0,
            signals: self.mask,
            lost: 0,
            end: false,
            values: heapless::Vec::new(),
        };
        let mut count = 0usize;
        for _ in 0..N {
            let Some(sample) = queue.peek() else { break };
            let index = sample.index;
            if index.wrapping_sub(self.start) >= 1 << 31 {
                // Before the start: an earlier run's, never sent.
                queue.dequeue();
                continue;
            }
            if count == 0 {
                // A gap before it: samples dropped on a full queue.
                self.lost = self.lost.wrapping_add(index.wrapping_sub(self.expected));
                self.expected = index;
                frame.first = index.wrapping_sub(self.start);
            } else if index != self.expected || count >= self.capacity {
                break;
            }
            for channel in Channel::of_mask(self.mask) {
                // capacity × per_sample ≤ MAX_TELEMETRY_VALUES: this cannot fail.
                let _ = frame.values.push(sample.values[channel as usize]);
            }
            queue.dequeue();
            self.expected = self.expected.wrapping_add(1);
            count += 1;
        }
        if count == 0 {
            let end = self.stopping?;
            // Drained: the samples from the last one sent to the end were dropped.
            self.lost = self.lost.wrapping_add(end.wrapping_sub(self.expected));
            self.expected = end;
            frame.first = end.wrapping_sub(self.start);
            frame.end = true;
            self.running = false;
            self.stopping = None;
        }
        frame.lost = self.lost;
        self.seq = self.seq.wrapping_add(1);
        Some(frame)
    }
}

/// Most values (samples × signals) one telemetry frame carries: at most 3 bytes each on the
/// wire, about 2 ms of the line at 2 Mbaud.
pub const MAX_TELEMETRY_VALUES: usize = 120;

/// One unsolicited telemetry frame (the board → host, between responses): consecutive
/// samples from `first`, each its signals in [`crate::services::recorder::Channel`] order and format
/// (as a capture's slots). Samples lost to a full queue on the board are never silent: the
/// next frame's `first` skips them and `lost` counts them.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TelemetryFrame {
    /// Frame number since the start (wrapping): a gap means a frame was lost on the line.
    pub seq: u16,
    /// Index of the first sample, counted from 0 at the start (sample `i` is the tick
    /// `i × decimation` after the first sample's).
    pub first: u32,
    /// The signal mask of the samples.
    pub signals: u8,
    /// Samples lost on the board (queue full) since the start, up to `first`.
    pub lost: u32,
    /// The last frame of the telemetry (it was stopped): `first` is then the number of
    /// samples the run produced, and `values` is empty.
    pub end: bool,
    /// The samples' values, frame-interleaved (one per signal per sample).
    pub values: heapless::Vec<i16, MAX_TELEMETRY_VALUES>,
}

/// Where the board's outgoing frames go: USART1 TX by DMA on the board (two buffers: one on
/// the line, one waiting), the polled TX in the emulator (QEMU models no DMA), the modelled
/// line in the simulator. Responses and telemetry frames go through the same link, whole
/// frames at a time.
pub trait FrameLink {
    /// Whether a frame handed over now is taken at once (a buffer is free).
    fn ready(&mut self) -> bool;
    /// Hands a complete frame over (copied). `false` if it could not be taken (no buffer
    /// free; the caller retries).
    fn send_frame(&mut self, frame: &[u8]) -> bool;
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::board::DacCode;
    use crate::control::{TickFlags, TickReport};
    use crate::protocol::decoder::FrameDecoder;
    use crate::protocol::frame;
    use crate::protocol::messages::Response;
    use crate::services::recorder::{Recorder, Trigger};
    use std::vec;
    use std::vec::Vec;

    fn report(k: i32) -> TickReport {
        TickReport {
            left: DacCode(k as u16),
            right: DacCode(4095u16.wrapping_sub(k as u16)),
            estimate: (10 * k) << 15,
            measured: 0,
            drive: 0,
            flags: TickFlags(0),
            triggers: 0,
        }
    }

    /// Ticks `k` in `range`: setpoint k (Q1.15), sensor −k.
    fn run<const N: usize>(
        tap: &mut TelemetryTap,
        p: &mut Producer<'_, TelemetrySample, N>,
        range: std::ops::Range<i32>,
    ) {
        for k in range {
            tap.push(p, &TickSignals::of(k << 15, -k << 15, &report(k)));
        }
    }

    fn drain<const N: usize>(
        packer: &mut TelemetryPacker,
        c: &mut Consumer<'_, TelemetrySample, N>,
    ) -> Vec<TelemetryFrame> {
        let mut frames = Vec::new();
        while let Some(f) = packer.next_frame(c) {
            frames.push(f);
        }
        frames
    }

    #[test]
    fn decimates_and_keeps_the_mask_order() {
        let mut q: Queue<TelemetrySample, 64> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut tap = TelemetryTap::new();
        // Sensor and setpoint (mask order: setpoint first), every third tick.
        let mask = Channel::Sensor.bit() | Channel::Setpoint.bit();
        assert_eq!(tap.start(mask, 3), Some(0));
        run(&mut tap, &mut p, 0..10);
        // Each sample holds the tick's seven signals (ticks 0, 3, 6, 9)…
        let mut packer = TelemetryPacker::new();
        packer.start(mask, 3, 0, 50_000);
        assert_eq!(c.len(), 4);
        let s = c.peek().copied().unwrap_or_default();
        assert_eq!(
            (s.index, s.values),
            (0, TickSignals::of(0, 0, &report(0)).0)
        );
        // …and the packer sends the mask's, in channel order: setpoint k, sensor −k.
        packer.stop(4);
        let f = packer.next_frame(&mut c).unwrap();
        assert_eq!((f.first, f.lost), (0, 0));
        assert_eq!(&f.values[..], &[0, 0, 3, -3, 6, -6, 9, -9]);
        assert_eq!(tap.stop(), 4);
        run(&mut tap, &mut p, 10..20);
        assert!(c.dequeue().is_none(), "a stopped tap takes nothing");
    }

    #[test]
    fn bad_starts_are_refused_and_change_nothing() {
        let mut tap = TelemetryTap::new();
        for (mask, dec) in [(0, 1), (0x80, 1), (1, 0)] {
            assert_eq!(tap.start(mask, dec), None);
        }
        assert!(!tap.is_running());
        let refusal = |s, d, r| check_request(s, d, r).map_err(|e| (e.field, e.rule));
        assert_eq!(
            refusal(0, 1, 50_000),
            Err((Field::TelemetrySignals, Rule::AtLeast(1.0)))
        );
        assert_eq!(
            refusal(0x81, 1, 50_000),
            Err((Field::TelemetrySignals, Rule::AtMost(127.0)))
        );
        assert_eq!(
            refusal(1, 0, 50_000),
            Err((Field::TelemetryDecimation, Rule::AtLeast(1.0)))
        );
        // A decimation of 0 is refused with the least decimation that fits, not with 1.
        assert_eq!(
            refusal(0b11_1111, 0, 50_000),
            Err((Field::TelemetryDecimation, Rule::AtLeast(6.0)))
        );
        // 2 signals at 50 kHz: 100 000 values/s; decimation 2 is the least that fits.
        assert_eq!(
            refusal(0b11, 1, 50_000),
            Err((Field::TelemetryDecimation, Rule::AtLeast(2.0)))
        );
        assert_eq!(refusal(0b11, 2, 50_000), Ok(()));
        // Five signals at 10 kHz: exactly the limit.
        assert_eq!(refusal(0b1_1111, 5, 50_000), Ok(()));
        assert_eq!(
            refusal(0b11_1111, 5, 50_000),
            Err((Field::TelemetryDecimation, Rule::AtLeast(6.0)))
        );
    }

    #[test]
    fn the_tap_wakes_the_packer_at_a_frame_s_worth_not_every_sample() {
        let mut q: Queue<TelemetrySample, 16> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut tap = TelemetryTap::new();
        tap.wake_at(frame_target(0b11, 2, 2_000) as u16); // 1 kHz of samples: 5 ms is 5
        tap.start(0b11, 2).unwrap();
        let signals = TickSignals::default();
        let wakes: Vec<bool> = (0..20).map(|_| tap.push(&mut p, &signals)).collect();
        // Every other tick samples; the fifth sample (tick 8) is a frame's worth.
        let at: Vec<usize> = (0..20).filter(|&i| wakes[i]).collect();
        assert_eq!(at, [8, 18]);
        // Five samples on (tick 18), once more: a frame's worth, whatever the packer left.
        assert_eq!(
            wakes.iter().filter(|&&w| w).count(),
            1 + usize::from(wakes[18])
        );
        assert!(wakes[18]);
        for _ in 0..5 {
            c.dequeue().unwrap();
        }
        let at: Vec<usize> = (0..10).filter(|_| tap.push(&mut p, &signals)).collect();
        assert_eq!(at.len(), 1);
        // A full queue (the packer stalled) wakes it a frame's worth of samples later, as
        // queued ones do, not on every sample it drops.
        for _ in 0..40 {
            tap.push(&mut p, &signals);
        }
        assert!(p.len() == 15 && tap.overflows() > 0);
        let wakes = (0..40).filter(|_| tap.push(&mut p, &signals)).count();
        assert_eq!(wakes, 4, "20 samples dropped in 40 ticks: one wake per 5");
        assert!(tap.overflows() >= 20);
    }

    #[test]
    fn the_tap_sends_what_the_recorder_records() {
        // One quantity in one form: all seven channels agree with a capture of the same ticks.
        let mut rec = Recorder::new(vec![0i16; 64]);
        rec.arm_capture(0b111_1111, 4, 0, Trigger::Now, 1).unwrap();
        let mut q: Queue<TelemetrySample, 8> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut tap = TelemetryTap::new();
        tap.start(0b111_1111, 1).unwrap();
        for (k, (sp, sensor)) in [
            (-(1 << 30), 1 << 29),
            (1 << 29, -(1 << 30)),
            (i32::MAX, i32::MIN),
            (123_456_789, -987_654),
        ]
        .into_iter()
        .enumerate()
        {
            let mut rep = report(k as i32 * 1000);
            rep.estimate = sp / 3;
            rep.triggers = (k as u8 * 5) & 0b1111;
            let signals = TickSignals::of(sp, sensor, &rep);
            rec.capture(&signals, sp, sensor, &rep);
            tap.push(&mut p, &signals);
        }
        let mut window = heapless::Vec::new();
        rec.read_capture(0, 28, &mut window).unwrap();
        let sent: Vec<i16> = core::iter::from_fn(|| c.dequeue())
            .flat_map(|s| s.values)
            .collect();
        assert_eq!(&sent[..], &window[..]);
    }

    #[test]
    fn a_full_queue_counts_overflows_and_the_frames_announce_the_gap() {
        // A queue of 7 samples, 20 ticks before the packer runs: 13 dropped.
        let mut q: Queue<TelemetrySample, 8> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut tap = TelemetryTap::new();
        let mut packer = TelemetryPacker::new();
        let first = tap.start(Channel::Setpoint.bit(), 1).unwrap();
        packer.start(Channel::Setpoint.bit(), 1, first, 50_000);
        run(&mut tap, &mut p, 0..20);
        assert_eq!(tap.overflows(), 13);
        let f = packer.next_frame(&mut c).unwrap();
        assert_eq!((f.seq, f.first, f.lost, f.end), (0, 0, 0, false));
        assert_eq!(&f.values[..], &[0, 1, 2, 3, 4, 5, 6]);
        // The next ticks find room again: the frame after the gap says where it resumes.
        run(&mut tap, &mut p, 20..23);
        let f = packer.next_frame(&mut c).unwrap();
        assert_eq!((f.seq, f.first, f.lost), (1, 20, 13));
        assert_eq!(&f.values[..], &[20, 21, 22]);
        assert!(packer.next_frame(&mut c).is_none());
        // Dropped at the tail, then stopped: the end frame counts them too.
        run(&mut tap, &mut p, 23..40);
        packer.stop(tap.stop());
        let frames = drain(&mut packer, &mut c);
        let end = frames.last().unwrap();
        assert!(end.end && end.values.is_empty());
        assert_eq!((end.first, end.lost), (40, 13 + 10));
        assert_eq!(tap.overflows(), 23);
        let received: usize = frames.iter().map(|f| f.values.len()).sum();
        assert_eq!(7 + 3 + received as u32 + end.lost, end.first);
        assert!(!packer.is_active());
    }

    #[test]
    fn frames_hold_whole_samples_and_wait_for_their_target() {
        let mut q: Queue<TelemetrySample, 512> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut tap = TelemetryTap::new();
        let mut packer = TelemetryPacker::new();
        // Three signals at 10 kHz: 50 samples are 5 ms; a frame holds 40.
        let mask = Channel::Setpoint.bit() | Channel::Left.bit() | Channel::Error.bit();
        let first = tap.start(mask, 5).unwrap();
        packer.start(mask, 5, first, 50_000);
        assert_eq!(packer.target_samples(), 40);
        run(&mut tap, &mut p, 0..(39 * 5));
        assert!(!packer.due(&c));
        run(&mut tap, &mut p, (39 * 5)..(100 * 5));
        assert!(packer.due(&c));
        let frames = drain(&mut packer, &mut c);
        assert_eq!(
            frames.iter().map(|f| f.values.len()).collect::<Vec<_>>(),
            [120, 120, 60]
        );
        assert_eq!(
            frames.iter().map(|f| (f.seq, f.first)).collect::<Vec<_>>(),
            [(0, 0), (1, 40), (2, 80)]
        );
        // Sample 41 (tick 205): setpoint 205, left 205, error (205 − (−205)) in Q2.14.
        assert_eq!(&frames[1].values[3..6], &[205, 205, 205]);
        // A slow rate sends every sample at once.
        packer.start(mask, 60_000, tap.start(mask, 60_000).unwrap(), 50_000);
        assert_eq!(packer.target_samples(), 1);
    }

    #[test]
    fn a_restart_drops_the_earlier_runs_samples() {
        let mut q: Queue<TelemetrySample, 64> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut tap = TelemetryTap::new();
        let mut packer = TelemetryPacker::new();
        packer.start(1, 1, tap.start(1, 1).unwrap(), 50_000);
        run(&mut tap, &mut p, 0..10);
        // Restarted with another mask before the packer ran.
        let first = tap.start(Channel::Left.bit(), 1).unwrap();
        packer.start(Channel::Left.bit(), 1, first, 50_000);
        run(&mut tap, &mut p, 10..13);
        let frames = drain(&mut packer, &mut c);
        assert_eq!(frames.len(), 1);
        assert_eq!((frames[0].first, frames[0].lost), (0, 0));
        assert_eq!(&frames[0].values[..], &[10, 11, 12]);
    }

    #[test]
    fn frames_round_trip_through_the_wire() {
        let mut q: Queue<TelemetrySample, 512> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut tap = TelemetryTap::new();
        let mut packer = TelemetryPacker::new();
        let mask = 0b11_1111;
        packer.start(mask, 1, tap.start(mask, 1).unwrap(), 50_000);
        run(&mut tap, &mut p, -3000..-2900);
        packer.stop(tap.stop());
        let mut out = [0u8; frame::MAX_ENCODED + 1];
        let mut decoder = FrameDecoder::new();
        let mut values = Vec::new();
        let mut ended = false;
        while let Some(n) =
            crate::protocol::messages::encode_telemetry(&mut packer, &mut c, &mut out)
        {
            // A full frame of the worst case (3 bytes a value) fits in what the docs say.
            assert!(n <= MAX_TELEMETRY_VALUES * 3 + 24, "{n} bytes");
            let (&delimiter, body) = out[..n].split_last().unwrap();
            body.iter()
                .for_each(|&b| assert!(decoder.push(b).is_none()));
            let body = decoder.push(delimiter).unwrap().unwrap();
            let Response::Telemetry(f) = frame::decode_body::<Response>(body).unwrap() else {
                panic!("not a telemetry frame");
            };
            assert_eq!((f.signals, f.lost), (mask, 0));
            assert_eq!(f.first as usize, values.len() / 6);
            values.extend_from_slice(&f.values);
            ended = f.end;
        }
        assert!(ended);
        assert_eq!(values.len(), 600);
        let setpoints: Vec<i16> = values.iter().step_by(6).copied().collect();
        assert_eq!(setpoints, (-3000..-2900).collect::<Vec<i16>>());
    }
}
