//! `twinstack._native`: the Python package's extension module, a thin layer over the `hal-sim`
//! library — the same protocol client, in-process board, identification and parameter file as
//! the `twinstack` command line. Nothing here speaks the wire protocol or runs a model itself:
//! it converts Python values (numpy arrays, strings, dicts) to the library's types and back,
//! maps the library's errors onto Python exceptions, and lets go of the interpreter's lock
//! (`Python::detach`) while it waits on a board or fits a model.
//!
//! The Python-facing documentation is in `twinstack/_native.pyi` and the book's Python
//! chapter (`docs/src/guide/python.md`).

use pyo3::exceptions::PyException;
use pyo3::prelude::*;

mod board;
mod convert;
mod errors;
mod params;

use board::{settings_schema, Board};
use params::{identify, load_params, Params};

pyo3::create_exception!(
    twinstack,
    BoardError,
    PyException,
    "A request the board refused (its NACK), or a parameter load refused before sending."
);

/// The extension module.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("BoardError", m.py().get_type::<BoardError>())?;
    m.add_class::<Board>()?;
    m.add_class::<Params>()?;
    m.add_function(wrap_pyfunction!(identify, m)?)?;
    m.add_function(wrap_pyfunction!(load_params, m)?)?;
    m.add_function(wrap_pyfunction!(settings_schema, m)?)?;
    Ok(())
}
