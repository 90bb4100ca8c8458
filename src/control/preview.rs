//! The preview on the board: every setpoint shaped for the stage's resonance before the
//! compensator, whatever its source (a stream, the board's generator, a scan, the analog
//! input), with the feedback aiming at the setpoint itself — a two-degree-of-freedom loop.
//!
//! The stage's mechanics are `G(s) = ω² / (s² + 2ζω s + ω²)` driven by a drive held over each
//! tick. Sampled at the holds' ends, the position `p_k` follows the held value `r_k` by the
//! zero-order hold ([`HeldResonance`]): `p_k + a₁ p_{k−1} + a₂ p_{k−2} = b₁ r_k + b₂ r_{k−1}`.
//! The preview gives the compensator, for setpoints `s` (each for the middle of its hold,
//! [`crate::control::instant`]), the held values that bring the position at each hold's end to
//! the setpoints' value there, `e_k` (the cubic between the holds' middles,
//! [`crate::control::instant::between_holds`]):
//!
//! `r_k = (w_k + c·w_{k+1}) / (b₁ (1 + c)²)`,  `w_k = e'_k + a₁ e'_{k−1} + a₂ e'_{k−2}`,
//! `e' = e − κ·δ²e`,  `c = b₂/b₁`,  `κ = c/(1 + c)²`.
//!
//! The hold's zero at `−c` (near −1) is not inverted, its reciprocal takes its place (the
//! zero-phase error tracking controller, Tomizuka 1987), and the trajectory is sharpened first
//! by what the resulting three-tap average takes away (Torfs et al. 1992): the position is the
//! setpoints' trajectory within `κ²δ⁴e`, with no ringing at a corner. The host's preview
//! (`twinstack_identify::preview`, for a planned trajectory shaped before it is sent) is the
//! same filter in `f64`.
//!
//! **On the board.** All of it is one linear filter of nine taps, `r_k = Σ h_i s_{k+i}`
//! (`i = −4 … 4`): it needs four setpoints after the one it shapes, so the preview delays the
//! trajectory by [`PREVIEW_DELAY_TICKS`] ticks — the compensator gets `r_{n−4}` and the
//! feedback aims at `s_{n−4}` on tick `n` (80 µs at 50 kHz). The taps are designed off the tick
//! ([`PreviewDesign::preview`], at the board's rate) and their sum is exactly 1, so the filter
//! is written on the differences from the middle setpoint: `r = s₀ + Σ h_i (s_i − s₀)` — a
//! setpoint held passes bit for bit, and the taps' rounding errs in proportion to the motion,
//! not to the position.
//!
//! **Fixed point.** Setpoints Q2.30 within full scale, so every difference fits an `i32`
//! exactly; taps `i32` with [`Preview::shift`] fractional bits, chosen so that the taps'
//! absolute sum times `2^shift` is at most `2^31`: the nine products summed in `i64` stay below
//! `2^62`. Rounded, saturated, limited to full scale: a shaped setpoint that would pass the
//! range (a corner too sharp for the resonance) is held at the range's end, and the drive's
//! own range and slew limits hold after it as always.

use crate::fixed_point::{clamp_full_scale, saturate_i64};
use crate::refusal::{Field, Refusal, Rule};

/// The filter's length: four setpoints before the one shaped, four after it.
pub const PREVIEW_TAPS: usize = 9;

/// How many ticks the preview delays the trajectory (the setpoints after the one shaped that
/// it waits for).
pub const PREVIEW_DELAY_TICKS: usize = PREVIEW_TAPS / 2;

/// The fewest fractional bits a design's taps may have: below it (a resonance so slow against
/// the rate that the taps reach `2^23`) the design is refused.
const MIN_SHIFT: u32 = 8;

/// The resonance the preview shapes for, in physical units (as `twinstack tune` fits it and
/// `twinstack calibrate` measures it).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PreviewDesign {
    /// Its frequency, Hz: positive, below half the control rate.
    pub frequency_hz: f64,
    /// Its damping ratio, in `(0, 1)`.
    pub damping: f64,
}

/// Why a preview design was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PreviewError {
    /// A value (or the control rate) is NaN or infinite.
    NotFinite,
    /// The frequency is not positive, or not below half the control rate (where the ticks
    /// cannot tell the resonance from a slower one).
    FrequencyOutOfRange,
    /// The damping ratio is not in `(0, 1)`.
    DampingOutOfRange,
    /// The resonance is so slow against the control rate that the taps would pass `2^23`
    /// (its held response over a tick all but nothing).
    TooSlow,
}

/// A design's refusal at `rate_hz`, on the settings' field it concerns
/// (`preview.frequency_hz` or `preview.damping`).
pub fn refusal(d: &PreviewDesign, e: PreviewError, rate_hz: f64) -> Refusal {
    match e {
        PreviewError::NotFinite if !d.frequency_hz.is_finite() => {
            Refusal::new(Field::PreviewFrequency, Rule::NotFinite)
        }
        PreviewError::NotFinite => Refusal::new(Field::PreviewDamping, Rule::NotFinite),
        PreviewError::FrequencyOutOfRange if d.frequency_hz <= 0.0 => {
            Refusal::new(Field::PreviewFrequency, Rule::Above(0.0))
        }
        PreviewError::FrequencyOutOfRange => {
            Refusal::new(Field::PreviewFrequency, Rule::Below(0.5 * rate_hz))
        }
        PreviewError::DampingOutOfRange if d.damping <= 0.0 => {
            Refusal::new(Field::PreviewDamping, Rule::Above(0.0))
        }
        PreviewError::DampingOutOfRange => Refusal::new(Field::PreviewDamping, Rule::Below(1.0)),
        // Its taps would not fit their format.
        PreviewError::TooSlow => Refusal::new(Field::PreviewFrequency, Rule::BeyondFixedPoint),
    }
}

/// The resonance held over a tick: `(b₂ + b₁z) / (a₂ + a₁z + z²)`, the position at a hold's
/// end from the values held, gain 1 at rest (`b₁ + b₂ = 1 + a₁ + a₂`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct HeldResonance {
    /// `a₁ = −2 e^{−ζωT} cos ω_d T`.
    pub a1: f64,
    /// `a₂ = e^{−2ζωT}`.
    pub a2: f64,
    /// `b₁ = 1 − e^{−ζωT}(cos ω_d T + (ζω/ω_d) sin ω_d T)`.
    pub b1: f64,
    /// `b₂ = e^{−2ζωT} + e^{−ζωT}((ζω/ω_d) sin ω_d T − cos ω_d T)`.
    pub b2: f64,
}

impl HeldResonance {
    /// The resonance `design` held over ticks at `rate_hz` (the exact zero-order hold of the
    /// underdamped second-order system).
    pub fn new(design: &PreviewDesign, rate_hz: f64) -> Result<Self, PreviewError> {
        let (f, zeta) = (design.frequency_hz, design.damping);
        if !(f.is_finite() && zeta.is_finite() && rate_hz.is_finite()) || rate_hz <= 0.0 {
            return Err(PreviewError::NotFinite);
        }
        if !(f > 0.0 && f < 0.5 * rate_hz) {
            return Err(PreviewError::FrequencyOutOfRange);
        }
        if !(zeta > 0.0 && zeta < 1.0) {
            return Err(PreviewError::DampingOutOfRange);
        }
        let w = 2.0 * core::f64::consts::PI * f;
        let t = 1.0 / rate_hz;
        let sigma = zeta * w;
        let wd = w * libm::sqrt(1.0 - zeta * zeta);
        let e = libm::exp(-sigma * t);
        let (s, c) = (libm::sin(wd * t), libm::cos(wd * t));
        let k = sigma / wd;
        Ok(Self {
            a1: -2.0 * e * c,
            a2: e * e,
            b1: 1.0 - e * (c + k * s),
            b2: e * e + e * (k * s - c),
        })
    }
}

impl PreviewDesign {
    /// The filter's taps at `rate_hz`, `f64`, oldest setpoint first (`h_{−4} … h_4`; they sum
    /// to 1): the reference the board's fixed-point filter is checked against.
    pub fn taps(&self, rate_hz: f64) -> Result<[f64; PREVIEW_TAPS], PreviewError> {
        let h = HeldResonance::new(self, rate_hz)?;
        if !(h.b1 > 0.0 && (h.b2 / h.b1).is_finite()) {
            return Err(PreviewError::TooSlow);
        }
        let c = h.b2 / h.b1;
        let kappa = c / ((1.0 + c) * (1.0 + c));
        // Each factor as coefficients of z^i from its lowest power, multiplied out: the cubic
        // between the holds' middles (z^−1 … z^2), the sharpening (z^−1 … z), the resonance's
        // poles (z^−2 … 1), the zero's reciprocal (1 … z); lowest powers −1, −1, −2, 0.
        let mut taps = [0.0f64; PREVIEW_TAPS];
        let between = [-1.0 / 16.0, 9.0 / 16.0, 9.0 / 16.0, -1.0 / 16.0];
        let sharpen = [-kappa, 1.0 + 2.0 * kappa, -kappa];
        let poles = [h.a2, h.a1, 1.0];
        let scale = 1.0 / (h.b1 * (1.0 + c) * (1.0 + c));
        let zero = [scale, c * scale];
        for (i, x) in between.iter().enumerate() {
            for (j, y) in sharpen.iter().enumerate() {
                for (k, p) in poles.iter().enumerate() {
                    for (l, q) in zero.iter().enumerate() {
                        // Power (i − 1) + (j − 1) + (k − 2) + l, from −4 at index 0.
                        taps[i + j + k + l] += x * y * p * q;
                    }
                }
            }
        }
        if taps.iter().any(|v| !v.is_finite()) {
            return Err(PreviewError::TooSlow);
        }
        Ok(taps)
    }

    /// The preview the tick runs at `rate_hz`: the taps in fixed point, their sum exactly 1
    /// (see the module doc). Refused: a value not finite, a frequency not below half the rate,
    /// a damping ratio outside `(0, 1)`, a resonance so slow against the rate that the taps
    /// pass `2^23`.
    ///
    /// ```
    /// use twinstack::control::preview::{PreviewDesign, PreviewError, PreviewLine};
    /// let design = PreviewDesign { frequency_hz: 3_500.0, damping: 0.03 };
    /// let p = design.preview(50_000.0).unwrap();
    /// // A step: the target moves four ticks late, the shaped setpoint before it (the
    /// // resonance's lag made up ahead), and once held the setpoint passes bit for bit.
    /// let mut line = PreviewLine::at(0);
    /// let out: Vec<(i32, i32)> = (0..9).map(|_| p.step(&mut line, 1 << 28)).collect();
    /// assert_eq!(out[3].0, 0);
    /// assert!(out[3].1 > 0);
    /// assert_eq!(out[4].0, 1 << 28);
    /// assert_eq!(out[8], (1 << 28, 1 << 28));
    /// // ...and a resonance the ticks cannot resolve is refused.
    /// assert_eq!(design.preview(6_000.0), Err(PreviewError::FrequencyOutOfRange));
    /// ```
    pub fn preview(&self, rate_hz: f64) -> Result<Preview, PreviewError> {
        let taps = self.taps(rate_hz)?;
        let mid = PREVIEW_DELAY_TICKS;
        let spread: f64 = taps
            .iter()
            .enumerate()
            .filter(|&(i, _)| i != mid)
            .map(|(_, h)| h.abs())
            .sum();
        // The most fractional bits with Σ|h_i|·2^shift ≤ 2^31.
        let mut shift = 30u32;
        while shift > MIN_SHIFT && spread * (1u64 << shift) as f64 > (1u64 << 31) as f64 {
            shift -= 1;
        }
        if spread * (1u64 << shift) as f64 > (1u64 << 31) as f64 {
            return Err(PreviewError::TooSlow);
        }
        let one = (1u64 << shift) as f64;
        let mut gains = [0i32; PREVIEW_TAPS];
        for (g, h) in gains.iter_mut().zip(taps.iter()) {
            *g = libm::round(h * one) as i32;
        }
        // The middle tap is not used: the filter is written on the differences from it, so
        // its sum with the others is 1 by construction.
        gains[mid] = 0;
        Ok(Preview { gains, shift })
    }
}

/// The preview the tick runs: nine taps on the differences from the middle setpoint, in
/// `i32` with [`Preview::shift`] fractional bits (built by [`PreviewDesign::preview`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Preview {
    /// `h_i` for `i ≠ 0`, oldest setpoint first; the middle entry is 0.
    gains: [i32; PREVIEW_TAPS],
    /// The taps' fractional bits (8 … 30).
    shift: u32,
}

/// The preview's memory: the last [`PREVIEW_TAPS`] setpoints, oldest first, Q2.30.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PreviewLine {
    setpoints: [i32; PREVIEW_TAPS],
}

impl PreviewLine {
    /// A line that has held `setpoint` (Q2.30, limited to full scale) for ever: the preview
    /// passes it as it is.
    pub fn at(setpoint: i32) -> Self {
        Self {
            setpoints: [clamp_full_scale(setpoint); PREVIEW_TAPS],
        }
    }

    /// The setpoint the preview shapes next (the middle of the line): the one the feedback
    /// aims at, [`PREVIEW_DELAY_TICKS`] ticks after it was given.
    #[inline(always)]
    pub fn target(&self) -> i32 {
        self.setpoints[PREVIEW_DELAY_TICKS]
    }
}

impl Preview {
    /// The taps' fractional bits.
    pub fn shift(&self) -> u32 {
        self.shift
    }

    /// The taps in `f64` as the tick applies them (the middle one `1 − Σ` of the others).
    pub fn taps(&self) -> [f64; PREVIEW_TAPS] {
        let one = (1u64 << self.shift) as f64;
        let mut t = [0.0; PREVIEW_TAPS];
        for (x, g) in t.iter_mut().zip(self.gains.iter()) {
            *x = *g as f64 / one;
        }
        t[PREVIEW_DELAY_TICKS] = 1.0 - t.iter().sum::<f64>();
        t
    }

    /// One tick: `setpoint` (Q2.30, the newest) into the line; returns the setpoint
    /// [`PREVIEW_DELAY_TICKS`] ticks ago (the feedback's target) and it shaped (the
    /// compensator's input), both Q2.30 within full scale. Eight multiply-adds, no call, no
    /// division, no branch on the data.
    #[inline(always)]
    pub fn step(&self, line: &mut PreviewLine, setpoint: i32) -> (i32, i32) {
        // Written out, tap by tap: straight-line code, no loop, no call, no branch to take.
        let [_, s1, s2, s3, s4, mid, s6, s7, s8] = line.setpoints;
        let newest = clamp_full_scale(setpoint);
        line.setpoints = [s1, s2, s3, s4, mid, s6, s7, s8, newest];
        let g = &self.gains;
        // Both within full scale: each difference is exact in an i32.
        let d = |x: i32| x.wrapping_sub(mid) as i64;
        let acc = g[0] as i64 * d(s1)
            + g[1] as i64 * d(s2)
            + g[2] as i64 * d(s3)
            + g[3] as i64 * d(s4)
            + g[5] as i64 * d(s6)
            + g[6] as i64 * d(s7)
            + g[7] as i64 * d(s8)
            + g[8] as i64 * d(newest);
        // Rounded to nearest (shift ≥ 8); |delta| < 2^54, so the sum cannot overflow.
        let delta = (acc + (1i64 << (self.shift - 1))) >> self.shift;
        (mid, clamp_full_scale(saturate_i64(mid as i64 + delta)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64, signal_to_f64, SIGNAL_ONE};

    fn design(f: f64, zeta: f64) -> PreviewDesign {
        PreviewDesign {
            frequency_hz: f,
            damping: zeta,
        }
    }

    /// The f64 filter on `s` (the line's convention: output k shapes s[k − 4]).
    fn reference(taps: &[f64; PREVIEW_TAPS], s: &[f64], k: usize) -> f64 {
        (0..PREVIEW_TAPS)
            .map(|i| taps[i] * s[(k + i).saturating_sub(PREVIEW_TAPS - 1)])
            .sum()
    }

    #[test]
    fn the_taps_sum_to_one_and_the_tick_s_filter_is_the_f64_one() {
        for &(f, zeta, rate) in &[
            (3_500.0, 0.03, 10_000.0),
            (3_500.0, 0.03, 100_000.0),
            (21_800.0, 0.017, 50_000.0),
            (300.0, 0.05, 100_000.0),
        ] {
            let d = design(f, zeta);
            let taps = d.taps(rate).unwrap();
            assert!(
                (taps.iter().sum::<f64>() - 1.0).abs() < 1e-9,
                "{f} Hz at {rate}"
            );
            let p = d.preview(rate).unwrap();
            // A sine and a triangle within ±0.9.
            const N: usize = 2_000;
            let n = N;
            let mut q = [0i32; N];
            let mut qf = [0.0f64; N];
            for k in 0..N {
                let t = k as f64 / rate;
                let x = 0.5 * libm::sin(2.0 * core::f64::consts::PI * 200.0 * t)
                    + 0.3
                        * (2.0 / core::f64::consts::PI)
                        * libm::asin(libm::sin(2.0 * core::f64::consts::PI * 90.0 * t));
                q[k] = signal_from_f64(x);
                qf[k] = signal_to_f64(q[k]);
            }
            let mut line = PreviewLine::at(q[0]);
            let mut worst = 0.0f64;
            for k in 0..n {
                let (target, shaped) = p.step(&mut line, q[k]);
                let back = k.saturating_sub(PREVIEW_DELAY_TICKS);
                assert_eq!(target, q[back], "{f} Hz at {rate}, tick {k}");
                let want = reference(&taps, &qf, k);
                if want.abs() < 0.99 {
                    worst = worst.max((signal_to_f64(shaped) - want).abs());
                }
            }
            // Within a few parts in 10⁷ of full scale (the taps' rounding on the motion).
            assert!(worst < 5e-7, "{f} Hz at {rate}: {worst}");
        }
    }

    #[test]
    fn the_shaped_drive_brings_the_held_resonance_to_the_setpoints_between_the_holds() {
        // The resonance held over each tick, exactly, from the recurrence; positions compared
        // with the cubic between the setpoints' middles, four ticks late.
        let (f, zeta, rate) = (3_500.0, 0.03, 50_000.0);
        let d = design(f, zeta);
        let h = HeldResonance::new(&d, rate).unwrap();
        let p = d.preview(rate).unwrap();
        let n = 3_000;
        // A 200 Hz triangle, ±0.6: corners every 125 ticks.
        let tri = |k: usize| {
            let x = k as f64 * 200.0 / rate;
            let ph = x - libm::floor(x);
            0.6 * (1.0 - 4.0 * (ph - 0.5).abs())
        };
        let s = |k: usize| signal_from_f64(tri(k));
        let mut line = PreviewLine::at(s(0));
        let (mut pos, mut pos1, mut r1) = (
            signal_to_f64(s(0)),
            signal_to_f64(s(0)),
            signal_to_f64(s(0)),
        );
        let mut worst_shaped = 0.0f64;
        let mut worst_raw = 0.0f64;
        let (mut raw, mut raw1, mut u1) = (pos, pos, pos);
        for k in 0..n - 4 {
            let (target, shaped) = p.step(&mut line, s(k));
            let r = signal_to_f64(shaped);
            let next = -h.a1 * pos - h.a2 * pos1 + h.b1 * r + h.b2 * r1;
            (pos1, pos, r1) = (pos, next, r);
            // Unshaped: the target itself held.
            let u = signal_to_f64(target);
            let next_raw = -h.a1 * raw - h.a2 * raw1 + h.b1 * u + h.b2 * u1;
            (raw1, raw, u1) = (raw, next_raw, u);
            if k > 200 {
                // The position at this hold's end is the trajectory between the middles of the
                // holds of the target and the one after it.
                let j = k - PREVIEW_DELAY_TICKS;
                let want = 0.5 * (tri(j) + tri(j + 1));
                worst_shaped = worst_shaped.max((pos - want).abs());
                worst_raw = worst_raw.max((raw - want).abs());
            }
        }
        // Unshaped, every corner rings; shaped, the corner is missed by a fraction of the change
        // of slope over a tick (0.019 here), a tenth of the ringing or less.
        assert!(
            worst_shaped < 0.1 * worst_raw,
            "{worst_shaped} vs {worst_raw}"
        );
        assert!(worst_shaped < 1e-3, "{worst_shaped} vs {worst_raw}");
    }

    #[test]
    fn a_design_the_ticks_cannot_run_is_refused() {
        assert_eq!(
            design(f64::NAN, 0.03).preview(50_000.0),
            Err(PreviewError::NotFinite)
        );
        assert_eq!(
            design(3_500.0, 0.03).preview(f64::INFINITY),
            Err(PreviewError::NotFinite)
        );
        assert_eq!(
            design(25_000.0, 0.03).preview(50_000.0),
            Err(PreviewError::FrequencyOutOfRange)
        );
        assert_eq!(
            design(-1.0, 0.03).preview(50_000.0),
            Err(PreviewError::FrequencyOutOfRange)
        );
        assert_eq!(
            design(3_500.0, 1.0).preview(50_000.0),
            Err(PreviewError::DampingOutOfRange)
        );
        assert_eq!(
            design(3_500.0, 0.0).preview(50_000.0),
            Err(PreviewError::DampingOutOfRange)
        );
        assert_eq!(
            design(1.0, 0.03).preview(100_000.0),
            Err(PreviewError::TooSlow)
        );
    }

    #[test]
    fn full_scale_steps_saturate_and_never_wrap() {
        let p = design(3_500.0, 0.03).preview(100_000.0).unwrap();
        let mut line = PreviewLine::at(-SIGNAL_ONE);
        for k in 0..40 {
            let s = if (k / 5) % 2 == 0 { i32::MAX } else { i32::MIN };
            let (target, shaped) = p.step(&mut line, s);
            assert!((-SIGNAL_ONE..SIGNAL_ONE).contains(&target));
            assert!((-SIGNAL_ONE..SIGNAL_ONE).contains(&shaped));
        }
    }
}
