//! Identification and parameters: the `Params` class (a fitted model, its file and its
//! ranking), `load_params` and `identify`.

use crate::convert::{array, json_to_py, vector};
use crate::errors::param_file_error;
use numpy::PyArray1;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use std::path::{Path, PathBuf};
use twinstack_identify::identification::auto::{Ranked, Validation};
use twinstack_identify::identification::run::{
    check_tick_rate, default_fit_until, identify_and_score, parse_model, BoardRate, Identified,
    RunError,
};
use twinstack_identify::identification::{
    coverage, IdentifyError, IdentifyOptions, ModelKind, ThresholdSpread, DEFAULT_OPERATORS,
};
use twinstack_identify::param_file::ParamFile;
use twinstack_identify::preview::ResonancePreview;
use twinstack_identify::stage_model::{Hysteresis, StageModel};
use twinstack_link::measured_data::{ColumnsError, MeasuredData};

/// The record's times: `t` as given, or `k / rate`, or (for a model with neither creep nor a
/// sensor lag, which need the sample period) any uniform spacing.
pub(crate) fn times(
    py: Python<'_>,
    model: &StageModel,
    n: usize,
    t: Option<&Bound<'_, PyAny>>,
    rate: Option<f64>,
) -> PyResult<Vec<f64>> {
    match (t, rate) {
        (Some(_), Some(_)) => Err(PyValueError::new_err("give t or rate, not both")),
        (Some(t), None) => {
            let t = vector(py, t, "t")?;
            if t.len() != n {
                return Err(PyValueError::new_err(format!(
                    "t has {} samples, the signal {n}",
                    t.len()
                )));
            }
            MeasuredData::check_columns(&t, &[]).map_err(|e| PyValueError::new_err(e.to_string()))?;
            Ok(t)
        }
        (None, Some(rate)) => {
            if !(rate.is_finite() && rate > 0.0) {
                return Err(PyValueError::new_err(format!(
                    "rate {rate}: must be a positive number of samples per second"
                )));
            }
            Ok((0..n).map(|k| k as f64 / rate).collect())
        }
        (None, None) if model.creep.is_none() && model.sensor_lag_s == 0.0 => {
            Ok((0..n).map(|k| k as f64).collect())
        }
        (None, None) => Err(PyValueError::new_err(
            "this model has a creep operator or a sensor lag, which run at the record's sample period: give t (seconds) or rate (samples per second)",
        )),
    }
}

/// An identified or loaded model with its parameter file: what `twinstack identify` writes and
/// `twinstack load` sends.
#[pyclass(module = "twinstack", frozen)]
pub(crate) struct Params {
    pub(crate) file: ParamFile,
    pub(crate) model: StageModel,
    ranking: Option<Vec<Ranked>>,
}

impl Params {
    pub(crate) fn from_file(file: ParamFile, model: StageModel) -> Self {
        Self {
            file,
            model,
            ranking: None,
        }
    }
}

#[pymethods]
impl Params {
    /// The model's predicted sensor reading for the drive `u` (volts).
    #[pyo3(signature = (u, t=None, rate=None))]
    fn predict<'py>(
        &self,
        py: Python<'py>,
        u: &Bound<'py, PyAny>,
        t: Option<&Bound<'py, PyAny>>,
        rate: Option<f64>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        let u = vector(py, u, "u")?;
        let t = times(py, &self.model, u.len(), t, rate)?;
        // A sample that is not a number would run through the model's memory into every
        // later one (and, through the sensor lag's alignment, earlier ones).
        MeasuredData::check_columns(&t, &[("u", &u)])
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let model = &self.model;
        let x = py
            .detach(|| model.predict(&t, &u))
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(array(py, x))
    }

    /// The drive (volts) the compensator gives for the desired reading `x`: every sample
    /// inverted exactly (a planned trajectory), or with `measured` a sensor's record followed
    /// through its noise band, as `identify` scores an inverse; with `resonance` (its
    /// frequency, Hz, and damping ratio) a planned trajectory shaped first so that the
    /// stage's resonance does not ring at its corners (`twinstack_identify::preview`).
    #[pyo3(signature = (x, t=None, rate=None, measured=false, resonance=None))]
    fn compensate<'py>(
        &self,
        py: Python<'py>,
        x: &Bound<'py, PyAny>,
        t: Option<&Bound<'py, PyAny>>,
        rate: Option<f64>,
        measured: bool,
        resonance: Option<(f64, f64)>,
    ) -> PyResult<Bound<'py, PyArray1<f64>>> {
        if resonance.is_some() && measured {
            return Err(PyValueError::new_err(
                "resonance shapes a planned trajectory: not with measured=True",
            ));
        }
        if resonance.is_some() && t.is_none() && rate.is_none() {
            return Err(PyValueError::new_err(
                "resonance needs t or rate: the preview is made at the trajectory's sample rate",
            ));
        }
        let x = vector(py, x, "x")?;
        let t = times(py, &self.model, x.len(), t, rate)?;
        MeasuredData::check_columns(&t, &[("x", &x)])
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        let preview = match resonance {
            Some((hz, zeta)) => Some(
                ResonancePreview::at_times(hz, zeta, &t)
                    .map_err(|e| PyValueError::new_err(format!("resonance: {e}")))?,
            ),
            None => None,
        };
        let model = &self.model;
        let shaped = match &preview {
            Some(p) => {
                let (lo, hi) = model.reading_range();
                Some(
                    p.shape_within(&x, lo, hi)
                        .map_err(|e| PyValueError::new_err(format!("resonance: {e}")))?,
                )
            }
            None => None,
        };
        let u = py
            .detach(|| match &shaped {
                Some(shaped) => model.compensate(&t, shaped),
                None if measured => model.compensate_measured(&t, &x),
                None => model.compensate(&t, &x),
            })
            .map_err(|e| PyValueError::new_err(e.to_string()))?;
        Ok(array(py, u))
    }

    /// Writes the parameter file (the JSON `twinstack identify` writes).
    fn save(&self, path: PathBuf) -> PyResult<()> {
        self.file.save(&path).map_err(param_file_error)
    }

    /// The parameter file's JSON text.
    fn to_json(&self) -> String {
        self.file.to_json()
    }

    /// A parameter file's JSON text, checked as `load_params` checks a file.
    #[staticmethod]
    fn from_json(text: &str) -> PyResult<Self> {
        let (file, model) =
            ParamFile::parse(Path::new("<json>"), text).map_err(param_file_error)?;
        Ok(Self::from_file(file, model))
    }

    /// The model's kind: `pi`, `duhem`, `gpi` or `bouc-wen`.
    #[getter]
    fn model(&self) -> &'static str {
        match self.model.hysteresis {
            Hysteresis::Pi(_) => "pi",
            Hysteresis::Duhem(_) => "duhem",
            Hysteresis::GeneralisedPi(_) => "gpi",
            Hysteresis::BoucWen(_) => "bouc-wen",
        }
    }

    /// Whether a creep operator runs in series with the model.
    #[getter]
    fn creep(&self) -> bool {
        self.model.creep.is_some()
    }

    /// Whether a static output map follows the model (a Bouc–Wen's, fitted with
    /// `output_map=True`, or `twinstack identify --output-map`).
    #[getter]
    fn output_map(&self) -> bool {
        self.model.output_map.is_some()
    }

    /// The model's input range, volts.
    #[getter]
    fn input_range(&self) -> (f64, f64) {
        (self.model.scaling.input_min, self.model.scaling.input_max)
    }

    /// The model's (sign-corrected) output range, in its output unit.
    #[getter]
    fn output_range(&self) -> (f64, f64) {
        (self.model.scaling.output_min, self.model.scaling.output_max)
    }

    /// `1.0`, or `-1.0` for a sensor that reads the model's output negated.
    #[getter]
    fn output_sign(&self) -> f64 {
        self.model.output_sign
    }

    /// The sensor's lag behind the drive, seconds.
    #[getter]
    fn sensor_lag_s(&self) -> f64 {
        self.model.sensor_lag_s
    }

    /// The stage's resonance as `calibrate` measured it, `(frequency_hz, damping)`, or
    /// `None` where the file holds none: what `compensate(..., resonance=params.resonance)`
    /// and `Board.stream(..., resonance=params.resonance)` shape a planned trajectory for.
    #[getter]
    fn resonance(&self) -> Option<(f64, f64)> {
        self.file.resonance.map(|r| (r.frequency_hz, r.damping))
    }

    /// The fastest motion the model was fitted on, Hz: the highest rate at which the fitted
    /// part's drive swings by a fifth of its span or more; `None` where the file does not
    /// say (a file written before it was recorded, or by hand).
    #[getter]
    fn fastest_motion_hz(&self) -> Option<f64> {
        self.file
            .identification
            .as_ref()
            .and_then(|r| r.fastest_motion_hz)
    }

    /// The unit of the model's output (the identified record's `x`).
    #[getter]
    fn output_unit(&self) -> &str {
        &self.file.units.output
    }

    /// The board settings the file carries, as a dict (the JSON's `settings`).
    #[getter]
    fn settings<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let v = serde_json::to_value(&self.file.settings)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        json_to_py(py, &v)
    }

    /// How the model was fitted and scored (the file's `identification`), or `None`.
    #[getter]
    fn identification<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyAny>>> {
        match &self.file.identification {
            None => Ok(None),
            Some(r) => {
                let v =
                    serde_json::to_value(r).map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
                json_to_py(py, &v).map(Some)
            }
        }
    }

    /// `model="auto"`'s ranking, best first, by what the stage will see: dicts with `label`,
    /// the forward fit's `max_pct`, `rms_pct`, the compensator's `inverse_max_pct`,
    /// `inverse_rms_pct` (its inverse on the measured output against the measured drive),
    /// `tracking_max_pct`, `tracking_rms_pct` (compensated tracking through the best forward
    /// model), `compensated_pct` (the larger max, the ranking's key), `set_aside` (why a
    /// candidate whose inverse ratchets was ranked last), `not_admitted` (the reason, for a
    /// model the board would not run at `tick_rate`), or `error` for one that could not be
    /// fitted; `None` when one model was asked for or the file was loaded.
    #[getter]
    fn ranking<'py>(&self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyList>>> {
        let Some(ranking) = &self.ranking else {
            return Ok(None);
        };
        let list = PyList::empty(py);
        for r in ranking {
            let d = PyDict::new(py);
            d.set_item("label", &r.label)?;
            if let Some(f) = r.validation.figures() {
                d.set_item("max_pct", f.max_pct)?;
                d.set_item("rms_pct", f.rms_pct)?;
            }
            for (name, figures) in [("inverse", r.inverse), ("tracking", r.tracking)] {
                if let Some(f) = figures {
                    d.set_item(format!("{name}_max_pct"), f.max_pct)?;
                    d.set_item(format!("{name}_rms_pct"), f.rms_pct)?;
                }
            }
            if let Some(c) = r.compensated() {
                d.set_item("compensated_pct", c)?;
            }
            if let Some(why) = &r.set_aside {
                d.set_item("set_aside", why)?;
            }
            match &r.validation {
                Validation::Scored(_) => {}
                Validation::NotAdmitted { why, .. } => d.set_item("not_admitted", why)?,
                Validation::NotFitted(why) => d.set_item("error", why)?,
            }
            list.append(d)?;
        }
        Ok(Some(list))
    }

    /// The model's kind, creep, ranges and output unit.
    fn __repr__(&self) -> String {
        let s = &self.model.scaling;
        format!(
            "Params(model={:?}, creep={}, output_map={}, input_range=({}, {}), output_range=({}, {}), output_unit={:?})",
            self.model(),
            self.creep(),
            self.output_map(),
            s.input_min,
            s.input_max,
            s.output_min,
            s.output_max,
            self.file.units.output
        )
    }
}

/// Reads and checks a parameter file (`twinstack identify`'s output, or `Params.save`'s).
#[pyfunction]
pub(crate) fn load_params(path: PathBuf) -> PyResult<Params> {
    let (file, model) = ParamFile::load(&path).map_err(param_file_error)?;
    Ok(Params::from_file(file, model))
}

/// Identifies a model from a measured record (`t` seconds, `u` drive volts, `x` reading).
#[pyfunction]
#[pyo3(signature = (t, u, x, model="auto", creep=None, fit_until=None, operators=None, thresholds="uniform", lag=None, output_unit="um", tick_rate=None, observer=true, output_map=false, fastest_hz=None))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn identify(
    py: Python<'_>,
    t: &Bound<'_, PyAny>,
    u: &Bound<'_, PyAny>,
    x: &Bound<'_, PyAny>,
    model: &str,
    creep: Option<bool>,
    fit_until: Option<f64>,
    operators: Option<usize>,
    thresholds: &str,
    lag: Option<f64>,
    output_unit: &str,
    tick_rate: Option<f64>,
    observer: bool,
    output_map: bool,
    fastest_hz: Option<f64>,
) -> PyResult<Params> {
    let choice = parse_model(model).map_err(PyValueError::new_err)?;
    if let Some(hz) = fastest_hz {
        coverage::check_named(hz).map_err(|e| PyValueError::new_err(format!("fastest_hz {e}")))?;
    }
    if let Some(rate) = tick_rate {
        check_tick_rate(rate).map_err(|e| PyValueError::new_err(format!("tick_rate {e}")))?;
    }
    // A P–I sized to the rate unless its operators were asked for.
    let rate = tick_rate.map(|hz| BoardRate::sizing(hz, operators.is_some()));
    let spread = match thresholds.to_ascii_lowercase().as_str() {
        "uniform" => ThresholdSpread::Uniform,
        "geometric" => ThresholdSpread::Geometric,
        other => {
            return Err(PyValueError::new_err(format!(
                "thresholds {other:?}: expected \"uniform\" or \"geometric\""
            )))
        }
    };
    let (t, u, x) = (
        vector(py, t, "t")?,
        vector(py, u, "u")?,
        vector(py, x, "x")?,
    );
    let data = MeasuredData::from_columns("<arrays>", t, Some(u), Some(x))
        .map_err(|e: ColumnsError| PyValueError::new_err(e.to_string()))?;
    let fit_until = fit_until.unwrap_or_else(|| default_fit_until(&data.t));
    if !fit_until.is_finite() {
        return Err(PyValueError::new_err(format!(
            "fit_until {fit_until}: not a finite number of seconds"
        )));
    }
    let mut options = IdentifyOptions::new(ModelKind::Pi, fit_until);
    options.operators = operators.unwrap_or(DEFAULT_OPERATORS);
    options.thresholds = spread;
    if let Some(lag) = lag {
        options.given_lag(lag).map_err(PyValueError::new_err)?;
    }
    options.observer = observer;
    options.output_map = output_map;
    let run: Result<Identified, RunError> =
        py.detach(|| identify_and_score(&data, choice, &options, creep, output_unit, rate));
    let run = run.map_err(|e| match e {
        RunError::Identify(e @ IdentifyError::NoOutputMapFor(_)) => {
            PyValueError::new_err(format!("output_map: {e}"))
        }
        e => PyValueError::new_err(e.to_string()),
    })?;
    let ranking = run.auto.as_ref().map(|a| a.ranking.clone());
    // A record an octave slower than the motion named: the same advice `identify
    // --fastest-hz` prints, as a `UserWarning` (the model is still returned).
    if let Some(advice) = fastest_hz.and_then(|n| {
        coverage::advice(
            run.file
                .identification
                .as_ref()
                .and_then(|r| r.fastest_motion_hz),
            n,
        )
    }) {
        let message =
            std::ffi::CString::new(advice).map_err(|e| PyValueError::new_err(e.to_string()))?;
        PyErr::warn(
            py,
            &py.get_type::<pyo3::exceptions::PyUserWarning>(),
            &message,
            1,
        )?;
    }
    Ok(Params {
        model: run.identification.model,
        file: run.file,
        ranking,
    })
}
