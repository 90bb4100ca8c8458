//! `--model auto`: pick the model family member that predicts best on data it was not fitted
//! on, then fit it on the whole window.
//!
//! The fit window (samples with `t < fit_until`) is split once more: every candidate is fitted
//! on its first part (from the start of motion up to [`VALIDATION_FRACTION`] before its end)
//! and scored, with the library's fixed-point `predict`, on the last part. The samples after
//! `fit_until` — the user's held-out part — are never looked at, so the held-out figure the
//! user is shown afterwards stays honest. Candidates are ranked by their validation max
//! error, then RMS (the figures the book and the papers quote); the best is refitted on the
//! whole window with the same options.
//!
//! A candidate that cannot be fitted (too few samples, a model the board refuses) is kept in
//! the ranking with its reason, last. So is one the caller does not admit
//! ([`identify_auto_admitting`]): `twinstack calibrate` (and `identify --tick-rate`) admits
//! only models the board's tick budget runs at the board's control rate, so that it never
//! picks one the board refuses; a candidate too dear only by its size is fitted and scored
//! again smaller ([`Admission::Smaller`]: fewer creep modes, fewer play operators).
//!
//! Parsimony: a model that generalises another (Bouc–Wen generalises Duhem,
//! [`super::ModelKind::special_case`]; with creep, Bouc–Wen + creep generalises Duhem + creep)
//! can always fit at least as well, so it wins only if its
//! validation max error beats its special case's by [`PARSIMONY_MARGIN`] (relative);
//! otherwise the special case is picked.

use super::score::{score, ErrorFigures};
use super::{identify, motion, Identification, IdentifyError, IdentifyOptions};
use crate::measured_data::MeasuredData;

/// Fraction of the fit window (after the start of motion) kept back to rank the candidates.
pub const VALIDATION_FRACTION: f64 = 0.3;
/// How much better (relative, on the validation max error) a generalisation must predict than
/// its special case to be picked over it.
pub const PARSIMONY_MARGIN: f64 = 0.05;

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
}

/// The size of a candidate that grows the tick's cost: its P–I's play operators and its creep
/// operator's modes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Size {
    /// Play operators (a P–I's, or a generalised P–I's P–I part).
    pub operators: usize,
    /// Creep modes (when the candidate has creep).
    pub creep_modes: usize,
}

impl Size {
    /// The size `options` ask for.
    pub fn of(options: &IdentifyOptions) -> Self {
        Self {
            operators: options.operators,
            creep_modes: options.creep_modes,
        }
    }

    /// Whether it is smaller than `asked` in one count at least and larger in none.
    pub fn is_smaller_than(&self, asked: &Size) -> bool {
        self.operators <= asked.operators && self.creep_modes <= asked.creep_modes && self != asked
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

/// Fewer play operators, fewer creep modes, or both: how [`Admission::Smaller`] makes a
/// candidate smaller.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Resize {
    /// The play operators to fit with (`None`: as asked).
    pub operators: Option<usize>,
    /// The creep modes to fit with (`None`: as asked).
    pub creep_modes: Option<usize>,
}

impl Resize {
    /// `options` resized.
    pub fn apply(&self, options: &IdentifyOptions) -> IdentifyOptions {
        IdentifyOptions {
            operators: self.operators.unwrap_or(options.operators),
            creep_modes: self.creep_modes.unwrap_or(options.creep_modes),
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
    admit: &impl Fn(&Identification) -> Admission,
) -> Result<(IdentifyOptions, Identification), IdentifyError> {
    let id = identify(data, &options)?;
    let refused =
        |why: String| IdentifyError::NoneAdmitted(format!("{}: {why}", options.model_label()));
    match admit(&id) {
        Admission::Admitted => Ok((options, id)),
        Admission::Refused(why) => Err(refused(why)),
        Admission::Smaller { resize, why } => {
            let smaller = resize.apply(&options);
            let id = identify(data, &smaller)?;
            match admit(&id) {
                Admission::Admitted if Size::of(&smaller).is_smaller_than(&Size::of(&options)) => {
                    Ok((smaller, id))
                }
                _ => Err(refused(why)),
            }
        }
    }
}

/// A candidate's name for the ranking table.
pub fn label(options: &IdentifyOptions) -> String {
    options.model_label()
}

/// Admitted candidates by their figures, then refused ones by theirs, then those not fitted.
fn rank_key(r: &Ranked) -> (u8, f64, f64) {
    match &r.validation {
        Validation::Scored(f) => (0, f.max_pct, f.rms_pct),
        Validation::NotAdmitted { figures: f, .. } => (1, f.max_pct, f.rms_pct),
        Validation::NotFitted(_) => (2, 0.0, 0.0),
    }
}

/// Fits every candidate in `candidates` (each with `fit_until_s` of the whole window) on the
/// first part of the window, ranks them on the rest, and refits the best on the whole window.
/// Fails only if no candidate can be fitted, with the first candidate's error.
pub fn identify_auto(
    data: &MeasuredData,
    candidates: &[IdentifyOptions],
) -> Result<AutoIdentification, IdentifyError> {
    identify_auto_admitting(data, candidates, |_| Admission::Admitted)
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
    admit: impl Fn(&Identification) -> Admission,
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
    // Fitted on the first part of the window, scored on the rest.
    let fit_and_score = |inner: &IdentifyOptions| {
        identify(&window, inner)
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
    let mut ranking: Vec<Ranked> = candidates
        .iter()
        .map(|c| {
            let mut options = c.clone();
            let mut inner = c.clone();
            inner.fit_until_s = validation_from_s;
            let mut sized_down_from = None;
            let validation = match fit_and_score(&inner) {
                Err(why) => Validation::NotFitted(why),
                Ok((id, figures)) => match admit(&id) {
                    Admission::Admitted => Validation::Scored(figures),
                    Admission::Refused(why) => Validation::NotAdmitted { figures, why },
                    Admission::Smaller { resize, why } => {
                        let asked = Size::of(c);
                        let smaller = resize.apply(&inner);
                        match fit_and_score(&smaller) {
                            Ok((id, smaller_figures))
                                if Size::of(&smaller).is_smaller_than(&asked)
                                    && admit(&id) == Admission::Admitted =>
                            {
                                sized_down_from = Some(asked);
                                options = resize.apply(&options);
                                Validation::Scored(smaller_figures)
                            }
                            _ => Validation::NotAdmitted { figures, why },
                        }
                    }
                },
            };
            Ranked {
                label: label(&options),
                options,
                validation,
                sized_down_from,
            }
        })
        .collect();
    ranking.sort_by(|a, b| {
        let (a, b) = (rank_key(a), rank_key(b));
        a.0.cmp(&b.0)
            .then(a.1.total_cmp(&b.1))
            .then(a.2.total_cmp(&b.2))
    });
    let best = ranking
        .iter()
        .find(|r| r.validation.admitted().is_some())
        .cloned();
    // Parsimony: the special case wins unless the generalisation beats it by the margin.
    let simpler = best.as_ref().and_then(|b| {
        let special = b.options.model.special_case()?;
        let best_max = b.validation.admitted()?.max_pct;
        ranking
            .iter()
            // Its special case with the same creep (Bouc–Wen + creep against Duhem + creep).
            .find(|r| r.options.model == special && r.options.creep == b.options.creep)
            .filter(|r| {
                r.validation
                    .admitted()
                    .is_some_and(|f| f.max_pct <= best_max * (1.0 + PARSIMONY_MARGIN))
            })
            .cloned()
    });
    let parsimony = simpler.is_some();
    if let Some(s) = &simpler {
        // Best first: the picked special case heads the ranking.
        if let Some(i) = ranking.iter().position(|r| r.label == s.label) {
            let picked = ranking.remove(i);
            ranking.insert(0, picked);
        }
    }
    let refused = |r: &Ranked| matches!(r.validation, Validation::NotAdmitted { .. });
    if best.is_none() && ranking.iter().any(refused) {
        let reasons: Vec<String> = ranking
            .iter()
            .filter_map(|r| Some(format!("\n  - {}: {}", r.label, r.validation.note()?)))
            .collect();
        return Err(IdentifyError::NoneAdmitted(reasons.concat()));
    }
    let Some(best) = simpler.or(best) else {
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
    // the first part (a creep mode the one fit gave no weight, the other may).
    let (options, identification) = identify_admitted(data, best.options.clone(), &admit)?;
    let runner_up = ranking
        .iter()
        .filter(|r| r.label != best.label)
        .find_map(|r| r.validation.admitted().map(|f| (r.label.clone(), *f)));
    let reason = match (best.validation.admitted(), runner_up) {
        (Some(b), Some((next, n))) if parsimony => format!(
            "{} predicts the validation part (t >= {:.4} s) within {:.0} % of the best ({next}: max {:.2} % / RMS {:.2} %) with fewer parameters: max {:.2} % / RMS {:.2} % of span",
            best.label, validation_from_s, 100.0 * PARSIMONY_MARGIN, n.max_pct, n.rms_pct, b.max_pct, b.rms_pct
        ),
        (Some(b), Some((next, n))) => format!(
            "{} predicts the validation part (t >= {:.4} s) best: max {:.2} % / RMS {:.2} % of span, against {:.2} % / {:.2} % for the next ({next})",
            best.label, validation_from_s, b.max_pct, b.rms_pct, n.max_pct, n.rms_pct
        ),
        (Some(b), None) => format!(
            "{} is the only candidate that could be fitted: validation max {:.2} % / RMS {:.2} %",
            best.label, b.max_pct, b.rms_pct
        ),
        // `best` is admitted by construction; its note, should that ever change.
        (None, _) => best.validation.note().unwrap_or_default(),
    };
    let asked = best.sized_down_from.unwrap_or(Size::of(&best.options));
    let reason = match Size::of(&options).sized_down_note(&asked) {
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
