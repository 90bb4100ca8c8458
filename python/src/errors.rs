//! The library's errors as Python exceptions: a board's refusal as `BoardError` with its
//! field and limit, link, port, parameter-file and settings-path errors as the built-in ones.

use crate::BoardError;
use hal_sim::port::PortError;
use pyo3::exceptions::{
    PyConnectionError, PyFileNotFoundError, PyKeyError, PyOSError, PyRuntimeError, PyTimeoutError,
    PyValueError,
};
use pyo3::prelude::*;
use twinstack::protocol::messages::NackReason;
use twinstack::refusal::Rule;
use twinstack_identify::param_file::ParamFileError;
use twinstack_identify::tune::measure::MeasureError;
use twinstack_identify::tune::TuneError;
use twinstack_link::capture::CaptureError;
use twinstack_link::client::{nack_text, LinkError};
use twinstack_link::learning::TableError;
use twinstack_link::settings_path;
use twinstack_link::telemetry::RunError;

/// The rule's limit, where it has one, in the field's own units.
pub(crate) fn rule_limit(rule: &Rule) -> Option<f64> {
    match *rule {
        Rule::AtLeast(x) | Rule::Above(x) | Rule::AtMost(x) | Rule::Below(x) => Some(x),
        Rule::TooMany(n) => Some(n as f64),
        _ => None,
    }
}

/// The rule's name without its limit (`AtMost`, `NotFinite`, …).
pub(crate) fn rule_name(rule: &Rule) -> String {
    let debug = format!("{rule:?}");
    debug.split('(').next().unwrap_or("").to_string()
}

/// A `BoardError` with its attributes set.
pub(crate) fn board_error(
    py: Python<'_>,
    message: String,
    request: &str,
    field: Option<String>,
    reason: String,
    rule: Option<String>,
    limit: Option<f64>,
) -> PyErr {
    let err = BoardError::new_err(message);
    let value = err.value(py);
    let set = || -> PyResult<()> {
        value.setattr("request", request)?;
        value.setattr("field", field)?;
        value.setattr("reason", reason)?;
        value.setattr("rule", rule)?;
        value.setattr("limit", limit)?;
        Ok(())
    };
    match set() {
        Ok(()) => err,
        Err(e) => e,
    }
}

/// A link error as a Python exception: a NACK is a `BoardError` carrying the field, the
/// reason and the limit; a timeout a `TimeoutError`; a failed link a `ConnectionError`.
pub(crate) fn link_error(py: Python<'_>, e: LinkError) -> PyErr {
    match e {
        LinkError::Nack { request, reason } => {
            let message = e.to_string();
            match reason {
                NackReason::Refused(r) => board_error(
                    py,
                    message,
                    request,
                    Some(r.field.to_string()),
                    r.rule.to_string(),
                    Some(rule_name(&r.rule)),
                    rule_limit(&r.rule),
                ),
                other => board_error(py, message, request, None, nack_text(&other), None, None),
            }
        }
        LinkError::Timeout { .. } => PyTimeoutError::new_err(e.to_string()),
        LinkError::Io(_) => PyConnectionError::new_err(e.to_string()),
        LinkError::Stopped { .. } => pyo3::exceptions::PyKeyboardInterrupt::new_err(e.to_string()),
        other => PyRuntimeError::new_err(other.to_string()),
    }
}

pub(crate) fn port_error(e: PortError) -> PyErr {
    match e {
        PortError::Empty => PyValueError::new_err(e.to_string()),
        PortError::Serial(twinstack_link::serial::SerialError::Missing { .. }) => {
            PyFileNotFoundError::new_err(format!("{e}; {}", hal_sim::port::available_ports()))
        }
        PortError::Serial(twinstack_link::serial::SerialError::BadBaud(_)) => {
            PyValueError::new_err(e.to_string())
        }
        PortError::Socket(_) => PyConnectionError::new_err(e.to_string()),
        other => PyOSError::new_err(other.to_string()),
    }
}

pub(crate) fn param_file_error(e: ParamFileError) -> PyErr {
    match e {
        ParamFileError::Io { ref source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        ParamFileError::Io { .. } => PyOSError::new_err(e.to_string()),
        other => PyValueError::new_err(other.to_string()),
    }
}

/// A settings path's error as Python's: ``KeyError`` for a path that names nothing (or a
/// part not set), ``ValueError`` for a value of the wrong type.
pub(crate) fn path_error(e: settings_path::PathError) -> PyErr {
    match e {
        settings_path::PathError::Invalid { .. } => PyValueError::new_err(e.to_string()),
        _ => PyKeyError::new_err(e.to_string()),
    }
}

/// A telemetry run's error: a rate the link cannot carry is the board's refusal
/// (`BoardError`, its message naming the most it can), a rate that cannot be had
/// `ValueError`, a run that stalls `TimeoutError`, the link's as [`link_error`].
pub(crate) fn run_error(py: Python<'_>, e: RunError) -> PyErr {
    match e {
        RunError::Link(l) => link_error(py, l),
        RunError::Rate(_) => PyValueError::new_err(e.to_string()),
        RunError::TooFast { refusal, .. } => board_error(
            py,
            e.to_string(),
            "Telemetry",
            Some(refusal.field.to_string()),
            refusal.rule.to_string(),
            Some(rule_name(&refusal.rule)),
            rule_limit(&refusal.rule),
        ),
        RunError::Stalled { .. } => PyTimeoutError::new_err(e.to_string()),
        RunError::Frame(_) | RunError::Convert(_) | RunError::Stopped { .. } => {
            PyRuntimeError::new_err(e.to_string())
        }
    }
}

/// A learning table's error: the link's as [`link_error`]; a table the board has no period
/// for, or of the wrong length, `ValueError`.
pub(crate) fn table_error(py: Python<'_>, e: TableError) -> PyErr {
    match e {
        TableError::Link(l) => link_error(py, l),
        TableError::NotConfigured | TableError::Length { .. } => {
            PyValueError::new_err(e.to_string())
        }
    }
}

/// A tuning's error: the link's as [`link_error`] (a board's refusal a `BoardError`), a
/// capture that does not finish `TimeoutError`, a sweep option out of range or a checked gain
/// set refused on the fitted model `ValueError`, a stage that cannot be measured, fitted or
/// tuned for the margins `RuntimeError`.
pub(crate) fn tune_error(py: Python<'_>, e: TuneError) -> PyErr {
    match e {
        TuneError::Link { source, .. }
        | TuneError::Measure(MeasureError::Link { source, .. })
        | TuneError::Measure(MeasureError::Capture {
            source: CaptureError::Link(source),
            ..
        }) => link_error(py, source),
        e @ TuneError::Measure(MeasureError::Capture {
            source: CaptureError::NotDone { .. },
            ..
        }) => PyTimeoutError::new_err(e.to_string()),
        e @ (TuneError::Measure(MeasureError::Option { .. }) | TuneError::Refused(_)) => {
            PyValueError::new_err(e.to_string())
        }
        e => PyRuntimeError::new_err(e.to_string()),
    }
}
