//! Preview: a planned trajectory shaped ahead of time so that the stage's resonance does not
//! ring at its corners — the zero-phase inverse of the resonance, which needs the trajectory's
//! next two samples and so can only be made where the trajectory is known in advance (a
//! `compensate` of a planned path, a stream computed on the host).
//!
//! The stage's mechanics are `G(s) = ω² / (s² + 2ζω s + ω²)` (the resonance `twinstack tune`
//! fits), driven by a drive held over each sample. Sampled at the ends of the holds, position
//! `p_k` (the end of hold `k`) follows the held value `r_k` exactly by the zero-order hold
//! ([`crate::zero_order_hold`]):
//!
//! `p_k + a₁ p_{k−1} + a₂ p_{k−2} = b₁ r_k + b₂ r_{k−1}`.
//!
//! Its zero, `−c = −b₂/b₁`, lies just inside the unit circle near −1 at every rate a board
//! runs (−0.95 for a 3.5 kHz resonance at 10 kHz, −0.99 at 50 kHz): inverted exactly, the drive
//! would alternate at half the sample rate, decaying by `c` a sample — the stage would ring
//! between the samples where the sensor does not look. So the zero is not inverted; its
//! reciprocal takes its place (the zero-phase error tracking controller, Tomizuka 1987):
//!
//! `r_k = (w_k + c·w_{k+1}) / (b₁ (1 + c)²)`,  `w_k = d'_k + a₁ d'_{k−1} + a₂ d'_{k−2}`,
//!
//! for the desired positions `d`, sharpened first: `d' = d − κ·δ²d`, `δ²d` the second
//! difference `d_{k−1} − 2d_k + d_{k+1}` and `κ = c/(1 + c)² ≈ ¼`. Without the sharpening the
//! position would be the desired trajectory through the three-tap, zero-phase average
//! `(c·d_{k−1} + (1 + c²)·d_k + c·d_{k+1}) / (1 + c)² = (1 + κδ²)·d` — a gain of exactly 1 at
//! rest and 0 only at half the sample rate, a sine's amplitude short by `κ(ωT)²` and a
//! triangle's corner missed by a quarter of the slope's change over one sample. The
//! sharpening takes that away to first order (Torfs et al. 1992 extend the bandwidth of the
//! zero-phase controller the same way): the position is `(1 − κ²δ⁴)·d`, no delay and no
//! ringing, a sine short by `κ²(ωT)⁴` and a corner missed by an eighth of the slope's change
//! over one sample. The resonance's own poles are cancelled, so the trajectory must not reach
//! them: the shaped values swing past the desired ones at a corner by about `Δslope/(ω² T)`
//! and the sharpening's `κ·Δslope·T`, which the drive's range and slew limits bound as they
//! bound any drive.
//!
//! A model's hysteresis and creep come before the resonance: shaped positions are then what
//! their inverse is given ([`crate::stage_model::StageModel::compensate`]), so that the whole
//! drive is `H⁻¹[C⁻¹[shaped]]`. A sensor's lag stays the model's ([`crate::stage_model`]); the
//! hold's and the resonance's delays are the preview's.

use crate::stage_model::between_samples;
use twinstack::control::mode_switch::Mode;
use twinstack::control::preview::HeldResonance;
use twinstack_link::setpoint_file::q1_15;

/// Why a preview cannot be made.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PreviewError {
    /// The sample rate is not positive and finite.
    #[error("sample rate {0} Hz: must be positive and finite")]
    Rate(f64),
    /// The resonance's frequency is not positive and finite.
    #[error("resonance {0} Hz: must be positive and finite")]
    Frequency(f64),
    /// The resonance is not below half the sample rate (where a sampled trajectory cannot
    /// tell it from a slower one).
    #[error("resonance {hz} Hz: must be below half the sample rate ({nyquist} Hz)")]
    Resonance {
        /// The resonance asked for, Hz.
        hz: f64,
        /// Half the sample rate, Hz.
        nyquist: f64,
    },
    /// The damping ratio is not in `(0, 1)`.
    #[error("damping ratio {0}: must be in (0, 1) (a lightly damped resonance)")]
    Damping(f64),
    /// The record's times are fewer than two, or not evenly spaced.
    #[error("t steps by {step_s} s at t = {at_s} s where it steps by {mean_s} s on average: a preview needs evenly spaced samples")]
    Uneven {
        /// Where the step is off, s.
        at_s: f64,
        /// The step there, s.
        step_s: f64,
        /// The mean step, s.
        mean_s: f64,
    },
    /// The record has fewer than two samples: no rate.
    #[error("fewer than two samples: no sample rate to shape at")]
    TooShort,
    /// A board's setpoints shaped leave its range.
    #[error("setpoint {setpoint} shaped is {value:.4}, outside −1…1 (the preview overshoots a turn there): keep the trajectory further inside the range")]
    OutOfRange {
        /// The setpoint, counted from 1.
        setpoint: usize,
        /// Its shaped value, normalised.
        value: f64,
    },
    /// A shaped position leaves the model's output range.
    #[error("sample {sample} shaped is {value:.4}, outside the model's output range {lo}…{hi} (the preview swings past the trajectory at a sharp turn there): keep the trajectory further inside the range or its turns gentler, or check the resonance")]
    OutsideRange {
        /// The sample, counted from 1.
        sample: usize,
        /// Its shaped value, the trajectory's unit.
        value: f64,
        /// The range, the trajectory's unit.
        lo: f64,
        /// The range, the trajectory's unit.
        hi: f64,
    },
    /// The resonance is so slow against the sample rate that its held response rounds to
    /// nothing: there is nothing to shape for.
    #[error("resonance {hz} Hz: too slow to shape at {rate_hz} Hz (its response over one sample rounds to nothing)")]
    TooSlow {
        /// The resonance, Hz.
        hz: f64,
        /// The sample rate, Hz.
        rate_hz: f64,
    },
    /// The board would not do with shaped setpoints what the preview assumes.
    #[error("the board is in {0:?}: shaped setpoints are for its compensator, in open or closed loop (in bypass they would be the drive, with no hysteresis compensated)")]
    Mode(Mode),
    /// Setpoints several ticks apart, which the board interpolates.
    #[error("the stream plays one setpoint every {0} ticks, interpolated in between, and the preview shapes one a tick (held over it)")]
    Divider(u16),
    /// The board runs its own preview, which would shape the setpoints a second time.
    #[error("the board runs its own preview (for a resonance at {0} Hz): it shapes every setpoint it is given, so send the trajectory as it is (or load with --no-preview first)")]
    OnBoard(f64),
}

/// A stage's lightly damped resonance, what a preview is shaped for: as `twinstack tune`
/// fits it, and as `twinstack calibrate` measures it into the parameter file
/// ([`crate::param_file::ParamFile::resonance`]). Rate-free: the preview at a sample rate
/// comes from [`Resonance::preview`].
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Resonance {
    /// Its frequency, Hz (positive and finite).
    pub frequency_hz: f64,
    /// Its damping ratio, in `(0, 1)`.
    pub damping: f64,
}

impl Resonance {
    /// A resonance at `frequency_hz` with damping ratio `damping`, checked as a preview
    /// needs it (the frequency positive and finite, the damping in `(0, 1)`; whether the
    /// samples resolve it is for [`Resonance::preview`] at their rate).
    ///
    /// ```
    /// use twinstack_identify::preview::{PreviewError, Resonance};
    /// let r = Resonance::new(3_500.0, 0.03).unwrap();
    /// assert!(r.preview(10_000.0).is_ok());
    /// // Sampled at 5 kHz, a 3.5 kHz resonance cannot be told from a slower one.
    /// assert!(matches!(r.preview(5_000.0), Err(PreviewError::Resonance { .. })));
    /// assert!(matches!(Resonance::new(3_500.0, 1.5), Err(PreviewError::Damping(_))));
    /// ```
    pub fn new(frequency_hz: f64, damping: f64) -> Result<Self, PreviewError> {
        let r = Self {
            frequency_hz,
            damping,
        };
        r.check()?;
        Ok(r)
    }

    /// Refuses a frequency that is not positive and finite, or a damping ratio outside
    /// `(0, 1)` (what [`Resonance::new`] checks; a resonance read from a file is checked so).
    pub fn check(&self) -> Result<(), PreviewError> {
        if !(self.frequency_hz.is_finite() && self.frequency_hz > 0.0) {
            return Err(PreviewError::Frequency(self.frequency_hz));
        }
        if !(self.damping > 0.0 && self.damping < 1.0) {
            return Err(PreviewError::Damping(self.damping));
        }
        Ok(())
    }

    /// Its preview for a trajectory sampled at `rate_hz` ([`ResonancePreview::new`]).
    pub fn preview(&self, rate_hz: f64) -> Result<ResonancePreview, PreviewError> {
        ResonancePreview::new(self.frequency_hz, self.damping, rate_hz)
    }

    /// Its preview for a trajectory sampled at the times `t` ([`ResonancePreview::at_times`]).
    pub fn preview_at_times(&self, t: &[f64]) -> Result<ResonancePreview, PreviewError> {
        ResonancePreview::at_times(self.frequency_hz, self.damping, t)
    }
}

/// The zero-phase inverse of a resonance at one sample rate (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct ResonancePreview {
    /// The resonance, Hz.
    pub resonance_hz: f64,
    /// Its damping ratio.
    pub zeta: f64,
    /// The sample rate, Hz.
    pub rate_hz: f64,
    a1: f64,
    a2: f64,
    b1: f64,
    /// `c = b₂/b₁`: the hold's zero is at `−c`.
    c: f64,
    /// `κ = c/(1 + c)²`: the sharpening's gain.
    kappa: f64,
}

impl ResonancePreview {
    /// The preview of a resonance at `resonance_hz` with damping ratio `zeta`, for a
    /// trajectory sampled at `rate_hz`.
    ///
    /// ```
    /// use twinstack_identify::preview::ResonancePreview;
    /// let p = ResonancePreview::new(3_500.0, 0.03, 10_000.0).unwrap();
    /// // At rest, the held value is the position (a gain of 1)...
    /// assert!(p.shape(&[4.0; 10]).iter().all(|&r| (r - 4.0).abs() < 1e-9));
    /// // ...a ramp is held a constant part of a sample behind itself (a position is read at
    /// // the end of its hold, about half a sample after the hold's middle)...
    /// let ramp: Vec<f64> = (0..50).map(|k| k as f64).collect();
    /// let lag: Vec<f64> = p.shape(&ramp).iter().zip(&ramp).map(|(s, r)| r - s).collect();
    /// assert!(lag[3..47].iter().all(|&l| (l - lag[3]).abs() < 1e-9));
    /// assert!(lag[3] > 0.4 && lag[3] < 0.6);
    /// // ...and a resonance the samples cannot resolve is refused.
    /// assert!(ResonancePreview::new(6_000.0, 0.03, 10_000.0).is_err());
    /// ```
    pub fn new(resonance_hz: f64, zeta: f64, rate_hz: f64) -> Result<Self, PreviewError> {
        if !(rate_hz.is_finite() && rate_hz > 0.0) {
            return Err(PreviewError::Rate(rate_hz));
        }
        Resonance {
            frequency_hz: resonance_hz,
            damping: zeta,
        }
        .check()?;
        let nyquist = 0.5 * rate_hz;
        if resonance_hz >= nyquist {
            return Err(PreviewError::Resonance {
                hz: resonance_hz,
                nyquist,
            });
        }
        // The held resonance as the board's preview designs it (gain 1, the position a sample
        // after a held value): `(b₂ + b₁z) / (a₂ + a₁z + z²)`.
        let design = twinstack::control::preview::PreviewDesign {
            frequency_hz: resonance_hz,
            damping: zeta,
        };
        let held = HeldResonance::new(&design, rate_hz).map_err(|_| PreviewError::TooSlow {
            hz: resonance_hz,
            rate_hz,
        })?;
        let (b2, b1, a2, a1) = (held.b2, held.b1, held.a2, held.a1);
        if !(b1 > 0.0 && [b2, a2, a1, b2 / b1].iter().all(|v| v.is_finite())) {
            return Err(PreviewError::TooSlow {
                hz: resonance_hz,
                rate_hz,
            });
        }
        let c = b2 / b1;
        Ok(Self {
            resonance_hz,
            zeta,
            rate_hz,
            a1,
            a2,
            b1,
            c,
            kappa: c / ((1.0 + c) * (1.0 + c)),
        })
    }

    /// [`Self::new`] at the rate of the times `t` (s), which must be evenly spaced: every step
    /// within 1 % of the mean step, else [`PreviewError::Uneven`] names the first that is not.
    ///
    /// ```
    /// use twinstack_identify::preview::{PreviewError, ResonancePreview};
    /// let t: Vec<f64> = (0..100).map(|k| k as f64 * 1e-4).collect();
    /// assert_eq!(ResonancePreview::at_times(3_500.0, 0.03, &t).unwrap().rate_hz.round(), 10_000.0);
    /// let mut uneven = t.clone();
    /// uneven[50] += 5e-5;
    /// assert!(matches!(
    ///     ResonancePreview::at_times(3_500.0, 0.03, &uneven),
    ///     Err(PreviewError::Uneven { .. })
    /// ));
    /// ```
    pub fn at_times(resonance_hz: f64, zeta: f64, t: &[f64]) -> Result<Self, PreviewError> {
        let n = t.len();
        let mean = match (t.first(), t.last()) {
            (Some(a), Some(b)) if n > 1 => (b - a) / (n - 1) as f64,
            _ => return Err(PreviewError::TooShort),
        };
        let off = |step: f64| {
            let d = (step - mean).abs();
            d.is_nan() || d > 0.01 * mean
        };
        if let Some(w) = t.windows(2).find(|w| off(w[1] - w[0])) {
            return Err(PreviewError::Uneven {
                at_s: w[1],
                step_s: w[1] - w[0],
                mean_s: mean,
            });
        }
        Self::new(resonance_hz, zeta, 1.0 / mean)
    }

    /// [`ResonancePreview::shape`], refusing a shaped position outside `lo … hi` (a model's
    /// output range, in the trajectory's unit), naming the first: there the drive would be
    /// clamped and the corner ring as if unshaped.
    pub fn shape_within(
        &self,
        desired: &[f64],
        lo: f64,
        hi: f64,
    ) -> Result<Vec<f64>, PreviewError> {
        let r = self.shape(desired);
        match r.iter().position(|v| !(lo..=hi).contains(v)) {
            Some(k) => Err(PreviewError::OutsideRange {
                sample: k + 1,
                value: r[k],
                lo,
                hi,
            }),
            None => Ok(r),
        }
    }

    /// `c`: the hold's zero, at `−c`, which the preview does not invert (see the module doc).
    pub fn zero(&self) -> f64 {
        self.c
    }

    /// The held values that bring the position to `desired` (positions at the ends of the
    /// holds, any unit), through the three-tap average of the module doc. The trajectory is
    /// taken as resting at its first value before it and at its last after it.
    pub fn shape(&self, desired: &[f64]) -> Vec<f64> {
        let n = desired.len();
        if n == 0 {
            return Vec::new();
        }
        let at = |k: isize| desired[k.clamp(0, n as isize - 1) as usize];
        let d = |k: isize| self.sharpened(at, k);
        let w = |k: isize| d(k) + self.a1 * d(k - 1) + self.a2 * d(k - 2);
        let scale = 1.0 / (self.b1 * (1.0 + self.c) * (1.0 + self.c));
        (0..n as isize)
            .map(|k| (w(k) + self.c * w(k + 1)) * scale)
            .collect()
    }

    /// A board's stream shaped: `samples` (Q1.15, one a tick at this preview's rate, each for
    /// the middle of its tick, as the board takes a setpoint) for a board with the settings
    /// `board` playing one every `divider` ticks. The positions between setpoints (at the ends
    /// of the ticks, [`between_samples`]) go through [`Self::shape`], back to Q1.15. Closed
    /// loop, the feedback follows the shaped setpoints as the compensator does: they stand off
    /// the trajectory by about `2ζẋ/ω + ẍ/ω²`, at a corner for a sample or two (by
    /// `Δslope/(ω² T)`), on fast smooth motion all along (the board's own preview,
    /// [`twinstack::control::preview`], has its feedback aim at the setpoints instead).
    /// Refused: a board that runs its own preview ([`PreviewError::OnBoard`]: the setpoints
    /// would be shaped twice), a board in
    /// bypass ([`PreviewError::Mode`]: the shaped values would be the drive), a divider above 1
    /// ([`PreviewError::Divider`]), a shaped value outside −1…1 ([`PreviewError::OutOfRange`],
    /// the first).
    ///
    /// ```
    /// use twinstack::control::mode_switch::Mode;
    /// use twinstack_identify::preview::{PreviewError, ResonancePreview};
    /// let p = ResonancePreview::new(21_800.0, 0.017, 50_000.0).unwrap();
    /// let ramp: Vec<i16> = (0..100).map(|k| (k * 100) as i16).collect();
    /// assert_eq!(p.shape_stream(&ramp, Mode::OpenLoop, 1).unwrap().len(), 100);
    /// assert_eq!(p.shape_stream(&ramp, Mode::ClosedLoop, 1).unwrap().len(), 100);
    /// assert_eq!(p.shape_stream(&ramp, Mode::Bypass, 1), Err(PreviewError::Mode(Mode::Bypass)));
    /// assert_eq!(p.shape_stream(&ramp, Mode::OpenLoop, 5), Err(PreviewError::Divider(5)));
    /// // A board that runs its own preview is given the trajectory as it is.
    /// let mut board = twinstack::config::settings::Settings {
    ///     mode: Mode::ClosedLoop,
    ///     ..Default::default()
    /// };
    /// assert!(p.shape_stream_for(&ramp, &board, 1).is_ok());
    /// board.preview = Some(twinstack::config::settings::PreviewDesign {
    ///     frequency_hz: 21_800.0,
    ///     damping: 0.017,
    /// });
    /// assert_eq!(p.shape_stream_for(&ramp, &board, 1), Err(PreviewError::OnBoard(21_800.0)));
    /// ```
    pub fn shape_stream_for(
        &self,
        samples: &[i16],
        board: &twinstack::config::settings::Settings,
        divider: u16,
    ) -> Result<Vec<i16>, PreviewError> {
        if let Some(p) = &board.preview {
            return Err(PreviewError::OnBoard(p.frequency_hz));
        }
        self.shape_stream(samples, board.mode, divider)
    }

    /// [`Self::shape_stream_for`] a board in `mode` without a preview of its own.
    pub fn shape_stream(
        &self,
        samples: &[i16],
        mode: Mode,
        divider: u16,
    ) -> Result<Vec<i16>, PreviewError> {
        if divider != 1 {
            return Err(PreviewError::Divider(divider));
        }
        if mode == Mode::Bypass {
            return Err(PreviewError::Mode(mode));
        }
        let x: Vec<f64> = samples.iter().map(|&q| q as f64 / 32768.0).collect();
        let r = self.shape(&between_samples(&x));
        if let Some(k) = r.iter().position(|v| !(-1.0..=1.0).contains(v)) {
            return Err(PreviewError::OutOfRange {
                setpoint: k + 1,
                value: r[k],
            });
        }
        Ok(r.into_iter().map(q1_15).collect())
    }

    /// What the position does under [`Self::shape`]`(desired)`: the three-tap zero-phase
    /// average of the sharpened trajectory, `(1 + κδ²)(1 − κδ²)·d = d − κ²δ⁴d` (the preview's
    /// own error is this less `desired`).
    pub fn smoothed(&self, desired: &[f64]) -> Vec<f64> {
        let n = desired.len();
        let at = |k: isize| desired[k.clamp(0, n as isize - 1) as usize];
        let d = |k: isize| self.sharpened(at, k);
        let norm = (1.0 + self.c) * (1.0 + self.c);
        (0..n as isize)
            .map(|k| {
                (self.c * d(k - 1) + (1.0 + self.c * self.c) * d(k) + self.c * d(k + 1)) / norm
            })
            .collect()
    }

    /// The desired trajectory `at` sharpened at sample `k` by what the three-tap average takes
    /// away, to first order: `d_k − κ·(d_{k−1} − 2d_k + d_{k+1})`, `κ = c/(1 + c)²` (about ¼).
    /// The average is `1 + κδ²`; after it the position is `(1 − κ²δ⁴)·d`: a sine's loss and a
    /// corner's miss of second order instead of first. Not the average's exact inverse, whose
    /// gain at half the sample rate, `((1 + c)/(1 − c))²`, would make the stage ring between
    /// the samples; this one's is `1 + 4κ`, below 2. The first sample is left as it is: the
    /// drive before it, which its sharpening would need, is the stage's rest.
    fn sharpened(&self, at: impl Fn(isize) -> f64, k: isize) -> f64 {
        if k <= 0 {
            return at(k);
        }
        at(k) - self.kappa * (at(k - 1) - 2.0 * at(k) + at(k + 1))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::zero_order_hold::ZeroOrderHold;
    use std::f64::consts::TAU;

    /// The board's preview (`twinstack::control::preview`: nine taps on the setpoints, the
    /// trajectory four ticks late) is this one on a stream ([`ResonancePreview::shape_stream`]'s
    /// positions between the setpoints), away from the ends.
    #[test]
    fn the_board_s_preview_is_the_host_s_on_a_stream() {
        for rate in [10_000.0, 50_000.0, 100_000.0] {
            let p = ResonancePreview::new(3_500.0, 0.03, rate).unwrap();
            let taps = twinstack::control::preview::PreviewDesign {
                frequency_hz: 3_500.0,
                damping: 0.03,
            }
            .taps(rate)
            .unwrap();
            let x: Vec<f64> = (0..400)
                .map(|k| {
                    let t = k as f64 / 400.0;
                    0.5 * (TAU * 3.0 * t).sin() + 0.3 * (1.0 - 4.0 * (t * 7.0 % 1.0 - 0.5).abs())
                })
                .collect();
            let host = p.shape(&between_samples(&x));
            for k in 8..390 {
                let board: f64 = (0..9).map(|i| taps[i] * x[k - 4 + i]).sum();
                assert!(
                    (board - host[k]).abs() < 1e-9,
                    "{rate} Hz, sample {k}: {board} vs {}",
                    host[k]
                );
            }
        }
    }

    /// The resonance held over each sample, exactly: the position at the end of each hold.
    fn run(resonance_hz: f64, zeta: f64, rate: f64, held: &[f64], start: f64) -> Vec<f64> {
        let w = TAU * resonance_hz;
        let zoh = ZeroOrderHold::<2, 1>::new(
            &[[0.0, 1.0], [-w * w, -2.0 * zeta * w]],
            &[[0.0], [w * w]],
            1.0 / rate,
        );
        let mut x = [start, 0.0];
        held.iter()
            .map(|&r| {
                zoh.step(&mut x, &[r]);
                x[0]
            })
            .collect()
    }

    /// A triangle: `samples` a half period, from 0 to 1 and back, `cycles` times.
    fn triangle(samples: usize, cycles: usize) -> Vec<f64> {
        (0..2 * samples * cycles)
            .map(|k| {
                let phase = k % (2 * samples);
                if phase < samples {
                    phase as f64 / samples as f64
                } else {
                    2.0 - phase as f64 / samples as f64
                }
            })
            .collect()
    }

    #[test]
    fn the_shaped_drive_brings_the_resonance_to_the_zero_phase_average_of_the_target() {
        for (f, zeta, rate) in [
            (3_500.0, 0.03, 10_000.0),
            (3_500.0, 0.03, 50_000.0),
            (21_800.0, 0.017, 50_000.0),
        ] {
            let p = ResonancePreview::new(f, zeta, rate).unwrap();
            let desired = triangle(25, 4);
            let position = run(f, zeta, rate, &p.shape(&desired), 0.0);
            let expected = p.smoothed(&desired);
            // The last sample rests at its last target (no sample after it).
            for k in 0..desired.len() - 1 {
                assert!(
                    (position[k] - expected[k]).abs() < 1e-9,
                    "{f} Hz at {rate} Hz, sample {k}: {} vs {}",
                    position[k],
                    expected[k]
                );
            }
        }
    }

    #[test]
    fn shaping_removes_the_ringing_a_triangle_corner_excites() {
        let (f, zeta, rate) = (3_500.0, 0.03, 50_000.0);
        let p = ResonancePreview::new(f, zeta, rate).unwrap();
        // 100 Hz at 50 kHz: 250 samples a half period.
        let desired = triangle(250, 3);
        let worst = |position: &[f64]| {
            desired[..desired.len() - 1]
                .iter()
                .zip(position)
                .map(|(d, x)| (d - x).abs())
                .fold(0.0, f64::max)
        };
        let plain = worst(&run(f, zeta, rate, &desired, 0.0));
        let shaped = worst(&run(f, zeta, rate, &p.shape(&desired), 0.0));
        // Unshaped: the corner rings by about Δslope/ω (1.8 % of the span). Shaped: an eighth
        // of the slope's change over a sample (`2κ²`), 0.1 %.
        assert!(plain > 0.015, "unshaped {plain}");
        assert!(shaped < 0.0011, "shaped {shaped}");
    }

    #[test]
    fn the_zero_is_inside_the_unit_circle_near_minus_one() {
        for (f, rate) in [
            (3_500.0, 10_000.0),
            (3_500.0, 50_000.0),
            (21_800.0, 100_000.0),
        ] {
            let c = ResonancePreview::new(f, 0.03, rate).unwrap().zero();
            assert!(c > 0.9 && c < 1.0, "{f} Hz at {rate} Hz: {c}");
        }
    }

    #[test]
    fn a_preview_it_cannot_make_is_refused_naming_the_value() {
        assert_eq!(
            ResonancePreview::new(1e3, 0.03, 0.0),
            Err(PreviewError::Rate(0.0))
        );
        for hz in [f64::NAN, f64::INFINITY, 0.0, -1e3] {
            assert!(matches!(
                ResonancePreview::new(hz, 0.03, 1e4),
                Err(PreviewError::Frequency(_))
            ));
        }
        // So slow against the rate that its held response rounds to nothing (it shaped
        // every position to NaN).
        assert!(matches!(
            ResonancePreview::new(1e-300, 0.03, 1e4),
            Err(PreviewError::TooSlow { .. })
        ));
        // Shaped positions leaving a model's range are named, the first of them. (Sharp turns
        // swing the shaped values toward the inside of a turn, `Δslope/(ω² T)`, and a ramp is
        // held part of a sample behind itself: a range as wide as the trajectory is left only
        // by a little, near its ends.)
        let p = ResonancePreview::new(10.0, 0.05, 200.0).unwrap();
        let triangle: Vec<f64> = (0..100)
            .map(|k| match (k + 10) % 40 {
                q if q <= 20 => q as f64 - 10.0,
                q => 30.0 - q as f64,
            })
            .collect();
        assert_eq!(
            (triangle[0], triangle[10], triangle[30]),
            (0.0, 10.0, -10.0)
        );
        let shaped = p.shape(&triangle);
        assert_eq!(p.shape_within(&triangle, -100.0, 100.0), Ok(shaped.clone()));
        let first = shaped.iter().position(|v| v.abs() > 5.0).unwrap();
        assert_eq!(
            p.shape_within(&triangle, -5.0, 5.0),
            Err(PreviewError::OutsideRange {
                sample: first + 1,
                value: shaped[first],
                lo: -5.0,
                hi: 5.0
            })
        );
        assert!(matches!(
            ResonancePreview::new(5e3, 0.03, 1e4),
            Err(PreviewError::Resonance { .. })
        ));
        for zeta in [0.0, 1.0, -0.1, f64::NAN] {
            assert!(matches!(
                ResonancePreview::new(1e3, zeta, 1e4),
                Err(PreviewError::Damping(_))
            ));
        }
        let e = ResonancePreview::new(6e3, 0.03, 1e4)
            .unwrap_err()
            .to_string();
        assert!(e.contains("6000 Hz") && e.contains("5000 Hz"), "{e}");
    }

    /// Setpoints for the middles of the ticks are shaped at the ends of the ticks: the shaped
    /// stream is the preview of the positions between them. A dip just below the range's top
    /// turns back up so sharply that the shaped setpoint leaves the range: refused, naming it.
    #[test]
    fn a_stream_is_shaped_between_its_setpoints_and_a_shaped_value_beyond_the_range_is_refused() {
        let p = ResonancePreview::new(3_000.0, 0.03, 50_000.0).unwrap();
        let x: Vec<f64> = (0..400).map(|k| 0.5 * (k as f64 * 0.05).sin()).collect();
        let q: Vec<i16> = x.iter().map(|&v| q1_15(v)).collect();
        let s = p.shape_stream(&q, Mode::OpenLoop, 1).unwrap();
        let xq: Vec<f64> = q.iter().map(|&v| v as f64 / 32768.0).collect();
        let expected = p.shape(&between_samples(&xq));
        assert!(s
            .iter()
            .zip(&expected)
            .all(|(&a, &b)| (a as f64 / 32768.0 - b).abs() <= 1.0 / 32768.0));
        // A V from 0.99 down to 0.9 and back within four ticks.
        let mut v = vec![0.99; 40];
        v[20..25].copy_from_slice(&[0.96, 0.93, 0.9, 0.93, 0.96]);
        let q: Vec<i16> = v.iter().map(|&v| q1_15(v)).collect();
        match p.shape_stream(&q, Mode::OpenLoop, 1) {
            Err(PreviewError::OutOfRange { setpoint, value }) => {
                assert!(
                    (18..=26).contains(&setpoint) && value > 1.0,
                    "{setpoint}: {value}"
                )
            }
            other => panic!("{other:?}"),
        }
        assert_eq!(
            p.shape_stream(&q, Mode::Bypass, 1),
            Err(PreviewError::Mode(Mode::Bypass))
        );
    }

    #[test]
    fn an_empty_or_single_sample_trajectory_is_shaped_into_itself() {
        let p = ResonancePreview::new(3_500.0, 0.03, 10_000.0).unwrap();
        assert!(p.shape(&[]).is_empty());
        let one = p.shape(&[2.5]);
        assert!((one[0] - 2.5).abs() < 1e-12);
    }
}
