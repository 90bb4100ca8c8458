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
    clamp_full_scale, gain_from_f64, limit, q54_to_signal_floor, saturate_q54_to_signal,
    signal_from_f64, GAIN_FRAC_BITS,
};
use crate::params::{CanonicalPi, ParamError, PiParams, MAX_CANONICAL_OPERATORS};
use crate::play_operator::play;
use crate::scaling::Scaling;

/// Most frozen segments a [`PiState`]'s memory holds: every segment holds at least one
/// operator, so a bank of `N` operators never needs more than `N`.
const MAX_SEGMENTS: usize = MAX_CANONICAL_OPERATORS;

/// [`Segment::direction`] of a segment whose operator outputs are stored one by one.
const EXPLICIT: i32 = 0;

/// Operators that were left together: a run that reversed, or the stored outputs of a state
/// built from arbitrary operator outputs.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Segment {
    /// One past the segment's last operator. Its first operator is the end of the segment
    /// above it on the stack, or the end of the current run for the top one.
    end: usize,
    /// The input at which the run reversed (a past extremum), Q2.30.
    extremum: i32,
    /// +1: the run was rising, outputs `extremum − r_i`; −1: falling, `extremum + r_i`;
    /// [`EXPLICIT`]: the outputs are in [`PiState::explicit`].
    direction: i32,
}

/// The memory of a bank of play operators.
///
/// A play operator bank remembers the input's past extrema (the wiping-out property): at any
/// time the operators form runs. The first `following` operators follow the input in its
/// present direction `d` (`p_i = x − d·r_i`); the rest are frozen in segments, each left by a
/// run that reversed at an extremum `e` (`p_i = e ∓ r_i`), below the oldest of which lie the
/// outputs of the state the bank started from, stored one by one. The state keeps that stack
/// of segments and `base`, chosen so that the bank's sum is `base + W_following · x` with
/// `W_k = Σ_{i<k} w_i` — one multiply-accumulate per step however many operators follow. See
/// [`PlayOperatorBank`] for the step.
///
/// The fields are private: every state comes from a constructor that establishes the bank's
/// invariant. Equality compares the live memory (the run, the segments in use and the stored
/// outputs still in use), not slots left over from earlier steps; two states reached by
/// different paths can still hold the same outputs and compare unequal — compare
/// [`PlayOperatorBank::outputs`] for the operators' values.
#[derive(Clone, Copy, Debug)]
pub struct PiState {
    /// Last input `x`, Q2.30.
    input: i32,
    /// Direction of the current run: +1 rising, −1 falling, 0 before the first move.
    direction: i32,
    /// Operators `[0, following)` follow the input.
    following: usize,
    /// `W_following`, Q8.24.
    run_weight: i32,
    /// The input beyond which (in the run's direction) the next frozen operator moves, Q2.30.
    trigger: i32,
    /// The bank's sum less `run_weight · input`, Q10.54.
    base: i64,
    /// Segments in use: `segments[depth − 1]` lies next to the current run.
    depth: usize,
    /// Frozen segments, oldest (highest operators) first.
    segments: [Segment; MAX_SEGMENTS],
    /// Stored operator outputs, Q2.30; they hold for the operators of an [`EXPLICIT`] segment.
    explicit: [i32; MAX_CANONICAL_OPERATORS],
}

impl PiState {
    /// The parts of the state in use (see the type's equality).
    #[allow(clippy::type_complexity)]
    fn live(&self) -> ((i32, i32, usize, i32, i32, i64), &[Segment], &[i32]) {
        let s = self;
        {
            let depth = s.depth.min(MAX_SEGMENTS);
            // The stored outputs in use: those of the bottom segment, if it is explicit.
            let stored = match s.segments[..depth].first() {
                Some(bottom) if bottom.direction == EXPLICIT => {
                    let start = s.segments[..depth]
                        .get(1)
                        .map_or(s.following, |above| above.end);
                    s.explicit.get(start..bottom.end).unwrap_or(&[])
                }
                _ => &[],
            };
            (
                (
                    s.input,
                    s.direction,
                    s.following,
                    s.run_weight,
                    s.trigger,
                    s.base,
                ),
                &s.segments[..depth],
                stored,
            )
        }
    }
}

impl PartialEq for PiState {
    fn eq(&self, other: &Self) -> bool {
        self.live() == other.live()
    }
}

impl Eq for PiState {}

impl PiState {
    /// The last input, Q2.30.
    pub fn input(&self) -> i32 {
        self.input
    }
}

/// A bank of play operators and their weights: `Σ_i w_i · P_{r_i}[x]`.
///
/// **A step costs one multiply-accumulate, plus a little for each operator that starts to
/// move.** With thresholds increasing, the states of a bank satisfy
/// `|p_{i+1} − p_i| ≤ r_{i+1} − r_i` (a play update is a clamp, which keeps that bound
/// exactly, in integers too), so the operators that move on a step form a prefix. While the
/// input keeps its direction `d`, the operators it has engaged follow it (`p_i = x − d·r_i`),
/// so their part of the sum is `W_k x` plus a constant, with the prefix sums
/// `W_k = Σ_{i<k} w_i` precomputed here. A step therefore only compares the input with the
/// trigger of the next frozen operator — usually it holds — and evaluates `base + W_k x`
/// ([`PiState`]). When the input reverses, the run freezes as a segment at that extremum
/// (constant time); a later run that passes the extremum takes the whole segment back at once
/// (the wiping-out property), and one that reaches into a segment left by a run the other way
/// takes its operators one by one. In exact integers the sum equals, bit for bit, updating
/// every operator and summing every product (property tests check it); no operator that
/// moves can saturate, since it moves toward the input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlayOperatorBank {
    len: usize,
    /// Thresholds `r_i`, Q2.30 normalised, increasing.
    thresholds: [i32; MAX_CANONICAL_OPERATORS],
    /// Weights `w_i`, Q8.24 normalised.
    weights: [i32; MAX_CANONICAL_OPERATORS],
    /// `W_k = Σ_{i<k} w_i`, Q8.24, `k = 0 ..= len` (|W_k| ≤ Σ|w_i| ≤ 64 by validation).
    weight_prefix: [i32; MAX_CANONICAL_OPERATORS + 1],
}

impl PlayOperatorBank {
    fn from_canonical(c: &CanonicalPi) -> Result<Self, ParamError> {
        c.check_fixed_point_range()?;
        let mut bank = Self {
            len: c.thresholds.len().min(MAX_CANONICAL_OPERATORS),
            thresholds: [0; MAX_CANONICAL_OPERATORS],
            weights: [0; MAX_CANONICAL_OPERATORS],
            weight_prefix: [0; MAX_CANONICAL_OPERATORS + 1],
        };
        let mut w_sum = 0i32;
        for (i, (&r, &w)) in c.thresholds.iter().zip(c.weights.iter()).enumerate() {
            let (r, w) = (signal_from_f64(r), gain_from_f64(w));
            bank.thresholds[i] = r;
            bank.weights[i] = w;
            // Σ|w| ≤ 64 (validated): the partial sums fit Q8.24.
            w_sum = w_sum.saturating_add(w);
            bank.weight_prefix[i + 1] = w_sum;
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
        let mut p = [0; MAX_CANONICAL_OPERATORS];
        let n = self.len;
        p[..n].copy_from_slice(&state.explicit[..n]);
        let mut start = state.following.min(n);
        for (out, &r) in p.iter_mut().zip(&self.thresholds).take(start) {
            *out = moved(state.input, state.direction, r);
        }
        for seg in state.segments[..state.depth.min(MAX_SEGMENTS)].iter().rev() {
            let end = seg.end.clamp(start, n);
            if seg.direction != EXPLICIT {
                for (out, &r) in p[start..end].iter_mut().zip(&self.thresholds[start..end]) {
                    *out = moved(seg.extremum, seg.direction, r);
                }
            }
            start = end;
        }
        p
    }

    /// Advances the bank by input `x` (Q2.30) and returns `Σ w_i p_i` as a Q10.54 accumulator.
    /// Validation bounds `Σ|w_i| · 2` below `2^63 / 2^54`, so the sum cannot overflow.
    ///
    /// The common step — the input moves on in its direction and the next frozen operator
    /// holds — is two compares against the state's trigger and one multiply-accumulate; the
    /// rest is in [`Self::reverse`] and [`Self::engage`], kept out of line.
    #[inline(always)]
    fn step(&self, s: &mut PiState, x: i32) -> i64 {
        if x > s.input {
            if s.direction <= 0 {
                self.reverse::<true>(s, x);
            } else if x > s.trigger {
                self.engage::<true>(s, x);
            }
        } else if x < s.input {
            if s.direction >= 0 {
                self.reverse::<false>(s, x);
            } else if x < s.trigger {
                self.engage::<false>(s, x);
            }
        }
        s.input = x;
        s.base + s.run_weight as i64 * x as i64
    }

    /// The input reversed (or made its first move) toward `x`, now rising if `UP`: the run
    /// that followed it stays at the last input, as a segment; then the operators `x` pushes
    /// are taken.
    #[inline(never)]
    fn reverse<const UP: bool>(&self, s: &mut PiState, x: i32) {
        if s.following > 0 {
            // The run's part of the sum, W_k x − d R_k, becomes frozen: base' = base + W_k x.
            s.base += s.run_weight as i64 * s.input as i64;
            // Every segment holds an operator, so the stack has room (depth < len ≤ capacity).
            if let Some(slot) = s.segments.get_mut(s.depth) {
                *slot = Segment {
                    end: s.following,
                    extremum: s.input,
                    direction: s.direction,
                };
                s.depth += 1;
            }
            s.following = 0;
            s.run_weight = 0;
            s.direction = if UP { 1 } else { -1 };
            // The first operator of the run just frozen has threshold 0 in every canonical
            // bank (P–I's `a0` term, the inverse's `r'_1`), so its trigger is the extremum
            // itself, which `x` has just left: it moves. If the second holds — the common
            // case — the reversal is done without the general walk.
            let e = s.input;
            if let (Some(&0), Some(&w), Some(&r), Some(true)) = (
                self.thresholds.first(),
                self.weights.first(),
                self.thresholds.get(1),
                s.segments
                    .get(s.depth.wrapping_sub(1))
                    .map(|seg| seg.end > 1),
            ) {
                let t = if UP {
                    e.wrapping_add(r).saturating_add(r)
                } else {
                    e.wrapping_sub(r).saturating_sub(r)
                };
                let holds = if UP { x <= t } else { x >= t };
                if holds {
                    s.base -= w as i64 * e as i64;
                    s.following = 1;
                    s.run_weight = w;
                    s.trigger = t;
                    return;
                }
            }
        }
        s.direction = if UP { 1 } else { -1 };
        self.engage::<UP>(s, x);
    }

    /// Takes into the run every frozen operator that input `x` (rising if `UP`) pushes, and
    /// sets the trigger for the next one.
    ///
    /// Operator `k` with output `p` moves iff `x − d·r_k` is beyond `p`, i.e. `x` is beyond
    /// its trigger `t_k = p + d·r_k`; it then joins the run (`p' = x − d·r_k`) and the sum's
    /// `base` loses `w_k p + d w_k r_k = w_k t_k` (see [`PiState`]). A trigger that is passed
    /// lies in the input's range, so `t_k` is exact there. Bounded: one pass per segment, and
    /// within a segment one per operator.
    #[inline(never)]
    fn engage<const UP: bool>(&self, s: &mut PiState, x: i32) {
        let d = if UP { 1 } else { -1 };
        let beyond = |t: i32| if UP { x > t } else { x < t };
        let never = if UP { i32::MAX } else { i32::MIN };
        // Work on locals; the state is written once, at the end.
        let (mut base, mut k, mut depth) = (s.base, s.following, s.depth);
        let trigger = 'walk: {
            for _ in 0..=MAX_SEGMENTS {
                let Some(seg) = depth.checked_sub(1).and_then(|top| s.segments.get(top)) else {
                    break 'walk never; // every operator follows: nothing left to trigger
                };
                let end = seg.end.min(self.len);
                let e = seg.extremum;
                if seg.direction == d {
                    // Left at `e − d·r` by a run in this direction: all move once x passes e.
                    if !beyond(e) {
                        break 'walk e;
                    }
                    let (Some(&w0), Some(&w1)) =
                        (self.weight_prefix.get(k), self.weight_prefix.get(end))
                    else {
                        break 'walk never; // unreachable: k ≤ end ≤ len ≤ capacity
                    };
                    base -= (w1 - w0) as i64 * e as i64; // |Σ w| ≤ 64
                    k = end;
                    depth -= 1;
                    continue;
                }
                let (Some(thresholds), Some(weights), Some(stored)) = (
                    self.thresholds.get(k..end),
                    self.weights.get(k..end),
                    s.explicit.get(k..end),
                ) else {
                    break 'walk never; // unreachable: k ≤ end ≤ len ≤ capacity
                };
                let explicit = seg.direction == EXPLICIT;
                for ((&r, &w), &p) in thresholds.iter().zip(weights).zip(stored) {
                    // Output `p` stored, or `e + d·r` left by a run the other way (a value
                    // the operator held: no overflow); the trigger is one more `d·r` on.
                    let t = match (explicit, UP) {
                        (true, true) => p.saturating_add(r),
                        (true, false) => p.saturating_sub(r),
                        (false, true) => e.wrapping_add(r).saturating_add(r),
                        (false, false) => e.wrapping_sub(r).saturating_sub(r),
                    };
                    if !beyond(t) {
                        break 'walk t;
                    }
                    base -= w as i64 * t as i64;
                    k += 1;
                }
                depth -= 1;
            }
            never // unreachable: the loop runs out only after every segment is taken
        };
        s.base = base;
        s.following = k;
        s.depth = depth;
        s.run_weight = self.weight_prefix.get(k).copied().unwrap_or(0);
        s.trigger = trigger;
    }

    /// A state from operator outputs: projected onto the bank's invariant
    /// (`p_1 = x`, `|p_{i+1} − p_i| ≤ r_{i+1} − r_i`, `|p_i − x| ≤ r_i`), stored one by one.
    #[inline(never)] // configuration, off the tick path: one copy in flash
    fn state_from(&self, mut operators: [i32; MAX_CANONICAL_OPERATORS], x: i32) -> PiState {
        let mut previous: Option<(i32, i32)> = None; // (p, r) of the operator before
        let mut sum = 0i64;
        for ((&r, &w), p) in self
            .thresholds
            .iter()
            .zip(&self.weights)
            .zip(operators.iter_mut())
            .take(self.len)
        {
            let mut v = play(x, r, *p);
            if let Some((pp, pr)) = previous {
                let d = r.saturating_sub(pr);
                v = limit(v, pp.saturating_sub(d), pp.saturating_add(d));
            }
            *p = v;
            previous = Some((v, r));
            sum += w as i64 * v as i64;
        }
        let mut segments = [Segment::default(); MAX_SEGMENTS];
        segments[0] = Segment {
            end: self.len,
            extremum: 0,
            direction: EXPLICIT,
        };
        PiState {
            input: x,
            direction: 0,
            following: 0,
            run_weight: 0,
            trigger: x,
            base: sum,
            depth: 1,
            segments,
            explicit: operators,
        }
    }

    /// State with every operator at `x` (the relaxed state after resting at input `x`).
    fn state_at(&self, x: i32) -> PiState {
        self.state_from([x; MAX_CANONICAL_OPERATORS], x)
    }
}

/// Output of an operator with threshold `r` pushed by input `x` in direction `d`:
/// `x − d·r` (and `x` itself before any move, `d = 0`).
#[inline(always)]
fn moved(x: i32, d: i32, r: i32) -> i32 {
    match d.signum() {
        1 => x.saturating_sub(r),
        -1 => x.saturating_add(r),
        _ => x,
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

    /// The relaxed state after resting at input `u` (Q2.30): every operator at `u`.
    pub fn state_at_rest(&self, u: i32) -> PiState {
        self.bank.state_at(clamp_full_scale(u))
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

    /// The relaxed state after resting at desired output `y` (Q2.30).
    pub fn state_at_rest(&self, y: i32) -> PiState {
        self.bank
            .state_at(clamp_full_scale(y).saturating_sub(self.offset))
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

    /// The plain definition: update every operator, sum every product.
    fn exhaustive_step(
        bank: &PlayOperatorBank,
        p: &mut [i32; MAX_CANONICAL_OPERATORS],
        x: i32,
    ) -> i64 {
        let mut sum = 0;
        let n = bank.len;
        for ((p, &r), &w) in p[..n].iter_mut().zip(&bank.thresholds).zip(&bank.weights) {
            *p = play(x, r, *p);
            sum += w as i64 * *p as i64;
        }
        sum
    }

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

    /// Runs `inputs` through the bank and the plain definition side by side.
    fn check_against_exhaustive(
        bank: &PlayOperatorBank,
        mut state: PiState,
        inputs: impl Iterator<Item = i32>,
    ) -> Result<(), TestCaseError> {
        let n = bank.len;
        let mut plain = bank.outputs(&state);
        for x in inputs {
            let fast = bank.step(&mut state, x);
            let slow = exhaustive_step(bank, &mut plain, x);
            prop_assert_eq!(fast, slow, "sum at x = {}", x);
            prop_assert_eq!(&bank.outputs(&state)[..n], &plain[..n]);
            prop_assert!(
                state.depth <= n.max(1),
                "depth {} for {} operators",
                state.depth,
                n
            );
        }
        Ok(())
    }

    proptest! {
        /// The memory stack gives, bit for bit, the states and the sum of updating every
        /// operator — over random banks and random inputs, jumps included.
        #[test]
        fn memory_stack_equals_the_exhaustive_update_on_jumps(
            n in 1usize..=32,
            weights in prop::collection::vec(-1.0f64..1.0, 32),
            geometric in any::<bool>(),
            inputs in prop::collection::vec(-1.0f64..=1.0, 1..300),
            start in -1.0f64..=1.0,
        ) {
            let bank = bank(n, &weights, geometric);
            let state = bank.state_at(signal_from_f64(start));
            check_against_exhaustive(&bank, state, inputs.iter().map(|&u| signal_from_f64(u)))?;
        }

        /// The same over random walks: small steps that reverse often, so that runs reach
        /// part-way into segments left by runs the other way (nested minor loops), and an
        /// input that may leave [-1, 1] as the inverse's does (`y − c`).
        #[test]
        fn memory_stack_equals_the_exhaustive_update_on_minor_loops(
            n in 1usize..=32,
            weights in prop::collection::vec(-1.0f64..1.0, 32),
            geometric in any::<bool>(),
            steps in prop::collection::vec(-0.2f64..0.2, 1..600),
            start in -1.5f64..=1.5,
        ) {
            let bank = bank(n, &weights, geometric);
            let state = bank.state_at(signal_from_f64(start));
            let mut x = start;
            let inputs = steps.iter().map(move |&dx| {
                x = (x + dx).clamp(-1.9, 1.9);
                signal_from_f64(x)
            });
            check_against_exhaustive(&bank, state, inputs)?;
        }

        /// Starting from arbitrary operator outputs (projected onto the invariant), as a
        /// state derived from another model's is.
        #[test]
        fn memory_stack_equals_the_exhaustive_update_from_stored_outputs(
            n in 1usize..=32,
            weights in prop::collection::vec(-1.0f64..1.0, 32),
            outputs in prop::collection::vec(-1.0f64..=1.0, 33),
            inputs in prop::collection::vec(-1.0f64..=1.0, 1..100),
            start in -1.0f64..=1.0,
        ) {
            let bank = bank(n, &weights, false);
            let mut p = [0; MAX_CANONICAL_OPERATORS];
            for (q, &v) in p.iter_mut().zip(&outputs) {
                *q = signal_from_f64(v);
            }
            let state = bank.state_from(p, signal_from_f64(start));
            check_against_exhaustive(&bank, state, inputs.iter().map(|&u| signal_from_f64(u)))?;
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
