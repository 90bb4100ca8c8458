//! The creep fit alternated with the hysteresis fit ([`with_creep`]): what [`super::identify`]
//! runs when creep is asked for.

use super::least_squares::LeastSquaresError;
use super::{
    creep, rms, FitRows, IdentifyError, CREEP_CONVERGED, CREEP_ITERATIONS, CREEP_PROGRESS,
};
use crate::stage_model::StageModel;
use twinstack::ParamError;
use twinstack_link::measured_data::MeasuredData;

/// A hysteresis fit of a (sign-corrected) target, adding its notes.
pub(super) type FitModel<'a> =
    dyn Fn(&[f64], &mut Vec<String>) -> Result<StageModel, IdentifyError> + 'a;

/// The creep fit alternated with the hysteresis fit: the creep weights on the hysteresis
/// model's output, then the hysteresis refitted on the target with the creep undone (its
/// exact inverse applied to `y`), until the fit RMS settles — an iterate changes it by less
/// than [`CREEP_CONVERGED`] of the previous one's and lowers the lowest before it by less than
/// [`CREEP_PROGRESS`] — or [`CREEP_ITERATIONS`] times; the iterate whose prediction scores the
/// lowest RMS on the fitted rows is kept.
///
/// The split of a slow mode between the model's gain and the creep converges slowly (about
/// ten iterates on a synthetic record), and the fit RMS is not monotone along the way: it can
/// rise for several iterates before it falls (a Duhem + creep on the bipolar record: 1.9 %
/// up to 4.4 % of span, then down to 0.2 %), or descend slowly by less than the settling
/// fraction (0.195 → 0.194 % on the lab stage's excitation recorded at 50 kHz, then down to
/// 0.173 %). A rule that stopped on any small change stopped on that slow descent, four
/// iterates short of the lowest RMS, and the same stage's model then depended on the rate its
/// record was sampled at (held out 1.83 % at 50 kHz against 1.20 % at 10 kHz).
///
/// Where the inverse creep starts: a record that starts at rest (`started_at_rest`) has its
/// stage settled at its first reading, so the inverse's modes start at rest at `y[0]`. A
/// record that starts in the middle of its motion says nothing there about where the stage
/// had settled (the micromanipulator record's first reading is 24 units below the model's
/// output at its first drive value: the stage was still settling from a long rest at 0 V),
/// so the inverse starts where `predict` starts the forward creep, at the hysteresis output
/// of the first sample. Started at the reading instead, a slow mode's inverse carries the
/// difference through the whole window and the hysteresis refit follows it.
#[allow(clippy::too_many_arguments)]
pub(super) fn with_creep(
    first: StageModel,
    data: &MeasuredData,
    y: &[f64],
    rows: &FitRows,
    n_fit: usize,
    started_at_rest: bool,
    modes: usize,
    fit_model: &FitModel<'_>,
    notes: &mut Vec<String>,
) -> Result<StageModel, IdentifyError> {
    let t = &data.t[..n_fit];
    let u = data.u.as_deref().unwrap_or_default();
    let u = &u[..n_fit.min(u.len())];
    let period = data.sample_period();
    let rate = 1.0 / period;
    let taus = creep::time_constants(period, t.last().unwrap_or(&0.0) - t[0], modes);
    let score = |m: &StageModel| -> Result<f64, IdentifyError> {
        let x = m.predict_targets(t, u).map_err(IdentifyError::Params)?;
        // Applied the sign and the lag as the fit pairs them: compare with the target at
        // k + lag.
        Ok(rms(rows.index.iter().map(|&k| {
            m.output_sign * x[k + rows.lag] - y[k + rows.lag]
        })))
    };
    // The model without creep is the iterate to beat: a creep is kept only if it lowers the
    // fit RMS. (A mode as slow as the fit window is nearly collinear with the free gain of
    // the creep fit; on a periodic record the fit can then put weight on it that the model
    // without that gain does not bear out.)
    let without = score(&first)?;
    let mut best: Option<(f64, StageModel)> = Some((without, first.clone()));
    let mut hysteresis = first;
    let mut history = Vec::new();
    for _ in 0..CREEP_ITERATIONS {
        // The hysteresis output itself: no sign, no lag, no creep.
        let bare = StageModel {
            output_sign: 1.0,
            sensor_lag_s: 0.0,
            creep: None,
            ..hysteresis.clone()
        };
        let h = bare
            .predict_reference(t, u)
            .map_err(IdentifyError::Params)?;
        let c = creep::fit(&h, y, rows, &taus, rate)?;
        let candidate = StageModel {
            creep: Some(c.clone()),
            ..hysteresis
        };
        let r = score(&candidate)?;
        // Progress is judged among the iterates (the model without creep may be better
        // than the first few, from which the alternation still descends).
        let lowest = history.iter().copied().fold(f64::INFINITY, f64::min);
        let settled = history.last().is_some_and(|&previous: &f64| {
            (previous - r).abs() <= CREEP_CONVERGED * previous
                && r >= lowest * (1.0 - CREEP_PROGRESS)
        });
        history.push(r);
        if best.as_ref().is_none_or(|(b, _)| r < *b) {
            best = Some((r, candidate));
        }
        if settled {
            break;
        }
        // The target with the creep undone, for the next hysteresis fit (the inverse's start:
        // see above).
        let start = if started_at_rest {
            y[0]
        } else {
            h.first().copied().unwrap_or(y[0])
        };
        let mut inverse =
            crate::reference::Creep::new(&c, rate, start).map_err(IdentifyError::Params)?;
        let corrected: Vec<f64> = y.iter().map(|&v| inverse.inverse_step(v)).collect();
        // A hysteresis fit that fails on the corrected target (a Duhem start the board cannot
        // hold, say) ends the alternation: the best iterate so far stands.
        hysteresis = match fit_model(&corrected, &mut Vec::new()) {
            Ok(h) => h,
            Err(_) => break,
        };
    }
    let (rms_best, mut model) = best.ok_or(IdentifyError::Fit(LeastSquaresError::NoRows))?;
    // A mode the fit gave no weight does nothing (forward and inverse alike) but costs the
    // board's tick on each side: dropped.
    if let Some(c) = model.creep.clone() {
        let kept: Vec<(f64, f64)> = c
            .time_constants_s
            .iter()
            .zip(&c.weights)
            .filter(|(_, &w)| w != 0.0)
            .map(|(&tau, &w)| (tau, w))
            .collect();
        let dropped = c.weights.len() - kept.len();
        if dropped > 0 {
            let (taus, weights): (Vec<f64>, Vec<f64>) = kept.into_iter().unzip();
            model.creep = if weights.is_empty() {
                None
            } else {
                Some(
                    twinstack::models::creep::CreepParams::new(&taus, &weights)
                        .map_err(|e| IdentifyError::Params(ParamError::Creep(e)))?,
                )
            };
            notes.push(format!(
                "creep: {dropped} of its {} modes fitted with no weight, dropped (they cost the board's tick and do nothing)",
                c.weights.len()
            ));
        }
    }
    let span = rows.target_span(y);
    if model.creep.is_none() {
        notes.push(format!(
            "creep: left out, no iterate lowered the fit RMS of the model without it ({:.3} % \
             of span; per iterate {} %)",
            100.0 * without / span,
            history
                .iter()
                .map(|r| format!("{:.3}", 100.0 * r / span))
                .collect::<Vec<_>>()
                .join(" / "),
        ));
    }
    if let Some(c) = &model.creep {
        notes.push(format!(
            "creep: tau {} s, weights {} (fit RMS per iterate {} % of span, kept {:.3} %)",
            c.time_constants_s
                .iter()
                .map(|v| format!("{v:.3e}"))
                .collect::<Vec<_>>()
                .join(", "),
            c.weights
                .iter()
                .map(|v| format!("{v:.4}"))
                .collect::<Vec<_>>()
                .join(", "),
            history
                .iter()
                .map(|r| format!("{:.3}", 100.0 * r / span))
                .collect::<Vec<_>>()
                .join(" / "),
            100.0 * rms_best / span
        ));
    }
    Ok(model)
}
