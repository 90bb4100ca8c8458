//! The setpoint CSV that `twinstack stream` sends to the board.
//!
//! Format: any `#` comment lines and blank lines, then a header naming the setpoint column,
//! then one setpoint per line (other columns are ignored):
//! * `setpoint` — normalised displacement, −1…1 over the model's output range (what the board
//!   runs on: it is sent as Q1.15, one LSB = 2⁻¹⁵ of the half range), or
//! * `x` — displacement in the model's output units; needs the parameter file, whose
//!   `output_range` maps it onto −1…1 (`x = min` → −1, `x = max` → +1).
//!
//! The reader ([`crate::csv_table`]) also takes `;` or tab as the delimiter, quoted cells, a
//! byte-order mark, unit suffixes (`t [s]`, `x [um]`) and any case in the header.
//!
//! An optional `t` column (seconds) is checked, not used to pace: it must step uniformly by
//! `divider / tick rate` (within 1 %), so a file sampled at another rate is refused instead of
//! being played at the wrong speed. Every failure names the file and the 1-based line; a
//! value outside the range is an error, never clamped.

use crate::csv_table::Table;
use std::path::{Path, PathBuf};
use twinstack::Scaling;

/// Which units the setpoint column is in.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum SetpointUnits<'a> {
    /// Normalised, −1…1 (column `setpoint`).
    Normalised,
    /// Output units, mapped by this scaling's output range (column `x`).
    Output(&'a Scaling),
}

/// Setpoints read from a file, ready for the wire.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Setpoints {
    /// Q1.15 normalised displacement.
    pub samples: Vec<i16>,
    /// The interval of the `t` column in ticks, when there is one.
    pub divider_from_t: Option<u16>,
}

/// Why a setpoint file was refused.
#[derive(Debug, thiserror::Error)]
pub enum SetpointFileError {
    /// Unreadable.
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// Something is wrong at a line.
    #[error("{}:{line}: {message}", path.display())]
    Line {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// What.
        message: String,
    },
}

/// Normalised value (−1…1) → Q1.15 (rounded; +1 saturates to 32767, i.e. 1 − 2⁻¹⁵).
pub fn q1_15(normalised: f64) -> i16 {
    (normalised * 32768.0)
        .round()
        .clamp(i16::MIN as f64, i16::MAX as f64) as i16
}

/// One setpoint `v` in `units` as the wire's Q1.15, or why it cannot be sent (not finite, or
/// outside −1…1 once normalised: refused, never clamped).
pub fn to_wire(v: f64, units: SetpointUnits<'_>) -> Result<i16, String> {
    let n = match units {
        SetpointUnits::Normalised => v,
        SetpointUnits::Output(s) => s.output_to_norm(v),
    };
    if !v.is_finite() {
        return Err(format!("setpoint {v} is not finite"));
    }
    if !(-1.0..=1.0).contains(&n) {
        return Err(match units {
            SetpointUnits::Normalised => {
                format!("setpoint {v} is outside -1…1 (normalised units)")
            }
            SetpointUnits::Output(s) => format!(
                "x = {v} is outside the model's output range {}…{}",
                s.output_min, s.output_max
            ),
        });
    }
    Ok(q1_15(n))
}

/// The rate divider that plays setpoints at `rate_hz` on a board ticking at `tick_rate_hz`:
/// the tick rate over the setpoint rate, which must be a whole number of ticks (within 1 %,
/// as a `t` column is checked) from 1 to 65 535.
///
/// ```
/// use twinstack_link::setpoint_file::divider_for_rate;
/// assert_eq!(divider_for_rate(50_000.0, 10_000.0), Ok(5));
/// assert!(divider_for_rate(50_000.0, 30_000.0).is_err());
/// ```
pub fn divider_for_rate(tick_rate_hz: f64, rate_hz: f64) -> Result<u16, String> {
    if !(rate_hz.is_finite() && rate_hz > 0.0) {
        return Err(format!(
            "rate {rate_hz}: must be a positive number of setpoints per second"
        ));
    }
    let ticks = tick_rate_hz / rate_hz;
    let divider = ticks.round();
    if !(1.0..=u16::MAX as f64).contains(&divider) || (ticks - divider).abs() > 0.01 * divider {
        return Err(format!(
            "rate {rate_hz} setpoints/s: the board ticks at {tick_rate_hz} Hz, so the rate must be {tick_rate_hz} Hz divided by a whole number from 1 to 65535 (e.g. {tick_rate_hz}, {}, {})",
            tick_rate_hz / 2.0,
            tick_rate_hz / 5.0
        ));
    }
    Ok(divider as u16)
}

/// Reads `path`. `tick_rate_hz` and `divider` are what the board will play it at (checked
/// against a `t` column if there is one; `divider = None` takes it from `t`).
pub fn read(
    path: &Path,
    units: SetpointUnits<'_>,
    tick_rate_hz: f64,
    divider: Option<u16>,
) -> Result<Setpoints, SetpointFileError> {
    let text = std::fs::read_to_string(path).map_err(|source| SetpointFileError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse(path, &text, units, tick_rate_hz, divider)
}

/// Parses `text` (from `path`, for messages); see [`read`].
pub fn parse(
    path: &Path,
    text: &str,
    units: SetpointUnits<'_>,
    tick_rate_hz: f64,
    divider: Option<u16>,
) -> Result<Setpoints, SetpointFileError> {
    let err = |line: usize, message: String| SetpointFileError::Line {
        path: path.to_path_buf(),
        line,
        message,
    };
    let wanted = match units {
        SetpointUnits::Normalised => "setpoint",
        SetpointUnits::Output(_) => "x",
    };
    let table = Table::parse(text)
        .map_err(|(line, message)| err(line, message))?
        .ok_or_else(|| {
            err(
                1,
                format!("no header line (expected a column named `{wanted}`)"),
            )
        })?;
    let header_line = table.header_line;
    let find = |name: &str| table.find(name).first().copied();
    let col = find(wanted).ok_or_else(|| {
        let other = match units {
            SetpointUnits::Normalised if find("x").is_some() => {
                " (an `x` column in output units needs --params)".to_string()
            }
            SetpointUnits::Output(_) if find("setpoint").is_some() => {
                " (a `setpoint` column is normalised: leave out --params)".to_string()
            }
            _ => format!(" (the header has {})", table.listed()),
        };
        err(
            header_line,
            format!("header has no column `{wanted}`{other}"),
        )
    })?;
    let t_col = find("t");
    let mut samples = Vec::new();
    let mut times: Vec<(usize, f64)> = Vec::new();
    for row in &table.rows {
        let (line, cells) = (row.line, &row.cells);
        let cell = |c: usize, name: &str| -> Result<f64, SetpointFileError> {
            let text = cells.get(c).ok_or_else(|| {
                err(
                    line,
                    format!("only {} cells, column `{name}` is missing", cells.len()),
                )
            })?;
            let v = table.number(text).ok_or_else(|| {
                err(
                    line,
                    format!(
                        "column `{}`: `{}` is not a number",
                        table.raw_names[c],
                        Table::excerpt(text)
                    ),
                )
            })?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err(err(line, format!("column `{name}` is not finite")))
            }
        };
        let v = cell(col, wanted)?;
        samples.push(to_wire(v, units).map_err(|m| err(line, m))?);
        if let Some(tc) = t_col {
            times.push((line, cell(tc, "t")?));
        }
    }
    if samples.is_empty() {
        return Err(err(header_line, "no setpoints after the header".into()));
    }
    let divider_from_t = check_times(&times, tick_rate_hz, divider).map_err(|(l, m)| err(l, m))?;
    Ok(Setpoints {
        samples,
        divider_from_t,
    })
}

/// Checks a `t` column steps uniformly by `divider / tick_rate`; returns the divider it
/// implies.
fn check_times(
    times: &[(usize, f64)],
    tick_rate_hz: f64,
    divider: Option<u16>,
) -> Result<Option<u16>, (usize, String)> {
    if times.len() < 2 {
        return Ok(None);
    }
    let dt = times[1].1 - times[0].1;
    let ticks = dt * tick_rate_hz;
    let implied = ticks.round();
    if implied > u16::MAX as f64 {
        return Err((
            times[1].0,
            format!(
                "t steps by {dt} s, {implied} ticks at {tick_rate_hz} Hz: the board plays one setpoint every 65535 ticks at most"
            ),
        ));
    }
    if implied < 1.0 || (ticks - implied).abs() > 0.01 * implied {
        return Err((
            times[1].0,
            format!(
                "t steps by {dt} s, which is not a whole number of ticks at {tick_rate_hz} Hz (the board plays one setpoint every 1…65535 ticks)"
            ),
        ));
    }
    let implied = implied as u16;
    if let Some(d) = divider {
        if d != implied {
            return Err((
                times[1].0,
                format!(
                    "t steps by {dt} s = {implied} ticks at {tick_rate_hz} Hz, but --divider is {d}"
                ),
            ));
        }
    }
    for w in times.windows(2) {
        let step = w[1].1 - w[0].1;
        if (step - dt).abs() > 0.01 * dt {
            return Err((
                w[1].0,
                format!("t steps by {step} s here, {dt} s before: setpoints must be evenly spaced"),
            ));
        }
    }
    Ok(Some(implied))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn p(text: &str) -> Result<Setpoints, SetpointFileError> {
        parse(
            Path::new("sp.csv"),
            text,
            SetpointUnits::Normalised,
            50_000.0,
            None,
        )
    }

    #[test]
    fn normalised_values_become_q1_15() {
        let s = p("# comment\nsetpoint\n0\n0.5\n-1\n1\n").unwrap();
        assert_eq!(s.samples, vec![0, 16384, -32768, 32767]);
        assert_eq!(s.divider_from_t, None);
    }

    #[test]
    fn output_units_are_mapped_by_the_output_range() {
        let sc = Scaling::new(0.0, 140.0, 0.0, 70.0).unwrap();
        let s = parse(
            Path::new("x.csv"),
            "t,x\n0,0\n0.00002,35\n0.00004,70\n",
            SetpointUnits::Output(&sc),
            50_000.0,
            None,
        )
        .unwrap();
        assert_eq!(s.samples, vec![-32768, 0, 32767]);
        assert_eq!(s.divider_from_t, Some(1));
        let e = parse(
            Path::new("x.csv"),
            "x\n10\n70.5\n",
            SetpointUnits::Output(&sc),
            50_000.0,
            None,
        )
        .unwrap_err();
        assert_eq!(
            e.to_string(),
            "x.csv:3: x = 70.5 is outside the model's output range 0…70"
        );
    }

    #[test]
    fn every_bad_line_is_named() {
        let cases = [
            ("", "sp.csv:1: no header line (expected a column named `setpoint`)"),
            ("t,x\n0,1\n", "sp.csv:1: header has no column `setpoint` (an `x` column in output units needs --params)"),
            ("setpoint\n", "sp.csv:1: no setpoints after the header"),
            ("setpoint\n0.1\nabc\n", "sp.csv:3: column `setpoint`: `abc` is not a number"),
            ("setpoint\n0.1\nNaN\n", "sp.csv:3: column `setpoint` is not finite"),
            ("setpoint\n1.5\n", "sp.csv:2: setpoint 1.5 is outside -1…1 (normalised units)"),
            ("t,setpoint\n0,0\n1e-4\n", "sp.csv:3: only 1 cells, column `setpoint` is missing"),
            ("t,setpoint\n0,0\n0.00002,0\n0.00005,0\n", "sp.csv:4: t steps by 0.00003 s here, 0.00002 s before: setpoints must be evenly spaced"),
            ("t,setpoint\n0,0\n0.000031,0\n", "sp.csv:3: t steps by 0.000031 s, which is not a whole number of ticks at 50000 Hz (the board plays one setpoint every 1…65535 ticks)"),
            ("t,setpoint\n0,0\n1000000,0\n", "sp.csv:3: t steps by 1000000 s, 50000000000 ticks at 50000 Hz: the board plays one setpoint every 65535 ticks at most"),
            ("setpoint\n0.1\n0.1,0.5\n", "sp.csv:3: 2 cells where the header names 1 columns (setpoint)"),
        ];
        for (text, want) in cases {
            let e = p(text).unwrap_err().to_string();
            assert_eq!(e, want, "for {text:?}");
        }
        let e = parse(
            Path::new("sp.csv"),
            "t,setpoint\n0,0\n0.0001,0\n",
            SetpointUnits::Normalised,
            50_000.0,
            Some(2),
        )
        .unwrap_err();
        assert!(
            e.to_string()
                .contains("= 5 ticks at 50000 Hz, but --divider is 2"),
            "{e}"
        );
    }
}
