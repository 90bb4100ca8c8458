//! Where each tick's setpoint comes from: the queue the host streams into, interpolated when the
//! stream is slower than the control rate, or the built-in waveform generator.
//!
//! Streamed samples are Q1.15 normalised displacement (the wire format, see
//! [`crate::protocol::messages`]); setpoints leave as Q2.30. With a rate divider `D`, sample
//! `s_k` is reached `D` ticks after `s_{k−1}`, in equal steps (one multiply by the divider's
//! reciprocal, prepared when the divider is set: no division on the tick), and the segment
//! ends exactly on `s_k`.
//!
//! When the queue runs dry the policy decides: **hold** returns `None`, so the control tick holds
//! the last setpoint and counts an underrun; **ramp to bias** walks the setpoint to the rest
//! position at a bounded rate (counted here, in [`SetpointStream::ramp_underruns`]).

use crate::sources::waveform::WaveformGenerator;
use heapless::spsc::Consumer;

/// Q1.15 wire sample → Q2.30 setpoint.
#[inline(always)]
pub fn setpoint_from_wire(sample: i16) -> i32 {
    (sample as i32) << 15
}

/// Q2.30 setpoint → Q1.15 wire sample (rounded, saturated).
pub fn setpoint_to_wire(setpoint: i32) -> i16 {
    let rounded = (setpoint as i64 + (1 << 14)) >> 15;
    rounded.clamp(i16::MIN as i64, i16::MAX as i64) as i16
}

/// What the board does when the setpoint queue runs dry.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum UnderrunPolicy {
    /// Hold the last setpoint.
    Hold,
    /// Ramp to the rest position (the bias), within the slew limit.
    RampToBias,
}

/// What to do when the queue runs dry.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Underrun {
    /// Hold the last setpoint (the tick counts the underrun).
    Hold,
    /// Walk to `rest` (Q2.30) by at most `step` (Q2.30) per tick.
    RampToRest {
        /// Rest setpoint, Q2.30.
        rest: i32,
        /// Largest change per tick, Q2.30, > 0.
        step: i32,
    },
}

/// The tick's setpoint source.
#[derive(Clone, Debug)]
pub struct SetpointStream {
    running: bool,
    divider: u16,
    /// `2^32 / divider`, rounded down (0 for divider 1, which needs no increment): a segment's
    /// step is `(|span| · reciprocal) >> 32` with the span's sign, one `UMULL`-class multiply
    /// instead of a 64-bit division, and never larger than `|span| / divider`.
    reciprocal: u64,
    /// Ticks left in the current segment.
    remaining: u16,
    /// Current setpoint, Q2.30.
    current: i32,
    /// End of the current segment, Q2.30.
    target: i32,
    /// Change per tick within the segment, Q2.30.
    increment: i32,
    underrun: Underrun,
    waveform: Option<WaveformGenerator>,
    ramp_underruns: u32,
    /// The host has sent its last setpoint ([`SetpointStream::finish`]): the stream stops
    /// when the queue runs dry instead of counting underruns.
    finishing: bool,
}

impl SetpointStream {
    /// A stopped stream holding `initial` (Q2.30), divider 1, underrun policy hold.
    pub fn new(initial: i32) -> Self {
        Self {
            running: false,
            divider: 1,
            reciprocal: 0,
            remaining: 0,
            current: initial,
            target: initial,
            increment: 0,
            underrun: Underrun::Hold,
            waveform: None,
            ramp_underruns: 0,
            finishing: false,
        }
    }

    /// Starts consuming the queue (and stops the waveform generator).
    pub fn start(&mut self) {
        self.running = true;
        self.waveform = None;
    }

    /// The queue holds the stream's last setpoints: play them, then stop (holding the last
    /// one) when the queue runs dry, so that the ticks after the end are not underruns. Sent
    /// before [`Self::start`] (a record queued whole), it holds for the stream that start
    /// begins; [`Self::stop`] and the waveform cancel it.
    pub fn finish(&mut self) {
        if self.waveform.is_none() {
            self.finishing = true;
        }
    }

    /// Whether the stream stops by itself when the queue runs dry ([`Self::finish`]).
    pub fn is_finishing(&self) -> bool {
        self.finishing
    }

    /// Stops: the setpoint holds where it is; queued samples stay queued.
    pub fn stop(&mut self) {
        self.running = false;
        self.finishing = false;
        self.waveform = None;
        self.remaining = 0;
        self.target = self.current;
    }

    /// Sets the rate divider (ticks per streamed sample); 0 is refused (returns `false`).
    pub fn set_divider(&mut self, divider: u16) -> bool {
        if divider == 0 {
            return false;
        }
        self.divider = divider;
        self.reciprocal = if divider == 1 {
            0
        } else {
            (1u64 << 32) / divider as u64
        };
        true
    }

    /// Sets the underrun policy; a ramp step ≤ 0 is refused (returns `false`).
    pub fn set_underrun(&mut self, policy: Underrun) -> bool {
        if let Underrun::RampToRest { step, .. } = policy {
            if step <= 0 {
                return false;
            }
        }
        self.underrun = policy;
        true
    }

    /// A stopped stream holds `setpoint` (Q2.30) from now on: after a reload, where the new
    /// configuration puts the stage (a stopped stream's old value is in the old output range's
    /// units). A running stream or waveform is left alone.
    pub fn hold_at_if_stopped(&mut self, setpoint: i32) {
        if !self.running {
            self.current = setpoint;
            self.target = setpoint;
            self.remaining = 0;
        }
    }

    /// Moves the ramp-to-rest policy's rest position to `rest` (Q2.30): a reload changes the
    /// rest position; the hold policy has none.
    #[inline(always)]
    pub fn move_rest(&mut self, rest: i32) {
        if let Underrun::RampToRest { rest: r, .. } = &mut self.underrun {
            *r = rest;
        }
    }

    /// Runs the waveform generator instead of the queue.
    pub fn play(&mut self, waveform: WaveformGenerator) {
        self.waveform = Some(waveform);
        self.running = true;
        self.finishing = false;
    }

    /// Whether the stream is running.
    pub fn is_running(&self) -> bool {
        self.running
    }

    /// Underruns met by ramping (the hold policy's are counted by the tick).
    pub fn ramp_underruns(&self) -> u32 {
        self.ramp_underruns
    }

    /// The next setpoint (Q2.30), or `None` on an underrun under the hold policy.
    /// Bounded work: at most one queue pop and one multiply; no division.
    #[inline]
    pub fn next<const N: usize>(&mut self, queue: &mut Consumer<'_, i16, N>) -> Option<i32> {
        if let Some(w) = self.waveform.as_mut() {
            self.current = w.next_sample();
            return Some(self.current);
        }
        if !self.running {
            return Some(self.current);
        }
        if self.remaining == 0 {
            match queue.dequeue() {
                Some(sample) => {
                    self.target = setpoint_from_wire(sample);
                    self.remaining = self.divider;
                    let span = self.target as i64 - self.current as i64;
                    // |span| < 2^32 and the reciprocal ≤ 2^31: the product fits u64, and the
                    // step (at most |span| / 2) fits i32. Both the reciprocal and the product
                    // round toward zero, so |step| ≤ |span| / D: D − 1 steps never pass the
                    // target, and the last tick lands on it exactly.
                    let magnitude = ((span.unsigned_abs() * self.reciprocal) >> 32) as i32;
                    self.increment = if span < 0 { -magnitude } else { magnitude };
                }
                None if self.finishing => {
                    // The last setpoint has been played: the stream ends where it is.
                    self.stop();
                    return Some(self.current);
                }
                None => return self.underrun(),
            }
        }
        self.remaining = self.remaining.saturating_sub(1);
        self.current = if self.remaining == 0 {
            self.target
        } else {
            self.current.saturating_add(self.increment)
        };
        Some(self.current)
    }

    fn underrun(&mut self) -> Option<i32> {
        match self.underrun {
            Underrun::Hold => None,
            Underrun::RampToRest { rest, step } => {
                self.ramp_underruns = self.ramp_underruns.wrapping_add(1);
                let d = (rest as i64 - self.current as i64)
                    .max(-(step as i64))
                    .min(step as i64);
                self.current = (self.current as i64 + d) as i32;
                self.target = self.current;
                Some(self.current)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use heapless::spsc::Queue;
    use std::vec::Vec;

    #[test]
    fn a_slow_stream_is_interpolated_linearly_and_lands_on_each_sample() {
        let mut q: Queue<i16, 8> = Queue::new();
        let (mut p, mut c) = q.split();
        p.enqueue(1000).unwrap();
        p.enqueue(-2000).unwrap();
        let mut s = SetpointStream::new(0);
        s.set_divider(4);
        s.start();
        let out: [Option<i32>; 8] = core::array::from_fn(|_| s.next(&mut c));
        let want = |x: i32| Some(x << 15);
        assert_eq!(out[3], want(1000));
        assert_eq!(out[7], want(-2000));
        assert_eq!(out[1], Some((1000 << 15) / 4 * 2));
        // Then the queue is dry: hold policy → None.
        assert_eq!(s.next(&mut c), None);
    }

    #[test]
    fn ramp_to_rest_walks_at_the_given_rate_and_counts() {
        let mut q: Queue<i16, 4> = Queue::new();
        let (_p, mut c) = q.split();
        let mut s = SetpointStream::new(1 << 29);
        s.start();
        assert!(s.set_underrun(Underrun::RampToRest {
            rest: 0,
            step: 1 << 27
        }));
        let v: [i32; 5] = core::array::from_fn(|_| s.next(&mut c).unwrap());
        assert_eq!(v, [3 << 27, 2 << 27, 1 << 27, 0, 0]);
        assert_eq!(s.ramp_underruns(), 5);
        assert!(!s.set_underrun(Underrun::RampToRest { rest: 0, step: 0 }));
    }

    #[test]
    fn a_stopped_stream_holds_and_leaves_the_queue_alone() {
        let mut q: Queue<i16, 4> = Queue::new();
        let (mut p, mut c) = q.split();
        p.enqueue(5).unwrap();
        let mut s = SetpointStream::new(7);
        assert_eq!(s.next(&mut c), Some(7));
        assert_eq!(c.len(), 1);
        assert!(!s.set_divider(0));
    }

    #[test]
    fn a_finishing_stream_plays_the_queue_then_stops_without_underruns() {
        let mut q: Queue<i16, 4> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut s = SetpointStream::new(0);
        s.start();
        p.enqueue(3).unwrap();
        p.enqueue(4).unwrap();
        s.finish();
        assert!(s.is_finishing());
        assert_eq!(s.next(&mut c), Some(setpoint_from_wire(3)));
        assert_eq!(s.next(&mut c), Some(setpoint_from_wire(4)));
        // Dry: stopped, holding the last setpoint; never `None` (an underrun).
        for _ in 0..3 {
            assert_eq!(s.next(&mut c), Some(setpoint_from_wire(4)));
        }
        assert!(!s.is_running() && !s.is_finishing());
        // A stream started again counts underruns as before.
        s.start();
        assert_eq!(s.next(&mut c), None);
        // Finish before the start: it holds for the stream that start begins.
        s.stop();
        p.enqueue(5).unwrap();
        s.finish();
        s.start();
        assert_eq!(s.next(&mut c), Some(setpoint_from_wire(5)));
        assert_eq!(s.next(&mut c), Some(setpoint_from_wire(5)));
        assert!(!s.is_running());
        // Stop cancels it.
        s.finish();
        s.stop();
        s.start();
        assert_eq!(s.next(&mut c), None);
    }

    #[test]
    fn wire_format_round_trips() {
        for x in [i16::MIN, -1, 0, 1, 12345, i16::MAX] {
            assert_eq!(setpoint_to_wire(setpoint_from_wire(x)), x);
        }
        assert_eq!(setpoint_to_wire(i32::MAX), i16::MAX);
    }

    #[test]
    fn a_segment_whose_rounded_step_would_pass_the_target_does_not() {
        // 2 wire LSB (65 536 Q2.30 LSB) in 722 ticks: a step rounded to nearest (91) would,
        // 721 times, pass the target by 75. Rounded toward zero each step is 90, the last 106.
        let mut q: Queue<i16, 4> = Queue::new();
        let (mut p, mut c) = q.split();
        let mut s = SetpointStream::new(setpoint_from_wire(6883));
        assert!(s.set_divider(722));
        s.start();
        p.enqueue(6881).unwrap();
        let path: Vec<i32> = (0..722).filter_map(|_| s.next(&mut c)).collect();
        let to = setpoint_from_wire(6881);
        assert!(path.windows(2).all(|w| w[1] <= w[0]), "monotone");
        assert!(path.iter().all(|&x| x >= to), "never below the target");
        assert_eq!(path.last(), Some(&to));
    }

    proptest::proptest! {
        /// With any divider, a segment moves in steps no larger than `span / D` and less than
        /// two Q2.30 LSB short of it (a sixteen-thousandth of a wire LSB), never overshoots,
        /// and lands exactly on the sample after `D` ticks.
        #[test]
        fn interpolation_lands_exactly_in_near_equal_steps(
            divider in 1u16..=2000, a: i16, b: i16,
        ) {
            let mut q: Queue<i16, 4> = Queue::new();
            let (mut p, mut c) = q.split();
            let mut s = SetpointStream::new(setpoint_from_wire(a));
            proptest::prop_assert!(s.set_divider(divider));
            s.start();
            p.enqueue(b).unwrap();
            let (from, to) = (setpoint_from_wire(a) as i64, setpoint_from_wire(b) as i64);
            let ideal = (to - from) as f64 / divider as f64;
            let mut last = from;
            for k in 1..=divider as i64 {
                let now = s.next(&mut c).unwrap() as i64;
                if k < divider as i64 {
                    let step = (now - last) as f64;
                    proptest::prop_assert!(step.abs() <= ideal.abs(), "{step} vs {ideal}");
                    proptest::prop_assert!((step - ideal).abs() < 2.0, "{step} vs {ideal}");
                    proptest::prop_assert!((now - from).abs() <= (to - from).abs());
                } else {
                    proptest::prop_assert_eq!(now, to);
                }
                last = now;
            }
        }
    }
}
