//! The static output map after a Bouc–Wen model (`--output-map`): what the board runs between
//! the model and the creep (`twinstack::models::output_map`, held by the Bouc–Wen model:
//! `drive → H → S → creep`), fitted with the model.
//!
//! A Bouc–Wen output is linear in its state (`k·u + δ + h`), so a static curve after the
//! hysteresis (a flexure's stiffening, a lever, a sensor's curve) is something it follows only
//! by distorting its loop. `S` is the generalised P–I's dead-zone map, centred at the middle
//! of the model's output range, its thresholds where the generalised P–I puts its map's
//! ([`super::gpi::dead_zone_thresholds`]: four a side at [`super::gpi::DEAD_ZONE_FRACTIONS`]
//! of the model output's half range), so only its slopes are unknown, and for a given model
//! output `z` they follow from the target `y` by one linear least-squares solve ([`fit`]): `S`
//! is piecewise linear, `S(z) − c` linear in the slopes, each held at least
//! [`MIN_MAP_SLOPE`] so that `S` is increasing and its inverse, which the compensator runs,
//! stays within the fixed point (the library refuses a map that is not). A free constant
//! beside the slopes takes what the model's offset left; it is moved into the model's offset
//! and the map's centre together (`S(z) + θ` is the map centred at `c + θ` of `z + θ`), so the
//! map keeps `S(c) = c`.
//!
//! A map fitted after a Bouc–Wen fitted without one finds little to take: the model has bent
//! its loop to follow the curve. So the model is refined with its map (`refine_bouc_wen`):
//! the Bouc–Wen refinement's simplex from the fitted model, each trial's map solved for by
//! least squares on its output (variable projection), scored on the rows after the drive has
//! seen both extremes (on the Bouc–Wen-class lab stage: slopes 0.99 … 0.80 against the
//! flexure's 1 … 0.89, fit RMS 0.368 → 0.253 % of span; `twinstack identify --model bouc-wen
//! --output-map --fit-until 1.9` on what `twinstack lab-stage --hysteresis bouc-wen
//! --write-excitation FILE` writes).
//!
//! The map is fitted, and kept only if it lowers the RMS of the model's output against the
//! target, over the fit rows after the drive has seen both extremes (before them the model's
//! state still carries the start it was guessed from, and a map fitted there bends to that
//! start), and only if the board builds it on the model's scaling; the output range is
//! widened where the map's output leaves it (the compensator clamps a desired output to the
//! range before the map's inverse). With creep, the creep is fitted after the map (the board
//! runs it after the map), alternating with the model and its map (the `alternation` module):
//! each later step refines the last step's model and map on the target with the creep undone,
//! rather than fitting the Bouc–Wen afresh from its Duhem starts (which lands elsewhere at
//! each step: on the lab stage 23 steps whose fit RMS wandered between 0.19 and 0.29 % of span,
//! against 10 steps descending to 0.19 %, in a fifth of the time).

use super::bouc_wen;
use super::gpi::dead_zone_thresholds;
use super::least_squares::{LeastSquaresError, NormalEquations};
use super::{rms, FitRows, IdentifyError, OUTPUT_MARGIN};
use crate::stage_model::{Hysteresis, StageModel};
use twinstack::models::output_map::{DeadZoneParams, OutputMap};
use twinstack::{BoucWenParams, ParamError, Scaling};

/// The least slope a fitted map's segment is given: its inverse's gain is at most 4, so that
/// the inverse map stays well within the fixed point and the compensator does not magnify
/// the sensor's noise by more than that.
pub const MIN_MAP_SLOPE: f64 = 0.25;

/// A map fitted to a model's output.
#[derive(Clone, Debug, PartialEq)]
pub struct MapFit {
    /// The map, its centre moved by `shift`: `S` of the model's output `z + shift`.
    pub map: DeadZoneParams,
    /// What the model's offset is to move by (output units).
    pub shift: f64,
    /// RMS of `y − z` over the rows: the model without the map.
    pub rms_without: f64,
    /// RMS of `y − S(z + shift)` over the rows.
    pub rms: f64,
}

/// The segments of a map with `thresholds` (increasing, relative to the centre, negative
/// ones first): segment 0 is the central one (between the innermost thresholds), then the
/// segments above the centre outward, then those below it outward.
struct Segments {
    /// Thresholds above the centre, outward.
    above: Vec<f64>,
    /// Thresholds below the centre, outward.
    below: Vec<f64>,
}

impl Segments {
    fn of(thresholds: &[f64]) -> Self {
        Self {
            above: thresholds.iter().filter(|&&d| d > 0.0).copied().collect(),
            below: thresholds
                .iter()
                .rev()
                .filter(|&&d| d < 0.0)
                .copied()
                .collect(),
        }
    }

    /// How far `x` (relative to the centre) runs through each segment, signed, so that the
    /// map is `c + Σ σ_s φ_s(x)` with `σ_s` the segments' slopes.
    fn lengths(&self, x: f64, out: &mut [f64]) {
        let (above, below) = (&self.above, &self.below);
        let inner_lo = below.first().copied().unwrap_or(f64::NEG_INFINITY);
        let inner_hi = above.first().copied().unwrap_or(f64::INFINITY);
        out[0] = x.clamp(inner_lo, inner_hi);
        for (i, &d) in above.iter().enumerate() {
            let next = above.get(i + 1).copied().unwrap_or(f64::INFINITY);
            out[1 + i] = (x.min(next) - d).max(0.0);
        }
        for (i, &d) in below.iter().enumerate() {
            let next = below.get(i + 1).copied().unwrap_or(f64::NEG_INFINITY);
            out[1 + above.len() + i] = (x.max(next) - d).min(0.0);
        }
    }
}

/// The dead-zone map (centre `centre`) whose segments have the slopes `sigma` (in
/// [`Segments`]' order).
fn map_of_slopes(
    centre: f64,
    thresholds: &[f64],
    sigma: &[f64],
) -> Result<DeadZoneParams, ParamError> {
    let above = thresholds.iter().filter(|&&d| d > 0.0).count();
    let below = thresholds.len() - above;
    // Weights in the thresholds' order: below the centre outermost first.
    let mut weights = vec![0.0; thresholds.len()];
    for i in 0..above {
        weights[below + i] = sigma[1 + i] - sigma[i];
    }
    for i in 0..below {
        let inner = if i == 0 {
            sigma[0]
        } else {
            sigma[1 + above + i - 1]
        };
        weights[below - 1 - i] = sigma[1 + above + i] - inner;
    }
    DeadZoneParams::new(centre, sigma[0], thresholds, &weights)
}

/// Fits `y[k + lag] ≈ S(z[k]) ` over `rows` (see the module doc), the map centred at
/// `centre`, its thresholds at the fixed fractions of `z`'s half range over the rows.
pub fn fit(z: &[f64], y: &[f64], rows: &FitRows, centre: f64) -> Result<MapFit, LeastSquaresError> {
    let (lo, hi) = rows
        .index
        .iter()
        .map(|&k| z[k])
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(v), h.max(v))
        });
    let half = 0.5 * (hi - lo);
    if !(half.is_finite() && half > 0.0 && centre.is_finite()) {
        return Err(LeastSquaresError::NotFinite);
    }
    let thresholds = dead_zone_thresholds(half);
    let layout = Segments::of(&thresholds);
    let segments = thresholds.len() + 1;
    // Unknowns: each segment's slope above the floor (≥ 0), then the constant θ.
    let mut ne = NormalEquations::new(segments + 1);
    let mut a = vec![0.0; segments + 1];
    for &k in &rows.index {
        layout.lengths(z[k] - centre, &mut a[..segments]);
        a[segments] = 1.0;
        let floor: f64 = MIN_MAP_SLOPE * a[..segments].iter().sum::<f64>();
        ne.add_row(&a, y[k + rows.lag] - centre - floor, 1.0);
    }
    let mut constrained = vec![true; segments + 1];
    constrained[segments] = false;
    let theta = ne.solve_constrained(&constrained)?;
    let sigma: Vec<f64> = theta[..segments]
        .iter()
        .map(|s| s + MIN_MAP_SLOPE)
        .collect();
    let shift = theta[segments];
    let map = map_of_slopes(centre + shift, &thresholds, &sigma)
        .map_err(|_| LeastSquaresError::NotFinite)?;
    let over_rows =
        |f: &dyn Fn(f64) -> f64| rms(rows.index.iter().map(|&k| y[k + rows.lag] - f(z[k])));
    let rms_without = over_rows(&|z| z);
    let mapped = over_rows(&|z| map.apply(z + shift));
    if !mapped.is_finite() {
        return Err(LeastSquaresError::NotFinite);
    }
    Ok(MapFit {
        map,
        shift,
        rms_without,
        rms: mapped,
    })
}

/// The record a map is fitted on: the fit window's times `t` and drive `u`, the rows fitted,
/// the first row after the drive has seen both extremes (where a model's refinement is scored,
/// as the Duhem and Bouc–Wen refinements are), and whether to refine.
pub(super) struct Record<'a> {
    /// Times of the fit window.
    pub t: &'a [f64],
    /// Drive over the fit window.
    pub u: &'a [f64],
    /// The rows fitted.
    pub rows: &'a FitRows,
    /// First sample after the drive has seen both extremes.
    pub steady_from: usize,
    /// Refine a Bouc–Wen model with its map on the simulated error.
    pub refine: bool,
}

/// `model` (a Bouc–Wen, without creep or map) with the output map fitted to the
/// (sign-corrected) target `y` over the record's rows — a Bouc–Wen's parameters refined with
/// the map on the simulated error (`refine_bouc_wen`) — or `model` as it is where the map
/// does not lower the fit RMS or the board would not build it; the notes say which.
pub(super) fn with_map(
    model: StageModel,
    record: &Record<'_>,
    y: &[f64],
    notes: &mut Vec<String>,
) -> Result<StageModel, IdentifyError> {
    // Fitted and judged on the rows after the drive has seen both extremes, as the model's
    // refinement is: before them the model's state still carries the start it was guessed
    // from, and a map fitted there bends to that start (on the bipolar record, a map fitted on
    // every row lowered the fit RMS 1.17 → 0.99 % of span and held out at 2.02 %, against
    // the model alone's 1.36 %).
    let rows = &bouc_wen::steady_rows(record.rows, record.steady_from);
    // Where too few rows follow both extremes, every fit row (`steady_rows`' fallback).
    let over = if rows.index.len() < record.rows.index.len() {
        "after the drive has seen both extremes"
    } else {
        "over every fit row"
    };
    let centre = model.scaling.output_mid();
    let z = bare_output(&model, record)?;
    let span = record.rows.target_span(y);
    let pct = |v: f64| 100.0 * v / span;
    let f = match fit(&z, y, rows, centre) {
        Ok(f) => f,
        Err(e) => {
            notes.push(format!("output map: not fitted ({e}): left out"));
            return Ok(model);
        }
    };
    let rms_without = f.rms_without;
    // The Bouc–Wen refined with its map (see the module doc).
    let (model, z, f, refined) = match refine_bouc_wen(&model, record, y, centre, &f) {
        Some((m, z, f)) => (m, z, f, true),
        None => (model, z, f, false),
    };
    if f.rms >= rms_without {
        notes.push(format!(
            "output map: left out, it did not lower the fit RMS {over} ({:.3} % of span without it, {:.3} % with it)",
            pct(rms_without),
            pct(f.rms)
        ));
        return Ok(model);
    }
    let mapped = match shifted(&model, &f, &z) {
        Ok(m) => m,
        Err(e) => {
            notes.push(format!(
                "output map: left out, the board would not run it ({e})"
            ));
            return Ok(model);
        }
    };
    notes.push(format!(
        "output map: kept, fit RMS {over} {:.3} % of span against {:.3} % without it{} (slopes {}, the model's offset moved by {:.4})",
        pct(f.rms),
        pct(rms_without),
        if refined {
            "; the Bouc-Wen refined with it on the simulated error"
        } else {
            ""
        },
        slopes(&f.map)
            .iter()
            .map(|s| format!("{s:.3}"))
            .collect::<Vec<_>>()
            .join(", "),
        f.shift
    ));
    Ok(mapped)
}

/// The model's own output over the record: no sign, no lag, no creep, no map.
fn bare_output(model: &StageModel, record: &Record<'_>) -> Result<Vec<f64>, IdentifyError> {
    StageModel {
        output_sign: 1.0,
        sensor_lag_s: 0.0,
        creep: None,
        output_map: None,
        ..model.clone()
    }
    .predict_reference(record.t, record.u)
    .map_err(IdentifyError::Params)
}

/// A Bouc–Wen `model` refined with its map (`fitted`, on its output) on the simulated error:
/// the Bouc–Wen refinement's simplex ([`bouc_wen::refine_on`]) from the model, every trial's
/// map fitted to its output by least squares ([`fit`]), the RMS over the rows after the drive
/// has seen both extremes; the model, its output and its map's fit where that lowers the RMS
/// there, else `None` (also for another model, or without refinement).
fn refine_bouc_wen(
    model: &StageModel,
    record: &Record<'_>,
    y: &[f64],
    centre: f64,
    fitted: &MapFit,
) -> Option<(StageModel, Vec<f64>, MapFit)> {
    let Hysteresis::BoucWen(start) = &model.hysteresis else {
        return None;
    };
    if !record.refine {
        return None;
    }
    let rows = record.rows;
    let steady = bouc_wen::steady_rows(rows, record.steady_from);
    let s = &model.scaling;
    let trial = |p: &BoucWenParams| -> Option<(Vec<f64>, MapFit)> {
        if !bouc_wen::held(p, s) {
            return None;
        }
        let z = bouc_wen::simulate(p, s, record.u)?;
        let f = fit(&z, y, &steady, centre).ok()?;
        Some((z, f))
    };
    let at_start = trial(start)?.1.rms;
    let cost = |p: &BoucWenParams| trial(p).map_or(f64::INFINITY, |(_, f)| f.rms);
    let p = bouc_wen::refine_on(
        start,
        rows.target_span(y),
        bouc_wen::REFINE_EVALUATIONS,
        cost,
    );
    let (z, on_steady) = trial(&p)?;
    if on_steady.rms >= at_start {
        return None;
    }
    // Its map as fitted on the steady rows; the output range as the refined model needs.
    let f = on_steady;
    if f.rms >= fitted.rms {
        return None;
    }
    let half = super::bouc_wen_half_span(&p, s.input_half_span()).max(s.output_half_span());
    let mid = s.output_mid();
    let scaling = Scaling::new(s.input_min, s.input_max, mid - half, mid + half).ok()?;
    Some((
        StageModel {
            hysteresis: Hysteresis::BoucWen(p),
            scaling,
            ..model.clone()
        },
        z,
        f,
    ))
}

/// The map's segments' slopes from its lowest to its highest.
fn slopes(map: &DeadZoneParams) -> Vec<f64> {
    let below: Vec<usize> = (0..map.thresholds.len())
        .filter(|&j| map.thresholds[j] < 0.0)
        .collect();
    let mut out = Vec::new();
    // Below the centre, outermost first: the central slope less the inner weights.
    let mut s = map.linear;
    let mut lower = Vec::new();
    for &j in below.iter().rev() {
        s += map.weights[j];
        lower.push(s);
    }
    out.extend(lower.into_iter().rev());
    let mut s = map.linear;
    out.push(s);
    for j in (0..map.thresholds.len()).filter(|&j| map.thresholds[j] > 0.0) {
        s += map.weights[j];
        out.push(s);
    }
    out
}

/// `model` with the fitted map: its offset moved by the fit's shift, its output range moved
/// with it and widened to hold the map's output (`z` the model's output before the shift),
/// checked as the board checks it.
fn shifted(model: &StageModel, f: &MapFit, z: &[f64]) -> Result<StageModel, ParamError> {
    let mut hysteresis = model.hysteresis.clone();
    match &mut hysteresis {
        Hysteresis::BoucWen(p) => p.offset += f.shift,
        // Refused by the options before any fit: the board takes a map after a Bouc–Wen only.
        Hysteresis::Pi(_) | Hysteresis::GeneralisedPi(_) | Hysteresis::Duhem(_) => {
            return Err(ParamError::NotFinite)
        }
    }
    let s = &model.scaling;
    let (lo, hi) = z
        .iter()
        .map(|&v| f.map.apply(v + f.shift))
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(l, h), v| {
            (l.min(v), h.max(v))
        });
    let margin = OUTPUT_MARGIN * (hi - lo);
    let scaling = Scaling::new(
        s.input_min,
        s.input_max,
        (s.output_min + f.shift).min(lo - margin),
        (s.output_max + f.shift).max(hi + margin),
    )?;
    let mapped = StageModel {
        hysteresis,
        scaling,
        output_map: Some(f.map.clone()),
        ..model.clone()
    };
    OutputMap::new(&f.map, &mapped.scaling)?;
    mapped.check()?;
    Ok(mapped)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A map built from its slopes runs through each segment at its slope.
    #[test]
    fn a_map_of_slopes_has_those_slopes() {
        let thresholds = dead_zone_thresholds(10.0);
        let sigma = [1.0, 0.9, 0.8, 0.7, 0.6, 1.1, 1.2, 1.3, 1.4];
        let map = map_of_slopes(3.0, &thresholds, &sigma).unwrap();
        map.validate().unwrap();
        assert_eq!(
            slopes(&map),
            vec![1.4, 1.3, 1.2, 1.1, 1.0, 0.9, 0.8, 0.7, 0.6]
        );
        let mut lengths = [0.0; 9];
        let layout = Segments::of(&thresholds);
        for x in [-12.0, -7.0, -0.5, 0.0, 2.0, 6.0, 9.0, 15.0] {
            layout.lengths(x, &mut lengths);
            let through: f64 = lengths.iter().zip(&sigma).map(|(l, s)| l * s).sum();
            assert!((map.apply(3.0 + x) - 3.0 - through).abs() < 1e-12, "{x}");
        }
    }

    /// A known map after a known output is recovered, shift and all.
    #[test]
    fn a_known_map_is_recovered_from_its_output() {
        // Triangles between 10 and 70: z's half range is 30 about 40.
        let z: Vec<f64> = (0..3000)
            .map(|k| 10.0 + 60.0 * ((k % 600) as f64 / 300.0 - 1.0).abs())
            .collect();
        let thresholds = dead_zone_thresholds(30.0);
        let sigma = [1.0, 0.95, 0.85, 0.7, 0.5, 0.97, 0.9, 0.8, 0.6];
        let truth = map_of_slopes(40.5, &thresholds, &sigma).unwrap();
        let y: Vec<f64> = z.iter().map(|&v| truth.apply(v + 0.5)).collect();
        let rows = FitRows {
            index: (0..z.len()).collect(),
            lag: 0,
        };
        let f = fit(&z, &y, &rows, 40.0).unwrap();
        assert!((f.shift - 0.5).abs() < 1e-9, "{}", f.shift);
        assert!(f.rms < 1e-9 && f.rms_without > 0.1, "{f:?}");
        for (got, want) in slopes(&f.map).iter().zip(slopes(&truth)) {
            assert!((got - want).abs() < 1e-9, "{:?}", slopes(&f.map));
        }
    }
}
