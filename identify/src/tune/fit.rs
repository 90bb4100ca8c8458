//! Fitting the measured response with a low-order model: a DC gain, one resonance (frequency
//! and damping) and the loop's delay in whole ticks, discretised exactly as the tick sees it
//! ([`LinearPlant::resonance`]).
//!
//! For each delay of 0…3 ticks, Nelder–Mead minimises the squared complex-log error
//! `Σ |ln(P(f)/H(f))|²` (log-magnitude and phase weighted alike: 1 rad ≙ 8.7 dB) over
//! `ln gain, ln f_r, ln ζ`, from the largest measured response (the resonance), the
//! low-frequency gain and the peak's height (`ζ ≈ gain / (2 |H|max)`); the delay with the
//! smallest error wins.

use super::loop_model::{LinearPlant, C64};
use super::measure::FrequencyPoint;

/// The fitted model and how well it matches.
#[derive(Clone, Debug, PartialEq)]
pub struct Fit {
    /// The model.
    pub plant: LinearPlant,
    /// RMS magnitude error, dB.
    pub rms_db: f64,
    /// RMS phase error, degrees.
    pub rms_deg: f64,
}

fn log_error(model: C64, measured: C64) -> (f64, f64) {
    let r = model.over(measured);
    (r.abs().ln(), r.arg())
}

fn cost(points: &[FrequencyPoint], plant: &LinearPlant) -> f64 {
    points
        .iter()
        .map(|p| {
            let (m, a) = log_error(plant.response(p.frequency_hz), p.response);
            m * m + a * a
        })
        .sum()
}

fn model(v: &[f64; 3], delay: usize, rate: f64) -> Option<LinearPlant> {
    let (g, f, z) = (v[0].exp(), v[1].exp(), v[2].exp());
    (g.is_finite() && f > 0.0 && f < 0.4999 * rate && z > 1e-5 && z < 2.0)
        .then(|| LinearPlant::resonance(g, f, z, delay, rate))
}

#[allow(clippy::needless_range_loop)] // three coordinates, indexed in step
/// Nelder–Mead on `f` from `x0` with initial steps `step`, a bounded number of iterations.
fn nelder_mead(f: impl Fn(&[f64; 3]) -> f64, x0: [f64; 3], step: [f64; 3]) -> ([f64; 3], f64) {
    let mut s: Vec<([f64; 3], f64)> = (0..4)
        .map(|i| {
            let mut x = x0;
            if i > 0 {
                x[i - 1] += step[i - 1];
            }
            (x, f(&x))
        })
        .collect();
    for _ in 0..600 {
        s.sort_by(|a, b| a.1.total_cmp(&b.1));
        if (s[3].1 - s[0].1).abs() <= 1e-12 * (1.0 + s[0].1.abs()) {
            break;
        }
        let mut c = [0.0; 3];
        for p in &s[..3] {
            for k in 0..3 {
                c[k] += p.0[k] / 3.0;
            }
        }
        let along = |t: f64| {
            let mut x = [0.0; 3];
            for k in 0..3 {
                x[k] = c[k] + t * (s[3].0[k] - c[k]);
            }
            x
        };
        let r = along(-1.0);
        let fr = f(&r);
        if fr < s[0].1 {
            let e = along(-2.0);
            let fe = f(&e);
            s[3] = if fe < fr { (e, fe) } else { (r, fr) };
        } else if fr < s[2].1 {
            s[3] = (r, fr);
        } else {
            let k = along(0.5);
            let fk = f(&k);
            if fk < s[3].1 {
                s[3] = (k, fk);
            } else {
                let best = s[0].0;
                for p in s.iter_mut().skip(1) {
                    for k in 0..3 {
                        p.0[k] = best[k] + 0.5 * (p.0[k] - best[k]);
                    }
                    p.1 = f(&p.0);
                }
            }
        }
    }
    s.sort_by(|a, b| a.1.total_cmp(&b.1));
    s[0]
}

/// Fits `points` (at least four) measured at `rate` Hz; `None` with fewer points or no finite
/// fit.
///
/// ```
/// use twinstack_identify::tune::fit::fit;
/// use twinstack_identify::tune::loop_model::LinearPlant;
/// use twinstack_identify::tune::measure::FrequencyPoint;
/// let truth = LinearPlant::resonance(0.8, 21_800.0, 0.017, 1, 50_000.0);
/// let points: Vec<FrequencyPoint> = [300.0, 3e3, 1e4, 1.8e4, 2.1e4, 2.18e4, 2.25e4]
///     .iter()
///     .map(|&f| FrequencyPoint { frequency_hz: f, response: truth.response(f),
///                                drive_volts: 1.0, sensor_amplitude: 1.0 })
///     .collect();
/// let fitted = fit(&points, 50_000.0).unwrap();
/// assert!((fitted.plant.resonance_hz / 21_800.0 - 1.0).abs() < 1e-4);
/// assert_eq!(fitted.plant.delay, 1);
/// ```
pub fn fit(points: &[FrequencyPoint], rate: f64) -> Option<Fit> {
    if points.len() < 4 {
        return None;
    }
    let peak = points
        .iter()
        .max_by(|a, b| a.response.abs().total_cmp(&b.response.abs()))?;
    let lowest = points
        .iter()
        .min_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz))?;
    let g0 = lowest.response.abs();
    let z0 = (g0 / (2.0 * peak.response.abs())).clamp(1e-3, 0.5);
    let x0 = [g0.ln(), peak.frequency_hz.ln(), z0.ln()];
    let mut best: Option<(f64, LinearPlant)> = None;
    for delay in 0..=3 {
        let f = |v: &[f64; 3]| model(v, delay, rate).map_or(f64::INFINITY, |p| cost(points, &p));
        let (x, c) = nelder_mead(f, x0, [0.1, 0.03, 0.5]);
        // Restart once from the result (Nelder–Mead stalls on long valleys).
        let (x, c2) = nelder_mead(f, x, [0.05, 0.01, 0.2]);
        let c = c.min(c2);
        if let Some(p) = model(&x, delay, rate) {
            if c.is_finite() && best.as_ref().is_none_or(|b| c < b.0) {
                best = Some((c, p));
            }
        }
    }
    let (_, plant) = best?;
    let n = points.len() as f64;
    let (mut sm, mut sa) = (0.0, 0.0);
    for p in points {
        let (m, a) = log_error(plant.response(p.frequency_hz), p.response);
        sm += m * m;
        sa += a * a;
    }
    Some(Fit {
        rms_db: 20.0 / std::f64::consts::LN_10 * (sm / n).sqrt(),
        rms_deg: (sa / n).sqrt().to_degrees(),
        plant,
    })
}
