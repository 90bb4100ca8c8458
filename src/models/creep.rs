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
//! ## Taking turns
//!
//! Where every mode is slow against the tick — each time constant spans at least
//! [`TURN_MIN_UPDATES`] of its updates when the `n` modes take turns, `τ_k ≥ 20·n` ticks
//! ([`takes_turns`]) — the modes are updated **round robin**, one a tick, each with the
//! coefficients of its own update period `n·T` (`a_k = exp(−nT/τ_k)`). The operator's output
//! is then `x = (1 − Σ c)·y + S`, with `S = Σ_k c_k z_k` kept in the state as a running sum
//! (exact: integer products of the weights and the states' high words, updated by the one
//! mode that moved), so a step costs the same whatever the number of modes. Only mode `j`
//! moves on the tick, so the exact inverse is `y = (x − S + c_j b_j z_j) / D_j` with
//! `D_j = 1 − Σ c + c_j b_j ≥ 0.1` (`1/D_j` formed per mode off the tick). A mode then sees
//! its input every `n` ticks rather than every tick: for `τ ≥ 20·n` ticks its response is
//! within `1/40` of its weight of the every-tick one at worst (a full-span step, for the
//! `n − 1` ticks before its turn), and it is the same first-order lag of the same time
//! constant. Faster modes (a creep identified from a slow record, or a fast mode at a low
//! rate) keep the every-tick form. Identification fits the weights with the schedule the
//! operator runs at the record's rate (`identify`'s creep columns take turns too).
//!
//! ## Formats
//!
//! | quantity | format | note |
//! |---|---|---|
//! | `y`, `x` | Q2.30 `i32` | the tick's signals |
//! | `z_k` | Q4.60 `i64` | `|z| ≤ 2`; 2^-60 resolves the increment `b·(y − z)` of τ = 100 s at 100 kHz (b ≈ 1e-7) |
//! | `y − z_k` | Q3.29 `i32` | `(y >> 1) − (z >> 31)`, saturating: the update's difference |
//! | `b_k` | Q0.32 `i32` | `b < 0.5` (τ ≥ 2 ticks); `b · (y − z)` is exact in `i64` (Q3.61), shifted to Q4.60 |
//! | `c_k`, `c_k a_k`, `c_k b_k`, `Σ c_k` | Q1.31 `i32` | weights in [0, 0.9]; `c0` is never formed: `x = y − Σ c_k (y − z_k)`, so the static gain is exactly 1 |
//! | `1/D`, `1/D_j` | Q5.27 `i32` | `1 ≤ 1/D ≤ 10` |
//! | sums | Q4.60 (forward), Q3.61 (inverse) `i64` | weight × signal products |
//! | `S` | Q4.60 `i64` | `Σ c_k · (z_k >> 31)`: Q1.31 × Q3.29 products, exact; taking turns only |
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
//! the output; taking turns, one mode's update and three multiplies whatever the number of
//! modes. No division (the reciprocals are formed in [`Creep::new`]).

use crate::models::Hysteresis;
use serde::{Deserialize, Serialize};

use crate::fixed_point::{q0_32_from_f64, q1_31_from_f64, q60_to_signal_floor, SIGNAL_FRAC_BITS};
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
/// Fewest updates each time constant must span for the modes to take turns (see the module
/// doc): `τ_k ≥ 20·n` ticks for `n` modes.
pub const TURN_MIN_UPDATES: f64 = 20.0;
/// The mode whose turn it is, as an index the compiler knows is in bounds (no bounds check,
/// no panic path on the tick): `turn < len ≤ MAX_CREEP_MODES` always, so the bound never bites.
#[inline(always)]
fn turn_index(turn: u32) -> usize {
    (turn as usize).min(MAX_CREEP_MODES - 1)
}

/// Whether modes with time constants `time_constants_s` (seconds) take turns at
/// `control_rate_hz` (see the module doc): each spans at least [`TURN_MIN_UPDATES`] updates
/// of its own, one every `n` ticks.
///
/// ```
/// use twinstack::models::creep::takes_turns;
/// // Identified creep (10 ms … 10 s, four modes): at 50 kHz 500 ticks ≥ 80.
/// assert!(takes_turns(&[0.01, 0.1, 1.0, 10.0], 50_000.0));
/// // A 0.1 ms mode is 5 ticks at 50 kHz: every mode updates every tick.
/// assert!(!takes_turns(&[1e-4, 1e-3, 0.01, 0.1], 50_000.0));
/// ```
pub fn takes_turns(time_constants_s: &[f64], control_rate_hz: f64) -> bool {
    let n = time_constants_s.len() as f64;
    !time_constants_s.is_empty()
        && time_constants_s
            .iter()
            .all(|&tau| tau * control_rate_hz >= TURN_MIN_UPDATES * n)
}

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

    /// Whether the modes take turns at `control_rate_hz` ([`takes_turns`]).
    pub fn takes_turns(&self, control_rate_hz: f64) -> bool {
        takes_turns(&self.time_constants_s, control_rate_hz)
    }

    /// The modes' coefficients `(a_k, b_k)` per update as the operator runs them at
    /// `control_rate_hz`: [`Self::poles`] at the rate, or, where the modes take turns, at the
    /// rate over the number of modes (each mode updates every `n` ticks).
    pub fn update_poles(&self, control_rate_hz: f64) -> impl Iterator<Item = (f64, f64)> + '_ {
        let n = self.time_constants_s.len().max(1) as f64;
        let rate = if self.takes_turns(control_rate_hz) {
            control_rate_hz / n
        } else {
            control_rate_hz
        };
        self.poles(rate)
    }
}

/// The states of a creep operator's modes, `z_k`, Q4.60 (see the module doc); where the modes
/// take turns, also their weighted sum `S` (Q4.60) and whose turn is next.
///
/// Each `i64` is held as its two 32-bit words (low, high), so the state is 4-byte aligned
/// like the rest of the controller: an 8-byte-aligned field would be laid out ahead of the
/// tick's other state and move it, which costs the tick without creep instructions.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CreepState {
    z: [[u32; 2]; MAX_CREEP_MODES],
    /// `S = Σ c_k (z_k >> 31)`, Q4.60: kept only where the modes take turns.
    sum: [u32; 2],
    /// The mode the next step updates (taking turns).
    turn: u32,
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
    /// The modes take turns, one a tick ([`takes_turns`]).
    turns: bool,
    /// `b_k = 1 − exp(−T_k/τ_k)`, Q0.32, `T_k` the mode's update period: the tick, or `n`
    /// ticks where the modes take turns.
    b: [i32; MAX_CREEP_MODES],
    /// `c_k`, Q1.31.
    c: [i32; MAX_CREEP_MODES],
    /// Every tick: `c_k a_k`, Q1.31.
    ca: [i32; MAX_CREEP_MODES],
    /// Every tick: `1/D`, `D = 1 − Σ c_k a_k` (from the rounded `c_k a_k`), Q5.27 (`1/D ≤ 10`).
    inverse_d: i32,
    /// Taking turns: `c_k b_k` (from the rounded `c_k` and `b_k`), Q1.31.
    cb: [i32; MAX_CREEP_MODES],
    /// Taking turns: `1/D_k`, `D_k = 1 − Σ c + c_k b_k` (rounded as the step forms it), Q5.27.
    inverse_d_turn: [i32; MAX_CREEP_MODES],
    /// Taking turns: `Σ c_k`, Q1.31.
    c_sum: i32,
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
            turns: params.takes_turns(control_rate_hz),
            b: [0; MAX_CREEP_MODES],
            c: [0; MAX_CREEP_MODES],
            ca: [0; MAX_CREEP_MODES],
            inverse_d: 1 << INVERSE_D_FRAC_BITS,
            cb: [0; MAX_CREEP_MODES],
            inverse_d_turn: [1 << INVERSE_D_FRAC_BITS; MAX_CREEP_MODES],
            c_sum: 0,
        };
        // D = 1 − Σ c_k a_k, Q1.31 in i64 (it may be 1.0 exactly).
        let mut d = 1i64 << WEIGHT_FRAC_BITS;
        for (k, ((a, b), &c)) in params
            .update_poles(control_rate_hz)
            .zip(&params.weights)
            .enumerate()
            .take(MAX_CREEP_MODES)
        {
            creep.b[k] = q0_32_from_f64(b);
            creep.c[k] = q1_31_from_f64(c);
            creep.ca[k] = q1_31_from_f64(c * a);
            // Q1.31 × Q0.32 → Q1.31, from the values the step uses.
            creep.cb[k] = ((creep.c[k] as i64 * creep.b[k] as i64) >> 32) as i32;
            creep.c_sum += creep.c[k];
            d -= creep.ca[k] as i64;
        }
        creep.inverse_d = reciprocal_q5_27(d);
        let rest = (1i64 << WEIGHT_FRAC_BITS) - creep.c_sum as i64;
        for k in 0..creep.len {
            creep.inverse_d_turn[k] = reciprocal_q5_27(rest + creep.cb[k] as i64);
        }
        Ok(creep)
    }

    /// Whether the modes take turns, one a tick ([`takes_turns`]).
    pub fn takes_turns(&self) -> bool {
        self.turns
    }

    /// Number of modes.
    pub fn modes(&self) -> usize {
        self.len
    }

    /// Every mode settled at `y` (Q2.30): forward and inverse then pass `y` through unchanged.
    pub fn state_at_rest(&self, y: i32) -> CreepState {
        let z = (y as i64) << SIGNAL_FRAC_BITS;
        // S = Σ c_k (z_k >> 31), every z_k the same.
        let sum = self.c_sum as i64 * (z >> 31);
        CreepState {
            z: [store(z); MAX_CREEP_MODES],
            sum: store(sum),
            turn: 0,
        }
    }

    /// One tick forward: the hysteresis model's output `y` (Q2.30) → displacement `x`
    /// (Q2.30, rounded toward −∞, saturated). Updates the modes first, then
    /// `x = c0·y + Σ c_k z_k`, computed as `y − Σ c_k (y − z_k)` (Q4.60 sum of Q1.31 ×
    /// Q3.29 products), so that the static gain is exactly 1.
    ///
    /// One copy in flash (not inlined), as [`Self::inverse_step`]'s every-tick form: the
    /// modes written out where they are called made the caller's other code dearer.
    #[inline(never)]
    pub fn forward_step(&self, state: &mut CreepState, y: i32) -> i32 {
        if self.turns {
            // x = y − Σc·y + S, S with this tick's mode moved (Q4.60).
            let j = turn_index(state.turn);
            let z = load(&state.z[j]);
            let sum = self.take_turn(state, j, z, (z >> 31) as i32, y);
            let acc = ((y as i64) << SIGNAL_FRAC_BITS) - self.c_sum as i64 * (y >> 1) as i64 + sum;
            return q60_to_signal_floor(acc);
        }
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
    /// on the states before the update; then the modes are updated with `y`. Where the modes
    /// take turns, `y = (x − S + c_j b_j z_j)·(1/D_j)` and mode `j` is updated.
    ///
    /// Taking turns, the step is written out where it is called, once in the tick (a short,
    /// straight path: a call would cost the tick as much again); every tick, it is one copy
    /// in flash.
    #[inline(always)]
    pub fn inverse_step(&self, state: &mut CreepState, x: i32) -> i32 {
        if self.turns {
            self.inverse_turn(state, x)
        } else {
            self.inverse_every_tick(state, x)
        }
    }

    /// [`Self::inverse_step`] where the modes take turns.
    #[inline(always)]
    fn inverse_turn(&self, state: &mut CreepState, x: i32) -> i32 {
        // y = (x − S + c_j b_j z_j) · (1/D_j) on the states before the update.
        let j = turn_index(state.turn);
        let z = load(&state.z[j]);
        // Q3.29.
        let high = (z >> 31) as i32;
        // S − c_j b_j z_j (Q4.60) as Q2.30: |S| ≤ Σ c · 2 · 2^60 < 2^61 (every state lies
        // between inputs, |y| ≤ 2), so it fits without saturating.
        let held = (load(&state.sum).wrapping_sub(self.cb[j] as i64 * high as i64)
            >> SIGNAL_FRAC_BITS) as i32;
        let y = floor_shift_to_signal::<INVERSE_D_FRAC_BITS>(
            self.inverse_d_turn[j] as i64 * x.saturating_sub(held) as i64,
        );
        self.take_turn(state, j, z, high, y);
        y
    }

    /// [`Self::inverse_step`] where every mode updates every tick.
    #[inline(never)]
    fn inverse_every_tick(&self, state: &mut CreepState, x: i32) -> i32 {
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

impl Creep {
    /// The turn's mode `j` (state `z`, its high word `high`, Q3.29) relaxes toward `y`, `S`
    /// follows it exactly (`+ c_j·Δ(z_j >> 31)`), and the next mode's turn comes; returns the
    /// new `S` (Q4.60).
    #[inline(always)]
    fn take_turn(&self, state: &mut CreepState, j: usize, z: i64, high: i32, y: i32) -> i64 {
        let moved = relax_from(z, high, self.b[j], y);
        state.z[j] = store(moved);
        // |Δ| ≤ b·|y − z| < 2^30 (Q3.29).
        let delta = ((moved >> 31) as i32).wrapping_sub(high);
        let sum = load(&state.sum).wrapping_add(self.c[j] as i64 * delta as i64);
        state.sum = store(sum);
        let next = state.turn.wrapping_add(1);
        state.turn = if next as usize >= self.len { 0 } else { next };
        sum
    }
}

/// `2^58 / d` (`d` Q1.31, at least 0.1 by the weights' bound) as Q5.27, rounded, saturated:
/// formed off the tick.
fn reciprocal_q5_27(d: i64) -> i32 {
    let one = 1i64 << (WEIGHT_FRAC_BITS + INVERSE_D_FRAC_BITS);
    (one + d / 2)
        .checked_div(d.max(1))
        .unwrap_or(i32::MAX as i64)
        .min(i32::MAX as i64) as i32
}

/// `y − z` in Q3.29 from the high words (`|y − z| < 4` fits; saturating for a state a hair
/// beyond −2): `z` Q4.60, `y` Q2.30.
#[inline(always)]
fn lag(z: i64, y: i32) -> i32 {
    lag_from((z >> 31) as i32, y)
}

/// [`lag`] with the state's high word `z >> 31` (Q3.29) already formed.
#[inline(always)]
fn lag_from(high: i32, y: i32) -> i32 {
    (y >> 1).saturating_sub(high)
}

/// One mode's update `z ← z + b·(y − z)`: `z` Q4.60, `b` Q0.32, `y` Q2.30; the product
/// `b·(y − z)` (Q0.32 × Q3.29 = Q3.61) is exact in `i64`, then shifted to Q4.60. The sum
/// cannot overflow (a plain add, not a 64-bit saturation): `|z| < 2^61 + 2^31` (a state stays
/// between its inputs, `|y| ≤ 2`, give or take the rounding) and `|b·(y − z)| >> 1 < 2^61`.
#[inline(always)]
fn relax(z: i64, b: i32, y: i32) -> i64 {
    relax_from(z, (z >> 31) as i32, b, y)
}

/// [`relax`] with the state's high word `z >> 31` (Q3.29) already formed.
#[inline(always)]
fn relax_from(z: i64, high: i32, b: i32, y: i32) -> i64 {
    z.wrapping_add((b as i64 * lag_from(high, y) as i64) >> 1)
}

/// `acc >> BITS` (rounding toward −∞) saturated to `i32`: a product with `BITS + 30`
/// fractional bits brought back to a Q2.30 signal (`1 ≤ BITS ≤ 32`). The shift fits `i32`
/// exactly when the bits above it, `acc >> (BITS + 31)`, are all sign: tested on the high
/// word alone, which is cheaper than comparing the 64-bit shift with both bounds.
#[inline(always)]
fn floor_shift_to_signal<const BITS: u32>(acc: i64) -> i32 {
    const { assert!(BITS >= 1 && BITS <= 32) };
    let high = (acc >> 32) as i32;
    if high >> (BITS - 1) == high >> 31 {
        (acc >> BITS) as i32
    } else {
        (high >> 31) ^ i32::MAX
    }
}

/// A creep operator beyond its modes, per side it runs on (the compensator's inverse, the
/// observer's forward), cycles at 5 wait states (see [`Hysteresis::cycles`]).
pub const CREEP_BASE_CYCLES: u32 = 95;
/// Each creep mode, per side (written out mode by mode: 40 as a loop).
pub const CREEP_MODE_CYCLES: u32 = 36;
/// A creep operator whose modes take turns, per side, whatever its number of modes: the
/// whole-interrupt bench's generalised P–I 17 × 8 + creep 4 configuration runs it (its worst
/// streamed tick 1 318 cycles against the 1 335 predicted; the bench attributes 105 cycles of
/// that tick to this file's lines, the test of the schedule and the join after it included).
pub const CREEP_TURN_CYCLES: u32 = 100;

/// The creep forward, after a forward model ([`crate::models::ObserverRun`]).
impl Hysteresis for Creep {
    type State = CreepState;

    #[inline(always)]
    fn step(&self, state: &mut CreepState, y: i32) -> i32 {
        self.forward_step(state, y)
    }

    fn cycles(&self) -> u32 {
        if self.turns {
            CREEP_TURN_CYCLES
        } else {
            CREEP_BASE_CYCLES + CREEP_MODE_CYCLES * self.modes() as u32
        }
    }
}

/// The creep's exact inverse, before an inverse model ([`crate::models::CompensatorRun`]): desired
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
    use crate::fixed_point::{saturate_i64, signal_from_f64, signal_to_f64, SIGNAL_ONE};

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

    /// Identified creep's shape: four modes from 10 ms, slow enough at 50 kHz to take turns.
    fn four_modes_taking_turns() -> (CreepParams, Creep) {
        let p = CreepParams::new(&[0.01, 0.1, 1.0, 10.0], &[0.05, 0.03, 0.02, 0.02]).unwrap();
        let c = Creep::new(&p, RATE).unwrap();
        (p, c)
    }

    #[test]
    fn slow_modes_take_turns_and_fast_ones_update_every_tick() {
        assert!(four_modes_taking_turns().1.takes_turns());
        assert!(!four_modes().takes_turns());
        // The boundary: 20 updates of 4 ticks.
        let at = |first: f64| {
            let p = CreepParams::new(&[first / RATE, 1.0, 2.0, 3.0], &[0.01; 4]).unwrap();
            Creep::new(&p, RATE).unwrap().takes_turns()
        };
        assert!(at(80.0) && !at(79.9));
    }

    #[test]
    fn taking_turns_a_step_arrives_with_the_instant_part_and_the_first_modes_share() {
        let (p, c) = four_modes_taking_turns();
        let mut s = c.state_at_rest(0);
        let step = SIGNAL_ONE / 2;
        let first = signal_to_f64(c.forward_step(&mut s, step)) / 0.5;
        // Instant part 1 − Σc, and mode 1 (the first turn) moves by b_1 of its update period.
        let b1 = p.update_poles(RATE).next().unwrap().1;
        let want = 1.0 - 0.12 + 0.05 * b1;
        assert!((first - want).abs() < 1e-7, "{first} vs {want}");
        // Settles to 1 (10 s of the slowest mode is 500 000 ticks: settle the others).
        for _ in 0..2_000_000 {
            c.forward_step(&mut s, step);
        }
        let last = signal_to_f64(c.forward_step(&mut s, step)) / 0.5;
        assert!((last - 1.0).abs() < 0.02 * (-2.0f64).exp() * 1.01, "{last}");
    }

    #[test]
    fn taking_turns_follows_the_every_tick_operator_and_inverse_within_a_fortieth_of_a_weight() {
        // The same modes at 50 kHz, taking turns and every tick (formed here by hand: at this
        // rate `Creep::new` makes them take turns).
        let (p, turns) = four_modes_taking_turns();
        let mut every = turns;
        every.turns = false;
        for (k, (a, b)) in p.poles(RATE).enumerate() {
            every.b[k] = q0_32_from_f64(b);
            every.ca[k] = q1_31_from_f64(p.weights[k] * a);
        }
        let d = (1i64 << WEIGHT_FRAC_BITS) - every.ca[..4].iter().map(|&v| v as i64).sum::<i64>();
        every.inverse_d = reciprocal_q5_27(d);
        let (mut st, mut se) = (turns.state_at_rest(0), every.state_at_rest(0));
        let (mut it, mut ie) = (turns.state_at_rest(0), every.state_at_rest(0));
        let (mut worst, mut worst_drive): (f64, f64) = (0.0, 0.0);
        // Full-span steps every 5 ms, and a 200 Hz sine: the worst the lag of a turn shows.
        for k in 0..50_000 {
            let y = if k < 25_000 {
                if (k / 250) % 2 == 0 {
                    SIGNAL_ONE
                } else {
                    -SIGNAL_ONE
                }
            } else {
                signal_from_f64((k as f64 * 200.0 / RATE * core::f64::consts::TAU).sin())
            };
            let a = signal_to_f64(turns.forward_step(&mut st, y));
            let b = signal_to_f64(every.forward_step(&mut se, y));
            worst = worst.max((a - b).abs());
            // The compensator's side: the drive each inverse gives for the same target.
            let a = signal_to_f64(turns.inverse_step(&mut it, y));
            let b = signal_to_f64(every.inverse_step(&mut ie, y));
            worst_drive = worst_drive.max((a - b).abs());
        }
        // A fortieth of the fastest mode's weight, on a span of 2: the operator's output and
        // the drive its inverse gives (measured 0.0009 and 0.0011).
        assert!(worst < 2.0 * 0.05 / 40.0, "{worst}");
        assert!(worst_drive < 2.0 * 0.05 / 40.0, "drive {worst_drive}");
        assert!(worst > 0.0, "the schedules differ");
    }

    #[test]
    fn taking_turns_the_running_sum_is_the_weighted_sum_of_the_states() {
        let (_, c) = four_modes_taking_turns();
        let mut s = c.state_at_rest(-SIGNAL_ONE / 3);
        let mut inv = c.state_at_rest(-SIGNAL_ONE / 3);
        let exact =
            |s: &CreepState| -> i64 { (0..4).map(|k| c.c[k] as i64 * (load(&s.z[k]) >> 31)).sum() };
        for k in 0..200_000u32 {
            let y = (k.wrapping_mul(2_654_435_761) as i32) >> 1;
            c.forward_step(&mut s, y);
            c.inverse_step(&mut inv, y);
        }
        assert_eq!(load(&s.sum), exact(&s), "forward");
        assert_eq!(load(&inv.sum), exact(&inv), "inverse");
    }

    #[test]
    fn the_shift_to_a_signal_saturates_as_the_64_bit_clamp_does() {
        let edges = [
            0i64,
            1,
            -1,
            1 << 57,
            1 << 58,
            (1 << 58) - 1,
            -(1 << 58),
            -(1 << 58) - 1,
            (1 << 61) - 1,
            -(1 << 61),
            1 << 62,
            i64::MAX,
            i64::MIN,
        ];
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        let random = core::iter::repeat_with(move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            (x as i64) >> (x % 40)
        });
        for v in edges.into_iter().chain(random.take(100_000)) {
            assert_eq!(floor_shift_to_signal::<27>(v), saturate_i64(v >> 27), "{v}");
            assert_eq!(floor_shift_to_signal::<31>(v), saturate_i64(v >> 31), "{v}");
            assert_eq!(floor_shift_to_signal::<30>(v), saturate_i64(v >> 30), "{v}");
        }
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
            first_tau_ticks in proptest::prop_oneof![2.0f64..50.0, 50.0f64..2000.0],
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
