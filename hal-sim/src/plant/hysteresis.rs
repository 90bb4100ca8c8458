//! The "truth" hysteresis of each stack: a Duhem or P–I model from [`twinstack_identify::reference`],
//! in volts, with an optional skew.
//!
//! Hysteresis sits in series with the stack's electrical port (see the book, docs/src/reference/physics.md): the stack moves as
//! if driven by the effective voltage `e = u − v^h`. The model here produces `e` directly,
//! `e = f(H[u])`, where `H` is a Duhem or P–I operator from volts to volts (slope near 1) and
//! `f` the skew below; `v^h = u − e`.
//!
//! **Skew.** Duhem and P–I loops are point-symmetric about their centre; the first paper's
//! unidirectional loop (its Fig. 3) is not. A memoryless quadratic after the operator,
//!
//! `f(w) = w + s (w − u_min)(w − u_max) / (u_max − u_min)`,  `|s| < 1`,
//!
//! keeps the range's ends fixed, stays monotone, and bends the loop (slope `1 − s` at the
//! bottom of the range, `1 + s` at the top). In the differential configuration the two stacks
//! work at `ū ± v`, and the quadratic terms cancel in `e_l − e_r` to first order: the
//! differential loop comes out nearly symmetric, as in the paper.

use twinstack::{DuhemParams, ParamError, PiParams, Scaling};
use twinstack_identify::reference;

/// Which operator a stack's hysteresis follows (parameters in volts → volts).
// Held by value like the operators it configures: no heap in the simulator's models.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
pub enum HysteresisModel {
    /// No hysteresis: `e = u` (before the skew).
    None,
    /// Duhem, `ẇ = α|u̇|(βu + δ − w) + γu̇` (α per volt, β and γ volts per volt, δ volts).
    Duhem(DuhemParams),
    /// Prandtl–Ishlinskii, `w = a0 u + Σ w_i P_{r_i}[u] + offset` (thresholds in volts).
    PrandtlIshlinskii(PiParams),
}

impl HysteresisModel {
    /// A Duhem stack with a loop about 11 % of the range wide on a full 0–150 V cycle:
    /// `α = 0.03 /V, β = 1, γ = 0.75` (asymptotic half-width `(β − γ)/α ≈ 8.3 V`).
    pub fn default_duhem() -> Self {
        Self::Duhem(DuhemParams {
            alpha: 0.03,
            beta: 1.0,
            gamma: 0.75,
            offset: 0.0,
        })
    }

    /// A P–I stack: 9 operators, thresholds spread uniformly over 0–150 V (the first paper's
    /// choice), weights summing to 1 with the slope rising from 0.6 just after a reversal.
    pub fn default_pi() -> Self {
        let thresholds: [f64; 9] = core::array::from_fn(|i| i as f64 * 150.0 / 9.0);
        let weights = [0.60, 0.12, 0.08, 0.06, 0.05, 0.04, 0.03, 0.01, 0.01];
        // Nine operators, equal lengths, finite and increasing thresholds: cannot fail.
        let params = PiParams::new(0.0, 0.0, &thresholds, &weights)
            .expect("the default P–I parameters are well formed");
        Self::PrandtlIshlinskii(params)
    }
}

/// A stack's hysteresis configuration.
#[derive(Clone, Debug, PartialEq)]
pub struct HysteresisConfig {
    /// The operator.
    pub model: HysteresisModel,
    /// Skew `s`, `|s| < 1` (0: a point-symmetric loop).
    pub skew: f64,
}

impl Default for HysteresisConfig {
    /// The default Duhem stack with a 0.15 skew.
    fn default() -> Self {
        Self {
            model: HysteresisModel::default_duhem(),
            skew: DEFAULT_SKEW,
        }
    }
}

/// Skew of the default stacks: enough to bend the unidirectional loop visibly.
pub const DEFAULT_SKEW: f64 = 0.15;

/// Why a hysteresis configuration was refused.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum HysteresisError {
    /// The operator's parameters are invalid.
    Params(ParamError),
    /// `|skew| ≥ 1` or not finite: `f` would not be monotone.
    SkewOutOfRange(f64),
}

// Inline on purpose: stepped every period, no heap and no indirection.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
enum Operator {
    None,
    Duhem(reference::Duhem),
    PrandtlIshlinskii(reference::PrandtlIshlinskii),
}

/// One stack's hysteresis with its memory: `u` (volts) → effective voltage `e` (volts).
#[derive(Clone, Debug, PartialEq)]
pub struct StackHysteresis {
    operator: Operator,
    skew: f64,
    range: Scaling,
}

impl StackHysteresis {
    /// The hysteresis `config` over the drive range `range` (input and output both in volts),
    /// at rest at drive `u0` (Duhem: on its loop's ascending branch, as the models start,
    /// `reference::Duhem::at_rest`; P–I: operators relaxed at `u0`).
    pub fn new(
        config: &HysteresisConfig,
        range: &Scaling,
        u0: f64,
    ) -> Result<Self, HysteresisError> {
        if !(config.skew.is_finite() && config.skew.abs() < 1.0) {
            return Err(HysteresisError::SkewOutOfRange(config.skew));
        }
        let operator = match &config.model {
            HysteresisModel::None => Operator::None,
            HysteresisModel::Duhem(p) => Operator::Duhem(
                reference::Duhem::at_rest(p, range, u0).map_err(HysteresisError::Params)?,
            ),
            HysteresisModel::PrandtlIshlinskii(p) => Operator::PrandtlIshlinskii(
                reference::PrandtlIshlinskii::new(p, range, u0).map_err(HysteresisError::Params)?,
            ),
        };
        Ok(Self {
            operator,
            skew: config.skew,
            range: *range,
        })
    }

    /// One sample: drive `u` (volts) → effective voltage `e = u − v^h` (volts).
    #[inline]
    pub fn effective_volts(&mut self, u: f64) -> f64 {
        let w = match &mut self.operator {
            Operator::None => u,
            Operator::Duhem(d) => d.step(u),
            Operator::PrandtlIshlinskii(p) => p.step(u),
        };
        let (lo, hi) = (self.range.input_min, self.range.input_max);
        w + self.skew * (w - lo) * (w - hi) / (hi - lo)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn range() -> Scaling {
        Scaling::new(0.0, 150.0, 0.0, 150.0).unwrap()
    }

    #[test]
    fn skew_keeps_the_range_ends_and_refuses_non_monotone_values() {
        let cfg = HysteresisConfig {
            model: HysteresisModel::None,
            skew: 0.5,
        };
        let mut h = StackHysteresis::new(&cfg, &range(), 0.0).unwrap();
        assert_eq!(h.effective_volts(0.0), 0.0);
        assert!((h.effective_volts(150.0) - 150.0).abs() < 1e-12);
        assert!(
            h.effective_volts(75.0) < 75.0,
            "positive skew sags the middle"
        );
        for bad in [1.0, -1.2, f64::NAN] {
            let cfg = HysteresisConfig {
                model: HysteresisModel::None,
                skew: bad,
            };
            assert!(matches!(
                StackHysteresis::new(&cfg, &range(), 0.0),
                Err(HysteresisError::SkewOutOfRange(_))
            ));
        }
    }

    #[test]
    fn invalid_operator_parameters_are_reported() {
        let cfg = HysteresisConfig {
            model: HysteresisModel::Duhem(DuhemParams {
                alpha: -1.0,
                beta: 1.0,
                gamma: 0.5,
                offset: 0.0,
            }),
            skew: 0.0,
        };
        assert_eq!(
            StackHysteresis::new(&cfg, &range(), 0.0),
            Err(HysteresisError::Params(ParamError::DuhemAlphaNotPositive))
        );
    }

    /// A full 0–150–0 V cycle: the descending branch lies above the ascending one (the loop
    /// is traversed counter-clockwise) and its width is in the intended 5–20 % band.
    #[test]
    fn default_models_form_a_counter_clockwise_loop_of_plausible_width() {
        for model in [
            HysteresisModel::default_duhem(),
            HysteresisModel::default_pi(),
        ] {
            let cfg = HysteresisConfig { model, skew: 0.0 };
            let mut h = StackHysteresis::new(&cfg, &range(), 0.0).unwrap();
            let n = 2000;
            let mut up_mid = 0.0;
            for k in 0..=n {
                let e = h.effective_volts(150.0 * k as f64 / n as f64);
                if k == n / 2 {
                    up_mid = e;
                }
            }
            let mut down_mid = 0.0;
            for k in (0..=n).rev() {
                let e = h.effective_volts(150.0 * k as f64 / n as f64);
                if k == n / 2 {
                    down_mid = e;
                }
            }
            let width = (down_mid - up_mid) / 150.0;
            assert!(width > 0.05 && width < 0.2, "{cfg:?}: width {width}");
        }
    }
}
