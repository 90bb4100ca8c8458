//! Golden vectors, host side: which sets there are, how their inputs are made, how they are
//! generated and written, and how they are checked against the `f64` reference.
//!
//! * [`sets`] — the vector sets: each compensator (none, inverse P–I N = 8/16/32, inverse
//!   Duhem, generalised P–I, Bouc–Wen) and each observer (none, P–I, Duhem, generalised P–I,
//!   Bouc–Wen), with creep, the preview and the output map, in bypass, open and closed loop, each a
//!   [`twinstack_golden::Recipe`] (the board's hardware and the settings a parameter load
//!   carries), on models identified from the repository's `data/` (parameter files committed in
//!   `tests/golden/params/`).
//! * [`scenario`] — the setpoint and fault timeline every set runs.
//! * [`generate`] — runs the library's tick in closed loop on a sensor model and records
//!   inputs and outputs ([`twinstack_golden`] holds the file format and the replay).
//! * [`reference_tick`] — the `f64` reference of the whole tick and the check of stored
//!   outputs against it.
//!
//! `cargo run --release -p twinstack-cli -- golden --write` regenerates `tests/golden/vectors.bin`.

pub mod generate;
pub mod reference_tick;
pub mod scenario;
pub mod sets;

use std::path::PathBuf;

/// The repository's golden directory (`tests/golden`), found from this crate's manifest.
pub fn default_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join("tests")
        .join("golden")
}

/// The vector file's name inside the golden directory.
pub const VECTOR_FILE: &str = "vectors.bin";

/// The command that regenerates the vectors (quoted in every failure message).
pub const REGENERATE: &str = "cargo run --release -p twinstack-cli -- golden --write";
