//! A stage's identified model as the board runs it: the hysteresis model, the scaling onto
//! the fixed-point ranges, the sensor's sign and its lag — and whole-record runs of it, in the
//! library's fixed point (the code the firmware runs) and in the `f64` reference.
//!
//! Conventions shared by `identify`, `predict` and `compensate`:
//! * the model's output is the *sign-corrected* output: `sensor reading = output_sign × y`;
//!   the scaling's output range is in those units (an inverted sensor needs no `max < min`);
//! * the sensor lags the drive by `sensor_lag_s`: the reading at sample `k` is the model's
//!   output at sample `k − L` (`L` = lag in samples of the record being run);
//! * forward runs start relaxed at the first drive value (P–I: every operator there; Duhem:
//!   on the anhysteretic curve, `y0 = β u0 + δ`; Bouc–Wen: `h = 0`); inverse runs start
//!   relaxed at the first desired output.

use crate::reference;
use twinstack::bouc_wen::{BoucWen, InverseBoucWen};
use twinstack::duhem::{Duhem, InverseDuhem};
use twinstack::fixed_point::{signal_from_f64, signal_to_f64};
use twinstack::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use twinstack::{BoucWenParams, DuhemParams, ParamError, PiParams, Scaling};

/// The hysteresis model of a stage, in physical units. (Built once per command, so the
/// size difference between the variants does not matter.)
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
pub enum Hysteresis {
    /// Prandtl–Ishlinskii.
    Pi(PiParams),
    /// Duhem.
    Duhem(DuhemParams),
    /// Generalised (asymmetric) Bouc–Wen.
    BoucWen(BoucWenParams),
}

/// Everything needed to run a stage's model on a record.
#[derive(Clone, Debug, PartialEq)]
pub struct StageModel {
    /// The hysteresis model (volts in, sign-corrected output units out).
    pub hysteresis: Hysteresis,
    /// Input and (sign-corrected) output ranges onto the normalised Q2.30 signals.
    pub scaling: Scaling,
    /// `+1` or `−1`: the sensor reads `output_sign × y`.
    pub output_sign: f64,
    /// Sensor lag behind the drive, seconds (`≥ 0`).
    pub sensor_lag_s: f64,
}

impl StageModel {
    /// The lag in samples for a record with times `t` (rounded to the median interval).
    pub fn lag_samples(&self, t: &[f64]) -> usize {
        let mut dt: Vec<f64> = t.windows(2).map(|w| w[1] - w[0]).collect();
        dt.sort_by(f64::total_cmp);
        match dt.get(dt.len() / 2) {
            Some(&d) if d > 0.0 => (self.sensor_lag_s / d).round().max(0.0) as usize,
            _ => 0,
        }
    }

    /// How many drive samples in `u` lie outside the input range (the models clamp them).
    pub fn drive_outside_range(&self, u: &[f64]) -> usize {
        let s = &self.scaling;
        u.iter()
            .filter(|&&v| v < s.input_min || v > s.input_max)
            .count()
    }

    /// How many readings in `x` lie outside the output range once sign-corrected (the
    /// compensator clamps them).
    pub fn reading_outside_range(&self, x: &[f64]) -> usize {
        let s = &self.scaling;
        x.iter()
            .map(|&v| self.output_sign * v)
            .filter(|&y| y < s.output_min || y > s.output_max)
            .count()
    }

    /// Checks the library accepts the model for both the observer and the compensator.
    pub fn check(&self) -> Result<(), ParamError> {
        match &self.hysteresis {
            Hysteresis::Pi(p) => {
                PrandtlIshlinskii::new(p, &self.scaling)?;
                InversePrandtlIshlinskii::new(p, &self.scaling)?;
            }
            Hysteresis::Duhem(p) => {
                InverseDuhem::new(p, &self.scaling)?;
            }
            Hysteresis::BoucWen(p) => {
                InverseBoucWen::new(p, &self.scaling)?;
            }
        }
        Ok(())
    }

    fn delay(&self, t: &[f64], y: Vec<f64>) -> Vec<f64> {
        let lag = self.lag_samples(t);
        (0..y.len())
            .map(|k| self.output_sign * y[k.saturating_sub(lag)])
            .collect()
    }

    fn advance(&self, t: &[f64], x: &[f64]) -> Vec<f64> {
        let lag = self.lag_samples(t);
        let last = x.len().saturating_sub(1);
        (0..x.len())
            .map(|k| self.output_sign * x[(k + lag).min(last)])
            .collect()
    }

    /// Forward model on drive `u` (volts) at times `t`, in the library's fixed point:
    /// the sensor reading it predicts at each sample.
    pub fn predict(&self, t: &[f64], u: &[f64]) -> Result<Vec<f64>, ParamError> {
        let s = &self.scaling;
        let u_norm = |v: f64| signal_from_f64(s.input_to_norm(v));
        let y_phys = |q: i32| s.norm_to_output(signal_to_f64(q));
        let u0 = u.first().copied().unwrap_or(0.0);
        let y: Vec<f64> = match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let m = PrandtlIshlinskii::new(p, s)?;
                let mut st = m.state_at_rest(u_norm(u0));
                u.iter()
                    .map(|&v| y_phys(m.step(&mut st, u_norm(v))))
                    .collect()
            }
            Hysteresis::Duhem(p) => {
                let m = Duhem::new(p, s)?;
                let u0 = u0.clamp(s.input_min, s.input_max);
                let y0 = signal_from_f64(s.output_to_norm(p.beta * u0 + p.offset));
                let mut st = m.state_at(u_norm(u0), y0);
                u.iter()
                    .map(|&v| y_phys(m.step(&mut st, u_norm(v))))
                    .collect()
            }
            Hysteresis::BoucWen(p) => {
                let m = BoucWen::new(p, s)?;
                let mut st = m.relaxed(u_norm(u0));
                u.iter()
                    .map(|&v| y_phys(m.step(&mut st, u_norm(v))))
                    .collect()
            }
        };
        Ok(self.delay(t, y))
    }

    /// [`Self::predict`] computed by the `f64` reference models.
    pub fn predict_reference(&self, t: &[f64], u: &[f64]) -> Result<Vec<f64>, ParamError> {
        let s = &self.scaling;
        let u0 = u.first().copied().unwrap_or(0.0);
        let y: Vec<f64> = match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let mut m = reference::PrandtlIshlinskii::new(p, s, u0)?;
                u.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::Duhem(p) => {
                let u0 = u0.clamp(s.input_min, s.input_max);
                let mut m = reference::Duhem::new(p, s, u0, p.beta * u0 + p.offset)?;
                u.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::BoucWen(p) => {
                let mut m = reference::BoucWen::new(p, s, u0)?;
                u.iter().map(|&v| m.step(v)).collect()
            }
        };
        Ok(self.delay(t, y))
    }

    /// Inverse model: the drive (volts) that makes the sensor read `x` at times `t`, in the
    /// library's fixed point. With a sensor lag of `L` samples the drive leads by `L`.
    pub fn compensate(&self, t: &[f64], x: &[f64]) -> Result<Vec<f64>, ParamError> {
        let s = &self.scaling;
        let y_norm = |v: f64| signal_from_f64(s.output_to_norm(v));
        let u_phys = |q: i32| s.norm_to_input(signal_to_f64(q));
        let desired = self.advance(t, x);
        let y0 = desired.first().copied().unwrap_or(0.0);
        Ok(match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let m = InversePrandtlIshlinskii::new(p, s)?;
                let mut st = m.state_at_rest(y_norm(y0));
                desired
                    .iter()
                    .map(|&v| u_phys(m.step(&mut st, y_norm(v))))
                    .collect()
            }
            Hysteresis::Duhem(p) => {
                let m = InverseDuhem::new(p, s)?;
                let y0 = y0.clamp(s.output_min, s.output_max);
                let u0 = ((y0 - p.offset) / p.beta).clamp(s.input_min, s.input_max);
                let mut st = m
                    .model()
                    .state_at(signal_from_f64(s.input_to_norm(u0)), y_norm(y0));
                desired
                    .iter()
                    .map(|&v| u_phys(m.step(&mut st, y_norm(v))))
                    .collect()
            }
            Hysteresis::BoucWen(p) => {
                let m = InverseBoucWen::new(p, s)?;
                let y0 = y0.clamp(s.output_min, s.output_max);
                let u0 = ((y0 - p.offset) / p.k).clamp(s.input_min, s.input_max);
                let mut st = m.model().relaxed(signal_from_f64(s.input_to_norm(u0)));
                desired
                    .iter()
                    .map(|&v| u_phys(m.step(&mut st, y_norm(v))))
                    .collect()
            }
        })
    }

    /// [`Self::compensate`] computed by the `f64` reference models.
    pub fn compensate_reference(&self, t: &[f64], x: &[f64]) -> Result<Vec<f64>, ParamError> {
        let s = &self.scaling;
        let desired = self.advance(t, x);
        let y0 = desired
            .first()
            .copied()
            .unwrap_or(0.0)
            .clamp(s.output_min, s.output_max);
        Ok(match &self.hysteresis {
            Hysteresis::Pi(p) => {
                let c = p.canonical()?;
                let total: f64 = c.weights.iter().sum();
                let mut m =
                    reference::InversePrandtlIshlinskii::new(p, s, (y0 - c.offset) / total)?;
                desired.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::Duhem(p) => {
                let u0 = ((y0 - p.offset) / p.beta).clamp(s.input_min, s.input_max);
                let mut m = reference::InverseDuhem::new(p, s, u0, y0)?;
                desired.iter().map(|&v| m.step(v)).collect()
            }
            Hysteresis::BoucWen(p) => {
                let u0 = ((y0 - p.offset) / p.k).clamp(s.input_min, s.input_max);
                let mut m = reference::InverseBoucWen::new(p, s, u0)?;
                desired.iter().map(|&v| m.step(v)).collect()
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pi_model(sign: f64, lag_s: f64) -> StageModel {
        StageModel {
            hysteresis: Hysteresis::Pi(
                PiParams::new(0.0, 1.0, &[0.0, 20.0, 40.0], &[0.08, 0.03, 0.02]).unwrap(),
            ),
            scaling: Scaling::new(-100.0, 100.0, -15.0, 17.0).unwrap(),
            output_sign: sign,
            sensor_lag_s: lag_s,
        }
    }

    fn record() -> (Vec<f64>, Vec<f64>) {
        let t: Vec<f64> = (0..800).map(|k| k as f64 * 0.01).collect();
        let u = t.iter().map(|&t| 90.0 * (t * 2.0).sin()).collect();
        (t, u)
    }

    #[test]
    fn fixed_point_prediction_tracks_the_f64_reference() {
        let m = pi_model(1.0, 0.0);
        let (t, u) = record();
        let fx = m.predict(&t, &u).unwrap();
        let rf = m.predict_reference(&t, &u).unwrap();
        let worst = fx
            .iter()
            .zip(&rf)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(worst < 1e-5, "{worst}");
    }

    #[test]
    fn sign_and_lag_are_applied_to_the_prediction() {
        let (t, u) = record();
        let plain = pi_model(1.0, 0.0).predict(&t, &u).unwrap();
        let turned = pi_model(-1.0, 0.02).predict(&t, &u).unwrap();
        for k in 2..t.len() {
            assert!((turned[k] + plain[k - 2]).abs() < 1e-12);
        }
    }

    proptest::proptest! {
        /// For any invertible P–I (non-negative weights, `w_1 > 0`), any sign and lag, and any
        /// drive inside the input range, the fixed-point compensator fed the fixed-point
        /// prediction gives back the drive.
        #[test]
        fn compensate_inverts_predict_for_any_invertible_pi(
            w1 in 0.05f64..0.5,
            rest in proptest::collection::vec(0.0f64..0.2, 1..8),
            offset in -3.0f64..3.0,
            negative in proptest::bool::ANY,
            lag in 0usize..4,
            drive in proptest::collection::vec(-100.0f64..100.0, 20..200),
        ) {
            let n = rest.len() + 1;
            let thresholds: Vec<f64> = (0..n).map(|i| 100.0 * i as f64 / n as f64).collect();
            let mut weights = vec![w1];
            weights.extend(&rest);
            let reach = 100.0 * weights.iter().sum::<f64>() + offset.abs() + 1.0;
            let m = StageModel {
                hysteresis: Hysteresis::Pi(PiParams::new(0.0, offset, &thresholds, &weights).unwrap()),
                scaling: Scaling::new(-100.0, 100.0, -reach, reach).unwrap(),
                output_sign: if negative { -1.0 } else { 1.0 },
                sensor_lag_s: lag as f64 * 0.01,
            };
            // Models whose inverse does not fit Q8.24 are refused (tested elsewhere).
            proptest::prop_assume!(m.check().is_ok());
            let t: Vec<f64> = (0..drive.len()).map(|k| k as f64 * 0.01).collect();
            let x = m.predict(&t, &drive).unwrap();
            let back = m.compensate(&t, &x).unwrap();
            for k in 0..drive.len() - lag {
                proptest::prop_assert!((back[k] - drive[k]).abs() < 1e-3, "k {}: {} vs {}", k, back[k], drive[k]);
            }
        }
    }

    #[test]
    fn compensating_the_prediction_returns_the_drive() {
        for sign in [1.0, -1.0] {
            let m = pi_model(sign, 0.02);
            let (t, u) = record();
            let x = m.predict(&t, &u).unwrap();
            let back = m.compensate(&t, &x).unwrap();
            // The last `lag` samples have no future reading to aim at.
            for k in 0..t.len() - 2 {
                assert!(
                    (back[k] - u[k]).abs() < 1e-3,
                    "k {k}: {} vs {}",
                    back[k],
                    u[k]
                );
            }
        }
    }
}
