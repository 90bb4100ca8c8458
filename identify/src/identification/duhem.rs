//! Duhem identification: the integrated least squares of the book's docs/src/reference/models.md, a stability check by
//! simulation, and a refinement on the simulated error.
//!
//! 1. **Integrated least squares.** Summing the discrete model over the samples from `τ0`
//!    gives `y(τ) = c0 + αβ J1 − α J2 + αδ J0 + γ u(τ)` with `J1 = Σ u|Δu|`, `J2 = Σ y|Δu|`,
//!    `J0 = Σ |Δu|` (the measured `y` stands in for the model's), linear in
//!    `θ = (c0, αβ, α, αδ, γ)`. `c0` (the output at `τ0` less `γ u(τ0)`) is fitted rather than
//!    read from one noisy sample. Signals are centred first for conditioning.
//! 2. **Output-error refit.** If the plain solution is not a valid Duhem model (`α, β, γ ≤ 0`)
//!    or its simulation misses the data by more than a tenth of their span (RMS: the
//!    integrated equation is the model's small-step form, and where a record's steps are not
//!    small it can be far off), it is refitted on the *simulated* error instead
//!    ([`output_error_fit`]), and the caller is told. (A refit of the same equation error with
//!    `αβ, α, γ ≥ 0` is no answer: where the constraint pins `α` at 0, `β = (αβ)/α` and
//!    `δ = (αδ)/α` come out as a finite product over a floored `α` — on the simulated lab stage
//!    `α = 1.3e-8 /V`, `β = 1.3e5`, `δ = −9.9e6 µm` — a model that starts on its anhysteretic
//!    curve ten million µm away and, with `α` that small, never relaxes towards the data.)
//! 3. **Refinement.** The least-squares fit uses the measured output inside `J2`, so noise and
//!    lag bias it. Starting from it, a simplex search minimises the RMS of the *simulated*
//!    output against the measurement (what `predict` is scored on), over `ln α, ln β, ln γ, δ`
//!    (so the parameters stay positive; `α` no slower than the output-error grid's, below
//!    which only `αβ` matters and the search could run off to `α → 0`, `β → ∞`), on the
//!    rows from `steady_from` on: the model's
//!    start (at rest on its loop: [`reference::Duhem::at_rest`]) is an assumption, and fitting
//!    the transient out of it trades away accuracy on the loops that follow. The refined
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
    /// The plain solution had a non-positive coefficient; refitted on the simulated error.
    ConstrainedNotPositive,
    /// The plain solution, simulated, missed the data by more than a tenth of their span (RMS);
    /// refitted on the simulated error.
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

/// Simulates `p` over `u` from rest at its first value (on the major loop's ascending
/// branch: [`reference::Duhem::at_rest`]), input clamped to `scaling`'s range — the same start
/// `predict` uses.
pub fn simulate(p: &DuhemParams, scaling: &Scaling, u: &[f64]) -> Option<Vec<f64>> {
    let mut m = reference::Duhem::at_rest(p, scaling, *u.first()?).ok()?;
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

/// Normalised rates `α·U` (`U` the input half-span: e-foldings of the distance to the
/// anhysteretic curve over half the range) that [`output_error_fit`] tries: log-spaced.
pub const ALPHA_GRID: [f64; 2] = [1e-2, 1e3];
/// Points of that grid (about four per decade).
pub const ALPHA_GRID_POINTS: usize = 21;

/// For a given `α`, the Duhem model simulated as [`simulate`] runs it is linear in
/// `(β, δ, γ)`: over each sample's step, with `q_k = 1 − e^{−α|Δu_k|}`, `E_k = 1 − q_k` and
/// `φ_k = q_k/α` set by `α` and the drive alone,
/// `y_k = E_k y_{k−1} + β (u_k − E_k u_{k−1} − s_k φ_k) + δ q_k + γ s_k φ_k`, from the start
/// at rest (on the anhysteretic curve at the range's top, `β u_max + δ`, then the strokes of
/// [`reference::rest_history`] to `u_0`). So `y = β Y_β + δ + γ Y_γ`, each `Y` the same
/// recursion driven by `u` (from `u_max`) or by `s φ` (from 0), the `δ` term staying 1. Returns the normal equations
/// of the simulated error in `(β, c, γ)`, drive centred at `uc` and target at `yc`
/// (`δ = c + yc − β uc`).
fn output_error_equations(
    alpha: f64,
    u: &[f64],
    y: &[f64],
    rows: &FitRows,
    scaling: &Scaling,
    (uc, yc): (f64, f64),
) -> NormalEquations {
    let mut ne = NormalEquations::new(3);
    let Some(&last) = rows.index.last() else {
        return ne;
    };
    let clamp = |v: f64| v.clamp(scaling.input_min, scaling.input_max);
    // The start at rest: on the anhysteretic curve at the range's top, then the rest history
    // to the first drive value (as `simulate`).
    let mut prev = scaling.input_max;
    let (mut y_beta, mut y_gamma) = (prev - uc, 0.0);
    let mut advance = |v: f64| {
        let v = clamp(v);
        let du = v - prev;
        let (q, phi) = reference::relax(alpha, du.abs());
        let s_phi = du.signum() * phi;
        y_beta = (1.0 - q) * y_beta + (v - uc) - (1.0 - q) * (prev - uc) - s_phi;
        y_gamma = (1.0 - q) * y_gamma + s_phi;
        prev = v;
        (y_beta, y_gamma)
    };
    reference::rest_history(scaling, u[0], |v| {
        advance(v);
    });
    let mut next_row = rows.index.iter().copied().peekable();
    for (k, &v) in u.iter().enumerate().take(last + 1) {
        let (y_beta, y_gamma) = advance(v);
        if next_row.next_if_eq(&k).is_some() {
            ne.add_row(&[y_beta, 1.0, y_gamma], y[k + rows.lag] - yc, 1.0);
        }
    }
    ne
}

/// The Duhem model that minimises the RMS of the *simulated* output against `y` over
/// `rows`: for each `α` of [`ALPHA_GRID`] the best `(β, δ, γ)` with `β, γ ≥ 0` is a linear
/// least-squares problem (`output_error_equations`); the best grid point is then refined
/// by a golden-section search on `ln α` between its neighbours. `β` or `γ` pinned at zero is
/// floored at a small positive value (`1e-6` of the data's mean slope). Any Duhem model
/// with `α > 0` simulates bounded (each step moves the distance to the anhysteretic curve a
/// fraction `q < 1` of the way to its target `s(β − γ)/α`), so what this returns does.
pub fn output_error_fit(
    u: &[f64],
    y: &[f64],
    rows: &FitRows,
    scaling: &Scaling,
) -> Result<DuhemParams, LeastSquaresError> {
    if rows.index.is_empty() {
        return Err(LeastSquaresError::NoRows);
    }
    let centre = (scaling.input_mid(), rows.mean_target(y));
    let half = scaling.input_half_span();
    let gain = rows.target_span(y).max(f64::MIN_POSITIVE) / (2.0 * half);
    let at = |ln_alpha: f64| -> Result<(f64, DuhemParams), LeastSquaresError> {
        let alpha = ln_alpha.exp() / half;
        let ne = output_error_equations(alpha, u, y, rows, scaling, centre);
        let t = ne.solve_constrained(&[true, false, true])?;
        let t = [t[0].max(1e-6 * gain), t[1], t[2].max(1e-6 * gain)];
        let sse = ne.residual_sum_of_squares(&t);
        let p = DuhemParams {
            alpha,
            beta: t[0],
            gamma: t[2],
            offset: t[1] + centre.1 - t[0] * centre.0,
        };
        Ok((if sse.is_finite() { sse } else { f64::INFINITY }, p))
    };
    let (lo, hi) = (ALPHA_GRID[0].ln(), ALPHA_GRID[1].ln());
    let step = (hi - lo) / (ALPHA_GRID_POINTS - 1) as f64;
    let mut best = (0usize, f64::INFINITY);
    for i in 0..ALPHA_GRID_POINTS {
        let (sse, _) = at(lo + step * i as f64)?;
        if sse < best.1 {
            best = (i, sse);
        }
    }
    // Golden section on ln α over the best point's neighbours.
    let ratio = 0.5 * (5f64.sqrt() - 1.0);
    let centre_ln = lo + step * best.0 as f64;
    let (mut a, mut b) = (centre_ln - step, centre_ln + step);
    let mut c = b - ratio * (b - a);
    let mut d = a + ratio * (b - a);
    let (mut fc, mut fd) = (at(c)?.0, at(d)?.0);
    for _ in 0..30 {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - ratio * (b - a);
            fc = at(c)?.0;
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + ratio * (b - a);
            fd = at(d)?.0;
        }
    }
    let (sse, p) = at(0.5 * (a + b))?;
    if sse <= best.1 {
        Ok(p)
    } else {
        Ok(at(centre_ln)?.1)
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
        (Ok(()), Some((rms, sim))) if rms < 0.1 * y_span => (plain, DuhemFitPath::Plain, rms, sim),
        (result, _) => {
            let path = if result.is_err() {
                DuhemFitPath::ConstrainedNotPositive
            } else {
                DuhemFitPath::ConstrainedDiverged
            };
            let p = output_error_fit(u, y, rows, scaling)?;
            let (rms, sim) = evaluate(&p).ok_or(LeastSquaresError::NotFinite)?;
            (p, path, rms, sim)
        }
    };

    let mut best = (ls, ls_rms, ls_sim);
    let steady = rows.from_sample(steady_from);
    if refine && steady.index.len() >= super::MIN_FIT_SAMPLES {
        let ls_steady = rms_error(&best.2, y, &steady);
        let start = [ls.alpha.ln(), ls.beta.ln(), ls.gamma.ln(), ls.offset];
        // No slower relaxation than the output-error grid's (α·U ≥ 1e-2): below it only the
        // product αβ matters, and the search can follow that valley to α → 0, β → ∞, a
        // model whose distance to the anhysteretic line no fixed point holds.
        let least_alpha = ALPHA_GRID[0] / scaling.input_half_span();
        let cost = |v: &[f64; 4]| -> f64 {
            let p = DuhemParams {
                alpha: v[0].exp(),
                beta: v[1].exp(),
                gamma: v[2].exp(),
                offset: v[3],
            };
            if p.alpha < least_alpha {
                return f64::INFINITY;
            }
            // Only models the board holds (its fixed point, on this record's ranges).
            match p
                .normalized(scaling)
                .ok()
                .and_then(|_| simulate(&p, scaling, u))
            {
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

    /// The output-error fit minimises the simulated error itself: on a noise-free record of a
    /// Duhem model it finds that model.
    #[test]
    fn the_output_error_fit_recovers_a_noise_free_model() {
        let s = Scaling::new(0.0, 120.0, -5.0, 25.0).unwrap();
        let truth = DuhemParams {
            alpha: 0.03,
            beta: 0.15,
            gamma: 0.08,
            offset: 1.0,
        };
        let (u, y) = record(&truth, &s);
        let rows = FitRows {
            index: (0..u.len()).collect(),
            lag: 0,
        };
        let p = output_error_fit(&u, &y, &rows, &s).unwrap();
        for (got, want) in [
            (p.alpha, truth.alpha),
            (p.beta, truth.beta),
            (p.gamma, truth.gamma),
            (p.offset, truth.offset),
        ] {
            assert!((got / want - 1.0).abs() < 0.01, "{p:?}");
        }
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
