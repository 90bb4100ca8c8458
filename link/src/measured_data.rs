//! Measured records: the CSV a user exports from their stage, read into columns.
//!
//! Format (see the book, docs/src/reference/parameter-files.md): any number of `#` comment lines (and blank lines), then a header that
//! names the columns `t`, `u`, `x` in any order (other columns are ignored), then one sample
//! per line. The reader ([`crate::csv_table`]) also takes `;` or tab as the delimiter, quoted
//! cells, a byte-order mark, unit suffixes (`t [s]`, `u (V)`) and any case in the header, and
//! other names for the three columns through [`ColumnNames`] (`--columns`). `t` is time in seconds, `u` the drive in volts, `x` the measured output
//! (displacement or sensor units). Every cell read must be a finite number and `t` must
//! increase strictly; any failure is a [`DataError`] naming the file and the 1-based line.

use crate::csv_table::Table;
use std::path::{Path, PathBuf};
use std::str::FromStr;

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

/// The names the `t`, `u`, `x` columns go by in a file, when they are called something else
/// (`--columns t=time,u=drive,x=sensor`; any of the three, matched like the header's names:
/// without a unit suffix, in any case).
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct ColumnNames {
    /// Name of the time column.
    pub t: Option<String>,
    /// Name of the drive column.
    pub u: Option<String>,
    /// Name of the output column.
    pub x: Option<String>,
}

impl ColumnNames {
    /// The name `column` (`t`, `u` or `x`) goes by, if it was given one.
    pub fn get(&self, column: &str) -> Option<&str> {
        match column {
            "t" => self.t.as_deref(),
            "u" => self.u.as_deref(),
            "x" => self.x.as_deref(),
            _ => None,
        }
    }
}

impl FromStr for ColumnNames {
    type Err = String;

    /// `t=NAME,u=NAME,x=NAME`, any subset, in any order.
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        let mut names = ColumnNames::default();
        for pair in s.split(',').map(str::trim).filter(|p| !p.is_empty()) {
            let (key, name) = pair
                .split_once('=')
                .map(|(k, n)| (k.trim(), n.trim()))
                .filter(|(_, n)| !n.is_empty())
                .ok_or_else(|| format!("`{pair}`: expected t=NAME, u=NAME or x=NAME"))?;
            let slot = match key {
                "t" => &mut names.t,
                "u" => &mut names.u,
                "x" => &mut names.x,
                _ => return Err(format!("`{pair}`: the columns are t, u and x")),
            };
            if slot.replace(name.to_string()).is_some() {
                return Err(format!("`{key}` is named twice"));
            }
        }
        Ok(names)
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
    /// The CSV is malformed (e.g. an unterminated quote).
    #[error("{}:{line}: {message}", path.display())]
    Malformed {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// What the CSV reader said.
        message: String,
    },
    /// The header does not name a required column.
    #[error("{}:{line}: header has no column `{column}`{hint}", path.display())]
    MissingColumn {
        /// The file.
        path: PathBuf,
        /// Line of the header, 1-based.
        line: usize,
        /// The missing column.
        column: &'static str,
        /// The name it was looked for under, and the names the header has.
        hint: String,
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
    /// Two of `t`, `u` and `x` are read from the same column (`--columns u=a,x=a`).
    #[error("{}:{line}: `{first}` and `{second}` both name column `{name}`", path.display())]
    SameColumn {
        /// The file.
        path: PathBuf,
        /// Line of the header, 1-based.
        line: usize,
        /// The first of the two.
        first: &'static str,
        /// The second.
        second: &'static str,
        /// The column, as the header names it.
        name: String,
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
    #[error("{}:{line}: column `{header}`: `{text}` is not a number", path.display())]
    NotNumeric {
        /// The file.
        path: PathBuf,
        /// Line, 1-based.
        line: usize,
        /// Column name.
        column: &'static str,
        /// The column as the header names it (`u (V)`, or a name given with `--columns`).
        header: String,
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

/// Why columns handed over as arrays (the Python package's `identify(t, u, x)`) were refused:
/// the same rules as a file's, with positions instead of lines.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ColumnsError {
    /// A column's length differs from `t`'s.
    #[error("`{column}` has {found} samples, `t` has {expected}")]
    Length {
        /// The column.
        column: &'static str,
        /// Its length.
        found: usize,
        /// `t`'s length.
        expected: usize,
    },
    /// A value is NaN or infinite.
    #[error("`{column}`[{index}] is not finite (NaN or infinity)")]
    NotFinite {
        /// The column.
        column: &'static str,
        /// Its 0-based position.
        index: usize,
    },
    /// Time does not increase strictly.
    #[error("t[{index}] = {t} s does not increase (the sample before is at {previous} s)")]
    TimeNotIncreasing {
        /// 0-based position.
        index: usize,
        /// Its time.
        t: f64,
        /// The time before it.
        previous: f64,
    },
    /// Fewer than [`MIN_SAMPLES`] samples.
    #[error("only {found} samples, at least {MIN_SAMPLES} needed")]
    TooFewSamples {
        /// Samples given.
        found: usize,
    },
}

impl MeasuredData {
    /// A record from columns already in memory (`label` stands in for the file name in
    /// messages), checked as a file is: every value finite, `t` strictly increasing, the
    /// columns of one length, at least [`MIN_SAMPLES`] samples.
    ///
    /// ```
    /// use twinstack_link::measured_data::MeasuredData;
    /// let t: Vec<f64> = (0..20).map(|k| k as f64 * 1e-3).collect();
    /// let d = MeasuredData::from_columns("arrays", t.clone(), Some(t.clone()), None).unwrap();
    /// assert_eq!(d.len(), 20);
    /// assert!(MeasuredData::from_columns("arrays", t.clone(), Some(vec![0.0; 3]), None).is_err());
    /// ```
    pub fn from_columns(
        label: &str,
        t: Vec<f64>,
        u: Option<Vec<f64>>,
        x: Option<Vec<f64>>,
    ) -> Result<Self, ColumnsError> {
        let mut others: Vec<(&'static str, &[f64])> = Vec::new();
        if let Some(u) = &u {
            others.push(("u", u));
        }
        if let Some(x) = &x {
            others.push(("x", x));
        }
        Self::check_columns(&t, &others)?;
        if t.len() < MIN_SAMPLES {
            return Err(ColumnsError::TooFewSamples { found: t.len() });
        }
        Ok(Self {
            path: PathBuf::from(label),
            t,
            u,
            x,
        })
    }

    /// Checks columns of any length as [`Self::from_columns`] does, short of the sample count:
    /// `t` finite and strictly increasing, each of `others` (name, values) as long as `t` and
    /// finite.
    pub fn check_columns(t: &[f64], others: &[(&'static str, &[f64])]) -> Result<(), ColumnsError> {
        for &(column, values) in std::iter::once(&("t", t)).chain(others) {
            if values.len() != t.len() {
                return Err(ColumnsError::Length {
                    column,
                    found: values.len(),
                    expected: t.len(),
                });
            }
            if let Some(index) = values.iter().position(|v| !v.is_finite()) {
                return Err(ColumnsError::NotFinite { column, index });
            }
        }
        if let Some(k) = t.windows(2).position(|w| w[1] <= w[0]) {
            return Err(ColumnsError::TimeNotIncreasing {
                index: k + 1,
                t: t[k + 1],
                previous: t[k],
            });
        }
        Ok(())
    }

    /// Reads `path`, requiring the columns in `columns`.
    pub fn read(path: &Path, columns: Columns) -> Result<Self, DataError> {
        let text = std::fs::read_to_string(path).map_err(|source| DataError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse(path, &text, columns)
    }

    /// Reads `path`, requiring the columns in `columns`, found under the names in `names`.
    pub fn read_with(
        path: &Path,
        columns: Columns,
        names: &ColumnNames,
    ) -> Result<Self, DataError> {
        let text = std::fs::read_to_string(path).map_err(|source| DataError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse_with(path, &text, columns, names)
    }

    /// Parses CSV `text` (as read from `path`, which is only used in errors).
    pub fn parse(path: &Path, text: &str, columns: Columns) -> Result<Self, DataError> {
        Self::parse_with(path, text, columns, &ColumnNames::default())
    }

    /// [`Self::parse`] with the columns found under the names in `names`.
    pub fn parse_with(
        path: &Path,
        text: &str,
        columns: Columns,
        names: &ColumnNames,
    ) -> Result<Self, DataError> {
        let p = || path.to_path_buf();
        let table = Table::parse(text)
            .map_err(|(line, message)| DataError::Malformed {
                path: p(),
                line,
                message,
            })?
            .ok_or_else(|| DataError::NoHeader { path: p() })?;
        let header_line = table.header_line;
        let require = |column: &'static str, needed: bool| -> Result<Option<usize>, DataError> {
            if !needed {
                return Ok(None);
            }
            let name = names.get(column).unwrap_or(column);
            let hits = table.find(name);
            match hits.as_slice() {
                [at] => Ok(Some(*at)),
                [] => Err(DataError::MissingColumn {
                    path: p(),
                    line: header_line,
                    column,
                    hint: if name == column {
                        format!(
                            " (the header has {}; name other columns with --columns {column}=NAME)",
                            table.listed()
                        )
                    } else {
                        format!(
                            " named `{name}` (from --columns; the header has {})",
                            table.listed()
                        )
                    },
                }),
                _ => Err(DataError::DuplicateColumn {
                    path: p(),
                    line: header_line,
                    column,
                }),
            }
        };
        let t_col = require("t", true)?.unwrap_or(0);
        let u_col = require("u", columns.needs_drive())?;
        let x_col = require("x", columns.needs_output())?;
        let roles = [("t", Some(t_col)), ("u", u_col), ("x", x_col)];
        for (i, &(first, a)) in roles.iter().enumerate() {
            for &(second, b) in &roles[i + 1..] {
                if let (Some(a), Some(b)) = (a, b) {
                    if a == b {
                        return Err(DataError::SameColumn {
                            path: p(),
                            line: header_line,
                            first,
                            second,
                            name: table.raw_names[a].clone(),
                        });
                    }
                }
            }
        }

        let mut t = Vec::new();
        let mut u = Vec::new();
        let mut x = Vec::new();
        let mut last_line = header_line;
        for row in &table.rows {
            let line = row.line;
            last_line = line;
            let cells = &row.cells;
            let cell = |col: usize, name: &'static str| -> Result<f64, DataError> {
                let text = cells.get(col).ok_or(DataError::ShortLine {
                    path: p(),
                    line,
                    found: cells.len(),
                    column: name,
                })?;
                let v = table.number(text).ok_or_else(|| DataError::NotNumeric {
                    path: p(),
                    line,
                    column: name,
                    header: table.raw_names[col].clone(),
                    text: Table::excerpt(text),
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
    fn two_roles_read_from_one_column_are_refused() {
        let rows: String = (0..12).map(|i| format!("{i},{i}.5,1\n")).collect();
        let text = format!("time,drive,x\n{rows}");
        let read = |names: &str| {
            let names: ColumnNames = names.parse().unwrap();
            MeasuredData::parse_with(Path::new("d.csv"), &text, Columns::TimeDriveOutput, &names)
                .unwrap_err()
                .to_string()
        };
        assert_eq!(
            read("t=time,u=drive,x=drive"),
            "d.csv:1: `u` and `x` both name column `drive`"
        );
        assert_eq!(
            read("t=time,u=time"),
            "d.csv:1: `t` and `u` both name column `time`"
        );
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
