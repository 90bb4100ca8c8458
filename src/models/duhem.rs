//! Duhem hysteresis in fixed point: the forward observer and the inverse compensator.
//!
//! Model (normalised by [`Scaling`]): `ẏ = α |u̇| (β u + δ − y) + γ u̇`, discretised per sample
//! as in the book (docs/src/reference/models.md):
//!
//! `y_k = y_{k−1} + a_k (β u_{k−1} + δ − y_{k−1}) + γ Δu_k`, with `a_k = min(α |Δu_k|, 1)`.
//!
//! The clamp `a_k ≤ 1` is the discrete form's stability bound: beyond it a single large step
//! would overshoot the anhysteretic curve. At control rates (tens of kHz) `α |Δu|` is far below
//! 1 and the clamp never acts; it only keeps a step to the range limits bounded.
//!
//! Formats: `u, y, δ` Q2.30 normalised; `α, β, γ` Q8.24 normalised; the factor `a` Q2.30 in
//! [0, 1]; the distance to the anhysteretic curve `e = β u + δ − y` Q2.30, saturated at ±2
//! (it only reaches that for states far outside the range); products in `i64`.
//!
//! **Inverse.** Writing `Δu = s·m` (`s` the sign, `m ≥ 0`), one step of the model gives
//! `Δy = s·m·g_s` with `g_s = γ + s·α·e`, the local slope in direction `s`. For a desired
//! `Δy`, take `s = sign(Δy)` and `m = |Δy| / g_s`. The slope can approach zero (or turn
//! negative for parameters outside the physical set); it is floored at
//! `g_min = min(β, γ) / 16`, so `m` — and the drive — stay bounded, and the drive is clamped to
//! the input range. The inverse runs its own forward model on the drive it produced, so any
//! shortfall in one sample is made up in the next.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, magnitude_over_gain, q60_to_signal_floor, saturate_i64,
    signal_from_f64, GAIN_FRAC_BITS, SIGNAL_FRAC_BITS, SIGNAL_ONE,
};
use crate::models::params::{DuhemParams, ParamError};
use crate::models::{Forward, Hysteresis, Inverse};
use crate::scaling::Scaling;

/// Fraction of `min(β, γ)` below which the inverse's slope is floored.
pub const MIN_SLOPE_DIVISOR: i32 = 16;

/// State of a Duhem model: the previous input and output, Q2.30 normalised.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct DuhemState {
    /// Previous input `u_{k−1}`, Q2.30 normalised drive.
    pub u: i32,
    /// Previous output `y_{k−1}`, Q2.30 normalised displacement.
    pub y: i32,
}

/// Forward Duhem model, fixed point (the observer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Duhem {
    /// `α`, Q8.24 normalised (per input half-span).
    alpha: i32,
    /// `β`, Q8.24 normalised (output span per input span).
    beta: i32,
    /// `γ`, Q8.24 normalised (the inverse's slope).
    gamma: i32,
    /// `γ` again, Q2.30 (`gamma << 6`, exact; validation keeps `γ < 2`): the step's
    /// `γ·Δu` is then a Q2.30 × Q2.30 product like `a·e`, and both accumulate in Q4.60.
    gamma_q30: i32,
    /// `δ`, offset of the anhysteretic curve, Q2.30 normalised output.
    offset: i32,
    /// `1/α`, Q2.30 (saturated just below 2): the input step at which `a = α|Δu|` reaches 1.
    inverse_alpha: i32,
}

impl Duhem {
    /// Validates `params` (physical units) and converts them, normalised by `scaling`, into the
    /// fixed-point form the tick runs.
    ///
    /// ```
    /// use twinstack::models::duhem::Duhem;
    /// use twinstack::{DuhemParams, Scaling};
    /// let params = DuhemParams { alpha: 0.02, beta: 0.5, gamma: 0.35, offset: 0.0 };
    /// let model = Duhem::new(&params, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).unwrap();
    /// // On the anhysteretic curve β·u: 70 V (mid-range) puts the stage at 35 µm (mid-range).
    /// assert_eq!(model.anhysteretic(0), 0);
    /// assert!(Duhem::new(&DuhemParams { alpha: -1.0, ..params }, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).is_err());
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &DuhemParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let n = params.normalized(scaling)?;
        let alpha = gain_from_f64(n.alpha);
        // 1/α: 2^(30+24) / α(Q8.24) in Q2.30; 2.0 does not fit Q2.30, so saturate below it.
        let inverse_alpha = (1i64 << (SIGNAL_FRAC_BITS + GAIN_FRAC_BITS))
            .checked_div(alpha as i64)
            .unwrap_or(i64::MAX)
            .clamp(1, i32::MAX as i64) as i32;
        let gamma = gain_from_f64(n.gamma);
        Ok(Self {
            alpha,
            beta: gain_from_f64(n.beta),
            gamma,
            // γ < 2 (validated): the Q8.24 value is below 2^25, so the shift is exact.
            gamma_q30: gamma.saturating_mul(1 << (SIGNAL_FRAC_BITS - GAIN_FRAC_BITS)),
            offset: signal_from_f64(n.offset),
            inverse_alpha,
        })
    }

    /// State at input `u` and output `y` (both Q2.30 normalised).
    pub fn state_at(&self, u: i32, y: i32) -> DuhemState {
        DuhemState {
            u: clamp_full_scale(u),
            y,
        }
    }

    /// The anhysteretic curve at input `u` (Q2.30): `β u + δ`, where the model settles when the
    /// input comes to rest after a long excursion; the natural initial output.
    pub fn anhysteretic(&self, u: i32) -> i32 {
        let u = clamp_full_scale(u);
        saturate_i64(((self.beta as i64 * u as i64) >> GAIN_FRAC_BITS) + self.offset as i64)
    }

    /// Distance to the anhysteretic curve, `e = β u + δ − y`, Q2.30, saturated at ±2.
    /// Validation keeps `β + |δ| < 2` (normalised), so `β u + δ` fits Q2.30 exactly and only
    /// the final subtraction can saturate (a `QSUB` on the M4).
    #[inline(always)]
    fn anhysteretic_error(&self, state: &DuhemState) -> i32 {
        let beta_u = ((self.beta as i64 * state.u as i64) >> GAIN_FRAC_BITS) as i32;
        beta_u.wrapping_add(self.offset).saturating_sub(state.y)
    }

    /// One sample: input `u` (Q2.30 normalised drive, clamped to full scale) → estimated
    /// displacement (Q2.30 normalised, saturated).
    ///
    /// The update `y + a·e + γ·Δu` is summed in one Q4.60 accumulator (`y` shifted up by 30,
    /// `a·e` and `γ·Δu` Q2.30 × Q2.30 products, one `SMLAL` each) and brought back to Q2.30
    /// once, rounding toward −∞ and saturating ([`q60_to_signal_floor`]): one rounding per
    /// step. This is bit for bit the Q10.54 sum `(y << 24) + (a·e >> 6) + γ₂₄·Δu` shifted
    /// down by 24 (`⌊(64X + ae)/2^30⌋ = ⌊(X + ⌊ae/64⌋)/2^24⌋`), without the shift of `a·e`.
    #[inline(always)]
    pub fn step(&self, state: &mut DuhemState, u: i32) -> i32 {
        let u = clamp_full_scale(u);
        // |Δu| ≤ 2; a full-range jump saturates 2^-30 short of 2 (QSUB).
        let du = u.saturating_sub(state.u);
        let magnitude = du.unsigned_abs();
        // a = min(α|Δu|, 1), Q2.30: below 1/α the product is < 2^54 and fits after the shift;
        // there |Δu| < 1/α < 2, so it is a non-negative i32 and a signed multiply serves.
        let a = if magnitude >= self.inverse_alpha as u32 {
            SIGNAL_ONE
        } else {
            ((self.alpha as i64 * magnitude as i32 as i64) >> GAIN_FRAC_BITS) as i32
        };
        let e = self.anhysteretic_error(state);
        // |y·2^30| ≤ 2^61, |a·e| ≤ 2^61, |γ·Δu| < 2^62: the sum fits i64.
        let acc = ((state.y as i64) << SIGNAL_FRAC_BITS)
            + a as i64 * e as i64
            + self.gamma_q30 as i64 * du as i64;
        state.u = u;
        state.y = q60_to_signal_floor(acc);
        state.y
    }
}

/// Inverse Duhem compensator, fixed point: per sample, the drive increment that produces the
/// desired displacement increment.
///
/// One sample's drive step `m` is capped at `1/α`: up to there the discrete model is exactly
/// linear in `Δu` (`α|Δu| ≤ 1`, so `a` does not clamp) and the step lands on the target or
/// short of it; beyond it `a` clamps, the step overshoots, and a large setpoint step would
/// ping-pong between the range ends for ever. A larger step is made over several samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InverseDuhem {
    model: Duhem,
    /// Floor of the slope `g_s`, Q8.24, `> 0`.
    min_slope: i32,
    /// Largest drive step per sample, `min(1/α, 2 − 2^-30)`, Q2.30.
    max_step: i32,
}

impl InverseDuhem {
    /// Validates `params` and builds the compensator for them, normalised by `scaling`.
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &DuhemParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let model = Duhem::new(params, scaling)?;
        let min_slope = (model.beta.min(model.gamma) / MIN_SLOPE_DIVISOR).max(1);
        Ok(Self {
            model,
            min_slope,
            max_step: model.inverse_alpha,
        })
    }

    /// The forward model the compensator inverts.
    pub fn model(&self) -> &Duhem {
        &self.model
    }

    /// One sample: desired displacement `y_d` (Q2.30 normalised, clamped to [-1, 1]) → drive
    /// (Q2.30 normalised, within [-1, 1]). `state` is the compensator's own forward model.
    #[inline(always)]
    pub fn step(&self, state: &mut DuhemState, y_desired: i32) -> i32 {
        let dy = clamp_full_scale(y_desired) as i64 - state.y as i64;
        if dy == 0 {
            return state.u;
        }
        let e = self.model.anhysteretic_error(state) as i64;
        let alpha_e = (self.model.alpha as i64 * e) >> SIGNAL_FRAC_BITS; // Q8.24
        let slope = if dy > 0 {
            self.model.gamma as i64 + alpha_e
        } else {
            self.model.gamma as i64 - alpha_e
        }
        .max(self.min_slope as i64);
        // m = |Δy| / g, Q2.30; the slope is at least min_slope ≥ 1.
        let m = magnitude_over_gain(dy.unsigned_abs(), slope);
        let m = (m as i64).min(self.max_step as i64);
        let du = if dy > 0 { m } else { -m };
        let u = clamp_full_scale(saturate_i64(state.u as i64 + du));
        self.model.step(state, u);
        u
    }
}

/// A Duhem model in the tick (either direction), cycles at 5 wait states (see
/// [`Hysteresis::cycles`]).
pub const DUHEM_CYCLES: u32 = 170;

impl Hysteresis for Duhem {
    type State = DuhemState;

    #[inline(always)]
    fn step(&self, state: &mut DuhemState, u: i32) -> i32 {
        Duhem::step(self, state, u)
    }

    fn cycles(&self) -> u32 {
        DUHEM_CYCLES
    }
}

impl Forward for Duhem {
    /// On the anhysteretic curve, where the model settles after a long excursion.
    fn relaxed(&self, u: i32) -> (DuhemState, i32) {
        let y = self.anhysteretic(u);
        (self.state_at(u, y), y)
    }
}

impl Hysteresis for InverseDuhem {
    type State = DuhemState;

    #[inline(always)]
    fn step(&self, state: &mut DuhemState, y: i32) -> i32 {
        InverseDuhem::step(self, state, y)
    }

    fn cycles(&self) -> u32 {
        DUHEM_CYCLES
    }
}

impl Inverse for InverseDuhem {
    fn relaxed(&self, u: i32, _y: i32) -> DuhemState {
        Forward::relaxed(self.model(), u).0
    }

    /// The observer's state, where it runs this compensator's model.
    type Forward = Duhem;

    fn matching(&self, forward: &Duhem, state: &DuhemState) -> Option<DuhemState> {
        (forward == self.model()).then_some(*state)
    }
}
