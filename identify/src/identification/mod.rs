//! Identification: from a measured record (`t, u, x`) to a [`StageModel`] the board can run.
//!
//! The record is split in time: samples with `t < fit_until` are fitted, the rest are kept
//! for scoring. On the fitted part:
//!
//! 1. **Motion start** ([`motion`]): rows before the drive moves carry no information; a drive
//!    that steps at the first sample of motion (a start-up glitch) makes the stage ring, and
//!    the settling samples are left out.
//! 2. **Sign**: a sensor whose reading falls as the drive rises is fitted on the negated
//!    reading, and the model records `output_sign = −1`.
//! 3. **Lag**: the sensor may lag the drive by a few samples, in half samples: a drive held
//!    for a sample (the board's DAC, a DAQ's output) acts on the stage as at the middle of its
//!    hold, so on such a record a reading of a hold's end is half a sample past the instant the
//!    drive's model output belongs to; a half lag `L + ½` pairs drive `k` with the value between the
//!    readings `k + L` and `k + L + 1` ([`crate::stage_model::between_samples`]). Unless given, a
//!    lag is estimated only where the data supports one: the P–I fit is repeated for 0,
//!    ½, 1, … `max_lag` samples (its
//!    residual screened for outliers as in step 4), and a
//!    lag is kept only if it lowers the residual RMS by at least [`LAG_EVIDENCE`] of the
//!    no-lag fit's (noise, resonance or creep shave a little off at any lag; a real delay
//!    takes off much more); then the smallest lag within [`LAG_TOLERANCE`] of the best.
//! 4. **Outliers**: rows whose P–I residual exceeds [`OUTLIER_FACTOR`] × its RMS (spikes,
//!    leftover ringing) are dropped and the model refitted.
//! 5. **Model**: P–I weights by NNLS ([`pi`]), or Duhem by integrated least squares with a
//!    stability check (an output-error refit where it fails) and a simulated-error refinement
//!    ([`duhem`]), or a generalised
//!    (asymmetric) P–I by Kuhnen's linear equation-error fit ([`gpi`]), or the generalised
//!    Bouc–Wen from that Duhem fit refined on the simulated error ([`bouc_wen`]); after a
//!    Bouc–Wen, where asked for, a static output map, the model refined with it
//!    ([`output_map`]).
//! 6. **Scaling**: the input range is the fitted drive range (widened by [`INPUT_MARGIN`],
//!    zero: the range's ends are the rails the stage was swept between, where the models'
//!    rest state puts the major loop, see `twinstack::models::prandtl_ishlinskii`), the
//!    output range the model's output range widened by [`OUTPUT_MARGIN`] — for Duhem, wider
//!    still if needed so that the distance to the anhysteretic curve stays within
//!    [`DUHEM_MAX_NORM_DISTANCE`] normalised (the fixed-point model saturates it at 2). The
//!    library then has to accept the model for both the observer and the compensator; a P–I
//!    whose inverse it refuses (`w_1 = 0`, inverse weights beyond Q8.24) is refitted with
//!    `w_1` floored at [`MIN_NORM_FIRST_WEIGHT`] (normalised).
//!
//! Every row is fitted against the model run over the whole record from rest, the way
//! `predict` runs it, so the fitted and the checked model see the same operator states.

mod alternation;
pub mod auto;
pub mod bouc_wen;
pub mod coverage;
pub mod creep;
pub mod duhem;
pub mod gpi;
pub mod least_squares;
pub mod motion;
pub mod output_map;
pub mod pi;
pub mod run;
pub mod score;
pub mod simplex;

use crate::stage_model::{between, between_samples, Hysteresis, StageModel};
use least_squares::LeastSquaresError;
pub use pi::ThresholdSpread;
use std::cell::RefCell;
use twinstack::{ParamError, Scaling};
use twinstack_link::measured_data::MeasuredData;

/// Residuals beyond this multiple of the RMS residual are dropped as outliers.
pub const OUTLIER_FACTOR: f64 = 5.0;

/// The widest span of a column (max − min over the fitted part, in its own units) the models
/// compute in: far beyond any drive in volts or reading in any length unit, well short of
/// where their arithmetic overflows.
pub const MAX_SPAN: f64 = 1e12;
/// The input range is the fitted drive range widened by this fraction of its span each side.
///
/// Zero: the models' rest state ("the drive came down from the top of the input range to
/// its bottom, then rose") is only right if the range's ends are where the stage's drive
/// actually turned. On the simulated lab stage a 2 % margin cost 0.2 % of span in tracking
/// (0.78 → 1.00 % max); a drive beyond the range is clamped by the forward model.
pub const INPUT_MARGIN: f64 = 0.0;
/// The output range is the model's output range widened by this fraction each side.
pub const OUTPUT_MARGIN: f64 = 0.05;
/// A lag is estimated only if it lowers the P–I residual RMS by at least this fraction of the
/// no-lag fit's.
pub const LAG_EVIDENCE: f64 = 0.05;
/// The largest lag [`IdentifyOptions::given_lag`] takes, samples.
pub const MAX_GIVEN_LAG: f64 = 100_000.0;

/// A given lag of `samples` in half samples: a whole or a half number from 0 to
/// [`MAX_GIVEN_LAG`], else an error naming it.
///
/// ```
/// use twinstack_identify::identification::half_samples;
/// assert_eq!(half_samples(1.5), Ok(3));
/// assert!(half_samples(-0.5).is_err() && half_samples(0.25).is_err());
/// ```
pub fn half_samples(samples: f64) -> Result<usize, String> {
    let halves = 2.0 * samples;
    if !(samples.is_finite() && (0.0..=MAX_GIVEN_LAG).contains(&samples)) || halves.fract() != 0.0 {
        return Err(format!(
            "lag {samples}: not a whole or half number of samples from 0 to {MAX_GIVEN_LAG}"
        ));
    }
    Ok(halves as usize)
}

/// Among the lags that do, the smallest whose RMS is within this fraction of the best.
pub const LAG_TOLERANCE: f64 = 0.01;

/// The lag the residuals `(lag, rms)` (increasing lags from 0, in half samples) support: 0
/// unless one lowers the RMS by [`LAG_EVIDENCE`], else the smallest within [`LAG_TOLERANCE`]
/// of the best.
pub fn supported_lag(fits: &[(usize, f64)]) -> usize {
    let Some(&(_, at_zero)) = fits.first() else {
        return 0;
    };
    let best = fits.iter().map(|f| f.1).fold(f64::INFINITY, f64::min);
    let evident = best < (1.0 - LAG_EVIDENCE) * at_zero;
    if !evident {
        return 0;
    }
    fits.iter()
        .find(|f| f.1 <= best * (1.0 + LAG_TOLERANCE))
        .map_or(0, |f| f.0)
}

/// A fitted model whose RMS error over the rows it was fitted to exceeds this (% of span) is
/// refused: it does not describe the data.
pub const MAX_FIT_RMS_PCT: f64 = 10.0;

/// Fewest samples to fit on.
pub const MIN_FIT_SAMPLES: usize = 50;
/// Smallest normalised first weight a P–I model gets when its inverse would otherwise not
/// fit the fixed-point formats (the inverse's `Σ|w'| ≈ 2/w_1` must stay below 64).
pub const MIN_NORM_FIRST_WEIGHT: f64 = 1.0 / 24.0;

/// Largest normalised distance to the anhysteretic curve a Duhem model may reach on the
/// fitted data (the fixed-point model saturates it at 2).
pub const DUHEM_MAX_NORM_DISTANCE: f64 = 1.0;

/// Largest normalised Bouc–Wen slope (`k` or `|A|`) an identified model is given: a margin
/// below the fixed point's 1.99 (the model's output range is widened where it needs).
pub const BOUC_WEN_MAX_NORM_SLOPE: f64 = 1.8;

/// Which hysteresis model to fit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelKind {
    /// Prandtl–Ishlinskii.
    Pi,
    /// Duhem.
    Duhem,
    /// Generalised (asymmetric) P–I: a P–I followed by a dead-zone map.
    Gpi,
    /// Generalised (asymmetric) Bouc–Wen (`--model bouc-wen`).
    BoucWen,
}

impl ModelKind {
    /// Every kind, in the order `--model auto` tries them and error messages list them.
    pub const ALL: [ModelKind; 4] = [
        ModelKind::Pi,
        ModelKind::Duhem,
        ModelKind::Gpi,
        ModelKind::BoucWen,
    ];

    /// The kind's name on the command line, in parameter files' reports and in Python:
    /// `pi`, `duhem`, `gpi`, `bouc-wen`.
    pub fn name(self) -> &'static str {
        match self {
            ModelKind::Pi => "pi",
            ModelKind::Duhem => "duhem",
            ModelKind::Gpi => "gpi",
            ModelKind::BoucWen => "bouc-wen",
        }
    }

    /// The model this one generalises, if any (Duhem is Bouc–Wen with `γ = ψ = 0`): `--model
    /// auto` prefers it when it predicts as well (see [`auto::PARSIMONY_MARGIN`]).
    pub fn special_case(self) -> Option<ModelKind> {
        match self {
            ModelKind::BoucWen => Some(ModelKind::Duhem),
            ModelKind::Pi | ModelKind::Duhem | ModelKind::Gpi => None,
        }
    }
}

/// The rows a fit uses: row `k` pairs the drive history up to sample `k` with the reading at
/// sample `k + lag`.
#[derive(Clone, Debug, PartialEq)]
pub struct FitRows {
    /// Sample indices of the rows, increasing.
    pub index: Vec<usize>,
    /// Sensor lag, samples.
    pub lag: usize,
}

impl FitRows {
    /// The rows from sample `first` on (where the refinements judge a trial: after the drive
    /// has seen both extremes).
    pub fn from_sample(&self, first: usize) -> FitRows {
        FitRows {
            index: self.index.iter().copied().filter(|&k| k >= first).collect(),
            lag: self.lag,
        }
    }

    /// Mean of the targets `y[k + lag]`.
    pub fn mean_target(&self, y: &[f64]) -> f64 {
        let n = self.index.len().max(1) as f64;
        self.index.iter().map(|&k| y[k + self.lag]).sum::<f64>() / n
    }

    /// Span (max − min) of the targets.
    pub fn target_span(&self, y: &[f64]) -> f64 {
        let (lo, hi) = self
            .index
            .iter()
            .map(|&k| y[k + self.lag])
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
                (l.min(v), h.max(v))
            });
        hi - lo
    }
}

/// The play operators of a P–I (and of a generalised P–I's P–I part) when the user does not
/// say: 17, uniform thresholds (the textbook fit the project measures itself against uses as
/// many).
pub const DEFAULT_OPERATORS: usize = 17;

/// Settings of one identification (the CLI's flags).
#[derive(Clone, Debug, PartialEq)]
pub struct IdentifyOptions {
    /// Model to fit.
    pub model: ModelKind,
    /// Samples with `t <` this (seconds) are fitted, the rest scored.
    pub fit_until_s: f64,
    /// Play operators of a P–I model (also used for the lag estimate).
    pub operators: usize,
    /// Modes of the creep operator, when `creep` (1 to the library's maximum).
    pub creep_modes: usize,
    /// Threshold spread of a P–I model.
    pub thresholds: ThresholdSpread,
    /// Sensor lag in samples; `None` to estimate it (in half samples).
    /// [`IdentifyOptions::given_lag`] sets it with [`IdentifyOptions::half_lag`] from a whole or half number.
    pub lag: Option<usize>,
    /// With a given `lag`: half a sample more (the reading of a held drive's end is half a
    /// sample past the middle of its hold, the instant the model's output belongs to).
    pub half_lag: bool,
    /// Largest lag tried when estimating, samples.
    pub max_lag: usize,
    /// Refine a Duhem or generalised P–I fit on its simulated error.
    pub refine: bool,
    /// Fit a creep operator in series with the model ([`creep`]), alternating with the
    /// hysteresis fit.
    pub creep: bool,
    /// Fit a static output map after a Bouc–Wen model ([`output_map`]), kept where it lowers
    /// the fit error. Refused for the other models, as the board refuses a map with them: the
    /// generalised P–I has its own map, a P–I with a map is the generalised P–I, and the
    /// board's Duhem takes none.
    pub output_map: bool,
    /// The parameter file runs the model as the board's observer too (its estimate of the
    /// displacement, and the reference of the sensor's drift check), as well as the
    /// compensator. `false`: the compensator only, and the observer's cost off the tick (with
    /// a sensor, the feedback runs on the sensor; the estimate and the drift check are gone).
    pub observer: bool,
}

impl IdentifyOptions {
    /// The defaults for `model` fitted on `t < fit_until_s`: 17 uniform operators, lag
    /// estimated over 0…10 samples, Duhem refined.
    pub fn new(model: ModelKind, fit_until_s: f64) -> Self {
        Self {
            model,
            fit_until_s,
            operators: DEFAULT_OPERATORS,
            creep_modes: creep::MODES,
            thresholds: ThresholdSpread::Uniform,
            lag: None,
            half_lag: false,
            max_lag: 10,
            refine: true,
            creep: false,
            output_map: false,
            observer: true,
        }
    }

    /// Gives the sensor lag as `samples`, a whole or a half number of samples from 0 to
    /// [`MAX_GIVEN_LAG`] (a half: the reading of a held drive's end, half a sample past the
    /// middle of its hold): sets [`IdentifyOptions::lag`] and [`IdentifyOptions::half_lag`].
    /// Anything else is refused, naming it.
    ///
    /// ```
    /// use twinstack_identify::identification::{IdentifyOptions, ModelKind};
    /// let mut o = IdentifyOptions::new(ModelKind::Pi, 1.0);
    /// o.given_lag(1.5).unwrap();
    /// assert_eq!((o.lag, o.half_lag), (Some(1), true));
    /// assert!(o.given_lag(0.3).is_err() && o.given_lag(f64::NAN).is_err());
    /// ```
    pub fn given_lag(&mut self, samples: f64) -> Result<(), String> {
        let halves = half_samples(samples)?;
        self.lag = Some(halves / 2);
        self.half_lag = halves % 2 == 1;
        Ok(())
    }
}

impl IdentifyOptions {
    /// The model these options fit, in words (the ranking's and the report's label).
    pub fn model_label(&self) -> String {
        let model = match self.model {
            ModelKind::Pi => format!(
                "P-I ({} {} operators)",
                self.operators,
                format!("{:?}", self.thresholds).to_lowercase()
            ),
            ModelKind::Duhem => "Duhem".into(),
            ModelKind::Gpi => format!(
                "generalised P-I ({} {} operators, {} dead zones)",
                self.operators,
                format!("{:?}", self.thresholds).to_lowercase(),
                2 * gpi::DEAD_ZONES_PER_SIDE
            ),
            ModelKind::BoucWen => "Bouc-Wen".into(),
        };
        let model = if self.output_map {
            format!("{model} + output map")
        } else {
            model
        };
        match (self.creep, self.creep_modes) {
            (false, _) => model,
            (true, creep::MODES) => format!("{model} + creep"),
            (true, 1) => format!("{model} + creep (1 mode)"),
            (true, n) => format!("{model} + creep ({n} modes)"),
        }
    }

    /// The model a fit with these options gave, in words: [`Self::model_label`], but saying
    /// what creep and output map the fit kept (each is kept only where it lowers the fit
    /// error, a creep's unweighted modes dropped), never "+ creep" or "+ output map" for a
    /// model that kept none.
    pub fn label_of_fit(&self, model: &StageModel) -> String {
        if self.output_map && model.output_map.is_none() {
            let without = IdentifyOptions {
                output_map: false,
                ..self.clone()
            };
            return format!(
                "{} (output map asked for, none kept)",
                without.label_of_fit(model)
            );
        }
        match (self.creep, &model.creep) {
            (true, None) => format!(
                "{} (creep asked for, none kept)",
                IdentifyOptions {
                    creep: false,
                    ..self.clone()
                }
                .model_label()
            ),
            (_, Some(c)) => IdentifyOptions {
                creep: true,
                creep_modes: c.weights.len(),
                ..self.clone()
            }
            .model_label(),
            (false, None) => self.model_label(),
        }
    }

    /// `--model auto`'s candidates: every model kind, each without and with creep (only with
    /// creep when these options ask for it), and the Bouc–Wen with an output map besides,
    /// with these options otherwise. (The Bouc–Wen with a map is fitted from the Bouc–Wen
    /// without one.) When these options ask for an output map, only the models that take one,
    /// each with it (the Bouc–Wen, with and without creep).
    ///
    /// ```
    /// use twinstack_identify::identification::{IdentifyOptions, ModelKind};
    /// let o = IdentifyOptions::new(ModelKind::Pi, 1.0);
    /// let all = o.candidates();
    /// assert_eq!(all.len(), 10);
    /// assert_eq!(all.iter().filter(|c| c.output_map).count(), 2);
    /// let mapped = IdentifyOptions { output_map: true, ..o }.candidates();
    /// assert!(mapped.iter().all(|c| c.output_map && c.model == ModelKind::BoucWen));
    /// assert_eq!(mapped.len(), 2);
    /// ```
    pub fn candidates(&self) -> Vec<IdentifyOptions> {
        let creep: &[bool] = if self.creep { &[true] } else { &[false, true] };
        ModelKind::ALL
            .iter()
            .flat_map(|&model| {
                let maps: &[bool] = match (self.output_map, model) {
                    (true, m) if Self::takes_output_map(m) => &[true],
                    (true, _) => &[],
                    (false, m) if Self::takes_output_map(m) => &[false, true],
                    (false, _) => &[false],
                };
                maps.iter().flat_map(move |&output_map| {
                    creep.iter().map(move |&creep| IdentifyOptions {
                        model,
                        creep,
                        output_map,
                        ..self.clone()
                    })
                })
            })
            .collect()
    }

    /// Whether `model` takes an output map ([`IdentifyOptions::output_map`]): the Bouc–Wen,
    /// the one model the board runs with a map
    /// (`twinstack::models::bouc_wen::BoucWen::with_output_map`).
    pub fn takes_output_map(model: ModelKind) -> bool {
        model == ModelKind::BoucWen
    }
}

/// The result of an identification.
#[derive(Clone, Debug)]
pub struct Identification {
    /// The model, ready for the board.
    pub model: StageModel,
    /// Where motion starts in the record.
    pub motion: motion::MotionStart,
    /// First held-out sample (samples before it were available to the fit).
    pub held_out_from: usize,
    /// Sensor lag, samples of this record (a whole or a half number).
    pub lag_samples: f64,
    /// Whether the lag was estimated (rather than given).
    pub lag_estimated: bool,
    /// Rows fitted (after outliers were dropped).
    pub fitted_rows: usize,
    /// Rows dropped as outliers.
    pub outliers: usize,
    /// What the fit had to do, for the user (constraints, refinements).
    pub notes: Vec<String>,
}

/// Why identification failed.
#[derive(Debug, thiserror::Error)]
pub enum IdentifyError {
    /// The record was read without the `u` or `x` column.
    #[error("{0}: identification needs the columns t, u and x")]
    MissingColumns(String),
    /// Too few samples before `--fit-until`.
    #[error("only {found} samples before t = {fit_until_s} s, at least {needed} needed to fit")]
    TooFewFitSamples {
        /// The split time.
        fit_until_s: f64,
        /// Samples found.
        found: usize,
        /// Samples needed.
        needed: usize,
    },
    /// Too few samples after `--fit-until`.
    #[error(
        "only {found} samples at or after t = {fit_until_s} s, at least {needed} needed to score"
    )]
    NothingToScore {
        /// The split time.
        fit_until_s: f64,
        /// Samples found.
        found: usize,
        /// Samples needed.
        needed: usize,
    },
    /// The drive never moves before `--fit-until`.
    #[error("the drive u does not move before t = {0} s: nothing to identify")]
    NoMotion(f64),
    /// The reading never moves over the fitted part.
    #[error(
        "the reading x does not move from t = {0} s to the end of the fit: nothing to identify"
    )]
    OutputFlat(f64),
    /// A column spans more than the models compute in (`MAX_SPAN`).
    #[error("the {column} column spans {span:e} over the fitted part, more than the {max:e} the models compute in: are its units right?", max = MAX_SPAN)]
    SpanTooWide {
        /// `u` or `x`.
        column: &'static str,
        /// Its span (max − min).
        span: f64,
    },
    /// The given lag leaves too few rows.
    #[error("lag of {lag} samples leaves too few samples to fit")]
    LagTooLong {
        /// The lag, samples.
        lag: usize,
    },
    /// `--operators` out of range.
    #[error("--operators {0}: must be 1 to {max}", max = twinstack::MAX_OPERATORS)]
    BadOperatorCount(usize),
    /// Creep modes out of range.
    #[error("{0} creep modes: must be 1 to {max}", max = twinstack::models::creep::MAX_CREEP_MODES)]
    BadCreepModes(usize),
    /// The least-squares problem failed.
    #[error("fit failed: {0}")]
    Fit(#[from] LeastSquaresError),
    /// The fitted model does not describe the data it was fitted to.
    #[error("{model} does not fit this record: RMS error {rms_pct:.1} % of span over the fitted part (more than {MAX_FIT_RMS_PCT} %); try another model")]
    DoesNotFit {
        /// The model tried.
        model: String,
        /// Its RMS error over the fitted rows, % of span.
        rms_pct: f64,
    },
    /// An output map was asked for a model that takes none.
    #[error("an output map is fitted after a Bouc-Wen model only, the one the board runs with a map, not after {0} (the generalised P-I has its own map, and a P-I with a map is the generalised P-I)")]
    NoOutputMapFor(String),
    /// `--model auto` was given no candidate to try.
    #[error("no candidate model to try")]
    NoCandidates,
    /// `--model auto` fitted candidates, but the caller admitted none of them (for
    /// `calibrate`: none runs within the board's tick budget at its control rate).
    #[error("no candidate model can be used: {0}")]
    NoneAdmitted(String),
    /// The fitted model is refused by the library.
    #[error("the fitted model cannot run on the board: {0}")]
    Params(ParamError),
}

/// Most alternations of the creep fit with the hysteresis fit.
pub const CREEP_ITERATIONS: usize = 40;
/// The alternation has settled once an iterate's fit RMS changes by less than this fraction
/// of the previous one's without making progress ([`CREEP_PROGRESS`]).
pub const CREEP_CONVERGED: f64 = 0.01;
/// An iterate of the alternation makes progress when it lowers the lowest fit RMS of the
/// iterates before it by at least this fraction of it: a slow descent is not a plateau.
pub const CREEP_PROGRESS: f64 = 0.001;

fn min_max(v: impl Iterator<Item = f64>) -> (f64, f64) {
    v.fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), x| {
        (l.min(x), h.max(x))
    })
}

fn rms(v: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = v.fold((0.0, 0usize), |(s, n), e| (s + e * e, n + 1));
    if n == 0 {
        f64::INFINITY
    } else {
        (s / n as f64).sqrt()
    }
}

/// Identifies a model of `data` with `options`.
pub fn identify(
    data: &MeasuredData,
    options: &IdentifyOptions,
) -> Result<Identification, IdentifyError> {
    identify_from(data, options, None)
}

/// [`identify`], the hysteresis model taken from `fitted` rather than fitted again where it
/// is given: `fitted` must be [`identify`]'s result on the same `data` with the same
/// `options` but without creep or output map (what `--model auto` has fitted already, its
/// map and creep fitted after it). Every later fit of the creep's alternation fits the model
/// afresh.
fn identify_from(
    data: &MeasuredData,
    options: &IdentifyOptions,
    fitted: Option<&Identification>,
) -> Result<Identification, IdentifyError> {
    let name = data.path.display().to_string();
    let (u, x) = match (&data.u, &data.x) {
        (Some(u), Some(x)) => (u.as_slice(), x.as_slice()),
        _ => return Err(IdentifyError::MissingColumns(name)),
    };
    if options.operators == 0 || options.operators > twinstack::MAX_OPERATORS {
        return Err(IdentifyError::BadOperatorCount(options.operators));
    }
    if options.creep
        && (options.creep_modes == 0
            || options.creep_modes > twinstack::models::creep::MAX_CREEP_MODES)
    {
        return Err(IdentifyError::BadCreepModes(options.creep_modes));
    }
    if options.output_map && !IdentifyOptions::takes_output_map(options.model) {
        return Err(IdentifyError::NoOutputMapFor(
            IdentifyOptions {
                output_map: false,
                creep: false,
                ..options.clone()
            }
            .model_label(),
        ));
    }
    let fit_until_s = options.fit_until_s;
    let n_fit = data.t.iter().take_while(|&&t| t < fit_until_s).count();
    if n_fit < MIN_FIT_SAMPLES {
        return Err(IdentifyError::TooFewFitSamples {
            fit_until_s,
            found: n_fit,
            needed: MIN_FIT_SAMPLES,
        });
    }
    if data.len() - n_fit < twinstack_link::measured_data::MIN_SAMPLES {
        return Err(IdentifyError::NothingToScore {
            fit_until_s,
            found: data.len() - n_fit,
            needed: twinstack_link::measured_data::MIN_SAMPLES,
        });
    }
    let u_fit = &u[..n_fit];
    let motion = motion::find(u_fit).ok_or(IdentifyError::NoMotion(fit_until_s))?;
    let first = motion.first_fitted;
    for (column, values) in [("u", &u[first..n_fit]), ("x", &x[first..n_fit])] {
        let (lo, hi) = min_max(values.iter().copied());
        let span = hi - lo;
        if span.is_nan() || span > MAX_SPAN {
            return Err(IdentifyError::SpanTooWide { column, span });
        }
        if column == "x" && span == 0.0 {
            return Err(IdentifyError::OutputFlat(data.t[first]));
        }
    }
    let mut notes = Vec::new();
    if motion.stepped {
        notes.push(format!(
            "the drive steps at t = {:.4} s (start-up glitch): fitting from t = {:.4} s",
            data.t[motion.first_moving], data.t[first]
        ));
    }

    // Sign: slope of the reading against the drive over the moving part.
    let n_rows = (n_fit - first) as f64;
    let (mu, mx) = (first..n_fit).fold((0.0, 0.0), |(a, b), k| {
        (a + u[k] / n_rows, b + x[k] / n_rows)
    });
    let cov: f64 = (first..n_fit).map(|k| (u[k] - mu) * (x[k] - mx)).sum();
    let output_sign = if cov < 0.0 { -1.0 } else { 1.0 };
    if output_sign < 0.0 {
        notes.push("the reading falls as the drive rises: output_sign = -1".into());
    }
    let y_readings: Vec<f64> = x[..n_fit].iter().map(|v| output_sign * v).collect();
    // The targets at a half lag: the value between each reading and the next (the middle of
    // a held drive's hold, half a sample before the reading of its end).
    let y_between = between_samples(&y_readings);
    // Lag `h` half samples: the targets and the whole samples they are taken ahead.
    let targets = |h: usize| -> (&[f64], usize) {
        if h % 2 == 1 {
            (&y_between, h / 2)
        } else {
            (&y_readings, h / 2)
        }
    };

    let (u_lo, u_hi) = min_max(u_fit.iter().copied());
    let margin = INPUT_MARGIN * (u_hi - u_lo);
    let (in_lo, in_hi) = (u_lo - margin, u_hi + margin);
    let u_mid = 0.5 * (in_lo + in_hi);

    // P–I regressors (also the lag estimate's and the outlier test's).
    let (m_lo, m_hi) = min_max(u[first..n_fit].iter().copied());
    let amplitude = 0.5 * (m_hi - m_lo);
    let thresholds = options
        .thresholds
        .generator()
        .generate(options.operators, amplitude)
        .map_err(IdentifyError::Params)?;
    let columns = pi::operator_outputs(u_fit, &thresholds, u_mid, (in_lo, in_hi));
    // A half lag also needs the reading after: one row fewer.
    let rows_for = |h: usize| FitRows {
        index: (first..n_fit.saturating_sub(h / 2 + h % 2)).collect(),
        lag: h / 2,
    };
    // A lag's P–I residual RMS, against the readings themselves: at a half lag the model
    // gives a reading as the outputs around it interpolated there (as `predict` does), so
    // that the readings' noise, smoothed by the interpolation, does not pass for a better fit.
    let pi_rms = |h: usize, rows: &FitRows| -> Result<f64, IdentifyError> {
        let (y, lag) = targets(h);
        let f = pi::fit(&columns, &thresholds, u_mid, y, rows, 0.0)?;
        let residuals: Vec<f64> = if h % 2 == 1 {
            // Reading `k + lag + 1` lies between the outputs of drives `k` and `k + 1`.
            rows.index
                .windows(4)
                .filter(|w| w[3] == w[0] + 3)
                .map(|w| {
                    let output = |k: usize| y[k + lag] - f.residuals[k];
                    let between = between(output(w[0]), output(w[1]), output(w[2]), output(w[3]));
                    y_readings[w[2] + lag] - between
                })
                .collect()
        } else {
            rows.index.iter().map(|&k| f.residuals[k]).collect()
        };
        // Screened as the outliers will be: a start-up transient's few large residuals
        // would otherwise drown the difference a lag makes.
        let all = rms(residuals.iter().copied());
        Ok(rms(residuals
            .into_iter()
            .filter(|r| r.abs() <= OUTLIER_FACTOR * all)))
    };

    let (half_lag, lag_estimated) = match options.lag {
        Some(l) => (2 * l + usize::from(options.half_lag), false),
        None => {
            let mut fits = Vec::new();
            for h in 0..=2 * options.max_lag {
                let rows = rows_for(h);
                if rows.index.len() < MIN_FIT_SAMPLES {
                    break;
                }
                fits.push((h, pi_rms(h, &rows)?));
            }
            (supported_lag(&fits), true)
        }
    };
    let (y, lag) = targets(half_lag);
    let y = y.to_vec();
    let mut rows = rows_for(half_lag);
    if rows.index.len() < MIN_FIT_SAMPLES {
        return Err(IdentifyError::LagTooLong { lag });
    }

    // Outliers, judged on the P–I residual.
    let screen = pi::fit(&columns, &thresholds, u_mid, &y, &rows, 0.0)?;
    let limit = OUTLIER_FACTOR * rms(rows.index.iter().map(|&k| screen.residuals[k]));
    let before = rows.index.len();
    rows.index.retain(|&k| screen.residuals[k].abs() <= limit);
    let outliers = before - rows.index.len();

    let sample_period = data.sample_period();
    let lag_samples = 0.5 * half_lag as f64;
    let sensor_lag_s = lag_samples * sample_period;
    let with_output_range = |hysteresis: Hysteresis, model_output: &[f64], min_half_span: f64| {
        let (lo, hi) = min_max(model_output.iter().copied().filter(|v| v.is_finite()));
        let half = (0.5 + OUTPUT_MARGIN) * (hi - lo);
        let half = half.max(min_half_span);
        let mid = 0.5 * (lo + hi);
        let scaling = Scaling::new(in_lo, in_hi, mid - half, mid + half)
            .map_err(|e| IdentifyError::Params(e.into()))?;
        Ok::<_, IdentifyError>(StageModel {
            hysteresis,
            scaling,
            output_sign,
            sensor_lag_s,
            creep: None,
            output_map: None,
        })
    };

    // The hysteresis model fitted to the (sign-corrected) target `y`.
    let fit_model = |y: &[f64], notes: &mut Vec<String>| -> Result<StageModel, IdentifyError> {
        Ok(match options.model {
            ModelKind::Pi => {
                let fit_pi = |min_first: f64| -> Result<StageModel, IdentifyError> {
                    let f = pi::fit(&columns, &thresholds, u_mid, y, &rows, min_first)?;
                    let output: Vec<f64> = (0..n_fit - lag)
                        .map(|k| y[k + lag] - f.residuals[k])
                        .collect();
                    with_output_range(Hysteresis::Pi(f.params), &output, 0.0)
                };
                with_first_weight_floor(fit_pi(0.0)?, notes, |floor, _| fit_pi(floor))?
            }
            ModelKind::Duhem => {
                let (y_lo, y_hi) = min_max(y.iter().copied());
                let provisional = Scaling::new(in_lo, in_hi, y_lo, y_hi.max(y_lo + 1e-9))
                    .map_err(|e| IdentifyError::Params(e.into()))?;
                let steady_from = motion::both_extremes_reached(&u_fit[first..]) + first;
                let f = duhem::fit(u_fit, y, &rows, &provisional, options.refine, steady_from)?;
                let span = rows.target_span(y);
                notes.push(format!(
                    "Duhem integrated least squares: simulated RMS {:.3} % of span{}",
                    100.0 * f.least_squares_rms / span,
                    match f.path {
                        duhem::DuhemFitPath::Plain => String::new(),
                        duhem::DuhemFitPath::ConstrainedNotPositive =>
                            " (plain fit had a non-positive coefficient: refitted on the simulated error)".into(),
                        duhem::DuhemFitPath::ConstrainedDiverged =>
                            " (plain fit missed the data by more than a tenth of their span when simulated: refitted on the simulated error)".into(),
                    }
                ));
                if f.params != f.least_squares {
                    notes.push(format!(
                        "Duhem refined on the simulated error from t = {:.4} s (drive has seen both extremes): RMS {:.3} % of span over the fit",
                        data.t[steady_from.min(n_fit - 1)],
                        100.0 * f.rms / span
                    ));
                }
                // The fixed-point Duhem saturates the distance to the anhysteretic curve,
                // e = βu + δ − y, at ±2 normalised: widen the output range until |e| stays
                // within DUHEM_MAX_NORM_DISTANCE of it on the data.
                let p = f.params;
                let max_distance = u_fit
                    .iter()
                    .zip(&f.simulated)
                    .map(|(&u, &y)| (p.beta * u + p.offset - y).abs())
                    .fold(0.0, f64::max);
                let needed = max_distance / DUHEM_MAX_NORM_DISTANCE;
                let model = with_output_range(Hysteresis::Duhem(p), &f.simulated, needed)?;
                let (lo, hi) = min_max(f.simulated.iter().copied());
                if needed > (0.5 + OUTPUT_MARGIN) * (hi - lo) {
                    notes.push(format!(
                        "output range widened to +/-{:.4} around the model's centre so that the distance to the anhysteretic curve fits the fixed point",
                        needed
                    ));
                }
                model
            }
            ModelKind::Gpi => gpi_model(
                &columns,
                &thresholds,
                u_mid,
                y,
                &rows,
                options.refine,
                notes,
                with_output_range,
            )?,
            ModelKind::BoucWen => {
                let (y_lo, y_hi) = min_max(y.iter().copied());
                let provisional = Scaling::new(in_lo, in_hi, y_lo, y_hi.max(y_lo + 1e-9))
                    .map_err(|e| IdentifyError::Params(e.into()))?;
                let steady_from = motion::both_extremes_reached(&u_fit[first..]) + first;
                let f = bouc_wen::fit(u_fit, y, &rows, &provisional, options.refine, steady_from)?;
                let span = rows.target_span(y);
                notes.push(format!(
                    "Bouc-Wen started from the Duhem fit (gamma = psi = chi = 0): RMS {:.3} % of span from t = {:.4} s{}",
                    100.0 * f.start_rms / span,
                    data.t[steady_from.min(n_fit - 1)],
                    if f.start_scaled {
                        " (A scaled down: the hysteretic slope was too steep for a monotone model)"
                    } else {
                        ""
                    }
                ));
                if f.refined {
                    notes.push(format!(
                        "Bouc-Wen refined on the simulated error: RMS {:.3} % of span (gamma = {:.4e}, psi = {:.4e}, chi = {:.4e})",
                        100.0 * f.rms / span,
                        f.params.gamma,
                        f.params.psi,
                        f.params.chi
                    ));
                } else {
                    notes.push(
                        "Bouc-Wen refinement did not improve on the Duhem start: kept it".into(),
                    );
                }
                // The fixed-point state is Q2.30: widen the output range until the state bound
                // |A|·max(1/c_min, 2U) is within DUHEM_MAX_NORM_DISTANCE of it, and
                // the slopes k and A, normalised, within BOUC_WEN_MAX_NORM_SLOPE.
                let p = f.params;
                let needed = bouc_wen_half_span(&p, provisional.input_half_span());
                let model = with_output_range(Hysteresis::BoucWen(p), &f.simulated, needed)?;
                let (lo, hi) = min_max(f.simulated.iter().copied());
                if needed > (0.5 + OUTPUT_MARGIN) * (hi - lo) {
                    notes.push(format!(
                        "output range widened to +/-{needed:.4} around the model's centre so that the hysteretic state fits the fixed point"
                    ));
                }
                model
            }
        })
    };
    // With an output map, the map after every fit of the model (the creep's alternation
    // refits both: the creep runs after the map).
    let steady_from = motion::both_extremes_reached(&u_fit[first..]) + first;
    let record = output_map::Record {
        t: &data.t[..n_fit],
        u: u_fit,
        rows: &rows,
        steady_from,
        refine: options.refine,
    };
    // A Bouc–Wen refined with its map is where the alternation's next fit starts: refined
    // with the map again on the target with the creep undone, rather than fitted afresh from
    // the Duhem starts (each of which lands elsewhere, and costs a fit and a refinement).
    let last_mapped: RefCell<Option<StageModel>> = RefCell::new(None);
    let fit_mapped = |y: &[f64], notes: &mut Vec<String>| -> Result<StageModel, IdentifyError> {
        if !options.output_map {
            return fit_model(y, notes);
        }
        let warm = last_mapped
            .borrow()
            .clone()
            .filter(|m| matches!(m.hysteresis, Hysteresis::BoucWen(_)) && m.output_map.is_some());
        let model = match warm {
            Some(m) => StageModel {
                output_map: None,
                ..m
            },
            None => fit_model(y, notes)?,
        };
        let mapped = output_map::with_map(model, &record, y, notes)?;
        *last_mapped.borrow_mut() = Some(mapped.clone());
        Ok(mapped)
    };
    let mut model = match fitted {
        Some(id) => {
            // Its notes of the model's fit (those of the record, made again above, once).
            for n in &id.notes {
                if !notes.contains(n) {
                    notes.push(n.clone());
                }
            }
            let model = id.model.clone();
            if options.output_map {
                let mapped = output_map::with_map(model, &record, &y, &mut notes)?;
                *last_mapped.borrow_mut() = Some(mapped.clone());
                mapped
            } else {
                model
            }
        }
        None => fit_mapped(&y, &mut notes)?,
    };
    if options.creep {
        model = alternation::with_creep(
            model,
            data,
            &y,
            &rows,
            n_fit,
            motion.started_at_rest,
            options.creep_modes,
            &fit_mapped,
            &mut notes,
        )?;
    }
    model.check().map_err(IdentifyError::Params)?;
    // A model the library accepts can still be useless (a fit that ran off on data its
    // family cannot describe): judge it, run as `predict` runs it, on the rows it was fitted to.
    let predicted = model
        .predict(&data.t[..n_fit], u_fit)
        .map_err(IdentifyError::Params)?;
    let fitted = score::score(&x[..n_fit], &predicted, first..n_fit);
    if let Some(f) = fitted.filter(|f| f.rms_pct.is_nan() || f.rms_pct > MAX_FIT_RMS_PCT) {
        return Err(IdentifyError::DoesNotFit {
            model: options.model_label(),
            rms_pct: f.rms_pct,
        });
    }
    Ok(Identification {
        model,
        motion,
        held_out_from: n_fit,
        lag_samples,
        lag_estimated,
        fitted_rows: rows.index.len(),
        outliers,
        notes,
    })
}

/// The half span of output range a Bouc–Wen model `p` on an input range of half span
/// `input_half` needs in the fixed point: its hysteretic state's bound `|A|·max(1/c_min, 2U)`
/// within [`DUHEM_MAX_NORM_DISTANCE`] of it, and its slopes `k` and `A`, normalised, within
/// [`BOUC_WEN_MAX_NORM_SLOPE`].
fn bouc_wen_half_span(p: &twinstack::BoucWenParams, input_half: f64) -> f64 {
    let bound = p.a.abs() * (1.0 / p.min_factor()).max(2.0 * input_half);
    (bound / DUHEM_MAX_NORM_DISTANCE).max(p.k.max(p.a.abs()) * input_half / BOUC_WEN_MAX_NORM_SLOPE)
}

/// The generalised P–I branch of [`identify`]: the fit ([`gpi::fit`]) on the P–I's rows, its
/// output range wide enough for both the model's output and its P–I part's (the inverse P–I
/// clamps its input to the range), refitted with `w_1` floored when the inverse P–I would not
/// fit the fixed point, as for the P–I.
#[allow(clippy::too_many_arguments)]
fn gpi_model(
    columns: &[Vec<f64>],
    thresholds: &[f64],
    u_mid: f64,
    y: &[f64],
    rows: &FitRows,
    refine: bool,
    notes: &mut Vec<String>,
    with_output_range: impl Fn(Hysteresis, &[f64], f64) -> Result<StageModel, IdentifyError>,
) -> Result<StageModel, IdentifyError> {
    let span = rows.target_span(y);
    let fit_gpi = |min_first: f64, notes: &mut Vec<String>| {
        let f = gpi::fit(columns, thresholds, u_mid, y, rows, min_first, refine)?;
        if f.dropped > 0 {
            notes.push(format!(
                "{} dead zone(s) dropped: they made the inverse map fall",
                f.dropped
            ));
        }
        notes.push(format!(
            "generalised P–I equation-error fit: simulated RMS {:.3} % of span over the fit{}",
            100.0 * f.least_squares_rms / span,
            if f.refined {
                format!(
                    "; refined on the simulated error: {:.3} %",
                    100.0 * f.rms / span
                )
            } else {
                String::new()
            }
        ));
        let both: Vec<f64> = f.pi_output.iter().chain(&f.output).copied().collect();
        with_output_range(Hysteresis::GeneralisedPi(f.params), &both, 0.0)
    };
    let model = fit_gpi(0.0, notes)?;
    with_first_weight_floor(model, notes, fit_gpi)
}

/// A P–I-based `model` as it is if the library builds its inverse, or — where the inverse P–I
/// is refused for its first weight (`w_1 = 0`, or inverse weights beyond Q8.24) — `refit` with
/// `w_1` floored at [`MIN_NORM_FIRST_WEIGHT`] (normalised), which the notes say.
fn with_first_weight_floor(
    model: StageModel,
    notes: &mut Vec<String>,
    refit: impl FnOnce(f64, &mut Vec<String>) -> Result<StageModel, IdentifyError>,
) -> Result<StageModel, IdentifyError> {
    match model.check() {
        Ok(()) => Ok(model),
        Err(
            e @ (ParamError::WeightOutOfRange { .. }
            | ParamError::GainSumTooLarge
            | ParamError::FirstWeightNotPositive),
        ) => {
            let floor = MIN_NORM_FIRST_WEIGHT / model.scaling.gain_to_norm();
            notes.push(format!(
                "the inverse could not be built ({e}): refitted with w_1 >= {floor:.4e}"
            ));
            refit(floor, notes)
        }
        Err(e) => Err(IdentifyError::Params(e)),
    }
}

#[cfg(test)]
mod tests;
