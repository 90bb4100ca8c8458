//! The drive an identification is recorded on: one record that shows a model every kind of
//! motion its compensator will be asked for. `twinstack calibrate` streams it to the board (in
//! bypass, so that the setpoint *is* the drive) and the laboratory stage's study plays it, so
//! both identify from the same excitation.
//!
//! Up to five parts follow each other without a jump, each a whole number of cycles of the
//! base frequency `hz` ([`Excitation`]):
//!
//! 1. **full cycles**: `−cos 2πft` over the whole swept range, from its bottom (where a stage
//!    at rest at 0 V already is): the major loop;
//! 2. **decaying cycles**: the same sine about the middle, its amplitude decaying geometrically
//!    to [`Excitation::final_amplitude`]: concentric minor loops;
//! 3. **nested loops**: straight sweeps at one speed between the reversal points of
//!    [`REVERSALS`], off the middle, each inside the last and then out again: minor loops
//!    that do not share a centre, and first-order reversal curves from both branches — what
//!    separates models that fit the concentric loops alike;
//! 4. **sweep** (where the user names the fastest motion they will run,
//!    [`Excitation::reaching`]): a sine about the middle whose frequency rises geometrically
//!    from `hz` to that motion's ([`Excitation::sweep_to_hz`]), its amplitude
//!    ([`SWEEP_AMPLITUDE`]) under a half-sine window, so that it starts and ends at the middle
//!    with no jump: minor loops at every speed between the base and the fastest, so that the
//!    creep the fit finds is the one fast motion shows, not only the slow one;
//! 5. **multisine**: three tones at `hz/5`, `hz/2` and `1.3·hz` ([`TONES`]), so that the
//!    reversals come at irregular points and at the speeds of a user's fastest motion.
//!
//! The last cycle (the multisine's) is what `calibrate` and `identify` hold out of the fit
//! ([`Excitation::held_out_from_s`]); `auto` ranks its candidates on the last part of the rest
//! ([`crate::identification::auto`]).
//!
//! [`Excitation::DEFAULT`] plays all but the sweep (4 full cycles, 6 decaying to 30 %, 5 of
//! nested loops, 5 of multisine: 2 s at 10 Hz), so that `auto` ranks its candidates on the nested
//! loops and the multisine rather than on the smallest concentric loops, where every
//! candidate is about equally wrong. [`Excitation::DECAYING`] is the first two parts alone
//! (6 full cycles, 14 decaying to 15 %: the major loop, then concentric loops), the
//! excitation before the nested loops were added (`calibrate --full-cycles 6 --decay-cycles 14
//! --final-amplitude 0.15 --loop-cycles 0 --multisine-cycles 0`). On the simulated lab
//! stages (`twinstack lab-stage --variants`, with and without `--hysteresis bouc-wen`),
//! identified from the default, `auto`'s pick tracks within 1 % on 19 of the Preisach stage's
//! 21 variants (17 from the decaying one) and better on every Bouc–Wen-class variant; the
//! Duhem and Bouc–Wen compensators that the nested loops rank first there hold that only
//! because they start at rest on their loop, as the stage rests (`twinstack::models::Rest`).

use std::f64::consts::TAU;

/// The reversal points of the nested loops (normalised about the middle, `−1 … 1`), after the
/// decaying cycles' last bottom: from the top, loops each inside the last (about `0`, then
/// off it), out to near the bottom, and in again; the sweep ends at the middle, where the
/// multisine starts.
pub const REVERSALS: [f64; 18] = [
    1.0, -0.7, 0.7, -0.4, 0.4, -0.1, 0.2, -0.9, 0.1, -0.5, 0.9, -0.6, 0.6, -0.2, 0.3, -0.8, 0.8,
    0.0,
];

/// The multisine's tones: `(frequency in units of hz, amplitude)`, normalised about the middle
/// (peaks add to 0.9, inside the swept range).
pub const TONES: [(f64, f64); 3] = [(0.2, 0.4), (0.5, 0.3), (1.3, 0.2)];

/// The sweep's peak amplitude, normalised about the middle (inside the swept range, as the
/// multisine's peaks are).
pub const SWEEP_AMPLITUDE: f64 = 0.8;

/// Cycles' time of the base frequency the sweep takes where the user names the fastest motion
/// ([`Excitation::reaching`]): four, 0.4 s at 10 Hz.
pub const SWEEP_CYCLES: u16 = 4;

/// The highest ratio of the sweep's top to the base frequency: three decades.
pub const MAX_SWEEP_RATIO: f64 = 1_000.0;

/// The excitation's shape (see the module doc). [`Excitation::DEFAULT`] is what `calibrate`
/// and the laboratory stage play: 2 s at 10 Hz.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Excitation {
    /// The base frequency, Hz.
    pub hz: f64,
    /// Cycles over the whole range.
    pub full_cycles: u16,
    /// Cycles decaying about the middle after them.
    pub decay_cycles: u16,
    /// The decaying cycles' last amplitude, fraction of the whole range's (in `(0, 1)`).
    pub final_amplitude: f64,
    /// Cycles' time the nested loops take.
    pub loop_cycles: u16,
    /// Cycles' time the multisine takes.
    pub multisine_cycles: u16,
    /// Cycles' time the sweep takes (0: no sweep).
    pub sweep_cycles: u16,
    /// The frequency the sweep rises to from `hz`, Hz: the fastest motion the user runs
    /// (unused without a sweep).
    pub sweep_to_hz: f64,
}

impl Excitation {
    /// 10 Hz: 6 full cycles, 14 decaying to 15 % (2 s; see the module doc).
    pub const DECAYING: Self = Self {
        hz: 10.0,
        full_cycles: 6,
        decay_cycles: 14,
        final_amplitude: 0.15,
        loop_cycles: 0,
        multisine_cycles: 0,
        sweep_cycles: 0,
        sweep_to_hz: 0.0,
    };

    /// 10 Hz: 4 full cycles, 6 decaying to 30 %, 5 of nested loops, 5 of multisine (2 s; see
    /// the module doc).
    pub const DEFAULT: Self = Self {
        hz: 10.0,
        full_cycles: 4,
        decay_cycles: 6,
        final_amplitude: 0.3,
        loop_cycles: 5,
        multisine_cycles: 5,
        sweep_cycles: 0,
        sweep_to_hz: 0.0,
    };

    /// This excitation with a sweep up to `fastest_hz` before the multisine
    /// ([`SWEEP_CYCLES`] cycles' time; see the module doc): for a user who names the fastest
    /// motion they will run. [`Excitation::check`] refuses a `fastest_hz` not above `hz`.
    ///
    /// ```
    /// use twinstack_identify::excitation::Excitation;
    /// let e = Excitation::DEFAULT.reaching(200.0);
    /// assert_eq!(e.duration_s(), 2.4);
    /// assert_eq!(e.fastest_hz(), 200.0);
    /// assert!(e.check().is_ok());
    /// ```
    pub const fn reaching(self, fastest_hz: f64) -> Self {
        Self {
            sweep_cycles: SWEEP_CYCLES,
            sweep_to_hz: fastest_hz,
            ..self
        }
    }

    /// The sweep's top, Hz, where the excitation has a sweep ([`Excitation::reaching`]).
    pub const fn sweep_top_hz(&self) -> Option<f64> {
        if self.sweep_cycles > 0 {
            Some(self.sweep_to_hz)
        } else {
            None
        }
    }

    /// The fastest frequency in the excitation, Hz: the sweep's top where there is one, else
    /// the multisine's highest tone (or the base frequency without a multisine).
    pub const fn fastest_hz(&self) -> f64 {
        match self.sweep_top_hz() {
            Some(hz) => hz,
            None if self.multisine_cycles > 0 => TONES[2].0 * self.hz,
            None => self.hz,
        }
    }

    /// Where the last cycle, held out of the fit, starts: the end of the fit window by
    /// default, seconds from the excitation's start.
    pub const fn held_out_from_s(&self) -> f64 {
        self.duration_s() - 1.0 / self.hz
    }

    /// Cycles in all.
    pub const fn cycles(&self) -> u32 {
        self.full_cycles as u32
            + self.decay_cycles as u32
            + self.loop_cycles as u32
            + self.multisine_cycles as u32
            + self.sweep_cycles as u32
    }

    /// Length, seconds.
    pub const fn duration_s(&self) -> f64 {
        self.cycles() as f64 / self.hz
    }

    /// The drive at `t` seconds from the start, normalised about the middle of the swept range
    /// (`−1` its bottom, `1` its top); held at the multisine's last value after the end.
    ///
    /// ```
    /// use twinstack_identify::excitation::Excitation;
    /// let e = Excitation::DEFAULT;
    /// assert_eq!(e.duration_s(), 2.0);
    /// // From the bottom, to the top half a cycle later.
    /// assert_eq!(e.at(0.0), -1.0);
    /// assert!((e.at(0.05) - 1.0).abs() < 1e-12);
    /// // Every sample within the range, and no jump between two at 10 kHz.
    /// let x = e.sampled(10_000.0);
    /// assert_eq!(x.len(), 20_000);
    /// assert!(x.iter().all(|v| v.abs() <= 1.0));
    /// assert!(x.windows(2).all(|w| (w[1] - w[0]).abs() < 0.01));
    /// ```
    pub fn at(&self, t: f64) -> f64 {
        // Each part's end, from its count of cycles (not by adding their lengths: the same
        // instants, to the last bit, whatever the parts before).
        let at_cycle = |n: u32| n as f64 / self.hz;
        let full_n = self.full_cycles as u32;
        let decayed_n = full_n + self.decay_cycles as u32;
        let looped_n = decayed_n + self.loop_cycles as u32;
        let swept_n = looped_n + self.sweep_cycles as u32;
        let (full, decayed, looped) = (at_cycle(full_n), at_cycle(decayed_n), at_cycle(looped_n));
        let swept = at_cycle(swept_n);
        let end = at_cycle(self.cycles());
        let t = t.clamp(0.0, end);
        if t < full {
            -(TAU * self.hz * t).cos()
        } else if t < decayed {
            let a = self.final_amplitude.powf((t - full) / (decayed - full));
            -a * (TAU * self.hz * t).cos()
        } else if t < looped {
            self.nested_loops((t - decayed) / (looped - decayed))
        } else if t < swept {
            self.sweep((t - looped) / (swept - looped), swept - looped)
        } else {
            let s = t - swept;
            TONES
                .iter()
                .map(|&(f, a)| a * (TAU * f * self.hz * s).sin())
                .sum()
        }
    }

    /// The excitation sampled at `rate` samples per second from `t = 0`: its whole length.
    /// (The parts with no cycles are left out.)
    pub fn sampled(&self, rate: f64) -> Vec<f64> {
        let n = (self.duration_s() * rate).round() as usize;
        (0..n).map(|k| self.at(k as f64 / rate)).collect()
    }

    /// The sweep at `phase` (`0 … 1` of its `length`, seconds): a sine whose frequency rises
    /// geometrically from `hz` to `sweep_to_hz` (its phase `2π·hz·L·(k^p − 1)/ln k`,
    /// `k = sweep_to_hz/hz`), under a half-sine window from 0 to [`SWEEP_AMPLITUDE`] and back.
    fn sweep(&self, phase: f64, length: f64) -> f64 {
        let k = self.sweep_to_hz / self.hz;
        let angle = TAU * self.hz * length * (k.powf(phase) - 1.0) / k.ln();
        SWEEP_AMPLITUDE * (core::f64::consts::PI * phase).sin() * angle.sin()
    }

    /// The nested loops at `phase` (`0 … 1` of their time): straight sweeps at one speed from
    /// the decaying cycles' last value through [`REVERSALS`].
    fn nested_loops(&self, phase: f64) -> f64 {
        let start = -self.final_amplitude;
        let length: f64 = core::iter::once(start)
            .chain(REVERSALS)
            .zip(REVERSALS)
            .map(|(a, b)| (b - a).abs())
            .sum();
        let mut left = phase * length;
        let mut from = start;
        for to in REVERSALS {
            let d = (to - from).abs();
            if left <= d {
                return from + (to - from).signum() * left;
            }
            left -= d;
            from = to;
        }
        from
    }

    /// Checks the shape (a positive finite frequency, at least one full and two decaying
    /// cycles, a final amplitude in `(0, 1)`, a sweep's top above the base frequency and at
    /// most [`MAX_SWEEP_RATIO`] times it, at most 10 000 cycles and 600 s in all), naming the
    /// first field that is wrong: `(field, rule, value)`. Whether a sample rate resolves the
    /// fastest motion is the caller's to check ([`Excitation::fastest_hz`]).
    pub fn check(&self) -> Result<(), (&'static str, &'static str, f64)> {
        if !(self.hz.is_finite() && self.hz > 0.0) {
            return Err(("excitation_hz", "a positive number of Hz", self.hz));
        }
        if self.full_cycles == 0 {
            return Err(("full_cycles", "at least 1", 0.0));
        }
        if self.decay_cycles < 2 {
            return Err(("decay_cycles", "at least 2", self.decay_cycles as f64));
        }
        if self.cycles() > 10_000 {
            return Err(("cycles", "at most 10 000 in all", self.cycles() as f64));
        }
        if self.duration_s() > 600.0 {
            return Err((
                "excitation_hz",
                "high enough for the excitation to last at most 600 s",
                self.hz,
            ));
        }
        if !(self.final_amplitude > 0.0 && self.final_amplitude < 1.0) {
            return Err(("final_amplitude", "in (0, 1)", self.final_amplitude));
        }
        if self.sweep_cycles > 0
            && !(self.sweep_to_hz > self.hz && self.sweep_to_hz <= MAX_SWEEP_RATIO * self.hz)
        {
            return Err((
                "fastest_hz",
                "above the excitation's frequency and at most 1 000 times it",
                self.sweep_to_hz,
            ));
        }
        Ok(())
    }
}

impl Default for Excitation {
    /// [`Excitation::DEFAULT`].
    fn default() -> Self {
        Self::DEFAULT
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_parts_join_without_a_jump_and_each_does_what_it_is_for() {
        let e = Excitation::DEFAULT;
        let rate = 50_000.0;
        let x = e.sampled(rate);
        // Continuous: no step between samples larger than the fastest part's speed allows
        // (the full cycles' peak, π·2·10 per second, 0.0013 a sample at 50 kHz).
        let largest = x
            .windows(2)
            .map(|w| (w[1] - w[0]).abs())
            .fold(0.0, f64::max);
        assert!(largest < 0.002, "{largest}");
        let part = |from: f64, to: f64| &x[(from * rate) as usize..(to * rate) as usize];
        let range = |v: &[f64]| {
            v.iter()
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &s| {
                    (l.min(s), h.max(s))
                })
        };
        // The full cycles span the range; the decay ends at its final amplitude.
        let (lo, hi) = range(part(0.0, 0.4));
        assert!(lo <= -0.999 && hi >= 0.999, "{lo} {hi}");
        let (lo, hi) = range(part(0.9, 1.0));
        assert!(
            hi > 0.3 && hi < 0.34 && lo <= -0.3 && lo > -0.37,
            "{lo} {hi}"
        );
        assert!((e.at(1.0 - 1e-9) + 0.3).abs() < 1e-6);
        // The nested loops reverse at every point of REVERSALS, in order.
        let loops = part(1.0, 1.5);
        let mut turns = Vec::new();
        for w in loops.windows(3) {
            if (w[1] - w[0]) * (w[2] - w[1]) < 0.0 {
                turns.push(w[1]);
            }
        }
        assert_eq!(turns.len(), REVERSALS.len() - 1, "{turns:?}");
        for (got, want) in turns.iter().zip(REVERSALS) {
            assert!((got - want).abs() < 1e-3, "{got} vs {want}");
        }
        // The multisine stays inside ±0.9 and reverses many times, at uneven points.
        let ms = part(1.5, 2.0);
        let (lo, hi) = range(ms);
        assert!(lo >= -0.9 && hi <= 0.9 && hi - lo > 1.0, "{lo} {hi}");
        let reversals = ms
            .windows(3)
            .filter(|w| (w[1] - w[0]) * (w[2] - w[1]) < 0.0)
            .count();
        assert!(reversals >= 10, "{reversals}");
    }

    #[test]
    fn the_decaying_excitation_is_the_major_loop_then_concentric_loops() {
        let e = Excitation::DECAYING;
        let rate = 10_000.0;
        let x = e.sampled(rate);
        assert_eq!(x.len(), 20_000);
        for (k, &v) in x.iter().enumerate() {
            let t = k as f64 / rate;
            let a = if t < 0.6 {
                1.0
            } else {
                0.15f64.powf((t - 0.6) / 1.4)
            };
            let want = -a * (std::f64::consts::TAU * 10.0 * t).cos();
            assert!((v - want).abs() < 1e-12, "{t}: {v} vs {want}");
        }
    }

    #[test]
    fn a_wrong_shape_is_named() {
        let bad = |e: Excitation| e.check().unwrap_err().0;
        let e = Excitation::DEFAULT;
        assert_eq!(bad(Excitation { hz: f64::NAN, ..e }), "excitation_hz");
        assert_eq!(bad(Excitation { hz: -1.0, ..e }), "excitation_hz");
        assert_eq!(
            bad(Excitation {
                full_cycles: 0,
                ..e
            }),
            "full_cycles"
        );
        assert_eq!(
            bad(Excitation {
                decay_cycles: 1,
                ..e
            }),
            "decay_cycles"
        );
        assert_eq!(
            bad(Excitation {
                loop_cycles: u16::MAX,
                ..e
            }),
            "cycles"
        );
        assert_eq!(bad(Excitation { hz: 0.01, ..e }), "excitation_hz");
        assert_eq!(
            bad(Excitation {
                final_amplitude: 1.0,
                ..e
            }),
            "final_amplitude"
        );
        assert!(e.check().is_ok());
        for top in [10.0, f64::NAN, -200.0, 10_001.0] {
            assert_eq!(bad(e.reaching(top)), "fastest_hz", "{top}");
        }
        assert!(e.reaching(10_000.0).check().is_ok());
    }

    #[test]
    fn the_sweep_rises_to_the_fastest_motion_between_the_loops_and_the_multisine() {
        let rate = 100_000.0;
        let e = Excitation::DEFAULT.reaching(200.0);
        let x = e.sampled(rate);
        let default = Excitation::DEFAULT.sampled(rate);
        assert_eq!(x.len(), default.len() + 40_000);
        // The default's parts before it, to the bit; its multisine after it.
        assert_eq!(x[..150_000], default[..150_000]);
        for (a, b) in x[190_000..].iter().zip(&default[150_000..]) {
            assert!((a - b).abs() < 1e-9, "{a} vs {b}");
        }
        // The sweep: inside its amplitude, from the middle back to it, no step larger than
        // its top speed allows (2π·200·0.8 a second, plus the window's share).
        let sweep = &x[150_000..190_000];
        assert!(sweep.iter().all(|v| v.abs() <= SWEEP_AMPLITUDE));
        assert!(sweep.iter().any(|v| v.abs() > 0.95 * SWEEP_AMPLITUDE));
        let largest = x[149_999..190_001]
            .windows(2)
            .map(|w| (w[1] - w[0]).abs())
            .fold(0.0, f64::max);
        let top_speed = std::f64::consts::TAU * 200.0 * SWEEP_AMPLITUDE / rate;
        assert!(largest < 1.05 * top_speed, "{largest} vs {top_speed}");
        // Its half-periods shorten from about the base's to the fastest motion's.
        let crossings: Vec<usize> = (1..sweep.len())
            .filter(|&k| (sweep[k - 1] < 0.0) != (sweep[k] < 0.0))
            .collect();
        let halves: Vec<f64> = crossings
            .windows(2)
            .map(|w| (w[1] - w[0]) as f64 / rate)
            .collect();
        let shortest = halves.iter().copied().fold(f64::INFINITY, f64::min);
        let longest = halves.iter().copied().fold(0.0, f64::max);
        assert!((shortest * 2.0 * 200.0 - 1.0).abs() < 0.03, "{shortest}");
        assert!(longest > 0.5 / 10.0 * 0.6, "{longest}");
        assert!(halves.windows(2).all(|w| w[1] <= w[0] * 1.01), "{halves:?}");
    }
}
