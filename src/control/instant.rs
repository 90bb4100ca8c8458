//! The instants a tick's values belong to, and the one rule that relates them.
//!
//! The DAC holds each tick's drive for a period, and a held drive acts on the stage as at the
//! **middle of its hold**: a setpoint is the displacement wanted there, the compensator aims
//! the drive at it, and a model (`identify` fits it so, with half a sample of lag) maps the
//! drive to the stage there. The sensor samples at the **holds' ends**, between two such
//! middles. What a reading is compared with — by the feedback ([`crate::control::feedback`]),
//! the learning's stored error ([`crate::services::learning`]) and the drift check
//! ([`crate::services::observer`]) — is the value at the reading's instant, interpolated from
//! the four middles around it ([`between_holds`]), and the host's studies score the stage
//! by the same rule.
//!
//! The interpolation is a cubic: midway, `(9·(b + c) − (a + d)) / 16`, exact for any cubic
//! through the four. The mean of the two neighbours alone would be off by an eighth of the
//! curvature over a period (`T²·ẍ/8`): 0.1 % of a 750 Hz sine's amplitude at 50 kHz, the size
//! of what the learning is there to remove.

/// The value midway between `b` and `c` of four consecutive ticks' values `a, b, c, d`
/// (oldest first, Q2.30): the cubic through the four, `m + (m − o)/8` with `m` the mean of
/// `b` and `c` and `o` that of `a` and `d` (each `⌊(x + y)/2⌋`, exact without overflow; the
/// difference saturating, the eighth rounded toward −∞). All in 32-bit integers: the same on
/// the host and the board, and a dozen instructions on the tick.
///
/// ```
/// use twinstack::control::instant::between_holds;
/// // Along a line, the midpoint; on a parabola too (k² at k = 1.5 is 2.25).
/// assert_eq!(between_holds([0, 16, 32, 48]), 24);
/// assert_eq!(between_holds([0, 16, 64, 144]), 36);
/// // Full scale saturates, never wraps.
/// assert_eq!(between_holds([i32::MIN, i32::MAX, i32::MAX, i32::MIN]), i32::MAX);
/// ```
#[inline(always)]
pub fn between_holds([a, b, c, d]: [i32; 4]) -> i32 {
    let m = mean(b, c);
    let o = mean(a, d);
    m.saturating_add(m.saturating_sub(o) >> 3)
}

/// `⌊(x + y)/2⌋`, exact and without overflow.
#[inline(always)]
fn mean(x: i32, y: i32) -> i32 {
    (x >> 1) + (y >> 1) + (x & y & 1)
}

/// The last ticks' values (setpoints, or the observer's estimates), each of the middle of its
/// drive's hold, and from them the value at the present reading's instant: the end of the hold
/// of the drive of [`SENSOR_DELAY_TICKS`](crate::control::feedback::SENSOR_DELAY_TICKS)
/// ticks ago ([`between_holds`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReadingInstant {
    /// The last three values, newest first, Q2.30: `values[i]` is of `i + 1` ticks ago
    /// (before a push; the present tick's once pushed, with the oldest dropped).
    values: [i32; 3],
}

impl ReadingInstant {
    /// A history that has held `value` (Q2.30) for ever.
    ///
    /// ```
    /// use twinstack::control::instant::ReadingInstant;
    /// let mut h = ReadingInstant::at(5);
    /// assert_eq!(h.push(5), 5);
    /// ```
    pub const fn at(value: i32) -> Self {
        Self { values: [value; 3] }
    }

    /// The newest value (the present tick's, once pushed).
    #[inline(always)]
    pub fn newest(&self) -> i32 {
        self.values[0]
    }

    /// Puts this tick's `value` into the history and returns the value at the instant of the
    /// present reading (between the middles of the holds of two ticks and one tick ago,
    /// [`SENSOR_DELAY_TICKS`](crate::control::feedback::SENSOR_DELAY_TICKS), from the values of
    /// three ticks ago to the present one).
    /// Constant time: four moves and the cubic, no call.
    #[inline(always)]
    pub fn push(&mut self, value: i32) -> i32 {
        let [one, two, three] = self.values;
        self.values = [value, one, two];
        between_holds([three, two, one, value])
    }
}

impl Default for ReadingInstant {
    /// At 0.
    fn default() -> Self {
        Self::at(0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::control::feedback::SENSOR_DELAY_TICKS;
    use crate::fixed_point::{signal_from_f64, signal_to_f64};

    #[test]
    fn a_cubic_is_interpolated_exactly_and_a_sine_within_its_fourth_order() {
        // x(t) = t³ − t: the value midway is the cubic's own.
        let x = |t: f64| signal_from_f64(0.1 * (t * t * t - t));
        for k in -5..5 {
            let t = k as f64 * 0.25;
            let got = between_holds([x(t), x(t + 0.25), x(t + 0.5), x(t + 0.75)]);
            let want = x(t + 0.375);
            assert!((got - want).abs() <= 2, "{k}: {got} vs {want}");
        }
        // A 750 Hz sine at 50 kHz: the mean of the neighbours is off by T²ẍ/8 (0.1 % of the
        // amplitude), the cubic by 3(ωT)⁴/128 (2 parts in a million).
        let w = 2.0 * core::f64::consts::PI * 750.0 / 50_000.0;
        let s = |k: f64| signal_from_f64(0.9 * (w * k).sin());
        let (mut cubic, mut mean) = (0.0f64, 0.0f64);
        for k in 0..200 {
            let k = k as f64;
            let truth = 0.9 * (w * (k + 1.5)).sin();
            let got = between_holds([s(k), s(k + 1.0), s(k + 2.0), s(k + 3.0)]);
            cubic = cubic.max((signal_to_f64(got) - truth).abs());
            mean = mean.max(
                (0.5 * (0.9 * (w * (k + 1.0)).sin() + 0.9 * (w * (k + 2.0)).sin()) - truth).abs(),
            );
        }
        assert!(cubic < 2e-6, "{cubic}");
        assert!(mean > 9e-4, "{mean}");
    }

    #[test]
    fn the_reading_meets_the_value_between_the_holds_of_the_delay() {
        // A ramp: tick k's value is 1000 k; the reading of tick k is of the end of the hold of
        // tick k − SENSOR_DELAY_TICKS, half a tick after its middle.
        let mut h = ReadingInstant::at(0);
        let d = SENSOR_DELAY_TICKS as i32;
        for k in 0..20i32 {
            let got = h.push(1000 * k);
            if k > d {
                assert_eq!(got, 1000 * (k - d) + 500, "tick {k}");
            }
        }
    }
}
