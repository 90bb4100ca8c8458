//! Renderings of one command's output as it prints it: a test's printed lines, criterion's
//! results, markdown, `tune`'s summary, verbatim text blocks and the golden vectors' distances.

use super::Run;

/// The lines of a command's output, trailing spaces trimmed, less those naming the files it
/// wrote (`wrote PATH`: where they go depends on the machine, not on the code).
pub(super) fn printed_lines(out: &str) -> impl Iterator<Item = &str> {
    out.lines()
        .map(str::trim_end)
        .filter(|l| !l.starts_with("wrote "))
}

/// What a `cargo test -- --nocapture` run printed, less the test harness's own lines (`running
/// N tests`, `test NAME ... ok`, `test result: …`).
pub(super) fn test_printed(out: &str) -> String {
    let mut kept = Vec::new();
    for line in out.lines() {
        let line = line.trim_end();
        if line.starts_with("running ") || line.starts_with("test result:") {
            continue;
        }
        // The harness writes `test NAME ... ` before the test's output and its verdict after it.
        let line = match line
            .strip_prefix("test ")
            .and_then(|l| l.split_once(" ... "))
        {
            Some((_, rest)) => rest,
            None => line,
        };
        let line = ["ok", "ignored", "FAILED"]
            .iter()
            .find_map(|v| line.strip_suffix(v))
            .unwrap_or(line)
            .trim_end();
        if !line.is_empty() {
            kept.push(line);
        }
    }
    kept.join("\n") + "\n"
}

/// A test's printed Markdown (see [`test_printed`] and [`markdown`]).
pub(super) fn test_markdown(out: &str) -> Result<String, String> {
    markdown(&test_printed(out))
}

/// criterion's results (`cargo bench`) as a table: each benchmark's estimate of one iteration
/// (the middle of its `time: [low estimate high]`).
pub(super) fn criterion_table(out: &str) -> Result<String, String> {
    let mut table = String::from("| benchmark | time per iteration |\n|---|---:|\n");
    let mut name = "";
    let mut rows = 0;
    for line in out.lines().map(str::trim) {
        let (before, times) = match line.split_once("time:") {
            Some(split) => split,
            None => {
                if !line.is_empty() && !line.contains(':') && !line.starts_with(['F', 'c']) {
                    name = line;
                }
                continue;
            }
        };
        let before = before.trim();
        if !before.is_empty() {
            name = before;
        }
        let words: Vec<&str> = times
            .trim()
            .trim_start_matches('[')
            .trim_end_matches(']')
            .split_whitespace()
            .collect();
        let [_, _, mid, unit, _, _] = words[..] else {
            return Err(format!("`{line}`: not criterion's `time: [a u b u c u]`"));
        };
        table.push_str(&format!("| `{name}` | {mid} {unit} |\n"));
        rows += 1;
    }
    if rows == 0 {
        return Err("no criterion results in the output".into());
    }
    Ok(table)
}

/// Output that is already Markdown (titles and tables, as `demo` and `closed-loop` print
/// them): each title line its own paragraph, each table as printed, the lines naming the files
/// the command wrote left out.
pub(super) fn markdown(out: &str) -> Result<String, String> {
    let mut body = String::new();
    let mut tables = 0;
    // Whether the last line written was a table row (`None` before the first line).
    let mut last_row = None;
    for line in printed_lines(out).filter(|l| !l.is_empty()) {
        let row = line.starts_with('|');
        if last_row.is_some() && !(row && last_row == Some(true)) {
            body.push('\n');
        }
        tables += usize::from(line.starts_with("|---"));
        body.push_str(line);
        body.push('\n');
        last_row = Some(row);
    }
    if tables == 0 {
        return Err("no Markdown table in the output".into());
    }
    Ok(body)
}

/// `tune`'s summary: its output less the measured response's lines (`FREQ Hz  GAIN dB  PHASE°`,
/// which the PNG draws), as Markdown.
pub(super) fn tune_summary(out: &str) -> Result<String, String> {
    let is_response = |l: &str| {
        let cols: Vec<&str> = l.split_whitespace().collect();
        matches!(cols[..], [f, "Hz", _, "dB", _] if f.parse::<f64>().is_ok())
    };
    let kept: String = out
        .lines()
        .filter(|l| !is_response(l))
        .map(|l| format!("{l}\n"))
        .collect();
    if !kept.contains("fit: ") || !kept.contains("tuned: ") {
        return Err("no `fit:` and `tuned:` lines in the output".into());
    }
    markdown(&kept)
}

/// Output shown as printed, in a text block, less the lines naming the files it wrote.
pub(super) fn verbatim(out: &str) -> Result<String, String> {
    let kept: Vec<&str> = printed_lines(out).collect();
    let text = kept.join("\n");
    let text = text.trim_matches('\n');
    if text.is_empty() {
        return Err("no output".into());
    }
    Ok(format!("```text\n{text}\n```\n"))
}

/// What a test printed (`cargo test -- --nocapture`), as a text block.
pub(super) fn test_verbatim(out: &str) -> Result<String, String> {
    verbatim(&test_printed(out))
}

/// The last run's output as a text block (the runs before it build what it runs).
pub(super) fn last_verbatim(runs: &[Run]) -> Result<String, String> {
    verbatim(&runs.last().ok_or("no runs")?.out)
}

/// `twinstack golden`'s per-set lines as the page's table: distances to the `f64` reference
/// tick, the worst DAC-code error, ambiguous flag decisions and the flag counts.
pub(super) fn golden_distances(out: &str) -> Result<String, String> {
    let mut table = String::from(
        "| set | drive LSB16 | estimate LSB16 | code | ambiguous | underrun/range/slew/adc/dac/drift |\n\
         |---|---:|---:|---:|---:|---|\n",
    );
    let mut sets = 0;
    let mut total = None;
    for line in out.lines() {
        let cols: Vec<&str> = line.split_whitespace().collect();
        if let ["total", bytes, "bytes", "in", n, "sets"] = cols[..] {
            total = Some((bytes.to_string(), n.to_string()));
            continue;
        }
        // set, ticks, bytes, CRC, drive, estimate, code, ambiguous, counts
        let [set, ticks, _bytes, _crc, drive, estimate, code, ambiguous, counts] = cols[..] else {
            continue;
        };
        if ticks.parse::<u32>().is_err() {
            continue; // the header
        }
        table.push_str(&format!(
            "| `{set}` | {drive} | {estimate} | {code} | {ambiguous} | {counts} |\n"
        ));
        sets += 1;
    }
    let Some((bytes, n)) = total else {
        return Err("no `total … bytes in … sets` line".into());
    };
    if n.parse::<usize>() != Ok(sets) {
        return Err(format!("{sets} set lines, but the total says {n}"));
    }
    table.push_str(&format!(
        "\n{sets} sets, {bytes} bytes in `tests/golden/vectors.bin`.\n"
    ));
    Ok(table)
}

#[cfg(test)]
mod tests {
    use super::*;

    const GOLDEN: &str = "set                   ticks    bytes  outputs CRC  drive LSB16  estimate LSB16  code    ambiguous  underrun/range/slew/adc/dac/drift
bypass                 2400    48011  1234abcd       0.0001       0.0000    0.4997     13      50/338/746/0/7/0
ipi8-pi-open           2400    48011  00ff00ff       1.0507       0.5686    0.4997      4      50/497/801/33/7/253
total 96022 bytes in 2 sets
tests/golden/vectors.bin is up to date
";

    #[test]
    fn test_output_loses_the_harness_lines_and_keeps_what_the_test_printed() {
        let out = "\nrunning 2 tests\ntest a ... | x |\n|---|\n| 1 |\nok\ntest b ... first line\nok\n\ntest result: ok. 2 passed\n";
        assert_eq!(test_printed(out), "| x |\n|---|\n| 1 |\nfirst line\n");
        assert_eq!(
            test_markdown(out).unwrap(),
            "| x |\n|---|\n| 1 |\n\nfirst line\n"
        );
        assert!(test_markdown("running 1 test\ntest a ... ok\n").is_err());
    }

    #[test]
    fn criterion_results_become_a_row_each() {
        let out = "pi_step/forward/8       time:   [5.5 ns 5.6 ns 5.7 ns]\n\
                   Found 3 outliers among 100 measurements (3.00%)\n\
                   duhem_step/inverse\n                        time:   [23.9 ns 24.1 ns 24.4 ns]\n\
                   change: [-1.0% +0.2% +1.1%] (p = 0.70 > 0.05)\n";
        assert_eq!(
            criterion_table(out).unwrap(),
            "| benchmark | time per iteration |\n|---|---:|\n| `pi_step/forward/8` | 5.6 ns |\n| `duhem_step/inverse` | 24.1 ns |\n"
        );
        assert!(criterion_table("nothing measured\n").is_err());
        assert!(criterion_table("x time: [1 ns]\n").is_err());
    }

    #[test]
    fn golden_lines_become_the_table() {
        let t = golden_distances(GOLDEN).unwrap();
        assert!(t.contains("| `bypass` | 0.0001 | 0.0000 | 0.4997 | 13 | 50/338/746/0/7/0 |\n"));
        assert!(
            t.contains("| `ipi8-pi-open` | 1.0507 | 0.5686 | 0.4997 | 4 | 50/497/801/33/7/253 |\n")
        );
        assert!(t.ends_with("\n2 sets, 96022 bytes in `tests/golden/vectors.bin`.\n"));
        // A lost line is an error, not a shorter table.
        let cut = GOLDEN.replace("bypass                 2400", "");
        assert!(golden_distances(&cut).is_err());
        assert!(golden_distances("").is_err());
    }

    #[test]
    fn markdown_output_keeps_its_tables_and_drops_the_files_written() {
        let out = "title one\n| a | b |\n|---|---:|\n| x | 1 |\n\nsecond line\nthird\n| c |\n|---|\n| y |\n\nwrote out/x.png\n";
        assert_eq!(
            markdown(out).unwrap(),
            "title one\n\n| a | b |\n|---|---:|\n| x | 1 |\n\nsecond line\n\nthird\n\n| c |\n|---|\n| y |\n"
        );
        // Output without a table is an error, not an empty figure.
        assert!(markdown("wrote out/x.png\n").is_err());
        assert!(markdown("just text\n").is_err());
    }

    #[test]
    fn tune_summary_leaves_out_the_response() {
        let out = "       200 Hz    -4.17 dB      -3.8°\n     10258 Hz    -2.23 dB    -112.4°\nfit: gain 0.6\ntuned: kp 0.05\n| a |\n|---:|\n| 1 |\n";
        assert_eq!(
            tune_summary(out).unwrap(),
            "fit: gain 0.6\n\ntuned: kp 0.05\n\n| a |\n|---:|\n| 1 |\n"
        );
        assert!(tune_summary("       200 Hz    -4.17 dB      -3.8°\n").is_err());
    }

    #[test]
    fn verbatim_output_is_a_text_block() {
        assert_eq!(
            verbatim("\nline 1  \n  line 2\nwrote a.png\n\n").unwrap(),
            "```text\nline 1\n  line 2\n```\n"
        );
        assert!(verbatim("wrote a.png\n").is_err());
    }
}
