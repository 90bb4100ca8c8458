//! Python values in and out: numpy arrays and sequences as `f64` vectors, vectors as numpy
//! arrays, JSON as Python objects, and setpoints as wire values.

use numpy::{PyArray1, PyArrayMethods};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use twinstack_link::setpoint_file::{to_wire, SetpointUnits};

/// `obj` as a one-dimensional array of `f64`: any numpy array or sequence of real numbers
/// (float or integer dtypes, converted to float64). Another dtype is a `TypeError`, another
/// shape or an empty array a `ValueError`, both naming `name`.
pub(crate) fn vector(py: Python<'_>, obj: &Bound<'_, PyAny>, name: &str) -> PyResult<Vec<f64>> {
    let np = py.import("numpy")?;
    let arr = np.call_method1("asarray", (obj,)).map_err(|e| {
        PyTypeError::new_err(format!(
            "{name}: cannot be read as an array of numbers ({})",
            e.value(py)
        ))
    })?;
    let dtype = arr.getattr("dtype")?;
    let kind: String = dtype.getattr("kind")?.extract()?;
    if !matches!(kind.as_str(), "f" | "i" | "u") {
        return Err(PyTypeError::new_err(format!(
            "{name}: dtype {} is not a real number type (give a float or integer array, e.g. float64)",
            dtype.str()?
        )));
    }
    let ndim: usize = arr.getattr("ndim")?.extract()?;
    if ndim != 1 {
        return Err(PyValueError::new_err(format!(
            "{name} must be one-dimensional, got shape {}",
            arr.getattr("shape")?.repr()?
        )));
    }
    let arr = np.call_method1("ascontiguousarray", (arr, np.getattr("float64")?))?;
    let arr = arr.cast::<PyArray1<f64>>().map_err(PyErr::from)?;
    let values = arr.readonly().as_slice()?.to_vec();
    if values.is_empty() {
        return Err(PyValueError::new_err(format!("{name} is empty")));
    }
    Ok(values)
}

pub(crate) fn array<'py>(py: Python<'py>, values: Vec<f64>) -> Bound<'py, PyArray1<f64>> {
    PyArray1::from_vec(py, values)
}

/// A JSON value as the Python object `json.loads` makes of it.
pub(crate) fn json_to_py<'py>(
    py: Python<'py>,
    value: &serde_json::Value,
) -> PyResult<Bound<'py, PyAny>> {
    py.import("json")?
        .call_method1("loads", (value.to_string(),))
}

/// `values` as wire setpoints: normalised (−1…1), or in the output units of `settings`'s
/// ranges; a bad value is refused naming `name[k]`.
pub(crate) fn wire_values(
    values: &[f64],
    normalised: bool,
    settings: &twinstack::config::settings::Settings,
    name: &str,
) -> PyResult<Vec<i16>> {
    let units = if normalised {
        SetpointUnits::Normalised
    } else {
        SetpointUnits::Output(&settings.ranges)
    };
    values
        .iter()
        .enumerate()
        .map(|(k, &v)| {
            to_wire(v, units).map_err(|m| PyValueError::new_err(format!("{name}[{k}]: {m}")))
        })
        .collect()
}
