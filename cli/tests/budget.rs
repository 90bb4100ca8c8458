//! `twinstack budget` as a user runs it: the model family's table, a parameter file's row, the
//! JSON, and every bad input refused with what and where, exit 1 or 2, no panic.

#[path = "support/tool.rs"]
mod tool;

use std::path::PathBuf;
use tool::{ok, twinstack};

fn golden(name: &str) -> String {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/golden/params")
        .join(name)
        .to_string_lossy()
        .into_owned()
}

#[test]
fn the_family_table_has_a_row_per_model_with_and_without_creep() {
    let out = ok(&["budget", "--rate", "100000"]);
    let rows: Vec<&str> = out
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| configuration"))
        .collect();
    assert_eq!(rows.len(), 8, "{out}");
    // Each row is the library's budget of that configuration; the P–I 17 row fits a 100 kHz
    // period (1 680 cycles) without its observer (which, below the tick, costs the services'
    // loop beside its bank), and not with every feature beside it.
    for (name, settings) in twinstack_identify::budget::family() {
        let row = twinstack_identify::budget::BudgetRow::of(&name, &settings).unwrap();
        let line = rows
            .iter()
            .find(|r| r.starts_with(&format!("| {name} |")))
            .unwrap_or_else(|| panic!("no row {name}: {out}"));
        assert!(
            line.starts_with(&format!("| {name} | {} |", row.loaded.cycles)),
            "{line}"
        );
    }
    let pi = rows
        .iter()
        .find(|r| r.starts_with("| P–I 17 + PI |"))
        .unwrap();
    assert!(
        pi.ends_with("| no (without its observer: yes; with every feature: no) |"),
        "{pi}"
    );
}

#[test]
fn the_json_matches_the_budget_and_says_what_is_admitted() {
    let out = ok(&["budget", "--json", "--rate", "50000"]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let rows = v.as_array().unwrap();
    assert_eq!(rows.len(), 8);
    for r in rows {
        let cycles = r["loaded"]["cycles"].as_u64().unwrap() as f64;
        let rate = r["loaded"]["highest_rate_hz"].as_f64().unwrap();
        // The rate whose period's share (`TICK_SHARE_PERCENT` of 168 MHz / rate) holds exactly
        // the cycles.
        let share = f64::from(twinstack::config::tick_budget::TICK_SHARE_PERCENT) / 100.0;
        assert!((rate * cycles / (share * 168e6) - 1.0).abs() < 1e-9, "{r}");
        assert_eq!(
            r["admitted_at_rate"].as_bool(),
            Some(rate >= 50_000.0),
            "{r}"
        );
        // Every feature adds its charges; with the configuration's observer below the tick
        // the services serve every snapshot already (`SERVICES_EVERY_CYCLES`), charged once.
        let every = r["every_feature"]["cycles"].as_u64().unwrap();
        assert_eq!(
            every as f64 - cycles,
            f64::from(
                twinstack_identify::budget::BESIDE_EVERY_FEATURE.cycles()
                    - twinstack::config::tick_budget::SERVICES_EVERY_CYCLES
            ),
            "{r}"
        );
    }
}

/// `--coarse-rate`: the rows of a dual-stage image, the coarse task's share charged beside
/// each at every rate (the library's `BudgetRow::beside_coarse`): the same cycles, lower
/// rates, none of the family at 100 kHz with its observer.
#[test]
fn beside_a_coarse_task_the_rates_are_the_dual_stage_board_s() {
    let out = ok(&[
        "budget",
        "--json",
        "--rate",
        "100000",
        "--coarse-rate",
        "5000",
    ]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    let rows = v.as_array().unwrap();
    assert_eq!(rows.len(), 8);
    for ((name, settings), r) in twinstack_identify::budget::family().iter().zip(rows) {
        let alone = twinstack_identify::budget::BudgetRow::of(name, settings).unwrap();
        let dual =
            twinstack_identify::budget::BudgetRow::beside_coarse(name, settings, 5_000).unwrap();
        assert_eq!(
            r["loaded"]["cycles"].as_u64(),
            Some(u64::from(alone.loaded.cycles))
        );
        assert_eq!(r["loaded"]["coarse_rate_hz"].as_u64(), Some(5_000), "{r}");
        let rate = r["loaded"]["highest_rate_hz"].as_f64().unwrap();
        assert_eq!(rate, dual.loaded.highest_rate_hz, "{r}");
        assert!(rate < alone.loaded.highest_rate_hz, "{r}");
        assert_eq!(r["admitted_at_rate"].as_bool(), Some(false), "{r}");
    }
    let table = ok(&["budget", "--coarse-rate", "5000"]);
    assert!(table.contains("coarse task runs at 5000 Hz"), "{table}");
    // Without it, the JSON names no coarse task.
    assert!(!ok(&["budget", "--json"]).contains("coarse_rate_hz"));
    for bad in ["0", "-1", "NaN", "1e9"] {
        let o = twinstack(&["budget", "--coarse-rate", bad]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{bad}: {err}");
        assert!(err.contains("--coarse-rate"), "{err}");
    }
}

#[test]
fn a_parameter_files_row_is_its_own_settings() {
    let pi16 = golden("micromanipulator-pi16.json");
    let bw = golden("micromanipulator-bouc-wen.json");
    let out = ok(&["budget", &pi16, &bw]);
    assert!(out.contains("micromanipulator-pi16.json |"), "{out}");
    assert!(out.contains("micromanipulator-bouc-wen.json |"), "{out}");
}

#[test]
fn bad_inputs_are_named_and_refused() {
    let o = twinstack(&["budget", "no-such-file.json"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("no-such-file.json"), "{err}");
    for rate in ["0", "-5", "inf", "NaN"] {
        let o = twinstack(&["budget", "--rate", rate]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{rate}: {err}");
        assert!(err.contains("--rate"), "{err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    let o = twinstack(&["budget", "--rate", "fast"]);
    assert_eq!(o.status.code(), Some(2));
}
