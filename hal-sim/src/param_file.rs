//! The versioned parameter file (`PARAMS.json`) that `identify` writes and `predict`,
//! `compensate` and the board loader read.
//!
//! ```json
//! { "format": "twinstack-params", "version": 1, "model": "pi",
//!   "units": { "time": "s", "input": "V", "output": "units of the x column" },
//!   "input_range": { "min": -153.0, "max": 153.0 },       // volts, maps to Q2.30 -1 … 1
//!   "output_range": { "min": -19.9, "max": 21.8 },        // sign-corrected output units
//!   "output_sign": 1, "sensor_lag_s": 0.0,
//!   "pi": { "a0": 0.0, "offset": …, "thresholds": [...], "weights": [...] },
//!   "fixed_point": { "signal_format": "Q2.30", "gain_format": "Q8.24", "pi_forward": {...}, "pi_inverse": {...} },
//!   "identification": { ... how it was fitted and scored; informative only ... } }
//! ```
//!
//! Loading checks, in order: JSON syntax, `format`, `version` (only [`VERSION`] is known),
//! the fields (unknown ones are refused), the model section matching `model`, the ranges,
//! sign and lag, that the library accepts the model for observer and compensator, and that
//! the `fixed_point` section is exactly what the library computes from the physical
//! parameters (so a hand-edited file cannot disagree with itself).

use crate::identification::score::ErrorFigures;
use crate::stage_model::{Hysteresis, StageModel};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use twinstack::duhem::Duhem;
use twinstack::fixed_point::{gain_from_f64, signal_from_f64};
use twinstack::prandtl_ishlinskii::{InversePrandtlIshlinskii, PrandtlIshlinskii};
use twinstack::{DuhemParams, ParamError, PiParams, Scaling};

/// The `format` tag of a parameter file.
pub const FORMAT: &str = "twinstack-params";
/// The one version this build reads and writes.
pub const VERSION: u64 = 1;

/// A closed range.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Range {
    /// Lower end.
    pub min: f64,
    /// Upper end.
    pub max: f64,
}

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

/// P–I section: `y = a0·u + Σ w_i P_{r_i}[u] + offset` (volts, output units per volt).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PiSection {
    /// Linear term, output units per volt.
    pub a0: f64,
    /// Offset, output units.
    pub offset: f64,
    /// Thresholds, volts.
    pub thresholds: Vec<f64>,
    /// Weights, output units per volt.
    pub weights: Vec<f64>,
}

/// Duhem section: `ẏ = α|u̇|(βu + offset − y) + γu̇`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DuhemSection {
    /// α, per volt.
    pub alpha: f64,
    /// β, output units per volt.
    pub beta: f64,
    /// γ, output units per volt.
    pub gamma: f64,
    /// Offset of the anhysteretic curve, output units.
    pub offset: f64,
}

/// A P–I operator bank as the firmware holds it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FixedBank {
    /// Thresholds, Q2.30 normalised input (forward) or output (inverse).
    pub thresholds_q2_30: Vec<i32>,
    /// Weights, Q8.24 normalised.
    pub weights_q8_24: Vec<i32>,
    /// Offset, Q2.30 normalised output.
    pub offset_q2_30: i32,
}

/// Duhem coefficients as the firmware holds them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FixedDuhem {
    /// α, Q8.24 normalised.
    pub alpha_q8_24: i32,
    /// β, Q8.24 normalised.
    pub beta_q8_24: i32,
    /// γ, Q8.24 normalised.
    pub gamma_q8_24: i32,
    /// Offset δ, Q2.30 normalised output.
    pub offset_q2_30: i32,
}

/// The fixed-point image of the model (derived; checked on load).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FixedPoint {
    /// Signal format.
    pub signal_format: String,
    /// Gain format.
    pub gain_format: String,
    /// Forward P–I bank (observer).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pi_forward: Option<FixedBank>,
    /// Inverse P–I bank (compensator).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pi_inverse: Option<FixedBank>,
    /// Duhem coefficients.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duhem: Option<FixedDuhem>,
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
    /// Lag, samples of the record.
    pub lag_samples: usize,
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
}

/// The whole file.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ParamFile {
    /// Always [`FORMAT`].
    pub format: String,
    /// Always [`VERSION`].
    pub version: u64,
    /// `"pi"` or `"duhem"`.
    pub model: String,
    /// Units.
    pub units: Units,
    /// Drive range, volts (maps to −1 … 1).
    pub input_range: Range,
    /// Sign-corrected output range (maps to −1 … 1).
    pub output_range: Range,
    /// `1` or `−1`: sensor reading = `output_sign` × model output.
    pub output_sign: f64,
    /// Sensor lag behind the drive, seconds.
    pub sensor_lag_s: f64,
    /// P–I parameters (when `model` is `"pi"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pi: Option<PiSection>,
    /// Duhem parameters (when `model` is `"duhem"`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub duhem: Option<DuhemSection>,
    /// Fixed-point image.
    pub fixed_point: FixedPoint,
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
    #[error("{}: `version` is {found}, this hal-sim reads version {VERSION} only", path.display())]
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
        /// The field.
        field: &'static str,
        /// Why.
        reason: String,
    },
}

fn fixed_bank(bank: &twinstack::prandtl_ishlinskii::PlayOperatorBank, offset: i32) -> FixedBank {
    let n = bank.operators();
    FixedBank {
        thresholds_q2_30: (0..n).map(|i| bank.threshold(i)).collect(),
        weights_q8_24: (0..n).map(|i| bank.weight(i)).collect(),
        offset_q2_30: offset,
    }
}

/// The fixed-point image of `model`, as the library computes it.
pub fn fixed_point_image(model: &StageModel) -> Result<FixedPoint, ParamError> {
    let s = &model.scaling;
    let mut fp = FixedPoint {
        signal_format: "Q2.30".into(),
        gain_format: "Q8.24".into(),
        pi_forward: None,
        pi_inverse: None,
        duhem: None,
    };
    match &model.hysteresis {
        Hysteresis::Pi(p) => {
            let fwd = PrandtlIshlinskii::new(p, s)?;
            let inv = InversePrandtlIshlinskii::new(p, s)?;
            fp.pi_forward = Some(fixed_bank(fwd.bank(), fwd.offset()));
            // The inverse subtracts the forward offset from the desired output.
            fp.pi_inverse = Some(fixed_bank(inv.bank(), fwd.offset()));
        }
        Hysteresis::Duhem(p) => {
            Duhem::new(p, s)?;
            let n = p.normalized(s)?;
            fp.duhem = Some(FixedDuhem {
                alpha_q8_24: gain_from_f64(n.alpha),
                beta_q8_24: gain_from_f64(n.beta),
                gamma_q8_24: gain_from_f64(n.gamma),
                offset_q2_30: signal_from_f64(n.offset),
            });
        }
    }
    Ok(fp)
}

impl ParamFile {
    /// The file for `model`, with `identification` recorded.
    pub fn from_model(
        model: &StageModel,
        output_units: &str,
        identification: Option<IdentificationRecord>,
    ) -> Result<Self, ParamError> {
        let s = &model.scaling;
        let (name, pi, duhem) = match &model.hysteresis {
            Hysteresis::Pi(p) => (
                "pi",
                Some(PiSection {
                    a0: p.a0,
                    offset: p.offset,
                    thresholds: p.thresholds.to_vec(),
                    weights: p.weights.to_vec(),
                }),
                None,
            ),
            Hysteresis::Duhem(p) => (
                "duhem",
                None,
                Some(DuhemSection {
                    alpha: p.alpha,
                    beta: p.beta,
                    gamma: p.gamma,
                    offset: p.offset,
                }),
            ),
        };
        Ok(Self {
            format: FORMAT.into(),
            version: VERSION,
            model: name.into(),
            units: Units {
                time: "s".into(),
                input: "V".into(),
                output: output_units.into(),
            },
            input_range: Range {
                min: s.input_min,
                max: s.input_max,
            },
            output_range: Range {
                min: s.output_min,
                max: s.output_max,
            },
            output_sign: model.output_sign,
            sensor_lag_s: model.sensor_lag_s,
            pi,
            duhem,
            fixed_point: fixed_point_image(model)?,
            identification,
        })
    }

    /// The JSON text.
    pub fn to_json(&self) -> String {
        // Serialising plain data with finite numbers cannot fail.
        serde_json::to_string_pretty(self).unwrap_or_default() + "\n"
    }

    /// Reads and validates `path`.
    pub fn load(path: &Path) -> Result<(Self, StageModel), ParamFileError> {
        let text = std::fs::read_to_string(path).map_err(|source| ParamFileError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(path, &text)
    }

    /// Parses and validates `text` (read from `path`, used in errors).
    pub fn parse(path: &Path, text: &str) -> Result<(Self, StageModel), ParamFileError> {
        let p = || path.to_path_buf();
        let json_err = |e: serde_json::Error| ParamFileError::Json {
            path: p(),
            line: e.line(),
            column: e.column(),
            message: e
                .to_string()
                .split(" at line ")
                .next()
                .unwrap_or("")
                .to_string(),
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
        let field = |field: &'static str, reason: String| ParamFileError::Field {
            path: p(),
            field,
            reason,
        };
        let hysteresis = match (file.model.as_str(), &file.pi, &file.duhem) {
            ("pi", Some(s), None) => Hysteresis::Pi(
                PiParams::new(s.a0, s.offset, &s.thresholds, &s.weights)
                    .and_then(|p| p.validate().map(|_| p))
                    .map_err(|e| field("pi", e.to_string()))?,
            ),
            ("duhem", None, Some(s)) => {
                let d = DuhemParams {
                    alpha: s.alpha,
                    beta: s.beta,
                    gamma: s.gamma,
                    offset: s.offset,
                };
                d.validate().map_err(|e| field("duhem", e.to_string()))?;
                Hysteresis::Duhem(d)
            }
            ("pi", None, _) => return Err(field("pi", "missing (model is \"pi\")".into())),
            ("duhem", _, None) => {
                return Err(field("duhem", "missing (model is \"duhem\")".into()))
            }
            ("pi", _, Some(_)) | ("duhem", Some(_), _) => {
                return Err(field(
                    "model",
                    format!(
                        "is \"{}\" but the file has both a pi and a duhem section",
                        file.model
                    ),
                ))
            }
            (other, _, _) => {
                return Err(field(
                    "model",
                    format!("\"{other}\" is not \"pi\" or \"duhem\""),
                ))
            }
        };
        let scaling = Scaling::new(
            file.input_range.min,
            file.input_range.max,
            file.output_range.min,
            file.output_range.max,
        )
        .map_err(|e| match e {
            ParamError::EmptyInputRange => {
                field("input_range", "must be finite with min < max".into())
            }
            _ => field("output_range", "must be finite with min < max".into()),
        })?;
        if file.output_sign != 1.0 && file.output_sign != -1.0 {
            return Err(field(
                "output_sign",
                format!("{} is not 1 or -1", file.output_sign),
            ));
        }
        if !(file.sensor_lag_s.is_finite() && file.sensor_lag_s >= 0.0) {
            return Err(field("sensor_lag_s", "must be a finite number >= 0".into()));
        }
        let model = StageModel {
            hysteresis,
            scaling,
            output_sign: file.output_sign,
            sensor_lag_s: file.sensor_lag_s,
        };
        model.check().map_err(|e| {
            field(
                if file.model == "pi" { "pi" } else { "duhem" },
                e.to_string(),
            )
        })?;
        let image = fixed_point_image(&model).map_err(|e| field("fixed_point", e.to_string()))?;
        if image != file.fixed_point {
            return Err(field(
                "fixed_point",
                "does not match the physical parameters and ranges (edited by hand? re-run identify)".into(),
            ));
        }
        Ok((file, model))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model() -> StageModel {
        StageModel {
            hysteresis: Hysteresis::Pi(
                PiParams::new(0.0, 0.5, &[0.0, 30.0, 60.0], &[0.08, 0.03, 0.02]).unwrap(),
            ),
            scaling: Scaling::new(-150.0, 150.0, -20.0, 21.0).unwrap(),
            output_sign: -1.0,
            sensor_lag_s: 0.005,
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
            let f = ParamFile::from_model(&m, "um", None).unwrap();
            let (back, loaded) = parse(&f.to_json()).unwrap();
            assert_eq!(back, f);
            assert_eq!(loaded, m);
        }
    }

    fn edited(f: impl Fn(&mut serde_json::Value)) -> ParamFileError {
        let mut v: serde_json::Value = serde_json::from_str(
            &ParamFile::from_model(&model(), "um", None)
                .unwrap()
                .to_json(),
        )
        .unwrap();
        f(&mut v);
        parse(&v.to_string()).unwrap_err()
    }

    #[test]
    fn each_bad_field_is_named() {
        let e = edited(|v| v["version"] = 2.into());
        assert!(matches!(e, ParamFileError::Version { .. }), "{e}");
        let e = edited(|v| v["format"] = "other".into());
        assert!(matches!(e, ParamFileError::Format { .. }), "{e}");
        let e = edited(|v| v["output_sign"] = 0.5.into());
        assert!(
            matches!(
                e,
                ParamFileError::Field {
                    field: "output_sign",
                    ..
                }
            ),
            "{e}"
        );
        let e = edited(|v| v["input_range"]["max"] = (-200.0).into());
        assert!(
            matches!(
                e,
                ParamFileError::Field {
                    field: "input_range",
                    ..
                }
            ),
            "{e}"
        );
        let e = edited(|v| v["pi"]["weights"][0] = (-0.5).into());
        assert!(
            matches!(e, ParamFileError::Field { field: "pi", .. }),
            "{e}"
        );
        assert!(e.to_string().contains("operator 1"), "{e}");
        let e = edited(|v| v["fixed_point"]["pi_forward"]["offset_q2_30"] = 7.into());
        assert!(
            matches!(
                e,
                ParamFileError::Field {
                    field: "fixed_point",
                    ..
                }
            ),
            "{e}"
        );
        let e = edited(|v| v["model"] = "duhem".into());
        assert!(
            matches!(e, ParamFileError::Field { field: "duhem", .. }),
            "{e}"
        );
        let e = edited(|v| v["surprise"] = 1.into());
        assert!(matches!(e, ParamFileError::Json { .. }), "{e}");
        assert!(e.to_string().contains("surprise"), "{e}");
        let e = parse("{ not json").unwrap_err();
        assert!(matches!(e, ParamFileError::Json { line: 1, .. }), "{e}");
    }
}
