//! Creep: a few first-order modes in series with a hysteresis model, and the operator's exact
//! inverse, in fixed point.
//!
//! After a step in drive a piezo stack keeps moving for a while: a few % of the step arrives
//! late, roughly logarithmically in time. The creep operator `C` models that as a sum of
//! log-spaced first-order lags behind the hysteresis model's output `y` (normalised):
//!
//! * `z_k ← a_k z_k + b_k y` per tick, `a_k = exp(−T/τ_k)`, `b_k = 1 − a_k` (`T` the tick);
//! * `x = c0·y + Σ_k c_k·z_k`, `c_k ≥ 0`, `c0 = 1 − Σ_k c_k ≥ 1 − `[`MAX_WEIGHT_SUM`].
//!
//! The static gain is 1: the hysteresis model keeps meaning the settled displacement and the
//! weights are pure dynamics (the fraction of a step that arrives late, with time constant
//! `τ_k`). With non-negative weights and an instant part `c0 ≥ 0.1` the operator is minimum
//! phase, so its inverse is stable. One tick of the forward operator is
//! `x = D·y + Σ_k c_k a_k z_k` (states before the update) with `D = c0 + Σ_k c_k b_k =
//! 1 − Σ_k c_k a_k ≥ 0.1`, so the **exact inverse** is, per tick and on the same states,
//! `y = (x − Σ_k c_k a_k z_k) · (1/D)`, then the `z_k` are updated with that `y`.
//!
//! In the tick: the compensator runs `setpoint → C⁻¹ → H⁻¹ → drive`, the observer
//! `drive → H → C → estimate` (see [`crate::control`]).
//!
//! ## Formats
//!
//! | quantity | format | note |
//! |---|---|---|
//! | `y`, `x` | Q2.30 `i32` | the tick's signals |
//! | `z_k` | Q4.60 `i64` | `|z| ≤ 2`; 2^-60 resolves the increment `b·(y − z)` of τ = 100 s at 100 kHz (b ≈ 1e-7) |
//! | `y − z_k` | Q3.29 `i32` | `(y >> 1) − (z >> 31)`, saturating: the update's difference |
//! | `b_k` | Q0.32 `i32` | `b < 0.5` (τ ≥ 2 ticks); `b · (y − z)` is exact in `i64` (Q3.61), shifted to Q4.60 |
//! | `c_k`, `c_k a_k` | Q1.31 `i32` | weights in [0, 0.9]; `c0` is never formed: `x = y − Σ c_k (y − z_k)`, so the static gain is exactly 1 |
//! | `1/D` | Q5.27 `i32` | `1 ≤ 1/D ≤ 10` |
//! | sums | Q4.60 (forward), Q3.61 (inverse) `i64` | weight × signal products |
//!
//! The weights are Q1.31 rather than the models' Q8.24 gains: the inverse's `c_k a_k` and the
//! forward's effective `c_k (1 − b_k)` are rounded apart, and that mismatch, multiplied by
//! `|z − y| ≤ 4` and by `1/D ≤ 10`, would reach 0.2 LSB16 with Q8.24 (2^-25 per weight); with
//! Q1.31 it is 128 times smaller.
//!
//! **Resolution of τ.** `b` is rounded to 2^-32 (Q0.32), so its relative error is at most
//! `2^-33 / b`: for τ = 100 s at 100 kHz (`b = 1.0e-7`, 429.5 LSB) 1.2e-3 (τ is off by
//! 0.12 %); at the longest time constant accepted, [`MAX_TIME_CONSTANT_TICKS`] = 2^26 ticks
//! (671 s at 100 kHz, 1342 s at 50 kHz), `b` is 64 LSB and the error at most 0.8 %. A state
//! settles to within 2^-29 of its input (the difference is Q3.29).
//!
//! **Cost.** A step costs the same whatever the input does: per mode, a saturating subtract,
//! a 32 × 32 → 64 multiply and a 64-bit add for the update, and one multiply-accumulate for
//! the output; no division (the reciprocal `1/D` is formed in [`Creep::new`]).

use crate::models::Hysteresis;
use serde::{Deserialize, Serialize};

use crate::fixed_point::{
    q0_32_from_f64, q1_31_from_f64, q60_to_signal_floor, saturate_i64, SIGNAL_FRAC_BITS,
};
use heapless::Vec;

/// Most creep modes (first-order lags) an operator may have.
pub const MAX_CREEP_MODES: usize = 6;
// The creep operator's steps write their modes out, 0 … 5.
const _: () = assert!(MAX_CREEP_MODES == 6);
/// Largest sum of the creep weights: the instant part `c0` stays at least `1 − 0.9 = 0.1`,
/// so the inverse's gain `1/D` stays at most 10.
pub const MAX_WEIGHT_SUM: f64 = 0.9;
/// Shortest time constant, in ticks: `b = 1 − exp(−1/2) = 0.39` stays below the 0.5 that a
/// Q0.32 `b` holds.
pub const MIN_TIME_CONSTANT_TICKS: f64 = 2.0;
/// Longest time constant, in ticks (2^26): `b ≈ 2^-26` is 64 LSB of Q0.32, so `b` (and τ) is
/// resolved to 0.8 % or better.
pub const MAX_TIME_CONSTANT_TICKS: f64 = (1u64 << 26) as f64;

/// Why a set of creep parameters was refused. Mode numbers are 1-based.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CreepError {
    /// No mode: leave the creep out (`None`) instead.
    NoModes,
    /// More than [`MAX_CREEP_MODES`] modes.
    TooManyModes {
        /// How many were given.
        count: usize,
    },
    /// Time constants and weights differ in length.
    LengthMismatch {
        /// Number of time constants.
        time_constants: usize,
        /// Number of weights.
        weights: usize,
    },
    /// A time constant or weight is NaN or infinite, or the control rate is not a positive
    /// finite number (`mode` 0).
    NotFinite {
        /// Mode number, 1-based (0: the rate).
        mode: usize,
    },
    /// A time constant is shorter than [`MIN_TIME_CONSTANT_TICKS`] ticks.
    TimeConstantTooShort {
        /// Mode number, 1-based.
        mode: usize,
    },
    /// A time constant is longer than [`MAX_TIME_CONSTANT_TICKS`] ticks.
    TimeConstantTooLong {
        /// Mode number, 1-based.
        mode: usize,
    },
    /// Time constants must increase strictly; this one does not exceed its predecessor.
    TimeConstantsNotIncreasing {
        /// Mode number, 1-based.
        mode: usize,
    },
    /// A weight is negative.
    NegativeWeight {
        /// Mode number, 1-based.
        mode: usize,
    },
    /// The weights sum to more than [`MAX_WEIGHT_SUM`].
    WeightSumTooLarge,
}

impl core::fmt::Display for CreepError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        use CreepError::*;
        match *self {
            NoModes => write!(f, "the creep operator has no mode"),
            TooManyModes { count } => {
                write!(f, "{count} creep modes given, at most {MAX_CREEP_MODES}")
            }
            LengthMismatch {
                time_constants,
                weights,
            } => write!(
                f,
                "{time_constants} creep time constants but {weights} weights"
            ),
            NotFinite { mode: 0 } => write!(f, "the control rate is not a positive number"),
            NotFinite { mode } => write!(f, "creep mode {mode} is NaN or infinite"),
            TimeConstantTooShort { mode } => write!(
                f,
                "creep time constant {mode} is shorter than {MIN_TIME_CONSTANT_TICKS} ticks"
            ),
            TimeConstantTooLong { mode } => write!(
                f,
                "creep time constant {mode} is longer than {MAX_TIME_CONSTANT_TICKS} ticks"
            ),
            TimeConstantsNotIncreasing { mode } => write!(
                f,
                "creep time constant {mode} does not exceed the one before it"
            ),
            NegativeWeight { mode } => write!(f, "creep weight {mode} is negative"),
            WeightSumTooLarge => write!(f, "creep weights sum to more than {MAX_WEIGHT_SUM}"),
        }
    }
}

impl core::error::Error for CreepError {}

/// A creep operator in physical units: the modes' time constants (seconds) and weights (the
/// fraction of a step each mode delivers late). See the module doc.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CreepParams {
    /// Time constants `τ_k`, seconds, strictly increasing.
    pub time_constants_s: Vec<f64, MAX_CREEP_MODES>,
    /// Weights `c_k ≥ 0`, `Σ c_k ≤ 0.9`.
    pub weights: Vec<f64, MAX_CREEP_MODES>,
}

impl CreepParams {
    /// Parameters from time constants (s) and weights; only the counts are checked here
    /// (the rest by [`CreepParams::check`], which needs the control rate).
    ///
    /// ```
    /// use twinstack::models::creep::{CreepError, CreepParams};
    /// let p = CreepParams::new(&[0.01, 1.0], &[0.02, 0.03]).unwrap();
    /// assert!((p.instant_weight() - 0.95).abs() < 1e-12);
    /// assert_eq!(p.check(50_000.0), Ok(()));
    /// assert_eq!(CreepParams::new(&[0.01], &[]).unwrap_err(),
    ///            CreepError::LengthMismatch { time_constants: 1, weights: 0 });
    /// ```
    pub fn new(time_constants_s: &[f64], weights: &[f64]) -> Result<Self, CreepError> {
        if time_constants_s.len() != weights.len() {
            return Err(CreepError::LengthMismatch {
                time_constants: time_constants_s.len(),
                weights: weights.len(),
            });
        }
        let too_many = CreepError::TooManyModes {
            count: weights.len(),
        };
        Ok(Self {
            time_constants_s: Vec::from_slice(time_constants_s).map_err(|_| too_many)?,
            weights: Vec::from_slice(weights).map_err(|_| too_many)?,
        })
    }

    /// The instant part `c0 = 1 − Σ c_k`.
    pub fn instant_weight(&self) -> f64 {
        1.0 - self.weights.iter().sum::<f64>()
    }

    /// Checks the parameters for a tick at `control_rate_hz` (see [`CreepError`]).
    pub fn check(&self, control_rate_hz: f64) -> Result<(), CreepError> {
        use CreepError as E;
        if !(control_rate_hz.is_finite() && control_rate_hz > 0.0) {
            return Err(E::NotFinite { mode: 0 });
        }
        let (n, nw) = (self.time_constants_s.len(), self.weights.len());
        if n != nw {
            return Err(E::LengthMismatch {
                time_constants: n,
                weights: nw,
            });
        }
        if n == 0 {
            return Err(E::NoModes);
        }
        let mut previous = 0.0;
        for (i, (&tau, &c)) in self.time_constants_s.iter().zip(&self.weights).enumerate() {
            let mode = i + 1;
            if !(tau.is_finite() && c.is_finite()) {
                return Err(E::NotFinite { mode });
            }
            let ticks = tau * control_rate_hz;
            if ticks < MIN_TIME_CONSTANT_TICKS {
                return Err(E::TimeConstantTooShort { mode });
            }
            if ticks > MAX_TIME_CONSTANT_TICKS {
                return Err(E::TimeConstantTooLong { mode });
            }
            if i > 0 && tau <= previous {
                return Err(E::TimeConstantsNotIncreasing { mode });
            }
            previous = tau;
            if c < 0.0 {
                return Err(E::NegativeWeight { mode });
            }
        }
        if self.weights.iter().sum::<f64>() > MAX_WEIGHT_SUM {
            return Err(E::WeightSumTooLarge);
        }
        Ok(())
    }

    /// The modes' per-tick coefficients `(a_k, b_k)` at `control_rate_hz` (`b = 1 − a`,
    /// computed as `−expm1(−T/τ)` so that a long τ keeps its digits).
    pub fn poles(&self, control_rate_hz: f64) -> impl Iterator<Item = (f64, f64)> + '_ {
        self.time_constants_s.iter().map(move |&tau| {
            let b = -libm::expm1(-1.0 / (tau * control_rate_hz));
            (1.0 - b, b)
        })
    }
}

/// The states of a creep operator's modes, `z_k`, Q4.60 (see the module doc).
///
/// Each `i64` is held as its two 32-bit words (low, high), so the state is 4-byte aligned
/// like the rest of the controller: an 8-byte-aligned field would be laid out ahead of the
/// tick's other state and move it, which costs the tick without creep instructions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CreepState {
    z: [[u32; 2]; MAX_CREEP_MODES],
}

/// A Q4.60 state from its words.
#[inline(always)]
fn load(w: &[u32; 2]) -> i64 {
    ((w[1] as i64) << 32) | w[0] as i64
}

/// A Q4.60 state as its words.
#[inline(always)]
fn store(z: i64) -> [u32; 2] {
    [z as u32, (z >> 32) as u32]
}

impl CreepState {
    /// Every mode settled at `y` (Q2.30): the operator's output is then `y`.
    pub fn at_rest(y: i32) -> Self {
        Self {
            z: [store((y as i64) << SIGNAL_FRAC_BITS); MAX_CREEP_MODES],
        }
    }

    /// The mode states as Q2.30 signals (rounded toward −∞).
    pub fn modes(&self) -> [i32; MAX_CREEP_MODES] {
        self.z.map(|w| q60_to_signal_floor(load(&w)))
    }
}

/// A creep operator in fixed point: forward (`y → x`) and inverse (`x → y`) steps on a
/// [`CreepState`]. Built once, off the tick, at the tick's rate.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Creep {
    len: usize,
    /// `b_k = 1 − exp(−T/τ_k)`, Q0.32.
    b: [i32; MAX_CREEP_MODES],
    /// `c_k`, Q1.31.
    c: [i32; MAX_CREEP_MODES],
    /// `c_k a_k`, Q1.31.
    ca: [i32; MAX_CREEP_MODES],
    /// `1/D`, `D = 1 − Σ c_k a_k` (from the rounded `c_k a_k`), Q5.27 (`1/D ≤ 10`).
    inverse_d: i32,
}

/// Fractional bits of the weights `c_k`, `c_k a_k` (Q1.31).
const WEIGHT_FRAC_BITS: u32 = 31;
/// Fractional bits of `1/D` (Q5.27).
const INVERSE_D_FRAC_BITS: u32 = 27;

impl Creep {
    /// Validates `params` ([`CreepParams::check`]) and discretises them for a tick at
    /// `control_rate_hz`.
    ///
    /// ```
    /// use twinstack::models::creep::{Creep, CreepParams};
    /// use twinstack::fixed_point::SIGNAL_ONE;
    /// let p = CreepParams::new(&[1e-3, 0.1], &[0.05, 0.05]).unwrap();
    /// let creep = Creep::new(&p, 50_000.0).unwrap();
    /// let mut s = creep.state_at_rest(0);
    /// // A step of 0.5: 90 % arrives at once, the rest later.
    /// let x = creep.forward_step(&mut s, SIGNAL_ONE / 2);
    /// assert!((x - (SIGNAL_ONE as f64 * 0.45) as i32).abs() < SIGNAL_ONE / 1000);
    /// assert!(Creep::new(&p, 1000.0).is_err(), "1 ms is shorter than 2 ticks at 1 kHz");
    /// ```
    #[inline(never)] // configuration, off the tick path
    pub fn new(params: &CreepParams, control_rate_hz: f64) -> Result<Self, CreepError> {
        params.check(control_rate_hz)?;
        let mut creep = Self {
            len: params.weights.len().min(MAX_CREEP_MODES),
            b: [0; MAX_CREEP_MODES],
            c: [0; MAX_CREEP_MODES],
            ca: [0; MAX_CREEP_MODES],
            inverse_d: 1 << INVERSE_D_FRAC_BITS,
        };
        // D = 1 − Σ c_k a_k, Q1.31 in i64 (it may be 1.0 exactly).
        let mut d = 1i64 << WEIGHT_FRAC_BITS;
        for (k, ((a, b), &c)) in params
            .poles(control_rate_hz)
            .zip(&params.weights)
            .enumerate()
            .take(MAX_CREEP_MODES)
        {
            creep.b[k] = q0_32_from_f64(b);
            creep.c[k] = q1_31_from_f64(c);
            creep.ca[k] = q1_31_from_f64(c * a);
            d -= creep.ca[k] as i64;
        }
        // D ≥ 0.1 (Σ c ≤ 0.9): 2^58 / D ≤ 10 · 2^27 fits Q5.27; the division is here, not
        // on the tick.
        let one = 1i64 << (WEIGHT_FRAC_BITS + INVERSE_D_FRAC_BITS);
        creep.inverse_d = (one + d / 2)
            .checked_div(d.max(1))
            .unwrap_or(i32::MAX as i64)
            .min(i32::MAX as i64) as i32;
        Ok(creep)
    }

    /// Number of modes.
    pub fn modes(&self) -> usize {
        self.len
    }

    /// Every mode settled at `y` (Q2.30): forward and inverse then pass `y` through unchanged.
    pub fn state_at_rest(&self, y: i32) -> CreepState {
        CreepState::at_rest(y)
    }

    /// One tick forward: the hysteresis model's output `y` (Q2.30) → displacement `x`
    /// (Q2.30, rounded toward −∞, saturated). Updates the modes first, then
    /// `x = c0·y + Σ c_k z_k`, computed as `y − Σ c_k (y − z_k)` (Q4.60 sum of Q1.31 ×
    /// Q3.29 products), so that the static gain is exactly 1.
    ///
    /// One copy in flash (not inlined), as [`Self::inverse_step`]: written out into each of
    /// the tick's model variants, the modes made the whole handler's other code dearer.
    #[inline(never)]
    pub fn forward_step(&self, state: &mut CreepState, y: i32) -> i32 {
        let mut acc = (y as i64) << SIGNAL_FRAC_BITS; // Q4.60
        let n = self.len;
        // Mode by mode, each behind a compare with the operator's size (a loop would pay its
        // counter and a taken branch on every mode).
        macro_rules! modes {
            ($($k:literal)*) => {$(
                if $k >= n {
                    return q60_to_signal_floor(acc);
                }
                let z = relax(load(&state.z[$k]), self.b[$k], y);
                state.z[$k] = store(z);
                acc -= self.c[$k] as i64 * lag(z, y) as i64;
            )*};
        }
        modes!(0 1 2 3 4 5);
        q60_to_signal_floor(acc)
    }

    /// One tick of the exact inverse: desired displacement `x` (Q2.30) → the hysteresis
    /// output `y` (Q2.30) the forward step turns into `x`, `y = (x − Σ c_k a_k z_k)·(1/D)`
    /// on the states before the update; then the modes are updated with `y`.
    #[inline(never)]
    pub fn inverse_step(&self, state: &mut CreepState, x: i32) -> i32 {
        // Q3.61: |x| ≤ 2 and Σ c_k a_k |z_k| ≤ 0.9 · 2 keep it below 2^63.
        let mut acc = (x as i64) << WEIGHT_FRAC_BITS;
        let n = self.len;
        // Written out as `forward_step`'s modes are: first the sum over the states before the
        // update, then the update.
        macro_rules! sum {
            ($($k:literal)*) => {'sum: {$(
                if $k >= n {
                    break 'sum;
                }
                acc -= self.ca[$k] as i64 * q60_to_signal_floor(load(&state.z[$k])) as i64;
            )*}};
        }
        sum!(0 1 2 3 4 5);
        let rest = floor_shift_to_signal::<WEIGHT_FRAC_BITS>(acc);
        let y = floor_shift_to_signal::<INVERSE_D_FRAC_BITS>(self.inverse_d as i64 * rest as i64);
        macro_rules! update {
            ($($k:literal)*) => {$(
                if $k >= n {
                    return y;
                }
                state.z[$k] = store(relax(load(&state.z[$k]), self.b[$k], y));
            )*};
        }
        update!(0 1 2 3 4 5);
        y
    }
}

/// `y − z` in Q3.29 from the high words (`|y − z| < 4` fits; saturating for a state a hair
/// beyond −2): `z` Q4.60, `y` Q2.30.
#[inline(always)]
fn lag(z: i64, y: i32) -> i32 {
    (y >> 1).saturating_sub((z >> 31) as i32)
}

/// One mode's update `z ← z + b·(y − z)`: `z` Q4.60, `b` Q0.32, `y` Q2.30; the product
/// `b·(y − z)` (Q0.32 × Q3.29 = Q3.61) is exact in `i64`, then shifted to Q4.60. The sum
/// cannot overflow (a plain add, not a 64-bit saturation): `|z| < 2^61 + 2^31` (a state stays
/// between its inputs, `|y| ≤ 2`, give or take the rounding) and `|b·(y − z)| >> 1 < 2^61`.
#[inline(always)]
fn relax(z: i64, b: i32, y: i32) -> i64 {
    z.wrapping_add((b as i64 * lag(z, y) as i64) >> 1)
}

/// `acc >> BITS` (rounding toward −∞) saturated to `i32`: a product with `BITS + 30`
/// fractional bits brought back to a Q2.30 signal.
#[inline(always)]
fn floor_shift_to_signal<const BITS: u32>(acc: i64) -> i32 {
    saturate_i64(acc >> BITS)
}

/// A creep operator beyond its modes, per side it runs on (the compensator's inverse, the
/// observer's forward), cycles at 5 wait states (see [`Hysteresis::cycles`]).
pub const CREEP_BASE_CYCLES: u32 = 95;
/// Each creep mode, per side (written out mode by mode: 40 as a loop).
pub const CREEP_MODE_CYCLES: u32 = 36;

/// The creep forward, after a forward model ([`crate::models::Series`]).
impl Hysteresis for Creep {
    type State = CreepState;

    #[inline(always)]
    fn step(&self, state: &mut CreepState, y: i32) -> i32 {
        self.forward_step(state, y)
    }

    fn cycles(&self) -> u32 {
        CREEP_BASE_CYCLES + CREEP_MODE_CYCLES * self.modes() as u32
    }
}

/// The creep's exact inverse, before an inverse model ([`crate::models::Series`]): desired
/// displacement `x` → the hysteresis model's output `y` that gives it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct InverseCreep(pub Creep);

impl Hysteresis for InverseCreep {
    type State = CreepState;

    #[inline(always)]
    fn step(&self, state: &mut CreepState, x: i32) -> i32 {
        self.0.inverse_step(state, x)
    }

    fn cycles(&self) -> u32 {
        self.0.cycles()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::fixed_point::{signal_from_f64, signal_to_f64, SIGNAL_ONE};

    const RATE: f64 = 50_000.0;

    fn four_modes() -> Creep {
        let p = CreepParams::new(&[2e-4, 2e-3, 2e-2, 0.2], &[0.03, 0.02, 0.02, 0.03]).unwrap();
        Creep::new(&p, RATE).unwrap()
    }

    #[test]
    fn a_step_arrives_with_the_instant_part_and_settles_to_one() {
        let c = four_modes();
        let mut s = c.state_at_rest(0);
        let step = SIGNAL_ONE / 2;
        let first = signal_to_f64(c.forward_step(&mut s, step)) / 0.5;
        // Instant part 0.9, plus each mode's first-tick share c_k b_k.
        let p = CreepParams::new(&[2e-4, 2e-3, 2e-2, 0.2], &[0.03, 0.02, 0.02, 0.03]).unwrap();
        let d: f64 = 0.9
            + p.poles(RATE)
                .zip(&p.weights)
                .map(|((_, b), c)| c * b)
                .sum::<f64>();
        assert!((first - d).abs() < 1e-7, "{first} vs {d}");
        let mut last = first;
        for k in 0..100_000 {
            let x = signal_to_f64(c.forward_step(&mut s, step)) / 0.5;
            assert!(
                x >= last - 1e-8,
                "creep only rises after a rising step (tick {k})"
            );
            last = x;
        }
        // 100 000 ticks = 2 s = 10 τ of the slowest mode: settled to 1 within e^-10 · 0.03.
        assert!((last - 1.0).abs() < 5e-6, "{last}");
    }

    #[test]
    fn at_rest_the_operator_and_its_inverse_pass_the_signal_through() {
        let c = four_modes();
        for y in [
            -SIGNAL_ONE,
            -12345,
            0,
            777,
            SIGNAL_ONE - 1,
            i32::MIN,
            i32::MAX,
        ] {
            let mut s = c.state_at_rest(y);
            assert_eq!(c.forward_step(&mut s, y), y);
            let mut s = c.state_at_rest(y);
            let back = c.inverse_step(&mut s, y);
            assert!((back - y).abs() <= 4, "{y}: {back}");
        }
    }

    #[test]
    fn the_longest_time_constant_still_moves() {
        // τ at the limit (2^26 ticks): b is 64 LSB of Q0.32 and a full-scale step moves z.
        let p = CreepParams::new(&[MAX_TIME_CONSTANT_TICKS / RATE], &[0.5]).unwrap();
        let c = Creep::new(&p, RATE).unwrap();
        let mut s = c.state_at_rest(0);
        for _ in 0..1000 {
            c.forward_step(&mut s, SIGNAL_ONE);
        }
        let moved = load(&s.z[0]) as f64 / (1u64 << 60) as f64;
        let want = 1000.0 / MAX_TIME_CONSTANT_TICKS;
        assert!((moved / want - 1.0).abs() < 0.01, "{moved} vs {want}");
    }

    #[test]
    fn refusals_say_what_is_wrong() {
        let p = |t: &[f64], w: &[f64]| CreepParams::new(t, w).unwrap().check(RATE);
        use CreepError as E;
        assert_eq!(p(&[], &[]), Err(E::NoModes));
        assert_eq!(
            CreepParams::new(&[1.0; 7], &[0.0; 7]),
            Err(E::TooManyModes { count: 7 })
        );
        assert_eq!(
            p(&[1.0, f64::NAN], &[0.1, 0.1]),
            Err(E::NotFinite { mode: 2 })
        );
        assert_eq!(
            p(&[1.0 / RATE], &[0.1]),
            Err(E::TimeConstantTooShort { mode: 1 })
        );
        assert_eq!(p(&[2.0 / RATE], &[0.1]), Ok(()));
        assert_eq!(
            p(&[1.0, 2e4], &[0.1, 0.1]),
            Err(E::TimeConstantTooLong { mode: 2 })
        );
        assert_eq!(
            p(&[1.0, 1.0], &[0.1, 0.1]),
            Err(E::TimeConstantsNotIncreasing { mode: 2 })
        );
        assert_eq!(
            p(&[1.0, 2.0], &[0.1, -0.1]),
            Err(E::NegativeWeight { mode: 2 })
        );
        assert_eq!(p(&[1.0, 2.0], &[0.5, 0.41]), Err(E::WeightSumTooLarge));
        assert_eq!(p(&[1.0, 2.0], &[0.5, 0.4]), Ok(()));
        let q = CreepParams::new(&[1.0], &[0.1]).unwrap();
        assert_eq!(q.check(f64::NAN), Err(E::NotFinite { mode: 0 }));
    }

    proptest::proptest! {
        /// For any valid operator and any input, the inverse fed the forward output gives the
        /// input back, tick after tick, to within a few LSB of Q2.30 amplified by the
        /// inverse's gain `1/D ≤ 1/(1 − Σ c)`: the forward's rounding (≤ 3 LSB) and the
        /// rounding of `1/D` to Q5.27 (2^-28 relative: 8 LSB at |y| = 2) — at most 160 LSB of
        /// Q2.30 (5e-3 LSB16) at Σ c = 0.9.
        #[test]
        fn the_inverse_undoes_the_forward_step(
            raw in proptest::collection::vec(0.0f64..1.0, 1..=MAX_CREEP_MODES),
            total in 0.0f64..MAX_WEIGHT_SUM,
            first_tau_ticks in 2.0f64..50.0,
            spacing in 1.5f64..20.0,
            start in -1.0f64..1.0,
            input in proptest::collection::vec(-2.0f64..2.0, 1..300),
        ) {
            let sum: f64 = raw.iter().sum::<f64>().max(1e-9);
            let weights: Vec<f64, MAX_CREEP_MODES> =
                raw.iter().map(|w| w * total / sum * 0.999).collect();
            let taus: Vec<f64, MAX_CREEP_MODES> = (0..weights.len())
                .map(|k| first_tau_ticks * spacing.powi(k as i32) / RATE)
                .filter(|&t| t * RATE <= MAX_TIME_CONSTANT_TICKS)
                .collect();
            let weights = &weights[..taus.len()];
            let c = Creep::new(&CreepParams::new(&taus, weights).unwrap(), RATE).unwrap();
            let y0 = signal_from_f64(start);
            let (mut fwd, mut inv) = (c.state_at_rest(y0), c.state_at_rest(y0));
            for (k, &v) in input.iter().enumerate() {
                let y = signal_from_f64(v);
                let x = c.forward_step(&mut fwd, y);
                let back = c.inverse_step(&mut inv, x);
                let bound = 16.0 / (1.0 - total);
                proptest::prop_assert!((back as i64 - y as i64).abs() as f64 <= bound,
                    "tick {}: {} → {} → {}", k, y, x, back);
            }
        }
    }
}
