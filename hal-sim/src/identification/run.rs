//! `identify`'s whole job short of printing and drawing, shared by `hal-sim identify` and the
//! Python package's `twinstack.identify`: fit the model asked for (or rank every model, `auto`),
//! score it on the fitted and the held-out part, in fixed point and against the `f64`
//! reference, and put it in a parameter file with that record.

use super::auto::{identify_auto_admitting, AutoIdentification};
use super::score::{score, ErrorFigures};
use super::{identify, Identification, IdentifyError, IdentifyOptions, ModelKind};
use crate::measured_data::MeasuredData;
use crate::param_file::{IdentificationRecord, ParamFile};
use twinstack::board::Hardware;
use twinstack::refusal::Field;
use twinstack::settings::Settings;

/// Which model to fit: every candidate, or one.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ModelChoice {
    /// Rank every model on held-back data and keep the best.
    Auto,
    /// This model only.
    Only(ModelKind),
}

/// Parses a model choice: `auto` or a model kind's name (`pi`, `duhem`, `gpi`, `bouc-wen`),
/// in any case.
///
/// ```
/// use hal_sim::identification::run::{parse_model, ModelChoice};
/// use hal_sim::identification::ModelKind;
/// assert_eq!(parse_model("auto"), Ok(ModelChoice::Auto));
/// assert_eq!(parse_model("GPI"), Ok(ModelChoice::Only(ModelKind::Gpi)));
/// assert!(parse_model("spline").unwrap_err().contains("expected auto, pi"));
/// ```
pub fn parse_model(s: &str) -> Result<ModelChoice, String> {
    use clap::ValueEnum;
    if s.eq_ignore_ascii_case("auto") {
        return Ok(ModelChoice::Auto);
    }
    ModelKind::from_str(s, true)
        .map(ModelChoice::Only)
        .map_err(|_| {
            let names: Vec<String> = ModelKind::value_variants()
                .iter()
                .filter_map(|v| v.to_possible_value().map(|p| p.get_name().to_string()))
                .collect();
            format!("unknown model '{s}': expected auto, {}", names.join(", "))
        })
}

/// Where a record is split when the caller does not say: this fraction of its duration is
/// fitted, the rest held out to score the model.
pub const DEFAULT_FIT_FRACTION: f64 = 0.7;

/// The split time for a record with times `t` when none is given: [`DEFAULT_FIT_FRACTION`]
/// of the way from its first to its last sample.
pub fn default_fit_until(t: &[f64]) -> f64 {
    match (t.first(), t.last()) {
        (Some(a), Some(b)) => a + DEFAULT_FIT_FRACTION * (b - a),
        _ => 0.0,
    }
}

/// An identified model with its scores and its parameter file.
#[derive(Clone, Debug)]
pub struct Identified {
    /// The ranking, when `auto` picked the model.
    pub auto: Option<AutoIdentification>,
    /// The options of the model kept.
    pub options: IdentifyOptions,
    /// The fit.
    pub identification: Identification,
    /// The model's prediction over the whole record (fixed point).
    pub predicted: Vec<f64>,
    /// The inverse on the held-out part, in the `f64` reference.
    pub inverse_reference: ErrorFigures,
    /// What the parameter file records about the fit and its scores.
    pub record: IdentificationRecord,
    /// The parameter file.
    pub file: ParamFile,
}

/// Why identifying and scoring failed.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// The fit failed.
    #[error(transparent)]
    Identify(#[from] IdentifyError),
    /// The fitted model could not be run over the record.
    #[error("{0}")]
    Params(twinstack::ParamError),
    /// The measured output does not move where the model is scored.
    #[error("the measured output is flat, cannot score")]
    Flat,
}

/// `auto`'s candidates for `options`: every model kind with and without creep (`creep =
/// None`), or only with (`Some(true)`) or only without (`Some(false)`).
pub fn candidates(options: &IdentifyOptions, creep: Option<bool>) -> Vec<IdentifyOptions> {
    let base = IdentifyOptions {
        creep: creep == Some(true),
        ..options.clone()
    };
    base.candidates()
        .into_iter()
        .filter(|c| creep.is_none_or(|want| c.creep == want))
        .collect()
}

/// `Ok(())` if the driver board's tick budget runs `settings` at `rate_hz`, the test the board
/// applies when they are loaded ([`twinstack::tick_budget`]); else why not, with the cycles
/// they need and the cycles the rate leaves.
///
/// ```
/// use hal_sim::identification::run::runs_at;
/// use twinstack::settings::{representative_gpi, Settings};
/// let s = Settings { compensator: Some(representative_gpi(16).unwrap()), ..Settings::default() };
/// assert!(runs_at(&s, 50_000.0).is_ok());
/// assert!(runs_at(&s, 100_000.0).unwrap_err().contains("100 kHz"));
/// ```
pub fn runs_at(settings: &Settings, rate_hz: f64) -> Result<(), String> {
    match settings.build(&Hardware::driver_board(rate_hz)) {
        Err(r) if r.field == Field::Workload => Err(format!(
            "the board at {:.0} kHz would refuse it: {r}",
            rate_hz / 1e3
        )),
        _ => Ok(()),
    }
}

/// Fits `data` (`t`, `u`, `x`) as `choice` says, with `options` (its `model` is ignored;
/// `creep`: see [`candidates`]; for one model, `Some(true)` adds a creep operator), scores
/// the model kept and writes its parameter file with `output_unit` as the unit of `x`.
///
/// With `tick_rate_hz`, only a model the board runs at that control rate is kept
/// ([`runs_at`], with the parameter file's settings: the board's own sensor and feedback are
/// not known here, and a derivative term or a notch there costs more): `auto` picks among
/// those, and one model asked for by name that does not fit fails with
/// [`IdentifyError::NoneAdmitted`].
pub fn identify_and_score(
    data: &MeasuredData,
    choice: ModelChoice,
    options: &IdentifyOptions,
    creep: Option<bool>,
    output_unit: &str,
    tick_rate_hz: Option<f64>,
) -> Result<Identified, RunError> {
    let admit = |id: &Identification| match tick_rate_hz {
        Some(rate) => runs_at(
            &ParamFile::from_model(&id.model, output_unit, None).settings,
            rate,
        ),
        None => Ok(()),
    };
    let (auto, options, id) = match choice {
        ModelChoice::Only(kind) => {
            let o = IdentifyOptions {
                model: kind,
                creep: creep == Some(true),
                ..options.clone()
            };
            let id = identify(data, &o)?;
            admit(&id).map_err(|why| {
                IdentifyError::NoneAdmitted(format!("{}: {why}", o.model_label()))
            })?;
            (None, o, id)
        }
        ModelChoice::Auto => {
            let auto = identify_auto_admitting(data, &candidates(options, creep), admit)?;
            let kept = auto
                .ranking
                .iter()
                .find(|r| r.validation.admitted().is_some())
                .map_or_else(|| options.clone(), |r| r.options.clone());
            let id = auto.identification.clone();
            (Some(auto), kept, id)
        }
    };
    let (t, u, x) = (
        &data.t,
        data.u.as_deref().unwrap_or_default(),
        data.x.as_deref().unwrap_or_default(),
    );
    let n = t.len();
    let model = &id.model;
    let predicted = model.predict(t, u).map_err(RunError::Params)?;
    let reference = model.predict_reference(t, u).map_err(RunError::Params)?;
    let drive = model.compensate(t, x).map_err(RunError::Params)?;
    let drive_reference = model.compensate_reference(t, x).map_err(RunError::Params)?;
    let fit_from = id.motion.first_fitted;
    let held = id.held_out_from;
    let fit = score(x, &predicted, fit_from..held).ok_or(RunError::Flat)?;
    let held_out = score(x, &predicted, held..n).ok_or(RunError::Flat)?;
    // The last `lag` samples have no later reading to aim the drive at: not scored.
    let aimed = n - model.lag_samples(t).min(n - held - 1);
    let inverse = score(u, &drive, held..aimed).ok_or(RunError::Flat)?;
    let fixed_vs_reference = score(&reference, &predicted, fit_from..n).ok_or(RunError::Flat)?;
    let inverse_reference = score(u, &drive_reference, held..aimed).ok_or(RunError::Flat)?;
    let inverse_fixed_vs_reference =
        score(&drive_reference, &drive, fit_from..n).ok_or(RunError::Flat)?;
    let record = IdentificationRecord {
        data: data.path.display().to_string(),
        fit_until_s: options.fit_until_s,
        fit_from_s: t[fit_from],
        operators: options.operators,
        thresholds: format!("{:?}", options.thresholds).to_lowercase(),
        lag_samples: id.lag_samples,
        lag_estimated: id.lag_estimated,
        outliers: id.outliers,
        fit,
        held_out,
        inverse_held_out: inverse,
        fixed_vs_reference_max_pct: fixed_vs_reference.max_pct,
        inverse_fixed_vs_reference_max_pct: inverse_fixed_vs_reference.max_pct,
        notes: id.notes.clone(),
    };
    let file = ParamFile::from_model(model, output_unit, Some(record.clone()));
    Ok(Identified {
        auto,
        options,
        identification: id,
        predicted,
        inverse_reference,
        record,
        file,
    })
}
