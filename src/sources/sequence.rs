//! TTL-stepped sequences: a list of positions advanced one per edge on the trigger input, with
//! a "settled" output — what a microscope's camera steps a Z stage with, instead of a serial
//! round trip per step.
//!
//! # Where the positions are
//!
//! In the setpoint queue ([`crate::control_loop::SetpointQueue`]), sent as the stream's are
//! (Q1.15 wire samples, with credits): while a sequence is armed the stream is stopped and
//! [`SteppedSequence::next`] pops **one position per edge** instead of one per tick. So a
//! sequence needs no RAM of its own, and it may be longer than the queue (19 999 positions on
//! the board) when the host keeps the queue topped up as edges consume it.
//!
//! # One tick
//!
//! 1. **Settled**: the stage's position as the tick knows it (the sensor's last reading; without
//!    a sensor the setpoint itself, [`crate::control::Controller::position`]: the observer's
//!    estimate is computed below the tick, a batch later) within `window` of the target, and the shaped
//!    setpoint on it, for `settle_ticks` ticks in a row: the settled output goes high
//!    ([`SETTLED`], on its own pin). A new target takes it low at once.
//! 2. **Edge**: the chosen edge of the trigger input (sampled before the tick) pops the next
//!    position. An edge while not settled is counted **early** (the position still advances:
//!    the camera's frames and the positions stay in step); an edge that finds the queue empty is
//!    counted **missed** (the stage holds).
//! 3. **Shaping**: the setpoint walks to the target by at most `step` per tick (a quarter of the
//!    drive's slew limit, as a scan's approach: the compensator and the feedback ride on top
//!    without reaching the limit), and goes through the compensator, the feedback and the
//!    drive's range and slew limits like any setpoint.
//!
//! The edge is seen by the tick that samples it, and that same tick's setpoint has moved toward
//! the new position: **the first moved DAC sample is the edge's own tick** (at most one tick
//! after the edge on the pin). O(1): one compare when disarmed, a queue pop on an edge, no
//! division, no loop.
//!
//! Every field is Q2.30 normalised displacement unless said.

use serde::{Deserialize, Serialize};

use crate::fixed_point::{signal_from_f64, SIGNAL_ONE};
use crate::refusal::{Field, Refusal, Rule};
use crate::sources::scan::{EdgeDetector, TriggerEdge};
use crate::sources::setpoint_stream::setpoint_from_wire;
use heapless::spsc::Consumer;

/// Output bit of the settled output, in [`crate::control_loop::ControlLoop::trigger_levels`]
/// (bit 4: bits 0–2 are the scan's clocks, bit 3 the trigger input in the capture's channel).
pub const SETTLED: u8 = 1 << 4;

/// Longest settle time, ticks (1.3 s at 50 kHz).
pub const MAX_SETTLE_TICKS: u16 = u16::MAX;

/// A sequence's settings (protocol `Sequence(Arm)`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SequenceConfig {
    /// The trigger input's edge that advances the sequence (`Rising` or `Falling`).
    pub edge: TriggerEdge,
    /// The settle window's half-width, normalised displacement (0 < window ≤ 1): the stage is
    /// settled within ± this of the target.
    pub window: f32,
    /// Ticks in a row within the window before the settled output goes high (at least 1).
    pub settle_ticks: u16,
}

impl SequenceConfig {
    /// Checks the settings; the refusal names the field and its limit.
    ///
    /// ```
    /// use twinstack::sources::scan::TriggerEdge;
    /// use twinstack::sources::sequence::SequenceConfig;
    /// let ok = SequenceConfig { edge: TriggerEdge::Rising, window: 0.01, settle_ticks: 50 };
    /// assert!(ok.check().is_ok());
    /// assert!(SequenceConfig { window: f32::NAN, ..ok }.check().is_err());
    /// assert!(SequenceConfig { edge: TriggerEdge::Off, ..ok }.check().is_err());
    /// ```
    pub fn check(&self) -> Result<(), Refusal> {
        if self.edge == TriggerEdge::Off {
            return Err(Refusal::new(Field::SequenceEdge, Rule::Required));
        }
        if !self.window.is_finite() {
            return Err(Refusal::new(Field::SequenceWindow, Rule::NotFinite));
        }
        // At least one Q2.30 LSB, at most the half stroke.
        if self.window <= 0.0 {
            return Err(Refusal::new(Field::SequenceWindow, Rule::Above(0.0)));
        }
        if self.window > 1.0 {
            return Err(Refusal::new(Field::SequenceWindow, Rule::AtMost(1.0)));
        }
        if self.settle_ticks == 0 {
            return Err(Refusal::new(Field::SequenceSettle, Rule::AtLeast(1.0)));
        }
        Ok(())
    }

    /// The settings in the tick's fixed point, moving by at most `max_step` (Q2.30, clamped
    /// to ≥ 1 LSB) per tick: computed before the lock that arms the sequence, so that the
    /// tick is never held off for the conversion (soft floating point on the board).
    ///
    /// ```
    /// use twinstack::sources::scan::TriggerEdge;
    /// use twinstack::sources::sequence::SequenceConfig;
    /// let c = SequenceConfig { edge: TriggerEdge::Rising, window: 0.5, settle_ticks: 0 };
    /// let p = c.prepare(0);
    /// assert_eq!((p.window, p.settle_ticks, p.step), (1 << 29, 1, 1));
    /// ```
    pub fn prepare(&self, max_step: i32) -> PreparedSequence {
        PreparedSequence {
            edge: self.edge,
            window: signal_from_f64(self.window as f64).unsigned_abs(),
            settle_ticks: self.settle_ticks.max(1),
            step: max_step.max(1),
        }
    }
}

/// A sequence's settings as the tick uses them ([`SequenceConfig::prepare`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PreparedSequence {
    /// The input's edge that advances the sequence.
    pub edge: TriggerEdge,
    /// The settle window's half-width, Q2.30.
    pub window: u32,
    /// Ticks in a row within the window before the settled output goes high (≥ 1).
    pub settle_ticks: u16,
    /// Largest setpoint change per tick, Q2.30 (≥ 1).
    pub step: i32,
}

/// Arm, stop or read a sequence (protocol `Request::Sequence`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum SequenceRequest {
    /// Arms a sequence over the positions queued (and those queued later): the stream, the
    /// waveform or a scan stops, the stage holds until the first edge, which moves it to the
    /// first position. Counters start at zero.
    Arm(SequenceConfig),
    /// Disarms: the stage holds where it is; positions not reached stay queued.
    Stop,
    /// Reads the sequence's state (answered with `Response::Sequence`).
    Status,
}

/// A sequence's state (the answer to `Sequence(Status)`). Counts since the last arming.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct SequenceStatus {
    /// Whether edges advance the sequence.
    pub armed: bool,
    /// Whether the settled output is high.
    pub settled: bool,
    /// Edges that moved the stage to a position (positions reached or under way).
    pub steps: u32,
    /// Edges that came while the stage had not settled (the position still advanced).
    pub early: u32,
    /// Edges that found no position queued (the stage held).
    pub missed: u32,
    /// The position in force, Q2.30 normalised displacement.
    pub target: i32,
}

/// The tick half of a sequence (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SteppedSequence {
    armed: bool,
    /// The trigger input's edges.
    edges: EdgeDetector,
    /// The shaped setpoint, Q2.30.
    current: i32,
    /// The position in force, Q2.30.
    target: i32,
    /// Largest setpoint change per tick, Q2.30, > 0.
    step: i32,
    /// The settle window's half-width, Q2.30.
    window: u32,
    settle_ticks: u16,
    /// Ticks in a row within the window.
    inside: u16,
    settled: bool,
    steps: u32,
    early: u32,
    missed: u32,
}

impl Default for SteppedSequence {
    fn default() -> Self {
        Self::new()
    }
}

impl SteppedSequence {
    /// Disarmed.
    pub const fn new() -> Self {
        Self {
            armed: false,
            edges: EdgeDetector::new(TriggerEdge::Rising, false),
            current: 0,
            target: 0,
            step: 1,
            window: 0,
            settle_ticks: 1,
            inside: 0,
            settled: false,
            steps: 0,
            early: 0,
            missed: 0,
        }
    }

    /// Arms `config` (checked, [`SequenceConfig::check`], and prepared,
    /// [`SequenceConfig::prepare`]) with the setpoint at `from` (Q2.30) and the input at
    /// `level`. Counters restart at zero. A few stores: no conversion, no loop.
    ///
    /// ```
    /// use heapless::spsc::Queue;
    /// use twinstack::sources::scan::TriggerEdge;
    /// use twinstack::sources::sequence::{SequenceConfig, SteppedSequence};
    /// let mut q: Queue<i16, 4> = Queue::new();
    /// let (mut p, mut c) = q.split();
    /// p.enqueue(16384).unwrap(); // 0.5
    /// let mut s = SteppedSequence::new();
    /// let config = SequenceConfig { edge: TriggerEdge::Rising, window: 0.01, settle_ticks: 1 };
    /// s.arm(&config.prepare(1 << 28), 0, false);
    /// assert_eq!(s.next(false, 0, &mut c), 0); // no edge: holds
    /// assert_eq!(s.next(true, 0, &mut c), 1 << 28); // the edge's own tick moves
    /// assert_eq!(s.next(true, 0, &mut c), 1 << 29); // and arrives
    /// ```
    pub fn arm(&mut self, config: &PreparedSequence, from: i32, level: bool) {
        *self = Self {
            armed: true,
            edges: EdgeDetector::new(config.edge, level),
            current: from,
            target: from,
            step: config.step,
            window: config.window,
            settle_ticks: config.settle_ticks,
            ..Self::new()
        };
    }

    /// Disarms (the stage holds where the setpoint is; the counts stay readable).
    pub fn disarm(&mut self) {
        self.armed = false;
        self.settled = false;
        self.inside = 0;
    }

    /// Whether edges advance it.
    #[inline(always)]
    pub fn is_armed(&self) -> bool {
        self.armed
    }

    /// The settled output's bit ([`SETTLED`] or 0).
    #[inline(always)]
    pub fn level(&self) -> u8 {
        if self.settled {
            SETTLED
        } else {
            0
        }
    }

    /// The state and counts.
    pub fn status(&self) -> SequenceStatus {
        SequenceStatus {
            armed: self.armed,
            settled: self.settled,
            steps: self.steps,
            early: self.early,
            missed: self.missed,
            target: self.target,
        }
    }

    /// One tick (armed): `level` the trigger input now, `position` where the stage is
    /// (Q2.30, the last tick's reading); returns this tick's setpoint (Q2.30). See the module
    /// doc. O(1).
    // Inlined into the tick, where its source is the rarer branch (`crate::rare`), which the
    // compiler would otherwise leave a call.
    #[inline(always)]
    pub fn next<const N: usize>(
        &mut self,
        level: bool,
        position: i32,
        queue: &mut Consumer<'_, i16, N>,
    ) -> i32 {
        // 1. Settled.
        let within = self.current == self.target
            && (position as i64 - self.target as i64).unsigned_abs() <= self.window as u64;
        if within {
            if self.inside < self.settle_ticks {
                self.inside = self.inside.wrapping_add(1);
            }
        } else {
            self.inside = 0;
        }
        self.settled = self.inside >= self.settle_ticks;
        // 2. Edge.
        if self.edges.poll(level) {
            self.advance(queue);
        }
        // 3. Shaping: at most `step` toward the target (`max`/`min`, not `clamp`: no panic
        // path on the tick).
        let d = (self.target as i64 - self.current as i64)
            .max(-(self.step as i64))
            .min(self.step as i64);
        self.current = (self.current as i64 + d) as i32;
        self.current
    }

    /// An edge: the next position, or a miss; early if not settled.
    #[inline(never)] // once per edge: kept out of the common tick
    fn advance<const N: usize>(&mut self, queue: &mut Consumer<'_, i16, N>) {
        if !self.settled {
            self.early = self.early.wrapping_add(1);
        }
        match queue.dequeue() {
            Some(sample) => {
                self.target = setpoint_from_wire(sample);
                self.steps = self.steps.wrapping_add(1);
                self.settled = false;
                self.inside = 0;
            }
            None => self.missed = self.missed.wrapping_add(1),
        }
    }
}

/// The largest step per tick (Q2.30) a sequence moves by with the drive's slew step
/// `slew_step` (Q2.30 per tick, [`crate::sources::scan::slew_step`]): a quarter of it, at least one LSB.
///
/// ```
/// assert_eq!(twinstack::sources::sequence::move_step(1 << 28), 1 << 26);
/// ```
pub const fn move_step(slew_step: i32) -> i32 {
    let q = slew_step / 4;
    if q < 1 {
        1
    } else if q > SIGNAL_ONE {
        SIGNAL_ONE
    } else {
        q
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use heapless::spsc::Queue;

    fn config(settle: u16) -> SequenceConfig {
        SequenceConfig {
            edge: TriggerEdge::Rising,
            window: 0.001,
            settle_ticks: settle,
        }
    }

    #[test]
    fn each_edge_pops_one_position_and_an_empty_queue_is_a_miss() {
        let mut q: Queue<i16, 8> = Queue::new();
        let (mut p, mut c) = q.split();
        for x in [1000, 2000] {
            p.enqueue(x).unwrap();
        }
        let mut s = SteppedSequence::new();
        s.arm(&config(3).prepare(SIGNAL_ONE), 0, false);
        let mut level = false;
        let mut toggle = |s: &mut SteppedSequence, c: &mut _, n: usize| {
            for _ in 0..n {
                level = !level;
                // The stage follows the setpoint exactly.
                let pos = s.current;
                s.next(level, pos, c);
            }
        };
        // Settle at the start (3 ticks), then edge (rise) and fall, and settle again.
        toggle(&mut s, &mut c, 0);
        for _ in 0..4 {
            s.next(false, 0, &mut c);
        }
        assert!(s.status().settled);
        toggle(&mut s, &mut c, 2);
        assert_eq!(s.status().target, setpoint_from_wire(1000));
        assert_eq!(c.len(), 1, "one position per edge, not per tick");
        for _ in 0..4 {
            let pos = s.current;
            s.next(false, pos, &mut c);
        }
        toggle(&mut s, &mut c, 2); // second position, settled before it
        toggle(&mut s, &mut c, 2); // nothing left: missed (and early: 2 ticks of 3)
        let st = s.status();
        assert_eq!((st.steps, st.missed, st.early), (2, 1, 1));
        assert_eq!(st.target, setpoint_from_wire(2000));
    }

    #[test]
    fn an_edge_before_settling_is_early_and_still_advances() {
        let mut q: Queue<i16, 8> = Queue::new();
        let (mut p, mut c) = q.split();
        for x in [5000, 6000, 7000] {
            p.enqueue(x).unwrap();
        }
        let mut s = SteppedSequence::new();
        s.arm(&config(10).prepare(SIGNAL_ONE), 0, false);
        // Edges every other tick: never 10 ticks within the window.
        for k in 0..6 {
            let pos = s.current;
            s.next(k % 2 == 1, pos, &mut c);
        }
        let st = s.status();
        assert_eq!((st.steps, st.early, st.missed), (3, 3, 0));
        assert!(!st.settled);
    }

    #[test]
    fn the_move_is_shaped_and_the_edge_tick_moves() {
        let mut q: Queue<i16, 4> = Queue::new();
        let (mut p, mut c) = q.split();
        p.enqueue(i16::MAX).unwrap();
        let mut s = SteppedSequence::new();
        let step = 1 << 24;
        s.arm(
            &config(1).prepare(step),
            setpoint_from_wire(i16::MIN),
            false,
        );
        let mut last = s.next(false, 0, &mut c);
        let first = s.next(true, 0, &mut c);
        assert_eq!(first - last, step, "the edge's own tick moves by one step");
        last = first;
        for _ in 0..200 {
            let x = s.next(true, 0, &mut c);
            assert!((x - last).abs() <= step);
            last = x;
        }
        assert_eq!(last, setpoint_from_wire(i16::MAX));
    }

    #[test]
    fn a_falling_edge_sequence_ignores_rising_edges_and_settles_on_the_reading() {
        let mut q: Queue<i16, 4> = Queue::new();
        let (mut p, mut c) = q.split();
        p.enqueue(100).unwrap();
        let mut s = SteppedSequence::new();
        let cfg = SequenceConfig {
            edge: TriggerEdge::Falling,
            ..config(3)
        };
        s.arm(&cfg.prepare(SIGNAL_ONE), 0, false);
        s.next(true, 0, &mut c);
        assert_eq!(s.status().steps, 0);
        s.next(false, 0, &mut c);
        assert_eq!(s.status().steps, 1);
        // A reading outside the window never settles; inside, after 3 ticks.
        let far = setpoint_from_wire(100) + signal_from_f64(0.01);
        for _ in 0..10 {
            s.next(false, far, &mut c);
        }
        assert_eq!(s.level(), 0);
        for _ in 0..3 {
            s.next(false, setpoint_from_wire(100), &mut c);
        }
        assert_eq!(s.level(), SETTLED);
    }

    #[test]
    fn bad_settings_are_refused_by_field() {
        let ok = config(5);
        assert_eq!(
            SequenceConfig { window: 2.0, ..ok }
                .check()
                .unwrap_err()
                .field,
            Field::SequenceWindow
        );
        assert_eq!(
            SequenceConfig {
                settle_ticks: 0,
                ..ok
            }
            .check()
            .unwrap_err()
            .field,
            Field::SequenceSettle
        );
    }
}
