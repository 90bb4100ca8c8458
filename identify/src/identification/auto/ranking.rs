//! The ranking of `--model auto`'s candidates from their validation figures alone: the
//! inverse's bound against its fit and the record's noise floor ([`InverseBound`]), the
//! order and the pick with its parsimony ([`rank`]). See the parent module's documentation
//! for what the figures are and why they rank this way.

use super::{Ranked, Validation};

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
/// [`identify_auto_admitting`](super::identify_auto_admitting) does from the validation
/// figures). `None` if no candidate is admitted.
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
    // without creep or without its output map, or several — wins unless the pick beats it by
    // the margin; the simplest such.
    let best_score = best.compensated();
    let special = best.options.model.special_case();
    let (creep, map) = (best.options.creep, best.options.output_map);
    let model = Some(best.options.model);
    let simpler_forms = [
        (special, false, false),
        (special, creep, false),
        (model, false, false),
        (model, creep, false),
        (model, false, map),
    ];
    let simpler = simpler_forms
        .iter()
        .filter(|&&(m, c, o)| m.is_some() && (m, c, o) != (model, creep, map))
        .find_map(|&(m, creep, map)| {
            ranking.iter().position(|r| {
                Some(r.options.model) == m
                    && r.options.creep == creep
                    && r.options.output_map == map
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

/// Sets each candidate's [`Ranked::bound`] from its inverse and forward max errors and the best
/// inverse of all, and, for an admitted one whose inverse does not hold, why
/// ([`Ranked::set_aside`]) for an admitted one that ratchets.
pub(super) fn bound_inverses(ranking: &mut [Ranked]) {
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
    use super::super::{IdentifyOptions, Ranked, Validation};
    use super::*;
    use crate::identification::score::ErrorFigures;
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

    /// An output map is a generalisation too: Bouc–Wen + map + creep is picked over
    /// Bouc–Wen + creep only where it beats it by the margin, else the model without the map.
    #[test]
    fn parsimony_weighs_the_output_map() {
        let with_map = |forward, inverse, tracking| {
            let mut r = scored(ModelKind::BoucWen, true, forward, inverse, tracking);
            r.options.output_map = true;
            r.label = r.options.model_label();
            r
        };
        let (ranking, picked) = ranked(vec![
            with_map(0.80, 0.85, 0.80),
            scored(ModelKind::BoucWen, true, 1.10, 1.20, 1.20),
        ]);
        assert_eq!(picked, Some(Picked::Best));
        assert!(ranking[0].options.output_map, "{}", ranking[0].label);
        assert_eq!(ranking[0].label, "Bouc-Wen + output map + creep");
        let (ranking, picked) = ranked(vec![
            with_map(0.80, 1.15, 0.80),
            scored(ModelKind::BoucWen, true, 1.10, 1.18, 1.18),
        ]);
        assert_eq!(picked, Some(Picked::Simpler));
        assert!(!ranking[0].options.output_map && ranking[0].options.creep);
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
