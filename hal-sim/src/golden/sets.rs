//! The vector sets: which compensator, observer, feedback and drive each one runs.
//!
//! The models are the micromanipulator record's (`data/micromanipulator-unipolar-
//! 3v6-1hz.csv`, 0…3.6 V, sensor units), identified by `hal-sim identify` and committed in
//! `tests/golden/params/` (see the README's "Golden vectors" for the commands), so the vectors
//! do not depend on refitting. Every set shares one scaling: the models' common input range and
//! the union of their output ranges.
//!
//! | set | compensator | observer | feedback | drive |
//! |---|---|---|---|---|
//! | `bypass` | none | none | off | differential, 16-bit DAC |
//! | `none-duhem-closed` | none | Duhem | PI, 12-bit ADC | differential, 12-bit DAC |
//! | `ipi8-pi-open` | inverse P–I, N = 8 | P–I, N = 8 | off | differential, 16-bit DAC |
//! | `ipi16-pi-closed` | inverse P–I, N = 16 | P–I, N = 16 | PI, 16-bit ADC, drift limit 2 % | differential, 16-bit DAC |
//! | `ipi32-duhem-closed` | inverse P–I, N = 32 | Duhem | PI, 16-bit ADC | unidirectional, 12-bit DAC |
//! | `iduhem-duhem-closed` | inverse Duhem | Duhem | PI, 16-bit ADC | differential, 16-bit DAC |
//! | `iduhem-pi-open` | inverse Duhem | P–I, N = 16 | off | unidirectional, 16-bit DAC |

use crate::param_file::ParamFile;
use crate::stage_model::Hysteresis;
use anyhow::{bail, Context};
use std::path::Path;
use twinstack::drive::{Configuration, DriveSettings, SafeState};
use twinstack::golden::{CompensatorChoice, ObserverChoice, Recipe};
use twinstack::settings::{FeedbackSettings, SensorSettings};
use twinstack::{DuhemParams, PiParams, Scaling};

/// The parameter files, relative to the golden directory.
pub const PARAM_FILES: [&str; 4] = [
    "params/micromanipulator-pi8.json",
    "params/micromanipulator-pi16.json",
    "params/micromanipulator-pi32.json",
    "params/micromanipulator-duhem.json",
];

/// Which model the sensor model ("the stage") follows while a set is generated: deliberately
/// not the controller's own, so the feedback has an error to correct. (Built once per set:
/// the variants' size difference does not matter.)
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
pub enum Truth {
    /// The identified P–I model (N = 16).
    Pi(PiParams),
    /// The identified Duhem model.
    Duhem(DuhemParams),
}

/// One vector set's definition.
#[derive(Clone, Debug, PartialEq)]
pub struct SetDefinition {
    /// Name (`[a-z0-9-]`).
    pub name: &'static str,
    /// The configuration.
    pub recipe: Recipe,
    /// The stage the sensor sees while generating.
    pub truth: Truth,
}

/// The identified models.
struct Models {
    pi: [PiParams; 3],
    duhem: DuhemParams,
    scaling: Scaling,
}

fn load_models(dir: &Path) -> anyhow::Result<Models> {
    let mut pi = Vec::new();
    let mut duhem = None;
    let mut ranges: Option<Scaling> = None;
    for file in PARAM_FILES {
        let path = dir.join(file);
        let (_, model) = ParamFile::load(&path).with_context(|| path.display().to_string())?;
        match model.hysteresis {
            Hysteresis::Pi(p) => pi.push(p),
            Hysteresis::Duhem(d) => duhem = Some(d),
        }
        let s = model.scaling;
        ranges = Some(match ranges {
            None => s,
            Some(r) => {
                if r.input_min != s.input_min || r.input_max != s.input_max {
                    bail!(
                        "{}: input range differs from the other models'",
                        path.display()
                    );
                }
                Scaling {
                    output_min: r.output_min.min(s.output_min),
                    output_max: r.output_max.max(s.output_max),
                    ..r
                }
            }
        });
    }
    let (Ok(pi), Some(duhem), Some(scaling)) = (<[PiParams; 3]>::try_from(pi), duhem, ranges)
    else {
        bail!(
            "{}: expected three P–I files and one Duhem file",
            dir.display()
        );
    };
    Ok(Models { pi, duhem, scaling })
}

/// The drive: 0…3.6 V per stack on a 5 V full-scale output, rest at 1.8 V, 4 kV/s slew
/// (0.08 V per tick at 50 kHz: a full-range step takes 45 ticks).
fn drive(configuration: Configuration, dac_full_scale: u16) -> DriveSettings {
    DriveSettings {
        configuration,
        amplifier_full_scale: 5.0,
        bias: 1.8,
        right_idle: 0.0,
        min_voltage: 0.0,
        max_voltage: 3.6,
        slew_rate: 4000.0,
        control_rate: 50_000.0,
        dac_full_scale,
        safe_state: SafeState::Bias,
    }
}

/// PI feedback on a sensor ADC of `adc_bits` spanning the output range plus 5 % each side.
fn feedback(scaling: &Scaling, adc_bits: u32) -> FeedbackSettings {
    let margin = 0.05 * (scaling.output_max - scaling.output_min);
    let sensor = SensorSettings {
        adc_bits,
        displacement_at_zero: scaling.output_min - margin,
        displacement_at_full_scale: scaling.output_max + margin,
    };
    FeedbackSettings::pi(sensor, 0.1, 1000.0, 0.1)
}

/// [`feedback`] with the drift check at `limit` (fraction of the output range).
fn with_drift_limit(fb: FeedbackSettings, limit: f64) -> FeedbackSettings {
    FeedbackSettings {
        drift_limit: Some(limit),
        ..fb
    }
}

/// Every set, from the parameter files in `dir` (the golden directory).
pub fn definitions(dir: &Path) -> anyhow::Result<Vec<SetDefinition>> {
    let m = load_models(dir)?;
    let s = m.scaling;
    let [pi8, pi16, pi32] = m.pi.clone();
    let duhem = m.duhem;
    use CompensatorChoice as C;
    use Configuration::{Differential, Unidirectional};
    use ObserverChoice as O;
    let set =
        |name, compensator, observer, pi: Option<&PiParams>, fb, drive, truth| SetDefinition {
            name,
            recipe: Recipe {
                compensator,
                observer,
                pi: pi.cloned(),
                duhem: Some(duhem),
                scaling: s,
                drive,
                feedback: fb,
            },
            truth,
        };
    let t_duhem = Truth::Duhem(duhem);
    let t_pi = Truth::Pi(pi16.clone());
    Ok(vec![
        set(
            "bypass",
            C::None,
            O::None,
            None,
            None,
            drive(Differential, 65535),
            t_duhem.clone(),
        ),
        set(
            "none-duhem-closed",
            C::None,
            O::Duhem,
            None,
            Some(feedback(&s, 12)),
            drive(Differential, 4095),
            t_pi.clone(),
        ),
        set(
            "ipi8-pi-open",
            C::InversePi,
            O::Pi,
            Some(&pi8),
            None,
            drive(Differential, 65535),
            t_duhem.clone(),
        ),
        set(
            "ipi16-pi-closed",
            C::InversePi,
            O::Pi,
            Some(&pi16),
            // The observer (P–I) and the stage (Duhem) differ by up to 3.6 % of the range
            // (low-passed): a 2 % drift limit flags the worst stretches.
            Some(with_drift_limit(feedback(&s, 16), 0.02)),
            drive(Differential, 65535),
            t_duhem.clone(),
        ),
        set(
            "ipi32-duhem-closed",
            C::InversePi,
            O::Duhem,
            Some(&pi32),
            Some(feedback(&s, 16)),
            drive(Unidirectional, 4095),
            t_duhem,
        ),
        set(
            "iduhem-duhem-closed",
            C::InverseDuhem,
            O::Duhem,
            None,
            Some(feedback(&s, 16)),
            drive(Differential, 65535),
            t_pi.clone(),
        ),
        set(
            "iduhem-pi-open",
            C::InverseDuhem,
            O::Pi,
            Some(&pi16),
            None,
            drive(Unidirectional, 65535),
            t_pi,
        ),
    ])
}
