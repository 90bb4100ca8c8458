//! Prandtl–Ishlinskii identification: play-operator regressors and non-negative weights.
//!
//! With the thresholds fixed, the P–I output `y = c + Σ w_i P_{r_i}[u]` is linear in the
//! weights and the offset, so the fit is one least-squares problem over the play operators'
//! outputs. The weights are kept non-negative (NNLS): then every partial sum `S_i` is
//! positive as soon as `w_1 > 0`, and the analytic inverse the compensator runs exists
//! (see the book, docs/src/reference/models.md). A lower bound on `w_1` keeps the inverse's first weight `1/w_1` inside the
//! fixed-point format when the data alone would let it shrink towards zero.
//!
//! The operators start relaxed at the record's first drive value and run over the whole
//! record, exactly as `predict` runs them, so the fitted model and the checked one agree.

use super::least_squares::{LeastSquaresError, NormalEquations};
use super::FitRows;
use crate::reference::play;
use twinstack::models::params::{PiParams, Thresholds};

/// How thresholds are spread (the CLI's `--thresholds`).
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ThresholdSpread {
    /// `r_i = (i − 1)/N · A`.
    Uniform,
    /// Geometric progression, denser near zero (ratio [`GEOMETRIC_RATIO`]).
    Geometric,
}

/// Common ratio of the geometric threshold spread.
pub const GEOMETRIC_RATIO: f64 = 1.15;

impl ThresholdSpread {
    /// The library's threshold generator for this spread.
    pub fn generator(self) -> Thresholds {
        match self {
            ThresholdSpread::Uniform => Thresholds::Uniform,
            ThresholdSpread::Geometric => Thresholds::Geometric {
                ratio: GEOMETRIC_RATIO,
            },
        }
    }
}

/// Outputs of the play operators over a record: `columns[i][k] = P_{r_i}[u](k)`, the
/// operators at rest at `u[0]` on the ascending branch of the model's input range
/// `range = (lo, hi)` (volts; the drive went to `hi`, down to `lo`, then up to `u[0]`: the
/// library's `state_at_rest`); shifted by `centre` (the play operator commutes with shifts,
/// and centred columns make the normal equations better conditioned).
pub fn operator_outputs(
    u: &[f64],
    thresholds: &[f64],
    centre: f64,
    range: (f64, f64),
) -> Vec<Vec<f64>> {
    let (lo, hi) = (range.0 - centre, range.1 - centre);
    let u0 = u.first().copied().unwrap_or(0.0) - centre;
    thresholds
        .iter()
        .map(|&r| {
            let mut p = play(u0, r, (lo + r).min((hi - r).max(lo)));
            u.iter()
                .map(|&v| {
                    p = play(v - centre, r, p);
                    p
                })
                .collect()
        })
        .collect()
}

/// A fitted P–I model and how well it fits.
#[derive(Clone, Debug)]
pub struct PiFit {
    /// The model, volts in, (sign-corrected) output units out; `a0 = 0`, the linear term is
    /// operator 1's weight (its threshold is zero).
    pub params: PiParams,
    /// Residuals `y − model` on every sample of the record where a target exists
    /// (`k + lag < y.len()`), `NaN` elsewhere.
    pub residuals: Vec<f64>,
}

/// Fits weights (≥ 0, `w_1 ≥ min_first_weight`) and a free offset to `y` over `rows`.
///
/// `columns` come from [`operator_outputs`] with the same `thresholds` and `u_centre`.
pub fn fit(
    columns: &[Vec<f64>],
    thresholds: &[f64],
    u_centre: f64,
    y: &[f64],
    rows: &FitRows,
    min_first_weight: f64,
) -> Result<PiFit, LeastSquaresError> {
    let n = columns.len();
    let y_centre = rows.mean_target(y);
    let mut ne = NormalEquations::new(n + 1);
    let mut a = vec![0.0; n + 1];
    for &k in &rows.index {
        for (i, c) in columns.iter().enumerate() {
            a[i] = c[k];
        }
        a[n] = 1.0;
        // w_1 = min_first_weight + w'_1 with w'_1 ≥ 0.
        let target = y[k + rows.lag] - y_centre - min_first_weight * columns[0][k];
        ne.add_row(&a, target, 1.0);
    }
    let mut constrained = vec![true; n + 1];
    constrained[n] = false;
    let theta = ne.solve_constrained(&constrained)?;
    let mut weights: Vec<f64> = theta[..n].to_vec();
    weights[0] += min_first_weight;
    let total: f64 = weights.iter().sum();
    let offset = theta[n] + y_centre - u_centre * total;
    let params = PiParams::new(0.0, offset, thresholds, &weights)
        .map_err(|_| LeastSquaresError::NotFinite)?;
    let residuals = (0..y.len())
        .map(|k| {
            if k + rows.lag >= y.len() {
                return f64::NAN;
            }
            let model: f64 = offset
                + u_centre * total
                + weights
                    .iter()
                    .zip(columns.iter())
                    .map(|(w, c)| w * c[k])
                    .sum::<f64>();
            y[k + rows.lag] - model
        })
        .collect();
    Ok(PiFit { params, residuals })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn operator_outputs_start_on_the_ascending_branch_of_the_range() {
        // At the bottom of the range (0 V, centred −1) the operator r = 1 sits r above the
        // input (the drive came down to it); raised to 3 V (centred 2) it sits r below.
        let cols = operator_outputs(&[0.0], &[0.0, 1.0], 1.0, (0.0, 4.0));
        assert_eq!((cols[0][0], cols[1][0]), (-1.0, 0.0));
        let cols = operator_outputs(&[3.0], &[0.0, 1.0], 1.0, (0.0, 4.0));
        assert_eq!((cols[0][0], cols[1][0]), (2.0, 1.0));
        // The virgin start (every operator at the input) would give 2.0 there.
    }

    #[test]
    fn operator_outputs_follow_the_play_rule() {
        let u = [1.0, 3.0, 2.0, 0.0];
        let cols = operator_outputs(&u, &[0.0, 1.0], 1.0, (0.0, 2.0));
        assert_eq!(cols[0], vec![0.0, 2.0, 1.0, -1.0]);
        // r = 1: held at 0 until pushed to 3−1−1 = 1, held, then dragged to 0−1+1 = 0.
        assert_eq!(cols[1], vec![0.0, 1.0, 1.0, 0.0]);
    }

    #[test]
    fn weights_of_a_known_model_are_recovered_and_stay_non_negative() {
        let u: Vec<f64> = (0..2000)
            .map(|k| 100.0 * (k as f64 * 0.01).sin() * (1.0 - k as f64 / 4000.0))
            .collect();
        let r = [0.0, 20.0, 40.0, 60.0];
        let w_true = [0.05, 0.02, 0.0, 0.01];
        let cols = operator_outputs(&u, &r, 0.0, (-1.0, 1.0));
        let y: Vec<f64> = (0..u.len())
            .map(|k| 3.0 + (0..4).map(|i| w_true[i] * cols[i][k]).sum::<f64>())
            .collect();
        let rows = FitRows {
            index: (0..u.len()).collect(),
            lag: 0,
        };
        let f = fit(&cols, &r, 0.0, &y, &rows, 0.0).unwrap();
        for (got, want) in f.params.weights.iter().zip(w_true) {
            assert!((got - want).abs() < 1e-6, "{:?}", f.params.weights);
        }
        assert!((f.params.offset - 3.0).abs() < 1e-6);
        assert!(f.residuals.iter().all(|r| r.abs() < 1e-6));
        // A first-weight floor above the truth is honoured.
        let f = fit(&cols, &r, 0.0, &y, &rows, 0.08).unwrap();
        assert!(f.params.weights[0] >= 0.08 - 1e-12);
        assert!(f.params.weights.iter().all(|&w| w >= 0.0));
    }
}
