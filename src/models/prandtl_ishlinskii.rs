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
//! Formats: signals Q2.30 normalised at the models' interfaces (see [`crate::fixed_point`]);
//! inside the bank the input, the operators' outputs and the thresholds are Q1.15 halfwords,
//! two to a word (see [`PlayOperatorBank`]); weights Q8.24 normalised (output span per input
//! span), multiplied in two 16-bit halves; the sum is exact in a Q25.39 `i64`, brought back to
//! Q2.30 once per step (rounding toward −∞, saturating).
//!
//! The inverse's offset is applied after the bank: the play operator commutes with a shift
//! (`P_r[y − c] = P_r[y] − c` from shifted states), so `Σ w'_i P_{r'_i}[y − c] =
//! Σ w'_i P_{r'_i}[y] − c·Σ w'_i`: the inverse's operators run on the clamped setpoint itself,
//! whose range `[−1, 1]` is the Q1.15 lane's, and `c·Σ w'_i` is a constant of the model.

use crate::fixed_point::{
    gain_from_f64, limit, q39_to_signal_floor, saturate_q54_to_signal, signal_from_f64,
    Q39_FRAC_BITS, SIGNAL_FRAC_BITS,
};
use crate::models::params::{CanonicalPi, ParamError, PiParams, MAX_CANONICAL_OPERATORS};
use crate::models::play_operator::{lanes, pack, play, play2, smlald, OFFSET_BINARY};
use crate::models::{Forward, Hysteresis, Inverse, Rest};
use crate::scaling::Scaling;

/// Operator pairs a bank holds: [`MAX_CANONICAL_OPERATORS`] two to a word, rounded up.
pub const MAX_PAIRS: usize = MAX_CANONICAL_OPERATORS.div_ceil(2);
// `PlayOperatorBank::step` writes its pairs out, 0 … 16: one per word of the largest bank.
const _: () = assert!(MAX_PAIRS == 17);

/// Largest threshold of the packed bank, Q1.15 units (`2 − 2^-15`, one unsigned lane). An
/// operator's input and state stay within `[−1, 1 − 2^-15]`, where this threshold already
/// never moves the operator, so every larger one is held exactly.
pub const MAX_THRESHOLD_Q15: i32 = u16::MAX as i32;

/// A threshold (normalised, `0 ≤ r ≤ 2`) in Q1.15 units, rounded to nearest, within
/// `[0, MAX_THRESHOLD_Q15]`.
pub fn threshold_q15(r: f64) -> i32 {
    let v = r * 32768.0 + 0.5;
    if v >= MAX_THRESHOLD_Q15 as f64 {
        MAX_THRESHOLD_Q15
    } else if v >= 0.0 {
        v as i32 // truncation of a non-negative value: rounding to nearest
    } else {
        0 // negative or NaN (validation refuses both)
    }
}

/// A Q2.30 signal as a Q1.15 lane: rounded to nearest, clamped to `[−1, 1 − 2^-15]` (the
/// models' full-scale clamp and the conversion in one saturation).
#[inline(always)]
pub fn signal_to_q15(x: i32) -> i32 {
    (x.saturating_add(1 << 14) >> 15).clamp(i16::MIN as i32, i16::MAX as i32)
}

/// The memory of a bank of play operators: each operator's output, Q1.15, two to a word.
///
/// The fields are private: every state comes from a constructor that establishes the bank's
/// invariant (`|p_{i+1} − p_i| ≤ r_{i+1} − r_i`, `|p_i − x| ≤ r_i`, every `p_i` in
/// `[−1, 1 − 2^-15]`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PiState {
    /// Operator `2k` in the low half of word `k`, `2k + 1` in the high half, offset binary
    /// (`p + 2^15`, see [`crate::models::play_operator`]; slots past the bank's operators follow the
    /// input and weigh 0).
    pairs: [u32; MAX_PAIRS],
}

/// One pair of operators' configuration, as the tick loads it (one `LDM`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct PairConfig {
    /// Thresholds, Q1.15 unsigned lanes (`0 … 2 − 2^-15`).
    band: u32,
    /// The weights' high halves `(w − w_lo) / 2^16` (signed lanes; Q8.24 weights).
    w_hi: u32,
    /// The weights' low halves, sign-extended (`w_lo ∈ [−2^15, 2^15)`).
    w_lo: u32,
}

/// A bank of play operators and their weights: `Σ_i w_i · P_{r_i}[x]`.
///
/// **Two operators per word, every operator every step.** Each pair's update is
/// [`play2`] — `UQADD16` and `UQSUB16` for the band's edges, `USUB16` + `SEL` twice for
/// `max(x − r, min(x + r, p))` — no branch on the input, so a reversal, a jump across the whole
/// range or the first step after a reload costs what a smooth step costs. The sum is an `EOR`
/// (offset binary back to signed) and two `SMLALD` per pair, one per 16-bit half of the Q8.24
/// weights (`w = w_hi · 2^16 + w_lo`), in two 64-bit accumulators combined once: exact, Q25.39.
///
/// Precision: the input and the operators' outputs are Q1.15 (a 16-bit converter's step,
/// 1 LSB16); the input is rounded to that grid and the thresholds too, so an output differs
/// from the `f64` model by up to about half a step times the model's slope, plus the
/// thresholds' rounding weighted by the weights (measured in `twinstack_identify::accuracy`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct PlayOperatorBank {
    len: usize,
    /// Pairs in use, `⌈len / 2⌉`.
    pairs: usize,
    config: [PairConfig; MAX_PAIRS],
}

impl PlayOperatorBank {
    fn from_canonical(c: &CanonicalPi) -> Result<Self, ParamError> {
        c.check_fixed_point_range()?;
        let len = c.thresholds.len().min(MAX_CANONICAL_OPERATORS);
        let mut t = [0i32; MAX_CANONICAL_OPERATORS + 1];
        let mut w = [0i32; MAX_CANONICAL_OPERATORS + 1];
        for (i, (&r, &g)) in c
            .thresholds
            .iter()
            .zip(c.weights.iter())
            .enumerate()
            .take(len)
        {
            t[i] = threshold_q15(r);
            w[i] = gain_from_f64(g);
        }
        let mut bank = Self {
            len,
            pairs: len.div_ceil(2),
            config: [PairConfig::default(); MAX_PAIRS],
        };
        let split = |g: i32| {
            let lo = g as i16 as i32;
            let hi = ((g as i64 - lo as i64) >> 16).clamp(i16::MIN as i64, i16::MAX as i64);
            (hi as i32, lo)
        };
        for (k, pc) in bank.config.iter_mut().enumerate() {
            let (a, b) = (2 * k, 2 * k + 1);
            let ((ha, la), (hb, lb)) = (split(w[a]), split(w[b]));
            *pc = PairConfig {
                band: pack(t[a], t[b]),
                w_hi: pack(ha, hb),
                w_lo: pack(la, lb),
            };
        }
        Ok(bank)
    }

    /// Number of play operators in use.
    pub fn operators(&self) -> usize {
        self.len
    }

    /// Threshold of operator `i + 1`, Q1.15 units (`0 … `[`MAX_THRESHOLD_Q15`]; 0 past the
    /// end).
    pub fn threshold(&self, i: usize) -> i32 {
        match self.config.get(i / 2) {
            Some(p) if i < self.len => (p.band >> (16 * (i % 2)) & 0xffff) as i32,
            _ => 0,
        }
    }

    /// Weight of operator `i + 1`, Q8.24 normalised (0 past the end).
    pub fn weight(&self, i: usize) -> i32 {
        let lane = |w: u32| if i % 2 == 0 { lanes(w).0 } else { lanes(w).1 };
        match self.config.get(i / 2) {
            Some(p) if i < self.len => lane(p.w_hi).wrapping_shl(16).wrapping_add(lane(p.w_lo)),
            _ => 0,
        }
    }

    /// Sum of the weights `Σ w_i`, Q8.24 (exact, in `i64`).
    fn weight_sum(&self) -> i64 {
        (0..self.len).map(|i| self.weight(i) as i64).sum()
    }

    /// The operators' outputs `p_i` in `state`, Q2.30 (slots past [`Self::operators`] are 0).
    pub fn outputs(&self, state: &PiState) -> [i32; MAX_CANONICAL_OPERATORS] {
        let mut out = [0; MAX_CANONICAL_OPERATORS];
        for (i, o) in out.iter_mut().enumerate().take(self.len) {
            let (lo, hi) = lanes(state.pairs[i / 2] ^ OFFSET_BINARY);
            *o = (if i % 2 == 0 { lo } else { hi }) << 15;
        }
        out
    }

    /// Advances the bank by input `x` (a Q1.15 lane, [`signal_to_q15`]) and returns
    /// `start + Σ w_i p_i`, Q25.39. Constant time: every pair, every step (see the type's doc).
    ///
    /// Written out pair by pair, each behind a compare with the bank's pair count, rather than
    /// as a loop: a loop pays its counter, its reload and a taken branch (with the flash's
    /// wait states) on every pair, about 40 % of a pair's cost; here a bank pays one taken
    /// branch, where its pairs end. One copy in flash (not inlined): the call costs less than
    /// the eight inlined copies the tick's model variants would take.
    #[inline(never)]
    fn step(&self, s: &mut PiState, x: i32, start: i64) -> i64 {
        let xx = pack(x, x) ^ OFFSET_BINARY;
        let pairs = self.pairs;
        let (mut hi, mut lo) = (0i64, start);
        macro_rules! pairs {
            ($($k:literal)*) => {$(
                if $k >= pairs {
                    return (hi << 16).wrapping_add(lo);
                }
                let c = &self.config[$k];
                let p = play2(xx, c.band, s.pairs[$k]);
                s.pairs[$k] = p;
                let signed = p ^ OFFSET_BINARY;
                hi = smlald(hi, signed, c.w_hi);
                lo = smlald(lo, signed, c.w_lo);
            )*};
        }
        pairs!(0 1 2 3 4 5 6 7 8 9 10 11 12 13 14 15 16);
        // |Σ w_hi p| < 33 · 2^30: the shift cannot overflow.
        (hi << 16).wrapping_add(lo)
    }

    /// A state from operator outputs (Q1.15 units), projected onto the bank's invariant
    /// (`p_1 = x`, `|p_{i+1} − p_i| ≤ r_{i+1} − r_i`, `|p_i − x| ≤ r_i`, within the lane).
    #[inline(never)] // configuration, off the tick path: one copy in flash
    fn state_from(&self, operators: [i32; MAX_CANONICAL_OPERATORS], x: i32) -> PiState {
        let x = x.clamp(i16::MIN as i32, i16::MAX as i32);
        let mut p = [x; MAX_PAIRS * 2];
        let mut previous: Option<(i32, i32)> = None; // (p, r) of the operator before
        for (i, (slot, &raw)) in p.iter_mut().zip(operators.iter()).enumerate() {
            if i >= self.len {
                break;
            }
            let r = self.threshold(i);
            let mut v = play(x, r, raw).clamp(i16::MIN as i32, i16::MAX as i32);
            if let Some((pp, pr)) = previous {
                let d = r.saturating_sub(pr);
                v = limit(v, pp.saturating_sub(d), pp.saturating_add(d));
            }
            *slot = v;
            previous = Some((v, r));
        }
        let mut pairs = [0u32; MAX_PAIRS];
        for (k, w) in pairs.iter_mut().enumerate() {
            *w = pack(p[2 * k], p[2 * k + 1]) ^ OFFSET_BINARY;
        }
        PiState { pairs }
    }

    /// The operators' outputs (Q1.15) after the input went to the top of the range and back
    /// down to the bottom (the major loop's bottom): `p_i = min(−1 + r_i, max(1 − r_i, −1))`,
    /// for thresholds `r_i` in Q1.15 units.
    fn major_loop_bottom(thresholds: &[i32]) -> [i32; MAX_CANONICAL_OPERATORS] {
        let (bottom, top) = (i16::MIN as i32, i16::MAX as i32);
        let mut p = [bottom; MAX_CANONICAL_OPERATORS];
        for (p, &r) in p.iter_mut().zip(thresholds) {
            *p = (bottom + r).min((top - r).max(bottom));
        }
        p
    }

    /// The state at rest at input `x` (Q1.15) on the ascending branch (see the module doc):
    /// the major loop's bottom, then the input raised to `x`.
    fn state_at_rest(&self, x: i32) -> PiState {
        let r: [i32; MAX_CANONICAL_OPERATORS] = core::array::from_fn(|i| self.threshold(i));
        self.state_from(Self::major_loop_bottom(&r[..self.len]), x)
    }

    /// State with every operator at `x` (Q1.15; the virgin state, demagnetised at `x`:
    /// [`crate::models::Rest::Relaxed`]).
    pub fn state_at(&self, x: i32) -> PiState {
        let x = x.clamp(i16::MIN as i32, i16::MAX as i32);
        PiState {
            pairs: [pack(x, x) ^ OFFSET_BINARY; MAX_PAIRS],
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
    /// Play operators the tick runs (the canonical count: `a0` is operator 0).
    pub fn operators(&self) -> usize {
        self.bank.operators()
    }

    /// Validates `params` (physical units) and converts them, normalised by `scaling`, into
    /// the fixed-point form the tick runs.
    ///
    /// ```
    /// use twinstack::models::prandtl_ishlinskii::PrandtlIshlinskii;
    /// use twinstack::{PiParams, Scaling};
    /// // Play operators at 0 and 70 V (0.3 and 0.2 µm/V): 0…140 V onto 0…70 µm.
    /// let params = PiParams::new(0.0, 0.0, &[0.0, 70.0], &[0.3, 0.2]).unwrap();
    /// let model = PrandtlIshlinskii::new(&params, &Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap()).unwrap();
    /// let mut rest = model.state_at_rest(-(1 << 30)); // relaxed at 0 V
    /// // Up to 140 V: 0.3·140 + 0.2·70 = 56 µm, i.e. 0.6 of the normalised range.
    /// let y = model.step(&mut rest, (1 << 30) - 1);
    /// // (within one LSB16, 2^-15: the operators run on a Q1.15 grid)
    /// assert!((y as f64 / (1 << 30) as f64 - 0.6).abs() < 1.0 / 32768.0);
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
        self.bank.state_at_rest(signal_to_q15(u))
    }

    /// One sample: input `u` (Q2.30 normalised drive, clamped to [-1, 1]) → output `y`
    /// (Q2.30 normalised displacement, saturated).
    #[inline(always)]
    pub fn step(&self, state: &mut PiState, u: i32) -> i32 {
        let offset = (self.offset as i64) << (Q39_FRAC_BITS - SIGNAL_FRAC_BITS);
        q39_to_signal_floor(self.bank.step(state, signal_to_q15(u), offset))
    }
}

/// Analytic inverse P–I, fixed point: `u = Σ w'_i P_{r'_i}[y_d − c]` (the compensator).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InversePrandtlIshlinskii {
    bank: PlayOperatorBank,
    /// Forward model's output offset `c`, Q2.30.
    offset: i32,
    /// `−c · Σ w'_i`, Q25.39: the offset, applied after the bank (see the module doc).
    bias: i64,
    /// Forward partial sums `S_i`, Q8.24, for [`Self::state_from_forward`].
    partial_sums: [i32; MAX_CANONICAL_OPERATORS],
    /// Forward weights `w_i`, Q8.24, for [`Self::state_from_forward`].
    forward_weights: [i32; MAX_CANONICAL_OPERATORS],
    /// Forward thresholds `r_i`, Q1.15 units ([`threshold_q15`]), to recognise the forward
    /// model ([`Self::inverts`]).
    forward_thresholds: [i32; MAX_CANONICAL_OPERATORS],
}

impl InversePrandtlIshlinskii {
    /// Play operators the tick runs (the canonical count).
    pub fn operators(&self) -> usize {
        self.bank.operators()
    }

    /// Builds the inverse of the forward model `params` (physical units), normalised by
    /// `scaling`. Refuses non-invertible models (`w_1 ≤ 0`, a partial sum `S_i ≤ 0`) with the
    /// first failing operator, and inverses whose weights do not fit Q8.24.
    ///
    /// ```
    /// use twinstack::models::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
    /// use twinstack::{PiParams, Scaling};
    /// let params = PiParams::new(0.0, 0.0, &[0.0, 70.0], &[0.3, 0.2]).unwrap();
    /// let ranges = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
    /// let (forward, inverse) = (
    ///     PrandtlIshlinskii::new(&params, &ranges).unwrap(),
    ///     InversePrandtlIshlinskii::new(&params, &ranges).unwrap(),
    /// );
    /// // The drive the inverse asks for makes the forward model reach the target.
    /// // Both at rest at 0 V: the inverse at the forward's output there.
    /// let mut f = forward.state_at_rest(-(1 << 30));
    /// let y0 = forward.step(&mut f, -(1 << 30));
    /// let mut i = inverse.state_at_rest(y0);
    /// let target = 1 << 28; // 0.25 of the normalised range
    /// let drive = inverse.step(&mut i, target);
    /// assert!((forward.step(&mut f, drive) - target).abs() < 1 << 15); // one LSB16
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
            forward_thresholds[i] = threshold_q15(r);
        }
        forward.check_fixed_point_range()?;
        let bank = PlayOperatorBank::from_canonical(&inverse)?;
        let offset = signal_from_f64(inverse.offset);
        // Q2.30 × Q8.24 = Q10.54, to Q25.39 (|c| ≤ 1.5, Σ|w'| ≤ 64: no overflow).
        let bias = -((offset as i64 * bank.weight_sum()) >> (54 - Q39_FRAC_BITS));
        Ok(Self {
            bank,
            offset,
            bias,
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
            // p'_i (Q2.30, relative to the offset) as the operator on the setpoint itself.
            *out = signal_to_q15(saturate_q54_to_signal(acc).saturating_add(self.offset));
        }
        // r'_1 = 0, so the inverse's input is its first operator's output.
        self.bank.state_from(operators, operators[0])
    }

    /// The state at rest at desired output `y` (Q2.30), matching the forward model's
    /// [`PrandtlIshlinskii::state_at_rest`]: the forward's major-loop bottom mapped by
    /// [`Self::state_from_forward`], then the input raised to `y` (a monotone model maps the
    /// history "top → bottom → u" to "top → bottom → y", so the inverse's operators end where
    /// that history leaves them).
    pub fn state_at_rest(&self, y: i32) -> PiState {
        let n = self.bank.operators();
        let bottom = PlayOperatorBank::major_loop_bottom(&self.forward_thresholds[..n]);
        let bottom: [i32; MAX_CANONICAL_OPERATORS] = core::array::from_fn(|i| bottom[i] << 15);
        let mapped = self.bank.outputs(&self.state_from_forward(&bottom));
        let ops: [i32; MAX_CANONICAL_OPERATORS] = core::array::from_fn(|i| mapped[i] >> 15);
        self.bank.state_from(ops, signal_to_q15(y))
    }

    /// One sample: desired displacement `y` (Q2.30 normalised, clamped to [-1, 1]) → drive `u`
    /// (Q2.30 normalised, saturated; the caller clamps it to the drive's limits).
    #[inline(always)]
    pub fn step(&self, state: &mut PiState, y: i32) -> i32 {
        q39_to_signal_floor(self.bank.step(state, signal_to_q15(y), self.bias))
    }
}

/// A P–I bank's cost beyond its operators (the inverse's and the forward's alike): the call
/// to the bank's step, the input's conversion, the sum's; cycles at 5 wait states (see
/// [`Hysteresis::cycles`]).
pub const PI_BASE_CYCLES: u32 = 92;
/// Each pair of play operators (one packed word) of a P–I bank (written out pair by pair:
/// 34 cycles as a loop).
pub const PI_PAIR_CYCLES: u32 = 22;

/// A P–I bank of `operators` operators in the tick, cycles at 5 wait states.
pub fn bank_cycles(operators: usize) -> u32 {
    PI_BASE_CYCLES + PI_PAIR_CYCLES * operators.div_ceil(2) as u32
}

impl Hysteresis for PrandtlIshlinskii {
    type State = PiState;

    #[inline(always)]
    fn step(&self, state: &mut PiState, u: i32) -> i32 {
        PrandtlIshlinskii::step(self, state, u)
    }

    fn cycles(&self) -> u32 {
        bank_cycles(self.operators())
    }
}

impl Forward for PrandtlIshlinskii {
    fn at_rest(&self, u: i32, rest: Rest) -> (PiState, i32) {
        let mut s = match rest {
            Rest::Ascending => self.state_at_rest(u),
            Rest::Relaxed => self.bank.state_at(signal_to_q15(u)),
        };
        let y = PrandtlIshlinskii::step(self, &mut s, u);
        (s, y)
    }
}

impl Hysteresis for InversePrandtlIshlinskii {
    type State = PiState;

    #[inline(always)]
    fn step(&self, state: &mut PiState, y: i32) -> i32 {
        InversePrandtlIshlinskii::step(self, state, y)
    }

    fn cycles(&self) -> u32 {
        bank_cycles(self.operators())
    }
}

impl Inverse for InversePrandtlIshlinskii {
    /// On the loop ([`InversePrandtlIshlinskii::state_at_rest`]), or every operator at `y`:
    /// the inverse of the forward's virgin state (its operators `p'_i = S_i p_i + Σ_{j>i}
    /// w_j p_j` all equal the output when every `p_j` equals the input).
    fn at_rest(&self, _u: i32, y: i32, rest: Rest) -> PiState {
        match rest {
            Rest::Ascending => self.state_at_rest(y),
            Rest::Relaxed => self.bank.state_at(signal_to_q15(y)),
        }
    }

    /// The operators from the observer's, where the observer is the model this inverts.
    type Forward = PrandtlIshlinskii;

    fn matching(&self, forward: &PrandtlIshlinskii, state: &PiState) -> Option<PiState> {
        self.inverts(forward)
            .then(|| self.state_from_forward(&forward.bank().outputs(state)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::models::params::Thresholds;
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
        /// threshold of the input, neighbours within their thresholds' difference, every
        /// output in the lane), and the sum is the exact weighted sum of the outputs.
        #[test]
        fn the_bank_keeps_its_invariant_and_sums_its_outputs(
            n in 1usize..=crate::models::params::MAX_OPERATORS,
            weights in proptest::collection::vec(-1.9f64..1.9, MAX_CANONICAL_OPERATORS),
            geometric: bool,
            start: i16,
            bias in -(1i64 << 50)..(1i64 << 50),
            inputs in proptest::collection::vec(any::<i16>(), 1..200),
        ) {
            let b = bank(n, &weights, geometric);
            let mut s = b.state_at(start as i32);
            for x in inputs {
                let x = x as i32;
                let sum = b.step(&mut s, x, bias);
                let p = b.outputs(&s).map(|v| v >> 15);
                let mut expected = bias;
                for i in 0..n {
                    let r = b.threshold(i);
                    prop_assert!((p[i] - x).abs() <= r, "operator {}", i + 1);
                    prop_assert!((i16::MIN as i32..=i16::MAX as i32).contains(&p[i]));
                    if i > 0 {
                        let d = r - b.threshold(i - 1);
                        prop_assert!((p[i] - p[i - 1]).abs() <= d);
                    }
                    expected += b.weight(i) as i64 * p[i] as i64;
                }
                prop_assert_eq!(sum, expected);
            }
        }

        /// The packed bank is the play operator, operator by operator: the same outputs as
        /// [`play`] on `i32` with the same (Q1.15) thresholds, wide thresholds included.
        #[test]
        fn the_packed_bank_is_the_scalar_play_operator(
            n in 1usize..=crate::models::params::MAX_OPERATORS,
            geometric: bool,
            inputs in proptest::collection::vec(any::<i16>(), 1..200),
        ) {
            let b = bank(n, &[0.1; MAX_CANONICAL_OPERATORS], geometric);
            let mut s = b.state_at(0);
            let mut scalar = [0i32; MAX_CANONICAL_OPERATORS];
            for x in inputs {
                let x = x as i32;
                b.step(&mut s, x, 0);
                for (i, p) in scalar.iter_mut().enumerate().take(n) {
                    *p = play(x, b.threshold(i), *p).clamp(i16::MIN as i32, i16::MAX as i32);
                }
                prop_assert_eq!(&b.outputs(&s).map(|v| v >> 15)[..n], &scalar[..n]);
            }
        }

        /// A state built from arbitrary outputs is projected onto the invariant, and one built
        /// from outputs that already satisfy it keeps them.
        #[test]
        fn states_from_outputs_are_projected_onto_the_invariant(
            n in 1usize..=crate::models::params::MAX_OPERATORS,
            outputs in proptest::array::uniform32(any::<i32>()),
            x: i16,
        ) {
            let b = bank(n, &[0.1; MAX_CANONICAL_OPERATORS], false);
            let mut raw = [0; MAX_CANONICAL_OPERATORS];
            raw[..32].copy_from_slice(&outputs.map(|v| v >> 15));
            let s = b.state_from(raw, x as i32);
            let p = b.outputs(&s).map(|v| v >> 15);
            for (i, &pi) in p.iter().enumerate().take(n) {
                prop_assert!((pi - x as i32).abs() <= b.threshold(i));
            }
            prop_assert_eq!(b.state_from(p, x as i32), s);
        }
    }

    #[test]
    fn thresholds_fill_one_unsigned_lane_and_weights_split_exactly() {
        let b = bank(16, &[0.1; MAX_CANONICAL_OPERATORS], false);
        assert_eq!(b.pairs, 8);
        // Uniform over 2.0: r_i = i / 8, above 1 from operator 10 on.
        assert_eq!(b.threshold(15), threshold_q15(15.0 / 8.0));
        assert_eq!(b.threshold(15), 61440);
        assert_eq!(threshold_q15(2.0), MAX_THRESHOLD_Q15);
        assert_eq!(threshold_q15(0.5), 1 << 14);
        assert_eq!(b.weight(3), gain_from_f64(0.1));
        assert_eq!(b.weight(16), 0);
        let c = CanonicalPi {
            thresholds: heapless::Vec::from_slice(&[0.0, 1.0]).unwrap(),
            weights: heapless::Vec::from_slice(&[-63.9, 0.000_123]).unwrap(),
            offset: 0.0,
        };
        let b = PlayOperatorBank::from_canonical(&c).unwrap();
        assert_eq!(
            (b.weight(0), b.weight(1)),
            (gain_from_f64(-63.9), gain_from_f64(0.000_123))
        );
    }

    /// At rest is the state the history "top of the range → bottom → u" leaves, whatever
    /// came before; and the inverse at rest at the forward's output composes with it to the
    /// identity from the first step (to a few LSB16: the bank's Q1.15 grid).
    #[test]
    fn at_rest_is_on_the_ascending_branch_and_the_inverse_matches_it() {
        use crate::fixed_point::{clamp_full_scale, FULL_SCALE_MAX, SIGNAL_ONE};
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
            let outputs = |s: &PiState| f.bank.outputs(s);
            assert_eq!(outputs(&s), outputs(&f.state_at_rest(u0)), "u0 = {u0}");
            // Not the virgin state (every operator at u0), except at the top.
            if u0 < 0 {
                assert_ne!(outputs(&s), outputs(&f.bank.state_at(signal_to_q15(u0))));
            }
            let mut fs = f.state_at_rest(u0);
            let y0 = f.step(&mut fs, u0);
            let mut is = inv.state_at_rest(y0);
            for k in 0..400i32 {
                let x = clamp_full_scale(u0 / 2 + ((k * 7919) % 2001 - 1000) * (1 << 20));
                let target = f.step(&mut fs, x);
                let drive = inv.step(&mut is, target);
                // 8 LSB16: the inverse's error bound for these weights (see twinstack_identify::accuracy).
                assert!(
                    (drive - x).abs() < 8 << 14,
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
