//! The tick-cost page's tables from the whole-interrupt bench's JSON (`target/figures/`):
//! cycles per configuration and scenario, the rates they allow, and the stack's high-water mark.

/// Thousands grouped by a space, as the book writes counts (`1 573`).
pub(super) fn grouped(n: u64) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (i, c) in digits.chars().enumerate() {
        if i > 0 && (digits.len() - i) % 3 == 0 {
            out.push(' ');
        }
        out.push(c);
    }
    out
}

/// A bench configuration's name (`inverse-pi16+pi16-observer+pi+drift`) as the book writes it
/// (`inverse P–I 16 + P–I 16 observer + PI + drift`); a part it does not know stays as it is.
pub(super) fn config_label(name: &str) -> String {
    if name == "bypass-no-model" {
        return "bypass, no model (the defaults)".into();
    }
    fn model(m: &str) -> String {
        if let Some(gpi) = m.strip_prefix("gpi") {
            if let Some((n, zones)) = gpi.split_once('x') {
                return format!("generalised P–I {n} ({zones} dead zones)");
            }
        }
        if let Some(n) = m.strip_prefix("pi").filter(|n| n.parse::<u32>().is_ok()) {
            return format!("P–I {n}");
        }
        match m {
            "duhem" => "Duhem".into(),
            "bouc-wen" => "Bouc–Wen".into(),
            other => other.into(),
        }
    }
    name.split('+')
        .map(|part| {
            if let Some(m) = part.strip_prefix("inverse-") {
                format!("inverse {}", model(m))
            } else if let Some(m) = part.strip_suffix("-observer") {
                format!("{} observer", model(m))
            } else if let Some(n) = part.strip_prefix("creep") {
                format!("creep {n}")
            } else if let Some(n) = part.strip_prefix("map") {
                format!("output map ({n} dead zones)")
            } else {
                match part {
                    "pi" => "PI".into(),
                    "pid" => "PID".into(),
                    other => other.into(),
                }
            }
        })
        .collect::<Vec<_>>()
        .join(" + ")
}

/// The streamed scenarios the first table takes each configuration's worst of.
pub(super) const STREAMED: [&str; 5] = [
    "triangle",
    "sine-750Hz",
    "full-range-steps",
    "random",
    "nested-loops",
];

/// The scan, analog-input, sequence, coarse-ramp, generator and trigger-input scenarios,
/// with their columns' titles.
pub(super) const SCANNED: [(&str, &str); 12] = [
    ("scan-raster-triggers", "raster"),
    ("scan-lissajous-triggers", "Lissajous"),
    ("scan-spiral-triggers", "spiral"),
    ("scan-raster-learning", "raster + learning"),
    ("scan-spiral-learning", "spiral + learning"),
    (
        "scan-spiral-on-trigger-learning",
        "spiral started by the input's edges + learning",
    ),
    ("analog-input", "analog input"),
    ("sequence-on-edges", "TTL-stepped sequence"),
    ("coarse-ramp", "the coarse axis's ramp (dual-stage)"),
    ("waveform-sine-decaying", "the board's generator"),
    ("waveform-sine-learning", "the board's generator + learning"),
    ("triangle-on-trigger", "stream, the input's edges"),
];

/// `site` without its source lines (`recorder.rs:799` → `recorder.rs`): the page names the
/// function and the file, and does not move with every edit above the line.
pub(super) fn without_lines(site: &str) -> String {
    let mut out = String::new();
    let mut rest = site;
    while let Some(at) = rest.find(".rs:") {
        out.push_str(&rest[..at + 3]);
        rest = rest[at + 4..].trim_start_matches(|c: char| c.is_ascii_digit());
    }
    out.push_str(rest);
    out
}

/// The whole-interrupt bench's figures (`target/figures/tick-cost.json`, written by
/// `tests/irq_bench.rs` when every assertion holds) as the tick-cost page's tables.
pub(super) fn tick_cost(out: &str) -> Result<String, String> {
    use serde_json::Value;
    let v: Value = serde_json::from_str(out).map_err(|e| format!("not the bench's JSON: {e}"))?;
    let field = |v: &Value, k: &str| -> Result<u64, String> {
        v.get(k)
            .and_then(Value::as_u64)
            .ok_or_else(|| format!("no number `{k}` in {v}"))
    };
    let sysclk = v
        .get("sysclk_hz")
        .and_then(Value::as_f64)
        .ok_or("no `sysclk_hz`")?;
    // The share of the period the tick budget lets the pipeline take.
    let share = field(&v, "tick_share_percent")? as f64 / 100.0;
    let (scan, learning, analog, trigger) = (
        field(&v, "scan_cycles")?,
        field(&v, "learning_cycles")?,
        field(&v, "analog_cycles")?,
        field(&v, "trigger_cycles")?,
    );
    let (sequence, coarse) = (field(&v, "sequence_cycles")?, field(&v, "coarse_cycles")?);
    // The services at their worst: a capture and telemetry taking every tick.
    let services = field(&v, "services_worst_cycles")?;
    // Every feature on: a scan, the learning, the trigger input armed, the services.
    let every_charge = scan + learning + trigger + services;
    let rows = v.get("rows").and_then(Value::as_array).ok_or("no `rows`")?;
    let budgets = v
        .get("budgets")
        .and_then(Value::as_object)
        .ok_or("no `budgets`")?;
    // Each measured row: (configuration, scenario) → (instructions, cycles 0 WS, cycles 5 WS,
    // the services' dearest batch at 5 WS, the interrupt and the services' share at 5 WS).
    let mut measured: Vec<(&str, &str, [u64; 5])> = Vec::new();
    for r in rows {
        let name = r
            .get("name")
            .and_then(Value::as_str)
            .ok_or("a row has no name")?;
        let counts = [
            field(r, "instructions_max")?,
            field(r, "cycles_max")?,
            field(r, "cycles_max_ws5")?,
            field(r, "services_max_ws5")?,
            field(r, "pipeline_ws5")?,
        ];
        let (config, scenario) = name.split_once('/').unwrap_or((name, ""));
        measured.push((config, scenario, counts));
    }
    let boot = measured.first().ok_or("no rows")?.2;
    // The configurations in the order the bench ran them.
    let mut configs: Vec<&str> = Vec::new();
    for (c, s, _) in &measured {
        if !s.is_empty() && !configs.contains(c) {
            configs.push(c);
        }
    }
    // The worst of each count over a configuration's scenarios that `pick` selects.
    let worst = |config: &str, pick: &dyn Fn(&str) -> bool| -> Result<[u64; 5], String> {
        let mut w = [0u64; 5];
        let mut any = false;
        for (_, _, c) in measured.iter().filter(|(c, s, _)| *c == config && pick(s)) {
            any = true;
            for i in 0..5 {
                w[i] = w[i].max(c[i]);
            }
        }
        if any {
            Ok(w)
        } else {
            Err(format!("{config}: no such scenario measured"))
        }
    };
    let triple = |c: [u64; 5]| format!("{} / {} / {}", grouped(c[0]), grouped(c[1]), grouped(c[2]));
    let rate = |cycles: u64| {
        let hz = (sysclk * share / cycles as f64 / 100.0).floor() as u64 * 100;
        format!("{} Hz", grouped(hz))
    };
    let predicted = |config: &str| -> Result<u64, String> {
        budgets
            .get(config)
            .and_then(Value::as_u64)
            .ok_or_else(|| format!("{config}: no prediction"))
    };

    let mut t = String::new();
    t.push_str(
        "Worst tick of each configuration, instructions / cycles at 0 WS / cycles at 5 WS: streamed \
         (the worst of triangle, sine, full-range steps, random, nested loops) and with every \
         feature on (the worst of the scans with the learning, each with its trigger outputs, one \
         of them started by the trigger input's edges). Every scenario captures all seven signals \
         and streams telemetry of all seven, each on every tick or every eighth (the scenarios \
         alternate). The interrupt's columns are the control interrupt alone; the services below \
         it (the capture, telemetry's tap) run in their own task, woken once every 8 snapshots: \
         \"services, a batch\" is its dearest invocation, and \"per tick, with the services\" \
         the interrupt's worst plus an eighth of that. \"Predicted\" is the tick budget's for \
         the interrupt as loaded, nothing beside it and nothing captured (cycles, 5 WS); \
         \"predicted, every feature\" adds the scan's ",
    );
    t.push_str(&format!(
        "({scan}), the learning's ({learning}) and the armed trigger input's ({trigger}) charges \
         and the services' at their worst ({services}: a capture and telemetry on every tick); \
         the highest admitted rate is the highest control rate whose period's share for the \
         pipeline (`tick_budget::TICK_SHARE_PERCENT`) holds that prediction.\n\n"
    ));
    t.push_str("| configuration | interrupt, streamed | interrupt, every feature on | services, a batch (5 WS) | per tick, with the services (5 WS) | predicted | predicted, every feature | highest admitted rate, streamed | highest admitted rate, every feature |\n");
    t.push_str("|---|---:|---:|---:|---:|---:|---:|---:|---:|\n");
    t.push_str(&format!(
        "| boot: bypass, no model, nothing running | {} | – | – | – | – | – | – | – |\n",
        triple(boot)
    ));
    for config in &configs {
        let streamed = worst(config, &|s| STREAMED.contains(&s))?;
        let every = worst(config, &|s| {
            s.starts_with("scan-") && s.ends_with("-learning")
        })?;
        let p = predicted(config)?;
        t.push_str(&format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            config_label(config),
            triple(streamed),
            triple(every),
            grouped(every[3]),
            grouped(every[4]),
            grouped(p),
            grouped(p + every_charge),
            rate(p),
            rate(p + every_charge),
        ));
    }

    t.push_str(&format!(
        "\nEach scan pattern (200 Hz on x, ±0.8, trigger pulses of 2 ticks), alone and with the \
         learning on; the spiral started by the trigger input's rising edge every 150 ticks (the \
         input armed again before each, a capture armed on the first); the analog setpoint input \
         as the source (budget's charge: {analog} cycles); a TTL-stepped sequence of full-range \
         steps, one a rising edge of the input every 30 ticks, before the stage settles, its last \
         edges finding no position (budget's charge: {sequence} cycles); the coarse axis's ramp, \
         the dual-stage images' source, posted every 10 ticks as the coarse task posts it (budget's \
         charge: {coarse} cycles); and a stream the input's \
         edges start again, a capture armed on the first (the armed input's charge: {trigger} \
         cycles); worst tick, instructions / cycles at 5 WS:\n\n"
    ));
    t.push_str("| configuration |");
    for (_, title) in SCANNED {
        t.push_str(&format!(" {title} |"));
    }
    t.push_str("\n|---|");
    t.push_str(&"---:|".repeat(SCANNED.len()));
    t.push('\n');
    for config in &configs {
        t.push_str(&format!("| {} |", config_label(config)));
        for (scenario, _) in SCANNED {
            let c = worst(config, &|s| s == scenario)?;
            t.push_str(&format!(" {} / {} |", grouped(c[0]), grouped(c[2])));
        }
        t.push('\n');
    }

    let parts = v
        .get("part_names")
        .and_then(Value::as_array)
        .ok_or("no `part_names`")?;
    t.push_str(
        "\nEach configuration's worst streamed tick with its services' share, cycles at 5 WS by \
         the part of the tick its source belongs to (\"services (share)\": an eighth of the \
         services' batch), against the tick budget's prediction with the services as that \
         scenario ran them:\n\n| configuration |",
    );
    for p in parts {
        t.push_str(&format!(" {} |", p.as_str().unwrap_or("?")));
    }
    t.push_str(" total | predicted | predicted / measured |\n|---|");
    t.push_str(&"---:|".repeat(parts.len() + 3));
    t.push('\n');
    for w in v
        .get("worst_by_config")
        .and_then(Value::as_array)
        .ok_or("no `worst_by_config`")?
    {
        let config = w.get("config").and_then(Value::as_str).ok_or("no config")?;
        let total = field(w, "cycles_ws5")?;
        let p = field(w, "predicted")?;
        let cells: Vec<String> = w
            .get("parts")
            .and_then(Value::as_array)
            .ok_or("no parts")?
            .iter()
            .map(|c| grouped(c.as_u64().unwrap_or(0)))
            .collect();
        t.push_str(&format!(
            "| {} | {} | {} | {} | {:.2} |\n",
            config_label(config),
            cells.join(" | "),
            grouped(total),
            grouped(p),
            p as f64 / total as f64
        ));
    }

    t.push_str(
        "\nThe services' own share a tick (an eighth of their dearest batch, 5 WS) against what \
         the tick budget charges them for that scenario's capture, telemetry and observer below \
         the tick: each configuration's scenario with the highest share over charge (the bench \
         fails any scenario whose share exceeds its charge):\n\n\
         | configuration | scenario | services' share a tick | charged | share / charge |\n\
         |---|---|---:|---:|---:|\n",
    );
    for config in &configs {
        let mut dearest: Option<(&str, u64, u64)> = None;
        for r in rows {
            let name = r.get("name").and_then(Value::as_str).unwrap_or("");
            let Some((c, scenario)) = name.split_once('/') else {
                continue;
            };
            if c != *config {
                continue;
            }
            let (share, charge) = (
                field(r, "services_share_ws5")?,
                field(r, "services_charge")?.max(1),
            );
            if dearest.is_none_or(|(_, s, c)| share * c > s * charge) {
                dearest = Some((scenario, share, charge));
            }
        }
        let (scenario, share, charge) =
            dearest.ok_or_else(|| format!("{config}: no services' share measured"))?;
        t.push_str(&format!(
            "| {} | {scenario} | {} | {} | {:.2} |\n",
            config_label(config),
            grouped(share),
            grouped(charge),
            share as f64 / charge as f64
        ));
    }

    let reference = configs.first().ok_or("no configuration")?;
    if let Some(by_file) = v.get("worst_by_file").and_then(|f| f.get(*reference)) {
        let files = by_file
            .get("files")
            .and_then(Value::as_array)
            .ok_or("no files")?;
        t.push_str(&format!(
            "\nThe reference configuration's ({}) worst streamed tick by source file (`(no \
             line)`: the exception's entry and return, code without line information):\n\n\
             | source file | cycles (5 WS) |\n|---|---:|\n",
            config_label(reference)
        ));
        let mut total = 0;
        for f in files {
            let name = f
                .get(0)
                .and_then(Value::as_str)
                .ok_or("a file has no name")?;
            let c = f
                .get(1)
                .and_then(Value::as_u64)
                .ok_or("a file has no cycles")?;
            total += c;
            t.push_str(&format!("| `{name}` | {} |\n", grouped(c)));
        }
        t.push_str(&format!("| **total** | **{}** |\n", grouped(total)));
    }

    let shipped = v.get("shipped_worst").ok_or("no `shipped_worst`")?;
    t.push_str(&format!(
        "\nThe shipped P–I and Duhem configurations' worst tick: **{} instructions, {} cycles at \
         0 WS, {} at 5 WS** (goal {} cycles at 0 WS: {}); the generalised P–I + creep \
         configuration's: {} instructions.\n",
        grouped(field(shipped, "instructions")?),
        grouped(field(shipped, "cycles")?),
        grouped(field(shipped, "cycles_ws5")?),
        grouped(field(&v, "goal_cycles")?),
        if field(shipped, "cycles")? <= field(&v, "goal_cycles")? {
            "met"
        } else {
            "not met"
        },
        grouped(field(&v, "family_worst_instructions")?),
    ));

    t.push_str(
        "\nThe critical sections outside the tick that hold it off (from the instruction that \
         masks it to the one that unmasks it), longest first:\n\n\
         | where (function, source line) | times | instructions | cycles (0 WS) | cycles (5 WS) | µs at 5 WS |\n\
         |---|---:|---:|---:|---:|---:|\n",
    );
    for h in v
        .get("held_off")
        .and_then(Value::as_array)
        .ok_or("no `held_off`")?
    {
        let c5 = field(h, "cycles_ws5")?;
        t.push_str(&format!(
            "| `{}` | {} | {} | {} | {} | {:.1} |\n",
            without_lines(h.get("site").and_then(Value::as_str).ok_or("no site")?),
            grouped(field(h, "count")?),
            grouped(field(h, "instructions")?),
            grouped(field(h, "cycles")?),
            grouped(c5),
            c5 as f64 / sysclk * 1e6
        ));
    }
    let stack = v.get("stack").ok_or("no `stack`")?;
    t.push_str(&format!(
        "\nThe bench image's stack high-water mark over every scenario: {} bytes of the {} its \
         static RAM leaves (reserve {}).\n",
        grouped(field(stack, "used")?),
        grouped(field(stack, "room")?),
        grouped(field(stack, "reserve")?),
    ));
    Ok(t)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bench_configurations_read_as_the_book_writes_them() {
        assert_eq!(
            config_label("inverse-pi16+pi16-observer+pi+drift"),
            "inverse P–I 16 + P–I 16 observer + PI + drift"
        );
        assert_eq!(
            config_label("inverse-gpi32x8+creep6+gpi32x8-observer+pid+notch+shaping+preview+drift"),
            "inverse generalised P–I 32 (8 dead zones) + creep 6 + generalised P–I 32 (8 dead zones) observer + PID + notch + shaping + preview + drift"
        );
        assert_eq!(
            config_label("inverse-bouc-wen+bouc-wen-observer"),
            "inverse Bouc–Wen + Bouc–Wen observer"
        );
        assert_eq!(
            config_label("bypass-no-model"),
            "bypass, no model (the defaults)"
        );
        assert_eq!(grouped(7), "7");
        assert_eq!(grouped(1573), "1 573");
        assert_eq!(grouped(100800), "100 800");
        assert_eq!(grouped(1234567), "1 234 567");
    }

    /// A bench output of one configuration with every scenario the tables read.
    fn bench_json() -> String {
        let mut rows = vec![r#"{"name": "boot (defaults: bypass, no model)", "ticks": 10, "instructions_mean": 300.0, "instructions_max": 326, "cycles_max": 569, "cycles_max_ws5": 689, "services_max_ws5": 0, "pipeline_ws5": 689}"#.to_string()];
        let scenarios = STREAMED
            .iter()
            .chain(SCANNED.iter().map(|(s, _)| s))
            .chain(["reload-and-mode-switches", "load"].iter());
        for (i, s) in scenarios.enumerate() {
            rows.push(format!(
                r#"{{"name": "inverse-pi16+pi16-observer+pi+drift/{s}", "ticks": 100, "instructions_mean": 800.0, "instructions_max": {}, "cycles_max": {}, "cycles_max_ws5": {}, "services_max_ws5": {}, "pipeline_ws5": {}, "services_share_ws5": {}, "services_charge": 120}}"#,
                900 + i,
                1400 + i,
                1570 + i,
                800 + i,
                1670 + i,
                100 + i
            ));
        }
        format!(
            r#"{{"sysclk_hz": 168000000.0, "tick_share_percent": 80, "goal_cycles": 600, "scan_cycles": 150, "learning_cycles": 90,
            "analog_cycles": 32, "sequence_cycles": 80, "coarse_cycles": 32, "trigger_cycles": 200, "services_worst_cycles": 400, "part_names": ["fixed", "P–I banks"],
            "stack": {{"used": 30000, "room": 55000, "reserve": 49152}},
            "budgets": {{"inverse-pi16+pi16-observer+pi+drift": 1666}},
            "rows": [{}],
            "worst_by_config": [{{"config": "inverse-pi16+pi16-observer+pi+drift", "parts": [1066, 507], "cycles_ws5": 1573, "cycles": 1408, "instructions": 899, "predicted": 1666}}],
            "worst_by_file": {{"inverse-pi16+pi16-observer+pi+drift": {{"row": "x", "files": [["prandtl_ishlinskii.rs", 400], ["(no line)", 22]]}}}},
            "shipped_worst": {{"instructions": 1000, "cycles": 1550, "cycles_ws5": 1740}},
            "family_worst_instructions": 1558,
            "held_off": [{{"site": "read_capture_piece, recorder.rs:770", "count": 12, "instructions": 276, "cycles": 500, "cycles_ws5": 591}}]}}"#,
            rows.join(", ")
        )
    }

    #[test]
    fn the_bench_output_becomes_the_tick_cost_tables() {
        let t = tick_cost(&bench_json()).unwrap();
        // The boot row, then the configuration: streamed is the worst of the five streamed
        // scenarios (the fifth, index 4); every feature on the worst scan with the learning
        // (the spiral on the trigger + learning, index 10), with the services' batch and the
        // tick's share of it beside it; the rates from the prediction and its charges (scan,
        // learning, trigger, the services at their worst: 1 666 + 150 + 90 + 200 + 400), at
        // 80 % of the period.
        assert!(
            t.contains("| boot: bypass, no model, nothing running | 326 / 569 / 689 | – | – | – |"),
            "{t}"
        );
        assert!(
            t.contains("| inverse P–I 16 + P–I 16 observer + PI + drift | 904 / 1 404 / 1 574 | 910 / 1 410 / 1 580 | 810 | 1 680 | 1 666 | 2 506 | 80 600 Hz | 53 600 Hz |"),
            "{t}"
        );
        // The scans: raster is index 5, the stream on the trigger index 13 (instructions /
        // 5 WS).
        assert!(t.contains("| 905 / 1 575 | 906 / 1 576 | 907 / 1 577 | 908 / 1 578 | 909 / 1 579 | 910 / 1 580 | 911 / 1 581 | 912 / 1 582 |"), "{t}");
        assert!(t.contains("| 1 066 | 507 | 1 573 | 1 666 | 1.06 |"), "{t}");
        // The services' share against their charge: the scenario with the highest ratio
        // (the last, `load`: 118 of 120).
        assert!(
            t.contains(
                "| inverse P–I 16 + P–I 16 observer + PI + drift | load | 118 | 120 | 0.98 |"
            ),
            "{t}"
        );
        assert!(
            t.contains(
                "| `prandtl_ishlinskii.rs` | 400 |\n| `(no line)` | 22 |\n| **total** | **422** |"
            ),
            "{t}"
        );
        assert!(t.contains("**1 000 instructions, 1 550 cycles at 0 WS, 1 740 at 5 WS** (goal 600 cycles at 0 WS: not met)"), "{t}");
        assert!(
            t.contains("| `read_capture_piece, recorder.rs` | 12 | 276 | 500 | 591 | 3.5 |"),
            "{t}"
        );
        assert_eq!(
            without_lines("handle, register/basepri_max.rs:24 in recorder.rs:799"),
            "handle, register/basepri_max.rs in recorder.rs"
        );
        assert!(t.contains("30 000 bytes of the 55 000"), "{t}");
        // A bench output without a scenario the tables read is an error, not a gap.
        let without = bench_json().replace("scan-spiral-learning", "something-else");
        assert!(tick_cost(&without).is_err());
        assert!(tick_cost("not json").is_err());
    }
}
