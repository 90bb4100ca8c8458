//! The CSV reader under the measured-data files ([`crate::measured_data`]) and the setpoint
//! files ([`crate::setpoint_file`]): what spreadsheet and instrument exports write, read into
//! a header and rows that keep their 1-based line numbers (for `file:line` errors).
//!
//! Accepted, on top of plain `t,u,x`:
//! * a UTF-8 byte-order mark before the first line;
//! * `#` comment lines and blank lines anywhere (skipped, line numbers kept);
//! * the delimiter `,`, `;` or tab, sniffed from the header line (the one that occurs most
//!   often outside quotes; `,` when none does);
//! * quoted cells (`"t","u","x"`), spaces around cells;
//! * header names with a unit suffix in brackets or parentheses (`t [s]`, `u (V)`, `x[um]`),
//!   matched without it and without regard to case ([`normalise_name`]);
//! * with `;` or tab as the delimiter, a decimal comma in numbers (`0,25`), as European
//!   locales export them ([`Table::number`]).

use csv::{ReaderBuilder, Trim};

/// A CSV file's header and data rows.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Table {
    /// Line of the header, 1-based.
    pub header_line: usize,
    /// Column names as written (quotes and surrounding spaces removed).
    pub raw_names: Vec<String>,
    /// Column names for matching: [`normalise_name`] of each.
    pub names: Vec<String>,
    /// The delimiter found on the header line.
    pub delimiter: u8,
    /// Data rows in file order.
    pub rows: Vec<Row>,
}

/// One data row.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Row {
    /// Line, 1-based.
    pub line: usize,
    /// Cells, trimmed.
    pub cells: Vec<String>,
}

/// A header name as matched: quotes and spaces removed, a trailing unit in brackets or
/// parentheses removed (`t [s]` → `t`, `u (V)` → `u`, `x[um]` → `x`), lower case.
pub fn normalise_name(name: &str) -> String {
    let mut s = name.trim().trim_matches('"').trim();
    for (open, close) in [('[', ']'), ('(', ')')] {
        if let Some(body) = s.strip_suffix(close) {
            if let Some(at) = body.rfind(open) {
                if !body[..at].trim().is_empty() {
                    s = body[..at].trim();
                }
            }
        }
    }
    s.to_lowercase()
}

/// The delimiter a header line uses: the most frequent of `,` `;` tab outside quotes (`,` on a
/// tie or when there is none).
fn sniff(header: &str) -> u8 {
    let (mut quoted, mut counts) = (false, [0usize; 3]);
    for c in header.chars() {
        match c {
            '"' => quoted = !quoted,
            ',' if !quoted => counts[0] += 1,
            ';' if !quoted => counts[1] += 1,
            '\t' if !quoted => counts[2] += 1,
            _ => {}
        }
    }
    let best = (0..3)
        .max_by_key(|&i| (counts[i], std::cmp::Reverse(i)))
        .unwrap_or(0);
    if counts[best] == 0 {
        b','
    } else {
        [b',', b';', b'\t'][best]
    }
}

impl Table {
    /// Parses `text`. `Ok(None)`: there is no header (only comments and blank lines).
    /// `Err((line, message))`: the CSV itself is malformed at that line.
    pub fn parse(text: &str) -> Result<Option<Self>, (usize, String)> {
        let text = text.strip_prefix('\u{feff}').unwrap_or(text);
        // Comment and blank lines are left out; `lines[k]` is the file's line number of the
        // reader's line k + 1 (its positions count the lines it was given).
        let mut cleaned = String::with_capacity(text.len());
        let mut lines = Vec::new();
        let mut header: Option<&str> = None;
        for (i, l) in text.lines().enumerate() {
            let t = l.trim();
            if !t.is_empty() && !t.starts_with('#') {
                header.get_or_insert(t);
                cleaned.push_str(l);
                cleaned.push('\n');
                lines.push(i + 1);
            }
        }
        let file_line = |reader_line: u64| {
            lines
                .get((reader_line as usize).saturating_sub(1))
                .copied()
                .unwrap_or(lines.last().map_or(1, |l| l + 1))
        };
        let Some(header) = header else {
            return Ok(None);
        };
        let delimiter = sniff(header);
        let mut reader = ReaderBuilder::new()
            .has_headers(false)
            .delimiter(delimiter)
            .flexible(true)
            .trim(Trim::All)
            .from_reader(cleaned.as_bytes());
        let mut table: Option<Table> = None;
        for record in reader.records() {
            let record = record.map_err(|e| {
                let line = e.position().map_or(0, |p| file_line(p.line()));
                (line, format!("malformed CSV: {e}"))
            })?;
            let line = record.position().map_or(0, |p| file_line(p.line()));
            let cells: Vec<String> = record.iter().map(|c| c.trim().to_string()).collect();
            // A line of only delimiters or spaces is as good as blank.
            if cells.iter().all(|c| c.is_empty()) {
                continue;
            }
            match &mut table {
                None => {
                    let raw_names: Vec<String> = cells
                        .iter()
                        .map(|c| c.trim_matches('"').trim().to_string())
                        .collect();
                    table = Some(Table {
                        header_line: line,
                        names: raw_names.iter().map(|n| normalise_name(n)).collect(),
                        raw_names,
                        delimiter,
                        rows: Vec::new(),
                    });
                }
                Some(t) => {
                    // A cell beyond the header's columns has no column to go to: refused,
                    // not dropped (an empty one, a trailing delimiter, is nothing).
                    if cells[t.names.len().min(cells.len())..]
                        .iter()
                        .any(|c| !c.is_empty())
                    {
                        return Err((
                            line,
                            format!(
                                "{} cells where the header names {} columns ({})",
                                cells.len(),
                                t.names.len(),
                                t.listed()
                            ),
                        ));
                    }
                    t.rows.push(Row { line, cells })
                }
            }
        }
        Ok(table)
    }

    /// Columns whose [normalised](normalise_name) name is `name`'s.
    pub fn find(&self, name: &str) -> Vec<usize> {
        let want = normalise_name(name);
        (0..self.names.len())
            .filter(|&i| self.names[i] == want)
            .collect()
    }

    /// A cell's text as a message quotes it: whole up to 40 characters, else its start and its
    /// length (an unclosed quote takes the rest of the file into one cell, and the message
    /// should not be the file).
    pub fn excerpt(cell: &str) -> String {
        const MOST: usize = 40;
        match cell.char_indices().nth(MOST) {
            None => cell.to_string(),
            Some((end, _)) => {
                let hint = if cell.contains('\n') {
                    ", over several lines: an unclosed quote?"
                } else {
                    ""
                };
                format!("{}… ({} bytes{hint})", &cell[..end], cell.len())
            }
        }
    }

    /// The header's names, as written, for messages (`a, b, c`).
    pub fn listed(&self) -> String {
        self.raw_names.join(", ")
    }

    /// A cell as a number: a plain `f64`, or with `;` or tab as the delimiter, a decimal
    /// comma (`0,25`). `None` if it is neither.
    pub fn number(&self, cell: &str) -> Option<f64> {
        let cell = cell.trim().trim_matches('"').trim();
        cell.parse().ok().or_else(|| {
            (self.delimiter != b',' && cell.matches(',').count() == 1 && !cell.contains('.'))
                .then(|| cell.replace(',', "."))
                .and_then(|c| c.parse().ok())
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_lose_quotes_units_and_case() {
        for (raw, want) in [
            ("t", "t"),
            ("\"t\"", "t"),
            ("t [s]", "t"),
            ("u (V)", "u"),
            ("x[um]", "x"),
            (" X [µm] ", "x"),
            ("Setpoint", "setpoint"),
            ("[s]", "[s]"),
        ] {
            assert_eq!(normalise_name(raw), want, "{raw:?}");
        }
    }

    #[test]
    fn the_delimiter_is_sniffed_from_the_header() {
        assert_eq!(sniff("t,u,x"), b',');
        assert_eq!(sniff("t;u;x"), b';');
        assert_eq!(sniff("t\tu\tx"), b'\t');
        assert_eq!(sniff("setpoint"), b',');
        assert_eq!(sniff("\"a;b\",c"), b',');
    }

    #[test]
    fn line_numbers_survive_comments_blank_lines_and_a_bom() {
        let t = Table::parse("\u{feff}# c\n\n\"t [s]\";\"u (V)\"\n# mid\n1;0,5\n\n2;1,5\n")
            .unwrap()
            .unwrap();
        assert_eq!(t.header_line, 3);
        assert_eq!(t.names, ["t", "u"]);
        assert_eq!(t.raw_names, ["t [s]", "u (V)"]);
        assert_eq!(
            t.rows.iter().map(|r| r.line).collect::<Vec<_>>(),
            vec![5, 7]
        );
        assert_eq!(t.number(&t.rows[0].cells[1]), Some(0.5));
        assert_eq!(Table::parse("# only\n\n").unwrap(), None);
    }

    #[test]
    fn a_long_cell_is_quoted_by_its_start() {
        assert_eq!(Table::excerpt("1.5x"), "1.5x");
        let long = format!("1.5\n{}", "0,1,2\n".repeat(1000));
        let e = Table::excerpt(&long);
        assert!(
            e.len() < 120 && e.contains("6004 bytes") && e.contains("unclosed quote"),
            "{e}"
        );
    }

    #[test]
    fn a_row_longer_than_the_header_is_refused_naming_its_line() {
        let (line, message) = Table::parse("t,u,x\n0,1,2\n0.1,1,5,-100\n").unwrap_err();
        assert_eq!(line, 3);
        assert!(
            message.contains("4 cells") && message.contains("t, u, x"),
            "{message}"
        );
        // A trailing delimiter on a row (or on every row) holds nothing: read.
        let t = Table::parse("t,u\n0,1,\n0.1,2\n").unwrap().unwrap();
        assert_eq!(t.rows.len(), 2);
    }
}
