//! Generalised (asymmetric) Bouc–Wen hysteresis in fixed point: the forward observer and the
//! inverse-multiplicative compensator.
//!
//! Model (normalised by [`Scaling`], as [`crate::models::duhem`]): `y = k·u + δ + h`, with the
//! hysteretic state advanced per sample by
//!
//! `h_k = h_{k−1} + A·Δu_k − β·|Δu_k|·h_{k−1} − γ·Δu_k·|h_{k−1}| − ψ·Δu_k·h_{k−1}`
//!
//! (exponent `n = 1`; `β, γ` the classical terms, `ψ` the asymmetric one). The last three terms
//! are one factor times `h`: `h_k = (1 − f_k)·h_{k−1} + A·Δu_k` with
//! `f_k = min(c·|Δu_k|, 1)` and `c = β + s·sgn(h)·γ + s·ψ` (`s` the sign of `Δu`): one of the
//! four constants `β ± γ ± ψ`, precomputed. Validation ([`BoucWenParams::validate`]) keeps all
//! four positive (`|γ| < β`, `|ψ| < β − |γ|`), so `f ≥ 0`; the clamp `f ≤ 1` is the discrete
//! form's stability bound, as Duhem's `min(α|Δu|, 1)`. At control rates `c·|Δu|` is far below 1.
//!
//! **Bound.** From rest (`h = 0`), `|h| ≤ H = |A|·max(1/(β − |γ| − |ψ|), 2)`: a step with
//! `f < 1` gives `|h'| ≤ (1 − f)H + |A||Δu| ≤ H` because `f ≥ (β − |γ| − |ψ|)|Δu|`, and one with
//! `f = 1` gives `h' = A·Δu`, `|Δu| ≤ 2`. Validation keeps `H ≤ 1.9` normalised
//! ([`crate::models::params::BOUC_WEN_MAX_NORM_STATE`]), so `h` never reaches the Q2.30 saturation.
//!
//! **Duhem** is the special case `γ = ψ = 0`: with `k = β_D`, `A = γ_D − β_D`, `β = α_D` and
//! `h = y − β_D u − δ` (minus Duhem's distance `e` to the anhysteretic curve), this step is
//! Duhem's `y_k = y_{k−1} + a_k·e_{k−1} + γ_D·Δu_k`, sample for sample
//! ([`BoucWenParams::from_duhem`]).
//!
//! **Inverse (multiplicative).** `u_k = (y_d,k − δ − h_{k−1})·(1/k)`, with `1/k` precomputed
//! off the tick, clamped to the input range; the compensator then advances its own `h` with
//! the `u_k` it produced (its own observer). No division on the tick, constant time, bounded by
//! construction: `|u_k| ≤ (1 + |δ| + H)/k` before the clamp. The output it obtains is
//! `y_k = y_d,k + (h_k − h_{k−1})`: the error is one sample's change of `h`,
//! `|A·Δu − f·h| ≤ (|A| + c_max·|h|)·|Δu|`.
//!
//! **Stability of the compensator's loop.** A perturbation `ε` of `h` moves the next drive by
//! `−ε/k`, which moves `h` by the local hysteretic slope `∂h/∂u = A − c·s·h` times that: the
//! loop gain is `|A − c·s·h|/k`, largest just after a reversal from the other branch's
//! saturation, `|A|·(1 + c_max/c_min)/k` ([`BoucWenParams::inverse_loop_gain`]). At 1 or
//! more the drive would chatter from sample to sample (still within its bound); the
//! compensator refuses such a model ([`ParamError::BoucWenNotInvertible`], at
//! [`BOUC_WEN_MAX_INVERSE_LOOP_GAIN`]). The observer has no such limit. (With the factor
//! `f` the loop's characteristic equation is `z² − (1 − f − r)z − r = 0`, `r` the gain: stable
//! for `r < 1 − f/2`. At control rates `f` is of order 1e-4; only a jump across the whole
//! range in one sample, which the drive's slew limit prevents, brings it near 1.)
//!
//! Formats: `u, y, δ, h, A` Q2.30 normalised; `k, 1/k` and the factors `β ± γ ± ψ` Q8.24;
//! the factor `f` Q2.30 in `[0, 1]`; products in `i64`, the update `h·(1 − f) + A·Δu`
//! summed in Q4.60 and brought back once, rounding toward −∞ and saturating.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, q60_to_signal_floor, saturate_i64, signal_from_f64,
    GAIN_FRAC_BITS, SIGNAL_ONE,
};
use crate::models::params::{
    BoucWenCoefficient, BoucWenParams, ParamError, BOUC_WEN_MAX_INVERSE_LOOP_GAIN,
};
use crate::models::{Forward, Hysteresis, Inverse};
use crate::scaling::Scaling;

/// State of a Bouc–Wen model: the previous input and the hysteretic state, Q2.30 normalised.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct BoucWenState {
    /// Previous input `u_{k−1}`, Q2.30 normalised drive.
    pub u: i32,
    /// Hysteretic state `h_{k−1}`, Q2.30 normalised displacement.
    pub h: i32,
}

/// Forward Bouc–Wen model, fixed point (the observer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BoucWen {
    /// `k`, Q8.24 normalised (output span per input span), in `[1/64, 2)`.
    slope: i32,
    /// `1/k`, Q8.24, at most 64 (`2^30`): the compensator's multiplier.
    inverse_slope: i32,
    /// `δ`, Q2.30 normalised output.
    offset: i32,
    /// `A`, Q2.30 normalised (`|A| < 2`), so that `A·Δu` is a Q2.30 × Q2.30 product.
    a: i32,
    /// The factors multiplying `h·|Δu|`, Q8.24, each at least one LSB: index
    /// `(Δu < 0)·2 + (h < 0)`: `β+γ+ψ`, `β−γ+ψ`, `β−γ−ψ`, `β+γ−ψ`.
    factors: [i32; 4],
}

impl BoucWen {
    /// Validates `params` (physical units) and converts them, normalised by `scaling`, into the
    /// fixed-point form the tick runs.
    ///
    /// ```
    /// use twinstack::models::bouc_wen::BoucWen;
    /// use twinstack::{BoucWenParams, Scaling};
    /// let params = BoucWenParams { k: 0.45, offset: 0.0, a: 0.08, beta: 0.03, gamma: 0.01, psi: 0.005 };
    /// let scaling = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
    /// let model = BoucWen::new(&params, &scaling).unwrap();
    /// // Relaxed (h = 0) at mid-range: k·70 V = 31.5 µm, 3.5 µm below the 35 µm mid-output.
    /// let y = model.output(&model.relaxed(0));
    /// assert!((twinstack::fixed_point::signal_to_f64(y) + 0.1).abs() < 1e-6);
    /// assert!(BoucWen::new(&BoucWenParams { gamma: 0.05, ..params }, &scaling).is_err());
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &BoucWenParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let n = params.normalized(scaling)?;
        let slope = gain_from_f64(n.k);
        // 1/k: 2^48 / k(Q8.24) in Q8.24, rounded; k ≥ 1/64 (validated) keeps it ≤ 2^30.
        let inverse_slope = ((1i64 << (2 * GAIN_FRAC_BITS)) + (slope as i64 >> 1))
            .checked_div(slope as i64)
            .unwrap_or(i64::MAX)
            .clamp(1, i32::MAX as i64) as i32;
        let factor = |x: f64| gain_from_f64(x).max(1);
        Ok(Self {
            slope,
            inverse_slope,
            offset: signal_from_f64(n.offset),
            a: signal_from_f64(n.a),
            factors: [
                factor(n.beta + n.gamma + n.psi),
                factor(n.beta - n.gamma + n.psi),
                factor(n.beta - n.gamma - n.psi),
                factor(n.beta + n.gamma - n.psi),
            ],
        })
    }

    /// The relaxed state at input `u` (Q2.30 normalised): `h = 0`, the output on the line
    /// `k·u + δ`.
    pub fn relaxed(&self, u: i32) -> BoucWenState {
        BoucWenState {
            u: clamp_full_scale(u),
            h: 0,
        }
    }

    /// The output in `state`: `k·u + δ + h`, Q2.30 normalised, saturated.
    #[inline(always)]
    pub fn output(&self, state: &BoucWenState) -> i32 {
        // |k·u| < 2^31·2^31 before the shift; the sum of three Q2.30 terms fits i64.
        saturate_i64(
            ((self.slope as i64 * state.u as i64) >> GAIN_FRAC_BITS)
                + self.offset as i64
                + state.h as i64,
        )
    }

    /// Advances the hysteretic state to input `u` (Q2.30 normalised, clamped to full scale).
    #[inline(always)]
    fn advance(&self, state: &mut BoucWenState, u: i32) {
        let u = clamp_full_scale(u);
        // |Δu| ≤ 2; a full-range jump saturates 2^-30 short of 2 (QSUB).
        let du = u.saturating_sub(state.u);
        let index = (((du < 0) as usize) << 1) | ((state.h < 0) as usize);
        let c = self.factors[index & 3];
        // f = min(c·|Δu|, 1), Q2.30: c (Q8.24, < 2^31) × |Δu| (< 2^31) < 2^62; c ≥ 1, so
        // f ≥ 0.
        let f = ((c as i64 * du.unsigned_abs() as i64) >> GAIN_FRAC_BITS).min(SIGNAL_ONE as i64);
        // |h·(1 − f)| ≤ 2^61 (0 ≤ 1 − f ≤ 2^30), |A·Δu| < 2^62: the Q4.60 sum fits i64.
        let acc = state.h as i64 * (SIGNAL_ONE as i64 - f) + self.a as i64 * du as i64;
        state.h = q60_to_signal_floor(acc);
        state.u = u;
    }

    /// One sample: input `u` (Q2.30 normalised drive, clamped to full scale) → estimated
    /// displacement (Q2.30 normalised, saturated).
    #[inline(always)]
    pub fn step(&self, state: &mut BoucWenState, u: i32) -> i32 {
        self.advance(state, u);
        self.output(state)
    }
}

/// Inverse-multiplicative Bouc–Wen compensator, fixed point: `u = (y_d − δ − h)·(1/k)`, then
/// its own model advanced on that `u` (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InverseBoucWen {
    model: BoucWen,
}

impl InverseBoucWen {
    /// Validates `params` and builds the compensator for them, normalised by `scaling`.
    ///
    /// ```
    /// use twinstack::models::bouc_wen::InverseBoucWen;
    /// use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
    /// use twinstack::{BoucWenParams, Scaling};
    /// let params = BoucWenParams { k: 0.45, offset: 0.0, a: 0.08, beta: 0.03, gamma: 0.01, psi: 0.005 };
    /// let inverse = InverseBoucWen::new(&params, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).unwrap();
    /// let mut state = inverse.model().relaxed(0);
    /// // From rest at 70 V (31.5 µm), ask for 40 µm: the drive rises, within the range.
    /// let u = inverse.step(&mut state, signal_from_f64(5.0 / 35.0));
    /// assert!(signal_to_f64(u) > 0.0 && signal_to_f64(u) < 1.0);
    /// ```
    ///
    /// Beyond [`BoucWenParams::validate`] and the fixed-point ranges, refuses a model whose
    /// compensator loop would oscillate ([`BoucWenParams::inverse_loop_gain`] at or above
    /// [`BOUC_WEN_MAX_INVERSE_LOOP_GAIN`]) with [`ParamError::BoucWenNotInvertible`] on `a`.
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &BoucWenParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let model = BoucWen::new(params, scaling)?;
        // A NaN gain is refused too (validation already refused NaN inputs).
        let gain = params.inverse_loop_gain();
        if gain.is_nan() || gain >= BOUC_WEN_MAX_INVERSE_LOOP_GAIN {
            return Err(ParamError::BoucWenNotInvertible(BoucWenCoefficient::A));
        }
        Ok(Self { model })
    }

    /// The forward model the compensator inverts (its observer).
    pub fn model(&self) -> &BoucWen {
        &self.model
    }

    /// One sample: desired displacement `y_d` (Q2.30 normalised, clamped to full scale) →
    /// drive (Q2.30 normalised, within full scale). `state` is the compensator's own forward
    /// model, advanced with the drive returned.
    #[inline(always)]
    pub fn step(&self, state: &mut BoucWenState, y_desired: i32) -> i32 {
        let m = &self.model;
        // Q2.30 in i64: |y_d| ≤ 1, |δ| ≤ 1.5, |h| < 2, so |r| < 4.5·2^30; × 1/k (≤ 2^30) < 2^63.
        let r = clamp_full_scale(y_desired) as i64 - m.offset as i64 - state.h as i64;
        let u = clamp_full_scale(saturate_i64((r * m.inverse_slope as i64) >> GAIN_FRAC_BITS));
        m.advance(state, u);
        u
    }
}

/// A Bouc–Wen model in the tick (either direction), cycles at 5 wait states (see
/// [`Hysteresis::cycles`]).
pub const BOUC_WEN_CYCLES: u32 = 88;

impl Hysteresis for BoucWen {
    type State = BoucWenState;

    #[inline(always)]
    fn step(&self, state: &mut BoucWenState, u: i32) -> i32 {
        BoucWen::step(self, state, u)
    }

    fn cycles(&self) -> u32 {
        BOUC_WEN_CYCLES
    }
}

impl Forward for BoucWen {
    /// Relaxed (`h = 0`) at `u`.
    fn relaxed(&self, u: i32) -> (BoucWenState, i32) {
        let s = BoucWen::relaxed(self, u);
        (s, self.output(&s))
    }
}

impl Hysteresis for InverseBoucWen {
    type State = BoucWenState;

    #[inline(always)]
    fn step(&self, state: &mut BoucWenState, y: i32) -> i32 {
        InverseBoucWen::step(self, state, y)
    }

    fn cycles(&self) -> u32 {
        BOUC_WEN_CYCLES
    }
}

impl Inverse for InverseBoucWen {
    /// Its own model relaxed (`h = 0`) at the present drive.
    fn relaxed(&self, u: i32, _y: i32) -> BoucWenState {
        BoucWen::relaxed(self.model(), u)
    }

    /// The observer's state, where it runs this compensator's model.
    type Forward = BoucWen;

    fn matching(&self, forward: &BoucWen, state: &BoucWenState) -> Option<BoucWenState> {
        (forward == self.model()).then_some(*state)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64 as q, signal_to_f64 as f};
    use crate::models::duhem::Duhem;
    use crate::models::params::DuhemParams;

    fn scaling() -> Scaling {
        Scaling::new(0.0, 140.0, -5.0, 75.0).unwrap()
    }

    fn asymmetric() -> BoucWenParams {
        BoucWenParams {
            k: 0.42,
            offset: 1.0,
            a: 0.1,
            beta: 0.04,
            gamma: 0.008,
            psi: 0.006,
        }
    }

    /// The Duhem special case runs the same discrete model: the outputs agree to a few LSB
    /// of Q2.30 (the two round differently) over a long random-walk drive.
    #[test]
    fn duhem_is_the_special_case_gamma_psi_zero() {
        let d = DuhemParams {
            alpha: 0.02,
            beta: 0.5,
            gamma: 0.35,
            offset: 2.0,
        };
        let s = Scaling::new(0.0, 140.0, -20.0, 90.0).unwrap();
        let duhem = Duhem::new(&d, &s).unwrap();
        let bw = BoucWen::new(&BoucWenParams::from_duhem(&d), &s).unwrap();
        let mut ds = duhem.state_at(0, duhem.anhysteretic(0));
        let mut bs = bw.relaxed(0);
        assert!((duhem.anhysteretic(0) - bw.output(&bs)).abs() <= 1);
        let mut u = 0.0f64;
        let mut seed = 99u32;
        let mut worst = 0i64;
        for _ in 0..20_000 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            u = (u + ((seed >> 8) as f64 / (1u32 << 24) as f64 - 0.5) * 0.02).clamp(-1.0, 1.0);
            let a = duhem.step(&mut ds, q(u));
            let b = bw.step(&mut bs, q(u));
            worst = worst.max((a as i64 - b as i64).abs());
        }
        assert!(worst < 1 << 12, "{worst} LSB of Q2.30");
    }

    #[test]
    fn psi_makes_the_rising_and_falling_branches_differ() {
        let s = scaling();
        let loop_height = |psi: f64| {
            let m = BoucWen::new(
                &BoucWenParams {
                    psi,
                    ..asymmetric()
                },
                &s,
            )
            .unwrap();
            let mut st = m.relaxed(q(-1.0));
            let mut rising_h = 0;
            let mut falling_h = 0;
            for _ in 0..3 {
                for k in 0..=2000 {
                    let u = -1.0 + 2.0 * k as f64 / 2000.0;
                    m.step(&mut st, q(u));
                }
                rising_h = st.h;
                for k in 0..=2000 {
                    let u = 1.0 - 2.0 * k as f64 / 2000.0;
                    m.step(&mut st, q(u));
                }
                falling_h = st.h;
            }
            (f(rising_h), f(falling_h))
        };
        let (r0, f0) = loop_height(0.0);
        assert!((r0 + f0).abs() < 1e-3, "symmetric without ψ: {r0} {f0}");
        // Rising, h saturates at A/(β+γ+ψ); falling at −A/(β+γ−ψ).
        let n = asymmetric().normalized(&s).unwrap();
        let expected = n.a / (n.beta + n.gamma + n.psi) - n.a / (n.beta + n.gamma - n.psi);
        let (r1, f1) = loop_height(asymmetric().psi);
        assert!(expected < -0.01, "{expected}");
        assert!(
            (r1 + f1 - expected).abs() < 0.05 * expected.abs(),
            "ψ: {r1} + {f1} against {expected}"
        );
    }

    /// Whatever the drive (steps across the whole range included), `|h|` stays within the
    /// documented bound `|A|·max(1/(β − |γ| − |ψ|), 2)`.
    #[test]
    fn the_state_stays_within_its_bound() {
        let s = scaling();
        let p = asymmetric();
        let bound = p.normalized(&s).unwrap().state_bound();
        let m = BoucWen::new(&p, &s).unwrap();
        let mut st = m.relaxed(0);
        let mut seed = 5u32;
        let mut worst = 0.0f64;
        for _ in 0..50_000 {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            m.step(&mut st, seed as i32);
            worst = worst.max(f(st.h).abs());
        }
        assert!(worst <= bound + 1e-6, "{worst} > {bound}");
        assert!(
            worst > 0.5 * bound,
            "the drive exercised the state: {worst}"
        );
    }

    /// The compensator driving its own model: the output is the desired one but for one
    /// sample's change of `h`.
    #[test]
    fn the_inverse_tracks_its_own_model() {
        let s = scaling();
        let inv = InverseBoucWen::new(&asymmetric(), &s).unwrap();
        let mut st = inv.model().relaxed(0);
        let mut plant = inv.model().relaxed(0);
        let mut worst = 0.0f64;
        for k in 0..20_000 {
            let yd = 0.5 * libm::sin(k as f64 * 2e-3);
            let u = inv.step(&mut st, q(yd));
            let y = inv.model().step(&mut plant, u);
            if k > 10 {
                worst = worst.max((f(y) - yd).abs());
            }
        }
        assert_eq!(
            st, plant,
            "the compensator's state is the model's on its drive"
        );
        // One sample's Δh at this rate: about |A|·|Δu| ≈ 0.175 · 1e-3 / 0.735.
        assert!(worst < 1e-3, "{worst}");
    }
}
