//! Physical parameter sets (in `f64`, volts and output units) and their validation.
//!
//! Parameters are checked and converted once, off the tick path, into the fixed-point
//! configurations of [`crate::models::prandtl_ishlinskii`] and [`crate::models::duhem`]; anything that would make
//! the tick misbehave (a non-invertible P–I, a gain the Q-formats cannot hold, NaN) is refused
//! here with a [`ParamError`] that says what and where. Operator numbers in errors are 1-based,
//! as in the equations of the book's docs/src/reference/models.md.

use crate::fixed_point::MAX_GAIN_SUM;
use crate::scaling::{RangeError, Scaling};
use heapless::Vec;

/// Most dead-zone operators a generalised P–I map may have besides its linear gain (e.g. 4
/// above and 4 below the centre).
pub const MAX_DEAD_ZONES: usize = 8;
/// Most play operators a P–I model may have (not counting its linear term `a0`).
pub const MAX_OPERATORS: usize = 32;
/// Operator slots in the canonical form: the linear term `a0` may need a slot of its own.
pub const MAX_CANONICAL_OPERATORS: usize = MAX_OPERATORS + 1;
/// Largest normalised threshold: the whole normalised span (2.0 in Q2.30 units).
pub const MAX_NORM_THRESHOLD: f64 = 2.0;
/// Largest normalised weight magnitude a Q8.24 gain holds, with a margin.
pub const MAX_NORM_WEIGHT: f64 = 127.0;

/// Why a parameter set was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ParamError {
    /// The P–I model has no play operator and no linear term.
    NoOperators,
    /// More than [`MAX_OPERATORS`] play operators.
    TooManyOperators {
        /// How many were given.
        count: usize,
    },
    /// Thresholds and weights have different lengths.
    LengthMismatch {
        /// Number of thresholds.
        thresholds: usize,
        /// Number of weights.
        weights: usize,
    },
    /// A parameter is NaN or infinite.
    NotFinite,
    /// A threshold is negative (1-based operator number).
    NegativeThreshold {
        /// Operator number, 1-based.
        operator: usize,
    },
    /// Thresholds must increase strictly; this one does not exceed its predecessor.
    ThresholdsNotIncreasing {
        /// Operator number, 1-based.
        operator: usize,
    },
    /// A threshold exceeds the full span of the configured range.
    ThresholdOutOfRange {
        /// Operator number, 1-based.
        operator: usize,
    },
    /// The first operator's threshold is not zero and there is no linear term: the model has
    /// a dead band at every reversal and no inverse.
    FirstThresholdNotZero,
    /// `w_1 ≤ 0` (after folding `a0` into the `r = 0` operator): the loading curve does not rise.
    FirstWeightNotPositive,
    /// The partial sum `S_i = Σ_{j≤i} w_j` is not positive: the loading curve stops rising at
    /// operator `i`, so the inverse does not exist.
    PartialSumNotPositive {
        /// Operator number, 1-based.
        operator: usize,
    },
    /// A (forward or inverse) weight, once normalised, does not fit the Q8.24 gain format.
    WeightOutOfRange {
        /// Operator number, 1-based.
        operator: usize,
    },
    /// `Σ|w|` exceeds [`MAX_GAIN_SUM`], so the tick's accumulator could overflow.
    GainSumTooLarge,
    /// The model's output offset, normalised, lies beyond ±1.5 of the output range: the
    /// ranges do not fit the model.
    OffsetOutOfRange,
    /// The input (drive) range is empty or not finite.
    EmptyInputRange,
    /// The output (displacement) range is empty or not finite.
    EmptyOutputRange,
    /// Duhem `α ≤ 0`.
    DuhemAlphaNotPositive,
    /// Duhem `β ≤ 0`.
    DuhemBetaNotPositive,
    /// Duhem `γ ≤ 0`.
    DuhemGammaNotPositive,
    /// A Duhem coefficient, once normalised, does not fit the Q8.24 gain format.
    DuhemCoefficientOutOfRange,
    /// More than [`crate::models::generalised_pi::MAX_DEAD_ZONES`] dead-zone operators.
    TooManyDeadZones {
        /// How many were given.
        count: usize,
    },
    /// Dead-zone thresholds and weights have different lengths.
    DeadZoneLengthMismatch {
        /// Number of thresholds.
        thresholds: usize,
        /// Number of weights.
        weights: usize,
    },
    /// A dead-zone threshold is zero (the `d = 0` operator is the linear gain) or does not
    /// exceed the one before it (1-based dead-zone number).
    DeadZoneThresholdsNotIncreasing {
        /// Dead-zone number, 1-based.
        dead_zone: usize,
    },
    /// A dead-zone threshold (or its inverse's), normalised, lies beyond the span of the output
    /// range (1-based dead-zone number).
    DeadZoneThresholdOutOfRange {
        /// Dead-zone number, 1-based.
        dead_zone: usize,
    },
    /// The dead-zone map's linear gain `g_0` is not positive: the map does not rise at its centre.
    DeadZoneLinearNotPositive,
    /// The dead-zone map's slope beyond this dead zone (`g_0` plus the weights of the dead
    /// zones between the centre and here) is not positive: the map is not invertible.
    DeadZoneSlopeNotPositive {
        /// Dead-zone number, 1-based.
        dead_zone: usize,
    },
    /// A dead-zone weight (forward or inverse), once normalised, does not fit Q8.24
    /// (1-based dead-zone number; 0 is the linear gain).
    DeadZoneWeightOutOfRange {
        /// Dead-zone number, 1-based (0: the linear gain).
        dead_zone: usize,
    },
    /// The dead-zone map's `Σ|g|` (forward or inverse, plus its centre) exceeds
    /// [`MAX_GAIN_SUM`], so the tick's accumulator could overflow.
    DeadZoneGainSumTooLarge,
    /// The dead-zone map's centre lies outside the output range.
    DeadZoneCentreOutOfRange,
    /// The creep operator in series with the model was refused (see
    /// [`crate::models::creep::CreepError`]).
    Creep(crate::models::creep::CreepError),
    /// A Bouc–Wen coefficient that must be positive (`k`, `β`) is not.
    BoucWenNotPositive(BoucWenCoefficient),
    /// A Bouc–Wen coefficient lets the hysteretic state grow without bound: every factor
    /// `β ± γ ± ψ ± χ` multiplying `h` must be positive (`|γ| < β`, `|ψ| < β`, and without
    /// `χ`, `|ψ| < β − |γ|`).
    BoucWenUnbounded(BoucWenCoefficient),
    /// A Bouc–Wen coefficient, once normalised, does not fit its fixed-point format (or the
    /// bound on the hysteretic state it implies does not fit Q2.30).
    BoucWenOutOfRange(BoucWenCoefficient),
    /// The Bouc–Wen model may not be monotone, so that its compensator's step is not unique:
    /// the hysteretic slope just after a reversal reaches [`BOUC_WEN_MAX_INVERSE_LOOP_GAIN`]
    /// of `k` (see [`BoucWenParams::inverse_loop_gain`]).
    BoucWenNotInvertible(BoucWenCoefficient),
}

/// A coefficient of a Bouc–Wen model ([`BoucWenParams`]), as errors name it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BoucWenCoefficient {
    /// `k`, the linear slope.
    K,
    /// `offset`, `δ`.
    Offset,
    /// `a`, `A`: the hysteretic state's gain on the input step.
    A,
    /// `beta`, `β`.
    Beta,
    /// `gamma`, `γ`.
    Gamma,
    /// `psi`, `ψ` (the asymmetric term).
    Psi,
    /// `chi`, `χ` (the term that depends on the state's sign).
    Chi,
}

impl BoucWenCoefficient {
    /// The coefficient's name as the settings spell it (`k`, `offset`, `a`, `beta`, …).
    pub fn name(self) -> &'static str {
        match self {
            BoucWenCoefficient::K => "k",
            BoucWenCoefficient::Offset => "offset",
            BoucWenCoefficient::A => "a",
            BoucWenCoefficient::Beta => "beta",
            BoucWenCoefficient::Gamma => "gamma",
            BoucWenCoefficient::Psi => "psi",
            BoucWenCoefficient::Chi => "chi",
        }
    }
}

impl core::fmt::Display for ParamError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        use ParamError::*;
        match *self {
            NoOperators => write!(f, "the P–I model has no operators and no linear term"),
            TooManyOperators { count } => {
                write!(f, "{count} play operators given, at most {MAX_OPERATORS} supported")
            }
            LengthMismatch {
                thresholds,
                weights,
            } => write!(f, "{thresholds} thresholds but {weights} weights"),
            NotFinite => write!(f, "a parameter is NaN or infinite"),
            NegativeThreshold { operator } => {
                write!(f, "threshold of operator {operator} is negative")
            }
            ThresholdsNotIncreasing { operator } => write!(
                f,
                "threshold of operator {operator} does not exceed the one before it"
            ),
            ThresholdOutOfRange { operator } => write!(
                f,
                "threshold of operator {operator} exceeds the span of the input range"
            ),
            FirstThresholdNotZero => write!(
                f,
                "first threshold is not zero and a0 = 0: the model is not invertible"
            ),
            FirstWeightNotPositive => write!(
                f,
                "not invertible: w_1 (with a0 folded in) is not positive (operator 1)"
            ),
            PartialSumNotPositive { operator } => write!(
                f,
                "not invertible: partial sum of weights S_{operator} is not positive (operator {operator})"
            ),
            WeightOutOfRange { operator } => write!(
                f,
                "weight of operator {operator} does not fit the Q8.24 format (|w| < {MAX_NORM_WEIGHT} normalised)"
            ),
            GainSumTooLarge => write!(
                f,
                "sum of |weights| exceeds {MAX_GAIN_SUM} (normalised): the accumulator could overflow"
            ),
            OffsetOutOfRange => write!(
                f,
                "the model's offset lies far outside the output range: check the ranges"
            ),
            EmptyInputRange => write!(f, "input range is empty or not finite"),
            EmptyOutputRange => write!(f, "output range is empty or not finite"),
            DuhemAlphaNotPositive => write!(f, "Duhem alpha must be positive"),
            DuhemBetaNotPositive => write!(f, "Duhem beta must be positive"),
            DuhemGammaNotPositive => write!(f, "Duhem gamma must be positive"),
            DuhemCoefficientOutOfRange => write!(
                f,
                "a Duhem coefficient, normalised, does not fit the Q8.24 format"
            ),
            TooManyDeadZones { count } => write!(
                f,
                "{count} dead zones given, at most {} supported",
                MAX_DEAD_ZONES
            ),
            DeadZoneLengthMismatch {
                thresholds,
                weights,
            } => write!(
                f,
                "{thresholds} dead-zone thresholds but {weights} weights"
            ),
            DeadZoneThresholdsNotIncreasing { dead_zone } => write!(
                f,
                "threshold of dead zone {dead_zone} is zero or does not exceed the one before it"
            ),
            DeadZoneThresholdOutOfRange { dead_zone } => write!(
                f,
                "threshold of dead zone {dead_zone} (or of its inverse) exceeds the span of the output range"
            ),
            DeadZoneLinearNotPositive => write!(
                f,
                "not invertible: the dead-zone map's linear gain is not positive"
            ),
            DeadZoneSlopeNotPositive { dead_zone } => write!(
                f,
                "not invertible: the dead-zone map's slope beyond dead zone {dead_zone} is not positive"
            ),
            DeadZoneWeightOutOfRange { dead_zone } => write!(
                f,
                "weight of dead zone {dead_zone} (or of its inverse) does not fit the Q8.24 format"
            ),
            DeadZoneGainSumTooLarge => write!(
                f,
                "the dead-zone map's sum of |weights| exceeds {MAX_GAIN_SUM} (normalised)"
            ),
            DeadZoneCentreOutOfRange => write!(
                f,
                "the dead-zone map's centre lies outside the output range: check the ranges"
            ),
            Creep(e) => write!(f, "{e}"),
            BoucWenNotPositive(c) => write!(f, "Bouc-Wen {} must be positive", c.name()),
            BoucWenUnbounded(c) => write!(
                f,
                "Bouc-Wen {} lets the hysteretic state grow without bound (need every rate beta +- gamma +- psi +- chi positive: without chi, |psi| < beta - |gamma|)",
                c.name()
            ),
            BoucWenOutOfRange(c) => write!(
                f,
                "Bouc-Wen {}, normalised, does not fit the fixed-point format",
                c.name()
            ),
            BoucWenNotInvertible(c) => write!(
                f,
                "Bouc-Wen {}: the hysteresis bends the output back too steeply (just after a reversal, |a| times 1 + one rate over another must stay below {BOUC_WEN_MAX_INVERSE_LOOP_GAIN} k) for the model to be monotone and its compensator's step unique",
                c.name()
            ),
        }
    }
}

impl core::error::Error for ParamError {}

impl From<crate::models::creep::CreepError> for ParamError {
    fn from(e: crate::models::creep::CreepError) -> Self {
        ParamError::Creep(e)
    }
}

impl From<RangeError> for ParamError {
    fn from(e: RangeError) -> Self {
        match e {
            RangeError::EmptyInput => ParamError::EmptyInputRange,
            RangeError::EmptyOutput => ParamError::EmptyOutputRange,
        }
    }
}

/// How P–I thresholds are spread over the input amplitude (see the book, docs/src/reference/models.md).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Thresholds {
    /// `r_i = (i − 1)/N · A` (the first paper; N = 9 was its best fit).
    Uniform,
    /// `r_i = A · (q^{i−1} − 1)/(q^N − 1)`: denser near zero for `q > 1` (the second paper's
    /// geometric progression); `q → 1` gives the uniform spread.
    Geometric {
        /// Common ratio `q > 0, q ≠ 1`.
        ratio: f64,
    },
}

impl Thresholds {
    /// The `n` thresholds over amplitude `amplitude` (input units), first one zero.
    pub fn generate(
        &self,
        n: usize,
        amplitude: f64,
    ) -> Result<Vec<f64, MAX_OPERATORS>, ParamError> {
        if n == 0 {
            return Err(ParamError::NoOperators);
        }
        if n > MAX_OPERATORS {
            return Err(ParamError::TooManyOperators { count: n });
        }
        if !amplitude.is_finite() || amplitude <= 0.0 {
            return Err(ParamError::NotFinite);
        }
        let mut out = Vec::new();
        for i in 0..n {
            let frac = match *self {
                Thresholds::Uniform => i as f64 / n as f64,
                Thresholds::Geometric { ratio } => {
                    if !ratio.is_finite() || ratio <= 0.0 {
                        return Err(ParamError::NotFinite);
                    }
                    if (ratio - 1.0).abs() < 1e-9 {
                        i as f64 / n as f64
                    } else {
                        (libm::pow(ratio, i as f64) - 1.0) / (libm::pow(ratio, n as f64) - 1.0)
                    }
                }
            };
            // Capacity is MAX_OPERATORS and n <= MAX_OPERATORS: push cannot fail.
            let _ = out.push(frac * amplitude);
        }
        Ok(out)
    }
}

/// A Prandtl–Ishlinskii model in physical units:
/// `y = a0·u + Σ_i w_i · P_{r_i}[u] + offset` (volts in, output units out).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PiParams {
    /// Linear term `a0`, output units per volt.
    pub a0: f64,
    /// Output offset, output units.
    pub offset: f64,
    /// Thresholds `r_i`, volts, `0 ≤ r_1 < r_2 < …`.
    pub thresholds: Vec<f64, MAX_OPERATORS>,
    /// Weights `w_i`, output units per volt.
    pub weights: Vec<f64, MAX_OPERATORS>,
}

/// A P–I model in canonical form: `y = offset + Σ_i w_i · P_{r_i}[u]` with `r_1 = 0` and the
/// linear term folded into operator 1. Units are those of the model it came from.
#[derive(Clone, Debug, PartialEq)]
pub struct CanonicalPi {
    /// Thresholds, first one zero, strictly increasing.
    pub thresholds: Vec<f64, MAX_CANONICAL_OPERATORS>,
    /// Weights.
    pub weights: Vec<f64, MAX_CANONICAL_OPERATORS>,
    /// Output offset (forward) or input offset subtracted first (inverse).
    pub offset: f64,
}

impl PiParams {
    /// A model from thresholds and weights (volts, output units per volt).
    pub fn new(
        a0: f64,
        offset: f64,
        thresholds: &[f64],
        weights: &[f64],
    ) -> Result<Self, ParamError> {
        if thresholds.len() > MAX_OPERATORS {
            return Err(ParamError::TooManyOperators {
                count: thresholds.len(),
            });
        }
        if weights.len() != thresholds.len() {
            return Err(ParamError::LengthMismatch {
                thresholds: thresholds.len(),
                weights: weights.len(),
            });
        }
        let p = Self {
            a0,
            offset,
            thresholds: Vec::from_slice(thresholds).map_err(|_| ParamError::TooManyOperators {
                count: thresholds.len(),
            })?,
            weights: Vec::from_slice(weights).map_err(|_| ParamError::TooManyOperators {
                count: weights.len(),
            })?,
        };
        Ok(p)
    }

    /// Checks the model is well formed: finite, thresholds non-negative and strictly
    /// increasing, at least one operator or a linear term. (It need not be invertible.)
    pub fn validate(&self) -> Result<(), ParamError> {
        if self.weights.len() != self.thresholds.len() {
            return Err(ParamError::LengthMismatch {
                thresholds: self.thresholds.len(),
                weights: self.weights.len(),
            });
        }
        if self.thresholds.is_empty() && self.a0 == 0.0 {
            return Err(ParamError::NoOperators);
        }
        let finite = self.a0.is_finite()
            && self.offset.is_finite()
            && self
                .thresholds
                .iter()
                .chain(self.weights.iter())
                .all(|v| v.is_finite());
        if !finite {
            return Err(ParamError::NotFinite);
        }
        for (i, &r) in self.thresholds.iter().enumerate() {
            if r < 0.0 {
                return Err(ParamError::NegativeThreshold { operator: i + 1 });
            }
            if i > 0 && r <= self.thresholds[i - 1] {
                return Err(ParamError::ThresholdsNotIncreasing { operator: i + 1 });
            }
        }
        Ok(())
    }

    /// The canonical form: `a0` folded into the `r = 0` operator (added to `w_1` when
    /// `r_1 = 0`, otherwise given an operator of its own in front).
    pub fn canonical(&self) -> Result<CanonicalPi, ParamError> {
        self.validate()?;
        let mut thresholds = Vec::new();
        let mut weights = Vec::new();
        let first_is_zero = self.thresholds.first() == Some(&0.0);
        if !first_is_zero && self.a0 != 0.0 {
            let _ = thresholds.push(0.0);
            let _ = weights.push(self.a0);
        }
        for (i, (&r, &w)) in self.thresholds.iter().zip(self.weights.iter()).enumerate() {
            let w = if i == 0 && first_is_zero {
                w + self.a0
            } else {
                w
            };
            // Capacity MAX_OPERATORS + 1 holds the linear slot plus every operator.
            let _ = thresholds.push(r);
            let _ = weights.push(w);
        }
        Ok(CanonicalPi {
            thresholds,
            weights,
            offset: self.offset,
        })
    }

    /// The model in normalised coordinates of `scaling` (both ranges onto [-1, 1]).
    ///
    /// The play operator commutes with affine maps of its input, so
    /// `r → r / U`, `w → w · U / Y`, and the offset absorbs both range centres.
    pub fn normalized(&self, scaling: &Scaling) -> Result<PiParams, ParamError> {
        self.validate()?;
        let u_half = scaling.input_half_span();
        let y_half = scaling.output_half_span();
        let g = scaling.gain_to_norm();
        let total: f64 = self.a0 + self.weights.iter().sum::<f64>();
        let offset = (self.offset + total * scaling.input_mid() - scaling.output_mid()) / y_half;
        let mut thresholds = Vec::new();
        let mut weights = Vec::new();
        // A finite value that overflows on scaling is beyond fixed point for that value, as
        // any other too large (1e300 and f64::MIN alike), not "not finite" for the model.
        for (i, (&r, &w)) in self.thresholds.iter().zip(self.weights.iter()).enumerate() {
            let (r, w) = (r / u_half, w * g);
            if !r.is_finite() {
                return Err(ParamError::ThresholdOutOfRange { operator: i + 1 });
            }
            if !w.is_finite() {
                return Err(ParamError::WeightOutOfRange { operator: i + 1 });
            }
            let _ = thresholds.push(r);
            let _ = weights.push(w);
        }
        // `a0` is the first operator's slope (folded into it by `canonical`).
        if !(self.a0 * g).is_finite() {
            return Err(ParamError::WeightOutOfRange { operator: 1 });
        }
        if !offset.is_finite() {
            return Err(ParamError::OffsetOutOfRange);
        }
        Ok(PiParams {
            a0: self.a0 * g,
            offset,
            thresholds,
            weights,
        })
    }
}

impl CanonicalPi {
    /// The analytic inverse (see the book, docs/src/reference/models.md): `r'_i = Σ_{j≤i} w_j (r_i − r_j)`, `w'_1 = 1/w_1`,
    /// `w'_i = −w_i / (S_i S_{i−1})`; its offset is the forward offset, subtracted from the
    /// desired output before the play operators. Refuses non-invertible models with the first
    /// failing operator.
    pub fn inverse(&self) -> Result<CanonicalPi, ParamError> {
        if self.thresholds.is_empty() {
            return Err(ParamError::NoOperators);
        }
        if self.thresholds[0] != 0.0 {
            return Err(ParamError::FirstThresholdNotZero);
        }
        if self.weights[0] <= 0.0 {
            return Err(ParamError::FirstWeightNotPositive);
        }
        let mut thresholds = Vec::new();
        let mut weights = Vec::new();
        let mut partial = 0.0;
        for i in 0..self.weights.len() {
            let previous = partial;
            partial += self.weights[i];
            if partial <= 0.0 {
                return Err(ParamError::PartialSumNotPositive { operator: i + 1 });
            }
            let r_i = self.thresholds[i];
            let r_inv: f64 = self.thresholds[..=i]
                .iter()
                .zip(self.weights[..=i].iter())
                .map(|(&r_j, &w_j)| w_j * (r_i - r_j))
                .sum();
            let w_inv = if i == 0 {
                1.0 / self.weights[0]
            } else {
                -self.weights[i] / (partial * previous)
            };
            let _ = thresholds.push(r_inv);
            let _ = weights.push(w_inv);
        }
        Ok(CanonicalPi {
            thresholds,
            weights,
            offset: self.offset,
        })
    }

    /// Checks a normalised canonical model fits the fixed-point formats: thresholds within
    /// the normalised span, weights within Q8.24, `Σ|w| + |offset|` within [`MAX_GAIN_SUM`].
    pub fn check_fixed_point_range(&self) -> Result<(), ParamError> {
        let mut sum = self.offset.abs();
        for (i, (&r, &w)) in self.thresholds.iter().zip(self.weights.iter()).enumerate() {
            // The physical parameters were checked finite (`PiParams::validate`): an infinite
            // or NaN value here is a finite one that overflowed on the way (scaled, or `a0`
            // folded in), so it is beyond fixed point like any other too large, not "not
            // finite" for the whole model.
            if !r.is_finite() || r > MAX_NORM_THRESHOLD {
                return Err(ParamError::ThresholdOutOfRange { operator: i + 1 });
            }
            if !w.is_finite() || w.abs() > MAX_NORM_WEIGHT {
                return Err(ParamError::WeightOutOfRange { operator: i + 1 });
            }
            sum += w.abs();
        }
        if !self.offset.is_finite() || self.offset.abs() > 1.5 {
            return Err(ParamError::OffsetOutOfRange);
        }
        if sum > MAX_GAIN_SUM {
            return Err(ParamError::GainSumTooLarge);
        }
        Ok(())
    }
}

/// A Duhem model in physical units: `ẏ = α |u̇| (β u + offset − y) + γ u̇`
/// (volts in, output units out), integrated exactly in the input over each sample's step
/// (see [`crate::models::duhem`] and the book, docs/src/reference/models.md).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DuhemParams {
    /// `α > 0`, per volt.
    pub alpha: f64,
    /// `β > 0`, output units per volt (slope of the anhysteretic curve).
    pub beta: f64,
    /// `γ > 0`, output units per volt (slope just after a reversal).
    pub gamma: f64,
    /// Offset of the anhysteretic curve, output units.
    pub offset: f64,
}

impl DuhemParams {
    /// Checks `α, β, γ > 0` and that everything is finite.
    pub fn validate(&self) -> Result<(), ParamError> {
        if ![self.alpha, self.beta, self.gamma, self.offset]
            .iter()
            .all(|v| v.is_finite())
        {
            return Err(ParamError::NotFinite);
        }
        if self.alpha <= 0.0 {
            return Err(ParamError::DuhemAlphaNotPositive);
        }
        if self.beta <= 0.0 {
            return Err(ParamError::DuhemBetaNotPositive);
        }
        if self.gamma <= 0.0 {
            return Err(ParamError::DuhemGammaNotPositive);
        }
        Ok(())
    }

    /// The model in the normalised coordinates of `scaling`:
    /// `α → α U`, `β, γ → (β, γ) U / Y`, `offset → (β u_mid + offset − y_mid) / Y`.
    pub fn normalized(&self, scaling: &Scaling) -> Result<DuhemParams, ParamError> {
        self.validate()?;
        let g = scaling.gain_to_norm();
        let n = DuhemParams {
            alpha: self.alpha * scaling.input_half_span(),
            beta: self.beta * g,
            gamma: self.gamma * g,
            offset: (self.beta * scaling.input_mid() + self.offset - scaling.output_mid())
                / scaling.output_half_span(),
        };
        // β + |δ| < 2 keeps the anhysteretic curve βu + δ inside Q2.30 for |u| ≤ 1 (the tick
        // relies on it), and γ < 2 lets the tick hold γ as a Q2.30 signal; an output range
        // that narrow against the model is a scaling error.
        let fits = [n.alpha, n.beta, n.gamma]
            .iter()
            .all(|v| *v <= MAX_NORM_WEIGHT)
            && n.offset.abs() <= 1.5
            && n.beta + n.offset.abs() < 1.99
            && n.gamma < 1.99;
        if !fits {
            return Err(ParamError::DuhemCoefficientOutOfRange);
        }
        Ok(n)
    }
}

/// Largest bound on the normalised Bouc–Wen hysteretic state `|h|` a model may have: `h` is
/// held in Q2.30 (saturating at ±2), with a margin.
pub const BOUC_WEN_MAX_NORM_STATE: f64 = 1.9;
/// Smallest normalised Bouc–Wen slope `k`: the compensator multiplies by `1/k` held in Q8.24,
/// and `1/k ≤ 64` keeps its product with the residual (`|y_d − δ − h| < 4.5`) inside `i64`.
pub const BOUC_WEN_MIN_NORM_SLOPE: f64 = 1.0 / 64.0;
/// Largest normalised Bouc–Wen `β`; every factor `β ± γ ± ψ ± χ` is held at most twice it,
/// which Q8.24 holds.
pub const BOUC_WEN_MAX_NORM_BETA: f64 = 40.0;
/// Largest hysteretic slope of a Bouc–Wen model the compensator accepts, relative to `k`
/// ([`BoucWenParams::inverse_loop_gain`]): at 1 the model's slope may reach zero (not
/// monotone, the inverse not unique); 0.9 keeps a margin for the rounding.
pub const BOUC_WEN_MAX_INVERSE_LOOP_GAIN: f64 = 0.9;

/// A generalised Bouc–Wen model in physical units (volts in, output units out):
/// `y = k·u + offset + h`, with the hysteretic state
/// `dh = a·du − β·|du|·h − γ·du·|h| − ψ·du·h − χ·|du|·|h|` (exponent `n = 1`), integrated
/// exactly in the input over each sample's step (see [`crate::models::bouc_wen`]).
///
/// `β, γ` are the classical Bouc–Wen terms; `ψ` and `χ` the asymmetric ones: `ψ` makes the
/// rising and the falling branches differ, `χ` a state of one sign decay faster than one of
/// the other. Together the four set the four rates at which `h` relaxes (by direction and by
/// the sign of `h`, [`BoucWenParams::factor`]) independently: a stage whose rising branch
/// saturates before its falling one does has no single `ψ`. The Duhem model of [`DuhemParams`] is the special case
/// `γ = ψ = 0`, `k = β_D`, `a = γ_D − β_D`, `β = α_D` (see the book,
/// docs/src/reference/models.md).
///
/// ```
/// use twinstack::models::params::{BoucWenCoefficient, BoucWenParams};
/// use twinstack::ParamError;
/// let p = BoucWenParams { k: 0.4, offset: 0.0, a: 0.15, beta: 0.03, gamma: 0.01, psi: 0.005, chi: 0.004 };
/// assert_eq!(p.validate(), Ok(()));
/// // The four rates β ± γ ± ψ ± χ: a rising step relaxes a positive state at β + γ + ψ + χ.
/// assert!((p.factor(1.0, 1.0) - 0.049).abs() < 1e-12);
/// let unbounded = BoucWenParams { psi: 0.03, ..p };
/// assert_eq!(unbounded.validate(), Err(ParamError::BoucWenUnbounded(BoucWenCoefficient::Psi)));
/// // Rising from a negative state, β − γ + ψ − χ = −0.001: h would grow without bound.
/// let unbounded = BoucWenParams { chi: 0.026, ..p };
/// assert_eq!(unbounded.validate(), Err(ParamError::BoucWenUnbounded(BoucWenCoefficient::Chi)));
/// ```
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BoucWenParams {
    /// `k > 0`, output units per volt: the linear slope.
    pub k: f64,
    /// `δ`, output units: the output at zero input with `h = 0`.
    pub offset: f64,
    /// `A`, output units per volt: the hysteretic state's gain on the input step (any sign:
    /// `k + A` is the slope just after a reversal).
    pub a: f64,
    /// `β > 0`, per volt: the classical decay of `h` with `|Δu|`.
    pub beta: f64,
    /// `γ`, per volt, `|γ| < β`: the classical `Δu·|h|` term.
    pub gamma: f64,
    /// `ψ`, per volt, `|ψ| < β`: the asymmetric `Δu·h` term.
    pub psi: f64,
    /// `χ`, per volt: the `|Δu|·|h|` term, by which a state of one sign decays faster than
    /// one of the other (0 when absent from a file). Every factor `β ± γ ± ψ ± χ` must be
    /// positive.
    #[serde(default)]
    pub chi: f64,
}

impl BoucWenParams {
    /// Checks the model is finite, `k > 0`, and bounded: `β > 0`, `|γ| < β`, `|ψ| < β`, and
    /// every factor `β ± γ ± ψ ± χ` multiplying `h` ([`BoucWenParams::factors`]) positive
    /// (without `χ`, `|ψ| < β − |γ|`). A factor that is not is refused naming `χ`, or `ψ` for
    /// a model without `χ`.
    pub fn validate(&self) -> Result<(), ParamError> {
        use BoucWenCoefficient as C;
        let all = [
            self.k,
            self.offset,
            self.a,
            self.beta,
            self.gamma,
            self.psi,
            self.chi,
        ];
        if !all.iter().all(|v| v.is_finite()) {
            return Err(ParamError::NotFinite);
        }
        if self.k <= 0.0 {
            return Err(ParamError::BoucWenNotPositive(C::K));
        }
        if self.beta <= 0.0 {
            return Err(ParamError::BoucWenNotPositive(C::Beta));
        }
        if self.gamma.abs() >= self.beta {
            return Err(ParamError::BoucWenUnbounded(C::Gamma));
        }
        if self.psi.abs() >= self.beta {
            return Err(ParamError::BoucWenUnbounded(C::Psi));
        }
        if self.min_factor() <= 0.0 {
            // Without χ the factors are all positive exactly when |ψ| < β − |γ|.
            let c = if self.chi == 0.0 { C::Psi } else { C::Chi };
            return Err(ParamError::BoucWenUnbounded(c));
        }
        Ok(())
    }

    /// The four factors multiplying `h` per unit `|Δu|`, [`BoucWenParams::factor`] of (rising,
    /// `h ≥ 0`), (rising, `h < 0`), (falling, `h ≥ 0`), (falling, `h < 0`).
    pub fn factors(&self) -> [f64; 4] {
        // c = (β + s·ψ) + sgn(h)·(s·γ + χ), in sums rather than products by ±1 (the board's
        // f64 arithmetic is software).
        let (rising, falling) = (self.beta + self.psi, self.beta - self.psi);
        let (by_sign_rising, by_sign_falling) = (self.gamma + self.chi, self.chi - self.gamma);
        [
            rising + by_sign_rising,
            rising - by_sign_rising,
            falling + by_sign_falling,
            falling - by_sign_falling,
        ]
    }

    /// The smallest factor multiplying `h` per unit `|Δu|` (positive for a valid model;
    /// `β − |γ| − |ψ|` without `χ`).
    pub fn min_factor(&self) -> f64 {
        self.factors().into_iter().fold(f64::INFINITY, f64::min)
    }

    /// The largest factor multiplying `h` per unit `|Δu|` (`β + |γ| + |ψ|` without `χ`).
    pub fn max_factor(&self) -> f64 {
        self.factors().into_iter().fold(f64::NEG_INFINITY, f64::max)
    }

    /// The model with slope `k`, `offset`, `a` and the four factors ([`BoucWenParams::factors`])
    /// `c`: `β` their mean, `γ`, `ψ`, `χ` their contrasts (each factor is `β ± γ ± ψ ± χ`, so
    /// the four determine the four).
    pub fn from_factors(k: f64, offset: f64, a: f64, c: [f64; 4]) -> Self {
        Self {
            k,
            offset,
            a,
            beta: (c[0] + c[1] + c[2] + c[3]) / 4.0,
            gamma: (c[0] - c[1] - c[2] + c[3]) / 4.0,
            psi: (c[0] + c[1] - c[2] - c[3]) / 4.0,
            chi: (c[0] - c[1] + c[2] - c[3]) / 4.0,
        }
    }

    /// The factor `c` multiplying `h` per unit `|Δu|` on a step in direction `s` (±1) from a
    /// state of sign `sh` (±1): `β + s·sh·γ + s·ψ + sh·χ`.
    pub fn factor(&self, s: f64, sh: f64) -> f64 {
        self.factors()[(usize::from(s < 0.0) << 1) | usize::from(sh < 0.0)]
    }

    /// The steepest the hysteresis bends the output back, relative to `k`: the most negative
    /// local slope `∂h/∂u = A − c·s·h` over the states the model reaches from rest (`h`
    /// between the two branches' saturations), negated. With `A ≥ 0` it is never negative
    /// (0: the output's slope is at least `k`). With `A < 0` it is most negative just after a
    /// reversal from the other branch's saturation: rising from the falling branch's
    /// `|A|/c(falling, h ≥ 0)`, `|A|·(1 + c(rising, h ≥ 0)/c(falling, h ≥ 0))`; falling from the
    /// rising branch's `−|A|/c(rising, h < 0)`, `|A|·(1 + c(falling, h < 0)/c(rising, h < 0))`
    /// ([`BoucWenParams::factors`]). Below 1 the model's slope `k + ∂h/∂u` stays positive in
    /// both directions: the model is monotone and the compensator's step (the drive change
    /// that gives a desired output change) unique. The name keeps the gain an inverse
    /// `u = (y_d − δ − h)/k` would loop with.
    pub fn inverse_loop_gain(&self) -> f64 {
        if self.a >= 0.0 {
            return 0.0;
        }
        let [rising_up, rising_down, falling_up, falling_down] = self.factors();
        let steepest = (rising_up / falling_up).max(falling_down / rising_down);
        -self.a * (1.0 + steepest) / self.k
    }

    /// The bound on the hysteretic state from rest (`h = 0`): `|h| ≤ |A| / c_min`,
    /// the farthest of the targets `±A/c` each step relaxes toward (a fraction `q ≤ 1` of the
    /// way). Meaningful in normalised units.
    pub fn state_bound(&self) -> f64 {
        self.a.abs() / self.min_factor()
    }

    /// The model in the normalised coordinates of `scaling`: `k, A → (k, A)·U/Y`,
    /// `β, γ, ψ, χ → (β, γ, ψ, χ)·U`, `offset → (k·u_mid + offset − y_mid)/Y` (`h` scales by `1/Y`).
    /// Refuses, naming it, a coefficient that does not fit the fixed point.
    pub fn normalized(&self, scaling: &Scaling) -> Result<BoucWenParams, ParamError> {
        use BoucWenCoefficient as C;
        self.validate()?;
        let g = scaling.gain_to_norm();
        let u_half = scaling.input_half_span();
        let n = BoucWenParams {
            k: self.k * g,
            offset: (self.k * scaling.input_mid() + self.offset - scaling.output_mid())
                / scaling.output_half_span(),
            a: self.a * g,
            beta: self.beta * u_half,
            gamma: self.gamma * u_half,
            psi: self.psi * u_half,
            chi: self.chi * u_half,
        };
        let out = |c| Err(ParamError::BoucWenOutOfRange(c));
        // k·u fits Q2.30 for k < 2; 1/k ≤ 64 (see BOUC_WEN_MIN_NORM_SLOPE).
        if !(BOUC_WEN_MIN_NORM_SLOPE..1.99).contains(&n.k) {
            return out(C::K);
        }
        if n.offset.abs() > 1.5 {
            return out(C::Offset);
        }
        // A is held in Q2.30.
        if n.a.abs() >= 1.99 {
            return out(C::A);
        }
        if n.beta > BOUC_WEN_MAX_NORM_BETA || n.max_factor() > 2.0 * BOUC_WEN_MAX_NORM_BETA {
            return out(C::Beta);
        }
        if n.state_bound() > BOUC_WEN_MAX_NORM_STATE {
            return out(C::A);
        }
        Ok(n)
    }

    /// The Bouc–Wen form of a Duhem model (the same discrete model, sample for sample):
    /// `k = β_D`, `offset = δ_D`, `A = γ_D − β_D`, `β = α_D`, `γ = ψ = χ = 0`.
    pub fn from_duhem(d: &DuhemParams) -> Self {
        Self {
            k: d.beta,
            offset: d.offset,
            a: d.gamma - d.beta,
            beta: d.alpha,
            gamma: 0.0,
            psi: 0.0,
            chi: 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pi(a0: f64, r: &[f64], w: &[f64]) -> PiParams {
        PiParams::new(a0, 0.0, r, w).unwrap()
    }

    #[test]
    fn each_failure_mode_has_its_own_error() {
        assert_eq!(
            PiParams::new(0.0, 0.0, &[0.0; 33], &[1.0; 33]),
            Err(ParamError::TooManyOperators { count: 33 })
        );
        assert_eq!(
            PiParams::new(0.0, 0.0, &[0.0, 1.0], &[1.0]),
            Err(ParamError::LengthMismatch {
                thresholds: 2,
                weights: 1
            })
        );
        assert_eq!(pi(0.0, &[], &[]).validate(), Err(ParamError::NoOperators));
        assert_eq!(
            pi(0.0, &[0.0, f64::NAN], &[1.0, 1.0]).validate(),
            Err(ParamError::NotFinite)
        );
        assert_eq!(
            pi(0.0, &[-1.0, 1.0], &[1.0, 1.0]).validate(),
            Err(ParamError::NegativeThreshold { operator: 1 })
        );
        assert_eq!(
            pi(0.0, &[0.0, 1.0, 1.0], &[1.0, 1.0, 1.0]).validate(),
            Err(ParamError::ThresholdsNotIncreasing { operator: 3 })
        );
        let inv = |p: PiParams| p.canonical().and_then(|c| c.inverse());
        assert_eq!(
            inv(pi(0.0, &[0.5, 1.0], &[1.0, 1.0])),
            Err(ParamError::FirstThresholdNotZero)
        );
        assert_eq!(
            inv(pi(0.0, &[0.0, 1.0], &[-0.1, 1.0])),
            Err(ParamError::FirstWeightNotPositive)
        );
        // w_1 = 0 is refused too (the boundary case of w_1 <= 0).
        assert_eq!(
            inv(pi(0.0, &[0.0, 1.0], &[0.0, 1.0])),
            Err(ParamError::FirstWeightNotPositive)
        );
        assert_eq!(
            inv(pi(0.0, &[0.0, 1.0, 2.0, 3.0], &[1.0, 0.5, -0.2, -1.5])),
            Err(ParamError::PartialSumNotPositive { operator: 4 })
        );
        // a0 rescues a negative first weight when it is folded in.
        assert!(inv(pi(2.0, &[0.0, 1.0], &[-1.0, 0.5])).is_ok());
    }

    #[test]
    fn fixed_point_range_errors_name_the_operator() {
        let c = CanonicalPi {
            thresholds: Vec::from_slice(&[0.0, 1.0, 2.5]).unwrap(),
            weights: Vec::from_slice(&[1.0, 1.0, 1.0]).unwrap(),
            offset: 0.0,
        };
        assert_eq!(
            c.check_fixed_point_range(),
            Err(ParamError::ThresholdOutOfRange { operator: 3 })
        );
        let c = CanonicalPi {
            thresholds: Vec::from_slice(&[0.0, 1.0]).unwrap(),
            weights: Vec::from_slice(&[1.0, -200.0]).unwrap(),
            offset: 0.0,
        };
        assert_eq!(
            c.check_fixed_point_range(),
            Err(ParamError::WeightOutOfRange { operator: 2 })
        );
        let c = CanonicalPi {
            thresholds: Vec::from_slice(&[0.0, 0.1, 0.2]).unwrap(),
            weights: Vec::from_slice(&[100.0, -50.0, 40.0]).unwrap(),
            offset: 0.0,
        };
        assert_eq!(
            c.check_fixed_point_range(),
            Err(ParamError::GainSumTooLarge)
        );
    }

    #[test]
    fn duhem_failure_modes_have_their_own_errors() {
        let ok = DuhemParams {
            alpha: 0.1,
            beta: 0.2,
            gamma: 0.15,
            offset: 0.0,
        };
        assert_eq!(ok.validate(), Ok(()));
        let bad = |f: fn(&mut DuhemParams)| {
            let mut p = ok;
            f(&mut p);
            p.validate()
        };
        assert_eq!(
            bad(|p| p.alpha = 0.0),
            Err(ParamError::DuhemAlphaNotPositive)
        );
        assert_eq!(
            bad(|p| p.beta = -1.0),
            Err(ParamError::DuhemBetaNotPositive)
        );
        assert_eq!(
            bad(|p| p.gamma = 0.0),
            Err(ParamError::DuhemGammaNotPositive)
        );
        assert_eq!(
            bad(|p| p.offset = f64::INFINITY),
            Err(ParamError::NotFinite)
        );
        let s = Scaling::new(0.0, 150.0, 0.0, 1.0).unwrap();
        assert_eq!(
            DuhemParams { alpha: 1.0, ..ok }.normalized(&s),
            Err(ParamError::DuhemCoefficientOutOfRange)
        );
        // β so steep against the output range that βu + δ would leave Q2.30.
        assert_eq!(
            DuhemParams { beta: 0.014, ..ok }.normalized(&s),
            Err(ParamError::DuhemCoefficientOutOfRange)
        );
    }

    #[test]
    fn bouc_wen_refusals_name_the_coefficient() {
        use BoucWenCoefficient as C;
        let ok = BoucWenParams {
            k: 0.4,
            offset: 1.0,
            a: -0.1,
            beta: 0.03,
            gamma: 0.01,
            psi: -0.005,
            chi: 0.004,
        };
        assert_eq!(ok.validate(), Ok(()));
        let bad = |f: fn(&mut BoucWenParams)| {
            let mut p = ok;
            f(&mut p);
            p.validate()
        };
        assert_eq!(
            bad(|p| p.k = 0.0),
            Err(ParamError::BoucWenNotPositive(C::K))
        );
        assert_eq!(
            bad(|p| p.beta = -0.1),
            Err(ParamError::BoucWenNotPositive(C::Beta))
        );
        assert_eq!(
            bad(|p| p.gamma = -0.03),
            Err(ParamError::BoucWenUnbounded(C::Gamma))
        );
        assert_eq!(
            bad(|p| p.psi = 0.03),
            Err(ParamError::BoucWenUnbounded(C::Psi))
        );
        // Without χ, |ψ| < β − |γ| is the rule, and ψ is named.
        assert_eq!(
            bad(|p| {
                p.chi = 0.0;
                p.psi = 0.02
            }),
            Err(ParamError::BoucWenUnbounded(C::Psi))
        );
        // β = 0.03, γ = 0.01, ψ = −0.005: the factors β ± γ ± ψ ± χ (rising with h ≥ 0, rising
        // with h < 0, falling with h ≥ 0, falling with h < 0) are 0.035 + χ, 0.015 − χ,
        // 0.025 + χ, 0.045 − χ: χ = 0.015 makes the second zero, χ = −0.025 the third.
        assert_eq!(
            bad(|p| p.chi = 0.015),
            Err(ParamError::BoucWenUnbounded(C::Chi))
        );
        assert_eq!(
            bad(|p| p.chi = -0.025),
            Err(ParamError::BoucWenUnbounded(C::Chi))
        );
        assert_eq!(bad(|p| p.chi = 0.0149), Ok(()));
        assert_eq!(bad(|p| p.chi = -0.0249), Ok(()));
        // Four factors determine the four coefficients, and back.
        let c = [0.02, 0.014, 0.002, 0.04];
        let m = BoucWenParams::from_factors(ok.k, ok.offset, ok.a, c);
        for (got, want) in m.factors().into_iter().zip(c) {
            assert!((got - want).abs() < 1e-15, "{got} vs {want}");
        }
        assert_eq!(
            BoucWenParams::from_factors(ok.k, ok.offset, ok.a, ok.factors()).validate(),
            Ok(())
        );
        assert_eq!(bad(|p| p.chi = f64::INFINITY), Err(ParamError::NotFinite));
        assert_eq!(bad(|p| p.a = f64::NAN), Err(ParamError::NotFinite));
        // A < 0: |A|(1 + the larger of c(rising, h ≥ 0)/c(falling, h ≥ 0) and
        // c(falling, h < 0)/c(rising, h < 0))/k = 0.1·(1 + 0.041/0.011)/0.4; with A > 0 the
        // hysteresis never bends the output back.
        assert!((ok.inverse_loop_gain() - 0.1 * (1.0 + 0.041 / 0.011) / 0.4).abs() < 1e-12);
        assert_eq!(BoucWenParams { a: 0.1, ..ok }.inverse_loop_gain(), 0.0);
        let s = Scaling::new(0.0, 150.0, 0.0, 60.0).unwrap();
        assert!(ok.normalized(&s).is_ok());
        let range = |p: BoucWenParams| p.normalized(&s);
        assert_eq!(
            range(BoucWenParams { k: 0.002, ..ok }),
            Err(ParamError::BoucWenOutOfRange(C::K))
        );
        assert_eq!(
            range(BoucWenParams {
                offset: 200.0,
                ..ok
            }),
            Err(ParamError::BoucWenOutOfRange(C::Offset))
        );
        assert_eq!(
            range(BoucWenParams { a: 0.9, ..ok }),
            Err(ParamError::BoucWenOutOfRange(C::A))
        );
        assert_eq!(
            range(BoucWenParams { beta: 0.6, ..ok }),
            Err(ParamError::BoucWenOutOfRange(C::Beta))
        );
        // A β barely above |γ| + |ψ| + |χ| lets h reach |A|/c_min ≈ 33 normalised.
        assert_eq!(
            range(BoucWenParams { beta: 0.0191, ..ok }),
            Err(ParamError::BoucWenOutOfRange(C::A))
        );
    }

    #[test]
    fn thresholds_uniform_and_geometric_start_at_zero_and_increase() {
        let u = Thresholds::Uniform.generate(9, 90.0).unwrap();
        assert_eq!(u[0], 0.0);
        assert!((u[8] - 80.0).abs() < 1e-12);
        let g = Thresholds::Geometric { ratio: 1.2 }
            .generate(17, 150.0)
            .unwrap();
        assert_eq!(g[0], 0.0);
        assert!(g.windows(2).all(|w| w[1] > w[0]));
        assert!(g[16] < 150.0);
        assert!(g[1] < 150.0 / 17.0, "geometric is denser near zero");
        assert_eq!(
            Thresholds::Uniform.generate(33, 1.0),
            Err(ParamError::TooManyOperators { count: 33 })
        );
    }
}
