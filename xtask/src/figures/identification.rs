//! Tables of the identification runs: `identify`'s held-out errors, `auto`'s ranking, the lab
//! stage's tracking, the variants and the learning runs (a row per run or per model).

use super::output::{printed_lines, verbatim};
use super::{Run, TOOL};

/// `identify`'s held-out errors of each run: a row per model (its name as `identify` prints it,
/// less the creep's mode count, which differs from record to record), forward and inverse
/// columns per record, `max / RMS %`.
pub(super) fn identify_table(runs: &[Run]) -> Result<String, String> {
    let mut records: Vec<(&str, &str)> = Vec::new();
    let mut rows: Vec<(String, Vec<Option<String>>)> = Vec::new();
    let mut cells = Vec::new();
    for run in runs {
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let data = run_arg(run, "--data").ok_or_else(|| what("no --data"))?;
        let until = run_arg(run, "--fit-until").ok_or_else(|| what("no --fit-until"))?;
        let model = run
            .out
            .lines()
            .find_map(|l| l.strip_prefix("identified "))
            .and_then(|l| l.split(" from ").next())
            .ok_or_else(|| what("no `identified … from` line"))?;
        // "+ creep (2 modes)" → "+ creep".
        let model = match model.split_once(" + creep") {
            Some((m, _)) => format!("{m} + creep"),
            None => model.to_string(),
        };
        let errors = |prefix: &str| -> Result<String, String> {
            let line = run
                .out
                .lines()
                .map(str::trim)
                .find(|l| l.starts_with(prefix))
                .ok_or_else(|| what(&format!("no `{prefix}` line")))?;
            let cols: Vec<&str> = line.split_whitespace().collect();
            let at = |word: &str| {
                cols.iter()
                    .position(|c| *c == word)
                    .and_then(|i| cols.get(i + 1))
            };
            match (at("max"), at("RMS")) {
                (Some(max), Some(rms)) => Ok(format!("{max} / {rms} %")),
                _ => Err(what(&format!("`{prefix}` has no max and RMS"))),
            }
        };
        let forward = errors("held-out (predict vs measured x):")?;
        let inverse = errors("inverse held-out (compensate u vs measured u):")?;
        let column = match records.iter().position(|(d, _)| *d == data) {
            Some(i) => i,
            None => {
                records.push((data, until));
                records.len() - 1
            }
        };
        cells.push((model, column, forward, inverse));
    }
    for (model, column, forward, inverse) in cells {
        let row = match rows.iter().position(|(m, _)| *m == model) {
            Some(i) => i,
            None => {
                rows.push((model, vec![None; records.len()]));
                rows.len() - 1
            }
        };
        if rows[row].1[column].is_some() {
            return Err(format!("{} twice on one record", rows[row].0));
        }
        rows[row].1[column] = Some(format!("{forward} | {inverse}"));
    }
    let mut table = String::from("| model |");
    for (data, until) in &records {
        let name = data
            .rsplit('/')
            .next()
            .unwrap_or(data)
            .trim_end_matches(".csv");
        table.push_str(&format!(
            " `{name}` (`--fit-until {until}`): held-out max / RMS | inverse |"
        ));
    }
    table.push_str("\n|---|");
    table.push_str(&"---:|---:|".repeat(records.len()));
    table.push('\n');
    for (model, cols) in rows {
        table.push_str(&format!("| {model} |"));
        for c in cols {
            table.push_str(&format!(" {} |", c.unwrap_or_else(|| "— | —".into())));
        }
        table.push('\n');
    }
    Ok(table)
}

/// What `identify` prints of `auto`'s choice: the ranking, its legend and the pick, then the
/// model kept and its held-out figures (its notes and the fixed-point check left out).
pub(super) fn ranking_only(out: &str) -> Result<String, String> {
    let kept: Vec<&str> = printed_lines(out)
        .filter(|l| {
            let l = l.trim_start();
            !(l.starts_with("note:")
                || l.starts_with("fitted t")
                || l.starts_with("sensor lag")
                || l.starts_with("fixed point")
                || l.starts_with("inverse held-out, f64"))
        })
        .collect();
    if !kept.iter().any(|l| l.starts_with("picked: ")) {
        return Err("no `picked:` line".into());
    }
    verbatim(&kept.join("\n"))
}

/// One `identify` ranking line (`  1.  LABEL forward  0.85 % (RMS 0.21 %)  inverse  1.22 %
/// tracking  0.74 %[  set aside: …]`) as its place, label, three figures and standing.
pub(super) fn ranking_row(line: &str) -> Option<(String, String, [String; 3], String)> {
    let line = line.trim_start();
    let (place, rest) = line.split_once(' ')?;
    if !place.ends_with('.') {
        return None;
    }
    let rest = rest.trim_start();
    let Some((label, figures)) = rest.split_once(" forward ") else {
        // Not fitted: no figures, only why.
        let (label, why) = rest.split_once("  ")?;
        let dash = || "—".to_string();
        return Some((
            place.into(),
            label.trim().into(),
            [dash(), dash(), dash()],
            why.trim().into(),
        ));
    };
    let after = |key: &str| -> Option<String> {
        let i = figures.find(key)? + key.len();
        let v = figures[i..].split_whitespace().next()?;
        Some(if v == "-" {
            "—".into()
        } else {
            format!("{v} %")
        })
    };
    let forward = figures.split_whitespace().next()?;
    let forward = if forward == "-" {
        "—".into()
    } else {
        format!("{forward} %")
    };
    let (inverse, tracking) = (after("inverse ")?, after("tracking ")?);
    // What follows the tracking figure: the standing, if any.
    let tracked = figures[figures.find("tracking ")? + "tracking ".len()..].trim_start();
    let value = tracked.split_whitespace().next()?;
    let tail = tracked[value.len()..].trim_start();
    let tail = tail.strip_prefix('%').unwrap_or(tail).trim();
    let ratio = |t: &str| {
        t.split(" is ")
            .nth(1)
            .and_then(|r| r.split(" × ").next())
            .map(str::to_string)
    };
    let standing = if let Some(t) = tail.strip_prefix("set aside: ") {
        format!(
            "set aside: inverse {} × its fit, far from the best",
            ratio(t)?
        )
    } else if let Some(t) = tail.strip_prefix("(inverse ") {
        let r = t.split(" × ").next()?;
        format!("inverse {r} × its fit: at the noise floor")
    } else if let Some(t) = tail.strip_prefix("not admitted: ") {
        match t
            .split("needs ")
            .nth(1)
            .and_then(|n| n.split(" cycles").next())
        {
            // Where the run also says what the compensator alone needs, that too.
            Some(cycles) => match t.split("without the observer, ").nth(1) {
                Some(alone) if alone.trim().parse::<u32>().is_ok() => format!(
                    "not admitted: {cycles} cycles per tick, {} as the compensator only",
                    alone.trim()
                ),
                _ => format!("not admitted: {cycles} cycles per tick"),
            },
            None => format!("not admitted: {t}"),
        }
    } else if tail.is_empty() {
        "inverse holds".into()
    } else {
        return None;
    };
    Some((
        place.into(),
        label.trim().into(),
        [forward, inverse, tracking],
        standing,
    ))
}

/// `auto`'s ranking from every run as one Markdown table: per record and tick rate, each
/// candidate's validation max errors (forward, inverse, tracking) and where it stands, the
/// pick marked with its held-out figures.
pub(super) fn ranking_table(runs: &[Run]) -> Result<String, String> {
    let mut table = String::from(
        "| record, tick rate | candidate | forward | inverse | tracking | standing |\n\
         |---|---|---:|---:|---:|---|\n",
    );
    for run in runs {
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let data = run_arg(run, "--data").ok_or_else(|| what("no --data"))?;
        let name = data
            .rsplit('/')
            .next()
            .unwrap_or(data)
            .trim_end_matches(".csv");
        let rate = run_arg(run, "--tick-rate").map_or("any".to_string(), |r| {
            r.parse::<f64>()
                .map_or(r.to_string(), |hz| format!("{:.0} kHz", hz / 1e3))
        });
        let held = |prefix: &str| -> Result<String, String> {
            run.out
                .lines()
                .map(str::trim)
                .find_map(|l| l.strip_prefix(prefix))
                .and_then(|l| l.split_whitespace().nth(1))
                .map(|v| format!("{v} %"))
                .ok_or_else(|| what(&format!("no `{prefix}` line")))
        };
        let (held_forward, held_inverse) = (
            held("held-out (predict vs measured x):")?,
            held("inverse held-out (compensate u vs measured u):")?,
        );
        let mut rows = 0;
        let mut in_ranking = false;
        for line in run.out.lines() {
            if line.starts_with("ranking ") {
                in_ranking = true;
                continue;
            }
            if !line.starts_with("  ") {
                in_ranking = false;
            }
            if !in_ranking || line.trim_start().starts_with('(') {
                continue;
            }
            let (place, label, [f, i, t], standing) =
                ranking_row(line).ok_or_else(|| what(&format!("unread ranking line `{line}`")))?;
            let standing = if rows == 0 {
                format!("**picked** (held out: forward {held_forward}, inverse {held_inverse})")
            } else if place == "-." {
                standing
            } else {
                format!("{place} {standing}")
            };
            let record = if rows == 0 {
                format!("`{name}`, {rate}")
            } else {
                String::new()
            };
            table.push_str(&format!(
                "| {record} | {label} | {f} | {i} | {t} | {standing} |\n"
            ));
            rows += 1;
        }
        if rows == 0 {
            return Err(what("no ranking"));
        }
    }
    Ok(table)
}

/// `lab-stage`'s rows from every run as one Markdown table, a method that several runs print
/// (`none`) once: held-out, the three trajectories and the worst max (`max / RMS %`), or the
/// reason a model was refused.
pub(super) fn lab_stage_table(runs: &[Run]) -> Result<String, String> {
    let mut table = String::from(
        "| method | held-out (last cycle) | triangle | minor loops | multisine | worst max |\n\
         |---|---:|---:|---:|---:|---:|\n",
    );
    let mut seen: Vec<String> = Vec::new();
    for run in runs {
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        // A stage with some of its non-idealities taken out: its rows say so.
        let without = run_arg(run, "--without")
            .map(|w| format!(", without {}", w.replace(',', ", ")))
            .unwrap_or_default();
        // Fitted as the board runs it at a control rate: its rows say at which.
        let without = match run_arg(run, "--tick-rate").and_then(|r| r.parse::<f64>().ok()) {
            Some(hz) => format!("{without}, board at {} kHz", hz / 1e3),
            None => without,
        };
        let mut lines = run.out.lines().skip_while(|l| !l.starts_with("method "));
        if lines.next().is_none() {
            return Err(what("no `method` header"));
        }
        let mut rows = 0;
        for line in lines.take_while(|l| !l.starts_with('(')) {
            let (name, rest) = match line.split_once(" failed: ") {
                Some((head, reason)) => {
                    let name = head.split_whitespace().next().unwrap_or("");
                    (name.to_string(), format!("refused: {reason} | | | | |"))
                }
                None => {
                    let cols: Vec<&str> = line.split_whitespace().collect();
                    let n = cols.len();
                    if n < 6 {
                        return Err(what(&format!("a row with {n} columns: {line:?}")));
                    }
                    let figure = |c: &str| c.replace('/', " / ");
                    (
                        cols[..n - 5].join(" "),
                        format!(
                            "{} | {} | {} | {} | {} |",
                            if cols[n - 5] == "-" {
                                "–".into()
                            } else {
                                figure(cols[n - 5])
                            },
                            figure(cols[n - 4]),
                            figure(cols[n - 3]),
                            figure(cols[n - 2]),
                            cols[n - 1]
                        ),
                    )
                }
            };
            let name = format!("{name}{without}");
            rows += 1;
            if seen.contains(&name) {
                continue;
            }
            table.push_str(&format!("| {name} | {rest}\n"));
            seen.push(name);
        }
        if rows == 0 {
            return Err(what("no rows"));
        }
    }
    Ok(table)
}

/// `lab-stage --variants`'s lines as a table: the stage, its settings, the worst max error of no
/// compensation, `auto` and the textbook P–I, and what `auto` picked.
pub(super) fn variants_table(out: &str) -> Result<String, String> {
    let mut table = String::from(
        "| stage | changes (`--set`) | none | textbook P–I | auto | auto picked |\n\
         |---|---|---:|---:|---:|---|\n",
    );
    let mut lines = out.lines().skip_while(|l| !l.starts_with("stage "));
    if lines.next().is_none() {
        return Err("no `stage` header".into());
    }
    let mut rows = 0;
    for line in lines.filter(|l| !l.trim().is_empty()) {
        let (head, settings) = line
            .rsplit_once(" / ")
            .ok_or_else(|| format!("no ` / ` in {line:?}"))?;
        // The stage's name in its column (`print_variants`), then the three rows' worst
        // errors in the order run (none, auto, the textbook P–I), then what auto picked
        // (words: `gpi (no observer)` where a board's rate sized it down).
        let (stage, rest) = head
            .split_at_checked(STAGE_COLUMN.min(head.len()))
            .ok_or_else(|| format!("not a stage's line: {line:?}"))?;
        let cols: Vec<&str> = rest.split_whitespace().collect();
        if cols.len() < 4 || cols[..3].iter().any(|c| c.parse::<f64>().is_err()) {
            return Err(format!("not a stage's line: {line:?}"));
        }
        let settings = match settings.trim() {
            "-" => "–".to_string(),
            s => format!("`{}`", s.replace(',', ", ")),
        };
        table.push_str(&format!(
            "| {} | {settings} | {} | {} | {} | {} |\n",
            stage.trim(),
            cols[0],
            cols[2],
            cols[1],
            cols[3..].join(" ")
        ));
        rows += 1;
    }
    if rows == 0 {
        return Err("no stages".into());
    }
    Ok(table)
}

/// The width of `twinstack lab-stage --variants`' stage column
/// (`twinstack_cli::tracking::print_variants`).
const STAGE_COLUMN: usize = 22;

/// `learn`'s summary of each run as one row: the feedforward alone (and shaped, with input
/// shaping), the learned and the replayed errors, the reduction, and `(not met)` beside a
/// figure that misses its goal (RMS ≥ 20× lower, max ≤ 0.1 %, replay max ≤ 0.2 %).
pub(super) fn learn_table(runs: &[Run]) -> Result<String, String> {
    let mut table = String::from(
        "| waveform | run | feedforward alone RMS % | shaped feedforward alone RMS % | learned max % | learned RMS % | RMS reduction | replay max % | RMS below 15 kHz % | RMS 15 kHz–Nyquist % |\n\
         |---|---|---:|---:|---:|---:|---:|---:|---:|---:|\n",
    );
    for run in runs {
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let label = run_arg(run, "--waveform")
            .and_then(waveform_label)
            .ok_or_else(|| what("no --waveform SHAPE:HZ"))?;
        let shaped = run_arg(run, "--shape-hz").is_some();
        // The summary table's row for `name`: its four figures.
        let row = |name: &str| -> Result<Vec<String>, String> {
            let line = run
                .out
                .lines()
                .find(|l| l.starts_with(&format!("| {name} |")))
                .ok_or_else(|| what(&format!("no `{name}` row")))?;
            let cols: Vec<String> = line
                .trim_matches('|')
                .split('|')
                .skip(1)
                .map(|c| c.trim().to_string())
                .collect();
            if cols.len() == 4 {
                Ok(cols)
            } else {
                Err(what(&format!(
                    "the `{name}` row has {} figures",
                    cols.len()
                )))
            }
        };
        let met = |goal: &str| -> Result<&str, String> {
            let line = run
                .out
                .lines()
                .find(|l| l.starts_with(&format!("goal: {goal}")))
                .ok_or_else(|| what(&format!("no goal `{goal}`")))?;
            Ok(if line.ends_with(": met") {
                ""
            } else {
                " (not met)"
            })
        };
        let alone = row("inverse P–I feedforward alone")?;
        let shaped_alone = if shaped {
            row("shaped feedforward alone")?[1].clone()
        } else {
            "—".into()
        };
        let learned = row("learned (last period)")?;
        let replay = row("replayed, sensor off")?;
        let reduction = run
            .out
            .lines()
            .find_map(|l| l.strip_prefix("RMS reduction "))
            .and_then(|l| l.split(';').next())
            .ok_or_else(|| what("no `RMS reduction`"))?;
        table.push_str(&format!(
            "| {label} | {} | {} | {shaped_alone} | {}{} | {} | {reduction}{} | {}{} | {} | {} |\n",
            if shaped {
                "shaping, corner 23 kHz"
            } else {
                "no shaping, corner 18 kHz"
            },
            alone[1],
            learned[0],
            met("max")?,
            learned[1],
            met("RMS")?,
            replay[0],
            met("replay")?,
            learned[2],
            learned[3],
        ));
    }
    Ok(table)
}

/// The lab stage's triangles (`twinstack lab-stage --triangles … --json`): a row per method,
/// a column per triangle frequency, max / RMS % of the span (`*` where the drive clipped);
/// with `--preview`, the resonance measured on the stage above it.
pub(super) fn triangles_table(out: &str) -> Result<String, String> {
    let v: serde_json::Value =
        serde_json::from_str(out).map_err(|e| format!("lab-stage's JSON: {e}"))?;
    let names: Vec<&str> = v["trajectories"]
        .as_array()
        .ok_or("no `trajectories`")?
        .iter()
        .filter_map(|n| n.as_str())
        .collect();
    // The triangles asked for follow the three standing trajectories.
    let columns: Vec<usize> = (0..names.len())
        .filter(|&i| names[i].starts_with("triangle ") && names[i].ends_with(" Hz"))
        .collect();
    if columns.is_empty() {
        return Err("no `triangle … Hz` trajectory: run with --triangles".into());
    }
    let mut table = String::new();
    if let Some(r) = v["resonance"].as_object() {
        let figure = |name: &str| {
            r.get(name)
                .and_then(|f| f.as_f64())
                .ok_or(format!("`resonance` without `{name}`"))
        };
        table.push_str(&format!(
            "The preview's resonance, measured on the stage as `tune` measures a board's: {:.0} Hz, damping ratio {:.4} (the fit within {:.2} dB and {:.1}° RMS).\n\n",
            figure("frequency_hz")?,
            figure("zeta")?,
            figure("rms_db")?,
            figure("rms_deg")?
        ));
    }
    table.push_str("| method |");
    for &i in &columns {
        table.push_str(&format!(" {} |", &names[i]["triangle ".len()..]));
    }
    table.push_str("\n|---|");
    table.push_str(&"---:|".repeat(columns.len()));
    table.push('\n');
    for row in v["rows"].as_array().ok_or("no `rows`")? {
        let method = row["method"].as_str().ok_or("a row without `method`")?;
        table.push_str(&format!("| {method} |"));
        match row["scores"].as_array() {
            Some(scores) if scores.len() == names.len() => {
                for &i in &columns {
                    let s = &scores[i];
                    let (max, rms) = (s["max_pct"].as_f64(), s["rms_pct"].as_f64());
                    let (Some(max), Some(rms)) = (max, rms) else {
                        return Err(format!("{method}: a score without its figures"));
                    };
                    let clipped = s["clipped"].as_u64().unwrap_or(0) > 0;
                    table.push_str(&format!(
                        " {max:.2} / {rms:.2}{} |",
                        if clipped { " *" } else { "" }
                    ));
                }
            }
            _ => {
                let why = row["error"].as_str().unwrap_or("no scores");
                table.push_str(&format!(" refused: {why} |"));
                table.push_str(&" |".repeat(columns.len() - 1));
            }
        }
        table.push('\n');
    }
    Ok(table)
}

/// The value following `flag` in a run's arguments.
fn run_arg<'a>(run: &'a Run, flag: &str) -> Option<&'a str> {
    run.args
        .iter()
        .position(|a| *a == flag)
        .and_then(|i| run.args.get(i + 1))
        .copied()
}

/// A waveform argument (`SHAPE:HZ`) as the learning tables name it (`750 Hz sine`).
fn waveform_label(waveform: &str) -> Option<String> {
    let (shape, hz) = waveform.split_once(':')?;
    let hz: f64 = hz.parse().ok()?;
    Some(if hz >= 1000.0 {
        format!("{} kHz {shape}", hz / 1000.0)
    } else {
        format!("{hz} Hz {shape}")
    })
}

/// The learning run's per-period RMS errors (`| period | max % | RMS % |`), period 1 first.
fn period_rms(out: &str) -> Vec<String> {
    out.lines()
        .filter_map(|l| {
            let cols: Vec<&str> = l.trim_matches('|').split('|').map(str::trim).collect();
            match cols.as_slice() {
                [period, _, rms] if period.parse::<u32>().is_ok() => Some(rms.to_string()),
                _ => None,
            }
        })
        .collect()
}

/// The learning curves: the RMS error (% of the stroke) at periods 1, 3, 5, 10, 20, 30 and 50
/// of each run, a row per waveform and shaping.
pub(super) fn learn_curves_table(runs: &[Run]) -> Result<String, String> {
    const PERIODS: [usize; 7] = [1, 3, 5, 10, 20, 30, 50];
    let mut table = String::from("| waveform | run |");
    for p in PERIODS {
        table.push_str(&format!(" {p} |"));
    }
    table.push_str("\n|---|---|");
    table.push_str(&"---:|".repeat(PERIODS.len()));
    table.push('\n');
    for run in runs {
        let what = |e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let label = run_arg(run, "--waveform")
            .and_then(waveform_label)
            .ok_or_else(|| what("no --waveform SHAPE:HZ"))?;
        let shaping = if run_arg(run, "--shape-hz").is_some() {
            "shaping"
        } else {
            "no shaping"
        };
        let rms = period_rms(&run.out);
        table.push_str(&format!("| {label} | {shaping} |"));
        for p in PERIODS {
            let v = rms
                .get(p - 1)
                .ok_or_else(|| what(&format!("no period {p}")))?;
            table.push_str(&format!(" {v} |"));
        }
        table.push('\n');
    }
    Ok(table)
}

/// The notch's robustness: the learned RMS (sine / triangle, % of the stroke) for each corner
/// (a row) and the notch's offset from the fitted resonance (a column). The runs come in
/// pairs (sine, triangle) for each notch frequency, corner by corner.
pub(super) fn learn_notch_table(runs: &[Run]) -> Result<String, String> {
    const RESONANCE_HZ: f64 = 21_807.0;
    let mut corners: Vec<(String, Vec<(String, String)>)> = Vec::new();
    for pair in runs.chunks(2) {
        let [sine, triangle] = pair else {
            return Err("the notch runs come in pairs (sine, triangle)".into());
        };
        let what = |run: &Run, e: &str| format!("`{TOOL} {}`: {e}", run.args.join(" "));
        let learned = |run: &Run| -> Result<String, String> {
            run.out
                .lines()
                .find(|l| l.starts_with("| learned (last period) |"))
                .and_then(|l| l.trim_matches('|').split('|').nth(2))
                .map(|v| v.trim().to_string())
                .ok_or_else(|| what(run, "no `learned (last period)` row"))
        };
        let corner = run_arg(sine, "--cutoff-hz").ok_or_else(|| what(sine, "no --cutoff-hz"))?;
        let notch: f64 = run_arg(sine, "--shape-hz")
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| what(sine, "no --shape-hz"))?;
        let offset = 100.0 * (notch / RESONANCE_HZ - 1.0);
        let offset = if offset.abs() < 0.05 {
            "0".to_string()
        } else {
            format!("{offset:+.1} %")
        };
        let cell = (
            offset,
            format!("{} / {}", learned(sine)?, learned(triangle)?),
        );
        match corners.last_mut() {
            Some((c, cells)) if c == corner => cells.push(cell),
            _ => corners.push((corner.to_string(), vec![cell])),
        }
    }
    let first = corners.first().ok_or("no notch runs")?;
    let mut table = String::from("| corner |");
    for (offset, _) in &first.1 {
        table.push_str(&format!(" {offset} |"));
    }
    table.push_str("\n|---|");
    table.push_str(&"---:|".repeat(first.1.len()));
    table.push('\n');
    for (corner, cells) in &corners {
        let hz: f64 = corner.parse().map_err(|_| format!("corner {corner}"))?;
        table.push_str(&format!("| {} kHz |", hz / 1000.0));
        for (_, cell) in cells {
            table.push_str(&format!(" {cell} |"));
        }
        table.push('\n');
    }
    Ok(table)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A learning run's output: the per-period table, then the summary.
    fn learn_out(rms: &[&str], learned: &str) -> String {
        let mut out = String::from("| period | max % | RMS % |\n|---:|---:|---:|\n");
        for (i, r) in rms.iter().enumerate() {
            out.push_str(&format!("| {} | 0.9 | {r} |\n", i + 1));
        }
        out.push_str(&format!(
            "\n| run | max % | RMS % | a | b |\n| learned (last period) | 0.1 | {learned} | 0 | 0 |\n"
        ));
        out
    }

    #[test]
    fn learning_curves_take_the_periods_rms_and_fail_on_a_short_run() {
        let rms: Vec<String> = (1..=50).map(|p| format!("0.{p:04}")).collect();
        let rms: Vec<&str> = rms.iter().map(String::as_str).collect();
        let runs = [
            Run {
                args: &["learn", "--waveform", "sine:750"],
                out: learn_out(&rms, "0.0050"),
            },
            Run {
                args: &["learn", "--waveform", "triangle:200", "--shape-hz", "21807"],
                out: learn_out(&rms, "0.0050"),
            },
        ];
        let table = learn_curves_table(&runs).unwrap();
        let rows: Vec<&str> = table.lines().skip(2).collect();
        assert_eq!(
            rows,
            [
                "| 750 Hz sine | no shaping | 0.0001 | 0.0003 | 0.0005 | 0.0010 | 0.0020 | 0.0030 | 0.0050 |",
                "| 200 Hz triangle | shaping | 0.0001 | 0.0003 | 0.0005 | 0.0010 | 0.0020 | 0.0030 | 0.0050 |",
            ]
        );
        let short = [Run {
            args: &["learn", "--waveform", "sine:750"],
            out: learn_out(&rms[..20], "0.0050"),
        }];
        assert!(learn_curves_table(&short)
            .unwrap_err()
            .contains("no period 30"));
    }

    #[test]
    fn the_notch_table_has_a_row_per_corner_and_a_column_per_offset() {
        let run = |w: &'static str, notch: &'static str, corner: &'static str, v: &str| Run {
            args: Box::leak(Box::new([
                "learn",
                "--waveform",
                w,
                "--shape-hz",
                notch,
                "--cutoff-hz",
                corner,
            ])),
            out: learn_out(&["1"], v),
        };
        let runs = [
            run("sine:750", "21371", "22000", "0.1"),
            run("triangle:200", "21371", "22000", "0.2"),
            run("sine:750", "21807", "22000", "0.3"),
            run("triangle:200", "21807", "22000", "0.4"),
            run("sine:750", "21371", "23000", "0.5"),
            run("triangle:200", "21371", "23000", "0.6"),
            run("sine:750", "21807", "23000", "0.7"),
            run("triangle:200", "21807", "23000", "0.8"),
        ];
        let table = learn_notch_table(&runs).unwrap();
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(
            lines,
            [
                "| corner | -2.0 % | 0 |",
                "|---|---:|---:|",
                "| 22 kHz | 0.1 / 0.2 | 0.3 / 0.4 |",
                "| 23 kHz | 0.5 / 0.6 | 0.7 / 0.8 |",
            ]
        );
        assert!(learn_notch_table(&runs[..3]).is_err());
    }

    #[test]
    fn triangles_become_a_column_each_and_a_refused_row_says_why() {
        let score =
            |m: f64, c: u64| format!(r#"{{"max_pct": {m}, "rms_pct": 0.5, "clipped": {c}}}"#);
        let scores = |a: f64| {
            [0.0, 0.0, 0.0, a, 2.0 * a]
                .iter()
                .enumerate()
                .map(|(i, &m)| score(m, (i == 4 && a > 1.0) as u64))
                .collect::<Vec<_>>()
                .join(",")
        };
        let out = format!(
            r#"{{"trajectories": ["triangle", "minor loops", "multisine", "triangle 1 Hz", "triangle 200 Hz"],
               "rows": [{{"method": "none", "scores": [{}], "error": null}},
                        {{"method": "auto: gpi", "scores": [{}], "error": null}},
                        {{"method": "duhem", "scores": [], "error": "not fitted"}}]}}"#,
            scores(10.0),
            scores(0.5)
        );
        let table = triangles_table(&out).unwrap();
        let lines: Vec<&str> = table.lines().collect();
        assert_eq!(
            lines,
            [
                "| method | 1 Hz | 200 Hz |",
                "|---|---:|---:|",
                "| none | 10.00 / 0.50 | 20.00 / 0.50 * |",
                "| auto: gpi | 0.50 / 0.50 | 1.00 / 0.50 |",
                "| duhem | refused: not fitted | |",
            ]
        );
        assert!(triangles_table(r#"{"trajectories": ["triangle"], "rows": []}"#).is_err());
        // With a preview, its measured resonance heads the table; one missing its figure is
        // refused.
        let previewed = out.replacen(
            "{",
            r#"{"resonance": {"frequency_hz": 3497.2, "zeta": 0.03121, "rms_db": 0.15, "rms_deg": 2.9}, "#,
            1,
        );
        let table = triangles_table(&previewed).unwrap();
        assert!(
            table.starts_with("The preview's resonance, measured on the stage as `tune` measures a board's: 3497 Hz, damping ratio 0.0312 (the fit within 0.15 dB and 2.9° RMS).\n\n| method |"),
            "{table}"
        );
        let incomplete = out.replacen("{", r#"{"resonance": {"frequency_hz": 3497.2}, "#, 1);
        assert!(triangles_table(&incomplete).is_err());
    }

    #[test]
    fn ranking_lines_become_rows_with_their_standing() {
        let out = [
            "ranking (fitted on t < 5.1502 s, scored on 5.1502 <= t < 5.95 s):",
            "  (legend)",
            "  1.  P-I (16 uniform operators)               forward  1.30 % (RMS 0.38 %)  inverse  1.59 %  tracking  1.02 %",
            "  2.  P-I (4 uniform operators) + creep (1 mode) forward  1.10 % (RMS 0.39 %)  inverse  1.81 %  tracking  1.84 %  (inverse 1.64 × its forward: at the record's noise floor)",
            "  -.  Bouc-Wen + creep (1 mode)                forward  0.90 % (RMS 0.23 %)  inverse 14.58 %  tracking 13.55 %  set aside: inverse max 14.58 % is 16.22 × its forward max 0.90 % and more",
            "  -.  Duhem + creep (1 mode)                   forward  1.11 % (RMS 0.30 %)  inverse 17.58 %  tracking 15.66 %  not admitted: the board at 100 kHz would refuse it: it needs 1732 cycles per tick, more",
            "  -.  Bouc-Wen                                 forward  1.42 % (RMS 0.54 %)  inverse  1.76 %  tracking  1.04 %  not admitted: the board at 100 kHz would refuse it: it needs 2260 cycles per tick, more than the 1344 that rate leaves; without the observer, 1465",
            "  -.  Duhem                                    not fitted: too few samples",
            "picked: P-I",
            "identified P-I (16 uniform operators) from x",
            "  held-out (predict vs measured x): max 1.16 %  RMS 0.30 %  (20251 samples)",
            "  inverse held-out (compensate u vs measured u): max 1.47 %  RMS 0.33 %  (20251 samples)",
        ]
        .join("\n");
        let out = out.as_str();
        let runs = [Run {
            args: &["identify", "--data", "data/a.csv", "--tick-rate", "100000"],
            out: out.into(),
        }];
        let table = ranking_table(&runs).unwrap();
        let rows: Vec<&str> = table.lines().skip(2).collect();
        assert_eq!(
            rows,
            [
                "| `a`, 100 kHz | P-I (16 uniform operators) | 1.30 % | 1.59 % | 1.02 % | **picked** (held out: forward 1.16 %, inverse 1.47 %) |",
                "|  | P-I (4 uniform operators) + creep (1 mode) | 1.10 % | 1.81 % | 1.84 % | 2. inverse 1.64 × its fit: at the noise floor |",
                "|  | Bouc-Wen + creep (1 mode) | 0.90 % | 14.58 % | 13.55 % | set aside: inverse 16.22 × its fit, far from the best |",
                "|  | Duhem + creep (1 mode) | 1.11 % | 17.58 % | 15.66 % | not admitted: 1732 cycles per tick |",
                "|  | Bouc-Wen | 1.42 % | 1.76 % | 1.04 % | not admitted: 2260 cycles per tick, 1465 as the compensator only |",
                "|  | Duhem | — | — | — | not fitted: too few samples |",
            ]
        );
        let kept = ranking_only(out).unwrap();
        assert!(
            kept.contains("picked: P-I") && kept.contains("inverse held-out"),
            "{kept}"
        );
    }

    #[test]
    fn learn_runs_become_rows_with_their_unmet_goals_marked() {
        let out = "| run | max % | RMS % | RMS below 15 kHz % | RMS 15 kHz–Nyquist % |\n\
                   |---|---:|---:|---:|---:|\n\
                   | inverse P–I feedforward alone | 1.9294 | 1.3000 | 1.2855 | 0.1939 |\n\
                   | learned (last period) | 0.7359 | 0.2212 | 0.0092 | 0.2210 |\n\
                   | replayed, sensor off | 0.7336 | 0.2199 | 0.0084 | 0.2198 |\n\n\
                   RMS reduction 5.9×; 50 tables posted, 0 periods missed\n\
                   goal: RMS ≥ 20× lower than feedforward alone: NOT met\n\
                   goal: max ≤ 0.1 % of the stroke: NOT met\n\
                   goal: replay (sensor off) max ≤ 0.2 %: met\n";
        let runs = [Run {
            args: &["learn", "--waveform", "triangle:250"],
            out: out.into(),
        }];
        let table = learn_table(&runs).unwrap();
        assert!(
            table.ends_with(
                "| 250 Hz triangle | no shaping, corner 18 kHz | 1.3000 | — | 0.7359 (not met) | \
                 0.2212 | 5.9× (not met) | 0.7336 | 0.0092 | 0.2210 |\n"
            ),
            "{table}"
        );
        // A shaped run needs its shaped row; a missing row is an error, not a blank.
        let shaped = [Run {
            args: &["learn", "--waveform", "triangle:250", "--shape-hz", "21807"],
            out: out.into(),
        }];
        assert!(learn_table(&shaped).is_err());
    }

    #[test]
    fn identify_runs_become_a_row_per_model_and_a_column_pair_per_record() {
        let out = |model: &str, fwd: &str, inv: &str| {
            format!(
                "identified {model} from data/x.csv\n  fit      (predict vs measured x): max 9 %  RMS 9 %\n  \
                 held-out (predict vs measured x): max {fwd}  (20251 samples)\n  \
                 inverse held-out (compensate u vs measured u): max {inv}  (20251 samples)\n"
            )
        };
        let runs = [
            Run {
                args: &[
                    "identify",
                    "--model",
                    "pi",
                    "--creep",
                    "--data",
                    "data/a.csv",
                    "--fit-until",
                    "5",
                ],
                out: out(
                    "P-I (17 uniform operators) + creep (2 modes)",
                    "0.83 %  RMS 0.18 %",
                    "1.29 %  RMS 0.24 %",
                ),
            },
            Run {
                args: &[
                    "identify",
                    "--model",
                    "pi",
                    "--creep",
                    "--data",
                    "data/b.csv",
                    "--fit-until",
                    "16",
                ],
                out: out(
                    "P-I (17 uniform operators) + creep (1 mode)",
                    "1.44 %  RMS 0.70 %",
                    "2.08 %  RMS 0.89 %",
                ),
            },
        ];
        let table = identify_table(&runs).unwrap();
        assert!(
            table.ends_with(
                "| P-I (17 uniform operators) + creep | 0.83 / 0.18 % | 1.29 / 0.24 % | 1.44 / 0.70 % | 2.08 / 0.89 % |\n"
            ),
            "{table}"
        );
        assert!(
            table.starts_with("| model | `a` (`--fit-until 5`)"),
            "{table}"
        );
        // A run without its held-out line is an error, not an empty cell.
        let cut = [Run {
            args: runs[0].args,
            out: runs[0].out.replace("held-out (predict", "(predict"),
        }];
        assert!(identify_table(&cut).is_err());
    }

    #[test]
    fn lab_stage_rows_of_every_run_become_one_table() {
        let runs = [
            Run {
                args: &["lab-stage"],
                out: "Lab stage (seed 1)\nmethod     held-out max/rms   triangle  minor loops  multisine  worst max\n\
                      none    -   10.47/5.46   10.47/4.80   10.50/5.06   10.50\n\
                      auto: gpi+creep   1.58/0.79   0.66/0.29   0.63/0.23   0.62/0.23   0.66\n\
                      (max/rms error in %)\n"
                    .into(),
            },
            Run {
                args: &["lab-stage", "--model", "duhem"],
                out: "method     held-out\nnone    -   10.47/5.46   10.47/4.80   10.50/5.06   10.50\n\
                      duhem     - failed: Duhem does not fit this record\n(max/rms)\n"
                    .into(),
            },
        ];
        assert_eq!(
            lab_stage_table(&runs).unwrap(),
            "| method | held-out (last cycle) | triangle | minor loops | multisine | worst max |\n\
             |---|---:|---:|---:|---:|---:|\n\
             | none | – | 10.47 / 5.46 | 10.47 / 4.80 | 10.50 / 5.06 | 10.50 |\n\
             | auto: gpi+creep | 1.58 / 0.79 | 0.66 / 0.29 | 0.63 / 0.23 | 0.62 / 0.23 | 0.66 |\n\
             | duhem | refused: Duhem does not fit this record | | | | |\n"
        );
        let headless = [Run {
            args: &["lab-stage"],
            out: "none - 1/1 1/1 1/1 1/1 1\n".into(),
        }];
        assert!(lab_stage_table(&headless).is_err());
    }

    #[test]
    fn variant_lines_become_the_table() {
        let out = "Worst max tracking error\n\
                   stage                      none     auto       pi  auto picked / settings\n\
                   default                   10.50     0.66     4.42  gpi+creep / -\n\
                   no creep                   8.88     0.74     3.63  gpi / creep_per_decade=0,noise_rms_nm=5\n";
        assert_eq!(
            variants_table(out).unwrap(),
            "| stage | changes (`--set`) | none | textbook P–I | auto | auto picked |\n\
             |---|---|---:|---:|---:|---|\n\
             | default | – | 10.50 | 4.42 | 0.66 | gpi+creep |\n\
             | no creep | `creep_per_decade=0, noise_rms_nm=5` | 8.88 | 3.63 | 0.74 | gpi |\n"
        );
        assert!(variants_table("default 10.50 0.66 4.42 gpi / -\n").is_err());
        assert!(variants_table("stage none auto pi\ndefault x y z gpi / -\n").is_err());
    }
}
