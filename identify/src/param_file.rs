//! The versioned parameter file (`PARAMS.json`) that `identify` writes, `load` sends, and
//! `predict` and `compensate` read. It carries the board's one settings type
//! ([`twinstack::config::settings::Settings`]) as it is, so what a file says is exactly what a
//! parameter load carries, what the board stores, and what `params` reads back.
//!
//! ```json
//! { "format": "twinstack-params", "version": 2,
//!   "units": { "time": "s", "input": "V", "output": "units of the x column" },
//!   "output_sign": 1, "sensor_lag_s": 0.0,
//!   "settings": { "ranges": { "input_min": -153.0, "input_max": 153.0,
//!                             "output_min": -19.9, "output_max": 21.8 },
//!                 "compensator": { "PrandtlIshlinskii": { "a0": 0.0, "offset": …,
//!                                  "thresholds": [...], "weights": [...] } },
//!                 "observer": { … }, "drive": { … }, "sensor": null, "feedback": null,
//!                 "mode": "OpenLoop" },
//!   "identification": { ... how it was fitted and scored; informative only ... } }
//! ```
//!
//! Loading checks, in order: JSON syntax, `format`, `version` (only [`VERSION`] is known),
//! the fields (unknown ones are refused, at any depth), `output_sign`, `sensor_lag_s` and
//! `resonance` (where present: what `calibrate` measured, for a planned trajectory's preview),
//! that the file has a model, and the settings as the driver board validates them (at
//! 50 kHz or 100 kHz; the board checks again at its own rate): every refusal names its field.

use crate::preview::Resonance;
use crate::stage_model::{Hysteresis, StageModel};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use twinstack::board::Hardware;
use twinstack::config::settings::{Mode, Model, Settings};
use twinstack::control::drive::DriveSettings;

/// Max and RMS error, % of the measured span (what [`crate::identification::score::score`]
/// computes, recorded in the file).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct ErrorFigures {
    /// Largest absolute error, % of span.
    pub max_pct: f64,
    /// Root-mean-square error, % of span.
    pub rms_pct: f64,
    /// Samples scored.
    pub samples: usize,
}

/// The `format` tag of a parameter file.
pub const FORMAT: &str = "twinstack-params";
/// The one version this build reads and writes (2: the board's settings type).
pub const VERSION: u64 = 2;

/// serde's message for a list past a bounded list's capacity ("invalid length 33, expected a
/// sequence": the item that did not fit) in words that say so, with the capacity; any other
/// message as it is.
fn list_too_long(message: &str) -> String {
    let length = message
        .strip_prefix("invalid length ")
        .and_then(|rest| rest.strip_suffix(", expected a sequence"))
        .and_then(|n| n.parse::<usize>().ok());
    match length {
        Some(n) if n > 0 => format!(
            "a list longer than the board holds: at most {} items here",
            n - 1
        ),
        _ => message.to_string(),
    }
}

/// The most a parameter file is read of, bytes (one is a few kilobytes).
pub const MAX_FILE_BYTES: u64 = 16 << 20;

/// The longest sensor lag a parameter file holds, seconds: a reading a second behind its
/// drive is no position sensor (`identify` estimates lags of a few samples).
pub const MAX_SENSOR_LAG_S: f64 = 1.0;

/// Units of the quantities in the file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Units {
    /// Time.
    pub time: String,
    /// Drive.
    pub input: String,
    /// Output (as in the identified record's `x` column).
    pub output: String,
}

/// How the model was identified and how it scored (informative; not read back).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct IdentificationRecord {
    /// The record fitted.
    pub data: String,
    /// Split time, seconds.
    pub fit_until_s: f64,
    /// First fitted sample's time, seconds.
    pub fit_from_s: f64,
    /// P–I operators (also used for the lag estimate).
    pub operators: usize,
    /// P–I threshold spread.
    pub thresholds: String,
    /// Lag, samples of the record: a whole or a half number (written as an integer when whole,
    /// as files from before half lags hold it).
    #[serde(serialize_with = "whole_as_integer")]
    pub lag_samples: f64,
    /// Whether the lag was estimated.
    pub lag_estimated: bool,
    /// Rows dropped as outliers.
    pub outliers: usize,
    /// Error on the fitted part (fixed-point predict).
    pub fit: ErrorFigures,
    /// Error on the held-out part (fixed-point predict).
    pub held_out: ErrorFigures,
    /// Error of the inverse on the held-out part (compensate's drive against the measured one).
    pub inverse_held_out: ErrorFigures,
    /// Largest |fixed point − f64 reference| of the prediction over the record, % of span.
    pub fixed_vs_reference_max_pct: f64,
    /// Largest |fixed point − f64 reference| of compensate's drive, % of the drive's span.
    pub inverse_fixed_vs_reference_max_pct: f64,
    /// What the fit had to do.
    pub notes: Vec<String>,
    /// The fitted part's fastest motion, Hz: the highest rate at which its drive swings by a
    /// fifth of its span or more between two turning points
    /// ([`crate::identification::coverage`]) — the fastest the model has seen. Absent where
    /// the drive never swings that far, and in files from before it was recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fastest_motion_hz: Option<f64>,
}

/// The whole file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamFile {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always [`VERSION`].
    pub version: u64,
    /// Units.
    pub units: Units,
    /// `1` or `−1`: sensor reading = `output_sign` × model output.
    pub output_sign: f64,
    /// Sensor lag behind the drive, seconds.
    pub sensor_lag_s: f64,
    /// The stage's resonance as `calibrate` measured it (`tune`'s sweep and fit), for a
    /// planned trajectory's preview (`compensate --preview`, `stream --preview`): host-side,
    /// not sent to the board. Absent where it was not measured.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub resonance: Option<Resonance>,
    /// The settings, as a parameter load carries them.
    pub settings: Settings,
    /// How it was identified.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub identification: Option<IdentificationRecord>,
}

/// Why a parameter file was refused.
#[derive(Debug, thiserror::Error)]
pub enum ParamFileError {
    /// Unreadable.
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// Not JSON, or a field of the wrong type / unknown / missing.
    #[error("{}:{line}:{column}: {message}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// Column, 1-based.
        column: usize,
        /// serde_json's message.
        message: String,
    },
    /// Not a twinstack parameter file.
    #[error("{}: `format` is {found}, expected \"{FORMAT}\"", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What was there.
        found: String,
    },
    /// A version this build does not know.
    #[error("{}: `version` is {found}, this twinstack reads version {VERSION} only", path.display())]
    Version {
        /// The file.
        path: PathBuf,
        /// What was there.
        found: String,
    },
    /// A field's value is not acceptable.
    #[error("{}: field `{field}`: {reason}", path.display())]
    Field {
        /// The file.
        path: PathBuf,
        /// The field (its path in the file, e.g. `settings.compensator.weights[0]`).
        field: String,
        /// Why.
        reason: String,
    },
}

impl ParamFile {
    /// The file for an identified `model`: the model as compensator and observer over its
    /// ranges, the board's default drive, no sensor calibration and no feedback (`load`
    /// keeps the board's own unless the file or the command line gives them), open loop.
    pub fn from_model(
        model: &StageModel,
        output_units: &str,
        identification: Option<IdentificationRecord>,
    ) -> Self {
        let m = match &model.hysteresis {
            Hysteresis::Pi(p) => Model::PrandtlIshlinskii(p.clone()),
            Hysteresis::Duhem(p) => Model::Duhem(*p),
            Hysteresis::GeneralisedPi(p) => Model::GeneralisedPi(p.clone()),
            Hysteresis::BoucWen(p) => Model::BoucWen(*p),
        };
        Self {
            format: FORMAT.into(),
            version: VERSION,
            units: Units {
                time: "s".into(),
                input: "V".into(),
                output: output_units.into(),
            },
            output_sign: model.output_sign,
            sensor_lag_s: model.sensor_lag_s,
            resonance: None,
            settings: Settings {
                ranges: model.scaling,
                compensator: Some(m.clone()),
                observer: Some(m),
                drive: DriveSettings::DEFAULT,
                sensor: None,
                feedback: None,
                mode: Mode::OpenLoop,
                creep: model.creep.clone(),
                shaping: None,
                preview: None,
                output_map: model.output_map.clone(),
            },
            identification,
        }
    }

    /// The same file with the model as compensator only (`observer: false`): no estimate and
    /// no drift check on the board, and the observer's cost off its tick.
    pub fn with_observer(mut self, observer: bool) -> Self {
        if !observer {
            self.settings.observer = None;
        }
        self
    }

    /// The JSON text.
    pub fn to_json(&self) -> String {
        // Serialising plain data with finite numbers cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default() + "\n"
    }

    /// Writes the file.
    pub fn save(&self, path: &Path) -> Result<(), ParamFileError> {
        std::fs::write(path, self.to_json()).map_err(|source| ParamFileError::Io {
            path: path.to_path_buf(),
            source,
        })
    }

    /// Reads and validates `path`.
    pub fn load(path: &Path) -> Result<(Self, StageModel), ParamFileError> {
        use std::io::Read;
        let io = |source| ParamFileError::Io {
            path: path.to_path_buf(),
            source,
        };
        // Read at most a bound past any parameter file (a device or a pipe that never ends,
        // `/dev/zero`, is refused, not read for ever).
        let mut text = String::new();
        std::fs::File::open(path)
            .map_err(io)?
            .take(MAX_FILE_BYTES + 1)
            .read_to_string(&mut text)
            .map_err(io)?;
        if text.len() as u64 > MAX_FILE_BYTES {
            return Err(io(std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("longer than {MAX_FILE_BYTES} bytes: not a parameter file"),
            )));
        }
        Self::parse(path, &text)
    }

    /// Parses and validates `text` (read from `path`, used in errors).
    pub fn parse(path: &Path, text: &str) -> Result<(Self, StageModel), ParamFileError> {
        // A byte-order mark (an editor's on Windows) is no part of the JSON, as a CSV's is not.
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        let p = || path.to_path_buf();
        let json_err = |e: serde_json::Error| ParamFileError::Json {
            path: p(),
            line: e.line(),
            column: e.column(),
            message: list_too_long(e.to_string().split(" at line ").next().unwrap_or("")),
        };
        let value: serde_json::Value = serde_json::from_str(text).map_err(json_err)?;
        match value.get("format") {
            Some(serde_json::Value::String(s)) if s == FORMAT => {}
            other => {
                return Err(ParamFileError::Format {
                    path: p(),
                    found: other.map_or("missing".into(), |v| v.to_string()),
                })
            }
        }
        match value.get("version") {
            Some(v) if v.as_u64() == Some(VERSION) => {}
            other => {
                return Err(ParamFileError::Version {
                    path: p(),
                    found: other.map_or("missing".into(), |v| v.to_string()),
                })
            }
        }
        let file: ParamFile = serde_json::from_str(text).map_err(json_err)?;
        let field = |field: String, reason: String| ParamFileError::Field {
            path: p(),
            field,
            reason,
        };
        // The quantities are in seconds and volts: a file that says otherwise would be read as
        // if it did not (a lag in "ms" taken as seconds).
        for (name, unit, want) in [
            ("units.time", &file.units.time, "s"),
            ("units.input", &file.units.input, "V"),
        ] {
            if unit != want {
                return Err(field(
                    name.into(),
                    format!("{unit:?}: the file's values are in {want:?}, the only unit read"),
                ));
            }
        }
        if file.output_sign != 1.0 && file.output_sign != -1.0 {
            return Err(field(
                "output_sign".into(),
                format!("{} is not 1 or -1", file.output_sign),
            ));
        }
        if !(file.sensor_lag_s >= 0.0 && file.sensor_lag_s <= MAX_SENSOR_LAG_S) {
            return Err(field(
                "sensor_lag_s".into(),
                format!(
                    "{:?}: must be from 0 to {MAX_SENSOR_LAG_S} s",
                    file.sensor_lag_s
                ),
            ));
        }
        if let Some(r) = &file.resonance {
            r.check().map_err(|e| {
                let name = match e {
                    crate::preview::PreviewError::Damping(_) => "resonance.damping",
                    _ => "resonance.frequency_hz",
                };
                field(name.into(), e.to_string())
            })?;
        }
        let s = &file.settings;
        // The board's own validation, at either end of its rates: a file is refused only
        // if no rate the board runs would take it. The tick budget is left to the board: what
        // the tick can afford depends on the rate it runs and on what runs beside the settings,
        // and the board refuses it at load (`Refused(Workload, TickOverrun)`).
        let rates = [50_000.0, 100_000.0];
        let refused_at = |rate: f64| match s.build(&Hardware::driver_board(rate)) {
            Err(r) if r.field != twinstack::refusal::Field::Workload => Some(r),
            _ => None,
        };
        let refusals: Vec<_> = rates.iter().map(|&r| refused_at(r)).collect();
        if refusals.iter().all(Option::is_some) {
            if let Some(Some(refusal)) = refusals.into_iter().next() {
                return Err(field(
                    format!("settings.{}", refusal.field),
                    refusal.rule.to_string(),
                ));
            }
        }
        let hysteresis = match s.compensator.as_ref().or(s.observer.as_ref()) {
            Some(Model::PrandtlIshlinskii(p)) => Hysteresis::Pi(p.clone()),
            Some(Model::Duhem(p)) => Hysteresis::Duhem(*p),
            Some(Model::GeneralisedPi(p)) => Hysteresis::GeneralisedPi(p.clone()),
            Some(Model::BoucWen(p)) => Hysteresis::BoucWen(*p),
            None => {
                return Err(field(
                    "settings.compensator".into(),
                    "the file has no model (neither compensator nor observer)".into(),
                ))
            }
        };
        let model = StageModel {
            hysteresis,
            scaling: s.ranges,
            output_sign: file.output_sign,
            sensor_lag_s: file.sensor_lag_s,
            creep: s.creep.clone(),
            output_map: s.output_map.clone(),
        };
        Ok((file, model))
    }
}

/// Writes `v` as an integer when it is a whole number that fits one, else as a float.
fn whole_as_integer<S: serde::Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
    if v.fract() == 0.0 && v.abs() < 9.0e15 {
        s.serialize_i64(*v as i64)
    } else {
        s.serialize_f64(*v)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use twinstack::{DuhemParams, PiParams, Scaling};

    fn model() -> StageModel {
        StageModel {
            hysteresis: Hysteresis::Pi(
                PiParams::new(0.0, 0.5, &[0.0, 30.0, 60.0], &[0.08, 0.03, 0.02]).unwrap(),
            ),
            scaling: Scaling::new(0.0, 140.0, -20.0, 21.0).unwrap(),
            output_sign: -1.0,
            sensor_lag_s: 0.005,
            creep: None,
            output_map: None,
        }
    }

    fn parse(text: &str) -> Result<(ParamFile, StageModel), ParamFileError> {
        ParamFile::parse(Path::new("p.json"), text)
    }

    #[test]
    fn a_written_file_loads_back_to_the_same_model() {
        for m in [
            model(),
            StageModel {
                hysteresis: Hysteresis::Duhem(DuhemParams {
                    alpha: 0.01,
                    beta: 0.13,
                    gamma: 0.1,
                    offset: 0.2,
                }),
                ..model()
            },
        ] {
            let f = ParamFile::from_model(&m, "um", None);
            let (back, loaded) = parse(&f.to_json()).unwrap();
            assert_eq!(back, f);
            assert_eq!(loaded, m);
        }
    }

    /// Every `f64` reads back to the bit it was written as (serde_json's default parser is
    /// off by an ULP on some: a file rewritten by `set --file` changed values nobody set).
    #[test]
    fn every_value_reads_back_to_the_bit() {
        let m = StageModel {
            hysteresis: Hysteresis::Pi(
                PiParams::new(
                    0.0,
                    0.5,
                    &[0.0, 30.105_882_352_941_176, 60.0],
                    &[0.08, 0.03, 0.02],
                )
                .unwrap(),
            ),
            scaling: Scaling::new(0.0, 140.0, -20.66912244948139, 21.0).unwrap(),
            ..model()
        };
        let f = ParamFile::from_model(&m, "um", None);
        let (back, loaded) = parse(&f.to_json()).unwrap();
        assert_eq!(back, f);
        assert_eq!(loaded, m);
        // With a byte-order mark before it, the same file.
        assert_eq!(parse(&format!("\u{feff}{}", f.to_json())).unwrap().0, f);
        let text = f.to_json();
        assert!(text.contains("30.105882352941176"), "{text}");
        assert!(text.contains("-20.66912244948139"), "{text}");
        assert_eq!(back.to_json(), text);
        // The reader itself, on values of every size a file holds.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        for _ in 0..20_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let x = (state >> 11) as f64 / (1u64 << 53) as f64 * 400.0 - 200.0;
            let back: f64 = serde_json::from_str(&serde_json::to_string(&x).unwrap()).unwrap();
            assert_eq!(back.to_bits(), x.to_bits(), "{x:?} read back as {back:?}");
        }
    }

    #[test]
    fn creep_round_trips_and_a_file_without_it_still_loads() {
        let m = StageModel {
            creep: Some(
                twinstack::models::creep::CreepParams::new(&[0.01, 0.1, 1.0], &[0.02, 0.01, 0.03])
                    .unwrap(),
            ),
            ..model()
        };
        let f = ParamFile::from_model(&m, "um", None);
        let (_, loaded) = parse(&f.to_json()).unwrap();
        assert_eq!(loaded, m);
        // A file written before the creep field existed: no `creep` key at all.
        let mut v: serde_json::Value =
            serde_json::from_str(&ParamFile::from_model(&model(), "um", None).to_json()).unwrap();
        v["settings"].as_object_mut().unwrap().remove("creep");
        let (_, loaded) = parse(&v.to_string()).unwrap();
        assert_eq!(loaded.creep, None);
        // A bad creep is refused naming the field.
        let mut v: serde_json::Value = serde_json::from_str(&f.to_json()).unwrap();
        v["settings"]["creep"]["weights"][1] = (-0.5).into();
        let e = parse(&v.to_string()).unwrap_err();
        assert_eq!(field_of(&e), "settings.creep.weights[1]", "{e}");
    }

    /// A Bouc–Wen model on the P–I model's ranges.
    fn bouc_wen_model() -> StageModel {
        StageModel {
            hysteresis: Hysteresis::BoucWen(twinstack::BoucWenParams {
                k: 0.1,
                offset: 0.5,
                a: 0.05,
                beta: 0.02,
                gamma: 0.004,
                psi: 0.003,
                chi: 0.001,
            }),
            ..model()
        }
    }

    /// A Bouc–Wen model with an output map writes it into the settings and loads back with
    /// it; a file without the field loads as no map; a map the board refuses, or a map with
    /// another model, is refused naming its field.
    #[test]
    fn an_output_map_round_trips_and_a_file_without_it_has_none() {
        use twinstack::models::output_map::DeadZoneParams;
        let m = StageModel {
            creep: Some(
                twinstack::models::creep::CreepParams::new(&[0.01, 0.1], &[0.02, 0.01]).unwrap(),
            ),
            output_map: Some(
                DeadZoneParams::new(
                    0.5,
                    1.02,
                    &[-15.0, -6.0, 6.0, 15.0],
                    &[-0.1, -0.05, -0.05, -0.1],
                )
                .unwrap(),
            ),
            ..bouc_wen_model()
        };
        m.check().unwrap();
        let f = ParamFile::from_model(&m, "um", None);
        assert_eq!(f.settings.output_map, m.output_map);
        let (back, loaded) = parse(&f.to_json()).unwrap();
        assert_eq!(back, f);
        assert_eq!(loaded, m);
        // Without the field: no map.
        let mut v: serde_json::Value = serde_json::from_str(&f.to_json()).unwrap();
        v["settings"].as_object_mut().unwrap().remove("output_map");
        let (_, loaded) = parse(&v.to_string()).unwrap();
        assert_eq!(loaded.output_map, None);
        assert_eq!(loaded.creep, m.creep);
        // A map that falls is refused, naming the dead zone.
        let mut v: serde_json::Value = serde_json::from_str(&f.to_json()).unwrap();
        v["settings"]["output_map"]["weights"][3] = (-1.5).into();
        let e = parse(&v.to_string()).unwrap_err();
        assert!(field_of(&e).starts_with("settings.output_map"), "{e}");
        // The board takes a map after a Bouc–Wen only.
        let with_pi = StageModel {
            hysteresis: model().hysteresis,
            ..m.clone()
        };
        let e = parse(&ParamFile::from_model(&with_pi, "um", None).to_json()).unwrap_err();
        assert!(e.to_string().contains("output_map"), "{e}");
    }

    fn edited(f: impl Fn(&mut serde_json::Value)) -> ParamFileError {
        let mut v: serde_json::Value =
            serde_json::from_str(&ParamFile::from_model(&model(), "um", None).to_json()).unwrap();
        f(&mut v);
        parse(&v.to_string()).unwrap_err()
    }

    fn field_of(e: &ParamFileError) -> &str {
        match e {
            ParamFileError::Field { field, .. } => field,
            _ => "",
        }
    }

    #[test]
    fn a_measured_resonance_round_trips_and_a_bad_one_is_named() {
        let mut f = ParamFile::from_model(&model(), "um", None);
        assert!(
            !f.to_json().contains("resonance"),
            "absent where not measured"
        );
        f.resonance = Some(Resonance::new(3_500.0, 0.03).unwrap());
        let (back, _) = parse(&f.to_json()).unwrap();
        assert_eq!(back.resonance, f.resonance);
        let with = |edit: &dyn Fn(&mut serde_json::Value)| {
            let mut v: serde_json::Value = serde_json::from_str(&f.to_json()).unwrap();
            edit(&mut v);
            parse(&v.to_string()).unwrap_err()
        };
        for (value, named) in [
            (
                serde_json::json!({ "frequency_hz": -3.0, "damping": 0.03 }),
                "resonance.frequency_hz",
            ),
            (
                serde_json::json!({ "frequency_hz": 0.0, "damping": 0.03 }),
                "resonance.frequency_hz",
            ),
            (
                serde_json::json!({ "frequency_hz": 3e3, "damping": 1.0 }),
                "resonance.damping",
            ),
            (
                serde_json::json!({ "frequency_hz": 3e3, "damping": 0.0 }),
                "resonance.damping",
            ),
        ] {
            let e = with(&|v| v["resonance"] = value.clone());
            assert_eq!(field_of(&e), named, "{e}");
        }
        let e = with(&|v| v["resonance"]["q"] = 2.0.into());
        assert!(
            matches!(e, ParamFileError::Json { .. }) && e.to_string().contains('q'),
            "{e}"
        );
        let e = with(&|v| {
            v["resonance"].as_object_mut().unwrap().remove("damping");
        });
        assert!(e.to_string().contains("damping"), "{e}");
    }

    #[test]
    #[cfg(unix)]
    fn a_file_that_never_ends_is_refused() {
        let e = ParamFile::load(Path::new("/dev/zero")).unwrap_err();
        assert!(e.to_string().contains("not a parameter file"), "{e}");
    }

    #[test]
    fn each_bad_field_is_named() {
        let e = edited(|v| v["version"] = 1.into());
        assert!(matches!(e, ParamFileError::Version { .. }), "{e}");
        let e = edited(|v| v["format"] = "other".into());
        assert!(matches!(e, ParamFileError::Format { .. }), "{e}");
        let e = edited(|v| v["output_sign"] = 0.5.into());
        assert_eq!(field_of(&e), "output_sign", "{e}");
        // A list longer than the board holds: said so, with how many it holds.
        let e = edited(|v| {
            let pi = &mut v["settings"]["compensator"]["PrandtlIshlinskii"];
            pi["thresholds"] = (0..40).map(f64::from).collect::<Vec<_>>().into();
            pi["weights"] = vec![0.01; 40].into();
        });
        assert!(
            e.to_string()
                .contains("a list longer than the board holds: at most 32 items here"),
            "{e}"
        );
        for (unit, value) in [("time", "ms"), ("input", "mV")] {
            let e = edited(|v| v["units"][unit] = value.into());
            assert_eq!(field_of(&e), format!("units.{unit}"), "{e}");
        }
        // A lag beyond a second (1e308 ran as 9.2e18 samples, the rest of any record).
        for lag in [-0.001, 3.5, 1e308] {
            let e = edited(|v| v["sensor_lag_s"] = lag.into());
            assert_eq!(field_of(&e), "sensor_lag_s", "{e}");
            assert!(e.to_string().contains("from 0 to 1 s"), "{e}");
        }
        let e = edited(|v| v["settings"]["ranges"]["input_max"] = (-200.0).into());
        assert_eq!(field_of(&e), "settings.ranges.input", "{e}");
        let e = edited(|v| {
            v["settings"]["compensator"]["PrandtlIshlinskii"]["weights"][0] = (-0.5).into()
        });
        assert_eq!(field_of(&e), "settings.compensator.weights[0]", "{e}");
        assert!(e.to_string().contains("non-invertible"), "{e}");
        let e = edited(|v| v["settings"]["drive"]["bias"] = 200.0.into());
        assert_eq!(field_of(&e), "settings.drive.bias", "{e}");
        let e = edited(|v| {
            v["settings"]["compensator"] = serde_json::Value::Null;
            v["settings"]["observer"] = serde_json::Value::Null;
            v["settings"]["mode"] = "Bypass".into();
        });
        assert_eq!(field_of(&e), "settings.compensator", "{e}");
        let e = edited(|v| v["surprise"] = 1.into());
        assert!(matches!(e, ParamFileError::Json { .. }), "{e}");
        assert!(e.to_string().contains("surprise"), "{e}");
        let e = edited(|v| v["settings"]["drive"]["surprise"] = 1.into());
        assert!(
            e.to_string().contains("surprise"),
            "unknown fields at any depth: {e}"
        );
        let e = parse("{ not json").unwrap_err();
        assert!(matches!(e, ParamFileError::Json { line: 1, .. }), "{e}");
    }
}
