//! Duhem identification: the integrated least squares of the book's docs/src/reference/models.md, a stability check by
//! simulation, and a refinement on the simulated error.
//!
//! 1. **Integrated least squares.** Summing the discrete model over the samples from `τ0`
//!    gives `y(τ) = c0 + αβ J1 − α J2 + αδ J0 + γ u(τ)` with `J1 = Σ u|Δu|`, `J2 = Σ y|Δu|`,
//!    `J0 = Σ |Δu|` (the measured `y` stands in for the model's), linear in
//!    `θ = (c0, αβ, α, αδ, γ)`. `c0` (the output at `τ0` less `γ u(τ0)`) is fitted rather than
//!    read from one noisy sample. Signals are centred first for conditioning.
//! 2. **Constraint.** If the plain solution is not a valid Duhem model (`α, β, γ ≤ 0`) or its
//!    simulation diverges on the data, it is refitted with `αβ, α, γ ≥ 0` (NNLS) and floored
//!    at a small positive value; the caller is told.
//! 3. **Refinement.** The least-squares fit uses the measured output inside `J2`, so noise and
//!    lag bias it. Starting from it, a simplex search minimises the RMS of the *simulated*
//!    output against the measurement (what `predict` is scored on), over `ln α, ln β, ln γ, δ`
//!    (so the parameters stay positive), on the rows from `steady_from` on: the model's
//!    start (on the anhysteretic curve) is an assumption, and fitting the transient out of it
//!    (the initial loading curve) trades away accuracy on the loops that follow. The refined
//!    model is kept only if it is better on those rows.

use super::least_squares::{LeastSquaresError, NormalEquations};
use super::simplex::minimise;
use super::FitRows;
use crate::reference;
use twinstack::models::params::DuhemParams;
use twinstack::Scaling;

/// What happened on the way to the fitted model (reported to the user).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum DuhemFitPath {
    /// The plain integrated least squares was valid and stable.
    Plain,
    /// The plain solution had a non-positive coefficient; refitted with constraints.
    ConstrainedNotPositive,
    /// The plain solution diverged when simulated; refitted with constraints.
    ConstrainedDiverged,
}

/// A fitted Duhem model.
#[derive(Clone, Debug)]
pub struct DuhemFit {
    /// The integrated-least-squares model (after the constraint, if one was needed).
    pub least_squares: DuhemParams,
    /// How the least-squares model was obtained.
    pub path: DuhemFitPath,
    /// RMS simulated error of the least-squares model over the fit rows, output units.
    pub least_squares_rms: f64,
    /// The final model (refined if that helped).
    pub params: DuhemParams,
    /// RMS simulated error of the final model over the fit rows (all of them), output units.
    pub rms: f64,
    /// Simulated output of the final model over the whole record.
    pub simulated: Vec<f64>,
}

/// Simulates `p` over `u` from rest: `y0 = β u0 + δ` (on the anhysteretic curve), input
/// clamped to `scaling`'s range — the same start `predict` uses.
pub fn simulate(p: &DuhemParams, scaling: &Scaling, u: &[f64]) -> Option<Vec<f64>> {
    let u0 = u.first()?.clamp(scaling.input_min, scaling.input_max);
    let mut m = reference::Duhem::new(p, scaling, u0, p.beta * u0 + p.offset).ok()?;
    Some(u.iter().map(|&v| m.step(v)).collect())
}

fn rms_error(sim: &[f64], y: &[f64], rows: &FitRows) -> f64 {
    let mut s = 0.0;
    let mut n = 0usize;
    for &k in &rows.index {
        let e = sim[k] - y[k + rows.lag];
        s += e * e;
        n += 1;
    }
    if n == 0 || !s.is_finite() {
        f64::INFINITY
    } else {
        (s / n as f64).sqrt()
    }
}

/// Fits a Duhem model of `y` (lag-aligned by `rows.lag`) driven by `u`.
///
/// `rows.index` must be increasing; the integrals run over every sample from its first entry
/// to its last, while only the listed rows are fitted (others, such as rejected outliers,
/// are integrated over but not fitted).
pub fn fit(
    u: &[f64],
    y: &[f64],
    rows: &FitRows,
    scaling: &Scaling,
    refine: bool,
    steady_from: usize,
) -> Result<DuhemFit, LeastSquaresError> {
    let (&first, &last) = match (rows.index.first(), rows.index.last()) {
        (Some(f), Some(l)) => (f, l),
        _ => return Err(LeastSquaresError::NoRows),
    };
    let uc = scaling.input_mid();
    let yc = rows.mean_target(y);
    let lag = rows.lag;
    let mut fitted = vec![false; last + 1];
    for &k in &rows.index {
        fitted[k] = true;
    }
    let mut ne = NormalEquations::new(5);
    let (mut j0, mut j1, mut j2) = (0.0, 0.0, 0.0);
    for k in first..=last {
        if k > first {
            let du = (u[k] - u[k - 1]).abs();
            j0 += du;
            j1 += du * (u[k - 1] - uc);
            j2 += du * (y[k - 1 + lag] - yc);
        }
        if fitted[k] {
            ne.add_row(&[1.0, j1, -j2, j0, u[k] - uc], y[k + lag] - yc, 1.0);
        }
    }
    let from_theta = |t: &[f64]| -> DuhemParams {
        let alpha = t[2];
        let beta = t[1] / alpha;
        let delta_c = t[3] / alpha;
        DuhemParams {
            alpha,
            beta,
            gamma: t[4],
            offset: delta_c + yc - beta * uc,
        }
    };
    let evaluate = |p: &DuhemParams| -> Option<(f64, Vec<f64>)> {
        p.validate().ok()?;
        let sim = simulate(p, scaling, u)?;
        let rms = rms_error(&sim, y, rows);
        rms.is_finite().then_some((rms, sim))
    };
    let y_span = rows.target_span(y).max(f64::MIN_POSITIVE);

    let plain = from_theta(&ne.solve()?);
    let (ls, path, ls_rms, ls_sim) = match (plain.validate(), evaluate(&plain)) {
        (Ok(()), Some((rms, sim))) if rms < 10.0 * y_span => (plain, DuhemFitPath::Plain, rms, sim),
        (result, _) => {
            let path = if result.is_err() {
                DuhemFitPath::ConstrainedNotPositive
            } else {
                DuhemFitPath::ConstrainedDiverged
            };
            let t = ne.solve_constrained(&[false, true, true, false, true])?;
            // Floors: a coefficient NNLS pinned at zero becomes a small positive one.
            let gain = y_span / (2.0 * scaling.input_half_span());
            let alpha = t[2].max(1e-6 / scaling.input_half_span());
            let floored = [
                t[0],
                t[1].max(1e-6 * gain * alpha),
                alpha,
                t[3],
                t[4].max(1e-6 * gain),
            ];
            let p = from_theta(&floored);
            let (rms, sim) = evaluate(&p).ok_or(LeastSquaresError::NotFinite)?;
            (p, path, rms, sim)
        }
    };

    let mut best = (ls, ls_rms, ls_sim);
    let steady = FitRows {
        index: rows
            .index
            .iter()
            .copied()
            .filter(|&k| k >= steady_from)
            .collect(),
        lag: rows.lag,
    };
    if refine && steady.index.len() >= super::MIN_FIT_SAMPLES {
        let ls_steady = rms_error(&best.2, y, &steady);
        let start = [ls.alpha.ln(), ls.beta.ln(), ls.gamma.ln(), ls.offset];
        let cost = |v: &[f64; 4]| -> f64 {
            let p = DuhemParams {
                alpha: v[0].exp(),
                beta: v[1].exp(),
                gamma: v[2].exp(),
                offset: v[3],
            };
            match p.validate().ok().and_then(|_| simulate(&p, scaling, u)) {
                Some(sim) => rms_error(&sim, y, &steady),
                None => f64::INFINITY,
            }
        };
        let steps = [0.3, 0.1, 0.1, 0.05 * y_span];
        let v = minimise(cost, start, steps, 800, 1e-10);
        let p = DuhemParams {
            alpha: v[0].exp(),
            beta: v[1].exp(),
            gamma: v[2].exp(),
            offset: v[3],
        };
        if let Some((rms, sim)) = evaluate(&p) {
            if rms_error(&sim, y, &steady) < ls_steady {
                best = (p, rms, sim);
            }
        }
    }
    Ok(DuhemFit {
        least_squares: ls,
        path,
        least_squares_rms: ls_rms,
        params: best.0,
        rms: best.1,
        simulated: best.2,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn record(p: &DuhemParams, s: &Scaling) -> (Vec<f64>, Vec<f64>) {
        let u: Vec<f64> = (0..3000)
            .map(|k| 60.0 + 60.0 * (k as f64 * 0.005).sin())
            .collect();
        let y = simulate(p, s, &u).unwrap();
        (u, y)
    }

    #[test]
    fn integrated_least_squares_recovers_a_noise_free_model() {
        let s = Scaling::new(0.0, 120.0, -5.0, 25.0).unwrap();
        let truth = DuhemParams {
            alpha: 0.02,
            beta: 0.15,
            gamma: 0.1,
            offset: 1.0,
        };
        let (u, y) = record(&truth, &s);
        let rows = FitRows {
            index: (0..u.len()).collect(),
            lag: 0,
        };
        let f = fit(&u, &y, &rows, &s, false, 0).unwrap();
        assert_eq!(f.path, DuhemFitPath::Plain);
        for (got, want) in [
            (f.params.alpha, truth.alpha),
            (f.params.beta, truth.beta),
            (f.params.gamma, truth.gamma),
        ] {
            assert!((got / want - 1.0).abs() < 0.02, "{:?}", f.params);
        }
        assert!(f.rms < 0.01 * 30.0, "rms {}", f.rms);
    }

    #[test]
    fn a_fit_that_is_not_a_valid_duhem_model_is_constrained_and_says_so() {
        // Output falls while the drive rises: the plain fit has β, γ < 0.
        let s = Scaling::new(0.0, 120.0, -30.0, 5.0).unwrap();
        let u: Vec<f64> = (0..2000)
            .map(|k| 60.0 + 60.0 * (k as f64 * 0.005).sin())
            .collect();
        let y: Vec<f64> = u.iter().map(|v| -0.2 * v).collect();
        let rows = FitRows {
            index: (0..u.len()).collect(),
            lag: 0,
        };
        let f = fit(&u, &y, &rows, &s, true, 0).unwrap();
        assert_eq!(f.path, DuhemFitPath::ConstrainedNotPositive);
        assert!(f.params.validate().is_ok());
        assert!(f.simulated.iter().all(|v| v.is_finite()));
    }
}
