//! Duhem hysteresis in fixed point: the forward observer and the inverse compensator.
//!
//! Model (normalised by [`Scaling`]): `ẏ = α |u̇| (β u + δ − y) + γ u̇`. On a monotone stretch
//! of input (direction `s`) the distance to the anhysteretic curve, `e = β u + δ − y`,
//! relaxes in the input: `de/du = (β − γ) − s·α·e`. The model takes that exactly over each
//! sample's step `Δu` (`m = |Δu|`), as in the book (docs/src/reference/models.md):
//!
//! `y_k = y_{k−1} + β·Δu_k + q_k·e_{k−1} − s·(β − γ)·φ_k`, with `q_k = 1 − e^{−α m}`,
//! `φ_k = q_k/α`
//!
//! ([`crate::models::relaxation`]). Integrated in the input, not stepped per sample, the
//! model's output depends on the path of the input alone, not on the sample rate: the same
//! drive sampled at 10 kHz or 100 kHz gives the same output (the physics is rate-independent,
//! and a model identified from a record at one rate runs at the board's). For small steps
//! `q ≈ α m`, `φ ≈ m` and this is the explicit step `y + α|Δu|·e + γ·Δu`.
//!
//! Formats: `u, y, δ` Q2.30 normalised; `α, β, γ` Q8.24 normalised; `q` Q0.32 and `φ` Q1.31
//! (rounded to nearest from `f32`); the distance `e` Q2.30, saturated at ±2 (it only reaches
//! that for states far outside the range); the update summed in Q10.54 (`i64`) and brought
//! back to Q2.30 once, rounding to nearest.
//!
//! **Inverse.** For a desired `Δy` in direction `s = sign(Δy)`, the step `m` with
//! `β·m + D·q(α m) = |Δy|`, `D = (γ − β)/α + s·e` the distance to the curve's target that
//! way: the linear guess `|Δy|/g_s`, `g_s = γ + s·α·e` the local slope, and one Newton step
//! ([`RelaxationRate::solve`]). The slope can approach zero (or turn negative for parameters
//! outside the physical set); it is floored at `g_min = min(β, γ) / 16`, so `m` — and the
//! drive — stay bounded; a step is capped at `0.99/α` (a larger one is made over several
//! samples), and the drive is clamped to the input range. The inverse runs its own forward
//! model on the drive it produced, so any shortfall in one sample is made up in the next.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, q54_to_signal_floor, saturate_i64, signal_from_f64,
    GAIN_FRAC_BITS, SIGNAL_FRAC_BITS,
};
use crate::models::params::{DuhemParams, ParamError};
use crate::models::relaxation::{RelaxationRate, SIGNAL_TO_F32, STEP_CAP};
use crate::models::{Forward, Hysteresis, Inverse, Rest};
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
    /// `β − γ`, Q8.24 (both below 2, validated: exact).
    beta_minus_gamma: i32,
    /// `δ`, offset of the anhysteretic curve, Q2.30 normalised output.
    offset: i32,
    /// `α` as the relaxation's rate, with `1/α`.
    rate: RelaxationRate,
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
        let alpha = gain_from_f64(n.alpha).max(1);
        let beta = gain_from_f64(n.beta);
        let gamma = gain_from_f64(n.gamma);
        Ok(Self {
            alpha,
            beta,
            gamma,
            beta_minus_gamma: beta - gamma,
            offset: signal_from_f64(n.offset),
            rate: RelaxationRate::from_gain(alpha),
        })
    }

    /// State at input `u` and output `y` (both Q2.30 normalised).
    pub fn state_at(&self, u: i32, y: i32) -> DuhemState {
        DuhemState {
            u: clamp_full_scale(u),
            y,
        }
    }

    /// The state of a stage at rest at input `u` (Q2.30 normalised): on its major loop's
    /// ascending branch, as every model starts ([`crate::models::rest_history`]: on the
    /// anhysteretic curve at the range's top, cycled over the range, taken to its bottom,
    /// then raised to `u`). Off the tick.
    pub fn state_at_rest(&self, u: i32) -> DuhemState {
        let top = crate::fixed_point::FULL_SCALE_MAX;
        let mut state = self.state_at(top, self.anhysteretic(top));
        crate::models::rest_history(u, |v| {
            self.step(&mut state, v);
        });
        state
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
    /// The update `β·Δu + q·e − s·(β − γ)·φ` is summed with `y` in one Q10.54 accumulator
    /// (`β·Δu` a Q8.24 × Q2.30 product, `q·e` Q0.32 × Q2.30 shifted down by 8, `(β − γ)·φ`
    /// Q8.24 × Q1.31 shifted down by 1) and brought back to Q2.30 once, rounding to nearest.
    #[inline(always)]
    pub fn step(&self, state: &mut DuhemState, u: i32) -> i32 {
        let u = clamp_full_scale(u);
        // |Δu| ≤ 2; a full-range jump saturates 2^-30 short of 2 (QSUB).
        let du = u.saturating_sub(state.u);
        let relaxed = self.rate.relax(du.unsigned_abs());
        let e = self.anhysteretic_error(state);
        // |β·Δu| < 2^25·2^31, |q·e| < 2^32·2^31, |(β − γ)·φ| < 2^25·2^32: the sum of the
        // three, shifted to Q10.54, and y·2^24 (< 2^55) fits i64.
        let pull = (self.beta_minus_gamma as i64 * relaxed.phi_q31() as i64) >> 1;
        let acc = ((state.y as i64) << GAIN_FRAC_BITS)
            + self.beta as i64 * du as i64
            + ((e as i64 * relaxed.q_q32() as i64) >> 8)
            + if du < 0 { pull } else { -pull };
        state.u = u;
        state.y = q54_to_signal_floor(acc + (1 << (GAIN_FRAC_BITS - 1)));
        state.y
    }
}

/// Inverse Duhem compensator, fixed point: per sample, the drive step that brings its own
/// model's output to the desired displacement (see the module doc), then its model advanced
/// on it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InverseDuhem {
    model: Duhem,
    /// `β`, `f32` bits: the output's slope in the input beside the relaxation.
    beta: u32,
    /// `(γ − β)/α`, `f32` bits: the distance to the anhysteretic curve the rising branch
    /// relaxes to, less `e`.
    shift: u32,
    /// Floor of the slope `g_s`, `min(β, γ)/16`, `f32` bits, `> 0`.
    min_slope: u32,
    /// Largest drive step per sample, `min(0.99/α, 2 − 2^-30)` ([`STEP_CAP`]), `f32` bits.
    max_step: u32,
}

impl InverseDuhem {
    /// Validates `params` and builds the compensator for them, normalised by `scaling`.
    ///
    /// ```
    /// use twinstack::models::duhem::InverseDuhem;
    /// use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
    /// use twinstack::{DuhemParams, Scaling};
    /// let params = DuhemParams { alpha: 0.02, beta: 0.5, gamma: 0.35, offset: 0.0 };
    /// let inverse = InverseDuhem::new(&params, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).unwrap();
    /// let mut state = inverse.model().state_at(0, 0);
    /// // From rest at mid-range, ask for a tenth of the span more: its own model lands there.
    /// let u = inverse.step(&mut state, signal_from_f64(0.1));
    /// assert!(signal_to_f64(u) > 0.1);
    /// assert!((signal_to_f64(state.y) - 0.1).abs() < 1e-6);
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &DuhemParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let model = Duhem::new(params, scaling)?;
        let to_f32 = |q24: i32| q24 as f32 / (1u32 << GAIN_FRAC_BITS) as f32;
        let min_slope = (model.beta.min(model.gamma) / MIN_SLOPE_DIVISOR).max(1);
        let max_step = (STEP_CAP * model.rate.reciprocal())
            .min(2.0 - (1.0 / (1u32 << SIGNAL_FRAC_BITS) as f32));
        Ok(Self {
            model,
            beta: to_f32(model.beta).to_bits(),
            shift: (-to_f32(model.beta_minus_gamma) * model.rate.reciprocal()).to_bits(),
            min_slope: to_f32(min_slope).to_bits(),
            max_step: max_step.to_bits(),
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
        let e = self.model.anhysteretic_error(state) as f32 * SIGNAL_TO_F32;
        let shift = f32::from_bits(self.shift);
        // D = (γ − β)/α + s·e; |Δy| < 3·2^30 fits u32.
        let d = if dy > 0 { shift + e } else { shift - e };
        let target = dy.unsigned_abs() as u32 as f32 * SIGNAL_TO_F32;
        let m = self.model.rate.solve(
            f32::from_bits(self.beta),
            d,
            f32::from_bits(self.min_slope),
            target,
            f32::from_bits(self.max_step),
        );
        let du = if dy > 0 { m } else { -m };
        let u = clamp_full_scale(state.u.saturating_add(du));
        self.model.step(state, u);
        u
    }
}

/// The forward Duhem model (the observer) in the tick, cycles at 5 wait states (see
/// [`Hysteresis::cycles`]): the relaxation's polynomial (one call) and the Q10.54 update.
pub const DUHEM_CYCLES: u32 = 150;

/// The Duhem compensator in the tick, cycles at 5 wait states: the step solved (the linear
/// guess, the relaxation at it and one Halley step: two `VDIV.F32`s), the forward step, and
/// the call that keeps its floating-point registers out of the tick's prologue
/// (`Running::step_out_of_line`; the floating-point context it costs the tick is charged
/// apart: `config::tick_budget::FP_CONTEXT_CYCLES`).
pub const INVERSE_DUHEM_CYCLES: u32 = 380;

impl Hysteresis for Duhem {
    type State = DuhemState;

    #[inline(always)]
    fn step(&self, state: &mut DuhemState, u: i32) -> i32 {
        Duhem::step(self, state, u)
    }

    fn cycles(&self) -> u32 {
        DUHEM_CYCLES
    }

    /// Its relaxation is computed in `f32` ([`crate::models::relaxation`]).
    fn uses_fpu(&self) -> bool {
        true
    }
}

impl Forward for Duhem {
    /// On the loop ([`Duhem::state_at_rest`]) or on the anhysteretic curve
    /// ([`Duhem::anhysteretic`]).
    fn at_rest(&self, u: i32, rest: Rest) -> (DuhemState, i32) {
        let s = match rest {
            Rest::Ascending => self.state_at_rest(u),
            Rest::Relaxed => self.state_at(u, self.anhysteretic(u)),
        };
        (s, s.y)
    }
}

impl Hysteresis for InverseDuhem {
    type State = DuhemState;

    #[inline(always)]
    fn step(&self, state: &mut DuhemState, y: i32) -> i32 {
        InverseDuhem::step(self, state, y)
    }

    fn cycles(&self) -> u32 {
        INVERSE_DUHEM_CYCLES
    }

    /// Its relaxation is computed in `f32` ([`crate::models::relaxation`]).
    fn uses_fpu(&self) -> bool {
        true
    }
}

impl Inverse for InverseDuhem {
    fn at_rest(&self, u: i32, _y: i32, rest: Rest) -> DuhemState {
        Forward::at_rest(self.model(), u, rest).0
    }

    /// The observer's state, where it runs this compensator's model.
    type Forward = Duhem;

    fn matching(&self, forward: &Duhem, state: &DuhemState) -> Option<DuhemState> {
        (forward == self.model()).then_some(*state)
    }
}
