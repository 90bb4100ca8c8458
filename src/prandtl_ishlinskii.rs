//! Prandtl–Ishlinskii models in fixed point: the forward model (observer) and its analytic
//! inverse (compensator).
//!
//! Both have the same shape, a weighted sum of play operators,
//!
//! * forward: `y = c + Σ_i w_i · P_{r_i}[u]`
//! * inverse: `u = Σ_i w'_i · P_{r'_i}[y − c]`
//!
//! so both are a [`PlayOperatorBank`] plus an offset on one side. Configuration (thresholds,
//! weights: built once from [`PiParams`], validated) is kept apart from state (the operators'
//! outputs, [`PiState`]), as idsp does, so a new configuration can be swapped in whole.
//!
//! Formats: signals Q2.30 normalised (see [`crate::fixed_point`]); thresholds Q2.30 normalised;
//! weights Q8.24 normalised (output span per input span); accumulation Q10.54 in `i64`.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, saturate_q54_to_signal, signal_from_f64, GAIN_FRAC_BITS,
};
use crate::params::{CanonicalPi, ParamError, PiParams, MAX_CANONICAL_OPERATORS};
use crate::play_operator::play;
use crate::scaling::Scaling;

/// The states of a bank's play operators, Q2.30 normalised. Index `i` is operator `i + 1`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PiState {
    /// Operator outputs `p_i`, Q2.30; only the first `operators()` entries are used.
    pub operators: [i32; MAX_CANONICAL_OPERATORS],
}

/// A bank of play operators and their weights: `Σ_i w_i · P_{r_i}[x]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlayOperatorBank {
    len: usize,
    /// Thresholds `r_i`, Q2.30 normalised, `0 = r_1 < r_2 < … ≤ 2`.
    thresholds: [i32; MAX_CANONICAL_OPERATORS],
    /// Weights `w_i`, Q8.24 normalised.
    weights: [i32; MAX_CANONICAL_OPERATORS],
}

impl PlayOperatorBank {
    fn from_canonical(c: &CanonicalPi) -> Result<Self, ParamError> {
        c.check_fixed_point_range()?;
        let mut bank = Self {
            len: c.thresholds.len(),
            thresholds: [0; MAX_CANONICAL_OPERATORS],
            weights: [0; MAX_CANONICAL_OPERATORS],
        };
        for (i, (&r, &w)) in c.thresholds.iter().zip(c.weights.iter()).enumerate() {
            bank.thresholds[i] = signal_from_f64(r);
            bank.weights[i] = gain_from_f64(w);
        }
        Ok(bank)
    }

    /// Number of play operators in use.
    pub fn operators(&self) -> usize {
        self.len
    }

    /// Thresholds in use, Q2.30 normalised.
    pub fn thresholds(&self) -> &[i32] {
        &self.thresholds[..self.len.min(MAX_CANONICAL_OPERATORS)]
    }

    /// Weights in use, Q8.24 normalised.
    pub fn weights(&self) -> &[i32] {
        &self.weights[..self.len.min(MAX_CANONICAL_OPERATORS)]
    }

    /// Advances every operator by input `x` (Q2.30) and returns `Σ w_i p_i` as a Q10.54
    /// accumulator. Validation bounds `Σ|w_i| · 2` below `2^63 / 2^54`, so the sum cannot
    /// overflow; iteration is bounded by the array length (no panic path).
    #[inline(always)]
    fn step(&self, state: &mut PiState, x: i32) -> i64 {
        let mut acc: i64 = 0;
        for ((&r, &w), p) in self
            .thresholds
            .iter()
            .zip(self.weights.iter())
            .zip(state.operators.iter_mut())
            .take(self.len)
        {
            *p = play(x, r, *p);
            acc += w as i64 * *p as i64;
        }
        acc
    }

    /// State with every operator at `x` (the relaxed state after resting at input `x`).
    fn state_at(&self, x: i32) -> PiState {
        PiState {
            operators: [x; MAX_CANONICAL_OPERATORS],
        }
    }
}

/// Forward P–I model, fixed point: `y = c + Σ w_i P_{r_i}[u]` (the observer).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PrandtlIshlinskii {
    bank: PlayOperatorBank,
    /// Output offset `c`, Q2.30 normalised output.
    offset: i32,
}

impl PrandtlIshlinskii {
    /// Validates `params` (physical units) and converts them, normalised by `scaling`, into
    /// the fixed-point form the tick runs.
    pub fn new(params: &PiParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let canonical = params.normalized(scaling)?.canonical()?;
        Ok(Self {
            bank: PlayOperatorBank::from_canonical(&canonical)?,
            offset: signal_from_f64(canonical.offset),
        })
    }

    /// The operator bank (thresholds and weights).
    pub fn bank(&self) -> &PlayOperatorBank {
        &self.bank
    }

    /// Output offset, Q2.30 normalised.
    pub fn offset(&self) -> i32 {
        self.offset
    }

    /// The relaxed state after resting at input `u` (Q2.30): every operator at `u`.
    pub fn state_at_rest(&self, u: i32) -> PiState {
        self.bank.state_at(clamp_full_scale(u))
    }

    /// One sample: input `u` (Q2.30 normalised drive, clamped to [-1, 1]) → output `y`
    /// (Q2.30 normalised displacement, saturated).
    #[inline]
    pub fn step(&self, state: &mut PiState, u: i32) -> i32 {
        let acc = self.bank.step(state, clamp_full_scale(u));
        saturate_q54_to_signal(acc + ((self.offset as i64) << GAIN_FRAC_BITS))
    }
}

/// Analytic inverse P–I, fixed point: `u = Σ w'_i P_{r'_i}[y_d − c]` (the compensator).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InversePrandtlIshlinskii {
    bank: PlayOperatorBank,
    /// Forward model's output offset `c`, Q2.30, subtracted from the desired output first.
    offset: i32,
    /// Forward partial sums `S_i`, Q8.24, for [`Self::state_from_forward`].
    partial_sums: [i32; MAX_CANONICAL_OPERATORS],
    /// Forward weights `w_i`, Q8.24, for [`Self::state_from_forward`].
    forward_weights: [i32; MAX_CANONICAL_OPERATORS],
}

impl InversePrandtlIshlinskii {
    /// Builds the inverse of the forward model `params` (physical units), normalised by
    /// `scaling`. Refuses non-invertible models (`w_1 ≤ 0`, a partial sum `S_i ≤ 0`) with the
    /// first failing operator, and inverses whose weights do not fit Q8.24.
    pub fn new(params: &PiParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let forward = params.normalized(scaling)?.canonical()?;
        let inverse = forward.inverse()?;
        let mut partial_sums = [0; MAX_CANONICAL_OPERATORS];
        let mut forward_weights = [0; MAX_CANONICAL_OPERATORS];
        let mut s = 0.0;
        for (i, &w) in forward.weights.iter().enumerate() {
            s += w;
            partial_sums[i] = gain_from_f64(s);
            forward_weights[i] = gain_from_f64(w);
        }
        forward.check_fixed_point_range()?;
        Ok(Self {
            bank: PlayOperatorBank::from_canonical(&inverse)?,
            offset: signal_from_f64(inverse.offset),
            partial_sums,
            forward_weights,
        })
    }

    /// The operator bank (inverse thresholds `r'_i` and weights `w'_i`).
    pub fn bank(&self) -> &PlayOperatorBank {
        &self.bank
    }

    /// The inverse's state matching a forward state (DESIGN §2):
    /// `p'_i = S_i p_i + Σ_{j>i} w_j p_j`, so that switching the compensator on mid-run
    /// continues from where the stage is. Off the tick path (O(N²)).
    pub fn state_from_forward(&self, forward: &PiState) -> PiState {
        let n = self.bank.operators();
        let mut out = self.bank.state_at(0);
        for i in 0..n {
            let mut acc = self.partial_sums[i] as i64 * forward.operators[i] as i64;
            for j in (i + 1)..n {
                acc += self.forward_weights[j] as i64 * forward.operators[j] as i64;
            }
            out.operators[i] = saturate_q54_to_signal(acc);
        }
        out
    }

    /// The relaxed state after resting at desired output `y` (Q2.30).
    pub fn state_at_rest(&self, y: i32) -> PiState {
        self.bank
            .state_at(clamp_full_scale(y).saturating_sub(self.offset))
    }

    /// One sample: desired displacement `y` (Q2.30 normalised, clamped to [-1, 1]) → drive `u`
    /// (Q2.30 normalised, saturated; the caller clamps it to the drive's limits).
    #[inline]
    pub fn step(&self, state: &mut PiState, y: i32) -> i32 {
        let x = clamp_full_scale(y).saturating_sub(self.offset);
        saturate_q54_to_signal(self.bank.step(state, x))
    }
}
