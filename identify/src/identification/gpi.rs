//! Generalised (asymmetric) P–I identification: Kuhnen's linear trick.
//!
//! The model is `y = S[z]`, `z = PI[u]`, with `S` a monotone dead-zone map. Its inverse map is
//! again a dead-zone superposition, `S⁻¹[y] = c + (y − c) + Σ_j h_j S_{e_j}(y − c)` (with
//! `h_0 = 1` fixed: the P–I's weights carry the scale), and applied to the **measured** output
//! it turns the model into an equation that is linear in every unknown:
//!
//! ```text
//! (y − c) = Σ_i w_i P_{r_i}[u] − Σ_j h_j S_{e_j}(y − c) + θ
//! ```
//!
//! so `(w, h, θ)` come from one least-squares solve (the P–I weights non-negative, as for the
//! P–I, so its inverse exists; the `h_j` free) on the rows the P–I fit uses (same lag, same
//! outlier screening). The thresholds `e_j` are spread over the measured output:
//! [`DEAD_ZONES_PER_SIDE`] above and as many below its centre `c`, at
//! [`DEAD_ZONE_FRACTIONS`] of its half range. A dead zone whose fitted `h_j` would make `S⁻¹`
//! fall is dropped and the rest refitted. `S = (S⁻¹)⁻¹` then follows in closed form
//! ([`DeadZoneParams::inverse`]).
//!
//! The equation error weighs the residual in `z` (the P–I's output), not in `y`: a short
//! refinement ([`refine`], Nelder–Mead over the forward map's gains and the P–I's offset, the
//! P–I's weights and every threshold kept) then minimises the simulated output error, and is
//! kept only if it is lower on the fitted rows.

use super::least_squares::{LeastSquaresError, NormalEquations};
use super::simplex::minimise;
use super::FitRows;
use twinstack::models::generalised_pi::{DeadZoneParams, GpiParams};
use twinstack::models::params::PiParams;

/// Dead zones of the fitted map on each side of its centre: four, the eight the board's map
/// holds ([`twinstack::models::generalised_pi::MAX_DEAD_ZONES`]).
pub const DEAD_ZONES_PER_SIDE: usize = 4;
/// Where the dead zones sit, as fractions of the measured output's half range from its centre:
/// one within 15 % of each end, where branches saturate. Against three a side at 0.25, 0.5 and
/// 0.75, the lab stage's worst tracking error fell on every one of its variants but one
/// (`twinstack lab-stage --variants`: 0.78 → 0.66 % on the default stage, 2.52 → 2.15 % with
/// a strong top saturation, 1.30 → 1.03 % with a stiff flexure; see the book,
/// results/lab-stage.md).
pub const DEAD_ZONE_FRACTIONS: [f64; DEAD_ZONES_PER_SIDE] = [0.15, 0.4, 0.65, 0.85];

/// A fitted generalised P–I and its output over the record.
#[derive(Clone, Debug)]
pub struct GpiFit {
    /// The model (volts in, sign-corrected output units out).
    pub params: GpiParams,
    /// The P–I part's output `z` at every sample (output units).
    pub pi_output: Vec<f64>,
    /// The model's output `y = S[z]` at every sample (output units).
    pub output: Vec<f64>,
    /// RMS output error over the fitted rows of the equation-error fit.
    pub least_squares_rms: f64,
    /// RMS output error over the fitted rows of the model returned (refined or not).
    pub rms: f64,
    /// Whether the refinement on the simulated error was kept.
    pub refined: bool,
    /// Dead zones dropped because they made the map non-invertible.
    pub dropped: usize,
}

/// The thresholds of a fitted dead-zone map whose input spans `half` either side of its
/// centre: [`DEAD_ZONE_FRACTIONS`] of it below the centre (outermost first) and above it,
/// increasing — the generalised P–I's inverse map's, and the output map's after a Duhem or
/// Bouc–Wen model ([`super::output_map`]).
pub fn dead_zone_thresholds(half: f64) -> Vec<f64> {
    DEAD_ZONE_FRACTIONS
        .iter()
        .rev()
        .map(|f| -f * half)
        .chain(DEAD_ZONE_FRACTIONS.iter().map(|f| f * half))
        .collect()
}

/// The one-sided dead-zone operator (`d ≠ 0`).
pub(super) fn dead_zone(x: f64, d: f64) -> f64 {
    if d > 0.0 {
        (x - d).max(0.0)
    } else {
        (x - d).min(0.0)
    }
}

/// The P–I's output with weights `w` and offset: `offset + Σ w_i P_i` from centred columns.
fn pi_output(columns: &[Vec<f64>], weights: &[f64], u_centre: f64, offset: f64) -> Vec<f64> {
    let n = columns.first().map_or(0, Vec::len);
    let total: f64 = weights.iter().sum();
    (0..n)
        .map(|k| {
            offset
                + u_centre * total
                + weights
                    .iter()
                    .zip(columns)
                    .map(|(w, c)| w * c[k])
                    .sum::<f64>()
        })
        .collect()
}

fn rms_error(y: &[f64], model: &[f64], rows: &FitRows) -> f64 {
    let n = rows.index.len().max(1) as f64;
    let s: f64 = rows
        .index
        .iter()
        .map(|&k| (y[k + rows.lag] - model[k]).powi(2))
        .sum();
    (s / n).sqrt()
}

/// Fits a generalised P–I to `y` over `rows` (see the module doc): P–I weights `≥ 0` with
/// `w_1 ≥ min_first_weight`, `columns` from [`super::pi::operator_outputs`] with the same
/// `thresholds` and `u_centre`. `refine`: run the simulated-error refinement.
pub fn fit(
    columns: &[Vec<f64>],
    thresholds: &[f64],
    u_centre: f64,
    y: &[f64],
    rows: &FitRows,
    min_first_weight: f64,
    refine_output_error: bool,
) -> Result<GpiFit, LeastSquaresError> {
    let (lo, hi) = rows
        .index
        .iter()
        .map(|&k| y[k + rows.lag])
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(v), h.max(v))
        });
    let centre = 0.5 * (lo + hi);
    let half = 0.5 * (hi - lo);
    if !(half.is_finite() && half > 0.0) {
        return Err(LeastSquaresError::NotFinite);
    }
    let mut e = dead_zone_thresholds(half);
    let mut dropped = 0;
    let n = columns.len();
    let (weights, offset, inverse_map) = loop {
        let m = e.len();
        let mut ne = NormalEquations::new(n + m + 1);
        let mut a = vec![0.0; n + m + 1];
        for &k in &rows.index {
            let x = y[k + rows.lag] - centre;
            for (i, c) in columns.iter().enumerate() {
                a[i] = c[k];
            }
            for (j, &d) in e.iter().enumerate() {
                a[n + j] = -dead_zone(x, d);
            }
            a[n + m] = 1.0;
            // w_1 = min_first_weight + w'_1 with w'_1 ≥ 0.
            ne.add_row(&a, x - min_first_weight * columns[0][k], 1.0);
        }
        let mut constrained = vec![false; n + m + 1];
        constrained[..n].fill(true);
        let theta = ne.solve_constrained(&constrained)?;
        let mut weights = theta[..n].to_vec();
        weights[0] += min_first_weight;
        let h = &theta[n..n + m];
        let inverse_map =
            DeadZoneParams::new(centre, 1.0, &e, h).map_err(|_| LeastSquaresError::NotFinite)?;
        match inverse_map.validate() {
            Ok(()) => {
                // z = c + θ + Σ w_i (P_i − u_centre)
                let offset = centre + theta[n + m] - u_centre * weights.iter().sum::<f64>();
                break (weights, offset, inverse_map);
            }
            Err(twinstack::ParamError::DeadZoneSlopeNotPositive { dead_zone }) if m > 0 => {
                e.remove(dead_zone - 1);
                dropped += 1;
            }
            Err(_) => return Err(LeastSquaresError::NotFinite),
        }
    };
    let map = inverse_map
        .inverse()
        .map_err(|_| LeastSquaresError::NotFinite)?;
    let pi = PiParams::new(0.0, offset, thresholds, &weights)
        .map_err(|_| LeastSquaresError::NotFinite)?;
    let z = pi_output(columns, &weights, u_centre, offset);
    let output: Vec<f64> = z.iter().map(|&v| map.apply(v)).collect();
    let least_squares_rms = rms_error(y, &output, rows);
    let mut result = GpiFit {
        params: GpiParams {
            pi,
            dead_zones: map,
        },
        pi_output: z,
        output,
        least_squares_rms,
        rms: least_squares_rms,
        refined: false,
        dropped,
    };
    if refine_output_error {
        refine(&mut result, y, rows);
    }
    Ok(result)
}

/// Nelder–Mead over the forward map's gains `g_0 … g_m` and a shift of the P–I's offset,
/// minimising the simulated output error over `rows`; kept only if lower.
pub fn refine(fit: &mut GpiFit, y: &[f64], rows: &FitRows) {
    const N: usize = 2 * DEAD_ZONES_PER_SIDE + 2;
    let map = &fit.params.dead_zones;
    let m = map.thresholds.len().min(N - 2);
    let mut start = [0.0; N];
    start[0] = map.linear;
    start[1..=m].copy_from_slice(&map.weights[..m]);
    let candidate = |p: &[f64; N]| -> Option<DeadZoneParams> {
        let d = DeadZoneParams::new(map.centre, p[0], &map.thresholds[..m], &p[1..=m]).ok()?;
        d.validate().ok()?;
        d.inverse().ok()?;
        Some(d)
    };
    let z = &fit.pi_output;
    let cost = |p: &[f64; N]| -> f64 {
        let Some(d) = candidate(p) else {
            return f64::INFINITY;
        };
        let s: f64 = rows
            .index
            .iter()
            .map(|&k| (y[k + rows.lag] - d.apply(z[k] + p[N - 1])).powi(2))
            .sum();
        (s / rows.index.len().max(1) as f64).sqrt()
    };
    let span = (0.5 * (fit.params.dead_zones.thresholds.len() as f64)).max(1.0);
    let mut steps = [0.05; N];
    steps[N - 1] = 0.01 * fit.rms.max(1e-9) * span;
    let best = minimise(cost, start, steps, 3000, 1e-10);
    let best_cost = cost(&best);
    if best_cost < fit.rms {
        if let Some(d) = candidate(&best) {
            fit.params.pi.offset += best[N - 1];
            fit.pi_output.iter_mut().for_each(|v| *v += best[N - 1]);
            fit.output = fit.pi_output.iter().map(|&v| d.apply(v)).collect();
            fit.params.dead_zones = d;
            fit.rms = best_cost;
            fit.refined = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::identification::pi::operator_outputs;

    /// A known asymmetric model is recovered from its own output (no noise).
    #[test]
    fn a_known_generalised_pi_is_recovered() {
        let u: Vec<f64> = (0..4000)
            .map(|k| 60.0 + 55.0 * (k as f64 * 0.006).sin() * (1.0 - k as f64 / 8000.0))
            .collect();
        let r = [0.0, 15.0, 30.0, 45.0];
        let w = [0.3, 0.1, 0.05, 0.05];
        let cols = operator_outputs(&u, &r, 60.0, (0.0, 120.0));
        let truth_pi = pi_output(&cols, &w, 60.0, 1.0);
        let (lo, hi) = truth_pi
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), &v| {
                (l.min(v), h.max(v))
            });
        // S⁻¹ has its dead zones where the fit puts them: at fixed fractions of the half
        // range of y = S[z] around its centre, which depend on S; iterate to the fixed point.
        let h = [0.2, 0.1, 0.07, 0.05, -0.05, -0.08, -0.1, -0.15];
        let (mut cy, mut hy) = (0.5 * (lo + hi), 0.5 * (hi - lo));
        let mut map = DeadZoneParams::identity();
        for _ in 0..200 {
            let e = dead_zone_thresholds(hy);
            map = DeadZoneParams::new(cy, 1.0, &e, &h)
                .unwrap()
                .inverse()
                .unwrap();
            let (a, b) = (map.apply(lo), map.apply(hi));
            (cy, hy) = (0.5 * (a + b), 0.5 * (b - a));
        }
        let truth = GpiParams {
            pi: PiParams::new(0.0, 1.0, &r, &w).unwrap(),
            dead_zones: map.clone(),
        };
        let y: Vec<f64> = truth_pi.iter().map(|&z| map.apply(z)).collect();
        let rows = FitRows {
            index: (0..u.len()).collect(),
            lag: 0,
        };
        let f = fit(&cols, &r, 60.0, &y, &rows, 0.0, false).unwrap();
        assert_eq!(f.dropped, 0);
        assert!(f.rms < 1e-6, "rms {}", f.rms);
        for (got, want) in f.params.pi.weights.iter().zip(&truth.pi.weights) {
            assert!((got - want).abs() < 1e-6, "{:?}", f.params.pi.weights);
        }
        for (got, want) in f
            .params
            .dead_zones
            .weights
            .iter()
            .zip(&truth.dead_zones.weights)
        {
            assert!((got - want).abs() < 1e-6, "{:?}", f.params.dead_zones);
        }
    }
}
