//! `twinstack selftest` as a user runs it: every check passes on the in-process board (the tick
//! rate skipped: it runs on simulated time) and on a virtual board paced by the wall clock;
//! each injected fault — a clock running fast, a corrupting link, an open loopback, a failing
//! flash write, a watchdog that never fires — fails exactly its own check, with its hint;
//! what flash held and the settings in force are put back; bad flags are one-line usage
//! errors.

use std::process::{Command, Output};

#[path = "support/virtual_board_process.rs"]
mod virtual_board_process;

fn twinstack(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twinstack"))
        .args(args)
        .output()
        .expect("twinstack runs")
}

fn text(o: &Output) -> (String, String) {
    (
        String::from_utf8_lossy(&o.stdout).into_owned(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

/// `selftest --json` with `args`: the exit code and each check's outcome by name, with the
/// whole report.
fn selftest(
    args: &[&str],
) -> (
    Option<i32>,
    Vec<(String, String, String)>,
    serde_json::Value,
) {
    let mut all = vec!["selftest", "--json"];
    all.extend_from_slice(args);
    let o = twinstack(&all);
    let (out, err) = text(&o);
    assert!(!err.contains("panicked"), "{args:?}: {err}");
    let report: serde_json::Value = serde_json::from_str(out.trim())
        .unwrap_or_else(|e| panic!("{args:?}: not one JSON object ({e}): {out}{err}"));
    let checks = report["checks"]
        .as_array()
        .expect("checks")
        .iter()
        .map(|c| {
            (
                c["check"].as_str().unwrap().to_string(),
                c["outcome"].as_str().unwrap().to_string(),
                format!("{} {}", c["detail"], c["hint"]),
            )
        })
        .collect();
    (o.status.code(), checks, report)
}

/// Asserts that the checks named in `fail` failed (their hint containing the needle) and
/// every other one passed, except those in `skip`.
fn expect(
    checks: &[(String, String, String)],
    fail: &[(&str, &str)],
    skip: &[&str],
    context: &str,
) {
    let names: Vec<&str> = checks.iter().map(|c| c.0.as_str()).collect();
    assert_eq!(
        names,
        [
            "safe-state",
            "link",
            "tick-rate",
            "loopback",
            "flash",
            "watchdog"
        ],
        "{context}"
    );
    for (name, outcome, line) in checks {
        let want = if let Some((_, needle)) = fail.iter().find(|f| f.0 == name) {
            assert!(
                line.contains(needle),
                "{context}: {name}'s line lacks {needle:?}: {line}"
            );
            "FAIL"
        } else if skip.contains(&name.as_str()) {
            "SKIP"
        } else {
            "PASS"
        };
        assert_eq!(outcome, want, "{context}: {name}: {line}");
    }
}

/// The in-process board: no wall clock (the tick rate skips), everything else passes (the
/// watchdog drill resets the board and it comes back reporting the watchdog); the lines and
/// the summary as a person reads them.
#[test]
fn every_check_passes_on_the_in_process_board_but_the_tick_rate_skips() {
    let (code, checks, report) = selftest(&["--port", "sim"]);
    expect(&checks, &[], &["tick-rate"], "sim");
    assert_eq!(code, Some(0), "{report}");
    assert_eq!(report["image"], "simulator");
    assert_eq!(report["fail"], 0);
    let link = &report["checks"][1]["figures"];
    assert_eq!(link["intact"], 200);
    assert_eq!(link["board_crc_errors"], 0);
    let loopback = &report["checks"][3]["figures"];
    assert!(loopback["slope"].as_f64().unwrap() > 0.99, "{loopback}");
    // The loop's delay, measured through the jumper: a write shows in the reading two ticks
    // later, as the feedback assumes.
    let delay = loopback["delay_ticks"].as_f64().unwrap();
    assert!((delay - 2.0).abs() < 0.05, "{loopback}");
    let watchdog = &report["checks"][5]["figures"];
    assert_eq!(watchdog["reset"], true, "{watchdog}");
    assert_eq!(watchdog["cause_watchdog"], true, "{watchdog}");
    // Back within the timeout and a few round trips.
    let ms = watchdog["back_within_ms"].as_f64().unwrap();
    assert!((20.0..100.0).contains(&ms), "{watchdog}");

    let o = twinstack(&["selftest", "--port", "sim", "--echoes", "20"]);
    let (out, err) = text(&o);
    assert_eq!(o.status.code(), Some(0), "{out}{err}");
    let lines: Vec<&str> = out.lines().collect();
    assert_eq!(lines.len(), 7, "{out}");
    assert!(lines[1].starts_with("PASS link       20 echoes"), "{out}");
    assert!(lines[2].starts_with("SKIP tick-rate"), "{out}");
    assert!(
        lines[5].starts_with("PASS watchdog   the drill reset"),
        "{out}"
    );
    assert_eq!(
        lines[6],
        "selftest of the simulator image: 5 PASS, 0 FAIL, 1 SKIP"
    );
}

#[test]
fn an_open_loopback_fails_the_loopback_check_only() {
    let (code, checks, _) = selftest(&["--port", "sim", "--sim-open-loopback"]);
    expect(
        &checks,
        &[("loopback", "fit the jumper from the left DAC channel (PA4)")],
        &["tick-rate"],
        "open loopback",
    );
    assert_eq!(code, Some(1));
    // A board without the jumper skips it.
    let (code, checks, _) =
        selftest(&["--port", "sim", "--sim-open-loopback", "--skip", "loopback"]);
    expect(&checks, &[], &["tick-rate", "loopback"], "--skip loopback");
    assert_eq!(code, Some(0));
}

/// Converters timed otherwise than the firmware's — the reading one tick sooner, as when the
/// conversion started on the tick's own timer event and a short tick read it complete — pass
/// the levels but fail the loopback check on the delay it measures, and only it.
#[test]
fn a_sensor_reading_a_tick_early_fails_the_loopback_check_on_its_delay() {
    let (code, checks, report) = selftest(&["--port", "sim", "--sim-sensor-latency", "0"]);
    expect(
        &checks,
        &[(
            "loopback",
            "the converters are not timed as the firmware expects",
        )],
        &["tick-rate"],
        "sensor latency 0",
    );
    assert_eq!(code, Some(1));
    let loopback = &report["checks"][3]["figures"];
    let delay = loopback["delay_ticks"].as_f64().unwrap();
    assert!((delay - 1.0).abs() < 0.05, "{loopback}");
    // Only on the in-process board, and within what the simulated ADC models.
    for args in [
        vec![
            "selftest",
            "--port",
            "tcp:127.0.0.1:9",
            "--sim-sensor-latency",
            "0",
        ],
        vec!["selftest", "--port", "sim", "--sim-sensor-latency", "9"],
    ] {
        let o = twinstack(&args);
        let (_, err) = text(&o);
        assert_eq!(o.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains("--sim-sensor-latency"), "{args:?}: {err}");
    }
}

#[test]
fn a_failing_flash_write_fails_the_flash_check_only() {
    let (code, checks, _) = selftest(&["--port", "sim", "--sim-fail-flash-writes"]);
    expect(
        &checks,
        &[("flash", "writing the settings in force to flash failed")],
        &["tick-rate"],
        "failing flash",
    );
    assert_eq!(code, Some(1));
}

#[test]
fn a_watchdog_that_never_fires_fails_the_watchdog_check_only() {
    let (code, checks, report) = selftest(&["--port", "sim", "--sim-no-watchdog"]);
    expect(
        &checks,
        &[("watchdog", "its watchdog is not running")],
        &["tick-rate"],
        "no watchdog",
    );
    assert_eq!(code, Some(1));
    assert_eq!(report["checks"][5]["figures"]["reset"], false);
}

#[test]
fn a_corrupting_link_fails_the_link_check_only() {
    let (code, checks, report) = selftest(&["--port", "sim", "--link-error-rate", "2e-5"]);
    expect(
        &checks,
        &[("link", "check the adapter's ground and the baud rate")],
        &["tick-rate"],
        "corrupting link",
    );
    assert_eq!(code, Some(1));
    let link = &report["checks"][1]["figures"];
    let bad = 200 - link["intact"].as_u64().unwrap();
    assert!(bad > 0, "{link}");
    // The board's and the host's counters saw the damage.
    let counted = link["board_crc_errors"].as_u64().unwrap()
        + link["board_frame_errors"].as_u64().unwrap()
        + link["host_corrupt_frames"].as_u64().unwrap();
    assert!(counted > 0, "{link}");
}

/// A virtual board paced by the wall clock, with the jumper: the tick rate is measured and
/// passes; the same board 10 % fast fails it, and only it.
#[test]
fn a_virtual_board_passes_on_time_and_fails_the_tick_rate_when_its_clock_runs_fast() {
    let link = [
        "--link-latency-ms",
        "2",
        "--link-jitter-ms",
        "1",
        "--loopback",
    ];
    let (_board, port) = virtual_board_process::start(&link);
    let (code, checks, report) = selftest(&["--port", &port, "--echoes", "60"]);
    expect(&checks, &[], &[], "virtual board");
    assert_eq!(code, Some(0), "{report}");
    let tick = &report["checks"][2]["figures"];
    assert!(tick["error_pct"].as_f64().unwrap().abs() < 1.0, "{tick}");

    let mut fast = link.to_vec();
    fast.extend(["--speed", "1.1"]);
    let (_board, port) = virtual_board_process::start(&fast);
    let (code, checks, report) = selftest(&["--port", &port, "--echoes", "20"]);
    expect(
        &checks,
        &[("tick-rate", "the board's clock runs")],
        &[],
        "fast clock",
    );
    assert_eq!(code, Some(1));
    let error = report["checks"][2]["figures"]["error_pct"]
        .as_f64()
        .unwrap();
    assert!((error - 10.0).abs() < 2.0, "{error}");
    assert!(checks[2].2.contains("% fast"), "{}", checks[2].2);
}

/// The flash check leaves the board as it found it: the settings in force stay, and flash
/// holds what it held (here bypass, while open loop is in force: putting the in-force settings
/// back in flash would show).
#[test]
fn the_flash_check_puts_back_what_flash_held() {
    let (_board, port) = virtual_board_process::start(&[
        "--speed",
        "0",
        "--link-latency-ms",
        "0",
        "--link-jitter-ms",
        "0",
    ]);
    let ok = |args: &[&str]| {
        let o = twinstack(args);
        let (out, err) = text(&o);
        assert_eq!(o.status.code(), Some(0), "{args:?}: {out}{err}");
        out
    };
    ok(&["mode", "open-loop", "--port", &port]);
    let in_force = ok(&["params", "--port", &port]);
    assert!(in_force.contains("\"OpenLoop\""), "{in_force}");
    let (code, checks, _) = selftest(&[
        "--port",
        &port,
        "--skip",
        "tick-rate",
        "--skip",
        "loopback",
        "--echoes",
        "5",
    ]);
    expect(&checks, &[], &["tick-rate", "loopback"], "restore");
    assert_eq!(code, Some(0));
    assert_eq!(
        ok(&["params", "--port", &port]),
        in_force,
        "the settings in force changed"
    );
    ok(&["recall", "--port", &port]);
    let stored = ok(&["params", "--port", &port]);
    assert!(
        stored.contains("\"Bypass\""),
        "flash no longer holds bypass: {stored}"
    );
}

/// Bad flags: one line naming the flag, exit 2, nothing run.
#[test]
fn bad_flags_are_one_line_usage_errors() {
    for (args, needle) in [
        (vec!["--port", "sim", "--echoes", "0"], "--echoes 0"),
        (
            vec!["--port", "sim", "--tick-seconds", "0.01"],
            "--tick-seconds 0.01",
        ),
        (
            vec!["--port", "sim", "--tick-seconds", "nan"],
            "--tick-seconds NaN",
        ),
        (
            vec!["--port", "sim", "--tick-tolerance-ppm=-1"],
            "--tick-tolerance-ppm -1",
        ),
        (
            vec!["--port", "sim", "--loopback-tolerance-pct", "0"],
            "--loopback-tolerance-pct 0",
        ),
        (vec!["--port", "sim", "--skip", "everything"], "everything"),
        (
            vec!["--port", "tcp:127.0.0.1:9", "--sim-open-loopback"],
            "fit the in-process board (--port sim)",
        ),
        (
            vec!["--port", "tcp:127.0.0.1:9", "--sim-no-watchdog"],
            "fit the in-process board (--port sim)",
        ),
        (
            vec!["--port", "sim", "--link-error-rate", "2"],
            "--link-error-rate 2",
        ),
    ] {
        let mut all = vec!["selftest"];
        all.extend(&args);
        let o = twinstack(&all);
        let (out, err) = text(&o);
        assert!(
            matches!(o.status.code(), Some(1) | Some(2)),
            "{args:?}: {:?}\n{out}{err}",
            o.status
        );
        assert!(out.is_empty(), "{args:?} ran: {out}");
        assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
        assert!(err.contains(needle), "{args:?}: {needle:?} not in {err}");
    }
}
