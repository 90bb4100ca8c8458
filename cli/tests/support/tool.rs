//! The `twinstack` binary run as a user runs it, for the tests that check its output and exit
//! code (included with `#[path]`).
#![allow(dead_code)] // each test binary uses its own subset

use std::process::{Command, Output};

/// `twinstack ARGS…`, run to its end.
pub fn twinstack(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(args)
        .output()
        .expect("twinstack runs")
}

/// `twinstack ARGS…`, which must succeed: its standard output.
pub fn ok(args: &[&str]) -> String {
    let o = twinstack(args);
    assert!(
        o.status.success(),
        "{args:?}: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// A run's standard output and standard error, as text.
pub fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}
