//! `--model auto`: pick the model family member whose compensator does best on data it was
//! not fitted on, then fit it on the whole window.
//!
//! The fit window (samples with `t < fit_until`) is split once more: every candidate is fitted
//! on its first part (from the start of motion up to [`VALIDATION_FRACTION`] before its end)
//! and scored on the last part, with the library's fixed point, three ways:
//! * **forward**: its `predict` on the measured drive against the measured output;
//! * **inverse**: its `compensate` on the measured output against the drive that produced it
//!   (what the stage will be sent, on real sensor noise);
//! * **tracking**: the drive its `compensate` makes for the measured output, played through
//!   the forward model of the candidate that predicts best (the closest stand-in for the
//!   stage the data has), against that output.
//!
//! The samples after `fit_until` — the user's held-out part — are never looked at, so the
//! held-out figure the user is shown afterwards stays honest.
//!
//! **The score.** A candidate is ranked by what the stage will see of it, its *compensated*
//! error: the larger of its inverse and tracking max errors ([`Ranked::compensated`]), its
//! forward max error beside it and breaking ties. The forward error alone is no score: a
//! model can predict the record well and still have a compensator that ratchets on the
//! sensor's noise or drifts from its own model (Bouc–Wen + creep on the bipolar record
//! predicts to 0.90 % and inverts to 14.6 %), and it is the compensator the stage is sent.
//! The larger of the two compensated figures, rather than one of them: the inverse alone sees
//! every sensor spike amplified by the loop's slope and none of the model's fit, the tracking
//! alone sees only the compensator against a stand-in stage; a compensator the stage can trust
//! must do well on both.
//!
//! **The bound** ([`InverseBound`]). Before the score, each candidate's inverse is held against
//! its fit and against the record's noise floor. Within [`INVERSE_TO_FORWARD_LIMIT`] × its
//! forward max error it *holds*. Beyond that but within as many times the best inverse of all
//! it is at the *noise floor*: the record's noise reaches every inverse through the model's
//! slope, most where the loop is flattest, so on a noisy record even the model that generated
//! the data inverts to twice its forward error (a P–I fitted to noisy P–I data: forward
//! 0.26 %, inverse 0.54 %), while a model that fits poorly "holds" only because its forward
//! error is large (a Duhem on the same data: forward 1.06 %, inverse 0.91 %, tracking 1.07 %).
//! Ranking the noise floor after every candidate that holds would pick that Duhem, with twice
//! the compensated error: the two rank together, by their score. Beyond both, the candidate
//! *ratchets* — its compensator departs from its own model (noise ratcheting, drift), by more
//! than the short validation part shows and worse the longer it runs — and is set aside:
//! ranked after every candidate that does not, whatever its score, and picked only if every
//! candidate ratchets ([`Ranked::set_aside`] says why). The pick is refitted on the whole window
//! with the same options, and the refit must predict the window at least as well as the fit
//! that was ranked ([`REFIT_MARGIN`]): a refinement that settles in a worse minimum, or a refit
//! that fails, gives way to the ranked fit itself, and the reason says so.
//!
//! A candidate that cannot be fitted (too few samples, a model the board refuses) is kept in
//! the ranking with its reason, last. So is one the caller does not admit
//! ([`identify_auto_admitting`]): `twinstack calibrate` (and `identify --tick-rate`) admits
//! only models the board's tick budget runs at the board's control rate, so that it never
//! picks one the board refuses; a candidate too dear only by its size is fitted and scored
//! again smaller ([`Admission::Smaller`]: fewer creep modes, fewer play operators).
//!
//! Parsimony: a model that generalises another (Bouc–Wen generalises Duhem,
//! [`super::ModelKind::special_case`]; a model + creep generalises the model alone) can always
//! fit at least as well, so it wins only if its compensated max error beats the simpler
//! one's by [`PARSIMONY_MARGIN`] (relative) and the simpler one's inverse stands as well
//! against the bound; otherwise the simplest such is picked. [`rank`] orders the candidates
//! and picks, from their figures alone.

use super::score::{score, ErrorFigures};
use super::{identify, identify_from, motion, Identification, IdentifyError, IdentifyOptions};
use crate::stage_model::StageModel;
use twinstack_link::measured_data::MeasuredData;

/// Fraction of the fit window (after the start of motion) kept back to rank the candidates.
pub const VALIDATION_FRACTION: f64 = 0.3;

mod ranking;

use ranking::bound_inverses;
pub use ranking::{rank, InverseBound, Picked, INVERSE_TO_FORWARD_LIMIT, PARSIMONY_MARGIN};

/// One candidate's result on the validation part.
#[derive(Clone, Debug)]
pub struct Ranked {
    /// What was fitted (the options' model and creep, in words).
    pub label: String,
    /// The candidate's options (with the full window's `fit_until`; its play operators or
    /// creep modes fewer than asked where `admit` sized it down, [`Admission::Smaller`]).
    pub options: IdentifyOptions,
    /// Where it stands after the validation part.
    pub validation: Validation,
    /// The size asked for, where the candidate was sized down from it to be admitted.
    pub sized_down_from: Option<Size>,
    /// Its inverse on the validation part: `compensate` on the measured output against the
    /// measured drive, % of the drive's span (`None` if it was not fitted).
    pub inverse: Option<ErrorFigures>,
    /// Its compensated tracking on the validation part through the best-predicting
    /// candidate's forward model, % of the output's span (`None` if it was not fitted).
    pub tracking: Option<ErrorFigures>,
    /// How its inverse stands against its fit (`None` if it has no inverse or forward
    /// figure).
    pub bound: Option<InverseBound>,
    /// Why an admitted candidate was set aside, ranked after every one that was not (its
    /// inverse ratchets: [`InverseBound::Ratchets`]); `None` if it was not.
    pub set_aside: Option<String>,
}

impl Ranked {
    /// What the stage will see of it: the larger of its inverse and tracking max errors on the
    /// validation part, % (`None` if it was not fitted).
    pub fn compensated(&self) -> Option<f64> {
        match (self.inverse, self.tracking) {
            (Some(i), Some(t)) => Some(i.max_pct.max(t.max_pct)),
            (Some(i), None) => Some(i.max_pct),
            (None, Some(t)) => Some(t.max_pct),
            (None, None) => None,
        }
    }

    /// Its figures in one line: forward, inverse and tracking max (and forward RMS), then
    /// why it cannot be picked or was set aside, if so.
    pub fn summary(&self) -> String {
        let pct = |f: Option<&ErrorFigures>| match f {
            Some(f) => format!("{:5.2} %", f.max_pct),
            None => "    - ".to_string(),
        };
        let figures = format!(
            "forward {} (RMS {})  inverse {}  tracking {}",
            pct(self.validation.figures()),
            self.validation
                .figures()
                .map_or("-".into(), |f| format!("{:.2} %", f.rms_pct)),
            pct(self.inverse.as_ref()),
            pct(self.tracking.as_ref()),
        );
        match (
            self.validation.admitted(),
            self.validation.note(),
            &self.set_aside,
        ) {
            (Some(_), _, Some(why)) => format!("{figures}  set aside: {why}"),
            (Some(f), _, None) => match (self.bound, self.inverse) {
                (Some(InverseBound::NoiseFloor), Some(i)) => format!(
                    "{figures}  (inverse {:.2} × its forward: at the record's noise floor)",
                    i.max_pct / f.max_pct
                ),
                _ => figures,
            },
            (None, _, _) => match &self.validation {
                Validation::NotAdmitted { why, .. } => format!("{figures}  not admitted: {why}"),
                v => v.note().unwrap_or_default(),
            },
        }
    }
}

/// The size of a candidate that grows the tick's cost: its P–I's play operators and its creep
/// operator's modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Size {
    /// Play operators (a P–I's, or a generalised P–I's P–I part).
    pub operators: usize,
    /// Creep modes (when the candidate has creep).
    pub creep_modes: usize,
    /// Whether the parameter file runs the model as the observer too.
    pub observer: bool,
}

impl Size {
    /// The size `options` ask for.
    pub fn of(options: &IdentifyOptions) -> Self {
        Self {
            operators: options.operators,
            creep_modes: options.creep_modes,
            observer: options.observer,
        }
    }

    /// Whether it is smaller than `asked` in one count at least and larger in none.
    pub fn is_smaller_than(&self, asked: &Size) -> bool {
        self.operators <= asked.operators
            && self.creep_modes <= asked.creep_modes
            && self.observer <= asked.observer
            && self != asked
    }

    /// What was made smaller than `asked` for the board, in words ("16 play operators instead
    /// of 17 asked for, the most the board runs at its rate"); `None` if nothing was.
    pub fn sized_down_note(&self, asked: &Size) -> Option<String> {
        let mut parts = Vec::new();
        if self.operators != asked.operators {
            parts.push(format!(
                "{} play operators instead of {}",
                self.operators, asked.operators
            ));
        }
        if self.creep_modes != asked.creep_modes {
            parts.push(format!(
                "{} creep modes instead of {}",
                self.creep_modes, asked.creep_modes
            ));
        }
        if self.observer != asked.observer {
            parts.push(
                "no observer (the model as the compensator only: no estimate, no drift check) \
                 instead of the observer"
                    .to_string(),
            );
        }
        (!parts.is_empty()).then(|| {
            format!(
                "{} asked for, the most the board runs at its rate",
                parts.join(" and ")
            )
        })
    }
}

/// What the caller of [`identify_auto_admitting`] says of a candidate's fit.
#[derive(Clone, Debug, PartialEq)]
pub enum Admission {
    /// It can be picked.
    Admitted,
    /// It cannot, for the reason given.
    Refused(String),
    /// Not as fitted, for the reason given; fitted again smaller it would be. The candidate
    /// is fitted and scored again so and admitted if `admit` then says
    /// [`Admission::Admitted`]; refused with the first reason otherwise.
    Smaller {
        /// What to fit it with.
        resize: Resize,
        /// Why it is not admitted as fitted.
        why: String,
    },
}

/// No observer, fewer play operators, fewer creep modes, or several: how
/// [`Admission::Smaller`] makes a candidate smaller.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Resize {
    /// The play operators to fit with (`None`: as asked).
    pub operators: Option<usize>,
    /// The creep modes to fit with (`None`: as asked).
    pub creep_modes: Option<usize>,
    /// The parameter file without the observer (the model as the compensator only).
    pub without_observer: bool,
}

impl Resize {
    /// `options` resized.
    pub fn apply(&self, options: &IdentifyOptions) -> IdentifyOptions {
        IdentifyOptions {
            operators: self.operators.unwrap_or(options.operators),
            creep_modes: self.creep_modes.unwrap_or(options.creep_modes),
            observer: options.observer && !self.without_observer,
            ..options.clone()
        }
    }
}

/// Where a candidate stands after the validation part: scored and admitted (it can be picked),
/// scored but refused by the caller, or not fitted.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Validation {
    /// Fitted, scored on the validation part and admitted: it can be picked.
    Scored(ErrorFigures),
    /// Fitted and scored, but the caller does not admit it
    /// ([`identify_auto_admitting`]'s `admit`), for the reason given.
    NotAdmitted {
        /// Its validation figures.
        figures: ErrorFigures,
        /// Why the caller refused it.
        why: String,
    },
    /// Could not be fitted or scored, for the reason given.
    NotFitted(String),
}

impl Validation {
    /// The figures of a candidate that can be picked (scored and admitted).
    pub fn admitted(&self) -> Option<&ErrorFigures> {
        match self {
            Validation::Scored(f) => Some(f),
            _ => None,
        }
    }

    /// The figures of a candidate that was scored, admitted or not.
    pub fn figures(&self) -> Option<&ErrorFigures> {
        match self {
            Validation::Scored(f) | Validation::NotAdmitted { figures: f, .. } => Some(f),
            Validation::NotFitted(_) => None,
        }
    }

    /// What the ranking table says of a candidate that cannot be picked (`None` for one that
    /// can): refused with its reason and figures, or not fitted with its reason.
    pub fn note(&self) -> Option<String> {
        match self {
            Validation::Scored(_) => None,
            Validation::NotAdmitted { figures, why } => Some(format!(
                "not admitted ({why}); validation max {:.2} % / RMS {:.2} %",
                figures.max_pct, figures.rms_pct
            )),
            Validation::NotFitted(why) => Some(format!("not fitted: {why}")),
        }
    }
}

/// The outcome of `--model auto`.
#[derive(Clone, Debug)]
pub struct AutoIdentification {
    /// Every candidate, best first (a special case picked for parsimony ahead of its
    /// generalisation).
    pub ranking: Vec<Ranked>,
    /// The time the validation part starts, seconds.
    pub validation_from_s: f64,
    /// The winner's options as refitted on the whole window (smaller than asked where
    /// `admit` sized it down).
    pub options: IdentifyOptions,
    /// The winner, refitted on the whole window.
    pub identification: Identification,
    /// Why the winner was picked, for the user.
    pub reason: String,
}

/// One model fitted as `options` say and admitted by `admit`, fitted again smaller where
/// `admit` says so ([`Admission::Smaller`]); the options it was fitted with and the fit, or
/// [`IdentifyError::NoneAdmitted`] with the reason.
pub fn identify_admitted(
    data: &MeasuredData,
    options: IdentifyOptions,
    admit: &impl Fn(&IdentifyOptions, &Identification) -> Admission,
) -> Result<(IdentifyOptions, Identification), IdentifyError> {
    let id = identify(data, &options)?;
    let refused =
        |why: String| IdentifyError::NoneAdmitted(format!("{}: {why}", options.model_label()));
    match admit(&options, &id) {
        Admission::Admitted => Ok((options, id)),
        Admission::Refused(why) => Err(refused(why)),
        Admission::Smaller { resize, why } => {
            let smaller = resize.apply(&options);
            let id = identify(data, &smaller)?;
            match admit(&smaller, &id) {
                Admission::Admitted if Size::of(&smaller).is_smaller_than(&Size::of(&options)) => {
                    Ok((smaller, id))
                }
                _ => Err(refused(why)),
            }
        }
    }
}

/// Whether `a` and `b` fit the same hysteresis model the same way, whatever creep, output
/// map and observer they add: a fit of `a` without creep or map is where `b`'s map and creep
/// start from.
fn same_model_fit(a: &IdentifyOptions, b: &IdentifyOptions) -> bool {
    let model_only = |o: &IdentifyOptions| IdentifyOptions {
        creep: false,
        creep_modes: 0,
        output_map: false,
        observer: true,
        ..o.clone()
    };
    model_only(a) == model_only(b)
}

/// A candidate's name for the ranking table.
pub fn label(options: &IdentifyOptions) -> String {
    options.model_label()
}

/// Fits every candidate in `candidates` (each with `fit_until_s` of the whole window) on the
/// first part of the window, ranks them on the rest, and refits the best on the whole window.
/// Fails only if no candidate can be fitted, with the first candidate's error.
pub fn identify_auto(
    data: &MeasuredData,
    candidates: &[IdentifyOptions],
) -> Result<AutoIdentification, IdentifyError> {
    identify_auto_admitting(data, candidates, |_, _| Admission::Admitted)
}

/// [`identify_auto`], picking only among the candidates `admit` accepts, given each one's fit
/// on the first part of the window; the winner's refit on the whole window is checked again
/// ([`identify_admitted`]: the two fits can differ in size). A candidate `admit` would take
/// with fewer play operators or creep modes ([`Admission::Smaller`]) is fitted and scored
/// again with them. A candidate it refuses stays in the ranking, after the admitted ones, with `admit`'s
/// reason and its validation figures. Fails with [`IdentifyError::NoneAdmitted`] if every
/// candidate that could be fitted was refused.
pub fn identify_auto_admitting(
    data: &MeasuredData,
    candidates: &[IdentifyOptions],
    admit: impl Fn(&IdentifyOptions, &Identification) -> Admission,
) -> Result<AutoIdentification, IdentifyError> {
    let first = candidates.first().ok_or(IdentifyError::NoCandidates)?;
    let fit_until_s = first.fit_until_s;
    let n_fit = data.t.iter().take_while(|&&t| t < fit_until_s).count();
    let u = data
        .u
        .as_deref()
        .ok_or_else(|| IdentifyError::MissingColumns(data.path.display().to_string()))?;
    let x = data
        .x
        .as_deref()
        .ok_or_else(|| IdentifyError::MissingColumns(data.path.display().to_string()))?;
    let start = motion::find(&u[..n_fit.min(u.len())])
        .map(|m| m.first_fitted)
        .ok_or(IdentifyError::NoMotion(fit_until_s))?;
    let split = start + ((n_fit - start) as f64 * (1.0 - VALIDATION_FRACTION)) as usize;
    let split = split.min(n_fit.saturating_sub(1));
    let validation_from_s = data.t[split];
    // The candidates see only the fit window: the held-out part stays unseen.
    let window = MeasuredData {
        path: data.path.clone(),
        t: data.t[..n_fit].to_vec(),
        u: Some(u[..n_fit].to_vec()),
        x: Some(x[..n_fit].to_vec()),
    };
    // Fitted on the first part of the window, scored on the rest; a candidate with an output
    // map from the same model's fit without creep or map, where there is one (`fitted`).
    let fit_and_score = |inner: &IdentifyOptions, fitted: Option<&Identification>| {
        identify_from(&window, inner, fitted)
            .map_err(|e| e.to_string())
            .and_then(|id| {
                let predicted = id
                    .model
                    .predict(&window.t, &u[..n_fit])
                    .map_err(|e| e.to_string())?;
                let figures = score(&x[..n_fit], &predicted, split..n_fit).ok_or_else(|| {
                    String::from("the measured output is flat on the validation part")
                })?;
                Ok((id, figures))
            })
    };
    let mut fits: Vec<Option<Identification>> = Vec::with_capacity(candidates.len());
    // The candidates' fits without creep or map, for those with a map to start from.
    let mut plain: Vec<(IdentifyOptions, Identification)> = Vec::new();
    let mut ranking: Vec<Ranked> = candidates
        .iter()
        .map(|c| {
            let mut options = c.clone();
            let mut inner = c.clone();
            inner.fit_until_s = validation_from_s;
            let mut sized_down_from = None;
            let mut fit = None;
            let start = plain
                .iter()
                .find(|(o, _)| inner.output_map && same_model_fit(o, &inner))
                .map(|(_, id)| id);
            let fitted = fit_and_score(&inner, start);
            if let Ok((id, _)) = &fitted {
                if !inner.creep && !inner.output_map {
                    plain.push((inner.clone(), id.clone()));
                }
            }
            let validation = match fitted {
                Err(why) => Validation::NotFitted(why),
                Ok((id, figures)) => match admit(&inner, &id) {
                    Admission::Admitted => {
                        fit = Some(id);
                        Validation::Scored(figures)
                    }
                    Admission::Refused(why) => {
                        fit = Some(id);
                        Validation::NotAdmitted { figures, why }
                    }
                    Admission::Smaller { resize, why } => {
                        let asked = Size::of(c);
                        let smaller = resize.apply(&inner);
                        match fit_and_score(&smaller, None) {
                            Ok((small, smaller_figures))
                                if Size::of(&smaller).is_smaller_than(&asked)
                                    && admit(&smaller, &small) == Admission::Admitted =>
                            {
                                sized_down_from = Some(asked);
                                options = resize.apply(&options);
                                fit = Some(small);
                                Validation::Scored(smaller_figures)
                            }
                            _ => {
                                fit = Some(id);
                                Validation::NotAdmitted { figures, why }
                            }
                        }
                    }
                },
            };
            let label = fit
                .as_ref()
                .map_or_else(|| label(&options), |f| options.label_of_fit(&f.model));
            fits.push(fit);
            Ranked {
                label,
                options,
                validation,
                sized_down_from,
                inverse: None,
                tracking: None,
                bound: None,
                set_aside: None,
            }
        })
        .collect();
    score_compensators(
        &mut ranking,
        &fits,
        &window.t,
        &u[..n_fit],
        &x[..n_fit],
        split,
    );
    // Each candidate's fit on the first part, by its label (the ranking is reordered).
    let first_part_fits: Vec<(String, Option<Identification>)> =
        ranking.iter().map(|r| r.label.clone()).zip(fits).collect();
    let picked = rank(&mut ranking);
    let parsimony = picked == Some(Picked::Simpler);
    let best = picked.map(|_| ranking[0].clone());
    let refused = |r: &Ranked| matches!(r.validation, Validation::NotAdmitted { .. });
    if best.is_none() && ranking.iter().any(refused) {
        let reasons: Vec<String> = ranking
            .iter()
            .filter_map(|r| Some(format!("\n  - {}: {}", r.label, r.validation.note()?)))
            .collect();
        return Err(IdentifyError::NoneAdmitted(reasons.concat()));
    }
    let Some(best) = best else {
        // No candidate could be ranked (the validation part too short for every one):
        // the first candidate on the whole window, or its error.
        let (options, identification) = identify_admitted(data, first.clone(), &admit)?;
        return Ok(AutoIdentification {
            reason: format!(
                "no candidate could be fitted on the first part of the window alone; {} was fitted on the whole window without a ranking",
                label(&options)
            ),
            ranking,
            validation_from_s,
            options,
            identification,
        });
    };
    // The refit on the whole window is checked again: its size can differ from the fit on
    // the first part (a creep mode the one fit gave no weight, the other may). And it must
    // predict the window at least as well as the fit that was ranked, or that fit is kept.
    let ranked_fit = first_part_fits
        .into_iter()
        .find(|(label, _)| *label == best.label)
        .and_then(|(_, fit)| fit);
    let refit = identify_admitted(data, best.options.clone(), &admit);
    let (options, identification, refit_note) =
        keep_the_better_fit(&window, n_fit, refit, ranked_fit, &best.options, &admit)?;
    let runner_up = ranking
        .iter()
        .filter(|r| r.label != best.label && r.validation.admitted().is_some())
        .find_map(|r| Some((r.label.clone(), r.compensated()?)));
    let figures = |r: &Ranked| {
        let forward = r.validation.figures().map_or(f64::NAN, |f| f.max_pct);
        format!(
            "compensated max {:.2} % (inverse {:.2} %, tracking {:.2} %), forward max {:.2} %",
            r.compensated().unwrap_or(f64::NAN),
            r.inverse.map_or(f64::NAN, |f| f.max_pct),
            r.tracking.map_or(f64::NAN, |f| f.max_pct),
            forward
        )
    };
    let reason = match runner_up {
        Some((next, n)) if parsimony => format!(
            "{}'s compensator does within {:.0} % of the best ({next}: {n:.2} %) on the validation part (t >= {:.4} s) with fewer parameters: {}",
            best.label, 100.0 * PARSIMONY_MARGIN, validation_from_s, figures(&best)
        ),
        Some((next, n)) => format!(
            "{}'s compensator does best on the validation part (t >= {:.4} s): {}; next {next}: compensated max {n:.2} %",
            best.label, validation_from_s, figures(&best)
        ),
        None => format!(
            "{} is the only candidate that could be fitted: {}",
            best.label,
            figures(&best)
        ),
    };
    let reason = match &best.set_aside {
        Some(why) => format!("{reason}; every candidate's inverse ratchets ({why})"),
        None => reason,
    };
    // What a ranking by the forward error alone would have picked, where that is another
    // candidate: why it was not.
    let forward_max = |r: &Ranked| r.validation.admitted().map(|f| f.max_pct);
    let forward_best = ranking
        .iter()
        .filter(|r| forward_max(r).is_some())
        .min_by(|a, b| {
            forward_max(a)
                .unwrap_or(f64::INFINITY)
                .total_cmp(&forward_max(b).unwrap_or(f64::INFINITY))
        });
    let reason = match forward_best {
        Some(f) if f.label != best.label => format!(
            "{reason}; the best forward fit, {} (forward max {:.2} %), was not picked: {}",
            f.label,
            forward_max(f).unwrap_or(f64::NAN),
            match &f.set_aside {
                Some(why) => why.clone(),
                None => format!(
                    "its compensated max is {:.2} %",
                    f.compensated().unwrap_or(f64::NAN)
                ),
            }
        ),
        _ => reason,
    };
    let asked = best.sized_down_from.unwrap_or(Size::of(&best.options));
    let reason = match Size::of(&options).sized_down_note(&asked) {
        Some(note) => format!("{reason}; {note}"),
        None => reason,
    };
    let reason = match refit_note {
        Some(note) => format!("{reason}; {note}"),
        None => reason,
    };
    Ok(AutoIdentification {
        ranking,
        validation_from_s,
        options,
        identification,
        reason,
    })
}

/// How much worse (relative) than the ranked fit's the refit's RMS error over the fit window
/// may be before the ranked fit is kept instead (`keep_the_better_fit`): the refit has seen
/// every row the ranked fit saw and the validation part besides, so a least-squares refit is
/// never worse there; only a refinement that settles in another, worse minimum (the Duhem and
/// Bouc–Wen fits refine by a simplex from a few starts) can be. The margin keeps a refit that
/// differs by a rounding.
pub const REFIT_MARGIN: f64 = 0.1;

/// The pick as it goes to the board: the refit on the whole window (`refit`: its options and
/// fit, or why it failed or was refused), unless it predicts the window (`window`'s first
/// `n_fit` samples, from where motion starts) worse than the fit on the first part that was
/// ranked (`ranked`) by more than [`REFIT_MARGIN`], or cannot be made: then that fit, with
/// `options` (the ranked candidate's) and a note saying why — where `admit` takes it as it is
/// returned (scored on the user's held-out part as the refit would be, `held_out_from` the
/// window's end); otherwise the refit, or its error, stands.
fn keep_the_better_fit(
    window: &MeasuredData,
    n_fit: usize,
    refit: Result<(IdentifyOptions, Identification), IdentifyError>,
    ranked: Option<Identification>,
    options: &IdentifyOptions,
    admit: &impl Fn(&IdentifyOptions, &Identification) -> Admission,
) -> Result<(IdentifyOptions, Identification, Option<String>), IdentifyError> {
    let window_rms = |id: &Identification| -> Option<f64> {
        let (u, x) = (window.u.as_deref()?, window.x.as_deref()?);
        let predicted = id.model.predict(&window.t, u).ok()?;
        score(x, &predicted, id.motion.first_fitted.min(n_fit - 1)..n_fit)
            .map(|f| f.rms_pct)
            .filter(|r| r.is_finite())
    };
    let ranked = ranked.map(|mut r| {
        r.held_out_from = n_fit;
        r
    });
    let Some(mut ranked) = ranked.filter(|r| admit(options, r) == Admission::Admitted) else {
        let (o, id) = refit?;
        return Ok((o, id, None));
    };
    // Why the refit gives way to the ranked fit, if it does.
    let why = match &refit {
        Ok((_, id)) => match (window_rms(id), window_rms(&ranked)) {
            (Some(r), Some(f)) if r > f * (1.0 + REFIT_MARGIN) => Some(format!(
                "predicted it worse (RMS {r:.2} %) than the fit on its first part that was ranked ({f:.2} %)"
            )),
            (None, Some(f)) => Some(format!(
                "could not be run over it (the fit on its first part that was ranked: RMS {f:.2} % over the window)"
            )),
            _ => None,
        },
        Err(e) => Some(format!("failed ({e})")),
    };
    match (refit, why) {
        (Ok((o, id)), None) => Ok((o, id, None)),
        (_, why) => {
            let note = format!(
                "the refit on the whole window {}: the fit on its first part that was ranked is kept",
                why.unwrap_or_default()
            );
            ranked.notes.push(note.clone());
            Ok((options.clone(), ranked, Some(note)))
        }
    }
}

/// Fills in each fitted candidate's inverse and tracking figures on the validation part
/// (`split..` of `t`, `u`, `x`, the last `lag` samples left out: they have no later reading to
/// aim the drive at), and where its inverse stands against its fit ([`InverseBound`], with
/// why for an admitted one whose inverse does not hold). `fits[i]` is
/// `ranking[i]`'s fit on the first part, if any. The tracking plant, the stand-in for the
/// stage, is the fitted model with the lowest forward max error among those whose inverse
/// does not ratchet ([`InverseBound::Ratchets`]: a model that ratchets on a noisy drive is no
/// stand-in for a stage that does not), admitted by the board or not; the best forward model if none does.
fn score_compensators(
    ranking: &mut [Ranked],
    fits: &[Option<Identification>],
    t: &[f64],
    u: &[f64],
    x: &[f64],
    split: usize,
) {
    let n = t.len();
    let models: Vec<Option<&StageModel>> =
        fits.iter().map(|f| f.as_ref().map(|f| &f.model)).collect();
    let mut drives: Vec<Option<(Vec<f64>, usize)>> = Vec::with_capacity(models.len());
    for (r, model) in ranking.iter_mut().zip(&models) {
        let drive = model.and_then(|m| {
            let aimed = n - m.lag_samples(t).min(n.saturating_sub(split + 1));
            Some((m.compensate_measured(t, x).ok()?, aimed))
        });
        r.inverse = drive
            .as_ref()
            .and_then(|(d, aimed)| score(u, d, split..*aimed));
        drives.push(drive);
    }
    bound_inverses(ranking);
    let consistent: Vec<bool> = ranking
        .iter()
        .map(|r| {
            matches!(
                r.bound,
                Some(InverseBound::Holds | InverseBound::NoiseFloor)
            )
        })
        .collect();
    let forward_max = |r: &Ranked| r.validation.figures().map_or(f64::INFINITY, |f| f.max_pct);
    let best_of = |only_consistent: bool| {
        (0..ranking.len())
            .filter(|&i| models[i].is_some() && (consistent[i] || !only_consistent))
            .min_by(|&a, &b| forward_max(&ranking[a]).total_cmp(&forward_max(&ranking[b])))
    };
    let Some(plant) = best_of(true)
        .or_else(|| best_of(false))
        .and_then(|i| models[i])
    else {
        return;
    };
    for (r, drive) in ranking.iter_mut().zip(&drives) {
        let Some((drive, aimed)) = drive else {
            continue;
        };
        r.tracking = plant
            .predict(t, drive)
            .ok()
            .and_then(|y| score(x, &y, split..*aimed));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::identification::ModelKind;
    use crate::reference;
    use crate::stage_model::Hysteresis;
    use std::path::PathBuf;
    use twinstack::models::params::{PiParams, Thresholds};
    use twinstack::Scaling;

    /// A known P–I driven by a ±60 V sine about 70 V (2 000 samples) and its options, fitted
    /// on `t < 1.6 s`.
    fn record() -> (MeasuredData, IdentifyOptions) {
        let n = 2000;
        let t: Vec<f64> = (0..n).map(|k| k as f64 * 1e-3).collect();
        let u: Vec<f64> = t
            .iter()
            .map(|&t| 70.0 - 60.0 * (std::f64::consts::TAU * 5.0 * t).cos())
            .collect();
        let thresholds = Thresholds::Uniform.generate(8, 60.0).unwrap();
        let weights: Vec<f64> = (0..8).map(|i| 0.3 / (1.0 + i as f64)).collect();
        let truth = PiParams::new(0.1, 1.0, &thresholds, &weights).unwrap();
        let s = Scaling::new(0.0, 140.0, 0.0, 100.0).unwrap();
        let mut m = reference::PrandtlIshlinskii::new(&truth, &s, u[0]).unwrap();
        let x: Vec<f64> = u.iter().map(|&v| m.step(v)).collect();
        let data = MeasuredData {
            path: PathBuf::from("sine.csv"),
            t,
            u: Some(u),
            x: Some(x),
        };
        let mut options = IdentifyOptions::new(ModelKind::Pi, 1.6);
        options.operators = 8;
        (data, options)
    }

    /// The window `identify_auto_admitting` passes: the samples before `fit_until_s`.
    fn window(data: &MeasuredData, fit_until_s: f64) -> (MeasuredData, usize) {
        let n = data.t.iter().take_while(|&&t| t < fit_until_s).count();
        let cut = |v: &Option<Vec<f64>>| v.as_ref().map(|v| v[..n].to_vec());
        (
            MeasuredData {
                path: data.path.clone(),
                t: data.t[..n].to_vec(),
                u: cut(&data.u),
                x: cut(&data.x),
            },
            n,
        )
    }

    /// The refit is the pick unless it predicts the window worse than the ranked fit by more
    /// than the margin, or fails: then the ranked fit is kept, said so, and scored on the
    /// user's held-out part from the window's end.
    #[test]
    fn a_refit_worse_than_the_ranked_fit_or_failed_gives_way_to_it() {
        let (data, options) = record();
        let (window, n_fit) = window(&data, options.fit_until_s);
        let mut first_part = options.clone();
        first_part.fit_until_s = 1.1;
        let ranked = identify(&window, &first_part).unwrap();
        let refit = identify(&data, &options).unwrap();
        let admitted = |_: &IdentifyOptions, _: &Identification| Admission::Admitted;
        assert!(ranked.held_out_from < n_fit);

        // A good refit is the pick.
        let (_, id, note) = keep_the_better_fit(
            &window,
            n_fit,
            Ok((options.clone(), refit.clone())),
            Some(ranked.clone()),
            &options,
            &admitted,
        )
        .unwrap();
        assert_eq!(id.model, refit.model);
        assert!(note.is_none());

        // A refit whose weights are off by half predicts the window worse: the ranked fit.
        let mut worse = refit.clone();
        if let Hysteresis::Pi(p) = &mut worse.model.hysteresis {
            for w in p.weights.iter_mut() {
                *w *= 0.5;
            }
        } else {
            panic!("a P–I was fitted");
        }
        let (o, id, note) = keep_the_better_fit(
            &window,
            n_fit,
            Ok((options.clone(), worse)),
            Some(ranked.clone()),
            &options,
            &admitted,
        )
        .unwrap();
        assert_eq!(id.model, ranked.model);
        assert_eq!(id.held_out_from, n_fit, "held out from the window's end");
        assert_eq!(o.fit_until_s, options.fit_until_s);
        let note = note.expect("the reason says so");
        assert!(note.contains("predicted it worse"), "{note}");
        assert!(id.notes.contains(&note));

        // A refit that failed: the ranked fit, and why.
        let (_, id, note) = keep_the_better_fit(
            &window,
            n_fit,
            Err(IdentifyError::NoCandidates),
            Some(ranked.clone()),
            &options,
            &admitted,
        )
        .unwrap();
        assert_eq!(id.model, ranked.model);
        assert!(note.unwrap().contains("failed"));

        // Without a ranked fit the refit's error stands.
        assert!(keep_the_better_fit(
            &window,
            n_fit,
            Err(IdentifyError::NoCandidates),
            None,
            &options,
            &admitted,
        )
        .is_err());
        // Nor where the caller does not admit the ranked fit as it would be returned.
        let refused = |_: &IdentifyOptions, _: &Identification| Admission::Refused("no".into());
        assert!(keep_the_better_fit(
            &window,
            n_fit,
            Err(IdentifyError::NoCandidates),
            Some(ranked.clone()),
            &options,
            &refused,
        )
        .is_err());
    }
}
