//! `identify`'s whole job short of printing and drawing, shared by `twinstack identify` and the
//! Python package's `twinstack.identify`: fit the model asked for (or rank every model, `auto`),
//! score it on the fitted and the held-out part, in fixed point and against the `f64`
//! reference, and put it in a parameter file with that record.

use super::auto::{
    identify_admitted, identify_auto_admitting, Admission, AutoIdentification, Resize,
};
use super::coverage::fastest_motion_in;
use super::score::{score, ErrorFigures};
use super::{Identification, IdentifyError, IdentifyOptions, ModelKind};
use crate::param_file::{IdentificationRecord, ParamFile};
use twinstack::board::Hardware;
use twinstack::config::settings::{Model, Settings};
use twinstack::config::tick_budget::{self, Beside, ServicesLoad};
use twinstack::models::params::PiParams;
use twinstack::refusal::{Field, Refusal, Rule};
use twinstack_link::measured_data::MeasuredData;

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
/// use twinstack_identify::identification::run::{parse_model, ModelChoice};
/// use twinstack_identify::identification::ModelKind;
/// assert_eq!(parse_model("auto"), Ok(ModelChoice::Auto));
/// assert_eq!(parse_model("GPI"), Ok(ModelChoice::Only(ModelKind::Gpi)));
/// assert_eq!(parse_model("bouc-wen"), Ok(ModelChoice::Only(ModelKind::BoucWen)));
/// assert!(parse_model("spline").unwrap_err().contains("expected auto, pi"));
/// ```
pub fn parse_model(s: &str) -> Result<ModelChoice, String> {
    if s.eq_ignore_ascii_case("auto") {
        return Ok(ModelChoice::Auto);
    }
    ModelKind::ALL
        .into_iter()
        .find(|kind| kind.name().eq_ignore_ascii_case(s))
        .map(ModelChoice::Only)
        .ok_or_else(|| {
            let names: Vec<&str> = ModelKind::ALL.iter().map(|k| k.name()).collect();
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
    /// The fixed-point model departs from its `f64` reference by more than arithmetic does
    /// ([`FIXED_VS_REFERENCE_LIMIT_PCT`]): one of the two does not compute what the model
    /// means (a degenerate fit, such as an anhysteretic slope near zero), and the board
    /// would run the fixed-point one. Nothing is written.
    #[error(
        "the fitted model's fixed-point {what} departs from its f64 reference by {max_pct:.3} % of span (arithmetic accounts for at most {FIXED_VS_REFERENCE_LIMIT_PCT} %): the fit is degenerate for the board; try another model"
    )]
    ReferenceDisagrees {
        /// `predict` or `compensate`.
        what: &'static str,
        /// Their largest difference, % of span.
        max_pct: f64,
    },
}

/// The most the fixed-point `predict` and `compensate` may depart from their `f64` references
/// over a record, % of span: what the arithmetic accounts for is three decades below (at
/// most 3·10⁻³ % on every record and stage in the book).
pub const FIXED_VS_REFERENCE_LIMIT_PCT: f64 = 0.1;

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
/// applies when they are loaded ([`twinstack::config::tick_budget`]); else why not, with the cycles
/// they need and the cycles the rate leaves.
///
/// ```
/// use twinstack_identify::identification::run::runs_at;
/// use twinstack::config::settings::{representative_gpi, Settings};
/// let gpi = representative_gpi(32).unwrap();
/// let s = Settings {
///     compensator: Some(gpi.clone()),
///     observer: Some(gpi),
///     ..Settings::default()
/// };
/// assert!(runs_at(&s, 50_000.0).is_ok());
/// assert!(runs_at(&s, 100_000.0).unwrap_err().contains("100 kHz"));
/// ```
pub fn runs_at(settings: &Settings, rate_hz: f64) -> Result<(), String> {
    match admission_at(settings, &BoardRate::exactly(rate_hz)) {
        Admission::Admitted => Ok(()),
        Admission::Refused(why) | Admission::Smaller { why, .. } => Err(why),
    }
}

/// `Ok(())` if `hz` is a control rate the board runs at
/// ([`Hardware::MIN_CONTROL_RATE_HZ`] to [`Hardware::MAX_CONTROL_RATE_HZ`]), else why not.
///
/// ```
/// use twinstack_identify::identification::run::check_tick_rate;
/// assert!(check_tick_rate(100_000.0).is_ok());
/// assert!(check_tick_rate(1e9).unwrap_err().contains("10000 to 100000 Hz"));
/// assert!(check_tick_rate(f64::NAN).is_err());
/// ```
pub fn check_tick_rate(hz: f64) -> Result<(), String> {
    let (lo, hi) = (
        Hardware::MIN_CONTROL_RATE_HZ as f64,
        Hardware::MAX_CONTROL_RATE_HZ as f64,
    );
    if (lo..=hi).contains(&hz) {
        Ok(())
    } else {
        Err(format!(
            "{hz}: must be {lo} to {hi} Hz, the control rates the board runs at"
        ))
    }
}

/// The control rate a model must run at, and how it may be made smaller so that it does.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoardRate {
    /// The board's control rate, Hz.
    pub hz: f64,
    /// A P–I or generalised P–I too dear at this rate may be fitted with fewer play
    /// operators (`false` when the user asked for a number of operators).
    pub fewer_operators: bool,
    /// A creep operator too dear at this rate may be fitted with fewer modes (at least one).
    pub fewer_creep_modes: bool,
    /// The board captures while it runs the model (as `calibrate`'s tracking check does), at
    /// this decimation or coarser: the services' share
    /// ([`twinstack::config::tick_budget::ServicesLoad`]) is charged beside it.
    pub capturing: Option<u16>,
    /// The observer may be left out where the model with it is too dear at this rate, before
    /// the model is made smaller: the observer only gives the estimate and the drift check
    /// (the feedback acts on the sensor), so the compensator's accuracy comes first. The
    /// file says what was left out.
    pub observer_optional: bool,
    /// Cycles a tick the board spends beside the pipeline whatever is loaded (a dual-stage
    /// image's coarse task: [`twinstack::config::tick_budget::coarse_task_share`]), charged
    /// beside every model; 0 on a piezo-only board.
    pub beside: u32,
}

impl BoardRate {
    /// `hz`, the model kept as asked.
    pub fn exactly(hz: f64) -> Self {
        Self {
            hz,
            fewer_operators: false,
            fewer_creep_modes: false,
            capturing: None,
            observer_optional: false,
            beside: 0,
        }
    }

    /// `hz`, the observer left out where needed ([`BoardRate::observer_optional`]), the
    /// creep's modes fewer where needed, and the play operators fewer where needed unless the
    /// user asked for a number of them (`operators_asked`).
    pub fn sizing(hz: f64, operators_asked: bool) -> Self {
        Self {
            hz,
            fewer_operators: !operators_asked,
            fewer_creep_modes: true,
            capturing: None,
            observer_optional: true,
            beside: 0,
        }
    }

    /// The same, with a capture at `decimation` (or coarser) running beside the model
    /// ([`BoardRate::capturing`]).
    pub fn capturing(self, decimation: u16) -> Self {
        Self {
            capturing: Some(decimation),
            ..self
        }
    }

    /// The same, with `cycles` a tick of the board's own beside every model
    /// ([`BoardRate::beside`]).
    pub fn beside(self, cycles: u32) -> Self {
        Self {
            beside: cycles,
            ..self
        }
    }
}

/// Whether the driver board's tick budget runs `settings` at `rate` ([`runs_at`]); where it
/// does not, but would with a smaller creep or smaller P–I banks and `rate` allows them
/// smaller, the largest such size ([`Admission::Smaller`]): the observer goes first where
/// `rate` lets it ([`BoardRate::observer_optional`]), then the creep loses modes (down to
/// one), then the P–I banks pairs of operators. Each size is costed by the library's
/// own tick budget, on `settings` with the model cut to that size.
///
/// ```
/// use twinstack_identify::identification::auto::{Admission, Resize};
/// use twinstack_identify::identification::run::{admission_at, BoardRate};
/// use twinstack::config::settings::{representative_pi, Settings};
/// let pi17 = representative_pi(17).unwrap();
/// let s = Settings {
///     compensator: Some(pi17.clone()),
///     observer: Some(pi17),
///     ..Settings::default()
/// };
/// // With a capture beside it (as `calibrate` checks its tracking) it is too dear at
/// // 80 kHz. Its observer kept, the P–I banks lose pairs of operators, unless the user
/// // asked for 17.
/// let keeping = |rate: BoardRate| BoardRate { observer_optional: false, ..rate };
/// let sized = admission_at(&s, &keeping(BoardRate::sizing(80_000.0, false).capturing(1)));
/// assert!(matches!(
///     sized,
///     Admission::Smaller {
///         resize: Resize { operators: Some(n), creep_modes: None, without_observer: false },
///         ..
///     } if n < 17
/// ));
/// let asked = BoardRate::sizing(80_000.0, true).capturing(1);
/// assert!(matches!(admission_at(&s, &keeping(asked)), Admission::Refused(_)));
/// // As sized by default, the observer goes first, and the model keeps its 17.
/// assert!(matches!(
///     admission_at(&s, &asked),
///     Admission::Smaller {
///         resize: Resize { operators: None, creep_modes: None, without_observer: true },
///         ..
///     }
/// ));
/// assert_eq!(admission_at(&s, &BoardRate::sizing(50_000.0, false).capturing(1)), Admission::Admitted);
///
/// // Bouc–Wen with six creep modes both ways at 50 kHz, the fastest too fast for them to
/// // take turns (1 ms is 50 ticks, less than 20 updates of 6 ticks): the creep loses modes
/// // first.
/// use twinstack::models::creep::CreepParams;
/// use twinstack::config::settings::representative_bouc_wen;
/// let s = Settings {
///     compensator: Some(representative_bouc_wen()),
///     observer: Some(representative_bouc_wen()),
///     creep: Some(CreepParams::new(&[0.001, 0.003, 0.01, 0.03, 0.1, 0.3], &[0.02; 6]).unwrap()),
///     ..Settings::default()
/// };
/// let sized = admission_at(&s, &keeping(BoardRate::sizing(50_000.0, true)));
/// assert!(matches!(
///     sized,
///     Admission::Smaller { resize: Resize { operators: None, creep_modes: Some(m), .. }, .. }
///         if m < 6
/// ));
/// ```
pub fn admission_at(settings: &Settings, rate: &BoardRate) -> Admission {
    let hardware = Hardware::driver_board(rate.hz);
    // The board's refusal at load, and (capturing) at the capture's arming: the cycles it
    // names are the configuration's with the capture's beside them either way.
    let capture = ServicesLoad {
        capture_decimation: rate.capturing,
        ..ServicesLoad::default()
    };
    let judge = |s: &Settings| -> Result<(), Refusal> {
        match s.build(&hardware) {
            Err(mut r) => {
                if let Rule::TickOverrun { needs, .. } = &mut r.rule {
                    // The capture's frames beside the configuration: where its observer
                    // already has the services serving every snapshot, its frames alone.
                    *needs += if s.observer.is_some() {
                        capture.observing(1).cycles()
                            - ServicesLoad::default().observing(1).cycles()
                    } else {
                        capture.cycles()
                    };
                    *needs = needs.saturating_add(rate.beside);
                }
                Err(r)
            }
            Ok(config) => {
                let services = Beside {
                    services: capture,
                    coarse_task: rate.beside,
                    ..Beside::default()
                };
                tick_budget::check_with(&config, rate.hz, services)
            }
        }
    };
    // Only the tick budget is judged here: what else the board would refuse (a sensor it
    // lacks, …) it says at load.
    let fits = |s: &Settings| !matches!(judge(s), Err(r) if r.field == Field::Workload);
    // The board's own refusal advises on every size a parameter file can set; identification
    // sets the dead zones itself, so only what its options change is named here.
    // What the compensator alone would need, where an observer runs beside it (asked only of
    // a refused configuration).
    let alone = || {
        settings.observer.as_ref()?;
        let alone = Settings {
            observer: None,
            ..settings.clone()
        };
        match judge(&alone) {
            Ok(_) => Some("; without the observer it fits".to_string()),
            Err(Refusal {
                rule: Rule::TickOverrun { needs, .. },
                ..
            }) => Some(format!("; without the observer, {needs}")),
            Err(_) => None,
        }
    };
    let why = match judge(settings) {
        Err(r) if r.field == Field::Workload => match r.rule {
            Rule::TickOverrun { needs, available } => format!(
                "the board at {:.0} kHz would refuse it: it needs {needs} cycles per tick{}{}, \
                 more than the {available} that rate leaves{}",
                rate.hz / 1e3,
                if rate.capturing.is_some() {
                    " with a capture beside it"
                } else {
                    ""
                },
                if rate.beside > 0 {
                    format!(" and the board's own {} beside every model", rate.beside)
                } else {
                    String::new()
                },
                alone().unwrap_or_default()
            ),
            _ => format!("the board at {:.0} kHz would refuse it: {r}", rate.hz / 1e3),
        },
        _ => return Admission::Admitted,
    };
    // The observer first, where it may go: the model keeps its size.
    let without_observer = rate.observer_optional && settings.observer.is_some();
    let bare;
    let settings = if without_observer {
        bare = Settings {
            observer: None,
            ..settings.clone()
        };
        if fits(&bare) {
            return Admission::Smaller {
                resize: Resize {
                    without_observer,
                    ..Resize::default()
                },
                why,
            };
        }
        &bare
    } else {
        settings
    };
    let operators = [&settings.compensator, &settings.observer]
        .into_iter()
        .find_map(|m| pi_part(m.as_ref()?).map(|p| p.thresholds.len()))
        .unwrap_or(0);
    let modes = settings.creep.as_ref().map_or(0, |c| c.weights.len());
    let fewer_modes = rate.fewer_creep_modes && modes > 1;
    // The creep alone, as many modes as fit …
    if fewer_modes {
        if let Some(m) = (1..modes)
            .rev()
            .find(|&m| fits(&cut(settings, None, Some(m))))
        {
            return Admission::Smaller {
                resize: Resize {
                    operators: None,
                    creep_modes: Some(m),
                    without_observer,
                },
                why,
            };
        }
    }
    // … then one mode and the P–I banks, as many pairs of operators as fit.
    let creep_modes = fewer_modes.then_some(1);
    if rate.fewer_operators && operators > 0 {
        let pairs = (1..operators.div_ceil(2))
            .rev()
            .find(|&p| fits(&cut(settings, Some(2 * p), creep_modes)));
        if let Some(p) = pairs {
            return Admission::Smaller {
                resize: Resize {
                    operators: Some(2 * p),
                    creep_modes,
                    without_observer,
                },
                why,
            };
        }
    }
    Admission::Refused(why)
}

/// The P–I part of a model (a P–I's, or a generalised P–I's).
fn pi_part(model: &Model) -> Option<&PiParams> {
    match model {
        Model::PrandtlIshlinskii(p) => Some(p),
        Model::GeneralisedPi(g) => Some(&g.pi),
        _ => None,
    }
}

/// `settings` with their P–I parts cut to their first `operators` and their creep to its first
/// `creep_modes` (`None`: as they are): the shape a smaller fit would have, for the tick
/// budget to cost.
fn cut(settings: &Settings, operators: Option<usize>, creep_modes: Option<usize>) -> Settings {
    let mut s = settings.clone();
    if let Some(n) = operators {
        for model in [&mut s.compensator, &mut s.observer].into_iter().flatten() {
            let pi = match model {
                Model::PrandtlIshlinskii(p) => p,
                Model::GeneralisedPi(g) => &mut g.pi,
                _ => continue,
            };
            pi.thresholds.truncate(n);
            pi.weights.truncate(n);
        }
    }
    if let (Some(m), Some(creep)) = (creep_modes, s.creep.as_mut()) {
        creep.time_constants_s.truncate(m);
        creep.weights.truncate(m);
    }
    s
}

/// What the board says of a fitted model at `rate` ([`admission_at`] on the parameter file's
/// settings, the observer as fitted: the board's own sensor and feedback are not known here);
/// every model is admitted without a rate. The admission [`identify_and_score`] and the
/// lab stage's study (`twinstack lab-stage --tick-rate`) fit with.
pub fn board_admission<'a>(
    rate: Option<&'a BoardRate>,
    output_unit: &'a str,
) -> impl Fn(&IdentifyOptions, &Identification) -> Admission + 'a {
    move |fitted: &IdentifyOptions, id: &Identification| match rate {
        Some(rate) => admission_at(
            &ParamFile::from_model(&id.model, output_unit, None)
                .with_observer(fitted.observer)
                .settings,
            rate,
        ),
        None => Admission::Admitted,
    }
}

/// Fits `data` (`t`, `u`, `x`) as `choice` says, with `options` (its `model` is ignored;
/// `creep`: see [`candidates`]; for one model, `Some(true)` adds a creep operator), scores
/// the model kept and writes its parameter file with `output_unit` as the unit of `x`.
///
/// With `rate`, only a model the board runs at that control rate is kept
/// ([`admission_at`], with the parameter file's settings: the board's own sensor and feedback
/// are not known here, and a derivative term or a notch there costs more), a P–I sized down
/// to fewer operators where `rate` allows: `auto` picks among those, and one model asked for
/// by name that does not fit fails with [`IdentifyError::NoneAdmitted`].
pub fn identify_and_score(
    data: &MeasuredData,
    choice: ModelChoice,
    options: &IdentifyOptions,
    creep: Option<bool>,
    output_unit: &str,
    rate: Option<BoardRate>,
) -> Result<Identified, RunError> {
    let admit = board_admission(rate.as_ref(), output_unit);
    let (auto, options, id) = match choice {
        ModelChoice::Only(kind) => {
            let o = IdentifyOptions {
                model: kind,
                creep: creep == Some(true),
                ..options.clone()
            };
            let (o, id) = identify_admitted(data, o, &admit)?;
            (None, o, id)
        }
        ModelChoice::Auto => {
            let auto = identify_auto_admitting(data, &candidates(options, creep), admit)?;
            let kept = auto.options.clone();
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
    let drive = model.compensate_measured(t, x).map_err(RunError::Params)?;
    let drive_reference = model
        .compensate_measured_reference(t, x)
        .map_err(RunError::Params)?;
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
    for (what, figures) in [
        ("predict", &fixed_vs_reference),
        ("compensate", &inverse_fixed_vs_reference),
    ] {
        // A figure that is not a number is refused too.
        if figures.max_pct.is_nan() || figures.max_pct > FIXED_VS_REFERENCE_LIMIT_PCT {
            return Err(RunError::ReferenceDisagrees {
                what,
                max_pct: figures.max_pct,
            });
        }
    }
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
        fastest_motion_hz: fastest_motion_in(t, u, fit_from..held),
    };
    let file = ParamFile::from_model(model, output_unit, Some(record.clone()))
        .with_observer(options.observer);
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
