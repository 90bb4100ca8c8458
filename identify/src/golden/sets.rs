//! The vector sets: which compensator, observer, sensor, feedback, drive and mode each one runs.
//!
//! The models are the micromanipulator record's (`data/micromanipulator-unipolar-
//! 3v6-1hz.csv`, 0…3.6 V, sensor units), identified by `twinstack identify` and committed in
//! `tests/golden/params/` (see the README's "Golden vectors" for the commands), so the vectors
//! do not depend on refitting. Every set shares one scaling: the models' common input range and
//! the union of their output ranges (the Bouc–Wen file's left out, see `load_models`). Each
//! set is a [`Recipe`]: the board's [`Hardware`] and the [`Settings`] a parameter load would
//! carry, so every pairing here is one the wire can carry
//! (any compensator with any observer).
//!
//! | set | compensator | observer | sensor | feedback | mode | drive, safe state | DAC, ADC |
//! |---|---|---|---|---|---|---|---|
//! | `bypass` | none | none | none | none | bypass | differential, bias | 16-bit, none |
//! | `ipi16-duhem-bypass` | inverse P–I, N = 16 | Duhem | drift limit 2 % | PI (unused) | bypass | differential, **zero** | 16-bit, 16-bit |
//! | `none-duhem-closed` | none | Duhem | no drift limit | PI | closed loop | differential, bias | 12-bit, 12-bit |
//! | `ipi8-pi-open` | inverse P–I, N = 8 | P–I, N = 8 | drift limit 2 % | none | open loop | differential, bias | 16-bit, 16-bit |
//! | `ipi16-pi-closed` | inverse P–I, N = 16 | P–I, N = 16 | drift limit 2 % | PI | closed loop | differential, bias | 16-bit, 16-bit |
//! | `ipi32-duhem-closed` | inverse P–I, N = 32 | Duhem | no drift limit | PI | closed loop | unidirectional, bias | 12-bit, 16-bit |
//! | `iduhem-duhem-closed` | inverse Duhem | Duhem | no drift limit | PI | closed loop | differential, bias | 16-bit, 16-bit |
//! | `ipi16-pi-creep-closed` | inverse P–I, N = 16, + inverse creep (4 modes) | P–I, N = 16, + creep | drift limit 2 % | PI | closed loop | differential, bias | 16-bit, 16-bit |
//! | `iduhem-pi-open` | inverse Duhem | P–I, N = 16 | none | none | open loop | unidirectional, bias | 16-bit, none |
//! | `igpi16-gpi-closed` | inverse generalised P–I, N = 16, 6 dead zones | the same | drift limit 2 % | PI | closed loop | differential, bias | 16-bit, 16-bit |
//! | `ibw-bw-closed` | inverse Bouc–Wen | Bouc–Wen | drift limit 2 % | PI | closed loop | unidirectional, bias | 16-bit, 16-bit |
//! | `ipi16-pi-creep-turns-closed` | inverse P–I, N = 16, + inverse creep (4 modes taking turns) | P–I, N = 16, + creep | drift limit 2 % | PI | closed loop | differential, bias | 16-bit, 16-bit |
//! | `ipi16-pi-preview-closed` | the preview (3 kHz, ζ 0.05), then inverse P–I, N = 16 | P–I, N = 16 | drift limit 2 % | PI (on the setpoint four ticks ago) | closed loop | differential, bias | 16-bit, 16-bit |
//! | `ibw-bw-map-creep-closed` | inverse creep (4 modes taking turns), then the inverse output map (a flexure's, 3 dead zones a side), then inverse Bouc–Wen | Bouc–Wen, then the output map, then creep | drift limit 2 % | PI | closed loop | unidirectional, bias | 16-bit, 16-bit (at 40 kHz) |
//!
//! The generalised P–I's and the Bouc–Wen's files widen their output ranges a little beyond
//! the others' (for the P–I part's output; 5 % beyond its own simulated output); the shared
//! scaling is the union of the other files' ranges only, so the sets before them keep their
//! vectors bit for bit (the generalised P–I part's input is clamped to that range at the very
//! bottom of the stroke, by the fixed point and the reference alike; the Bouc–Wen's simulated
//! output lies within the union of the others').
//!
//! The bypass set with models runs the compensator on every tick without using it, reads the
//! sensor and checks drift (a bypassed tick still monitors the stage), and starts from the
//! zero safe state, so the right stack slews up to its mirror from 0 V.

use crate::param_file::ParamFile;
use crate::stage_model::Hysteresis;
use anyhow::{bail, Context};
use std::path::Path;
use twinstack::board::Hardware;
use twinstack::config::settings::{
    representative_output_map, CreepParams, DeadZoneParams, FeedbackSettings, Mode, Model,
    SensorSettings, Settings,
};
use twinstack::control::drive::{Configuration, DriveSettings, SafeState};
use twinstack::control::preview::PreviewDesign;
use twinstack::models::generalised_pi::GpiParams;
use twinstack::{BoucWenParams, DuhemParams, PiParams, Scaling};
use twinstack_golden::Recipe;

/// The parameter files, relative to the golden directory.
pub const PARAM_FILES: [&str; 6] = [
    "params/micromanipulator-pi8.json",
    "params/micromanipulator-pi16.json",
    "params/micromanipulator-pi32.json",
    "params/micromanipulator-duhem.json",
    "params/micromanipulator-gpi16.json",
    "params/micromanipulator-bouc-wen.json",
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
    gpi: GpiParams,
    bouc_wen: BoucWenParams,
    scaling: Scaling,
}

fn load_models(dir: &Path) -> anyhow::Result<Models> {
    let mut pi = Vec::new();
    let mut duhem = None;
    let mut gpi = None;
    let mut bouc_wen = None;
    let mut ranges: Option<Scaling> = None;
    for file in PARAM_FILES {
        let path = dir.join(file);
        let (_, model) = ParamFile::load(&path).with_context(|| path.display().to_string())?;
        let s = model.scaling;
        match model.hysteresis {
            Hysteresis::Pi(p) => pi.push(p),
            Hysteresis::Duhem(d) => duhem = Some(d),
            Hysteresis::GeneralisedPi(g) => {
                // Not in the union (see the module doc), but on the same input range.
                let (s, r) = (model.scaling, ranges.unwrap_or(model.scaling));
                if r.input_min != s.input_min || r.input_max != s.input_max {
                    bail!(
                        "{}: input range differs from the other models'",
                        path.display()
                    );
                }
                gpi = Some(g);
                continue;
            }
            Hysteresis::BoucWen(b) => {
                // Its output range (5 % beyond its own simulated output) is left out of the
                // union, so that the sets before it keep their scaling and their vectors; its
                // simulated output lies within the union of the others'.
                if ranges.is_some_and(|r| r.input_min != s.input_min || r.input_max != s.input_max)
                {
                    bail!(
                        "{}: input range differs from the other models'",
                        path.display()
                    );
                }
                bouc_wen = Some(b);
                continue;
            }
        }
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
    let (Ok(pi), Some(duhem), Some(gpi), Some(bouc_wen), Some(scaling)) =
        (<[PiParams; 3]>::try_from(pi), duhem, gpi, bouc_wen, ranges)
    else {
        bail!(
            "{}: expected three P–I files, one Duhem file, one generalised P–I file and one Bouc–Wen file",
            dir.display()
        );
    };
    Ok(Models {
        pi,
        duhem,
        gpi,
        bouc_wen,
        scaling,
    })
}

/// The board: a 5 V full-scale output on a DAC of `dac_full_scale`, the sensor on an ADC of
/// `adc_bits` (`None`: no sensor input), 50 kHz.
fn hardware(dac_full_scale: u16, adc_bits: Option<u8>) -> Hardware {
    Hardware {
        amplifier_full_scale: 5.0,
        dac_full_scale,
        sensor_adc_bits: adc_bits,
        control_rate_hz: 50_000.0,
    }
}

/// The drive: 0…3.6 V per stack, rest at 1.8 V, 4 kV/s slew (0.08 V per tick at 50 kHz: a
/// full-range step takes 45 ticks).
fn drive(configuration: Configuration, safe_state: SafeState) -> DriveSettings {
    DriveSettings {
        configuration,
        bias: 1.8,
        min_voltage: 0.0,
        max_voltage: 3.6,
        slew_rate: 4000.0,
        safe_state,
    }
}

/// The sensor calibration: the ADC spans the output range plus 5 % each side; the drift check
/// at `drift_limit` (fraction of the output range), if any.
fn sensor(scaling: &Scaling, drift_limit: Option<f64>) -> SensorSettings {
    let margin = 0.05 * (scaling.output_max - scaling.output_min);
    SensorSettings {
        displacement_at_zero: scaling.output_min - margin,
        displacement_at_full_scale: scaling.output_max + margin,
        drift_limit,
    }
}

/// The feedback of every set that has one: PI, `kp = 0.1`, `ki = 1000 /s`, within ±10 % of
/// the drive range.
fn feedback() -> FeedbackSettings {
    FeedbackSettings::pi(0.1, 1000.0, 0.1)
}

/// Every set, from the parameter files in `dir` (the golden directory).
pub fn definitions(dir: &Path) -> anyhow::Result<Vec<SetDefinition>> {
    let m = load_models(dir)?;
    let s = m.scaling;
    let [pi8, pi16, pi32] = m.pi.clone().map(Model::PrandtlIshlinskii);
    let duhem = Model::Duhem(m.duhem);
    let gpi16 = Model::GeneralisedPi(m.gpi.clone());
    let bouc_wen = Model::BoucWen(m.bouc_wen);
    use Configuration::{Differential, Unidirectional};
    use SafeState::{Bias, Zero};
    struct Set {
        name: &'static str,
        compensator: Option<Model>,
        observer: Option<Model>,
        sensor: Option<SensorSettings>,
        feedback: Option<FeedbackSettings>,
        mode: Mode,
        drive: DriveSettings,
        hardware: Hardware,
        truth: Truth,
        creep: Option<CreepParams>,
        preview: Option<PreviewDesign>,
        output_map: Option<DeadZoneParams>,
    }
    let def = |set: Set| SetDefinition {
        name: set.name,
        recipe: Recipe {
            hardware: set.hardware,
            settings: Settings {
                ranges: s,
                compensator: set.compensator,
                observer: set.observer,
                drive: set.drive,
                sensor: set.sensor,
                feedback: set.feedback,
                mode: set.mode,
                creep: set.creep,
                shaping: None,
                preview: set.preview,
                output_map: set.output_map,
            },
        },
        truth: set.truth,
    };
    let t_duhem = Truth::Duhem(m.duhem);
    let t_pi = Truth::Pi(m.pi[1].clone());
    // Most sets run closed loop on the 16-bit board with a 2 % drift limit; each differs from
    // this in the fields it names.
    let closed = |name, compensator: &Model, observer: &Model, truth: &Truth| Set {
        name,
        compensator: Some(compensator.clone()),
        observer: Some(observer.clone()),
        sensor: Some(sensor(&s, Some(0.02))),
        feedback: Some(feedback()),
        mode: Mode::ClosedLoop,
        drive: drive(Differential, Bias),
        hardware: hardware(65535, Some(16)),
        truth: truth.clone(),
        creep: None,
        preview: None,
        output_map: None,
    };
    let no_drift_limit = Some(sensor(&s, None));
    Ok(vec![
        def(Set {
            compensator: None,
            observer: None,
            sensor: None,
            feedback: None,
            mode: Mode::Bypass,
            hardware: hardware(65535, None),
            ..closed("bypass", &duhem, &duhem, &t_duhem)
        }),
        // The observer (Duhem) and the stage (P–I) differ by a few % of the range: the drift
        // check flags in bypass too.
        def(Set {
            mode: Mode::Bypass,
            drive: drive(Differential, Zero),
            ..closed("ipi16-duhem-bypass", &pi16, &duhem, &t_pi)
        }),
        def(Set {
            compensator: None,
            sensor: no_drift_limit,
            hardware: hardware(4095, Some(12)),
            ..closed("none-duhem-closed", &duhem, &duhem, &t_pi)
        }),
        def(Set {
            feedback: None,
            mode: Mode::OpenLoop,
            ..closed("ipi8-pi-open", &pi8, &pi8, &t_duhem)
        }),
        // The observer (P–I) and the stage (Duhem) differ by up to 3.6 % of the range
        // (low-passed): a 2 % drift limit flags the worst stretches.
        def(closed("ipi16-pi-closed", &pi16, &pi16, &t_duhem)),
        def(Set {
            sensor: no_drift_limit,
            drive: drive(Unidirectional, Bias),
            hardware: hardware(4095, Some(16)),
            ..closed("ipi32-duhem-closed", &pi32, &duhem, &t_duhem)
        }),
        def(Set {
            sensor: no_drift_limit,
            ..closed("iduhem-duhem-closed", &duhem, &duhem, &t_pi)
        }),
        // The inverse P–I N = 16 set with four creep modes (0.1 ms … 100 ms) in series with
        // both models.
        def(Set {
            creep: Some(CreepParams::new(
                &[1e-4, 1e-3, 1e-2, 1e-1],
                &[0.02, 0.02, 0.02, 0.03],
            )?),
            ..closed("ipi16-pi-creep-closed", &pi16, &pi16, &t_duhem)
        }),
        def(Set {
            sensor: None,
            feedback: None,
            mode: Mode::OpenLoop,
            drive: drive(Unidirectional, Bias),
            hardware: hardware(65535, None),
            ..closed("iduhem-pi-open", &duhem, &pi16, &t_pi)
        }),
        def(closed("igpi16-gpi-closed", &gpi16, &gpi16, &t_duhem)),
        // The observer (Bouc–Wen) and the stage (P–I) differ: the drift check flags. Single
        // ended: the models start on their loop's ascending branch (`Rest::Ascending`), where
        // the differential sets start them relaxed.
        def(Set {
            drive: drive(Unidirectional, Bias),
            ..closed("ibw-bw-closed", &bouc_wen, &bouc_wen, &t_pi)
        }),
        // The inverse P–I N = 16 set with creep as identification picks its modes (10 ms …
        // 10 s): they take turns, one a tick.
        def(Set {
            creep: Some(CreepParams::new(
                &[1e-2, 1e-1, 1.0, 10.0],
                &[0.04, 0.02, 0.02, 0.03],
            )?),
            ..closed("ipi16-pi-creep-turns-closed", &pi16, &pi16, &t_duhem)
        }),
        // The inverse P–I N = 16 set with the preview: every setpoint shaped for a 3 kHz
        // resonance before the compensator, the feedback on the setpoint four ticks ago (the
        // scenario's steps shape beyond full scale and are held there).
        def(Set {
            preview: Some(PreviewDesign {
                frequency_hz: 3_000.0,
                damping: 0.05,
            }),
            ..closed("ipi16-pi-preview-closed", &pi16, &pi16, &t_duhem)
        }),
        // The Bouc–Wen set with a static output map between the model and creep as
        // identification picks its modes (10 ms … 10 s, taking turns: every mode every tick
        // would overrun the tick's budget with the map): the compensator runs the inverse
        // creep, the inverse map, then the inverse model; the observer the model, the map,
        // then the creep. At 40 kHz: with its observer, the tick budget admits this pair up to
        // 49.8 kHz (`twinstack budget`), its floating-point context charged.
        def(Set {
            drive: drive(Unidirectional, Bias),
            hardware: Hardware {
                control_rate_hz: 40_000.0,
                ..hardware(65535, Some(16))
            },
            creep: Some(CreepParams::new(
                &[1e-2, 1e-1, 1.0, 10.0],
                &[0.04, 0.02, 0.02, 0.03],
            )?),
            output_map: Some(flexure_map(&s)?),
            ..closed("ibw-bw-map-creep-closed", &bouc_wen, &bouc_wen, &t_pi)
        }),
    ])
}

/// The representative output map (a flexure's stiffening over 0…70 µm:
/// [`representative_output_map`]) carried onto `scaling`'s output range: centred in it, the
/// thresholds scaled from the 35 µm half span to its half span, the weights as they are (6 %
/// flatter toward either end, in three dead zones a side).
pub fn flexure_map(scaling: &Scaling) -> anyhow::Result<DeadZoneParams> {
    let m = representative_output_map();
    let scale = scaling.output_half_span() / 35.0;
    let thresholds: Vec<f64> = m.thresholds.iter().map(|d| d * scale).collect();
    let map = DeadZoneParams::new(scaling.output_mid(), m.linear, &thresholds, &m.weights)
        .map_err(|e| anyhow::anyhow!("the output map: {e:?}"))?;
    map.validate()
        .map_err(|e| anyhow::anyhow!("the output map: {e:?}"))?;
    Ok(map)
}
