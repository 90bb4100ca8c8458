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
//! with the same options.
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
use super::{identify, motion, Identification, IdentifyError, IdentifyOptions};
use crate::stage_model::StageModel;
use twinstack_link::measured_data::MeasuredData;

/// Fraction of the fit window (after the start of motion) kept back to rank the candidates.
pub const VALIDATION_FRACTION: f64 = 0.3;
/// How much better (relative, on the compensated max error) a generalisation must do than its
/// special case to be picked over it.
pub const PARSIMONY_MARGIN: f64 = 0.05;
/// A candidate's inverse holds if its max error on the validation part is within this
/// multiple of its forward max error there ([`InverseBound`]): the ratio the compensators aim
/// at. One whose inverse is also beyond this multiple of the best inverse of all candidates
/// (the record's noise floor, which no compensator beats) ratchets.
pub const INVERSE_TO_FORWARD_LIMIT: f64 = 1.5;

/// How a candidate's inverse stands against its fit on the validation part (ordered from best);
/// the ranking puts those that ratchet after all others (see the module's documentation).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum InverseBound {
    /// Inverse max ≤ [`INVERSE_TO_FORWARD_LIMIT`] × its forward max.
    Holds,
    /// Beyond that, but within [`INVERSE_TO_FORWARD_LIMIT`] × the best inverse of all (the
    /// record's noise reaches every inverse): ranked with those that hold, by its score.
    NoiseFloor,
    /// Beyond both: a compensator that ratchets on the noise or drifts from its own model.
    Ratchets,
}

impl InverseBound {
    /// Where an inverse max error `inverse` stands, given its forward max error `forward` and
    /// the best inverse max error of all candidates `best_inverse` (all % of span).
    ///
    /// ```
    /// use twinstack_identify::identification::auto::InverseBound;
    /// assert_eq!(InverseBound::of(1.2, 1.0, 1.2), InverseBound::Holds);
    /// assert_eq!(InverseBound::of(1.8, 1.0, 1.3), InverseBound::NoiseFloor);
    /// assert_eq!(InverseBound::of(14.6, 0.9, 1.2), InverseBound::Ratchets);
    /// ```
    pub fn of(inverse: f64, forward: f64, best_inverse: f64) -> Self {
        if inverse <= INVERSE_TO_FORWARD_LIMIT * forward {
            InverseBound::Holds
        } else if inverse <= INVERSE_TO_FORWARD_LIMIT * best_inverse {
            InverseBound::NoiseFloor
        } else {
            InverseBound::Ratchets
        }
    }

    /// What the ranking says of a candidate with these figures, in words (`None` if its
    /// inverse holds).
    pub fn why(self, inverse: f64, forward: f64, best_inverse: f64) -> Option<String> {
        let ratio = inverse / forward;
        match self {
            InverseBound::Holds => None,
            InverseBound::NoiseFloor => Some(format!(
                "inverse {ratio:.2} × its forward, within {INVERSE_TO_FORWARD_LIMIT} × the best inverse {best_inverse:.2} % (the record's noise floor)"
            )),
            InverseBound::Ratchets => Some(format!(
                "inverse max {inverse:.2} % is {ratio:.2} × its forward max {forward:.2} % and > {INVERSE_TO_FORWARD_LIMIT} × \
                 the best inverse {best_inverse:.2} %: its compensator departs from its model (ratchets on the noise or drifts)"
            )),
        }
    }
}

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

/// Admitted candidates first, those whose inverse does not ratchet ([`InverseBound`]) before
/// those that do, each group by its compensated max error then its forward max error; then
/// refused ones likewise, then those not fitted.
fn rank_key(r: &Ranked) -> (u8, bool, f64, f64) {
    let compensated = r.compensated().unwrap_or(f64::INFINITY);
    let ratchets = r.bound.is_none_or(|b| b == InverseBound::Ratchets);
    match &r.validation {
        Validation::Scored(f) => (0, ratchets, compensated, f.max_pct),
        Validation::NotAdmitted { figures: f, .. } => (1, ratchets, compensated, f.max_pct),
        Validation::NotFitted(_) => (2, false, 0.0, 0.0),
    }
}

/// How [`rank`] picked the candidate it put first.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Picked {
    /// The best of the ranking.
    Best,
    /// A special case of the best (or the same model without creep), within
    /// [`PARSIMONY_MARGIN`] of it and ratcheting only if the best does.
    Simpler,
}

/// Orders `ranking` best first (admitted before refused before not fitted;
/// among the admitted, those whose inverse does not ratchet first, then by the compensated
/// error) and
/// puts the pick first: the best admitted candidate, or a simpler one for parsimony (see the
/// module's documentation). Each candidate's [`Ranked::bound`] must be set (what
/// [`identify_auto_admitting`] does from the validation figures). `None` if no candidate is
/// admitted.
pub fn rank(ranking: &mut [Ranked]) -> Option<Picked> {
    ranking.sort_by(|a, b| {
        let (a, b) = (rank_key(a), rank_key(b));
        a.0.cmp(&b.0)
            .then(a.1.cmp(&b.1))
            .then(a.2.total_cmp(&b.2))
            .then(a.3.total_cmp(&b.3))
    });
    let best = ranking.iter().find(|r| r.validation.admitted().is_some())?;
    // Parsimony: a simpler candidate — the special case (Duhem for Bouc–Wen), the same model
    // without creep, or both — wins unless the pick beats it by the margin; the simplest such.
    let best_score = best.compensated();
    let special = best.options.model.special_case();
    let simpler_forms = [
        (special, false),
        (special, best.options.creep),
        (Some(best.options.model), false),
    ];
    let simpler = simpler_forms
        .iter()
        .filter(|(m, creep)| {
            m.is_some() && (*m != Some(best.options.model) || *creep != best.options.creep)
        })
        .find_map(|&(m, creep)| {
            ranking.iter().position(|r| {
                Some(r.options.model) == m
                    && r.options.creep == creep
                    && r.validation.admitted().is_some()
                    && r.set_aside.is_none() == best.set_aside.is_none()
                    && r.compensated()
                        .zip(best_score)
                        .is_some_and(|(c, b)| c <= b * (1.0 + PARSIMONY_MARGIN))
            })
        });
    match simpler {
        Some(i) => {
            // Best first: the picked special case heads the ranking.
            ranking[..=i].rotate_right(1);
            Some(Picked::Simpler)
        }
        None => {
            let i = ranking
                .iter()
                .position(|r| r.validation.admitted().is_some())?;
            ranking[..=i].rotate_right(1);
            Some(Picked::Best)
        }
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
    let mut models: Vec<Option<StageModel>> = Vec::with_capacity(candidates.len());
    let mut ranking: Vec<Ranked> = candidates
        .iter()
        .map(|c| {
            let mut options = c.clone();
            let mut inner = c.clone();
            inner.fit_until_s = validation_from_s;
            let mut sized_down_from = None;
            let mut model = None;
            let validation = match fit_and_score(&inner) {
                Err(why) => Validation::NotFitted(why),
                Ok((id, figures)) => match admit(&id) {
                    Admission::Admitted => {
                        model = Some(id.model);
                        Validation::Scored(figures)
                    }
                    Admission::Refused(why) => {
                        model = Some(id.model);
                        Validation::NotAdmitted { figures, why }
                    }
                    Admission::Smaller { resize, why } => {
                        let asked = Size::of(c);
                        let smaller = resize.apply(&inner);
                        match fit_and_score(&smaller) {
                            Ok((small, smaller_figures))
                                if Size::of(&smaller).is_smaller_than(&asked)
                                    && admit(&small) == Admission::Admitted =>
                            {
                                sized_down_from = Some(asked);
                                options = resize.apply(&options);
                                model = Some(small.model);
                                Validation::Scored(smaller_figures)
                            }
                            _ => {
                                model = Some(id.model);
                                Validation::NotAdmitted { figures, why }
                            }
                        }
                    }
                },
            };
            let label = model
                .as_ref()
                .map_or_else(|| label(&options), |m| options.label_of_fit(m));
            models.push(model);
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
        &models,
        &window.t,
        &u[..n_fit],
        &x[..n_fit],
        split,
    );
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
    // the first part (a creep mode the one fit gave no weight, the other may).
    let (options, identification) = identify_admitted(data, best.options.clone(), &admit)?;
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
    Ok(AutoIdentification {
        ranking,
        validation_from_s,
        options,
        identification,
        reason,
    })
}

/// Fills in each fitted candidate's inverse and tracking figures on the validation part
/// (`split..` of `t`, `u`, `x`, the last `lag` samples left out: they have no later reading to
/// aim the drive at), and where its inverse stands against its fit ([`InverseBound`], with
/// why for an admitted one whose inverse does not hold). `models[i]` is
/// `ranking[i]`'s fit on the first part, if any. The tracking plant, the stand-in for the
/// stage, is the fitted model with the lowest forward max error among those whose inverse
/// does not ratchet ([`InverseBound::Ratchets`]: a model that ratchets on a noisy drive is no
/// stand-in for a stage that does not), admitted by the board or not; the best forward model if none does.
fn score_compensators(
    ranking: &mut [Ranked],
    models: &[Option<StageModel>],
    t: &[f64],
    u: &[f64],
    x: &[f64],
    split: usize,
) {
    let n = t.len();
    let mut drives: Vec<Option<(Vec<f64>, usize)>> = Vec::with_capacity(models.len());
    for (r, model) in ranking.iter_mut().zip(models) {
        let drive = model.as_ref().and_then(|m| {
            let aimed = n - m.lag_samples(t).min(n.saturating_sub(split + 1));
            Some((m.compensate(t, x).ok()?, aimed))
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
        .and_then(|i| models[i].as_ref())
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

/// Sets each candidate's [`Ranked::bound`] from its inverse and forward max errors and the best
/// inverse of all, and, for an admitted one whose inverse does not hold, why
/// ([`Ranked::set_aside`]) for an admitted one that ratchets.
fn bound_inverses(ranking: &mut [Ranked]) {
    // The record's noise reaches the inverse through the model's local slope: no compensator
    // beats that floor, whatever its fit. The best inverse of all stands for it.
    let best_inverse = ranking
        .iter()
        .filter_map(|r| r.inverse.map(|f| f.max_pct))
        .fold(f64::INFINITY, f64::min);
    for r in ranking.iter_mut() {
        let figures = r.inverse.zip(r.validation.figures().copied());
        r.bound = figures.map(|(i, f)| InverseBound::of(i.max_pct, f.max_pct, best_inverse));
        r.set_aside = match (r.validation.admitted(), r.bound, figures) {
            (Some(_), Some(b @ InverseBound::Ratchets), Some((i, f))) => {
                b.why(i.max_pct, f.max_pct, best_inverse)
            }
            _ => None,
        };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::identification::ModelKind;

    /// A candidate scored on the validation part with these max errors (%).
    fn scored(model: ModelKind, creep: bool, forward: f64, inverse: f64, tracking: f64) -> Ranked {
        let figures = |max_pct| ErrorFigures {
            max_pct,
            rms_pct: max_pct / 4.0,
            samples: 1000,
        };
        let mut options = IdentifyOptions::new(model, 1.0);
        options.creep = creep;
        Ranked {
            label: options.model_label(),
            options,
            validation: Validation::Scored(figures(forward)),
            sized_down_from: None,
            inverse: Some(figures(inverse)),
            tracking: Some(figures(tracking)),
            bound: None,
            set_aside: None,
        }
    }

    fn ranked(mut ranking: Vec<Ranked>) -> (Vec<Ranked>, Option<Picked>) {
        bound_inverses(&mut ranking);
        let picked = rank(&mut ranking);
        (ranking, picked)
    }

    /// The lowest forward error among the admitted candidates: what a forward-only ranking
    /// picks.
    fn forward_best(ranking: &[Ranked]) -> &Ranked {
        ranking
            .iter()
            .filter(|r| r.validation.admitted().is_some())
            .min_by(|a, b| {
                let f = |r: &Ranked| r.validation.figures().unwrap().max_pct;
                f(a).total_cmp(&f(b))
            })
            .unwrap()
    }

    /// The bipolar record's validation figures at 100 kHz (the board admits these five): the
    /// best forward fit, Bouc–Wen + creep, has an inverse 16 × its fit. It is set aside and the
    /// P–I, whose inverse holds, picked; a forward-only ranking picks Bouc–Wen + creep.
    #[test]
    fn the_best_forward_fit_whose_inverse_ratchets_is_not_picked() {
        let (ranking, picked) = ranked(vec![
            scored(ModelKind::BoucWen, true, 0.90, 14.58, 13.55),
            scored(ModelKind::Pi, true, 1.10, 1.81, 1.84),
            scored(ModelKind::Pi, false, 1.30, 1.59, 1.02),
            scored(ModelKind::BoucWen, false, 1.47, 10.71, 11.95),
            scored(ModelKind::Duhem, false, 1.57, 2.28, 1.51),
        ]);
        assert_eq!(forward_best(&ranking).options.model, ModelKind::BoucWen);
        assert_eq!(picked, Some(Picked::Best));
        let pick = &ranking[0];
        assert_eq!(
            (pick.options.model, pick.options.creep),
            (ModelKind::Pi, false)
        );
        assert_eq!(pick.bound, Some(InverseBound::Holds));
        assert!(pick.set_aside.is_none());
        let order: Vec<(ModelKind, bool, Option<InverseBound>)> = ranking
            .iter()
            .map(|r| (r.options.model, r.options.creep, r.bound))
            .collect();
        use InverseBound::*;
        assert_eq!(
            order,
            [
                (ModelKind::Pi, false, Some(Holds)),         // compensated 1.59
                (ModelKind::Pi, true, Some(NoiseFloor)),     // 1.84: 1.81 > 1.5 × 1.10
                (ModelKind::Duhem, false, Some(Holds)),      // 2.28
                (ModelKind::BoucWen, false, Some(Ratchets)), // set aside: 11.95
                (ModelKind::BoucWen, true, Some(Ratchets)),  // set aside: 14.58
            ]
        );
        let bw_creep = &ranking[4];
        assert!(
            bw_creep
                .summary()
                .contains("set aside: inverse max 14.58 %"),
            "{}",
            bw_creep.summary()
        );
        assert!(
            ranking[1].summary().contains("noise floor") && ranking[1].set_aside.is_none(),
            "{}",
            ranking[1].summary()
        );
    }

    /// On noisy data the model that generated it inverts to twice its forward error (P–I data
    /// at 0.5 % noise, as `tests/model_selection.rs` builds it: P–I forward 0.26 %, inverse
    /// 0.54 %), while a model that fits poorly stays within 1.5 × its large forward error
    /// (Duhem: 1.06 % / 0.91 %, tracking 1.07 %). At the record's noise floor the P–I ranks
    /// by its score with those that hold, and is picked.
    #[test]
    fn an_inverse_at_the_noise_floor_ranks_by_its_score() {
        let (ranking, picked) = ranked(vec![
            scored(ModelKind::Duhem, false, 1.06, 0.91, 1.07),
            scored(ModelKind::Pi, false, 0.28, 0.59, 0.07),
        ]);
        assert_eq!(picked, Some(Picked::Best));
        assert_eq!(ranking[0].options.model, ModelKind::Pi);
        assert_eq!(ranking[0].bound, Some(InverseBound::NoiseFloor));
        assert_eq!(ranking[1].bound, Some(InverseBound::Holds));
    }

    /// A ratcheting candidate is ranked after every other, even with the lower compensated
    /// error (here the other's stand-in tracking is worse), and picked only if every candidate
    /// ratchets.
    #[test]
    fn a_ratcheting_inverse_is_set_aside_whatever_its_score() {
        let (ranking, picked) = ranked(vec![
            scored(ModelKind::BoucWen, false, 0.30, 2.00, 0.50),
            scored(ModelKind::Pi, false, 1.00, 1.00, 2.50),
        ]);
        assert_eq!(picked, Some(Picked::Best));
        let order: Vec<ModelKind> = ranking.iter().map(|r| r.options.model).collect();
        assert_eq!(order, [ModelKind::Pi, ModelKind::BoucWen]);
        assert!(ranking[1].set_aside.as_ref().unwrap().contains("6.67 ×"));
        // Alone, it is picked, and says so.
        let (ranking, picked) = ranked(vec![
            scored(ModelKind::BoucWen, false, 0.30, 2.00, 0.50),
            scored(ModelKind::Gpi, false, 0.20, 1.20, 0.50),
        ]);
        assert_eq!(picked, Some(Picked::Best));
        assert_eq!(ranking[0].options.model, ModelKind::Gpi);
        assert_eq!(ranking[0].bound, Some(InverseBound::NoiseFloor));
        assert_eq!(ranking[1].bound, Some(InverseBound::Ratchets));
    }

    /// A special case within the margin of its generalisation is picked for parsimony only if
    /// it ratchets no more than the generalisation.
    #[test]
    fn parsimony_keeps_to_the_bound() {
        let (ranking, picked) = ranked(vec![
            scored(ModelKind::BoucWen, false, 1.00, 1.20, 1.00),
            scored(ModelKind::Duhem, false, 1.10, 1.24, 1.00),
        ]);
        assert_eq!(picked, Some(Picked::Simpler));
        assert_eq!(ranking[0].options.model, ModelKind::Duhem);
        let (ranking, picked) = ranked(vec![
            scored(ModelKind::BoucWen, false, 1.00, 1.20, 2.00),
            scored(ModelKind::Duhem, false, 0.50, 1.90, 1.00),
        ]);
        assert_eq!(ranking[1].bound, Some(InverseBound::Ratchets));
        assert_eq!(picked, Some(Picked::Best));
        assert_eq!(ranking[0].options.model, ModelKind::BoucWen);
    }

    /// Refused and unfitted candidates are never picked; with none admitted there is no pick.
    #[test]
    fn only_admitted_candidates_are_picked() {
        let mut refused = scored(ModelKind::Gpi, false, 0.5, 0.6, 0.5);
        refused.validation = Validation::NotAdmitted {
            figures: *refused.validation.figures().unwrap(),
            why: "too dear".into(),
        };
        let mut unfitted = scored(ModelKind::Duhem, false, 0.5, 0.6, 0.5);
        unfitted.validation = Validation::NotFitted("too few samples".into());
        let (ranking, picked) = ranked(vec![
            refused.clone(),
            unfitted.clone(),
            scored(ModelKind::Pi, false, 1.0, 1.4, 1.0),
        ]);
        assert_eq!(picked, Some(Picked::Best));
        assert_eq!(ranking[0].options.model, ModelKind::Pi);
        assert!(matches!(ranking[2].validation, Validation::NotFitted(_)));
        assert_eq!(ranked(vec![refused, unfitted]).1, None);
    }
}
