//! The built-in waveform generator: sine or triangle, with offset, amplitude and frequency, in
//! fixed point. The identification runs of the first paper (750 Hz, 70 ± 70 V) come from here.
//!
//! **Decay** ([`WaveformGenerator::with_decay`]): the amplitude may shrink by a constant factor
//! per cycle after a number of full-amplitude cycles — full-range cycles, then nested minor
//! loops about the offset, the excitation `twinstack calibrate` identifies a stage from. The
//! factor is Q0.16 (`keep / 65536`, below 1 by construction) and is applied where the phase
//! wraps, i.e. where both shapes cross the offset, so the output stays continuous. Integer
//! arithmetic only (one multiply and shift per cycle), so the board and the host generate the
//! same samples bit for bit.
//!
//! Phase is a `u32` accumulator (2^32 = one cycle) advanced by `f / f_ctrl · 2^32` per tick, so
//! the frequency error is below `f_ctrl / 2^32` (12 µHz at 50 kHz) and the phase never drifts.
//! The sine comes from a quarter-wave table of 256 segments, interpolated linearly (error
//! below 5e-6 of the amplitude, a sixth of a 16-bit LSB); the table ([`unit_sine`]) is
//! computed at compile time, one for every generator and scan pattern.

use crate::fixed_point::{saturate_i64, SIGNAL_ONE};

/// Segments in the quarter-wave sine table.
const QUARTER: usize = 256;

/// Wave shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Shape {
    /// Sine.
    Sine,
    /// Symmetric triangle, starting at the offset and rising.
    Triangle,
}

/// Why a waveform was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WaveformError {
    /// Frequency zero, negative, or at or above half the control rate.
    FrequencyOutOfRange,
    /// Offset ± amplitude leaves the normalised range [-1, 1].
    AmplitudeOutOfRange,
}

/// `sin x` for `x` in [0, π/2], by its Taylor series to x^19 (error below 1e-13 there), in
/// IEEE arithmetic alone, so the compiler evaluates it (for [`SINE_TABLE`]) bit for bit as
/// the board and the host would.
const fn quarter_sine(x: f64) -> f64 {
    let x2 = x * x;
    // Horner over the odd terms, from x^19/19! down.
    let mut term = 1.0;
    let mut k = 19.0;
    while k > 1.0 {
        term = 1.0 - x2 / (k * (k - 1.0)) * term;
        k -= 2.0;
    }
    x * term
}

/// `sin(i · π/2 / 256)`, Q2.30, `i = 0 ..= 256`: the quarter-wave table of [`unit_sine`],
/// computed at compile time. One table for every waveform and scan pattern, so a generator
/// carries no 1 KiB copy of its own to be moved under the tick's lock when it starts (that
/// would hold the tick off for about 1 000 instructions). On the board it is in RAM (`.data`, copied from flash
/// at reset), so the tick reads it without flash wait states.
// A section name only: cortex-m-rt's `.data`, which its reset handler copies from flash.
#[cfg_attr(target_os = "none", allow(unsafe_code), link_section = ".data")]
static SINE_TABLE: [i32; QUARTER + 1] = {
    let mut table = [0i32; QUARTER + 1];
    let mut i = 0;
    while i <= QUARTER {
        let x = i as f64 * core::f64::consts::FRAC_PI_2 / QUARTER as f64;
        table[i] = crate::fixed_point::signal_from_f64(quarter_sine(x));
        i += 1;
    }
    table
};

/// The unit sine (Q2.30, ±1) at `phase` (2^32 per cycle): the quarter-wave sine table
/// (computed at compile time) interpolated linearly (22 fractional bits) by quadrant. O(1),
/// no division, no panic path.
///
/// ```
/// use twinstack::fixed_point::signal_to_f64 as f;
/// use twinstack::sources::waveform::unit_sine;
/// assert_eq!(f(unit_sine(1 << 30)), 1.0);
/// assert!((f(unit_sine(0x2AAA_AAAB)) - 0.866_025_4).abs() < 5e-6); // 60°
/// ```
#[inline(always)]
pub fn unit_sine(phase: u32) -> i32 {
    let quadrant = phase >> 30;
    let within = phase & 0x3FFF_FFFF; // position in the quadrant, 2^30 per quadrant
    let pos = if quadrant & 1 == 0 {
        within
    } else {
        0x4000_0000 - within
    };
    let index = (pos >> 22) as usize; // 256 segments
    let frac = (pos & 0x3F_FFFF) as i64; // 22 fractional bits
    let a = SINE_TABLE.get(index).copied().unwrap_or(SIGNAL_ONE) as i64;
    let b = SINE_TABLE.get(index + 1).copied().unwrap_or(SIGNAL_ONE) as i64;
    let v = a + (((b - a) * frac) >> 22);
    if quadrant >= 2 {
        -(v as i32)
    } else {
        v as i32
    }
}

/// A configured generator and its phase.
#[derive(Clone, Debug)]
pub struct WaveformGenerator {
    shape: Shape,
    /// Offset, Q2.30 normalised displacement.
    offset: i32,
    /// Amplitude, Q2.30 normalised displacement.
    amplitude: i32,
    /// Phase increment per tick, 2^32 per cycle.
    step: u32,
    /// Phase, 2^32 per cycle.
    phase: u32,
    /// Amplitude kept per cycle once decaying, Q0.16 (65 536: no decay).
    keep: u32,
    /// Cycles still to play at full amplitude before each wrap decays it (see
    /// [`WaveformGenerator::with_decay`]).
    hold: u16,
}

impl WaveformGenerator {
    /// A generator for `shape` at `frequency_hz` with `offset` and `amplitude` (Q2.30
    /// normalised), ticking at `control_rate_hz`.
    pub fn new(
        shape: Shape,
        offset: i32,
        amplitude: i32,
        frequency_hz: f64,
        control_rate_hz: f64,
    ) -> Result<Self, WaveformError> {
        if !(frequency_hz > 0.0 && control_rate_hz > 0.0 && frequency_hz < 0.5 * control_rate_hz) {
            return Err(WaveformError::FrequencyOutOfRange);
        }
        let reach_hi = offset as i64 + (amplitude as i64).abs();
        let reach_lo = offset as i64 - (amplitude as i64).abs();
        if reach_hi > SIGNAL_ONE as i64 || reach_lo < -(SIGNAL_ONE as i64) {
            return Err(WaveformError::AmplitudeOutOfRange);
        }
        let step = libm::round(frequency_hz / control_rate_hz * 4_294_967_296.0) as u32;
        Ok(Self {
            shape,
            offset,
            amplitude,
            step,
            phase: 0,
            keep: 1 << 16,
            hold: 0,
        })
    }

    /// The same generator with a decaying amplitude: the first `hold_cycles` cycles (at least
    /// one) at the full amplitude, then each cycle's amplitude is the previous one's ×
    /// `keep / 65536` (Q0.16, so always below 1: the amplitude of cycle `n` is
    /// `A · (keep/65536)^max(0, n + 1 − hold_cycles)`, rounded down once per cycle). Applied
    /// where the phase wraps, where the output crosses the offset.
    ///
    /// ```
    /// use twinstack::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};
    /// use twinstack::sources::waveform::{Shape, WaveformGenerator};
    /// // 1 kHz at 4 kHz: four samples a cycle; two full cycles, then halved each cycle.
    /// let mut g = WaveformGenerator::new(Shape::Triangle, 0, q(0.5), 1000.0, 4000.0)
    ///     .unwrap()
    ///     .with_decay(2, 32768);
    /// let peaks: Vec<f64> = (0..16).map(|_| f(g.next_sample())).skip(1).step_by(4).collect();
    /// assert_eq!(peaks, [0.5, 0.5, 0.25, 0.125]);
    /// ```
    pub fn with_decay(mut self, hold_cycles: u16, keep: u16) -> Self {
        self.keep = keep as u32;
        self.hold = hold_cycles;
        self
    }

    /// The amplitude in force (Q2.30), after the decay so far.
    pub fn amplitude(&self) -> i32 {
        self.amplitude
    }

    /// The unit waveform (Q2.30, ±1) at `phase`.
    #[inline(always)]
    fn unit(&self, phase: u32) -> i32 {
        match self.shape {
            Shape::Sine => unit_sine(phase),
            Shape::Triangle => {
                // 0 → 1 over the first quarter, 1 → −1 over the middle half, −1 → 0 last.
                let p = phase as i64;
                let q = 1i64 << 30;
                let v = if p < q {
                    p
                } else if p < 3 * q {
                    2 * q - p
                } else {
                    p - 4 * q
                };
                v as i32
            }
        }
    }

    /// The next sample (Q2.30 normalised displacement); advances the phase by one tick.
    ///
    /// Not inlined: the tick calls it only while the generator plays, and inlined its cycle
    /// bookkeeping cost the tick's other paths registers (the whole-interrupt bench's worst
    /// tick, which never plays a waveform, went from 980 to 1 002 instructions).
    #[inline(never)]
    pub fn next_sample(&mut self) -> i32 {
        let unit = self.unit(self.phase);
        let sample =
            saturate_i64(self.offset as i64 + ((self.amplitude as i64 * unit as i64) >> 30));
        let (phase, wrapped) = self.phase.overflowing_add(self.step);
        self.phase = phase;
        if wrapped {
            // A cycle ended: one multiply and shift (a no-op without decay, keep = 2^16).
            self.hold = self.hold.saturating_sub(1);
            if self.hold == 0 {
                self.amplitude = ((self.amplitude as i64 * self.keep as i64) >> 16) as i32;
            }
        }
        sample
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};

    #[test]
    fn sine_matches_libm_within_a_sixth_of_a_16_bit_lsb() {
        let mut g = WaveformGenerator::new(Shape::Sine, q(0.1), q(0.8), 750.0, 50_000.0).unwrap();
        let step = g.step;
        let mut worst: f64 = 0.0;
        for k in 0..20_000u32 {
            // The accumulator's own phase: this checks the table and interpolation.
            let phase = k.wrapping_mul(step) as f64 / 4_294_967_296.0;
            let want = 0.1 + 0.8 * libm::sin(core::f64::consts::TAU * phase);
            worst = worst.max((f(g.next_sample()) - want).abs());
        }
        assert!(worst < (2.0 / 65536.0) / 6.0, "worst {worst}");
        // And the frequency the accumulator realises is within f_ctrl / 2^32 of the request.
        let realised = step as f64 / 4_294_967_296.0 * 50_000.0;
        assert!((realised - 750.0).abs() <= 50_000.0 / 4_294_967_296.0);
    }

    #[test]
    fn the_compile_time_table_is_the_one_computed_at_run_time() {
        // The compiler's IEEE arithmetic is the board's and the host's: the table is the one
        // computed at run time, bit for bit (the golden vectors hold it).
        let x = core::hint::black_box(core::f64::consts::FRAC_PI_2 / QUARTER as f64);
        for (i, &t) in SINE_TABLE.iter().enumerate() {
            let run = crate::fixed_point::signal_from_f64(quarter_sine(i as f64 * x));
            assert_eq!(t, run, "entry {i}");
        }
        assert_eq!((SINE_TABLE[0], SINE_TABLE[QUARTER]), (0, SIGNAL_ONE));
    }

    #[test]
    fn the_table_sine_matches_libm_over_the_quarter_wave() {
        for i in 0..=1000 {
            let x = i as f64 * core::f64::consts::FRAC_PI_2 / 1000.0;
            assert!((quarter_sine(x) - libm::sin(x)).abs() < 1e-13, "x = {x}");
        }
    }

    #[test]
    fn triangle_reaches_its_peaks_and_is_linear() {
        let mut g = WaveformGenerator::new(Shape::Triangle, 0, q(0.5), 100.0, 40_000.0).unwrap();
        let s: [f64; 400] = core::array::from_fn(|_| f(g.next_sample()));
        assert!((s[100] - 0.5).abs() < 1e-6 && (s[300] + 0.5).abs() < 1e-6);
        assert!((s[50] - 0.25).abs() < 1e-6 && (s[200]).abs() < 1e-6);
    }

    #[test]
    fn the_decay_shrinks_each_cycle_after_the_held_ones_as_the_f64_law_says() {
        // 10 Hz at 1 kHz: 100 samples a cycle; 3 full cycles, then 0.8 kept per cycle.
        let keep = (0.8f64 * 65536.0).round() as u16;
        let mut g = WaveformGenerator::new(Shape::Sine, q(0.05), q(0.9), 10.0, 1000.0)
            .unwrap()
            .with_decay(3, keep);
        for cycle in 0..12i32 {
            let s: [f64; 100] = core::array::from_fn(|_| f(g.next_sample()));
            let peak = s.iter().copied().fold(f64::MIN, f64::max) - 0.05;
            let want = 0.9 * (keep as f64 / 65536.0).powi((cycle - 2).max(0));
            // One rounding down per cycle (2^-30 each) and the table's interpolation.
            assert!(
                (peak - want).abs() < 1e-6,
                "cycle {cycle}: {peak} vs {want}"
            );
            // Each cycle starts at the offset (the amplitude changes there).
            assert!(
                (s[0] - 0.05).abs() < 1e-6,
                "cycle {cycle} starts at {}",
                s[0]
            );
        }
        // Without decay the amplitude never changes, over many cycles.
        let mut g = WaveformGenerator::new(Shape::Triangle, 0, q(0.5), 10.0, 1000.0).unwrap();
        for _ in 0..10_000 {
            g.next_sample();
        }
        assert_eq!(g.amplitude(), q(0.5));
        // A keep of 0: silent after the held cycle, at the offset.
        let mut g = WaveformGenerator::new(Shape::Sine, q(0.1), q(0.5), 10.0, 1000.0)
            .unwrap()
            .with_decay(1, 0);
        let s: [f64; 300] = core::array::from_fn(|_| f(g.next_sample()));
        assert!(s[..100].iter().any(|&v| v > 0.5));
        assert!(s[100..].iter().all(|&v| (v - 0.1).abs() < 1e-9));
    }

    #[test]
    fn refuses_out_of_range_settings() {
        assert_eq!(
            WaveformGenerator::new(Shape::Sine, 0, q(0.5), 30_000.0, 50_000.0).err(),
            Some(WaveformError::FrequencyOutOfRange)
        );
        assert_eq!(
            WaveformGenerator::new(Shape::Sine, q(0.6), q(0.5), 10.0, 50_000.0).err(),
            Some(WaveformError::AmplitudeOutOfRange)
        );
        assert_eq!(
            WaveformGenerator::new(Shape::Sine, 0, q(0.5), f64::NAN, 50_000.0).err(),
            Some(WaveformError::FrequencyOutOfRange)
        );
    }
}
