//! The `twinstack` subcommands, one module each: `run(&Args) -> anyhow::Result<()>`.
//!
//! Board commands (`calibrate`, `stream`, `load`, `params`, `mode`, `recall`, `status`,
//! `get`, `set`, `waveform`, `stop`, `record`, `telemetry`, `coarse`, `scan`, `sequence`, `selftest`, `analog`, `tune`, `view`, and `learn` with
//! `--port`) share [`board_link`]'s `--port` / `--baud` / `--timeout-ms`.

/// The exit codes of every `twinstack` command, as `twinstack --help` lists them.
pub const EXIT_CODES: &str = "\
Exit codes:
  0  done
  1  error: a bad file, a link failure, a refusal by the board (the message names the field and
     its limit), a failed check; the message says which
  2  usage: a bad or missing argument (including no --port and no TWINSTACK_PORT)
  3  `stream` completed with underruns: every setpoint was accepted, but the board's queue ran
     dry while setpoints were still to come

Environment:
  TWINSTACK_PORT  the board's port when --port is not given (e.g. /dev/ttyUSB0, tcp:127.0.0.1:4000)";

/// Exit code of an error.
pub const EXIT_ERROR: u8 = 1;
/// Exit code of a usage error (clap's, and [`board_link::UsageError`]).
pub const EXIT_USAGE: u8 = 2;

/// The longest wait or duration a flag takes, seconds: a day.
pub const MAX_SECONDS: f64 = 86_400.0;

/// A flag's wait that may be none (clap's value parser: a usage error naming the value): a
/// number of seconds from 0 to [`MAX_SECONDS`].
pub fn parse_seconds(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if (0.0..=MAX_SECONDS).contains(&v) => Ok(v),
        _ => Err(format!("{s:?}: a number of seconds from 0 to 86400")),
    }
}

/// A flag's wait or duration (clap's value parser: a usage error naming the value): a number
/// of seconds above 0 and at most [`MAX_SECONDS`].
pub fn parse_positive_seconds(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if positive_seconds(v) => Ok(v),
        _ => Err(format!(
            "{s:?}: a number of seconds above 0 and at most 86400"
        )),
    }
}

/// [`parse_positive_seconds`]'s rule on a value already parsed (arguments built in a
/// program, not by clap): refused naming `flag`.
pub fn check_positive_seconds(flag: &str, v: f64) -> anyhow::Result<()> {
    if positive_seconds(v) {
        Ok(())
    } else {
        anyhow::bail!("{flag} {v}: a number of seconds above 0 and at most 86400")
    }
}

fn positive_seconds(v: f64) -> bool {
    v > 0.0 && v <= MAX_SECONDS
}

// The board connection is a library module (the learning over the link uses it too); the
// commands reach it here as before.
pub use crate::board_link;
pub mod analog;
pub mod budget;
pub mod calibrate;
pub mod closed_loop;
pub mod coarse;
pub mod compensate;
pub mod demo;
pub mod dual_stage;
pub mod golden;
pub mod identify;
pub mod lab_stage;
pub mod learn;
pub mod load;
pub mod params;
pub mod progress;
pub mod record;
pub mod scan;
pub mod selftest;
pub mod sequence;
pub mod serve;
pub mod settings;
pub mod status;
pub mod stop;
pub mod stream;
pub mod telemetry;
pub mod tune;
pub mod view;
pub mod virtual_board;
pub mod waveform;
