//! The coarse stage's axis logic, independent of any register: quadrature decoding and counter
//! extension for its encoders, the step generator (with backlash take-up) for its step/dir
//! motor driver, and the timer values of a step burst.
//!
//! Units: motor positions in **microsteps** (`i64`, one STEP pulse each), encoder positions in
//! **counts** (`i64`, one quadrature edge each). Integers throughout: a count or a step is
//! exact, and an `i64` never wraps on any travel (2^63 steps).
//!
//! * [`QuadratureDecoder`] — the ×4 state machine of a timer in encoder mode (used by the
//!   simulator's emulated encoders; the firmware's timers do this in hardware).
//! * [`EncoderCounter`] — extends the timer's wrapping 16-bit counter to an `i64` position.
//! * [`StepGenerator`] — turns a commanded motor position into bursts of at most
//!   `max_steps_per_burst` pulses, keeps what it could not send for the next burst, and adds
//!   the backlash take-up when the direction reverses.
//! * [`StepTiming`] — prescaler, period and pulse width of a burst on a timer with a repetition
//!   counter (TIM1 on the board: one-pulse mode, `RCR = steps − 1`); [`BurstTiming`] prepares
//!   what does not change from burst to burst.

use crate::board::{StepBurst, StepDirection};

/// Counts the edges of a quadrature signal pair (A, B) the way an STM32 timer in encoder mode 3
/// does: every edge of either line counts ±1, the sign from the other line's level. A change
/// of both lines at once (an edge missed) is not counted but recorded.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct QuadratureDecoder {
    state: u8,
    count: i64,
    missed: u32,
}

/// Gray-code position (0…3) of the line levels: 00 → 0, 01 (B) → 3, 11 → 2, 10 (A) → 1,
/// so that forward motion (A leads B) counts up.
fn gray_phase(a: bool, b: bool) -> u8 {
    match (a, b) {
        (false, false) => 0,
        (true, false) => 1,
        (true, true) => 2,
        (false, true) => 3,
    }
}

impl QuadratureDecoder {
    /// A decoder whose lines rest at `(a, b)`, count 0.
    pub fn new(a: bool, b: bool) -> Self {
        Self {
            state: gray_phase(a, b),
            count: 0,
            missed: 0,
        }
    }

    /// The line levels of quadrature position `count` (A leads B when counting up).
    pub fn lines_at(count: i64) -> (bool, bool) {
        match count.rem_euclid(4) {
            0 => (false, false),
            1 => (true, false),
            2 => (true, true),
            _ => (false, true),
        }
    }

    /// New line levels; returns the count.
    pub fn update(&mut self, a: bool, b: bool) -> i64 {
        let next = gray_phase(a, b);
        match next.wrapping_sub(self.state) & 3 {
            0 => {}
            1 => self.count += 1,
            3 => self.count -= 1,
            _ => self.missed = self.missed.wrapping_add(1),
        }
        self.state = next;
        self.count
    }

    /// Edges counted (signed).
    pub fn count(&self) -> i64 {
        self.count
    }

    /// The timer's 16-bit counter register: the count modulo 2^16.
    pub fn counter_register(&self) -> u16 {
        self.count as u16
    }

    /// Transitions where both lines changed at once (an edge was missed).
    pub fn missed(&self) -> u32 {
        self.missed
    }
}

/// Extends a wrapping 16-bit encoder counter to an `i64` position. Correct as long as the
/// counter moves less than 32768 counts between two reads (the coarse loop reads it every
/// millisecond: 32 M counts/s).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EncoderCounter {
    last: u16,
    position: i64,
}

impl EncoderCounter {
    /// Starts at position 0 with the counter reading `raw`.
    pub fn new(raw: u16) -> Self {
        Self {
            last: raw,
            position: 0,
        }
    }

    /// Takes a new reading; returns the extended position, counts.
    pub fn update(&mut self, raw: u16) -> i64 {
        let delta = raw.wrapping_sub(self.last) as i16;
        self.last = raw;
        self.position = self.position.saturating_add(delta as i64);
        self.position
    }

    /// The extended position, counts.
    pub fn position(&self) -> i64 {
        self.position
    }
}

/// Turns commanded motor positions into step bursts.
///
/// The motor position sent so far (`issued`, microsteps) follows the command plus a backlash
/// take-up: moving forward the motor leads the carriage command by `+backlash/2` steps, moving
/// in reverse by `−backlash/2`, so a reversal adds `backlash` steps in the new direction and the
/// nut crosses its gap without the carriage command waiting for it. Steps a burst cannot hold
/// stay owed to the next one: none is lost.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StepGenerator {
    issued: i64,
    backlash_steps: i64,
    take_up: i64,
    max_steps: u16,
}

impl StepGenerator {
    /// Motor at `position` (microsteps), backlash take-up `backlash_steps` (0: none), bursts of
    /// at most `max_steps` pulses (at least 1).
    pub fn new(position: i64, backlash_steps: u16, max_steps: u16) -> Self {
        Self {
            issued: position,
            backlash_steps: backlash_steps as i64,
            take_up: 0,
            max_steps: max_steps.max(1),
        }
    }

    /// The burst that moves the motor toward carriage command `command` (microsteps), or `None`
    /// when it is there. The burst is not yet issued: call [`StepGenerator::issued`] once the
    /// output accepted it.
    pub fn plan(&mut self, command: i64) -> Option<StepBurst> {
        let mut delta = command
            .saturating_add(self.take_up)
            .saturating_sub(self.issued);
        // Reversal of travel: the take-up switches sides, which only adds to the steps owed
        // in the new direction (so the sign of `delta` does not change again).
        let take_up = match delta.signum() {
            1 => self.backlash_steps / 2,
            -1 => -(self.backlash_steps - self.backlash_steps / 2),
            _ => self.take_up,
        };
        if take_up != self.take_up {
            self.take_up = take_up;
            delta = command.saturating_add(take_up).saturating_sub(self.issued);
        }
        let steps = delta.unsigned_abs().min(self.max_steps as u64) as u16;
        if steps == 0 {
            return None;
        }
        Some(StepBurst {
            direction: if delta > 0 {
                StepDirection::Forward
            } else {
                StepDirection::Reverse
            },
            steps,
        })
    }

    /// Records that `burst` was emitted.
    pub fn issued(&mut self, burst: StepBurst) {
        let s = burst.steps as i64;
        self.issued = match burst.direction {
            StepDirection::Forward => self.issued.saturating_add(s),
            StepDirection::Reverse => self.issued.saturating_sub(s),
        };
    }

    /// Motor position issued so far, microsteps (including the backlash take-up).
    pub fn motor_position(&self) -> i64 {
        self.issued
    }

    /// The carriage position the issued steps stand for: motor position less the take-up.
    pub fn carriage_position(&self) -> i64 {
        self.issued - self.take_up
    }
}

/// Timer values of one step burst on a timer with a repetition counter, in one-pulse PWM mode:
/// the timer counts `period` ticks of `clock / (prescaler + 1)` per pulse, the output is high
/// for the first `pulse` ticks of each, and stops after `RCR + 1 = steps` periods.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StepTiming {
    /// PSC register: the timer counts at `clock / (prescaler + 1)`.
    pub prescaler: u16,
    /// Ticks per pulse (ARR + 1).
    pub period: u32,
    /// Ticks the STEP line is high (CCR), at least the driver's minimum pulse width.
    pub pulse: u32,
}

impl StepTiming {
    /// The prescaler that lets one pulse span a whole coarse period in 16 bits.
    pub fn prescaler_for(timer_clock_hz: u32, coarse_rate_hz: u32) -> u16 {
        let per_period = timer_clock_hz / coarse_rate_hz.max(1);
        (per_period.div_ceil(65_536).max(1) - 1).min(u16::MAX as u32) as u16
    }

    /// Timing of `steps` pulses (1 at least) spread evenly over one coarse period, each high
    /// for `min_pulse_ns` (or half the period, if shorter). The burst ends within the period.
    /// ([`BurstTiming::burst`], its timer prepared for this burst alone.)
    pub fn for_burst(
        timer_clock_hz: u32,
        coarse_rate_hz: u32,
        steps: u16,
        min_pulse_ns: u32,
    ) -> Self {
        BurstTiming::new(timer_clock_hz, coarse_rate_hz, min_pulse_ns).burst(steps)
    }
}

/// A step output's timing, prepared once for its timer's clock, the coarse rate and the
/// driver's shortest pulse (when the output is set up, off the coarse task): each burst then
/// costs one 32-bit division ([`BurstTiming::burst`]), where [`StepTiming::for_burst`] from
/// scratch takes four and a 64-bit product.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BurstTiming {
    /// PSC register ([`StepTiming::prescaler_for`]).
    prescaler: u16,
    /// Timer ticks in one coarse period, at the prescaled clock.
    per_period: u32,
    /// Ticks of the driver's shortest pulse, rounded up (at least 1).
    min_pulse: u32,
}

impl BurstTiming {
    /// The timing of a timer counting at `timer_clock_hz` (before its prescaler), bursts
    /// spread over a coarse period at `coarse_rate_hz`, each pulse high `min_pulse_ns` at
    /// least.
    ///
    /// ```
    /// use twinstack::dual_stage::coarse_axis::{BurstTiming, StepTiming};
    /// let timing = BurstTiming::new(168_000_000, 5_000, 2_000);
    /// // 10 steps over 200 µs: a pulse every 20 µs, high 2 µs.
    /// let t = timing.burst(10);
    /// assert_eq!(t, StepTiming::for_burst(168_000_000, 5_000, 10, 2_000));
    /// assert_eq!((t.period, t.pulse), (3_360, 336));
    /// ```
    pub fn new(timer_clock_hz: u32, coarse_rate_hz: u32, min_pulse_ns: u32) -> Self {
        let prescaler = StepTiming::prescaler_for(timer_clock_hz, coarse_rate_hz);
        let tick_hz = timer_clock_hz / (prescaler as u32 + 1);
        let min_pulse = (tick_hz as u64 * min_pulse_ns as u64).div_ceil(1_000_000_000);
        Self {
            prescaler,
            per_period: tick_hz / coarse_rate_hz.max(1),
            // A pulse of more than 2^32 ticks (seconds long) saturates.
            min_pulse: u32::try_from(min_pulse).unwrap_or(u32::MAX).max(1),
        }
    }

    /// The timing of `steps` pulses (1 at least) spread evenly over one coarse period, each
    /// high for the shortest pulse (or half the period, if shorter): one 32-bit division.
    #[inline]
    pub fn burst(&self, steps: u16) -> StepTiming {
        let period = (self.per_period / steps.max(1) as u32).clamp(2, 65_536);
        StepTiming {
            prescaler: self.prescaler,
            period,
            pulse: self.min_pulse.min(period / 2),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decoder_counts_every_edge_with_direction_and_flags_missed_edges() {
        let mut d = QuadratureDecoder::new(false, false);
        for c in 1..=10 {
            let (a, b) = QuadratureDecoder::lines_at(c);
            assert_eq!(d.update(a, b), c);
        }
        for c in (-5..10).rev() {
            let (a, b) = QuadratureDecoder::lines_at(c);
            assert_eq!(d.update(a, b), c);
        }
        assert_eq!(d.counter_register(), (-5i64) as u16);
        // Both lines at once: not counted, recorded.
        let (a, b) = QuadratureDecoder::lines_at(-3);
        assert_eq!(d.update(a, b), -5);
        assert_eq!(d.missed(), 1);
    }

    #[test]
    fn counter_extension_follows_wraps_both_ways() {
        let mut e = EncoderCounter::new(65_530);
        assert_eq!(e.update(4), 10);
        assert_eq!(e.update(65_000), 10 - 540);
        let mut raw = 65_000u16;
        let mut pos = e.position();
        for _ in 0..100 {
            raw = raw.wrapping_add(30_000);
            pos += 30_000;
            assert_eq!(e.update(raw), pos);
        }
    }

    #[test]
    fn step_generator_carries_what_a_burst_cannot_hold() {
        let mut g = StepGenerator::new(0, 0, 100);
        let mut bursts = 0;
        while let Some(b) = g.plan(250) {
            assert!(b.steps <= 100 && b.direction == StepDirection::Forward);
            g.issued(b);
            bursts += 1;
        }
        assert_eq!((g.motor_position(), bursts), (250, 3));
        // A refused burst (not issued) is planned again.
        let b = g.plan(200).unwrap();
        assert_eq!(b.direction, StepDirection::Reverse);
        assert_eq!(g.plan(200), Some(b));
    }

    #[test]
    fn reversal_adds_the_backlash_take_up() {
        let mut g = StepGenerator::new(0, 8, 1000);
        let run = |g: &mut StepGenerator, c| {
            while let Some(b) = g.plan(c) {
                g.issued(b);
            }
        };
        run(&mut g, 100);
        assert_eq!((g.motor_position(), g.carriage_position()), (104, 100));
        run(&mut g, 50);
        assert_eq!((g.motor_position(), g.carriage_position()), (46, 50));
        run(&mut g, 60);
        assert_eq!((g.motor_position(), g.carriage_position()), (64, 60));
    }

    /// Each burst's timing from the prepared timer is the one computed from scratch (every
    /// division done again, as the step output did per burst), for every burst length on
    /// boards' and odd clocks and rates.
    #[test]
    fn a_prepared_timing_gives_every_burst_the_timing_computed_from_scratch() {
        fn from_scratch(clock: u32, rate: u32, steps: u16, min_pulse_ns: u32) -> StepTiming {
            let prescaler = StepTiming::prescaler_for(clock, rate);
            let tick_hz = clock / (prescaler as u32 + 1);
            let per_period = tick_hz / rate.max(1);
            let period = (per_period / steps.max(1) as u32).clamp(2, 65_536);
            let pulse = (tick_hz as u64 * min_pulse_ns as u64).div_ceil(1_000_000_000) as u32;
            StepTiming {
                prescaler,
                period,
                pulse: pulse.max(1).min(period / 2),
            }
        }
        for clock in [168_000_000, 84_000_000, 16_000_000, 1_000_003] {
            for rate in [1, 999, 1_000, 5_000, 10_000, 100_000] {
                for min_pulse_ns in [0, 1, 2_000, 33_333] {
                    let timing = BurstTiming::new(clock, rate, min_pulse_ns);
                    for steps in 0..=256u16 {
                        assert_eq!(
                            timing.burst(steps),
                            from_scratch(clock, rate, steps, min_pulse_ns),
                            "{clock} Hz, {rate} Hz, {min_pulse_ns} ns, {steps} steps"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn burst_timing_fits_the_coarse_period_and_the_registers() {
        for steps in [1u16, 2, 7, 64, 255, 256] {
            let t = StepTiming::for_burst(168_000_000, 1000, steps, 2_000);
            let tick_hz = 168_000_000 / (t.prescaler as u32 + 1);
            assert!(t.period <= 65_536 && t.pulse >= 1 && t.pulse <= t.period / 2);
            assert!(
                steps as u64 * t.period as u64 * 1000 <= tick_hz as u64,
                "{steps}: {t:?}"
            );
            if t.period >= 2 * 112 {
                // 2 µs at 56 MHz = 112 ticks
                assert!(t.pulse as u64 * 1_000_000_000 >= 2_000 * tick_hz as u64);
            }
        }
    }
}
