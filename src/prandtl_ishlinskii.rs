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
//! ## At rest: on the ascending branch
//!
//! A stage at rest at drive `u` is not a demagnetised stage: its drive was last taken down to
//! the bottom of its range (0 V at power-off and at boot) and then raised to `u`, so its
//! hysteresis memory is the major loop's bottom, wiped above `u`. `state_at_rest` puts a
//! model in that state — every operator as the input history "top of the range → bottom →
//! `u`" leaves it (`p_i = max(u − r_i, min(−1 + r_i, 1 − r_i))`) — for the forward model, and
//! for the inverse the matching state ([`InversePrandtlIshlinskii::state_from_forward`] of
//! the forward's bottom state, raised to the desired output), so compensator, observer, the
//! stage and the identification (which starts its regressors the same way) agree from the
//! first sample. The virgin state (every operator at `u`) would describe a stage
//! demagnetised at `u`, and its first rise would follow the initial loading curve, which a
//! stage in use never does: on a simulated Preisach stage that mismatch alone cost 0.5 % of
//! span on the first rise of every tracked trajectory.
//!
//! Formats: signals Q2.30 normalised (see [`crate::fixed_point`]); thresholds Q2.30 normalised;
//! weights Q8.24 normalised (output span per input span); accumulation Q10.54 in `i64`.

use crate::fixed_point::{
    clamp_full_scale, gain_from_f64, limit, q54_to_signal_floor, saturate_q54_to_signal,
    signal_from_f64, FULL_SCALE_MAX, GAIN_FRAC_BITS, SIGNAL_ONE,
};
use crate::params::{CanonicalPi, ParamError, PiParams, MAX_CANONICAL_OPERATORS};
use crate::play_operator::play;
use crate::scaling::Scaling;

/// The memory of a bank of play operators: each operator's output, and the last input.
///
/// The fields are private: every state comes from a constructor that establishes the bank's
/// invariant (`|p_{i+1} − p_i| ≤ r_{i+1} − r_i`, `|p_i − x| ≤ r_i`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PiState {
    /// Last input `x`, Q2.30.
    input: i32,
    /// The operators' outputs `p_i`, Q2.30 (slots past the bank's operators stay 0).
    outputs: [i32; MAX_CANONICAL_OPERATORS],
}

impl PiState {
    /// The last input, Q2.30.
    pub fn input(&self) -> i32 {
        self.input
    }
}

/// A bank of play operators and their weights: `Σ_i w_i · P_{r_i}[x]`.
///
/// **A step costs the same whatever the input does**: every operator is updated
/// (`p_i ← max(x − r_i, min(x + r_i, p_i))`, a `QADD`, a `QSUB` and two conditional moves
/// on the Cortex-M4) and multiply-accumulated (`SMLAL`) — no branch on the input's history,
/// so a reversal, a jump across the whole range or the first step after a reload costs what
/// a smooth step costs. (The memory-stack bank this replaced was cheaper on smooth inputs and
/// several times dearer on jumps; the interrupt's budget is its worst case.) The sum is exact
/// in a 64-bit accumulator (Q10.54): validation bounds `Σ|w_i| · 2` below `2^63 / 2^54`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlayOperatorBank {
    len: usize,
    /// Thresholds `r_i`, Q2.30 normalised, increasing.
    thresholds: [i32; MAX_CANONICAL_OPERATORS],
    /// Weights `w_i`, Q8.24 normalised.
    weights: [i32; MAX_CANONICAL_OPERATORS],
}

impl PlayOperatorBank {
    fn from_canonical(c: &CanonicalPi) -> Result<Self, ParamError> {
        c.check_fixed_point_range()?;
        let mut bank = Self {
            len: c.thresholds.len().min(MAX_CANONICAL_OPERATORS),
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

    /// Threshold of operator `i + 1`, Q2.30 normalised (0 past the end).
    pub fn threshold(&self, i: usize) -> i32 {
        self.thresholds.get(i).copied().unwrap_or(0)
    }

    /// Weight of operator `i + 1`, Q8.24 normalised (0 past the end).
    pub fn weight(&self, i: usize) -> i32 {
        self.weights.get(i).copied().unwrap_or(0)
    }

    /// The operators' outputs `p_i` in `state`, Q2.30 (slots past [`Self::operators`] are 0).
    pub fn outputs(&self, state: &PiState) -> [i32; MAX_CANONICAL_OPERATORS] {
        state.outputs
    }

    /// Advances the bank by input `x` (Q2.30) and returns `Σ w_i p_i` as a Q10.54 accumulator.
    /// Constant time: every operator, every step (see the type's doc).
    #[inline(always)]
    fn step(&self, s: &mut PiState, x: i32) -> i64 {
        let n = self.len.min(MAX_CANONICAL_OPERATORS);
        let mut acc = 0i64;
        for ((p, &r), &w) in s.outputs[..n]
            .iter_mut()
            .zip(&self.thresholds[..n])
            .zip(&self.weights[..n])
        {
            *p = play(x, r, *p);
            acc += w as i64 * *p as i64;
        }
        s.input = x;
        acc
    }

    /// A state from operator outputs: projected onto the bank's invariant
    /// (`p_1 = x`, `|p_{i+1} − p_i| ≤ r_{i+1} − r_i`, `|p_i − x| ≤ r_i`).
    #[inline(never)] // configuration, off the tick path: one copy in flash
    fn state_from(&self, mut operators: [i32; MAX_CANONICAL_OPERATORS], x: i32) -> PiState {
        let mut previous: Option<(i32, i32)> = None; // (p, r) of the operator before
        for (i, p) in operators.iter_mut().enumerate() {
            if i >= self.len {
                *p = 0;
                continue;
            }
            let r = self.thresholds[i];
            let mut v = play(x, r, *p);
            if let Some((pp, pr)) = previous {
                let d = r.saturating_sub(pr);
                v = limit(v, pp.saturating_sub(d), pp.saturating_add(d));
            }
            *p = v;
            previous = Some((v, r));
        }
        PiState {
            input: x,
            outputs: operators,
        }
    }

    /// The operators' outputs after the input went to the top of the range and back down to
    /// the bottom (the major loop's bottom): `p_i = min(−1 + r_i, max(1 − r_i, −1))`.
    fn major_loop_bottom(thresholds: &[i32]) -> [i32; MAX_CANONICAL_OPERATORS] {
        let mut p = [0; MAX_CANONICAL_OPERATORS];
        for (p, &r) in p.iter_mut().zip(thresholds) {
            let after_top = FULL_SCALE_MAX.saturating_sub(r).max(-SIGNAL_ONE);
            *p = (-SIGNAL_ONE).saturating_add(r).min(after_top);
        }
        p
    }

    /// The state at rest at input `x` on the ascending branch (see the module doc): the
    /// major loop's bottom, then the input raised to `x`.
    fn state_at_rest(&self, x: i32) -> PiState {
        let n = self.len.min(MAX_CANONICAL_OPERATORS);
        self.state_from(Self::major_loop_bottom(&self.thresholds[..n]), x)
    }

    /// State with every operator at `x` (the virgin state, demagnetised at `x`).
    #[cfg(test)]
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
    ///
    /// ```
    /// use twinstack::prandtl_ishlinskii::PrandtlIshlinskii;
    /// use twinstack::{PiParams, Scaling};
    /// // Play operators at 0 and 70 V (0.3 and 0.2 µm/V): 0…140 V onto 0…70 µm.
    /// let params = PiParams::new(0.0, 0.0, &[0.0, 70.0], &[0.3, 0.2]).unwrap();
    /// let model = PrandtlIshlinskii::new(&params, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).unwrap();
    /// let mut rest = model.state_at_rest(-(1 << 30)); // relaxed at 0 V
    /// // Up to 140 V: 0.3·140 + 0.2·70 = 56 µm, i.e. 0.6 of the normalised range.
    /// let y = model.step(&mut rest, (1 << 30) - 1);
    /// assert!((y as f64 / (1 << 30) as f64 - 0.6).abs() < 1e-6);
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
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

    /// The state at rest at input `u` (Q2.30), on the ascending branch: the input last came
    /// down from the top of the range to the bottom, then rose to `u` (see the module doc).
    pub fn state_at_rest(&self, u: i32) -> PiState {
        self.bank.state_at_rest(clamp_full_scale(u))
    }

    /// One sample: input `u` (Q2.30 normalised drive, clamped to [-1, 1]) → output `y`
    /// (Q2.30 normalised displacement, saturated).
    #[inline(always)]
    pub fn step(&self, state: &mut PiState, u: i32) -> i32 {
        let acc = self.bank.step(state, clamp_full_scale(u));
        q54_to_signal_floor(acc + ((self.offset as i64) << GAIN_FRAC_BITS))
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
    /// Forward thresholds `r_i`, Q2.30, to recognise the forward model ([`Self::inverts`]).
    forward_thresholds: [i32; MAX_CANONICAL_OPERATORS],
}

impl InversePrandtlIshlinskii {
    /// Builds the inverse of the forward model `params` (physical units), normalised by
    /// `scaling`. Refuses non-invertible models (`w_1 ≤ 0`, a partial sum `S_i ≤ 0`) with the
    /// first failing operator, and inverses whose weights do not fit Q8.24.
    ///
    /// ```
    /// use twinstack::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
    /// use twinstack::{PiParams, Scaling};
    /// let params = PiParams::new(0.0, 0.0, &[0.0, 70.0], &[0.3, 0.2]).unwrap();
    /// let ranges = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
    /// let (forward, inverse) = (
    ///     PrandtlIshlinskii::new(&params, &ranges).unwrap(),
    ///     InversePrandtlIshlinskii::new(&params, &ranges).unwrap(),
    /// );
    /// // The drive the inverse asks for makes the forward model reach the target.
    /// let (mut f, mut i) = (forward.state_at_rest(-(1 << 30)), inverse.state_at_rest(-(1 << 30)));
    /// let target = 1 << 28; // 0.25 of the normalised range
    /// let drive = inverse.step(&mut i, target);
    /// assert!((forward.step(&mut f, drive) - target).abs() < 64);
    /// assert!(PiParams::new(0.0, 0.0, &[0.0], &[-0.1]).map(|p| InversePrandtlIshlinskii::new(&p, &ranges)).unwrap().is_err());
    /// ```
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn new(params: &PiParams, scaling: &Scaling) -> Result<Self, ParamError> {
        let forward = params.normalized(scaling)?.canonical()?;
        let inverse = forward.inverse()?;
        let mut partial_sums = [0; MAX_CANONICAL_OPERATORS];
        let mut forward_weights = [0; MAX_CANONICAL_OPERATORS];
        let mut forward_thresholds = [0; MAX_CANONICAL_OPERATORS];
        let mut s = 0.0;
        for (i, (&w, &r)) in forward.weights.iter().zip(&forward.thresholds).enumerate() {
            s += w;
            partial_sums[i] = gain_from_f64(s);
            forward_weights[i] = gain_from_f64(w);
            forward_thresholds[i] = signal_from_f64(r);
        }
        forward.check_fixed_point_range()?;
        Ok(Self {
            bank: PlayOperatorBank::from_canonical(&inverse)?,
            offset: signal_from_f64(inverse.offset),
            partial_sums,
            forward_weights,
            forward_thresholds,
        })
    }

    /// Whether this is the inverse of `forward` (the same model, operator for operator): only
    /// then does [`Self::state_from_forward`] of `forward`'s state describe this compensator.
    pub fn inverts(&self, forward: &PrandtlIshlinskii) -> bool {
        let n = self.bank.operators();
        let b = forward.bank();
        b.operators() == n
            && forward.offset() == self.offset
            && (0..n).all(|i| {
                b.weight(i) == self.forward_weights[i]
                    && b.threshold(i) == self.forward_thresholds[i]
            })
    }

    /// The operator bank (inverse thresholds `r'_i` and weights `w'_i`).
    pub fn bank(&self) -> &PlayOperatorBank {
        &self.bank
    }

    /// The inverse's state matching the forward model's operator outputs `p` (see the book, docs/src/reference/models.md,
    /// from [`PlayOperatorBank::outputs`] of the observer's bank):
    /// `p'_i = S_i p_i + Σ_{j>i} w_j p_j`, so that switching the compensator on mid-run
    /// continues from where the stage is. Off the tick path (O(N²)).
    #[inline(never)] // configuration, off the tick path: one copy in flash
    pub fn state_from_forward(&self, p: &[i32; MAX_CANONICAL_OPERATORS]) -> PiState {
        let n = self.bank.operators();
        let mut operators = [0; MAX_CANONICAL_OPERATORS];
        for (i, out) in operators.iter_mut().enumerate().take(n) {
            let mut acc = self.partial_sums[i] as i64 * p[i] as i64;
            for (&w, &pj) in self.forward_weights[i + 1..n].iter().zip(&p[i + 1..n]) {
                acc += w as i64 * pj as i64;
            }
            *out = saturate_q54_to_signal(acc);
        }
        // r'_1 = 0, so the inverse's input is its first operator's output.
        self.bank.state_from(operators, operators[0])
    }

    /// The state at rest at desired output `y` (Q2.30), matching the forward model's
    /// [`PrandtlIshlinskii::state_at_rest`]: the forward's major-loop bottom mapped by
    /// [`Self::state_from_forward`], then the input raised to `y − c` (a monotone model maps
    /// the history "top → bottom → u" to "top → bottom → y", so the inverse's operators end
    /// where that history leaves them).
    pub fn state_at_rest(&self, y: i32) -> PiState {
        let n = self.bank.operators();
        let bottom = self.state_from_forward(&PlayOperatorBank::major_loop_bottom(
            &self.forward_thresholds[..n],
        ));
        self.bank.state_from(
            bottom.outputs,
            clamp_full_scale(y).saturating_sub(self.offset),
        )
    }

    /// One sample: desired displacement `y` (Q2.30 normalised, clamped to [-1, 1]) → drive `u`
    /// (Q2.30 normalised, saturated; the caller clamps it to the drive's limits).
    #[inline(always)]
    pub fn step(&self, state: &mut PiState, y: i32) -> i32 {
        let x = clamp_full_scale(y).saturating_sub(self.offset);
        q54_to_signal_floor(self.bank.step(state, x))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::params::Thresholds;
    use proptest::prelude::*;

    fn bank(n: usize, weights: &[f64], geometric: bool) -> PlayOperatorBank {
        let spacing = if geometric {
            Thresholds::Geometric { ratio: 1.3 }
        } else {
            Thresholds::Uniform
        };
        let r = spacing.generate(n, 2.0).unwrap();
        let c = CanonicalPi {
            thresholds: heapless::Vec::from_slice(&r).unwrap(),
            weights: heapless::Vec::from_slice(&weights[..n]).unwrap(),
            offset: 0.0,
        };
        PlayOperatorBank::from_canonical(&c).unwrap()
    }

    proptest! {
        /// Whatever the inputs, the bank keeps its invariant (each operator within its
        /// threshold of the input, neighbours within their thresholds' difference), and the
        /// sum is the weighted sum of the outputs.
        #[test]
        fn the_bank_keeps_its_invariant_and_sums_its_outputs(
            n in 1usize..=crate::params::MAX_OPERATORS,
            weights in proptest::collection::vec(0.01f64..0.5, MAX_CANONICAL_OPERATORS),
            geometric: bool,
            start: i32,
            inputs in proptest::collection::vec(any::<i32>(), 1..200),
        ) {
            let b = bank(n, &weights, geometric);
            let mut s = b.state_at(start >> 1);
            for x in inputs {
                let x = x >> 1; // the models clamp to full scale first
                let sum = b.step(&mut s, x);
                let p = b.outputs(&s);
                let mut expected = 0i64;
                for i in 0..n {
                    let r = b.threshold(i) as i64;
                    prop_assert!((p[i] as i64 - x as i64).abs() <= r, "operator {}", i + 1);
                    if i > 0 {
                        let d = r - b.threshold(i - 1) as i64;
                        prop_assert!((p[i] as i64 - p[i - 1] as i64).abs() <= d);
                    }
                    expected += b.weight(i) as i64 * p[i] as i64;
                }
                prop_assert_eq!(sum, expected);
            }
        }

        /// A state built from arbitrary outputs is projected onto the invariant, and one built
        /// from outputs that already satisfy it keeps them.
        #[test]
        fn states_from_outputs_are_projected_onto_the_invariant(
            n in 1usize..=crate::params::MAX_OPERATORS,
            outputs in proptest::array::uniform32(any::<i32>()),
            x: i32,
        ) {
            let b = bank(n, &[0.1; MAX_CANONICAL_OPERATORS], false);
            let mut raw = [0; MAX_CANONICAL_OPERATORS];
            raw[..32].copy_from_slice(&outputs.map(|v| v >> 1));
            let s = b.state_from(raw, x >> 1);
            let p = b.outputs(&s);
            for (i, &pi) in p.iter().enumerate().take(n) {
                prop_assert!((pi as i64 - (x >> 1) as i64).abs() <= b.threshold(i) as i64);
            }
            prop_assert_eq!(b.state_from(p, x >> 1), s);
        }
    }

    /// At rest is the state the history "top of the range → bottom → u" leaves, whatever
    /// came before; and the inverse at rest at the forward's output composes with it to the
    /// identity from the first step (to a few LSB of Q2.30).
    #[test]
    fn at_rest_is_on_the_ascending_branch_and_the_inverse_matches_it() {
        let scaling = Scaling::new(0.0, 140.0, 0.0, 160.0).unwrap();
        let r = Thresholds::Uniform.generate(16, 70.0).unwrap();
        let w: heapless::Vec<f64, 32> = (0..16).map(|i| 0.3 / (1.0 + i as f64)).collect();
        let params = PiParams::new(0.0, 5.0, &r, &w).unwrap();
        let (f, inv) = (
            PrandtlIshlinskii::new(&params, &scaling).unwrap(),
            InversePrandtlIshlinskii::new(&params, &scaling).unwrap(),
        );
        for u0 in [-SIGNAL_ONE, -(1 << 29), 0, 3 << 28, FULL_SCALE_MAX] {
            // Any history that goes to the top, then the bottom, then u0.
            let mut s = f.state_at_rest(1 << 27);
            for x in [1 << 28, -(1 << 29), FULL_SCALE_MAX, -SIGNAL_ONE, u0] {
                f.step(&mut s, x);
            }
            assert_eq!(s, f.state_at_rest(u0), "u0 = {u0}");
            // Not the virgin state (every operator at u0), except at the top.
            if u0 < 0 {
                assert_ne!(s, f.bank.state_at(u0));
            }
            let mut fs = f.state_at_rest(u0);
            let y0 = f.step(&mut fs, u0);
            let mut is = inv.state_at_rest(y0);
            for k in 0..400i32 {
                let x = clamp_full_scale(u0 / 2 + ((k * 7919) % 2001 - 1000) * (1 << 20));
                let target = f.step(&mut fs, x);
                let drive = inv.step(&mut is, target);
                assert!(
                    (drive - x).abs() < 1 << 8,
                    "u0 {u0} step {k}: {drive} vs {x}"
                );
            }
        }
    }

    #[test]
    fn an_inverse_recognises_its_own_forward_model_only() {
        let scaling = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
        let pi = |n: usize, w1: f64| {
            let r = Thresholds::Uniform.generate(n, 140.0).unwrap();
            let w: heapless::Vec<f64, 32> =
                (0..n).map(|i| if i == 0 { w1 } else { 0.01 }).collect();
            PiParams::new(0.0, 0.0, &r, &w).unwrap()
        };
        let inverse = InversePrandtlIshlinskii::new(&pi(16, 0.3), &scaling).unwrap();
        assert!(inverse.inverts(&PrandtlIshlinskii::new(&pi(16, 0.3), &scaling).unwrap()));
        assert!(!inverse.inverts(&PrandtlIshlinskii::new(&pi(8, 0.3), &scaling).unwrap()));
        assert!(!inverse.inverts(&PrandtlIshlinskii::new(&pi(16, 0.31), &scaling).unwrap()));
    }
}
