//! Notch filter at the stage resonance: a fixed-point biquad designed in the library from the
//! resonance frequency, its width and depth, and the control rate in use.
//!
//! The stage's first resonance (21.8 kHz differential, ζ ≈ 0.017, see the book, docs/src/reference/physics.md) sits close to the
//! Nyquist frequency of a 50 kHz tick. The feedback loop sees it amplified some 30 times; a
//! notch on the feedback error removes it from the loop, so the controller neither excites nor
//! sustains the ringing and its gains can go higher. The same notch on the feedforward (input
//! shaping, [`crate::config::settings::Settings::shaping`]) keeps the drive from exciting it in open
//! loop, where the learning feedforward runs ([`crate::services::learning`]).
//!
//! **Design.** The analog notch `H(s) = (s² + 2ζ_z ω₀ s + ω₀²) / (s² + 2ζ_p ω₀ s + ω₀²)` with
//! `ζ_p = 1 / (2Q)` and `ζ_z = depth · ζ_p` is mapped to the tick's rate by the bilinear
//! transform, prewarped so the notch lands exactly on `f` ([`NotchDesign::coefficients`]).
//! The bilinear transform maps the whole analog frequency axis onto `0 … f_s/2`, so the digital
//! filter keeps the analog magnitude: unity at DC and at Nyquist, at most 1 everywhere
//! (`depth ≤ 1`). A design that ignored the rate (an analog notch sampled naively) would put
//! the notch elsewhere and could amplify near Nyquist; this one cannot.
//!
//! **Fixed point.** Coefficients in Q2.30 (`|b₁|, |a₁| < 2`, the others ≤ 1), direct form I,
//! the products summed in `i64` (Q4.60) and rounded back to Q2.30. The input and the output
//! are limited to ±1 (full scale): that bounds the accumulator below 2^63 (see [`Notch::step`])
//! and costs nothing in use, because the feedback correction is limited far below full scale.
//! `b₁` is adjusted after rounding so that `b₀ + b₁ + b₂ = 1 + a₁ + a₂` exactly: the DC gain
//! is exactly 1, a filter settled at a constant ([`Notch::state_at`]) passes it bit for bit, and
//! from rest it settles within a few LSB of it (no offset creeping into the integrator).

use crate::fixed_point::{limit, saturate_i64, SIGNAL_FRAC_BITS, SIGNAL_ONE};
use crate::refusal::{Field, Refusal, Rule};

/// What the notch is to remove, in physical units.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NotchDesign {
    /// Centre frequency, Hz (the stage's resonance).
    pub frequency_hz: f64,
    /// Quality factor: centre frequency over the −3 dB width (0.1 … 50).
    pub q: f64,
    /// Gain at the centre, 0 (a full notch) … 1 (no notch); e.g. 0.1 for −20 dB.
    pub depth: f64,
}

/// Why a notch design was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum NotchError {
    /// A value is NaN or infinite.
    NotFinite,
    /// The centre frequency is not within 0.0005 … 0.49 of the control rate.
    FrequencyOutOfRange,
    /// The quality factor is outside 0.1 … 50.
    QOutOfRange,
    /// The depth is outside 0 … 1.
    DepthOutOfRange,
}

/// Biquad coefficients in `f64`, `a₀ = 1`:
/// `y_k = b₀x_k + b₁x_{k−1} + b₂x_{k−2} − a₁y_{k−1} − a₂y_{k−2}`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BiquadCoefficients {
    /// Feedforward coefficients `b₀, b₁, b₂`.
    pub b: [f64; 3],
    /// Feedback coefficients `a₁, a₂`.
    pub a: [f64; 2],
}

impl NotchDesign {
    /// The notch for a tick at `control_rate` Hz: bilinear transform of the analog notch,
    /// prewarped at the centre frequency.
    pub fn coefficients(&self, control_rate: f64) -> Result<BiquadCoefficients, NotchError> {
        let finite = [self.frequency_hz, self.q, self.depth, control_rate]
            .iter()
            .all(|v| v.is_finite());
        if !finite || control_rate <= 0.0 {
            return Err(NotchError::NotFinite);
        }
        let ratio = self.frequency_hz / control_rate;
        if !(0.0005..=0.49).contains(&ratio) {
            return Err(NotchError::FrequencyOutOfRange);
        }
        if !(0.1..=50.0).contains(&self.q) {
            return Err(NotchError::QOutOfRange);
        }
        if !(0.0..=1.0).contains(&self.depth) {
            return Err(NotchError::DepthOutOfRange);
        }
        // s → (z − 1) / (K (z + 1)) in units of ω₀, K = tan(π f / f_s) (prewarped).
        let k = tan_pi(ratio);
        let zeta_p = 0.5 / self.q;
        let zeta_z = self.depth * zeta_p;
        let k2 = k * k;
        let a0 = 1.0 + 2.0 * zeta_p * k + k2;
        Ok(BiquadCoefficients {
            b: [
                (1.0 + 2.0 * zeta_z * k + k2) / a0,
                2.0 * (k2 - 1.0) / a0,
                (1.0 - 2.0 * zeta_z * k + k2) / a0,
            ],
            a: [2.0 * (k2 - 1.0) / a0, (1.0 - 2.0 * zeta_p * k + k2) / a0],
        })
    }
}

/// A design's refusal on the settings' fields `[frequency, q, depth]` of the notch it
/// configures (the feedback's, `feedback.notch`, or the feedforward's, `shaping`).
pub fn refusal(d: &NotchDesign, e: NotchError, fields: [Field; 3]) -> Refusal {
    let [frequency, q, depth] = fields;
    match e {
        NotchError::NotFinite => {
            let field = if !d.frequency_hz.is_finite() {
                frequency
            } else if !d.q.is_finite() {
                q
            } else {
                depth
            };
            Refusal::new(field, Rule::NotFinite)
        }
        NotchError::FrequencyOutOfRange => Refusal::new(frequency, Rule::Unreachable),
        NotchError::QOutOfRange => Refusal::new(q, Rule::AtMost(50.0)),
        NotchError::DepthOutOfRange => Refusal::new(depth, Rule::AtMost(1.0)),
    }
}

/// `tan(π·r)` for `r` in `[0, 0.5)`, to within a few ULP of `f64`: reduced to `[0, π/4]`
/// (`tan(π r) = 1 / tan(π (½ − r))` above a quarter), then the sine and cosine series to
/// the 17th power (truncation below 2^-60 there). A dozen multiply-adds where `libm::tan`'s
/// general argument reduction would cost the firmware about 8 KiB of flash; the notch is
/// designed on the board, at its own control rate.
fn tan_pi(r: f64) -> f64 {
    let (x, invert) = if r > 0.25 {
        (core::f64::consts::PI * (0.5 - r), true)
    } else {
        (core::f64::consts::PI * r, false)
    };
    let x2 = x * x;
    // Horner forms of sin(x)/x and cos(x): Σ (−x²)^n / (2n+1)! and Σ (−x²)^n / (2n)!.
    let (mut sin, mut cos) = (0.0f64, 0.0f64);
    let mut n = 9;
    while n > 0 {
        let (s_den, c_den) = ((2 * n) * (2 * n + 1), (2 * n - 1) * (2 * n));
        sin = 1.0 - x2 / s_den as f64 * sin;
        cos = 1.0 - x2 / c_den as f64 * cos;
        n -= 1;
    }
    let t = x * sin / cos;
    if invert {
        1.0 / t
    } else {
        t
    }
}

impl BiquadCoefficients {
    /// Magnitude of the frequency response at `frequency_hz` for a tick at `control_rate` Hz.
    pub fn gain_at(&self, frequency_hz: f64, control_rate: f64) -> f64 {
        let w = 2.0 * core::f64::consts::PI * frequency_hz / control_rate;
        // Evaluate at z⁻¹ = e^{−jw}.
        let (c1, s1) = (libm::cos(w), -libm::sin(w));
        let (c2, s2) = (libm::cos(2.0 * w), -libm::sin(2.0 * w));
        let num = (
            self.b[0] + self.b[1] * c1 + self.b[2] * c2,
            self.b[1] * s1 + self.b[2] * s2,
        );
        let den = (
            1.0 + self.a[0] * c1 + self.a[1] * c2,
            self.a[0] * s1 + self.a[1] * s2,
        );
        libm::sqrt((num.0 * num.0 + num.1 * num.1) / (den.0 * den.0 + den.1 * den.1))
    }
}

/// The notch in fixed point: coefficients in Q2.30.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Notch {
    /// `b₀`, Q2.30.
    pub b0: i32,
    /// `b₁`, Q2.30 (adjusted for an exact unity DC gain).
    pub b1: i32,
    /// `b₂`, Q2.30.
    pub b2: i32,
    /// `a₁`, Q2.30.
    pub a1: i32,
    /// `a₂`, Q2.30.
    pub a2: i32,
}

/// The notch's memory: the last two inputs and outputs, Q2.30 (each within ±1).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct NotchState {
    x1: i32,
    x2: i32,
    y1: i32,
    y2: i32,
}

impl Notch {
    /// Designs the notch for a tick at `control_rate` Hz.
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(design: &NotchDesign, control_rate: f64) -> Result<Self, NotchError> {
        Ok(Self::from_coefficients(&design.coefficients(control_rate)?))
    }

    /// Rounds `c` to Q2.30. The coefficients of a valid notch design fit (`|b₁|, |a₁| < 2`,
    /// the others in `[0, 1]`); `b₁` absorbs the rounding so that the DC gain is exactly 1.
    pub fn from_coefficients(c: &BiquadCoefficients) -> Self {
        let q = |x: f64| crate::fixed_point::signal_from_f64(x);
        let (b0, b2, a1, a2) = (q(c.b[0]), q(c.b[2]), q(c.a[0]), q(c.a[1]));
        let b1 = saturate_i64(SIGNAL_ONE as i64 + a1 as i64 + a2 as i64 - b0 as i64 - b2 as i64);
        Self { b0, b1, b2, a1, a2 }
    }

    /// The state in which the filter has long seen the constant `x` (its output is then `x`):
    /// what a bumpless start needs.
    pub fn state_at(x: i32) -> NotchState {
        let x = limit(x, -SIGNAL_ONE, SIGNAL_ONE);
        NotchState {
            x1: x,
            x2: x,
            y1: x,
            y2: x,
        }
    }

    /// One sample: Q2.30 in, Q2.30 out, both limited to ±1.
    ///
    /// Accumulator bound: `|b₀| + |b₁| + |b₂| ≤ 4` on inputs `≤ 2^30`, `|a₁| + |a₂| < 3` on
    /// outputs `≤ 2^30`, all in Q2.30 coefficients: `< 7 · 2^60 < 2^63`.
    #[inline(always)]
    pub fn step(&self, s: &mut NotchState, x: i32) -> i32 {
        let x = limit(x, -SIGNAL_ONE, SIGNAL_ONE);
        let acc =
            self.b0 as i64 * x as i64 + self.b1 as i64 * s.x1 as i64 + self.b2 as i64 * s.x2 as i64
                - self.a1 as i64 * s.y1 as i64
                - self.a2 as i64 * s.y2 as i64;
        let y = saturate_i64((acc + (1 << (SIGNAL_FRAC_BITS - 1))) >> SIGNAL_FRAC_BITS);
        let y = limit(y, -SIGNAL_ONE, SIGNAL_ONE);
        s.x2 = s.x1;
        s.x1 = x;
        s.y2 = s.y1;
        s.y1 = y;
        y
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::signal_from_f64;

    /// The differential stage's resonance, as wide as the one in the demo.
    fn stage_notch() -> NotchDesign {
        NotchDesign {
            frequency_hz: 21_800.0,
            q: 2.0,
            depth: 0.0,
        }
    }

    #[test]
    fn the_notch_lands_on_its_frequency_at_every_rate_and_never_amplifies() {
        for rate in [50_000.0, 100_000.0] {
            let c = stage_notch().coefficients(rate).unwrap();
            assert!(
                c.gain_at(21_800.0, rate) < 1e-9,
                "{rate}: notch at 21.8 kHz"
            );
            assert!((c.gain_at(0.0, rate) - 1.0).abs() < 1e-12, "unity at DC");
            assert!(
                (c.gain_at(rate / 2.0, rate) - 1.0).abs() < 1e-9,
                "unity at Nyquist"
            );
            // At most 1 everywhere, in particular between the notch and Nyquist.
            for i in 0..=1000 {
                let f = rate / 2.0 * i as f64 / 1000.0;
                assert!(c.gain_at(f, rate) <= 1.0 + 1e-12, "{rate}: gain at {f} Hz");
            }
            // Width: Q = 2 puts the −3 dB points about f/2 apart.
            let g = c.gain_at(21_800.0 - 5_450.0 * 1.05, rate);
            assert!(g > 0.7, "{rate}: {g}");
        }
    }

    #[test]
    fn a_finite_depth_leaves_that_much_at_the_centre() {
        let d = NotchDesign {
            frequency_hz: 1_000.0,
            q: 1.0,
            depth: 0.1,
        };
        let c = d.coefficients(50_000.0).unwrap();
        assert!((c.gain_at(1_000.0, 50_000.0) - 0.1).abs() < 1e-9);
    }

    #[test]
    fn a_constant_passes_unchanged_and_the_state_at_it_is_steady() {
        let notch = Notch::new(&stage_notch(), 50_000.0).unwrap();
        for x in [
            0,
            1,
            -1,
            signal_from_f64(0.3),
            signal_from_f64(-0.77),
            SIGNAL_ONE,
        ] {
            let mut s = Notch::state_at(x);
            for _ in 0..10 {
                assert_eq!(notch.step(&mut s, x), x);
            }
            // From rest the output settles on the input to within the rounding's dead band
            // of a few LSB (1e-9 each): unity DC gain, no offset.
            let mut s = NotchState::default();
            let mut y = 0;
            for _ in 0..2000 {
                y = notch.step(&mut s, x);
            }
            assert!((y as i64 - x as i64).abs() <= 8, "{y} vs {x}");
        }
    }

    #[test]
    fn out_of_range_input_is_limited_not_wrapped() {
        let notch = Notch::new(&stage_notch(), 50_000.0).unwrap();
        let mut s = NotchState::default();
        for k in 0..1000 {
            let x = if k % 2 == 0 { i32::MAX } else { i32::MIN };
            let y = notch.step(&mut s, x);
            assert!((-SIGNAL_ONE..=SIGNAL_ONE).contains(&y));
        }
    }

    #[test]
    fn the_series_tangent_matches_libm() {
        for i in 0..=4900 {
            let r = i as f64 / 10_000.0;
            let (ours, libm) = (tan_pi(r), libm::tan(core::f64::consts::PI * r));
            assert!(
                (ours - libm).abs() <= 1e-14 * libm.abs().max(1.0), // far below Q2.30
                "r = {r}: {ours} vs {libm}"
            );
        }
    }

    #[test]
    fn designs_that_cannot_work_are_refused() {
        let ok = stage_notch();
        let bad = |f: fn(&mut NotchDesign)| {
            let mut d = ok;
            f(&mut d);
            d.coefficients(50_000.0).unwrap_err()
        };
        assert_eq!(
            bad(|d| d.frequency_hz = 25_000.0),
            NotchError::FrequencyOutOfRange
        );
        assert_eq!(
            bad(|d| d.frequency_hz = 0.0),
            NotchError::FrequencyOutOfRange
        );
        assert_eq!(bad(|d| d.q = 0.0), NotchError::QOutOfRange);
        assert_eq!(bad(|d| d.depth = 1.5), NotchError::DepthOutOfRange);
        assert_eq!(bad(|d| d.q = f64::NAN), NotchError::NotFinite);
        assert_eq!(
            ok.coefficients(f64::INFINITY).unwrap_err(),
            NotchError::NotFinite
        );
    }
}
