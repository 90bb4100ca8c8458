//! Generalised (asymmetric) Bouc–Wen hysteresis in fixed point: the forward observer and the
//! compensator, both integrated exactly in the input.
//!
//! Model (normalised by [`Scaling`], as [`crate::models::duhem`]): `y = k·u + δ + h`, with the
//! hysteretic state
//!
//! `dh = A·du − β·|du|·h − γ·du·|h| − ψ·du·h − χ·|du|·|h|`
//!
//! (exponent `n = 1`; `β, γ` the classical terms, `ψ` and `χ` the asymmetric ones). The last
//! four terms are one factor times `h`: on a monotone stretch of input (direction `s`) with
//! `h` of one sign, `dh/dm = s·A − c·h` (`m = |Δu|`), `c = β + s·sgn(h)·γ + s·ψ + sgn(h)·χ`
//! ([`BoucWenParams::factor`]) one of four constants `β ± γ ± ψ ± χ`, set independently by the
//! four coefficients and precomputed: `h` relaxes toward `h* = s·A/c`. The model takes that
//! exactly over each sample's step ([`crate::models::relaxation`]):
//!
//! `h_k = h_{k−1} − q_k·h_{k−1} + s·A·φ_k`, `q_k = 1 − e^{−c·m}`, `φ_k = q_k/c`,
//!
//! with `c` chosen by the direction and the sign of `h_{k−1}` (at `h_{k−1} = 0`, the sign `h`
//! takes on the step, that of `s·A`: the rate is continuous in `h`). Integrated in the input, the
//! output depends on the path of the drive, not on the sample rate: a sample whose step
//! carries `h` through zero is split where it crosses, the rest taken from zero at the other
//! sign's rate ([`BoucWen::step`]). For small steps `q ≈ c·m`, `φ ≈ m`
//! and this is the explicit step `h + A·Δu − c·|Δu|·h`. Validation
//! ([`BoucWenParams::validate`]) keeps all four factors positive (without `χ`: `|γ| < β`,
//! `|ψ| < β − |γ|`).
//!
//! **Bound.** From rest (`h = 0`), `|h| ≤ H = |A|/c_min` (`c_min` the least factor): each step moves `h` a
//! fraction `q ≤ 1` of the way to `h*`, `|h*| ≤ H`. Validation keeps `H ≤ 1.9` normalised
//! ([`crate::models::params::BOUC_WEN_MAX_NORM_STATE`]), so `h` never reaches the Q2.30
//! saturation.
//!
//! **Duhem** is the special case `γ = ψ = χ = 0`: with `k = β_D`, `A = γ_D − β_D`, `β = α_D` and
//! `h = y − β_D u − δ` (minus Duhem's distance `e` to the anhysteretic curve), this step is
//! Duhem's, to the rounding ([`BoucWenParams::from_duhem`]).
//!
//! **Inverse.** For the desired `y_d` the compensator takes `s = sign(y_d − y_{k−1})` and the
//! step `m` with `k·m + D·q(c·m) = |y_d − y_{k−1}|`, `D = A/c − s·h_{k−1}` (the distance to
//! `h*` that way): the linear guess over the slope `g_s = k + A − c·s·h_{k−1}` and one Newton
//! step ([`RelaxationRate::solve`]), capped at `0.99/c` (a larger step is made over several
//! samples); it clamps the drive to the input range and advances its own model with it (its
//! own observer): the model's output lands on `y_d` to within the Newton step's
//! `O((c·m)²)` of the step, and a shortfall is made up on the next sample. So the drive does
//! not depend on how finely the target is sampled, and nothing lags by a sample (an inverse
//! `u = (y_d − δ − h_{k−1})/k` would miss by one sample's change of `h` and feed that back).
//! The quotients are `VDIV.F32`s, as in Duhem's inverse: host and board agree bit for bit.
//!
//! **Invertibility.** The slope `g_s` stays positive — the model is monotone, and the step
//! unique — when the hysteretic slope `A − c·s·h` never falls to `−k`. With `A ≥ 0` it is never
//! negative; with `A < 0` it is most negative just after a reversal from the other branch's
//! saturation, `−|A|·(1 + c/c')` with `c` the new direction's rate and `c'` the saturated
//! branch's, both at that sign of `h` ([`BoucWenParams::inverse_loop_gain`] of `k`). The compensator refuses a model at
//! [`BOUC_WEN_MAX_INVERSE_LOOP_GAIN`] or above ([`ParamError::BoucWenNotInvertible`]); the
//! tick floors the slope at `k/16` besides, so that a state beyond the bound (after a
//! rounding) still gives a bounded step. The observer has no such limit.
//!
//! Formats: `u, y, δ, h, A` Q2.30 normalised; `k` and the factors `β ± γ ± ψ ± χ` Q8.24; `q`
//! Q0.32 and `φ` Q1.31 (rounded to nearest from `f32`); the update `h − q·h + s·A·φ` summed
//! in Q4.60 (`i64`) and brought back once, rounding to nearest and saturating.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, q60_to_signal_floor, saturate_i64, signal_from_f64,
    FULL_SCALE_MAX, GAIN_FRAC_BITS, SIGNAL_FRAC_BITS,
};
use crate::models::generalised_pi::{DeadZoneBank, DEAD_ZONE_MAP_CYCLES};
use crate::models::output_map::OutputMap;
use crate::models::params::{
    BoucWenCoefficient, BoucWenParams, ParamError, BOUC_WEN_MAX_INVERSE_LOOP_GAIN,
};
use crate::models::relaxation::{
    magnitude, smaller, to_signal, RelaxationRate, Relaxed, SIGNAL_TO_F32, STEP_CAP,
};
use crate::models::{Forward, Hysteresis, Inverse, Rest};
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
    /// `A`, Q2.30 normalised (`|A| < 2`), so that `A·φ` is a Q2.30 × Q1.31 product.
    a: i32,
    /// The relaxation rates `c` (from the Q8.24 factors, each at least one LSB): index
    /// `(Δu < 0)·2 + (h < 0)`: `β+γ+ψ+χ`, `β−γ+ψ−χ`, `β−γ−ψ+χ`, `β+γ−ψ−χ`.
    rates: [RelaxationRate; 4],
    /// `1/A`, `f32` bits (0 for `A = 0`, where `h` never crosses zero).
    a_reciprocal: u32,
    /// The static output map `S` after the model, if any ([`crate::models::output_map`]): the
    /// model's output is `S(k·u + δ + h)`.
    map: Option<DeadZoneBank>,
}

impl BoucWen {
    /// Validates `params` (physical units) and converts them, normalised by `scaling`, into the
    /// fixed-point form the tick runs.
    ///
    /// ```
    /// use twinstack::models::bouc_wen::BoucWen;
    /// use twinstack::{BoucWenParams, Scaling};
    /// let params = BoucWenParams { k: 0.45, offset: 0.0, a: 0.08, beta: 0.03, gamma: 0.01, psi: 0.005, chi: 0.002 };
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
        let rate = |x: f64| RelaxationRate::from_gain(gain_from_f64(x).max(1));
        let a = signal_from_f64(n.a);
        let a_f32 = a as f32 * SIGNAL_TO_F32;
        Ok(Self {
            slope: gain_from_f64(n.k),
            offset: signal_from_f64(n.offset),
            a,
            a_reciprocal: if a == 0 { 0.0f32 } else { 1.0 / a_f32 }.to_bits(),
            rates: n.factors().map(rate),
            map: None,
        })
    }

    /// The same model followed by the static output map `map` (`None`: none): its output is
    /// `S(k·u + δ + h)` ([`crate::models::output_map`]). Off the tick.
    pub fn with_output_map(self, map: Option<&OutputMap>) -> Self {
        Self {
            map: map.map(|m| *m.forward_bank()),
            ..self
        }
    }

    /// Whether an output map follows the model.
    pub fn has_output_map(&self) -> bool {
        self.map.is_some()
    }

    /// The relaxed state at input `u` (Q2.30 normalised): `h = 0`, the output on the line
    /// `k·u + δ`.
    pub fn relaxed(&self, u: i32) -> BoucWenState {
        BoucWenState {
            u: clamp_full_scale(u),
            h: 0,
        }
    }

    /// The state of a stage at rest at input `u` (Q2.30 normalised): on its major loop's
    /// ascending branch, as every model starts ([`crate::models::rest_history`]: relaxed at
    /// the range's top, cycled over the range, taken to its bottom, then raised to `u`).
    /// Off the tick.
    pub fn state_at_rest(&self, u: i32) -> BoucWenState {
        let mut state = self.relaxed(FULL_SCALE_MAX);
        crate::models::rest_history(u, |v| self.advance(&mut state, v));
        state
    }

    /// The model's own output in `state`, before any output map: `k·u + δ + h`, Q2.30
    /// normalised, saturated.
    #[inline(always)]
    pub fn output(&self, state: &BoucWenState) -> i32 {
        // |k·u| < 2^31·2^31 before the shift; the sum of three Q2.30 terms fits i64.
        saturate_i64(
            ((self.slope as i64 * state.u as i64) >> GAIN_FRAC_BITS)
                + self.offset as i64
                + state.h as i64,
        )
    }

    /// The index of the rate `c` for a step falling (or not) from `state`: its direction
    /// and the sign of `h` — at `h = 0`, the sign `h` takes on the step (that of `s·A`), so
    /// that the rate is continuous in `h`: a state a rounding above zero and one a rounding
    /// below it relax alike.
    #[inline(always)]
    fn factor_index(&self, falling: bool, state: &BoucWenState) -> usize {
        let negative = state.h < 0 || (state.h == 0 && falling != (self.a < 0));
        ((falling as usize) << 1) | (negative as usize)
    }

    /// Advances the hysteretic state to input `u` (Q2.30 normalised, clamped to full scale).
    #[inline(always)]
    fn advance(&self, state: &mut BoucWenState, u: i32) {
        self.advance_knowing(state, u, None);
    }

    /// [`BoucWen::advance`], given where a state heading across zero reaches it (`to_zero`,
    /// the input from here to zero at this step's rate, normalised) where the caller has it
    /// already: the compensator computes it to solve its step, and does not take the
    /// logarithm again. The same state either way.
    ///
    /// A step whose relaxation carries `h` past zero is split where it crosses, the rest taken
    /// from zero at the other sign's rate ([`BoucWen::past_zero`]). A step no longer than the
    /// way to zero that a rounding carries a hair past it ends at zero: what the split would
    /// give for a rest of nothing, without relaxing over it.
    #[inline(always)]
    fn advance_knowing(&self, state: &mut BoucWenState, u: i32, to_zero: Option<f32>) {
        let u = clamp_full_scale(u);
        // |Δu| ≤ 2; a full-range jump saturates 2^-30 short of 2 (QSUB).
        let du = u.saturating_sub(state.u);
        let falling = du < 0;
        let index = self.factor_index(falling, state) & 3;
        let h = self.relaxed_by(state.h, self.rates[index].relax(du.unsigned_abs()), falling);
        // A sign change: h crossed zero within the step, past which the other rate holds.
        state.h = if (h ^ state.h) < 0 && state.h != 0 {
            let rate = &self.rates[index];
            let to_zero = match to_zero {
                Some(m) => m,
                None => rate.step_to_cover(self.crossing_ratio(state.h, rate)),
            };
            let m = du.unsigned_abs() as f32 * SIGNAL_TO_F32;
            if m > to_zero {
                self.past_zero(m - to_zero, index, falling)
            } else {
                0
            }
        } else {
            h
        };
        state.u = u;
    }

    /// Advances to `u` on a step the compensator found to pass zero `to_zero` (normalised)
    /// into it at rate `index`, the step longer than that (what [`BoucWen::advance`] would
    /// find again): from zero, at the other sign's rate, over the rest.
    #[inline(always)]
    fn advance_past_zero(&self, state: &mut BoucWenState, u: i32, rest: f32, index: usize) {
        state.h = self.past_zero(rest, index, u < state.u);
        state.u = u;
    }

    /// `h` relaxed over one step: `h − q·h + s·A·φ`, Q2.30 rounded to nearest.
    #[inline(always)]
    fn relaxed_by(&self, h: i32, relaxed: Relaxed, falling: bool) -> i32 {
        // Q4.60: h·2^30 and q·h (Q2.30 × Q0.32, shifted down by 2) below 2^61 (|h| < 2),
        // A·φ (Q2.30 × Q1.31, shifted down by 1) below 2^62: the sum fits i64.
        let pull = (self.a as i64 * relaxed.phi_q31() as i64) >> 1;
        let acc = ((h as i64) << SIGNAL_FRAC_BITS) - ((h as i64 * relaxed.q_q32() as i64) >> 2)
            + if falling { -pull } else { pull };
        q60_to_signal_floor(acc + (1 << (SIGNAL_FRAC_BITS - 1)))
    }

    /// The state after a step at rate `index` that carries `h` through zero, `rest`
    /// (normalised, positive) beyond it: from zero, over the rest, at the rate of the other
    /// sign.
    #[inline(never)] // a crossing of zero only, once per branch
    fn past_zero(&self, rest: f32, index: usize, falling: bool) -> i32 {
        let relaxed = self.rates[index ^ 1].relax_normalised(rest);
        self.relaxed_by(0, relaxed, falling)
    }

    /// `w = −h/h*` for a state `h` heading across zero toward its target `h* = s·A/c` at
    /// `rate` (the two of opposite signs): `|h|·c/|A|`.
    #[inline(always)]
    fn crossing_ratio(&self, h: i32, rate: &RelaxationRate) -> f32 {
        magnitude(h as f32 * SIGNAL_TO_F32)
            * rate.rate()
            * magnitude(f32::from_bits(self.a_reciprocal))
    }

    /// The output in `state`, the output map applied where there is one (Q2.30 normalised,
    /// saturated).
    #[inline(always)]
    pub fn mapped_output(&self, state: &BoucWenState) -> i32 {
        let z = self.output(state);
        match &self.map {
            Some(m) => m.apply(z),
            None => z,
        }
    }

    /// One sample: input `u` (Q2.30 normalised drive, clamped to full scale) → estimated
    /// displacement (Q2.30 normalised, saturated), through the output map where there is one.
    #[inline(always)]
    pub fn step(&self, state: &mut BoucWenState, u: i32) -> i32 {
        self.advance(state, u);
        self.mapped_output(state)
    }
}

/// Bouc–Wen compensator, fixed point: per sample, the drive step that brings its own model's
/// output to the desired displacement (see the module doc), then its model advanced on it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InverseBoucWen {
    model: BoucWen,
    /// `k`, `f32` bits.
    slope: u32,
    /// The floor of the step's slope: `k/16`, `f32` bits, at least one Q8.24 LSB.
    min_slope: u32,
    /// `A/c` for each rate (indexed as the rates), `f32` bits: `h*` rising.
    targets: [u32; 4],
    /// The largest drive step per sample for each rate: `0.99/c` ([`STEP_CAP`]), below 2,
    /// `f32` bits.
    max_steps: [u32; 4],
    /// The output map's inverse `S⁻¹`, run on the desired displacement before the model's
    /// inverse, where the model has a map.
    inverse_map: Option<DeadZoneBank>,
}

impl InverseBoucWen {
    /// Validates `params` and builds the compensator for them, normalised by `scaling`.
    ///
    /// ```
    /// use twinstack::models::bouc_wen::InverseBoucWen;
    /// use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
    /// use twinstack::{BoucWenParams, Scaling};
    /// let params = BoucWenParams { k: 0.45, offset: 0.0, a: 0.08, beta: 0.03, gamma: 0.01, psi: 0.005, chi: 0.002 };
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
        let slope = model.slope as f32 / (1u32 << GAIN_FRAC_BITS) as f32;
        let a = model.a as f32 * SIGNAL_TO_F32;
        let below_two = 2.0 - SIGNAL_TO_F32;
        Ok(Self {
            model,
            slope: slope.to_bits(),
            min_slope: ((model.slope >> 4).max(1) as f32 / (1u32 << GAIN_FRAC_BITS) as f32)
                .to_bits(),
            targets: model.rates.map(|r| (a * r.reciprocal()).to_bits()),
            max_steps: model
                .rates
                .map(|r| (STEP_CAP * r.reciprocal()).min(below_two).to_bits()),
            inverse_map: None,
        })
    }

    /// The compensator of the model followed by the output map `map` (`None`: none): the
    /// map's inverse runs on the desired displacement first (`y → S⁻¹ → H⁻¹`), and its own
    /// model carries the map (so that it matches an observer with the same). Off the tick.
    pub fn with_output_map(self, map: Option<&OutputMap>) -> Self {
        Self {
            model: self.model.with_output_map(map),
            inverse_map: map.map(|m| *m.inverse_bank()),
            ..self
        }
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
        // Through the output map's inverse: what the model itself is to give.
        let y_desired = match &self.inverse_map {
            Some(map) => map.apply(clamp_full_scale(y_desired)),
            None => y_desired,
        };
        // Q2.30 in i64: |y_d| ≤ 1 and the model's output is saturated, so |r| < 3·2^30.
        let r = clamp_full_scale(y_desired) as i64 - m.output(state) as i64;
        if r == 0 {
            return state.u;
        }
        let falling = r < 0;
        let index = m.factor_index(falling, state) & 3;
        // D = A/c − s·h.
        let h = state.h as f32 * SIGNAL_TO_F32;
        let target = f32::from_bits(self.targets[index]);
        let d = if falling { target + h } else { target - h };
        let (slope, floor) = (f32::from_bits(self.slope), f32::from_bits(self.min_slope));
        let reach = r.unsigned_abs() as u32 as f32 * SIGNAL_TO_F32;
        let rate = &m.rates[index];
        let cap = f32::from_bits(self.max_steps[index]);
        // `h` heads across zero (its target `s·A/c` of the other sign, `s·h·A < 0`): where it
        // reaches zero (the input from here to zero), which the solve and the advance both
        // take, so that no step relaxes twice or takes the logarithm twice.
        let toward = if falling { h } else { -h };
        let to_zero =
            (toward * target > 0.0).then(|| rate.step_to_cover(m.crossing_ratio(state.h, rate)));
        let step = match to_zero {
            // The output change wanted is more than reaching zero gives (`k·m' + |h|`): the
            // step passes zero, the rest at the other sign's rate.
            Some(to_zero) if reach > slope * to_zero + toward => {
                let other = index ^ 1;
                let rest = m.rates[other].solve_normalised(
                    slope,
                    f32::from_bits(self.targets[other]),
                    floor,
                    reach - (slope * to_zero + toward),
                    // Both parts within the polynomial's range: the whole step at the first
                    // rate, the rest at the other's.
                    smaller(f32::from_bits(self.max_steps[other]), cap - to_zero),
                );
                to_signal(to_zero + rest)
            }
            _ => rate.solve(slope, d, floor, reach, cap),
        };
        let du = if falling { -step } else { step };
        let u = clamp_full_scale(state.u.saturating_add(du));
        // Split by the drive as it is sent (rounded, and clamped to the range), not as it was
        // solved: a step solved to stop short of zero that its rounding carries past is split
        // too, and one solved to pass zero that the range cuts short is not.
        let rest = match to_zero {
            Some(to_zero) => {
                u.saturating_sub(state.u).unsigned_abs() as f32 * SIGNAL_TO_F32 - to_zero
            }
            None => 0.0,
        };
        if rest > 0.0 {
            m.advance_past_zero(state, u, rest, index);
        } else {
            m.advance_knowing(state, u, to_zero);
        }
        u
    }
}

/// The forward Bouc–Wen model (the observer) in the tick, cycles at 5 wait states (see
/// [`Hysteresis::cycles`]).
pub const BOUC_WEN_CYCLES: u32 = 480;

/// The Bouc–Wen compensator in the tick, cycles at 5 wait states: the forward step and the
/// step's slope and quotient before it (one `VDIV.F32` and its conversions, as Duhem's
/// inverse), and the call that keeps its floating-point registers out of the tick's prologue
/// (`Running::step_out_of_line`; the floating-point context it costs the tick is charged
/// apart: `config::tick_budget::FP_CONTEXT_CYCLES`).
pub const INVERSE_BOUC_WEN_CYCLES: u32 = 625;

impl Hysteresis for BoucWen {
    type State = BoucWenState;

    #[inline(always)]
    fn step(&self, state: &mut BoucWenState, u: i32) -> i32 {
        BoucWen::step(self, state, u)
    }

    fn cycles(&self) -> u32 {
        BOUC_WEN_CYCLES + self.map.map_or(0, |_| DEAD_ZONE_MAP_CYCLES)
    }

    /// Its relaxation is computed in `f32` ([`crate::models::relaxation`]).
    fn uses_fpu(&self) -> bool {
        true
    }
}

impl Forward for BoucWen {
    /// On the loop ([`BoucWen::state_at_rest`]) or relaxed (`h = 0`, [`BoucWen::relaxed`]).
    fn at_rest(&self, u: i32, rest: Rest) -> (BoucWenState, i32) {
        let s = match rest {
            Rest::Ascending => self.state_at_rest(u),
            Rest::Relaxed => BoucWen::relaxed(self, u),
        };
        (s, self.mapped_output(&s))
    }
}

impl Hysteresis for InverseBoucWen {
    type State = BoucWenState;

    #[inline(always)]
    fn step(&self, state: &mut BoucWenState, y: i32) -> i32 {
        InverseBoucWen::step(self, state, y)
    }

    fn cycles(&self) -> u32 {
        INVERSE_BOUC_WEN_CYCLES + self.inverse_map.map_or(0, |_| DEAD_ZONE_MAP_CYCLES)
    }

    /// Its relaxation is computed in `f32` ([`crate::models::relaxation`]).
    fn uses_fpu(&self) -> bool {
        true
    }
}

impl Inverse for InverseBoucWen {
    /// Its own model at rest at the present drive.
    fn at_rest(&self, u: i32, _y: i32, rest: Rest) -> BoucWenState {
        Forward::at_rest(self.model(), u, rest).0
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

    /// Uniform numbers in `[0, 1)` from a xorshift generator seeded with `seed`.
    fn uniform(mut seed: u64) -> impl FnMut() -> f64 {
        move || {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            (seed >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    fn asymmetric() -> BoucWenParams {
        BoucWenParams {
            k: 0.42,
            offset: 1.0,
            a: 0.1,
            beta: 0.04,
            gamma: 0.008,
            psi: 0.006,
            chi: 0.002,
        }
    }

    /// With an output map, the observer's output is the map of the model's, the compensator
    /// runs the map's inverse on the desired displacement first and then what it ran without
    /// it, its own model carries the map (so it matches an observer with the same, and not
    /// one without), and each declares the map's cost.
    #[test]
    fn an_output_map_follows_the_model_and_its_inverse_comes_first() {
        use crate::models::output_map::DeadZoneParams;
        let s = scaling();
        let params = DeadZoneParams::new(
            35.0,
            1.02,
            &[-30.0, -15.0, 15.0, 30.0],
            &[-0.03, -0.02, -0.02, -0.04],
        )
        .unwrap();
        let map = OutputMap::new(&params, &s).unwrap();
        let plain = BoucWen::new(&asymmetric(), &s).unwrap();
        let mapped = plain.with_output_map(Some(&map));
        assert!(mapped.has_output_map() && !plain.has_output_map());
        assert_eq!(
            Hysteresis::cycles(&mapped),
            Hysteresis::cycles(&plain) + DEAD_ZONE_MAP_CYCLES
        );
        let inverse = InverseBoucWen::new(&asymmetric(), &s).unwrap();
        let inverse_mapped = inverse.with_output_map(Some(&map));
        assert_eq!(inverse_mapped.model(), &mapped);
        assert_eq!(
            Hysteresis::cycles(&inverse_mapped),
            Hysteresis::cycles(&inverse) + DEAD_ZONE_MAP_CYCLES
        );
        let (mut a, y0) = Forward::at_rest(&mapped, q(-0.3), Rest::Ascending);
        let (mut b, z0) = Forward::at_rest(&plain, q(-0.3), Rest::Ascending);
        assert_eq!((a, y0), (b, map.forward(z0)));
        let mut c = Inverse::at_rest(&inverse_mapped, q(-0.3), y0, Rest::Ascending);
        let mut d = c;
        let mut next = uniform(7);
        let mut bent = false;
        for k in 0..3000 {
            let u = q(2.0 * next() - 1.0);
            assert_eq!(
                mapped.step(&mut a, u),
                map.forward(plain.step(&mut b, u)),
                "{k}"
            );
            let y = q(1.8 * next() - 0.9);
            let target = map.inverse(y);
            bent |= target != y;
            let drive = inverse_mapped.step(&mut c, y);
            assert_eq!(drive, inverse.step(&mut d, target), "{k}");
            assert_eq!(c, d, "{k}");
        }
        assert!(bent, "the map bends the targets");
        // The compensator's state carries over from an observer with the same map only.
        let state = BoucWenState {
            u: q(0.1),
            h: q(0.02),
        };
        assert_eq!(inverse_mapped.matching(&mapped, &state), Some(state));
        assert_eq!(inverse_mapped.matching(&plain, &state), None);
        assert_eq!(inverse.matching(&mapped, &state), None);
    }

    /// At rest is on the major loop's ascending branch, as the board prepares it: one more
    /// cycle over the range changes nothing, the state lies where the major loop's rising
    /// branch passes `u` (not the falling one's), and both the observer and the compensator
    /// start there; the Duhem special case rests where its Duhem does.
    #[test]
    fn at_rest_is_on_the_major_loop_rising() {
        use crate::fixed_point::SIGNAL_ONE;
        let s = scaling();
        let m = BoucWen::new(&asymmetric(), &s).unwrap();
        let bottom = m.state_at_rest(-SIGNAL_ONE);
        let mut again = bottom;
        m.advance(&mut again, FULL_SCALE_MAX);
        m.advance(&mut again, -SIGNAL_ONE);
        assert!(
            (again.h - bottom.h).abs() <= 4,
            "{again:?} against {bottom:?}"
        );
        // Rising to mid-range from the bottom, against falling to it from the top.
        let rising = m.state_at_rest(0);
        let mut falling = rising;
        m.advance(&mut falling, FULL_SCALE_MAX);
        m.advance(&mut falling, 0);
        // (A > 0: rising, h heads for +A/c; falling, for −A/c.)
        assert!(
            rising.h > q(0.01) && falling.h < -q(0.01),
            "{rising:?} {falling:?}"
        );
        assert_eq!(Forward::at_rest(&m, 0, Rest::Ascending).0, rising);
        let inverse = InverseBoucWen::new(&asymmetric(), &s).unwrap();
        assert_eq!(Inverse::at_rest(&inverse, 0, 0, Rest::Ascending), rising);
        // The differential pair's rest is relaxed, for the observer and the compensator.
        assert_eq!(Forward::at_rest(&m, 0, Rest::Relaxed).0, m.relaxed(0));
        assert_eq!(
            Inverse::at_rest(&inverse, 0, 0, Rest::Relaxed),
            m.relaxed(0)
        );
        // The relaxed state (h = 0) is not on the loop: the rest differs from it.
        assert!(rising.h.abs() > q(0.01));
        let d = DuhemParams {
            alpha: 0.02,
            beta: 0.5,
            gamma: 0.35,
            offset: 0.0,
        };
        let duhem = Duhem::new(&d, &s).unwrap();
        let bw = BoucWen::new(&BoucWenParams::from_duhem(&d), &s).unwrap();
        let (a, b) = (duhem.state_at_rest(q(0.3)), bw.state_at_rest(q(0.3)));
        assert!((a.y - bw.output(&b)).abs() < 1 << 12, "{a:?} {b:?}");
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
                    chi: 0.0,
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
        // Rising, h saturates at A/(β+γ+ψ); falling at −A/(β+γ−ψ) (χ = 0 here).
        let n = BoucWenParams {
            chi: 0.0,
            ..asymmetric()
        }
        .normalized(&s)
        .unwrap();
        let expected = n.a / (n.beta + n.gamma + n.psi) - n.a / (n.beta + n.gamma - n.psi);
        let (r1, f1) = loop_height(asymmetric().psi);
        assert!(expected < -0.01, "{expected}");
        assert!(
            (r1 + f1 - expected).abs() < 0.05 * expected.abs(),
            "ψ: {r1} + {f1} against {expected}"
        );
    }

    /// `χ` moves the rates after a reversal apart from the saturations: `ψ = 0.006` and
    /// `ψ = χ = 0.003` saturate both branches alike (`β + γ ± (ψ + χ)`), but fall from the top
    /// of the range (`h > 0`) at `β − γ − ψ + χ`, 0.026 against 0.032: the output just after
    /// the reversal is lower where the state decays faster.
    #[test]
    fn chi_sets_the_rates_after_a_reversal_apart_from_the_saturations() {
        let s = scaling();
        let run = |psi: f64, chi: f64| {
            let m = BoucWen::new(
                &BoucWenParams {
                    psi,
                    chi,
                    ..asymmetric()
                },
                &s,
            )
            .unwrap();
            let mut st = m.relaxed(q(-1.0));
            let (mut top, mut bottom, mut after_top) = (0, 0, 0);
            for _ in 0..3 {
                for k in 0..=2000 {
                    m.step(&mut st, q(-1.0 + 2.0 * k as f64 / 2000.0));
                }
                top = st.h;
                for k in 0..=2000 {
                    let y = m.step(&mut st, q(1.0 - 2.0 * k as f64 / 2000.0));
                    if k == 200 {
                        after_top = y;
                    }
                }
                bottom = st.h;
            }
            (f(top), f(bottom), f(after_top))
        };
        let (top_psi, bottom_psi, after_psi) = run(0.006, 0.0);
        let (top_chi, bottom_chi, after_chi) = run(0.003, 0.003);
        assert!(
            (top_psi - top_chi).abs() < 1e-3 && (bottom_psi - bottom_chi).abs() < 1e-3,
            "the same saturations: {top_psi} {top_chi}, {bottom_psi} {bottom_chi}"
        );
        assert!(
            after_chi + 1e-3 < after_psi,
            "the faster decay after the reversal takes h down sooner: {after_chi} against {after_psi}"
        );
    }

    /// A state at zero relaxes as a state a rounding on either side of it: at `h = 0` the
    /// step takes the rate of the sign `h` heads for, so that the output is continuous in
    /// the state (a state at zero once took the rate of positive `h` whichever way it went).
    #[test]
    fn the_rate_is_continuous_in_the_state_at_zero() {
        let s = scaling();
        for a in [0.1, -0.1] {
            let m = BoucWen::new(&BoucWenParams { a, ..asymmetric() }, &s).unwrap();
            for (from, to) in [(-0.5, 0.4), (0.5, -0.4)] {
                let outputs = [-1, 0, 1].map(|h| {
                    let mut st = BoucWenState { u: q(from), h };
                    m.step(&mut st, q(to))
                });
                for y in [outputs[0], outputs[2]] {
                    assert!(
                        (y - outputs[1]).abs() <= 4,
                        "A = {a}, {from} → {to}: {outputs:?}"
                    );
                }
            }
        }
    }

    /// Whatever the drive (steps across the whole range included), `|h|` stays within the
    /// documented bound `|A|/c_min`, and comes near it.
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
            // Fine: some tens of LSB of Q2.30 (one is 9.3e-10), the f32 quotients and the
            // roundings. Coarse (steps of 5 % of the range): the Newton step's miss, of the
            // order of (c·m)² of the step, 3e-7 (a hundredth of a 16-bit DAC code). A
            // compensator that lagged one sample would miss by that sample's change of h,
            // 1e-3 and more; one that took the linear guess alone, by 3e-5 even finely sampled.
            let bound = if samples_per_period > 1_000.0 {
                3e-8
            } else {
                1e-6
            };
            assert!(worst < bound, "{name}: {worst}");
        }
    }

    /// On a drive that reverses often, at step sizes over four decades, the compensator's
    /// state stays its model's on its drive bit for bit over thousands of crossings of zero
    /// (a step it solves to pass zero is taken from zero at the other sign's rate, as its
    /// model splits a crossing), and its output lands on its target. A crossing split in
    /// the wrong place parts them within a few hundred steps.
    #[test]
    fn the_compensator_s_crossings_are_its_model_s() {
        let s = scaling();
        let inv = InverseBoucWen::new(&asymmetric(), &s).unwrap();
        let mut next = uniform(0x2545_f491_4f6c_dd1d);
        let (mut st, mut plant) = (inv.model().relaxed(0), inv.model().relaxed(0));
        let (mut crossings, mut worst_y) = (0u32, 0.0f64);
        let mut yd = 0.0;
        for k in 0..200_000 {
            // A random walk whose steps span four decades, reversing at random.
            let size = 1e-6 * libm::pow(10.0, 4.0 * next());
            yd = (yd + if next() < 0.5 { -size } else { size }).clamp(-0.6, 0.6);
            let before = st.h;
            let u = inv.step(&mut st, q(yd));
            inv.model().step(&mut plant, u);
            if (st.h ^ before) < 0 {
                crossings += 1;
            }
            assert_eq!(
                st, plant,
                "step {k}: the compensator's state is its model's"
            );
            if k > 0 {
                worst_y = worst_y.max((f(inv.model().output(&st)) - yd).abs());
            }
        }
        assert!(
            worst_y < 1e-6,
            "the compensator's output misses by {worst_y}"
        );
        assert!(crossings > 1_000, "{crossings} crossings of zero");
    }

    /// Asked for an output change within a rounding of what reaching zero gives, the
    /// compensator solves a step that stops at zero or a hair either side of it, and the
    /// drive's rounding carries about a third of those that stop short a hair past zero (the
    /// rare path a stream takes when a setpoint lands where the state crosses). Such a step
    /// ends at zero, in the compensator as in its model, bit for bit, without relaxing a
    /// second time; one that passes zero is split where it crosses; the output lands on its
    /// target either way.
    #[test]
    fn a_step_a_rounding_carries_past_zero_ends_there() {
        let s = scaling();
        let inv = InverseBoucWen::new(&asymmetric(), &s).unwrap();
        let m = inv.model();
        let mut next = uniform(0x9e37_79b9_7f4a_7c15);
        let (mut at_zero, mut split, mut worst_y) = (0u32, 0u32, 0.0f64);
        for _ in 0..200_000 {
            // A state of either sign, over four decades, at a drive inside the range.
            let h = (next() - 0.5) * 0.2 * libm::pow(10.0, -4.0 * next());
            let start = BoucWenState {
                u: q((next() - 0.5) * 1.6),
                h: q(h),
            };
            // The direction in which it heads across zero (A > 0: falling for h > 0).
            let falling = start.h > 0;
            let index = m.factor_index(falling, &start) & 3;
            let rate = &m.rates[index];
            let to_zero = rate.step_to_cover(m.crossing_ratio(start.h, rate));
            let slope = f32::from_bits(inv.slope);
            let toward = (start.h as f32 * SIGNAL_TO_F32).abs();
            // The output change at zero, and a request within 5 parts in a million of it.
            let reach = (slope * to_zero + toward) as f64 * (1.0 + (next() - 0.5) * 1e-5);
            let y = f(m.output(&start)) + if falling { -reach } else { reach };
            let (mut st, mut plant) = (start, start);
            let u = inv.step(&mut st, q(y));
            m.step(&mut plant, u);
            // Would one relaxation over the whole step have carried the state past zero?
            let du = u.saturating_sub(start.u);
            let relaxed = m.relaxed_by(start.h, rate.relax(du.unsigned_abs()), du < 0);
            let past = (relaxed ^ start.h) < 0;
            let step = du.unsigned_abs() as f32 * SIGNAL_TO_F32;
            if past && step <= to_zero {
                // Short of zero, a rounding past it: at zero, as its model.
                at_zero += 1;
                assert_eq!(st.h, 0, "{start:?} → {u}");
                assert_eq!(st, plant, "{start:?} → {u}");
            } else if past {
                split += 1;
                assert_eq!(st, plant, "{start:?} → {u}");
            }
            // Where the step is within the cap (a longer one is made over several samples) and
            // the range.
            if to_zero * rate.rate() < 0.5 * STEP_CAP && u.abs() < q(1.0) {
                worst_y = worst_y.max((f(m.output(&st)) - y).abs());
            }
        }
        assert!(
            at_zero > 1_000 && split > 1_000,
            "{at_zero} at zero, {split} split"
        );
        assert!(
            worst_y < 1e-6,
            "the compensator's output misses by {worst_y}"
        );
    }
}
