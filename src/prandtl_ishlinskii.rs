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
    clamp_full_scale, gain_from_f64, limit, saturate_q54_to_signal, signal_from_f64, GAIN_FRAC_BITS,
};
use crate::params::{CanonicalPi, ParamError, PiParams, MAX_CANONICAL_OPERATORS};
use crate::play_operator::play;
use crate::scaling::Scaling;

/// The states of a bank's play operators. Index `i` is operator `i + 1`.
///
/// Besides the operator outputs it keeps the last input and the running sum `Σ w_i p_i`, so
/// that a step only touches the operators that move (see [`PlayOperatorBank`]). The fields are
/// private: every state comes from a constructor that establishes the bank's invariant.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PiState {
    /// Operator outputs `p_i`, Q2.30; only the first `operators()` entries are used.
    operators: [i32; MAX_CANONICAL_OPERATORS],
    /// Last input `x`, Q2.30.
    input: i32,
    /// `Σ w_i p_i`, Q10.54.
    sum: i64,
}

impl PiState {
    /// Operator outputs `p_i`, Q2.30 (all slots; the bank uses its first `operators()`).
    pub fn operators(&self) -> &[i32; MAX_CANONICAL_OPERATORS] {
        &self.operators
    }
}

/// One play operator's configuration, side by side so the tick loads it in one go.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct WeightedOperator {
    /// Threshold `r_i`, Q2.30 normalised.
    threshold: i32,
    /// Weight `w_i`, Q8.24 normalised.
    weight: i32,
    /// `−w_i`, Q8.24: the sum's update `w·p_new + (−w)·p_old` is then two `SMLAL`s on the
    /// Cortex-M4, where `w·(p_new − p_old)` would need a 33-bit difference and a 64-bit multiply.
    neg_weight: i32,
}

/// A bank of play operators and their weights: `Σ_i w_i · P_{r_i}[x]`.
///
/// **Only the operators that move are touched.** With thresholds increasing, the states of a
/// bank that started relaxed satisfy `|p_{i+1} − p_i| ≤ r_{i+1} − r_i` (a play update is a
/// clamp, which keeps that Lipschitz bound exactly, in integers too). So when the input rises,
/// operator `i + 1` can only be pushed if operator `i` was (`p_i ≥ x − r_i` implies
/// `p_{i+1} ≥ x − r_{i+1}`), and likewise downwards: the operators that move form a prefix.
/// A step walks that prefix, stops at the first operator that holds, and updates the running
/// sum by `w_i (p_new − p_old)` — exactly the full sum, in integers, at a fraction of the cost
/// on a slowly varying input (and none at all when the input holds).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlayOperatorBank {
    len: usize,
    operators: [WeightedOperator; MAX_CANONICAL_OPERATORS],
}

impl PlayOperatorBank {
    fn from_canonical(c: &CanonicalPi) -> Result<Self, ParamError> {
        c.check_fixed_point_range()?;
        let mut bank = Self {
            len: c.thresholds.len(),
            operators: [WeightedOperator::default(); MAX_CANONICAL_OPERATORS],
        };
        for (op, (&r, &w)) in bank
            .operators
            .iter_mut()
            .zip(c.thresholds.iter().zip(c.weights.iter()))
        {
            op.threshold = signal_from_f64(r);
            op.weight = gain_from_f64(w);
            op.neg_weight = -op.weight; // |w| < 128 in Q8.24: no overflow
        }
        Ok(bank)
    }

    /// Number of play operators in use.
    pub fn operators(&self) -> usize {
        self.len
    }

    /// Threshold of operator `i + 1`, Q2.30 normalised (0 past the end).
    pub fn threshold(&self, i: usize) -> i32 {
        self.operators.get(i).map_or(0, |op| op.threshold)
    }

    /// Weight of operator `i + 1`, Q8.24 normalised (0 past the end).
    pub fn weight(&self, i: usize) -> i32 {
        self.operators.get(i).map_or(0, |op| op.weight)
    }

    /// Advances the bank by input `x` (Q2.30) and returns `Σ w_i p_i` as a Q10.54 accumulator.
    /// Validation bounds `Σ|w_i| · 2` below `2^63 / 2^54`, so the sum cannot overflow;
    /// iteration is bounded by the array length (no panic path).
    #[inline(always)]
    fn step(&self, state: &mut PiState, x: i32) -> i64 {
        let mut sum = state.sum;
        let n = self.len;
        let (Some(config), Some(outputs)) = (self.operators.get(..n), state.operators.get_mut(..n))
        else {
            return sum; // unreachable: len ≤ capacity by construction
        };
        let ops = config.iter().zip(outputs.iter_mut());
        if x > state.input {
            for (op, p) in ops {
                let lower = x.saturating_sub(op.threshold);
                if *p >= lower {
                    break;
                }
                sum += op.weight as i64 * lower as i64 + op.neg_weight as i64 * *p as i64;
                *p = lower;
            }
        } else if x < state.input {
            for (op, p) in ops {
                let upper = x.saturating_add(op.threshold);
                if *p <= upper {
                    break;
                }
                sum += op.weight as i64 * upper as i64 + op.neg_weight as i64 * *p as i64;
                *p = upper;
            }
        }
        state.input = x;
        state.sum = sum;
        sum
    }

    /// A state from operator outputs: projected onto the bank's invariant
    /// (`p_1 = x`, `|p_{i+1} − p_i| ≤ r_{i+1} − r_i`, `|p_i − x| ≤ r_i`) and with its sum.
    fn state_from(&self, mut operators: [i32; MAX_CANONICAL_OPERATORS], x: i32) -> PiState {
        let mut previous: Option<(i32, i32)> = None; // (p, r) of the operator before
        let mut sum = 0i64;
        for (op, p) in self
            .operators
            .iter()
            .zip(operators.iter_mut())
            .take(self.len)
        {
            let mut v = play(x, op.threshold, *p);
            if let Some((pp, pr)) = previous {
                let d = op.threshold.saturating_sub(pr);
                v = limit(v, pp.saturating_sub(d), pp.saturating_add(d));
            }
            *p = v;
            previous = Some((v, op.threshold));
            sum += op.weight as i64 * v as i64;
        }
        PiState {
            operators,
            input: x,
            sum,
        }
    }

    /// State with every operator at `x` (the relaxed state after resting at input `x`).
    fn state_at(&self, x: i32) -> PiState {
        self.state_from([x; MAX_CANONICAL_OPERATORS], x)
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
        let mut operators = [0; MAX_CANONICAL_OPERATORS];
        for (i, out) in operators.iter_mut().enumerate().take(n) {
            let mut acc = self.partial_sums[i] as i64 * forward.operators[i] as i64;
            for j in (i + 1)..n {
                acc += self.forward_weights[j] as i64 * forward.operators[j] as i64;
            }
            *out = saturate_q54_to_signal(acc);
        }
        // r'_1 = 0, so the inverse's input is its first operator's output.
        self.bank.state_from(operators, operators[0])
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::Thresholds;
    use proptest::prelude::*;

    /// The plain definition: update every operator, sum every product.
    fn exhaustive_step(
        bank: &PlayOperatorBank,
        p: &mut [i32; MAX_CANONICAL_OPERATORS],
        x: i32,
    ) -> i64 {
        let mut sum = 0;
        for (op, p) in bank.operators.iter().zip(p.iter_mut()).take(bank.len) {
            *p = play(x, op.threshold, *p);
            sum += op.weight as i64 * *p as i64;
        }
        sum
    }

    proptest! {
        /// Walking only the moving prefix gives, bit for bit, the states and the sum of
        /// updating every operator — over random banks and random inputs, jumps included.
        #[test]
        fn prefix_walk_equals_the_exhaustive_update(
            n in 1usize..=32,
            weights in prop::collection::vec(-1.0f64..1.0, 32),
            inputs in prop::collection::vec(-1.0f64..=1.0, 1..300),
            start in -1.0f64..=1.0,
        ) {
            let r = Thresholds::Uniform.generate(n, 2.0).unwrap();
            let c = CanonicalPi {
                thresholds: heapless::Vec::from_slice(&r).unwrap(),
                weights: heapless::Vec::from_slice(&weights[..n]).unwrap(),
                offset: 0.0,
            };
            let bank = PlayOperatorBank::from_canonical(&c).unwrap();
            let mut state = bank.state_at(signal_from_f64(start));
            let mut plain = state.operators;
            for &u in &inputs {
                let x = signal_from_f64(u);
                let fast = bank.step(&mut state, x);
                let slow = exhaustive_step(&bank, &mut plain, x);
                prop_assert_eq!(fast, slow);
                prop_assert_eq!(&state.operators[..n], &plain[..n]);
            }
        }
    }
}
