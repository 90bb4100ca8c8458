//! Creep identification: the weights of log-spaced first-order modes behind a fitted
//! hysteresis model.
//!
//! With the time constants fixed, the creep operator (`twinstack::models::creep`) is linear in its
//! weights: `x = h + Σ_k c_k (L_k[h] − h)`, `h` the hysteresis model's output and `L_k` the
//! first-order lag of mode `k` at the data's sample period (the operator's own
//! discretisation, at rest at `h[0]`, its modes taking turns where the operator's do). So the
//! weights are one non-negative least-squares problem on `x − h`; `Σ c_k ≤ 0.9` (the
//! library's bound) is then enforced by scaling the weights down when the unconstrained-sum
//! solution exceeds it.
//!
//! Two free columns join the creep's: `h` itself and a constant. A hysteresis model fitted
//! without creep has absorbed the slow modes into its gain and offset (a mode slower than
//! the record's holds looks like a smaller gain), so `x − h` is not a pure creep of `h`; with
//! a free gain and offset the weights still come out, and the alternation in
//! [`super::identify`] then refits the model on the target with the creep undone. The free
//! coefficients are not part of the result.
//!
//! [`time_constants`] picks the modes for a record: log-spaced from [`FIRST_TAU_SAMPLES`]
//! sample periods up to the fit window's length, capped at [`MAX_TAU_S`].

use super::least_squares::{LeastSquaresError, NormalEquations};
use super::FitRows;
use twinstack::models::creep::{CreepParams, MAX_WEIGHT_SUM};

/// Modes fitted by default.
pub const MODES: usize = 4;
/// The shortest time constant, in sample periods of the record …
pub const FIRST_TAU_SAMPLES: f64 = 10.0;
/// … and at least this, seconds: faster modes fit sensor lag, amplifier dynamics or a
/// resonance rather than creep, and their inverse amplifies the sensor's noise.
pub const FIRST_TAU_MIN_S: f64 = 0.01;
/// The longest time constant picked, seconds.
pub const MAX_TAU_S: f64 = 100.0;

/// `modes` log-spaced time constants (s) for a record sampled every `sample_period` seconds
/// whose fit window lasts `window_s` seconds: from [`FIRST_TAU_SAMPLES`] periods (at least
/// [`FIRST_TAU_MIN_S`]) up to
/// `min(window_s, MAX_TAU_S)` (at least a decade above the first).
pub fn time_constants(sample_period: f64, window_s: f64, modes: usize) -> Vec<f64> {
    let first = (FIRST_TAU_SAMPLES * sample_period).max(FIRST_TAU_MIN_S);
    let last = window_s.min(MAX_TAU_S).max(10.0 * first);
    let n = modes.max(1);
    if n == 1 {
        return vec![first];
    }
    (0..n)
        .map(|k| first * (last / first).powf(k as f64 / (n - 1) as f64))
        .collect()
}

/// Which samples a mode updates on: every one, or, where the modes take turns
/// (`twinstack::models::creep::takes_turns`), mode `mode` of `of` on every `of`-th from its own.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Updates {
    /// Every sample.
    Every,
    /// Taking turns.
    Turn {
        /// The mode, 0-based: it updates on samples `mode`, `mode + of`, …
        mode: usize,
        /// The number of modes.
        of: usize,
    },
}

/// First-order lag of `h` with time constant `tau` at `rate_hz`, at rest at `h[0]`, with the
/// creep operator's discretisation (`z ← a z + b h`, `b = −expm1(−T/τ)`, `T` the mode's
/// update period: a sample, or `of` samples taking turns, holding between its updates).
pub fn lag(h: &[f64], tau: f64, rate_hz: f64, updates: Updates) -> Vec<f64> {
    let (period, phase) = match updates {
        Updates::Every => (1, 0),
        Updates::Turn { mode, of } => (of.max(1), mode),
    };
    let b = -(-(period as f64) / (tau * rate_hz)).exp_m1();
    let a = 1.0 - b;
    let mut z = h.first().copied().unwrap_or(0.0);
    h.iter()
        .enumerate()
        .map(|(k, &v)| {
            if k % period == phase {
                z = a * z + b * v;
            }
            z
        })
        .collect()
}

/// Fits the weights of modes with time constants `taus` (s) so that the creep of `h` (the
/// hysteresis model's output at every sample) matches the target `y[k + rows.lag]` on
/// `rows`, at `rate_hz`. Weights are non-negative and sum to at most 0.9.
pub fn fit(
    h: &[f64],
    y: &[f64],
    rows: &FitRows,
    taus: &[f64],
    rate_hz: f64,
) -> Result<CreepParams, LeastSquaresError> {
    let turns = twinstack::models::creep::takes_turns(taus, rate_hz);
    let columns: Vec<Vec<f64>> = taus
        .iter()
        .enumerate()
        .map(|(mode, &tau)| {
            let updates = if turns {
                Updates::Turn {
                    mode,
                    of: taus.len(),
                }
            } else {
                Updates::Every
            };
            lag(h, tau, rate_hz, updates)
                .iter()
                .zip(h)
                .map(|(l, v)| l - v)
                .collect()
        })
        .collect();
    let n = columns.len();
    let h_mean =
        rows.index.iter().filter_map(|&k| h.get(k)).sum::<f64>() / rows.index.len().max(1) as f64;
    let mut ne = NormalEquations::new(n + 2);
    let mut a = vec![0.0; n + 2];
    for &k in &rows.index {
        let (Some(&target), Some(&hk)) = (y.get(k + rows.lag), h.get(k)) else {
            continue;
        };
        for (ai, c) in a.iter_mut().zip(&columns) {
            *ai = c[k];
        }
        // The free gain (on h about its mean) and offset.
        a[n] = hk - h_mean;
        a[n + 1] = 1.0;
        ne.add_row(&a, target - hk, 1.0);
    }
    let mut constrained = vec![true; n + 2];
    constrained[n] = false;
    constrained[n + 1] = false;
    let mut weights = ne.solve_constrained(&constrained)?;
    weights.truncate(n);
    for w in weights.iter_mut() {
        *w = w.max(0.0);
    }
    let sum: f64 = weights.iter().sum();
    if sum > MAX_WEIGHT_SUM {
        for w in weights.iter_mut() {
            *w *= MAX_WEIGHT_SUM / sum * (1.0 - 1e-12);
        }
    }
    CreepParams::new(taus, &weights).map_err(|_| LeastSquaresError::NotFinite)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference;

    #[test]
    fn time_constants_are_log_spaced_from_ten_samples_to_the_window() {
        let t = time_constants(1e-3, 16.0, 4);
        assert_eq!(t.len(), 4);
        assert!((t[0] - 0.01).abs() < 1e-15 && (t[3] - 16.0).abs() < 1e-12);
        assert!((t[1] / t[0] - t[2] / t[1]).abs() < 1e-9);
        assert!((time_constants(1e-3, 1e4, 4)[3] - MAX_TAU_S).abs() < 1e-12);
        // A window shorter than a decade above the first mode still spans a decade.
        assert!((time_constants(1e-3, 0.02, 2)[1] - 0.1).abs() < 1e-12);
    }

    #[test]
    fn known_weights_are_recovered_from_the_creep_of_a_signal() {
        // At 1 kHz the modes update every sample; at 10 kHz they take turns, and the fit's
        // columns take them as the operator does.
        for rate in [1000.0, 10_000.0] {
            known_weights_are_recovered_at(rate);
        }
    }

    fn known_weights_are_recovered_at(rate: f64) {
        assert_eq!(
            twinstack::models::creep::takes_turns(&[0.01, 0.1, 1.0, 10.0], rate),
            rate > 1000.0
        );
        let h: Vec<f64> = (0..(20.0 * rate) as usize)
            .map(|k| {
                let t = k as f64 / rate;
                (t * 0.7).sin() * 3.0 + if (t as usize) % 4 < 2 { 1.0 } else { -1.0 }
            })
            .collect();
        let taus = [0.01, 0.1, 1.0, 10.0];
        let truth = CreepParams::new(&taus, &[0.02, 0.0, 0.05, 0.03]).unwrap();
        let mut c = reference::Creep::new(&truth, rate, h[0]).unwrap();
        let x: Vec<f64> = h.iter().map(|&v| c.step(v)).collect();
        let rows = FitRows {
            index: (0..h.len()).collect(),
            lag: 0,
        };
        let got = fit(&h, &x, &rows, &taus, rate).unwrap();
        for (g, w) in got.weights.iter().zip(&truth.weights) {
            assert!((g - w).abs() < 1e-6, "{:?}", got.weights);
        }
        // A model that absorbed part of the creep into its gain and offset: the weights, as
        // fractions of the scaled model's output, still come out.
        let scaled: Vec<f64> = h.iter().map(|v| 0.9 * v + 0.3).collect();
        let got = fit(&scaled, &x, &rows, &taus, rate).unwrap();
        for (g, w) in got.weights.iter().zip(&truth.weights) {
            assert!((g - w / 0.9).abs() < 1e-6, "{:?}", got.weights);
        }
        // A target with more creep than the bound allows is scaled to the bound.
        let big: Vec<f64> = h.iter().zip(&x).map(|(h, x)| h + 20.0 * (x - h)).collect();
        let got = fit(&h, &big, &rows, &taus, rate).unwrap();
        let sum: f64 = got.weights.iter().sum();
        assert!(sum <= MAX_WEIGHT_SUM && sum > 0.89, "{sum}");
        assert!(got.check(rate).is_ok());
    }
}
