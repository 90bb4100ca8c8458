//! Measured records: the CSV a user exports from their stage, read into columns.
//!
//! Format (see the book, docs/src/reference/parameter-files.md): any number of `#` comment lines (and blank lines), then a header that
//! names the columns `t`, `u`, `x` in any order (other columns are ignored), then one sample
//! per line. `t` is time in seconds, `u` the drive in volts, `x` the measured output
//! (displacement or sensor units). Every cell read must be a finite number and `t` must
//! increase strictly; any failure is a [`DataError`] naming the file and the 1-based line.

use std::path::{Path, PathBuf};

/// Fewest samples a record must hold to be of any use.
pub const MIN_SAMPLES: usize = 10;

/// Which columns a caller needs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Columns {
    /// `t`, `u` and `x` (identification).
    TimeDriveOutput,
    /// `t` and `u` (the forward model: `predict`).
    TimeDrive,
    /// `t` and `x` (the inverse model: `compensate`).
    TimeOutput,
}

impl Columns {
    fn needs_drive(self) -> bool {
        matches!(self, Columns::TimeDriveOutput | Columns::TimeDrive)
    }
    fn needs_output(self) -> bool {
        matches!(self, Columns::TimeDriveOutput | Columns::TimeOutput)
    }
}

/// A measured record, one `Vec` per column, all of the same length.
#[derive(Clone, Debug, PartialEq)]
pub struct MeasuredData {
    /// The file it came from.
    pub path: PathBuf,
    /// Time, seconds, strictly increasing.
    pub t: Vec<f64>,
    /// Drive, volts (`None` when the caller did not ask for it).
    pub u: Option<Vec<f64>>,
    /// Measured output, output units (`None` when the caller did not ask for it).
    pub x: Option<Vec<f64>>,
}

/// Why a record could not be read.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The file could not be read at all.
    #[error("{}: cannot read: {source}", path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        source: std::io::Error,
    },
    /// Only comments (or nothing): no header line.
    #[error("{}: no header line (expected a line naming the columns t,u,x)", path.display())]
    NoHeader {
        /// The file.
        path: PathBuf,
    },
    /// The header does not name a required column.
    #[error("{}:{line}: header has no column `{column}`", path.display())]
    MissingColumn {
        /// The file.
        path: PathBuf,
        /// Line of the header, 1-based.
        line: usize,
        /// The missing column.
        column: &'static str,
    },
    /// The header names a column twice.
    #[error("{}:{line}: header names column `{column}` twice", path.display())]
    DuplicateColumn {
        /// The file.
        path: PathBuf,
        /// Line of the header, 1-based.
        line: usize,
        /// The repeated column.
        column: &'static str,
    },
    /// A data line has fewer cells than the header needs.
    #[error("{}:{line}: only {found} cells, column `{column}` is missing", path.display())]
    ShortLine {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// Cells found on the line.
        found: usize,
        /// The column that is not there.
        column: &'static str,
    },
    /// A cell is not a number.
    #[error("{}:{line}: column `{column}`: `{text}` is not a number", path.display())]
    NotNumeric {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// Column name.
        column: &'static str,
        /// The offending text.
        text: String,
    },
    /// A cell is NaN or infinite.
    #[error("{}:{line}: column `{column}` is not finite (NaN or infinity)", path.display())]
    NotFinite {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// Column name.
        column: &'static str,
    },
    /// Time does not increase strictly.
    #[error("{}:{line}: time {t} s does not increase (previous sample at {previous} s)", path.display())]
    TimeNotIncreasing {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// This sample's time.
        t: f64,
        /// The previous sample's time.
        previous: f64,
    },
    /// Fewer than [`MIN_SAMPLES`] samples.
    #[error("{}:{line}: only {found} samples, at least {needed} needed", path.display())]
    TooFewSamples {
        /// The file.
        path: PathBuf,
        /// Last line of the file, 1-based.
        line: usize,
        /// Samples read.
        found: usize,
        /// Samples needed.
        needed: usize,
    },
}

impl MeasuredData {
    /// Reads `path`, requiring the columns in `columns`.
    pub fn read(path: &Path, columns: Columns) -> Result<Self, DataError> {
        let text = std::fs::read_to_string(path).map_err(|source| DataError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(path, &text, columns)
    }

    /// Parses CSV `text` (as read from `path`, which is only used in errors).
    pub fn parse(path: &Path, text: &str, columns: Columns) -> Result<Self, DataError> {
        let p = || path.to_path_buf();
        let mut lines = text
            .lines()
            .enumerate()
            .map(|(i, l)| (i + 1, l.trim()))
            .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
        let (header_line, header) = lines
            .next()
            .ok_or_else(|| DataError::NoHeader { path: p() })?;
        let find = |name: &'static str| -> Result<Option<usize>, DataError> {
            let mut hits = header
                .split(',')
                .enumerate()
                .filter(|(_, c)| c.trim().eq_ignore_ascii_case(name));
            let first = hits.next().map(|(i, _)| i);
            if hits.next().is_some() {
                return Err(DataError::DuplicateColumn {
                    path: p(),
                    line: header_line,
                    column: name,
                });
            }
            Ok(first)
        };
        let require = |name: &'static str, needed: bool| -> Result<Option<usize>, DataError> {
            let at = find(name)?;
            if needed && at.is_none() {
                return Err(DataError::MissingColumn {
                    path: p(),
                    line: header_line,
                    column: name,
                });
            }
            Ok(if needed { at } else { None })
        };
        let t_col = require("t", true)?.unwrap_or(0);
        let u_col = require("u", columns.needs_drive())?;
        let x_col = require("x", columns.needs_output())?;

        let mut t = Vec::new();
        let mut u = Vec::new();
        let mut x = Vec::new();
        let mut last_line = header_line;
        for (line, l) in lines {
            last_line = line;
            let cells: Vec<&str> = l.split(',').collect();
            let cell = |col: usize, name: &'static str| -> Result<f64, DataError> {
                let text = cells.get(col).ok_or(DataError::ShortLine {
                    path: p(),
                    line,
                    found: cells.len(),
                    column: name,
                })?;
                let text = text.trim();
                let v: f64 = text.parse().map_err(|_| DataError::NotNumeric {
                    path: p(),
                    line,
                    column: name,
                    text: text.to_string(),
                })?;
                if !v.is_finite() {
                    return Err(DataError::NotFinite {
                        path: p(),
                        line,
                        column: name,
                    });
                }
                Ok(v)
            };
            let tv = cell(t_col, "t")?;
            if let Some(&previous) = t.last() {
                if tv <= previous {
                    return Err(DataError::TimeNotIncreasing {
                        path: p(),
                        line,
                        t: tv,
                        previous,
                    });
                }
            }
            t.push(tv);
            if let Some(c) = u_col {
                u.push(cell(c, "u")?);
            }
            if let Some(c) = x_col {
                x.push(cell(c, "x")?);
            }
        }
        if t.len() < MIN_SAMPLES {
            return Err(DataError::TooFewSamples {
                path: p(),
                line: last_line,
                found: t.len(),
                needed: MIN_SAMPLES,
            });
        }
        Ok(Self {
            path: path.to_path_buf(),
            t,
            u: u_col.map(|_| u),
            x: x_col.map(|_| x),
        })
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        self.t.len()
    }

    /// Always false: a record holds at least [`MIN_SAMPLES`] samples.
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }

    /// The median sample interval, seconds.
    pub fn sample_period(&self) -> f64 {
        let mut dt: Vec<f64> = self.t.windows(2).map(|w| w[1] - w[0]).collect();
        dt.sort_by(f64::total_cmp);
        dt.get(dt.len() / 2).copied().unwrap_or(0.0)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str, c: Columns) -> Result<MeasuredData, DataError> {
        MeasuredData::parse(Path::new("in.csv"), text, c)
    }

    fn rows(n: usize) -> String {
        (0..n).map(|i| format!("{i},{}.5,{}\n", i, 2 * i)).collect()
    }

    #[test]
    fn columns_are_found_by_name_in_any_order_after_comments() {
        let text = format!("# comment\n\n#more\nx, extra ,t,u\n{}", {
            (0..12)
                .map(|i| format!("{},9,{i},{}\n", 2 * i, i + 1))
                .collect::<String>()
        });
        let d = parse(&text, Columns::TimeDriveOutput).unwrap();
        assert_eq!(d.len(), 12);
        assert_eq!(d.t[3], 3.0);
        assert_eq!(d.u.as_ref().unwrap()[3], 4.0);
        assert_eq!(d.x.as_ref().unwrap()[3], 6.0);
    }

    #[test]
    fn compensate_needs_only_t_and_x() {
        let text = format!(
            "t,x\n{}",
            (0..12).map(|i| format!("{i},{i}\n")).collect::<String>()
        );
        let d = parse(&text, Columns::TimeOutput).unwrap();
        assert!(d.u.is_none());
        let e = parse(&text, Columns::TimeDrive).unwrap_err();
        assert!(
            matches!(
                e,
                DataError::MissingColumn {
                    column: "u",
                    line: 1,
                    ..
                }
            ),
            "{e}"
        );
    }

    #[test]
    fn each_bad_input_names_its_line() {
        let base = format!("# c\nt,u,x\n{}", rows(12));
        let with = |line: usize, replacement: &str| {
            let mut ls: Vec<String> = base.lines().map(String::from).collect();
            ls[line - 1] = replacement.to_string();
            parse(&ls.join("\n"), Columns::TimeDriveOutput).unwrap_err()
        };
        assert!(matches!(
            with(5, "2,abc,4"),
            DataError::NotNumeric {
                line: 5,
                column: "u",
                ..
            }
        ));
        assert!(matches!(
            with(6, "3,NaN,4"),
            DataError::NotFinite {
                line: 6,
                column: "u",
                ..
            }
        ));
        assert!(matches!(
            with(7, "3,1,4"),
            DataError::TimeNotIncreasing { line: 7, .. }
        ));
        assert!(matches!(
            with(8, "5,1"),
            DataError::ShortLine {
                line: 8,
                column: "x",
                ..
            }
        ));
        assert!(matches!(
            with(2, "t,u,y"),
            DataError::MissingColumn {
                line: 2,
                column: "x",
                ..
            }
        ));
        assert!(matches!(
            with(2, "t,u,x,u"),
            DataError::DuplicateColumn { column: "u", .. }
        ));
        let e = parse(&format!("t,u,x\n{}", rows(3)), Columns::TimeDriveOutput).unwrap_err();
        assert!(matches!(e, DataError::TooFewSamples { found: 3, .. }));
        assert!(matches!(
            parse("# only comments\n", Columns::TimeDriveOutput).unwrap_err(),
            DataError::NoHeader { .. }
        ));
        let msg = with(5, "2,abc,4").to_string();
        assert!(msg.starts_with("in.csv:5:"), "{msg}");
    }

    proptest::proptest! {
        /// Whatever the bytes, the reader returns a record or an error — never panics — and
        /// a record it returns holds only finite numbers with strictly increasing time.
        #[test]
        fn any_text_gives_a_valid_record_or_an_error(
            text in "(#[a-z ]{0,8}\n)?(t,u,x|x,t|t,u)?\n([0-9.eE+-]{0,6}(,[0-9.naNIf-]{0,5}){0,3}\n){0,14}"
        ) {
            for c in [Columns::TimeDriveOutput, Columns::TimeDrive, Columns::TimeOutput] {
                if let Ok(d) = parse(&text, c) {
                    proptest::prop_assert!(d.t.windows(2).all(|w| w[1] > w[0]));
                    proptest::prop_assert!(d.t.iter().all(|v| v.is_finite()));
                    for col in [&d.u, &d.x].into_iter().flatten() {
                        proptest::prop_assert_eq!(col.len(), d.t.len());
                        proptest::prop_assert!(col.iter().all(|v| v.is_finite()));
                    }
                }
            }
        }
    }
}
