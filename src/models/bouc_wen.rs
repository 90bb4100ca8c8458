//! Generalised (asymmetric) Bouc–Wen hysteresis in fixed point: the forward observer and the
//! compensator, exact per sample.
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
//! **Inverse (exact, per sample).** While `f < 1`, one step of the model is linear in `Δu`
//! in each direction: writing `Δu = s·m` (`s` the sign, `m ≥ 0`),
//! `y_k = y_{k−1} + (k + A − c·s·h_{k−1})·Δu`, the slope `g_s = k + A − c·s·h_{k−1}` with
//! `c` the factor of that direction and of the sign of `h`. For the desired `y_d` the
//! compensator takes `s = sign(y_d − y_{k−1})` and `m = |y_d − y_{k−1}| / g_s`, capped at
//! `1/c` (where `f` reaches 1 and the step stops being linear: a larger step is made over
//! several samples), clamps the drive to the input range, and advances its own model with
//! it (its own observer): the model's output lands on `y_d`, to the rounding, on every sample
//! the cap and the range leave alone, and a shortfall is made up on the next. So the drive
//! does not depend on how finely the target is sampled beyond what the discrete model itself
//! does, and nothing lags by a sample (an inverse `u = (y_d − δ − h_{k−1})/k` would miss by
//! one sample's change of `h` and feed that back). The division is one `VDIV.F32`, as
//! Duhem's ([`crate::fixed_point::magnitude_over_gain`]): host and board agree bit for bit.
//!
//! **Invertibility.** The slope `g_s` stays positive — the model is monotone, and the step
//! unique — when the hysteretic slope `|A − c·s·h|` stays below `k`; it is largest just after
//! a reversal from the other branch's saturation, `|A|·(1 + c_max/c_min)`
//! ([`BoucWenParams::inverse_loop_gain`] of `k`). The compensator refuses a model at
//! [`BOUC_WEN_MAX_INVERSE_LOOP_GAIN`] or above ([`ParamError::BoucWenNotInvertible`]); the
//! tick floors the slope at `k/16` besides, so that a state beyond the bound (after a
//! rounding) still gives a bounded step. The observer has no such limit.
//!
//! Formats: `u, y, δ, h, A` Q2.30 normalised; `k`, the slope `g_s` and the factors `β ± γ ± ψ`
//! Q8.24; the step caps `1/c` Q2.30;
//! the factor `f` Q2.30 in `[0, 1]`; products in `i64`, the update `h·(1 − f) + A·Δu`
//! summed in Q4.60 and brought back once, rounding toward −∞ and saturating.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, magnitude_over_gain, q60_to_signal_floor, saturate_i64,
    signal_from_f64, GAIN_FRAC_BITS, SIGNAL_FRAC_BITS, SIGNAL_ONE,
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
        let factor = |x: f64| gain_from_f64(x).max(1);
        Ok(Self {
            slope,
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

    /// The index of the factor `c` for a step falling (or not) from `state`: its direction
    /// and the sign of `h`.
    #[inline(always)]
    fn factor_index(falling: bool, state: &BoucWenState) -> usize {
        ((falling as usize) << 1) | ((state.h < 0) as usize)
    }

    /// Advances the hysteretic state to input `u` (Q2.30 normalised, clamped to full scale).
    #[inline(always)]
    fn advance(&self, state: &mut BoucWenState, u: i32) {
        let u = clamp_full_scale(u);
        // |Δu| ≤ 2; a full-range jump saturates 2^-30 short of 2 (QSUB).
        let du = u.saturating_sub(state.u);
        let c = self.factors[Self::factor_index(du < 0, state) & 3];
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

/// Bouc–Wen compensator, fixed point: per sample, the drive step that brings its own model's
/// output to the desired displacement (see the module doc), then its model advanced on it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InverseBoucWen {
    model: BoucWen,
    /// The floor of the step's slope `g_s`: `k/16`, Q8.24, at least one LSB.
    min_slope: i32,
    /// The largest drive step per sample for each factor (indexed as the factors): `1/c`,
    /// Q2.30, saturated just below 2: up to there `f = c·|Δu| ≤ 1` and the step is linear.
    max_steps: [i32; 4],
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
    /// Beyond [`BoucWenParams::validate`] and the fixed-point ranges, refuses a model that may
    /// not be monotone ([`BoucWenParams::inverse_loop_gain`] at or above
    /// [`BOUC_WEN_MAX_INVERSE_LOOP_GAIN`]) with [`ParamError::BoucWenNotInvertible`] on `a`.
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &BoucWenParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let model = BoucWen::new(params, scaling)?;
        // A NaN gain is refused too (validation already refused NaN inputs).
        let gain = params.inverse_loop_gain();
        if gain.is_nan() || gain >= BOUC_WEN_MAX_INVERSE_LOOP_GAIN {
            return Err(ParamError::BoucWenNotInvertible(BoucWenCoefficient::A));
        }
        // 1/c in Q2.30: 2^54 / c(Q8.24); c ≥ 1 LSB, the quotient saturated at i32::MAX.
        let max_steps = model.factors.map(|c| {
            ((1i64 << (SIGNAL_FRAC_BITS + GAIN_FRAC_BITS)) / i64::from(c.max(1)))
                .min(i32::MAX as i64) as i32
        });
        Ok(Self {
            model,
            min_slope: (model.slope >> 4).max(1),
            max_steps,
        })
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
        // Q2.30 in i64: |y_d| ≤ 1 and the model's output is saturated, so |r| < 3·2^30.
        let r = clamp_full_scale(y_desired) as i64 - m.output(state) as i64;
        if r == 0 {
            return state.u;
        }
        let falling = r < 0;
        let index = BoucWen::factor_index(falling, state) & 3;
        // The slope g_s = k + A − c·s·h, Q8.24: A (Q2.30) shifted down by 6, c·h (Q8.24 ×
        // Q2.30 < 2^62) by 30; |g_s| < 2^27, floored at k/16.
        let ch = (i64::from(m.factors[index]) * i64::from(state.h)) >> SIGNAL_FRAC_BITS;
        let g = i64::from(m.slope) + (i64::from(m.a) >> (SIGNAL_FRAC_BITS - GAIN_FRAC_BITS));
        let g = if falling { g + ch } else { g - ch }.max(i64::from(self.min_slope));
        let step = magnitude_over_gain(r.unsigned_abs(), g).min(self.max_steps[index]);
        let du = if falling { -step } else { step };
        let u = clamp_full_scale(state.u.saturating_add(du));
        m.advance(state, u);
        u
    }
}

/// The forward Bouc–Wen model (the observer) in the tick, cycles at 5 wait states (see
/// [`Hysteresis::cycles`]).
pub const BOUC_WEN_CYCLES: u32 = 88;

/// The Bouc–Wen compensator in the tick, cycles at 5 wait states: the forward step and the
/// step's slope and quotient before it (one `VDIV.F32` and its conversions, as Duhem's
/// inverse).
pub const INVERSE_BOUC_WEN_CYCLES: u32 = 175;

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
        INVERSE_BOUC_WEN_CYCLES
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

    /// The compensator driving its own model: the output lands on the desired one, to the
    /// rounding, on every sample, finely sampled or coarsely (steps of 5 % of the range, with
    /// reversals on both branches), well inside the step cap.
    #[test]
    fn the_inverse_tracks_its_own_model() {
        let s = scaling();
        let inv = InverseBoucWen::new(&asymmetric(), &s).unwrap();
        for (name, samples_per_period) in [("fine", 3_000.0), ("coarse", 40.0)] {
            let mut st = inv.model().relaxed(0);
            let mut plant = inv.model().relaxed(0);
            let mut worst = 0.0f64;
            for k in 0..20_000 {
                let phase = k as f64 / samples_per_period;
                // A triangle whose amplitude shrinks and grows: nested minor loops.
                let tri = 2.0 * (phase - libm::floor(phase + 0.5)).abs() * 2.0 - 1.0;
                let yd = 0.5 * tri * (0.6 + 0.4 * libm::cos(phase * 0.37));
                let u = inv.step(&mut st, q(yd));
                let y = inv.model().step(&mut plant, u);
                if k > 0 {
                    worst = worst.max((f(y) - yd).abs());
                }
            }
            assert_eq!(
                st, plant,
                "{name}: the compensator's state is the model's on its drive"
            );
            // Some tens of LSB of Q2.30 (one is 9.3e-10): the step's f32 quotient (24 bits of
            // a step up to 0.1) and the roundings. A compensator that lagged one sample would
            // miss by that sample's change of h, 1e-3 and more.
            assert!(worst < 3e-8, "{name}: {worst}");
        }
    }
}
